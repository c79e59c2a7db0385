"""The lens family (lensfun's calibrations as a low-dimensional space) and the
lens-family estimator built on it."""

import json
import math

import numpy as np
import pytest

import vigproc
from vigproc.errors import ModelError
from vigproc.core.estimate import estimate_default
from vigproc.core.family_fit import (
    FamilySettings,
    LensHint,
    estimate_family,
    family_pairs,
    irls,
    fit_centre,
    pair_index,
    fit_family,
    profile_to_model,
)
from vigproc.core.lensfamily import N_RADII, LensFamily, build_family, default_family
from vigproc.stores.lensfun import pa_field

from conftest import chromatic_glow, coloured_scene, textured

H, W = 320, 480
RADII = np.linspace(0.0, 1.0, N_RADII)


def _pa_log(k1, k2=0.0, k3=0.0):
    r2 = RADII**2
    return np.log(1 + k1 * r2 + k2 * r2**2 + k3 * r2**3)


def _toy_family(n=60, seed=0):
    rng = np.random.default_rng(seed)
    rows = [_pa_log(-rng.uniform(0.05, 0.6), rng.uniform(-0.1, 0.1)) for _ in range(n)]
    f35 = rng.uniform(14, 200, n)
    fno = rng.uniform(1.4, 16, n)
    return build_family(np.array(rows), f35, fno, lenses=n)


def test_family_components_reconstruct_their_profiles():
    fam = _toy_family()
    assert fam.n_components == 2
    np.testing.assert_allclose(fam.components @ fam.components.T, np.eye(2), atol=1e-12)
    # two pa terms span a two-dimensional family: rebuilt almost exactly
    assert fam.reconstruction_ev < 1e-3
    # the convention: a component's corner value is negative (more fall-off)
    assert np.all(fam.components[:, -1] <= 0)


def test_family_prior_narrows_to_calibrations_like_the_exif():
    fam = _toy_family(200)
    mean_all, cov_all = fam.prior()
    mean_near, cov_near = fam.prior(focal35=24.0, fnumber=2.8, neighbours=20)
    near = np.argsort(np.hypot(np.log(fam.focal35 / 24.0), np.log(fam.fnumber / 2.8)))[:20]
    np.testing.assert_allclose(mean_near, fam.coefficients[near].mean(axis=0))
    assert not np.allclose(mean_near, mean_all)
    # without both numbers (or with nonsense) the prior is the whole family's
    for f, n in ((None, 2.8), (24.0, None), (float("nan"), 2.8), (-5.0, 2.8)):
        np.testing.assert_allclose(fam.prior(f, n)[0], mean_all)


def test_family_round_trips_and_refuses_junk(tmp_path):
    fam = _toy_family()
    back = LensFamily.from_dict(json.loads(json.dumps(fam.to_dict())))
    np.testing.assert_allclose(back.mean, fam.mean, atol=1e-7)
    np.testing.assert_allclose(back.coefficients, fam.coefficients, atol=1e-4)
    d = fam.to_dict()
    for bad in ({**d, "format": 99}, {**d, "mean": d["mean"][:-1]}, {**d, "components": "x"},
                {k: v for k, v in d.items() if k != "radii"}, {**d, "mean": [math.nan] * N_RADII},
                # a radius twice: the centre fits divided by the gap between them (ZeroDivisionError)
                {**d, "radii": [d["radii"][0]] + list(d["radii"][:-1])}):
        with pytest.raises(ModelError):
            LensFamily.from_dict(bad)
    with pytest.raises(ModelError):
        build_family(np.zeros((2, N_RADII)), np.ones(2), np.ones(2), 2)


def test_shipped_family_is_lensfuns():
    fam = default_family()
    assert fam.n_components == 2
    assert fam.lenses > 400 and fam.coefficients.shape[0] > 20_000
    assert fam.reconstruction_ev < 0.01


def test_profile_written_as_kang_weiss_model_matches_it():
    fam = default_family()
    for c in ([0.0, 0.0], [-1.5, 0.2], [1.0, -0.3]):
        prof = fam.mean + np.asarray(c) @ fam.components
        model, err = profile_to_model(prof, fam.radii, W, H)
        assert err < 2e-3
        # the model's field over the frame is the profile at each pixel's radius
        ys, xs = np.mgrid[0:H, 0:W]
        rho = np.hypot(xs - (W - 1) / 2, ys - (H - 1) / 2) / math.hypot((W - 1) / 2, (H - 1) / 2)
        want = np.interp(rho, fam.radii, prof)
        assert np.max(np.abs(model.log_field((H, W)) - want)) / math.log(2) < 0.01


