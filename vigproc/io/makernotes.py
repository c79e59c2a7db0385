"""The camera maker's own vignetting calibration, read from a raw file's metadata.

Some cameras store the vignetting of the lens on the frame they took in the raw file,
for the raw converter to remove: Sony in the ARW's raw IFD, Fujifilm in the RAF's
FujiIFD.  darktable's lens module ("embedded metadata" mode) reads both; this module
reads them the way darktable 4.2.1 does (``src/common/exif.cc``
``_check_lens_correction_data``, ``src/iop/lens.cc`` ``_init_coeffs_md`` and
``_process_md``), through exiftool (the one :class:`vigproc.io.exif.ExifReader`).

Sony -- ``SubIFD:VignettingCorrParams`` (tag 0x7032 of the raw IFD, where darktable reads
it; the copies in the encrypted SR2SubIFD and in the maker notes' Tag9416/940c are not read):
int16, the count n ≤ 16 first, then n values v_i.  The knots lie at radii
r_i = (i + ½)/(n − 1) and carry s_i = 2^(½ − 2^(v_i·2⁻¹³ − 1)).
Fujifilm -- ``FujiIFD:VignettingParams`` (RAF tag 0xf010): 19 rationals, [1..9] the
knots' radii r_i and [10..18] the brightness V_i in percent: s_i = V_i/100; the radii are
multiplied by 1.25 when ``CropMode`` is 2 or 4 (the camera's 1.25× crop modes).

For both, r is the distance from the centre of the frame over its half-diagonal,
s(r) the linear interpolation between the knots (held beyond the first and the last),
and darktable divides the pixel by s(r)²: the attenuation the calibration describes is
φ(r) = s(r)².  That darktable applies exactly this is measured
(``scripts/bench_darktable_dng.py``, docs/benchmarks/dng.md); that it is what the camera
means is darktable's reading of undocumented tags, not checked here against the
camera's own JPEG.

Not read: Olympus/OM System and Panasonic store distortion and chromatic aberration,
no vignetting darktable or exiftool decode; Canon's ``VignettingCorr`` maker notes hold
the in-camera correction's settings, not a curve; Fujifilm files with another count
than 19 (older and newer models) are reported as not understood.

:class:`MakerNoteCalibration` is used like a DNG's opcodes
(:class:`vigproc.io.dng_vignette.EmbeddedCalibration`): a profile source
(``--profile embedded`` and ``auto``) whose correction divides out the curve itself
(:class:`vigproc.io.dng_vignette.GainFieldModel`), with its Kang-Weiss fit and the fit's
error stated, and a forensic reference for ``vigproc check``.
:func:`calibration_for` picks a file's calibration: a DNG's opcodes first (they describe
the DNG's own frame), else the maker notes.
"""

from __future__ import annotations

import logging
import math
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Mapping, Sequence

import numpy as np

from vigproc.errors import ImageReadError, VigprocError, one_line
from vigproc.io.formats import CALIBRATED_RAW_SUFFIXES

__all__ = [
    "MAKERNOTE_TAGS",
    "MakerNoteCalibration",
    "MakerNoteError",
    "calibration_for",
    "from_tags",
    "read_makernote",
]

logger = logging.getLogger(__name__)

#: Tags read (exiftool family-1 group names, numeric values).
SONY_TAG = "SubIFD:VignettingCorrParams"
FUJI_TAG = "FujiIFD:VignettingParams"
FUJI_CROP_TAG = "FujiFilm:CropMode"
MAKERNOTE_TAGS = (SONY_TAG, FUJI_TAG, FUJI_CROP_TAG)
#: File suffixes whose metadata may carry a maker's calibration (raw files).
RAW_SUFFIXES = CALIBRATED_RAW_SUFFIXES
#: Attenuations outside this range are no vignetting calibration (a corrupt file).
PHI_RANGE = (1.0 / 256.0, 1.5)
_LN2 = math.log(2.0)


class MakerNoteError(ImageReadError):
    """A maker's vignetting tag is present but malformed (wrong count, values out of range)."""


def _numbers(value: Any, what: str) -> list[float]:
    """exiftool's numeric value of a list tag (``"16 0 7 ..."`` or a JSON list) as floats."""
    if isinstance(value, (int, float)) and not isinstance(value, bool):
        items: Sequence[Any] = [value]
    elif isinstance(value, str):
        items = value.split()
    elif isinstance(value, list):
        items = value
    else:
        raise MakerNoteError(f"{what}: not a list of numbers ({type(value).__name__})")
    out = []
    for v in items:
        try:
            x = float(v)
        except (TypeError, ValueError):
            raise MakerNoteError(one_line(f"{what}: {str(v)[:20]!r} is not a number")) from None
        if not math.isfinite(x):
            raise MakerNoteError(f"{what}: a value is not finite")
        out.append(x)
    return out


