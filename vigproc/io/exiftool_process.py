"""One persistent ``exiftool`` process (``-stay_open``), shared by vigproc's EXIF reader and its metadata writer.

Starting exiftool costs about 0.1 s (Perl and its modules); a command through a running one
costs a few milliseconds.  :class:`ExiftoolProcess` wraps PyExifTool's
:class:`exiftool.ExifToolHelper` (which starts the process, passes ``-config`` and the
common arguments, and makes the process die with its parent) and runs commands through it
with what a long-running worker needs on top:

* **Death and hangs.**  PyExifTool waits for the end-of-output sentinel forever, and a
  process that died mid-command leaves it spinning on an empty pipe.  Commands here read
  the pipes themselves: end of file (the process died) and a deadline (it hangs; it is
  killed) raise :class:`ExiftoolDied`.  :meth:`ExiftoolProcess.execute` then starts a new
  process and runs the command once more; a second failure is raised.
* **Forks.**  A process forked after the start (a daemon or pool worker) must not share the
  parent's pipes: a handle used from another process id is dropped (never terminated: it is
  the parent's) and a new exiftool is started for this one.
* **Threads.**  Commands are serialised by a lock.

Arguments travel over a pipe, one per line (exiftool's ``-@`` argument-file protocol):
nothing passes through a shell, but an argument holding a line break would be split in two.
:func:`line_safe` tells which paths can be sent as they are; callers pass other paths
under a safe alias (see :mod:`vigproc.io.metadata`) or refuse them (:mod:`vigproc.io.exif`).

:func:`shared_process` is the process-wide one that writes metadata (:mod:`vigproc.io.metadata`,
:mod:`vigproc.io.dng_vignette`), started with vigproc's XMP namespace (:data:`CONFIG_FILE`, a
file shipped in the package: nothing is written to a temporary folder that a killed process
would leave behind).
"""

from __future__ import annotations

import atexit
import logging
import os
import select
import signal
import threading
import time
import warnings
from dataclasses import dataclass
from importlib import resources
from typing import Callable, Sequence, Union

import exiftool

from vigproc.errors import VigprocError

__all__ = ["CONFIG_FILE", "ExiftoolDied", "ExiftoolProcess", "ExiftoolResult", "line_safe", "shared_process"]

logger = logging.getLogger(__name__)

#: How long one command may take before its process is killed (seconds).
DEFAULT_TIMEOUT = 300.0
#: vigproc's XMP namespace (``XMP-vigproc``) for exiftool, shipped in the package.
CONFIG_FILE = str(resources.files("vigproc.data").joinpath("exiftool.config"))

Arg = Union[str, bytes]


class ExiftoolDied(VigprocError):
    """The exiftool process died, hung past its deadline, or its pipe broke during a command."""


@dataclass(frozen=True)
class ExiftoolResult:
    """What one exiftool command returned.

    Attributes
    ----------
    stdout, stderr : bytes
        The command's output, without PyExifTool's sentinels.
    status : int
        exiftool's exit status for the command (0 ok, 1 an error, 2 a condition failed).
    """

    stdout: bytes
    stderr: bytes
    status: int


def line_safe(path: str) -> bool:
    """Whether ``path`` can be sent to a ``-stay_open`` exiftool as one argument line.

    Parameters
    ----------
    path : str
        An absolute path (a relative one could start with ``-`` or ``#`` and be read as an
        option or a comment).

    Returns
    -------
    bool
        False for line breaks (the line would split) and names that are not valid UTF-8
        (surrogate-escaped bytes cannot be encoded for the pipe).
    """
    if "\n" in path or "\r" in path or not os.path.isabs(path):
        return False
    try:
        path.encode("utf-8")
    except UnicodeEncodeError:
        return False
    return True


def _exit_reason(proc: object) -> str:
    code = getattr(proc, "returncode", None)
    if code is None:
        return "its pipe closed"
    if code < 0:
        try:
            return f"killed by {signal.Signals(-code).name}"
        except ValueError:
            return f"killed by signal {-code}"
    return f"exit status {code}"


