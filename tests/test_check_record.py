"""What an examiner files (issue 36): the check's report and JSON state the file's hash,
its capture date, camera and metadata conflicts, and the run's date, version and command
line; one frame has one confidence in estimate, check, the hook and the report; correct
runs without a profile store it cannot create; Ctrl-C says what was done."""

import datetime
import hashlib
import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from vigproc._version import __version__
from vigproc.frontends.cli import main
from vigproc.io.images import write_image

from conftest import textured

SAMPLE = Path(__file__).resolve().parents[1] / "vigproc" / "data" / "samples" / "kodim13_vignetted.jpg"
VIGPROC = [sys.executable, "-m", "vigproc.frontends.cli"]


def _cli(capsys, *args):
    """``vigproc ARGS`` in this process: (exit code, stdout, stderr)."""
    capsys.readouterr()
    code = main([os.fspath(a) for a in args])
    out, err = capsys.readouterr()
    assert "Traceback" not in err
    return code, out, err


@pytest.fixture
def conflicted(tmp_path, _conflicted_bytes):
    """The 105 mm sample with a capture date, an offset and a serial, whose XMP gives
    another date, another lens and another focal length (an editor rewrote one side).
    Its name is hostile HTML.  Each test's own copy."""
    path = tmp_path / "a<b>&'x.jpg"
    path.write_bytes(_conflicted_bytes)
    return path


@pytest.fixture(scope="module")
def _conflicted_bytes(tmp_path_factory):
    """:func:`conflicted`'s file, tagged once (an exiftool run costs about 0.3 CPU s)."""
    if shutil.which("exiftool") is None:
        pytest.skip("exiftool is not installed")
    path = tmp_path_factory.mktemp("conflicted") / "conflicted.jpg"
    shutil.copyfile(SAMPLE, path)
    subprocess.run(["exiftool", "-q", "-overwrite_original", "-EXIF:DateTimeOriginal=2021:05:06 07:08:09",
                    "-EXIF:OffsetTimeOriginal=+02:00", "-EXIF:SerialNumber=SN12345",
                    "-XMP:DateTimeOriginal=2022:01:01 10:00:00", "-XMP:LensModel=EF 50mm f/1.8",
                    "-XMP-exif:FocalLength=18", "--", str(path)], check=True, capture_output=True, timeout=60)
    return path.read_bytes()


def test_the_report_and_json_hold_hash_dates_camera_conflicts_and_the_run(conflicted, tmp_path, capsys):
    before = datetime.datetime.now(datetime.timezone.utc).replace(microsecond=0)
    digest = hashlib.sha256(conflicted.read_bytes()).hexdigest()
    code, out, err = _cli(capsys, "check", "--json", conflicted)
    doc = json.loads(out)
    [rec] = doc["results"]
    p = rec["provenance"]
    assert p["sha256"] == digest and p["size_bytes"] == conflicted.stat().st_size
    assert (p["captured"], p["captured_offset"]) == ("2021:05:06 07:08:09", "+02:00")
    assert (p["make"], p["model"], p["serial"]) == ("Sigma", "vigproc sample", "SN12345")
    assert p["lens"] == "105mm F1.4 DG HSM | Art 018"
    assert any(c.startswith("capture date:") and "2022:01:01" in c for c in p["conflicts"]), p
    assert any(c.startswith("lens:") and "EF 50mm" in c for c in p["conflicts"]), p
    assert any(c.startswith("focal_mm:") for c in p["problems"]), p  # the lens reading's own contradiction
    # the reason says what is wrong with the metadata, not "no lensfun calibration"
    assert rec["verdict"] == "unknown-lens" and "contradictory" in rec["reason"], rec["reason"]
    assert "lensfun" not in rec["reason"]
    run = doc["run"]
    when = datetime.datetime.fromisoformat(run["analysed_utc"])
    assert when.utcoffset() == datetime.timedelta(0) and before <= when <= datetime.datetime.now(datetime.timezone.utc)
    assert run["vigproc"] == __version__ and run["argv"] == ["vigproc", "check", "--json", str(conflicted)]
    assert run["settings"]["method"] == "default" and run["settings"]["alpha"] == 0.01
    assert run["references"]["calibration"]["test"] == "lens-family"
    assert code == 21, err

    report = tmp_path / "r.html"
    code, out, err = _cli(capsys, "check", conflicted, "--report", report)
    page = report.read_text(encoding="utf-8")
    for text in (digest, "2021:05:06 07:08:09 +02:00", "SN12345", f"vigproc</th><td>{__version__}",
                 "XMP:DateTimeOriginal=&#x27;2022:01:01 10:00:00&#x27;", "analysed (UTC)"):
        assert text in page, text
    # the command line, escaped: the hostile name never becomes markup
    assert "a&lt;b&gt;&amp;" in page and "<b>" not in page
    assert "vigproc check" in page and "--report" in page


def test_the_png_report_has_the_run_at_its_head(conflicted, tmp_path, capsys):
    """The PNG report is the figures stacked under the run's record: taller by it."""
    from vigproc.forensics.check import forensic_check
    from vigproc.forensics.report import ReportItem, png_bytes, report_figure, write_report

    v = forensic_check(np.repeat(textured(160, 240, seed=1)[..., None], 3, axis=2), None)
    item = ReportItem("x.jpg", v)
    plain, with_run = tmp_path / "a.png", tmp_path / "b.png"
    write_report(plain, [item])
    write_report(with_run, [item], run={"analysed_utc": "2026-01-01T00:00:00+00:00", "vigproc": __version__,
                                         "argv": ["vigproc", "check", "x.jpg"]})
    assert with_run.stat().st_size > plain.stat().st_size
    assert len(png_bytes(report_figure(item))) > 0


