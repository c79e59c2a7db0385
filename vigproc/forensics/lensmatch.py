"""Lens-mismatch test in the lens family: does a frame's fall-off match the claimed lens?

Real lenses' fall-offs span a two-dimensional family (:mod:`vigproc.core.lensfamily`), so
a frame and a claimed lens can be compared in two coefficients rather than in the
features of a twelve-parameter fit:

1. **The frame's data alone** (:func:`luminance_family_fit`: :func:`vigproc.core.family_fit.frame_coefficients`,
   the first :data:`~vigproc.core.lensfamily.N_COMPONENTS` components, no prior). The
   data term is equivariant: a field of the family multiplied onto a frame moves the
   fit by exactly its coefficients, so what a frame gets wrong is its scene's, the same
   whatever lens took it. (An estimate under the family prior would be shrunk towards
   the prior's mean, most for the strongest lenses, and its error would depend on the
   lens.)
2. **The claimed lens in the family** (:func:`reference_coefficients`): its log field
   projected onto the family by least squares over the frame (a free constant: a gain
   is not vignetting).
3. **Mahalanobis distance** D² = (r − μ)ᵀ Σ⁻¹ (r − μ) of r = c_frame − c_lens, where μ
   and Σ are the *scenes'* bias and scatter of the coefficients, measured on
   vignetting-free camera frames × lensfun fields (:class:`MatchCalibration`; the
   clean protocol of ``vigproc bench clean``). The fit's own jackknife covariance is far
   smaller than that scatter and ranks frames worse (measured, see
   docs/benchmarks/forensics.md), so it is not used.
4. **False-alarm probability**: the share of held-out calibration frames (5-fold by
   photograph) with a D² at least as large, an empirical p-value.
4b. **A single frame no lens explains is left undecided** (:func:`scene_d2`): when its
   fit is further from lensfun's lenses, seen through a scene's scatter, than a frame of
   a lens would be once in 1 / :data:`SCENE_GATE_P` frames (were lenses and scenes
   Gaussian with the measured spreads: a χ² quantile), its own light shaped the
   estimate (a sunset's radial glow, a scene that brightens towards its corners), and
   comparing it with the claimed lens would judge the scene. On the clean protocol a
   few such scenes make most of a single frame's errors (without the three worst of 51
   photographs the mismatch AUC at ≥ 0.3 EV goes 0.932 -> 0.973); the gate leaves 4 %
   of genuine frames undecided (docs/benchmarks/forensics.md). Sets of frames are
   pooled by their median, which one such frame moves by one rank, and keep them all.
5. **Several frames** of one claimed lens: the coordinate-wise median of their whitened
   residuals z̄, statistic n·|z̄|², against medians of n calibration frames from
   different photographs, each set shifted by one draw of the calibration centre's own
   sampling error (a set shares that error; n frames do not average it away) (the median, as lens profiles pool their frames,
   :mod:`vigproc.core.pooling`: one fooled frame moves it by one rank).

References
----------
S. Lyu, "Estimating Vignetting Function from a Single Image for Image Authentication",
ACM MM&Sec 2010 (vignetting as forensic evidence).
Y. Zheng et al., "Single-image vignetting correction from gradient distribution
symmetries", IEEE TPAMI 35(6), 2013 (the per-frame data term).
P. C. Mahalanobis, "On the generalized distance in statistics", 1936.
"""

from __future__ import annotations

import functools
import json
import logging
import math
from dataclasses import dataclass, field, replace
from importlib import resources
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from vigproc.atomic import atomic_write_text
from vigproc.core.lensfamily import default_family
from vigproc.core.pixels import binned_coords, binned_log_channels, binned_log_copy
from vigproc.errors import EXIT_CODES, VigprocError

log = logging.getLogger(__name__)

__all__ = [
    "GaussianNull",
    "MatchCalibration",
    "MatchCalibrationError",
    "beyond_scene_limit",
    "default_match_calibration",
    "family_fingerprint",
    "fit_match_calibration",
    "luminance_family_fit",
    "pooled_d2",
    "reference_coefficients",
    "scene_d2",
    "whiten",
]

