"""A durable record of every input file of a job, so that a restarted job neither repeats nor misses work.

The journal is an embedded SQLite database shared by the watch-folder daemon
(``vigproc watch``) and batch runs.  Each input file is one *entry* per job, keyed by
its absolute path and remembering the :class:`Fingerprint` (size, modification time
and SHA-256 of the content) it had when it was last handled, and its state::

    (new) --claim--> running --done--> done
                        |  \\--failed(transient, attempts left)--> pending --claim--> running ...
                        |   \\--failed(permanent, or no attempts left)--> quarantined
                        |    \\--crashed(its worker died on it)--> pending (quarantined at max_crashes)
                        \\--(process killed) recover()--> pending (never charged)

:meth:`Journal.start` marks a claimed entry as actually being worked on, with who
works on it (:func:`runner_identity`: host, boot, process and worker).  A crash is
charged only by :meth:`Journal.crashed`, which the process that survived it calls
(a worker died or hung on the file while the daemon lived).  :meth:`Journal.recover`
charges nothing: an entry left running means the process that owned it stopped
(``kill -9``, a power cut), and nothing ties that to the file -- decoding happens
in workers, whose deaths the surviving daemon charges at once.

A path whose content changes (a new SHA-256 or size) is new work whatever its
entry's state; a path whose content is unchanged and is ``done`` or ``quarantined``
is never handed out again.  :meth:`Journal.claim` is one atomic transaction, so
duplicate events and several workers or processes racing for the same file are
harmless: exactly one of them gets it.

Exactly-once outputs rely on idempotent output names plus atomic publishing (see
:mod:`vigproc.atomic`): if a process dies after publishing an output but before
:meth:`Journal.done`, :meth:`Journal.recover` makes the entry pending again and the
rerun rewrites the same names atomically, so each input still has exactly one set
of outputs.

Counts
------
:meth:`Journal.counts` reports ``pending`` (never failed), ``failed`` (pending again
after a transient failure, waiting for its retry time), ``running``, ``done`` and
``quarantined``; every entry is counted once.

Durability and concurrency
--------------------------
WAL journal mode (readers never block the writer), ``synchronous=FULL`` (a ``done``
that returned survives a power cut), every change one ``BEGIN IMMEDIATE``
transaction (the write lock is taken up front, so a read-modify-write cannot
interleave with another writer), and a busy timeout.  A :class:`Journal` object is
used by one thread; each process or thread opens its own.  Several jobs (watch
folders, batch runs) may share one database file.

References
----------
SQLite, "Write-Ahead Logging", https://www.sqlite.org/wal.html;
"Atomic Commit In SQLite", https://www.sqlite.org/atomiccommit.html.
"""

from __future__ import annotations

import errno
import hashlib
import json
import logging
import os
import sqlite3
import stat
import time
from dataclasses import dataclass
from datetime import datetime, timezone
from typing import Any, Callable

from vigproc.stores.db import SQLiteFile
from vigproc.stores.retry import DEFAULT_MAX_ATTEMPTS, DEFAULT_RETRY_BASE, DEFAULT_RETRY_CAP, retry_delay
from vigproc.errors import EXIT_CODES, SETTINGS, ImageReadError, VigprocError

__all__ = [
    "COUNT_KEYS",
    "Entry",
    "FileChangedError",
    "Fingerprint",
    "FingerprintError",
    "Journal",
    "JournalError",
    "STATES",
    "boot_id",
    "fingerprint",
    "runner_identity",
]

log = logging.getLogger(__name__)

