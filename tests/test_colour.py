"""Colour shading (issue 41): the colour field, its files, correction per channel, flat frames."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from vigproc.core.colour import ColourField, planar_gradient
from vigproc.core.correct import correct, correct_codes
from vigproc.core.estimate import estimate
from vigproc.core.model import VignettingModel
from vigproc.errors import ModelError
from vigproc.io.images import encode_steps, srgb_to_linear

W, H = 300, 200
TINT = [[0.12, 0.05, 0.0], [0.0, 0.0, 0.0], [-0.15, 0.0, 0.02]]


def lens(center=(6.0, -4.0)) -> VignettingModel:
    cf = ColourField(W, H, center, TINT, source="test")
    return VignettingModel(W, H, center=center, p=(1 / 250**2, 0.0, 1 / 250**2), method="flat-field", colour=cf)


def test_ratios_have_luminance_weighted_mean_one():
    r = lens().colour.ratios()
    assert r.shape == (H, W, 3)
    np.testing.assert_allclose(r @ np.array([0.2126, 0.7152, 0.0722]), 1.0, atol=1e-12)
    # corners: R up, B down (the TINT's signs); the centre neutral
    assert r[0, 0, 0] > 1.05 and r[0, 0, 2] < 0.95
    np.testing.assert_allclose(r[H // 2 - 4, W // 2 + 6], 1.0, atol=1e-4)


def test_model_round_trips_and_old_files_load_colourless():
    m = lens()
    d = json.loads(m.to_json())
    assert d["schema"] == "vigproc.model/2" and "colour" in d
    back = VignettingModel.from_json(json.dumps(d))
    assert back == m and back.colour == m.colour
    np.testing.assert_array_equal(back.channel_log_fields((50, 75)), m.channel_log_fields((50, 75)))
    old = VignettingModel(W, H, p=(1 / 250**2, 0.0, 1 / 250**2))
    od = old.to_dict()
    assert od["schema"] == "vigproc.model/1" and "colour" not in od
    assert VignettingModel.from_dict(od).colour is None
    # a /1 file cannot smuggle in a colour field; a malformed one is a ModelError
    with pytest.raises(ModelError):
        VignettingModel.from_dict({**od, "colour": d["colour"]})
    with pytest.raises(ModelError):
        VignettingModel.from_dict({**d, "colour": {**d["colour"], "coeffs": [[1, 2]]}})
    with pytest.raises(ModelError):
        VignettingModel.from_dict({**d, "colour": {**d["colour"], "coeffs": [[9, 9, 9], [0, 0, 0], [0, 0, 0]]}})


def test_rescale_keeps_the_colour_field():
    m = lens()
    big = m.rescale(3 * W, 3 * H)
    assert big.colour.size == (3 * W, 3 * H)
    np.testing.assert_allclose(big.channel_log_fields((H, W)), m.channel_log_fields(), atol=1e-9)


def test_correct_divides_each_channel_by_its_own_field():
    m = lens()
    img = 0.4 * np.exp(m.channel_log_fields())
    out = correct(img, m)
    np.testing.assert_allclose(out, 0.4, rtol=2e-5)  # the gain's interpolation tolerance
    # the luminance model alone leaves the tint in
    plain = correct(img, VignettingModel(W, H, m.center, m.p, m.alpha))
    assert np.abs(plain[0, 0] - 0.4).max() > 0.02
    half = correct(img, m, strength=0.5)
    np.testing.assert_allclose(half, 0.4 * np.exp(0.5 * m.channel_log_fields()), rtol=2e-5)
    # a grey frame: the luminance field only
    np.testing.assert_allclose(correct(img[..., 1], m), img[..., 1] / np.exp(m.log_field()), rtol=2e-5)


@pytest.mark.parametrize("depth", ["uint8", "uint16"])
def test_encoded_path_agrees_with_float_within_one_code(depth):
    m = lens()
    top = 255 if depth == "uint8" else 65535
    rng = np.random.default_rng(3)
    codes = rng.integers(0, top + 1, (H, W, 3)).astype(np.uint8 if depth == "uint8" else np.uint16)
    decode = srgb_to_linear(np.arange(top + 1) / top).astype(np.float32)
    decode.setflags(write=False)  # as EncodedImage.decode_table passes it: the kernel the pipeline runs
    steps = encode_steps("srgb", depth)
    got = correct_codes(codes, m, decode, steps).astype(np.int64)
    ref = np.searchsorted(steps, correct(decode[codes], m, clip=1.0), side="right")
    assert np.abs(got - ref).max() <= 1
    # the colour field does move codes (not a test that cannot fail)
    plain = correct_codes(codes, VignettingModel(W, H, m.center, m.p, m.alpha), decode, steps).astype(np.int64)
    assert np.abs(plain - got).max() > 1


def _flat(m, rng, gradient, grey=(0.9, 1.0, 0.8)):
    yy, xx = np.mgrid[0:H, 0:W]
    a = rng.uniform(0, 2 * math.pi)
    ramp = np.exp(gradient * ((xx / W - 0.5) * math.cos(a) + (yy / H - 0.5) * math.sin(a)))
    return 0.5 * np.exp(m.channel_log_fields()) * ramp[..., None] * np.array(grey) * (
        1 + 0.01 * rng.standard_normal((H, W, 3)))


def test_flat_field_recovers_the_per_channel_field_with_a_gradient_present():
    m = lens()
    rng = np.random.default_rng(0)
    for _ in range(2):
        est = estimate(_flat(m, rng, 0.08), "flat-field")
        assert est.colour is not None and est.colour.source == "flat-field"
        d = (est.channel_log_fields() - m.channel_log_fields()) / math.log(2)
        d -= d.mean(axis=(0, 1))
        assert np.sqrt(np.mean(d * d, axis=(0, 1))).max() < 0.01
        assert math.hypot(est.colour.center[0] - 6.0, est.colour.center[1] + 4.0) < 5.0


def test_planar_gradient_is_found_about_the_optical_centre():
    m = VignettingModel(W, H, center=(6.0, -4.0), p=(1 / 250**2, 0.0, 1 / 250**2))
    yy, xx = np.mgrid[0:H, 0:W]
    g = np.array([3e-4, -2e-4])
    lum = np.exp(m.log_field() + g[0] * (xx - (W - 1) / 2) + g[1] * (yy - (H - 1) / 2))
    np.testing.assert_allclose(planar_gradient(lum, (6.0, -4.0), block=4), g, rtol=0.02)


def test_a_neutral_flat_frame_has_no_colour_field():
    m = VignettingModel(W, H, p=(1 / 250**2, 0.0, 1 / 250**2))
    est = estimate(_flat(m, np.random.default_rng(1), 0.05), "flat-field")
    assert est.colour is None


def test_cfa_planes_measure_the_tint_before_demosaicing():
    from vigproc.core.colour import cfa_rgb, fit_colour_field

    m = lens(center=(0.0, 0.0))
    truth = np.exp(m.channel_log_fields())  # H×W×3 at the mosaic's full resolution
    pattern = np.array([[0, 1], [3, 2]])  # rawpy's RGBG: R G / G2 B
    mosaic = np.empty((H, W))
    for r in range(2):
        for c in range(2):
            ch = {0: 0, 1: 1, 3: 1, 2: 2}[pattern[r, c]]
            mosaic[r::2, c::2] = 1000 + 8000 * [0.7, 1.0, 0.6][ch] * truth[r::2, c::2, ch]
    planes = cfa_rgb(mosaic, pattern, "RGBG", black=[1000] * 4, white=16383)
    assert planes.shape == (H // 2, W // 2, 3)
    cf = fit_colour_field(planes)
    d = (cf.log_ratios(W, H) - m.colour.log_ratios()) / math.log(2)
    assert np.sqrt(np.mean(d * d)) < 0.002
    with pytest.raises(Exception):
        cfa_rgb(mosaic, np.array([[0, 1], [1, 0]]), "RGBG")  # no blue phase


def test_read_cfa_planes_of_a_real_dng():
    from pathlib import Path

    from vigproc.io.images import read_cfa_planes

    path = Path(__file__).resolve().parents[2] / "shared" / "data" / "raw" / "tinydng" / "colorchart.dng"
    if not path.exists():
        pytest.skip(f"{path} is absent (the shared data set)")
    a = read_cfa_planes(path)
    assert a.shape == (578, 867, 3) and 0.0 < float(a.mean()) < 1.0


def test_flat_field_on_a_scene_reads_no_tint():
    """A photograph's colours are not a lens's tint: flat-field estimates it without a
    colour field (and without failing on absurd ratios)."""
    from conftest import coloured_scene

    est = estimate(coloured_scene(H, W, seed=5), "flat-field")
    assert est.colour is None


@pytest.mark.parametrize("shape", [(8, 2000), (2000, 8), (40, 2000)])
def test_a_strip_of_a_flat_frame_is_estimated_without_a_colour_field_or_a_scipy_error(shape):
    # a frame a colour block high gave the colour fit no points at all: scipy's
    # "Residuals are not finite" reached the caller of vigproc.estimate
    h, w = shape
    img = 0.3 + 0.2 * np.random.default_rng(1).random((h, w, 3))
    m = estimate(img, "flat-field")
    if min(shape) < 2 * max(shape) // 64:
        assert m.colour is None
