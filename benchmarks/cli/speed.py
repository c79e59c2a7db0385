"""``vigproc bench`` for speed and resources: ``speed``, ``learn``, ``correct``, ``io``,
``throughput``, ``scaling`` and ``memory``."""

from __future__ import annotations

import argparse
import os
import sys
import time
from dataclasses import asdict
from importlib import resources
from pathlib import Path

from benchmarks.cli._common import Table, write_json_result
from vigproc.core.methods import METHODS
from vigproc.errors import VigprocError
from vigproc.frontends.commands._options import add_transfer, number
from vigproc.pipeline.processor import images_in as _images_in
#: bench speed --api's table (one row a case) and bench io's (one row a format).
API_SPEED_TABLE = Table((("case", "<10"), ("vigproc ms", ">12.1f"), ("peer ms", ">10.1f"), ("ratio", ">8.2f"),
                         ("net", ">8.2f"), ("vigproc CPU", ">13.1f"), ("peer CPU", ">10.1f"), ("ratio", ">8.2f"),
                         ("fall-backs", ">12"), ("off-centre", ">12")))
IO_TABLE = Table((("format", "<20"), ("MP", ">7.1f"), ("MB", ">9.1f"), ("read ms", ">10.1f"), ("bytes ms", ">10.1f"),
                  ("ratio", ">7.1f")))


def speed_arguments(bp: argparse.ArgumentParser) -> None:
    """``vigproc bench speed``'s options."""
    bp.add_argument("--images", help="folder of images (default: the bundled samples)")
    bp.add_argument("--limit", type=int, default=10, help="use at most this many images (default %(default)s)")
    bp.add_argument("--repeat", type=int, default=5, help="timing rounds (default %(default)s)")
    bp.add_argument("--methods", nargs="+", default=["ga", "default"], choices=list(METHODS),
                    help="estimators to time (default: ga default)")
    bp.add_argument("--api", action="store_true", help="time vigproc.estimate (colour, default method) on central "
                    "crops of --images's camera frames with a lensfun lens, Lyu's Table 1 setting 2 and no fall-off, "
                    "interleaved with the published peer")
    bp.add_argument("--peer", help="with --api: the built rgs_peer (scripts/build_rgs_peer.sh; default $VIGPROC_RGS_PEER)")
    add_transfer(bp)
    bp.set_defaults(fn=cmd_bench_speed)


def learn_arguments(bp: argparse.ArgumentParser) -> None:
    """``vigproc bench learn``'s options."""
    bp.add_argument("--images", help="folder of photographs (default: the bundled samples)")
    bp.add_argument("--limit", type=int, default=60, help="use at most this many images (default %(default)s)")
    bp.add_argument("--stored", type=int, default=50, help="frames already in the profile (default %(default)s)")
    bp.add_argument("--rounds", type=int, default=5, help="timing rounds (default %(default)s)")
    bp.add_argument("--json", help="write the figures as JSON")
    add_transfer(bp)
    bp.set_defaults(fn=cmd_bench_learn)


def correct_arguments(bp: argparse.ArgumentParser) -> None:
    """``vigproc bench correct``'s options."""
    bp.add_argument("--width", type=int, default=6000, help="frame width in px (default %(default)s)")
    bp.add_argument("--height", type=int, default=4000, help="frame height in px (default %(default)s)")
    bp.add_argument("--repeat", type=int, default=15, help="timing rounds (default %(default)s)")
    bp.set_defaults(fn=cmd_bench_correct)


def io_arguments(bp: argparse.ArgumentParser) -> None:
    """``vigproc bench io``'s options."""
    bp.add_argument("--width", type=int, default=6000, help="frame width in px (default %(default)s)")
    bp.add_argument("--height", type=int, default=4000, help="frame height in px (default %(default)s)")
    bp.add_argument("--repeat", type=int, default=3, help="timing rounds (default %(default)s)")
    bp.add_argument("--raw", help="folder of RAW files to time (full and half size)")
    bp.add_argument("--exif", help="folder of images to time EXIF reading on")
    bp.set_defaults(fn=cmd_bench_io)


