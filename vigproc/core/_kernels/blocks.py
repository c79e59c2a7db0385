"""Numba kernel of the lens-family fit's per-block normal equations
(:func:`vigproc.core.family_fit.linear_jackknife`).

The delete-one-block jackknife refits the field once per block, each refit a few IRLS
passes over every pair. Linearised about the full fit, every refit needs only each
block's sums at the full fit's residuals: the reweighted (IRLS) and the Newton
curvature of the Cauchy loss and its gradient, all gathered in one pass here.
"""

from __future__ import annotations

import numpy as np
from numba import njit


@njit(cache=True, nogil=True)
def block_normal(at, d, weight, labels, c, inv_s, n_blocks, HI, HN, G):
    """Fill, per block b (``labels``), HI[b] = Σ w·a·aᵀ, HN[b] = Σ w'·a·aᵀ and
    G[b] = Σ w·a·r, with r = d − a·c, u = r·inv_s, w = weight / (1 + u²) (the IRLS weight)
    and w' = weight·(1 − u²) / (1 + u²)² (the Cauchy loss's own curvature).

    Parameters
    ----------
    at : ndarray (K, n)
        The pairs' regressors, a row per coefficient.
    d, weight : ndarray (n,)
        The pairs' data and prior weights.
    labels : ndarray (n,) of int
        Each pair's block, 0 .. n_blocks − 1.
    c : ndarray (K,)
        The coefficients the residuals are taken at.
    inv_s : float
        1 / the Cauchy scale.
    n_blocks : int
    HI, HN, G : ndarray (n_blocks, K, K), (n_blocks, K, K), (n_blocks, K)
        Written (not accumulated into).
    """
    K, n = at.shape
    HI[:] = 0.0
    HN[:] = 0.0
    G[:] = 0.0
    for i in range(n):
        wt = weight[i]
        if wt == 0.0:
            continue
        b = labels[i]
        r = d[i]
        for k in range(K):
            r -= c[k] * at[k, i]
        u = r * inv_s
        q = 1.0 / (1.0 + u * u)
        w = wt * q
        wn = w * q * (1.0 - u * u)
        for k in range(K):
            ak = at[k, i]
            G[b, k] += w * ak * r
            for m in range(k, K):
                p = ak * at[m, i]
                HI[b, k, m] += w * p
                HN[b, k, m] += wn * p
    for b in range(n_blocks):
        for k in range(K):
            for m in range(k + 1, K):
                HI[b, m, k] = HI[b, k, m]
                HN[b, m, k] = HN[b, k, m]


@njit(cache=True, nogil=True)
def linear_refits(HI, HN, G, c, pinv, pmean, scale, iterations, tolerance):
    """The delete-one-block refits of the quadratic model about the full fit ``c``: for
    each block b, δ ← δ + A₋ᵦ⁻¹ (S₋ᵦ − N₋ᵦ δ) at most ``iterations`` times, stopping when no
    coefficient moves by ``tolerance``, with A₋ᵦ = scale·(ΣHI − HI[b]) + Λ,
    N₋ᵦ = scale·(ΣHN − HN[b]) + Λ and S₋ᵦ = scale·(ΣG − G[b]) − Λ(c − μ). Returns the refits
    c + δ as rows (n_blocks, K)."""
    nb, K = G.shape
    hi = np.zeros((K, K))
    hn = np.zeros((K, K))
    g = np.zeros(K)
    for b in range(nb):
        hi += HI[b]
        hn += HN[b]
        g += G[b]
    prior = pinv @ (c - pmean)
    rows = np.empty((nb, K))
    for b in range(nb):
        A = scale * (hi - HI[b]) + pinv
        N = scale * (hn - HN[b]) + pinv
        S = scale * (g - G[b]) - prior
        delta = np.zeros(K)
        for _ in range(iterations):
            step = np.linalg.solve(A, S - N @ delta)
            delta += step
            move = 0.0
            for k in range(K):
                move = max(move, abs(step[k]))
            if not move >= tolerance:
                break
        rows[b] = c + delta
    return rows