#: The schema of a calibration file.
MATCH_SCHEMA = "vigproc.lensmatch-calibration/1"
#: The shipped calibration (package data).
SHIPPED_MATCH_CALIBRATION = "lensmatch_calibration.json"
#: Default false-alarm probability below which a frame is inconsistent with its lens.
DEFAULT_ALPHA = 0.01
#: Draws of a multi-frame null distribution.
NULL_DRAWS = 4000
#: The spread of a median relative to the standard deviation of a Gaussian sample's
#: mean (sqrt(pi/2)): the sampling error of the calibration's centre.
MEDIAN_EFFICIENCY = math.sqrt(math.pi / 2)
#: A calibration's ``scene_limit`` is the χ² quantile (its components' degrees of
#: freedom) that a frame of a lens exceeds with this probability were lenses and scenes
#: Gaussian. Their tails are heavier: on the clean protocol 0.001 leaves 4.3 % of
#: genuine frames and 2.7 % of forged claims undecided (mismatch AUC at ≥ 0.3 EV 0.953
#: over the rest); 0.01 leaves 7.0 % / 4.7 % (0.955); a limit at the calibration
#: frames' own 99th percentile left the one sunset of each half's 25 photographs half
#: inside its null (0.951, a script).
SCENE_GATE_P = 0.001
#: Grid (rows) on which a claimed lens's field is projected onto the family.
_PROJECTION_ROWS = 48


class MatchCalibrationError(VigprocError):
    """The lens-mismatch calibration is missing, invalid or made for another family."""

    exit_code = EXIT_CODES["forensics"]


def family_fingerprint(family) -> tuple[float, ...]:
    """A few numbers that change when the family does: its size, and each component's
    sum and corner value (a calibration holds for the family it was made in)."""
    comps = np.asarray(family.components, dtype=np.float64)
    return tuple([float(comps.shape[0])] + [round(float(v), 4) for c in comps for v in (c.sum(), c[-1])])


def luminance_family_fit(lum: np.ndarray, family=None, settings=None, colour: np.ndarray | None = None):
    """The family coefficients of an H×W linear luminance frame from its data alone
    (with ``colour``, H×W×3, its pairs weighted by how alike their channels change).

    Returns
    -------
    FrameCoefficients or None
        :func:`vigproc.core.family_fit.frame_coefficients` on the frame's working copy; None
        when too few pixels are usable.
    """
    from vigproc.core.family_fit import EVIDENCE_SETTINGS, frame_coefficients

    s = settings or EVIDENCE_SETTINGS  # the covariance its shipped calibration read
    fam = family or default_family()
    h, w = lum.shape
    L, valid, k = binned_log_copy(lum, s.work_size, s.dark_fraction, None)
    channels = None if colour is None else binned_log_channels(colour[..., :3], k, valid, s.dark_fraction)
    return frame_coefficients(L, valid, binned_coords(w, k), binned_coords(h, k), w, h, s, fam, channels=channels)


