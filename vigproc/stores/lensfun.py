"""Calibrated lens vignetting from the lensfun database bundled with lensfunpy.

lensfunpy (PyPI) ships lensfun 0.3.4 together with lensfun's XML database
(``lensfunpy/db_files/*.xml``, database format version 1).  This module
parses those XML files directly with :mod:`xml.etree.ElementTree`; it needs
the lensfunpy *package files* but never imports lensfunpy's C extension.

The vignetting model
--------------------
lensfun's only vignetting model is ``pa`` (Pablo d'Angelo's model, used by
Hugin).  lensfun describes it as (``lfLens::GetVignettingModelDesc``)::

    Cd = Cs * (1 + k1 * R^2 + k2 * R^4 + k3 * R^6)

i.e. the recorded value ``Cd`` is the true value ``Cs`` times the attenuation
``1 + k1 r^2 + k2 r^4 + k3 r^6``.

Radius normalisation (verified)
-------------------------------
The block comment "About coordinate systems in Lensfun" in lensfun's
``modifier.cpp`` states: "For vignetting, r = 1 is the corner of the image".
In code, ``lfModifier::lfModifier`` builds the normalised pixel scale from
``coordinate_correction = 1/sqrt(ar_img^2 + 1) * calib_crop / crop *
sqrt(ar_lens^2 + 1)`` and ``lfModifier::AddColorCallbackVignetting``
(``mod-color.cpp``) multiplies coordinates by ``1 / sqrt(ar_lens^2 + 1)``.
The lens aspect-ratio factors cancel, so a pixel at distance ``d`` from the
centre has ``r = d / half_diagonal_of_image * calib_crop / image_crop``: r is
1 at the image corner when the image has the calibration crop factor (the
calibration aspect ratio does not enter).  For an image with crop factor
``c``, the corner lies at ``r = lens.crop_factor / c``.

This was also checked numerically against lensfun itself (lensfunpy 1.18,
``Modifier.apply_color_modification`` with ``reverse=True`` on an all-ones
image): the corner value equals ``1 + k1 + k2 + k3`` to float32 precision for
landscape, portrait and square images.  One small difference remains on
purpose: lensfun places the centre of the long image axis at
``W (S - 1) / (2 S)`` (``S`` = short side) rather than ``(W - 1) / 2``;
:func:`pa_field` uses the exact pixel centre ``((W-1)/2, (H-1)/2)`` and
the exact half-diagonal, a sub-pixel difference.

Interpolation (verified)
------------------------
See :func:`interpolate_pa`; it follows ``lfLens::InterpolateVignetting`` and
``__vignetting_dist`` in lensfun's ``lens.cpp`` (lensfun 0.3.x, preserved as
``libs/lensfun/legacy/legacy-lens.cpp`` in lensfun's repository).

References
----------
.. [1] lensfun, ``libs/lensfun/lens.cpp``: ``GetVignettingModelDesc``,
   ``__vignetting_dist``, ``InterpolateVignetting`` (0.3.x;
   ``libs/lensfun/legacy/legacy-lens.cpp`` on lensfun master).
.. [2] lensfun, ``libs/lensfun/modifier.cpp``: "About coordinate systems in
   Lensfun" and ``lfModifier::lfModifier``;
   ``libs/lensfun/mod-color.cpp``: ``AddColorCallbackVignetting``,
   ``ModifyColor_Vignetting_PA``.
.. [3] P. d'Angelo, Hugin vignetting model, http://hugin.sourceforge.net/tech/
"""

from __future__ import annotations

import functools
import os
import importlib.util
import logging
import math
import xml.etree.ElementTree as ET
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from vigproc.core.lensfamily import N_COMPONENTS, N_RADII, PLAUSIBLE, LensFamily, build_family
from vigproc.errors import InvalidImageError, ModelError
from vigproc.stores.xmlsafe import parse_xml, read_capped

