"""Real full frames whose lens lensfun calibrated (``vigproc bench real-frames``, part a).

**One frame.** Each full-size camera JPEG whose EXIF names a lens lensfun holds a
``pa`` vignetting calibration for (:func:`vigproc.stores.lensfun_match.match_lens`, as
``correct --profile lensfun`` finds it) goes through the default correction as
``vigproc correct`` runs it (``--profile estimate``, the harm rules on). Its truth is
lensfun's field at the frame's focal length, f-number and focus distance
(:func:`vigproc.stores.lensfun.interpolate_pa`), with the corner at
ρ = calibration crop / camera crop (lensfun's own rule for another sensor size).
Error: the RMS over the frame of log2(φ̂/φ) about its mean, in EV (``bench clean``'s
metric, :func:`benchmarks.clean.gain_free_ev`): of the field applied (the identity when
the gate left the frame alone) and of the estimator's candidate fit before the gate.
The estimate's lens-family prior is lensfun's population without the lenses measured
(:func:`without_lenses`), as in ``bench clean`` and the series: the shipped family holds
their own calibrations.

The truth holds only where the JPEG still carries the lens's fall-off: not where the
camera corrected it (:mod:`vigproc.io.incamera`: a maker-note flag on, a phone), nor where
a raw converter wrote the JPEG with its own lens correction (XMP ``LensProfileEnable``),
nor where the frame was cropped (its aspect is not the camera's ``RelatedImageWidth`` ×
``RelatedImageHeight``: centre and corner are no longer the lens's), nor where an editor wrote it (its Software or XMP names Lightroom, Photoshop, …: tone,
crop and vignettes of its own), nor beyond lensfun's calibrated corner (ρ > :data:`MAX_RHO`: a larger sensor than the
calibration's, where the pa polynomial is extrapolated); and lensfun measured its fields on RAW data, linear, while a JPEG's tone curve is only
approximately sRGB (the linearisation the estimate reads): the figures say for which
frames the truth is taken to hold, and why not for the others.

**A series of one lens** (``series``). ``../shared`` holds one frame per camera, so a
series is built: for each lens setting above, ``n`` vignetting-free bases (the central
40 % of full-size camera frames, cut to the frame's aspect and box-resized to
``long_side`` pixels, at about their native resolution: no lens fall-off to speak of)
times lensfun's field of that setting. Each frame is estimated and learned into a
temporary profile store keyed as the pipeline keys the lens
(:meth:`~vigproc.stores.profiles.ProfileStore.key_for` of the frame's EXIF), exactly as
``vigproc profile learn`` does (:func:`vigproc.core.estimate.estimate_with_evidence`,
then :meth:`~vigproc.stores.profiles.ProfileStore.learn` with the evidence), pooling in
a lens family built without the lenses measured. Reported: the profile's error after
1, 5, 10 … frames, and once the profile is trusted, the corner fall-off of the field
each later frame is corrected with against the frames' own single-frame estimates: its
spread is the series' consistency. That field is the one the hot folder applies
(:class:`~vigproc.pipeline.learning.SteadyProfiles`: the revision its series took when
the profile became trusted, the frames of a setting being one series, a second apart),
looked up before the frame is learned.
"""

from __future__ import annotations

import logging
import math
import re
import tempfile
from contextlib import contextmanager
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, Iterator, Sequence

import numpy as np

log = logging.getLogger(__name__)

#: Capture time (s, epoch) of a series' first frame; its frames follow a second apart.
T0 = 1.7e9

#: Long side of the grid fields are compared on (the metric is an RMS over the frame:
#: a coarser grid of the same frame gives the same figure to a few 1e-4 EV).
GRID = 240
#: Tags read beside the in-camera flags: a raw converter's or an editor's hand on the pixels.
#: ``XMP-dc:Creator``: Picasa signs its edits there; ``RelatedImageWidth``/``Height``
#: (Interop): the camera's frame, whose aspect a crop no longer has.
CONVERTER_TAGS = ("Software", "ProcessingSoftware", "CreatorTool", "LensProfileEnable", "VignetteAmount",
                  "PostCropVignetteAmount", "XMP-dc:Creator", "RelatedImageWidth", "RelatedImageHeight")
