import numpy as np
import pytest

from vigproc.errors import InvalidImageError
from vigproc.core.stats import DELTA_MAX, derivative_means, derivative_means_bruteforce


@pytest.mark.parametrize("shape", [(320, 480), (51, 51), (77, 130), (200, 61)])
def test_telescoped_means_equal_bruteforce(shape):
    rng = np.random.default_rng(sum(shape))
    img = np.log(rng.uniform(0.01, 1.0, shape))
    fast = derivative_means(img)
    slow = derivative_means_bruteforce(img)
    assert fast.shape == (5, DELTA_MAX)
    assert np.max(np.abs(fast - slow)) < 1e-12


def test_means_of_quadratic_are_exact():
    # i = -1/2 (v-c)^T P (v-c): mean D^xx = -p1 Δ², D^xy = -p2 Δ², mean D^x / Δ = p1 c1 + p2 c2
    h, w = 120, 160
    y, x = np.mgrid[0:h, 0:w].astype(float)
    x -= (w - 1) / 2
    y -= (h - 1) / 2
    p1, p2, p3, c1, c2 = 2e-4, 5e-5, 3e-4, 7.0, -4.0
    dx, dy = x - c1, y - c2
    img = -0.5 * (p1 * dx * dx + 2 * p2 * dx * dy + p3 * dy * dy)
    m = derivative_means(img)
    d = np.arange(1, DELTA_MAX + 1)
    np.testing.assert_allclose(m[2], -p1 * d**2, rtol=1e-9)
    np.testing.assert_allclose(m[3], -p3 * d**2, rtol=1e-9)
    np.testing.assert_allclose(m[4], -p2 * d**2, rtol=1e-9)
    np.testing.assert_allclose(m[0] / d, p1 * c1 + p2 * c2, rtol=1e-9)
    np.testing.assert_allclose(m[1] / d, p2 * c1 + p3 * c2, rtol=1e-9)


def test_too_small_image_is_a_typed_error():
    with pytest.raises(InvalidImageError, match="too small"):
        derivative_means(np.zeros((40, 100)))
