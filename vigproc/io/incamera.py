"""What the camera already did: in-camera vignetting correction of a JPEG.

Many cameras remove their lens's fall-off from the JPEGs they write and record it in
their maker notes; every phone's image processor corrects lens shading. Removing the
fall-off again from such a frame would take the scene's own light for the lens's
(an iPhone 5s frame had 1.1 EV "removed" at its corners). A RAW file is never
affected: its pixels are the sensor's.

Read through exiftool (the pipeline's one :class:`vigproc.io.exif.ExifReader`,
``read_tags``, numeric values), any group:

=============================  ==========================================  ================
tag                            cameras                                     corrected when
=============================  ==========================================  ================
PeripheralIlluminationCorr     Canon (EOS 7D on), Pentax                   ≠ 0 (On)
PeripheralLighting             Canon PowerShot, Fujifilm                   ≠ 0 (On)
PeripheralLightingSetting      Canon                                       ≠ 0 (On)
VignetteControl                Nikon                                       ≠ 0 (Low/Normal/High)
VignettingCorrection           Sony (maker notes: 2 Auto)                  2
ShadingCompensation            Olympus/OM System, Panasonic                ≠ 0 (On)
=============================  ==========================================  ================

A JPEG from a phone is taken as corrected in camera: its Make is one of
:data:`PHONE_MAKES` (Samsung only for its phone models, ``SM-``/``GT-``/… or Galaxy;
Sony only for Xperia). An explicit Off flag of a camera is what it says.

A file of any format that vigproc itself corrected (its ``XMP-vigproc:Applied`` record,
read as ``XMP:Applied``) is corrected already too: an output fed back in is left alone.
"""

from __future__ import annotations

import logging
import os
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Mapping

from vigproc.errors import VigprocError
from vigproc.io.formats import READ_SUFFIXES

log = logging.getLogger(__name__)

__all__ = ["FLAG_TAGS", "InCamera", "PHONE_MAKES", "from_tags", "read_in_camera"]

#: Maker-note flags of in-camera vignetting correction, and the numeric values that mean On
#: (None: any value but 0).
FLAG_TAGS: dict[str, frozenset[int] | None] = {
    "PeripheralIlluminationCorr": None,
    "PeripheralLighting": None,
    "PeripheralLightingSetting": None,
    "VignetteControl": None,
    "VignettingCorrection": frozenset({2}),  # Sony maker notes: 0 Off, 2 Auto, 0xffffffff n/a
    "ShadingCompensation": None,
}
#: Makes (casefolded, first word) whose cameras are phones, whose image processor corrects lens shading.
PHONE_MAKES = frozenset({
    "apple", "google", "huawei", "honor", "xiaomi", "redmi", "poco", "oneplus", "oppo", "vivo", "realme",
    "htc", "motorola", "blackberry", "jolla", "nokia", "hmd", "lge", "lg", "zte", "meizu", "asus", "lenovo",
    "fairphone", "nothing", "tecno", "infinix", "microsoft", "sony ericsson",
})
#: Samsung's phone models (its cameras are NX, WB, ES, PL, Digimax...).
_SAMSUNG_PHONE = re.compile(r"^(sm-|gt-|sgh-|sch-|sph-|shv-|galaxy)", re.IGNORECASE)
#: Suffixes of JPEG files (the only outputs of a camera's image processor vigproc reads as such).
JPEG_SUFFIXES = frozenset(READ_SUFFIXES["jpeg"])
#: Tags read: the flags, and the make and model for phones.
TAGS = ("Make", "Model", *FLAG_TAGS, "XMP:Applied")
#: vigproc's own record that it corrected the file (metadata.py writes it).
_VIGPROC_APPLIED = "XMP:Applied"


@dataclass(frozen=True)
class InCamera:
    """A frame whose camera corrected its vignetting.

    Attributes
    ----------
    evidence : str
        The tag and value (``VignetteControl=3``) or ``phone`` that says so.
    reason : str
        A sentence for the record and the log.
    """

    evidence: str
    reason: str


def _int(value: Any) -> int | None:
    if isinstance(value, bool):
        return None
    if isinstance(value, (int, float)):
        return int(value)
    try:
        return int(str(value).split()[0])
    except (ValueError, IndexError):
        return None


def _is_phone(make: str, model: str) -> bool:
    m = make.casefold().strip()
    first = m.split()[0] if m else ""
    if m.startswith("sony ericsson") or first in PHONE_MAKES or m in PHONE_MAKES:
        return True
    if first == "samsung":
        return bool(_SAMSUNG_PHONE.match(model.strip()))
    if first == "sony":
        return "xperia" in model.casefold()
    return False


def from_tags(tags: Mapping[str, Any]) -> InCamera | None:
    """In-camera correction from exiftool's numeric values of :data:`TAGS` (keyed by
    tag name), or None when nothing says so.

    Examples
    --------
    >>> from_tags({"Make": "NIKON CORPORATION", "VignetteControl": 3}).evidence
    'VignetteControl=3'
    >>> from_tags({"Make": "Apple", "Model": "iPhone 5s"}).evidence
    'phone'
    >>> from_tags({"Make": "OLYMPUS IMAGING CORP.", "ShadingCompensation": 0}) is None
    True
    """
    if tags.get(_VIGPROC_APPLIED) in (True, 1, "True", "true"):
        return InCamera("XMP-vigproc:Applied", "vigproc already corrected it (the file's XMP-vigproc record)")
    for name, on in FLAG_TAGS.items():
        v = _int(tags.get(name))
        if v is None:
            continue
        if (v != 0 if on is None else v in on):
            return InCamera(f"{name}={v}", f"the camera already corrected its vignetting ({name} is on)")
    make, model = str(tags.get("Make") or ""), str(tags.get("Model") or "")
    if _is_phone(make, model):
        return InCamera("phone", f"a phone's JPEG ({make.strip()} {model.strip()}): its image processor already "
                                 "corrected the lens shading")
    return None


def read_in_camera(path: str | os.PathLike[str], reader) -> InCamera | None:
    """Whether the camera already corrected the vignetting of the JPEG at ``path``.

    Parameters
    ----------
    path : path
    reader : ExifReader or None
        The pipeline's exiftool process (None: nothing is read, None returned).

    Returns
    -------
    InCamera or None
        None for any file that is not a JPEG (a RAW is never affected), a file whose
        metadata cannot be read (logged), or one whose metadata says nothing.
    """
    read_tags = getattr(reader, "read_tags", None)  # a host's stand-in reader may have none
    if read_tags is None:
        return None
    jpeg = Path(path).suffix.lower() in JPEG_SUFFIXES
    try:
        tags = read_tags(path, TAGS if jpeg else (_VIGPROC_APPLIED,))
    except VigprocError as exc:  # the lens read already reported it; the frame is estimated as before
        log.debug("%s: in-camera correction flags not read: %s", os.fspath(path), exc)
        return None
    return from_tags(tags)  # any other format: only vigproc's own record is read
