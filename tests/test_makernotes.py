"""The camera maker's own vignetting calibration (vigproc.io.makernotes): Sony's
VignettingCorrParams and Fujifilm's VignettingParams, read the way darktable 4.2 reads
them, as a profile source and a forensic reference."""

from __future__ import annotations

import json
import math
import os
import shutil
from pathlib import Path

import numpy as np
import pytest

from vigproc.errors import ImageReadError, ModelError
from vigproc.io.dng_opcodes import FixVignetteRadial, OpcodeList
from vigproc.io.images import read_image
from vigproc.io.makernotes import (
    MakerNoteCalibration,
    MakerNoteError,
    calibration_for,
    from_tags,
    read_makernote,
)
from vigproc.pipeline.processor import Processor, Settings

from conftest import photo_like, textured
from dngfixture import _SSHORT, SONY_VIGNETTING_CORR_PARAMS, make_dng, sony_vignetting_tags

rawpy = pytest.importorskip("rawpy")
needs_exiftool = pytest.mark.skipif(shutil.which("exiftool") is None, reason="exiftool program not installed")

W, H = 384, 256
#: 16 knots, up to ~0.6 EV of fall-off in the corners.
SONY = [round(6000 * (i / 15) ** 2.5) for i in range(16)]
#: A strong fall-off (~1.5 EV in the corners) for the forensic check.
STRONG = [round(11000 * (i / 15) ** 2) for i in range(16)]
#: A Fujifilm X-Trans IV VignettingParams as exiftool -n prints it (19 rationals: an
#: unknown first value, 9 knot radii, 9 brightnesses in percent).
FUJI = ("416.555555555556 0.353521126760563 0.5 0.612676056338028 0.707042253521127 0.790845070422535 "
        "0.866197183098592 0.935211267605634 1 1.06056338028169 94.1171875 89.82421875 86.3041992 83.5576172 "
        "77.2827148 67.859375 58.4472656 49.4204102 42.8090820")


def sony_phi(r: np.ndarray, values=SONY) -> np.ndarray:
    """darktable 4.2's Sony curve, written out independently: knots (i + ½)/(n − 1),
    s = 2^(½ − 2^(v 2⁻¹³ − 1)) interpolated linearly, the pixel divided by s²."""
    n = len(values)
    knots = (np.arange(n) + 0.5) / (n - 1)
    s = np.array([2 ** (0.5 - 2 ** (v / 8192 - 1)) for v in values])
    return np.interp(r, knots, s) ** 2


def radius(w: int = W, h: int = H) -> np.ndarray:
    y, x = np.mgrid[:h, :w]
    return np.hypot(x + 0.5 - w / 2, y + 0.5 - h / 2) / math.hypot(w / 2, h / 2)


# --------------------------------------------------------------------------- #
# the tags
# --------------------------------------------------------------------------- #


def test_sony_curve_is_darktables() -> None:
    tags = {"SubIFD:VignettingCorrParams": " ".join(str(v) for v in [16, *SONY])}
    cal = from_tags(tags, "a.arw")
    assert isinstance(cal, MakerNoteCalibration) and cal.maker == "sony" and cal.kind == "sony:VignettingCorrParams"
    np.testing.assert_allclose(-cal.log_gain(W, H), np.log(sony_phi(radius())), atol=1e-12)
    # v = 0 is no fall-off; v = 8192 a gain of 2 (log2 g = 2^(v/8192) − 1)
    flat = from_tags({"SubIFD:VignettingCorrParams": "2 0 8192"})
    assert flat.scale[0] == pytest.approx(1.0) and flat.scale[1] ** -2 == pytest.approx(2.0)
    # the Kang-Weiss fit of the curve, its error stated
    m, rms, mx = cal.fit(W, H)
    assert m.method == "makernote:sony" and rms < 5e-3 and rms <= mx < 0.02
    d = cal.to_dict(W, H)
    assert d["fit_rms_ev"] == rms and d["tag"] == "SubIFD:VignettingCorrParams" and len(d["knots"]) == 16


def test_fuji_curve_and_its_crop_mode() -> None:
    cal = from_tags({"FujiIFD:VignettingParams": FUJI}, "a.raf")
    v = [float(x) for x in FUJI.split()]
    assert cal.maker == "fujifilm" and cal.knots == tuple(v[1:10])
    # darktable: s = V/100, the pixel divided by s²
    np.testing.assert_allclose(-cal.log_gain(W, H), 2 * np.log(np.interp(radius(), v[1:10], np.array(v[10:]) / 100)))
    crop = from_tags({"FujiIFD:VignettingParams": FUJI, "FujiFilm:CropMode": 2})
    assert crop.knots == pytest.approx(tuple(1.25 * k for k in v[1:10]))


