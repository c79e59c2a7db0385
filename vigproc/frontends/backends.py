"""Where a batch's tasks run: in this process, a local process pool, or a Dask cluster.

Every backend has the same small interface, which :func:`vigproc.frontends.batch.run_batch`
drives: ``capacity`` (tasks worth keeping in flight), ``describe()``, ``start(spec)``,
``submit(task)``, ``completed()`` (yields each task with its
:class:`~vigproc.frontends.batch_worker.Outcome` or the exception it raised), ``cancel()`` and
``close()``; ``remote`` is true when tasks may outlive an interrupt on other machines.
The Dask backend also has ``hand_out(handout)``: the client's
:class:`~vigproc.frontends.batch_worker.Handout` for the tasks it submits from then on
(learning as it goes on a cluster).

References
----------
dask.distributed: "Futures" (``Client.submit``, ``as_completed``, retries) and
"Worker plugins", https://distributed.dask.org/.
"""

from __future__ import annotations

import collections
import contextlib
import hashlib
import logging
import os
import re
import shutil
import signal
import time
from typing import Any, Iterator

from vigproc._version import __version__
from vigproc.frontends.batch_inputs import BatchError
from vigproc.frontends.batch_worker import JobSpec, Outcome, Task, release_worker_state, run_task, warm_up
from vigproc.processes import die_with_parent

log = logging.getLogger(__name__)

_SCHEDULER_RE = re.compile(r"^(tcp|tls|inproc|ucx|ws|wss)://[A-Za-z0-9._\-\[\]:%]+$")


class _InProcess:
    """Runs tasks one at a time in the client process (``--workers 1``)."""

    remote = False

    def __init__(self, numba_threads: int | None = None) -> None:
        self.numba_threads = numba_threads or cores()
        self._queue: collections.deque[Task] = collections.deque()
        self.spec: JobSpec | None = None

    @property
    def capacity(self) -> int:
        return 1

    def describe(self) -> str:
        return "1 local worker (in-process)"

    def start(self, spec: JobSpec) -> None:
        self.spec = spec
        warm_up(spec.numba_threads)

    def submit(self, task: Task) -> None:
        self._queue.append(task)

    @property
    def in_flight(self) -> int:
        return len(self._queue)

    def completed(self) -> Iterator[tuple[Task, Outcome | BaseException]]:
        while self._queue:
            task = self._queue.popleft()
            yield task, run_task(task, self.spec)

    def cancel(self) -> None:
        self._queue.clear()

    def abort(self) -> None:
        self._queue.clear()

    def close(self) -> None:
        release_worker_state()


