"""A picture of an estimated vignetting function, for people who would rather look."""

from __future__ import annotations

import math

import numpy as np

from vigproc.model import VignettingModel

#: Iso-attenuation contours drawn, in EV below the centre.
CONTOUR_EV = (0.25, 0.5, 1.0, 2.0, 3.0, 4.0)


def vignetting_picture(model: VignettingModel, long_side: int = 480) -> np.ndarray:
    """Render φ as an RGB float image in [0, 1] (to be stored sRGB-encoded).

    Gray level is the attenuation φ itself (white = no fall-off); coloured lines are
    the iso-attenuation contours at :data:`CONTOUR_EV` EV, a red cross marks the
    vignetting centre when it lies inside the frame.
    """
    s = long_side / max(model.width, model.height)
    h, w = max(2, round(model.height * s)), max(2, round(model.width * s))
    lf = model.log_field((h, w)) / math.log(2.0)
    rgb = np.repeat(np.exp2(lf)[..., None], 3, axis=2)
    colours = np.array([[0.2, 0.8, 1.0], [0.2, 1.0, 0.4], [1.0, 0.9, 0.2], [1.0, 0.5, 0.1], [1.0, 0.2, 0.6], [0.7, 0.3, 1.0]])
    for ev, col in zip(CONTOUR_EV, colours):
        below = lf < -ev
        edge = np.zeros_like(below)
        edge[:, 1:] |= below[:, 1:] != below[:, :-1]
        edge[1:, :] |= below[1:, :] != below[:-1, :]
        rgb[edge] = col
    m = model.rescale(w, h) if not model.is_identity else model
    cx = m.center[0] + (w - 1) / 2
    cy = m.center[1] + (h - 1) / 2
    if 0 <= cx < w and 0 <= cy < h:
        x, y = int(round(cx)), int(round(cy))
        arm = max(3, w // 40)
        rgb[max(0, y - 1) : y + 2, max(0, x - arm) : x + arm + 1] = (1.0, 0.0, 0.0)
        rgb[max(0, y - arm) : y + arm + 1, max(0, x - 1) : x + 2] = (1.0, 0.0, 0.0)
    return rgb.astype(np.float32)


#: Curve colours for the major and minor ellipse axes.
_AXIS_COLOURS = ((1.0, 0.45, 0.1), (0.2, 0.6, 1.0))


def _text(img: np.ndarray, x: int, y: int, text: str, size: int = 14, colour=(0.9, 0.9, 0.9)) -> None:
    """Draw text into an RGB float array in place (OpenImageIO's built-in font)."""
    import OpenImageIO as oiio

    buf = oiio.ImageBuf(np.ascontiguousarray(img))
    oiio.ImageBufAlgo.render_text(buf, int(x), int(y), text, size, "", tuple(colour))
    img[...] = buf.get_pixels(oiio.FLOAT).reshape(img.shape)


def _axes(model: VignettingModel) -> tuple[np.ndarray, np.ndarray]:
    """Unit vectors of the ellipse's major (slow fall-off) and minor (fast) axes."""
    ev, evec = np.linalg.eigh(model.shape_matrix)
    # the smallest eigenvalue of P is the direction where r grows slowest: the major axis
    return evec[:, 0], evec[:, 1]


def _falloff_along(model: VignettingModel, u: np.ndarray, n: int = 400) -> tuple[np.ndarray, np.ndarray]:
    """EV of φ along the line through the centre in direction u, to the frame edges."""
    hw, hh = (model.width - 1) / 2, (model.height - 1) / 2
    c = np.array(model.center)
    # distances t (both signs) for which c + t·u stays inside the frame
    lims = []
    for k, half in ((0, hw), (1, hh)):
        if abs(u[k]) > 1e-12:
            lims += [(-half - c[k]) / u[k], (half - c[k]) / u[k]]
    lims = np.sort(lims)
    # the two middle limits bound the part of the line inside both axes' ranges
    t = np.linspace(lims[1], lims[2], n) if len(lims) == 4 else np.linspace(lims[0], lims[1], n)
    pts = c[None, :] + t[:, None] * u[None, :]
    return t, model.log_field_at(pts[:, 0], pts[:, 1]) / math.log(2.0)


def falloff_figure(model: VignettingModel, title: str = "") -> np.ndarray:
    """A figure of a vignetting model: gain map with contours, centre and ellipse axes
    (left), and the fall-off in EV along both ellipse axes across the frame (right).

    Returns
    -------
    ndarray, float32, H×W×3 in [0, 1] (to be stored sRGB-encoded)
    """
    left = vignetting_picture(model, long_side=420)
    lh, lw = left.shape[:2]
    H = max(lh, 360) + 60
    W = lw + 560
    fig = np.full((H, W, 3), 0.12, dtype=np.float32)
    y0 = 40
    fig[y0 : y0 + lh, 10 : 10 + lw] = left
    s = lw / model.width
    if not model.is_identity:
        major, minor = _axes(model)
        cx = (model.width - 1) / 2 + model.center[0]
        cy = (model.height - 1) / 2 + model.center[1]
        for u, col in zip((major, minor), _AXIS_COLOURS):
            for t in np.linspace(-max(model.width, model.height), max(model.width, model.height), 4000):
                x, y = (cx + t * u[0]) * s, (cy + t * u[1]) * s
                if 0 <= x < lw and 0 <= y < lh:
                    fig[y0 + int(y), 10 + int(x)] = col
    # right panel: EV against position along each axis
    px0, py0, pw, ph = lw + 80, y0, 440, H - y0 - 50
    fig[py0 : py0 + ph, px0] = 0.7
    fig[py0 + ph, px0 : px0 + pw] = 0.7
    curves = [_falloff_along(model, u) for u in (_axes(model) if not model.is_identity else
                                                  (np.array([1.0, 0.0]), np.array([0.0, 1.0])))]
    ev_min = min(-0.5, min(float(c[1].min()) for c in curves))
    ev_lo = -math.ceil(-ev_min * 2) / 2
    t_max = max(float(np.abs(c[0]).max()) for c in curves)
    for ev in np.arange(0.0, ev_lo - 1e-9, -0.5 if ev_lo > -3 else -1.0):
        y = py0 + int(round(ev / ev_lo * (ph - 1))) if ev_lo < 0 else py0
        fig[y, px0 : px0 + pw : 3] = 0.35
        _text(fig, px0 - 58, y + 5, f"{ev:+.1f} EV", 13)
    for (t, ev), col in zip(curves, _AXIS_COLOURS):
        xs = px0 + ((t / t_max + 1) / 2 * (pw - 1)).astype(int)
        ys = py0 + np.clip(np.round(ev / ev_lo * (ph - 1)), 0, ph - 1).astype(int)
        for dx in (0, 1):
            fig[ys, np.clip(xs + dx, 0, W - 1)] = col
    _text(fig, px0 + pw // 2 - 8, py0 + ph + 18, "0", 13)
    _text(fig, px0, py0 + ph + 18, f"-{t_max:.0f} px", 13)
    _text(fig, px0 + pw - 60, py0 + ph + 18, f"+{t_max:.0f} px", 13)
    _text(fig, px0 + 10, py0 + 18, "major axis", 13, _AXIS_COLOURS[0])
    _text(fig, px0 + 110, py0 + 18, "minor axis", 13, _AXIS_COLOURS[1])
    _text(fig, 10, 26, title or f"fall-off {model.field_ev_rms():.2f} EV RMS, centre "
          f"({model.center[0]:.0f}, {model.center[1]:.0f}) px", 15)
    return np.clip(fig, 0, 1)
