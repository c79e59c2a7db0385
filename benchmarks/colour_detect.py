"""How often one photograph's colour-cast report is right, and how often a scene's
colour is mistaken for a cast (:func:`vigproc.core.colour_cast.detect_colour_cast`).

Bases: the clean protocol's vignetting-free central crops of camera frames
(:func:`benchmarks.clean.load_clean_bases`, in colour). Casts: a physical model of
angle-dependent sensor response, channel c transmitting

    T_c(θ) = cos^{k_c}(θ),  θ = atan(r·d/f),

r the radius in half-diagonals, d/f = tan(θ_max) (the chief ray's angle at the corner),
k_G the luminance fall-off's exponent and k_R, k_B chosen so that the corner's
(log R/G, log B/G) shift points in one of ``directions`` hues at a given ΔE00 on a mid
grey (equal luminance). Each base is rendered through each cast; the detection rate is
the share of those frames reported as cast. False detections: the bases as they are
(no cast) and the bases under luminance-only fall-offs (lensfun's ``pa`` fields of real
lenses), which must not be called casts.
"""

from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass, field
from typing import Sequence

import numpy as np

from vigproc.core.cast_series import SeriesSettings, pool_cast
from vigproc.core.colour_cast import CastSettings, detect_colour_cast
from vigproc.core.colour_difference import grey_cast_de

log = logging.getLogger(__name__)

#: corner ΔE00 of the rendered casts (the target is stated at 5)
TARGETS_DE = (1.0, 2.0, 3.0, 4.0, 5.0, 7.0, 10.0)
#: chief-ray angles at the corner (degrees): a normal lens, a wide angle, an adapted rangefinder wide
THETA_MAX = (25.0, 40.0)
#: the luminance fall-off's exponent (the cos⁴ law)
K_GREEN = 4.0


@dataclass(frozen=True)
class Cast:
    """A per-channel angle-dependent transmission: T_c = cos^{k_c}(atan(r·tan θ_max))."""

    name: str
    target_de: float
    theta_max: float
    k: tuple[float, float, float]

    def log_transmission(self, shape: tuple[int, int]) -> np.ndarray:
        """H×W×3 natural-log transmission on a frame of ``shape`` (1 at the centre)."""
        h, w = shape
        y, x = np.mgrid[0:h, 0:w]
        r = np.hypot(x - (w - 1) / 2, y - (h - 1) / 2) / (0.5 * math.hypot(w, h))
        lc = np.log(np.cos(np.arctan(r * math.tan(math.radians(self.theta_max)))))
        return lc[..., None] * np.asarray(self.k)[None, None, :]

    def corner_shift(self) -> tuple[float, float]:
        """(log R/G, log B/G) at the corner versus the centre."""
        lcm = math.log(math.cos(math.radians(self.theta_max)))
        return (self.k[0] - self.k[1]) * lcm, (self.k[2] - self.k[1]) * lcm


def cast_for(target_de: float, hue_deg: float, theta_max: float, k_green: float = K_GREEN) -> Cast:
    """The cast whose corner shift points at ``hue_deg`` in the (log R/G, log B/G)
    plane with ΔE00 = ``target_de`` on a mid grey."""
    u, v = math.cos(math.radians(hue_deg)), math.sin(math.radians(hue_deg))
    lo, hi = 0.0, 2.0
    for _ in range(50):  # ΔE grows monotonically with the shift's length
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if grey_cast_de(mid * u, mid * v) < target_de else (lo, mid)
    s = 0.5 * (lo + hi)
    lcm = math.log(math.cos(math.radians(theta_max)))
    k = (k_green + s * u / lcm, k_green, k_green + s * v / lcm)
    return Cast(f"dE{target_de:g}/hue{hue_deg:g}/{theta_max:g}deg", float(target_de), float(theta_max), k)


def physical_casts(targets: Sequence[float] = TARGETS_DE, directions: int = 8,
                   theta_max: Sequence[float] = THETA_MAX) -> list[Cast]:
    """Every target ΔE × ``directions`` hues (equally spaced, starting at +R/G) × corner angle."""
    return [cast_for(t, 360.0 * i / directions, th) for t in targets for i in range(directions) for th in theta_max]


