"""``vigproc bench`` for the estimators' accuracy: ``synthetic``, ``lensfun``, ``clean``,
``crops``, ``real``, ``scene-scatter`` and ``colour`` (:mod:`benchmarks`)."""

from __future__ import annotations

import argparse
import json
import logging
import os
import sys
from dataclasses import asdict
from pathlib import Path

from benchmarks.cli._common import (Table, add_clean_bases, add_colour, add_estimator_bench, add_scene_prior,
                                   estimator, scene_settings, write_json_result)
from vigproc.errors import VigprocError
from vigproc.frontends.commands._options import number
from vigproc.pipeline.processor import images_in as _images_in, output_file

log = logging.getLogger("vigproc")

#: bench lensfun's tables: the fields' errors, and the harm on the same images unvignetted.
LENSFUN_TABLE = Table((("method", "<14"), ("frames", ">7"), ("median EV", ">11.3f"), ("p90 EV", ">9.3f"),
                       ("uncorr EV", ">11.3f"), ("gain-free", ">11.3f"), ("uncorr gf", ">11.3f"),
                       ("differ. EV", ">12.3f"), ("fallbk", ">8"), ("s/img", ">8.3f")))
LENSFUN_HARM_TABLE = Table((("method", "<14"), ("frames", ">7"), ("median EV", ">11.3f"), ("worst EV", ">10.3f"),
                            ("cand. med", ">11.3f"), ("fallbk", ">8")))
#: bench clean's tables: the fields' errors, and the harm on the same crops unvignetted.
CLEAN_TABLE = Table((("method", "<18"), ("fields", "<9"), ("median EV", ">10.3f"), ("p90 EV", ">8.3f"),
                     ("frames med", ">11.3f"), ("uncorr", ">8.3f"), ("<=1sd", ">7.2f"), ("<=2sd", ">7.2f"),
                     ("fallbk", ">8"), ("ms/frame", ">10.1f"), ("PSNR dB", ">9.2f")))
CLEAN_HARM_TABLE = Table((("method", "<18"), ("frames", ">7"), ("median EV", ">11.3f"), ("worst EV", ">10.3f"),
                          ("fallbk", ">8")))


def synthetic_arguments(bp: argparse.ArgumentParser) -> None:
    """``vigproc bench synthetic``'s options."""
    bp.add_argument("--images", required=True, help="folder of images (BSDS val, say)")
    bp.add_argument("--limit", type=int, help="use at most this many images")
    bp.add_argument("--quantize", action="store_true", help="quantise the vignetted frames to 8 bits, as a JPEG would")
    bp.add_argument("--input-transfer", choices=("auto", "linear", "srgb"), default="linear",
                    help="the paper's protocol takes stored values as linear (default)")
    bp.add_argument("--methods", nargs="+", default=["ga", "lyu2010-rand", "lyu2010", "default"],
                    choices=["ga", "lyu2010-rand", "lyu2010", "robust", "lens-family", "default", "rgs"],
                    help="rgs: the radial-gradient-symmetry peer (benchmarks.peers)")
    add_colour(bp)
    add_scene_prior(bp)
    bp.add_argument("--json", help="write the figures to this file")
    bp.set_defaults(fn=cmd_bench_synthetic)


def lensfun_arguments(bp: argparse.ArgumentParser) -> None:
    """``vigproc bench lensfun``'s options."""
    bp.add_argument("--images", required=True, help="folder of images")
    bp.add_argument("--limit", type=int, help="use at most this many images")
    bp.add_argument("--lenses", type=int, default=20, help="lensfun lenses (default %(default)s)")
    bp.add_argument("--frames-per-lens", type=int, default=5, help="frames per lens (default %(default)s)")
    add_colour(bp)
    add_estimator_bench(bp)
    bp.set_defaults(fn=cmd_bench_lensfun)


