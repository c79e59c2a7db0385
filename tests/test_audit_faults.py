"""Audit (issue 37): a full or read-only output disk never quarantines a healthy photo.

Real tmpfs mounts, real `vigproc watch` and `vigproc correct` processes, real
writers (OpenImageIO's libjpeg, exiftool): nothing is stubbed.  The output tmpfs is
sized so that it fills mid-run; space comes back by deleting a filler file (or the
tmpfs is remounted read-only, then read-write).  Hostile names that spell the words
an older classifier read ("no space left on device", "refusing") must not change
what becomes of a file.  Skipped, with the reason, where ``mount -t tmpfs`` is not
permitted.  Each test is bounded in time (a timeout on every wait).
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from conftest import run_cli, textured
from benchmarks.faults import _Watch, _results, why_not

REPO = Path(__file__).resolve().parents[1]
PROFILE = REPO / "profiles" / "examples" / "sony-rx100-10.4mm-f1.8.json"  # 3:2 frames

_WHY_NOT = why_not()
needs_tmpfs = pytest.mark.skipif(_WHY_NOT is not None, reason=f"needs a tmpfs of its own: {_WHY_NOT or ''}")

#: Healthy photos with names that carry the words of disk and refusal messages.
HOSTILE = ["IMG_0001 no space left on device.jpg", "refusing to pose.jpg", "disk quota exceeded.jpg",
           "Output file write error --- out of disk space.jpg", "database is locked.jpg", "Input output error.jpg",
           "read-only file system.jpg", "cannot read the source.jpg"]


def _env() -> dict[str, str]:
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join([str(REPO), *filter(None, [env.get("PYTHONPATH")])])
    return env


def _mount(mnt: Path, opts: str, remount: bool = False) -> None:
    cmd = ["mount", "-o", f"remount,{opts}", str(mnt)] if remount else \
        ["mount", "-t", "tmpfs", "-o", opts, "tmpfs", str(mnt)]
    subprocess.run(cmd, check=True, capture_output=True)


@pytest.fixture
def tmpfs(tmp_path):
    """A factory of tmpfs mounts under ``tmp_path``, unmounted afterwards."""
    mounted: list[Path] = []

    def make(name: str, kb: int) -> Path:
        mnt = tmp_path / name
        mnt.mkdir()
        _mount(mnt, f"size={kb}k,mode=0755")
        mounted.append(mnt)
        return mnt

    yield make
    for mnt in reversed(mounted):
        subprocess.run(["umount", "-l", str(mnt)], check=False, capture_output=True)


def _jpeg(path: Path, seed: int, h: int = 240, w: int = 360) -> Path:
    """A small healthy JPEG (about 100 KB: a 1/f texture compresses poorly)."""
    from vigproc.io.images import write_image

    img = np.stack([textured(h, w, seed=seed + 7 * c, contrast=0.4) for c in range(3)], -1)
    write_image(path, np.clip(img, 0, 1).astype(np.float32), bit_depth="uint8", transfer="srgb", quality=95)
    return path


def _photos(folder: Path, n: int) -> list[Path]:
    """``n`` healthy photos, the hostile names first."""
    made = folder / ".made"
    made.mkdir(parents=True, exist_ok=True)
    names = (HOSTILE + [f"IMG_{i:04d}.jpg" for i in range(100, 100 + n)])[:n]
    return [_jpeg(made / name, i) for i, name in enumerate(names)]


def _drop(files: list[Path], in_dir: Path) -> None:
    """Drop files into the watch folder complete (by rename)."""
    for src in files:
        os.rename(src, in_dir / src.name)


def _journal(path: Path) -> dict[str, tuple[str, int, int]]:
    """Input name -> (state, attempts, crashes) as the daemon's journal has it."""
    import sqlite3

    con = sqlite3.connect(f"file:{path}?mode=ro", uri=True)
    try:
        rows = con.execute("SELECT path, state, attempts, crashes FROM entries").fetchall()
    finally:
        con.close()
    return {os.path.basename(os.fsdecode(p)): (s, int(a), int(c)) for p, s, a, c in rows}