@dataclass(frozen=True, eq=False)
class MakerNoteCalibration:
    """A maker's radial vignetting curve: φ(r) = s(r)², s linear between knots.

    Attributes
    ----------
    maker : str
        ``sony`` or ``fujifilm``.
    tag : str
        The tag it was read from.
    source : str
        The file (for messages and records).
    knots : tuple of float
        Radii (over the frame's half-diagonal), increasing.
    scale : tuple of float
        s at each knot (the correction divides by s²).
    values : tuple of float
        The tag's values the curve was made from (for records).
    """

    maker: str
    tag: str
    source: str
    knots: tuple[float, ...]
    scale: tuple[float, ...]
    values: tuple[float, ...] = ()
    _fits: dict = field(default_factory=dict, repr=False)

    def __post_init__(self) -> None:
        k = np.asarray(self.knots, dtype=np.float64)
        s = np.asarray(self.scale, dtype=np.float64)
        if k.ndim != 1 or k.size < 2 or k.shape != s.shape:
            raise MakerNoteError(f"{self.tag}: needs at least two knots with a value each")
        if not (np.all(np.isfinite(k)) and np.all(np.isfinite(s))):
            raise MakerNoteError(f"{self.tag}: knots or values are not finite")
        if np.any(np.diff(k) <= 0) or k[0] < 0 or k[-1] > 4:
            raise MakerNoteError(f"{self.tag}: knot radii must increase within [0, 4]")
        phi = s * s
        if not (PHI_RANGE[0] <= phi.min() and phi.max() <= PHI_RANGE[1]):
            raise MakerNoteError(one_line(
                f"{self.tag}: attenuations {phi.min():.3g}..{phi.max():.3g} are no vignetting calibration "
                f"(allowed {PHI_RANGE[0]:.3g}..{PHI_RANGE[1]:.3g})"))

    # the interface of vigproc.io.dng_vignette.EmbeddedCalibration -------------------------

    @property
    def kind(self) -> str:
        return f"{self.maker}:{self.tag.split(':')[-1]}"

    @property
    def label(self) -> str:
        """How a verdict names this reference."""
        return f"the camera's own {self.tag.split(':')[-1]} ({self.maker})"

    has_gain_map = False

    def describe(self) -> list[str]:
        phi = np.square(self.scale)
        return [f"{self.tag} ({self.maker}): {len(self.knots)} knots r {self.knots[0]:.3f}..{self.knots[-1]:.3f}, "
                f"fall-off {float(np.log2(phi.min())):+.2f} EV at most"]

    def log_phi_r(self, r: np.ndarray) -> np.ndarray:
        """ln φ at radii ``r`` (over the half-diagonal)."""
        s = np.interp(np.asarray(r, dtype=np.float64), self.knots, self.scale)
        return 2.0 * np.log(s)

    def log_gain(self, width: int, height: int, channel: int | None = None, *,
                 rel: tuple[np.ndarray, np.ndarray] | None = None) -> np.ndarray:
        """ln g = −ln φ of a ``width``×``height`` frame (every channel alike), at its pixel
        centres or at the relative positions ``rel`` (down, across); see
        :meth:`vigproc.io.dng_vignette.EmbeddedCalibration.log_gain`."""
        rv, rh = rel if rel is not None else ((np.arange(height) + 0.5) / height, (np.arange(width) + 0.5) / width)
        y = (np.asarray(rv, dtype=np.float64) - 0.5) * height
        x = (np.asarray(rh, dtype=np.float64) - 0.5) * width
        r = np.hypot(y[:, None], x[None, :]) / math.hypot(width / 2.0, height / 2.0)
        return -self.log_phi_r(r)

    def fit(self, width: int, height: int):
        """The Kang-Weiss model closest to the curve on a ``width``×``height`` frame and its
        RMS and largest error over the frame, EV (:func:`vigproc.io.dng_vignette.fit_log_field`).

        Raises
        ------
        ModelError
            No model fits.
        """
        from vigproc.io.dng_vignette import cached_fit

        return cached_fit(self, width, height, f"makernote:{self.maker}", self.tag)

    def model(self, width: int, height: int):
        """The model a ``width``×``height`` frame is corrected with: its parameters are the
        Kang-Weiss fit (records, pictures, comparisons), its correction divides out the
        curve itself (:class:`vigproc.io.dng_vignette.GainFieldModel`)."""
        from vigproc.io.dng_vignette import GainFieldModel

        m, _, _ = self.fit(width, height)
        return GainFieldModel(m.width, m.height, m.center, m.p, m.alpha, method=m.method, quality=m.quality,
                              calibration=self)

    def to_dict(self, width: int | None = None, height: int | None = None) -> dict[str, Any]:
        d: dict[str, Any] = {"source": self.source, "kind": self.kind, "maker": self.maker, "tag": self.tag,
                             "knots": list(self.knots), "scale": list(self.scale), "opcodes": self.describe()}
        if width and height:
            _, rms, mx = self.fit(width, height)
            d.update(fit_rms_ev=rms, fit_max_ev=mx)
        return d


