"""Learn as you go, end to end: a series of one lens setting through ``vigproc batch``.

Frames are clean bases (:func:`benchmarks.clean.load_clean_bases`: central crops of
camera frames and linear natural images, 480×320, colour) multiplied by a lensfun lens's
"pa" field (:func:`benchmarks.clean.lens_fields`), written as linear 16-bit TIFFs
with the lens's EXIF (camera, lens name, focal length, f-number; one exiftool call), and
run through ``vigproc batch --mode correct`` (learning as it goes by default) into a
fresh profile store. Frames of one series were taken :data:`FRAME_STEP_S` apart
(``DateTimeOriginal``); with several series of the lens, each is a day after the one
before and goes through its own ``vigproc batch`` run into the same store (the next
shoot: :data:`vigproc.pipeline.learning.SERIES_GAP_S`). Each frame's record says what corrected it (its own estimate, or
the stored profile and which revision of it) and what its pooling did; the field each
frame was corrected with is compared with the lens's field (gain-free RMS, EV, as the
clean protocol measures: :func:`benchmarks.clean.gain_free_ev`).
"""

from __future__ import annotations

import json
import math
import shutil
import subprocess
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Sequence

import numpy as np

#: The camera the frames claim: unknown to lensfun, with its lens named (so it pools).
CAMERA = ("Vigproc", "Series 1")
#: Seconds between the capture times of two frames of a series.
FRAME_STEP_S = 30


@dataclass
class FrameRow:
    """One frame of the series, in the order its pooling reached the store."""

    name: str
    pooled_as: int | None  # the profile's frame count after this frame was pooled
    trusted_after: bool | None
    source: str
    applied: bool
    revision: int | None  # frames of the profile revision that corrected it (stored-profile)
    revision_id: str | None  # the store's applied revision that corrected it (stored-profile)
    error_ev: float  # applied field vs the lens's, gain-free RMS
    seconds: float
    alone_ev: float = math.nan  # the frame's own estimate vs the lens's (= error_ev unless the profile was chosen)


@dataclass
class SeriesResult:
    lens: str
    series: int  # 1 for the first series of the lens, 2 for the next (a day later), ...
    frames: int
    workers: int
    trusted_at: int | None  # the pooled-frame count at which the profile became trusted
    before_median_ev: float  # frames corrected by their own estimate
    after_median_ev: float  # frames corrected by the stored profile
    after_max_ev: float
    revisions: list[int]  # distinct profile revisions applied after trust
    revision_spread_ev: float  # largest RMS difference between two fields applied after trust
    revision_ids: int  # distinct applied revisions (ids) after trust
    switches: int  # field changes between consecutive frames after trust, in pooling order
    same_revision_spread_ev: float  # largest RMS difference between two fields of one revision id
    uncorrected_ev: float
    wall_s: float
    rows: list[FrameRow] = field(default_factory=list)
    before_alone_median_ev: float = math.nan  # the same frames' own estimates
    evidence_frames: int = 0  # frames before trust corrected by the profile so far (profile-evidence)
    profile_frames: int | None = None  # frames in the stored profile after the series



def write_series(folder: Path, bases: Sequence[np.ndarray], log_field: np.ndarray, *, lens: str,
                 focal_mm: float, fnumber: float, focal35: float | None, day: int = 0) -> list[Path]:
    """The bases × the field as linear 16-bit TIFFs in ``folder``, with the lens's EXIF,
    taken :data:`FRAME_STEP_S` apart on day ``day`` of the bench's calendar.

    Raises
    ------
    VigprocError
        exiftool is missing.
    """
    from vigproc.errors import VigprocError
    from vigproc.io.images import write_image

    exiftool = shutil.which("exiftool")
    if exiftool is None:
        raise VigprocError("the series needs exiftool to write its EXIF")
    folder.mkdir(parents=True, exist_ok=True)
    gain = np.exp(log_field)[..., None]
    files = []
    for i, b in enumerate(bases):
        p = folder / f"series{i:03d}.tif"
        write_image(p, np.clip(0.8 * b * gain, 0.0, 1.0).astype(np.float32), bit_depth="uint16")
        files.append(p)
    tags = [f"-Make={CAMERA[0]}", f"-Model={CAMERA[1]}", f"-LensModel={lens}", f"-FocalLength={focal_mm:g}",
            f"-FNumber={fnumber:g}"]
    if focal35:
        tags.append(f"-FocalLengthIn35mmFormat={round(focal35)}")
    subprocess.run([exiftool, "-q", "-overwrite_original", *tags, "--", *map(str, files)], check=True,
                   capture_output=True)
    t0 = time.mktime((2026, 6, 1 + day, 10, 0, 0, 0, 0, 0))
    for i, p in enumerate(files):  # one shoot: a frame every FRAME_STEP_S seconds
        stamp = time.strftime("%Y:%m:%d %H:%M:%S", time.localtime(t0 + i * FRAME_STEP_S))
        subprocess.run([exiftool, "-q", "-overwrite_original", f"-DateTimeOriginal={stamp}", "--", str(p)],
                       check=True, capture_output=True)
    return files


def _log2_field(rec: dict) -> np.ndarray:
    from vigproc.core.model import VignettingModel

    m = VignettingModel.from_dict(rec["model"])
    if not rec.get("applied"):
        return np.zeros((m.height, m.width))
    return m.log_field((m.height, m.width)) / math.log(2.0)


