"""Lens keys: a photograph's metadata as a normalised, deterministic :class:`LensKey`.

A vignetting profile belongs to a camera body + lens and varies with focal
length, aperture and (a little) focus distance.  :func:`lens_key_from_metadata` turns
one ExifTool record (``-G`` group names, numeric values) into a :class:`LensKey` holding
exactly those fields; :mod:`vigproc.io.exif` reads the records; the rules that say which
lens a name states and whether the shot fits it are :mod:`vigproc.io.lensident`'s.

Normalisation
-------------
Text fields (see :func:`normalise_text`): Unicode NFKC; control, line-separator
and format characters (C0/C1, bidi overrides, zero-width) removed or turned into a
space; white space collapsed and stripped; ``casefold()``.  Values that carry no
information (``unknown``, ``n/a``, ``----``, ``0``, punctuation/zeros only,
``(Binary data ...)``) are *missing*; absurdly long values (> 200 characters) are
*missing* with a warning.  A model repeating the make (``Canon Canon EOS 10D``) is
reduced to ``canon eos 10d``.  Lens names must contain a digit (a focal length) to
count; unresolved numeric IDs (``65535``, Nikon ``7A 02 ...`` byte strings),
``Unknown 18-55mm``-style names and bare specs (``18.0-55.0 mm``, ``100.0mm
f/2.8``: what ExifTool or a DNG converter writes for an unidentified lens) are
missing.

Numbers come from ExifTool's numeric (``TAG#``, i.e. per-tag ``-n``) values.  A
value outside its physical range (focal length <= 0 or > 10000 mm, f-number < 0.5
or > 1000, negative distance) or two sources disagreeing by more than 20 % make
the field *missing* and log a warning: a contradiction never yields a value.  A
focal length or f-number of 0 is how cameras write "unknown" (manual lenses, many
DNGs): missing, without a warning.  A bad or unknown primary value is not replaced
by a fallback (a Magic Lantern DNG writes FNumber 0 and ApertureValue 1: both wrong).

Every field that is missing is listed in :attr:`LensKey.missing`; the reasons are
in :attr:`LensKey.problems`.
"""

from __future__ import annotations

import logging
import math
import re
import unicodedata
from dataclasses import dataclass, field
from typing import Any, Mapping, Sequence

from vigproc.errors import MetadataError
from vigproc.io.lensident import (
    LensSpec, generic_description, lens_spec, make_brand, shot_problem, strip_make_prefix,
)
# A bare focal/aperture spec ("18.0-55.0 mm", "100.0mm f/2.8") names no lens: ExifTool and
# DNG converters write it when the lens is unidentified (lensident's rule, the one for every front end).
from vigproc.io.lensident import _SPEC_ONLY

__all__ = [
    "KEY_FIELDS",
    "LensKey",
    "casefold_lens_id",
    "escape_key_part",
    "lens_key_from_metadata",
    "normalise_text",
]

logger = logging.getLogger(__name__)

#: The identity/condition fields of a :class:`LensKey`, in key order.
KEY_FIELDS: tuple[str, ...] = (
    "make", "model", "lens", "lens_serial", "focal_mm", "fnumber", "focus_distance_m",
)

MAX_TEXT_LEN = 200
# Longer raw strings are not even cleaned (cost bound for hostile metadata).
_MAX_RAW_LEN = 4096
# Disagreement between two sources of one number that counts as a contradiction.
_REL_TOL = 0.20
# Distances at least this large are "infinity" (Canon encodes inf as 655.35 m,
# EXIF SubjectDistance as 0xFFFFFFFF); the vignetting is the same beyond.
_INF_DISTANCE_M = 600.0
# Physical ranges: focal length in mm, f-number (0.5 ~ the limit of a lens in air).
_MAX_FOCAL = 10000.0
_MIN_FNUMBER = 0.5
_MAX_FNUMBER = 1000.0


def _q(path: str) -> str:
    # repr() keeps messages on one line even for names containing newlines.
    return repr(path)


# --------------------------------------------------------------------------- #
# text normalisation
# --------------------------------------------------------------------------- #

_JUNK = frozenset(
    {
        "", "unknown", "n/a", "na", "none", "null", "nil", "undef", "undefined",
        "not available", "not specified", "(none)", "unknown ()", "unknown ( )",
        "-", "--", "---", "----", "?", "0",
    }
)
_ONLY_PUNCT_OR_ZERO = re.compile(r"^[\W_0]*$")
_HEX_BYTES = re.compile(r"^[0-9a-f]{2}( [0-9a-f]{2})+$")
_DIGITS = re.compile(r"^[\d.\s]+$")
_UNKNOWN_PREFIX = re.compile(r"^unknown\b")
_OR_SPLIT = re.compile(r"\s+or\s+")


