"""Public estimation API: one linear image in, a :class:`VignettingModel` out."""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, replace

import numpy as np

from vigproc.errors import InvalidImageError, ModelError
from vigproc.core import family_fit, robust  # three calls go through the module: tests replace them there
from vigproc.core.colour import fit_colour_field, planar_gradient, symmetric_centre, white_balance
from vigproc.core.family_fit import CENTRE_WORK_SIZE, EVIDENCE_FIT, FamilySettings, LensHint, colour_of, \
    estimate_family, fit_family, luminance_copy, off_centre_fit, same_copy, settings_index, \
    with_colour
from vigproc.core.glow import GlowTest, glow_advantage
from vigproc.core.lensfamily import profile_family
from vigproc.core.methods import EVIDENCE_METHODS, METHODS, ROBUST_METHODS  # noqa: F401  (re-exported)
from vigproc.core.pixels import LUMA_709, bin_mean, check_image, log_image, luminance, require_size
from vigproc.core.model import VignettingModel, frame_coords
from vigproc.core.prior import NaturalPrior, default_prior
from vigproc.core.robust import REAL_LENS_SHAPE_RATIO, RobustSettings, estimate_robust, fit_with_evidence, \
    luminance_evidence, reduced_luminance_evidence, reduced_working_copy

log = logging.getLogger(__name__)

#: Long side of the working copy used by the paper's methods (its protocol size).
LYU_WORK_SIZE = 480
#: A pixel at or above this fraction of the frame's maximum counts as clipped
#: when more than ``CLIP_MIN_FRACTION`` of the pixels reach it.
CLIP_LEVEL = 0.995
CLIP_MIN_FRACTION = 1e-3
@dataclass(frozen=True)
class OffCentreRule:
    """When vigproc's default estimate (:func:`estimate_default`) tries an off-centre fit,
    which one, and when it keeps it. Each threshold was measured on the clean protocol
    (``vigproc bench clean``: vignetting-free camera frames × 20 lensfun lenses, and Lyu's
    Table 1 fields), where every base is an uncropped centre crop, so any off-centre fit
    kept on a real lens's frame is wrong; the measurements that chose each value are in
    docs/benchmarks/clean.md, "How the default's off-centre rule was chosen".

    Attributes
    ----------
    any_min_ev : float
        EV RMS over the frame. No off-centre fit at all when the centred fit rules out a
        fall-off of this much (its candidate's fall-off plus 2σ is below it): a fall-off
        strong enough for a free fit to place shows in the centred fit too, and where the
        centred fit surely sees almost none, a free fit's twelve parameters follow the
        scene's own light.
    grey_min_ev : float
        EV RMS. A fit whose pairs are not weighted by colour (a grey frame, or one whose
        channels change alike) is tried off-centre only when its centred fall-off is at
        least this strong: without the colour weights a scene's shading moves a weaker
        fall-off's centre, and the free fit follows it.
    family_shift, family_min_ev : float
        Half-diagonals; EV RMS. A colour frame's fall-off is fitted in the lens family
        off-centre and elliptical (:func:`vigproc.core.family_fit.fit_off_centre`) rather
        than by the free Kang-Weiss fit when the centre tests put the centre at least
        ``family_shift`` off and the centred fit's fall-off is at least ``family_min_ev``:
        a fall-off's shape and place can be read only when it is strong.
    free_min_ev : float
        EV RMS. From this centred fall-off on, the free fit is made with ``free_settings``,
        below it with the robust estimator's own.
    keep_min_ev : float
        EV RMS of log2 φ over the frame. An off-centre fit that explains the frame better is
        kept only when the fall-off it finds is at least this strong: a scene's own shading
        makes weaker off-centre fits win.
    settings : FamilySettings
        The centre tests, the off-centre family fit, the centred fit they are compared with,
        and the comparison: the lens-family fit's evidence settings (``EVIDENCE_FIT``), not
        the ones retuned for centred fits. The off-centre fit's σ reads their jackknife
        with the single-frame scale and floor.
    glow : GlowTest
        When the centred fit the default would apply is asked whether its fall-off is a
        light source's glow rather than a lens's (:mod:`vigproc.core.glow`): a sunset with
        the sun in the middle is not corrected.
    free_settings : RobustSettings
        The free fit of a strong fall-off. The centre tests have already put it off-centre,
        so the free estimator's priors ("robust": a real lens's centred, round fall-off, and
        the mean scene of centred photographs divided out) are overruled: the centre and
        shape priors are widened (0.15 -> 0.5 half-diagonals, ellipticity 0.3 -> 1.0), no
        scene prior is divided out, and the pairs weigh more against the α prior (n_eff
        400 -> 1600, Cauchy scale 0.2 -> 0.1).
    colour_test_steps : int
        Gauss-Newton steps. A colour frame whose pairs are weighted by colour and whose
        centred fall-off is at least ``family_min_ev``, once its luminance's centre moves,
        is fitted off-centre in the family at once, in at most this many steps, and that
        fit's centre is the colour-weighted pairs' centre test (and, when the test passes,
        the fit the choice reads); 0: a circular centre test of the colour-weighted pairs,
        then the family fit of up to ``family_fit.OFF_CENTRE_ITERATIONS`` steps. A fit
        whose shift, or the luminance's, is short of ``family_shift`` (the free fit's
        band) is refused as the test, and the frame then goes as with 0.
    """

    any_min_ev: float = 0.25
    grey_min_ev: float = 0.9
    family_shift: float = 0.25
    family_min_ev: float = 0.5
    free_min_ev: float = 0.8
    keep_min_ev: float = 1.5
    settings: FamilySettings = FamilySettings(**EVIDENCE_FIT)
    glow: GlowTest = GlowTest()
    free_settings: RobustSettings = RobustSettings(sigma_center=0.5, sigma_ellipticity=1.0, scene_prior=False,
                                                   n_eff=1600.0, sigma_scale=0.1)
    colour_test_steps: int = 8


