"""``vigproc bench watch`` (watch-folder throughput with a trusted profile vs bare read and write) and
``vigproc bench faults`` (the daemon under a filling disk and kill -9, :mod:`benchmarks.faults`)."""

from __future__ import annotations

import argparse
import json
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

from vigproc.errors import VigprocError
from vigproc.frontends.commands.watch import _default_workers
from vigproc.pipeline.processor import OUTPUT_FORMATS


def _write_jpeg(path: Path, rgb01, quality: int = 92) -> None:
    import numpy as np
    import OpenImageIO as oiio

    from vigproc.io.images import linear_to_srgb

    data = np.round(255 * np.clip(linear_to_srgb(rgb01), 0, 1)).astype(np.uint8)
    spec = oiio.ImageSpec(data.shape[1], data.shape[0], 3, oiio.UINT8)
    spec.attribute("Compression", f"jpeg:{quality}")
    out = oiio.ImageOutput.create(str(path))
    if out is None or not out.open(str(path), spec):
        raise VigprocError(f"cannot write {path}: {oiio.geterror()}")
    ok = out.write_image(data)
    out.close()
    if not ok:
        raise VigprocError(f"cannot write {path}: {oiio.geterror()}")


def _make_inputs(folder: Path, n: int, width: int, height: int, fmt: str, model) -> list[Path]:
    """N distinct synthetic frames with the model's vignetting, plus camera/lens EXIF."""
    import numpy as np

    from vigproc.io.images import write_image

    from benchmarks.io import synthetic_frame

    base = synthetic_frame(height, width) * model.field((height, width)).astype(np.float32)[..., None]
    rng = np.random.default_rng(1)
    files = []
    for i in range(n):
        img = np.clip(base * np.float32(rng.uniform(0.8, 1.2)), 0, 1)
        img[i % height, :, :] = 0.5  # distinct content per file
        p = folder / (f"frame {i:03d}.jpg" if fmt == "jpeg" else f"frame {i:03d}.tif")
        if fmt == "jpeg":
            _write_jpeg(p, img)
        else:
            write_image(p, img, bit_depth="uint16")
        files.append(p)
    exe = shutil.which("exiftool")
    if exe is None:
        raise VigprocError("the benchmark needs the exiftool program to give its frames a lens")
    tags = {"Make": "Vigproc", "Model": "Bench Camera", "LensModel": "Bench 35mm F2", "FocalLength": 35,
            "FNumber": 2.8}
    subprocess.run([exe, "-q", "-overwrite_original", *[f"-{k}={v}" for k, v in tags.items()], "--",
                    *map(str, files)], check=True, capture_output=True)
    return files


def _trusted_profile(db: Path, sample: Path, model, width: int, height: int) -> str:
    """Store ``model`` as a trusted profile of the sample's lens; returns its key."""
    from vigproc.io.exif import ExifReader
    from vigproc.stores.profiles import Profile, ProfileKey, ProfileStore, normalise

    with ExifReader() as r:
        lens = r.read(sample)
    key = ProfileKey.from_lens(lens, width, height)
    with ProfileStore(db) as store:
        store.put(Profile(key=key, theta=normalise(model.rescale(width, height))[0], covariance=None,
                          provenance="user", trusted=True, notes="vigproc bench watch"))
    return str(key)


def _bare_io(task: tuple[str, str, str, str, Any]) -> float:
    """Seconds to read one input and write one output of the benchmark's format.

    ``what``: ``pixels`` (the input's own pixels, no metadata), ``pixels+metadata``
    (plus the source's metadata, as the daemon's outputs get it) or ``output`` (the
    very pixels the daemon writes -- the correction is computed outside the timed
    part -- with metadata and the correction record).  The last is the bare cost of
    reading and writing the same files: deflating corrected 16-bit pixels costs more
    than deflating a JPEG's 8-bit levels.
    """
    from vigproc.io.images import read_image, write_image
    from vigproc.io.metadata import make_record, write_corrected
    from vigproc.pipeline.processor import output_format_for

    src, dst, fmt, what, model = task
    of = output_format_for(fmt, src)
    suffix, depth = of.suffix, of.depth
    t0 = time.perf_counter()
    img, _ = read_image(src)
    t_read = time.perf_counter() - t0
    record = None
    if what == "output":
        from vigproc.core.correct import correct

        img = correct(img, model, channel_axis=-1, clip=1.0 if of.integer else None)
        record = make_record(model, strength=1.0)
    t1 = time.perf_counter()
    if what == "pixels":
        write_image(dst + suffix, img, format=of.format, bit_depth=depth, transfer=of.transfer, quality=of.quality)
    else:
        write_corrected(dst + suffix, img, src, record, bit_depth=depth, format=of.format, transfer=of.transfer,
                        quality=of.quality)
    return t_read + time.perf_counter() - t1


def _pool_init() -> None:
    signal.signal(signal.SIGINT, signal.SIG_IGN)


