"""Metadata that survives a correction (issue 36) and the persistent exiftool that copies it (issue 39)."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest

from dngfixture import make_dng
from vigproc.core.model import VignettingModel
from vigproc.io import metadata
from vigproc.io.exiftool_process import ExiftoolDied, ExiftoolProcess
from vigproc.io.images import read_image
from vigproc.io.metadata import make_record, write_corrected

pytestmark = pytest.mark.skipif(shutil.which("exiftool") is None, reason="exiftool program not installed")

#: The camera's EXIF a corrected RAW must keep (exiftool tag names and values to write).
CAMERA = {
    "Make": "Vigproc", "Model": "Synthetic DNG 1", "SerialNumber": "BODY-1234",
    "DateTimeOriginal": "2024:05:06 07:08:09", "CreateDate": "2024:05:06 07:08:09",
    "OffsetTimeOriginal": "+02:00", "SubSecTimeOriginal": "42",
    "ExposureTime": "0.008", "FNumber": "2", "ISO": "200", "ExposureProgram": "Aperture-priority AE",
    "ExposureCompensation": "-0.7", "MeteringMode": "Multi-segment", "Flash": "Off, Did not fire",
    "LensMake": "Vigproc Optics", "LensModel": "VP 35mm F2.0 Test", "LensSerialNumber": "LS-0042",
    "FocalLength": "35", "FocalLengthIn35mmFormat": "52",
    "GPSLatitude": "48.8584", "GPSLatitudeRef": "N", "GPSLongitude": "2.2945", "GPSLongitudeRef": "E",
    "Artist": "Zoë Ångström", "OwnerName": "Studio 日本", "Copyright": "(c) 2024 Zoë",
    "ImageDescription": "Eiffel tower at dawn", "XMP-dc:Description": "Tour Eiffel, caption",
    "XMP-dc:Subject": "paris",
}


def exif_of(path: Path, names) -> dict:
    out = subprocess.run(["exiftool", "-j", "-n", *[f"-{n}" for n in names], os.path.abspath(path)],
                         capture_output=True, check=True).stdout
    d = json.loads(out)[0]
    d.pop("SourceFile")
    return {k: str(v) for k, v in d.items()}


def record() -> dict:
    return make_record(VignettingModel(64, 48, alpha=(0.01, 0, 0, 0, 0, 0, 0)))


@pytest.fixture(scope="module")
def _dng_bytes(tmp_path_factory: pytest.TempPathFactory) -> bytes:
    """The camera DNG, made once (its EXIF by an exiftool run, about 0.3 CPU s)."""
    path = tmp_path_factory.mktemp("dng") / "shot.dng"
    make_dng(path, width=64, height=48, exif=CAMERA)
    return path.read_bytes()


@pytest.fixture
def dng(tmp_path: Path, _dng_bytes: bytes) -> Path:
    """Each test's own copy of the camera DNG."""
    path = tmp_path / "in" / "shot.dng"
    path.parent.mkdir()
    path.write_bytes(_dng_bytes)
    return path


def test_raw_to_tiff_keeps_the_camera_tags(dng: Path, tmp_path: Path) -> None:
    src = exif_of(dng, CAMERA)
    assert len(src) >= 25, src  # the fixture wrote them
    img, _ = read_image(dng)
    dst = tmp_path / "shot.corrected.tif"
    write_corrected(dst, img, dng, record(), bit_depth="uint16")
    out = exif_of(dst, CAMERA)
    lost = {k: v for k, v in src.items() if out.get(k) != v}
    assert lost == {}, (lost, out)
    # the transfer lives in vigproc's namespace; the caption stays the photographer's
    assert exif_of(dst, ["XMP-vigproc:Transfer"]) == {"Transfer": "linear"}
    assert read_image(dst)[1].transfer == "linear"
    # what vigproc wrote now is not claimed to be the capture: no XMP CreateDate of today
    assert "CreateDate" not in exif_of(dst, ["XMP-xmp:CreateDate"])


def test_dng_output_keeps_the_camera_tags(dng: Path, tmp_path: Path) -> None:
    from vigproc.io.dng_vignette import write_dng_correction

    src = exif_of(dng, CAMERA)
    dst = tmp_path / "shot.corrected.dng"
    write_dng_correction(dng, dst, VignettingModel(64, 48, alpha=(0.01, 0, 0, 0, 0, 0, 0)))
    out = exif_of(dst, CAMERA)
    assert {k: v for k, v in src.items() if out.get(k) != v} == {}


