"""``vigproc forensics train|evaluate|calibrate``.

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
from pathlib import Path

from vigproc.frontends.commands._options import add_method, add_transfer, number
from vigproc.errors import VigprocError
from vigproc.pipeline.processor import InputFiles, images_in, output_file, refuse_input


#: --classifier choices: name -> (kind, features).
CLASSIFIERS = {"vigproc": ("gaussian", "falloff"), "lyu2010": ("nn", "lyu2010")}


def add_arguments(sp: argparse.ArgumentParser) -> None:
    """``vigproc forensics``'s sub-commands (its summary: :data:`vigproc.frontends.cli.COMMANDS`)."""
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

    ims = [im for folder in folders for im in read_protocol_images(images_in(Path(folder), limit), transfer)]
    if len(ims) < 10:
        raise VigprocError(f"need at least 10 readable photographs, found {len(ims)}")
    return ims


# ------------------------------------------------------------------ commands
def cmd_train(args: argparse.Namespace) -> int:
    import numpy as np

    from vigproc.forensics.identify import feature_vector, train_classifier

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
