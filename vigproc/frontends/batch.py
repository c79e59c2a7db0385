"""Batch jobs: whole archives through the pipeline, on local cores or a Dask cluster.

A task is one file.  The *client* (the process that runs ``vigproc batch``) collects
the files, keeps the journal and, in learn mode, is the only writer of the profile
store.  *Workers* (local processes or ``dask.distributed`` workers) fingerprint a
file, run it through a per-process :class:`vigproc.pipeline.processor.Processor` and write its
outputs, atomically, into the output tree; they return what they did.

Resumable and exactly-once
--------------------------
Every input gets one deterministic output location: ``OUT/<its path relative to
DIR>`` (or its absolute path, for a list of files), named after the full file name
(``a/IMG_1.jpg`` → ``OUT/a/IMG_1.jpg.vigproc.json``), so two ``IMG_1.jpg`` in
different folders, or ``x.jpg`` and ``x.png``, never share an output, and a rerun
writes the same names.  Outputs are published by rename (:mod:`vigproc.atomic`), so a
worker killed mid-task leaves no half file, and a retried or repeated task replaces
its own outputs.  The journal (:mod:`vigproc.stores.journal`, SQLite, client side only)
records a file as done, with its content fingerprint, only after its outputs exist:
a killed worker's task is rerun (by the scheduler or here), an interrupted job is
resumed by running the same command again, and a file whose content changed is new
work.

The job is three modules, one concept each: its inputs (:mod:`vigproc.frontends.batch_inputs`),
what a worker does with one file (:mod:`vigproc.frontends.batch_worker`) and, here, the
client that runs the job; the public names of the first two are re-exported here.

Learn mode pools across workers without a shared database: workers hand each
frame's estimate (model with covariance, profile key) back, and the client pools it
with :meth:`vigproc.stores.profiles.ProfileStore.learn` as results stream in.  The store's
sums are exact, so the pooled profile does not depend on the order in which frames
finish.  Modes that read profiles (``correct --profile auto``, ``check``) get a
consistent snapshot of the store taken by the client at the start of the job and
shipped to every worker, which opens it from a private local temporary file: no
SQLite file is ever shared over the network, and every frame of the job sees the
same profiles.

Correct mode that learns as it goes (``Settings.learn``, :mod:`vigproc.pipeline.learning`):
local workers open the client's own store (``JobSpec.store_path``, on this machine), pool
their frames there keyed by their content (``BEGIN IMMEDIATE`` serialises the workers; a
frame pooled before a crash is not pooled again) and read the profiles as they become
trusted.  A cluster's workers cannot share the store (``JobSpec.client_learns``): they
read the job's snapshot plus what the client hands out (:class:`Handout`: each lens
setting's applied revision and its profile pooled so far) and return each frame's
pooled material (:func:`vigproc.pipeline.learning.pooled_of`'s fit and evidence) with
its record; the client pools it into the store, keyed by content as above, applies the
series rule there (:class:`~vigproc.pipeline.learning.SteadyProfiles`) and hands the
revision it applies to the tasks it submits next.

References
----------
dask.distributed: "Futures" (``Client.submit``, ``as_completed``, retries) and
"Worker plugins", https://distributed.dask.org/.
SQLite, "Online backup API" and "sqlite3_serialize", https://www.sqlite.org/.
"""

from __future__ import annotations

import collections
import contextlib
import dataclasses
import fcntl
import hashlib
import json
import logging
import math
import os
import sqlite3
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Iterable, Iterator

from vigproc.atomic import atomic_write_text
from vigproc.errors import ImageWriteError, VigprocError  # noqa: F401  (ImageWriteError: its old import path)
from vigproc.frontends.batch_inputs import (NETWORK_FS, BatchError, BatchItem, check_local_disk, collect,
                                            collect_dir, filesystem_type, read_list)
from vigproc.frontends.batch_worker import (Handout, JobSpec, Outcome, Shipped, Task, release_worker_state,
                                            run_task, warm_up, worker_name)
from vigproc.pipeline.faults import DISK_FULL, attempt_limit
from vigproc.pipeline.learning import Learned, SteadyProfiles
from vigproc.pipeline.processor import Settings, sweep_temporaries
from vigproc.stores.journal import Journal, fingerprint
from vigproc.stores.retry import DEFAULT_MAX_ATTEMPTS

