"""The worker side of a batch job: what a worker is sent (:class:`JobSpec`, :class:`Task`,
:class:`Handout`), what it does with one file (:func:`run_task`) and what it returns
(:class:`Outcome`).

A worker keeps one :class:`~vigproc.pipeline.processor.Processor` per thread (it owns an
exiftool process and an SQLite connection) and, in the modes that learn, a stand-in for
the profile store that keeps each frame's material for the client, the one writer of the
store (:mod:`vigproc.frontends.batch`). Every backend (:mod:`vigproc.frontends.backends`)
submits :func:`run_task`; a Dask worker imports this module, not the client's.
"""

from __future__ import annotations

import atexit
import dataclasses
import hashlib
import json
import logging
import os
import shutil
import socket
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path, PurePosixPath
from typing import Any

from vigproc.errors import VigprocError
from vigproc.pipeline.faults import PERMANENT, classify_error
from vigproc.pipeline.processor import SIDECAR_SUFFIX, Processor, Settings, output_location, safe_output
from vigproc.scratch import scratch_folder
from vigproc.stores.opening import open_profile_store

log = logging.getLogger("vigproc.frontends.batch")  # the batch job's one logger name, as before the split

@dataclass(frozen=True)
class Shipped:
    """A small file the client sends to every worker (a profile file, a store snapshot)."""

    name: str
    data: bytes = field(repr=False)
    digest: str = ""

    @classmethod
    def of(cls, name: str, data: bytes) -> Shipped:
        return cls(name, data, hashlib.sha256(data).hexdigest())


@dataclass(frozen=True)
class JobSpec:
    """Everything a worker needs besides the file (sent once per worker).

    Attributes
    ----------
    settings : Settings
        As for :class:`vigproc.pipeline.processor.Processor`; a profile *file* is shipped in
        ``profile_file`` instead of being read from the client's path.
    outdir : str
        Absolute output folder (on storage every worker sees at the same path).
    numba_threads : int
        Numba threads per task (cores / concurrent tasks on a host).
    profile_file : Shipped or None
        Content of ``--profile PATH``.
    store_snapshot : Shipped or None
        Snapshot of the profile store (``correct --profile auto``, ``check``).
    store_path : str or None
        The live profile store, for correct mode that learns as it goes (local
        workers only: the file is on the client's machine).
    client_learns : bool
        Correct mode that learns as it goes on a cluster: the workers read
        ``store_snapshot`` and the client's :class:`Handout`, and return each frame's
        pooled material; the client pools it (the one writer of the store).
    """

    settings: Settings
    outdir: str
    numba_threads: int = 1
    profile_file: Shipped | None = None
    store_snapshot: Shipped | None = None
    store_path: str | None = None
    client_learns: bool = False

    @property
    def token(self) -> str:
        """Identity of the spec: worker state is cached per token."""
        h = hashlib.sha256(json.dumps([self.settings.to_dict(), self.outdir]
                                      + ([self.store_path] if self.store_path else [])
                                      + (["client-learns"] if self.client_learns else []), sort_keys=True).encode())
        for s in (self.profile_file, self.store_snapshot):
            h.update((s.digest if s is not None else "-").encode())
        return h.hexdigest()[:16]


@dataclass(frozen=True)
class Task:
    """One file to process (what a worker receives per task)."""

    path: str
    rel: str
    #: sha256 of the content already done (or quarantined): unchanged content is skipped
    known_sha: str | None = None
    #: reprocess even if ``known_sha`` matches (outputs missing); the journal is not updated
    force: bool = False


@dataclass(frozen=True)
class Handout:
    """What the client of a cluster job that learns as it goes hands the tasks it
    submits (``JobSpec.client_learns``): the store's state the workers' correction
    reads, as the client pooled it so far.

    Attributes
    ----------
    version : int
        Raised at every change (the backend ships each version once).
    applied : dict
        Profile key text → (revision id, Profile): the revision each lens setting's
        series is corrected with (:meth:`ProfileStore.series_revision
        <vigproc.stores.profiles.ProfileStore.series_revision>`).
    latest : dict
        Profile key text → Profile: the profiles pooled into during this job, as stored
        after the last frame (trust, the profile's evidence before trust, settling).
    """

    version: int = 0
    applied: dict[str, tuple[str, Any]] = field(default_factory=dict)
    latest: dict[str, Any] = field(default_factory=dict)


