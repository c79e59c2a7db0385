"""EXIF lens identity for vignetting profiles.

A vignetting profile belongs to a camera body + lens and varies with focal
length, aperture and (a little) focus distance.  This module turns a photograph's
metadata into a normalised, deterministic :class:`LensKey` holding exactly those
fields, read with ExifTool.

Reading
-------
:class:`ExifReader` wraps **one** persistent ``exiftool -stay_open`` process
(:class:`vigproc.io.exiftool_process.ExiftoolProcess`, over PyExifTool): a file costs a few
milliseconds through the open process against the start-up of a process per file
(``docs/benchmarks/io.md``, ``vigproc bench io``, benchmarks/io.py), so a batch
is read with one process and, per chunk of files, one ExifTool command.
:meth:`ExifReader.read_many` never raises for a bad file: each result is a
:class:`LensKey` or a typed :class:`~vigproc.errors.VigprocError` naming the file
and the cause, so one bad file cannot stop a batch.  :func:`read_lens_key` is the
one-shot convenience (own process, opened and closed per call).

File names
----------
PyExifTool sends arguments to the process one per line (ExifTool's ``-@`` argfile
protocol).  What was found with ExifTool 12.57:

* spaces, quotes, ``$``, ``@``, ``#``, ``*``, ``?``, ``%``, ``=``, tabs, backslashes
  and non-ASCII (UTF-8) names pass through unchanged;
* a **newline** splits the name into two arguments: ``a\\nb.jpg`` is read as the two
  files ``a`` and ``b.jpg`` (a misread if those exist); a trailing carriage
  return is stripped; leading white space is stripped and a leading ``-``/``#``
  makes the line an option/comment.  Absolute paths (always used here) cure the
  last two; names with CR/LF are sent as an argfile ``#[CSTR]`` line with C
  escapes, which ExifTool 12.57 decodes correctly **except** that it keeps a
  backslash before ``$`` and ``@``: a name with a line break *and* ``$`` or ``@``
  cannot be passed and gets :class:`FileNameError`;
* names that are not valid UTF-8 reach ExifTool as raw bytes but come back with
  ``?`` in place of the bad bytes, so they are read alone (one command for that
  file) and not matched by name.

Every result is matched back to its input by ExifTool's ``SourceFile``; a file
ExifTool did not report gets an error, never another file's metadata.

Normalisation and the key are :mod:`vigproc.io.lenskey`'s (re-exported here).
"""

from __future__ import annotations

import json
import logging
import os
import re
import stat
from collections import deque
from dataclasses import dataclass
from typing import Any, Iterable, Sequence, Union

from vigproc.errors import FileNameError, ImageReadError, MetadataError, UnsupportedFormatError, VigprocError
from vigproc.io.exiftool_process import ExiftoolProcess
from vigproc.io.lenskey import (  # noqa: F401  (re-exported: their public path was this module)
    KEY_FIELDS, MAX_TEXT_LEN, LensKey, casefold_lens_id, escape_key_part, lens_key_from_metadata, normalise_text,
)
from vigproc.io.lensident import unescape_key_part  # noqa: F401  (re-exported)

__all__ = [
    "ExifReader",
    "FileNameError",
    "FileTags",
    "KEY_FIELDS",
    "RECORD_TAGS",
    "LensKey",
    "MetadataError",
    "lens_key_from_metadata",
    "normalise_text",
    "read_lens_key",
]

logger = logging.getLogger(__name__)

PathLike = Union[str, "os.PathLike[str]", bytes]

