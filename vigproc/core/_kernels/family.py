"""Numba kernels of the lens-family estimator: pair data and IRLS normal equations.

For each pair (v, v + s·e), e ∈ {x, y}, of valid bins of the log working copy L, the
datum is the log difference per unit step d = (L(v+se) − L(v) − M(v+se) + M(v)) / s
(M: the family's mean log profile) and its regressors a = (B(v+se) − B(v)) / s
(B: the components). The model predicts d = a·c; a Cauchy weight
w = 1 / (1 + (e/σ)²) of the residual e gives the weighted normal equations H c = g
of one IRLS step. A pair may carry a prior weight of its own (how alike its colour
channels change), which multiplies the Cauchy weight.
"""

from __future__ import annotations

import numpy as np
from numba import njit


@njit(cache=True, nogil=True)
def family_pairs(L, valid, M, B, steps, block, C, tau):
    """Pair data of a working copy.

    Parameters
    ----------
    L : float64 (h, w)       log working copy
    valid : bool (h, w)      bins that may be used (with colour: every channel usable)
    M : float64 (h, w)       mean log profile at each bin
    B : float64 (h, w, K)    components at each bin
    steps : int64 (S,)       pair steps in bins
    block : int64 (h, w)     block label of each bin (a pair is its first bin's)
    C : float64 (3, h, w)    log working copy of R, G, B, or (0, h, w): no colour
    tau : float              the chroma change (log units per step) of weight 1/2

    Returns
    -------
    d : float64 (n,), a : float64 (n, K), labels : int64 (n,)
    weight : float64 (n,)
        Each pair's weight by how alike its colour channels change: with the chroma
        change q = (ΔR − ΔG)² + (ΔB − ΔG)² of the per-unit-step log differences,
        1 / (1 + q/τ²); ones without colour. A lens's fall-off changes every channel
        alike; much of a scene's own shading does not.
    """
    h, w = L.shape
    K = B.shape[2]
    colour = C.shape[0] == 3
    inv_t2 = 1.0 / (tau * tau) if colour else 0.0
    n_max = 0
    for si in range(steps.shape[0]):
        s = steps[si]
        n_max += max(h - s, 0) * w + h * max(w - s, 0)
    d = np.empty(n_max)
    a = np.empty((n_max, K))
    labels = np.empty(n_max, dtype=np.int64)
    weight = np.ones(n_max)
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
                    if colour:
                        g = C[1, y + dy, x + dx] - C[1, y, x]
                        r = (C[0, y + dy, x + dx] - C[0, y, x] - g) * inv
                        b = (C[2, y + dy, x + dx] - C[2, y, x] - g) * inv
                        weight[n] = 1.0 / (1.0 + (r * r + b * b) * inv_t2)
                    n += 1
    return d[:n], a[:n], labels[:n], weight[:n]


@njit(cache=True, nogil=True)
def cauchy_normal_equations(d, a, labels, c, sigma, skip, weight):
    """Weighted normal equations of one IRLS step at coefficients ``c``.

    Pairs labelled ``skip`` are left out (-1: none); ``weight`` (n,) is each pair's
    prior weight (ones: none).

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
        wt = weight[i] / (1.0 + t)
        for p in range(K):
            g[p] += wt * a[i, p] * d[i]
            for q in range(K):
                H[p, q] += wt * a[i, p] * a[i, q]
    return H, g
