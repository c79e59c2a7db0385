"""``vigproc hook`` (JSON answer, stable exit codes, requests, hostile names) and ``vigproc plugins``."""

from __future__ import annotations

import hashlib
import io
import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from vigproc.core.model import VignettingModel
from vigproc.frontends.cli import main
from vigproc.io.images import read_image, write_image

from conftest import run_cli as in_process, textured
from test_api import ESTIMATORS, PLUGIN_CODE, install_plugin

VIGPROC = [sys.executable, "-m", "vigproc.frontends.cli"]
pytestmark = pytest.mark.skipif(shutil.which("exiftool") is None, reason="exiftool program not installed")


def sha(p: Path) -> str:
    return hashlib.sha256(p.read_bytes()).hexdigest()


@pytest.fixture(autouse=True)
def private_store(tmp_path, monkeypatch):
    monkeypatch.setenv("VIGPROC_PROFILE_DB", str(tmp_path / "profiles.sqlite"))


#: The vignetting of :func:`frame`.
FRAME_MODEL = VignettingModel(240, 160, p=(1 / 70**2, 0.0, 1 / 70**2))


@pytest.fixture(scope="module")
def _frame_bytes(tmp_path_factory) -> bytes:
    """The frame of :func:`frame`, made once (an exiftool run costs about 0.3 CPU s)."""
    img = textured(160, 240, seed=1, contrast=0.05) * FRAME_MODEL.field()
    path = tmp_path_factory.mktemp("frame") / "frame.tif"
    write_image(path, np.repeat(img[..., None], 3, axis=2).astype(np.float32), bit_depth="float")
    subprocess.run(["exiftool", "-q", "-overwrite_original", "-Make=Canon", "-Model=Canon EOS 5D",
                    "-LensModel=EF50mm f/1.8 II", "-FocalLength=50", "-FNumber=2.8", str(path)], check=True)
    return path.read_bytes()


@pytest.fixture
def frame(tmp_path, _frame_bytes) -> Path:
    """A vignetted linear float TIFF with camera and lens EXIF: 2.1 EV at the corners, within
    what real 50 mm f/2.8 lenses show (Table 1 setting 2, 6.7 EV deep, is beyond them: issue 38).
    Each test's own copy."""
    path = tmp_path / "in" / "frame.tif"
    path.parent.mkdir()
    path.write_bytes(_frame_bytes)
    return path


def run_cli(*args, stdin: bytes | None = None, env: dict | None = None):
    r = subprocess.run([*VIGPROC, *map(os.fsdecode, args)], input=stdin, capture_output=True, timeout=300,
                       env={**os.environ, **(env or {})})
    return r.returncode, r.stdout, r.stderr.decode("utf-8", "replace")


def hook(capsys, monkeypatch, *args, stdin: bytes | None = None):
    """``vigproc hook`` in this process: (exit code, answer)."""
    if stdin is not None:
        monkeypatch.setattr(sys, "stdin", io.TextIOWrapper(io.BytesIO(stdin)))
    capsys.readouterr()
    code = main(["hook", *map(os.fsdecode, args)])
    out, err = capsys.readouterr()
    assert "Traceback" not in err
    answer = json.loads(out)  # stdout is exactly one JSON document
    assert answer["exit_code"] == code
    return code, answer


