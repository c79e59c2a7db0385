"""What an examiner files beside a forensic verdict: the file's content hash, its capture
date, the camera and lens its metadata names, and where that metadata contradicts itself.

:func:`read_provenance` reads them through the check's one ExifTool process
(:meth:`vigproc.io.exif.ExifReader.read_tags`: EXIF, XMP, maker notes; answered from the
file's one metadata read when given its :class:`vigproc.io.exif.FileTags`) and compares what EXIF and XMP say of the capture date, the lens and the serial
numbers: an editor that rewrote one and not the other leaves them disagreeing, which is
evidence too (:attr:`Provenance.conflicts`). The contradictions the lens reading itself
found (:attr:`vigproc.io.exif.LensKey.problems`: a focal length or a camera model that two
sources give differently, an ambiguous lens) are carried as they are
(:attr:`Provenance.problems`), so that they reach the verdict's record instead of stderr only.

Every string comes from the file: it is kept as text, never interpreted (the report
escapes it).
"""

from __future__ import annotations

import hashlib
import logging
import os
import re
from dataclasses import dataclass
from typing import Any, Mapping, Sequence

from vigproc.errors import ImageReadError, VigprocError

log = logging.getLogger(__name__)

__all__ = ["Provenance", "file_sha256", "read_provenance"]

#: Tags read per group: one ExifTool command each (a tag name may appear once per command).
_EXIF_TAGS = ("EXIF:DateTimeOriginal", "EXIF:OffsetTimeOriginal", "EXIF:Make", "EXIF:Model", "EXIF:SerialNumber",
              "EXIF:LensModel", "EXIF:LensSerialNumber")
_XMP_TAGS = ("XMP:DateTimeOriginal", "XMP:SerialNumber", "XMP:LensModel", "XMP:Lens", "XMP:LensSerialNumber")
_MAKERNOTE_TAGS = ("MakerNotes:SerialNumber", "MakerNotes:InternalSerialNumber")
#: Longest text kept from a tag (hostile metadata can be long).
_MAX_TEXT = 200
_DATE = re.compile(r"^\s*(\d{4})[:-](\d{2})[:-](\d{2})[ T](\d{2}):(\d{2})(?::(\d{2}))?(?:\.\d+)?\s*"
                   r"(Z|[+-]\d{2}:?\d{2})?\s*$")


def file_sha256(path: str | os.PathLike[str]) -> str:
    """Hex SHA-256 of a file's content, streamed (a frame's content id).

    Raises
    ------
    ImageReadError
        The file cannot be read.
    """
    h = hashlib.sha256()
    try:
        with open(path, "rb") as f:
            while chunk := f.read(1 << 20):
                h.update(chunk)
    except OSError as exc:
        raise ImageReadError(f"cannot read {os.fspath(path)!r}: {exc.strerror or exc}") from None
    return h.hexdigest()


@dataclass(frozen=True)
class Provenance:
    """One checked file as its metadata states it.

    Attributes
    ----------
    sha256 : str
        Hex SHA-256 of the file's bytes.
    size_bytes : int
    captured : str or None
        DateTimeOriginal as written (EXIF, else XMP), e.g. ``2019:06:01 14:03:22``.
    captured_offset : str or None
        Its time zone offset (EXIF OffsetTimeOriginal, else the XMP date's own), e.g.
        ``+02:00``; None when the file does not say.
    make, model, serial : str or None
        The camera as written (EXIF; the serial also from XMP or the maker notes).
    lens : str or None
        The lens name as written (EXIF LensModel, else XMP); the normalised id the check
        used is the verdict's ``lens_id``.
    lens_serial : str or None
    conflicts : tuple of str
        Where EXIF and XMP (or the maker notes) disagree: capture date, lens, serials.
    problems : tuple of str
        What the lens reading found (contradictory or rejected values, an ambiguous lens).
    unread : str or None
        Why the metadata could not be read (the hash is still given).
    """

    sha256: str
    size_bytes: int
    captured: str | None = None
    captured_offset: str | None = None
    make: str | None = None
    model: str | None = None
    serial: str | None = None
    lens: str | None = None
    lens_serial: str | None = None
    conflicts: tuple[str, ...] = ()
    problems: tuple[str, ...] = ()
    unread: str | None = None

    def to_dict(self) -> dict[str, Any]:
        """JSON-able (lists for the tuples)."""
        return {k: (list(v) if isinstance(v, tuple) else v) for k, v in self.__dict__.items()}


def _text(v: Any) -> str | None:
    """A tag's value as one line of text (lists joined), or None when empty."""
    if v is None:
        return None
    if isinstance(v, list):
        v = ", ".join(str(x) for x in v)
    s = " ".join(str(v).split())[:_MAX_TEXT]
    return s or None


def _squash(s: str) -> str:
    return re.sub(r"[^0-9a-z]+", "", s.casefold())


def _date_parts(s: str | None) -> tuple[tuple[str, ...], str | None] | None:
    """(Y, M, D, h, m, s) and the offset of an EXIF or XMP date, or None when unparsable."""
    if s is None:
        return None
    m = _DATE.match(s)
    if m is None:
        return None
    off = m.group(7)
    if off is not None and off != "Z" and ":" not in off:
        off = off[:3] + ":" + off[3:]
    return tuple(g or "00" for g in m.groups()[:6]), off


