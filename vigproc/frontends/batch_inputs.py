"""The inputs of a batch job: the image files of a folder or a list, and the local disk
its SQLite files need.

:class:`BatchError` (a job that cannot run) is defined here, the lowest of the batch
modules; :mod:`vigproc.frontends.batch` re-exports everything public of this module.
"""

from __future__ import annotations

import logging
import os
from dataclasses import dataclass
from pathlib import Path, PurePosixPath
from typing import Iterable

from vigproc.errors import EXIT_CODES, SETTINGS, VigprocError
from vigproc.pipeline.processor import IMAGE_SUFFIXES

log = logging.getLogger("vigproc.frontends.batch")  # the batch job's one logger name, as before the split

#: Filesystems SQLite must not live on (locking and WAL's shared memory need a local disk).
NETWORK_FS = frozenset({"nfs", "nfs4", "cifs", "smb3", "smbfs", "ncpfs", "afs", "9p", "lustre", "gpfs",
                        "ceph", "glusterfs", "fuse.glusterfs", "beegfs", "fuse.sshfs", "fuse.s3fs",
                        "fuse.gcsfuse", "fuse.rclone", "davfs", "fuse.cephfs", "orangefs", "pvfs2"})


class BatchError(VigprocError):
    """A batch job cannot run: bad file list, journal unusable or locked, cluster
    unreachable or misconfigured."""

    exit_code = EXIT_CODES["batch"]
    blame = SETTINGS


@dataclass(frozen=True)
class BatchItem:
    """One input file.

    Attributes
    ----------
    path : str
        Absolute path, as every worker opens it (and the journal records it).
    rel : str
        POSIX path mirrored under the output folder (no ``..``, not absolute).
    """

    path: str
    rel: str


def _hidden(name: str) -> bool:
    # dot files include the temporaries of atomic writes still in progress
    return name.startswith(".")


def collect_dir(root: str | os.PathLike[str], *, exclude: Iterable[str | os.PathLike[str]] = ()) -> list[BatchItem]:
    """Image files under ``root`` (recursive, sorted; hidden files and folders, and
    the ``exclude`` folders, skipped; symbolic links to folders not followed).

    Raises
    ------
    BatchError
        ``root`` is not a readable folder.
    """
    top = Path(root).resolve()
    if not top.is_dir():
        raise BatchError(f"not a folder: {root}")
    skip = {str(Path(e).resolve()) for e in exclude}
    items: list[BatchItem] = []
    errors: list[OSError] = []
    for dirpath, dirnames, filenames in os.walk(top, onerror=errors.append):
        dirnames[:] = sorted(d for d in dirnames if not _hidden(d) and os.path.join(dirpath, d) not in skip)
        rel_dir = PurePosixPath(*Path(dirpath).relative_to(top).parts)
        for name in sorted(filenames):
            if _hidden(name) or os.path.splitext(name)[1].lower() not in IMAGE_SUFFIXES:
                continue
            full = os.path.join(dirpath, name)
            if os.path.islink(full):  # as for folders: links are not followed (the journal refuses them too)
                log.warning("skipping symbolic link %s", full)
            elif os.path.isfile(full):
                items.append(BatchItem(full, str(rel_dir / name)))
    if errors and errors[0].filename and Path(errors[0].filename) == top:
        raise BatchError(f"cannot read folder {root}: {errors[0].strerror}")
    for e in errors:
        log.warning("skipping unreadable folder %s: %s", e.filename, e.strerror)
    return items


def read_list(list_file: str | os.PathLike[str]) -> tuple[list[BatchItem], list[str]]:
    """Files named in a list (UTF-8, one path per line; blank lines and lines starting
    with ``#`` ignored; relative paths are relative to the list's folder).

    Returns
    -------
    items : list of BatchItem
        Existing files, in list order, duplicates dropped; each mirrored under the
        output folder by its absolute path.
    missing : list of str
        Listed paths that are not files.

    Raises
    ------
    BatchError
        The list cannot be read or is not UTF-8 text.
    """
    lf = Path(list_file)
    try:
        text = lf.read_bytes().decode("utf-8")
    except OSError as exc:
        raise BatchError(f"cannot read file list {list_file}: {exc.strerror or exc}") from None
    except UnicodeDecodeError as exc:
        raise BatchError(f"file list {list_file} is not UTF-8 text (byte {exc.start})") from None
    base = lf.resolve().parent
    items, missing, seen = [], [], set()
    for line in text.splitlines():
        name = line.rstrip("\r")
        if not name.strip() or name.lstrip().startswith("#"):
            continue
        if "\x00" in name:
            missing.append(name.replace("\x00", "\\0"))
            continue
        full = os.path.realpath(os.path.join(base, name))  # a listed link means its target
        if full in seen:
            continue
        seen.add(full)
        if not os.path.isfile(full):
            missing.append(name)
            continue
        items.append(BatchItem(full, str(PurePosixPath(*Path(full).parts[1:]))))
    return items, missing


def collect(source: str | os.PathLike[str], outdir: str | os.PathLike[str]) -> tuple[list[BatchItem], list[str]]:
    """Inputs of a job: a folder (recursive, the output folder excluded) or a list file
    (listed files inside the output folder skipped).

    Outputs are never inputs: a rerun would otherwise process the outputs of the run
    before (``x.tif.corrected.tif.corrected.tif`` ...) and a listed output could be
    replaced while it is read.

    Returns
    -------
    items, missing
        See :func:`collect_dir` and :func:`read_list`.

    Raises
    ------
    BatchError
        Missing source, the output folder is the source folder, unreadable list, or
        no images at all.
    """
    src = Path(source)
    out = Path(outdir).resolve()
    if src.is_dir():
        if src.resolve() == out:
            raise BatchError(f"the output folder cannot be the source folder itself ({str(out)!r}); "
                             "pass another -o")
        items, missing = collect_dir(src, exclude=[out]), []
    elif src.is_file():
        items, missing = read_list(src)
        keep = [i for i in items if not Path(i.path).is_relative_to(out)]  # listed paths are resolved
        if len(keep) < len(items):
            log.warning("skipping %d listed file(s) inside the output folder %s", len(items) - len(keep), out)
            items = keep
    else:
        raise BatchError(f"no such folder or file list: {source}")
    if not items and not missing:
        raise BatchError(f"no images found in {source}")
    return items, missing


def filesystem_type(path: str | os.PathLike[str]) -> str | None:
    """The type (``ext4``, ``nfs4``, ...) of the filesystem holding ``path`` (or its
    nearest existing parent), from ``/proc/self/mounts``; None where unknown."""
    p = Path(path).resolve()
    while not p.exists() and p != p.parent:
        p = p.parent
    try:
        mounts = Path("/proc/self/mounts").read_text().splitlines()
    except OSError:
        return None
    best, best_type = "", None
    for line in mounts:
        parts = line.split()
        if len(parts) < 3:
            continue
        mnt = parts[1].replace("\\040", " ")
        if (str(p) == mnt or str(p).startswith(mnt.rstrip("/") + "/")) and len(mnt) >= len(best):
            best, best_type = mnt, parts[2]
    return best_type


def check_local_disk(path: str | os.PathLike[str], what: str) -> None:
    """Refuse an SQLite file on a network filesystem (locking and WAL's shared
    memory are not reliable there).

    Raises
    ------
    BatchError
    """
    fs = filesystem_type(path)
    if fs in NETWORK_FS:
        raise BatchError(f"{what} {path} would be on a {fs} network filesystem; SQLite needs a local disk "
                         f"(pass --journal PATH on a local disk)")

