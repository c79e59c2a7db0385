"""The command line: outputs, JSON, exit codes, hostile names.  The calls where the
process boundary matters (exit codes of failures and usage errors, hostile names in
stderr, the store a new process opens, each command's start-up) run a real subprocess;
the others run ``main`` in this process, which gives the same exit code and output text
without a second's start-up per call."""

import json
import os
import re
import subprocess
import sys

import numpy as np
import pytest

from benchmarks.synthetic import table1_model
from vigproc.io.images import read_image, write_image
from vigproc.core.model import VignettingModel

from conftest import coloured_scene, photo_like, run_cli as run, textured

VIGPROC = [sys.executable, "-m", "vigproc.frontends.cli"]


def run_process(*args, cwd=None):
    """``vigproc ARGS`` as a new process."""
    return subprocess.run([*VIGPROC, *map(str, args)], capture_output=True, text=True, cwd=cwd, timeout=300)


@pytest.fixture
def vignetted_tiff(tmp_path):
    truth = table1_model(2).rescale(240, 160)
    img = photo_like(160, 240, seed=1) * truth.field()
    path = tmp_path / "frame.tif"
    write_image(path, np.repeat(img[..., None], 3, axis=2).astype(np.float32), bit_depth="float")
    return path, truth


@pytest.fixture
def lens_tiff(tmp_path):
    """A frame with a real lens's depth of fall-off (1.2 EV at the corners, centred)."""
    truth = VignettingModel(240, 160, p=(1 / 100**2, 0.0, 1 / 100**2))
    img = photo_like(160, 240, seed=1) * truth.field()
    path = tmp_path / "frame.tif"
    write_image(path, np.repeat(img[..., None], 3, axis=2).astype(np.float32), bit_depth="float")
    return path, truth


def test_estimate_json(vignetted_tiff):
    path, truth = vignetted_tiff
    r = run_process("estimate", path, "--json")
    assert r.returncode == 0, r.stderr
    top = json.loads(r.stdout)  # one document, for one file as for many (README, --json)
    assert (top["done"], top["failed"], top["exit_code"]) == (1, 0, 0)
    [doc] = top["results"]
    assert doc["model"]["width"] == 240
    # Lyu's Table 1 setting 2 is 6.7 EV deep at this frame's farthest corner: deeper than any
    # real lens, so not applied (issue 38); the fit is kept, with its centre
    assert doc["not_applied_rule"] == "beyond-real-lenses" and doc["model"]["quality"]["fallback"]
    c = np.array(doc["model"]["candidate"]["center"])
    assert np.linalg.norm(c - np.array(truth.center)) < 0.15 * np.linalg.norm(truth.center)


def test_estimate_takes_many_files(vignetted_tiff, tmp_path):
    path, _ = vignetted_tiff
    other = tmp_path / "copy.tif"
    other.write_bytes(path.read_bytes())
    r = run("estimate", path, tmp_path / "missing.tif", other, "--json")
    top = json.loads(r.stdout)  # the same one document as for one file, failures in their place
    docs = top["results"]
    assert [d["file"] for d in docs] == [str(path), str(tmp_path / "missing.tif"), str(other)]
    assert docs[1]["exit_code"] == 4 and docs[1]["type"] == "ImageReadError" and "model" not in docs[1]
    for d in (docs[0], docs[2]):
        for m in (d["model"], d["model"].get("candidate") or {"quality": {"seconds": 0}}):
            del m["quality"]["seconds"]
    assert docs[0]["model"] == docs[2]["model"]
    # some files failed: 1, as correct, check and hook say it (a file's own code only when all fail alike)
    assert (top["done"], top["failed"], top["exit_code"]) == (2, 1, 1)
    assert r.returncode == 1 and "missing.tif" in r.stderr
    r = run("estimate", tmp_path / "missing.tif", tmp_path / "gone.tif", "--json")
    assert r.returncode == 4 and json.loads(r.stdout)["exit_code"] == 4
    r = run("estimate", path, other)
    assert r.returncode == 0 and sum(ln.startswith("  fall-off") for ln in r.stdout.splitlines()) == 2


def test_correct_writes_outputs_atomically_and_keeps_input(lens_tiff, tmp_path):
    path, truth = lens_tiff
    before = path.read_bytes()
    out = tmp_path / "out"
    r = run_process("correct", path, "-o", out, "--picture", "--json")
    assert r.returncode == 0, r.stderr
    assert path.read_bytes() == before
    names = sorted(p.name for p in out.iterdir())
    # the one naming policy: the input's name; the image drops its extension when the format is its own
    assert names == ["frame.corrected.tif", "frame.tif.vignetting.png", "frame.tif.vigproc.json"]
    from vigproc.io.metadata import read_record

    rec = read_record(out / "frame.corrected.tif")
    assert rec is not None and rec["model"].width == 240
    corrected, _ = read_image(out / "frame.corrected.tif")
    src, _ = read_image(path)
    # the corners were brightened relative to the centre
    assert corrected[0, 0, 0] / corrected[80, 120, 0] > 2 * src[0, 0, 0] / src[80, 120, 0]


