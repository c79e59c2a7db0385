"""``vigproc bench forensics`` (lens identification, Lyu 2010 Fig. 6, and the consistency check) and
``vigproc bench forensics-clean`` (the same on the clean protocol)."""

from __future__ import annotations

import argparse
import sys
import time

from benchmarks.cli._common import Table, add_clean_bases, write_json_result
from vigproc.frontends.commands._options import add_transfer, number
from vigproc.frontends.commands.forensics import _forensic_method, _protocol_images


def forensics_arguments(bp: argparse.ArgumentParser) -> None:
    """``vigproc bench forensics``'s options."""
    bp.add_argument("--images", nargs="+", required=True, help="folders of photographs (not the prior's)")
    bp.add_argument("--lenses", type=int, default=8, help="lensfun lenses (classes; default %(default)s)")
    bp.add_argument("--frames", type=int, default=5, help="frames per multi-frame decision")
    bp.add_argument("--alpha", type=float, default=0.05,
                    help="false-alarm probability of the check (default %(default)s)")
    bp.add_argument("--seed", type=int, default=0, help="seed of the train/test split")
    bp.add_argument("--limit", type=int, help="photographs per folder")
    bp.add_argument("--json", help="write the figures to this file")
    add_transfer(bp)
    bp.set_defaults(fn=cmd_bench_forensics)

#: bench forensics' lens identification table (accuracies in %).
IDENTIFICATION_TABLE = Table((("classifier", "<48"), ("frames", ">7"), ("tests", ">7"), ("lens+ap.", ">10.1f"),
                              ("per-class", ">11.1f"), ("lens", ">7.1f")))


def forensics_clean_arguments(bp: argparse.ArgumentParser) -> None:
    """``vigproc bench forensics-clean``'s options."""
    add_clean_bases(bp)
    bp.add_argument("--alpha", type=number(0.0, 0.5, open_lo=True), default=0.01,
                    help="false-alarm probability of the check (default %(default)s)")
    bp.add_argument("--frames", type=number(2, 20, integer=True), default=5,
                    help="frames per multi-frame decision (default %(default)s)")
    bp.add_argument("--seed", type=int, default=0, help="seed of the multi-frame groups")
    bp.add_argument("--folds", type=number(2, 100, integer=True), default=2,
                    help="the bases are split into this many folds; each is tested against a calibration "
                         "of the others (default %(default)s: even/odd halves)")
    bp.add_argument("--calibrate", metavar="FILE",
                    help="also write the calibration 'vigproc check' ships (every base, the shipped family)")
    bp.add_argument("--json", help="write the figures to this file")
    bp.set_defaults(fn=cmd_bench_forensics_clean)


def cmd_bench_forensics(args: argparse.Namespace) -> int:
    from dataclasses import asdict

    import numpy as np

    from vigproc.core.estimate import estimate
    from vigproc.forensics.identify import format_confusion
    from vigproc.pipeline.processor import output_file

    from benchmarks import forensics as B

    output_file(args.json)
    ims = _protocol_images(args.images, args.limit, args.input_transfer)
    fn = lambda v: estimate(v, _forensic_method("default"), channel_axis=None)  # noqa: E731
    fn(ims[0])  # JIT warm-up
    t0 = time.perf_counter()
    from vigproc.core.robust import estimate_robust_joint

    r = B.run(ims, fn, n_lenses=args.lenses, frames=args.frames, seed=args.seed, alpha=args.alpha, progress=print,
              joint=estimate_robust_joint)
    print(f"\nforensics benchmark: {len(r.classes)} classes ({args.lenses} lensfun lenses x 2 apertures), "
          f"{r.n_train_images} training / {r.n_test_images} test photographs from {', '.join(args.images)} "
          f"(480x320, linearised); {time.perf_counter() - t0:.0f} s")
    print("\nclasses:")
    for i, c in enumerate(r.classes):
        print(f"  [{i + 1}] {c['label']} ({c['focal']:g} mm)")
    print("\nlens identification (accuracy in %; chance: "
          f"{100 / len(r.classes):.1f} for lens+aperture, {200 / len(r.classes):.1f} for the lens)")
    IDENTIFICATION_TABLE.print_rows((row.classifier, row.n_frames, row.n_tests, 100 * row.accuracy,
                                     100 * row.mean_class_accuracy, 100 * row.lens_accuracy)
                                    for row in r.identification)
    for row in r.identification:
        if row.confusion:
            print(f"\nconfusion matrix, {row.classifier}, one frame:")
            print(format_confusion(np.array(row.confusion), [f"{c['label']}" for c in r.classes], width=4))
    print(f"\nconsistency check (calibrated on {r.calibration_frames} training frames; inconsistent when the "
          f"false-alarm probability < {r.alpha:g}; rates are of frames with a verdict)")
    hdr = (f"{'case':<52}{'frames':>7}{'null':>6}{'alt':>7}{'AUC':>7}{'AUC dec.':>9}{'FA %':>7}{'det %':>7}"
           f"{'undec. %':>10}")
    print(hdr)
    for row in r.check + r.separation:
        print(f"{row.case:<52}{row.n_frames:>7}{row.n_null:>6}{row.n_alt:>7}{row.auc:>7.3f}{row.auc_decided:>9.3f}"
              f"{100 * row.false_alarm:>7.1f}{100 * row.detection:>7.1f}"
              f"{100 * row.null_undecided:>5.0f}/{100 * row.alt_undecided:<4.0f}")
    if args.json:
        write_json_result(args.json, asdict(r))
        print(f"-> {args.json}")
    return 0


