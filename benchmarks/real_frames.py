"""Harm on real full frames (``vigproc bench real-frames``).

Every full-size camera JPEG of the given folders (long side at least
``min_long_side``) goes through the default correction exactly as ``vigproc
correct`` runs it (:class:`vigproc.pipeline.processor.Processor`, ``--profile
estimate``: no profile store), once with the harm rules off (no plausibility gate,
``--in-camera ignore``: what vigproc did before them) and once with them on. Counted
over the fields that were applied:

* corners brighter than the field's centre (> 0.02 EV, :func:`vigproc.core.plausible.corner_ev`);
* a corner fall-off beyond lensfun's real lenses of the frame's focal length and
  f-number plus the margin (:func:`vigproc.core.plausible.population_max_ev`);
* a fit stating a confidence below 0.5;
* the share of the frame's pixels newly pushed past white (on the whole frame as
  written: below 1.0 before, at 1.0 after the clipping of the 8-bit output);
* on frames whose camera corrected the vignetting (:mod:`vigproc.io.incamera`), the
  corner fall-off removed, in absolute value (a field with brighter corners darkens
  them; 0 when nothing was applied).

These frames carry no known truth: the counts say where a field is implausible,
not how far from the truth a plausible one is (``vigproc bench clean`` measures that).
"""

from __future__ import annotations

import logging
import math
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Iterable, Sequence

import numpy as np

from vigproc.io.formats import READ_SUFFIXES

log = logging.getLogger(__name__)

#: Suffixes of the frames taken.
JPEG_SUFFIXES = READ_SUFFIXES["jpeg"]


@dataclass(frozen=True)
class FrameRow:
    """One frame through the default correction."""

    file: str
    camera: str
    in_camera: str | None  # the evidence the camera corrected it, or None
    applied: bool
    method: str | None
    rule: str | None  # the rule that stopped the correction (sidecar ``not_applied_rule``)
    confidence: float  # of the applied fit (NaN when none was applied or none stated)
    brightest_ev: float  # brightest corner over the field's centre (applied field)
    removed_ev: float  # corner fall-off removed (0 when nothing was applied)
    population_ev: float  # the real-lens bound with its margin
    new_white: float  # share of pixels newly pushed past white
    seconds: float


@dataclass(frozen=True)
class Counts:
    """The harm counts of one run over all frames."""

    rules: bool
    frames: int
    applied: int
    brighter_corners: int
    beyond_population: int
    below_confidence: int
    new_white_max: float
    new_white_median: float
    over_1ev: int  # frames with more than 1 EV removed at a corner
    in_camera_frames: int
    in_camera_removed_median: float
    in_camera_removed_max: float
    rows: list[FrameRow] = field(default_factory=list)


def full_frames(folders: Iterable[str | Path], min_long_side: int = 1000, limit: int | None = None) -> list[Path]:
    """The JPEG files under ``folders`` whose long side is at least ``min_long_side``
    (the size read from the file's header), sorted by path."""
    import OpenImageIO as oiio

    def read_header(p: Path) -> tuple[int, int]:
        inp = oiio.ImageInput.open(str(p))
        if inp is None:
            raise OSError(oiio.geterror())
        try:
            return inp.spec().width, inp.spec().height
        finally:
            inp.close()

    out = []
    for folder in folders:
        for p in sorted(Path(folder).rglob("*")):
            if not (p.is_file() and p.suffix.lower() in JPEG_SUFFIXES):
                continue
            try:
                w, h = read_header(p)
            except Exception as exc:  # noqa: BLE001 - an unreadable file is no frame of the bench
                log.debug("skipping %s: %s", p, exc)
                continue
            if max(w, h) >= min_long_side:
                out.append(p)
    return out[:limit] if limit else out


def _row(path: Path, proc, rules) -> FrameRow:
    from vigproc.core.plausible import corner_ev, population_max_ev
    from vigproc.io.images import EncodedImage
    from vigproc.io.incamera import read_in_camera
    from vigproc.pipeline.processor import output_format_for

    t0 = time.perf_counter()
    # the path process_file takes, without writing the output; the frame as read is kept
    # beside its correction (not corrected in place) to count the pixels pushed past white
    out, res, img, _info, _fmt = proc._process_path(path, None, lambda info: output_format_for("auto", path, info),
                                                    consume=False)
    m = res.model
    key = (res.lens or {}).get("key") or {}
    camera = " ".join(str(key.get(k) or "") for k in ("make", "model")).strip() or "?"
    ic = read_in_camera(path, proc.reader)
    brightest = removed = 0.0
    conf = math.nan
    # an identity model "applied" divides nothing out (a fit with nothing to say)
    applied = bool(res.applied) and m is not None and not m.is_identity
    if applied:
        brightest, removed = corner_ev(m)
        if m.quality is not None:
            conf = m.quality.confidence
    # a JPEG's codes (vigproc.pipeline.encoded) as the light they decode to
    img, out = (x.linear() if isinstance(x, EncodedImage) else x for x in (img, out))
    before = img.max(axis=-1) if img.ndim == 3 else img
    after = out.max(axis=-1) if out.ndim == 3 else out
    white = float(np.count_nonzero((before < 1.0) & (after >= 1.0))) / before.size
    return FrameRow(
        file=path.name, camera=camera, in_camera=ic.evidence if ic else None, applied=applied,
        method=getattr(m.candidate or m, "method", None) if m is not None else None,
        rule=res.extra.get("not_applied_rule"), confidence=conf, brightest_ev=brightest, removed_ev=removed,
        population_ev=population_max_ev(key.get("focal_35mm"), key.get("fnumber"), rules.neighbours) + rules.margin_ev,
        new_white=white, seconds=time.perf_counter() - t0)


def run(files: Sequence[Path], *, rules_on: bool) -> Counts:
    """The default correction of every file, with the harm rules on or off.

    Returns
    -------
    Counts
    """
    from vigproc.core.plausible import Rules
    from vigproc.pipeline.processor import Processor, Settings

    rules = Rules()
    settings = Settings(mode="correct", profile="estimate", in_camera="respect" if rules_on else "ignore")
    rows = []
    with Processor(settings, plausibility=rules_on) as proc:
        for p in files:
            try:
                rows.append(_row(p, proc, rules))
            except Exception as exc:  # noqa: BLE001 - a frame that fails is reported, not counted
                log.warning("%s: %s", p, exc)
    applied = [r for r in rows if r.applied]
    ic = [abs(r.removed_ev) for r in rows if r.in_camera]  # corners darkened count as harm too
    white = [r.new_white for r in rows] or [0.0]
    return Counts(
        rules=rules_on, frames=len(rows), applied=len(applied),
        brighter_corners=sum(r.brightest_ev > rules.corner_tolerance_ev for r in applied),
        beyond_population=sum(r.removed_ev > r.population_ev for r in applied),
        below_confidence=sum(r.confidence < rules.min_confidence for r in applied if math.isfinite(r.confidence)),
        new_white_max=float(np.max(white)), new_white_median=float(np.median(white)),
        over_1ev=sum(r.removed_ev > 1.0 for r in applied), in_camera_frames=len(ic),
        in_camera_removed_median=float(np.median(ic)) if ic else math.nan,
        in_camera_removed_max=float(np.max(ic)) if ic else math.nan, rows=rows)


def as_dict(c: Counts) -> dict:
    """JSON-able figures of a run."""
    return asdict(c)