# Tags requested from ExifTool.  "#" = numeric value (per-tag -n); text tags keep
# their print conversion because Composite:LensID is only a name when printed.
# The focal range the camera reports for the mounted lens (lens identity checks, lensident.py).
_LENS_RANGE_TAGS: tuple[str, ...] = ("-MinFocalLength#", "-MaxFocalLength#", "-MaxApertureValue#")
_TAGS: tuple[str, ...] = _LENS_RANGE_TAGS + (
    "-File:FileType", "-File:MIMEType", "-ExifTool:Error", "-ExifTool:Warning",
    "-Make", "-Model",
    "-Composite:LensID", "-LensModel", "-Lens", "-LensType", "-LensSerialNumber", "-LensMake",
    "-FocalLength#", "-FocalLengthIn35mmFormat#", "-Composite:FocalLength35efl#",
    "-FNumber#", "-ApertureValue#", "-Composite:Aperture#",
    "-Composite:FocusDistance#", "-FocusDistance#", "-FocusDistanceUpper#",
    "-FocusDistanceLower#", "-SubjectDistance#",
    "-Composite:ImageSize#",
    # vigproc's own correction record (metadata.py) has a Model tag, the model JSON:
    # it is not the camera's Model. Its Applied flag is read (incamera.py: no second pass).
    "--XMP-vigproc:Model", "-XMP-vigproc:Applied",
) + (
    # Read in the same command so that each file is read once (FileTags): the capture date
    # and serials of a check's provenance (provenance.py), the in-camera correction flags
    # (incamera.py), a raw file's maker calibration (makernotes.py). Numeric values, as
    # read_tags asks for them (a Canon serial's print conversion pads it with zeros).
    "-DateTimeOriginal#", "-OffsetTimeOriginal#", "-SerialNumber#", "-InternalSerialNumber#",
    "-PeripheralIlluminationCorr#", "-PeripheralLighting#", "-PeripheralLightingSetting#",
    "-VignetteControl#", "-VignettingCorrection#", "-ShadingCompensation#",
    "-SubIFD:VignettingCorrParams#", "-FujiIFD:VignettingParams#", "-FujiFilm:CropMode#",
)
#: What :meth:`FileTags.read_tags` answers from the one command's record, as the callers
#: spell it (``GROUP:Name`` with a family-0 group: that group's value; a family-1 group the
#: command itself names, or no group: the value of that name in any group). Text tags here
#: have no print conversion in these groups: their text is their numeric value.
RECORD_TAGS: frozenset[str] = frozenset({
    "Make", "Model", "PeripheralIlluminationCorr", "PeripheralLighting", "PeripheralLightingSetting",
    "VignetteControl", "VignettingCorrection", "ShadingCompensation",
    "SubIFD:VignettingCorrParams", "FujiIFD:VignettingParams", "FujiFilm:CropMode",
    "EXIF:DateTimeOriginal", "EXIF:OffsetTimeOriginal", "EXIF:Make", "EXIF:Model", "EXIF:SerialNumber",
    "EXIF:LensModel", "EXIF:LensSerialNumber",
    "XMP:DateTimeOriginal", "XMP:SerialNumber", "XMP:LensModel", "XMP:Lens", "XMP:LensSerialNumber",
    "MakerNotes:SerialNumber", "MakerNotes:InternalSerialNumber", "XMP:Applied",
})
_FAMILY0 = frozenset({"EXIF", "XMP", "MakerNotes", "File", "Composite", "IPTC", "ICC_Profile", "QuickTime"})
# What every record needs for _check_record (file type, exiftool's own error and warning).
_CHECK_TAGS: tuple[str, ...] = ("-File:FileType", "-File:MIMEType", "-ExifTool:Error", "-ExifTool:Warning")
# -G: family-0 group names ("EXIF:Make", "MakerNotes:LensType", "XMP:Lens", ...).
# -fast: do not scan JPEGs to the end for trailers (no lens data there); ~10 %
# faster on the shared camera JPEGs with identical keys.  (-fast2 would skip
# maker notes, i.e. most lens IDs.)
_COMMON_ARGS = ["-G", "-fast"]
# Files per ExifTool command: bounds the JSON held in memory and what one fatal
# ExifTool failure can take down before the per-file fallback.
_CHUNK = 256

_IMAGE_MIME_PREFIXES = ("image/",)


# --------------------------------------------------------------------------- #
# errors
# --------------------------------------------------------------------------- #


def _q(path: str) -> str:
    # repr() keeps messages on one line even for names containing newlines.
    return repr(path)


