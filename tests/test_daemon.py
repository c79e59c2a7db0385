"""The watch-folder daemon, run as a real subprocess on real folders.

Files are copied in, some written slowly in chunks, some corrupt, some with hostile
names or writers' temporary names; the daemon is killed with SIGKILL mid-run and
restarted, stopped with SIGTERM while busy, made to crash its worker, to hang and to
hit a full disk.  Every good file must end with exactly one output and sidecar, every
bad one quarantined with a reason, nothing lost, nothing done twice.
"""

from __future__ import annotations

import ast
import hashlib
import json
import os
import shutil
import signal
import subprocess
import sys
import threading
import time
from collections import Counter
from pathlib import Path

import numpy as np
import pytest

from conftest import run_cli, textured
from vigproc.frontends.daemon import (
    DISK_FULL,
    PERMANENT,
    TRANSIENT,
    SettleTracker,
    _move,
    classify_error,
    is_temporary_name,
    output_stem,
)
from vigproc.errors import ImageReadError, ImageWriteError, write_error
from vigproc.pipeline.faults import OUTPUT
from vigproc.stores.journal import Journal, fingerprint
from vigproc.pipeline.processor import corrected_name, output_location
from vigproc.stores.profiles import ProfileStoreError

REPO = Path(__file__).resolve().parents[1]
PROFILE = REPO / "profiles" / "examples" / "sony-rx100-10.4mm-f1.8.json"  # 3:2 frames
VIGPROC = [sys.executable, "-m", "vigproc.frontends.cli"]


@pytest.fixture(autouse=True)
def _private_profile_store(tmp_path, monkeypatch):
    """No daemon started here may touch the user's profile store."""
    monkeypatch.setenv("VIGPROC_PROFILE_DB", str(tmp_path / "default-profiles.sqlite"))


# ====================================================================== units
def test_temporary_names_are_ignored():
    temp = [".x.jpg", ".x.jpg.Ab12Cd", "._x.jpg", ".~lock.x.jpg#", "~$x.jpg", "x.jpg~", "x.jpg.part",
            "x.jpg.crdownload", "x.JPG.TMP", "x.jpg.!ut", "x.jpg.filepart", "x.download", "x.jpg.partial", ""]
    real = ["x.jpg", "-x.jpg", "~x.jpg", "x y.jpg", "x.part.jpg", "x.tmp.tif", "写真.png"]
    assert [n for n in temp if not is_temporary_name(n)] == []
    assert [n for n in real if is_temporary_name(n)] == []


def test_output_stems_are_distinct_stable_and_safe():
    rels = ["x.jpg", "x.png", "a/x.jpg", "b/x.jpg", "a%2Fx.jpg", "a_x.jpg", ".x.jpg", "%2Ex.jpg",
            "new\nline.jpg", "new%0Aline.jpg", os.fsdecode(b"latin-\xe9.jpg"), "latin-%E9.jpg",
            "a/" * 150 + "long.jpg", "a/" * 150 + "long2.jpg", "é" * 200 + ".jpg", "é" * 201 + ".jpg"]
    stems = [output_stem(r) for r in rels]
    assert len(set(stems)) == len(rels)  # one-to-one
    assert stems == [output_stem(r) for r in rels]  # deterministic
    for s in stems:
        assert "/" not in s and not s.startswith(".") and not any(ord(c) < 32 for c in s)
        assert len(s.encode("utf-8")) <= 180
        s.encode("utf-8")  # no surrogates: every output name is valid UTF-8


def test_errors_are_classified():
    """The daemon's classifier is the shared policy (vigproc.pipeline.faults; more in test_faults)."""
    assert classify_error(ImageReadError("cannot read 'x.jpg': corrupt or truncated JPEG")).kind == PERMANENT
    assert classify_error(write_error("cannot write 'x.tif'", OSError(28, "No space left on device"))).kind == DISK_FULL
    assert classify_error(OSError(28, "No space left on device")).kind == DISK_FULL
    # the words alone (in a file name) are no full disk: an output failure, never the photo's
    assert classify_error(ImageWriteError("cannot write 'No space left on device.tif'")).kind == OUTPUT
    assert classify_error(OSError(16, "Device or resource busy")).kind == TRANSIENT
    locked = ProfileStoreError("store: learn failed: locked by another process for more than 30 s")
    locked.transient = True  # as vigproc.stores.db marks SQLITE_BUSY (a real one: test_faults)
    assert classify_error(locked).kind == TRANSIENT
    f = classify_error(ModuleNotFoundError("No module named 'vigproc.forensics.check'"))
    assert f.kind == PERMANENT and "vigproc.forensics.check" in f.reason
    f = classify_error(ZeroDivisionError("division by zero"))
    assert f.kind == PERMANENT and f.reason.startswith("internal error (ZeroDivisionError")
    assert "\n" not in classify_error(ImageReadError("two\nlines")).reason
    # LibRaw's IO error is about a truncated RAW's data, not the device: no retries
    truncated = ImageReadError("cannot read image 'a.dng': RAW decoding failed (LibRawIOError: Input/output error)")
    assert classify_error(truncated).kind == PERMANENT
    assert classify_error(OSError(5, "Input/output error")).kind == TRANSIENT  # the device's: retried
    # a write failure with no errno and no "no space" in it is the output side's, not the photo's
    assert classify_error(ImageWriteError("cannot write 'x.tif': TIFFWriteScanline failed: Write error")).output_side


def test_text_log_lines_cannot_be_forged_by_file_names():
    import logging

    from vigproc.frontends.daemon import JsonLogFormatter, TextLogFormatter

    rec = logging.LogRecord("vigproc.watch", logging.INFO, __file__, 1, "done %s", ("a\nFAKE ERROR line\r.jpg",), None)
    text = TextLogFormatter().format(rec)
    assert "\n" not in text and "\r" not in text and "a\\nFAKE" in text
    assert json.loads(JsonLogFormatter().format(rec))["msg"] == "done a\nFAKE ERROR line\r.jpg"


def test_settle_tracker_waits_for_a_quiet_file(tmp_path):
    now = [0.0]
    tr = SettleTracker(2.0, clock=lambda: now[0])
    p = tmp_path / "a.jpg"
    p.write_bytes(b"12")
    tr.see(str(p))
    now[0] = 1.9
    assert tr.ripe() == []
    with open(p, "ab") as fh:  # the writer adds a chunk
        fh.write(b"34")
    now[0] = 2.5
    assert tr.ripe() == []  # changed: its clock restarts now
    now[0] = 4.4
    assert tr.ripe() == []
    now[0] = 4.6
    assert tr.ripe() == [str(p)] and len(tr) == 0
    tr.see(str(p))
    p.unlink()
    now[0] = 10.0
    assert tr.ripe() == [] and len(tr) == 0  # gone
    os.mkfifo(tmp_path / "f.jpg")
    tr.see(str(tmp_path / "f.jpg"))
    assert len(tr) == 0  # not a regular file