@dataclass
class Outcome:
    """What a worker did with one :class:`Task`.

    ``status`` is ``done``, ``unchanged`` (content equal to ``known_sha``: nothing
    done) or ``failed`` (``transient`` failures are worth retrying; ``fault`` is the
    kind of :func:`vigproc.pipeline.faults.classify_error`).
    """

    path: str
    status: str
    fingerprint: Any = None
    record: dict[str, Any] | None = None
    #: (ProfileKey, VignettingModel, bytes|None, LensKey|None, dict): the last item holds
    #: ``ProfileStore.learn``'s optional keywords the frame has (``grid``, ``cast``)
    evidence: list[tuple[Any, ...]] = field(default_factory=list)
    frame: tuple[Any, int, int] | None = None  # client_learns: (LensKey, width, height) the profiles were read for
    captured: float | None = None  # client_learns: the frame's capture time (None: the client's clock)
    error: str | None = None
    error_type: str | None = None
    transient: bool = False
    fault: str = PERMANENT
    worker: str = ""
    seconds: float = 0.0


def _item(key, model, evidence, lens_key, extra: dict) -> tuple[Any, ...]:
    """One frame's material for the client to pool: ``learn``'s optional keywords
    (a flat frame's ``grid``, a colour-cast record ``cast``) only where the frame has them."""
    return (key, model, evidence, lens_key, {k: v for k, v in extra.items() if v is not None})


class _Evidence:
    """Stands in for the profile store of a learn-mode Processor on a worker: keeps
    each frame's (key, model) for the client to pool; workers never write the store."""

    def __init__(self) -> None:
        self.items: list[tuple[Any, ...]] = []

    #: the frame's colour-cast record travels with its evidence (ProfileStore.learn's ``cast``)
    records_casts = True

    def learn(self, key, model, *, notes: str | None = None, frame_id: str | None = None,
              evidence: bytes | None = None, lens_key=None, **extra):
        # the client pools under the fingerprint it journals (same content id)
        self.items.append(_item(key, model, evidence, lens_key, extra))
        return _Learned(key)

    def close(self) -> None:
        pass


@dataclass(frozen=True)
class _Learned:
    key: Any


@dataclass(frozen=True)
class _Pending:
    """What a cluster worker's stand-in store says a frame's pooling gives, until the
    client has pooled it and rewritten the record (:meth:`vigproc.frontends.batch._Run.learn_on_client`)."""

    key: Any
    n_frames: int
    trusted: bool
    field_sigma_ev: float | None = None

    def label(self) -> str:
        """As :meth:`vigproc.stores.profile.Profile.label` names it, before the client's
        record does: the key (the frames' focal lengths are the client's to know)."""
        return str(self.key)


class _ClientPooled:
    """Stands in for the profile store of a correct-mode Processor that learns as it
    goes on a cluster worker (``JobSpec.client_learns``): reads the job's snapshot of
    the store and the client's :class:`Handout`; keeps each frame's pooled material
    (and the lens setting it read profiles for) for the client, the one writer."""

    def __init__(self, snapshot) -> None:
        self.snapshot = snapshot
        self.handout = Handout()
        self.items: list[tuple[Any, ...]] = []
        self.frame: tuple[Any, int, int] | None = None

    def begin(self, handout: Handout | None) -> None:
        """A new task: what the client handed it, nothing of the task before."""
        self.handout = handout if handout is not None else Handout()
        self.items.clear()
        self.frame = None

    def key_for(self, lens_key, width: int, height: int):
        return self.snapshot.key_for(lens_key, width, height)

    def lookup(self, lens_key, width: int, height: int, *, trusted_only: bool = False):
        self.frame = (lens_key, int(width), int(height))
        p = self.handout.latest.get(str(self.snapshot.key_for(lens_key, width, height)))
        if p is not None and (p.trusted or not trusted_only):
            return p
        return self.snapshot.lookup(lens_key, width, height, trusted_only=trusted_only)

    def series_revision(self, profile, key, *, at: float, clock: str, gap: float, now: float | None = None):
        # the client applies the series rule; a worker follows the revision handed out
        held = self.handout.applied.get(str(key)) or self.snapshot.applied_revision(key)
        return (held[0], held[1], False) if held is not None else None

    def get(self, key):
        p = self.handout.latest.get(str(key))
        return p if p is not None else self.snapshot.get(key)

    def holds_frame(self, key, frame_id: str) -> bool:
        return self.snapshot.holds_frame(key, frame_id)  # pooled in this job: the client's learn() knows

    records_casts = True

    def learn(self, key, model, *, notes: str | None = None, frame_id: str | None = None,
              evidence: bytes | None = None, lens_key=None, **extra):
        self.items.append(_item(key, model, evidence, lens_key, extra))
        known = self.get(key)
        return _Pending(key, (known.n_frames if known is not None else 0) + 1,
                        bool(known is not None and known.trusted))

    def close(self) -> None:
        self.snapshot.close()


