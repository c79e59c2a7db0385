"""Full-resolution correction: the Numba kernel against the model's field."""

import numpy as np
import pytest

import vigproc
from benchmarks.synthetic import table1_model
from vigproc.core.correct import correct_stripe
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
    from vigproc.core.correct import GAIN_TOLERANCE, gain_step

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


def test_a_model_that_blacks_out_the_frame_is_refused_as_field_refuses_it():
    from vigproc.errors import ModelError
    from vigproc.core.model import VignettingModel

    bad = VignettingModel(64, 48, p=(1e-3, 0, 1e-3), alpha=(1.0,) + (0.0,) * 6)
    with pytest.raises(ModelError, match="geometric factor"):
        bad.field()
    with pytest.raises(ModelError, match="geometric factor"):  # the kernel's floor gave gains of ~1e9
        vigproc.correct(np.full((48, 64), 0.5, np.float32), bad)


@pytest.mark.parametrize("center, p, alpha", [
    ((0.0, 0.0), (1e-3, 0.0, 1e-3), (0.3, 0.1)),
    ((-40.0, -30.0), (1e-3, 2e-4, 5e-4), (0.3, -0.05)),    # centre near a corner
    ((90.0, 10.0), (2e-4, -1e-4, 3e-3), (-0.2, 0.4)),      # centre outside the frame, G not monotone
])
def test_smallest_g_over_the_frame_matches_the_grid(center, p, alpha):
    from vigproc.core.correct import _min_g
    from vigproc.core.model import VignettingModel, frame_coords

    m = VignettingModel(64, 48, center=center, p=p, alpha=alpha + (0.0,) * 5)
    ex = frame_coords(64)[None, :] - center[0]
    ey = frame_coords(48)[:, None] - center[1]
    r = np.sqrt(np.maximum(p[0] * ex * ex + 2 * p[1] * ex * ey + p[2] * ey * ey, 0))
    g = 1.0 - alpha[0] * r - alpha[1] * r * r
    assert _min_g(m, 64, 48) <= g.min() + 1e-12  # never more optimistic than the pixels
    assert _min_g(m, 64, 48) == pytest.approx(g.min(), abs=0.02)


@pytest.mark.parametrize("kind", ["shifted", "flipped", "fortran", "strided"])
def test_out_may_alias_or_be_laid_out_anyhow(frame, kind):
    """An ``out`` overlapping the input, or not C-ordered, gets the same result (it used to
    give garbage, or Numba typing errors for the documented in-place call on a view)."""
    rgb, m = frame
    ref = vigproc.correct(rgb, m)
    if kind == "shifted":  # the output one element after the input in the same buffer
        buf = np.empty(rgb.size + 1, np.float32)
        src, dst = buf[:-1].reshape(rgb.shape), buf[1:].reshape(rgb.shape)
        src[...] = rgb
        vigproc.correct(src, m, out=dst)
        np.testing.assert_array_equal(dst, ref)
        return
    if kind == "flipped":  # in place on a reversed view
        a = rgb[::-1].copy()[::-1]
        vigproc.correct(a, m, out=a)
        np.testing.assert_array_equal(a, ref)
        return
    out = np.asfortranarray(np.empty_like(rgb)) if kind == "fortran" else np.empty((400, 1200, 3), np.float32)[:, ::2]
    vigproc.correct(rgb, m, out=out)
    np.testing.assert_array_equal(out, ref)


@pytest.mark.parametrize("call, message", [
    (lambda rgb, m: vigproc.correct(rgb, m, strength=1e6), "strength"),
    (lambda rgb, m: vigproc.correct(rgb, m, strength=None), "strength"),
    (lambda rgb, m: vigproc.correct(rgb, m, strength=True), "strength"),
    (lambda rgb, m: vigproc.correct(rgb, m, clip=0), "clip"),
    (lambda rgb, m: vigproc.correct(rgb, m, clip=float("nan")), "clip"),
    (lambda rgb, m: vigproc.correct(rgb, m, clip=-1.0), "clip"),
    (lambda rgb, m: vigproc.correct(rgb, None), "VignettingModel"),
    (lambda rgb, m: vigproc.correct(rgb > 0.5, m), "real numbers"),
    (lambda rgb, m: vigproc.correct(rgb.astype(complex), m), "real numbers"),
    (lambda rgb, m: vigproc.correct(rgb.astype(str), m), "real numbers"),
    (lambda rgb, m: vigproc.correct(rgb, m, channel_axis=3), "channel_axis"),
    (lambda rgb, m: vigproc.correct(rgb, m, channel_axis=1.5), "channel_axis"),
    (lambda rgb, m: vigproc.estimate(rgb, channel_axis=-4), "channel_axis"),
    (lambda rgb, m: vigproc.correct(rgb, m, out=_read_only(rgb)), "read-only"),
    (lambda rgb, m: correct_stripe(rgb, m, 0, (400, 600), step=0), "step"),
    (lambda rgb, m: correct_stripe(rgb, m, 1.5, (400, 600)), "integers"),
    (lambda rgb, m: correct_stripe(rgb, m, 0, (400,)), "integers"),
])
def test_bad_arguments_are_typed_errors(frame, call, message):
    rgb, m = frame
    before = rgb.copy()
    with pytest.raises(InvalidImageError, match=message):
        call(rgb, m)
    np.testing.assert_array_equal(rgb, before)  # never modified


def _read_only(a):
    o = np.empty_like(a)
    o.setflags(write=False)
    return o


def test_nan_or_overflow_in_the_corrected_frame_is_an_error(frame):
    rgb, m = frame
    bad = rgb.copy()
    bad[17, 3, 1] = np.nan
    with pytest.raises(InvalidImageError, match="NaN or Inf values in 1 rows"):
        vigproc.correct(bad, m)
    bad[17, 3, 1] = np.inf
    with pytest.raises(InvalidImageError, match="NaN or Inf"):
        vigproc.correct(bad, m)
    huge = (rgb / rgb.max() * 3e38).astype(np.float32)  # finite, but not once corrected
    assert np.isfinite(huge).all()
    with pytest.raises(InvalidImageError, match="too large for float32"):
        vigproc.correct(huge, m)
    assert np.isfinite(vigproc.correct(rgb, m)).all()