def _clean(value: Any, casefold: bool = True) -> tuple[str | None, str | None]:
    """Normalise one metadata text value (``casefold=False``: the same, case kept).

    Returns
    -------
    (text, problem)
        ``text`` is the normalised string or None; ``problem`` explains a
        rejection that deserves a warning (absurd length), else None.
    """
    if isinstance(value, list):  # repeated tag: first non-empty element decides
        value = next((v for v in value if v not in (None, "")), None)
    if value is None or isinstance(value, (bool, dict)):
        return None, None
    if isinstance(value, float):
        text = repr(value) if math.isfinite(value) else ""
    else:
        text = str(value)
    if len(text) > _MAX_RAW_LEN:
        return None, f"implausibly long text ({len(text)} characters)"
    text = unicodedata.normalize("NFKC", text)
    out = []
    for ch in text:
        cat = unicodedata.category(ch)
        if cat in ("Cc", "Zl", "Zp"):  # control / line breaks: a word boundary
            out.append(" ")
        elif cat in ("Cf", "Cs", "Co", "Cn"):  # invisible, bidi, unassigned: dropped
            continue
        else:
            out.append(ch)
    text = " ".join("".join(out).split())
    text = unicodedata.normalize("NFKC", text.casefold() if casefold else text)
    if text.casefold().startswith("(binary data"):
        return None, None
    if len(text) > MAX_TEXT_LEN:
        return None, f"implausibly long text ({len(text)} characters)"
    if text.casefold() in _JUNK or _ONLY_PUNCT_OR_ZERO.match(text):
        return None, None
    return text, None


def _spelt(meta: Mapping[str, Any], tags: Sequence[str], value: str | None, tail: bool = False) -> str | None:
    """How the metadata spelt ``value`` (a normalised text): the first of ``tags``
    (``"Make"``: any group; ``"EXIF:LensModel"``: that one) whose value normalises to
    it, cleaned but with its case kept; also one alternative of an "A or B" LensID.
    ``tail=True`` also takes a value whose last words normalise to it (a name from
    which the key dropped a leading brand)."""
    if value is None:
        return None
    for tag in tags:
        raws = [raw for _, raw in _sources(meta, tag)] if ":" not in tag else [meta.get(tag)]
        for raw in raws:
            text, _ = _clean(raw, casefold=False)
            for part in [text] + (_OR_SPLIT.split(text) if text else []):
                if part and _clean(part)[0] == value:
                    return part
                if tail and part and len(part.casefold()) == len(part) and len(part) > len(value) \
                        and _clean(part[-len(value):])[0] == value and part[-len(value) - 1] == " ":
                    return part[-len(value):]
    return None


def normalise_text(value: Any) -> str | None:
    """Normalise a metadata string for use in a key (None when it carries no information).

    Parameters
    ----------
    value : Any
        A value as ExifTool reports it (str, number or list).

    Returns
    -------
    str or None
        NFKC, control/format characters removed, white space collapsed,
        casefolded; None for empty, placeholder (``Unknown``, ``N/A``, ``----``,
        ``0``...), binary or longer-than-200-character values.
    """
    return _clean(value)[0]


def _lens_text(value: Any) -> tuple[str | None, str | None]:
    """Normalise a lens name; unresolved IDs and "Unknown ..." names are missing."""
    text, problem = _clean(value)
    if text is None:
        return None, problem
    if (_UNKNOWN_PREFIX.match(text) or _HEX_BYTES.match(text) or _DIGITS.match(text)
            or _SPEC_ONLY.match(text)):
        return None, None
    if not any(c.isdigit() for c in text):  # e.g. Nikon LensType "G": flags, not a name
        return None, None
    return text, None


def _dedupe_model(make: str | None, model: str | None) -> str | None:
    """Drop a make prefix that is repeated in the model ("canon canon eos 10d" -> "canon eos 10d")."""
    if not make or not model:
        return model
    first = make.split()[0]
    changed = True
    while changed:
        changed = False
        for prefix in (make, first):
            rest = model[len(prefix) + 1:]
            if model.startswith(prefix + " ") and rest.startswith(first):
                model, changed = rest, True
                break
    return model


def _squash(text: str) -> str:
    # Loose form for comparing lens names from different tags ("EF16-35mm f/2.8L"
    # vs "Canon EF 16-35mm f/2.8L"): letters, digits and dots only.
    return "".join(c for c in text if c.isalnum() or c == ".")


def escape_key_part(part: str | None) -> str:
    # "|" separates key components and "?" marks a missing one: escape so a
    # hostile value cannot forge another key.
    if part is None:
        return "?"
    return part.replace("%", "%25").replace("|", "%7C").replace("?", "%3F")


def casefold_lens_id(lens_id: str) -> str:
    """A typed lens id in the form :meth:`LensKey.lens_id` gives: casefolded, except its
    ``%XX`` escapes, which stay as :func:`escape_key_part` writes them (``%7C``)."""
    parts = re.split(r"(%[0-9A-Fa-f]{2})", lens_id)
    return "".join(p.upper() if i % 2 else p.casefold() for i, p in enumerate(parts))


def _fmt_num(x: float | None) -> str:
    if x is None:
        return "?"
    if math.isinf(x):
        return "inf"
    s = f"{x:.2f}".rstrip("0").rstrip(".")
    return s or "0"


# --------------------------------------------------------------------------- #
# the key
# --------------------------------------------------------------------------- #


