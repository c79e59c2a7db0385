"""Numba kernels of the estimators' working copies (:func:`vigproc.core.pixels.binned_log_copy`,
:func:`vigproc.core.pixels.binned_log_channels`): a frame binned k×k in one pass.

In NumPy each copy was a mask, a masked copy of the frame, a k×k mean through a 4-D
view and a k×k ``all`` of the mask (about 2 ms for a 480×320 frame, four copies a
frame on the default's off-centre path). Here one pass reads each pixel once. The
sums are NumPy's, in its order (no fastmath): a block's mean is the sequential sum of
its rows' pairwise sums (:func:`_row_sum`, NumPy's ``pairwise_sum``) divided by k²; a
channel's, the sequential sum over its columns of the sequential sums down them
(``tests/test_binning_kernels.py`` checks the bits).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

#: Longest row :func:`_row_sum` sums as NumPy does (its ``PW_BLOCKSIZE``): above it NumPy
#: splits the row recursively, and the callers keep NumPy's own code.
MAX_BLOCK = 128


@njit(cache=True, nogil=True, inline="always")
def _row_sum(v, k):
    """NumPy's ``pairwise_sum`` of ``v[:k]`` for k ≤ :data:`MAX_BLOCK`: a plain sum from 0
    below 8 entries, else eight running sums combined as a tree, then the rest."""
    if k < 8:
        s = 0.0
        for i in range(k):
            s += v[i]
        return s
    r0, r1, r2, r3, r4, r5, r6, r7 = v[0], v[1], v[2], v[3], v[4], v[5], v[6], v[7]
    end = k - k % 8
    i = 8
    while i < end:
        r0 += v[i]
        r1 += v[i + 1]
        r2 += v[i + 2]
        r3 += v[i + 3]
        r4 += v[i + 4]
        r5 += v[i + 5]
        r6 += v[i + 6]
        r7 += v[i + 7]
        i += 8
    s = ((r0 + r1) + (r2 + r3)) + ((r4 + r5) + (r6 + r7))
    while i < k:
        s += v[i]
        i += 1
    return s


@njit(cache=True, nogil=True)
def bin_usable(lum, mask, use_mask, k):
    """k×k block means of a 2-D frame over its usable pixels (positive, finite and, with
    ``use_mask``, in ``mask``; the others count as 0), and which blocks hold only usable
    pixels; the remainder rows and columns dropped.

    Parameters
    ----------
    lum : ndarray (H, W), float64, C-contiguous
    mask : ndarray (H, W) of bool, C-contiguous (read only with ``use_mask``)
    use_mask : bool
    k : int
        Block size, 2 to :data:`MAX_BLOCK`.

    Returns
    -------
    binned : ndarray (H // k, W // k)
    valid : ndarray of bool, the same shape
    """
    hb, wb = lum.shape[0] // k, lum.shape[1] // k
    out = np.empty((hb, wb))
    valid = np.ones((hb, wb), dtype=np.bool_)
    row = np.empty(k)
    kk = float(k * k)
    for j in range(hb):
        for i in range(wb):
            s = 0.0
            ok_all = True
            for r in range(k):
                y = j * k + r
                for c in range(k):
                    x = i * k + c
                    v = lum[y, x]
                    ok = math.isfinite(v) and v > 0.0
                    if use_mask:
                        ok = ok and mask[y, x]
                    if ok:
                        row[c] = v
                    else:
                        row[c] = 0.0
                        ok_all = False
                s += _row_sum(row, k)
            out[j, i] = s / kk
            valid[j, i] = ok_all
    return out, valid


@njit(cache=True, nogil=True)
def bin_channels(img, hb, wb, k):
    """k×k block means of each channel of an H×W×C frame, channels first.

    Parameters
    ----------
    img : ndarray (H, W, C), float64, C-contiguous
    hb, wb : int
        Blocks down and across (at most H // k, W // k).
    k : int
        Block size.

    Returns
    -------
    ndarray (C, hb, wb)
    """
    C = img.shape[2]
    out = np.empty((C, hb, wb))
    cols = np.empty((wb * k, C))
    kk = float(k * k)
    for j in range(hb):
        # each column's sum down the block row, the rows read in memory order
        for x in range(wb * k):
            for ch in range(C):
                cols[x, ch] = 0.0
        for r in range(k):
            y = j * k + r
            for x in range(wb * k):
                for ch in range(C):
                    cols[x, ch] += img[y, x, ch]
        for i in range(wb):
            for ch in range(C):
                s = 0.0
                for c in range(k):
                    s += cols[i * k + c, ch]
                out[ch, j, i] = s / kk
    return out
