"""Carry the source photo's metadata into a corrected output, plus a record of the correction.

After vigproc writes a corrected image it copies the source file's metadata
(camera, lens, exposure, dates, author, GPS, IPTC/XMP descriptions, maker notes)
into it with the ``exiftool`` program, and adds what vigproc did as XMP in its
own namespace.  :func:`write_corrected` does pixels and metadata on a temporary
file and renames it into place only when both succeeded, so a crash never
leaves an output without (or with half of) its metadata.

What is preserved, per output format
------------------------------------
===========  ===============================================================
output       metadata
===========  ===============================================================
TIFF, PNG    All writable EXIF/GPS/IPTC/XMP tags and maker notes of the
             source (``exiftool -tagsFromFile SRC -all:all``), *minus* the
             tags listed below; the record as XMP (``XMP-vigproc:*``).
             PNG keeps EXIF in an ``eXIf`` chunk and XMP in ``iTXt``.
OpenEXR      exiftool cannot write OpenEXR (it is read-only there), so the
             file is rewritten with OpenImageIO header attributes instead:
             the camera/lens/exposure fields of :data:`EXR_TAGS` (``Make``,
             ``Model``, ``Exif:LensModel``, ``Exif:FocalLength``...; the
             capture time also goes to ``DateTime``, which OpenEXR stores as
             its standard ``capDate``) and the record as ``vigproc:*``
             attributes.  No GPS, IPTC, XMP or maker notes.
===========  ===============================================================

Tags that are *not* copied because they would be wrong for the output:

* thumbnails and previews (IFD1, ``*Thumbnail*``, ``*Preview*``, ``JpgFromRaw``,
  ``OtherImage``; a preview inside maker notes is deleted too);
* the description of the pixel encoding, which :func:`vigproc.io.images.write_image`
  sets for the data it wrote: EXIF ``ColorSpace``, ``Gamma``, the
  interoperability IFD (``R98`` = sRGB...), PNG gamma/chromaticity/sRGB chunks.
  Captions stay: IFD0 ``ImageDescription`` (where ``write_image`` puts its linear-TIFF
  marker :data:`vigproc.io.images.LINEAR_TIFF_MARKER`: the copy replaces it and the
  transfer is recorded as ``XMP-vigproc:Transfer``), XMP ``dc:description``, IPTC
  ``Caption-Abstract``;
* the ICC profile.  A linear output's source profile describes the source's own
  tone curve, so keeping it would make colour-managed viewers decode the output
  wrongly (a linear RGB TIFF carries vigproc's own linear-sRGB profile instead,
  :mod:`vigproc.io.icc`).  exiftool does not copy it with ``-all:all`` anyway; it is excluded
  explicitly as well.  (A display-encoded output of a display-encoded source --
  a JPEG back as a JPEG -- keeps the source's colour description, ICC profile and
  interoperability index included: ``keep_colour`` of :func:`copy_metadata`.);
* image-structure tags (size, bits, compression, YCbCr layout, EXIF pixel
  dimensions, their XMP ``tiff:``/``exif:`` copies) -- exiftool protects the
  TIFF ones; the others are excluded here;
* ``Software`` and ``ModifyDate`` in every group, with its ``SubSecTime`` and
  ``OffsetTime`` (the output is vigproc's, written now; so is the XMP ``CreateDate``
  OpenImageIO stamps, removed unless the source has its own), and all composite
  tags (exiftool would otherwise write ``ModifyDate`` back through
  ``Composite:SubSecModifyDate``; the real tags behind composites are copied
  directly);
* RAW/DNG-only data: DNG version, ``UniqueCameraModel``, private DNG data,
  the embedded original RAW, CFA/level tags (most are protected by exiftool);
* Adobe Camera Raw settings (``XMP-crs``): they include ACR's own vignette and
  lens-profile corrections, which an editor would apply a second time;
* an existing ``XMP-vigproc`` record of the source.

``Orientation`` is kept: :func:`vigproc.io.images.read_image` never rotates pixels
(nor does the RAW development), so the output's pixel grid is the source's
stored grid and the source's orientation flag still describes it.

The correction record
---------------------
=========================  ============================================
XMP (TIFF, PNG)            OpenEXR attribute
=========================  ============================================
``XMP-vigproc:Model``      ``vigproc:Model`` -- :meth:`VignettingModel.to_json`
``XMP-vigproc:Method``     ``vigproc:Method`` -- estimator name
``XMP-vigproc:Version``    ``vigproc:Version`` -- vigproc version
``XMP-vigproc:Applied``    ``vigproc:Applied`` -- bool (int 0/1 in EXR)
``XMP-vigproc:Strength``   ``vigproc:Strength`` -- correction strength
=========================  ============================================

The namespace URI is :data:`XMP_NAMESPACE`; exiftool learns it from a config
file shipped in the package (``vigproc/data/exiftool.config``,
:data:`vigproc.io.exiftool_process.CONFIG_FILE`).  The record is written after the copy, and any
record the *source* carried is excluded from the copy: it described an earlier
correction, not this output.

RAW formats that are not TIFF-based keep their camera tags in groups a TIFF has not
(CRW's ``CanonRaw``, X3F's header): :data:`_CAMERA_TAGS` are also copied into EXIF by
name, before the group-preserving copy (which wins where the source has them in EXIF).

Cost: two commands per output (check/read the source, then write) through one persistent
exiftool per process (:func:`vigproc.io.exiftool_process.shared_process`, started on the
first copy, restarted once if it dies or hangs during one); an OpenEXR output is written
twice (pixels, then with attributes).

File names
----------
exiftool is never run through a shell: the persistent process takes its arguments one per
line on a pipe.  Paths are passed absolute, so a name starting with ``-`` (or equal to ``-``
or ``@``) cannot be taken as an option, and no ``--`` is sent (it would turn the protocol's
own closing options into file names).  A name the protocol cannot carry (a line break,
bytes that are not UTF-8) is never sent: the source is read through a symbolic link with a
plain name in a private folder (:func:`vigproc.scratch.scratch_folder`: removed after the
call, or by the next process's sweep if this one is killed), and the output is rewritten as a private copy there and put
back atomically.  exiftool expands ``%d``, ``%f``, ``%e``... in the ``-tagsFromFile`` name
and has no escape for ``%``; such a source takes the same link.  Warnings and errors name
the caller's files, not the aliases.

The program is ``$VIGPROC_EXIFTOOL`` if set, else ``exiftool`` on ``PATH``.
"""

