"""The watch-folder daemon: every complete image dropped into a folder is processed exactly once.

How a file goes through
-----------------------
1. *Seen*: a file system event (watchdog's native observer, or its polling observer
   for network shares) or a rescan of the folder (at start, every ``rescan``
   seconds, on SIGHUP) names a path.  Temporary names of common writers
   (:func:`is_temporary_name`), non-image suffixes, symbolic links, and our own
   output, quarantine and archive folders are ignored.
2. *Settled*: its size, mtime and inode did not change for ``settle`` seconds
   (:class:`SettleTracker`: two looks that far apart).
3. *Claimed*: the main process fingerprints it (size, mtime, SHA-256) and claims it
   in the :class:`~vigproc.stores.journal.Journal`; a path whose content is already done
   or quarantined is skipped, so duplicate events, rescans and restarts are
   harmless.
4. *Processed* by a worker process (:func:`_worker_main`, one
   :class:`~vigproc.pipeline.processor.Processor` each) with deterministic output names
   (:func:`vigproc.pipeline.processor.output_location`: the input's sub-folders mirrored under
   the output folder, its name kept); outputs and the JSON sidecar are published
   atomically.
5. *Recorded*: ``done`` (then optionally moved to the archive folder), ``retry``
   after a transient error (locked file: exponential backoff), or ``quarantined``
   with the reason (optionally moved to the quarantine folder; a file that fails to
   decode while it is still young gets one more look first: a writer that paused
   longer than ``settle`` leaves an incomplete, not a corrupt, file).  If the file
   changed while it was processed, it is simply seen again.

Whose fault (:mod:`vigproc.pipeline.faults`, shared with batch runs and ``vigproc correct``):
only what is wrong with the photo quarantines it.  A failure to write an output is
the output side's: retried without limit, never quarantined or moved.  A full output
disk (ENOSPC/EDQUOT, or a write failure -- OpenImageIO's ``TIFFWriteScanline failed``,
exiftool's ``Error writing image data`` -- while the output file system is under
``min_free``) *pauses* the daemon: the file goes back without an attempt counted,
nothing more is handed out, the status says ``paused`` (output disk full) and the log
``disk-full``; it resumes as soon as the free space has grown, or when a probe (one
file, after a backoff that doubles up to ``retry_cap``) is written.

Crash safety
------------
The journal is updated in one fsynced transaction per step (one that fails, e.g. on
a full disk, is retried until it succeeds).  After a kill -9 the next start calls
:meth:`~vigproc.stores.journal.Journal.recover`: files left running become pending *without*
a crash charge -- the daemon's own death is not the files' fault, and decoding
happens in workers, never in the daemon -- then it removes the temporary files of
the unfinished files and rescans the folder, so files dropped while the daemon was
down are found.  A worker that crashes or hangs while the daemon lives charges its
file a crash (:meth:`~vigproc.stores.journal.Journal.crashed`; quarantined at
``max_crashes``); its process group (exiftool included) is killed and its
temporaries removed.  Workers raise their OOM score, so that a file exhausting
memory takes its worker, not the daemon.  A sidecar
that already records the same input content and settings (a crash after the sidecar
but before the journal) is taken as the result instead of processing the file again.
In ``learn`` mode each frame content is pooled at most once: the input's SHA-256 is
the ``frame_id`` of :meth:`~vigproc.stores.profiles.ProfileStore.learn`, recorded in the
store's own transaction.

Workers are processes (``spawn``), not threads: a decoder crash on a hostile file
kills one worker, not the daemon, and the GIL is not shared.  Each leads a process
group of its own (a terminal's Ctrl-C does not reach it or its exiftool), ignores
SIGINT/SIGTERM (the main process drains them) and dies with the main process
(``PR_SET_PDEATHSIG`` on Linux; they also exit when their pipe closes), and so does
its exiftool.  An exiftool failure while the daemon stops gives the file back
without an attempt: a stop signal may have killed it.
"""

from __future__ import annotations

import contextlib
import errno
import hashlib
import json
import logging
import multiprocessing as mp
import multiprocessing.connection as mpc
import os
import queue
import shutil
import signal
import socket
import stat
import sys
import tempfile
import threading
import time
from collections import deque
from dataclasses import dataclass, field
from datetime import datetime, timezone
from pathlib import Path
from typing import Any, Callable, Iterable

from vigproc.errors import VigprocError, one_line
from vigproc.pipeline.faults import (
    CRASH,
    DEFAULT_MIN_FREE,
    DISK_FULL,
    PERMANENT,
    TRANSIENT,
    attempt_limit,
    classify_error,
    disk_space,
)
from vigproc.stores.journal import (FileChangedError, Fingerprint, FingerprintError, Journal, JournalError, boot_id,
                             fingerprint, runner_identity)
from vigproc.pipeline.processor import output_location, percent_encode, shorten_stem, sweep_temporaries
from vigproc.processes import die_with_parent

__all__ = [
    "Daemon",
    "SettleTracker",
    "WatchConfig",
    "WatchError",
    "classify_error",
    "is_temporary_name",
    "output_stem",
    "read_status",
]

log = logging.getLogger("vigproc.watch")

#: Image suffixes the daemon takes (the pipeline's).
_IMAGE_SUFFIXES: frozenset[str] | None = None

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


def _image_suffixes() -> frozenset[str]:
    global _IMAGE_SUFFIXES
    if _IMAGE_SUFFIXES is None:  # the pipeline imports numba: only when first needed
        from vigproc.pipeline.processor import IMAGE_SUFFIXES

        _IMAGE_SUFFIXES = IMAGE_SUFFIXES
    return _IMAGE_SUFFIXES


def is_candidate_name(name: str) -> bool:
    """An image suffix the pipeline reads, and not a temporary name."""
    return not is_temporary_name(name) and os.path.splitext(name)[1].lower() in _image_suffixes()


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


# ------------------------------------------------------------------ errors
# The kinds of failure and who is to blame are one policy shared with batch runs and
# `vigproc correct` (vigproc.pipeline.faults); re-exported here, where they were first defined.
#: Errors that a truncated (still being written) file also gives.
_READ_ERRORS = frozenset({"ImageReadError", "UnsupportedFormatError", "InvalidImageError"})


# ------------------------------------------------------------------ settling
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


class SettleTracker:
    """Files seen but perhaps still being written.

    A file is *ripe* when two looks at least ``settle`` seconds apart see the same
    size, mtime and inode: a writer that pauses for less than ``settle`` between
    chunks keeps it from ripening, a rename-into-place starts its clock afresh.

    Parameters
    ----------
    settle : float
        Seconds.
    clock : callable
        Monotonic clock (injectable for tests).
    """

    def __init__(self, settle: float, clock: Callable[[], float] = time.monotonic) -> None:
        self.settle = float(settle)
        self._clock = clock
        self._files: dict[str, tuple[tuple[int, int, int], float]] = {}

    def see(self, path: str) -> None:
        """Start (or keep) watching ``path``; a changed file restarts its clock."""
        sig = _signature(path)
        if sig is None:
            self._files.pop(path, None)
            return
        old = self._files.get(path)
        if old is None or old[0] != sig:
            self._files[path] = (sig, self._clock())

    def forget(self, path: str) -> None:
        self._files.pop(path, None)

    def ripe(self) -> list[str]:
        """Files unchanged for ``settle`` seconds, oldest first; they leave the tracker."""
        now = self._clock()
        out = []
        for path, (sig, since) in sorted(self._files.items(), key=lambda kv: kv[1][1]):
            if now - since < self.settle:
                continue
            cur = _signature(path)
            if cur is None:
                del self._files[path]
            elif cur != sig:
                self._files[path] = (cur, now)
            else:
                del self._files[path]
                out.append(path)
        return out

    def __len__(self) -> int:
        return len(self._files)

    def __contains__(self, path: object) -> bool:
        return path in self._files


# ------------------------------------------------------------------ config
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
    max_attempts: int = 5
    max_crashes: int = 3
    retry_base: float = 5.0
    retry_cap: float = 600.0
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


