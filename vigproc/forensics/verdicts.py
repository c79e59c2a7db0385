"""Verdicts: a frame's vignetting against what its claimed lens should give, one frame or
several pooled.

:func:`forensic_check` estimates the frame's vignetting, looks up the reference
(:mod:`vigproc.forensics.references`) and turns the difference into a calibrated
false-alarm probability (:mod:`vigproc.forensics.rings`, or the lens-family test of
:mod:`vigproc.forensics.lensmatch`) and a verdict.

Several frames that claim the same lens pool their evidence (:func:`pool_verdicts`):
the mean whitened residual of n frames, D² = n·|z̄|², against the null of means
of n calibration frames from different photographs.

References
----------
S. Lyu, "Estimating Vignetting Function from a Single Image for Image
Authentication", ACM MM&Sec 2010.
"""

from __future__ import annotations

import dataclasses
import logging
import math
from dataclasses import dataclass, field
from typing import Any, Sequence

import numpy as np

from vigproc.errors import ModelError, VigprocError
from vigproc.core.model import half_diagonal
from vigproc.forensics.lensmatch import (
    MatchCalibration, beyond_scene_limit, default_match_calibration, luminance_family_fit, pooled_d2, reference_coefficients,
    scene_d2, whiten,
)
from vigproc.forensics.references import (
    Expected, Reference, expected_for, expected_from_field, find_reference, unknown_lens_reason,
)
from vigproc.forensics.rings import (
    CENTRE, DEFAULT_ALPHA, FALLOFF, FAMILY_TEST_METHOD, RING_RADII, _LN2, Calibration, ForensicsError,
    _fit_of, _is_weak, _mean_d2, _shape_ratio, _stated, _warn_if_stale, default_calibration,
    forensic_method, frame_features, frame_quality, ring_falloff,
)
from vigproc.core.lensfamily import default_family
from vigproc.core.model import FitQuality, VignettingModel
from vigproc.core.pixels import check_image as valid_image
from vigproc.core.pixels import luminance

__all__ = ["Evidence", "TESTS", "VERDICTS", "Verdict", "check_embedded", "check_family", "check_model",
           "forensic_check", "is_weak", "pool_verdicts", "score"]

log = logging.getLogger(__name__)

#: The verdicts :func:`forensic_check` gives. ``unlike-any-lens`` (the lens-family test): the
#: frame's fall-off is unlike any lens's, so no lens claim is judged; it is not
#: ``inconsistent``, whose false-alarm rate is calibrated on the frames it decides.
VERDICTS = ("consistent", "inconsistent", "unknown-lens", "insufficient-signal", "unlike-any-lens")
#: The statistics a verdict can come from (:attr:`Verdict.test`).
TESTS = ("lens-family", "rings")


# ------------------------------------------------------------------ verdicts
@dataclass(frozen=True)
class Evidence:
    """What differs between the frame's vignetting and the claimed lens's.

    Attributes
    ----------
    ring_radii : tuple of float
        Ring radii (half-diagonals) of the fall-off numbers.
    falloff_ev : tuple of float
        Estimated mean fall-off on each ring, EV (negative = darker than the centre).
    expected_falloff_ev : tuple of float or None
        What a matching frame gives there on average (the lens plus the image bias).
    falloff_diff_ev : tuple of float or None
        ``falloff_ev − expected_falloff_ev``: positive = less fall-off than the lens
        (a crop, a corrected frame, a weaker lens).
    falloff_sigma_ev : tuple of float or None
        Spread of matching frames on each ring.
    centre_px, expected_centre_px : tuple of float
        Vignetting centres (x, y), pixels from the frame centre.
    centre_offset : float
        Distance between them in half-diagonals (cropping moves the optical centre).
    falloff_d2, centre_d2 : float or None
        The two parts of the statistic alone (4 and 2 degrees of freedom).
    shape_ratio, expected_shape_ratio : float
        Minor/major axis ratio of the iso-attenuation ellipses.
    field_diff_ev : float or None
        RMS over the frame of log2(φ̂/φ_expected), EV (raw, no bias removed).
    scene_d2, scene_limit : float or None
        The lens-family test: how unlike any lens's the frame's fit is
        (:func:`vigproc.forensics.lensmatch.scene_d2`) and the calibration's limit above
        which the frame is left undecided.
    grey : bool or None
        The lens-family test: the frame had no colour to weigh its pairs by, and was
        judged by the scatter of grey fits (a check against its file's own calibration
        reads this).
    """

    ring_radii: tuple[float, ...]
    falloff_ev: tuple[float, ...]
    centre_px: tuple[float, float]
    shape_ratio: float
    expected_falloff_ev: tuple[float, ...] | None = None
    falloff_diff_ev: tuple[float, ...] | None = None
    falloff_sigma_ev: tuple[float, ...] | None = None
    expected_centre_px: tuple[float, float] | None = None
    centre_offset: float | None = None
    falloff_d2: float | None = None
    centre_d2: float | None = None
    expected_shape_ratio: float | None = None
    field_diff_ev: float | None = None
    scene_d2: float | None = None
    scene_limit: float | None = None
    grey: bool | None = None

    def to_dict(self) -> dict[str, Any]:
        return {k: (list(v) if isinstance(v, tuple) else v) for k, v in self.__dict__.items()}

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> Evidence:
        kw = {k: (tuple(v) if isinstance(v, list) else v) for k, v in d.items() if k in cls.__dataclass_fields__}
        return cls(**kw)


