"""vigproc's default estimator: a robust per-pixel fit of the Kang-Weiss model.

Lyu 2010 fits the model to 125 border statistics (the telescoped derivative means);
measured here, that objective is not minimised near the true parameters on textured
images. This estimator instead uses every pixel of a binned working copy:

1. Bin the linear luminance to a working copy (long side ≈ ``work_size``), masking
   dark, clipped and invalid pixels, and take logs (the model is multiplicative).
2. Data: log differences d = L(v+s·e) − L(v) for steps s and e ∈ {x, y}. Natural
   images have sparse, heavy-tailed log-derivatives peaked at zero, so a smooth field
   shows as the mode of d. The Cauchy loss ρ(e) = log(1 + (e/σ_s)²) follows the mode
   and ignores edges and texture (the same insight as Zheng et al.'s radial-gradient
   symmetry, without assuming a centred, circular fall-off).
3. Start: a robust linear fit of the quadratic log-field −½(v−c)ᵀP(v−c) (the
   per-pixel form of Lyu's Gaussian approximation, Eqs. 7–12), by IRLS.
4. Levenberg–Marquardt on the full model (c, P, α1..α7) with Gaussian priors on c and
   α, and penalties that keep G > 0 and the fall-off monotone inside the frame.
5. Uncertainty: the parameter covariance from the Gauss-Newton information (scaled
   to an effective number of independent observations), propagated to the field.
   When the field is not significantly non-flat, return the identity model
   ("do no harm") and keep the fit as ``candidate``.

References
----------
S. Lyu, "Estimating Vignetting Function from a Single Image for Image
Authentication", ACM MM&Sec 2010 (model, Eq. 2; Gaussian approximation, Eqs. 7–16).
Y. Zheng, S. Lin, C. Kambhamettu, J. Yu, S. B. Kang, "Single-Image Vignetting
Correction", IEEE TPAMI 31(12), 2009 (radial gradient symmetry).
P. W. Holland and R. E. Welsch, "Robust regression using iteratively reweighted
least-squares", Comm. Statist. 1977 (IRLS).
"""

from __future__ import annotations

import io
import json
import logging
import math
import time
from dataclasses import dataclass, replace

import numpy as np

from vigproc.core._kernels.robust import (
    CAUCHY,
    HUBER,
    POWER,
    POWER_EXPONENT,
    count_pairs,
    normal_equations,
    pair_residuals,
    robust_loss,
)
from vigproc.core._kernels.field import log_field_grid
from vigproc.core.pixels import binned_coords, binned_log_channels, binned_log_copy
from vigproc.core.model import N_ALPHA, FitQuality, VignettingModel, kw_field_and_jacobian
from vigproc.core.scene import SceneFalloff, default_scene_falloff
from vigproc.errors import InvalidImageError

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class RobustSettings:
    """Tuning of the default estimator (defaults measured on BSDS train, see README).

    Attributes
    ----------
    work_size : int
        Long side of the binned working copy, in bins.
    steps : tuple of int
        Difference steps in working pixels.
    n_eff : float
        Effective number of independent observations the data term is worth
        (pixels of one photo are strongly correlated); sets the weight of the data
        against the priors and the size of the reported uncertainty.
    sigma_center : float
        Prior std of the centre, in half-diagonals (real lenses on uncropped
        frames are centred; off-centre needs evidence).
    sigma_alpha : float
        Prior std of each α_i.
    sigma_ellipticity : float
        Prior std of the ellipticity (e1, e2) of P̃ = s·[[1+e1, e2], [e2, 1−e1]].
    max_iter : int
        Levenberg–Marquardt iterations at most.
    rel_tol : float
        Stop when an iteration lowers the objective by less than this fraction
        (1e-4 measured as accurate as 1e-7 and 2x faster: late iterations mostly
        fit scene detail).
    min_snr : float
        Fall back to the identity model when the fitted field's RMS is below
        ``min_snr`` times its uncertainty (with the scene prior, this keeps the
        median false field on clean photos at 0; see README) ...
    min_ev : float
        ... or below this many EV (RMS over the frame).
    dark_fraction : float
        Bins darker than this fraction of the 99th-percentile luminance are masked.
    sigma_scale : float
        Cauchy scale σ_s as a multiple of the residuals' robust spread (1.4826·MAD):
        small values make the fit follow the mode of the log-differences (flat
        regions) rather than their mean (texture); 0.2 measured best of 1, 0.5,
        0.25, 0.15 on 12 BSDS train images.
    loss : {"cauchy", "huber", "power"}
        Robust loss. Huber (closer to a sign/median criterion) measured worse:
        0.51 EV median false field on clean images against 0.33 EV for Cauchy.
        "power" is the smoothed hyper-Laplacian |e|^0.8 of Zheng et al.'s radial-
        gradient method (scale fitted by maximum likelihood, smoothed below
        ``power_eps``); on 20 BSDS train images it gained on Table 1 setting 1
        (31.4 against 30.4 dB) and lost on settings 2–3 (24.9/24.2 against
        25.8/25.5 dB), and tied on the lensfun protocol, so Cauchy stays.
    power_eps : float
        Smoothing of the "power" loss, in log units.
    scene_prior : bool
        Divide the fall-off natural photos carry on average (:mod:`vigproc.core.scene`)
        out of the image before fitting, so that the fit is of the lens alone.
    scene : SceneFalloff, optional
        The scene prior to use; None means the shipped one.
    centred_sigma_center, centred_sigma_ellipticity : float
        Prior stds of the centre (half-diagonals) and of the ellipticity in the
        second, *centred circular* fit.
    centred_z : float
        Model selection: unless the free fit departs from a centred circular
        fall-off by at least this many standard deviations (:func:`shape_z`, its
        own covariance), the centred circular fit is returned.  Real lenses on
        uncropped frames vignette centred and circular (what makes Zheng et al.'s
        radial-gradient method strong on them), and an off-centre or elliptical fit
        without strong evidence mostly follows the scene.  Measured on 30 BSDS train
        images (lensfun protocol, no fall-back, no scene prior): free fit 0.091 EV
        gain-free; centre-only selection (the previous default) 0.089; centred
        circular selection 0.069; centred circular always 0.062 — but that cannot
        follow Lyu's off-centre Table 1 settings, where selection keeps the free
        fit (settings 2–3, 20 images: 25.0/24.3 dB against 21.4/21.2 before).
        ``inf`` always returns the free fit.
    selection : {"shape", "centre"}
        What the selection tests: centre and ellipticity (default), or the centre
        alone (the refit then keeps the ellipticity free).
    max_shape_ratio : float
        Fall back also when the fit's :func:`shape_ratio` exceeds this: a fall-off
        that starts nearer the centre than real lenses' does is more likely the
        photo's own shading.  ``inf`` (the default) turns it off; ``method="real-lens"``
        sets :data:`REAL_LENS_SHAPE_RATIO`.
    """

    work_size: int = 96
    steps: tuple[int, ...] = (1, 2, 4)
    n_eff: float = 400.0
    sigma_center: float = 0.15
    sigma_alpha: float = 0.3
    sigma_ellipticity: float = 0.3
    max_iter: int = 30
    rel_tol: float = 1e-4
    min_snr: float = 1.5
    min_ev: float = 0.02
    dark_fraction: float = 0.01
    sigma_scale: float = 0.2
    loss: str = "cauchy"
    scene_prior: bool = True
    scene: SceneFalloff | None = None
    centred_sigma_center: float = 0.01
    centred_z: float = 4.0
    power_eps: float = 1e-3
    centred_sigma_ellipticity: float = 0.02
    selection: str = "shape"
    max_shape_ratio: float = math.inf

    def __post_init__(self) -> None:
        # a misspelt choice must not silently fall back to another loss or test
        if self.loss not in ("cauchy", "huber", "power"):
            raise ValueError(f"loss must be 'cauchy', 'huber' or 'power', not {self.loss!r}")
        if self.selection not in ("shape", "centre"):
            raise ValueError(f"selection must be 'shape' or 'centre', not {self.selection!r}")