# ------------------------------------------------------------------ logging
class JsonLogFormatter(logging.Formatter):
    """One JSON object per line: ts, level, logger, msg and the record's ``fields``."""

    def format(self, record: logging.LogRecord) -> str:
        d = {"ts": datetime.fromtimestamp(record.created, timezone.utc).isoformat(timespec="milliseconds")
             .replace("+00:00", "Z"),
             "level": record.levelname.lower(), "logger": record.name, "pid": record.process,
             "msg": record.getMessage()}
        d.update(getattr(record, "fields", None) or {})
        if record.exc_info:
            d["exc"] = self.formatException(record.exc_info)
        return json.dumps(d, default=str, ensure_ascii=True)


class TextLogFormatter(logging.Formatter):
    """``time level process: message``, one line per record: control characters of
    hostile file names are escaped, so a name cannot forge log lines."""

    def __init__(self) -> None:
        super().__init__("%(asctime)s %(levelname)s %(processName)s: %(message)s")

    def format(self, record: logging.LogRecord) -> str:
        return one_line(super().format(record))


def configure_logging(json_lines: bool, level: int) -> None:
    """Log to stderr: JSON lines or ``time level message``; replaces earlier handlers."""
    handler = logging.StreamHandler(sys.stderr)
    handler.setFormatter(JsonLogFormatter() if json_lines else TextLogFormatter())
    logging.basicConfig(level=level, handlers=[handler], force=True)


def _ev(event: str, **fields: Any) -> dict[str, Any]:
    return {"fields": {"event": event, **{k: v for k, v in fields.items() if v is not None}}}


# ------------------------------------------------------------------ worker process
def _no_op(_signum: int, _frame: Any) -> None:
    pass


def _read_sidecar(sidecar: Path) -> dict[str, Any] | None:
    """An earlier run's sidecar as a dict, or None when it is missing or unreadable."""
    try:
        with open(sidecar, "rb") as fh:
            d = json.loads(fh.read(1 << 22))
    except (OSError, ValueError):
        return None
    return d if isinstance(d, dict) else None


def _sidecar_result(sidecar: Path, fp: Fingerprint, settings: dict[str, Any]) -> dict[str, Any] | None:
    """The result recorded by an earlier run's sidecar for this very content and these
    settings (its outputs still present), or None."""
    d = _read_sidecar(sidecar)
    if d is None or d.get("input_sha256") != fp.sha256 or d.get("settings") != settings:
        return None
    if d.get("output") and not os.path.isfile(d["output"]):
        return None
    return d


def _summary(d: dict[str, Any], sidecar: Path) -> dict[str, Any]:
    verdict = d.get("verdict")
    return {k: v for k, v in {
        "output": d.get("output"), "sidecar": str(sidecar), "picture": d.get("picture"), "source": d.get("source"),
        "applied": d.get("applied"), "profile": d.get("profile"), "seconds": d.get("seconds"),
        "lens_id": (d.get("lens") or {}).get("lens_id"),
        "verdict": (verdict.get("verdict", verdict.get("label")) if isinstance(verdict, dict) else verdict),
    }.items() if v is not None}


def _worker_main(conn: mpc.Connection, settings: dict[str, Any], profile_db: str | None,
                 log_json: bool, log_level: int, min_free: int = DEFAULT_MIN_FREE) -> None:
    """A worker process: one Processor, tasks in, results out, until told to stop or
    the daemon goes away."""
    die_with_parent()  # even when the daemon is killed with SIGKILL
    # a file whose decoding exhausts memory must cost its worker, not the daemon: the
    # daemon then lives to charge the file the crash (the OOM killer picks the top score)
    with contextlib.suppress(OSError), open("/proc/self/oom_score_adj", "w") as fh:
        fh.write("500")
    # The daemon drains us.  A process group of our own keeps a terminal's Ctrl-C (sent to
    # the whole foreground group) from us and from the exiftool we start, which would die of it.
    with contextlib.suppress(OSError):
        os.setpgrp()
    for sig in (signal.SIGINT, signal.SIGTERM):  # systemd may signal every process
        # a no-op handler, not SIG_IGN: an ignored signal stays ignored across exec, and our
        # exiftool would then outlive us (pyexiftool has it sent SIGTERM when we die)
        signal.signal(sig, _no_op)
        signal.siginterrupt(sig, False)
    configure_logging(log_json, log_level)
    wlog = logging.getLogger("vigproc.watch.worker")
    store = proc = None
    try:
        from vigproc.pipeline.processor import SIDECAR_SUFFIX, Processor, Settings, safe_output

        s = Settings(**settings)
        if s.needs_store:
            from vigproc.stores.profiles import ProfileStore

            store = ProfileStore(profile_db)
        proc = Processor(s, store=store)
    except Exception as exc:  # a worker that cannot start is fatal for the daemon: say why
        conn.send(("fatal", None, f"{type(exc).__name__}: {exc}"))
        return
    try:
        conn.send(("ready", None, os.getpid()))
        while True:
            try:
                msg = conn.recv()
            except (EOFError, OSError):
                break
            if msg[0] == "stop":
                break
            _, task_id, path, out_root, rel, fpd, extra = msg
            conn.send(("start", task_id, None))
            fp = Fingerprint.from_dict(fpd)
            try:
                # the one output policy of every front end: sub-folders mirrored, the input's name
                outdir, stem = output_location(out_root, rel)
                sidecar = safe_output(outdir, stem, SIDECAR_SUFFIX)
                old = _sidecar_result(sidecar, fp, settings)
                if old is not None:  # done before a crash, not yet in the journal: do not repeat
                    wlog.info("%s: already done by an earlier run (sidecar %s)", path, sidecar)
                    conn.send(("ok", task_id, {**_summary(old, sidecar), "recovered": True}))
                    continue
                res = proc.process_file(path, outdir, stem, extra=extra,
                                        frame_id=fp.sha256 if s.mode == "learn" else None)
                conn.send(("ok", task_id, _summary(res.to_dict(), sidecar)))
            except Exception as exc:  # noqa: BLE001 - every failure becomes a per-file record
                # judged here, at once: a failed writer's temporary is gone, so the output
                # disk's free space is what the next file would find
                fault = classify_error(exc, outdir, min_free=min_free)
                if fault.kind == PERMANENT and fault.reason.startswith("internal error"):
                    wlog.debug("internal error on %s", path, exc_info=True)
                conn.send(("error", task_id, {"kind": fault.kind, "reason": fault.reason, "type": type(exc).__name__,
                                              "free_bytes": fault.space.free_bytes if fault.space else None}))
    except (BrokenPipeError, EOFError, OSError):
        pass  # the daemon is gone
    finally:
        with contextlib.suppress(Exception):
            proc.close()
        if store is not None:
            with contextlib.suppress(Exception):
                store.close()


def _kill_group(process: Any) -> None:
    """SIGKILL a worker and what it started (exiftool): it leads a process group of its own."""
    pid = process.pid
    if pid is not None and pid != os.getpgrp():  # never our own group (if the worker could not leave it)
        with contextlib.suppress(OSError):
            os.killpg(pid, signal.SIGKILL)
    with contextlib.suppress(OSError, ValueError):
        process.kill()


@dataclass
class _Task:
    id: int
    path: str
    rel: str
    stem: str
    fp: Fingerprint
    started: float | None = None  # monotonic, when the worker said it began
    probe: bool = False  # sent while paused for a full disk, to see whether there is room again


@dataclass
class _DiskPause:
    """The daemon stopped handing out files: the output disk is full (every file would
    fail there).  It resumes when the free space has grown, or when a probe (one file
    sent after a backoff delay) is written."""

    reason: str
    since: float  # epoch seconds
    free_bytes: int | None  # the output file system's free bytes when it was found full
    delay: float  # seconds until the next probe; doubles after each failed probe
    probe_at: float  # monotonic
    next_look: float = 0.0  # monotonic: next look at the free space
    probing: bool = False  # a probe is in flight
    held: set[str] = field(default_factory=set)  # files given back for the disk, not charged


@dataclass
class _Worker:
    name: str
    process: Any
    conn: mpc.Connection
    ready: bool = False
    pid: int | None = None  # as the worker said when ready
    tasks: list[_Task] = field(default_factory=list)  # sent, in order; the first may be running
    stopping: bool = False