def _marker_line(buf: bytes, end: bytes, start: int = 0) -> int:
    """Where the line ending in ``end`` stops in ``buf`` (past its line break once it has
    come), or -1. Only a line's end counts: a tag value quoting the marker is followed by
    the JSON's closing quote."""
    at = buf.find(end, start)
    while at >= 0:
        stop = at + len(end)
        if stop == len(buf) or buf[stop:stop + 1] in (b"\n", b"\r"):
            while buf[stop:stop + 1] in (b"\r", b"\n") and stop < len(buf):
                if buf[stop:stop + 1] == b"\n":
                    return stop + 1
                stop += 1
            return stop
        at = buf.find(end, at + 1)
    return -1


def _check_args(args: Sequence[Arg]) -> None:
    if "--" in args or b"--" in args:
        # it would make the protocol's own closing options (-echo4, -execute) file names
        raise ValueError("no '--' through a -stay_open exiftool: pass absolute paths instead")
    for a in args:
        if (b"\n" in a or b"\r" in a) if isinstance(a, bytes) else ("\n" in a or "\r" in a):
            raise ValueError(f"exiftool argument with a line break: {a!r}")


class Pending:
    """A command sent by :meth:`ExiftoolProcess.submit`, its answer not yet read."""

    def __init__(self, proc: object) -> None:
        self.proc = proc
        self.ends: tuple[bytes, bytes] = (b"", b"")
        self.answer: ExiftoolResult | None = None
        self.error: ExiftoolDied | None = None


