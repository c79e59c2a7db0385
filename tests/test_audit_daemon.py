"""Issue 37's audit, replayed: a second daemon on one job (same folders; ``--journal
elsewhere``; after ``rm -rf OUT``), a stalled hook client against the warm server, and
hostile names through ``batch``'s messages. Loopback and temporary folders only; every
wait is a hang guard with a generous bound, not a timing."""

from __future__ import annotations

import os
import shutil
import signal
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from conftest import photo_like, run_cli
from vigproc.frontends import hookserver
from vigproc.io.images import write_image

REPO = Path(__file__).resolve().parents[1]
PROFILE = REPO / "profiles" / "examples" / "sony-rx100-10.4mm-f1.8.json"
VIGPROC = [sys.executable, "-m", "vigproc.frontends.cli"]


@pytest.fixture
def env(tmp_path, monkeypatch):
    """A private lock folder, hook runtime folder and profile store for this test."""
    monkeypatch.setenv("VIGPROC_LOCK_DIR", str(tmp_path / "locks"))
    monkeypatch.setenv("VIGPROC_PROFILE_DB", str(tmp_path / "profiles.sqlite"))
    monkeypatch.setenv(hookserver.ENV_DIR, str(tmp_path / "run"))
    monkeypatch.setenv("PYTHONPATH", os.pathsep.join([str(REPO), os.environ.get("PYTHONPATH", "")]))
    return os.environ.copy()


def _watch(in_dir, out_dir, log, *extra, env):
    fh = open(log, "ab")
    proc = subprocess.Popen([*VIGPROC, "watch", str(in_dir), "-o", str(out_dir), "--profile", str(PROFILE),
                             "--workers", "1", "--settle", "0.2", "--log-json", *extra],
                            stdout=subprocess.DEVNULL, stderr=fh, env=env)
    fh.close()
    return proc


def _wait_started(proc, log, timeout=90):
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if '"event": "start"' in log.read_text("utf-8", "replace"):
            return
        assert proc.poll() is None, log.read_text("utf-8", "replace")[-3000:]
        time.sleep(0.1)
    raise AssertionError("the daemon did not start: " + log.read_text("utf-8", "replace")[-3000:])


def _second(in_dir, out_dir, *extra, env):
    """A second ``vigproc watch`` on the job, in this process (``env`` is this process's
    environment, set by the ``env`` fixture): refused, or the test fails (not_here)."""
    return run_cli("watch", in_dir, "-o", out_dir, "--profile", PROFILE, *extra)


@pytest.fixture
def not_here(monkeypatch):
    """The daemon's loop (after its lock) must not start in the test process: a refusal
    that let a second daemon through fails the test (exit 70, no "already running")
    instead of hanging it."""
    from vigproc.frontends.daemon import Daemon

    def loop(self) -> int:
        raise AssertionError("a second daemon was let through")

    monkeypatch.setattr(Daemon, "_run", loop)


def test_a_second_daemon_on_the_same_folders_is_refused_in_every_variant(tmp_path, env, not_here):
    in_dir, out_dir = tmp_path / "in", tmp_path / "out"
    in_dir.mkdir()
    log = tmp_path / "d1.log"
    d1 = _watch(in_dir, out_dir, log, env=env)
    try:
        _wait_started(d1, log)
        # --status asks the running one, is not refused; asked as soon as the start is logged,
        # it finds the status file (written before the start line, not at the loop's first tick)
        st = _second(in_dir, out_dir, "--status", env=env)
        assert st.returncode == 0 and "running, pid" in st.stdout, (st.stdout, st.stderr)
        # the same folders, as given and through another spelling of them
        for args in ([in_dir, out_dir], [tmp_path / "in" / ".." / "in", out_dir],
                     # its own journal elsewhere: the folders are still taken
                     [in_dir, out_dir, "--journal", tmp_path / "elsewhere.sqlite"],
                     [in_dir, out_dir, "--journal", tmp_path / "elsewhere.sqlite", "--mode", "check"]):
            r = _second(*args, env=env)
            assert r.returncode == 1 and "already running" in r.stderr, (args, r.stderr)
            assert "Traceback" not in r.stderr
        assert not (tmp_path / "elsewhere.sqlite").exists()
        # the output folder deleted under the daemon: the lock is not in it, so a second daemon
        # is still refused while the first lives (stopped here so that it cannot react yet) ...
        d1.send_signal(signal.SIGSTOP)
        shutil.rmtree(out_dir)
        r = _second(in_dir, out_dir, env=env)
        assert r.returncode == 1 and "already running" in r.stderr, r.stderr
        # ... and the first one, let go on, stops with a clear message instead of writing nowhere
        d1.send_signal(signal.SIGCONT)
        assert d1.wait(timeout=60) == 1
        text = log.read_text("utf-8", "replace")
        assert "was deleted or replaced under the running daemon" in text and "Traceback" not in text
        # once it has gone, a new daemon may take the job
        log2 = tmp_path / "d2.log"
        d2 = _watch(in_dir, out_dir, log2, env=env)
        try:
            _wait_started(d2, log2)
        finally:
            d2.send_signal(signal.SIGTERM)
            assert d2.wait(timeout=60) == 0
    finally:
        if d1.poll() is None:
            d1.send_signal(signal.SIGCONT)
            d1.kill()
            d1.wait(timeout=30)


