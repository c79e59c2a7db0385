"""Interop with lensfun: import its ``pa`` vignetting, export vigproc profiles as lensfun XML.

vigproc describes vignetting with the generalised Kang-Weiss model
(:class:`vigproc.core.model.VignettingModel`)::

    phi = A * G,   A = 1 / (1 + (r/2)^2)^2,   G = 1 - sum_i alpha_i r^i,
    r^2 = (v - c)^T P (v - c)      (v, c in pixels from the frame centre)

lensfun (and through it darktable, RawTherapee, digiKam, Hugin) uses the
``pa`` polynomial in the radius rho normalised to the image half-diagonal::

    pa(rho) = 1 + k1 rho^2 + k2 rho^4 + k3 rho^6

(see :mod:`vigproc.stores.lensfun` for the verified normalisation and interpolation).
Neither model contains the other exactly, so both directions are least-squares
fits of log attenuation over the frame, every frame point weighted equally:

* :func:`kw_from_pa` / :func:`import_lensfun`: lensfun -> vigproc (centred,
  circular Kang-Weiss model).
* :func:`pa_from_model` / :func:`export_lensfun_xml`: vigproc -> lensfun.

Both report the misfit as an RMS over the frame in EV (stops); measured over
the 20 lenses of :func:`vigproc.stores.lensfun.diverse_lenses` it stays below 1e-3 EV
(see ``tests/test_lensfun_io.py``).

Database version
----------------
lensfunpy 1.18 bundles lensfun 0.3.4, whose parser accepts
``<lensdatabase version="0">`` and ``"1"`` and rejects ``"2"`` and above
("Database version is 2, but newest supported is only 1!", checked with
``lensfunpy.Database(xml=...)``).  :func:`export_lensfun_xml` therefore writes
version 1, the format of lensfun 0.3.x and of all files bundled with lensfunpy;
lensfun 0.3.95+ reads version 1 as well.

References
----------
.. [1] lensfun documentation, "Database file format" (``docs/manual/
   dbformat.txt``/ https://lensfun.github.io/manual/latest/dbformat.html) and
   "Vignetting models" (``lfVignettingModel``, ``LF_VIGNETTING_MODEL_PA``),
   https://lensfun.github.io/manual/latest/group__Lens.html
.. [2] lensfun ``libs/lensfun/database.cpp`` (XML parser, version check) and
   ``libs/lensfun/lens.cpp`` (``InterpolateVignetting``), 0.3.x.
.. [3] S. B. Kang and R. Weiss, "Can we calibrate a camera using an image of a
   flat, textureless Lambertian surface?", ECCV 2000; S. Lyu, ACM MM&Sec 2010.
"""

from __future__ import annotations

import functools
import logging
import math
import time
import unicodedata
from collections.abc import Iterable
from pathlib import Path
from typing import TYPE_CHECKING, NamedTuple

import numpy as np
from scipy.optimize import least_squares

from vigproc.errors import ModelError
from vigproc.stores.lensfun import LensfunLens, find_camera, interpolate_pa, load_lenses, pa_poly
from vigproc.core.model import N_ALPHA, FitQuality, VignettingModel
from vigproc.core.plausible import judge
from vigproc.stores.lensfun_match import calibration_for, corner_rho, covers, crop_of, frame_crop, match_lens
# the XML writer is its own module; imported here so callers find the whole interop in one place
from vigproc.stores.lensfun_xml import LENSFUN_DB_VERSION, export_lensfun_xml

if TYPE_CHECKING:
    from vigproc.io.exif import LensKey
    from vigproc.stores.profiles import Profile

__all__ = [
    "LENSFUN_DB_VERSION",
    "LensfunEntry",
    "PaFit",
    "export_lensfun_xml",
    "find_lens",
    "frame_crop_for",
    "import_lensfun",
    "lensfun_entries",
    "kw_from_pa",
    "lensfun_model",
    "pa_from_model",
    "pa_misfit_ev",
]

logger = logging.getLogger(__name__)

#: Samples along the long side of the frame for the least-squares grids.
GRID_SAMPLES = 64
#: Radii (0 .. corner) at which G > 0 and monotonicity are enforced.
CONSTRAINT_SAMPLES = 65
#: Ridge on alpha.  Without it the fit is degenerate: as the effective focal
#: length grows (P -> 0), G alone reproduces the pa polynomial exactly with
#: alpha_i ~ s^-i blowing up.  This weight costs < 1e-3 EV on real lenses
#: (measured: 1e-2 -> 2.0e-3 EV max, 1e-3 -> 6e-4, 1e-4 -> 2e-4 over
#: diverse_lenses(20)) and keeps alpha of order 0.1-0.3, the range vigproc's
#: estimators use (robust prior sigma_alpha = 0.3).
ALPHA_RIDGE = 1e-3
#: Floor kept on G (penalty) on [0, r_corner]; the model must not black out a corner.
G_FLOOR = 0.01
#: Weight of the constraint penalties relative to the data term.
PENALTY_WEIGHT = 10.0
#: Weight of the fall-off along the half-diagonals (to the corners) in :func:`pa_from_model`,
#: relative to the frame's cells.
DIAGONAL_WEIGHT = 1.0
#: Floor kept on the pa polynomial on [0, 1] when exporting.
PA_FLOOR = 1e-3
#: pa_from_model warns when the model is further from centred/circular than this.
MAX_CENTRE_OFFSET = 0.02
MAX_ELLIPTICITY = 0.05

_LN2 = math.log(2.0)
_K = np.arange(1, N_ALPHA + 1, dtype=np.float64)


