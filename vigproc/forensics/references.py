"""What the claimed lens should give: the reference a frame is checked against (a stored
profile, else lensfun's calibration), as ring features with the spread of matching frames.

For a learned profile (whose mean already carries the average image bias), μ is
not added and Σ blends the calibration with the profile's own frame-to-frame
scatter (``Profile.theta_scatter``), weighted by its number of frames.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from vigproc.errors import VigprocError
from vigproc.forensics.lensmatch import whitener as _whitener
from vigproc.forensics.rings import PRIOR_FRAMES, Calibration, frame_features
from vigproc.core.normalised import denormalise
from vigproc.core.model import VignettingModel

__all__ = ["Expected", "Reference", "expected_for", "expected_from_field", "find_reference", "unknown_lens_reason"]

log = logging.getLogger(__name__)


@dataclass(frozen=True, eq=False)
class Expected:
    """What the claimed lens should give, and how far matching frames scatter."""

    model: VignettingModel
    source: str  # "stored-profile" or "lensfun"
    profile: str  # the profile key or the lensfun lens
    features: np.ndarray  # f(model), plus μ when the model is a true field
    covariance: np.ndarray  # Σ of matching frames around ``features``
    n_profile_frames: int = 0
    _whitener: list = field(default_factory=list, init=False, repr=False)

    @property
    def whitener(self) -> np.ndarray:
        """L⁻¹ with Σ = L Lᵀ (computed once)."""
        if not self._whitener:
            self._whitener.append(_whitener(self.covariance))
        return self._whitener[0]


def _feature_covariance_from_theta(theta: np.ndarray, theta_cov: np.ndarray, width: int, height: int) -> np.ndarray:
    """First-order propagation of a normalised-θ covariance to :func:`frame_features`."""
    base = frame_features(denormalise(theta, None, width, height))
    k = theta.size
    jac = np.zeros((base.size, k))
    for i in range(k):
        step = 1e-4 * max(abs(theta[i]), math.sqrt(max(theta_cov[i, i], 0.0)), 1e-3)
        t = theta.copy()
        t[i] += step
        jac[:, i] = (frame_features(denormalise(t, None, width, height)) - base) / step
    return jac @ theta_cov @ jac.T


def expected_from_field(model: VignettingModel, calibration: Calibration, *, source: str = "lensfun",
                        profile: str = "") -> Expected:
    """The expectation for a true lens field (lensfun, an imported profile): matching
    frames scatter around f(model) + μ with the calibration's Σ."""
    return Expected(model, source, profile, frame_features(model) + calibration.mean_vector,
                    calibration.covariance_matrix)


@dataclass(frozen=True, eq=False)
class Reference:
    """What the claimed lens is compared with, before any calibration.

    Attributes
    ----------
    model : VignettingModel
        The lens's vignetting on this frame.
    source : str
        ``stored-profile``, ``lensfun`` or ``embedded``.
    profile : str
        The profile's key or the lensfun lens.
    learned : bool
        A profile learned from frames (it already holds the scenes' average bias);
        False for a true field (lensfun, an imported profile, a DNG's calibration).
    n_frames : int
        Frames a learned profile pooled (0 for a true field).
    trusted : bool or None
        Whether a stored profile is trusted (None for lensfun and embedded).
    profile_obj : object or None
        The stored :class:`~vigproc.stores.profiles.Profile`.
    """

    model: VignettingModel
    source: str
    profile: str
    learned: bool = False
    n_frames: int = 0
    trusted: bool | None = None
    profile_obj: Any = None

    def describe(self) -> str:
        """The reference in words, for a verdict's reason."""
        if self.source == "lensfun":
            return f"lensfun's calibration of {self.profile}"
        if self.source == "embedded":
            return self.profile
        what = f"{self.n_frames} frame(s)" if self.learned else "imported"
        return f"the stored profile {self.profile} ({what}, {'trusted' if self.trusted else 'untrusted'})"


#: The lens key's fields a reference is looked up by (lensfun needs all three).
_LOOKUP_FIELDS = {"lens": "lens", "focal_mm": "focal length", "fnumber": "f-number"}


