"""The estimator's compiled passes give what the NumPy they replaced gave, and the default's
off-centre choice reuses its working copies and defers the off-centre fit's jackknife
without changing its answer."""

import math

import numpy as np
import pytest

from vigproc.core._kernels.robust import CAUCHY, HUBER, POWER, normal_equations
from vigproc.core.estimate import OffCentreRule, _off_centre_choice
from vigproc.core.family_fit import (FamilySettings, _geometry_columns, _geometry_pairs, fit_family, fit_off_centre,
                                     corner_radius, luminance_copy, off_centre_fit, pairs_at, settings_index,
                                     with_colour)
from vigproc.core.lensfamily import profile_family
from vigproc.core.pixels import luminance

from conftest import textured

H, W = 200, 300


def _table1_colour_frame() -> np.ndarray:
    from benchmarks.synthetic import table1_model

    scene = np.stack([textured(H, W, seed=3 + k, contrast=0.05) for k in range(3)], axis=-1)
    return scene * table1_model(2).field((H, W))[..., None]


def _colour_pairs():
    """The default settings, and the Table 1 colour frame's log working copy L, its pairs
    (colour-weighted) and its bins' centres (w,), (h,) in half-diagonals."""
    frame = _table1_colour_frame()
    s = FamilySettings()
    L, valid, xs, ys, C, _ = with_colour(luminance_copy(luminance(frame), s, None), frame, s)
    radius = corner_radius(W, H)
    return s, L, settings_index(L, valid, C, s), xs / radius, ys / radius


@pytest.mark.parametrize("geo", [[0.0, 0.0], [0.3, -0.2], [0.0, 0.0, 0.0, 0.0], [0.5, 0.4, 0.6, -0.3],
                                 [1.5, 0.4, 0.1, -0.3]])
def test_geometry_pairs_are_the_numpy_columns_differenced(geo):
    """One compiled pass over the bins and the pairs (centre only, or centre and shape; a
    centre off the frame puts bins past the profile's last radius) gives the bits of
    _geometry_columns' field and derivatives differenced over the pairs by pairs_at."""
    s, L, index, X, Y = _colour_pairs()
    fam = profile_family()
    X, Y = X[None, :], Y[:, None]
    coef = np.array([0.4, -0.2, 0.1])
    geo = np.array(geo)
    want_d, want_a = pairs_at(index, *_geometry_columns(fam, coef, geo, X, Y))
    d, a = _geometry_pairs(index, X.ravel(), Y.ravel(), fam, coef, geo)
    assert a.shape == want_a.shape == (d.size, 3 + geo.size)
    np.testing.assert_array_equal(d, want_d)
    np.testing.assert_array_equal(a, want_a)


@pytest.mark.parametrize("kind", [CAUCHY, HUBER])
def test_robust_normal_equations_match_their_definition(kind):
    """The chunked sums (more pairs than a chunk, and not a multiple of it) are Σ w/σ²·j·jᵀ
    and Σ w/σ²·j·e over every pair of usable bins."""
    rng = np.random.default_rng(4)
    h, w, n = 23, 31, 12
    L = rng.normal(size=(h, w)) * 0.05
    F = rng.normal(size=(h, w)) * 0.05
    J = rng.normal(size=(h, w, n))
    valid = rng.random((h, w)) > 0.15
    steps = np.array([1, 2, 4], dtype=np.int64)
    sigma = np.array([0.02, 0.03, 0.05])
    Hm, g, loss, npairs = normal_equations(L, valid, F, J, steps, sigma, kind)
    want_H, want_g, want_loss, count = np.zeros((n, n)), np.zeros(n), 0.0, 0
    for si, s in enumerate(steps):
        for dy, dx in ((0, s), (s, 0)):
            for y in range(h - dy):
                for x in range(w - dx):
                    if not (valid[y, x] and valid[y + dy, x + dx]):
                        continue
                    e = L[y + dy, x + dx] - L[y, x] - F[y + dy, x + dx] + F[y, x]
                    u2 = e * e / sigma[si] ** 2
                    if kind == CAUCHY:
                        rho, wt = math.log1p(u2), 1 / (1 + u2)
                    else:
                        rho, wt = (0.5 * u2, 1.0) if u2 <= 1 else (math.sqrt(u2) - 0.5, 1 / math.sqrt(u2))
                    j = J[y + dy, x + dx] - J[y, x]
                    want_H += wt / sigma[si] ** 2 * np.outer(j, j)
                    want_g += wt / sigma[si] ** 2 * j * e
                    want_loss += rho
                    count += 1
    assert npairs == count > 256 and count % 256
    np.testing.assert_allclose(Hm, want_H, rtol=1e-12, atol=1e-12 * np.abs(want_H).max())
    np.testing.assert_allclose(g, want_g, rtol=1e-12, atol=1e-12 * np.abs(want_g).max())
    assert loss == pytest.approx(want_loss, rel=1e-12)
    np.testing.assert_array_equal(Hm, Hm.T)


