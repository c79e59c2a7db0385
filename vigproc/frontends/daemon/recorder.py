"""What records: every step of a file in the :class:`~vigproc.stores.journal.Journal`
(done, failed and retried, crashed, quarantined, given back), the moves of finished
inputs to the archive or quarantine folder (with the quarantined file's reason
sidecar), the status file, and the clean-up of what an interrupted run left.

Order is what makes a kill safe:

* a result is in the journal before its input is moved: a kill between the two leaves
  a finished entry whose file is still in the watch folder, and the next look at it
  (:meth:`Recorder.after_finished`, from a rescan or a claim) moves it then;
* a move never loses the file (:func:`_move`: a hard link or an atomically published
  copy first, the source unlinked after) and a quarantined file's reason sidecar is
  written before the file gets there;
* a journal write that fails (its disk full too?) is kept and tried again in order
  (:meth:`Recorder.flush_backlog`) rather than lost; meanwhile the entry stays
  ``running``, so nothing else takes the file, and a restart hands it back (and finds
  its sidecar, if it was done).
"""

from __future__ import annotations

import contextlib
import errno
import fcntl
import json
import os
import shutil
import time
from collections import deque
from datetime import datetime, timezone
from pathlib import Path
from typing import Any, Callable, Iterable

from vigproc.atomic import replacing
from vigproc.errors import VigprocError
from vigproc.pipeline.faults import CRASH, PERMANENT, attempt_limit
from vigproc.pipeline.processor import SIDECAR_SUFFIX, output_location, safe_output, sweep_temporaries
from vigproc.stores.journal import Fingerprint, FingerprintError, Journal, JournalError, boot_id, fingerprint

from .config import REASON_SUFFIX, WatchConfig, _inside, _signature, _Task, output_stem
from .logs import _ev, _sd_notify, log
from .worker import _read_sidecar

__all__ = ["Recorder", "read_status"]


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
        with replacing(dst, prefix=".vigproc-move.") as tmp:
            shutil.copyfile(src, tmp)
            shutil.copystat(src, tmp)
    os.unlink(src)
    return dst


# ------------------------------------------------------------------ status
def read_status(cfg: WatchConfig) -> dict[str, Any]:
    """What ``vigproc watch --status`` shows: the daemon's status file (if any), whether
    it is running (it holds the job lock) and the journal's counts."""
    out: dict[str, Any] = {"in_dir": str(cfg.in_dir), "out_dir": str(cfg.out_dir), "job": cfg.job,
                           "journal": str(cfg.journal), "running": False}
    if cfg.lock_file.exists():
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
    with replacing(path, prefix=f".{path.name}.", suffix=".tmp", mode=0o644, sync=False) as tmp, \
            open(tmp, "w", encoding="utf-8") as fh:
        json.dump(data, fh, indent=1)
        fh.write("\n")


