"""Metadata carried into corrected outputs (vigproc.io.metadata), with the exiftool program."""

from __future__ import annotations

import hashlib
import json
import logging
import os
import shutil
import stat
import subprocess
import tempfile
from pathlib import Path

import numpy as np
import OpenImageIO as oiio
import pytest

import vigproc
from vigproc.errors import ImageWriteError, InvalidImageError
from vigproc.io.images import LINEAR_TIFF_MARKER, read_image, write_image
from vigproc.io.metadata import copy_metadata, make_record, read_record, write_corrected
from vigproc.core.model import FitQuality, VignettingModel

pytestmark = pytest.mark.skipif(shutil.which("exiftool") is None, reason="exiftool program not installed")

EXIF = {
    "Make": "Canon",
    "Model": "Canon EOS 5D Mark II",
    "LensModel": "EF24-105mm f/4L IS USM",
    "FocalLength": 24.0,
    "FNumber": 4.0,
    "DateTimeOriginal": "2021:06:07 08:09:10",
    "Artist": "Zoë Ångström 日本",
}
H, W = 48, 72


def sha256(path: Path) -> str:
    return hashlib.sha256(Path(path).read_bytes()).hexdigest()


def tags(path: Path, *names: str, numeric: bool = True) -> dict:
    """exiftool's view of ``path`` (all tags when no names are given)."""
    args = ["exiftool", "-j", "-a"] + (["-n"] if numeric else [])
    args += [f"-{n}" for n in names]
    out = subprocess.run(args + ["--", os.path.abspath(path)], capture_output=True, check=True).stdout
    d = json.loads(out)[0]
    d.pop("SourceFile")
    return d


_JPEGS: dict[tuple, bytes] = {}


def make_jpeg(path: Path, exif: dict | None = None, *, thumbnail: bool = True) -> Path:
    """A small JPEG with camera EXIF (set by exiftool), an sRGB ColorSpace and a thumbnail:
    made once per (exif, thumbnail) under a plain name and copied to ``path`` (its bytes do
    not depend on the name; an exiftool start costs about 0.3 CPU s)."""
    tags_ = EXIF if exif is None else exif
    key = (tuple(tags_.items()), thumbnail)
    if key not in _JPEGS:
        with tempfile.TemporaryDirectory() as d:
            _JPEGS[key] = _make_jpeg(Path(d) / "photo.jpg", tags_, thumbnail).read_bytes()
    path.write_bytes(_JPEGS[key])
    return path


def _make_jpeg(path: Path, exif: dict, thumbnail: bool) -> Path:
    rng = np.random.default_rng(0)
    data = (rng.random((H, W, 3)) * 255).astype(np.uint8)
    out = oiio.ImageOutput.create(str(path))
    assert out.open(str(path), oiio.ImageSpec(W, H, 3, "uint8")) and out.write_image(data)
    out.close()
    args = ["exiftool", "-q", "-overwrite_original"]
    args += [f"-{k}={v}" for k, v in exif.items()]
    args += ["-ColorSpace=sRGB", "-ImageDescription=Holiday", "-Software=Firmware 1.0", "-ExifImageWidth=5616"]
    if thumbnail:
        args.append(f"-ThumbnailImage<={os.path.abspath(path)}")  # itself, as a JPEG thumbnail
    subprocess.run(args + ["--", os.path.abspath(path)], check=True, capture_output=True)
    return path


def rich_model() -> VignettingModel:
    """A model with every serialised part: covariance, quality (inf SNR), odd floats."""
    cov = np.diag(np.linspace(1e-9, 1.0, 12))
    return VignettingModel(
        W, H, center=(1.25, -3.0), p=(1.0 / 3.0e3, 1e-6, 2.0 / 7.0e3),
        alpha=(0.02, 0.01, 0, 0, 0, 0, 1e-17), method="default",
        covariance=tuple(tuple(r) for r in cov),
        quality=FitQuality(confidence=0.87, field_ev_rms=0.31, snr=float("inf"), objective=0.5, iterations=12),
    )


def _umask() -> int:
    old = os.umask(0o022)
    os.umask(old)
    return old


def image() -> np.ndarray:
    rng = np.random.default_rng(1)
    return (0.05 + 0.9 * rng.random((H, W, 3))).astype(np.float32)


