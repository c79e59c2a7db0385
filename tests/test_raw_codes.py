"""A RAW through ``correct`` in LibRaw's own linear 16-bit codes (issue 39): read as
codes (vigproc.io.images.read_encoded), estimated from a copy binned from them, corrected
in them; and the RAW floor of ``vigproc bench throughput --raw``."""

import shutil
import subprocess

import numpy as np
import pytest

from benchmarks import throughput as T
from vigproc.core.correct import correct
from vigproc.core.model import VignettingModel
from vigproc.io.images import EncodedImage, read_encoded, read_image
from vigproc.io.metadata import exiftool_path
from vigproc.pipeline.encoded import correct_encoded
from vigproc.pipeline.processor import OUTPUT_FORMATS, Processor, Settings

RAWS = ("raw/rawpy/RAW_KODAK_DC50.KDC", "raw/tinydng/colorchart.dng")


@pytest.fixture(params=RAWS, ids=["kdc", "dng"])
def raw_file(request, shared_data):
    p = shared_data / request.param
    if not p.is_file():
        pytest.skip(f"{request.param} not in the shared data")
    return p


def test_a_raw_reads_as_its_linear_codes(raw_file):
    enc, info = read_encoded(raw_file)
    img, info2 = read_image(raw_file)
    assert isinstance(enc, EncodedImage) and enc.transfer == "linear" and enc.codes.dtype == np.uint16
    assert info == info2 and info.format == "raw"
    np.testing.assert_allclose(enc.linear(), img, rtol=0, atol=1e-7)  # the float frame, to float rounding


def test_a_raw_corrected_in_its_codes_is_within_one_code_of_the_float_path(raw_file):
    enc, _ = read_encoded(raw_file)
    img, _ = read_image(raw_file)
    h, w = img.shape[:2]
    m = VignettingModel(w, h, p=(1.2 / (w * w + h * h), 0.0, 1.0 / (w * w + h * h)), center=(w * 0.03, -h * 0.02))
    fmt = OUTPUT_FORMATS["tiff16"]
    for s in (1.0, 0.5):
        ref = np.round(np.clip(correct(img, m, channel_axis=-1, strength=s, clip=1.0), 0, 1) * 65535).astype(int)
        got = correct_encoded(enc, m, fmt, s)
        assert got.codes.dtype == np.uint16
        assert np.abs(got.codes.astype(int) - ref).max() <= 1


def test_correct_writes_a_raw_as_a_16_bit_tiff(raw_file, tmp_path):
    out = tmp_path / "out"
    out.mkdir()
    with Processor(Settings(mode="correct", profile="estimate", unapplied="write")) as proc:
        res = proc.process_file(raw_file, out)
    written, info = read_image(res.output)
    assert res.output.endswith(".tif") and info.bit_depth == "uint16"
    assert written.shape == read_image(raw_file)[0].shape


def test_the_raw_floor_develops_writes_and_copies_the_exif(shared_data, tmp_path):
    if shutil.which("exiftool") is None:
        pytest.skip("exiftool program not installed")
    photos, skipped = T.select_raws(shared_data / "raw")
    assert photos and all(p.path.suffix.lower() in (".kdc", ".dng") for p in photos)
    assert skipped  # the stripped exiftool test files
    staged = T.stage(photos[:1], tmp_path / "in")
    assert T.raw_floor_run(tmp_path / "in", tmp_path / "out") == 1
    out = tmp_path / "out" / (staged[0].name + ".tif")
    _, info = read_image(out)
    assert info.bit_depth == "uint16" and (info.width, info.height) == (photos[0].width, photos[0].height)
    make = [subprocess.run([exiftool_path(), "-s3", "-Make", str(p)], capture_output=True, text=True).stdout
            for p in (out, staged[0])]
    assert make[0].strip() and make[0] == make[1]