from __future__ import annotations

import json
import logging
import math
import os
import re
import shutil
from typing import Any, Mapping

import numpy as np
import OpenImageIO as oiio

from vigproc._version import __version__
from vigproc.atomic import replacing
from vigproc.scratch import scratch_folder
from vigproc.errors import (ImageReadError, ImageWriteError, InvalidImageError, ModelError, OutputRefusedError,
                            OutputSettingsError, VigprocError, write_error)
from vigproc.io.exiftool_process import ExiftoolDied, ExiftoolProcess, ExiftoolResult, line_safe, shared_process
from vigproc.io.formats import WRITE_EXT_FORMAT as _EXT_FORMAT
from vigproc.io.formats import WRITE_FORMAT_ALIASES as _FORMAT_ALIASES
from vigproc.io.formats import WRITE_FORMAT_EXT as _FORMAT_EXT
from vigproc.io.images import recorded_transfer, write_image
from vigproc.core.model import VignettingModel

__all__ = [
    "EXR_TAGS",
    "XMP_NAMESPACE",
    "copy_metadata",
    "exiftool_path",
    "make_record",
    "read_record",
    "write_corrected",
]

logger = logging.getLogger(__name__)

#: URI of vigproc's XMP namespace (prefix ``vigproc``).  ``.invalid`` (RFC 6761)
#: can never be registered by anyone, so the URI cannot collide.
XMP_NAMESPACE = "http://vigproc.invalid/ns/xmp/1.0/"

#: Record fields: record key -> (XMP/EXR tag name, kind).
_RECORD_FIELDS: dict[str, tuple[str, str]] = {
    "model": ("Model", "str"),
    "method": ("Method", "str"),
    "version": ("Version", "str"),
    "applied": ("Applied", "bool"),
    "strength": ("Strength", "float"),
}

#: Tags not copied from the source (see the module docstring for why).
_EXCLUDE = (
    # thumbnails / previews
    "IFD1:all", "*Thumbnail*", "*Preview*", "JpgFromRaw", "OtherImage",
    # pixel encoding: write_image describes the data it wrote
    "ColorSpace", "Gamma", "InteropIFD:all", "ICC_Profile:all",
    "SRGBRendering", "WhitePointX", "WhitePointY", "RedX", "RedY", "GreenX", "GreenY",
    "BlueX", "BlueY",
    # image structure
    "ImageWidth", "ImageHeight", "ExifImageWidth", "ExifImageHeight", "BitsPerSample",
    "Compression", "PhotometricInterpretation", "SamplesPerPixel", "PlanarConfiguration",
    "YCbCrSubSampling", "YCbCrPositioning", "YCbCrCoefficients", "ComponentsConfiguration",
    "CompressedBitsPerPixel",
    # written by vigproc now (composites such as SubSecModifyDate would write ModifyDate back)
    "Software", "ModifyDate", "SubSecTime", "OffsetTime", "XMP-tiff:DateTime",
    "XMP-xmp:MetadataDate", "XMP-xmp:CreatorTool", "Composite:all",
    # RAW/DNG only
    "DNGVersion", "DNGBackwardVersion", "UniqueCameraModel", "LocalizedCameraModel",
    "DNGPrivateData", "DNGAdobeData", "MakerNoteSafety", "OriginalRawFileData",
    "CFAPattern2", "CFARepeatPatternDim", "BlackLevel", "WhiteLevel",
    # Camera Raw develop settings; an older vigproc record
    "XMP-crs:all", "XMP-vigproc:all",
)
#: Camera tags copied into EXIF by name (``-EXIF:TAG<TAG``) besides the group-preserving copy:
#: RAW formats that are not TIFF-based keep them in groups a TIFF has not (a CRW's
#: ``CanonRaw``, an X3F's header), where ``-all:all`` alone would copy nothing.
_CAMERA_TAGS = (
    "Make", "Model", "SerialNumber", "OwnerName", "Artist", "Copyright", "ImageDescription",
    "DateTimeOriginal", "CreateDate", "SubSecTimeOriginal", "SubSecTimeDigitized",
    "OffsetTimeOriginal", "OffsetTimeDigitized",
    "ExposureTime", "FNumber", "ISO", "ExposureProgram", "ExposureCompensation", "MeteringMode",
    "Flash", "FocalLength", "FocalLengthIn35mmFormat", "MaxApertureValue",
    "LensMake", "LensModel", "LensSerialNumber", "LensInfo",
)
#: exiftool's warnings when a value of the copy by name has no EXIF form (Canon's MeteringMode
#: "Evaluative", an XMP Flash structure, an empty date): that tag is left out, as meant.
_UNMAPPED = ("Can't convert ", "Can't write a structure to ", "Invalid date/time")
#: Deleted after the copy: images inside copied maker-note blocks (not excludable).
_DELETE_AFTER = ("PreviewImage", "ThumbnailImage", "JpgFromRaw", "OtherImage")