class ExiftoolProcess:
    """A persistent exiftool process, restarted when it dies.

    Parameters
    ----------
    executable : str, optional
        The exiftool program (default: ``exiftool`` on ``PATH``).
    common_args : sequence of str
        Arguments exiftool adds to every command (``-common_args``), e.g. ``("-G",)``.
    config_file : str, optional
        An exiftool config file (``-config``); it also stops ``~/.ExifTool_config`` loading.
    timeout : float
        Seconds one command may take before the process is killed.

    Notes
    -----
    Start is lazy (the first :meth:`execute`) or explicit (:meth:`start`); :meth:`close`
    stops the process.  :attr:`launches` counts the processes started.
    """

    def __init__(self, executable: str | None = None, *, common_args: Sequence[str] = (),
                 config_file: str | None = None, timeout: float = DEFAULT_TIMEOUT) -> None:
        self.executable = executable
        self.common_args = list(common_args)
        self.config_file = config_file
        self.timeout = float(timeout)
        self._et: exiftool.ExifToolHelper | None = None
        self._owner = 0  # os.getpid() of the process that started _et
        self._lock = threading.RLock()
        self._unprobed = False  # spawned, its version (its readiness) not yet asked
        self._pending: list[Pending] = []  # submitted commands whose answers are not read yet, in order
        self._rest: dict[int, bytes] = {}  # per pipe: what was read past the last answer
        #: Number of exiftool processes started (1 unless one died).
        self.launches = 0

    # ---- lifetime ---------------------------------------------------------- #

    @property
    def running(self) -> bool:
        """Whether this process's exiftool is running (a forked child's inherited one is not)."""
        et = self._et
        if et is None or self._owner != os.getpid():
            return False
        with warnings.catch_warnings():  # PyExifTool warns when it notices a death: we restart
            warnings.simplefilter("ignore")
            return bool(et.running)

    @property
    def pid(self) -> int | None:
        """Process id of the running exiftool, or None."""
        proc = getattr(self._et, "_process", None) if self.running else None
        return proc.pid if proc is not None else None

    @property
    def version(self) -> str | None:
        """exiftool's version, or None when not running."""
        with self._lock:
            if not self.running or self._et is None:
                return None
            self._ready()
            return self._et.version if self._et is not None else None

    def start(self) -> "ExiftoolProcess":
        """Start exiftool unless it is running (a no-op then).

        Raises
        ------
        VigprocError
            exiftool cannot be started.
        """
        return self._launch(wait=True)

    def spawn(self) -> "ExiftoolProcess":
        """Start exiftool without waiting for it to be ready (a no-op when it runs).

        Perl's start-up (about 0.2 s of CPU) then runs beside the caller's work; the
        first command waits for what is left of it. A program that cannot run is
        reported by that first command, as :meth:`start` would have.

        Raises
        ------
        VigprocError
            exiftool cannot be launched at all (no such program).
        """
        return self._launch(wait=False)

    def _launch(self, *, wait: bool) -> "ExiftoolProcess":
        with self._lock:
            if self.running:
                return self
            self._drop()
            kwargs: dict = {"common_args": list(self.common_args), "encoding": "utf-8"}
            if self.executable:
                kwargs["executable"] = self.executable
            if self.config_file is not None:
                kwargs["config_file"] = self.config_file
            et = None
            try:
                et = _Helper(check_execute=False, auto_start=False, **kwargs)
                et.probe = self._probe if wait else (lambda _et: "")
                et.run()
            except (OSError, RuntimeError, ValueError, exiftool.exceptions.ExifToolException) as exc:
                if et is not None:  # dead already: PyExifTool would warn of it when collected
                    et._running, et._process = False, None
                raise VigprocError(f"cannot run exiftool {self.executable or 'exiftool'!r}: {exc}") from exc
            self._et, self._owner, self._unprobed = et, os.getpid(), not wait
            self.launches += 1
            logger.debug("exiftool %s started (pid %s)", et.version or "(not yet asked)", self.pid)
            return self

    def _ready(self) -> None:
        """Wait for a spawned exiftool to answer (its version); one that cannot is
        dropped and started again, which reports why it cannot run."""
        if not self._unprobed:
            return
        self._unprobed = False
        try:
            self._et._ver = self._probe(self._et)  # type: ignore[union-attr]
        except RuntimeError as exc:
            logger.debug("spawned exiftool did not answer (%s): starting it again", exc)
            self._drop()
            self.start()

    def close(self) -> None:
        """Stop exiftool (only one this process started)."""
        with self._lock:
            self._fail_pending("was closed before answering")
            et, owned = self._et, self._owner == os.getpid()
            self._et = None
            if et is None or not owned:
                self._forget(et)
                return
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                try:
                    if et.running:
                        et.terminate(timeout=5)
                except Exception:  # noqa: BLE001 - shutting down: nothing useful to do
                    logger.debug("exiftool terminate failed", exc_info=True)

    def _drop(self) -> None:
        """Forget a dead, hung or inherited process: kill it only if it is ours."""
        self._fail_pending("was stopped before answering")
        self._rest.clear()
        et, self._et = self._et, None
        if et is None:
            return
        proc = getattr(et, "_process", None)
        if self._owner == os.getpid() and proc is not None:
            try:
                proc.kill()
                proc.wait(timeout=5)
            except Exception:  # noqa: BLE001 - already gone
                pass
        self._forget(et)

    @staticmethod
    def _forget(et: exiftool.ExifToolHelper | None) -> None:
        # PyExifTool's __del__ would send "-stay_open False" down a pipe that may be the
        # parent's (after a fork) or broken: mark it stopped without touching the pipes
        if et is not None:
            try:
                et._flag_running_false()
            except AttributeError:  # another PyExifTool version: let it be
                pass

    def __enter__(self) -> "ExiftoolProcess":
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.close()

    # ---- commands ---------------------------------------------------------- #

    def execute(self, args: Sequence[Arg], *, before_retry: Callable[[], None] | None = None) -> ExiftoolResult:
        """Run one exiftool command; if the process dies or hangs, restart it and run it once more.

        Parameters
        ----------
        args : sequence of str or bytes
            The command's arguments, one per line: none may contain a line break (see
            :func:`line_safe`).
        before_retry : callable, optional
            Called before the second attempt (e.g. to remove a half-written file).

        Returns
        -------
        ExiftoolResult

        Raises
        ------
        ExiftoolDied
            The command failed twice because the process died or hung.
        VigprocError
            exiftool cannot be started.
        ValueError
            An argument holds a line break, or is ``--``.
        """
        _check_args(args)
        with self._lock:
            try:
                return self._once(args)
            except ExiftoolDied as exc:
                logger.warning("exiftool %s; restarting it and retrying once", exc)
                self._drop()
            if before_retry is not None:
                before_retry()
            return self._once(args)

    def _once(self, args: Sequence[Arg]) -> ExiftoolResult:
        self._drain()  # answers come in order: the submitted ones first
        return self._command(self._live(), args)

    def _live(self):
        """The process of a running exiftool that has answered: started, or a spawned
        one waited for, when need be (the one way :meth:`execute` and :meth:`submit`
        reach it; the caller holds the lock)."""
        self.start()
        self._ready()
        et = self._et
        assert et is not None
        return et._process

    def submit(self, args: Sequence[Arg]) -> "Pending":
        """Send one command and return at once; :meth:`result` reads its answer.

        exiftool answers commands in order, so the process works on this one while the
        caller does something else; a later :meth:`execute` or :meth:`result` first
        reads the answers of the commands submitted before it.  A submitted command is
        not retried: if the process dies, :meth:`result` raises and the caller asks
        again with :meth:`execute` (which restarts it).

        Raises
        ------
        VigprocError
            exiftool cannot be started.
        ValueError
            An argument holds a line break, or is ``--``.
        """
        _check_args(args)
        with self._lock:
            proc = self._live()
            pending = Pending(proc)
            try:
                pending.ends = self._send(proc, args)
            except ExiftoolDied as exc:
                pending.error = exc
                self._drop()
                return pending
            self._pending.append(pending)
            return pending

    def result(self, pending: "Pending") -> ExiftoolResult:
        """The answer to a command of :meth:`submit` (waiting for it if need be).

        Raises
        ------
        ExiftoolDied
            The process died, hung or was stopped before answering it.
        """
        with self._lock:
            if pending in self._pending:
                self._drain(until=pending)
            if pending.error is not None:
                raise pending.error
            assert pending.answer is not None
            return pending.answer

    def _drain(self, until: "Pending | None" = None) -> None:
        """Read the answers of submitted commands, in order (up to ``until``)."""
        while self._pending:
            pending = self._pending.pop(0)
            try:
                pending.answer = self._receive(pending.proc, *pending.ends)
            except ExiftoolDied as exc:
                pending.error = exc
                self._drop()  # the later ones cannot be answered either
            if pending is until:
                return

    def _fail_pending(self, why: str) -> None:
        pending, self._pending = self._pending, []
        for p in pending:
            p.error = ExiftoolDied(why)

    def _probe(self, et: "exiftool.ExifToolHelper") -> str:
        """exiftool's version, asked of a process PyExifTool just started (its own probe
        reads an empty pipe for ever when the program exits at once)."""
        try:
            return self._command(et._process, ["-ver"]).stdout.decode("utf-8", "replace").strip()
        except ExiftoolDied as exc:
            raise RuntimeError(f"it {exc}") from None

    def _command(self, proc, args: Sequence[Arg]) -> ExiftoolResult:
        """One command through the stay-open protocol of ``proc``."""
        return self._receive(proc, *self._send(proc, args))

    def _send(self, proc, args: Sequence[Arg]) -> tuple[bytes, bytes]:
        """Write one command; returns the markers that end its answer on stdout and stderr."""
        # PyExifTool's own protocol (ExifTool.execute), read here with end-of-file and a deadline
        tag = int.from_bytes(os.urandom(3), "big") % 900000 + 100000
        ready, post = f"{{ready{tag}}}".encode(), f"post{tag}".encode()
        lines = [a if isinstance(a, bytes) else a.encode("utf-8") for a in args]
        lines += [b"-echo4", b"=${status}=" + post, f"-execute{tag}".encode(), b""]
        try:
            proc.stdin.write(b"\n".join(lines))
            proc.stdin.flush()
        except (BrokenPipeError, OSError, ValueError) as exc:
            self._reap(proc)
            raise ExiftoolDied(f"could not take the command ({_exit_reason(proc)})") from exc
        return ready, post

    def _receive(self, proc, ready: bytes, post: bytes) -> ExiftoolResult:
        """Read the answer of the command whose markers are ``ready`` and ``post``."""
        deadline = time.monotonic() + self.timeout
        out = self._read_until(proc, proc.stdout.fileno(), ready, deadline)
        err = self._read_until(proc, proc.stderr.fileno(), post, deadline)
        stdout = out.strip()[: -len(ready)]
        err = err.strip()[: -len(post)]
        # stderr ends with "=STATUS="
        head, _, status = err[:-1].rpartition(b"=")
        try:
            code = int(status)
        except ValueError:
            raise ExiftoolDied(f"answered out of protocol: {err[-80:]!r}") from None
        return ExiftoolResult(stdout=stdout.strip(), stderr=head.strip(), status=code)

    def _read_until(self, proc: object, fd: int, end: bytes, deadline: float) -> bytes:
        """Read ``fd`` up to the line ``end`` (included). With commands submitted ahead
        (:meth:`submit`) one read may also bring the start of the next answer: that rest
        is kept for the next call."""
        buf = self._rest.pop(fd, b"")
        searched = 0
        while True:
            at = _marker_line(buf, end, searched)
            if at >= 0:
                self._rest[fd] = buf[at:]
                return buf[:at]
            searched = max(0, len(buf) - len(end) - 1)
            left = deadline - time.monotonic()
            if left <= 0:
                proc.kill()  # type: ignore[attr-defined]
                self._reap(proc)
                raise ExiftoolDied(f"did not answer within {self.timeout:.0f} s and was killed")
            ready, _, _ = select.select([fd], [], [], min(left, 1.0))
            if not ready:
                if proc.poll() is not None:  # type: ignore[attr-defined]
                    # dead, while something it started still holds the pipe open
                    raise ExiftoolDied(f"died during a command ({_exit_reason(proc)})")
                continue
            chunk = os.read(fd, 65536)
            if not chunk:  # end of file: the process is gone
                self._reap(proc)
                raise ExiftoolDied(f"died during a command ({_exit_reason(proc)})")
            buf += chunk

    @staticmethod
    def _reap(proc: object) -> None:
        try:
            proc.wait(timeout=5)  # type: ignore[attr-defined]
        except Exception:  # noqa: BLE001 - its return code is only for the message
            pass


