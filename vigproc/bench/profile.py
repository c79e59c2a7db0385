"""Profile accuracy versus number of frames (issue 4's protocol).

For each lens of :func:`vigproc.lensfun.bench_lenses` (widest aperture), frames are
natural images multiplied by the lens's "pa" field; each frame is estimated on its
own (the default estimator's fit, kept even when it would fall back, with its
covariance), and the per-frame estimates are pooled three ways after n frames:

* ``information``: inverse-variance pooling of the normalised parameters
  (:func:`vigproc.profiles.pool_information`, what the store does);
* ``mean-theta``: the plain mean of the normalised parameters;
* ``mean-field``: the mean of the per-frame log-fields (field-space pooling, the
  best a refit of the pooled field could do);
* ``joint``: one robust fit to the first n frames' data together
  (:func:`vigproc.robust.estimate_robust_joint`), the joint multi-frame fit;
* ``store``: what the profile store holds after learning the n frames one by one
  with their evidence (:meth:`vigproc.profiles.ProfileStore.learn`: information sums,
  then the debiased mean of centred fits of :mod:`vigproc.pooling`), in a temporary
  store.

The error is the RMS over the frame of log2(φ̂/φ), in EV.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Callable, Sequence

import numpy as np

from vigproc.errors import ModelError
from vigproc.lensfun import bench_lenses, pa_field
from vigproc.model import VignettingModel

POOLINGS = ("information", "mean-theta", "mean-field", "joint", "store")


@dataclass
class ProfileAccuracy:
    pooling: str
    n_frames: int
    n_lenses: int
    median_ev: float
    p90_ev: float


@dataclass
class TrustResult:
    """When the store's profiles became trusted (``--profile auto`` applies them)."""

    n_lenses: int
    n_trusted: int  # lenses whose profile became trusted within max_frames
    max_frames: int
    median_frames: float  # frames learned until then
    median_ev: float  # error of the profile at that moment
    p90_ev: float
    single_frame_median_ev: float  # each frame estimated alone, as applied


def _rms_ev(x: np.ndarray) -> float:
    return float(np.sqrt(np.mean(x * x)) / math.log(2.0))


def _learned_fields(frames, fits, li, w, h):
    """(n, log field of the stored profile after n frames, trusted?) through a real
    store, for every n; ``fits`` are the frames' estimates already made (None: no
    usable fit)."""
    import tempfile
    from pathlib import Path

    from vigproc.estimate import frame_evidence
    from vigproc.profiles import ProfileKey, ProfileStore, aspect_label

    key = ProfileKey(f"bench|lens|{li}", "any", "any", aspect_label(w / h))
    with tempfile.TemporaryDirectory(prefix="vigproc-bench-") as tmp, \
            ProfileStore(Path(tmp) / "profiles.sqlite") as st:
        for j, (f, m) in enumerate(zip(frames, fits)):
            if m is None:
                continue
            p = st.learn(key, m, frame_id=f"frame{j:04d}", evidence=frame_evidence(f, channel_axis=None))
            yield j + 1, p.model(w, h).log_field((h, w)), p.trusted


def run(
    images: Sequence[np.ndarray], estimate: Callable[[np.ndarray], VignettingModel],
    n_lenses: int = 20, counts: Sequence[int] = (1, 5, 20),
    joint: Callable[[list[np.ndarray]], VignettingModel] | None = None,
    store: bool = False,
) -> list[ProfileAccuracy] | tuple[list[ProfileAccuracy], TrustResult]:
    """Pooled-profile errors after each of ``counts`` frames, per pooling method
    (``joint`` only when a joint estimator is given, ``store`` only when asked; then
    also when each lens's stored profile became trusted, as a :class:`TrustResult`)."""
    from vigproc.profiles import denormalise, normalise, pool_information, pool_mean

    nmax = max(counts)
    errors: dict[tuple[str, int], list[float]] = {(p, n): [] for p in POOLINGS for n in counts}
    trust: list[tuple[int, float] | None] = []  # per lens: (frames until trusted, error then)
    single: list[float] = []  # error of each frame's own estimate, as applied (fall-back included)
    for li, (_lens, pa) in enumerate(bench_lenses(n_lenses)):
        h, w = images[0].shape
        true_log = np.log(pa_field((h, w), pa.k1, pa.k2, pa.k3))
        thetas, covs, fields, frames, fits, applied = [], [], [], [], [], []
        # lens li takes nmax consecutive images from a start of its own; once the
        # lenses have to share images, the starts are also shifted by one per
        # round, so that no two lenses see the same images in the same order
        start = (li * nmax) % len(images) + (li * nmax) // len(images)
        for j in range(nmax):
            im = images[(start + j) % len(images)]
            frames.append(im * np.exp(true_log))
            m = estimate(frames[-1])
            applied.append(m)
            m = m.candidate if m.candidate is not None else m
            fits.append(m if m.covariance is not None else None)
            if m.covariance is None:  # an identity model without a fit: no evidence
                continue
            th, cov, _ = normalise(m)
            thetas.append(th)
            covs.append(cov)
            fields.append(m.log_field((h, w)))
        for n in counts:
            if len(thetas) < n:
                continue
            th_i, _ = pool_information(thetas[:n], covs[:n])
            for name, th in (("information", th_i), ("mean-theta", pool_mean(thetas[:n]))):
                try:
                    lf = denormalise(th, None, w, h).log_field((h, w))
                except ModelError:  # an invalid pooled model counts as no correction
                    lf = np.zeros((h, w))
                errors[(name, n)].append(_rms_ev(lf - true_log))
            errors[("mean-field", n)].append(_rms_ev(np.mean(fields[:n], axis=0) - true_log))
        for n in counts:
            if joint is not None and len(frames) >= n:
                errors[("joint", n)].append(_rms_ev(joint(frames[:n]).log_field((h, w)) - true_log))
        if store:
            first = None
            for n, lf, trusted in _learned_fields(frames, fits, li, w, h):
                err = _rms_ev(lf - true_log)
                if n in counts:
                    errors[("store", n)].append(err)
                if trusted and first is None:
                    first = (n, err)
            trust.append(first)
            single.extend(_rms_ev(m.log_field((h, w)) - true_log) for m in applied)
    out = []
    for p in POOLINGS:
        for n in counts:
            e = errors[(p, n)]
            if e:
                out.append(ProfileAccuracy(p, n, len(e), float(np.median(e)), float(np.percentile(e, 90))))
    if store:
        reached = [t for t in trust if t is not None]
        return out, TrustResult(
            n_lenses=len(trust), n_trusted=len(reached), max_frames=nmax,
            median_frames=float(np.median([t[0] for t in reached])) if reached else math.nan,
            median_ev=float(np.median([t[1] for t in reached])) if reached else math.nan,
            p90_ev=float(np.percentile([t[1] for t in reached], 90)) if reached else math.nan,
            single_frame_median_ev=float(np.median(single)))
    return out
