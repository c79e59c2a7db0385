"""Which lensfun calibration belongs to a frame's lens: names matched by their tokens, and verified.

EXIF and lensfun spell one lens differently: ``minolta/sony af dt 18-70mm f3.5-5.6 (d)``
(ExifTool) is lensfun's ``Minolta/Sony AF DT 18-70mm f/3.5-5.6 (D)``, ``ef 16-35mm f/2.8l
ii usm`` (a Canon's LensID without its brand, :func:`vigproc.io.lensident.strip_make_prefix`)
is ``Canon EF 16-35mm f/2.8L II USM``.  :func:`match_lens` compares *tokens*:

* case, ``F``/``f/``, ``.0`` in numbers, spacing (``ef70-200mm``), brackets and commas do
  not count;
* the focal range (``18-70mm``) and the aperture (``f3.5-5.6``) must be equal;
* maker words (the lensfun lens's maker, the camera's brand, each side of ``minolta/sony``)
  are dropped from both names;
* the remaining words must be the same, except for a few that name no other optics
  (:data:`SOFT_WORDS`: ``af``, ``hsm``, ``usm``, ``ex``...).  A word such as ``ii``,
  ``is``, ``vr`` or ``stm`` tells two lenses apart and is never ignored;
* a name that matches several lensfun lenses equally well is ambiguous: no match.

Every match is then verified: the lens's focal range must hold the shot's focal length,
and a lens whose EXIF identity has a problem (``LensKey.lens_problem``), that EXIF only
describes (``18-55mm``) or names ambiguously is never matched.  Where lensfun holds one lens
calibrated on several sensors, the frame's crop factor (from its 35-mm equivalent focal
length, else lensfunpy's ``Database.find_cameras`` for the camera) picks the calibration:
the nearest of those measured on a sensor no smaller than the frame's (whose corner lies
within the calibrated radius, as lensfun itself requires a lens calibrated for the camera's
crop or a larger one), else the nearest.

lensfunpy's own ``Database.find_lenses`` scores names too loosely to be trusted alone: on a
Canon 350D, with ``loose_search``, its best for ``18-55mm`` is ``Super-Takumar 55mm f/1.8``
and for ``EF 70-200mm f/2.8L IS III USM`` (a lens lensfun does not hold) ``Canon EF 70-200mm
f/2.8L IS USM``, another lens.  Here lensfunpy is used only for the camera's crop factor.
"""

from __future__ import annotations

import functools
import logging
import math
import re
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path

from vigproc.io.lensident import make_brand
from vigproc.stores.lensfun import LensfunLens, load_lenses

__all__ = ["CROP_MODE", "LensfunMatch", "SOFT_WORDS", "calibration_for", "corner_rho", "covers", "crop_of",
           "frame_crop", "lens_tokens", "match_lens", "match_name"]

logger = logging.getLogger(__name__)

#: Words two names of one lens may differ by: autofocus, motor and series marks that
#: EXIF and lensfun write or leave out for the same optics.
SOFT_WORDS = frozenset({"af", "lens", "hsm", "usm", "ex", "digital", "zoom", "asph", "aspherical", "if", "mc"})
# focal lengths may stray this far outside a lens's nominal range (rounding, Nikon's 18.3-71.3 mm)
_FOCAL_SLACK = 0.06
#: A calibration covers a frame when its crop factor is at most the frame's times this
#: (the EXIF's 35-mm focal lengths are rounded: 1.62 against a 1.6 body still covers it).
_COVER_SLACK = 1.02
#: A frame whose EXIF 35-mm focal length says a crop factor this much (relative) off its
#: camera's sensor is a crop of the sensor (:func:`frame_crop`); nominal factors are
#: within 4 % of the sensors' (Nikon DX 1.5 against 1.52-1.56, Canon 1.6 against 1.61-1.62).
CROP_MODE = 0.10

