"""The estimators on images with known vignetting."""

import numpy as np
import pytest

import vigproc
from benchmarks.synthetic import relative_errors, table1_model
from vigproc.errors import InvalidImageError
from vigproc.core.robust import RobustSettings
from vigproc.core.scene import default_scene_falloff

from conftest import textured


@pytest.mark.parametrize("setting", [1, 2, 3])
def test_default_recovers_table1_on_mild_texture(setting):
    # a synthetic texture has no scene fall-off: estimate without the scene prior
    truth = table1_model(setting)
    img = textured(320, 480, seed=setting, contrast=0.05) * truth.field()
    m = vigproc.estimate(img, channel_axis=None, settings=RobustSettings(scene_prior=False))
    assert not m.quality.fallback
    rp, rc, _ = relative_errors(m, truth)
    assert rp < 0.10
    if setting > 1:
        assert rc < 0.10
    err = np.log2(m.field() / truth.field())
    assert np.sqrt(np.mean(err**2)) < 0.1


def test_scene_prior_is_divided_out_before_the_fit():
    # a photo carrying exactly the scene fall-off, estimated with the prior, gives
    # the lens alone: the same as the photo without it, estimated without the prior
    truth = table1_model(2)
    base = textured(320, 480, seed=5, contrast=0.05) * truth.field()
    scene = default_scene_falloff()
    assert scene.field_ev_rms > 0.1
    with_scene = base * scene.model(480, 320).field()
    m1 = vigproc.estimate(with_scene, "robust", channel_axis=None)
    m0 = vigproc.estimate(base, channel_axis=None, settings=RobustSettings(scene_prior=False))
    err = np.log2(m1.field() / m0.field())
    assert np.sqrt(np.mean(err**2)) < 0.02
    # and it is really used: without it, the same photo looks strongly vignetted
    m2 = vigproc.estimate(with_scene, channel_axis=None, settings=RobustSettings(scene_prior=False))
    assert np.sqrt(np.mean(np.log2(m2.field() / truth.field()) ** 2)) > 0.2


def test_robust_falls_back_on_vignetting_free_texture():
    m = vigproc.estimate(textured(320, 480, seed=11, contrast=0.3), "robust", channel_axis=None)
    assert m.quality.fallback
    assert m.is_identity
    assert m.candidate is not None


def test_default_does_no_harm_on_vignetting_free_textures():
    models = [vigproc.estimate(textured(320, 480, seed=s, contrast=0.05), channel_axis=None) for s in range(6)]
    # most are left alone; what is applied to the others is negligible (SNR just above
    # the threshold: a field of about 0.015 EV)
    assert sum(m.quality.fallback for m in models) >= 4
    assert all(m.is_identity and m.candidate is not None for m in models if m.quality.fallback)
    assert max(float(np.std(m.log_field())) / np.log(2) for m in models) < 0.02


def test_ga_is_exact_for_a_gaussian_field():
    # GA's Eq. (7) model is exact for φ = exp(-½ (v-c)ᵀP(v-c)) on a flat scene
    h, w = 320, 480
    y, x = np.mgrid[0:h, 0:w].astype(float)
    dx, dy = x - (w - 1) / 2 + 30, y - (h - 1) / 2 - 20
    p = (2e-5, 4e-6, 3e-5)
    img = np.exp(-0.5 * (p[0] * dx * dx + 2 * p[1] * dx * dy + p[2] * dy * dy))
    m = vigproc.estimate(img, "ga", channel_axis=None)
    np.testing.assert_allclose(m.p, p, rtol=1e-6)
    np.testing.assert_allclose(m.center, (-30, 20), atol=1e-3)


def test_lyu2010_runs_and_stays_valid():
    # half the side of table1's frames: the assertions are about validity, not accuracy
    # (lyu2010's cost grows with the frame: 160x240 is half that of 320x480)
    truth = table1_model(2).rescale(240, 160)
    img = textured(160, 240, seed=5, contrast=0.1) * truth.field()
    m = vigproc.estimate(img, "lyu2010", channel_axis=None)
    assert m.method == "lyu2010"
    assert np.all(np.isfinite(m.field()))
    assert m.quality.objective >= 0


def test_colour_and_channel_axis():
    truth = table1_model(1)
    g = textured(320, 480, seed=2, contrast=0.1) * truth.field()
    rgb = np.stack([g, g * 0.8, g * 1.1], axis=-1)
    a = vigproc.estimate(rgb)
    b = vigproc.estimate(np.moveaxis(rgb, -1, 0), channel_axis=0)
    assert a.center == b.center and a.p == b.p


