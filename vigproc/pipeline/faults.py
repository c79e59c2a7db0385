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
    low on space or inodes), or the disk of a store (:attr:`Fault.disk` says which).  Every file would fail the same way until space is
    freed: the daemon pauses, a batch run stops handing out files, ``correct``
    stops with :class:`~vigproc.errors.DiskFullError`.  Never the photo's fault.
:data:`OUTPUT`
    Any other failure of the output side (an I/O error, a read-only remount, an output
    folder that is gone or cannot be made, a writer that gave up: exiftool's ``Error
    writing output file``): retried with backoff and never charged to the photo.
:data:`CRASH`
    Not a verdict of :func:`classify_error` (there is no exception to look at): the
    file killed or hung the worker process handling it.  Retried up to the daemon's
    ``--max-crashes`` -- unless the output side was failing then
    (:func:`output_trouble`): native code may end its process on a write error.

Classified by type, where the failure happened, never by the words of a message (which
carry file names: a photo named "no space left on device.jpg" is no full disk):

* every vigproc error class states whose fault it is (``blame`` in
  :mod:`vigproc.errors`: the input's, the output side's or the settings'); the
  writers raise :class:`~vigproc.errors.DiskFullError` on ENOSPC/EDQUOT and keep the
  ``errno`` of other failed calls (:func:`vigproc.errors.write_error`);
* an :class:`OSError` (and a vigproc error carrying one) by its ``errno``: ENOSPC and
  EDQUOT are a full disk; EAGAIN, EBUSY, ESTALE, EIO... on the input side are
  transient; a plain OSError on a file of the output folder is the output side's;
* a third-party error by its type's code (``sqlite_errorcode``: SQLITE_FULL, BUSY,
  LOCKED).

