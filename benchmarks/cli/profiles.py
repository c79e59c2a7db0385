"""``vigproc bench`` for the profiles' accuracy: ``profile``, ``profile-clean``,
``profile-interp`` and ``profile-flat`` (:mod:`benchmarks.profile`)."""

from __future__ import annotations

import argparse
import os
import sys
from dataclasses import asdict
from pathlib import Path

from benchmarks.cli._common import Table, add_clean_bases, estimator, write_json_result
from vigproc.core.methods import METHODS
from vigproc.errors import EXIT_CODES
from vigproc.frontends.commands._options import add_transfer, number
from vigproc.pipeline.processor import images_in as _images_in, output_file
#: The tables of bench profile (by pooling), profile-clean (by method), profile-interp
#: (between which bins) and profile-flat (by frame).
PROFILE_TABLE = Table((("pooling", "<14"), ("frames", ">7"), ("lenses", ">8"), ("median EV", ">11.3f"),
                       ("p90 EV", ">9.3f")))
PROFILE_CLEAN_TABLE = Table((("method", "<24"), ("frames", ">7"), ("lenses", ">8"), ("median EV", ">11.3f"),
                             ("p90 EV", ">9.3f"), ("<=1sd", ">7.2f"), ("<=2sd", ">7.2f")))
PROFILE_INTERP_TABLE = Table((("method", "<24"), ("between", "<10"), ("points", ">7"), ("median EV", ">11.4f"),
                              ("p90 EV", ">9.4f"), ("<=1sd", ">7.2f"), ("<=2sd", ">7.2f")))
PROFILE_FLAT_TABLE = Table((("frame", "<20"), ("method", "<12"), ("error EV", ">9.3f"), ("uncorr", ">8.3f"),
                            ("sigma", ">7.3f"), ("trusted", ">9"), ("grid EV", ">9.3f")))


def profile_arguments(bp: argparse.ArgumentParser) -> None:
    """``vigproc bench profile``'s options."""
    bp.add_argument("--images", required=True, help="folder of images")
    bp.add_argument("--limit", type=int, help="use at most this many images")
    bp.add_argument("--lenses", type=int, default=20, help="lensfun lenses (default %(default)s)")
    bp.add_argument("--counts", type=number(1, 100_000, integer=True), nargs="+", default=[1, 5, 20],
                    help="numbers of frames per lens to report (default 1 5 20)")
    bp.add_argument("--no-joint", action="store_true",
                    help="skip the joint multi-frame fit (its cost grows with the frames)")
    add_transfer(bp)
    bp.set_defaults(fn=cmd_bench_profile)


def profile_clean_arguments(bp: argparse.ArgumentParser) -> None:
    """``vigproc bench profile-clean``'s options."""
    add_clean_bases(bp)
    bp.add_argument("--lenses", type=number(1, 100, integer=True), default=20,
                    help="lensfun lenses (default %(default)s)")
    bp.add_argument("--counts", type=number(1, 100_000, integer=True), nargs="+", default=[1, 5, 20, 50],
                    help="numbers of frames per lens to report (default 1 5 20 50)")
    bp.add_argument("--seed", type=int, default=0, help="seed of each lens's frame order (default 0)")
    bp.add_argument("--orders", type=number(1, 100, integer=True), default=1,
                    help="frame orders per lens, each into a new store (default %(default)s)")
    bp.add_argument("--peer", help="the built rgs_peer executable (default: $VIGPROC_RGS_PEER)")
    bp.add_argument("--json", help="write the figures to this file")
    bp.set_defaults(fn=cmd_bench_profile_clean)


def profile_interp_arguments(bp: argparse.ArgumentParser) -> None:
    """``vigproc bench profile-interp``'s options."""
    bp.add_argument("--points", type=number(1, 100_000, integer=True), default=200,
                    help="held-out calibrations at most (default %(default)s)")
    bp.add_argument("--json", help="write the figures to this file")
    bp.set_defaults(fn=cmd_bench_profile_interp)


def profile_flat_arguments(bp: argparse.ArgumentParser) -> None:
    """``vigproc bench profile-flat``'s options."""
    bp.add_argument("--images", default="../shared/data/vignetted", help="folder with white*_vig / white pairs "
                    "(default %(default)s)")
    bp.add_argument("--methods", nargs="+", default=["flat-field", "default"], choices=list(METHODS),
                    help="methods to learn with (default %(default)s)")
    add_transfer(bp)
    bp.add_argument("--json", help="write the figures to this file")
    bp.set_defaults(fn=cmd_bench_profile_flat)


def cmd_bench_profile(args: argparse.Namespace) -> int:
    """Profile accuracy after 1, 5, 20 frames of real lens fields, per pooling method."""
    from vigproc.io.images import read_image

    from benchmarks import profile as B
    from benchmarks.synthetic import protocol_image

    files = _images_in(Path(args.images), args.limit)
    if len(files) < max(args.counts):
        # a lens would see an image twice, and the store learns a repeated frame once
        print(f"vigproc: bench profile: {max(args.counts)} frames per lens need at least as many images; "
              f"{args.images!r} has {len(files)}", file=sys.stderr)
        return EXIT_CODES["usage"]
    ims = [protocol_image(read_image(f, transfer=args.input_transfer)[0]) for f in files]
    fn = estimator("robust")  # the estimator whose fits the profile store pools (frame evidence)
    fn(ims[0])
    from vigproc.core.robust import estimate_robust_joint

    joint = None if args.no_joint else estimate_robust_joint
    rows, trust = B.run(ims, fn, args.lenses, args.counts, joint=joint, store=True)
    print(f"profile accuracy: {args.lenses} lensfun lenses, frames from {len(ims)} images (480x320); "
          "RMS of log2(pooled/true field)")
    PROFILE_TABLE.print_rows((r.pooling, r.n_frames, r.n_lenses, r.median_ev, r.p90_ev) for r in rows)
    print(f"trusted store profiles: {trust.n_trusted}/{trust.n_lenses} lenses within {trust.max_frames} frames, "
          f"after a median {trust.median_frames:.0f} frames, error then {trust.median_ev:.3f} EV median "
          f"(p90 {trust.p90_ev:.3f}); each frame estimated alone: {trust.single_frame_median_ev:.3f} EV median")
    return 0


