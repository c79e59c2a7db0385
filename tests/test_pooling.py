"""Pooling a lens's frames into its profile (vigproc.core.pooling) and the frames' evidence."""

import io
import json
import math

import numpy as np
import pytest

from vigproc.errors import ModelError
from vigproc.core.estimate import frame_evidence
from vigproc.core.family_fit import FrameCoefficients, frame_coefficients
from vigproc.core.lensfamily import N_COMPONENTS, PROFILE_COMPONENTS, default_family, profile_family
from vigproc.stores.lensfun import diverse_lenses, pa_field
from vigproc.core.pooling import (SIGMA_SCALE, frame_fit, pool_family, pooled_coefficients, scene_scatter,
                                  t_location)
from vigproc.core.robust import RobustSettings, evidence_copy, working_copy
from vigproc.core.scene import default_scene_falloff

from conftest import chromatic_glow, coloured_scene, textured

H, W = 160, 240


def _gain_free_ev(x: np.ndarray) -> float:
    return float(np.std(x) / np.log(2))


def _fits(frames):
    return [frame_fit(evidence_copy(frame_evidence(f, channel_axis=None))) for f in frames]


def _lens(i: int = 0) -> np.ndarray:
    _, pa = diverse_lenses(i + 1)[i]
    return np.log(pa_field((H, W), pa.k1, pa.k2, pa.k3))


def test_pooled_profile_recovers_the_lens():
    lens = _lens()
    frames = [textured(H, W, seed=70 + i, contrast=0.05) * np.exp(lens) for i in range(5)]
    pooled = pool_family(_fits(frames), W, H)
    assert pooled.method == "profile-pooled" and pooled.covariance is not None
    assert pooled.center == (0.0, 0.0)
    err = _gain_free_ev(pooled.log_field((H, W)) - lens)
    assert err < 0.03 and err < 0.2 * _gain_free_ev(lens), err
    assert 0 < pooled.quality.field_sigma_ev < 0.2


def test_a_fooled_frame_does_not_pull_the_profile():
    """One frame of five whose scene has a strong fall-off of its own (a lit centre):
    the median leaves it out, where a mean would move by a fifth of it."""
    lens = _lens()
    frames = [textured(H, W, seed=170 + i, contrast=0.05) * np.exp(lens) for i in range(5)]
    clean = pool_family(_fits(frames), W, H).log_field((H, W))
    from benchmarks.synthetic import table1_model

    frames[2] = frames[2] * np.exp(table1_model(1).log_field((H, W)))  # 0.84 EV of "scene"
    fooled = pool_family(_fits(frames), W, H).log_field((H, W))
    assert _gain_free_ev(fooled - clean) < 0.02
    assert _gain_free_ev(fooled - lens) < 0.04


def test_the_frame_fit_is_equivariant():
    """A field of the family added to a frame moves its coefficients by exactly the
    field's (no prior pulls them): what lets frames' errors average away."""
    fam = profile_family()
    base = textured(H, W, seed=11, contrast=0.05)
    c = np.array([3.0, -0.5, 0.2])
    rho = np.hypot(*np.meshgrid(np.arange(W) - (W - 1) / 2, np.arange(H) - (H - 1) / 2)) \
        / math.hypot((W - 1) / 2, (H - 1) / 2)
    field = np.exp(fam.log_profile(c, rho) - fam.log_profile(np.zeros(3), rho))
    a, b = (frame_fit(working_copy(x, RobustSettings())) for x in (base, base * field))
    np.testing.assert_allclose(b.coefficients - a.coefficients, c, atol=0.05)


def test_pooled_uncertainty_is_the_medians():
    fit = _fits([textured(H, W, seed=95, contrast=0.05) * np.exp(_lens())])[0]
    c1, s1 = pooled_coefficients([fit])
    np.testing.assert_allclose(c1, fit.coefficients)
    np.testing.assert_allclose(s1, SIGMA_SCALE**2 * math.pi / 2 * fit.covariance)
    # n identical frames: no scatter, the frames' own covariance shrinks as 1/n (and
    # its weight as the scatter's grows)
    _, s4 = pooled_coefficients([fit] * 4)
    np.testing.assert_allclose(s4, s1 * (1 - 3 / 8) / 4)