@dataclass
class _WorkerState:
    token: str
    processor: Processor
    store: Any
    evidence: _Evidence | None
    pooled: _ClientPooled | None = None


# Per-process worker state: materialised shipped files (shared by the process's
# threads) and one Processor per thread (it owns an exiftool process and an SQLite
# connection, neither of which may be shared between threads).
_files_lock = threading.Lock()
_files: dict[str, str] = {}
_files_dir: list[str] = []
_thread = threading.local()
_warm_lock = threading.Lock()
_warm = [False]


def _materialise(s: Shipped) -> str:
    with _files_lock:
        if s.digest in _files:
            return _files[s.digest]
        if not _files_dir:
            d = scratch_folder("batch")  # a killed worker's: removed by the next process's sweep
            _files_dir.append(d)
            atexit.register(shutil.rmtree, d, True)
        dst = os.path.join(_files_dir[0], f"{s.digest[:16]}-{os.path.basename(s.name) or 'file'}")
        with open(dst, "wb") as fh:
            fh.write(s.data)
        _files[s.digest] = dst
        return dst


def _worker_state(spec: JobSpec) -> _WorkerState:
    st: _WorkerState | None = getattr(_thread, "state", None)
    token = spec.token
    if st is not None and st.token == token:
        return st
    release_worker_state()
    settings = spec.settings
    if spec.profile_file is not None:
        settings = dataclasses.replace(settings, profile=_materialise(spec.profile_file))
    store = evidence = pooled = None
    if settings.mode == "learn":
        store = evidence = _Evidence()
    elif spec.client_learns:  # learning as it goes on a cluster: the client pools
        store = pooled = _ClientPooled(open_profile_store(_materialise(spec.store_snapshot)))
    elif spec.store_path is not None:  # learning as you go: the live store, pooled into here
        store = open_profile_store(spec.store_path, write=True)
    elif spec.store_snapshot is not None:
        store = open_profile_store(_materialise(spec.store_snapshot))
    st = _WorkerState(token, Processor(settings, store=store), store, evidence, pooled)
    st.processor.prepare()  # exiftool's start beside the first file's read, not before it
    _thread.state = st
    return st


def release_worker_state() -> None:
    """Close this thread's Processor (its exiftool) and snapshot store, if any."""
    st: _WorkerState | None = getattr(_thread, "state", None)
    _thread.state = None
    if st is not None:
        st.processor.close()
        if st.store is not None:
            st.store.close()


def warm_up(numba_threads: int | None = None) -> None:
    """Load (or compile, the first time on a machine) the Numba kernels of the
    estimator and the correction once in this process, so tasks do not pay it.

    ``numba_threads``: this process's share of the cores, for Numba and for
    OpenImageIO's own thread pool (N workers × all-core pools would oversubscribe)."""
    if numba_threads:
        _set_numba_threads(numba_threads)
        _set_oiio_threads(numba_threads)
    with _warm_lock:
        if _warm[0]:
            return
        import numpy as np

        from vigproc.core.correct import correct
        from vigproc.core.estimate import estimate

        yy, xx = np.mgrid[0:64, 0:96]
        img = (0.3 + 0.2 * np.sin(xx / 5.0) * np.cos(yy / 7.0))[..., None].repeat(3, -1).astype(np.float32)
        try:
            correct(img, estimate(img, "default", channel_axis=-1), channel_axis=-1)
        except VigprocError:  # a degenerate warm-up frame still compiled the kernels it reached
            pass
        _warm[0] = True


