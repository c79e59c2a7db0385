"""Write vigproc's lensfun calibrations as a lensfun database file (``<lensdatabase version="1">``).

The writer of :mod:`vigproc.stores.lensfun_io`'s export (``vigproc profile export-lensfun``):
names checked as XML 1.0 can carry them, numbers as lensfun reads them, the file built with
:mod:`xml.etree.ElementTree` and written atomically.

References
----------
.. [1] lensfun documentation, "Database file format",
   https://lensfun.github.io/manual/latest/dbformat.html
.. [2] lensfun ``libs/lensfun/database.cpp`` (XML parser, version check), 0.3.x.
"""

from __future__ import annotations

import logging
import math
import re
import xml.etree.ElementTree as ET
from collections.abc import Iterable, Sequence
from pathlib import Path

from vigproc.atomic import atomic_write_text
from vigproc.errors import ModelError

__all__ = ["LENSFUN_DB_VERSION", "export_lensfun_xml"]

logger = logging.getLogger(__name__)

#: ``<lensdatabase version=...>`` written by :func:`export_lensfun_xml` (the newest
#: version lensfun 0.3.4, bundled with lensfunpy 1.18, accepts).
LENSFUN_DB_VERSION = 1

#: Characters XML 1.0 cannot carry, plus all other control characters (names are one line).
_BAD_CHARS = re.compile("[\x00-\x1f\x7f-\x9f\ud800-\udfff\ufffe\uffff]")


def _clean_name(value: object, what: str) -> str:
    if not isinstance(value, str):
        raise ModelError(f"lens {what} must be a string, got {type(value).__name__}")
    text = value.strip()
    if not text:
        raise ModelError(f"lens {what} must not be empty")
    bad = _BAD_CHARS.search(text)
    if bad:
        raise ModelError(f"lens {what} {text!r} contains the control character U+{ord(bad.group()):04X}")
    return text


def _number(value: object, what: str, positive: bool) -> float:
    try:
        x = float(value)  # type: ignore[arg-type]
    except (TypeError, ValueError):
        raise ModelError(f"{what} must be a number, got {value!r}") from None
    if not math.isfinite(x) or (positive and x <= 0):
        raise ModelError(f"{what} must be {'positive and ' if positive else ''}finite, got {value!r}")
    return x


def _fmt(x: float) -> str:
    # shortest round-trip repr; lensfun reads it with atof / g_ascii_strtod
    return repr(float(x))


def export_lensfun_xml(entries: Iterable[Sequence[object]], path: str | Path) -> int:
    """Write pa vignetting calibrations as a lensfun database file.

    Parameters
    ----------
    entries : iterable of 10-sequences
        ``(maker, model, mount, crop_factor, focal, aperture, distance, k1,
        k2, k3)`` (see :class:`vigproc.stores.lensfun_io.LensfunEntry`); focal in mm, aperture as
        f-number, distance in metres (1000 = infinity).  Entries of the same
        ``(maker, model, crop_factor)`` form one ``<lens>`` (their mounts are
        collected); a repeated ``(focal, aperture, distance)`` point keeps the
        last entry, as lensfun does.
    path : str or Path
        Output file, written atomically (UTF-8).  Put it in lensfun's user
        database folder (``~/.local/share/lensfun/``) or pass it to
        ``lensfunpy.Database(paths=[...])``.

    Returns
    -------
    int
        Number of ``<lens>`` elements written.

    Raises
    ------
    ModelError
        If an entry is malformed (empty or control characters in a name, a
        non-positive focal/aperture/distance/crop factor, non-finite k) or
        there are no entries.
    ImageWriteError
        If the file cannot be written.

    Notes
    -----
    The file is ``<lensdatabase version="1">`` (:data:`LENSFUN_DB_VERSION`),
    the newest version lensfun 0.3.4 accepts; it is built with
    :mod:`xml.etree.ElementTree`, so names with quotes, ``<``, ``&`` or any
    Unicode survive.

    References
    ----------
    .. [1] lensfun, "Database file format",
       https://lensfun.github.io/manual/latest/dbformat.html
    """
    lenses: dict[tuple[str, str, float], dict] = {}
    for i, entry in enumerate(entries):
        try:
            maker, model, mount, crop, focal, aperture, distance, k1, k2, k3 = entry
        except (TypeError, ValueError):
            raise ModelError(f"entry {i}: expected (maker, model, mount, crop_factor, focal, aperture, "
                             "distance, k1, k2, k3)") from None
        maker, model = _clean_name(maker, "maker"), _clean_name(model, "model")
        mount = _clean_name(mount, "mount")
        crop = _number(crop, "crop factor", True)
        point = tuple(_number(v, n, True) for v, n in ((focal, "focal"), (aperture, "aperture"),
                                                       (distance, "distance")))
        ks = tuple(_number(v, n, False) for v, n in ((k1, "k1"), (k2, "k2"), (k3, "k3")))
        lens = lenses.setdefault((maker, model, crop), {"mounts": [], "points": {}})
        if mount not in lens["mounts"]:
            lens["mounts"].append(mount)
        if point in lens["points"] and lens["points"][point] != ks:
            logger.warning("%s / %s: repeated calibration point %s; keeping the last", maker, model, point)
        lens["points"][point] = ks
    if not lenses:
        raise ModelError("no lens calibration entries to export")

    root = ET.Element("lensdatabase", version=str(LENSFUN_DB_VERSION))
    for (maker, model, crop), lens in lenses.items():
        el = ET.SubElement(root, "lens")
        ET.SubElement(el, "maker").text = maker
        ET.SubElement(el, "model").text = model
        for mount in lens["mounts"]:
            ET.SubElement(el, "mount").text = mount
        ET.SubElement(el, "cropfactor").text = _fmt(crop)
        cal = ET.SubElement(el, "calibration")
        for (focal, aperture, distance), (k1, k2, k3) in sorted(lens["points"].items()):
            ET.SubElement(cal, "vignetting", {
                "model": "pa", "focal": _fmt(focal), "aperture": _fmt(aperture), "distance": _fmt(distance),
                "k1": _fmt(k1), "k2": _fmt(k2), "k3": _fmt(k3),
            })
    ET.indent(root)
    text = '<?xml version="1.0" encoding="UTF-8"?>\n' + ET.tostring(root, encoding="unicode") + "\n"
    ET.fromstring(text.encode("utf-8"))  # well-formed by construction; cheap self-check
    atomic_write_text(path, text)
    logger.info("wrote %d lens(es) to lensfun database %s", len(lenses), path)
    return len(lenses)