__all__ = [
    "LensfunCamera",
    "LensfunLens",
    "PaVignetting",
    "bundled_db_dir",
    "diverse_lenses",
    "find_camera",
    "interpolate_pa",
    "load_lenses",
    "pa_corner",
    "pa_field",
]

logger = logging.getLogger(__name__)

#: Inverse-distance-weighting power used by lensfun's InterpolateVignetting.
IDW_POWER = 3.5
#: Largest lensfun database file read (lensfun's own largest, slr-canon.xml, is 0.7 MB): a
#: file is refused by its size before parsing, which bounds the parser's memory.
MAX_DB_FILE_BYTES = 8 << 20
#: Normalised distance below which lensfun returns a calibration point as is.
EXACT_MATCH_DISTANCE = 1e-4
#: Normalised distance beyond which lensfun refuses to interpolate.
MAX_INTERPOLATION_DISTANCE = 1.0
#: Corner attenuation below which :func:`diverse_lenses` calls a fall-off noticeable.
NOTICEABLE_CORNER = 0.9


@dataclass(frozen=True)
class PaVignetting:
    """One ``pa`` vignetting calibration (or interpolated) entry.

    The attenuation at normalised radius r (1 = image corner) is
    ``1 + k1 r^2 + k2 r^4 + k3 r^6``.

    Parameters
    ----------
    focal : float
        Focal length in mm.
    aperture : float
        Aperture as f-number.
    distance : float
        Focus distance in metres (lensfun uses 1000 for "infinity").
    k1, k2, k3 : float
        Polynomial coefficients of the pa model.
    """

    focal: float
    aperture: float
    distance: float
    k1: float
    k2: float
    k3: float

    @property
    def corner(self) -> float:
        """Attenuation at the image corner (r = 1): ``1 + k1 + k2 + k3``."""
        return pa_corner(self.k1, self.k2, self.k3)


@dataclass(frozen=True)
class LensfunLens:
    """A lensfun lens with its ``pa`` vignetting calibration.

    Parameters
    ----------
    maker : str
        Untranslated ``<maker>``.
    model : str
        Untranslated ``<model>`` (the one without a ``lang`` attribute).
    mounts : tuple of str
        All ``<mount>`` entries of the lens.
    crop_factor : float
        ``<cropfactor>`` of the calibration sensor.
    aspect_ratio : float or None
        ``<aspect-ratio>`` of the calibration sensor (``"4:3"`` -> 1.333...),
        ``None`` if the database does not give one.
    vignetting : tuple of PaVignetting
        The calibration entries, in database order, duplicates removed.
    focal_norm_range : tuple of float or None
        Focal range lensfun uses to normalise focal length when interpolating
        (its ``MinFocal``/``MaxFocal``): the ``<focal>`` element and the focal
        lengths of *all* calibration entries (distortion, TCA, ...), not only
        the vignetting ones.  ``None`` means :attr:`focal_range`.
    """

    maker: str
    model: str
    mounts: tuple[str, ...]
    crop_factor: float
    aspect_ratio: float | None
    vignetting: tuple[PaVignetting, ...]
    focal_norm_range: tuple[float, float] | None = None

    @property
    def focal_range(self) -> tuple[float, float]:
        """``(min, max)`` focal length over the vignetting calibration entries.

        Raises
        ------
        ModelError
            If the lens has no vignetting data.
        """
        _require_vignetting(self)
        focals = [v.focal for v in self.vignetting]
        return (min(focals), max(focals))

    def widest_aperture(self, focal: float) -> float:
        """Smallest calibrated f-number at the calibrated focal nearest ``focal``.

        Parameters
        ----------
        focal : float
            Focal length in mm; ties between two calibrated focals go to the
            shorter one.

        Returns
        -------
        float
            The smallest f-number calibrated at that focal length.
        """
        _require_vignetting(self)
        nearest = _nearest_focal(self, focal)
        return min(v.aperture for v in self.vignetting if v.focal == nearest)


# --------------------------------------------------------------------------
# database loading


