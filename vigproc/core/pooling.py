"""A lens profile from many frames: a robust centre of the frames' lens-family fits.

Every photograph carries shading of its own, which a single-frame estimate reads as
vignetting. Over many frames of one lens the scenes differ and the lens does not,
so a profile pools its frames' evidence:

1. **Each frame's data alone, in the lens family** (:func:`frame_fit`:
   :func:`vigproc.core.family_fit.frame_coefficients` on the frame's stored working copy,
   :data:`~vigproc.core.lensfamily.PROFILE_COMPONENTS` components, no prior). A lens on
   an uncropped frame vignettes around the frame centre, radially, as lensfun's
   calibrations do; the data term alone is equivariant, so what a frame gets wrong
   is its scene's, not a pull towards a prior that is strongest for the strongest
   lenses. In a colour frame each log-difference pair is weighted by how alike its
   R, G and B change (a lens divides them alike; much of a scene's shading does not;
   :mod:`vigproc.core.family_fit`, step 2).
2. **A robust centre of the frames' coefficients**: the location of a multivariate t
   with ν = :data:`POOL_NU` (far heavier-tailed than a Gaussian) whose scatter is the
   scenes' own (:func:`scene_scatter`: how vignetting-free photographs scatter the fit,
   measured once, shipped), by IRLS from the coordinate-wise median. A frame whose scene
   fooled the fit (a lit wall, a centred bright subject) lies far out in that scatter's
   units and weighs little; frames that agree weigh alike, as in a mean, and the
   components' correlated errors are weighed together. On the clean protocol (the
   frames' stored fits, 20 lenses × 10 orders, scatter measured on the other half of
   the bases): 0.020 / 0.012 / 0.008 EV after 5 / 20 / 50 frames, against the
   coordinate-wise median's 0.027 / 0.013 / 0.008 (the single-frame fit's Cauchy scale;
   with :data:`FRAME_SETTINGS` ``vigproc bench profile-clean`` gives 0.015 / 0.007 /
   0.006), which had beaten the mean, trimmed
   means, Hodges-Lehmann, the spatial median and Huber weights. The median is the
   fall-back when no scatter is known.
3. **Nothing subtracted, no prior**: the scenes' median effect on vignetting-free
   photos is below 0.01 EV (``vigproc bench profile --clean``), and a bias fitted to
   film scans held their cameras' own fall-off (the store once subtracted
   one). Applying the family prior to the pooled coefficients measured worse at every
   number of frames: it shrinks strong lenses.

The pooled uncertainty is the median's (a bound on the t location's): π/2 times the
frames' covariance over n,
where the covariance is the frames' robust scatter, shrunk towards their mean
jackknife covariance when there are few frames (weight (n−1)/(n+4)), times
:data:`SIGMA_SCALE` measured on the clean protocol.

References
----------
Y. Zheng et al., "Single-image vignetting correction from gradient distribution
symmetries", IEEE TPAMI 35(6), 2013 (the per-frame data term); lensfun's "pa"
vignetting model (centred, radial); P. J. Huber, E. M. Ronchetti, *Robust
Statistics*, 2nd ed., 2009, §3.2 (the median and its asymptotic variance π/2·σ²/n);
K. L. Lange, R. J. A. Little, J. M. G. Taylor, "Robust statistical modeling using the t
distribution", JASA 84(408), 1989 (the t location by IRLS).
"""

from __future__ import annotations

import functools
import json
import math
from dataclasses import replace
from importlib import resources
from typing import Sequence

import numpy as np

from vigproc.errors import InvalidImageError, ModelError
from vigproc.core.family_fit import EVIDENCE_SETTINGS, FamilySettings, FrameCoefficients, field_sigma_ev, \
    frame_coefficients, profile_to_model
from vigproc.core.lensfamily import LensFamily, profile_family
from vigproc.core.model import FitQuality, VignettingModel
from vigproc.core.normalised import _field_grid, denormalise, log_field_and_jacobian, normalise
from vigproc.core.robust import RobustWorkingCopy

#: Method name of pooled profiles.
METHOD = "profile-pooled"
#: Scale of the pooled σ (dimensionless, a factor on the robust scatter of the frames'
#: coefficients): at 0.5 the pooled profile's error is within 1σ on about 9 in 10
#: profiles from 5 frames on (``vigproc bench profile-clean`` prints the shares; how it was
#: chosen: ``docs/benchmarks/profiles.md``, "How the pooling settings were chosen").
SIGMA_SCALE = 0.5
#: Frames whose coefficients lie further than this many robust s.d. from the median
#: are clipped there when the scatter is estimated.
_WINSOR = 2.5
_LN2 = math.log(2.0)


