"""The clean protocol: vignetting-free bases × real lens fields.

BSDS and Kodak are film scans that carry their own lens fall-off, so an estimator
judged (or a prior fitted) on them learns vignetting. Here the bases are the central
``CROP`` (40 %) of full-size camera frames: a lens's fall-off there is negligible.
Each crop is cut to 3:2 (portrait turned landscape), box-resized to 480×320 and
linearised (the file's transfer: sRGB for camera JPEGs; a file named ``*linear*`` is
read as linear), then multiplied by:

- the ``pa`` field of each of 20 lensfun lenses (:func:`vigproc.stores.lensfun.diverse_lenses`:
  shortest focal length, widest aperture), the crop taken as the full frame (ρ = 1
  at its corner);
- Lyu 2010's Table 1 fields (settings 1–3);
- nothing ("no harm").

Error of an estimate: the RMS over the frame of log2(φ̂/φ) about its mean, in EV
(a correction is defined up to a global gain); median over a lens's frames, then
median and p90 over the lenses. No harm: the same RMS of the applied field log2 φ̂.
Calibration: the share of frames whose error is within 1σ and 2σ of the estimate's
``quality.field_sigma_ev``.

The lens-family estimator is given a family built *without* the 20 test lenses
(:func:`vigproc.stores.lensfun.lensfun_family` with ``exclude``): an estimate never holds
the lens it is measured on.
"""

from __future__ import annotations

import csv
import logging
import math
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Iterable, Sequence

import numpy as np

from vigproc.io.protocol import rgb_of, vignetted  # noqa: F401  (vignetted re-exported for the benches)
from vigproc.stores.lensfun import diverse_lenses, pa_field

log = logging.getLogger(__name__)

WIDTH, HEIGHT = 480, 320
#: Side fraction of the frame kept around its centre.
CROP = 0.4
#: Frames whose long side is shorter are not used (their crop would be upsampled).
MIN_LONG_SIDE = 1000
_LN2 = math.log(2.0)


@dataclass
class Estimate:
    """What a bench needs of one estimate: the applied log field (natural log, H×W),
    whether it fell back, and its stated 1-σ error in EV (NaN when it states none)."""

    log_field: np.ndarray
    fallback: bool = False
    sigma_ev: float = math.nan


@dataclass(frozen=True)
class Field:
    """A known vignetting field on the 480×320 frame (natural log), with what EXIF
    would say of its lens (35-mm focal length and f-number; None for Table 1's)."""

    name: str
    log_field: np.ndarray
    focal35: float | None = None
    fnumber: float | None = None


#: ``fn(lum, field)``: an estimate of a frame vignetted by ``field`` (None: no field).
#: Only estimators that take EXIF look at the field, and only at its focal35/fnumber.
Estimator = Callable[[np.ndarray, "Field | None"], Estimate]


def crop_base(lum: np.ndarray, frac: float = CROP) -> np.ndarray:
    """Central ``frac`` of each side, cut to 3:2 landscape, box-resized to 480×320."""
    from vigproc.core.resample import resize_area

    g = np.asarray(lum, dtype=np.float64)
    if g.shape[0] > g.shape[1]:
        g = np.rot90(g)
    h, w = g.shape
    ch, cw = h * frac, w * frac
    if cw / ch > 1.5:
        cw = ch * 1.5
    else:
        ch = cw / 1.5
    y0, x0 = int(round((h - ch) / 2)), int(round((w - cw) / 2))
    return resize_area(g[y0:y0 + int(round(ch)), x0:x0 + int(round(cw))], HEIGHT, WIDTH)


def base_files(folders: Iterable[Path], min_long_side: int = MIN_LONG_SIDE) -> list[Path]:
    """Image files under ``folders`` whose long side is at least ``min_long_side``,
    read from each folder tree's ``files.csv`` when present (size column), else by
    probing. BSDS and Kodak are left out: film scans with their own fall-off."""
    from vigproc.io.images import read_image

    out: list[Path] = []
    for folder in folders:
        folder = Path(folder)
        index = folder / "files.csv"
        if index.is_file():
            with index.open(newline="", encoding="utf-8") as fh:
                for row in csv.DictReader(fh):
                    p = row.get("path", "")
                    if any(k in p.lower() for k in ("bsds", "kodak", "kodim")):
                        continue
                    try:
                        w, h = (int(v) for v in row.get("size", "").split("x"))
                    except ValueError:
                        continue
                    if max(w, h) >= min_long_side and (folder / p).is_file():
                        out.append(folder / p)
            continue
        for p in sorted(folder.rglob("*")):
            if p.suffix.lower() not in (".jpg", ".jpeg", ".png", ".tif", ".tiff"):
                continue
            try:
                a, _ = read_image(p)
            except Exception:  # noqa: BLE001 - a probe: unreadable files are not bases
                continue
            if max(a.shape[:2]) >= min_long_side:
                out.append(p)
    return out