@dataclass(frozen=True)
class LensKey:
    """Normalised camera + lens identity and shooting conditions of one photograph.

    Text fields are normalised (see :func:`normalise_text`); any field may be
    None, and then it is listed in :attr:`missing` -- degradation is explicit.

    Attributes
    ----------
    make, model : str or None
        Camera maker and model (EXIF, else maker notes / XMP).
    lens : str or None
        Lens name: Composite:LensID, else EXIF:LensModel, MakerNotes:LensModel,
        XMP:LensModel, XMP-aux:Lens, MakerNotes:Lens, MakerNotes:LensType.  When
        the LensID is ambiguous ("A or B"), the alternative that another lens tag
        names (compared ignoring spaces/punctuation, also without the
        alternative's first word, e.g. the brand) is chosen; if none does,
        ``lens`` is the alternatives sorted and joined with ``" or "``.
    lens_serial : str or None
        Lens serial number (EXIF, maker notes, XMP); all-zero serials are missing.
    focal_mm : float or None
        Real (not 35 mm-equivalent) focal length in mm.
    fnumber : float or None
        F-number.
    focus_distance_m : float or None
        Focus distance in metres (``math.inf`` for infinity); Canon's
        upper/lower bounds are averaged.
    missing : tuple of str
        Names of the fields above that are None, in field order.
    lens_candidates : tuple of str
        All alternatives of an ambiguous LensID (sorted), else empty.
    focal_35mm : float or None
        35 mm-equivalent focal length (informational; not compared).
    width, height : int or None
        Image size as recorded (informational; not compared).
    lens_source : str or None
        The tag the lens came from (informational).
    problems : tuple of str
        Why fields are missing when that is not plain absence (contradictions,
        absurd values); not compared.
    source : str or None
        The file the key was read from; not compared.
    spelling : (make, model, lens, lens make), each str or None
        The names as the metadata spelt them (case kept, control characters removed),
        for what is written for other programs (a lensfun database); not compared.
    lens_problem : str or None
        Why the named lens cannot be the one the frame was shot with (a focal length
        or f-number outside the lens's range, the camera's reported focal range
        contradicting the name); not compared.  Such a lens is never looked up in
        lensfun, and a forensic check never calls the frame consistent with it.
    lens_range : tuple of float or None
        The lens's focal range in mm (the camera's MinFocalLength/MaxFocalLength, else
        what the lens's name states); not compared.
    legacy_ids : tuple of str
        Lens ids earlier versions gave this lens (with the camera's brand in the lens
        name, or ``?`` for a lens now keyed by its description), so that profiles stored
        under them stay findable; not compared.
    """

    make: str | None
    model: str | None
    lens: str | None
    lens_serial: str | None = None
    focal_mm: float | None = None
    fnumber: float | None = None
    focus_distance_m: float | None = None
    missing: tuple[str, ...] = ()
    lens_candidates: tuple[str, ...] = ()
    focal_35mm: float | None = field(default=None, compare=False)
    width: int | None = field(default=None, compare=False)
    height: int | None = field(default=None, compare=False)
    lens_source: str | None = field(default=None, compare=False)
    problems: tuple[str, ...] = field(default=(), compare=False)
    source: str | None = field(default=None, compare=False)
    spelling: tuple[str | None, str | None, str | None, str | None] = field(
        default=(None, None, None, None), compare=False)
    lens_problem: str | None = field(default=None, compare=False)
    lens_range: tuple[float, float] | None = field(default=None, compare=False)
    legacy_ids: tuple[str, ...] = field(default=(), compare=False)

    def __post_init__(self) -> None:
        # `missing` is derived, so a hand-built or deserialised key cannot lie about it.
        derived = tuple(f for f in KEY_FIELDS if getattr(self, f) is None)
        object.__setattr__(self, "missing", derived)

    @property
    def ambiguous(self) -> bool:
        """True when the lens could not be resolved to one of several LensID alternatives."""
        return len(self.lens_candidates) > 1 and self.lens not in self.lens_candidates

    def lens_id(self, with_serial: bool = False) -> str:
        """Deterministic camera + lens identifier, suitable as a database key.

        Parameters
        ----------
        with_serial : bool
            Append ``|sn:<serial>`` (``?`` when unknown) to tell lens units apart.

        Returns
        -------
        str
            ``"make|model|lens"``, e.g. ``"canon|canon eos 5d mark ii|ef24-105mm
            f/4l is usm"``; a missing part is ``?``; ``|``, ``%`` and ``?`` inside
            values are percent-escaped.  No focal length or aperture.
        """
        parts = [escape_key_part(self.make), escape_key_part(self.model), escape_key_part(self.lens)]
        if with_serial:
            parts.append("sn:" + escape_key_part(self.lens_serial))
        return "|".join(parts)

    def key_string(self) -> str:
        """The full key: lens id with serial, focal length, f-number and focus distance.

        Returns
        -------
        str
            e.g. ``"canon|canon eos 40d|?|sn:?|f:135|n:7.1|d:?"`` (numbers rounded
            to 0.01).
        """
        return (
            f"{self.lens_id(with_serial=True)}|f:{_fmt_num(self.focal_mm)}"
            f"|n:{_fmt_num(self.fnumber)}|d:{_fmt_num(self.focus_distance_m)}"
        )

    def profile_key(self, focal_bins: Sequence[float], aperture_bins: Sequence[float]) -> str:
        """Lens id plus the nearest focal-length and f-number bins (nearest in log scale).

        Parameters
        ----------
        focal_bins, aperture_bins : sequence of float
            Positive bin centres (e.g. the focal lengths / f-numbers a profile was
            calibrated at).

        Returns
        -------
        str
            ``"<lens_id>|f:<bin>|n:<bin>"``; ``?`` for a missing value.
        """

        def nearest(x: float | None, bins: Sequence[float], name: str) -> float | None:
            good = [float(b) for b in bins if b is not None and math.isfinite(b) and b > 0]
            if not good:
                raise ValueError(f"{name} must contain positive finite numbers")
            if x is None:
                return None
            return min(good, key=lambda b: (abs(math.log(b / x)), b))

        f = nearest(self.focal_mm, focal_bins, "focal_bins")
        n = nearest(self.fnumber, aperture_bins, "aperture_bins")
        return f"{self.lens_id()}|f:{_fmt_num(f)}|n:{_fmt_num(n)}"

    def to_dict(self) -> dict[str, Any]:
        """JSON-safe dict (infinite distance as the string ``"inf"``)."""
        d = {
            "make": self.make, "model": self.model, "lens": self.lens,
            "lens_serial": self.lens_serial, "focal_mm": self.focal_mm,
            "fnumber": self.fnumber,
            "focus_distance_m": (
                "inf" if self.focus_distance_m is not None and math.isinf(self.focus_distance_m)
                else self.focus_distance_m
            ),
            "missing": list(self.missing),
            "focal_35mm": self.focal_35mm,
            "lens_candidates": list(self.lens_candidates),
            "width": self.width, "height": self.height,
            "lens_source": self.lens_source, "problems": list(self.problems),
            "source": self.source, "lens_problem": self.lens_problem,
            "lens_range": list(self.lens_range) if self.lens_range is not None else None,
            "legacy_ids": list(self.legacy_ids),
            "spelling": list(self.spelling),
        }
        return d

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> "LensKey":
        """Rebuild a key from :meth:`to_dict` output, re-validating every field.

        Raises
        ------
        MetadataError
            If ``d`` is not a mapping or a field has the wrong type/value (stored
            keys are input too).
        """

        def bad(cause: str) -> MetadataError:
            err = MetadataError(f"invalid stored lens key: {cause}")
            err.path, err.cause = None, cause  # type: ignore[attr-defined]
            return err

        if not isinstance(d, Mapping):
            raise bad(f"expected a mapping, got {type(d).__name__}")
        unknown = set(d) - _DICT_FIELDS
        if unknown:
            raise bad(f"unknown fields {sorted(map(str, unknown))}")

        def text(name: str) -> str | None:
            v = d.get(name)
            if v is None:
                return None
            if not isinstance(v, str):
                raise bad(f"{name} must be a string or null")
            out = normalise_text(v)
            if out != v:
                raise bad(f"{name} {v!r} is not normalised")
            return out

        def num(name: str, lo: float, hi: float, allow_inf: bool = False) -> float | None:
            v = d.get(name)
            if v is None:
                return None
            if allow_inf and v == "inf":
                return math.inf
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
                raise bad(f"{name} must be a finite number or null")
            if not lo <= v <= hi:
                raise bad(f"{name}={v} outside [{lo}, {hi}]")
            return float(v)

        def intval(name: str) -> int | None:
            v = d.get(name)
            if v is None:
                return None
            if isinstance(v, bool) or not isinstance(v, int) or v <= 0:
                raise bad(f"{name} must be a positive integer or null")
            return v

        def strlist(name: str) -> tuple[str, ...]:
            v = d.get(name, [])
            if not isinstance(v, (list, tuple)) or not all(isinstance(x, str) for x in v):
                raise bad(f"{name} must be a list of strings")
            return tuple(v)

        spelling = d.get("spelling", [None] * 4)
        if not (isinstance(spelling, (list, tuple)) and len(spelling) == 4
                and all(v is None or (isinstance(v, str) and _clean(v, casefold=False)[0] == v) for v in spelling)):
            raise bad("spelling must be 4 cleaned strings or nulls")
        key = cls(
            make=text("make"), model=text("model"), lens=text("lens"),
            lens_serial=text("lens_serial"),
            focal_mm=num("focal_mm", 1e-9, _MAX_FOCAL),
            fnumber=num("fnumber", _MIN_FNUMBER, _MAX_FNUMBER),
            focus_distance_m=num("focus_distance_m", 0.0, math.inf, allow_inf=True),
            lens_candidates=tuple(sorted(strlist("lens_candidates"))),
            focal_35mm=num("focal_35mm", 1e-9, _MAX_FOCAL * 10),
            width=intval("width"), height=intval("height"),
            lens_source=d.get("lens_source") if isinstance(d.get("lens_source"), str) else None,
            problems=strlist("problems"),
            source=d.get("source") if isinstance(d.get("source"), str) else None,
            spelling=tuple(spelling),
            lens_problem=d.get("lens_problem") if isinstance(d.get("lens_problem"), str) else None,
            lens_range=_stored_range(d.get("lens_range")),
            legacy_ids=strlist("legacy_ids"),
        )
        stored_missing = d.get("missing")
        if stored_missing is not None and tuple(stored_missing) != key.missing:
            raise bad(f"'missing' {stored_missing!r} disagrees with the fields {list(key.missing)!r}")
        return key