def _sony(values: list[float], tag: str, source: str) -> MakerNoteCalibration | None:
    if not values:
        return None
    n = values[0]
    if n != int(n) or not 2 <= n <= 16 or len(values) < int(n) + 1:
        raise MakerNoteError(one_line(f"{source}: {tag}: count {values[0]:g} with {len(values) - 1} values "
                                      "(expected 2..16 values after the count)"))
    n = int(n)
    v = np.asarray(values[1:n + 1])
    if np.any(np.abs(v) > 32768):
        raise MakerNoteError(f"{source}: {tag}: values outside int16")
    if not np.any(v):
        return None  # all zero: no correction
    knots = (np.arange(n) + 0.5) / (n - 1)
    scale = 2.0 ** (0.5 - 2.0 ** (v * 2.0 ** -13 - 1.0))
    return MakerNoteCalibration("sony", tag, source, tuple(knots), tuple(float(s) for s in scale),
                                tuple(values[:n + 1]))


def _fuji(values: list[float], crop_mode: Any, tag: str, source: str) -> MakerNoteCalibration | None:
    if len(values) != 19:
        raise MakerNoteError(one_line(f"{source}: {tag}: {len(values)} values; only the 19-value layout "
                                      "(9 knots, as darktable 4.2 reads it) is understood"))
    cropf = 1.25 if crop_mode in (2, 4, "2", "4") else 1.0
    knots = np.asarray(values[1:10]) * cropf
    v = np.asarray(values[10:19])
    if np.all(v == 100.0):
        return None
    return MakerNoteCalibration("fujifilm", tag, source, tuple(float(k) for k in knots),
                                tuple(float(x) / 100.0 for x in v), tuple(values))


def from_tags(tags: Mapping[str, Any], source: str = "metadata") -> MakerNoteCalibration | None:
    """The calibration in exiftool's record ``tags`` (family-1 group names, numeric
    values: ``exiftool -G1 -n``), or None when it has none.

    Raises
    ------
    MakerNoteError
        A vignetting tag is present but malformed.
    """
    if SONY_TAG in tags:
        return _sony(_numbers(tags[SONY_TAG], f"{source}: {SONY_TAG}"), SONY_TAG, source)
    if FUJI_TAG in tags:
        return _fuji(_numbers(tags[FUJI_TAG], f"{source}: {FUJI_TAG}"), tags.get(FUJI_CROP_TAG), FUJI_TAG, source)
    return None


def read_makernote(path: str | os.PathLike[str], reader=None) -> MakerNoteCalibration | None:
    """The maker's vignetting calibration in the file's metadata, or None.

    Parameters
    ----------
    path : path-like
    reader : vigproc.io.exif.ExifReader, optional
        The exiftool process to ask (default: one of its own for this call).

    Raises
    ------
    ImageReadError
        exiftool cannot read the file.
    MakerNoteError
        A vignetting tag is malformed.
    """
    from vigproc.io.exif import ExifReader

    if reader is None:
        with ExifReader() as own:
            tags = own.read_tags(path, MAKERNOTE_TAGS)
    else:
        tags = reader.read_tags(path, MAKERNOTE_TAGS)
    return from_tags(tags, os.path.abspath(os.fspath(path)))


def calibration_for(path: str | os.PathLike[str], profile: str, reader=None):
    """The file's own calibration when the profile choice can use it (``auto`` or
    ``embedded``): a DNG's vignetting opcodes
    (:func:`vigproc.io.dng_vignette.embedded_for`), else the maker's calibration of a raw
    file (:func:`read_makernote`); None when there is none.

    The opcodes win: they describe the DNG's own frame, while maker notes a converter
    copied describe the camera's (which a crop may have changed).  With ``auto`` a
    calibration that cannot be read is only logged (the frame is estimated instead);
    with ``embedded`` the error is raised.

    Raises
    ------
    ImageReadError
        ``profile == "embedded"`` and the calibration cannot be read (DngOpcodeError,
        MakerNoteError included).
    """
    from vigproc.io.dng_vignette import embedded_for

    if profile not in ("auto", "embedded"):
        return None
    cal = embedded_for(path, profile)
    if cal is not None or Path(path).suffix.lower() not in RAW_SUFFIXES:
        return cal
    try:
        return read_makernote(path, reader)
    except VigprocError as exc:
        if profile == "embedded":
            raise
        logger.warning("%s: its maker's vignetting calibration is not used: %s", os.fspath(path), exc)
        return None
