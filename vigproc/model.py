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
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from vigproc._kernels.field import log_field_grid, log_field_grid_parallel
from vigproc.errors import ModelError

#: Degree of the geometric polynomial G (Lyu 2010 fixes k = 7).
N_ALPHA = 7
#: Order of the parameter vector used for covariances: (cx, cy, p1, p2, p3, α1..α7).
PARAM_NAMES = ("cx", "cy", "p1", "p2", "p3") + tuple(f"alpha{i}" for i in range(1, N_ALPHA + 1))
SCHEMA = "vigproc.model/1"


def frame_coords(n: int) -> np.ndarray:
    """Pixel-centre coordinates of ``n`` samples relative to the frame centre ((n−1)/2)."""
    return np.arange(n, dtype=np.float64) - (n - 1) / 2.0


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
    """

    confidence: float = 1.0
    field_ev_rms: float = 0.0
    field_sigma_ev: float = 0.0
    snr: float = math.inf
    fallback: bool = False
    objective: float = math.nan
    iterations: int = 0
    seconds: float = 0.0


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

    def __post_init__(self) -> None:
        if int(self.width) < 1 or int(self.height) < 1:
            raise ModelError(f"frame size must be positive, got {self.width}x{self.height}")
        values = [*self.center, *self.p, *self.alpha]
        if len(self.center) != 2 or len(self.p) != 3 or len(self.alpha) != N_ALPHA:
            raise ModelError(
                f"model needs 2 centre, 3 shape and {N_ALPHA} alpha values, got "
                f"{len(self.center)}, {len(self.p)}, {len(self.alpha)}"
            )
        if not all(math.isfinite(float(v)) for v in values):
            raise ModelError(f"model parameters must be finite, got {values}")
        p1, p2, p3 = (float(v) for v in self.p)
        # P must be positive semi-definite (P = 0 is the identity model).
        tol = 1e-12 * max(abs(p1), abs(p3), 1e-30)
        if p1 < -tol or p3 < -tol or p1 * p3 - p2 * p2 < -tol * max(abs(p1), abs(p3)):
            raise ModelError(f"shape matrix P must be positive semi-definite, got p={self.p}")
        object.__setattr__(self, "width", int(self.width))
        object.__setattr__(self, "height", int(self.height))
        object.__setattr__(self, "center", (float(self.center[0]), float(self.center[1])))
        object.__setattr__(self, "p", (p1, p2, p3))
        object.__setattr__(self, "alpha", tuple(float(a) for a in self.alpha))

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
        return self.p == (0.0, 0.0, 0.0) and not any(self.alpha)

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
        h, w = int(shape[0]), int(shape[1])
        if h < 1 or w < 1:
            raise ModelError(f"field shape must be positive, got {shape}")
        return w / self.width, h / self.height

    def log_field(self, shape: tuple[int, int] | None = None) -> np.ndarray:
        """log φ on an H×W grid covering the same frame (any resolution).

        Parameters
        ----------
        shape : (H, W), optional
            Output resolution; defaults to the model's own frame size. A different
            resolution is the same frame resampled (``rescale``), not a crop.

        Returns
        -------
        ndarray, float64, H×W
        """
        if shape is None:
            shape = (self.height, self.width)
        m = self.rescale(shape[1], shape[0]) if tuple(shape) != (self.height, self.width) else self
        out = np.empty((int(shape[0]), int(shape[1])), dtype=np.float64)
        if m.is_identity:
            out.fill(0.0)
            return out
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
            raise ModelError(
                f"the geometric factor G falls to {gmin:.3g} inside the frame: the model "
                "would black out part of the image"
            )
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
        g = 1.0 - (r[..., None] ** np.arange(1, N_ALPHA + 1)) @ np.asarray(self.alpha)
        if np.any(g <= 0.0):
            raise ModelError(
                f"the geometric factor G falls to {g.min():.3g} inside the frame: the model "
                "would black out part of the image"
            )
        return -2.0 * np.log1p(0.25 * q) + np.log(g)

    def field(self, shape: tuple[int, int] | None = None) -> np.ndarray:
        """φ on an H×W grid: the attenuation, 1.0 at the vignetting centre."""
        return np.exp(self.log_field(shape))

    def field_ev_rms(self, shape: tuple[int, int] | None = None) -> float:
        """RMS of log2 φ over the frame, in EV (stops)."""
        if shape is None:
            # never upsampled: an upsampled grid's corner samples lie outside the frame
            s = min(1.0, 256.0 / max(self.width, self.height))
            shape = (max(2, round(self.height * s)), max(2, round(self.width * s)))
        lf = self.log_field(shape) / math.log(2.0)
        return float(np.sqrt(np.mean(lf * lf)))

    # ------------------------------------------------------------ transforms
    def rescale(self, width: int, height: int) -> VignettingModel:
        """The same frame at another resolution (estimate small, apply at full size).

        Pixel coordinates relative to the frame centre scale exactly by s = new/old
        per axis, so c' = S c and P' = S⁻¹ P S⁻¹ with S = diag(sx, sy); α (a function
        of the dimensionless r) is unchanged.
        """
        sx, sy = float(width) / self.width, float(height) / self.height
        if not (sx > 0 and sy > 0):
            raise ModelError(f"cannot rescale to {width}x{height}")
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
            width=int(width),
            height=int(height),
            center=(self.center[0] * sx, self.center[1] * sy),
            p=(p1 / sx**2, p2 / (sx * sy), p3 / sy**2),
            covariance=cov,
            candidate=self.candidate.rescale(width, height) if self.candidate else None,
        )

    # ---------------------------------------------------------- serialising
    def to_dict(self) -> dict[str, Any]:
        d: dict[str, Any] = {
            "schema": SCHEMA,
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
        return d

    def to_json(self, **kw: Any) -> str:
        return json.dumps(self.to_dict(), **kw)

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> VignettingModel:
        if not isinstance(d, dict):
            raise ModelError("a vignetting model must be a JSON object")
        schema = d.get("schema", SCHEMA)
        if schema != SCHEMA:
            raise ModelError(f"unknown model schema {schema!r} (expected {SCHEMA!r})")
        try:
            cov = d.get("covariance")
            if cov is not None:
                cov_a = np.asarray(cov, dtype=np.float64)
                if cov_a.shape != (len(PARAM_NAMES),) * 2 or not np.all(np.isfinite(cov_a)):
                    raise ModelError(f"covariance must be a finite {len(PARAM_NAMES)}x{len(PARAM_NAMES)} matrix")
                cov = tuple(tuple(float(v) for v in r) for r in cov_a)
            q = d.get("quality")
            quality = None
            if q is not None:
                q = dict(q)
                for k in ("confidence", "field_ev_rms", "field_sigma_ev", "snr", "objective", "seconds"):
                    if k in q and q[k] is None:
                        q[k] = math.inf if k == "snr" else math.nan
                if q.get("snr") is None:
                    q["snr"] = math.inf
                quality = FitQuality(**q)
            cand = d.get("candidate")
            return cls(
                width=int(d["width"]),
                height=int(d["height"]),
                center=tuple(float(v) for v in d["center"]),
                p=tuple(float(v) for v in d["p"]),
                alpha=tuple(float(v) for v in d["alpha"]),
                method=str(d.get("method", "unknown")),
                covariance=cov,
                quality=quality,
                candidate=cls.from_dict(cand) if cand is not None else None,
            )
        except ModelError:
            raise
        except (KeyError, TypeError, ValueError) as exc:
            raise ModelError(f"invalid vignetting model: {exc!r}") from None

    @classmethod
    def from_json(cls, text: str) -> VignettingModel:
        try:
            d = json.loads(text)
        except (json.JSONDecodeError, RecursionError) as exc:  # RecursionError: absurdly nested
            raise ModelError(f"vignetting model is not valid JSON: {exc}") from None
        return cls.from_dict(d)
