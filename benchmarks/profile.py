"""Profile accuracy versus number of frames (issue 4's protocol).

For each lens of :func:`vigproc.stores.lensfun.diverse_lenses` (widest aperture), frames are
natural images multiplied by the lens's "pa" field; each frame is estimated on its
own (the default estimator's fit, kept even when it would fall back, with its
covariance), and the per-frame estimates are pooled three ways after n frames:

* ``information``: inverse-variance pooling of the normalised parameters
  (:func:`vigproc.stores.profiles.pool_information`, what the store does);
* ``mean-theta``: the plain mean of the normalised parameters;
* ``mean-field``: the mean of the per-frame log-fields (field-space pooling, the
  best a refit of the pooled field could do);
* ``joint``: one robust fit to the first n frames' data together
  (:func:`vigproc.core.robust.estimate_robust_joint`), the joint multi-frame fit;
* ``store``: what the profile store holds after learning the n frames one by one
  with their evidence (:meth:`vigproc.stores.profiles.ProfileStore.learn`: information sums,
  then the debiased mean of centred fits of :mod:`vigproc.core.pooling`), in a temporary
  store.

The error is the RMS over the frame of log2(φ̂/φ), in EV.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Callable, Sequence

import numpy as np

from vigproc.errors import ModelError
from vigproc.stores.lensfun import diverse_lenses, pa_field
from vigproc.core.model import VignettingModel

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

    from vigproc.core.estimate import frame_evidence
    from vigproc.stores.profiles import ProfileKey, ProfileStore, aspect_label

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
    from vigproc.stores.profiles import denormalise, normalise, pool_information, pool_mean

    nmax = max(counts)
    errors: dict[tuple[str, int], list[float]] = {(p, n): [] for p in POOLINGS for n in counts}
    trust: list[tuple[int, float] | None] = []  # per lens: (frames until trusted, error then)
    single: list[float] = []  # error of each frame's own estimate, as applied (fall-back included)
    for li, (_lens, pa) in enumerate(diverse_lenses(n_lenses)):
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


# --------------------------------------------------------------------------- #
# the clean protocol (issue 18): vignetting-free bases × lensfun fields
# --------------------------------------------------------------------------- #


@dataclass
class CleanProfileRow:
    """One way of pooling, after ``n_frames`` frames of each lens (clean protocol)."""

    method: str
    n_frames: int
    n_lenses: int
    median_ev: float
    p90_ev: float
    within_1sigma: float = math.nan  # lenses whose error is within the stated 1σ
    within_2sigma: float = math.nan


@dataclass
class CleanTrust:
    """When the store's profiles became trusted, and whether trust held its bound."""

    bound_ev: float
    n_lenses: int
    n_trusted: int  # lenses trusted within the frames shown
    median_frames: float  # frames learned until trusted
    share_within_bound: float  # trusted lenses whose error was then below the bound
    share_within_bound_later: float  # trusted profiles (every later count) below it


