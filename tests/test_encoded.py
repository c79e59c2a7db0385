"""A display-encoded frame (a JPEG's or PNG's codes) corrected in its own domain and
estimated from a reduced copy binned straight from its codes."""

from __future__ import annotations

import json

import numpy as np
import pytest

import vigproc
from benchmarks.synthetic import table1_model
from vigproc.core.correct import correct_codes
from vigproc.core.estimate import estimate_checked, estimate_reduced, from_reduced, reduction_factor
from vigproc.core.pixels import bin_mean, check_image, reduce_codes
from vigproc.errors import ImageWriteError, InvalidImageError
from vigproc.io.images import (EncodedImage, _stored_values, encode_steps, jpeg_quality, read_encoded, read_image,
                               write_image)
from vigproc.pipeline.processor import Processor, Settings

from conftest import coloured_scene, textured


def _codes(h: int, w: int, depth: str = "uint8", seed: int = 0, colour: bool = True) -> np.ndarray:
    lin = coloured_scene(h, w, seed=seed) if colour else textured(h, w, seed=seed)
    return _stored_values(np.clip(lin, 0, 1).astype(np.float32), "png", depth, "srgb", "x")


@pytest.mark.parametrize("depth,colour", [("uint8", True), ("uint16", True), ("uint8", False)])
def test_correcting_codes_is_within_one_code_of_the_float_path(depth, colour):
    codes = _codes(300, 450, depth, colour=colour)
    enc = EncodedImage(codes, "srgb")
    m = table1_model(2).rescale(450, 300)  # off-centre, strong: corners pushed past white
    out = correct_codes(codes, m, enc.decode_table(), encode_steps("srgb", depth))
    ref = _stored_values(vigproc.correct(enc.linear(), m, channel_axis=-1 if colour else None, clip=1.0),
                         "png", depth, "srgb", "x")
    assert out.dtype == ref.dtype and out.shape == ref.shape
    diff = np.abs(out.astype(np.int64) - ref.astype(np.int64))
    assert diff.max() <= 1
    # float32 rounding at a step's edge only (a 16-bit step is 256 times finer)
    assert np.mean(diff > 0) < (1e-3 if depth == "uint8" else 1e-2)
    assert np.count_nonzero(out == np.iinfo(out.dtype).max) > np.count_nonzero(codes == np.iinfo(codes.dtype).max)


def test_strength_and_linear_output():
    codes = _codes(120, 180)
    enc = EncodedImage(codes, "srgb")
    m = table1_model(3).rescale(180, 120)
    same = correct_codes(codes, m, enc.decode_table(), encode_steps("srgb", "uint8"), strength=0.0)
    np.testing.assert_array_equal(same, codes)  # decode then encode is exact
    half = correct_codes(codes, m, enc.decode_table(), encode_steps("linear", "uint16"), strength=0.5)
    ref = _stored_values(vigproc.correct(enc.linear(), m, strength=0.5, clip=1.0), "tiff", "uint16", "linear", "x")
    assert np.abs(half.astype(np.int64) - ref.astype(np.int64)).max() <= 1


def test_bad_codes_are_refused():
    m = table1_model(1).rescale(60, 40)
    with pytest.raises(InvalidImageError):
        correct_codes(np.zeros((40, 60), np.float32), m, np.zeros(256, np.float32), encode_steps("srgb", "uint8"))
    with pytest.raises(InvalidImageError):  # a table too short for the codes
        correct_codes(np.full((40, 60), 300, np.uint16), m, np.zeros(256, np.float32), encode_steps("srgb", "uint8"))


