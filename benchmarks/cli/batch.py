"""``vigproc bench batch``: files/s of vigproc batch on 1 and 2 local workers and a 2-process LocalCluster."""

from __future__ import annotations

import argparse
import importlib.util
import logging
import os
import time
from pathlib import Path

from vigproc.frontends.commands.batch import _quiet_dask

_BENCH_DESC = {"local1": "local, 1 worker (in-process)", "local2": "local, 2 worker processes",
               "localcluster2": "dask LocalCluster, 2 processes"}


def _bench_images(folder: Path, n: int, width: int, height: int) -> list[Path]:
    """``n`` textured, vignetted 16-bit TIFFs (a few distinct scenes, flipped and
    shifted), with camera and lens EXIF written by one exiftool call."""
    import shutil
    import subprocess

    import numpy as np

    from vigproc.io.images import write_image

    from benchmarks.synthetic import table1_model

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

    from benchmarks.synthetic import table1_model

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


def batch_arguments(bp: argparse.ArgumentParser) -> None:
    """``vigproc bench batch``'s options."""
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