#: Fields carried into OpenEXR outputs: (exiftool tag, OpenImageIO attribute, type).
EXR_TAGS: tuple[tuple[str, str, str], ...] = (
    ("Make", "Make", "str"),
    ("Model", "Model", "str"),
    ("SerialNumber", "Exif:BodySerialNumber", "str"),
    ("LensMake", "Exif:LensMake", "str"),
    ("LensModel", "Exif:LensModel", "str"),
    ("LensSerialNumber", "Exif:LensSerialNumber", "str"),
    ("LensInfo", "Exif:LensSpecification", "float4"),
    ("FocalLength", "Exif:FocalLength", "float"),
    ("FocalLengthIn35mmFormat", "Exif:FocalLengthIn35mmFilm", "int"),
    ("FNumber", "FNumber", "float"),
    ("ExposureTime", "ExposureTime", "float"),
    ("ISO", "Exif:PhotographicSensitivity", "int"),
    ("ExposureCompensation", "Exif:ExposureBiasValue", "float"),
    ("DateTimeOriginal", "Exif:DateTimeOriginal", "str"),
    ("CreateDate", "Exif:DateTimeDigitized", "str"),
    ("OffsetTimeOriginal", "Exif:OffsetTimeOriginal", "str"),
    ("Orientation", "Orientation", "int"),
    ("Artist", "Artist", "str"),
    ("Copyright", "Copyright", "str"),
)

_EXR_MAGIC = b"v/1\x01"
# exiftool's FilenameSPrintf tokens: a -tagsFromFile name containing one is a pattern
_EXIFTOOL_FMT = re.compile(r"%[-+]?\d*[.:]?\d*[lu]?[dDfFeEtgso]")
_TIMEOUT = 300.0


# --------------------------------------------------------------------------- #
# exiftool plumbing
# --------------------------------------------------------------------------- #


def exiftool_path() -> str:
    """Path of the exiftool program (``$VIGPROC_EXIFTOOL``, else ``exiftool`` on PATH).

    Raises
    ------
    ImageWriteError
        exiftool is not installed.
    """
    env = os.environ.get("VIGPROC_EXIFTOOL")
    found = shutil.which(env) if env else shutil.which("exiftool")
    if not found:
        raise OutputSettingsError(
            f"exiftool program not found ({env!r})" if env else
            "exiftool program not found: install it (Debian/Ubuntu: libimage-exiftool-perl)"
        )
    return found


def _q(path: str) -> str:
    return repr(path)  # one line even for names with newlines


def _trim(name: str, nbytes: int = 60) -> str:
    """At most ``nbytes`` UTF-8 bytes of ``name`` (for temp names within NAME_MAX).

    Bytes that are not UTF-8 (surrogate-escaped names) are dropped, so the
    temporary name is always valid UTF-8 for OpenImageIO.
    """
    return name.encode("utf-8", "surrogateescape")[:nbytes].decode("utf-8", "ignore")


def _one_line(text: str) -> str:
    return " / ".join(s.strip() for s in text.splitlines() if s.strip())


def _process() -> ExiftoolProcess:
    """The persistent exiftool that copies metadata in this process (one per program path).

    Raises
    ------
    ImageWriteError
        exiftool is not installed.
    """
    return shared_process(exiftool_path(), timeout=_TIMEOUT)


