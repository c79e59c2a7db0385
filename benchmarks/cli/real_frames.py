"""``vigproc bench real-frames``: harm of the default correction on real full frames
(:mod:`benchmarks.real_frames`), with the harm rules off and on; the error against
lensfun's field where lensfun calibrated the frame's lens, one frame and a series
through the profile store (:mod:`benchmarks.real_frames_lensfun`)."""

from __future__ import annotations

import argparse
import math

from vigproc.frontends.commands._options import number


def real_frames_arguments(bp: argparse.ArgumentParser) -> None:
    """``vigproc bench real-frames``'s options."""
    bp.add_argument("--images", nargs="+", action="extend", metavar="DIR",
                    help="folders of camera JPEGs (repeatable; default ../shared/data/jpeg_exif)")
    bp.add_argument("--min-long-side", type=number(64, 10**6, integer=True), default=1000,
                    help="frames whose long side is shorter are not used (default %(default)s)")
    bp.add_argument("--limit", type=number(1, 10**6, integer=True), help="use at most this many frames")
    bp.add_argument("--rules", choices=["both", "off", "on"], default="both",
                    help="run with the harm rules off (as before them), on, or both (default)")
    bp.add_argument("--no-harm", action="store_true", help="skip the harm counts (parts b and c)")
    bp.add_argument("--no-lensfun", action="store_true",
                    help="skip the error against lensfun's field on the frames whose lens it calibrated (part a)")
    bp.add_argument("--shipped-family", action="store_true",
                    help="part (a): the default estimate's prior from the shipped lens family, which holds "
                         "the measured lenses' own calibrations (default: lensfun's family without them)")
    bp.add_argument("--ambiguity-shrink", nargs="?", const="scene", choices=["scene", "scene3", "all"],
                    help="part (a): score the experiment of vigproc.core.ambiguity (the fit shrunk toward the "
                         "EXIF population by its half fits' disagreement: 'scene', less the fit's own noise, "
                         "the default; 'scene3', less three times it; 'all', the whole disagreement) instead of the default "
                         "estimate")
    bp.add_argument("--lensfun-series", type=number(0, 1000, integer=True), default=0, metavar="N",
                    help="also a series of N frames per lensfun-known lens setting learned through a profile "
                         "store: vignetting-free bases x lensfun's field (default 0: none)")
    bp.add_argument("--series-images", nargs="+", action="extend", metavar="DIR",
                    help="folders of the series' vignetting-free bases (full-size camera frames, their central "
                         "40 %%; default ../shared/data/jpeg_exif)")
    bp.add_argument("--series-long-side", type=number(64, 8000, integer=True), default=1000,
                    help="long side of the series' frames in pixels (default %(default)s)")
    bp.add_argument("--series-min-long-side", type=number(64, 10**6, integer=True), default=2000,
                    help="bases whose long side is shorter are not used (default %(default)s)")
    bp.add_argument("--json", help="write the figures as JSON")
    bp.set_defaults(fn=cmd_bench_real_frames)


def _fmt(x: float, spec: str) -> str:
    return "-" if not math.isfinite(x) else format(x, spec)


def _print_lensfun(s) -> None:
    print(f"\nlensfun-known lenses: {s.frames} frames, the truth holds on {s.truth_frames}")
    print(f"{'file':<30} {'lens':<40} {'mm':>4} {'f/':>4} {'rho':>4} {'truth':>5} {'appl.':>5} {'cand.':>5} "
          f"{'err':>6} {'cand':>6} {'none':>6}  rule / why")
    for r in s.rows:
        print(f"{r.file[:30]:<30} {r.lens[:40]:<40} {r.focal_mm:4.0f} {r.fnumber:4.1f} {r.corner_rho:4.2f} "
              f"{r.truth_corner_ev:5.2f} {r.applied_corner_ev:5.2f} {r.candidate_corner_ev:5.2f} {r.error_ev:6.3f} "
              f"{r.candidate_error_ev:6.3f} {r.uncorrected_ev:6.3f}  {r.rule or '-'}; "
              f"{'truth holds' if r.truth_holds else 'NO TRUTH'}: {r.why}")
    print(f"median over the truth frames, EV: applied {_fmt(s.median_error_ev, '.3f')}, candidate fit "
          f"{_fmt(s.median_candidate_ev, '.3f')}, uncorrected {_fmt(s.median_uncorrected_ev, '.3f')}")


def _print_series(s) -> None:
    counts = sorted(s.median_ev)
    print(f"\nseries through the store: {len(s.rows)} lens settings x {s.n} frames ({s.bases} bases, "
          f"{s.long_side} px), trusted {s.trusted}")
    print(f"{'lens':<40} {'mm':>4} {'f/':>4} {'truth':>5} {'single':>6} "
          + " ".join(f"{'n=' + str(c):>6}" for c in counts) + f" {'trust@':>6} {'spread':>6} {'alone':>6}")
    for r in s.rows:
        print(f"{r.lens[:40]:<40} {r.focal_mm:4.0f} {r.fnumber:4.1f} {r.truth_corner_ev:5.2f} "
              f"{r.single_median_ev:6.3f} " + " ".join(f"{_fmt(r.profile_ev.get(c, math.nan), '6.3f'):>6}"
                                                       for c in counts)
              + f" {r.trusted_at if r.trusted_at is not None else '-':>6} "
              f"{_fmt(r.corner_spread_after_trust_ev, '6.3f'):>6} {_fmt(r.single_corner_spread_ev, '6.3f'):>6}")
    print(f"median, EV: single frame {_fmt(s.median_single_ev, '.3f')}; profile "
          + ", ".join(f"after {c}: {s.median_ev[c]:.3f}" for c in counts))


def cmd_bench_real_frames(args: argparse.Namespace) -> int:
    from benchmarks.cli._common import write_json_result

    from benchmarks import real_frames_lensfun as rfl
    from benchmarks.real_frames import as_dict, full_frames, run

    images = args.images or ["../shared/data/jpeg_exif"]
    files = full_frames(images, args.min_long_side, args.limit)
    if not files:
        print(f"vigproc: bench real-frames: no JPEG of {args.min_long_side} px or more under {' '.join(images)}")
        return 2
    result: dict = {}
    if not args.no_lensfun or args.lensfun_series:
        found, _other = rfl.lensfun_frames(files)
        if not args.no_lensfun:
            lf = rfl.run_lensfun([p for p, *_ in found], family=None if args.shipped_family else "exclude",
                                 shrink=args.ambiguity_shrink)
            _print_lensfun(lf)
            result["lensfun"] = rfl.as_dict(lf)
        if args.lensfun_series and found:
            bases = rfl.series_bases(args.series_images or ["../shared/data/jpeg_exif"], args.series_min_long_side)
            if not bases:
                print("vigproc: bench real-frames: no base of the series found")
                return 2
            se = rfl.run_series(found, bases, n=args.lensfun_series, long_side=args.series_long_side,
                                counts=sorted({1, 5, 10, args.lensfun_series}))
            _print_series(se)
            result["series"] = rfl.as_dict(se)
    if args.no_harm:
        write_json_result(args.json, result)
        return 0
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
    result.update({("on" if c.rules else "off"): as_dict(c) for c in runs})
    write_json_result(args.json, result)
    return 0