__all__ = ["BREAKER_FILES", "JOURNAL_NAME", "NETWORK_FS", "BatchError", "BatchItem", "BatchSummary", "Handout",
           "JobSpec", "Outcome", "Shipped", "Task", "check_local_disk", "collect", "collect_dir",
           "filesystem_type", "job_id", "read_list", "release_worker_state", "run_batch", "run_task",
           "snapshot_store", "warm_up", "worker_name"]

log = logging.getLogger(__name__)

#: Permanent failures of the first files that stop a job when all alike (a setup problem).
BREAKER_FILES = 12
#: Default journal file name inside the output folder.
JOURNAL_NAME = ".vigproc-batch.sqlite"


def job_id(source: str | os.PathLike[str], outdir: str | os.PathLike[str], settings: Settings,
           profile_digest: str | None = None) -> str:
    """Journal job name: a rerun of the same source, output folder and settings
    resumes; other settings are another job (its outputs differ)."""
    d = {"source": str(Path(source).resolve()), "out": str(Path(outdir).resolve()), "settings": settings.to_dict(),
         "profile_file": profile_digest}
    return f"batch-{settings.mode}-" + hashlib.sha256(json.dumps(d, sort_keys=True).encode()).hexdigest()[:12]



def snapshot_store(store) -> bytes:
    """A consistent copy of the profile store's database (SQLite online backup), as bytes."""
    mem = sqlite3.connect(":memory:")
    try:
        store.con.backup(mem)
        return mem.serialize()
    except sqlite3.Error as exc:
        raise BatchError(f"cannot snapshot profile store {store.path}: {exc}") from None
    finally:
        mem.close()


@dataclass
class BatchSummary:
    """What a batch run did.

    Attributes
    ----------
    total : int
        Input files of the job.
    processed : int
        Files processed (and journaled done) by this run.
    skipped : int
        Files already done (same content) by an earlier run.
    quarantined : int
        Files that failed for good (now or earlier, same content); rerunning skips them.
    retry_later : int
        Files that failed transiently beyond the retries, or for the output side's
        fault; a rerun tries them again.
    missing : int
        Listed files that do not exist.
    disk_full : str or None
        Set when the output disk filled: the run stopped handing out files (every
        one would fail), journaled none of them against the photos, and left
        ``not_started`` files for a rerun.
    """

    job: str
    journal: str
    backend: str
    mode: str
    total: int = 0
    processed: int = 0
    skipped: int = 0
    quarantined: int = 0
    retry_later: int = 0
    missing: int = 0
    resubmitted: int = 0
    redone: int = 0
    swept: int = 0
    interrupted: bool = False
    disk_full: str | None = None  # why the run stopped handing out files: the output disk is full
    not_started: int = 0  # files left untouched after that (a rerun does them)
    seconds: float = 0.0
    errors: list[dict[str, str]] = field(default_factory=list)
    profiles: dict[str, dict[str, Any]] = field(default_factory=dict)
    sources: dict[str, int] = field(default_factory=dict)

    @property
    def files_per_second(self) -> float:
        return self.processed / self.seconds if self.seconds > 0 else 0.0

    @property
    def failed(self) -> int:
        return self.quarantined + self.retry_later + self.missing

    def to_dict(self) -> dict[str, Any]:
        d = dataclasses.asdict(self)
        d["files_per_second"] = round(self.files_per_second, 3)
        d["failed"] = self.failed
        return d


_MAX_ERRORS = 100


def _journal_result(rec: dict[str, Any], worker: str) -> dict[str, Any]:
    keep = ("output", "picture", "sidecar", "source", "applied", "profile", "seconds")
    d = {k: rec[k] for k in keep if k in rec}
    d["lens_id"] = (rec.get("lens") or {}).get("lens_id")
    d["worker"] = worker
    return d