def throughput_arguments(bp: argparse.ArgumentParser) -> None:
    """``vigproc bench throughput``'s options."""
    bp.add_argument("--images", help="folder of JPEG photographs")
    bp.add_argument("--raw", metavar="DIR", help="folder of camera RAW files: vigproc correct beside rawpy's "
                    "development and the same TIFF written")
    bp.add_argument("--min-mp", type=float, default=0.75, help="smallest photograph, megapixels (default %(default)s)")
    bp.add_argument("--limit", type=int, help="use at most this many photographs")
    bp.add_argument("--rounds", type=int, default=3, help="timing rounds, interleaved (default %(default)s)")
    bp.add_argument("--no-darktable", action="store_true", help="leave darktable-cli out")
    bp.add_argument("--baseline", metavar="TREE", help="also time vigproc correct from this source tree "
                    "(another checkout's root): before and after in one run")
    bp.add_argument("--json", help="write the figures as JSON")
    bp.set_defaults(fn=cmd_bench_throughput)


def scaling_arguments(bp: argparse.ArgumentParser) -> None:
    """``vigproc bench scaling``'s options."""
    bp.add_argument("--images", required=True, help="folder of JPEG photographs")
    bp.add_argument("--min-mp", type=float, default=0.75, help="smallest photograph, megapixels (default %(default)s)")
    bp.add_argument("--limit", type=number(1, 100_000, integer=True), help="use at most this many photographs")
    bp.add_argument("--workers", type=number(1, 64, integer=True), nargs="+", default=[1, 2],
                    help="worker counts (default 1 2)")
    bp.add_argument("--frontends", nargs="+", choices=["watch", "batch"], default=["watch", "batch"],
                    help="what to time (default both)")
    bp.add_argument("--rounds", type=number(1, 100, integer=True), default=2,
                    help="timing rounds, interleaved (default %(default)s)")
    bp.add_argument("--copies", type=number(1, 1000, integer=True), default=1,
                    help="stage each photograph this many times, under distinct names and bytes (more work per "
                         "round, so the steady state shows; default %(default)s)")
    bp.add_argument("--tmp", help="folder for the temporary files (default: the system's)")
    bp.add_argument("--json", help="write the figures as JSON")
    bp.set_defaults(fn=cmd_bench_scaling)


def memory_arguments(bp: argparse.ArgumentParser) -> None:
    """``vigproc bench memory``'s options."""
    bp.add_argument("--width", type=number(64, 100_000, integer=True), default=6000,
                    help="frame width in px (default %(default)s)")
    bp.add_argument("--height", type=number(64, 100_000, integer=True), default=4000,
                    help="frame height in px (default %(default)s)")
    bp.add_argument("--tmp", help="folder for the temporary files (default: the system's)")
    bp.add_argument("--json", help="write the figures as JSON")
    bp.set_defaults(fn=cmd_bench_memory)


def cmd_bench_speed(args: argparse.Namespace) -> int:
    """Per-image estimation time on 480×320 protocol frames (Table 1 setting 2)."""
    import numpy as np

    from vigproc.core.estimate import estimate
    from vigproc.io.images import read_image

    from benchmarks.synthetic import protocol_image, table1_model

    if args.api:
        return _bench_speed_api(args)
    folder = Path(args.images) if args.images else Path(str(resources.files("vigproc.data").joinpath("samples")))
    files = _images_in(folder, args.limit)
    phi = table1_model(2).field()
    frames = [protocol_image(read_image(f, transfer=args.input_transfer)[0]) * phi for f in files]
    print(f"{len(frames)} frames of 480x320 from {folder}, {args.repeat} rounds, one thread")
    for method in args.methods:
        estimate(frames[0], method, channel_axis=None)  # JIT warm-up
        ts = []
        for _ in range(args.repeat):
            for fr in frames:
                t0 = time.perf_counter()
                estimate(fr, method, channel_axis=None)
                ts.append(time.perf_counter() - t0)
        print(f"{method:<14} median {1000 * np.median(ts):8.2f} ms  p90 {1000 * np.percentile(ts, 90):8.2f} ms")
    return 0


