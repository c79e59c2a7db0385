"""A lens's colour cast from a series of its frames.

One photograph rarely tells a lens's corner tint from its scene's colour: the
per-quadrant corner shifts :func:`vigproc.core.colour_cast.detect_colour_cast` measures
spread over ±10–25 ΔE00 between scenes (docs/benchmarks/colour.md). Between frames of
one lens setting the cast stays and the scene changes, so the scene's part averages
down about as 1/√N. This module pools the frames' per-quadrant shifts:

- each frame adds, per quadrant and per log-chromaticity (ln R/G, ln B/G), its shift
  weighted by w = 1 / (se² + τ²): its own standard error and :data:`SCENE_SCATTER` τ, the
  scatter of a scene's quadrant shift about the lens's (information form: the pooled
  shift is Σ w·x / Σ w, its variance 1 / Σ w);
- a Cauchy weight on each frame's distance from the pooled value (scale τ) keeps one
  sunset from carrying a short series;
- the pooled quadrants are judged as one frame's are: projected on their common
  direction, the weakest quadrant's ΔE00 (mid grey) and z decide.

A series of at least ``min_frames`` frames reports a cast at ``score`` ≥ 1
(:class:`SeriesSettings`), and calls it *decisive* when, besides, every pooled quadrant's
z reaches ``decisive_z`` on at least ``decisive_frames`` frames: the rule a caller must
meet before correcting a cast it did not measure from a flat frame (vigproc itself only
reports one). The rule's rates are measured by ``vigproc bench colour-detect --frames``
(docs/benchmarks/colour.md, "Series of frames").

References
----------
S. Lyu, "Removing vignetting from a single image using natural image statistics",
ICASSP 2010 (../shared/paper/): the per-frame statistic.
P. J. Huber, E. M. Ronchetti, "Robust Statistics", 2nd ed., Wiley 2009, ch. 3
(M-estimates of location, here with the Cauchy ψ).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Sequence

import numpy as np

from vigproc.core.colour_difference import grey_cast_de

#: τ: the scatter (natural-log units, per quadrant and per log-chromaticity) of a
#: scene's quadrant shift about its lens's, a robust SD over the 47 clean colour bases
#: of ``bench colour-detect`` (docs/benchmarks/colour.md, "Series of frames").
SCENE_SCATTER = 0.25


@dataclass(frozen=True)
class SeriesSettings:
    """Decision rule of :func:`pool_cast`.

    Attributes
    ----------
    scene_scatter : float
        τ (see :data:`SCENE_SCATTER`).
    min_sector_de : float
        ΔE00 the weakest pooled quadrant must show along the common direction.
    min_sector_z : float
        z score (against the pooled standard error) the weakest quadrant must reach.
    min_frames : int
        Fewest frames for any cast to be reported.
    decisive_z : float
        z every pooled quadrant must reach for a decisive call.
    decisive_frames : int
        Fewest frames for a decisive call.
    cauchy_c : float
        Cauchy scale of the frames' weights, in τ.
    iterations : int
        IRLS iterations.
    """

    scene_scatter: float = SCENE_SCATTER
    min_sector_de: float = 2.5
    min_sector_z: float = 1.0
    min_frames: int = 3
    decisive_z: float = 3.0
    decisive_frames: int = 9
    # a narrow Cauchy (about a mode): at 2 τ one frame in ten still carried a series
    cauchy_c: float = 0.5
    iterations: int = 10


@dataclass(frozen=True)
class SeriesCast:
    """What a series of one lens setting's frames says about its corner cast.

    Attributes
    ----------
    n_frames : int
        Frames pooled.
    detected : bool
        ``score`` ≥ 1 on at least ``min_frames`` frames.
    decisive : bool
        Detected, every quadrant's z ≥ ``decisive_z``, at least ``decisive_frames`` frames.
    shift : tuple of float
        Pooled corner-versus-centre (ln R/G, ln B/G), the quadrants' weighted mean.
    delta_e : float
        ΔE00 of ``shift`` on a mid grey.
    delta_e_se : float
        Its standard error (ΔE00 of one standard error of ``shift`` along its direction).
    sector_de, sector_z : tuple of float
        Each pooled quadrant's shift along the common direction, as ΔE00 and as z.
    score : float
        min(weakest quadrant ΔE / ``min_sector_de``, weakest z / ``min_sector_z``).
    """

    n_frames: int
    detected: bool
    decisive: bool
    shift: tuple[float, float]
    delta_e: float
    delta_e_se: float
    sector_de: tuple[float, ...]
    sector_z: tuple[float, ...]
    score: float

    def describe(self) -> str:
        """One line for people."""
        what = ("this lens shows a corner cast" if self.detected
                else "no corner cast established for this lens")
        verdict = " (decisive)" if self.decisive else ""
        return (f"{what}{verdict}: dE2000 {self.delta_e:.1f} ± {self.delta_e_se:.1f} "
                f"({self.n_frames} frame{'' if self.n_frames == 1 else 's'})")

    def to_dict(self) -> dict:
        """The JSON report (``profile show --json``'s ``colour_cast``)."""
        return {"frames": self.n_frames, "detected": self.detected, "decisive": self.decisive,
                "delta_e": round(self.delta_e, 3), "delta_e_se": round(self.delta_e_se, 3),
                "shift_log_rg": round(self.shift[0], 5), "shift_log_bg": round(self.shift[1], 5),
                "sector_delta_e": [round(d, 3) for d in self.sector_de],
                "sector_z": [round(z, 3) for z in self.sector_z], "score": round(self.score, 4),
                "summary": self.describe()}


def frame_record(evidence) -> dict | None:
    """What one frame adds to a series: its quadrants' shifts and standard errors (JSON),
    or None when the frame could not be judged.

    Parameters
    ----------
    evidence : ColourCastEvidence
        :func:`vigproc.core.colour_cast.detect_colour_cast`'s result.

    Returns
    -------
    dict or None
        ``{"shift": 4×2, "se": 4×2}``.
    """
    s, e = evidence.sector_shift, evidence.sector_se
    if len(s) != 4 or len(e) != 4:
        return None
    a, b = np.asarray(s, dtype=np.float64), np.asarray(e, dtype=np.float64)
    if not (np.all(np.isfinite(a)) and np.all(np.isfinite(b)) and np.all(b >= 0)):
        return None
    return {"shift": a.round(6).tolist(), "se": b.round(6).tolist()}


def check_record(rec: object) -> tuple[np.ndarray, np.ndarray]:
    """A :func:`frame_record` as arrays (4×2 each). Raises ValueError when it is not one."""
    if not isinstance(rec, dict):
        raise ValueError("a frame's cast record must be a dict")
    try:
        a = np.asarray(rec["shift"], dtype=np.float64)
        b = np.asarray(rec["se"], dtype=np.float64)
    except (KeyError, TypeError, ValueError):
        raise ValueError("a frame's cast record needs 4×2 'shift' and 'se'") from None
    if a.shape != (4, 2) or b.shape != (4, 2) or not (np.all(np.isfinite(a)) and np.all(np.isfinite(b))) \
            or np.any(b < 0):
        raise ValueError("a frame's cast record needs finite 4×2 'shift' and 'se' (se ≥ 0)")
    return a, b


def pool_cast(shifts: np.ndarray, ses: np.ndarray, settings: SeriesSettings = SeriesSettings()) -> SeriesCast:
    """Pool N frames' per-quadrant corner shifts into the lens's cast.

    Parameters
    ----------
    shifts : numpy.ndarray
        N×4×2 per-quadrant (ln R/G, ln B/G) corner shifts.
    ses : numpy.ndarray
        N×4×2 their standard errors.
    settings : SeriesSettings
        τ and the decision rule.

    Returns
    -------
    SeriesCast
        The pooled cast and the decision.

    Raises
    ------
    ValueError
        Shapes that are not N×4×2 with N ≥ 1.
    """
    x = np.asarray(shifts, dtype=np.float64)
    se = np.asarray(ses, dtype=np.float64)
    if x.ndim != 3 or x.shape[1:] != (4, 2) or x.shape != se.shape or x.shape[0] < 1:
        raise ValueError(f"shifts and ses must be N×4×2 with N ≥ 1, got {x.shape} and {se.shape}")
    n = x.shape[0]
    tau = settings.scene_scatter
    w0 = 1.0 / (se * se + tau * tau)
    m = np.median(x, axis=0)
    s2 = (settings.cauchy_c * tau) ** 2
    for _ in range(settings.iterations):
        r = x - m
        w = w0 / (1.0 + r * r / s2)
        m = (w * x).sum(axis=0) / w.sum(axis=0)
    var = 1.0 / w0.sum(axis=0)  # the information's, not the down-weighted frames': no false confidence
    qw = 1.0 / var
    shift = (qw * m).sum(axis=0) / qw.sum(axis=0)
    shift_var = 1.0 / qw.sum(axis=0)
    norm = float(np.hypot(*shift))
    if norm <= 0:
        z4 = (0.0,) * 4
        return SeriesCast(n, False, False, (0.0, 0.0), 0.0, 0.0, z4, z4, 0.0)
    e = shift / norm
    proj = m @ e
    proj_se = np.sqrt(var @ (e * e))
    sector_de = np.sign(proj) * grey_cast_de(np.abs(proj) * e[0], np.abs(proj) * e[1])
    sector_z = proj / np.maximum(proj_se, 1e-12)
    score = min(float(sector_de.min()) / settings.min_sector_de, float(sector_z.min()) / settings.min_sector_z)
    delta_e = float(grey_cast_de(shift[0], shift[1]))
    se_along = math.sqrt(float(shift_var @ (e * e)))
    delta_e_se = abs(float(grey_cast_de(*(shift + se_along * e))) - delta_e)
    detected = score >= 1.0 and n >= settings.min_frames
    decisive = detected and float(sector_z.min()) >= settings.decisive_z and n >= settings.decisive_frames
    return SeriesCast(n, detected, decisive,
                      (float(shift[0]), float(shift[1])), delta_e, delta_e_se,
                      tuple(float(d) for d in sector_de), tuple(float(z) for z in sector_z), float(score))