def _path_error(cls: type[ImageReadError], path: str, cause: str) -> ImageReadError:
    """Build a typed error whose message names the file and the cause."""
    err = cls(f"cannot read EXIF of {_q(path)}: {cause}")
    err.path = path  # type: ignore[attr-defined]
    err.cause = cause  # type: ignore[attr-defined]
    return err


# --------------------------------------------------------------------------- #
# reading files
# --------------------------------------------------------------------------- #


@dataclass
class _Job:
    display: str  # the path as the caller gave it (for messages)
    arg: Union[str, bytes]  # what is sent to ExifTool
    expect: str | None  # the SourceFile ExifTool will report (None: do not match by name)
    solo: bool = False  # read in its own command


def _prepare(path: PathLike) -> _Job | ImageReadError:
    """Check a path and decide how to pass it to ExifTool."""
    try:
        p = os.fspath(path)
    except TypeError:
        return _path_error(ImageReadError, repr(path), f"not a path ({type(path).__name__})")
    display = os.fsdecode(p) if isinstance(p, bytes) else p
    try:
        st = os.stat(p)
    except FileNotFoundError:
        return _path_error(ImageReadError, display, "file not found")
    except PermissionError:
        return _path_error(ImageReadError, display, "permission denied")
    except ValueError as exc:  # embedded NUL
        return _path_error(FileNameError, display, f"invalid file name ({exc})")
    except OSError as exc:
        return _path_error(ImageReadError, display, exc.strerror or str(exc))
    if stat.S_ISDIR(st.st_mode):
        # ExifTool would read every file inside.
        return _path_error(ImageReadError, display, "is a directory")
    if not stat.S_ISREG(st.st_mode):
        # A FIFO/device could block the shared ExifTool process forever.
        return _path_error(ImageReadError, display, "not a regular file")
    if st.st_size == 0:
        return _path_error(ImageReadError, display, "file is empty (0 bytes)")
    # Absolute: a name starting with "-", "#" or white space is never an option,
    # comment or trimmed argfile line.  No normpath: "link/../x" must stay as is.
    absolute = display if os.path.isabs(display) else os.path.join(os.getcwd(), display)
    try:
        absolute.encode("utf-8")
    except UnicodeEncodeError:
        try:
            raw = os.fsencode(absolute)
        except UnicodeEncodeError:
            return _path_error(FileNameError, display, "file name cannot be encoded for the file system")
        if b"\n" in raw or b"\r" in raw:
            return _path_error(
                FileNameError, display,
                "file name is not valid UTF-8 and contains a line break; ExifTool cannot be given it safely; rename the file",
            )
        return _Job(display, raw, None, solo=True)
    if "\n" in absolute or "\r" in absolute:
        if "$" in absolute or "@" in absolute:
            return _path_error(
                FileNameError, display,
                "file name contains a line break together with '$' or '@', which ExifTool's argument "
                "protocol (-stay_open/-@ #[CSTR]) cannot carry; rename the file",
            )
        esc = (absolute.replace("\\", "\\\\").replace('"', '\\"')
               .replace("\n", "\\n").replace("\r", "\\r"))
        return _Job(display, "#[CSTR]" + esc, absolute)
    return _Job(display, absolute, absolute)


_STDERR_LINE = re.compile(r"^(Error|Warning): (.*?) - (.*)$")


def _stderr_causes(stderr: str) -> dict[str, str]:
    causes: dict[str, str] = {}
    for line in stderr.splitlines():
        m = _STDERR_LINE.match(line)
        if m:
            causes.setdefault(m.group(3), f"exiftool: {m.group(2)}")
    return causes


def _safe_msg(text: Any) -> str:
    # ExifTool messages can quote file content: keep them short and printable.
    s = "".join(c if c.isprintable() else " " for c in str(text))
    return " ".join(s.split())[:200]


