"""Command-line options shared by every command that processes frames, so that
``correct``, ``watch``, ``batch``, ``hook``, ``check`` and ``forensics`` spell and
document them the same way (and accept installed estimator plugins alike)."""

from __future__ import annotations

import argparse
import json
import math
import sys
from typing import Callable, Sequence

from vigproc.core.methods import METHODS
from vigproc.errors import EXIT_CODES, VigprocError, one_line

PROFILE_HELP = ("auto (a trusted stored profile of the frame's lens, else a DNG's own vignetting opcodes, else "
                "an installed profile-source plugin, else estimate), estimate, lensfun (lensfun's calibration of "
                "the frame's lens), embedded (the DNG's own FixVignetteRadial/GainMap opcodes), source:NAME "
                "(that profile-source plugin) or PATH of a profile file")


def number(lo: float = -math.inf, hi: float = math.inf, *, integer: bool = False,
           open_lo: bool = False) -> Callable[[str], float]:
    """An argparse ``type``: a finite number within [lo, hi] (``open_lo``: above lo),
    so that a bad value is a usage error (exit 2) before any work is done."""
    what = "an integer" if integer else "a number"
    bounds = f"{'(' if open_lo else '['}{lo:g}, {hi:g}]"

    def parse(text: str) -> float:
        try:
            v = int(text) if integer else float(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"{text!r} is not {what}") from None
        if not math.isfinite(v) or v < lo or v > hi or (open_lo and v == lo):
            raise argparse.ArgumentTypeError(f"{text} is not within {bounds}")
        return v

    parse.__name__ = "integer" if integer else "number"  # argparse names the type in its messages
    return parse


def add_transfer(sp: argparse.ArgumentParser, default: str = "auto") -> None:
    sp.add_argument("--input-transfer", choices=("auto", "linear", "srgb"), default=default,
                    help="how to decode stored values to linear light (default: %(default)s; auto: from the "
                         "file's metadata)")


def add_method(sp: argparse.ArgumentParser) -> None:
    # not argparse choices: installed estimator plugins are valid too (checked by Settings)
    sp.add_argument("--method", default="default", metavar="NAME",
                    help=f"estimator: {', '.join(METHODS)} or an installed estimator plugin "
                         "(see 'vigproc plugins'; default: default)")


def add_profile(sp: argparse.ArgumentParser, default: str = "auto") -> None:
    sp.add_argument("--profile", default=default, help=PROFILE_HELP + f" (default {default})")


def add_profile_db(sp: argparse.ArgumentParser) -> None:
    sp.add_argument("--profile-db", help="profile store (default: $VIGPROC_PROFILE_DB or the user data folder)")


def add_learn(sp: argparse.ArgumentParser, default: str) -> None:
    """``--learn`` / ``--no-learn``: whether correct mode also pools each frame into its
    lens's stored profile (:mod:`vigproc.pipeline.learning`); ``default`` says when it
    does without either."""
    g = sp.add_mutually_exclusive_group()
    g.add_argument("--learn", dest="learn", action="store_const", const=True, default=None,
                   help="correct mode: also pool each frame into its lens's stored profile (once per file "
                        f"content); once the profile is trusted it corrects that lens setting (default: {default})")
    g.add_argument("--no-learn", dest="learn", action="store_const", const=False,
                   help="correct mode: do not pool frames into the profile store (it is still read)")


def learn_setting(args: argparse.Namespace, *, default: bool) -> bool:
    """What ``--learn``/``--no-learn`` (:func:`add_learn`) decide for a run: without
    either, ``default`` in correct mode with ``--profile auto``; ``--learn`` in another
    mode is refused by :class:`~vigproc.pipeline.processor.Settings`."""
    chosen = getattr(args, "learn", None)
    if chosen is not None:
        return chosen
    return default and getattr(args, "mode", "correct") == "correct" and args.profile == "auto"