def spawn_exiftool() -> None:
    """Launch this process's metadata-writing exiftool now, without waiting for it
    (a no-op when it runs).

    Its start (a Perl interpreter loading ExifTool's modules) is otherwise paid, waiting,
    by the first output that copies metadata; a caller that knows it will write can
    launch it earlier, to start beside other work
    (:meth:`vigproc.pipeline.processor.Processor.prepare`).

    Raises
    ------
    OutputSettingsError
        exiftool is not installed or cannot be launched.
    """
    try:
        _process().spawn()
    except VigprocError as exc:
        raise OutputSettingsError(f"cannot start exiftool: {exc}") from None


class _Exiftool:
    """One call's use of the persistent exiftool: safe names for the argument protocol
    (aliases in a private folder, made on demand), warnings said once per file."""

    def __enter__(self) -> _Exiftool:
        self.proc = _process()
        self._dir: str | None = None
        self.aliases: dict[str, str] = {}  # alias -> the caller's path, for messages
        self._said: set[tuple[str, str]] = set()
        return self

    def __exit__(self, *exc: object) -> None:
        if self._dir is not None:
            shutil.rmtree(self._dir, ignore_errors=True)

    @property
    def dir(self) -> str:
        if self._dir is None:  # removed by __exit__, or after a kill by the next process's sweep
            self._dir = scratch_folder("exiftool")
        return self._dir

    def run(self, args: list[str], what: str, *, check: bool = True, name: str = "",
            before_retry: Any = None) -> ExiftoolResult:
        """Run one exiftool command; log its warnings (about ``name``); raise ImageWriteError(``what``...) on failure.

        With ``check=False`` a non-zero exit status is left to the caller.  A process that
        died or hung is restarted and the command run once more (``before_retry`` first);
        a second failure raises with ``transient`` set (a later retry may succeed).
        """
        try:
            res = self.proc.execute(args, before_retry=before_retry)
        except ExiftoolDied as exc:
            err = ImageWriteError(f"{what}: exiftool {exc}")
            err.transient = True
            raise err from None
        except VigprocError as exc:  # cannot start it: the set-up's fault
            raise OutputSettingsError(f"{what}: {exc}") from None
        err = res.stderr.decode("utf-8", "replace")
        errors = [ln for ln in err.splitlines() if ln.strip() and not ln.startswith("Warning:")]
        paths = [a for a in args if os.path.sep in a]
        for ln in err.splitlines():
            if not ln.startswith("Warning:"):
                continue
            # exiftool names the file it warns about ("... - /tmp/.x.tmp-1234.tif"): our
            # temporary names mean nothing to a user, who already sees ``name``
            text = ln
            for a in paths:
                text = text.replace(f" - {a}", "").replace(f" in {a}", "")
            if (name, text) in self._said:  # once per file, not once per exiftool call
                continue
            self._said.add((name, text))
            if "[minor]" in ln:  # harmless, said once when the source's EXIF was read
                logger.debug("%s: exiftool: %s", name, text)
            elif any(w in ln for w in _UNMAPPED):  # a value EXIF has no place for: not copied, as meant
                logger.debug("%s: exiftool: %s", name, text)
            elif "No writable tags set from" in ln:  # the source just has no metadata
                logger.info("%s: exiftool: %s", name, text)
            else:
                logger.warning("%s: exiftool: %s", name, text)
        if check and (res.status != 0 or any(ln.startswith("Error") for ln in errors)):
            msg = _one_line("\n".join(errors) or err) or f"exit status {res.status}"
            for alias, real in self.aliases.items():
                msg = msg.replace(alias, real)
            raise ImageWriteError(f"{what}: exiftool failed: {msg}")
        return res

    def _alias(self, path: str, stem: str) -> str:
        ext = re.sub(r"[^A-Za-z0-9.]", "", os.path.splitext(path)[1])[:10]
        alias = os.path.join(self.dir, stem + ext)
        self.aliases[alias] = path
        return alias

    def source_name(self, src: str) -> str:
        """A name for ``-tagsFromFile`` that exiftool takes literally and the protocol carries."""
        if line_safe(src) and not _EXIFTOOL_FMT.search(src):
            return src
        for alias, real in self.aliases.items():
            if real == src and os.path.basename(alias).startswith("source"):
                return alias  # made by an earlier command of this call
        alias = self._alias(src, "source")
        try:
            os.symlink(src, alias)
        except OSError:  # no symlinks here: a private copy (the source stays untouched)
            shutil.copyfile(src, alias)
        return alias

    def target_name(self, dst: str) -> str:
        """A name for the file exiftool rewrites: ``dst`` itself, or a private copy of it
        when the protocol cannot carry its name (see :meth:`put_back`)."""
        if line_safe(dst):
            return dst
        alias = self._alias(dst, "target")
        shutil.copyfile(dst, alias)
        return alias

    def put_back(self, target: str, dst: str) -> None:
        """Replace ``dst`` by the rewritten private copy ``target``, atomically."""
        if target == dst:
            return
        with replacing(dst, prefix=f".{_trim(os.path.basename(dst))}.meta-") as tmp:
            shutil.copyfile(target, tmp)