def clean_arguments(bp: argparse.ArgumentParser) -> None:
    """``vigproc bench clean``'s options."""
    add_clean_bases(bp)
    bp.add_argument("--crop", type=number(0.05, 1.0), default=0.4,
                    help="side fraction of each frame kept about its centre (default %(default)s; the "
                         "camera lens's own fall-off inside the crop grows with it)")
    bp.add_argument("--lenses", type=number(1, 100, integer=True), default=20,
                    help="lensfun lenses (default %(default)s)")
    bp.add_argument("--methods", nargs="+", default=["default", "flat-field", "lens-family", "rgs", "rgs-c++"],
                    choices=["default", "default+exif", "robust", "real-lens", "flat-field", "lens-family",
                             "lens-family+exif", "lyu2010", "ga", "rgs", "rgs-c++", "rgs-c++-srgb"],
                    help="+exif: told each lens's 35-mm focal length and f-number (never the lens); rgs: "
                         "vigproc's reimplementation of Zheng et al.; rgs-c++: their published code "
                         "(built by scripts/build_rgs_peer.sh), given linear or sRGB-encoded 8-bit frames")
    bp.add_argument("--peer", help="the built rgs_peer executable (default: $VIGPROC_RGS_PEER)")
    bp.add_argument("--no-table1", action="store_true", help="only the lensfun fields")
    bp.add_argument("--base-falloff", action="store_true",
                    help="give each base a test lens's fall-off first (the lenses in turn), as a film scan "
                         "carries its camera's, and score Table 1's fields against the bases with it, as the "
                         "BSDS protocols do (Table 1's fields and no harm only)")
    bp.add_argument("--calibrate", action="store_true",
                    help="only fit the lens-family estimator's sigma scale and floor (even frames) and check "
                         "them (odd frames)")
    bp.add_argument("--json", help="write the figures to this file")
    bp.set_defaults(fn=cmd_bench_clean)


def crops_arguments(bp: argparse.ArgumentParser) -> None:
    """``vigproc bench crops``'s options."""
    add_clean_bases(bp)
    bp.add_argument("--lenses", type=number(1, 100, integer=True), default=10,
                    help="lensfun lens shapes (default %(default)s)")
    bp.add_argument("--alpha", type=number(0.0, 1.0, open_lo=True), default=0.01,
                    help="false-alarm probability of the test (default %(default)s)")
    bp.add_argument("--statistic", choices=["shift", "z", "known-profile"], default="shift",
                    help="shift: the free-centre fit's centre's distance from the frame's in half-diagonals (the "
                    "test's); z: its Mahalanobis distance by the jackknife covariance; known-profile: the shift "
                    "when the centre is fitted with the lens's own profile known exactly, how far any test of "
                    "the centre could go (default %(default)s)")
    bp.add_argument("--calibrate", metavar="FILE", help="write the null distribution (every uncropped frame's "
                    "statistic) as a crop calibration")
    bp.add_argument("--json", help="write the figures to this file")
    bp.set_defaults(fn=cmd_bench_crops)


def real_arguments(bp: argparse.ArgumentParser) -> None:
    """``vigproc bench real``'s options."""
    bp.add_argument("--images", required=True, help="folder tree, e.g. ../shared/data/vignetted")
    add_estimator_bench(bp)
    bp.set_defaults(fn=cmd_bench_real)


def scene_scatter_arguments(bp: argparse.ArgumentParser) -> None:
    """``vigproc bench scene-scatter``'s options."""
    bp.add_argument("-o", "--output", required=True, help="file to write (JSON)")
    add_clean_bases(bp)
    bp.set_defaults(fn=cmd_bench_scene_scatter)


def colour_arguments(bp: argparse.ArgumentParser) -> None:
    """``vigproc bench colour``'s options."""
    bp.add_argument("--part", choices=["flat", "detect", "all"], default="flat",
                    help="which part to run (default %(default)s)")
    add_clean_bases(bp)
    bp.add_argument("--frames", type=number(1, 100, integer=True), default=3,
                    help="flat frames per lens (default %(default)s)")
    bp.add_argument("--seed", type=number(0, 2**31, integer=True), default=0, help="random seed (default %(default)s)")
    bp.add_argument("--json", help="write the figures to this file")
    bp.set_defaults(fn=cmd_bench_colour)


