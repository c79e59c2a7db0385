"""The arguments of the commands whose handlers import the numeric stack (``estimate``,
``correct``, ``demo``, ``profile``, ``prior``): declared here, apart from their handlers,
so that ``vigproc CMD --help`` and a usage error load none of it. Each handler is named
``"module:function"`` (:mod:`vigproc.frontends.commands`), imported when the command runs.
"""

from __future__ import annotations

import argparse

from vigproc.frontends.commands._options import (JSON_HELP, add_learn, add_method, add_processing, add_profile_db,
                                                 add_transfer, number)

__all__ = ["correct", "demo", "estimate", "prior", "profile"]


def estimate(sp: argparse.ArgumentParser) -> None:
    """``vigproc estimate FILE...``."""
    sp.add_argument("files", nargs="+", metavar="FILE", help="images to estimate")
    add_method(sp)
    sp.add_argument("--json", action="store_true", help=JSON_HELP)
    sp.add_argument("--seed", type=int, default=0, help="random start of --method lyu2010-rand")
    add_transfer(sp)
    sp.set_defaults(fn="estimate:cmd_estimate")


def correct(sp: argparse.ArgumentParser) -> None:
    """``vigproc correct FILE... -o OUT_DIR``."""
    sp.add_argument("files", nargs="+", metavar="FILE", help="images to correct (RAW, TIFF, EXR, JPEG, PNG)")
    sp.add_argument("-o", "--output", required=True, metavar="OUT_DIR",
                    help="folder for the corrected images and their JSON records")
    add_processing(sp)
    add_learn(sp, "on when --profile-db is given and --profile is auto")
    sp.add_argument("--json", action="store_true", help=JSON_HELP)
    sp.set_defaults(fn="correct:cmd_correct")


def demo(sp: argparse.ArgumentParser) -> None:
    """``vigproc demo``."""
    sp.add_argument("-o", "--output", default="vigproc-demo", metavar="OUT_DIR",
                    help="output folder (default %(default)s)")
    add_transfer(sp)
    sp.set_defaults(fn="correct:cmd_demo")