@pytest.fixture
def src(tmp_path: Path) -> Path:
    d = tmp_path / "in"
    d.mkdir()
    return make_jpeg(d / "photo.jpg")


@pytest.fixture
def outdir(tmp_path: Path) -> Path:
    d = tmp_path / "out"
    d.mkdir()
    return d


@pytest.mark.parametrize("depth", ["uint16", "float"])
def test_tiff_round_trip(src: Path, outdir: Path, depth: str) -> None:
    before = sha256(src)
    model = rich_model()
    dst = outdir / "photo.tif"
    img = image()
    write_corrected(dst, img, src, make_record(model), bit_depth=depth)

    t = tags(dst, numeric=False)
    assert t["Make"] == EXIF["Make"] and t["Model"] == EXIF["Model"]
    assert t["LensModel"] == EXIF["LensModel"]
    assert t["FocalLength"] == "24.0 mm" and float(t["FNumber"]) == 4.0
    assert t["DateTimeOriginal"] == EXIF["DateTimeOriginal"]
    assert t["Artist"] == EXIF["Artist"]
    # dropped or re-stated: thumbnail, encoding, structure, software
    assert "ThumbnailImage" not in t and "ExifImageWidth" not in t
    assert t["ColorSpace"] == "Uncalibrated"
    assert t["ImageDescription"] == "Holiday"  # the source's caption; the transfer is in XMP
    assert tags(dst, "XMP-vigproc:Transfer")["Transfer"] == "linear"
    assert read_image(dst)[1].transfer == "linear"
    assert t["Software"] == "vigproc"
    assert t["BitsPerSample"] == ("16 16 16" if depth == "uint16" else "32 32 32")

    rec = read_record(dst)
    assert rec is not None
    assert rec["model"] == model
    assert VignettingModel.from_json(rec["model_json"]) == model
    assert rec["method"] == "default" and rec["applied"] is True and rec["strength"] == 1.0
    assert rec["version"] == vigproc.__version__

    back, info = read_image(dst)
    assert info.transfer == "linear"
    np.testing.assert_allclose(back, img, atol=1e-4 if depth == "uint16" else 0)

    # an output read back (a later pass, a check) gives the camera's lens key: the
    # record's own Model tag (the model JSON) is not taken for the camera model
    from vigproc.io.exif import read_lens_key

    key = read_lens_key(dst)
    assert key.model is not None and key.problems == (), key.problems

    assert sha256(src) == before
    assert sorted(os.listdir(outdir)) == ["photo.tif"]
    assert sorted(os.listdir(src.parent)) == ["photo.jpg"]
    assert stat.S_IMODE(os.stat(dst).st_mode) == 0o666 & ~_umask()


def test_png_round_trip(src: Path, outdir: Path) -> None:
    dst = outdir / "photo.png"
    write_corrected(dst, image(), src, make_record(rich_model()))
    t = tags(dst, "Make", "LensModel", "Artist", "ColorSpace")
    assert t["Make"] == "Canon" and t["LensModel"] == EXIF["LensModel"] and t["Artist"] == EXIF["Artist"]
    assert t.get("ColorSpace") != 1  # the source's sRGB flag is not copied
    assert read_record(dst)["model"] == rich_model()
    assert read_image(dst)[1].transfer == "linear"


HOSTILE = [
    "with space",
    "quote's \"double\"",
    "new\nline",
    "-leading-dash",
    "-",
    "@",
    "pct %d%f%e %c",
    "日本語 é ü",
]


@pytest.mark.parametrize("name", HOSTILE)
def test_hostile_names(tmp_path: Path, monkeypatch: pytest.MonkeyPatch, name: str) -> None:
    src = make_jpeg(tmp_path / f"{name}.jpg")
    before = sha256(src)
    # relative names: a leading '-' must not be read as an exiftool option
    monkeypatch.chdir(tmp_path)
    dst = f"{name}.tif"
    write_corrected(dst, image(), f"{name}.jpg", make_record(rich_model()))
    assert tags(tmp_path / dst, "LensModel")["LensModel"] == EXIF["LensModel"]
    assert read_record(dst)["model"] == rich_model()
    assert sha256(src) == before
    assert sorted(os.listdir(tmp_path)) == sorted([f"{name}.jpg", dst])