# ------------------------------------------------------------------ end to end
def test_correct_answers_json_and_writes_outputs(frame, tmp_path):
    before = sha(frame)
    out = tmp_path / "out"
    code, stdout, stderr = run_cli("hook", "-o", out, "--", frame)
    assert code == 0, stderr
    answer = json.loads(stdout)
    assert answer["protocol"] == 1 and answer["ok"] == 1 and answer["failed"] == 0
    r = answer["results"][0]
    assert r["status"] == "ok" and r["applied"] and r["source"] == "estimate"
    assert r["lens"]["lens_id"] == "canon|canon eos 5d|ef50mm f/1.8 ii"
    assert r["falloff_ev"] > 0.6 and "EV fall-off removed" in r["summary"]  # 0.97 EV RMS in truth
    assert sorted(p.name for p in out.iterdir()) == ["frame.corrected.tif", "frame.tif.vigproc.json"]
    assert r["output"] == str(out / "frame.corrected.tif") and r["sidecar"] == str(out / "frame.tif.vigproc.json")
    assert sha(frame) == before
    corrected, _ = read_image(out / "frame.corrected.tif")
    src, _ = read_image(frame)
    assert corrected[-3, -3, 0] / corrected[80, 120, 0] > 2.5 * src[-3, -3, 0] / src[80, 120, 0]  # 4.2 in truth


def test_request_on_stdin_with_host_lens_and_exact_output(frame, tmp_path, capsys, monkeypatch):
    target = tmp_path / "dk" / "BatchTool-1.digikamtempfile.tif"
    target.parent.mkdir()
    req = {"mode": "correct", "output_format": "tiff16", "files": [
        {"path": str(frame), "output": str(target),
         "lens": {"make": "Nikon", "model": "Nikon D700", "lens": "AF-S 24-70mm f/2.8G", "focal_mm": 35,
                  "fnumber": 4}},
        {"path": str(frame), "output": str(tmp_path / "dk" / "x.jpg")},  # wrong suffix for TIFF
        {"path": str(frame), "output": str(frame)},  # never overwrite the input
    ]}
    code, answer = hook(capsys, monkeypatch, "--request", "-", stdin=json.dumps(req).encode())
    assert code == 1 and answer["ok"] == 1, answer
    ok, bad_suffix, onto_input = answer["results"]
    assert ok["status"] == "ok" and ok["output"] == str(target)
    assert ok["lens"]["lens_id"] == "nikon|nikon d700|af-s 24-70mm f/2.8g"  # the host's lens, not the file's
    assert bad_suffix["exit_code"] == 2 and bad_suffix["type"] == "UsageError" and ".tif" in bad_suffix["error"]
    assert onto_input["exit_code"] == 5
    assert os.listdir(target.parent) == [target.name]  # no sidecar, no temporary folder left
    img, info = read_image(target)
    assert info.bit_depth == "uint16" and img.shape == (160, 240, 3)


def test_hostile_file_names(frame, tmp_path, capsys, monkeypatch):
    names = ["a b 'q' \"dq\" ; $(touch PWNED) `touch PWNED`\n\\ é.tif", "-rf.tif", "..tif"]
    src = tmp_path / "hostile"
    src.mkdir()
    paths = [src / n for n in names]
    raw = os.path.join(os.fsencode(src), b"caf\xe9 latin-1.tif")  # not UTF-8
    for p in [*paths, raw]:
        shutil.copyfile(frame, p)
    out = tmp_path / "out"
    code, answer = hook(capsys, monkeypatch, "--mode", "correct", "-o", out, "--", *paths, raw)
    assert code == 0 and answer["ok"] == 4
    assert [r["file"] for r in answer["results"]] == [*map(str, paths), os.fsdecode(raw)]
    for r in answer["results"]:
        assert Path(r["output"]).parent == out and Path(r["sidecar"]).parent == out
    # control characters and a leading '-' or '.' percent-encoded, as every front end names outputs
    assert [Path(r["output"]).name for r in answer["results"][:3]] == [
        "a b 'q' \"dq\" ; $(touch PWNED) `touch PWNED`%0A\\ é.corrected.tif", "%2Drf.corrected.tif",
        "%2E.corrected.tif"]
    # a name that is not UTF-8 is processed too, its bytes percent-encoded in the output's name
    assert Path(answer["results"][3]["output"]).name == "caf%E9 latin-1.corrected.tif"
    assert len(os.listdir(out)) == 8
    assert not list(tmp_path.rglob("PWNED")) and not Path("PWNED").exists()