def test_hostile_names_stay_inside_output(tmp_path, vignetted_tiff):
    path, _ = vignetted_tiff
    weird = tmp_path / "a b 'q' \"dq\" ; $(rm -rf x) \u00e9\n.tif"
    weird.write_bytes(path.read_bytes())
    out = tmp_path / "out"
    r = run("correct", weird, "-o", out)  # names in stderr, as a process: test_file_names_cannot_forge_message_lines
    assert r.returncode == 0, r.stderr
    produced = list(out.iterdir())
    assert len(produced) == 2 and all(p.parent == out for p in produced)


@pytest.mark.parametrize("content,code,runner", [(b"", 4, run_process), (b"not an image at all", 4, run)])
def test_bad_files_exit_nonzero_without_traceback(tmp_path, content, code, runner):
    bad = tmp_path / "bad.jpg"
    bad.write_bytes(content)
    r = runner("estimate", bad)
    assert r.returncode == code
    assert "Traceback" not in r.stderr and "bad.jpg" in r.stderr


def test_missing_file_and_partial_failure(tmp_path, vignetted_tiff):
    path, _ = vignetted_tiff
    r = run("correct", path, tmp_path / "missing.tif", "-o", tmp_path / "o")
    assert r.returncode == 1
    assert "missing.tif" in r.stderr and "Traceback" not in r.stderr
    assert (tmp_path / "o" / "frame.corrected.tif").exists()


# A child that runs the program's entry (vigproc.frontends.cli.run) as the console script
# does, with marks of what the interpreter's exit does: an atexit callback, a finaliser
# run by the teardown, and optionally a thread that is not a daemon, still running.
_PROGRAM = """\
import atexit, os, sys, threading, time
from vigproc.frontends.cli import run

class Teardown:
    def __del__(self, write=os.write):  # the file descriptor: sys.stderr may be gone by then
        write(2, b"TEARDOWN\\n")

mark = Teardown()  # freed by the interpreter's teardown, not before
atexit.register(lambda: sys.stderr.write(f"ATEXIT {os.environ.get('OMP_WAIT_POLICY')}\\n"))
if "--thread" in sys.argv:  # a thread still running once main() has returned
    import vigproc.frontends.cli as cli
    sys.argv.remove("--thread")
    returned, main = threading.Event(), cli.main
    cli.main = lambda argv: (main(argv), returned.set())[0]
    threading.Thread(target=lambda: (returned.wait(), time.sleep(0.5), sys.stderr.write("THREAD DONE\\n"))).start()
sys.argv[0] = "vigproc"
sys.exit(run())
"""


def _program(*args, env=None) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-c", _PROGRAM, *map(str, args)], capture_output=True, text=True,
                          timeout=300, env={k: v for k, v in {**os.environ, **(env or {})}.items() if v is not None})


def test_correct_ends_its_process_without_the_teardown_and_loses_nothing(tmp_path, vignetted_tiff):
    path, _ = vignetted_tiff
    r = _program("correct", path, tmp_path / "missing.tif", "-o", tmp_path / "o", env={"OMP_WAIT_POLICY": None})
    assert r.returncode == 1, r.stderr  # one file failed: the exit code as main() returned it
    assert r.stdout.endswith(f" 1 failed; outputs in {tmp_path / 'o'}\n")  # flushed
    assert "missing.tif" in r.stderr
    assert "ATEXIT PASSIVE" in r.stderr  # atexit callbacks ran (the shared exiftool's close); OpenMP's workers slept
    assert "TEARDOWN" not in r.stderr  # ... and no teardown after them
    assert sorted(f.name for f in (tmp_path / "o").iterdir()) == ["frame.corrected.tif", "frame.tif.vigproc.json"]


def test_other_commands_and_running_threads_keep_the_interpreters_exit_and_a_set_policy(tmp_path, vignetted_tiff):
    r = _program("plugins", env={"OMP_WAIT_POLICY": None})  # not a quick-exit command
    assert r.returncode == 0 and "ATEXIT None" in r.stderr and "TEARDOWN" in r.stderr, r.stderr
    path, _ = vignetted_tiff
    r = _program("correct", path, "-o", tmp_path / "o", "--thread", env={"OMP_WAIT_POLICY": "ACTIVE"})  # the user's
    assert r.returncode == 0 and "THREAD DONE" in r.stderr and "TEARDOWN" in r.stderr, r.stderr  # exit waits
    assert "ATEXIT ACTIVE" in r.stderr
    assert (tmp_path / "o" / "frame.corrected.tif").exists()


def test_constant_image_is_a_clear_error(tmp_path):
    p = tmp_path / "flat.tif"
    write_image(p, np.full((64, 64, 3), 0.5, np.float32), bit_depth="float")
    r = run("estimate", p)
    assert r.returncode == 3 and "constant" in r.stderr


