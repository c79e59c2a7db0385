"""Physical plausibility: the rules a field must pass before it is divided out of a frame.

A single-frame estimate can take a scene's own light (a sky, a lit room, the black
surround of a circular fisheye) for vignetting. Whatever path produced a field (the
default estimator and its off-centre fits, ``robust``, an estimator plugin, a profile
source), the pipeline asks :func:`judge` before applying it
(:meth:`vigproc.pipeline.processor.Processor.process_image`), and refuses it when:

``brighter-corners``
    a corner of the frame is brighter than the field's centre by more than
    :attr:`Rules.corner_tolerance_ev`: no lens brightens its corners; nor, for a fitted
    field, may it brighten on the way out from its centre to a corner by more than
    :attr:`Rules.outward_tolerance_ev` (:func:`outward_rise_ev`: a bright ring inside the
    frame, or a dip that comes back up, is a scene's light, not a lens's);
``beyond-real-lenses``
    its fall-off (the field's centre against its darkest corner) is deeper than any of
    lensfun's calibrations at a similar 35-mm focal length and f-number
    (:func:`population_max_ev`: the :attr:`Rules.neighbours` calibrations nearest in log
    focal length and log f-number, every calibration when the EXIF gives neither), plus
    :attr:`Rules.margin_ev`;
``low-confidence``
    its fit states a confidence below :attr:`Rules.min_confidence` (each estimator's
    confidence is 0.5 at its own fall-back threshold);
``clips-highlights``
    the correction would push more than :attr:`Rules.max_new_white` of the frame's
    pixels past white in an output that clips there (an integer format), counted on
    a strided sample of the frame (every k-th row and column: exact pixel values,
    about :attr:`Rules.sample_long_side` on the long side).

A field of another kind of evidence (a trusted learned profile, lensfun's calibration,
a DNG's or a maker's own calibration, a profile file the user named: ``calibrated=True``)
is measured, not fitted to this frame: only ``brighter-corners`` applies to it. Its
depth is the lens's, its confidence is not a single frame's, and the highlights it
pushes past white are the lens's fall-off removed (a float output keeps them; the
pipeline warns).
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, replace

import numpy as np

from vigproc.core.lensfamily import profile_family
from vigproc.core.model import FitQuality, VignettingModel
from vigproc.errors import ModelError

log = logging.getLogger(__name__)

__all__ = ["Refusal", "Rules", "corner_ev", "judge", "new_white_share", "outward_rise_ev", "population_max_ev",
           "refused"]

BRIGHTER_CORNERS = "brighter-corners"
BEYOND_REAL_LENSES = "beyond-real-lenses"
LOW_CONFIDENCE = "low-confidence"
CLIPS_HIGHLIGHTS = "clips-highlights"


@dataclass(frozen=True)
class Rules:
    """The plausibility rules' thresholds.

    Attributes
    ----------
    corner_tolerance_ev : float
        How much brighter than the field's centre a corner may be (numerical slack).
    outward_tolerance_ev : float
        How much a fitted field may brighten on its way out to a corner
        (:func:`outward_rise_ev`). lensfun's pa calibrations, each to its own corner and to a
        1.5× smaller sensor's (47,395 fields): 99 % rise by at most 0.053 EV, 99.9 % by
        0.10 EV; 48 (0.1 %) by more than 0.1 EV.
    margin_ev : float
        Added to the deepest real-lens fall-off of the population.
    neighbours : int
        Calibrations nearest the frame's 35-mm focal length and f-number that form the
        population.
    min_confidence : float
        Fits stating a lower confidence are refused.
    max_new_white : float
        Largest share of pixels the correction may push past white (clipping outputs).
    sample_long_side : int
        Long side of the strided sample the share is counted on.
    """

    corner_tolerance_ev: float = 0.02
    outward_tolerance_ev: float = 0.1
    margin_ev: float = 0.25
    neighbours: int = 200
    min_confidence: float = 0.5
    max_new_white: float = 0.005
    sample_long_side: int = 512


@dataclass(frozen=True)
class Refusal:
    """Why a field is not applied: the rule's name and a sentence for people."""

    rule: str
    reason: str