@pytest.mark.parametrize("tags, match", [
    ({"SubIFD:VignettingCorrParams": "17 " + " ".join(["0"] * 17)}, "count 17"),
    ({"SubIFD:VignettingCorrParams": "16 1 2 3"}, "count 16 with 3 values"),
    ({"SubIFD:VignettingCorrParams": "4 0 x 2 3"}, "not a number"),
    ({"SubIFD:VignettingCorrParams": "2 0 nan"}, "not finite"),
    ({"SubIFD:VignettingCorrParams": "2 0 32000"}, "no vignetting calibration"),
    ({"SubIFD:VignettingCorrParams": {"a": 1}}, "not a list"),
    ({"FujiIFD:VignettingParams": "1 2 3"}, "only the 19-value layout"),
    ({"FujiIFD:VignettingParams": " ".join(["1"] * 10 + ["50"] * 9)}, "must increase"),
])
def test_malformed_tags_are_typed_errors(tags: dict, match: str) -> None:
    with pytest.raises(MakerNoteError, match=match):
        from_tags(tags, "bad.arw")
    assert issubclass(MakerNoteError, ImageReadError)


def test_no_tag_or_no_correction_is_none() -> None:
    assert from_tags({}) is None
    assert from_tags({"SubIFD:VignettingCorrParams": "4 0 0 0 0"}) is None
    assert from_tags({"FujiIFD:VignettingParams": " ".join(["0"] + [str(k / 10) for k in range(1, 10)] + ["100"] * 9)}) \
        is None


# --------------------------------------------------------------------------- #
# files
# --------------------------------------------------------------------------- #


def scene() -> np.ndarray:
    s = textured(H, W, seed=0, contrast=0.05)
    return s * (0.8 / s.max())


