"""``vigproc forensics train|evaluate|calibrate`` and ``vigproc bench forensics``.

* ``train DIR... -o MODEL.json``: each subfolder of each DIR is a class (its name is
  the label; the same name in several DIRs is one class); every image is estimated
  and the classifier is trained on the estimates (:mod:`vigproc.forensics.identify`).
* ``evaluate MODEL.json DIR``: the subfolders of DIR, named like the classes, are
  classified; prints the confusion matrix as in Lyu 2010 Fig. 6.
* ``calibrate --images DIR... -o FILE``: the null distribution of the consistency
  check (:func:`vigproc.forensics.check.fit_calibration`) from vignetting-free photographs
  × real lensfun lens fields.  The shipped ``vigproc/data/forensics_calibration.json``
  was made this way (the command is recorded in the file).
"""

from __future__ import annotations

import argparse
import json
import shlex
import sys
import time
from pathlib import Path

from vigproc.frontends.commands._options import add_method, add_transfer, number, write_json_result
from vigproc.errors import VigprocError
from vigproc.frontends.commands._bench import benchmark


#: --classifier choices: name -> (kind, features).
CLASSIFIERS = {"vigproc": ("gaussian", "falloff"), "lyu2010": ("nn", "lyu2010")}


def register(subparsers) -> None:

    sp = subparsers.add_parser("forensics", help="lens identification from vignetting (Lyu 2010 Fig. 6) "
                                                 "and the calibration of 'vigproc check'")
    fsub = sp.add_subparsers(dest="forensics_command", required=True)
    q = fsub.add_parser("train", help="train a lens classifier: each subfolder of DIR is a class")
    q.add_argument("dirs", nargs="+", metavar="DIR", help="one folder of frames per lens (its name is the class)")
    q.add_argument("-o", "--output", required=True, help="classifier file (JSON)")
    q.add_argument("--classifier", choices=list(CLASSIFIERS), default="vigproc",
                   help="vigproc: Gaussian on the ring fall-off, pooled spread (default); "
                        "lyu2010: the paper's nearest neighbour on (p1, p2, p3, α1..α7)")
    q.add_argument("--shrinkage", type=number(0.0, 1.0), default=1.0,
                   help="vigproc classifier: 1 = one spread for all classes (default), 0 = one per class")
    add_method(q)
    add_transfer(q)
    q.set_defaults(fn=cmd_train)
    q = fsub.add_parser("evaluate", help="classify labelled folders and print the confusion matrix")
    q.add_argument("model", help="classifier file written by 'vigproc forensics train'")
    q.add_argument("dir", help="folder with one sub-folder of frames per lens")
    q.add_argument("--frames", type=number(1, 10_000, integer=True), default=1,
                   help="decide on groups of N frames of a class at once (multi-frame evidence)")
    q.add_argument("--json", action="store_true", help="print the results as JSON")
    add_transfer(q)
    q.set_defaults(fn=cmd_evaluate)
    q = fsub.add_parser("calibrate", help="calibrate 'vigproc check' on vignetting-free photographs "
                                          "x real lensfun lens fields")
    q.add_argument("--images", nargs="+", required=True, help="folders of vignetting-free photographs")
    q.add_argument("-o", "--output", required=True, help="calibration file to write (JSON)")
    q.add_argument("--lenses", type=int, default=16, help="lensfun lenses (two apertures each)")
    q.add_argument("--per-image", type=int, default=4, help="lens fields per photograph")
    q.add_argument("--alpha", type=number(0.0, 0.5, open_lo=True), default=0.05,
                   help="false-alarm probability of the verdict")
    q.add_argument("--limit", type=int, help="use at most this many images")
    add_method(q)
    add_transfer(q)
    q.set_defaults(fn=cmd_calibrate)


def register_bench(bench_subparsers) -> None:
    bp = bench_subparsers.add_parser("forensics", help="lens identification (Fig. 6) and the consistency "
                                                       "check on real lensfun fields: accuracy, ROC AUC")
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
    from vigproc.frontends.commands._options import add_clean_bases

    bp = bench_subparsers.add_parser(
        "forensics-clean", help="lens mismatch and lens identification on vignetting-free bases x lensfun "
                                "fields (the check's lens-family test): AUC, false alarms, accuracy")
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