def bundled_db_dir() -> Path:
    """Directory of the lensfun XML database shipped inside lensfunpy.

    Returns
    -------
    Path
        ``<site-packages>/lensfunpy/db_files``.

    Raises
    ------
    ModelError
        If lensfunpy is not installed or ships no database.
    """
    spec = importlib.util.find_spec("lensfunpy")
    locations = list(spec.submodule_search_locations or []) if spec else []
    for location in locations:
        candidate = Path(location) / "db_files"
        if any(candidate.glob("*.xml")):
            return candidate
    raise ModelError("lensfunpy with its bundled lensfun database (db_files/*.xml) is not installed")


def load_lenses(db_paths: Iterable[str | Path] | None = None) -> list[LensfunLens]:
    """Load every lens that has at least one ``pa`` vignetting entry.

    Parameters
    ----------
    db_paths : iterable of str or Path, optional
        XML files and/or directories (all ``*.xml`` inside, sorted by name).
        Default: lensfunpy's bundled database (:func:`bundled_db_dir`).

    Returns
    -------
    list of LensfunLens
        Sorted by ``(maker, model)`` (then crop factor and mounts, since the
        database holds a few lenses calibrated on several sensors).

    Raises
    ------
    ModelError
        If no XML file is found or one cannot be parsed.

    References
    ----------
    .. [1] lensfun database format, ``docs/database.txt`` / ``lensfun.h.in``.
    """
    # the cache key includes each file's mtime and size: a rewritten file is re-read
    return list(_load_lenses_cached(_stamps(_resolve_xml_files(db_paths))))


def _stamps(files: tuple[str, ...]) -> tuple[tuple[str, int, int], ...]:
    """Each file with its mtime and size (one stat a file): the parsed databases' cache key."""
    return tuple((f, st.st_mtime_ns, st.st_size) for f, st in ((f, os.stat(f)) for f in files))


def _resolve_xml_files(db_paths: Iterable[str | Path] | None) -> tuple[str, ...]:
    if db_paths is None:
        # the bundled folder's files, listed again only when the folder changes (a file added
        # or removed): a frame without a lens name asks for its body once per frame
        # (pipeline.learning), and listing and resolving 55 files took 40-60 ms of it
        where = bundled_db_dir()
        return _bundled_xml_files(str(where), os.stat(where).st_mtime_ns)
    return _xml_files([Path(p) for p in db_paths])


@functools.lru_cache(maxsize=4)
def _bundled_xml_files(where: str, mtime_ns: int) -> tuple[str, ...]:
    return _xml_files([Path(where)])


def _xml_files(paths: list[Path]) -> tuple[str, ...]:
    files: list[str] = []
    for path in paths:
        if path.is_dir():
            files.extend(str(p.resolve()) for p in sorted(path.glob("*.xml")))
        elif path.is_file():
            files.append(str(path.resolve()))
        else:
            raise ModelError(f"lensfun database path does not exist: {path}")
    if not files:
        raise ModelError(f"no lensfun XML files found in {[str(p) for p in paths]}")
    return tuple(files)


@functools.lru_cache(maxsize=8)
def _load_lenses_cached(stamps: tuple[tuple[str, int, int], ...]) -> tuple[LensfunLens, ...]:
    files = [f for f, _, _ in stamps]
    lenses: list[LensfunLens] = []
    for file in files:
        lenses.extend(_parse_file(file))
    lenses.sort(key=_lens_sort_key)
    logger.debug("loaded %d lenses with pa vignetting from %d files", len(lenses), len(files))
    return tuple(lenses)


def _lens_sort_key(lens: LensfunLens) -> tuple[str, str, float, tuple[str, ...]]:
    return (lens.maker, lens.model, lens.crop_factor, lens.mounts)