def _projection_grid(width: int, height: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    rows = min(_PROJECTION_ROWS, height)
    cols = max(2, round(rows * width / height))
    x = np.linspace(-(width - 1) / 2, (width - 1) / 2, cols)
    y = np.linspace(-(height - 1) / 2, (height - 1) / 2, rows)
    rho = np.hypot(x[None, :], y[:, None]) / math.hypot((width - 1) / 2, (height - 1) / 2)
    return x, y, rho


def reference_coefficients(model, width: int, height: int, family=None) -> np.ndarray:
    """A lens's vignetting (any :class:`~vigproc.core.model.VignettingModel`) as family
    coefficients: least squares of its natural-log field over a grid of the
    ``width``×``height`` frame, against the family's mean + components and a constant."""
    fam = family or default_family()
    x, y, rho = _projection_grid(width, height)
    target = np.asarray(model.log_field_at(x[None, :], y[:, None]), dtype=np.float64)
    mean, basis = fam.profiles(rho)
    a = np.column_stack([np.ones(rho.size), basis.reshape(-1, fam.n_components)])
    sol, *_ = np.linalg.lstsq(a, (target - mean).ravel(), rcond=None)
    return sol[1:]


def whitener(cov: np.ndarray) -> np.ndarray:
    """L⁻¹ with Σ = L Lᵀ (Cholesky, with a tiny ridge for a near-singular Σ)."""
    cov = 0.5 * (cov + cov.T)
    ridge = 1e-9 * float(np.trace(cov)) / cov.shape[0]
    return np.linalg.inv(np.linalg.cholesky(cov + ridge * np.eye(cov.shape[0])))


def held_out_whitened(r: np.ndarray, groups: np.ndarray, folds: int, centre=np.mean) -> np.ndarray:
    """Each row whitened by the centre and covariance of the other folds, photographs
    (``groups``) assigned to folds by a fixed shuffle: a null of frames the whitening
    has not seen (k-fold cross-validation by photograph)."""
    uniq = np.unique(groups)
    order = np.random.default_rng(0).permutation(uniq.size)
    fold_of = dict(zip(uniq[order], np.arange(uniq.size) % folds))
    fold = np.array([fold_of[v] for v in groups])
    z = np.empty_like(r)
    for f in range(folds):
        out = fold == f
        z[out] = (r[out] - centre(r[~out], axis=0)) @ whitener(np.atleast_2d(np.cov(r[~out].T))).T
    return z


def pooled_null(z: np.ndarray, groups: np.ndarray, n_frames: int, statistic, *, seed: int,
                draws: int = NULL_DRAWS, shift_spread: float = 0.0) -> np.ndarray:
    """Sorted ``statistic`` of ``draws`` sets of ``n_frames`` rows of ``z``, each set from
    different photographs (``groups``; one row of each): the null of a test pooling
    frames of different scenes. The draws are fixed by ``seed``, so a p-value is the
    same every run. The caller checks that there are ``n_frames`` photographs.

    ``shift_spread``: each set is shifted by one draw of N(0, shift_spread²) per
    coordinate (its own stream, ``seed + 1``): an error that every frame of a set shares,
    such as the calibration centre's sampling error, which n frames do not average away.

    Parameters
    ----------
    z : ndarray (N, K)
        The whitened null rows.
    groups : ndarray (N,)
        The photograph of each row.
    n_frames : int
        Rows per set.
    statistic : callable
        Called once with the stack of all sets, shape (draws, n_frames, K); returns one
        value per set, shape (draws,) (:func:`pooled_d2` and the ring test's mean D²
        take a stack).
    seed : int
        The draws' seed.
    draws : int
        Number of sets.
    shift_spread : float
        See above; 0 adds no shift.

    Returns
    -------
    ndarray (draws,)
        The statistics, sorted.
    """
    g = np.asarray(groups)
    uniq = np.unique(g)
    by_group = [np.flatnonzero(g == u) for u in uniq]
    sizes = np.array([b.size for b in by_group], dtype=np.int64)
    first = np.concatenate([[0], np.cumsum(sizes)[:-1]])
    members = np.concatenate(by_group)
    rows = _distinct_group_rows(sizes, first, members, n_frames, seed, draws)
    sample = z[rows]
    if shift_spread > 0:
        # one K-vector per set, consecutive in the stream: the same values as K at a time
        shifts = np.random.default_rng(seed + 1).normal(0.0, shift_spread, (draws, z.shape[1]))
        sample = sample + shifts[:, None, :]
    out = np.asarray(statistic(sample), dtype=np.float64)
    out.sort()
    return out


#: Photographs above which NumPy's ``choice`` shuffles a tail instead of Floyd's
#: algorithm (:mod:`vigproc.core._kernels.draws` follows Floyd's only).
_FLOYD_MAX = 10_000


def _distinct_group_rows(sizes: np.ndarray, first: np.ndarray, members: np.ndarray, n_frames: int, seed: int,
                         draws: int) -> np.ndarray:
    """The rows of :func:`pooled_null`'s sets: per set, ``rng.choice(P, n_frames,
    replace=False)`` photographs, then ``rng.integers(sizes[picks])`` for one row of
    each, ``rng = default_rng(seed)`` -- the same numbers, drawn by a Numba kernel from
    the generator's raw outputs (NumPy's own calls above :data:`_FLOYD_MAX` photographs).

    Parameters
    ----------
    sizes, first : ndarray of int64 (P,)
        Each photograph's number of rows and the index of its first in ``members``.
    members : ndarray of int64
        Row indices, photograph by photograph.
    n_frames, seed, draws : int
        As :func:`pooled_null`'s.

    Returns
    -------
    ndarray of int64 (draws, n_frames)
    """
    rows = np.empty((draws, n_frames), dtype=np.int64)
    if sizes.size > _FLOYD_MAX:
        rng = np.random.default_rng(seed)
        for i in range(draws):
            picks = rng.choice(sizes.size, n_frames, replace=False)
            rows[i] = members[first[picks] + rng.integers(sizes[picks])]
        return rows
    from vigproc.core._kernels.draws import distinct_group_rows  # Numba: not at import

    need = draws * (2 * n_frames + 2) + 64  # 32-bit draws per set: about 3 n, two a raw output
    while not distinct_group_rows(np.random.default_rng(seed).bit_generator.random_raw(need), sizes, first,
                                  members, n_frames, rows):
        need *= 2  # many rejections: rare
    return rows


def empirical_p(null: np.ndarray, statistic: float) -> float:
    """False-alarm probability of ``statistic`` against a sorted null sample:
    (k + 1)/(N + 1) with k of the N at least as large (never exactly 0 from a finite
    sample)."""
    k = null.size - int(np.searchsorted(null, float(statistic), side="left"))
    return (k + 1.0) / (null.size + 1.0)


class GaussianNull:
    """The Gaussian part of a calibration's null, stored as its ``mean`` and ``covariance``
    fields (tuples, as in its file), read as arrays: the lens-mismatch test's
    (:class:`MatchCalibration`) and the ring test's
    (:class:`vigproc.forensics.rings.Calibration`)."""

    mean: tuple[float, ...]
    covariance: tuple[tuple[float, ...], ...]

    @property
    def mean_vector(self) -> np.ndarray:
        """The mean, shape (k,)."""
        return np.asarray(self.mean, dtype=np.float64)

    @property
    def covariance_matrix(self) -> np.ndarray:
        """The covariance, shape (k, k)."""
        return np.asarray(self.covariance, dtype=np.float64)


@dataclass(frozen=True)
class MatchCalibration(GaussianNull):
    """The scenes' scatter of the family coefficients, and the test's null distribution.

    Attributes
    ----------
    mean : tuple of float
        μ: median over calibration frames of c_frame − c_lens (the scenes' bias).
    covariance : tuple of tuple of float
        Σ: their covariance.
    null : tuple of tuple of float
        Whitened held-out residuals L⁻¹(r − μ_k), Σ_k = L Lᵀ fitted on the other folds
        (5-fold by photograph): D² of a matching frame is distributed as their squared
        norms.
    null_groups : tuple of int
        The photograph of each ``null`` row (multi-frame draws take distinct ones).
    family : tuple of float
        :func:`family_fingerprint` of the family the coefficients are in.
    alpha : float
        False-alarm probability below which a frame is called inconsistent.
    n_frames, n_images : int
    source : str
        The command that made it.
    grey_inflate : float
        Σ's scale for a grey frame: its fit has no colour to weigh pairs by, so the
        scenes scatter it more (the ratio of the mean D² of the calibration frames' grey
        and colour fits; 1 when the calibration was made on grey frames).
    scene_limit : float or None
        The :func:`scene_d2` above which a single frame's fit is unlike any lens's and
        the test leaves it undecided (:data:`SCENE_GATE_P`). None (a calibration made
        before it, or without the frames' own coefficients): no frame is left out.
    scene_share : float or None
        The share of the calibration's own frames (genuine, each with its lens) beyond
        ``scene_limit``: how often a genuine frame is left undecided, measured (scenes are
        not Gaussian: it is far above SCENE_GATE_P).
    """

    mean: tuple[float, ...]
    covariance: tuple[tuple[float, ...], ...]
    null: tuple[tuple[float, ...], ...]
    null_groups: tuple[int, ...]
    family: tuple[float, ...]
    alpha: float = DEFAULT_ALPHA
    n_frames: int = 0
    n_images: int = 0
    source: str = ""
    grey_inflate: float = 1.0
    scene_limit: float | None = None
    scene_share: float | None = None
    _cache: dict = field(default_factory=dict, init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        try:
            mu = np.asarray(self.mean, dtype=np.float64)
            cov = np.asarray(self.covariance, dtype=np.float64)
            z = np.asarray(self.null, dtype=np.float64)
        except (TypeError, ValueError):
            raise MatchCalibrationError("lens-mismatch calibration: non-numeric arrays") from None
        k = mu.size
        if mu.shape != (k,) or k < 1 or cov.shape != (k, k) or z.ndim != 2 or z.shape[1] != k \
                or not all(np.all(np.isfinite(a)) for a in (mu, cov, z)):
            raise MatchCalibrationError("lens-mismatch calibration: mean, covariance and null must be finite "
                                        "arrays of one dimension")
        if not np.allclose(cov, cov.T, rtol=1e-6, atol=1e-12) or np.linalg.eigvalsh(cov)[0] <= 0:
            raise MatchCalibrationError("lens-mismatch calibration: covariance is not symmetric positive definite")
        if len(z) < 20 or len(self.null_groups) != len(z):
            raise MatchCalibrationError("lens-mismatch calibration: needs at least 20 null rows, each with its "
                                        "photograph")
        if not 0.0 < float(self.alpha) < 1.0:
            raise MatchCalibrationError(f"lens-mismatch calibration: alpha must be within (0, 1), got {self.alpha}")
        if not (math.isfinite(float(self.grey_inflate)) and float(self.grey_inflate) > 0):
            raise MatchCalibrationError(f"lens-mismatch calibration: grey_inflate must be positive, got "
                                        f"{self.grey_inflate}")
        if self.scene_limit is not None and not (math.isfinite(float(self.scene_limit))
                                                 and float(self.scene_limit) > 0):
            raise MatchCalibrationError(f"lens-mismatch calibration: scene_limit must be positive, got "
                                        f"{self.scene_limit}")
        if self.scene_share is not None and not 0.0 <= float(self.scene_share) <= 1.0:
            raise MatchCalibrationError(f"lens-mismatch calibration: scene_share must be within [0, 1], got "
                                        f"{self.scene_share}")

    @property
    def n_components(self) -> int:
        return len(self.mean)

    def check_family(self, family) -> None:
        """Raise when the calibration was made in another family than ``family``."""
        if tuple(self.family) != family_fingerprint(family):
            raise MatchCalibrationError("the lens-mismatch calibration was made in another lens family; "
                                        "recalibrate (vigproc bench forensics-clean --calibrate FILE)")

    def null_d2(self, n_frames: int = 1) -> np.ndarray:
        """Sorted statistics of matching frames: |z|² for one frame, n·|median of n z|²
        for ``n_frames`` frames of different photographs (fixed draws)."""
        n = int(n_frames)
        if n in self._cache:
            return self._cache[n]
        z = np.asarray(self.null, dtype=np.float64)
        if n <= 1:
            out = np.sort(np.einsum("ij,ij->i", z, z))
        else:
            g = np.asarray(self.null_groups)
            uniq = np.unique(g)
            if uniq.size < n:
                raise MatchCalibrationError(f"the calibration has {uniq.size} photographs, too few for "
                                            f"{n}-frame evidence")
            # The centre μ is the median of the calibration's photographs, so a set of
            # frames sees it off by its sampling error, the same for every frame of the
            # set: n frames shrink their own scatter, not that offset. Each draw adds one
            # offset of the median's spread, 1.2533/sqrt(photographs) in whitened units.
            out = pooled_null(z, g, n, pooled_d2, seed=2010 + n,
                              shift_spread=MEDIAN_EFFICIENCY / math.sqrt(uniq.size))
        self._cache[n] = out
        return out

    def p_value(self, d2: float, n_frames: int = 1) -> float:
        """False-alarm probability (k + 1)/(N + 1): k of the N null statistics are at
        least ``d2``."""
        return empirical_p(self.null_d2(n_frames), d2)

    # -- files --------------------------------------------------------------
    def to_dict(self) -> dict[str, Any]:
        return {"schema": MATCH_SCHEMA, "family": list(self.family), "mean": list(self.mean),
                "covariance": [list(r) for r in self.covariance], "alpha": self.alpha,
                "n_frames": self.n_frames, "n_images": self.n_images, "source": self.source,
                "grey_inflate": round(float(self.grey_inflate), 4),
                **({} if self.scene_limit is None else {"scene_limit": round(float(self.scene_limit), 4)}),
                **({} if self.scene_share is None else {"scene_share": round(float(self.scene_share), 4)}),
                "null_groups": list(self.null_groups), "null": [[round(v, 5) for v in r] for r in self.null]}

    @classmethod
    def from_dict(cls, d: Any) -> MatchCalibration:
        if not isinstance(d, dict) or d.get("schema") != MATCH_SCHEMA:
            raise MatchCalibrationError(f"not a lens-mismatch calibration (schema {MATCH_SCHEMA!r} expected)")
        try:
            return cls(mean=tuple(float(v) for v in d["mean"]),
                       covariance=tuple(tuple(float(v) for v in r) for r in d["covariance"]),
                       null=tuple(tuple(float(v) for v in r) for r in d["null"]),
                       null_groups=tuple(int(v) for v in d["null_groups"]),
                       family=tuple(float(v) for v in d["family"]), alpha=float(d.get("alpha", DEFAULT_ALPHA)),
                       n_frames=int(d.get("n_frames", 0)), n_images=int(d.get("n_images", 0)),
                       source=str(d.get("source", "")), grey_inflate=float(d.get("grey_inflate", 1.0)),
                       scene_limit=None if d.get("scene_limit") is None else float(d["scene_limit"]),
                       scene_share=None if d.get("scene_share") is None else float(d["scene_share"]))
        except (KeyError, TypeError, ValueError) as exc:
            raise MatchCalibrationError(f"invalid lens-mismatch calibration: {exc!r}") from None

    def save(self, path: str | Path) -> None:
        atomic_write_text(Path(path), json.dumps(self.to_dict(), separators=(",", ":")) + "\n")


def whiten(residual: np.ndarray, calibration: MatchCalibration, *, add_bias: bool = True,
           inflate: float = 1.0) -> np.ndarray:
    """z = L⁻¹(r − μ) with Σ·``inflate`` = L Lᵀ; without ``add_bias`` μ is not subtracted
    (a learned profile already holds the scenes' median bias)."""
    r = np.asarray(residual, dtype=np.float64)
    if add_bias:
        r = r - calibration.mean_vector
    return whitener(calibration.covariance_matrix * float(inflate)) @ r


def scene_d2(coefficients: np.ndarray, calibration: MatchCalibration, family, *, inflate: float = 1.0) -> float:
    """How unlike any lens's fall-off a frame's data-only fit is (module doc, step 4b).

    D² = eᵀ Q⁻¹ e, e = c − μ − m, Q = Σ·``inflate`` + C: the frame's coefficients c
    less the scenes' bias μ against lensfun's calibrations, whose spread in the family
    is N(m, C) (:meth:`~vigproc.core.lensfamily.LensFamily.prior`), each seen through a
    scene's scatter Σ. It asks nothing of the claimed lens: a frame that no lens
    explains is one whose scene shaped its fit.

    Parameters
    ----------
    coefficients : ndarray (K,)
        :func:`luminance_family_fit`'s coefficients.
    calibration : MatchCalibration
    family : LensFamily
        The family the calibration was made in.
    inflate : float
        Σ's scale (a grey frame's: ``calibration.grey_inflate``).

    Returns
    -------
    float
    """
    m, cov = family.prior()
    k = calibration.n_components
    e = np.asarray(coefficients, dtype=np.float64) - calibration.mean_vector - m[:k]
    q = calibration.covariance_matrix * float(inflate) + cov[:k, :k]
    return float(e @ np.linalg.solve(q, e))


def beyond_scene_limit(scene: float | None, limit: float | None) -> bool:
    """Whether a single frame of scene D² ``scene`` (:func:`scene_d2`) is left undecided
    by a calibration's ``scene_limit`` (None: no limit, or no D²)."""
    return scene is not None and limit is not None and scene > limit


def pooled_d2(z: np.ndarray):
    """n·|coordinate-wise median of the n whitened residuals|² (one row per frame).

    Parameters
    ----------
    z : ndarray (n, K) or (m, n, K)
        One set of rows, or a stack of ``m`` sets.

    Returns
    -------
    float or ndarray (m,)
        The statistic of the set, or of each set of the stack.
    """
    z = np.asarray(z, dtype=np.float64)
    if z.ndim == 3:
        med = np.median(z, axis=1)
        n = z.shape[1]
        return np.array([float(n * m @ m) for m in med])
    z = np.atleast_2d(z)
    med = np.median(z, axis=0)
    return float(z.shape[0] * med @ med)


def fit_match_calibration(residuals: np.ndarray, groups: Sequence[int], family, *, alpha: float = DEFAULT_ALPHA,
                          folds: int = 5, source: str = "",
                          coefficients: np.ndarray | None = None) -> MatchCalibration:
    """A :class:`MatchCalibration` from the residuals c_frame − c_lens of frames that match
    their lens.

    Parameters
    ----------
    residuals : ndarray (N, K)
    groups : sequence of int
        The photograph each row was made from: folds never split one.
    family : LensFamily
        The family the coefficients are in (recorded by its fingerprint).
    alpha, folds, source
    coefficients : ndarray (N, K), optional
        The same frames' own coefficients c_frame: the calibration then sets its
        ``scene_limit`` (:data:`SCENE_GATE_P`, :func:`scene_d2`).

    Raises
    ------
    MatchCalibrationError
        Too few photographs or rows, or a degenerate scatter.
    """
    r = np.asarray(residuals, dtype=np.float64)
    g = np.asarray(groups)
    if r.ndim != 2 or len(g) != len(r) or not np.all(np.isfinite(r)):
        raise MatchCalibrationError("calibration needs an N×K array of finite residuals and a photograph per row")
    uniq = np.unique(g)
    if uniq.size < max(folds, 10) or len(r) < 20:
        raise MatchCalibrationError(f"calibration needs at least {max(folds, 10)} photographs and 20 frames, "
                                    f"got {uniq.size} and {len(r)}")
    if coefficients is not None and np.shape(coefficients) != r.shape:
        raise MatchCalibrationError(f"calibration needs the frames' coefficients in the residuals' shape {r.shape}, "
                                    f"got {np.shape(coefficients)}")
    z = held_out_whitened(r, g, folds, np.median)
    try:
        cal = MatchCalibration(
            mean=tuple(float(v) for v in np.median(r, axis=0)),
            covariance=tuple(tuple(float(v) for v in row) for row in np.atleast_2d(np.cov(r.T))),
            null=tuple(tuple(float(v) for v in row) for row in z), null_groups=tuple(int(v) for v in g),
            family=family_fingerprint(family), alpha=float(alpha), n_frames=len(r), n_images=int(uniq.size),
            source=source)
        if coefficients is None:
            return cal
        from scipy.stats import chi2

        # The null keeps every row, those beyond the limit too: conditioned on the gate
        # (a lighter tail) it let 1.9 % of decided genuine frames fall below α = 0.01 on
        # the clean protocol with 10 folds, against none unconditioned (bench forensics-clean).
        limit = float(chi2.isf(SCENE_GATE_P, cal.n_components))
        beyond = [beyond_scene_limit(scene_d2(c, cal, family), limit)
                  for c in np.asarray(coefficients, dtype=np.float64)]
        return replace(cal, scene_limit=limit, scene_share=float(np.mean(beyond)))
    except np.linalg.LinAlgError:
        raise MatchCalibrationError("degenerate scatter of the calibration frames") from None


@functools.lru_cache(maxsize=1)
def default_match_calibration() -> MatchCalibration:
    """The shipped calibration (package data, made by the command in its ``source``)."""
    try:
        text = resources.files("vigproc.data").joinpath(SHIPPED_MATCH_CALIBRATION).read_text(encoding="utf-8")
    except (FileNotFoundError, OSError):
        raise MatchCalibrationError("the shipped lens-mismatch calibration is missing; make one with "
                                    "'vigproc bench forensics-clean --calibrate FILE'") from None
    return MatchCalibration.from_dict(json.loads(text))


def load_match_calibration(path: str | Path) -> MatchCalibration:
    """The calibration in ``path``.

    Raises
    ------
    MatchCalibrationError
        Unreadable, not JSON, or not a lens-mismatch calibration.
    """
    try:
        d = json.loads(Path(path).read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, ValueError, RecursionError) as exc:
        raise MatchCalibrationError(f"cannot read calibration {path}: {exc}") from None
    return MatchCalibration.from_dict(d)
