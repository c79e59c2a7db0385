"""The generalized Kang-Weiss vignetting model and its parameters.

References
----------
S. Lyu, "Estimating Vignetting Function from a Single Image for Image
Authentication", ACM MM&Sec 2010, Eq. (2).
S. B. Kang and R. Weiss, "Can we calibrate a camera using an image of a flat,
textureless Lambertian surface?", ECCV 2000.
"""

from __future__ import annotations

import json
import math
import numbers
from dataclasses import dataclass, field, fields, replace
from typing import Any

import numpy as np

from vigproc.core.colour import ColourField
from vigproc.errors import ModelError

#: Degree of the geometric polynomial G (Lyu 2010 fixes k = 7).
N_ALPHA = 7
#: Order of the parameter vector used for covariances: (cx, cy, p1, p2, p3, α1..α7).
PARAM_NAMES = ("cx", "cy", "p1", "p2", "p3") + tuple(f"alpha{i}" for i in range(1, N_ALPHA + 1))
SCHEMA = "vigproc.model/1"
#: Schema of a model with a colour field (:mod:`vigproc.core.colour`); a colourless
#: model is still written as :data:`SCHEMA`, which every vigproc reads.
SCHEMA_COLOUR = "vigproc.model/2"
SCHEMAS = (SCHEMA, SCHEMA_COLOUR)


def _show(v: Any) -> str:
    """``repr(v)`` cut short, for error messages about arbitrary input."""
    try:
        r = repr(v)
    except ValueError:  # an int of more digits than Python will print
        return f"a {type(v).__name__} too large to show"
    return r if len(r) <= 60 else r[:57] + "..."


def _is_real(v: Any) -> bool:
    # bool is an int to Python, but true/false is never a meaningful number here
    return isinstance(v, numbers.Real) and not isinstance(v, (bool, np.bool_))


def _real(name: str, v: Any) -> float:
    """``v`` as a float; ModelError unless it is a real number (NaN/Inf allowed)."""
    if not _is_real(v):
        raise ModelError(f"{name} must be a number, got {_show(v)}")
    try:
        return float(v)
    except OverflowError:  # an int beyond float range, e.g. 10**400
        raise ModelError(f"{name} is out of range, got {_show(v)}") from None


def _reals(name: str, v: Any, n: int) -> tuple[float, ...]:
    """``v`` as ``n`` finite floats; ModelError unless a list/tuple of ``n`` real numbers."""
    # a string is a sequence too: "12" would read as (1.0, 2.0)
    if not isinstance(v, (list, tuple, np.ndarray)) or np.ndim(v) != 1 or len(v) != n:
        raise ModelError(f"{name} must be a list of {n} numbers, got {_show(v)}")
    out = tuple(_real(name, x) for x in v)
    if not all(math.isfinite(x) for x in out):
        raise ModelError(f"{name} must be finite, got {list(out)}")
    return out


def _integer(name: str, v: Any, minimum: int = 1) -> int:
    """``v`` as an int ≥ ``minimum``; an integral float (64.0, as JSON may write it) counts."""
    what = "a positive integer" if minimum == 1 else f"an integer >= {minimum}"
    if isinstance(v, numbers.Integral) and not isinstance(v, (bool, np.bool_)):
        n = int(v)
        try:
            float(n)  # sizes are scaled in floating point: beyond its range is no size
        except OverflowError:
            raise ModelError(f"{name} is out of range, got {_show(v)}") from None
    elif _is_real(v) and math.isfinite(_real(name, v)) and float(v).is_integer():
        n = int(v)
    else:
        raise ModelError(f"{name} must be {what}, got {_show(v)}")
    if n < minimum:
        raise ModelError(f"{name} must be {what}, got {n}")
    return n


