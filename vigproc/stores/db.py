"""An SQLite file shared by several processes: the base of vigproc's embedded stores.

The profile store (:mod:`vigproc.stores.profiles`) and the journal of the daemon and of
batch jobs (:mod:`vigproc.stores.journal`) open their files the same way:

* ``journal_mode=WAL``: readers and one writer proceed concurrently;
* ``synchronous=FULL``: the WAL is fsynced at every commit, so what was reported
  stored survives a power cut;
* every write is one ``BEGIN IMMEDIATE`` transaction, which takes the write lock up
  front (a read-modify-write cannot interleave with another writer's, so no update
  is lost) and is retried as a whole when SQLite answers BUSY without waiting;
* sqlite3 errors become the store's own typed error, naming the file and the cause.

References
----------
SQLite, "Write-Ahead Logging" and "File Locking And Concurrency In SQLite Version 3",
https://www.sqlite.org/wal.html, https://www.sqlite.org/lockingv3.html.
"""

from __future__ import annotations

import contextlib
import logging
import os
import random
import sqlite3
import time
from pathlib import Path
from typing import Any, Callable, Iterator

from vigproc.errors import VigprocError

log = logging.getLogger(__name__)


#: SQLite's primary result codes that say whose fault a failure is (``sqlite_errorcode & 0xff``).
SQLITE_BUSY, SQLITE_LOCKED, SQLITE_READONLY, SQLITE_CORRUPT, SQLITE_FULL, SQLITE_NOTADB = 5, 6, 8, 11, 13, 26


def sqlite_code(exc: sqlite3.Error) -> int | None:
    """The primary SQLite result code of ``exc`` (Python 3.11+), or None."""
    code = getattr(exc, "sqlite_errorcode", None)
    return code & 0xFF if isinstance(code, int) else None


def explain_sqlite_error(exc: sqlite3.Error, timeout: float) -> str:
    """What an sqlite3 error means for the user, in words (the message kept).  By its
    result code; SQLite's own fixed messages (no file name in them) where there is none."""
    msg = str(exc)
    low = msg.lower()
    code = sqlite_code(exc)
    if code is not None:  # the words below are SQLite's messages for these codes
        low = {SQLITE_BUSY: "busy", SQLITE_LOCKED: "locked", SQLITE_CORRUPT: "malformed", SQLITE_NOTADB: "not a database",
               SQLITE_READONLY: "readonly", SQLITE_FULL: "disk full"}.get(code, "")
    if "locked" in low or "busy" in low:
        return f"locked by another process for more than {timeout:g} s ({msg})"
    if "not a database" in low or "malformed" in low or "corrupt" in low:
        return f"the file is corrupt or not an SQLite database ({msg})"
    if "readonly" in low or "read-only" in low:
        return f"the file is read-only ({msg})"
    if "disk" in low and "full" in low:
        return f"the disk is full ({msg})"
    return msg


