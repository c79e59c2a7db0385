"""Pixel-array helpers shared by the estimators: validation, luminance, log, binning.

All functions are pure and take float images in linear light.
"""

from __future__ import annotations

import operator

import numpy as np

from vigproc.errors import InvalidImageError

#: Rec. ITU-R BT.709 luminance weights for linear RGB.
LUMA_709 = np.array([0.2126, 0.7152, 0.0722])
#: Linear intensities are floored here before the log, so that a zero pixel does
#: not produce −inf (about half an 8-bit sRGB code step above black).
LOG_FLOOR = 1e-4
#: Largest frame accepted by the estimators (a decompression-bomb guard).
MAX_PIXELS = 1_000_000_000


def as_channels_last(img: np.ndarray, channel_axis: int | None) -> np.ndarray:
    """Return ``img`` as H×W or H×W×C (channels last) without copying when possible."""
    a = np.asarray(img)
    if a.ndim == 2:
        if channel_axis is not None:
            raise InvalidImageError("a 2-D image has no channel axis; pass channel_axis=None")
        return a
    if a.ndim == 3:
        if channel_axis is None:
            raise InvalidImageError(f"3-D image of shape {a.shape} needs a channel_axis")
        try:
            axis = operator.index(channel_axis)  # not 1.5, "0" or True
        except TypeError:
            axis = None
        if axis is None or isinstance(channel_axis, (bool, np.bool_)) or not -3 <= axis < 3:
            raise InvalidImageError(f"channel_axis must be an integer from -3 to 2 (or None), got {channel_axis!r}")
        return np.moveaxis(a, axis, -1)
    raise InvalidImageError(f"expected an H×W or H×W×C image, got shape {a.shape}")


#: Most negative value accepted, as a fraction of the image's maximum (noise around black).
NEGATIVE_FRACTION = 0.05


#: The smallest frame side an estimator takes, in pixels.
MIN_SIZE = 8


def require_size(a: np.ndarray, min_size: int = MIN_SIZE) -> None:
    """Raise :class:`InvalidImageError` when the H×W(×C) array ``a`` has a side shorter
    than ``min_size`` px."""
    h, w = a.shape[:2]
    if h < min_size or w < min_size:
        raise InvalidImageError(f"image of {w}x{h} px is too small (need at least {min_size} px a side)")


def check_image(img: np.ndarray, channel_axis: int | None = -1, min_size: int = MIN_SIZE) -> np.ndarray:
    """Validate a linear image and return it as float H×W or H×W×C.

    Raises
    ------
    InvalidImageError
        Wrong dimensions, non-numeric data, fewer than ``min_size`` px on a side,
        more than :data:`MAX_PIXELS`, any NaN/Inf, no positive pixel, a
        constant image (nothing to estimate from), or values below
        −:data:`NEGATIVE_FRACTION` × the maximum (not linear intensities).
    """
    a = np.asarray(img)
    if a.ndim == 2:
        channel_axis = None
    a = as_channels_last(a, channel_axis)
    if a.ndim == 3 and a.shape[2] == 1:
        a = a[..., 0]
    if a.dtype.kind not in "fiu" or a.dtype == np.bool_:
        raise InvalidImageError(f"image must be numeric, got dtype {a.dtype}")
    if a.ndim == 3 and not 1 <= a.shape[2] <= 4:
        raise InvalidImageError(f"expected 1-4 channels, got {a.shape[2]} (wrong channel_axis?)")
    require_size(a, min_size)
    h, w = a.shape[:2]
    if h * w > MAX_PIXELS:
        raise InvalidImageError(f"image of {w}x{h} px exceeds the {MAX_PIXELS} px limit")
    # one pass each, no mask: NaN propagates to both extremes and ±Inf shows in one of them
    hi, lo = a.max(), a.min()
    if a.dtype.kind == "f" and not (np.isfinite(hi) and np.isfinite(lo)):
        n = int(np.size(a) - np.count_nonzero(np.isfinite(a)))
        raise InvalidImageError(f"image has {n} NaN/Inf values; vigproc needs finite linear intensities")
    if not hi > 0:
        raise InvalidImageError("image has no positive pixel: linear intensities must be > 0")
    if lo == hi:
        raise InvalidImageError("image is constant: there is nothing to estimate vignetting from")
    # slightly negative values are noise around black in developed RAW data (kept in a
    # correction, left out of an estimate); large ones are not linear intensities
    if lo < -NEGATIVE_FRACTION * hi:
        raise InvalidImageError(
            f"image has values down to {float(lo):.4g} (its maximum is {float(hi):.4g}): not linear intensities "
            f"(negative values are accepted down to -{NEGATIVE_FRACTION:g} x the maximum, as noise around black)")
    return a


