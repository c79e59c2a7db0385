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


def correct_stripe(
    stripe: np.ndarray, model: VignettingModel, row0: int, frame_shape: tuple[int, int], *,
    strength: float = 1.0, clip: float | None = None, out: np.ndarray | None = None,
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
    correct_rows(x, o, int(row0), m.center[0], cy, *m.p, np.asarray(m.alpha, dtype=np.float64),
                 s, -1.0 if clip is None else float(clip))
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
