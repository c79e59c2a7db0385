"""Pooling a lens's frames into its profile (vigproc.pooling) and the frames' evidence."""

import io
import json

import numpy as np
import pytest

from vigproc.errors import ModelError
from vigproc.estimate import frame_evidence
from vigproc.lensfun import bench_lenses, pa_field
from vigproc.pooling import centred_fit, default_profile_bias, pool_fits
from vigproc.robust import RobustSettings, evidence_copy, working_copy
from vigproc.scene import NONE, SceneFalloff, default_scene_falloff

from conftest import textured

H, W = 160, 240


def _rms_ev(x: np.ndarray) -> float:
    return float(np.sqrt(np.mean(x * x)) / np.log(2))


def _fits(frames):
    return [centred_fit(evidence_copy(frame_evidence(f, channel_axis=None))) for f in frames]


def test_pooling_subtracts_the_bias_and_recovers_the_lens():
    """Frames carry a common 'scene' fall-off and a real lens: with that fall-off as
    the bias, the pooled profile is the lens; without it, the lens and the scene."""
    _, pa = bench_lenses(1)[0]
    lens = np.log(pa_field((H, W), pa.k1, pa.k2, pa.k3))
    scene_model = default_scene_falloff().model(W, H)
    scene = scene_model.log_field((H, W))
    frames = [textured(H, W, seed=70 + i, contrast=0.05) * np.exp(scene + lens) for i in range(4)]
    fits = _fits(frames)
    bias = SceneFalloff(theta=tuple(default_scene_falloff().theta))
    pooled = pool_fits(fits, W, H, bias=bias)
    raw = pool_fits(fits, W, H, bias=NONE)
    assert pooled.method == "profile-pooled" and pooled.covariance is not None
    err = _rms_ev(pooled.log_field((H, W)) - lens)
    assert err < 0.25 * _rms_ev(lens), err
    assert _rms_ev(raw.log_field((H, W)) - lens - scene) < 0.25 * _rms_ev(lens + scene)
    assert np.hypot(*pooled.center) < 0.02 * np.hypot(W, H) / 2  # centred (up to the bias fit)


def test_pooled_profile_never_brightens():
    """A bias larger than the frames' fall-off leaves no correction, not a brightening."""
    frames = [textured(H, W, seed=80 + i, contrast=0.05) for i in range(2)]
    from vigproc.bench.synthetic import table1_model
    from vigproc.normalised import normalise

    strong = SceneFalloff(theta=tuple(normalise(table1_model(1))[0]))  # far more fall-off than the frames
    pooled = pool_fits(_fits(frames), W, H, bias=strong)
    assert pooled.is_identity


def test_pooling_needs_frames():
    with pytest.raises(ModelError, match="no frames"):
        pool_fits([], W, H)


def test_shipped_profile_bias_is_the_documented_one():
    bias = default_profile_bias()
    assert bias.n_images == 200 and "fit-profile-bias" in bias.source
    assert 0.2 < bias.field_ev_rms < 0.8


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


def test_pooled_covariance_is_the_frames_field_uncertainty_over_n():
    """The same frame's fit pooled four times: the pooled field's σ is the frame's / 2,
    in the pooled model's own parametrisation (not the frames')."""
    from vigproc.normalised import _field_sigma_ev, normalise

    _, pa = bench_lenses(1)[0]
    img = textured(H, W, seed=95, contrast=0.05) * pa_field((H, W), pa.k1, pa.k2, pa.k3)
    fit = _fits([img])[0]
    one = normalise(pool_fits([fit], W, H, bias=NONE))
    four = normalise(pool_fits([fit] * 4, W, H, bias=NONE))
    s_frame = _field_sigma_ev(fit.theta, fit.cov, W / H)
    s_one = _field_sigma_ev(one[0], one[1], W / H)
    s_four = _field_sigma_ev(four[0], four[1], W / H)
    assert s_one == pytest.approx(s_frame, rel=0.25)
    assert s_four == pytest.approx(s_one / 2, rel=0.05)