def _parse_json(stdout: bytes) -> dict[str, Any]:
    """The first object of exiftool's ``-j`` output, numbers kept as their text.

    exiftool prints number-like strings unquoted, so ``"1.10"`` would come back
    as ``1.1``; parsing numbers as ``str`` keeps them exact.
    """
    try:
        data = json.loads(stdout.decode("utf-8", "replace"), parse_float=str, parse_int=str)
        first = data[0]
    except (ValueError, IndexError, TypeError, KeyError):
        raise ValueError("not exiftool JSON") from None
    if not isinstance(first, dict):
        raise ValueError("not exiftool JSON")
    return first


def _read_tags(et: _Exiftool, src: str, what: str) -> dict[str, Any]:
    """Check that ``src`` is an image exiftool can read; return its :data:`EXR_TAGS` fields.

    Values are exiftool's numeric (``-n``) ones, keyed by exiftool tag name.  For
    an OpenEXR source they come from its OpenImageIO attributes instead.
    """
    tags = ["-FileType", "-MIMEType", "-Error", "-Warning"] + [f"-{t}" for t, _, _ in EXR_TAGS]
    # exit status 1 with JSON output: the file's problem is in its "Error" field
    res = et.run(["-j", "-n", "-G0", *tags, et.source_name(src)], what, check=False, name=src)
    try:
        info = _parse_json(res.stdout)
    except ValueError:
        msg = _one_line(res.stderr.decode("utf-8", "replace")) or f"exit status {res.status}"
        raise OutputRefusedError(f"{what}: exiftool cannot read the source {_q(src)}: {msg}") from None
    if info.get("ExifTool:Error"):
        raise OutputRefusedError(f"{what}: source {_q(src)}: {info['ExifTool:Error']}")
    warning = info.get("ExifTool:Warning")
    if warning:  # e.g. "JPEG format error": metadata may still copy
        # "[minor]" ones (a maker-note offset exiftool fixes) were already said, once, when
        # the file's EXIF was read (vigproc.io.exif)
        (logger.debug if "[minor]" in str(warning) else logger.warning)("%s: exiftool: %s", src, warning)
    mime = str(info.get("File:MIMEType", ""))
    if not mime.startswith("image/"):
        kind = info.get("File:FileType", "unknown")
        raise OutputRefusedError(f"{what}: source {_q(src)} is not an image (exiftool: file type {kind})")
    out: dict[str, Any] = {}
    if _is_exr(src):
        try:
            attrs = _exr_attributes(src)
        except ImageReadError as exc:
            raise OutputRefusedError(f"{what}: {exc}") from None
        for et_name, oiio_name, kind in EXR_TAGS:
            if oiio_name in attrs:
                v = attrs[oiio_name]
                out[et_name] = " ".join(f"{x:g}" for x in v) if kind == "float4" else v
        return out
    for key, val in info.items():
        group, _, name = key.partition(":")
        if group in ("File", "ExifTool") or not name:
            continue
        if name not in out or group == "EXIF":  # EXIF wins over maker notes / XMP copies
            out[name] = val
    return out


# --------------------------------------------------------------------------- #
# the record
# --------------------------------------------------------------------------- #


def make_record(
    model: VignettingModel,
    *,
    applied: bool | None = None,
    strength: float = 1.0,
    method: str | None = None,
) -> dict[str, Any]:
    """Build the correction record for :func:`copy_metadata` / :func:`write_corrected`.

    Parameters
    ----------
    model : VignettingModel
        The model that was (or would have been) divided out.
    applied : bool, optional
        Whether the pixels were corrected; default: the model is not the
        identity and ``strength > 0``.
    strength : float
        Strength passed to :func:`vigproc.correct`.
    method : str, optional
        Estimator name; default ``model.method``.

    Returns
    -------
    dict
        Keys ``model``, ``method``, ``version``, ``applied``, ``strength``.
    """
    if applied is None:
        applied = (not model.is_identity) and strength > 0
    return {
        "model": model,
        "method": method or model.method,
        "version": __version__,
        "applied": bool(applied),
        "strength": float(strength),
    }


def _normalise_record(record: Mapping[str, Any]) -> dict[str, Any]:
    """Record -> {tag name: value} with the model as JSON text."""
    unknown = set(record) - set(_RECORD_FIELDS)
    if unknown:
        raise ValueError(f"unknown record keys {sorted(unknown)}; allowed: {sorted(_RECORD_FIELDS)}")
    out: dict[str, Any] = {}
    for key, value in record.items():
        if value is None:
            continue
        tag, kind = _RECORD_FIELDS[key]
        if key == "model":
            if isinstance(value, VignettingModel):
                value = value.to_json()
            elif isinstance(value, Mapping):
                value = json.dumps(dict(value))
            elif not isinstance(value, str):
                raise ValueError(f"record 'model' must be a VignettingModel, dict or JSON text, got {type(value).__name__}")
        elif kind == "bool":
            value = bool(value)
        elif kind == "float":
            value = float(value)
            if not math.isfinite(value):
                raise ValueError(f"record {key!r} must be finite, got {value}")
        else:
            value = str(value)
        out[tag] = value
    if "Method" not in out and isinstance(record.get("model"), VignettingModel):
        out["Method"] = record["model"].method
    return out