#: The settings of a frame's fit for pooling: the evidence fit's, with a Cauchy scale σ
#: of 0.005 (log units per step; half the single-frame fit's 0.01: without the prior a
#: smaller scale follows the mode of the log-gradients more closely, and the pooled frames
#: agree better), the single-frame fit's chroma scale τ = 0.002 and each pair's chroma
#: change as a covariate (weight 0.3), as in the single-frame fit. How they were chosen:
#: ``docs/benchmarks/profiles.md``, "How the pooling settings were chosen".
FRAME_SETTINGS = replace(EVIDENCE_SETTINGS, sigma=0.005, chroma_tau=0.002, chroma_covariate=0.3)


def frame_fit(wc: RobustWorkingCopy, family: LensFamily | None = None,
              settings: FamilySettings = FRAME_SETTINGS) -> FrameCoefficients:
    """One frame's lens-family coefficients from its working copy (the profile
    store's frame evidence, :func:`vigproc.core.robust.evidence_copy`).

    Raises
    ------
    InvalidImageError
        Too few usable bins.
    """
    fam = family or profile_family()
    xs, ys = wc.xs * wc.radius, wc.ys * wc.radius
    channels = None if wc.channels is None else (wc.channels, wc.channels_valid)
    fit = frame_coefficients(wc.L, wc.valid, xs, ys, wc.width, wc.height, settings, fam, channels=channels)
    if fit is None:
        raise InvalidImageError(f"too few usable pixels for a fit ({int(wc.valid.sum())} of {wc.valid.size} bins; "
                                "the rest are black, clipped or too dark)")
    return fit


#: Degrees of freedom of the multivariate t whose location pools the frames (module doc,
#: step 2): on the clean protocol ν = 0.1 / 0.25 / 0.5 / 1 gave 0.022 / 0.020 / 0.021 /
#: 0.022 EV after 5 frames and 0.011 / 0.012 / 0.012 / 0.013 after 20.
POOL_NU = 0.25
#: The shipped scenes' scatter (``vigproc bench scene-scatter``).
SCENE_SCATTER = "scene_scatter.json"


@functools.lru_cache(maxsize=1)
def _shipped_scene_scatter() -> tuple[np.ndarray, np.ndarray]:
    """The shipped scatter as a log-profile covariance at its radii (radii, F)."""
    d = json.loads(resources.files("vigproc.data").joinpath(SCENE_SCATTER).read_text(encoding="utf-8"))
    comps = np.asarray(d["components"], dtype=np.float64)
    return np.asarray(d["radii"], dtype=np.float64), comps.T @ np.asarray(d["covariance"], dtype=np.float64) @ comps


def scene_scatter(family: LensFamily) -> np.ndarray:
    """How vignetting-free photographs scatter a frame's data-only fit, as a covariance of
    ``family``'s coefficients (K×K).

    Shipped as a covariance of the log profile (the coefficients' covariance with the
    components it was measured in; it holds no lens: the frames carry none), so that
    any family, such as one built without a benchmark's test lenses, reads it in its
    own coefficients: Σ_c = C F Cᵀ for orthonormal components C.
    """
    radii, F = _shipped_scene_scatter()
    if radii.shape != family.radii.shape or not np.allclose(radii, family.radii):
        # the field covariance at the family's radii, bilinearly
        rows = np.array([np.interp(family.radii, radii, col) for col in F.T]).T
        F = np.array([np.interp(family.radii, radii, row) for row in rows])
    C = family.components
    S = C @ F @ C.T
    return 0.5 * (S + S.T)


def scene_scatter_record(fits: Sequence[FrameCoefficients], family: LensFamily, source: str) -> dict:
    """The shipped form of the scenes' scatter (:func:`scene_scatter`) from data-only fits
    of vignetting-free frames in ``family``: their winsorised covariance (as
    :func:`pooled_coefficients` winsorises) with the family's radii and components."""
    C = np.array([f.coefficients for f in fits], dtype=np.float64)
    if C.ndim != 2 or C.shape[1] != family.n_components:
        raise ModelError(f"the scenes' scatter needs fits in the family's {family.n_components} components")
    if C.shape[0] < 10:
        raise ModelError(f"the scenes' scatter needs at least 10 fits, got {C.shape[0]}")
    S = _winsorised_cov(C)
    return {"radii": family.radii.round(6).tolist(),
            "components": [[round(float(v), 8) for v in row] for row in family.components],
            "covariance": [[round(float(v), 8) for v in row] for row in S], "frames": int(C.shape[0]),
            "source": source}


def _winsorised_cov(C: np.ndarray) -> np.ndarray:
    """Covariance of rows clipped to :data:`_WINSOR` robust s.d. of the median."""
    centre = np.median(C, axis=0)
    mad = 1.4826 * np.median(np.abs(C - centre), axis=0)
    return np.atleast_2d(np.cov(np.clip(C, centre - _WINSOR * mad, centre + _WINSOR * mad).T))


