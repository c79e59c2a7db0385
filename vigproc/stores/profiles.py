"""Per-lens vignetting profiles: an embedded SQLite store that learns across frames.

A *profile* is the vignetting of one camera + lens at one focal-length bin, one
aperture bin and one frame aspect ratio (:class:`ProfileKey`).  It is stored in
frame-independent (normalised) units so that frames of any resolution of the same
sensor -- a RAW at full size, its half-size preview, a downscaled JPEG -- pool into
one profile (:func:`normalise`, :func:`denormalise`).

Learning
--------
Each frame's estimate (θ_i, Σ_i) is pooled in information form: the store keeps
Λ = Σ_i Σ_i⁻¹ and η = Σ_i Σ_i⁻¹ θ_i, and reports θ = Λ⁻¹ η with covariance Λ⁻¹
(the inverse-variance weighted mean).  The sums are kept *exactly* (every float64
is an integer multiple of a power of two, so they are accumulated as big
integers, see :class:`_Exact`): the result is the same whatever the order in which
concurrent workers add their frames.  Because one image's covariance understates
the frame-to-frame scatter (scene content biases each single-image estimate), the
store also keeps Welford running moments of θ and of the log2 field across frames
and reports that scatter (:attr:`Profile.scatter_sigma_ev`).  A profile is
*trusted* when it has at least :data:`TRUSTED_MIN_FRAMES` frames and its pooled
field uncertainty is below :data:`TRUSTED_SIGMA_EV` (its 2σ bound below
:data:`TRUSTED_BOUND_EV`): for a profile learned with frame evidence, the median's
σ (:mod:`vigproc.core.pooling`); without, the larger of the covariance-propagated σ and
scatter/√n.

Concurrency and durability
--------------------------
SQLite in WAL mode: readers never block the (single) writer and vice versa;
:meth:`ProfileStore.learn` is a read-modify-write inside ``BEGIN IMMEDIATE``, so
concurrent learners (daemon workers, CLI runs) serialise on the write lock and no
update is lost.  Every change is one transaction: the store is never half-written.

Files
-----
Profiles are exchanged as JSON files of schema ``vigproc.profile/1`` (documented in
``profiles/README.md``; examples in ``profiles/examples/``): :func:`export_profile`,
:func:`import_profile`, :meth:`ProfileStore.import_file`.

References
----------
S. Lyu, "Estimating Vignetting Function from a Single Image for Image
Authentication", ACM MM&Sec 2010 (the Kang-Weiss parameterisation used here).
B. P. Welford, "Note on a method for calculating corrected sums of squares and
products", Technometrics 4(3), 1962 (running moments).
J. R. Shewchuk, "Adaptive precision floating-point arithmetic and fast robust
geometric predicates", Discrete Comput. Geom. 18, 1997 (exact float summation;
here the simpler big-integer form of the same idea).
SQLite, "Write-Ahead Logging", https://www.sqlite.org/wal.html and
"Isolation in SQLite", https://www.sqlite.org/isolation.html.
"""

from __future__ import annotations

import builtins
import hashlib
import json
import logging
import math
import numbers
import os
import stat
import re
import sqlite3
import unicodedata
from dataclasses import dataclass, field, replace
from datetime import datetime, timezone
from fractions import Fraction
from pathlib import Path
from typing import Any, Callable, Sequence

import numpy as np

from vigproc.atomic import atomic_write_text
from vigproc.stores.db import SQLiteFile
from vigproc.errors import EXIT_CODES, SETTINGS, ModelError, VigprocError
from vigproc.io.exif import LensKey, normalise_text, unescape_key_part
from vigproc.core.colour import ColourPool
from vigproc.core.model import N_ALPHA, PARAM_NAMES, FitQuality, VignettingModel
from vigproc.core.normalised import (  # noqa: F401  (normalise, denormalise, fit_model_to_field: re-exported)
    FIELD_GRID,
    N_PARAMS,
    _field_and_jacobian,
    _field_sigma_ev,
    denormalise,
    fit_model_to_field,
    normalise,
)

__all__ = [
    "ANY",
    "DB_ENV",
    "FILE_SCHEMA",
    "FILE_SCHEMA_COLOUR",
    "FILE_SCHEMAS",
    "N_PARAMS",
    "PROVENANCES",
    "SCHEMA_VERSION",
    "TRUSTED_BOUND_EV",
    "TRUSTED_MIN_FRAMES",
    "TRUSTED_SIGMA_EV",
    "Profile",
    "ProfileKey",
    "ProfileStore",
    "ProfileStoreError",
    "Shots",
    "aperture_bin",
    "aspect_label",
    "default_db_path",
    "denormalise",
    "export_profile",
    "fixed_indices",
    "fit_model_to_field",
    "focal_bin",
    "frame_information",
    "import_profile",
    "normalise",
    "pool_information",
    "pool_mean",
]

logger = logging.getLogger(__name__)


class ProfileStoreError(VigprocError):
    """The profile store or a profile file cannot be used (corrupt, locked, invalid)."""

    exit_code = EXIT_CODES["profile_store"]
    blame = SETTINGS


# --------------------------------------------------------------------------- #
# constants
# --------------------------------------------------------------------------- #

#: Environment variable overriding the default database location.
DB_ENV = "VIGPROC_PROFILE_DB"
#: Schema tag of the human-readable profile files vigproc writes (``/2``: a parameter a
#: fit held fixed is listed in ``fixed`` and left out of the covariance).
FILE_SCHEMA = "vigproc.profile/2"
#: Schema of a profile file with a colour field (``colour``: a pooled
#: :class:`vigproc.core.colour.ColourPool`); a colourless profile is still written ``/2``.
FILE_SCHEMA_COLOUR = "vigproc.profile/3"
#: Schema tags vigproc reads (``/1``: a 12×12 covariance; an all-zero row and column
#: there is a fixed parameter, as learned profiles exported before ``/2`` wrote it).
FILE_SCHEMAS = ("vigproc.profile/1", FILE_SCHEMA, FILE_SCHEMA_COLOUR)
#: Where a profile came from.
PROVENANCES = ("learned", "lensfun", "user")
#: Bin label for a focal length / aperture the metadata does not give.
ANY = "any"

#: A profile is trusted (``--profile auto`` applies it instead of estimating) when twice
#: its pooled field uncertainty (RMS over the frame of the 1-σ uncertainty of log2 φ)
#: is below this bound, in EV: the bound its error then meets.  Measured on the clean
#: protocol (``vigproc bench profile-clean``: 20 lensfun lenses learning vignetting-free
#: bases, docs/benchmarks/profiles.md): see there how many frames trust takes and on
#: how many lenses the error then stays below the bound (the target is ≥ 90 %).  A
#: single frame's estimate errs by 0.086 EV (median) on the same protocol.
TRUSTED_BOUND_EV = 0.08
#: The 1-σ uncertainty below which a profile is trusted.
TRUSTED_SIGMA_EV = TRUSTED_BOUND_EV / 2
#: Bins a lookup interpolates across (:func:`interpolate_profiles`) are at most this far
#: apart: (octaves of focal length, stops of aperture).
INTERPOLATION_REACH = (2.0, 2.0)
#: ... and it was learned from at least this many frames (a scatter estimate needs
#: more than two).
TRUSTED_MIN_FRAMES = 3

#: Focal bins: f_k = 2^((k + FOCAL_OFFSET)/FOCAL_STEPS_PER_OCTAVE) mm, nearest in log.
FOCAL_STEPS_PER_OCTAVE = 4
#: Shift of the focal series by 1/16 octave: with it no common marked focal length
#: (8..800 mm: 10, 14, 16, 18, 24, 28, 35, 50, 70, 85, 105, 135, 200, ...) lies
#: within 1.2 % of a bin boundary (on the unshifted series 35 and 70 mm lie 0.4 %
#: from one), so EXIF rounding does not flip bins.
FOCAL_OFFSET = 0.25
#: Aperture bins: third stops N_k = 2^(k/6).
APERTURE_STEPS_PER_STOP = 3
#: Frames whose aspect ratio differs by more than this (relative) are a different key.
ASPECT_TOLERANCE = 0.01

#: Relative ridge added to the correlation matrix before inverting covariances.
RIDGE = 1e-10

#: Import sanity bounds (normalised units; R = half-diagonal).
MAX_ABS_CENTER = 2.0          # centre at most 2 half-diagonals from the frame centre
MAX_SHAPE = 1e3               # p ≤ 1e3 R⁻²: effective focal length ≥ 0.03 R
MAX_ABS_ALPHA = 1e3
MAX_FALLOFF_EV = 8.0          # φ ≥ 2⁻⁸ inside the frame
MAX_GAIN_EV = 1.0             # φ ≤ 2 inside the frame
MAX_FRAMES = 10**9
MAX_NOTES = 20_000
MAX_FILE_BYTES = 1 << 20
MAX_LENS_ID = 1000

#: Busy timeout (seconds) for the write lock held by another process.
DEFAULT_TIMEOUT = 30.0

_LN2 = math.log(2.0)


def _now() -> str:
    return datetime.now(timezone.utc).isoformat(timespec="milliseconds").replace("+00:00", "Z")


# --------------------------------------------------------------------------- #
# binning
# --------------------------------------------------------------------------- #

_FOCAL_RE = re.compile(r"^f=(\d+(?:\.\d)?)mm$")
_APERTURE_RE = re.compile(r"^N=(\d+\.\d)$")
_ASPECT_RE = re.compile(r"^(?:(\d+):(\d+)|a=(\d+\.\d{3}))$")

# Nominal third-stop f-numbers, labels of N_k = 2^(k/6) for k = 0..42.
_NOMINAL_APERTURES = (
    1.0, 1.1, 1.2, 1.4, 1.6, 1.8, 2.0, 2.2, 2.5, 2.8, 3.2, 3.5, 4.0, 4.5, 5.0, 5.6, 6.3, 7.1,
    8.0, 9.0, 10.0, 11.0, 13.0, 14.0, 16.0, 18.0, 20.0, 22.0, 25.0, 29.0, 32.0, 36.0, 40.0,
    45.0, 51.0, 57.0, 64.0, 72.0, 80.0, 90.0, 101.0, 114.0, 128.0,
)
# Named frame aspect ratios (landscape; portrait is the inverse, e.g. "2:3").
_NAMED_ASPECTS = ((1, 1), (5, 4), (4, 3), (7, 5), (3, 2), (16, 10), (5, 3), (16, 9), (2, 1), (21, 9), (65, 24), (3, 1))


def _focal_index(focal_mm: float) -> int:
    return round(FOCAL_STEPS_PER_OCTAVE * math.log2(focal_mm) - FOCAL_OFFSET)


def _focal_centre(k: int) -> float:
    return 2.0 ** ((k + FOCAL_OFFSET) / FOCAL_STEPS_PER_OCTAVE)


def _focal_label(k: int) -> str:
    return f"f={_focal_centre(k):.1f}mm"


def focal_bin(focal_mm: float | None) -> str:
    """Focal-length bin label: the nearest (in log) step of the series 2^((k+¼)/4) mm.

    Steps are a quarter octave (×1.19): finer than the change of vignetting across
    the marked steps of a zoom.  None gives :data:`ANY`.

    Examples
    --------
    >>> focal_bin(24.0), focal_bin(25.0), focal_bin(35.0), focal_bin(None)
    ('f=23.6mm', 'f=23.6mm', 'f=33.4mm', 'any')
    """
    if focal_mm is None:
        return ANY
    f = float(focal_mm)
    if not (math.isfinite(f) and f > 0):
        raise ProfileStoreError(f"focal length must be a positive number of mm, got {focal_mm!r}")
    return _focal_label(_focal_index(f))


def _aperture_index(fnumber: float) -> int:
    return round(2 * APERTURE_STEPS_PER_STOP * math.log2(fnumber))


def _aperture_label(k: int) -> str:
    if 0 <= k < len(_NOMINAL_APERTURES):
        return f"N={_NOMINAL_APERTURES[k]:.1f}"
    return f"N={2.0 ** (k / (2 * APERTURE_STEPS_PER_STOP)):.1f}"


def aperture_bin(fnumber: float | None) -> str:
    """Aperture bin label: the nearest third stop N = 2^(k/6), labelled by its nominal value.

    Examples
    --------
    >>> aperture_bin(4.0), aperture_bin(4.5), aperture_bin(5.6), aperture_bin(None)
    ('N=4.0', 'N=4.5', 'N=5.6', 'any')
    """
    if fnumber is None:
        return ANY
    n = float(fnumber)
    if not (math.isfinite(n) and n > 0):
        raise ProfileStoreError(f"f-number must be a positive number, got {fnumber!r}")
    return _aperture_label(_aperture_index(n))


def aspect_label(aspect: float) -> str:
    """Aspect-ratio (W/H) label: a named ratio ("3:2", "2:3", "4:3", ...) when within
    ±1 % (or when its cell of the grid below is), else ``"a=<W/H>"`` on a 2 %
    logarithmic grid.

    Portrait frames get their own label: a frame rotated by an unknown ±90° cannot be
    mapped onto the landscape profile (the sign of cx or cy would be a guess).
    """
    a = float(aspect)
    if not (math.isfinite(a) and a > 0):
        raise ProfileStoreError(f"aspect ratio must be positive, got {aspect!r}")
    k = round(math.log(a) / math.log(1.02))
    # a grid cell whose value is a named ratio's is that ratio too: its label must read
    # back as itself (a 3000x2030 frame's cell, a=1.486, is 3:2's; it was refused)
    for value in (a, 1.02**k):
        for w, h in _NAMED_ASPECTS:
            for num, den in ((w, h), (h, w)):
                if abs(math.log(value * den / num)) <= math.log1p(ASPECT_TOLERANCE):
                    return f"{num}:{den}"
    return f"a={1.02 ** k:.3f}"


def _aspect_value(label: str) -> float:
    m = _ASPECT_RE.match(label)
    if not m:
        raise ProfileStoreError(f"invalid aspect label {label!r} (expected e.g. '3:2' or 'a=1.234')")
    if m.group(3):
        return float(m.group(3))
    return int(m.group(1)) / int(m.group(2))


