"""Atomic file output: write to a temporary file in the same folder, fsync, rename.

A crash or kill leaves either the old file or the new one, never a half-written one.
"""

from __future__ import annotations

import contextlib
import os
import stat
import tempfile
from pathlib import Path
from typing import Iterator

from vigproc.errors import write_error


#: Markers in the temporary names of vigproc's writers (this module, io, metadata, and
#: exiftool's own).
TEMP_MARKERS = (".tmp", ".meta-", "_exiftool_tmp")
#: Characters of an output's name that every writer keeps in its temporary names.
TEMP_KEY = 12


def temporary_keys(name: str) -> set[str]:
    """The output names (cut to :data:`TEMP_KEY` characters) whose temporary file ``name``
    could be: ``.NAME...`` or, for a writer's temporary inside another's (the image
    written under the metadata step's temporary name), ``..NAME...``; empty if ``name``
    is not a temporary one.  Sweeps of files left by killed writers match on this."""
    if not name.startswith(".") or not any(m in name for m in TEMP_MARKERS):
        return set()
    return {name[d:d + n] for d in (1, 2) for n in range(1, TEMP_KEY + 1)}


def new_file_mode_mask() -> int:
    """The process umask (what a plain ``open()`` would apply to a new file's mode)."""
    try:  # Linux: read it without the racy set-and-restore
        with open("/proc/self/status") as fh:
            for line in fh:
                if line.startswith("Umask:"):
                    return int(line.split()[1], 8)
    except (OSError, ValueError, IndexError):
        pass
    old = os.umask(0o022)
    os.umask(old)
    return old


def fsync_dir(directory: str | Path) -> None:
    """fsync a folder so a rename into it is durable; best effort (not every
    filesystem allows it)."""
    try:
        fd = os.open(directory, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


def publish(tmp: str | Path, dst: str | Path) -> None:
    """Make a finished temporary file ``dst``: fsync it, give it ``dst``'s current mode
    (or the umask default for a new file; mkstemp made it 0600), rename it onto
    ``dst`` and fsync the folder. Raises OSError."""
    try:
        mode = stat.S_IMODE(os.stat(dst).st_mode)
    except OSError:
        mode = 0o666 & ~new_file_mode_mask()
    os.chmod(tmp, mode)
    fd = os.open(tmp, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)
    os.replace(tmp, dst)
    fsync_dir(os.path.dirname(os.path.abspath(dst)))


@contextlib.contextmanager
def atomic_path(path: str | Path, suffix: str | None = None) -> Iterator[Path]:
    """Yield a temporary path beside ``path``; on success rename it onto ``path``.

    The temporary name keeps ``path``'s extension (or ``suffix``) so format-sniffing
    writers pick the right format. On any exception the temporary file is removed.
    """
    path = Path(path)
    suffix = path.suffix if suffix is None else suffix
    try:
        fd, tmp = tempfile.mkstemp(prefix=f".{path.stem[:40]}.", suffix=f".tmp{suffix}", dir=path.parent)
    except OSError as exc:
        raise write_error(f"cannot create a temporary file next to {path}: {exc.strerror or exc}", exc) from None
    os.close(fd)
    tmp_path = Path(tmp)
    try:
        yield tmp_path
        publish(tmp_path, path)
    except BaseException:
        with contextlib.suppress(OSError):
            tmp_path.unlink()
        raise


def atomic_write_bytes(path: str | Path, data: bytes) -> None:
    """Atomically write ``data`` to ``path``."""
    try:
        with atomic_path(path) as tmp:
            tmp.write_bytes(data)
    except OSError as exc:
        raise write_error(f"cannot write {path}: {exc.strerror or exc}", exc) from None


def atomic_write_text(path: str | Path, text: str) -> None:
    """Atomically write UTF-8 ``text`` to ``path``."""
    atomic_write_bytes(path, text.encode("utf-8"))
