"""Lyu 2010, faithfully: Gaussian-approximation start and maximum-likelihood fit.

Both stages work only on the spatial means of the discrete derivative operators
(:mod:`vigproc.core.stats`), which telescope to the image borders: the method sees the
border strips of the (log) image and nothing else.

References
----------
S. Lyu, "Estimating Vignetting Function from a Single Image for Image
Authentication", ACM MM&Sec 2010: Eqs. (6), (13)–(20), Section 3.3–3.5.
"""

from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass

import numpy as np
from scipy.optimize import minimize

from vigproc.core._kernels.field import log_field_grid
from vigproc.core.model import N_ALPHA, FitQuality, VignettingModel, frame_coords
from vigproc.core.prior import NaturalPrior
from vigproc.core.stats import border_sums_from_strips, check_size, derivative_means_from_sums

log = logging.getLogger(__name__)

#: Penalty slope for G approaching zero on the border strips (keeps the model valid).
_G_MARGIN = 1e-3


@dataclass(frozen=True)
class MLSettings:
    """Coordinate-descent settings for the Eq. (6) fit.

    Attributes
    ----------
    rounds : int
        Alternations α-step / (c, P)-step.
    inner_evaluations : int
        Objective evaluations allowed per step.
    tol : float
        Stop when a round improves the objective by less than this (relative).
    """

    rounds: int = 4
    inner_evaluations: int = 400
    tol: float = 1e-4


def model_derivative_means(
    height: int, width: int, center: tuple[float, float], p: tuple[float, float, float],
    alpha: np.ndarray, delta_max: int,
) -> tuple[np.ndarray, float]:
    """Means D̄^t_Δ log φ(v; θ) for an H×W frame, from the field on its border strips.

    Returns
    -------
    means : ndarray, (5, Δmax)
    gmin : float
        Smallest value of G on the strips (≤ 0 means the model is invalid there).
    """
    k = 2 * delta_max
    xs, ys = frame_coords(width), frame_coords(height)
    alpha = np.asarray(alpha, dtype=np.float64)
    strips = []
    gmin = math.inf
    for sx, sy in ((xs[:k], ys), (xs[::-1][:k], ys), (xs, ys[:k]), (xs, ys[::-1][:k])):
        out = np.empty((sy.shape[0], sx.shape[0]))
        gmin = min(gmin, log_field_grid(sx, sy, center[0], center[1], p[0], p[1], p[2], alpha, out))
        strips.append(out)
    bs = border_sums_from_strips(*strips, height, width, delta_max)
    return derivative_means_from_sums(bs, delta_max), gmin


def gaussian_approximation(
    means: np.ndarray, prior: NaturalPrior, height: int, width: int
) -> tuple[tuple[float, float], tuple[float, float, float]]:
    """Centre and shape matrix from derivative means, Lyu 2010 Eqs. (17)–(20).

    Parameters
    ----------
    means : ndarray, (5, Δmax)
        Derivative means of the log image (operators x, y, xx, yy, xy).
    prior : NaturalPrior
        Supplies the weights w = 1/std of the natural-image means.

    Returns
    -------
    center : (cx, cy) in px from the frame centre
    p : (p1, p2, p3) in px⁻², projected to positive semi-definite
    """
    dmax = means.shape[1]
    d2 = np.arange(1, dmax + 1, dtype=np.float64) ** 2
    w = 1.0 / np.maximum(prior.std[:, :dmax], 1e-300)
    # Eqs. (17)-(19): weighted LS of mean D^t ≈ −p Δ²
    p1 = -np.sum(w[2] * means[2] * d2) / np.sum(w[2] * d2 * d2)
    p3 = -np.sum(w[3] * means[3] * d2) / np.sum(w[3] * d2 * d2)
    p2 = -np.sum(w[4] * means[4] * d2) / np.sum(w[4] * d2 * d2)
    pm = np.array([[p1, p2], [p2, p3]])
    # Real images can give an indefinite estimate; keep the closest PSD matrix.
    ev, evec = np.linalg.eigh(pm)
    ev = np.maximum(ev, 0.0)
    pm = (evec * ev) @ evec.T
    # Eq. (20): P c = mean over Δ of (1/Δ) D̄^x_Δ, (1/Δ) D̄^y_Δ
    deltas = np.arange(1, dmax + 1)
    rhs = np.array([np.mean(means[0] / deltas), np.mean(means[1] / deltas)])
    if ev.min() > 1e-12 * max(ev.max(), 1e-300):
        c = np.linalg.solve(pm, rhs)
    else:
        c = np.linalg.lstsq(pm, rhs, rcond=1e-9)[0] if ev.max() > 0 else np.zeros(2)
    # A centre far outside the frame is numerically meaningless; clamp to 2 frame sizes.
    c = np.clip(c, [-2 * width, -2 * height], [2 * width, 2 * height])
    return (float(c[0]), float(c[1])), (float(pm[0, 0]), float(pm[0, 1]), float(pm[1, 1]))


def ml_objective_terms(means: np.ndarray, model_means: np.ndarray, prior: NaturalPrior) -> float:
    """Eq. (6): Σ_{t,Δ} |(D̄ i_v − D̄ log A − D̄ log G) / γ|^β (note the absolute value)."""
    d = means.shape[1]
    z = np.abs((means - model_means) / prior.gamma[:, :d])
    return float(np.sum(z ** prior.beta[:, :d]))


def _chol_to_p(a: float, b: float, d: float) -> tuple[float, float, float]:
    # P = L Lᵀ with L = [[e^a, 0], [b, e^d]]: positive definite for any (a, b, d)
    ea, ed = math.exp(a), math.exp(d)
    return ea * ea, ea * b, b * b + ed * ed


