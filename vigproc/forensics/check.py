"""Forensic consistency check: does a frame's vignetting match the lens its EXIF names?

A photograph whose vignetting does not match the lens named in its metadata has
been cropped, edited or mislabelled (Lyu 2010, Section 1).  :func:`forensic_check`
estimates the frame's vignetting, looks up what the claimed lens should give (a
stored profile, else lensfun's calibration) and turns the difference into a
calibrated false-alarm probability and a verdict.

The statistic
-------------
Each model is summarised by :func:`frame_features`: the mean fall-off (log2 φ, EV)
on four rings at ρ = 0.3, 0.5, 0.7, 0.85 half-diagonals around the frame centre,
and the vignetting centre in half-diagonals.  Rings average out most of what an
elliptical or off-centre fit absorbs from the scene; the centre moves when a
frame is cropped off-centre.  The residual r = f(estimate) − f(expected) is
compared with the residuals of frames that truly match their lens:

    D² = (r − μ)ᵀ Σ⁻¹ (r − μ)

μ and Σ come from a :class:`Calibration`: natural photographs multiplied by real
lens fields (lensfun), estimated like any frame.  μ is the bias natural images
add to the estimate (their own outward darkening), Σ the frame-to-frame spread.
Both are large -- the estimator reads a photograph's own shading as vignetting
(README, "Measured") -- so a distance normalised by the fit's covariance would be
badly over-confident.  The false-alarm probability is the fraction of matching
frames, held out from the μ, Σ they are whitened with (5-fold by image), whose
D² is at least as large: an empirical p-value.

For a learned profile (whose mean already carries the average image bias), μ is
not added and Σ blends the calibration with the profile's own frame-to-frame
scatter (``Profile.theta_scatter``), weighted by its number of frames.

Several frames that claim the same lens pool their evidence (:func:`pool_verdicts`):
the mean whitened residual of n frames, D² = n·|z̄|², against the null of means
of n calibration frames from different photographs.

References
----------
S. Lyu, "Estimating Vignetting Function from a Single Image for Image
Authentication", ACM MM&Sec 2010.
"""

from __future__ import annotations

import functools
import json
import logging
import math
from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from vigproc.errors import EXIT_CODES, SETTINGS, ModelError, VigprocError
from vigproc.forensics.lensmatch import MatchCalibration, empirical_p, held_out_whitened, pooled_null
from vigproc.forensics.lensmatch import whitener as _whitener
from vigproc.core.model import VignettingModel

log = logging.getLogger(__name__)

__all__ = [
    "Calibration",
    "Evidence",
    "ForensicsError",
    "Verdict",
    "VERDICTS",
    "check_embedded",
    "check_family",
    "forensic_check",
    "check_model",
    "default_calibration",
    "expected_for",
    "expected_from_field",
    "find_reference",
    "frame_quality",
    "load_calibration",
    "fit_calibration",
    "frame_features",
    "is_weak",
    "pool_verdicts",
    "score",
    "unknown_lens_reason",
]

#: The estimator a check uses when asked for "default": the shipped calibration was
#: measured with it (vigproc's default before the lens-family fit). The lens-family
#: default needs its own calibration on vignetting-free frames first.
FORENSICS_METHOD = "robust"


#: Method name of the lens-family test's frame fit (the data term alone, no prior).
FAMILY_TEST_METHOD = "lens-family-data"


def forensic_method(method: str) -> str:
    """The estimator forensics runs for ``method`` ("default" → :data:`FORENSICS_METHOD`)."""
    return FORENSICS_METHOD if method == "default" else method


