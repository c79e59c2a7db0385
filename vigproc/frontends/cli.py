"""The ``vigproc`` command line: the table of commands and the dispatch.

Every user-facing failure is a :class:`~vigproc.errors.VigprocError` turned into one
line on stderr and its exit code; no traceback reaches the user.

The commands are declared in :data:`COMMANDS`: each one's summary and the function that
declares its arguments. ``vigproc --help`` lists them without building any; a command's
parser is built when it runs or its help is asked for (start-up is paid on every call a
host makes). The handlers live in :mod:`vigproc.frontends.commands`, imported when their
command runs.
"""

from __future__ import annotations

import argparse
import atexit
import contextlib
import io
import logging
import os
import signal
import sys
import threading
import warnings
from typing import Sequence

from vigproc.errors import EXIT_CODES, VigprocError, one_line
from vigproc.frontends.commands._subcommands import Command, add_commands, chosen_command, command_parser, resolve

log = logging.getLogger("vigproc")

#: The package the :data:`COMMANDS` specs and the ``"module:function"`` handlers are in.
COMMANDS_PACKAGE = "vigproc.frontends.commands"

#: Every command, in the order ``vigproc --help`` lists them: its summary and the
#: ``"module:function"`` (in :data:`COMMANDS_PACKAGE`) declaring its arguments and handler.
COMMANDS: dict[str, Command] = {
    "estimate": Command("estimate the vignetting of images (nothing is written)", "_parsers:estimate"),
    "correct": Command("remove vignetting: a stored profile of the lens, else an estimate (each input's own "
                       "format back by default)", "_parsers:correct"),
    "demo": Command("correct the bundled sample images (the README's first command)", "_parsers:demo"),
    "batch": Command("process a whole archive (folder or file list), resumable, on local cores or a Dask cluster",
                     "batch:add_arguments"),
    "check": Command("forensics: does each frame's vignetting match the lens its EXIF names?",
                     "check:add_arguments"),
    "forensics": Command("lens identification from vignetting (Lyu 2010 Fig. 6) and the calibration of "
                         "'vigproc check'", "forensics:add_arguments"),
    "hook": Command("for host programs: process files, answer JSON on stdout (stable exit codes)",
                    "hook:add_arguments"),
    "plugins": Command("list installed extensions (estimators, profile sources)", "plugins:add_arguments"),
    "watch": Command("watch a folder: process every complete image dropped into it, exactly once",
                     "watch:add_arguments"),
    "profile": Command("the per-lens profile store", "_parsers:profile"),
    "prior": Command("natural-image prior of the paper's method", "_parsers:prior"),
    "bench": Command("benchmarks (print measured figures; from a source checkout)", "_bench:add_arguments",
                     add_help=False),  # its --help lists the checkout's benchmarks
}

#: Commands run by :func:`run` as a program of their own: their process ends without the
#: interpreter's teardown once :func:`main` has returned (they finish what they open
#: themselves: outputs renamed into place, exiftool closed, thread pools shut down; the
#: teardown, the garbage collector's passes over what Numba loaded, cost 0.15-0.3 s after
#: the last output), and their idle OpenMP workers sleep (:data:`OMP_WAIT`).
QUICK_EXIT_COMMANDS = frozenset({"correct", "demo"})
#: The OpenMP wait policy of :data:`QUICK_EXIT_COMMANDS` unless the environment sets one:
#: passive, so that Numba's idle workers sleep instead of spinning between parallel
#: kernels; the command's own threads (reading ahead, writing behind) want those cores.
OMP_WAIT = ("OMP_WAIT_POLICY", "PASSIVE")


# ------------------------------------------------------------------ parser
def build_parser(argv: Sequence[str] | None = None) -> argparse.ArgumentParser:
    """The ``vigproc`` parser.

    A command's handler is its ``fn`` default: a function, or ``"module:function"`` in
    :data:`COMMANDS_PACKAGE`, imported when it runs.

    Parameters
    ----------
    argv : sequence of str, optional
        A command line (without the program's name): only the command it names gets its
        arguments; the others are listed by name and summary. None: every command is
        built (what a test or a documentation tool walks).

    Returns
    -------
    argparse.ArgumentParser
    """
    p = argparse.ArgumentParser(prog="vigproc", description="Lens vignetting: estimate, correct, learn, check.")
    p.add_argument("-v", "--verbose", action="count", default=0,
                   help="more log output (-v: info, -vv: debug and tracebacks)")
    sub = p.add_subparsers(dest="command", required=True)
    add_commands(sub, COMMANDS, COMMANDS_PACKAGE, COMMANDS.keys() if argv is None else {chosen_command(argv)})
    return p


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
    argv = list(sys.argv[1:] if argv is None else argv)
    parser = build_parser(argv)
    args, extra = parser.parse_known_args(argv)
    args.argv = argv  # as run: a report an examiner files states its command line
    if extra:  # said by the command's own parser (its usage line), not the top level's
        command_parser(parser, args).error(f"unrecognized arguments: {' '.join(extra)}")
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


def _hook_via_server(args: argparse.Namespace, argv: list[str], hookserver) -> int:
    """A host's call: on the warm server when one runs (vigproc.frontends.hookserver), else here,
    starting one for the calls that follow."""
    from vigproc.frontends.commands.hook import MAX_REQUEST_BYTES  # loaded already: it declared this command

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
        fn = resolve(args.fn, COMMANDS_PACKAGE) if isinstance(args.fn, str) else args.fn  # imported once, to run
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


def run() -> int:
    """The ``vigproc`` program (its console script, ``python -m vigproc``): :func:`main`
    on ``sys.argv``; a command of :data:`QUICK_EXIT_COMMANDS` runs with :data:`OMP_WAIT`
    and then ends the process at once (:func:`_quick_exit`). Returns the exit code when
    the process goes on."""
    argv = sys.argv[1:]
    quick = chosen_command(argv) in QUICK_EXIT_COMMANDS
    if quick:  # read by OpenMP when Numba first loads it, later
        os.environ.setdefault(*OMP_WAIT)
    code = main(argv)
    if quick:
        _quick_exit(code)
    return code


def _flushed() -> bool:
    """Flush Python's stdout and stderr; False when one cannot be (a closed pipe: the
    interpreter's own exit reports it as it always does)."""
    try:
        for stream in (sys.stdout, sys.stderr):
            if stream is not None and not stream.closed:
                stream.flush()
    except (OSError, ValueError):
        return False
    return True


def _quick_exit(code: int) -> None:
    """End the process with ``code`` as the interpreter's exit would, without its
    teardown (module clean-up and the garbage collector's passes, which free memory the
    process's end frees anyway).

    What the interpreter's exit does that matters is done first, in its order: no thread
    that is not a daemon may still run (the exit would wait for it), then the ``atexit``
    callbacks run (``logging.shutdown``, the shared exiftool's close, ``weakref.finalize``
    clean-ups), then Python's and C's standard streams are flushed. Returns, leaving the
    exit to the interpreter, when a thread still runs, a stream cannot be flushed, or
    this Python has no ``atexit._run_exitfuncs``.
    """
    run_exitfuncs = getattr(atexit, "_run_exitfuncs", None)
    if os.name != "posix" or run_exitfuncs is None:
        return
    if any(t.is_alive() and not t.daemon for t in threading.enumerate() if t is not threading.main_thread()):
        return
    run_exitfuncs()
    if not _flushed():
        return
    import ctypes  # loaded already (Numba): C's own buffered output, e.g. a codec's messages

    ctypes.CDLL(None).fflush(None)
    os._exit(code)


if __name__ == "__main__":
    sys.exit(run())
