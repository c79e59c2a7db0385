"""A warm process for ``vigproc hook``: host calls without the start-up cost.

Hosts (darktable, digiKam, scripts) run one ``vigproc hook`` process per image.
Most of such a call is start-up, not work: importing numpy and Numba and loading
the estimator's compiled kernels from Numba's cache (Numba imports scipy.linalg to
look for BLAS) cost ~0.8 s per process, against ~0.1 s of reading, EXIF and
estimating a 1 MP frame.

So the first hook call does its work itself and then starts this server in the
background; later calls hand their arguments to it over a Unix socket and print
its answer: the same stdout, stderr and exit code, from a process whose kernels are
already loaded. The server leaves after :data:`IDLE_SECONDS` without a call.

Safety and correctness:

- The socket lives in a folder only this user can enter (mode 0700, checked), and
  the server answers only its own user (``SO_PEERCRED``).
- The socket's name carries a fingerprint of the Python and the vigproc code in
  use, so an upgraded vigproc never talks to a server of the old code.
- Each call runs with the client's working folder and its ``VIGPROC_*``
  environment; calls run one at a time, but every connection is read by its own
  thread, with a :data:`READ_TIMEOUT` between bytes: a client that stalls mid-request
  is dropped after a second of silence and never holds up another call.
- While a call waits for its turn or runs, the server sends the client a heartbeat
  every :data:`HEARTBEAT` seconds; a client that hears nothing for
  :data:`CLIENT_SILENCE` seconds (a stopped or wedged server) gives up and does the
  work itself, as when no server runs.
- ``VIGPROC_HOOK_SERVER=off`` turns it off (every call in-process, nothing started).

Only the standard library is imported here: the client side must stay cheap.
"""

from __future__ import annotations

import base64
import contextlib
import errno
import hashlib
import io
import json
import logging
import os
import signal
import socket
import stat
import struct
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Any, Callable, Sequence

log = logging.getLogger(__name__)

#: Environment switch: ``off`` runs every hook call in-process and starts nothing.
ENV_SWITCH = "VIGPROC_HOOK_SERVER"
#: Folder for the socket (default ``$XDG_RUNTIME_DIR/vigproc`` or ``/tmp/vigproc-UID``).
ENV_DIR = "VIGPROC_RUNTIME_DIR"
#: The server leaves after this many seconds without a call (``VIGPROC_HOOK_SERVER_IDLE``).
IDLE_SECONDS = 600.0
#: Largest message accepted (the hook's own request limit, 16 MiB, plus room).
MAX_MESSAGE = 32 * 2**20
_LEN = struct.Struct("!I")
#: Seconds of silence from a client mid-request before the server drops it.
READ_TIMEOUT = 1.0
#: Seconds between the server's heartbeats to a client whose call waits or runs.
HEARTBEAT = 1.0
#: Seconds a client waits for any word of the server (connect, heartbeat, answer)
#: before it does the call itself.
CLIENT_SILENCE = 5.0
#: Connections read at once; more are closed at once (the client then works in-process).
MAX_CONNECTIONS = 64
#: True inside the server: its calls run here, never handed on again.
_SERVING = False

#: What runs one call: ``vigproc.frontends.cli.main`` (given by the ``python -m`` entry below, so
#: that this module, which the CLI imports, does not import the CLI back).
Runner = Callable[[Sequence[str]], int]


def serving() -> bool:
    return _SERVING


def enabled() -> bool:
    return os.environ.get(ENV_SWITCH, "on").strip().lower() not in ("off", "0", "no", "false")


def _fingerprint() -> str:
    """The Python and the vigproc code this process runs: a server of other code is not used."""
    pkg = Path(__file__).resolve().parents[1]  # the whole vigproc package
    newest = max((p.stat().st_mtime_ns for p in pkg.rglob("*.py")), default=0)
    text = f"{sys.executable}|{sys.version}|{pkg}|{newest}"
    return hashlib.sha256(text.encode("utf-8", "surrogateescape")).hexdigest()[:16]