def _record_from_tags(tags: Mapping[str, Any], path: str) -> dict[str, Any] | None:
    by_tag = {tag: key for key, (tag, _) in _RECORD_FIELDS.items()}
    rec: dict[str, Any] = {}
    for tag, value in tags.items():
        key = by_tag.get(tag)
        if key is None:
            continue
        kind = _RECORD_FIELDS[key][1]
        if kind == "bool":
            value = value if isinstance(value, bool) else str(value).strip().lower() in ("1", "true", "yes")
        elif kind == "float":
            value = float(value)
        else:
            value = str(value)
        rec[key] = value
    if not rec:
        return None
    if "model" in rec:
        text = rec["model"]
        rec["model_json"] = text
        try:
            rec["model"] = VignettingModel.from_json(text)
        except ModelError as exc:
            raise ImageReadError(f"cannot read the vigproc record of {_q(path)}: {exc}") from None
    return rec


# --------------------------------------------------------------------------- #
# public API
# --------------------------------------------------------------------------- #


def _fspath(path: Any) -> str:
    p = os.fspath(path)
    return os.path.abspath(os.fsdecode(p) if isinstance(p, bytes) else p)


def _linear_tiff(path: str) -> str | None:
    """``"linear"`` if ``path`` is a TIFF :func:`vigproc.io.images.write_image` marked linear, else None."""
    inp = oiio.ImageInput.open(path)
    if inp is None:
        oiio.geterror()
        return None
    try:
        return "linear" if inp.format_name() == "tiff" and recorded_transfer(inp.spec()) == "linear" else None
    finally:
        inp.close()


def _is_exr(path: str) -> bool:
    try:
        with open(path, "rb") as fh:
            return fh.read(4) == _EXR_MAGIC
    except OSError:
        return False


#: The source's description of its colours, kept by ``keep_colour`` (see copy_metadata).
_COLOUR_TAGS = ("ColorSpace", "InteropIFD:all", "ICC_Profile:all")


def copy_metadata(src: Any, dst: Any, record: Mapping[str, Any] | None = None, *,
                  keep_colour: bool = False, shown_as: Any = None, source_read: bool = False) -> None:
    """Copy ``src``'s metadata into the image ``dst`` and add the vigproc record.

    ``dst`` is modified in place (exiftool rewrites it to a temporary file and
    renames it over ``dst``; for OpenEXR OpenImageIO does the same); ``src`` is
    only read.  What is copied per format: see the module docstring.

    Parameters
    ----------
    src : str or os.PathLike
        The original image (JPEG, TIFF, PNG, camera RAW, OpenEXR...).
    dst : str or os.PathLike
        The corrected TIFF, PNG or OpenEXR written by vigproc.
    record : dict, optional
        Correction record (see :func:`make_record`): keys ``model``
        (VignettingModel, dict or JSON text), ``method``, ``version``,
        ``applied``, ``strength``; ``None`` copies metadata only.
    keep_colour : bool
        Keep the source's colour description (EXIF ``ColorSpace``, the interoperability
        index, the ICC profile) instead of the one :func:`vigproc.io.images.write_image` wrote.
        For a display-encoded output of a display-encoded source: vigproc divides a
        gain out and never converts primaries, so an Adobe RGB or Display P3 JPEG is still
        one (tagged sRGB, its colours would be shown wrong).
    shown_as : str or os.PathLike, optional
        The name exiftool's warnings are logged under (default ``dst``):
        :func:`write_corrected` gives the output's name, not its temporary's.
    source_read : bool
        The caller has already decoded ``src`` and read its EXIF (the pipeline): the
        check that it is an image exiftool can read is skipped, one exiftool round trip
        fewer per output (an OpenEXR source or output still reads its fields).

    Raises
    ------
    ImageWriteError
        exiftool is missing or failed (message names the file and quotes
        exiftool), the source is not an image, or ``src`` and ``dst`` are the
        same file.
    ValueError
        Unknown record keys.
    """
    s, d = _fspath(src), _fspath(dst)
    what = f"cannot copy metadata into {_q(d)}"
    tags = _normalise_record(record) if record is not None else {}
    for p, role in ((s, "source"), (d, "destination")):
        if not os.path.isfile(p):
            raise OutputRefusedError(f"{what}: {role} {_q(p)} does not exist or is not a file")
    if os.path.samefile(s, d):
        raise OutputSettingsError(f"{what}: source and destination are the same file")
    linear = _linear_tiff(d)  # before the copy replaces the marker with the source's caption
    with _Exiftool() as et:
        exr = _is_exr(s) or _is_exr(d)
        src_tags = _read_tags(et, s, what) if exr or not source_read else {}
        if _is_exr(d):
            _exr_write_metadata(d, src_tags, tags, what)
            return
        # what write_image set and only the source may say: deleted first, then copied if it has them
        args = ["-IFD0:ImageDescription=", "-XMP-xmp:CreateDate="]
        # EXIF's camera tags by name, for RAW formats that keep them elsewhere (a CRW's
        # CanonRaw, an X3F's header); -all:all, later, wins for those already in EXIF
        args += ["-tagsFromFile", et.source_name(s), *(f"-EXIF:{t}<{t}" for t in _CAMERA_TAGS), "-all:all"]
        args += [f"--{t}" for t in _EXCLUDE if not (keep_colour and t in _COLOUR_TAGS)]
        if keep_colour:  # -all:all copies neither the ICC profile nor the interop index: name them
            args += ["-ICC_Profile", "-InteropIndex", "-InteropVersion"]
        if _is_exr(s):
            # an EXR holds no EXIF exiftool can copy: assign the key fields read above
            # (on one line each: the argument protocol is line-based)
            args += [f"-{k}=" + " ".join(str(v).splitlines()) for k, v in src_tags.items()]
        args += [f"-{t}=" for t in _DELETE_AFTER]
        if linear:
            args.append(f"-XMP-vigproc:Transfer={linear}")
        for tag, value in tags.items():
            if isinstance(value, bool):
                value = "True" if value else "False"
            # one line: the argument protocol is line-based (a plugin's method name is free text)
            args.append(f"-XMP-vigproc:{tag}=" + " ".join(str(value).splitlines()))
        target = et.target_name(d)
        # a half-written target of a killed exiftool would make the retry fail
        leftover = target + "_exiftool_tmp"
        args += ["-overwrite_original", target]
        et.run(args, what, name=_fspath(shown_as) if shown_as is not None else d, before_retry=lambda: os.path.exists(leftover) and os.unlink(leftover))
        et.put_back(target, d)
    logger.debug("copied metadata %s -> %s (record: %s)", s, d, sorted(tags))