#: A frame whose aspect (long / short side) differs from its camera's by more than this
#: is a crop: its centre and corner are no longer the lens's.
MAX_ASPECT_CHANGE = 0.01
#: Programs whose output is an edited frame (tone, crop, vignettes of their own), not the camera's JPEG.
EDITORS = re.compile(r"photoshop|lightroom|camera raw|photo editor|gimp|capture one|darktable|rawtherapee|"
                     r"picasa|aperture|photos|snapseed|affinity|luminar|dxo", re.IGNORECASE)
_LN2 = math.log(2.0)


@dataclass(frozen=True)
class Truth:
    """lensfun's field for one frame's lens setting."""

    lens: str  # lensfun's maker / model
    focal_mm: float
    fnumber: float
    distance_m: float
    corner_rho: float  # where the frame's corner lies in the calibration's radius (1: its corner)
    k: tuple[float, float, float]  # the interpolated pa coefficients

    def log_field(self, shape: tuple[int, int]) -> np.ndarray:
        """log φ (natural) on an H×W grid of the frame (centred, r = 1 at the corner × ρ).

        Raises
        ------
        ModelError
            If the pa polynomial is not positive on the frame (an extrapolation
            beyond what the calibration can say).
        """
        from vigproc.errors import ModelError
        from vigproc.stores.lensfun import pa_field

        g = pa_field(shape, *self._scaled_k())
        if not np.all(g > 0):
            raise ModelError(f"lensfun's field of {self.lens} is not positive over this frame (ρ = {self.corner_rho:.3f})")
        return np.log(g)

    def _scaled_k(self) -> tuple[float, float, float]:
        # pa in r·ρ: 1 + k1 ρ² r² + k2 ρ⁴ r⁴ + k3 ρ⁶ r⁶
        s = self.corner_rho * self.corner_rho
        return self.k[0] * s, self.k[1] * s * s, self.k[2] * s * s * s

    @property
    def corner_ev(self) -> float:
        """The fall-off at the frame's corner, EV (positive: darker)."""
        from vigproc.stores.lensfun import pa_corner

        return -math.log2(pa_corner(*self._scaled_k()))


def lensfun_truth(lens_key) -> tuple[Truth | None, str]:
    """lensfun's field for a frame's :class:`~vigproc.io.exif.LensKey`, or None with the
    reason (no lens named, no calibration, settings lensfun declines to interpolate)."""
    from vigproc.errors import ModelError
    from vigproc.stores.lensfun import interpolate_pa
    from vigproc.stores.lensfun_match import corner_rho, covers, frame_crop, match_lens

    if lens_key is None or lens_key.focal_mm is None or lens_key.fnumber is None:
        return None, "no focal length or f-number in the EXIF"
    found = match_lens(lens_key)
    if found.lens is None:
        return None, found.reason
    lens = found.lens
    dist = lens_key.focus_distance_m if lens_key.focus_distance_m not in (None, math.inf) else 1000.0
    try:
        pa = interpolate_pa(lens, lens_key.focal_mm, lens_key.fnumber, dist)
    except ModelError as exc:
        return None, str(exc)
    crop = frame_crop(lens_key)
    # the frame's corner as --profile lensfun puts it (a sensor within rounding of the calibration's
    # is its own, rho = 1); past the calibrated corner, where it is extrapolated, as far as it lies
    covered = crop is None or covers(lens.crop_factor, crop)
    rho = corner_rho(lens.crop_factor, crop) if covered else lens.crop_factor / crop
    return Truth(found.name or "?", float(lens_key.focal_mm), float(lens_key.fnumber), float(dist), float(rho),
                 (float(pa.k1), float(pa.k2), float(pa.k3))), found.reason


def grid_shape(width: int, height: int, long_side: int = GRID) -> tuple[int, int]:
    """(H, W) of a grid of the frame's aspect with the given long side."""
    s = long_side / max(width, height)
    return max(2, int(round(height * s))), max(2, int(round(width * s)))


def _ev(log_ratio: np.ndarray) -> float:
    from benchmarks.clean import gain_free_ev

    return gain_free_ev(log_ratio)


@dataclass(frozen=True)
class LensfunRow:
    """One frame whose lens lensfun calibrated, through the default correction."""

    file: str
    camera: str
    lens: str
    focal_mm: float
    fnumber: float
    corner_rho: float
    truth_holds: bool
    why: str  # why the truth holds or not (the flags read)
    truth_corner_ev: float  # lensfun's fall-off at the frame's corner (EV, positive: darker)
    applied: bool
    rule: str | None
    applied_corner_ev: float  # the applied field's fall-off at its darkest corner (0: nothing applied)
    candidate_corner_ev: float
    error_ev: float  # applied field against lensfun's (gain-free RMS of log2 ratio)
    candidate_error_ev: float  # the estimator's fit before the gate
    uncorrected_ev: float  # lensfun's field itself (the error of leaving the frame alone)