_DICT_FIELDS = frozenset(
    {
        "make", "model", "lens", "lens_serial", "focal_mm", "fnumber", "focus_distance_m",
        "missing", "lens_candidates", "focal_35mm", "width", "height", "lens_source", "problems", "source",
        "spelling", "lens_problem", "lens_range", "legacy_ids",
    }
)


def _stored_range(v: Any) -> tuple[float, float] | None:
    """A stored ``lens_range`` (two positive finite numbers, low first), else None."""
    if (isinstance(v, (list, tuple)) and len(v) == 2
            and all(isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x) and x > 0 for x in v)
            and v[0] <= v[1]):
        return (float(v[0]), float(v[1]))
    return None


# --------------------------------------------------------------------------- #
# metadata dict -> LensKey
# --------------------------------------------------------------------------- #


# Group priority per tag: EXIF is what the camera wrote in the standard place;
# maker notes next; XMP last (often rewritten by editors).  Unlisted groups
# follow, alphabetically, so the choice is deterministic.  Composite values are
# derived from these, so they never count as an independent second source.
_GROUP_ORDER = ("EXIF", "MakerNotes", "SigmaRaw", "QuickTime", "XMP")


def _sources(meta: Mapping[str, Any], tag: str) -> list[tuple[str, Any]]:
    """All ``(group, value)`` for ``tag`` except Composite, in priority order."""
    found = []
    suffix = ":" + tag
    for key, value in meta.items():
        if isinstance(key, str) and key.endswith(suffix):
            group = key[: -len(suffix)]
            if group != "Composite":
                found.append((group, value))

    def rank(item: tuple[str, Any]) -> tuple[int, str]:
        g = item[0]
        return (_GROUP_ORDER.index(g) if g in _GROUP_ORDER else len(_GROUP_ORDER), g)

    return sorted(found, key=rank)


