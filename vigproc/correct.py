"""Removing vignetting: divide the linear image by the attenuation field.

The field is evaluated on the fly by a parallel Numba kernel
(:mod:`vigproc._kernels.correct`): no H×W field array is allocated, every channel
shares one gain computation, and a frame can be corrected in horizontal stripes
(:func:`correct_stripe`) so memory stays bounded for very large frames.
"""

from __future__ import annotations

import numpy as np

from vigproc._kernels.correct import correct_rows
from vigproc.errors import InvalidImageError
from vigproc.image import as_channels_last
from vigproc.model import VignettingModel


def _check_strength(strength: float) -> float:
    s = float(strength)
    if not np.isfinite(s) or s < 0:
        raise InvalidImageError(f"strength must be a finite number >= 0, got {strength}")
    return s


#: Relative error allowed from interpolating the gain between evaluated columns:
#: 1e-5 (1.4e-5 EV) is below a 16-bit output's quantisation step (1.5e-5 of full
#: scale, more relative to mid-tones) and far below anything visible.
GAIN_TOLERANCE = 1e-5
#: Largest interpolation step (columns).
MAX_GAIN_STEP = 16


def exact_radius(model: VignettingModel, step: int, tol: float = GAIN_TOLERANCE) -> float:
    """Radius (px) around the centre where gains must be evaluated exactly at ``step``.

    α1·r is a cone at the centre; near it r'' ≈ √λmax(P)/d at distance d, so linear
    interpolation over h columns errs by about |α1|·√λmax·h²/(8d) relative, which is
    within ``tol`` for d > |α1|·√λmax·h²/(8·tol).
    """
    if step <= 1:
        return 0.0
    lam = float(np.linalg.eigvalsh(model.shape_matrix).max())
    return abs(model.alpha[0]) * np.sqrt(max(lam, 0.0)) * step * step / (8 * tol) + step + 1.0


def gain_step(model: VignettingModel, width: int, height: int, tol: float = GAIN_TOLERANCE) -> int:
    """Column step at which linear interpolation of 1/φ stays within ``tol`` (relative).

    Linear interpolation over a step h errs by at most h²/8·max|g''|; the relative
    second difference of the exact gain g = 1/φ is measured along 9 rows spanning
    the frame (the corners, where it is largest, included), away from the centre's
    cone (:func:`exact_radius`), which is evaluated exactly.
    """
    m = model if (model.width, model.height) == (width, height) else model.rescale(width, height)
    if m.is_identity or width < 3:
        return MAX_GAIN_STEP if m.is_identity else 1
    rows = np.linspace(0, height - 1, 9).round().astype(int)
    g = np.exp(-_sample_rows(m, width, height, rows))
    curv = np.abs(g[:, 2:] - 2 * g[:, 1:-1] + g[:, :-2]) / g[:, 1:-1]
    xs = np.arange(1, width - 1) - ((width - 1) / 2 + m.center[0])
    ys = rows[:, None] - ((height - 1) / 2 + m.center[1])
    for step in range(MAX_GAIN_STEP, 1, -1):
        away = np.hypot(xs[None, :], ys) >= exact_radius(m, step, tol)
        if away.mean() < 0.9:  # the exact disc would cover much of the frame: no gain
            continue
        if step * step * float(curv[away].max()) / 8 <= tol:
            return step
    return 1


def _sample_rows(m: VignettingModel, width: int, height: int, rows: np.ndarray) -> np.ndarray:
    from vigproc._kernels.field import log_field_grid
    from vigproc.model import frame_coords

    out = np.empty((rows.shape[0], width))
    ys = frame_coords(height)[rows]
    log_field_grid(frame_coords(width), ys, m.center[0], m.center[1], *m.p,
                   np.asarray(m.alpha, dtype=np.float64), out)
    return out


def correct_stripe(
    stripe: np.ndarray, model: VignettingModel, row0: int, frame_shape: tuple[int, int], *,
    strength: float = 1.0, clip: float | None = None, out: np.ndarray | None = None,
    step: int | None = None,
) -> np.ndarray:
    """Correct rows ``row0 .. row0 + h − 1`` of a frame of ``frame_shape`` = (H, W).

    Parameters
    ----------
    stripe : ndarray, h×W×C (channels last) or h×W
    model : VignettingModel
        Any resolution of the same frame; rescaled to (W, H) here.
    row0 : int
        Frame row of ``stripe[0]``.
    frame_shape : (H, W)
    strength, clip : see :func:`correct`
    out : ndarray, float32, same shape as ``stripe``, optional
        Destination (may be ``stripe`` itself when it is float32: in place).
    step : int, optional
        Gain interpolation step in columns (1 = exact); default :func:`gain_step`.

    Returns
    -------
    ndarray, float32
    """
    s = _check_strength(strength)
    x = stripe[..., None] if stripe.ndim == 2 else stripe
    fh, fw = int(frame_shape[0]), int(frame_shape[1])
    if x.ndim != 3 or x.shape[1] != fw or not 0 <= row0 <= fh - x.shape[0]:
        raise InvalidImageError(f"stripe of shape {stripe.shape} at row {row0} does not fit a {fw}x{fh} frame")
    m = model if (model.width, model.height) == (fw, fh) else model.rescale(fw, fh)
    x = np.ascontiguousarray(x, dtype=np.float32)
    if out is None:
        out = np.empty(stripe.shape, dtype=np.float32)
    o = out[..., None] if out.ndim == 2 else out
    if o.shape != x.shape or o.dtype != np.float32:
        raise InvalidImageError(f"out must be float32 of shape {stripe.shape}, got {out.dtype} {out.shape}")
    cy = (fh - 1) / 2.0 + m.center[1]
    step = gain_step(m, fw, fh) if step is None else int(step)
    correct_rows(x, o, int(row0), m.center[0], cy, *m.p, np.asarray(m.alpha, dtype=np.float64),
                 s, -1.0 if clip is None else float(clip), step, exact_radius(m, step))
    return out


def correct(
    img: np.ndarray, model: VignettingModel, *, channel_axis: int | None = -1,
    strength: float = 1.0, clip: float | None = None, out: np.ndarray | None = None,
) -> np.ndarray:
    """Remove vignetting from a linear image: I = I_v / φ^strength (Lyu 2010, Eq. 1).

    Parameters
    ----------
    img : ndarray
        H×W or H×W×C linear image (any resolution of the model's frame).
    model : VignettingModel
    channel_axis : int or None
    strength : float
        0 leaves the image unchanged, 1 removes the full fall-off.
    clip : float, optional
        Clip results above this white point (e.g. 1.0 for integer outputs); None
        keeps values above it (float outputs).
    out : ndarray, optional
        float32 destination of ``img``'s shape; pass ``img`` itself (float32,
        channels last) to correct in place.

    Returns
    -------
    ndarray, float32, same layout as ``img``
    """
    a = np.asarray(img)
    if a.ndim == 2:
        channel_axis = None
    x = as_channels_last(a, channel_axis)
    h, w = x.shape[:2]
    if a.ndim == 3 and channel_axis not in (-1, 2) and out is not None:
        raise InvalidImageError("out= needs a channels-last image")
    res = correct_stripe(x, model, 0, (h, w), strength=strength, clip=clip, out=out)
    if a.ndim == 3 and channel_axis is not None and channel_axis not in (-1, 2):
        res = np.moveaxis(res, -1, channel_axis)
    return res
