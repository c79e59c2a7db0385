"""A lens's colour cast from one photograph, reported only where the evidence holds.

At steep angles a sensor's microlenses and colour filters pass the three colours
differently, so a lens can tint the corners (magenta, cyan, green) as well as darken
them. A luminance fall-off divides R, G and B alike and leaves the log-chromaticities
u = log R/G and v = log B/G untouched; a cast adds a smooth radial field to them,
c(r) ≈ A·r² (r in half-diagonals, A the corner-versus-centre shift).

The scene's own colours are the difficulty: a blue sky at the top, a red subject in the
middle. Two facts separate them from a cast (Lyu 2010's argument for the luminance
field, carried to chroma):

- *Sparse derivatives.* Natural images' log-chroma derivatives are mostly near zero with
  a heavy tail at object edges; a cast's are small, dense and smooth. The shift A is
  fitted to the radial component of the log-chroma differences with a redescending
  (Cauchy) loss, so edges between coloured objects count for little.
- *Radial symmetry.* A cast is the same in every direction from the optical centre; a
  scene's colour is not. The fit is made separately in the four quadrants, and a cast
  is reported only when every quadrant shows it in the same direction and strongly
  enough: the weakest quadrant's shift along the common direction, as ΔE00 on a mid
  grey, must reach :attr:`CastSettings.min_sector_de` (and its z score
  :attr:`CastSettings.min_sector_z`). A colour gradient across the frame (sky to
  ground) points outwards in one half and inwards in the other and fails it.

The detector never corrects: a cast detected here is a report (``vigproc estimate
--json``'s ``colour_cast``); colour fields are applied from flat frames, profiles or a
DNG's gain maps.

References
----------
S. Lyu, "Removing vignetting from a single image using natural image statistics",
ICASSP 2010 (../shared/paper/).
G. Sharma, W. Wu, E. N. Dalal, "The CIEDE2000 color-difference formula", Color Research
and Application 30(1), 2005.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field, replace

import numpy as np

from vigproc.core.colour_difference import grey_cast_de
from vigproc.core.pixels import as_channels_last, require_size
from vigproc.core.resample import resize_area_sums
from vigproc.errors import InvalidImageError

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class CastSettings:
    """Parameters of :func:`detect_colour_cast`.

    Attributes
    ----------
    work_long_side : int
        The frame is box-reduced to this long side (px) before fitting.
    steps : tuple of int
        Pixel distances (on the working copy) of the log-chroma differences fitted.
    dark_fraction : float
        Pixels with any channel below this fraction of the frame's 99th percentile are
        left out (their chroma is noise).
    clip_fraction : float
        Pixels with any channel at or above this fraction of the frame's maximum are
        left out (clipped: their chroma is the clip's, not the scene's).
    cauchy_c : float
        Cauchy loss scale, in robust standard deviations of the differences.
    min_sector_de : float
        ΔE00 (mid grey) the weakest quadrant must show along the common cast direction.
    min_sector_z : float
        z score the weakest quadrant's shift must reach.
    min_samples : int
        Fewest usable differences per quadrant for any verdict.
    iterations : int
        IRLS iterations of the Cauchy fits.
    nuisance : bool
        Fit the scene's non-radial colour trends (x, y, x²−y², xy) over the whole frame
        with the cast and take them out before the quadrant fits; the shift reported is
        then the whole-frame fit's. Off by default: on the clean bases it gave more
        false detections at the same power.
    flat_quantile : float
        Only differences whose log-luminance change is within this quantile are fitted:
        chroma edges mostly come with luminance edges, so the smooth insides of objects
        carry the cast with less of the scene.
    """

    work_long_side: int = 240
    steps: tuple[int, ...] = (2,)
    dark_fraction: float = 0.01
    clip_fraction: float = 0.98
    cauchy_c: float = 2.385
    min_sector_de: float = 2.5
    min_sector_z: float = 4.0
    min_samples: int = 200
    iterations: int = 12
    nuisance: bool = False
    flat_quantile: float = 0.5


@dataclass(frozen=True)
class ColourCastEvidence:
    """What one frame says about a colour cast at its corners.

    Attributes
    ----------
    detected : bool
        Every quadrant shows the same corner tint, strongly enough.
    confidence : float
        In [0, 1]: how far the weakest quadrant's evidence is past the decision
        threshold (0.5 at the threshold; a smooth, monotone map of the margin).
    shift : tuple of float
        Estimated corner-versus-centre change of (log R/G, log B/G), natural log,
        from all quadrants together.
    delta_e : float
        ΔE00 of a mid grey at the corner versus the centre under ``shift`` (equal
        luminance).
    sector_shift : tuple of (float, float)
        The same per quadrant (top-left, top-right, bottom-left, bottom-right).
    sector_de : tuple of float
        Each quadrant's shift projected on the common direction, as ΔE00 (negative
        when it points the other way).
    sector_z : tuple of float
        Each projection over its standard error.
    n_samples : int
        Log-chroma differences used.
    reason : str
        Why no cast is reported, when it is not ("" when detected).
    score : float
        The decision statistic, min(weakest quadrant ΔE / ``min_sector_de``, weakest z /
        ``min_sector_z``): a cast is reported at ≥ 1. NaN when the frame could not be
        judged. Benchmarks calibrate a threshold on it (``benchmarks.colour_detect``).
    sector_se : tuple of (float, float)
        Standard errors of ``sector_shift`` (what a series of frames pools:
        :mod:`vigproc.core.cast_series`).
    """

    detected: bool
    confidence: float
    shift: tuple[float, float]
    delta_e: float
    sector_shift: tuple[tuple[float, float], ...] = field(default_factory=tuple)
    sector_de: tuple[float, ...] = field(default_factory=tuple)
    sector_z: tuple[float, ...] = field(default_factory=tuple)
    n_samples: int = 0
    reason: str = ""
    score: float = math.nan
    sector_se: tuple[tuple[float, float], ...] = field(default_factory=tuple)

    @property
    def weakest_de(self) -> float:
        """The weakest quadrant's ΔE00 along the common direction (the test statistic)."""
        return float(min(self.sector_de)) if self.sector_de else 0.0

    def to_dict(self) -> dict:
        """The JSON report (``vigproc estimate --json``'s ``colour_cast``)."""
        return {
            "detected": self.detected,
            "confidence": round(self.confidence, 4),
            "delta_e": round(self.delta_e, 3),
            "shift_log_rg": round(self.shift[0], 5),
            "shift_log_bg": round(self.shift[1], 5),
            "weakest_sector_delta_e": round(self.weakest_de, 3),
            "sector_delta_e": [round(d, 3) for d in self.sector_de],
            **({"score": round(self.score, 4)} if math.isfinite(self.score) else {}),
            **({"reason": self.reason} if self.reason else {}),
        }


