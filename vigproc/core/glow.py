"""Is a frame's radial fall-off a lens's, or the glow of a light source in the scene?

A lens's fall-off steepens all the way to the frame's corner: the cos⁴ law, the
mechanical vignetting of the lens barrel and every calibration in lensfun make a log
profile whose slope grows with the radius. Light scattered around a bright source in
the scene (the sun in haze, a lamp in mist) falls as a power of the distance from it,
log I = k·log(ρ² + ρ0²) with k < 0: steepest near ρ0 and easing beyond it. A sunset
photographed with the sun in the middle of the frame is then, to a single-frame fit,
a strong centred vignetting: the lens-family fit removed 0.68 EV from such a frame of
the clean protocol (``vigproc bench clean``), the published radial-gradient peer 0.73.

The test fits both to the luminance's log-difference pairs of the frame's working copy
(:mod:`vigproc.core.family_fit`, module doc steps 1–2; no colour weights, which hide the glow's
shape: the sky around the sun changes colour with its brightness) under the same
Cauchy loss: the centred lens family in its first two components with its prior, and a
glow centred on the frame for each core radius ρ0. When the glow explains the pairs
better by more than a margin, the frame's fall-off is its scene's light, and the default
estimator applies no correction (:func:`vigproc.core.estimate.estimate_default`).

The glow's shape is also the Kang-Weiss model's off-axis illumination
A = (1 + (r/f)²)⁻² when f is short: Lyu's Table 1 fields (f = 100 px on 480×320,
ρ0 ≈ 0.35) have it. On those frames the lens family explains the pairs about as well as a
glow (an advantage of at most 0.016 on the clean protocol's bases other than the sunset),
because their fall-off keeps steepening to the corners; a scene's glow, whose tail
eases, is what the family cannot follow.

References
----------
Y. Zheng, S. Lin, S. B. Kang, R. Xiao, J. Gee, C. Kambhamettu, "Single-image
vignetting correction from gradient distribution symmetries", IEEE TPAMI 35(6), 2013
(the log-gradient pairs).
S. B. Kang, R. Weiss, "Can we calibrate a camera using an image of a flat, textureless
Lambertian surface?", ECCV 2000 (the off-axis illumination factor).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np

from vigproc.core.family_fit import (FamilySettings, FamilyWorkingCopy, bin_rho, family_for, corner_radius, irls,
                                     mean_cauchy_loss, pairs_at, settings_index)
from vigproc.core.lensfamily import LensFamily


@dataclass(frozen=True)
class GlowTest:
    """When the default estimator asks whether a fall-off is a light source's glow.

    Attributes
    ----------
    radii : tuple of float
        The glow's core radii ρ0 tried (half-diagonals). A core beyond 0.5 makes a
        profile that steepens across the frame, as a lens's does.
    margin : float
        The glow must lower the mean Cauchy loss per pair (:func:`glow_advantage`)
        by more than this (dimensionless, as the loss): the clean
        protocol's sunset, a glow, clears it; the lens fields and vignetting-free frames
        mostly do not (measured: ``docs/benchmarks/clean.md``, "How the glow test's
        settings were chosen").
    min_ev : float
        Only a fit that would remove at least this much (EV RMS about the frame mean)
        is tested: a weaker one does little harm if it is a glow (the clean protocol's
        do-no-harm target is 0.25 EV).
    steps, iterations : tuple of int, int
        The pairs' step (working-copy bins) and the most IRLS steps of each fit. With
        the step of 2 alone and 6 steps the test costs about 1 ms a frame and separates the
        sunset as well as steps 1, 2, 4 and 100 IRLS steps (5 ms) did
        (``docs/benchmarks/clean.md``, "How the glow test's settings were chosen").
    """

    radii: tuple[float, ...] = (0.2, 0.4)
    margin: float = 0.1
    min_ev: float = 0.25
    steps: tuple[int, ...] = (2,)
    iterations: int = 6


def glow_advantage(copy: FamilyWorkingCopy, width: int, height: int, family: LensFamily,
                   start: np.ndarray | None = None, settings: FamilySettings = FamilySettings(),
                   test: GlowTest = GlowTest()) -> float:
    """How much better a light source's glow explains a frame's luminance than a lens.

    Parameters
    ----------
    copy : FamilyWorkingCopy
        The frame's luminance working copy (:func:`vigproc.core.family_fit.luminance_copy`;
        its colour copies, if any, are not read).
    width, height : int
        The frame (ρ = 1 at its corner).
    family : LensFamily
        The lens family; its first two components are fitted.
    start : ndarray, optional
        Where the lens fit starts (e.g. the colour fit's first two coefficients).
    settings : FamilySettings
        The fits' Cauchy scale (``grey_sigma``: the pairs are not weighted by colour),
        tempering and tolerance.
    test : GlowTest
        The glow's core radii, the pair steps and the fits' most steps.

    Returns
    -------
    float
        The lens fit's mean Cauchy loss per pair minus the best glow's (module doc);
        positive when the glow explains the pairs better. NaN when the copy has no pairs.
    """
    L, valid, xs, ys = copy.L, copy.valid, copy.xs, copy.ys
    s = replace(settings, sigma=settings.grey_sigma, steps=test.steps, iterations=test.iterations)
    index = settings_index(L, valid, None, s)
    if index.dlog.size == 0:
        return math.nan
    rho = bin_rho(xs, ys, corner_radius(width, height))
    fam = family_for(family, False)
    M, B = fam.profiles(rho)
    d, a = pairs_at(index, M, B)
    pmean, pcov = fam.prior()
    c0 = pmean if start is None else np.asarray(start, dtype=np.float64)[:fam.n_components]
    c = irls(d, a, index.weight, c0, pmean, np.linalg.inv(pcov), s.sigma, s.kappa, s.iterations,
             tolerance=s.tolerance, relaxation=1.6)
    lens = mean_cauchy_loss(d - a @ c, s.sigma, index.weight)
    glows = np.stack([np.log(rho * rho + r0 * r0) for r0 in test.radii], axis=-1)
    dg, ag = pairs_at(index, np.zeros(L.shape), glows)
    best = math.inf
    for j in range(len(test.radii)):
        # a glow brightens towards its source: k ≤ 0 (k > 0 is a dark hole, read as flat)
        k = irls(dg, ag[:, j:j + 1], index.weight, np.array([-1.0]), np.zeros(1), np.full((1, 1), 1e-6),
                 s.sigma, s.kappa, s.iterations, tolerance=s.tolerance, relaxation=1.6)
        best = min(best, mean_cauchy_loss(dg - ag[:, j] * min(float(k[0]), 0.0), s.sigma, index.weight))
    return lens - best