def test_output_names_never_collide(frame, tmp_path, capsys, monkeypatch):
    src = tmp_path / "src"
    src.mkdir()
    names = ["a.tif", "a.png", "a-2.tif"]
    for n in names:
        shutil.copyfile(frame, src / n)
    for _ in range(2):  # a rerun writes the same names
        out = tmp_path / "out"
        code, answer = hook(capsys, monkeypatch, "--mode", "estimate", "-o", out, "--", *[src / n for n in names])
        assert code == 0
        assert [Path(r["sidecar"]).name for r in answer["results"]] == [
            "a.tif.vigproc.json", "a.png.vigproc.json", "a-2.tif.vigproc.json"]
        for r in answer["results"]:  # each sidecar is its own input's, none overwritten by another
            assert json.loads(Path(r["sidecar"]).read_text())["file"] == r["file"]


def test_outputs_never_replace_an_input_of_the_call(frame, tmp_path, capsys, monkeypatch):
    o = tmp_path / "o"
    o.mkdir()
    first, second = o / "a.corrected.tif", o / "a.tif"
    shutil.copyfile(frame, first)
    shutil.copyfile(frame, second)
    os.utime(first, (1, 1))  # a different file of the same content
    before = sha(first)
    code, answer = hook(capsys, monkeypatch, "-o", o, "--", first, second)
    assert code == 1 and answer["results"][0]["status"] == "ok"
    r = answer["results"][1]
    assert r["exit_code"] == 5 and r["type"] == "OutputSettingsError" and "input of this run" in r["error"]
    assert sha(first) == before and os.stat(first).st_mtime == 1
    assert not (o / "a.tif.vigproc.json").exists()  # nothing written for the refused file
    # an exact output file onto another input of the call (relative: inside -o): refused as well
    req = {"files": [{"path": str(first), "output": "a.tif"}, {"path": str(second), "output": "b.tif"}]}
    before = sha(second)
    code, answer = hook(capsys, monkeypatch, "--request", "-", "-o", o, stdin=json.dumps(req).encode())
    assert code == 1 and answer["results"][0]["exit_code"] == 5 and answer["results"][1]["status"] == "ok"
    assert answer["results"][1]["output"] == str((o / "b.tif").resolve())
    assert sha(second) == before


def test_output_files_stay_inside_the_output_folder(frame, tmp_path, capsys, monkeypatch):
    work, out, elsewhere = tmp_path / "x", tmp_path / "x" / "out", tmp_path / "elsewhere"
    elsewhere.mkdir()
    out.mkdir(parents=True)
    (out / "link").symlink_to(elsewhere)
    monkeypatch.chdir(work)  # "../escaped.tif" once landed here, beside -o, relative to the working folder
    escapes = ["../escaped.tif", "sub/../../escaped.tif", str(elsewhere / "escaped.tif"), "link/escaped.tif", ".."]
    req = {"files": [*({"path": str(frame), "output": e} for e in escapes), {"path": str(frame), "output": "ok.tif"}]}
    code, answer = hook(capsys, monkeypatch, "--request", "-", "-o", out, stdin=json.dumps(req).encode())
    *refused, ok = answer["results"]
    assert code == 1 and ok["status"] == "ok" and ok["output"] == str(out.resolve() / "ok.tif")
    for r in refused:
        assert r["exit_code"] == 2 and r["type"] == "UsageError" and "inside the output folder" in r["error"], r
    # one file, as a host sends it: a usage error, and nothing written outside -o
    req = {"files": [{"path": str(frame), "output": "../escaped.tif"}]}
    code, answer = hook(capsys, monkeypatch, "--mode", "correct", "-o", out, "--request", "-",
                        stdin=json.dumps(req).encode())
    assert code == 2 and answer["results"][0]["exit_code"] == 2
    assert [p.name for p in tmp_path.rglob("*.tif") if p.parent != frame.parent] == ["ok.tif"]
    assert sorted(os.listdir(out)) == ["link", "ok.tif"] and os.listdir(elsewhere) == []


