"""``vigproc batch``: a whole archive, resumable, on local cores or a Dask cluster;
``vigproc bench batch``: its throughput with 1 and 2 local workers and a 2-process
``dask.distributed.LocalCluster``.

The job itself is :mod:`vigproc.frontends.batch`; this module parses options, reads the
optional TOML config file, prints the summary and the benchmark table.
"""

from __future__ import annotations

import argparse
import dataclasses
import importlib.util
import json
import logging
import os
import sys
import time
from pathlib import Path
from typing import Any

from vigproc.errors import one_line
from vigproc.frontends.commands._bench import benchmark

log = logging.getLogger(__name__)

#: Keys allowed in the ``[batch]`` table of ``--config`` (name -> type).
CONFIG_KEYS: dict[str, type] = {"scheduler": str, "workers": int, "journal": str, "retries": int,
                                "numba_threads": int, "connect_timeout": float, "profile_db": str}


def read_config(path: str | os.PathLike[str]) -> dict[str, Any]:
    """The ``[batch]`` table of a TOML config file, type-checked.

    Raises
    ------
    BatchError
        Unreadable file, TOML syntax error, unknown key or wrong type.
    """
    import tomllib

    from vigproc.frontends.batch import BatchError

    try:
        with open(path, "rb") as fh:
            doc = tomllib.load(fh)
    except OSError as exc:
        raise BatchError(f"cannot read config file {path}: {exc.strerror or exc}") from None
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
        raise BatchError(f"config file {path} is not valid TOML: {exc}") from None
    table = doc.get("batch", {})
    if not isinstance(table, dict):
        raise BatchError(f"config file {path}: [batch] must be a table")
    out: dict[str, Any] = {}
    for k, v in table.items():
        want = CONFIG_KEYS.get(k)
        if want is None:
            raise BatchError(f"config file {path}: unknown key batch.{k} (known: {', '.join(sorted(CONFIG_KEYS))})")
        if want is float and isinstance(v, int) and not isinstance(v, bool):
            v = float(v)
        if not isinstance(v, want) or isinstance(v, bool):
            what = {str: "a string", int: "an integer", float: "a number"}[want]
            raise BatchError(f"config file {path}: batch.{k} must be {what}, got {v!r}")
        out[k] = v
    return out


def _option(args: argparse.Namespace, config: dict[str, Any], name: str, default: Any = None) -> Any:
    v = getattr(args, name, None)
    return v if v is not None else config.get(name, default)


