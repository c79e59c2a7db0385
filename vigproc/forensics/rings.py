"""The ring test's statistic: a model's fall-off on rings, and the calibration that says how
far frames that truly match their lens stray from it.

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

from vigproc.atomic import atomic_write_text
from vigproc.errors import EXIT_CODES, SETTINGS, VigprocError
from vigproc.forensics.lensmatch import GaussianNull, MatchCalibration, empirical_p, held_out_whitened, pooled_null
from vigproc.core.model import VignettingModel, half_diagonal

__all__ = [
    "CALIBRATION_SCHEMA",
    "CENTRE",
    "CENTRE_FALLOFF_EV",
    "DEFAULT_ALPHA",
    "FALLOFF",
    "FAMILY_TEST_METHOD",
    "FEATURE_NAMES",
    "FORENSICS_METHOD",
    "MIN_CONFIDENCE",
    "NULL_DRAWS",
    "PRIOR_FRAMES",
    "RING_RADII",
    "SHIPPED_CALIBRATION",
    "Calibration",
    "default_calibration",
    "estimator_fingerprint",
    "fit_calibration",
    "forensic_method",
    "ForensicsError",
    "frame_features",
    "frame_quality",
    "load_calibration",
    "read_json",
    "ring_falloff",
]

log = logging.getLogger(__name__)

#: The estimator a check uses when asked for "default": the shipped calibration was
#: measured with it (vigproc's default before the lens-family fit). The lens-family
#: default needs its own calibration on vignetting-free frames first.
FORENSICS_METHOD = "robust"


#: Method name of the lens-family test's frame fit (the data term alone, no prior).
FAMILY_TEST_METHOD = "lens-family-data"


def forensic_method(method: str) -> str:
    """The estimator forensics runs for ``method`` ("default" → :data:`FORENSICS_METHOD`)."""
    return FORENSICS_METHOD if method == "default" else method


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
def ring_falloff(model: VignettingModel, radii: Sequence[float] = RING_RADII) -> np.ndarray:
    """Mean log2 φ (EV) of ``model`` on circles of radius ρ half-diagonals around the
    frame centre, over the parts of each circle inside the frame.

    Raises
    ------
    ModelError
        If G falls to zero on a ring.
    """
    w, h = model.width, model.height
    big_r = half_diagonal(w, h)
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
    big_r = half_diagonal(model.width, model.height)
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
class Calibration(GaussianNull):
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


def _mean_d2(z: np.ndarray):
    """n·|mean of the n whitened residuals|² (one row per frame): D² of their mean.

    Parameters
    ----------
    z : ndarray (n, K) or (m, n, K)
        One set of rows, or a stack of ``m`` sets.

    Returns
    -------
    float or ndarray (m,)
        The statistic of the set, or of each set of the stack.
    """
    if z.ndim == 3:
        n = z.shape[1]
        return np.array([n * float(m @ m) for m in z.mean(axis=1)])
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
