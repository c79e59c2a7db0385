"""A picture of an estimated vignetting function, for people who would rather look."""

from __future__ import annotations

import math

import numpy as np

from vigproc.core.model import VignettingModel

#: Iso-attenuation contours drawn, in EV below the centre.
CONTOUR_EV = (0.25, 0.5, 1.0, 2.0, 3.0, 4.0)
_CONTOUR_COLOURS = ((0.2, 0.8, 1.0), (0.2, 1.0, 0.4), (1.0, 0.9, 0.2), (1.0, 0.5, 0.1), (1.0, 0.2, 0.6),
                    (0.7, 0.3, 1.0))


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
    for ev, col in zip(CONTOUR_EV, _CONTOUR_COLOURS):
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
    """Draw text into an RGB float array in place (OpenImageIO's built-in font).

    Only the text's box (``text_size``, widened by ``size`` pixels each side) goes
    through OpenImageIO, at the same pixel offsets: the same pixels as drawing into the
    whole array, without copying the whole array twice.

    Parameters
    ----------
    img : ndarray, H×W×3 float32
        The picture, changed in place.
    x, y : int
        The text's origin (left end of its baseline), in pixels.
    text : str
        What to write.
    size : int
        Font size in pixels.
    colour : tuple of float
        RGB in [0, 1].

    Returns
    -------
    None
    """
    import OpenImageIO as oiio

    x, y = int(x), int(y)
    box = oiio.ImageBufAlgo.text_size(text, size, "")
    if box.defined:
        x0, x1 = max(0, x + box.xbegin - size), min(img.shape[1], x + box.xend + size)
        y0, y1 = max(0, y + box.ybegin - size), min(img.shape[0], y + box.yend + size)
    else:
        x0, x1, y0, y1 = 0, img.shape[1], 0, img.shape[0]
    if x1 <= x0 or y1 <= y0:
        return
    part = img[y0:y1, x0:x1]
    buf = oiio.ImageBuf(np.ascontiguousarray(part))
    oiio.ImageBufAlgo.render_text(buf, x - x0, y - y0, text, size, "", tuple(colour))
    part[...] = buf.get_pixels(oiio.FLOAT).reshape(part.shape)


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


def falloff_figure(model: VignettingModel, title: str = "", *, rejected: bool = False) -> np.ndarray:
    """A figure of a vignetting model: gain map with contours (and their legend), centre
    and ellipse axes (left), and the fall-off in EV along both ellipse axes across the
    frame (right).

    ``rejected``: the model is a fit that was *not* applied (weak evidence): the map is
    dimmed and crossed out, the curves dashed, and a banner says so.

    Returns
    -------
    ndarray, float32, H×W×3 in [0, 1] (to be stored sRGB-encoded)
    """
    left = vignetting_picture(model, long_side=420)
    lh, lw = left.shape[:2]
    H = max(lh + 40, 360) + 80
    W = lw + 560
    fig = np.full((H, W, 3), 0.12, dtype=np.float32)
    y0 = 40
    if rejected:  # dimmed toward the background and crossed: not what was applied
        left = 0.35 * left + 0.65 * 0.12
        n = max(lh, lw)
        for k in np.linspace(0, 1, 4 * n):
            for yy in (int(k * (lh - 1)), int((1 - k) * (lh - 1))):
                left[yy, min(lw - 1, int(k * (lw - 1)))] = (0.85, 0.2, 0.2)
    fig[y0 : y0 + lh, 10 : 10 + lw] = left
    s = lw / model.width
    cx = (model.width - 1) / 2 + model.center[0]
    cy = (model.height - 1) / 2 + model.center[1]
    # the ellipse axes only through a centre inside the frame (else they are lines from nowhere)
    if not model.is_identity and 0 <= cx < model.width and 0 <= cy < model.height:
        major, minor = _axes(model)
        for u, col in zip((major, minor), _AXIS_COLOURS):
            for t in np.linspace(-max(model.width, model.height), max(model.width, model.height), 4000):
                x, y = (cx + t * u[0]) * s, (cy + t * u[1]) * s
                if 0 <= x < lw and 0 <= y < lh:
                    fig[y0 + int(y), 10 + int(x)] = col
    # contour legend under the map: the levels the field reaches
    lf_min = float(model.log_field((max(2, round(lh)), max(2, round(lw)))).min()) / math.log(2.0)
    shown = [(ev, col) for ev, col in zip(CONTOUR_EV, _CONTOUR_COLOURS) if lf_min < -ev]
    x = 10
    if shown:
        _text(fig, x, y0 + lh + 24, "contours:", 13)
        x += 72
    for ev, col in shown:
        fig[y0 + lh + 14 : y0 + lh + 26, x : x + 14] = col
        _text(fig, x + 18, y0 + lh + 24, f"-{ev:g} EV", 13)
        x += 80
    if not shown:
        _text(fig, 10, y0 + lh + 24, "no contour: the fall-off stays under 0.25 EV", 13)
    if rejected:
        _text(fig, 20, y0 + 24, "NOT APPLIED: the evidence was too weak", 15, (1.0, 0.35, 0.35))
    if model.is_identity:
        _text(fig, 20, y0 + 24, "no correction", 15, (1.0, 0.35, 0.35))
    # right panel: EV against position along each axis
    px0, py0, pw, ph = lw + 80, y0, 440, H - y0 - 70
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
        keep = (np.arange(xs.size) // 12) % 2 == 0 if rejected else slice(None)  # dashed: not applied
        for dx in (0, 1):
            fig[ys[keep], np.clip(xs[keep] + dx, 0, W - 1)] = col
    _text(fig, px0 + pw // 2 - 8, py0 + ph + 18, "0", 13)
    _text(fig, px0, py0 + ph + 18, f"-{t_max:.0f} px", 13)
    _text(fig, px0 + pw - 60, py0 + ph + 18, f"+{t_max:.0f} px", 13)
    # the curve legend below the axis, never on the curves
    names = ("major axis", "minor axis") if not model.is_identity else ("horizontal", "vertical")
    for k, (label, col) in enumerate(zip(names, _AXIS_COLOURS)):
        lx = px0 + 10 + 215 * k
        fig[py0 + ph + 32 : py0 + ph + 35, lx : lx + 20] = col
        _text(fig, lx + 26, py0 + ph + 40, f"fall-off along the {label}", 13, col)
    _text(fig, 10, 26, title or f"fall-off {model.field_ev_rms():.2f} EV RMS, centre "
          f"({model.center[0]:.0f}, {model.center[1]:.0f}) px", 15)
    return np.clip(fig, 0, 1)