def run_clean(bases: Sequence[np.ndarray], fields: Sequence, family, counts: Sequence[int] = (1, 5, 20, 50),
              peer: Callable | None = None, seed: int = 0, orders: int = 1) -> tuple[list[CleanProfileRow], CleanTrust]:
    """Profiles learned through a real store on the clean protocol.

    Each lens (``fields``: :func:`benchmarks.clean.lens_fields`) sees the bases in
    ``orders`` orders of its own (seeded by ``seed``, the lens and the order; each
    order a new store), up to ``max(counts)`` frames; the 51 bases are the same for
    every lens, so one order per lens leaves the figures at the mercy of which
    scenes come first. Bases are H×W (grey) or H×W×3 (colour, channels last).
    Every frame is estimated and learned as ``vigproc profile learn`` does
    (:func:`vigproc.core.estimate.estimate_with_evidence`, then
    :meth:`~vigproc.stores.profiles.ProfileStore.learn` with its evidence), in a store
    pooling in ``family`` (built without the test lenses). Error: the RMS of
    log2(profile/true field) about its mean (a gain is free), EV; median and p90 over
    the lenses. Beside it: each frame estimated alone by the default estimator, and
    the published peer's per-frame fields pooled by their point-wise median (given
    the luminance). Rows and trust count lens × order runs.
    """
    import tempfile
    from pathlib import Path

    from benchmarks.clean import gain_free_ev, vignetted
    from vigproc.core.estimate import estimate, estimate_with_evidence
    from vigproc.stores.profiles import TRUSTED_BOUND_EV, ProfileKey, ProfileStore, aspect_label

    from vigproc.core.pixels import luminance

    h, w = bases[0].shape[:2]
    axis = -1 if bases[0].ndim == 3 else None
    nmax = min(max(counts), len(bases))
    counts = [n for n in counts if n <= nmax]
    store_err: dict[int, list[float]] = {n: [] for n in counts}
    store_z: dict[int, list[float]] = {n: [] for n in counts}
    peer_err: dict[int, list[float]] = {n: [] for n in counts}
    single: list[float] = []
    trusted_at: list[tuple[int, float] | None] = []
    later: list[bool] = []
    runs = [(li, fld, o) for li, fld in enumerate(fields) for o in range(orders)]
    for li, fld, o in runs:
        true_log = fld.log_field
        # order 0 is the single order of earlier runs (seed + lens)
        order = np.random.default_rng(seed + li + 1000 * o).permutation(len(bases))[:nmax]
        key = ProfileKey(f"bench|lens|{li}", "any", "any", aspect_label(w / h))
        peer_fields, lens_single, first = [], [], None
        with tempfile.TemporaryDirectory(prefix="vigproc-bench-") as tmp, \
                ProfileStore(Path(tmp) / "profiles.sqlite", family=family) as st:
            for n, j in enumerate(order, 1):
                frame = vignetted(bases[j], true_log)
                lens_single.append(gain_free_ev(estimate(frame, channel_axis=axis).log_field((h, w)) - true_log))
                m, evidence = estimate_with_evidence(frame, channel_axis=axis)
                fit = m.candidate if m.candidate is not None else m
                p = st.learn(key, fit, frame_id=f"frame{j:04d}", evidence=evidence)
                err = gain_free_ev(p.model(w, h).log_field((h, w)) - true_log)
                if p.trusted:
                    if first is None:
                        first = (n, err)
                    if n in counts:
                        later.append(err <= TRUSTED_BOUND_EV)
                if peer is not None:
                    peer_fields.append(peer(frame if axis is None else luminance(frame)).log_field)
                if n in counts:
                    store_err[n].append(err)
                    store_z[n].append(err / p.field_sigma_ev if p.field_sigma_ev else math.inf)
                    if peer is not None:
                        peer_err[n].append(gain_free_ev(np.median(peer_fields, axis=0) - true_log))
        single.append(float(np.median(lens_single)))
        trusted_at.append(first)

    def row(name, errs, n, zs=None):
        e = np.asarray(errs)
        z = np.asarray(zs) if zs is not None else None
        return CleanProfileRow(name, n, e.size, float(np.median(e)), float(np.percentile(e, 90)),
                               float(np.mean(z <= 1)) if z is not None else math.nan,
                               float(np.mean(z <= 2)) if z is not None else math.nan)

    rows = [row("single frame (default)", single, 1)]
    rows += [row("store", store_err[n], n, store_z[n]) for n in counts]
    if peer is not None:
        rows += [row("rgs-c++ median", peer_err[n], n) for n in counts]
    reached = [t for t in trusted_at if t is not None]
    trust = CleanTrust(
        TRUSTED_BOUND_EV, len(trusted_at), len(reached),
        float(np.median([t[0] for t in reached])) if reached else math.nan,
        float(np.mean([t[1] <= TRUSTED_BOUND_EV for t in reached])) if reached else math.nan,
        float(np.mean(later)) if later else math.nan)
    return rows, trust


# --------------------------------------------------------------------------- #
# between bins: a lens's profiles interpolated to a held-out setting
# --------------------------------------------------------------------------- #


@dataclass
class InterpolationRow:
    """Errors (EV) at held-out calibrations of lensfun's zoom lenses, by the way of
    answering for a setting between a lens's profiles."""

    method: str
    axis: str  # "focal" or "aperture": what lies between the neighbours
    n_points: int
    median_ev: float
    p90_ev: float
    within_1sigma: float = math.nan
    within_2sigma: float = math.nan