def test_one_confidence_in_estimate_check_hook_and_report(tmp_path, capsys):
    """A user saw 'estimator confidence 1.00' in the report for a frame estimate called
    0.47, and the hook's check said 1.0 with SNR 0.08: every command states the same
    figure, the frame's estimate with the same settings."""
    frame = tmp_path / "weak.tif"
    write_image(frame, np.repeat(textured(240, 360, seed=3, contrast=0.3)[..., None], 3, axis=2).astype(np.float32),
                bit_depth="float")
    _, out, _ = _cli(capsys, "estimate", "--json", frame)
    q = json.loads(out)["results"][0]["model"]["quality"]
    assert 0.0 < q["confidence"] < 0.9, q  # the premise: a frame of weak evidence
    _, out, _ = _cli(capsys, "check", "--json", frame)
    rec = json.loads(out)["results"][0]
    assert rec["confidence"] == pytest.approx(q["confidence"], abs=1e-9)
    assert rec["snr"] == pytest.approx(q["snr"], abs=1e-9)
    assert rec["estimate"]["quality"]["confidence"] is None  # the test's own fit claims none
    _, out, _ = _cli(capsys, "hook", "--mode", "check", "--", frame)
    answer = json.loads(out)
    [r] = answer["results"]
    assert r["confidence"] == pytest.approx(q["confidence"], abs=1e-4)
    assert r["snr"] == pytest.approx(q["snr"], abs=1e-4)
    assert r["verdict"]["confidence"] == pytest.approx(q["confidence"], abs=1e-9)
    assert r["provenance"]["sha256"] == hashlib.sha256(frame.read_bytes()).hexdigest()
    datetime.datetime.fromisoformat(answer["analysed_utc"])
    report = tmp_path / "r.html"
    _cli(capsys, "check", frame, "--report", report)
    assert f"<td>{q['confidence']:.2f} (SNR {q['snr']:.1f})</td>" in report.read_text(encoding="utf-8")


def test_correct_runs_without_a_default_store_it_cannot_create(tmp_path, monkeypatch, capsys):
    """correct exited 8 when the default store's folder could not be created, though no
    stored profile was used: the home is a regular file here, so no folder can be made
    under it (whoever runs the test, root too)."""
    blocker = tmp_path / "not-a-folder"
    blocker.write_text("x")
    monkeypatch.delenv("VIGPROC_PROFILE_DB", raising=False)
    monkeypatch.setenv("HOME", str(blocker))
    monkeypatch.setenv("XDG_DATA_HOME", str(blocker / "data"))
    code, out, err = _cli(capsys, "correct", SAMPLE, "-o", tmp_path / "out")
    assert code == 0, err
    assert "no profile store" in err and "going on without stored profiles" in err
    assert (tmp_path / "out" / "kodim13_vignetted.corrected.jpg").is_file()
    # an existing store that cannot be opened still fails: its profiles would be missed
    bad = tmp_path / "bad.sqlite"
    bad.write_bytes(b"this is not a database" * 100)
    code, out, err = _cli(capsys, "correct", SAMPLE, "-o", tmp_path / "out2", "--profile-db", bad)
    assert code == 8, err


N_LINKED = 150


def test_ctrl_c_says_what_was_done_and_exits_130(tmp_path):
    """Ctrl-C (SIGINT to the whole process group, as a terminal sends it, exiftool too)
    printed pyexiftool's UserWarning with a literal \\n and no summary."""
    big = tmp_path / "big.jpg"
    rng = np.random.default_rng(0)
    write_image(big, rng.random((2000, 3000, 3)).astype(np.float32), format="jpeg", bit_depth="uint8",
                transfer="srgb", quality=90)
    files = []
    # many hard links: the write queue may put the first record out late, and the run must
    # still be going when the signal comes (40 were all done under a loaded machine's delay)
    for i in range(N_LINKED):
        f = tmp_path / f"f{i:02d}.jpg"
        os.link(big, f)
        files.append(str(f))
    out = tmp_path / "out"
    p = subprocess.Popen([*VIGPROC, "correct", *files, "-o", str(out)], stdout=subprocess.PIPE,
                         stderr=subprocess.PIPE, text=True, start_new_session=True)
    try:
        deadline = time.monotonic() + 240
        while not list(out.glob("*.vigproc.json")) and p.poll() is None and time.monotonic() < deadline:
            time.sleep(0.1)
        os.killpg(p.pid, signal.SIGINT)
        stdout, stderr = p.communicate(timeout=120)
    finally:
        if p.poll() is None:
            os.killpg(p.pid, signal.SIGKILL)
    assert p.returncode == 130, stderr
    assert "UserWarning" not in stderr and "exiftool.py" not in stderr and "\\n" not in stderr, stderr
    [line] = [ln for ln in stderr.splitlines() if "interrupted" in ln]
    assert line.startswith("vigproc correct: interrupted: ") and "not started" in line, stderr
    import re

    m = re.search(r"(\d+) corrected, (\d+) not corrected, (\d+) failed, (\d+) not started", line)
    assert m, line
    corrected, unapplied, failed, not_started = map(int, m.groups())
    assert corrected + unapplied >= 1 and failed == 0 and not_started >= 1, line  # what it had done
    assert corrected + unapplied + failed + not_started == N_LINKED, line