def run_batch(
    items: list[BatchItem],
    spec: JobSpec,
    backend,
    *,
    journal_path: str | os.PathLike[str],
    job: str,
    store=None,
    retries: int = 2,
    missing: Iterable[str] = (),
    progress: bool | None = None,
    on_result: Callable[[BatchSummary, Task, Outcome | BaseException], None] | None = None,
    window: int | None = None,
    retry_quarantined: bool = False,
) -> BatchSummary:
    """Run ``items`` through ``backend``, journaled and resumable.

    Parameters
    ----------
    items : list of BatchItem
        From :func:`collect`.
    spec : JobSpec
    backend
        :func:`vigproc.frontends.backends.local_backend` or :func:`vigproc.frontends.backends.dask_backend`; started and closed here.
    journal_path : path
        SQLite journal (on a local disk); ``job`` names this job in it.
    store : ProfileStore, optional
        Learn mode, and learning as it goes on a cluster (``spec.client_learns``): the
        store the client pools the workers' frames into (its one writer).
    retries : int
        Immediate resubmissions of a task whose worker died or that failed
        transiently; after that the file is journaled as failed (a later run retries
        it until the journal quarantines it).
    missing : iterable of str
        Listed files that do not exist (reported in the summary).
    progress : bool, optional
        Show a tqdm bar on stderr (default: when stderr is a terminal).
    on_result : callable, optional
        Called after each result as ``on_result(summary, task, outcome)`` (tests,
        front ends); may raise KeyboardInterrupt to stop the job.
    window : int, optional
        Tasks in flight (default 2 per worker thread): bounded so that an archive
        of millions of files is streamed, not submitted at once.
    retry_quarantined : bool
        Give the files quarantined by earlier runs another chance (after the cause
        was fixed).

    Returns
    -------
    BatchSummary
        ``interrupted`` is set if the run was stopped (Ctrl-C); rerun to resume.
    """
    learn = spec.settings.mode == "learn"
    if (learn or spec.client_learns) and store is None:
        raise BatchError("learn mode needs a profile store" if learn else
                         "learning as it goes on a cluster needs the client's profile store")
    if spec.client_learns and not hasattr(backend, "hand_out"):
        raise BatchError("the client pools frames for a cluster backend only (local workers pool into the "
                         "store itself: JobSpec.store_path)")
    missing = list(missing)
    summary = BatchSummary(job=job, journal=str(journal_path), backend="", mode=spec.settings.mode,
                           total=len(items) + len(missing))
    for m in missing:
        summary.missing += 1
        _note_error(summary, m, "not a file", "missing")
    jpath = Path(journal_path)
    try:
        jpath.parent.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise BatchError(f"cannot create the folder of journal {jpath}: {exc.strerror or exc}") from None
    try:
        with _job_lock(jpath, job), Journal(jpath, job=job) as journal:
            recovered = journal.recover()
            if recovered:
                log.info("recovered %d entries left running by an interrupted run", recovered)
            if retry_quarantined:
                log.info("%d quarantined files get another chance", journal.requeue("quarantined"))
            run = _Run(items, spec, backend, journal, summary, store=store if learn or spec.client_learns else None,
                       retries=retries, window=window)
            show = sys.stderr.isatty() if progress is None else progress
            if show:
                from tqdm import tqdm

                run.bar = tqdm(total=summary.total, unit="file", desc=f"vigproc batch {spec.settings.mode}")
                run.bar.update(summary.missing)
            try:
                run.run(on_result)
            finally:
                if run.bar is not None:
                    run.bar.close()
    finally:
        backend.close()  # also when the job could not start (idempotent)
    # once every task has finished, temporaries left are orphans of killed tasks (cancelled
    # dask tasks may still be running on their workers after an interrupt)
    if not summary.interrupted or not getattr(backend, "remote", False):
        summary.swept = sweep_temporaries(spec.outdir, [it.rel for it in items])
        if summary.swept:
            log.info("removed %d temporary files left by killed tasks", summary.swept)
    return summary