def test_pooling_needs_frames_of_one_family():
    with pytest.raises(ModelError, match="no frames"):
        pool_family([], W, H)
    two = FrameCoefficients(np.zeros(2), np.eye(2), 100)
    three = FrameCoefficients(np.zeros(3), np.eye(3), 100)
    with pytest.raises(ModelError, match="different lens families"):
        pooled_coefficients([two, three])
    with pytest.raises(ModelError, match="2 coefficients"):
        pool_family([two], W, H)


def test_the_t_location_weighs_down_a_far_frame_and_averages_the_rest():
    """Under the scenes' scatter, frames that agree are averaged (not ranked, as by a
    median), and one far out in that scatter's units barely moves the centre."""
    S = np.diag([1.0, 0.25])
    close = np.array([[0.1, 0.0], [-0.2, 0.1], [0.3, -0.1], [0.0, 0.05]])
    np.testing.assert_allclose(t_location(close, S * 100), close.mean(axis=0), atol=1e-3)  # all near: a mean
    fooled = np.vstack([close, [[12.0, -4.0]]])
    m = t_location(fooled, S)
    assert np.linalg.norm(m - close.mean(axis=0)) < 0.1
    assert np.linalg.norm(fooled.mean(axis=0) - close.mean(axis=0)) > 2  # what a mean would do
    np.testing.assert_allclose(t_location(fooled + [1.0, -2.0], S), m + [1.0, -2.0], atol=1e-6)  # equivariant
    np.testing.assert_array_equal(t_location(close[:1], S), close[0])


def test_the_scenes_scatter_reads_in_any_family():
    """The shipped scatter is a log-profile covariance: a family whose components are the
    shipped ones reordered and negated reads the same scatter, rotated alike."""
    from dataclasses import replace as dc_replace

    fam = profile_family()
    S = scene_scatter(fam)
    assert S.shape == (fam.n_components,) * 2 and np.all(np.linalg.eigvalsh(S) > 0)
    R = -np.eye(fam.n_components)[::-1]
    turned = dc_replace(fam, components=R @ fam.components, coefficients=fam.coefficients @ R.T)
    np.testing.assert_allclose(scene_scatter(turned), R @ S @ R.T, atol=1e-9)
    np.testing.assert_allclose(scene_scatter(fam.truncated(2)), S[:2, :2], atol=1e-9)
    # a family sampled at other radii reads the same scatter through the log profile
    fine = np.linspace(0.0, 1.0, 2 * fam.radii.size - 1)
    resampled = dc_replace(fam, radii=fine, mean=np.interp(fine, fam.radii, fam.mean),
                           components=np.array([np.interp(fine, fam.radii, c) for c in fam.components]))
    C = resampled.components
    G = C @ C.T  # not orthonormal at the new radii: Σ = C F Cᵀ with F the field covariance
    np.testing.assert_allclose(scene_scatter(resampled), G @ S @ G, rtol=1e-6, atol=1e-9)
    with pytest.raises(ModelError, match="scatter"):
        pooled_coefficients([FrameCoefficients(np.zeros(3), np.eye(3), 100)], np.eye(2))
    # a singular scatter (a family with more components than it was measured in): the median
    fits = [FrameCoefficients(np.array([v, 0.0, 0.0]), np.eye(3), 100) for v in (0.0, 1.0, 10.0)]
    c, _ = pooled_coefficients(fits, np.diag([1.0, 1.0, 0.0]))
    np.testing.assert_array_equal(c, [1.0, 0.0, 0.0])


