"""Full-resolution correction: the Numba kernel against the model's field."""

import numpy as np
import pytest

import vigproc
from vigproc.bench.synthetic import table1_model
from vigproc.correct import correct_stripe
from vigproc.errors import InvalidImageError

from conftest import textured


@pytest.fixture
def frame():
    m = table1_model(3).rescale(600, 400)
    rgb = np.stack([textured(400, 600, seed=s) for s in range(3)], axis=-1).astype(np.float32)
    return rgb, m


def test_matches_division_by_the_field(frame):
    rgb, m = frame
    ref = rgb / m.field()[..., None]
    out = vigproc.correct(rgb, m)
    assert out.dtype == np.float32
    np.testing.assert_allclose(out, ref, rtol=2e-6)


def test_strength_and_clip(frame):
    rgb, m = frame
    half = vigproc.correct(rgb, m, strength=0.5)
    np.testing.assert_allclose(half, rgb / np.sqrt(m.field())[..., None], rtol=2e-6)
    clipped = vigproc.correct(rgb, m, clip=1.0)
    assert clipped.max() <= 1.0
    unclipped = vigproc.correct(rgb, m)
    assert unclipped.max() > 1.0  # float output keeps values above the white point


def test_stripes_equal_whole_frame_and_in_place(frame):
    rgb, m = frame
    whole = vigproc.correct(rgb, m)
    work = rgb.copy()
    for r0 in range(0, 400, 64):  # bounded memory: one stripe at a time, in place
        stripe = work[r0 : r0 + 64]
        correct_stripe(stripe, m, r0, (400, 600), out=stripe)
    np.testing.assert_array_equal(work, whole)


def test_channel_first_and_gray_and_other_resolution(frame):
    rgb, m = frame
    whole = vigproc.correct(rgb, m)
    cf = vigproc.correct(np.moveaxis(rgb, -1, 0), m, channel_axis=0)
    np.testing.assert_array_equal(np.moveaxis(cf, 0, -1), whole)
    gray = vigproc.correct(rgb[..., 1].astype(np.float64), m, channel_axis=None)
    np.testing.assert_allclose(gray, whole[..., 1], rtol=1e-6)
    big = vigproc.correct(np.ones((800, 1200), np.float32), m, channel_axis=None)
    np.testing.assert_allclose(big, 1 / m.field((800, 1200)), rtol=2e-6)


def test_bad_stripe_and_strength(frame):
    rgb, m = frame
    with pytest.raises(InvalidImageError):
        correct_stripe(rgb[:10], m, 395, (400, 600))
    with pytest.raises(InvalidImageError):
        vigproc.correct(rgb, m, strength=float("nan"))


def test_interpolated_gains_stay_within_tolerance():
    from vigproc.correct import GAIN_TOLERANCE, gain_step

    # a real-lens-like gentle field at 12 MP: interpolation kicks in
    m = vigproc.VignettingModel(4200, 2800, center=(40.0, -25.0), p=(1 / 2600.0**2, 2e-9, 1 / 2400.0**2),
                                alpha=(0.05, 0.02, 0.01, 0, 0, 0, 0))
    step = gain_step(m, 4200, 2800)
    assert step > 1
    ones = np.ones((2800, 4200), np.float32)
    fast = vigproc.correct(ones, m, channel_axis=None)
    exact = correct_stripe(ones, m, 0, (2800, 4200), step=1)
    assert np.max(np.abs(fast / exact - 1)) <= 2 * GAIN_TOLERANCE + 1e-6
    # a strongly curved field (Table 1 at 480 px) is evaluated exactly
    assert gain_step(table1_model(2), 480, 320) == 1