def t_location(C: np.ndarray, scatter: np.ndarray, nu: float = POOL_NU, start: np.ndarray | None = None,
               iterations: int = 100) -> np.ndarray:
    """Location of a multivariate t with ``nu`` degrees of freedom and fixed ``scatter``,
    by IRLS: weights (ν + K) / (ν + d²), d the Mahalanobis distance from the current
    location (Lange, Little and Taylor 1989). From ``start`` (default: the
    coordinate-wise median): with ν < 1 the likelihood may have several maxima, and the
    one nearest the median is the one a robust centre means."""
    C = np.atleast_2d(np.asarray(C, dtype=np.float64))
    K = C.shape[1]
    P = np.linalg.inv(scatter)
    m = np.median(C, axis=0) if start is None else np.asarray(start, dtype=np.float64).copy()
    for _ in range(iterations):
        dev = C - m
        w = (nu + K) / (nu + np.einsum("ij,jk,ik->i", dev, P, dev))
        m_new = w @ C / w.sum()
        done = float(np.max(np.abs(m_new - m))) < 1e-7
        m = m_new
        if done:
            break
    return m


def pooled_coefficients(fits: Sequence[FrameCoefficients],
                        scatter: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """The robust centre of the frames' coefficients and its covariance (module doc):
    the t location under the scenes' ``scatter`` (K×K), or without one the
    coordinate-wise median.

    Raises
    ------
    ModelError
        No fits, fits of different families, or a scatter of another size.
    """
    if not fits:
        raise ModelError("no frames to pool")
    k = np.asarray(fits[0].coefficients).size
    if any(np.asarray(f.coefficients).shape != (k,) or np.asarray(f.covariance).shape != (k, k) for f in fits):
        raise ModelError("the frames' fits are of different lens families")
    if scatter is not None and np.shape(scatter) != (k, k):
        raise ModelError(f"a {np.shape(scatter)} scatter cannot pool {k} coefficients")
    C = np.array([f.coefficients for f in fits], dtype=np.float64)
    n = C.shape[0]
    if scatter is not None:
        ev = np.linalg.eigvalsh(0.5 * (scatter + scatter.T))
        if not np.all(np.isfinite(ev)) or ev[0] <= 1e-8 * ev[-1]:
            # a family with more components than the scatter was measured in: no distance
            # along the others, so no t location
            scatter = None
    centre = np.median(C, axis=0) if scatter is None else t_location(C, scatter)
    jack = np.mean([f.covariance for f in fits], axis=0)
    spread = _winsorised_cov(C) if n >= 3 else jack
    w = (n - 1) / (n + 4)
    cov = SIGMA_SCALE**2 * (math.pi / 2) * (w * spread + (1 - w) * jack) / n
    return centre, 0.5 * (cov + cov.T)


def coefficients_model(c: np.ndarray, width: int, height: int, family: LensFamily | None = None) -> VignettingModel:
    """The centred Kang-Weiss model (Lyu 2010, Eq. 2) of family coefficients ``c`` for
    a ``width``×``height`` frame (:func:`vigproc.core.family_fit.profile_to_model`)."""
    fam = family or profile_family()
    return profile_to_model(fam.mean + np.asarray(c, dtype=np.float64) @ fam.components, fam.radii,
                            width, height)[0]


def prior_coefficients(theta: np.ndarray, cov: np.ndarray, aspect: float,
                       family: LensFamily | None = None) -> tuple[np.ndarray, np.ndarray]:
    """A profile known without its frames (imported from a file, another store or a
    calibration) as family coefficients with their covariance: what it adds to the
    frames pooled after it (:func:`pool_family`'s ``prior``).

    Its ln φ on the normalised field grid (:data:`vigproc.core.normalised.FIELD_GRID`²
    points over a frame of aspect ``aspect``) is projected by least squares onto the
    family's components at each point's ρ; the covariance follows to first order,
    C = A J Σ Jᵀ Aᵀ (A the projection, J = ∂ ln φ / ∂θ̃). A centred, circular profile
    (vigproc's own exports, lensfun's "pa" fields) is a point of the family and comes
    back as the coefficients it was written from; an off-centre one is read as its
    nearest radial field.

    Parameters
    ----------
    theta : ndarray (12,)
        Normalised parameters (:func:`vigproc.core.normalised.normalise`).
    cov : ndarray (12, 12)
        Their covariance; parameters an import fixed (zero variance) add no spread.
    aspect : float
        W/H of the profile's frames.
    family : LensFamily, optional
        Default: :func:`vigproc.core.lensfamily.profile_family`.

    Returns
    -------
    coefficients : ndarray (K,)
    covariance : ndarray (K, K)

    Raises
    ------
    ModelError
        θ or its covariance not finite, or G ≤ 0 on the frame.
    """
    fam = family or profile_family()
    theta = np.asarray(theta, dtype=np.float64)
    cov = np.asarray(cov, dtype=np.float64)
    if not (np.all(np.isfinite(theta)) and np.all(np.isfinite(cov))):
        raise ModelError("a prior profile needs finite parameters and covariance")
    xs, ys = _field_grid(aspect)
    F, J, gmin = log_field_and_jacobian(theta, xs, ys)
    if not gmin > 0:
        raise ModelError(f"the prior profile's geometric factor G falls to {gmin:.3g} inside the frame")
    rho = np.hypot(*np.meshgrid(xs, ys)).ravel()
    mean, basis = fam.profiles(rho)
    A = np.linalg.pinv(basis)
    c = A @ (F - mean)
    AJ = A @ J
    cov_c = AJ @ cov @ AJ.T
    return c, 0.5 * (cov_c + cov_c.T)


def _with_prior(c: np.ndarray, cov: np.ndarray, prior: tuple[np.ndarray, np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """The frames' pooled coefficients ``(c, cov)`` combined with a prior profile's, both
    Gaussian, in information form: Λ = Σ₀⁻¹ + Σ⁻¹, c = Λ⁻¹(Σ₀⁻¹c₀ + Σ⁻¹c). Directions the
    prior does not constrain (zero information) are the frames' alone."""
    c0, cov0 = (np.asarray(a, dtype=np.float64) for a in prior)
    if c0.shape != c.shape or cov0.shape != cov.shape:
        raise ModelError(f"a prior of {c0.size} coefficients cannot join {c.size}")
    lam0 = np.linalg.pinv(0.5 * (cov0 + cov0.T), rcond=1e-10, hermitian=True)
    lam = np.linalg.inv(cov)
    total = lam0 + lam
    out_cov = np.linalg.inv(total)
    return out_cov @ (lam0 @ c0 + lam @ c), 0.5 * (out_cov + out_cov.T)


def pool_family(fits: Sequence[FrameCoefficients], width: int, height: int,
                family: LensFamily | None = None,
                prior: tuple[np.ndarray, np.ndarray] | None = None) -> VignettingModel:
    """The profile of a lens from its frames' lens-family fits.

    Parameters
    ----------
    fits : sequence of FrameCoefficients
        From :func:`frame_fit`, one per frame, all in ``family``.
    width, height : int
        Frame the returned model refers to.
    family : LensFamily, optional
        Default: :func:`vigproc.core.lensfamily.profile_family`.
    prior : (ndarray (K,), ndarray (K, K)), optional
        What was known of the lens before these frames (an imported profile,
        :func:`prior_coefficients`): joined to the frames' robust centre in information
        form, so an imported profile's frames keep their weight when the store learns
        more of the lens (Bishop, *Pattern Recognition and Machine Learning*, 2006,
        Eq. 2.116–2.117: the posterior of a Gaussian mean).

    Returns
    -------
    VignettingModel
        ``method="profile-pooled"``, centred and circular (the family's radial profile
        written as the Kang-Weiss model, Lyu 2010 Eq. 2); its covariance is the pooled
        coefficients' mapped onto the model's parameters, and
        ``quality.field_sigma_ev`` the pooled 1-σ error of log2 φ about its mean.

    Raises
    ------
    ModelError
        No fits, fits of another family, or a profile the model cannot write.
    """
    fam = family or profile_family()
    if fits and np.asarray(fits[0].coefficients).size != fam.n_components:
        raise ModelError(f"fits with {np.asarray(fits[0].coefficients).size} coefficients cannot pool in a "
                         f"{fam.n_components}-component family")
    c, cov_c = pooled_coefficients(fits, scene_scatter(fam))
    if prior is not None:
        c, cov_c = _with_prior(c, cov_c, prior)
    model = coefficients_model(c, width, height, fam)
    theta = normalise(model)[0]
    # the model's parameters move with the coefficients through a least-squares fit:
    # its Jacobian by central differences (the map is smooth, the steps small)
    jac = np.empty((theta.size, c.size))
    for k in range(c.size):
        step = np.eye(c.size)[k] * 1e-4
        up = normalise(coefficients_model(c + step, width, height, fam))[0]
        down = normalise(coefficients_model(c - step, width, height, fam))[0]
        jac[:, k] = (up - down) / 2e-4
    cov = jac @ cov_c @ jac.T
    sigma = field_sigma_ev(fam, cov_c, width, height)
    ev_rms = model.field_ev_rms()
    q = FitQuality(confidence=1.0, field_ev_rms=ev_rms, field_sigma_ev=sigma,
                   snr=ev_rms / sigma if sigma > 0 else math.inf)
    return denormalise(theta, 0.5 * (cov + cov.T), width, height, method=METHOD, quality=q)
