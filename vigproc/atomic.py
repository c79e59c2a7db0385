"""Atomic file output: write to a temporary file in the same folder, fsync, rename.

A crash or kill leaves either the old file or the new one, never a half-written one.
"""

from __future__ import annotations

import contextlib
import os
import stat
import tempfile
from pathlib import Path
from typing import Any, Iterator

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


def publish(tmp: str | Path, dst: str | Path, *, mode: int | None = None, chmod: bool = True,
            sync: bool = True) -> None:
    """Make a finished temporary file ``dst``: give it ``mode`` (by default ``dst``'s current
    mode, or the umask default for a new file; mkstemp made it 0600; none with
    ``chmod=False``, e.g. for a hard link of an input), fsync it, rename it onto ``dst``
    and fsync the folder (neither fsync with ``sync=False``: a file worthless after a
    power cut). Raises OSError."""
    if chmod:
        if mode is None:
            try:
                mode = stat.S_IMODE(os.stat(dst).st_mode)
            except OSError:
                mode = 0o666 & ~new_file_mode_mask()
        os.chmod(tmp, mode)
    if sync:
        fd = os.open(tmp, os.O_RDONLY)
        try:
            os.fsync(fd)
        finally:
            os.close(fd)
    os.replace(tmp, dst)
    if sync:
        fsync_dir(os.path.dirname(os.path.abspath(dst)))


def temporary_name(dst: str | Path, *, marker: str = ".tmp-", suffix: str = "", keep: int = 100,
                   prefix: str | None = None, create: bool = True) -> str:
    """A new temporary file beside ``dst``, named ``.NAME{marker}XXXXXXXX{suffix}`` (NAME:
    ``dst``'s name cut to ``keep`` characters, so a temporary inside a temporary stays
    within NAME_MAX; or ``prefix`` instead of ``.NAME{marker}``).  Sweeps of killed
    writers' leftovers (:func:`temporary_keys`) match on this form.

    Parameters
    ----------
    create : bool
        Create it empty (mkstemp, mode 0600), else only pick a free name (for
        :func:`os.link`, which never overwrites).

    Returns
    -------
    str
        Its path.  Raises OSError or ValueError (a name with a NUL byte).
    """
    directory = os.path.dirname(os.path.abspath(dst))
    if prefix is None:
        prefix = f".{os.path.basename(os.fspath(dst))[:keep]}{marker}"
    if not create:
        return tempfile.mktemp(prefix=prefix, suffix=suffix, dir=directory)
    fd, tmp = tempfile.mkstemp(prefix=prefix, suffix=suffix, dir=directory)
    os.close(fd)
    return tmp


@contextlib.contextmanager
def replacing(dst: str | Path, *, what: str | None = None, leftovers: tuple[str, ...] = (),
              mode: int | None = None, chmod: bool = True, sync: bool = True, **name: Any) -> Iterator[str]:
    """Yield a temporary file beside ``dst`` (:func:`temporary_name`, taking ``name``'s
    keywords); when the block ends normally :func:`publish` it onto ``dst`` (with ``mode``,
    ``chmod``, ``sync``), on any exception remove it and the files named by it plus each
    of ``leftovers`` (``"_exiftool_tmp"``: exiftool's own, if it was killed).

    The temporary may itself be the ``dst`` of an inner :func:`replacing` (a temporary
    inside a temporary: pass the outer a short ``keep``).  With ``what`` a failure to
    make the temporary raises :func:`vigproc.errors.write_error` (``"{what}: cannot create
    a temporary file in ..."``), else its OSError; errors of the block and of the rename
    pass unchanged.
    """
    try:
        tmp = temporary_name(dst, **name)
    except (OSError, ValueError) as exc:
        if what is None:
            raise
        directory = os.path.dirname(os.path.abspath(dst))
        raise write_error(f"{what}: cannot create a temporary file in {directory!r}: {exc}", exc) from None
    try:
        yield tmp
        publish(tmp, dst, mode=mode, chmod=chmod, sync=sync)
    except BaseException:
        for p in (tmp, *(tmp + x for x in leftovers)):
            with contextlib.suppress(OSError):
                os.unlink(p)
        raise


@contextlib.contextmanager
def atomic_path(path: str | Path, suffix: str | None = None) -> Iterator[Path]:
    """Yield a temporary path beside ``path``; on success rename it onto ``path``.

    The temporary name keeps ``path``'s extension (or ``suffix``) so format-sniffing
    writers pick the right format. On any exception the temporary file is removed.
    """
    path = Path(path)
    suffix = path.suffix if suffix is None else suffix
    with replacing(path, what=f"cannot write {path}", prefix=f".{path.stem[:40]}.", suffix=f".tmp{suffix}") as tmp:
        yield Path(tmp)


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