@dataclass(frozen=True)
class Verdict:
    """The outcome of a consistency check of one frame (or of several pooled).

    Attributes
    ----------
    verdict : str
        One of :data:`VERDICTS`.
    reason : str
        One sentence for people.
    lens_id : str or None
        The lens the metadata claims.
    expected_source : str or None
        ``stored-profile``, ``lensfun`` or ``embedded`` (the DNG's own calibration,
        :func:`check_embedded`); None for an unknown lens.
    profile : str or None
        The stored profile's key or the lensfun lens compared with.
    score : float or None
        D², the squared whitened distance to matching frames (6 degrees of freedom).
    p_false_alarm : float or None
        Probability that a frame truly taken with the claimed lens scores at least
        ``score`` (calibrated on natural photographs; small = suspicious).
    alpha : float
        The false-alarm probability below which the verdict is "inconsistent".
    n_frames : int
        Frames the evidence comes from.
    confidence, snr : float or None
        The confidence and SNR of vigproc's estimate of the frame with the same method
        and the EXIF's focal length and f-number as its hint: the figures ``vigproc
        estimate`` prints and ``correct`` decides by (:func:`frame_quality`), whatever
        the test compared. None when not measured (a verdict made from a model alone).
    evidence : Evidence or None
    estimate : VignettingModel or None
        The frame's estimate (its rejected fit is ``estimate.candidate`` when weak).
    expected : VignettingModel or None
        The claimed lens's model for this frame.
    whitened : tuple of float or None
        The whitened residual z (D² = |z|²), for pooling frames.
    test : str
        ``lens-family`` (the default check, :mod:`vigproc.forensics.lensmatch`: the frame's
        data-only family coefficients against the lens's, 2 degrees of freedom) or
        ``rings`` (fall-off on four rings and the centre, 6 degrees of freedom, with a
        calibration of :func:`fit_calibration`).
    lens_problem : str or None
        Why the lens the EXIF names cannot be the frame's (``LensKey.lens_problem``: a
        focal length or f-number outside its range); the verdict is then ``unknown-lens``,
        compared with no reference.
    """

    verdict: str
    reason: str
    lens_id: str | None = None
    expected_source: str | None = None
    profile: str | None = None
    score: float | None = None
    p_false_alarm: float | None = None
    alpha: float = DEFAULT_ALPHA
    n_frames: int = 1
    confidence: float | None = None
    evidence: Evidence | None = None
    estimate: VignettingModel | None = field(default=None, repr=False)
    expected: VignettingModel | None = field(default=None, repr=False)
    whitened: tuple[float, ...] | None = field(default=None, repr=False)
    test: str = "rings"
    lens_problem: str | None = None  # why the EXIF's lens cannot be the frame's (LensKey.lens_problem)
    snr: float | None = None

    def __post_init__(self) -> None:
        if self.verdict not in VERDICTS:
            raise ForensicsError(f"unknown verdict {self.verdict!r}")
        if self.test not in TESTS:
            raise ForensicsError(f"unknown test {self.test!r}")

    @property
    def decided(self) -> bool:
        return self.verdict in ("consistent", "inconsistent")

    def to_dict(self) -> dict[str, Any]:
        """JSON-able (floats, strings, lists; models as :meth:`VignettingModel.to_dict`)."""
        d: dict[str, Any] = {
            "verdict": self.verdict, "reason": self.reason, "lens_id": self.lens_id,
            "expected_source": self.expected_source, "profile": self.profile,
            "score": self.score, "p_false_alarm": self.p_false_alarm, "alpha": self.alpha,
            "n_frames": self.n_frames, "confidence": self.confidence, "snr": self.snr,
            "evidence": self.evidence.to_dict() if self.evidence is not None else None,
            "estimate": self.estimate.to_dict() if self.estimate is not None else None,
            "expected": self.expected.to_dict() if self.expected is not None else None,
            "whitened": list(self.whitened) if self.whitened is not None else None,
            "test": self.test, "lens_problem": self.lens_problem,
        }
        return d

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> Verdict:
        if not isinstance(d, dict):
            raise ForensicsError("a verdict must be a JSON object")
        try:
            return cls(
                verdict=d["verdict"], reason=str(d.get("reason", "")), lens_id=d.get("lens_id"),
                expected_source=d.get("expected_source"), profile=d.get("profile"), score=d.get("score"),
                p_false_alarm=d.get("p_false_alarm"), alpha=float(d.get("alpha", DEFAULT_ALPHA)),
                n_frames=int(d.get("n_frames", 1)), confidence=d.get("confidence"),
                evidence=Evidence.from_dict(d["evidence"]) if d.get("evidence") else None,
                estimate=VignettingModel.from_dict(d["estimate"]) if d.get("estimate") else None,
                expected=VignettingModel.from_dict(d["expected"]) if d.get("expected") else None,
                whitened=tuple(float(v) for v in d["whitened"]) if d.get("whitened") else None,
                test=str(d.get("test", "rings")), snr=d.get("snr"),
                lens_problem=d.get("lens_problem") if isinstance(d.get("lens_problem"), str) else None,
            )
        except (KeyError, TypeError, ValueError) as exc:
            raise ForensicsError(f"invalid verdict record: {exc!r}") from None


