"""``vigproc watch``: the watch-folder daemon; ``vigproc bench watch``, its throughput, and
``vigproc bench faults``, its behaviour on a filling disk (:mod:`benchmarks.faults`).

The daemon itself is :mod:`vigproc.frontends.daemon`; the journal :mod:`vigproc.stores.journal`.
"""

from __future__ import annotations

import argparse
import json
import logging
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
from vigproc.stores.retry import DEFAULT_MAX_ATTEMPTS, DEFAULT_MAX_CRASHES, DEFAULT_RETRY_BASE, DEFAULT_RETRY_CAP
from vigproc.frontends.commands._bench import benchmark

log = logging.getLogger("vigproc.watch")


def _default_workers() -> int:
    return max(1, (os.cpu_count() or 2) // 2)


def _config(args: argparse.Namespace):
    from vigproc.frontends.daemon import WatchConfig
    from vigproc.pipeline.processor import names_profile_file

    profile = args.profile
    if names_profile_file(profile):
        profile = str(Path(profile).expanduser().resolve())  # workers must find it whatever their cwd
    settings = {"mode": args.mode, "profile": profile, "method": args.method, "transfer": args.input_transfer,
                "output_format": args.output_format, "picture": bool(args.picture), "strength": args.strength,
                "unapplied": args.unapplied, "in_camera": args.in_camera}
    from vigproc.frontends.commands._options import learn_setting

    if learn_setting(args, default=True):  # a hot folder learns each lens as its photos arrive
        settings["learn"] = True
    level = logging.DEBUG if args.verbose else logging.INFO
    return WatchConfig(
        in_dir=Path(args.in_dir), out_dir=Path(args.output), settings=settings, workers=args.workers, poll=args.poll,
        settle=args.settle, journal=args.journal, job=args.job, quarantine_dir=args.quarantine,
        archive_dir=args.archive, profile_db=args.profile_db, status_file=args.status_file, rescan=args.rescan,
        timeout=args.timeout, max_attempts=args.max_attempts, max_crashes=args.max_crashes,
        retry_base=args.retry_base, retry_cap=args.retry_cap, retry_quarantined=args.retry_quarantined,
        min_free=int(args.min_free * 1e6), log_json=args.log_json, log_level=level)


def _check_settings(cfg) -> None:
    """Fail at start, not once per file, on settings that cannot work."""
    import importlib.util

    from vigproc.pipeline.processor import Settings

    settings = Settings(**cfg.settings)
    if settings.mode == "correct" and settings.profile_is_file:
        from vigproc.stores.profiles import import_profile

        import_profile(settings.profile)
    if settings.needs_store:
        from vigproc.stores.opening import open_profile_store

        store = open_profile_store(cfg.profile_db, write=settings.mode == "learn")
        if store is not None:
            store.close()
    if cfg.settings["mode"] == "check" and importlib.util.find_spec("vigproc.forensics.check") is None:
        log.warning("check mode needs vigproc.forensics.check, which this installation lacks: every file will be "
                    "quarantined with that reason (requeue them later with --retry-quarantined)")


def _print_status(st: dict[str, Any]) -> None:
    d = st.get("daemon") or {}
    c = st.get("journal_counts") or {}
    state = "running" if st["running"] else "not running"
    print(f"vigproc watch {st['in_dir']} -> {st['out_dir']}: {state}"
          + (f", pid {d.get('pid')}, {d.get('workers')} worker(s), {d.get('mode')} mode" if st["running"] and d else ""))
    if d:
        q = d.get("queue") or {}
        print(f"  status file updated {st.get('age_s', '?')} s ago (daemon state: {d.get('state')})")
        p = d.get("paused")
        if st["running"] and p:
            free = p.get("free_bytes")
            print(f"  PAUSED: {p.get('why')} since {p.get('since')}"
                  + (f" ({free / 1e6:.1f} MB free)" if isinstance(free, (int, float)) else "")
                  + f"; {p.get('files_waiting', 0)} file(s) waiting, next try in {p.get('next_try_s', 0):.0f} s "
                  "or as soon as space is freed; nothing is quarantined for it")
        if st["running"]:
            print(f"  queue {q.get('settling', 0) + q.get('ready', 0) + q.get('dispatched', 0)} "
                  f"(settling {q.get('settling', 0)}, ready {q.get('ready', 0)}, dispatched {q.get('dispatched', 0)}), "
                  f"running {len(d.get('running') or [])}, waiting to retry {q.get('retry_wait', 0)}, "
                  f"{d.get('files_per_min', 0)} files in the last minute")
        t = d.get("this_run") or {}
        print(f"  this run: {t.get('done', 0)} done, {t.get('quarantined', 0)} quarantined, "
              f"{t.get('failed_attempts', 0)} failed attempts, {t.get('retried', 0)} retries")
    if c:
        print(f"  journal: {c.get('done', 0)} done, {c.get('failed', 0)} failed (will retry), "
              f"{c.get('quarantined', 0)} quarantined, {c.get('pending', 0)} pending, {c.get('running', 0)} running")
    else:
        print("  no journal yet (never started with these folders)")
    for q in st.get("quarantined") or []:
        print(f"  quarantined: {q['path']!r}: {q['reason']}")


def cmd_watch(args: argparse.Namespace) -> int:
    from vigproc.frontends.daemon import Daemon, configure_logging, read_status

    cfg = _config(args)
    if args.status:
        st = read_status(cfg)
        if args.json:
            print(json.dumps(st, indent=1))
        else:
            _print_status(st)
        return 0 if st["running"] else 3  # LSB: 3 = not running
    configure_logging(cfg.log_json, cfg.log_level)
    cfg.validate()
    _check_settings(cfg)
    return Daemon(cfg).run()


def register(subparsers) -> None:
    from vigproc.frontends.commands._options import add_learn, add_processing, number
    from vigproc.pipeline.faults import DEFAULT_MIN_FREE

    sp = subparsers.add_parser(
        "watch", help="watch a folder: process every complete image dropped into it, exactly once",
        description="Watch IN_DIR and process every complete image that appears in it (correct, check or learn), "
                    "exactly once across restarts and crashes. Stop with SIGTERM or Ctrl-C (work in progress is "
                    "finished first).")
    sp.add_argument("in_dir", metavar="IN_DIR", help="folder to watch")
    sp.add_argument("-o", "--output", required=True, metavar="OUT_DIR", help="outputs and JSON sidecars")
    sp.add_argument("--mode", choices=("correct", "check", "learn"), default="correct",
                    help="correct (default), check or learn")
    sp.add_argument("--workers", type=number(1, 1024, integer=True), default=_default_workers(),
                    help=f"worker processes (default: half the cores, here {_default_workers()})")
    sp.add_argument("--poll", type=float, metavar="SECONDS",
                    help="poll the folder every SECONDS instead of native file events (network shares)")
    sp.add_argument("--settle", type=float, default=2.0, metavar="SECONDS",
                    help="a file is complete once its size and mtime were unchanged this long (default 2)")
    sp.add_argument("--journal", metavar="PATH", help="journal database (default OUT_DIR/.vigproc-watch.sqlite)")
    sp.add_argument("--job", help="job name in the journal (default: from the mode and the folders)")
    sp.add_argument("--quarantine", metavar="DIR", help="move files that fail for good here, with a .reason.json")
    sp.add_argument("--archive", metavar="DIR", help="move inputs here once done (mirroring their sub-folders)")
    sp.add_argument("--retry-quarantined", action="store_true", help="try quarantined files once more on start")
    add_processing(sp)
    add_learn(sp, "on in correct mode with --profile auto")
    sp.add_argument("--log-json", action="store_true", help="log JSON lines (one object per event) on stderr")
    sp.add_argument("--status", action="store_true",
                    help="print the status of the daemon on these folders and exit (0 running, 3 not running)")
    sp.add_argument("--json", action="store_true", help="with --status: JSON")
    sp.add_argument("--status-file", metavar="PATH", help="status file the daemon rewrites every second "
                    "(default OUT_DIR/.vigproc-watch-<tag>.status.json, <tag> a short hash of the job)")
    sp.add_argument("--rescan", type=float, default=300.0, metavar="SECONDS",
                    help="full rescan period, for events a file system did not deliver (default 300)")
    sp.add_argument("--timeout", type=float, default=900.0, metavar="SECONDS",
                    help="stop a worker stuck on one file this long (default 900)")
    sp.add_argument("--max-attempts", type=int, default=DEFAULT_MAX_ATTEMPTS, help="quarantine after this many transient failures")
    sp.add_argument("--max-crashes", type=int, default=DEFAULT_MAX_CRASHES,
                    help="quarantine a file that crashed or hung its worker this many times (a kill of the daemon "
                         "itself is not charged to the files in progress)")
    sp.add_argument("--retry-base", type=float, default=DEFAULT_RETRY_BASE, metavar="SECONDS", help="first retry delay (doubles)")
    sp.add_argument("--retry-cap", type=float, default=DEFAULT_RETRY_CAP, metavar="SECONDS", help="longest retry delay")
    sp.add_argument("--min-free", type=number(0, 1e9), default=DEFAULT_MIN_FREE / 1e6, metavar="MB",
                    help="a failure to write an output with less free space than this on the output disk is a full "
                         "disk: the daemon pauses (nothing quarantined) and resumes once the free space has grown "
                         "(default %(default).0f)")
    sp.set_defaults(fn=cmd_watch)


# ====================================================================== benchmark
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

    synthetic_frame = benchmark("io").synthetic_frame

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
    table1_model = benchmark("synthetic").table1_model

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


def register_bench(bench_subparsers) -> None:
    from vigproc.pipeline.processor import OUTPUT_FORMATS

    bp = bench_subparsers.add_parser("watch", help="watch-folder throughput with a trusted profile vs bare read+write")
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

    _register_bench_faults(bench_subparsers)


def cmd_bench_faults(args: argparse.Namespace) -> int:
    """``vigproc bench faults``: the daemon under a filling disk and kill -9 (benchmarks/faults.py)."""
    return benchmark("faults").cmd_bench_faults(args)


def _register_bench_faults(bench_subparsers) -> None:
    bp = bench_subparsers.add_parser(
        "faults", help="the watch daemon with its output on a small tmpfs that fills, is grown, and kill -9 (root)")
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