@dataclass
class LensfunSummary:
    frames: int
    truth_frames: int  # frames whose truth holds
    median_error_ev: float  # over the truth frames: applied field
    median_candidate_ev: float
    median_uncorrected_ev: float
    rows: list[LensfunRow] = field(default_factory=list)


#: A frame whose corner lies this far beyond the calibration's (a larger sensor than
#: lensfun measured on) has an extrapolated truth: the pa polynomial is not bound there.
MAX_RHO = 1.05


def _aspect(w: Any, h: Any) -> float | None:
    try:
        w, h = float(w), float(h)
    except (TypeError, ValueError):
        return None
    return max(w, h) / min(w, h) if w > 0 and h > 0 else None


def _truth_holds(tags: dict[str, Any], ic, corner_rho: float = 1.0,
                 size: tuple[int, int] | None = None) -> tuple[bool, str]:
    """Whether lensfun's field is the frame's truth, and why (module doc). ``size``: the
    frame's (width, height), compared with the camera's (``RelatedImageWidth``/``Height``)."""
    if corner_rho > MAX_RHO:
        return False, f"beyond lensfun's calibrated corner (ρ = {corner_rho:.2f})"
    if ic is not None:
        return False, f"corrected in camera ({ic.evidence})"
    cam = _aspect(tags.get("RelatedImageWidth"), tags.get("RelatedImageHeight"))
    own = _aspect(*size) if size else None
    if cam and own and abs(own / cam - 1.0) > MAX_ASPECT_CHANGE:
        return False, (f"cropped ({size[0]}x{size[1]} of the camera's "
                       f"{tags['RelatedImageWidth']}x{tags['RelatedImageHeight']})")
    lp = tags.get("LensProfileEnable")
    if lp not in (None, 0, "0"):
        return False, f"a raw converter's lens profile (LensProfileEnable={lp}, {tags.get('Software') or '?'})"
    for name in ("Software", "ProcessingSoftware", "CreatorTool", "XMP-dc:Creator"):
        if EDITORS.search(str(tags.get(name) or "")):
            return False, f"edited ({name.rsplit(':', 1)[-1]}={str(tags[name])[:40]})"
    for name in ("VignetteAmount", "PostCropVignetteAmount"):
        if tags.get(name) not in (None, 0, "0", "+0"):
            return False, f"an editor's own vignette ({name}={tags[name]})"
    from vigproc.io.incamera import FLAG_TAGS

    flags = [f"{k}={tags[k]}" for k in FLAG_TAGS if tags.get(k) is not None]
    return True, ("flags off: " + ", ".join(flags)) if flags else "no in-camera flag recorded"


def corrected(path: Path, proc) -> tuple[Any, np.ndarray]:
    """One file through the default correction as ``vigproc correct`` runs it (``proc``: a
    :class:`~vigproc.pipeline.processor.Processor`): its result and its linear image."""
    from vigproc.pipeline.processor import output_format_for

    _out, res, img, _info, _fmt = proc._process_path(path, None, lambda info: output_format_for("auto", path, info))
    return res, img


def candidate_of(model):
    """The estimator's fit before the gate: the model itself, or the candidate an identity keeps."""
    return None if model is None else (model.candidate if model.candidate is not None else model)


