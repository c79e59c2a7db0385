"""Natural-image prior on spatially averaged log-derivatives (Lyu 2010, Section 3.2).

For each operator t and step Δ, the mean D̄^t_Δ i over a block of a vignetting-free
log image follows a zero-mean generalized Laplacian (generalized Gaussian) density

    p(x) ∝ exp(−|x/γ_{t,Δ}|^{β_{t,Δ}})

whose (γ, β) are fitted by moment matching [Simoncelli & Adelson 1996]:
E|x|² / (E|x|)² = Γ(1/β) Γ(3/β) / Γ(2/β)²,  γ = σ · sqrt(Γ(1/β) / Γ(3/β)).

The paper fits it on 20,000 200×200 blocks of the van Hateren database; that database
is not available here, so the shipped prior is fitted on the vignetting-free natural
images of ``shared/data/natural`` (see :data:`SHIPPED_PRIOR` for the command).
"""

from __future__ import annotations

import functools
import json
import logging
import math
from dataclasses import dataclass
from importlib import resources
from pathlib import Path
from typing import Iterable

import numpy as np

from vigproc.atomic import atomic_write_text
from vigproc.errors import PriorError
from vigproc.core.pixels import log_image, luminance
from vigproc.core.stats import DELTA_MAX, OPERATORS, derivative_means

log = logging.getLogger(__name__)

SHIPPED_PRIOR = "prior_lyu2010.json"
SCHEMA = "vigproc.prior/1"
BETA_RANGE = (0.2, 8.0)


@dataclass(frozen=True)
class NaturalPrior:
    """Generalized-Laplacian parameters per (operator, Δ), arrays of shape (5, Δmax).

    Attributes
    ----------
    gamma, beta : ndarray
        Scale and shape of the zero-mean generalized Laplacian.
    mean, std : ndarray
        Sample mean and standard deviation of the block means (std gives the
        inverse-σ weights of Eqs. 17–19).
    n_blocks : int
    block : int
        Block side in pixels.
    source : str
        How the prior was made (the command and data).
    """

    gamma: np.ndarray
    beta: np.ndarray
    mean: np.ndarray
    std: np.ndarray
    n_blocks: int
    block: int
    source: str = ""

    @property
    def delta_max(self) -> int:
        return int(self.gamma.shape[1])

    def to_dict(self) -> dict:
        return {
            "schema": SCHEMA,
            "operators": list(OPERATORS),
            "delta_max": self.delta_max,
            "n_blocks": self.n_blocks,
            "block": self.block,
            "source": self.source,
            **{k: getattr(self, k).tolist() for k in ("gamma", "beta", "mean", "std")},
        }

    @classmethod
    def from_dict(cls, d: dict) -> NaturalPrior:
        try:
            if d.get("schema") != SCHEMA:
                raise PriorError(f"unknown prior schema {d.get('schema')!r}")
            arrs = {k: np.asarray(d[k], dtype=np.float64) for k in ("gamma", "beta", "mean", "std")}
        except (KeyError, TypeError, ValueError, AttributeError) as exc:
            raise PriorError(f"invalid prior: {exc!r}") from None
        shape = arrs["gamma"].shape
        if len(shape) != 2 or shape[0] != len(OPERATORS) or any(a.shape != shape for a in arrs.values()):
            raise PriorError(f"prior arrays must all be ({len(OPERATORS)}, Δmax), got {shape}")
        if not all(np.all(np.isfinite(a)) for a in arrs.values()) or np.any(arrs["gamma"] <= 0) or np.any(arrs["beta"] <= 0):
            raise PriorError("prior has non-finite or non-positive γ/β")
        return cls(n_blocks=int(d.get("n_blocks", 0)), block=int(d.get("block", 0)), source=str(d.get("source", "")), **arrs)

    def save(self, path: str | Path) -> None:
        atomic_write_text(Path(path), json.dumps(self.to_dict(), indent=1) + "\n")

    @classmethod
    def load(cls, path: str | Path) -> NaturalPrior:
        try:
            return cls.from_dict(json.loads(Path(path).read_text()))
        except (OSError, json.JSONDecodeError, RecursionError) as exc:  # RecursionError: absurdly nested
            raise PriorError(f"cannot read prior {path}: {exc}") from None


