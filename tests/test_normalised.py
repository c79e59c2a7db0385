"""Model parameters in frame-normalised units, and fitting the model to a known field
(vigproc.core.normalised)."""

import math

import numpy as np
import pytest

from benchmarks.synthetic import table1_model
from vigproc.errors import ModelError
from vigproc.core.normalised import denormalise, fit_model_to_field, normalise


def test_the_same_field_at_two_resolutions_has_the_same_normalised_parameters():
    m = table1_model(2)  # 480x320, off-centre and elliptical
    big = m.rescale(960, 640)
    t1, _, a1 = normalise(m)
    t2, _, a2 = normalise(big)
    np.testing.assert_allclose(t1, t2, rtol=1e-12, atol=1e-15)
    assert a1 == a2 == 1.5


def test_denormalise_inverts_normalise_with_the_covariance():
    m = table1_model(3)
    cov = np.diag(np.linspace(1.0, 12.0, 12)) * 1e-6
    m = m.__class__(m.width, m.height, center=m.center, p=m.p, alpha=m.alpha,
                    covariance=tuple(map(tuple, cov)))
    theta, ncov, _ = normalise(m)
    back = denormalise(theta, ncov, m.width, m.height)
    np.testing.assert_allclose(back.as_vector(), m.as_vector(), rtol=1e-12)
    np.testing.assert_allclose(np.asarray(back.covariance), cov, rtol=1e-12)
    np.testing.assert_allclose(back.log_field(), m.log_field(), atol=1e-12)
    with pytest.raises(ModelError):
        denormalise(theta[:5], None, 480, 320)


def test_fit_model_to_field_recovers_a_kang_weiss_field():
    truth = table1_model(1)
    small = truth.log_field((40, 60))  # a coarse sample of the field is enough
    model, rms_ev = fit_model_to_field(small, truth.width, truth.height)
    assert rms_ev < 0.01
    err = (model.log_field() - truth.log_field()) / math.log(2)
    assert float(np.sqrt(np.mean(err**2))) < 0.02
    with pytest.raises(ModelError, match="aspect"):
        fit_model_to_field(small, 400, 400)
    with pytest.raises(ModelError):
        fit_model_to_field(np.full((40, 60), np.nan), 480, 320)
