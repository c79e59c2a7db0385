"""Private scratch folders that do not outlive their process, even one killed with SIGKILL.

A folder made with :func:`tempfile.mkdtemp` and removed in a ``finally`` or an ``atexit``
handler stays behind when its process is killed (a daemon or pool worker stopped with
SIGKILL, the kernel's out-of-memory killer): nothing of the process runs any more.  The
folders made here carry their owner in their name, ``vigproc-KIND-PID.START-XXXXXXXX``
(START: the process's start time, so a recycled process id is not taken for its owner),
and the first one a process makes in a directory sweeps that directory of the folders of
owners that are gone (:func:`sweep`). A folder made beside its output (so that one rename
publishes the result on the same file system) is hidden, ``.vigproc-KIND-...``, and swept
the same way by the next process writing there.  So a killed process's folder lasts until the next vigproc process needs
one, and never accumulates.

Folders of vigproc versions before this module, ``vigproc-exiftool-XXXXXXXX`` holding
only the metadata writer's ``vigproc.config`` (now shipped in the package), are swept as
well once an hour old: a process of such a version that still runs writes its config again
when it finds it gone.
"""

from __future__ import annotations

import contextlib
import logging
import os
import re
import shutil
import stat
import tempfile
import threading
import time
from typing import Iterator

__all__ = ["owner_alive", "scratch", "scratch_folder", "sweep"]

logger = logging.getLogger(__name__)

_NAME = re.compile(r"^\.?vigproc-[a-z]+-(\d+)\.(\d+)-[A-Za-z0-9_]+$")
_LEGACY = re.compile(r"^vigproc-exiftool-[A-Za-z0-9_]{8}$")
_LEGACY_FILES = {"vigproc.config"}
#: Age (s) after which a folder of the old form holding only a config file is swept.
LEGACY_AGE = 3600.0

_swept: set[tuple[int, str]] = set()  # (os.getpid(), directory) swept already
_lock = threading.Lock()


def _start_time(pid: int) -> int | None:
    """The start time of process ``pid`` in clock ticks since boot (Linux), None when
    unknown; -1 when the process is a zombie (dead, not yet reaped)."""
    try:
        with open(f"/proc/{pid}/stat", "rb") as fh:
            data = fh.read()
    except OSError:
        return None
    # the command name (field 2) is in parentheses and may hold spaces: split after it
    fields = data[data.rfind(b")") + 2:].split()
    try:
        return -1 if fields[0] == b"Z" else int(fields[19])
    except (IndexError, ValueError):
        return None


def owner_alive(pid: int, start: int) -> bool:
    """Whether the process that made a folder named with ``pid`` and ``start`` still runs.

    Parameters
    ----------
    pid : int
        Its process id.
    start : int
        Its start time as :func:`_start_time` gave it (0: unknown, the id alone decides).

    Returns
    -------
    bool
        False when no process has that id, it is a zombie, or it started at another time.
    """
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # another user's process holds the id now
        return start == 0
    except OSError:
        return True
    now = _start_time(pid)
    if now == -1:
        return False
    return start == 0 or now is None or now == start


def sweep(directory: str | None = None) -> int:
    """Remove the scratch folders of processes that are gone.

    Parameters
    ----------
    directory : str, optional
        Where to look (default: :func:`tempfile.gettempdir`).

    Returns
    -------
    int
        Folders removed.  Only this user's folders of the forms above are touched; errors
        are logged, never raised.
    """
    directory = directory or tempfile.gettempdir()
    removed = 0
    try:
        entries = list(os.scandir(directory))
    except OSError:
        return 0
    uid = os.getuid() if hasattr(os, "getuid") else None
    for e in entries:
        m = _NAME.match(e.name)
        legacy = m is None and _LEGACY.match(e.name) is not None
        if m is None and not legacy:
            continue
        try:
            st = e.stat(follow_symlinks=False)
        except OSError:
            continue
        if not stat.S_ISDIR(st.st_mode) or (uid is not None and st.st_uid != uid):
            continue
        if m is not None:
            if owner_alive(int(m.group(1)), int(m.group(2))):
                continue
        else:
            try:
                if time.time() - st.st_mtime < LEGACY_AGE or not set(os.listdir(e.path)) <= _LEGACY_FILES:
                    continue
            except OSError:
                continue
        shutil.rmtree(e.path, ignore_errors=True)
        if not os.path.exists(e.path):
            removed += 1
    if removed:
        logger.debug("removed %d scratch folder(s) of processes that are gone from %s", removed, directory)
    return removed


def scratch_folder(kind: str, directory: str | os.PathLike[str] | None = None) -> str:
    """A new private folder (mode 0700), named for this process.

    The caller removes it when done (see :func:`scratch`); if this process is killed first,
    the next process's first :func:`scratch_folder` in the same directory removes it.

    Parameters
    ----------
    kind : str
        Lower-case letters naming its use (``exiftool``, ``batch``...).
    directory : path, optional
        Where to make it (default: :func:`tempfile.gettempdir`). Elsewhere (beside an
        output, for one rename to publish it) the folder is hidden: ``.vigproc-KIND-...``.

    Returns
    -------
    str
        Its path.  Raises OSError.
    """
    if not kind.isalpha() or not kind.islower():
        raise ValueError(f"scratch kind must be lower-case letters: {kind!r}")
    where = os.fspath(directory) if directory is not None else tempfile.gettempdir()
    pid = os.getpid()
    with _lock:
        first = (pid, where) not in _swept
        _swept.add((pid, where))
    if first:
        sweep(where)
    start = _start_time(pid)
    dot = "." if directory is not None else ""
    return tempfile.mkdtemp(prefix=f"{dot}vigproc-{kind}-{pid}.{start if start and start > 0 else 0}-", dir=where)


@contextlib.contextmanager
def scratch(kind: str, directory: str | os.PathLike[str] | None = None) -> Iterator[str]:
    """A :func:`scratch_folder` removed with its content when the block ends."""
    folder = scratch_folder(kind, directory)
    try:
        yield folder
    finally:
        shutil.rmtree(folder, ignore_errors=True)