class PaFit(NamedTuple):
    """Result of :func:`pa_from_model`: pa coefficients and the misfit over the frame."""

    k1: float
    k2: float
    k3: float
    rms_ev: float


class LensfunEntry(NamedTuple):
    """One calibration point for :func:`export_lensfun_xml` (a plain 10-tuple works too)."""

    maker: str
    model: str
    mount: str
    crop_factor: float
    focal: float
    aperture: float
    distance: float
    k1: float
    k2: float
    k3: float


# --------------------------------------------------------------------------
# sampling and evaluation


def _frame_samples(width: int, height: int, n: int = GRID_SAMPLES) -> tuple[np.ndarray, np.ndarray, float]:
    """Cell centres of an n x (n * short/long) partition of the frame.

    Returns flattened ``(dx, dy)`` in pixels from the frame centre ((W-1)/2,
    (H-1)/2) and the half-diagonal ``hypot((W-1)/2, (H-1)/2)`` that lensfun's
    rho (and :func:`vigproc.stores.lensfun.pa_field`) is normalised to.  Equal-area
    cells, so every frame point carries the same weight.
    """
    width, height = int(width), int(height)
    if width < 1 or height < 1 or width * height < 2:
        raise ModelError(f"frame of {width}x{height} px is too small for a vignetting field")
    long_side = max(width, height)
    nx = max(4, round(n * width / long_side))
    ny = max(4, round(n * height / long_side))
    # pixel j's centre sits at continuous position j + 0.5, the frame centre at W/2
    xs = (np.arange(nx) + 0.5) * (width / nx) - width / 2.0
    ys = (np.arange(ny) + 0.5) * (height / ny) - height / 2.0
    dx, dy = np.meshgrid(xs, ys)
    half_diag = math.hypot((width - 1) / 2.0, (height - 1) / 2.0)
    return dx.ravel(), dy.ravel(), half_diag


def _log_pa(rho: np.ndarray, k1: float, k2: float, k3: float) -> np.ndarray:
    pa = pa_poly(rho * rho, k1, k2, k3)
    if np.any(pa <= 0.0):
        raise ModelError(
            f"pa attenuation 1 + {k1:g} r^2 + {k2:g} r^4 + {k3:g} r^6 falls to {pa.min():.3g} inside the "
            "frame: the profile blacks out the corners (e.g. a lens that does not cover the sensor, "
            "or settings far outside the calibration), so it has no vignetting model to convert to"
        )
    return np.log(pa)


def pa_misfit_ev(
    model: VignettingModel, k1: float, k2: float, k3: float, *, corner_rho: float = 1.0,
    samples: int = GRID_SAMPLES,
) -> float:
    """RMS over the model's frame of log2(phi_model / pa), in EV.

    Parameters
    ----------
    model : VignettingModel
        Any vigproc model; evaluated on its own ``width`` x ``height`` frame.
    k1, k2, k3 : float
        pa coefficients.
    corner_rho : float, optional
        lensfun's rho at the frame corner: ``calibration crop / image crop``
        (1 for an image of the calibration crop factor).
    samples : int, optional
        Grid samples along the long side.

    Returns
    -------
    float
        RMS EV; 0 for identical fields.  Neither field is re-normalised (both
        are 1 at their centre), as in vigproc's benchmarks.
    """
    dx, dy, half_diag = _frame_samples(model.width, model.height, samples)
    rho = np.hypot(dx, dy) / half_diag * corner_rho
    diff = model.log_field_at(dx, dy) - _log_pa(rho, k1, k2, k3)
    return float(np.sqrt(np.mean(diff * diff)) / _LN2)


# --------------------------------------------------------------------------
# lensfun pa -> Kang-Weiss