def run_interpolation(width: int = 480, height: int = 320, max_points: int = 400) -> list[InterpolationRow]:
    """A lens's profiles answering between their bins, on lensfun's own calibrations.

    For every lens of the bundled lensfun database with calibrations (at infinity
    focus) at three or more focal lengths of one aperture (or three or more apertures
    of one focal length), each interior calibration is held out; the lens's other
    calibrations become trusted profiles in a temporary store (each with a stated σ
    of 0), and the store's :meth:`~vigproc.stores.profiles.ProfileStore.lookup` answers for
    the held-out setting. Error: the RMS of log2(answer / held-out calibration) about
    its mean. Beside it: the nearest neighbour (the profile of the nearest bin along
    the axis, what a store without interpolation could give at best) and lensfun's
    own interpolation of the remaining calibrations (:func:`vigproc.stores.lensfun.interpolate_pa`).
    Points whose bin coincides with a neighbour's are skipped.
    """
    import tempfile
    from dataclasses import replace
    from pathlib import Path

    from benchmarks.clean import gain_free_ev
    from vigproc.io.exif import LensKey
    from vigproc.stores.lensfun import LensfunLens, interpolate_pa, load_lenses
    from vigproc.core.normalised import denormalise, fit_model_to_field, normalise
    from vigproc.stores.profiles import Profile, ProfileKey, ProfileStore, aperture_bin, focal_bin

    shape = (height, width)
    errs: dict[tuple[str, str], list[float]] = {}
    zs: dict[str, list[float]] = {"focal": [], "aperture": []}
    points = 0
    with tempfile.TemporaryDirectory(prefix="vigproc-bench-") as tmp:
        for li, lens in enumerate(load_lenses()):
            entries = [v for v in lens.vignetting if v.distance >= 1000]
            thetas: dict[int, np.ndarray] = {}  # each calibration written as a profile once

            def theta(v) -> np.ndarray:
                if id(v) not in thetas:
                    m, _ = fit_model_to_field(np.log(pa_field((64, 96), v.k1, v.k2, v.k3)), width, height)
                    thetas[id(v)] = normalise(m)[0]
                return thetas[id(v)]

            for axis in ("focal", "aperture"):
                groups: dict[float, list] = {}
                for v in entries:
                    groups.setdefault(v.aperture if axis == "focal" else v.focal, []).append(v)
                for fixed, row in groups.items():
                    row = sorted(row, key=lambda v: v.focal if axis == "focal" else v.aperture)
                    for k in range(1, len(row) - 1):
                        if points >= max_points:
                            break
                        held = row[k]
                        others = [v for v in entries if v is not held]
                        bins = {(focal_bin(v.focal), aperture_bin(v.aperture)) for v in others}
                        key_bins = (focal_bin(held.focal), aperture_bin(held.aperture))
                        if key_bins in bins:
                            continue
                        truth = np.log(pa_field(shape, held.k1, held.k2, held.k3))
                        db = Path(tmp) / f"l{li}-{axis}-{k}-{fixed}.sqlite"
                        lens_key = LensKey(make="bench", model="bench", lens=f"{lens.maker} {lens.model}",
                                           focal_mm=held.focal, fnumber=held.aperture)
                        with ProfileStore(db) as st:
                            for v in others:
                                key = ProfileKey.from_lens(replace(lens_key, focal_mm=v.focal, fnumber=v.aperture),
                                                           width, height)
                                st.put(Profile(key=key, theta=theta(v), n_frames=1, provenance="lensfun",
                                               trusted=True, field_sigma_ev=0.0))
                            got = st.lookup(lens_key, width, height)
                        if got is None or not got.notes.startswith("interpolated"):
                            continue
                        points += 1
                        e = gain_free_ev(got.model(width, height).log_field(shape) - truth)
                        errs.setdefault(("store interpolation", axis), []).append(e)
                        if got.field_sigma_ev:
                            zs[axis].append(e / got.field_sigma_ev)
                        near = min((row[k - 1], row[k + 1]), key=lambda v: abs(math.log(
                            (v.focal / held.focal) if axis == "focal" else (v.aperture / held.aperture))))
                        nearest = denormalise(theta(near), None, width, height)  # the same conversion
                        errs.setdefault(("nearest neighbour", axis), []).append(
                            gain_free_ev(nearest.log_field(shape) - truth))
                        rest = LensfunLens(lens.maker, lens.model, lens.mounts, lens.crop_factor, lens.aspect_ratio,
                                           tuple(others), lens.focal_norm_range)
                        pa = interpolate_pa(rest, held.focal, held.aperture, 1000.0)
                        errs.setdefault(("lensfun interpolate_pa", axis), []).append(
                            gain_free_ev(np.log(pa_field(shape, pa.k1, pa.k2, pa.k3)) - truth))
    rows = []
    for (method, axis), e in sorted(errs.items(), key=lambda kv: (kv[0][1], kv[0][0])):
        a = np.asarray(e)
        z = np.asarray(zs[axis]) if method == "store interpolation" and zs[axis] else None
        rows.append(InterpolationRow(method, axis, a.size, float(np.median(a)), float(np.percentile(a, 90)),
                                     float(np.mean(z <= 1)) if z is not None else math.nan,
                                     float(np.mean(z <= 2)) if z is not None else math.nan))
    return rows


