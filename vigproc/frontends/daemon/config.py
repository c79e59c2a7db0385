"""What ``vigproc watch`` was asked to do (:class:`WatchConfig`) and which files it is
about: the names it takes (:func:`is_candidate_name`), the names it ignores
(:func:`is_temporary_name`, :data:`IGNORED_DIRS`) and the flat name a quarantined file
gets (:func:`output_stem`)."""

from __future__ import annotations

import hashlib
import logging
import os
import stat
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from vigproc.errors import SETTINGS, VigprocError
from vigproc.io.formats import IMAGE_SUFFIXES
from vigproc.pipeline.faults import DEFAULT_MIN_FREE
from vigproc.pipeline.processor import percent_encode, shorten_stem
from vigproc.stores.journal import Fingerprint
from vigproc.stores.retry import DEFAULT_MAX_ATTEMPTS, DEFAULT_MAX_CRASHES, DEFAULT_RETRY_BASE, DEFAULT_RETRY_CAP

#: Suffixes of files that writers are still filling (browsers, torrent clients, scp/WinSCP,
#: download managers, editors): ignored until renamed.
TEMP_SUFFIXES = frozenset({
    ".tmp", ".temp", ".part", ".partial", ".crdownload", ".download", ".opdownload", ".!ut", ".!qb", ".!bt",
    ".filepart", ".aria2", ".swp", ".swx", ".lock", ".dwl", ".dwl2", ".sb", ".bak", ".inprogress", ".uploading",
})
#: Folder names never descended into (NAS snapshots and thumbnails, recycle bins).
IGNORED_DIRS = frozenset({"@eaDir", "#recycle", "#snapshot", "$RECYCLE.BIN", "System Volume Information",
                          "lost+found", "__MACOSX"})
#: Sidecar of a quarantined file: why it is there.
REASON_SUFFIX = ".reason.json"


class WatchError(VigprocError):
    """The watch folder cannot be run as asked (bad folders, another daemon on the job, ...)."""

    exit_code = 1
    blame = SETTINGS


# ------------------------------------------------------------------ names
def is_temporary_name(name: str) -> bool:
    """Whether a file name is a writer's temporary name, ignored until renamed.

    Dotfiles (rsync's ``.name.XXXXXX``, our own and OpenImageIO's ``.x.tmp.tif``,
    macOS ``._x``, LibreOffice ``.~lock``), Office's ``~$x``, editor backups
    ``x~``, and the suffixes of :data:`TEMP_SUFFIXES` (``x.jpg.part``,
    ``x.jpg.crdownload``, ``x.!ut``...).

    Examples
    --------
    >>> [is_temporary_name(n) for n in ("a.jpg", ".a.jpg.Xy12Zq", "a.jpg.part", "~$a.jpg", "a.jpg~", "-a b.jpg")]
    [False, True, True, True, True, False]
    """
    if not name or name.startswith((".", "~$")) or name.endswith("~"):
        return True
    low = name.lower()
    return any(low.endswith(s) for s in TEMP_SUFFIXES)


def is_candidate_name(name: str) -> bool:
    """An image suffix the pipeline reads, and not a temporary name."""
    return not is_temporary_name(name) and os.path.splitext(name)[1].lower() in IMAGE_SUFFIXES


def output_stem(rel: str) -> str:
    """A deterministic, distinct flat name for an input's path relative to the watch
    folder: the name a quarantined file gets in the (flat) quarantine folder. Outputs
    follow :func:`vigproc.pipeline.processor.output_location` (sub-folders mirrored), as in every
    front end.

    The relative path is flattened into one name, extension kept (``a/x.jpg`` →
    ``a%2Fx.jpg``, so ``a/x.jpg``, ``b/x.jpg`` and ``a/x.png`` differ), with ``%``,
    ``/``, control characters, bytes that are not UTF-8 and a leading dot
    percent-encoded: the mapping is one-to-one and the same after a restart.
    Names over :data:`vigproc.pipeline.processor.MAX_STEM_BYTES` are cut and given a hash of the
    full path (:func:`vigproc.pipeline.processor.shorten_stem`).

    Examples
    --------
    >>> output_stem("a/x.jpg"), output_stem("100%.jpg"), output_stem("new\\nline.png")
    ('a%2Fx.jpg', '100%25.jpg', 'new%0Aline.png')
    """
    stem = percent_encode(rel, also="%", leading=".")  # "%" too: one-to-one, so names never collide
    return shorten_stem(stem, os.fsencode(rel))