def test_pairs_match_their_definition():
    rng = np.random.default_rng(1)
    L = rng.normal(size=(12, 15))
    valid = rng.random((12, 15)) > 0.1
    M = rng.normal(size=(12, 15))
    B = rng.normal(size=(12, 15, 2))
    blocks = np.zeros((12, 15), dtype=np.int64)
    blocks[6:] = 1
    C = rng.normal(size=(3, 12, 15))
    steps = np.array([1, 2], dtype=np.int64)
    d, a, labels, weight = family_pairs(L, valid, M, B, steps, blocks, C, 0.7)
    want_d, want_a, want_w, want_l = [], [], [], []
    for s in (1, 2):
        for dy, dx in ((s, 0), (0, s)):
            for y in range(12 - dy):
                for x in range(15 - dx):
                    if valid[y, x] and valid[y + dy, x + dx]:
                        want_d.append((L[y + dy, x + dx] - L[y, x] - M[y + dy, x + dx] + M[y, x]) / s)
                        want_a.append((B[y + dy, x + dx] - B[y, x]) / s)
                        want_l.append(blocks[y, x])
                        dc = (C[:, y + dy, x + dx] - C[:, y, x]) / s
                        q = (dc[0] - dc[1]) ** 2 + (dc[2] - dc[1]) ** 2
                        want_w.append(1 / (1 + q / 0.7**2))
    np.testing.assert_allclose(d, want_d)
    np.testing.assert_allclose(a, want_a)
    np.testing.assert_array_equal(labels, want_l)
    np.testing.assert_allclose(weight, want_w)
    # each pair's chroma change per step, the colour fit's covariates: rows ΔR − ΔG, ΔB − ΔG
    index = pair_index(L, valid, steps, blocks, C, 0.7)
    want_c = [[], []]
    for s in (1, 2):
        for dy, dx in ((s, 0), (0, s)):
            for y in range(12 - dy):
                for x in range(15 - dx):
                    if valid[y, x] and valid[y + dy, x + dx]:
                        dc = (C[:, y + dy, x + dx] - C[:, y, x]) / s
                        want_c[0].append(dc[0] - dc[1])
                        want_c[1].append(dc[2] - dc[1])
    np.testing.assert_allclose(index.chroma, want_c)
    assert pair_index(L, valid, steps, blocks, None, 0.7).chroma.shape == (0, d.size)
    grey = family_pairs(L, valid, M, B, steps, blocks, None, 0.7)
    np.testing.assert_array_equal(grey[0], d)
    np.testing.assert_array_equal(grey[3], np.ones(d.size))  # no colour: every pair weighs 1
    none = family_pairs(L, valid, M, np.zeros((12, 15, 0)), steps, blocks, None, 0.7)
    assert none[1].shape == (d.size, 0)


def test_irls_solves_the_weighted_normal_equations():
    """At its fixed point, IRLS's c solves (AᵀWA/(σ²κ) + Λ) c = AᵀWd/(σ²κ) + Λμ with the
    Cauchy weights of its own residuals; a Gaussian fit (σ huge) is least squares."""
    rng = np.random.default_rng(2)
    a = rng.normal(size=(400, 2))
    d = a @ np.array([0.4, -0.3]) + 0.05 * rng.standard_cauchy(400)
    weight = rng.random(400)
    pmean, pinv = np.array([0.1, 0.0]), np.eye(2) * 3.0
    sigma, kappa = 0.05, 0.5
    c = irls(d, a, weight, np.zeros(2), pmean, pinv, sigma, kappa, 500)
    w = weight / (1 + ((d - a @ c) / sigma) ** 2)
    s = 1 / (sigma**2 * kappa)
    H = (a * w[:, None]).T @ a * s + pinv
    np.testing.assert_allclose(H @ c, (a * w[:, None]).T @ d * s + pinv @ pmean, rtol=1e-3)
    assert np.allclose(c, [0.4, -0.3], atol=0.02)  # the outliers do not pull it
    ls = irls(d, a, np.ones(400), np.zeros(2), np.zeros(2), np.zeros((2, 2)), 1e6, 1.0, 5)
    np.testing.assert_allclose(ls, np.linalg.lstsq(a, d, rcond=None)[0], rtol=1e-6)
    # watching only the first coefficient for the stop: that one is converged as well
    first = irls(d, a, weight, np.zeros(2), pmean, pinv, sigma, kappa, 500, tolerance=1e-3, converged_on=1)
    assert abs(first[0] - c[0]) < 5e-3
    # over-relaxed steps reach the same fixed point
    np.testing.assert_allclose(irls(d, a, weight, np.zeros(2), pmean, pinv, sigma, kappa, 500, relaxation=1.6), c,
                               atol=5e-4)


def test_irls_leaves_out_pairs_of_weight_zero_and_steps_as_numpy_does():
    """A pair weighed 0 is no pair (the jackknife leaves a block out so); a step is the
    NumPy solve of the reweighted normal equations (five plain steps, to rounding); data
    no system can be solved for give NaN, not an error."""
    rng = np.random.default_rng(5)
    a = rng.normal(size=(600, 5))
    d = a @ rng.normal(size=5) + 0.05 * rng.standard_cauchy(600)
    weight = rng.random(600)
    out = np.arange(600) % 3 == 0
    pmean, pinv, sigma, kappa = np.zeros(5), np.eye(5) * 2.0, 0.05, 0.7
    left = irls(d, a, weight * ~out, np.zeros(5), pmean, pinv, sigma, kappa, 7, tolerance=0.0)
    kept = irls(d[~out], a[~out], weight[~out], np.zeros(5), pmean, pinv, sigma, kappa, 7, tolerance=0.0)
    np.testing.assert_allclose(left, kept, rtol=1e-10, atol=1e-12)
    c = np.zeros(5)
    for _ in range(5):
        w = weight / (1 + ((d - a @ c) / sigma) ** 2)
        s = 1 / (sigma**2 * kappa)
        c = np.linalg.solve((a * w[:, None]).T @ a * s + pinv, (a * w[:, None]).T @ d * s + pinv @ pmean)
    np.testing.assert_allclose(irls(d, a, weight, np.zeros(5), pmean, pinv, sigma, kappa, 5, tolerance=0.0), c,
                               rtol=1e-9, atol=1e-12)
    bad = d.copy()
    bad[3] = np.inf
    assert np.all(np.isnan(irls(bad, a, weight, np.zeros(5), pmean, pinv, sigma, kappa, 5)))


def _lens_field(k1=-0.55, k2=0.05, center=None):
    return pa_field((H, W), k1, k2, 0.0, center=center)


def test_lens_family_recovers_a_real_lens_field():
    truth = np.log(_lens_field())
    errs = []
    for seed in range(3):
        img = textured(H, W, seed=seed, contrast=0.1) * np.exp(truth)
        m = estimate_family(img)
        assert m.method == "lens-family" and not m.quality.fallback
        assert m.center == (0.0, 0.0)
        errs.append(np.std(m.log_field((H, W)) - truth) / math.log(2))
    assert np.median(errs) < 0.05 < np.std(truth) / math.log(2)