# ------------------------------------------------------------------ helpers
def _class_dirs(root: Path) -> list[Path]:
    if not root.is_dir():
        raise VigprocError(f"not a folder: {root}")
    subs = sorted(p for p in root.iterdir() if p.is_dir() and not p.name.startswith("."))
    if not subs:
        raise VigprocError(f"{root} has no class subfolders (one subfolder of images per lens)")
    return subs


def _forensic_method(method: str) -> str:
    from vigproc.forensics.check import forensic_method  # imported when used: --help stays fast

    return forensic_method(method)


def _estimates(files: list[Path], method: str, transfer: str, what: str):
    """Estimate each file; unreadable ones are reported and skipped."""
    from vigproc.core.estimate import estimate
    from vigproc.io.images import read_image

    out = []
    for f in files:
        try:
            img, _ = read_image(f, transfer=transfer)
            out.append((f, estimate(img, _forensic_method(method), channel_axis=-1 if img.ndim == 3 else None)))
        except VigprocError as exc:
            print(f"vigproc: {exc} (skipped)", file=sys.stderr)
    if not out:
        raise VigprocError(f"no usable image in {what}")
    return out


def _protocol_images(folders, limit, transfer):
    from vigproc.io.protocol import read_protocol_images
    from vigproc.pipeline.processor import images_in

    ims = [im for folder in folders for im in read_protocol_images(images_in(Path(folder), limit), transfer)]
    if len(ims) < 10:
        raise VigprocError(f"need at least 10 readable photographs, found {len(ims)}")
    return ims


# ------------------------------------------------------------------ commands
def cmd_train(args: argparse.Namespace) -> int:
    import numpy as np

    from vigproc.forensics.identify import feature_vector, train_classifier
    from vigproc.pipeline.processor import InputFiles, images_in, output_file, refuse_input

    kind, feats = CLASSIFIERS[args.classifier]
    classes = [(sub, images_in(sub)) for root in args.dirs for sub in _class_dirs(Path(root))]
    refuse_input(args.output, InputFiles(f for _, files in classes for f in files))
    output_file(args.output)
    X, labels = [], []
    for sub, files in classes:
        est = _estimates(files, args.method, args.input_transfer, str(sub))
        X += [feature_vector(m, feats) for _, m in est]
        labels += [sub.name] * len(est)
        print(f"{sub.name}: {len(est)} frames")
    source = ("vigproc forensics train " + " ".join(shlex.quote(str(d)) for d in args.dirs)
              + f" --classifier {args.classifier} --shrinkage {args.shrinkage:g} --method {args.method}")
    clf = train_classifier(np.array(X), labels, kind=kind, features=feats, shrinkage=args.shrinkage,
                           method=_forensic_method(args.method), source=source)
    clf.save(args.output)
    print(f"{args.classifier} classifier, {len(clf.labels)} classes, {len(labels)} frames -> {args.output}")
    return 0