def test_estimate_at_other_resolution_maps_to_full_frame():
    truth = table1_model(2).rescale(960, 640)
    img = textured(640, 960, seed=4, contrast=0.05) * truth.field()
    for method in ("default", "ga"):
        m = vigproc.estimate(img, method, channel_axis=None)
        assert (m.width, m.height) == (960, 640)
    m = vigproc.estimate(img, channel_axis=None, settings=RobustSettings(scene_prior=False))
    rp, rc, _ = relative_errors(m, truth)
    assert rp < 0.1 and rc < 0.1


def test_correct_removes_known_field():
    truth = table1_model(3)
    clean = textured(320, 480, seed=8)
    out = vigproc.correct((clean * truth.field()).astype(np.float32), truth, channel_axis=None)
    np.testing.assert_allclose(out, clean, rtol=1e-5)
    half = vigproc.correct(clean * truth.field(), truth, channel_axis=None, strength=0.0)
    np.testing.assert_allclose(half, clean * truth.field(), rtol=1e-6)


@pytest.mark.parametrize("img,msg", [
    (np.full((64, 64), np.nan), "NaN"),
    (np.full((64, 64), 0.5), "constant"),
    (np.zeros((64, 64)), "no positive"),
    (-np.ones((64, 64)), "no positive"),
    (np.ones((4, 4)), "too small"),
    (np.ones((8, 8, 8, 8)), "H×W"),
    (np.ones((64, 64, 9)), "channels"),
])
def test_bad_input_is_a_typed_error(img, msg):
    with pytest.raises(InvalidImageError, match=msg):
        vigproc.estimate(img, channel_axis=-1 if img.ndim == 3 else None)


def test_small_image_for_paper_method():
    with pytest.raises(InvalidImageError, match="too small"):
        vigproc.estimate(textured(40, 60), "lyu2010", channel_axis=None)


def test_unknown_method():
    with pytest.raises(ValueError, match="unknown method"):
        vigproc.estimate(textured(64, 64), "magic", channel_axis=None)


def test_centred_refit_only_without_evidence_of_an_off_centre_fall_off(monkeypatch):
    """Model selection: a centred lens gets the centred refit; Table 1 setting 3
    (centre well off the middle, clear evidence) keeps the free fit."""
    import vigproc.core.robust as R
    from conftest import photo_like
    from vigproc.stores.lensfun import diverse_lenses, pa_field

    calls = []
    real = R.fit_robust

    def spy(wc, s, start=None):
        calls.append(s.sigma_center)
        return real(wc, s, start)

    monkeypatch.setattr(R, "fit_robust", spy)
    _, pa = diverse_lenses(1)[0]
    centred = photo_like(320, 480, seed=1) * pa_field((320, 480), pa.k1, pa.k2, pa.k3)
    m = vigproc.estimate(centred, "robust", channel_axis=None)
    assert calls == [RobustSettings().sigma_center, RobustSettings().centred_sigma_center]
    assert np.hypot(*(m.candidate or m).center) < 0.02 * np.hypot(480, 320) / 2
    calls.clear()
    truth = table1_model(3)
    off = textured(320, 480, seed=3, contrast=0.05) * truth.field()
    m = vigproc.estimate(off, channel_axis=None, settings=RobustSettings(scene_prior=False))
    assert calls == [RobustSettings().sigma_center]
    assert relative_errors(m, truth)[1] < 0.10
    calls.clear()
    vigproc.estimate(centred, channel_axis=None, settings=RobustSettings(centred_z=float("inf")))
    assert len(calls) == 1  # selection off


def test_shape_z_measures_departure_from_a_centred_circle():
    from vigproc.core.robust import shape_z

    cov = np.diag([0.01**2, 0.01**2, 0.02**2, 0.01**2, 0.02**2] + [1.0] * 7)
    circle = np.array([0.0, 0.0, 1.0, 0.0, 1.0] + [0.0] * 7)
    assert shape_z(circle, cov) == pytest.approx(0.0)
    # p1 − p3 = 0.1 with var(p1) + var(p3) = 8e-4: z = 0.1 / sqrt(8e-4)
    ellipse = circle.copy()
    ellipse[2] = 1.1
    assert shape_z(ellipse, cov) == pytest.approx(0.1 / np.sqrt(8e-4))
    off = circle.copy()
    off[:2] = 0.03, 0.04  # 3 and 4 sigma: |z| = 5
    assert shape_z(off, cov) == pytest.approx(5.0)
    assert shape_z(ellipse, np.zeros((12, 12))) == float("inf")


