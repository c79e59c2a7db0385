"""The estimator's faster paths give the bits of the code they replace: the compiled working
copies (vigproc/core/_kernels/binning.py), the pairs' gather, a centred field's RMS."""

import numpy as np
import pytest

from vigproc.core.pixels import _MAX_BLOCK, bin_mean, binned_log_channels, binned_log_copy, log_image


def _copy_numpy(lum, work_size, dark_fraction, mask=None):
    """binned_log_copy as NumPy computed it before the kernel."""
    h, w = lum.shape
    k = max(1, int(round(max(h, w) / work_size)))
    ok = np.isfinite(lum) & (lum > 0)
    if mask is not None:
        ok &= mask
    b, valid = bin_mean(np.where(ok, lum, 0.0), k, ok)
    if valid.any():
        valid &= b > dark_fraction * np.percentile(b[valid], 99)
    return log_image(b), valid, k


def _channels_numpy(img, k, valid, dark_fraction):
    """binned_log_channels as NumPy computed it before the kernel."""
    h, w, c = img.shape
    hb, wb = valid.shape
    a = np.asarray(img[: hb * k, : wb * k], dtype=np.float64)
    sums = a.reshape(hb, k, wb * k, c).sum(axis=1).reshape(hb, wb, k, c).sum(axis=2)
    b = np.moveaxis(sums / (k * k), -1, 0)
    ok = np.broadcast_to(valid, b.shape).copy()
    for i in range(c):
        if ok[i].any():
            ok[i] &= b[i] > dark_fraction * np.percentile(b[i][ok[i]], 99)
    return log_image(b), ok


def _frame(shape, seed):
    rng = np.random.default_rng(seed)
    img = np.exp(rng.normal(-1.0, 1.0, shape))  # a wide range: the sums' rounding shows
    img[3, 5] = np.nan
    img[7, 2] = -0.01
    img[11, 13] = 0.0
    return img


@pytest.mark.parametrize("shape", [(320, 480), (333, 517), (97, 130), (1100, 1700)])
@pytest.mark.parametrize("work_size", [96, 60, 37, 15])
@pytest.mark.parametrize("masked", [False, True])
def test_working_copy_is_numpys_to_the_bit(shape, work_size, masked):
    img = _frame(shape + (3,), sum(shape) + work_size)
    lum = img @ np.array([0.2126, 0.7152, 0.0722])
    mask = np.random.default_rng(1).uniform(size=shape) > 0.02 if masked else None
    k = max(1, int(round(max(shape) / work_size)))
    assert k <= _MAX_BLOCK
    L, valid, kk = binned_log_copy(lum, work_size, 0.01, mask)
    L0, valid0, k0 = _copy_numpy(lum, work_size, 0.01, mask)
    assert kk == k0 == k
    np.testing.assert_array_equal(valid, valid0)
    np.testing.assert_array_equal(L, L0)  # NaN where NumPy has NaN, every other bit equal
    assert not valid.all()  # the bad pixels were seen
    C, ok = binned_log_channels(img, k, valid, 0.01)
    C0, ok0 = _channels_numpy(img, k, valid, 0.01)
    np.testing.assert_array_equal(ok, ok0)
    np.testing.assert_array_equal(C, C0)


def test_channels_of_an_rgba_float32_frame():
    img = _frame((200, 300, 4), 3).astype(np.float32)
    img[..., 3] = 1.0
    lum = img[..., :3].astype(np.float64) @ np.array([0.2126, 0.7152, 0.0722])
    L, valid, k = binned_log_copy(lum, 30, 0.01)
    C, ok = binned_log_channels(img[..., :3], k, valid, 0.01)
    C0, ok0 = _channels_numpy(img[..., :3], k, valid, 0.01)
    np.testing.assert_array_equal(C, C0)
    np.testing.assert_array_equal(ok, ok0)


def test_blocks_longer_than_numpys_pairwise_block_keep_numpy():
    """Above 128 px a block is summed by NumPy itself (its recursive pairwise sum)."""
    lum = _frame((400, 300), 4)
    L, valid, k = binned_log_copy(lum, 2, 0.01)
    assert k == 200 > _MAX_BLOCK
    L0, valid0, _ = _copy_numpy(lum, 2, 0.01)
    np.testing.assert_array_equal(L, L0)
    np.testing.assert_array_equal(valid, valid0)


def test_pairs_gathered_in_one_pass_are_numpys_gathers():
    """pairs_at's compiled gather (vigproc/core/_kernels/pairs.py) gives the NumPy gathers' bits."""
    from vigproc.core.family_fit import FamilySettings, luminance_copy, pairs_at, settings_index, with_colour

    rng = np.random.default_rng(5)
    img = np.exp(rng.normal(-1.0, 0.5, (320, 480, 3)))
    lum = img @ np.array([0.2126, 0.7152, 0.0722])
    s = FamilySettings()
    copy = with_colour(luminance_copy(lum, s, None), img, s)
    index = settings_index(copy.L, copy.valid, copy.C, s)
    assert index.first.size > 1000
    M = rng.normal(size=copy.L.shape)
    B = rng.normal(size=copy.L.shape + (3,))
    d, a = pairs_at(index, M, B)
    m = M.reshape(-1)
    d0 = index.dlog - (m.take(index.second) - m.take(index.first)) * index.inv_step
    bt = np.ascontiguousarray(np.moveaxis(B, -1, 0)).reshape(3, m.size)
    at0 = bt.take(index.second, axis=1)
    at0 -= bt.take(index.first, axis=1)
    at0 *= index.inv_step
    np.testing.assert_array_equal(d, d0)
    np.testing.assert_array_equal(a, at0.T)
    assert a.T.flags.c_contiguous  # the layout irls reads without a copy