def test_lens_family_sigma_is_stated_and_falls_back_on_no_evidence():
    img = textured(H, W, seed=4, contrast=0.3)
    m = estimate_family(img)
    q = m.quality
    assert q.field_sigma_ev > 0
    if q.fallback:
        assert m.is_identity and m.candidate is not None
    # an image of too few usable pixels: no estimate
    dark = np.zeros((H, W))
    dark[:5, :5] = 1.0
    m = estimate_family(dark)
    assert m.is_identity and m.quality.fallback


def test_hint_narrows_the_prior():
    img = textured(H, W, seed=2, contrast=0.3) * _lens_field()
    c0 = fit_family(img).coefficients
    c1 = fit_family(img, hint=LensHint(focal35=24.0, fnumber=2.8)).coefficients
    assert c0 is not None and c1 is not None and not np.allclose(c0, c1)


def test_centre_fit_finds_an_off_centre_fall_off():
    img = textured(H, W, seed=3, contrast=0.3)
    c = fit_family(img * _lens_field()).coefficients
    centred = fit_centre(img * _lens_field(), c)
    shifted_img = img * _lens_field(center=(-90.0, -60.0))
    c2 = fit_family(shifted_img).coefficients
    shifted = fit_centre(shifted_img, c2)
    s = FamilySettings()
    assert not centred.off_centre(s.off_centre_shift)
    assert shifted.off_centre(s.off_centre_shift)
    # towards the true centre (the fit is pulled towards the frame's: a prior)
    assert shifted.offset[0] < -40 and shifted.offset[1] < -30


def _colour_texture(seed: int = 3) -> np.ndarray:
    """R, G and B textured independently: chroma changes everywhere, so the fit weighs
    pairs by colour (a flat-coloured patchwork weighs most pairs 1 and fits as grey)."""
    return np.stack([textured(H, W, seed=seed + k, contrast=0.05) for k in range(3)], axis=-1)


def test_default_fits_a_strong_off_centre_fall_off_in_the_family_off_centre():
    from benchmarks.synthetic import table1_model
    from vigproc.core.pixels import luminance
    from vigproc.core.robust import estimate_robust

    img = textured(H, W, seed=3, contrast=0.05)
    m = vigproc.estimate(img * _lens_field(), channel_axis=None)
    assert m.method == "lens-family"
    # Lyu's Table 1 setting 2: off-centre and elliptical, beyond the centred family
    truth = table1_model(2)
    frame = _colour_texture() * truth.field()[..., None]
    m = estimate_default(luminance(frame), colour=frame)
    assert m.method == "lens-family-off-centre"
    err = np.std(m.log_field() - truth.log_field())
    family_only = estimate_family(luminance(frame), colour=frame)
    assert err < 0.5 * np.std((family_only.candidate or family_only).log_field() - truth.log_field())
    free = estimate_robust(luminance(frame))
    assert err < np.std((free.candidate or free).log_field() - truth.log_field())
    # its centre is towards the true one, and it states its uncertainty
    assert m.center[0] < -30 and m.center[1] < -20
    assert 0 < m.quality.field_sigma_ev < 0.5 * m.field_ev_rms()
    # a grey frame (or one stored as R = G = B) keeps the free fit: its off-centre family
    # fit would be judged on the very pairs it was fitted to
    grey = img * truth.field()
    assert estimate_default(grey).method == "robust"
    assert estimate_default(grey, colour=np.repeat(grey[..., None], 3, axis=2)).method == "robust"


def _off_centre_kw(p: float) -> "vigproc.VignettingModel":
    """A Kang-Weiss fall-off centred where Lyu's Table 1 setting 2 puts it, of strength ``p``."""
    return vigproc.VignettingModel(W, H, center=(-80.0, -60.0), p=(p, p / 2, 1.5 * p),
                                   alpha=(0.02, 0.01, 0.0, 0.0, 0.0, 0.0, 0.0))


def _spy_free_fits(monkeypatch) -> list:
    """The settings of every free Kang-Weiss fit the default makes."""
    import vigproc.core.estimate as E

    calls, real = [], E.estimate_robust

    def spy(lum, settings, mask=None):
        calls.append(settings)
        return real(lum, settings, mask)

    monkeypatch.setattr(E, "estimate_robust", spy)
    return calls


def test_default_free_fit_drops_the_real_lens_priors_only_for_a_strong_fall_off(monkeypatch):
    """Once the centre tests put a strong fall-off off-centre, the free fit is made without
    the priors of a centred, round real lens and without the scene prior; a fall-off the
    centred fit sees as weaker than OffCentreRule.free_min_ev keeps the robust settings, and
    in a grey frame is not fitted off-centre at all (OffCentreRule.grey_min_ev)."""
    from dataclasses import replace

    from vigproc.core.estimate import OffCentreRule
    from vigproc.core.pixels import luminance
    from vigproc.core.robust import RobustSettings

    img = textured(H, W, seed=3, contrast=0.05)
    calls = _spy_free_fits(monkeypatch)
    strong = _off_centre_kw(1e-4)  # Table 1 setting 2's strength: 2.6 EV RMS
    m = estimate_default(img * strong.field())
    rule = OffCentreRule()
    assert calls == [rule.free_settings] and m.method == "robust"
    assert np.std(m.log_field() - strong.log_field()) / math.log(2) < 0.1
    milder = _off_centre_kw(2e-5)  # 0.8 EV RMS, which the centred fit sees as less
    assert estimate_family(img * milder.field()).quality.field_ev_rms < min(rule.free_min_ev, rule.grey_min_ev)
    calls.clear()
    frame = _colour_texture() * milder.field()[..., None]
    m = estimate_default(luminance(frame), colour=frame)
    # tried with the robust settings; what it finds is weaker than rule.keep_min_ev,
    # where a scene's shading makes off-centre fits win, and the centred fit is kept
    assert calls == [RobustSettings()] and m.method == "lens-family"
    assert estimate_default(luminance(frame), colour=frame, rule=replace(rule, keep_min_ev=0.0)).method == "robust"
    calls.clear()
    m = estimate_default(img * milder.field())
    assert calls == [] and m.method == "lens-family"


