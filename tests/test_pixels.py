"""The numeric core's pixel helpers (vigproc.core.pixels) and area resampling
(vigproc.core.resample): the one validation at the door, luminance, logs, binning.

Every estimator trusts what :func:`check_image` let in, so what it refuses, and with
which typed error, is pinned here case by case.
"""

from __future__ import annotations

import numpy as np
import pytest

from vigproc.core.pixels import (LOG_FLOOR, LUMA_709, NEGATIVE_FRACTION, as_channels_last, bin_mean, binned_coords,
                                 binned_log_copy, check_image, log_image, luminance)
from vigproc.core.resample import area_matrix, resize_area, resize_area_sums
from vigproc.errors import InvalidImageError


def _ramp(h: int = 12, w: int = 16, c: int | None = None) -> np.ndarray:
    a = np.linspace(0.1, 1.0, h * w).reshape(h, w)
    return a if c is None else np.stack([a * (i + 1) / c for i in range(c)], axis=-1)


# ------------------------------------------------------------------ the door
@pytest.mark.parametrize("img, axis, match", [
    (np.ones(20), -1, "H×W or H×W×C"),
    (np.ones((4, 12, 16, 3)), -1, "H×W or H×W×C"),
    (np.ones((12, 16, 3)), None, "needs a channel_axis"),
    (_ramp(c=3), 1.5, "channel_axis must be an integer"),
    (_ramp(c=3), True, "channel_axis must be an integer"),
    (_ramp(c=3), 3, "channel_axis must be an integer"),
    (_ramp(c=5), -1, "1-4 channels"),
    (_ramp().astype(bool), None, "numeric"),
    (_ramp().astype(complex), None, "numeric"),
    (_ramp()[:7], None, "too small"),
    (np.zeros((12, 16)), None, "no positive pixel"),
    (-_ramp(), None, "no positive pixel"),
    (np.full((12, 16), 0.3), None, "constant"),
    (np.where(_ramp() > 0.9, np.nan, _ramp()), None, "NaN/Inf"),
    (np.where(_ramp() > 0.9, np.inf, _ramp()), None, "NaN/Inf"),
    (_ramp() - 0.5, None, "not linear intensities"),
])
def test_check_image_refuses_with_a_typed_error(img, axis, match):
    with pytest.raises(InvalidImageError, match=match):
        check_image(img, axis)


def test_check_image_counts_the_bad_values():
    a = _ramp()
    a[0, :3] = np.nan
    a[1, 0] = -np.inf
    with pytest.raises(InvalidImageError, match="has 4 NaN/Inf values"):
        check_image(a, None)


def test_check_image_lets_in_linear_frames_as_channels_last():
    a = _ramp(c=3)
    out = check_image(np.moveaxis(a, -1, 0), 0)  # channels first in, channels last out
    np.testing.assert_array_equal(out, a)
    assert check_image(a[..., :1]).shape == (12, 16)  # one channel: a 2-D frame
    assert check_image(_ramp(), -1).shape == (12, 16)  # a 2-D frame ignores channel_axis
    assert check_image((1000 * _ramp()).astype(np.uint16), None).dtype == np.uint16  # integers as they are
    # noise around black, down to NEGATIVE_FRACTION of the maximum, is linear data
    noisy = _ramp()
    noisy[0, 0] = -0.9 * NEGATIVE_FRACTION * noisy.max()
    assert check_image(noisy, None) is not None
    assert check_image(_ramp(8, 8), None, min_size=8).shape == (8, 8)


def test_as_channels_last_does_not_copy():
    a = np.zeros((3, 12, 16))
    out = as_channels_last(a, 0)
    assert out.shape == (12, 16, 3) and np.shares_memory(out, a)
    with pytest.raises(InvalidImageError, match="no channel axis"):
        as_channels_last(np.zeros((12, 16)), -1)


# ------------------------------------------------------------------ luminance and logs
def test_luminance_is_rec709_for_rgb_and_the_mean_otherwise():
    rgb = _ramp(c=3)
    np.testing.assert_allclose(luminance(rgb), rgb @ LUMA_709)
    assert LUMA_709.sum() == pytest.approx(1.0)
    np.testing.assert_allclose(luminance(np.ones((12, 16, 3)) * 0.5), 0.5)  # grey stays grey
    rgba = np.concatenate([rgb, np.full((12, 16, 1), 9.0)], axis=-1)
    np.testing.assert_allclose(luminance(rgba), luminance(rgb))  # alpha is not light
    two = _ramp(c=2)
    np.testing.assert_allclose(luminance(two), two.mean(axis=2))
    assert luminance(_ramp().astype(np.float32)).dtype == np.float64


