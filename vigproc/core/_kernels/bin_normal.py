"""Numba kernels of an IRLS step's normal equations summed over bins instead of pairs
(the lens family's centre and shape fit, :mod:`vigproc.core._kernels.gauss_newton`).

Every pair's regressor is a difference of per-bin values, a_p = (J[:, v + o] − J[:, v])·t
(o the pair's offset in the flat working copy, t = 1/step), so Σ_p w·a·aᵀ = Jᵀ·L·J with L
the pairs' weighted graph Laplacian, and Σ_p w·a·d = Jᵀ·z with z the pairs' w·t·d
scattered to their bins. The pairs of one offset are a shifted copy of the bins ("slots":
a slot per bin, weight 0 where no pair starts), so L·J is a few shifted sums over the
bins, which vectorise: about 2 multiply-adds per pair and coefficient instead of the
(K + 1)/2 + 2 of the pair sums (:func:`vigproc.core._kernels.irls.weighted_normal`), over
arrays of bins that stay in cache. The sums are the same up to rounding (their order
differs): the fits agree to about 1e-10 (``tests/test_estimator_kernels.py``).

Numba caches :func:`bin_irls_into` with :func:`vigproc.core._kernels.irls.solved_step`
compiled into it and checks only this file's time stamp; the package's cache guard
(:mod:`vigproc.core._kernels`) drops the cache when any kernel source changes.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from vigproc.core._kernels.irls import solved_step


@njit(cache=True, nogil=True)
def pair_slots(first, second, inv_step, dlog, weight, nb):
    """The pairs laid out as slots: per offset q, ``dl[q, v]`` and ``wt[q, v]`` of the pair
    (v, v + offs[q]) (0 and 0 where there is none). A pair listed more than once (settings
    that give a step twice) counts as often as the sums over pairs count it: its slot's
    weight is the sum of its weights (its data are the same each time).

    Parameters
    ----------
    first, second, inv_step, dlog, weight : ndarray (n,)
        The pairs (:class:`vigproc.core.family_fit.PairIndex`) and their weights.
    nb : int
        Bins in the working copy.

    Returns
    -------
    offs : ndarray of int (Q,)
    invs : ndarray (Q,)
        Each offset's 1/step (the pairs of one offset share a step).
    dl, wt : ndarray (Q, nb)
    """
    n = first.shape[0]
    # at most an offset per pair (not a fixed cap: every step gives two offsets)
    offs_all = np.empty(max(n, 1), dtype=np.int64)
    invs_all = np.empty(max(n, 1))
    q_of = np.empty(n, dtype=np.int64)
    Q = 0
    for p in range(n):
        o = second[p] - first[p]
        q = q_of[p - 1] if p > 0 else 0  # the pairs come in runs of one offset
        if q >= Q or offs_all[q] != o:
            q = 0
        while q < Q and offs_all[q] != o:
            q += 1
        if q == Q:
            offs_all[q] = o
            invs_all[q] = inv_step[p]
            Q += 1
        elif invs_all[q] != inv_step[p]:
            raise ValueError("pairs of one offset with different steps")
        q_of[p] = q
    dl = np.zeros((Q, nb))
    wt = np.zeros((Q, nb))
    seen = np.zeros((Q, nb), dtype=np.bool_)
    for p in range(n):
        q = q_of[p]
        v = first[p]
        if seen[q, v] and dl[q, v] != dlog[p]:
            raise ValueError("one pair listed twice with different data")
        seen[q, v] = True
        dl[q, v] = dlog[p]
        wt[q, v] += weight[p]
    return offs_all[:Q].copy(), invs_all[:Q].copy(), dl, wt


@njit(cache=True, nogil=True)
def slot_data(M, offs, invs, dl, out):
    """Fill ``out`` (Q, nb) with each slot's data, the field ``M`` (nb,) divided out:
    dl − (M[v + o] − M[v])·t, the pairs' arithmetic (the same bits as their d); 0 past the
    last bin an offset reaches."""
    Q, nb = dl.shape
    for q in range(Q):
        o = offs[q]
        t = invs[q]
        for v in range(nb - o):
            out[q, v] = dl[q, v] - (M[v + o] - M[v]) * t
        for v in range(nb - o, nb):
            out[q, v] = 0.0


# error_model numpy: no zero test at each division (1 + r² ≥ 1), which kept the weights' loop
# from being vectorised; the same bits
@njit(cache=True, nogil=True, fastmath=True, error_model="numpy")
def bin_normal(J, ds, wt, offs, invs, c, inv_s, H, g, scratch):
    """Fill ``H`` (K×K, symmetric) with Σ w·a·aᵀ and ``g`` (K) with Σ w·a·d over the pairs,
    w = wt / (1 + ((d − a·c)·inv_s)²), summed over the bins: H = Jᵀ·(L·J), g = Jᵀ·z.

    Parameters
    ----------
    J : ndarray (K, nb)
        The regressors at each bin, a row per coefficient.
    ds, wt : ndarray (Q, nb)
        The slots' data (:func:`slot_data`) and weights (:func:`pair_slots`).
    offs, invs : ndarray (Q,)
        The slots' offsets and 1/steps.
    c, inv_s, H, g
        As :func:`vigproc.core._kernels.irls.weighted_normal`'s (``H``, ``g`` written).
    scratch : ndarray (2·Q + 3, nb)
        Scratch.
    """
    K, nb = J.shape
    Q = offs.shape[0]
    V = scratch[:Q]  # w·t² of each slot: its edge's weight in L
    Z = scratch[Q:2 * Q]  # w·t·d of each slot: its part of g
    F = scratch[2 * Q]
    z = scratch[2 * Q + 1]
    LJ = scratch[2 * Q + 2]
    for v in range(nb):
        F[v] = 0.0
        z[v] = 0.0
    for k in range(K):
        ck = c[k]
        Jk = J[k]
        for v in range(nb):
            F[v] += ck * Jk[v]
    # each loop elementwise over views shifted by the offset (the scatter to the bins apart;
    # an index v + o would be checked for wrapping at every access): the compiler vectorises
    for q in range(Q):
        o = offs[q]
        t = invs[q]
        m = nb - o
        Vq = V[q, :m]
        Zq = Z[q, :m]
        dq = ds[q, :m]
        wq = wt[q, :m]
        Flo = F[:m]
        Fhi = F[o:]
        for v in range(m):
            r = (dq[v] - (Fhi[v] - Flo[v]) * t) * inv_s
            w = wq[v] / (1.0 + r * r)  # 0 in an empty slot (weight 0, data 0, F finite)
            Vq[v] = w * t * t
            Zq[v] = w * t * dq[v]
        zlo = z[:m]
        zhi = z[o:]
        for v in range(m):
            zlo[v] -= Zq[v]
        for v in range(m):
            zhi[v] += Zq[v]
    for k in range(K):
        Jk = J[k]
        s = 0.0
        for v in range(nb):
            s += Jk[v] * z[v]
        g[k] = s
        for v in range(nb):
            LJ[v] = 0.0
        # (L·J_k)[v] = Σ over v's edges of their weight × (J_k[v] − J_k[the other end]),
        # differences first: J's range across the frame is far larger than a step's change.
        # Per offset one pass over the bins with an edge on both sides, the ends apart
        for q in range(Q):
            o = offs[q]
            Vq = V[q]
            for v in range(min(o, nb - o)):  # no edge below
                LJ[v] += Vq[v] * (Jk[v] - Jk[v + o])
            for v in range(max(nb - o, o), nb):  # no edge above
                LJ[v] += Vq[v - o] * (Jk[v] - Jk[v - o])
            m = nb - 2 * o
            if m > 0:
                Lc = LJ[o:nb - o]
                Jc = Jk[o:nb - o]
                Jup = Jk[2 * o:]
                Jdn = Jk[:m]
                Vc = Vq[o:nb - o]
                Vdn = Vq[:m]
                for v in range(m):
                    Lc[v] += Vc[v] * (Jc[v] - Jup[v]) + Vdn[v] * (Jc[v] - Jdn[v])
        for m in range(k, K):
            Jm = J[m]
            s = 0.0
            for v in range(nb):
                s += Jm[v] * LJ[v]
            H[k, m] = s
            H[m, k] = s


@njit(cache=True, nogil=True)
def bin_irls_into(J, ds, wt, offs, invs, c0, pinv, prior, scale, inv_s, iterations, tolerance, n_watch, H, g,
                  scratch):
    """:func:`vigproc.core._kernels.irls.irls_into` (relaxation 1) with each step's sums
    from :func:`bin_normal`. Returns c (K,)."""
    c = c0.copy()
    for _ in range(iterations):
        bin_normal(J, ds, wt, offs, invs, c, inv_s, H, g, scratch)
        c, move, finite = solved_step(H, g, c, pinv, prior, scale, n_watch, 1.0)
        if not finite or move < tolerance:
            break
    return c