def test_own_folders_inside_the_watch_folder_are_not_watched(tmp_path):
    from vigproc.frontends.daemon import Daemon as D, WatchConfig

    in_dir = tmp_path / "in"
    cfg = WatchConfig(in_dir=in_dir, out_dir=in_dir / "out", settings={"mode": "correct", "profile": "estimate"},
                      quarantine_dir=in_dir / "q", journal=in_dir / "j.sqlite")
    (in_dir / "sub").mkdir(parents=True)
    cfg.validate()
    d = D(cfg)
    wanted = {rel: d.watcher.wanted(str(cfg.in_dir / rel)) for rel in
              ["a.jpg", "sub/a.png", "out/a.corrected.tif", "q/bad.jpg", "outside.jpg.part", ".cache/a.jpg",
               "@eaDir/a.jpg", "a.txt", "sub/.a.jpg", "output/a.jpg"]}
    assert [r for r, w in wanted.items() if w] == ["a.jpg", "sub/a.png", "output/a.jpg"]
    assert not d.watcher.wanted(str(tmp_path / "elsewhere.jpg"))


def test_archive_and_quarantine_folders_must_be_their_own(tmp_path):
    from vigproc.frontends.daemon import WatchConfig, WatchError

    (tmp_path / "in").mkdir()
    base = dict(in_dir=tmp_path / "in", out_dir=tmp_path / "out", settings={"mode": "correct", "profile": "estimate"})
    for extra in ({"archive_dir": tmp_path / "out"}, {"quarantine_dir": tmp_path / "out"},
                  {"archive_dir": tmp_path / "x", "quarantine_dir": tmp_path / "x"}):
        with pytest.raises(WatchError, match="must differ|cannot be the output folder"):
            WatchConfig(**base, **extra).validate()
    WatchConfig(**base, archive_dir=tmp_path / "a", quarantine_dir=tmp_path / "q").validate()


def test_move_never_overwrites_or_loses(tmp_path):
    src_dir, dst = tmp_path / "in", tmp_path / "archive"
    src_dir.mkdir()
    a = src_dir / "a.jpg"
    a.write_bytes(b"first")
    fa = fingerprint(a)
    assert _move(str(a), dst, "a.jpg", fa) == dst / "a.jpg" and not a.exists()
    a.write_bytes(b"second version")  # same name, other content: kept beside, not over
    fb = fingerprint(a)
    moved = _move(str(a), dst, "a.jpg", fb)
    assert moved != dst / "a.jpg" and moved.read_bytes() == b"second version"
    assert (dst / "a.jpg").read_bytes() == b"first"
    a.write_bytes(b"first")  # a move interrupted after the link: the copy is there already
    assert _move(str(a), dst, "a.jpg", fingerprint(a)) == dst / "a.jpg" and not a.exists()


# ====================================================================== harness
def _image(h: int, w: int, seed: int) -> np.ndarray:
    return np.stack([textured(h, w, seed=seed + c) for c in range(3)], -1).astype(np.float32)


def _write_png_tif(path: Path, seed: int, size=(64, 96)) -> None:
    from vigproc.io.images import write_image

    fmt = "png" if path.suffix.lower() == ".png" else "tiff"
    write_image(path, np.clip(_image(*size, seed), 0, 1), bit_depth="uint16", format=fmt)


def _write_jpeg(path: Path, seed: int, size=(64, 96)) -> None:
    import OpenImageIO as oiio

    data = np.round(255 * np.clip(_image(*size, seed), 0, 1) ** (1 / 2.2)).astype(np.uint8)
    out = oiio.ImageOutput.create(str(path))
    assert out.open(str(path), oiio.ImageSpec(size[1], size[0], 3, oiio.UINT8))
    assert out.write_image(data)
    out.close()


def make_good(stage: Path, rel: str, seed: int) -> Path:
    """A small 3:2 image at ``stage/rel`` (JPEG, PNG or TIFF by suffix)."""
    p = stage / rel
    p.parent.mkdir(parents=True, exist_ok=True)
    sizes = [(64, 96), (96, 144), (160, 240)]
    if p.suffix.lower() in (".jpg", ".jpeg"):
        _write_jpeg(p, seed, sizes[seed % 3])
    else:
        _write_png_tif(p, seed, sizes[seed % 3])
    return p


def sha(p: Path) -> str:
    return hashlib.sha256(p.read_bytes()).hexdigest()


class Daemon:
    """``vigproc watch`` as a subprocess with JSON logs in a file."""

    def __init__(self, in_dir: Path, out_dir: Path, log: Path, *extra: str, env: dict | None = None,
                 workers: int = 2) -> None:
        """``workers``: 2 where two workers at once are part of what is tested, else 1
        (each worker is a new process that loads the pipeline and Numba)."""
        self.in_dir, self.out_dir, self.log = in_dir, out_dir, log
        self.args = [*VIGPROC, "watch", str(in_dir), "-o", str(out_dir), "--workers", str(workers), "--log-json",
                     "--profile", str(PROFILE), "--output-format", "tiff16", "--retry-base", "0.3", *extra]
        self.env = env
        self.proc: subprocess.Popen | None = None

    def start(self, new_session: bool = False) -> Daemon:
        """``new_session``: in a process group of its own, as a terminal runs a command."""
        self._fh = open(self.log, "ab")
        self.proc = subprocess.Popen(self.args, stdout=subprocess.DEVNULL, stderr=self._fh, env=self.env,
                                     start_new_session=new_session)
        return self

    def stop(self, sig=signal.SIGTERM, timeout: float = 90) -> int:
        self.proc.send_signal(sig)
        try:
            return self.proc.wait(timeout=timeout)
        finally:
            self._fh.close()

    def wait(self, timeout: float = 60) -> int:
        try:
            return self.proc.wait(timeout=timeout)
        finally:
            self._fh.close()

    def kill9(self) -> None:
        os.kill(self.proc.pid, signal.SIGKILL)
        self.proc.wait(timeout=30)
        self._fh.close()

    def events(self) -> list[dict]:
        out = []
        for line in self.log.read_bytes().decode("utf-8", "replace").splitlines():
            if line.startswith("{"):
                out.append(json.loads(line))
        return out

    def wait_for(self, what: str, pred, timeout: float = 120) -> None:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if pred():
                return
            if self.proc is not None and self.proc.poll() is not None:
                break
            time.sleep(0.1)
        tail = self.log.read_bytes().decode("utf-8", "replace")[-4000:]
        raise AssertionError(f"timed out waiting for {what} (daemon exit code {self.proc.poll()}); log tail:\n{tail}")


def journal_entries(out_dir: Path) -> dict:
    """path -> Entry of every job in the daemon's default journal."""
    import sqlite3

    db = out_dir / ".vigproc-watch.sqlite"
    if not db.exists():
        return {}
    con = sqlite3.connect(db)
    try:
        jobs = [r[0] for r in con.execute("SELECT DISTINCT job FROM entries")]
    except sqlite3.Error:  # not created yet
        jobs = []
    finally:
        con.close()
    out = {}
    for job in jobs:
        with Journal(db, job=job) as j:
            out.update({e.path: e for e in j.entries()})
    return out


