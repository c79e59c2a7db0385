"""The family of real lens fall-offs that lensfun's calibrations span.

lensfun holds ~23 600 ``pa`` vignetting calibrations of ~550 lenses. As radial
profiles of log attenuation over the normalised radius ρ (1 = the frame's corner,
lensfun's own convention for an image of the calibration crop), they lie close to a
low-dimensional space: measured on lensfunpy's database, 2 principal components
reconstruct them to 0.005 EV (median; p90 0.028), 1 component to 0.019 EV.

A :class:`LensFamily` keeps that space: the mean log profile, the first components,
and every calibration's coefficients with its 35-mm-equivalent focal length and
f-number, so that an estimate can use the family's spread as its prior, or the
spread of calibrations like the frame's EXIF (:meth:`LensFamily.prior`).

The shipped family (``vigproc/data/lens_family.json``, :data:`PROFILE_COMPONENTS`
components) is built from every lens of the bundled lensfun database by
:func:`vigproc.stores.lensfun.lensfun_family` (``vigproc prior fit-lens-family``); a grey frame's fit
and the forensic tests use its first :data:`N_COMPONENTS` (:func:`default_family`), a
colour frame's fit and a lens profile all of them (:func:`profile_family`;
:func:`vigproc.core.family_fit.family_for`). The benchmarks build families that leave
their test lenses out.

References
----------
lensfun, ``libs/lensfun/mod-color.cpp`` (the ``pa`` model; r = 1 at the corner).
Principal components: I. T. Jolliffe, *Principal Component Analysis*, 2002, ch. 3.
"""

from __future__ import annotations

import json
import logging
import math
from dataclasses import dataclass
from contextlib import contextmanager
from functools import lru_cache
from importlib.resources import files
from pathlib import Path
from typing import Iterable, Iterator

import numpy as np

from vigproc.atomic import atomic_write_text
from vigproc.errors import ModelError

log = logging.getLogger(__name__)

#: Samples of the radial profile over ρ ∈ [0, 1].
N_RADII = 65
#: Components a grey frame's fit and the forensic tests use (2 reconstruct lensfun's
#: calibrations to 0.005 EV): a grey photograph's scene cannot pin down more (a colour
#: frame's fit, its pairs weighted by colour, uses all of the shipped family's).
N_COMPONENTS = 2
#: Components the shipped family keeps, and a lens profile pools in (3 reconstruct
#: the calibrations to 0.002 EV): many frames average the scenes away, and then the
#: family's own reconstruction error is what remains (clean protocol, 50 frames:
#: 0.021 EV with 2 components, 0.009 with 3; docs/benchmarks/profiles.md).
PROFILE_COMPONENTS = 3
#: Calibrations whose attenuation leaves (0.02, 1.05] on ρ ∈ [0, 1] are not lenses'
#: fall-offs (fits that extrapolate badly); they are left out of the family.
PLAUSIBLE = (0.02, 1.05)
#: Nearest calibrations (in log focal length and log f-number) forming an EXIF prior.
NEIGHBOURS = 50
#: Format version of the family file.
FORMAT = 1