def _time_bare(files: list[Path], outdir: Path, fmt: str, workers: int, what: str, model) -> float:
    """Files per second of the bare read+write of ``files`` by ``workers`` processes (after
    one warm-up file each): n / (sum of the timed reads and writes / workers)."""
    import multiprocessing as mp

    outdir.mkdir(parents=True, exist_ok=True)
    ctx = mp.get_context("spawn")
    with ctx.Pool(workers, initializer=_pool_init) as pool:
        pool.map(_bare_io, [(str(files[i % len(files)]), str(outdir / f"warm{i}"), fmt, what, model)
                            for i in range(workers)], chunksize=1)
        secs = pool.map(_bare_io, [(str(f), str(outdir / f"{i:04d}"), fmt, what, model) for i, f in enumerate(files)],
                        chunksize=1)
    shutil.rmtree(outdir, ignore_errors=True)
    return len(files) / (sum(secs) / workers)


def _cpu_seconds(pid: int) -> float | None:
    """User + system CPU seconds of a running process (Linux)."""
    try:
        fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
        return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")
    except (OSError, ValueError, IndexError):
        return None


def _wait_done(journal: Path, job: str | None, n: int, proc: subprocess.Popen, timeout: float) -> list[float]:
    """Poll the daemon's journal until ``n`` entries are done; returns their completion
    times (epoch seconds, from the journal's timestamps)."""
    from datetime import datetime

    from vigproc.stores.journal import Journal

    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if proc.poll() is not None:
            raise VigprocError(f"the daemon exited early (code {proc.returncode})")
        if journal.exists():
            with Journal(journal, job=job or "default") as j:
                c = j.counts()
                if c["quarantined"]:
                    raise VigprocError(f"the daemon quarantined files: {[e.reason for e in j.entries('quarantined')]}")
                if c["done"] >= n:
                    return sorted(datetime.fromisoformat(e.updated.replace("Z", "+00:00")).timestamp()
                                  for e in j.entries("done"))
        time.sleep(0.05)
    raise VigprocError(f"the daemon did not finish {n} files within {timeout:.0f} s")


def files_in(folder: Path) -> list[Path]:
    return sorted(p for p in folder.iterdir() if p.is_file() and not p.name.startswith(("warm", ".")))


def cmd_bench_watch(args: argparse.Namespace) -> int:
    """Sustained daemon throughput with a trusted profile vs the bare read+write of the
    same files in the same run."""
    from benchmarks.synthetic import table1_model

    n, w, h, k = args.files, args.width, args.height, args.workers
    model = table1_model(1).rescale(w, h)
    mp_per = w * h / 1e6
    tmp = Path(tempfile.mkdtemp(prefix="vigproc-bench-watch-", dir=args.tmp))
    proc = None
    try:
        stage, warm = tmp / "stage", tmp / "warm"
        stage.mkdir()
        warm.mkdir()
        t0 = time.perf_counter()
        files = _make_inputs(stage, n, w, h, args.input_format, model)
        warm_files = [shutil.copy2(files[i % n], warm / f"warm {i}{files[0].suffix}") for i in range(k)]
        key = _trusted_profile(tmp / "profiles.sqlite", files[0], model, w, h)
        in_mb = sum(f.stat().st_size for f in files) / 1e6
        print(f"{n} files of {w}x{h} ({mp_per:.1f} MP, {args.input_format}, {in_mb / n:.1f} MB each) -> "
              f"{args.output_format}; trusted profile {key}; {k} worker process(es); inputs made in "
              f"{time.perf_counter() - t0:.1f} s")

        bare = {}
        for what in ("pixels", "pixels+metadata", "output"):
            bare[what] = _time_bare(files, tmp / f"bare-{what}", args.output_format, k, what, model)

        # the daemon, as a real process, on a warm start; the files appear at once by rename
        in_dir, out_dir = tmp / "in", tmp / "out"
        in_dir.mkdir()
        journal = tmp / "journal.sqlite"
        cmd = [sys.executable, "-m", "vigproc.frontends.cli", "watch", str(in_dir), "-o", str(out_dir), "--workers", str(k),
               "--settle", str(args.settle), "--journal", str(journal), "--job", "bench",
               "--profile-db", str(tmp / "profiles.sqlite"), "--output-format", args.output_format, "--log-json"]
        with open(tmp / "daemon.log", "wb") as logf:
            proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=logf)
            for f in warm_files:
                os.rename(f, in_dir / Path(f).name)
            _wait_done(journal, "bench", k, proc, timeout=600)
            t_drop = time.time()
            for f in files:
                os.rename(f, in_dir / f.name)
            cpu0 = _cpu_seconds(proc.pid)
            done_at = _wait_done(journal, "bench", n + k, proc, timeout=600 + 60 * n)[k:]
            cpu1 = _cpu_seconds(proc.pid)
            proc.send_signal(signal.SIGTERM)
            code = proc.wait(timeout=120)
        wall = done_at[-1] - t_drop
        steady = (n - k) / (done_at[-1] - done_at[k - 1]) if n > k and done_at[-1] > done_at[k - 1] else float("nan")
        sources = set()
        for sc in out_dir.glob("frame*.vigproc.json"):
            sources.add(json.loads(sc.read_text()).get("source"))
        # the same bare run once more: how much the machine's load drifted meanwhile
        bare["output, again after"] = _time_bare(files_in(in_dir), tmp / "bare-again", args.output_format, k,
                                                 "output", model)
        labels = {"pixels": "input's pixels, no metadata", "pixels+metadata": "input's pixels + metadata",
                  "output": "the daemon's output pixels + metadata",
                  "output, again after": "the same, measured after the daemon"}
        print(f"{'':<56}{'files/s':>9}{'MP/s':>8}{'s/file/worker':>15}")
        for what, rate in bare.items():
            print(f"{'bare read+write, ' + labels[what]:<56}{rate:>9.2f}{rate * mp_per:>8.1f}{k / rate:>15.3f}")
        print(f"{'daemon, files dropped -> last done':<56}{n / wall:>9.2f}{n * mp_per / wall:>8.1f}{wall * k / n:>15.3f}")
        if steady == steady:
            print(f"{'daemon, steady state (after the first ' + str(k) + ')':<56}{steady:>9.2f}{steady * mp_per:>8.1f}"
                  f"{k / steady:>15.3f}")
        for what, rate in bare.items():
            print(f"daemon / bare ({labels[what]}): {100 * (n / wall) / rate:.0f} % (drop to last done)"
                  + (f", {100 * steady / rate:.0f} % (steady)" if steady == steady else ""))
        if cpu0 is not None and cpu1 is not None:
            print(f"daemon main process: {cpu1 - cpu0:.2f} CPU s for {n} files ({1000 * (cpu1 - cpu0) / n:.0f} ms/file: "
                  "events, hashing, journal, status)")
        print(f"daemon exit code after SIGTERM: {code}; sources used: {', '.join(sorted(map(str, sources)))}")
        proc = None
    finally:
        if proc is not None and proc.poll() is None:
            proc.kill()
            proc.wait()
        if args.keep:
            print(f"kept {tmp}")
        else:
            shutil.rmtree(tmp, ignore_errors=True)
    return 0