#: The verdicts :func:`forensic_check` gives. ``unlike-any-lens`` (the lens-family test): the
#: frame's fall-off is unlike any lens's, so no lens claim is judged; it is not
#: ``inconsistent``, whose false-alarm rate is calibrated on the frames it decides.
VERDICTS = ("consistent", "inconsistent", "unknown-lens", "insufficient-signal", "unlike-any-lens")
#: The statistics a verdict can come from (:attr:`Verdict.test`).
TESTS = ("lens-family", "rings")
#: Ring radii, in half-diagonals from the frame centre, of the fall-off features.
RING_RADII = (0.3, 0.5, 0.7, 0.85)
#: Names of the entries of :func:`frame_features`.
FEATURE_NAMES = tuple(f"falloff_ev@{r:g}" for r in RING_RADII) + ("centre_x", "centre_y")
#: Indices of the fall-off and centre parts of the features.
FALLOFF = slice(0, len(RING_RADII))
CENTRE = slice(len(RING_RADII), len(RING_RADII) + 2)
#: Fall-off (EV, outer ring) below which a model's centre counts only in proportion:
#: the centre of a nearly flat field is undefined (weak fits put it anywhere).
CENTRE_FALLOFF_EV = 0.1
#: Estimates below this confidence give "insufficient-signal" (the default
#: estimator's own fall-back threshold corresponds to 0.5).
MIN_CONFIDENCE = 0.5
#: Default false-alarm probability below which a frame is called inconsistent.
DEFAULT_ALPHA = 0.05
#: Prior weight, in frames, of the calibration's spread against a learned profile's own.
PRIOR_FRAMES = 10.0
#: Draws of the multi-frame null distribution.
NULL_DRAWS = 4000
CALIBRATION_SCHEMA = "vigproc.forensics-calibration/1"
SHIPPED_CALIBRATION = "forensics_calibration.json"
_ANGLES = np.linspace(0.0, 2.0 * math.pi, 180, endpoint=False)
_LN2 = math.log(2.0)


class ForensicsError(VigprocError):
    """A forensics calibration or classifier is missing, invalid or does not fit the request."""

    exit_code = EXIT_CODES["forensics"]
    blame = SETTINGS


# ------------------------------------------------------------------ features
def _half_diagonal(width: int, height: int) -> float:
    return 0.5 * math.hypot(width, height)


def ring_falloff(model: VignettingModel, radii: Sequence[float] = RING_RADII) -> np.ndarray:
    """Mean log2 φ (EV) of ``model`` on circles of radius ρ half-diagonals around the
    frame centre, over the parts of each circle inside the frame.

    Raises
    ------
    ModelError
        If G falls to zero on a ring.
    """
    w, h = model.width, model.height
    big_r = _half_diagonal(w, h)
    hx, hy = (w - 1) / 2.0, (h - 1) / 2.0
    out = np.empty(len(radii))
    for i, rho in enumerate(radii):
        x = rho * big_r * np.cos(_ANGLES)
        y = rho * big_r * np.sin(_ANGLES)
        inside = (np.abs(x) <= hx) & (np.abs(y) <= hy)
        if not inside.any():  # only for absurd aspect ratios: use the nearest points
            inside = np.abs(np.abs(x) - hx) <= np.abs(np.abs(x) - hx).min() + 1e-9
        out[i] = float(np.mean(model.log_field_at(x[inside], y[inside]))) / _LN2
    return out


def frame_features(model: VignettingModel) -> np.ndarray:
    """The forensic feature vector of a vignetting model (see :data:`FEATURE_NAMES`).

    Parameters
    ----------
    model : VignettingModel
        An estimate (pass ``m.candidate`` for a fall-back) or an expected model.

    Returns
    -------
    ndarray (6,)
        Fall-off in EV on the rings of :data:`RING_RADII` (≤ 0 for a darkening
        lens), then the vignetting centre (cx, cy) in half-diagonals, scaled down
        when the outer ring's fall-off is below :data:`CENTRE_FALLOFF_EV`.
    """
    big_r = _half_diagonal(model.width, model.height)
    rings = ring_falloff(model)
    weight = min(1.0, abs(float(rings[-1])) / CENTRE_FALLOFF_EV)
    return np.concatenate([rings, [weight * model.center[0] / big_r, weight * model.center[1] / big_r]])


def _shape_ratio(model: VignettingModel) -> float:
    """Minor/major axis ratio of the iso-attenuation ellipses (1 = circular)."""
    ev = np.linalg.eigvalsh(model.shape_matrix)
    if ev[1] <= 0:
        return 1.0
    return float(math.sqrt(max(ev[0], 0.0) / ev[1]))


def _fit_of(m: VignettingModel) -> VignettingModel:
    return m.candidate if m.candidate is not None else m


