"""Numba kernel of one Gauss-Newton step's data in the lens family's centre and shape fit
(:func:`vigproc.core.family_fit._geometry_fit`).

At each step the fit needs, for every pair of bins (v, v + s·e), the log difference with
the family's mean field divided out and the differences of the field's derivatives by
the coefficients and the geometry (:func:`vigproc.core.family_fit._geometry_columns`,
:func:`vigproc.core.family_fit.pairs_at`). In NumPy that was about twenty temporaries
over the bins and two gathers of a K+E-column array per step; here it is one pass over
the bins and one over the pairs, with the same operations in the same order (the same
bits: ``np.interp``'s arithmetic is reproduced, no fastmath).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit


@njit(cache=True, nogil=True, inline="always")
def _locate(x, xp):
    """The interval of ``xp`` (ascending) that holds x ≥ xp[0]: lo with xp[lo] ≤ x <
    xp[lo + 1], or the last index for x ≥ xp[-1]."""
    n = xp.shape[0]
    if x >= xp[n - 1]:
        return n - 1
    lo, hi = 0, n - 1
    while hi - lo > 1:
        mid = (lo + hi) >> 1
        if xp[mid] <= x:
            lo = mid
        else:
            hi = mid
    return lo


@njit(cache=True, nogil=True, inline="always")
def _locate_near(x, xp, inv_dx):
    """:func:`_locate` for ``xp`` strictly increasing and about evenly spaced (1 /
    ``inv_dx`` apart): started at (x − xp[0])·inv_dx and walked to the interval that holds x,
    the same index as the binary search (a strictly increasing ``xp`` has one such
    interval) in a step or two instead of log₂ n."""
    n = xp.shape[0]
    if not x < xp[n - 1]:  # also NaN: where the binary search ends for it
        return n - 1 if x >= xp[n - 1] else _locate(x, xp)
    g = (x - xp[0]) * inv_dx
    lo = 0 if not g > 0.0 else (int(g) if g < n - 2 else n - 2)
    while lo > 0 and xp[lo] > x:
        lo -= 1
    while xp[lo + 1] <= x:
        lo += 1
    return lo


@njit(cache=True, nogil=True, inline="always")
def _interp_at(lo, x, xp, fp):
    """``np.interp(x, xp, fp)`` in the interval :func:`_locate` found (NumPy's formula and
    branches: the same bits)."""
    if lo == xp.shape[0] - 1 or xp[lo] == x:
        return fp[lo]
    slope = (fp[lo + 1] - fp[lo]) / (xp[lo + 1] - xp[lo])
    return slope * (x - xp[lo]) + fp[lo]


@njit(cache=True, nogil=True, inline="always")
def _interp_sloped(lo, x, xp, fp, slopes):
    """:func:`_interp_at` with its interval's slope looked up in ``slopes``
    (:func:`_interval_slopes`): the same bits, without a division."""
    if lo == xp.shape[0] - 1 or xp[lo] == x:
        return fp[lo]
    return slopes[lo] * (x - xp[lo]) + fp[lo]


@njit(cache=True, nogil=True)
def _interval_slopes(xp, fp):
    """Each interval's slope of ``fp`` over ``xp``, in :func:`_interp_at`'s arithmetic (as
    ``np.interp`` tabulates them for many points)."""
    n = xp.shape[0]
    out = np.zeros(n)
    for lo in range(n - 1):
        out[lo] = (fp[lo + 1] - fp[lo]) / (xp[lo + 1] - xp[lo])
    return out


@njit(cache=True, nogil=True)
def geometry_pairs(xs, ys, geo, radii, mean, comps, slope_profile, first, second, inv_step, dlog):
    """The pairs' data and regressors of one Gauss-Newton step.

    Parameters
    ----------
    xs, ys : ndarray (w,), (h,)
        Bin centres in half-diagonals from the frame centre.
    geo : ndarray (2,) or (4,)
        Centre (u_x, u_y) and, with four entries, shape (e1, e2).
    radii, mean : ndarray (R,)
        The family's radii and mean log profile.
    comps : ndarray (K, R)
        Its components.
    slope_profile : ndarray (R,)
        d/dρ of the full profile at the current coefficients.
    first, second, inv_step, dlog : ndarray (n,)
        The pairs (:class:`vigproc.core.family_fit.PairIndex`).

    Returns
    -------
    d : ndarray (n,)
        ``dlog`` less the mean field's difference per unit step.
    at : ndarray (K + E, n)
        The regressors as rows (the components', then the geometry's derivatives).
    """
    nb = xs.shape[0] * ys.shape[0]
    nc = comps.shape[0] + geo.shape[0]
    n = first.shape[0]
    d = np.empty(n)
    at = np.empty((nc, n))
    fill_geometry_pairs(xs, ys, geo, radii, mean, comps, slope_profile, first, second, inv_step, dlog,
                        np.empty(nb), np.empty((nc, nb)), d, at)
    return d, at


@njit(cache=True, nogil=True)
def fill_geometry_pairs(xs, ys, geo, radii, mean, comps, slope_profile, first, second, inv_step, dlog, M, J, d, at):
    """:func:`geometry_pairs` written into the caller's arrays: ``M`` (h·w,) and ``J``
    (K + E, h·w) scratch over the bins, ``d`` (n,) and ``at`` (K + E, n) the result (a
    Gauss-Newton loop reuses them at every step)."""
    fill_geometry_bins(xs, ys, geo, radii, mean, comps, slope_profile, M, J)
    difference_pairs(M, J, first, second, inv_step, dlog, d, at)


@njit(cache=True, nogil=True)
def difference_pairs(M, J, first, second, inv_step, dlog, d, at):
    """Fill the pairs' data ``d`` (n,) (``dlog`` less the field ``M``'s difference per unit
    step) and regressors ``at`` (K + E, n) (``J``'s rows differenced) from the bins' values."""
    n = first.shape[0]
    for p in range(n):
        d[p] = dlog[p] - (M[second[p]] - M[first[p]]) * inv_step[p]
    for c in range(J.shape[0]):  # a row at a time: each written in order
        Jc = J[c]
        for p in range(n):
            at[c, p] = (Jc[second[p]] - Jc[first[p]]) * inv_step[p]


@njit(cache=True, nogil=True)
def fill_geometry_bins(xs, ys, geo, radii, mean, comps, slope_profile, M, J):
    """The bins' part of :func:`fill_geometry_pairs`: the mean field ``M`` (h·w,) and the
    derivatives ``J`` (K + E, h·w) by the coefficients and the geometry at each bin."""
    w, h = xs.shape[0], ys.shape[0]
    K, R = comps.shape
    E = geo.shape[0]
    rlast = radii[R - 1]
    step_last = radii[R - 1] - radii[R - 2]
    mean_tail = (mean[R - 1] - mean[R - 2]) / step_last
    comp_tail = np.empty(K)
    for k in range(K):
        comp_tail[k] = (comps[k, R - 1] - comps[k, R - 2]) / step_last
    # the profile's slope past ρ = 1 (its value at 1), looked up once
    slope_1 = _interp_at(_locate(1.0, radii), 1.0, radii, slope_profile)
    # the radii of the lens family are evenly spaced: each bin's interval found from a guess
    # (any strictly increasing radii: the same interval as the binary search)
    even = R >= 2
    for r in range(R - 1):
        even = even and radii[r + 1] > radii[r]
    inv_dr = (R - 1) / (radii[R - 1] - radii[0]) if even else 0.0
    # the profiles' slopes per interval, divided once a call rather than at every bin
    mean_sl = _interval_slopes(radii, mean)
    comp_sl = np.empty((K, R))
    for k in range(K):
        comp_sl[k] = _interval_slopes(radii, comps[k])
    slope_sl = _interval_slopes(radii, slope_profile)
    elliptical = E == 4
    e1 = geo[2] if elliptical else 0.0
    e2 = geo[3] if elliptical else 0.0
    for j in range(h):
        dy = ys[j] - geo[1]
        for i in range(w):
            b = j * w + i
            dx = xs[i] - geo[0]
            if elliptical:
                q = (1 + e1) * dx * dx + 2 * e2 * dx * dy + (1 - e1) * dy * dy
                rho = math.sqrt(max(q, 1e-18))
                gx = (1 + e1) * dx + e2 * dy
                gy = e2 * dx + (1 - e1) * dy
            else:
                rho = max(math.hypot(dx, dy), 1e-9)
                gx = dx
                gy = dy
            past = max(rho - rlast, 0.0)
            # one search for every profile at this bin
            lo = _locate_near(rho, radii, inv_dr) if even else _locate(rho, radii)
            M[b] = _interp_sloped(lo, rho, radii, mean, mean_sl) + past * mean_tail
            for k in range(K):
                J[k, b] = _interp_sloped(lo, rho, radii, comps[k], comp_sl[k]) + past * comp_tail[k]
            # the slope at min(ρ, 1): past the last radius, its last value
            slope = _interp_sloped(lo, rho, radii, slope_profile, slope_sl) if rho < 1.0 else slope_1
            J[K, b] = -slope * gx / rho
            J[K + 1, b] = -slope * gy / rho
            if elliptical:
                J[K + 2, b] = slope * 0.5 * (dx * dx - dy * dy) / rho
                J[K + 3, b] = slope * dx * dy / rho