@dataclass(frozen=True)
class RobustWorkingCopy:
    """Binned log luminance with validity mask and coordinates in half-diagonals.

    ``channels`` and ``channels_valid`` (C×h×w), when present, are the same copy of each
    colour channel: a lens profile fits each of them (:func:`vigproc.core.pooling.frame_fit`).
    """

    L: np.ndarray
    valid: np.ndarray
    xs: np.ndarray
    ys: np.ndarray
    radius: float
    width: int
    height: int
    channels: np.ndarray | None = None
    channels_valid: np.ndarray | None = None


def working_copy(lum: np.ndarray, settings: RobustSettings, mask: np.ndarray | None = None,
                 colour: np.ndarray | None = None) -> RobustWorkingCopy:
    """Bin an H×W linear luminance image for the estimator.

    Parameters
    ----------
    lum : ndarray, H×W, linear
    mask : ndarray of bool, optional
        Pixels to use (e.g. not clipped); all positive finite pixels by default.
    colour : ndarray, H×W×C, linear, optional
        The frame's colour channels, binned the same way into ``channels``.
    """
    h, w = lum.shape
    L, valid, k = binned_log_copy(lum, settings.work_size, settings.dark_fraction, mask)
    radius = 0.5 * math.hypot(w, h)
    channels = channels_valid = None
    if colour is not None:
        channels, channels_valid = binned_log_channels(colour, k, valid, settings.dark_fraction)
    return RobustWorkingCopy(
        L=L, valid=valid, xs=binned_coords(w, k) / radius, ys=binned_coords(h, k) / radius,
        radius=radius, width=w, height=h, channels=channels, channels_valid=channels_valid,
    )