#: States an entry can be in.
STATES = ("pending", "running", "done", "quarantined")
#: Keys of :meth:`Journal.counts` ("failed": pending again after a transient failure).
COUNT_KEYS = ("pending", "failed", "running", "done", "quarantined")
#: Schema version written into the database.
SCHEMA_VERSION = 1
#: Busy timeout (seconds) for a write lock held by another process.
DEFAULT_TIMEOUT = 30.0
#: Longest reason text kept (a traceback-sized message is cut).
MAX_REASON = 4000
_CHUNK = 1 << 20
# errors reading a file that waiting may cure (a writer's lock on a network share, a busy device)
_TRANSIENT_ERRNOS = frozenset(getattr(errno, n) for n in ("EACCES", "EBUSY", "EAGAIN", "ETXTBSY", "EINTR", "ENOLCK",
                                                         "ESTALE", "ETIMEDOUT", "EIO") if hasattr(errno, n))


class JournalError(VigprocError):
    """The journal database cannot be used (corrupt, locked, not a journal) or was misused."""

    exit_code = EXIT_CODES["journal"]
    blame = SETTINGS


class FingerprintError(ImageReadError):
    """A file cannot be read to fingerprint it (missing, not a regular file, no permission).

    ``transient`` says whether waiting may help (a locked or still-changing file).
    """

    transient = False


class FileChangedError(FingerprintError):
    """The file changed while it was being fingerprinted (it is still being written)."""

    transient = True


@dataclass(frozen=True)
class Fingerprint:
    """What identifies one version of a file's content.

    Attributes
    ----------
    size : int
        Bytes.
    mtime_ns : int
        Modification time (ns since the epoch); recorded, but content identity is
        ``size`` + ``sha256`` (a ``touch`` is not new work).
    sha256 : str
        Hex digest of the content.
    """

    size: int
    mtime_ns: int
    sha256: str

    def same_content(self, other: Fingerprint) -> bool:
        return self.size == other.size and self.sha256 == other.sha256

    def to_dict(self) -> dict[str, Any]:
        return {"size": self.size, "mtime_ns": self.mtime_ns, "sha256": self.sha256}

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> Fingerprint:
        return cls(int(d["size"]), int(d["mtime_ns"]), str(d["sha256"]))


def _describe_oserror(exc: OSError) -> str:
    return exc.strerror or str(exc)


def fingerprint(path: str | os.PathLike[str]) -> Fingerprint:
    """Size, modification time and streamed SHA-256 of a regular file.

    The file is opened without following a final symbolic link and without blocking
    (a FIFO named like an image must not hang the caller), checked to be a regular
    file, hashed, and its size and mtime compared before and after hashing.

    Parameters
    ----------
    path : str or os.PathLike

    Returns
    -------
    Fingerprint

    Raises
    ------
    FingerprintError
        Missing, not a regular file, a symbolic link or unreadable (``transient``
        for errors a retry may cure: EACCES/EBUSY/EAGAIN, as with a file locked by
        its writer on a network share).
    FileChangedError
        Size or mtime changed while hashing (still being written).
    """
    p = os.fspath(path)
    flags = os.O_RDONLY | getattr(os, "O_NONBLOCK", 0) | getattr(os, "O_NOFOLLOW", 0) | getattr(os, "O_CLOEXEC", 0)
    try:
        fd = os.open(p, flags)
    except OSError as exc:
        err = FingerprintError(f"cannot read {p!r}: {_describe_oserror(exc)}")
        err.transient = exc.errno in _TRANSIENT_ERRNOS
        raise err from None
    try:
        st0 = os.fstat(fd)
        if not stat.S_ISREG(st0.st_mode):
            raise FingerprintError(f"cannot read {p!r}: not a regular file")
        h = hashlib.sha256()
        with os.fdopen(os.dup(fd), "rb", buffering=0) as fh:
            while chunk := fh.read(_CHUNK):
                h.update(chunk)
        st1 = os.fstat(fd)
    except FingerprintError:
        raise
    except OSError as exc:
        err = FingerprintError(f"cannot read {p!r}: {_describe_oserror(exc)}")
        err.transient = exc.errno in _TRANSIENT_ERRNOS
        raise err from None
    finally:
        os.close(fd)
    if (st0.st_size, st0.st_mtime_ns) != (st1.st_size, st1.st_mtime_ns):
        raise FileChangedError(f"{p!r} changed while it was read (still being written?)")
    return Fingerprint(int(st1.st_size), int(st1.st_mtime_ns), h.hexdigest())