def cmd_bench_synthetic(args: argparse.Namespace) -> int:
    """Lyu 2010's synthetic protocol (Tables 2-3): Table 1's fields on natural images, every method."""
    from vigproc.io.images import read_image

    from benchmarks import synthetic as S

    settings = scene_settings(args.scene_prior)
    output_file(args.json)
    files = _images_in(Path(args.images), args.limit)
    ims = [S.protocol_image(read_image(f, transfer=args.input_transfer)[0], args.colour) for f in files]
    order = ("ga", "lyu2010-rand", "lyu2010", "robust", "lens-family", "default", "rgs")
    chosen = {k: estimator(k, settings=settings) for k in order if k in args.methods}
    for fn in chosen.values():  # JIT warm-up outside the timings
        fn(ims[0])
    print(f"Lyu 2010 synthetic protocol: {len(ims)} images from {args.images}, "
          f"{'8-bit quantised' if args.quantize else 'float'}, input transfer {args.input_transfer}, "
          f"scene prior {args.scene_prior}")
    print(S.HEADER)
    rows = S.run(ims, chosen, quantize=args.quantize, progress=print)
    if args.json:
        meta = {"images": str(args.images), "n": len(ims), "quantize": args.quantize,
                "input_transfer": args.input_transfer, "scene_prior": args.scene_prior}
        S.write_json(rows, Path(args.json), meta)
    return 0


def cmd_bench_lensfun(args: argparse.Namespace) -> int:
    """Real lens fields from lensfun on natural images, and no harm on the same images unvignetted."""
    from vigproc.io.images import read_image

    from benchmarks import lensfun as B
    from benchmarks.synthetic import protocol_image

    settings = scene_settings(args.scene_prior)
    output_file(args.json)
    files = _images_in(Path(args.images), args.limit)
    ims = [protocol_image(read_image(f, transfer=args.input_transfer)[0], args.colour) for f in files]
    results = []
    print(f"lensfun protocol: {args.lenses} lenses x {args.frames_per_lens} frames from {len(ims)} images "
          f"(input transfer {args.input_transfer}, 480x320, scene prior {args.scene_prior}); "
          "RMS of log2(estimated/true field)")
    print(LENSFUN_TABLE.header())
    from vigproc.core.lensfamily import PROFILE_COMPONENTS
    from vigproc.stores.lensfun import lensfun_family
    from vigproc.stores.lensfun import diverse_lenses

    # the lens-family fits never hold the lens they are scored on
    family = lensfun_family(exclude={(lens.maker, lens.model) for lens, _ in diverse_lenses(args.lenses)},
                            n_components=PROFILE_COMPONENTS)
    for name in args.methods:
        fn = estimator(name, settings=settings, family=family)
        fn(ims[0])
        r = B.run_lensfun(ims, name, fn, args.lenses, args.frames_per_lens)
        results.append(asdict(r))
        print(LENSFUN_TABLE.row(r.method, r.n_frames, r.median_ev, r.p90_ev, r.uncorrected_median_ev,
                                r.gain_free_median_ev, r.gain_free_uncorrected_ev, r.differential_median_ev,
                                r.fallbacks, r.seconds_per_image))
    print("do no harm (same images, no vignetting): RMS log2 of the applied field")
    print(LENSFUN_HARM_TABLE.header())
    for name in args.methods:
        r = B.run_flat(ims, name, estimator(name, settings=settings, family=family))
        results.append(asdict(r))
        print(LENSFUN_HARM_TABLE.row(r.method, r.n_frames, r.median_ev, r.worst_ev, r.candidate_median_ev, r.fallbacks))
    write_json_result(args.json, results)
    return 0