def test_output_file_and_output_folder_exclude_each_other(frame, tmp_path, capsys, monkeypatch):
    out, target = tmp_path / "out", tmp_path / "fixed.tif"
    code, answer = hook(capsys, monkeypatch, "-o", out, f"--output-file={target}", "--", frame)
    assert code == 2 and "cannot be used together" in answer["error"] and answer["results"] == []
    code, answer = hook(capsys, monkeypatch, f"--output-file={target}", "--request", "-",
                        stdin=json.dumps({"output_dir": str(out), "files": [str(frame)]}).encode())
    assert code == 2 and "cannot be used together" in answer["error"]
    assert not out.exists() and not target.exists()


def test_file_names_cannot_forge_stderr_lines(tmp_path):
    bad = tmp_path / "x\nvigproc: FAKE\r.tif"
    bad.write_bytes(b"not an image")
    r = in_process("hook", "--mode", "estimate", "--", bad, tmp_path / "nope\n.tif")
    code, stdout, stderr = r.returncode, r.stdout, r.stderr
    assert code == 4 and json.loads(stdout)["results"][0]["file"] == str(bad)
    lines = stderr.splitlines()
    assert len(lines) == 2 and all(ln.startswith("vigproc: '") for ln in lines), stderr
    assert not any(ln.startswith("vigproc: FAKE") for ln in lines)


# ------------------------------------------------------------------ exit codes and requests
@pytest.fixture
def constant(tmp_path) -> Path:
    p = tmp_path / "in" / "flat.tif"
    p.parent.mkdir(exist_ok=True)
    write_image(p, np.full((64, 64), 0.5, np.float32), bit_depth="float")
    return p


def test_exit_codes(frame, constant, tmp_path, capsys, monkeypatch):
    missing = tmp_path / "nope.tif"
    out = tmp_path / "out"
    assert hook(capsys, monkeypatch, "-o", out, missing)[0] == 4  # every file: unreadable
    assert hook(capsys, monkeypatch, "-o", out, missing, missing)[0] == 4
    assert hook(capsys, monkeypatch, "-o", out, missing, constant)[0] == 1  # different errors
    code, answer = hook(capsys, monkeypatch, "-o", out, frame, missing)
    assert code == 1 and answer["ok"] == 1 and answer["results"][1]["type"] == "ImageReadError"
    code, answer = hook(capsys, monkeypatch, "-o", out, constant)
    assert code == 3 and answer["results"][0]["type"] == "InvalidImageError"
    code, answer = hook(capsys, monkeypatch, frame)  # correct needs somewhere to write
    assert code == 2 and "output folder" in answer["results"][0]["error"]
    code, answer = hook(capsys, monkeypatch)
    assert code == 2 and "no files" in answer["error"] and answer["results"] == []


def test_internal_error_fails_one_file_only(frame, tmp_path, capsys, monkeypatch):
    from vigproc.pipeline.processor import Processor

    real = Processor.process_file

    def flaky(self, path, *a, **kw):
        if Path(path).name == "bug.tif":
            raise ZeroDivisionError("simulated bug")
        return real(self, path, *a, **kw)

    monkeypatch.setattr(Processor, "process_file", flaky)
    bug = frame.with_name("bug.tif")
    shutil.copyfile(frame, bug)
    code, answer = hook(capsys, monkeypatch, "-o", tmp_path / "out", bug, frame)
    assert code == 1 and answer["results"][1]["status"] == "ok"
    assert answer["results"][0]["exit_code"] == 70 and "ZeroDivisionError" in answer["results"][0]["error"]
    code, _ = hook(capsys, monkeypatch, "-o", tmp_path / "out", bug)
    assert code == 70