A writer that gives up without an errno (exiftool's "Error writing output file")
raises a plain :class:`~vigproc.errors.ImageWriteError`: the output side's; it is a
full disk when the output file system has less than ``min_free`` bytes
(:data:`DEFAULT_MIN_FREE`) or no free inode left *after* the failure (the writer
removed its temporary, giving back the space it held).
"""

from __future__ import annotations

import errno
import os
import shutil
from dataclasses import dataclass
from typing import Callable

from vigproc.errors import DISK_FULL_ERRNOS, OUTPUT_SIDE, SETTINGS, DiskFullError, VigprocError

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
    "output_trouble",
]

#: Kinds of failure (see the module docstring).
PERMANENT, TRANSIENT, DISK_FULL, OUTPUT = "permanent", "transient", "disk-full", "output"
CRASH = "crash"
_OUTPUT_SIDE = frozenset({DISK_FULL, OUTPUT})

#: Free bytes below which the output file system counts as full when a write fails
#: (and above which a paused daemon resumes): room for a few 24-MP 16-bit TIFFs.
DEFAULT_MIN_FREE = 256 * 2**20

_TRANSIENT_ERRNOS = frozenset(getattr(errno, n) for n in ("EAGAIN", "EBUSY", "ESTALE", "ETXTBSY", "EINTR", "ETIMEDOUT",
                                                         "EIO", "ENOLCK") if hasattr(errno, n))
# errno values that name a write's cause other than room: a read-only file system, a
# permission; a small or nearly full disk that refuses a write for one of these is not full
_NOT_ROOM_ERRNOS = frozenset(getattr(errno, n) for n in ("EROFS", "EACCES", "EPERM") if hasattr(errno, n))
# SQLite's result codes (sqlite3 errors carry them as ``sqlite_errorcode``, Python 3.11+)
_SQLITE_BUSY, _SQLITE_LOCKED, _SQLITE_FULL = 5, 6, 13


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


def output_trouble(out_dir: str | os.PathLike[str], min_free: int = DEFAULT_MIN_FREE, *,
                   space: Callable[[str], DiskSpace | None] | None = None) -> Fault | None:
    """What is wrong with the output side now, if anything.

    Asked when a worker died or hung with no exception to classify: a death while the
    output side fails (native code that ends its process on a write error) is not the
    photo's fault.

    Parameters
    ----------
    out_dir : path
        The output folder.
    min_free : int
        Bytes: less free space than this is a full disk.
    space : callable, optional
        ``space(out_dir)`` -> :class:`DiskSpace` or None; default :func:`disk_space`.

    Returns
    -------
    Fault or None
        :data:`DISK_FULL` (low on space or inodes), :data:`OUTPUT` (the folder is gone,
        on a read-only file system, or not writable), or None when it looks healthy.
    """
    folder = os.fspath(out_dir)
    found = (space or disk_space)(folder)
    if os.path.isdir(folder):
        try:
            read_only = bool(os.statvfs(folder).f_flag & os.ST_RDONLY)
        except (OSError, AttributeError):
            read_only = False
        # said before the room left: freeing space makes neither writable
        if read_only or not os.access(folder, os.W_OK):
            why = "on a read-only file system" if read_only else "not writable"
            return Fault(OUTPUT, f"the output folder {folder} is {why}", found)
    if found is not None and found.low(min_free):
        return Fault(DISK_FULL, f"output disk full ({found.describe()} on {folder})", found)
    if not os.path.isdir(folder):
        return Fault(OUTPUT, f"the output folder {folder} is gone", found)
    return None


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
        The full disk's free space (the output file system's otherwise) when it was looked at.
    disk : str
        Which disk is full (:data:`DISK_FULL`): ``"output disk"``, ``"profile store disk"``...
    """

    kind: str
    reason: str
    space: DiskSpace | None = None
    disk: str = "output disk"

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


def _output_side(exc: BaseException, out_dir: str | None) -> bool:
    """Whether ``exc`` is a failure of the output side: a vigproc error that says so, or
    a plain OSError on a file of the output folder."""
    blame = getattr(exc, "blame", None)
    if blame is not None:
        return blame == OUTPUT_SIDE
    if isinstance(exc, OSError) and out_dir:
        name = exc.filename if isinstance(exc.filename, str) else None
        root = os.path.abspath(out_dir)
        return name is not None and (os.path.abspath(name) + os.sep).startswith(root.rstrip(os.sep) + os.sep)
    return False


def _full_disk(exc: BaseException, out_dir: str | None) -> tuple[str, str | None] | None:
    """``(which disk, its folder)`` when ``exc`` is a full disk (by type or errno), else None."""
    if isinstance(exc, OSError) and exc.errno in DISK_FULL_ERRNOS or isinstance(exc, DiskFullError) \
            or getattr(exc, "sqlite_errorcode", None) == _SQLITE_FULL:
        disk = getattr(exc, "disk", None)
        if isinstance(disk, str) and disk != "output disk":  # a store's disk names its folder itself
            return disk, getattr(exc, "folder", None)
        if disk is not None or _output_side(exc, out_dir) or getattr(exc, "blame", None) is None:
            return "output disk", out_dir
        return "disk", None
    return None


def classify_error(exc: BaseException, out_dir: str | os.PathLike[str] | None = None, *,
                   min_free: int = DEFAULT_MIN_FREE,
                   space: Callable[[str], DiskSpace | None] | None = None) -> Fault:
    """Whose fault ``exc``, raised while processing one file, is (by its type and errno).

    Parameters
    ----------
    exc : BaseException
        What processing the file raised.
    out_dir : path, optional
        The output folder: its file system's free space decides whether a write
        failure without an errno is a full disk.
    min_free : int
        Bytes: an output-side failure with less free space than this is a full disk.
    space : callable, optional
        ``space(out_dir)`` -> :class:`DiskSpace` or None; default :func:`disk_space`.

    Returns
    -------
    Fault
        The input's fault (corrupt, unsupported, absurd) and the settings' are
        permanent (a later attempt with the same settings cannot help); a busy or locked file, a
        locked store, a stale network handle are transient; a full disk or quota is
        :data:`DISK_FULL`; any other failure of the output side is :data:`OUTPUT`.  An
        unexpected exception is a bug: permanent, so that the file is quarantined
        rather than retried forever.
    """
    msg = " ".join(str(exc).split()) or type(exc).__name__
    if isinstance(exc, ImportError):
        return Fault(PERMANENT, f"this vigproc installation cannot do it: {msg}")
    if isinstance(exc, MemoryError):
        return Fault(TRANSIENT, "out of memory")
    look = space or disk_space
    folder = os.fspath(out_dir) if out_dir is not None else None
    full = _full_disk(exc, folder)
    if full is not None:
        disk, where = full
        found = look(where) if where is not None else None
        free = f" ({found.describe()} on {where})" if found is not None else ""
        return Fault(DISK_FULL, f"{disk} full{free}: {msg}", found, disk)
    code = getattr(exc, "sqlite_errorcode", None)
    # marked transient by its raiser (a killed exiftool, a locked store, a file still being
    # written): a retry may help; limited, as such a failure can be the file's
    if getattr(exc, "transient", False) or code in (_SQLITE_BUSY, _SQLITE_LOCKED):
        return Fault(TRANSIENT, msg)
    if _output_side(exc, folder):
        found = look(folder) if folder is not None else None
        where = f" on {folder}" if folder is not None else ""
        if found is not None and found.low(min_free) and getattr(exc, "errno", None) not in _NOT_ROOM_ERRNOS:
            return Fault(DISK_FULL, f"output disk full ({found.describe()}{where}): {msg}", found)
        free = f"; {found.describe()}{where}" if found is not None else ""
        return Fault(OUTPUT, f"output write failed (not the photo's fault{free}): {msg}", found)
    if isinstance(exc, OSError) and exc.errno in _TRANSIENT_ERRNOS and getattr(exc, "blame", None) != SETTINGS:
        return Fault(TRANSIENT, msg)
    if isinstance(exc, (VigprocError, OSError)):
        return Fault(PERMANENT, msg)
    return Fault(PERMANENT, f"internal error ({type(exc).__name__}: {msg})")