def _evidence(fit: VignettingModel, f_est: np.ndarray, exp: Expected | None) -> Evidence:
    big_r = half_diagonal(fit.width, fit.height)
    ev = Evidence(ring_radii=RING_RADII, falloff_ev=tuple(float(v) for v in f_est[FALLOFF]),
                  centre_px=(float(fit.center[0]), float(fit.center[1])), shape_ratio=_shape_ratio(fit))
    if exp is None:
        return ev
    diff = f_est - exp.features
    cov = exp.covariance
    fd = diff[FALLOFF]
    cd = diff[CENTRE]
    m = exp.model
    grid = (64, max(2, round(64 * fit.width / fit.height)))
    try:
        field_diff = float(np.sqrt(np.mean((fit.log_field(grid) - m.log_field(grid)) ** 2))) / _LN2
    except ModelError:
        field_diff = None
    return Evidence(
        ring_radii=RING_RADII, falloff_ev=ev.falloff_ev, centre_px=ev.centre_px, shape_ratio=ev.shape_ratio,
        expected_falloff_ev=tuple(float(v) for v in exp.features[FALLOFF]),
        falloff_diff_ev=tuple(float(v) for v in fd),
        falloff_sigma_ev=tuple(float(v) for v in np.sqrt(np.diag(cov)[FALLOFF])),
        expected_centre_px=(float(m.center[0]), float(m.center[1])),
        centre_offset=float(math.hypot(fit.center[0] - m.center[0], fit.center[1] - m.center[1]) / big_r),
        falloff_d2=float(fd @ np.linalg.solve(cov[FALLOFF, FALLOFF], fd)),
        centre_d2=float(cd @ np.linalg.solve(cov[CENTRE, CENTRE], cd)),
        expected_shape_ratio=_shape_ratio(m), field_diff_ev=field_diff,
    )


def _describe(ev: Evidence) -> str:
    """The largest contributor, in words."""
    if ev.falloff_d2 is None or ev.centre_d2 is None or ev.falloff_diff_ev is None:
        return ""
    if ev.centre_d2 / 2.0 > ev.falloff_d2 / 4.0:  # per degree of freedom
        return f"the vignetting centre is {ev.centre_offset:.2f} half-diagonals off the lens's (cropped off-centre?)"
    d = ev.falloff_diff_ev[-1]
    more = "less" if d > 0 else "more"
    return f"{abs(d):.2f} EV {more} fall-off at ρ={ev.ring_radii[-1]:g} than the lens gives"


