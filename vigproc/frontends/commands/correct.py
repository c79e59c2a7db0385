"""``vigproc correct FILES... -o OUT`` and ``vigproc demo``: remove the vignetting of each
frame through the processor (:class:`vigproc.pipeline.processor.Processor`)."""

from __future__ import annotations

import argparse
import contextlib
import logging
import sys
import threading
from collections import deque
from concurrent.futures import Future, ThreadPoolExecutor
from importlib import resources
from pathlib import Path

from vigproc.core.model import VignettingModel
from vigproc.errors import DiskFullError, VigprocError, one_line
from vigproc.frontends.commands._options import (failure_record, files_exit_code, interrupted, learn_setting,
                                                 print_json_results)
from vigproc.frontends.commands._progress import _progress
from vigproc.io.lensident import display_lens_id
from vigproc.pipeline.faults import DISK_FULL, classify_error
from vigproc.pipeline.outputs import sweep_flat_temporaries
from vigproc.pipeline.processor import InputFiles, Processor, Settings, output_folder, output_stems
from vigproc.stores.opening import open_profile_store

logger = logging.getLogger(__name__)

#: Files whose outputs are being written or wait for the writer thread, at most. A file
#: whose write is slow (a corrected frame: its encode and exiftool's metadata copy) no
#: longer stops the next files' reading and estimating; lines and records still come
#: in input order, as each file is written.
WRITE_QUEUE = 6
#: Of those, at most this many hold a frame to encode (one frame's codes each: the
#: memory bound); a file not corrected holds none (its input is copied).
WRITE_FRAMES = 2


def _applied_ev(rec: dict) -> float:
    """The fall-off divided out of a corrected frame (the model's, times the strength)."""
    return VignettingModel.from_dict(rec["model"]).field_ev_rms() * rec.get("strength", 1.0)


def _as_given(path: str, outdir: Path) -> str:
    """An output's path under ``outdir`` as the user wrote it (``-o out`` prints
    ``out/NAME``, not the absolute path the record keeps)."""
    try:
        return str(outdir / Path(path).relative_to(outdir.resolve()))
    except ValueError:
        return path