def test_source_not_an_image(tmp_path: Path, outdir: Path) -> None:
    bad = tmp_path / "notes.jpg"
    bad.write_text("just text\n")
    dst = outdir / "out.tif"
    with pytest.raises(ImageWriteError, match=r"out\.tif.*notes\.jpg.*not an image"):
        write_corrected(dst, image(), bad, make_record(rich_model()))
    assert os.listdir(outdir) == []


def test_source_empty_or_missing(tmp_path: Path, outdir: Path) -> None:
    empty = tmp_path / "empty.jpg"
    empty.write_bytes(b"")
    with pytest.raises(ImageWriteError, match="empty"):
        write_corrected(outdir / "a.tif", image(), empty, None)
    with pytest.raises(ImageWriteError, match="does not exist"):
        write_corrected(outdir / "a.tif", image(), tmp_path / "nope.jpg", None)
    assert os.listdir(outdir) == []


def test_failure_keeps_existing_output(src: Path, outdir: Path, tmp_path: Path) -> None:
    dst = outdir / "photo.tif"
    write_corrected(dst, image(), src, make_record(rich_model()))
    good = sha256(dst)
    bad = tmp_path / "bad.jpg"
    bad.write_bytes(b"%PDF-1.4 not an image")
    with pytest.raises(ImageWriteError):
        write_corrected(dst, image() * 0.5, bad, None)
    assert sha256(dst) == good
    assert os.listdir(outdir) == ["photo.tif"]