def test_default_applies_an_uncertain_off_centre_fit_rather_than_none(monkeypatch):
    """The centred fit surely sees a fall-off and the off-centre fit explains the frame
    better: that fit is applied even when its own uncertainty would have it fall back
    (an identity would be the one answer surely wrong)."""
    import dataclasses

    import vigproc.core.estimate as E

    real = E.estimate_robust

    def unsure(lum, settings, mask=None):
        fit = real(lum, settings, mask)
        fit = dataclasses.replace(fit, quality=dataclasses.replace(fit.quality, fallback=True))
        return vigproc.VignettingModel.identity(W, H, method="robust", quality=fit.quality, candidate=fit)

    monkeypatch.setattr(E, "estimate_robust", unsure)
    truth = _off_centre_kw(1e-4)
    m = estimate_default(textured(H, W, seed=3, contrast=0.05) * truth.field())
    assert m.method == "robust" and not m.is_identity and not m.quality.fallback
    assert np.std(m.log_field() - truth.log_field()) / math.log(2) < 0.1


def test_off_centre_family_fit_recovers_a_shifted_elliptical_lens():
    """A real lens's profile, off-centre and elliptical: fit_off_centre finds its centre
    and shape from the centred fit's start, and its field to a few hundredths of an EV."""
    from vigproc.core.family_fit import fit_off_centre

    fam = default_family()
    prof = fam.mean + np.array([-2.5, 0.3]) @ fam.components[:2]
    truth, _ = profile_to_model(prof, fam.radii, W, H, center=(-70.0, 40.0), shape=(0.3, -0.2))
    img = textured(H, W, seed=5, contrast=0.05)
    frame = img * truth.field()
    c = fit_family(frame).coefficients
    m = fit_off_centre(frame, c)
    assert m is not None and m.method == "lens-family-off-centre" and not m.quality.fallback
    assert abs(m.center[0] + 70) < 15 and abs(m.center[1] - 40) < 15
    assert np.std(m.log_field() - truth.log_field()) / math.log(2) < 0.05


def test_off_centre_family_fit_of_too_few_pixels_is_none():
    from vigproc.core.family_fit import fit_off_centre

    img = textured(H, W, seed=5, contrast=0.05)
    mask = np.zeros((H, W), bool)
    mask[:20, :20] = True
    assert fit_off_centre(img, np.zeros(2), mask=mask) is None


def test_profile_written_off_centre_and_elliptical_matches_it():
    fam = default_family()
    prof = fam.mean + np.array([-1.5, 0.2]) @ fam.components[:2]
    center, (e1, e2) = (60.0, -35.0), (0.25, 0.15)
    model, err = profile_to_model(prof, fam.radii, W, H, center=center, shape=(e1, e2))
    assert err < 0.015  # seven α over a longer span of radii than a centred frame's
    ys, xs = np.mgrid[0:H, 0:W]
    dx = (xs - (W - 1) / 2 - center[0]) / math.hypot((W - 1) / 2, (H - 1) / 2)
    dy = (ys - (H - 1) / 2 - center[1]) / math.hypot((W - 1) / 2, (H - 1) / 2)
    rho = np.sqrt((1 + e1) * dx**2 + 2 * e2 * dx * dy + (1 - e1) * dy**2)
    # past the corner radius of a centred frame the profile goes on linearly
    slope = (prof[-1] - prof[-2]) / (fam.radii[-1] - fam.radii[-2])
    want = np.interp(rho, fam.radii, prof) + np.maximum(rho - 1, 0) * slope
    assert rho.max() > 1.2
    diff = (model.log_field((H, W)) - want) / math.log(2)
    assert np.std(diff) < 0.015 and np.max(np.abs(diff - diff.mean())) < 0.05


def test_colour_weights_leave_out_shading_that_changes_colour():
    """A warm glow from one side of the frame (the scene's light: red brightens most,
    blue least) pulls the fit of the luminance alone; told the frame's colour, the fit
    weighs each pair by how alike its channels change, and the glow's pairs weigh
    little."""
    truth = np.log(_lens_field())
    lum_errs, colour_errs = [], []
    for seed in range(3):
        img = coloured_scene(H, W, seed=seed) * np.exp(truth)[..., None] * np.exp(chromatic_glow(H, W, 1.0))
        lum = vigproc.core.pixels.luminance(img)
        s = FamilySettings(min_snr=0.0, grey_min_snr=0.0)
        for errs, colour in ((lum_errs, None), (colour_errs, img)):
            m = estimate_family(lum, s, colour=colour)
            errs.append(np.std(m.log_field((H, W)) - truth) / math.log(2))
    assert np.median(colour_errs) < 0.05 and np.median(colour_errs) < 0.5 * np.median(lum_errs), \
        (colour_errs, lum_errs)