def cmd_bench_clean(args: argparse.Namespace) -> int:
    """Vignetting-free bases × lensfun and Table 1 fields, every method side by side."""
    from vigproc.core.lensfamily import PROFILE_COMPONENTS
    from vigproc.core.pixels import luminance
    from vigproc.stores.lensfun import lensfun_family

    from benchmarks import clean as C
    from benchmarks.peers import PEER_ENV, published_rgs

    output_file(args.json)
    bases, names = C.load_clean_bases(args.images, args.min_long_side, args.limit, args.crop, colour=not args.grey)
    if len(bases) < 2:
        print(f"vigproc: bench clean: {len(bases)} usable frames under {' '.join(args.images)}; need 2",
              file=sys.stderr)
        return 2
    lens, excluded = C.lens_fields(args.lenses)
    # never the lens an estimate is scored on; all the components a colour frame's fit uses
    family = lensfun_family(exclude=excluded, n_components=PROFILE_COMPONENTS)
    if args.base_falloff and (args.calibrate or args.no_table1):
        print("vigproc: bench clean: --base-falloff scores Table 1's fields; not with --calibrate or --no-table1",
              file=sys.stderr)
        return 2
    if args.base_falloff:  # the bases' own fall-off is then part of what is scored against
        bases = [C.vignetted(b, lens[i % len(lens)].log_field) for i, b in enumerate(bases)]
    if args.calibrate:
        cal = C.calibrate_sigma(bases, lens, family)
        print(f"lens-family sigma = hypot({cal.scale:g} x jackknife sigma, {cal.floor:g} EV), fitted on "
              f"{cal.n_frames // 2} frames (even bases x {len(lens)} lenses + none): within 1 sigma "
              f"{cal.train_within_1sigma:.2f}, 2 sigma {cal.train_within_2sigma:.2f}; on the other half: "
              f"{cal.test_within_1sigma:.2f}, {cal.test_within_2sigma:.2f}")
        return 0
    peer = args.peer or os.environ.get(PEER_ENV)
    methods = {}
    for name in args.methods:
        if name in ("rgs-c++", "rgs-c++-srgb"):
            if not peer:
                print(f"vigproc: bench clean: skipping {name}: no peer built (scripts/build_rgs_peer.sh; "
                      f"--peer or ${PEER_ENV})", file=sys.stderr)
                continue
            rgs = published_rgs(peer, "srgb" if name.endswith("srgb") else "linear")
            methods[name] = lambda v, f=None, rgs=rgs: rgs(luminance(v), f)  # it reads grey
        elif name.endswith("+exif"):  # told the field's focal length and f-number, as EXIF would
            base = name[: -len("+exif")]
            methods[name] = C.model_estimator(estimator(base, family=family), exif=True)
        else:
            methods[name] = C.model_estimator(estimator(name, family=family))
    print(f"clean protocol: {len(bases)} central {args.crop:.0%} crops (480x320, "
          f"{'luminance' if args.grey else 'colour'}, linear{', each with a test lens fall-off' if args.base_falloff else ''}) of frames >= "
          f"{args.min_long_side} px from {' '.join(args.images)}; error = RMS of log2(estimated/true) "
          "about its mean (EV); median per field, then median / p90 over fields")
    print(f"lens family for lens-family: {family.lenses} lensfun lenses, the {len(lens)} test lenses left out")
    results = []
    groups = ([] if args.base_falloff else [("lensfun", lens)]) + ([] if args.no_table1 else
                                    [(f"table1-{i + 1}", [f]) for i, f in enumerate(C.table1_fields())])
    print(CLEAN_TABLE.header())
    for name, fn in methods.items():
        fn(bases[0], None)  # JIT warm-up outside the timings
        for label, fields in groups:
            r = C.run_fields(bases, name, fn, fields, label)
            results.append(asdict(r))
            print(CLEAN_TABLE.row(r.method, r.fields, r.median_ev, r.p90_ev, r.frame_median_ev, r.uncorrected_ev,
                                  r.within_1sigma, r.within_2sigma, r.fallbacks, r.ms_per_frame, r.psnr_db), flush=True)
    print("no harm (the same crops, no vignetting): RMS of log2 of the applied field about its mean")
    print(CLEAN_HARM_TABLE.header())
    for name, fn in methods.items():
        r = C.run_harm(bases, name, fn)
        results.append(asdict(r))
        print(CLEAN_HARM_TABLE.row(r.method, r.n_frames, r.median_ev, r.worst_ev, r.fallbacks))
    write_json_result(args.json, {"bases": names, "results": results})
    return 0


