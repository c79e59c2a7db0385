"""Model parameters in frame-normalised units, and fitting the model to a known field.

A vignetting field belongs to the optics, not to a file's pixel count: measured in
half-diagonals R = ½·hypot(W, H) from the frame centre (c̃ = c/R, P̃ = P·R², α
unchanged), the same field sampled at 6000×4000 and 3000×2000 has the same
parameters.  Profiles, the scene prior and pooling all work in these units.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from vigproc.errors import ModelError
from vigproc.core.model import N_ALPHA, PARAM_NAMES, VignettingModel, frame_coords, half_diagonal, kw_field_and_jacobian

#: Number of model parameters (cx, cy, p1, p2, p3, α1..α7).
N_PARAMS = len(PARAM_NAMES)
#: Field grid (per axis) on which the uncertainty and the frame-to-frame scatter of
#: log2 φ are evaluated.  Part of the profile store's schema: its Welford state is
#: stored on it.
FIELD_GRID = 16

_LN2 = math.log(2.0)


# --------------------------------------------------------------------------- #
# normalised parameters
# --------------------------------------------------------------------------- #


def _to_normalised(radius: float) -> np.ndarray:
    """Diagonal T with θ̃ = T θ: c̃ = c/R, P̃ = P·R², α unchanged."""
    return np.array([1 / radius, 1 / radius] + [radius**2] * 3 + [1.0] * N_ALPHA)


def normalise(model: VignettingModel) -> tuple[np.ndarray, np.ndarray | None, float]:
    """Frame-independent parameters of ``model``.

    Coordinates are measured in units of the frame half-diagonal R = ½·hypot(W, H)
    from the frame centre: c̃ = c/R, P̃ = P·R², α unchanged (r² = (v−c)ᵀP(v−c) is
    invariant), and the covariance transforms as T Σ T with T = diag(1/R, 1/R, R²,
    R², R², 1, ...).  The same field sampled at 6000×4000 and 3000×2000 (e.g.
    :meth:`VignettingModel.rescale`) gives the same θ̃.

    Returns
    -------
    theta : ndarray (12,)
    cov : ndarray (12, 12) or None
    aspect : float
        W/H.
    """
    r = half_diagonal(model.width, model.height)
    t = _to_normalised(r)
    theta = model.as_vector() * t
    cov = None
    if model.covariance is not None:
        cov = np.asarray(model.covariance, dtype=np.float64) * np.outer(t, t)
    return theta, cov, model.width / model.height


def denormalise(
    theta: np.ndarray, cov: np.ndarray | None, width: int, height: int, **kw: Any
) -> VignettingModel:
    """The :class:`VignettingModel` of normalised ``theta`` (and ``cov``) for a
    ``width``×``height`` frame (inverse of :func:`normalise`).

    Extra keyword arguments go to the model (``method``, ``quality``).

    Raises
    ------
    ModelError
        If the parameters are not a valid model (non-finite, P not PSD).
    """
    r = half_diagonal(int(width), int(height))
    t = 1.0 / _to_normalised(r)
    theta = np.asarray(theta, dtype=np.float64)
    if theta.shape != (N_PARAMS,):
        raise ModelError(f"normalised θ must have {N_PARAMS} entries, got shape {theta.shape}")
    covariance = None
    if cov is not None:
        c = np.asarray(cov, dtype=np.float64) * np.outer(t, t)
        covariance = tuple(tuple(float(v) for v in row) for row in c)
    kw.setdefault("method", "profile")
    return VignettingModel.from_vector(theta * t, int(width), int(height), covariance=covariance, **kw)


def _field_grid(aspect: float, n: int = FIELD_GRID) -> tuple[np.ndarray, np.ndarray]:
    """Normalised sample coordinates covering a frame of aspect W/H (corners at R = 1)."""
    s = math.hypot(aspect, 1.0)
    hx, hy = aspect / s, 1.0 / s
    # cell centres: never exactly on the vignetting centre (r = 0 is a kink for α1 ≠ 0)
    u = (np.arange(n) + 0.5) / n * 2.0 - 1.0
    return u * hx, u * hy


def log_field_and_jacobian(theta: np.ndarray, xs: np.ndarray, ys: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
    """ln φ (flattened, rows over ``ys``) and ∂ ln φ / ∂θ̃ (points × 12) for normalised
    θ̃ on the grid ``xs`` × ``ys`` (half-diagonals); min G over the grid."""
    F = np.empty((ys.size, xs.size))
    J = np.empty((ys.size, xs.size, N_PARAMS))
    gmin = kw_field_and_jacobian(xs, ys, np.ascontiguousarray(theta, dtype=np.float64), F, J)
    return F.ravel(), J.reshape(F.size, N_PARAMS), float(gmin)


def _field_and_jacobian(theta: np.ndarray, aspect: float) -> tuple[np.ndarray, np.ndarray, float]:
    """log2 φ (flattened) and ∂ log2 φ / ∂θ̃ on the standard grid; min G."""
    F, J, gmin = log_field_and_jacobian(theta, *_field_grid(aspect))
    return F / _LN2, J / _LN2, gmin


def _field_sigma_ev(theta: np.ndarray, cov: np.ndarray, aspect: float) -> float:
    """RMS over the frame of the 1-σ uncertainty of log2 φ (first-order propagation)."""
    _, J, _ = _field_and_jacobian(theta, aspect)
    var = np.einsum("ij,jk,ik->i", J, cov, J)
    return float(math.sqrt(max(float(np.mean(np.maximum(var, 0.0))), 0.0)))


# --------------------------------------------------------------------------- #
# fitting the model to a known field (examples, lensfun)
# --------------------------------------------------------------------------- #


def fit_model_to_field(log_field: np.ndarray, width: int, height: int) -> tuple[VignettingModel, float]:
    """Least-squares fit of the Kang-Weiss model to a known log φ (natural log).

    Parameters
    ----------
    log_field : ndarray, h×w
        log φ sampled on the frame at any resolution of the same aspect (pixel
        centres as in :meth:`VignettingModel.log_field`), e.g. a lensfun ``pa``
        field on a small grid.
    width, height : int
        Frame the returned model refers to.

    Returns
    -------
    model : VignettingModel
        Without covariance (a fit to a known field has no sampling uncertainty).
    rms_ev : float
        RMS fit residual in EV.

    Notes
    -----
    Fitted in normalised units with P = LLᵀ (L lower triangular, so P stays PSD)
    and a weak ridge (1e-4) on c and α that picks one of the nearly equivalent
    (A, G) splits; ``scipy.optimize.least_squares`` (Levenberg-Marquardt; measured
    ~10x faster than trust-region-reflective here), three starts.  Cost grows with
    the grid: a 60×40 grid fits in well under a second and is ample for a smooth
    field.

    References
    ----------
    S. B. Kang and R. Weiss, ECCV 2000; S. Lyu, ACM MM&Sec 2010, Eq. (2).
    """
    from scipy.optimize import least_squares

    lf = np.asarray(log_field, dtype=np.float64)
    if lf.ndim != 2 or min(lf.shape) < 4 or not np.all(np.isfinite(lf)):
        raise ModelError("log_field must be a finite 2-D array of at least 4x4 samples")
    h, w = lf.shape
    if abs(math.log((w / h) / (width / height))) > 0.02:
        raise ModelError(f"a {w}x{h} field does not have the aspect ratio of {width}x{height}")
    r = half_diagonal(w, h)
    xs, ys = frame_coords(w) / r, frame_coords(h) / r
    target = lf.ravel()
    ridge = 1e-2  # sqrt of the 1e-4 ridge weight

    def theta_of(x: np.ndarray) -> np.ndarray:
        a, b, dd = x[2], x[3], x[4]
        return np.concatenate([x[:2], [a * a, a * b, b * b + dd * dd], x[5:]])

    F = np.empty((h, w))
    J = np.empty((h, w, N_PARAMS))

    def residuals(x: np.ndarray) -> np.ndarray:
        th = theta_of(x)
        gmin = kw_field_and_jacobian(xs, ys, th, F, J)
        res = F.ravel() - target
        pen = 0.0 if gmin > 1e-6 else 1e3 * (1e-6 - gmin)
        return np.concatenate([res + pen, ridge * x[:2], ridge * x[5:]])

    def jac(x: np.ndarray) -> np.ndarray:
        th = theta_of(x)
        kw_field_and_jacobian(xs, ys, th, F, J)
        Jt = J.reshape(-1, N_PARAMS)
        a, b, dd = x[2], x[3], x[4]
        # chain rule through P = LLᵀ: (p1, p2, p3) = (a², ab, b² + d²)
        Jx = np.empty((Jt.shape[0], N_PARAMS))
        Jx[:, :2] = Jt[:, :2]
        Jx[:, 2] = Jt[:, 2] * 2 * a + Jt[:, 3] * b
        Jx[:, 3] = Jt[:, 3] * a + Jt[:, 4] * 2 * b
        Jx[:, 4] = Jt[:, 4] * 2 * dd
        Jx[:, 5:] = Jt[:, 5:]
        reg = np.zeros((2 + N_ALPHA, N_PARAMS))
        reg[0, 0] = reg[1, 1] = ridge
        reg[2:, 5:] = ridge * np.eye(N_ALPHA)
        return np.vstack([Jx, reg])

    best = None
    for s in (0.1, 0.5, 2.0):  # a few starts: the A/G split has several basins
        x0 = np.zeros(N_PARAMS)
        x0[2] = x0[4] = math.sqrt(s)
        sol = least_squares(residuals, x0, jac=jac, method="lm", x_scale="jac", max_nfev=2000)
        th = theta_of(sol.x)
        if kw_field_and_jacobian(xs, ys, th, F, J) <= 0:
            continue
        rms = float(np.sqrt(np.mean((F.ravel() - target) ** 2)))
        if best is None or rms < best[1]:
            best = (th, rms)
    if best is None:
        raise ModelError("could not fit the Kang-Weiss model to the field (G falls to zero)")
    th, rms = best
    return denormalise(th, None, width, height, method="fit"), rms / _LN2