def test_chroma_covariates_take_up_scene_light_whose_brightness_goes_with_its_colour():
    """A centred glow that whitens as it brightens over a scene of coloured surfaces (R, G
    and B change together inside a surface): its pairs' luminance change goes with their
    chroma change, which no lens makes. With the chroma change as covariates (step 3) the
    glow is not read as less fall-off; without them it is."""
    truth = np.log(_lens_field())
    x = np.linspace(-1.0, 1.0, W)[None, :]
    y = np.linspace(-1.0, 1.0, H)[:, None]
    glow = 0.4 * np.exp(-(x**2 + y**2) / 0.8)[..., None] * np.array([1.0, 0.8, 0.6])
    errs = {0.0: [], 0.3: []}
    for seed in range(4):
        img = coloured_scene(H, W, seed=seed) * np.exp(truth)[..., None] * np.exp(glow)
        lum = vigproc.core.pixels.luminance(img)
        for covariate, out in errs.items():
            m = estimate_family(lum, FamilySettings(min_snr=0.0, chroma_covariate=covariate), colour=img)
            out.append(np.std(m.log_field((H, W)) - truth) / math.log(2))
    assert FamilySettings().chroma_covariate == 0.3
    # the evidence fits (profiles, forensics) keep the model their calibrations were made with
    from vigproc.core.family_fit import EVIDENCE_SETTINGS
    assert EVIDENCE_SETTINGS.chroma_covariate == 0.0
    assert np.median(errs[0.3]) < 0.07 and np.median(errs[0.3]) < 0.5 * np.median(errs[0.0]), errs


def test_a_grey_frame_in_three_channels_fits_as_its_luminance():
    """Channels that change alike weigh every pair 1: the colour fit is the grey one."""
    img = textured(H, W, seed=5, contrast=0.1) * _lens_field()
    rgb = img[..., None] * np.array([0.8, 1.0, 0.6])
    lum = vigproc.core.pixels.luminance(rgb)
    c_grey = fit_family(lum).coefficients
    c_rgb = fit_family(lum, colour=rgb).coefficients
    np.testing.assert_allclose(c_rgb, c_grey, atol=1e-6)
    np.testing.assert_allclose(vigproc.estimate(rgb).field(), vigproc.estimate(lum, channel_axis=None).field(),
                               rtol=1e-5)


def test_a_fit_no_model_can_hold_falls_back(monkeypatch):
    """Data far outside what lenses do can give coefficients whose profile no
    Kang-Weiss model holds (G ≤ 0 in the frame): no correction, the coefficients kept
    (the crop test reads them), no exception."""
    from vigproc.core import family_fit

    def no_model(*a, **k):
        raise ModelError("the geometric factor G falls to -0.1 inside the frame")

    monkeypatch.setattr(family_fit, "profile_to_model", no_model)
    img = textured(H, W, seed=6, contrast=0.1) * _lens_field()
    m, c, _ = fit_family(img)
    assert m.is_identity and m.quality.fallback and m.quality.confidence == 0.0 and m.candidate is None
    assert c is not None and m.quality.snr > 0


@pytest.mark.parametrize("colour_test_steps", [8, 0])
def test_the_default_asks_the_centre_and_the_choice_of_the_luminance(monkeypatch, colour_test_steps):
    """A colour frame's centre must move for the luminance and for the colour-weighted
    pairs; which fit explains the frame better is asked of the luminance alone: the free
    Kang-Weiss fit does not weigh pairs by colour, and a loss weighted by colour would
    favour the fit that does. An off-centre, elliptical fall-off (Table 1 setting 2)
    still goes to an off-centre fit. The colour-weighted pairs' centre is the off-centre
    family fit's own (OffCentreRule.colour_test_steps), or with 0 steps a circular centre
    test's, the off-centre fit made after it."""
    from benchmarks.synthetic import table1_model
    from vigproc.core import estimate as est
    from vigproc.core import family_fit

    seen = []
    real_centre, real_losses, real_off = family_fit.fit_centre, family_fit.pair_losses, est.off_centre_fit

    def centre(*a, **k):
        # colour given, or a working copy that weighs pairs by it
        seen.append(("centre", k.get("colour") if k.get("copy") is None else k["copy"].C))
        return real_centre(*a, **k)

    def off(*a, **k):
        seen.append(("off-centre", a[7].C if len(a) > 7 and a[7] is not None else a[6]))
        return real_off(*a, **k)

    def losses(*a, **k):
        seen.append(("losses", None if np.ndim(a[0]) == 2 else "a colour frame"))  # the luminance, H×W
        return real_losses(*a, **k)

    monkeypatch.setattr(family_fit, "fit_centre", centre)
    monkeypatch.setattr(family_fit, "pair_losses", losses)
    monkeypatch.setattr(est, "off_centre_fit", off)
    img = _colour_texture() * table1_model(2).field()[..., None]
    rule = est.OffCentreRule(colour_test_steps=colour_test_steps)
    m = estimate_default(vigproc.core.pixels.luminance(img), colour=img, rule=rule)
    assert m.method == "lens-family-off-centre"
    expected = [("centre", False), ("off-centre", True), ("losses", False)]
    if not colour_test_steps:
        expected.insert(1, ("centre", True))
    assert [(what, c is not None) for what, c in seen] == expected


def test_a_colour_shift_that_would_send_a_frame_to_the_free_fit_is_the_circular_tests(monkeypatch):
    """The off-centre family fit answers the colour-weighted pairs' centre test only where its
    answer keeps the frame in the family: a shift short of OffCentreRule.family_shift (the
    free fit's band) is asked of the circular test, as before (the elliptical fit's centre
    passed a vignetting-free frame's scene light, and the free fit then applied 2.2 EV)."""
    from dataclasses import replace

    from benchmarks.synthetic import table1_model
    from vigproc.core import estimate as est
    from vigproc.core import family_fit

    seen, real_centre, real_off = [], family_fit.fit_centre, est.off_centre_fit
    rule = est.OffCentreRule()

    def centre(*a, **k):
        seen.append(k["copy"].C is not None)
        return real_centre(*a, **k)

    def off(lum, *a, **k):  # the fit, its centre moved into the free fit's band
        fit = real_off(lum, *a, **k)
        shift = 0.5 * (rule.settings.off_centre_shift + rule.family_shift)
        ux, uy = fit.field.center
        scale = shift / fit.shift(lum.shape)
        return replace(fit, field=replace(fit.field, center=(ux * scale, uy * scale)))

    monkeypatch.setattr(family_fit, "fit_centre", centre)
    monkeypatch.setattr(est, "off_centre_fit", off)
    img = _colour_texture() * table1_model(2).field()[..., None]
    estimate_default(vigproc.core.pixels.luminance(img), colour=img, rule=rule)
    assert seen == [False, True]  # the luminance's test, then the colour-weighted pairs' circular one