def test_demo_runs_on_bundled_samples(tmp_path):
    r = run_process("demo", "-o", tmp_path / "demo")
    assert r.returncode == 0, r.stderr
    # JPEG samples come back as JPEG, every one (the embedded default keeps an uncorrected
    # photo under its output name); the sidecar says why one was not corrected
    assert len(list((tmp_path / "demo").glob("*.vigproc.json"))) == 3
    corrected = list((tmp_path / "demo").glob("*.corrected.jpg"))
    assert len(corrected) == 3
    for side in (tmp_path / "demo").glob("*.vigproc.json"):
        rec = json.loads(side.read_text())
        # kodim05's fit has corners 0.29 EV brighter than its centre: refused (issue 38)
        assert rec["applied"] or rec["not_applied"].startswith("weak evidence") or \
            rec["not_applied_rule"] == "brighter-corners"
    assert len(list((tmp_path / "demo").glob("*.vignetting.png"))) == 3


def test_bench_io_runs(tmp_path):
    r = run_process("bench", "io", "--width", "64", "--height", "48", "--repeat", "1")
    assert r.returncode == 0, r.stderr
    for label in ("TIFF 16-bit", "TIFF float", "EXR half", "EXR float", "PNG 16-bit"):
        assert label in r.stdout


def test_usage_errors_exit_2_without_traceback():
    r = run_process("estimate")
    assert r.returncode == 2 and "Traceback" not in r.stderr


def test_same_stem_inputs_get_distinct_outputs(tmp_path, vignetted_tiff):
    path, _ = vignetted_tiff
    a, b = tmp_path / "x" / "frame.tif", tmp_path / "y" / "frame.tif"
    for p in (a, b):
        p.parent.mkdir()
        p.write_bytes(path.read_bytes())
    out = tmp_path / "out"
    r = run("correct", a, b, "-o", out)
    assert r.returncode == 0, r.stderr
    assert sorted(p.name for p in out.glob("*.tif")) == ["frame-2.corrected.tif", "frame.corrected.tif"]


def test_output_stems_are_unique_deterministic_and_safe():
    from pathlib import Path

    from vigproc.pipeline.processor import output_stems, safe_output

    names = ["x/a.tif", "y/a.png", "a-2.tif", "A.tif", "a-3.jpg", "new\nline.tif", "-rf.tif", "..tif", ".h.tif",
             "%2Drf.tif", "a b é 100%.tif", "tab\there.tif", "b.tif", "b.png", "b-2.png"]
    files = [Path(n) for n in names]
    stems = output_stems(files)
    assert stems == ["a.tif", "a.png", "a-2.tif", "A-3.tif", "a-3.jpg", "new%0Aline.tif", "%2Drf.tif", "%2E.tif",
                     "%2Eh.tif", "%252Drf.tif", "a b é 100%25.tif", "tab%09here.tif", "b.tif", "b.png", "b-2.png"]
    assert stems == output_stems(files)  # the same inputs in the same order: the same names
    assert len({s.casefold() for s in stems}) == len(stems)  # distinct, also on case-insensitive filesystems
    for s in stems:  # each stem is its file name: nothing left for safe_output to fold together
        assert safe_output(Path("/o"), s, ".vigproc.json").name == s + ".vigproc.json"
        assert not s.startswith(("-", ".")) and not any(ord(c) < 32 for c in s)


def test_long_names_are_shortened_distinctly(tmp_path, vignetted_tiff):
    from pathlib import Path

    from vigproc.pipeline.processor import MAX_STEM_BYTES, output_stems

    long_a, long_b = "é" * 150 + "a", "é" * 150 + "b"  # 301 bytes each, same 180-byte prefix
    stems = output_stems([Path(long_a + ".tif"), Path(long_b + ".tif"), Path("short.tif")])
    assert stems[2] == "short.tif"
    assert all(len(s.encode()) <= MAX_STEM_BYTES for s in stems) and stems[0] != stems[1]
    # a 250-byte name still gets its outputs (NAME_MAX is 255 bytes with the suffixes)
    src = tmp_path / ("x" * 246 + ".tif")
    src.write_bytes(vignetted_tiff[0].read_bytes())
    r = run("correct", src, "-o", tmp_path / "out", "--profile", "estimate")
    assert r.returncode == 0, r.stderr
    assert len(list((tmp_path / "out").glob("*.corrected.tif"))) == 1


def test_correct_never_overwrites_an_input_and_names_never_collide(tmp_path, vignetted_tiff):
    path, _ = vignetted_tiff
    o = tmp_path / "o"
    o.mkdir()
    for n in ("a.corrected.tif", "a.tif", "b.tif", "b-2.tif"):
        (o / n).write_bytes(path.read_bytes())
    (o / "b.png").write_bytes(b"not an image")  # reserves b-? without an output
    victim = (o / "a.corrected.tif").read_bytes()
    r = run("correct", o / "a.corrected.tif", o / "a.tif", o / "b.tif", o / "b.png", o / "b-2.tif", "-o", o)
    assert r.returncode == 1
    assert (o / "a.corrected.tif").read_bytes() == victim  # a.tif's output would have replaced it
    err = r.stderr.splitlines()
    assert len(err) == 2 and "a.tif" in err[0] and "input of this run" in err[0], r.stderr
    assert not (o / "a.tif.vigproc.json").exists()  # a refused frame writes nothing
    made = {json.loads(p.read_text())["file"]: p.name for p in o.glob("*.vigproc.json")}
    assert made == {str(o / "a.corrected.tif"): "a.corrected.tif.vigproc.json",
                    str(o / "b.tif"): "b.tif.vigproc.json", str(o / "b-2.tif"): "b-2.tif.vigproc.json"}