def _field_shape(shape: Any) -> tuple[int, int]:
    """``shape`` as (H, W); ModelError unless two positive integers."""
    if not isinstance(shape, (list, tuple, np.ndarray)) or np.ndim(shape) != 1 or len(shape) != 2:
        raise ModelError(f"field shape must be (height, width), got {_show(shape)}")
    return _integer("field shape height", shape[0]), _integer("field shape width", shape[1])


def blackout_error(gmin: float) -> ModelError:
    """The error for a model whose geometric factor G reaches ``gmin`` ≤ 0 in the frame."""
    return ModelError(f"the geometric factor G falls to {gmin:.3g} inside the frame: the model "
                      "would black out part of the image")


def half_diagonal(width: int, height: int) -> float:
    """Half the frame's diagonal (px): the radius that normalises a model's parameters
    and the forensic rings' radii (:mod:`vigproc.core.normalised`)."""
    return 0.5 * math.hypot(width, height)


def frame_coords(n: int) -> np.ndarray:
    """Pixel-centre coordinates of ``n`` samples relative to the frame centre ((n−1)/2)."""
    return np.arange(n, dtype=np.float64) - (n - 1) / 2.0


def kw_field_and_jacobian(xs: np.ndarray, ys: np.ndarray, theta: np.ndarray, F: np.ndarray,
                          J: np.ndarray) -> float:
    """ln φ and ∂ ln φ / ∂θ of the generalized Kang-Weiss model on a grid.

    φ(v; θ) = A·G with A = 1 / (1 + r²/4)², G = 1 − Σ α_k r^k and
    r² = (v − c)ᵀ P (v − c), θ = (cx, cy, p1, p2, p3, α1..α7), P = [[p1, p2], [p2, p3]].

    Parameters
    ----------
    xs, ys : ndarray (w,), (h,)
        Grid coordinates, in the unit θ is in (the estimators use half-diagonals).
    theta : ndarray (12,)
    F : ndarray (h, w), output
        ln φ (G below 1e-9 is taken as 1e-9).
    J : ndarray (h, w, 12), output
        ∂ ln φ / ∂θ.

    Returns
    -------
    float
        The smallest G on the grid (≤ 0: the model blacks out part of it).

    References
    ----------
    S. Lyu, "Estimating vignetting function from a single image for image
    authentication", ACM MM&Sec 2010, Eq. (2).
    """
    cx, cy, p1, p2, p3 = (float(t) for t in theta[:5])
    alpha = np.asarray(theta[5:], dtype=np.float64)
    dx = (np.asarray(xs, dtype=np.float64) - cx)[None, :]
    dy = (np.asarray(ys, dtype=np.float64) - cy)[:, None]
    q = np.maximum(p1 * dx * dx + 2.0 * p2 * dx * dy + p3 * dy * dy, 0.0)
    r = np.sqrt(q)
    # G = 1 − Σ α_k r^k and dG/dr, by Horner
    g = np.zeros_like(r)
    dg = np.zeros_like(r)
    for k in range(alpha.size - 1, -1, -1):
        dg = dg * r + (k + 1) * alpha[k]
        g = (g + alpha[k]) * r
    g = 1.0 - g
    gs = np.maximum(g, 1e-9)
    F[...] = -2.0 * np.log1p(0.25 * q) + np.log(gs)
    dfdq = -0.5 / (1.0 + 0.25 * q) - dg / (2.0 * np.maximum(r, 1e-9) * gs)
    J[..., 0] = -2.0 * dfdq * (p1 * dx + p2 * dy)
    J[..., 1] = -2.0 * dfdq * (p2 * dx + p3 * dy)
    J[..., 2] = dfdq * dx * dx
    J[..., 3] = 2.0 * dfdq * dx * dy
    J[..., 4] = dfdq * dy * dy
    rk = np.ones_like(r)
    for k in range(alpha.size):
        rk = rk * r
        J[..., 5 + k] = -rk / gs
    return float(g.min()) if g.size else math.inf