def _own_field(rec: dict) -> np.ndarray | None:
    """The log2 field of the frame's own estimate when the profile so far was applied instead."""
    from vigproc.core.model import VignettingModel

    own = (rec.get("profile_evidence") or {}).get("own")
    if own is None:
        return None
    m = VignettingModel.from_dict(own)
    if m.candidate is not None:  # too weak to apply alone: nothing would have been applied
        return np.zeros((m.height, m.width))
    return m.log_field((m.height, m.width)) / math.log(2.0)


def run_series(bases: Sequence[np.ndarray], log_field: np.ndarray, *, lens: str, focal_mm: float, fnumber: float,
               focal35: float | None, workers: int = 2, tmp: Path | None = None,
               series: int = 1) -> list[SeriesResult]:
    """Write ``series`` series of the bases (split evenly, a day apart), run each through
    ``vigproc batch --mode correct`` into one store, and read their records.

    Raises
    ------
    VigprocError
        The batch run failed.
    """
    import os
    import tempfile

    from benchmarks.clean import gain_free_ev
    from vigproc.errors import VigprocError
    from vigproc.stores.profiles import ProfileStore

    root = Path(tempfile.mkdtemp(prefix="vigproc-learn-series-", dir=tmp))
    per = len(bases) // series
    results = []
    try:
        for k in range(series):
            part = root / f"s{k + 1}"
            files = write_series(part / "in", bases[k * per:(k + 1) * per], log_field, lens=lens, focal_mm=focal_mm,
                                 fnumber=fnumber, focal35=focal35, day=k)
            cmd = [sys.executable, "-m", "vigproc.frontends.cli", "batch", str(part / "in"), "--mode", "correct",
                   "-o", str(part / "out"), "--workers", str(workers), "--profile-db", str(root / "profiles.sqlite"),
                   "--output-format", "tiff16", "--no-progress", "--json"]
            t0 = time.perf_counter()
            r = subprocess.run(cmd, capture_output=True, text=True, env=dict(os.environ))
            wall = time.perf_counter() - t0
            if r.returncode != 0:
                raise VigprocError(f"vigproc batch failed ({r.returncode}): {r.stderr[-2000:]}")
            with ProfileStore(root / "profiles.sqlite") as store:
                n_profile = max((p.n_frames for p in store.list()), default=None)
            results.append(_read_series(part, files, log_field, lens=lens, workers=workers, wall=wall,
                                        index=k + 1, profile_frames=n_profile, gain_free_ev=gain_free_ev))
    finally:
        shutil.rmtree(root, ignore_errors=True)
    return results


def _read_series(part: Path, files: list[Path], log_field: np.ndarray, *, lens: str, workers: int, wall: float,
                 index: int, profile_frames: int | None, gain_free_ev) -> SeriesResult:
    truth = log_field / math.log(2.0)
    rows, fields = [], {}
    for f in files:
        rec = json.loads((part / "out" / f"{f.name}.vigproc.json").read_text())
        learned = rec.get("learned") or {}
        used = rec.get("profile_applied") or {}
        lf = _log2_field(rec)
        fields[f.name] = lf
        own = _own_field(rec)
        err = gain_free_ev((lf - truth) * math.log(2.0))
        rows.append(FrameRow(f.name, learned.get("frames") if learned.get("pooled") else None,
                             learned.get("trusted"), rec["source"], bool(rec.get("applied")), used.get("frames"),
                             used.get("revision"), err, float(rec.get("seconds", math.nan)),
                             err if own is None else gain_free_ev((own - truth) * math.log(2.0))))
    rows.sort(key=lambda x: (x.pooled_as is None, x.pooled_as or 0))
    trusted = [x.pooled_as for x in rows if x.trusted_after and x.pooled_as is not None]
    before = [x for x in rows if x.source != "stored-profile"]
    after = [x for x in rows if x.source == "stored-profile"]
    spread = same = 0.0
    for i, a in enumerate(after):
        for b in after[i + 1:]:
            d = float(np.sqrt(np.mean((fields[a.name] - fields[b.name]) ** 2)))
            spread = max(spread, d)
            if a.revision_id is not None and a.revision_id == b.revision_id:
                same = max(same, d)
    order = [x.revision_id for x in after if x.pooled_as is not None] + [
        x.revision_id for x in after if x.pooled_as is None]
    med = (lambda xs: float(np.median(xs)) if xs else math.nan)
    return SeriesResult(
        lens=lens, series=index, frames=len(rows), workers=workers, trusted_at=min(trusted) if trusted else None,
        before_median_ev=med([x.error_ev for x in before]),
        after_median_ev=med([x.error_ev for x in after]),
        after_max_ev=max((x.error_ev for x in after), default=math.nan),
        revisions=sorted({x.revision for x in after if x.revision is not None}), revision_spread_ev=spread,
        revision_ids=len({x.revision_id for x in after}), switches=sum(a != b for a, b in zip(order, order[1:])),
        same_revision_spread_ev=same,
        uncorrected_ev=gain_free_ev(log_field), wall_s=wall, rows=rows,
        before_alone_median_ev=med([x.alone_ev for x in before]),
        evidence_frames=sum(x.source == "profile-evidence" for x in rows), profile_frames=profile_frames)