@pytest.mark.parametrize("k", [1, 3, 8])
def test_reduced_copy_is_the_binned_linear_frame(k):
    codes = _codes(101, 157, "uint16")
    enc = EncodedImage(codes, "srgb")
    small, usable = reduce_codes(codes, enc.decode_table(), k)
    lin = enc.linear()
    assert usable is None  # no black pixel, no clipped highlight
    assert small.shape == (101 // k, 157 // k, 3)
    for c in range(3):
        np.testing.assert_allclose(small[..., c], bin_mean(lin[..., c], k)[0], rtol=1e-5)
    with pytest.raises(InvalidImageError):
        reduce_codes(codes, enc.decode_table(), 200)


def test_a_model_of_the_reduced_frame_maps_to_the_full_frame():
    k, w, h = 7, 1003, 671  # remainders dropped: the reduced frame covers 1001 x 665 px
    small = table1_model(2).rescale(w // k, round((w // k) * 2 / 3))
    small = vigproc.VignettingModel(w // k, h // k, center=(3.5, -2.0), p=small.p, alpha=small.alpha)
    cand = vigproc.VignettingModel.identity(w // k, h // k, candidate=small)
    for m in (small, cand):
        big = from_reduced(m, k, w, h)
        assert (big.width, big.height) == (w, h)
        shown = big if big.candidate is None else big.candidate
        full = shown.field((h, w))
        # the full model at each block's centre pixel is the small model at that pixel
        centres = full[(k - 1) // 2::k, (k - 1) // 2::k][: h // k, : w // k]
        np.testing.assert_allclose(centres, small.field(), rtol=1e-9)


def test_reduction_factor_keeps_the_working_bins():
    assert reduction_factor(4000, 3000) == 21  # the fit bins 42 px: 2 bins of a 190-px copy
    assert reduction_factor(3264, 2448) == 17  # 34 px
    assert reduction_factor(2463, 1391) == 13  # 26 px
    assert reduction_factor(2208, 1472) == 23  # 23 px, prime: a copy of one bin a pixel
    assert reduction_factor(768, 512) == 1
    for w in range(1000, 12000, 37):
        k = reduction_factor(w, w * 2 // 3)
        assert k > 1 and round((w // k) / 96) * k == round(w / 96)


def test_the_estimate_from_a_reduced_copy_is_the_full_frames():
    h, w = 1000, 1500
    lens = vigproc.VignettingModel(w, h, p=(1 / 900**2, 0.0, 1 / 900**2))
    lin = np.clip(coloured_scene(h, w, seed=3) * lens.field()[..., None], 0, 1).astype(np.float32)
    enc = EncodedImage(_stored_values(lin, "png", "uint8", "srgb", "x"), "srgb")
    k = reduction_factor(w, h)
    assert k > 1
    full = estimate_checked(check_image(enc.linear()))
    reduced = estimate_reduced(*enc.reduced(k)[:1], k, w, h, usable=enc.reduced(k)[1])
    assert (reduced.width, reduced.height) == (w, h)
    assert abs(reduced.field_ev_rms() - full.field_ev_rms()) < 0.02
    assert abs(reduced.field_ev_rms() - lens.field_ev_rms()) < 0.1


def test_read_encoded_and_write_its_codes(tmp_path):
    codes8, codes16 = _codes(60, 90), _codes(60, 90, "uint16")
    for name, codes in (("a.png", codes8), ("b.png", codes16)):
        p = tmp_path / name
        write_image(p, EncodedImage(codes, "srgb"), bit_depth=str(codes.dtype), transfer="srgb")
        enc, info = read_encoded(p)
        assert isinstance(enc, EncodedImage) and enc.transfer == "srgb"
        np.testing.assert_array_equal(enc.codes, codes)  # written as given
        np.testing.assert_array_equal(enc.linear(), read_image(p)[0])
        assert info.bit_depth == str(codes.dtype)
    with pytest.raises(ImageWriteError):  # 8-bit codes are not a 16-bit output
        write_image(tmp_path / "c.png", EncodedImage(codes8, "srgb"), bit_depth="uint16", transfer="srgb")
    write_image(tmp_path / "f.tif", np.full((20, 30), 0.5, np.float32), bit_depth="float")
    img, _ = read_encoded(tmp_path / "f.tif")  # a float file stays float
    assert isinstance(img, np.ndarray) and img.dtype == np.float32
    write_image(tmp_path / "q.jpg", enc.linear(), transfer="srgb", quality=87)
    _, info = read_encoded(tmp_path / "q.jpg")
    assert info.quality == jpeg_quality(tmp_path / "q.jpg") == 87


def test_the_processor_corrects_a_png_in_its_codes_as_the_float_path_would(tmp_path):
    h, w = 700, 1050
    lens = vigproc.VignettingModel(w, h, p=(1 / 700**2, 0.0, 1 / 700**2))
    lin = np.clip(coloured_scene(h, w, seed=5) * lens.field()[..., None], 0, 1).astype(np.float32)
    src = tmp_path / "in.png"
    write_image(src, lin, bit_depth="uint8", transfer="srgb")
    (tmp_path / "out").mkdir()
    with Processor(Settings(profile="estimate")) as proc:
        res = proc.process_file(src, tmp_path / "out")
    assert res.applied and res.output
    model = vigproc.VignettingModel.from_dict(json.loads((tmp_path / "out" / "in.png.vigproc.json").read_text())["model"])
    got, _ = read_encoded(res.output)
    ref = _stored_values(vigproc.correct(read_image(src)[0], model, clip=1.0), "png", "uint8", "srgb", "x")
    assert np.abs(got.codes.astype(int) - ref.astype(int)).max() <= 1


def test_a_constant_or_black_frame_is_bad_input(tmp_path):
    (tmp_path / "out").mkdir()
    with Processor(Settings(profile="estimate")) as proc:
        for name, value in (("black.png", 0.0), ("grey.png", 0.5)):
            write_image(tmp_path / name, np.full((40, 60), value, np.float32), bit_depth="uint8", transfer="srgb")
            with pytest.raises(InvalidImageError):
                proc.process_file(tmp_path / name, tmp_path / "out")


def test_the_reduced_copy_masks_the_blocks_the_full_frame_would():
    from vigproc.core.estimate import clipped_mask

    codes = _codes(90, 120)
    codes[10:20, 30:50] = 255  # a clipped highlight (over 0.1 % of the pixels)
    codes[70, 100] = 0  # one black pixel
    enc = EncodedImage(codes, "srgb")
    lin = enc.linear()
    keep = clipped_mask(lin) & (lin.max(axis=2) > 0)
    for k in (2, 5):
        _, usable = reduce_codes(codes, enc.decode_table(), k)
        np.testing.assert_array_equal(usable, bin_mean(lin[..., 0], k, keep)[1])
        assert not usable.all() and usable.mean() > 0.9


def test_vigproc_estimate_of_a_large_jpeg_reads_the_reduced_copy(tmp_path, capsys):
    from vigproc.frontends.cli import main

    h, w = 1000, 1500
    lens = vigproc.VignettingModel(w, h, p=(1 / 900**2, 0.0, 1 / 900**2))
    src = tmp_path / "big.jpg"
    write_image(src, np.clip(coloured_scene(h, w, seed=7) * lens.field()[..., None], 0, 1), transfer="srgb",
                quality=95)
    assert main(["estimate", "--json", str(src)]) == 0
    doc = json.loads(capsys.readouterr().out)
    got = vigproc.VignettingModel.from_dict(doc["results"][0]["model"])
    full = estimate_checked(check_image(read_image(src)[0]))
    assert (got.width, got.height) == (w, h)
    assert abs(got.field_ev_rms() - full.field_ev_rms()) < 0.02


@pytest.mark.parametrize("depth,colour", [("uint8", True), ("uint16", False)])
def test_correcting_codes_in_place_gives_the_same_codes(depth, colour):
    codes = _codes(97, 143, depth, colour=colour)
    enc = EncodedImage(codes, "srgb")
    m = table1_model(2).rescale(143, 97)
    ref = correct_codes(codes, m, enc.decode_table(), encode_steps("srgb", depth))
    work = codes.copy()
    out = correct_codes(work, m, enc.decode_table(), encode_steps("srgb", depth), out=work)
    assert np.shares_memory(out, work) and not np.array_equal(work, codes)
    np.testing.assert_array_equal(out, ref)
    with pytest.raises(InvalidImageError):  # the output's dtype, not the input's
        correct_codes(codes, m, enc.decode_table(), encode_steps("srgb", "uint16" if depth == "uint8" else "uint8"),
                      out=codes.copy())
    with pytest.raises(InvalidImageError):  # overlapping, shifted: rows would be read after being written
        correct_codes(work[1:], m, enc.decode_table(), encode_steps("srgb", depth), out=np.ascontiguousarray(work[:-1]))


def test_white_samples_are_counted_in_bands_as_on_the_whole_frame():
    from vigproc.pipeline.encoded import white_samples

    rng = np.random.default_rng(3)
    codes = rng.integers(250, 256, (700, 33, 3), dtype=np.uint8)  # several bands of 256 rows
    assert white_samples(EncodedImage(codes, "srgb")) == np.count_nonzero(codes == 255)
    lin = rng.uniform(0.9, 1.1, (600, 17)).astype(np.float32)
    lin[::7, ::3] = 1.0
    assert white_samples(lin) == np.count_nonzero(lin >= 1.0)
    assert white_samples(lin, source=True) == np.count_nonzero(lin == 1.0)


def test_the_processor_corrects_a_frame_it_read_in_place_and_a_given_one_not(tmp_path, caplog):
    """process_file owns the frame it read (corrected in place, the same output and
    the same clipping note); process_image leaves a caller's frame alone."""
    import logging

    h, w = 420, 630
    lens = vigproc.VignettingModel(w, h, p=(1 / 420**2, 0.0, 1 / 420**2))
    lin = np.clip(2.2 * coloured_scene(h, w, seed=5) * lens.field()[..., None], 0, 1).astype(np.float32)
    codes = _stored_values(lin, "png", "uint8", "srgb", "x")
    codes[:20, :20] = 255  # the source's own white: not counted as clipped by the correction
    src = tmp_path / "in.png"
    write_image(src, EncodedImage(codes, "srgb"), bit_depth="uint8", transfer="srgb")
    from vigproc.pipeline.processor import OutputFormat

    proc = Processor(Settings(mode="correct", profile="estimate"))
    enc = EncodedImage(codes.copy(), "srgb")
    given, res0 = proc.process_image(enc, where="given", output=OutputFormat(".png", "png", "uint8", "srgb"))
    np.testing.assert_array_equal(enc.codes, codes)  # untouched
    assert res0.applied and not np.array_equal(given.codes, codes)
    (tmp_path / "out").mkdir()
    with caplog.at_level(logging.INFO, logger="vigproc"):
        res = proc.process_file(src, tmp_path / "out")
    assert res.applied and res.output
    back, _ = read_encoded(res.output)
    ref = correct_codes(codes, res.model, EncodedImage(codes, "srgb").decode_table(), encode_steps("srgb", "uint8"))
    np.testing.assert_array_equal(back.codes, ref)
    lost = np.count_nonzero(ref == 255) - np.count_nonzero(codes == 255)
    said = [r.getMessage() for r in caplog.records if "above the white point" in r.getMessage()]
    # some corners clip, fewer than the 0.1 % that is said; the source's own white not counted
    assert 0 < lost <= 1e-3 * codes.size and not said


def test_the_clipping_note_counts_the_source_white_before_or_after(caplog):
    import logging

    from vigproc.pipeline.processor import OutputFormat, _note_clipping

    src = np.full((100, 100, 3), 200, np.uint8)
    src[:10] = 255  # the source's own
    out = src.copy()
    out[10:15] = 255  # 1500 samples of 30000 pushed to white by the correction: 5 %
    fmt = OutputFormat(".png", "png", "uint8", "srgb")
    with caplog.at_level(logging.INFO, logger="vigproc"):
        _note_clipping(EncodedImage(src, "srgb"), EncodedImage(out, "srgb"), "a", fmt)
        _note_clipping(None, EncodedImage(out, "srgb"), "b", fmt, source_white=3000)
    said = [r.getMessage() for r in caplog.records if "above the white point" in r.getMessage()]
    assert said == [f"{w}: 5.0 % of the samples are above the white point and 8-bit PNG clips them "
                    "(a float output format keeps them)" for w in "ab"]
