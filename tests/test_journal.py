"""The job journal: fingerprints, the entry life cycle, retries, crash recovery, concurrency."""

from __future__ import annotations

import hashlib
import multiprocessing as mp
import os
import signal
import sqlite3
import subprocess
import sys
import time
from pathlib import Path

import pytest

from vigproc.errors import VigprocError
from vigproc.stores.journal import (
    COUNT_KEYS,
    FileChangedError,
    Fingerprint,
    FingerprintError,
    Journal,
    JournalError,
    fingerprint,
)


def _file(tmp_path: Path, name: str, data: bytes) -> Path:
    p = tmp_path / name
    p.write_bytes(data)
    return p


# ------------------------------------------------------------------ fingerprint
def test_fingerprint_is_size_mtime_and_sha256(tmp_path):
    data = os.urandom(3 * (1 << 20) + 17)  # several read chunks
    p = _file(tmp_path, "a.jpg", data)
    fp = fingerprint(p)
    st = p.stat()
    assert fp == Fingerprint(len(data), st.st_mtime_ns, hashlib.sha256(data).hexdigest())
    os.utime(p, ns=(st.st_atime_ns, st.st_mtime_ns + 10**9))
    touched = fingerprint(p)
    assert touched.mtime_ns != fp.mtime_ns and touched.same_content(fp)
    p.write_bytes(data[:-1] + bytes([data[-1] ^ 1]))
    assert not fingerprint(p).same_content(fp)
    assert Fingerprint.from_dict(fp.to_dict()) == fp


def test_fingerprint_refuses_what_is_not_a_regular_file(tmp_path):
    with pytest.raises(FingerprintError, match="a.jpg"):
        fingerprint(tmp_path / "a.jpg")
    with pytest.raises(FingerprintError):
        fingerprint(tmp_path)
    fifo = tmp_path / "pipe.jpg"
    os.mkfifo(fifo)
    with pytest.raises(FingerprintError, match="not a regular file"):  # must not block on the FIFO
        fingerprint(fifo)
    target = _file(tmp_path, "t.jpg", b"x")
    (tmp_path / "link.jpg").symlink_to(target)
    with pytest.raises(FingerprintError):
        fingerprint(tmp_path / "link.jpg")
    assert issubclass(FingerprintError, VigprocError)


def test_fingerprint_locked_file_is_transient(tmp_path, monkeypatch):
    p = _file(tmp_path, "a.jpg", b"data")

    def locked(*a, **kw):  # what a writer's lock on a network share looks like
        raise PermissionError(13, "Permission denied")

    monkeypatch.setattr(os, "open", locked)
    with pytest.raises(FingerprintError, match="Permission denied") as ei:
        fingerprint(p)
    assert ei.value.transient


def test_fingerprint_detects_a_file_growing_while_hashed(tmp_path, monkeypatch):
    p = _file(tmp_path, "a.jpg", b"x" * (3 << 20))
    calls = []
    orig = os.fstat

    def growing_fstat(fd):
        calls.append(fd)
        if len(calls) == 2:  # the second fstat (after hashing) sees the writer's new data
            with open(p, "ab") as fh:
                fh.write(b"more")
        return orig(fd)

    monkeypatch.setattr(os, "fstat", growing_fstat)
    with pytest.raises(FileChangedError) as ei:
        fingerprint(p)
    assert ei.value.transient


# ------------------------------------------------------------------ life cycle
def fp_of(tag: str, size: int = 10) -> Fingerprint:
    return Fingerprint(size, 1, hashlib.sha256(os.fsencode(tag)).hexdigest())


@pytest.fixture
def db(tmp_path) -> Path:
    return tmp_path / "journal.sqlite"


def test_claim_done_and_needs_work(db):
    a, fa = "/in/a.jpg", fp_of("a")
    with Journal(db, job="j") as j:
        assert j.counts() == dict.fromkeys(COUNT_KEYS, 0)
        assert j.needs_work(a, fa)
        assert j.claim(a, fa, worker="w1")
        assert not j.claim(a, fa, worker="w2")  # a duplicate event: harmless
        assert j.counts()["running"] == 1
        j.done(a, fa, {"output": "/out/a.tif"})
        assert not j.needs_work(a, fa)
        assert not j.claim(a, fa, worker="w2")
        e = j.lookup(a)
        assert (e.state, e.claims, e.worker, e.result) == ("done", 1, "w1", {"output": "/out/a.tif"})
        # same content, new mtime (touched): still done
        touched = Fingerprint(fa.size, 99, fa.sha256)
        assert not j.needs_work(a, touched)
        assert j.touch(a, touched) and j.lookup(a).fingerprint.mtime_ns == 99
        # new content: new work, counters restart
        fb = fp_of("a2")
        assert j.needs_work(a, fb)
        assert j.claim(a, fb, worker="w2")
        assert j.lookup(a).claims == 1 and j.lookup(a).result is None
        with pytest.raises(JournalError, match="other content"):
            j.done(a, fa, {})  # the old version's result must not mark the new one
        j.done(a, fb, {})
        assert j.counts()["done"] == 1