def sidecars(out_dir: Path) -> list[Path]:
    return sorted(out_dir.rglob("*.vigproc.json"))


def out_sidecar(out_dir: Path, rel: str) -> Path:
    """Where the sidecar of the input at ``rel`` goes (the policy of every front end:
    sub-folders mirrored, the input's name kept)."""
    folder, stem = output_location(out_dir, rel, create=False)
    return folder / (stem + ".vigproc.json")


def out_image(out_dir: Path, rel: str, suffix: str = ".tif") -> Path:
    """Where the corrected image of the input at ``rel`` goes, written as ``suffix``."""
    folder, stem = output_location(out_dir, rel, create=False)
    return folder / corrected_name(stem, Path(rel), suffix)


def output_files(out_dir: Path) -> list[str]:
    """Every output file under ``out_dir`` (relative, hidden files and folders left out)."""
    return sorted(str(p.relative_to(out_dir)) for p in out_dir.rglob("*")
                  if p.is_file() and not any(part.startswith(".") for part in p.relative_to(out_dir).parts))


def slow_write(src: Path, dst: Path, chunks: int = 6, pause: float = 0.15) -> threading.Thread:
    """Copy ``src`` to ``dst`` in chunks with pauses (shorter than the settle time)."""
    data = src.read_bytes()

    def run():
        dst.parent.mkdir(parents=True, exist_ok=True)
        step = -(-len(data) // chunks)
        with open(dst, "wb") as fh:
            for i in range(0, len(data), step):
                fh.write(data[i:i + step])
                fh.flush()
                time.sleep(pause)

    t = threading.Thread(target=run)
    t.start()
    return t


# ====================================================================== end to end
GOOD_NAMES = [
    "plain.png", "with space.png", "quote's \"double\".png", "-leading-dash.tif", "ünïcödé 写真.png",
    "new\nline.png", "50%.tif", "100%d.png", "$(touch pwned).png", "sub dir/x.png", "other/x.png", "other/x.tif",
    "deep/a/b/c.tif", "camera one.jpg", "UPPER.PNG", "semi;colon.tif", "back\\slash.png", "tab\there.png",
]
BAD = {  # name -> bytes
    "random.jpg": os.urandom(3000),
    "empty.tif": b"",
    "text.png": b"this is just text, not a PNG\n" * 20,
    "sub dir/fake raw.dng": b"II*\x00" + os.urandom(500),
}
IGNORED = ["~$office.png", ".hidden.png", "downloading.png.crdownload", "in progress.jpg.part", "notes.txt"]


def test_daemon_end_to_end_kill9_restart_and_drain(tmp_path):
    stage, in_dir, out_dir, qdir = (tmp_path / n for n in ("stage", "in", "out", "quarantine"))
    for d in (stage, in_dir):
        d.mkdir()
    log = tmp_path / "daemon.log"
    good: dict[str, str] = {}  # rel -> sha256 of the final content

    def add_good(rel: str, seed: int, how: str = "copy") -> threading.Thread | None:
        src = make_good(stage, f"s{seed}/{Path(rel).name}", seed)
        good[rel] = sha(src)
        dst = in_dir / rel
        dst.parent.mkdir(parents=True, exist_ok=True)
        if how == "slow":
            return slow_write(src, dst)
        if how == "rename":  # a writer that uses a temporary name, then renames
            tmp = dst.with_name(dst.name + ".part")
            shutil.copyfile(src, tmp)
            time.sleep(0.3)
            os.rename(tmp, dst)
            return None
        shutil.copyfile(src, dst)
        return None

    def add_bad(rel: str, data: bytes) -> None:
        (in_dir / rel).parent.mkdir(parents=True, exist_ok=True)
        (in_dir / rel).write_bytes(data)

    for i, name in enumerate(IGNORED):
        p = in_dir / name
        p.write_bytes(b"not for us")
    common = ["--quarantine", str(qdir), "--settle", "0.6"]

    # ---- run 1: native events; files arrive while it runs; killed with SIGKILL mid-run
    d1 = Daemon(in_dir, out_dir, log, *common).start()
    threads = []
    for i, name in enumerate(GOOD_NAMES):
        if i % 6 == 5:
            threads.append(add_good(name, i, "slow"))
        elif i % 6 == 4:
            add_good(name, i, "rename")
        else:
            add_good(name, i)
    for name, data in BAD.items():
        add_bad(name, data)
    # a truncated PNG: a real image cut short
    trunc = make_good(stage, "trunc/truncated.png", 99)
    add_bad("truncated.png", trunc.read_bytes()[: trunc.stat().st_size // 2])
    for t in threads:
        t.join()
    d1.wait_for("a few outputs", lambda: len(sidecars(out_dir)) >= 5)
    d1.kill9()
    worker_pids = [e["worker_pid"] for e in d1.events() if e.get("event") == "worker-ready"]
    assert len(worker_pids) >= 2
    deadline = time.monotonic() + 10
    while any(Path(f"/proc/{p}").exists() and "zombie" not in Path(f"/proc/{p}/status").read_text().lower()
              for p in worker_pids) and time.monotonic() < deadline:
        time.sleep(0.1)
    alive = [p for p in worker_pids if Path(f"/proc/{p}").exists()
             and "zombie" not in Path(f"/proc/{p}/status").read_text().lower()]
    assert alive == [], "workers must die with the daemon (no orphan keeps writing)"
    n_after_kill = len(sidecars(out_dir))

    # ---- while it is down: more files arrive
    for i, name in enumerate(["while down 1.png", "while down/2.tif", "while down 3.jpg"]):
        add_good(name, 100 + i)
    add_bad("while down bad.jpg", b"\xff\xd8\xff\xe0 truncated jpeg")

    # ---- run 2: polling observer; catches up, then SIGTERM while busy must drain and exit 0
    d2 = Daemon(in_dir, out_dir, log, *common, "--poll", "0.3").start()
    n_bad = len(BAD) + 2

    def all_settled() -> bool:
        e = journal_entries(out_dir)
        return (sum(x.state == "done" for x in e.values()) >= len(good)
                and sum(x.state == "quarantined" for x in e.values()) >= n_bad)

    d2.wait_for("every file of run 1 and the downtime", all_settled)
    late = [f"late {i}.png" if i % 3 else f"late {i}.tif" for i in range(8)]
    for i, name in enumerate(late):
        add_good(name, 200 + i)
    d2.wait_for("a late file in progress",
                lambda: any(e.state == "running" for e in journal_entries(out_dir).values()), timeout=60)
    assert d2.stop(signal.SIGTERM) == 0
    entries = journal_entries(out_dir)
    assert not [p for p, e in entries.items() if e.state == "running"], "SIGTERM must drain work in progress"
    for p, e in entries.items():  # whatever a drained run recorded done has its sidecar
        if e.state == "done":
            assert Path(e.result["sidecar"]).is_file()

    # ---- run 3: native events again; finishes the late files; then SIGINT
    d3 = Daemon(in_dir, out_dir, log, *common).start()
    d3.wait_for("the late files",
                lambda: sum(e.state == "done" for e in journal_entries(out_dir).values()) >= len(good))
    time.sleep(1.0)  # give a wrongly taken ignored file the chance to show up
    assert d3.stop(signal.SIGINT) == 0

    # ================= the checks
    entries = journal_entries(out_dir)
    in_root = in_dir.resolve()
    # every good file: done, exactly one output + sidecar for its final content, input untouched
    outputs = output_files(out_dir)
    expected = sorted([str(out_image(out_dir, rel).relative_to(out_dir)) for rel in good]
                      + [str(out_sidecar(out_dir, rel).relative_to(out_dir)) for rel in good])
    assert outputs == expected
    for rel, digest in good.items():
        path = str(in_root / rel)
        e = entries[path]
        assert e.state == "done", (rel, e.state, e.reason)
        assert sha(in_dir / rel) == digest  # inputs never modified, nor moved
        sc = json.loads(out_sidecar(out_dir, rel).read_text())
        assert sc["input_sha256"] == digest and sc["input"] == rel and sc["source"] == "profile-file"
        assert Path(sc["output"]) == out_image(out_dir, rel)
        assert e.claims <= 2
    # a good file is handed out twice only if it was in flight when killed (2 workers x 2 queued)
    assert sum(entries[str(in_root / rel)].claims > 1 for rel in good) <= 4
    # nothing done twice: at most one "done" event per file and content over the three runs
    # (a log line can be lost to the SIGKILL after its journal commit, never repeated; a
    # writer that stalled past --settle may have had a partial version done before)
    events = d3.events()
    done_by_version = Counter((ev["file"], ev["sha256"]) for ev in events if ev.get("event") == "done")
    assert {v: n for v, n in done_by_version.items() if n > 1} == {}
    assert {f for f, _ in done_by_version} <= {str(in_root / rel) for rel in good}
    # every bad file quarantined with a reason, moved to the quarantine folder with its reason file
    bad = [*BAD, "truncated.png", "while down bad.jpg"]
    for rel in bad:
        e = entries[str(in_root / rel)]
        assert e.state == "quarantined" and e.reason and "cannot read" in e.reason, (rel, e.state, e.reason)
        assert not (in_dir / rel).exists()
        assert (qdir / output_stem(rel)).is_file()
        why = json.loads((qdir / (output_stem(rel) + ".reason.json")).read_text())
        assert why["reason"] == e.reason
    # writers' temporary names and other files were never touched
    for name in IGNORED:
        assert (in_dir / name).read_bytes() == b"not for us"
        assert str(in_root / name) not in entries
    assert set(entries) == {str(in_root / r) for r in [*good, *bad]}
    # no temporary leftovers in the output folder
    assert [p.name for p in out_dir.iterdir() if ".tmp" in p.name] == []
    assert n_after_kill >= 5
    # --status: a stopped daemon, with the journal's counts (asked in this process)
    st = run_cli("watch", in_dir, "-o", out_dir, "--profile", PROFILE, "--status", "--json")
    assert st.returncode == 3, st.stderr
    status = json.loads(st.stdout)
    assert status["running"] is False
    assert status["journal_counts"]["done"] == len(good)
    assert status["journal_counts"]["quarantined"] == len(bad)
    assert status["daemon"]["state"] == "stopped"


# ====================================================================== faults
_PATCH_ON_IMPORT = r'''
import importlib.abc, importlib.machinery, sys


class _Finder(importlib.abc.MetaPathFinder):
    def find_spec(self, name, path, target=None):
        if name != MODULE:
            return None
        sys.meta_path.remove(self)
        spec = importlib.machinery.PathFinder.find_spec(name, path)
        run = spec.loader.exec_module

        def exec_module(module):
            run(module)
            _patch(module)

        spec.loader.exec_module = exec_module
        return spec


sys.meta_path.insert(0, _Finder())
'''


def sitecustomize(module: str, faults: str) -> str:
    """A ``sitecustomize`` for every process of a daemon: ``faults`` (which defines
    ``_patch(module)``) applied to ``module`` as soon as it is imported."""
    return faults + _PATCH_ON_IMPORT.replace("MODULE", repr(module))


_FAULTS = sitecustomize("vigproc.pipeline.processor", r'''
"""Test-only faults, injected into every vigproc process through sitecustomize."""
import os, time

MARK = os.environ["VIGPROC_TEST_FAULT_DIR"]


def _patch(module):
    orig = module.Processor.process_file

    def process_file(self, path, *a, **kw):
        name = os.path.basename(str(path))
        if "CRASH" in name or "DECODE" in name:
            os._exit(3)  # as a decoder segfault would
        if "HANG" in name:
            time.sleep(3600)
        if "FULL" in name:
            marker = os.path.join(MARK, "full-count")
            n = int(open(marker).read()) if os.path.exists(marker) else 0
            if n < 2:
                open(marker, "w").write(str(n + 1))
                import errno
                from vigproc.errors import write_error
                raise write_error(f"cannot write output of {name}: No space left on device",
                                  OSError(errno.ENOSPC, os.strerror(errno.ENOSPC)))
        return orig(self, path, *a, **kw)

    module.Processor.process_file = process_file
    read_counted = module._read_counted

    def _read_counted(path, *a, **kw):  # the read ahead, in a worker's thread
        if "DECODE" in os.path.basename(str(path)):
            os._exit(3)
        return read_counted(path, *a, **kw)

    module._read_counted = _read_counted
    prefetch = module.Processor.prefetch

    def prefetch_(self, path, *a, **kw):  # the read ahead's EXIF, in the worker's own thread
        if "AHEADHANG" in os.path.basename(str(path)):
            time.sleep(3600)  # as an exiftool stuck on it would hold the running file's reads
        return prefetch(self, path, *a, **kw)

    module.Processor.prefetch = prefetch_
    read_ahead = module.Processor.read_ahead

    def read_ahead_(self, path, *a, **kw):  # what the worker holds read ahead when it reads one more
        with open(os.path.join(MARK, "ahead.log"), "a") as fh:
            fh.write(repr([os.path.basename(p) for p, *_ in self._ahead]) + " " + os.path.basename(str(path)) + "\n")
        return read_ahead(self, path, *a, **kw)

    module.Processor.read_ahead = read_ahead_
''')


def _faulty_folders(tmp_path: Path) -> tuple[Path, Path, Path, dict[str, str]]:
    """tmp_path's stage, in and out folders, and the environment of a daemon whose
    processes run with the faults of ``_FAULTS``."""
    stage, in_dir, out_dir = (tmp_path / n for n in ("stage", "in", "out"))
    for d in (stage, in_dir, tmp_path / "site"):
        d.mkdir()
    (tmp_path / "site" / "sitecustomize.py").write_text(_FAULTS)
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(tmp_path / "site"), os.environ.get("PYTHONPATH", "")]),
           "VIGPROC_TEST_FAULT_DIR": str(tmp_path)}
    return stage, in_dir, out_dir, env


