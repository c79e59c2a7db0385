"""The :class:`Daemon`: one job's lock, its journal, its signals and its loop, composing
what watches (:class:`~.watcher.Watcher`), what schedules (:class:`~.scheduler.Scheduler`)
and what records (:class:`~.recorder.Recorder`).

One turn of the loop: the watcher takes its events (and rescans when due), the files
that settled are offered; due retries come back; the scheduler hands files to idle
workers, waits a tick for what they say and has the recorder record it; workers that
overran ``--timeout`` are killed; the status file is rewritten every second.
"""

from __future__ import annotations

import fcntl
import os
import signal
import socket
import threading
import time
from typing import Any

from vigproc.stores.journal import Journal

from .config import RunFlags, WatchConfig, WatchError
from .logs import _ev, _sd_notify, log
from .recorder import Recorder
from .scheduler import Scheduler
from .watcher import Watcher

__all__ = ["Daemon"]


def _identity(path: Any) -> tuple[int, int] | None:
    """(device, inode) of ``path``, None when it is gone."""
    try:
        st = os.stat(path)
    except OSError:
        return None
    return st.st_dev, st.st_ino


def _fd_identity(fd: int) -> tuple[int, int]:
    st = os.fstat(fd)
    return st.st_dev, st.st_ino


def _flock(path: Any, cfg: WatchConfig) -> int:
    """Open ``path`` (creating it and its folder), lock it exclusively and write our pid in
    it; returns the descriptor, held for the daemon's life.

    Raises
    ------
    WatchError
        The lock is held by another daemon, or the file cannot be made.
    """
    for _ in range(5):  # a file replaced between our open and our lock is locked again
        try:
            path.parent.mkdir(parents=True, exist_ok=True)
            fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o644)
        except OSError as exc:
            raise WatchError(f"cannot create the lock file {str(path)!r}: {exc.strerror or exc}") from None
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            try:
                other = os.read(fd, 64).decode("ascii", "replace").strip()
            except OSError:
                other = "?"
            os.close(fd)
            raise WatchError(f"another vigproc watch (pid {other or '?'}) is already running on {str(cfg.in_dir)!r} "
                             f"-> {str(cfg.out_dir)!r} (lock {str(path)!r})") from None
        if _identity(path) == _fd_identity(fd):
            os.ftruncate(fd, 0)
            os.write(fd, f"{os.getpid()}\n".encode())
            return fd
        os.close(fd)
    raise WatchError(f"cannot hold the lock file {str(path)!r}: it keeps being replaced")