def _watch(in_dir: Path, out: Path, q: Path, base: Path, *extra: str) -> _Watch:
    w = _Watch([sys.executable, "-m", "vigproc.frontends.cli", "watch", str(in_dir), "-o", str(out),
                "--quarantine", str(q), "--workers", "2", "--settle", "0.2", "--profile", str(PROFILE),
                "--journal", str(base / "journal.sqlite"), "--status-file", str(base / "status.json"),
                "--retry-base", "0.5", "--retry-cap", "2", "--min-free", "1", "--log-json", *extra],
               base / "daemon.log")
    env = _env()
    old = dict(os.environ)
    os.environ.update(env)  # _Watch starts the daemon with this process's environment
    try:
        w.start()
    finally:
        os.environ.clear()
        os.environ.update(old)
    return w


def _figures(w: _Watch, out: Path, q: Path, base: Path, healthy: list[str]) -> dict[str, int]:
    done = _results(out)[0]
    j = _journal(base / "journal.sqlite")
    quarantined = {n for n, (s, _a, _c) in j.items() if s == "quarantined"}
    if q.is_dir():
        quarantined |= {p.name for p in q.iterdir() if not p.name.endswith(".reason.json")}
    return {
        "done": sum(1 for n in healthy if n in done),
        "healthy_quarantined": len(quarantined & set(healthy)),
        "worker_deaths": w.count("worker-restart"),
        "crashes_charged": sum(c for n, (_s, _a, c) in j.items() if n in healthy),
        "pauses": w.count("disk-full"),
        "temporaries": sum(1 for p in out.iterdir() if p.name.startswith(".") and ".tmp" in p.name),
    }


@needs_tmpfs
def test_watch_on_a_full_output_disk_quarantines_no_healthy_photo(tmp_path, tmpfs):
    """30 healthy JPEGs into `watch`, its output on a tmpfs with about 1 MB left, so that
    it fills mid-run; a filler is deleted a few seconds into the trouble.  Every healthy
    photo done, none quarantined, no worker death; then a corrupt file with a disk-full
    name is quarantined (its name does not make it a full disk)."""
    from benchmarks.faults import FaultBenchError

    in_dir, q = tmp_path / "in", tmp_path / "q"
    in_dir.mkdir()
    out = tmpfs("out", 6 * 1024)
    files = _photos(tmp_path, 30)
    assert all(60_000 <= f.stat().st_size <= 200_000 for f in files), [f.stat().st_size for f in files]
    filler = out / "filler"
    filler.write_bytes(b"\0" * (shutil.disk_usage(out).free - 2**19))  # 0.5 MB left: room for a few results
    bad = tmp_path / ".made" / "IMG_0002 no space left on device.jpg"
    bad.write_bytes(os.urandom(5000))
    healthy = [f.name for f in files]
    w = _watch(in_dir, out, q, tmp_path)
    timed_out = None
    try:
        _drop(files, in_dir)
        w.wait_for("trouble (a pause or a worker death)",
                   lambda: w.count("disk-full") + w.count("worker-restart") > 0, 180)
        time.sleep(4.0)  # full for a while
        filler.unlink()
        w.wait_for("every healthy photo done",
                   lambda: _figures(w, out, q, tmp_path, healthy)["done"] == len(healthy), 300)
        _drop([bad], in_dir)
        w.wait_for("the corrupt one quarantined",
                   lambda: _journal(tmp_path / "journal.sqlite").get(bad.name, ("",))[0] == "quarantined", 30)
    except FaultBenchError as exc:
        timed_out = str(exc)
    finally:
        if w.proc is not None and w.proc.poll() is None:
            w.stop()
    fig = _figures(w, out, q, tmp_path, healthy)
    print("full output disk:", json.dumps(fig), timed_out or "")
    assert timed_out is None, (timed_out, fig)
    assert fig["pauses"] >= 1, fig  # it did fill
    assert (fig["done"], fig["healthy_quarantined"], fig["worker_deaths"], fig["crashes_charged"]) == \
        (30, 0, 0, 0), fig
    assert (q / bad.name).is_file() and fig["temporaries"] == 0


