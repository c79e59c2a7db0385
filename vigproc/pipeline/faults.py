"""Whose fault a failure is: the photo's, a passing condition's, or the output side's.

One policy for every front end that processes files -- the watch-folder daemon
(:mod:`vigproc.frontends.daemon`), batch runs (:mod:`vigproc.frontends.batch`) and ``vigproc correct``
-- so that they never disagree about a photo.

Kinds
-----
:data:`PERMANENT`
    Something is wrong with the photo (corrupt, unsupported, absurd, no usable fit)
    or with the installation: a later attempt cannot help.  Only this kind may
    quarantine a file.
:data:`TRANSIENT`
    A passing condition on the *input* side or of the machine: a locked or busy
    file, a stale network handle, a locked profile store, memory.  Retried a
    limited number of times.
:data:`DISK_FULL`
    The output file system is full (ENOSPC, EDQUOT, or a write failure while it is
    low on space or inodes).  Every file would fail the same way until space is
    freed: the daemon pauses, a batch run stops handing out files, ``correct``
    stops with :class:`~vigproc.errors.DiskFullError`.  Never the photo's fault.
:data:`OUTPUT`
    Any other failure to write an output (an I/O error, a read-only remount, a
    writer that gave up: OpenImageIO's ``TIFFWriteScanline failed ... Write
    error``, exiftool's ``Error writing image data``).  *A failure to write an
    output is the output side's fault until proven otherwise*: retried with
    backoff and never charged to the photo.
:data:`CRASH`
    Not a verdict of :func:`classify_error` (there is no exception to look at): the
    file killed or hung the worker process handling it.  Retried up to the daemon's
    ``--max-crashes``.

"Proven otherwise" means a write error that names what is wrong with the frame or
the settings rather than with the disk (values beyond the output format's range,
an unreadable source, a refused output name): those stay :data:`PERMANENT`.

Writers lose the errno on the way (OpenImageIO and exiftool report text), and
they remove their temporary file when they fail, which gives back the space it
held: so a write failure is taken as a full disk when the output file system has
less than ``min_free`` bytes (:data:`DEFAULT_MIN_FREE`) or no free inode left
*after* the failure, as well as on ENOSPC/EDQUOT or their words in the message.
"""

from __future__ import annotations

import errno
import os
import shutil
from dataclasses import dataclass
from typing import Callable

from vigproc.errors import ImageWriteError, VigprocError

__all__ = [
    "CRASH",
    "DEFAULT_MIN_FREE",
    "DISK_FULL",
    "Fault",
    "OUTPUT",
    "PERMANENT",
    "TRANSIENT",
    "DiskSpace",
    "attempt_limit",
    "classify_error",
    "disk_space",
]

#: Kinds of failure (see the module docstring).
PERMANENT, TRANSIENT, DISK_FULL, OUTPUT = "permanent", "transient", "disk-full", "output"
CRASH = "crash"
_OUTPUT_SIDE = frozenset({DISK_FULL, OUTPUT})

#: Free bytes below which the output file system counts as full when a write fails
#: (and above which a paused daemon resumes): room for a few 24-MP 16-bit TIFFs.
DEFAULT_MIN_FREE = 256 * 2**20

_TRANSIENT_TEXT = ("resource temporarily unavailable", "device or resource busy", "stale file handle",
                   "locked by another process", "database is locked", "text file busy", "interrupted system call",
                   "connection timed out", "input/output error")
_DISK_FULL_TEXT = ("no space left on device", "disk quota exceeded", "disk is full", "not enough space")
_TRANSIENT_ERRNOS = frozenset(getattr(errno, n) for n in ("EAGAIN", "EBUSY", "ESTALE", "ETXTBSY", "EINTR", "ETIMEDOUT",
                                                         "EIO", "ENOLCK") if hasattr(errno, n))
_DISK_FULL_ERRNOS = frozenset(getattr(errno, n) for n in ("ENOSPC", "EDQUOT") if hasattr(errno, n))
# write errors that name the frame, the source or the settings, not the disk: the
# "proven otherwise" of an output failure (messages of vigproc.io.images, .metadata, .pipeline)
_NOT_OUTPUT_SIDE_TEXT = ("cannot read the source", ": source ", "is not an image", "values reach", "refusing",
                         "unknown extension", "unsupported format", "does not take bit_depth", "transfer must be",
                         "transfer='srgb'", "not valid utf-8", "path must be", "is a folder",
                         "does not exist or is not a file", "source and destination are the same file",
                         "cannot run exiftool", "program not found")


@dataclass(frozen=True)
class DiskSpace:
    """Free space of the file system holding a folder (what an unprivileged writer may use)."""

    free_bytes: int
    total_bytes: int
    free_inodes: int | None  # None where the file system does not count inodes

    def low(self, min_free: int = DEFAULT_MIN_FREE) -> bool:
        """Too little room for another output: under ``min_free`` bytes, or no inode left."""
        return self.free_bytes < min_free or self.free_inodes == 0

    def describe(self) -> str:
        return f"{_mb(self.free_bytes)} free of {_mb(self.total_bytes)}"


def _mb(n: int) -> str:
    return f"{n / 1e6:.1f} MB" if n < 10e9 else f"{n / 1e9:.1f} GB"