def test_off_centre_fit_states_its_field_before_its_uncertainty():
    """The deferred fit's field is fit_off_centre's, and its uncertainty, asked for, is
    fit_off_centre's σ and fall-back: the default reads the field to choose and pays for
    the jackknife only for a fit it keeps."""
    frame = _table1_colour_frame()
    lum = luminance(frame)
    s = OffCentreRule().settings
    c = fit_family(lum, FamilySettings(), colour=frame).coefficients
    whole = fit_off_centre(lum, c, s, colour=frame)
    part = off_centre_fit(lum, c, s, colour=frame)
    assert whole is not None and part is not None
    fitted = whole.candidate or whole
    assert (part.field.center, part.field.p, part.field.alpha) == (fitted.center, fitted.p, fitted.alpha)
    assert math.isnan(part.field.quality.field_sigma_ev) and not part.field.quality.fallback
    later = part.with_uncertainty()
    assert later.quality.field_sigma_ev == whole.quality.field_sigma_ev > 0
    assert later.quality.fallback == whole.quality.fallback
    assert later.quality.snr == whole.quality.snr


def test_off_centre_choice_is_the_same_with_the_default_s_working_copies():
    """Given the default's own working copies (its settings make the same ones), the choice
    is the one it makes binning the frame again for each fit."""
    frame = _table1_colour_frame()
    lum = luminance(frame)
    fs = FamilySettings()
    work = luminance_copy(lum, fs, None)
    work_colour = with_colour(work, frame, fs)
    fit = fit_family(lum, fs, colour=frame, copy=work_colour)
    rule = OffCentreRule()
    again = _off_centre_choice(lum, None, None, None, frame, rule, fit)
    shared = _off_centre_choice(lum, None, None, None, frame, rule, fit, (work, work_colour))
    assert shared.method == again.method == "lens-family-off-centre"
    assert (shared.center, shared.p, shared.alpha) == (again.center, again.p, again.alpha)
    assert shared.quality.field_sigma_ev == again.quality.field_sigma_ev


def test_the_fits_the_choice_weighs_state_their_own_field_rms():
    """The off-centre choice reads a fit's stated field RMS instead of computing it again:
    the off-centre family fit and the free fit (applied or not) state their model's own."""
    from vigproc.core.robust import RobustSettings, estimate_robust

    frame = _table1_colour_frame()
    lum = luminance(frame)
    rule = OffCentreRule()
    c = fit_family(lum, FamilySettings(), colour=frame).coefficients
    fits = [off_centre_fit(lum, c, rule.settings, colour=frame).field]
    for settings in (rule.free_settings, RobustSettings()):
        m = estimate_robust(lum, settings)
        fits.append(m.candidate or m)
    for m in fits:
        assert m.quality.field_ev_rms == m.field_ev_rms() > 0.5


def _geometry_fit_reference(index, X, Y, fam, c, pm, pinv, settings, elliptical, iterations, tolerance=1e-3):
    """The Gauss-Newton loop in Python over _geometry_pairs and _solve (what the compiled
    loop replaced), step for step."""
    from vigproc.core.family_fit import MAX_ELLIPTICITY, _solve

    K = fam.n_components
    E = 4 if elliptical else 2
    geo = np.zeros(E)
    coef = np.asarray(c, dtype=np.float64).copy()
    d = a = sol = pm_it = None
    steps = 0
    xs, ys = np.ascontiguousarray(np.ravel(X)), np.ascontiguousarray(np.ravel(Y))
    for _ in range(iterations):
        d, a = _geometry_pairs(index, xs, ys, fam, coef, geo)
        x0 = np.concatenate([coef, np.zeros(E)])
        pm_it = pm.copy()
        pm_it[K:] = -geo
        sol = _solve(d, a, index.weight, x0, pm_it, pinv, settings, 4)
        if not np.all(np.isfinite(sol)):
            break
        steps += 1
        coef = sol[:K]
        step = sol[K:].copy()
        if elliptical:
            e = geo[2:] + step[2:]
            size = float(np.hypot(*e))
            if size > MAX_ELLIPTICITY:
                step[2:] = e * (MAX_ELLIPTICITY / size) - geo[2:]
        geo = geo + step
        if float(np.max(np.abs(sol[K:]))) < tolerance:
            break
    return coef, geo, d, a, sol, pm_it, steps