def _signature(path: str) -> tuple[int, int, int] | None:
    """(size, mtime_ns, inode) of a regular file, None if gone or not a regular file
    (symbolic links are not followed)."""
    try:
        st = os.lstat(path)
    except OSError:
        return None
    if not stat.S_ISREG(st.st_mode):
        return None
    return st.st_size, st.st_mtime_ns, st.st_ino


# ------------------------------------------------------------------ config
#: Environment: the folder of the daemons' per-folder locks (default: the user's state folder).
ENV_LOCK_DIR = "VIGPROC_LOCK_DIR"


def job_lock_dir() -> Path:
    """Where the per-folder locks of ``vigproc watch`` live: ``$VIGPROC_LOCK_DIR``, else
    ``<user state dir>/vigproc/locks`` (platformdirs): outside the output folder and beside
    no journal, so neither ``--journal elsewhere`` nor deleting the output folder frees it."""
    env = os.environ.get(ENV_LOCK_DIR)
    if env:
        return Path(env).expanduser().resolve()
    import platformdirs

    return Path(platformdirs.user_state_dir("vigproc", appauthor=False)).resolve() / "locks"


def folders_lock_name(in_dir: Path, out_dir: Path) -> str:
    """The lock file's name for a daemon on the resolved ``in_dir`` and ``out_dir``: one
    daemon per pair, whatever its journal, job name or mode."""
    key = os.fsencode(in_dir) + b"\0" + os.fsencode(out_dir)
    return f"watch-{hashlib.sha256(key).hexdigest()[:24]}.lock"