def score(features: np.ndarray, expected: Expected) -> tuple[float, np.ndarray]:
    """D² of a frame's :func:`frame_features` against an expectation, and the whitened
    residual z (D² = |z|²)."""
    z = expected.whitener @ (np.asarray(features, dtype=np.float64) - expected.features)
    return float(z @ z), z


def is_weak(estimate: VignettingModel) -> bool:
    """Whether an estimate is too weak for a verdict (fall-back, low confidence, no fit)."""
    return _is_weak(estimate) or _fit_of(estimate).is_identity


def check_model(
    estimate: VignettingModel, expected: Expected | None, *, calibration: Calibration,
    lens_id: str | None = None, alpha: float | None = None, quality=None, why_unknown: str | None = None,
) -> Verdict:
    """Verdict for an estimate against an expected model (no image: benchmarks, tests).

    Parameters
    ----------
    estimate : VignettingModel
        The frame's estimate as returned by :func:`vigproc.core.estimate.estimate`
        (a fall-back's ``candidate`` is used for the numbers).
    expected : Expected or None
        From :func:`expected_for`; None means the lens is unknown.
    calibration : Calibration
    lens_id : str, optional
    alpha : float, optional
        False-alarm probability threshold (default: the calibration's).
    quality : FitQuality, optional
        What the verdict states as the frame's confidence (:func:`frame_quality`);
        default the estimate's own.
    why_unknown : str, optional
        Why the lens is unknown when the metadata says more than "no lens"
        (:func:`unknown_lens_reason`).

    Returns
    -------
    Verdict
    """
    alpha = calibration.alpha if alpha is None else float(alpha)
    fit = _fit_of(estimate)
    f_est = frame_features(fit)
    ev = _evidence(fit, f_est, expected)
    conf = estimate.quality.confidence if estimate.quality is not None else None
    stated = _stated(quality if quality is not None else estimate.quality)
    common = dict(lens_id=lens_id, alpha=alpha, evidence=ev, estimate=estimate, **stated)
    if expected is None:
        why = why_unknown or ("the metadata names no lens" if lens_id is None else
                              "no stored profile and no lensfun calibration for this lens")
        return Verdict("unknown-lens", why, **common)
    d2, z = score(f_est, expected)
    weak = is_weak(estimate)
    p = calibration.p_value(d2, decided=not weak)
    common.update(expected_source=expected.source, profile=expected.profile, score=d2, p_false_alarm=p,
                  expected=expected.model, whitened=tuple(float(v) for v in z))
    if weak:
        return Verdict("insufficient-signal", f"the test's own fit of the frame ({estimate.method}) is too weak "
                       f"to decide (its confidence {conf if conf is not None else 0:.2f}); the numbers are of its "
                       f"rejected fit",
                       **common)
    if p < alpha:
        return Verdict("inconsistent", f"false-alarm probability {p:.3g} < {alpha:g}: " + _describe(ev), **common)
    return Verdict("consistent", f"within the spread of frames taken with this lens (false-alarm "
                   f"probability {p:.3g} ≥ {alpha:g})", **common)


def check_embedded(estimate: VignettingModel, embedded: VignettingModel, *,
                   calibration: Calibration | MatchCalibration,
                   lens_id: str | None = None, alpha: float | None = None, profile: str = "embedded",
                   grey: bool = False) -> Verdict:
    """Verdict for a frame's estimate against the calibration its own file carries (a
    DNG's vignetting opcodes, :mod:`vigproc.io.dng_vignette`): a true field, so matching
    frames scatter around it plus the image bias, as for lensfun (:func:`expected_from_field`).
    A frame whose vignetting disagrees with its own embedded calibration was cropped,
    edited or given another file's metadata.

    Parameters
    ----------
    estimate : VignettingModel
        The frame's estimate (``Verdict.estimate`` of :func:`forensic_check`).
    embedded : VignettingModel
        The embedded calibration as a model of the same frame
        (:meth:`vigproc.io.dng_vignette.EmbeddedCalibration.model`).
    calibration, lens_id, alpha
        As for :func:`check_model`.
    profile : str
        What the verdict names as the reference.
    grey : bool
        The lens-family test: the frame had no colour (``Verdict.evidence.grey`` of its
        lens check), so it is judged by the scatter of grey fits.
    """
    if isinstance(calibration, MatchCalibration):  # the lens-family test: the estimate is its data-only fit
        fam = default_family()
        calibration.check_family(fam)
        fit = _fit_of(estimate)
        c = None if fit.is_identity and estimate.quality is not None and estimate.quality.fallback else \
            reference_coefficients(fit, fit.width, fit.height, fam)
        return _family_verdict(estimate, c, Reference(embedded, "embedded", profile), calibration=calibration,
                               family=fam, lens_id=lens_id, alpha=alpha, grey=grey)
    exp = expected_from_field(embedded, calibration, source="embedded", profile=profile)
    return check_model(estimate, exp, calibration=calibration, lens_id=lens_id, alpha=alpha)


