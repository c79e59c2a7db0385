"""The ``vigproc`` command line: the parser and the dispatch.

Every user-facing failure is a :class:`~vigproc.errors.VigprocError` turned into one
line on stderr and its exit code; no traceback reaches the user.

The handlers live in :mod:`vigproc.frontends.commands`: the commands declared here
(``estimate``, ``correct``, ``demo``, ``profile``, ``prior``) name theirs as
``"module:function"`` (:data:`HANDLER_MODULES`), imported once when the command runs, so
``vigproc --help`` loads none of them and they import what they need at their top; the
other command modules declare their own parsers (``register``).
"""

from __future__ import annotations

import argparse
import contextlib
import importlib
import io
import logging
import pkgutil
import signal
import sys
import threading
import warnings
from typing import Sequence

import vigproc.frontends.commands
from vigproc.errors import EXIT_CODES, VigprocError, one_line
from vigproc.frontends.commands._bench import add_benchmarks_dir
from vigproc.frontends.commands._options import (JSON_HELP, add_learn, add_method, add_processing, add_transfer,
                                                 number)
from vigproc.frontends.commands.hook import MAX_REQUEST_BYTES  # imported by build_parser anyway
from vigproc.pipeline.processor import OUTPUT_FORMATS, images_in as _images_in, output_file  # noqa: F401  (re-exported names)

log = logging.getLogger("vigproc")

#: Modules of :mod:`vigproc.frontends.commands` that hold handlers of commands declared
#: here: imported only to run one, never to build the parser.
HANDLER_MODULES = frozenset({"estimate", "correct", "profile", "prior"})


def _handler(spec: str):
    """The function ``"module:function"`` names, ``module`` in :mod:`vigproc.frontends.commands`."""
    module, _, name = spec.partition(":")
    return getattr(importlib.import_module(f"vigproc.frontends.commands.{module}"), name)


# ------------------------------------------------------------------ parser
def build_parser() -> argparse.ArgumentParser:
    """The parser of every command; a command's handler is its ``fn`` default (a function, or
    ``"module:function"`` in :mod:`vigproc.frontends.commands`, imported when it runs)."""
    p = argparse.ArgumentParser(prog="vigproc", description="Lens vignetting: estimate, correct, learn, check.")
    p.add_argument("-v", "--verbose", action="count", default=0,
                   help="more log output (-v: info, -vv: debug and tracebacks)")
    sub = p.add_subparsers(dest="command", required=True)

    sp = sub.add_parser("estimate", help="estimate the vignetting of images (nothing is written)")
    sp.add_argument("files", nargs="+", metavar="FILE", help="images to estimate")
    add_method(sp)
    sp.add_argument("--json", action="store_true", help=JSON_HELP)
    sp.add_argument("--seed", type=int, default=0, help="random start of --method lyu2010-rand")
    add_transfer(sp)
    sp.set_defaults(fn="estimate:cmd_estimate")

    sp = sub.add_parser("correct", help="remove vignetting: a stored profile of the lens, else an estimate "
                                        "(each input's own format back by default)")
    sp.add_argument("files", nargs="+", metavar="FILE", help="images to correct (RAW, TIFF, EXR, JPEG, PNG)")
    sp.add_argument("-o", "--output", required=True, metavar="OUT_DIR",
                    help="folder for the corrected images and their JSON records")
    add_processing(sp)
    add_learn(sp, "on when --profile-db is given and --profile is auto")
    sp.add_argument("--json", action="store_true", help=JSON_HELP)
    sp.set_defaults(fn="correct:cmd_correct")

    sp = sub.add_parser("demo", help="correct the bundled sample images (the README's first command)")
    sp.add_argument("-o", "--output", default="vigproc-demo", metavar="OUT_DIR",
                    help="output folder (default %(default)s)")
    add_transfer(sp)
    sp.set_defaults(fn="correct:cmd_demo")

    # further commands live in their own modules under vigproc/commands (watch, check,
    # batch, hook, ...); each exposes register(subparsers)
    command_modules = [importlib.import_module(f"vigproc.frontends.commands.{m.name}")
                       for m in sorted(pkgutil.iter_modules(vigproc.frontends.commands.__path__), key=lambda m: m.name)
                       if not m.name.startswith("_") and m.name not in HANDLER_MODULES]
    for mod in command_modules:
        mod.register(sub)

    sp = sub.add_parser("profile", help="the per-lens profile store")
    sp.add_argument("--profile-db", help="profile store (default: $VIGPROC_PROFILE_DB or the user data folder)")
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
                   help="the camera's crop factor (lenses calibrated on several sensors)")
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

    sp = sub.add_parser("prior", help="natural-image prior of the paper's method")
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

    sp = sub.add_parser("bench", help="benchmarks (print measured figures; from a source checkout)")
    add_benchmarks_dir(sp)  # the benchmarks are found at run time, in a source checkout
    bsub = sp.add_subparsers(dest="bench_command", required=True)
    for mod in command_modules:  # the benchmarks live in the command modules (register_bench is optional)
        if hasattr(mod, "register_bench"):
            mod.register_bench(bsub)
    _list_in_order(bsub, _BENCH_ORDER)
    return p


#: ``vigproc bench --help`` lists these first, in this order (the order users know);
#: the command modules' other benchmarks follow in their registration order.
_BENCH_ORDER = ("synthetic", "lensfun", "clean", "crops", "real", "speed", "scene-scatter", "learn", "io",
                "throughput", "scaling", "memory", "profile", "profile-clean", "profile-interp",
                "profile-flat", "colour", "correct")