def unknown_lens_reason(lens_key) -> str | None:
    """Why a lens has no reference when its metadata is the cause: a field the lookup needs
    is missing, and what the metadata reading found about it (two sources that contradict
    each other, a rejected value; :attr:`vigproc.io.exif.LensKey.problems`). None when
    the metadata gives them all (then nothing knows the lens).

    Parameters
    ----------
    lens_key : LensKey or None

    Returns
    -------
    str or None
    """
    if lens_key is None:
        return None
    missing = [f for f in _LOOKUP_FIELDS if getattr(lens_key, f, None) is None]
    if not missing:
        return None
    # problems are "field: what" (vigproc.io.exif); those of the missing fields say why
    why = [p for p in getattr(lens_key, "problems", ()) if p.split(":", 1)[0] in missing]
    names = " and ".join(_LOOKUP_FIELDS[f] for f in missing)
    if why:
        return f"the metadata gives no usable {names}: {'; '.join(why)}"
    return f"the metadata gives no {names}, so no profile or calibration can be looked up"


def find_reference(lens_key, width: int, height: int, *, store=None, frame_id: str | None = None) -> Reference | None:
    """The vignetting of the lens ``lens_key`` names, for a ``width``×``height`` frame: a
    stored profile (trusted or not), else lensfun's calibration, else None.

    A stored profile that pooled the frame under check (content id ``frame_id``, or a
    copy of it) is not used: the frame would vouch for itself.
    """
    from vigproc.stores.lensfun_io import lensfun_model  # scipy.optimize: only when a reference is needed

    if lens_key is None:
        return None
    if getattr(lens_key, "lens_problem", None):  # a lens the frame cannot be from: nothing to compare with
        log.info("lens identity problem, no reference: %s", lens_key.lens_problem)
        return None
    if store is not None:
        try:
            p = store.lookup(lens_key, width, height)
        except VigprocError as exc:  # an odd key or a busy store: try lensfun
            log.warning("profile lookup failed: %s", exc)
            p = None
        if p is not None and frame_id is not None and store.holds_frame(p.key, frame_id):
            log.info("the stored profile %s holds this very frame; not used as its reference", p.key)
            p = None
        if p is not None:
            try:
                m = p.model(width, height)
            except VigprocError as exc:
                log.warning("stored profile %s is unusable here: %s", p.key, exc)
            else:
                learned = p.provenance == "learned"
                return Reference(m, "stored-profile", str(p.key), learned, max(int(p.n_frames), 1) if learned else 0,
                                 bool(p.trusted), p)
    try:
        m = lensfun_model(lens_key, width, height)
    except VigprocError as exc:  # unknown, ambiguous or uncalibrated lens: no expectation
        log.debug("no lensfun calibration: %s", exc)
        return None
    from vigproc.stores.lensfun_match import match_lens

    name = match_lens(lens_key).name or lens_key.lens  # lensfun's name of the lens compared with
    return Reference(m, "lensfun", f"{name} @ {lens_key.focal_mm:g} mm f/{lens_key.fnumber:g}")


def expected_for(lens_key, width: int, height: int, *, store=None, calibration: Calibration,
                 frame_id: str | None = None) -> Expected | None:
    """The expected ring features of the lens ``lens_key`` names (:func:`find_reference`)
    for a ``width``×``height`` frame, with the spread of matching frames; None for an
    unknown lens.

    Raises
    ------
    ForensicsError
        Never for an unknown lens (None is returned); only for a bad calibration.
    """
    ref = find_reference(lens_key, width, height, store=store, frame_id=frame_id)
    if ref is None:
        return None
    if not ref.learned:  # a true field: add the image bias
        return expected_from_field(ref.model, calibration, source=ref.source, profile=ref.profile)
    cov_cal = calibration.covariance_matrix
    p, m, n = ref.profile_obj, ref.model, ref.n_frames
    try:
        f = frame_features(m)
    except VigprocError as exc:  # as an unknown profile: lensfun's calibration, if any
        log.warning("stored profile %s is unusable here: %s", ref.profile, exc)
        return expected_for(lens_key, width, height, calibration=calibration)
    cov = cov_cal
    scatter = p.theta_scatter
    if scatter is not None and n >= 2:
        try:
            own = _feature_covariance_from_theta(np.asarray(p.theta, dtype=np.float64), scatter, width, height)
            cov = (PRIOR_FRAMES * cov_cal + (n - 1) * own) / (PRIOR_FRAMES + n - 1)
        except VigprocError as exc:
            log.debug("profile scatter not propagated: %s", exc)
    # the profile's mean is itself uncertain by Σ/n
    return Expected(m, "stored-profile", ref.profile, f, cov * (1.0 + 1.0 / n), n)


