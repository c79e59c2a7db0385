import numpy as np
import pytest
from scipy.stats import gennorm

from vigproc.errors import PriorError
from vigproc.core.prior import NaturalPrior, default_prior, fit_prior, ggd_moment_match
from vigproc.core.stats import DELTA_MAX, OPERATORS

from conftest import textured


@pytest.mark.parametrize("beta", [0.7, 1.0, 2.0])
def test_moment_matching_recovers_known_ggd(beta):
    x = gennorm.rvs(beta, scale=0.01, size=200_000, random_state=np.random.default_rng(3))
    gamma, b = ggd_moment_match(x)
    assert b == pytest.approx(beta, rel=0.05)
    assert gamma == pytest.approx(0.01, rel=0.05)


def test_shipped_prior_is_complete_and_sane():
    p = default_prior()
    assert p.gamma.shape == (len(OPERATORS), DELTA_MAX)
    assert np.all(p.gamma > 0) and np.all((p.beta > 0.1) & (p.beta < 10))
    assert p.n_blocks >= 1000
    assert "prior fit" in p.source


def test_fit_prior_round_trip(tmp_path):
    imgs = [textured(256, 256, seed=s) for s in range(8)]
    p = fit_prior(imgs, blocks_per_image=2, source="test")
    assert p.n_blocks == 8 * 2 * 4
    p.save(tmp_path / "p.json")
    q = NaturalPrior.load(tmp_path / "p.json")
    np.testing.assert_allclose(q.gamma, p.gamma, rtol=1e-9)


def test_too_few_blocks_is_a_typed_error():
    with pytest.raises(PriorError):
        fit_prior([textured(100, 100)])