def _list_in_order(subparsers, first: Sequence[str]) -> None:
    """Put the subcommands named in ``first`` at the head of ``subparsers``'s help and
    choices, in that order (module discovery registers them by module name)."""
    rank = {name: i for i, name in enumerate(first)}
    key = lambda name: rank.get(name, len(first))  # noqa: E731 - stable sort: the others keep their order
    subparsers._choices_actions.sort(key=lambda a: key(a.dest))  # noqa: SLF001 - argparse keeps its help rows there
    ordered = sorted(subparsers.choices, key=key)
    subparsers.choices.update({name: subparsers.choices.pop(name) for name in ordered})


class _OneLineFormatter(logging.Formatter):
    """Log messages quote file names: one line per message whatever a name holds
    (a traceback at -vv keeps its lines)."""

    def formatMessage(self, record: logging.LogRecord) -> str:
        return one_line(super().formatMessage(record))


@contextlib.contextmanager
def _terminate_like_ctrl_c():
    """SIGTERM (a service manager, ``kill``) stops a command as Ctrl-C does: running
    work is finished or cleaned up (temporary files removed) instead of the process
    vanishing mid-write.  Commands with their own handlers (``watch``) replace it; the
    previous handler is restored on the way out.  Yields a function telling whether
    SIGTERM arrived (exit 143 = 128 + SIGTERM)."""
    got: list[int] = []
    if threading.current_thread() is not threading.main_thread() \
            or signal.getsignal(signal.SIGTERM) is not signal.SIG_DFL:
        yield lambda: False
        return

    def on_term(signum, frame):
        got.append(signum)
        raise KeyboardInterrupt

    signal.signal(signal.SIGTERM, on_term)
    try:
        yield lambda: bool(got)
    finally:
        signal.signal(signal.SIGTERM, signal.SIG_DFL)


def main(argv: Sequence[str] | None = None) -> int:
    """Run ``vigproc ARGV`` (default ``sys.argv[1:]``); returns the exit code."""
    parser = build_parser()
    argv = list(sys.argv[1:] if argv is None else argv)
    args, extra = parser.parse_known_args(argv)
    args.argv = argv  # as run: a report an examiner files states its command line
    if extra:  # said by the command's own parser (its usage line), not the top level's
        _command_parser(parser, args).error(f"unrecognized arguments: {' '.join(extra)}")
    handler = logging.StreamHandler()  # the current sys.stderr (the hook server swaps it per call)
    handler.setFormatter(_OneLineFormatter("%(levelname)s %(name)s: %(message)s"))
    logging.basicConfig(level=logging.WARNING - 10 * min(args.verbose, 2), handlers=[handler], force=True)
    logging.captureWarnings(True)  # libraries' warnings as one log line each, not raw stderr text
    # Ctrl-C reaches the exiftool child too; the reader restarts it when needed, and the
    # "died" warning it gave on closing was noise (with a virtualenv path)
    warnings.filterwarnings("ignore", "ExifTool process was previously running but died", UserWarning)
    if getattr(args, "hook_call", False):
        from vigproc.frontends import hookserver  # hook calls only: sockets are no start-up cost of every command

        if hookserver.enabled() and not hookserver.serving():
            return _hook_via_server(args, argv, hookserver)
    with _terminate_like_ctrl_c() as terminated:
        return _run(args, terminated)


def _command_parser(parser: argparse.ArgumentParser, args: argparse.Namespace) -> argparse.ArgumentParser:
    """The (sub)parser of the command ``args`` are for: ``vigproc profile show``'s, say."""
    for action in parser._actions:  # noqa: SLF001 - argparse keeps its subcommands there
        if isinstance(action, argparse._SubParsersAction):  # noqa: SLF001
            name = getattr(args, action.dest, None)
            if name in action.choices:
                return _command_parser(action.choices[name], args)
    return parser


def _hook_via_server(args: argparse.Namespace, argv: list[str], hookserver) -> int:
    """A host's call: on the warm server when one runs (vigproc.frontends.hookserver), else here,
    starting one for the calls that follow."""
    stdin = None
    if args.request == "-":  # the server cannot read our stdin: pass its bytes (the hook's own limit)
        stdin = sys.stdin.buffer.read(MAX_REQUEST_BYTES + 1)
    code = hookserver.call(argv, stdin)
    if code is not None:
        return code
    if stdin is not None:
        sys.stdin = io.TextIOWrapper(io.BytesIO(stdin), encoding="utf-8")
    with _terminate_like_ctrl_c() as terminated:
        code = _run(args, terminated)
    hookserver.start_in_background()
    return code


def _run(args: argparse.Namespace, terminated) -> int:
    """Run the parsed command's handler: a typed error becomes one line and its exit code."""
    try:
        fn = _handler(args.fn) if isinstance(args.fn, str) else args.fn  # imported once, to run
        code = int(fn(args) or 0)
        return EXIT_CODES["terminated"] if terminated() and code == EXIT_CODES["interrupted"] else code
    except VigprocError as exc:
        print(one_line(f"vigproc: {exc}"), file=sys.stderr)
        return exc.exit_code
    except KeyboardInterrupt:
        print("vigproc: terminated" if terminated() else "vigproc: interrupted", file=sys.stderr)
        return EXIT_CODES["terminated" if terminated() else "interrupted"]
    except BrokenPipeError:  # output piped into e.g. head: nothing left to say
        sys.stderr.close()
        return 0
    except Exception as exc:  # a bug, not bad input: still no traceback unless asked (-vv)
        log.debug("internal error", exc_info=True)
        print(one_line(f"vigproc: internal error ({type(exc).__name__}: {exc}); rerun with -vv for details"),
              file=sys.stderr)
        return 70


if __name__ == "__main__":
    sys.exit(main())