def watch_arguments(bp: argparse.ArgumentParser) -> None:
    """``vigproc bench watch``'s options."""
    bp.add_argument("--files", type=int, default=40, help="generated frames (default %(default)s)")
    bp.add_argument("--width", type=int, default=3000, help="frame width in px (default %(default)s)")
    bp.add_argument("--height", type=int, default=2000, help="frame height in px (default %(default)s)")
    bp.add_argument("--workers", type=int, default=_default_workers(), help="daemon workers (default %(default)s)")
    bp.add_argument("--input-format", choices=("jpeg", "tiff16"), default="jpeg",
                    help="format of the generated frames (default %(default)s)")
    bp.add_argument("--output-format", choices=list(OUTPUT_FORMATS), default="tiff16",
                    help="the daemon's output format (default %(default)s)")
    bp.add_argument("--settle", type=float, default=0.2,
                    help="seconds a file must stay unchanged before it is processed (default %(default)s)")
    bp.add_argument("--tmp", help="folder for the temporary files (default: the system's)")
    bp.add_argument("--keep", action="store_true", help="keep the temporary folder")
    bp.set_defaults(fn=cmd_bench_watch)


def cmd_bench_faults(args: argparse.Namespace) -> int:
    """``vigproc bench faults``: the daemon under a filling disk and kill -9 (benchmarks/faults.py)."""
    from benchmarks.faults import cmd_bench_faults as run

    return run(args)


def faults_arguments(bp: argparse.ArgumentParser) -> None:
    """``vigproc bench faults``'s options."""
    bp.add_argument("--images", help="folder of camera JPEGs (default: the shared data's jpeg_exif)")
    bp.add_argument("--files", type=int, default=24, help="healthy inputs (default %(default)s)")
    bp.add_argument("--workers", type=int, default=2, help="daemon workers (default %(default)s)")
    bp.add_argument("--small", type=int, default=20, help="tmpfs size in MB while it fills (default %(default)s)")
    bp.add_argument("--grow", type=int, default=1024, help="tmpfs size in MB once grown (default %(default)s)")
    bp.add_argument("--kills", type=int, default=5,
                    help="kill -9 of the daemon: half while the disk is full, the rest once it was grown "
                         "(default %(default)s)")
    bp.add_argument("--tmp", help="folder for the run's files (default: the system's temporary folder)")
    bp.add_argument("--keep", action="store_true", help="keep the run's folder (the daemon's log)")
    bp.add_argument("--json", action="store_true", help="the figures as JSON")
    bp.set_defaults(fn=cmd_bench_faults)