def _family_model(c: np.ndarray, width: int, height: int, family, calibration) -> VignettingModel:
    """The frame's data-only family fit as a (centred) Kang-Weiss model, its stated σ
    the scenes' scatter (the calibration's Σ) propagated to the field."""
    from vigproc.core.family_fit import field_spread_ev, profile_to_model  # its Numba kernel: only when used

    m, _ = profile_to_model(family.mean + np.asarray(c) @ family.components, family.radii, width, height)
    gx = np.linspace(0.0, 1.0, 33)
    _, basis = family.profiles(gx)
    sigma = field_spread_ev(basis, calibration.covariance_matrix)
    ev = m.field_ev_rms()
    # no confidence of its own (NaN, null in JSON): it is no correction; the verdict states
    # the frame's estimate's (frame_quality), the one figure every command gives
    q = FitQuality(confidence=math.nan, field_ev_rms=ev, field_sigma_ev=sigma,
                   snr=ev / sigma if sigma > 0 else math.inf)
    return VignettingModel(width, height, center=m.center, p=m.p, alpha=m.alpha, method=FAMILY_TEST_METHOD, quality=q)


def _family_verdict(estimate: VignettingModel, c: np.ndarray | None, ref: Reference | None, *, calibration,
                    family, lens_id: str | None, alpha: float | None, grey: bool = False,
                    quality=None, why_unknown: str | None = None) -> Verdict:
    """The lens-family test's verdict (:mod:`vigproc.forensics.lensmatch`) for a frame's data-only
    coefficients ``c`` (None: too few usable pixels) against a reference; ``grey``: a
    frame without colour, whose fit the scenes scatter more
    (:attr:`~vigproc.forensics.lensmatch.MatchCalibration.grey_inflate`); ``quality``: the
    frame's confidence as the verdict states it (:func:`frame_quality`; the data-only fit
    has none)."""
    alpha = calibration.alpha if alpha is None else float(alpha)
    fit = _fit_of(estimate)
    rings = ring_falloff(fit)
    big_r = half_diagonal(fit.width, fit.height)
    ev = Evidence(ring_radii=RING_RADII, falloff_ev=tuple(float(v) for v in rings),
                  centre_px=(float(fit.center[0]), float(fit.center[1])), shape_ratio=_shape_ratio(fit))
    common: dict[str, Any] = dict(lens_id=lens_id, alpha=alpha, estimate=estimate, test="lens-family",
                                  **_stated(quality))
    if ref is None:
        why = why_unknown or ("the metadata names no lens" if lens_id is None else
                              "no stored profile and no lensfun calibration for this lens")
        return Verdict("unknown-lens", why, evidence=ev, **common)
    if c is None:
        return Verdict("insufficient-signal", "too few usable pixels for a fit of the frame's vignetting",
                       evidence=ev, expected_source=ref.source, profile=ref.profile, expected=ref.model, **common)
    c_ref = reference_coefficients(ref.model, fit.width, fit.height, family)
    # a learned profile holds the scenes' median bias already, and is uncertain by about
    # the median of its n frames' scatter (pi/2 sigma^2/n)
    inflate = 1.0 + math.pi / (2.0 * ref.n_frames) if ref.learned else 1.0
    if grey:
        inflate *= calibration.grey_inflate
    scene = scene_d2(c, calibration, family, inflate=calibration.grey_inflate if grey else 1.0)
    z = whiten(np.asarray(c) - c_ref, calibration, add_bias=not ref.learned, inflate=inflate)
    d2 = float(z @ z)
    p = calibration.p_value(d2)
    # the same numbers on the four rings, for people: what frames of the lens give there
    _, b_ring = family.profiles(np.asarray(RING_RADII))
    cov = calibration.covariance_matrix * inflate
    bias = np.zeros(len(RING_RADII)) if ref.learned else b_ring @ calibration.mean_vector / _LN2
    expected_rings = ring_falloff(ref.model) + bias
    diff = rings - expected_rings
    sd = np.sqrt(np.einsum("ij,jk,ik->i", b_ring, cov, b_ring)) / _LN2
    m = ref.model
    grid = (64, max(2, round(64 * fit.width / fit.height)))
    try:
        field_diff = float(np.std(fit.log_field(grid) - m.log_field(grid))) / _LN2
    except ModelError:
        field_diff = None
    ev = Evidence(
        ring_radii=RING_RADII, falloff_ev=ev.falloff_ev, centre_px=ev.centre_px, shape_ratio=ev.shape_ratio,
        expected_falloff_ev=tuple(float(v) for v in expected_rings), falloff_diff_ev=tuple(float(v) for v in diff),
        falloff_sigma_ev=tuple(float(v) for v in sd), expected_centre_px=(float(m.center[0]), float(m.center[1])),
        centre_offset=float(math.hypot(fit.center[0] - m.center[0], fit.center[1] - m.center[1]) / big_r),
        expected_shape_ratio=_shape_ratio(m), field_diff_ev=field_diff, scene_d2=scene,
        scene_limit=calibration.scene_limit, grey=bool(grey))
    common.update(expected_source=ref.source, profile=ref.profile, score=d2, p_false_alarm=p, expected=m,
                  whitened=tuple(float(v) for v in z), evidence=ev)
    against = f"against {ref.describe()}"
    if beyond_scene_limit(scene, calibration.scene_limit):
        # the frame's own light (or an edit) shaped its fit: comparing it with the lens
        # would judge the scene (lensmatch, step 4b); its numbers stay, for pooling and
        # for people, and the reason says an edit is one cause
        # (a label of its own: 'insufficient-signal' read as "no fall-off" beside a strong one)
        share = ("" if calibration.scene_share is None else
                 f", as {100 * calibration.scene_share:.1f} % of the calibration's genuine frames are")
        return Verdict("unlike-any-lens", f"the frame's shading is unlike any lens's fall-off (scene D² "
                       f"{scene:.1f} > {calibration.scene_limit:.1f}{share}): its own light or an edit (an added "
                       f"vignette, say), not a lens, shaped the estimate, so the claim is not judged {against} "
                       f"(false-alarm probability {p:.3g} if it were: a figure that holds for frames some lens explains, "
                       f"not for this one)",
                       **common)
    if p < alpha:
        d = float(diff[-1])
        return Verdict("inconsistent", f"false-alarm probability {p:.3g} < {alpha:g} {against}: {abs(d):.2f} EV "
                       f"{'less' if d > 0 else 'more'} fall-off at ρ={RING_RADII[-1]:g} than frames of this lens "
                       f"give (± {sd[-1]:.2f})", **common)
    return Verdict("consistent", f"within the spread of frames taken with this lens (false-alarm probability "
                   f"{p:.3g} ≥ {alpha:g} {against})", **common)


