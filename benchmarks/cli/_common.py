"""What the ``vigproc bench`` commands (:mod:`benchmarks.cli`) share: their estimator
table, the ``--scene-prior`` setting, a few option groups, the JSON result file and the
printed tables (:class:`Table`)."""

from __future__ import annotations

import argparse
import json
from dataclasses import dataclass
from pathlib import Path

from vigproc.atomic import atomic_write_text
from vigproc.core.methods import METHODS
from vigproc.errors import PriorError
from vigproc.frontends.commands._options import add_transfer, number


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
                    help="rgs: the radial-gradient-symmetry peer (benchmarks/peers.py)")
    add_scene_prior(bp)
    bp.add_argument("--json", help="write the figures to this file")


def add_scene_prior(bp: argparse.ArgumentParser) -> None:
    """``--scene-prior``, read by :func:`scene_settings`."""
    bp.add_argument("--scene-prior", default="shipped", metavar="shipped|none|FILE",
                    help="scene prior of the default estimator: the shipped one (fitted on linearised "
                         "photos), none, or a file from 'vigproc prior fit-scene' (default: shipped)")


def add_clean_bases(bp: argparse.ArgumentParser) -> None:
    """The clean protocol's bases (:mod:`benchmarks.clean`), as the clean benchmarks take them."""
    bp.add_argument("--images", nargs="+", default=["../shared/data/jpeg_exif", "../shared/data/natural"],
                    help="folders of full-size camera frames (BSDS/Kodak are skipped: film scans)")
    bp.add_argument("--min-long-side", type=number(64, 10**6, integer=True), default=1000,
                    help="frames whose long side is shorter are not used (default %(default)s)")
    bp.add_argument("--limit", type=number(1, 10**6, integer=True), help="use at most this many frames")
    bp.add_argument("--grey", action="store_true",
                    help="give the estimators the bases' luminance only (as before session 12), not their colour")


def write_json_result(path: str | None, data: object) -> None:
    """A bench's figures as JSON at ``path`` (atomically; nothing when None)."""
    if path:
        atomic_write_text(Path(path), json.dumps(data, indent=1) + "\n")


# ------------------------------------------------------------------ printed tables
@dataclass(frozen=True)


class Table:
    """A printed table of fixed-width columns: its header line and its rows, each value
    formatted by its column's spec (what every bench prints).

    Parameters
    ----------
    columns : tuple of (str, str)
        Each column's title and format spec, e.g. ``("median EV", ">11.3f")``: the
        title takes the spec's alignment and width, a value the whole spec (a text
        value in a number column, such as ``"-"``, its alignment and width only).
    """

    columns: tuple[tuple[str, str], ...]

    @staticmethod
    def _width(spec: str) -> str:
        """The alignment and width of a format spec (``">11.3f"`` -> ``">11"``)."""
        head = spec[:1] if spec[:1] in "<>^" else ""
        digits = ""
        for ch in spec[len(head):]:
            if not ch.isdigit():
                break
            digits += ch
        return head + digits

    def header(self) -> str:
        """The line of the column titles."""
        return "".join(format(title, self._width(spec)) for title, spec in self.columns)

    def row(self, *values) -> str:
        """One row: ``values`` in column order."""
        if len(values) != len(self.columns):
            raise ValueError(f"{len(values)} values for {len(self.columns)} columns")
        return "".join(format(v, self._width(spec) if isinstance(v, str) else spec)
                       for v, (_, spec) in zip(values, self.columns))

    def print_rows(self, rows) -> None:
        """Print the header, then each row of ``rows`` (sequences of values), flushed."""
        print(self.header())
        for values in rows:
            print(self.row(*values), flush=True)