def _p_to_chol(p: tuple[float, float, float], floor: float) -> tuple[float, float, float]:
    p1 = max(p[0], floor)
    l11 = math.sqrt(p1)
    b = p[1] / l11
    l22sq = max(p[2] - b * b, floor)
    return math.log(l11), b, 0.5 * math.log(l22sq)


def ml_fit(
    means: np.ndarray, prior: NaturalPrior, height: int, width: int,
    center: tuple[float, float], p: tuple[float, float, float], alpha: np.ndarray,
    settings: MLSettings = MLSettings(),
) -> tuple[tuple[float, float], tuple[float, float, float], np.ndarray, float, int]:
    """Maximum-likelihood fit of Eq. (6) by coordinate descent (Lyu 2010, Section 3.3).

    Alternates a minimisation over α with (c, P) fixed and one over (c, P) with α
    fixed; P is kept positive definite through a log-Cholesky parameterisation, and
    parameters are optimised in units of the half-diagonal R so all are of order one.

    The paper uses gradient-based steps (MATLAB fmincon). Eq. (6) has cusps wherever a
    term with β < 1 crosses zero (the shipped prior has β down to 0.25), and measured
    here L-BFGS-B stalls at its first line search on them, so each step uses Powell's
    derivative-free method instead; the objective and the alternation are the paper's.

    Returns
    -------
    center, p, alpha, objective, rounds
    """
    dmax = means.shape[1]
    r = 0.5 * math.hypot(width, height)
    floor = 1e-8  # P̃ = P·R² eigenvalue floor: an effective focal length of 10⁴ R

    def objective(c_n, chol, al) -> float:
        pt = _chol_to_p(*chol)
        pp = (pt[0] / r**2, pt[1] / r**2, pt[2] / r**2)
        mm, gmin = model_derivative_means(height, width, (c_n[0] * r, c_n[1] * r), pp, al, dmax)
        val = ml_objective_terms(means, mm, prior)
        if gmin < _G_MARGIN:
            val += 1e6 * (_G_MARGIN - gmin)
        return val if math.isfinite(val) else 1e300

    c_n = np.array(center, dtype=np.float64) / r
    chol = np.array(_p_to_chol((p[0] * r**2, p[1] * r**2, p[2] * r**2), floor))
    al = np.asarray(alpha, dtype=np.float64).copy()
    best = objective(c_n, chol, al)
    opts = {"maxfev": settings.inner_evaluations, "xtol": 1e-5, "ftol": 1e-7}
    rounds = 0
    for rounds in range(1, settings.rounds + 1):
        prev = best
        res = minimize(lambda a_: objective(c_n, chol, a_), al, method="Powell", options=opts)
        if res.fun <= best:
            al, best = res.x, float(res.fun)
        x0 = np.concatenate([c_n, chol])
        res = minimize(lambda x: objective(x[:2], x[2:], al), x0, method="Powell",
                       bounds=[(-4, 4), (-4, 4), (-12, 6), (-50, 50), (-12, 6)], options=opts)
        if res.fun <= best:
            c_n, chol, best = res.x[:2], res.x[2:], float(res.fun)
        if prev - best <= settings.tol * max(abs(prev), 1e-12):
            break
    pt = _chol_to_p(*chol)
    return (
        (float(c_n[0] * r), float(c_n[1] * r)),
        (pt[0] / r**2, pt[1] / r**2, pt[2] / r**2),
        al,
        best,
        rounds,
    )


def estimate_lyu2010(
    log_img: np.ndarray, prior: NaturalPrior, *, ml: bool = True, random_start: bool = False,
    seed: int | None = None, settings: MLSettings = MLSettings(),
) -> VignettingModel:
    """Estimate φ from an H×W log-luminance image with the paper's method.

    Parameters
    ----------
    log_img : ndarray, H×W
        i_v = log I_v of the frame (the working copy).
    prior : NaturalPrior
    ml : bool
        False: Gaussian approximation only (Eqs. 17–20, "GA only" of Table 3).
    random_start : bool
        Start the ML fit from random parameters instead of GA ("ML + rand").
    seed : int, optional
        Seed of the random start.

    Returns
    -------
    VignettingModel
        For the H×W frame of ``log_img``; ``method`` is "ga", "lyu2010" or
        "lyu2010-rand".
    """
    t0 = time.perf_counter()
    h, w = log_img.shape
    dmax = prior.delta_max
    check_size(h, w, dmax)
    k = 2 * dmax
    bs = border_sums_from_strips(
        log_img[:, :k], log_img[:, w - k :][:, ::-1], log_img[:k, :], log_img[h - k :, :][::-1, :], h, w, dmax
    )
    means = derivative_means_from_sums(bs, dmax)
    center, p = gaussian_approximation(means, prior, h, w)
    alpha = np.zeros(N_ALPHA)
    if not ml:
        q = FitQuality(seconds=time.perf_counter() - t0)
        return VignettingModel(w, h, center=center, p=p, alpha=tuple(alpha), method="ga", quality=q)
    method = "lyu2010"
    if random_start:
        rng = np.random.default_rng(seed)
        r = 0.5 * math.hypot(w, h)
        f = r * rng.uniform(0.3, 3.0)
        center = (float(rng.uniform(-w / 4, w / 4)), float(rng.uniform(-h / 4, h / 4)))
        p = (1 / f**2, 0.0, 1 / f**2)
        alpha = rng.normal(0.0, 0.01, N_ALPHA)
        method = "lyu2010-rand"
    center, p, alpha, obj, rounds = ml_fit(means, prior, h, w, center, p, alpha, settings)
    q = FitQuality(objective=obj, iterations=rounds, seconds=time.perf_counter() - t0)
    return VignettingModel(w, h, center=center, p=p, alpha=tuple(alpha), method=method, quality=q)
