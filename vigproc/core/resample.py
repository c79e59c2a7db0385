"""Area-weighted resampling of small 2-D arrays (benchmark protocols, previews)."""

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
