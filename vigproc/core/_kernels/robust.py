"""Numba kernels of the default (robust per-pixel) estimator.

The data are log-intensity differences d = L(v + s·e) − L(v) between valid pixels of
a binned working copy, for steps s and directions e ∈ {x, y}. A model F(v; θ) = log φ
predicts them as F(v + s·e) − F(v); the residual e = d − ΔF is scored with the
Cauchy loss ρ(e) = log(1 + (e/σ_s)²), minimised by iteratively reweighted
Gauss-Newton (weights w = 1 / (1 + (e/σ_s)²)).
"""

from __future__ import annotations

import numpy as np
from numba import njit

N_PARAMS = 12
#: Loss kinds: Cauchy ρ(u) = log(1 + u²); Huber ρ(u) = u²/2 (|u| ≤ 1), |u| − ½ otherwise;
#: POWER ρ(u) = (1 + u²)^(p/2) − 1, a smoothed hyper-Laplacian |u|^p (p = POWER_EXPONENT).
CAUCHY = 0
HUBER = 1
POWER = 2
#: Exponent of the POWER loss: the heavy-tailed (hyper-Laplacian) law of natural-image
#: log-gradients, p ≈ 0.8 (Levin et al., SIGGRAPH 2007), as used by the radial-gradient
#: method of Zheng et al. (2009) for vignetting.
POWER_EXPONENT = 0.8


@njit(cache=True, nogil=True, inline="always")
def _rho_w(u2, kind):
    """Loss ρ and IRLS weight w (with ρ'(u) ∝ w·u) for squared normalised residual u²."""
    if kind == CAUCHY:
        return np.log1p(u2), _weight(u2, kind)
    if kind == POWER:
        t = (1.0 + u2) ** (0.5 * POWER_EXPONENT - 1.0)
        return t * (1.0 + u2) - 1.0, _weight(u2, kind)
    if u2 <= 1.0:
        return 0.5 * u2, 1.0
    return np.sqrt(u2) - 0.5, _weight(u2, kind)


@njit(cache=True, nogil=True, inline="always")
def _weight(u2, kind):
    """:func:`_rho_w`'s weight alone (the loss's logarithm or power is most of its cost)."""
    if kind == CAUCHY:
        return 1.0 / (1.0 + u2)
    if kind == POWER:
        return 0.5 * POWER_EXPONENT * (1.0 + u2) ** (0.5 * POWER_EXPONENT - 1.0)
    if u2 <= 1.0:
        return 1.0
    return 1.0 / np.sqrt(u2)


@njit(cache=True, nogil=True)
def robust_loss(L, valid, F, steps, sigma, kind=CAUCHY):
    """Σ ρ(e) over all valid pairs, and the number of pairs."""
    h, w = L.shape
    loss = 0.0
    n = 0
    for si in range(steps.shape[0]):
        s = steps[si]
        inv = 1.0 / (sigma[si] * sigma[si])
        for j in range(h):
            for i in range(w):
                if not valid[j, i]:
                    continue
                if i + s < w and valid[j, i + s]:
                    e = (L[j, i + s] - L[j, i]) - (F[j, i + s] - F[j, i])
                    loss += _rho_w(e * e * inv, kind)[0]
                    n += 1
                if j + s < h and valid[j + s, i]:
                    e = (L[j + s, i] - L[j, i]) - (F[j + s, i] - F[j, i])
                    loss += _rho_w(e * e * inv, kind)[0]
                    n += 1
    return loss, n


@njit(cache=True, nogil=True)
def count_pairs(valid, steps):
    """The number of pairs :func:`robust_loss` sums over (it depends on the usable bins
    alone: no residual, no logarithm)."""
    h, w = valid.shape
    n = 0
    for si in range(steps.shape[0]):
        s = steps[si]
        for j in range(h):
            for i in range(w):
                if not valid[j, i]:
                    continue
                if i + s < w and valid[j, i + s]:
                    n += 1
                if j + s < h and valid[j + s, i]:
                    n += 1
    return n