# ------------------------------------------------------------------ systemd
def _sd_notify(message: str) -> None:
    """Tell systemd (Type=notify) how we are; no-op outside systemd."""
    addr = os.environ.get("NOTIFY_SOCKET")
    if not addr:
        return
    if addr.startswith("@"):
        addr = "\0" + addr[1:]
    with contextlib.suppress(OSError), socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM) as s:
        s.connect(addr)
        s.sendall(message.encode("utf-8", "replace"))


# ------------------------------------------------------------------ file moves
def _move(src: str, dst_dir: Path, name: str, fp: Fingerprint | None,
          before: Callable[[Path], None] | None = None) -> Path:
    """Move ``src`` into ``dst_dir`` as ``name`` without overwriting a different file
    (a clash gets the content hash in its name) and without ever losing it: a hard
    link (or an atomically published copy across file systems) is made first, the
    source unlinked after.  If ``name`` already holds this very content (a move
    interrupted after the link), the source is just unlinked.

    ``before(dst)``, if given, is called with the final destination before the file
    gets there (a sidecar named after the file, present whenever the file is)."""
    dst_dir.mkdir(parents=True, exist_ok=True)
    dst = dst_dir / name
    if fp is not None:
        try:
            if fingerprint(dst).same_content(fp):
                if before is not None:  # again: the interrupted move may have lost it
                    before(dst)
                os.unlink(src)
                return dst
        except FingerprintError:
            pass
        if os.path.lexists(dst):
            root, ext = os.path.splitext(name)
            dst = dst_dir / f"{root}.{fp.sha256[:12]}{ext}"
    if before is not None:
        before(dst)
    try:
        os.link(src, dst, follow_symlinks=False)
    except FileExistsError:
        if fp is not None and fingerprint(dst).same_content(fp):
            os.unlink(src)
            return dst
        raise
    except OSError as exc:
        if exc.errno not in (errno.EXDEV, errno.EPERM, errno.EMLINK, errno.ENOTSUP, errno.EOPNOTSUPP):
            raise
        from vigproc.atomic import publish

        fd, tmp = tempfile.mkstemp(prefix=".vigproc-move.", dir=dst_dir)
        os.close(fd)
        try:
            shutil.copyfile(src, tmp)
            shutil.copystat(src, tmp)
            publish(tmp, dst)
        except BaseException:
            with contextlib.suppress(OSError):
                os.unlink(tmp)
            raise
    os.unlink(src)
    return dst


# ------------------------------------------------------------------ status
def read_status(cfg: WatchConfig) -> dict[str, Any]:
    """What ``vigproc watch --status`` shows: the daemon's status file (if any), whether
    it is running (it holds the job lock) and the journal's counts."""
    out: dict[str, Any] = {"in_dir": str(cfg.in_dir), "out_dir": str(cfg.out_dir), "job": cfg.job,
                           "journal": str(cfg.journal), "running": False}
    if cfg.lock_file.exists():
        import fcntl

        try:
            fd = os.open(cfg.lock_file, os.O_RDONLY)
        except OSError:
            fd = -1
        if fd >= 0:
            try:
                fcntl.flock(fd, fcntl.LOCK_SH | fcntl.LOCK_NB)
            except OSError:
                out["running"] = True
            finally:
                os.close(fd)
    try:
        with open(cfg.status_file, "rb") as fh:
            st = json.loads(fh.read(1 << 20))
        if isinstance(st, dict):
            out["daemon"] = st
            out["age_s"] = round(max(time.time() - float(st.get("updated_epoch", 0)), 0.0), 1)
    except (OSError, ValueError):
        pass
    if cfg.journal.is_file():
        with Journal(cfg.journal, job=cfg.job) as j:
            out["journal_counts"] = j.counts()
            out["quarantined"] = [{"path": e.path, "reason": e.reason} for e in j.entries("quarantined")[-20:]]
    return out


def _overwrite_in_place(path: Path, data: dict[str, Any]) -> bool:
    """Rewrite an existing JSON file in the blocks it already has (padded with spaces, so
    no new block is needed): the status file on a full disk, where no temporary file can
    be made.  Not atomic: a reader may catch it half written, and reads it again.
    Returns whether it fitted."""
    text = json.dumps(data, indent=1).encode()
    try:
        with open(path, "r+b") as fh:
            size = os.fstat(fh.fileno()).st_size
            if len(text) + 1 > size:
                text = json.dumps(data, separators=(",", ":")).encode()
                if len(text) + 1 > size:
                    return False
            fh.write(text + b"\n" + b" " * (size - len(text) - 1))
        return True
    except OSError:
        return False


def _write_json_quick(path: Path, data: dict[str, Any]) -> None:
    """Atomic (rename) but not fsynced: a status file is rewritten every second and is
    worthless after a power cut anyway."""
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "w", encoding="utf-8") as fh:
            json.dump(data, fh, indent=1)
            fh.write("\n")
        os.chmod(tmp, 0o644)
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        raise