@pytest.mark.parametrize("size", [(480, 320), (257, 171), (101, 101), (7, 5), (6000, 4000)])
def test_centred_field_rms_from_one_quadrant_is_the_whole_grids(size):
    """A centred field without a tilted axis is evaluated on a quadrant and mirrored: the
    RMS is the one over the whole grid, to the bit (and a blackout is still refused)."""
    import math

    from vigproc.core.model import VignettingModel, frame_coords
    from vigproc.errors import ModelError

    W, H = size
    rng = np.random.default_rng(W)
    for _ in range(20):
        a = 1.0 / (rng.uniform(0.3, 2.0) * max(W, H)) ** 2
        m = VignettingModel(W, H, center=(0.0, 0.0), p=(a, 0.0, a * rng.uniform(0.5, 1.5)),
                            alpha=tuple(np.r_[rng.uniform(-0.3, 0.3, 3), np.zeros(4)]))
        s = min(1.0, 256.0 / max(W, H))
        h, w = max(2, round(H * s)), max(2, round(W * s))
        mm = m.rescale(w, h) if (w, h) != (W, H) else m
        try:
            lf = mm.log_field_at(frame_coords(w)[None, :], frame_coords(h)[:, None]) / math.log(2.0)
        except ModelError:
            with pytest.raises(ModelError):
                m.field_ev_rms()
            continue
        assert m.field_ev_rms() == float(np.sqrt(np.mean(lf * lf)))


def _reduce_codes_numpy(codes, lut, k, hot_code):
    """The code-domain kernel's sums (vigproc/core/_kernels/codes.py) as NumPy: each block's
    float64 sum in its pixels' order (row by row, left to right), the counts per pixel."""
    h, w, c = codes.shape
    hb, wb = h // k, w // k
    blocks = codes[: hb * k, : wb * k].reshape(hb, k, wb, k, c)
    acc = np.zeros((hb, wb, c))
    for dy in range(k):
        for dx in range(k):
            acc += lut[blocks[:, dy, :, dx]].astype(np.float64)
    top = blocks.max(axis=-1)
    hot = (top >= hot_code).sum(axis=(1, 3))
    dark = (top == 0).sum(axis=(1, 3))
    return acc.astype(np.float32) * np.float32(1.0 / (k * k)), hot, dark


@pytest.mark.parametrize("depth", ["uint8", "uint16"])
@pytest.mark.parametrize("channels", [1, 3, 4])
@pytest.mark.parametrize("shape,k", [((97, 131), 3), ((250, 333), 7), ((96, 144), 24), ((61, 45), 1)])
def test_reduced_codes_are_numpys_to_the_bit(depth, channels, shape, k):
    from vigproc.core._kernels.codes import reduce_codes

    rng = np.random.default_rng(sum(shape) + k + channels)
    top = np.iinfo(depth).max
    codes = rng.integers(0, top + 1, shape + (channels,)).astype(depth)
    codes[: shape[0] // 3, : shape[1] // 4] = 0  # black pixels and a saturated corner: the counts show
    codes[-5:, -7:] = top
    codes[shape[0] // 2, ::2, 0] = top
    # a steep table (gamma 2.4): values over many binades, as a 16-bit gamma file has
    lut = ((np.arange(top + 1) / top) ** 2.4).astype(np.float32)
    hot_code = int(0.97 * top)
    out = np.empty((shape[0] // k, shape[1] // k, channels), np.float32)
    hot = np.zeros(out.shape[:2], np.int64)
    dark = np.zeros(out.shape[:2], np.int64)
    reduce_codes(codes, lut, k, hot_code, out, hot, dark)
    out0, hot0, dark0 = _reduce_codes_numpy(codes, lut, k, hot_code)
    np.testing.assert_array_equal(out.view(np.uint32), out0.view(np.uint32))
    np.testing.assert_array_equal(hot, hot0)
    np.testing.assert_array_equal(dark, dark0)
    assert hot.any() and dark.any()


def test_the_guessed_interval_is_the_binary_searchs():
    """fill_geometry_pairs finds each bin's radius interval from a guess on evenly spaced
    radii (vigproc/core/_kernels/geometry.py): the binary search's interval, for radii on
    and between the grid points, beyond it, NaN, and radii not quite even."""
    from vigproc.core._kernels.geometry import _locate, _locate_near

    rng = np.random.default_rng(7)
    even = np.linspace(0.0, 1.0, 65)
    uneven = np.sort(np.concatenate([[0.0], rng.uniform(0.0, 1.3, 40)]))
    shifted = np.linspace(0.25, 1.5, 33)
    for xp in (even, uneven, shifted):
        inv = (xp.size - 1) / (xp[-1] - xp[0])
        xs = np.concatenate([rng.uniform(xp[0], xp[-1] * 1.2, 3000), xp, np.nextafter(xp, 0.0),
                             np.nextafter(xp, 2.0), [xp[-1] * 5, np.nan]])
        xs = xs[~(xs < xp[0])]  # the kernel's radii are at least the first
        for x in xs:
            assert _locate_near(x, xp, inv) == _locate(x, xp), (x, xp[:3])