def _parse_file(file: str) -> list[LensfunLens]:
    # hostile input (``prior fit-lens-family --db``, ``profile import-lensfun``): refused by
    # size before it is read, decoded before a DTD is looked for
    raw = read_capped(file, MAX_DB_FILE_BYTES, ModelError, "lensfun database file")
    root = parse_xml(raw, ModelError, file, "lensfun database file")
    lenses = []
    for element in root.findall("lens"):
        lens = _parse_lens(element, file)
        if lens is not None:
            lenses.append(lens)
    return lenses


@dataclass(frozen=True)
class LensfunCamera:
    """A camera body of the lensfun database: what a lens profile written for it needs.

    Parameters
    ----------
    maker, model : str
        As lensfun spells them (untranslated).
    mount : str
        The body's lens mount (``"Nikon F AF"``; a compact's own, ``"canonA70"``).
    crop_factor : float
        ``<cropfactor>``: the 35-mm diagonal over the sensor's.
    """

    maker: str
    model: str
    mount: str
    crop_factor: float

    @property
    def fixed_lens(self) -> bool:
        """A compact's body: lensfun names a fixed lens's mount in lower camel case
        (``"canonA70"``), an interchangeable one's capitalised (``"Nikon F AF"``)."""
        return self.mount[:1].islower()


def _name_key(text: str | None) -> str:
    # lensfun compares names ignoring case and spacing ("NIKON CORPORATION" is "Nikon Corporation")
    return "".join((text or "").casefold().split())


@functools.lru_cache(maxsize=8)
def _load_cameras_cached(stamps: tuple[tuple[str, int, int], ...]) -> dict[tuple[str, str], LensfunCamera]:
    cameras: dict[tuple[str, str], LensfunCamera] = {}
    for file, _, _ in stamps:
        try:
            root = ET.parse(file).getroot()
        except (ET.ParseError, OSError) as exc:
            raise ModelError(f"cannot parse lensfun database file {file}: {exc}") from exc
        for el in root.findall("camera"):
            maker, model = _untranslated_text(el, "maker"), _untranslated_text(el, "model")
            mount, crop = _untranslated_text(el, "mount"), _positive_float(_untranslated_text(el, "cropfactor"))
            if maker and model and mount and crop:
                cam = LensfunCamera(maker, model, mount, crop)
                # every spelling lensfun gives (a translated "Nikon" / "D70" too) finds the body
                for mk in {maker, *(c.text.strip() for c in el.findall("maker") if c.text)}:
                    for md in {model, *(c.text.strip() for c in el.findall("model") if c.text)}:
                        cameras.setdefault((_name_key(mk), _name_key(md)), cam)
    return cameras


def find_camera(maker: str | None, model: str | None,
                db_paths: Iterable[str | Path] | None = None) -> LensfunCamera | None:
    """The lensfun database's camera body ``maker`` ``model`` (as EXIF names it, any case
    or spacing), or None when lensfun does not know it.

    Raises
    ------
    ModelError
        The database cannot be found or parsed.
    """
    if not maker or not model:
        return None
    return _load_cameras_cached(_stamps(_resolve_xml_files(db_paths))).get((_name_key(maker), _name_key(model)))


def _untranslated_text(element: ET.Element, tag: str) -> str | None:
    """Text of the ``tag`` child without ``lang`` attribute (else the first)."""
    children = element.findall(tag)
    plain = [c for c in children if "lang" not in c.attrib]
    chosen = (plain or children)[:1]
    return chosen[0].text.strip() if chosen and chosen[0].text else None


def _parse_aspect_ratio(text: str | None) -> float | None:
    """``"4:3"`` -> 4/3, ``"1.5"`` -> 1.5, missing/garbage -> None."""
    if not text:
        return None
    try:
        if ":" in text:
            num, den = text.split(":", 1)
            value = float(num) / float(den)
        else:
            value = float(text)
    except (ValueError, ZeroDivisionError):
        return None
    return value if math.isfinite(value) and value > 0 else None