def cmd_bench_forensics_clean(args: argparse.Namespace) -> int:
    """Lens mismatch and identification on the clean protocol (benchmarks.forensics_clean)."""
    from dataclasses import asdict

    from vigproc.pipeline.processor import output_file

    from benchmarks import clean as C
    from benchmarks import forensics_clean as F

    output_file(args.json)
    if args.calibrate:
        output_file(args.calibrate)
    bases, _ = C.load_clean_bases(args.images, args.min_long_side, args.limit, colour=not args.grey)
    if len(bases) < 20:
        print(f"vigproc: bench forensics-clean: {len(bases)} usable frames; need 20", file=sys.stderr)
        return 2
    t0 = time.perf_counter()
    try:
        r = F.run(bases, alpha=args.alpha, frames=args.frames, seed=args.seed, folds=args.folds, progress=print)
    except ValueError as exc:
        print(f"vigproc: bench forensics-clean: {exc}", file=sys.stderr)
        return 2
    split = ("calibrated on the even bases x {n} other lenses and no field, tested on the odd ones, and the "
             "other way round" if args.folds == 2 else
             f"{args.folds} folds: each tested against a calibration of the other folds' bases x {{n}} other "
             "lenses and no field")
    print(f"\nlens mismatch on {r.n_bases} clean bases (480x320, {'luminance' if args.grey else 'colour'}, linear) "
          f"x {len(r.test_lenses)} lensfun lenses; "
          f"{split.format(n=len(r.calibration_lenses))}; {r.ms_per_frame:.1f} ms per fit; "
          f"{time.perf_counter() - t0:.0f} s")
    print("AUC: over the frames the test decides; undecided: frames whose fit no lens explains (genuine / "
          "forged); AUC all: every frame by its D2")
    print(f"{'frames':>6}  {'true vs claimed field':<24}{'genuine':>9}{'forged':>8}{'AUC':>8}"
          f"{f'found at {r.alpha:g}':>15}{'undecided':>15}{'AUC all':>9}")
    for row in r.mismatch:
        print(f"{row.frames:>6}  {row.bucket:<24}{row.n_genuine:>9}{row.n_forged:>8}{row.auc:>8.3f}"
              f"{row.detection:>15.3f}{f'{row.undecided_genuine:.3f} / {row.undecided_forged:.3f}':>15}"
              f"{row.auc_ungated:>9.3f}")
    for n, fa in r.false_alarm.items():
        print(f"false alarms at {r.alpha:g}, {n} frame(s): {fa:.4f} of {r.n_genuine[n]} genuine")
    print(f"\nlens identification among {len(r.id_lenses)} lensfun lenses (fields >= "
          f"{r.id_min_separation_ev:.3f} EV apart; chance {100 / len(r.id_lenses):.1f} %): "
          + ", ".join(r.id_lenses))
    for n, acc in r.identification.items():
        print(f"  {n} frame(s): {100 * acc:.1f} % of {r.n_identification[n]}")
    if args.calibrate:
        cal = F.shipped_calibration(
            bases, alpha=args.alpha, progress=print,
            source=f"vigproc bench forensics-clean --alpha {args.alpha:g} --calibrate FILE "
                   f"({len(bases)} clean bases x no field and {len(r.calibration_lenses)} lensfun lenses)")
        cal.save(args.calibrate)
        print(f"calibration ({cal.n_frames} frames of {cal.n_images} bases) -> {args.calibrate}")
    if args.json:
        write_json_result(args.json, asdict(r))
        print(f"-> {args.json}")
    return 0