# ------------------------------------------------------------------ the recorder
class Recorder:
    """What records (see the module docstring).  :attr:`journal` is set by the daemon
    once it holds the job's lock.

    Attributes
    ----------
    known : dict
        path -> (size, mtime_ns) of the files done or quarantined this run: the watcher
        does not offer them again while they are unchanged.
    stats : dict
        This run's counts, as the status file and the ``stopped`` log line give them.
    """

    def __init__(self, cfg: WatchConfig) -> None:
        self.cfg = cfg
        self.journal: Journal = None  # type: ignore[assignment]  # opened by Daemon.run
        self.known: dict[str, tuple[int, int]] = {}  # path -> (size, mtime_ns) done/quarantined this run
        # "failed_attempts": attempts that failed this run (a file retried once, then
        # quarantined, counts 2); the journal's "failed" is files waiting to retry now
        self.stats = {"done": 0, "failed_attempts": 0, "quarantined": 0, "retried": 0, "recovered": 0, "released": 0,
                      "disk_full": 0}
        self._counts: dict[str, int] = {}
        self._started = time.time()
        self._rates: deque[float] = deque(maxlen=100_000)  # monotonic times of recent completions
        # journal writes that failed (its disk full too?), retried in order until they succeed
        self._backlog: deque[Callable[[], None]] = deque()
        self._backlog_ids: set[int] = set()  # tasks whose journal write failed once (logged once)

    # ---------------------------------------------------------- at start
    def recover(self) -> None:
        """Hand back the files that a stopped run left running, uncharged (Journal.recover):
        the daemon's own death (kill -9, a power cut) is not the files' fault.  A file that
        kills its worker is charged while the daemon lives (:meth:`failure`)."""
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

    def return_quarantined(self, wanted: Callable[[str], bool]) -> int:
        """Move this job's files in the ``--quarantine`` folder back to where they were
        found (the ``file`` of their reason file), so that ``--retry-quarantined`` finds
        them: the journal knows files by their path in the watch folder.  A file whose
        place is taken by other content is put beside it (:func:`_move`), never over it;
        one whose place is not a candidate in the watch folder (``wanted``) stays.
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
            if not _inside(str(dst), str(cfg.in_dir)) or dst == cfg.in_dir or not wanted(str(dst)):
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

    def remove_stale_temps(self, unfinished: list[str]) -> None:
        """Temporary files that the outputs of ``unfinished`` inputs (running or pending when
        the last run stopped) and our status file were being written to when their writer
        was killed: nothing writes them now."""
        cfg = self.cfg
        removed = self.remove_temps(unfinished)
        with contextlib.suppress(OSError), os.scandir(cfg.status_file.parent) as it:
            for e in it:
                if e.name.startswith(f".{cfg.status_file.name}.") and e.name.endswith(".tmp"):
                    with contextlib.suppress(OSError):
                        os.unlink(e.path)
                        removed += 1
        if removed:
            log.info("removed %d temporary file(s) left by the interrupted run", removed,
                     extra=_ev("cleanup", count=removed))

    def remove_temps(self, paths: Iterable[str], keep: Iterable[str] = ()) -> int:
        """Remove the temporary files that the outputs of the inputs ``paths`` were being
        written to by a writer that is dead now, none of ``keep`` (still being written):
        :func:`vigproc.pipeline.processor.sweep_temporaries`."""
        in_dir = str(self.cfg.in_dir)

        def rels(ps: Iterable[str]) -> list[str]:
            return [os.path.relpath(p, in_dir) for p in ps if _inside(p, in_dir)]

        return sweep_temporaries(self.cfg.out_dir, rels(paths), keep=rels(keep))

    # ---------------------------------------------------------- a file's end
    def done(self, task: _Task, summary: dict[str, Any], worker: str) -> None:
        """``task``'s file was processed by ``worker``: journaled, then archived if asked."""
        summary = {**summary, "worker": worker}
        try:
            self.journal.done(task.path, task.fp, summary)
        except JournalError as exc:
            self._later(task, "as done", exc, lambda: self.done(task, summary, worker))
            return
        self.known[task.path] = (task.fp.size, task.fp.mtime_ns)
        self.stats["done"] += 1
        if summary.get("recovered"):
            self.stats["recovered"] += 1
        self._rates.append(time.monotonic())
        # a frame nothing was applied to says so: its output (if any) is the original
        why = f"; not corrected: {summary['not_applied']}" if summary.get("not_applied") else ""
        if summary.get("learned"):  # learning as you go: where the frame went
            why += f"; {summary['learned']}"
        log.info("done %s -> %s (%s, %.2f s%s)", task.rel, summary.get("output") or summary.get("sidecar"),
                 summary.get("source"), summary.get("seconds") or 0.0, why,
                 extra=_ev("done", file=task.path, sha256=task.fp.sha256, output=summary.get("output"),
                           sidecar=summary.get("sidecar"), not_applied=summary.get("not_applied"),
                           source=summary.get("source"), seconds=summary.get("seconds"), worker=worker,
                           verdict=summary.get("verdict"), recovered=summary.get("recovered"),
                           learned=summary.get("learned")))
        self.after_finished(task.path, task.fp, "done", None)

    def failure(self, task: _Task, kind: str, reason: str) -> None:
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
            self._later(task, f"as {'crashed' if crash else 'failed'} ({reason})", exc,
                        lambda: self.failure(task, kind, reason))
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
        self.after_finished(task.path, task.fp, "quarantined", reason, earlier)

    def unreadable(self, path: str, sig: tuple[int, int, int], reason: str) -> None:
        """Quarantine a file that cannot even be read to fingerprint it (for good)."""
        self.journal.quarantine(path, Fingerprint(sig[0], sig[1], "unreadable"), reason)
        self.known[path] = sig[:2]
        self.stats["quarantined"] += 1
        log.error("quarantined %s: %s", path, reason, extra=_ev("quarantined", file=path, reason=reason))

    def _earlier_outputs(self, rel: str, fp: Fingerprint) -> list[str]:
        """The sidecar and output in the output folder for ``rel`` when they record
        another content than ``fp`` (the file was replaced and its new content failed)."""
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

    def release(self, task: _Task, not_before: float = 0.0, reason: str | None = None) -> None:
        """Give ``task``'s file back (pending, no attempt charged)."""
        try:
            self.journal.release(task.path, task.fp, not_before=not_before, reason=reason)
        except JournalError as exc:
            self._later(task, "as given back", exc, lambda: self.release(task, not_before, reason))

    def _later(self, task: _Task, what: str, exc: JournalError, again: Callable[[], None]) -> None:
        """A journal write failed (its disk may be full too): try it again later rather than
        lose the result.  Meanwhile the entry stays ``running``, so nothing else takes the
        file; a restart would hand it back (and find its sidecar, if it was done)."""
        first = task.id not in self._backlog_ids
        self._backlog_ids.add(task.id)
        (log.error if first else log.debug)("%s: cannot record it %s in the journal: %s; trying again shortly",
                                            task.rel, what, exc, extra=_ev("journal-error", file=task.path))
        self._backlog.append(again)

    def flush_backlog(self) -> None:
        """Retry the journal writes that failed (each puts itself back if it fails again)."""
        for _ in range(len(self._backlog)):
            self._backlog.popleft()()

    def after_finished(self, path: str, fp: Fingerprint, state: str, reason: str | None,
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

    # ---------------------------------------------------------- status
    def write_status(self, state: str, *, stopping: bool, settling: int, ready: int, dispatched: int,
                     unreadable: int, running: list[str], paused: dict[str, Any] | None) -> None:
        """Rewrite the status file (what ``vigproc watch --status`` shows) and tell systemd.

        ``state`` is ``running`` (``paused`` while ``paused`` says why, ``draining``
        once ``stopping``), ``stopped`` or ``aborted``; the queue's counts are the
        watcher's (``settling``, ``ready``) and the scheduler's (``dispatched``,
        ``unreadable``: waiting to be read again), ``running`` the files being processed."""
        cfg = self.cfg
        with contextlib.suppress(JournalError):
            self._counts = self.journal.counts()
        now = time.monotonic()
        recent = [t for t in self._rates if now - t <= 60]
        if state == "running" and paused is not None:
            state = "paused"
        st = {
            "state": state if not stopping or state not in ("running", "paused") else "draining",
            "pid": os.getpid(), "in_dir": str(cfg.in_dir), "out_dir": str(cfg.out_dir), "job": cfg.job,
            "mode": cfg.settings.get("mode"), "workers": cfg.workers,
            "started": datetime.fromtimestamp(self._started, timezone.utc).isoformat(timespec="seconds"),
            "updated": datetime.now(timezone.utc).isoformat(timespec="seconds"), "updated_epoch": time.time(),
            "queue": {"settling": settling, "ready": ready, "dispatched": dispatched,
                      "retry_wait": self._counts.get("failed", 0) + unreadable},
            "running": running, "journal": self._counts, "this_run": dict(self.stats),
            "files_per_min": len(recent),
        }
        if paused is not None:
            st["paused"] = paused
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