def _positive_float(text: str | None) -> float | None:
    try:
        value = float(text) if text is not None else math.nan
    except ValueError:
        return None
    return value if math.isfinite(value) and value > 0 else None


def _parse_pa(element: ET.Element) -> PaVignetting | None:
    """A ``<vignetting model="pa">`` element, or None if an attribute is missing/invalid."""
    focal, aperture, distance = (_positive_float(element.get(a)) for a in ("focal", "aperture", "distance"))
    try:
        k1, k2, k3 = (float(element.get(a, "nan")) for a in ("k1", "k2", "k3"))
    except ValueError:
        return None
    if focal is None or aperture is None or distance is None:
        return None
    if not all(math.isfinite(k) for k in (k1, k2, k3)):
        return None
    return PaVignetting(focal, aperture, distance, k1, k2, k3)


def _dedupe_entries(entries: Sequence[PaVignetting]) -> tuple[PaVignetting, ...]:
    """Drop repeated (focal, aperture, distance) points; the later one wins, as in lensfun."""
    by_point: dict[tuple[float, float, float], PaVignetting] = {}
    for entry in entries:
        by_point[(entry.focal, entry.aperture, entry.distance)] = entry
    return tuple(by_point.values())


def _focal_norm_range(lens: ET.Element, calibration: ET.Element) -> tuple[float, float]:
    focals = [_positive_float(e.get("focal")) for e in calibration]
    focal_element = lens.find("focal")
    if focal_element is not None:
        focals += [_positive_float(focal_element.get(a)) for a in ("min", "max", "value")]
    valid = [f for f in focals if f is not None]
    return (min(valid), max(valid))


def _parse_lens(element: ET.Element, file: str) -> LensfunLens | None:
    calibration = element.find("calibration")
    if calibration is None:
        return None
    raw = [v for v in calibration.findall("vignetting") if v.get("model") == "pa"]
    if not raw:
        return None
    maker = _untranslated_text(element, "maker")
    model = _untranslated_text(element, "model")
    crop = _positive_float(_untranslated_text(element, "cropfactor"))
    parsed = [_parse_pa(v) for v in raw]
    entries = _dedupe_entries([p for p in parsed if p is not None])
    if len(entries) < len(raw):
        logger.debug("%s: %s: dropped %d malformed/duplicate pa entries", file, model, len(raw) - len(entries))
    if not maker or not model or crop is None or not entries:
        logger.warning("%s: skipping lens %r: missing maker, model, cropfactor or valid pa data", file, model)
        return None
    mounts = tuple(m.text.strip() for m in element.findall("mount") if m.text and m.text.strip())
    return LensfunLens(
        maker=maker,
        model=model,
        mounts=mounts,
        crop_factor=crop,
        aspect_ratio=_parse_aspect_ratio(_untranslated_text(element, "aspect-ratio")),
        vignetting=entries,
        focal_norm_range=_focal_norm_range(element, calibration),
    )


# --------------------------------------------------------------------------
# interpolation


def _require_vignetting(lens: LensfunLens) -> None:
    if not lens.vignetting:
        raise ModelError(f"lens {lens.maker} / {lens.model} has no pa vignetting calibration data")


def _nearest_focal(lens: LensfunLens, focal: float) -> float:
    focals = sorted({v.focal for v in lens.vignetting})
    return min(focals, key=lambda f: (abs(f - focal), f))


def _check_positive(name: str, value: float) -> float:
    value = float(value)
    if not (math.isfinite(value) and value > 0):
        raise ModelError(f"{name} must be a positive finite number, got {value!r}")
    return value


def _normalised_points(
    lens: LensfunLens, focal: np.ndarray, aperture: np.ndarray, distance: np.ndarray
) -> np.ndarray:
    """Map (focal, aperture, distance) to lensfun's roughly 0..1 interpolation space."""
    lo, hi = lens.focal_norm_range or lens.focal_range
    span = hi - lo
    f = (focal - lo) / span if span != 0 else focal - lo
    return np.stack([f, 4.0 / aperture, 0.1 / distance], axis=-1)