def frame_quality(img: np.ndarray, lens_key, method: str = "default"):
    """The fit quality of vigproc's estimate of ``img`` as ``vigproc estimate``, ``correct``
    and the hook make it: ``method`` with the EXIF's focal length and f-number as its hint
    (:func:`vigproc.core.estimate.exif_hint`). A verdict states its confidence, whatever
    fit the test itself compares, so that a frame has one confidence in every command.

    Parameters
    ----------
    img : ndarray
        H×W or H×W×C (channels last) linear image.
    lens_key : LensKey or None
    method : str

    Returns
    -------
    FitQuality or None
        None when the estimator states none or cannot estimate this frame (said in the log:
        the check itself still runs).
    """
    from vigproc.core.estimate import estimate, exif_hint

    try:
        m = estimate(img, method, channel_axis=-1 if np.ndim(img) == 3 else None, hint=exif_hint(lens_key, method))
    except VigprocError as exc:
        log.info("no confidence for this frame: %s", exc)
        return None
    return m.quality


def _stated(q) -> dict[str, float | None]:
    """A fit quality's confidence and SNR as a verdict states them (JSON: no NaN or Inf)."""
    if q is None:
        return {"confidence": None, "snr": None}
    return {k: (float(v) if math.isfinite(float(v)) else None) for k, v in (("confidence", q.confidence),
                                                                               ("snr", q.snr))}


def _is_weak(m: VignettingModel) -> bool:
    q = m.quality
    if q is None:
        return False
    if q.fallback or q.confidence < MIN_CONFIDENCE:
        return True
    return False


# ------------------------------------------------------------------ calibration
def _as_matrix(a: Any, n: int, what: str) -> np.ndarray:
    try:
        m = np.asarray(a, dtype=np.float64)
    except (TypeError, ValueError):
        raise ForensicsError(f"calibration: {what} is not numeric") from None
    if m.ndim != 2 or m.shape[1] != n or not np.all(np.isfinite(m)):
        raise ForensicsError(f"calibration: {what} must be a finite N×{n} array")
    return m


