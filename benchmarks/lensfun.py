"""Real-lens protocol: lensfun's calibrated vignetting applied to natural images.

For each of ``n_lenses`` lenses from :func:`vigproc.stores.lensfun.diverse_lenses` (shortest
focal length, widest aperture), each natural image (linearised, 480×320, the frame
taken as the lens's full calibration frame) is multiplied by the lens's "pa" field.
The error of an estimate is the RMS over the frame of log2(φ̂ / φ), in EV (both
fields are 1 at their centres, no gain is fitted away); "uncorrected" is φ̂ ≡ 1.
The gain-free figure is the same RMS about the frame mean of log2(φ̂/φ), i.e. up to a
global exposure gain (a correction is only defined up to one).

"Do no harm": the same images without vignetting; the false field is the RMS of
log2 φ̂ (EV) of what the estimator would apply.

The "vignetting-free" photos are not free of radial fall-off: measured here, 53–56 %
of the radial log-gradients in their outer ring point inwards (50 % for a symmetric
scene; adding a real lens of 0.24 EV RMS makes it 58 %). An estimator that sees that
fall-off is charged for it by the absolute error. The *differential* error compares
the change of the estimate, log φ̂(vignetted) − log φ̂(clean), with the injected field:
it measures how well the added vignetting is recovered, whatever the photo carried
(it uses the candidate fits, i.e. before the do-no-harm fall-back).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Callable, Sequence

import numpy as np

from vigproc.io.protocol import vignetted
from vigproc.stores.lensfun import diverse_lenses, pa_field
from vigproc.core.model import VignettingModel


def rms_ev(log_ratio: np.ndarray) -> float:
    """RMS of a natural-log field, in EV."""
    return float(np.sqrt(np.mean(log_ratio * log_ratio)) / math.log(2.0))


def gain_free_ev(log_ratio: np.ndarray) -> float:
    """RMS of a natural-log field about its mean, in EV: the error up to a global
    gain (exposure is arbitrary; this is the figure the PSNR's best gain also ignores)."""
    return float(np.std(log_ratio) / math.log(2.0))


@dataclass
class LensfunResult:
    method: str
    n_lenses: int
    n_frames: int
    median_ev: float
    p90_ev: float
    uncorrected_median_ev: float
    gain_free_median_ev: float
    gain_free_uncorrected_ev: float
    differential_median_ev: float
    fallbacks: int
    seconds_per_image: float


@dataclass
class FlatResult:
    method: str
    n_frames: int
    median_ev: float
    worst_ev: float
    candidate_median_ev: float
    fallbacks: int


def run_lensfun(
    images: Sequence[np.ndarray], method: str, fn: Callable[[np.ndarray], VignettingModel],
    n_lenses: int = 20, frames_per_lens: int = 5,
) -> LensfunResult:
    import time

    errs, unc, diff, secs, fb = [], [], [], [], 0
    gf, gf_unc = [], []
    clean_cache: dict[int, np.ndarray] = {}
    lenses = diverse_lenses(n_lenses)
    for idx, (lens, pa) in enumerate(lenses):
        # each lens gets the next ``frames_per_lens`` images, cycling through the set
        for j in range(frames_per_lens):
            k = (idx * frames_per_lens + j) % len(images)
            im = images[k]
            h, w = im.shape[:2]
            true_log = np.log(pa_field((h, w), pa.k1, pa.k2, pa.k3))
            t0 = time.perf_counter()
            m = fn(vignetted(im, true_log))
            secs.append(time.perf_counter() - t0)
            errs.append(rms_ev(m.log_field((h, w)) - true_log))
            unc.append(rms_ev(true_log))
            gf.append(gain_free_ev(m.log_field((h, w)) - true_log))
            gf_unc.append(gain_free_ev(true_log))
            if k not in clean_cache:
                c0 = fn(im)
                clean_cache[k] = (c0.candidate or c0).log_field((h, w))
            diff.append(rms_ev((m.candidate or m).log_field((h, w)) - clean_cache[k] - true_log))
            fb += bool(m.quality and m.quality.fallback)
    return LensfunResult(method, len(lenses), len(errs), float(np.median(errs)), float(np.percentile(errs, 90)),
                         float(np.median(unc)), float(np.median(gf)), float(np.median(gf_unc)),
                         float(np.median(diff)), fb, float(np.mean(secs)))


def run_flat(images: Sequence[np.ndarray], method: str, fn: Callable[[np.ndarray], VignettingModel]) -> FlatResult:
    out, cand, fb = [], [], 0
    for im in images:
        m = fn(im)
        out.append(rms_ev(m.log_field(im.shape[:2])))
        c = m.candidate if m.candidate is not None else m
        cand.append(rms_ev(c.log_field(im.shape[:2])))
        fb += bool(m.quality and m.quality.fallback)
    return FlatResult(method, len(images), float(np.median(out)), float(np.max(out)), float(np.median(cand)), fb)