class ExifReader:
    """Read :class:`LensKey` s through one persistent ExifTool process.

    Parameters
    ----------
    executable : str, optional
        ExifTool program (default: ``exiftool`` on ``PATH``).
    require : iterable of str
        Fields of :data:`KEY_FIELDS` that must be present; a file missing one
        gets :class:`MetadataError`.  Regardless of this, a file without any of
        make, model and lens gets :class:`MetadataError` (no identity at all).
    chunk_size : int
        Files per ExifTool command in :meth:`read_many`.

    Notes
    -----
    Use as a context manager (the process is started on entry and stopped on
    exit) or call :meth:`start` / :meth:`close`.  Not safe for concurrent use by
    several threads beyond the internal lock serialising commands.

    Examples
    --------
    >>> with ExifReader() as reader:                      # doctest: +SKIP
    ...     keys = reader.read_many(paths)
    """

    def __init__(
        self,
        executable: str | None = None,
        *,
        require: Iterable[str] = (),
        chunk_size: int = _CHUNK,
    ) -> None:
        self.require = tuple(require)
        bad = [f for f in self.require if f not in KEY_FIELDS]
        if bad:
            raise ValueError(f"unknown required fields {bad}; choose from {KEY_FIELDS}")
        if chunk_size < 1:
            raise ValueError("chunk_size must be >= 1")
        self.chunk_size = int(chunk_size)
        # check_execute is off there: a batch with one bad file exits with status 1,
        # which is per-file information, not a failure of the command
        self._proc = ExiftoolProcess(executable, common_args=_COMMON_ARGS)
        # prefetch()'s commands in order: (path, identity, job, pending answer)
        self._ahead: list[tuple[str, tuple[int, int, int], _Job, Any]] = []

    # ---- process lifetime ------------------------------------------------- #

    def start(self) -> "ExifReader":
        """Start the ExifTool process (no-op when running).

        Raises
        ------
        VigprocError
            If ExifTool cannot be started.
        """
        self._proc.start()
        return self

    def spawn(self) -> "ExifReader":
        """Start the ExifTool process without waiting for it to be ready (see
        :meth:`vigproc.io.exiftool_process.ExiftoolProcess.spawn`).

        Raises
        ------
        VigprocError
            If ExifTool cannot be launched.
        """
        self._proc.spawn()
        return self

    def close(self) -> None:
        """Stop the ExifTool process."""
        self._proc.close()

    def __enter__(self) -> "ExifReader":
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.close()

    def __del__(self) -> None:  # pragma: no cover - best effort
        try:
            self.close()
        except Exception:  # noqa: BLE001
            pass

    @property
    def launches(self) -> int:
        """Number of ExifTool processes this reader has launched (1 unless one died)."""
        return self._proc.launches

    @property
    def pid(self) -> int | None:
        """Process id of the running ExifTool, or None."""
        return self._proc.pid

    @property
    def version(self) -> str | None:
        """ExifTool version string, or None when not running."""
        return self._proc.version

    # ---- reading ---------------------------------------------------------- #

    def read(self, path: PathLike) -> LensKey:
        """Read one file.

        Raises
        ------
        ImageReadError, UnsupportedFormatError, FileNameError, MetadataError
            Typed errors naming the file and the cause.
        """
        result = self.read_many([path])[0]
        if isinstance(result, BaseException):
            raise result
        return result

    def prefetch(self, path: PathLike) -> None:
        """Ask exiftool now for what :meth:`read_file` of ``path`` will read, without
        waiting: exiftool reads the file while the caller works on another one.

        Only the next :meth:`read_file` of the same path takes the answer, and only
        if the file is still the one asked about (same inode, size and modification
        time); otherwise the answer is dropped and the file read again. Best effort:
        a path :meth:`read_file` would refuse, or a process that cannot start, is
        left to :meth:`read_file` to report.
        """
        job = _prepare(path)
        if isinstance(job, VigprocError):
            return
        try:
            ident = _identity(job.display)
            pending = self._proc.submit(["-j", *_TAGS, job.arg])
        except (OSError, VigprocError) as exc:
            logger.debug("exiftool prefetch of %s not sent: %s", _q(job.display), _safe_msg(exc))
            return
        self._ahead.append((job.display, ident, job, pending))

    def read_file(self, path: PathLike) -> FileTags:
        """Read one file once: its :class:`LensKey` and the tags of :data:`RECORD_TAGS`
        (:class:`FileTags`). Never raises for the file: a failed read is kept in
        :attr:`FileTags.error` and raised by what asks it."""
        res = self._prefetched(path)
        if res is None:
            res = self.read_metadata_many([path])[0]
        if isinstance(res, VigprocError):
            return FileTags(self, path, None, res)
        return FileTags(self, path, res[1])

    def read_many(self, paths: Iterable[PathLike]) -> list[LensKey | VigprocError]:
        """Read many files with one ExifTool command per chunk (one process).

        Parameters
        ----------
        paths : iterable of path-like

        Returns
        -------
        list
            One entry per input, in order: a :class:`LensKey` or the typed error
            for that file (returned, not raised).
        """
        metas = self.read_metadata_many(paths)
        out: list[LensKey | VigprocError] = []
        for item in metas:
            if isinstance(item, VigprocError):
                out.append(item)
                continue
            display, meta = item
            out.append(self._to_key(display, meta))
        return out

    def read_metadata_many(
        self, paths: Iterable[PathLike]
    ) -> list[tuple[str, dict[str, Any]] | VigprocError]:
        """Raw ExifTool records (``-G`` keys) for each path, or its typed error."""
        jobs: list[_Job | ImageReadError] = [_prepare(p) for p in paths]
        results: list[tuple[str, dict[str, Any]] | VigprocError | None] = [None] * len(jobs)
        batch: list[int] = []
        for i, job in enumerate(jobs):
            if isinstance(job, VigprocError):
                results[i] = job
            elif job.solo:
                results[i] = self._run_jobs([job])[0]
            else:
                batch.append(i)
        for start in range(0, len(batch), self.chunk_size):
            idx = batch[start:start + self.chunk_size]
            chunk_jobs = [jobs[i] for i in idx]
            for i, res in zip(idx, self._run_jobs(chunk_jobs)):  # type: ignore[arg-type]
                results[i] = res
        return results  # type: ignore[return-value]

    def read_tags(self, path: PathLike, tags: Sequence[str]) -> dict[str, Any]:
        """Numeric values (``-TAG#``) of ``tags`` (``GROUP:Name``, family-1 groups such as
        ``SubIFD:VignettingCorrParams``) in one file, keyed as requested; tags the file
        lacks are absent.

        exiftool reads each tag from the group named only, but reports it under its
        family-0 group (the reader's ``-G``): the names must differ from one another.

        Raises
        ------
        ImageReadError, UnsupportedFormatError, FileNameError
            Typed errors naming the file and the cause.
        ValueError
            Two requested tags share a name.
        """
        wanted = {t.rsplit(":", 1)[-1]: t for t in tags}
        if len(wanted) != len(tags):
            raise ValueError(f"tag names must differ: {list(tags)}")
        job = _prepare(path)
        if isinstance(job, VigprocError):
            raise job
        res = self._run_jobs([job], tags=(*_CHECK_TAGS, *(f"-{t}#" for t in tags)))[0]
        if isinstance(res, VigprocError):
            raise res
        out: dict[str, Any] = {}
        for key, value in res[1].items():
            name = key.rsplit(":", 1)[-1]
            if name in wanted and key not in ("SourceFile", *(t[1:] for t in _CHECK_TAGS)):
                out[wanted[name]] = value
        return out

    def _execute(self, args: list[Union[str, bytes]], tags: Sequence[str] = _TAGS) -> tuple[list[Any], str]:
        """One ExifTool command (``tags`` then ``args``); returns (JSON records, stderr)."""
        return _parse_records(self._proc.execute(["-j", *tags, *args]))

    def _prefetched(self, path: PathLike) -> tuple[str, dict[str, Any]] | VigprocError | None:
        """:meth:`prefetch`'s answer for ``path`` if it is still the file asked about, else None."""
        try:
            name = os.fsdecode(os.fspath(path))
        except TypeError:
            return None
        at = next((i for i, a in enumerate(self._ahead) if a[0] == name), None)
        if at is None:
            return None
        # the ones asked before it were not read (their files failed earlier): dropped
        display, ident, job, pending = self._ahead[at]
        del self._ahead[:at + 1]
        try:
            same = _identity(display) == ident
        except OSError:
            same = False
        try:
            res = self._proc.result(pending)
        except VigprocError as exc:
            logger.debug("exiftool prefetch of %s lost (%s): reading again", _q(display), _safe_msg(exc))
            return None
        if not same:
            return None

        def answer(args: list[Union[str, bytes]], tags: Sequence[str]) -> tuple[list[Any], str]:
            return _parse_records(res)

        return self._run_jobs([job], answer=answer)[0]

    def _run_jobs(self, jobs: list[_Job], tags: Sequence[str] = _TAGS, *, answer: Any = None
                  ) -> list[tuple[str, dict[str, Any]] | VigprocError]:
        try:
            records, stderr = (answer or self._execute)([j.arg for j in jobs], tags)
        except Exception as exc:  # noqa: BLE001 - any failure of the command itself
            logger.warning("exiftool command failed for %d file(s): %s", len(jobs), _safe_msg(exc))
            self._restart()
            if len(jobs) > 1:
                # Isolate the culprit: the others must still be read.
                return [self._run_jobs([j], tags)[0] for j in jobs]
            return [_path_error(ImageReadError, jobs[0].display, f"exiftool failed: {_safe_msg(exc)}")]
        by_name: dict[str, deque[dict[str, Any]]] = {}
        for rec in records:
            if isinstance(rec, dict) and isinstance(rec.get("SourceFile"), str):
                by_name.setdefault(rec["SourceFile"], deque()).append(rec)
        causes = _stderr_causes(stderr)
        out: list[tuple[str, dict[str, Any]] | VigprocError] = []
        for job in jobs:
            rec: dict[str, Any] | None = None
            if job.expect is None:  # solo job, matched by being alone
                if len(records) == 1 and isinstance(records[0], dict):
                    rec = records[0]
            else:
                queue = by_name.get(job.expect)
                if queue:
                    rec = queue.popleft()
            if rec is None:
                cause = causes.get(job.expect or "", "exiftool returned no metadata for this file")
                out.append(_path_error(ImageReadError, job.display, _safe_msg(cause)))
                continue
            out.append(self._check_record(job.display, rec))
        return out

    def _restart(self) -> None:
        self.close()  # start() happens lazily on the next command

    @staticmethod
    def _check_record(display: str, rec: dict[str, Any]) -> tuple[str, dict[str, Any]] | VigprocError:
        error = rec.get("ExifTool:Error")
        if error:
            msg = _safe_msg(error)
            cls = UnsupportedFormatError if re.search(r"unknown file type|format error|not supported", msg, re.I) else ImageReadError
            return _path_error(cls, display, f"exiftool: {msg}")
        warning = rec.get("ExifTool:Warning")
        if warning:
            logger.info("%s: exiftool warning: %s", _q(display), _safe_msg(warning))
        mime = rec.get("File:MIMEType")
        ftype = _safe_msg(rec.get("File:FileType") or "unknown")
        if not (isinstance(mime, str) and mime.startswith(_IMAGE_MIME_PREFIXES)):
            return _path_error(UnsupportedFormatError, display, f"not an image (exiftool file type {ftype})")
        return display, rec

    def _to_key(self, display: str, meta: dict[str, Any]) -> LensKey | VigprocError:
        key = lens_key_from_metadata(meta, source=display)
        if key.make is None and key.model is None and key.lens is None:
            why = "; ".join(key.problems)
            return _path_error(
                MetadataError, display,
                "no camera make, model or lens in the metadata" + (f" ({why})" if why else ""),
            )
        lacking = [f for f in self.require if getattr(key, f) is None]
        if lacking:
            why = [p for p in key.problems if p.split(":", 1)[0] in lacking]
            return _path_error(
                MetadataError, display,
                f"required EXIF field(s) missing: {', '.join(lacking)}" + (f" ({'; '.join(why)})" if why else ""),
            )
        return key