def cmd_batch(args: argparse.Namespace) -> int:
    from vigproc.frontends import backends as BK
    from vigproc.frontends import batch as B
    from vigproc.frontends.commands._options import learn_setting
    from vigproc.pipeline.processor import Settings

    config = read_config(args.config) if args.config else {}
    learn = learn_setting(args, default=True)
    settings = Settings(mode=args.mode, profile=args.profile, method=args.method, transfer=args.input_transfer,
                        output_format=args.output_format, strength=args.strength, picture=args.picture,
                        unapplied=args.unapplied, in_camera=args.in_camera, learn=learn)
    outdir = Path(args.output).resolve()
    items, missing = B.collect(args.source, outdir)

    profile_file = None
    if settings.profile_is_file:
        from vigproc.stores.profiles import import_profile

        import_profile(settings.profile)  # validate here: one clear error, not one per file
        profile_file = B.Shipped.of(Path(settings.profile).name, Path(settings.profile).read_bytes())
    if settings.mode == "check":
        try:
            from vigproc.forensics.check import default_calibration
        except ImportError:
            raise B.BatchError("check mode is not available in this vigproc installation (no vigproc.forensics.check)") \
                from None
        default_calibration()  # missing: one clear error now, not one per file

    job = B.job_id(args.source, outdir, settings, profile_file.digest if profile_file else None)
    journal = Path(_option(args, config, "journal") or outdir / B.JOURNAL_NAME)
    B.check_local_disk(journal, "journal")

    scheduler = _option(args, config, "scheduler")
    retries = int(_option(args, config, "retries", 2))
    if retries < 0:
        raise B.BatchError(f"retries must be >= 0, got {retries}")
    if scheduler:
        _quiet_dask()
        if args.workers is not None:
            log.warning("--workers is ignored with --scheduler (the cluster decides)")
        client = BK.connect(scheduler, timeout=float(_option(args, config, "connect_timeout", 20.0)))
        backend = BK.dask_backend(client, retries=retries, numba_threads=int(_option(args, config, "numba_threads", 1)),
                                 owns_client=True)
    else:
        backend = BK.local_backend(_option(args, config, "workers"))

    store = snapshot = store_path = None
    client_learns = False
    profile_db = _option(args, config, "profile_db")
    try:
        if settings.needs_store:
            from vigproc.stores.opening import open_profile_store

            store = open_profile_store(profile_db, write=settings.mode == "learn" or settings.learn)
            fs = B.filesystem_type(store.path) if settings.learn else None
            if fs in B.NETWORK_FS:  # every worker would write it: SQLite's locks need a local disk
                why = f"profile store {store.path} is on a {fs} network filesystem; learning as it goes needs a local disk"
                if args.learn:
                    raise B.BatchError(f"{why} (--profile-db, or --no-learn)")
                log.warning("%s: not learning (pass --profile-db on a local disk)", why)
                settings = dataclasses.replace(settings, learn=False)
            if settings.learn and scheduler:
                # a cluster's workers read a snapshot and what the client hands out; the
                # client pools their frames into the store (its one writer)
                log.info("learning as it goes on a cluster: this client pools every frame into %s", store.path)
                snapshot = B.Shipped.of("profiles.sqlite", B.snapshot_store(store))
                client_learns = True
            elif settings.learn:  # local workers pool into the store itself, and read it as profiles become trusted
                store_path = str(store.path.resolve())
                store.close()
                store = None
            elif store is not None and settings.mode != "learn":  # workers read a snapshot; only learn writes, here
                snapshot = B.Shipped.of("profiles.sqlite", B.snapshot_store(store))
                store.close()
                store = None
            elif store is not None:
                fs = B.filesystem_type(store.path)
                if fs in B.NETWORK_FS:
                    log.warning("profile store %s is on a %s network filesystem; SQLite wants a local disk",
                                store.path, fs)
        # created only now: a bad source, option, cluster or store leaves no empty output folder behind
        try:
            outdir.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise B.BatchError(f"cannot create output folder {outdir}: {exc.strerror or exc}") from None
        spec = B.JobSpec(settings=settings, outdir=str(outdir), numba_threads=getattr(backend, "numba_threads", 1),
                         profile_file=profile_file, store_snapshot=snapshot, store_path=store_path,
                         client_learns=client_learns)
        summary = B.run_batch(items, spec, backend, journal_path=journal, job=job, store=store, retries=retries,
                              missing=missing, progress=None if not args.no_progress else False,
                              retry_quarantined=args.retry_quarantined)
    finally:
        backend.close()  # idempotent: also when the job failed before it started
        if store is not None:
            store.close()
    print_summary(summary, outdir, as_json=args.json)
    if summary.interrupted:
        return 130
    if summary.disk_full is not None:
        from vigproc.errors import DiskFullError

        raise DiskFullError(f"batch stopped: {summary.disk_full}; {summary.not_started} file(s) not started, none "
                            f"quarantined for it: free space on {outdir} and rerun the same command to resume")
    return 0 if summary.failed == 0 else 1


def _quiet_dask() -> None:
    """dask configures its loggers at INFO (when imported); vigproc's own -v decides
    what is shown."""
    try:
        import distributed  # noqa: F401  (its import sets the levels overridden here)
    except ImportError:
        return
    level = max(logging.WARNING, logging.getLogger().getEffectiveLevel())
    for name in ("distributed", "dask"):
        logging.getLogger(name).setLevel(level)