def runtime_dir() -> Path:
    """The private folder of this user's sockets (created 0700; refused if anyone else
    could enter it)."""
    base = os.environ.get(ENV_DIR)
    if base:
        d = Path(base)
    elif os.environ.get("XDG_RUNTIME_DIR"):
        d = Path(os.environ["XDG_RUNTIME_DIR"]) / "vigproc"
    else:
        d = Path("/tmp") / f"vigproc-{os.getuid()}"
    d.mkdir(mode=0o700, parents=True, exist_ok=True)
    st = os.lstat(d)
    if not stat.S_ISDIR(st.st_mode) or st.st_uid != os.getuid() or st.st_mode & 0o077:
        raise PermissionError(f"{d} is not a private folder of this user")
    return d


def socket_path() -> Path:
    return runtime_dir() / f"hook-{_fingerprint()}.sock"


_WARNED: set[str] = set()


def _warn_disabled(exc: OSError) -> None:
    """Say once per process why there is no warm server (a runtime folder of another user,
    or one anyone may enter, would otherwise disable it silently)."""
    text = f"the warm hook server is disabled: {exc} (set {ENV_DIR} to a folder of your own)"
    if text not in _WARNED:
        _WARNED.add(text)
        log.warning("%s", text)


# ------------------------------------------------------------------ framing
def _send(sock: socket.socket, doc: dict[str, Any]) -> None:
    data = json.dumps(doc, ensure_ascii=True).encode("ascii")
    sock.sendall(_LEN.pack(len(data)) + data)


def _recv_exact(sock: socket.socket, n: int) -> bytes:
    buf = bytearray()
    while len(buf) < n:
        chunk = sock.recv(min(n - len(buf), 1 << 20))
        if not chunk:
            raise ConnectionError("connection closed")
        buf += chunk
    return bytes(buf)


def _recv(sock: socket.socket) -> dict[str, Any]:
    (n,) = _LEN.unpack(_recv_exact(sock, _LEN.size))
    if n > MAX_MESSAGE:
        raise ConnectionError(f"message of {n} bytes refused")
    doc = json.loads(_recv_exact(sock, n).decode("ascii"))
    if not isinstance(doc, dict):
        raise ConnectionError("malformed message")
    return doc


# ------------------------------------------------------------------ client
def _client_env() -> dict[str, str]:
    return {k: v for k, v in os.environ.items() if k.startswith("VIGPROC_")}


def call(argv: Sequence[str], stdin_bytes: bytes | None = None, timeout: float | None = None) -> int | None:
    """Run ``vigproc ARGV`` (a hook call) on the warm server, writing its stdout and
    stderr here; returns its exit code, or None when no server answered (the caller
    then runs the call itself)."""
    try:
        path = socket_path()
    except PermissionError as exc:
        _warn_disabled(exc)
        return None
    except OSError:
        return None
    deadline = None if timeout is None else time.monotonic() + timeout
    s = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    try:
        s.settimeout(min(2.0, CLIENT_SILENCE))
        s.connect(os.fspath(path))
        s.settimeout(CLIENT_SILENCE)
        _send(s, {"argv": list(argv), "cwd": os.getcwd(), "env": _client_env(),
                  "stdin": base64.b64encode(stdin_bytes).decode("ascii") if stdin_bytes is not None else None})
        while True:  # heartbeats until the answer; silence or the caller's deadline: give up
            if deadline is not None:
                left = deadline - time.monotonic()
                if left <= 0:
                    raise TimeoutError("no answer in time")
                s.settimeout(min(CLIENT_SILENCE, left))
            answer = _recv(s)
            if "code" in answer:
                break
    except (OSError, ConnectionError, ValueError) as exc:
        log.debug("no answer from the hook server (%s): the call runs here", exc)
        return None  # no server, a stale socket, it died or is wedged: do the call here
    finally:
        s.close()
    sys.stderr.write(answer.get("stderr", ""))
    sys.stderr.flush()
    sys.stdout.write(answer.get("stdout", ""))
    sys.stdout.flush()
    return int(answer.get("code", 70))