class SQLiteFile:
    """One connection to an SQLite file, opened for safe use by several processes.

    Subclasses set :attr:`error` (the typed error raised) and :attr:`what` (how the
    file is named in messages), and create or migrate their schema in
    :meth:`_setup_schema`, which runs under the retry of :meth:`_retry_busy`.

    Parameters
    ----------
    path : path
        The database file; its folder is created if needed.
    timeout : float
        Seconds to wait for another process's lock before giving up.

    Notes
    -----
    One object per thread (sqlite3 connections are not shared between threads);
    each process opens its own.  Use as a context manager or call :meth:`close`.
    """

    error: type[VigprocError] = VigprocError
    what: str = "database"
    #: What a user can do about a corrupt file (appended to that error's message).
    recovery: str = ""
    #: Run ``PRAGMA quick_check`` when an existing file is opened: a corrupt store is
    #: refused with a typed error rather than used (a small file: milliseconds).
    check_on_open: bool = False

    def __init__(self, path: str | os.PathLike[str], *, timeout: float) -> None:
        self.path = Path(path).expanduser()
        self.timeout = float(timeout)
        self._con: sqlite3.Connection | None = None
        if self.path.is_dir():
            raise self.error(f"{self.what} {self.path} is a folder, not a database file")
        try:
            self.path.parent.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise self.error(f"cannot create the folder of {self.what} {self.path}: {exc.strerror or exc}") from None
        try:
            self._con = sqlite3.connect(str(self.path), timeout=self.timeout, isolation_level=None)
        except sqlite3.Error as exc:
            raise self.error(f"cannot open {self.what} {self.path}: {exc}") from None
        try:
            with self._errors("open"):
                self._con.execute(f"PRAGMA busy_timeout = {int(self.timeout * 1000)}")
                self._retry_busy(self._setup)
        except BaseException:
            self.close()
            raise

    def _setup(self) -> None:
        con = self.con
        mode = str(con.execute("PRAGMA journal_mode").fetchone()[0]).lower()
        if mode != "wal":  # WAL is persistent: only a new (or foreign-mode) file needs the switch
            mode = str(con.execute("PRAGMA journal_mode = WAL").fetchone()[0]).lower()
            if mode != "wal":
                log.warning("%s %s: journal mode is %s, not WAL (file system without shared memory?)",
                            self.what, self.path, mode)
        con.execute("PRAGMA synchronous = FULL")
        con.execute("PRAGMA foreign_keys = ON")
        if self.check_on_open:
            rows = con.execute("PRAGMA quick_check(3)").fetchall()
            if [tuple(r) for r in rows] != [("ok",)]:
                found = "; ".join(str(r[0]) for r in rows)[:300]
                # SQLITE_CORRUPT's own words, so that _errors names the recovery
                raise sqlite3.DatabaseError(f"database disk image is malformed (quick_check: {found})")
        self._setup_schema()

    def _setup_schema(self) -> None:
        """Create or migrate the schema (subclasses)."""

    def _retry_busy(self, fn: Callable[[], None]) -> None:
        """Run ``fn``, retrying on SQLITE_BUSY until the timeout.

        SQLite returns BUSY *without* calling the busy handler when waiting could
        deadlock, e.g. two processes that both read a new file and then both want the
        exclusive lock to switch it to WAL; one of them must back off and retry.
        """
        deadline = time.monotonic() + self.timeout
        delay = 0.005
        while True:
            try:
                fn()
                return
            except sqlite3.OperationalError as exc:
                low = str(exc).lower()
                if not ("locked" in low or "busy" in low) or time.monotonic() + delay > deadline:
                    raise
                if self.con.in_transaction:
                    self.con.execute("ROLLBACK")
                time.sleep(delay * (0.5 + random.random()))
                delay = min(delay * 2, 0.25)

    @contextlib.contextmanager
    def _errors(self, op: str) -> Iterator[None]:
        """Turn sqlite3 errors into :attr:`error` naming the file and the cause."""
        try:
            yield
        except sqlite3.Error as exc:
            why = explain_sqlite_error(exc, self.timeout)
            if self.recovery and why.startswith("the file is corrupt"):
                why += f"; {self.recovery}"
            err = self.error(f"{self.what} {self.path}: {op} failed: {why}")
            code = sqlite_code(exc)
            if code in (SQLITE_BUSY, SQLITE_LOCKED):  # another process holds it: a retry may help
                err.transient = True
            elif code == SQLITE_FULL:  # the store's disk, not the output's (vigproc.pipeline.faults)
                err.sqlite_errorcode, err.disk, err.folder = code, f"{self.what} disk", str(self.path.parent)
            raise err from None

    @property
    def con(self) -> sqlite3.Connection:
        if self._con is None:
            raise self.error(f"{self.what} {self.path} is closed")
        return self._con

    @contextlib.contextmanager
    def _txn(self) -> Iterator[sqlite3.Connection]:
        """One write transaction (BEGIN IMMEDIATE ... COMMIT, ROLLBACK on any error)."""
        con = self.con
        con.execute("BEGIN IMMEDIATE")
        try:
            yield con
        except BaseException:
            if con.in_transaction:  # SQLite may already have rolled back (e.g. disk full)
                con.execute("ROLLBACK")
            raise
        con.execute("COMMIT")

    def _transact(self, op: str, body: Callable[[sqlite3.Connection], Any]) -> Any:
        """Run ``body(con)`` in one write transaction; retried as a whole if SQLite
        reports BUSY without waiting (the transaction was rolled back, so a retry
        cannot apply anything twice); errors become :attr:`error`."""
        out: list[Any] = []

        def attempt() -> None:
            out.clear()
            with self._txn() as con:
                out.append(body(con))

        with self._errors(op):
            self._retry_busy(attempt)
        return out[0]

    def _read(self, op: str, sql: str, args: tuple = ()) -> list[tuple]:
        with self._errors(op):
            return self.con.execute(sql, args).fetchall()

    def close(self) -> None:
        con, self._con = self._con, None
        if con is not None:
            with contextlib.suppress(sqlite3.Error):
                con.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