def test_worker_crash_hang_and_full_disk(tmp_path):
    """A worker that dies on a file, a full output disk, then a worker that hangs.

    The hang is a phase of its own, the only file in the folder: ``--timeout`` is a
    wall clock, so a good file beside it could overrun any timeout on a loaded machine
    and be charged a crash (4 s did, on a fresh clone under load).  Nothing here waits
    for a time to pass: every step waits for what the daemon records."""
    stage, in_dir, out_dir, env = _faulty_folders(tmp_path)
    names = ["a CRASH.png", "c FULL.png", "d ok.png", "e ok.tif", "f ok.png"]
    for i, n in enumerate([*names, "b HANG.png"]):
        make_good(stage, n, i)

    def finished(count: int):
        def pred() -> bool:
            e = journal_entries(out_dir)
            return len(e) == count and all(x.state in ("done", "quarantined") for x in e.values())
        return pred

    # 1. a crash and a full disk among good files (no --timeout: the default leaves them all the time they need)
    d = Daemon(in_dir, out_dir, tmp_path / "daemon.log", "--settle", "0.3", "--max-crashes", "2", env=env).start()
    for n in names:
        shutil.copyfile(stage / n, in_dir / n)
    d.wait_for("all files finished", finished(len(names)), timeout=150)
    assert d.stop() == 0
    # 2. a hang, alone: the timeout can only be the hung file's
    d = Daemon(in_dir, out_dir, tmp_path / "daemon.log", "--settle", "0.3", "--timeout", "2", "--max-crashes", "2",
               env=env).start()
    shutil.copyfile(stage / "b HANG.png", in_dir / "b HANG.png")
    d.wait_for("the hung file quarantined", finished(len(names) + 1), timeout=150)
    assert d.stop() == 0

    e = {Path(p).name: x for p, x in journal_entries(out_dir).items()}
    assert e["a CRASH.png"].state == "quarantined" and "died" in e["a CRASH.png"].reason
    assert e["b HANG.png"].state == "quarantined" and "timed out" in e["b HANG.png"].reason
    # a full disk pauses the daemon and gives the file back without an attempt: not its fault
    assert e["c FULL.png"].state == "done" and e["c FULL.png"].attempts == 0
    assert {ev["file"] for ev in d.events() if ev.get("event") == "disk-full"} == {str(in_dir.resolve() / "c FULL.png")}
    for n in ("d ok.png", "e ok.tif", "f ok.png"):
        # a file queued behind a crash goes back without an attempt counted against it
        assert e[n].state == "done" and e[n].attempts == 0 and e[n].crashes == 0
    assert len(sidecars(out_dir)) == 4
    restarts = [ev for ev in d.events() if ev.get("event") == "worker-restart"]
    # two charged crashes and two hangs restarted workers, the daemon never fell over; a
    # crash while the daemon was paused on the (faked) full disk is not charged to the file
    # (issue 37), and restarts its worker too -- but only once per pause: as the probe, or a
    # second time, the crash is the file's (else it could be probed, uncharged, for ever: 8
    # restarts were seen).  4 restarts, one more for each of the (at most two) pauses it fell in
    # -- and one more for each death with a file read ahead beside the crashing one (not charged)
    pauses = sum(ev.get("event") == "disk-full" for ev in d.events())
    shared = sum(ev.get("event") == "worker-died-open" for ev in d.events())
    assert e["a CRASH.png"].crashes == 2 and 4 + shared <= len(restarts) <= 4 + shared + pauses
    assert sum(ev.get("event") == "timeout" for ev in d.events()) == 2


