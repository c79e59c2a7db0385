"""Numba kernels over a display-encoded frame's integer code values (8- or 16-bit).

A JPEG or PNG is stored as code values; decoding every sample to float linear light,
dividing, and encoding back with a float power costs several passes over a frame of
float32 temporaries. These kernels stay in the codes' own domain: a decode table
(code → linear), the gain, and the encode as a search in the table of the linear
values at which the output code steps up (exact round-half-up quantisation).
"""

from __future__ import annotations

import numpy as np
from numba import njit, prange

from vigproc.core._kernels.correct import row_gains


@njit(cache=True, nogil=True, inline="always")
def _reduce_rows(codes, lut, k, hot_code, j, wb, c, acc, nh, nd):
    # block row j's sums into acc (wb·c), its hot and black pixel counts into nh, nd. Each
    # block's sum runs row by row, left to right (the order fixes the float rounding).
    # Inlined with c a literal (see reduce_codes) so that the channel loop unrolls: with c
    # known only at run time the loop costs twice the lookups and adds it does
    for y in range(j * k, j * k + k):
        row = codes[y].reshape(-1)  # one contiguous line of w·c codes
        for i in range(wb):
            a = nh[i]
            b = nd[i]
            for dx in range(k):
                p = (i * k + dx) * c
                top = 0
                for ch in range(c):
                    v = row[p + ch]
                    acc[i * c + ch] += lut[v]
                    top = max(top, np.int64(v))
                a += top >= hot_code
                b += top == 0
            nh[i] = a
            nd[i] = b


@njit(cache=True, nogil=True, parallel=True)
def reduce_codes(codes, lut, k, hot_code, out, hot, dark):
    """out[j, i, c] = mean of lut[codes] over the k×k block (j, i) (remainder dropped).

    ``codes``: h×w×C integers, C-contiguous; ``lut``: float32 table code → linear;
    ``out``: (h//k)×(w//k)×C float32. Means in linear light, as binning a decoded frame
    gives. Per block, ``hot`` counts the pixels with a channel at or above ``hot_code``
    and ``dark`` those whose channels are all code 0 (what the estimators mask per pixel).
    """
    hb, wb, c = out.shape
    inv = np.float32(1.0 / (k * k))
    for j in prange(hb):
        acc = np.zeros(wb * c, dtype=np.float64)
        nh = np.zeros(wb, dtype=np.int64)
        nd = np.zeros(wb, dtype=np.int64)
        if c == 3:  # the usual frames: the channel count a constant the compiler unrolls
            _reduce_rows(codes, lut, k, hot_code, j, wb, 3, acc, nh, nd)
        elif c == 1:
            _reduce_rows(codes, lut, k, hot_code, j, wb, 1, acc, nh, nd)
        else:
            _reduce_rows(codes, lut, k, hot_code, j, wb, c, acc, nh, nd)
        for i in range(wb):
            hot[j, i] += nh[i]
            dark[j, i] += nd[i]
            for ch in range(c):
                out[j, i, ch] = np.float32(acc[i * c + ch]) * inv


@njit(cache=True, nogil=True, inline="always")
def _encode(v, steps, start):
    # the number of steps at or below v: the output code. ``start[i]`` counts the steps
    # below i / n (n its length), a lower bound for any v in that cell; from it a short
    # walk up (one or two steps for 8-bit output) finds the code exactly
    n = start.shape[0]
    i = int(v * n) - 1  # one cell lower: float32 rounding of v·n cannot overshoot
    code = start[min(max(i, 0), n - 1)]
    top = steps.shape[0]
    while code < top and steps[code] <= v:
        code += 1
    return code


@njit(cache=True, nogil=True, parallel=True)
def correct_codes(codes, out, lut, steps, start, row0, cx, cy, p1, p2, p3, alpha, strength, step=1,
                  exact_radius=0.0):
    """out = encode(lut[codes] / φ^strength) for the rows of ``codes`` (h×W×C).

    ``steps[c]``: the linear value from which the output code is c + 1 (sorted); values
    above the last step are the top code (clipped at the white point). ``start[i]``: the
    number of steps below i / len(start) (where the search for a code starts). The gain is the
    float kernel's (:func:`vigproc.core._kernels.correct.correct_rows`: interpolated
    between ``step`` columns, exact within ``exact_radius`` px of the centre).
    """
    h, w, c = codes.shape
    xs = (np.arange(w) - ((w - 1) / 2.0 + cx)).astype(np.float32)
    nk = (w - 1 + step - 1) // step + 1
    for j in prange(h):
        gains = np.empty(w, dtype=np.float32)
        row_gains(xs, (row0 + j) - cy, cx, p1, p2, p3, alpha, strength, step, nk, exact_radius, gains)
        src = codes[j]
        dst = out[j]
        for i in range(w):
            g = gains[i]
            for ch in range(c):
                dst[i, ch] = _encode(lut[src[i, ch]] * g, steps, start)