def _exr_attributes(path: str) -> dict[str, Any]:
    inp = oiio.ImageInput.open(path)
    if inp is None:
        raise ImageReadError(f"cannot read {_q(path)}: {_one_line(oiio.geterror())}")
    try:
        return {a.name: a.value for a in inp.spec().extra_attribs}
    finally:
        inp.close()


def _exr_write_metadata(path: str, src_tags: Mapping[str, Any], record: Mapping[str, Any], what: str) -> None:
    """Rewrite the EXR ``path`` with the key source fields and the record as attributes."""
    oiio.geterror()
    inp = oiio.ImageInput.open(path)
    if inp is None:
        raise ImageWriteError(f"{what}: cannot reopen it: {_one_line(oiio.geterror())}")
    try:
        spec = inp.spec()
        pixels = inp.read_image(0, 0, 0, spec.nchannels, spec.format)
        err = inp.geterror()
    finally:
        inp.close()
    if pixels is None:
        raise ImageWriteError(f"{what}: cannot reread its pixels: {_one_line(err)}")
    for et_name, name, kind in EXR_TAGS:
        value = src_tags.get(et_name)
        if value is None or value == "":
            continue
        try:
            if kind == "str":
                spec.attribute(name, str(value))
            elif kind == "int":
                spec.attribute(name, int(float(value)))
            elif kind == "float":
                spec.attribute(name, float(value))
            else:  # "float4": exiftool -n gives "min max fmin fmax"
                vals = tuple(float(x) for x in str(value).split())
                if len(vals) == 4:
                    spec.attribute(name, oiio.TypeDesc("float[4]"), vals)
        except (TypeError, ValueError):
            logger.warning("%s: source %s=%r is not a valid %s; not copied", path, et_name, value, kind)
    if src_tags.get("DateTimeOriginal"):
        # OpenEXR's standard capDate ("when the image was captured") is OIIO's DateTime
        spec.attribute("DateTime", str(src_tags["DateTimeOriginal"]))
    for tag, value in record.items():
        name = f"vigproc:{tag}"
        if isinstance(value, bool):
            spec.attribute(name, int(value))
        elif isinstance(value, float):
            spec.attribute(name, value)
        else:
            spec.attribute(name, str(value))
    try:
        with replacing(path, prefix=f".{_trim(os.path.basename(path))}.meta-", suffix=".exr") as tmp:
            out = oiio.ImageOutput.create(tmp)
            if out is None:
                raise ImageWriteError(f"{what}: {_one_line(oiio.geterror())}")
            ok = bool(out.open(tmp, spec)) and bool(out.write_image(pixels))
            ok = bool(out.close()) and ok
            if not ok:
                raise ImageWriteError(f"{what}: {_one_line(out.geterror() or oiio.geterror())}")
    except ImageWriteError:
        raise
    except OSError as exc:
        raise write_error(f"{what}: {exc.strerror or exc}", exc) from None