def test_done_without_claim_and_bad_arguments(db):
    with Journal(db) as j:
        with pytest.raises(JournalError, match="no entry"):
            j.done("/in/x.jpg", fp_of("x"), {})
        with pytest.raises(JournalError, match="absolute"):
            j.claim("relative/x.jpg", fp_of("x"), worker="w")
        j.claim("/in/x.jpg", fp_of("x"), worker="w")
        with pytest.raises(JournalError, match="not JSON"):
            j.done("/in/x.jpg", fp_of("x"), {"v": float("nan")})
        with pytest.raises(JournalError, match="state"):
            j.entries("bogus")
    with pytest.raises(JournalError):
        Journal(db, job="")


def test_transient_failures_back_off_then_quarantine(db):
    a, fa = "/in/a.jpg", fp_of("a")
    with Journal(db, job="j", retry_base=10.0, retry_cap=25.0) as j:
        t = 1000.0
        delays = []
        for attempt in range(1, 4):
            assert j.claim(a, fa, worker="w", now=t)
            assert j.failed(a, fa, "disk full", transient=True, max_attempts=4, now=t) == "retry"
            e = j.lookup(a)
            assert (e.state, e.attempts, e.reason) == ("pending", attempt, "disk full")
            delays.append(e.not_before - t)
            assert j.counts()["failed"] == 1 and j.counts()["pending"] == 0
            assert not j.claim(a, fa, worker="w", now=t + 0.5 * delays[-1])  # not yet due
            assert j.due(now=t + 0.5 * delays[-1]) == []
            t = e.not_before
            assert j.due(now=t) == [(a, fa)]
        # 10 s, 20 s, then capped at 25 s; each times a jitter factor in [0.8, 1]
        for d, nominal in zip(delays, (10.0, 20.0, 25.0)):
            assert 0.8 * nominal - 1e-6 <= d <= nominal + 1e-6
        assert j.claim(a, fa, worker="w", now=t)
        assert j.failed(a, fa, "disk full", transient=True, max_attempts=4, now=t) == "quarantined"
        assert [e.path for e in j.entries("quarantined")] == [a]
        assert not j.needs_work(a, fa)
        # a permanent failure is quarantined at once; unlimited attempts never quarantine
        b, fb = "/in/b.jpg", fp_of("b")
        j.claim(b, fb, worker="w")
        assert j.failed(b, fb, "corrupt JPEG", transient=False) == "quarantined"
        c, fc = "/in/c.jpg", fp_of("c")
        for k in range(8):
            later = 1e12 + 1e5 * k  # past every backoff so far
            assert j.claim(c, fc, worker="w", now=later)
            assert j.failed(c, fc, "disk full", transient=True, max_attempts=None, now=later) == "retry"
        assert j.counts() == {"pending": 0, "failed": 1, "running": 0, "done": 0, "quarantined": 2}
        assert j.requeue("quarantined") == 2
        assert j.lookup(b).state == "pending" and j.lookup(b).attempts == 0
        assert j.needs_work(b, fb)