@dataclass(frozen=True)
class FitQuality:
    """How much the image supports an estimate (filled in by the estimators).

    Attributes
    ----------
    confidence : float
        0..1; the default estimator falls back to "no correction" below its threshold.
    field_ev_rms : float
        RMS of log2 φ over the frame of the fitted (candidate) model, in EV.
    field_sigma_ev : float
        1-σ uncertainty of log2 φ (RMS over the frame), in EV, from the fit's covariance.
    snr : float
        ``field_ev_rms / field_sigma_ev``.
    fallback : bool
        True when the candidate was rejected and the identity model returned.
    objective : float
        Final value of the estimator's objective.
    iterations : int
    seconds : float
    reason : str
        Why the fit was not applied, when ``fallback`` and the evidence was not merely
        weak (e.g. a fall-off shaped like a light source's glow, :mod:`vigproc.core.glow`).
    """

    confidence: float = 1.0
    field_ev_rms: float = 0.0
    field_sigma_ev: float = 0.0
    snr: float = math.inf
    fallback: bool = False
    objective: float = math.nan
    iterations: int = 0
    seconds: float = 0.0
    reason: str = ""


@dataclass(frozen=True)
class VignettingModel:
    """Parameters θ = (c, P, α) of φ(v; θ) = A(v)·G(v) for a frame of ``width``×``height``.

    Attributes
    ----------
    width, height : int
        Size in pixels of the frame the parameters refer to.
    center : tuple of float
        Vignetting centre (cx, cy) in pixels relative to the frame centre
        ((W−1)/2, (H−1)/2); x to the right, y down.
    p : tuple of float
        Shape matrix entries (p1, p2, p3), P = [[p1, p2], [p2, p3]] in px⁻²;
        for a circular fall-off of effective focal length f, p1 = p3 = 1/f², p2 = 0.
    alpha : tuple of float
        Geometric-factor coefficients α1..α7, G = 1 − Σ α_i r^i.
    method : str
        Estimator that produced the model.
    covariance : tuple of tuple of float or None
        12×12 covariance of (cx, cy, p1, p2, p3, α1..α7) in the units above.
    quality : FitQuality or None
    candidate : VignettingModel or None
        When the default estimator fell back to the identity model, the rejected fit.
    colour : ColourField or None
        Per-channel ratios of the fall-off (:class:`vigproc.core.colour.ColourField`):
        channel c's field is φ·ρ_c. None: the channels share φ (colourless).

    Examples
    --------
    A centred, circular fall-off of effective focal length 150 px on a 240×160 frame:

    >>> from vigproc import VignettingModel
    >>> m = VignettingModel(240, 160, p=(1 / 150**2, 0.0, 1 / 150**2))
    >>> round(m.field_ev_rms(), 2)  # how strong: RMS of log2 φ over the frame, in EV
    0.25
    >>> VignettingModel.identity(240, 160).is_identity
    True
    """

    width: int
    height: int
    center: tuple[float, float] = (0.0, 0.0)
    p: tuple[float, float, float] = (0.0, 0.0, 0.0)
    alpha: tuple[float, ...] = (0.0,) * N_ALPHA
    method: str = "identity"
    covariance: tuple[tuple[float, ...], ...] | None = None
    quality: FitQuality | None = None
    candidate: VignettingModel | None = field(default=None, repr=False)
    colour: ColourField | None = field(default=None, repr=False)

    def __post_init__(self) -> None:
        width, height = _integer("width", self.width), _integer("height", self.height)
        center = _reals("center", self.center, 2)
        p1, p2, p3 = _reals("p", self.p, 3)
        alpha = _reals("alpha", self.alpha, N_ALPHA)
        # P must be positive semi-definite (P = 0 is the identity model).
        tol = 1e-12 * max(abs(p1), abs(p3), 1e-30)
        if p1 < -tol or p3 < -tol or p1 * p3 - p2 * p2 < -tol * max(abs(p1), abs(p3)):
            raise ModelError(f"shape matrix P must be positive semi-definite, got p={(p1, p2, p3)}")
        if self.quality is not None and not isinstance(self.quality, FitQuality):
            raise ModelError(f"quality must be a FitQuality, got {_show(self.quality)}")
        cand = self.candidate
        if cand is not None:
            if not isinstance(cand, VignettingModel):
                raise ModelError(f"candidate must be a VignettingModel, got {_show(cand)}")
            # a candidate is the rejected fit of this very frame, never a chain of them
            if cand.candidate is not None:
                raise ModelError("a candidate cannot have a candidate of its own")
            if cand.size != (width, height):
                raise ModelError(
                    f"candidate is for a {cand.width}x{cand.height} frame, the model for {width}x{height}"
                )
        col = self.colour
        if col is not None:
            if not isinstance(col, ColourField):
                raise ModelError(f"colour must be a ColourField, got {_show(col)}")
            if col.size != (width, height):
                if abs((col.width / col.height) / (width / height) - 1.0) > 0.02:
                    raise ModelError(f"colour field is for a {col.width}x{col.height} frame, the model for "
                                     f"{width}x{height}")
                col = col.rescale(width, height)
            object.__setattr__(self, "colour", None if col.is_neutral else col)
        object.__setattr__(self, "width", width)
        object.__setattr__(self, "height", height)
        object.__setattr__(self, "center", center)
        object.__setattr__(self, "p", (p1, p2, p3))
        object.__setattr__(self, "alpha", alpha)

    # ------------------------------------------------------------------ views
    @classmethod
    def identity(cls, width: int, height: int, **kw: Any) -> VignettingModel:
        """The model φ ≡ 1 (no vignetting) for a ``width``×``height`` frame."""
        return cls(width=width, height=height, method=kw.pop("method", "identity"), **kw)

    @property
    def shape_matrix(self) -> np.ndarray:
        """P as a 2×2 array in px⁻²."""
        p1, p2, p3 = self.p
        return np.array([[p1, p2], [p2, p3]])

    @property
    def is_identity(self) -> bool:
        """No fall-off and no colour shading: correcting changes nothing."""
        return self.p == (0.0, 0.0, 0.0) and not any(self.alpha) and self.colour is None

    @property
    def size(self) -> tuple[int, int]:
        """(width, height) of the reference frame."""
        return (self.width, self.height)

    def as_vector(self) -> np.ndarray:
        """θ as a 12-vector (cx, cy, p1, p2, p3, α1..α7)."""
        return np.array([*self.center, *self.p, *self.alpha], dtype=np.float64)

    @classmethod
    def from_vector(cls, theta: np.ndarray, width: int, height: int, **kw: Any) -> VignettingModel:
        theta = np.asarray(theta, dtype=np.float64)
        return cls(
            width=width,
            height=height,
            center=(theta[0], theta[1]),
            p=(theta[2], theta[3], theta[4]),
            alpha=tuple(theta[5 : 5 + N_ALPHA]),
            **kw,
        )

    # ------------------------------------------------------------- evaluation
    def _scale_to(self, shape: tuple[int, int]) -> tuple[float, float]:
        h, w = _field_shape(shape)
        return w / self.width, h / self.height

    def log_field(self, shape: tuple[int, int] | None = None) -> np.ndarray:
        """log φ on an H×W grid covering the same frame (any resolution).

        Parameters
        ----------
        shape : (H, W), optional
            Output resolution (two positive integers); defaults to the model's own
            frame size. A different resolution is the same frame resampled
            (``rescale``), not a crop.

        Returns
        -------
        ndarray, float64, H×W

        Raises
        ------
        ModelError
            If ``shape`` is not two positive integers, or G falls to zero or below.
        """
        shape = (self.height, self.width) if shape is None else _field_shape(shape)
        m = self.rescale(shape[1], shape[0]) if shape != (self.height, self.width) else self
        out = np.empty(shape, dtype=np.float64)
        if m.is_identity:
            out.fill(0.0)
            return out
        # imported here: importing the model (the profile store does) need not load Numba
        from vigproc.core._kernels.field import log_field_grid, log_field_grid_parallel

        # threads pay off only on large grids
        kernel = log_field_grid_parallel if out.size >= 1 << 20 else log_field_grid
        gmin = kernel(
            frame_coords(out.shape[1]),
            frame_coords(out.shape[0]),
            m.center[0],
            m.center[1],
            *m.p,
            np.asarray(m.alpha, dtype=np.float64),
            out,
        )
        if gmin <= 0.0:
            raise blackout_error(gmin)
        return out

    def log_field_at(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """log φ at arbitrary points (x, y), pixels from the frame centre (numpy).

        The point-wise counterpart of :meth:`log_field` (which evaluates a grid with
        the Numba kernel), for curves and fits.

        Raises
        ------
        ModelError
            If G falls to zero or below at any of the points.
        """
        x = np.asarray(x, dtype=np.float64)
        y = np.asarray(y, dtype=np.float64)
        if self.is_identity:
            return np.zeros(np.broadcast(x, y).shape)
        ex, ey = x - self.center[0], y - self.center[1]
        p1, p2, p3 = self.p
        q = np.maximum(p1 * ex * ex + 2.0 * p2 * ex * ey + p3 * ey * ey, 0.0)
        r = np.sqrt(q)
        g = np.zeros_like(r)
        for a in reversed(self.alpha):  # Horner: 1 − Σ α_i r^i
            g = (g + a) * r
        g = 1.0 - g
        if np.any(g <= 0.0):
            raise blackout_error(float(g.min()))
        return -2.0 * np.log1p(0.25 * q) + np.log(g)

    def field(self, shape: tuple[int, int] | None = None) -> np.ndarray:
        """φ on an H×W grid: the attenuation, 1.0 at the vignetting centre.

        ``shape`` as for :meth:`log_field` (default: the model's own frame size).

        Examples
        --------
        >>> from vigproc import VignettingModel
        >>> m = VignettingModel(240, 160, center=(20.0, 0.0), p=(1 / 150**2, 0.0, 1 / 150**2))
        >>> phi = m.field()
        >>> phi.shape, phi.dtype
        ((160, 240), dtype('float64'))
        >>> round(float(phi.max()), 3)  # 1 at the vignetting centre, 20 px right of the frame's
        1.0
        >>> round(float(phi[0, 0]), 2), round(float(phi[0, -1]), 2)  # the top corners: left is further out
        (0.6, 0.72)
        >>> m.field((80, 120)).shape  # the same frame at half the resolution
        (80, 120)
        """
        return np.exp(self.log_field(shape))

    def field_ev_rms(self, shape: tuple[int, int] | None = None) -> float:
        """RMS of log2 φ over the frame, in EV (stops)."""
        if shape is None:
            # never upsampled: an upsampled grid's corner samples lie outside the frame
            s = min(1.0, 256.0 / max(self.width, self.height))
            shape = (max(2, round(self.height * s)), max(2, round(self.width * s)))
        h, w = _field_shape(shape)
        m = self.rescale(w, h) if (h, w) != (self.height, self.width) else self
        # NumPy on this small grid (≤ 256 per side): as fast as the kernel, and a process
        # that only pools a profile never waits for Numba to load
        xs, ys = frame_coords(w), frame_coords(h)
        if m.center == (0.0, 0.0) and m.p[1] == 0.0:
            # a centred field without a tilted axis is even in x and in y, and the grid is
            # symmetric (exactly): one quadrant evaluated, mirrored, gives the same array
            q = m.log_field_at(xs[w // 2:][None, :], ys[h // 2:][:, None])
            q = np.concatenate([q[:, w % 2:][:, ::-1], q], axis=1)
            lf = np.concatenate([q[h % 2:][::-1], q], axis=0) / math.log(2.0)
        else:
            lf = m.log_field_at(xs[None, :], ys[:, None]) / math.log(2.0)
        return float(np.sqrt(np.mean(lf * lf)))

    # ------------------------------------------------------------ transforms
    def rescale(self, width: int, height: int) -> VignettingModel:
        """The same frame at another resolution (estimate small, apply at full size).

        Pixel coordinates relative to the frame centre scale exactly by s = new/old
        per axis, so c' = S c and P' = S⁻¹ P S⁻¹ with S = diag(sx, sy); α (a function
        of the dimensionless r) is unchanged.

        Raises
        ------
        ModelError
            If ``width``/``height`` are not positive integers (an integral float such
            as 64.0 counts), or the aspect ratio changes.

        Examples
        --------
        Estimated on a 240×160 preview, applied to the 2400×1600 original:

        >>> import numpy as np
        >>> from vigproc import VignettingModel
        >>> small = VignettingModel(240, 160, center=(12.0, -4.0), p=(1 / 150**2, 0.0, 1 / 150**2))
        >>> big = small.rescale(2400, 1600)
        >>> big.center, round(1 / big.p[0] ** 0.5)
        ((120.0, -40.0), 1500)
        >>> bool(np.allclose(big.field((160, 240)), small.field()))  # one frame, two resolutions
        True
        >>> small.rescale(240, 240)
        Traceback (most recent call last):
        ...
        vigproc.errors.ModelError: rescaling 240x160 to 240x240 changes the aspect ratio: that is a different frame (crop?), not a resolution change
        """
        # the frame is stored as whole pixels: a fractional size would scale by one
        # factor and record another
        width, height = _integer("rescale width", width), _integer("rescale height", height)
        sx, sy = width / self.width, height / self.height
        if abs(sx / sy - 1.0) > 0.02:
            raise ModelError(
                f"rescaling {self.width}x{self.height} to {width}x{height} changes the aspect "
                "ratio: that is a different frame (crop?), not a resolution change"
            )
        p1, p2, p3 = self.p
        cov = None
        if self.covariance is not None:
            t = np.diag([sx, sy, 1 / sx**2, 1 / (sx * sy), 1 / sy**2] + [1.0] * N_ALPHA)
            c = t @ np.asarray(self.covariance) @ t
            cov = tuple(tuple(float(v) for v in row) for row in c)
        return replace(
            self,
            width=width,
            height=height,
            center=(self.center[0] * sx, self.center[1] * sy),
            p=(p1 / sx**2, p2 / (sx * sy), p3 / sy**2),
            covariance=cov,
            candidate=self.candidate.rescale(width, height) if self.candidate else None,
            colour=self.colour.rescale(width, height) if self.colour is not None else None,
        )

    def channel_log_fields(self, shape: tuple[int, int] | None = None) -> np.ndarray:
        """ln φ_c = ln φ + ln ρ_c per channel on an H×W grid (H×W×3); the three
        channels alike (ln φ) for a colourless model."""
        lf = self.log_field(shape)
        if self.colour is None:
            return np.repeat(lf[..., None], 3, axis=2)
        return lf[..., None] + self.colour.log_ratios(lf.shape[1], lf.shape[0])

    # ---------------------------------------------------------- serialising
    def to_dict(self) -> dict[str, Any]:
        d: dict[str, Any] = {
            "schema": SCHEMA if self.colour is None else SCHEMA_COLOUR,
            "width": self.width,
            "height": self.height,
            "center": list(self.center),
            "p": list(self.p),
            "alpha": list(self.alpha),
            "method": self.method,
        }
        if self.covariance is not None:
            d["covariance"] = [list(r) for r in self.covariance]
        if self.quality is not None:
            # JSON has no NaN/Inf: a non-finite figure is null (snr: infinite; others: unknown)
            q = {k: None if isinstance(v, float) and not math.isfinite(v) else v
                 for k, v in self.quality.__dict__.items()}
            d["quality"] = q
        if self.candidate is not None:
            d["candidate"] = self.candidate.to_dict()
        if self.colour is not None:
            d["colour"] = self.colour.to_dict()
        return d

    def to_json(self, **kw: Any) -> str:
        """The model as JSON text (:meth:`to_dict`; ``kw`` goes to :func:`json.dumps`),
        read back by :meth:`from_json`.

        Examples
        --------
        >>> from vigproc import VignettingModel
        >>> m = VignettingModel(240, 160, center=(12.0, -4.0), p=(1 / 150**2, 0.0, 1 / 150**2), method="robust")
        >>> text = m.to_json()
        >>> text[:70]
        '{"schema": "vigproc.model/1", "width": 240, "height": 160, "center": ['
        >>> VignettingModel.from_json(text) == m  # exact: floats survive JSON
        True
        """
        return json.dumps(self.to_dict(), **kw)

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> VignettingModel:
        """The model of a :meth:`to_dict` mapping (e.g. parsed JSON).

        Raises
        ------
        ModelError
            If a field is missing, of the wrong type or absurd: sizes that are not
            positive integers, parameters that are not lists of finite numbers, a
            covariance that is not a symmetric positive semi-definite 12×12 matrix, a
            malformed quality block, or a candidate for another frame size or with a
            candidate of its own.
        """
        if not isinstance(d, dict):
            raise ModelError("a vignetting model must be a JSON object")
        schema = d.get("schema", SCHEMA)
        if schema not in SCHEMAS:
            raise ModelError(f"unknown model schema {schema!r} (expected one of {', '.join(map(repr, SCHEMAS))})")
        col = d.get("colour")
        if col is not None and schema == SCHEMA:
            raise ModelError(f"a colour field needs schema {SCHEMA_COLOUR!r}, the model says {schema!r}")
        # a bad size is named before missing fields ({"width": 1e999} is about width)
        for k in ("width", "height"):
            if k in d:
                _integer(k, d[k])
        missing = [k for k in ("width", "height", "center", "p", "alpha") if k not in d]
        if missing:
            raise ModelError(f"vignetting model is missing field {missing[0]!r}")
        # the parameters themselves are checked by __post_init__; only JSON's
        # list form is accepted here
        for k in ("center", "p", "alpha"):
            if not isinstance(d[k], list):
                raise ModelError(f"{k} must be a list of numbers, got {_show(d[k])}")
        cov = d.get("covariance")
        q = d.get("quality")
        cand = d.get("candidate")
        if cand is not None:
            # refused before recursing, so a deep chain cannot exhaust the stack
            if not isinstance(cand, dict):
                raise ModelError("candidate must be a vignetting model object")
            if cand.get("candidate") is not None:
                raise ModelError("a candidate cannot have a candidate of its own")
        try:
            return cls(
                width=d["width"],
                height=d["height"],
                center=tuple(d["center"]),
                p=tuple(d["p"]),
                alpha=tuple(d["alpha"]),
                method=str(d.get("method", "unknown")),
                covariance=None if cov is None else _covariance_from(cov),
                quality=None if q is None else _quality_from(q),
                candidate=None if cand is None else cls.from_dict(cand),
                colour=None if col is None else ColourField.from_dict(col),
            )
        except ModelError:
            raise
        except (KeyError, TypeError, ValueError, OverflowError) as exc:  # not expected: checked above
            raise ModelError(f"invalid vignetting model: {exc!r}") from None

    @classmethod
    def from_json(cls, text: str | bytes) -> VignettingModel:
        """The model of a :meth:`to_json` text (see :meth:`from_dict` for the checks).

        Examples
        --------
        >>> from vigproc import VignettingModel
        >>> m = VignettingModel.from_json('{"schema": "vigproc.model/1", "width": 240, "height": 160, '
        ...                               '"center": [0, 0], "p": [4e-05, 0, 4e-05], "alpha": [0, 0, 0, 0, 0, 0, 0]}')
        >>> m.width, m.height, m.p
        (240, 160, (4e-05, 0.0, 4e-05))
        >>> VignettingModel.from_json('{"width": 240, "height": 160}')
        Traceback (most recent call last):
        ...
        vigproc.errors.ModelError: vignetting model is missing field 'center'
        """
        if not isinstance(text, (str, bytes, bytearray)):
            raise ModelError(f"a vignetting model must be JSON text, got {type(text).__name__}")
        try:
            d = json.loads(text)
        # ValueError: also undecodable bytes and over-long integer literals;
        # RecursionError: absurdly nested
        except (ValueError, RecursionError) as exc:
            raise ModelError(f"vignetting model is not valid JSON: {exc}") from None
        return cls.from_dict(d)


#: Relative tolerance for rounding in a serialised covariance (asymmetry relative to
#: its largest entry, negative eigenvalues relative to its largest eigenvalue).
COV_RTOL = 1e-9


def _covariance_from(cov: Any) -> tuple[tuple[float, ...], ...]:
    """A serialised covariance as a tuple of rows; ModelError unless a symmetric
    positive semi-definite 12×12 matrix of finite numbers (up to :data:`COV_RTOL`)."""
    n = len(PARAM_NAMES)
    if not (isinstance(cov, list) and len(cov) == n and all(isinstance(r, list) and len(r) == n for r in cov)):
        raise ModelError(f"covariance must be a {n}x{n} matrix (a list of {n} lists of {n} numbers)")
    c = np.array([[_real("covariance entry", v) for v in r] for r in cov])
    if not np.all(np.isfinite(c)):
        raise ModelError(f"covariance must be a finite {n}x{n} matrix")
    if np.max(np.abs(c - c.T)) > COV_RTOL * np.max(np.abs(c)):
        raise ModelError("covariance must be symmetric")
    # a variance is never negative, however small: rounding does not flip its sign
    neg = np.flatnonzero(np.diag(c) < 0)
    if neg.size:
        raise ModelError(f"covariance is not positive semi-definite: negative variance of {PARAM_NAMES[neg[0]]}")
    try:
        w = np.linalg.eigvalsh(0.5 * c + 0.5 * c.T)  # halves first: no overflow near float max
    except np.linalg.LinAlgError:
        raise ModelError("covariance has no eigen-decomposition (absurd entries?)") from None
    if w[0] < -COV_RTOL * max(w[-1], 0.0):
        raise ModelError(f"covariance is not positive semi-definite (eigenvalue {w[0]:.3g}, largest {w[-1]:.3g})")
    return tuple(tuple(float(v) for v in r) for r in c)


def _quality_from(q: Any) -> FitQuality:
    """A serialised FitQuality; ModelError on an unknown field or a wrong type."""
    if not isinstance(q, dict):
        raise ModelError(f"quality must be a JSON object, got {_show(q)}")
    unknown = sorted(repr(k) for k in q if k not in {f.name for f in fields(FitQuality)})
    if unknown:
        raise ModelError(f"unknown quality field(s): {', '.join(unknown)}")
    kw: dict[str, Any] = {}
    for k, v in q.items():
        if k == "fallback":
            if not isinstance(v, bool):
                raise ModelError(f"quality.fallback must be true or false, got {_show(v)}")
        elif k == "iterations":
            v = _integer("quality.iterations", v, minimum=0)
        elif k == "reason":
            if not isinstance(v, str):
                raise ModelError(f"quality.reason must be a string, got {_show(v)}")
        elif v is None:
            # to_dict's null for a non-finite figure: snr infinite, the others unknown
            v = math.inf if k == "snr" else math.nan
        else:
            v = _real(f"quality.{k}", v)
        kw[k] = v
    return FitQuality(**kw)