_APERTURE = re.compile(r"(?:\bf\s*/?\s*|\b1:)(\d+(?:\.\d+)?(?:\s*-\s*\d+(?:\.\d+)?)?)")
_FOCAL = re.compile(r"(\d+(?:\.\d+)?(?:\s*-\s*\d+(?:\.\d+)?)?)\s*mm\b")
_EDGE = "()[]{},;:|&\"'"


@dataclass(frozen=True)
class LensfunMatch:
    """The result of :func:`match_lens`.

    Attributes
    ----------
    lens : LensfunLens or None
        lensfun's calibrated lens, None when there is no trustworthy match.
    reason : str
        How it matched (``exact``, ``tolerant``), or why there is no match, for people.
    """

    lens: LensfunLens | None
    reason: str

    @property
    def name(self) -> str | None:
        """lensfun's name of the matched lens (``Sony / Minolta/Sony AF DT ...``)."""
        return None if self.lens is None else f"{self.lens.maker} / {self.lens.model}"


def _num(text: str) -> str:
    # "18.0-55.0" -> "18-55", "4.0" -> "4": one spelling per number
    return "-".join(re.sub(r"\.0+$", "", p.strip()) for p in text.split("-"))


def lens_tokens(name: str, makers: Iterable[str] = ()) -> tuple[frozenset[str], frozenset[str]]:
    """A lens name as ``(numbers, words)``: focal range and aperture, and the other words.

    Parameters
    ----------
    name : str
        A lens name in any spelling (``Canon EF70-200mm F2.8L IS II USM``).
    makers : iterable of str
        Maker words to drop (lower case).

    Returns
    -------
    (frozenset, frozenset)
        e.g. ``({"70-200mm", "f2.8"}, {"ef", "l", "is", "ii", "usm"})``.
    """
    t = " ".join(name.casefold().split())
    nums = set()
    for m in list(_APERTURE.finditer(t)):
        nums.add("f" + _num(m.group(1)))
    t = _APERTURE.sub(" ", t)
    for m in list(_FOCAL.finditer(t)):
        nums.add(_num(m.group(1)) + "mm")
    t = _FOCAL.sub(" ", t)
    drop = {m.casefold() for m in makers}
    words = set()
    for raw in t.split():
        for w in raw.split("/") if "/" in raw else (raw,):
            w = w.strip(_EDGE)
            if w and w not in drop:
                words.add(w)
    words.discard("")
    return frozenset(nums), frozenset(words)


@functools.lru_cache(maxsize=4)
def _index(db_key: tuple[str, ...] | None) -> tuple[tuple[LensfunLens, frozenset[str], frozenset[str]], ...]:
    lenses = load_lenses(None if db_key is None else [Path(p) for p in db_key])
    out = []
    for lens in lenses:
        makers = set(lens.maker.casefold().split())
        nums, words = lens_tokens(lens.model, makers)
        out.append((lens, nums, words))
    return tuple(out)