def test_a_deleted_journal_elsewhere_stops_the_daemon(tmp_path, env):
    in_dir, out_dir, journal = tmp_path / "in", tmp_path / "out", tmp_path / "j" / "job.sqlite"
    in_dir.mkdir()
    log = tmp_path / "d.log"
    d = _watch(in_dir, out_dir, log, "--journal", str(journal), env=env)
    try:
        _wait_started(d, log)
        shutil.rmtree(journal.parent)
        assert d.wait(timeout=60) == 1
        assert "journal" in log.read_text("utf-8", "replace").split("deleted or replaced")[0][-300:]
    finally:
        if d.poll() is None:
            d.kill()
            d.wait(timeout=30)


# ------------------------------------------------------------------ hook server
def _server_pids(rt: Path) -> list[int]:
    r = subprocess.run(["pgrep", "-f", "--", f"--socket {rt}"], capture_output=True, text=True)
    return [int(x) for x in r.stdout.split()]


def _hook(*args, env, cwd=None):
    return subprocess.run([*VIGPROC, "hook", *map(str, args)], capture_output=True, text=True, timeout=120,
                          env=env, cwd=cwd)


def test_a_stalled_hook_client_delays_no_other_call(tmp_path, env, monkeypatch):
    rt = tmp_path / "run"
    env = {**env, hookserver.ENV_SWITCH: "on", "VIGPROC_HOOK_SERVER_IDLE": "60"}
    monkeypatch.setenv(hookserver.ENV_SWITCH, "on")
    img = np.repeat(photo_like(96, 144, seed=4)[..., None], 3, axis=2).astype(np.float32)
    write_image(tmp_path / "a.tif", img, bit_depth="float")
    call = ["--mode", "estimate", "--profile", "estimate", "--", str(tmp_path / "a.tif")]
    try:
        assert _hook(*call, env=env).returncode == 0  # in-process; starts the server
        deadline = time.monotonic() + 90
        while not any(rt.glob("*.sock")) and time.monotonic() < deadline:
            time.sleep(0.2)
        sock_path = next(rt.glob("*.sock"))
        stalled = []
        for _ in range(3):  # clients that send 2 bytes of a request and hold the connection
            s = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
            s.connect(str(sock_path))
            s.sendall(b"\0\0")
            stalled.append(s)
        # a normal call is answered by the server (not given up on): call() returns its code
        got: list = []
        t = threading.Thread(target=lambda: got.append(hookserver.call(["hook", *call])), daemon=True)
        t.start()
        t.join(60)  # hang guard: before the fix this call waited for ever
        assert got == [0], got
        r = _hook(*call, env=env)
        assert r.returncode == 0, r.stderr
        for s in stalled:
            s.close()
        # a server that stops answering altogether (SIGSTOP) is given up on: the call runs here
        pids = _server_pids(rt)
        assert pids
        for pid in pids:
            os.kill(pid, signal.SIGSTOP)
        try:
            r = _hook(*call, env=env)
            assert r.returncode == 0 and '"ok": 1' in r.stdout, r.stderr
        finally:
            for pid in pids:
                os.kill(pid, signal.SIGCONT)
    finally:
        for pid in _server_pids(rt):
            os.kill(pid, signal.SIGTERM)


# ------------------------------------------------------------------ names
def _bright_textured(path: Path) -> None:
    rng = np.random.default_rng(0)
    img = np.clip(0.9 + 0.05 * rng.standard_normal((120, 180, 3)), 0, 1).astype(np.float32)
    write_image(path, img, bit_depth="uint16")


HOSTILE = b"a\nvigproc: forged\tline\xe2\x80\xaegpj.png"
NOT_UTF8 = b"bad\xff\xfe.png"


def test_hostile_names_through_batch_and_correct(tmp_path, env):
    """Every name the file system holds is processed (percent-encoded in output names), and
    no name reaches stderr raw: not in the summary, not in a worker process's log line (here
    the clipping warning a bright frame gets)."""
    in_dir = tmp_path / "in"
    in_dir.mkdir()
    _bright_textured(in_dir / "x.png")
    shutil.copyfile(in_dir / "x.png", os.path.join(os.fsencode(in_dir), NOT_UTF8))
    os.rename(in_dir / "x.png", os.path.join(os.fsencode(in_dir), HOSTILE))
    open(os.path.join(os.fsencode(in_dir), b"junk\n\xe2\x80\xae.png"), "wb").write(b"not an image")
    r = subprocess.run([*VIGPROC, "batch", str(in_dir), "--mode", "correct", "-o", str(tmp_path / "out"),
                        "--profile", str(PROFILE), "--workers", "2", "--output-format", "png"],
                       capture_output=True, timeout=300, env=env)
    err = r.stderr.decode("utf-8", "replace")
    assert r.returncode == 1, err  # the junk file failed; the two photos did not
    assert b"2 processed" in r.stdout and b"1 failed for good" in r.stdout, r.stdout
    assert "\u202e" not in err and "\t" not in err and "Traceback" not in err
    lines = err.splitlines()
    assert not any(line.startswith("vigproc: forged") for line in lines), err
    assert sum("% of the samples are above the white point" in line for line in lines) == 2, err
    assert any("junk\\n\\u202e.png" in line for line in lines), err
    outs = sorted(os.listdir(tmp_path / "out"))
    assert "bad%FF%FE.corrected.png" in outs and "a%0Avigproc: forged%09line%E2%80%AEgpj.corrected.png" in outs, outs
    # correct: the name that is not UTF-8 is read, not refused
    r = subprocess.run([*VIGPROC, "correct", os.path.join(os.fsencode(in_dir), NOT_UTF8), "-o",
                        str(tmp_path / "out2"), "--profile", str(PROFILE), "--output-format", "png"],
                       capture_output=True, timeout=300, env=env)
    assert r.returncode == 0, r.stderr
    assert sorted(os.listdir(tmp_path / "out2")) == ["bad%FF%FE.corrected.png", "bad%FF%FE.png.vigproc.json"]
