"""The default estimator's own module (vigproc.core.robust), called directly: what it
recovers on synthetic frames with a known Kang-Weiss field, its working copy, its
start, its fall-back, its evidence blobs and what it refuses.

Through ``vigproc.estimate`` the same estimator is measured further in test_estimate
(Lyu's Table 1 settings, the scene prior, model selection, joint fits); the frames here
are small (240×160) so that the file runs in seconds.
"""

from __future__ import annotations

import io
import json
import math
from dataclasses import FrozenInstanceError, replace

import numpy as np
import pytest

from conftest import textured
from vigproc.core import robust as R
from vigproc.core.model import N_ALPHA, VignettingModel
from vigproc.errors import InvalidImageError

W, H = 240, 160
#: No scene prior: a synthetic texture carries no scene fall-off to divide out.
PLAIN = R.RobustSettings(scene_prior=False)
#: Off-centre and elliptical, strong enough (0.48 EV RMS) that model selection keeps the free fit.
OFF_CENTRE = VignettingModel(W, H, center=(30.0, -20.0), p=(1 / 110**2, 0.0, 1 / 150**2))
#: Centred and circular, with a geometric factor G = 1 − 0.1 r − 0.05 r².
CENTRED = VignettingModel(W, H, p=(1 / 200**2, 0.0, 1 / 200**2), alpha=(0.1, 0.05) + (0.0,) * (N_ALPHA - 2))


def _ev_rms(a: VignettingModel, b: VignettingModel) -> float:
    """RMS over the frame of log2(φ_a / φ_b): how far two fields are apart, in EV."""
    return float(np.sqrt(np.mean(np.log2(a.field() / b.field()) ** 2)))


def _frame(truth: VignettingModel, seed: int) -> np.ndarray:
    return textured(H, W, seed=seed, contrast=0.05) * truth.field()


# ------------------------------------------------------------------ recovery
@pytest.mark.parametrize("seed", [1, 2, 3])
def test_recovers_an_off_centre_elliptical_field(seed):
    m = R.estimate_robust(_frame(OFF_CENTRE, seed), PLAIN)
    assert not m.quality.fallback and m.method == "robust" and (m.width, m.height) == (W, H)
    assert OFF_CENTRE.field_ev_rms() > 0.4
    assert _ev_rms(m, OFF_CENTRE) < 0.1  # of a 0.48 EV field
    # the centre is found off the frame centre, where it is (0.1 half-diagonals = 14 px)
    assert math.dist(m.center, OFF_CENTRE.center) < 0.1 * 0.5 * math.hypot(W, H)
    # the ellipse's long axis is the horizontal one, as in the truth (p1 > p3)
    assert m.p[0] > 1.2 * m.p[2]
    assert m.quality.snr > R.RobustSettings().min_snr and m.covariance is not None


@pytest.mark.parametrize("seed", [1, 2])
def test_recovers_a_centred_field_with_a_geometric_factor(seed):
    m = R.estimate_robust(_frame(CENTRED, seed), PLAIN)
    assert not m.quality.fallback
    assert _ev_rms(m, CENTRED) < 0.06  # of a 0.22 EV field
    assert abs(m.center[0]) < 1.0 and abs(m.center[1]) < 1.0  # the centred fit was selected
    assert m.p[0] == pytest.approx(m.p[2], rel=0.01)


def test_the_reported_field_figure_is_the_models_own():
    m = R.estimate_robust(_frame(OFF_CENTRE, 1), PLAIN)
    assert m.quality.field_ev_rms == pytest.approx(m.field_ev_rms(), rel=1e-12)
    assert m.quality.field_ev_rms == pytest.approx(OFF_CENTRE.field_ev_rms(), abs=0.1)


