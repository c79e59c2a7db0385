"""The watch-folder daemon under the faults of issue 22: a full output disk, and a
``--retry-quarantined`` restart with a quarantine folder (kill -9 of the daemon with
healthy files in progress, charged nothing: tests/test_daemon.py).

The full disk is simulated (nothing is mounted): a ``sitecustomize`` loaded by every
process of the daemon makes the corrected image's writer fail as OpenImageIO does on
a full tmpfs (``TIFFWriteScanline failed ... Write error``: no errno, no "no space")
and ``shutil.disk_usage`` report an almost full file system, while marker files say so.
"""

from __future__ import annotations

import json
import os
import time
from pathlib import Path

import pytest

from conftest import run_cli
from test_daemon import (Daemon, journal_entries, make_good, out_sidecar, output_files, output_stem, sha,
                         sidecars, sitecustomize)

_FAULTS = sitecustomize("vigproc.io.metadata", r'''
"""Test-only faults, injected into every vigproc process through sitecustomize."""
import os, shutil
from collections import namedtuple

MARK = os.environ["VIGPROC_TEST_FAULT_DIR"]
Usage = namedtuple("usage", "total used free")


def _on(name):
    return os.path.exists(os.path.join(MARK, name))


def disk_usage(path):
    if _on("low-space"):  # the audit's 20 MB tmpfs, nearly full
        return Usage(20_000_000, 19_000_000, 1_000_000)
    return Usage(10**12, 10**11, 9 * 10**11)


shutil.disk_usage = disk_usage


def _patch(module):
    orig = module.write_corrected

    def write_corrected(dst, *a, **kw):
        if _on("write-fails"):
            from vigproc.errors import ImageWriteError
            raise ImageWriteError(f"cannot write {str(dst)!r}: TIFFWriteScanline failed: Write error at scanline 7")
        if _on("photo-refused"):
            from vigproc.errors import ModelError
            raise ModelError("simulated: this installation cannot correct it (yet)")
        return orig(dst, *a, **kw)

    module.write_corrected = write_corrected
''')


@pytest.fixture(autouse=True)
def _no_daemon_outlives_its_test(monkeypatch):
    """A failed wait leaves no daemon running (killed at teardown)."""
    started = []
    start = Daemon.start

    def tracked(self, *a, **kw):
        started.append(self)
        return start(self, *a, **kw)

    monkeypatch.setattr(Daemon, "start", tracked)
    yield
    for d in started:
        if d.proc is not None and d.proc.poll() is None:
            d.proc.kill()
            d.proc.wait(timeout=30)


@pytest.fixture
def faults(tmp_path):
    """(environment with the faults, marker folder)."""
    site = tmp_path / "site"
    site.mkdir()
    (site / "sitecustomize.py").write_text(_FAULTS)
    marks = tmp_path / "marks"
    marks.mkdir()
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(site), os.environ.get("PYTHONPATH", "")]),
           "VIGPROC_TEST_FAULT_DIR": str(marks)}
    return env, marks


def _status(out_dir: Path) -> dict:
    for p in out_dir.glob(".vigproc-watch-*.status.json"):
        try:
            return json.loads(p.read_text())
        except (OSError, ValueError):
            pass
    return {}


def _inputs(in_dir: Path) -> list[str]:
    return sorted(str(p.relative_to(in_dir)) for p in in_dir.rglob("*") if p.is_file())


def test_a_full_output_disk_pauses_the_daemon_and_quarantines_nothing(tmp_path, faults):
    """Issue 22: with the output disk full, 5 of 6 healthy JPEGs were quarantined for
    good (and moved out of the input folder with --quarantine).  Now the daemon pauses,
    says so in its status and log, gives the files back without an attempt, and once
    a probe is written (space was freed) does every file exactly once."""
    env, marks = faults
    in_dir, out_dir, qdir = tmp_path / "in", tmp_path / "out", tmp_path / "quarantine"
    names = ["a.png", "b.tif", "sub/c.png", "d.jpg"]
    digests = {n: sha(make_good(in_dir, n, i)) for i, n in enumerate(names)}
    (marks / "write-fails").touch()
    (marks / "low-space").touch()
    d = Daemon(in_dir, out_dir, tmp_path / "daemon.log", "--settle", "0.2", "--quarantine", str(qdir),
               env=env).start()
    d.wait_for("the daemon paused for the full disk",
               lambda: _status(out_dir).get("state") == "paused"
               and any("output disk full" in (e.reason or "") for e in journal_entries(out_dir).values()), timeout=90)
    st = run_cli("watch", in_dir, "-o", out_dir, "--status")  # asked in this process
    assert "PAUSED: output disk full" in st.stdout and "nothing is quarantined" in st.stdout, st.stdout
    paused = _status(out_dir)["paused"]
    assert paused["why"] == "output disk full" and paused["free_bytes"] == 1_000_000 and paused["files_waiting"] >= 1
    assert "TIFFWriteScanline failed" in paused["reason"]
    # a few failed probes: still nothing quarantined, nothing moved, no attempt counted
    d.wait_for("two failed probes", lambda: sum(ev.get("event") == "disk-still-full" for ev in d.events()) >= 2,
               timeout=60)
    entries = journal_entries(out_dir).values()
    assert not [e for e in entries if e.state == "quarantined" or e.attempts or e.crashes]
    assert _inputs(in_dir) == sorted(names) and list(qdir.iterdir()) == []

    (marks / "write-fails").unlink()  # space freed, though the disk still counts as nearly full: a probe tells
    d.wait_for("every file done", lambda: sum(e.state == "done" for e in journal_entries(out_dir).values())
               == len(names), timeout=120)
    assert _status(out_dir).get("state") == "running"
    assert d.stop() == 0
    entries = journal_entries(out_dir)
    assert all(e.state == "done" and e.attempts == 0 and e.crashes == 0 for e in entries.values())
    assert _inputs(in_dir) == sorted(names) and list(qdir.iterdir()) == []  # nothing moved out of the input folder
    for n, digest in digests.items():  # exactly one output and sidecar each, for the right content
        assert sha(in_dir / n) == digest
        sc = json.loads(out_sidecar(out_dir, n).read_text())
        assert sc["input_sha256"] == digest and Path(sc["output"]).is_file()
    assert len(sidecars(out_dir)) == len(names)
    outputs = [p for p in output_files(out_dir) if not p.endswith(".vigproc.json")]
    assert len(outputs) == len(names)
    events = [ev.get("event") for ev in d.events()]
    assert events.count("disk-full") == 1 and events.count("disk-resumed") == 1 and "quarantined" not in events
    resumed = next(ev for ev in d.events() if ev.get("event") == "disk-resumed")
    assert "was written" in resumed["why"]  # by the probe, not by the free space (still "low")