def start_in_background() -> None:
    """Start a server for the next calls (detached; it outlives this process). A second
    one started at the same time finds the socket taken and leaves."""
    try:
        path = socket_path()
    except PermissionError as exc:
        _warn_disabled(exc)
        return
    except OSError as exc:
        log.debug("no hook server: %s", exc)
        return
    cmd = [sys.executable, "-m", "vigproc.frontends.hookserver", "--socket", os.fspath(path)]
    try:
        subprocess.Popen(cmd, stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                         start_new_session=True, close_fds=True, cwd="/")
    except OSError as exc:
        log.debug("cannot start the hook server: %s", exc)


# ------------------------------------------------------------------ server
@contextlib.contextmanager
def _as_client(doc: dict[str, Any]):
    """The client's folder, VIGPROC_* environment, stdin and fresh stdout/stderr buffers."""
    old_cwd, old_env = os.getcwd(), {k: v for k, v in os.environ.items() if k.startswith("VIGPROC_")}
    old_streams = sys.stdin, sys.stdout, sys.stderr
    out, err = io.StringIO(), io.StringIO()
    stdin = base64.b64decode(doc["stdin"]) if doc.get("stdin") is not None else b""
    try:
        os.chdir(doc["cwd"])
        for k in old_env:
            os.environ.pop(k, None)
        os.environ.update({k: str(v) for k, v in (doc.get("env") or {}).items() if str(k).startswith("VIGPROC_")})
        sys.stdin = io.TextIOWrapper(io.BytesIO(stdin), encoding="utf-8")
        sys.stdout, sys.stderr = out, err
        yield out, err
    finally:
        sys.stdin, sys.stdout, sys.stderr = old_streams
        for k in [k for k in os.environ if k.startswith("VIGPROC_")]:
            os.environ.pop(k, None)
        os.environ.update(old_env)
        os.chdir(old_cwd)


class _Heartbeat:
    """Sends the client a heartbeat every :data:`HEARTBEAT` seconds while its call waits
    or runs, from a thread of its own (sends are serialised with the answer's)."""

    def __init__(self, conn: socket.socket) -> None:
        self.conn, self.lock = conn, threading.Lock()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._beat, daemon=True, name="hook-heartbeat")

    def _beat(self) -> None:
        while not self._stop.wait(HEARTBEAT):
            try:
                self.send({"wait": 1})
            except OSError:
                return  # the client left; its answer's send fails too

    def send(self, doc: dict[str, Any]) -> None:
        with self.lock:
            _send(self.conn, doc)

    def __enter__(self) -> "_Heartbeat":
        self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self._stop.set()
        self._thread.join()


def _handle(conn: socket.socket, run: Runner, turn: threading.Lock) -> None:
    """One connection: read its request (dropped after :data:`READ_TIMEOUT` of silence),
    wait for ``turn`` (calls change the folder, environment and streams of this process, so
    they run one at a time), run it and send the answer."""
    creds = conn.getsockopt(socket.SOL_SOCKET, socket.SO_PEERCRED, struct.calcsize("3i"))
    _pid, uid, _gid = struct.unpack("3i", creds)
    if uid != os.getuid():  # the folder is private; this is the second lock
        return
    conn.settimeout(READ_TIMEOUT)  # per recv: a stalled client is dropped, no one else waits on it
    doc = _recv(conn)
    argv = doc.get("argv")
    if not (isinstance(argv, list) and all(isinstance(a, str) for a in argv) and isinstance(doc.get("cwd"), str)):
        return
    conn.settimeout(max(READ_TIMEOUT, 10 * HEARTBEAT))  # a client that stops reading is dropped too
    with _Heartbeat(conn) as beat:
        with turn:
            try:
                with _as_client(doc) as (out, err):
                    code = run(argv)
            except SystemExit as exc:  # argparse's usage errors
                code = exc.code if isinstance(exc.code, int) else 2
            except Exception as exc:  # noqa: BLE001 - one bad call must not end the server
                err = io.StringIO(f"vigproc: internal error in the hook server ({type(exc).__name__}: {exc})\n")
                out, code = io.StringIO(), 70
    beat.send({"stdout": out.getvalue(), "stderr": err.getvalue(), "code": int(code)})


