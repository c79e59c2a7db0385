"""The paper's estimator (vigproc.core.lyu2010): its pieces, one by one (Lyu 2010, Section 3)."""

import math

import numpy as np
import pytest

from vigproc.core.lyu2010 import _chol_to_p, _p_to_chol, gaussian_approximation, ml_objective_terms, \
    model_derivative_means
from vigproc.core.prior import default_prior

H, W = 320, 480


@pytest.mark.parametrize("p", [(1e-4, 0.0, 1e-4), (1e-4, 0.5e-4, 1.5e-4), (2e-5, -1e-5, 3e-5)])
def test_the_ml_fit_parametrises_p_by_its_cholesky_factor(p):
    """P = L Lᵀ keeps every step of the ML fit positive definite; the map is exact both ways."""
    np.testing.assert_allclose(_chol_to_p(*_p_to_chol(p, 1e-12)), p, rtol=1e-12)
    # any (a, b, d) gives a positive-definite P
    for a, b, d in ((-5.0, 3.0, -7.0), (0.0, -2.0, 1.0)):
        p1, p2, p3 = _chol_to_p(a, b, d)
        assert p1 > 0 and p1 * p3 - p2 * p2 > 0


def test_no_vignetting_has_zero_derivative_means():
    """D̄ log φ of φ = 1 vanishes for every operator and Δ (Eq. 5's model term)."""
    means, gmin = model_derivative_means(H, W, (0.0, 0.0), (0.0, 0.0, 0.0), np.zeros(7), 25)
    assert means.shape == (5, 25) and gmin == 1.0
    np.testing.assert_allclose(means, 0.0, atol=1e-15)


def test_gaussian_approximation_inverts_the_model_means_of_a_pure_a_field():
    """For α = 0 the log field is that of A alone, whose derivative means Eqs. (17)–(20)
    read back: the shape matrix closely, the centre to within a few pixels."""
    prior = default_prior()
    c, p = (-60.0, 40.0), (1e-5, 0.2e-5, 1.4e-5)
    means, _ = model_derivative_means(H, W, c, p, np.zeros(7), prior.delta_max)
    c_hat, p_hat = gaussian_approximation(means, prior, H, W)
    np.testing.assert_allclose(p_hat, p, rtol=0.15, atol=5e-7)
    assert math.dist(c_hat, c) < 0.05 * math.hypot(W, H)


def test_the_ml_objective_is_lowest_at_the_true_model():
    """Eq. (6) on the derivative means of a known field: zero at the truth, larger for a
    wrong centre, shape or fall-off."""
    prior = default_prior()
    c, p, alpha = (20.0, -10.0), (1e-4, 0.0, 1e-4), np.array([0.02, 0.01, 0, 0, 0, 0, 0])
    truth, _ = model_derivative_means(H, W, c, p, alpha, prior.delta_max)
    assert ml_objective_terms(truth, truth, prior) == 0.0
    for wrong in (((60.0, -10.0), p, alpha), (c, (1.5e-4, 0.0, 1e-4), alpha), (c, p, alpha * 3)):
        other, _ = model_derivative_means(H, W, *wrong, prior.delta_max)
        assert ml_objective_terms(truth, other, prior) > 0.0
