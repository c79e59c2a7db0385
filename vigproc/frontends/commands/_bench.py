"""What the ``vigproc bench`` command modules (``bench_*.py``) share: where the
benchmarks are (:func:`benchmark`), their estimator table, the ``--scene-prior`` setting
and a few option groups. No command of its own (a leading underscore: command discovery
passes it by).

The benchmark protocols are not part of the installed package: they live in the
repository's top-level ``benchmarks/`` folder, beside ``vigproc/`` in a source checkout.
``vigproc bench`` finds them there, or where ``--benchmarks-dir`` or
``$VIGPROC_BENCHMARKS`` says, and otherwise stops with
:class:`~vigproc.errors.BenchmarksNotFoundError`.
"""

from __future__ import annotations

import argparse
import importlib
import json
import os
import sys
from pathlib import Path
from types import ModuleType

from vigproc.core.methods import METHODS
from vigproc.errors import BenchmarksNotFoundError, PriorError
from vigproc.frontends.commands._options import add_transfer

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


def scene_settings(spec: str):
    """RobustSettings for a bench's ``--scene-prior``: "shipped", "none" or a file
    written by ``vigproc prior fit-scene``."""
    from vigproc.core.robust import RobustSettings
    from vigproc.core.scene import SceneFalloff

    if spec == "shipped":
        return RobustSettings()
    if spec == "none":
        return RobustSettings(scene_prior=False)
    try:
        text = Path(spec).read_text()
    except OSError as exc:
        raise PriorError(f"cannot read the scene prior {spec!r}: {exc.strerror or exc}") from exc
    try:
        data = json.loads(text)
    except (json.JSONDecodeError, RecursionError) as exc:  # RecursionError: absurdly nested
        raise PriorError(f"the scene prior {spec!r} is not JSON: {exc}") from exc
    try:
        return RobustSettings(scene=SceneFalloff.from_dict(data))
    except PriorError as exc:
        raise PriorError(f"{spec!r}: {exc}") from exc


def estimator(method: str, seed: int = 0, settings=None, family=None):
    """A bench's estimator: ``vigproc.estimate`` on a frame (H×W grey, or H×W×3 with
    channels last), or the "rgs" peer (on its luminance).

    ``settings`` (``--scene-prior``) tune the robust Kang-Weiss estimators; the
    default and lens-family estimators have no scene prior. ``family``: the lens
    family they fit in (a bench whose fields are lensfun lenses leaves them out); they
    also take ``hint=`` (EXIF's focal length and f-number).
    """
    from vigproc.core.estimate import HINT_METHODS, estimate, estimate_checked
    from vigproc.core.pixels import luminance

    if method == "rgs":
        estimate_rgs = benchmark("peers").estimate_rgs
        return lambda v: estimate_rgs(luminance(v))
    if method in HINT_METHODS:
        # the product's own path (clipped highlights masked, colour read), in ``family``; a
        # bench's frames are float, channels last: what check_image would hand on
        return lambda v, hint=None: estimate_checked(v, method, hint=hint, family=family)
    return lambda v: estimate(v, method, channel_axis=-1 if v.ndim == 3 else None, seed=seed, settings=settings)


def add_colour(bp: argparse.ArgumentParser) -> None:
    """``--colour``: the benches' estimators see R, G, B."""
    bp.add_argument("--colour", action="store_true",
                    help="give the estimators the images' R, G, B (the paper's protocol is grey: its luminance)")


def add_estimator_bench(bp: argparse.ArgumentParser) -> None:
    """Options of a benchmark that runs estimators on photographs (lensfun, real)."""
    add_transfer(bp)
    bp.add_argument("--methods", nargs="+", default=["default"], choices=[*METHODS, "rgs"],
                    help="rgs: the radial-gradient-symmetry peer (benchmarks/peers.py)")
    add_scene_prior(bp)
    bp.add_argument("--json", help="write the figures to this file")


def add_scene_prior(bp: argparse.ArgumentParser) -> None:
    """``--scene-prior``, read by :func:`scene_settings`."""
    bp.add_argument("--scene-prior", default="shipped", metavar="shipped|none|FILE",
                    help="scene prior of the default estimator: the shipped one (fitted on linearised "
                         "photos), none, or a file from 'vigproc prior fit-scene' (default: shipped)")