class _Run:
    """The client's side of one batch run: hands files to the backend, journals what
    comes back, pools learn-mode evidence (see :func:`run_batch`)."""

    def __init__(self, items: list[BatchItem], spec: JobSpec, backend, journal, summary: BatchSummary, *,
                 store, retries: int, window: int | None) -> None:
        self.todo = iter(items)
        self.spec = spec
        self.backend = backend
        self.journal = journal
        self.summary = summary
        self.store = store  # learn mode, and learning as it goes on a cluster
        self.learn_mode = spec.settings.mode == "learn"
        # learning as it goes on a cluster: the series rule on the store itself, and what
        # the next tasks are handed (Handout)
        self.steady = None
        if spec.client_learns:
            self.steady = SteadyProfiles(store)
        self.handout = Handout()
        self.handed = -1  # the Handout version the backend ships
        self.retries = retries
        self.window = window
        self.me = worker_name()
        self.bar = None
        self.attempts: collections.Counter[str] = collections.Counter()
        # entries of files in flight whose content the journal has as done or quarantined
        # (looked up file by file: the journal of a million files is not loaded into memory)
        self.known: dict[str, Any] = {}
        self.held: list[tuple[Task, Outcome]] = []  # permanent failures before the first success
        self.seen_done = False
        self.stopping = False

    # -- the loop ---------------------------------------------------------
    def run(self, on_result) -> None:
        s, backend = self.summary, self.backend
        t_start = time.perf_counter()
        try:
            backend.start(self.spec)
            s.backend = backend.describe()
            t_start = time.perf_counter()
            self.feed()
            for task, res in backend.completed():
                self.handle(task, res)
                if on_result is not None:
                    on_result(s, task, res)
                self.feed()
            self.flush_held()  # fewer files than the breaker needs, or all different
            if s.disk_full is not None:
                s.not_started = sum(1 for _ in self.todo)
        except BatchError:
            backend.abort()
            raise
        except KeyboardInterrupt:
            # stop handing out files; record the ones already running as they finish
            # (a second Ctrl-C stops at once: a rerun redoes those)
            s.interrupted = self.stopping = True
            backend.cancel()
            try:
                for task, res in backend.completed():
                    self.handle(task, res)
            except KeyboardInterrupt:
                backend.abort()
        finally:
            s.seconds = round(time.perf_counter() - t_start, 3)
            backend.close()

    def tick(self) -> None:
        if self.bar is not None:
            s = self.summary
            self.bar.update(1)
            self.bar.set_postfix(done=s.processed, skipped=s.skipped, failed=s.failed, refresh=False)

    def feed(self) -> None:
        if self.summary.disk_full is not None:  # every file would fail the same way: hand out no more
            return
        limit = self.window or 2 * max(1, self.backend.capacity)
        while self.backend.in_flight < limit:
            t = self.next_task()
            if t is None:
                return
            if self.steady is not None and self.handed != self.handout.version:
                self.backend.hand_out(self.handout)  # to this task and the next ones
                self.handed = self.handout.version
            self.backend.submit(t)

    def next_task(self) -> Task | None:
        s = self.summary
        for it in self.todo:
            e = self.journal.lookup(it.path)
            if e is None or e.state not in ("done", "quarantined"):
                return Task(it.path, it.rel)
            try:
                st = os.stat(it.path)
            except OSError:
                return Task(it.path, it.rel)  # let the worker report it
            same = (st.st_size, st.st_mtime_ns) == (e.fingerprint.size, e.fingerprint.mtime_ns)
            if same and e.state == "quarantined":
                s.quarantined += 1
                _note_error(s, it.path, f"quarantined by an earlier run: {_reason(e)}", "quarantined")
                self.tick()
                continue
            if same and e.state == "done":
                sidecar = (e.result or {}).get("sidecar")
                if sidecar and not os.path.exists(sidecar) and not self.learn_mode:
                    s.redone += 1  # outputs deleted since: write them again (not in learn mode: no re-pooling)
                    return Task(it.path, it.rel, e.fingerprint.sha256, force=True)
                s.skipped += 1
                self.tick()
                continue
            self.known[it.path] = e
            return Task(it.path, it.rel, e.fingerprint.sha256)  # touched: the worker compares content
        return None

    # -- results ----------------------------------------------------------
    def handle(self, task: Task, res: Outcome | BaseException) -> None:
        s = self.summary
        lost = isinstance(res, BaseException)
        if self.stopping and (lost or res.status == "failed"):
            return  # not journaled: the rerun tries it again
        if lost or (res.status == "failed" and res.transient):
            disk = not lost and res.fault == DISK_FULL
            self.attempts[task.path] += 1
            if self.attempts[task.path] <= self.retries and not disk and s.disk_full is None:
                s.resubmitted += 1
                self.backend.submit(task)
                return
            if lost:
                self.journal_failure(task, None, f"worker lost ({type(res).__name__}: {res})", "worker-lost", True)
            else:
                # the output side's fault is never the photo's: retried by later runs without limit
                self.journal_failure(task, res.fingerprint, res.error or "failed", res.error_type or "error", True,
                                     max_attempts=attempt_limit(res.fault, DEFAULT_MAX_ATTEMPTS))
            if disk and s.disk_full is None:
                s.disk_full = res.error or "output disk full"
                log.error("output disk full: no more files are handed out; free space and rerun to resume (%s)",
                          s.disk_full)
        elif res.status == "failed":
            if not self.seen_done and not self.stopping:  # held back until a file succeeds: see breaker()
                self.held.append((task, res))
                self.breaker()
                return
            self.journal_failure(task, res.fingerprint, res.error or "failed", res.error_type or "error", False)
        elif res.status == "unchanged":
            e = self.known.get(task.path)
            if e is not None and e.state == "quarantined":
                s.quarantined += 1
                _note_error(s, task.path, f"quarantined by an earlier run: {_reason(e)}", "quarantined")
            else:
                s.skipped += 1
                if e is not None and res.fingerprint is not None:
                    self.journal.touch(task.path, res.fingerprint)  # next time known from size + mtime
        elif task.force and res.fingerprint.sha256 == task.known_sha:  # outputs rewritten; journal has it
            if self.steady is not None:  # the record says what the store holds (pooled before)
                self.learn_on_client(res)
            s.processed += 1
            _count_source(s, res.record)
        else:
            self.record_done(task, res)
        self.known.pop(task.path, None)
        self.tick()

    def record_done(self, task: Task, res: Outcome) -> None:
        s, fp = self.summary, res.fingerprint
        if not _claim(self.journal, task.path, fp, self.me):
            s.skipped += 1  # same content done meanwhile (e.g. listed twice)
            return
        if self.steady is not None:  # learning as it goes on a cluster: pooled here (the record follows)
            self.learn_on_client(res)
        result = _journal_result(res.record or {}, res.worker)
        if self.steady is None and self.store is not None:  # learn: pool here, the one writer of the store
            for key, model, evidence, lens_key, extra in res.evidence:
                # keyed by content: a frame pooled before a crash, then redone, is not pooled twice
                p = self.store.learn(key, model, frame_id=fp.sha256, evidence=evidence, lens_key=lens_key,
                                     **extra)
                s.profiles[str(p.key)] = {"n_frames": p.n_frames, "trusted": p.trusted,
                                          "field_sigma_ev": p.field_sigma_ev}
        learned = (res.record or {}).get("learned") or {}
        if learned.get("profile"):  # learning as you go: the workers pooled it; the latest state is shown
            old = s.profiles.get(learned["profile"])
            if old is None or learned["frames"] >= old["n_frames"]:
                s.profiles[learned["profile"]] = {"n_frames": learned["frames"], "trusted": learned["trusted"],
                                                  "field_sigma_ev": learned.get("field_sigma_ev")}
        self.journal.done(task.path, fp, result)
        s.processed += 1
        _count_source(s, res.record)
        self.seen_done = True
        self.flush_held()

    def learn_on_client(self, res: Outcome) -> None:
        """Learning as it goes on a cluster (``spec.client_learns``), for a frame a worker
        corrected: pool its material into the store under its content id (a frame
        pooled before, by an earlier run or before a crash, is not pooled again:
        :meth:`ProfileStore.learn`), then apply the series rule to its lens setting with
        its capture time (:class:`~vigproc.pipeline.learning.SteadyProfiles`, the store's
        applied revision), and hand the result to the tasks submitted next. The
        record, and the sidecar the worker wrote, then say what the store did."""
        from vigproc.stores.profiles import ProfileStoreError

        fid = res.fingerprint.sha256
        applied, latest = dict(self.handout.applied), dict(self.handout.latest)
        learned = None
        for key, model, evidence, lens_key, extra in res.evidence:
            try:
                known = self.store.holds_frame(key, fid)
                p = self.store.learn(key, model, frame_id=fid, evidence=evidence, lens_key=lens_key, **extra)
            except ProfileStoreError as exc:
                if getattr(exc, "transient", False) or getattr(exc, "sqlite_errorcode", None) is not None:
                    raise  # the store itself: the job stops, the frame is not journaled and is redone
                log.warning("%s: not learned: %s", res.path, exc)  # as a local worker says it
                learned = Learned(False, reason=str(exc))
                continue
            latest[str(p.key)] = p
            learned = Learned.of(p, pooled=not known, reason="this content is already pooled" if known else None)
        if res.frame is not None:
            lens_key, width, height = res.frame
            self.steady.at(res.captured)
            try:
                self.steady.lookup(lens_key, width, height, trusted_only=True)
            except VigprocError as exc:  # an odd key: the frame was corrected; its series is not kept
                log.warning("%s: series of its lens setting not kept: %s", res.path, exc)
            if self.steady.revision is not None:
                applied[str(self.steady.last.key)] = (self.steady.revision, self.steady.last)
        changed = applied.keys() != self.handout.applied.keys() or latest.keys() != self.handout.latest.keys() or any(
            applied[k][0] != self.handout.applied[k][0] for k in applied) or any(
            latest[k] is not self.handout.latest[k] for k in latest)
        if changed:
            self.handout = Handout(self.handout.version + 1, applied, latest)
        if learned is not None and res.record is not None:
            self._rewrite_learned(res.record, learned)

    @staticmethod
    def _rewrite_learned(record: dict[str, Any], learned) -> None:
        """The record's and the sidecar's ``learned`` (and ``profile``) as the store
        pooled the frame (the worker could only say what it handed over)."""
        record["learned"] = learned.to_dict()
        if learned.pooled:
            record["profile"] = learned.profile
        else:
            record.pop("profile", None)
        sidecar = record.get("sidecar")
        if not sidecar:
            return
        try:
            with open(sidecar, encoding="utf-8") as fh:
                doc = json.load(fh)
            doc["learned"] = record["learned"]
            if "profile" in record:
                doc["profile"] = record["profile"]
            else:
                doc.pop("profile", None)
            atomic_write_text(sidecar, json.dumps(doc, indent=1) + "\n")
        except (OSError, ValueError) as exc:  # the store is right; the sidecar keeps the worker's words
            log.warning("sidecar %s: its 'learned' not updated: %s", sidecar, exc)

    def journal_failure(self, task: Task, fp, reason: str, kind: str, transient: bool,
                        max_attempts: int | None = DEFAULT_MAX_ATTEMPTS) -> None:
        if fp is None:  # the worker could not even read it: try here, to key the journal entry
            with contextlib.suppress(VigprocError):
                fp = fingerprint(task.path)
        state = "retry" if transient else "quarantined"
        if fp is not None and _claim(self.journal, task.path, fp, self.me):
            state = self.journal.failed(task.path, fp, reason, transient=transient, max_attempts=max_attempts)
        if state == "quarantined":
            self.summary.quarantined += 1
        else:
            self.summary.retry_later += 1
        _note_error(self.summary, task.path, reason, kind)

    def flush_held(self) -> None:
        while self.held:
            t, r = self.held.pop(0)
            self.journal_failure(t, r.fingerprint, r.error or "failed", r.error_type or "error", False)
            self.tick()

    def breaker(self) -> None:
        """The first files all failing the same way is a setup problem (a missing
        calibration, a broken installation on the workers), not bad files: stop
        before quarantining the whole archive."""
        if len(self.held) < BREAKER_FILES:
            return
        kinds = {(r.error_type, (r.error or "").replace(t.path, "")) for t, r in self.held}
        if len(kinds) == 1:
            first = self.held[0][1].error
            self.held.clear()
            raise BatchError(f"the first {BREAKER_FILES} files all failed with: {first}; stopped without "
                             "quarantining them (fix the cause and rerun)")
        self.flush_held()