def _set_numba_threads(n: int) -> None:
    import numba

    # thread-local in Numba: set in the thread that runs the task
    numba.set_num_threads(max(1, min(int(n), numba.config.NUMBA_NUM_THREADS)))


def _set_oiio_threads(n: int) -> None:
    import OpenImageIO as oiio

    oiio.attribute("threads", max(1, int(n)))  # process-wide


def worker_name() -> str:
    return f"{socket.gethostname()}:{os.getpid()}"


def _out_folder(spec: JobSpec, rel: str) -> tuple[Path, str]:
    """Output folder and stem of a task: the policy every front end shares
    (:func:`vigproc.pipeline.processor.output_location`: sub-folders mirrored, never outside
    ``spec.outdir``)."""
    return output_location(spec.outdir, PurePosixPath(rel))


def run_task(task: Task, spec: JobSpec, handout: Handout | None = None) -> Outcome:
    """Process one file on a worker (the function the client submits).

    Fingerprints the file, skips it if its content is ``task.known_sha`` (unless
    ``task.force``), else runs it through this thread's Processor; outputs are
    written atomically under ``spec.outdir``.  Failures of the file are returned,
    not raised (the client journals them); only the loss of the worker itself
    reaches the client as an exception.  ``handout``: the client's profiles as of
    this task's submission (``spec.client_learns``).
    """
    from vigproc.stores.journal import FileChangedError, fingerprint

    t0 = time.perf_counter()
    out = Outcome(task.path, "failed", worker=worker_name())
    try:
        _set_numba_threads(spec.numba_threads)
        out.fingerprint = fp = fingerprint(task.path)
        if fp.sha256 == task.known_sha and not task.force:
            out.status = "unchanged"
            return out
        warm_up()
        st = _worker_state(spec)
        folder, stem = _out_folder(spec, task.rel)
        if st.evidence is not None:
            st.evidence.items.clear()
        if st.pooled is not None:
            st.pooled.begin(handout)
            st.processor.captured = None
        res = st.processor.process_file(task.path, folder, stem,
                                        frame_id=fp.sha256 if spec.settings.learn else None)
        after = os.stat(task.path)
        if (after.st_size, after.st_mtime_ns) != (fp.size, fp.mtime_ns):
            raise FileChangedError(f"{task.path} changed while it was being processed")
        out.record = res.to_dict()
        out.record["sidecar"] = str(safe_output(folder, stem, SIDECAR_SUFFIX))
        holder = st.evidence if st.evidence is not None else st.pooled  # what the client pools
        out.evidence = list(holder.items) if holder is not None else []
        if st.pooled is not None:
            out.frame, out.captured = st.pooled.frame, st.processor.captured
        out.status = "done"
    except Exception as exc:  # the file's fault or not: the policy the daemon and correct use too
        fault = classify_error(exc, spec.outdir)
        out.fault, out.transient, out.error_type = fault.kind, not fault.photo_fault, type(exc).__name__
        if fault.output_side:  # says so: "output disk full (... free on OUT): cannot write ..."
            out.error = fault.reason
        elif isinstance(exc, VigprocError):  # the file: unreadable, unsupported, no usable fit ...
            out.error = str(exc)
        elif not isinstance(exc, (OSError, MemoryError)):  # a bug: report it against the file, keep going
            log.debug("internal error on %s", task.path, exc_info=True)
            out.error, out.error_type = f"{task.path}: internal error ({type(exc).__name__}: {exc})", "internal"
        else:
            out.error = f"{task.path}: {fault.reason}"
    finally:
        out.seconds = round(time.perf_counter() - t0, 4)
    return out