@pytest.mark.parametrize("elliptical, iterations", [(False, 12), (True, 30), (True, 3)])
def test_geometry_fit_in_one_compiled_loop_is_the_python_loop(elliptical, iterations):
    """The compiled Gauss-Newton loop (the centre test's circular fit, the off-centre fit's
    elliptical one, and one stopped by its step limit) takes the Python loop's steps: the
    same number, and every output equal to 1e-9 (relative). Not the same bits: the compiled
    loop sums each IRLS step's normal equations over the bins (Jᵀ·L·J), the Python loop over
    the pairs, and the two orders round differently (a few 1e-16 in the sums, about 1e-10
    in the coefficients after the solves)."""
    from vigproc.core.family_fit import _geometry_fit, _prior_with_geometry, LensHint

    frame = _table1_colour_frame()
    s = OffCentreRule().settings
    lum = luminance(frame)
    c = fit_family(lum, FamilySettings(), colour=frame).coefficients
    L, valid, xs, ys, C, _ = with_colour(luminance_copy(lum, s, None), frame, s)
    index = settings_index(L, valid, C, s)
    fam = profile_family().truncated(len(c))
    radius = corner_radius(W, H)
    pm, pinv = _prior_with_geometry(fam, LensHint(), 4 if elliptical else 2, 0.5)
    args = (index, xs[None, :] / radius, ys[:, None] / radius, fam, c, pm, pinv, s, elliptical, iterations)
    got = _geometry_fit(*args)
    want = _geometry_fit_reference(*args)
    assert got[6] == want[6] >= min(iterations, 3)
    for g, w in zip(got[:6], want[:6]):
        np.testing.assert_allclose(g, w, rtol=1e-9, atol=1e-9 * float(np.max(np.abs(w))))


def test_comparison_fit_started_from_a_fit_ends_where_it_ends_from_the_prior():
    """The luminance's comparison fit started from the colour fit's coefficients (as the
    default estimator starts it) reaches the fit it reaches from the prior mean, to the
    IRLS's own tolerance."""
    frame = _table1_colour_frame()
    lum = luminance(frame)
    s = OffCentreRule().settings
    coef = fit_family(lum, FamilySettings(), colour=frame).coefficients
    work = luminance_copy(lum, s, None)
    cold = fit_family(lum, s, uncertainty=False, copy=work)
    warm = fit_family(lum, s, uncertainty=False, copy=work, start=coef)
    assert len(coef) > len(warm.coefficients)  # the colour fit has a component more: the first ones start
    assert not np.array_equal(warm.coefficients, cold.coefficients)
    np.testing.assert_allclose(warm.coefficients, cold.coefficients, atol=20 * s.tolerance)
    again = fit_family(lum, s, uncertainty=False, copy=work, start=warm.coefficients)
    np.testing.assert_allclose(again.coefficients, warm.coefficients, atol=2 * s.tolerance)


def test_pair_losses_read_the_pairs_listed_for_the_fit_they_judge():
    """The comparison's losses from the pairs listed for the luminance's fit (jackknife
    labels and all) are the losses of the pairs it lists for itself, to the bit."""
    from vigproc.core.family_fit import pair_losses

    frame = _table1_colour_frame()
    lum = luminance(frame)
    s = OffCentreRule().settings
    work = luminance_copy(lum, s, None)
    index = settings_index(work.L, work.valid, None, s)
    grey = fit_family(lum, s, uncertainty=False, copy=work, index=index).model
    alone = fit_family(lum, s, uncertainty=False, copy=work).model
    assert (grey.p, grey.alpha) == (alone.p, alone.alpha)
    c = fit_family(lum, FamilySettings(), colour=frame).coefficients
    models = [grey.candidate or grey, off_centre_fit(lum, c, s, colour=frame).field]
    assert pair_losses(lum, models, s, None, work, index) == pair_losses(lum, models, s, None, work)