#: Pairs gathered before their products are summed (:func:`normal_equations`): their
#: regressors' differences (12 × 256 floats) stay in the first-level cache.
_CHUNK = 256


@njit(cache=True, nogil=True, fastmath=True)
def _flush(H, g, D, we, e, m):
    """Add Σ w·j·jᵀ (upper triangle) and Σ w·j·e over the first ``m`` gathered pairs
    (fastmath: the reductions vectorised; the residuals and weights are not)."""
    n = D.shape[0]
    row = np.empty(m)
    for a in range(n):
        s = 0.0
        Da = D[a]
        for p in range(m):
            row[p] = Da[p] * we[p]
            s += row[p] * e[p]
        g[a] += s
        for b in range(a, n):
            Db = D[b]
            s = 0.0
            for p in range(m):
                s += row[p] * Db[p]
            H[a, b] += s


@njit(cache=True, nogil=True)
def normal_equations(L, valid, F, J, steps, sigma, kind=CAUCHY, with_loss=True):
    """IRLS Gauss-Newton system for the robust loss ``kind``.

    The pairs are gathered a chunk at a time and each sum is a reduction over the
    chunk's rows (pair by pair, the n(n+1)/2 sums were read and written in memory at
    every pair: 1.6× the time).

    Returns
    -------
    H : (n, n) Σ w/σ² j jᵀ over pairs (j = ΔJ), symmetric
    g : (n,)   Σ w/σ² j e
    loss : Σ ρ(e); NaN without ``with_loss`` (the Cauchy loss's logarithm at every pair
        was a third of the time of a system whose loss the caller does not read)
    n_pairs : int
    """
    h, w = L.shape
    n = J.shape[2]
    H = np.zeros((n, n))
    g = np.zeros(n)
    D = np.empty((n, _CHUNK))
    we = np.empty(_CHUNK)
    ee = np.empty(_CHUNK)
    loss = 0.0
    npairs = 0
    m = 0
    for si in range(steps.shape[0]):
        s = steps[si]
        inv = 1.0 / (sigma[si] * sigma[si])
        for j in range(h):
            for i in range(w):
                if not valid[j, i]:
                    continue
                for d in range(2):
                    if d == 0:
                        j2, i2 = j, i + s
                    else:
                        j2, i2 = j + s, i
                    if i2 >= w or j2 >= h or not valid[j2, i2]:
                        continue
                    e = (L[j2, i2] - L[j, i]) - (F[j2, i2] - F[j, i])
                    if with_loss:
                        rho, wt = _rho_w(e * e * inv, kind)
                        loss += rho
                    else:
                        wt = _weight(e * e * inv, kind)
                    npairs += 1
                    for a in range(n):
                        D[a, m] = J[j2, i2, a] - J[j, i, a]
                    we[m] = inv * wt
                    ee[m] = e
                    m += 1
                    if m == _CHUNK:
                        _flush(H, g, D, we, ee, m)
                        m = 0
    if m:
        _flush(H, g, D, we, ee, m)
    for a in range(n):
        for b in range(a):
            H[a, b] = H[b, a]
    return H, g, loss if with_loss else np.nan, npairs


@njit(cache=True, nogil=True)
def pair_residuals(L, valid, F, s):
    """All residuals of step ``s`` (both directions), for robust scale estimates."""
    h, w = L.shape
    out = np.empty(2 * h * w)
    n = 0
    for j in range(h):
        for i in range(w):
            if not valid[j, i]:
                continue
            if i + s < w and valid[j, i + s]:
                out[n] = (L[j, i + s] - L[j, i]) - (F[j, i + s] - F[j, i])
                n += 1
            if j + s < h and valid[j + s, i]:
                out[n] = (L[j + s, i] - L[j, i]) - (F[j + s, i] - F[j, i])
                n += 1
    return out[:n]