def test_file_names_cannot_forge_message_lines(tmp_path, vignetted_tiff):
    path, _ = vignetted_tiff
    good = tmp_path / "ok\nvigproc: 0 corrected.tif"
    good.write_bytes(path.read_bytes())
    bad = tmp_path / "x\nvigproc: FAKE\r\u2028.tif"
    bad.write_bytes(b"not an image")
    r = run_process("correct", good, bad, "-o", tmp_path / "out")
    assert r.returncode == 1
    assert len(r.stderr.splitlines()) == 1 and "FAKE" in r.stderr, r.stderr
    assert len(r.stdout.splitlines()) == 2, r.stdout  # the file's line and the summary
    r = run_process("estimate", bad)
    assert r.returncode == 4 and len(r.stderr.splitlines()) == 1 and "x\\nvigproc: FAKE" in r.stderr


def test_estimate_raw_uses_half_size_and_reports_full_frame(tmp_path):
    from dngfixture import make_dng

    from vigproc.core.model import VignettingModel

    h, w = 256, 384
    truth = VignettingModel(w, h, center=(12.0, -8.0), p=(1 / 210.0**2, 0, 1 / 210.0**2),
                            alpha=(0.02, 0.01, 0, 0, 0, 0, 0))
    dng = tmp_path / "shot one.dng"
    make_dng(dng, width=w, height=h, field=truth.field(), scene=textured(h, w, seed=3, contrast=0.05),
             exif={"Make": "Canon", "Model": "Canon EOS 5D", "LensModel": "EF24-105mm f/4L IS USM",
                   "FocalLength": 24, "FNumber": 4})
    r = run("estimate", dng, "--json")
    assert r.returncode == 0, r.stderr
    [doc] = json.loads(r.stdout)["results"]
    m = VignettingModel.from_dict(doc["model"])
    assert (m.width, m.height) == (w, h)
    err = np.log2(m.field() / truth.field())
    assert np.sqrt(np.mean(err**2)) < 0.1
    assert doc["lens"]["lens_id"].startswith("canon|canon eos 5d|")
    r = run("estimate", dng)  # the text names the frame the model is for, not the half-size development
    assert r.returncode == 0 and f": {w}x{h} raw (linear, estimated on its {w // 2}x{h // 2} half-size" in r.stdout, r.stdout


@pytest.mark.parametrize("fmt,suffix", [("tiff16", ".tif"), ("exr-half", ".exr"), ("exr-float", ".exr")])
def test_output_formats_carry_the_record(tmp_path, vignetted_tiff, fmt, suffix):
    from vigproc.io.metadata import read_record

    path, _ = vignetted_tiff
    out = tmp_path / "out"
    r = run("correct", path, "-o", out, "--output-format", fmt)
    assert r.returncode == 0, r.stderr
    dst = out / ("frame.corrected.tif" if suffix == ".tif" else f"frame.tif.corrected{suffix}")
    img, info = read_image(dst)
    assert img.shape[:2] == (160, 240) and info.transfer == "linear"
    assert read_record(dst)["model"].width == 240


def test_profile_store_flow(tmp_path, monkeypatch):
    """learn pools frames per lens; a trusted stored profile is applied with no estimation."""
    from dngfixture import make_dng

    from vigproc.stores.lensfun import diverse_lenses, pa_field
    from vigproc.core.model import VignettingModel

    monkeypatch.setenv("VIGPROC_PROFILE_DB", str(tmp_path / "store.sqlite"))
    lens, pa = diverse_lenses(1)[0]
    h, w = 256, 384
    # the frames claim the lens setting whose lensfun calibration they carry
    exif = {"Make": "Canon", "Model": "Canon EOS 5D", "LensModel": "EF24-105mm f/4L IS USM",
            "FocalLength": pa.focal, "FNumber": pa.aperture}
    dngs = []
    for i in range(2):
        p = tmp_path / f"f{i}.dng"
        make_dng(p, width=w, height=h, field=pa_field((h, w), pa.k1, pa.k2, pa.k3),
                 scene=photo_like(h, w, seed=10 + i), exif=exif)
        dngs.append(p)
    r = run_process("profile", "learn", *dngs)
    assert r.returncode == 0, r.stderr
    r = run("profile", "learn", dngs[0])  # a frame learned again (a rerun) is not pooled twice
    assert r.returncode == 0, r.stderr
    r = run("profile", "list")
    assert "frames=2" in r.stdout and "learning" in r.stdout
    lens_id = json.loads(run("estimate", dngs[0], "--json").stdout)["results"][0]["lens"]["lens_id"]
    r = run("profile", "import-lensfun", lens.maker, lens.model, "--focal", pa.focal, "--aperture", pa.aperture,
            "--width", w, "--height", h, "--lens-id", lens_id, "--crop-factor", lens.crop_factor)
    assert r.returncode == 0, r.stderr
    # the learned (untrusted) profile and the imported one share the key: the import replaced it
    r = run_process("correct", dngs[0], "-o", tmp_path / "out", "--profile", "auto", "--json")
    assert r.returncode == 0, r.stderr
    rec = json.loads(r.stdout)["results"][0]
    assert rec["source"] == "stored-profile"
    m = VignettingModel.from_dict(rec["model"])
    err = np.log2(m.field() / pa_field((h, w), pa.k1, pa.k2, pa.k3))
    assert np.sqrt(np.mean(err**2)) < 0.01


