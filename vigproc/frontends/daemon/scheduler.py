"""What schedules: the worker processes (:mod:`.worker`), which file goes to which
worker, what comes back, retries, timeouts and the pause for a full output disk.

A file the watcher offers (:attr:`~.watcher.Watcher.ready`) is fingerprinted and
claimed in the journal here (:meth:`Scheduler.prepare`), in the daemon's process: a
path whose content is already done or quarantined is not sent again.  Each worker
has at most :attr:`Scheduler.per_worker` files queued (one running, one or two ready).  What
a worker says is turned into a record by the recorder: done, a failed attempt (retried
after a backoff, or quarantined), a crash (its worker died or hung while the daemon
lives), or given back uncharged (the input changed while it was processed, the disk
is full, the daemon is stopping).

A worker with a core to spare reads its next file ahead while it processes one
(:func:`.worker._read_next`): when it dies or hangs with two files open, either may have
killed or held it, so neither is charged; both are tried again *alone* (not read ahead,
nothing read ahead beside them), where a crash or a timeout names its file.  The journal
says so (:data:`ALONE` in the reason), and a file that has crashed a worker before runs
alone too, so a restart of the daemon does not give a poison file another uncharged death.

A full output disk (:data:`~vigproc.pipeline.faults.DISK_FULL`) *pauses* the
scheduler: the file goes back without an attempt counted, nothing more is handed out,
and it resumes as soon as the free space has grown, or when a probe (one file, after a
backoff that doubles up to ``retry_cap``) is written.
"""

from __future__ import annotations

import contextlib
import multiprocessing as mp
import multiprocessing.connection as mpc
import os
import socket
import time
from dataclasses import dataclass, field
from datetime import datetime, timezone
from typing import Any, Callable

from vigproc.pipeline.faults import CRASH, DISK_FULL, OUTPUT, PERMANENT, TRANSIENT, disk_space, output_trouble
from vigproc.stores.journal import FileChangedError, FingerprintError, JournalError, fingerprint, runner_identity
from vigproc.stores.retry import retry_delay

from .config import RunFlags, WatchConfig, WatchError, _signature, _Task
from .logs import _ev, log
from .recorder import Recorder
from .watcher import Watcher
from .worker import _kill_group, _worker_main

__all__ = ["Scheduler"]

#: What the journal's reason says of a file given back uncharged by a worker that died
#: with two files open: it runs alone, after a restart of the daemon too.
ALONE = "tried again alone"

#: Errors that a truncated (still being written) file also gives.
_READ_ERRORS = frozenset({"ImageReadError", "UnsupportedFormatError", "InvalidImageError"})


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
    probes: int = 0  # failed probes
    next_look: float = 0.0  # monotonic: next look at the free space
    probing: bool = False  # a probe is in flight
    held: set[str] = field(default_factory=set)  # files given back for the disk, not charged
    disk: str = "output disk"  # which disk is full: "output disk", "profile store disk"
    crashed: set[str] = field(default_factory=set)  # held files whose worker died on them in this pause


@dataclass
class _Worker:
    name: str
    process: Any
    conn: mpc.Connection
    ready: bool = False
    pid: int | None = None  # as the worker said when ready
    tasks: list[_Task] = field(default_factory=list)  # sent, in order; the first may be running
    stopping: bool = False