def _bench_speed_api(args: argparse.Namespace) -> int:
    """``bench speed --api``: vigproc.estimate on clean-protocol crops beside the published peer."""
    from benchmarks.api_speed import api_speed
    from benchmarks.clean import load_clean_bases
    from benchmarks.peers import PEER_ENV, published_rgs

    if not args.images:
        print("vigproc: bench speed --api: give --images (full-size camera frames, e.g. ../shared/data/jpeg_exif)",
              file=sys.stderr)
        return 2
    bases, _ = load_clean_bases([args.images], limit=args.limit, colour=True)
    if not bases:
        print(f"vigproc: bench speed --api: no frame of at least 1000 px in {args.images}", file=sys.stderr)
        return 2
    exe = args.peer or os.environ.get(PEER_ENV)
    r = api_speed(bases, published_rgs(exe) if exe else None, rounds=args.repeat)
    print(f"vigproc.estimate on {r.n_frames} central crops (480x320, colour, linear) of {args.images}, "
          f"{r.rounds} rounds" + (f", interleaved with the published peer {exe}" if exe else " (no peer: --peer or "
                                  f"${PEER_ENV})"))
    if exe:
        print(f"peer floor (process start and file I/O, a 16x16 frame): {r.peer_floor_ms:.1f} ms, "
              f"{r.peer_floor_cpu_ms:.1f} ms CPU")
    API_SPEED_TABLE.print_rows((c.case, c.vigproc_ms, c.peer_ms, c.ratio, c.ratio_net, c.vigproc_cpu_ms, c.peer_cpu_ms,
                                c.ratio_cpu, c.fallbacks, c.off_centre) for c in r.cases)
    print("medians (ms); ratio: vigproc / peer; net: vigproc / (peer - its floor); CPU: process time (the peer's "
          "child process by getrusage), first-round fall-backs and off-centre fits of the frames")
    return 0


def cmd_bench_learn(args: argparse.Namespace) -> int:
    """Learning one more frame into a profile, warm and in a new process."""
    import numpy as np

    from vigproc.io.protocol import read_protocol_images, vignetted
    from vigproc.stores.lensfun import diverse_lenses, pa_field

    from benchmarks.learn import learn_speed

    folder = Path(args.images) if args.images else Path(str(resources.files("vigproc.data").joinpath("samples")))
    ims = read_protocol_images(_images_in(folder, args.limit), args.input_transfer, colour=True)
    if not ims:
        print(f"vigproc: bench learn: no readable images in {folder}", file=sys.stderr)
        return 2
    lens, pa = diverse_lenses(1)[0]
    log_field = np.log(pa_field(ims[0].shape[:2], pa.k1, pa.k2, pa.k3))
    frames = [vignetted(im, log_field) for im in ims]
    r = learn_speed(frames, stored=args.stored, rounds=args.rounds)
    print(f"{len(ims)} photographs from {folder} x {lens.maker} {lens.model} (lensfun); a profile of "
          f"{r.stored} frames learns one more, {r.rounds} rounds")
    print(f"{'warm process':<34} median {r.warm_ms:8.1f} ms")
    print(f"{'new process, the learn':<34} median {r.new_process_learn_ms:8.1f} ms  (largest "
          f"{r.new_process_learn_ms_max:.1f} ms)")
    print(f"{'new process, its imports':<34} median {r.new_process_import_ms:8.1f} ms")
    write_json_result(args.json, asdict(r))
    return 0


def cmd_bench_correct(args: argparse.Namespace) -> int:
    """Full-resolution correction against a plain copy and a numpy divide, in one run."""
    import numpy as np

    import numba

    from vigproc.core.correct import correct, gain_step
    from vigproc.stores.lensfun import diverse_lenses
    from vigproc.stores.lensfun_io import kw_from_pa

    from benchmarks.synthetic import table1_model

    h, w = args.height, args.width
    img = np.random.default_rng(0).random((h, w, 3), dtype=np.float32)
    out = np.empty_like(img)
    lens, pa = diverse_lenses(1)[0]
    fields = [
        (f"real lens ({lens.maker} {lens.model}, lensfun)", kw_from_pa(pa.k1, pa.k2, pa.k3, w, h)),
        ("Lyu Table 1 setting 2 (extreme)", table1_model(2).rescale(480, round(480 * h / w))),
    ]
    print(f"{w}x{h} RGB float32 ({img.nbytes / 1e6:.0f} MB), median of {args.repeat} after warm-up, "
          f"{numba.get_num_threads()} threads")

    def timed(fn) -> float:
        fn()
        ts = []
        for _ in range(args.repeat):
            t0 = time.perf_counter()
            fn()
            ts.append(time.perf_counter() - t0)
        return 1000 * float(np.median(ts))

    base = timed(lambda: np.copyto(out, img))
    print(f"{'copy (memory floor)':<50}{base:>9.1f} ms {1.0:>6.2f}x copy")
    for label, model in fields:
        field = model.field((h, w)).astype(np.float32)
        rows = [
            ("numpy divide by precomputed field", lambda: np.divide(img, field[..., None], out=out)),
            ("vigproc.correct, field on the fly", lambda: correct(img, model, out=out)),
            ("vigproc.correct, new output array", lambda: correct(img, model)),
        ]
        print(f"{label}: gain step {gain_step(model.rescale(w, h), w, h)} px")
        for name, fn in rows:
            ms = timed(fn)
            print(f"  {name:<48}{ms:>9.1f} ms {ms / base:>6.2f}x copy")
    return 0