def cmd_bench_crops(args: argparse.Namespace) -> int:
    """The crop test's AUC by fall-off and offset, its false alarms and power, on clean bases."""
    import numpy as np

    from vigproc.stores.lensfun import lensfun_family
    from vigproc.stores.lensfun import diverse_lenses

    from benchmarks import clean as C
    from benchmarks import crops as K

    if args.calibrate and args.statistic != "shift":
        print("vigproc: bench crops: --calibrate writes the test's own null: it needs --statistic shift",
              file=sys.stderr)
        return 2
    output_file(args.json)
    if args.calibrate:
        output_file(args.calibrate)
    bases, _ = C.load_clean_bases(args.images, args.min_long_side, args.limit, colour=not args.grey)
    if len(bases) < 4:
        print(f"vigproc: bench crops: {len(bases)} usable frames; need 4", file=sys.stderr)
        return 2
    chosen = diverse_lenses(args.lenses)
    family = lensfun_family(exclude={(lens.maker, lens.model) for lens, _ in chosen})
    r = K.run(bases, [(pa.k1, pa.k2, pa.k3) for _, pa in chosen], family, alpha=args.alpha,
              statistic=args.statistic)
    print(f"crop test on {r.n_bases} clean bases x {r.n_lenses} lensfun lens shapes (480x320, {'luminance' if args.grey else 'colour'}, linear); "
          f"statistic: {args.statistic} of the free-centre fit's centre; {r.ms_per_frame:.1f} ms/frame")
    print("AUC (cropped vs uncropped frames of the same fall-off):")
    print(f"{'corner fall-off':<18}" + "".join(f"{f'offset {o:.0%}':>14}" for o in K.OFFSETS))
    for ev in K.FALLOFFS_EV:
        print(f"{f'{ev:g} EV':<18}" + "".join(f"{r.auc[f'{ev:g}EV/{o:.0%}']:>14.3f}" for o in K.OFFSETS))
    print(f"calibrated on the even bases, checked on the odd ones, at alpha {r.alpha:g}:")
    print(f"{'corner fall-off':<18}{'false alarms':>14}" + "".join(f"{f'found {o:.0%}':>12}" for o in K.OFFSETS))
    for ev in K.FALLOFFS_EV:
        print(f"{f'{ev:g} EV':<18}{r.false_alarm[f'{ev:g}EV']:>14.3f}"
              + "".join(f"{r.power[f'{ev:g}EV/{o:.0%}']:>12.2f}" for o in K.OFFSETS))
    if args.calibrate:
        from vigproc.forensics.crops import CropCalibration

        CropCalibration(np.asarray(r.null_z), f"vigproc bench crops: {r.n_bases} clean bases x {r.n_lenses} "
                        f"lenses x {len(K.FALLOFFS_EV)} fall-offs, uncropped").save(args.calibrate)
        print(f"calibration ({len(r.null_z)} uncropped frames) written to {args.calibrate}")
    write_json_result(args.json, asdict(r))
    return 0


def cmd_bench_real(args: argparse.Namespace) -> int:
    """Photographs vignetted by others: pairs with a known field, and real lenses."""
    import numpy as np

    from vigproc.core.pixels import luminance
    from vigproc.io.images import read_image
    from vigproc.pipeline.processor import IMAGE_SUFFIXES

    from benchmarks import real as R

    settings = scene_settings(args.scene_prior)
    output_file(args.json)
    pairs, photos = R.find_inputs(Path(args.images), IMAGE_SUFFIXES)
    if not pairs and not photos:
        raise VigprocError(f"no images in {args.images}")

    def lum(f: Path):
        return luminance(read_image(f, transfer=args.input_transfer)[0])

    results: list[dict] = []
    print(f"{len(pairs)} pairs and {len(photos)} photographs from {args.images} (input transfer "
          f"{args.input_transfer}, full frames, scene prior {args.scene_prior})")
    fns = {name: estimator(name, settings=settings) for name in args.methods}
    if pairs:
        print(f"pairs: gain-free RMS of log2(estimated/true field) over {R.BLOCK}px blocks, EV")
        print(f"{'pair':<22}{'true corner':>12}{'uncorr':>8}" + "".join(f"{m:>12}" for m in args.methods))
        errs: dict[str, list[float]] = {m: [] for m in args.methods}
        unc = []
        for v, c in pairs:
            try:
                lv, lc = lum(v), lum(c)
            except VigprocError as exc:
                log.warning("skipping %s", exc)
                continue
            rows = [R.run_pair(lv, lc, v.stem, m, fns[m]) for m in args.methods]
            results.extend(asdict(r) for r in rows)
            unc.append(rows[0].uncorrected_ev)
            for r in rows:
                errs[r.method].append(r.error_ev)
            print(f"{v.stem:<22}{rows[0].true_corner_ev:>12.2f}{rows[0].uncorrected_ev:>8.3f}"
                  + "".join(f"{r.error_ev:>11.3f}{'*' if r.fallback else ' '}" for r in rows))
        print(f"{'median':<22}{'':>12}{np.median(unc):>8.3f}" + "".join(f"{np.median(errs[m]):>11.3f} " for m in args.methods))
        print("(* fell back to no correction)")
    if photos:
        print("photographs with real vignetting: corner fall-off applied (log2 at the frame corners; "
              "'-' = no correction) and the crude corner-minus-centre log2 luminance")
        print(f"{'photograph':<22}{'crude':>8}" + "".join(f"{m:>12}" for m in args.methods))
        corrected = {m: 0 for m in args.methods}
        n = 0
        for f in photos:
            try:
                lf = lum(f)
            except VigprocError as exc:
                log.warning("skipping %s", exc)
                continue
            rows = [R.run_photo(lf, f.stem, m, fns[m]) for m in args.methods]
            results.extend(asdict(r) for r in rows)
            n += 1
            for r in rows:
                corrected[r.method] += r.corrected
            print(f"{f.stem:<22}{rows[0].crude_corner_ev:>8.2f}"
                  + "".join(f"{r.corner_ev:>12.2f}" if r.corrected else f"{'-':>12}" for r in rows))
        print(f"{'corrected':<22}{'':>8}" + "".join(f"{f'{corrected[m]}/{n}':>12}" for m in args.methods))
    write_json_result(args.json, results)
    return 0


