"""Numba kernels evaluating the generalized Kang-Weiss vignetting function.

φ(v; θ) = A(v)·G(v),  A = 1 / (1 + (r/2)²)²,  G = 1 − Σ_{i=1..7} α_i r^i,
r² = (v − c)ᵀ P (v − c)                                  (Lyu 2010, Eq. 2)

Coordinates are pixels relative to the frame centre ((W−1)/2, (H−1)/2), x to the
right (columns), y down (rows). The kernels take explicit coordinate vectors so the
same code serves full frames, working copies and border strips.
"""

from __future__ import annotations

import numpy as np
from numba import njit, prange

#: G below this is treated as "no light": the model is invalid there.
G_FLOOR = 1e-9


@njit(cache=True, nogil=True, inline="always")
def _poly_g(r, alpha):
    # Horner evaluation of 1 - sum_i alpha_i r^i
    acc = 0.0
    for i in range(alpha.shape[0] - 1, -1, -1):
        acc = (acc + alpha[i]) * r
    return 1.0 - acc


@njit(cache=True, nogil=True, inline="always")
def _log_field_row(xs, dy, cx, p1, p2, p3, alpha, out_row):
    gmin = np.inf
    for i in range(xs.shape[0]):
        dx = xs[i] - cx
        q = p1 * dx * dx + 2.0 * p2 * dx * dy + p3 * dy * dy
        if q < 0.0:
            q = 0.0
        g = _poly_g(np.sqrt(q), alpha)
        if g < gmin:
            gmin = g
        if g < G_FLOOR:
            g = G_FLOOR
        out_row[i] = -2.0 * np.log1p(0.25 * q) + np.log(g)
    return gmin


@njit(cache=True, nogil=True)
def log_field_grid(xs, ys, cx, cy, p1, p2, p3, alpha, out):
    """Fill ``out[j, i]`` with log φ at (xs[i], ys[j]); returns min G on the grid.

    Serial: for strips and working copies, where thread start-up would dominate.
    """
    gmin = np.inf
    for j in range(ys.shape[0]):
        gmin = min(gmin, _log_field_row(xs, ys[j] - cy, cx, p1, p2, p3, alpha, out[j]))
    return gmin


@njit(cache=True, nogil=True, parallel=True)
def log_field_grid_parallel(xs, ys, cx, cy, p1, p2, p3, alpha, out):
    """:func:`log_field_grid` with rows spread over threads, for full frames."""
    ny = ys.shape[0]
    gmin_rows = np.empty(ny)
    for j in prange(ny):
        gmin_rows[j] = _log_field_row(xs, ys[j] - cy, cx, p1, p2, p3, alpha, out[j])
    return gmin_rows.min() if ny > 0 else np.inf