def test_a_fit_refused_as_the_colour_test_is_not_the_fit_the_choice_reads(monkeypatch):
    """When the off-centre fit's centre is refused as the colour-weighted pairs' test (its
    shift in the free fit's band) and the circular test then sends the frame to the family's
    off-centre fit, that fit is made as before (up to OFF_CENTRE_ITERATIONS steps): the
    refused fit of OffCentreRule.colour_test_steps steps, whose centre the circular test
    contradicts, is not applied."""
    from dataclasses import replace

    from benchmarks.synthetic import table1_model
    from vigproc.core import estimate as est
    from vigproc.core import family_fit

    calls, real_off = [], est.off_centre_fit
    rule = est.OffCentreRule()
    moved = []

    def off(lum, *a, **k):  # the short fit, its centre moved into the free fit's band
        steps = a[7] if len(a) > 7 else k.get("iterations", family_fit.OFF_CENTRE_ITERATIONS)
        calls.append(steps)
        fit = real_off(lum, *a, **k)
        if steps != rule.colour_test_steps:
            return fit
        shift = 0.5 * (rule.settings.off_centre_shift + rule.family_shift)
        ux, uy = fit.field.center
        scale = shift / fit.shift(lum.shape)
        moved.append((ux * scale, uy * scale))
        return replace(fit, field=replace(fit.field, center=moved[-1]))

    monkeypatch.setattr(est, "off_centre_fit", off)
    img = _colour_texture() * table1_model(2).field()[..., None]
    m = estimate_default(vigproc.core.pixels.luminance(img), colour=img, rule=rule)
    assert calls == [rule.colour_test_steps, family_fit.OFF_CENTRE_ITERATIONS]
    assert m.method == "lens-family-off-centre"
    assert not np.allclose(m.center, moved[0])


def test_a_colour_test_fit_with_no_answer_leaves_the_fit_to_the_old_path(monkeypatch):
    """When the off-centre fit of OffCentreRule.colour_test_steps steps gives no answer (None:
    its shape at the bound within its steps), the circular test decides, and a frame it
    sends to the family's off-centre fit gets that fit of up to OFF_CENTRE_ITERATIONS steps,
    not the free fit at once."""
    from benchmarks.synthetic import table1_model
    from vigproc.core import estimate as est
    from vigproc.core import family_fit

    calls, real_off = [], est.off_centre_fit
    rule = est.OffCentreRule()

    def off(lum, *a, **k):  # the short fit gives no answer
        steps = a[7] if len(a) > 7 else k.get("iterations", family_fit.OFF_CENTRE_ITERATIONS)
        calls.append(steps)
        return None if steps == rule.colour_test_steps else real_off(lum, *a, **k)

    monkeypatch.setattr(est, "off_centre_fit", off)
    img = _colour_texture() * table1_model(2).field()[..., None]
    m = estimate_default(vigproc.core.pixels.luminance(img), colour=img, rule=rule)
    assert calls == [rule.colour_test_steps, family_fit.OFF_CENTRE_ITERATIONS]
    assert m.method == "lens-family-off-centre"


def test_a_channel_too_dark_to_use_makes_a_grey_fit():
    """A frame whose blue is too dark to read everywhere (an empty channel, sodium
    light) is fitted as a grey frame, not dropped for want of pixels."""
    img = textured(H, W, seed=7, contrast=0.1) * _lens_field()
    rgb = img[..., None] * np.array([1.0, 0.8, 0.0])
    lum = vigproc.core.pixels.luminance(rgb)
    c_grey = fit_family(lum).coefficients
    m, c_rgb, _ = fit_family(lum, colour=rgb)
    assert c_rgb is not None and not m.quality.fallback
    np.testing.assert_allclose(c_rgb, c_grey, atol=1e-6)


def test_estimate_reads_the_colour_of_a_colour_frame():
    """vigproc.estimate hands a colour frame's R, G, B to the lens-family fit: a warm
    glow from one side pulls the estimate of its luminance alone, not the colour one."""
    truth = np.log(_lens_field())
    img = coloured_scene(H, W, seed=1) * np.exp(truth)[..., None] * np.exp(chromatic_glow(H, W, 1.0))
    lum = vigproc.core.pixels.luminance(img)
    err = {k: np.std(vigproc.estimate(x, "lens-family", channel_axis=ax).log_field() - truth) / math.log(2)
           for k, x, ax in (("colour", img, -1), ("grey", lum, None))}
    assert err["colour"] < 0.5 * err["grey"], err


def test_colour_of_another_shape_is_refused():
    img = textured(H, W, seed=8, contrast=0.1)
    from vigproc.errors import InvalidImageError

    for bad in (np.stack([img] * 3), img, np.stack([img] * 3, axis=-1)[:-1], np.stack([img] * 2, axis=-1)):
        with pytest.raises(InvalidImageError, match="colour must be"):
            fit_family(img, colour=bad)