def check_family(img: np.ndarray, lens_key, *, store=None, calibration=None, alpha: float | None = None,
                 frame_id: str | None = None, family=None, quality=None) -> Verdict:
    """The lens-family test (:mod:`vigproc.forensics.lensmatch`) of a frame against the lens its
    metadata names: the default check of :func:`forensic_check`.

    Parameters
    ----------
    img : ndarray
        H×W or H×W×C (channels last) linear image.
    lens_key : LensKey or None
    store : ProfileStore, optional
    calibration : MatchCalibration, optional
        Default: the shipped one (:func:`vigproc.forensics.lensmatch.default_match_calibration`).
    alpha : float, optional
        Default: the calibration's (0.01).
    frame_id : str, optional
        The frame's content id: a stored profile that pooled it is not its reference.
    family : LensFamily, optional
        Default: the shipped family; the calibration must have been made in it.
    quality : FitQuality, optional
        The frame's confidence as the verdict states it (:func:`frame_quality`, which
        :func:`forensic_check` passes); None: none stated.

    Returns
    -------
    Verdict
        ``test="lens-family"``; ``estimate`` is the frame's data-only fit.

    Raises
    ------
    InvalidImageError
        Unusable pixels.
    MatchCalibrationError
        The calibration was made in another family.
    """
    from vigproc.core.family_fit import colour_of  # its Numba kernel: only when used

    cal = calibration if calibration is not None else default_match_calibration()
    fam = family if family is not None else default_family()
    cal.check_family(fam)
    a = valid_image(img, -1 if np.asarray(img).ndim == 3 else None)
    lum = luminance(a)
    h, w = lum.shape
    colour = colour_of(a)
    fc = luminance_family_fit(lum, fam, colour=colour)
    c = None if fc is None else np.asarray(fc.coefficients)
    est = None
    if c is not None:
        try:
            est = _family_model(c, w, h, fam, cal)
        except ModelError:
            # coefficients no lens has (a frame of no usable structure, the data alone
            # wildly extrapolated): no evidence either way, as with too few pixels
            log.info("the frame's lens-family fit is no vignetting a model can hold; insufficient signal")
            c = None
    if est is None:
        est = VignettingModel.identity(w, h, method=FAMILY_TEST_METHOD,
                                       quality=FitQuality(confidence=0.0, fallback=True))
    ref = find_reference(lens_key, w, h, store=store, frame_id=frame_id)
    return _family_verdict(est, c, ref, calibration=cal, family=fam,
                           lens_id=lens_key.lens_id() if lens_key is not None else None, alpha=alpha,
                           grey=colour is None, quality=quality, why_unknown=unknown_lens_reason(lens_key))


