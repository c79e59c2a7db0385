"""Numba kernel of one reweighted step of the lens-family fit's IRLS
(:func:`vigproc.core.family_fit.irls`).

A step needs, over every pair, the Cauchy weight of its residual and the sums
Σ w·a·aᵀ and Σ w·a·d. In NumPy that was a matrix-vector product over a precomputed
array of the K(K+1)/2 + K products per pair (tens of MB read per step, through the
BLAS, whose threads spin against each other on a busy machine: 7× the time with other
processes running); here it is one pass over the K regressors, on one thread.
"""

from __future__ import annotations

import numpy as np
from numba import njit


# error_model numpy: no zero test at each division (1 + r² ≥ 1), which kept the weights' loop
# from being vectorised; the same bits
@njit(cache=True, nogil=True, fastmath=True, error_model="numpy")
def weighted_normal(at, d, weight, c, inv_s, H, g, wa):
    """Fill ``H`` (K×K, symmetric) with Σ w·a·aᵀ and ``g`` (K) with Σ w·a·d, where
    w = weight / (1 + ((d − a·c)·inv_s)²).

    Parameters
    ----------
    at : ndarray (K, n)
        The pairs' regressors, a row per coefficient.
    d, weight : ndarray (n,)
        The pairs' data and prior weights (a weight of 0 leaves a pair out).
    c : ndarray (K,)
        The coefficients the residuals are taken at.
    inv_s : float
        1 / the Cauchy scale.
    H, g : ndarray (K, K), (K,)
        Written (not accumulated into).
    wa : ndarray (2, n)
        Scratch.
    """
    K, n = at.shape
    w = wa[0]
    row = wa[1]
    # row by row over the pairs: each sum is a reduction over contiguous rows, which the
    # compiler vectorises (pair by pair, the K(K+1)/2 sums waited on each other in memory)
    for i in range(n):
        w[i] = d[i]
    for k in range(K):
        ck = c[k]
        for i in range(n):
            w[i] -= ck * at[k, i]
    for i in range(n):
        r = w[i] * inv_s
        w[i] = weight[i] / (1.0 + r * r)
    for k in range(K):
        s = 0.0
        for i in range(n):
            row[i] = w[i] * at[k, i]
            s += row[i] * d[i]
        g[k] = s
        # two sums a pass: each row read once for both (each sum in its own order, the
        # same bits as one a pass; 6-13 % less time, a micro-benchmark)
        m = k
        while m + 1 < K:
            s = 0.0
            s2 = 0.0
            for i in range(n):
                r = row[i]
                s += r * at[m, i]
                s2 += r * at[m + 1, i]
            H[k, m] = s
            H[m, k] = s
            H[k, m + 1] = s2
            H[m + 1, k] = s2
            m += 2
        if m < K:
            s = 0.0
            for i in range(n):
                s += row[i] * at[m, i]
            H[k, m] = s
            H[m, k] = s


@njit(cache=True, nogil=True)
def irls_fit(at, d, weight, c0, pinv, prior, scale, inv_s, iterations, tolerance, n_watch, relaxation):
    """The IRLS loop of :func:`vigproc.core.family_fit.irls`: each step solves
    (H·scale + Λ) c = g·scale + Λμ (``prior`` = Λμ) from :func:`weighted_normal`'s sums;
    it stops when none of the first ``n_watch`` coefficients moves by ``tolerance``.
    Each step moves ``relaxation`` times as far as the solve says. Returns c (K,)."""
    K, n = at.shape
    return irls_into(at, d, weight, c0, pinv, prior, scale, inv_s, iterations, tolerance, n_watch, relaxation,
                     np.empty((K, K)), np.empty(K), np.empty((2, n)))


@njit(cache=True, nogil=True)
def irls_into(at, d, weight, c0, pinv, prior, scale, inv_s, iterations, tolerance, n_watch, relaxation, H, g,
              scratch):
    """:func:`irls_fit` with the caller's scratch: ``H`` (K×K), ``g`` (K) and ``scratch``
    (2×n), which a loop of fits over the same pairs allocates once. Returns c (K,)."""
    c = c0.copy()
    for _ in range(iterations):
        weighted_normal(at, d, weight, c, inv_s, H, g, scratch)
        c, move, finite = solved_step(H, g, c, pinv, prior, scale, n_watch, relaxation)
        if not finite or move < tolerance:
            break
    return c


@njit(cache=True, nogil=True)
def solved_step(H, g, c, pinv, prior, scale, n_watch, relaxation):
    """One IRLS step from its sums ``H``, ``g`` at ``c``: the solution of
    (H·scale + Λ) c' = g·scale + Λμ (``pinv`` = Λ, ``prior`` = Λμ), moved ``relaxation`` times
    as far from c, the largest move of its first ``n_watch`` coefficients, and whether the
    system was finite (if not: NaNs, and the loop stops)."""
    A = H * scale + pinv
    b = g * scale + prior
    if not (np.all(np.isfinite(A)) and np.all(np.isfinite(b))):
        # what LAPACK gives for such a system, without its refusal here
        return np.full(c.shape[0], np.nan), np.nan, False
    c_new = np.linalg.solve(A, b)
    if relaxation != 1.0:
        c_new = c + relaxation * (c_new - c)
    move = 0.0
    for k in range(n_watch):
        move = max(move, abs(c_new[k] - c[k]))
    return c_new, move, True