def _as_float(value: Any) -> float | None:
    if isinstance(value, list):
        value = value[0] if value else None
    if isinstance(value, bool) or value is None:
        return None
    if isinstance(value, (int, float)):
        try:
            return float(value)
        except OverflowError:  # an int beyond float range: absurd, dropped like other absurd values
            return math.inf
    if isinstance(value, str):
        s = value.strip().lower()
        if s in ("inf", "infinity", "+inf"):
            return math.inf
        s = re.sub(r"\s*(mm|m)$", "", s)
        try:
            x = float(s)
        except ValueError:
            return None
        return x if not math.isnan(x) else None
    return None


class _Builder:
    """Collects field values and the reasons fields are missing for one file."""

    def __init__(self, source: str | None) -> None:
        self.source = source
        self.problems: list[str] = []

    def problem(self, msg: str) -> None:
        self.problems.append(msg)
        logger.warning("%s: %s", _q(self.source) if self.source is not None else "<metadata>", msg)

    def text_field(self, meta: Mapping[str, Any], tag: str, name: str) -> str | None:
        """First informative text value of ``tag``; other sources must not contradict it."""
        chosen: tuple[str, str] | None = None
        for group, raw in _sources(meta, tag):
            text, prob = _clean(raw)
            if prob:
                self.problem(f"{name}: {group}:{tag} rejected: {prob}")
            if text is None:
                continue
            if chosen is None:
                chosen = (group, text)
            elif not (text.startswith(chosen[1]) or chosen[1].startswith(text)):
                self.problem(
                    f"{name}: contradictory {chosen[0]}:{tag}={chosen[1]!r} and {group}:{tag}={text!r}"
                )
                return None
        return chosen[1] if chosen else None

    def number_field(
        self,
        meta: Mapping[str, Any],
        tags: Sequence[str],
        name: str,
        valid: Any,
        expect: str,
        zero_is_unknown: bool = False,
    ) -> float | None:
        """First present value among ``tags`` (in group priority).

        An invalid first value, or another source disagreeing with it by more
        than 20 %, makes the field missing (None) and records a problem.
        """
        values: list[tuple[str, float]] = []
        for tag in tags:
            for group, raw in _sources(meta, tag):
                x = _as_float(raw)
                if x is None or (zero_is_unknown and x == 0):
                    continue
                values.append((f"{group}:{tag}", x))
        if not values:
            return None
        label, primary = values[0]
        if not valid(primary):
            self.problem(f"{name}: {label}={primary:g} is not a valid value (expected {expect})")
            return None
        for other_label, x in values[1:]:
            if not valid(x):
                continue  # an absurd secondary value does not discredit the primary
            if math.isinf(primary) or math.isinf(x):
                continue  # "infinity" vs a far distance is no contradiction
            if abs(x - primary) > _REL_TOL * max(abs(primary), abs(x)):
                self.problem(f"{name}: contradictory {label}={primary:g} and {other_label}={x:g}")
                return None
        return round(primary, 6)


