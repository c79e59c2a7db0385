"""Removing vignetting: divide the linear image by the attenuation field."""

from __future__ import annotations

import numpy as np

from vigproc.errors import InvalidImageError
from vigproc.image import as_channels_last
from vigproc.model import VignettingModel


def correct(
    img: np.ndarray, model: VignettingModel, *, channel_axis: int | None = -1,
    strength: float = 1.0, clip: float | None = None,
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

    Returns
    -------
    ndarray, float32, same layout as ``img``
    """
    if not np.isfinite(strength) or strength < 0:
        raise InvalidImageError(f"strength must be a finite number >= 0, got {strength}")
    a = np.asarray(img)
    if a.ndim == 2:
        channel_axis = None
    x = as_channels_last(a, channel_axis)
    gain = np.exp(-strength * model.log_field(x.shape[:2])).astype(np.float32)
    out = x.astype(np.float32) * (gain if x.ndim == 2 else gain[..., None])
    if clip is not None:
        np.minimum(out, np.float32(clip), out=out)
    if a.ndim == 3 and channel_axis is not None:
        out = np.moveaxis(out, -1, channel_axis)
    return out