def interpolate_pa(
    lens: LensfunLens, focal: float, aperture: float, distance: float = 1000.0
) -> PaVignetting:
    """pa coefficients of ``lens`` at any focal length, aperture and distance.

    Follows lensfun's ``lfLens::InterpolateVignetting``: every calibration
    point is mapped to a normalised space ``((f - f_min) / (f_max - f_min),
    4 / aperture, 0.1 / distance)`` (``f_min``/``f_max`` = lensfun's
    ``MinFocal``/``MaxFocal``, no division when they are equal), and k1, k2,
    k3 are the inverse-distance-weighted mean (Shepard, power 3.5) over all
    points.  A point closer than 1e-4 is returned as is; if even the nearest
    point is farther than 1, lensfun declines to correct and so do we.

    Parameters
    ----------
    lens : LensfunLens
        Lens with pa calibration data.
    focal : float
        Focal length in mm.
    aperture : float
        f-number.
    distance : float, optional
        Focus distance in metres, default 1000 ("infinity" in lensfun).

    Returns
    -------
    PaVignetting
        Interpolated coefficients, labelled with the requested focal,
        aperture and distance.

    Raises
    ------
    ModelError
        If the lens has no vignetting data, an argument is not a positive
        finite number, or the request is too far from every calibration point.

    Notes
    -----
    Simplifications relative to lensfun 0.3.4: computed in float64 instead of
    float32; lensfun's ``MinFocal``/``MaxFocal`` additionally come from
    parsing the lens *name* (e.g. "80-210mm"), which is not done here, so
    :attr:`LensfunLens.focal_norm_range` uses the ``<focal>`` element and all
    calibration focal lengths only (this differs for 1 of the 548 bundled
    lenses: Tamron AF 80-210mm f/4.5-5.6 280D, whose data stop at 200 mm).

    References
    ----------
    .. [1] lensfun ``lens.cpp``: ``__vignetting_dist`` and
       ``lfLens::InterpolateVignetting`` (0.3.x; ``legacy/legacy-lens.cpp``).
    .. [2] D. Shepard, "A two-dimensional interpolation function for
       irregularly-spaced data", Proc. ACM National Conference, 1968.
    """
    _require_vignetting(lens)
    focal = _check_positive("focal", focal)
    aperture = _check_positive("aperture", aperture)
    distance = _check_positive("distance", distance)

    entries = lens.vignetting
    calib = np.array([(v.focal, v.aperture, v.distance) for v in entries], dtype=np.float64)
    ks = np.array([(v.k1, v.k2, v.k3) for v in entries], dtype=np.float64)
    points = _normalised_points(lens, calib[:, 0], calib[:, 1], calib[:, 2])
    query = _normalised_points(lens, np.array(focal), np.array(aperture), np.array(distance))
    dist = np.sqrt(((points - query) ** 2).sum(axis=1))

    exact = np.flatnonzero(dist < EXACT_MATCH_DISTANCE)
    if exact.size:
        k1, k2, k3 = ks[exact[0]]
        return PaVignetting(focal, aperture, distance, float(k1), float(k2), float(k3))
    if dist.min() > MAX_INTERPOLATION_DISTANCE:
        raise ModelError(
            f"{lens.maker} / {lens.model}: focal={focal:g} mm, f/{aperture:g}, distance={distance:g} m "
            f"is too far from the calibrated range (focal {lens.focal_range[0]:g}-{lens.focal_range[1]:g} mm) "
            "for lensfun-style interpolation"
        )
    weights = dist ** (-IDW_POWER)
    k1, k2, k3 = (weights @ ks) / weights.sum()
    return PaVignetting(focal, aperture, distance, float(k1), float(k2), float(k3))


# --------------------------------------------------------------------------
# the attenuation field


def pa_corner(k1: float, k2: float, k3: float) -> float:
    """pa attenuation at r = 1 (the image corner): ``1 + k1 + k2 + k3``."""
    return 1.0 + k1 + k2 + k3