@functools.lru_cache(maxsize=1)
def default_prior() -> NaturalPrior:
    """The prior shipped with vigproc (fitted on shared/data/natural); read-only arrays."""
    text = resources.files("vigproc.data").joinpath(SHIPPED_PRIOR).read_text()
    prior = NaturalPrior.from_dict(json.loads(text))
    for a in (prior.gamma, prior.beta, prior.mean, prior.std):
        a.setflags(write=False)
    return prior


def ggd_moment_match(samples: np.ndarray) -> tuple[float, float]:
    """Fit a zero-mean generalized Gaussian by moment matching.

    Parameters
    ----------
    samples : ndarray, 1-D

    Returns
    -------
    gamma, beta : float

    References
    ----------
    E. P. Simoncelli and E. H. Adelson, "Noise removal via Bayesian wavelet coring",
    ICIP 1996 (moment matching of E|x| and E x²); Lyu 2010, Section 3.2.
    """
    x = np.asarray(samples, dtype=np.float64)
    m1 = float(np.mean(np.abs(x)))
    m2 = float(np.mean(x * x))
    if not (m1 > 0 and m2 > 0):
        raise PriorError("cannot fit a generalized Laplacian to all-zero samples")
    target = m2 / (m1 * m1)

    def ratio(b: float) -> float:
        # Γ(1/β)Γ(3/β)/Γ(2/β)², decreasing in β; log-gamma for stability
        return math.exp(math.lgamma(1 / b) + math.lgamma(3 / b) - 2 * math.lgamma(2 / b)) - target

    from scipy.optimize import brentq  # only when fitting: scipy.optimize takes 0.3 s to import

    lo, hi = BETA_RANGE
    if ratio(lo) < 0:
        beta = lo
    elif ratio(hi) > 0:
        beta = hi
    else:
        beta = brentq(ratio, lo, hi, xtol=1e-10)
    gamma = math.sqrt(m2 * math.exp(math.lgamma(1 / beta) - math.lgamma(3 / beta)))
    return gamma, beta


def block_derivative_means(
    lum: np.ndarray, rng: np.random.Generator, n_blocks: int, block: int = 200, delta_max: int = DELTA_MAX
) -> np.ndarray:
    """Derivative means of ``n_blocks`` random ``block``×``block`` blocks of a linear
    luminance image, each also mirrored left-right and up-down (the statistics are
    mirror-symmetric, so this doubles the samples without bias).

    Returns
    -------
    ndarray, shape (4·n_blocks, 5, Δmax)
    """
    h, w = lum.shape
    if h < block or w < block:
        return np.empty((0, len(OPERATORS), delta_max))
    logi = log_image(lum)
    out = []
    for _ in range(n_blocks):
        y = int(rng.integers(0, h - block + 1))
        x = int(rng.integers(0, w - block + 1))
        b = logi[y : y + block, x : x + block]
        for view in (b, b[:, ::-1], b[::-1, :], b[::-1, ::-1]):
            out.append(derivative_means(view, delta_max))
    return np.stack(out)


def fit_prior(
    images: Iterable[np.ndarray], *, blocks_per_image: int = 4, block: int = 200,
    delta_max: int = DELTA_MAX, seed: int = 0, source: str = "",
) -> NaturalPrior:
    """Fit the natural-image prior from vignetting-free linear images.

    Parameters
    ----------
    images : iterable of ndarray
        Linear images, H×W or H×W×C channels-last.
    blocks_per_image, block, delta_max, seed : int
    source : str
        Provenance recorded in the prior.

    Returns
    -------
    NaturalPrior
    """
    rng = np.random.default_rng(seed)
    chunks = [block_derivative_means(luminance(img), rng, blocks_per_image, block, delta_max) for img in images]
    samples = np.concatenate(chunks) if chunks else np.empty((0, len(OPERATORS), delta_max))
    if samples.shape[0] < 20:
        raise PriorError(f"need at least 20 blocks of {block}x{block} px to fit a prior, got {samples.shape[0]}")
    gamma = np.empty((len(OPERATORS), delta_max))
    beta = np.empty_like(gamma)
    for t in range(len(OPERATORS)):
        for d in range(delta_max):
            gamma[t, d], beta[t, d] = ggd_moment_match(samples[:, t, d])
    log.info("fitted prior on %d blocks", samples.shape[0])
    return NaturalPrior(
        gamma=gamma, beta=beta, mean=samples.mean(axis=0), std=samples.std(axis=0),
        n_blocks=int(samples.shape[0]), block=block, source=source,
    )