def _one_worker_run(tmp_path, names: list[str], *args: str, timeout: float) -> dict:
    """Drop ``names`` (good PNGs; a name's marker makes the faulty exiftool misbehave on it)
    into a one-worker daemon (--max-crashes 2, ``args``), wait until every file is done or
    quarantined, stop it cleanly; the journal's entries by file name."""
    stage, in_dir, out_dir, env = _faulty_folders(tmp_path)
    for i, n in enumerate(names):
        make_good(stage, n, i)
    d = Daemon(in_dir, out_dir, tmp_path / "daemon.log", "--settle", "0.3", "--workers", "1", "--max-crashes", "2",
               *args, env=env).start()
    for n in names:
        shutil.copyfile(stage / n, in_dir / n)

    def finished() -> bool:
        e = journal_entries(out_dir)
        return len(e) == len(names) and all(x.state in ("done", "quarantined") for x in e.values())

    d.wait_for("all files finished", finished, timeout=timeout)
    assert d.stop() == 0
    return {Path(p).name: x for p, x in journal_entries(out_dir).items()}


def test_a_worker_killed_by_the_file_it_reads_ahead_charges_no_other_file(tmp_path):
    """A worker reads its next file ahead while it processes one (a core to spare): a
    file whose decoding kills its worker, there or when processed, is charged its
    crashes (quarantined after --max-crashes) and the files open beside it are not:
    each death with two files open charges neither, and both are tried again alone."""
    names = ["a ok.png", "b ok.png", "c DECODE.png", "d ok.png", "e ok.png"]
    e = _one_worker_run(tmp_path, names, timeout=150)
    assert e["c DECODE.png"].state == "quarantined" and e["c DECODE.png"].crashes == 2
    for n in names:
        if n != "c DECODE.png":
            assert e[n].state == "done" and e[n].crashes == 0 and e[n].attempts == 0, (n, e[n])


def test_a_file_that_hangs_its_worker_when_read_ahead_charges_no_other_file(tmp_path):
    """A hang while a file is read ahead is not the running file's: the worker is stopped
    at the running file's --timeout, but either file may have held it (an exiftool stuck
    on the one read ahead holds the running file's reads), so neither is charged and both
    are tried again alone, where the hung file is timed out and charged on its own."""
    names = ["a ok.png", "b AHEADHANG.png", "c ok.png"]
    e = _one_worker_run(tmp_path, names, "--timeout", "6", timeout=240)
    hung = e["b AHEADHANG.png"]
    assert hung.state == "quarantined" and hung.crashes == 2 and "timed out" in hung.reason, hung
    for n in ("a ok.png", "c ok.png"):
        assert e[n].state == "done" and e[n].crashes == 0 and e[n].attempts == 0, (n, e[n])


def test_a_file_read_ahead_and_done_by_its_sidecar_is_not_held(tmp_path):
    """A file read ahead whose task ends without reading it (an earlier run's sidecar
    answers: done before a kill, not yet in the journal) leaves nothing read ahead behind:
    the worker holds at most the running file's frame and the next one's, not a third."""
    stage, in_dir, out_dir, env = _faulty_folders(tmp_path)
    names = ["a ok.png", "b ok.png", "c ok.png", "d ok.png", "e ok.png"]
    for i, n in enumerate(names):
        make_good(stage, n, i)
    args = ("--settle", "0.3", "--workers", "1")
    d = Daemon(in_dir, out_dir, tmp_path / "daemon.log", *args, env=env).start()
    shutil.copyfile(stage / "c ok.png", in_dir / "c ok.png")
    d.wait_for("c done", lambda: any(x.state == "done" for x in journal_entries(out_dir).values()))
    assert d.stop() == 0
    for f in out_dir.glob(".vigproc-watch.sqlite*"):  # its sidecar stays: done, as if killed before the journal said so
        f.unlink()
    (in_dir / "c ok.png").unlink()  # copied again below, in its turn: read ahead while b runs
    (tmp_path / "ahead.log").unlink(missing_ok=True)
    d = Daemon(in_dir, out_dir, tmp_path / "daemon.log", *args, env=env).start()
    for n in names:
        shutil.copyfile(stage / n, in_dir / n)

    def finished() -> bool:
        e = journal_entries(out_dir)
        return len(e) == len(names) and all(x.state == "done" for x in e.values())

    d.wait_for("all files done", finished)
    assert d.stop() == 0
    held = (tmp_path / "ahead.log").read_text().splitlines()
    assert any(line.endswith("] c ok.png") for line in held), held  # c was read ahead
    for line in held:  # what it held before reading one more: the running file's frame at most
        assert len(ast.literal_eval(line[:line.rindex("]") + 1])) <= 1, held