def test_log_image_floors_instead_of_minus_infinity():
    out = log_image(np.array([[0.0, -1.0, 1.0, np.e]]))
    np.testing.assert_allclose(out, [[np.log(LOG_FLOOR), np.log(LOG_FLOOR), 0.0, 1.0]])


# ------------------------------------------------------------------ binning
def test_bin_mean_averages_blocks_and_drops_the_remainder():
    a = np.arange(7 * 9, dtype=float).reshape(7, 9)
    b, valid = bin_mean(a, 3)
    assert b.shape == (2, 3) and valid.all()
    assert b[0, 0] == pytest.approx(a[:3, :3].mean()) and b[1, 2] == pytest.approx(a[3:6, 6:9].mean())
    mask = np.ones_like(a, dtype=bool)
    mask[4, 1] = False  # one bad pixel spoils its whole block, nothing else
    _, valid = bin_mean(a, 3, mask)
    assert valid.tolist() == [[True, True, True], [False, True, True]]
    same, valid1 = bin_mean(a, 1, mask)
    np.testing.assert_array_equal(same, a)
    np.testing.assert_array_equal(valid1, mask)
    assert valid1 is not mask  # a copy


def test_binned_coords_are_bin_centres_about_the_frame_centre():
    np.testing.assert_allclose(binned_coords(6, 2), [-2.0, 0.0, 2.0])
    np.testing.assert_allclose(binned_coords(7, 2), [-2.5, -0.5, 1.5])  # the last row is dropped
    np.testing.assert_allclose(binned_coords(5, 1), [-2, -1, 0, 1, 2])


def test_binned_log_copy_masks_what_a_log_cannot_use():
    lum = np.full((40, 60), 0.5)
    lum[:4, :4] = 0.0  # black
    lum[-4:, -4:] = np.nan  # invalid
    lum[8:12, 20:24] = 1e-4  # far darker than dark_fraction of the 99th percentile
    mask = np.ones(lum.shape, dtype=bool)
    mask[20:24, 40:44] = False  # left out by the caller (clipped)
    L, valid, k = binned_log_copy(lum, work_size=15, dark_fraction=0.01, mask=mask)
    assert k == 4 and L.shape == (10, 15)
    bad = {(0, 0), (9, 14), (2, 5), (5, 10)}
    assert {tuple(ix) for ix in np.argwhere(~valid)} == bad
    np.testing.assert_allclose(L[valid], np.log(0.5))
    assert np.all(np.isfinite(L))


# ------------------------------------------------------------------ area resampling
@pytest.mark.parametrize("n_in, n_out", [(10, 5), (10, 3), (7, 7), (3, 8)])
def test_area_matrix_rows_are_averages(n_in, n_out):
    M = area_matrix(n_in, n_out)
    assert M.shape == (n_out, n_in) and np.all(M >= 0)
    np.testing.assert_allclose(M.sum(axis=1), 1.0)
    # each input sample weighs the same in total: the mean is kept
    np.testing.assert_allclose(M.sum(axis=0), n_out / n_in)


def test_resize_area_keeps_means_and_box_averages():
    a = np.arange(4 * 6, dtype=float).reshape(4, 6)
    half = resize_area(a, 2, 3)
    np.testing.assert_allclose(half, a.reshape(2, 2, 3, 2).mean(axis=(1, 3)))
    odd = resize_area(a, 3, 4)
    assert odd.shape == (3, 4) and odd.mean() == pytest.approx(a.mean())
    np.testing.assert_allclose(resize_area(np.full((5, 7), 2.5), 2, 3), 2.5)


@pytest.mark.parametrize("shape, out", [((500, 333, 3), (240, 160)), ((7, 5), (3, 2)), ((101, 37, 2), (50, 36)),
                                        ((9, 9), (9, 9)), ((3, 4), (8, 5))])
def test_running_sums_resize_as_the_area_matrices_do(shape, out):
    a = np.random.default_rng(4).random(shape) * 100
    got = resize_area_sums(a, *out)
    want = (resize_area(a, *out) if a.ndim == 2 else
            np.stack([resize_area(a[..., c], *out) for c in range(a.shape[2])], axis=-1))
    assert got.shape == want.shape
    np.testing.assert_allclose(got, want, rtol=1e-12, atol=1e-12)