# ------------------------------------------------------------------ the daemon
class Daemon:
    """The watch-folder loop (see the module docstring). ``Daemon(cfg).run()`` returns an
    exit code: 0 after a drained SIGTERM/SIGINT, 1 after an abort (a second signal).

    Raises
    ------
    WatchError, JournalError
        Startup problems (another daemon on the job, unusable folders or journal,
        workers that cannot start).
    """

    #: Tasks queued per worker (one running + one ready, so the worker never waits for
    #: the main process to fingerprint and claim its next file).
    PER_WORKER = 2
    #: Seconds between journal queries for due retries and between status writes.
    DUE_EVERY = 1.0
    STATUS_EVERY = 1.0

    def __init__(self, cfg: WatchConfig) -> None:
        self.cfg = cfg
        self.tracker = SettleTracker(cfg.settle)
        self.events: queue.SimpleQueue[tuple[str, str]] = queue.SimpleQueue()
        self.ready: dict[str, None] = {}  # ripe paths, in order (an ordered set)
        self.inflight: dict[str, _Task] = {}
        self.workers: list[_Worker] = []
        self.known: dict[str, tuple[int, int]] = {}  # path -> (size, mtime_ns) done/quarantined this run
        self.unreadable: dict[str, tuple[int, float]] = {}  # path -> (attempts, retry at, monotonic)
        # "failed_attempts": attempts that failed this run (a file retried once, then
        # quarantined, counts 2); the journal's "failed" is files waiting to retry now
        self.stats = {"done": 0, "failed_attempts": 0, "quarantined": 0, "retried": 0, "recovered": 0, "released": 0,
                      "disk_full": 0}
        self._stop: str | None = None
        self._abort = False
        self._rescan_asked = False
        self._task_ids = 0
        self._early_deaths = 0
        self._observer = None
        self._lock_fd: int | None = None
        self._wake_r: socket.socket | None = None
        self._wake_w: socket.socket | None = None
        self._counts: dict[str, int] = {}
        self._started = time.time()
        self._excluded = cfg.excluded_dirs()
        self._rates: deque[float] = deque(maxlen=100_000)  # monotonic times of recent completions
        self._pause_until = 0.0
        self._next_rescan = 0.0
        self._disk: _DiskPause | None = None  # paused: the output disk is full
        self._disk_ready: set[str] = set()  # given back for the disk, due again now that there is room
        # journal writes that failed (its disk full too?), retried in order until they succeed
        self._backlog: deque[Callable[[], None]] = deque()
        self._backlog_ids: set[int] = set()  # tasks whose journal write failed once (logged once)

    # ---------------------------------------------------------- life cycle
    def run(self) -> int:
        cfg = self.cfg
        cfg.validate()
        self._take_lock()
        try:
            self.journal = Journal(cfg.journal, job=cfg.job, retry_base=cfg.retry_base, retry_cap=cfg.retry_cap)
            try:
                return self._run()
            finally:
                self.journal.close()
        finally:
            self._release_lock()

    def _run(self) -> int:
        cfg = self.cfg
        unfinished = [e.path for state in ("running", "pending", "failed") for e in self.journal.entries(state)]
        self._recover()
        self._remove_stale_temps(unfinished)
        if cfg.retry_quarantined:
            # first back into the watch folder, then pending: in this order a crash between the
            # two leaves files the next start simply quarantines (moves) again, never stranded
            back = self._return_quarantined()
            k = self.journal.requeue("quarantined")
            log.info("%d quarantined file(s) will be tried again (%d moved back from the quarantine folder)", k, back,
                     extra=_ev("requeue", count=k, moved_back=back))
        old_handlers = self._install_signals()
        try:
            for i in range(cfg.workers):
                self._start_worker(i)
            self._start_observer()
            self._rescan()
            log.info("watching %s -> %s (%s mode, %d worker(s), %s, settle %.3g s)", cfg.in_dir, cfg.out_dir,
                     cfg.settings.get("mode"), cfg.workers,
                     f"polling every {cfg.poll:g} s" if cfg.poll else "native events", cfg.settle,
                     extra=_ev("start", in_dir=str(cfg.in_dir), out_dir=str(cfg.out_dir), job=cfg.job,
                               workers=cfg.workers, poll=cfg.poll, settle=cfg.settle, pid=os.getpid()))
            _sd_notify("READY=1\nSTATUS=watching")
            self._loop()
        finally:
            self._stop_observer()
            self._shutdown_workers()
            self._restore_signals(old_handlers)
            self._write_status(state="stopped" if not self._abort else "aborted")
            _sd_notify("STOPPING=1")
        if self._abort:
            log.warning("aborted: files in progress were handed back for the next start", extra=_ev("aborted"))
            return 1
        log.info("stopped (%s): %d done, %d quarantined, %d retried this run", self._stop, self.stats["done"],
                 self.stats["quarantined"], self.stats["retried"], extra=_ev("stopped", reason=self._stop, **self.stats))
        return 0

    def _recover(self) -> None:
        """Hand back the files that a stopped run left running, uncharged (Journal.recover):
        the daemon's own death (kill -9, a power cut) is not the files' fault.  A file that
        kills its worker is charged while the daemon lives (:meth:`_record_failure`)."""
        interrupted = self.journal.entries("running")
        if not interrupted:
            return
        self.journal.recover()
        boot = boot_id()
        for e in interrupted:
            who = e.runner or {}
            if not e.started:
                how = "was queued for a worker when the daemon stopped"
            elif who.get("boot") and boot and who.get("boot") != boot:
                how = "was in progress when the machine stopped (another boot)"
            else:
                how = f"was in progress when daemon pid {who.get('pid', '?')} stopped"
            log.info("%s %s; tried again, not charged a crash", os.path.relpath(e.path, self.cfg.in_dir), how,
                     extra=_ev("recovered", file=e.path, started=e.started, runner=who or None))
        log.warning("%d file(s) were being processed when the daemon last stopped; they are tried again",
                    len(interrupted), extra=_ev("recover", count=len(interrupted)))

    def _return_quarantined(self) -> int:
        """Move this job's files in the ``--quarantine`` folder back to where they were
        found (the ``file`` of their reason file), so that ``--retry-quarantined`` finds
        them: the journal knows files by their path in the watch folder.  A file whose
        place is taken by other content is put beside it (:func:`_move`), never over it.
        Returns the number of files moved back."""
        cfg = self.cfg
        qdir = cfg.quarantine_dir
        if qdir is None or not qdir.is_dir():
            return 0
        n = 0
        for why_file in sorted(qdir.glob("*" + REASON_SUFFIX)):
            why = _read_sidecar(why_file)
            if why is None or why.get("job") != cfg.job or not isinstance(why.get("file"), str):
                continue  # another job's, or not ours at all
            held = why_file.with_name(why_file.name[: -len(REASON_SUFFIX)])
            dst = Path(os.path.normpath(cfg.in_dir / why["file"]))
            if not _inside(str(dst), str(cfg.in_dir)) or dst == cfg.in_dir or not self._wanted(str(dst)):
                log.warning("%s names %r, not a place in the watch folder; left in quarantine", why_file, why["file"],
                            extra=_ev("unquarantine-skipped", file=str(held)))
                continue
            if _signature(str(held)) is None:
                continue  # moved back by a run that stopped before removing the reason file
            try:
                fp = fingerprint(held)
                back = _move(str(held), dst.parent, dst.name, fp)
            except (OSError, FingerprintError) as exc:
                log.error("cannot move %s back to the watch folder: %s", held, getattr(exc, "strerror", None) or exc,
                          extra=_ev("move-error", file=str(held)))
                continue
            with contextlib.suppress(OSError):
                why_file.unlink()
            n += 1
            log.info("moved %s back from the quarantine folder to %s", held.name, back,
                     extra=_ev("unquarantined", file=str(back), source=str(held)))
        return n

    def _remove_stale_temps(self, unfinished: list[str]) -> None:
        """Temporary files that the outputs of ``unfinished`` inputs (running or pending when
        the last run stopped) and our status file were being written to when their writer
        was killed: nothing writes them now."""
        cfg = self.cfg
        removed = self._remove_temps(unfinished)
        with contextlib.suppress(OSError), os.scandir(cfg.status_file.parent) as it:
            for e in it:
                if e.name.startswith(f".{cfg.status_file.name}.") and e.name.endswith(".tmp"):
                    with contextlib.suppress(OSError):
                        os.unlink(e.path)
                        removed += 1
        if removed:
            log.info("removed %d temporary file(s) left by the interrupted run", removed,
                     extra=_ev("cleanup", count=removed))

    def _remove_temps(self, paths: Iterable[str], keep: Iterable[str] = ()) -> int:
        """Remove the temporary files that the outputs of the inputs ``paths`` were being
        written to by a writer that is dead now, none of ``keep`` (still being written):
        :func:`vigproc.pipeline.processor.sweep_temporaries`."""
        in_dir = str(self.cfg.in_dir)

        def rels(ps: Iterable[str]) -> list[str]:
            return [os.path.relpath(p, in_dir) for p in ps if _inside(p, in_dir)]

        return sweep_temporaries(self.cfg.out_dir, rels(paths), keep=rels(keep))

    def _take_lock(self) -> None:
        import fcntl

        cfg = self.cfg
        try:
            cfg.lock_file.parent.mkdir(parents=True, exist_ok=True)
            fd = os.open(cfg.lock_file, os.O_RDWR | os.O_CREAT, 0o644)
        except OSError as exc:
            raise WatchError(f"cannot create the lock file {str(cfg.lock_file)!r}: {exc.strerror or exc}") from None
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            try:
                other = os.read(fd, 64).decode("ascii", "replace").strip()
            except OSError:
                other = "?"
            os.close(fd)
            raise WatchError(f"another vigproc watch (pid {other or '?'}) is already running on {str(cfg.in_dir)!r} "
                             f"-> {str(cfg.out_dir)!r} (lock {str(cfg.lock_file)!r})") from None
        os.ftruncate(fd, 0)
        os.write(fd, f"{os.getpid()}\n".encode())
        self._lock_fd = fd

    def _release_lock(self) -> None:
        if self._lock_fd is not None:
            os.close(self._lock_fd)
            self._lock_fd = None

    # ---------------------------------------------------------- signals
    def _install_signals(self) -> dict[Any, Any]:
        self._wake_r, self._wake_w = socket.socketpair()
        self._wake_r.setblocking(False)
        self._wake_w.setblocking(False)
        if threading.current_thread() is not threading.main_thread():  # embedded: the host handles signals
            return {}
        old: dict[Any, Any] = {"wakeup": signal.set_wakeup_fd(self._wake_w.fileno(), warn_on_full_buffer=False)}

        def on_stop(signum: int, _frame: Any) -> None:
            if self._stop is None:
                self._stop = signal.Signals(signum).name
            else:
                self._abort = True

        def on_hup(_signum: int, _frame: Any) -> None:
            self._rescan_asked = True

        for sig in (signal.SIGTERM, signal.SIGINT):
            old[sig] = signal.signal(sig, on_stop)
        if hasattr(signal, "SIGHUP"):
            old[signal.SIGHUP] = signal.signal(signal.SIGHUP, on_hup)
        return old

    def _restore_signals(self, old: dict[Any, Any]) -> None:
        for sig, handler in old.items():
            if sig == "wakeup":
                signal.set_wakeup_fd(handler)
            else:
                signal.signal(sig, handler)
        for s in (self._wake_r, self._wake_w):
            if s is not None:
                s.close()

    # ---------------------------------------------------------- workers
    def _start_worker(self, index: int) -> None:
        cfg = self.cfg
        ctx = mp.get_context("spawn")  # no fork: the observer thread and sqlite handles must not be cloned
        parent, child = ctx.Pipe(duplex=True)
        env_threads = os.environ.get("NUMBA_NUM_THREADS")
        if env_threads is None:  # N workers x all-core kernels would oversubscribe the cores
            os.environ["NUMBA_NUM_THREADS"] = str(max(1, (os.cpu_count() or 1) // cfg.workers))
        try:
            p = ctx.Process(target=_worker_main, name=f"worker-{index}",
                            args=(child, cfg.settings, cfg.profile_db, cfg.log_json, cfg.log_level,
                                  cfg.min_free))
            p.start()
        finally:
            if env_threads is None:
                del os.environ["NUMBA_NUM_THREADS"]
        child.close()
        w = _Worker(name=f"worker-{index}", process=p, conn=parent)
        if index < len(self.workers):
            self.workers[index] = w
        else:
            self.workers.append(w)

    def _worker_gone(self, index: int, why: str) -> None:
        """A worker died or was killed: its running file failed, its queued files go back."""
        w = self.workers[index]
        with contextlib.suppress(OSError):
            w.conn.close()
        _kill_group(w.process)  # its exiftool too, which would otherwise live on (and write on)
        w.process.join(timeout=5)
        code = w.process.exitcode
        with contextlib.suppress(ValueError):
            w.process.close()
        if not w.ready:
            self._early_deaths += 1
            if self._early_deaths >= 3:
                raise WatchError(f"worker processes die while starting ({why}, exit code {code}); see the log")
        else:
            self._early_deaths = 0
        for t in w.tasks:
            self.inflight.pop(t.path, None)
            if t.probe and self._disk is not None:
                self._disk.probing = False
            if t.started is not None:
                # the worker died (or hung) on this file while the daemon lives: a crash the
                # file caused, the only kind charged (a kill of the daemon is not: Journal.recover)
                self._record_failure(t, CRASH, f"{why} (worker exit code {code})")
            else:
                self._release(t)
        self._remove_temps([t.path for t in w.tasks], keep=self.inflight)
        w.tasks.clear()
        if not self._stop:
            log.warning("%s %s; starting a new one", w.name, why, extra=_ev("worker-restart", worker=w.name, why=why))
            self._start_worker(index)
        else:
            w.stopping = True

    def _shutdown_workers(self) -> None:
        for w in self.workers:
            if self._abort:
                _kill_group(w.process)
            elif w.process.is_alive():
                with contextlib.suppress(OSError, ValueError):
                    w.conn.send(("stop",))
        deadline = time.monotonic() + 10 + (self.cfg.timeout if any(w.tasks for w in self.workers) else 0)
        unfinished = []
        for w in self.workers:
            w.process.join(timeout=max(deadline - time.monotonic(), 0.1))
            if w.process.is_alive():
                _kill_group(w.process)
                w.process.join(timeout=5)
            for t in w.tasks:  # only after an abort or a startup error
                self.inflight.pop(t.path, None)
                self._release(t)
                unfinished.append(t.path)
            w.tasks.clear()
            with contextlib.suppress(OSError):
                w.conn.close()
            with contextlib.suppress(ValueError):
                w.process.close()
        if unfinished:  # their writers were killed
            self._remove_temps(unfinished)

    # ---------------------------------------------------------- observer
    def _start_observer(self) -> None:
        from watchdog.events import FileSystemEventHandler

        events = self.events
        wake = self._wake_w

        class Handler(FileSystemEventHandler):
            def on_any_event(self, event: Any) -> None:
                kind = event.event_type
                if kind in ("opened", "closed_no_write"):  # our own reads
                    return
                path = event.dest_path if kind == "moved" else event.src_path
                path = os.fsdecode(path)
                if event.is_directory:
                    if kind in ("created", "moved"):
                        events.put(("dir", path))
                elif kind == "deleted":
                    events.put(("gone", path))
                else:
                    events.put(("file", path))
                    if kind == "moved":
                        events.put(("gone", os.fsdecode(event.src_path)))
                with contextlib.suppress(OSError):
                    if wake is not None:
                        wake.send(b"e")

        cfg = self.cfg
        if cfg.poll:
            from watchdog.observers.polling import PollingObserver

            obs = PollingObserver(timeout=cfg.poll)
        else:
            from watchdog.observers import Observer

            obs = Observer()
        try:
            obs.schedule(Handler(), str(cfg.in_dir), recursive=True)
            obs.start()
        except OSError as exc:  # e.g. the inotify watch limit: polling still works
            if cfg.poll:
                raise WatchError(f"cannot watch {str(cfg.in_dir)!r}: {exc.strerror or exc}") from None
            log.warning("native file events unavailable (%s); polling every 5 s instead", exc.strerror or exc,
                        extra=_ev("fallback-polling"))
            from watchdog.observers.polling import PollingObserver

            obs = PollingObserver(timeout=5.0)
            obs.schedule(Handler(), str(cfg.in_dir), recursive=True)
            obs.start()
        self._observer = obs

    def _stop_observer(self) -> None:
        if self._observer is not None:
            with contextlib.suppress(Exception):
                self._observer.stop()
                self._observer.join(timeout=10)
            self._observer = None

    # ---------------------------------------------------------- discovery
    def _wanted(self, path: str) -> bool:
        if not _inside(path, str(self.cfg.in_dir)) or path == str(self.cfg.in_dir):
            return False
        if any(_inside(path, d) for d in self._excluded):
            return False
        rel = os.path.relpath(path, self.cfg.in_dir)
        parts = rel.split(os.sep)
        if any(p.startswith(".") or p in IGNORED_DIRS for p in parts[:-1]):
            return False
        return is_candidate_name(parts[-1])

    def _seen(self, path: str) -> None:
        if not self._wanted(path) or path in self.inflight:
            return  # a changed in-flight file is caught when its result comes back
        known = self.known.get(path)
        if known is not None:
            sig = _signature(path)
            if sig is not None and sig[:2] == known:
                return
            self.known.pop(path, None)
        self.ready.pop(path, None)
        self.tracker.see(path)

    def _walk(self, top: str) -> Iterable[str]:
        def onerror(exc: OSError) -> None:
            log.warning("cannot list %s: %s", exc.filename, exc.strerror or exc, extra=_ev("list-error",
                        folder=exc.filename))

        for root, dirs, files in os.walk(top, onerror=onerror, followlinks=False):
            dirs[:] = sorted(d for d in dirs if not d.startswith(".") and d not in IGNORED_DIRS
                             and not any(_inside(os.path.join(root, d), x) for x in self._excluded))
            for f in sorted(files):
                yield os.path.join(root, f)

    def _rescan(self, top: str | None = None) -> None:
        """Look at every file under the watch folder (or ``top``): what events missed,
        what arrived while we were down, what a crash left half-moved."""
        t0 = time.monotonic()
        n = 0
        if not self.cfg.in_dir.is_dir():
            log.error("watch folder %s is gone (unmounted?); waiting for it", self.cfg.in_dir,
                      extra=_ev("folder-missing"))
            return
        self._next_rescan = time.monotonic() + self.cfg.rescan
        for path in self._walk(top or str(self.cfg.in_dir)):
            if not self._wanted(path) or path in self.inflight or path in self.ready:
                continue
            sig = _signature(path)
            if sig is None:
                continue
            if self.known.get(path) == sig[:2]:
                continue
            try:
                entry = self.journal.lookup(path)
            except JournalError as exc:
                log.error("rescan stopped, journal unavailable: %s", exc, extra=_ev("journal-error"))
                self._next_rescan = time.monotonic() + 10
                return
            if (entry is not None and entry.state in ("done", "quarantined")
                    and (entry.fingerprint.size, entry.fingerprint.mtime_ns) == sig[:2]):
                self.known[path] = sig[:2]  # same size and mtime as when it was finished: no need to hash it
                self._after_finished(path, entry.fingerprint, entry.state, entry.reason)
                continue
            self.tracker.see(path)
            n += 1
        log.debug("rescan of %s: %d file(s) to look at (%.2f s)", top or self.cfg.in_dir, n, time.monotonic() - t0,
                  extra=_ev("rescan", files=n))

    def _handle_events(self) -> None:
        while True:
            try:
                kind, path = self.events.get_nowait()
            except queue.Empty:
                return
            if kind == "file":
                self._seen(path)
            elif kind == "dir":
                if self._wanted(os.path.join(path, "x.jpg")):  # not inside an excluded/hidden folder
                    self._rescan(path)
            elif kind == "gone":
                self.tracker.forget(path)
                self.ready.pop(path, None)
                self.known.pop(path, None)

    # ---------------------------------------------------------- dispatch
    def _idle_worker(self) -> _Worker | None:
        best = None
        for w in self.workers:
            if w.ready and not w.stopping and len(w.tasks) < self.PER_WORKER:
                if best is None or len(w.tasks) < len(best.tasks):
                    best = w
        return best

    def _dispatch(self) -> None:
        if time.monotonic() < self._pause_until:
            return
        probe = False
        if self._disk is not None:
            go = self._disk_go()
            if go is None:
                return
            probe = go == "probe"
        while self.ready and not self._stop:
            w = self._idle_worker()
            if w is None:
                return
            if probe and self._disk is not None:
                # the probe: one file, preferably not the one that failed last
                path = next((p for p in self.ready if p not in self._disk.held), next(iter(self.ready)))
            else:
                path = next(iter(self.ready))
            del self.ready[path]
            try:
                task = self._prepare(path)
            except JournalError as exc:  # e.g. its disk is full: keep the file, try again shortly
                log.error("journal unavailable: %s; pausing 5 s", exc, extra=_ev("journal-error", file=path))
                self.tracker.see(path)
                self._pause_until = time.monotonic() + 5
                return
            if task is None:
                continue
            try:
                w.conn.send(("task", task.id, task.path, str(self.cfg.out_dir), task.stem, task.fp.to_dict(),
                             {"input": task.rel, "input_sha256": task.fp.sha256, "input_size": task.fp.size,
                              "settings": self.cfg.settings, "watch_job": self.cfg.job}))
            except (OSError, ValueError):  # the worker just died: the next wait() sees it
                self._release(task)
                self.tracker.see(path)
                continue
            w.tasks.append(task)
            self.inflight[path] = task
            if probe and self._disk is not None:
                task.probe = self._disk.probing = True
                log.info("output disk full: trying %s to see whether there is room again", task.rel,
                         extra=_ev("disk-probe", file=task.path))
                return

    def _prepare(self, path: str) -> _Task | None:
        """Fingerprint and claim a ripe file; None if there is nothing to do (yet)."""
        sig = _signature(path)
        if sig is None:
            entry = self.journal.lookup(path)
            if entry is not None and entry.state == "pending":
                self.journal.forget(path)  # deleted before it was processed: nothing to do
            return None
        retry = self.unreadable.get(path)
        if retry is not None and time.monotonic() < retry[1]:
            return None
        try:
            fp = fingerprint(path)
        except FileChangedError:
            self.tracker.see(path)
            return None
        except FingerprintError as exc:
            self._unreadable(path, sig, exc)
            return None
        self.unreadable.pop(path, None)
        entry = self.journal.lookup(path)
        if entry is not None and entry.fingerprint.same_content(fp) and entry.state in ("done", "quarantined"):
            if entry.fingerprint.mtime_ns != fp.mtime_ns:
                self.journal.touch(path, fp)
            self.known[path] = (fp.size, fp.mtime_ns)
            self._after_finished(path, fp, entry.state, entry.reason)
            return None
        # a file given back for a full disk is due as soon as there is room, whatever its retry time
        now = float("inf") if path in self._disk_ready else None
        if not self.journal.claim(path, fp, worker=f"{os.uname().nodename}:{os.getpid()}", now=now):
            return None  # waiting for its retry time (due() brings it back) or running elsewhere
        self._disk_ready.discard(path)
        self._task_ids += 1
        rel = os.path.relpath(path, self.cfg.in_dir)
        return _Task(self._task_ids, path, rel, rel, fp)

    def _unreadable(self, path: str, sig: tuple[int, int, int], exc: FingerprintError) -> None:
        attempts = self.unreadable.get(path, (0, 0.0))[0] + 1
        if exc.transient and attempts < self.cfg.max_attempts:
            delay = min(self.cfg.retry_cap, self.cfg.retry_base * 2 ** (attempts - 1))
            self.unreadable[path] = (attempts, time.monotonic() + delay)
            log.warning("%s: %s; trying again in %.0f s", path, exc, delay, extra=_ev("unreadable", file=path))
            return
        self.unreadable.pop(path, None)
        self.journal.quarantine(path, Fingerprint(sig[0], sig[1], "unreadable"), str(exc))
        self.known[path] = sig[:2]
        self.stats["quarantined"] += 1
        log.error("quarantined %s: %s", path, exc, extra=_ev("quarantined", file=path, reason=str(exc)))

    def _due_retries(self) -> None:
        now = time.monotonic()
        for path, (_n, at) in self.unreadable.items():
            if now >= at and path not in self.inflight:
                self.ready[path] = None
        for path, _fp in self.journal.due(limit=1000):  # a huge backlog comes back in slices
            if path not in self.inflight and path not in self.ready and path not in self.tracker:
                if os.path.lexists(path):
                    self.ready[path] = None
                else:
                    self.journal.forget(path)

    # ---------------------------------------------------------- results
    def _collect(self, timeout: float) -> None:
        objs: list[Any] = [self._wake_r] if self._wake_r is not None else []
        by_conn = {}
        for i, w in enumerate(self.workers):
            if not w.stopping:
                objs += [w.conn, w.process.sentinel]
                by_conn[w.conn] = i
                by_conn[w.process.sentinel] = i
        try:
            ready = mpc.wait(objs, timeout=timeout)
        except OSError:
            ready = []
        dead: set[int] = set()
        for obj in ready:
            if obj is self._wake_r:
                with contextlib.suppress(OSError):
                    while self._wake_r.recv(4096):
                        pass
                continue
            i = by_conn[obj]
            w = self.workers[i]
            if obj is w.conn:
                try:
                    while w.conn.poll():
                        self._message(i, w.conn.recv())
                except (EOFError, OSError):
                    dead.add(i)
            elif not w.process.is_alive():
                dead.add(i)
        for i in sorted(dead):
            w = self.workers[i]
            with contextlib.suppress(EOFError, OSError):  # what it said before dying
                while w.conn.poll():
                    self._message(i, w.conn.recv())
            self._worker_gone(i, "died")

    def _message(self, index: int, msg: tuple) -> None:
        w = self.workers[index]
        kind, task_id, payload = msg
        if kind == "ready":
            w.ready = True
            w.pid = payload
            log.info("%s ready (pid %s)", w.name, payload, extra=_ev("worker-ready", worker=w.name, worker_pid=payload))
            return
        if kind == "fatal":
            raise WatchError(f"{w.name} cannot start: {payload}")
        task = next((t for t in w.tasks if t.id == task_id), None)
        if task is None:
            return
        if kind == "start":
            task.started = time.monotonic()
            try:  # from now on a death of its worker charges this file a crash (_worker_gone)
                self.journal.start(task.path, task.fp, runner=runner_identity(w.pid))
            except JournalError as exc:
                log.error("%s: cannot record its start: %s", task.path, exc, extra=_ev("journal-error", file=task.path))
            return
        w.tasks.remove(task)
        self.inflight.pop(task.path, None)
        if task.probe and self._disk is not None:
            self._disk.probing = False
        if self._changed(task):
            return
        if kind == "ok":
            self._done(task, payload, w.name)
        else:
            kind_, reason = payload["kind"], payload["reason"]
            if kind_ == DISK_FULL:  # the machine's fault, not the photo's: no attempt counted
                self._disk_full(task, reason, payload.get("free_bytes"))
                return
            if self._stop and "exiftool" in reason:
                # the stop signal may have reached exiftool too (systemd can signal every
                # process): not the file's fault, so it goes back without an attempt
                self._release(task)
                log.warning("%s failed while stopping (%s); it will be tried again", task.rel, reason,
                            extra=_ev("released", file=task.path, reason=reason))
                return
            if kind_ == PERMANENT and payload.get("type") in _READ_ERRORS and self._young(task):
                e = self.journal.lookup(task.path)
                if e is not None and e.attempts == 0:
                    # a writer that paused longer than --settle leaves a "corrupt" file that is
                    # in fact incomplete: one more look before quarantining (and moving) it
                    kind_ = TRANSIENT
                    reason += " (recently written: tried again in case it was incomplete)"
            self._record_failure(task, kind_, reason)

    # ---------------------------------------------------------- full output disk
    def _disk_full(self, task: _Task, reason: str, free_bytes: int | None) -> None:
        """``task`` failed for want of space on the output disk: give it back uncharged,
        and pause (or stay paused, backing off if it was the probe)."""
        cfg = self.cfg
        now = time.monotonic()
        if free_bytes is None:
            sp = disk_space(cfg.out_dir)
            free_bytes = sp.free_bytes if sp is not None else None
        d = self._disk
        if d is None:
            d = self._disk = _DiskPause(reason=reason, since=time.time(), free_bytes=free_bytes,
                                        delay=max(cfg.retry_base, 0.1), probe_at=now + max(cfg.retry_base, 0.1))
            self.stats["disk_full"] += 1
            log.warning("output disk full, paused: %s (%s); nothing is quarantined for it, the files are tried "
                        "again when there is room", reason, task.rel,
                        extra=_ev("disk-full", file=task.path, reason=reason, free_bytes=free_bytes))
        else:
            d.reason, d.free_bytes = reason, free_bytes  # the latest look: the growth that resumes is from here
            if task.probe:
                d.delay = min(d.delay * 2, max(cfg.retry_cap, cfg.retry_base))
                d.probe_at = now + d.delay
                log.warning("output disk still full (%s); next try in %.0f s", reason, d.delay,
                            extra=_ev("disk-still-full", file=task.path, reason=reason, retry_in=round(d.delay, 1)))
        d.held.add(task.path)
        self._disk_ready.discard(task.path)
        # back to pending with no attempt counted; the pause holds it here, the short delay is
        # for a restart (which finds out about the disk afresh)
        self._release(task, not_before=time.time() + cfg.retry_base, reason=reason)
        self._write_status()

    def _disk_go(self) -> str | None:
        """While paused for a full disk: None (hand out nothing yet), ``"probe"`` (one
        file, to see whether it fits) or ``"resume"`` (the free space grew: carry on)."""
        cfg, d = self.cfg, self._disk
        assert d is not None
        now = time.monotonic()
        if now >= d.next_look:
            d.next_look = now + self.DUE_EVERY
            sp = disk_space(cfg.out_dir)
            # grown, not merely "not low": a quota (EDQUOT) or a full disk that reported
            # plenty would otherwise resume and fail again every second
            grown = d.free_bytes is None or sp is None or sp.free_bytes >= d.free_bytes + max(cfg.min_free // 4, 1 << 20)
            if sp is not None and not sp.low(cfg.min_free) and grown:
                self._disk_resume(sp.describe())
                return "resume"
        if d.probing or now < d.probe_at:
            return None
        if not self.ready:  # nothing new to try: one of the files given back
            for p in sorted(d.held):
                if p not in self.inflight and os.path.lexists(p):
                    self.ready[p] = None
                    self._disk_ready.add(p)
                    break
        if not self.ready:
            return None
        d.probe_at = now + d.delay  # also if the probe fails for another reason
        return "probe"

    def _disk_resume(self, why: str) -> None:
        d, self._disk = self._disk, None
        if d is None:
            return
        back = [p for p in sorted(d.held) if p not in self.inflight and os.path.lexists(p)]
        for p in back:
            self.ready[p] = None
            self._disk_ready.add(p)
        log.info("output disk has room again (%s): resumed after %.0f s; %d file(s) given back are tried again",
                 why, time.time() - d.since, len(back),
                 extra=_ev("disk-resumed", why=why, paused_s=round(time.time() - d.since, 1), files=len(back)))
        self._write_status()

    def _young(self, task: _Task) -> bool:
        return time.time() - task.fp.mtime_ns / 1e9 < max(30.0, 10 * self.cfg.settle)

    def _changed(self, task: _Task) -> bool:
        """Whether the input changed while it was processed; if so it is handed back
        and seen again (its outputs will be rewritten under the same names)."""
        sig = _signature(task.path)
        if sig is not None and sig[:2] == (task.fp.size, task.fp.mtime_ns):
            return False
        if sig is not None:
            try:
                fp = fingerprint(task.path)
                if fp.same_content(task.fp):
                    return False  # only touched
            except FingerprintError:
                pass
        self._release(task)
        self.stats["released"] += 1
        if sig is not None:
            log.info("%s changed while it was processed; it will be processed again", task.path,
                     extra=_ev("changed", file=task.path))
            self.tracker.see(task.path)
        else:
            log.info("%s disappeared while it was processed", task.path, extra=_ev("vanished", file=task.path))
        return True

    def _done(self, task: _Task, summary: dict[str, Any], worker: str) -> None:
        if task.probe and self._disk is not None:
            self._disk_resume(f"{task.rel} was written")
        summary = {**summary, "worker": worker}
        try:
            self.journal.done(task.path, task.fp, summary)
        except JournalError as exc:
            self._journal_later(task, "as done", exc, lambda: self._done(task, summary, worker))
            return
        self.known[task.path] = (task.fp.size, task.fp.mtime_ns)
        self.stats["done"] += 1
        if summary.get("recovered"):
            self.stats["recovered"] += 1
        self._rates.append(time.monotonic())
        log.info("done %s -> %s (%s, %.2f s)", task.rel, summary.get("output") or summary.get("sidecar"),
                 summary.get("source"), summary.get("seconds") or 0.0,
                 extra=_ev("done", file=task.path, sha256=task.fp.sha256, output=summary.get("output"),
                           sidecar=summary.get("sidecar"),
                           source=summary.get("source"), seconds=summary.get("seconds"), worker=worker,
                           verdict=summary.get("verdict"), recovered=summary.get("recovered")))
        self._after_finished(task.path, task.fp, "done", None)

    def _record_failure(self, task: _Task, kind: str, reason: str) -> None:
        """Charge a failed attempt to ``task``'s file: a ``kind`` of :mod:`vigproc.pipeline.faults`,
        :data:`~vigproc.pipeline.faults.CRASH` when it killed or hung its worker.  The journal
        decides: retried after a backoff, or quarantined once the file has used up its
        ``--max-attempts`` (never for an output-side failure), its ``--max-crashes``, or
        at once when the photo is to blame."""
        crash = kind == CRASH
        try:
            if crash:
                outcome = self.journal.crashed(task.path, task.fp, reason, max_crashes=self.cfg.max_crashes)
            else:
                outcome = self.journal.failed(task.path, task.fp, reason, transient=kind != PERMANENT,
                                              max_attempts=attempt_limit(kind, self.cfg.max_attempts))
        except JournalError as exc:
            self._journal_later(task, f"as {'crashed' if crash else 'failed'} ({reason})", exc,
                                lambda: self._record_failure(task, kind, reason))
            return
        self.stats["failed_attempts"] += 1
        e = self.journal.lookup(task.path)
        if outcome == "retry":
            self.stats["retried"] += 1
            wait = max((e.not_before if e else 0) - time.time(), 0.0)
            count = (f"crash {e.crashes if e else 0} of {self.cfg.max_crashes} allowed" if crash
                     else f"attempt {e.attempts if e else 0}")
            log.warning("%s failed (%s: %s); %s, retry in %.0f s", task.rel, kind, reason, count, wait,
                        extra=_ev("retry", file=task.path, kind=kind, reason=reason, retry_in=round(wait, 1)))
            return
        self.known[task.path] = (task.fp.size, task.fp.mtime_ns)
        self.stats["quarantined"] += 1
        reason = e.reason if e is not None and e.reason else reason  # as journaled (a crash's says how often)
        log.error("quarantined %s: %s", task.rel, reason, extra=_ev("quarantined", file=task.path, kind=kind,
                                                                     reason=reason))
        earlier = self._earlier_outputs(task.rel, task.fp)
        if earlier:
            # not deleted (they were right for what the file held then), but said
            log.warning("%s: the outputs %s are of an earlier content of this file, not of the one "
                        "quarantined", task.rel, ", ".join(earlier),
                        extra=_ev("earlier-outputs", file=task.path, outputs=earlier))
        self._after_finished(task.path, task.fp, "quarantined", reason, earlier)

    def _earlier_outputs(self, rel: str, fp: Fingerprint) -> list[str]:
        """The sidecar and output in the output folder for ``rel`` when they record
        another content than ``fp`` (the file was replaced and its new content failed)."""
        from vigproc.pipeline.processor import SIDECAR_SUFFIX, safe_output

        try:
            folder, stem = output_location(self.cfg.out_dir, rel, create=False)
        except VigprocError:
            return []
        sidecar = safe_output(folder, stem, SIDECAR_SUFFIX)
        d = _read_sidecar(sidecar)
        if d is None or d.get("input_sha256") in (None, fp.sha256):
            return []
        out = d.get("output")
        return [str(sidecar)] + ([out] if isinstance(out, str) and os.path.isfile(out) else [])

    def _release(self, task: _Task, not_before: float = 0.0, reason: str | None = None) -> None:
        try:
            self.journal.release(task.path, task.fp, not_before=not_before, reason=reason)
        except JournalError as exc:
            self._journal_later(task, "as given back", exc, lambda: self._release(task, not_before, reason))

    def _journal_later(self, task: _Task, what: str, exc: JournalError, again: Callable[[], None]) -> None:
        """A journal write failed (its disk may be full too): try it again later rather than
        lose the result.  Meanwhile the entry stays ``running``, so nothing else takes the
        file; a restart would hand it back (and find its sidecar, if it was done)."""
        first = task.id not in self._backlog_ids
        self._backlog_ids.add(task.id)
        (log.error if first else log.debug)("%s: cannot record it %s in the journal: %s; trying again shortly",
                                            task.rel, what, exc, extra=_ev("journal-error", file=task.path))
        self._backlog.append(again)

    def _flush_backlog(self) -> None:
        """Retry the journal writes that failed (each puts itself back if it fails again)."""
        for _ in range(len(self._backlog)):
            self._backlog.popleft()()

    def _after_finished(self, path: str, fp: Fingerprint, state: str, reason: str | None,
                        earlier: list[str] | None = None) -> None:
        """Archive a done input / move a quarantined one aside, if asked (again after a
        crash that came between the journal and the move)."""
        cfg = self.cfg
        target = cfg.archive_dir if state == "done" else cfg.quarantine_dir
        if target is None or fp.sha256 == "unreadable":
            return
        sig = _signature(path)
        if sig is None or sig[:2] != (fp.size, fp.mtime_ns):
            return  # gone, or changed since: then it is new work, not ours to move
        rel = os.path.relpath(path, cfg.in_dir)
        try:
            if state == "done":
                dst = _move(path, cfg.archive_dir / os.path.dirname(rel), os.path.basename(rel), fp)
            else:
                why = {"file": rel, "reason": reason, "sha256": fp.sha256, "size": fp.size, "job": cfg.job,
                       "time": datetime.now(timezone.utc).isoformat()}
                if earlier:
                    why["earlier_outputs"] = earlier
                # named after the name the file really gets (a clash adds its hash), so that
                # a second file of the same name never replaces the first one's reason
                dst = _move(path, cfg.quarantine_dir, output_stem(rel), fp,
                            before=lambda d: _write_json_quick(d.with_name(d.name + REASON_SUFFIX), why))
        except (OSError, FingerprintError) as exc:
            log.error("cannot move %s to the %s folder: %s", path, "archive" if state == "done" else "quarantine",
                      getattr(exc, "strerror", None) or exc, extra=_ev("move-error", file=path))
            return
        self.known.pop(path, None)
        log.info("moved %s to %s", rel, dst, extra=_ev("archived" if state == "done" else "quarantine-moved",
                                                        file=path, to=str(dst)))

    def _check_timeouts(self) -> None:
        now = time.monotonic()
        for i, w in enumerate(self.workers):
            t = w.tasks[0] if w.tasks else None
            if t is not None and t.started is not None and now - t.started > self.cfg.timeout and not w.stopping:
                log.error("%s took more than %.0f s on %s; stopping it", w.name, self.cfg.timeout, t.rel,
                          extra=_ev("timeout", file=t.path, worker=w.name))
                _kill_group(w.process)
                w.process.join(timeout=5)
                self._worker_gone(i, f"timed out after {self.cfg.timeout:.0f} s")

    # ---------------------------------------------------------- status
    def _write_status(self, state: str = "running") -> None:
        cfg = self.cfg
        with contextlib.suppress(JournalError):
            self._counts = self.journal.counts()
        now = time.monotonic()
        recent = [t for t in self._rates if now - t <= 60]
        running = [t.rel for w in self.workers for t in w.tasks if t.started is not None]
        d = self._disk
        if state == "running" and d is not None:
            state = "paused"
        st = {
            "state": state if not self._stop or state not in ("running", "paused") else "draining",
            "pid": os.getpid(), "in_dir": str(cfg.in_dir), "out_dir": str(cfg.out_dir), "job": cfg.job,
            "mode": cfg.settings.get("mode"), "workers": cfg.workers,
            "started": datetime.fromtimestamp(self._started, timezone.utc).isoformat(timespec="seconds"),
            "updated": datetime.now(timezone.utc).isoformat(timespec="seconds"), "updated_epoch": time.time(),
            "queue": {"settling": len(self.tracker), "ready": len(self.ready),
                      "dispatched": sum(len(w.tasks) for w in self.workers) - len(running),
                      "retry_wait": self._counts.get("failed", 0) + len(self.unreadable)},
            "running": running, "journal": self._counts, "this_run": dict(self.stats),
            "files_per_min": len(recent),
        }
        if d is not None:
            st["paused"] = {
                "why": "output disk full", "reason": d.reason,
                "since": datetime.fromtimestamp(d.since, timezone.utc).isoformat(timespec="seconds"),
                "free_bytes": d.free_bytes, "files_waiting": len(d.held),
                "next_try_s": round(max(d.probe_at - now, 0.0), 1) if not d.probing else 0.0,
            }
        if self._backlog:
            st["journal_writes_waiting"] = len(self._backlog)
        try:
            _write_json_quick(cfg.status_file, st)
        except OSError as exc:
            if exc.errno not in (errno.ENOSPC, getattr(errno, "EDQUOT", errno.ENOSPC)) or \
                    not _overwrite_in_place(cfg.status_file, st):
                log.debug("cannot write the status file: %s", exc)
        q = st["queue"]
        _sd_notify(f"STATUS={'paused (output disk full)' if state == 'paused' else state}: "
                   f"{q['settling'] + q['ready'] + q['dispatched']} queued, {len(running)} running, "
                   f"{self._counts.get('done', 0)} done, {self._counts.get('quarantined', 0)} quarantined")

    # ---------------------------------------------------------- loop
    def _loop(self) -> None:
        cfg = self.cfg
        tick = min(0.25, max(cfg.settle / 4, 0.02))
        next_due = next_status = 0.0
        watchdog_usec = int(os.environ.get("WATCHDOG_USEC", "0") or 0)
        next_ping = 0.0
        draining_logged = False
        while True:
            if self._abort:
                return
            if self._stop:
                if not draining_logged:
                    n = sum(len(w.tasks) for w in self.workers)
                    log.info("%s received: finishing %d file(s) in progress, then stopping", self._stop, n,
                             extra=_ev("draining", signal=self._stop, in_progress=n))
                    _sd_notify("STOPPING=1")
                    self._stop_observer()
                    draining_logged = True
                if not self.inflight:
                    self._flush_backlog()  # once more: what a full journal disk held back
                    return
            else:
                self._handle_events()
                now = time.monotonic()
                if self._rescan_asked or now >= self._next_rescan:
                    self._rescan_asked = False
                    if self._observer is not None and not self._observer.is_alive():
                        log.warning("file system observer stopped; restarting it", extra=_ev("observer-restart"))
                        self._stop_observer()
                        with contextlib.suppress(WatchError, OSError):
                            self._start_observer()
                    self._rescan()
                for path in self.tracker.ripe():
                    self.ready[path] = None
                if now >= next_due:
                    self._flush_backlog()
                    self._due_retries()
                    next_due = now + self.DUE_EVERY
                self._dispatch()
            self._collect(tick)
            self._check_timeouts()
            now = time.monotonic()
            if now >= next_status:
                self._write_status()
                next_status = now + self.STATUS_EVERY
            if watchdog_usec and now >= next_ping:
                _sd_notify("WATCHDOG=1")
                next_ping = now + watchdog_usec / 2e6
