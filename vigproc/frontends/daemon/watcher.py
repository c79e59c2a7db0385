"""What watches: the paths the daemon is to look at, from file system events (watchdog's
native observer, or its polling observer for network shares) and rescans of the
folder (at start, every ``rescan`` seconds, on SIGHUP, for a new sub-folder), filtered
to candidates (:meth:`Watcher.wanted`), held until they settle (:class:`SettleTracker`)
and then offered, in order, in :attr:`Watcher.ready`.

The watcher decides nothing about a file's content: the scheduler fingerprints and
claims what it takes from :attr:`Watcher.ready`; the recorder's :attr:`~.recorder.Recorder.known`
(files finished this run, by size and mtime) keeps an unchanged finished file from
being offered again.
"""

from __future__ import annotations

import contextlib
import os
import queue
import socket
import time
from typing import Any, Callable, Iterable

from vigproc.stores.journal import JournalError

from .config import IGNORED_DIRS, WatchConfig, WatchError, _inside, _signature, is_candidate_name
from .logs import _ev, log
from .recorder import Recorder

__all__ = ["SettleTracker", "Watcher"]


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


class Watcher:
    """What watches (see the module docstring).

    Parameters
    ----------
    cfg : WatchConfig
    recorder : Recorder
        Its journal is looked up on rescans; a file found finished but not yet moved to
        the archive or quarantine folder (a crash between the journal and the move) is
        handed to it again.
    busy : callable
        Whether a path is being processed now (the scheduler's in-flight files): not
        looked at until its result is back.
    """

    def __init__(self, cfg: WatchConfig, recorder: Recorder, busy: Callable[[str], bool]) -> None:
        self.cfg = cfg
        self.recorder = recorder
        self.busy = busy
        self.tracker = SettleTracker(cfg.settle)
        self.events: queue.SimpleQueue[tuple[str, str]] = queue.SimpleQueue()
        self.ready: dict[str, None] = {}  # ripe paths, in order (an ordered set)
        self.next_rescan = 0.0
        self._observer: Any = None
        self._excluded = cfg.excluded_dirs()

    # ---------------------------------------------------------- observer
    def start_observer(self, wake: socket.socket | None) -> None:
        """Start the file system observer; each event also writes a byte to ``wake``
        (the daemon's loop waits on it)."""
        from watchdog.events import FileSystemEventHandler

        events = self.events

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

    def stop_observer(self) -> None:
        if self._observer is not None:
            with contextlib.suppress(Exception):
                self._observer.stop()
                self._observer.join(timeout=10)
            self._observer = None

    # ---------------------------------------------------------- one look
    def look(self, rescan: bool, wake: socket.socket | None) -> None:
        """One turn of the daemon's loop: take the events, rescan if asked (SIGHUP) or
        due (restarting an observer that died), and offer the files that have settled."""
        self.handle_events()
        now = time.monotonic()
        if rescan or now >= self.next_rescan:
            if self._observer is not None and not self._observer.is_alive():
                log.warning("file system observer stopped; restarting it", extra=_ev("observer-restart"))
                self.stop_observer()
                with contextlib.suppress(WatchError, OSError):
                    self.start_observer(wake)
            self.rescan()
        for path in self.tracker.ripe():
            self.ready[path] = None

    # ---------------------------------------------------------- discovery
    def wanted(self, path: str) -> bool:
        """Whether ``path`` is a candidate: an image name (not a writer's temporary one)
        inside the watch folder, not in a hidden or ignored folder nor in our own output,
        quarantine or archive folder."""
        if not _inside(path, str(self.cfg.in_dir)) or path == str(self.cfg.in_dir):
            return False
        if any(_inside(path, d) for d in self._excluded):
            return False
        rel = os.path.relpath(path, self.cfg.in_dir)
        parts = rel.split(os.sep)
        if any(p.startswith(".") or p in IGNORED_DIRS for p in parts[:-1]):
            return False
        return is_candidate_name(parts[-1])

    def seen(self, path: str) -> None:
        """An event named ``path``: watch it settle (unless it is finished and unchanged)."""
        if not self.wanted(path) or self.busy(path):
            return  # a changed in-flight file is caught when its result comes back
        known = self.recorder.known.get(path)
        if known is not None:
            sig = _signature(path)
            if sig is not None and sig[:2] == known:
                return
            self.recorder.known.pop(path, None)
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

    def rescan(self, top: str | None = None) -> None:
        """Look at every file under the watch folder (or ``top``): what events missed,
        what arrived while we were down, what a crash left half-moved."""
        t0 = time.monotonic()
        n = 0
        if not self.cfg.in_dir.is_dir():
            log.error("watch folder %s is gone (unmounted?); waiting for it", self.cfg.in_dir,
                      extra=_ev("folder-missing"))
            return
        self.next_rescan = time.monotonic() + self.cfg.rescan
        known = self.recorder.known
        for path in self._walk(top or str(self.cfg.in_dir)):
            if not self.wanted(path) or self.busy(path) or path in self.ready:
                continue
            sig = _signature(path)
            if sig is None:
                continue
            if known.get(path) == sig[:2]:
                continue
            try:
                entry = self.recorder.journal.lookup(path)
            except JournalError as exc:
                log.error("rescan stopped, journal unavailable: %s", exc, extra=_ev("journal-error"))
                self.next_rescan = time.monotonic() + 10
                return
            if (entry is not None and entry.state in ("done", "quarantined")
                    and (entry.fingerprint.size, entry.fingerprint.mtime_ns) == sig[:2]):
                known[path] = sig[:2]  # same size and mtime as when it was finished: no need to hash it
                self.recorder.after_finished(path, entry.fingerprint, entry.state, entry.reason)
                continue
            self.tracker.see(path)
            n += 1
        log.debug("rescan of %s: %d file(s) to look at (%.2f s)", top or self.cfg.in_dir, n, time.monotonic() - t0,
                  extra=_ev("rescan", files=n))

    def handle_events(self) -> None:
        while True:
            try:
                kind, path = self.events.get_nowait()
            except queue.Empty:
                return
            if kind == "file":
                self.seen(path)
            elif kind == "dir":
                if self.wanted(os.path.join(path, "x.jpg")):  # not inside an excluded/hidden folder
                    self.rescan(path)
            elif kind == "gone":
                self.tracker.forget(path)
                self.ready.pop(path, None)
                self.recorder.known.pop(path, None)

    def hand_back(self, path: str) -> None:
        """A path taken from :attr:`ready` that is not done with: watch it settle again."""
        self.tracker.see(path)

    def waiting(self, path: str) -> bool:
        """Whether ``path`` is settling or ready (on its way to the scheduler)."""
        return path in self.ready or path in self.tracker