def test_bad_arguments_are_refused_with_one_line(tmp_path, monkeypatch):
    """(A second daemon on the same folders, and ``--status`` of a running one:
    test_audit_daemon.test_a_second_daemon_on_the_same_folders_is_refused_in_every_variant.)"""
    from vigproc.frontends.daemon import Daemon as D

    in_dir, out_dir = tmp_path / "in", tmp_path / "out"
    in_dir.mkdir()
    monkeypatch.setattr(D, "run", no_daemon_here)
    # (--workers 0 is a usage error, exit 2, with the other bad option values in test_cli)
    for args, msg in [
        ([str(tmp_path / "missing"), "-o", str(out_dir)], "does not exist"),
        ([str(in_dir), "-o", str(in_dir)], "cannot be the watch folder"),
        ([str(in_dir), "-o", str(out_dir), "--profile", str(tmp_path / "nope.json")], "nope.json"),
    ]:
        r = run_cli("watch", *args)  # in this process: a check that let one through fails the test, not hangs it
        assert r.returncode != 0 and msg in r.stderr and "Traceback" not in r.stderr, (args, r.stderr)
        assert len(r.stderr.strip().splitlines()) == 1


def no_daemon_here(self) -> int:
    """``Daemon.run`` for a test that runs ``vigproc watch`` in the test process: the
    arguments were to be refused, so reaching the daemon's loop fails the test."""
    raise AssertionError("the arguments were accepted: a daemon would start in the test process")


def test_a_profile_source_is_not_a_profile_file(tmp_path):
    """``--profile source:NAME`` names a profile-source plugin: watch took it for the file
    OUT/../source:foo and refused to start (exit 8, issue 23). It now does what batch
    does with the same argument: the frame fails for good, the plugin being unknown."""
    in_dir, out_dir = tmp_path / "in", tmp_path / "out"
    in_dir.mkdir()
    make_good(in_dir, "a.png", 0)
    db = ("--profile-db", str(tmp_path / "p.sqlite"))
    b = run_cli("batch", in_dir, "--mode", "correct", "-o", tmp_path / "batch", "--profile", "source:foo", *db,
                "--workers", "1")
    assert b.returncode == 1 and "a.png: unknown profile source 'foo'" in b.stdout + b.stderr, b.stderr
    d = Daemon(in_dir, out_dir, tmp_path / "daemon.log", "--profile", "source:foo", "--settle", "0.2", *db,
               workers=1).start()
    d.wait_for("the file quarantined", lambda: [e.state for e in journal_entries(out_dir).values()] == ["quarantined"],
               timeout=120)
    assert d.stop() == 0
    [entry] = journal_entries(out_dir).values()
    assert entry.reason.startswith("unknown profile source 'foo'"), entry.reason


@pytest.mark.skipif(shutil.which("exiftool") is None, reason="the DNG fixture needs exiftool for its EXIF")
def test_learn_mode_pools_each_frame_once_across_a_kill(tmp_path):
    from dngfixture import make_dngs

    from benchmarks.synthetic import table1_model
    from vigproc.stores.profiles import ProfileStore

    in_dir, out_dir, db = tmp_path / "in", tmp_path / "out", tmp_path / "profiles.sqlite"
    in_dir.mkdir()
    truth = table1_model(1).rescale(192, 128)
    n = 4
    make_dngs([(in_dir / f"frame {i}.dng", dict(width=192, height=128, field=truth.field(),
                                               scene=textured(128, 192, seed=i, contrast=0.2), seed=i))
               for i in range(n)])
    args = ("--mode", "learn", "--profile-db", str(db), "--settle", "0.2")
    # one worker: the kill is the point (two workers pooling at once: test_learn_as_you_go's watch and batch)
    d = Daemon(in_dir, out_dir, tmp_path / "daemon.log", *args, workers=1).start()
    d.wait_for("one frame learned", lambda: len(sidecars(out_dir)) >= 1, timeout=120)
    d.kill9()
    d = Daemon(in_dir, out_dir, tmp_path / "daemon.log", *args, workers=1).start()
    d.wait_for("all frames learned", lambda: sum(e.state == "done" for e in journal_entries(out_dir).values()) == n,
               timeout=180)
    assert d.stop() == 0
    with ProfileStore(db) as store:
        profiles = store.list()
    assert len(profiles) == 1 and profiles[0].n_frames == n  # each frame pooled exactly once
    for sc in sidecars(out_dir):
        rec = json.loads(sc.read_text())
        assert rec["mode"] == "learn" and rec["profile"] == str(profiles[0].key)


def test_check_mode_gives_a_verdict_or_a_clear_per_file_error(tmp_path):
    import importlib.util

    in_dir, out_dir = tmp_path / "in", tmp_path / "out"
    in_dir.mkdir()
    for i in range(2):
        make_good(in_dir, f"c{i}.png", i)
    d = Daemon(in_dir, out_dir, tmp_path / "daemon.log", "--mode", "check", "--settle", "0.2",
               "--profile-db", str(tmp_path / "p.sqlite"), workers=1).start()
    d.wait_for("both files finished", lambda: sum(e.state in ("done", "quarantined")
                                                  for e in journal_entries(out_dir).values()) == 2, timeout=120)
    assert d.stop() == 0
    entries = journal_entries(out_dir).values()
    if importlib.util.find_spec("vigproc.forensics.check") is None:
        for e in entries:
            assert e.state == "quarantined" and "vigproc.forensics.check" in e.reason
    else:  # a verdict, or a clear reason why this installation cannot give one (e.g. no calibration)
        for e in entries:
            if e.state == "done":
                assert "verdict" in json.loads(Path(e.result["sidecar"]).read_text())
            else:
                assert e.reason and not e.reason.startswith("internal error"), e.reason