@pytest.mark.parametrize("K", [1, 2, 5, 7])
def test_irls_normal_equations_two_sums_a_pass_are_their_definition(K):
    """The IRLS step's sums (two of H's entries a pass over the pairs, and the odd one left
    over) are Σ w·a·aᵀ and Σ w·a·d with w = weight / (1 + ((d − a·c)/σ)²), symmetric."""
    from vigproc.core._kernels.irls import weighted_normal

    rng = np.random.default_rng(K)
    n = 1001
    at = rng.standard_normal((K, n))
    d = 0.01 * rng.standard_normal(n)
    weight = rng.uniform(0.0, 1.0, n)
    c = 1e-3 * rng.standard_normal(K)
    Hm, g = np.full((K, K), np.nan), np.full(K, np.nan)
    weighted_normal(at, d, weight, c, 100.0, Hm, g, np.empty((2, n)))
    w = weight / (1.0 + ((d - c @ at) * 100.0) ** 2)
    want_H = (at * w) @ at.T
    np.testing.assert_allclose(Hm, want_H, rtol=1e-12, atol=1e-12 * np.abs(want_H).max())
    np.testing.assert_allclose(g, (at * w) @ d, rtol=1e-12, atol=1e-14)
    np.testing.assert_array_equal(Hm, Hm.T)


@pytest.mark.parametrize("geo", [[0.3, -0.2], [0.5, 0.4, 0.6, -0.3]])
def test_normal_equations_over_bins_are_the_sums_over_pairs(geo):
    """An IRLS step's sums over the bins (Jᵀ·L·J and Jᵀ·z of the pairs laid out as slots) are
    its sums over the pairs, Σ w·a·aᵀ and Σ w·a·d, to rounding, on a colour frame's pairs
    (weights between 0 and 1, every step and direction) with its field's derivatives."""
    from vigproc.core._kernels.bin_normal import bin_normal, pair_slots, slot_data
    from vigproc.core._kernels.geometry import fill_geometry_bins
    from vigproc.core.family_fit import _profile_slopes

    s, L, index, X, Y = _colour_pairs()
    fam = profile_family()
    coef, geo = np.array([0.4, -0.2, 0.1]), np.array(geo)
    d, a = _geometry_pairs(index, X, Y, fam, coef, geo)
    K = a.shape[1]
    c = np.concatenate([coef, 0.01 * np.arange(1, geo.size + 1)])
    w = index.weight / (1.0 + ((d - a @ c) / s.sigma) ** 2)
    want_H, want_g = (a.T * w) @ a, (a.T * w) @ d
    nb = L.size
    grads = _profile_slopes(fam)
    M, J = np.empty(nb), np.empty((K, nb))
    fill_geometry_bins(X, Y, geo, fam.radii, fam.mean, fam.components, grads[0] + coef @ grads[1], M, J)
    offs, invs, dl, wt = pair_slots(index.first, index.second, index.inv_step, index.dlog, index.weight, nb)
    assert sorted(offs) == sorted({st * m for st in s.steps for m in (1, L.shape[1])})
    ds = np.empty(dl.shape)
    slot_data(M, offs, invs, dl, ds)
    Hm, g = np.full((K, K), np.nan), np.full(K, np.nan)
    bin_normal(J, ds, wt, offs, invs, c, 1.0 / s.sigma, Hm, g, np.empty((2 * offs.size + 3, nb)))
    np.testing.assert_allclose(Hm, want_H, rtol=1e-12, atol=1e-12 * np.abs(want_H).max())
    np.testing.assert_allclose(g, want_g, rtol=1e-12, atol=1e-12 * np.abs(want_g).max())
    np.testing.assert_array_equal(Hm, Hm.T)


@pytest.mark.parametrize("kind", [CAUCHY, HUBER, POWER])
def test_robust_normal_equations_without_the_loss_are_the_same_system(kind):
    """The system without its loss (what the Levenberg-Marquardt steps read) is the system
    with it, bit for bit, and states no loss."""
    rng = np.random.default_rng(5)
    h, w, n = 19, 27, 12
    L, F = rng.normal(size=(h, w)) * 0.05, rng.normal(size=(h, w)) * 0.05
    J = rng.normal(size=(h, w, n))
    valid = rng.random((h, w)) > 0.15
    steps, sigma = np.array([1, 2, 4], dtype=np.int64), np.array([0.02, 0.03, 0.05])
    H1, g1, loss, n1 = normal_equations(L, valid, F, J, steps, sigma, kind)
    H2, g2, none, n2 = normal_equations(L, valid, F, J, steps, sigma, kind, False)
    np.testing.assert_array_equal(H1, H2)
    np.testing.assert_array_equal(g1, g2)
    assert n1 == n2 > 0 and math.isfinite(loss) and math.isnan(none)


