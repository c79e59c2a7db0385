"""Numba kernel of the lens family's centre and shape fit: the whole Gauss-Newton loop of
:func:`vigproc.core.family_fit._geometry_fit` in one compiled call.

Each step is :func:`vigproc.core._kernels.geometry.fill_geometry_bins` (the field and its
derivatives by the coefficients and the geometry at each bin, at the current centre, shape
and coefficients) and four IRLS steps whose sums run over the bins
(:func:`vigproc.core._kernels.bin_normal.bin_irls_into`), in the order of the Python loop
it replaces: the same fit up to the rounding of those sums (``tests/test_estimator_kernels.py``).
What it saves is the loop's own cost: the pairs as slots over the bins and the IRLS scratch
made once a fit rather than at every step, and a dozen small NumPy calls a step; and,
summed over bins, no K + E regressors per pair at each step (about 2 MB for a 96-px working
copy), which only the last step's pairs are differenced into (for the jackknife).

Numba caches this kernel with :mod:`~vigproc.core._kernels.geometry`'s and
:mod:`~vigproc.core._kernels.bin_normal`'s compiled into it, and checks only this file's
time stamp; the package's cache guard (:mod:`vigproc.core._kernels`) drops the cache when
any kernel source changes.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from vigproc.core._kernels.bin_normal import bin_irls_into, pair_slots, slot_data
from vigproc.core._kernels.geometry import difference_pairs, fill_geometry_bins


@njit(cache=True, nogil=True)
def geometry_gauss_newton(xs, ys, geo0, radii, mean, comps, grad_mean, grad_comps, first, second, inv_step, dlog,
                          weight, coef0, pm, pinv, scale, inv_s, inner, inner_tolerance, iterations, tolerance,
                          max_ellipticity):
    """Gauss-Newton on the fall-off's centre (and, with a four-entry ``geo0``, its shape),
    the family coefficients by ``inner`` IRLS steps inside each step.

    Parameters
    ----------
    xs, ys : ndarray (w,), (h,)
        Bin centres in half-diagonals from the frame centre.
    geo0 : ndarray (2,) or (4,)
        Where the geometry starts: centre (u_x, u_y) and, with four entries, shape (e1, e2).
    radii, mean : ndarray (R,)
        The family's radii and mean log profile.
    comps : ndarray (K, R)
        Its components.
    grad_mean, grad_comps : ndarray (R,), (K, R)
        d/dρ of the mean and of the components.
    first, second, inv_step, dlog, weight : ndarray (n,)
        The pairs and their weights (:class:`vigproc.core.family_fit.PairIndex`).
    coef0 : ndarray (K,)
        Where the coefficients start.
    pm, pinv : ndarray (K + E,), (K + E, K + E)
        Prior mean (coefficients, then the geometry) and precision.
    scale, inv_s : float
        1 / (σ²κ) and 1 / σ (:func:`vigproc.core._kernels.irls.irls_fit`).
    inner : int
        IRLS steps inside each Gauss-Newton step; ``inner_tolerance`` their stop.
    iterations : int
        Most Gauss-Newton steps (at least 1).
    tolerance : float
        Stop when no geometry parameter moves by this much in a step.
    max_ellipticity : float
        A step is shortened so that |(e1, e2)| stays within it.

    Returns
    -------
    coef : ndarray (K,)
    geo : ndarray (E,)
    d : ndarray (n,), at : ndarray (K + E, n)
        The last step's pairs.
    sol : ndarray (K + E,)
        The last step's solution (coefficients, then the geometry's step).
    pm_it : ndarray (K + E,)
        The last step's prior mean (the geometry's as a step: −geo).
    steps : int
        Steps taken (a step whose solution is not finite is not counted, and ends the loop).
    """
    K = comps.shape[0]
    E = geo0.shape[0]
    nc = K + E
    n = first.shape[0]
    nb = xs.shape[0] * ys.shape[0]
    M = np.empty(nb)
    J = np.empty((nc, nb))
    # the pairs as slots over the bins: each step's sums over bins (bin_normal), not pairs
    # (a pair listed twice, its slot's weight twice: the sums over pairs count it twice)
    offs, invs, dl, wt = pair_slots(first, second, inv_step, dlog, weight, nb)
    ds = np.empty(dl.shape)
    H = np.empty((nc, nc))
    g = np.empty(nc)
    scratch = np.empty((2 * offs.shape[0] + 3, nb))
    x0 = np.zeros(nc)
    pm_it = pm.copy()
    geo = geo0.copy()
    coef = coef0.copy()
    sol = np.full(nc, np.nan)
    steps = 0
    for _ in range(iterations):
        slope = grad_mean + np.dot(coef, grad_comps)
        fill_geometry_bins(xs, ys, geo, radii, mean, comps, slope, M, J)
        slot_data(M, offs, invs, dl, ds)
        for k in range(K):
            x0[k] = coef[k]
        for k in range(K, nc):
            x0[k] = 0.0
        for k in range(nc):
            pm_it[k] = pm[k]
        for k in range(E):
            pm_it[K + k] = -geo[k]  # the prior is on the geometry, not on the step
        sol = bin_irls_into(J, ds, wt, offs, invs, x0, pinv, np.dot(pinv, pm_it), scale, inv_s, inner,
                            inner_tolerance, nc, H, g, scratch)
        if not np.all(np.isfinite(sol)):
            break
        steps += 1
        coef = sol[:K].copy()
        step = sol[K:].copy()
        if E == 4:
            e1 = geo[2] + step[2]
            e2 = geo[3] + step[3]
            size = math.hypot(e1, e2)
            if size > max_ellipticity:  # along the step, to the largest shape allowed
                step[2] = e1 * (max_ellipticity / size) - geo[2]
                step[3] = e2 * (max_ellipticity / size) - geo[3]
        geo = geo + step
        move = 0.0
        for k in range(E):
            move = max(move, abs(sol[K + k]))
        if move < tolerance:
            break
    # the last step's pairs, from its bins (M and J are still the last step's)
    d = np.empty(n)
    at = np.empty((nc, n))
    difference_pairs(M, J, first, second, inv_step, dlog, d, at)
    return coef, geo, d, at, sol, pm_it, steps
