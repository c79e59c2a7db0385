"""The crop test's power and false alarms on the clean protocol (``vigproc bench crops``).

Bases: the vignetting-free crops of :mod:`benchmarks.clean`. Fields: the radial
fall-off of lensfun lenses (their shapes), scaled to a corner fall-off of 0.25, 0.5
or 1 EV at the lens's own frame corner, with the optical centre moved by 0, 10, 25 or
40 % of the frame's half-diagonal in a random direction (a crop of a larger frame, or
a shifted lens). Beyond the lens's corner the log profile continues with its slope
there. Uncropped frames (offset 0) are the negatives: their statistic is the null
distribution that calibrates the false-alarm probability (fitted on the even-numbered
bases, checked on the odd-numbered ones); cropped frames are the positives.

``statistic="known-profile"`` measures how far the test could go: the centre is fitted
with the lens's own profile known exactly (:func:`known_profile_family`), so only the
scene can move it.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from typing import Sequence

import numpy as np

from benchmarks.clean import HEIGHT, WIDTH
from vigproc.stores.lensfun import pa_poly

FALLOFFS_EV = (0.25, 0.5, 1.0)
OFFSETS = (0.10, 0.25, 0.40)


def lens_log_profile(k: tuple[float, float, float], corner_ev: float, rho: np.ndarray) -> np.ndarray:
    """ln attenuation of a lensfun ``pa`` lens, scaled to ``corner_ev`` at ρ = 1 and
    continued linearly (in ln) past it."""
    def pa(r):
        return np.log(np.maximum(pa_poly(r * r, *k), 1e-6))

    edge = float(pa(np.asarray(1.0)))
    if not edge < 0:
        raise ValueError("the lens has no fall-off at its corner")
    scale = -corner_ev * math.log(2.0) / edge
    slope = (edge - float(pa(np.asarray(0.999)))) / 0.001
    inside = np.minimum(rho, 1.0)
    return scale * (pa(inside) + np.maximum(rho - 1.0, 0.0) * slope)


def shifted_field(k, corner_ev: float, offset: float, angle: float) -> np.ndarray:
    """The 480×320 frame's ln field for a lens centred ``offset`` half-diagonals away
    from the frame's centre in direction ``angle``."""
    big_r = math.hypot((WIDTH - 1) / 2, (HEIGHT - 1) / 2)
    ox, oy = offset * big_r * math.cos(angle), offset * big_r * math.sin(angle)
    x = np.arange(WIDTH) - (WIDTH - 1) / 2 - ox
    y = np.arange(HEIGHT) - (HEIGHT - 1) / 2 - oy
    rho = np.hypot(x[None, :], y[:, None]) / big_r
    return lens_log_profile(k, corner_ev, rho)


def known_profile_family(k: tuple[float, float, float], corner_ev: float):
    """A lens family that is one lens: the profile of ``k`` at ``corner_ev`` as its mean,
    and one component (ρ², centred) held at 0 by a prior of spread 0.01: the crop test
    (:func:`vigproc.forensics.crops.crop_statistic`) in it fits the centre alone."""
    from vigproc.core.lensfamily import N_RADII, LensFamily

    radii = np.linspace(0.0, 1.0, N_RADII)
    comp = radii**2 - np.mean(radii**2)
    spread = np.random.default_rng(0).normal(0.0, 0.01, (50, 1))
    return LensFamily(radii, lens_log_profile(k, corner_ev, radii), (comp / np.linalg.norm(comp))[None, :],
                      spread - spread.mean(), np.full(50, 50.0), np.full(50, 2.8), 0.0, 1)


@dataclass
class CropBench:
    """AUC per (corner fall-off, offset), and false alarms of the calibrated test."""

    n_bases: int
    n_lenses: int
    auc: dict[str, float] = field(default_factory=dict)  # "0.5EV/25%" -> AUC
    false_alarm: dict[str, float] = field(default_factory=dict)  # "0.5EV" -> share of held-out negatives
    power: dict[str, float] = field(default_factory=dict)  # detected share of held-out positives at alpha
    alpha: float = 0.01
    null_z: list[float] = field(default_factory=list)  # every negative's z (the shipped calibration)
    ms_per_frame: float = 0.0


def run(bases: Sequence[np.ndarray], lenses: Sequence[tuple[float, float, float]], family, *,
        alpha: float = 0.01, seed: int = 0, falloffs=FALLOFFS_EV, offsets=OFFSETS,
        statistic: str = "shift") -> CropBench:
    from vigproc.io.protocol import vignetted
    from vigproc.core.family_fit import colour_of
    from vigproc.core.pixels import luminance
    from vigproc.forensics.crops import CropCalibration, auc, crop_statistic

    rng = np.random.default_rng(seed)
    res = CropBench(len(bases), len(lenses), alpha=alpha)
    secs = []
    all_null = []
    for ev in falloffs:
        z = {o: [] for o in (0.0, *offsets)}
        even = {o: [] for o in z}
        for li, k in enumerate(lenses):
            known = known_profile_family(k, ev) if statistic == "known-profile" else None
            for bi, im in enumerate(bases):
                angle = float(rng.uniform(0, 2 * math.pi))
                for o in z:
                    frame = vignetted(im, shifted_field(k, ev, o, angle))
                    t0 = time.perf_counter()
                    # the crop test itself, in the lens's own family when its profile is known
                    _, _, zz, shift, _ = crop_statistic(luminance(frame), known if known is not None else family, colour_of(frame))
                    zz = zz if statistic == "z" else shift
                    secs.append(time.perf_counter() - t0)
                    z[o].append(zz)
                    even[o].append(bi % 2 == 0)
        neg = np.asarray(z[0.0])
        all_null += list(neg)
        ev_mask = np.asarray(even[0.0])
        cal = CropCalibration(np.sort(neg[ev_mask]), "even bases")
        held = neg[~ev_mask]
        res.false_alarm[f"{ev:g}EV"] = float(np.mean([cal.p_value(v) < alpha for v in held]))
        for o in offsets:
            pos = np.asarray(z[o])
            res.auc[f"{ev:g}EV/{o:.0%}"] = auc(pos, neg)
            pm = ~np.asarray(even[o])
            res.power[f"{ev:g}EV/{o:.0%}"] = float(np.mean([cal.p_value(v) < alpha for v in pos[pm]]))
    res.null_z = sorted(float(v) for v in all_null)
    res.ms_per_frame = 1000 * float(np.median(secs))
    return res
