"""Know what the camera already did (issue 38): a JPEG whose camera corrected its
vignetting (maker-note flag, or a phone's) is left alone by default (vigproc.io.incamera)."""

import json
import shutil
import subprocess

import numpy as np
import pytest

from vigproc.core.model import VignettingModel
from vigproc.io.exif import ExifReader
from vigproc.io.images import write_image
from vigproc.io.incamera import from_tags, read_in_camera
from vigproc.pipeline.processor import Processor, Settings

from conftest import photo_like, run_cli

needs_exiftool = pytest.mark.skipif(shutil.which("exiftool") is None, reason="exiftool program not installed")


@pytest.mark.parametrize("tags, evidence", [
    ({"Make": "Canon", "Model": "Canon EOS 7D", "PeripheralIlluminationCorr": 1}, "PeripheralIlluminationCorr=1"),
    ({"Make": "Canon", "PeripheralIlluminationCorr": 0}, None),
    ({"Make": "Canon", "Model": "PowerShot G12", "PeripheralLighting": 1}, "PeripheralLighting=1"),
    ({"Make": "NIKON CORPORATION", "VignetteControl": 3}, "VignetteControl=3"),
    ({"Make": "NIKON CORPORATION", "VignetteControl": 0}, None),
    ({"Make": "SONY", "Model": "SLT-A58", "VignettingCorrection": 2}, "VignettingCorrection=2"),
    ({"Make": "SONY", "Model": "NEX-5N", "VignettingCorrection": 0}, None),
    ({"Make": "SONY", "Model": "RX100", "VignettingCorrection": 0xFFFFFFFF}, None),  # n/a
    ({"Make": "OLYMPUS IMAGING CORP.", "ShadingCompensation": 1}, "ShadingCompensation=1"),
    ({"Make": "OLYMPUS IMAGING CORP.", "ShadingCompensation": 0}, None),
    ({"Make": "Panasonic", "ShadingCompensation": "1"}, "ShadingCompensation=1"),
    ({"Make": "Apple", "Model": "iPhone 5s"}, "phone"),
    ({"Make": "samsung", "Model": "SM-J327T1"}, "phone"),
    ({"Make": "SAMSUNG", "Model": "NX300"}, None),  # Samsung's cameras are not phones
    ({"Make": "Sony", "Model": "Xperia Z5"}, "phone"),
    ({"Make": "Google", "Model": "Pixel 7"}, "phone"),
    ({"Make": "HUAWEI", "Model": "P30"}, "phone"),
    ({"Make": "Sony Ericsson", "Model": "K800i"}, "phone"),
    ({"Make": "FUJIFILM", "Model": "X-T3"}, None),
    ({}, None),
])
def test_flags_and_phones(tags, evidence):
    got = from_tags(tags)
    assert (got.evidence if got else None) == evidence
    if got is not None:
        assert "corrected" in got.reason


def _jpeg(path, make, model):
    truth = VignettingModel(360, 240, p=(1 / 200**2, 0.0, 1 / 200**2))  # 0.73 EV at the corners: a real lens's
    img = np.repeat((photo_like(240, 360, seed=5) * truth.field())[..., None], 3, axis=2).astype(np.float32)
    write_image(path, img, transfer="srgb", quality=90)
    subprocess.run(["exiftool", "-q", "-overwrite_original", f"-Make={make}", f"-Model={model}",
                    "-FocalLength=4.15", "-FNumber=2.2", str(path)], check=True)
    return path


@needs_exiftool
def test_read_in_camera_reads_a_phone_jpeg_and_never_a_raw(tmp_path):
    phone = _jpeg(tmp_path / "IMG_1.jpg", "Apple", "iPhone 5s")
    camera = _jpeg(tmp_path / "DSC_1.jpg", "NIKON CORPORATION", "NIKON D70")
    raw = tmp_path / "IMG_1.dng"
    raw.write_bytes(phone.read_bytes())  # a RAW's pixels are the sensor's: never read as corrected
    with ExifReader() as reader:
        assert read_in_camera(phone, reader).evidence == "phone"
        assert read_in_camera(camera, reader) is None
        assert read_in_camera(raw, reader) is None
    assert read_in_camera(phone, None) is None


@needs_exiftool
def test_a_maker_note_flag_of_a_real_camera_file(shared_data):
    f = shared_data / "jpeg_exif" / "exif-py" / "Sony_alpha_a58.JPG"
    if not f.is_file():
        pytest.skip(f"{f} not present")
    with ExifReader() as reader:
        assert read_in_camera(f, reader).evidence == "VignettingCorrection=2"


@needs_exiftool
def test_correct_leaves_a_phone_jpeg_alone_unless_told(tmp_path):
    src = _jpeg(tmp_path / "IMG_1.jpg", "Apple", "iPhone 5s")
    before = src.read_bytes()
    out = tmp_path / "out"
    r = run_cli("correct", src, "-o", out, "--profile", "estimate")  # in this process: not about the process
    assert r.returncode == 0, r.stderr
    side = json.loads((out / "IMG_1.jpg.vigproc.json").read_text())
    assert side["applied"] is False and side["not_applied_rule"] == "in-camera"
    assert "phone" in side["not_applied"] and "not corrected: a phone's JPEG" in r.stdout
    assert (out / "IMG_1.corrected.jpg").read_bytes() == before == src.read_bytes()
    # overridden: the same frame is estimated and corrected as any other
    (tmp_path / "o2").mkdir()
    with Processor(Settings(profile="estimate", in_camera="ignore")) as proc:
        res = proc.process_file(src, tmp_path / "o2")
    assert res.applied and res.extra.get("not_applied_rule") is None, res.extra


def test_settings_refuse_an_unknown_in_camera_policy():
    from vigproc.errors import VigprocError

    with pytest.raises(VigprocError, match="in-camera"):
        Settings(in_camera="maybe")


@needs_exiftool
def test_bench_real_frames_counts_what_the_rules_prevent(tmp_path):
    from benchmarks.real_frames import full_frames, run

    phone = _jpeg(tmp_path / "IMG_1.jpg", "Apple", "iPhone 5s")
    _jpeg(tmp_path / "DSC_1.jpg", "NIKON CORPORATION", "NIKON D70")
    write_image(tmp_path / "small.jpg", np.full((40, 60, 3), 0.3, np.float32), transfer="srgb")
    files = full_frames([tmp_path], min_long_side=300)
    assert [f.name for f in files] == ["DSC_1.jpg", "IMG_1.jpg"]  # the small frame is left out
    off, on = run(files, rules_on=False), run(files, rules_on=True)
    assert off.frames == on.frames == 2 and off.in_camera_frames == on.in_camera_frames == 1
    row = {r.file: r for r in off.rows}[phone.name]
    assert row.in_camera == "phone" and row.applied and row.removed_ev > 0.3  # the 0.73 EV field, removed again
    assert off.in_camera_removed_max == row.removed_ev
    assert on.in_camera_removed_max == 0.0 and {r.file: r for r in on.rows}[phone.name].rule == "in-camera"
    assert on.applied == 1 and on.brighter_corners == on.beyond_population == on.below_confidence == 0