def test_coloured_light_off_centre_does_not_send_a_colour_frame_to_the_free_fit():
    """A warm glow from one side moves the luminance's fall-off centre, and a grey frame
    tried off-centre would go to the free Kang-Weiss fit; a colour frame's centre must also
    move for its colour-weighted pairs, which leave the glow out: it stays with the lens
    family."""
    from vigproc.core.estimate import OffCentreRule

    anything_off_centre = OffCentreRule(grey_min_ev=0.0, keep_min_ev=0.0)
    for seed in (0, 3, 5):
        img = coloured_scene(H, W, seed=seed) * _lens_field()[..., None] * np.exp(chromatic_glow(H, W, 1.5))
        lum = vigproc.core.pixels.luminance(img)
        # the grey frame's fall-off is too weak to be tried off-centre at all ...
        assert estimate_default(lum).method == "lens-family"
        # ... and were it tried, the glow would send it to the free fit
        assert estimate_default(lum, rule=anything_off_centre).method == "robust"
        assert estimate_default(lum, colour=img).method == "lens-family"


def test_a_centre_fit_without_its_uncertainty_answers_for_the_shift():
    """The default's centre test skips the jackknife: z is NaN, and the shift alone decides."""
    lum = textured(160, 240, seed=5, contrast=0.05) * _lens_field(center=(50.0, 0.0))[::2, ::2]
    fam = default_family()
    full = fit_centre(lum, fam.prior()[0], family=fam)
    quick = fit_centre(lum, fam.prior()[0], family=fam, uncertainty=False)
    assert quick.offset == full.offset and quick.shift == full.shift
    assert np.isnan(quick.z) and np.all(np.isnan(quick.covariance - np.eye(2) * 1e-6))
    assert quick.off_centre(0.5 * full.shift) == full.off_centre(0.5 * full.shift) is True
    assert not quick.off_centre(0.5 * full.shift, min_z=1.0)  # a z it does not have is not met


def test_a_fit_not_weighted_by_colour_reads_its_own_cauchy_scale():
    """grey_sigma is the Cauchy scale of a fit whose pairs are not weighted by colour; a
    colour-weighted fit reads sigma. The evidence fits keep one scale for both (their
    calibrations were made so)."""
    from vigproc.core.family_fit import EVIDENCE_SETTINGS, FamilySettings

    grey = textured(H, W, seed=6, contrast=0.1) * _lens_field()
    coef = lambda **kw: fit_family(grey, FamilySettings(**kw)).coefficients  # noqa: E731
    assert np.array_equal(coef(grey_sigma=0.01), coef(sigma=0.02, grey_sigma=0.01))
    assert not np.array_equal(coef(grey_sigma=0.01), coef(grey_sigma=0.004))
    frame = _colour_texture(6) * _lens_field()[..., None]
    lum = vigproc.core.pixels.luminance(frame)
    col = lambda **kw: fit_family(lum, FamilySettings(**kw), colour=frame)  # noqa: E731
    assert col().colour_weighted
    assert np.array_equal(col(grey_sigma=0.01).coefficients, col(grey_sigma=0.004).coefficients)
    assert EVIDENCE_SETTINGS.grey_sigma == EVIDENCE_SETTINGS.sigma


def test_a_colour_weighted_fit_uses_every_component_a_grey_one_two():
    """Pairs weighted by colour let a third component pay; a grey frame, or one stored as
    R = G = B (every weight 1), keeps to the first two."""
    from vigproc.core.family_fit import colour_weighted, family_for
    from vigproc.core.lensfamily import profile_family

    fam = profile_family()
    # channels with textures of their own: the chroma changes everywhere, as in a
    # photograph's foliage or fabric (the weights average well below 0.5)
    scene = np.stack([textured(H, W, seed=30 + k, contrast=0.1) for k in range(3)], axis=-1)
    img = scene * _lens_field()[..., None]
    lum = vigproc.core.pixels.luminance(img)
    fits = [fit_family(lum, family=f, colour=c) for f in (fam, fam.truncated(2))
            for c in (img, None, np.repeat(lum[..., None], 3, axis=-1))]
    assert [len(f.coefficients) for f in fits] == [3, 2, 2, 2, 2, 2]
    # the flag says how the pairs were weighed, whatever the family's size: a caller
    # cannot read it from the number of coefficients
    assert [f.colour_weighted for f in fits] == [True, False, False, True, False, False]
    assert colour_weighted(np.full(10, 0.1)) and not colour_weighted(np.ones(10))
    assert not colour_weighted(np.zeros(0))
    assert family_for(fam, True) is fam and family_for(fam, False).n_components == 2
    assert family_for(fam.truncated(1), False).n_components == 1


def test_a_strip_too_thin_for_any_pair_step_is_no_crash():
    """A 32:1 strip: its centre test's working copy is one bin high, so no pair step
    fits; the fits answer (no pairs) instead of failing."""
    strip = textured(90, 2880, seed=8, contrast=0.05)
    m = vigproc.estimate(strip, channel_axis=None)
    assert m.width == 2880 and m.height == 90
    d, a, labels, w = family_pairs(np.zeros((1, 5)), np.ones((1, 5), bool), np.zeros((1, 5)),
                                   np.zeros((1, 5, 2)), np.array([1, 2], dtype=np.int64),
                                   np.zeros((1, 5), np.int64), None, 0.003)
    assert d.shape == (7,) and a.shape == (7, 2)  # x pairs only: 4 one apart, 3 two apart
    d, a, labels, w = family_pairs(np.zeros((1, 1)), np.ones((1, 1), bool), np.zeros((1, 1)),
                                   np.zeros((1, 1, 2)), np.array([], dtype=np.int64),
                                   np.zeros((1, 1), np.int64), None, 0.003)
    assert d.shape == (0,) and a.shape == (0, 2) and labels.dtype == np.int64 and w.shape == (0,)


