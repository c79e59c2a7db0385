"""The worker process: one :class:`~vigproc.pipeline.processor.Processor`, tasks in over a
pipe, results out, until told to stop or the daemon goes away.

Workers are processes (``spawn``), not threads: a decoder crash on a hostile file
kills one worker, not the daemon.  Each leads a process group of its own, ignores
SIGINT/SIGTERM (the daemon drains it), dies with the daemon and raises its OOM score.

The messages, daemon to worker: ``("task", id, path, out_root, rel, fingerprint, extra,
alone)`` and ``("stop",)``; worker to daemon: ``("ready", None, pid)``, ``("fatal", None,
why)``, ``("start", id, None)``, ``("ahead", id, None)`` (its file is being read ahead,
while the task before it runs), ``("ok", id, summary)``, ``("error", id, {kind, reason,
type, disk, free_bytes})``.  A task ``alone`` is neither read ahead nor run beside a
read ahead.
"""

from __future__ import annotations

import collections
import contextlib
import json
import logging
import multiprocessing.connection as mpc
import os
import signal
from pathlib import Path
from typing import Any

from vigproc.frontends.batch_worker import warm_up
from vigproc.pipeline.faults import DEFAULT_MIN_FREE, PERMANENT, classify_error
from vigproc.pipeline.processor import SIDECAR_SUFFIX, Processor, Settings, output_location, safe_output
from vigproc.processes import die_with_parent
from vigproc.stores.journal import Fingerprint
from vigproc.stores.opening import open_profile_store

from .logs import configure_logging


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
        "applied": d.get("applied"), "not_applied": d.get("not_applied"), "profile": d.get("profile"),
        "learned": (d.get("learned") or {}).get("summary"),
        "seconds": d.get("seconds"),
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
        s = Settings(**settings)
        if s.needs_store:
            store = open_profile_store(profile_db, write=s.mode == "learn")
        proc = Processor(s, store=store)
    except Exception as exc:  # a worker that cannot start is fatal for the daemon: say why
        conn.send(("fatal", None, f"{type(exc).__name__}: {exc}"))
        return
    # exiftool's start (Perl loading its modules) beside the warm-up, not waited for: one
    # that cannot start is reported by the first file that needs it, as before
    proc.prepare()
    _warm(wlog)
    try:
        conn.send(("ready", None, os.getpid()))
        queued: collections.deque = collections.deque()  # received, not begun: at most the next task
        while True:
            try:
                msg = queued.popleft() if queued else conn.recv()
            except (EOFError, OSError):
                break
            if msg[0] == "stop":
                break
            _, task_id, path, out_root, rel, fpd, extra, alone = msg
            conn.send(("start", task_id, None))
            if not alone and not queued and conn.poll():
                queued.append(conn.recv())
                _read_next(conn, proc, queued[0])
            fp = Fingerprint.from_dict(fpd)
            outdir = Path(out_root)  # judged on the output root until its sub-folder is made
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
                                        frame_id=fp.sha256 if s.mode == "learn" or s.learn else None)
                conn.send(("ok", task_id, _summary(res.to_dict(), sidecar)))
            except Exception as exc:  # noqa: BLE001 - every failure becomes a per-file record
                # judged here, at once: a failed writer's temporary is gone, so the output
                # disk's free space is what the next file would find
                fault = classify_error(exc, outdir, min_free=min_free)
                if fault.kind == PERMANENT and fault.reason.startswith("internal error"):
                    wlog.debug("internal error on %s", path, exc_info=True)
                output_disk = fault.space is not None and fault.disk == "output disk"
                conn.send(("error", task_id, {"kind": fault.kind, "reason": fault.reason, "type": type(exc).__name__,
                                              "disk": fault.disk,
                                              "free_bytes": fault.space.free_bytes if output_disk else None}))
            finally:  # read ahead and not read (its sidecar answered, or it failed first): not held on
                proc.drop_read_ahead(path)
    except (BrokenPipeError, EOFError, OSError):
        pass  # the daemon is gone
    finally:
        with contextlib.suppress(Exception):
            proc.close()
        if store is not None:
            with contextlib.suppress(Exception):
                store.close()


def _read_next(conn: mpc.Connection, proc: Processor, msg: tuple) -> None:
    """Read the next queued task's file ahead (its EXIF by exiftool, its pixels in a
    thread: :meth:`Processor.prefetch`, :meth:`Processor.read_ahead`) while this one is
    processed, so the worker does not wait for them (issue 39).  The daemon is told
    first (``ahead``): a worker that dies now may have died of either file, and the
    daemon charges neither but tries both again alone.  A task sent ``alone`` is
    not read ahead."""
    if msg[0] != "task" or msg[7]:
        return
    conn.send(("ahead", msg[1], None))
    proc.prefetch(msg[2])
    proc.read_ahead(msg[2])


def _warm(wlog: logging.Logger) -> None:
    """Pay the worker's start-up once, before it says it is ready, not on its first
    file: the Numba kernels loaded from their cache (compiled the first time on a
    machine) and this worker's share of the cores for Numba and OpenImageIO.  Not
    fatal: what fails now fails again, and is reported, on a file.  (Its exiftool
    processes start with the first file and persist: a hung exiftool is then charged to
    the file that met it, with the worker's timeout.)"""
    threads = os.environ.get("NUMBA_NUM_THREADS", "")  # set per worker by the scheduler
    try:
        warm_up(int(threads) if threads.isdigit() else None)
    except Exception:  # noqa: BLE001 - the first file says it again, with its name
        wlog.debug("warm-up of the kernels failed", exc_info=True)


def _kill_group(process: Any) -> None:
    """SIGKILL a worker and what it started (exiftool): it leads a process group of its own."""
    pid = process.pid
    if pid is not None and pid != os.getpgrp():  # never our own group (if the worker could not leave it)
        with contextlib.suppress(OSError):
            os.killpg(pid, signal.SIGKILL)
    with contextlib.suppress(OSError, ValueError):
        process.kill()