def cmd_correct(args: argparse.Namespace) -> int:
    """Each file through the processor into ``-o``, one line each (or ``--json``); stops
    early when the output disk is full. Exit code: :func:`files_exit_code`'s."""
    made = not Path(args.output).exists()
    outdir = output_folder(args.output)
    files = [Path(f) for f in args.files]
    inputs = InputFiles(files)  # no output may replace an input of this run
    settings = Settings(mode="correct", profile=args.profile, method=args.method, transfer=args.input_transfer,
                        output_format=args.output_format, picture=args.picture, strength=args.strength,
                        unapplied=args.unapplied, in_camera=getattr(args, "in_camera", "respect"),
                        # a one-off correct learns only into a store it was given (or with --learn)
                        learn=learn_setting(args, default=args.profile_db is not None))
    failed = unapplied = 0
    results = []
    full = None  # the fault of the last failure (vigproc.pipeline.faults)
    if settings.learn:  # it writes: a store that cannot be opened is an error now, not per file
        store = open_profile_store(args.profile_db, write=True)
    else:
        store = open_profile_store(args.profile_db) if settings.needs_store else None  # reads only: may be absent
    # Writing (encode, metadata copy, sidecar) runs in one thread beside the next files'
    # read, estimate and correction: OpenImageIO's codecs, exiftool's pipe and Numba's
    # kernels release the GIL, so two cores overlap. Up to WRITE_QUEUE files are being
    # written or wait for the writer, WRITE_FRAMES of them with a frame to encode (that
    # many frames' codes more in memory); lines, records and outputs keep their order.
    # Learning as you go stays one file at a time: a file is pooled only once the file
    # before it is written.
    overlap = not settings.learn and len(files) > 1
    writer = ThreadPoolExecutor(1, thread_name_prefix="vigproc-write") if overlap else None
    # the files being written or waiting for the writer, oldest first: (file, result of
    # written()); reported in this order once written
    pending: deque[tuple[Path, Future]] = deque()
    stopped = threading.Event()  # a write met a full output disk: the writer takes no more

    def written(finish) -> tuple:
        """The writer thread's step for one file: ``(record, None)``, ``(None, (error,
        fault))``, or ``(None, None)`` when a write before it met a full disk (the file
        is then not started: nothing of it is written)."""
        if stopped.is_set():
            return None, None
        try:
            return finish(), None
        except VigprocError as exc:
            fault = classify_error(exc, outdir)  # judged at once, as the file fails
            if fault.kind == DISK_FULL:
                stopped.set()
            return None, (exc, fault)

    def report(f: Path, rec: dict) -> None:
        nonlocal unapplied
        results.append(rec)
        unapplied += not rec.get("applied")
        if not args.json:
            lens = display_lens_id(rec["lens"]["lens_id"])
            if rec.get("applied"):
                tag = f"{rec['source']}: {_applied_ev(rec):.2f} EV fall-off removed"
            else:
                tag = f"not corrected: {rec.get('not_applied', 'nothing applied')}"
            if rec.get("learned"):  # learning as you go: where the frame went
                tag += f"; {rec['learned']['summary']}"
            where = _as_given(rec["output"], outdir) if rec.get("output") else \
                "no image written (see its .vigproc.json)"
            print(one_line(f"{f} -> {where}  [{tag}; lens {lens}]"))

    def fail(f: Path, exc: VigprocError, fault=None) -> bool:
        """Record a file's failure; True when the run must stop (the output disk is full)."""
        nonlocal failed, full
        failed += 1
        results.append(failure_record(f, exc))
        print(one_line(f"vigproc: {str(f)!r}: {exc}"), file=sys.stderr)
        full = fault if fault is not None else classify_error(exc, outdir)
        return full.kind == DISK_FULL  # the machine's fault: every further file would fail the same way

    def settle(keep: int = 0, frames: int | None = None) -> bool:
        """Wait for the oldest files being written and report them, in order, until at
        most ``keep`` are pending and, with ``frames``, at most ``frames`` of them hold
        a frame to encode; True when the run must stop (the files still pending are
        then not started: the writer skips them)."""
        while pending and (len(pending) > keep or
                           (frames is not None and sum(fut.encodes for _, fut in pending) > frames)):
            f, fut = pending[0]
            rec, err = fut.result()
            pending.popleft()
            if rec is None and err is None:  # a write before it stopped the run
                stop = True
            elif err is not None:
                stop = fail(f, *err)
            else:
                report(f, rec.to_dict())
                stop = False
            if stop:
                while pending:  # skipped by the writer (stopped), or cancelled before it starts
                    pending.pop()[1].cancel()
                return True
        return False

    def interrupt_writes() -> None:
        """Ctrl-C: the files waiting for the writer are not started; the one being
        written is finished and reported."""
        while pending and pending[-1][1].cancel():  # newest first: what is cancelled is a run of the last files
            pending.pop()
        settle()

    try:
        with Processor(settings, store=store) as proc:  # one exiftool process for the whole batch
            # Numba's set-up and exiftool's start beside the first file's read; with a writer
            # thread, the metadata writer's exiftool starts there, at the first corrected frame
            proc.prepare(metadata_writer=writer is None)
            for k, (f, stem) in enumerate(_progress(list(zip(files, output_stems(files))), "correcting")):
                try:
                    if k == 0:  # the decode first: the EXIF's waits for exiftool's start (0.1-0.2 s)
                        proc.read_ahead(f)
                        proc.prefetch(f)
                    if k + 1 < len(files):  # the next file's EXIF and pixels read while this one is processed
                        proc.prefetch(files[k + 1])
                        proc.read_ahead(files[k + 1])
                    finish = proc.begin_file(f, outdir, stem, protect=inputs)
                except VigprocError as exc:
                    if settle() or fail(f, exc):
                        break
                    continue
                if writer is None:
                    try:
                        report(f, finish().to_dict())
                    except VigprocError as exc:
                        if fail(f, exc):
                            break
                    continue
                encodes = getattr(finish, "encodes", True)
                # room in the writer's queue; a file before this one that stopped the run
                # makes this one not started
                if settle(keep=WRITE_QUEUE - 1, frames=WRITE_FRAMES - encodes):
                    break
                fut = writer.submit(written, finish)
                fut.encodes = encodes
                pending.append((f, fut))
            settle()
    except KeyboardInterrupt:  # Ctrl-C (SIGTERM alike): what was done, in one line; exit 130 (143)
        with contextlib.suppress(KeyboardInterrupt):  # a file being written is finished and counted
            interrupt_writes()
        return interrupted("correct", f"{len(results) - failed - unapplied} corrected, {unapplied} not corrected, "
                           f"{failed} failed, {len(files) - len(results)} not started; outputs in {outdir}")
    finally:
        if writer is not None:
            writer.shutdown(wait=True)
        if store is not None:
            store.close()
    # nothing writes now: what a killed run's writer left of these files' outputs goes
    swept = sweep_flat_temporaries(outdir, files, output_stems(files))
    if swept:
        logger.info("removed %d temporary file(s) a killed run left in %s", swept, outdir)
    not_started = len(files) - len(results)
    failed += not_started
    stop = None
    if full is not None and full.kind == DISK_FULL:
        where = outdir if full.disk == "output disk" else f"the {full.disk}"  # a store's disk names its folder
        stop = DiskFullError(f"{full.reason}; stopped with {not_started} file(s) not started: free space on "
                             f"{where} and run again")
        results += [failure_record(f, DiskFullError("not started: the output disk is full")) for f in files[len(results):]]
    if made and failed == len(files):  # nothing written: leave no empty folder behind
        with contextlib.suppress(OSError):
            outdir.rmdir()
    # every file failed alike: that error's code, as estimate, check and hook say it
    code = stop.exit_code if stop is not None else files_exit_code([r.get("exit_code") for r in results])
    if args.json:
        print_json_results(results, code)
    else:
        print(f"{len(files) - failed - unapplied} corrected, {unapplied} not corrected, {failed} failed; "
              + (f"outputs in {outdir}" if failed < len(files) else "nothing written"))
    if stop is not None:
        raise stop
    return code


def cmd_demo(args: argparse.Namespace) -> int:
    """Estimate and correct the bundled sample images with the embedded defaults."""
    samples = resources.files("vigproc.data").joinpath("samples")
    files = sorted(Path(str(samples)).glob("*.jpg"))
    if not files:
        raise VigprocError("the bundled samples are missing from this installation")
    ns = argparse.Namespace(files=[str(f) for f in files], output=args.output, method="default",
                            input_transfer=args.input_transfer, picture=True, json=False,
                            output_format="auto", profile="estimate", profile_db=None,
                            strength=1.0, unapplied="keep", in_camera="respect")
    return cmd_correct(ns)
