"""What a correct run writes: each input's own kind back, and nothing that bloats a hot
folder when nothing was applied (issue 20)."""

import json
import os
import shutil
import subprocess

import numpy as np
import pytest

from benchmarks.synthetic import table1_model
from vigproc.io.images import jpeg_quality, read_image, write_image
from vigproc.pipeline.processor import OUTPUT_FORMATS, Processor, Settings, output_format_for

from conftest import photo_like, run_cli

pytestmark = pytest.mark.skipif(shutil.which("exiftool") is None, reason="exiftool program not installed")



def run(*args):
    """``vigproc ARGS``, in this process (what is tested is not the process boundary)."""
    return run_cli(*args)


def _vignetted(h=240, w=360, seed=3):
    truth = table1_model(1).rescale(w, h)
    return np.repeat((photo_like(h, w, seed=seed) * truth.field())[..., None], 3, axis=2).astype(np.float32)


@pytest.fixture(scope="module")
def _camera_jpeg_bytes(tmp_path_factory):
    """The camera JPEG, made once (an exiftool run costs about 0.3 CPU s)."""
    p = tmp_path_factory.mktemp("camera") / "IMG_0001.jpg"
    write_image(p, _vignetted(), transfer="srgb", quality=80)
    subprocess.run(["exiftool", "-q", "-overwrite_original", "-Make=Canon", "-Model=Canon EOS 600D",
                    "-LensModel=EF-S18-55mm f/3.5-5.6 IS II", "-FocalLength=18", "-FNumber=3.5", str(p)], check=True)
    return p.read_bytes()


@pytest.fixture
def camera_jpeg(tmp_path, _camera_jpeg_bytes):
    """A vignetted JPEG at quality 80 with camera EXIF written by exiftool: each test's own copy."""
    p = tmp_path / "IMG_0001.jpg"
    p.write_bytes(_camera_jpeg_bytes)
    return p


def _exif(path):
    out = subprocess.run(["exiftool", "-j", "-Make", "-Model", "-LensModel", "-ColorSpace", str(path)],
                         capture_output=True, text=True, check=True).stdout
    return json.loads(out)[0]


@pytest.mark.parametrize("q", [40, 75, 92])
def test_jpeg_quality_reads_the_ijg_quality_back(tmp_path, q):
    p = tmp_path / "q.jpg"
    write_image(p, _vignetted(64, 96), transfer="srgb", quality=q)
    assert jpeg_quality(p) == q
    assert jpeg_quality(tmp_path) is None
    (tmp_path / "x.jpg").write_bytes(b"\xff\xd8\xff\xd9")  # no table
    assert jpeg_quality(tmp_path / "x.jpg") is None


def test_jpeg_in_jpeg_out_with_its_exif_and_no_bloat(camera_jpeg, tmp_path):
    out = tmp_path / "out"
    r = run("correct", camera_jpeg, "-o", out, "--profile", "estimate")
    assert r.returncode == 0, r.stderr
    dst = out / "IMG_0001.corrected.jpg"
    assert dst.is_file() and not list(out.glob("*.tif")), sorted(p.name for p in out.iterdir())
    img, info = read_image(dst)
    assert info.format == "jpeg" and info.bit_depth == "uint8" and info.transfer == "srgb"
    assert jpeg_quality(dst) == 90  # the source's 80, raised to the floor of a second lossy pass
    assert dst.stat().st_size < 3 * camera_jpeg.stat().st_size
    tags = _exif(dst)
    assert tags["Model"] == "Canon EOS 600D" and tags["LensModel"] == "EF-S18-55mm f/3.5-5.6 IS II"
    # the correction lifted the corners
    src, _ = read_image(camera_jpeg)
    assert img[:20, :20].mean() > 1.2 * src[:20, :20].mean()


def test_fixed_formats_and_raw_default(tmp_path, camera_jpeg):
    fmt = output_format_for("auto", camera_jpeg)
    assert fmt.suffix == ".jpg" and fmt.format == "jpeg"
    assert output_format_for("auto", tmp_path / "a.JPEG").suffix == ".jpeg"
    assert output_format_for("auto", tmp_path / "a.nef") == OUTPUT_FORMATS["tiff16"]
    assert output_format_for("auto", tmp_path / "a.png").format == "png"
    assert output_format_for("tiff-float", camera_jpeg) == OUTPUT_FORMATS["tiff-float"]
    assert output_format_for("auto", camera_jpeg, like=tmp_path / "x.png").format == "png"
    out = tmp_path / "o"
    r = run("correct", camera_jpeg, "-o", out, "--profile", "estimate", "--output-format", "tiff16")
    assert r.returncode == 0, r.stderr
    _, info = read_image(out / "IMG_0001.jpg.corrected.tif")  # the format changed: the extension stays
    assert info.bit_depth == "uint16" and info.transfer == "linear"


