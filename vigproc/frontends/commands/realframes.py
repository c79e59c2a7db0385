"""``vigproc bench real-frames``: harm of the default correction on real full frames
(:mod:`vigproc.bench.real_frames`), with the harm rules off and on."""

from __future__ import annotations

import argparse
import math


def register(subparsers) -> None:
    """No command of its own: a benchmark only (:func:`register_bench`)."""


def register_bench(bsub) -> None:
    from vigproc.frontends.commands._options import number

    bp = bsub.add_parser("real-frames", help="harm of the default correction on real full-size camera JPEGs: "
                         "brighter corners, fall-offs beyond real lenses, low confidence, pixels pushed past "
                         "white, in-camera corrected frames; the harm rules off and on")
    bp.add_argument("--images", nargs="+", default=["../shared/data/jpeg_exif"],
                    help="folders of camera JPEGs (default %(default)s)")
    bp.add_argument("--min-long-side", type=number(64, 10**6, integer=True), default=1000,
                    help="frames whose long side is shorter are not used (default %(default)s)")
    bp.add_argument("--limit", type=number(1, 10**6, integer=True), help="use at most this many frames")
    bp.add_argument("--rules", choices=["both", "off", "on"], default="both",
                    help="run with the harm rules off (as before them), on, or both (default)")
    bp.add_argument("--json", help="write the figures as JSON")
    bp.set_defaults(fn=cmd_bench_real_frames)


def _fmt(x: float, spec: str) -> str:
    return "-" if not math.isfinite(x) else format(x, spec)


def cmd_bench_real_frames(args: argparse.Namespace) -> int:
    from vigproc.bench.real_frames import as_dict, full_frames, run
    from vigproc.frontends.commands._options import write_json_result

    files = full_frames(args.images, args.min_long_side, args.limit)
    if not files:
        print(f"vigproc: bench real-frames: no JPEG of {args.min_long_side} px or more under {' '.join(args.images)}")
        return 2
    runs = [run(files, rules_on=on) for on in {"both": (False, True), "off": (False,), "on": (True,)}[args.rules]]
    for c in runs:
        print(f"\nrules {'on' if c.rules else 'off'}: {c.frames} frames")
        print(f"{'file':<34} {'camera':<34} {'in-camera':<24} {'applied':<7} {'rule':<18} {'conf':>5} "
              f"{'bright':>6} {'removed':>7} {'bound':>5} {'white%':>6}")
        for r in c.rows:
            print(f"{r.file[:34]:<34} {r.camera[:34]:<34} {(r.in_camera or '-')[:24]:<24} "
                  f"{'yes' if r.applied else 'no':<7} {(r.rule or '-')[:18]:<18} {_fmt(r.confidence, '5.2f'):>5} "
                  f"{r.brightest_ev:+6.2f} {r.removed_ev:7.2f} {r.population_ev:5.2f} {100 * r.new_white:6.2f}")
    print(f"\n{'':<44}" + "".join(f"{'rules ' + ('on' if c.rules else 'off'):>12}" for c in runs))
    lines = [("frames", lambda c: str(c.frames)), ("fields applied", lambda c: str(c.applied)),
             ("applied with brighter corners", lambda c: str(c.brighter_corners)),
             ("applied beyond real lenses", lambda c: str(c.beyond_population)),
             ("applied below confidence 0.5", lambda c: str(c.below_confidence)),
             ("more than 1 EV removed at a corner", lambda c: str(c.over_1ev)),
             ("pixels newly past white, max %", lambda c: f"{100 * c.new_white_max:.2f}"),
             ("pixels newly past white, median %", lambda c: f"{100 * c.new_white_median:.2f}"),
             ("in-camera corrected frames", lambda c: str(c.in_camera_frames)),
             ("  EV removed there, median", lambda c: _fmt(c.in_camera_removed_median, ".3f")),
             ("  EV removed there, max", lambda c: _fmt(c.in_camera_removed_max, ".3f"))]
    for name, f in lines:
        print(f"{name:<44}" + "".join(f"{f(c):>12}" for c in runs))
    write_json_result(args.json, {("on" if c.rules else "off"): as_dict(c) for c in runs})
    return 0
