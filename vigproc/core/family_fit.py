"""The lens-family estimator: a centred fall-off in the space real lenses span.

Why one module over the house's 1000 lines: steps 1-7 below are one estimator. Its stages (the
working copy and its gradient pairs, the IRLS fit, the jackknife, the profile written as a
Kang-Weiss model and the off-centre fits) share one settings record
(:class:`FamilySettings`) and one working copy (:class:`FamilyWorkingCopy`) and are tuned
together (``docs/benchmarks/clean.md``); split by stage, each module would import most of
the others' internals. Its compiled loop is in :mod:`vigproc.core._kernels.irls`.

Real lenses' fall-offs are a two- or three-parameter family
(:mod:`vigproc.core.lensfamily`), so a single photograph need only fix two or three
coefficients, not the twelve of the free Kang-Weiss model: far less room for the
scene's own shading to pass as vignetting.

1. Bin the linear luminance to a working copy (long side ≈ ``work_size``), masking
   dark, clipped and invalid pixels; take logs.
2. Data: log differences per unit step d = (L(v+s·e) − L(v))/s, s ∈ ``steps``,
   e ∈ {x, y}. Natural images' log-gradients are sparse and peaked at zero, so the
   lens shows as their mode: a Cauchy loss of small scale σ follows the mode and
   ignores edges and texture (Zheng et al.'s radial-gradient insight).
   In a colour frame each pair is also weighted by how alike its R, G and B change
   (:func:`family_pairs`, ``chroma_tau``): a lens
   divides every channel alike, while much of a scene's own smooth shading changes
   colour as it changes brightness (a sky whitening towards the horizon, daylight
   meeting lamplight, one coloured surface meeting another); measured in
   ``docs/benchmarks/clean.md``.
3. Model: log φ(ρ) = m(ρ) + Σ_k c_k b_k(ρ), ρ = distance from the frame centre in
   half-diagonals, in every component of the family when the pairs are weighted by
   colour and in the first two otherwise (:func:`family_for`); a Gaussian prior on c from lensfun's calibrations (narrowed to
   lenses like the frame's EXIF when given). In a colour frame a pair's luminance
   change also has its chroma change as covariates, d = a·c + γ·Δchroma with γ ~
   N(0, ``chroma_covariate``²): where a scene's brightness goes with its colour
   (surfaces, coloured light), γ explains it and the field need not; a lens moves no
   chroma (``docs/benchmarks/clean.md``). Linear in c: IRLS solves it exactly
   (:func:`irls`: one compiled loop on one thread, each step's weighted sums as
   reductions over the regressors' rows; as BLAS matrix-vector products, the BLAS's
   threads spun against other processes. A process that pools a profile loads this one
   cached kernel).
4. Uncertainty: neighbouring pairs are far from independent, so the Gauss-Newton
   covariance understates the error. A delete-one-block jackknife (3×3 blocks) measures
   how much the scene moves the estimate; its field spread, scaled by a factor measured
   on vignetting-free photographs (``sigma_scale``, ``sigma_floor``), is
   ``quality.field_sigma_ev``.
5. Do no harm: when the field is not ``min_snr`` times its uncertainty, return the
   identity model and keep the fit as ``candidate``.
6. The profile is written as the Kang-Weiss model (centred, circular P, α1..α7 by
   least squares) so every consumer of :class:`~vigproc.core.model.VignettingModel` works
   unchanged; the conversion error is about 0.001 EV.
7. Off-centre: :func:`fit_centre` fits the centre too (the test that sends a frame to an
   off-centre fit, and the crop evidence of forensics); :func:`fit_off_centre` fits the
   family's profile with a free centre and an elliptical radius (the default
   estimator's fit of a strong fall-off whose centre moves).

References
----------
S. Lyu, ACM MM&Sec 2010, Eq. (2) (the model the result is written in).
Y. Zheng, S. Lin, S. B. Kang, R. Xiao, J. Gee, C. Kambhamettu, "Single-image
vignetting correction from gradient distribution symmetries", IEEE TPAMI 35(6), 2013.
B. Efron, C. Stein, "The jackknife estimate of variance", Ann. Statist. 9(3), 1981.
"""

from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass, replace
from typing import NamedTuple, Sequence

import numpy as np

from vigproc.core._kernels.geometry import geometry_pairs
from vigproc.core._kernels.irls import irls_fit
from vigproc.core._kernels.blocks import block_normal, linear_refits
from vigproc.core._kernels.gauss_newton import geometry_gauss_newton
from vigproc.core._kernels.pairs import gather_pairs, list_pairs
from vigproc.core.pixels import binned_coords, binned_log_channels, binned_log_copy
from vigproc.core.lensfamily import N_COMPONENTS, LensFamily, default_family, profile_family
from vigproc.core.model import N_ALPHA, FitQuality, VignettingModel
from vigproc.errors import InvalidImageError, ModelError

log = logging.getLogger(__name__)

_LN2 = math.log(2.0)
#: Method name recorded in the models this estimator returns.
METHOD = "lens-family"
#: Fewer usable bins than this: no estimate (identity, fallback).
MIN_VALID_BINS = 200
#: ρ samples for writing the profile as a Kang-Weiss model.
_KW_SAMPLES = 129
#: r = KW_SCALE at the frame corner in the written model (A = 1/(1+(r/2)²)² there).
KW_SCALE = 1.0


@dataclass(frozen=True)
class LensHint:
    """What EXIF says of the lens, to narrow the prior to lenses like it.

    Attributes
    ----------
    focal35 : float or None
        35-mm-equivalent focal length in mm.
    fnumber : float or None
    """

    focal35: float | None = None
    fnumber: float | None = None


@dataclass(frozen=True)
class FamilySettings:
    """Tuning of the lens-family estimator (measured on vignetting-free photographs:
    ``vigproc bench clean``; see docs/estimator.md).

    Attributes
    ----------
    work_size : int
        Long side of the binned working copy.
    steps : tuple of int
        Pair steps in working-copy bins.
    sigma : float
        Cauchy scale of the per-step log-difference residual. Small: the fit follows
        the mode of the gradients (flat parts of the scene), not their mean.
    kappa : float
        Tempering of the data's information (pairs are correlated).
    iterations : int
        Most IRLS steps.
    tolerance : float
        IRLS stops when no coefficient moves by this much in a step (1e-3: the field
        then moves by well under 0.001 EV; 1e-4 took a third more steps for the same
        errors, a script).
    jackknife_blocks : int
        The frame is cut into this many × this many blocks for the jackknife.
    jackknife_iterations : int
        Most IRLS steps of each jackknife fit (started from the full fit).
    dark_fraction : float
        Bins darker than this fraction of the 99th percentile are masked.
    sigma_scale, sigma_floor : float
        Calibration of the reported uncertainty: σ = hypot(scale·σ_jackknife, floor) EV.
    grey_sigma : float
        The Cauchy scale of a fit whose pairs are not weighted by colour (a grey frame, or
        one whose channels change alike): without the colour weights, more of a scene's
        own shading is in the pairs, and a smaller scale follows the mode of the
        gradients more closely. In log units per step, like ``sigma``; chosen in
        ``docs/benchmarks/clean.md``.
    grey_sigma_scale : float
        The scale for a fit whose pairs are not weighted by colour (a grey frame, or one
        whose channels change alike), dimensionless: calibrated on the clean protocol's
        luminance (``vigproc bench clean --grey``, ``docs/benchmarks/clean.md``).
    min_snr, grey_min_snr : float
        Fall back to no correction below this field / σ; ``grey_min_snr`` for a fit whose
        pairs are not weighted by colour. Dimensionless (the field's spread in units of its
        σ); the trade between frames left alone and real lenses corrected is measured in
        ``docs/benchmarks/clean.md``.
    off_centre_shift : float
        A centre at least this far from the frame's (half-diagonals,
        :func:`fit_centre`) makes the default estimator try an off-centre fit
        (:func:`fit_off_centre` or the free Kang-Weiss fit).
    select_margin : float
        ... which it keeps when its mean Cauchy loss per pair (:func:`pair_losses`) is
        lower than the lens-family fit's by more than this.
    chroma_tau : float
        Colour frames: the chroma change per step (log units, (ΔR − ΔG, ΔB − ΔG)) at
        which a pair's weight halves; 0 leaves colour out. Well above a lens's own
        colour shading per step and well below a scene's colour edges (measured on
        the clean protocol, ``vigproc bench clean``).

    chroma_covariate : float
        Colour frames: the prior s.d. of the two coefficients γ by which a pair's chroma
        change ((ΔR − ΔG, ΔB − ΔG) per step) enters the model of its luminance change,
        d = a·c + γ·Δchroma (module doc, step 3); 0 leaves them out. A scene's surfaces
        and lights change brightness with colour; a lens changes no colour, so γ takes
        up scene shading the field would otherwise. In log units of luminance change per
        unit of chroma change; chosen in ``docs/benchmarks/clean.md``.

    The defaults of ``sigma``, ``kappa`` and ``chroma_tau`` were tuned together on the
    clean protocol (``docs/benchmarks/clean.md``).
    """

    work_size: int = 96
    steps: tuple[int, ...] = (1, 2, 4)
    sigma: float = 0.0075
    kappa: float = 0.15
    iterations: int = 100
    tolerance: float = 1e-3
    jackknife_blocks: int = 3
    jackknife_iterations: int = 5
    dark_fraction: float = 0.01
    sigma_scale: float = 1.6
    sigma_floor: float = 0.005
    grey_sigma: float = 0.006
    grey_sigma_scale: float = 4.0
    min_snr: float = 1.0
    grey_min_snr: float = 0.9
    off_centre_shift: float = 0.2
    select_margin: float = 0.01
    chroma_tau: float = 0.002
    chroma_covariate: float = 0.3