def cmd_bench_profile_clean(args: argparse.Namespace) -> int:
    """Profiles learned through a real store on vignetting-free bases x lensfun fields."""
    from vigproc.core.lensfamily import PROFILE_COMPONENTS
    from vigproc.stores.lensfun import lensfun_family

    from benchmarks import clean as C
    from benchmarks import profile as B
    from benchmarks.peers import PEER_ENV, published_rgs

    output_file(args.json)
    bases, _ = C.load_clean_bases(args.images, args.min_long_side, args.limit, colour=not args.grey)
    if len(bases) < max(args.counts):
        print(f"vigproc: bench profile-clean: {max(args.counts)} frames per lens need as many bases; "
              f"{len(bases)} usable under {' '.join(args.images)}", file=sys.stderr)
        return EXIT_CODES["usage"]
    lens, excluded = C.lens_fields(args.lenses)
    # the store pools in a family without the test lenses: no profile holds the lens it is scored on
    family = lensfun_family(exclude=excluded, n_components=PROFILE_COMPONENTS)
    exe = args.peer or os.environ.get(PEER_ENV)
    peer = published_rgs(exe) if exe else None
    if peer is None:
        print(f"vigproc: bench profile-clean: no published peer (scripts/build_rgs_peer.sh; --peer or ${PEER_ENV}); "
              "its rows are left out", file=sys.stderr)
    rows, trust = B.run_clean(bases, lens, family, args.counts, peer=peer, seed=args.seed, orders=args.orders)
    print(f"profiles on the clean protocol: {len(lens)} lensfun lenses, each learning up to {max(args.counts)} of "
          f"{len(bases)} clean bases (480x320, {'luminance' if args.grey else 'colour'}, linear) in "
          f"{args.orders} order(s) of its own; error = RMS of log2(profile/true field) about its mean (EV), "
          "median / p90 over the lens x order runs")
    PROFILE_CLEAN_TABLE.print_rows((r.method, r.n_frames, r.n_lenses, r.median_ev, r.p90_ev, r.within_1sigma,
                                    r.within_2sigma) for r in rows)
    print(f"trusted (2 sigma < {trust.bound_ev:g} EV): {trust.n_trusted}/{trust.n_lenses} lenses, after a median "
          f"{trust.median_frames:.0f} frames; error then below the bound on {trust.share_within_bound:.0%} of them, "
          f"and on {trust.share_within_bound_later:.0%} of trusted profiles at the counts above")
    write_json_result(args.json, {"rows": [asdict(r) for r in rows], "trust": asdict(trust)})
    return 0


def cmd_bench_profile_interp(args: argparse.Namespace) -> int:
    """A lens's profiles answering between their bins, on lensfun's held-out calibrations."""
    from benchmarks import profile as B

    output_file(args.json)
    rows = B.run_interpolation(max_points=args.points)
    print("between bins: lensfun zoom lenses' interior calibrations held out, the others stored as profiles; "
          "error = RMS of log2(answer/held-out calibration) about its mean (EV)")
    PROFILE_INTERP_TABLE.print_rows((r.method, r.axis, r.n_points, r.median_ev, r.p90_ev, r.within_1sigma,
                                     r.within_2sigma) for r in rows)
    write_json_result(args.json, [asdict(r) for r in rows])
    return 0


def cmd_bench_profile_flat(args: argparse.Namespace) -> int:
    """Profiles learned from three shots of a flat field (Zheng et al.'s white pairs)."""
    from vigproc.core.pixels import luminance
    from vigproc.io.images import read_image
    from vigproc.pipeline.processor import IMAGE_SUFFIXES

    from benchmarks import profile as B
    from benchmarks.real import find_inputs

    output_file(args.json)
    pairs = [(v, c) for v, c in find_inputs(Path(args.images), IMAGE_SUFFIXES)[0]
             if c.stem.lower().startswith("white")]
    if not pairs:
        print(f"vigproc: bench profile-flat: no white pairs (white*_vig with white) under {args.images}",
              file=sys.stderr)
        return EXIT_CODES["usage"]
    frames = [(luminance(read_image(v, transfer=args.input_transfer)[0]),
               luminance(read_image(c, transfer=args.input_transfer)[0]), v.name) for v, c in pairs]
    rows = B.run_flat_field([f for f in frames if f[0].shape == f[1].shape], args.methods)
    print(f"flat-field profiles: {len(pairs)} white pairs under {args.images}, 3 unevenly lit shots of each "
          f"learned into a store (input transfer {args.input_transfer}); error = RMS of log2(profile/true field) "
          "about its mean (EV); grid: the same for the profile's grid field, which it corrects by (flat-field)")
    PROFILE_FLAT_TABLE.print_rows((r.name, r.method, r.error_ev, r.uncorrected_ev, r.sigma_ev,
                                   "yes" if r.trusted else "no", r.grid_error_ev) for r in rows)
    write_json_result(args.json, [asdict(r) for r in rows])
    return 0
