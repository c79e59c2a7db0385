"""Numba kernel of the pooled nulls' draws (:func:`vigproc.forensics.lensmatch.pooled_null`):
sets of rows from distinct photographs, the same numbers NumPy's ``Generator`` gives.

A set was drawn in Python as ``rng.choice(P, n, replace=False)`` (P photographs) and then
``rng.integers(sizes[picks])`` (one row of each), 4000 sets a null: about 30 µs a set, most
of it ``choice``'s Python-level checks. Here the same algorithms run on the generator's
raw 64-bit outputs (``bit_generator.random_raw``), consumed as NumPy consumes them:

- a 32-bit draw is the low half of a raw output, the next one its high half (PCG64's
  ``next_uint32`` keeps the other half);
- a bounded integer in [0, r], r < 2³², is Lemire's multiply-and-reject on 32-bit draws
  (``buffered_bounded_lemire_uint32``; r = 0 draws nothing, r = 2³² − 1 is a 32-bit draw);
- ``choice`` without replacement from P ≤ 10 000 is Floyd's algorithm (for j from P − n
  to P − 1: a bounded draw in [0, j], or j itself when that one is taken), then the n
  picks are shuffled (for i from n − 1 down to 1: swap with a bounded draw in [0, i]).

The caller checks the result against NumPy's own ``choice`` (tests/test_lensmatch.py) and
falls back to it for more than 10 000 photographs (where NumPy uses a tail shuffle).
"""

from __future__ import annotations

import numpy as np
from numba import njit

_LOW32 = np.uint64(0xFFFFFFFF)


@njit(cache=True, nogil=True)
def _next_uint32(raw, st):
    """The next 32-bit draw; ``st`` = [next raw index, has a kept half, the kept half,
    ran out]."""
    if st[1] != 0:
        st[1] = 0
        return st[2]
    i = st[0]
    if i >= raw.size:
        st[3] = 1
        return np.uint64(0)
    v = raw[i]
    st[0] = i + 1
    st[1] = 1
    st[2] = v >> np.uint64(32)
    return v & _LOW32


@njit(cache=True, nogil=True)
def _bounded(raw, st, r):
    """A draw in [0, r] (r < 2³², uint64), Lemire's method as NumPy's."""
    if r == 0:
        return np.uint64(0)
    if r == _LOW32:
        return _next_uint32(raw, st)
    excl = r + np.uint64(1)
    m = _next_uint32(raw, st) * excl
    left = m & _LOW32
    if left < excl:
        threshold = (_LOW32 - r) % excl
        while left < threshold:
            m = _next_uint32(raw, st) * excl
            left = m & _LOW32
    return m >> np.uint64(32)


@njit(cache=True, nogil=True)
def distinct_group_rows(raw, sizes, first, members, n, rows):
    """Fill ``rows`` (draws × n) with sets of rows of distinct photographs.

    Parameters
    ----------
    raw : ndarray of uint64
        The generator's raw outputs, from its start.
    sizes, first : ndarray of int64 (P,)
        Each photograph's number of rows and the index of its first in ``members``.
    members : ndarray of int64
        Row indices, photograph by photograph.
    n : int
        Photographs per set (≤ P).
    rows : ndarray of int64 (draws, n)
        Written.

    Returns
    -------
    bool
        False when ``raw`` ran out (then ``rows`` is incomplete: call again with more).
    """
    P = sizes.size
    st = np.zeros(4, dtype=np.uint64)
    taken = np.zeros(P, dtype=np.bool_)
    picks = np.empty(n, dtype=np.int64)
    for d in range(rows.shape[0]):
        for j in range(P - n, P):
            v = np.int64(_bounded(raw, st, np.uint64(j)))
            if taken[v]:
                v = j
            taken[v] = True
            picks[j - (P - n)] = v
        for k in range(n):
            taken[picks[k]] = False
        for i in range(n - 1, 0, -1):
            k = np.int64(_bounded(raw, st, np.uint64(i)))
            t = picks[k]
            picks[k] = picks[i]
            picks[i] = t
        for k in range(n):
            p = picks[k]
            off = np.int64(_bounded(raw, st, np.uint64(sizes[p] - 1)))
            rows[d, k] = members[first[p] + off]
        if st[3] != 0:
            return False
    return True