#: The lens tags read after Composite:LensID, in order.
_LENS_TAGS = ("EXIF:LensModel", "MakerNotes:LensModel", "XMP:LensModel", "XMP:Lens", "MakerNotes:Lens",
              "MakerNotes:LensType")


# A maker's own lens line as a name's first word (af-s, ef-m, dt, smc, nikkor...): the
# name exiv2 hosts gave such a lens carried the camera's brand first.
_LENS_LINE = re.compile(r"^(?:[a-z]{1,3}(?:-[a-z]{1,2})?|[a-z]*nikkor|m?\.?zuiko)\s")


def _reported_range(meta: Mapping[str, Any]) -> tuple[float, float] | None:
    """The focal range the camera reports for the mounted lens (MinFocalLength /
    MaxFocalLength, maker notes), None when absent or absurd."""
    lo = next((x for _, raw in _sources(meta, "MinFocalLength") if (x := _as_float(raw))), None)
    hi = next((x for _, raw in _sources(meta, "MaxFocalLength") if (x := _as_float(raw))), None)
    if lo is None or hi is None or not (0 < lo <= hi <= _MAX_FOCAL) or math.isinf(hi):
        return None
    return (lo, hi)


def _fits_range(spec: LensSpec | None, rng: tuple[float, float] | None) -> bool:
    """Whether a lens name's focal range agrees with a reported one (unknown: agrees)."""
    if spec is None or rng is None:
        return True
    return shot_problem("", spec, rng[0], None) is None and shot_problem("", spec, rng[1], None) is None


def _choose_lens(
    meta: Mapping[str, Any], b: _Builder
) -> tuple[str | None, tuple[str, ...], str | None]:
    """Pick the lens name.  Returns ``(lens, candidates, source_tag)``.

    ExifTool's Composite:LensID wins: it resolves a maker note's LensType code, which
    several lenses share, with the focal range the camera reports.  When it cannot
    (``Unknown (251) 16-35mm``), a lens tag whose name states another range is not the
    lens (a problem is recorded) and the lens is keyed by its description (``16-35mm``);
    so is a lens that only a bare spec describes (``18.0-55.0mm f/3.5-5.6``).
    """
    reported = _reported_range(meta)
    raw_id = meta.get("Composite:LensID")
    lens_id_text, prob = _clean(raw_id)
    if prob:
        b.problem(f"lens: Composite:LensID rejected: {prob}")
    generic = generic_description(lens_id_text)
    generic_source = "Composite:LensID" if generic else None
    if generic and reported is None:
        spec = lens_spec(generic)
        reported = (spec.focal_min, spec.focal_max) if spec is not None else None
    fallbacks: list[tuple[str, str]] = []
    named = [k for k in _LENS_TAGS if k in meta]
    # Any other group's LensType (e.g. SigmaRaw) after the named ones.
    named += [f"{g}:LensType" for g, _ in _sources(meta, "LensType") if g != "MakerNotes"]
    for tag_key in named:
        text, prob = _lens_text(meta[tag_key])
        if prob:
            b.problem(f"lens: {tag_key} rejected: {prob}")
        if text is None:
            desc = generic_description(_clean(meta[tag_key])[0])
            if desc and generic is None:
                generic, generic_source = desc, tag_key
            continue
        if not _fits_range(lens_spec(text), reported):
            lo, hi = reported  # type: ignore[misc]  # _fits_range is only False with a range
            b.problem(f"lens: {tag_key}={text!r} is not the mounted lens: the camera reports a {lo:g}-{hi:g} mm lens")
            continue
        fallbacks.append((tag_key, text))

    if lens_id_text is not None and generic_source != "Composite:LensID":
        parts = [p.strip() for p in _OR_SPLIT.split(lens_id_text) if p.strip()]
        if len(parts) > 1:
            # Alternatives are kept even without a digit ("... or tamron lens"):
            # dropping one would fake certainty.
            candidates = tuple(sorted(set(parts)))
            if len(candidates) == 1:
                lens, _ = _lens_text(candidates[0])
                if lens is not None:
                    return lens, (), "Composite:LensID"
            else:
                for tag_key, other in fallbacks:
                    so = _squash(other)
                    for cand in candidates:
                        words = cand.split(" ", 1)
                        if so and (_squash(cand) == so or (len(words) == 2 and _squash(words[1]) == so)):
                            return cand, candidates, f"Composite:LensID+{tag_key}"
                b.problem(f"lens: ambiguous Composite:LensID ({len(candidates)} alternatives)")
                return " or ".join(candidates), candidates, "Composite:LensID"
        else:
            lens, _ = _lens_text(lens_id_text)
            if lens is not None:
                return lens, (), "Composite:LensID"
    if fallbacks:
        tag_key, text = fallbacks[0]
        return text, (), tag_key
    if generic:
        return generic, (), f"{generic_source} (description)"
    return None, (), None


