"""Information-form pooling of vignetting estimates, exact order-independent sums and
Welford running moments (the maths of learning a profile, without the database).

Each frame's estimate (θ_i, Σ_i) is pooled in information form: Λ = Σ_i Σ_i⁻¹ and
η = Σ_i Σ_i⁻¹ θ_i, θ = Λ⁻¹ η with covariance Λ⁻¹ (the inverse-variance weighted
mean).  The sums are kept exactly (:class:`_Exact`) so the result does not depend on
the order frames arrive in; :class:`_Welford` keeps the frame-to-frame scatter.

References
----------
B. P. Welford, "Note on a method for calculating corrected sums of squares and
products", Technometrics 4(3), 1962 (running moments).
J. R. Shewchuk, "Adaptive precision floating-point arithmetic and fast robust
geometric predicates", Discrete Comput. Geom. 18, 1997 (exact float summation;
here the simpler big-integer form of the same idea).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from fractions import Fraction
from typing import Any, Sequence

import numpy as np

from vigproc.core.model import PARAM_NAMES, VignettingModel
from vigproc.core.normalised import FIELD_GRID, N_PARAMS, normalise
from vigproc.errors import ProfileStoreError

#: Relative ridge added to the correlation matrix before inverting covariances.
RIDGE = 1e-10

# --------------------------------------------------------------------------- #
# information-form pooling
# --------------------------------------------------------------------------- #


def fixed_indices(cov: np.ndarray) -> tuple[int, ...]:
    """The parameters a covariance holds fixed: those whose row and column are all zero
    (the lens-family fit fixes the centre and the shape, so its σ is exactly 0 there).

    Parameters
    ----------
    cov : ndarray (n, n)

    Returns
    -------
    tuple of int
        Indices into :data:`vigproc.core.model.PARAM_NAMES`, ascending.
    """
    cov = np.asarray(cov, dtype=np.float64)
    return tuple(i for i in range(cov.shape[0]) if not np.any(cov[i]) and not np.any(cov[:, i]))


def _scaled_pinv(m: np.ndarray, what: str, *, allow_fixed: bool = False) -> np.ndarray:
    """Pseudo-inverse of a symmetric PSD matrix, computed on its correlation form with
    a tiny ridge (parameters differ in scale by orders of magnitude).  With
    ``allow_fixed``, parameters held fixed (:func:`fixed_indices`) get zero rows and
    columns: a value known by construction adds no information to pool."""
    m = 0.5 * (m + m.T)
    keep = np.arange(m.shape[0])
    if allow_fixed:
        fixed = fixed_indices(m)
        keep = np.array([i for i in keep if i not in fixed], dtype=int)
        if keep.size == 0:
            raise ProfileStoreError(f"{what} holds every parameter fixed")
    sub = m[np.ix_(keep, keep)]
    d = np.sqrt(np.diag(sub))
    if not (np.all(np.isfinite(sub)) and np.all(d > 0)):
        bad = [PARAM_NAMES[keep[i]] for i in np.flatnonzero(~(d > 0))]
        raise ProfileStoreError(f"{what} has zero or invalid variance for {bad or 'some parameters'}")
    c = sub / np.outer(d, d)
    inv = np.linalg.pinv(c + RIDGE * np.eye(c.shape[0]), hermitian=True) / np.outer(d, d)
    out = np.zeros_like(m)
    out[np.ix_(keep, keep)] = 0.5 * (inv + inv.T)
    return out


#: Largest variance a profile file may give a (normalised) parameter.
MAX_FILE_VARIANCE = 1e8


def _check_covariance(cov: np.ndarray, what: str, *, allow_fixed: bool = False) -> np.ndarray:
    """``cov`` symmetrised, or :class:`ProfileStoreError` unless it is a finite symmetric
    PSD 12×12 matrix with positive variances; with ``allow_fixed`` an all-zero row and
    column (a parameter held fixed, :func:`fixed_indices`) is allowed too."""
    cov = np.asarray(cov, dtype=np.float64)
    if cov.shape != (N_PARAMS, N_PARAMS):
        raise ProfileStoreError(f"{what}: covariance must be {N_PARAMS}x{N_PARAMS}, got shape {cov.shape}")
    if not np.all(np.isfinite(cov)):
        raise ProfileStoreError(f"{what}: covariance contains NaN or Inf")
    scale = float(np.max(np.abs(cov))) or 1.0
    if not np.allclose(cov, cov.T, rtol=1e-6, atol=1e-9 * scale):
        raise ProfileStoreError(f"{what}: covariance is not symmetric")
    fixed = fixed_indices(cov) if allow_fixed else ()
    free = [i for i in range(N_PARAMS) if i not in fixed]
    if not free:
        raise ProfileStoreError(f"{what}: covariance holds every parameter fixed (use null for an unknown uncertainty)")
    sub = cov[np.ix_(free, free)]
    if np.any(np.diag(sub) <= 0):
        raise ProfileStoreError(f"{what}: covariance has a non-positive variance")
    d = np.sqrt(np.diag(sub))
    w = np.linalg.eigvalsh(0.5 * (sub + sub.T) / np.outer(d, d))
    if w[0] < -1e-6:
        raise ProfileStoreError(f"{what}: covariance is not positive semi-definite (eigenvalue {w[0]:.3g} of its correlation)")
    return 0.5 * (cov + cov.T)


def frame_information(model: VignettingModel) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """One frame's evidence in information form, normalised units.

    Returns
    -------
    theta : ndarray (12,)
        Normalised parameters θ_i.
    info_matrix : ndarray (12, 12)
        Λ_i = Σ_i⁻¹ (pseudo-inverse with a tiny ridge on the correlation matrix).
    info_vector : ndarray (12,)
        η_i = Λ_i θ_i.

    Raises
    ------
    ProfileStoreError
        If the model has no covariance (e.g. the identity fallback) or it is invalid.
    """
    theta, cov, _ = normalise(model)
    if cov is None:
        raise ProfileStoreError(
            f"a {model.method!r} estimate without covariance cannot be pooled (identity fallback? "
            "pass its .candidate to learn from weak evidence)"
        )
    cov = _check_covariance(cov, "frame estimate")
    lam = _scaled_pinv(cov, "frame estimate covariance")
    return theta, lam, lam @ theta


def pool_information(thetas: Sequence[np.ndarray], covs: Sequence[np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """Inverse-variance (information-form) pooling of normalised estimates.

    θ = (Σ Λ_i)⁻¹ Σ Λ_i θ_i, covariance (Σ Λ_i)⁻¹, Λ_i = Σ_i⁻¹: the same arithmetic as
    :meth:`ProfileStore.learn`, without the database (for benchmarks).
    """
    if len(thetas) == 0 or len(thetas) != len(covs):
        raise ProfileStoreError("pool_information needs as many covariances as estimates (at least one)")
    lam = np.zeros((N_PARAMS, N_PARAMS))
    eta = np.zeros(N_PARAMS)
    for th, cv in zip(thetas, covs):
        li = _scaled_pinv(_check_covariance(cv, "estimate"), "estimate covariance")
        lam += li
        eta += li @ np.asarray(th, dtype=np.float64)
    cov = _scaled_pinv(lam, "pooled information")
    return cov @ eta, cov


def pool_mean(thetas: Sequence[np.ndarray]) -> np.ndarray:
    """Plain (unweighted) mean of normalised parameter vectors, for comparison with
    the information-form pooling."""
    a = np.asarray([np.asarray(t, dtype=np.float64) for t in thetas])
    if a.ndim != 2 or a.shape[0] == 0 or a.shape[1] != N_PARAMS:
        raise ProfileStoreError(f"pool_mean needs a non-empty list of {N_PARAMS}-vectors")
    return a.mean(axis=0)


class _Exact:
    """Exact, order-independent sums of float64 arrays.

    Every finite float64 is m·2^e with integers m, e; the sum of such numbers is
    again of that form, so it is kept as (m, e) pairs of Python integers and is
    exact.  Converting back rounds once, correctly.  Hence Λ = Σ Λ_i does not depend
    on the order in which concurrent workers added their frames.
    """

    __slots__ = ("m", "e")

    def __init__(self, m: list[int], e: list[int]) -> None:
        self.m, self.e = m, e

    @classmethod
    def zeros(cls, n: int) -> _Exact:
        return cls([0] * n, [0] * n)

    @staticmethod
    def _split(x: float) -> tuple[int, int]:
        num, den = float(x).as_integer_ratio()
        if num == 0:
            return 0, 0
        e = -(den.bit_length() - 1)
        tz = (num & -num).bit_length() - 1
        return num >> tz, e + tz

    @classmethod
    def from_array(cls, a: np.ndarray) -> _Exact:
        a = np.asarray(a, dtype=np.float64).ravel()
        if not np.all(np.isfinite(a)):
            raise ProfileStoreError("cannot accumulate NaN or Inf evidence")
        pairs = [cls._split(v) for v in a.tolist()]
        return cls([p[0] for p in pairs], [p[1] for p in pairs])

    def add(self, other: _Exact) -> _Exact:
        if len(other.m) != len(self.m):
            raise ProfileStoreError("exact sums of different sizes")
        m, e = [], []
        for m1, e1, m2, e2 in zip(self.m, self.e, other.m, other.e):
            if m1 == 0:
                mm, ee = m2, e2
            elif m2 == 0:
                mm, ee = m1, e1
            else:
                ee = min(e1, e2)
                mm = (m1 << (e1 - ee)) + (m2 << (e2 - ee))
                if mm == 0:
                    ee = 0
                else:
                    tz = (mm & -mm).bit_length() - 1
                    mm, ee = mm >> tz, ee + tz
            m.append(mm)
            e.append(ee)
        return _Exact(m, e)

    def to_array(self) -> np.ndarray:
        out = np.empty(len(self.m))
        for i, (m, e) in enumerate(zip(self.m, self.e)):
            try:
                out[i] = float(m << e) if e >= 0 else float(Fraction(m, 1 << -e))
            except OverflowError:
                raise ProfileStoreError("accumulated information overflows float64") from None
        return out

    def to_json(self) -> list[list[int]]:
        return [[m, e] for m, e in zip(self.m, self.e)]

    @classmethod
    def from_json(cls, data: Any, n: int) -> _Exact:
        if not isinstance(data, list) or len(data) != n:
            raise ValueError(f"expected {n} exact values")
        m, e = [], []
        for item in data:
            if not (isinstance(item, list) and len(item) == 2 and all(type(v) is int for v in item)):
                raise ValueError("exact value is not an [int, int] pair")
            if abs(item[1]) > 4000:
                raise ValueError("exact value exponent out of range")
            m.append(item[0])
            e.append(item[1])
        return cls(m, e)


@dataclass
class _Welford:
    """Running mean and centred sums of squares (and cross-products) across frames."""

    n: int
    theta_mean: np.ndarray
    theta_m2: np.ndarray      # 12×12 Σ (θ−μ)(θ−μ)ᵀ
    field_mean: np.ndarray    # log2 φ on the FIELD_GRID² grid
    field_m2: np.ndarray      # per grid point Σ (f−μ)²

    @classmethod
    def empty(cls) -> _Welford:
        g = FIELD_GRID * FIELD_GRID
        return cls(0, np.zeros(N_PARAMS), np.zeros((N_PARAMS, N_PARAMS)), np.zeros(g), np.zeros(g))

    def add(self, theta: np.ndarray, field_: np.ndarray) -> _Welford:
        """Welford (1962) update with one more frame (returns a new state)."""
        n = self.n + 1
        d = theta - self.theta_mean
        mu = self.theta_mean + d / n
        m2 = self.theta_m2 + np.outer(d, theta - mu)
        df = field_ - self.field_mean
        fmu = self.field_mean + df / n
        fm2 = self.field_m2 + df * (field_ - fmu)
        return _Welford(n, mu, 0.5 * (m2 + m2.T), fmu, fm2)

    @property
    def scatter_sigma_ev(self) -> float | None:
        """Frame-to-frame RMS (over the frame) standard deviation of log2 φ, EV."""
        if self.n < 2:
            return None
        return float(math.sqrt(max(float(np.mean(self.field_m2)) / (self.n - 1), 0.0)))

    @property
    def theta_scatter(self) -> np.ndarray | None:
        """Sample covariance of θ̃ across frames."""
        if self.n < 2:
            return None
        return self.theta_m2 / (self.n - 1)