def reduced_working_copy(lum: np.ndarray, d: int, width: int, height: int, settings: RobustSettings,
                         mask: np.ndarray | None = None, colour: np.ndarray | None = None) -> RobustWorkingCopy:
    """:func:`working_copy` of a width×height frame from a copy of it binned d×d.

    ``lum`` (and ``colour``) is the full frame's linear light averaged over d×d blocks,
    the remainder rows and columns dropped (:func:`vigproc.core.pixels.reduce_codes`);
    ``mask`` its blocks without a pixel the full frame's working copy would leave out.
    When the full frame's bin size k is a multiple of d (as
    :func:`vigproc.core.estimate.reduction_factor` chooses d), every bin covers the very
    pixels the full frame's own bin covers, so its value is the same mean (to float
    rounding), and the copy states the full frame's geometry: bin centres, radius,
    width and height. A pooling fit reads that geometry
    (:func:`vigproc.core.pooling.frame_fit`: ρ from the frame's half-diagonal in px); the
    reduced frame's own is off by up to (d − 1)/2 px and a pixel's share of the diagonal.

    Parameters
    ----------
    lum : ndarray, (H//d)×(W//d), linear
    d : int
        The reduction's block size.
    width, height : int
        The full frame's size W, H.
    settings : RobustSettings
    mask : ndarray of bool, (H//d)×(W//d), optional
    colour : ndarray, (H//d)×(W//d)×C, linear, optional

    Returns
    -------
    RobustWorkingCopy
        As :func:`working_copy` of the full frame would give it.

    Raises
    ------
    ValueError
        ``lum`` is not the full frame reduced by d, or d does not divide the full
        frame's bin size.
    """
    d, width, height = int(d), int(width), int(height)
    if d < 1 or lum.shape != (height // d, width // d):
        raise ValueError(f"a {lum.shape[1]}x{lum.shape[0]} copy is not a {width}x{height} frame binned by {d}")
    k = max(1, int(round(max(width, height) / settings.work_size)))
    wc = working_copy(lum, settings, mask, colour)
    kr = max(1, int(round(max(lum.shape) / settings.work_size)))
    if kr * d != k or wc.L.shape != (height // k, width // k):
        raise ValueError(f"a copy binned by {d} does not bin as the {width}x{height} frame does "
                         f"({kr} x {d} against {k})")
    radius = 0.5 * math.hypot(width, height)
    return replace(wc, xs=binned_coords(width, k) / radius, ys=binned_coords(height, k) / radius, radius=radius,
                   width=width, height=height)


def _robust_scales(wc: RobustWorkingCopy, F: np.ndarray, steps: np.ndarray, scale: float = 1.0) -> np.ndarray:
    sig = np.empty(steps.shape[0])
    for i, s in enumerate(steps):
        r = pair_residuals(wc.L, wc.valid, F, int(s))
        mad = np.median(np.abs(r - np.median(r))) if r.size else 0.0
        # floor: a perfectly flat synthetic image has MAD 0
        sig[i] = max(scale * 1.4826 * mad, 1e-3)
    return sig


def _power_scale(wc: RobustWorkingCopy, F: np.ndarray, steps: np.ndarray) -> float:
    """Maximum-likelihood scale λ of a hyper-Laplacian law of the residuals:
    λ^p = p·mean|e|^p (generalised Gaussian with exponent p)."""
    r = np.concatenate([pair_residuals(wc.L, wc.valid, F, int(st)) for st in steps])
    if r.size == 0:
        return 1.0
    return max(float(POWER_EXPONENT * np.mean(np.abs(r) ** POWER_EXPONENT)) ** (1.0 / POWER_EXPONENT), 1e-6)


def quadratic_start(wc: RobustWorkingCopy, steps: np.ndarray, iters: int = 6) -> np.ndarray:
    """Robust (IRLS) fit of F = −½ vᵀPv + bᵀv: returns θ₀ (12 params).

    The log-field is linear in (p1, p2, p3, b1, b2), so each IRLS step is an exact
    weighted least-squares solve; c = P⁻¹ b. This is Lyu's Gaussian approximation
    (Eqs. 7–12) fitted to all pixels rather than to border means.
    """
    X, Y = np.meshgrid(wc.xs, wc.ys)
    B = np.stack([-0.5 * X * X, -X * Y, -0.5 * Y * Y, X, Y], axis=-1)
    beta = np.zeros(5)
    F = np.zeros_like(wc.L)
    sigma = _robust_scales(wc, F, steps)
    for it in range(iters):
        H, g, _, n = normal_equations(wc.L, wc.valid, F, B, steps, sigma, CAUCHY, False)
        if n == 0:
            break
        beta = beta + np.linalg.solve(H + 1e-9 * np.trace(H) * np.eye(5), g)
        F = B @ beta
        if it == 1:
            sigma = _robust_scales(wc, F, steps)
    pm = np.array([[beta[0], beta[1]], [beta[1], beta[2]]])
    ev, evec = np.linalg.eigh(pm)
    ev = np.clip(ev, 1e-3, None)  # a mild positive definite start
    pm = (evec * ev) @ evec.T
    c = np.linalg.solve(pm, beta[3:5])
    c = np.clip(c, -1.0, 1.0)
    theta = np.zeros(12)
    theta[:2] = c
    theta[2:5] = pm[0, 0], pm[0, 1], pm[1, 1]
    return theta


def _radii(theta: np.ndarray, wc: RobustWorkingCopy, n: int = 24, edges: bool = False) -> np.ndarray:
    """Radii r sampled from 0 to the largest r inside the frame (reached at a corner):
    at its corner pixel centres, or with ``edges`` at its outer edges (±W/2, ±H/2)."""
    off = 0.0 if edges else 1.0
    hx = (wc.width - off) / 2 / wc.radius
    hy = (wc.height - off) / 2 / wc.radius
    cx, cy, p1, p2, p3 = theta[:5]
    qmax = 0.0
    for x in (-hx, hx):
        for y in (-hy, hy):
            dx, dy = x - cx, y - cy
            qmax = max(qmax, p1 * dx * dx + 2 * p2 * dx * dy + p3 * dy * dy)
    return np.linspace(0.0, math.sqrt(max(qmax, 0.0)), n)


#: :func:`shape_ratio` above which ``method="real-lens"`` does not apply a fit.  Of the
#: 23 495 "pa" calibrations in lensfun's database 96 % lie below it (median 0.23, 95th
#: percentile 0.375); the default estimator's fits to vignetting-free BSDS train photos
#: have a median of 0.30.  Measured on the 200 BSDS train photos: it nearly
#: halves the correction applied to clean photos (mean 0.169 → 0.106 EV) at no cost on
#: the lensfun protocol (0.302 → 0.303 EV), but Lyu's Table 1 fields are as broad
#: (0.37–0.45), so it is not the default.
REAL_LENS_SHAPE_RATIO = 0.4


def shape_ratio(theta: np.ndarray, wc: RobustWorkingCopy) -> float:
    """log φ at half the largest radius inside the frame over log φ at that radius.

    Real lenses keep the centre of the frame nearly flat and fall off towards the
    corners (lensfun: median 0.23); a scene's own shading, or Lyu's synthetic fields,
    fall off more broadly.  0 for a field that does not fall off.

    Parameters
    ----------
    theta : ndarray (12,), normalised parameters
    wc : RobustWorkingCopy
        For the frame's extent.
    """
    r = _radii(theta, wc, 2)[-1]
    k = np.arange(1, N_ALPHA + 1)

    def log_phi(rr: float) -> float:
        g = 1.0 - float(np.sum(theta[5:] * rr**k))
        return -2.0 * math.log1p(0.25 * rr * rr) + math.log(max(g, 1e-12))

    edge = log_phi(r)
    return log_phi(0.5 * r) / edge if edge < -1e-3 else 0.0


#: Fewest usable bins a fit is made from (fewer: no fit, or no correction).
MIN_VALID_BINS = 64

#: Hard floor of G on [0, r_max] (the frame's corners): a fit may not black out a corner.
G_MIN = 0.02


def _min_g(theta: np.ndarray, wc: RobustWorkingCopy) -> float:
    # up to the frame's edges: a model is also evaluated at other resolutions (pictures,
    # a RAW's full size), whose corner pixel centres lie further out (a 64-px fit was
    # valid at its own corners and fell below G = 0 on a 256-px grid)
    r = _radii(theta, wc, 64, edges=True)
    k = np.arange(1, N_ALPHA + 1)
    return float(np.min(1.0 - (r[:, None] ** k) @ theta[5:]))


def _constraint_system(theta: np.ndarray, wc: RobustWorkingCopy, weight: float) -> tuple[np.ndarray, np.ndarray, float]:
    """Quadratic penalties keeping G ≥ 0.05 and d log φ / dr ≤ 0 on [0, r_max].

    Returns their Gauss-Newton (H, g) in α and the penalty value.
    """
    alpha = theta[5:]
    r = _radii(theta, wc)
    k = np.arange(1, N_ALPHA + 1)
    rk = r[:, None] ** k  # (n, 7)
    G = 1.0 - rk @ alpha
    dG = -(k * r[:, None] ** (k - 1)) @ alpha
    Gs = np.maximum(G, 1e-6)
    slope = -r / (1.0 + 0.25 * r * r) + dG / Gs  # d log φ / dr
    H = np.zeros((12, 12))
    g = np.zeros(12)
    pen = 0.0
    # G floor: residual (0.05 − G) where positive; ∂G/∂α_i = −r^i
    act = G < 0.05
    if act.any():
        res = 0.05 - G[act]
        jac = rk[act]  # ∂res/∂α = r^i
        H[5:, 5:] += weight * jac.T @ jac
        g[5:] -= weight * jac.T @ res
        pen += weight * float(res @ res)
    # monotone: residual = slope where positive
    act = slope > 0
    if act.any():
        res = slope[act]
        ra = r[act][:, None]
        # ∂(G'/G)/∂α_i = (−i r^{i−1} G + G' r^i) / G²
        jac = (-(k * ra ** (k - 1)) * Gs[act][:, None] + dG[act][:, None] * ra**k) / Gs[act][:, None] ** 2
        H[5:, 5:] += weight * jac.T @ jac
        g[5:] -= weight * jac.T @ res
        pen += weight * float(res @ res)
    return H, g, pen


def kw_field(xs: np.ndarray, ys: np.ndarray, theta: np.ndarray, out: np.ndarray) -> float:
    """log φ for the 12-vector θ on the grid (xs, ys) into ``out``; returns the smallest G."""
    return log_field_grid(xs, ys, theta[0], theta[1], theta[2], theta[3], theta[4], theta[5:], out)


def _p_from_shape(sh: np.ndarray) -> np.ndarray:
    """(s, e1, e2) → (p1, p2, p3): P̃ = s·[[1+e1, e2], [e2, 1−e1]] (PD iff s>0, e1²+e2²<1)."""
    s_, e1, e2 = sh
    return np.array([s_ * (1 + e1), s_ * e2, s_ * (1 - e1)])


def _shape_from_p(p: np.ndarray) -> np.ndarray:
    s_ = 0.5 * (p[0] + p[2])
    if s_ <= 0:
        return np.zeros(3)
    return np.array([s_, (p[0] - p[2]) / (2 * s_), p[1] / s_])


def _to_internal(theta: np.ndarray) -> np.ndarray:
    return np.concatenate([theta[:2], _shape_from_p(theta[2:5]), theta[5:]])


def _to_model(phi: np.ndarray) -> np.ndarray:
    return np.concatenate([phi[:2], _p_from_shape(phi[2:5]), phi[5:]])


def _chain(phi: np.ndarray) -> np.ndarray:
    """∂θ/∂φ (12×12): model parameters w.r.t. the internal ones."""
    s_, e1, e2 = phi[2:5]
    T = np.eye(12)
    T[2:5, 2:5] = [[1 + e1, s_, 0.0], [e2, 0.0, s_], [1 - e1, -s_, 0.0]]
    return T


def _prior_system(phi: np.ndarray, s: RobustSettings) -> tuple[np.ndarray, np.ndarray, float]:
    """Gaussian priors on the internal parameters: centre, ellipticity (e1, e2), α."""
    lam = np.zeros(12)
    lam[:2] = 1.0 / s.sigma_center**2
    lam[3:5] = 1.0 / s.sigma_ellipticity**2
    lam[5:] = 1.0 / s.sigma_alpha**2
    return np.diag(lam), -lam * phi, float(np.sum(lam * phi * phi))


def _kind(s: RobustSettings) -> int:
    return {"cauchy": CAUCHY, "huber": HUBER, "power": POWER}[s.loss]


def _total(wc, F, steps, sigma, scale, phi, s, penalty_w):
    loss, _ = robust_loss(wc.L, wc.valid, F, steps, sigma, _kind(s))
    _, _, pp = _prior_system(phi, s)
    _, _, pc = _constraint_system(_to_model(phi), wc, penalty_w)
    return scale * loss + pp + pc


def fit_robust(wc: RobustWorkingCopy, s: RobustSettings,
               start: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, dict]:
    """Levenberg–Marquardt fit in normalised units. Returns θ, its covariance, info.

    Internally P̃ is s·[[1+e1, e2], [e2, 1−e1]] so that the prior can favour the
    near-circular fall-off of real lenses while s (the strength) stays free.
    ``start``: initial θ (normalised); default the robust quadratic start.
    """
    steps = np.asarray(s.steps, dtype=np.int64)
    theta = quadratic_start(wc, steps) if start is None else np.array(start, dtype=float)
    phi = _to_internal(theta)
    phi[3:5] = np.clip(phi[3:5], -0.9, 0.9)
    h, w = wc.L.shape
    F = np.empty((h, w))
    J = np.empty((h, w, 12))
    kw_field_and_jacobian(wc.xs, wc.ys, _to_model(phi), F, J)
    sigma = _robust_scales(wc, F, steps, s.sigma_scale)
    npairs = count_pairs(wc.valid, steps)
    scale = s.n_eff / max(npairs, 1)  # data worth n_eff independent observations
    if s.loss == "power":
        # hyper-Laplacian likelihood exp(−|e/λ|^p), smoothed below ε: ρ = (ε/λ)^p·(1+(e/ε)²)^(p/2)
        lam = _power_scale(wc, F, steps)
        scale *= (s.power_eps / lam) ** POWER_EXPONENT
        sigma = np.full(steps.shape[0], s.power_eps)
    penalty_w = 1e4
    current = _total(wc, F, steps, sigma, scale, phi, s, penalty_w)
    lam = 1e-3
    it = 0
    Ft = np.empty((h, w))
    for it in range(1, s.max_iter + 1):
        theta = _to_model(phi)
        kw_field_and_jacobian(wc.xs, wc.ys, theta, F, J)
        Hd, gd, _, _ = normal_equations(wc.L, wc.valid, F, J, steps, sigma, _kind(s), False)
        Hc, gc, _ = _constraint_system(theta, wc, penalty_w)
        T = _chain(phi)
        Hp, gp, _ = _prior_system(phi, s)
        H = T.T @ (scale * Hd + Hc) @ T + Hp
        g = T.T @ (scale * gd + gc) + gp
        improved = False
        rel = 0.0
        for _ in range(8):
            A = H + lam * np.diag(np.diag(H) + 1e-12)
            try:
                delta = np.linalg.solve(A, g)
            except np.linalg.LinAlgError:
                lam *= 10
                continue
            trial = phi + delta
            if trial[2] < 0 or trial[3] ** 2 + trial[4] ** 2 >= 0.98:
                lam *= 10
                continue
            if kw_field(wc.xs, wc.ys, _to_model(trial), Ft) <= 0.0 or _min_g(_to_model(trial), wc) < G_MIN:
                lam *= 10
                continue
            val = _total(wc, Ft, steps, sigma, scale, trial, s, penalty_w)
            if val < current:
                rel = (current - val) / max(abs(current), 1e-12)
                phi, current = trial, val
                lam = max(lam / 3, 1e-7)
                improved = True
                break
            lam *= 4
        if not improved or rel < s.rel_tol:
            break
    # Covariance of θ from the data + prior information at the optimum (internal
    # parameters, mapped back through the chain rule).
    theta = _to_model(phi)
    kw_field_and_jacobian(wc.xs, wc.ys, theta, F, J)
    Hd, _, _, _ = normal_equations(wc.L, wc.valid, F, J, steps, sigma, _kind(s), False)
    T = _chain(phi)
    Hp, _, _ = _prior_system(phi, s)
    info = T.T @ (scale * Hd) @ T + Hp
    try:
        cov_phi = np.linalg.inv(info)
    except np.linalg.LinAlgError:
        cov_phi = np.linalg.pinv(info)
    return theta, T @ cov_phi @ T.T, {"objective": current, "iterations": it, "sigma": sigma}


def _to_pixels(theta: np.ndarray, cov: np.ndarray, radius: float) -> tuple[np.ndarray, np.ndarray]:
    t = np.concatenate([[radius, radius], [radius**-2] * 3, [1.0] * N_ALPHA])
    return theta * t, cov * np.outer(t, t)


def field_uncertainty_ev(model_theta: np.ndarray, cov: np.ndarray, wc: RobustWorkingCopy, n: int = 16) -> tuple[float, float]:
    """RMS over the frame of log2 φ and of its 1-σ uncertainty (normalised θ, cov)."""
    hx = (wc.width - 1) / 2 / wc.radius
    hy = (wc.height - 1) / 2 / wc.radius
    xs = np.linspace(-hx, hx, n)
    ys = np.linspace(-hy, hy, n)
    F = np.empty((n, n))
    J = np.empty((n, n, 12))
    kw_field_and_jacobian(xs, ys, model_theta, F, J)
    Jf = J.reshape(-1, 12)
    var = np.einsum("ij,jk,ik->i", Jf, cov, Jf)
    ln2 = math.log(2.0)
    return float(np.sqrt(np.mean(F * F)) / ln2), float(np.sqrt(np.mean(np.maximum(var, 0))) / ln2)


def _mahalanobis(theta: np.ndarray, cov: np.ndarray, M: np.ndarray) -> float:
    """Norm of the linear functions M·θ in standard deviations of the fit's own
    covariance (inf when that covariance is singular)."""
    d = M @ np.asarray(theta, dtype=float)
    C = M @ np.asarray(cov) @ M.T
    try:
        return float(np.sqrt(max(d @ np.linalg.solve(C, d), 0.0)))
    except np.linalg.LinAlgError:
        return math.inf


#: Selectors for the model-selection tests: the centre (cx, cy) ...
_CENTRE = np.eye(2, 12)
#: ... and the centre with the ellipticity terms (p1 − p3, p2), all 0 for a centred circle.
_SHAPE = np.vstack([_CENTRE, np.eye(1, 12, 2) - np.eye(1, 12, 4), np.eye(1, 12, 3)])


def centre_z(theta: np.ndarray, cov: np.ndarray) -> float:
    """Distance of the fitted centre from the frame centre in standard deviations
    (Mahalanobis, with the fit's own 2×2 centre covariance)."""
    return _mahalanobis(theta, cov, _CENTRE)


def shape_z(theta: np.ndarray, cov: np.ndarray) -> float:
    """How far the fit is from a centred, circular fall-off, in standard deviations:
    the Mahalanobis norm of (cx, cy, p1 − p3, p2), which is 0 exactly for c = 0, P ∝ I,
    with the fit's own covariance (4 degrees of freedom)."""
    return _mahalanobis(theta, cov, _SHAPE)


def _select(wc: RobustWorkingCopy, s: RobustSettings) -> tuple[np.ndarray, np.ndarray, dict]:
    """Free fit, then model selection: unless the free fit departs from a centred
    (``selection="centre"``) or centred circular (``"shape"``) fall-off by at least
    ``centred_z`` standard deviations, refit with the centre (and ellipticity) held
    near the frame centre (a circle) by tight priors, from the neutral start
    (measured better than warm-starting at the free fit)."""
    # both fits start from the same robust quadratic start: made once
    start = quadratic_start(wc, np.asarray(s.steps, dtype=np.int64))
    theta, cov, info = fit_robust(wc, s, start)
    if not math.isfinite(s.centred_z):
        return theta, cov, info
    if s.selection == "shape":
        z = shape_z(theta, cov)
        held = replace(s, sigma_center=s.centred_sigma_center, sigma_ellipticity=s.centred_sigma_ellipticity)
    else:
        z = centre_z(theta, cov)
        held = replace(s, sigma_center=s.centred_sigma_center)
    return fit_robust(wc, held, start) if z < s.centred_z else (theta, cov, info)


def _scene_divided(lum: np.ndarray, settings: RobustSettings, mask: np.ndarray | None = None) -> RobustWorkingCopy:
    """The working copy of one frame, with the scene prior divided out if enabled."""
    return divide_scene(working_copy(lum, settings, mask), settings)


def divide_scene(wc: RobustWorkingCopy, settings: RobustSettings) -> RobustWorkingCopy:
    """``wc`` with the scene prior divided out if ``settings`` enable it."""
    if settings.scene_prior:
        scene = settings.scene if settings.scene is not None else default_scene_falloff()
        if any(scene.theta):  # fit φ_lens = φ / φ_scene: divide the scene prior out
            wc = replace(wc, L=wc.L - scene.log_field(wc.xs, wc.ys))
    return wc


def fit_joint(wcs: list[RobustWorkingCopy], settings: RobustSettings) -> tuple[np.ndarray, np.ndarray, dict]:
    """One fit to several frames' working copies (same bin grid), in normalised units.

    The copies are stacked, separated by invalid rows so that no log-difference pairs
    bins of two frames, and fitted as one image whose data are worth ``n_eff`` per
    frame; the centred/free model selection is the same as for one frame.

    Raises
    ------
    InvalidImageError
        No frames, frames of different bin grids, or too few usable bins.
    """
    if not wcs:
        raise InvalidImageError("a joint fit needs at least one frame")
    if any(wc.L.shape != wcs[0].L.shape for wc in wcs):
        raise InvalidImageError("a joint fit needs frames of one size")
    gap = max(settings.steps)
    rows_L, rows_v, rows_y = [], [], []
    for i, wc in enumerate(wcs):
        if i:  # invalid separator rows: no step crosses from one frame into the next
            rows_L.append(np.zeros((gap, wc.L.shape[1])))
            rows_v.append(np.zeros((gap, wc.L.shape[1]), dtype=bool))
            rows_y.append(np.zeros(gap))
        rows_L.append(wc.L)
        rows_v.append(wc.valid)
        rows_y.append(wc.ys)
    joint = replace(wcs[0], L=np.vstack(rows_L), valid=np.vstack(rows_v), ys=np.concatenate(rows_y),
                    channels=None, channels_valid=None)  # the joint fit reads the luminance
    if joint.valid.sum() < MIN_VALID_BINS:
        raise InvalidImageError("too few usable pixels for a joint fit")
    return _select(joint, replace(settings, n_eff=settings.n_eff * len(wcs)))


def estimate_robust_joint(lums: list[np.ndarray], settings: RobustSettings = RobustSettings()) -> VignettingModel:
    """One model fitted jointly to several H×W linear luminance frames of one lens
    (:func:`fit_joint`).  No fall-back: the fit is returned with its covariance.

    This is the "joint multi-frame fit" of the profile protocol (``vigproc bench
    profile``), measured against pooling per-frame estimates (the profile store's
    rule once; it now pools centred fits, :mod:`vigproc.core.pooling`).

    Raises
    ------
    InvalidImageError
        No frames, frames of different sizes, or too few usable pixels.
    """
    if lums and any(lum.shape != lums[0].shape for lum in lums):
        raise InvalidImageError("a joint fit needs frames of one size")
    return joint_model([_scene_divided(lum, settings) for lum in lums], settings)


def joint_model(wcs: list[RobustWorkingCopy], settings: RobustSettings = RobustSettings()) -> VignettingModel:
    """:func:`fit_joint` as a :class:`VignettingModel` of the first copy's frame size."""
    t0 = time.perf_counter()
    theta, cov, info = fit_joint(wcs, settings)
    ev_rms, ev_sigma = field_uncertainty_ev(theta, cov, wcs[0])
    th_px, cov_px = _to_pixels(theta, cov, wcs[0].radius)
    q = FitQuality(confidence=1.0, field_ev_rms=ev_rms, field_sigma_ev=ev_sigma,
                   snr=ev_rms / ev_sigma if ev_sigma > 0 else math.inf, objective=float(info["objective"]),
                   iterations=int(info["iterations"]), seconds=time.perf_counter() - t0)
    covt = tuple(tuple(float(v) for v in row) for row in cov_px)
    return VignettingModel.from_vector(th_px, wcs[0].width, wcs[0].height, method="robust-joint",
                                       covariance=covt, quality=q)


#: Format tag of :func:`luminance_evidence` blobs: the working copy before the scene
#: division, with the colour channels' copies when the frame has them.  Format 1
#: stored it after the division by the scene prior shipped with the writing version;
#: format 2 held the luminance copy only.
EVIDENCE_FORMAT = "vigproc.robust-evidence/3"
_EVIDENCE_V1 = "vigproc.robust-evidence/1"
_EVIDENCE_V2 = "vigproc.robust-evidence/2"


def luminance_evidence(lum: np.ndarray, settings: RobustSettings = RobustSettings(),
                   mask: np.ndarray | None = None, colour: np.ndarray | None = None) -> bytes:
    """What a frame contributes to its lens's profile: its binned log working copy,
    before any scene prior, and the same copy of each colour channel when ``colour``
    (H×W×C, linear) is given (≈ 80 KB at 96×64 bins with three channels), as bytes
    for the profile store (:mod:`vigproc.core.pooling`)."""
    return _evidence_bytes(working_copy(lum, settings, mask, colour))


def reduced_luminance_evidence(lum: np.ndarray, d: int, width: int, height: int,
                           settings: RobustSettings = RobustSettings(), mask: np.ndarray | None = None,
                           colour: np.ndarray | None = None) -> bytes:
    """:func:`luminance_evidence` of a width×height frame from a copy of it binned d×d
    (:func:`reduced_working_copy`): the same blob, the full frame's geometry."""
    return _evidence_bytes(reduced_working_copy(lum, d, width, height, settings, mask, colour))


def _evidence_bytes(wc: RobustWorkingCopy) -> bytes:
    buf = io.BytesIO()
    meta = json.dumps({"format": EVIDENCE_FORMAT, "radius": wc.radius, "width": wc.width, "height": wc.height})
    extra = {} if wc.channels is None else {"C": wc.channels.astype(np.float32), "Cvalid": wc.channels_valid}
    np.savez_compressed(buf, L=wc.L.astype(np.float32), valid=wc.valid, xs=wc.xs, ys=wc.ys,
                        meta=np.frombuffer(meta.encode(), dtype=np.uint8), **extra)
    return buf.getvalue()


def evidence_copy(blob: bytes) -> RobustWorkingCopy:
    """The working copy of a :func:`luminance_evidence` blob, before the scene division.

    A format-1 blob held the copy divided by the scene prior of its day; the shipped
    scene prior is multiplied back in (exact unless the shipped prior has changed
    since the blob was written).

    Raises
    ------
    ValueError
        Not such a blob, or inconsistent arrays.
    """
    try:
        with np.load(io.BytesIO(blob), allow_pickle=False) as z:
            meta = json.loads(bytes(z["meta"]).decode())
            L = z["L"].astype(np.float64)
            valid, xs, ys = z["valid"].astype(bool), z["xs"].astype(np.float64), z["ys"].astype(np.float64)
            C = z["C"].astype(np.float64) if "C" in z.files else None
            Cvalid = z["Cvalid"].astype(bool) if "Cvalid" in z.files else None
    except Exception as exc:  # noqa: BLE001 - any decoding failure means "not evidence"
        raise ValueError(f"not frame evidence: {exc}") from None
    if meta.get("format") not in (EVIDENCE_FORMAT, _EVIDENCE_V2, _EVIDENCE_V1) or L.shape != valid.shape \
            or L.shape != (ys.size, xs.size) or not np.all(np.isfinite(L[valid])):
        raise ValueError("not frame evidence: inconsistent arrays")
    if (C is None) != (Cvalid is None) or (C is not None and (
            C.ndim != 3 or C.shape[0] != 3 or C.shape[1:] != L.shape or Cvalid.shape != C.shape
            or not np.all(np.isfinite(C[Cvalid])))):
        raise ValueError("not frame evidence: inconsistent colour channels")
    if meta["format"] == _EVIDENCE_V1:
        L = L + default_scene_falloff().log_field(xs, ys)
    return RobustWorkingCopy(L=L, valid=valid, xs=xs, ys=ys, radius=float(meta["radius"]), width=int(meta["width"]),
                       height=int(meta["height"]), channels=C, channels_valid=Cvalid)


def estimate_robust(lum: np.ndarray, settings: RobustSettings = RobustSettings(),
                    mask: np.ndarray | None = None) -> VignettingModel:
    """Estimate φ from an H×W linear luminance image with the default estimator.

    Parameters
    ----------
    lum : ndarray, H×W, linear intensities
    settings : RobustSettings
    mask : ndarray of bool, H×W, optional
        Pixels that may be used (e.g. excluding clipped highlights).

    Returns
    -------
    VignettingModel
        For the H×W frame. If the evidence is weak (SNR below ``min_snr`` or
        field below ``min_ev``), the identity model with ``quality.fallback`` set
        and the rejected fit as ``candidate``.
    """
    t0 = time.perf_counter()
    return _fit_copy(_scene_divided(lum, settings, mask), settings, t0)


def estimate_robust_with_evidence(lum: np.ndarray, settings: RobustSettings = RobustSettings(),
                                  mask: np.ndarray | None = None,
                                  colour: np.ndarray | None = None) -> tuple[VignettingModel, bytes]:
    """:func:`estimate_robust` and the frame's :func:`luminance_evidence` (with ``colour``'s
    channels), from one working copy (learn mode needs both; binning a large frame
    twice would cost as much as the fit)."""
    return fit_with_evidence(working_copy(lum, settings, mask, colour), settings)


def fit_with_evidence(raw: RobustWorkingCopy, settings: RobustSettings = RobustSettings()) -> tuple[VignettingModel, bytes]:
    """:func:`estimate_robust_with_evidence` of a working copy made already (the full
    frame's, or :func:`reduced_working_copy`'s): the model of the frame whose geometry it
    states, and its evidence."""
    t0 = time.perf_counter()
    return _fit_copy(divide_scene(raw, settings), settings, t0), _evidence_bytes(raw)


def _fit_copy(wc: RobustWorkingCopy, settings: RobustSettings, t0: float) -> VignettingModel:
    """The single-frame fit of a working copy, with the do-no-harm fall-back."""
    h, w = wc.height, wc.width
    if wc.valid.sum() < MIN_VALID_BINS:
        q = FitQuality(confidence=0.0, fallback=True, seconds=time.perf_counter() - t0)
        log.debug("too few usable pixels (%d bins); no correction", int(wc.valid.sum()))
        return VignettingModel.identity(w, h, method="robust", quality=q)
    theta, cov, info = _select(wc, settings)
    ev_rms, ev_sigma = field_uncertainty_ev(theta, cov, wc)
    snr = ev_rms / ev_sigma if ev_sigma > 0 else math.inf
    # confidence: smooth in SNR, 0.5 at the decision threshold
    confidence = float(1.0 / (1.0 + math.exp(-2.0 * (snr - settings.min_snr))))
    accept = snr >= settings.min_snr and ev_rms >= settings.min_ev
    if accept and math.isfinite(settings.max_shape_ratio):
        ratio = shape_ratio(theta, wc)
        if ratio > settings.max_shape_ratio:
            log.debug("the fitted fall-off is broader than a real lens's (shape ratio %.2f); no correction", ratio)
            accept = False
    th_px, cov_px = _to_pixels(theta, cov, wc.radius)
    q = FitQuality(
        confidence=confidence, field_ev_rms=ev_rms, field_sigma_ev=ev_sigma, snr=snr,
        fallback=not accept, objective=float(info["objective"]), iterations=int(info["iterations"]),
        seconds=time.perf_counter() - t0,
    )
    covt = tuple(tuple(float(v) for v in row) for row in cov_px)
    fit = VignettingModel.from_vector(th_px, w, h, method="robust", covariance=covt, quality=q)
    # one figure, one name: quality.field_ev_rms is the model's own RMS of log2 phi over the
    # frame (what every command prints); the SNR above is on the fit's grid, about its mean
    q = replace(q, field_ev_rms=fit.field_ev_rms())
    fit = replace(fit, quality=q)
    if accept:
        return fit
    return VignettingModel.identity(w, h, method="robust", quality=q, candidate=fit)