def test_a_blank_frame_has_no_fit():
    flat = np.zeros((H, W))
    assert frame_coefficients(flat, np.zeros((H, W), bool), np.arange(W) - W / 2, np.arange(H) - H / 2,
                              W, H) is None


def test_the_shipped_family_nests():
    """Profiles pool in all the shipped components; a single frame uses the first two,
    which are exactly the two-component family."""
    full, single = profile_family(), default_family()
    assert full.n_components == PROFILE_COMPONENTS and single.n_components == N_COMPONENTS
    np.testing.assert_array_equal(single.components, full.components[:N_COMPONENTS])
    np.testing.assert_array_equal(single.coefficients, full.coefficients[:, :N_COMPONENTS])
    errs = full.reconstruction_by_k
    assert len(errs) == PROFILE_COMPONENTS and list(errs) == sorted(errs, reverse=True)
    assert single.reconstruction_ev == errs[N_COMPONENTS - 1] < 0.01


def test_evidence_is_the_copy_before_the_scene_prior():
    img = textured(H, W, seed=90, contrast=0.05)
    wc = evidence_copy(frame_evidence(img, channel_axis=None))
    raw = working_copy(img, RobustSettings())
    np.testing.assert_allclose(wc.L[wc.valid], raw.L[raw.valid], atol=1e-5)  # stored as float32


def test_format_1_evidence_gets_the_scene_prior_back():
    """Evidence written before session 5 held the copy divided by the scene prior."""
    img = textured(H, W, seed=91, contrast=0.05)
    raw = working_copy(img, RobustSettings())
    divided = raw.L - default_scene_falloff().log_field(raw.xs, raw.ys)
    buf = io.BytesIO()
    meta = json.dumps({"format": "vigproc.robust-evidence/1", "radius": raw.radius, "width": W, "height": H})
    np.savez_compressed(buf, L=divided.astype(np.float32), valid=raw.valid, xs=raw.xs, ys=raw.ys,
                        meta=np.frombuffer(meta.encode(), dtype=np.uint8))
    wc = evidence_copy(buf.getvalue())
    np.testing.assert_allclose(wc.L[wc.valid], raw.L[raw.valid], atol=1e-5)


def _rgb(seed: int, lens: np.ndarray) -> np.ndarray:
    return np.stack([textured(H, W, seed=seed + c, contrast=0.05) for c in range(3)], axis=-1) * np.exp(lens)[..., None]


def test_colour_evidence_holds_each_channels_copy():
    img = _rgb(300, _lens())
    wc = evidence_copy(frame_evidence(img))
    assert wc.channels.shape == (3,) + wc.L.shape and wc.channels_valid.shape == wc.channels.shape
    assert not np.any(wc.channels_valid & ~wc.valid)  # a channel's bins are among the luminance's
    for c in range(3):
        raw = working_copy(img[..., c], RobustSettings())
        both = wc.channels_valid[c] & raw.valid
        assert both.sum() > 0.9 * raw.valid.sum()
        np.testing.assert_allclose(wc.channels[c][both], raw.L[both], atol=1e-5)
    assert evidence_copy(frame_evidence(img[..., 1], channel_axis=None)).channels is None


def test_format_2_evidence_without_channels_still_pools():
    """Evidence written before session 12 held the luminance copy only."""
    img = textured(H, W, seed=92, contrast=0.05) * np.exp(_lens())
    raw = working_copy(img, RobustSettings())
    buf = io.BytesIO()
    meta = json.dumps({"format": "vigproc.robust-evidence/2", "radius": raw.radius, "width": W, "height": H})
    np.savez_compressed(buf, L=raw.L.astype(np.float32), valid=raw.valid, xs=raw.xs, ys=raw.ys,
                        meta=np.frombuffer(meta.encode(), dtype=np.uint8))
    wc = evidence_copy(buf.getvalue())
    assert wc.channels is None
    fit = frame_fit(wc)
    np.testing.assert_allclose(fit.coefficients, frame_fit(raw).coefficients, atol=1e-6)  # stored as float32