class _Pool:
    """A local process pool (spawned processes: no state inherited from the client)."""

    remote = False

    def __init__(self, workers: int) -> None:
        self.workers = int(workers)
        self.numba_threads = max(1, cores() // self.workers)
        self._pool = None
        self._gen = 0
        self._pending: dict[Any, tuple[Task, int]] = {}
        self.spec: JobSpec | None = None

    @property
    def capacity(self) -> int:
        return self.workers

    def describe(self) -> str:
        return f"{self.workers} local worker processes"

    def _new_pool(self):
        import multiprocessing
        from concurrent.futures import ProcessPoolExecutor

        return ProcessPoolExecutor(self.workers, mp_context=multiprocessing.get_context("spawn"),
                                   initializer=_pool_worker_init,
                                   initargs=(self.numba_threads, os.getpid(), logging.getLogger().getEffectiveLevel()))

    def start(self, spec: JobSpec) -> None:
        self.spec = spec
        self._pool = self._new_pool()

    def submit(self, task: Task) -> None:
        self._pending[self._pool.submit(run_task, task, self.spec)] = (task, self._gen)

    @property
    def in_flight(self) -> int:
        return len(self._pending)

    def completed(self) -> Iterator[tuple[Task, Outcome | BaseException]]:
        from concurrent.futures import FIRST_COMPLETED, wait
        from concurrent.futures.process import BrokenProcessPool

        while self._pending:
            done, _ = wait(list(self._pending), return_when=FIRST_COMPLETED)
            for f in done:
                task, gen = self._pending.pop(f)
                try:
                    res: Outcome | BaseException = f.result()
                except BrokenProcessPool as exc:  # a worker died: the pool is unusable, make a new one
                    res = exc
                    if gen == self._gen:
                        log.warning("a local worker process died; restarting the pool")
                        self._pool.shutdown(wait=False, cancel_futures=True)
                        self._pool = self._new_pool()
                        self._gen += 1
                except Exception as exc:  # e.g. a result that could not be sent back
                    res = exc
                yield task, res

    def cancel(self) -> None:
        """Drop the tasks not started; the running ones stay, to be collected."""
        for f in list(self._pending):
            if f.cancel():
                del self._pending[f]

    def abort(self) -> None:
        """Stop now: kill the workers (outputs are atomic, so nothing is left half-written)."""
        self.cancel()
        self._pending.clear()
        if self._pool is not None:
            procs = list(getattr(self._pool, "_processes", {}).values())  # no public way before 3.14
            self._pool.shutdown(wait=False, cancel_futures=True)
            for proc in procs:
                with contextlib.suppress(Exception):
                    proc.kill()
            self._pool = None

    def close(self) -> None:
        if self._pool is not None:
            self._pool.shutdown(wait=True, cancel_futures=True)
            self._pool = None


def _pool_worker_init(numba_threads: int, client_pid: int, log_level: int = logging.WARNING) -> None:
    from vigproc.frontends.daemon.logs import configure_logging

    # the worker's log lines on the shared stderr, control and bidi characters of hostile
    # file names escaped as the client's are (unconfigured, Python would print them raw)
    configure_logging(False, log_level)

    # Ctrl-C is the client's to handle: it stops handing out files and lets the running
    # ones finish.  A process group of its own keeps the terminal's SIGINT from the worker
    # and from the exiftool it starts (which would die of it).
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    with contextlib.suppress(OSError):
        os.setpgrp()
    die_with_parent(client_pid)  # a pool worker of a killed client would wait for tasks forever
    warm_up(numba_threads)


class _WarmUpPlugin:
    """Worker plugin: warm the Numba kernels once on every worker, including workers
    that join or are restarted later (in a thread, not blocking the worker's loop)."""

    name = "vigproc-warm-up"

    def __init__(self, numba_threads: int = 1) -> None:
        self.numba_threads = numba_threads

    async def setup(self, worker) -> None:
        import asyncio

        await asyncio.get_running_loop().run_in_executor(None, warm_up, None)

    def teardown(self, worker) -> None:
        pass

    def transition(self, key, start, finish, **kwargs) -> None:
        pass


class _Dask:
    """Tasks on a ``dask.distributed`` cluster, results streamed with ``as_completed``.

    Parameters
    ----------
    client : distributed.Client
        Borrowed unless ``owns_client``.
    retries : int
        Extra attempts of a task that raised (the scheduler already reruns the tasks
        of a worker that died).
    numba_threads : int
        Numba threads per task (1: a cluster runs one task per core).
    """

    remote = True  # cancelled tasks may still run on their workers after an interrupt

    def __init__(self, client, *, retries: int = 2, numba_threads: int = 1, owns_client: bool = False) -> None:
        self.client = client
        self.retries = retries
        self.numba_threads = numba_threads
        self.owns_client = owns_client
        self._ac = None
        self._tasks: dict[str, Task] = {}
        self._spec_future = None
        self._handout = None  # a future of the client's latest Handout, once it hands one out
        self._capacity = 1
        self._capacity_checked = 0.0

    @property
    def capacity(self) -> int:
        now = time.monotonic()
        if now - self._capacity_checked > 5.0:  # workers come and go
            self._capacity_checked = now
            with contextlib.suppress(Exception):
                self._capacity = max(1, sum(self.client.nthreads().values()))
        return self._capacity

    def describe(self) -> str:
        info = self.client.scheduler_info()
        workers = info.get("workers", {})
        return (f"dask cluster {info.get('address', '?')}: {len(workers)} workers, "
                f"{sum(w.get('nthreads', 0) for w in workers.values())} threads")

    def start(self, spec: JobSpec) -> None:
        from distributed import WorkerPlugin, as_completed

        class WarmUp(_WarmUpPlugin, WorkerPlugin):
            pass

        check_workers(self.client, spec)
        # once per worker, not per task: the spec (with any shipped files) and the warm-up
        self._spec_future = self.client.scatter(spec, broadcast=True, hash=False)
        self.client.register_plugin(WarmUp(self.numba_threads), name=_WarmUpPlugin.name)
        self._ac = as_completed(loop=self.client.loop)

    def hand_out(self, handout) -> None:
        """The tasks submitted from now on get ``handout`` (shipped once to the cluster,
        not with every task; the version before is released with its last task)."""
        self._handout = self.client.scatter(handout, hash=False)

    def submit(self, task: Task) -> None:
        key = f"vigproc-batch-{hashlib.sha1(task.path.encode('utf-8', 'surrogateescape')).hexdigest()[:12]}-" \
              f"{os.urandom(4).hex()}"
        f = self.client.submit(run_task, task, self._spec_future, self._handout, key=key, retries=self.retries,
                               pure=False)
        self._tasks[f.key] = task
        self._ac.add(f)

    @property
    def in_flight(self) -> int:
        return len(self._tasks)

    def completed(self) -> Iterator[tuple[Task, Outcome | BaseException]]:
        for f in self._ac:
            task = self._tasks.pop(f.key)
            try:
                res: Outcome | BaseException = f.result()
            except Exception as exc:  # KilledWorker (the task took down workers too often), lost connection ...
                res = exc
            f.release()
            yield task, res

    def cancel(self) -> None:
        """Cancel every task (a remote task cannot be waited for usefully; a rerun
        redoes the few that were running)."""
        if self._ac is not None:
            futures = list(self._ac.futures)
            self._ac.clear()
            with contextlib.suppress(Exception):
                self.client.cancel(futures)
        self._tasks.clear()

    def abort(self) -> None:
        self.cancel()

    def close(self) -> None:
        if self.owns_client:
            with contextlib.suppress(Exception):
                self.client.close()


def cores() -> int:
    try:
        return len(os.sched_getaffinity(0))
    except (AttributeError, OSError):
        return os.cpu_count() or 1


def _worker_check(outdir: str) -> dict[str, Any]:
    return {"vigproc": __version__, "outdir": os.path.isdir(outdir) and os.access(outdir, os.W_OK | os.X_OK),
            "exiftool": shutil.which("exiftool") is not None}


def check_workers(client, spec: JobSpec) -> None:
    """Every worker must run this vigproc version and see the output folder.

    Raises
    ------
    BatchError
    """
    try:
        info = client.run(_worker_check, spec.outdir)
    except Exception as exc:
        raise BatchError(f"the dask workers cannot run vigproc ({type(exc).__name__}: {exc}); "
                         "install the same vigproc on every worker") from None
    if not info:
        raise BatchError("the dask cluster has no workers")
    for w, i in sorted(info.items()):
        if i["vigproc"] != __version__:
            raise BatchError(f"worker {w} runs vigproc {i['vigproc']}, this client {__version__}")
        if not i["outdir"]:
            raise BatchError(f"worker {w} cannot write the output folder {spec.outdir} "
                             "(inputs and outputs must be on storage every worker mounts at the same path)")
        if not i["exiftool"]:
            log.warning("worker %s has no exiftool: lens keys and output metadata will be missing there", w)


def connect(address: str, *, timeout: float = 20.0):
    """A ``distributed.Client`` for a running scheduler (``tcp://HOST:PORT``).

    Raises
    ------
    BatchError
        Malformed address, dask.distributed not installed, scheduler unreachable.
    """
    if not isinstance(address, str) or not _SCHEDULER_RE.match(address):
        raise BatchError(f"not a scheduler address: {address!r} (expected tcp://HOST:PORT)")
    try:
        from distributed import Client
    except ImportError:
        raise BatchError("--scheduler needs dask.distributed: pip install 'dask[distributed]'") from None
    try:
        return Client(address, timeout=timeout, set_as_default=False)
    except (OSError, TimeoutError, ValueError) as exc:
        raise BatchError(f"cannot reach the dask scheduler at {address}: {exc}") from None


def local_backend(workers: int | None = None):
    """The default backend: ``workers`` local processes (default: all cores; 1 runs
    in the client process)."""
    n = cores() if workers is None else int(workers)
    if n < 1:
        raise BatchError(f"--workers must be at least 1, got {workers}")
    return _InProcess() if n == 1 else _Pool(n)


def dask_backend(client, *, retries: int = 2, numba_threads: int = 1, owns_client: bool = False):
    """A backend running tasks on the cluster of ``client`` (see :class:`_Dask`)."""
    return _Dask(client, retries=retries, numba_threads=numba_threads, owns_client=owns_client)
