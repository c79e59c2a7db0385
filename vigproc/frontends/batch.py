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

import atexit
import collections
import contextlib
import dataclasses
import hashlib
import json
import logging
import math
import os
import shutil
import socket
import sqlite3
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path, PurePosixPath
from typing import Any, Callable, Iterable, Iterator

from vigproc.errors import EXIT_CODES, SETTINGS, ImageWriteError, VigprocError
from vigproc.scratch import scratch_folder
from vigproc.pipeline.faults import DISK_FULL, PERMANENT, attempt_limit, classify_error
from vigproc.pipeline.processor import (IMAGE_SUFFIXES, SIDECAR_SUFFIX, Processor, Settings, output_location, safe_output,
                              sweep_temporaries)
from vigproc.stores.retry import DEFAULT_MAX_ATTEMPTS

log = logging.getLogger(__name__)

#: Permanent failures of the first files that stop a job when all alike (a setup problem).
BREAKER_FILES = 12
#: Default journal file name inside the output folder.
JOURNAL_NAME = ".vigproc-batch.sqlite"
#: Filesystems SQLite must not live on (locking and WAL's shared memory need a local disk).
NETWORK_FS = frozenset({"nfs", "nfs4", "cifs", "smb3", "smbfs", "ncpfs", "afs", "9p", "lustre", "gpfs",
                        "ceph", "glusterfs", "fuse.glusterfs", "beegfs", "fuse.sshfs", "fuse.s3fs",
                        "fuse.gcsfuse", "fuse.rclone", "davfs", "fuse.cephfs", "orangefs", "pvfs2"})


class BatchError(VigprocError):
    """A batch job cannot run: bad file list, journal unusable or locked, cluster
    unreachable or misconfigured."""

    exit_code = EXIT_CODES["batch"]
    blame = SETTINGS


# --------------------------------------------------------------------- inputs
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


# ------------------------------------------------------------------ job spec
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


def job_id(source: str | os.PathLike[str], outdir: str | os.PathLike[str], settings: Settings,
           profile_digest: str | None = None) -> str:
    """Journal job name: a rerun of the same source, output folder and settings
    resumes; other settings are another job (its outputs differ)."""
    d = {"source": str(Path(source).resolve()), "out": str(Path(outdir).resolve()), "settings": settings.to_dict(),
         "profile_file": profile_digest}
    return f"batch-{settings.mode}-" + hashlib.sha256(json.dumps(d, sort_keys=True).encode()).hexdigest()[:12]


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
    evidence: list[tuple[Any, ...]] = field(default_factory=list)  # (ProfileKey, VignettingModel, bytes|None, LensKey|None)
    frame: tuple[Any, int, int] | None = None  # client_learns: (LensKey, width, height) the profiles were read for
    captured: float | None = None  # client_learns: the frame's capture time (None: the client's clock)
    error: str | None = None
    error_type: str | None = None
    transient: bool = False
    fault: str = PERMANENT
    worker: str = ""
    seconds: float = 0.0


# -------------------------------------------------------------- worker side
class _Evidence:
    """Stands in for the profile store of a learn-mode Processor on a worker: keeps
    each frame's (key, model) for the client to pool; workers never write the store."""

    #: the frame's colour-cast record travels with its evidence (ProfileStore.learn's ``cast``)
    records_casts = True

    def __init__(self) -> None:
        self.items: list[tuple[Any, ...]] = []

    def learn(self, key, model, *, notes: str | None = None, frame_id: str | None = None,
              evidence: bytes | None = None, lens_key=None, cast: dict | None = None):
        # the client pools under the fingerprint it journals (same content id)
        self.items.append((key, model, evidence, lens_key, cast))
        return _Learned(key)

    def close(self) -> None:
        pass


@dataclass(frozen=True)
class _Learned:
    key: Any


@dataclass(frozen=True)
class _Pending:
    """What a cluster worker's stand-in store says a frame's pooling gives, until the
    client has pooled it and rewritten the record (:meth:`_Run.learn_on_client`)."""

    key: Any
    n_frames: int
    trusted: bool
    field_sigma_ev: float | None = None


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
              evidence: bytes | None = None, lens_key=None, cast: dict | None = None):
        self.items.append((key, model, evidence, lens_key, cast))
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
        from vigproc.stores.opening import open_profile_store

        store = pooled = _ClientPooled(open_profile_store(_materialise(spec.store_snapshot)))
    elif spec.store_path is not None:  # learning as you go: the live store, pooled into here
        from vigproc.stores.opening import open_profile_store

        store = open_profile_store(spec.store_path, write=True)
    elif spec.store_snapshot is not None:
        from vigproc.stores.opening import open_profile_store

        store = open_profile_store(_materialise(spec.store_snapshot))
    st = _WorkerState(token, Processor(settings, store=store), store, evidence, pooled)
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


# ------------------------------------------------------------- the client
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
    import sys

    from vigproc.stores.journal import Journal

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
            from vigproc.pipeline.learning import SteadyProfiles

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
            for key, model, evidence, lens_key, cast in res.evidence:
                # keyed by content: a frame pooled before a crash, then redone, is not pooled twice
                p = self.store.learn(key, model, frame_id=fp.sha256, evidence=evidence, lens_key=lens_key, cast=cast)
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
        from vigproc.pipeline.learning import Learned
        from vigproc.stores.profiles import ProfileStoreError

        fid = res.fingerprint.sha256
        applied, latest = dict(self.handout.applied), dict(self.handout.latest)
        learned = None
        for key, model, evidence, lens_key, cast in res.evidence:
            try:
                known = self.store.holds_frame(key, fid)
                p = self.store.learn(key, model, frame_id=fid, evidence=evidence, lens_key=lens_key, cast=cast)
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
        from vigproc.atomic import atomic_write_text

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
        from vigproc.stores.journal import fingerprint

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
    import fcntl

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