def test_centred_refit_holds_the_fall_off_circular(monkeypatch):
    """The selection's refit tightens both the centre and the ellipticity priors;
    selection="centre" only the centre."""
    import vigproc.core.robust as R
    from conftest import photo_like
    from vigproc.stores.lensfun import diverse_lenses, pa_field

    seen = []
    real = R.fit_robust

    def spy(wc, s, start=None):
        seen.append((s.sigma_center, s.sigma_ellipticity))
        return real(wc, s, start)

    monkeypatch.setattr(R, "fit_robust", spy)
    _, pa = diverse_lenses(1)[0]
    img = photo_like(320, 480, seed=2) * pa_field((320, 480), pa.k1, pa.k2, pa.k3)
    d = RobustSettings()
    m = vigproc.estimate(img, "robust", channel_axis=None)
    assert seen == [(d.sigma_center, d.sigma_ellipticity), (d.centred_sigma_center, d.centred_sigma_ellipticity)]
    fit = m.candidate or m
    p1, p2, p3 = fit.p
    assert abs(p1 - p3) < 0.1 * (p1 + p3) and abs(p2) < 0.1 * (p1 + p3)
    seen.clear()
    vigproc.estimate(img, channel_axis=None, settings=RobustSettings(selection="centre"))
    assert seen[-1] == (d.centred_sigma_center, d.sigma_ellipticity)


def test_power_loss_recovers_a_table1_field():
    truth = table1_model(2)
    img = textured(320, 480, seed=4, contrast=0.05) * truth.field()
    m = vigproc.estimate(img, channel_axis=None, settings=RobustSettings(loss="power", scene_prior=False))
    err = np.log2(m.field() / truth.field())
    assert np.sqrt(np.mean((err - err.mean()) ** 2)) < 0.05  # up to an exposure gain
    assert relative_errors(m, truth)[1] < 0.10


def test_centre_z():
    from vigproc.core.robust import centre_z

    cov = np.diag([0.01**2, 0.02**2] + [1.0] * 10)
    assert centre_z(np.array([0.03, 0.0] + [0.0] * 10), cov) == pytest.approx(3.0)
    assert centre_z(np.array([0.0, -0.08] + [0.0] * 10), cov) == pytest.approx(4.0)
    assert centre_z(np.zeros(12), np.zeros((12, 12))) == float("inf")


def test_joint_fit_of_several_frames():
    from vigproc.errors import InvalidImageError
    from vigproc.core.robust import estimate_robust, estimate_robust_joint

    truth = table1_model(2)
    s = RobustSettings(scene_prior=False)
    frames = [textured(320, 480, seed=40 + i, contrast=0.05) * truth.field() for i in range(3)]
    one = estimate_robust(frames[0], s)
    # one frame: exactly the single-frame fit (no separator rows, same data weight)
    np.testing.assert_allclose(estimate_robust_joint(frames[:1], s).log_field(), (one.candidate or one).log_field(),
                               atol=1e-9)
    m = estimate_robust_joint(frames, s)
    assert m.covariance is not None and m.method == "robust-joint"
    err = np.log2(m.field() / truth.field())
    assert np.sqrt(np.mean(err**2)) < 0.1
    with pytest.raises(InvalidImageError):
        estimate_robust_joint([], s)
    with pytest.raises(InvalidImageError):
        estimate_robust_joint([frames[0], frames[1][:, :400]], s)


def test_settings_reject_unknown_choices():
    with pytest.raises(ValueError, match="loss"):
        RobustSettings(loss="cauchyy")
    with pytest.raises(ValueError, match="selection"):
        RobustSettings(selection="circle")


def test_power_loss_kernel_is_the_smoothed_hyper_laplacian():
    from vigproc.core._kernels.robust import CAUCHY, POWER, POWER_EXPONENT, robust_loss

    L = np.array([[0.0, 0.3]])
    valid = np.ones((1, 2), dtype=bool)
    F = np.zeros((1, 2))
    steps = np.array([1], dtype=np.int64)
    eps = np.array([0.01])
    loss, n = robust_loss(L, valid, F, steps, eps, POWER)
    assert n == 1
    assert loss == pytest.approx((1 + 30.0**2) ** (POWER_EXPONENT / 2) - 1)
    assert robust_loss(L, valid, F, steps, eps, CAUCHY)[0] == pytest.approx(np.log1p(30.0**2))


