"""``vigproc bench learn-series``: a series of one lens setting through ``vigproc batch``,
learning as it goes (:mod:`benchmarks.learn_series`): when the profile is trusted, each
frame's field error before and after, and whether the frames after trust share one field."""

from __future__ import annotations

import argparse
import dataclasses
import math

from benchmarks.cli._common import add_clean_bases
from vigproc.frontends.commands._options import number


def learn_series_arguments(bp: argparse.ArgumentParser) -> None:
    """``vigproc bench learn-series``'s options."""
    add_clean_bases(bp)
    bp.add_argument("--frames", type=number(3, 1000, integer=True), default=16,
                    help="frames in each series (default %(default)s)")
    bp.add_argument("--series", type=number(1, 20, integer=True), default=2,
                    help="series of each lens, a day apart, each its own batch run into one store "
                         "(default %(default)s)")
    bp.add_argument("--lenses", type=number(1, 20, integer=True), default=1,
                    help="series of this many lensfun lenses, one after the other (default %(default)s)")
    bp.add_argument("--workers", type=number(1, 64, integer=True), default=2,
                    help="batch workers (default %(default)s)")
    bp.add_argument("--tmp", help="folder for the temporary files (default: the system's)")
    bp.add_argument("--frames-table", action="store_true", help="also print every frame's row")
    bp.add_argument("--json", help="write the figures as JSON")
    bp.set_defaults(fn=cmd_bench_learn_series)


def _fmt(x: float, spec: str = ".3f") -> str:
    return "-" if x is None or not math.isfinite(x) else format(x, spec)


def cmd_bench_learn_series(args: argparse.Namespace) -> int:
    import os
    from pathlib import Path

    from benchmarks.cli._common import write_json_result
    from vigproc.stores.lensfun import diverse_lenses

    from benchmarks.clean import lens_fields, load_clean_bases
    from benchmarks.learn_series import run_series

    bases, _ = load_clean_bases(args.images, args.min_long_side, args.limit, colour=not args.grey)
    need = args.frames * args.series
    if len(bases) < need:
        print(f"only {len(bases)} bases under {args.images}; {args.series} series of {args.frames} need {need}")
        return 1
    fields, _ = lens_fields()
    lenses = diverse_lenses(20)
    results = []
    print(f"learn as you go: {args.series} series of {args.frames} frames of one lens setting, a day apart, each "
          f"through 'vigproc batch --mode correct --workers {args.workers}' into one store "
          f"(load {os.getloadavg()[0]:.1f})")
    print("| lens | series | trusted at frame | before trust: applied / alone median EV (profile chosen) | "
          "stored profile: median / max EV | revisions applied after trust | revision ids / field changes | "
          "spread EV: all / within an id | profile frames after | uncorrected EV | s |")
    print("|---|---|---|---|---|---|---|---|---|---|---|")
    for k in range(args.lenses):
        fld = fields[k]
        lens, pa = lenses[k]
        rot = [bases[(k * need + i) % len(bases)] for i in range(need)]
        rs = run_series(rot, fld.log_field, lens=f"{lens.maker} {lens.model}", focal_mm=pa.focal,
                        fnumber=pa.aperture, focal35=fld.focal35, workers=args.workers,
                        tmp=Path(args.tmp) if args.tmp else None, series=args.series)
        results.extend(rs)
        for r in rs:
            print(f"| {r.lens} | {r.series} | {r.trusted_at or '-'} | {_fmt(r.before_median_ev)} / "
                  f"{_fmt(r.before_alone_median_ev)} ({r.evidence_frames}) | {_fmt(r.after_median_ev)} / "
                  f"{_fmt(r.after_max_ev)} | {', '.join(map(str, r.revisions)) or '-'} | "
                  f"{r.revision_ids} / {r.switches} | {_fmt(r.revision_spread_ev, '.4f')} / "
                  f"{_fmt(r.same_revision_spread_ev, '.4f')} | {r.profile_frames or '-'} | "
                  f"{_fmt(r.uncorrected_ev)} | {r.wall_s:.0f} |")
            if args.frames_table:
                for x in r.rows:
                    print(f"    {x.name}: pooled as {x.pooled_as}, trusted {x.trusted_after}, {x.source}"
                          f"{f' (revision {x.revision}, {x.revision_id})' if x.revision else ''}, error "
                          f"{x.error_ev:.3f} EV (alone {x.alone_ev:.3f}), {x.seconds:.1f} s")
    _before_trust(results)
    write_json_result(args.json, [dataclasses.asdict(r) for r in results])
    return 0


def _before_trust(results) -> None:
    """Error against the frame's place in its series before trust (pooling order), over
    every series that had frames before trust: the field applied and the frame's own."""
    import numpy as np

    by: dict[int, list] = {}
    for r in results:
        for x in r.rows:
            if x.source != "stored-profile" and x.pooled_as is not None:
                by.setdefault(x.pooled_as, []).append(x)
    if not by:
        return
    print("\nbefore trust, by frame (pooling order; median over the series):")
    print("| frame | series | applied EV | alone EV | profile chosen |")
    print("|---|---|---|---|---|")
    for n in sorted(by):
        xs = by[n]
        print(f"| {n} | {len(xs)} | {np.median([x.error_ev for x in xs]):.3f} | "
              f"{np.median([x.alone_ev for x in xs]):.3f} | {sum(x.source == 'profile-evidence' for x in xs)} |")