def print_summary(summary, outdir: Path, *, as_json: bool = False) -> None:
    """The job's summary on stdout (text, or one JSON object)."""
    if as_json:
        d = summary.to_dict()
        d["output"] = str(outdir)
        print(json.dumps(d, indent=1))
        return
    s = summary
    state = "interrupted" if s.interrupted else "finished"
    print(f"vigproc batch {s.mode} {state}: {s.total} files; {s.processed} processed, {s.skipped} done earlier, "
          f"{s.quarantined} failed for good, {s.retry_later} to retry, {s.missing} missing "
          f"in {s.seconds:.1f} s ({s.files_per_second:.2f} files/s) on {s.backend}")
    if s.redone:
        print(f"  {s.redone} done files had lost their outputs: written again")
    if s.resubmitted:
        print(f"  {s.resubmitted} tasks resubmitted after a worker died or a transient failure")
    if s.disk_full is not None:
        print(f"  stopped handing out files: the output disk is full ({s.not_started} not started)")
    if s.sources:
        print("  model source: " + ", ".join(f"{k} {v}" for k, v in sorted(s.sources.items())))
    for key, p in sorted(s.profiles.items()):
        sigma = "±?" if p["field_sigma_ev"] is None else f"±{p['field_sigma_ev']:.3f} EV"
        print(f"  profile {key}: {p['n_frames']} frames, {sigma}, {'trusted' if p['trusted'] else 'learning'}")
    for e in s.errors[:20]:  # names and errors escaped: a file name cannot forge a line
        print(one_line(f"  failed: {e['file']}: {e['error']}"), file=sys.stderr)
    if len(s.errors) > 20 or s.failed > len(s.errors):
        print(f"  ... {s.failed - min(20, len(s.errors))} more failures (see the journal or --json)", file=sys.stderr)
    print(f"outputs in {outdir}; journal {s.journal}" + ("; rerun the same command to resume" if s.interrupted
                                                           or s.retry_later else ""))


def register(subparsers) -> None:
    from vigproc.frontends.commands._options import add_learn, add_processing, number
    from vigproc.pipeline.processor import MODES

    sp = subparsers.add_parser(
        "batch", help="process a whole archive (folder or file list), resumable, on local cores or a Dask cluster",
        description="Process every image under DIR (recursive; hidden files skipped) or listed in LIST (one path "
                    "per line, relative to the list's folder). Outputs mirror the input tree under OUT (not DIR "
                    "itself; nothing inside OUT is ever taken as input). Interrupt "
                    "at any time and rerun the same command to resume: done files are not redone.")
    sp.add_argument("source", metavar="DIR|LIST", help="folder of images, or a text file listing them (one per line)")
    sp.add_argument("--mode", choices=MODES, required=True, help="correct, estimate, check or learn")
    sp.add_argument("-o", "--output", required=True, help="output folder (sidecars, corrected images)")
    sp.add_argument("--workers", type=number(1, 1024, integer=True), help="local worker processes (default: all cores)")
    sp.add_argument("--scheduler", help="run on a dask.distributed cluster: tcp://HOST:PORT of its scheduler")
    sp.add_argument("--config", help="TOML file with a [batch] table: scheduler, workers, journal, retries, "
                                     "numba_threads, connect_timeout, profile_db")
    sp.add_argument("--journal", help="journal database (default OUT/.vigproc-batch.sqlite; must be on a local disk)")
    sp.add_argument("--retries", type=int, help="resubmissions of a file whose worker died (default 2)")
    add_processing(sp)
    add_learn(sp, "on with --mode correct and --profile auto")
    sp.add_argument("--json", action="store_true", help="print the summary as JSON")
    sp.add_argument("--no-progress", action="store_true", help="no progress bar even on a terminal")
    sp.add_argument("--retry-quarantined", action="store_true",
                    help="process again the files earlier runs gave up on (after fixing the cause)")
    sp.set_defaults(fn=cmd_batch)