@dataclass(frozen=True)
class LensFamily:
    """Radial log-attenuation profiles of real lenses: mean + components.

    Attributes
    ----------
    radii : ndarray (N,)
        ρ samples in [0, 1] (1 = frame corner).
    mean : ndarray (N,)
        Mean natural-log attenuation profile.
    components : ndarray (K, N)
        Orthonormal principal components (rows).
    coefficients : ndarray (M, K)
        Each calibration's coefficients in the components.
    focal35 : ndarray (M,)
        35-mm-equivalent focal length (mm) of each calibration.
    fnumber : ndarray (M,)
        f-number of each calibration.
    reconstruction_ev : float
        Median RMS error (EV) of the calibrations' profiles rebuilt from K components.
    lenses : int
        Number of lenses the calibrations come from.
    reconstruction_by_k : tuple of float
        The same error with 1, 2, …, K components.
    """

    radii: np.ndarray
    mean: np.ndarray
    components: np.ndarray
    coefficients: np.ndarray
    focal35: np.ndarray
    fnumber: np.ndarray
    reconstruction_ev: float
    lenses: int
    reconstruction_by_k: tuple[float, ...] = ()

    @property
    def n_components(self) -> int:
        return int(self.components.shape[0])

    def truncated(self, k: int) -> LensFamily:
        """The family of the first ``k`` components (principal components nest: the
        first k of a K-component family are the k-component family)."""
        if not 1 <= k <= self.n_components:
            raise ModelError(f"a {self.n_components}-component family has no {k}-component truncation")
        if k == self.n_components:
            return self
        # kept, as the priors are: a grey frame's fit asks for the same truncation every time
        cache = self.__dict__.setdefault("_truncations", {})
        if k not in cache:
            by_k = self.reconstruction_by_k[:k]
            cache[k] = LensFamily(self.radii, self.mean, self.components[:k], self.coefficients[:, :k],
                                  self.focal35, self.fnumber, by_k[-1] if len(by_k) == k else math.nan,
                                  self.lenses, by_k)
        return cache[k]

    def profiles(self, rho: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Mean profile and components at radii ``rho`` (any shape; clipped to [0, 1]).

        Returns
        -------
        mean : ndarray, rho.shape
        basis : ndarray, rho.shape + (K,)
        """
        r = np.clip(np.asarray(rho, dtype=np.float64), 0.0, 1.0)
        flat = r.ravel()
        mean = np.interp(flat, self.radii, self.mean).reshape(r.shape)
        basis = np.stack([np.interp(flat, self.radii, c) for c in self.components], axis=-1)
        return mean, basis.reshape(r.shape + (self.n_components,))

    def log_profile(self, coef: np.ndarray, rho: np.ndarray) -> np.ndarray:
        """Natural-log attenuation ``mean + Σ coef_k component_k`` at radii ``rho``."""
        mean, basis = self.profiles(rho)
        return mean + basis @ np.asarray(coef, dtype=np.float64)

    def prior(self, focal35: float | None = None, fnumber: float | None = None,
              neighbours: int = NEIGHBOURS) -> tuple[np.ndarray, np.ndarray]:
        """Gaussian prior (mean, covariance) of the coefficients.

        Without EXIF, the spread of all calibrations. With a 35-mm-equivalent focal
        length and an f-number, the spread of the ``neighbours`` calibrations nearest
        in (log focal, log f-number): lenses like it.

        Returns
        -------
        mean : ndarray (K,)
        cov : ndarray (K, K)
        """
        # memoised per family: every frame of a batch (and the default's two fits of one
        # frame) asks for the same prior
        usable = bool(focal35 and fnumber and math.isfinite(focal35) and math.isfinite(fnumber)
                      and focal35 > 0 and fnumber > 0)
        key = (float(focal35), float(fnumber), neighbours) if usable else (None, None, neighbours)
        cache = self.__dict__.setdefault("_priors", {})
        if key not in cache:
            cache[key] = self._prior(*key)
        mean, cov = cache[key]
        return mean.copy(), cov.copy()

    def _prior(self, focal35: float | None, fnumber: float | None,
               neighbours: int) -> tuple[np.ndarray, np.ndarray]:
        c = self.coefficients
        if focal35 is not None and fnumber is not None:
            dist = np.hypot(np.log(self.focal35 / focal35), np.log(self.fnumber / fnumber))
            c = c[np.argsort(dist, kind="stable")[:max(neighbours, self.n_components + 2)]]
        # einsum, not BLAS: the same bits whatever the thread count (a batch's workers
        # and the main process must give identical results)
        mean = np.einsum("ij->j", c) / c.shape[0]
        dev = c - mean
        cov = np.einsum("ij,ik->jk", dev, dev) / (c.shape[0] - 1) + 1e-6 * np.eye(self.n_components)
        return mean, cov

    # ----------------------------------------------------------------- storage
    def to_dict(self) -> dict:
        return {
            "format": FORMAT,
            "lenses": self.lenses,
            "reconstruction_ev": self.reconstruction_ev,
            "reconstruction_by_k": [round(e, 6) for e in self.reconstruction_by_k],
            "radii": self.radii.round(6).tolist(),
            "mean": self.mean.round(8).tolist(),
            "components": self.components.round(8).tolist(),
            "coefficients": self.coefficients.round(5).tolist(),
            "focal35": self.focal35.round(3).tolist(),
            "fnumber": self.fnumber.round(3).tolist(),
        }

    @classmethod
    def from_dict(cls, d: dict) -> LensFamily:
        try:
            if d.get("format") != FORMAT:
                raise ModelError(f"lens family format {d.get('format')!r} is not {FORMAT}")
            fam = cls(
                radii=np.asarray(d["radii"], dtype=np.float64),
                mean=np.asarray(d["mean"], dtype=np.float64),
                components=np.atleast_2d(np.asarray(d["components"], dtype=np.float64)),
                coefficients=np.atleast_2d(np.asarray(d["coefficients"], dtype=np.float64)),
                focal35=np.asarray(d["focal35"], dtype=np.float64),
                fnumber=np.asarray(d["fnumber"], dtype=np.float64),
                reconstruction_ev=float(d["reconstruction_ev"]),
                lenses=int(d["lenses"]),
                reconstruction_by_k=tuple(float(e) for e in d.get("reconstruction_by_k", ())),
            )
        except (KeyError, TypeError, ValueError, AttributeError) as exc:
            raise ModelError(f"not a lens family: {exc}") from None
        n, k, m = fam.radii.size, fam.components.shape[0], fam.coefficients.shape[0]
        if (n < 2 or fam.mean.shape != (n,) or fam.components.shape != (k, n)
                or fam.coefficients.shape != (m, k) or fam.focal35.shape != (m,)
                or fam.fnumber.shape != (m,) or m < k + 2
                or not all(np.all(np.isfinite(a)) for a in (fam.radii, fam.mean, fam.components,
                                                             fam.coefficients))):
            raise ModelError("lens family arrays have inconsistent shapes or non-finite values")
        if not np.all(np.diff(fam.radii) > 0):  # the fits interpolate the profile between them
            raise ModelError("lens family radii do not increase")
        return fam

    def save(self, path: str | Path) -> None:
        atomic_write_text(Path(path), json.dumps(self.to_dict(), separators=(",", ":")))


def build_family(profiles: np.ndarray, focal35: np.ndarray, fnumber: np.ndarray, lenses: int,
                 n_components: int = N_COMPONENTS) -> LensFamily:
    """Principal components of log-attenuation profiles sampled on :data:`N_RADII` radii.

    Parameters
    ----------
    profiles : ndarray (M, N_RADII)
        Natural-log attenuation of each calibration at ``linspace(0, 1, N_RADII)``.
    focal35, fnumber : ndarray (M,)
    lenses : int
        Number of distinct lenses behind the profiles (reported only).
    n_components : int

    Returns
    -------
    LensFamily
    """
    p = np.asarray(profiles, dtype=np.float64)
    if p.ndim != 2 or p.shape[1] != N_RADII or p.shape[0] < n_components + 2:
        raise ModelError(f"need at least {n_components + 2} profiles of {N_RADII} samples, got {p.shape}")
    mean = p.mean(axis=0)
    _, _, vt = np.linalg.svd(p - mean, full_matrices=False)
    comps = vt[:n_components]
    # sign convention: a component's corner value is negative (more fall-off)
    comps = comps * np.where(comps[:, -1] > 0, -1.0, 1.0)[:, None]
    coef = (p - mean) @ comps.T
    by_k = []
    for k in range(1, n_components + 1):
        rebuilt = mean + coef[:, :k] @ comps[:k]
        by_k.append(float(np.median(np.sqrt(np.mean((rebuilt - p) ** 2, axis=1)) / math.log(2.0))))
    return LensFamily(
        radii=np.linspace(0.0, 1.0, N_RADII), mean=mean, components=comps, coefficients=coef,
        focal35=np.asarray(focal35, dtype=np.float64), fnumber=np.asarray(fnumber, dtype=np.float64),
        reconstruction_ev=by_k[-1], lenses=int(lenses), reconstruction_by_k=tuple(by_k),
    )


@lru_cache(maxsize=1)
def family_path() -> Path:
    """The shipped family file (found once: importlib's lookup took longer than the
    estimator's own use of the family, three times a frame)."""
    return Path(str(files("vigproc") / "data" / "lens_family.json"))


@lru_cache(maxsize=4)
def _load(path: str) -> LensFamily:
    try:
        text = Path(path).read_text(encoding="utf-8")
        return LensFamily.from_dict(json.loads(text))
    except (OSError, ValueError) as exc:
        raise ModelError(f"cannot read lens family {path}: {exc}") from None


#: The family standing in for the shipped one inside :func:`shipped_family_replaced`, or None.
_STAND_IN: LensFamily | None = None


@contextmanager
def shipped_family_replaced(family: LensFamily) -> Iterator[LensFamily]:
    """Within the block, :func:`profile_family` and :func:`default_family` answer ``family``.

    For a benchmark that scores the default estimate as the pipeline runs it (``vigproc
    bench real-frames``, part a) against a lens lensfun calibrated: the shipped family
    holds that lens's own calibrations, so the prior would know the answer; ``family``
    is one built without it (:func:`vigproc.stores.lensfun.lensfun_family` with
    ``exclude``). Process-wide (threads included), for one block at a time; the
    pipeline itself never uses it.

    Parameters
    ----------
    family : LensFamily

    Returns
    -------
    context manager yielding ``family``
    """
    global _STAND_IN
    before, _STAND_IN = _STAND_IN, family
    try:
        yield family
    finally:
        _STAND_IN = before


def profile_family() -> LensFamily:
    """The shipped lens family with all its components (:data:`PROFILE_COMPONENTS`):
    what lens profiles pool in."""
    if _STAND_IN is not None:
        return _STAND_IN
    return _load(str(family_path()))


def default_family() -> LensFamily:
    """The shipped lens family truncated to :data:`N_COMPONENTS`: what a grey frame's
    fit and the forensic tests use (every lens of the bundled lensfun database)."""
    # truncated() keeps its truncations: the same object every call
    return profile_family().truncated(N_COMPONENTS)