def read_record(path: Any) -> dict[str, Any] | None:
    """Read back the vigproc correction record of an output file.

    Parameters
    ----------
    path : str or os.PathLike
        A TIFF/PNG (XMP) or OpenEXR (attributes) written by :func:`write_corrected`.

    Returns
    -------
    dict or None
        ``None`` if the file has no record; else the keys present among
        ``model`` (:class:`VignettingModel`), ``model_json`` (the stored text),
        ``method``, ``version``, ``applied`` (bool), ``strength`` (float).

    Raises
    ------
    ImageReadError
        The file cannot be read, or the stored model is invalid.
    """
    p = _fspath(path)
    if not os.path.isfile(p):
        raise ImageReadError(f"cannot read {_q(p)}: file not found")
    if _is_exr(p):
        attrs = _exr_attributes(p)
        tags = {k[len("vigproc:"):]: v for k, v in attrs.items() if k.startswith("vigproc:")}
        return _record_from_tags(tags, p)
    try:
        with _Exiftool() as et:
            res = et.run(["-j", "-n", "-XMP-vigproc:all", et.source_name(p)], f"cannot read {_q(p)}", name=p)
    except ImageWriteError as exc:  # same failure, reading side
        raise ImageReadError(str(exc)) from None
    try:
        info = _parse_json(res.stdout)
    except ValueError:
        raise ImageReadError(f"cannot read {_q(p)}: cannot parse exiftool's output") from None
    info.pop("SourceFile", None)
    return _record_from_tags(info, p)


def _resolve_format(path: str, format: str | None) -> str:
    if format is None:
        fmt = _EXT_FORMAT.get(os.path.splitext(path)[1].lower())
        if fmt is None:
            raise OutputSettingsError(
                f"cannot write {_q(path)}: unknown extension (use .tif, .png, .exr or .jpg, or pass format=)"
            )
        return fmt
    fmt = _FORMAT_ALIASES.get(str(format).lower())
    if fmt is None:
        raise OutputSettingsError(f"cannot write {_q(path)}: unsupported format {format!r} (tiff, png, openexr, jpeg)")
    return fmt


def write_corrected(
    dst: Any,
    img: np.ndarray,
    src: Any,
    record: Mapping[str, Any] | None,
    *,
    bit_depth: str | None = None,
    format: str | None = None,
    transfer: str = "linear",
    quality: int | None = None,
    keep_colour: bool = False,
    source_read: bool = False,
) -> None:
    """Write a corrected image with the source's metadata and the record, atomically.

    Pixels are written with :func:`vigproc.io.images.write_image` to a temporary file in
    ``dst``'s folder, the metadata is added to that file (:func:`copy_metadata`),
    and only then is it renamed onto ``dst``.  On any failure the temporary
    files are removed and an existing ``dst`` is left as it was.

    Parameters
    ----------
    dst : str or os.PathLike
        Output path (``.tif``/``.tiff``, ``.png``, ``.exr`` or pass ``format``).
    img : numpy.ndarray
        Linear ``HxW`` or ``HxWx3`` image (see :func:`vigproc.io.images.write_image`).
    src : str or os.PathLike
        The source image whose metadata is copied; never modified.
    record : dict or None
        Correction record (:func:`make_record`); ``None`` for metadata only.
    bit_depth, format, transfer, quality
        As for :func:`vigproc.io.images.write_image`.
    keep_colour, source_read : bool
        As for :func:`copy_metadata`.

    Raises
    ------
    ImageWriteError
        Pixel or metadata writing failed.
    InvalidImageError
        ``img`` cannot be written.
    """
    d = _fspath(dst)
    fmt = _resolve_format(d, format)
    if record is not None:
        _normalise_record(record)  # a bad record fails before any pixel is written
    # a short prefix: io.write_image nests its own temporary inside this one
    name = os.path.basename(d)
    try:
        with replacing(d, what=f"cannot write {_q(d)}", prefix=f".{_trim(name)}.tmp-", suffix=_FORMAT_EXT[fmt],
                       leftovers=("_exiftool_tmp",)) as tmp:  # the latter: exiftool's own, if it was killed
            try:
                write_image(tmp, img, format=fmt, bit_depth=bit_depth, transfer=transfer, quality=quality)
                copy_metadata(src, tmp, record, keep_colour=keep_colour, shown_as=d, source_read=source_read)
            except (ImageWriteError, InvalidImageError) as exc:  # name the user's file, not our temp
                err = type(exc)(str(exc).replace(_q(tmp), _q(d)).replace(tmp, d))
                err.__dict__.update(exc.__dict__)  # e.g. ``transient``
                err.errno = getattr(exc, "errno", None)
                raise err from None
    except ImageWriteError:
        raise
    except OSError as exc:
        raise write_error(f"cannot write {_q(d)}: {exc.strerror or exc}", exc) from None
    logger.debug("wrote %s with metadata from %s", d, src)