def frame_row(path: Path, proc, truth: Truth, lens_key, tags: dict[str, Any], ic) -> LensfunRow:
    """The default correction of one frame against lensfun's field (module doc)."""
    from vigproc.core.plausible import corner_ev

    res, img = corrected(path, proc)
    h, w = img.shape[:2]
    shape = grid_shape(w, h)
    true_log = truth.log_field(shape)
    m = res.model
    applied = bool(res.applied) and m is not None and not m.is_identity
    cand = candidate_of(m)
    est = m.log_field(shape) if applied else np.zeros(shape)
    cand_log = cand.log_field(shape) if cand is not None and not cand.is_identity else np.zeros(shape)
    holds, why = _truth_holds(tags, ic, truth.corner_rho, (w, h))
    camera = " ".join(str(getattr(lens_key, k, None) or "") for k in ("make", "model")).strip() or "?"
    return LensfunRow(
        file=path.name, camera=camera, lens=truth.lens, focal_mm=truth.focal_mm, fnumber=truth.fnumber,
        corner_rho=truth.corner_rho, truth_holds=holds, why=why, truth_corner_ev=truth.corner_ev,
        applied=applied, rule=res.extra.get("not_applied_rule"),
        applied_corner_ev=corner_ev(m)[1] if applied else 0.0,
        candidate_corner_ev=corner_ev(cand)[1] if cand is not None else 0.0,
        error_ev=_ev(est - true_log), candidate_error_ev=_ev(cand_log - true_log), uncorrected_ev=_ev(true_log))


def lensfun_frames(files: Sequence[Path]) -> tuple[list[tuple[Path, Any, Truth, dict, Any]], list[tuple[Path, str]]]:
    """The files whose lens lensfun calibrated: (path, lens key, truth, tags, in-camera),
    and the others with the reason."""
    from vigproc.io.exif import ExifReader, LensKey
    from vigproc.io.incamera import TAGS, from_tags

    found, other = [], []
    with ExifReader() as reader:
        keys = reader.read_many(list(files))
        for p, k in zip(files, keys):
            if not isinstance(k, LensKey):
                other.append((p, f"no lens key ({type(k).__name__})"))
                continue
            truth, why = lensfun_truth(k)
            if truth is None:
                other.append((p, why))
                continue
            try:
                tags = dict(reader.read_tags(p, TAGS + CONVERTER_TAGS))
            except Exception as exc:  # noqa: BLE001 - unread flags: the frame is reported as unknown
                log.warning("%s: flags not read: %s", p, exc)
                tags = {}
            found.append((p, k, truth, tags, from_tags(tags)))
    return found, other


def without_lenses(found: Sequence[tuple[Path, Any, Truth, dict, Any]]):
    """lensfun's lens family (all the shipped family's components) built without the
    lenses of ``found``: the prior of an estimate that is scored against one of them
    must not hold that lens's own calibrations."""
    from vigproc.core.lensfamily import PROFILE_COMPONENTS
    from vigproc.stores.lensfun import lensfun_family

    names = {tuple(t.lens.split(" / ", 1)) for _p, _k, t, _tg, _ic in found}
    return lensfun_family(exclude=names, n_components=PROFILE_COMPONENTS)


@contextmanager
def ambiguity_shrink(subtract_noise: bool = True, noise_factor: float = 1.0) -> Iterator[None]:
    """Within the block, the pipeline's default estimate is
    :func:`vigproc.core.ambiguity.estimate_shrunk` (the centred fit shrunk toward the EXIF
    population by the frame's half-fit disagreement, less the fit's own noise unless
    ``subtract_noise`` is False, ``noise_factor`` times its variance): an experiment scored as the default is, never the
    pipeline's own setting. Process-wide, one block at a time."""
    import vigproc.core.estimate as E
    from vigproc.core.ambiguity import estimate_shrunk

    orig = E.estimate_default

    def shrunk(lum, mask=None, hint=None, family=None, colour=None, rule=None):
        return estimate_shrunk(lum, mask, hint, family, colour, base=orig, subtract_noise=subtract_noise,
                               noise_factor=noise_factor)

    E.estimate_default = shrunk
    try:
        yield
    finally:
        E.estimate_default = orig