def match_name(name: str, *, brand: str | None = None,
               db_paths: Iterable[str | Path] | None = None) -> tuple[list[LensfunLens], str]:
    """lensfun lenses (every calibration of one name) whose name is ``name`` up to spelling.

    Parameters
    ----------
    name : str
        The lens name as EXIF gives it.
    brand : str, optional
        The camera's brand word (``nikon``): dropped from ``name`` like a maker word.
    db_paths : iterable, optional
        lensfun XML files or folders (default: lensfunpy's bundled database).

    Returns
    -------
    (list of LensfunLens, str)
        The calibrations of the one matching name (empty when none or several names
        match) and how it matched, or why not.
    """
    db_key = None if db_paths is None else tuple(str(p) for p in db_paths)
    q_nums, _ = lens_tokens(name)
    # a name without a focal length (a compact's "digital ixus 80 is & compatibles
    # (standard)") must match word for word
    soft = SOFT_WORDS if any(n.endswith("mm") for n in q_nums) else frozenset()
    best: dict[tuple[str, str], list[LensfunLens]] = {}
    best_cost = None
    for lens, nums, words in _index(db_key):
        if nums != q_nums:
            continue
        drop = set(lens.maker.casefold().split()) | ({brand.casefold()} if brand else set())
        _, q_words = lens_tokens(name, drop)
        diff = q_words ^ words
        if not diff <= soft:
            continue
        cost = len(diff)
        if best_cost is None or cost < best_cost:
            best, best_cost = {}, cost
        if cost == best_cost:
            best.setdefault((lens.maker, lens.model), []).append(lens)
    if not best:
        return [], f"lensfun has no calibrated lens named like {name!r}"
    if len(best) > 1:
        names = "; ".join(f"{mk} / {md}" for mk, md in sorted(best))
        return [], f"{name!r} matches several lensfun lenses equally well ({names})"
    ((_, lenses),) = best.items()
    return lenses, "exact" if best_cost == 0 else "tolerant"


@functools.lru_cache(maxsize=256)
def _camera_crop(make: str | None, model: str | None) -> float | None:
    """The crop factor lensfunpy's database gives the camera, None when it does not know it."""
    if not make or not model:
        return None
    try:
        cams = _lensfun_db().find_cameras(make, model)
    except Exception as exc:  # noqa: BLE001 - an unusable lensfunpy only loses the crop factor
        logger.debug("lensfunpy camera lookup failed: %s", exc)
        return None
    return float(cams[0].crop_factor) if cams and cams[0].crop_factor > 0 else None


@functools.lru_cache(maxsize=1)
def _lensfun_db():
    import lensfunpy  # the C extension: only for the camera's crop factor

    return lensfunpy.Database()


def frame_crop(lens_key) -> float | None:
    """The crop factor of a frame (35-mm film's diagonal over the frame's), where lensfun's
    ρ = calibration crop / frame crop puts the calibration's corner.

    The camera's sensor as lensfun's database gives it; the EXIF's 35-mm focal length over
    its focal length where lensfun does not know the camera, or where the two differ by
    more than :data:`CROP_MODE` (the frame is a crop of the sensor: a DX crop on an FX body,
    a 1:1 or 16:9 frame). Cameras write the 35-mm focal length with a nominal factor
    (Nikon's DX bodies 1.5 for sensors of 1.52-1.56), which read as the frame's puts a DX
    lens's calibrated corner beyond the frame's (ρ = 1.02) and an FX lens's inside too
    far. None when neither is known.
    """
    f, f35 = getattr(lens_key, "focal_mm", None), getattr(lens_key, "focal_35mm", None)
    exif = f35 / f if f and f35 and f > 0 and f35 > 0 else None
    return crop_of(_camera_crop(getattr(lens_key, "make", None), getattr(lens_key, "model", None)), exif)


def crop_of(camera: float | None, exif: float | None) -> float | None:
    """:func:`frame_crop`'s rule: the camera's sensor (lensfun's crop factor of the body),
    the EXIF's 35-mm ratio where the camera's is unknown or more than :data:`CROP_MODE`
    away from it (a crop mode); None when neither is known."""
    if camera is None or (exif is not None and abs(math.log(exif / camera)) > math.log1p(CROP_MODE)):
        return exif
    return camera


def covers(calibration: float, frame: float) -> bool:
    """Whether a calibration on a sensor of crop factor ``calibration`` holds the whole of a
    frame of crop factor ``frame`` (rounded crop factors: 1.62 against a 1.6 body does)."""
    return calibration <= frame * _COVER_SLACK