@dataclass
class RateRow:
    """Detections among frames of one kind."""

    label: str
    n: int
    detected: int
    rate: float
    median_de_est: float = math.nan
    #: which frames were reported as cast (names of bases; fields for the luminance row)
    hits: list[str] = field(default_factory=list)
    #: per frame: the detector's decision statistic (``ColourCastEvidence.score``, -inf
    #: where it could not judge) and the index of the base it was rendered on
    scores: list[float] = field(default_factory=list)
    base_index: list[int] = field(default_factory=list)
    #: per frame: which cast (or luminance field) of the row it was rendered under, and
    #: the detector's per-quadrant shifts and standard errors (4×2 each; None where it
    #: could not judge): what a series pools (:func:`series_rates`); not in the JSON
    cast_index: list[int] = field(default_factory=list)
    sectors: list = field(default_factory=list)


@dataclass
class DetectionResult:
    n_bases: int
    by_target: list[RateRow]
    clean: RateRow
    luminance_only: RateRow
    #: detection rate over every cast of ΔE ≥ 5
    rate_at_5: float
    ms_per_frame: float
    settings: dict = field(default_factory=dict)
    #: :func:`split_calibrated` of this result (two folds)
    split: list[dict] = field(default_factory=list)
    #: :func:`series_rates` per series length (``--frames``)
    series: list[dict] = field(default_factory=list)


def _row(label: str, flags: list[bool], des: list[float], names: list[str],
         scores: list[float] = (), idx: list[int] = (), cast_idx: list[int] = (), sectors: list = ()) -> RateRow:
    n, k = len(flags), int(sum(flags))
    return RateRow(label, n, k, k / n if n else math.nan, float(np.median(des)) if des else math.nan,
                   sorted({nm for nm, f in zip(names, flags) if f}), list(scores), list(idx), list(cast_idx),
                   list(sectors))


def _sectors(ev):
    if len(ev.sector_shift) != 4 or len(ev.sector_se) != 4:
        return None
    return np.asarray(ev.sector_shift, dtype=np.float64), np.asarray(ev.sector_se, dtype=np.float64)


def _score(ev) -> float:
    return float(ev.score) if math.isfinite(ev.score) else -math.inf


def threshold_at_false_rate(clean_scores, false_rate: float = 0.05) -> float:
    """The lowest score threshold at which at most ``floor(false_rate * N)`` of the N
    clean frames' scores reach it: just above the (k+1)-th highest (-inf when every
    frame may).

    Parameters
    ----------
    clean_scores : array_like
        The clean frames' detection scores.
    false_rate : float
        The share of clean frames allowed at or above the threshold.

    Returns
    -------
    float
    """
    cs = np.sort(np.asarray(clean_scores, dtype=np.float64))[::-1]
    k = int(math.floor(false_rate * cs.size))  # frames allowed above the threshold
    return float(np.nextafter(cs[k], math.inf)) if k < cs.size else -math.inf


def half_threshold(clean_scores, base_index, half: int, false_rate: float = 0.05) -> float:
    """:func:`threshold_at_false_rate` of the clean frames rendered on bases of one index
    parity (``half``: 0 even, 1 odd): the threshold calibrated on that half."""
    s, b = np.asarray(clean_scores, dtype=np.float64), np.asarray(base_index)
    return threshold_at_false_rate(s[b % 2 == half], false_rate)


def half_rate(scores, base_index, half: int, threshold: float) -> float:
    """The share of the frames on bases of index parity ``half`` whose score reaches
    ``threshold`` (nan when that half holds none): a rate counted out of sample when the
    threshold came from the other half (:func:`half_threshold`)."""
    s, b = np.asarray(scores, dtype=np.float64), np.asarray(base_index)
    s = s[b % 2 == half]
    return float(np.mean(s >= threshold)) if s.size else math.nan