def cmd_bench_io(args: argparse.Namespace) -> int:
    """Frame read times per format (vs reading the bytes) and EXIF per file in batch."""
    from benchmarks.io import bench_exif, bench_formats, bench_raw

    print(f"reading a {args.width}x{args.height} RGB frame (best of {args.repeat}); 'bytes' = reading the file's bytes")
    print(IO_TABLE.header())
    rows = bench_formats(args.height, args.width, args.repeat)
    if args.raw:
        rows += bench_raw(sorted(p for p in Path(args.raw).rglob("*") if p.is_file()), args.repeat)
    for r in rows:
        print(IO_TABLE.row(r.label, r.megapixels, r.megabytes, r.read_ms, r.bytes_ms, r.read_ms / max(r.bytes_ms, 1e-9)))
    if args.exif:
        files = _images_in(Path(args.exif))
        e = bench_exif(files, repeat=args.repeat)
        print(f"EXIF lens key, {int(e['n_files'])} files: {e['batch_ms_per_file']:.1f} ms/file in one exiftool "
              f"process ({e['batch_total_ms_per_file']:.1f} with its {e['startup_ms']:.0f} ms start-up), "
              f"{e['per_process_ms_per_file']:.1f} ms/file with a process per file ({e['speedup']:.1f}x)")
    return 0


def cmd_bench_throughput(args: argparse.Namespace) -> int:
    """``vigproc correct`` on full-size photographs beside the floor (decode + encode +
    one exiftool batch) and darktable-cli, in one run (:mod:`benchmarks.throughput`)."""
    from benchmarks import throughput as T

    if not (args.images or args.raw):
        raise VigprocError("bench throughput needs --images DIR or --raw DIR")
    for raw, folder in ((False, args.images), (True, args.raw)):
        if folder is None:
            continue
        photos, skipped = (T.select_raws(Path(folder), args.limit) if raw else
                           T.select_photos(Path(folder), args.min_mp, args.limit))
        r = T.run_throughput(photos, rounds=args.rounds, darktable=not args.no_darktable, skipped=skipped,
                             baseline=args.baseline, raw=raw)
        print(("RAW: " if raw else "") + "\n".join(T.format_result(r)))
        write_json_result(args.json if not raw else (args.json and args.json + ".raw.json"), asdict(r))
    return 0


def cmd_bench_scaling(args: argparse.Namespace) -> int:
    """``vigproc watch`` and ``vigproc batch`` on full-size photographs with 1 and 2
    workers, interleaved (:mod:`benchmarks.scaling`)."""
    from benchmarks import scaling as S
    from benchmarks import throughput as T

    photos, _ = T.select_photos(Path(args.images), args.min_mp, args.limit)
    r = S.run_scaling(photos, workers=args.workers, rounds=args.rounds, frontends=args.frontends,
                      workdir=Path(args.tmp) if args.tmp else None, copies=args.copies)
    print("\n".join(S.format_result(r)))
    write_json_result(args.json, asdict(r))
    return 0


def cmd_bench_memory(args: argparse.Namespace) -> int:
    """Peak memory of one worker (``vigproc correct``) on a 24 MP JPEG and 16-bit TIFF
    (:mod:`benchmarks.memory`)."""
    from benchmarks import memory as M

    r = M.run_memory(args.width, args.height, workdir=Path(args.tmp) if args.tmp else None)
    print("\n".join(M.format_result(r)))
    write_json_result(args.json, asdict(r))
    return 0