@needs_tmpfs
def test_watch_on_a_read_only_output_retries_and_quarantines_nothing(tmp_path, tmpfs):
    """The output remounted read-only while photos arrive (one named "refusing to pose"):
    retried, none quarantined; all done once it is writable again."""
    in_dir, q = tmp_path / "in", tmp_path / "q"
    in_dir.mkdir()
    out = tmpfs("out", 20 * 1024)
    files = _photos(tmp_path, 6)
    w = _watch(in_dir, out, q, tmp_path)
    try:
        w.wait_for("the workers", lambda: w.count("worker-ready") >= 2, 60)
        _mount(out, "ro", remount=True)
        _drop(files, in_dir)
        healthy = [f.name for f in files]
        w.wait_for("each photo to fail at least twice on the read-only output",
                   lambda: all(_journal(tmp_path / "journal.sqlite").get(n, ("", 0))[1] >= 2 for n in healthy), 60)
        assert _figures(w, out, q, tmp_path, healthy)["healthy_quarantined"] == 0
        _mount(out, "rw", remount=True)
        w.wait_for("every photo done", lambda: _figures(w, out, q, tmp_path, healthy)["done"] == len(healthy), 60)
    finally:
        if w.proc is not None and w.proc.poll() is None:
            w.stop()
    fig = _figures(w, out, q, tmp_path, healthy)
    print("read-only output:", json.dumps(fig))
    assert (fig["done"], fig["healthy_quarantined"], fig["worker_deaths"]) == (6, 0, 0), fig


@needs_tmpfs
def test_correct_on_a_full_output_disk_exits_5_with_its_summary(tmp_path, tmpfs):
    """`correct a.jpg b.jpg c.jpg -o OUT`, OUT a 48 KB tmpfs (libjpeg used to end the
    process mid-write: exit 1, no summary, two temporaries left): exit 5, the summary
    printed, no temporary left, the rest reported not started."""
    out = tmpfs("out", 48)
    files = _photos(tmp_path, 3)
    r = subprocess.run([sys.executable, "-m", "vigproc.frontends.cli", "correct", "--profile", str(PROFILE),
                        "-o", str(out), *map(str, files)], capture_output=True, text=True, env=_env(), timeout=120)
    print("correct on a full disk:", r.returncode, r.stdout, r.stderr)
    assert r.returncode == 5, r.stderr
    assert "Traceback" not in r.stderr and "output disk full" in r.stderr
    assert "0 corrected, 0 not corrected, 3 failed" in r.stdout
    assert "2 file(s) not started" in r.stderr
    assert [p.name for p in out.iterdir() if ".tmp" in p.name or "exiftool" in p.name] == []


def test_a_corrupt_file_named_like_a_full_disk_is_the_files_fault(tmp_path):
    """`correct` of a corrupt file whose name says "no space left on device", then a good
    one: the corrupt one fails as unreadable (exit 4 for it), the good one is done."""
    files = _photos(tmp_path, 1)
    bad = tmp_path / "IMG_0001 no space left on device.jpg"
    bad.write_bytes(os.urandom(5000))
    r = run_cli("correct", "--profile", PROFILE, "-o", tmp_path / "out", bad, files[0])  # in this process
    assert r.returncode == 1 and "disk full" not in r.stderr, r.stderr
    assert "1 corrected" in r.stdout or "1 not corrected" in r.stdout, r.stdout


def test_an_output_sub_folder_that_cannot_be_made_is_the_output_sides(tmp_path):
    """Issue 37.4: a file where the output sub-folder should be (`echo x > out/sub1`) made
    the worker die of an UnboundLocalError on its first task, and the photo was
    quarantined after three deaths.  Now: an output failure with a clear reason, retried,
    no worker death; done once the file is out of the way."""
    from benchmarks.faults import FaultBenchError

    in_dir, q, out = tmp_path / "in", tmp_path / "q", tmp_path / "out"
    (in_dir / "sub1").mkdir(parents=True)
    out.mkdir()
    (out / "sub1").write_text("x\n")
    (photo,) = _photos(tmp_path, 1)
    w = _watch(in_dir, out, q, tmp_path, "--workers", "1")
    try:
        os.rename(photo, in_dir / "sub1" / photo.name)
        w.wait_for("two output failures", lambda: sum(ev.get("event") == "retry" for ev in w.events()) >= 2, 120)
        retries = [ev for ev in w.events() if ev.get("event") == "retry"]
        assert all(ev["kind"] == "output" and "a file of that name is in the way" in ev["reason"] for ev in retries), \
            retries
        (out / "sub1").unlink()
        w.wait_for("the photo done", lambda: (out / "sub1" / f"{photo.name}.vigproc.json").is_file(), 120)
    except FaultBenchError as exc:
        pytest.fail(f"{exc}: {w.log_file.read_text()[-3000:]}")
    finally:
        if w.proc is not None and w.proc.poll() is None:
            w.stop()
    assert w.count("worker-restart") == 0 and w.count("quarantined") == 0