def split_calibrated(result: "DetectionResult", false_rate: float = 0.05) -> list[dict]:
    """Detection curve with the decision threshold calibrated out of sample.

    The bases are split by index parity. On one half the threshold on the detector's
    score is set to the lowest value that calls at most ``false_rate`` of that half's clean
    frames cast; the rates are then counted on the other half (clean, luminance-only and
    every cast target). Both folds are returned (even→odd, odd→even).

    Parameters
    ----------
    result : DetectionResult
        From :func:`detection_rates` (its rows carry per-frame scores).
    false_rate : float
        Allowed share of clean calibration frames called cast.

    Returns
    -------
    list of dict
        Per fold: ``calibrated_on``, ``threshold`` (score; the detector's own rule is 1),
        ``clean_calibration``, ``clean``, ``luminance_only`` and ``by_target``
        (``{"dE 5": rate, ...}``), rates on the evaluation half.
    """
    def rate(row: RateRow, half: int, thr: float) -> float:
        return half_rate(row.scores, row.base_index, half, thr)

    folds = []
    for cal in (0, 1):
        thr = half_threshold(result.clean.scores, result.clean.base_index, cal, false_rate)
        ev = 1 - cal
        folds.append({"calibrated_on": "even" if cal == 0 else "odd", "threshold": thr,
                      "clean_calibration": rate(result.clean, cal, thr), "clean": rate(result.clean, ev, thr),
                      "luminance_only": rate(result.luminance_only, ev, thr),
                      "by_target": {row.label: rate(row, ev, thr) for row in result.by_target}})
    return folds


def _series_stats(row: RateRow, allowed: set[int], n: int, count: int, rng: np.random.Generator,
                   settings: SeriesSettings) -> list[tuple[float, bool, bool]]:
    """``count`` series of ``n`` frames of different bases from ``allowed`` under one cast
    (or field) of ``row``, each pooled by :func:`pool_cast`: (score, detected, decisive)."""
    by_cast: dict[int, list[tuple[np.ndarray, np.ndarray]]] = {}
    for b, c, sec in zip(row.base_index, row.cast_index, row.sectors):
        if b in allowed and sec is not None:  # a frame the detector could not judge adds nothing
            by_cast.setdefault(c, []).append(sec)
    pools = [v for v in by_cast.values() if len(v) >= n]
    out = []
    for _ in range(count if pools else 0):
        frames = pools[rng.integers(len(pools))]
        pick = rng.choice(len(frames), size=n, replace=False)
        sc = pool_cast(np.stack([frames[i][0] for i in pick]), np.stack([frames[i][1] for i in pick]), settings)
        out.append((sc.score, sc.detected, sc.decisive))
    return out


def series_rates(result: "DetectionResult", n: int, *, count: int = 400, seed: int = 0,
                 false_rate: float = 0.05, settings: SeriesSettings = SeriesSettings()) -> dict:
    """Detection and false rates of series of ``n`` frames of one lens setting.

    A series is ``n`` different bases under the same cast (or the same luminance-only
    field, or none), each frame's per-quadrant shifts pooled as the profile store pools
    them (:func:`vigproc.core.cast_series.pool_cast`). Two rules are counted:

    - the store's fixed rule (``detected``: score ≥ 1; ``decisive``), on series drawn
      from all bases;
    - out of sample, as :func:`split_calibrated`: the threshold on the series' score set
      on clean series from one half of the bases (at most ``false_rate`` called), the rates
      counted on series from the other half; both folds.

    Parameters
    ----------
    result : DetectionResult
        From :func:`detection_rates` (its rows carry the frames' quadrant shifts).
    n : int
        Frames per series (at most the bases in one half).
    count : int
        Series drawn per row (and per fold).
    seed : int
        Of the draws.
    false_rate : float
        Allowed share of clean calibration series called cast.
    settings : SeriesSettings
        The pooling and the store's rule.

    Returns
    -------
    dict
        ``frames``, ``fixed`` (per row: ``detected`` and ``decisive`` rates) and ``split``
        (per fold: ``threshold``, ``clean``, ``luminance_only``, ``by_target``).

    Raises
    ------
    ValueError
        ``n`` < 1.
    """
    if n < 1:
        raise ValueError(f"a series needs at least one frame, got {n}")
    rng = np.random.default_rng(seed)
    everything = set(range(result.n_bases))
    rows = [result.clean, result.luminance_only] + list(result.by_target)
    labels = ["clean", "luminance_only"] + [r.label for r in result.by_target]

    def rates(stats: list, k: int) -> float:
        return float(np.mean([s[k] for s in stats])) if stats else math.nan

    fixed = {}
    for lab, row in zip(labels, rows):
        st = _series_stats(row, everything, n, count, rng, settings)
        fixed[lab] = {"detected": rates(st, 1), "decisive": rates(st, 2), "series": len(st)}
    folds = []
    for cal in (0, 1):
        half = {i for i in everything if i % 2 == cal}
        other = everything - half
        cs = [s[0] for s in _series_stats(result.clean, half, n, count, rng, settings)]
        if not cs:
            continue
        thr = threshold_at_false_rate(cs, false_rate)
        ev = {lab: float(np.mean([s[0] >= thr for s in st])) if st else math.nan
              for lab, row in zip(labels, rows)
              for st in [_series_stats(row, other, n, count, rng, settings)]}
        folds.append({"calibrated_on": "even" if cal == 0 else "odd", "threshold": thr,
                      "clean": ev["clean"], "luminance_only": ev["luminance_only"],
                      "by_target": {lab: ev[lab] for lab in labels[2:]}})
    return {"frames": n, "fixed": fixed, "split": folds}