def test_png_in_png_out(tmp_path):
    src = tmp_path / "scan.png"
    write_image(src, _vignetted(), bit_depth="uint8", transfer="srgb")
    (tmp_path / "o").mkdir()
    with Processor(Settings(profile="estimate")) as proc:
        res = proc.process_file(src, tmp_path / "o")
    assert res.applied and res.output.endswith("scan.corrected.png")
    _, info = read_image(res.output)
    assert info.format == "png" and info.bit_depth == "uint8" and info.transfer == "srgb"


def test_nothing_applied_puts_the_original_under_the_output_name_by_default(camera_jpeg, tmp_path):
    """Every photo comes out: a next step watching OUT for images loses none (issue 38)."""
    out = tmp_path / "out"
    before = camera_jpeg.read_bytes()
    r = run("correct", camera_jpeg, "-o", out, "--profile", "estimate", "--strength", "0")
    assert r.returncode == 0, r.stderr
    assert sorted(p.name for p in out.iterdir()) == ["IMG_0001.corrected.jpg", "IMG_0001.jpg.vigproc.json"]
    kept = out / "IMG_0001.corrected.jpg"
    assert kept.read_bytes() == before and camera_jpeg.read_bytes() == before  # its bytes: no second lossy pass
    side = json.loads((out / "IMG_0001.jpg.vigproc.json").read_text())
    assert side["applied"] is False and side["not_applied"] == "strength 0" and side["output"] == str(kept)
    assert side["not_applied_rule"] == "strength-0"
    assert "0 corrected, 1 not corrected, 0 failed" in r.stdout and "not corrected: strength 0" in r.stdout


def test_keep_writes_the_frame_as_read_when_the_format_changes(camera_jpeg, tmp_path):
    out = tmp_path / "out"
    r = run("correct", camera_jpeg, "-o", out, "--profile", "estimate", "--strength", "0", "--output-format", "png")
    assert r.returncode == 0, r.stderr
    written = out / "IMG_0001.jpg.corrected.png"
    got, info = read_image(written)
    src, _ = read_image(camera_jpeg)
    assert info.format == "png" and np.abs(got - src).max() < 2e-3  # the original's pixels, not a JPEG renamed


def test_skip_writes_no_image(camera_jpeg, tmp_path):
    out = tmp_path / "out"
    r = run("correct", camera_jpeg, "-o", out, "--profile", "estimate", "--strength", "0", "--unapplied", "skip")
    assert r.returncode == 0, r.stderr
    assert sorted(p.name for p in out.iterdir()) == ["IMG_0001.jpg.vigproc.json"]
    side = json.loads((out / "IMG_0001.jpg.vigproc.json").read_text())
    assert side["applied"] is False and side["not_applied"] == "strength 0" and "output" not in side
    assert "0 corrected, 1 not corrected, 0 failed" in r.stdout
    assert "no image written" in r.stdout


@pytest.mark.parametrize("policy", ["copy", "link"])
def test_nothing_applied_keeps_the_original_when_asked(camera_jpeg, tmp_path, policy):
    out = tmp_path / policy
    before = camera_jpeg.read_bytes()
    r = run("correct", camera_jpeg, "-o", out, "--profile", "estimate", "--strength", "0", "--unapplied", policy)
    assert r.returncode == 0, r.stderr
    kept = out / "IMG_0001.uncorrected.jpg"
    assert kept.read_bytes() == before and camera_jpeg.read_bytes() == before
    assert not list(out.glob("*.corrected.*"))
    side = json.loads((out / "IMG_0001.jpg.vigproc.json").read_text())
    assert side["output"] == str(kept) and side["applied"] is False
    if policy == "link":
        assert os.stat(kept).st_ino == os.stat(camera_jpeg).st_ino  # same file system here: a hard link
    else:
        assert os.stat(kept).st_ino != os.stat(camera_jpeg).st_ino
        from vigproc.atomic import new_file_mode_mask

        assert kept.stat().st_mode & 0o777 == 0o666 & ~new_file_mode_mask()  # like every output, not 0600
    assert not [p for p in out.iterdir() if p.name.startswith(".")]  # no temporary left