def cmd_evaluate(args: argparse.Namespace) -> int:
    from vigproc.forensics.identify import LensClassifier, accuracy, confusion_matrix, feature_vector, format_confusion
    import numpy as np

    from vigproc.pipeline.processor import images_in

    clf = LensClassifier.load(args.model)
    known = {name: i for i, name in enumerate(clf.labels)}
    true, pred, unknown = [], [], []
    for sub in _class_dirs(Path(args.dir)):
        if sub.name not in known:
            unknown.append(sub.name)
            continue
        est = _estimates(images_in(sub), clf.method, args.input_transfer, str(sub))
        X = np.array([feature_vector(m, clf.features) for _, m in est])
        if args.frames == 1:
            pred += list(clf.predict(X))
            true += [known[sub.name]] * len(X)
        else:  # consecutive groups of N frames (sorted file order); a short remainder is dropped
            for k in range(0, len(X) - args.frames + 1, args.frames):
                pred.append(clf.predict_pooled(X[k : k + args.frames]))
                true.append(known[sub.name])
    if unknown:
        print(f"vigproc: classes the model does not know, not evaluated: {', '.join(unknown)}", file=sys.stderr)
    if not true and len(unknown) < len(_class_dirs(Path(args.dir))):
        raise VigprocError(f"no class folder of {args.dir} has {args.frames} readable frames for one decision")
    if not true:
        raise VigprocError(f"no subfolder of {args.dir} is named like a class of the model "
                           f"({', '.join(clf.labels)})")
    cm = confusion_matrix(true, pred, len(clf.labels))
    acc, mean_acc = accuracy(cm)
    if args.json:
        print(json.dumps({"labels": list(clf.labels), "confusion": cm.tolist(), "accuracy": acc,
                          "mean_class_accuracy": mean_acc, "frames_per_decision": args.frames}, indent=1))
    else:
        print(format_confusion(cm, clf.labels))
        print(f"accuracy {100 * acc:.1f} % ({len(true)} decisions of {args.frames} frame(s)); "
              f"mean per-class accuracy {100 * mean_acc:.1f} %")
    return 0


def cmd_calibrate(args: argparse.Namespace) -> int:
    from vigproc.core.estimate import estimate
    import numpy as np

    from vigproc.forensics.calibration_frames import calibration_residuals, lens_classes
    from vigproc.forensics.check import estimator_fingerprint, fit_calibration

    from vigproc.pipeline.processor import InputFiles, images_in, output_file, refuse_input

    refuse_input(args.output, InputFiles(f for d in args.images for f in images_in(Path(d), args.limit)))
    output_file(args.output)
    ims = _protocol_images(args.images, args.limit, args.input_transfer)
    classes = lens_classes(args.lenses)
    print(f"calibrating on {len(ims)} photographs x {args.per_image} of {len(classes)} lens fields")
    res, groups, weak = calibration_residuals(ims, lambda v: estimate(v, _forensic_method(args.method), channel_axis=None), classes,
                                              per_image=args.per_image, progress=print)
    source = ("vigproc forensics calibrate --images " + " ".join(shlex.quote(str(d)) for d in args.images)
              + f" --lenses {args.lenses} --per-image {args.per_image} --alpha {args.alpha:g} --method {args.method}"
              + (f" --limit {args.limit}" if args.limit else ""))
    cal = fit_calibration(res, groups, weak=weak, method=_forensic_method(args.method), alpha=args.alpha,
                          source=source, fingerprint=estimator_fingerprint(args.method))
    cal.save(args.output)
    null = cal.null_d2(1, decided=True)
    print(f"{cal.n_frames} frames of {cal.n_images} photographs; image bias μ (EV at ρ=0.3..0.85): "
          + ", ".join(f"{v:+.2f}" for v in cal.mean[:4]) + "; spread σ: "
          + ", ".join(f"{v:.2f}" for v in np.sqrt(np.diag(cal.covariance_matrix))[:4])
          + f"; {np.mean(weak):.0%} weak; D² at p={args.alpha:g} (frames with a verdict): "
          f"{np.quantile(null, 1 - args.alpha):.1f} -> {args.output}")
    return 0


def cmd_bench_forensics(args: argparse.Namespace) -> int:
    from dataclasses import asdict

    import numpy as np

    from vigproc.core.estimate import estimate
    from vigproc.forensics.identify import format_confusion
    from vigproc.pipeline.processor import output_file

    B = benchmark("forensics")

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
    print(f"{'classifier':<48}{'frames':>7}{'tests':>7}{'lens+ap.':>10}{'per-class':>11}{'lens':>7}")
    for row in r.identification:
        print(f"{row.classifier:<48}{row.n_frames:>7}{row.n_tests:>7}{100 * row.accuracy:>10.1f}"
              f"{100 * row.mean_class_accuracy:>11.1f}{100 * row.lens_accuracy:>7.1f}")
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

    C = benchmark("clean")
    F = benchmark("forensics_clean")

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