class _Helper(exiftool.ExifToolHelper):
    """PyExifTool's helper whose start-up version probe is :meth:`ExiftoolProcess._probe`
    (read with end of file and a deadline)."""

    probe: Callable[["_Helper"], str]

    def _parse_ver(self) -> str:
        return self.probe(self)


#: The process-wide persistent exiftool per program path (:func:`shared_process`).
_SHARED: dict[str, ExiftoolProcess] = {}
_SHARED_LOCK = threading.Lock()


def shared_process(executable: str, *, timeout: float = DEFAULT_TIMEOUT) -> ExiftoolProcess:
    """The persistent exiftool of this process that writes metadata (one per program path),
    started lazily with :data:`CONFIG_FILE` and closed at exit.

    Parameters
    ----------
    executable : str
        The exiftool program.
    timeout : float
        Seconds one command may take (the first call's value holds).

    Returns
    -------
    ExiftoolProcess
    """
    with _SHARED_LOCK:
        proc = _SHARED.get(executable)
        if proc is None:
            proc = _SHARED[executable] = ExiftoolProcess(executable, config_file=CONFIG_FILE, timeout=timeout)
    return proc


@atexit.register
def _close_shared() -> None:
    for proc in list(_SHARED.values()):
        proc.close()  # a forked child's inherited ones are only forgotten
