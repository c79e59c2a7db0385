"""``vigproc bench``'s own command line: the benchmarks by name, each with its options,
run and printed (``vigproc bench NAME`` hands ``NAME [OPTIONS]`` to :func:`main`).

The benchmarks are declared in :data:`BENCHMARKS` like ``vigproc``'s commands
(:class:`vigproc.frontends.commands._subcommands.Command`): a summary and the function
declaring the options, in the module of :mod:`benchmarks.cli` that runs the benchmark
and prints its tables; only the one asked for is built.
"""

from __future__ import annotations

import argparse
from typing import Sequence

from vigproc.frontends.commands._bench import add_benchmarks_dir
from vigproc.frontends.commands._subcommands import Command, add_commands, chosen_command, command_parser

#: Every benchmark, in the order ``vigproc bench --help`` lists them: its summary and the
#: ``"module:function"`` (in :mod:`benchmarks.cli`) declaring its options and handler.
BENCHMARKS: dict[str, Command] = {
    "synthetic": Command("Lyu 2010 Tables 2-3 protocol",
                         "estimators:synthetic_arguments"),
    "lensfun": Command("real lens profiles from lensfun applied to natural images",
                       "estimators:lensfun_arguments"),
    "clean": Command("vignetting-free bases (central crops of camera frames) x real lens fields, "
                     "with the published peer when built",
                     "estimators:clean_arguments"),
    "crops": Command("the crop/shift test's AUC by fall-off and offset on clean bases, its false "
                     "alarms and power; --calibrate writes its calibration",
                     "estimators:crops_arguments"),
    "real": Command("photographs vignetted by others: known-field pairs and real lenses",
                    "estimators:real_arguments"),
    "speed": Command("estimator timings on 480x320 frames",
                     "speed:speed_arguments"),
    "scene-scatter": Command("how vignetting-free photographs scatter a frame's lens-family fit, "
                             "from the clean protocol's bases: the profile store's pooling "
                             "(vigproc/data/scene_scatter.json)",
                             "estimators:scene_scatter_arguments"),
    "learn": Command("learning one more frame into a lens profile, warm and in a new process",
                     "speed:learn_arguments"),
    "io": Command("frame read times per format and EXIF per file in batch",
                  "speed:io_arguments"),
    "throughput": Command("vigproc correct on full-size photographs beside the floor (decode, "
                          "encode, EXIF copy) and darktable-cli, in one run",
                          "speed:throughput_arguments"),
    "scaling": Command("vigproc watch and vigproc batch on full-size photographs with 1 and 2 "
                       "workers, interleaved: photos/s and the ratio to one worker",
                       "speed:scaling_arguments"),
    "memory": Command("peak memory of one worker (vigproc correct) on a 24 MP JPEG and 16-bit "
                      "TIFF",
                      "speed:memory_arguments"),
    "profile": Command("profile accuracy versus number of frames (lensfun lenses)",
                       "profiles:profile_arguments"),
    "profile-clean": Command("profiles learned through a real store on vignetting-free bases x "
                             "lensfun fields, beside the published peer pooled the same way",
                             "profiles:profile_clean_arguments"),
    "profile-interp": Command("a lens's profiles answering between their focal and aperture bins,"
                              " on lensfun's held-out calibrations",
                              "profiles:profile_interp_arguments"),
    "profile-flat": Command("profiles learned from a few shots of a flat field (Zheng et al.'s "
                            "white pairs), flat-field against the default",
                            "profiles:profile_flat_arguments"),
    "colour": Command("colour shading: per-channel fields from flat frames and DNG gain maps "
                      "(flat), a single photograph's corner cast (detect)",
                      "estimators:colour_arguments"),
    "correct": Command("full-resolution correction speed (24 MP by default)",
                       "speed:correct_arguments"),
    "batch": Command("batch files/s: 1 and 2 local workers, 2-process LocalCluster",
                     "batch:batch_arguments"),
    "colour-detect": Command("colour-cast detection from one photograph: physical casts (cos^k_c "
                             "of the chief ray's angle) rendered on the clean bases; detection "
                             "rate by corner dE2000, false detections on the bases and under "
                             "luminance-only fall-offs",
                             "colour_detect:colour_detect_arguments"),
    "forensics": Command("lens identification (Fig. 6) and the consistency check on real lensfun "
                         "fields: accuracy, ROC AUC",
                         "forensics:forensics_arguments"),
    "forensics-clean": Command("lens mismatch and lens identification on vignetting-free bases x "
                               "lensfun fields (the check's lens-family test): AUC, false alarms,"
                               " accuracy",
                               "forensics:forensics_clean_arguments"),
    "hook": Command("cost of one vigproc hook call vs the in-process API",
                    "hook:hook_arguments"),
    "learn-series": Command("learn as you go: a series of one lens setting (clean bases x a "
                            "lensfun lens's field, with its EXIF) through 'vigproc batch --mode "
                            "correct'",
                            "learn_series:learn_series_arguments"),
    "real-frames": Command("harm of the default correction on real full-size camera JPEGs: "
                           "brighter corners, fall-offs beyond real lenses, low confidence, "
                           "pixels pushed past white, in-camera corrected frames; the harm rules "
                           "off and on",
                           "real_frames:real_frames_arguments"),
    "watch": Command("watch-folder throughput with a trusted profile vs bare read+write",
                     "watch:watch_arguments"),
    "faults": Command("the watch daemon with its output on a small tmpfs that fills, is grown, "
                      "and kill -9 (root)",
                      "watch:faults_arguments"),
}


def build_parser(argv: Sequence[str] | None = None) -> argparse.ArgumentParser:
    """The parser of ``vigproc bench``.

    Parameters
    ----------
    argv : sequence of str, optional
        ``NAME [OPTIONS]``: only NAME's options are built; None: every benchmark's.

    Returns
    -------
    argparse.ArgumentParser
    """
    p = argparse.ArgumentParser(prog="vigproc bench")
    add_benchmarks_dir(p)  # taken by ``vigproc bench`` before NAME; listed here for its help
    sub = p.add_subparsers(dest="bench_command", required=True)
    add_commands(sub, BENCHMARKS, __name__,
                 BENCHMARKS.keys() if argv is None else {chosen_command(argv, frozenset({"--benchmarks-dir"}))})
    return p


def main(argv: Sequence[str]) -> int:
    """Run ``vigproc bench NAME [OPTIONS]``.

    Parameters
    ----------
    argv : sequence of str
        ``NAME [OPTIONS]``.

    Returns
    -------
    int
        The benchmark's exit code (a usage error exits 2 from argparse; a
        :class:`~vigproc.errors.VigprocError` is raised to ``vigproc``'s dispatch).
    """
    argv = list(argv)
    parser = build_parser(argv)
    args, extra = parser.parse_known_args(argv)
    if extra:  # said by the benchmark's own parser (its usage line)
        command_parser(parser, args).error(f"unrecognized arguments: {' '.join(extra)}")
    return int(args.fn(args) or 0)