def test_a_host_named_output_is_written_even_when_nothing_is_applied(camera_jpeg, tmp_path):
    target = tmp_path / "export" / "fixed.png"
    target.parent.mkdir()
    r = run("hook", "--mode", "correct", "--profile", "estimate", "--strength", "0", f"--output-file={target}",
            "--", camera_jpeg)
    assert r.returncode == 0, r.stderr
    doc = json.loads(r.stdout)
    assert doc["results"][0]["applied"] is False and doc["results"][0]["output"] == str(target)
    _, info = read_image(target)
    assert info.format == "png"  # auto: the suffix the host named picks the format


def test_settings_refuse_an_unknown_policy():
    from vigproc.errors import VigprocError

    with pytest.raises(VigprocError, match="not corrected"):
        Settings(unapplied="delete")
    r = run("correct", "x.jpg", "-o", "o", "--unapplied", "delete")
    assert r.returncode == 2 and "invalid choice" in r.stderr


def test_write_policy_still_says_why_nothing_was_applied(camera_jpeg, tmp_path):
    out = tmp_path / "w"
    r = run("correct", camera_jpeg, "-o", out, "--profile", "estimate", "--strength", "0", "--unapplied", "write")
    assert r.returncode == 0, r.stderr
    side = json.loads((out / "IMG_0001.jpg.vigproc.json").read_text())
    assert side["applied"] is False and side["not_applied"] == "strength 0"
    assert (out / "IMG_0001.corrected.jpg").is_file() and "not corrected: strength 0" in r.stdout


def test_profile_list_and_learn_say_what_happened(camera_jpeg, tmp_path):
    db = tmp_path / "p.sqlite"
    r = run("profile", "--profile-db", db, "list")
    assert r.returncode == 0 and "no profiles in" in r.stdout  # not an empty output
    r = run("profile", "--profile-db", db, "learn", camera_jpeg)
    assert r.returncode == 0 and r.stdout.splitlines()[-1] == "1 frame learned, 0 failed", r.stdout
    r = run("profile", "--profile-db", db, "learn", camera_jpeg)  # the same content again: pooled once
    assert r.returncode == 0 and "already learned" in r.stdout
    assert r.stdout.splitlines()[-1] == "0 frames learned, 1 already learned before, 0 failed", r.stdout


def test_an_adobe_rgb_jpeg_stays_tagged_adobe_rgb(camera_jpeg, tmp_path):
    """vigproc divides a gain out and never converts primaries: a display-encoded output
    of an Adobe RGB JPEG is still Adobe RGB (it came back tagged sRGB)."""
    subprocess.run(["exiftool", "-q", "-overwrite_original", "-ExifIFD:ColorSpace=Uncalibrated",
                    "-InteropIFD:InteropIndex=R03", str(camera_jpeg)], check=True)

    def colour(path):
        out = subprocess.run(["exiftool", "-j", "-n", "-ColorSpace", "-InteropIndex", str(path)],
                             capture_output=True, text=True, check=True).stdout
        d = json.loads(out)[0]
        return d.get("ColorSpace"), d.get("InteropIndex")

    out = tmp_path / "o"
    r = run("correct", camera_jpeg, "-o", out, "--profile", "estimate")
    assert r.returncode == 0, r.stderr
    assert colour(out / "IMG_0001.corrected.jpg") == (65535, "R03")
    # a linear output describes its own encoding, whatever the source's was
    r = run("correct", camera_jpeg, "-o", tmp_path / "lin", "--profile", "estimate", "--output-format", "tiff16")
    assert r.returncode == 0, r.stderr
    assert colour(tmp_path / "lin" / "IMG_0001.jpg.corrected.tif")[1] is None


def test_output_names_encode_bidi_and_c1_controls_one_to_one():
    """A right-to-left override would show 'IMG_gpj.exe' as 'IMG_exe.jpg' in a file
    manager: output names carry such controls as their UTF-8 bytes, percent-encoded."""
    from vigproc.pipeline.processor import output_name

    rlo = output_name("IMG_\u202egpj.exe")
    assert "\u202e" not in rlo and rlo == "IMG_%E2%80%AEgpj.exe"
    assert output_name("a\x85b.jpg") == "a%C2%85b.jpg"
    assert output_name("été.jpg") == "été.jpg"  # letters of any script are kept
    # one-to-one: the encoded form of a control differs from the literal text it encodes to
    assert output_name("IMG_%E2%80%AEgpj.exe") != rlo