def test_exiftool_write_error_is_reported(src: Path, outdir: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    # the persistent exiftool reads as usual but fails every write, naming our temporary
    from vigproc.io.exiftool_process import ExiftoolProcess, ExiftoolResult

    real = ExiftoolProcess.execute

    def failing(self, args, **kwargs):
        if "-overwrite_original" in args:
            return ExiftoolResult(b"", f"Error: simulated disk full - {args[-1]}".encode(), 1)
        return real(self, args, **kwargs)

    monkeypatch.setattr(ExiftoolProcess, "execute", failing)
    dst = outdir / "photo.tif"
    with pytest.raises(ImageWriteError, match=r"photo\.tif.*simulated disk full") as info:
        write_corrected(dst, image(), src, make_record(rich_model()))
    assert ".tmp" not in str(info.value)  # the user's file is named, not our temporary
    assert os.listdir(outdir) == []


def test_missing_exiftool(src: Path, outdir: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("VIGPROC_EXIFTOOL", "/nonexistent/exiftool")
    with pytest.raises(ImageWriteError, match="exiftool program not found"):
        write_corrected(outdir / "x.tif", image(), src, None)
    assert os.listdir(outdir) == []


@pytest.mark.skipif(os.name != "posix" or os.geteuid() == 0, reason="root ignores directory permissions")
def test_read_only_folder(src: Path, outdir: Path) -> None:
    outdir.chmod(0o555)
    try:
        with pytest.raises(ImageWriteError, match="out"):
            write_corrected(outdir / "x.tif", image(), src, None)
    finally:
        outdir.chmod(0o755)
    assert os.listdir(outdir) == []


def test_copy_metadata_in_place_without_record(src: Path, outdir: Path) -> None:
    dst = outdir / "plain.tif"
    write_image(dst, image())
    copy_metadata(src, dst, None)
    assert tags(dst, "Model")["Model"] == EXIF["Model"]
    assert read_record(dst) is None
    assert os.listdir(outdir) == ["plain.tif"]


def test_old_record_is_not_inherited(src: Path, outdir: Path) -> None:
    first = outdir / "first.tif"
    write_corrected(first, image(), src, make_record(rich_model()))
    second = outdir / "second.tif"
    write_corrected(second, image(), first, None)
    assert read_record(second) is None
    assert tags(second, "LensModel")["LensModel"] == EXIF["LensModel"]


def test_fallback_record_and_version_text(src: Path, outdir: Path) -> None:
    ident = VignettingModel.identity(W, H)
    rec = make_record(ident)
    assert rec["applied"] is False
    rec["version"] = "1.10"  # exiftool prints number-like text unquoted in JSON
    dst = outdir / "id.tif"
    write_corrected(dst, image(), src, rec)
    back = read_record(dst)
    assert back["applied"] is False and back["version"] == "1.10"
    assert back["model"].is_identity


def test_same_file_and_bad_record(src: Path, outdir: Path) -> None:
    dst = outdir / "x.tif"
    write_image(dst, image())
    with pytest.raises(ImageWriteError, match="same file"):
        copy_metadata(dst, dst, None)
    with pytest.raises(ValueError, match="unknown record keys"):
        copy_metadata(src, dst, {"modle": "{}"})


def test_no_metadata_source_is_fine(tmp_path: Path, outdir: Path, caplog: pytest.LogCaptureFixture) -> None:
    bare = tmp_path / "bare.png"
    write_image(bare, image())
    dst = outdir / "x.tif"
    with caplog.at_level(logging.INFO, logger="vigproc.io.metadata"):
        write_corrected(dst, image(), bare, make_record(rich_model()))
    assert read_record(dst)["model"] == rich_model()
    assert not [r for r in caplog.records if r.levelno >= logging.WARNING]


def test_exiftool_warnings_are_logged(tmp_path: Path, outdir: Path, caplog: pytest.LogCaptureFixture) -> None:
    odd = tmp_path / "odd.jpg"
    odd.write_bytes(b"\xff\xd8\xff but no JPEG segments follow")
    with caplog.at_level(logging.INFO, logger="vigproc.io.metadata"):
        write_corrected(outdir / "x.tif", image(), odd, None)
    assert any("JPEG format error" in r.getMessage() and r.levelno == logging.WARNING for r in caplog.records)
    # nothing to copy is only worth a note
    notes = [r for r in caplog.records if "No writable tags" in r.getMessage()]
    assert notes and all(r.levelno == logging.INFO for r in notes)


# --------------------------------------------------------------------------- OpenEXR


def test_exiftool_cannot_write_exr(tmp_path: Path) -> None:
    # the reason EXR outputs get their metadata through OpenImageIO
    p = tmp_path / "a.exr"
    write_image(p, image())
    res = subprocess.run(["exiftool", "-Artist=x", "--", str(p)], capture_output=True, text=True)
    assert res.returncode != 0 and "not yet supported" in res.stderr


def exr_attrs(path: Path) -> dict:
    inp = oiio.ImageInput.open(str(path))
    try:
        return {a.name: a.value for a in inp.spec().extra_attribs}
    finally:
        inp.close()


@pytest.mark.parametrize("depth", ["half", "float"])
def test_exr_output(src: Path, outdir: Path, depth: str) -> None:
    before = sha256(src)
    dst = outdir / "photo.exr"
    img = image()
    write_corrected(dst, img, src, make_record(rich_model()), bit_depth=depth)
    a = exr_attrs(dst)
    assert a["Make"] == "Canon" and a["Model"] == EXIF["Model"]
    assert a["Exif:LensModel"] == EXIF["LensModel"]
    assert a["Exif:FocalLength"] == pytest.approx(24.0)
    assert a["FNumber"] == pytest.approx(4.0)
    assert a["Exif:DateTimeOriginal"] == EXIF["DateTimeOriginal"]
    assert a["DateTime"] == EXIF["DateTimeOriginal"]  # OpenEXR capDate
    assert a["Artist"] == EXIF["Artist"]
    assert a["vigproc:Applied"] == 1
    rec = read_record(dst)
    assert rec["model"] == rich_model() and rec["applied"] is True
    back, info = read_image(dst)
    assert info.bit_depth == depth and info.transfer == "linear"
    np.testing.assert_allclose(back, img, rtol=1e-3 if depth == "half" else 0)
    # exiftool reads (not writes) EXR attributes, e.g. for other tools
    assert tags(dst, "Make")["Make"] == "Canon"
    assert sha256(src) == before
    assert os.listdir(outdir) == ["photo.exr"]


def test_exr_source_to_tiff(src: Path, outdir: Path) -> None:
    exr = outdir / "a.exr"
    write_corrected(exr, image(), src, None)
    tif = outdir / "b.tif"
    write_corrected(tif, image(), exr, None)
    t = tags(tif, "Make", "LensModel", "FocalLength", "Artist")
    assert t == {"Make": "Canon", "LensModel": EXIF["LensModel"], "FocalLength": 24, "Artist": EXIF["Artist"]}


# --------------------------------------------------------------------------- real camera files


def test_real_camera_jpeg_icc_and_previews(shared_data: Path, outdir: Path) -> None:
    d = shared_data / "jpeg_exif" / "metadata-extractor-images"
    iphone, nikon = d / "Apple_iPhone_4.jpg", d / "Nikon_E5700.jpg"
    if not (iphone.is_file() and nikon.is_file()):
        pytest.skip("sample camera JPEGs not present")
    assert "ICC_Profile:ProfileDescription" in {f"{k}" for k in _g0(iphone)}
    out = outdir / "iphone.tif"
    write_corrected(out, image(), iphone, None)
    t = _g0(out)
    assert t["EXIF:Model"] == "iPhone 4" and "EXIF:GPSLatitude" in t
    # linear output: not the source's sRGB profile, but the linear one that says what it holds
    assert t.get("ICC_Profile:ProfileDescription") == "vigproc linear sRGB (gamma 1.0)"
    assert t["EXIF:ColorSpace"] == 65535
    out = outdir / "nikon.tif"
    write_corrected(out, image(), nikon, None)
    t = _g0(out)
    assert "MakerNotes:MakerNoteVersion" in t  # maker notes kept (lens data)
    assert int(t.get("MakerNotes:PreviewImageLength", 0)) == 0  # their preview dropped
    assert "EXIF:ThumbnailImage" not in t


def _g0(path: Path) -> dict:
    out = subprocess.run(["exiftool", "-j", "-n", "-G0", "-a", "--", str(path)], capture_output=True, check=True)
    return json.loads(out.stdout)[0]


@pytest.mark.parametrize("name", ["-", "@", "-all=", "-tagsFromFile"])
def test_source_named_like_exiftool_syntax(tmp_path: Path, monkeypatch: pytest.MonkeyPatch, name: str) -> None:
    # bare '-' is stdin and '@' the target file for exiftool; these are plain files here
    make_jpeg(tmp_path / "x.jpg")
    os.replace(tmp_path / "x.jpg", tmp_path / name)
    monkeypatch.chdir(tmp_path)
    write_corrected("out.tif", image(), name, None)
    assert tags(tmp_path / "out.tif", "LensModel")["LensModel"] == EXIF["LensModel"]
    assert sorted(os.listdir(tmp_path)) == sorted([name, "out.tif"])


def test_bad_pixels_or_record_name_the_output(src: Path, outdir: Path) -> None:
    with pytest.raises(InvalidImageError, match=r"'.*/out/x\.tif'"):
        write_corrected(outdir / "x.tif", np.zeros((4, 4, 2)), src, None)
    with pytest.raises(ValueError, match="unknown record keys"):
        write_corrected(outdir / "x.tif", image(), src, {"bogus": 1})
    assert os.listdir(outdir) == []


def test_long_non_ascii_name(src: Path, outdir: Path) -> None:
    name = "日本語" * 27 + ".tif"  # 243 bytes: temp names must be shortened
    write_corrected(outdir / name, image(), src, None)
    assert os.listdir(outdir) == [name]


def test_source_read_skips_only_the_source_check(src: Path, outdir: Path, monkeypatch) -> None:
    """The pipeline has decoded the source and read its EXIF: the copy asks exiftool once
    (the write), not twice, and copies the same tags; a caller that has not still gets
    the source check (a non-image source refused)."""
    from vigproc.io import metadata as md

    calls: list[list[str]] = []
    orig = md._Exiftool.run

    def run(self, args, *a, **kw):
        calls.append(list(args))
        return orig(self, args, *a, **kw)

    monkeypatch.setattr(md._Exiftool, "run", run)
    for source_read, expected in ((False, 2), (True, 1)):
        calls.clear()
        dst = outdir / f"read-{source_read}.tif"
        write_image(dst, image())
        copy_metadata(src, dst, make_record(rich_model()), source_read=source_read)
        assert len(calls) == expected
        assert tags(dst, "Model", "LensModel") == {"Model": EXIF["Model"], "LensModel": EXIF["LensModel"]}
        assert read_record(dst) is not None
    bad = outdir / "notes.jpg"
    bad.write_bytes(b"%PDF-1.4 not an image")
    dst = outdir / "after-bad.tif"
    write_image(dst, image())
    with pytest.raises(ImageWriteError, match="not an image"):
        copy_metadata(bad, dst, None)