def forensic_check(
    img: np.ndarray, lens_key, *, store=None, method: str = "default", calibration: Calibration | None = None,
    alpha: float | None = None, frame_id: str | None = None,
) -> Verdict:
    """Does the vignetting of ``img`` match the lens its metadata names?

    Parameters
    ----------
    img : ndarray
        H×W or H×W×C (channels last) linear image.
    lens_key : LensKey or None
        The lens the metadata claims (:mod:`vigproc.io.exif`); None = unknown.
    store : ProfileStore, optional
        Learned profiles, consulted before lensfun (trusted or not).
    method : str
        ``default``: the lens-family test (:func:`check_family`); another estimator:
        the ring test, with a calibration made with it.
    calibration : Calibration or MatchCalibration, optional
        A :class:`~vigproc.forensics.lensmatch.MatchCalibration` runs the lens-family test, a
        :class:`Calibration` the ring test. Default: the shipped one of the test
        ``method`` selects.
    alpha : float, optional
        False-alarm probability threshold (default: the calibration's).
    frame_id : str, optional
        The frame's content id (SHA-256 of its file): a stored profile that pooled this
        frame is not its reference (:func:`find_reference`).

    Returns
    -------
    Verdict
        ``consistent``, ``inconsistent``, ``unknown-lens``, ``insufficient-signal`` or
        ``unlike-any-lens``.

    Raises
    ------
    InvalidImageError
        Unusable pixels.
    ForensicsError
        No calibration for ``method``.
    """
    from vigproc.core.estimate import estimate, exif_hint

    if isinstance(calibration, MatchCalibration) or (calibration is None and method == "default"):
        if method != "default":
            raise ForensicsError(f"the lens-family test runs its own fit, not the {method!r} estimator (give "
                                 f"--calibration a ring calibration made with 'vigproc forensics calibrate "
                                 f"--method {method}')")
        v = check_family(img, lens_key, store=store, calibration=calibration, alpha=alpha, frame_id=frame_id,
                         quality=frame_quality(img, lens_key))
        return _say_lens_problem(_say_own_frame(v, lens_key, img.shape[1], img.shape[0], store, frame_id), lens_key)
    cal = calibration if calibration is not None else default_calibration()
    asked, method = method, forensic_method(method)
    if cal.method != method:
        raise ForensicsError(f"the forensics calibration is for the {cal.method!r} estimator, not {method!r} "
                             f"(make one: vigproc forensics calibrate --method {method})")
    _warn_if_stale(cal, method)
    m = estimate(img, method, channel_axis=-1 if img.ndim == 3 else None)
    h, w = img.shape[:2]
    exp = expected_for(lens_key, w, h, store=store, calibration=cal, frame_id=frame_id)
    # the confidence stated is the frame's estimate with the user's method and hint; the
    # ring test's own estimate (no hint: a check is not told what it checks) when they agree
    same = method == asked and exif_hint(lens_key, asked) is None
    v = check_model(m, exp, calibration=cal, lens_id=lens_key.lens_id() if lens_key is not None else None,
                    alpha=alpha, quality=m.quality if same else frame_quality(img, lens_key, asked),
                    why_unknown=unknown_lens_reason(lens_key))
    return _say_lens_problem(_say_own_frame(v, lens_key, w, h, store, frame_id), lens_key)