def test_shape_ratio_separates_real_lenses_from_broad_fall_off():
    """Real lenses keep the frame centre flat (lensfun: ratio 0.23 in the median);
    Lyu's Table 1 setting 2 falls off from the centre on (0.45)."""
    from vigproc.stores.lensfun import diverse_lenses
    from vigproc.stores.lensfun_io import kw_from_pa
    from vigproc.core.normalised import normalise
    from vigproc.core.robust import REAL_LENS_SHAPE_RATIO, RobustSettings, shape_ratio, working_copy

    wc = working_copy(np.ones((320, 480)), RobustSettings())
    _, pa = diverse_lenses(20)[8]
    lens = normalise(kw_from_pa(pa.k1, pa.k2, pa.k3, 480, 320))[0]
    broad = normalise(table1_model(2))[0]
    assert shape_ratio(lens, wc) < REAL_LENS_SHAPE_RATIO < shape_ratio(broad, wc)
    assert shape_ratio(np.zeros(12), wc) == 0.0


def test_real_lens_method_refuses_broad_fall_off_only():
    from vigproc.stores.lensfun import diverse_lenses, pa_field

    base = textured(320, 480, seed=1, contrast=0.05)
    broad = base * table1_model(2).field()
    assert not vigproc.estimate(broad, "robust", channel_axis=None).quality.fallback
    refused = vigproc.estimate(broad, "real-lens", channel_axis=None)
    assert refused.quality.fallback and refused.is_identity and refused.candidate is not None
    _, pa = diverse_lenses(20)[8]
    lens = base * pa_field((320, 480), pa.k1, pa.k2, pa.k3)
    m = vigproc.estimate(lens, "real-lens", channel_axis=None)
    assert not m.quality.fallback
    np.testing.assert_allclose(m.log_field(), vigproc.estimate(lens, "robust", channel_axis=None).log_field())


def test_evidence_only_from_the_robust_methods():
    from vigproc.core.estimate import estimate_with_evidence
    from vigproc.core.extensions import UnknownMethodError

    img = textured(160, 240, seed=2, contrast=0.05)
    m, ev = estimate_with_evidence(img, channel_axis=None, method="real-lens")
    assert isinstance(ev, bytes) and m.width == 240
    with pytest.raises(UnknownMethodError, match="frame evidence"):
        estimate_with_evidence(img, channel_axis=None, method="ga")


def test_real_lens_estimates_name_their_method():
    img = textured(160, 240, seed=3, contrast=0.05) * table1_model(1).rescale(240, 160).field()
    m = vigproc.estimate(img, "real-lens", channel_axis=None)
    assert m.method == "real-lens"
    assert vigproc.estimate(img, "robust", channel_axis=None).method == "robust"


def test_fit_stays_valid_beyond_its_corner_pixels():
    """A fit to a tiny frame must hold G > 0 up to the frame's edges, not only at its
    corner pixel centres: pictures and RAW full sizes evaluate it on finer grids
    (a 64x48 sawtooth once gave a model whose G fell below 0 on a 256-px grid)."""
    y, x = np.mgrid[0:48, 0:64]
    img = np.stack([((21 * x + 9 * y + c) % 256) / 255.0 for c in range(3)], axis=-1)
    lin = np.where(img <= 0.04045, img / 12.92, ((img + 0.055) / 1.055) ** 2.4)
    m = vigproc.estimate(lin)
    fit = m.candidate if m.candidate is not None else m
    for w, h in ((256, 192), (640, 480)):
        assert np.all(np.isfinite(fit.rescale(w, h).log_field()))
    assert np.isfinite(fit.field_ev_rms())


def test_flat_field_method_reads_a_frame_without_scene_exactly():
    """A white frame under a real lens's fall-off: "flat-field" recovers it; the default
    divides out the scene prior (the darker edges photographs of scenes have), which a
    frame of no scene does not have, and so under-corrects."""
    from vigproc.stores.lensfun import diverse_lenses, pa_field

    _, pa = diverse_lenses(1)[0]
    h, w = 320, 480
    truth = pa_field((h, w), pa.k1, pa.k2, pa.k3)
    rng = np.random.default_rng(0)
    white = 0.7 * truth * (1 + 0.002 * rng.standard_normal((h, w)))  # a little sensor noise
    ff = vigproc.estimate(white, "flat-field", channel_axis=None)
    assert ff.method == "flat-field" and not ff.quality.fallback
    err_ff = float(np.std(np.log2(ff.field((h, w)) / truth)))
    err_default = float(np.std(np.log2(vigproc.estimate(white, "robust", channel_axis=None).field((h, w)) / truth)))
    assert err_ff < 0.03 and err_ff < 0.5 * err_default, (err_ff, err_default)