@pytest.mark.parametrize("request_bytes, match", [
    (b"not json", "not valid JSON"),
    (b"[]", "JSON object"),
    (b'{"files": ["a.tif"], "colour": 1}', "unknown request fields"),
    (b'{"files": "a.tif"}', "must be a list"),
    (b'{"files": ["a.tif"], "strength": "1"}', "must be a number"),
    (b'{"files": ["a.tif"], "mode": "learn"}', "unknown mode"),
    (b'{"files": ["a.tif"], "method": "nope"}', "unknown method"),
    (b'{"files": ' + b"[" * 100_000 + b"]" * 100_000 + b"}", "not valid JSON"),  # not a RecursionError
])
def test_bad_requests_are_usage_errors(request_bytes, match, capsys, monkeypatch):
    code, answer = hook(capsys, monkeypatch, "--request", "-", stdin=request_bytes)
    assert code == 2 and match in answer["error"]


def test_bad_entries_fail_alone(frame, tmp_path, capsys, monkeypatch):
    req = {"mode": "estimate", "files": [str(frame), {"path": "a\x00b.tif"}, {"path": str(frame), "lens": ["x"]},
                                         {"path": str(frame), "colour": 1}, 42]}
    code, answer = hook(capsys, monkeypatch, "--request", "-", stdin=json.dumps(req).encode())
    assert code == 1 and [r["status"] for r in answer["results"]] == ["ok"] + ["error"] * 4
    assert all(r["exit_code"] == 2 for r in answer["results"][1:])


def test_estimate_without_output_folder_writes_nothing(frame, tmp_path, capsys, monkeypatch):
    files = lambda: sorted(p for p in tmp_path.rglob("*") if not p.name.startswith("profiles.sqlite"))
    before = files()
    code, answer = hook(capsys, monkeypatch, "--mode", "estimate", "--", frame)
    assert code == 0
    r = answer["results"][0]
    assert r["model"]["width"] == 240 and not r["applied"] and "output" not in r
    assert files() == before


@pytest.mark.parametrize("stored, verdict, reason", [
    (False, "unknown-lens", "no stored profile and no lensfun calibration"),
    (True, "consistent", "within the spread of frames taken with this lens"),
])
def test_check_mode_answers_a_verdict(frame, tmp_path, capsys, monkeypatch, stored, verdict, reason):
    """The frame's lens has no profile anywhere (a private store, lensfun lacks it): no
    reference, so ``unknown-lens``; with the frame's own field stored as the lens's
    trusted profile it is ``consistent``."""
    if stored:
        from vigproc.io.exif import ExifReader
        from vigproc.stores.profiles import Profile, ProfileKey, ProfileStore, normalise

        with ExifReader() as r:
            key = ProfileKey.from_lens(r.read(frame), 240, 160)
        with ProfileStore(tmp_path / "profiles.sqlite") as store:
            store.put(Profile(key=key, theta=normalise(FRAME_MODEL.rescale(240, 160))[0], covariance=None,
                              provenance="user", trusted=True, notes="the frame's own field"))
    code, answer = hook(capsys, monkeypatch, "--mode", "check", "--", frame)
    r = answer["results"][0]
    assert code == 0 and r["status"] == "ok", r
    assert r["verdict"]["verdict"] == verdict and reason in r["verdict"]["reason"], r["verdict"]
    assert r["summary"] == f"check: {verdict}" and not r["applied"]