@pytest.mark.parametrize("fmt,ext", [("jpeg", ".jpg"), ("tiff", ".tif")])
def test_a_jpeg_keeps_its_captions(tmp_path: Path, fmt: str, ext: str) -> None:
    src = tmp_path / "holiday.jpg"
    write_corrected(src, np.full((32, 48, 3), 0.4, np.float32), _blank(tmp_path), None, format="jpeg",
                    transfer="srgb")
    subprocess.run(["exiftool", "-q", "-overwrite_original", "-ImageDescription=Holiday in Rome",
                    "-XMP-dc:Description=Rome, XMP caption", "-IPTC:Caption-Abstract=Rome, IPTC caption",
                    "-Make=Canon", str(src)], check=True)
    dst = tmp_path / f"holiday.corrected{ext}"
    transfer = "srgb" if fmt == "jpeg" else "linear"
    write_corrected(dst, read_image(src)[0], src, record(), format=fmt, transfer=transfer,
                    bit_depth="uint8" if fmt == "jpeg" else "uint16")
    got = exif_of(dst, ["IFD0:ImageDescription", "XMP-dc:Description", "IPTC:Caption-Abstract", "Make"])
    assert got == {"ImageDescription": "Holiday in Rome", "Description": "Rome, XMP caption",
                   "Caption-Abstract": "Rome, IPTC caption", "Make": "Canon"}
    assert read_image(dst)[1].transfer == transfer


def _blank(tmp_path: Path) -> Path:
    p = tmp_path / "blank.png"
    from vigproc.io.images import write_image

    write_image(p, np.full((8, 8, 3), 0.5, np.float32), bit_depth="uint8", transfer="srgb")
    return p


def test_old_files_with_the_description_marker_still_read_linear(tmp_path: Path) -> None:
    from vigproc.io.images import LINEAR_TIFF_MARKER, write_image

    p = tmp_path / "old.tif"
    write_image(p, np.full((8, 8, 3), 0.25, np.float32), bit_depth="uint16", transfer="linear")
    assert exif_of(p, ["ImageDescription"]) == {"ImageDescription": LINEAR_TIFF_MARKER}
    img, info = read_image(p)
    assert info.transfer == "linear" and abs(float(img.mean()) - 0.25) < 1e-3


@pytest.mark.parametrize("name", ["with space", "ünï cödé 日本", "new\nline", "cr\rname"])
def test_hostile_names_keep_the_tags(dng: Path, tmp_path: Path, name: str) -> None:
    folder = tmp_path / f"dir {name}"
    folder.mkdir()
    src = folder / f"{name}.dng"
    shutil.copyfile(dng, src)
    dst = folder / f"{name}.tif"
    img, _ = read_image(src)
    write_corrected(dst, img, src, record(), bit_depth="uint16")
    want = exif_of(dng, ["Make", "LensModel", "Artist", "ImageDescription"])
    assert exif_of(dst, ["Make", "LensModel", "Artist", "ImageDescription"]) == want
    assert sorted(p.name for p in folder.iterdir()) == sorted([src.name, dst.name])


def test_one_persistent_process_copies_every_output(dng: Path, tmp_path: Path) -> None:
    img, _ = read_image(dng)
    write_corrected(tmp_path / "a.tif", img, dng, record(), bit_depth="uint16")
    proc = metadata._process()
    pid, launches = proc.pid, proc.launches
    assert pid is not None
    for n in "bcd":
        write_corrected(tmp_path / f"{n}.tif", img, dng, record(), bit_depth="uint16")
    assert (proc.pid, proc.launches) == (pid, launches)
    os.kill(pid, 9)  # dies between two outputs: the next one starts a new process
    write_corrected(tmp_path / "e.tif", img, dng, record(), bit_depth="uint16")
    assert proc.launches == launches + 1 and proc.pid != pid
    assert exif_of(tmp_path / "e.tif", ["LensModel"]) == {"LensModel": CAMERA["LensModel"]}


def _config(tmp_path: Path, conv: str) -> str:
    """An exiftool config whose composite tag ``Trap`` runs the Perl ``conv`` when asked for."""
    cfg = tmp_path / "trap.config"
    cfg.write_text("%Image::ExifTool::UserDefined = ('Image::ExifTool::Composite' => {\n"
                   f"  Trap => {{ Require => 'FileName', ValueConv => q{{{conv}}} }},\n}});\n1;\n")
    return str(cfg)