def test_inconsistent_colour_channels_are_not_evidence():
    raw = working_copy(textured(H, W, seed=93, contrast=0.05), RobustSettings())
    buf = io.BytesIO()
    meta = json.dumps({"format": "vigproc.robust-evidence/3", "radius": raw.radius, "width": W, "height": H})
    np.savez_compressed(buf, L=raw.L.astype(np.float32), valid=raw.valid, xs=raw.xs, ys=raw.ys,
                        C=np.zeros((3, 2, 2), np.float32), Cvalid=np.ones((3, 2, 2), bool),
                        meta=np.frombuffer(meta.encode(), dtype=np.uint8))
    with pytest.raises(ValueError, match="colour channels"):
        evidence_copy(buf.getvalue())


def _family_error(lens: np.ndarray):
    """The gain-free error (EV) of family coefficients against the H×W log field ``lens``."""
    fam = profile_family()
    rho = np.hypot(*np.meshgrid(np.arange(W) - (W - 1) / 2, np.arange(H) - (H - 1) / 2)) / \
        math.hypot((W - 1) / 2, (H - 1) / 2)
    m, b = fam.profiles(rho)
    return lambda c: _gain_free_ev(m + b @ c - lens)


def test_a_colour_frame_leaves_out_shading_that_changes_colour():
    """A warm glow from one side (the scene's own light: red brightens most, blue
    least) pulls a luminance fit; a colour frame's pairs are weighted by how alike
    their channels change, and the glow's are not."""
    lens = _lens()
    img = coloured_scene(H, W, seed=310) * np.exp(lens)[..., None] * np.exp(chromatic_glow(H, W, 1.0))
    wc = evidence_copy(frame_evidence(img))
    colour = frame_fit(wc)
    from dataclasses import replace

    lum = frame_fit(replace(wc, channels=None, channels_valid=None))
    err = _family_error(lens)
    # measured: 0.044 EV against 0.100 (0.009 / 0.018 without the glow)
    assert err(colour.coefficients) < 0.05 and err(colour.coefficients) < 0.5 * err(lum.coefficients), \
        (err(colour.coefficients), err(lum.coefficients))
    np.testing.assert_allclose(colour.covariance, colour.covariance.T)


def test_a_frame_fit_for_pooling_reads_chroma_covariates():
    """A centred glow that whitens as it brightens, over surfaces of different colour: a
    pair's luminance change goes with its chroma change, which no lens makes. The frame's
    fit for pooling reads the chroma change as a covariate (as the single-frame fit does)
    and is not pulled by the glow; without it, it is. The forensic lens-match fit keeps
    the model its shipped calibration was made with (no covariates)."""
    from dataclasses import replace

    from vigproc.core.family_fit import EVIDENCE_SETTINGS
    from vigproc.core.pooling import FRAME_SETTINGS

    lens = _lens()
    x = np.linspace(-1.0, 1.0, W)[None, :]
    y = np.linspace(-1.0, 1.0, H)[:, None]
    glow = 0.4 * np.exp(-(x**2 + y**2) / 0.8)[..., None] * np.array([1.0, 0.8, 0.6])
    err = _family_error(lens)
    with_cov, without = [], []
    for seed in range(4):
        wc = evidence_copy(frame_evidence(coloured_scene(H, W, seed=seed) * np.exp(lens)[..., None] * np.exp(glow)))
        with_cov.append(err(frame_fit(wc).coefficients))
        without.append(err(frame_fit(wc, settings=replace(FRAME_SETTINGS, chroma_covariate=0.0)).coefficients))
    # measured: 0.014-0.048 EV against 0.102-0.124
    assert np.median(with_cov) < 0.06 and np.median(with_cov) < 0.5 * np.median(without), (with_cov, without)
    assert FRAME_SETTINGS.chroma_covariate > 0 and EVIDENCE_SETTINGS.chroma_covariate == 0