def test_recover_release_quarantine_forget(db):
    with Journal(db, job="j") as j:
        for name in "abc":
            assert j.claim(f"/in/{name}", fp_of(name), worker="w")
        j.start("/in/a", fp_of("a"), runner={"pid": 4242, "boot": "b1", "worker_pid": 4243})  # a in progress
        j.release("/in/c", fp_of("c"))
        assert j.lookup("/in/c").state == "pending" and j.lookup("/in/c").attempts == 0
        assert j.lookup("/in/a").runner == {"pid": 4242, "boot": "b1", "worker_pid": 4243}
    # the process "died" with a and b running
    with Journal(db, job="j") as j:
        assert j.recover() == 2
        assert {e.path for e in j.entries("pending")} == {"/in/a", "/in/b", "/in/c"}
        assert j.lookup("/in/a").crashes == 0 and j.lookup("/in/b").crashes == 0
        assert j.claim("/in/a", fp_of("a"), worker="w")
        assert j.lookup("/in/a").claims == 2 and not j.lookup("/in/a").started and j.lookup("/in/a").runner is None
        j.quarantine("/in/unreadable", Fingerprint(5, 1, "-"), "permission denied")
        assert j.lookup("/in/unreadable").state == "quarantined"
        assert j.needs_work("/in/unreadable", fp_of("readable now", 5))
        assert j.forget("/in/c") and j.lookup("/in/c") is None and not j.forget("/in/c")
        j.release("/in/a", fp_of("a"), not_before=time.time() + 60, reason="output disk full")
        e = j.lookup("/in/a")  # given back for the disk: no attempt, a reason, not due yet
        assert (e.state, e.attempts, e.reason) == ("pending", 0, "output disk full")
        assert "/in/a" not in [p for p, _ in j.due()]
        assert not j.claim("/in/a", fp_of("a"), worker="w") and j.claim("/in/a", fp_of("a"), worker="w", now=1e12)


def test_a_kill_of_the_process_never_charges_the_file_in_progress(db):
    """Issue 22: every kill -9 of the daemon charged the healthy file in progress a
    crash (three kills quarantined it).  The process's own death is not the file's:
    however often it happens, the file goes back uncharged."""
    with Journal(db, job="j") as j:
        for _ in range(5):
            assert j.claim("/in/a", fp_of("a"), worker="w")
            j.start("/in/a", fp_of("a"))  # started by a worker: the old code charged this one
            assert j.lookup("/in/a").runner["pid"] == os.getpid()
            assert j.recover() == 1
        e = j.lookup("/in/a")
        assert e.state == "pending" and e.crashes == 0 and e.attempts == 0 and e.claims == 5


def test_a_worker_crash_under_a_live_process_is_charged_and_quarantines(db):
    """What a file does cause -- its worker dying or hanging on it while the daemon
    lives -- is charged at once, and max_crashes of them quarantine it."""
    with Journal(db, job="j") as j:
        for n in (1, 2):
            assert j.claim("/in/a", fp_of("a"), worker="w", now=1e12)
            j.start("/in/a", fp_of("a"))
            outcome = j.crashed("/in/a", fp_of("a"), "died (worker exit code -11)", max_crashes=3)
            e = j.lookup("/in/a")
            assert outcome == "retry" and (e.state, e.crashes, e.attempts) == ("pending", n, 0)
            assert e.not_before > time.time()  # backed off
        assert j.claim("/in/a", fp_of("a"), worker="w", now=1e12)
        j.start("/in/a", fp_of("a"))
        assert j.crashed("/in/a", fp_of("a"), "died (worker exit code -11)", max_crashes=3) == "quarantined"
        e = j.lookup("/in/a")
        assert e.state == "quarantined" and e.crashes == 3 and "3 times" in e.reason and "exit code -11" in e.reason
        with pytest.raises(JournalError):  # only a running entry can be charged
            j.crashed("/in/a", fp_of("a"), "died", max_crashes=3)


def test_recover_never_charges_a_file_that_was_only_claimed(db):
    """A file queued for a worker (claimed, not started) when the process is killed did
    not cause the kill: however often that happens, it goes back without a crash."""
    with Journal(db, job="j") as j:
        for _ in range(5):
            assert j.claim("/in/queued", fp_of("q"), worker="w")
            with pytest.raises(JournalError):
                j.start("/in/other", fp_of("o"))  # only a running entry can be started
            assert j.recover() == 1
        e = j.lookup("/in/queued")
        assert e.state == "pending" and e.crashes == 0 and e.claims == 5


def test_journal_of_an_older_vigproc_gains_the_started_column(tmp_path):
    old = tmp_path / "old.sqlite"
    with Journal(old, job="j") as j:
        assert j.claim("/in/a", fp_of("a"), worker="w")
        j.con.execute("ALTER TABLE entries DROP COLUMN started")  # as an older vigproc wrote it
        j.con.execute("ALTER TABLE entries DROP COLUMN runner")
    with Journal(old, job="j") as j:
        e = j.lookup("/in/a")
        assert e.state == "running" and not e.started and e.runner is None
        j.start("/in/a", fp_of("a"))
        assert j.lookup("/in/a").started and j.lookup("/in/a").runner["pid"] == os.getpid()