def _frame_size(width: Any, height: Any) -> tuple[int, int]:
    """``(width, height)`` as ints, or :class:`ProfileStoreError` unless both are
    positive whole numbers (``int()`` would truncate 0.5 to a zero-width frame, and
    reject ``'a'`` or NaN with a bare ``ValueError``)."""
    for v in (width, height):
        if (isinstance(v, bool) or not isinstance(v, numbers.Real) or not math.isfinite(v)
                or v < 1 or v != int(v)):
            raise ProfileStoreError(f"frame size must be positive integers, got {width!r} x {height!r}")
    return int(width), int(height)


def _check_key(key: Any, op: str) -> ProfileKey:
    if not isinstance(key, ProfileKey):
        raise ProfileStoreError(f"{op}() needs a ProfileKey, got {type(key).__name__}")
    return key


def _check_lens_id(lens_id: Any) -> str:
    if not isinstance(lens_id, str):
        raise ProfileStoreError(f"lens id must be a string, got {type(lens_id).__name__}")
    if not lens_id.strip():
        raise ProfileStoreError("lens id is empty")
    if len(lens_id) > MAX_LENS_ID:
        raise ProfileStoreError(f"lens id is implausibly long ({len(lens_id)} characters)")
    for ch in lens_id:
        cat = unicodedata.category(ch)
        # Quotes, semicolons, any printable Unicode are fine (values are bound, never
        # formatted into SQL); control characters and lone surrogates are not text.
        if cat in ("Cc", "Cs"):
            raise ProfileStoreError(f"lens id {lens_id!r} contains a control character or invalid code point")
    return lens_id


@dataclass(frozen=True)
class ProfileKey:
    """Identity of a profile: lens, focal bin, aperture bin and frame aspect ratio.

    Attributes
    ----------
    lens_id : str
        ``LensKey.lens_id()``: ``"make|model|lens"`` (normalised, escaped).
    focal_bin : str
        ``"f=23.6mm"`` (see :func:`focal_bin`) or ``"any"``.
    aperture_bin : str
        ``"N=4.0"`` (see :func:`aperture_bin`) or ``"any"``.
    aspect : str
        ``"3:2"``, ``"2:3"``, ``"4:3"``, ... or ``"a=1.234"`` (see :func:`aspect_label`).

    Raises
    ------
    ProfileStoreError
        If a component is not canonical (labels must come from the binning functions).
    """

    lens_id: str
    focal_bin: str
    aperture_bin: str
    aspect: str

    def __post_init__(self) -> None:
        _check_lens_id(self.lens_id)
        fb, ab, asp = self.focal_bin, self.aperture_bin, self.aspect
        if not isinstance(fb, str) or (fb != ANY and not (_FOCAL_RE.match(fb) and focal_bin(float(fb[2:-2])) == fb)):
            raise ProfileStoreError(f"invalid focal bin {fb!r} (expected a label such as 'f=23.6mm' or 'any')")
        if not isinstance(ab, str) or (ab != ANY and not (_APERTURE_RE.match(ab) and aperture_bin(float(ab[2:])) == ab)):
            raise ProfileStoreError(f"invalid aperture bin {ab!r} (expected a label such as 'N=4.0' or 'any')")
        if not isinstance(asp, str) or aspect_label(_aspect_value(asp)) != asp:
            raise ProfileStoreError(f"invalid aspect label {asp!r} (expected e.g. '3:2' or 'a=1.234')")

    @classmethod
    def from_lens(cls, lens_key: LensKey, width: int, height: int, *, with_serial: bool = False) -> ProfileKey:
        """The key of a photograph with EXIF ``lens_key`` and a ``width``×``height`` frame.

        Raises
        ------
        ProfileStoreError
            If neither the camera model nor the lens is known (nothing identifies
            the optics, and pooling such frames would mix lenses), if ``lens_key``
            is not a :class:`~vigproc.io.exif.LensKey`, or if the frame size is not
            two positive integers.
        """
        if not isinstance(lens_key, LensKey):
            raise ProfileStoreError(f"a profile key needs a LensKey, got {type(lens_key).__name__}")
        if lens_key.model is None and lens_key.lens is None:
            raise ProfileStoreError(
                "the metadata names neither the camera model nor the lens: no profile can be keyed"
            )
        w, h = _frame_size(width, height)
        return cls(
            lens_id=lens_key.lens_id(with_serial=with_serial),
            focal_bin=focal_bin(lens_key.focal_mm),
            aperture_bin=aperture_bin(lens_key.fnumber),
            aspect=aspect_label(w / h),
        )

    @property
    def aspect_ratio(self) -> float:
        """W/H of the bin's representative frame."""
        return _aspect_value(self.aspect)

    def __str__(self) -> str:
        return f"{self.lens_id} @ {self.focal_bin} {self.aperture_bin} {self.aspect}"


def _canonical_focal(value: Any, where: str) -> str:
    """Bin label from a file: 'any', a label, or a number (then binned)."""
    if isinstance(value, str):
        s = value.strip()
        if s == ANY:
            return ANY
        m = re.match(r"^(?:f\s*=\s*)?(\d+(?:\.\d+)?)\s*(?:mm)?$", s)
        if not m:
            raise ProfileStoreError(f"{where}: focal_bin {value!r} is not 'any', a bin label like 'f=23.6mm' or a number")
        value = float(m.group(1))
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise ProfileStoreError(f"{where}: focal_bin must be a string or number, got {type(value).__name__}")
    if not (math.isfinite(value) and 0.5 <= value <= 10_000):
        raise ProfileStoreError(f"{where}: focal_bin {value!r} mm is absurd")
    return focal_bin(float(value))


def _canonical_aperture(value: Any, where: str) -> str:
    if isinstance(value, str):
        s = value.strip()
        if s == ANY:
            return ANY
        m = re.match(r"^(?:N\s*=\s*|f\s*/\s*)?(\d+(?:\.\d+)?)$", s)
        if not m:
            raise ProfileStoreError(f"{where}: aperture_bin {value!r} is not 'any', a bin label like 'N=4.0' or a number")
        value = float(m.group(1))
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise ProfileStoreError(f"{where}: aperture_bin must be a string or number, got {type(value).__name__}")
    if not (math.isfinite(value) and 0.5 <= value <= 1000):
        raise ProfileStoreError(f"{where}: aperture_bin f/{value!r} is absurd")
    return aperture_bin(float(value))


def _canonical_aspect(value: Any, where: str) -> str:
    if isinstance(value, str):
        s = value.strip()
        m = re.match(r"^(\d+(?:\.\d+)?)\s*:\s*(\d+(?:\.\d+)?)$", s)
        if m and float(m.group(2)) > 0:
            value = float(m.group(1)) / float(m.group(2))
        else:
            m = re.match(r"^(?:a\s*=\s*)?(\d+(?:\.\d+)?)$", s)
            if not m:
                raise ProfileStoreError(f"{where}: aspect {value!r} is not a ratio like '3:2' or a number W/H")
            value = float(m.group(1))
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise ProfileStoreError(f"{where}: aspect must be a string or number, got {type(value).__name__}")
    if not (math.isfinite(value) and 0.1 <= value <= 10):
        raise ProfileStoreError(f"{where}: aspect ratio {value!r} is absurd")
    return aspect_label(float(value))


# --------------------------------------------------------------------------- #
# information-form pooling
# --------------------------------------------------------------------------- #


def fixed_indices(cov: np.ndarray) -> tuple[int, ...]:
    """The parameters a covariance holds fixed: those whose row and column are all zero
    (the lens-family fit fixes the centre and the shape, so its σ is exactly 0 there).

    Parameters
    ----------
    cov : ndarray (n, n)

    Returns
    -------
    tuple of int
        Indices into :data:`vigproc.core.model.PARAM_NAMES`, ascending.
    """
    cov = np.asarray(cov, dtype=np.float64)
    return tuple(i for i in range(cov.shape[0]) if not np.any(cov[i]) and not np.any(cov[:, i]))


def _scaled_pinv(m: np.ndarray, what: str, *, allow_fixed: bool = False) -> np.ndarray:
    """Pseudo-inverse of a symmetric PSD matrix, computed on its correlation form with
    a tiny ridge (parameters differ in scale by orders of magnitude).  With
    ``allow_fixed``, parameters held fixed (:func:`fixed_indices`) get zero rows and
    columns: a value known by construction adds no information to pool."""
    m = 0.5 * (m + m.T)
    keep = np.arange(m.shape[0])
    if allow_fixed:
        fixed = fixed_indices(m)
        keep = np.array([i for i in keep if i not in fixed], dtype=int)
        if keep.size == 0:
            raise ProfileStoreError(f"{what} holds every parameter fixed")
    sub = m[np.ix_(keep, keep)]
    d = np.sqrt(np.diag(sub))
    if not (np.all(np.isfinite(sub)) and np.all(d > 0)):
        bad = [PARAM_NAMES[keep[i]] for i in np.flatnonzero(~(d > 0))]
        raise ProfileStoreError(f"{what} has zero or invalid variance for {bad or 'some parameters'}")
    c = sub / np.outer(d, d)
    inv = np.linalg.pinv(c + RIDGE * np.eye(c.shape[0]), hermitian=True) / np.outer(d, d)
    out = np.zeros_like(m)
    out[np.ix_(keep, keep)] = 0.5 * (inv + inv.T)
    return out


#: Largest variance a profile file may give a (normalised) parameter.
MAX_FILE_VARIANCE = 1e8


def _check_covariance(cov: np.ndarray, what: str, *, allow_fixed: bool = False) -> np.ndarray:
    """``cov`` symmetrised, or :class:`ProfileStoreError` unless it is a finite symmetric
    PSD 12×12 matrix with positive variances; with ``allow_fixed`` an all-zero row and
    column (a parameter held fixed, :func:`fixed_indices`) is allowed too."""
    cov = np.asarray(cov, dtype=np.float64)
    if cov.shape != (N_PARAMS, N_PARAMS):
        raise ProfileStoreError(f"{what}: covariance must be {N_PARAMS}x{N_PARAMS}, got shape {cov.shape}")
    if not np.all(np.isfinite(cov)):
        raise ProfileStoreError(f"{what}: covariance contains NaN or Inf")
    scale = float(np.max(np.abs(cov))) or 1.0
    if not np.allclose(cov, cov.T, rtol=1e-6, atol=1e-9 * scale):
        raise ProfileStoreError(f"{what}: covariance is not symmetric")
    fixed = fixed_indices(cov) if allow_fixed else ()
    free = [i for i in range(N_PARAMS) if i not in fixed]
    if not free:
        raise ProfileStoreError(f"{what}: covariance holds every parameter fixed (use null for an unknown uncertainty)")
    sub = cov[np.ix_(free, free)]
    if np.any(np.diag(sub) <= 0):
        raise ProfileStoreError(f"{what}: covariance has a non-positive variance")
    d = np.sqrt(np.diag(sub))
    w = np.linalg.eigvalsh(0.5 * (sub + sub.T) / np.outer(d, d))
    if w[0] < -1e-6:
        raise ProfileStoreError(f"{what}: covariance is not positive semi-definite (eigenvalue {w[0]:.3g} of its correlation)")
    return 0.5 * (cov + cov.T)


def frame_information(model: VignettingModel) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """One frame's evidence in information form, normalised units.

    Returns
    -------
    theta : ndarray (12,)
        Normalised parameters θ_i.
    info_matrix : ndarray (12, 12)
        Λ_i = Σ_i⁻¹ (pseudo-inverse with a tiny ridge on the correlation matrix).
    info_vector : ndarray (12,)
        η_i = Λ_i θ_i.

    Raises
    ------
    ProfileStoreError
        If the model has no covariance (e.g. the identity fallback) or it is invalid.
    """
    theta, cov, _ = normalise(model)
    if cov is None:
        raise ProfileStoreError(
            f"a {model.method!r} estimate without covariance cannot be pooled (identity fallback? "
            "pass its .candidate to learn from weak evidence)"
        )
    cov = _check_covariance(cov, "frame estimate")
    lam = _scaled_pinv(cov, "frame estimate covariance")
    return theta, lam, lam @ theta