def detection_rates(bases: Sequence[np.ndarray], casts: Sequence[Cast], *,
                    names: Sequence[str] | None = None,
                    luminance_fields: Sequence[tuple[str, np.ndarray]] = (),
                    settings: CastSettings = CastSettings(), frames: Sequence[int] = (),
                    series_count: int = 400) -> DetectionResult:
    """Detection rates of casts rendered on ``bases`` and false detections without one.

    Parameters
    ----------
    bases : sequence of numpy.ndarray
        Vignetting-free linear RGB frames (H×W×3).
    casts : sequence of Cast
        Rendered on every base; rates are grouped by their ``target_de``.
    names : sequence of str, optional
        The bases' names (for the false detections' list).
    luminance_fields : sequence of (name, H×W natural-log field)
        Luminance-only fall-offs, each applied to every base (all channels alike).
    settings : CastSettings
        The detector's.
    frames : sequence of int
        Series lengths for :func:`series_rates` (``result.series``).
    series_count : int
        Series drawn per row, fold and length.

    Returns
    -------
    DetectionResult
        Per-target rates (with the median estimated ΔE), the clean and luminance-only
        false-detection rates with the frames that were called cast.
    """
    names = list(names) if names is not None else [f"base{i}" for i in range(len(bases))]
    secs: list[float] = []

    def run(frame: np.ndarray):
        t0 = time.perf_counter()
        ev = detect_colour_cast(frame, settings=settings)
        secs.append(time.perf_counter() - t0)
        return ev

    clean = [run(b) for b in bases]
    clean_row = _row("clean", [e.detected for e in clean], [e.delta_e for e in clean], names,
                     [_score(e) for e in clean], list(range(len(bases))), [0] * len(bases),
                     [_sectors(e) for e in clean])
    lf, ld, ln, ls, li, lc, lsec = [], [], [], [], [], [], []
    for j, (fname, lfield) in enumerate(luminance_fields):
        for i, (b, nm) in enumerate(zip(bases, names)):
            e = run(b * np.exp(lfield)[..., None])
            lf.append(e.detected)
            ld.append(e.delta_e)
            ln.append(f"{nm} x {fname}")
            ls.append(_score(e))
            li.append(i)
            lc.append(j)
            lsec.append(_sectors(e))
    lum_row = _row("luminance only", lf, ld, ln, ls, li, lc, lsec)
    groups: dict[float, tuple[list, ...]] = {}
    cache: dict[tuple[tuple[int, int], Cast], np.ndarray] = {}
    for j, c in enumerate(casts):
        g = groups.setdefault(c.target_de, ([], [], [], [], [], [], []))
        for i, (b, nm) in enumerate(zip(bases, names)):
            key = (b.shape[:2], c)
            if key not in cache:
                cache[key] = np.exp(c.log_transmission(b.shape[:2]))
            e = run(b * cache[key])
            g[0].append(e.detected)
            g[1].append(e.delta_e)
            g[2].append(f"{nm} x {c.name}")
            g[3].append(_score(e))
            g[4].append(i)
            g[5].append(j)
            g[6].append(_sectors(e))
        cache.clear()
    rows = [_row(f"dE {t:g}", *groups[t]) for t in sorted(groups)]
    big = [f for t in groups if t >= 5 for f in groups[t][0]]
    res = DetectionResult(len(bases), rows, clean_row, lum_row, float(np.mean(big)) if big else math.nan,
                          1000 * float(np.median(secs)) if secs else math.nan,
                          {k: getattr(settings, k) for k in settings.__dataclass_fields__})
    if len(bases) >= 2:
        res.split = split_calibrated(res)
    for n in frames:
        if n > (len(bases) + 1) // 2:
            log.warning("series of %d frames: more than the %d bases of a half; left out", n, (len(bases) + 1) // 2)
            continue
        res.series.append(series_rates(res, int(n), count=series_count))
    return res
