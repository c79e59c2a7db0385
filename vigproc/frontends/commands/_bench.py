"""What the ``vigproc bench`` command modules (``bench_*.py``) share: their estimator
table, the ``--scene-prior`` setting and a few option groups. No command of its own
(a leading underscore: command discovery passes it by)."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from vigproc.core.methods import METHODS
from vigproc.errors import PriorError
from vigproc.frontends.commands._options import add_transfer


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
        from benchmarks.peers import estimate_rgs

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
                    help="rgs: the radial-gradient-symmetry peer (benchmarks.peers)")
    add_scene_prior(bp)
    bp.add_argument("--json", help="write the figures to this file")


def add_scene_prior(bp: argparse.ArgumentParser) -> None:
    """``--scene-prior``, read by :func:`scene_settings`."""
    bp.add_argument("--scene-prior", default="shipped", metavar="shipped|none|FILE",
                    help="scene prior of the default estimator: the shipped one (fitted on linearised "
                         "photos), none, or a file from 'vigproc prior fit-scene' (default: shipped)")