@dataclass(frozen=True)
class Calibration:
    """Null distribution of the consistency statistic for one estimator.

    Attributes
    ----------
    method : str
        Estimator the calibration holds for.
    mean : tuple of float
        μ: mean of f(estimate) − f(true field) over matching frames.
    covariance : tuple of tuple of float
        Σ: their covariance.
    null : tuple of tuple of float
        Whitened held-out residuals L⁻¹(r − μ_k) of the calibration frames (5-fold by
        photograph; Σ_k = L Lᵀ from the other folds): D² of a matching frame is
        distributed as their squared norms.
    null_groups : tuple of int
        Photograph of each ``null`` row (multi-frame draws take distinct ones).
    null_weak : tuple of bool
        Whether each ``null`` row's estimate was too weak for a verdict: a single
        frame's verdict is calibrated on the frames that get one.
    alpha : float
        False-alarm probability below which a frame is called inconsistent.
    n_frames, n_images : int
        Calibration frames and photographs.
    source : str
        The command that produced it.
    fingerprint : tuple of float or None
        :func:`estimator_fingerprint` of the estimator when calibrated.
    """

    method: str
    mean: tuple[float, ...]
    covariance: tuple[tuple[float, ...], ...]
    null: tuple[tuple[float, ...], ...]
    null_groups: tuple[int, ...]
    null_weak: tuple[bool, ...] = ()
    alpha: float = DEFAULT_ALPHA
    n_frames: int = 0
    n_images: int = 0
    source: str = ""
    fingerprint: tuple[float, ...] | None = None
    _null_cache: dict = field(default_factory=dict, init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        k = len(FEATURE_NAMES)
        mu = np.asarray(self.mean, dtype=np.float64)
        if mu.shape != (k,) or not np.all(np.isfinite(mu)):
            raise ForensicsError(f"calibration: mean must be {k} finite numbers")
        cov = _as_matrix(self.covariance, k, "covariance")
        if cov.shape != (k, k) or not np.allclose(cov, cov.T, rtol=1e-6, atol=1e-12):
            raise ForensicsError("calibration: covariance must be a symmetric matrix")
        if np.linalg.eigvalsh(cov)[0] <= 0:
            raise ForensicsError("calibration: covariance is not positive definite")
        z = _as_matrix(self.null, k, "null sample")
        if len(z) < 20 or len(self.null_groups) != len(z):
            raise ForensicsError("calibration: needs at least 20 null residuals, each with its photograph")
        if self.null_weak and len(self.null_weak) != len(z):
            raise ForensicsError("calibration: one weak flag per null residual")
        if not (0.0 < float(self.alpha) < 1.0):
            raise ForensicsError(f"calibration: alpha must be within (0, 1), got {self.alpha}")

    # -- the null -----------------------------------------------------------
    @property
    def mean_vector(self) -> np.ndarray:
        return np.asarray(self.mean, dtype=np.float64)

    @property
    def covariance_matrix(self) -> np.ndarray:
        return np.asarray(self.covariance, dtype=np.float64)

    def null_d2(self, n_frames: int = 1, *, decided: bool = False) -> np.ndarray:
        """Sorted D² of matching frames (``n_frames`` = 1) or of the mean of
        ``n_frames`` matching frames from different photographs (deterministic draws).
        ``decided``: single frames whose estimate was strong enough for a verdict
        (all frames when fewer than 20 were)."""
        return _null_d2(self, int(n_frames), bool(decided) and int(n_frames) <= 1)

    def p_value(self, d2: float, n_frames: int = 1, *, decided: bool = False) -> float:
        """False-alarm probability: the fraction of matching frames (or means of
        ``n_frames`` of them; or, ``decided``, of single frames that get a verdict)
        with a statistic at least ``d2``, (k + 1)/(N + 1)."""
        return empirical_p(self.null_d2(n_frames, decided=decided), d2)

    # -- files --------------------------------------------------------------
    def to_dict(self) -> dict[str, Any]:
        return {
            "schema": CALIBRATION_SCHEMA, "method": self.method, "features": list(FEATURE_NAMES),
            "mean": list(self.mean), "covariance": [list(r) for r in self.covariance],
            "alpha": self.alpha, "n_frames": self.n_frames, "n_images": self.n_images, "source": self.source,
            "fingerprint": list(self.fingerprint) if self.fingerprint is not None else None,
            "null_groups": list(self.null_groups),
            "null_weak": [int(v) for v in self.null_weak],
            "null": [[round(v, 6) for v in r] for r in self.null],
        }

    @classmethod
    def from_dict(cls, d: Any) -> Calibration:
        if not isinstance(d, dict) or d.get("schema") != CALIBRATION_SCHEMA:
            raise ForensicsError(f"not a forensics calibration (schema {CALIBRATION_SCHEMA!r} expected)")
        if list(d.get("features", [])) != list(FEATURE_NAMES):
            raise ForensicsError("calibration was made for other features; recalibrate "
                                 "('vigproc forensics calibrate')")
        try:
            fp = d.get("fingerprint")
            return cls(
                method=str(d["method"]),
                mean=tuple(float(v) for v in d["mean"]),
                covariance=tuple(tuple(float(v) for v in r) for r in d["covariance"]),
                null=tuple(tuple(float(v) for v in r) for r in d["null"]),
                null_groups=tuple(int(v) for v in d["null_groups"]),
                null_weak=tuple(bool(v) for v in d.get("null_weak", ())),
                alpha=float(d.get("alpha", DEFAULT_ALPHA)), n_frames=int(d.get("n_frames", 0)),
                n_images=int(d.get("n_images", 0)), source=str(d.get("source", "")),
                fingerprint=tuple(float(v) for v in fp) if fp is not None else None,
            )
        except (KeyError, TypeError, ValueError) as exc:
            raise ForensicsError(f"invalid forensics calibration: {exc!r}") from None

    def save(self, path: str | Path) -> None:
        """Write as JSON, atomically."""
        from vigproc.atomic import atomic_write_text

        atomic_write_text(Path(path), json.dumps(self.to_dict(), indent=None, separators=(",", ":")) + "\n")

    @classmethod
    def load(cls, path: str | Path) -> Calibration:
        return cls.from_dict(read_json(path, "calibration"))


def load_calibration(path: str | Path) -> Calibration | MatchCalibration:
    """A calibration file of either test: the lens-family test's
    (:class:`~vigproc.forensics.lensmatch.MatchCalibration`) or the ring test's (:class:`Calibration`).

    Raises
    ------
    ForensicsError, MatchCalibrationError
        Unreadable or not a calibration.
    """
    d = read_json(path, "calibration")
    if isinstance(d, dict) and d.get("schema") != CALIBRATION_SCHEMA:
        if str(d.get("schema", "")).startswith("vigproc.lensmatch"):
            return MatchCalibration.from_dict(d)
    return Calibration.from_dict(d)


def read_json(path: str | Path, what: str) -> Any:
    """The JSON document in ``path`` (a calibration, a classifier).

    Raises
    ------
    ForensicsError
        Unreadable, not UTF-8 or not JSON, naming ``what`` and the file.
    """
    try:
        text = Path(path).read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise ForensicsError(f"cannot read {what} {path}: {exc}") from None
    try:
        return json.loads(text)
    except (json.JSONDecodeError, RecursionError) as exc:  # RecursionError: absurdly nested
        raise ForensicsError(f"{what} {path} is not valid JSON: {exc}") from None


def _null_d2(cal: Calibration, n_frames: int, decided: bool) -> np.ndarray:
    cached = cal._null_cache.get((n_frames, decided))
    if cached is not None:
        return cached
    z = np.asarray(cal.null, dtype=np.float64)
    if decided and cal.null_weak:
        strong = ~np.asarray(cal.null_weak, dtype=bool)
        if strong.sum() >= 20:
            z = z[strong]
    if n_frames <= 1:
        out = np.sort(np.einsum("ij,ij->i", z, z))
    else:
        g = np.asarray(cal.null_groups)
        uniq = np.unique(g)
        if uniq.size < n_frames:
            raise ForensicsError(f"the calibration has {uniq.size} photographs, too few for {n_frames}-frame evidence")
        out = pooled_null(z, g, n_frames, _mean_d2, seed=12345 + n_frames, draws=NULL_DRAWS)
    cal._null_cache[(n_frames, decided)] = out
    return out


def _mean_d2(z: np.ndarray) -> float:
    """n·|mean of the n whitened residuals|² (one row per frame): D² of their mean."""
    zm = z.mean(axis=0)
    return z.shape[0] * float(zm @ zm)


def fit_calibration(
    residuals: np.ndarray, groups: Sequence[int], *, weak: Sequence[bool] | None = None, method: str = "default",
    alpha: float = DEFAULT_ALPHA, folds: int = 5, source: str = "", fingerprint: Sequence[float] | None = None,
) -> Calibration:
    """Calibration from the feature residuals of frames that match their lens.

    Parameters
    ----------
    residuals : ndarray (N, 6)
        f(estimate) − f(true field) per calibration frame (:func:`frame_features`).
    groups : sequence of int
        The photograph each frame was made from: folds never split a photograph, so
        the held-out null is of photographs the whitening has not seen.
    weak : sequence of bool, optional
        Which frames' estimates were too weak for a verdict (:func:`is_weak`).
    method, alpha, source, fingerprint
        Recorded in the calibration (see :class:`Calibration`).
    folds : int
        Folds of the held-out null.

    Returns
    -------
    Calibration

    Raises
    ------
    ForensicsError
        Too few frames or photographs, or a degenerate spread.
    """
    r = np.asarray(residuals, dtype=np.float64)
    g = np.asarray(groups)
    k = len(FEATURE_NAMES)
    if weak is not None and len(weak) != len(r):
        raise ForensicsError("calibration needs one weak flag per frame")
    if r.ndim != 2 or r.shape[1] != k or len(g) != len(r) or not np.all(np.isfinite(r)):
        raise ForensicsError(f"calibration needs an N×{k} array of finite residuals and a photograph per row")
    uniq = np.unique(g)
    if uniq.size < max(folds, 10) or len(r) < 5 * k:
        raise ForensicsError(f"calibration needs at least {max(folds, 10)} photographs and {5 * k} frames, "
                             f"got {uniq.size} and {len(r)}")
    # photographs to folds by a fixed shuffle, so every fold mixes sources
    z = held_out_whitened(r, g, folds)
    mu = r.mean(axis=0)
    cov = np.cov(r.T)
    return Calibration(
        method=method, mean=tuple(float(v) for v in mu), covariance=tuple(tuple(float(v) for v in row) for row in cov),
        null=tuple(tuple(float(v) for v in row) for row in z), null_groups=tuple(int(v) for v in g),
        null_weak=tuple(bool(v) for v in weak) if weak is not None else (),
        alpha=float(alpha), n_frames=len(r), n_images=int(uniq.size), source=source,
        fingerprint=tuple(float(v) for v in fingerprint) if fingerprint is not None else None,
    )


@functools.lru_cache(maxsize=1)
def default_calibration() -> Calibration:
    """The calibration shipped with vigproc (package data; made by the command in its
    ``source`` field)."""
    try:
        text = resources.files("vigproc.data").joinpath(SHIPPED_CALIBRATION).read_text(encoding="utf-8")
    except (FileNotFoundError, OSError):
        raise ForensicsError("the shipped forensics calibration is missing; make one with "
                             "'vigproc forensics calibrate --images DIR -o FILE'") from None
    return Calibration.from_dict(json.loads(text))


def _fingerprint_image() -> np.ndarray:
    """A fixed synthetic frame (smooth log-normal texture × a Table 1-like field)."""
    rng = np.random.default_rng(2010)
    h, w = 96, 144
    f = np.fft.rfft2(rng.normal(size=(h, w)))
    fy, fx = np.fft.fftfreq(h)[:, None], np.fft.rfftfreq(w)[None, :]
    f /= np.maximum(np.hypot(fx, fy), 1.0 / w) ** 0.9
    tex = np.fft.irfft2(f, s=(h, w))
    y, x = np.mgrid[0:h, 0:w]
    q = ((x - w / 2) ** 2 + (y - h / 2) ** 2) / (0.6 * w) ** 2
    return 0.4 * np.exp(0.2 * tex / tex.std()) / (1.0 + q) ** 2


@functools.lru_cache(maxsize=8)
def estimator_fingerprint(method: str = "default") -> tuple[float, ...]:
    """Features of the estimate of a fixed synthetic frame: a change of the estimator
    (settings, scene prior) changes it, and then the calibration is stale."""
    from vigproc.core.estimate import estimate

    m = estimate(_fingerprint_image(), forensic_method(method), channel_axis=None)
    return tuple(round(float(v), 4) for v in frame_features(_fit_of(m)))


def _warn_if_stale(cal: Calibration, method: str) -> None:
    if cal.fingerprint is not None:
        _check_fingerprint(tuple(cal.fingerprint), method, cal.source)


@functools.lru_cache(maxsize=8)
def _check_fingerprint(fingerprint: tuple[float, ...], method: str, source: str) -> bool:
    """Whether the estimator still gives the calibration's fingerprint (warns once if not)."""
    try:
        now = np.asarray(estimator_fingerprint(method))
    except VigprocError:
        return True
    if np.max(np.abs(now - np.asarray(fingerprint))) > 0.02:
        log.warning("the forensics calibration was made with a different version of the %r estimator; "
                    "its false-alarm probabilities may be off (recalibrate: %s)", method,
                    source or "vigproc forensics calibrate")
        return False
    return True


# ------------------------------------------------------------------ the expected model
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
    from vigproc.core.normalised import denormalise

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
    big_r = _half_diagonal(fit.width, fit.height)
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
        from vigproc.core.lensfamily import default_family
        from vigproc.forensics.lensmatch import reference_coefficients

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
    from vigproc.core.family_fit import field_spread_ev, profile_to_model
    from vigproc.core.model import FitQuality

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
    from vigproc.forensics.lensmatch import beyond_scene_limit, reference_coefficients, scene_d2, whiten

    alpha = calibration.alpha if alpha is None else float(alpha)
    fit = _fit_of(estimate)
    rings = ring_falloff(fit)
    big_r = _half_diagonal(fit.width, fit.height)
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
    from vigproc.core.pixels import check_image as valid_image
    from vigproc.core.pixels import luminance
    from vigproc.core.lensfamily import default_family
    from vigproc.core.family_fit import colour_of
    from vigproc.forensics.lensmatch import default_match_calibration, frame_fit

    cal = calibration if calibration is not None else default_match_calibration()
    fam = family if family is not None else default_family()
    cal.check_family(fam)
    a = valid_image(img, -1 if np.asarray(img).ndim == 3 else None)
    lum = luminance(a)
    h, w = lum.shape
    colour = colour_of(a)
    fc = frame_fit(lum, fam, colour=colour)
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
        from vigproc.core.model import FitQuality

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
    import dataclasses

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
    import dataclasses

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
    from vigproc.forensics.lensmatch import default_match_calibration, pooled_d2

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