def _say_lens_problem(v: Verdict, lens_key) -> Verdict:
    """An unknown-lens verdict says why lensfun had nothing: a lens the frame cannot have
    been shot with (never "consistent" with it), a lens EXIF only describes, a name
    lensfun does not hold."""
    if v.verdict != "unknown-lens" or lens_key is None or lens_key.lens is None:
        return v
    problem = getattr(lens_key, "lens_problem", None)
    if problem:
        return dataclasses.replace(v, lens_problem=problem, reason=f"the metadata's lens identity is contradictory "
                                                                   f"({problem}): the frame is compared with no reference")
    if v.reason.startswith("no stored profile and no lensfun calibration"):
        from vigproc.stores.lensfun_match import match_lens

        found = match_lens(lens_key)
        if found.lens is None:
            why = found.reason
        elif lens_key.focal_mm is None or lens_key.fnumber is None:
            why = f"lensfun has {found.name}, but the EXIF lacks the focal length or f-number"
        else:
            why = f"lensfun's {found.name} has no calibration usable at these settings"
        return dataclasses.replace(v, reason=f"{v.reason} ({why})")
    return v


def _say_own_frame(v: Verdict, lens_key, width: int, height: int, store, frame_id: str | None) -> Verdict:
    """An unknown-lens verdict whose lens has a stored profile that pooled this very frame
    says so: 'no stored profile' read as a lie to a user who had just learned the frame."""
    if v.verdict != "unknown-lens" or lens_key is None or store is None or frame_id is None:
        return v
    try:
        p = store.lookup(lens_key, width, height)
        own = p is not None and store.holds_frame(p.key, frame_id)
    except VigprocError:
        return v
    if not own:
        return v
    return dataclasses.replace(v, reason=f"the stored profile {p.key} was learned from this very frame (a frame "
                                         "cannot vouch for itself) and lensfun has no calibration for this lens")


def pool_verdicts(verdicts: Sequence[Verdict], *,
                  calibration: Calibration | MatchCalibration | None = None) -> Verdict:
    """One verdict from several frames that claim the same lens profile.

    The whitened residuals are pooled -- the lens-family test's by their coordinate-wise
    median (:func:`vigproc.forensics.lensmatch.pooled_d2`), the ring test's by their mean -- and
    D² = n·|z̄|² is compared with the same pooling of n calibration frames from
    different photographs.  Weak frames count (the
    calibration includes them); the pooled verdict is "insufficient-signal" only when
    every frame is weak.

    Raises
    ------
    ForensicsError
        No frame with an expected model, or frames compared with different profiles.
    """
    usable = [v for v in verdicts if v.whitened is not None]
    if not usable:
        raise ForensicsError("no frame with a known lens to pool")
    profiles = {(v.expected_source, v.profile) for v in usable}
    if len(profiles) > 1:
        raise ForensicsError(f"cannot pool frames compared with different profiles: {sorted(map(str, profiles))}")
    tests = {v.test for v in usable}
    if len(tests) > 1:
        raise ForensicsError(f"cannot pool verdicts of different tests: {sorted(tests)}")
    n = len(usable)
    rows = np.array([v.whitened for v in usable], dtype=np.float64)
    if tests == {"lens-family"}:  # the coordinate-wise median (vigproc.forensics.lensmatch)
        cal = calibration if isinstance(calibration, MatchCalibration) else default_match_calibration()
        z = np.median(rows, axis=0)
        d2 = pooled_d2(rows)
    else:  # the mean of the whitened ring residuals
        cal = calibration if isinstance(calibration, Calibration) else default_calibration()
        z = rows.mean(axis=0)
        d2 = _mean_d2(rows)
    if z.size != len(cal.mean):
        raise ForensicsError("the verdicts were not made with this calibration")
    p = cal.p_value(d2, n)
    alpha = usable[0].alpha
    first = usable[0]
    common = dict(lens_id=first.lens_id, expected_source=first.expected_source, profile=first.profile,
                  score=d2, p_false_alarm=p, alpha=alpha, n_frames=n, whitened=tuple(float(v) for v in z),
                  expected=first.expected, test=first.test)
    # frames the lens-family test left undecided because no lens explains their fit
    # (lensmatch, step 4b) are pooled by their median like any other and decide with them
    if all(v.verdict == "insufficient-signal" for v in usable):
        return Verdict("insufficient-signal", f"all {n} frames have weak vignetting estimates", **common)
    if p < alpha:
        return Verdict("inconsistent", f"{n} frames: false-alarm probability {p:.3g} < {alpha:g}", **common)
    return Verdict("consistent", f"{n} frames: false-alarm probability {p:.3g} ≥ {alpha:g}", **common)