class _KwProblem:
    """Residuals and Jacobian of the centred circular KW fit, in half-diagonal units.

    Unknowns ``x = (log s, alpha_1..alpha_7)`` with ``r = s u`` and u the distance
    from the centre in half-diagonals (1 at the corner), so s = sqrt(p) * half-diagonal
    (the frame's half-diagonal over the effective focal length) is of order one.
    """

    def __init__(
        self, u: np.ndarray, weight: np.ndarray, target: np.ndarray, uc: np.ndarray, allow: np.ndarray
    ) -> None:
        self.u, self.target, self.uc, self.allow = u, target, uc, allow
        self.w = np.sqrt(weight / weight.sum())  # data cost = mean square over the frame
        self.wc = PENALTY_WEIGHT / math.sqrt(uc.size)

    @staticmethod
    def _g(r: np.ndarray, alpha: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """G, G', G'' at r and the powers r^i (n x 7)."""
        rk = r[:, None] ** _K
        rk1 = r[:, None] ** (_K - 1)
        g = 1.0 - rk @ alpha
        g1 = -rk1 @ (_K * alpha)
        # r^(i-2) only for i >= 2 (the i = 1 term of G'' vanishes; avoid 0^-1)
        g2 = -(r[:, None] ** (_K[1:] - 2)) @ (_K[1:] * (_K[1:] - 1) * alpha[1:])
        return g, g1, g2, rk

    def residuals(self, x: np.ndarray) -> np.ndarray:
        return self._evaluate(x, jac=False)[0]

    def jacobian(self, x: np.ndarray) -> np.ndarray:
        return self._evaluate(x, jac=True)[1]

    def _evaluate(self, x: np.ndarray, jac: bool) -> tuple[np.ndarray, np.ndarray | None]:
        s, alpha = math.exp(x[0]), x[1:]
        # data: w (log A + log G - target)
        r = s * self.u
        g, g1, _, rk = self._g(r, alpha)
        gs = np.maximum(g, 1e-12)
        a_slope = -r / (1.0 + 0.25 * r * r)  # d log A / dr
        res_data = self.w * (-2.0 * np.log1p(0.25 * r * r) + np.log(gs) - self.target)
        # constraints on [0, r_corner]: G >= floor, d log phi / du <= max(0, target slope)
        rc = s * self.uc
        gc, gc1, gc2, rck = self._g(rc, alpha)
        gcs = np.maximum(gc, 1e-12)
        h = -rc / (1.0 + 0.25 * rc * rc) + gc1 / gcs  # d log phi / dr
        slope = s * h
        floor_act = gc < G_FLOOR
        mono_act = slope > self.allow
        res = np.concatenate([
            res_data,
            ALPHA_RIDGE * alpha,
            self.wc * np.where(floor_act, G_FLOOR - gc, 0.0),
            self.wc * np.where(mono_act, slope - self.allow, 0.0),
        ])
        if not jac:
            return res, None
        n, nc = self.u.size, self.uc.size
        J = np.zeros((res.size, 1 + N_ALPHA))
        J[:n, 0] = self.w * r * (a_slope + g1 / gs)
        J[:n, 1:] = -self.w[:, None] * rk / gs[:, None]
        J[n : n + N_ALPHA, 1:] = ALPHA_RIDGE * np.eye(N_ALPHA)
        o = n + N_ALPHA
        J[o : o + nc, 0] = np.where(floor_act, -self.wc * gc1 * rc, 0.0)
        J[o : o + nc, 1:] = np.where(floor_act[:, None], self.wc * rck, 0.0)
        o += nc
        dh_dr = -(1.0 - 0.25 * rc * rc) / (1.0 + 0.25 * rc * rc) ** 2 + (gc2 * gcs - gc1 * gc1) / gcs**2
        rck1 = rc[:, None] ** (_K - 1)
        dslope_da = s * (-(_K * rck1) * gcs[:, None] + gc1[:, None] * rck) / gcs[:, None] ** 2
        J[o : o + nc, 0] = np.where(mono_act, self.wc * s * (h + rc * dh_dr), 0.0)
        J[o : o + nc, 1:] = np.where(mono_act[:, None], self.wc * dslope_da, 0.0)
        return res, J

    def linear_start(self, s: float) -> np.ndarray:
        """alpha for a fixed s: ridge least squares of G against pa / A, linearised in log G."""
        r = s * self.u
        g_target = np.exp(self.target) * (1.0 + 0.25 * r * r) ** 2
        # log G ~ log Gt + (G - Gt)/Gt: weight rows by 1/Gt
        rows = self.w[:, None] * (r[:, None] ** _K) / g_target[:, None]
        rhs = self.w * (1.0 - g_target) / g_target
        a = np.vstack([rows, ALPHA_RIDGE * np.eye(N_ALPHA)])
        b = np.concatenate([rhs, np.zeros(N_ALPHA)])
        return np.linalg.lstsq(a, b, rcond=None)[0]


def kw_from_pa(
    k1: float, k2: float, k3: float, width: int, height: int, *, corner_rho: float = 1.0,
    method: str = "lensfun",
) -> VignettingModel:
    """The centred, circular Kang-Weiss model closest to a lensfun pa field.

    Least squares on log phi over a grid of equal-area cells covering the
    ``width`` x ``height`` frame (64 along the long side), with unknowns the
    effective focal length (p1 = p3 = p, p2 = 0, c = 0) and alpha_1..alpha_7.
    Penalties keep G >= 0.01 and the fall-off monotone (d log phi / dr <= 0,
    unless the pa field itself rises there) for r in [0, r_corner]; a tiny ridge
    on alpha removes the degeneracy between the A term and G (see
    :data:`ALPHA_RIDGE`).

    Parameters
    ----------
    k1, k2, k3 : float
        pa coefficients: attenuation ``1 + k1 rho^2 + k2 rho^4 + k3 rho^6``.
    width, height : int
        Frame size in pixels.
    corner_rho : float, optional
        lensfun's rho at the frame corner, ``calibration crop factor / image
        crop factor``; 1 (default) for an image of the calibration crop factor.
    method : str, optional
        ``method`` label of the returned model.

    Returns
    -------
    VignettingModel
        ``quality.field_sigma_ev`` and ``quality.objective`` hold the fit's RMS
        misfit over the frame in EV (see also :func:`pa_misfit_ev`),
        ``quality.field_ev_rms`` the RMS of log2 phi.

    Raises
    ------
    ModelError
        If the pa field is not positive over the frame, an argument is not
        finite/positive, or no model with G > 0 on the frame fits.

    Notes
    -----
    Measured (600 x 400 frames, vigproc's field kernel at every pixel against
    :func:`vigproc.stores.lensfun.pa_field`): over the 20 lenses of
    :func:`vigproc.stores.lensfun.diverse_lenses` RMS misfit max 7.1e-4 EV, median
    2.8e-4 EV; over 1603 random calibration entries of the bundled database
    (450 x 300, fit grid) median 1.0e-4, 99th percentile 8.6e-4, max 5.5e-3 EV
    (a non-monotone entry, k1 = +2.17); 13 entries whose pa polynomial reaches
    zero inside the frame (compact cameras, fisheyes) are refused.

    The fit is a pure function of its arguments, so its results are kept (the
    last 256; a model is immutable): a lens's model is fitted once per frame
    size, not once per frame checked. ``quality.seconds`` is the first fit's time.

    References
    ----------
    .. [1] lensfun, "Vignetting models", ``LF_VIGNETTING_MODEL_PA``,
       https://lensfun.github.io/manual/latest/group__Lens.html
    .. [2] S. Lyu, ACM MM&Sec 2010, Eq. (2) (generalised Kang-Weiss model).
    """
    return _kw_from_pa(float(k1), float(k2), float(k3), width, height, float(corner_rho), method)


@functools.lru_cache(maxsize=256, typed=True)
def _kw_from_pa(k1: float, k2: float, k3: float, width: int, height: int, corner_rho: float,
                method: str) -> VignettingModel:
    """:func:`kw_from_pa`'s fit, cached by its arguments.

    Parameters
    ----------
    k1, k2, k3, width, height, corner_rho, method
        As :func:`kw_from_pa`'s (the floats already converted).

    Returns
    -------
    VignettingModel
        As :func:`kw_from_pa`.
    """
    t0 = time.perf_counter()
    ks = tuple(float(k) for k in (k1, k2, k3))
    if not all(math.isfinite(k) for k in ks):
        raise ModelError(f"pa coefficients must be finite, got k1={k1}, k2={k2}, k3={k3}")
    corner_rho = float(corner_rho)
    if not (math.isfinite(corner_rho) and corner_rho > 0):
        raise ModelError(f"corner_rho must be positive and finite, got {corner_rho!r}")
    dx, dy, half_diag = _frame_samples(width, height)
    # the field is radial: one residual per distinct radius, weighted by its count
    # (exact, and ~4x fewer rows by the grid's quadrant symmetry)
    u, counts = np.unique(np.round(np.hypot(dx, dy) / half_diag, 12), return_counts=True)
    target = _log_pa(u * corner_rho, *ks)
    uc = np.linspace(0.0, 1.0, CONSTRAINT_SAMPLES)
    _log_pa(uc * corner_rho, *ks)  # the corner itself must be lit too
    # allowed slope: the target's own rise (a non-monotone pa field is followed), else 0
    rho_c = uc * corner_rho
    pa_c = pa_poly(rho_c * rho_c, *ks)
    dpa = corner_rho * (2 * ks[0] * rho_c + 4 * ks[1] * rho_c**3 + 6 * ks[2] * rho_c**5)
    allow = np.maximum(dpa / pa_c, 0.0) + 1e-9
    prob = _KwProblem(u, counts.astype(np.float64), target, uc, allow)

    if not np.any(np.abs(target) > 1e-12):
        logger.debug("pa field is flat: identity model")
        return VignettingModel.identity(int(width), int(height), method=method, quality=FitQuality())

    # coarse scan over s (half-diagonal / effective focal length), linear in alpha
    starts = []
    for s in np.geomspace(0.25, 4.0, 13):
        x0 = np.concatenate([[math.log(s)], prob.linear_start(s)])
        starts.append((float(np.sum(prob.residuals(x0) ** 2)), x0))
    starts.sort(key=lambda c: c[0])
    lo, hi = math.log(0.02), math.log(50.0)
    best = None
    for _, x0 in starts[:2]:
        x0[0] = min(max(x0[0], lo + 1e-9), hi - 1e-9)
        sol = least_squares(
            prob.residuals, x0, jac=prob.jacobian, method="trf",
            bounds=([lo] + [-np.inf] * N_ALPHA, [hi] + [np.inf] * N_ALPHA),
            x_scale="jac", xtol=1e-12, ftol=1e-12, gtol=1e-12, max_nfev=500,
        )
        if best is None or sol.cost < best.cost:
            best = sol
    assert best is not None
    s, alpha = math.exp(best.x[0]), best.x[1:]

    # constraint check on the result (the penalties are soft)
    gc, gc1, _, _ = _KwProblem._g(s * uc, alpha)
    if gc.min() <= 0.0:
        raise ModelError(f"no Kang-Weiss model with G > 0 on the frame matches pa k=({k1:g}, {k2:g}, {k3:g})")
    slope = s * (-(s * uc) / (1.0 + 0.25 * (s * uc) ** 2) + gc1 / gc)
    if np.any(slope > allow + 1e-3):
        logger.warning("Kang-Weiss fit of pa k=(%g, %g, %g) is not monotone (max slope %.3g)", *ks, slope.max())

    p = s * s / half_diag**2
    n = u.size
    misfit = float(np.sqrt(np.sum(best.fun[:n] ** 2)) / _LN2)
    ev_rms = float(np.sqrt(np.sum(prob.w**2 * target * target)) / _LN2)
    quality = FitQuality(
        confidence=1.0, field_ev_rms=ev_rms, field_sigma_ev=misfit,
        snr=ev_rms / misfit if misfit > 0 else math.inf, objective=misfit,
        iterations=int(best.nfev), seconds=time.perf_counter() - t0,
    )
    logger.debug("kw_from_pa k=(%g, %g, %g) %dx%d: s=%.4g, misfit %.2e EV, %d evaluations",
                 *ks, width, height, s, misfit, best.nfev)
    return VignettingModel(int(width), int(height), center=(0.0, 0.0), p=(p, 0.0, p), alpha=tuple(alpha),
                           method=method, quality=quality)


# --------------------------------------------------------------------------
# finding lenses and importing


def _norm(text: str) -> str:
    """Case- and width-insensitive form: NFKC, casefold, whitespace collapsed."""
    return " ".join(unicodedata.normalize("NFKC", text).casefold().split())


def _describe(lens: LensfunLens) -> str:
    return f"{lens.maker} / {lens.model} (crop {lens.crop_factor:g})"


def _checked_crop(crop_factor: float | None) -> float | None:
    """A caller's crop factor as a float (None kept); a :class:`ModelError` for one that is
    not positive and finite (it divides lensfun's ρ and is the log of a ratio)."""
    if crop_factor is None:
        return None
    crop = float(crop_factor)
    if not (math.isfinite(crop) and crop > 0):
        raise ModelError(f"crop factor must be positive and finite, got {crop_factor!r}")
    return crop


def _pick_calibration(matches: list[LensfunLens], crop_factor: float | None) -> LensfunLens:
    """One lens of a single (maker, model) name, calibrated on possibly several sensors."""
    crop_factor = _checked_crop(crop_factor)
    if len(matches) == 1:
        return matches[0]
    if crop_factor is None:
        crops = ", ".join(f"{m.crop_factor:g}" for m in matches)
        raise ModelError(
            f"lens {matches[0].maker} / {matches[0].model} is calibrated for several sensors "
            f"(crop factors {crops}); pass the image's crop factor to choose"
        )
    return calibration_for(matches, crop_factor)  # as --profile lensfun picks: one that covers the frame


def find_lens(
    maker: str | None, model: str, *, crop_factor: float | None = None,
    db_paths: Iterable[str | Path] | None = None,
) -> LensfunLens | None:
    """Find a lens with pa vignetting data in the lensfun database.

    Matching is on normalised strings (Unicode NFKC, case-folded, whitespace
    collapsed): first an exact match of maker and model (the model may also be
    given as ``"<maker> <model>"``), then a unique substring match of the model
    (the maker, if given, must match one way or the other as a substring).

    Parameters
    ----------
    maker : str or None
        Lens maker as in lensfun (``"Canon"``); None or ``""`` to match on the
        model alone.
    model : str
        Lens model, whole or a distinctive part.
    crop_factor : float, optional
        Crop factor of the image; chooses among calibrations of the same lens on
        several sensors (:func:`~vigproc.stores.lensfun_match.calibration_for`: the
        nearest that covers the image).
    db_paths : iterable of str or Path, optional
        Passed to :func:`vigproc.stores.lensfun.load_lenses` (default: lensfunpy's
        bundled database).

    Returns
    -------
    LensfunLens or None
        None if nothing matches.

    Raises
    ------
    ModelError
        If the substring match is ambiguous (the message lists the
        candidates), the lens has calibrations for several sensors and no
        ``crop_factor`` is given, or the query is empty.
    """
    if not isinstance(model, str) or not _norm(model):
        raise ModelError("lens model must be a non-empty string")
    q_model = _norm(model)
    q_maker = _norm(maker) if maker else ""
    lenses = load_lenses(db_paths)

    def maker_ok(lens: LensfunLens, exact: bool) -> bool:
        if not q_maker:
            return True
        m = _norm(lens.maker)
        return m == q_maker if exact else (q_maker in m or m in q_maker)

    kind = "exact"
    matches = [
        lens for lens in lenses
        if maker_ok(lens, True) and q_model in (_norm(lens.model), _norm(f"{lens.maker} {lens.model}"))
    ]
    if not matches:
        kind = "substring"  # "maker model" contains the model, so one test covers both
        matches = [
            lens for lens in lenses
            if maker_ok(lens, False) and q_model in _norm(f"{lens.maker} {lens.model}")
        ]
    if not matches:
        logger.debug("no lensfun lens matches maker=%r model=%r", maker, model)
        return None
    names = sorted({(lens.maker, lens.model) for lens in matches})
    if len(names) > 1:
        shown = "; ".join(f"{mk} / {md}" for mk, md in names[:12])
        more = f" and {len(names) - 12} more" if len(names) > 12 else ""
        raise ModelError(f"lens {model!r} is ambiguous in the lensfun database: {shown}{more}")
    chosen = _pick_calibration([lens for lens in matches if (lens.maker, lens.model) == names[0]], crop_factor)
    logger.debug("lensfun lens (%s match): %s", kind, _describe(chosen))
    return chosen


def import_lensfun(
    maker_or_lens: str | LensfunLens | None,
    model: str | None,
    focal: float,
    aperture: float,
    distance: float = 1000.0,
    *,
    width: int,
    height: int,
    crop_factor: float | None = None,
    db_paths: Iterable[str | Path] | None = None,
) -> VignettingModel:
    """lensfun's calibrated vignetting for a lens and shooting settings, as a vigproc model.

    Finds the lens (:func:`find_lens`), interpolates its pa coefficients as
    lensfun does (:func:`vigproc.stores.lensfun.interpolate_pa`) and converts them to
    a centred circular Kang-Weiss model (:func:`kw_from_pa`).

    Parameters
    ----------
    maker_or_lens : str, LensfunLens or None
        Lens maker (with ``model``), or a :class:`LensfunLens` (then ``model``
        is ignored), or None to search by model alone.
    model : str or None
        Lens model (see :func:`find_lens`).
    focal : float
        Focal length in mm.
    aperture : float
        f-number.
    distance : float, optional
        Focus distance in metres, default 1000 ("infinity" in lensfun).
    width, height : int
        Size of the frame the model is for.
    crop_factor : float, optional
        Crop factor of the image.  Default: the calibration's, i.e. the frame
        is the full calibration frame (rho = 1 at its corner).  Otherwise the
        corner lies at rho = calibration crop / image crop, as in lensfun.
    db_paths : iterable of str or Path, optional
        lensfun XML files or folders (default: lensfunpy's bundled database).

    Returns
    -------
    VignettingModel
        ``method="lensfun"``; ``quality.objective`` is the conversion misfit in EV.

    Raises
    ------
    ModelError
        Unknown or ambiguous lens, settings too far from the calibration for
        lensfun-style interpolation, or an unusable profile.

    References
    ----------
    .. [1] lensfun ``lfLens::InterpolateVignetting``,
       https://lensfun.github.io/manual/latest/group__Lens.html
    """
    if isinstance(maker_or_lens, LensfunLens):
        lens = maker_or_lens
    else:
        if not model and isinstance(maker_or_lens, str):
            maker_or_lens, model = None, maker_or_lens  # a single string: search by model
        if not model:
            raise ModelError("import_lensfun needs a lens model")
        found = find_lens(maker_or_lens, model, crop_factor=crop_factor, db_paths=db_paths)
        if found is None:
            who = f"{maker_or_lens} / {model}" if maker_or_lens else model
            raise ModelError(
                f"lens {who!r} has no pa vignetting calibration in the lensfun database "
                "(unknown lens, or a lens lensfun knows only for distortion/TCA)"
            )
        lens = found
    corner_rho = 1.0
    crop = _checked_crop(crop_factor)
    if crop is not None:
        corner_rho = lens.crop_factor / crop
        if not covers(lens.crop_factor, crop):
            logger.warning("%s covers a sensor of crop factor %g, not the frame's %g: its field is extrapolated "
                           "to rho = %.2f at the frame's corner (lensfun's rule)", _describe(lens), lens.crop_factor,
                           crop, corner_rho)
    f_lo, f_hi = lens.focal_range
    if not f_lo <= float(focal) <= f_hi:
        logger.info("%s: %g mm is outside the calibrated %g-%g mm; lensfun-style extrapolation",
                    _describe(lens), focal, f_lo, f_hi)
    pa = interpolate_pa(lens, focal, aperture, distance)  # raises ModelError when out of range
    logger.debug("%s at %g mm f/%g %g m: pa k=(%g, %g, %g)", _describe(lens), focal, aperture, distance,
                 pa.k1, pa.k2, pa.k3)
    return kw_from_pa(pa.k1, pa.k2, pa.k3, width, height, corner_rho=corner_rho, method="lensfun")


def lensfun_model(lens_key: LensKey | None, width: int, height: int) -> VignettingModel:
    """The lensfun calibration of a frame's lens at its focal length, aperture and focus
    distance (infinity when the EXIF gives none), for a ``width`` x ``height`` frame, its
    corner at ρ = calibration crop / frame crop (:func:`~vigproc.stores.lensfun_match.frame_crop`;
    lensfun's rule for another sensor size) where the frame is a smaller sensor's, else at the
    calibration's own corner (:func:`frame_crop_for`: a sensor within rounding of the
    calibration's, an unknown one, or a larger one, logged: the calibration is not extrapolated).

    The lens is found by :func:`vigproc.stores.lensfun_match.match_lens` (names compared
    by their tokens, the match verified against the shot's focal length); a lens whose
    EXIF identity has a problem (``LensKey.lens_problem``) is never looked up.

    Raises
    ------
    ModelError
        The EXIF lacks the lens, focal length or f-number, its lens identity has a
        problem, or lensfun has no usable calibration (:func:`import_lensfun`); the
        message says which.
    """
    if lens_key is None or lens_key.lens is None or lens_key.focal_mm is None or lens_key.fnumber is None:
        raise ModelError("lensfun needs the lens, focal length and f-number from EXIF")
    found = match_lens(lens_key)
    if found.lens is None:
        raise ModelError(f"no lensfun calibration for this lens: {found.reason}")
    distance = lens_key.focus_distance_m if lens_key.focus_distance_m not in (None, float("inf")) else 1000.0
    return import_lensfun(found.lens, None, lens_key.focal_mm, lens_key.fnumber, distance,
                          width=width, height=height, crop_factor=frame_crop_for(found.lens, frame_crop(lens_key)))


def frame_crop_for(lens: LensfunLens, crop: float | None) -> float | None:
    """The crop factor :func:`import_lensfun` is given for a frame of crop factor ``crop``
    behind ``lens``'s calibration: ``crop`` where the frame's corner lies inside the
    calibrated field (:func:`~vigproc.stores.lensfun_match.corner_rho`: a DX frame behind a
    full-frame lens, its inner 0.66), else None, the calibration's own frame (a frame of
    unknown size or of the calibration's sensor; a frame larger than the calibrated field,
    which is logged: its corners are not extrapolated)."""
    if crop is not None and not covers(lens.crop_factor, crop):
        logger.warning("%s covers a sensor of crop factor %g, not the frame's %g (its corner at rho = %.2f): "
                       "lensfun's calibration is not extrapolated, its whole field is put over the frame",
                       _describe(lens), lens.crop_factor, crop, lens.crop_factor / crop)
    return crop if corner_rho(lens.crop_factor, crop) != 1.0 else None


# --------------------------------------------------------------------------
# Kang-Weiss -> lensfun pa


def pa_from_model(model: VignettingModel) -> PaFit:
    """pa coefficients closest to a vigproc model, for export to lensfun.

    Least squares of ``log(1 + k1 rho^2 + k2 rho^4 + k3 rho^6)`` against
    log phi of the model at equal-area cells over the model's frame (rho =
    distance from the frame centre / half-diagonal) and, with the same weight in all,
    along its half-diagonals out to the corners, uniformly in rho (the mean of the
    four): the corners, where hosts' fall-off is compared, are fitted too.  For a centred circular
    model this fits its fall-off along r; for an off-centre or elliptical one
    the same fit is the best *radial* approximation (the radially averaged
    fall-off, area-weighted), and ``rms_ev`` shows how much is lost.

    Parameters
    ----------
    model : VignettingModel
        Model of the calibration frame (the frame lensfun's rho = 1 refers to).

    Returns
    -------
    PaFit
        ``(k1, k2, k3, rms_ev)``: rms_ev is the RMS over the frame of
        log2(pa / phi) in EV (callers should warn when it is large).

    Raises
    ------
    ModelError
        If the model blacks out part of the frame (G <= 0).

    Notes
    -----
    A warning is logged when the centre is more than 2 % of the half-diagonal
    off the frame centre or the ellipticity (|p1 - p3| + 2|p2|) / (p1 + p3)
    exceeds 0.05: lensfun's pa model is centred and circular.

    References
    ----------
    .. [1] lensfun, ``LF_VIGNETTING_MODEL_PA``,
       https://lensfun.github.io/manual/latest/group__Lens.html
    """
    dx, dy, half_diag = _frame_samples(model.width, model.height)
    offset = math.hypot(*model.center) / half_diag
    p1, p2, p3 = model.p
    ellipticity = (abs(p1 - p3) + 2 * abs(p2)) / (p1 + p3) if p1 + p3 > 0 else 0.0
    if offset > MAX_CENTRE_OFFSET or ellipticity > MAX_ELLIPTICITY:
        logger.warning(
            "model centre is %.1f %% of the half-diagonal off-centre, ellipticity %.3f: lensfun's pa "
            "model is centred and circular, exporting the radially averaged fall-off", 100 * offset, ellipticity,
        )
    frame_target = model.log_field_at(dx, dy)
    if not np.any(np.abs(frame_target) > 1e-12):
        return PaFit(0.0, 0.0, 0.0, 0.0)
    frame_rho = np.hypot(dx, dy) / half_diag
    # ... and the fall-off along the half-diagonals out to the corners (the mean of the
    # four), uniform in rho: the frame's cells alone leave the corners, where a host's
    # fall-off is strongest and is compared, a few cells (0.036 EV off at the corner of a
    # 1.7 EV lens; 0.015 with these rows, the frame's RMS 0.0015 -> 0.0021 EV)
    u = np.linspace(0.0, 1.0, CONSTRAINT_SAMPLES)
    cw, ch = (model.width - 1) / 2.0, (model.height - 1) / 2.0
    diag_target = np.mean([model.log_field_at(sx * cw * u, sy * ch * u) for sx in (-1, 1) for sy in (-1, 1)], axis=0)
    rho = np.concatenate([frame_rho, u])
    target = np.concatenate([frame_target, diag_target])
    r2 = rho * rho
    basis = np.stack([r2, r2**2, r2**3], axis=1)  # d pa / dk
    rho_c = np.linspace(0.0, 1.0, CONSTRAINT_SAMPLES)
    basis_c = np.stack([rho_c**2, rho_c**4, rho_c**6], axis=1)
    # the frame and the diagonals weigh the same in all
    w = np.concatenate([np.full(frame_rho.size, 1.0 / math.sqrt(frame_rho.size)),
                        np.full(u.size, DIAGONAL_WEIGHT / math.sqrt(u.size))])
    wc = PENALTY_WEIGHT / math.sqrt(rho_c.size)

    # linear start: pa ~ phi, rows weighted 1/phi (first-order log residual)
    phi = np.exp(target)
    k0 = np.linalg.lstsq(basis / phi[:, None], (phi - 1.0) / phi, rcond=None)[0]

    def evaluate(k: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        pa = 1.0 + basis @ k
        pas = np.maximum(pa, 1e-12)
        pa_c = 1.0 + basis_c @ k
        act = pa_c < PA_FLOOR
        res = np.concatenate([w * (np.log(pas) - target), wc * np.where(act, PA_FLOOR - pa_c, 0.0)])
        jac = np.vstack([w[:, None] * basis / pas[:, None], np.where(act[:, None], -wc * basis_c, 0.0)])
        return res, jac

    sol = least_squares(lambda k: evaluate(k)[0], k0, jac=lambda k: evaluate(k)[1], method="lm",
                        xtol=1e-14, ftol=1e-14, gtol=1e-14, max_nfev=1000)
    k1, k2, k3 = (float(v) for v in sol.x)
    if (1.0 + basis_c @ sol.x).min() <= 0.0:
        raise ModelError("no pa polynomial positive on the frame approximates this model")
    n = frame_rho.size  # the misfit reported is over the frame
    rms = float(np.sqrt(np.mean((np.log(1.0 + basis[:n] @ sol.x) - frame_target) ** 2)) / _LN2)
    logger.debug("pa_from_model: k=(%g, %g, %g), misfit %.2e EV", k1, k2, k3, rms)
    return PaFit(k1, k2, k3, rms)


# --------------------------------------------------------------------------
# profiles -> calibration entries


def _profile_names(profile: Profile) -> tuple[tuple[str | None, ...], tuple[str | None, ...]]:
    """(make, model, lens) of a profile from its (casefolded) lens id, and (make, model,
    lens, lens make) as its frames' EXIF spelt them (None where unknown)."""
    from vigproc.io.exif import unescape_key_part

    parts = tuple(([unescape_key_part(v) for v in profile.key.lens_id.split("|")] + [None] * 3)[:3])
    spelt = profile.shots.names if profile.shots is not None else (None,) * 4
    return parts, tuple(spelt)


def colour_notes(profiles: Iterable[Profile]) -> list[str]:
    """One sentence per profile with a colour field or a measured grid field: lensfun's
    vignetting model is one radial field for all channels, so only the profile's
    luminance part (its Kang-Weiss fit) is exported."""
    out = []
    for p in profiles:
        colour, grid = getattr(p, "colour", None), getattr(p, "grid", None)
        if colour is None and grid is None:
            continue
        what = " and ".join(w for w in (
            f"its colour shading (per-channel field, {colour.n} frames)" if colour is not None else "",
            f"its measured grid field ({grid.n} flat frames, per channel)" if grid is not None else "") if w)
        out.append(f"{p.key}: {what} cannot be expressed in lensfun's vignetting model: only the luminance "
                   "fall-off (the profile's Kang-Weiss fit) is exported")
    return out


def warn_colour(profiles: Iterable[Profile]) -> list[str]:
    """:func:`colour_notes`, each logged as a warning; returns them."""
    notes = colour_notes(profiles)
    for n in notes:
        logger.warning("%s", n)
    return notes


def lensfun_entries(profiles: Iterable[Profile], *, crop_factor: float | None = None,
                    mount: str | None = None) -> tuple[list[LensfunEntry], list[str]]:
    """The lensfun calibration entries of learned profiles, for :func:`export_lensfun_xml`.

    Each profile is written for the camera its frames were shot with, so that a host
    applies it as vigproc does:

    * crop factor and mount: the lensfun database's entry for the camera (by its maker
      and model), else the crop factor the frames' EXIF gave (35-mm focal length over
      focal length) and ``mount``, else ``crop_factor`` (then "Generic"); the EXIF's crop
      factor too where it is more than :data:`~vigproc.stores.lensfun_match.CROP_MODE` off
      the camera's (frames of a crop mode: :func:`~vigproc.stores.lensfun_match.crop_of`);
    * lens maker and model as EXIF spelt them (a compact's lens under its camera's name);
    * the focal length the frames were shot at (their median), not the profile's bin;
    * pa coefficients fitted with rho = 1 at the frame's corner: lensfun's rho is 1 at
      the corner of an image of the calibration's crop factor (:mod:`vigproc.stores.lensfun`),
      which is the crop factor written;
    * of a profile with a colour field, the luminance part only (a warning is logged:
      lensfun's vignetting model has no per-channel terms);
    * no profile whose field is brighter at a corner than at its centre
      (:func:`vigproc.core.plausible.judge`'s rule for a calibration): a host would
      darken that frame's corners.

    Parameters
    ----------
    profiles : iterable of Profile
        Only learned ones with a focal and an aperture bin are written.
    crop_factor : float, optional
        For cameras neither lensfun nor the frames' EXIF give a crop factor for.
    mount : str, optional
        For cameras lensfun does not know (default "Generic").

    Returns
    -------
    (entries, skipped)
        The entries, and why each learned profile left out was.
    """
    entries: list[LensfunEntry] = []
    skipped: list[str] = []
    for p in profiles:
        if p.provenance != "learned" or p.key.focal_bin == "any" or p.key.aperture_bin == "any":
            continue
        ids, spelt = _profile_names(p)
        make, model, lens = (b or a for a, b in zip(ids, spelt[:3]))
        camera = find_camera(make, model)
        if lens is None and camera is not None and not camera.fixed_lens:
            skipped.append(f"{p.key}: its frames name no lens, and a {camera.maker} {camera.model} takes "
                           "interchangeable lenses")
            continue
        shots_crop = p.shots.crop_factor if p.shots is not None else None
        # the frames' sensor: the camera's, unless the frames are a crop of it (a DX crop mode
        # on an FX body), whose corner a host (darktable: the EXIF's crop) puts at ρ = 1
        crop = crop_of(camera.crop_factor if camera is not None else None, shots_crop) or crop_factor
        if crop is None:
            skipped.append(f"{p.key}: the camera's crop factor is unknown (lensfun does not know the camera "
                           "and the frames' EXIF gave no 35-mm focal length): pass --crop-factor")
            continue
        # a frame of the profile's own aspect: lensfun's pa radius is 1 at the corner of any
        # frame of the written crop factor, so the coefficients do not depend on which one
        a = p.key.aspect_ratio
        size = (3000, max(1, round(3000 / a))) if a >= 1 else (max(1, round(3000 * a)), 3000)
        field = p.model(*size)
        # the rule every correction path applies (a host would darken the frame's corners);
        # correct --profile refuses such a profile too, but a host reading the file does not
        refusal = judge(field, calibrated=True)
        if refusal is not None:
            skipped.append(f"{p.key}: {refusal.reason}")
            continue
        try:
            k1, k2, k3, rms = pa_from_model(field)
        except ModelError as exc:  # one profile lensfun's model cannot hold does not stop the others
            skipped.append(f"{p.key}: {exc}")
            continue
        focal = p.shots.focal_median if p.shots is not None else None
        entries.append(LensfunEntry(
            # the lens's maker as EXIF spelt it, else the camera's (lensfun's spelling before a casefolded id)
            maker=spelt[3] or spelt[0] or (camera.maker if camera is not None else None) or make or "unknown",
            model=next(v for v in (lens, model, make, p.key.lens_id) if v),
            mount=camera.mount if camera is not None else mount or "Generic",
            crop_factor=float(crop), focal=float(focal if focal is not None else p.key.focal_bin[2:-2]),
            aperture=float(p.key.aperture_bin[2:]), distance=1000.0, k1=k1, k2=k2, k3=k3))
        warn_colour([p])  # the luminance part only: lensfun has no per-channel vignetting
        logger.info("%s -> lensfun %s / %s, crop %.3f (%s), %g mm, pa misfit %.1e EV", p.key, entries[-1].maker,
                    entries[-1].model, crop, "lensfun's camera" if camera is not None and crop == camera.crop_factor
                    else "EXIF" if shots_crop else "--crop-factor", entries[-1].focal, rms)
    return entries, skipped