def test_retry_quarantined_brings_files_back_from_the_quarantine_folder(tmp_path, faults):
    """Issue 22: a restart with --retry-quarantined deleted the journal records of files
    moved into --quarantine DIR and processed nothing, leaving them stranded there.  They
    are now moved back to where they were found and processed."""
    env, marks = faults
    in_dir, out_dir, qdir = tmp_path / "in", tmp_path / "out", tmp_path / "quarantine"
    names = ["a.png", "sub dir/b.png"]
    digests = {n: sha(make_good(in_dir, n, i)) for i, n in enumerate(names)}
    (marks / "photo-refused").touch()
    common = ("--settle", "0.2", "--quarantine", str(qdir))
    d = Daemon(in_dir, out_dir, tmp_path / "daemon.log", *common, env=env, workers=1).start()
    d.wait_for("both moved to the quarantine folder", lambda: _inputs(in_dir) == [], timeout=90)
    d.wait_for("the status to count them", lambda: _status(out_dir).get("this_run", {}).get("quarantined", 0)
               >= len(names), timeout=30)
    run = _status(out_dir)["this_run"]
    # failed attempts under their own name: the journal's "failed" means files waiting to retry
    assert "failed" not in run and run.get("failed_attempts", 0) >= len(names), run
    assert d.stop() == 0
    assert sorted(p.name for p in qdir.iterdir()) == sorted(
        [output_stem(n) for n in names] + [output_stem(n) + ".reason.json" for n in names])

    (marks / "photo-refused").unlink()  # the cause was fixed
    d = Daemon(in_dir, out_dir, tmp_path / "daemon.log", *common, "--retry-quarantined", env=env,
               workers=1).start()
    d.wait_for("both done", lambda: sum(e.state == "done" for e in journal_entries(out_dir).values()) == 2,
               timeout=90)
    assert d.stop() == 0
    assert _inputs(in_dir) == sorted(names) and list(qdir.iterdir()) == []
    for n, digest in digests.items():
        assert sha(in_dir / n) == digest
        assert json.loads(out_sidecar(out_dir, n).read_text())["input_sha256"] == digest
    assert sum(ev.get("event") == "unquarantined" for ev in d.events()) == 2


def test_a_pause_resumes_as_soon_as_the_free_space_grows(tmp_path, monkeypatch):
    """The other way out of a pause: the free space grew (the disk was grown or cleaned),
    seen within a second; a quota (free space unchanged) waits for the probe instead."""
    import vigproc.frontends.daemon as D
    import vigproc.frontends.daemon.scheduler as S
    from vigproc.pipeline.faults import DiskSpace

    in_dir = tmp_path / "in"
    in_dir.mkdir()
    cfg = D.WatchConfig(in_dir=in_dir, out_dir=tmp_path / "out", settings={"mode": "correct", "profile": "estimate"})
    cfg.validate()
    d = D.Daemon(cfg)
    s = d.scheduler  # what schedules holds the pause
    d.journal = D.Journal(cfg.journal, job=cfg.job)  # for the status the resume writes
    free = [5_000_000]
    monkeypatch.setattr(S, "disk_space", lambda p: DiskSpace(free[0], 20_000_000, 1000))
    now = time.monotonic()
    s.disk = S._DiskPause(reason="output disk full", since=time.time(), free_bytes=5_000_000, delay=60,
                          probe_at=now + 60, held={str(in_dir / "a.png")})
    (in_dir / "a.png").write_bytes(b"x")
    assert s.disk_go() is None  # still full, and no probe due
    cfg.min_free = 1_000_000  # "not low" now, but not grown either: a quota, say
    s.disk.next_look = 0
    assert s.disk_go() is None
    free[0] = 500_000_000  # grown
    s.disk.next_look = 0
    assert s.disk_go() == "resume" and s.disk is None
    assert list(d.watcher.ready) == [str(in_dir / "a.png")] and str(in_dir / "a.png") in s.disk_ready
    assert json.loads(cfg.status_file.read_text())["state"] == "running"
    d.journal.close()
