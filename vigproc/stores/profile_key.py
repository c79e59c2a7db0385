"""The key of a lens profile (:class:`ProfileKey`: lens, focal-length bin, aperture bin,
frame aspect ratio), its bins, and the constants shared by the profile modules."""

from __future__ import annotations

import math
import numbers
import re
import unicodedata
from dataclasses import dataclass
from datetime import datetime, timezone
from typing import Any

from vigproc.errors import ProfileStoreError
from vigproc.io.exif import LensKey

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
#: Schema of a profile file with a measured grid field (``grid``: a pooled
#: :class:`vigproc.stores.profile_grid.GridPool`); one without is still ``/2`` or ``/3``.
#: vigproc before ``/4`` refuses such a file ("schema must be one of ...").
FILE_SCHEMA_GRID = "vigproc.profile/4"
FILE_SCHEMAS = ("vigproc.profile/1", FILE_SCHEMA, FILE_SCHEMA_COLOUR, FILE_SCHEMA_GRID)
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