def _lens_identity(make: str | None, model: str | None, lens: str | None, lens_source: str | None,
                   candidates: tuple[str, ...], focal: float | None, fnum: float | None, meta: Mapping[str, Any],
                   b: _Builder) -> tuple[str | None, tuple[str, ...], str | None, tuple[float, float] | None,
                                     tuple[str, ...]]:
    """The lens as keyed (a brand equal to the camera's make dropped, also from the
    alternatives of an ambiguous LensID), why the shot cannot be with it (None: it
    can), its focal range, and the ids earlier versions gave it.  Returns ``(lens,
    candidates, lens_problem, lens_range, legacy_ids)``."""
    if lens is None:
        return None, candidates, None, None, ()
    keyed = strip_make_prefix(make, lens)
    if candidates:
        stripped = tuple(sorted({strip_make_prefix(make, c) or c for c in candidates}))
        keyed = keyed if lens in candidates else " or ".join(stripped)
        candidates = stripped
    described = bool(lens_source and lens_source.endswith("(description)"))
    old: list[str | None] = []
    # A described lens has no earlier id of its own: earlier versions keyed it "?", with
    # every other undescribed lens of the body, a profile of several lenses.
    if described:
        pass
    elif keyed != lens:
        old.append(lens)
    elif (brand := make_brand(make)) and _LENS_LINE.match(lens):
        old.append(f"{brand} {lens}")  # what an exiv2 host sent for the maker's own lens
    legacy = tuple(dict.fromkeys(
        "|".join(escape_key_part(p) for p in (make, model, o)) for o in old if o != keyed))
    spec = lens_spec(lens)
    reported = _reported_range(meta)
    problem = None
    if spec is not None and reported is not None and not _fits_range(spec, reported):
        problem = (f"the camera reports a {reported[0]:g}-{reported[1]:g} mm lens, not {lens} "
                   f"({spec.focal_min:g}-{spec.focal_max:g} mm)")
    if problem is None and reported is not None:
        problem = shot_problem(lens, LensSpec(*reported), focal, None,
                               spec_from="the focal range the camera reports")
    if problem is None and spec is not None:
        max_ap = next((x for _, raw in _sources(meta, "MaxApertureValue") if (x := _as_float(raw))), None)
        problem = shot_problem(lens, spec, focal, fnum, spec_from="its name",
                               max_aperture=max_ap if max_ap is not None and _valid_fnumber(max_ap) else None)
    if candidates and keyed not in candidates:
        problem = None  # an unresolved choice between lenses: no one name to hold the shot against
    if problem is not None:
        b.problem(f"lens: {problem}")
    rng = reported if reported is not None else ((spec.focal_min, spec.focal_max) if spec is not None else None)
    return keyed, candidates, problem, rng, legacy


def _valid_focal(x: float) -> bool:
    return 0 < x <= _MAX_FOCAL


def _valid_fnumber(x: float) -> bool:
    return _MIN_FNUMBER <= x <= _MAX_FNUMBER


def _valid_distance(x: float) -> bool:
    return x >= 0  # inf allowed


def _focus_distance(meta: Mapping[str, Any], b: _Builder) -> float | None:
    """Focus distance in m: FocusDistance tags, else Canon bounds, else SubjectDistance."""

    def norm(x: float) -> float:
        return math.inf if x >= _INF_DISTANCE_M else x

    def failed() -> bool:
        return any(p.startswith("focus_distance_m:") for p in b.problems)

    # 0 means "not recorded" in all of these tags.
    d = b.number_field(meta, ("FocusDistance",), "focus_distance_m", _valid_distance, ">= 0",
                       zero_is_unknown=True)
    if d is not None or failed():
        return norm(d) if d is not None else None
    comp = _as_float(meta.get("Composite:FocusDistance"))
    if comp is not None and comp != 0:
        if comp < 0:
            b.problem(f"focus_distance_m: Composite:FocusDistance={comp:g} is negative")
            return None
        return norm(comp)
    upper = _as_float(meta.get("MakerNotes:FocusDistanceUpper"))
    lower = _as_float(meta.get("MakerNotes:FocusDistanceLower"))
    if upper is not None and upper != 0:
        if upper < 0 or (lower is not None and lower < 0):
            b.problem("focus_distance_m: negative MakerNotes:FocusDistanceUpper/Lower")
            return None
        if norm(upper) == math.inf:
            return math.inf
        if lower is not None and lower > 0:
            if lower > upper:
                b.problem(
                    f"focus_distance_m: contradictory MakerNotes:FocusDistanceLower={lower:g} "
                    f"> FocusDistanceUpper={upper:g}"
                )
                return None
            return round((upper + lower) / 2, 6)
        return round(upper, 6)
    # SubjectDistance last: compacts often fill it with a rough guess.
    d = b.number_field(meta, ("SubjectDistance",), "focus_distance_m", _valid_distance, ">= 0",
                       zero_is_unknown=True)
    return norm(d) if d is not None else None