def clipped_mask(img: np.ndarray) -> np.ndarray | None:
    """Pixels that are not clipped highlights (any channel), or None if none are clipped.

    Clipped areas have zero gradient whatever the vignetting, so they would pull the
    estimate towards "no vignetting".
    """
    peak = float(img.max())
    hot = img >= CLIP_LEVEL * peak
    floor = CLIP_MIN_FRACTION * img.shape[0] * img.shape[1]
    if np.count_nonzero(hot) < floor:  # a hot pixel has a hot value: most frames stop here
        return None
    if img.ndim == 3:
        # channel by channel: ``any(axis=2)`` over the last axis took 1.4 ms of a 480×320 frame
        hot = hot[..., 0] | hot[..., 1] | hot[..., 2] if hot.shape[2] == 3 else np.logical_or.reduce(hot, axis=2)
    if np.count_nonzero(hot) < floor:
        return None
    return ~hot


def _from_working(m: VignettingModel, k: int, width: int, height: int) -> VignettingModel:
    """Map a model estimated on a k×k-binned copy (remainder cropped) to the full frame."""
    if k == 1 and (m.width, m.height) == (width, height):
        return m
    # the binned frame's centre sits (W_b·k − W)/2 px from the full frame's centre
    ox = (m.width * k - width) / 2.0
    oy = (m.height * k - height) / 2.0
    p1, p2, p3 = m.p
    return replace(
        m, width=width, height=height,
        center=(m.center[0] * k + ox, m.center[1] * k + oy),
        p=(p1 / k**2, p2 / k**2, p3 / k**2),
    )


#: The estimators that take a lens hint (``hint=``, :func:`exif_hint`: EXIF's 35-mm focal
#: length and f-number for the lens-family prior); the others ignore it.
HINT_METHODS = ("default", "lens-family")

#: The estimators that read the frame only through binned working copies of about
#: ``work_size`` px (96; the centre tests 60): a reduced copy of a large frame gives
#: them the same data (:func:`estimate_reduced`).
REDUCIBLE_METHODS = ("default", "lens-family", "robust", "real-lens", "flat-field")