#: The jackknife and σ of a single frame's estimate (:class:`FamilySettings`' defaults):
#: 3×3 blocks, refits of at most 5 steps (the chroma covariates held at the full fit's),
#: σ = hypot(1.6·σ_jackknife, 0.005 EV); how the scale and the 3×3 blocks were chosen:
#: docs/benchmarks/clean.md, "How the lens-family fit's settings were chosen".
#:
#: Profile pooling, the lens-match test and the crop test were calibrated (their
#: shipped scene scatter and null tables) on fits made with the earlier single-frame
#: settings (a 2×2 jackknife of 30-step refits, σ scale 2.25 and floor 0.01, Cauchy scale
#: 0.01, κ = 0.3, τ = 0.003), and keep them: :data:`EVIDENCE_SETTINGS`.
#:
#: The fit those settings make (Cauchy scale, κ, tolerance, τ), apart from its jackknife
#: and σ calibration: the evidence's, and the default estimator's off-centre path's
#: (:attr:`vigproc.core.estimate.OffCentreRule.settings`).
EVIDENCE_FIT = {"sigma": 0.01, "grey_sigma": 0.01, "kappa": 0.3, "tolerance": 1e-4, "chroma_tau": 0.003,
                "chroma_covariate": 0.0}
EVIDENCE_SETTINGS = FamilySettings(**EVIDENCE_FIT, jackknife_blocks=2, jackknife_iterations=30,
                                   sigma_scale=2.25, sigma_floor=0.01, grey_sigma_scale=2.25, min_snr=0.75)


class FamilyWorkingCopy(NamedTuple):
    """A frame's binned log working copy: log luminance ``L`` and its usable bins
    ``valid`` (h, w), the bins' centres ``xs`` (w,), ``ys`` (h,) in px from the frame
    centre, the R, G, B log copies ``C`` (3, h, w) that weigh pairs by colour (None: a
    grey fit), and the bin size ``k``."""

    L: np.ndarray
    valid: np.ndarray
    xs: np.ndarray
    ys: np.ndarray
    C: np.ndarray | None
    k: int


def luminance_copy(lum: np.ndarray, settings: FamilySettings, mask: np.ndarray | None) -> FamilyWorkingCopy:
    """The luminance's working copy (step 1 of the module doc)."""
    h, w = lum.shape
    L, valid, k = binned_log_copy(lum, settings.work_size, settings.dark_fraction, mask)
    return FamilyWorkingCopy(L, valid, binned_coords(w, k), binned_coords(h, k), None, k)


def with_colour(copy: FamilyWorkingCopy, colour: np.ndarray, settings: FamilySettings) -> FamilyWorkingCopy:
    """A luminance working copy made the colour fit's: the R, G, B log copies of
    ``colour`` (H×W×3, linear), and only the bins every channel can use
    (:func:`_with_chroma`)."""
    hb, wb = copy.L.shape
    if np.ndim(colour) != 3 or np.shape(colour)[2] < 3 or np.shape(colour)[0] // copy.k != hb \
            or np.shape(colour)[1] // copy.k != wb:
        raise InvalidImageError(f"colour must be the frame's R, G, B (channels last), "
                                f"got an array of shape {np.shape(colour)}")
    channels = binned_log_channels(np.asarray(colour)[..., :3], copy.k, copy.valid, settings.dark_fraction)
    valid, C = _with_chroma(copy.valid, channels, settings)
    return copy._replace(valid=valid, C=C)


def same_copy(a: FamilySettings, b: FamilySettings) -> bool:
    """Whether settings ``a`` and ``b`` make the same working copy of a frame (its
    luminance's, and its colour fit's: :func:`luminance_copy`, :func:`with_colour`), so
    that one copy serves fits with either."""
    return a.work_size == b.work_size and a.dark_fraction == b.dark_fraction \
        and (a.chroma_tau > 0) == (b.chroma_tau > 0)


def _working_copy(lum: np.ndarray, settings: FamilySettings, mask: np.ndarray | None,
                  colour: np.ndarray | None = None) -> FamilyWorkingCopy:
    """The working copy a fit reads: the colour fit's when ``colour`` is given
    (:func:`with_colour`), else the luminance's."""
    h, w = lum.shape
    if colour is not None and (np.ndim(colour) != 3 or np.shape(colour)[:2] != (h, w) or np.shape(colour)[2] < 3):
        raise InvalidImageError(f"colour must be the frame's {h}x{w} R, G, B (channels last), "
                                f"got an array of shape {np.shape(colour)}")
    copy = luminance_copy(lum, settings, mask)
    return copy if colour is None else with_colour(copy, colour, settings)


#: A colour frame whose channels are all usable on less than this share of its usable
#: bins (an empty channel, monochromatic light) is fitted as a grey frame.
MIN_CHROMA_SHARE = 0.5


def _with_chroma(valid: np.ndarray, channels: tuple[np.ndarray, np.ndarray] | None, settings: FamilySettings):
    """The usable bins and the R, G, B log copies (3×h×w) the pair weights read, or
    (``valid``, None): no colour, ``chroma_tau`` off, or too few bins where every
    channel is usable (:data:`MIN_CHROMA_SHARE`).

    A bin too dark in one channel (< 1 % of its 99th percentile: a deeply saturated
    colour) is left out of a colour fit: its chroma cannot be read, and keeping its
    pairs at weight 1 brought back the coloured shading the weights leave out (clean
    protocol: 0.053 EV against 0.046).
    """
    if channels is None or settings.chroma_tau <= 0:
        return valid, None
    C, cvalid = channels
    if C.ndim != 3 or C.shape[0] != 3 or cvalid.shape != C.shape or C.shape[1:] != valid.shape:
        raise ValueError(f"colour channels must be 3×{valid.shape[0]}×{valid.shape[1]} with their masks, "
                         f"got {C.shape} and {cvalid.shape}")
    both = valid & cvalid.all(axis=0)
    if both.sum() < max(MIN_CHROMA_SHARE * valid.sum(), MIN_VALID_BINS):
        return valid, None
    return both, np.ascontiguousarray(C, dtype=np.float64)


def _confidence(snr: float, min_snr: float) -> float:
    """A fit's confidence: a logistic of its SNR about the fall-back threshold."""
    return float(1.0 / (1.0 + math.exp(-2.0 * (snr - min_snr))))


def colour_of(img: np.ndarray) -> np.ndarray | None:
    """The R, G, B channels of a checked frame (H×W×C, channels last) whose chroma the
    fit may weigh pairs by, or None (a grey frame, or one with fewer channels)."""
    return img[..., :3] if img.ndim == 3 and img.shape[-1] >= 3 else None


@dataclass(frozen=True)
class PairIndex:
    """The usable log-difference pairs of a working copy, apart from the field divided
    out: what :func:`pairs_at` needs to give a fit's data for any field (the centre fit
    asks for a new field at each step; the pairs and their weights stay).

    Attributes
    ----------
    first, second : ndarray of int (n,)
        Flat bin indices of each pair's bins (v and v + s·e).
    inv_step : ndarray (n,)
        1/s.
    dlog : ndarray (n,)
        (L(v + s·e) − L(v)) / s.
    labels : ndarray of int (n,)
        The block of each pair's first bin.
    weight : ndarray (n,)
        Each pair's colour weight (:func:`family_pairs`).
    chroma : ndarray (2, n) or (0, n)
        Each pair's chroma change per unit step, (ΔR − ΔG)/s and (ΔB − ΔG)/s of the
        log channels, as rows (the layout :func:`irls` reads); no rows without colour.
    """

    first: np.ndarray
    second: np.ndarray
    inv_step: np.ndarray
    dlog: np.ndarray
    labels: np.ndarray
    weight: np.ndarray
    chroma: np.ndarray


def pair_index(L: np.ndarray, valid: np.ndarray, steps: np.ndarray, block: np.ndarray,
               C: np.ndarray | None, tau: float) -> PairIndex:
    """The :class:`PairIndex` of a working copy; parameters as :func:`family_pairs`
    (listed in one compiled pass: :mod:`vigproc.core._kernels.pairs`)."""
    colour = C is not None
    first, second, inv, dl, lab, wt, chroma = list_pairs(
        np.ascontiguousarray(L, dtype=np.float64), np.ascontiguousarray(valid, dtype=np.bool_),
        np.ascontiguousarray(steps, dtype=np.int64), np.ascontiguousarray(block, dtype=np.int64),
        np.ascontiguousarray(C, dtype=np.float64) if colour else np.zeros((3, 1, 1)),
        1.0 / (tau * tau) if colour else 0.0, colour)
    return PairIndex(first, second, inv, dl, lab, wt, np.ascontiguousarray(chroma))