def load_bases(files: Sequence[Path], frac: float = CROP, colour: bool = False) -> tuple[list[np.ndarray], list[str]]:
    """Linear luminance crops (central ``frac`` of each side) of ``files``; unreadable or
    blank ones are skipped. With ``colour``, 480×320×3 R, G, B crops of the same
    frames (grey files repeated in each channel), scaled as their luminance is."""
    from vigproc.errors import VigprocError
    from vigproc.core.pixels import luminance
    from vigproc.io.images import read_image

    ims, names = [], []
    for f in files:
        try:
            a, _ = read_image(f, transfer="linear" if "linear" in f.name.lower() else "auto")
        except VigprocError as exc:
            log.warning("skipping %s", exc)
            continue
        c = crop_base(luminance(a), frac)
        if not np.all(np.isfinite(c)) or c.max() <= 0 or np.ptp(c) <= 1e-6 * c.max():
            log.warning("skipping %s: its central crop is blank", f.name)
            continue
        if colour:
            rgb = rgb_of(a)
            ims.append(np.stack([crop_base(rgb[..., ch], frac) for ch in range(3)], axis=-1) / c.max())
        else:
            ims.append(c / c.max())
        names.append(f.name)
    return ims, names


def load_clean_bases(folders: Iterable[str | Path], min_long_side: int = MIN_LONG_SIDE, limit: int | None = None,
                     frac: float = CROP, colour: bool = False) -> tuple[list[np.ndarray], list[str]]:
    """:func:`load_bases` of the first ``limit`` frames :func:`base_files` finds under
    ``folders`` (what every clean-protocol bench reads, from its --images,
    --min-long-side and --limit)."""
    files = base_files([Path(f) for f in folders], min_long_side)
    return load_bases(files[:limit] if limit else files, frac, colour)


def gain_free_ev(log_ratio: np.ndarray) -> float:
    """RMS of a natural-log field about its mean, in EV."""
    return float(np.std(log_ratio) / _LN2)


@dataclass
class FieldResult:
    """One method on one family of fields (lensfun lenses or a Table 1 setting)."""

    method: str
    fields: str
    n_fields: int
    n_frames: int
    median_ev: float
    p90_ev: float
    frame_median_ev: float
    uncorrected_ev: float
    within_1sigma: float
    within_2sigma: float
    fallbacks: int
    ms_per_frame: float
    per_field_ev: list[float] = field(default_factory=list)
    #: mean PSNR (dB, peak 1, best scalar gain) of the restored frames against their bases:
    #: Lyu 2010's Table 2 measure
    psnr_db: float = math.nan


@dataclass
class HarmResult:
    method: str
    n_frames: int
    median_ev: float
    worst_ev: float
    fallbacks: int


def run_fields(bases: Sequence[np.ndarray], method: str, fn: Estimator,
               fields: Sequence[Field], label: str) -> FieldResult:
    """Every base × every field: per-field median error, then median/p90 over fields."""
    from benchmarks.synthetic import psnr_best_gain

    per_field, frames, unc, z, secs, fb, psnr = [], [], [], [], [], 0, []
    for f in fields:
        true_log = f.log_field
        errs = []
        for im in bases:
            v = vignetted(im, true_log)
            t0 = time.perf_counter()
            est = fn(v, f)
            secs.append(time.perf_counter() - t0)
            psnr.append(psnr_best_gain(vignetted(v, -est.log_field), im))
            e = gain_free_ev(est.log_field - true_log)
            errs.append(e)
            unc.append(gain_free_ev(true_log))
            if math.isfinite(est.sigma_ev) and est.sigma_ev > 0:
                z.append(e / est.sigma_ev)
            fb += est.fallback
        per_field.append(float(np.median(errs)))
        frames += errs
    zs = np.asarray(z)
    return FieldResult(
        method, label, len(fields), len(frames), float(np.median(per_field)),
        float(np.percentile(per_field, 90)), float(np.median(frames)), float(np.median(unc)),
        float(np.mean(zs <= 1)) if zs.size else math.nan, float(np.mean(zs <= 2)) if zs.size else math.nan,
        fb, 1000 * float(np.median(secs)), per_field, float(np.mean(psnr)),
    )


