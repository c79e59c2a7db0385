"""Numba kernels of the lens-family estimator: pair data and IRLS normal equations.

For each pair (v, v + s·e), e ∈ {x, y}, of valid bins of the log working copy L, the
datum is the log difference per unit step d = (L(v+se) − L(v) − M(v+se) + M(v)) / s
(M: the family's mean log profile) and its regressors a = (B(v+se) − B(v)) / s
(B: the components). The model predicts d = a·c; a Cauchy weight
w = 1 / (1 + (e/σ)²) of the residual e gives the weighted normal equations H c = g
of one IRLS step.
"""

from __future__ import annotations

import numpy as np
from numba import njit


@njit(cache=True, nogil=True)
def family_pairs(L, valid, M, B, steps, block):
    """Pair data of a working copy.

    Parameters
    ----------
    L : float64 (h, w)       log working copy
    valid : bool (h, w)      bins that may be used
    M : float64 (h, w)       mean log profile at each bin
    B : float64 (h, w, K)    components at each bin
    steps : int64 (S,)       pair steps in bins
    block : int64 (h, w)     block label of each bin (a pair is its first bin's)

    Returns
    -------
    d : float64 (n,), a : float64 (n, K), labels : int64 (n,)
    """
    h, w = L.shape
    K = B.shape[2]
    n_max = 0
    for si in range(steps.shape[0]):
        s = steps[si]
        n_max += max(h - s, 0) * w + h * max(w - s, 0)
    d = np.empty(n_max)
    a = np.empty((n_max, K))
    labels = np.empty(n_max, dtype=np.int64)
    n = 0
    for si in range(steps.shape[0]):
        s = steps[si]
        inv = 1.0 / s
        for axis in range(2):
            dy = s if axis == 0 else 0
            dx = 0 if axis == 0 else s
            for y in range(h - dy):
                for x in range(w - dx):
                    if not (valid[y, x] and valid[y + dy, x + dx]):
                        continue
                    d[n] = (L[y + dy, x + dx] - L[y, x] - M[y + dy, x + dx] + M[y, x]) * inv
                    for k in range(K):
                        a[n, k] = (B[y + dy, x + dx, k] - B[y, x, k]) * inv
                    labels[n] = block[y, x]
                    n += 1
    return d[:n], a[:n], labels[:n]


@njit(cache=True, nogil=True)
def cauchy_normal_equations(d, a, labels, c, sigma, skip):
    """Weighted normal equations of one IRLS step at coefficients ``c``.

    Pairs labelled ``skip`` are left out (-1: none).

    Returns
    -------
    H : float64 (K, K), g : float64 (K,)
    """
    K = a.shape[1]
    H = np.zeros((K, K))
    g = np.zeros(K)
    inv_s2 = 1.0 / (sigma * sigma)
    for i in range(d.shape[0]):
        if labels[i] == skip:
            continue
        pred = 0.0
        for k in range(K):
            pred += a[i, k] * c[k]
        e = d[i] - pred
        t = e * e * inv_s2
        wt = 1.0 / (1.0 + t)
        for p in range(K):
            g[p] += wt * a[i, p] * d[i]
            for q in range(K):
                H[p, q] += wt * a[i, p] * a[i, q]
    return H, g