# ------------------------------------------------------------------ plugins
def test_plugins_command_and_plugin_methods_in_the_hook(frame, tmp_path, capsys, monkeypatch):
    site = install_plugin(tmp_path / "site", "vp-hook-plugins", "vp_hook_plugin", PLUGIN_CODE, {
        ESTIMATORS: {"centre-only": "vp_hook_plugin:centre_only", "missing": "vp_hook_nope:fn"}})
    monkeypatch.syspath_prepend(str(site))
    capsys.readouterr()
    assert main(["plugins"]) == 0
    text = capsys.readouterr().out
    assert "centre-only" in text and "ok, use --method centre-only" in text
    assert "BROKEN" in text and "vp_hook_nope" in text
    assert main(["plugins", "--json", "--strict"]) == 1
    doc = json.loads(capsys.readouterr().out)
    assert doc["broken"] == 1
    assert {e["name"]: e["ok"] for e in doc["extensions"]} == {"centre-only": True, "missing": False}
    code, answer = hook(capsys, monkeypatch, "--mode", "estimate", "--method", "centre-only", "--", frame)
    assert code == 0 and answer["results"][0]["model"]["method"] == "centre-only"
    code, answer = hook(capsys, monkeypatch, "--mode", "estimate", "--method", "missing", "--", frame)
    r = answer["results"][0]
    assert code == 12 and r["type"] == "ExtensionError" and "failed to load" in r["error"]
    code, answer = hook(capsys, monkeypatch, "--mode", "estimate", "--method", "nope", "--", frame)
    assert code == 2 and "unknown method" in answer["error"]


def test_a_plugin_is_found_by_a_separate_process(frame, tmp_path):
    """Entry points of an installed distribution reach the real command (here via PYTHONPATH)."""
    site = install_plugin(tmp_path / "site", "vp-proc-plugins", "vp_proc_plugin", PLUGIN_CODE, {
        ESTIMATORS: {"centre-only": "vp_proc_plugin:centre_only"}})
    code, stdout, stderr = run_cli("hook", "--mode", "estimate", "--method", "centre-only", "--", frame,
                                   env={"PYTHONPATH": str(site)})
    assert code == 0, stderr
    assert json.loads(stdout)["results"][0]["model"]["method"] == "centre-only"


def test_a_hosts_lens_keeps_the_frames_crop_factor(frame, tmp_path, capsys, monkeypatch):
    """darktable's script sends the lens, camera, focal length and f-number but no 35-mm focal
    length: a D800 frame shot in its DX crop mode (EXIF 75 mm for 50) then read as the full
    sensor's, so check's lensfun reference put the FX 50mm's whole field over the DX frame
    (1.37 EV at ring 0.85 where the frame's own EXIF gives 0.65)."""
    dx = tmp_path / "in" / "dx.tif"
    subprocess.run(["exiftool", "-q", "-o", str(dx), "-Make=NIKON CORPORATION", "-Model=NIKON D800",
                    "-LensModel=AF-S Nikkor 50mm f/1.8G", "-FocalLength=50", "-FNumber=1.8",
                    "-FocalLengthIn35mmFormat=75", str(frame)], check=True)
    plain = tmp_path / "in" / "plain.tif"
    shutil.copyfile(dx, plain)
    lens = {"make": "NIKON CORPORATION", "model": "NIKON D800", "lens": "AF-S Nikkor 50mm f/1.8G",
            "focal_mm": 50, "fnumber": 1.8}  # what plugins/darktable/vigproc.lua sends
    req = {"mode": "check", "files": [{"path": str(dx), "lens": lens}, str(plain)]}
    code, answer = hook(capsys, monkeypatch, "--request", "-", stdin=json.dumps(req).encode())
    assert code == 0, answer
    host, own = answer["results"]
    assert host["lens"]["key"]["focal_35mm"] == own["lens"]["key"]["focal_35mm"] == 75.0
    want = own["verdict"]["evidence"]["expected_falloff_ev"]
    assert host["verdict"]["evidence"]["expected_falloff_ev"] == pytest.approx(want, abs=0.01)
    assert want[-1] > -0.8  # the inner 0.66 of the lens's field
    # a host's lens of another shot than the file's (another camera) takes nothing from it
    other = {**lens, "model": "NIKON D700"}
    req = {"mode": "check", "files": [{"path": str(dx), "lens": other}]}
    code, answer = hook(capsys, monkeypatch, "--request", "-", stdin=json.dumps(req).encode())
    assert answer["results"][0]["lens"]["key"]["focal_35mm"] is None