def _working_copy(img: np.ndarray, long_side: int) -> np.ndarray:
    a = img[..., :3]
    h, w = a.shape[:2]
    b = int(max(h, w) // (2 * long_side))
    if b >= 2:  # integer binning first: the area matrices of a full frame would be large
        hb, wb = h // b, w // b
        a = a[:hb * b, :wb * b].reshape(hb, b, wb, b, 3).mean(axis=(1, 3), dtype=np.float64)
        h, w = hb, wb
    k = max(h, w) / long_side
    if k <= 1:
        return np.asarray(a, dtype=np.float64)
    hh, ww = max(8, int(round(h / k))), max(8, int(round(w / k)))
    return resize_area_sums(a, hh, ww)


def _cauchy_slope(x: np.ndarray, y: np.ndarray, scale: float, c: float, iters: int) -> tuple[float, float]:
    """Robust slope of y ≈ a·x (Cauchy loss by IRLS) and its sandwich standard error."""
    a = 0.0
    s2 = (c * scale) ** 2
    for _ in range(iters):
        r = y - a * x
        w = 1.0 / (1.0 + r * r / s2)
        den = float(np.dot(w, x * x))
        if den <= 0:
            return 0.0, math.inf
        a = float(np.dot(w, x * y)) / den
    r = y - a * x
    w = 1.0 / (1.0 + r * r / s2)
    se = math.sqrt(float(np.dot((w * x * r) ** 2, np.ones_like(x)))) / float(np.dot(w, x * x))
    return a, se


def _cauchy_fit(X: np.ndarray, y: np.ndarray, scale: float, c: float, iters: int) -> tuple[np.ndarray, np.ndarray]:
    """Robust least squares y ≈ X·b (Cauchy loss by IRLS); b and its sandwich covariance."""
    b = np.zeros(X.shape[1])
    s2 = (c * scale) ** 2
    for _ in range(iters):
        r = y - X @ b
        w = 1.0 / (1.0 + r * r / s2)
        A = (X * w[:, None]).T @ X
        b = np.linalg.solve(A + 1e-12 * np.eye(len(b)), (X * w[:, None]).T @ y)
    r = y - X @ b
    w = 1.0 / (1.0 + r * r / s2)
    A = (X * w[:, None]).T @ X
    Ai = np.linalg.inv(A + 1e-12 * np.eye(len(b)))
    G = X * (w * r)[:, None]
    return b, Ai @ (G.T @ G) @ Ai


def detect_colour_cast(img: np.ndarray, *, channel_axis: int | None = -1, luminance_model=None,
                       usable: np.ndarray | None = None,
                       settings: CastSettings = CastSettings()) -> ColourCastEvidence:
    """Whether a frame's corners carry a colour cast its scene does not explain.

    Parameters
    ----------
    img : numpy.ndarray
        Linear RGB frame (H×W×3, or with the channels on ``channel_axis``).
    channel_axis : int
        Axis of the colour channels.
    luminance_model : VignettingModel, optional
        The frame's luminance estimate: its optical centre is used as the cast's
        centre (the frame centre without it). Its fall-off needs no undoing: it
        leaves the log-chromaticities alone.
    usable : numpy.ndarray, optional
        H×W bool mask of pixels to use (e.g. unclipped blocks of a reduced copy).
    settings : CastSettings
        Working size, masks, loss and decision thresholds.

    Returns
    -------
    ColourCastEvidence
        The estimate and the decision; ``detected`` is False with a ``reason`` when
        the frame has too little usable colour to tell.

    Raises
    ------
    InvalidImageError
        Not a 3-channel image, too small, or not finite.
    """
    a = as_channels_last(np.asarray(img), channel_axis)
    if a.ndim != 3 or a.shape[2] < 3:
        raise InvalidImageError("a colour cast needs an RGB frame (3 channels)")
    require_size(a)
    if not np.all(np.isfinite(a[..., :3])):
        raise InvalidImageError("image has NaN/Inf values")
    h0, w0 = a.shape[:2]
    wc = _working_copy(a, settings.work_long_side)
    h, w = wc.shape[:2]
    top = float(np.percentile(wc.max(axis=2), 99.0))
    peak = float(wc.max())
    none = ColourCastEvidence(False, 0.0, (0.0, 0.0), 0.0)
    if not top > 0:
        return _replace(none, reason="no light in the frame")
    ok = (wc.min(axis=2) > settings.dark_fraction * top) & (wc.max(axis=2) < settings.clip_fraction * peak)
    if usable is not None:
        um = np.asarray(usable, dtype=np.float64)
        if um.shape != (h, w):
            um = resize_area_sums(um, h, w)
        ok &= um > 0.999
    lg = np.log(np.maximum(wc, 1e-12))
    chroma = (lg[..., 0] - lg[..., 1], lg[..., 2] - lg[..., 1])
    lum = np.log(np.maximum(wc @ np.array([0.2126, 0.7152, 0.0722]), 1e-12))
    cx, cy = (w - 1) / 2.0, (h - 1) / 2.0
    if luminance_model is not None:
        cx += luminance_model.center[0] * w / luminance_model.width
        cy += luminance_model.center[1] * h / luminance_model.height
    half_diag = 0.5 * math.hypot(w, h)
    xs = (np.arange(w) - cx) / half_diag
    ys = (np.arange(h) - cy) / half_diag
    # samples: every difference at each step, horizontal and vertical. Its regressors are
    # the differences between its two ends of the field's terms: the cast A·r² and, as
    # nuisance, the scene's colour trends that are not radially symmetric (x, y, x²−y², xy)
    X, Y = np.meshgrid(xs, ys)
    terms = np.stack([X, Y, X * X - Y * Y, X * Y, X * X + Y * Y])
    r4 = terms[-1] ** 2
    dus, dvs, regs, qs, dls = [], [], [], [], []
    for s in settings.steps:
        for axis in (1, 0):
            sl0 = (slice(None), slice(0, w - s)) if axis == 1 else (slice(0, h - s), slice(None))
            sl1 = (slice(None), slice(s, w)) if axis == 1 else (slice(s, h), slice(None))
            m = ok[sl0] & ok[sl1]
            reg = terms[(slice(None),) + sl1] - terms[(slice(None),) + sl0]
            mx = 0.5 * (X[sl0] + X[sl1])
            my = 0.5 * (Y[sl0] + Y[sl1])
            q = (mx >= 0).astype(np.int8) + 2 * (my >= 0).astype(np.int8)
            dus.append((chroma[0][sl1] - chroma[0][sl0])[m])
            dvs.append((chroma[1][sl1] - chroma[1][sl0])[m])
            regs.append(reg[:, m])
            dls.append(np.stack([(lum[sl1] - lum[sl0])[m], reg[-1][m], (r4[sl1] - r4[sl0])[m]]))
            qs.append(q[m])
    du, dv, quad = (np.concatenate(z) for z in (dus, dvs, qs))
    R = np.concatenate(regs, axis=1).T
    if du.size < 4 * settings.min_samples:  # e.g. a usable mask that leaves (almost) nothing
        return _replace(none, n_samples=int(du.size), reason="too few usable pixels in some quadrant")
    if settings.flat_quantile < 1:
        # chroma edges mostly come with luminance edges: keep the smooth parts of objects
        # judged after the frame's radial luminance fall-off is taken out: a vignetting
        # gradient would otherwise choose the samples, and with them a colour bias
        dl, q2, q4 = np.concatenate(dls, axis=1)
        mad = max(1.4826 * float(np.median(np.abs(dl - np.median(dl)))), 1e-4)
        b, _ = _cauchy_fit(np.stack([q2, q4], axis=1), dl, mad, settings.cauchy_c, settings.iterations)
        dl = np.abs(dl - b[0] * q2 - b[1] * q4)
        keep = dl <= np.quantile(dl, settings.flat_quantile)
        du, dv, quad, R = du[keep], dv[keep], quad[keep], R[keep]
    n = int(du.size)
    counts = np.bincount(quad, minlength=4)
    if counts.min() < settings.min_samples:
        return _replace(none, n_samples=n, reason="too few usable pixels in some quadrant")
    scales = []
    for d in (du, dv):
        mad = float(np.median(np.abs(d - np.median(d))))
        scales.append(max(1.4826 * mad, 1e-4))
    est = np.zeros((4, 2))
    se = np.zeros((4, 2))
    glob = np.zeros(2)
    glob_se = np.zeros(2)
    for ch, d in enumerate((du, dv)):
        if settings.nuisance:
            b, cov = _cauchy_fit(R, d, scales[ch], settings.cauchy_c, settings.iterations)
            glob[ch], glob_se[ch] = b[-1], math.sqrt(max(cov[-1, -1], 0.0))
            rest = d - R[:, :-1] @ b[:-1]
        else:
            rest = d
        for qd in range(4):
            sel = quad == qd
            est[qd, ch], se[qd, ch] = _cauchy_slope(R[sel, -1], rest[sel], scales[ch], settings.cauchy_c,
                                                     settings.iterations)
    if settings.nuisance:
        shift = glob
    else:
        wts = 1.0 / np.maximum(se, 1e-12) ** 2
        shift = (wts * est).sum(axis=0) / wts.sum(axis=0)
    norm = float(np.hypot(*shift))
    delta_e = float(grey_cast_de(shift[0], shift[1]))
    if norm <= 0:
        return ColourCastEvidence(False, 0.0, (0.0, 0.0), 0.0, tuple(map(tuple, est)), (0.0,) * 4, (0.0,) * 4, n,
                                  "no chroma shift", 0.0)
    e = shift / norm
    proj = est @ e
    proj_se = np.sqrt((se ** 2) @ (e ** 2))
    sector_de = np.sign(proj) * grey_cast_de(np.abs(proj) * e[0], np.abs(proj) * e[1])
    sector_z = proj / np.maximum(proj_se, 1e-12)
    weakest = float(sector_de.min())
    zmin = float(sector_z.min())
    detected = weakest >= settings.min_sector_de and zmin >= settings.min_sector_z
    # margin past both thresholds, in units of the threshold: 0.5 at the decision
    score = min(weakest / settings.min_sector_de, zmin / settings.min_sector_z)
    margin = score - 1.0
    confidence = float(1.0 / (1.0 + math.exp(-4.0 * margin)))
    reason = ""
    if not detected:
        reason = ("the quadrants disagree: a scene's colour, not a lens's cast" if weakest < 0.5 * settings.min_sector_de
                  and delta_e >= settings.min_sector_de else "no corner tint beyond the scene's colour")
    log.debug("colour cast: shift %s, dE %.2f, sectors %s (z %s)", shift, delta_e, sector_de, sector_z)
    return ColourCastEvidence(detected, confidence, (float(shift[0]), float(shift[1])), delta_e,
                              tuple((float(u), float(v)) for u, v in est), tuple(float(d) for d in sector_de),
                              tuple(float(z) for z in sector_z), n, reason, float(score),
                              tuple((float(u), float(v)) for u, v in se))


def _replace(ev: ColourCastEvidence, **kw) -> ColourCastEvidence:
    return replace(ev, **kw)
