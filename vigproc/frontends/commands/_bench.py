"""``vigproc bench [--benchmarks-dir DIR] NAME [OPTIONS]``: the thin entry to the
benchmarks. It finds them (:func:`benchmarks_dir`) and hands ``NAME [OPTIONS]`` to their
own command line, :func:`benchmarks.cli.main`, which parses, runs and prints.

The benchmarks (their protocols and their commands) are not part of the installed package: they live in the
repository's top-level ``benchmarks/`` folder, beside ``vigproc/`` in a source checkout.
``vigproc bench`` finds them there, or where ``--benchmarks-dir`` or
``$VIGPROC_BENCHMARKS`` says, and otherwise stops with
:class:`~vigproc.errors.BenchmarksNotFoundError`.
"""

from __future__ import annotations

import argparse
import importlib
import os
import sys
from pathlib import Path
from types import ModuleType

from vigproc.errors import BenchmarksNotFoundError

#: Environment variable naming the ``benchmarks`` folder (or the checkout holding it).
BENCHMARKS_ENV = "VIGPROC_BENCHMARKS"
#: The folder beside the package in a source checkout (vigproc/frontends/commands/ -> root).
CHECKOUT_BENCHMARKS = Path(__file__).resolve().parents[3] / "benchmarks"

_chosen: list[Path] = []  # --benchmarks-dir, as parsed (the last one wins)


class _BenchmarksDir(argparse.Action):
    """``--benchmarks-dir``: remembered for :func:`benchmarks_dir` (the handlers reach the
    benchmarks from helpers that do not see ``args``)."""

    def __call__(self, parser, namespace, values, option_string=None):
        setattr(namespace, self.dest, values)
        _chosen.append(Path(values))


def add_benchmarks_dir(bp: argparse.ArgumentParser) -> None:
    """``vigproc bench --benchmarks-dir DIR``."""
    bp.add_argument("--benchmarks-dir", action=_BenchmarksDir, metavar="DIR",
                    help=f"the benchmarks/ folder of a vigproc source checkout, or the checkout (default: "
                         f"${BENCHMARKS_ENV}, else the one beside the package)")


def _as_benchmarks(folder: Path) -> Path | None:
    """``folder`` if it is a benchmarks package, else its ``benchmarks/`` if that is one."""
    for d in (folder, folder / "benchmarks"):
        if d.name == "benchmarks" and (d / "__init__.py").is_file():
            return d.resolve()
    return None


def benchmarks_dir() -> Path:
    """The ``benchmarks/`` folder ``vigproc bench`` runs: ``--benchmarks-dir``, else
    ``$VIGPROC_BENCHMARKS``, else the one beside the package in a source checkout.

    Returns
    -------
    Path
        A folder named ``benchmarks`` holding an ``__init__.py``.

    Raises
    ------
    BenchmarksNotFoundError
        The folder asked for is not one, or none was asked for and the package is an
        installed copy (no ``benchmarks/`` beside it).
    """
    asked = _chosen[-1] if _chosen else (Path(os.environ[BENCHMARKS_ENV]) if os.environ.get(BENCHMARKS_ENV) else None)
    if asked is not None:
        found = _as_benchmarks(asked)
        if found is None:
            raise BenchmarksNotFoundError(f"{str(asked)!r} is neither a vigproc benchmarks/ folder nor a checkout "
                                          "holding one")
        return found
    found = _as_benchmarks(CHECKOUT_BENCHMARKS)
    if found is None:
        raise BenchmarksNotFoundError(
            "the benchmarks are not installed with vigproc: run 'vigproc bench' from a source checkout "
            f"(git clone), or point --benchmarks-dir or ${BENCHMARKS_ENV} at its benchmarks/ folder")
    return found


def benchmark(name: str) -> ModuleType:
    """The benchmark module ``benchmarks.<name>`` of :func:`benchmarks_dir`.

    Its parent folder is put on ``sys.path`` (after what is there, so the vigproc already
    imported stays the one used).

    Raises
    ------
    BenchmarksNotFoundError
        No benchmarks folder, or another package named ``benchmarks`` is imported.
    """
    folder = benchmarks_dir()
    loaded = sys.modules.get("benchmarks")
    if loaded is None:
        root = str(folder.parent)
        if root not in sys.path:
            sys.path.append(root)
        importlib.invalidate_caches()
        loaded = importlib.import_module("benchmarks")
    where = Path(getattr(loaded, "__file__", None) or "").resolve().parent
    if where != folder:
        raise BenchmarksNotFoundError(f"the package 'benchmarks' imported is {str(where)!r}, not vigproc's "
                                      f"{str(folder)!r}")
    return importlib.import_module(f"benchmarks.{name}")


def add_arguments(sp: argparse.ArgumentParser) -> None:
    """``vigproc bench``'s own arguments: where the benchmarks are, and what it hands on."""
    sp.description = ("Run a benchmark of a vigproc source checkout (its benchmarks/ folder, not installed with "
                      "vigproc); 'vigproc bench --help' lists them, 'vigproc bench NAME --help' gives a "
                      "benchmark's options.")
    sp.add_argument("-h", "--help", action="store_true", help="list the benchmarks (or NAME's options)")
    add_benchmarks_dir(sp)
    sp.add_argument("bench_argv", nargs=argparse.REMAINDER, metavar="NAME [OPTIONS]",
                    help="the benchmark and its options, handed to it")
    sp.set_defaults(fn=cmd_bench)


def cmd_bench(args: argparse.Namespace) -> int:
    """Run ``vigproc bench NAME [OPTIONS]``: the checkout's :func:`benchmarks.cli.main`.

    Returns
    -------
    int
        The benchmark's exit code (a usage error exits 2 from its parser).

    Raises
    ------
    BenchmarksNotFoundError
        No benchmarks folder (an installed copy), or not the one asked for.
    """
    argv = list(args.bench_argv)
    if args.help:
        argv.append("--help")
    return int(benchmark("cli").main(argv) or 0)
