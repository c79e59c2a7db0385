"""Lens identity rules: which lens a frame's EXIF names, and whether the shot fits it.

Pure functions on the normalised (casefolded) text of :mod:`vigproc.io.exif`, kept apart
so that every front end (files read with ExifTool, a host's lens fields, the Python API)
keys a lens by one rule:

* :func:`generic_description`: what ExifTool or a converter writes for a lens it cannot
  name (``Unknown (251) 16-35mm``, ``18.0-55.0 mm``, ``100.0mm f/2.8``) becomes a
  description such as ``16-35mm`` or ``18-55mm f/3.5-5.6``: still a key (with the camera's
  make and model), never a lens name to look up.
* :func:`lens_spec`: the focal range and widest aperture a lens name or description states
  (``canon ef 70-200mm f/2.8l is ii usm`` -> 70-200 mm, f/2.8).
* :func:`shot_problem`: a frame shot at a focal length the lens cannot reach, or wider
  open than it opens, names the wrong lens.
* :func:`strip_make_prefix`: ``nikon af-s dx ...`` (darktable, exiv2) and ``af-s dx ...``
  (ExifTool) are one lens on a Nikon: a leading brand equal to the camera's make is dropped.
* :func:`display_lens_id`: a key's escapes (``%7C``) are for storage; people read the text.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass

__all__ = ["LensSpec", "display_lens_id", "generic_description", "lens_spec", "make_brand", "shot_problem",
           "strip_make_prefix", "unescape_key_part"]

_NUM = r"\d+(?:\.\d+)?"
# "unknown (251) 16-35mm", "unknown 18-55mm": ExifTool's LensID for a code it cannot match
# to the focal range the camera reports (a Canon LensType shared by several lenses)
_UNKNOWN_RANGE = re.compile(rf"^unknown\b(?:\s*\([^)]*\))?\s*({_NUM})(?:\s*-\s*({_NUM}))?\s*mm\s*$")
# a bare spec: "18.0-55.0 mm", "100.0mm f/2.8", "18.0-55.0mm f/3.5-5.6"
_SPEC_ONLY = re.compile(
    rf"^({_NUM})(?:\s*-\s*({_NUM}))?\s*mm(?:\s*f\s*/?\s*({_NUM})(?:\s*-\s*({_NUM}))?)?$"
)
_FOCAL_IN_NAME = re.compile(rf"(?<![\d.])({_NUM})(?:\s*-\s*({_NUM}))?\s*mm\b")
_APERTURE_IN_NAME = re.compile(rf"(?:\bf\s*/?\s*|1:)({_NUM})(?:\s*-\s*({_NUM}))?")
# a teleconverter or adapter in the name multiplies the focal length: its range says nothing
_CONVERTER = re.compile(r"(?:\d(?:\.\d)?\s*x\b|extender|converter|teleplus|speed ?booster|adapter)")
# how far EXIF numbers stray from a lens's nominal ones (Nikon's 18-70 reports 18.3-71.3 mm,
# focal lengths and f-numbers are rounded): beyond this the shot does not fit the lens
FOCAL_TOLERANCE = 0.06
APERTURE_TOLERANCE = 0.06


@dataclass(frozen=True)
class LensSpec:
    """What a lens name states about the lens.

    Attributes
    ----------
    focal_min, focal_max : float
        Focal range in mm (equal for a prime).
    aperture_min : float or None
        The widest f-number at the wide end (``f/3.5-5.6`` -> 3.5), None when not stated.
    aperture_max : float or None
        The widest f-number at the long end (``f/3.5-5.6`` -> 5.6; ``f/2.8`` -> 2.8).
    """

    focal_min: float
    focal_max: float
    aperture_min: float | None = None
    aperture_max: float | None = None


def _fmt(x: float) -> str:
    return f"{x:.2f}".rstrip("0").rstrip(".")


def generic_description(text: str | None) -> str | None:
    """A normalised description for a lens EXIF does not name, else None.

    Parameters
    ----------
    text : str or None
        A normalised lens tag value (``unknown (251) 16-35mm``, ``18.0-55.0 mm``).

    Returns
    -------
    str or None
        ``16-35mm``, ``18-55mm f/3.5-5.6``, ``100mm f/2.8``; None for a lens name or
        an ``unknown`` without a focal range.
    """
    if not text:
        return None
    m = _UNKNOWN_RANGE.match(text)
    groups: tuple[str | None, ...]
    if m:
        groups = (m.group(1), m.group(2), None, None)
    else:
        m = _SPEC_ONLY.match(text)
        if not m:
            return None
        groups = m.groups()
    lo, hi, a_lo, a_hi = (float(g) if g is not None else None for g in groups)
    if lo is None or lo <= 0 or (hi is not None and hi < lo):
        return None
    focal = _fmt(lo) if hi is None or hi == lo else f"{_fmt(lo)}-{_fmt(hi)}"
    if a_lo is None or a_lo <= 0:  # "f/0" is how LensInfo writes an unknown aperture
        return f"{focal}mm"
    ap = _fmt(a_lo) if a_hi is None or a_hi == a_lo else f"{_fmt(a_lo)}-{_fmt(a_hi)}"
    return f"{focal}mm f/{ap}"


def lens_spec(name: str | None) -> LensSpec | None:
    """The focal range (and widest aperture) a lens name or description states.

    Parameters
    ----------
    name : str or None
        A normalised lens name (``ef-m 15-45mm f/3.5-6.3 is stm``) or description.

    Returns
    -------
    LensSpec or None
        None when the name states no focal length in mm, or names a converter (whose
        factor changes the focal length the camera reports).
    """
    if not name or _CONVERTER.search(name):
        return None
    m = _FOCAL_IN_NAME.search(name)
    if not m:
        return None
    lo = float(m.group(1))
    hi = float(m.group(2)) if m.group(2) else lo
    if lo <= 0 or hi < lo:
        return None
    a = _APERTURE_IN_NAME.search(name, m.end())
    ap = float(a.group(1)) if a else None
    if not ap or ap <= 0:
        return LensSpec(lo, hi)
    ap_hi = float(a.group(2)) if a.group(2) else ap
    return LensSpec(lo, hi, ap, max(ap, ap_hi))


def shot_problem(lens: str, spec: LensSpec, focal_mm: float | None, fnumber: float | None,
                 *, spec_from: str = "its name", max_aperture: float | None = None) -> str | None:
    """Why a frame cannot have been shot with ``lens`` (None when it can).

    Parameters
    ----------
    lens : str
        The lens, for the message.
    spec : LensSpec
        What is known of the lens (its name, or the focal range the camera reports).
    focal_mm, fnumber : float or None
        The shot's focal length (real, not 35-mm equivalent) and f-number.
    spec_from : str
        Where ``spec`` comes from, for the message.
    max_aperture : float or None
        The widest f-number the camera reports for the lens at the shot's focal length
        (EXIF MaxApertureValue): brighter than the name's widest, it is another lens.

    Returns
    -------
    str or None
        One sentence, e.g. ``shot at 31 mm, outside the 70-200 mm of canon ef 70-200mm
        f/2.8l is ii usm (its name)``.
    """
    if focal_mm is not None and math.isfinite(focal_mm):
        lo = spec.focal_min * (1 - FOCAL_TOLERANCE) - 0.5
        hi = spec.focal_max * (1 + FOCAL_TOLERANCE) + 0.5
        if not lo <= focal_mm <= hi:
            rng = (f"{_fmt(spec.focal_min)} mm" if spec.focal_min == spec.focal_max
                   else f"{_fmt(spec.focal_min)}-{_fmt(spec.focal_max)} mm")
            return f"shot at {_fmt(focal_mm)} mm, outside the {rng} of {lens} ({spec_from})"
    if fnumber is not None and spec.aperture_min is not None and fnumber < spec.aperture_min * (1 - APERTURE_TOLERANCE):
        return f"shot at f/{_fmt(fnumber)}, wider open than the f/{_fmt(spec.aperture_min)} of {lens} ({spec_from})"
    # only brighter than the name says: a macro lens focused close reports a darker effective
    # aperture (a Nikon D70's 100mm f/2.8 reports f/3.1), a lens never a brighter one
    if max_aperture is not None and spec.aperture_min is not None and \
            max_aperture < spec.aperture_min * (1 - APERTURE_TOLERANCE):
        return (f"the camera reports a widest aperture of f/{_fmt(max_aperture)}, wider than the "
                f"f/{_fmt(spec.aperture_min)} of {lens} ({spec_from})")
    return None


def make_brand(make: str | None) -> str | None:
    """The brand word of a normalised camera make (``nikon corporation`` -> ``nikon``,
    ``olympus imaging corp.`` -> ``olympus``), None when there is none."""
    if not make:
        return None
    word = re.split(r"[\s,./]+", make.strip(), maxsplit=1)[0]
    return word if len(word) >= 2 and any(c.isalpha() for c in word) else None


def strip_make_prefix(make: str | None, lens: str | None) -> str | None:
    """``lens`` without a leading brand equal to the camera's (``nikon af-s ...`` on a
    Nikon -> ``af-s ...``): hosts that read EXIF with exiv2 (darktable, digiKam) prefix
    the maker, ExifTool often does not, and the key must not depend on which did.

    A third-party brand (``sigma 10-20mm`` on a Nikon) and ``minolta/sony`` on a Sony stay:
    they say which lens it is.  A name that would be left without a focal length stays whole.
    """
    brand = make_brand(make)
    if not lens or not brand or not lens.startswith(brand + " "):
        return lens
    rest = lens[len(brand) + 1:].lstrip()
    return rest if any(c.isdigit() for c in rest) else lens


def unescape_key_part(part: str) -> str | None:
    """The inverse of :func:`vigproc.io.exif.escape_key_part`: the text a key component
    holds ("?", a missing one, is None), for people and exports; never to build a key from."""
    if part == "?":
        return None
    return part.replace("%7C", "|").replace("%3F", "?").replace("%25", "%")


def display_lens_id(lens_id: str | None) -> str:
    """A lens id (``make|model|lens``, escaped for storage) as people read it: the parts
    unescaped, a missing one as ``?``.  Never a key: ``|`` inside a part is ambiguous here."""
    if lens_id is None:
        return "unknown"
    parts = (unescape_key_part(p) for p in lens_id.split("|"))
    return "|".join("?" if p is None else p for p in parts)
