"""The lens-family fit's σ from the linearised jackknife: its compiled block sums are their
definition, it is the refits exactly where the loss is quadratic and near them on a real
fit, and the refits themselves decide where the SNR is close to its threshold."""

import math
from dataclasses import replace

import numpy as np
import pytest

from vigproc.core import family_fit as ff
from vigproc.core._kernels.blocks import block_normal
from vigproc.core.family_fit import (FamilySettings, bin_rho, family_for, field_sigma_ev, fit_family,
                                     corner_radius, linear_jackknife, luminance_copy, pairs_at, settings_index,
                                     with_colour)
from vigproc.core.lensfamily import profile_family
from vigproc.core.pixels import luminance

from conftest import textured

H, W = 200, 300


def _frame(seed: int = 3) -> np.ndarray:
    from benchmarks.synthetic import table1_model

    scene = np.stack([textured(H, W, seed=seed + k, contrast=0.05) for k in range(3)], axis=-1)
    return scene * table1_model(1).field((H, W))[..., None]


def _pairs(frame: np.ndarray, s: FamilySettings):
    """A colour frame's pairs, regressors (two components), blocks, weights, fit and prior,
    as fit_family makes them."""
    L, valid, xs, ys, C, _ = with_colour(luminance_copy(luminance(frame), s, None), frame, s)
    fam = family_for(profile_family(), True)
    M, B = fam.profiles(bin_rho(xs, ys, corner_radius(W, H)))
    index = settings_index(L, valid, C, s)
    d, a = pairs_at(index, M, B)
    a = a[:, :fam.n_components]
    pmean, pcov = fam.prior(None, None)
    pinv = np.linalg.inv(pcov)
    c, d = ff._fit_with_chroma(d, a, index, index.weight, pmean, pinv, s, s.iterations)
    return fam, d, a, index.labels, index.weight, c, pmean, pinv


def test_block_sums_are_their_definition():
    rng = np.random.default_rng(1)
    n, K, nb = 1001, 3, 4
    a = rng.normal(size=(n, K))
    d = rng.normal(size=n) * 0.1
    wt = rng.uniform(0, 1, n) * (rng.uniform(size=n) > 0.1)
    labels = rng.integers(0, nb, n)
    c = rng.normal(size=K) * 0.05
    inv_s = 1 / 0.07
    HI, HN, G = np.empty((nb, K, K)), np.empty((nb, K, K)), np.empty((nb, K))
    block_normal(np.ascontiguousarray(a.T), d, wt, labels, c, inv_s, nb, HI, HN, G)
    r = d - a @ c
    u2 = (r * inv_s) ** 2
    w = wt / (1 + u2)
    wn = w * (1 - u2) / (1 + u2)
    for b in range(nb):
        m = labels == b
        np.testing.assert_allclose(HI[b], (a[m] * w[m, None]).T @ a[m], rtol=1e-12)
        np.testing.assert_allclose(HN[b], (a[m] * wn[m, None]).T @ a[m], rtol=1e-12)
        np.testing.assert_allclose(G[b], a[m].T @ (w[m] * r[m]), rtol=1e-12)


def test_linear_jackknife_is_the_refits_where_the_loss_is_quadratic():
    """A Cauchy scale far above every residual makes each refit one linear solve: the
    linearised refits are then the refits to rounding."""
    s = replace(FamilySettings(), sigma=1e4, tolerance=1e-12)
    fam, d, a, labels, wt, c, pmean, pinv = _pairs(_frame(), s)
    want = ff._jackknife(d, a, labels, wt, c, pmean, pinv, s)
    got = linear_jackknife(d, a, labels, wt, c, pmean, pinv, s)
    assert got.shape == want.shape == (s.jackknife_blocks**2, a.shape[1])
    np.testing.assert_allclose(got, want, rtol=1e-7, atol=1e-10)


@pytest.mark.parametrize("seed", [3, 11])
def test_linear_jackknife_sigma_is_near_the_refits(seed):
    """With the default Cauchy scale the field's σ is within the band fit_family trusts it
    to (and in fact much nearer on these frames)."""
    s = FamilySettings()
    fam, d, a, labels, wt, c, pmean, pinv = _pairs(_frame(seed), s)
    jk = field_sigma_ev(fam, ff._jackknife_cov(d, a, labels, wt, c, pmean, pinv, s), W, H)
    lin = field_sigma_ev(fam, ff._spread(linear_jackknife(d, a, labels, wt, c, pmean, pinv, s)), W, H)
    assert jk > 0
    assert 0.8 < lin / jk < 1.25


def test_the_refits_decide_near_the_threshold(monkeypatch):
    """Far from min_snr, fit_family's σ is the linearised one (no refits); with min_snr set
    at the fit's SNR the refits run and their σ is the one stated."""
    frame = _frame()
    lum = luminance(frame)
    calls = []
    real = ff._jackknife_cov
    monkeypatch.setattr(ff, "_jackknife_cov", lambda *a: calls.append(1) or real(*a))
    s = FamilySettings()
    far = replace(s, min_snr=1e-3)
    q_far = fit_family(lum, far, colour=frame).model.quality
    assert not calls
    near = replace(s, min_snr=q_far.snr)
    q_near = (lambda m: (m.candidate or m).quality)(fit_family(lum, near, colour=frame).model)
    assert calls
    fam, d, a, labels, wt, c, pmean, pinv = _pairs(frame, s)
    sigma_jk = field_sigma_ev(fam, real(d, a, labels, wt, c, pmean, pinv, s), W, H)
    assert q_near.field_sigma_ev == pytest.approx(math.hypot(s.sigma_scale * sigma_jk, s.sigma_floor), rel=1e-9)
    # a comparison of RMS + 2σ with a level near it asks the refits too
    calls.clear()
    fit_family(lum, far, colour=frame, ev_checks=(q_far.field_ev_rms + 2 * q_far.field_sigma_ev,))
    assert calls


def test_off_centre_sigma_is_linearised_unless_near_its_threshold(monkeypatch):
    """The off-centre fit's σ: no refits far from min_snr; with min_snr at its SNR, the
    refits' σ."""
    from benchmarks.synthetic import table1_model
    from vigproc.core.estimate import OffCentreRule
    from vigproc.core.family_fit import off_centre_fit

    scene = np.stack([textured(H, W, seed=3 + k, contrast=0.05) for k in range(3)], axis=-1)
    frame = scene * table1_model(2).field((H, W))[..., None]
    lum = luminance(frame)
    s = OffCentreRule().settings
    c = fit_family(lum, FamilySettings(), colour=frame).coefficients
    calls = []
    real = ff._jackknife
    monkeypatch.setattr(ff, "_jackknife", lambda *a: calls.append(1) or real(*a))
    far = off_centre_fit(lum, c, replace(s, min_snr=1e-3), colour=frame).with_uncertainty()
    assert not calls and far.quality.field_sigma_ev > s.sigma_floor
    part = off_centre_fit(lum, c, replace(s, min_snr=far.quality.snr), colour=frame)
    near = part.with_uncertainty()
    assert len(calls) == 1
    d, a, index, sol, pm_it, pinv, settings, J = part._jackknife
    jk = ff.field_spread_ev(J, ff._spread(real(d, a, index.labels, index.weight, sol, pm_it, pinv, settings)))
    q = (near.candidate or near).quality
    assert q.field_sigma_ev == pytest.approx(math.hypot(s.sigma_scale * jk, s.sigma_floor), rel=1e-12)
