"""The warm hook server (vigproc.frontends.hookserver): same answers as an in-process call, only
faster; private to its user; never a second copy of the code."""

import json
import os
import subprocess
import sys
import time

import numpy as np
import pytest

from vigproc.frontends import hookserver
from vigproc.io.images import write_image

from conftest import photo_like

VIGPROC = [sys.executable, "-m", "vigproc.frontends.cli"]


@pytest.fixture
def server_env(tmp_path, monkeypatch):
    rt = tmp_path / "run"
    monkeypatch.setenv(hookserver.ENV_SWITCH, "on")
    monkeypatch.setenv(hookserver.ENV_DIR, str(rt))
    monkeypatch.setenv("VIGPROC_HOOK_SERVER_IDLE", "20")
    yield rt
    subprocess.run(["pkill", "-f", "--", f"--socket {rt}"], check=False)  # leave no process behind


def _hook(*args, cwd=None, stdin=None):
    return subprocess.run([*VIGPROC, "hook", *map(str, args)], capture_output=True, text=True, cwd=cwd,
                          input=stdin, timeout=120, env=os.environ.copy())


def _strip(doc):
    for r in doc.get("results", []):
        r.pop("seconds", None)
        for k in ("model",):
            if isinstance(r.get(k), dict):
                (r[k].get("quality") or {}).pop("seconds", None)
    return doc


def _wait_for_socket(rt, seconds=60):
    t0 = time.time()
    while time.time() - t0 < seconds:
        if rt.exists() and any(rt.glob("*.sock")):
            return True
        time.sleep(0.2)
    return False


def test_a_warm_server_gives_the_same_answers(tmp_path, server_env):
    img = np.repeat(photo_like(120, 180, seed=2)[..., None], 3, axis=2).astype(np.float32)
    write_image(tmp_path / "a.tif", img, bit_depth="float")
    first = _hook("--mode", "estimate", "--profile", "estimate", "--", "a.tif", cwd=tmp_path)  # in-process
    assert first.returncode == 0, first.stderr
    assert _wait_for_socket(server_env), "the first call did not start a server"
    assert os.stat(server_env).st_mode & 0o777 == 0o700
    # once started, the server answers calls: call() returns its exit code (None would mean
    # that no server answered, and the caller works itself)
    assert hookserver.call(["hook", "--mode", "estimate", "--profile", "estimate", "--", str(tmp_path / "a.tif")]) == 0
    # relative names resolve in the caller's folder, on the server too
    again = _hook("--mode", "estimate", "--profile", "estimate", "--", "a.tif", cwd=tmp_path)
    assert again.returncode == 0, again.stderr
    assert _strip(json.loads(again.stdout)) == _strip(json.loads(first.stdout))
    # a failure: same exit code and message as in-process
    bad = _hook("--mode", "estimate", "--", "missing.tif", cwd=tmp_path)
    assert bad.returncode == 4 and "missing.tif" in bad.stderr
    assert json.loads(bad.stdout)["results"][0]["status"] == "error"
    # a request on standard input
    req = json.dumps({"mode": "estimate", "profile": "estimate", "files": [str(tmp_path / "a.tif")]})
    piped = _hook("--request", "-", stdin=req, cwd=tmp_path)
    assert piped.returncode == 0 and json.loads(piped.stdout)["ok"] == 1, piped.stderr
    # usage errors stay usage errors
    usage = _hook("--mode", "nonsense", cwd=tmp_path)
    assert usage.returncode == 2 and "invalid choice" in usage.stderr


def test_no_server_for_a_folder_others_can_enter(tmp_path, monkeypatch):
    rt = tmp_path / "open"
    rt.mkdir(mode=0o755)
    rt.chmod(0o755)
    monkeypatch.setenv(hookserver.ENV_DIR, str(rt))
    with pytest.raises(PermissionError):
        hookserver.runtime_dir()
    assert hookserver.call(["hook", "--help"]) is None  # the caller does the work itself


def test_a_runtime_folder_of_another_user_is_said_once(tmp_path, monkeypatch, caplog):
    """A runtime folder that is not ours disabled the warm server silently: now one warning
    says so and why, once per process."""
    rt = tmp_path / "theirs"
    rt.mkdir(mode=0o700)
    os.chown(rt, 12345, 12345) if os.getuid() == 0 else rt.chmod(0o755)
    monkeypatch.setenv(hookserver.ENV_DIR, str(rt))
    hookserver._WARNED.clear()
    with caplog.at_level("WARNING", logger=hookserver.__name__):
        assert hookserver.call(["hook", "--help"]) is None
        hookserver.start_in_background()
        assert hookserver.call(["hook", "--help"]) is None
    said = [r.getMessage() for r in caplog.records if "warm hook server is disabled" in r.getMessage()]
    assert len(said) == 1 and str(rt) in said[0] and hookserver.ENV_DIR in said[0], said


def test_off_switch(monkeypatch):
    monkeypatch.setenv(hookserver.ENV_SWITCH, "off")
    assert not hookserver.enabled()
    monkeypatch.setenv(hookserver.ENV_SWITCH, "on")
    assert hookserver.enabled()


def test_a_terminated_server_removes_its_socket(tmp_path, server_env):
    """SIGTERM (a logout, pkill) ends the server as its idle timeout does: no socket file
    is left behind."""
    write_image(tmp_path / "c.tif", photo_like(120, 180, seed=3)[..., None].repeat(3, axis=2).astype("float32"))
    r = _hook("--mode", "estimate", "--profile", "estimate", "--", tmp_path / "c.tif")  # starts the server
    assert r.returncode == 0, r.stderr
    assert _wait_for_socket(server_env)
    # "--": a pattern that starts with "--" is not an option of pkill's
    assert subprocess.run(["pkill", "-TERM", "-f", "--", f"--socket {server_env}"]).returncode == 0
    t0 = time.time()
    while any(server_env.glob("*.sock")) and time.time() - t0 < 10:  # well before its 20 s idle exit
        time.sleep(0.2)
    assert not any(server_env.glob("*.sock"))


def test_a_server_whose_socket_is_removed_leaves_within_seconds(tmp_path, server_env):
    """vigproc bench hook removes its server's socket when done; the server went on for up
    to 10 s more (a new user saw it in ps after the benchmark had ended)."""
    img = np.repeat(photo_like(60, 90, seed=3)[..., None], 3, axis=2).astype(np.float32)
    write_image(tmp_path / "a.tif", img, bit_depth="float")
    assert _hook("--mode", "estimate", "--profile", "estimate", "--", "a.tif", cwd=tmp_path).returncode == 0
    assert _wait_for_socket(server_env), "the first call did not start a server"
    assert _hook("--mode", "estimate", "--profile", "estimate", "--", "a.tif", cwd=tmp_path).returncode == 0

    def running() -> bool:
        return subprocess.run(["pgrep", "-f", "--", f"--socket {server_env}"], capture_output=True).returncode == 0

    assert running()
    for sock in server_env.glob("*.sock"):
        sock.unlink()
    # it looks for its socket about once a second; its idle exit (20 s here) is the other
    # way out, so leaving well before that is leaving because the socket went (a bound
    # against that, not a timing of the server, so a loaded machine cannot fail it)
    t0 = time.time()
    while running() and time.time() - t0 < 14:
        time.sleep(0.1)
    assert not running(), f"still running {time.time() - t0:.1f} s after its socket was removed (idle exit: 20 s)"
