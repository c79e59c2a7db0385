"""The frame's ambiguity between scene and lens (half fits against the whole frame's) and
the fit shrunk toward the EXIF population by it (vigproc.core.ambiguity)."""

import math

import numpy as np

from vigproc.core.ambiguity import Ambiguity, ambiguity, estimate_shrunk, shrunk_fit
from vigproc.core.estimate import estimate_default
from vigproc.core.family_fit import FamilySettings, LensHint, family_for, fit_family
from vigproc.core.lensfamily import profile_family
from vigproc.stores.lensfun import pa_field

from conftest import textured

H, W = 160, 240
HINT = LensHint(focal35=50.0, fnumber=2.8)


def _lens() -> np.ndarray:
    return pa_field((H, W), -0.35, 0.05, 0.0)


def _scene_falloff() -> np.ndarray:
    # a scene darker below than above (a road under a bright sky): not a lens's, not centred
    y = np.linspace(-1.0, 1.0, H)[:, None]
    return np.exp(-1.2 * np.clip(y, 0.0, None) ** 2) * np.ones((1, W))


def _fit_and_amb(lum):
    fit = fit_family(lum, FamilySettings(), None, None, HINT)
    return fit, ambiguity(lum, fit, None, HINT)


def test_a_lens_field_on_a_plain_scene_is_kept():
    lum = textured(H, W, seed=5, contrast=0.2) * _lens()
    fit, amb = _fit_and_amb(lum)
    assert amb.halves == 4
    assert amb.prior_spread_ev > 0
    # the halves see one field: little disagreement, the fit is mostly kept
    assert amb.disagreement_ev < 0.5 * amb.prior_spread_ev
    assert amb.weight > 0.8
    # the whole disagreement holds the halves' own noise too: never less than the scene's part
    raw = ambiguity(lum, fit, None, HINT, subtract_noise=False)
    assert raw.disagreement_ev >= amb.disagreement_ev and raw.weight <= amb.weight


def test_a_one_sided_scene_falloff_is_read_as_ambiguity():
    plain = _fit_and_amb(textured(H, W, seed=5, contrast=0.2) * _lens())[1]
    _, amb = _fit_and_amb(textured(H, W, seed=5, contrast=0.2) * _lens() * _scene_falloff())
    # the bottom half's fit sees the road, the top's does not
    assert amb.disagreement_ev > 2 * plain.disagreement_ev
    assert amb.weight < plain.weight


def test_the_weight_moves_the_field_between_the_fit_and_the_population():
    lum = textured(H, W, seed=6, contrast=0.2) * _lens()
    fit, amb = _fit_and_amb(lum)
    assert shrunk_fit(lum, fit, Ambiguity(amb.disagreement_ev, amb.prior_spread_ev, 1.0, 4), HINT) is fit.model
    pop = shrunk_fit(lum, fit, Ambiguity(math.inf, amb.prior_spread_ev, 0.0, 4), HINT)
    half = shrunk_fit(lum, fit, Ambiguity(amb.prior_spread_ev, amb.prior_spread_ev, 0.5, 4), HINT)
    fit_log = fit.model.log_field((H, W))
    pop_log = pop.log_field((H, W))
    half_log = half.log_field((H, W))
    gain_free = lambda x: x - x.mean()  # noqa: E731
    np.testing.assert_allclose(gain_free(half_log), gain_free(0.5 * (fit_log + pop_log)), atol=0.02)
    assert not np.allclose(gain_free(pop_log), gain_free(fit_log), atol=0.02)
    # weight 0 is the population mean's field: its corner (ρ = 1) against its centre, EV
    fam = family_for(profile_family(), fit.colour_weighted)
    pm, _ = fam.prior(HINT.focal35, HINT.fnumber)
    want = float(np.diff(fam.log_profile(pm, np.array([0.0, 1.0])))[0]) / math.log(2)
    got = float(pop_log[0, 0] - pop_log[H // 2, W // 2]) / math.log(2)
    assert abs(got - want) < 0.05


def test_without_exif_the_default_comes_back_unchanged():
    lum = textured(H, W, seed=7, contrast=0.2) * _lens() * _scene_falloff()
    a = estimate_default(lum)
    b = estimate_shrunk(lum)
    assert a.alpha == b.alpha and a.p == b.p and a.is_identity == b.is_identity