def test_a_grey_fit_states_its_sigma_on_the_grey_scale():
    """A fit whose pairs are not weighted by colour has its own σ scale (calibrated on
    luminance fits); a colour-weighted fit's σ does not read it."""
    from dataclasses import replace

    grey = textured(H, W, seed=4, contrast=0.05) * _lens_field()
    colour = _colour_texture(seed=4) * _lens_field()[..., None]
    s = FamilySettings()
    for frame, col, follows in ((grey, None, True), (colour, colour, False)):
        lum = frame if frame.ndim == 2 else vigproc.core.pixels.luminance(frame)
        a = fit_family(lum, s, colour=col).model
        b = fit_family(lum, replace(s, grey_sigma_scale=2 * s.grey_sigma_scale), colour=col).model
        ratio = b.quality.field_sigma_ev / a.quality.field_sigma_ev
        assert (1.6 < ratio < 2.01) if follows else ratio == 1.0


def test_a_grey_fit_falls_back_on_its_own_threshold():
    """The do-no-harm threshold (field / σ) is ``grey_min_snr`` for a fit whose pairs are
    not weighted by colour and ``min_snr`` for one whose are: each reads its own σ scale."""
    from dataclasses import replace

    grey = textured(H, W, seed=4, contrast=0.05) * _lens_field()
    colour = _colour_texture(seed=4) * _lens_field()[..., None]
    s = FamilySettings()
    for frame, col, own in ((grey, None, "grey_min_snr"), (colour, colour, "min_snr")):
        lum = frame if frame.ndim == 2 else vigproc.core.pixels.luminance(frame)
        snr = (fit_family(lum, s, colour=col).model.candidate or fit_family(lum, s, colour=col).model).quality.snr
        other = "min_snr" if own == "grey_min_snr" else "grey_min_snr"
        # above its own threshold: falls back; the other threshold is not read
        assert fit_family(lum, replace(s, **{own: snr * 1.01}), colour=col).model.quality.fallback
        assert not fit_family(lum, replace(s, **{own: snr * 0.99, other: snr * 2}), colour=col).model.quality.fallback


def test_a_frame_whose_centred_fit_sees_little_is_not_fitted_off_centre(monkeypatch):
    """Where the centred fit rules out OffCentreRule.any_min_ev of fall-off (at 2σ), no
    off-centre fit is tried: a free fit there follows the scene's light (a camera JPEG of
    a lit room had 1.32 EV removed by it at confidence 1.00)."""
    import vigproc.core.estimate as est
    import vigproc.core.family_fit as ff

    def refuse(*a, **k):
        raise AssertionError("an off-centre fit was tried")

    monkeypatch.setattr(ff, "fit_centre", refuse)
    monkeypatch.setattr(est, "estimate_robust", refuse)
    weak = textured(H, W, seed=4, contrast=0.1) * _lens_field(k1=-0.15, k2=0.0)
    m = estimate_default(weak)
    assert m.method == "lens-family"
    q = (m.candidate or m).quality
    assert q.field_ev_rms + 2 * q.field_sigma_ev < est.OffCentreRule().any_min_ev
    # a strong fall-off still asks where its centre is (a colour frame: a grey one's
    # fall-off must be stronger still, OffCentreRule.grey_min_ev)
    frame = _colour_texture(4) * _lens_field()[..., None]
    with pytest.raises(AssertionError, match="off-centre fit was tried"):
        estimate_default(vigproc.core.pixels.luminance(frame), colour=frame)


def test_a_lit_room_is_not_corrected_by_a_free_fit(shared_data):
    """The Canon IXUS 400 JPEG of ../shared/data (a museum room lit from above): its
    centred fit sees 0.02 EV, and the default leaves it alone (the free fit removed 1.32 EV)."""
    from vigproc.core.estimate import estimate
    from vigproc.io import read_image

    f = shared_data / "jpeg_exif" / "metadata-extractor-images" / "Canon_IXUS_400.jpg"
    if not f.is_file():
        pytest.skip(f"{f} not present")
    m = estimate(read_image(f)[0], channel_axis=-1)
    assert m.method == "lens-family" and m.field_ev_rms() < 0.25


def test_family_expresses_a_full_frame_lens_seen_by_a_smaller_sensor():
    # A DX / APS-C body behind a full-frame lens sees the lens's field out to ρ = 1/1.5 of
    # its calibration only; the family is built from fields over their own whole frame. Every
    # full-frame calibration lensfun holds, cut there and stretched to the frame, must still
    # lie in the family the default fits (3 components; 2 for a grey frame), as close as the
    # native calibrations do (docs/benchmarks/real-frames.md). One component does not hold
    # them (p90 0.022 EV).
    from vigproc.core.lensfamily import PLAUSIBLE, profile_family
    from vigproc.stores.lensfun import load_lenses, pa_poly

    fam = profile_family()
    ks = np.array([(v.k1, v.k2, v.k3) for lens in load_lenses() if lens.crop_factor <= 1.05
                   for v in lens.vignetting])
    r2 = fam.radii[None, :] ** 2
    full = pa_poly(r2, *ks.T[:, :, None])
    ks = ks[(full.min(axis=1) > PLAUSIBLE[0]) & (full.max(axis=1) <= PLAUSIBLE[1])]
    assert len(ks) > 5000
    cut = np.log(pa_poly(r2 / 1.5**2, *ks.T[:, :, None])) - fam.mean

    def floor_ev(k):
        c = fam.components[:k]
        return np.sqrt(np.mean((cut - cut @ c.T @ c) ** 2, axis=1)) / math.log(2)

    assert np.max(floor_ev(3)) < 0.005
    assert np.percentile(floor_ev(2), 90) < 0.01
    assert np.percentile(floor_ev(1), 90) > 0.01  # the test can tell a family that cannot