def test_a_death_mid_command_is_retried_once(tmp_path: Path) -> None:
    once = tmp_path / "die-once"
    once.write_text("")
    proc = ExiftoolProcess(config_file=_config(tmp_path, f"if (unlink '{once}') {{ exit 9 }} 1"))
    with proc:
        res = proc.execute(["-j", "-Trap", str(_blank(tmp_path))])  # dies, restarted, answers
        assert res.status == 0 and proc.launches == 2 and not once.exists()
    always = ExiftoolProcess(config_file=_config(tmp_path, "exit 9"))
    with always, pytest.raises(ExiftoolDied, match="died"):
        always.execute(["-j", "-Trap", str(_blank(tmp_path))])
    assert always.launches == 2


def test_a_hung_process_is_killed(tmp_path: Path) -> None:
    proc = ExiftoolProcess(config_file=_config(tmp_path, "sleep 60"), timeout=1.0)
    with proc, pytest.raises(ExiftoolDied, match="did not answer"):
        proc.execute(["-j", "-Trap", str(_blank(tmp_path))])


def test_arguments_the_protocol_cannot_carry_are_refused() -> None:
    proc = ExiftoolProcess()
    for bad in (["-j", "/a\nb"], ["-j", "--", "/x"]):
        with pytest.raises(ValueError):
            proc.execute(bad)
    assert proc.launches == 0


def test_a_forked_worker_starts_its_own_process(tmp_path: Path) -> None:
    """A process forked after the start never writes into its parent's exiftool's pipes."""
    with ExiftoolProcess() as proc:
        version = proc.execute(["-ver"]).stdout
        parent = proc.pid
        r, w = os.pipe()
        child = os.fork()
        if child == 0:  # the worker: only the exiftool process, no other library after a fork
            code = 1
            try:
                res = proc.execute(["-ver"])
                os.write(w, f"{proc.pid} {proc.launches} {res.stdout.decode()}".encode())
                proc.close()
                code = 0
            finally:
                os._exit(code)
        os.close(w)
        with os.fdopen(r) as fh:
            pid, launches, ver = fh.read().split()
        assert os.waitpid(child, 0)[1] == 0
        assert int(pid) != parent and int(launches) == 2 and ver.encode() == version
        assert proc.pid == parent and proc.execute(["-ver"]).stdout == version  # the parent's still answers
        assert proc.launches == 1


def test_an_exiftool_that_cannot_start_is_a_typed_error(dng: Path, tmp_path: Path,
                                                        monkeypatch: pytest.MonkeyPatch) -> None:
    from vigproc.errors import ImageWriteError
    from vigproc.pipeline.faults import PERMANENT, classify_error

    fake = tmp_path / "not-exiftool"
    fake.write_text("#!/bin/sh\nexit 3\n")
    fake.chmod(0o755)
    monkeypatch.setenv("VIGPROC_EXIFTOOL", str(fake))
    dst = tmp_path / "out" / "x.tif"
    dst.parent.mkdir()
    with pytest.raises(ImageWriteError, match=r"x\.tif.*cannot run exiftool") as info:
        write_corrected(dst, np.full((16, 16, 3), 0.5, np.float32), dng, record(), bit_depth="uint16")
    assert classify_error(info.value, dst.parent).kind == PERMANENT  # the set-up's fault, not the disk's
    assert os.listdir(dst.parent) == []


def test_warnings_name_the_users_file_not_our_temporary(dng: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
                                                        caplog: pytest.LogCaptureFixture) -> None:
    real = ExiftoolProcess.execute

    def warning_about_the_target(self, args, **kwargs):
        res = real(self, args, **kwargs)
        if "-overwrite_original" in args:  # what exiftool says of a file it writes
            warn = f"Warning: Odd maker notes offset - {args[-1]}\n".encode()
            return type(res)(res.stdout, warn + res.stderr, res.status)
        return res

    monkeypatch.setattr(ExiftoolProcess, "execute", warning_about_the_target)
    dst = tmp_path / "named by the user.tif"
    with caplog.at_level("WARNING", logger="vigproc.io.metadata"):
        write_corrected(dst, np.full((16, 16, 3), 0.5, np.float32), dng, record(), bit_depth="uint16")
    said = [r.getMessage() for r in caplog.records if "Odd maker notes offset" in r.getMessage()]
    assert said and all(".tmp" not in m and "named by the user.tif" in m for m in said), said


def test_a_death_is_seen_while_a_child_of_it_holds_the_pipe(tmp_path: Path) -> None:
    # exiftool dies, but a process it started keeps its output pipe open: no end of file comes
    proc = ExiftoolProcess(config_file=_config(tmp_path, "system(q{sleep 20 &}); exit 9"), timeout=120)
    with proc, pytest.raises(ExiftoolDied, match="died during a command"):
        proc.execute(["-j", "-Trap", str(_blank(tmp_path))])
    assert proc.launches == 2
