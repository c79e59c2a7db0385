"""Area-weighted resampling of 2-D arrays (benchmark protocols, previews, working copies)."""

from __future__ import annotations

import numpy as np


def area_matrix(n_in: int, n_out: int) -> np.ndarray:
    """Matrix M (n_out×n_in) averaging input samples over each output cell's footprint.

    Output cell i covers [i·s, (i+1)·s) in input units, s = n_in / n_out; each input
    sample contributes its overlap length. Rows sum to one.
    """
    s = n_in / n_out
    lo = np.arange(n_out)[:, None] * s
    hi = lo + s
    j = np.arange(n_in)[None, :]
    overlap = np.clip(np.minimum(hi, j + 1) - np.maximum(lo, j), 0.0, None)
    return overlap / overlap.sum(axis=1, keepdims=True)


def resize_area(img: np.ndarray, height: int, width: int) -> np.ndarray:
    """Resize an H×W array to ``height``×``width`` with an area (box) filter."""
    a = np.asarray(img, dtype=np.float64)
    return area_matrix(a.shape[0], height) @ a @ area_matrix(a.shape[1], width).T


def _area_axis(a: np.ndarray, n_out: int, axis: int) -> np.ndarray:
    """:func:`area_matrix`'s average along ``axis``, from running sums: the integral of
    the piecewise-constant samples at each cell's edges, differenced."""
    a = np.moveaxis(a, axis, 0)
    n_in = a.shape[0]
    s = n_in / n_out
    csum = np.concatenate([np.zeros((1,) + a.shape[1:]), np.cumsum(a, axis=0)])
    edges = np.arange(n_out + 1) * s
    j = np.minimum(np.floor(edges).astype(np.intp), n_in - 1)
    frac = (edges - j).reshape((-1,) + (1,) * (a.ndim - 1))
    integral = csum[j] + frac * a[j]
    return np.moveaxis((integral[1:] - integral[:-1]) / s, 0, axis)


def resize_area_sums(img: np.ndarray, height: int, width: int) -> np.ndarray:
    """:func:`resize_area` by running sums, for H×W or H×W×C arrays: O(H·W) per call
    where the dense matrix product costs O(H·W·(height + width)) (a per-frame working
    copy, not a one-off protocol). Equal to :func:`resize_area` to rounding (about 1e-12
    relative: the sums are taken in another order)."""
    a = np.asarray(img, dtype=np.float64)
    return _area_axis(_area_axis(a, height, 0), width, 1)