def reduction_factor(width: int, height: int, work_size: int = 96) -> int:
    """The block size by which a width×height frame is binned before
    :func:`estimate_reduced`, so that the estimators read the same working copy.

    The working copy bins the frame by k = round(long side / ``work_size``). A reduction
    by a divisor d of k keeps its bins exactly (the same pixels, means of means: the
    reduced frame is binned by k / d), so the largest divisor leaving at least two
    working bins per block is taken, or k itself when k is prime (a reduced frame of
    ``work_size`` px). Only the centre test's coarser copy (60 px) then bins a little
    differently (by 1.5-2 k rather than 1.6 k). Returns 1 for frames under
    10 × ``work_size`` px on the long side: their own binning costs little.
    """
    n = max(int(width), int(height))
    if n < 10 * work_size:  # a small frame's own binning costs little
        return 1
    k = max(1, round(n / work_size))
    for d in sorted((d for d in range(2, k + 1) if k % d == 0 and (k // d >= 2 or d == k)),
                    key=lambda d: (d == k, -d)):
        if round((n // d) / work_size) * d == k:  # the reduced frame's own binning is k / d
            return d
    return 1


def from_reduced(m: VignettingModel, k: int, width: int, height: int) -> VignettingModel:
    """A model estimated on a frame binned k×k (remainder rows and columns dropped) as
    the model of the full width×height frame (its candidate and covariance too)."""
    if k == 1 and (m.width, m.height) == (width, height):
        return m
    big = m.rescale(m.width * k, m.height * k)
    # the binned frame's centre sits (W_b·k − W)/2 px from the full frame's centre
    ox, oy = (big.width - width) / 2.0, (big.height - height) / 2.0

    def moved(x: VignettingModel, candidate=None) -> VignettingModel:
        col = x.colour
        if col is not None:
            col = replace(col, width=width, height=height, center=(col.center[0] + ox, col.center[1] + oy))
        return replace(x, width=width, height=height, center=(x.center[0] + ox, x.center[1] + oy),
                       candidate=candidate, colour=col)

    return moved(big, moved(big.candidate) if big.candidate is not None else None)


def estimate_reduced(small: np.ndarray, k: int, width: int, height: int, method: str = "default", *,
                     hint: LensHint | None = None, usable: np.ndarray | None = None) -> VignettingModel:
    """:func:`estimate_checked` of a frame read as ``small``, its linear light binned k×k
    (:func:`reduction_factor`; e.g. :func:`vigproc.core.pixels.reduce_codes`), for the
    full width×height frame: the estimators of :data:`REDUCIBLE_METHODS` read binned
    working copies only, and a full frame's own binning costs a float copy of every
    pixel. ``small`` is validated here (:func:`check_image`). ``usable``: its pixels
    that hold no clipped highlight or black pixel of the full frame (None: all; the
    second result of :func:`vigproc.core.pixels.reduce_codes`).

    Raises
    ------
    InvalidImageError
        As :func:`estimate`; also a ``method`` not in :data:`REDUCIBLE_METHODS`.
    """
    if method not in REDUCIBLE_METHODS:
        raise InvalidImageError(f"method {method!r} reads the full frame, not a reduced copy")
    a = check_image(small, -1 if np.ndim(small) == 3 else None)
    return from_reduced(estimate_checked(a, method, hint=hint, usable=usable), k, width, height)


def reduced_evidence(small: np.ndarray, k: int, width: int, height: int, method: str = "default", *,
                     usable: np.ndarray | None = None) -> bytes:
    """:func:`frame_evidence` of a width×height frame read as ``small``, its linear light
    binned k×k (:func:`reduction_factor`, as :func:`estimate_reduced` reads it): the same
    binned values, and the full frame's geometry (bin centres, radius, size), which the
    profile's frame fit reads (:func:`vigproc.core.robust.reduced_working_copy`).
    ``usable`` as :func:`estimate_reduced`'s.

    Raises
    ------
    InvalidImageError
        As :func:`estimate`; also a ``method`` not in :data:`EVIDENCE_METHODS`, or a
        ``small`` that is not the frame binned by ``k``.
    """
    if method not in EVIDENCE_METHODS:
        raise InvalidImageError(f"frame evidence comes with {', '.join(EVIDENCE_METHODS)}, not {method!r}")
    a = check_image(small, -1 if np.ndim(small) == 3 else None)
    try:
        return reduced_luminance_evidence(luminance(a), k, width, height, _robust_settings(method, None), usable,
                                          colour_of(a))
    except ValueError as exc:
        raise InvalidImageError(str(exc)) from None


def reduced_estimate_with_evidence(small: np.ndarray, k: int, width: int, height: int, method: str = "default", *,
                                   usable: np.ndarray | None = None) -> tuple[VignettingModel, bytes]:
    """:func:`estimate_with_evidence` of a width×height frame read as ``small`` (its linear
    light binned k×k, as :func:`reduced_evidence` reads it): the robust fit and the
    evidence of one working copy with the full frame's geometry, so the model is the
    full frame's (to float rounding) without :func:`from_reduced`'s shift.

    Raises
    ------
    InvalidImageError
        As :func:`reduced_evidence`.
    """
    if method not in EVIDENCE_METHODS:
        raise InvalidImageError(f"frame evidence comes with {', '.join(EVIDENCE_METHODS)}, not {method!r}")
    a = check_image(small, -1 if np.ndim(small) == 3 else None)
    s = _robust_settings(method, None)
    try:
        raw = reduced_working_copy(luminance(a), k, width, height, s, usable, colour_of(a))
    except ValueError as exc:
        raise InvalidImageError(str(exc)) from None
    m, evidence = fit_with_evidence(raw, s)
    return _named(m, method), evidence


def _named(model: VignettingModel, method: str) -> VignettingModel:
    """A real-lens or flat-field estimate says so (the corrected file's record names
    the method)."""
    return replace(model, method=method) if method in ("real-lens", "flat-field") else model


def _robust_settings(method: str, settings: RobustSettings | None) -> RobustSettings:
    """The robust estimator's settings for ``method`` (one of :data:`ROBUST_METHODS`)."""
    s = settings or RobustSettings()
    if method == "real-lens":
        return replace(s, max_shape_ratio=REAL_LENS_SHAPE_RATIO)
    if method == "flat-field":  # no scene: no scene shading to divide out
        return replace(s, scene_prior=False)
    return s


def estimate(
    img: np.ndarray, method: str = "default", *, channel_axis: int | None = -1,
    prior: NaturalPrior | None = None, settings: RobustSettings | None = None,
    seed: int | None = None, hint: LensHint | None = None,
) -> VignettingModel:
    """Estimate the vignetting function of one linear image.

    Parameters
    ----------
    img : ndarray
        H×W or H×W×C (``channel_axis``) linear intensities, any float/int dtype.
        The fit reads Rec. 709 luminance; the default and lens-family estimators
        also weigh each luminance difference by how alike the R, G and B channels
        change there (a lens darkens them alike; a scene's coloured light does not).
    method : {"default", "robust", "real-lens", "flat-field", "lyu2010", "lyu2010-rand", "ga"} or str
        "default": the lens-family fit, or an off-centre fit for a frame whose centre
        clearly moves (:func:`estimate_default`), with fall-back to no correction when
        the evidence is weak. "robust": vigproc's free Kang-Weiss fit (off-centre,
        elliptical), with the same fall-back. "real-lens": the same, also falling
        back when the fitted fall-off is broader than real lenses' (for photographs
        of real lenses: fewer corrections of photos that do not vignette; see
        :data:`vigproc.core.robust.REAL_LENS_SHAPE_RATIO`). "flat-field": the same without
        the scene prior, for frames of no scene (a white wall, a diffuser over the
        lens, an evenly lit sky), whose fall-off is all the lens's; on a photograph
        of a scene it reads the scene's own darker edges as vignetting. On a colour
        frame it also measures the lens's colour shading (``model.colour``,
        :func:`with_flat_colour`, docs/colour.md).
        "lens-family": a centred fall-off in the two- or three-parameter family
        (three for a colour frame) that lensfun's calibrations of real lenses span (:mod:`vigproc.core.family_fit`), with
        a calibrated uncertainty; for uncropped frames of real lenses.
        "lyu2010": the paper's Gaussian
        approximation followed by the ML fit of Eq. (6). "lyu2010-rand": the ML fit
        from a random start. "ga": Gaussian approximation only (Eqs. 17–20).
        Any other name: an installed estimator plugin (:mod:`vigproc.core.extensions`).
    channel_axis : int or None
        Axis of colour channels; None for a 2-D image.
    prior : NaturalPrior, optional
        Natural-image prior for the paper's methods (default: the shipped one).
    settings : RobustSettings, optional
        Tuning of the robust Kang-Weiss estimators ("robust", "real-lens",
        "flat-field"); given with "default", the robust estimator runs with them.
    seed : int, optional
        Seed for "lyu2010-rand".
    hint : LensHint, optional
        EXIF focal length (35-mm equivalent) and f-number for "lens-family": its
        prior becomes the spread of lensfun calibrations like them. Never the
        lens's own calibration: only focal length and aperture are used.

    Returns
    -------
    VignettingModel
        Parameters for the input's full H×W frame.

    Raises
    ------
    UnknownMethodError
        ``method`` is neither built in nor an installed estimator plugin.
    ExtensionError
        The estimator plugin is broken or returned no valid model.
    InvalidImageError
        Bad dimensions, NaN/Inf, no positive pixel, constant image, or too small
        for the method (the paper's methods need 51×51 px at the working size).

    References
    ----------
    S. Lyu, ACM MM&Sec 2010 (methods "lyu2010", "ga").

    Examples
    --------
    A white wall photographed through a lens with a known fall-off (0.25 EV RMS),
    with a little sensor noise; "flat-field" is the estimator for frames of no scene:

    >>> import numpy as np
    >>> import vigproc
    >>> lens = vigproc.VignettingModel(240, 160, p=(1 / 150**2, 0.0, 1 / 150**2))
    >>> rng = np.random.default_rng(0)
    >>> wall = 0.5 * lens.field() * (1 + 0.01 * rng.standard_normal((160, 240)))
    >>> m = vigproc.estimate(wall, "flat-field", channel_axis=None)
    >>> m.method, m.quality.fallback, round(m.field_ev_rms(), 2)
    ('flat-field', False, 0.25)
    >>> bool(np.abs(np.log2(m.field() / lens.field())).max() < 0.05)  # within 0.05 EV everywhere
    True

    A frame with no fall-off to find is left alone ("do no harm"):

    >>> flat = vigproc.estimate(0.5 * (1 + 0.01 * rng.standard_normal((160, 240))), channel_axis=None)
    >>> flat.is_identity, flat.quality.fallback
    (True, True)
    >>> vigproc.estimate(np.zeros((160, 240)), channel_axis=None)
    Traceback (most recent call last):
    ...
    vigproc.errors.InvalidImageError: image has no positive pixel: linear intensities must be > 0
    """
    plugin = None
    if method not in METHODS:
        # an installed estimator plugin (vigproc.core.extensions), else UnknownMethodError
        # before the pixels are read
        from vigproc.core.extensions import estimator

        plugin = estimator(method)
    a = check_image(img, channel_axis)
    if plugin is not None:
        return plugin(a, channel_axis=-1 if a.ndim == 3 else None, seed=seed)
    return estimate_checked(a, method, prior=prior, settings=settings, seed=seed, hint=hint)


def exif_hint(lens_key, method: str) -> LensHint | None:
    """What a frame's EXIF says of its lens for the lens-family prior (35-mm focal length
    and f-number, never the lens's identity), for the estimators that use it: the hint
    every command gives :func:`estimate` (so a frame's confidence is one figure).

    Parameters
    ----------
    lens_key : LensKey or None
        Anything with ``focal_35mm`` and ``fnumber`` attributes.
    method : str

    Returns
    -------
    LensHint or None
    """
    if method not in HINT_METHODS or lens_key is None:
        return None
    f35, fno = getattr(lens_key, "focal_35mm", None), getattr(lens_key, "fnumber", None)
    return LensHint(f35, fno) if f35 and fno else None


def estimate_checked(
    a: np.ndarray, method: str = "default", *, prior: NaturalPrior | None = None,
    settings: RobustSettings | None = None, seed: int | None = None, hint: LensHint | None = None,
    family=None, usable: np.ndarray | None | object = ...,
) -> VignettingModel:
    """:func:`estimate` of a frame that :func:`~vigproc.core.pixels.check_image` has
    accepted: ``a`` is its result (H×W, or H×W×C with channels last, float). The
    pipeline validates a frame once, at its door, and hands the checked array inward.

    Parameters and errors as :func:`estimate` (``method`` may name a plugin), and
    ``family`` (:class:`~vigproc.core.lensfamily.LensFamily`, optional): the lens family
    of the "default" and "lens-family" fits (default: the shipped one; a benchmark
    passes one without the lenses it scores), and ``usable`` (H×W bool or None): the
    pixels to fit, when the caller knows them better than the frame's own clipped
    highlights (:func:`clipped_mask`) tell (a reduced copy's: :func:`estimate_reduced`).
    """
    require_size(a)  # the door may accept smaller frames (a correction by a profile)
    if method not in METHODS:
        from vigproc.core.extensions import estimator

        return estimator(method)(a, channel_axis=-1 if a.ndim == 3 else None, seed=seed)
    h, w = a.shape[:2]
    keep = clipped_mask(a) if usable is ... else usable
    lum = luminance(a)
    if method == "default" and settings is None:
        return estimate_default(lum, keep, hint, family, colour=colour_of(a))
    if method in ROBUST_METHODS:
        m = _named(estimate_robust(lum, _robust_settings(method, settings), keep), method)
        if method == "flat-field" and a.ndim == 3 and a.shape[2] >= 3:
            m = with_flat_colour(m, a, settings)
        elif method == "flat-field":  # a grey flat frame: no tint, the fall-off's own centre
            m = _about_symmetric_centre(m, a, lum, settings)
        return m
    if method == "lens-family":
        return estimate_family(lum, mask=keep, family=family, hint=hint, colour=colour_of(a))

    from vigproc.core.lyu2010 import estimate_lyu2010

    k = max(1, -(-max(h, w) // LYU_WORK_SIZE))
    work, _ = bin_mean(lum, k)
    if min(work.shape) < 2 * (prior or default_prior()).delta_max + 1:
        raise InvalidImageError(
            f"image of {w}x{h} px is too small for method {method!r} (needs 51 px a side)"
        )
    m = estimate_lyu2010(
        log_image(work), prior or default_prior(), ml=method != "ga",
        random_start=method == "lyu2010-rand", seed=seed,
    )
    m = _from_working(m, k, w, h)
    # the paper's fits state no uncertainty: their fall-off is measured, their σ unknown
    # (NaN), not the "certain" defaults of an empty FitQuality
    try:
        ev = m.field_ev_rms()
    except ModelError:  # a fit that blacks out part of the frame has no fall-off to state
        ev = math.nan
    return replace(m, quality=replace(m.quality, field_ev_rms=ev, field_sigma_ev=math.nan, snr=math.nan))


#: Largest RMS (ln, per block) of a flat frame's channel ratios about its fitted colour
#: field: a white wall's blocks differ by their noise (well under 1 %); a scene's colours
#: by far more, and no tint is read from them.
FLAT_MAX_RESIDUAL = 0.03
#: A flat frame's colour field is kept when some channel's tint (RMS over the frame)
#: exceeds both this (EV) and 3 σ of its fit: below, the channels are taken as alike.
COLOUR_MIN_EV = 0.002


def _without_gradient(m: VignettingModel, a: np.ndarray, lum: np.ndarray, center: tuple[float, float],
                      settings: RobustSettings | None, why: str) -> VignettingModel:
    """``m`` fitted again to the flat frame's luminance with the wall's planar gradient
    about ``center`` (the optical centre) divided out (:func:`planar_gradient`)."""
    g = planar_gradient(lum, center)
    h, w = lum.shape
    tilt = np.exp(-(g[0] * frame_coords(w)[None, :] + g[1] * frame_coords(h)[:, None]))
    m2 = _named(estimate_robust(lum * tilt, _robust_settings("flat-field", settings), clipped_mask(a)), "flat-field")
    log.debug("flat field: wall gradient (%.2e, %.2e) ln/px removed about %s %s", *g, why, center)
    return m2 if not m2.quality.fallback or m.quality.fallback else m


def _about_symmetric_centre(m: VignettingModel, a: np.ndarray, lum: np.ndarray,
                            settings: RobustSettings | None) -> VignettingModel:
    """``m`` refitted without the wall's gradient, removed about the point where the flat
    frame's fall-off is even (:func:`vigproc.core.colour.symmetric_centre`); ``m`` itself
    when the fall-off is too weak to place it."""
    ref = m.candidate if m.candidate is not None else m
    sym = symmetric_centre(lum, ref.center)
    return m if sym is None else _without_gradient(m, a, lum, sym[0], settings, "the fall-off's centre")


def with_flat_colour(m: VignettingModel, a: np.ndarray, settings: RobustSettings | None = None) -> VignettingModel:
    """The flat-field estimate ``m`` of the H×W×C frame ``a`` with the frame's colour
    field (:func:`vigproc.core.colour.fit_colour_field`, centred on ``m``'s centre, or
    its candidate's when it fell back), when the tint is measurable, and its luminance
    fitted again without the wall's planar gradient, removed about the optical centre:
    the tint's centre, or for a colourless lens the point about which the fall-off is
    even (:func:`vigproc.core.colour.symmetric_centre`)."""
    ref = m.candidate if m.candidate is not None else m
    cf = fit_colour_field(a, ref.center, max_residual=FLAT_MAX_RESIDUAL)
    if cf is None:  # a frame with colours of its own (a scene): no tint is read from it
        return m
    lum = luminance(a)
    strong = float(np.max(cf.rms_ev()))
    if strong < max(COLOUR_MIN_EV, 3.0 * cf.sigma_ev()):
        log.debug("flat field: colour shading %.4f EV RMS is not measurable (sigma %.4f EV): none kept",
                  strong, cf.sigma_ev())
        # no tint to place the optical centre: the fall-off's own symmetry places it
        return _about_symmetric_centre(m, a, lum, settings)
    # the tint's centre is the optical centre, which no brightness gradient of the wall
    # moves: the wall's planar gradient is the luminance's part odd about it, removed
    # before the luminance is fitted again -- the luminance of the white-balanced frame,
    # the one the colour field splits between the channels
    lum = np.asarray(a[..., :3]) @ (LUMA_709 / white_balance(a, cf))  # no balanced copy of the frame
    m = _without_gradient(m, a, lum, cf.center, settings, "the tint's centre")
    # a fit too weak to apply alone (the candidate) is still learned from: it keeps the tint too
    cand = replace(m.candidate, colour=cf) if m.candidate is not None else None
    return replace(m, colour=cf, candidate=cand)


def estimate_default(lum: np.ndarray, mask: np.ndarray | None = None,
                     hint: LensHint | None = None, family=None, colour: np.ndarray | None = None,
                     rule: OffCentreRule = OffCentreRule()) -> VignettingModel:
    """vigproc's default estimate of a linear luminance frame.

    An uncropped frame of a real lens: the lens-family fit
    (:func:`vigproc.core.family_fit.estimate_family`). When the fall-off's centre may be
    off the frame's (:func:`vigproc.core.family_fit.fit_centre`: a crop, a shifted lens, a
    stitched image), an off-centre fit is tried too, and kept when it explains the frame's
    log differences clearly better (:func:`vigproc.core.family_fit.pair_losses`): in a
    colour frame whose fall-off is strong and whose centre is clearly off
    (``rule``: :class:`OffCentreRule`) the family's profile with
    a free centre and an elliptical shape (:func:`vigproc.core.family_fit.fit_off_centre`),
    else the free off-centre, elliptical Kang-Weiss fit
    (:func:`vigproc.core.robust.estimate_robust`), kept only when what it finds is strong.
    A frame whose centred fit rules out a fall-off, or a fit not weighted by colour whose
    fall-off is weak, is not fitted off-centre at all. A centred fall-off shaped like the
    light around a source in the scene rather than like a lens's (:mod:`vigproc.core.glow`:
    a sunset with the sun in the middle) is not applied.
    ``colour`` (H×W×3, the frame's R, G, B): the lens-family fit weighs each pair by
    how alike its channels change; the centre must move for the luminance and for the
    colour-weighted pairs; the choice between the fits reads the luminance.
    """
    fs = FamilySettings()
    # one binning of the luminance for the fit (its colour copies added) and the glow test
    work = luminance_copy(lum, fs, mask)
    work_colour = with_colour(work, colour, fs) if colour is not None else work
    # σ from the refits themselves where it could decide whether to try an off-centre fit
    fit = fit_family(lum, fs, mask, family, hint, colour, copy=work_colour, ev_checks=(rule.any_min_ev,))
    # the off-centre choice reads the same copies when its settings make the same ones
    copies = (work, work_colour) if same_copy(fs, rule.settings) else None
    model = _off_centre_choice(lum, mask, hint, family, colour, rule, fit, copies)
    q = model.quality
    # the glow test is asked of a centred fit that would be applied, and strongly enough to harm
    if model is not fit.model or q.fallback or q.snr * q.field_sigma_ev < rule.glow.min_ev:
        return model
    h, w = lum.shape
    advantage = glow_advantage(work, w, h, family or profile_family(), fit.coefficients, fs, rule.glow)
    if not advantage > rule.glow.margin:
        return model
    why = "the fall-off is shaped like the light around a source in the scene, not like a lens's"
    log.info("no correction: %s (%.2f EV about the mean; loss advantage of a glow %.3f > %.3f)", why,
             q.snr * q.field_sigma_ev, advantage, rule.glow.margin)
    return VignettingModel.identity(w, h, method=model.method, candidate=model,
                                    quality=replace(q, fallback=True, confidence=0.0, reason=why))


def _off_centre_choice(lum: np.ndarray, mask: np.ndarray | None, hint: LensHint | None, family,
                       colour: np.ndarray | None, rule: OffCentreRule, fit, copies=None) -> VignettingModel:
    """:func:`estimate_default`'s choice between the centred lens-family fit ``fit``
    (:class:`vigproc.core.family_fit.FamilyFit`) and an off-centre fit: ``fit.model`` itself
    when the centred fit is kept. ``copies``: the frame's luminance and colour working
    copies at ``rule.settings``' size, when the caller has them."""
    model, coef, weighted = fit
    q = (model.candidate or model).quality
    if coef is None or q.field_ev_rms + 2.0 * q.field_sigma_ev < rule.any_min_ev:
        return model
    if not weighted and q.field_ev_rms < rule.grey_min_ev:
        return model
    s = rule.settings
    # The centre must move for the luminance and, in a colour frame, for the colour-weighted
    # pairs too: a scene's coloured light moves the luminance's centre (a sunset, a lit
    # room), not the colour fit's. Which fit explains the frame better is asked of the
    # luminance alone, as of a grey frame: the free Kang-Weiss fit does not weigh pairs by
    # colour, and a loss weighted by colour favours a fit that does (with colour in the
    # loss, Lyu's Table 1 setting 3 on the clean bases went 0.69 -> 1.15 EV). The
    # luminance's own family fit is made only for that comparison.
    # (the shift is all the test reads: no jackknife of the centre)
    # one binning of the luminance for both centre fits
    centre_copy = luminance_copy(lum, replace(s, work_size=CENTRE_WORK_SIZE), mask)
    centre = family_fit.fit_centre(lum, coef, s, mask, family, hint, uncertainty=False, copy=centre_copy)
    if not centre.off_centre(s.off_centre_shift):
        return model
    work, work_colour = copies if copies is not None else (None, None)
    strong = q.field_ev_rms >= rule.family_min_ev
    centre_colour = off = None
    # a colour frame that would be fitted off-centre in the family asks that fit for the
    # colour-weighted pairs' centre: one elliptical fit instead of a circular test and then
    # the fit (OffCentreRule.colour_test_steps; docs/benchmarks/clean.md)
    tried = colour is not None and strong and weighted and rule.colour_test_steps > 0
    if tried:
        off = off_centre_fit(lum, coef, s, mask, family, hint, colour, work_colour, rule.colour_test_steps)
        if off is not None:
            centre_colour = family_fit.CentreFit(off.field.center, np.full((2, 2), math.nan), math.nan,
                                                 off.shift(lum.shape))
        else:  # no answer in its steps: the circular test, and the fit of up to 30 steps, as before
            tried = False
    if colour is not None:
        if centre_colour is not None and centre_colour.off_centre(s.off_centre_shift) \
                and min(centre.shift, centre_colour.shift) < rule.family_shift:
            # a shift that would send the frame to the free fit is the circular test's to give, as
            # before: the elliptical fit's centre passed a clean frame's scene light (2.2 EV applied);
            # that fit, refused as the test, is not the fit the choice reads either: a frame the
            # circular test sends to the family is fitted there as before (up to 30 steps)
            centre_colour = off = None
            tried = False
        if centre_colour is None:  # no family fit off-centre (its shape at the bound): a circular test
            centre_colour = family_fit.fit_centre(lum, coef, s, mask, family, hint, uncertainty=False,
                                                  copy=with_colour(centre_copy, colour, s))
        if not centre_colour.off_centre(s.off_centre_shift):
            return model
    shift = centre.shift if colour is None else min(centre.shift, centre_colour.shift)
    alt = None
    # a grey frame's off-centre family fit is fitted on the very pairs that judge it, and
    # wins too easily (BSDS x lensfun fields, grey: 0.086 EV with it, 0.074 without); a
    # colour frame's is fitted on colour-weighted pairs and judged on the luminance's. A
    # grey frame, or one stored as R = G = B, is fitted as grey and goes the same way.
    if shift >= rule.family_shift and strong and weighted:
        # its σ (a jackknife) only for a fit that is kept: the choice reads its field alone
        if not tried:
            off = off_centre_fit(lum, coef, s, mask, family, hint, colour, work_colour)
        alt = None if off is None else off.field
    if alt is None:
        off = None
        free = rule.free_settings if q.field_ev_rms >= rule.free_min_ev else RobustSettings()
        alt = estimate_robust(lum, free, mask)
    # a fit too weak to keep needs no comparison (both fits state their field's RMS: the
    # model's own field_ev_rms(), not computed again)
    if not (alt.candidate or alt).quality.field_ev_rms >= rule.keep_min_ev:
        return model
    # the luminance's, as the comparison reads (its field alone: no jackknife); its pairs
    # listed once for the fit and the comparison; its IRLS started from the centred colour
    # fit's coefficients (the same fixed point, fewer steps than from the prior mean)
    if work is None:
        work = luminance_copy(lum, s, mask)
    index = settings_index(work.L, work.valid, None, s)
    grey = fit_family(lum, s, mask, family, hint, uncertainty=False, copy=work, index=index,
                      start=coef).model
    loss_family, loss_alt = family_fit.pair_losses(lum, [grey.candidate or grey, alt.candidate or alt], s, mask, work,
                                                   index)
    if loss_alt < loss_family - s.select_margin:
        if off is not None:
            alt = off.with_uncertainty()
        if alt.quality.fallback and alt.candidate is not None and not model.quality.fallback:
            # the centred fit surely sees a fall-off and the off-centre fit places it better:
            # the off-centre fit's own uncertainty is no reason to apply no correction at all
            alt = replace(alt.candidate, quality=replace(alt.candidate.quality, fallback=False))
        log.debug("vignetting centre off the frame's by (%.0f, %.0f) px and the %s fit explains the frame better "
                  "(loss %.3f < %.3f): using it", centre.offset[0], centre.offset[1], alt.method, loss_alt, loss_family)
        return alt
    return model


def frame_evidence(img: np.ndarray, channel_axis: int | None = -1,
                   settings: RobustSettings | None = None) -> bytes:
    """A frame's data for its lens's profile (:func:`vigproc.core.robust.luminance_evidence`,
    pooled by :mod:`vigproc.core.pooling`), prepared as :func:`estimate` prepares it for
    the default method (luminance, clipped pixels masked, binned, log), before the
    scene prior.

    The profile store keeps it per frame and pools the lens's profile from all of
    them (:meth:`vigproc.stores.profiles.ProfileStore.learn`).

    Raises
    ------
    InvalidImageError
        As :func:`estimate`.
    """
    a = check_image(img, channel_axis)
    return luminance_evidence(luminance(a), settings or RobustSettings(), clipped_mask(a), colour_of(a))


def estimate_with_evidence(img: np.ndarray, channel_axis: int | None = -1,
                           settings: RobustSettings | None = None, method: str = "default", *,
                           checked: bool = False) -> tuple[VignettingModel, bytes]:
    """``estimate(img, method)`` and :func:`frame_evidence` of the same frame,
    preparing the frame once (learn mode needs both); ``method`` is one of
    :data:`EVIDENCE_METHODS`. With ``checked``, ``img`` is already the result of
    :func:`~vigproc.core.pixels.check_image` (the pipeline's door) and is not
    validated again.

    Raises
    ------
    InvalidImageError
        As :func:`estimate`.
    """
    if method not in EVIDENCE_METHODS:
        from vigproc.core.extensions import UnknownMethodError

        raise UnknownMethodError(f"frame evidence comes with {', '.join(EVIDENCE_METHODS)}, not {method!r}")
    a = img if checked else check_image(img, channel_axis)
    require_size(a)
    m, evidence = robust.estimate_robust_with_evidence(luminance(a), _robust_settings(method, settings),
                                                       clipped_mask(a), colour_of(a))
    return _named(m, method), evidence