@pytest.fixture(scope="module")
def files(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """Bayer DNGs with the raw image in a SubIFD, where an ARW has it, carrying Sony's tags."""
    if shutil.which("exiftool") is None:
        pytest.skip("exiftool program not installed")
    d = tmp_path_factory.mktemp("makernotes")
    phi = sony_phi(radius())
    out = {"sony": d / "sony.dng", "plain": d / "plain.dng", "both": d / "both.dng", "bad": d / "bad.dng"}
    make_dng(out["sony"], field=phi, scene=scene(), noise=0.001, subifd=True, raw_tags=sony_vignetting_tags(SONY))
    make_dng(out["plain"], field=phi, scene=scene(), noise=0.001, subifd=True)
    fvr = OpcodeList((FixVignetteRadial((0.5, 0, 0, 0, 0), 0.5, 0.5).to_opcode(),))
    make_dng(out["both"], scene=scene(), subifd=True, raw_tags=sony_vignetting_tags(SONY),
             opcode_lists={3: fvr.to_bytes()})
    make_dng(out["bad"], scene=scene(), subifd=True, raw_tags=[(SONY_VIGNETTING_CORR_PARAMS, _SSHORT, [16, 1, 2])])
    # for the forensic check: a photograph-like scene, the lens's fall-off and the camera's
    # calibration of it; and the same calibration on a frame cropped off-centre
    photo = photo_like(H, W, seed=1)
    photo *= 0.8 / photo.max()
    out["honest"] = d / "honest.dng"
    make_dng(out["honest"], field=sony_phi(radius(), STRONG), scene=photo, noise=0.001, subifd=True,
             raw_tags=sony_vignetting_tags(STRONG))
    y, x = np.mgrid[:H, :W]
    shifted = np.hypot(x + 0.5 - W / 2 - 150, y + 0.5 - H / 2) / math.hypot(W / 2, H / 2)
    out["lying"] = d / "lying.dng"
    make_dng(out["lying"], field=sony_phi(shifted, STRONG), scene=photo, noise=0.001, subifd=True,
             raw_tags=sony_vignetting_tags(STRONG))
    return out


@needs_exiftool
def test_read_from_the_raw_subifd_through_the_exif_reader(files: dict[str, Path]) -> None:
    from vigproc.io.exif import ExifReader

    with ExifReader() as reader:
        tags = reader.read_tags(files["sony"], ["SubIFD:VignettingCorrParams", "FujiIFD:VignettingParams"])
        assert tags == {"SubIFD:VignettingCorrParams": " ".join(str(v) for v in [16, *SONY])}
        assert reader.read_tags(files["sony"], ["IFD0:VignettingCorrParams"]) == {}  # the group named only
        cal = read_makernote(files["sony"], reader)
        assert cal.source == str(files["sony"].resolve()) and cal.values[0] == 16
        assert read_makernote(files["plain"], reader) is None
        with pytest.raises(MakerNoteError, match="count 16 with 2 values"):
            read_makernote(files["bad"], reader)
        assert reader.launches == 1  # one exiftool process for all of it
    with pytest.raises(ImageReadError, match="file not found"):
        read_makernote(files["sony"].with_name("missing.arw"))


@needs_exiftool
def test_a_dngs_opcodes_win_over_its_maker_notes(files: dict[str, Path]) -> None:
    assert calibration_for(files["both"], "auto").kind == "FixVignetteRadial"
    assert calibration_for(files["sony"], "auto").kind == "sony:VignettingCorrParams"
    assert calibration_for(files["sony"], "estimate") is None
    assert calibration_for(files["bad"], "auto") is None  # logged; the frame is estimated
    with pytest.raises(MakerNoteError):
        calibration_for(files["bad"], "embedded")


def correct(path: Path, outdir: Path, **settings) -> tuple[dict, np.ndarray]:
    outdir.mkdir(exist_ok=True)
    with Processor(Settings(mode="correct", output_format="tiff-float", **settings)) as proc:
        res = proc.process_file(path, outdir).to_dict()
    return res, read_image(res["output"])[0]


def residual_ev(out: np.ndarray, sc: np.ndarray, block: int = 8) -> float:
    def blocks(a: np.ndarray) -> np.ndarray:
        return a.reshape(H // block, block, W // block, block).mean(axis=(1, 3))

    ratio = np.log2(blocks(out.mean(axis=2)) / blocks(sc))
    ratio -= np.median(ratio)
    return float(np.sqrt(np.mean(ratio**2)))


@needs_exiftool
def test_profile_embedded_corrects_with_the_makers_curve(files: dict[str, Path], tmp_path: Path) -> None:
    res, out = correct(files["sony"], tmp_path, profile="embedded")
    assert res["source"] == "embedded" and res["applied"] and res["model"]["method"] == "makernote:sony"
    assert res["embedded"]["kind"] == "sony:VignettingCorrParams" and res["embedded"]["fit_rms_ev"] < 5e-3
    before = float(np.sqrt(np.mean(np.log2(sony_phi(radius())) ** 2)))
    assert residual_ev(out, scene()) < 0.01 < before
    side = json.loads(next(tmp_path.glob("*.vigproc.json")).read_text())
    assert side["embedded"]["tag"] == "SubIFD:VignettingCorrParams"
    # auto uses it too (no stored profile of the lens)
    res, _ = correct(files["sony"], tmp_path / "auto", profile="auto")
    assert res["source"] == "embedded"
    with pytest.raises(ModelError, match="no Sony or Fujifilm vignetting tag"):
        correct(files["plain"], tmp_path / "none", profile="embedded")


@needs_exiftool
def test_a_malformed_tag_is_a_typed_error_on_the_command_line(files: dict[str, Path], tmp_path: Path, capsys) -> None:
    from vigproc.frontends.cli import main

    code = main(["correct", str(files["bad"]), "-o", str(tmp_path), "--profile", "embedded"])
    err = capsys.readouterr().err
    assert code != 0 and "Traceback" not in err and "VignettingCorrParams" in err


@needs_exiftool
def test_check_compares_a_frame_with_its_makers_calibration(files: dict[str, Path], capsys) -> None:
    from vigproc.frontends.cli import main

    def check(path: Path) -> tuple[int, dict]:
        code = main(["check", "--json", "--no-store", "--method", "robust", str(path)])
        return code, json.loads(capsys.readouterr().out)["results"][0]

    code, rec = check(files["honest"])
    emb = rec["embedded"]
    assert emb["expected_source"] == "embedded" and emb["verdict"] == "consistent", emb["reason"]
    assert emb["profile"] == "the camera's own VignettingCorrParams (sony)"
    code, rec = check(files["lying"])
    assert rec["embedded"]["verdict"] == "inconsistent", rec["embedded"]["reason"]
    assert code == 20


#: A real Sony ARW with VignettingCorrParams (none with a licence allowing it in the
#: repository was found; point this at one to run the test).
REAL_ARW = os.environ.get("VIGPROC_TEST_ARW")


@needs_exiftool
@pytest.mark.skipif(not REAL_ARW, reason="no real Sony ARW available: set VIGPROC_TEST_ARW=FILE.ARW to run")
def test_a_real_sony_arw() -> None:
    cal = read_makernote(REAL_ARW)
    assert cal is not None and cal.maker == "sony"
    img, _ = read_image(REAL_ARW)
    _, rms, mx = cal.fit(img.shape[1], img.shape[0])
    assert rms < 0.02