def corner_rho(calibration: float, frame: float | None) -> float:
    """lensfun's ρ at the corner of a frame of crop factor ``frame`` for a calibration on a
    sensor of crop factor ``calibration``: calibration / frame where the frame is a smaller
    sensor's (a DX frame behind a full-frame lens: 0.66), else 1, the calibration's own frame:

    * the frame's crop unknown (None);
    * within :data:`_COVER_SLACK` of the calibration's: the same sensor, its crop factor
      rounded otherwise (a 1.6 calibration on a 1.62 body, lensfun's 1.528 DX calibration
      on its 1.525 D70), whose frames get exactly what they got before lensfun's rule;
    * a larger sensor than the calibration's (:func:`covers` False: an APS-C calibration
      on a full-frame body): its corners lie past the calibrated field, where the pa
      polynomial is not a measurement (extrapolated to ρ = 1.5 a third of the DX
      calibrations fall to zero, others brighten the corners or darken them by 5 EV).
    """
    if frame is None or not covers(calibration, frame) or calibration * _COVER_SLACK >= frame:
        return 1.0
    return calibration / frame


def calibration_for(lenses: Sequence[LensfunLens], crop: float) -> LensfunLens:
    """Of one lens's calibrations on several sensors, the one for a frame of crop factor
    ``crop``: the nearest whose sensor is no smaller than the frame's (else the nearest).

    A calibration on a smaller sensor than the frame's is extrapolated at its corners (an
    APS-C calibration on an APS-H body: ρ = 1.26); one that covers the frame is not.
    """
    covering = [lz for lz in lenses if covers(lz.crop_factor, crop)] or list(lenses)
    return min(covering, key=lambda lz: (abs(math.log(lz.crop_factor / crop)), lz.crop_factor))


def match_lens(lens_key, *, db_paths: Iterable[str | Path] | None = None) -> LensfunMatch:
    """lensfun's calibrated lens for a frame's :class:`~vigproc.io.exif.LensKey`, verified.

    Parameters
    ----------
    lens_key : LensKey or None
        The frame's lens identity.
    db_paths : iterable, optional
        lensfun XML files or folders (default: lensfunpy's bundled database).

    Returns
    -------
    LensfunMatch
        ``lens`` None with the reason when the EXIF names no lens, names it with a
        problem, only describes it, names several, or lensfun has no lens of that name
        whose focal range holds the shot's focal length.
    """
    if lens_key is None or lens_key.lens is None:
        return LensfunMatch(None, "the metadata names no lens")
    if lens_key.lens_problem:
        return LensfunMatch(None, f"the metadata's lens identity is contradictory: {lens_key.lens_problem}")
    if lens_key.lens_source and lens_key.lens_source.endswith("(description)"):
        return LensfunMatch(None, f"the metadata only describes the lens ({lens_key.lens}), it does not name it")
    if lens_key.ambiguous:
        return LensfunMatch(None, f"the metadata names one of several lenses ({lens_key.lens})")
    lenses, how = match_name(lens_key.lens, brand=make_brand(lens_key.make), db_paths=db_paths)
    if not lenses:
        return LensfunMatch(None, how)
    focal = lens_key.focal_mm
    lo, hi = lenses[0].focal_norm_range or lenses[0].focal_range
    if focal is not None and not lo * (1 - _FOCAL_SLACK) - 0.5 <= focal <= hi * (1 + _FOCAL_SLACK) + 0.5:
        return LensfunMatch(None, f"lensfun's {lenses[0].maker} / {lenses[0].model} covers {lo:g}-{hi:g} mm, "
                                  f"the frame was shot at {focal:g} mm")
    chosen = lenses[0]
    if len(lenses) > 1:
        crop = frame_crop(lens_key)
        if crop is None:  # no sensor size known: the calibration with the most data
            chosen = max(lenses, key=lambda lz: (len(lz.vignetting), -lz.crop_factor))
        else:
            chosen = calibration_for(lenses, crop)
    logger.debug("lensfun match (%s): %r -> %s / %s (crop %g)", how, lens_key.lens, chosen.maker, chosen.model,
                 chosen.crop_factor)
    return LensfunMatch(chosen, how)
