"""Numba kernel listing the lens-family fit's log-difference pairs
(:func:`vigproc.core.family_fit.pair_index`).

NumPy built them step by step and direction by direction from sliced copies of the
working copy, boolean masks and concatenations (a dozen temporaries per step); here each
pair is visited once, in the same order and with the same arithmetic (the same bits).
"""

from __future__ import annotations

import numpy as np
from numba import njit


@njit(cache=True, nogil=True)
def list_pairs(L, valid, steps, block, C, inv_t2, colour):
    """Every pair (v, v + s·e) of usable bins, s ∈ ``steps``, e = y then x for each s,
    in row-major order of v.

    Parameters
    ----------
    L : ndarray (h, w)
        Log working copy.
    valid : ndarray of bool (h, w)
    steps : ndarray of int (S,)
    block : ndarray of int (h, w)
        Each bin's jackknife block.
    C : ndarray (3, h, w)
        R, G, B log copies (read only with ``colour``).
    inv_t2 : float
        1 / τ² of the colour weight.
    colour : bool

    Returns
    -------
    first, second, inv_step, dlog, labels, weight, chroma (2, n; 0 rows without colour)
    """
    h, w = L.shape
    cap = 0
    for si in range(steps.shape[0]):
        s = steps[si]
        cap += max(h - s, 0) * w + h * max(w - s, 0)
    first = np.empty(cap, dtype=np.int64)
    second = np.empty(cap, dtype=np.int64)
    inv = np.empty(cap)
    dl = np.empty(cap)
    lab = np.empty(cap, dtype=np.int64)
    wt = np.empty(cap)
    chroma = np.empty((2 if colour else 0, cap))
    n = 0
    for si in range(steps.shape[0]):
        s = steps[si]
        for direction in range(2):
            dj, di = (s, 0) if direction == 0 else (0, s)
            for j in range(h - dj):
                for i in range(w - di):
                    j2, i2 = j + dj, i + di
                    if not (valid[j, i] and valid[j2, i2]):
                        continue
                    first[n] = j * w + i
                    second[n] = j2 * w + i2
                    inv[n] = 1.0 / s
                    dl[n] = (L[j2, i2] - L[j, i]) / s
                    lab[n] = block[j, i]
                    if colour:
                        g = C[1, j2, i2] - C[1, j, i]
                        r = (C[0, j2, i2] - C[0, j, i] - g) / s
                        b = (C[2, j2, i2] - C[2, j, i] - g) / s
                        wt[n] = 1.0 / (1.0 + (r * r + b * b) * inv_t2)
                        chroma[0, n] = r
                        chroma[1, n] = b
                    else:
                        wt[n] = 1.0
                    n += 1
    return first[:n], second[:n], inv[:n], dl[:n], lab[:n], wt[:n], chroma[:, :n]


@njit(cache=True, nogil=True)
def gather_pairs(m, bt, first, second, inv_step, dlog):
    """The pairs' data with a field divided out and their regressors
    (:func:`vigproc.core.family_fit.pairs_at`), in one pass each: the arithmetic of its
    NumPy gathers, in their order (the same bits).

    Parameters
    ----------
    m : ndarray (nb,)
        The field at each bin (flat).
    bt : ndarray (K, nb)
        The regressors at each bin, a row per component.
    first, second, inv_step, dlog : ndarray (n,)
        The pairs (:class:`vigproc.core.family_fit.PairIndex`).

    Returns
    -------
    d : ndarray (n,)
        dlog − (m[second] − m[first]) · inv_step.
    at : ndarray (K, n)
        (bt[:, second] − bt[:, first]) · inv_step.
    """
    n = first.shape[0]
    K = bt.shape[0]
    d = np.empty(n)
    at = np.empty((K, n))
    for p in range(n):
        d[p] = dlog[p] - (m[second[p]] - m[first[p]]) * inv_step[p]
    for k in range(K):
        row = bt[k]
        for p in range(n):
            at[k, p] = (row[second[p]] - row[first[p]]) * inv_step[p]
    return d, at