def settings_index(L: np.ndarray, valid: np.ndarray, C: np.ndarray | None, settings: FamilySettings) -> PairIndex:
    """The :class:`PairIndex` of a working copy with ``settings``' pair steps, jackknife
    blocks and chroma scale."""
    return pair_index(L, valid, _pair_steps(settings, L.shape), _block_labels(L.shape, settings.jackknife_blocks),
                      C, settings.chroma_tau)


def pairs_at(index: PairIndex, M: np.ndarray, B: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The pairs' data with field ``M`` (h, w) divided out and its components ``B``
    (h, w, K) as regressors: d (n,) and a (n, K) of :func:`family_pairs`."""
    m = np.ascontiguousarray(M, dtype=np.float64).reshape(-1)
    # gathered component by component (K × n), in one compiled pass each: the transposed
    # layout is what irls's products read (pair_products: no copy)
    bt = np.ascontiguousarray(np.moveaxis(B, -1, 0), dtype=np.float64).reshape(B.shape[-1], m.size)
    d, at = gather_pairs(m, bt, index.first, index.second, index.inv_step, index.dlog)
    return d, at.T


def family_pairs(L: np.ndarray, valid: np.ndarray, M: np.ndarray, B: np.ndarray, steps: np.ndarray,
                 block: np.ndarray, C: np.ndarray | None, tau: float):
    """The log-difference pairs of a working copy: the data of the lens-family fit.

    For each pair (v, v + s·e), e ∈ {y, x}, s ∈ ``steps``, of usable bins: the log
    difference per unit step d = (L(v+se) − L(v) − M(v+se) + M(v)) / s and its
    regressors a = (B(v+se) − B(v)) / s; the model predicts d = a·c (module doc,
    steps 2–3).

    Parameters
    ----------
    L : ndarray (h, w)
        Log working copy.
    valid : ndarray of bool (h, w)
        Bins that may be used (with colour: every channel usable).
    M : ndarray (h, w)
        The family's mean log profile at each bin (or any field to divide out).
    B : ndarray (h, w, K)
        The components at each bin (K may be 0).
    steps : ndarray of int (S,)
        Pair steps in bins.
    block : ndarray of int (h, w)
        Each bin's block label (a pair takes its first bin's).
    C : ndarray (3, h, w) or None
        Log working copies of R, G, B; None: no colour.
    tau : float
        The chroma change (log units per step) at which a pair's weight halves.

    Returns
    -------
    d : ndarray (n,), a : ndarray (n, K), labels : ndarray of int (n,)
    weight : ndarray (n,)
        Each pair's weight by how alike its colour channels change: with the chroma
        change q = (ΔR − ΔG)² + (ΔB − ΔG)² of the per-unit-step log differences,
        1 / (1 + q/τ²); ones without colour. A lens's fall-off changes every channel
        alike; much of a scene's own shading does not.

    References
    ----------
    Zheng et al., TPAMI 2013 (log-gradient pairs of a radial fall-off).
    """
    index = pair_index(L, valid, steps, block, C, tau)
    d, a = pairs_at(index, M, B)
    return d, a, index.labels, index.weight


def irls(d: np.ndarray, a: np.ndarray, weight: np.ndarray, c0: np.ndarray, pmean: np.ndarray,
         pinv: np.ndarray, sigma: float, kappa: float, iterations: int,
         products: PairProducts | None = None, tolerance: float = 1e-4, converged_on: int | None = None,
         relaxation: float = 1.0) -> np.ndarray:
    """The Cauchy-loss fit of d ≈ a·c with a Gaussian prior, by iteratively reweighted
    least squares.

    Each step solves (AᵀWA / (σ²κ) + Λ) c = AᵀWd / (σ²κ) + Λ·μ with the pair weights
    W = weight / (1 + ((d − a·c)/σ)²); it stops when c moves by less than ``tolerance``.

    Parameters
    ----------
    d, a, weight : ndarray (n,), (n, K), (n,)
        Pairs (:func:`family_pairs`) and each pair's prior weight.
    c0 : ndarray (K,)
        Where the fit starts.
    pmean, pinv : ndarray (K,), (K, K)
        Prior mean μ and precision Λ.
    sigma, kappa : float
        Cauchy scale; tempering of the data's information.
    iterations : int
        Most steps.
    products : PairProducts, optional
        :func:`pair_products` of ``d``, ``a``, when the caller has them.
    tolerance : float
        Stop when no coefficient moves by this much in a step.
    converged_on : int, optional
        Only the first this many coefficients are watched for the stop (the field's,
        when nuisance covariates follow them).
    relaxation : float
        Each step moves ω times as far as the reweighted solve says (ω = 1: plain
        IRLS). The fixed point is the same; over-relaxation (1 < ω < 2) reaches it in
        fewer steps where plain IRLS creeps along a flat direction.

    Returns
    -------
    ndarray (K,)

    References
    ----------
    P. W. Holland, R. E. Welsch, "Robust regression using iteratively reweighted
    least-squares", Comm. Statist. 6(9), 1977.
    """
    at = pair_products(d, a) if products is None else products
    K = at.shape[0]
    c0 = np.array(c0, dtype=np.float64, copy=True)
    if K == 0 or iterations <= 0:
        return c0
    # the loop in one compiled call, on one thread (the BLAS's threads spun on a busy machine)
    return irls_fit(at, np.ascontiguousarray(d, dtype=np.float64), np.ascontiguousarray(weight, dtype=np.float64),
                    c0, np.ascontiguousarray(pinv, dtype=np.float64), np.asarray(pinv @ pmean, dtype=np.float64),
                    1.0 / (sigma * sigma * kappa), 1.0 / sigma, int(iterations), float(tolerance),
                    K if converged_on is None else min(int(converged_on), K), float(relaxation))

#: :func:`irls`'s regressors as rows, aᵀ (K×n, contiguous): a step reads each row in order.
PairProducts = np.ndarray


def pair_products(d: np.ndarray, a: np.ndarray) -> PairProducts:
    """:data:`PairProducts` of pairs ``d``, ``a`` (``d`` is not needed: the step reads it
    itself), computed once for many :func:`irls` fits of the same pairs."""
    return np.ascontiguousarray(a.T, dtype=np.float64)


def _pair_steps(settings: FamilySettings, shape: tuple[int, int]) -> np.ndarray:
    """The pair steps that fit in a working copy of ``shape``."""
    return np.asarray([s for s in settings.steps if s < min(shape)], dtype=np.int64)


def _block_labels(shape: tuple[int, int], nb: int) -> np.ndarray:
    """Each bin's block in an nb × nb cut of the working copy (row-major labels)."""
    hb, wb = shape
    return (nb * (np.arange(hb) * nb // hb)[:, None] + (np.arange(wb) * nb // wb)[None, :]).astype(np.int64)


def corner_radius(width: int, height: int) -> float:
    """Distance (px) from the frame centre to its corner pixel's centre: ρ = 1 there."""
    return math.hypot((width - 1) / 2.0, (height - 1) / 2.0)


def bin_rho(xs: np.ndarray, ys: np.ndarray, radius: float) -> np.ndarray:
    """ρ (h, w) of bins centred at ``xs`` (w,), ``ys`` (h,) px from the frame centre, in
    units of ``radius`` (the half-diagonal: ρ = 1 at the frame's corner)."""
    return np.sqrt(xs[None, :] ** 2 + ys[:, None] ** 2) / radius


def mean_cauchy_loss(e: np.ndarray, sigma: float, weight: np.ndarray | None = None) -> float:
    """Mean Cauchy loss log(1 + (e/σ)²) over residuals ``e`` (weighted by ``weight`` when
    given): how well a field explains a frame's pairs. inf when there is nothing to weigh."""
    if e.size == 0 or (weight is not None and not float(np.sum(weight)) > 0):
        return math.inf
    loss = np.log1p((e / sigma) ** 2)
    return float(np.mean(loss) if weight is None else np.average(loss, weights=weight))


def _solve(d, a, wt, c0, pmean, pinv, s: FamilySettings, iterations: int, converged_on: int | None = None,
           relaxation: float = 1.0) -> np.ndarray:
    """One :func:`irls` fit of the Cauchy loss with a Gaussian prior, from ``c0``."""
    return irls(d, a, wt, c0, pmean, pinv, s.sigma, s.kappa, iterations, tolerance=s.tolerance,
                converged_on=converged_on, relaxation=relaxation)


#: Over-relaxation of a fit without chroma covariates made only to be compared with another
#: (:func:`fit_family` without ``uncertainty``: the default estimator's luminance fit, whose
#: field only its pair loss reads): plain IRLS took 34-100 steps on the off-centre frames of
#: ``vigproc bench speed --api`` (Cauchy scale 0.01, tolerance 1e-4), 21-66 at ω = 1.6; the
#: coefficients moved by at most 6e-4 and the loss compared by at most 9e-7 (a script; the
#: closest choice was 0.016 from its margin).
COMPARISON_RELAXATION = 1.6
#: Over-relaxation of the colour fit with chroma covariates (:func:`irls`): its five
#: coefficients took 19 plain steps on the clean protocol's frames (a script), 13.5 at
#: ω = 1.6, and ended nearer the converged fit (median largest coefficient difference
#: 0.0008 against 0.0011).
COVARIATE_RELAXATION = 1.6


def _fit_with_chroma(d, a, index: PairIndex, wt, pmean, pinv, s: FamilySettings,
                     iterations: int, relaxation: float = 1.0, start: np.ndarray | None = None
                     ) -> tuple[np.ndarray, np.ndarray]:
    """The field's coefficients (K = a's columns) fitted with the pairs' chroma changes as
    covariates (module doc, step 3; ``s.chroma_covariate`` the s.d. of their centred prior),
    and the pairs' data with the covariates' part taken out: a jackknife refits the field
    on it with the covariates held (a third of the cost of refitting them too; σ is
    calibrated on fits made so). Without covariates (``chroma_covariate`` 0, a grey frame,
    or one whose channels are proportional and so change no chroma): the plain fit (over-relaxed
    by ``relaxation``, :func:`irls`) and ``d`` itself."""
    K = a.shape[1]
    if s.chroma_covariate <= 0 or not index.chroma.size or float(np.max(np.abs(index.chroma))) <= 1e-9:
        return _solve(d, a, wt, pmean if start is None else start, pmean, pinv, s, iterations,
                      relaxation=relaxation), d
    pm = np.concatenate([pmean, np.zeros(2)])
    prec = np.block([[pinv, np.zeros((K, 2))], [np.zeros((2, K)), np.eye(2) / s.chroma_covariate**2]])
    # rows stacked, then seen as columns: irls reads the rows without a copy
    c_all = _solve(d, np.vstack([a.T, index.chroma]).T, wt, pm, pm, prec, s, iterations,
                   converged_on=K, relaxation=COVARIATE_RELAXATION)
    return c_all[:K], d - c_all[K:] @ index.chroma


def _jackknife(d, a, labels, wt, c, pmean, pinv, s: FamilySettings) -> np.ndarray:
    """The delete-one-block refits (``s.jackknife_blocks``² of them, each started from
    the full fit's coefficients ``c``), as rows."""
    products = pair_products(d, a)
    # a block is left out by weighing its pairs 0: cheaper than copying the others
    return np.array([irls(d, a, wt * (labels != j), c, pmean, pinv, s.sigma, s.kappa, s.jackknife_iterations,
                          products, s.tolerance) for j in range(s.jackknife_blocks**2)])


def linear_jackknife(d, a, labels, wt, c, pmean, pinv, s: FamilySettings) -> np.ndarray:
    """:func:`_jackknife`'s refits linearised about the full fit ``c``, as rows.

    One compiled pass gathers each block's sums at the full fit's residuals
    (:func:`vigproc.core._kernels.blocks.block_normal`): the IRLS matrix Aᵦ, the Cauchy
    loss's curvature Nᵦ and the gradient. Without block b the refit's IRLS steps are then
    those of the loss's quadratic model about ``c``: δ ← δ + A₋ᵦ⁻¹ (S₋ᵦ − N₋ᵦ δ), with S₋ᵦ the
    gradient without the block, as many steps and the same stop as :func:`irls`'s. This
    is the jackknife's infinitesimal (sandwich) form with the refits' finite number of
    steps kept; it departs from the refits only where leaving a block out moves pairs
    across the Cauchy loss's bend.

    Parameters
    ----------
    d, a, labels, wt, c, pmean, pinv, s
        As :func:`_jackknife`'s.

    Returns
    -------
    ndarray (nb², K)

    References
    ----------
    B. Efron, "Nonparametric standard errors and confidence intervals", Canad. J.
    Statist. 9(2), 1981 (the infinitesimal jackknife).
    """
    nb = s.jackknife_blocks ** 2
    at = pair_products(d, a)
    K = at.shape[0]
    HI = np.empty((nb, K, K))
    HN = np.empty((nb, K, K))
    G = np.empty((nb, K))
    c = np.asarray(c, dtype=np.float64)
    block_normal(at, np.ascontiguousarray(d, dtype=np.float64), np.ascontiguousarray(wt, dtype=np.float64),
                 np.ascontiguousarray(labels, dtype=np.int64), c, 1.0 / s.sigma, nb, HI, HN, G)
    # the full fit's own gradient (zero when it converged; what is left, a refit sees too)
    # is in S₋ᵦ: the refits start where the full fit stopped
    return linear_refits(HI, HN, G, c, np.ascontiguousarray(pinv, dtype=np.float64),
                         np.ascontiguousarray(pmean, dtype=np.float64), 1.0 / (s.sigma * s.sigma * s.kappa),
                         int(s.jackknife_iterations), float(s.tolerance))


def _jackknife_cov(d, a, labels, wt, c, pmean, pinv, s: FamilySettings) -> np.ndarray:
    """Delete-one-block jackknife covariance of the coefficients."""
    return _spread(_jackknife(d, a, labels, wt, c, pmean, pinv, s))


def _spread(jack: np.ndarray) -> np.ndarray:
    """The jackknife covariance of delete-one refits (rows; Efron and Stein 1981)."""
    nb = jack.shape[0]
    dev = jack - jack.mean(axis=0)
    return (nb - 1) / nb * dev.T @ dev


def field_spread_ev(basis: np.ndarray, cov: np.ndarray) -> float:
    """RMS over the samples of the s.d. of log2 φ about its frame mean, for coefficient
    covariance ``cov`` (``basis``: samples × K components)."""
    b = basis - basis.mean(axis=0)
    var = np.einsum("ij,jk,ik->i", b, cov, b)
    return float(math.sqrt(max(float(np.mean(var)), 0.0)) / _LN2)


def _frame_grid(width: int, height: int, n: int = 16) -> tuple[np.ndarray, np.ndarray]:
    """x (n,) and y (n,), px from the frame centre, of an n×n grid spanning a frame: where
    a fit's field and its uncertainty are summarised."""
    return (np.linspace(-(width - 1) / 2, (width - 1) / 2, n),
            np.linspace(-(height - 1) / 2, (height - 1) / 2, n))


def _frame_corners(width: int, height: int) -> tuple[np.ndarray, np.ndarray]:
    """x (4,) and y (4,) of the frame's corner pixels' centres, px from the frame centre."""
    x, y = (width - 1) / 2.0, (height - 1) / 2.0
    return np.array([-x, -x, x, x]), np.array([-y, y, -y, y])


def frame_rho_grid(width: int, height: int, n: int = 16) -> np.ndarray:
    """ρ (half-diagonals from the frame centre) on the :func:`_frame_grid`: where a
    family fit's field and its uncertainty are summarised."""
    return bin_rho(*_frame_grid(width, height, n), corner_radius(width, height))


def field_sigma_ev(family: LensFamily, cov: np.ndarray, width: int, height: int) -> float:
    """:func:`field_spread_ev` of family coefficients with covariance ``cov`` over a
    ``width``×``height`` frame (:func:`frame_rho_grid`)."""
    _, basis = family.profiles(frame_rho_grid(width, height))
    return field_spread_ev(basis.reshape(-1, family.n_components), cov)


def profile_to_model(log_profile: np.ndarray, radii: np.ndarray, width: int, height: int,
                     center: tuple[float, float] = (0.0, 0.0), shape: tuple[float, float] = (0.0, 0.0),
                     **kw) -> tuple[VignettingModel, float]:
    """Write a radial log-attenuation profile as the Kang-Weiss model.

    ρ is in half-diagonals; the profile is extended linearly past its last radius. By
    default the profile is centred and circular: P circular with r = :data:`KW_SCALE`
    at the corner. With ``center`` (px from the frame centre) and ``shape`` (e1, e2),
    ρ² = (1 + e1)·dx² + 2·e2·dx·dy + (1 − e1)·dy² about the centre (:func:`fit_off_centre`),
    and P is that quadratic form scaled alike. α1..α7 by least squares so that A·G
    matches the profile over the radii the frame holds (Lyu 2010, Eq. 2).

    Returns
    -------
    model : VignettingModel
    rms_ev : float
        RMS (over ρ) of the written model's log2 error against the profile.
    """
    R = corner_radius(width, height)
    e1, e2 = shape
    cx, cy = _frame_corners(width, height)
    cx, cy = (cx - center[0]) / R, (cy - center[1]) / R
    reach = float(np.sqrt(np.max((1 + e1) * cx**2 + 2 * e2 * cx * cy + (1 - e1) * cy**2)))
    rho = np.linspace(0.0, reach if reach > 1.0 + 1e-9 else 1.0, _KW_SAMPLES)
    f = _extrapolated(rho, radii, log_profile)
    r = KW_SCALE * rho
    a = 1.0 / (1.0 + (r / 2.0) ** 2) ** 2
    target = 1.0 - np.exp(f) / a  # = Σ α_i r^i
    V = np.stack([r**i for i in range(1, N_ALPHA + 1)], axis=1)
    alpha, *_ = np.linalg.lstsq(V, target, rcond=None)
    g = 1.0 - V @ alpha
    err = float(np.sqrt(np.mean((np.log(np.maximum(a * g, 1e-300)) - f) ** 2)) / _LN2)
    p = (KW_SCALE / R) ** 2
    model = VignettingModel(width, height, center=(float(center[0]), float(center[1])),
                            p=(p * (1 + e1), p * e2, p * (1 - e1)),
                            alpha=tuple(float(x) for x in alpha), method=METHOD, **kw)
    return model, err


@dataclass(frozen=True)
class CentreFit:
    """Where the fall-off's centre is, by the lens-family fit with a free centre.

    Attributes
    ----------
    offset : tuple of float
        (cx, cy) px from the frame centre.
    covariance : ndarray (2, 2)
        Its jackknife covariance (px²), scaled by ``sigma_scale``².
    z : float
        Mahalanobis distance of the offset from the frame centre (NaN: not computed).
    shift : float
        |offset| in half-diagonals.
    """

    offset: tuple[float, float]
    covariance: np.ndarray
    z: float
    shift: float

    def off_centre(self, min_shift: float, min_z: float = 0.0) -> bool:
        """At least ``min_shift`` half-diagonals off, and ``min_z`` s.d. when asked (a fit
        without its uncertainty has z NaN: it answers only for the shift)."""
        return self.shift >= min_shift and (min_z <= 0.0 or self.z >= min_z)


#: A frame whose pairs' colour weights average at least this is fitted as grey (in
#: :data:`~vigproc.core.lensfamily.N_COMPONENTS` components). The clean protocol's colour
#: camera frames average 0.00–0.14; its black-and-white ones, and a grey frame stored
#: as R = G = B, 1.
GREY_WEIGHT = 0.5


def colour_weighted(weight: np.ndarray) -> bool:
    """Whether pair weights (:func:`family_pairs`) tell a scene's coloured shading from
    a lens: their mean is below :data:`GREY_WEIGHT`."""
    return bool(weight.size) and float(np.mean(weight)) < GREY_WEIGHT


def family_for(family: LensFamily, colour: bool) -> LensFamily:
    """The components a single frame's fit uses: all of ``family``'s when its pairs are
    weighted by colour (:func:`colour_weighted`), the first
    :data:`~vigproc.core.lensfamily.N_COMPONENTS` otherwise.

    With its pairs weighted by colour, a frame's scene passes for less of a lens, and a
    third component measures better (clean protocol, lens-family fit: 0.044 EV, p90
    0.059, against 0.046 / 0.067 with two); a grey frame's scene fools a third
    component more than it helps (0.085 / 0.135 against 0.080 / 0.101).
    """
    return family if colour else family.truncated(min(family.n_components, N_COMPONENTS))


def _in_components(family: LensFamily, k: int) -> LensFamily:
    """``family`` cut to the ``k`` components a fit's coefficients are in."""
    if k > family.n_components:
        raise ModelError(f"{k} coefficients cannot be read in a {family.n_components}-component family")
    return family.truncated(k)


def _extrapolated(rho: np.ndarray, radii: np.ndarray, values: np.ndarray) -> np.ndarray:
    """``values`` (a profile over ``radii``) at ``rho``, extended linearly past the last
    radius with the last interval's slope (ρ > 1 occurs once the centre moves off the
    frame's)."""
    r = np.asarray(rho)
    slope = (values[-1] - values[-2]) / (radii[-1] - radii[-2])
    return np.interp(r.ravel(), radii, values).reshape(r.shape) + np.maximum(r - radii[-1], 0.0) * slope


def _extended(fam: LensFamily, c: np.ndarray, rho: np.ndarray):
    """Mean, components and the full profile's slope at ``rho``, extended linearly
    past the corner (:func:`_extrapolated`)."""
    r = np.asarray(rho)
    grads = _profile_slopes(fam)
    slope = grads[0] + c @ grads[1]
    mean = _extrapolated(r, fam.radii, fam.mean)
    basis = np.stack([_extrapolated(r, fam.radii, b) for b in fam.components], axis=-1)
    return mean, basis, np.interp(np.minimum(r, 1.0).ravel(), fam.radii, slope).reshape(r.shape)


def _prior_with_geometry(fam: LensFamily, hint: LensHint, n_geometry: int, spread: float):
    """The family prior extended by ``n_geometry`` centre (and shape) parameters, each
    N(0, ``spread``²): mean and precision."""
    pmean, pcov = fam.prior(hint.focal35, hint.fnumber)
    K = fam.n_components
    P = np.zeros((K + n_geometry, K + n_geometry))
    P[:K, :K] = pcov
    P[K:, K:] = np.eye(n_geometry) * spread**2
    return np.concatenate([pmean, np.zeros(n_geometry)]), np.linalg.inv(P)


#: Largest |e| = |(e1, e2)| a Gauss-Newton step of the elliptical fit may reach: ρ² stays
#: positive over the frame (at |e| = 1 the ellipse degenerates to a line).
MAX_ELLIPTICITY = 0.9


def _geometry_columns(fam: LensFamily, coef: np.ndarray, geo: np.ndarray, X: np.ndarray, Y: np.ndarray):
    """The family's log field at (X, Y) (half-diagonals from the frame centre) for centre
    u = geo[:2] and, when ``geo`` has four entries, shape e = geo[2:]: its mean part M and
    its derivatives J by (c, geometry), shape (…, K + 2 or 4); log φ = M + J[..., :K]·c.

    ρ² = (1 + e1)·dx² + 2·e2·dx·dy + (1 − e1)·dy², (dx, dy) = v − u; ∂f/∂θ = f'(ρ)·∂ρ/∂θ with
    ∂ρ/∂u = −(gx, gy)/ρ, (gx, gy) = ((1 + e1)·dx + e2·dy, e2·dx + (1 − e1)·dy), and
    ∂ρ/∂e = ((dx² − dy²)/2, dx·dy)/ρ.
    """
    dx, dy = X - geo[0], Y - geo[1]
    if geo.size == 4:
        e1, e2 = geo[2], geo[3]
        rho = np.sqrt(np.maximum((1 + e1) * dx * dx + 2 * e2 * dx * dy + (1 - e1) * dy * dy, 1e-18))
        gx, gy = (1 + e1) * dx + e2 * dy, e2 * dx + (1 - e1) * dy
    else:
        rho = np.maximum(np.hypot(dx, dy), 1e-9)
        gx, gy = dx, dy
    M, B, slope = _extended(fam, coef, rho)
    cols = [B, (-slope * gx / rho)[..., None], (-slope * gy / rho)[..., None]]
    if geo.size == 4:
        cols += [(slope * 0.5 * (dx * dx - dy * dy) / rho)[..., None], (slope * dx * dy / rho)[..., None]]
    return M, np.concatenate(cols, axis=-1)


def _profile_slopes(fam: LensFamily) -> tuple[np.ndarray, np.ndarray]:
    """d/dρ of the family's mean and components (kept on the family: a Gauss-Newton fit
    asks at every step, as for its priors)."""
    grads = fam.__dict__.get("_gradients")
    if grads is None:
        grads = fam.__dict__.setdefault(
            "_gradients", (np.gradient(fam.mean, fam.radii), np.gradient(fam.components, fam.radii, axis=1)))
    return grads


def _geometry_pairs(index: PairIndex, xs: np.ndarray, ys: np.ndarray, fam: LensFamily, coef: np.ndarray,
                    geo: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """:func:`pairs_at` of :func:`_geometry_columns` at bins ``xs`` (w,) × ``ys`` (h,)
    (half-diagonals): one compiled pass over the bins and one over the pairs
    (:mod:`vigproc.core._kernels.geometry`), the same values."""
    grads = _profile_slopes(fam)
    slope = grads[0] + coef @ grads[1]
    d, at = geometry_pairs(xs, ys, np.asarray(geo, dtype=np.float64), np.ascontiguousarray(fam.radii, dtype=np.float64),
                           np.ascontiguousarray(fam.mean, dtype=np.float64),
                           np.ascontiguousarray(fam.components, dtype=np.float64),
                           np.ascontiguousarray(slope, dtype=np.float64), index.first, index.second,
                           index.inv_step, index.dlog)
    return d, at.T


def _geometry_fit(index: PairIndex, X, Y, fam: LensFamily, c, pm, pinv, settings: FamilySettings,
                  elliptical: bool, iterations: int, tolerance: float = 1e-3):
    """Gauss-Newton on the fall-off's centre u (and, ``elliptical``, its shape (e1, e2)),
    four IRLS steps of the family coefficients inside each (:func:`_geometry_columns`;
    a step is shortened so that |e| stays within :data:`MAX_ELLIPTICITY`): one compiled
    loop (:mod:`vigproc.core._kernels.gauss_newton`) over :func:`_geometry_pairs`' values and
    :func:`_solve`'s steps, each step's sums over the bins instead of the pairs
    (:mod:`vigproc.core._kernels.bin_normal`: the same fit up to rounding).

    Returns the coefficients, the geometry (u, or u and e), the last step's pairs,
    solution and prior mean (for the jackknife), and the number of steps taken.
    """
    E = 4 if elliptical else 2
    geo = np.zeros(E)
    coef = np.asarray(c, dtype=np.float64).copy()
    xs, ys = np.ascontiguousarray(np.ravel(X), dtype=np.float64), np.ascontiguousarray(np.ravel(Y), dtype=np.float64)
    if iterations <= 0:
        return coef, geo, None, None, None, None, 0
    if index.first.size < MIN_VALID_BINS:  # too few pairs: no step
        d, a = _geometry_pairs(index, xs, ys, fam, coef, geo)
        return coef, geo, d, a, None, None, 0
    grads = _profile_slopes(fam)
    f64 = np.float64
    coef, geo, d, at, sol, pm_it, steps = geometry_gauss_newton(
        xs, ys, geo, np.ascontiguousarray(fam.radii, dtype=f64), np.ascontiguousarray(fam.mean, dtype=f64),
        np.ascontiguousarray(fam.components, dtype=f64), np.ascontiguousarray(grads[0], dtype=f64),
        np.ascontiguousarray(grads[1], dtype=f64), index.first, index.second, index.inv_step, index.dlog,
        np.ascontiguousarray(index.weight, dtype=f64), coef, np.ascontiguousarray(pm, dtype=f64),
        np.ascontiguousarray(pinv, dtype=f64), 1.0 / (settings.sigma * settings.sigma * settings.kappa),
        1.0 / settings.sigma, 4, float(settings.tolerance), int(iterations), float(tolerance), MAX_ELLIPTICITY)
    return coef, geo, d, at.T, sol, pm_it, int(steps)


#: Long side of :func:`fit_centre`'s working copy.
CENTRE_WORK_SIZE = 60


def fit_centre(lum: np.ndarray, c: np.ndarray, settings: FamilySettings = FamilySettings(),
               mask: np.ndarray | None = None, family: LensFamily | None = None,
               hint: LensHint | None = None, work_size: int = CENTRE_WORK_SIZE, iterations: int = 12,
               colour: np.ndarray | None = None, uncertainty: bool = True,
               copy: FamilyWorkingCopy | None = None) -> CentreFit:
    """Fit the fall-off's centre together with its family coefficients (Gauss-Newton
    on the centre, IRLS inside), from the centred fit's coefficients ``c``.

    The lens family describes uncropped frames; a crop of a larger frame, a shifted
    lens or a stitched image moves the centre. This is the test that sends such
    frames to the off-centre fits, and the crop evidence of forensics.
    ``colour`` (H×W×3): pairs weighted as in :func:`fit_family` (the forensic crop test
    does; the default estimator asks the luminance and, in a colour frame, the
    colour-weighted pairs too). The fit is in the components of ``c``. Without
    ``uncertainty`` the jackknife is skipped (a third of the time): covariance and z are
    NaN, for a caller that reads only the shift. ``copy``: the frame's working copy at
    ``work_size`` (:func:`luminance_copy`, :func:`with_colour`), when the caller has it (``mask`` and
    ``colour`` are then not read).
    """
    fam = _in_components(family or profile_family(), len(c))
    h, w = lum.shape
    if copy is None:
        copy = _working_copy(lum, replace(settings, work_size=work_size), mask, colour)
    L, valid, xs, ys, C, _ = copy
    radius = corner_radius(w, h)
    # the centre within about half a half-diagonal
    pm, pinv = _prior_with_geometry(fam, hint or LensHint(), 2, 0.5)
    # the pairs and their weights stay; only the field divided out moves with the centre
    index = settings_index(L, valid, C, settings)
    K = fam.n_components
    _, u, d, a, sol, pm_it, _ = _geometry_fit(index, xs[None, :] / radius, ys[:, None] / radius, fam, c, pm, pinv,
                                              settings, False, iterations)
    cov = np.zeros((2, 2))
    if not uncertainty:
        cov = np.full((2, 2), math.nan)
    elif d is not None and d.size >= MIN_VALID_BINS:
        cov = _spread(_jackknife(d, a, index.labels, index.weight, sol, pm_it, pinv, settings)[:, K:]) \
            * settings.sigma_scale**2
    cov_px = cov * radius**2 + np.eye(2) * 1e-6
    off = u * radius
    z = float(math.sqrt(max(float(off @ np.linalg.solve(cov_px, off)), 0.0))) if uncertainty else math.nan
    return CentreFit((float(off[0]), float(off[1])), cov_px, z, float(np.hypot(*u)))


#: The method a :func:`fit_off_centre` model records.
OFF_CENTRE_METHOD = "lens-family-off-centre"
#: Most Gauss-Newton steps of :func:`fit_off_centre`.
OFF_CENTRE_ITERATIONS = 30
#: The prior s.d. of :func:`fit_off_centre`'s centre (half-diagonals) and shape (e1, e2).
OFF_CENTRE_SPREAD = 0.5


def fit_off_centre(lum: np.ndarray, c: np.ndarray, settings: FamilySettings = FamilySettings(),
                   mask: np.ndarray | None = None, family: LensFamily | None = None,
                   hint: LensHint | None = None, colour: np.ndarray | None = None,
                   copy: FamilyWorkingCopy | None = None) -> VignettingModel | None:
    """The lens family's fall-off with a free centre and an elliptical shape, from the
    centred fit's coefficients ``c``: the default estimator's fit for a frame whose
    centre moves (a crop, a shifted lens, a stitched image).

    Gauss-Newton on the centre u and the shape (e1, e2) of ρ² = (1 + e1)·dx² +
    2·e2·dx·dy + (1 − e1)·dy² (half-diagonals from u), each with a N(0, 0.5²) prior, the
    family coefficients by IRLS inside each step, on the :attr:`FamilySettings.work_size`
    copy. The radial profile stays one that real lenses have; only where it sits on the
    frame is free. Written as the Kang-Weiss model (Lyu 2010, Eq. 2) with centre u and
    P ∝ the shape (:func:`profile_to_model`).

    ``copy``: the frame's working copy at ``settings.work_size`` (:func:`luminance_copy`,
    and :func:`with_colour` for ``colour``), when the caller has it (``mask`` and
    ``colour`` are then not read).

    Returns
    -------
    VignettingModel or None
        ``quality.field_sigma_ev`` as :func:`fit_family`'s (its jackknife over the centre
        and shape too; calibrated on centred fits); the identity with the fit as
        ``candidate`` when the fall-off is below ``min_snr`` σ. None when too few pixels
        are usable or no Kang-Weiss model holds the fit (it would black out part of the
        frame).
    """
    fit = off_centre_fit(lum, c, settings, mask, family, hint, colour, copy)
    return None if fit is None else fit.with_uncertainty()


@dataclass(frozen=True)
class OffCentreFit:
    """:func:`fit_off_centre`'s fit before its uncertainty: the default estimator reads its
    field first (:attr:`field`) and pays for the jackknife (:meth:`with_uncertainty`) only
    for a fit it keeps."""

    #: The fit as a model, σ not yet measured (quality's ``field_sigma_ev`` and ``snr`` NaN)
    field: VignettingModel
    spread: float
    _jackknife: tuple
    _t0: float

    def shift(self, shape: tuple[int, int]) -> float:
        """The fitted centre's distance from the frame's, in half-diagonals of an H×W
        (``shape``) frame (:class:`CentreFit`'s ``shift``)."""
        return float(np.hypot(*self.field.center)) / corner_radius(shape[1], shape[0])

    def with_uncertainty(self) -> VignettingModel:
        """The model :func:`fit_off_centre` returns: σ from the jackknife (as :func:`fit_family`'s:
        linearised unless near the threshold), and the identity
        with the fit as ``candidate`` when the fall-off is below ``min_snr`` σ."""
        d, a, index, sol, pm_it, pinv, settings, J = self._jackknife
        # σ and the signal as fit_family's: the jackknife over every parameter carried to the
        # field by its derivatives at the fit, both on a 16×16 grid over the whole frame;
        # linearised (linear_jackknife) unless it is close enough to sway the fall-back
        refits = (index.labels, index.weight, sol, pm_it, pinv, settings)
        sigma_jk = field_spread_ev(J, _spread(linear_jackknife(d, a, *refits)))
        if _near_threshold(sigma_jk, settings.sigma_scale, settings.sigma_floor, self.spread, settings.min_snr,
                           math.nan, ()):
            sigma_jk = field_spread_ev(J, _spread(_jackknife(d, a, *refits)))
        sigma = math.hypot(settings.sigma_scale * sigma_jk, settings.sigma_floor)
        snr = self.spread / sigma if sigma > 0 else math.inf
        q = replace(self.field.quality, confidence=_confidence(snr, settings.min_snr), field_sigma_ev=sigma,
                    snr=snr, fallback=snr < settings.min_snr, seconds=time.perf_counter() - self._t0)
        model = replace(self.field, quality=q)
        if q.fallback:
            m = self.field
            return VignettingModel.identity(m.width, m.height, method=OFF_CENTRE_METHOD, quality=q, candidate=model)
        return model


def off_centre_fit(lum: np.ndarray, c: np.ndarray, settings: FamilySettings = FamilySettings(),
                   mask: np.ndarray | None = None, family: LensFamily | None = None,
                   hint: LensHint | None = None, colour: np.ndarray | None = None,
                   copy: FamilyWorkingCopy | None = None,
                   iterations: int = OFF_CENTRE_ITERATIONS) -> OffCentreFit | None:
    """:func:`fit_off_centre` up to its uncertainty (:class:`OffCentreFit`), in at most
    ``iterations`` Gauss-Newton steps; parameters and None as there."""
    t0 = time.perf_counter()
    fam = _in_components(family or profile_family(), len(c))
    h, w = lum.shape
    L, valid, xs, ys, C, _ = _working_copy(lum, settings, mask, colour) if copy is None else copy
    if int(valid.sum()) < MIN_VALID_BINS:
        return None
    radius = corner_radius(w, h)
    pm, pinv = _prior_with_geometry(fam, hint or LensHint(), 4, OFF_CENTRE_SPREAD)
    index = settings_index(L, valid, C, settings)
    coef, geo, d, a, sol, pm_it, steps = _geometry_fit(index, xs[None, :] / radius, ys[:, None] / radius, fam, c,
                                                       pm, pinv, settings, True, iterations)
    if d is None or d.size < MIN_VALID_BINS or not np.all(np.isfinite(geo)) \
            or float(np.hypot(geo[2], geo[3])) >= MAX_ELLIPTICITY - 1e-9:
        return None  # no pairs, or a shape held at the bound: no fit
    gx, gy = _frame_grid(w, h)
    GX, GY = np.meshgrid(gx, gy)
    _, J = _geometry_columns(fam, coef, geo, GX / radius, GY / radius)
    try:
        model, _ = profile_to_model(fam.mean + coef @ fam.components, fam.radii, w, h,
                                    center=(float(geo[0] * radius), float(geo[1] * radius)),
                                    shape=(float(geo[2]), float(geo[3])))
        # G > 0 over the frame: on the working copy's bins and at the corners (the
        # largest radius of a convex form over a rectangle is at a corner)
        cx, cy = _frame_corners(w, h)
        model.log_field_at(np.concatenate([np.broadcast_to(xs[None, :], L.shape)[valid], cx]),
                           np.concatenate([np.broadcast_to(ys[:, None], L.shape)[valid], cy]))
        spread = float(np.std(model.log_field_at(GX, GY))) / _LN2
        ev_rms = model.field_ev_rms()
    except ModelError:
        return None
    q = FitQuality(confidence=math.nan, field_ev_rms=ev_rms, field_sigma_ev=math.nan, snr=math.nan,
                   fallback=False, iterations=steps, seconds=time.perf_counter() - t0)
    return OffCentreFit(replace(model, method=OFF_CENTRE_METHOD, quality=q), spread,
                        (d, a, index, sol, pm_it, pinv, settings, J.reshape(GX.size, -1)), t0)


def pair_losses(lum: np.ndarray, models: Sequence[VignettingModel], settings: FamilySettings = FamilySettings(),
                mask: np.ndarray | None = None, copy: FamilyWorkingCopy | None = None,
                index: PairIndex | None = None) -> list[float]:
    """Mean Cauchy loss log(1 + (e/σ)²) per pair of the frame's log differences once each
    model's field is divided out: how well a field explains the frame, the same measure
    for any model (the default estimator's choice between fits). One working copy of
    the luminance: no pair weighs more by its colour, so a fit that weighs pairs by
    colour has no edge over one that does not. ``copy``: that copy
    (:func:`luminance_copy` at ``settings.work_size``), when the caller has it; ``index``:
    its pairs (:func:`settings_index` of ``copy`` with ``settings``, no colour), listed
    once for the fit that is compared and for the comparison."""
    L, valid, xs, ys, _, _ = _working_copy(lum, settings, mask) if copy is None else copy
    X = np.ascontiguousarray(np.broadcast_to(xs[None, :], L.shape))
    Y = np.ascontiguousarray(np.broadcast_to(ys[:, None], L.shape))
    if index is None:  # the pairs' order and data do not depend on the blocks' labels
        index = pair_index(L, valid, _pair_steps(settings, L.shape), np.zeros(L.shape, dtype=np.int64), None,
                           settings.chroma_tau)
    none = np.zeros(L.shape + (1,))
    out = []
    for model in models:
        d, _ = pairs_at(index, model.log_field_at(X, Y), none)
        out.append(mean_cauchy_loss(d, settings.sigma))
    return out


@dataclass(frozen=True)
class FrameCoefficients:
    """What one frame says of its lens in the family, without the prior: the pooling
    unit of a lens profile (:func:`vigproc.core.pooling.pool_family`).

    A frame's estimate under the prior is shrunk towards the prior's mean: the
    shrinkage is largest for the strongest lenses, and averaging shrunk estimates
    keeps it (measured on the clean protocol: strong lenses under-estimated by about
    15 % whatever the number of frames). The data term alone is equivariant (a
    field in the family added to a frame moves the fit by exactly its coefficients),
    so its frame-to-frame errors are the scenes' and average away; the prior is
    applied once, to the pooled coefficients.

    Attributes
    ----------
    coefficients : ndarray (K,)
        The fit of the data term alone (a vanishing ridge towards the prior mean keeps
        it defined on a frame without structure).
    covariance : ndarray (K, K)
        Its delete-one-block jackknife covariance, scaled by ``sigma_scale``².
    pairs : int
        Log-difference pairs the fit used.
    """

    coefficients: np.ndarray
    covariance: np.ndarray
    pairs: int


#: The likelihood fit's ridge: the prior's precision times this (it only keeps a
#: frame without structure from a singular system).
LIKELIHOOD_RIDGE = 1e-6
#: Most IRLS steps of the likelihood fit: without the prior the objective is flat
#: along the first component, and 8 steps from the prior mean stop short of the
#: minimum on strong lenses (another source of shrinkage).
LIKELIHOOD_ITERATIONS = 100


def frame_coefficients(L: np.ndarray, valid: np.ndarray, xs: np.ndarray, ys: np.ndarray,
                       width: int, height: int, settings: FamilySettings = FamilySettings(),
                       family: LensFamily | None = None, *,
                       channels: tuple[np.ndarray, np.ndarray] | None = None) -> FrameCoefficients | None:
    """The family coefficients of one frame's working copy, from its data alone.

    Parameters
    ----------
    L, valid : ndarray (h, w)
        Log working copy and its usable bins (:func:`vigproc.core.pixels.binned_log_copy`).
    xs, ys : ndarray (w,), (h,)
        Bin centres in px from the frame centre.
    width, height : int
        The full frame (ρ = 1 at its corner).
    settings : FamilySettings
    family : LensFamily, optional
    channels : (ndarray (3, h, w), ndarray of bool (3, h, w)), optional
        The R, G, B log working copies and their usable bins: pairs weighted by how
        alike their channels change (module doc, step 2).

    Returns
    -------
    FrameCoefficients, or None when fewer than :data:`MIN_VALID_BINS` bins are usable.

    References
    ----------
    Zheng et al., TPAMI 2013 (the per-frame data term); Efron and Stein 1981 (the
    jackknife).
    """
    fam = family or default_family()
    valid, C = _with_chroma(valid, channels, settings)
    if int(valid.sum()) < MIN_VALID_BINS:
        return None
    M, B = fam.profiles(bin_rho(xs, ys, corner_radius(width, height)))
    index = settings_index(L, valid, C, settings)
    d, a = pairs_at(index, M, B)
    labels, wt = index.labels, index.weight
    if d.size < MIN_VALID_BINS:
        return None
    pmean, pcov = fam.prior()
    pinv = np.linalg.inv(pcov) * LIKELIHOOD_RIDGE
    c, d = _fit_with_chroma(d, a, index, wt, pmean, pinv, settings, LIKELIHOOD_ITERATIONS)
    jk = replace(settings, jackknife_iterations=max(settings.jackknife_iterations, 30))
    cov = _jackknife_cov(d, a, labels, wt, c, pmean, pinv, jk) * settings.sigma_scale**2
    return FrameCoefficients(c, 0.5 * (cov + cov.T), int(d.size))


def estimate_family(lum: np.ndarray, settings: FamilySettings = FamilySettings(),
                    mask: np.ndarray | None = None, family: LensFamily | None = None,
                    hint: LensHint | None = None, colour: np.ndarray | None = None) -> VignettingModel:
    """Estimate a centred lens fall-off from an H×W linear luminance image.

    :func:`fit_family` without its coefficients; see there.
    """
    return fit_family(lum, settings, mask, family, hint, colour).model


class FamilyFit(NamedTuple):
    """:func:`fit_family`'s answer.

    Attributes
    ----------
    model : VignettingModel
        Centred, circular, for the H×W frame; ``quality.field_sigma_ev`` is the
        calibrated 1-σ error of log2 φ (RMS over the frame, about its mean). When the
        evidence is weak, the identity model with ``quality.fallback`` and the fit as
        ``candidate``.
    coefficients : ndarray (K,) or None
        The family coefficients of the fit (None when too few pixels were usable).
    colour_weighted : bool
        Whether the pairs were weighted by how alike their colour channels change
        (:func:`colour_weighted`): the fit is then in every component of the family,
        else in the first :data:`~vigproc.core.lensfamily.N_COMPONENTS`
        (:func:`family_for`).
    """

    model: VignettingModel
    coefficients: np.ndarray | None
    colour_weighted: bool = False


#: How far (a factor on σ) the linearised jackknife's σ (:func:`linear_jackknife`) may be
#: from the refits' before :func:`fit_family` lets the refits decide: on the 36 api-bench
#: frames and the clean protocol's the two σ were within 0.94–1.61 of each other.
JACKKNIFE_CHECK = 2.0


def _near_threshold(sigma_lin: float, scale: float, floor: float, spread: float, min_snr: float,
                    ev_rms: float, ev_checks: tuple[float, ...]) -> bool:
    """Whether a σ within :data:`JACKKNIFE_CHECK` of ``sigma_lin`` (before ``scale`` and
    ``floor``) could put the SNR (``spread`` / σ) on the other side of ``min_snr``, or the
    field's RMS ``ev_rms`` + 2σ on the other side of one of ``ev_checks``."""
    lo = math.hypot(scale * sigma_lin / JACKKNIFE_CHECK, floor)
    hi = math.hypot(scale * sigma_lin * JACKKNIFE_CHECK, floor)
    if not (math.isfinite(lo) and math.isfinite(hi) and lo > 0):
        return True
    if spread / hi < min_snr <= spread / lo:
        return True
    return any(ev_rms + 2.0 * lo <= level <= ev_rms + 2.0 * hi for level in ev_checks)


def fit_family(lum: np.ndarray, settings: FamilySettings = FamilySettings(),
               mask: np.ndarray | None = None, family: LensFamily | None = None,
               hint: LensHint | None = None,
               colour: np.ndarray | None = None, copy: FamilyWorkingCopy | None = None,
               uncertainty: bool = True, ev_checks: tuple[float, ...] = (),
               index: PairIndex | None = None, start: np.ndarray | None = None) -> FamilyFit:
    """Estimate a centred lens fall-off from an H×W linear luminance image.

    Parameters
    ----------
    lum : ndarray, H×W, linear intensities
    settings : FamilySettings
    mask : ndarray of bool, H×W, optional
        Pixels that may be used (e.g. excluding clipped highlights).
    family : LensFamily, optional
        Default: the shipped family (every lensfun lens, three components). A frame
        whose pairs are weighted by colour is fitted in all its components, any other in
        the first two (:func:`family_for`): how many coefficients come back depends on
        the frame.
    hint : LensHint, optional
        EXIF focal length (35-mm equivalent) and f-number: the prior becomes the
        spread of the calibrations nearest to them.
    colour : ndarray, H×W×3, linear, optional
        The frame's R, G, B (:func:`colour_of`): pairs are weighted by how alike their
        channels change (module doc, step 2).
    copy : FamilyWorkingCopy, optional
        The frame's working copy at ``settings.work_size`` (:func:`luminance_copy`, and
        :func:`with_colour` for ``colour``), when the caller has it; ``mask`` and
        ``colour`` are then not read.
    uncertainty : bool
        False: no jackknife (σ NaN) and no fall-back, for a fit that is only compared
        with another (the default estimator's choice between fits reads its field alone);
        its IRLS is over-relaxed (:data:`COMPARISON_RELAXATION`), and its quality's
        ``field_ev_rms`` and ``objective`` are NaN (not worked out).
    ev_checks : tuple of float
        Levels (EV) a caller compares the field's RMS + 2σ with: σ comes from the
        linearised jackknife (:func:`linear_jackknife`) unless the SNR or one of these
        comparisons is within :data:`JACKKNIFE_CHECK` of its threshold, where the
        jackknife itself decides.
    index : PairIndex, optional
        The pairs of ``copy`` with ``settings`` (:func:`settings_index`), when the caller
        lists them once for this fit and another use (:func:`pair_losses`).
    start : ndarray, optional
        Where the IRLS starts (its first K entries; default: the prior mean): the
        default estimator starts the luminance's comparison fit from the colour fit's
        coefficients. Only a fit without chroma covariates reads it.

    Returns
    -------
    FamilyFit
        The model, its family coefficients and whether its pairs were weighted by colour.
    """
    t0 = time.perf_counter()
    h, w = lum.shape
    L, valid, xs, ys, C, _ = _working_copy(lum, settings, mask, colour) if copy is None else copy
    fam = family or profile_family()
    if int(valid.sum()) < MIN_VALID_BINS:
        log.debug("too few usable pixels (%d bins); no correction", int(valid.sum()))
        q = FitQuality(confidence=0.0, fallback=True, seconds=time.perf_counter() - t0)
        return FamilyFit(VignettingModel.identity(w, h, method=METHOD, quality=q), None)
    radius = corner_radius(w, h)
    M, B = fam.profiles(bin_rho(xs, ys, radius))
    index = settings_index(L, valid, C, settings) if index is None else index
    d, a = pairs_at(index, M, B)
    labels, wt = index.labels, index.weight
    # components nest: the first k columns of a are the k-component family's
    weighted = colour_weighted(wt)
    fam = family_for(fam, weighted)
    K = fam.n_components
    a = a[:, :K]
    if not weighted:
        settings = replace(settings, sigma=settings.grey_sigma)
    hint = hint or LensHint()
    pmean, pcov = fam.prior(hint.focal35, hint.fnumber)
    pinv = np.linalg.inv(pcov)
    n = d.size
    c0 = None if start is None else np.asarray(start, dtype=np.float64)[:K]
    c, d = _fit_with_chroma(d, a, index, wt, pmean, pinv, settings, settings.iterations,
                            1.0 if uncertainty else COMPARISON_RELAXATION, c0)
    grid = frame_rho_grid(w, h)
    # a fit that does not weigh its pairs by colour is calibrated on its own
    scale = settings.sigma_scale if weighted else settings.grey_sigma_scale
    min_snr = settings.min_snr if weighted else settings.grey_min_snr
    # the error and σ are about the frame mean (a gain is free), so is the signal
    # a fit only compared with another is read for its field (or its coefficients) alone:
    # its signal, field RMS and loss are not worked out
    spread = float(np.std(fam.log_profile(c, grid))) / _LN2 if uncertainty else math.nan
    try:
        fit, conv_ev = profile_to_model(fam.mean + c @ fam.components, fam.radii, w, h)
        ev_rms = fit.field_ev_rms() if uncertainty else math.nan
    except ModelError:
        fit, conv_ev, ev_rms = None, math.nan, math.nan
    # without the uncertainty (a fit only compared with another): no jackknife, never a fall-back
    sigma_jk = math.nan
    if uncertainty:
        sigma_jk = field_sigma_ev(fam, _spread(linear_jackknife(d, a, labels, wt, c, pmean, pinv, settings)), w, h)
        if _near_threshold(sigma_jk, scale, settings.sigma_floor, spread, min_snr, ev_rms, ev_checks):
            # the decision is the refits' own where the linearisation could sway it
            sigma_jk = field_sigma_ev(fam, _jackknife_cov(d, a, labels, wt, c, pmean, pinv, settings), w, h)
    sigma = math.hypot(scale * sigma_jk, settings.sigma_floor)
    snr = spread / sigma if sigma > 0 else math.inf
    confidence = _confidence(snr, min_snr)
    accept = snr >= min_snr or not uncertainty
    objective = math.nan
    if uncertainty:
        residual = d - np.einsum("ij,j->i", a, c)  # einsum: no BLAS threads, the same bits in every process
        objective = mean_cauchy_loss(residual, settings.sigma, wt)
    q = FitQuality(confidence=confidence, field_ev_rms=math.nan, field_sigma_ev=sigma, snr=snr,
                   fallback=not accept,
                   objective=objective,
                   iterations=settings.iterations,
                   seconds=time.perf_counter() - t0)
    if fit is None:
        # the data alone, far outside what lenses do (a fall-off that blacks out the
        # corners): no model holds it, so nothing to apply or to offer as a candidate
        log.debug("lens-family fit c=%s is no fall-off a model can hold; no correction", np.round(c, 3))
        q = replace(q, confidence=0.0, fallback=True)
        return FamilyFit(VignettingModel.identity(w, h, method=METHOD, quality=q), c, weighted)
    q = replace(q, field_ev_rms=ev_rms)
    fit = VignettingModel(w, h, center=fit.center, p=fit.p, alpha=fit.alpha, method=METHOD, quality=q)
    log.debug("lens-family fit: c=%s, %.3f EV ± %.3f (jackknife %.3f), %d pairs, written with %.4f EV error",
              np.round(c, 3), ev_rms, sigma, sigma_jk, n, conv_ev)
    if accept:
        return FamilyFit(fit, c, weighted)
    log.debug("weak evidence (%.3f EV about the mean at SNR %.2f); no correction", spread, snr)
    return FamilyFit(VignettingModel.identity(w, h, method=METHOD, quality=q, candidate=fit), c, weighted)