def test_jobs_share_a_database_without_seeing_each_other(db):
    with Journal(db, job="watch A") as a, Journal(db, job="batch B") as b:
        assert a.claim("/x", fp_of("x"), worker="w")
        assert b.claim("/x", fp_of("x"), worker="w")
        a.done("/x", fp_of("x"), {})
        assert a.counts()["done"] == 1 and b.counts()["running"] == 1
        assert b.recover() == 1 and a.lookup("/x").state == "done"


def test_hostile_paths_round_trip(db):
    names = ["/in/sp ace 'q\" -x.jpg", "/in/new\nline.jpg", "/in/ünï cødé 写真.jpg", "/in/-lead.jpg",
             os.fsdecode(b"/in/latin1-\xe9.jpg")]  # not UTF-8: a surrogate-escaped str
    with Journal(db) as j:
        for n in names:
            assert j.claim(n, fp_of(n), worker="w")
            j.done(n, fp_of(n), {"file": n})
        assert sorted(e.path for e in j.entries("done")) == sorted(names)
        assert all(not j.needs_work(n, fp_of(n)) for n in names)


def test_not_a_journal_or_corrupt(tmp_path):
    other = tmp_path / "other.sqlite"
    con = sqlite3.connect(other)
    con.execute("CREATE TABLE t (x)")
    con.commit()
    con.close()
    with pytest.raises(JournalError, match="not a vigproc journal"):
        Journal(other)
    junk = _file(tmp_path, "junk.sqlite", b"this is not a database" * 100)
    with pytest.raises(JournalError, match="corrupt or not an SQLite database"):
        Journal(junk)
    with pytest.raises(JournalError, match="folder"):
        Journal(tmp_path)


# ------------------------------------------------------------------ concurrency & crashes
def _claimer(db: str, paths: list[str], worker: str, out) -> None:
    won = []
    with Journal(db, job="race") as j:
        for p in paths:
            if j.claim(p, fp_of(p), worker=worker):
                won.append(p)
                j.done(p, fp_of(p), {"by": worker})
    out.put(won)


def test_concurrent_processes_claim_each_file_exactly_once(db):
    paths = [f"/in/{i:03d}.jpg" for i in range(150)]
    Journal(db, job="race").close()
    ctx = mp.get_context("spawn")
    q = ctx.Queue()
    procs = [ctx.Process(target=_claimer, args=(str(db), paths[::step], f"w{k}", q))
             for k, step in enumerate((1, 1, -1))]  # two front-to-back, one back-to-front
    for p in procs:
        p.start()
    won = [q.get(timeout=120) for _ in procs]
    for p in procs:
        p.join(timeout=60)
        assert p.exitcode == 0
    flat = [p for w in won for p in w]
    assert sorted(flat) == paths  # every file once, none twice
    with Journal(db, job="race") as j:
        assert j.counts()["done"] == len(paths)
        assert all(e.claims == 1 for e in j.entries())


_KILLED_WRITER = r"""
import sys, hashlib
from vigproc.stores.journal import Journal, Fingerprint
j = Journal(sys.argv[1], job="k")
i = 0
while True:
    p = f"/in/{i:06d}"
    fp = Fingerprint(1, 1, hashlib.sha256(p.encode()).hexdigest())
    j.claim(p, fp, worker="w")
    j.done(p, fp, {"i": i})
    print(i, flush=True)
    i += 1
"""


def test_kill_minus_9_mid_write_loses_nothing_reported(db):
    proc = subprocess.Popen([sys.executable, "-c", _KILLED_WRITER, str(db)], stdout=subprocess.PIPE, text=True)
    reported = -1
    deadline = time.monotonic() + 60
    while reported < 40 and time.monotonic() < deadline:
        reported = int(proc.stdout.readline())
    os.kill(proc.pid, signal.SIGKILL)
    proc.wait()
    proc.stdout.close()
    with Journal(db, job="k") as j:
        assert j.con.execute("PRAGMA integrity_check").fetchone()[0] == "ok"
        done = {e.path for e in j.entries("done")}
        # every done() that returned (its number was printed) is on disk ...
        assert {f"/in/{i:06d}" for i in range(reported + 1)} <= done
        # ... and at most the one claimed when killed is left running; recover() hands it back
        assert j.counts()["running"] <= 1
        assert j.recover() == j.counts()["pending"]