def disk_space(folder: str | os.PathLike[str]) -> DiskSpace | None:
    """Free space and inodes of the file system of ``folder`` (or of its nearest existing
    parent); None when it cannot be asked."""
    p = os.path.abspath(os.fspath(folder))
    while not os.path.exists(p) and os.path.dirname(p) != p:
        p = os.path.dirname(p)
    try:
        usage = shutil.disk_usage(p)
    except OSError:
        return None
    inodes = None
    try:
        st = os.statvfs(p)
        if st.f_files > 0:  # 0: the file system does not count inodes (btrfs, some FUSE)
            inodes = int(st.f_favail)
    except (OSError, AttributeError):
        pass
    return DiskSpace(int(usage.free), int(usage.total), inodes)


@dataclass(frozen=True)
class Fault:
    """The verdict on one failure.

    Attributes
    ----------
    kind : str
        :data:`PERMANENT`, :data:`TRANSIENT`, :data:`DISK_FULL` or :data:`OUTPUT`.
    reason : str
        One line: the error's message, with what was found about the output disk.
    space : DiskSpace or None
        The output file system's free space when it was looked at.
    """

    kind: str
    reason: str
    space: DiskSpace | None = None

    @property
    def photo_fault(self) -> bool:
        """Whether the photo (or the installation) is to blame: only then may it be quarantined."""
        return self.kind == PERMANENT

    @property
    def output_side(self) -> bool:
        """A failure to write an output: retried without limit, never charged to the photo."""
        return self.kind in _OUTPUT_SIDE

    def max_attempts(self, limit: int | None) -> int | None:
        """Failed attempts after which the file is given up (:func:`attempt_limit`)."""
        return attempt_limit(self.kind, limit)


def attempt_limit(kind: str, limit: int | None) -> int | None:
    """Failed attempts of ``kind`` after which a file is given up: ``limit``, or None
    (never) for an output-side failure, which is not the photo's."""
    return None if kind in _OUTPUT_SIDE else limit


def _output_write(exc: BaseException, low: str, out_dir: str | None) -> bool:
    """Whether ``exc`` is a failure to write an output (see the module docstring)."""
    marked = getattr(exc, "output_side", None)
    if marked is not None:
        return bool(marked)
    if isinstance(exc, ImageWriteError):
        return not any(t in low for t in _NOT_OUTPUT_SIDE_TEXT)
    if isinstance(exc, OSError) and not isinstance(exc, VigprocError) and out_dir:
        name = exc.filename if isinstance(exc.filename, str) else None
        root = os.path.abspath(out_dir)
        return name is not None and (os.path.abspath(name) + os.sep).startswith(root.rstrip(os.sep) + os.sep)
    return False


def classify_error(exc: BaseException, out_dir: str | os.PathLike[str] | None = None, *,
                   min_free: int = DEFAULT_MIN_FREE,
                   space: Callable[[str], DiskSpace | None] | None = None) -> Fault:
    """Whose fault ``exc``, raised while processing one file, is.

    Parameters
    ----------
    exc : BaseException
        What processing the file raised.
    out_dir : path, optional
        The output folder: its file system's free space decides whether a write
        failure is a full disk.  Without it only errno and the message can tell.
    min_free : int
        Bytes: a write failure with less free space than this is a full disk.
    space : callable, optional
        ``space(out_dir)`` -> :class:`DiskSpace` or None; default :func:`disk_space`.

    Returns
    -------
    Fault
        Bad input (corrupt, unsupported, absurd) is permanent; a busy or locked file,
        a locked profile store, a stale network handle are transient; a full output
        disk or quota is :data:`DISK_FULL`; any other failure to write an output is
        :data:`OUTPUT`.  An unexpected exception is a bug: permanent, so that the file
        is quarantined rather than retried forever.
    """
    msg = " ".join(str(exc).split()) or type(exc).__name__
    low = msg.lower()
    if isinstance(exc, ImportError):
        return Fault(PERMANENT, f"this vigproc installation cannot do it: {msg}")
    if isinstance(exc, MemoryError):
        return Fault(TRANSIENT, "out of memory")
    err_no = getattr(exc, "errno", None)
    folder = os.fspath(out_dir) if out_dir is not None else None
    said_full = err_no in _DISK_FULL_ERRNOS or any(t in low for t in _DISK_FULL_TEXT)
    # marked transient by its raiser (a killed exiftool, a file still being written): a
    # retry may help; limited, as such a failure can be the file's (exiftool dying on it)
    if not said_full and getattr(exc, "transient", False):
        return Fault(TRANSIENT, msg)
    if said_full or _output_write(exc, low, folder):
        found = (space or disk_space)(folder) if folder is not None else None
        where = f" on {folder}" if folder is not None else ""
        if said_full or (found is not None and found.low(min_free)):
            free = f" ({found.describe()}{where})" if found is not None else ""
            return Fault(DISK_FULL, f"output disk full{free}: {msg}", found)
        free = f"; {found.describe()}{where}" if found is not None else ""
        return Fault(OUTPUT, f"output write failed (not the photo's fault{free}): {msg}", found)
    if "libraw" in low:
        # LibRaw's own words about the file's data ("LibRawIOError: Input/output error" for
        # a truncated RAW): the photo's fault, not the device's; retrying cannot help
        return Fault(PERMANENT, msg)
    if err_no in _TRANSIENT_ERRNOS or any(t in low for t in _TRANSIENT_TEXT):
        return Fault(TRANSIENT, msg)
    if isinstance(exc, (VigprocError, OSError)):
        return Fault(PERMANENT, msg)
    return Fault(PERMANENT, f"internal error ({type(exc).__name__}: {msg})")