def corner_ev(model: VignettingModel) -> tuple[float, float]:
    """The field's corners against its centre, in EV.

    The centre is the brighter of the field's own centre and the frame's (a
    Kang-Weiss field is 1 at its own centre, which may lie outside the frame).

    Returns
    -------
    (brightest, depth) : tuple of float
        ``brightest``: how much the brightest corner exceeds the centre (> 0: brighter
        corners); ``depth``: how much the darkest corner falls below it (the fall-off
        a correction removes there).
    """
    if model.is_identity:
        return 0.0, 0.0
    hx, hy = (model.width - 1) / 2.0, (model.height - 1) / 2.0
    xs = np.array([-hx, hx, -hx, hx, 0.0, model.center[0]])
    ys = np.array([-hy, -hy, hy, hy, 0.0, model.center[1]])
    lg = model.log_field_at(xs, ys) / math.log(2.0)
    centre = float(max(lg[4], lg[5]))
    corners = lg[:4]
    return float(corners.max()) - centre, centre - float(corners.min())


def outward_rise_ev(model: VignettingModel, samples: int = 65) -> float:
    """How much the field brightens, at most, anywhere on a straight line from its own
    centre out to a corner of the frame: the largest rise of the field over the darkest
    point nearer the centre on that line, in EV (0 for a field that only darkens outward,
    as a lens's does; a bright ring inside the frame or corners that come back up count).

    Parameters
    ----------
    model : VignettingModel
    samples : int
        Points on each line, the centre and the corner included.

    Returns
    -------
    float
        ≥ 0.
    """
    if model.is_identity:
        return 0.0
    hx, hy = (model.width - 1) / 2.0, (model.height - 1) / 2.0
    t = np.linspace(0.0, 1.0, samples)
    cx, cy = model.center
    rise = 0.0
    for x, y in ((-hx, -hy), (hx, -hy), (-hx, hy), (hx, hy)):
        try:
            lg = model.log_field_at(cx + t * (x - cx), cy + t * (y - cy)) / math.log(2.0)
        except ModelError:  # the field reaches zero off the frame, before its corner: no line to read
            continue
        rise = max(rise, float(np.max(lg - np.minimum.accumulate(lg))))
    return rise