# --------------------------------------------------------------------------- #
# flat-field calibration: a few frames of a white wall
# --------------------------------------------------------------------------- #


@dataclass
class FlatFieldRow:
    """A profile learned from three frames of one flat field (a white wall)."""

    name: str
    method: str
    error_ev: float  # gain-free RMS of log2(profile / true field), over the frame's blocks
    uncorrected_ev: float
    sigma_ev: float
    trusted: bool
    grid_error_ev: float = math.nan  # the same for the profile's grid field (flat-field: what it corrects by)


def run_flat_field(pairs: Sequence[tuple[np.ndarray, np.ndarray, str]], methods: Sequence[str] = ("flat-field",
                   "default"), frames: int = 3, seed: int = 0) -> list[FlatFieldRow]:
    """Profiles learned as ``vigproc profile learn --method M`` does from ``frames``
    shots of a flat field.

    ``pairs``: (vignetted flat frame, the flat frame without vignetting, name), linear
    luminance (Zheng et al.'s white pairs); the true field is their ratio. The shots
    are the vignetted frame under a different gentle light each (a linear ramp of up
    to ±3 % across the frame in a random direction, as a wall is never evenly lit) and
    1 % noise. Evidence methods pool the frames' lens-family fits (centred); others,
    such as ``flat-field``, their per-frame estimates (information form).
    """
    import tempfile
    from pathlib import Path

    from benchmarks.real import _blocks
    from vigproc.core.estimate import EVIDENCE_METHODS, estimate, estimate_with_evidence
    from vigproc.pipeline.flat_grid import frame_grid
    from vigproc.stores.profiles import ProfileKey, ProfileStore, aspect_label

    rng = np.random.default_rng(seed)
    out = []
    for vig, clean, name in pairs:
        h, w = vig.shape
        bc, bv = _blocks(clean), _blocks(vig)
        ok = (bc > 0.02 * np.median(bc)) & (bv > 0)
        true = np.log2(np.where(ok, bv, 1.0) / np.where(ok, bc, 1.0))
        yy, xx = np.mgrid[0:h, 0:w]
        shots = []
        for _ in range(frames):
            a = rng.uniform(0, 2 * math.pi)
            ramp = 1 + 0.03 * rng.uniform(-1, 1) * ((xx / w - 0.5) * math.cos(a) + (yy / h - 0.5) * math.sin(a)) * 2
            shots.append(np.clip(vig * ramp * (1 + 0.01 * rng.standard_normal((h, w))), 1e-6, None))
        for method in methods:
            key = ProfileKey(f"bench|flat|{name}", "any", "any", aspect_label(w / h))
            with tempfile.TemporaryDirectory(prefix="vigproc-bench-") as tmp, \
                    ProfileStore(Path(tmp) / "profiles.sqlite") as st:
                p = None
                for i, shot in enumerate(shots):
                    if method in EVIDENCE_METHODS:
                        m, evidence = estimate_with_evidence(shot, channel_axis=None, method=method)
                    else:
                        m, evidence = estimate(shot, method, channel_axis=None), None
                    fit = m.candidate if m.candidate is not None else m
                    # as learn mode does: a flat-field frame's grid field goes with it
                    grid = frame_grid(shot, fit) if method == "flat-field" else None
                    p = st.learn(key, fit, frame_id=f"shot{i}", evidence=evidence, grid=grid)
                model = p.model(w, h)
                est = np.log2(np.maximum(_blocks(model.field((h, w))), 1e-12))
                grid_err = math.nan
                if getattr(model, "grid", None) is not None:  # the field the profile corrects by
                    g = _blocks(np.exp(model.grid.log_fields(w, h)[..., 1]))
                    dg = np.log2(np.maximum(g, 1e-12))[ok] - true[ok]
                    grid_err = float(np.sqrt(np.mean((dg - dg.mean()) ** 2)))
            d = est[ok] - true[ok]
            t = true[ok] - true[ok].mean()
            out.append(FlatFieldRow(name, method, float(np.sqrt(np.mean((d - d.mean()) ** 2))),
                                    float(np.sqrt(np.mean(t * t))), float(p.field_sigma_ev or math.nan), p.trusted,
                                    grid_err))
    return out