def _serve_connection(conn: socket.socket, run: Runner, turn: threading.Lock, active: threading.Semaphore) -> None:
    try:
        with conn:
            _handle(conn, run, turn)
    except (OSError, ConnectionError, ValueError) as exc:
        log.debug("hook call dropped: %s", exc)
    finally:
        active.release()


def serve(path: Path, run: Runner, idle: float = IDLE_SECONDS) -> int:
    """Answer hook calls on the Unix socket ``path`` with ``run`` (the CLI's ``main``)
    until ``idle`` seconds pass without one."""
    global _SERVING
    _SERVING = True
    import numpy as np  # noqa: F401 - warm now, not in the first call

    from vigproc.core.estimate import estimate

    srv = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    try:
        if path.exists():
            # a live server holds it: leave; a dead one left it: take it over
            probe = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
            try:
                probe.connect(os.fspath(path))
                return 0
            except OSError:
                path.unlink(missing_ok=True)
            finally:
                probe.close()
        # load the estimator's kernels before the socket appears: a host that finds the
        # socket gets a warm answer, and a SIGTERM during the warm-up (the signal waits for
        # the compiled code) leaves no socket behind
        estimate(np.exp(np.random.default_rng(0).normal(0.0, 0.1, (96, 128))))
        old = os.umask(0o177)
        try:
            srv.bind(os.fspath(path))
        finally:
            os.umask(old)
        srv.listen(16)
    except OSError as exc:
        if exc.errno == errno.EADDRINUSE:
            return 0
        raise
    try:
        # wake every second: is the socket still ours to serve? (a removed socket, as a host's
        # or the hook benchmark's clean-up leaves it, ends the server within a second, not 10)
        srv.settimeout(min(idle, 1.0))
        last = time.monotonic()
        turn = threading.Lock()
        active = threading.BoundedSemaphore(MAX_CONNECTIONS)
        while True:
            try:
                conn, _ = srv.accept()
            except socket.timeout:
                if turn.locked():  # a call running is not idleness
                    last = time.monotonic()
                elif time.monotonic() - last >= idle or not path.exists():
                    break
                continue
            last = time.monotonic()
            if not active.acquire(blocking=False):
                conn.close()  # too many at once: that client works in-process
                continue
            # a thread per connection: a client that stalls holds up only itself
            threading.Thread(target=_serve_connection, args=(conn, run, turn, active), daemon=True,
                             name="hook-call").start()
            if not path.exists():  # removed by someone: stop serving a name nobody finds
                break
        with turn:  # let a call that runs finish (those still queued fall back to in-process)
            pass
    finally:
        srv.close()
        with contextlib.suppress(OSError):
            if path.exists() and path.is_socket():
                path.unlink()
    return 0


def _main(run: Runner, argv: Sequence[str] | None = None) -> int:
    import argparse

    p = argparse.ArgumentParser(prog="python -m vigproc.frontends.hookserver", description=__doc__.splitlines()[0])
    p.add_argument("--socket", required=True, help="Unix socket path")
    p.add_argument("--idle", type=float, default=float(os.environ.get("VIGPROC_HOOK_SERVER_IDLE", IDLE_SECONDS)),
                   help="seconds without a call before leaving")
    a = p.parse_args(argv)
    logging.basicConfig(level=logging.WARNING)
    # SIGTERM (a logout, `pkill`) ends the loop like the idle timeout: the socket is removed
    signal.signal(signal.SIGTERM, lambda *_: sys.exit(0))
    return serve(Path(a.socket), run, a.idle)


if __name__ == "__main__":
    # run as the importable module, not as __main__: the CLI asks vigproc.frontends.hookserver
    # whether it runs inside the server (a second copy of the module would say no,
    # and the server would hand its calls to itself)
    from vigproc.frontends.cli import main as _cli_main
    from vigproc.frontends.hookserver import _main as _module_main

    sys.exit(_module_main(_cli_main))