def cmd_bench_scene_scatter(args: argparse.Namespace) -> int:
    """How vignetting-free photographs scatter a frame's data-only lens-family fit
    (vigproc.core.pooling.scene_scatter), from the clean protocol's bases, fitted as the
    profile store fits a frame (its evidence, the profile family)."""
    import numpy as np

    from vigproc.atomic import atomic_write_text
    from vigproc.core.estimate import frame_evidence
    from vigproc.core.lensfamily import profile_family
    from vigproc.core.pooling import frame_fit, scene_scatter_record
    from vigproc.core.robust import evidence_copy

    from benchmarks import clean as C

    output_file(args.output)
    bases, names = C.load_clean_bases(args.images, args.min_long_side, args.limit, colour=not args.grey)
    family = profile_family()
    fits = []
    for b, name in zip(bases, names):
        try:
            fits.append(frame_fit(evidence_copy(frame_evidence(b)), family))
        except VigprocError as exc:  # a base with too few usable pixels: leave it out
            log.warning("skipping %s: %s", name, exc)
    record = scene_scatter_record(
        fits, family, source=f"vigproc bench scene-scatter -o FILE ({len(fits)} clean bases, "
                             f"{'luminance' if args.grey else 'colour'}, no field)")
    atomic_write_text(Path(args.output), json.dumps(record) + "\n")
    sd = np.sqrt(np.diag(record["covariance"]))
    print(f"wrote {args.output}: the scatter of {len(fits)} vignetting-free frames' fits; s.d. of the "
          f"{family.n_components} coefficients {', '.join(f'{v:.3f}' for v in sd)}")
    return 0


def cmd_bench_colour(args: argparse.Namespace) -> int:
    """Colour shading: ``--part flat`` (flat frames and DNG gain maps, benchmarks.colour),
    ``detect`` (one photograph's cast, benchmarks.colour_detect), or ``all``."""
    output_file(args.json)
    data: dict = {}
    if args.part in ("flat", "all"):
        from benchmarks import colour as B
        from benchmarks.clean import load_clean_bases

        bases, _ = load_clean_bases(args.images, args.min_long_side, args.limit, colour=True)
        rows = B.run_flat(B.physical_fields() + B.gainmap_fields(), bases, frames=args.frames, seed=args.seed)
        dng = B.run_dng()
        print(B.report_flat(rows, dng, len(bases), args.frames))
        data["flat"] = [asdict(r) for r in rows]
        data["dng"] = [asdict(r) for r in dng]
    if args.part in ("detect", "all"):
        from benchmarks.cli.colour_detect import bench_detect_report

        code, data["detect"] = bench_detect_report(args)  # its options at their defaults (see bench colour-detect)
        if code:
            return code
    write_json_result(args.json, data)
    return 0
