"""How far one frame's lens-family fit can be told from its scene, and a fit shrunk
toward the EXIF population accordingly (issue 38, part a: an experiment, not the default).

A centred scene fall-off (lamp light, a dark road below and a wall above, a chart on a
dark board) and a lens's fall-off look alike to the whole-frame fit, and its jackknife σ
(the spread of refits without one block of pairs) does not see it: every block carries
the same centred scene. Fits of the frame's halves do: top, bottom, left and right see the
scene's fall-off from different sides, while a lens's field is the same in each. Their
disagreement with the whole-frame fit, D (EV, the gain-free RMS over the frame of the
fields' log2 ratio, averaged in square over the halves), less the part the fit's own noise
explains, is read as the fit's scene error: a half holds half the pairs, so its fit's
variance about the truth is about twice the whole frame's, σ² (the fit's calibrated σ), and
its variance about the whole frame's fit about σ² (2σ² − σ², the whole being the halves'
mean); D_scene² = max(0, D² − σ²). The fit is then combined with the EXIF population (the prior of the calibrations
nearest the frame's focal length and f-number, field spread s) by their inverse
variances, w = s² / (s² + D_scene²), c = μ + w (ĉ − μ). Nothing is tuned: D, σ and s are
all read, the frame's own and the population's.

References
----------
issue 38 and docs/benchmarks/real-frames.md, part (a): the designs tried on the frames
whose lens lensfun calibrated (the prior narrowed, the population alone, a shrinkage by
the jackknife σ) and why each was not adopted.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, replace

import numpy as np

from vigproc.core.family_fit import (METHOD, FamilyFit, FamilySettings, LensHint, family_for, field_sigma_ev,
                                     fit_family, frame_rho_grid, profile_to_model)
from vigproc.core.lensfamily import profile_family
from vigproc.core.model import VignettingModel
from vigproc.errors import ModelError

log = logging.getLogger(__name__)

_LN2 = math.log(2.0)
#: The halves whose fits are compared with the whole frame's.
HALVES = ("top", "bottom", "left", "right")


@dataclass(frozen=True)
class Ambiguity:
    """The frame's half fits against its whole-frame fit, and the weight that follows.

    Attributes
    ----------
    disagreement_ev : float
        D_scene (EV): D less the fit's own noise σ, in square (module doc); D itself with
        ``subtract_noise`` False. D: RMS over the halves of the gain-free field RMS (EV) between a half's fit and the
        whole frame's. NaN when fewer than two halves could be fitted.
    prior_spread_ev : float
        s: the field spread (EV) of the EXIF prior the fit is shrunk toward.
    weight : float
        w = s² / (s² + D_scene²): the share of the fit kept (1: the fit, 0: the population mean).
    halves : int
        How many halves were fitted.
    """

    disagreement_ev: float
    prior_spread_ev: float
    weight: float
    halves: int


def _half_masks(shape: tuple[int, int], mask: np.ndarray | None) -> dict[str, np.ndarray]:
    h, w = shape
    yy, xx = np.mgrid[0:h, 0:w]
    base = np.ones(shape, bool) if mask is None else mask.astype(bool)
    return {"top": base & (yy < h / 2), "bottom": base & (yy >= h / 2),
            "left": base & (xx < w / 2), "right": base & (xx >= w / 2)}


def _log2_field(fam, coef: np.ndarray, rho: np.ndarray) -> np.ndarray:
    return fam.log_profile(coef, rho) / _LN2


def _gain_free_rms(x: np.ndarray) -> float:
    return float(np.sqrt(np.mean((x - x.mean()) ** 2)))


def ambiguity(lum: np.ndarray, fit: FamilyFit, mask: np.ndarray | None = None, hint: LensHint | None = None,
              family=None, colour: np.ndarray | None = None,
              settings: FamilySettings = FamilySettings(), subtract_noise: bool = True,
              noise_factor: float = 1.0) -> Ambiguity:
    """Measure the frame's ambiguity between scene and lens (module doc).

    Parameters
    ----------
    lum : ndarray, H×W, linear luminance (the one ``fit`` was made from)
    fit : FamilyFit
        The whole frame's :func:`~vigproc.core.family_fit.fit_family` result.
    mask, hint, family, colour, settings
        As given to that fit.
    subtract_noise : bool
        False: D itself, the noise of the halves' fits included (the first form tried;
        docs/benchmarks/real-frames.md).
    noise_factor : float
        D_scene² = max(0, D² − noise_factor·σ²): 1 if a half's error and the whole's are
        nested (the whole the halves' mean), 3 if they were independent (2σ² + σ²).

    Returns
    -------
    Ambiguity
        ``weight`` 1 (keep the fit) when the fit has no coefficients.
    """
    h, w = lum.shape
    base_fam = family or profile_family()
    fam = family_for(base_fam, fit.colour_weighted)
    hint = hint or LensHint()
    _pm, pcov = fam.prior(hint.focal35, hint.fnumber)
    s = field_sigma_ev(fam, pcov, w, h)
    if fit.coefficients is None:
        return Ambiguity(math.nan, s, 1.0, 0)
    rho = frame_rho_grid(w, h)
    whole = _log2_field(fam, fit.coefficients, rho)
    sq = []
    for name, m in _half_masks((h, w), mask).items():
        part = fit_family(lum, settings, m, family, hint, colour, uncertainty=False)
        if part.coefficients is None:
            continue
        pf = family_for(base_fam, part.colour_weighted)
        sq.append(_gain_free_rms(_log2_field(pf, part.coefficients, rho) - whole) ** 2)
    if len(sq) < 2:
        return Ambiguity(math.nan, s, 1.0, len(sq))
    d2 = float(np.mean(sq))
    m = fit.model.candidate if fit.model.candidate is not None else fit.model
    sigma = m.quality.field_sigma_ev if m.quality is not None else math.nan
    if subtract_noise and math.isfinite(sigma):
        d2 = max(0.0, d2 - noise_factor * sigma * sigma)
    d = math.sqrt(d2)
    wgt = s * s / (s * s + d * d) if s > 0 else 1.0
    return Ambiguity(d, s, wgt, len(sq))


def shrunk_fit(lum: np.ndarray, fit: FamilyFit, amb: Ambiguity, hint: LensHint | None = None,
               family=None) -> VignettingModel:
    """The whole-frame fit combined with the EXIF population by ``amb.weight``.

    The gate's decision is the fit's own: an applied fit stays applied (its field moved
    toward the population), a fit left alone stays alone with the shrunk field as its
    candidate.

    Parameters
    ----------
    lum : ndarray, H×W (only its shape is read)
    fit : FamilyFit
    amb : Ambiguity
        From :func:`ambiguity` of the same fit.
    hint, family
        As given to the fit.

    Returns
    -------
    VignettingModel
        ``fit.model`` itself when the weight is 1, the fit has no coefficients, or the
        combined profile cannot be written as a model.
    """
    if fit.coefficients is None or not (amb.weight < 1.0):
        return fit.model
    h, w = lum.shape
    fam = family_for(family or profile_family(), fit.colour_weighted)
    hint = hint or LensHint()
    pm, _ = fam.prior(hint.focal35, hint.fnumber)
    c = pm + amb.weight * (fit.coefficients - pm)
    try:
        field, _ = profile_to_model(fam.mean + c @ fam.components, fam.radii, w, h)
    except ModelError:
        return fit.model
    m = fit.model
    cand = m.candidate if m.candidate is not None else m
    q = replace(cand.quality, field_ev_rms=field.field_ev_rms()) if cand.quality is not None else None
    new = VignettingModel(w, h, center=field.center, p=field.p, alpha=field.alpha, method=METHOD, quality=q)
    log.debug("fit shrunk to the EXIF population: D %.3f EV, s %.3f EV, weight %.2f",
              amb.disagreement_ev, amb.prior_spread_ev, amb.weight)
    if m.is_identity:
        return replace(m, candidate=new)
    return new


def estimate_shrunk(lum: np.ndarray, mask: np.ndarray | None = None, hint: LensHint | None = None,
                    family=None, colour: np.ndarray | None = None, base=None,
                    subtract_noise: bool = True, noise_factor: float = 1.0) -> VignettingModel:
    """:func:`vigproc.core.estimate.estimate_default`, its centred lens-family fit shrunk
    toward the EXIF population by the frame's ambiguity (module doc).

    Only a frame with an EXIF focal length and f-number is shrunk (without them the prior
    is every lens's, no population of lenses like this one); an off-centre fit, a fit the
    glow test refused and a frame without EXIF come back as the default gives them.

    Parameters
    ----------
    lum, mask, hint, family, colour
        As :func:`~vigproc.core.estimate.estimate_default` takes them.
    base : callable, optional
        The default estimator itself (``estimate_default`` when None): for a caller that
        stands this function in for it.
    subtract_noise, noise_factor
        As :func:`ambiguity` takes them.

    Returns
    -------
    VignettingModel
    """
    if base is None:
        from vigproc.core.estimate import estimate_default as base

    model = base(lum, mask, hint, family, colour)
    if hint is None or hint.focal35 is None or hint.fnumber is None:
        return model
    fit = fit_family(lum, FamilySettings(), mask, family, hint, colour)
    same = (model.is_identity and fit.model.is_identity) or (
        not model.is_identity and not fit.model.is_identity and model.center == (0.0, 0.0)
        and model.alpha == fit.model.alpha)
    if not same:
        return model
    amb = ambiguity(lum, fit, mask, hint, family, colour, subtract_noise=subtract_noise, noise_factor=noise_factor)
    return shrunk_fit(lum, fit, amb, hint, family)