# ------------------------------------------------------------------- bench
def _bench_images(folder: Path, n: int, width: int, height: int) -> list[Path]:
    """``n`` textured, vignetted 16-bit TIFFs (a few distinct scenes, flipped and
    shifted), with camera and lens EXIF written by one exiftool call."""
    import shutil
    import subprocess

    import numpy as np

    from vigproc.io.images import write_image

    table1_model = benchmark("synthetic").table1_model

    rng = np.random.default_rng(0)
    field = table1_model(1).rescale(width, height).field((height, width))
    scenes = []
    for _ in range(4):
        f = np.fft.rfft2(rng.normal(size=(height, width)))
        fy, fx = np.fft.fftfreq(height)[:, None], np.fft.rfftfreq(width)[None, :]
        tex = np.fft.irfft2(f / np.maximum(np.hypot(fx, fy), 1.0 / max(height, width)) ** 0.9, s=(height, width))
        scenes.append(0.4 * np.exp(0.3 * tex / tex.std()))
    files = []
    for i in range(n):
        s = np.roll(scenes[i % 4], 37 * i, axis=1)
        s = s[:, ::-1] if (i // 4) % 2 else s
        img = (s * field)[..., None] * np.array([1.0, 0.9, 0.8])
        p = folder / f"frame{i:03d}.tif"
        write_image(p, img, bit_depth="uint16")
        files.append(p)
    if shutil.which("exiftool"):
        subprocess.run(["exiftool", "-q", "-overwrite_original", "-Make=Vigproc", "-Model=Bench 1",
                        "-LensModel=VP 35mm F2.0 Bench", "-FocalLength=35", "-FNumber=2.0", "--",
                        *map(str, files)], check=True, capture_output=True)
    return files


def _bench_profile(path: Path, width: int, height: int) -> None:
    from vigproc.stores.profiles import Profile, ProfileKey, aspect_label, export_profile, normalise

    table1_model = benchmark("synthetic").table1_model

    theta, _, aspect = normalise(table1_model(1).rescale(width, height))
    key = ProfileKey("vigproc|bench 1|vp 35mm f2.0 bench", "any", "any", aspect_label(aspect))
    export_profile(Profile(key=key, theta=theta, provenance="user", trusted=True, notes="vigproc bench batch"), path)


def _cpu_seconds() -> float:
    """CPU time of this process and of its finished (waited-for) descendants."""
    import resource

    me, kids = resource.getrusage(resource.RUSAGE_SELF), resource.getrusage(resource.RUSAGE_CHILDREN)
    return me.ru_utime + me.ru_stime + kids.ru_utime + kids.ru_stime


def _load() -> float:
    """1-minute load average (other users of a shared machine skew the figures)."""
    return os.getloadavg()[0] if hasattr(os, "getloadavg") else float("nan")


def cmd_bench_batch(args: argparse.Namespace) -> int:
    """Files per second of one job with 1 and 2 local workers and a 2-process LocalCluster."""
    import tempfile

    from vigproc.frontends import backends as BK
    from vigproc.frontends import batch as B
    from vigproc.pipeline.processor import Settings

    _quiet_dask()
    load = _load()
    with tempfile.TemporaryDirectory(prefix="vigproc-bench-batch-", dir=args.tmp) as tmp:
        root = Path(tmp)
        src = root / "in"
        src.mkdir()
        t0 = time.perf_counter()
        _bench_images(src, args.files, args.width, args.height)
        prof = root / "bench-profile.json"
        _bench_profile(prof, args.width, args.height)
        items, _ = B.collect(src, root / "out")
        mb = sum(os.path.getsize(i.path) for i in items) / 1e6
        print(f"{len(items)} files of {args.width}x{args.height} RGB 16-bit TIFF ({mb / len(items):.1f} MB each, "
              f"made in {time.perf_counter() - t0:.1f} s); {BK.cores()} cores, load average {load:.2f} at start "
              "(the machine may be shared)")
        print(f"best of {args.repeat} interleaved runs per row; files/s: 'steady' = (n-1) / (last - first completion); 'wall' includes worker start-up and warm-up; "
              "'cpu/f' = CPU seconds per file of all our processes (client, workers, exiftool), start-up included; "
              "'load' = 1-min load average after the row")
        print(f"{'mode':<26}{'backend':<34}{'start s':>8}{'wall s':>8}{'files/s':>9}{'steady':>9}{'vs 1':>7}"
              f"{'cpu/f':>7}{'load':>6}")
        modes = {"correct": Settings(mode="correct", profile=str(prof), output_format=args.output_format),
                 "estimate": Settings(mode="estimate", profile="estimate")}
        backends = []
        for name in args.backends:
            if name == "localcluster2" and importlib.util.find_spec("distributed") is None:
                print("dask LocalCluster: not installed (pip install 'dask[distributed]'); row skipped")
                continue
            backends.append(name)
        for mode in args.modes:
            label = f"{mode} ({'profile file' if mode == 'correct' else 'default method'})"
            runs: dict[str, list[dict[str, float]]] = {name: [] for name in backends}
            for r in range(args.repeat):  # interleaved, so that a burst of other load hits all rows alike
                for name in backends:
                    runs[name].append(_bench_run(B, items, modes[mode], name, root / f"out-{mode}-{name}-{r}",
                                                 prof if mode == "correct" else None))
            base = None
            for name in backends:
                best = max(runs[name], key=lambda x: x["steady"])
                base = base or best["steady"]
                print(f"{label:<26}{_BENCH_DESC[name]:<34}{best['start']:>8.2f}{best['wall']:>8.2f}"
                      f"{best['rate']:>9.2f}{best['steady']:>9.2f}{best['steady'] / base:>6.2f}x{best['cpu']:>7.2f}"
                      f"{best['load']:>6.1f}", flush=True)
    return 0


_BENCH_DESC = {"local1": "local, 1 worker (in-process)", "local2": "local, 2 worker processes",
               "localcluster2": "dask LocalCluster, 2 processes"}


def _bench_run(B, items, settings, name: str, out: Path, prof: Path | None) -> dict[str, float]:
    """One job on one backend, from creating the backend to closing it."""
    from vigproc.frontends import backends as BK

    t_start = time.perf_counter()
    cpu0 = _cpu_seconds()
    cluster = client = None
    if name == "localcluster2":
        from distributed import Client, LocalCluster

        # dashboard on a free port: None would still bind the scheduler's HTTP server to 8787
        cluster = LocalCluster(n_workers=2, processes=True, threads_per_worker=1, dashboard_address=":0",
                               silence_logs=logging.ERROR)
        client = Client(cluster, set_as_default=False)
        backend = BK.dask_backend(client, numba_threads=1)
    else:
        backend = BK.local_backend(1 if name == "local1" else 2)
    start_s = time.perf_counter() - t_start
    stamps: list[float] = []
    pf = B.Shipped.of(prof.name, prof.read_bytes()) if prof is not None else None
    spec = B.JobSpec(settings=settings, outdir=str(out.resolve()), profile_file=pf,
                     numba_threads=getattr(backend, "numba_threads", 1))
    out.mkdir()
    try:
        s = B.run_batch(items, spec, backend, journal_path=out / B.JOURNAL_NAME, job="bench",
                        progress=False, on_result=lambda *_: stamps.append(time.perf_counter()))
    finally:
        if client is not None:
            client.close()
            cluster.close()
    cpu = (_cpu_seconds() - cpu0) / max(1, s.processed)  # the workers are gone (and counted) by now
    if s.processed != len(items):
        print(f"  {name}: only {s.processed} of {len(items)} files processed: {s.errors[:3]}")
    wall = s.seconds + start_s
    steady = (len(stamps) - 1) / (stamps[-1] - stamps[0]) if len(stamps) > 1 else float("nan")
    return {"start": start_s, "wall": wall, "rate": s.processed / wall, "steady": steady, "cpu": cpu,
            "load": _load()}


def register_bench(bench_subparsers) -> None:
    bp = bench_subparsers.add_parser("batch", help="batch files/s: 1 and 2 local workers, 2-process LocalCluster")
    bp.add_argument("--files", type=int, default=40, help="generated frames (default %(default)s)")
    bp.add_argument("--width", type=int, default=1500, help="frame width in px (default %(default)s)")
    bp.add_argument("--height", type=int, default=1000, help="frame height in px (default %(default)s)")
    bp.add_argument("--modes", nargs="+", choices=["correct", "estimate"], default=["correct", "estimate"],
                    help="modes to time (default: correct estimate)")
    bp.add_argument("--backends", nargs="+", choices=["local1", "local2", "localcluster2"],
                    default=["local1", "local2", "localcluster2"],
                    help="one process, a pool of two, a Dask LocalCluster of two (default: all three)")
    bp.add_argument("--output-format", default="tiff16", help="output format of the correct rows (default tiff16)")
    bp.add_argument("--repeat", type=int, default=2, help="runs per row, interleaved; the best is shown (default 2)")
    bp.add_argument("--tmp", help="folder for the temporary files (default: the system's)")
    bp.set_defaults(fn=cmd_bench_batch)
