"""A lens profile from many frames: the debiased mean of centred fits.

Every photograph carries shading of its own, which a single-frame estimate reads as
vignetting; averaging frames of one lens shrinks the scatter of that shading but
not its mean.  The profile of a lens is therefore pooled in three steps:

1. **A centred circular fit per frame, without the scene prior**
   (:data:`CENTRED`).  A lens on an uncropped frame vignettes around the frame
   centre, and lensfun's own "pa" model is centred and radial too.  Without the
   scene prior, every frame's fit sees the scene's fall-off plus the lens's, so the
   fit stays in its linear regime (the monotone constraint and the do-no-harm
   fall-back rarely act), and its log-fields average as fields do.
2. **The mean of the frames' log-fields**, on a normalised grid.
3. **Minus the estimator's own mean on vignetting-free photos**, the *profile
   bias* (:func:`default_profile_bias`, ``vigproc prior fit-profile-bias``), clamped
   to a field that does not brighten, and refitted as a Kang-Weiss model.

Measured on the profile protocol (``vigproc bench profile``, BSDS val, 20 lensfun
lenses, script-level run of the same steps with the bias fitted on BSDS train):
0.284 / 0.173 / 0.069 EV after 1 / 5 / 20 frames, against 0.299 / 0.222 / 0.159
for one joint robust fit of the scene-divided frames (session 5; with session 7's
image order, ``vigproc bench profile`` gives 0.265 / 0.116 / 0.072 against 0.312 /
0.182 / 0.173, and 0.035 EV after 100 frames).  Dividing the scene prior out
of each frame before the centred fits instead measured 0.297 / 0.232 / 0.127: the
clamped fits of scene-divided frames do not average.

References
----------
Y. Zheng et al., IEEE TPAMI 35(6), 2013 (a centred radial fall-off per frame, the
assumption made here for a lens's uncropped frames); lensfun's "pa" vignetting
model (centred, radial).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Sequence

import numpy as np

from vigproc.errors import InvalidImageError, ModelError
from vigproc.model import VignettingModel
from vigproc.normalised import denormalise, fit_model_to_field, log_field_and_jacobian, normalise
from vigproc.robust import MIN_VALID_BINS, RobustSettings, WorkingCopy, fit_robust
from vigproc.scene import SceneFalloff, frame_grid, shipped_falloff

#: The shipped profile bias (package data), fitted by ``vigproc prior fit-profile-bias``.
SHIPPED_BIAS = "profile_bias.json"

#: Per-frame fit of a profile: centre and circle held, no scene prior, no fall-back.
CENTRED = RobustSettings(scene_prior=False, sigma_center=0.01, sigma_ellipticity=0.02, centred_z=math.inf)


@dataclass(frozen=True)
class FrameFit:
    """One frame's centred fit, normalised (12 parameters) with its covariance."""

    theta: np.ndarray
    cov: np.ndarray


def centred_fit(wc: WorkingCopy, settings: RobustSettings = CENTRED) -> FrameFit:
    """The centred circular fit of one frame's working copy (before the scene
    division: :func:`vigproc.robust.evidence_copy` returns such copies).

    Raises
    ------
    InvalidImageError
        Too few usable bins.
    """
    if int(wc.valid.sum()) < MIN_VALID_BINS:
        raise InvalidImageError(f"too few usable pixels for a fit ({int(wc.valid.sum())} bins)")
    theta, cov, _ = fit_robust(wc, settings)
    return FrameFit(theta=theta, cov=cov)


def default_profile_bias() -> SceneFalloff:
    """The shipped profile bias (package data, read once); none when it is missing."""
    return shipped_falloff(SHIPPED_BIAS)


def pool_fits(fits: Sequence[FrameFit], width: int, height: int,
              bias: SceneFalloff | None = None, min_ev: float = CENTRED.min_ev) -> VignettingModel:
    """The profile of a lens from its frames' centred fits (module doc, steps 2–3).

    Parameters
    ----------
    fits : sequence of FrameFit
        From :func:`centred_fit`, one per frame (all of one aspect ratio).
    width, height : int
        Frame the returned model refers to.
    bias : SceneFalloff, optional
        The estimator's mean fall-off on vignetting-free photos; None: the shipped one.
    min_ev : float
        A pooled fall-off weaker than this (EV RMS over the frame) is no correction,
        as for a single frame (:class:`~vigproc.robust.RobustSettings`).

    Returns
    -------
    VignettingModel
        ``method="profile-pooled"``, centred; its covariance is what the frames'
        covariances give the mean field if the frames were independent (the profile
        store also tracks their actual scatter).

    Raises
    ------
    ModelError
        No fits, or the pooled field cannot be fitted.
    """
    if not fits:
        raise ModelError("no frames to pool")
    bias = default_profile_bias() if bias is None else bias
    xs, ys, _, _ = frame_grid(width / height)
    fields, jacobians, _ = zip(*(log_field_and_jacobian(f.theta, xs, ys) for f in fits))
    mean = np.mean(fields, axis=0) - bias.log_field(xs, ys).ravel()
    target = np.minimum(mean, 0.0).reshape(ys.size, xs.size)  # a lens does not brighten its corners
    if float(np.sqrt(np.mean(target * target))) / math.log(2.0) < min_ev:
        fitted = VignettingModel.identity(width, height)
    else:
        fitted, _ = fit_model_to_field(target, width, height)
    theta, _, _ = normalise(fitted)
    # covariance of the pooled θ: the frames' field covariances J_i Σ_i J_iᵀ / n², mapped
    # through the least-squares refit at θ (pseudo-inverse of its Jacobian, since the
    # Kang-Weiss split between A and G leaves directions the field does not see)
    g = np.linalg.pinv(log_field_and_jacobian(theta, xs, ys)[1], rcond=1e-8)
    maps = [g @ j for j in jacobians]  # 12×12: frame parameters → pooled parameters
    cov = sum(a @ f.cov @ a.T for a, f in zip(maps, fits)) / len(fits) ** 2
    return denormalise(theta, 0.5 * (cov + cov.T), width, height, method="profile-pooled")

