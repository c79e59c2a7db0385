"""Numba kernel dividing a full-resolution image by φ computed on the fly.

One pass over the pixels: for each pixel the gain 1/φ = (1 + q/4)² / G is computed
once and applied to every channel, so the cost stays close to a memory copy. No
field array is ever allocated.
"""

from __future__ import annotations

import numpy as np
from numba import njit, prange

from vigproc.core._kernels.field import G_FLOOR


@njit(cache=True, nogil=True, fastmath=True)
def _row_gains(xs, dy, p1, p2, p3, alpha, strength, gains):
    # A branch-free loop over x with the 7-term Horner unrolled, so LLVM vectorises
    # it (sqrt, divide); the model fixes k = 7 (Lyu 2010).
    # float32: twice the SIMD width; ~1e-6 relative error, far below any photo's noise
    f = np.float32
    a1, a2, a3, a4, a5, a6, a7 = (f(alpha[0]), f(alpha[1]), f(alpha[2]), f(alpha[3]), f(alpha[4]),
                                  f(alpha[5]), f(alpha[6]))
    qy = f(p3 * dy * dy)
    qxy = f(2.0 * p2 * dy)
    fp1 = f(p1)
    one = f(1.0)
    quarter = f(0.25)
    floor = f(G_FLOOR)
    zero = f(0.0)
    for i in range(xs.shape[0]):
        dx = xs[i]
        q = max((fp1 * dx + qxy) * dx + qy, zero)
        r = np.sqrt(q)
        acc = r * (a1 + r * (a2 + r * (a3 + r * (a4 + r * (a5 + r * (a6 + r * a7))))))
        g = max(one - acc, floor)
        a = one + quarter * q
        gains[i] = a * a / g
    if strength != 1.0:
        for i in range(xs.shape[0]):
            gains[i] = np.exp(np.float32(strength) * np.log(gains[i]))


@njit(cache=True, nogil=True, fastmath=True)
def _row_gains_interp(xs, dy, p1, p2, p3, alpha, strength, step, knots, gains):
    """Gains at every ``step``-th column (and the last), linearly interpolated between.

    The caller picks ``step`` so the interpolation error stays below a bound
    (:func:`vigproc.core.correct.gain_step`); step 1 is exact evaluation.
    """
    w = xs.shape[0]
    if step == 1:
        _row_gains(xs, dy, p1, p2, p3, alpha, strength, gains)
        return
    nk = knots.shape[0]
    kx = np.empty(nk, dtype=np.float32)
    for t in range(nk):
        kx[t] = xs[min(t * step, w - 1)]
    kg = np.empty(nk, dtype=np.float32)
    _row_gains(kx, dy, p1, p2, p3, alpha, strength, kg)
    for t in range(nk - 1):
        i0 = t * step
        i1 = min(i0 + step, w - 1)
        g0 = kg[t]
        d = (kg[t + 1] - g0) / np.float32(i1 - i0) if i1 > i0 else np.float32(0.0)
        for i in range(i0, i1):
            gains[i] = g0 + d * np.float32(i - i0)
    gains[w - 1] = kg[nk - 1]


@njit(cache=True, nogil=True)
def row_gains(xs, dy, cx, p1, p2, p3, alpha, strength, step, nk, exact_radius, gains):
    """The gains 1/φ^strength of one row ``dy`` px from the centre (``xs``: the columns'
    offsets), interpolated between ``step`` columns (``nk`` knots) except within
    ``exact_radius`` px of the centre, where α1·r makes the gain a cone."""
    w = xs.shape[0]
    _row_gains_interp(xs, dy, p1, p2, p3, alpha, strength, step, np.empty(nk), gains)
    if step > 1 and abs(dy) < exact_radius:
        i0 = max(0, int(np.floor((w - 1) / 2.0 + cx - exact_radius)))
        i1 = min(w, int(np.ceil((w - 1) / 2.0 + cx + exact_radius)) + 1)
        if i1 > i0:
            _row_gains(xs[i0:i1], dy, p1, p2, p3, alpha, strength, gains[i0:i1])


@njit(cache=True, nogil=True, parallel=True)
def correct_rows(img, out, row0, cx, cy, p1, p2, p3, alpha, strength, clip, step=1, exact_radius=0.0):
    """out[j, i, :] = img[j, i, :] / φ^strength for the rows of ``img`` (h×W×C).

    ``row0`` is the frame row of ``img[0]``, so a stripe of a larger frame can be
    corrected on its own. ``cx`` is the centre's x offset from the frame centre and
    ``cy`` the centre's absolute row. ``clip`` ≤ 0 means no clipping. With
    ``step`` > 1 the gain is interpolated between columns, except within
    ``exact_radius`` px of the centre, where α1·r makes it a cone (not smooth).

    Returns the number of rows whose output holds NaN or Inf (checked in the same
    pass, so validating costs no second sweep over the frame).
    """
    h, w, c = img.shape
    bad = np.zeros(h, dtype=np.int64)
    xs = (np.arange(w) - ((w - 1) / 2.0 + cx)).astype(np.float32)
    nk = (w - 1 + step - 1) // step + 1  # knots at 0, step, 2·step, ..., and w−1
    for j in prange(h):
        gains = np.empty(w, dtype=np.float32)
        row_gains(xs, (row0 + j) - cy, cx, p1, p2, p3, alpha, strength, step, nk, exact_radius, gains)
        if not _apply_row(img[j].reshape(w * c), out[j].reshape(w * c), gains, c, np.float32(clip)):
            bad[j] = 1
    return bad.sum()


# fast-math without "no NaN/Inf": the finiteness check below must not be folded away
_FINITE_SAFE = {"nsz", "arcp", "contract", "afn", "reassoc"}


@njit(cache=True, nogil=True, fastmath=_FINITE_SAFE)
def _apply_row(src, dst, gains, c, clip):
    # one gain per sample in a small (cache-resident) buffer, then a flat multiply
    # that vectorises; clipping is a separate pass, only when asked for.  Returns
    # whether the row's output is finite: x·0 is 0 for finite x and NaN otherwise,
    # a reduction that vectorises with the multiply (the row is in cache)
    n = src.shape[0]
    g = np.empty(n, dtype=np.float32)
    for i in range(gains.shape[0]):
        gi = gains[i]
        for k in range(c):
            g[i * c + k] = gi
    zero = np.float32(0.0)
    acc = np.float32(0.0)
    for t in range(n):
        v = src[t] * g[t]
        dst[t] = v
        acc += v * zero
    if clip > 0.0:
        for t in range(n):
            dst[t] = min(dst[t], clip)
    return acc == zero