def pool_information(thetas: Sequence[np.ndarray], covs: Sequence[np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """Inverse-variance (information-form) pooling of normalised estimates.

    θ = (Σ Λ_i)⁻¹ Σ Λ_i θ_i, covariance (Σ Λ_i)⁻¹, Λ_i = Σ_i⁻¹: the same arithmetic as
    :meth:`ProfileStore.learn`, without the database (for benchmarks).
    """
    if len(thetas) == 0 or len(thetas) != len(covs):
        raise ProfileStoreError("pool_information needs as many covariances as estimates (at least one)")
    lam = np.zeros((N_PARAMS, N_PARAMS))
    eta = np.zeros(N_PARAMS)
    for th, cv in zip(thetas, covs):
        li = _scaled_pinv(_check_covariance(cv, "estimate"), "estimate covariance")
        lam += li
        eta += li @ np.asarray(th, dtype=np.float64)
    cov = _scaled_pinv(lam, "pooled information")
    return cov @ eta, cov


def pool_mean(thetas: Sequence[np.ndarray]) -> np.ndarray:
    """Plain (unweighted) mean of normalised parameter vectors, for comparison with
    the information-form pooling."""
    a = np.asarray([np.asarray(t, dtype=np.float64) for t in thetas])
    if a.ndim != 2 or a.shape[0] == 0 or a.shape[1] != N_PARAMS:
        raise ProfileStoreError(f"pool_mean needs a non-empty list of {N_PARAMS}-vectors")
    return a.mean(axis=0)


class _Exact:
    """Exact, order-independent sums of float64 arrays.

    Every finite float64 is m·2^e with integers m, e; the sum of such numbers is
    again of that form, so it is kept as (m, e) pairs of Python integers and is
    exact.  Converting back rounds once, correctly.  Hence Λ = Σ Λ_i does not depend
    on the order in which concurrent workers added their frames.
    """

    __slots__ = ("m", "e")

    def __init__(self, m: list[int], e: list[int]) -> None:
        self.m, self.e = m, e

    @classmethod
    def zeros(cls, n: int) -> _Exact:
        return cls([0] * n, [0] * n)

    @staticmethod
    def _split(x: float) -> tuple[int, int]:
        num, den = float(x).as_integer_ratio()
        if num == 0:
            return 0, 0
        e = -(den.bit_length() - 1)
        tz = (num & -num).bit_length() - 1
        return num >> tz, e + tz

    @classmethod
    def from_array(cls, a: np.ndarray) -> _Exact:
        a = np.asarray(a, dtype=np.float64).ravel()
        if not np.all(np.isfinite(a)):
            raise ProfileStoreError("cannot accumulate NaN or Inf evidence")
        pairs = [cls._split(v) for v in a.tolist()]
        return cls([p[0] for p in pairs], [p[1] for p in pairs])

    def add(self, other: _Exact) -> _Exact:
        if len(other.m) != len(self.m):
            raise ProfileStoreError("exact sums of different sizes")
        m, e = [], []
        for m1, e1, m2, e2 in zip(self.m, self.e, other.m, other.e):
            if m1 == 0:
                mm, ee = m2, e2
            elif m2 == 0:
                mm, ee = m1, e1
            else:
                ee = min(e1, e2)
                mm = (m1 << (e1 - ee)) + (m2 << (e2 - ee))
                if mm == 0:
                    ee = 0
                else:
                    tz = (mm & -mm).bit_length() - 1
                    mm, ee = mm >> tz, ee + tz
            m.append(mm)
            e.append(ee)
        return _Exact(m, e)

    def to_array(self) -> np.ndarray:
        out = np.empty(len(self.m))
        for i, (m, e) in enumerate(zip(self.m, self.e)):
            try:
                out[i] = float(m << e) if e >= 0 else float(Fraction(m, 1 << -e))
            except OverflowError:
                raise ProfileStoreError("accumulated information overflows float64") from None
        return out

    def to_json(self) -> list[list[int]]:
        return [[m, e] for m, e in zip(self.m, self.e)]

    @classmethod
    def from_json(cls, data: Any, n: int) -> _Exact:
        if not isinstance(data, list) or len(data) != n:
            raise ValueError(f"expected {n} exact values")
        m, e = [], []
        for item in data:
            if not (isinstance(item, list) and len(item) == 2 and all(type(v) is int for v in item)):
                raise ValueError("exact value is not an [int, int] pair")
            if abs(item[1]) > 4000:
                raise ValueError("exact value exponent out of range")
            m.append(item[0])
            e.append(item[1])
        return cls(m, e)


@dataclass
class _Welford:
    """Running mean and centred sums of squares (and cross-products) across frames."""

    n: int
    theta_mean: np.ndarray
    theta_m2: np.ndarray      # 12×12 Σ (θ−μ)(θ−μ)ᵀ
    field_mean: np.ndarray    # log2 φ on the FIELD_GRID² grid
    field_m2: np.ndarray      # per grid point Σ (f−μ)²

    @classmethod
    def empty(cls) -> _Welford:
        g = FIELD_GRID * FIELD_GRID
        return cls(0, np.zeros(N_PARAMS), np.zeros((N_PARAMS, N_PARAMS)), np.zeros(g), np.zeros(g))

    def add(self, theta: np.ndarray, field_: np.ndarray) -> _Welford:
        """Welford (1962) update with one more frame (returns a new state)."""
        n = self.n + 1
        d = theta - self.theta_mean
        mu = self.theta_mean + d / n
        m2 = self.theta_m2 + np.outer(d, theta - mu)
        df = field_ - self.field_mean
        fmu = self.field_mean + df / n
        fm2 = self.field_m2 + df * (field_ - fmu)
        return _Welford(n, mu, 0.5 * (m2 + m2.T), fmu, fm2)

    @property
    def scatter_sigma_ev(self) -> float | None:
        """Frame-to-frame RMS (over the frame) standard deviation of log2 φ, EV."""
        if self.n < 2:
            return None
        return float(math.sqrt(max(float(np.mean(self.field_m2)) / (self.n - 1), 0.0)))

    @property
    def theta_scatter(self) -> np.ndarray | None:
        """Sample covariance of θ̃ across frames."""
        if self.n < 2:
            return None
        return self.theta_m2 / (self.n - 1)


# --------------------------------------------------------------------------- #
# profiles
# --------------------------------------------------------------------------- #


#: Distinct focal lengths (and crop factors) a profile's :class:`Shots` keeps at most.
MAX_SHOT_VALUES = 1000
#: Crop factors outside this range are an EXIF mistake (a 35-mm focal length of 11113 mm).
CROP_RANGE = (0.2, 15.0)
_MAX_NAME = 200


def _histogram_add(hist: tuple[tuple[float, int], ...], value: float, n: int = 1) -> tuple[tuple[float, int], ...]:
    d = dict(hist)
    if value in d or len(d) < MAX_SHOT_VALUES:
        d[value] = d.get(value, 0) + n
    return tuple(sorted(d.items()))


def _histogram_median(hist: tuple[tuple[float, int], ...]) -> float | None:
    total = sum(n for _, n in hist)
    if not total:
        return None
    seen = 0
    for v, n in hist:  # the lower median: a focal length a frame was really shot at
        seen += n
        if 2 * seen >= total:
            return v
    return hist[-1][0]


@dataclass(frozen=True)
class Shots:
    """How a profile's frames were shot, as their EXIF said: what a profile written for
    another program needs and its key does not keep (the key's names are casefolded and
    its focal length is a bin).

    Attributes
    ----------
    names : (make, model, lens, lens make)
        As the metadata spelt them (:attr:`vigproc.io.exif.LensKey.spelling`), of the
        latest frame that gave them; None when unknown.
    focal_mm : tuple of (focal length in mm, frames)
        The frames' real focal lengths (0.01 mm), ascending.
    crop : tuple of (crop factor, frames)
        The frames' 35-mm focal length over their focal length (0.001), ascending.
    """

    names: tuple[str | None, str | None, str | None, str | None] = (None, None, None, None)
    focal_mm: tuple[tuple[float, int], ...] = ()
    crop: tuple[tuple[float, int], ...] = ()

    @classmethod
    def of_frame(cls, lens_key: LensKey) -> Shots:
        """One frame's :class:`Shots` from its EXIF lens key."""
        names = tuple(getattr(lens_key, "spelling", None) or (None,) * 4)
        focal = lens_key.focal_mm
        focal_mm = ((round(float(focal), 2), 1),) if focal is not None and focal > 0 else ()
        crop: tuple[tuple[float, int], ...] = ()
        f35 = lens_key.focal_35mm
        if focal_mm and f35 is not None:
            c = round(float(f35) / float(focal), 3)
            crop = ((c, 1),) if CROP_RANGE[0] <= c <= CROP_RANGE[1] else ()
        return cls(names, focal_mm, crop)  # type: ignore[arg-type]

    def add(self, other: Shots) -> Shots:
        """These frames and ``other``'s; names from ``other`` where it has them."""
        focal, crop = self.focal_mm, self.crop
        for v, n in other.focal_mm:
            focal = _histogram_add(focal, v, n)
        for v, n in other.crop:
            crop = _histogram_add(crop, v, n)
        names = tuple(b if b is not None else a for a, b in zip(self.names, other.names))
        return Shots(names, focal, crop)  # type: ignore[arg-type]

    @property
    def focal_median(self) -> float | None:
        """The median focal length the frames were shot at (mm), or None."""
        return _histogram_median(self.focal_mm)

    @property
    def crop_factor(self) -> float | None:
        """The median crop factor the frames' EXIF gave, or None."""
        return _histogram_median(self.crop)

    def describe_focal(self) -> str | None:
        """``"70 mm"``, or ``"67-70 mm (median 70)"`` for frames shot at several; None
        when no frame gave its focal length."""
        med = self.focal_median
        if med is None:
            return None
        lo, hi = self.focal_mm[0][0], self.focal_mm[-1][0]
        if lo == hi:
            return f"{lo:g} mm"
        return f"{lo:g}-{hi:g} mm (median {med:g})"

    def to_json(self) -> dict[str, Any]:
        """The JSON object stored in the profile store and in profile files."""
        return {"make": self.names[0], "model": self.names[1], "lens": self.names[2], "lens_make": self.names[3],
                "focal_mm": [[v, n] for v, n in self.focal_mm], "crop": [[v, n] for v, n in self.crop]}

    @classmethod
    def from_json(cls, d: Any, where: str) -> Shots:
        """Validate :meth:`to_json`'s object (from a file or the store).

        Raises
        ------
        ProfileStoreError
            Naming ``where`` and the field.
        """
        if not isinstance(d, dict):
            raise ProfileStoreError(f"{where}: shots must be an object")
        names = []
        for k in ("make", "model", "lens", "lens_make"):
            v = d.get(k)
            if v is not None and not (isinstance(v, str) and 0 < len(v) <= _MAX_NAME and v.strip() == v
                                      and not any(unicodedata.category(ch) in ("Cc", "Cs") for ch in v)):
                raise ProfileStoreError(f"{where}: shots.{k} must be a one-line name of at most {_MAX_NAME} "
                                        "characters or null")
            names.append(v)

        def hist(k: str, lo: float, hi: float) -> tuple[tuple[float, int], ...]:
            v = d.get(k, [])
            ok = isinstance(v, list) and len(v) <= MAX_SHOT_VALUES and all(
                isinstance(e, list) and len(e) == 2 and isinstance(e[0], (int, float))
                and not isinstance(e[0], bool) and math.isfinite(e[0]) and lo <= e[0] <= hi
                and type(e[1]) is int and 1 <= e[1] <= MAX_FRAMES for e in v)
            if not ok:
                raise ProfileStoreError(f"{where}: shots.{k} must be a list of [value in {lo:g}..{hi:g}, frames]")
            out: tuple[tuple[float, int], ...] = ()
            for val, n in v:
                out = _histogram_add(out, float(val), n)
            return out

        return cls(tuple(names), hist("focal_mm", 0.01, 10_000.0), hist("crop", *CROP_RANGE))  # type: ignore[arg-type]


def _is_trusted(n_frames: int, sigma_ev: float | None) -> bool:
    return n_frames >= TRUSTED_MIN_FRAMES and sigma_ev is not None and sigma_ev < TRUSTED_SIGMA_EV


@dataclass(eq=False)
class Profile:
    """A lens profile: pooled model parameters in normalised units plus their evidence.

    Attributes
    ----------
    key : ProfileKey
    theta : ndarray (12,)
        Normalised (cx, cy, p1, p2, p3, α1..α7): centre in half-diagonals R, P in R⁻².
    covariance : ndarray (12, 12) or None
        Covariance of ``theta`` (Λ⁻¹ for learned profiles).
    info_matrix, info_vector : ndarray or None
        Pooled evidence Λ = Σ Λ_i and η = Σ Λ_i θ_i (None when no uncertainty is known).
    n_frames : int
        Frames the profile was learned from (for imports: as stated by the file).
    provenance : {"learned", "lensfun", "user"}
    created, updated : str
        UTC ISO 8601 timestamps.
    trusted : bool
        ``n_frames >= TRUSTED_MIN_FRAMES`` and ``field_sigma_ev < TRUSTED_SIGMA_EV``
        (imports may state it explicitly).
    field_sigma_ev : float or None
        Pooled uncertainty of log2 φ, RMS over a frame of the key's aspect, in EV:
        the larger of ``cov_sigma_ev`` and ``scatter_sigma_ev / √n``.
    cov_sigma_ev : float or None
        The same from ``covariance`` alone (first-order propagation).
    scatter_sigma_ev : float or None
        Frame-to-frame RMS spread of log2 φ across the learned frames, EV (≥ 2 frames).
    notes : str
    colour : ColourPool or None
        The frames' colour fields pooled (:class:`vigproc.core.colour.ColourPool`):
        per-channel shading a flat-field or a DNG's per-plane maps measured; None:
        colourless.
    shots : Shots or None
        How the frames were shot (their real focal lengths, crop factor and names as
        EXIF spelt them); None when unknown (a store or file from before schema v10/2).
    """

    key: ProfileKey
    theta: np.ndarray
    covariance: np.ndarray | None = None
    info_matrix: np.ndarray | None = None
    info_vector: np.ndarray | None = None
    n_frames: int = 0
    provenance: str = "learned"
    created: str = ""
    updated: str = ""
    trusted: bool = False
    field_sigma_ev: float | None = None
    cov_sigma_ev: float | None = None
    scatter_sigma_ev: float | None = None
    notes: str = ""
    shots: Shots | None = None
    colour: ColourPool | None = None
    _exact: tuple[_Exact, _Exact] | None = field(default=None, repr=False)
    _welford: _Welford | None = field(default=None, repr=False)

    def __post_init__(self) -> None:
        self.theta = np.asarray(self.theta, dtype=np.float64).copy()
        if self.theta.shape != (N_PARAMS,) or not np.all(np.isfinite(self.theta)):
            raise ProfileStoreError(f"profile {self.key}: θ must be {N_PARAMS} finite numbers")
        if self.provenance not in PROVENANCES:
            raise ProfileStoreError(f"profile {self.key}: provenance must be one of {PROVENANCES}, got {self.provenance!r}")
        now = _now()
        self.created = self.created or now
        self.updated = self.updated or self.created

    @property
    def theta_scatter(self) -> np.ndarray | None:
        """Sample covariance of the per-frame θ̃ (Welford), or None with fewer than 2 frames."""
        return self._welford.theta_scatter if self._welford is not None else None

    @property
    def theta_mean(self) -> np.ndarray | None:
        """Plain mean of the per-frame θ̃ (Welford), or None."""
        return self._welford.theta_mean.copy() if self._welford is not None and self._welford.n else None

    def mismatch(self, lens_key: LensKey | None) -> str | None:
        """Why this profile is not of the camera and lens a frame's EXIF names (``None``
        when it is, or when the EXIF names neither): a profile file given by hand may be
        of any lens, and applying another lens's fall-off is a silent miscorrection.

        Returns
        -------
        str or None
            A sentence naming both.
        """
        if not isinstance(lens_key, LensKey) or (lens_key.model is None and lens_key.lens is None):
            return None
        frame = lens_key.lens_id()
        mine = "|".join(self.key.lens_id.split("|")[:3])  # a lens unit's serial aside
        if mine == frame:
            return None
        return f"the profile is of {mine!r}, the frame's EXIF names {frame!r} (another camera or lens)"

    def model(self, width: int, height: int) -> VignettingModel:
        """The profile as a :class:`VignettingModel` for a ``width``×``height`` frame.

        Raises
        ------
        ProfileStoreError
            If the frame size is not two positive integers, or the frame's aspect
            ratio is not the profile's.
        """
        width, height = _frame_size(width, height)
        if aspect_label(width / height) != self.key.aspect:
            raise ProfileStoreError(
                f"profile {self.key} is for aspect {self.key.aspect}; a {width}x{height} frame is "
                f"{aspect_label(width / height)} (a crop or a rotated frame)"
            )
        ev_rms = float(np.sqrt(np.mean(_field_and_jacobian(self.theta, self.key.aspect_ratio)[0] ** 2)))
        sigma = self.field_sigma_ev
        q = FitQuality(
            confidence=1.0 if self.trusted else 0.0,
            field_ev_rms=ev_rms,
            field_sigma_ev=sigma if sigma is not None else math.nan,
            snr=ev_rms / sigma if sigma else math.inf,
        )
        m = denormalise(self.theta, self.covariance, width, height, method=f"profile:{self.provenance}", quality=q)
        return m if self.colour is None else replace(m, colour=self.colour.field(width, height))


def _profile_stats(theta: np.ndarray, cov: np.ndarray | None, aspect: float,
                   welford: _Welford | None) -> tuple[float | None, float | None, float | None]:
    """(pooled σ, covariance σ, scatter σ) in EV."""
    cov_sigma = _field_sigma_ev(theta, cov, aspect) if cov is not None else None
    scatter = welford.scatter_sigma_ev if welford is not None else None
    parts = [s for s in (cov_sigma, scatter / math.sqrt(welford.n) if scatter is not None else None) if s is not None]
    pooled = max(parts) if parts else None
    return pooled, cov_sigma, scatter


def _valid_theta(theta: np.ndarray, aspect: float) -> bool:
    try:
        VignettingModel.from_vector(theta, 1000, 1000)
    except ModelError:
        return False
    return _field_and_jacobian(theta, aspect)[2] > 0.0


def _bin_value(label: str) -> float | None:
    """The number of a focal or aperture bin label ("f=23.6mm", "N=4.0"); None for "any"."""
    if label == ANY:
        return None
    return float(label[2:-2] if label.endswith("mm") else label[2:])


def _bracket(points: dict[float, Any], x: float, reach: float) -> list[tuple[Any, float]] | None:
    """Linear-interpolation weights at ``x`` between the nearest points on either side
    (a point at ``x`` itself: weight 1); None when ``x`` is not bracketed or the two
    points are further apart than ``reach``."""
    if x in points:
        return [(points[x], 1.0)]
    lo = max((p for p in points if p < x), default=None)
    hi = min((p for p in points if p > x), default=None)
    if lo is None or hi is None or hi - lo > reach:
        return None
    t = (x - lo) / (hi - lo)
    return [(points[lo], 1.0 - t), (points[hi], t)]


def interpolate_profiles(profiles: Sequence[Profile], key: ProfileKey, focal_mm: float,
                         fnumber: float) -> Profile | None:
    """A lens's profile at a focal length and f-number between its bins.

    Bilinear in (log2 focal length, stops = 2·log2 N), as lensfun interpolates its
    calibrations between focal lengths and apertures: at each of the two nearest
    aperture bins on either side of ``fnumber`` (or at its own), linear in log focal
    length between the nearest bins on either side (or its own), then linear across
    the two apertures; the log2 fields are combined, then written as the Kang-Weiss
    model. Never extrapolated; bins further apart than :data:`INTERPOLATION_REACH`
    are not bridged.

    Uncertainty: σ = hypot(Σ w_i σ_i, s), s the weighted RMS of the bins' fields
    about the interpolated one (how much the lens changes across the span, of which
    a linear interpolation may miss a part; ``vigproc bench profile-interp`` measures
    how often the error stays within it).

    Parameters
    ----------
    profiles : sequence of Profile
        Profiles of one lens and aspect (others are ignored).
    key : ProfileKey
        The key asked for (its lens id and aspect select the profiles).

    Returns
    -------
    Profile or None
        ``key``'s profile, notes naming the bins and weights; None when the bins do
        not bracket the request.
    """
    aspect = key.aspect_ratio
    grid: dict[float, dict[float, Profile]] = {}
    for p in profiles:
        f, n = _bin_value(p.key.focal_bin), _bin_value(p.key.aperture_bin)
        if p.key.lens_id != key.lens_id or p.key.aspect != key.aspect or f is None or n is None:
            continue
        grid.setdefault(2.0 * math.log2(n), {})[math.log2(f)] = p
    x, y = math.log2(focal_mm), 2.0 * math.log2(fnumber)
    reach_f, reach_n = INTERPOLATION_REACH
    levels = {}
    for level, row in grid.items():
        w = _bracket(row, x, reach_f)
        if w is not None:
            levels[level] = w
    across = _bracket(levels, y, reach_n)
    if across is None:
        return None
    weights: list[tuple[Profile, float]] = [(p, wa * wf) for row, wa in across for p, wf in row if wa * wf > 0]
    if len(weights) == 1:
        return weights[0][0]
    # the fields on a small frame of the key's aspect (natural log), combined
    gw, gh = 48, max(4, round(48 / aspect))
    fields = np.array([denormalise(p.theta, None, gw, gh).log_field((gh, gw)).ravel() for p, _ in weights])
    w = np.array([wt for _, wt in weights])
    mean = w @ fields
    spread = float(math.sqrt(max(float(w @ np.mean((fields - mean) ** 2, axis=1)), 0.0))) / math.log(2.0)
    sigmas = [p.field_sigma_ev for p, _ in weights]
    sigma = None if any(sg is None for sg in sigmas) else math.hypot(float(w @ np.array(sigmas)), spread)
    model, _ = fit_model_to_field(mean.reshape(gh, gw), gw, gh)
    provenances = {p.provenance for p, _ in weights}
    parts = ", ".join(f"{p.key.focal_bin} {p.key.aperture_bin} ({wt:.2f})" for p, wt in weights)
    return Profile(
        key=key, theta=normalise(model)[0], covariance=None, n_frames=sum(p.n_frames for p, _ in weights),
        provenance=provenances.pop() if len(provenances) == 1 else "user",
        trusted=all(p.trusted for p, _ in weights) and sigma is not None and sigma < TRUSTED_SIGMA_EV,
        field_sigma_ev=sigma, notes=f"interpolated from {parts}",
        colour=ColourPool.blend([(p.colour, wt) for p, wt in weights]),
    )


# --------------------------------------------------------------------------- #
# the store
# --------------------------------------------------------------------------- #


def default_db_path() -> Path:
    """``$VIGPROC_PROFILE_DB``, else ``<user data dir>/vigproc/profiles.sqlite`` (platformdirs)."""
    env = os.environ.get(DB_ENV, "").strip()
    if env:
        return Path(env).expanduser()
    import platformdirs

    return Path(platformdirs.user_data_dir("vigproc", appauthor=False)) / "profiles.sqlite"


_COLUMNS = (
    "lens_id", "focal_bin", "aperture_bin", "aspect", "theta", "covariance", "info_exact",
    "info_matrix", "info_vector", "n_frames", "n_scatter", "theta_mean", "theta_m2",
    "field_mean", "field_m2", "provenance", "created", "updated", "trusted",
    "field_sigma_ev", "cov_sigma_ev", "scatter_sigma_ev", "notes", "shots", "colour",
)


def _migration_1(con: sqlite3.Connection) -> None:
    """v1: the profiles table."""
    con.execute(
        """
        CREATE TABLE profiles (
            id               INTEGER PRIMARY KEY,
            lens_id          TEXT NOT NULL,
            focal_bin        TEXT NOT NULL,
            aperture_bin     TEXT NOT NULL,
            aspect           TEXT NOT NULL,
            theta            BLOB NOT NULL,          -- 12 float64 LE, normalised units
            covariance       BLOB,                   -- 144 float64 LE or NULL
            info_exact       TEXT,                   -- JSON exact sums of Λ (144) and η (12)
            info_matrix      BLOB,                   -- Λ rounded to float64 (for reading)
            info_vector      BLOB,                   -- η rounded to float64
            n_frames         INTEGER NOT NULL CHECK (n_frames >= 0),
            n_scatter        INTEGER NOT NULL DEFAULT 0 CHECK (n_scatter >= 0),
            theta_mean       BLOB,                   -- Welford state across frames
            theta_m2         BLOB,
            field_mean       BLOB,
            field_m2         BLOB,
            provenance       TEXT NOT NULL CHECK (provenance IN ('learned', 'lensfun', 'user')),
            created          TEXT NOT NULL,
            updated          TEXT NOT NULL,
            trusted          INTEGER NOT NULL CHECK (trusted IN (0, 1)),
            field_sigma_ev   REAL,
            cov_sigma_ev     REAL,
            scatter_sigma_ev REAL,
            notes            TEXT NOT NULL DEFAULT '',
            UNIQUE (lens_id, focal_bin, aperture_bin, aspect)
        )
        """
    )


def _migration_2(con: sqlite3.Connection) -> None:
    """v2: the frames pooled into each profile, by content id, so that a frame offered
    again (a restarted daemon, a resumed batch, the same file under another name) is
    not pooled twice.  Recorded in the same transaction as the profile update."""
    con.execute(
        """
        CREATE TABLE pooled_frames (
            frame      TEXT NOT NULL,
            profile_id INTEGER NOT NULL REFERENCES profiles (id) ON DELETE CASCADE,
            pooled     TEXT NOT NULL,
            PRIMARY KEY (frame, profile_id)
        )
        """
    )


def _migration_3(con: sqlite3.Connection) -> None:
    """v3: each pooled frame may keep its evidence for a refit of the profile
    (:func:`vigproc.core.robust.frame_evidence`, ≈ 25 KB a frame)."""
    con.execute("ALTER TABLE pooled_frames ADD COLUMN evidence BLOB")


def _migration_4(con: sqlite3.Connection) -> None:
    """v4: each frame's centred fit (:func:`vigproc.core.pooling.centred_fit`) is kept with
    its evidence, so that pooling every frame of a profile costs no refit.  Frames
    stored by v3 get theirs the first time their profile is pooled."""
    con.execute("ALTER TABLE pooled_frames ADD COLUMN fit BLOB")


def _migration_5(con: sqlite3.Connection) -> None:
    """v5: each frame's lens-family fit (:func:`vigproc.core.pooling.frame_fit`), what a
    profile now pools; the v4 centred fits are no longer read.  Frames stored before
    get theirs from their evidence the first time their profile is pooled."""
    con.execute("ALTER TABLE pooled_frames ADD COLUMN family BLOB")


def _migration_6(con: sqlite3.Connection) -> None:
    """v6: the frames' lens-family fits are made again from their evidence the first
    time their profile is pooled: fits stored before weighed no pair by its colour and
    carried the σ scale of their day (:mod:`vigproc.core.family_fit`, session 13), and a
    profile must not pool fits of two kinds."""
    con.execute("UPDATE pooled_frames SET family = NULL")


def _migration_7(con: sqlite3.Connection) -> None:
    """v7: the frames' lens-family fits are made again from their evidence the first
    time their profile is pooled: a frame's fit for pooling now follows the gradients'
    mode more closely (:data:`vigproc.core.pooling.FRAME_SETTINGS`, session 14), and a
    profile must not pool fits of two kinds."""
    con.execute("UPDATE pooled_frames SET family = NULL")


def _migration_8(con: sqlite3.Connection) -> None:
    """v8: the same again: a frame's fit for pooling weighs colour with the single-frame
    fit's chroma scale since session 15 (:data:`vigproc.core.pooling.FRAME_SETTINGS`), and
    the shipped scene scatter was measured for such fits."""
    con.execute("UPDATE pooled_frames SET family = NULL")


def _migration_9(con: sqlite3.Connection) -> None:
    """v9: the same again: a frame's fit for pooling reads each pair's chroma change as
    covariates since session 18 (:data:`vigproc.core.pooling.FRAME_SETTINGS`), and the
    shipped scene scatter was measured for such fits."""
    con.execute("UPDATE pooled_frames SET family = NULL")


def _migration_10(con: sqlite3.Connection) -> None:
    """v10: how each profile's frames were shot (:class:`Shots`: their real focal
    lengths, crop factor and names as EXIF spelt them), for ``profile list`` and a
    lensfun export; profiles learned before have none until their next frame."""
    # a store whose recorded version was set back (tests do) may have the column already
    if "shots" not in {r[1] for r in con.execute("PRAGMA table_info(profiles)")}:
        con.execute("ALTER TABLE profiles ADD COLUMN shots TEXT")


def _migration_11(con: sqlite3.Connection) -> None:
    """v11: each profile's pooled colour field (:class:`vigproc.core.colour.ColourPool`,
    JSON), NULL for the colourless."""
    if "colour" not in {r[1] for r in con.execute("PRAGMA table_info(profiles)")}:
        con.execute("ALTER TABLE profiles ADD COLUMN colour TEXT")


def _migration_12(con: sqlite3.Connection) -> None:
    """v12: the revision of each trusted profile that correct runs apply (learning as
    you go, :meth:`ProfileStore.apply_revision`), shared by every worker: the profile
    file's JSON, its frame count and an id (SHA-256 of that JSON, 16 hex digits)."""
    con.execute(
        """
        CREATE TABLE IF NOT EXISTS applied_profiles (
            lens_id      TEXT NOT NULL,
            focal_bin    TEXT NOT NULL,
            aperture_bin TEXT NOT NULL,
            aspect       TEXT NOT NULL,
            revision     TEXT NOT NULL,
            n_frames     INTEGER NOT NULL,
            profile      TEXT NOT NULL,          -- vigproc.profile/2 or /3 JSON
            applied      TEXT NOT NULL,          -- ISO time it became the applied revision
            PRIMARY KEY (lens_id, focal_bin, aperture_bin, aspect)
        )
        """
    )


#: Numbered migrations: MIGRATIONS[i] brings the schema from version i to i + 1.
#: Append a function for the next version; never edit a released one.
MIGRATIONS: tuple[Callable[[sqlite3.Connection], None], ...] = (_migration_1, _migration_2, _migration_3,
                                                                 _migration_4, _migration_5, _migration_6,
                                                                 _migration_7, _migration_8, _migration_9,
                                                                 _migration_10, _migration_11, _migration_12)
#: A profile is pooled from at most this many frames (:mod:`vigproc.core.pooling`): those
#: with the smallest frame ids (content hashes, so a random sample that does not
#: depend on the order frames arrive in).  Every frame refines the profile up to
#: there: measured on the profile protocol, 0.074 EV after 40 frames and 0.035 after
#: 100 (README, "Profile accuracy versus frames"); the pooling runs inside the
#: learning transaction, from the stored fits.
MAX_POOLED_FRAMES = 1000
#: Frames' fits kept in memory per store object.
_FIT_CACHE_SIZE = 4096
#: Schema version this code writes.
SCHEMA_VERSION = len(MIGRATIONS)


def _blob(a: np.ndarray | None) -> bytes | None:
    return None if a is None else np.ascontiguousarray(a, dtype="<f8").tobytes()


def _fit_blob(fit: Any, size: tuple[int, int]) -> bytes:
    """A frame's lens-family fit as stored: K, frame (w, h), pairs, coefficients (K),
    covariance (K×K)."""
    k = fit.coefficients.size
    return _blob(np.concatenate([[k, size[0], size[1], fit.pairs], fit.coefficients, fit.covariance.ravel()]))


def _fit_from_blob(b: Any) -> tuple[Any, tuple[int, int]]:
    """Inverse of :func:`_fit_blob`. Raises ValueError for a damaged value."""
    from vigproc.core.family_fit import FrameCoefficients

    if not isinstance(b, bytes) or len(b) < 32 or len(b) % 8:
        raise ValueError("column family is not a fit")
    a = np.frombuffer(b, dtype="<f8").astype(np.float64)
    k = int(a[0]) if np.isfinite(a[0]) and 1 <= a[0] <= 16 else 0
    if k == 0 or a.size != 4 + k + k * k or not np.all(np.isfinite(a)) or np.any(a[1:4] < 1) \
            or np.any(a[:4] != np.round(a[:4])):
        raise ValueError("column family holds non-finite values or impossible sizes")
    fit = FrameCoefficients(a[4:4 + k].copy(), a[4 + k:].reshape(k, k).copy(), int(a[3]))
    return fit, (int(a[1]), int(a[2]))


def _unblob(b: Any, shape: tuple[int, ...], name: str) -> np.ndarray | None:
    if b is None:
        return None
    n = int(np.prod(shape))
    if not isinstance(b, bytes) or len(b) != 8 * n:
        raise ValueError(f"column {name} has {len(b) if isinstance(b, bytes) else type(b).__name__} bytes, expected {8 * n}")
    return np.frombuffer(b, dtype="<f8").reshape(shape).astype(np.float64)


class ProfileStore(SQLiteFile):
    """SQLite store of lens profiles, safe for concurrent processes.

    Parameters
    ----------
    path : str or Path, optional
        Database file; default :func:`default_db_path` (``$VIGPROC_PROFILE_DB`` or
        the platform's user data folder).  Missing folders are created.
    timeout : float
        Seconds (finite, >= 0) to wait for another process's write lock before
        :class:`ProfileStoreError` (SQLite busy timeout).
    family : LensFamily, optional
        The lens family profiles pool in (:mod:`vigproc.core.pooling`); default the
        shipped one (:func:`vigproc.core.lensfamily.profile_family`).

    Notes
    -----
    ``journal_mode=WAL`` (readers and one writer proceed concurrently),
    ``synchronous=FULL`` (the WAL is fsynced at every commit, so a learned frame
    that was reported stored survives a power cut; the cost, one fsync per frame,
    is negligible next to estimating the frame; NORMAL would be corruption-safe
    too but could roll back the last commits), ``foreign_keys=ON``.  One store
    object per thread (sqlite3 connections are not shared between threads); each
    process opens its own.

    Raises
    ------
    ProfileStoreError
        When ``path`` is not a path or ``timeout`` not a number of seconds, or the
        file is not a (vigproc) database, is corrupt, is from a newer vigproc, or
        stays locked beyond ``timeout``.
    """

    error = ProfileStoreError
    what = "profile store"
    check_on_open = True
    recovery = ("move it aside (vigproc then starts an empty store there), restore a backup or re-import "
                "exported profiles with 'vigproc profile import FILE'; meanwhile '--profile estimate' or "
                "'--profile lensfun' correct without a store")

    def __init__(self, path: str | os.PathLike[str] | None = None, *, timeout: float = DEFAULT_TIMEOUT,
                 family: Any = None) -> None:
        # SHA-256 of a frame's evidence -> its lens-family fit: a long-lived learner fits each frame once
        self._fit_cache: dict[bytes, Any] = {}
        # the lens family profiles pool in (None: the shipped one); a benchmark passes
        # one without its test lenses
        self._family = family
        # Checked here: the base class would fail with TypeError/ValueError (or
        # OverflowError for an infinite timeout) from Path(), float() or SQLite.
        if path is not None:
            try:
                path = os.fspath(path)
            except TypeError:
                raise ProfileStoreError(
                    f"profile store path must be a str or os.PathLike, got {type(path).__name__}") from None
            path = os.fsdecode(path) if isinstance(path, bytes) else path
            if not path or "\0" in path:
                raise ProfileStoreError(f"profile store path {path!r} is empty or contains a NUL character")
        if (isinstance(timeout, bool) or not isinstance(timeout, numbers.Real)
                or not (math.isfinite(timeout) and timeout >= 0)):
            raise ProfileStoreError(f"timeout must be a finite number of seconds >= 0, got {timeout!r}")
        super().__init__(path if path is not None else default_db_path(), timeout=timeout)

    def _setup_schema(self) -> None:
        self._migrate()

    def _version(self) -> int | None:
        """Recorded schema version; None for an empty (new) database."""
        con = self.con
        # one statement = one snapshot: another process may be creating the schema right now
        names = {r[0] for r in con.execute("SELECT name FROM sqlite_master WHERE name NOT LIKE 'sqlite_%'")}
        if "schema_version" not in names:
            if names:
                raise ProfileStoreError(
                    f"profile store {self.path}: the database has tables but no schema_version: "
                    "not a vigproc profile store (refusing to modify it)"
                )
            return None
        v = con.execute("SELECT max(version) FROM schema_version").fetchone()[0]
        return int(v) if v is not None else 0

    def _migrate(self) -> None:
        """Bring the schema to :data:`SCHEMA_VERSION` (idempotent; safe when several
        processes open a new store at once: the version is re-read under the lock)."""
        current = self._version()
        if current is not None and current > SCHEMA_VERSION:
            raise ProfileStoreError(
                f"profile store {self.path} has schema v{current}, newer than this vigproc (v{SCHEMA_VERSION})"
            )
        if current == SCHEMA_VERSION:
            return
        with self._txn() as con:  # retried by the caller (_retry_busy)
            current = self._version()
            if current is None:
                con.execute(
                    "CREATE TABLE schema_version (version INTEGER PRIMARY KEY, applied TEXT NOT NULL)"
                )
                current = 0
            if current > SCHEMA_VERSION:
                raise ProfileStoreError(
                    f"profile store {self.path} has schema v{current}, newer than this vigproc (v{SCHEMA_VERSION})"
                )
            for version in range(current + 1, SCHEMA_VERSION + 1):
                MIGRATIONS[version - 1](con)
                con.execute("INSERT INTO schema_version (version, applied) VALUES (?, ?)", (version, _now()))
                logger.info("profile store %s: migrated to schema v%d", self.path, version)

    @property
    def schema_version(self) -> int:
        """Schema version recorded in the database."""
        with self._errors("reading the schema version"):
            return int(self._version() or 0)

    # ------------------------------------------------------------ rows
    def _row_to_profile(self, row: sqlite3.Row | tuple) -> Profile:
        d = dict(zip(_COLUMNS, row))
        try:
            key = ProfileKey(d["lens_id"], d["focal_bin"], d["aperture_bin"], d["aspect"])
            exact = None
            if d["info_exact"] is not None:
                ej = json.loads(d["info_exact"])
                exact = (_Exact.from_json(ej["matrix"], N_PARAMS**2), _Exact.from_json(ej["vector"], N_PARAMS))
            welford = None
            if d["n_scatter"]:
                welford = _Welford(
                    int(d["n_scatter"]),
                    _unblob(d["theta_mean"], (N_PARAMS,), "theta_mean"),
                    _unblob(d["theta_m2"], (N_PARAMS, N_PARAMS), "theta_m2"),
                    _unblob(d["field_mean"], (FIELD_GRID**2,), "field_mean"),
                    _unblob(d["field_m2"], (FIELD_GRID**2,), "field_m2"),
                )
                if any(a is None for a in (welford.theta_mean, welford.theta_m2, welford.field_mean, welford.field_m2)):
                    raise ValueError("incomplete scatter state")
            return Profile(
                key=key,
                theta=_unblob(d["theta"], (N_PARAMS,), "theta"),
                covariance=_unblob(d["covariance"], (N_PARAMS, N_PARAMS), "covariance"),
                info_matrix=_unblob(d["info_matrix"], (N_PARAMS, N_PARAMS), "info_matrix"),
                info_vector=_unblob(d["info_vector"], (N_PARAMS,), "info_vector"),
                n_frames=int(d["n_frames"]),
                provenance=str(d["provenance"]),
                created=str(d["created"]),
                updated=str(d["updated"]),
                trusted=bool(d["trusted"]),
                field_sigma_ev=None if d["field_sigma_ev"] is None else float(d["field_sigma_ev"]),
                cov_sigma_ev=None if d["cov_sigma_ev"] is None else float(d["cov_sigma_ev"]),
                scatter_sigma_ev=None if d["scatter_sigma_ev"] is None else float(d["scatter_sigma_ev"]),
                notes=str(d["notes"]),
                shots=None if d["shots"] is None else Shots.from_json(json.loads(d["shots"]), "shots"),
                colour=None if d["colour"] is None else ColourPool.from_json(json.loads(d["colour"])),
                _exact=exact,
                _welford=welford,
            )
        except (ProfileStoreError, ModelError) as exc:
            raise ProfileStoreError(f"profile store {self.path}: corrupt profile row: {exc}") from None
        except (ValueError, TypeError, KeyError, json.JSONDecodeError) as exc:
            raise ProfileStoreError(
                f"profile store {self.path}: corrupt profile row for {d.get('lens_id')!r}: {exc}"
            ) from None

    def _profile_to_row(self, p: Profile) -> tuple:
        k = p.key
        exact = None
        if p._exact is not None:
            exact = json.dumps({"matrix": p._exact[0].to_json(), "vector": p._exact[1].to_json()}, separators=(",", ":"))
        w = p._welford
        return (
            k.lens_id, k.focal_bin, k.aperture_bin, k.aspect,
            _blob(p.theta), _blob(p.covariance), exact, _blob(p.info_matrix), _blob(p.info_vector),
            int(p.n_frames), int(w.n) if w is not None else 0,
            _blob(w.theta_mean) if w else None, _blob(w.theta_m2) if w else None,
            _blob(w.field_mean) if w else None, _blob(w.field_m2) if w else None,
            p.provenance, p.created, p.updated, int(bool(p.trusted)),
            p.field_sigma_ev, p.cov_sigma_ev, p.scatter_sigma_ev, p.notes,
            None if p.shots is None else json.dumps(p.shots.to_json(), ensure_ascii=False, separators=(",", ":")),
            None if p.colour is None else json.dumps(p.colour.to_json(), separators=(",", ":")),
        )

    def _select(self, where: str, args: tuple) -> builtins.list[Profile]:
        sql = f"SELECT {', '.join(_COLUMNS)} FROM profiles {where}"  # column names are constants
        rows = self.con.execute(sql, args).fetchall()
        return [self._row_to_profile(r) for r in rows]

    def _get(self, key: ProfileKey) -> Profile | None:
        found = self._select(
            "WHERE lens_id = ? AND focal_bin = ? AND aperture_bin = ? AND aspect = ?",
            (key.lens_id, key.focal_bin, key.aperture_bin, key.aspect),
        )
        return found[0] if found else None

    def _upsert(self, con: sqlite3.Connection, p: Profile) -> int:
        """Insert or update ``p``; returns its row id (kept across updates)."""
        cols = ", ".join(_COLUMNS)
        marks = ", ".join("?" for _ in _COLUMNS)
        updates = ", ".join(f"{c} = excluded.{c}" for c in _COLUMNS[4:])
        con.execute(
            f"INSERT INTO profiles ({cols}) VALUES ({marks}) "
            f"ON CONFLICT (lens_id, focal_bin, aperture_bin, aspect) DO UPDATE SET {updates}",
            self._profile_to_row(p),
        )
        return self._row_id(con, p.key)

    @staticmethod
    def _row_id(con: sqlite3.Connection, key: ProfileKey) -> int | None:
        row = con.execute(
            "SELECT id FROM profiles WHERE lens_id = ? AND focal_bin = ? AND aperture_bin = ? AND aspect = ?",
            (key.lens_id, key.focal_bin, key.aperture_bin, key.aspect),
        ).fetchone()
        return None if row is None else int(row[0])

    # ------------------------------------------------------------ API
    def get(self, key: ProfileKey) -> Profile | None:
        """The profile stored under exactly ``key``, or None.

        Raises
        ------
        ProfileStoreError
            ``key`` is not a :class:`ProfileKey`, or the store cannot be read.
        """
        _check_key(key, "get")
        with self._errors(f"reading {key}"):
            return self._get(key)

    def holds_frame(self, key: ProfileKey, frame_id: str) -> bool:
        """Whether the frame with content id ``frame_id`` was pooled into the profile
        stored under ``key`` (a forensic check must not use a frame's own evidence).

        Raises
        ------
        ProfileStoreError
            ``key`` is not a :class:`ProfileKey`, or the store cannot be read.
        """
        _check_key(key, "holds_frame")
        with self._errors(f"reading {key}"):
            row_id = self._row_id(self.con, key)
            if row_id is None:
                return False
            return self.con.execute("SELECT 1 FROM pooled_frames WHERE frame = ? AND profile_id = ?",
                                    (str(frame_id), row_id)).fetchone() is not None

    def key_for(self, lens_key: LensKey, width: int, height: int) -> ProfileKey:
        """The key a photograph's frames pool under: :meth:`ProfileKey.from_lens`, or, while
        only a lens id an earlier version gave this lens (``LensKey.legacy_ids``) has
        profiles, that id, so that a lens learned before keeps learning into its profiles.

        Raises
        ------
        ProfileStoreError
            As :meth:`ProfileKey.from_lens`, or the store cannot be read.
        """
        key = ProfileKey.from_lens(lens_key, width, height)
        legacy = getattr(lens_key, "legacy_ids", ())
        if not legacy:
            return key
        with self._errors(f"looking up {key}"):
            for lens_id in (key.lens_id, *legacy):
                if self.con.execute("SELECT 1 FROM profiles WHERE lens_id = ? LIMIT 1", (lens_id,)).fetchone():
                    return replace(key, lens_id=lens_id)
        return key

    def lookup(self, lens_key: LensKey, width: int, height: int, *, trusted_only: bool = False) -> Profile | None:
        """The profile to use for a photograph: :meth:`_lookup` of its lens id, else of the
        ids earlier versions gave the lens (``LensKey.legacy_ids``: stored profiles stay
        findable after a change of the lens-identity rule)."""
        hit = self._lookup(lens_key, width, height, trusted_only=trusted_only)
        for lens_id in getattr(lens_key, "legacy_ids", ()):
            if hit is not None:
                break
            make, model, lens = (unescape_key_part(p) for p in lens_id.split("|"))
            hit = self._lookup(replace(lens_key, make=make, model=model, lens=lens, legacy_ids=()), width, height,
                               trusted_only=trusted_only)
        return hit

    def _lookup(self, lens_key: LensKey, width: int, height: int, *, trusted_only: bool = False) -> Profile | None:
        """The profile to use for a photograph.

        1. The exact key (lens, focal bin, aperture bin, aspect).
        2. Else, with the focal length and f-number known, the lens's profiles at
           other bins interpolated to them (:func:`interpolate_profiles`: linear in
           log focal length and in stops, between the nearest bins on either side,
           never extrapolated), with the interpolated uncertainty.
        3. Else, for a known focal length, the neighbouring focal bin (±1 quarter
           octave) of the same lens, aperture bin and aspect whose centre is nearest
           the focal length (ties: trusted, then more frames).

        The aperture is never relaxed without a bin on either side (vignetting changes
        fastest with aperture near wide open), and ``"any"`` bins only match ``"any"``
        (a key without focal length is never merged with a real bin).

        Parameters
        ----------
        trusted_only : bool
            Ignore profiles that are not trusted (an interpolation is trusted when all
            the profiles it uses are and its uncertainty is below the bound).
        """
        key = ProfileKey.from_lens(lens_key, width, height)
        with self._errors(f"looking up {key}"):
            cands: builtins.list[Profile] = []
            exact = self._get(key)
            if exact is not None and (exact.trusted or not trusted_only):
                return exact
            if lens_key.focal_mm is None:
                return None
            if lens_key.fnumber is not None:
                same_lens = [p for p in self._select("WHERE lens_id = ? AND aspect = ?", (key.lens_id, key.aspect))
                             if p.trusted or not trusted_only]
                inter = interpolate_profiles(same_lens, key, float(lens_key.focal_mm), float(lens_key.fnumber))
                if inter is not None and (inter.trusted or not trusted_only):
                    return inter
            k = _focal_index(float(lens_key.focal_mm))
            for kk in (k - 1, k + 1):
                p = self._get(replace(key, focal_bin=_focal_label(kk)))
                if p is not None and (p.trusted or not trusted_only):
                    cands.append(p)
        if not cands:
            return None
        lf = math.log(float(lens_key.focal_mm))

        def rank(p: Profile) -> tuple[float, int, int]:
            centre = float(p.key.focal_bin[2:-2])
            return (round(abs(math.log(centre) - lf), 9), 0 if p.trusted else 1, -p.n_frames)

        best = min(cands, key=rank)
        logger.debug("no profile for %s; using neighbouring focal bin %s", key, best.key.focal_bin)
        return best

    def put(self, profile: Profile) -> None:
        """Insert or replace ``profile`` (imports; replaces any profile under its key)."""
        if not isinstance(profile, Profile):
            raise ProfileStoreError(f"put() needs a Profile, got {type(profile).__name__}")
        if not _valid_theta(profile.theta, profile.key.aspect_ratio):
            raise ProfileStoreError(
                f"profile {profile.key}: θ is not a valid model (P not positive semi-definite or G <= 0 in the frame)"
            )
        if profile.covariance is not None:
            _check_covariance(profile.covariance, f"profile {profile.key}", allow_fixed=True)

        def body(con: sqlite3.Connection) -> None:
            row_id = self._upsert(con, profile)
            # the stored evidence was replaced: no frame is pooled into it any more
            con.execute("DELETE FROM pooled_frames WHERE profile_id = ?", (row_id,))
            _drop_applied(con, profile.key)

        self._transact(f"storing {profile.key}", body)

    def import_file(self, path: str | os.PathLike[str]) -> Profile:
        """:func:`import_profile` then :meth:`put`; returns the stored profile."""
        p = import_profile(path)
        self.put(p)
        return p

    def learn(self, key: ProfileKey, model: VignettingModel, *, notes: str | None = None,
              frame_id: str | None = None, evidence: bytes | None = None,
              lens_key: LensKey | None = None) -> Profile:
        """Pool one frame's estimate into the profile under ``key``; returns the new profile.

        The frame adds Λ_i = Σ_i⁻¹ and η_i = Λ_i θ_i (normalised units) to the
        profile's exact sums; θ = Λ⁻¹η, covariance Λ⁻¹.  The Welford moments of θ and
        of the log2 field across frames are updated, and the trust flag recomputed.
        All of it is one ``BEGIN IMMEDIATE`` transaction: concurrent learners
        serialise and no frame is lost.

        If the pooled θ is not a valid model (P not PSD or G ≤ 0 in the frame; rare:
        information weighting is not a convex combination), the plain mean of the
        frames is used, else the previous θ is kept; a warning is logged.

        Learning onto an imported profile: a profile with a covariance acts as prior
        evidence; one without (no information) is superseded by the learned frames
        (provenance becomes "learned"; the notes say so).

        Parameters
        ----------
        frame_id : str, optional
            The frame's content id (e.g. the file's SHA-256).  A frame already pooled
            into this profile is not pooled again: the profile is returned unchanged.
            The id is recorded in the same transaction as the update, so a crash
            between pooling a frame and recording elsewhere that it was done (the
            daemon's or a batch job's journal) cannot make a rerun pool it twice.
        evidence : bytes, optional
            The frame's data (:func:`vigproc.core.estimate.frame_evidence`), kept with the
            frame.  Once frames of the profile have evidence, the profile's θ,
            covariance and σ are a robust centre (a multivariate t location under the
            scenes' scatter) of their lens-family fits
            (:mod:`vigproc.core.pooling`, at most :data:`MAX_POOLED_FRAMES` frames), which
            measured better than pooling the per-frame estimates and than the centred
            Kang-Weiss fits pooled until session 10 (``vigproc bench profile --clean``).
            The information sums are still kept.
            Needs ``frame_id`` (default: the SHA-256 of the evidence).
        lens_key : LensKey, optional
            The frame's EXIF: its focal length, crop factor and names as spelt are
            added to the profile's :attr:`Profile.shots`.

        Raises
        ------
        ProfileStoreError
            Arguments of the wrong type, no covariance in ``model``, aspect ratio
            not the key's, evidence that is not frame evidence, invalid values,
            database locked or corrupt.
        """
        # Checked up front: a bad argument must not surface as a raw error from
        # inside the transaction (``notes`` is only joined there).
        _check_key(key, "learn")
        if not isinstance(model, VignettingModel):
            raise ProfileStoreError(f"learn() needs a VignettingModel, got {type(model).__name__}")
        if notes is not None and not isinstance(notes, str):
            raise ProfileStoreError(f"notes must be a string, got {type(notes).__name__}")
        if evidence is not None:
            if not isinstance(evidence, bytes):
                raise ProfileStoreError(f"evidence must be bytes, got {type(evidence).__name__}")
            try:
                # fitted before the transaction: the refit below finds it in the cache
                frame_fit, frame_size = self._frame_fit(evidence)
            except VigprocError as exc:  # first: InvalidImageError (too few usable bins) is a ValueError too
                raise ProfileStoreError(f"nothing to learn from this frame: {exc}") from None
            except ValueError as exc:
                # the decoder's own wording (numpy's allow_pickle...) would only confuse
                logger.debug("evidence rejected: %s", exc)
                raise ProfileStoreError(
                    "evidence is not frame evidence (the bytes vigproc.core.estimate.frame_evidence returns)"
                ) from None
            if frame_id is None:
                frame_id = "evidence:" + hashlib.sha256(evidence).hexdigest()
        if lens_key is not None and not isinstance(lens_key, LensKey):
            raise ProfileStoreError(f"lens_key must be a LensKey, got {type(lens_key).__name__}")
        frame_shots = Shots.of_frame(lens_key) if lens_key is not None else None
        if frame_id is not None and (not isinstance(frame_id, str) or not frame_id or len(frame_id) > 256):
            raise ProfileStoreError(f"frame_id must be a non-empty string of at most 256 characters, got {frame_id!r}")
        if aspect_label(model.width / model.height) != key.aspect:
            raise ProfileStoreError(
                f"a {model.width}x{model.height} estimate ({aspect_label(model.width / model.height)}) "
                f"cannot refine the {key.aspect} profile {key}"
            )
        theta_i, lam_i, eta_i = frame_information(model)
        aspect = key.aspect_ratio
        field_i, _, gmin = _field_and_jacobian(theta_i, aspect)
        if not (gmin > 0 and np.all(np.isfinite(field_i))):
            raise ProfileStoreError(f"the estimate's geometric factor G falls to {gmin:.3g} inside the frame")
        add_lam, add_eta = _Exact.from_array(lam_i), _Exact.from_array(eta_i)
        if evidence is not None:
            # the scatter that matters is that of what the profile pools: the family fits
            from vigproc.core.pooling import coefficients_model

            try:
                theta_i = normalise(coefficients_model(frame_fit.coefficients, *frame_size, self._family))[0]
            except ModelError as exc:
                raise ProfileStoreError(f"unusable frame evidence: {exc}") from None
            field_i = _field_and_jacobian(theta_i, aspect)[0]

        def body(con: sqlite3.Connection) -> tuple[Profile | None, Profile]:
            old = self._get(key)
            if old is not None and frame_id is not None:
                seen = con.execute("SELECT 1 FROM pooled_frames WHERE frame = ? AND profile_id = ?",
                                   (frame_id, self._row_id(con, key))).fetchone()
                if seen is not None:
                    logger.info("profile %s: frame %s is already pooled; not again", key, frame_id[:16])
                    return old, old
            now = _now()
            extra = ""
            if old is None:
                exact, welford, n_frames = (add_lam, add_eta), _Welford.empty(), 1
                created, old_notes, prev_theta = now, "", None
            elif old._exact is None:
                # an import without uncertainty carries no information to pool with
                exact, welford, n_frames = (add_lam, add_eta), _Welford.empty(), 1
                created, old_notes, prev_theta = old.created, old.notes, None
                extra = f"learned frames superseded a {old.provenance} profile without uncertainty ({now})"
                logger.warning("profile %s: %s", key, extra)
            else:
                exact = (old._exact[0].add(add_lam), old._exact[1].add(add_eta))
                welford = old._welford if old._welford is not None else _Welford.empty()
                n_frames = old.n_frames + 1
                created, old_notes, prev_theta = old.created, old.notes, old.theta
                if old.provenance != "learned":
                    extra = f"seeded from a {old.provenance} profile"
            welford = welford.add(theta_i, field_i)
            lam = exact[0].to_array().reshape(N_PARAMS, N_PARAMS)
            eta = exact[1].to_array()
            # an import's fixed parameters carry no information: the frames decide them
            cov = _scaled_pinv(lam, f"pooled information of {key}", allow_fixed=True)
            theta = cov @ eta
            if not _valid_theta(theta, aspect):
                # with evidence the pooled refit below usually replaces θ: no need to alarm anyone
                say = logger.warning if evidence is None else logger.debug
                fallback = welford.theta_mean
                if _valid_theta(fallback, aspect):
                    say("profile %s: pooled θ is not a valid model; using the plain mean of the frames", key)
                    theta = fallback
                elif prev_theta is not None:
                    say("profile %s: pooled θ is not a valid model; keeping the previous θ", key)
                    theta = prev_theta
                else:
                    theta = theta_i
            pooled, cov_sigma, scatter = _profile_stats(theta, cov, aspect, welford)
            shots = old.shots if old is not None and old._exact is not None else None
            if frame_shots is not None:
                shots = frame_shots if shots is None else shots.add(frame_shots)
            note_parts = [s for s in (old_notes, extra if extra and extra not in old_notes else "", notes or "") if s]
            colour = old.colour if old is not None else None
            if model.colour is not None:
                mine = ColourPool.of(model.colour)
                colour = mine if colour is None else colour.add(mine)
            profile = Profile(
                key=key, theta=theta, covariance=cov, info_matrix=lam, info_vector=eta,
                n_frames=n_frames, provenance="learned", created=created, updated=now,
                trusted=_is_trusted(n_frames, pooled), field_sigma_ev=pooled, cov_sigma_ev=cov_sigma,
                scatter_sigma_ev=scatter, notes="\n".join(note_parts)[:MAX_NOTES], shots=shots, colour=colour,
                _exact=exact, _welford=welford,
            )
            row_id = self._upsert(con, profile)
            if frame_id is not None:
                con.execute("INSERT OR IGNORE INTO pooled_frames (frame, profile_id, pooled, evidence, family) "
                            "VALUES (?, ?, ?, ?, ?)", (frame_id, row_id, now, evidence,
                                                       None if evidence is None else
                                                       _fit_blob(frame_fit, frame_size)))
            if evidence is not None:
                refit = self._pooled_refit(con, row_id, key, frame_size)
                if refit is not None:
                    r_theta, r_cov, r_sigma, n_pooled = refit
                    _, cov_sigma, scatter = _profile_stats(r_theta, r_cov, aspect, welford)
                    # the pooled σ is the median's (vigproc.core.pooling), robust to the frames
                    # a scene fooled; the plain scatter of the frames is kept for reports
                    profile = replace(profile, theta=r_theta, covariance=r_cov, field_sigma_ev=r_sigma,
                                      cov_sigma_ev=cov_sigma, scatter_sigma_ev=scatter,
                                      trusted=_is_trusted(n_frames, r_sigma))
                    self._upsert(con, profile)
                    logger.debug("profile %s: pooled from %d frames' evidence", key, n_pooled)
            return old, profile

        old, profile = self._transact(f"learning {key}", body)
        if profile.trusted and not (old is not None and old.trusted):
            logger.info("profile %s is now trusted (%d frames, σ = %.4f EV)", key, profile.n_frames,
                        profile.field_sigma_ev)
        return profile

    def _frame_fit(self, blob: bytes) -> tuple[Any, tuple[int, int]]:
        """The lens-family fit of a frame's evidence (:func:`vigproc.core.pooling.frame_fit`)
        and the frame's size; cached by the evidence's SHA-256 (a caller's frame ids
        need not be unique across profiles).

        Raises
        ------
        ValueError
            Not frame evidence.
        VigprocError
            Too few usable bins for a fit.
        """
        from vigproc.core.pooling import frame_fit
        from vigproc.core.robust import evidence_copy

        digest = hashlib.sha256(blob).digest()
        cached = self._fit_cache.get(digest)
        if cached is None:
            wc = evidence_copy(blob)
            cached = (frame_fit(wc, self._family), (wc.width, wc.height))
            if len(self._fit_cache) >= _FIT_CACHE_SIZE:
                self._fit_cache.pop(next(iter(self._fit_cache)))
            self._fit_cache[digest] = cached
        return cached

    def _pooled_refit(self, con: sqlite3.Connection, row_id: int, key: ProfileKey,
                      frame_size: tuple[int, int]) -> tuple[np.ndarray, np.ndarray, float, int] | None:
        """θ, covariance (normalised) and field σ (EV) of the profile pooled from its
        frames' lens-family fits by :mod:`vigproc.core.pooling`, and how many frames it
        pooled; None when no frame's evidence gives a fit or the pooled model is not
        valid (the θ pooled from the frames' estimates stays)."""
        from vigproc.core.lensfamily import profile_family
        from vigproc.core.pooling import pool_family

        family = self._family or profile_family()
        fits = []
        # chosen in frame-id order: the same frames give the same profile whatever
        # order they came in (a batch job's workers finish in any order)
        rows = con.execute("SELECT frame, family FROM pooled_frames WHERE profile_id = ? AND evidence IS NOT NULL "
                           "ORDER BY frame LIMIT ?", (row_id, MAX_POOLED_FRAMES)).fetchall()
        missing = sum(blob is None for _, blob in rows)
        if missing > 10:
            logger.info("profile %s: fitting %d frames stored by an older vigproc (once)", key, missing)
        for frame, blob in rows:
            try:
                fit = _fit_from_blob(blob)[0] if blob is not None else None
                if fit is None or fit.coefficients.size != family.n_components:
                    # stored before v5 (or in another family): fit its evidence now, and keep the fit
                    (evidence,) = con.execute("SELECT evidence FROM pooled_frames WHERE frame = ? AND profile_id = ?",
                                              (frame, row_id)).fetchone()
                    fit, size = self._frame_fit(bytes(evidence))
                    con.execute("UPDATE pooled_frames SET family = ? WHERE frame = ? AND profile_id = ?",
                                (_fit_blob(fit, size), frame, row_id))
            except (ValueError, VigprocError) as exc:  # a damaged blob costs that frame, not the profile
                logger.warning("profile %s: skipping a frame's evidence: %s", key, exc)
                continue
            fits.append(fit)
        if not fits:
            return None
        try:
            m = pool_family(fits, *frame_size, family=family)
        except ModelError as exc:
            logger.warning("profile %s: pooling the frames failed (%s); keeping the pooled estimate", key, exc)
            return None
        theta, cov, _ = normalise(m)
        if cov is None or not _valid_theta(theta, key.aspect_ratio):
            logger.warning("profile %s: the pooled fit is not a valid model; keeping the pooled estimate", key)
            return None
        return theta, cov, float(m.quality.field_sigma_ev), len(fits)

    def list(self, lens_id: str | None = None) -> builtins.list[Profile]:
        """All profiles (of one ``lens_id`` if given), ordered by key."""
        order = "ORDER BY lens_id, aspect, focal_bin, aperture_bin"
        with self._errors("listing profiles"):
            if lens_id is None:
                return self._select(order, ())
            return self._select(f"WHERE lens_id = ? {order}", (lens_id,))

    def delete(self, key: ProfileKey) -> bool:
        """Delete the profile under ``key``; True if there was one.

        Raises
        ------
        ProfileStoreError
            ``key`` is not a :class:`ProfileKey`, or the store cannot be written.
        """
        _check_key(key, "delete")

        def body(con: sqlite3.Connection) -> bool:
            cur = con.execute(
                "DELETE FROM profiles WHERE lens_id = ? AND focal_bin = ? AND aperture_bin = ? AND aspect = ?",
                (key.lens_id, key.focal_bin, key.aperture_bin, key.aspect),
            )
            _drop_applied(con, key)
            return cur.rowcount > 0

        return bool(self._transact(f"deleting {key}", body))

    def applied_revision(self, key: ProfileKey) -> tuple[str, Profile] | None:
        """The revision of the profile under ``key`` that correct runs apply (shared by
        every worker and kept across restarts), as ``(revision id, profile)``; None when
        none was applied yet (or the stored one cannot be read: it is then replaced).

        Raises
        ------
        ProfileStoreError
            ``key`` is not a :class:`ProfileKey`, or the store cannot be read.
        """
        _check_key(key, "applied_revision")
        with self._errors(f"reading the applied revision of {key}"):
            return self._read_applied(self.con, key)

    def apply_revision(self, profile: Profile, *, replaces: str | None = None) -> tuple[str, Profile]:
        """Make ``profile`` the applied revision of its key, if no other worker got there
        first; returns the revision applied now, ``(revision id, profile)``.

        One ``BEGIN IMMEDIATE`` transaction: with ``replaces=None`` ``profile`` is
        written only when the key has no applied revision (else the one there is
        returned); with ``replaces=ID`` it replaces the applied revision only while that
        is still ``ID`` (compare-and-set: of two workers that both found the stored
        profile moved, one replaces it and the other follows).

        Parameters
        ----------
        profile : Profile
            The stored profile as the caller read it.
        replaces : str, optional
            The revision id the caller found applied.

        Returns
        -------
        tuple of (str, Profile)
            The revision id (16 hex digits of the SHA-256 of its JSON) and the
            profile as read back from its JSON.

        Raises
        ------
        ProfileStoreError
            ``profile`` is not a :class:`Profile`, or the store cannot be written.
        """
        if not isinstance(profile, Profile):
            raise ProfileStoreError(f"apply_revision() needs a Profile, got {type(profile).__name__}")
        text = json.dumps(profile_to_dict(profile), sort_keys=True, ensure_ascii=False, allow_nan=False)
        rev = hashlib.sha256(text.encode("utf-8")).hexdigest()[:16]
        key = profile.key

        def body(con: sqlite3.Connection) -> tuple[str, Profile]:
            held = self._read_applied(con, key)
            if held is not None and held[0] != replaces:
                return held  # another worker wrote (or replaced) it first: follow
            con.execute(
                "INSERT INTO applied_profiles (lens_id, focal_bin, aperture_bin, aspect, revision, n_frames, profile, "
                "applied) VALUES (?, ?, ?, ?, ?, ?, ?, ?) ON CONFLICT (lens_id, focal_bin, aperture_bin, aspect) "
                "DO UPDATE SET revision = excluded.revision, n_frames = excluded.n_frames, "
                "profile = excluded.profile, applied = excluded.applied",
                (key.lens_id, key.focal_bin, key.aperture_bin, key.aspect, rev, int(profile.n_frames), text, _now()),
            )
            return rev, profile_from_dict(json.loads(text), f"applied revision {rev} of {key}")

        return self._transact(f"applying a revision of {key}", body)

    def _read_applied(self, con: sqlite3.Connection, key: ProfileKey) -> tuple[str, Profile] | None:
        row = con.execute(
            "SELECT revision, profile FROM applied_profiles "
            "WHERE lens_id = ? AND focal_bin = ? AND aperture_bin = ? AND aspect = ?",
            (key.lens_id, key.focal_bin, key.aperture_bin, key.aspect),
        ).fetchone()
        if row is None:
            return None
        try:
            p = profile_from_dict(json.loads(row[1]), f"applied revision {row[0]} of {key}")
        except (ProfileStoreError, ValueError, TypeError) as exc:  # a damaged row is replaced, not fatal
            logger.warning("profile store %s: %s; it will be replaced", self.path, exc)
            return None
        if p.key != key:
            logger.warning("profile store %s: applied revision %s is of %s, not %s; it will be replaced",
                           self.path, row[0], p.key, key)
            return None
        return str(row[0]), p

    def check(self) -> builtins.list[str]:
        """``PRAGMA integrity_check`` and ``foreign_key_check``, plus decoding every
        row: the problems found (empty when the store is sound)."""
        problems: builtins.list[str] = []
        with self._errors("checking integrity"):
            rows = [str(r[0]) for r in self.con.execute("PRAGMA integrity_check(100)").fetchall()]
            if rows != ["ok"]:
                problems.extend(line for r in rows for line in r.splitlines() if line.strip())
            problems.extend(f"foreign key violation: {r}" for r in self.con.execute("PRAGMA foreign_key_check").fetchall())
            if not problems:
                for row in self.con.execute(f"SELECT {', '.join(_COLUMNS)} FROM profiles").fetchall():
                    try:
                        self._row_to_profile(row)
                    except ProfileStoreError as exc:
                        problems.append(str(exc))
        return problems

    def __repr__(self) -> str:
        return f"ProfileStore({str(self.path)!r})"


# --------------------------------------------------------------------------- #
# human-readable files
# --------------------------------------------------------------------------- #

_UNITS = {
    "center": "frame half-diagonals R = hypot(W, H)/2, from the frame centre; x right, y down",
    "p": "R^-2 (P = [[p1, p2], [p2, p3]], r^2 = (v - c)^T P (v - c) with v in units of R)",
    "alpha": "dimensionless (G = 1 - sum_i alpha_i r^i)",
    "covariance": "of the free parameters: (cx, cy, p1, p2, p3, alpha1..alpha7) in that order and the units "
                  "above, without those listed in 'fixed'",
}


def _drop_applied(con: sqlite3.Connection, key: ProfileKey) -> None:
    """Forget the applied revision of ``key`` (its profile was replaced or deleted)."""
    con.execute("DELETE FROM applied_profiles WHERE lens_id = ? AND focal_bin = ? AND aperture_bin = ? AND aspect = ?",
                (key.lens_id, key.focal_bin, key.aperture_bin, key.aspect))


def _split_lens_id(lens_id: str) -> dict[str, str | None]:
    parts = lens_id.split("|")
    if len(parts) == 4 and parts[3].startswith("sn:"):
        return {"make": unescape_key_part(parts[0]), "model": unescape_key_part(parts[1]),
                "lens": unescape_key_part(parts[2]), "lens_serial": unescape_key_part(parts[3][3:])}
    if len(parts) == 3:
        return {"make": unescape_key_part(parts[0]), "model": unescape_key_part(parts[1]),
                "lens": unescape_key_part(parts[2])}
    return {}


def profile_to_dict(profile: Profile) -> dict[str, Any]:
    """The ``vigproc.profile/2`` JSON object of ``profile``."""
    th = [float(v) for v in profile.theta]
    cov = profile.covariance
    fixed = fixed_indices(cov) if cov is not None else ()
    free = [i for i in range(N_PARAMS) if i not in fixed]
    d: dict[str, Any] = {
        "schema": FILE_SCHEMA,
        "lens": {**_split_lens_id(profile.key.lens_id), "lens_id": profile.key.lens_id},
        "focal_bin": profile.key.focal_bin,
        "aperture_bin": profile.key.aperture_bin,
        "aspect": profile.key.aspect,
        "provenance": profile.provenance,
        "n_frames": int(profile.n_frames),
        "trusted": bool(profile.trusted),
        "model": {
            "units": dict(_UNITS),
            "coordinates": "half-diagonal",
            "center": th[0:2],
            "p": th[2:5],
            "alpha": th[5:],
        },
        # a parameter the fit held fixed is named, not written as a zero variance (which no reader
        # can tell from a broken covariance)
        "fixed": [PARAM_NAMES[i] for i in fixed],
        "covariance": None if cov is None else [[float(cov[i, j]) for j in free] for i in free],
        "field_sigma_ev": profile.field_sigma_ev,
        "scatter_sigma_ev": profile.scatter_sigma_ev,
        "created": profile.created,
        "updated": profile.updated,
        "notes": profile.notes,
        "shots": None if profile.shots is None else profile.shots.to_json(),
    }
    if profile.colour is not None:
        # a colour field needs a reader that knows it: /3 (a colourless profile stays /2)
        d["schema"] = FILE_SCHEMA_COLOUR
        d["colour"] = profile.colour.to_json()
    return d


def export_profile(profile: Profile, path: str | os.PathLike[str]) -> None:
    """Write ``profile`` as a ``vigproc.profile/2`` JSON file, atomically.

    Raises
    ------
    vigproc.errors.ImageWriteError
        If the file cannot be written (the old file, if any, is left intact).
    """
    text = json.dumps(profile_to_dict(profile), indent=2, ensure_ascii=False, allow_nan=False) + "\n"
    atomic_write_text(path, text)


def _reject_constant(name: str) -> Any:
    raise ValueError(f"{name} is not a number JSON allows")


def _no_duplicates(pairs: builtins.list[tuple[str, Any]]) -> dict[str, Any]:
    d: dict[str, Any] = {}
    for k, v in pairs:
        if k in d:
            raise ValueError(f"duplicate field {k!r}")
        d[k] = v
    return d


def _numbers(value: Any, n: int, where: str, name: str) -> np.ndarray:
    if not isinstance(value, list) or len(value) != n:
        raise ProfileStoreError(f"{where}: {name} must be a list of {n} numbers")
    if not all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in value):
        raise ProfileStoreError(f"{where}: {name} must contain only numbers")
    a = np.asarray(value, dtype=np.float64)
    if not np.all(np.isfinite(a)):
        raise ProfileStoreError(f"{where}: {name} contains NaN or Inf")
    return a


def _opt_text(d: dict[str, Any], name: str, where: str) -> str | None:
    v = d.get(name)
    if v is None:
        return None
    if not isinstance(v, str):
        raise ProfileStoreError(f"{where}: {name} must be a string or null, got {type(v).__name__}")
    return v


def _timestamp(d: dict[str, Any], name: str, where: str) -> str:
    v = _opt_text(d, name, where)
    if v is None:
        return ""
    try:
        datetime.fromisoformat(v.replace("Z", "+00:00"))
    except ValueError:
        raise ProfileStoreError(f"{where}: {name} {v!r} is not an ISO 8601 timestamp") from None
    return v


def profile_from_dict(d: Any, where: str = "profile") -> Profile:
    """Validate a ``vigproc.profile/1`` object and build the :class:`Profile`.

    Raises
    ------
    ProfileStoreError
        Naming ``where`` and the offending field.
    """
    if not isinstance(d, dict):
        raise ProfileStoreError(f"{where}: a profile must be a JSON object")
    schema = d.get("schema")
    if schema not in FILE_SCHEMAS:
        raise ProfileStoreError(f"{where}: schema must be one of {', '.join(map(repr, FILE_SCHEMAS))}, got {schema!r}")
    for req in ("lens", "focal_bin", "aperture_bin", "aspect", "provenance", "model"):
        if req not in d:
            raise ProfileStoreError(f"{where}: missing field {req!r}")

    # identity
    lens = d["lens"]
    if not isinstance(lens, dict):
        raise ProfileStoreError(f"{where}: lens must be an object with make, model, lens and/or lens_id")
    names = {k: _opt_text(lens, k, f"{where}: lens") for k in ("make", "model", "lens", "lens_serial")}
    norm = {k: (normalise_text(v) if v is not None else None) for k, v in names.items()}
    derived = None
    if norm["model"] is not None or norm["lens"] is not None:
        derived = LensKey(make=norm["make"], model=norm["model"], lens=norm["lens"], lens_serial=norm["lens_serial"]).lens_id(
            with_serial=norm["lens_serial"] is not None
        )
    lens_id = lens.get("lens_id")
    if lens_id is None:
        if derived is None:
            raise ProfileStoreError(f"{where}: lens needs lens_id or at least model or lens")
        lens_id = derived
    else:
        try:
            _check_lens_id(lens_id)
        except ProfileStoreError as exc:
            raise ProfileStoreError(f"{where}: lens.lens_id: {exc}") from None
        if derived is not None and derived != lens_id:
            raise ProfileStoreError(
                f"{where}: lens.lens_id {lens_id!r} does not match make/model/lens (which give {derived!r})"
            )

    try:
        key = ProfileKey(
            lens_id,
            _canonical_focal(d["focal_bin"], where),
            _canonical_aperture(d["aperture_bin"], where),
            _canonical_aspect(d["aspect"], where),
        )
    except ProfileStoreError as exc:
        msg = str(exc)
        raise ProfileStoreError(msg if msg.startswith(where) else f"{where}: {msg}") from None

    prov = d["provenance"]
    if prov not in PROVENANCES:
        raise ProfileStoreError(f"{where}: provenance must be one of {', '.join(PROVENANCES)}, got {prov!r}")
    n_frames = d.get("n_frames", 0)
    if isinstance(n_frames, bool) or not isinstance(n_frames, int) or not 0 <= n_frames <= MAX_FRAMES:
        raise ProfileStoreError(f"{where}: n_frames must be an integer 0..{MAX_FRAMES}, got {n_frames!r}")
    trusted_claim = d.get("trusted")
    if trusted_claim is not None and not isinstance(trusted_claim, bool):
        raise ProfileStoreError(f"{where}: trusted must be true, false or absent")
    notes = d.get("notes", "")
    if notes is None:
        notes = ""
    if not isinstance(notes, str) or len(notes) > MAX_NOTES:
        raise ProfileStoreError(f"{where}: notes must be a string of at most {MAX_NOTES} characters")

    # parameters
    m = d["model"]
    if not isinstance(m, dict):
        raise ProfileStoreError(f"{where}: model must be an object")
    for req in ("coordinates", "center", "p", "alpha"):
        if req not in m:
            raise ProfileStoreError(f"{where}: missing field 'model.{req}'")
    if m["coordinates"] != "half-diagonal":
        raise ProfileStoreError(
            f"{where}: model.coordinates must be 'half-diagonal' (parameters in frame half-diagonals), got {m['coordinates']!r}"
        )
    c = _numbers(m["center"], 2, where, "model.center")
    p = _numbers(m["p"], 3, where, "model.p")
    a = _numbers(m["alpha"], N_ALPHA, where, "model.alpha")
    if np.any(np.abs(c) > MAX_ABS_CENTER):
        raise ProfileStoreError(f"{where}: model.center {c.tolist()} is absurd (more than {MAX_ABS_CENTER} half-diagonals off centre)")
    if np.any(np.abs(p) > MAX_SHAPE):
        raise ProfileStoreError(f"{where}: model.p {p.tolist()} is absurd (|p| > {MAX_SHAPE:g} R^-2)")
    if np.any(np.abs(a) > MAX_ABS_ALPHA):
        raise ProfileStoreError(f"{where}: model.alpha {a.tolist()} is absurd (|alpha| > {MAX_ABS_ALPHA:g})")
    theta = np.concatenate([c, p, a])
    # P PSD and G > 0 inside the frame, checked through the model itself on a small grid
    asp = key.aspect_ratio
    h = 120
    w = max(2, round(h * asp))
    try:
        lf = denormalise(theta, None, w, h).log_field((h, w)) / _LN2
    except ModelError as exc:
        raise ProfileStoreError(f"{where}: model: {exc}") from None
    if lf.min() < -MAX_FALLOFF_EV or lf.max() > MAX_GAIN_EV:
        raise ProfileStoreError(
            f"{where}: model: the field spans {lf.min():.2f}..{lf.max():.2f} EV inside the frame "
            f"(absurd: allowed -{MAX_FALLOFF_EV:g}..+{MAX_GAIN_EV:g} EV)"
        )

    cov_a = _file_covariance(d, schema, where)
    sigma = d.get("field_sigma_ev")
    if sigma is not None and (isinstance(sigma, bool) or not isinstance(sigma, (int, float))
                              or not (math.isfinite(sigma) and 0 <= sigma <= MAX_FALLOFF_EV)):
        raise ProfileStoreError(f"{where}: field_sigma_ev must be a number of EV in 0..{MAX_FALLOFF_EV:g} or null")
    shots = None if d.get("shots") is None else Shots.from_json(d["shots"], where)
    colour = None
    if d.get("colour") is not None:
        if schema != FILE_SCHEMA_COLOUR:
            raise ProfileStoreError(f"{where}: a colour field needs schema {FILE_SCHEMA_COLOUR!r}, got {schema!r}")
        try:
            colour = ColourPool.from_json(d["colour"])
        except ModelError as exc:
            raise ProfileStoreError(f"{where}: colour: {exc}") from None
    created = _timestamp(d, "created", where)
    updated = _timestamp(d, "updated", where)

    exact = None
    lam = eta = None
    if cov_a is not None:
        lam = _scaled_pinv(cov_a, f"{where}: covariance", allow_fixed=True)
        eta = lam @ theta
        exact = (_Exact.from_array(lam), _Exact.from_array(eta))
    pooled, cov_sigma, _ = _profile_stats(theta, cov_a, asp, None)
    if sigma is not None and cov_a is not None:
        # the σ the profile was trusted on (a learned one's is its frames' median's, which its
        # covariance alone does not give): the file travels with the same trust
        pooled = float(sigma)
    trusted = trusted_claim if trusted_claim is not None else _is_trusted(n_frames, pooled)
    return Profile(
        key=key, theta=theta, covariance=cov_a, info_matrix=lam, info_vector=eta, n_frames=n_frames,
        provenance=prov, created=created, updated=updated or created, trusted=trusted,
        field_sigma_ev=pooled, cov_sigma_ev=cov_sigma, scatter_sigma_ev=None, notes=notes, shots=shots,
        colour=colour, _exact=exact,
    )


def _file_covariance(d: dict[str, Any], schema: str, where: str) -> np.ndarray | None:
    """The 12×12 covariance of a profile file (zero rows and columns for its fixed
    parameters), or None.  ``/1``: a 12×12 matrix; ``/2``: ``fixed`` names the
    parameters held fixed and the matrix covers the others, in :data:`PARAM_NAMES` order."""
    cov = d.get("covariance")
    fixed_names = d.get("fixed", [])
    if schema == "vigproc.profile/1":
        fixed_names = []
    if not (isinstance(fixed_names, list) and all(isinstance(v, str) for v in fixed_names)):
        raise ProfileStoreError(f"{where}: fixed must be a list of parameter names")
    unknown = [v for v in fixed_names if v not in PARAM_NAMES]
    if unknown or len(set(fixed_names)) != len(fixed_names):
        raise ProfileStoreError(f"{where}: fixed {fixed_names!r} must name distinct parameters of "
                                f"{', '.join(PARAM_NAMES)}")
    if cov is None:
        return None
    free = [i for i, name in enumerate(PARAM_NAMES) if name not in fixed_names]
    n = len(free)
    if not free:
        raise ProfileStoreError(f"{where}: fixed names every parameter; the covariance must be null")
    if not (isinstance(cov, list) and len(cov) == n and all(isinstance(r, list) and len(r) == n for r in cov)):
        raise ProfileStoreError(f"{where}: covariance must be a {n}x{n} list of lists (the parameters not "
                                "in 'fixed') or null")
    sub = np.asarray([_numbers(r, n, where, "covariance") for r in cov])
    full = np.zeros((N_PARAMS, N_PARAMS))
    full[np.ix_(free, free)] = sub
    if fixed_names and not np.all(np.diag(sub) > 0):
        raise ProfileStoreError(f"{where}: covariance has a non-positive variance (a parameter held fixed "
                                "belongs in 'fixed')")
    # /1 files of learned profiles wrote a fixed parameter as an all-zero row: read it as fixed
    cov_a = _check_covariance(full, f"{where}: covariance", allow_fixed=True)
    if float(np.max(np.diag(cov_a))) > MAX_FILE_VARIANCE:  # a standard deviation of 10⁴ says nothing
        raise ProfileStoreError(f"{where}: covariance has a variance of {float(np.max(np.diag(cov_a))):.3g}, "
                                f"above {MAX_FILE_VARIANCE:g} (use null for an unknown uncertainty)")
    return cov_a


def import_profile(path: str | os.PathLike[str]) -> Profile:
    """Read and validate a ``vigproc.profile/2`` (or ``/1``) file (does not touch any store).

    Checks: size, JSON syntax (NaN/Infinity and duplicate fields rejected), schema,
    required fields and their types, bin labels, provenance, finite parameters
    within sane bounds, P positive semi-definite, G > 0 and a plausible fall-off
    inside the frame, covariance symmetric PSD.  A ``trusted`` value in the file is
    honoured; without it, trust follows the rule of learned profiles.

    Raises
    ------
    ProfileStoreError
        Naming the file and the field.
    """
    where = str(path)
    try:
        st = os.stat(path)
        if not stat.S_ISREG(st.st_mode):  # a FIFO or device would block or never end
            raise ProfileStoreError(f"{where}: not a regular file")
        size = st.st_size
        if size > MAX_FILE_BYTES:
            raise ProfileStoreError(f"{where}: {size} bytes is too large for a profile file (limit {MAX_FILE_BYTES})")
        with open(path, "rb") as fh:
            raw = fh.read(MAX_FILE_BYTES + 1)
    except OSError as exc:
        raise ProfileStoreError(f"cannot read profile file {where}: {exc.strerror or exc}") from None
    try:
        text = raw.decode("utf-8")
        d = json.loads(text, parse_constant=_reject_constant, object_pairs_hook=_no_duplicates)
    except UnicodeDecodeError as exc:
        raise ProfileStoreError(f"{where}: not UTF-8 text ({exc.reason} at byte {exc.start})") from None
    except (json.JSONDecodeError, ValueError, RecursionError) as exc:  # RecursionError: absurdly nested
        raise ProfileStoreError(f"{where}: not valid profile JSON: {exc}") from None
    return profile_from_dict(d, where)