def profile(sp: argparse.ArgumentParser) -> None:
    """``vigproc profile SUBCOMMAND``: its sub-commands, each handled by ``profile:cmd_profile``."""
    add_profile_db(sp)
    psub = sp.add_subparsers(dest="profile_command", required=True)
    psub.add_parser("list", help="stored profiles").set_defaults(fn="profile:cmd_profile")
    q = psub.add_parser("show", help="one profile as a model for a frame size, optionally as a picture")
    q.add_argument("id", help="index from 'profile list' or the key text")
    q.add_argument("--width", type=number(2, 1_000_000, integer=True),
                   help="frame width in px the model is shown for (default: 6000 px on the long side, "
                        "the profile's aspect ratio)")
    q.add_argument("--height", type=number(2, 1_000_000, integer=True),
                   help="frame height in px (default: from the width and the profile's aspect ratio)")
    q.add_argument("--plot", help="write a PNG picture of the fall-off")
    q.add_argument("--json", action="store_true", help="print the profile's model as JSON instead of a summary")
    q.set_defaults(fn="profile:cmd_profile")
    q = psub.add_parser("learn", help="estimate frames and pool them into their lenses' profiles")
    q.add_argument("files", nargs="+", metavar="FILE", help="frames of one or more lenses (their EXIF names the lens)")
    add_transfer(q)
    add_method(q)
    q.set_defaults(fn="profile:cmd_profile")
    q = psub.add_parser("apply", help="learning as you go: correct this lens setting's frames with the profile "
                        "as stored now, from the next frame on (a new series; docs/watch.md)")
    q.add_argument("id", help="index from 'profile list' or the key text")
    q.set_defaults(fn="profile:cmd_profile")
    q = psub.add_parser("delete", help="delete a stored profile (its pooled frames, prior and applied revision "
                        "with it)")
    q.add_argument("id", help="index from 'profile list' or the key text")
    q.set_defaults(fn="profile:cmd_profile")
    q = psub.add_parser("import", help="import a profile file (profiles/README.md)")
    q.add_argument("file", help="profile file (JSON) to import")
    q.set_defaults(fn="profile:cmd_profile")
    q = psub.add_parser("export", help="export a stored profile to a file")
    q.add_argument("id", help="profile id (see 'vigproc profile list')")
    q.add_argument("file", help="file to write (JSON)")
    q.set_defaults(fn="profile:cmd_profile")
    q = psub.add_parser("import-lensfun", help="store lensfun's calibration of a lens as a profile")
    q.add_argument("maker", help="lens maker as lensfun names it")
    q.add_argument("model", help="lens model as lensfun names it")
    q.add_argument("--focal", type=number(0.0, 10_000.0, open_lo=True), required=True, help="mm")
    q.add_argument("--aperture", type=number(0.0, 1_000.0, open_lo=True), required=True, help="f-number")
    q.add_argument("--distance", type=number(0.0, 1e6, open_lo=True), default=1000.0, help="m (1000: infinity)")
    q.add_argument("--width", type=number(2, 1_000_000, integer=True), default=6000,
                   help="frame width in px the model is made for (default %(default)s)")
    q.add_argument("--height", type=number(2, 1_000_000, integer=True), default=4000,
                   help="frame height in px (default %(default)s)")
    q.add_argument("--lens-id", help="store under this lens id: the 'lens' line that 'vigproc estimate' "
                   "prints for your camera (default: 'maker|model')")
    q.add_argument("--crop-factor", type=number(0.0, 100.0, open_lo=True),
                   help="the crop factor of your frames: the calibration ends where their sensor ends "
                   "(default: the camera --lens-id names, from lensfun's database; else the calibration's)")
    q.set_defaults(fn="profile:cmd_profile")
    q = psub.add_parser("import-lcp", help="store the vignetting of Adobe lens profiles (.lcp) as profiles, keyed "
                                           "like the EXIF of the camera and lens they name")
    q.add_argument("files", nargs="+", metavar="FILE", help="LCP files, or folders of them")
    q.add_argument("--camera-model", help="key the profiles for this camera model (files made for a whole make "
                                          "name none)")
    q.add_argument("--lens-id", help="store under this lens id (the 'lens' line 'vigproc estimate' prints) "
                                     "instead of the camera and lens the file names")
    q.add_argument("--aspect", help="aspect ratio of your frames, e.g. 3:2 (default: the calibration images', "
                                    "else 3:2)")
    q.add_argument("--include-jpeg", action="store_true",
                   help="also consider profiles made on the camera's JPEGs where a raw one exists")
    q.add_argument("--dry-run", action="store_true", help="convert and report, store nothing")
    q.add_argument("--json", action="store_true", help="print the conversions as JSON")
    q.set_defaults(fn="profile:cmd_profile")
    q = psub.add_parser("export-lensfun", help="write learned profiles as a lensfun XML database")
    q.add_argument("file", help="lensfun XML file to write")
    q.add_argument("--mount", help="lensfun mount written for cameras lensfun does not know (default Generic)")
    q.add_argument("--crop-factor", type=number(0.0, 100.0, open_lo=True),
                   help="crop factor for cameras neither lensfun nor the frames' EXIF give one for")
    q.set_defaults(fn="profile:cmd_profile")


def prior(sp: argparse.ArgumentParser) -> None:
    """``vigproc prior fit|fit-scene|fit-lens-family``."""
    psub = sp.add_subparsers(dest="prior_command", required=True)
    fp = psub.add_parser("fit", help="fit the prior on a folder of vignetting-free images")
    fp.add_argument("folder", help="vignetting-free photographs")
    fp.add_argument("-o", "--output", required=True, help="prior file to write (JSON)")
    fp.add_argument("--blocks-per-image", type=int, default=4, help="random blocks drawn per image (default 4)")
    fp.add_argument("--seed", type=int, default=0, help="seed of the block draw")
    fp.add_argument("--limit", type=int, help="use at most this many images")
    fp.add_argument("--source", help="provenance text stored in the prior")
    add_transfer(fp)
    fp.set_defaults(fn="prior:cmd_prior_fit")
    fp = psub.add_parser("fit-scene", help="fit the scene fall-off prior of the robust estimator on a folder "
                         "of vignetting-free photos")
    fp.add_argument("folder", help="vignetting-free photographs")
    fp.add_argument("-o", "--output", required=True, help="file to write (JSON)")
    fp.add_argument("--iterations", type=int, default=1, help="refits with the prior so far (default 1)")
    fp.add_argument("--limit", type=int, help="use at most this many images")
    add_transfer(fp)
    fp.set_defaults(fn="prior:cmd_prior_fit_scene")
    fp = psub.add_parser("fit-lens-family", help="the family of real lens fall-offs (vigproc/data/lens_family.json) "
                         "from lensfun's calibrations")
    fp.add_argument("-o", "--output", required=True, help="file to write (JSON)")
    fp.add_argument("--components", type=number(1, 8, integer=True), default=3,
                    help="principal components kept (default %(default)s; single frames use the first 2)")
    fp.add_argument("--db", nargs="*", help="lensfun XML files or folders (default: lensfunpy's bundled database)")
    fp.set_defaults(fn="prior:cmd_prior_fit_lens_family")