def test_archive_moves_done_inputs_only(tmp_path):
    in_dir, out_dir, arch, qdir = (tmp_path / n for n in ("in", "out", "archive", "quarantine"))
    in_dir.mkdir()
    digests = {}
    for i, rel in enumerate(["a.png", "sub/b.tif", "sub/c.png"]):
        digests[rel] = sha(make_good(in_dir, rel, i))
    (in_dir / "bad.png").write_bytes(b"not a png")
    (in_dir / "keep.txt").write_bytes(b"not an image")
    d = Daemon(in_dir, out_dir, tmp_path / "daemon.log", "--settle", "0.2", "--archive", str(arch),
               "--quarantine", str(qdir), workers=1).start()
    d.wait_for("everything moved", lambda: sorted(p.name for p in in_dir.rglob("*") if p.is_file()) == ["keep.txt"],
               timeout=120)
    assert d.stop() == 0
    for rel, digest in digests.items():  # archived under the same relative path, content intact
        assert sha(arch / rel) == digest
        assert out_image(out_dir, rel).is_file()
    assert (qdir / "bad.png").read_bytes() == b"not a png" and not (arch / "bad.png").exists()
    # a restart neither re-processes nor re-moves anything
    d = Daemon(in_dir, out_dir, tmp_path / "daemon.log", "--settle", "0.2", "--archive", str(arch), workers=1).start()
    d.wait_for("the second start", lambda: sum(ev.get("event") == "start" for ev in d.events()) == 2, timeout=60)
    time.sleep(1)
    assert d.stop() == 0
    assert Counter(ev.get("event") for ev in d.events())["done"] == len(digests)


def test_quarantine_reason_follows_a_clash_renamed_file(tmp_path):
    """A second bad file of the same name is kept beside the first, each with its own reason."""
    in_dir, out_dir, qdir = (tmp_path / n for n in ("in", "out", "quarantine"))
    in_dir.mkdir()
    d = Daemon(in_dir, out_dir, tmp_path / "daemon.log", "--settle", "0.2", "--quarantine", str(qdir),
               workers=1).start()
    first, second = b"just text, not a JPEG\n", b"other text, not a JPEG either\n"
    digests = [hashlib.sha256(b).hexdigest() for b in (first, second)]
    (in_dir / "text.jpg").write_bytes(first)
    d.wait_for("the first file quarantined", lambda: (qdir / "text.jpg").is_file() and not (in_dir / "text.jpg").exists())
    (in_dir / "text.jpg").write_bytes(second)
    renamed = qdir / f"text.{digests[1][:12]}.jpg"
    d.wait_for("the second file quarantined", lambda: renamed.is_file() and not (in_dir / "text.jpg").exists())
    assert d.stop() == 0
    assert (qdir / "text.jpg").read_bytes() == first and renamed.read_bytes() == second
    for moved, digest in zip((qdir / "text.jpg", renamed), digests):
        why = json.loads(moved.with_name(moved.name + ".reason.json").read_text())
        assert why["sha256"] == digest and why["file"] == "text.jpg" and "cannot read" in why["reason"]
    assert sorted(p.name for p in qdir.iterdir()) == sorted(
        ["text.jpg", "text.jpg.reason.json", renamed.name, renamed.name + ".reason.json"])


def test_a_replaced_file_that_fails_names_the_outputs_of_its_earlier_content(tmp_path):
    """A good photo is corrected, then replaced by a broken file of the same name: the
    earlier outputs stay (they were right for what the file held), and the quarantine
    reason and the log say they are not of the content quarantined."""
    in_dir, out_dir, qdir = (tmp_path / n for n in ("in", "out", "quarantine"))
    in_dir.mkdir()
    d = Daemon(in_dir, out_dir, tmp_path / "daemon.log", "--settle", "0.2", "--quarantine", str(qdir),
               workers=1).start()
    make_good(tmp_path / "stage", "a.png", seed=3).replace(in_dir / "a.png")
    sidecar = out_sidecar(out_dir, "a.png")
    d.wait_for("the photo corrected", sidecar.is_file)
    first = json.loads(sidecar.read_text())
    (in_dir / "a.png").write_bytes(b"no longer a PNG\n")
    d.wait_for("the broken file quarantined", lambda: (qdir / "a.png").is_file())
    assert d.stop() == 0
    assert json.loads(sidecar.read_text()) == first and Path(first["output"]).is_file()  # kept
    why = json.loads((qdir / "a.png.reason.json").read_text())
    assert why["earlier_outputs"] == [str(sidecar), first["output"]]
    assert any(ev.get("event") == "earlier-outputs" for ev in d.events())


# ====================================================================== kills, signals, leftovers
def _exiftool_env(tmp_path: Path, then: str) -> tuple[dict, Path]:
    """An environment whose metadata-copying exiftool (``VIGPROC_EXIFTOOL``) first writes its
    arguments to ``marks/<pid>``, then runs the shell command ``then``; and ``marks``.  Every
    process started with it carries the tag, so that none can hide from :func:`_alive`."""
    marks = tmp_path / "marks"
    marks.mkdir()
    script = tmp_path / "slow-exiftool"
    script.write_text(f'#!/bin/sh\necho "$@" > "{marks}/$$"\n{then}\n')
    script.chmod(0o755)
    return {**os.environ, "VIGPROC_EXIFTOOL": str(script), "VIGPROC_TEST_TAG": str(tmp_path)}, marks


def _alive(tag: str) -> list[str]:
    """Command lines of the live (not zombie) processes whose environment holds ``VIGPROC_TEST_TAG=tag``."""
    out = []
    for proc in Path("/proc").iterdir():
        try:
            if f"VIGPROC_TEST_TAG={tag}".encode() not in (proc / "environ").read_bytes().split(b"\0"):
                continue
            if (proc / "stat").read_text().rsplit(")", 1)[1].split()[0] != "Z":
                out.append((proc / "cmdline").read_bytes().replace(b"\0", b" ").decode("utf-8", "replace"))
        except OSError:  # not a process, gone, or not ours
            continue
    return out


def _none_alive(tag: str, timeout: float = 10) -> list[str]:
    deadline = time.monotonic() + timeout
    while (alive := _alive(tag)) and time.monotonic() < deadline:
        time.sleep(0.1)
    return alive


def _temps(out_dir: Path) -> set[str]:
    return {p.name for p in out_dir.iterdir() if p.name.startswith(".") and ".tmp" in p.name}