def test_robust_pair_count_is_the_loss_s():
    """The pairs counted alone are the pairs the robust loss sums over."""
    from vigproc.core._kernels.robust import count_pairs, robust_loss

    rng = np.random.default_rng(6)
    valid = rng.random((21, 33)) > 0.2
    steps = np.array([1, 2, 4], dtype=np.int64)
    L, F = rng.normal(size=valid.shape), rng.normal(size=valid.shape)
    assert count_pairs(valid, steps) == robust_loss(L, valid, F, steps, np.full(3, 0.02))[1] > 0


def _bins_against_pairs(h, w, steps, seed, K=4):
    """The sums over bins of a random h×w copy's pairs with ``steps`` (random regressors,
    weights and field, some bins unusable) against the sums over its pairs: (H, g) of both,
    and the slots' offsets."""
    from vigproc.core._kernels.bin_normal import bin_normal, pair_slots, slot_data
    from vigproc.core.family_fit import pair_index

    rng = np.random.default_rng(seed)
    L = 0.05 * rng.standard_normal((h, w))
    valid = rng.random((h, w)) > 0.2
    index = pair_index(L, valid, np.array(steps), np.zeros((h, w), dtype=np.int64), None, 0.0)
    weight = rng.uniform(0.1, 1.0, index.first.size)
    J, M = rng.standard_normal((K, h * w)), rng.standard_normal(h * w)
    c = 0.1 * rng.standard_normal(K)
    a = ((J[:, index.second] - J[:, index.first]) * index.inv_step).T
    d = index.dlog - (M[index.second] - M[index.first]) * index.inv_step
    wt = weight / (1.0 + ((d - a @ c) / 0.01) ** 2)
    want_H, want_g = (a.T * wt) @ a, (a.T * wt) @ d
    offs, invs, dl, sw = pair_slots(index.first, index.second, index.inv_step, index.dlog, weight, h * w)
    ds = np.empty(dl.shape)
    slot_data(M, offs, invs, dl, ds)
    Hm, g = np.full((K, K), np.nan), np.full(K, np.nan)
    bin_normal(J, ds, sw, offs, invs, c, 100.0, Hm, g, np.empty((2 * offs.size + 3, h * w)))
    return (Hm, g), (want_H, want_g), offs


def _assert_same_sums(got, want):
    for x, y in zip(got, want):
        np.testing.assert_allclose(x, y, rtol=1e-12, atol=1e-12 * np.abs(y).max())


def test_normal_equations_over_bins_on_a_copy_shorter_than_two_steps():
    """A working copy only 5 bins high with steps up to 4: most bins have an edge on one
    side only or none (the ends of L·J's passes overlap); random regressors and weights,
    some bins unusable: the sums over bins are still the sums over pairs."""
    got, want, offs = _bins_against_pairs(5, 7, [1, 2, 4], 7)
    assert max(offs) > 5 * 7 / 2
    _assert_same_sums(got, want)


def test_normal_equations_over_bins_count_a_step_given_twice_twice():
    """Settings that list a step twice list its pairs twice (:func:`pair_index`), and the
    sums over pairs, the jackknife's pairs and the centred fit count each twice: so do the
    sums over bins (the repeated pair's slot was overwritten, counted once)."""
    got, want, offs = _bins_against_pairs(9, 11, [1, 2, 1, 4, 4], 8)
    assert sorted(offs) == [1, 2, 4, 11, 22, 44]
    _assert_same_sums(got, want)


def test_normal_equations_over_bins_with_more_than_64_offsets():
    """Forty steps (eighty offsets) on a 45×50 copy: the slots are not capped at 64 offsets
    (which raised a ValueError where the sums over pairs had none)."""
    got, want, offs = _bins_against_pairs(45, 50, list(range(1, 41)), 9)
    assert len(offs) == 80
    _assert_same_sums(got, want)