# ------------------------------------------------------------------ the pieces
def test_working_copy_bins_masks_and_normalises():
    lum = textured(H, W, seed=7, contrast=0.05)
    lum[:20, :30] = np.nan  # invalid pixels
    lum[-20:, -30:] = 0.0  # and black ones
    mask = np.ones((H, W), dtype=bool)
    mask[:, 100:110] = False  # and pixels the caller excludes (clipped, say)
    wc = R.working_copy(lum, PLAIN, mask)
    k = round(W / PLAIN.work_size)  # bins k×k, the long side about work_size bins
    assert wc.L.shape == (H // k, W // k) and (wc.width, wc.height) == (W, H)
    assert wc.radius == pytest.approx(0.5 * math.hypot(W, H))
    # bin centres, in half-diagonals from the frame centre, symmetric about it
    assert wc.xs[0] == pytest.approx(-wc.xs[-1]) and wc.ys[0] == pytest.approx(-wc.ys[-1])
    assert abs(wc.xs).max() < (W / 2) / wc.radius
    assert not wc.valid[0, 0] and not wc.valid[-1, -1]  # the NaN and the black corner
    assert not wc.valid[:, 100 // k].any()  # the masked column
    assert wc.valid.mean() > 0.8
    assert np.all(np.isfinite(wc.L[wc.valid]))
    # log luminance: a brighter frame moves L by the log of the gain, nothing else
    wc2 = R.working_copy(4.0 * lum, PLAIN, mask)
    np.testing.assert_allclose(wc2.L[wc.valid] - wc.L[wc.valid], math.log(4.0), atol=1e-9)


def test_kw_field_is_the_models_log_field_in_normalised_units():
    wc = R.working_copy(textured(H, W, seed=8), PLAIN)
    for truth in (OFF_CENTRE, CENTRED):
        theta = np.concatenate([np.asarray(truth.center) / wc.radius, np.asarray(truth.p) * wc.radius**2,
                                truth.alpha])
        out = np.empty(wc.L.shape)
        gmin = R.kw_field(wc.xs, wc.ys, theta, out)
        expect = truth.log_field_at(wc.xs[None, :] * wc.radius, wc.ys[:, None] * wc.radius)
        np.testing.assert_allclose(out, expect, atol=1e-9)
        assert 0.0 < gmin <= 1.0
        # and back to pixels: the model the estimator returns is this θ
        th_px, _ = R._to_pixels(theta, np.zeros((12, 12)), wc.radius)
        back = VignettingModel.from_vector(th_px, W, H)
        np.testing.assert_allclose(back.log_field(), truth.log_field(), atol=1e-9)


def test_quadratic_start_recovers_a_log_quadratic_field():
    """Lyu's Gaussian approximation fitted to every bin: exact for a field that is
    log-quadratic, −½ (v − c)ᵀP(v − c), whatever the texture on it."""
    wc = R.working_copy(textured(H, W, seed=4, contrast=0.05), PLAIN)
    P, c = np.array([[1.2, 0.2], [0.2, 0.8]]), np.array([0.1, -0.05])
    X, Y = np.meshgrid(wc.xs - c[0], wc.ys - c[1])
    q = P[0, 0] * X * X + 2 * P[0, 1] * X * Y + P[1, 1] * Y * Y
    theta = R.quadratic_start(replace(wc, L=wc.L - 0.5 * q), np.asarray(PLAIN.steps))
    np.testing.assert_allclose(theta[:2], c, atol=0.02)
    np.testing.assert_allclose(theta[2:5], [P[0, 0], P[0, 1], P[1, 1]], atol=0.06)
    assert not theta[5:].any()  # the start has no geometric factor


def test_shape_ratio_says_how_broad_a_fall_off_is():
    wc = R.working_copy(textured(H, W, seed=9), PLAIN)
    assert R.shape_ratio(np.zeros(12), wc) == 0.0  # no fall-off
    circle = np.zeros(12)
    circle[2] = circle[4] = 1.0
    broad = circle.copy()
    broad[5] = 0.3  # a geometric factor falling off from the centre on
    r_circle, r_broad = R.shape_ratio(circle, wc), R.shape_ratio(broad, wc)
    assert 0.0 < r_circle < r_broad < 1.0
    # the setting that uses it: a fit broader than a real lens's is not applied
    m = R.estimate_robust(_frame(OFF_CENTRE, 1), replace(PLAIN, max_shape_ratio=0.01))
    assert m.quality.fallback and m.is_identity and m.candidate is not None


def test_uncertainty_shrinks_with_the_data_it_is_worth():
    wc = R.working_copy(_frame(CENTRED, 1), PLAIN)
    sig = []
    for n_eff in (100.0, 1600.0):
        theta, cov, _ = R.fit_robust(wc, replace(PLAIN, n_eff=n_eff))
        ev, sigma = R.field_uncertainty_ev(theta, cov, wc)
        assert ev > 0.15
        sig.append(sigma)
    assert sig[1] < 0.5 * sig[0]  # 16 times the data: about a quarter of the σ (priors aside)


# ------------------------------------------------------------------ do no harm
def test_a_flat_frame_falls_back_to_the_identity():
    m = R.estimate_robust(np.full((H, W), 0.5), PLAIN)
    assert m.quality.fallback and m.is_identity and m.method == "robust"
    assert m.candidate is not None and m.candidate.quality.field_ev_rms < 1e-6
    assert m.quality.confidence < 0.5
    np.testing.assert_array_equal(m.field(), 1.0)


def test_a_weak_field_is_not_applied_below_min_ev():
    frame = _frame(CENTRED, 1)
    applied = R.estimate_robust(frame, PLAIN)
    held = R.estimate_robust(frame, replace(PLAIN, min_ev=1.0))  # more than the field has
    assert not applied.quality.fallback and held.quality.fallback and held.is_identity
    # the rejected fit is kept, and is the fit that was applied before
    assert _ev_rms(held.candidate, applied) < 1e-9


@pytest.mark.parametrize("what", ["black", "masked", "tiny"])
def test_too_few_usable_bins_is_no_fit_at_all(what):
    lum = textured(H, W, seed=5)
    mask = None
    if what == "black":
        lum = np.zeros((H, W))
    elif what == "masked":
        mask = np.zeros((H, W), dtype=bool)
        mask[:8, :8] = True
    else:
        lum = lum[:6, :9]
    m = R.estimate_robust(lum, PLAIN, mask)
    assert m.quality.fallback and m.is_identity and m.candidate is None
    assert m.quality.confidence == 0.0 and m.quality.iterations == 0
    assert (m.width, m.height) == (lum.shape[1], lum.shape[0])


# ------------------------------------------------------------------ evidence
def test_evidence_is_the_working_copy_before_the_scene_division():
    frame = _frame(CENTRED, 2)
    blob = R.luminance_evidence(frame, PLAIN)
    wc, back = R.working_copy(frame, PLAIN), R.evidence_copy(blob)
    np.testing.assert_allclose(back.L, wc.L, atol=1e-6)  # stored as float32
    np.testing.assert_array_equal(back.valid, wc.valid)
    assert (back.width, back.height, back.radius) == (wc.width, wc.height, wc.radius)
    # one working copy for both: the same model and the same evidence as separately
    scene = R.RobustSettings()
    m, blob2 = R.estimate_robust_with_evidence(frame, scene)
    assert blob2 == R.luminance_evidence(frame, scene)
    assert _ev_rms(m.candidate or m, R.estimate_robust(frame, scene).candidate or m) < 1e-9


def test_format_1_evidence_had_the_scene_divided_out():
    from vigproc.core.scene import default_scene_falloff

    wc = R.working_copy(_frame(CENTRED, 3), PLAIN)
    old = replace(wc, L=wc.L - default_scene_falloff().log_field(wc.xs, wc.ys))
    buf = io.BytesIO()
    meta = json.dumps({"format": "vigproc.robust-evidence/1", "radius": wc.radius, "width": W, "height": H})
    np.savez_compressed(buf, L=old.L.astype(np.float32), valid=wc.valid, xs=wc.xs, ys=wc.ys,
                        meta=np.frombuffer(meta.encode(), dtype=np.uint8))
    np.testing.assert_allclose(R.evidence_copy(buf.getvalue()).L, wc.L, atol=1e-5)


def test_evidence_refuses_what_is_not_evidence():
    good = R.luminance_evidence(_frame(CENTRED, 1), PLAIN)
    with pytest.raises(ValueError, match="not frame evidence"):
        R.evidence_copy(b"junk")
    with pytest.raises(ValueError, match="not frame evidence"):
        R.evidence_copy(good[: len(good) // 2])  # truncated
    with np.load(io.BytesIO(good)) as z:
        parts = {k: z[k] for k in z.files}
    for change in ({"meta": np.frombuffer(b'{"format": "other/1"}', dtype=np.uint8)},
                   {"valid": parts["valid"][:-1]}, {"L": np.full_like(parts["L"], np.nan)}):
        buf = io.BytesIO()
        np.savez(buf, **{**parts, **change})
        with pytest.raises(ValueError, match="inconsistent|not frame evidence"):
            R.evidence_copy(buf.getvalue())


# ------------------------------------------------------------------ refusals
def test_settings_are_frozen_and_refuse_unknown_choices():
    s = R.RobustSettings()
    with pytest.raises(FrozenInstanceError):
        s.loss = "huber"  # type: ignore[misc]
    for bad in ({"loss": "Cauchy"}, {"loss": ""}, {"selection": "circle"}):
        with pytest.raises(ValueError, match="loss|selection"):
            R.RobustSettings(**bad)
    assert R.RobustSettings(loss="huber").loss == "huber"  # the other choices are taken


def test_joint_fits_refuse_typed():
    frame = _frame(CENTRED, 1)
    with pytest.raises(InvalidImageError, match="at least one frame"):
        R.fit_joint([], PLAIN)
    with pytest.raises(InvalidImageError, match="one size"):
        R.estimate_robust_joint([frame, frame[:, :200]], PLAIN)
    black = R.working_copy(np.zeros((H, W)), PLAIN)
    with pytest.raises(InvalidImageError, match="too few usable pixels"):
        R.fit_joint([black, black], PLAIN)


@pytest.mark.parametrize("bad", [np.ones(10), np.ones((4, 5, 6, 7)), np.full((H, W), np.nan), np.ones((0, 5))])
def test_the_door_refuses_what_the_estimator_may_not_see(bad):
    """The core trusts its input: ``vigproc.estimate`` validates it first (one check at
    the door) and refuses with a typed error, never with the estimator's own."""
    import vigproc

    with pytest.raises(InvalidImageError):
        vigproc.estimate(bad, "robust", channel_axis=None)