def add_output(sp: argparse.ArgumentParser, *, picture: bool = True) -> None:
    """Options of the corrected output: format, strength and (optionally) the picture."""
    from vigproc.pipeline.processor import IN_CAMERA_POLICIES, OUTPUT_FORMATS, UNAPPLIED_POLICIES

    sp.add_argument("--output-format", choices=list(OUTPUT_FORMATS), default="auto",
                    help="auto (default): each input's own kind back (a JPEG as a JPEG at its quality, a PNG as "
                         "a PNG, a TIFF/EXR as stored, a RAW as a linear 16-bit TIFF); jpeg, png (16-bit): "
                         "sRGB; tiff16, tiff-float, exr-half, exr-float: linear, for further editing; dng (DNG "
                         "inputs): a copy with its pixels untouched and the correction as a FixVignetteRadial "
                         "opcode in OpcodeList3, for raw editors")
    sp.add_argument("--unapplied", choices=list(UNAPPLIED_POLICIES), default="keep",
                    help="when nothing is applied (weak evidence, a refused field, in-camera correction, "
                         "strength 0): keep (default: the original under the output's name, its bytes when the "
                         "format is the input's own), skip (only the JSON sidecar, saying why), copy or link the "
                         "original as NAME.uncorrected.EXT, or write the frame as read under the output's name")
    sp.add_argument("--in-camera", choices=list(IN_CAMERA_POLICIES), default="respect",
                    help="respect (default): a JPEG whose camera already corrected its vignetting (maker-note "
                         "flag, or a phone's), or a file vigproc corrected, is left alone; ignore: correct it anyway")
    sp.add_argument("--strength", type=number(0.0, 2.0), default=1.0,
                    help="fraction of the fall-off removed, 0 to 2 (default 1)")
    if picture:
        sp.add_argument("--picture", action="store_true", help="also write a PNG picture of each estimated field")


def add_processing(sp: argparse.ArgumentParser, *, profile_default: str = "auto", picture: bool = True) -> None:
    """Everything a frame-processing command takes besides its files and folders."""
    add_profile(sp, profile_default)
    add_profile_db(sp)
    add_method(sp)
    add_output(sp, picture=picture)
    add_transfer(sp)


# ------------------------------------------------------------------ --json and exit codes
#: The help of ``--json`` on the commands that take several files (estimate, correct, check).
JSON_HELP = ("print one JSON document at the end, for one file as for many: {results: one record per file, "
             "in order (a failure as {file, error, type, exit_code}), done, failed, exit_code}")


def files_exit_code(codes: Sequence[int | None]) -> int:
    """The exit code of a command over several files, one code per file (None: done):
    0 when every file is done; the files' code when every file failed alike (so one
    bad file gives that file's code); else 1. estimate, correct, check and hook say it alike."""
    failed = [c for c in codes if c is not None]
    if not failed:
        return 0
    if len(failed) == len(codes) and len(set(failed)) == 1:
        return failed[0]
    return 1


def failure_record(file, exc: VigprocError) -> dict:
    """A failed file's record in a command's ``--json`` results."""
    return {"file": str(file), "error": str(exc), "type": type(exc).__name__, "exit_code": exc.exit_code}


def print_json_results(results: list[dict], code: int, **extra) -> None:
    """The one ``--json`` document of estimate, correct and check: every file's record in
    ``results`` (in the order given; a failure as {file, error, type, exit_code}), then
    how many were done and failed and the command's exit code."""
    failed = sum("error" in r for r in results)
    doc = {"results": results, "done": len(results) - failed, "failed": failed, **extra, "exit_code": code}
    print(json.dumps(doc, indent=1), flush=True)


def interrupted(command: str, done: str) -> int:
    """What an interrupted command (Ctrl-C, or SIGTERM handled alike) says: one line on
    stderr of what it had done, and exit code 130 (the front end turns it into 143 for
    SIGTERM).

    Parameters
    ----------
    command : str
    done : str
        What was done so far, e.g. ``3 corrected, 0 failed, 27 not started``.

    Returns
    -------
    int
        :data:`vigproc.errors.EXIT_CODES` ``["interrupted"]``.
    """
    print(one_line(f"vigproc {command}: interrupted: {done}"), file=sys.stderr, flush=True)
    return EXIT_CODES["interrupted"]