@dataclass(frozen=True)
class Entry:
    """One input file of a job as the journal records it."""

    path: str
    fingerprint: Fingerprint
    state: str
    attempts: int  # failed attempts with this content
    crashes: int  # times a process died while it was started (see Journal.start)
    claims: int  # times it was handed out with this content
    not_before: float  # epoch seconds: no retry before
    worker: str | None
    reason: str | None  # why it last failed / was quarantined
    result: dict[str, Any] | None  # what done() stored
    first_seen: str
    updated: str
    started: bool = False  # begun by a worker since it was last claimed (see Journal.start)
    runner: dict[str, Any] | None = None  # who began it (runner_identity), while running

    @property
    def retrying(self) -> bool:
        """Pending again after a transient failure (counted as "failed")."""
        return self.state == "pending" and self.attempts > 0


def _now_iso() -> str:
    return datetime.now(timezone.utc).isoformat(timespec="milliseconds").replace("+00:00", "Z")


_SCHEMA = """
CREATE TABLE IF NOT EXISTS vigproc_journal_meta (key TEXT PRIMARY KEY, value TEXT NOT NULL);
CREATE TABLE IF NOT EXISTS entries (
    job        TEXT    NOT NULL,
    path       BLOB    NOT NULL,   -- os.fsencode(absolute path): any byte string a file name can be
    size       INTEGER NOT NULL,
    mtime_ns   INTEGER NOT NULL,
    sha256     TEXT    NOT NULL,
    state      TEXT    NOT NULL CHECK (state IN ('pending', 'running', 'done', 'quarantined')),
    attempts   INTEGER NOT NULL DEFAULT 0,
    crashes    INTEGER NOT NULL DEFAULT 0,
    started    INTEGER NOT NULL DEFAULT 0,  -- begun since the last claim, not just claimed: see start()
    runner     TEXT,                        -- JSON: who began it (host, boot, pid, worker): see start()
    claims     INTEGER NOT NULL DEFAULT 0,
    not_before REAL    NOT NULL DEFAULT 0,
    worker     TEXT,
    reason     TEXT,
    result     TEXT,
    first_seen TEXT    NOT NULL,
    updated    TEXT    NOT NULL,
    PRIMARY KEY (job, path)
);
CREATE INDEX IF NOT EXISTS entries_by_state ON entries (job, state, not_before);
"""

_COLUMNS = ("path, size, mtime_ns, sha256, state, attempts, crashes, claims, not_before, worker, reason, result, "
            "first_seen, updated, started, runner")


def boot_id() -> str | None:
    """This boot of the machine (Linux), or None: a process of another boot is long gone."""
    try:
        with open("/proc/sys/kernel/random/boot_id", encoding="ascii") as fh:
            return fh.read().strip() or None
    except OSError:
        return None


def runner_identity(worker_pid: int | None = None) -> dict[str, Any]:
    """Who is working on a file, as :meth:`Journal.start` records it: host, boot, the
    calling process (the daemon) and the worker process."""
    return {"host": os.uname().nodename, "boot": boot_id(), "pid": os.getpid(), "worker_pid": worker_pid}