def luminance(img: np.ndarray) -> np.ndarray:
    """Linear luminance (float64) of an H×W or H×W×C channels-last image.

    RGB(A) uses the Rec. 709 weights; other channel counts use the channel mean.
    """
    a = np.asarray(img, dtype=np.float64)
    if a.ndim == 2:
        return a
    if a.shape[2] >= 3:
        return a[..., :3] @ LUMA_709
    return a.mean(axis=2)


def log_image(lum: np.ndarray, floor: float = LOG_FLOOR) -> np.ndarray:
    """log of a linear image, floored at ``floor`` (Lyu 2010, Eq. 3: i_v = log I_v)."""
    return np.log(np.maximum(lum, floor))


def bin_mean(a: np.ndarray, k: int, mask: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Average ``k``×``k`` blocks of a 2-D array (the remainder rows/cols are dropped).

    Parameters
    ----------
    a : ndarray, H×W
    k : int
        Block size (1 returns a copy).
    mask : ndarray of bool, H×W, optional
        Pixels to use; a block is valid only when all its pixels are.

    Returns
    -------
    binned : ndarray, (H//k)×(W//k), float64
    valid : ndarray of bool, same shape
    """
    h, w = a.shape
    if k == 1:
        valid = np.ones((h, w), dtype=bool) if mask is None else mask.copy()
        return np.array(a, dtype=np.float64), valid
    hb, wb = h // k, w // k
    blocks = np.asarray(a[: hb * k, : wb * k], dtype=np.float64).reshape(hb, k, wb, k)
    binned = blocks.mean(axis=(1, 3))
    if mask is None:
        valid = np.ones((hb, wb), dtype=bool)
    else:
        valid = mask[: hb * k, : wb * k].reshape(hb, k, wb, k).all(axis=(1, 3))
    return binned, valid


def binned_coords(n: int, k: int) -> np.ndarray:
    """Centre coordinates (relative to the full frame's centre) of ``n // k`` bins of size k."""
    nb = n // k
    return np.arange(nb) * k + (k - 1) / 2.0 - (n - 1) / 2.0


#: A 1×1 stand-in for "no mask" in the compiled binning (one signature for both cases).
_NO_MASK = np.ones((1, 1), dtype=np.bool_)
#: The largest block the compiled binning sums as NumPy does (NumPy's pairwise block,
#: :data:`vigproc.core._kernels.binning.MAX_BLOCK`; not imported here: a process that
#: only pools a profile never loads Numba).
_MAX_BLOCK = 128


def binned_log_copy(lum: np.ndarray, work_size: int, dark_fraction: float,
                    mask: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, int]:
    """The estimators' working copy of an H×W linear luminance frame.

    Bins it k×k (long side ≈ ``work_size``; a bin is valid when all its pixels are
    positive, finite and in ``mask``), masks bins darker than ``dark_fraction`` of
    the 99th percentile (noise and quantisation swamp their logs), and takes logs.

    Returns
    -------
    L : ndarray, (H//k)×(W//k), log luminance
    valid : ndarray of bool, same shape
    k : int
        The bin size (:func:`binned_coords` gives the bins' centres).
    """
    h, w = lum.shape
    k = max(1, int(round(max(h, w) / work_size)))
    if 1 < k <= _MAX_BLOCK:
        # one compiled pass, the same bits as the NumPy below (:mod:`vigproc.core._kernels.binning`)
        from vigproc.core._kernels.binning import bin_usable

        b, valid = bin_usable(np.ascontiguousarray(lum, dtype=np.float64),
                              np.ascontiguousarray(mask, dtype=np.bool_) if mask is not None else _NO_MASK,
                              mask is not None, k)
    else:
        ok = np.isfinite(lum) & (lum > 0)
        if mask is not None:
            ok &= mask
        b, valid = bin_mean(np.where(ok, lum, 0.0), k, ok)
    if valid.any():
        valid &= b > dark_fraction * np.percentile(b[valid], 99)
    return log_image(b), valid, k


def binned_log_channels(img: np.ndarray, k: int, valid: np.ndarray, dark_fraction: float) -> tuple[np.ndarray, np.ndarray]:
    """The working copy of each channel of an H×W×C linear frame, binned k×k as
    :func:`binned_log_copy` bins its luminance (``valid``: that copy's usable bins).

    A bin is usable in a channel when it is in ``valid`` and not darker than
    ``dark_fraction`` of the channel's 99th percentile. Two strided sums, not a
    k×k×C reshape: one pass over a 24 MP frame (about 0.1 s).

    Returns
    -------
    L : ndarray, C×(H//k)×(W//k), log of each channel's bin means
    valid : ndarray of bool, same shape
    """
    h, w, c = img.shape
    hb, wb = valid.shape
    a = np.asarray(img[: hb * k, : wb * k], dtype=np.float64)
    if k > 1:
        # one compiled pass, the same bits as the NumPy below (:mod:`vigproc.core._kernels.binning`)
        from vigproc.core._kernels.binning import bin_channels

        b = bin_channels(np.ascontiguousarray(a), hb, wb, k)
    else:
        sums = a.reshape(hb, k, wb * k, c).sum(axis=1).reshape(hb, wb, k, c).sum(axis=2)
        b = np.moveaxis(sums / (k * k), -1, 0)
    ok = np.broadcast_to(valid, b.shape).copy()
    for i in range(c):
        if ok[i].any():
            ok[i] &= b[i] > dark_fraction * np.percentile(b[i][ok[i]], 99)
    return log_image(b), ok


def reduce_codes(codes: np.ndarray, decode: np.ndarray, k: int, clip_level: float = 0.995,
                 clip_fraction: float = 1e-3) -> tuple[np.ndarray, np.ndarray | None]:
    """A display-encoded frame binned ``k``×``k`` in linear light, straight from its code
    values: the mean of ``decode[codes]`` over each block (the remainder rows and columns
    dropped, as :func:`bin_mean`), without a full-frame float copy; and which blocks
    hold only pixels the estimators would use.

    Parameters
    ----------
    codes : ndarray, H×W or H×W×C, uint8 or uint16
    decode : ndarray, float, increasing
        Linear value of every code.
    k : int
        Block size, at least 1 and at most the frame's shorter side.
    clip_level, clip_fraction : float
        A pixel with a channel at or above ``clip_level`` × the frame's largest value is
        a clipped highlight when at least ``clip_fraction`` of the pixels are
        (:func:`vigproc.core.estimate.clipped_mask`'s rule).

    Returns
    -------
    binned : ndarray, float32, (H//k)×(W//k) or (H//k)×(W//k)×C
    usable : ndarray of bool, (H//k)×(W//k), or None
        Blocks without a clipped highlight or a black pixel (None: all of them), as
        the mask the estimators take: a working copy's bin is usable when every pixel
        in it is.
    """
    from vigproc.core._kernels.codes import reduce_codes as _reduce

    a = np.asarray(codes)
    if a.dtype not in (np.uint8, np.uint16) or a.ndim not in (2, 3):
        raise InvalidImageError(f"codes must be an H×W(×C) uint8 or uint16 array, got {a.dtype} {a.shape}")
    x = np.ascontiguousarray(a[..., None] if a.ndim == 2 else a)
    h, w, c = x.shape
    if not 1 <= int(k) <= min(h, w):
        raise InvalidImageError(f"cannot bin a {w}x{h} frame by {k}")
    lut = np.ascontiguousarray(decode, dtype=np.float32)
    peak = int(x.max())
    if lut.ndim != 1 or lut.shape[0] < peak + 1:
        raise InvalidImageError(f"the decode table has {lut.shape[0]} entries for codes up to {peak}")
    # the smallest code at or above clip_level × the largest value (the table increases)
    hot_code = int(np.searchsorted(lut[: peak + 1], clip_level * lut[peak], side="left"))
    out = np.empty((h // k, w // k, c), dtype=np.float32)
    hot = np.zeros((h // k, w // k), dtype=np.int64)
    dark = np.zeros((h // k, w // k), dtype=np.int64)
    _reduce(x, lut, int(k), hot_code, out, hot, dark)
    usable = dark == 0
    if hot.sum() >= clip_fraction * h * w:
        usable &= hot == 0
    return (out[..., 0] if a.ndim == 2 else out), (None if usable.all() else usable)


def finish_corrected(out: np.ndarray, ndim: int, clip: float, channel_axis: int | None) -> np.ndarray:
    """The last steps of a per-plane correction (``out``: H×W×C float32, corrected in
    place): the clip (``clip`` > 0), the check that every value is finite, and the
    input's layout back (``ndim`` 2: one plane; ``channel_axis``).

    Raises
    ------
    InvalidImageError
        NaN or Inf in the result.
    """
    if clip > 0:
        np.minimum(out, np.float32(clip), out=out)
    if not np.all(np.isfinite(out)):
        raise InvalidImageError("the corrected image has NaN or Inf values (NaN/Inf in the input, or values "
                                "too large for float32 once corrected)")
    out = out[..., 0] if ndim == 2 else out
    if ndim == 3 and channel_axis not in (None, -1, 2):
        out = np.moveaxis(out, -1, channel_axis)
    return out