def test_single_output_never_replaces_an_input(tmp_path, vignetted_tiff):
    """A report or classifier named like one of the command's inputs is refused before
    any work (exit 5), and the input keeps its bytes."""
    path, _ = vignetted_tiff
    before = path.read_bytes()
    r = run_process("check", path, "--report", path)
    assert r.returncode == 5 and "it is an input of this run" in r.stderr, r.stderr
    for c in ("A", "B"):
        (tmp_path / "tr" / c).mkdir(parents=True)
        (tmp_path / "tr" / c / "1.tif").write_bytes(before)
    victim = tmp_path / "tr" / "A" / "1.tif"
    r = run_process("forensics", "train", tmp_path / "tr", "-o", victim)
    assert r.returncode == 5 and "it is an input of this run" in r.stderr, r.stderr
    assert path.read_bytes() == before and victim.read_bytes() == before


@pytest.mark.parametrize("args", [
    ("correct", "--strength", "nan", "-o", "o", "x.tif"),
    ("correct", "--strength", "-1", "-o", "o", "x.tif"),
    ("check", "--alpha", "2", "x.tif"),
    ("forensics", "train", "d", "-o", "m.json", "--shrinkage", "5"),
    ("forensics", "evaluate", "m.json", "d", "--frames", "0"),
    ("profile", "import-lensfun", "a", "b", "--focal", "nan", "--aperture", "2"),
    ("profile", "show", "0", "--width", "0", "--height", "0"),
    ("watch", "in", "-o", "o", "--workers", "0"),
    ("batch", "in", "--mode", "correct", "-o", "o", "--workers", "0"),
    ("bench", "profile", "--images", "in", "--counts", "0"),
])
def test_bad_option_values_are_usage_errors(tmp_path, args):
    r = run(*args, cwd=tmp_path)
    assert r.returncode == 2, (args, r.returncode, r.stderr)
    assert "Traceback" not in r.stderr and "is not within" in r.stderr
    assert not (tmp_path / "o").exists()


def test_unusable_output_folder_is_a_write_error(tmp_path, vignetted_tiff):
    path, _ = vignetted_tiff
    afile = tmp_path / "afile"
    afile.write_text("x")
    for out in (afile, afile / "sub"):
        r = run("correct", path, "-o", out)
        assert r.returncode == 5 and "cannot create output folder" in r.stderr, r.stderr


def test_values_beyond_the_output_format_fail_the_frame(tmp_path, lens_tiff):
    """An HDR frame whose corrected values exceed half-float range is not written as Inf."""
    path, _ = lens_tiff
    img, _ = read_image(path)
    img[-1, -1] = img.max()  # a highlight in the corner the fall-off darkens most
    hdr = tmp_path / "hdr.tif"
    write_image(hdr, (img * (60000.0 / img.max())).astype(np.float32), bit_depth="float")  # fits in half
    out = tmp_path / "out"
    r = run("correct", hdr, "-o", out, "--output-format", "exr-half", "--profile", "estimate")
    # the only file failed: its error's code (5, output not writable), as estimate and hook say it
    assert r.returncode == 5 and "beyond the 6.55e+04 that exr-half holds" in r.stderr, r.stderr
    assert not out.exists()  # nothing written (the folder it made for it is gone too)
    r = run("correct", hdr, "-o", out, "--output-format", "exr-float", "--profile", "estimate")
    assert r.returncode == 0, r.stderr
    corrected, _ = read_image(out / "hdr.tif.corrected.exr")  # the format changed: the input's extension stays
    assert np.all(np.isfinite(corrected))