def _same_text(a: str, b: str) -> bool:
    """Two names of one thing agree when one, squashed, starts the other (XMP often
    writes the lens with or without its maker)."""
    x, y = _squash(a), _squash(b)
    return not x or not y or x.startswith(y) or y.startswith(x) or x.endswith(y) or y.endswith(x)


def _conflicts(exif: Mapping[str, Any], xmp: Mapping[str, Any], notes: Mapping[str, Any]) -> list[str]:
    out: list[str] = []
    d1, d2 = _text(exif.get("EXIF:DateTimeOriginal")), _text(xmp.get("XMP:DateTimeOriginal"))
    p1, p2 = _date_parts(d1), _date_parts(d2)
    if p1 is not None and p2 is not None:
        off1 = _text(exif.get("EXIF:OffsetTimeOriginal")) or p1[1]
        if p1[0] != p2[0] or (off1 and p2[1] and off1 != p2[1]):
            out.append(f"capture date: EXIF:DateTimeOriginal={d1!r}{f' {off1}' if off1 else ''} but "
                       f"XMP:DateTimeOriginal={d2!r}")
    lens = _text(exif.get("EXIF:LensModel"))
    for tag in ("XMP:LensModel", "XMP:Lens"):
        other = _text(xmp.get(tag))
        if lens and other and not _same_text(lens, other):
            out.append(f"lens: EXIF:LensModel={lens!r} but {tag}={other!r}")
    serials = [(t, _text(m.get(t))) for m, t in ((exif, "EXIF:SerialNumber"), (xmp, "XMP:SerialNumber"),
                                                   (notes, "MakerNotes:SerialNumber"))]
    serials = [(t, v) for t, v in serials if v and _squash(v).strip("0")]
    for t, v in serials[1:]:
        if _squash(v) != _squash(serials[0][1]):
            out.append(f"camera serial: {serials[0][0]}={serials[0][1]!r} but {t}={v!r}")
    ls1, ls2 = _text(exif.get("EXIF:LensSerialNumber")), _text(xmp.get("XMP:LensSerialNumber"))
    if ls1 and ls2 and _squash(ls1) != _squash(ls2):
        out.append(f"lens serial: EXIF:LensSerialNumber={ls1!r} but XMP:LensSerialNumber={ls2!r}")
    return out


def read_provenance(path: str | os.PathLike[str], reader=None, problems: Sequence[str] = (), *,
                    sha256: str | None = None) -> Provenance:
    """The provenance of one file.

    Parameters
    ----------
    path : path-like
    reader : ExifReader, optional
        The run's reader (its one ExifTool process); None: the metadata is not read.
    problems : sequence of str
        What reading the lens found (:attr:`vigproc.io.exif.LensKey.problems`): carried.
    sha256 : str, optional
        The file's hash when the caller has it already.

    Returns
    -------
    Provenance

    Raises
    ------
    ImageReadError
        The file cannot be read (its hash cannot be taken). Unreadable metadata is not
        an error: :attr:`Provenance.unread` says why.
    """
    digest = sha256 or file_sha256(path)
    try:
        size = os.stat(path).st_size
    except OSError as exc:
        raise ImageReadError(f"cannot read {os.fspath(path)!r}: {exc.strerror or exc}") from None
    problems = tuple(str(p) for p in problems)
    if reader is None or not hasattr(reader, "read_tags"):
        return Provenance(digest, size, problems=problems, unread="metadata not read")
    try:
        exif = reader.read_tags(path, _EXIF_TAGS)
        xmp = reader.read_tags(path, _XMP_TAGS)
        notes = reader.read_tags(path, _MAKERNOTE_TAGS)
    except VigprocError as exc:
        log.info("%r: metadata for the report not read: %s", os.fspath(path), exc)
        return Provenance(digest, size, problems=problems, unread=str(exc))
    when = _text(exif.get("EXIF:DateTimeOriginal")) or _text(xmp.get("XMP:DateTimeOriginal"))
    parts = _date_parts(when)
    offset = _text(exif.get("EXIF:OffsetTimeOriginal")) or (parts[1] if parts is not None else None)
    serial = next((v for v in (_text(exif.get("EXIF:SerialNumber")), _text(notes.get("MakerNotes:SerialNumber")),
                               _text(xmp.get("XMP:SerialNumber")), _text(notes.get("MakerNotes:InternalSerialNumber")))
                   if v), None)
    lens = _text(exif.get("EXIF:LensModel")) or _text(xmp.get("XMP:LensModel")) or _text(xmp.get("XMP:Lens"))
    return Provenance(
        digest, size, captured=when, captured_offset=offset, make=_text(exif.get("EXIF:Make")),
        model=_text(exif.get("EXIF:Model")), serial=serial, lens=lens,
        lens_serial=_text(exif.get("EXIF:LensSerialNumber")) or _text(xmp.get("XMP:LensSerialNumber")),
        conflicts=tuple(_conflicts(exif, xmp, notes)), problems=problems)