class Daemon:
    """The watch-folder loop (see :mod:`vigproc.frontends.daemon`). ``Daemon(cfg).run()``
    returns an exit code: 0 after a drained SIGTERM/SIGINT, 1 after an abort (a second
    signal).

    Attributes
    ----------
    watcher : Watcher
        What watches: events, rescans, settling, candidate filtering.
    scheduler : Scheduler
        What schedules: workers, dispatch, retries, timeouts, the full-disk pause.
    recorder : Recorder
        What records: the journal, archive and quarantine moves, the status file.

    Raises
    ------
    WatchError, JournalError
        Startup problems (another daemon on the job, unusable folders or journal,
        workers that cannot start).
    """

    #: Seconds between journal queries for due retries and between status writes.
    DUE_EVERY = 1.0
    STATUS_EVERY = 1.0

    def __init__(self, cfg: WatchConfig) -> None:
        self.cfg = cfg
        self.flags = RunFlags()
        self.recorder = Recorder(cfg)
        self.watcher = Watcher(cfg, self.recorder, busy=self._busy)
        self.scheduler = Scheduler(cfg, self.watcher, self.recorder, self.flags, on_status=self._write_status)
        self._locks: list[tuple[Any, int]] = []
        self._ground: dict[str, tuple[int, int] | None] = {}
        self._lost: str | None = None
        self._wake_r: socket.socket | None = None
        self._wake_w: socket.socket | None = None

    def _busy(self, path: str) -> bool:
        return path in self.scheduler.inflight

    @property
    def journal(self) -> Journal:
        """The job's journal (open while :meth:`run` runs); the recorder's."""
        return self.recorder.journal

    @journal.setter
    def journal(self, journal: Journal) -> None:
        self.recorder.journal = journal

    @property
    def stats(self) -> dict[str, int]:
        """This run's counts (the recorder's)."""
        return self.recorder.stats

    # ---------------------------------------------------------- life cycle
    def run(self) -> int:
        cfg = self.cfg
        cfg.validate()
        self._take_lock()
        try:
            self.journal = Journal(cfg.journal, job=cfg.job, retry_base=cfg.retry_base, retry_cap=cfg.retry_cap)
            try:
                self._remember_ground()
                code = self._run()
            finally:
                self.journal.close()
        finally:
            self._release_lock()
        if self._lost:
            raise WatchError(self._lost)
        return code

    def _run(self) -> int:
        cfg, rec, flags = self.cfg, self.recorder, self.flags
        unfinished = [e.path for state in ("running", "pending", "failed") for e in self.journal.entries(state)]
        rec.recover()
        rec.remove_stale_temps(unfinished)
        if cfg.retry_quarantined:
            # first back into the watch folder, then pending: in this order a crash between the
            # two leaves files the next start simply quarantines (moves) again, never stranded
            back = rec.return_quarantined(self.watcher.wanted)
            k = self.journal.requeue("quarantined")
            log.info("%d quarantined file(s) will be tried again (%d moved back from the quarantine folder)", k, back,
                     extra=_ev("requeue", count=k, moved_back=back))
        old_handlers = self._install_signals()
        try:
            for i in range(cfg.workers):
                self.scheduler.start_worker(i)
            self.watcher.start_observer(self._wake_w)
            self.watcher.rescan()
            # the status file before the start is announced: `--status` asked right after it
            # would otherwise find no file for up to STATUS_EVERY (running, but no pid)
            self._write_status()
            log.info("watching %s -> %s (%s mode, %d worker(s), %s, settle %.3g s)", cfg.in_dir, cfg.out_dir,
                     cfg.settings.get("mode"), cfg.workers,
                     f"polling every {cfg.poll:g} s" if cfg.poll else "native events", cfg.settle,
                     extra=_ev("start", in_dir=str(cfg.in_dir), out_dir=str(cfg.out_dir), job=cfg.job,
                               workers=cfg.workers, poll=cfg.poll, settle=cfg.settle, pid=os.getpid()))
            _sd_notify("READY=1\nSTATUS=watching")
            self._loop()
        finally:
            self.watcher.stop_observer()
            self.scheduler.shutdown()
            self._restore_signals(old_handlers)
            self._write_status(state="stopped" if not flags.abort else "aborted")
            _sd_notify("STOPPING=1")
        if self._lost:
            log.error("%s", self._lost, extra=_ev("lost", reason=self._lost))
            return 1
        if flags.abort:
            log.warning("aborted: files in progress were handed back for the next start", extra=_ev("aborted"))
            return 1
        log.info("stopped (%s): %d done, %d quarantined, %d retried this run", flags.stop, self.stats["done"],
                 self.stats["quarantined"], self.stats["retried"], extra=_ev("stopped", reason=flags.stop, **self.stats))
        return 0

    def _take_lock(self) -> None:
        """Lock the folders (a file in the user's state folder, named by the in and out
        folders) and the journal (a file beside it): a second daemon on either is refused."""
        cfg = self.cfg
        self._locks = []
        try:
            for path in (cfg.folders_lock_file, cfg.lock_file):
                self._locks.append((path, _flock(path, cfg)))
        except BaseException:
            self._release_lock()
            raise

    def _release_lock(self) -> None:
        for _path, fd in getattr(self, "_locks", []):
            os.close(fd)
        self._locks = []

    def _remember_ground(self) -> None:
        """What the job stands on, to notice it vanishing: the output folder and the journal."""
        self._ground = {str(p): _identity(p) for p in (self.cfg.out_dir, self.cfg.journal)}

    def _ground_lost(self) -> str | None:
        """Why this daemon cannot go on (its output folder or journal deleted or replaced, its
        lock taken by another daemon), or None. A deleted lock file is made again, locked."""
        for p, ident in getattr(self, "_ground", {}).items():
            if _identity(p) != ident:
                what = "journal" if p == str(self.cfg.journal) else "output folder"
                return (f"the {what} {p!r} was deleted or replaced under the running daemon: stopping "
                        f"(start it again to go on)")
        for i, (path, fd) in enumerate(self._locks):
            if _identity(path) != _fd_identity(fd):
                try:
                    self._locks[i] = (path, _flock(path, self.cfg))
                except WatchError as exc:
                    return f"the lock file was deleted and {exc}"
                os.close(fd)
        return None

    # ---------------------------------------------------------- signals
    def _install_signals(self) -> dict[Any, Any]:
        self._wake_r, self._wake_w = socket.socketpair()
        self._wake_r.setblocking(False)
        self._wake_w.setblocking(False)
        if threading.current_thread() is not threading.main_thread():  # embedded: the host handles signals
            return {}
        old: dict[Any, Any] = {"wakeup": signal.set_wakeup_fd(self._wake_w.fileno(), warn_on_full_buffer=False)}
        flags = self.flags

        def on_stop(signum: int, _frame: Any) -> None:
            if flags.stop is None:
                flags.stop = signal.Signals(signum).name
            else:
                flags.abort = True

        def on_hup(_signum: int, _frame: Any) -> None:
            flags.rescan = True

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

    # ---------------------------------------------------------- status
    def _write_status(self, state: str = "running") -> None:
        w, s = self.watcher, self.scheduler
        running = s.running()
        self.recorder.write_status(state, stopping=bool(self.flags.stop), settling=len(w.tracker), ready=len(w.ready),
                                   dispatched=s.queued() - len(running), unreadable=len(s.unreadable),
                                   running=running, paused=s.pause_status())

    # ---------------------------------------------------------- loop
    def _loop(self) -> None:
        cfg, flags = self.cfg, self.flags
        watcher, scheduler, rec = self.watcher, self.scheduler, self.recorder
        tick = min(0.25, max(cfg.settle / 4, 0.02))
        next_due = next_status = 0.0
        watchdog_usec = int(os.environ.get("WATCHDOG_USEC", "0") or 0)
        next_ping = 0.0
        draining_logged = False
        while True:
            if flags.abort:
                return
            if flags.stop:
                if not draining_logged:
                    n = scheduler.queued()
                    log.info("%s received: finishing %d file(s) in progress, then stopping", flags.stop, n,
                             extra=_ev("draining", signal=flags.stop, in_progress=n))
                    _sd_notify("STOPPING=1")
                    watcher.stop_observer()
                    draining_logged = True
                if not scheduler.inflight:
                    rec.flush_backlog()  # once more: what a full journal disk held back
                    return
            else:
                rescan, flags.rescan = flags.rescan, False
                watcher.look(rescan, self._wake_w)
                now = time.monotonic()
                if now >= next_due:
                    self._lost = self._ground_lost()
                    if self._lost:  # go on writing nowhere? no: hand the files back and stop
                        flags.abort = True
                        continue
                    rec.flush_backlog()
                    scheduler.due_retries()
                    next_due = now + self.DUE_EVERY
                scheduler.dispatch()
            scheduler.collect(tick, self._wake_r)
            scheduler.check_timeouts()
            now = time.monotonic()
            if now >= next_status:
                self._write_status()
                next_status = now + self.STATUS_EVERY
            if watchdog_usec and now >= next_ping:
                _sd_notify("WATCHDOG=1")
                next_ping = now + watchdog_usec / 2e6