def run_lensfun(files: Sequence[Path], family: Any = "exclude", shrink: str | None = None) -> LensfunSummary:
    """Part (a) on one frame each: every file whose lens lensfun calibrated.

    Parameters
    ----------
    files : sequence of Path
    family : "exclude", None or LensFamily
        The lens family the default estimate's prior comes from, standing in for the
        shipped one (:func:`vigproc.core.lensfamily.shipped_family_replaced`):
        "exclude" builds lensfun's without the lenses of these frames
        (:func:`without_lenses`; the shipped family holds every lensfun lens, the
        measured ones too); None: the shipped family, as a user's ``correct`` runs.
    shrink : {None, "scene", "scene3", "all"}
        Score :func:`ambiguity_shrink`'s estimate instead of the default ("all": its
        ``subtract_noise`` False; "scene3": its ``noise_factor`` 3).

    Returns
    -------
    LensfunSummary
        Medians over the frames whose truth holds.
    """
    from contextlib import nullcontext

    from vigproc.core.lensfamily import shipped_family_replaced
    from vigproc.pipeline.processor import Processor, Settings

    found, _ = lensfun_frames(files)
    if isinstance(family, str) and family == "exclude":
        family = without_lenses(found) if found else None
    rows = []
    with shipped_family_replaced(family) if family is not None else nullcontext(), \
            ambiguity_shrink(shrink != "all", 3.0 if shrink == "scene3" else 1.0) if shrink else nullcontext(), \
            Processor(Settings(mode="correct", profile="estimate"), plausibility=True) as proc:
        for p, k, truth, tags, ic in found:
            try:
                rows.append(frame_row(p, proc, truth, k, tags, ic))
            except Exception as exc:  # noqa: BLE001 - a frame that fails is reported, not counted
                log.warning("%s: %s", p, exc)
    good = [r for r in rows if r.truth_holds]
    med = lambda v: float(np.median(v)) if v else math.nan  # noqa: E731
    return LensfunSummary(len(rows), len(good), med([r.error_ev for r in good]),
                          med([r.candidate_error_ev for r in good]), med([r.uncorrected_ev for r in good]), rows)


# --------------------------------------------------------------------------- #
# a series of one lens setting, through the store
# --------------------------------------------------------------------------- #


def crop_to(img: np.ndarray, width: int, height: int, frac: float = 0.4) -> np.ndarray:
    """The central ``frac`` of each side of ``img`` (H×W or H×W×C), cut to the
    aspect ``width:height`` (turned to the same orientation) and box-resized to it."""
    from vigproc.core.resample import resize_area

    a = np.asarray(img, dtype=np.float64)
    if (a.shape[0] > a.shape[1]) != (height > width):
        a = np.rot90(a)
    h, w = a.shape[:2]
    ch, cw = h * frac, w * frac
    aspect = width / height
    if cw / ch > aspect:
        cw = ch * aspect
    else:
        ch = cw / aspect
    y0, x0 = int(round((h - ch) / 2)), int(round((w - cw) / 2))
    c = a[y0:y0 + int(round(ch)), x0:x0 + int(round(cw))]
    if c.ndim == 2:
        return resize_area(c, height, width)
    return np.stack([resize_area(c[..., i], height, width) for i in range(c.shape[2])], axis=-1)


@dataclass(frozen=True)
class SeriesRow:
    """One lens setting's series through the store."""

    lens: str
    focal_mm: float
    fnumber: float
    frames: int
    single_median_ev: float  # each frame estimated alone (the applied default)
    profile_ev: dict[int, float]  # the profile's error after n frames
    trusted_at: int | None  # frames learned when the profile became trusted
    corner_spread_after_trust_ev: float  # max - min corner fall-off applied after trust
    single_corner_spread_ev: float  # the same of the frames' own estimates (same frames)
    truth_corner_ev: float


@dataclass
class SeriesSummary:
    n: int
    long_side: int
    bases: int
    median_ev: dict[int, float]
    median_single_ev: float
    trusted: int
    rows: list[SeriesRow] = field(default_factory=list)