def test_kill9_charges_no_file_and_leaves_no_process(tmp_path):
    """kill -9 of the daemon while a.png is in progress and b.png is queued behind it on
    the one worker, three times.  Issue 22: each kill used to charge a.png a crash and
    the third quarantined it; the daemon's own death is not the file's fault, so neither
    file is charged and both end done (a worker dying on a file while the daemon lives
    is still charged: test_worker_crash_hang_and_full_disk).  No worker or exiftool
    outlives the daemon, and the in-progress mark names the daemon that ran it."""
    in_dir, out_dir, qdir = tmp_path / "in", tmp_path / "out", tmp_path / "quarantine"
    a, b = (str(make_good(in_dir, n, i).resolve()) for i, n in enumerate(["a.png", "b.png"]))
    env, marks = _exiftool_env(tmp_path, "exec sleep 60")  # a.png is stuck in its metadata copy
    args = ("--workers", "1", "--settle", "0.2", "--max-crashes", "2", "--quarantine", str(qdir))
    log = tmp_path / "daemon.log"

    def a_started_b_queued(pid: int) -> bool:
        e = journal_entries(out_dir)
        return (any(marks.iterdir()) and a in e and e[a].state == "running" and e[a].started
                and (e[a].runner or {}).get("pid") == pid and b in e and e[b].state == "running")

    for k in range(3):
        for m in marks.iterdir():
            m.unlink()
        d = Daemon(in_dir, out_dir, log, *args, env=env).start()
        d.wait_for(f"a.png in progress, b.png queued (run {k + 1})", lambda: a_started_b_queued(d.proc.pid),
                   timeout=60)
        d.kill9()
        assert _none_alive(str(tmp_path)) == [], "workers and exiftool must die with the daemon"
    n_events = len(d.events())
    d = Daemon(in_dir, out_dir, log, *args).start()  # the real exiftool again
    d.wait_for("both done", lambda: all(journal_entries(out_dir)[p].state == "done" for p in (a, b)), timeout=60)
    assert d.stop() == 0
    e = journal_entries(out_dir)
    for p in (a, b):
        assert e[p].crashes == 0 and e[p].attempts == 0 and e[p].claims == 4, (p, e[p])
    assert (in_dir / "a.png").is_file() and list(qdir.iterdir()) == []
    events = d.events()[n_events:]
    assert not [ev for ev in events if ev.get("event") == "quarantined"]
    assert {ev["file"] for ev in events if ev.get("event") == "recovered"} == {a, b}


def test_ctrl_c_to_the_process_group_drains_without_quarantining(tmp_path):
    """Ctrl-C in a terminal signals the daemon's whole process group: the files in progress
    are finished (their exiftool is not in that group), and one whose exiftool a stop
    signal killed anyway (systemd may signal every process) is finished too: the worker's
    persistent exiftool is restarted and the copy retried once, without an attempt charged."""
    in_dir, out_dir, stage = tmp_path / "in", tmp_path / "out", tmp_path / "stage"
    in_dir.mkdir()
    # a slow exiftool: like the real one, it exits on SIGINT even though the worker ignores it.
    # The persistent one is sent its commands on stdin: this one logs them to its mark, takes
    # 3 s over each write, and hands them on to the real exiftool
    slow = ("exec perl -e '$SIG{INT} = sub { exit 1 }; open(my $log, \">>\", shift) or die; "
            "my $pid = open(my $et, \"|-\", @ARGV) or die; $SIG{TERM} = sub { kill 9, $pid; exit 1 }; "
            "select((select($et), $| = 1)[0]); "
            "select((select($log), $| = 1)[0]); while (my $l = <STDIN>) { print $log $l; "
            "sleep 3 if $l =~ /^-overwrite_original/; print $et $l } close $et' "
            f"\"{tmp_path}/marks/$$\" exiftool \"$@\"")
    env, marks = _exiftool_env(tmp_path, slow)
    d = Daemon(in_dir, out_dir, tmp_path / "daemon.log", "--settle", "0.2", env=env).start(new_session=True)
    d.wait_for("both workers", lambda: sum(ev.get("event") == "worker-ready" for ev in d.events()) == 2, timeout=60)
    for i, n in enumerate(["a.png", "b.png"]):  # one per worker
        shutil.copyfile(make_good(stage, n, i), in_dir / n)

    def copying() -> dict[str, int]:
        """Input name -> pid of the exiftool copying its metadata."""
        return {n: int(m.name) for m in marks.iterdir() for n in ("a.png", "b.png") if n in m.read_text()}

    d.wait_for("both files in their metadata copy", lambda: len(copying()) == 2, timeout=60)
    os.killpg(d.proc.pid, signal.SIGINT)  # what a terminal's Ctrl-C does
    os.kill(copying()["b.png"], signal.SIGTERM)
    assert d.wait() == 0
    e = {Path(p).name: x for p, x in journal_entries(out_dir).items()}
    assert e["a.png"].state == "done", e["a.png"].reason
    assert e["b.png"].state == "done" and e["b.png"].attempts == 0, (e["b.png"].state, e["b.png"].reason)
    assert not [ev for ev in d.events() if ev.get("event") == "quarantined"]
    assert len(list(marks.iterdir())) == 3  # one exiftool per worker, and b.png's restarted once


def test_temporaries_of_killed_writers_are_removed(tmp_path):
    """Temporary files are removed when their writer is killed: left by an earlier run for a
    file that is now pending (at start), of a killed worker (at once), after an abort."""
    in_dir, out_dir = tmp_path / "in", tmp_path / "out"
    for i, n in enumerate(["a.png", "b.png"]):
        make_good(in_dir, n, i)
    out_dir.mkdir()
    b = str((in_dir / "b.png").resolve())
    with Journal(out_dir / ".vigproc-watch.sqlite", job=f"watch:correct:{in_dir.resolve()}->{out_dir.resolve()}") as j:
        fp = fingerprint(b)
        assert j.claim(b, fp, worker="an earlier run") and j.failed(b, fp, "busy", transient=True) == "retry"
    stale = {".b.png.corrected.tif.tmp-x1.tif", "..b.png.corrected.tif.tmp-x1.tif.tmp-y2.tif",
             ".b.png.corrected.tif.tmp-x1.tif_exiftool_tmp", ".b.png.vigproc.tmp.json"}
    foreign = {".c.png.corrected.tif.tmp-z.tif", ".b.png notes.txt"}  # another input's; not a temporary
    for name in stale | foreign:
        (out_dir / name).write_bytes(b"x")
    env, marks = _exiftool_env(tmp_path, "exec sleep 60")  # every file gets stuck in its metadata copy
    d = Daemon(in_dir, out_dir, tmp_path / "daemon.log", "--workers", "1", "--settle", "0.2", env=env).start()
    # exiftool starts with the worker (Processor.prepare), so its mark alone does not say a
    # file reached its metadata copy: the file's own temporary does
    d.wait_for("a file in its metadata copy", lambda: _temps(out_dir) - foreign - stale, timeout=60)
    assert not stale & set(p.name for p in out_dir.iterdir())
    assert foreign <= set(p.name for p in out_dir.iterdir())
    first = _temps(out_dir) - foreign
    assert first, "the file in progress is being written to a temporary"
    # the daemon logs a worker's "ready" when its loop reads the message, which under load can
    # come after the worker has already taken the file and written its temporary
    d.wait_for("the worker's ready event", lambda: any(ev.get("event") == "worker-ready" for ev in d.events()))
    worker = [ev["worker_pid"] for ev in d.events() if ev.get("event") == "worker-ready"][0]
    for m in marks.iterdir():
        m.unlink()
    os.kill(worker, signal.SIGKILL)
    d.wait_for("the worker restarted", lambda: any(ev.get("event") == "worker-restart" for ev in d.events()))
    assert not first & _temps(out_dir)
    d.wait_for("the next file in its metadata copy", lambda: _temps(out_dir) - foreign, timeout=60)
    d.proc.send_signal(signal.SIGINT)  # twice: abort
    time.sleep(0.2)
    d.proc.send_signal(signal.SIGINT)
    assert d.wait() == 1
    assert _temps(out_dir) <= foreign
    assert _none_alive(str(tmp_path)) == []