class Scheduler:
    """What schedules (see the module docstring).

    Parameters
    ----------
    cfg : WatchConfig
    watcher : Watcher
        Where ripe files come from (:attr:`~.watcher.Watcher.ready`) and go back to
        when they are not done with (:meth:`~.watcher.Watcher.hand_back`).
    recorder : Recorder
        Its journal claims files; it records what becomes of them.
    flags : RunFlags
        What the signals asked (stop: hand out nothing more; abort: kill the workers).
    on_status : callable
        Called when the state a status file shows changes (paused, resumed).
    """

    #: Tasks queued per worker (one running + one ready, so the worker never waits for
    #: the main process to fingerprint and claim its next file); one more where workers
    #: read ahead (:attr:`read_ahead`), so the file after the running one is there to be read.
    PER_WORKER = 2
    #: Seconds between looks at the free space while paused for a full disk.
    LOOK_EVERY = 1.0

    def __init__(self, cfg: WatchConfig, watcher: Watcher, recorder: Recorder, flags: RunFlags,
                 on_status: Callable[[], None]) -> None:
        self.cfg = cfg
        self.watcher = watcher
        self.recorder = recorder
        self.flags = flags
        self.on_status = on_status
        self.inflight: dict[str, _Task] = {}
        self.workers: list[_Worker] = []
        self.unreadable: dict[str, tuple[int, float]] = {}  # path -> (attempts, retry at, monotonic)
        self._task_ids = 0
        self._early_deaths = 0
        self._pause_until = 0.0
        self.disk: _DiskPause | None = None  # paused: the output disk is full
        self.disk_ready: set[str] = set()  # given back for the disk, due again now that there is room
        self.alone: set[str] = set()  # open together when their worker died: each is run alone until it ends
        # a worker with a core to spare reads its next file ahead; with a core a worker (or
        # fewer) it would only take time from the other workers (measured: issue 39)
        self.read_ahead = (os.cpu_count() or 1) // cfg.workers >= 2
        self.per_worker = self.PER_WORKER + self.read_ahead

    @property
    def journal(self) -> Any:
        return self.recorder.journal

    # ---------------------------------------------------------- what the status shows
    def running(self) -> list[str]:
        """The files being processed now (relative paths)."""
        return [t.rel for w in self.workers for t in w.tasks if t.started is not None]

    def queued(self) -> int:
        """Files sent to a worker (running or waiting there)."""
        return sum(len(w.tasks) for w in self.workers)

    def pause_status(self) -> dict[str, Any] | None:
        """Why nothing is handed out (the output disk is full), or None."""
        d = self.disk
        if d is None:
            return None
        return {
            "why": f"{d.disk} full", "reason": d.reason,
            "since": datetime.fromtimestamp(d.since, timezone.utc).isoformat(timespec="seconds"),
            "free_bytes": d.free_bytes, "files_waiting": len(d.held),
            "next_try_s": round(max(d.probe_at - time.monotonic(), 0.0), 1) if not d.probing else 0.0,
        }

    # ---------------------------------------------------------- workers
    def start_worker(self, index: int) -> None:
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
        """A worker died or was killed (it overran its timeout): its running file failed,
        its queued files go back.  With a file read ahead beside the running one, which of
        the two did it is unknown, a hang as much as a crash (an exiftool stuck on the file
        read ahead holds the running file's reads): neither is charged, each runs alone."""
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
        open_ = [t for t in w.tasks if t.started is not None or t.ahead]
        if len(open_) > 1:  # which of them killed it is unknown: neither is charged, each runs alone
            self.alone.update(t.path for t in open_)
            log.warning("%s %s with %d files open (%s); each is tried again alone", w.name, why, len(open_),
                        ", ".join(t.rel for t in open_), extra=_ev("worker-died-open", worker=w.name, why=why,
                                                                  files=[t.path for t in open_]))
        for t in w.tasks:
            self.inflight.pop(t.path, None)
            if t.probe and self.disk is not None:
                self.disk.probing = False
            if t.started is not None and len(open_) == 1:
                self._died_on(t, f"{why} (worker exit code {code})")
            elif len(open_) > 1 and t in open_:
                self.recorder.release(t, reason=f"{why} with {len(open_)} files open (exit code {code}): {ALONE}")
            else:
                self.recorder.release(t)
        self.recorder.remove_temps([t.path for t in w.tasks], keep=self.inflight)
        w.tasks.clear()
        if not self.flags.stop:
            log.warning("%s %s; starting a new one", w.name, why, extra=_ev("worker-restart", worker=w.name, why=why))
            self.start_worker(index)
        else:
            w.stopping = True

    def _died_on(self, task: _Task, why: str) -> None:
        """Its worker died (or hung) on ``task`` while the daemon lives: a crash the file
        caused, the only kind charged (a kill of the daemon is not: Journal.recover) --
        unless the output side was failing then (full, read-only, gone): native code may
        end its process on a write error, which is the disk's fault, not the photo's."""
        trouble = output_trouble(self.cfg.out_dir, self.cfg.min_free)
        d = self.disk
        if d is not None and trouble is None and (task.probe or task.path in d.crashed):
            # the disk shows no trouble and the file crashed alone as the probe, or crashed
            # twice in this pause: the file's fault -- else a crashing file, probed again and
            # again, would hold the daemon paused for ever (nothing else ends a fake "full")
            self.recorder.failure(task, CRASH, why)
        elif d is not None or (trouble is not None and trouble.kind == DISK_FULL):
            if d is not None:
                d.crashed.add(task.path)
            reason = f"{why} while {trouble.reason if trouble is not None else self.disk.reason}"
            self._disk_full(task, reason, trouble.space.free_bytes if trouble and trouble.space else None)
        elif trouble is not None:
            self.recorder.failure(task, OUTPUT, f"{why} while {trouble.reason}")
        else:
            self.recorder.failure(task, CRASH, why)

    def shutdown(self) -> None:
        """Stop the workers: drained ones are told to stop (and given the time to finish
        their file), after an abort they are killed; files still with them go back."""
        for w in self.workers:
            if self.flags.abort:
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
                self.recorder.release(t)
                unfinished.append(t.path)
            w.tasks.clear()
            with contextlib.suppress(OSError):
                w.conn.close()
            with contextlib.suppress(ValueError):
                w.process.close()
        if unfinished:  # their writers were killed
            self.recorder.remove_temps(unfinished)

    def check_timeouts(self) -> None:
        now = time.monotonic()
        for i, w in enumerate(self.workers):
            t = w.tasks[0] if w.tasks else None
            if t is not None and t.started is not None and now - t.started > self.cfg.timeout and not w.stopping:
                log.error("%s took more than %.0f s on %s; stopping it", w.name, self.cfg.timeout, t.rel,
                          extra=_ev("timeout", file=t.path, worker=w.name))
                _kill_group(w.process)
                w.process.join(timeout=5)
                self._worker_gone(i, f"timed out after {self.cfg.timeout:.0f} s")

    # ---------------------------------------------------------- dispatch
    def _idle_worker(self) -> _Worker | None:
        best = None
        for w in self.workers:
            if w.ready and not w.stopping and len(w.tasks) < self.per_worker:
                if best is None or len(w.tasks) < len(best.tasks):
                    best = w
        return best

    def dispatch(self) -> None:
        """Hand the ready files to idle workers (while paused for a full disk: nothing,
        or one probe)."""
        if time.monotonic() < self._pause_until:
            return
        probe = False
        if self.disk is not None:
            go = self.disk_go()
            if go is None:
                return
            probe = go == "probe"
        ready = self.watcher.ready
        while ready and not self.flags.stop:
            w = self._idle_worker()
            if w is None:
                return
            if probe and self.disk is not None:
                # the probe: one file, preferably not the one that failed last
                path = next((p for p in ready if p not in self.disk.held),
                            next((p for p in ready if p not in self.disk.crashed), next(iter(ready))))
            else:
                path = next(iter(ready))
            del ready[path]
            try:
                task = self.prepare(path)
            except JournalError as exc:  # e.g. its disk is full: keep the file, try again shortly
                log.error("journal unavailable: %s; pausing 5 s", exc, extra=_ev("journal-error", file=path))
                self.watcher.hand_back(path)
                self._pause_until = time.monotonic() + 5
                return
            if task is None:
                continue
            try:
                w.conn.send(("task", task.id, task.path, str(self.cfg.out_dir), task.stem, task.fp.to_dict(),
                             {"input": task.rel, "input_sha256": task.fp.sha256, "input_size": task.fp.size,
                              "settings": self.cfg.settings, "watch_job": self.cfg.job},
                             path in self.alone or not self.read_ahead))
            except (OSError, ValueError):  # the worker just died: the next wait() sees it
                self.recorder.release(task)
                self.watcher.hand_back(path)
                continue
            w.tasks.append(task)
            self.inflight[path] = task
            if probe and self.disk is not None:
                task.probe = self.disk.probing = True
                log.info("output disk full: trying %s to see whether there is room again", task.rel,
                         extra=_ev("disk-probe", file=task.path))
                return

    def prepare(self, path: str) -> _Task | None:
        """Fingerprint and claim a ripe file; None if there is nothing to do (yet)."""
        journal = self.journal
        sig = _signature(path)
        if sig is None:
            entry = journal.lookup(path)
            if entry is not None and entry.state == "pending":
                journal.forget(path)  # deleted before it was processed: nothing to do
            return None
        retry = self.unreadable.get(path)
        if retry is not None and time.monotonic() < retry[1]:
            return None
        try:
            fp = fingerprint(path)
        except FileChangedError:
            self.watcher.hand_back(path)
            return None
        except FingerprintError as exc:
            self._unreadable(path, sig, exc)
            return None
        self.unreadable.pop(path, None)
        entry = journal.lookup(path)
        if entry is not None and entry.fingerprint.same_content(fp) and entry.state in ("done", "quarantined"):
            if entry.fingerprint.mtime_ns != fp.mtime_ns:
                journal.touch(path, fp)
            self.recorder.known[path] = (fp.size, fp.mtime_ns)
            self.recorder.after_finished(path, fp, entry.state, entry.reason)
            return None
        if entry is not None and entry.fingerprint.same_content(fp) \
                and (entry.crashes > 0 or ALONE in (entry.reason or "")):
            self.alone.add(path)  # it died with a file beside it or crashed before (this run or an earlier one)
        # a file given back for a full disk is due as soon as there is room, whatever its retry time
        now = float("inf") if path in self.disk_ready else None
        if not journal.claim(path, fp, worker=f"{os.uname().nodename}:{os.getpid()}", now=now):
            return None  # waiting for its retry time (due() brings it back) or running elsewhere
        self.disk_ready.discard(path)
        self._task_ids += 1
        rel = os.path.relpath(path, self.cfg.in_dir)
        return _Task(self._task_ids, path, rel, rel, fp)

    def _unreadable(self, path: str, sig: tuple[int, int, int], exc: FingerprintError) -> None:
        attempts = self.unreadable.get(path, (0, 0.0))[0] + 1
        if exc.transient and attempts < self.cfg.max_attempts:
            delay = retry_delay(attempts, self.cfg.retry_base, self.cfg.retry_cap)
            self.unreadable[path] = (attempts, time.monotonic() + delay)
            log.warning("%s: %s; trying again in %.0f s", path, exc, delay, extra=_ev("unreadable", file=path))
            return
        self.unreadable.pop(path, None)
        self.recorder.unreadable(path, sig, str(exc))

    def due_retries(self) -> None:
        """Offer again the files whose retry time has come (the journal's, and those that
        could not be read to fingerprint them)."""
        ready = self.watcher.ready
        now = time.monotonic()
        for path, (_n, at) in self.unreadable.items():
            if now >= at and path not in self.inflight:
                ready[path] = None
        for path, _fp in self.journal.due(limit=1000):  # a huge backlog comes back in slices
            if path not in self.inflight and not self.watcher.waiting(path):
                if os.path.lexists(path):
                    ready[path] = None
                else:
                    self.journal.forget(path)

    # ---------------------------------------------------------- results
    def collect(self, timeout: float, wake: socket.socket | None) -> None:
        """Wait up to ``timeout`` seconds for what the workers say (or for ``wake``: a file
        event, a signal) and act on it; a worker that died is replaced."""
        objs: list[Any] = [wake] if wake is not None else []
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
            if obj is wake:
                with contextlib.suppress(OSError):
                    while wake.recv(4096):
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
        if kind == "ahead":
            task.ahead = True
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
        self.alone.discard(task.path)  # ended: what it did is its own
        if task.probe and self.disk is not None:
            self.disk.probing = False
        if self._changed(task):
            return
        if kind == "ok":
            if task.probe and self.disk is not None:
                self._disk_resume(f"{task.rel} was written")
            self.recorder.done(task, payload, w.name)
        else:
            kind_, reason = payload["kind"], payload["reason"]
            if kind_ == DISK_FULL:  # the machine's fault, not the photo's: no attempt counted
                self._disk_full(task, reason, payload.get("free_bytes"), payload.get("disk") or "output disk")
                return
            if self.flags.stop and kind_ == TRANSIENT:
                # the stop signal may have reached exiftool too (systemd can signal every
                # process; vigproc.io.metadata marks that transient): not the file's fault, so
                # it goes back without an attempt (judged by kind: the reason carries the name)
                self.recorder.release(task)
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
            self.recorder.failure(task, kind_, reason)

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
        self.recorder.release(task)
        self.recorder.stats["released"] += 1
        if sig is not None:
            log.info("%s changed while it was processed; it will be processed again", task.path,
                     extra=_ev("changed", file=task.path))
            self.watcher.hand_back(task.path)
        else:
            log.info("%s disappeared while it was processed", task.path, extra=_ev("vanished", file=task.path))
        return True

    # ---------------------------------------------------------- full output disk
    def _disk_full(self, task: _Task, reason: str, free_bytes: int | None, disk: str = "output disk") -> None:
        """``task`` failed for want of space on the output disk: give it back uncharged,
        and pause (or stay paused, backing off if it was the probe)."""
        cfg = self.cfg
        now = time.monotonic()
        if free_bytes is None:
            sp = disk_space(cfg.out_dir)
            free_bytes = sp.free_bytes if sp is not None else None
        d = self.disk
        if d is None:
            d = self.disk = _DiskPause(reason=reason, since=time.time(), disk=disk, free_bytes=free_bytes,
                                       delay=max(cfg.retry_base, 0.1), probe_at=now + max(cfg.retry_base, 0.1))
            self.recorder.stats["disk_full"] += 1
            log.warning("%s full, paused: %s (%s); nothing is quarantined for it, the files are tried "
                        "again when there is room", disk, reason, task.rel,
                        extra=_ev("disk-full", file=task.path, reason=reason, free_bytes=free_bytes))
        else:
            d.reason, d.disk, d.free_bytes = reason, disk, free_bytes  # the latest look: the growth that resumes is from here
            if task.probe:
                d.probes += 1
                d.delay = retry_delay(d.probes + 1, max(cfg.retry_base, 0.1), max(cfg.retry_cap, cfg.retry_base))
                d.probe_at = now + d.delay
                log.warning("%s still full (%s); next try in %.0f s", disk, reason, d.delay,
                            extra=_ev("disk-still-full", file=task.path, reason=reason, retry_in=round(d.delay, 1)))
        d.held.add(task.path)
        self.disk_ready.discard(task.path)
        # back to pending with no attempt counted; the pause holds it here, the short delay is
        # for a restart (which finds out about the disk afresh)
        self.recorder.release(task, not_before=time.time() + cfg.retry_base, reason=reason)
        self.on_status()

    def disk_go(self) -> str | None:
        """While paused for a full disk: None (hand out nothing yet), ``"probe"`` (one
        file, to see whether it fits) or ``"resume"`` (the free space grew: carry on)."""
        cfg, d = self.cfg, self.disk
        assert d is not None
        ready = self.watcher.ready
        now = time.monotonic()
        if now >= d.next_look:
            d.next_look = now + self.LOOK_EVERY
            sp = disk_space(cfg.out_dir)
            # grown, not merely "not low": a quota (EDQUOT) or a full disk that reported
            # plenty would otherwise resume and fail again every second
            grown = d.free_bytes is None or sp is None or sp.free_bytes >= d.free_bytes + max(cfg.min_free // 4, 1 << 20)
            if sp is not None and not sp.low(cfg.min_free) and grown:
                self._disk_resume(sp.describe())
                return "resume"
        if d.probing or now < d.probe_at:
            return None
        if not ready:  # nothing new to try: one of the files given back
            for p in sorted(d.held, key=lambda p: (p in d.crashed, p)):  # one that crashed comes last
                if p not in self.inflight and os.path.lexists(p):
                    ready[p] = None
                    self.disk_ready.add(p)
                    break
        if not ready:
            return None
        d.probe_at = now + d.delay  # also if the probe fails for another reason
        return "probe"

    def _disk_resume(self, why: str) -> None:
        d, self.disk = self.disk, None
        if d is None:
            return
        back = [p for p in sorted(d.held) if p not in self.inflight and os.path.lexists(p)]
        for p in back:
            self.watcher.ready[p] = None
            self.disk_ready.add(p)
        log.info("output disk has room again (%s): resumed after %.0f s; %d file(s) given back are tried again",
                 why, time.time() - d.since, len(back),
                 extra=_ev("disk-resumed", why=why, paused_s=round(time.time() - d.since, 1), files=len(back)))
        self.on_status()