def _claim(journal, path: str, fp, worker: str) -> bool:
    # now=inf: a file waiting for its retry time is due for a batch run the user started
    return journal.claim(path, fp, worker=worker, now=math.inf)


def _reason(entry) -> str:
    return entry.reason or "see the journal"


def _note_error(summary: BatchSummary, path: str, error: str, kind: str) -> None:
    if len(summary.errors) < _MAX_ERRORS:
        summary.errors.append({"file": path, "error": error, "type": kind})


def _count_source(summary: BatchSummary, rec: dict[str, Any] | None) -> None:
    src = (rec or {}).get("source") or "none"
    summary.sources[src] = summary.sources.get(src, 0) + 1


@contextlib.contextmanager
def _job_lock(journal_path: Path, job: str) -> Iterator[None]:
    """One client per job at a time (two would both dispatch the same files)."""
    lock = journal_path.with_name(f"{journal_path.name}.{job}.lock")
    try:
        fd = os.open(lock, os.O_RDWR | os.O_CREAT, 0o644)
    except OSError as exc:
        raise BatchError(f"cannot create lock file {lock}: {exc.strerror or exc}") from None
    try:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            raise BatchError(f"another 'vigproc batch' is running this job (lock {lock})") from None
        yield
    finally:
        os.close(fd)