@dataclass
class WatchConfig:
    """Everything ``vigproc watch`` was asked to do (see the command's help)."""

    in_dir: Path
    out_dir: Path
    settings: dict[str, Any]  # vigproc.pipeline.processor.Settings fields
    workers: int = 1
    poll: float | None = None  # seconds between polls; None: native events
    settle: float = 2.0
    journal: Path | None = None
    job: str | None = None
    quarantine_dir: Path | None = None
    archive_dir: Path | None = None
    profile_db: str | None = None
    status_file: Path | None = None
    rescan: float = 300.0
    timeout: float = 900.0
    max_attempts: int = DEFAULT_MAX_ATTEMPTS
    max_crashes: int = DEFAULT_MAX_CRASHES
    retry_base: float = DEFAULT_RETRY_BASE
    retry_cap: float = DEFAULT_RETRY_CAP
    retry_quarantined: bool = False
    min_free: int = DEFAULT_MIN_FREE  # bytes: a write failure with less free is a full disk
    log_json: bool = False
    log_level: int = logging.INFO

    def __post_init__(self) -> None:
        self.in_dir = Path(self.in_dir).expanduser().resolve()
        self.out_dir = Path(self.out_dir).expanduser().resolve()
        if self.quarantine_dir is not None:
            self.quarantine_dir = Path(self.quarantine_dir).expanduser().resolve()
        if self.archive_dir is not None:
            self.archive_dir = Path(self.archive_dir).expanduser().resolve()
        if self.job is None:
            self.job = f"watch:{self.settings.get('mode', 'correct')}:{self.in_dir}->{self.out_dir}"
        tag = hashlib.sha256(self.job.encode("utf-8", "surrogateescape")).hexdigest()[:10]
        self.journal = (Path(self.journal).expanduser().resolve() if self.journal is not None
                        else self.out_dir / ".vigproc-watch.sqlite")
        if self.status_file is None:
            self.status_file = self.out_dir / f".vigproc-watch-{tag}.status.json"
        self.status_file = Path(self.status_file).expanduser().resolve()
        self.lock_file = self.journal.with_name(f"{self.journal.name}.{tag}.lock")
        self.folders_lock_file = job_lock_dir() / folders_lock_name(self.in_dir, self.out_dir)

    def validate(self) -> None:
        """Check the folders and numbers; create the output folders.

        Raises
        ------
        WatchError
        """
        if not self.in_dir.is_dir():
            raise WatchError(f"watch folder {str(self.in_dir)!r} does not exist or is not a folder")
        if not (1 <= self.workers <= 256):
            raise WatchError(f"--workers must be between 1 and 256, got {self.workers}")
        for name, v in (("--settle", self.settle), ("--rescan", self.rescan), ("--timeout", self.timeout),
                        ("--retry-base", self.retry_base)):
            if not (v >= 0 and v < float("inf")):
                raise WatchError(f"{name} must be a non-negative number of seconds, got {v}")
        if self.poll is not None and not (0 < self.poll < float("inf")):
            raise WatchError(f"--poll must be a positive number of seconds, got {self.poll}")
        if self.timeout <= 0 or self.rescan <= 0:
            raise WatchError("--timeout and --rescan must be positive")
        if self.max_attempts < 1 or self.max_crashes < 1:
            raise WatchError("--max-attempts and --max-crashes must be at least 1")
        if not (0 <= self.min_free < 2**63):
            raise WatchError(f"--min-free must be a non-negative number of bytes, got {self.min_free}")
        if self.archive_dir is not None and self.archive_dir == self.quarantine_dir:
            raise WatchError(f"the archive and quarantine folders must differ ({str(self.archive_dir)!r})")
        for name, d in (("output", self.out_dir), ("quarantine", self.quarantine_dir), ("archive", self.archive_dir)):
            if d is None:
                continue
            if d == self.in_dir:
                raise WatchError(f"the {name} folder cannot be the watch folder itself ({str(d)!r})")
            if name != "output" and d == self.out_dir:  # inputs would land among the outputs
                raise WatchError(f"the {name} folder cannot be the output folder ({str(d)!r})")
            try:
                d.mkdir(parents=True, exist_ok=True)
            except OSError as exc:
                raise WatchError(f"cannot create the {name} folder {str(d)!r}: {exc.strerror or exc}") from None
            if not os.access(d, os.W_OK | os.X_OK):
                raise WatchError(f"the {name} folder {str(d)!r} is not writable")

    def excluded_dirs(self) -> tuple[str, ...]:
        """Folders inside the watch folder that hold our own files (the journal and status
        files need no exclusion: they are not images)."""
        out = []
        for d in (self.out_dir, self.quarantine_dir, self.archive_dir):
            if d is not None and _inside(str(d), str(self.in_dir)):
                out.append(str(d))
        return tuple(out)


def _inside(path: str, folder: str) -> bool:
    return path == folder or path.startswith(folder.rstrip(os.sep) + os.sep)




@dataclass
class RunFlags:
    """What the signals asked of a running daemon (set by its handlers, read by its loop
    and its scheduler)."""

    stop: str | None = None  # the name of the first SIGTERM/SIGINT: drain, then stop
    abort: bool = False  # a second one: stop now, handing the files in progress back
    rescan: bool = False  # SIGHUP: look at the whole folder again


@dataclass
class _Task:
    """A file claimed in the journal and sent to a worker: what the scheduler and the
    recorder pass between them."""

    id: int
    path: str
    rel: str
    stem: str
    fp: Fingerprint
    started: float | None = None  # monotonic, when the worker said it began
    probe: bool = False  # sent while paused for a full disk, to see whether there is room again
    ahead: bool = False  # its worker is reading it ahead, while the task before it runs
