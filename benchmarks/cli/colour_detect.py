"""``vigproc bench colour-detect``: how often one photograph's colour-cast report is
right, and how often a scene's colour is mistaken for a cast
(:mod:`benchmarks.colour_detect`)."""

from __future__ import annotations

import argparse
import math
import sys

from benchmarks.cli._common import Table, add_clean_bases
from vigproc.frontends.commands._options import number

#: Detection rates by the casts' corner dE2000, then on the clean bases and under
#: luminance-only fall-offs (false detections).
DETECTION_TABLE = Table((("frames", "<22"), ("n", ">7"), ("called cast", ">13"), ("rate", ">10"),
                         ("median dE est", ">15.2f")))


def colour_detect_arguments(bp: argparse.ArgumentParser) -> None:
    """``vigproc bench colour-detect``'s options."""
    add_clean_bases(bp)
    bp.add_argument("--targets", type=number(0.1, 100), nargs="+", default=None,
                    help="corner dE2000 of the rendered casts (default 1 2 3 4 5 7 10)")
    bp.add_argument("--directions", type=number(1, 64, integer=True), default=8,
                    help="hues of the casts, equally spaced in (log R/G, log B/G) (default %(default)s)")
    bp.add_argument("--theta-max", type=number(1, 70), nargs="+", default=None,
                    help="chief-ray angles at the corner, degrees (default 25 40)")
    bp.add_argument("--lenses", type=number(0, 100, integer=True), default=10,
                    help="lensfun lenses whose luminance-only fall-off must not be called a cast "
                         "(default %(default)s)")
    bp.add_argument("--frames", type=number(1, 100, integer=True), nargs="+", default=None,
                    help="also series of N frames of different bases under one cast, pooled as the profile "
                         "store pools a lens's frames (e.g. 1 3 5 9 15)")
    bp.add_argument("--series", type=number(10, 100000, integer=True), default=400,
                    help="series drawn per row, fold and length with --frames (default %(default)s)")
    bp.add_argument("--json", help="write the figures as JSON")
    bp.set_defaults(fn=cmd_bench_colour_detect)


def _pct(x: float) -> str:
    return "-" if not math.isfinite(x) else f"{100 * x:.1f} %"


def cmd_bench_colour_detect(args: argparse.Namespace) -> int:
    from benchmarks.cli._common import write_json_result
    from vigproc.pipeline.processor import output_file

    output_file(args.json)
    code, data = bench_detect_report(args)
    if data is not None:
        write_json_result(args.json, data)
    return code


def bench_detect_report(args: argparse.Namespace) -> tuple[int, dict | None]:
    """Run the detection benchmark and print its table: ``(exit code, figures)``; also
    ``vigproc bench colour --part detect`` (its options at their defaults there)."""
    from dataclasses import asdict

    import numpy as np

    from benchmarks import clean as C
    from benchmarks import colour_detect as D

    targets, directions = getattr(args, "targets", None), getattr(args, "directions", 8)
    theta_max, lenses = getattr(args, "theta_max", None), getattr(args, "lenses", 10)
    bases, names = C.load_clean_bases(args.images, args.min_long_side, args.limit, colour=True)
    colour = [(b, n) for b, n in zip(bases, names) if np.ptp(b[..., 0] - b[..., 1]) > 1e-6
              or np.ptp(b[..., 2] - b[..., 1]) > 1e-6]
    if len(colour) < 2:
        print(f"vigproc: bench colour-detect: {len(colour)} usable colour frames under {' '.join(args.images)}; "
              "need 2", file=sys.stderr)
        return 2, None
    bases, names = [b for b, _ in colour], [n for _, n in colour]
    casts = D.physical_casts(targets or D.TARGETS_DE, directions, theta_max or D.THETA_MAX)
    fields = []
    if lenses:
        lf, _ = C.lens_fields(lenses)
        fields = [(f.name, f.log_field) for f in lf]
    r = D.detection_rates(bases, casts, names=names, luminance_fields=fields,
                          frames=getattr(args, "frames", None) or (), series_count=getattr(args, "series", 400))
    print(f"colour-cast detection on {r.n_bases} clean colour bases (480x320, linear), casts cos^k_c(theta) at "
          f"{', '.join(f'{t:g}' for t in (theta_max or D.THETA_MAX))} deg corner angles x {directions} "
          f"hues; {r.ms_per_frame:.0f} ms/frame")
    DETECTION_TABLE.print_rows((f"cast {row.label}" if row.label.startswith("dE") else row.label, row.n, row.detected,
                                _pct(row.rate), row.median_de_est if math.isfinite(row.median_de_est) else "-")
                               for row in r.by_target + [r.clean, r.luminance_only])
    print(f"detected at dE >= 5: {_pct(r.rate_at_5)} (target >= 80 %); false detections: clean "
          f"{_pct(r.clean.rate)}, luminance only {_pct(r.luminance_only.rate)} (target <= 5 %)")
    if r.clean.hits:
        print("clean bases called cast: " + ", ".join(r.clean.hits))
    for f in r.split:
        # out of sample: the score threshold set on one half of the bases (<= 5 % clean called cast there)
        curve = ", ".join(f"{k} {_pct(v)}" for k, v in f["by_target"].items())
        print(f"threshold from the {f['calibrated_on']} bases (score >= {f['threshold']:.3g}; the detector's "
              f"own is 1), rates on the others: clean {_pct(f['clean'])}, luminance only "
              f"{_pct(f['luminance_only'])}; {curve}")
    for sr in r.series:
        fx = sr["fixed"]
        curve = ", ".join(f"{k} {_pct(v['detected'])}" for k, v in fx.items() if k.startswith("dE"))
        print(f"series of {sr['frames']} frames, the store's rule (score >= 1): clean {_pct(fx['clean']['detected'])}, "
              f"luminance only {_pct(fx['luminance_only']['detected'])}; {curve}; decisive: clean "
              f"{_pct(fx['clean']['decisive'])}, luminance only {_pct(fx['luminance_only']['decisive'])}, "
              + ", ".join(f"{k} {_pct(v['decisive'])}" for k, v in fx.items() if k.startswith("dE")))
        for f in sr["split"]:
            curve = ", ".join(f"{k} {_pct(v)}" for k, v in f["by_target"].items())
            print(f"series of {sr['frames']} frames, threshold from the {f['calibrated_on']} bases (score >= "
                  f"{f['threshold']:.3g}), rates on the others: clean {_pct(f['clean'])}, luminance only "
                  f"{_pct(f['luminance_only'])}; {curve}")
    data = asdict(r)
    for row in [data["clean"], data["luminance_only"]] + data["by_target"]:
        row.pop("sectors", None)  # arrays per frame: what the series pooled, not figures
    return 0, data