class Journal(SQLiteFile):
    """The journal of one job in an SQLite database.

    Parameters
    ----------
    db_path : str or Path
        Database file (created with its folder if missing).
    job : str
        Name of the job; several jobs may share a database and never see each
        other's entries.
    timeout : float
        Seconds to wait for another process's write lock.
    retry_base, retry_cap : float
        Backoff after the n-th transient failure: ``min(cap, base * 2**(n-1))``
        seconds, times a random factor in [0.8, 1] (so retries of many files do
        not fire in lockstep).

    Raises
    ------
    JournalError
        The file cannot be opened, is not a vigproc journal, is corrupt or is from a
        newer vigproc.

    Notes
    -----
    Paths are stored as given; they must be absolute (resolve them first).  One
    object per thread.  Use as a context manager or call :meth:`close`.  The file
    is opened as :class:`vigproc.stores.db.SQLiteFile` does (WAL, fsync at every commit).
    """

    error = JournalError
    what = "journal"
    recovery = "move it aside and rerun (a new journal is started)"

    def __init__(self, db_path: str | os.PathLike[str], *, job: str = "default", timeout: float = DEFAULT_TIMEOUT,
                 retry_base: float = DEFAULT_RETRY_BASE, retry_cap: float = DEFAULT_RETRY_CAP) -> None:
        if not isinstance(job, str) or not job or len(job) > 4096:
            raise JournalError(f"journal job name must be a non-empty string, got {job!r}")
        if not (retry_base >= 0 and retry_cap >= retry_base):
            raise JournalError(f"bad retry backoff: base {retry_base}, cap {retry_cap}")
        self.job = job
        self.retry_base = float(retry_base)
        self.retry_cap = float(retry_cap)
        super().__init__(db_path, timeout=timeout)

    # ------------------------------------------------------------ plumbing
    def _setup_schema(self) -> None:
        con = self.con
        names = {r[0] for r in con.execute("SELECT name FROM sqlite_master WHERE type = 'table'")}
        if names and "vigproc_journal_meta" not in names:
            raise JournalError(f"{self.path} is an SQLite database but not a vigproc journal")
        with self._txn() as con:  # retried as a whole by the caller on BUSY
            for statement in _SCHEMA.split(";\n"):  # not executescript: it would COMMIT first
                if statement.strip():
                    con.execute(statement)
            # a journal of an older vigproc lacks "started"; older code ignores the column
            columns = {r[1] for r in con.execute("PRAGMA table_info(entries)")}
            if "started" not in columns:
                con.execute("ALTER TABLE entries ADD COLUMN started INTEGER NOT NULL DEFAULT 0")
            if "runner" not in columns:  # likewise
                con.execute("ALTER TABLE entries ADD COLUMN runner TEXT")
            row = con.execute("SELECT value FROM vigproc_journal_meta WHERE key = 'schema'").fetchone()
            if row is None:
                con.execute("INSERT INTO vigproc_journal_meta VALUES ('schema', ?)", (str(SCHEMA_VERSION),))
            elif int(row[0]) > SCHEMA_VERSION:
                raise JournalError(f"journal {self.path} has schema {row[0]}, newer than this vigproc's "
                                   f"({SCHEMA_VERSION}); upgrade vigproc")

    @staticmethod
    def _key(path: str | os.PathLike[str]) -> bytes:
        p = os.fspath(path)
        raw = p if isinstance(p, bytes) else os.fsencode(p)
        if not os.path.isabs(raw):
            raise JournalError(f"journal paths must be absolute, got {os.fsdecode(raw)!r}")
        return raw

    def _entry(self, row: tuple) -> Entry:
        (path, size, mtime, sha, state, attempts, crashes, claims, not_before, worker, reason, result,
         first_seen, updated, started, runner) = row
        try:
            res = json.loads(result) if result is not None else None
        except ValueError:
            res = {"unparsed": result}
        try:
            who = json.loads(runner) if runner is not None else None
        except ValueError:
            who = {"unparsed": runner}
        return Entry(os.fsdecode(bytes(path)), Fingerprint(int(size), int(mtime), str(sha)), str(state), int(attempts),
                     int(crashes), int(claims), float(not_before), worker, reason, res, str(first_seen), str(updated),
                     bool(started), who)

    def _backoff(self, attempts: int) -> float:
        return retry_delay(attempts, self.retry_base, self.retry_cap, jitter=True)

    # ------------------------------------------------------------ queries
    def lookup(self, path: str | os.PathLike[str]) -> Entry | None:
        """The entry of ``path`` (any state), or None."""
        rows = self._read("lookup", f"SELECT {_COLUMNS} FROM entries WHERE job = ? AND path = ?",
                          (self.job, self._key(path)))
        return self._entry(rows[0]) if rows else None

    def needs_work(self, path: str | os.PathLike[str], fp: Fingerprint) -> bool:
        """False if this path with this content is done or quarantined; True otherwise
        (unknown, new content, pending or running -- :meth:`claim` decides who gets it)."""
        e = self.lookup(path)
        if e is None or not e.fingerprint.same_content(fp):
            return True
        return e.state not in ("done", "quarantined")

    def due(self, now: float | None = None, *, limit: int | None = None) -> list[tuple[str, Fingerprint]]:
        """Pending entries whose retry time has come (oldest retry time first)."""
        t = time.time() if now is None else float(now)
        sql = ("SELECT path, size, mtime_ns, sha256 FROM entries WHERE job = ? AND state = 'pending' "
               "AND not_before <= ? ORDER BY not_before, path")
        args: tuple = (self.job, t)
        if limit is not None:
            sql += " LIMIT ?"
            args += (int(limit),)
        return [(os.fsdecode(bytes(p)), Fingerprint(int(s), int(m), str(h))) for p, s, m, h in self._read("due", sql, args)]

    def next_retry(self) -> float | None:
        """Earliest retry time (epoch seconds) of a pending entry, or None."""
        rows = self._read("next_retry", "SELECT min(not_before) FROM entries WHERE job = ? AND state = 'pending'",
                          (self.job,))
        return None if not rows or rows[0][0] is None else float(rows[0][0])

    def counts(self) -> dict[str, int]:
        """Entries per state: pending, failed (pending again after a transient failure),
        running, done, quarantined."""
        out = dict.fromkeys(COUNT_KEYS, 0)
        rows = self._read("counts", "SELECT state, attempts > 0, count(*) FROM entries WHERE job = ? GROUP BY 1, 2",
                          (self.job,))
        for state, retried, n in rows:
            key = "failed" if state == "pending" and retried else str(state)
            out[key] = out.get(key, 0) + int(n)
        return out

    def entries(self, state: str | None = None) -> list[Entry]:
        """All entries of the job, or those in ``state`` (one of :data:`COUNT_KEYS`)."""
        if state is None:
            where, args = "", ()
        elif state == "failed":
            where, args = " AND state = 'pending' AND attempts > 0", ()
        elif state == "pending":
            where, args = " AND state = 'pending' AND attempts = 0", ()
        elif state in STATES:
            where, args = " AND state = ?", (state,)
        else:
            raise JournalError(f"unknown journal state {state!r} (choose from {', '.join(COUNT_KEYS)})")
        rows = self._read("entries", f"SELECT {_COLUMNS} FROM entries WHERE job = ?{where} ORDER BY path",
                          (self.job, *args))
        return [self._entry(r) for r in rows]

    # ------------------------------------------------------------ changes
    def claim(self, path: str | os.PathLike[str], fp: Fingerprint, *, worker: str, now: float | None = None) -> bool:
        """Atomically take ``path`` with content ``fp`` for processing.

        True if the caller now owns it (state ``running``): the path is new, its
        content changed (attempt counters restart), or it is pending and due.  False
        if it is running elsewhere, done or quarantined with this content, or
        waiting for its retry time.
        """
        key = self._key(path)
        t = time.time() if now is None else float(now)
        stamp = _now_iso()

        def body(con: sqlite3.Connection) -> bool:
            row = con.execute("SELECT size, sha256, state, not_before FROM entries WHERE job = ? AND path = ?",
                              (self.job, key)).fetchone()
            if row is None:
                con.execute(
                    "INSERT INTO entries (job, path, size, mtime_ns, sha256, state, claims, worker, first_seen, updated)"
                    " VALUES (?, ?, ?, ?, ?, 'running', 1, ?, ?, ?)",
                    (self.job, key, fp.size, fp.mtime_ns, fp.sha256, worker, stamp, stamp))
                return True
            size, sha, state, not_before = row
            if (int(size), str(sha)) != (fp.size, fp.sha256):
                con.execute(
                    "UPDATE entries SET size = ?, mtime_ns = ?, sha256 = ?, state = 'running', attempts = 0, crashes = 0,"
                    " started = 0, runner = NULL, claims = 1, not_before = 0, worker = ?, reason = NULL, result = NULL,"
                    " updated = ?"
                    " WHERE job = ? AND path = ?",
                    (fp.size, fp.mtime_ns, fp.sha256, worker, stamp, self.job, key))
                return True
            if state == "pending" and float(not_before) <= t:
                con.execute("UPDATE entries SET state = 'running', started = 0, runner = NULL, claims = claims + 1,"
                            " mtime_ns = ?,"
                            " worker = ?, updated = ? WHERE job = ? AND path = ?",
                            (fp.mtime_ns, worker, stamp, self.job, key))
                return True
            return False

        return bool(self._transact("claim", body))

    def _update_running(self, op: str, path: str | os.PathLike[str], fp: Fingerprint,
                        change: Callable[[sqlite3.Connection, bytes, tuple], Any]) -> Any:
        """Apply ``change`` to the running entry of ``path`` with content ``fp``;
        JournalError if there is none (not claimed, or claimed with other content)."""
        key = self._key(path)

        def body(con: sqlite3.Connection) -> Any:
            row = con.execute("SELECT size, sha256, state, attempts, crashes FROM entries WHERE job = ? AND path = ?",
                              (self.job, key)).fetchone()
            if row is None or (int(row[0]), str(row[1])) != (fp.size, fp.sha256) or row[2] != "running":
                what = "no entry" if row is None else (
                    f"state {row[2]}" if row[2] != "running" else "it was claimed with other content")
                raise JournalError(f"{op}({os.fsdecode(key)!r}): not running with this content ({what})")
            return change(con, key, row)

        return self._transact(op, body)

    def start(self, path: str | os.PathLike[str], fp: Fingerprint, *, runner: dict[str, Any] | None = None) -> None:
        """Record that work on a claimed file has begun (a worker took it from its queue),
        and who works on it (``runner``, by default :func:`runner_identity` of the caller).

        Raises
        ------
        JournalError
            The file is not running with this content.
        """
        stamp = _now_iso()
        who = json.dumps(runner if runner is not None else runner_identity(), sort_keys=True, default=str)

        def change(con: sqlite3.Connection, key: bytes, row: tuple) -> None:
            con.execute("UPDATE entries SET started = 1, runner = ?, updated = ? WHERE job = ? AND path = ?",
                        (who, stamp, self.job, key))

        self._update_running("start", path, fp, change)

    def done(self, path: str | os.PathLike[str], fp: Fingerprint, result: dict[str, Any]) -> None:
        """Record a claimed file as processed, with ``result`` (outputs, sidecar; JSON).

        Raises
        ------
        JournalError
            The file is not running with this content (never claimed, or already
            finished), or ``result`` is not JSON-able.
        """
        try:
            text = json.dumps(result, sort_keys=True, allow_nan=False)
        except (TypeError, ValueError) as exc:
            raise JournalError(f"done({os.fspath(path)!r}): result is not JSON: {exc}") from None
        stamp = _now_iso()

        def change(con: sqlite3.Connection, key: bytes, row: tuple) -> None:
            con.execute("UPDATE entries SET state = 'done', result = ?, reason = NULL, not_before = 0, mtime_ns = ?,"
                        " updated = ? WHERE job = ? AND path = ?", (text, fp.mtime_ns, stamp, self.job, key))

        self._update_running("done", path, fp, change)

    def failed(self, path: str | os.PathLike[str], fp: Fingerprint, reason: str, *, transient: bool,
               max_attempts: int | None = DEFAULT_MAX_ATTEMPTS, now: float | None = None) -> str:
        """Record a failed attempt of a claimed file.

        Parameters
        ----------
        reason : str
            Why (kept, cut to :data:`MAX_REASON` characters).
        transient : bool
            Whether a later attempt may succeed (a locked file, a full disk).
        max_attempts : int or None
            A transient failure is retried while fewer than this many attempts
            failed (None: retried forever, as for a full disk).

        Returns
        -------
        str
            ``"retry"`` (pending again, not before a backoff time) or
            ``"quarantined"``.
        """
        t = time.time() if now is None else float(now)
        why = str(reason)[:MAX_REASON]
        stamp = _now_iso()

        def change(con: sqlite3.Connection, key: bytes, row: tuple) -> str:
            attempts = int(row[3]) + 1
            if transient and (max_attempts is None or attempts < max_attempts):
                con.execute("UPDATE entries SET state = 'pending', attempts = ?, not_before = ?, reason = ?, updated = ?"
                            " WHERE job = ? AND path = ?",
                            (attempts, t + self._backoff(attempts), why, stamp, self.job, key))
                return "retry"
            con.execute("UPDATE entries SET state = 'quarantined', attempts = ?, not_before = 0, reason = ?,"
                        " updated = ? WHERE job = ? AND path = ?", (attempts, why, stamp, self.job, key))
            return "quarantined"

        return str(self._update_running("failed", path, fp, change))

    def release(self, path: str | os.PathLike[str], fp: Fingerprint, *, not_before: float = 0.0,
                reason: str | None = None) -> None:
        """Give a claimed file back without counting an attempt: the caller stopped before
        finishing, e.g. the file changed under it or the process is shutting down, or the
        failure was not the file's (the output disk is full: then ``not_before``, epoch
        seconds, delays it and ``reason`` says why)."""
        stamp = _now_iso()
        why = None if reason is None else str(reason)[:MAX_REASON]

        def change(con: sqlite3.Connection, key: bytes, row: tuple) -> None:
            con.execute("UPDATE entries SET state = 'pending', not_before = ?, reason = coalesce(?, reason),"
                        " updated = ? WHERE job = ? AND path = ?", (float(not_before), why, stamp, self.job, key))

        self._update_running("release", path, fp, change)

    def quarantine(self, path: str | os.PathLike[str], fp: Fingerprint, reason: str) -> None:
        """Record ``path`` (with content ``fp``) as quarantined whatever its state, e.g. a
        file that could not even be fingerprinted (pass what is known of it)."""
        key = self._key(path)
        why = str(reason)[:MAX_REASON]
        stamp = _now_iso()

        def body(con: sqlite3.Connection) -> None:
            con.execute(
                "INSERT INTO entries (job, path, size, mtime_ns, sha256, state, reason, first_seen, updated)"
                " VALUES (?, ?, ?, ?, ?, 'quarantined', ?, ?, ?) ON CONFLICT (job, path) DO UPDATE SET"
                " size = excluded.size, mtime_ns = excluded.mtime_ns, sha256 = excluded.sha256, state = 'quarantined',"
                " reason = excluded.reason, not_before = 0, updated = excluded.updated",
                (self.job, key, fp.size, fp.mtime_ns, fp.sha256, why, stamp, stamp))

        self._transact("quarantine", body)

    def crashed(self, path: str | os.PathLike[str], fp: Fingerprint, reason: str, *, max_crashes: int | None,
                now: float | None = None) -> str:
        """Charge a started file a crash: the worker processing it died or hung while the
        caller lived, so the file is the likely cause.

        Returns
        -------
        str
            ``"retry"`` (pending again after a backoff) or ``"quarantined"`` (it has now
            crashed ``max_crashes`` times: a file that kills its worker every time must
            not crash-loop the job).
        """
        t = time.time() if now is None else float(now)
        stamp = _now_iso()

        def change(con: sqlite3.Connection, key: bytes, row: tuple) -> str:
            n = int(row[4]) + 1
            if max_crashes is not None and n >= max_crashes:
                why = f"{reason}; it crashed or hung its worker {n} times; not retried"[:MAX_REASON]
                con.execute("UPDATE entries SET state = 'quarantined', crashes = ?, started = 0, not_before = 0,"
                            " reason = ?, updated = ? WHERE job = ? AND path = ?", (n, why, stamp, self.job, key))
                return "quarantined"
            con.execute("UPDATE entries SET state = 'pending', crashes = ?, started = 0, not_before = ?, reason = ?,"
                        " updated = ? WHERE job = ? AND path = ?",
                        (n, t + self._backoff(n), str(reason)[:MAX_REASON], stamp, self.job, key))
            return "retry"

        return str(self._update_running("crashed", path, fp, change))

    def recover(self) -> int:
        """Entries left ``running`` by a process that stopped become ``pending`` again, due
        now, *without* a crash charge.

        The process that owned them is gone (killed, crashed, or the machine restarted:
        see each entry's ``runner``), and its death is not evidence against the file: the
        files in progress when a daemon is killed are as healthy as any.  What a file
        does cause, a worker dying or hanging on it under a live daemon, is charged at
        once by :meth:`crashed`.

        Call it when no other process works on this job (the daemon holds a per-job
        lock while it runs).

        Returns
        -------
        int
            Number of entries recovered (read them first with ``entries("running")``
            to see who ran them).
        """
        stamp = _now_iso()

        def body(con: sqlite3.Connection) -> int:
            return con.execute("UPDATE entries SET state = 'pending', started = 0, not_before = 0, updated = ?"
                               " WHERE job = ? AND state = 'running'", (stamp, self.job)).rowcount

        n = int(self._transact("recover", body))
        if n:
            log.info("journal %s: %d entries of job %r were left running by a stopped process; pending again "
                     "(not charged a crash)", self.path, n, self.job)
        return n

    def touch(self, path: str | os.PathLike[str], fp: Fingerprint) -> bool:
        """Remember ``fp``'s mtime for an entry with the same content (a touched file), so
        that a later rescan can recognise it from its size and mtime without hashing.
        Returns whether an entry was updated."""
        key = self._key(path)

        def body(con: sqlite3.Connection) -> bool:
            cur = con.execute("UPDATE entries SET mtime_ns = ? WHERE job = ? AND path = ? AND size = ? AND sha256 = ?",
                              (fp.mtime_ns, self.job, key, fp.size, fp.sha256))
            return cur.rowcount > 0

        return bool(self._transact("touch", body))

    def requeue(self, state: str = "quarantined") -> int:
        """Make every entry in ``state`` (``quarantined`` or ``done``) pending again with
        fresh attempt counters, e.g. after the cause of failures was fixed.  Returns the
        number of entries."""
        if state not in ("quarantined", "done"):
            raise JournalError(f"requeue: state must be 'quarantined' or 'done', got {state!r}")
        stamp = _now_iso()

        def body(con: sqlite3.Connection) -> int:
            cur = con.execute("UPDATE entries SET state = 'pending', attempts = 0, crashes = 0, not_before = 0,"
                              " updated = ? WHERE job = ? AND state = ?", (stamp, self.job, state))
            return cur.rowcount

        return int(self._transact("requeue", body))

    def forget(self, path: str | os.PathLike[str]) -> bool:
        """Drop the entry of ``path`` (e.g. a pending file that was deleted). Returns
        whether there was one."""
        key = self._key(path)
        return bool(self._transact("forget", lambda con: con.execute(
            "DELETE FROM entries WHERE job = ? AND path = ?", (self.job, key)).rowcount > 0))