def _image_size(meta: Mapping[str, Any]) -> tuple[int | None, int | None]:
    size = meta.get("Composite:ImageSize")
    if isinstance(size, str):
        m = re.match(r"^\s*(\d+)\s*[x ]\s*(\d+)\s*$", size)
        if m:
            w, h = int(m.group(1)), int(m.group(2))
            if 0 < w < 10**6 and 0 < h < 10**6:
                return w, h
    return None, None


def lens_key_from_metadata(meta: Mapping[str, Any], source: str | None = None) -> LensKey:
    """Build a :class:`LensKey` from one ExifTool JSON record (``-G`` group names).

    Parameters
    ----------
    meta : mapping
        Tag -> value, keys like ``"EXIF:Make"``, ``"Composite:LensID"``; numeric
        tags as numbers (ExifTool ``TAG#`` / ``-n``).  Treated as hostile.
    source : str, optional
        File name, used in warnings and stored in :attr:`LensKey.source`.

    Returns
    -------
    LensKey
        Never raises for bad values: they become missing fields with a problem
        recorded and a warning logged.
    """
    b = _Builder(source)
    make = b.text_field(meta, "Make", "make")
    model = _dedupe_model(make, b.text_field(meta, "Model", "model"))
    lens, candidates, lens_source = _choose_lens(meta, b)
    serial = None
    for group, raw in _sources(meta, "LensSerialNumber"):
        serial, prob = _clean(raw)
        if prob:
            b.problem(f"lens_serial: {group}:LensSerialNumber rejected: {prob}")
        if serial is not None:
            break
    # 0 is how cameras and converters write "unknown" (manual and adapted lenses, many
    # DNGs): a missing value, not a problem to warn about on every command
    focal = b.number_field(meta, ("FocalLength",), "focal_mm", _valid_focal, f"0 < mm <= {_MAX_FOCAL:g}",
                           zero_is_unknown=True)
    fnum_range = f"{_MIN_FNUMBER:g}..{_MAX_FNUMBER:g}"
    fnum = b.number_field(meta, ("FNumber",), "fnumber", _valid_fnumber, fnum_range, zero_is_unknown=True)
    # FNumber 0 says "unknown": its fallbacks are no better (Magic Lantern writes ApertureValue 1)
    fnum_unknown = any(_as_float(raw) == 0 for _, raw in _sources(meta, "FNumber"))
    if fnum is None and not fnum_unknown and not any(p.startswith("fnumber:") for p in b.problems):
        # ApertureValue only as a fallback, never as a cross-check: some cameras
        # write a wrong one next to a right FNumber (Ricoh RR330: f/2.88 vs APEX 4).
        fnum = b.number_field(meta, ("ApertureValue",), "fnumber", _valid_fnumber, fnum_range)
    if fnum is None and not fnum_unknown and not any(p.startswith("fnumber:") for p in b.problems):
        # Composite:Aperture only when nothing else exists (it is derived from them).
        ap = _as_float(meta.get("Composite:Aperture"))
        if ap is not None:
            if _valid_fnumber(ap):
                fnum = round(ap, 6)
            else:
                b.problem(f"fnumber: Composite:Aperture={ap:g} is not a valid value")
    dist = _focus_distance(meta, b)
    f35 = None
    for k in ("EXIF:FocalLengthIn35mmFormat", "Composite:FocalLength35efl"):
        x = _as_float(meta.get(k))
        if x is None or not 0 < x <= _MAX_FOCAL * 10:
            continue
        if k.startswith("Composite") and focal is not None and abs(x - focal) <= 0.01 * focal:
            # exiftool's composite falls back to a scale factor of 1 when it cannot tell the
            # sensor size: a phone's 3.85 mm is not a 3.85-mm-equivalent ultra-wide
            continue
        f35 = round(x, 6)
        break
    w, h = _image_size(meta)
    lens, candidates, lens_problem, lens_range, legacy = _lens_identity(
        make, model, lens, lens_source, candidates, focal, fnum, meta, b)
    spelt_model = _spelt(meta, ("Model",), model)
    if spelt_model is None and model is not None:  # a repeated make was dropped from the model
        whole = _spelt(meta, ("Model",), b.text_field(meta, "Model", "model"))
        spelt_model = whole[len(whole) - len(model):] if whole and len(whole.casefold()) == len(whole) else None
    lens_tags = ("Composite:LensID",) + _LENS_TAGS + ("LensType",)
    spelt_lens = _spelt(meta, lens_tags, lens)
    if spelt_lens is None and lens is not None:  # the camera's brand was dropped from the lens's name
        spelt_lens = _spelt(meta, lens_tags, lens, tail=True)
    spelling = (_spelt(meta, ("Make",), make), spelt_model, spelt_lens,
                _clean(next((raw for _, raw in _sources(meta, "LensMake")), None), casefold=False)[0])
    return LensKey(
        make=make, model=model, lens=lens, lens_serial=serial, focal_mm=focal,
        fnumber=fnum, focus_distance_m=dist, lens_candidates=candidates,
        focal_35mm=f35, width=w, height=h, lens_source=lens_source, problems=tuple(b.problems),
        source=source, lens_problem=lens_problem, lens_range=lens_range, legacy_ids=legacy,
        spelling=spelling,
    )
