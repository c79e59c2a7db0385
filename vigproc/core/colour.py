"""Colour shading: how a lens tints the corners, not only darkens them.

A lens on a digital sensor darkens the three colour channels by slightly different
amounts towards the corners (the microlenses and the filter stack pass each colour
differently at steep chief-ray angles). vigproc models the per-channel field as the
luminance fall-off φ (:class:`vigproc.core.model.VignettingModel`) times a smooth
per-channel ratio::

    φ_c(v) = φ(v) · ρ_c(v),    ρ_c = exp(d_c) / Σ_k w_k exp(d_k)

with w the Rec. 709 luminance weights, so Σ_c w_c ρ_c = 1 at every pixel: the colour
field never changes the luminance fall-off, only how it splits between the channels.

Form of d_c
-----------
d_c is an even polynomial of the radius about the field's own centre c,
d_c(ρ) = a_c1 ρ² + a_c2 ρ⁴ + a_c3 ρ⁶, ρ = |v − c| / (half-diagonal of the frame) -- a
radius independent of the luminance model's shape matrix (an identity luminance model
still has a colour field). No constant term: a channel's overall level is white
balance, not shading. No tilt: a linear colour tilt across a flat frame cannot be told
from a colour gradient of the light on the wall. The centre is fitted
(:func:`fit_log_ratios`, held near the luminance centre where the tint is too weak to
place it): no brightness gradient of a wall moves a channel ratio, so it locates the
optical axis, about which :func:`planar_gradient` then finds the wall's gradient. Three
even terms follow the cos^k(θ) fall-off of a chief-ray angle θ = atan(r/f) to
≤ 0.001 EV over a frame (``vigproc bench colour``).

References
----------
.. [1] Y. Zheng, S. Lin, S. B. Kang, R. Xiao, J. C. Gee, C. Kambhamettu, "Single-image
   vignetting correction from gradient distribution symmetries", IEEE TPAMI 35(6), 2013
   (flat-field calibration as ground truth).
.. [2] G. Sharma, W. Wu, E. N. Dalal, "The CIEDE2000 color-difference formula:
   implementation notes, supplementary test data, and mathematical observations",
   Color Research & Application 30(1), 2005.
.. [3] Adobe, *Digital Negative (DNG) Specification* 1.4.0.0, "GainMap" (per-plane gains).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Sequence

import logging

import numpy as np

from vigproc.core.fieldjson import check_field_dict, field_to_dict
from vigproc.errors import InvalidImageError, ModelError

logger = logging.getLogger(__name__)

#: Rec. 709 luminance weights of R, G, B (as :func:`vigproc.core.pixels.luminance`).
LUMA = np.array([0.2126, 0.7152, 0.0722])
#: Even powers of ρ in d_c.
POWERS = (2, 4, 6)
#: Channel names of the rows of :attr:`ColourField.coeffs`.
CHANNELS = ("R", "G", "B")
SCHEMA = "vigproc.colour/1"
#: Largest difference between channels at ρ = 1 accepted (EV).
MAX_SPREAD_EV = 6.0
#: Fewest usable blocks, and rows and columns of blocks, a flat frame's colour field is
#: fitted from (its coefficients and centre need more points than they are; a strip of
#: a frame a block high has none).
MIN_COLOUR_BLOCKS, MIN_BLOCK_LINES = 16, 2
_LN2 = math.log(2.0)


def frame_coords(n: int) -> np.ndarray:
    """Pixel-centre coordinates of ``n`` samples from the frame centre (as
    :func:`vigproc.core.model.frame_coords`, which imports this module)."""
    return np.arange(n, dtype=np.float64) - (n - 1) / 2.0


def _floats(name: str, v: Any, shape: tuple[int, ...]) -> np.ndarray:
    try:
        a = np.asarray(v, dtype=np.float64)
    except (TypeError, ValueError):
        raise ModelError(f"colour field {name} must be numbers of shape {shape}") from None
    if a.shape != shape or not np.all(np.isfinite(a)):
        raise ModelError(f"colour field {name} must be finite numbers of shape {shape}, got {np.shape(v)}")
    return a


@dataclass(frozen=True, eq=False)
class ColourField:
    """Per-channel ratios of a lens's fall-off to its luminance fall-off.

    Attributes
    ----------
    width, height : int
        The frame the centre refers to (any resolution of it can be evaluated).
    center : (float, float)
        Centre of the radius, px from the frame centre (the luminance model's centre).
    coeffs : ndarray (3, 3)
        Row c: (a_c1, a_c2, a_c3) of d_c = Σ a_ck ρ^(2k) for R, G, B (natural log).
        Only differences between rows matter (ρ_c is normalised per pixel).
    sigma : ndarray (3, 3) or None
        1-σ uncertainty of each coefficient.
    source : str
        Where it came from (``flat-field``, ``dng:GainMap``, ...).
    """

    width: int
    height: int
    center: tuple[float, float] = (0.0, 0.0)
    coeffs: Any = None
    sigma: Any = None
    source: str = ""

    def __post_init__(self) -> None:
        for k in ("width", "height"):
            v = getattr(self, k)
            if isinstance(v, bool) or not isinstance(v, (int, np.integer, float)) or v < 1 or int(v) != v:
                raise ModelError(f"colour field {k} must be a positive integer, got {v!r}")
            object.__setattr__(self, k, int(v))
        c = _floats("center", self.center, (2,))
        object.__setattr__(self, "center", (float(c[0]), float(c[1])))
        n = (len(CHANNELS), len(POWERS))
        co = np.zeros(n) if self.coeffs is None else _floats("coeffs", self.coeffs, n)
        co.setflags(write=False)
        object.__setattr__(self, "coeffs", co)
        if self.sigma is not None:
            s = _floats("sigma", self.sigma, n)
            if np.any(s < 0):
                raise ModelError("colour field sigma must be >= 0")
            s.setflags(write=False)
            object.__setattr__(self, "sigma", s)
        object.__setattr__(self, "source", str(self.source))
        # channels more than 6 EV apart at ρ = 1 (a frame's corner): a corrupt file, not a lens
        if float(np.abs(self.coeffs - self.coeffs[1]).sum(axis=1).max()) > MAX_SPREAD_EV * _LN2:
            raise ModelError(f"colour field coefficients are absurd (channels more than {MAX_SPREAD_EV:g} EV "
                             "apart in the corners)")

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, ColourField):
            return NotImplemented
        return (self.size == other.size and self.center == other.center and self.source == other.source
                and np.array_equal(self.coeffs, other.coeffs)
                and (self.sigma is None) == (other.sigma is None)
                and (self.sigma is None or np.array_equal(self.sigma, other.sigma)))

    __hash__ = None  # type: ignore[assignment]

    @property
    def size(self) -> tuple[int, int]:
        return (self.width, self.height)

    @property
    def is_neutral(self) -> bool:
        """All channels alike: no colour shading."""
        return bool(np.all(self.coeffs == self.coeffs[1]))

    # ------------------------------------------------------------ evaluation
    def _rho2(self, x: np.ndarray, y: np.ndarray, sx: float, sy: float) -> np.ndarray:
        # x, y: px from the centre of a frame sx, sy times the reference size
        hd = 0.5 * math.hypot(self.width * sx, self.height * sy)
        ex, ey = x - self.center[0] * sx, y - self.center[1] * sy
        return (ex * ex + ey * ey) / (hd * hd)

    def log_ratios_at(self, x: np.ndarray, y: np.ndarray, width: int | None = None,
                      height: int | None = None) -> np.ndarray:
        """ln ρ_c at points (x, y), px from the frame centre of a ``width``×``height``
        resolution of the frame (default its own); shape ``broadcast(x, y) + (3,)``."""
        sx = 1.0 if width is None else width / self.width
        sy = 1.0 if height is None else height / self.height
        r2 = self._rho2(np.asarray(x, dtype=np.float64), np.asarray(y, dtype=np.float64), sx, sy)
        basis = np.stack([r2 ** (p // 2) for p in POWERS], axis=-1)
        d = basis @ self.coeffs.T  # (..., 3)
        d = d - d[..., 1:2]  # relative to G: exact in floating point where all rows agree
        return d - np.log(np.exp(d) @ LUMA)[..., None]

    def log_ratios(self, width: int | None = None, height: int | None = None,
                   rows: np.ndarray | None = None) -> np.ndarray:
        """ln ρ_c on the pixel grid of a ``width``×``height`` resolution of the frame
        (default its own), H×W×3; ``rows``: only these rows (len(rows)×W×3)."""
        w = self.width if width is None else int(width)
        h = self.height if height is None else int(height)
        ys = frame_coords(h) if rows is None else frame_coords(h)[np.asarray(rows)]
        return self.log_ratios_at(frame_coords(w)[None, :], ys[:, None], w, h)

    def ratios(self, width: int | None = None, height: int | None = None) -> np.ndarray:
        """ρ_c, H×W×3 multiplicative per-channel factors whose luminance-weighted mean
        (Rec. 709) is 1 at every pixel: the channel c's field is φ·ρ_c."""
        return np.exp(self.log_ratios(width, height))

    def rms_ev(self, n: int = 64) -> np.ndarray:
        """RMS of log2 ρ_c over the frame, EV, per channel (how strong the tint is)."""
        s = n / max(self.width, self.height)
        w, h = max(2, round(self.width * s)), max(2, round(self.height * s))
        lr = self.log_ratios(w, h) / _LN2
        return np.sqrt(np.mean(lr * lr, axis=(0, 1)))

    def sigma_ev(self, n: int = 32) -> float:
        """1-σ uncertainty of log2 ρ (RMS over the frame and the channels), EV, from
        the coefficients' σ (treated as independent); NaN when unknown."""
        if self.sigma is None:
            return math.nan
        s = n / max(self.width, self.height)
        w, h = max(2, round(self.width * s)), max(2, round(self.height * s))
        r2 = self._rho2(frame_coords(w)[None, :], frame_coords(h)[:, None], w / self.width, h / self.height)
        basis = np.stack([r2 ** (p // 2) for p in POWERS], axis=-1)
        var = (basis * basis) @ (self.sigma.T ** 2)  # (h, w, 3)
        return float(np.sqrt(np.mean(var))) / _LN2

    # ----------------------------------------------------------- transforms
    def rescale(self, width: int, height: int) -> ColourField:
        """The same field for another resolution of the frame (the centre scales)."""
        sx, sy = width / self.width, height / self.height
        return ColourField(int(width), int(height), (self.center[0] * sx, self.center[1] * sy),
                           self.coeffs, self.sigma, self.source)

    def with_center(self, center: tuple[float, float]) -> ColourField:
        return ColourField(self.width, self.height, center, self.coeffs, self.sigma, self.source)

    # ---------------------------------------------------------- serialising
    def to_dict(self) -> dict[str, Any]:
        return field_to_dict(SCHEMA, self.width, self.height,
                             {"center": list(self.center), "powers": list(POWERS), "channels": list(CHANNELS),
                              "coeffs": self.coeffs.tolist()}, self.sigma, self.source)

    @classmethod
    def from_dict(cls, d: Any) -> ColourField:
        """The field of a :meth:`to_dict` mapping (one without ``schema`` is read as
        ``vigproc.colour/1``).

        Raises
        ------
        ModelError
            Unknown schema, missing or malformed fields.
        """
        sigma, source = check_field_dict(d, "colour field", SCHEMA, ("width", "height", "coeffs"),
                                         schema_optional=True)
        if d.get("powers", list(POWERS)) != list(POWERS) or d.get("channels", list(CHANNELS)) != list(CHANNELS):
            raise ModelError(f"colour field must have powers {list(POWERS)} and channels {list(CHANNELS)}")
        return cls(d["width"], d["height"], tuple(d.get("center", (0.0, 0.0))), d["coeffs"], sigma, source)


# --------------------------------------------------------------------------- #
# fitting
# --------------------------------------------------------------------------- #


def _solve_ratios(lr: np.ndarray, x: np.ndarray, y: np.ndarray, width: int, height: int,
                  center: tuple[float, float], wts: np.ndarray, tilt: bool):
    """Weighted linear least squares of d_R − d_G and d_B − d_G about ``center``:
    (coeffs, sigma, residuals (n, 2), residual rms (3,))."""
    cf0 = ColourField(width, height, center)
    r2 = cf0._rho2(x, y, 1.0, 1.0)
    hd = 0.5 * math.hypot(width, height)
    cols = [np.ones_like(r2)] + [r2 ** (p // 2) for p in POWERS]
    if tilt:
        cols += [x / hd, y / hd]
    A = np.stack(cols, axis=1)
    sw = np.sqrt(wts)
    Aw = A * sw[:, None]
    ata_inv = np.linalg.pinv(Aw.T @ Aw)
    coeffs = np.zeros((3, len(POWERS)))
    sigma = np.zeros((3, len(POWERS)))
    rms = np.zeros(3)
    res_all = []
    for c in (0, 2):
        t = lr[:, c] - lr[:, 1]
        sol = ata_inv @ (Aw.T @ (t * sw))
        res = t - A @ sol
        dof = max(t.size - A.shape[1], 1)
        s2 = float(np.sum(wts * res * res) / dof)
        coeffs[c] = sol[1:1 + len(POWERS)]
        sigma[c] = np.sqrt(np.maximum(np.diag(ata_inv)[1:1 + len(POWERS)] * s2, 0.0))
        rms[c] = float(np.sqrt(np.mean(res * res)))
        res_all.append(res * sw)
    return coeffs, sigma, np.stack(res_all, axis=1), rms


#: Prior spread of a colour field's centre about the luminance centre, in half-diagonals:
#: it only matters where the tint is too weak to place its own centre.
CENTER_PRIOR = 0.25


def fit_log_ratios(log_ratio: np.ndarray, x: np.ndarray, y: np.ndarray, width: int, height: int,
                   center: tuple[float, float], *, weights: np.ndarray | None = None,
                   free_center: bool = False, tilt: bool = False,
                   source: str = "") -> tuple[ColourField, np.ndarray]:
    """The :class:`ColourField` whose d_R − d_G and d_B − d_G best fit measured log
    ratios, by weighted least squares (linear in the coefficients).

    Parameters
    ----------
    log_ratio : ndarray (n, 3)
        ln of each channel at the points over any common reference (a per-channel
        constant, white balance, is absorbed by a free constant per channel).
    x, y : ndarray (n,)
        Points, px from the frame centre of the ``width``×``height`` frame.
    center : (float, float)
        The radius's centre (the luminance model's), or the start of its search.
    weights : ndarray (n,), optional
        Inverse variances of the points (default equal).
    free_center : bool
        Fit the centre too (shared by R and B, variable projection), held near
        ``center`` by a weak prior (:data:`CENTER_PRIOR`): a lens's tint need not be
        centred where an unevenly lit flat frame puts its luminance centre.
    tilt : bool
        Also fit a linear tilt per channel, as a nuisance dropped from the field.
    source : str

    Returns
    -------
    (ColourField, residual_rms)
        residual_rms: per channel RMS of the fit's residual, natural log.
    """
    x = np.asarray(x, dtype=np.float64).ravel()
    y = np.asarray(y, dtype=np.float64).ravel()
    lr = np.asarray(log_ratio, dtype=np.float64).reshape(-1, 3)
    wts = np.ones_like(x) if weights is None else np.asarray(weights, dtype=np.float64).ravel()
    c0 = (float(center[0]), float(center[1]))
    if free_center:
        from scipy.optimize import least_squares

        hd = 0.5 * math.hypot(width, height)

        def resid(u: np.ndarray) -> np.ndarray:
            c = (c0[0] + u[0] * hd, c0[1] + u[1] * hd)
            r = _solve_ratios(lr, x, y, width, height, c, wts, tilt)[2].ravel()
            # the prior in the data's own units: as strong as one point's noise per 1/CENTER_PRIOR
            noise = max(float(np.sqrt(np.mean(r * r))), 1e-6)
            return np.concatenate([r, noise * u / CENTER_PRIOR])

        sol = least_squares(resid, np.zeros(2), method="lm", x_scale=0.05)
        c0 = (c0[0] + float(sol.x[0]) * hd, c0[1] + float(sol.x[1]) * hd)
    coeffs, sigma, _, rms = _solve_ratios(lr, x, y, width, height, c0, wts, tilt)
    return ColourField(width, height, c0, coeffs, sigma, source), rms


def fit_colour_field(img: np.ndarray, center: tuple[float, float] = (0.0, 0.0), *, block: int | None = None,
                     source: str = "flat-field", max_residual: float | None = None) -> ColourField | None:
    """The colour field of a flat frame (a white wall, a diffuser over the lens).

    The ratio of each channel to green is taken in blocks and fitted in log
    (:func:`fit_log_ratios`). The light's brightness, even or not, cancels in a ratio:
    a wall lit more on one side changes no channel ratio as long as the light's colour
    is the same across it; a linear colour gradient is fitted as a tilt and dropped.

    Parameters
    ----------
    img : ndarray, H×W×3 linear RGB (channels last), or a list of such frames of
        one size (their log ratios are averaged: the noise falls as 1/√n)
    center : (float, float)
        The luminance model's centre, px from the frame centre.
    block : int, optional
        Block size in px (default: about 64 blocks on the long side).
    max_residual : float, optional
        Largest RMS (natural log, per block) of the ratios about the fitted field for a
        flat frame: above it the frame has colours of its own (a scene, a stained wall)
        and None is returned.

    Returns
    -------
    ColourField or None
        None when ``max_residual`` is exceeded, the ratios are no lens's (channels
        more than :data:`MAX_SPREAD_EV` apart in the corners), or the frame gives fewer
        usable blocks than :data:`MIN_COLOUR_BLOCKS` (or fewer than two rows or columns).

    Raises
    ------
    InvalidImageError
        Not H×W×3 (or more channels), or frames of different sizes.
    """
    frames = list(img) if isinstance(img, (list, tuple)) else [img]
    shapes = {np.shape(f) for f in frames}
    if len(shapes) != 1:
        raise InvalidImageError(f"flat frames differ in size: {sorted(shapes)}")
    shape = shapes.pop()
    if len(shape) != 3 or shape[2] < 3:
        raise InvalidImageError(f"a colour field needs an H×W×3 frame, got shape {shape}")
    h, w = shape[:2]
    k = block or max(1, max(h, w) // 64)
    hb, wb = h // k, w // k
    acc = np.zeros((hb, wb, 3))
    ok = np.ones((hb, wb), dtype=bool)
    for f in frames:
        a = np.asarray(f, dtype=np.float64)[: hb * k, : wb * k, :3]
        m = a.reshape(hb, k, wb, k, 3).mean(axis=(1, 3))
        good = np.all(m > 0, axis=2)
        ok &= good
        acc += np.log(np.where(good[..., None], m, 1.0))
    if hb < MIN_BLOCK_LINES or wb < MIN_BLOCK_LINES or int(ok.sum()) < MIN_COLOUR_BLOCKS:
        logger.debug("no colour field: %d usable blocks of %d px in %d x %d", int(ok.sum()), k, wb, hb)
        return None
    acc /= len(frames)
    # block centres in px from the frame centre
    xs = (np.arange(wb) * k + (k - 1) / 2.0) - (w - 1) / 2.0
    ys = (np.arange(hb) * k + (k - 1) / 2.0) - (h - 1) / 2.0
    X, Y = np.meshgrid(xs, ys)
    try:
        cf, rms = fit_log_ratios(acc[ok], X[ok], Y[ok], w, h, center, free_center=True, source=source)
    except ModelError as exc:  # absurd coefficients: colours of a scene, not of a lens
        logger.debug("no colour field: %s", exc)
        return None
    if max_residual is not None and float(np.max(rms)) > max_residual:
        logger.debug("no colour field: the frame's colours vary by %.3f (ln RMS) about any lens's field",
                     float(np.max(rms)))
        return None
    return cf


def _to_cell_centre(plane: np.ndarray, r: int, c: int) -> np.ndarray:
    """Phase (r, c) of a 2×2 cell, sampled at sensor pixel (2i + r, 2j + c), interpolated
    (bilinear) at the cell centre (2i + ½, 2j + ½): a quarter plane pixel towards the
    neighbour on the centre's side, the edge row or column held."""
    def shift(a: np.ndarray, axis: int, towards_next: bool) -> np.ndarray:
        if a.shape[axis] < 2:
            return a
        n = a.shape[axis]
        idx = np.minimum(np.arange(n) + 1, n - 1) if towards_next else np.maximum(np.arange(n) - 1, 0)
        return 0.75 * a + 0.25 * np.take(a, idx, axis=axis)

    return shift(shift(plane, 0, r == 0), 1, c == 0)


def cfa_rgb(raw: np.ndarray, pattern: np.ndarray, colours: Sequence[str], black: Sequence[float] | float = 0.0,
            white: float = 1.0) -> np.ndarray:
    """A Bayer mosaic's colour planes before demosaicing, one pixel per 2×2 cell:
    (H/2)×(W/2)×3 linear R, G (the mean of the two green phases), B.

    Each phase is resampled to the cell's centre (bilinear: a quarter of a plane pixel
    in each axis, edges held): a phase's photosites lie half a sensor pixel off it, and a
    channel ratio is a small difference of strong fields, so a quarter-pixel offset
    between the R and B planes moves a tint's fitted centre by about a pixel
    (k_R/(k_R − k_G) quarter pixels for cos^k fall-offs).

    Parameters
    ----------
    raw : ndarray H×W
        The mosaic as stored (rawpy's ``raw_image_visible``).
    pattern : ndarray 2×2 of int
        Colour index of each phase of the cell (rawpy's ``raw_pattern``).
    colours : sequence of str
        Name of each colour index (rawpy's ``color_desc``, e.g. "RGBG").
    black : float or sequence of float
        Black level, per colour index (rawpy's ``black_level_per_channel``) or one.
    white : float
        White level.

    Returns
    -------
    ndarray float64, (H // 2) × (W // 2) × 3

    Raises
    ------
    InvalidImageError
        Not a 2×2 pattern of R, G and B phases (an X-Trans or a four-colour sensor).
    """
    pat = np.asarray(pattern)
    names = [str(c).upper() for c in colours]
    if pat.shape != (2, 2) or any(not (0 <= int(i) < len(names)) for i in pat.ravel()):
        raise InvalidImageError(f"colour planes need a 2x2 Bayer pattern, got {pat.tolist()}")
    phases = [names[int(i)] for i in pat.ravel()]
    if sorted(phases) != ["B", "G", "G", "R"]:
        raise InvalidImageError(f"colour planes need one R, two G and one B phase, got {''.join(phases)}")
    a = np.asarray(raw, dtype=np.float64)
    h2, w2 = a.shape[0] // 2, a.shape[1] // 2
    cells = a[: 2 * h2, : 2 * w2].reshape(h2, 2, w2, 2)
    bl = np.broadcast_to(np.asarray(black, dtype=np.float64), (len(names),)) if np.ndim(black) else \
        np.full(len(names), float(black))
    out = np.zeros((h2, w2, 3))
    for r in range(2):
        for c in range(2):
            idx = int(pat[r, c])
            plane = _to_cell_centre((cells[:, r, :, c] - bl[idx]) / max(float(white) - bl[idx], 1e-12), r, c)
            k = "RGB".index(names[idx])
            out[..., k] += plane / (2.0 if k == 1 else 1.0)
    return out


def _log_blocks(lum: np.ndarray, block: int | None):
    """ln of a frame's k×k block means and the blocks' centres (px from the frame
    centre): (ln means hb×wb, X, Y, k, (h, w))."""
    a = np.asarray(lum, dtype=np.float64)
    h, w = a.shape
    k = block or max(1, max(h, w) // 64)
    hb, wb = h // k, w // k
    m = a[: hb * k, : wb * k].reshape(hb, k, wb, k).mean(axis=(1, 3))
    xs = (np.arange(wb) * k + (k - 1) / 2.0) - (w - 1) / 2.0
    ys = (np.arange(hb) * k + (k - 1) / 2.0) - (h - 1) / 2.0
    X, Y = np.meshgrid(xs, ys)
    lm = np.where(m > 0, np.log(np.maximum(m, 1e-300)), np.nan)
    return lm, X, Y, k, (h, w)


def _odd_part(lm: np.ndarray, X: np.ndarray, Y: np.ndarray, k: int, size: tuple[int, int],
              center: tuple[float, float]) -> tuple[np.ndarray, np.ndarray] | None:
    """The planar gradient fit to the log blocks' part odd about ``center`` and its
    residual: ((g_x, g_y), residual per block pair); None with fewer than 16 pairs."""
    from scipy.ndimage import map_coordinates

    h, w = size
    hb, wb = lm.shape
    # mirror of each block about the centre, as a (fractional) block index
    mi = ((2 * center[0] - X) + (w - 1) / 2.0 - (k - 1) / 2.0) / k
    mj = ((2 * center[1] - Y) + (h - 1) / 2.0 - (k - 1) / 2.0) / k
    ok = (mi >= 0) & (mi <= wb - 1) & (mj >= 0) & (mj <= hb - 1) & np.isfinite(lm)
    if np.count_nonzero(ok) < 16:
        return None
    filled = np.where(np.isfinite(lm), lm, np.nanmean(lm))
    odd = lm[ok] - map_coordinates(filled, [mj[ok], mi[ok]], order=1)
    A = np.stack([2 * (X[ok] - center[0]), 2 * (Y[ok] - center[1])], axis=1)
    g = np.linalg.lstsq(A, odd, rcond=None)[0]
    return g, odd - A @ g


def planar_gradient(lum: np.ndarray, center: tuple[float, float], block: int | None = None) -> np.ndarray:
    """The planar illumination gradient (g_x, g_y) of a flat frame, ln per px, from its
    part that is odd about ``center`` (px from the frame centre).

    A lens's fall-off is even about its optical centre (radially symmetric, or an
    ellipse centred there); ln of a wall's light falling off linearly is odd about any
    point. So ln L(c + v) − ln L(c − v) = 2 g·v, fitted by least squares over the block
    pairs that both lie in the frame. This needs the optical centre: a colour field's
    centre (:func:`fit_colour_field`), which no brightness gradient moves, or, for a
    colourless lens, :func:`symmetric_centre`.

    Parameters
    ----------
    lum : ndarray, H×W linear luminance
    center : (float, float)
    block : int, optional
        Block size (default about 64 blocks on the long side).

    Returns
    -------
    ndarray (2,)
    """
    lm, X, Y, k, size = _log_blocks(lum, block)
    fit = _odd_part(lm, X, Y, k, size, center)
    return np.zeros(2) if fit is None else fit[0]


def white_balance(img: np.ndarray, cf: ColourField, block: int | None = None) -> np.ndarray:
    """The per-channel levels of a flat frame relative to green, beside its colour field:
    (3,) factors b with b_G = 1 such that img_c / b_c = φ·ρ_c times one common level.

    A wall's colour (and the camera's white balance, or none on a RAW's planes) scales
    each channel by a constant; ρ_c has no constant term (it is 1 where the field's
    polynomial is 0). The luminance the colour field splits (Σ w_c ρ_c = 1) is that of
    the balanced frame: the luminance of an unbalanced one weighs the channels' fall-offs
    by the wall's colour too (a wall of R, G, B levels (0.4, 0.8, 0.56) through a phone
    module's tint: 0.006-0.009 EV off in every channel).

    Parameters
    ----------
    img : ndarray, H×W×3 linear (channels last)
    cf : ColourField
        The frame's colour field (:func:`fit_colour_field`).
    block : int, optional
        Block size (default about 64 blocks on the long side).

    Returns
    -------
    ndarray (3,)
    """
    a = np.asarray(img)
    h, w = a.shape[:2]
    k = block or max(1, max(h, w) // 64)
    hb, wb = h // k, w // k
    m = a[: hb * k, : wb * k, :3].reshape(hb, k, wb, k, 3).mean(axis=(1, 3), dtype=np.float64)
    ok = np.all(m > 0, axis=2)
    xs = (np.arange(wb) * k + (k - 1) / 2.0) - (w - 1) / 2.0
    ys = (np.arange(hb) * k + (k - 1) / 2.0) - (h - 1) / 2.0
    X, Y = np.meshgrid(xs, ys)
    lr = cf.rescale(w, h).log_ratios_at(X[ok], Y[ok])
    off = np.median(np.log(m[ok]) - lr, axis=0)
    return np.exp(off - off[1])


#: Largest 1-σ uncertainty of a centre found from the fall-off's symmetry alone
#: (:func:`symmetric_centre`), in half-diagonals: a weaker fall-off does not place it.
SYMMETRIC_CENTRE_MAX_SIGMA = 0.01


def symmetric_centre(lum: np.ndarray, start: tuple[float, float] = (0.0, 0.0), block: int | None = None,
                     reach: float = 0.15) -> tuple[tuple[float, float], float] | None:
    """The point about which a flat frame's log luminance is even up to a planar
    gradient: the optical centre of a colourless lens on an unevenly lit wall.

    A planar gradient of the wall's light shifts a fall-off's apparent centre (ln of the
    fall-off about c + δ is, to first order, the fall-off about c plus a linear ramp),
    so a Kang-Weiss fit with a free centre reads the gradient as an off-centre lens. The
    ramp is odd about every point; the fall-off's higher even terms (r⁴, r⁶, r⁸) are
    even only about the optical centre. So the log blocks are fitted (least squares,
    variable projection over the centre c) by a constant, a plane, a quadratic form and
    r⁴, r⁶, r⁸ about c: the plane takes the gradient and any first-order shift, the
    higher terms place c. Needs a fall-off with curvature beyond r²: the answer is None
    when the centre's 1-σ uncertainty exceeds :data:`SYMMETRIC_CENTRE_MAX_SIGMA`
    half-diagonals.

    Parameters
    ----------
    lum : ndarray, H×W linear luminance of a flat frame
    start : (float, float)
        Where the search starts (px from the frame centre).
    block : int, optional
        Block size (default about 64 blocks on the long side).
    reach : float
        The search stays within this many half-diagonals of the frame centre.

    Returns
    -------
    ((cx, cy), sigma) or None
        The centre (px from the frame centre) and its 1-σ uncertainty (px).

    References
    ----------
    G. H. Golub, V. Pereyra, "Separable nonlinear least squares: the variable projection
    method and its applications", Inverse Problems 19(2), 2003.
    """
    from scipy.optimize import least_squares

    lm, X, Y, _, size = _log_blocks(lum, block)
    h, w = size
    hd = 0.5 * math.hypot(w, h)
    ok = np.isfinite(lm)
    if np.count_nonzero(ok) < 32:
        return None
    t, x, y = lm[ok], X[ok] / hd, Y[ok] / hd

    def resid(u: np.ndarray) -> np.ndarray:
        ex, ey = x - u[0], y - u[1]
        r2 = ex * ex + ey * ey
        A = np.stack([np.ones_like(x), x, y, ex * ex, ex * ey, ey * ey, r2 * r2, r2 ** 3, r2 ** 4], axis=1)
        return t - A @ np.linalg.lstsq(A, t, rcond=None)[0]

    # a coarse grid first: the fit is not convex far from the centre
    grid = np.linspace(-reach, reach, 7)
    s0 = (float(np.clip(start[0] / hd, -reach, reach)), float(np.clip(start[1] / hd, -reach, reach)))
    u0 = min([(float(a), float(b)) for a in grid for b in grid] + [s0],
             key=lambda u: float(np.sum(resid(np.array(u)) ** 2)))
    sol = least_squares(resid, np.array(u0), bounds=([-reach, -reach], [reach, reach]), x_scale=0.01)
    J = sol.jac
    s2 = 2.0 * sol.cost / max(t.size - 11, 1)
    try:
        cov = np.linalg.inv(J.T @ J) * s2
    except np.linalg.LinAlgError:
        return None
    sigma = float(math.sqrt(max(float(np.max(np.diag(cov))), 0.0)))
    if not math.isfinite(sigma) or sigma > SYMMETRIC_CENTRE_MAX_SIGMA:
        logger.debug("no symmetric centre: its uncertainty %.3g half-diagonals is too large", sigma)
        return None
    return (float(sol.x[0]) * hd, float(sol.x[1]) * hd), sigma * hd


def fit_gain_planes(log_gains: np.ndarray, x: np.ndarray, y: np.ndarray, width: int, height: int,
                    center: tuple[float, float], source: str) -> tuple[ColourField, np.ndarray]:
    """The colour field of per-plane gain maps (ln g per R, G, B at the points; the
    fall-off is 1/g): for records, profiles and outputs that hold a model, not a map.

    Returns
    -------
    (ColourField, residual_rms_ev)
        The fit and its residual per channel, EV.
    """
    cf, rms = fit_log_ratios(-np.asarray(log_gains).reshape(-1, 3), x, y, width, height, center,
                             free_center=True, source=source)
    return cf, rms / _LN2


# --------------------------------------------------------------------------- #
# pooling (profiles)
# --------------------------------------------------------------------------- #

#: Smallest σ of a coefficient pooled (a frame stating none, or zero, gets this).
POOL_SIGMA_FLOOR = 1e-4


@dataclass(frozen=True, eq=False)
class ColourPool:
    """Colour fields of several frames of one lens setting, pooled: the coefficients'
    inverse-variance weighted mean (information form, as a profile pools its θ), the
    centre's plain mean, in half-diagonals (any resolution of the frame).

    Attributes
    ----------
    info : ndarray (3, 3)
        Σ 1/σ² per coefficient.
    weighted : ndarray (3, 3)
        Σ a/σ².
    center_sum : (float, float)
        Σ centre / half-diagonal.
    n : int
        Frames pooled.
    source : str
    """

    info: Any
    weighted: Any
    center_sum: tuple[float, float] = (0.0, 0.0)
    n: int = 0
    source: str = ""

    def __post_init__(self) -> None:
        shape = (len(CHANNELS), len(POWERS))
        info = _floats("pool info", self.info, shape)
        if np.any(info < 0):
            raise ModelError("colour pool info must be >= 0")
        object.__setattr__(self, "info", info)
        object.__setattr__(self, "weighted", _floats("pool weighted", self.weighted, shape))
        c = _floats("pool center", self.center_sum, (2,))
        object.__setattr__(self, "center_sum", (float(c[0]), float(c[1])))
        if isinstance(self.n, bool) or not isinstance(self.n, (int, np.integer)) or self.n < 1:
            raise ModelError(f"colour pool n must be a positive integer, got {self.n!r}")
        object.__setattr__(self, "n", int(self.n))

    @classmethod
    def of(cls, cf: ColourField) -> ColourPool:
        """One frame's field as a pool."""
        s = np.maximum(cf.sigma if cf.sigma is not None else 0.0, POOL_SIGMA_FLOOR)
        s = np.broadcast_to(s, cf.coeffs.shape)
        info = 1.0 / (s * s)
        info[1] = 1.0 / POOL_SIGMA_FLOOR ** 2  # G is the reference: its zeros are exact
        hd = 0.5 * math.hypot(cf.width, cf.height)
        return cls(info, info * cf.coeffs, (cf.center[0] / hd, cf.center[1] / hd), 1, cf.source)

    def add(self, other: ColourPool) -> ColourPool:
        src = self.source if self.source == other.source else "pooled"
        return ColourPool(self.info + other.info, self.weighted + other.weighted,
                          (self.center_sum[0] + other.center_sum[0], self.center_sum[1] + other.center_sum[1]),
                          self.n + other.n, src)

    def field(self, width: int, height: int) -> ColourField:
        """The pooled field on a ``width``×``height`` frame."""
        hd = 0.5 * math.hypot(width, height)
        info = np.maximum(self.info, 1e-300)
        return ColourField(width, height, (self.center_sum[0] / self.n * hd, self.center_sum[1] / self.n * hd),
                           self.weighted / info, 1.0 / np.sqrt(info), self.source)

    @staticmethod
    def blend(parts: list[tuple[ColourPool | None, float]]) -> ColourPool | None:
        """Linear interpolation of pools (a profile between focal lengths and apertures):
        the weighted mean of their coefficients and centres; None unless all have one."""
        if not parts or any(p is None for p, _ in parts):
            return None
        shape = (len(CHANNELS), len(POWERS))
        mean = np.zeros(shape)
        var = np.zeros(shape)
        cen = np.zeros(2)
        for p, w in parts:
            info = np.maximum(p.info, 1e-300)
            mean += w * p.weighted / info
            var += w / info
            cen += w * np.asarray(p.center_sum) / p.n
        info = 1.0 / var
        n = sum(p.n for p, _ in parts)
        return ColourPool(info, info * mean, (float(cen[0] * n), float(cen[1] * n)), n, "interpolated")

    def to_json(self) -> dict[str, Any]:
        return {"info": self.info.tolist(), "weighted": self.weighted.tolist(),
                "center_sum": list(self.center_sum), "n": self.n, "source": self.source}

    @classmethod
    def from_json(cls, d: Any) -> ColourPool:
        if not isinstance(d, dict) or any(k not in d for k in ("info", "weighted", "n")):
            raise ModelError("a colour pool must be an object with info, weighted and n")
        return cls(d["info"], d["weighted"], tuple(d.get("center_sum", (0.0, 0.0))), d["n"], str(d.get("source", "")))