def run_series(found: Sequence[tuple[Path, Any, Truth, dict, Any]], bases: Sequence[np.ndarray], n: int = 10,
               long_side: int = 1200, counts: Sequence[int] = (1, 5, 10), seed: int = 0,
               family: Any = "exclude") -> SeriesSummary:
    """A series of ``n`` frames per lens setting of ``found`` through a profile store (module doc).

    Parameters
    ----------
    found : sequence
        :func:`lensfun_frames`'s lens settings (one per frame; the frame's own pixels are
        not used, only its lens key, truth and size).
    bases : sequence of ndarray (H×W×3, linear) or paths
        Vignetting-free frames (files are read when a series takes them: linear RGB);
        cut and resized per setting by :func:`crop_to`.
    family : "exclude", None or LensFamily
        The lens family the store pools in: "exclude" builds lensfun's without the
        lenses of ``found`` (an estimate never holds the lens it is measured on);
        None: the shipped one.
    """
    from vigproc.core.estimate import estimate_with_evidence
    from vigproc.core.plausible import corner_ev
    from vigproc.errors import ModelError
    from vigproc.io.protocol import vignetted
    from vigproc.pipeline.learning import SteadyProfiles
    from vigproc.stores.profiles import ProfileStore

    if family == "exclude":
        from vigproc.stores.lensfun import lensfun_family

        names = {tuple(t.lens.split(" / ", 1)) for _p, _k, t, _tg, _ic in found}
        family = lensfun_family(exclude=names)
    counts = [c for c in counts if c <= n] or [n]
    rows = []
    for li, (path, key, truth, _tags, _ic) in enumerate(found):
        fw, fh = (key.width, key.height) if key.width and key.height else (3, 2)
        s = long_side / max(fw, fh)
        w, h = max(2, int(round(fw * s))), max(2, int(round(fw * s * fh / fw)))
        gshape = grid_shape(w, h)
        try:
            true_log, true_grid = truth.log_field((h, w)), truth.log_field(gshape)
        except ModelError as exc:  # lensfun's field is no field on this frame: no series of it
            log.warning("%s: %s", truth.lens, exc)
            continue
        order = np.random.default_rng(seed + li).permutation(len(bases))
        errs: dict[int, float] = {}
        single, single_corner, after_corner, trusted_at = [], [], [], None
        with tempfile.TemporaryDirectory(prefix="vigproc-bench-series-") as tmp, \
                ProfileStore(Path(tmp) / "profiles.sqlite", family=family) as st:
            pkey = st.key_for(key, w, h)
            steady = SteadyProfiles(st)
            used = 0
            for j in order:
                if used >= n:
                    break
                try:
                    frame = vignetted(crop_to(_base(bases[j]), w, h), true_log)
                    m, evidence = estimate_with_evidence(frame)
                except Exception as exc:  # noqa: BLE001 - a blank base: no frame of the series
                    log.debug("base %d: %s", j, exc)
                    continue
                used += 1
                fit = m.candidate if m.candidate is not None else m
                single.append(_ev(m.log_field(gshape) - true_grid))
                single_corner.append(corner_ev(m)[1])
                if fit.covariance is None:
                    continue
                # as the hot folder corrects a frame: the revision its series applies (one
                # series: the frames a second apart), looked up before the frame is learned
                steady.at(T0 + used)
                applied = steady.lookup(key, w, h, trusted_only=True)
                if applied is not None:
                    after_corner.append(corner_ev(applied.model(w, h))[1])
                p = st.learn(pkey, fit, frame_id=f"frame{j:04d}", evidence=evidence, lens_key=key)
                if used in counts:
                    errs[used] = _ev(p.model(w, h).log_field(gshape) - true_grid)
                if p.trusted:
                    trusted_at = trusted_at or used
        k = len(after_corner)
        rows.append(SeriesRow(
            truth.lens, truth.focal_mm, truth.fnumber, used, float(np.median(single)) if single else math.nan,
            errs, trusted_at, float(np.ptp(after_corner)) if k else math.nan,
            float(np.ptp(single_corner[-k:])) if k else math.nan, truth.corner_ev))
    med = {c: float(np.median([r.profile_ev[c] for r in rows if c in r.profile_ev]))
           for c in counts if any(c in r.profile_ev for r in rows)}
    return SeriesSummary(n, long_side, len(bases), med,
                         float(np.median([r.single_median_ev for r in rows])) if rows else math.nan,
                         sum(r.trusted_at is not None for r in rows), rows)


def _base(b) -> np.ndarray:
    """A base as linear RGB (a file is read; a blank one raises VigprocError)."""
    from vigproc.errors import InvalidImageError
    from vigproc.io.images import read_image
    from vigproc.io.protocol import rgb_of

    if isinstance(b, np.ndarray):
        return b
    a, _ = read_image(b, transfer="linear" if "linear" in Path(b).name.lower() else "auto")
    rgb = rgb_of(a)
    if not np.all(np.isfinite(rgb)) or rgb.max() <= 0:
        raise InvalidImageError(f"{Path(b).name}: blank")
    return rgb


def series_bases(folders: Sequence[str | Path], min_long_side: int = 2000, limit: int | None = None) -> list[Path]:
    """Full-size camera frames for :func:`run_series` (:func:`benchmarks.clean.base_files`:
    BSDS and Kodak left out), read when a series takes them."""
    from benchmarks.clean import base_files

    files = base_files([Path(x) for x in folders], min_long_side)
    return files[:limit] if limit else files


def as_dict(x) -> dict:
    """JSON-able figures."""
    return asdict(x)