def _parse_records(res: Any) -> tuple[list[Any], str]:
    """An exiftool ``-j`` answer: (JSON records, stderr)."""
    text = res.stdout.decode("utf-8", errors="replace").strip()
    records = json.loads(text) if text else []
    if not isinstance(records, list):
        raise ValueError("exiftool JSON output is not a list")
    return records, res.stderr.decode("utf-8", errors="replace")


def _identity(path: Union[str, bytes]) -> tuple[int, int, int]:
    st = os.stat(path)
    return st.st_ino, st.st_size, st.st_mtime_ns


class FileTags:
    """One file's metadata as one ExifTool command read it (:meth:`ExifReader.read_file`):
    its :class:`LensKey` and the other tags the pipeline reads (:data:`RECORD_TAGS`), so
    that each file is read once. Quacks like the reader (``read``, ``read_tags``), so it
    can be handed to :func:`vigproc.io.incamera.read_in_camera`,
    :func:`vigproc.io.makernotes.calibration_for` and
    :func:`vigproc.io.provenance.read_provenance`; another file, or a tag the record does
    not hold, is asked of the reader.

    Parameters
    ----------
    reader : ExifReader
    path : path-like
        The file as the caller named it.
    record : dict or None
        ExifTool's record (``-G`` keys); None when the read failed.
    error : VigprocError or None
        Why the read failed: raised by ``read`` and ``read_tags`` (no second attempt).
    """

    def __init__(self, reader: "ExifReader", path: PathLike, record: dict[str, Any] | None,
                 error: VigprocError | None = None) -> None:
        self.reader = reader
        self.path = os.fspath(path)
        self.record = record
        self.error = error
        self._key: LensKey | VigprocError | None = None

    def _own(self, path: PathLike) -> bool:
        try:
            return os.fspath(path) == self.path
        except TypeError:
            return False

    def read(self, path: PathLike | None = None) -> LensKey:
        """The file's :class:`LensKey` (``path``: another file is read by the reader).

        Raises
        ------
        ImageReadError, UnsupportedFormatError, FileNameError, MetadataError
        """
        if path is not None and not self._own(path):
            return self.reader.read(path)
        if self.error is not None:
            raise self.error
        if self._key is None:
            self._key = self.reader._to_key(_display(self.path), self.record or {})
        if isinstance(self._key, BaseException):
            raise self._key
        return self._key

    def read_tags(self, path: PathLike, tags: Sequence[str]) -> dict[str, Any]:
        """:meth:`ExifReader.read_tags` from the record when it holds every tag asked for.

        Raises
        ------
        ImageReadError, UnsupportedFormatError, FileNameError
            The file's one read failed (that error), or the reader's.
        ValueError
            Two requested tags share a name.
        """
        if not self._own(path) or not all(t in RECORD_TAGS for t in tags):
            return self.reader.read_tags(path, tags)
        if self.error is not None:
            raise self.error
        wanted = {t.rsplit(":", 1)[-1]: t for t in tags}
        if len(wanted) != len(tags):
            raise ValueError(f"tag names must differ: {list(tags)}")
        out: dict[str, Any] = {}
        for key, value in (self.record or {}).items():
            group, _, name = key.rpartition(":")
            tag = wanted.get(name)
            if tag is None:
                continue
            asked = tag.rpartition(":")[0]
            # a family-0 group asked for is matched; a family-1 one the command itself named
            if asked in _FAMILY0 and asked != group:
                continue
            out[tag] = value  # the last one wins, as in ExifReader.read_tags
        return out


def _display(path: Union[str, bytes]) -> str:
    return os.fsdecode(path) if isinstance(path, bytes) else path


def read_lens_key(path: PathLike, **kwargs: Any) -> LensKey:
    """Read one file's :class:`LensKey` with a reader of its own (starts/stops ExifTool).

    For more than a few files use :class:`ExifReader` (one process for all).

    Raises
    ------
    ImageReadError, UnsupportedFormatError, FileNameError, MetadataError
    """
    with ExifReader(**kwargs) as reader:
        return reader.read(path)