def test_large_negative_values_are_bad_input(tmp_path, vignetted_tiff):
    path, _ = vignetted_tiff
    img, _ = read_image(path)
    neg = tmp_path / "neg.tif"
    bad = img.copy()
    bad[:, : img.shape[1] // 2] = -0.5
    write_image(neg, bad, bit_depth="float")
    r = run("estimate", neg)
    assert r.returncode == 3 and "not linear intensities" in r.stderr and "neg.tif" in r.stderr, r.stderr
    r = run("correct", neg, "-o", tmp_path / "out", "--profile", "estimate")
    assert r.returncode == 3 and "not linear intensities" in r.stderr, r.stderr  # as estimate says it
    # noise around black (slightly negative values) is fine
    noisy = tmp_path / "noisy.tif"
    ok = img.copy()
    ok[0, :10] = -0.01 * img.max()
    write_image(noisy, ok, bit_depth="float")
    assert run("estimate", noisy).returncode == 0


def test_absurdly_nested_json_is_a_clear_error(tmp_path):
    deep = tmp_path / "deep.json"
    deep.write_text("[" * 100_000 + "]" * 100_000)
    r = run("profile", "--profile-db", tmp_path / "p.sqlite", "import", deep)
    assert r.returncode == 8 and "not valid profile JSON" in r.stderr, r.stderr
    r = run("forensics", "evaluate", deep, tmp_path)
    assert r.returncode == 11 and "not valid JSON" in r.stderr, r.stderr


def test_tiff16_says_when_it_clips(tmp_path, vignetted_tiff):
    """Values above the white point are clipped in a 16-bit output by design, and said."""
    path, _ = vignetted_tiff
    img, _ = read_image(path)
    bright = tmp_path / "bright.tif"
    write_image(bright, (img * (3.0 / img.max())).astype(np.float32), bit_depth="float")
    r = run("correct", bright, "-o", tmp_path / "out", "--output-format", "tiff16", "--profile", "estimate")
    assert r.returncode == 0 and "above the white point and tiff16 clips them" in r.stderr, r.stderr
    r = run("correct", path, "-o", tmp_path / "out2", "--output-format", "tiff16", "--profile", "estimate",
            "--strength", "0")
    assert r.returncode == 0 and "white point" not in r.stderr, r.stderr


def test_correct_reports_the_fall_off_its_strength_removed(tmp_path, lens_tiff):
    path, _ = lens_tiff
    full = run("correct", path, "-o", tmp_path / "full", "--profile", "estimate")
    half = run("correct", path, "-o", tmp_path / "half", "--profile", "estimate", "--strength", "0.5")
    assert full.returncode == 0 and half.returncode == 0, half.stderr
    ev = [float(re.search(r"([0-9.]+) EV fall-off removed", r.stdout).group(1)) for r in (full, half)]
    assert ev[0] > 0.1 and abs(ev[1] - ev[0] / 2) <= 0.01, ev
    side = json.loads(next((tmp_path / "half").glob("*.json")).read_text())
    assert side["strength"] == 0.5


def test_correct_on_a_symlink_loop_is_a_read_error(tmp_path):
    (tmp_path / "loop_a.jpg").symlink_to("loop_b.jpg")
    (tmp_path / "loop_b.jpg").symlink_to("loop_a.jpg")
    r = run("correct", "-o", tmp_path / "out", "--", tmp_path / "loop_a.jpg")
    assert r.returncode == 4, r.stderr  # an unreadable file (its only file), not an internal error (70)
    assert "Symlink loop" in r.stderr and "internal error" not in r.stderr


def test_check_store_options_exclude_each_other(tmp_path):
    r = run("check", "x.jpg", "--profile-db", tmp_path / "p.sqlite", "--no-store")
    assert r.returncode == 2 and "not allowed with" in r.stderr and not (tmp_path / "p.sqlite").exists()


def test_help_and_usage_errors_import_no_numeric_stack():
    # `vigproc --help` and a usage error must stay fast (a host pays start-up per call):
    # they must not import numpy, scipy or numba (0.55 s of start-up before)
    code = (
        "import sys\n"
        "from vigproc.frontends.cli import main\n"
        "for argv in (['--help'], ['correct', 'x.jpg', '--strength', 'x'], ['bench', 'clean', '--help']):\n"
        "    try:\n"
        "        main(argv)\n"
        "    except SystemExit:\n"
        "        pass\n"
        "heavy = sorted(m for m in ('numpy', 'scipy', 'numba') if m in sys.modules)\n"
        "print('HEAVY', heavy, file=sys.stderr)\n"
    )
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert "HEAVY []" in r.stderr, r.stderr[-2000:]


def _fresh_python_says_true(code: str) -> None:
    """Run ``code`` in a new interpreter (a clean import state); it must print True."""
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert r.returncode == 0 and r.stdout.strip() == "True", r.stderr[-2000:]


def test_public_names_are_imported_on_first_use():
    _fresh_python_says_true(
        "import sys, vigproc\n"
        "assert 'numba' not in sys.modules\n"
        "from vigproc import estimate, VignettingModel, Pipeline, METHODS\n"
        "assert callable(estimate) and 'default' in METHODS and 'numba' in sys.modules\n"
        "print(sorted(vigproc.__all__) == sorted(n for n in vigproc.__all__ if hasattr(vigproc, n)))\n")


def test_estimate_and_correct_stay_functions_when_their_modules_load_first():
    _fresh_python_says_true(
        "import vigproc.core.estimate, vigproc.core.correct, vigproc.pipeline.processor\n"
        "import vigproc\n"
        "print(callable(vigproc.estimate) and callable(vigproc.correct)"
        " and vigproc.estimate.__module__ == 'vigproc.core.estimate')\n")


def test_every_option_and_argument_has_help_text():
    import argparse

    from vigproc.frontends.cli import build_parser

    missing = []

    def walk(parser, path):
        for action in parser._actions:
            if isinstance(action, argparse._SubParsersAction):
                for name, sub in action.choices.items():
                    walk(sub, [*path, name])
            elif not isinstance(action, argparse._HelpAction) and not action.help:
                missing.append((" ".join(path), action.option_strings or action.dest))

    from benchmarks.cli import build_parser as bench_parser

    walk(build_parser(), ["vigproc"])
    walk(bench_parser(), ["vigproc", "bench"])
    assert missing == []


def test_estimate_reports_an_unknown_method_once_and_check_counts_only_failures(tmp_path, vignetted_tiff):
    path, _ = vignetted_tiff
    r = run("estimate", path, path, "--method", "no-such-method")
    assert r.returncode == 2 and r.stderr.count("unknown method") == 1 and str(path) not in r.stderr
    r = run("check", tmp_path / "missing.jpg", "--profile-db", tmp_path / "p.sqlite")
    # its only file unreadable: 4, as estimate says it
    assert r.returncode == 4 and r.stdout.strip().splitlines()[-1] == "1 failed", r.stdout
    r = run("check", tmp_path / "missing.jpg", path, "--profile-db", tmp_path / "p.sqlite")
    assert r.returncode == 1, r.stdout  # one failed, one checked: "some files failed"


def test_profile_show_uses_the_profiles_own_frame_and_prints_a_summary(tmp_path):
    db = tmp_path / "p.sqlite"
    r = run("profile", "--profile-db", db, "import-lensfun", "Sigma", "105mm F1.4 DG HSM | Art 018",
            "--focal", "105", "--aperture", "1.4", "--width", "4000", "--height", "3000")
    assert r.returncode == 0, r.stderr
    r = run("profile", "--profile-db", db, "show", "0")  # a 4:3 profile: no --width/--height needed
    assert r.returncode == 0, r.stderr
    assert "frame       6000x4500" in r.stdout and "EV RMS" in r.stdout and "{" not in r.stdout
    r = run("profile", "--profile-db", db, "show", "0", "--json", "--height", "300")
    doc = json.loads(r.stdout)  # JSON only on stdout: the profile's record and its model
    assert (doc["width"], doc["height"]) == (400, 300) == (doc["model"]["width"], doc["model"]["height"])
    assert doc["frames"] == 0 and doc["trusted"] is True and doc["provenance"].startswith("lensfun"), doc  # imported: no frames
    assert doc["key"].startswith(doc["lens_id"]) and doc["aperture_bin"] == "N=1.4"
    # by the lens id that estimate and check print, while the lens has one profile
    lens_id = run("profile", "--profile-db", db, "list").stdout.split("] ", 1)[1].split(" @ ")[0]
    r = run("profile", "--profile-db", db, "show", lens_id)
    assert r.returncode == 0 and "frame       6000x4500" in r.stdout, r.stderr
    r = run("profile", "--profile-db", db, "import-lensfun", "Sigma", "105mm F1.4 DG HSM | Art 018",
            "--focal", "105", "--aperture", "2.8", "--width", "4000", "--height", "3000")
    r = run("profile", "--profile-db", db, "show", lens_id)
    assert r.returncode == 8 and "has 2 profiles" in r.stderr, r.stderr


def test_lines_printed_during_a_progress_bar_stay_whole(monkeypatch):
    """In a terminal, results and log lines go above the progress bar, not onto its line."""
    import io
    import logging

    from vigproc.frontends.commands._progress import _progress

    class Tty(io.StringIO):
        def isatty(self):
            return True

    err, out = Tty(), Tty()
    monkeypatch.setattr(sys, "stderr", err)
    monkeypatch.setattr(sys, "stdout", out)
    log = logging.getLogger("vigproc.test_progress")
    for i in _progress([1, 2, 3], "testing"):
        print(f"result {i}")
        log.warning("warned %d", i)
    assert [ln for ln in out.getvalue().splitlines() if ln.startswith("result")] == ["result 1", "result 2",
                                                                                       "result 3"]
    # every warning has a line of its own: never on the bar's line (the bar redraws after '\r')
    segments = [seg for ln in err.getvalue().splitlines() for seg in ln.split("\r")]
    for i in (1, 2, 3):
        assert any(seg.strip() == f"warned {i}" for seg in segments), segments
    assert not any("warned" in seg and "testing" in seg for seg in segments), segments


def test_correct_leaves_no_empty_folder_when_every_file_fails(tmp_path):
    out = tmp_path / "new-out"
    r = run("correct", tmp_path / "missing.jpg", "-o", out)
    assert r.returncode == 4 and "nothing written" in r.stdout
    assert not out.exists()  # it made the folder to check it is writable; nothing went in
    (tmp_path / "kept").mkdir()
    r = run("correct", tmp_path / "missing.jpg", "-o", tmp_path / "kept")
    assert (tmp_path / "kept").is_dir()  # a folder that was there stays


def test_json_is_one_document_for_estimate_correct_and_check(tmp_path, vignetted_tiff):
    """A new user got an indented object from one file and JSON lines from several, and
    another shape from correct and check: now one document each, with the same keys."""
    path, _ = vignetted_tiff
    missing = tmp_path / "missing.tif"
    for cmd in (["estimate"], ["correct", "-o", tmp_path / "out"], ["check", "--no-store"]):
        for files in ([path], [path, missing]):
            r = run(*cmd, *files, "--json")
            doc = json.loads(r.stdout)  # the whole of stdout is one JSON document
            assert {"results", "done", "failed", "exit_code"} <= set(doc), (cmd, doc.keys())
            assert [x["file"] for x in doc["results"]] == [str(f) for f in files]
            assert doc["exit_code"] == r.returncode
            if len(files) == 2:
                assert doc["failed"] == 1 and doc["results"][1]["exit_code"] == 4
                assert r.returncode == 1  # some files failed (check: none inconsistent)


def test_a_rejected_fit_is_said_with_the_figure_its_json_holds(tmp_path):
    """estimate printed 'fall-off 0.000 EV RMS' for a frame whose fit was rejected while
    its JSON's field_ev_rms (and the demo's picture) said 0.085 EV: one figure, one name.

    The frame: a weak fall-off (0.04 EV) under strong pixel noise, whose fit the
    estimator does not trust (SNR about 0.4)."""
    rng = np.random.default_rng(4)
    img = coloured_scene(160, 240, seed=4)
    lens = VignettingModel(240, 160, p=(0.04 / 75**2, 0.0, 0.04 / 75**2))
    frame = img * lens.field()[..., None] * np.exp(0.5 * rng.standard_normal(img.shape))
    sample = tmp_path / "weak.tif"
    write_image(sample, frame.astype(np.float32), bit_depth="float")
    [doc] = json.loads(run("estimate", sample, "--json").stdout)["results"]
    q = doc["model"]["quality"]
    assert q["fallback"] and q["field_ev_rms"] > 0.01
    text = run("estimate", sample).stdout
    assert "NOT applied" in text and "0.000 EV" not in text
    assert f"the rejected fit: {q['field_ev_rms']:.3f} EV RMS" in text


def test_correct_prints_outputs_under_the_folder_as_given(tmp_path, vignetted_tiff):
    """'-o out' printed '-> /abs/path/out/NAME' beside 'outputs in out' (the README's first
    example shows the line)."""
    path, _ = vignetted_tiff
    r = run("correct", path, "-o", "out", "--profile", "estimate", cwd=tmp_path)
    assert r.returncode == 0, r.stderr
    assert f"{path} -> out/frame.corrected.tif  [" in r.stdout, r.stdout
    assert r.stdout.rstrip().endswith("outputs in out")


def test_an_unknown_option_is_reported_by_its_command():
    """'vigproc estimate --strength 3 x' printed the top-level usage and 'vigproc: error':
    the command's own usage says which options it takes."""
    r = run("estimate", "--strength", "3", "x.jpg")
    assert r.returncode == 2
    assert "usage: vigproc estimate" in r.stderr and "vigproc estimate: error: unrecognized arguments: --strength" \
        in r.stderr, r.stderr
    r = run("profile", "show", "0", "--bogus")
    assert r.returncode == 2 and "vigproc profile show: error: unrecognized arguments: --bogus" in r.stderr


def test_output_folder_paths_are_taken_as_meant(tmp_path, vignetted_tiff):
    """An empty -o is refused (it wrote into the current folder); a path through '..'
    makes only the folder it names (mkdir made the folders it passed through too); an
    output format the input cannot have is a write error of that file (exit 5), as every
    other failure of the only file is its own code."""
    path, _ = vignetted_tiff
    work = tmp_path / "w"
    work.mkdir()
    r = run("correct", path, "-o", "", cwd=work)
    assert r.returncode == 5 and "empty path" in r.stderr, r.stderr
    r = run("correct", path, "-o", "x/../y/../../s/dots", cwd=work)
    assert r.returncode == 0, r.stderr
    assert sorted(p.name for p in work.iterdir()) == [] and (tmp_path / "s" / "dots").is_dir()
    r = run("correct", path, "-o", tmp_path / "d", "--output-format", "dng")
    assert r.returncode == 5 and "needs a DNG input" in r.stderr, r.stderr


def test_correct_given_a_folder_says_how_a_folder_is_given(tmp_path):
    """The README's "Correct a folder of photos": `vigproc correct FOLDER -o OUT` said only
    "is a directory" and no more; it now names the two ways (its files, or `vigproc batch`)."""
    (tmp_path / "photos").mkdir()
    r = run("correct", str(tmp_path / "photos"), "-o", str(tmp_path / "out"))
    assert r.returncode == 4 and "Traceback" not in r.stderr
    assert "is a directory (give its photos" in r.stderr and "photos/*" in r.stderr and "vigproc batch" in r.stderr, r.stderr
    assert not (tmp_path / "out").exists()
