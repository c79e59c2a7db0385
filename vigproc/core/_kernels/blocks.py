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