def pa_poly(r2: np.ndarray, k1: float, k2: float, k3: float) -> np.ndarray:
    """The pa attenuation ``1 + k1 r² + k2 r⁴ + k3 r⁶`` at squared radii ``r2``."""
    return 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))


def pa_field(
    shape: tuple[int, int],
    k1: float,
    k2: float,
    k3: float,
    *,
    center: tuple[float, float] | None = None,
) -> np.ndarray:
    """pa attenuation field ``1 + k1 r^2 + k2 r^4 + k3 r^6`` for an image.

    Parameters
    ----------
    shape : tuple of int
        ``(H, W)`` (further trailing dimensions are ignored).
    k1, k2, k3 : float
        pa coefficients.
    center : tuple of float, optional
        ``(cx, cy)`` offset in pixels of the optical centre from the image
        centre ``((W-1)/2, (H-1)/2)``.  The normalisation (half-diagonal of
        the image) does not change with the offset.

    Returns
    -------
    numpy.ndarray
        float64 array ``(H, W)``; 1 at the optical centre and
        ``1 + k1 + k2 + k3`` at the corners when ``center`` is None.

    Raises
    ------
    InvalidImageError
        If the shape is not at least 1 x 2 / 2 x 1 pixels.
    ModelError
        If a coefficient or the centre offset is not finite.

    Notes
    -----
    r is the distance to the centre divided by the image half-diagonal
    ``hypot((W-1)/2, (H-1)/2)``, lensfun's vignetting coordinate for an image
    with the calibration crop factor (see the module docstring).

    References
    ----------
    .. [1] lensfun ``modifier.cpp`` ("For vignetting, r = 1 is the corner of
       the image") and ``mod-color.cpp`` (``ModifyColor_Vignetting_PA``).
    """
    if len(shape) < 2:
        raise InvalidImageError(f"shape must be (H, W), got {tuple(shape)!r}")
    height, width = int(shape[0]), int(shape[1])
    if height < 1 or width < 1 or height * width < 2:
        raise InvalidImageError(f"image of shape {(height, width)} is too small for a vignetting field")
    if not all(math.isfinite(float(k)) for k in (k1, k2, k3)):
        raise ModelError(f"pa coefficients must be finite, got k1={k1}, k2={k2}, k3={k3}")
    off_x, off_y = (0.0, 0.0) if center is None else (float(center[0]), float(center[1]))
    if not (math.isfinite(off_x) and math.isfinite(off_y)):
        raise ModelError(f"centre offset must be finite, got {center!r}")

    half_w, half_h = (width - 1) / 2.0, (height - 1) / 2.0
    dx = np.arange(width, dtype=np.float64) - (half_w + off_x)
    dy = np.arange(height, dtype=np.float64) - (half_h + off_y)
    r2 = (dy[:, None] ** 2 + dx[None, :] ** 2) / (half_w**2 + half_h**2)
    return pa_poly(r2, float(k1), float(k2), float(k3))


# --------------------------------------------------------------------------
# benchmark selection


def _selection_entry(lens: LensfunLens) -> PaVignetting:
    """Calibration point at the shortest focal, widest aperture there, farthest distance."""
    focal = lens.focal_range[0]
    aperture = lens.widest_aperture(focal)
    at_point = [v for v in lens.vignetting if v.focal == focal and v.aperture == aperture]
    return max(at_point, key=lambda v: v.distance)


def _plausible_falloff(entry: PaVignetting, samples: int = 101) -> bool:
    """Attenuation stays within (0, 1] (1e-3 slack) for r in [0, 1]."""
    r2 = np.linspace(0.0, 1.0, samples) ** 2
    values = pa_poly(r2, entry.k1, entry.k2, entry.k3)
    return bool(values.min() > 0.0 and values.max() <= 1.0 + 1e-3)