def _corner_population() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(corner fall-off in EV, 35-mm focal length, f-number) of every calibration of the
    shipped lens family (its profile at ρ = 1, the calibration's corner)."""
    fam = profile_family()
    cache = fam.__dict__.setdefault("_corner_ev", None)
    if cache is None:
        ev = -(fam.mean[-1] + fam.coefficients @ fam.components[:, -1]) / math.log(2.0)
        cache = fam.__dict__["_corner_ev"] = (ev, fam.focal35, fam.fnumber)
    return cache


def population_max_ev(focal35: float | None = None, fnumber: float | None = None,
                      neighbours: int = Rules.neighbours) -> float:
    """The deepest corner fall-off (EV) of lensfun's calibrations like the frame's lens.

    Parameters
    ----------
    focal35, fnumber : float, optional
        The frame's 35-mm-equivalent focal length and f-number (EXIF). With either,
        the ``neighbours`` calibrations nearest in log focal length and log f-number
        (the one given); with neither, every calibration.

    Returns
    -------
    float
        The largest corner fall-off among them, in EV (no margin added).
    """
    ev, f35, fno = _corner_population()
    dist = np.zeros(ev.shape)
    usable = [(v, arr) for v, arr in ((focal35, f35), (fnumber, fno))
              if v is not None and math.isfinite(v) and v > 0]
    if not usable:
        return float(ev.max())
    for v, arr in usable:
        dist = dist + np.log(arr / v) ** 2
    near = np.argsort(dist, kind="stable")[:neighbours]
    return float(ev[near].max())


def new_white_share(img: np.ndarray, model: VignettingModel, strength: float = 1.0,
                    sample_long_side: int = Rules.sample_long_side) -> float:
    """Share of the frame's pixels that a correction pushes past white (1.0).

    Counted on a strided sample (every k-th row and column, exact pixel values) of
    about ``sample_long_side`` on the long side; a pixel counts when its brightest
    channel is below 1.0 before and at or above it after.

    Parameters
    ----------
    img : ndarray
        The linear frame, H×W or H×W×C (channels last).
    model : VignettingModel
        The field to divide out (a model with ``correct_image``, such as a DNG gain
        map, is asked to correct itself).
    strength : float

    Returns
    -------
    float
        In [0, 1].
    """
    from vigproc.core.correct import correct

    a = np.asarray(img)
    k = max(1, -(-max(a.shape[:2]) // sample_long_side))
    sample = np.ascontiguousarray(a[::k, ::k], dtype=np.float32)
    how = dict(channel_axis=-1 if sample.ndim == 3 else None, strength=strength)
    out = model.correct_image(sample, **how) if hasattr(model, "correct_image") else correct(sample, model, **how)
    before, after = _brightest(sample), _brightest(out)
    return float(np.count_nonzero((before < 1.0) & (after >= 1.0))) / max(1, before.size)


def _brightest(x: np.ndarray) -> np.ndarray:
    """Each pixel's brightest channel (H×W) of an H×W×C frame; an H×W frame as it is."""
    if x.ndim != 3:
        return x
    # channel by channel: max(axis=-1) over 3 channels reduces along the short axis, about
    # 50 times slower (50-70 ms of a 512-px sample on a loaded machine against 1 ms)
    b = x[..., 0].copy()
    for i in range(1, x.shape[2]):
        np.maximum(b, x[..., i], out=b)
    return b


def judge(model: VignettingModel, img: np.ndarray | None = None, *, calibrated: bool = False,
          focal35: float | None = None, fnumber: float | None = None, strength: float = 1.0,
          clips: bool = True, rules: Rules = Rules()) -> Refusal | None:
    """Whether a field may be divided out of its frame: None, or the first rule it breaks.

    Parameters
    ----------
    model : VignettingModel
        The field about to be applied (not a fall-back: ``model.candidate`` is None).
    img : ndarray, optional
        The frame (linear, channels last) for the highlights rule; without it that rule
        is not asked.
    calibrated : bool
        A measured calibration of the lens (stored profile, lensfun, DNG/maker
        calibration, profile file): only the brighter-corners rule applies.
    focal35, fnumber : float, optional
        The frame's EXIF 35-mm focal length and f-number (the real-lens population).
    strength : float
        Fraction of the fall-off that would be removed.
    clips : bool
        Whether the output clips at white (an integer format).
    rules : Rules

    Returns
    -------
    Refusal or None
    """
    if model.is_identity or strength <= 0:
        return None
    brightest, depth = corner_ev(model)
    if brightest > rules.corner_tolerance_ev:
        return Refusal(BRIGHTER_CORNERS, f"a corner of the field is {brightest:+.2f} EV brighter than its centre: "
                                         "no lens brightens its corners")
    if calibrated:  # a measured field is the lens's, whatever its shape
        return None
    rise = outward_rise_ev(model)
    if rise > rules.outward_tolerance_ev:
        return Refusal(BRIGHTER_CORNERS, f"the field brightens by {rise:.2f} EV on its way out to a corner: "
                                         "no lens brightens towards its corners")
    q = model.quality
    if q is not None and math.isfinite(q.confidence) and q.confidence < rules.min_confidence:
        return Refusal(LOW_CONFIDENCE, f"confidence {q.confidence:.2f} is below {rules.min_confidence:.2f}: "
                                       "the frame does not show this fall-off clearly")
    limit = population_max_ev(focal35, fnumber, rules.neighbours) + rules.margin_ev
    if strength * depth > limit:
        like = (f"lenses like this one ({_describe(focal35, fnumber)})" if (focal35 or fnumber)
                else "any real lens")
        return Refusal(BEYOND_REAL_LENSES, f"a {strength * depth:.2f} EV corner fall-off is beyond what {like} "
                                           f"show in lensfun's calibrations ({limit:.2f} EV with margin)")
    if clips and img is not None:
        share = new_white_share(img, model, strength, rules.sample_long_side)
        if share > rules.max_new_white:
            return Refusal(CLIPS_HIGHLIGHTS, f"the correction would push {100 * share:.1f} % of the pixels past "
                                             f"white (at most {100 * rules.max_new_white:.1f} %): a scene's light, "
                                             "not a lens's fall-off")
    return None


def _describe(focal35: float | None, fnumber: float | None) -> str:
    parts = ([f"{focal35:g} mm (35-mm equivalent)"] if focal35 else []) + ([f"f/{fnumber:g}"] if fnumber else [])
    return " at ".join(parts)


def refused(model: VignettingModel, refusal: Refusal) -> VignettingModel:
    """The identity model that replaces a refused field: the field kept as its
    ``candidate``, its quality marked fallen back with the refusal's reason."""
    q = model.quality or FitQuality()
    plain = model if model.candidate is None else replace(model, candidate=None)
    return VignettingModel.identity(model.width, model.height, method=model.method, candidate=plain,
                                    quality=replace(q, fallback=True, reason=refusal.reason))