def run_harm(bases: Sequence[np.ndarray], method: str, fn: Estimator) -> HarmResult:
    out, fb = [], 0
    for im in bases:
        est = fn(im, None)
        out.append(gain_free_ev(est.log_field))
        fb += est.fallback
    return HarmResult(method, len(bases), float(np.median(out)), float(np.max(out)), fb)


def lens_fields(n: int = 20) -> tuple[list[Field], set[tuple[str, str]]]:
    """The 20 lensfun fields on the 480×320 frame (with their calibration's 35-mm focal
    length and f-number), and the lenses' (maker, model)."""
    lenses = diverse_lenses(n)
    fields = [Field(f"{lens.maker} {lens.model}", np.log(pa_field((HEIGHT, WIDTH), pa.k1, pa.k2, pa.k3)),
                    pa.focal * lens.crop_factor, pa.aperture)
              for lens, pa in lenses]
    return fields, {(lens.maker, lens.model) for lens, _ in lenses}


def table1_fields() -> list[Field]:
    from benchmarks.synthetic import table1_model

    return [Field(f"Table 1 setting {s}", table1_model(s).log_field((HEIGHT, WIDTH))) for s in (1, 2, 3)]


def model_estimator(fn: Callable[..., object], exif: bool = False) -> Estimator:
    """An :data:`Estimator` from a function returning a VignettingModel; with ``exif``,
    ``fn(lum, hint=LensHint(...))`` is told the field's 35-mm focal length and f-number
    (never which lens it is)."""
    from vigproc.core.family_fit import LensHint

    def run(im: np.ndarray, field: Field | None = None) -> Estimate:
        if exif:
            hint = LensHint(field.focal35, field.fnumber) if field is not None else None
            m = fn(im, hint=hint)
        else:
            m = fn(im)
        q = m.quality
        return Estimate(m.log_field(im.shape[:2]), bool(q and q.fallback),
                        float(q.field_sigma_ev) if q and q.field_sigma_ev > 0 else math.nan)

    return run


@dataclass
class SigmaCalibration:
    """The scale and floor of the lens-family estimator's σ, fitted on one half of the
    bases and checked on the other."""

    scale: float
    floor: float
    train_within_1sigma: float
    train_within_2sigma: float
    test_within_1sigma: float
    test_within_2sigma: float
    n_frames: int


def calibrate_sigma(bases: Sequence[np.ndarray], fields: Sequence[Field], family,
                    target_1sigma: float = 0.68, min_2sigma: float = 0.92) -> SigmaCalibration:
    """Fit σ = hypot(scale·σ_jackknife, floor) of :mod:`vigproc.core.family_fit` so that on
    the even-numbered bases (× every field, and no field) the error is within 1σ on
    ``target_1sigma`` of the frames and within 2σ on at least ``min_2sigma``; report the
    shares on the odd-numbered bases, which the fit did not see."""
    from vigproc.core.family_fit import FamilySettings, colour_of, estimate_family
    from vigproc.core.pixels import luminance

    raw = FamilySettings(sigma_scale=1.0, sigma_floor=0.0, min_snr=0.0, grey_min_snr=0.0)
    rows = []
    for f in list(fields) + [Field("none", np.zeros((HEIGHT, WIDTH)))]:
        true_log = f.log_field
        for i, im in enumerate(bases):
            frame = vignetted(im, true_log)
            m = estimate_family(luminance(frame), raw, family=family, colour=colour_of(frame))
            rows.append((i % 2, gain_free_ev(m.log_field((HEIGHT, WIDTH)) - true_log), m.quality.field_sigma_ev))
    r = np.asarray(rows)
    train, test = r[:, 0] == 0, r[:, 0] == 1

    def shares(scale: float, floor: float, sel: np.ndarray) -> tuple[float, float]:
        z = r[sel, 1] / np.hypot(scale * r[sel, 2], floor)
        return float(np.mean(z <= 1)), float(np.mean(z <= 2))

    best = None
    for scale in np.arange(0.5, 8.001, 0.25):
        for floor in np.arange(0.0, 0.1501, 0.005):
            c1, c2 = shares(scale, floor, train)
            if c2 >= min_2sigma and (best is None or abs(c1 - target_1sigma) < best[0]):
                best = (abs(c1 - target_1sigma), float(scale), float(floor))
    if best is None:
        raise ValueError("no scale and floor reach the 2-sigma share on the training half")
    _, scale, floor = best
    return SigmaCalibration(scale, round(floor, 4), *shares(scale, floor, train), *shares(scale, floor, test),
                            len(rows))