def _round_robin(groups: dict[str, list[tuple[LensfunLens, PaVignetting]]], n: int, out: list) -> None:
    depth = 0
    while len(out) < n and any(depth < len(g) for g in groups.values()):
        for maker in sorted(groups, key=lambda m: (-len(groups[m]), m.casefold())):
            if depth < len(groups[maker]) and len(out) < n:
                out.append(groups[maker][depth])
        depth += 1


def diverse_lenses(
    n: int = 20, *, db_paths: Iterable[str | Path] | None = None
) -> list[tuple[LensfunLens, PaVignetting]]:
    """A deterministic, maker-diverse selection of ``n`` lensfun lenses: the lens fields
    of ``forensics calibrate``, the shipped samples and the benchmarks.

    Each lens comes with its calibration entry at the shortest calibrated
    focal length, the widest aperture calibrated there and the largest
    calibrated distance.  Lenses whose attenuation leaves (0, 1] on
    ``r in [0, 1]`` are skipped; lenses with a noticeable fall-off (corner
    attenuation below 0.9) are taken first, round-robin over makers (makers
    with more such lenses first, ties alphabetically; models alphabetically
    within a maker), then the remaining plausible ones the same way.  Lenses are distinct by
    ``(maker, model)``.

    Parameters
    ----------
    n : int, optional
        Number of lenses, default 20.
    db_paths : iterable of str or Path, optional
        Passed to :func:`load_lenses`.

    Returns
    -------
    list of tuple of (LensfunLens, PaVignetting)
        ``n`` pairs, in selection order.

    Raises
    ------
    ModelError
        If ``n`` is not positive or fewer than ``n`` suitable lenses exist.
    """
    if n < 1:
        raise ModelError(f"n must be a positive number of lenses, got {n}")
    strong: dict[str, list[tuple[LensfunLens, PaVignetting]]] = {}
    weak: dict[str, list[tuple[LensfunLens, PaVignetting]]] = {}
    seen: set[tuple[str, str]] = set()
    for lens in load_lenses(db_paths):
        if (lens.maker, lens.model) in seen:
            continue
        entry = _selection_entry(lens)
        if not _plausible_falloff(entry):
            continue
        seen.add((lens.maker, lens.model))
        target = strong if entry.corner < NOTICEABLE_CORNER else weak
        target.setdefault(lens.maker, []).append((lens, entry))
    chosen: list[tuple[LensfunLens, PaVignetting]] = []
    _round_robin(strong, n, chosen)
    _round_robin(weak, n, chosen)
    if len(chosen) < n:
        raise ModelError(f"only {len(chosen)} lenses with usable pa vignetting data, {n} requested")
    return chosen


def lensfun_family(exclude: Iterable[tuple[str, str]] = (), n_components: int = N_COMPONENTS,
                   db_paths: Iterable[str | Path] | None = None) -> LensFamily:
    """:func:`vigproc.core.lensfamily.build_family` over lensfun's ``pa`` calibrations.

    Parameters
    ----------
    exclude : iterable of (maker, model)
        Lenses left out (a benchmark's test lenses: the estimate must not contain
        the lens it is measured on).
    n_components : int
    db_paths : optional
        lensfun XML files or folders (default: the database bundled with lensfunpy).
    """
    skip = set(exclude)
    rho2 = np.linspace(0.0, 1.0, N_RADII) ** 2
    rows, f35, fno, names = [], [], [], set()
    lo, hi = PLAUSIBLE
    for lens in load_lenses(db_paths):
        if (lens.maker, lens.model) in skip:
            continue
        for v in lens.vignetting:
            g = pa_poly(rho2, v.k1, v.k2, v.k3)
            if g.min() <= lo or g.max() > hi:
                continue
            rows.append(np.log(g))
            f35.append(v.focal * lens.crop_factor)
            fno.append(v.aperture)
            names.add((lens.maker, lens.model))
    return build_family(np.array(rows), np.array(f35), np.array(fno), len(names), n_components)
