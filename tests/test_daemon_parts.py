"""The daemon's parts in-process (vigproc.frontends.daemon: watcher, scheduler, recorder),
without workers: the orders that make a kill safe and the look-ups that make a file
done exactly once.  tests/test_daemon.py runs the whole daemon as a subprocess.
"""

from __future__ import annotations

import json
import os
from pathlib import Path

import pytest

import vigproc.frontends.daemon.recorder as recorder_module
from vigproc.frontends.daemon import Daemon, WatchConfig
from vigproc.frontends.daemon.config import _Task
from vigproc.stores.journal import Journal, JournalError, fingerprint


class Killed(BaseException):
    """The daemon dies here (kill -9): nothing after this line runs."""


@pytest.fixture
def make(tmp_path):
    """A Daemon on tmp_path/in -> tmp_path/out with an archive folder, its journal open
    (as run() opens it); each call is a new start on the same folders and journal."""
    (tmp_path / "in").mkdir(exist_ok=True)
    opened = []

    def start() -> Daemon:
        cfg = WatchConfig(in_dir=tmp_path / "in", out_dir=tmp_path / "out", archive_dir=tmp_path / "archive",
                          settings={"mode": "correct", "profile": "estimate"})
        cfg.validate()
        d = Daemon(cfg)
        d.journal = Journal(cfg.journal, job=cfg.job)
        opened.append(d.journal)
        return d

    yield start
    for j in opened:
        j.close()


def _claimed(d: Daemon, name: str, data: bytes = b"\x89PNG pretend") -> _Task:
    path = d.cfg.in_dir / name
    path.write_bytes(data)
    task = d.scheduler.prepare(str(path))  # fingerprinted and claimed, as before a dispatch
    assert task is not None and d.journal.lookup(str(path)).state == "running"
    return task


def test_the_journal_says_done_before_the_input_is_archived(make, monkeypatch):
    """A kill between the two leaves a done entry and the input in place; the next start's
    rescan archives it, and nothing is processed again."""
    d = make()
    task = _claimed(d, "a.png")

    def killed(*_a, **_k):
        raise Killed

    monkeypatch.setattr(recorder_module, "_move", killed)
    with pytest.raises(Killed):
        d.recorder.done(task, {"output": None, "sidecar": "x.vigproc.json"}, "worker-0")
    assert d.journal.lookup(task.path).state == "done"  # recorded first ...
    assert Path(task.path).is_file()  # ... the move had not happened
    monkeypatch.undo()

    d2 = make()
    d2.watcher.rescan()
    assert not Path(task.path).exists() and (d2.cfg.archive_dir / "a.png").is_file()
    assert len(d2.watcher.tracker) == 0 and not d2.watcher.ready  # not offered for processing again
    assert d2.journal.lookup(task.path).state == "done"


def test_a_failed_journal_write_holds_the_move_back_until_it_succeeds(make, monkeypatch):
    d = make()
    task = _claimed(d, "b.png")
    real_done = d.journal.done
    calls = []

    def full_disk(*a, **k):
        calls.append(a)
        if len(calls) == 1:
            raise JournalError("database or disk is full")
        return real_done(*a, **k)

    monkeypatch.setattr(d.journal, "done", full_disk)
    d.recorder.done(task, {"sidecar": "b.vigproc.json"}, "worker-0")
    # not done, not moved, not counted: the entry stays running, so nothing else takes the file
    assert d.journal.lookup(task.path).state == "running" and Path(task.path).is_file()
    assert d.recorder.stats["done"] == 0
    d._write_status()
    assert json.loads(d.cfg.status_file.read_text())["journal_writes_waiting"] == 1
    d.recorder.flush_backlog()
    assert d.journal.lookup(task.path).state == "done" and (d.cfg.archive_dir / "b.png").is_file()
    assert d.recorder.stats["done"] == 1 and len(calls) == 2


def test_a_file_whose_content_is_done_is_not_claimed_again(make):
    """Duplicate events, rescans and a restart all come to prepare(): done content is
    skipped, whatever the path's mtime; new content is claimed."""
    d = make()
    task = _claimed(d, "c.png")
    d.journal.done(task.path, task.fp, {"sidecar": "c.vigproc.json"})
    os.utime(task.path, ns=(task.fp.mtime_ns + 10**9,) * 2)  # touched, same content
    d2 = make()
    d2.cfg.archive_dir = None  # keep it in place for the look-ups below (the parts share the config)
    assert d2.scheduler.prepare(task.path) is None
    entry = d2.journal.lookup(task.path)
    assert entry.state == "done" and entry.fingerprint.mtime_ns == task.fp.mtime_ns + 10**9  # the touch recorded
    d2.watcher.seen(task.path)  # an event for the unchanged finished file: nothing to watch
    assert len(d2.watcher.tracker) == 0
    Path(task.path).write_bytes(b"\x89PNG other content")
    d2.watcher.seen(task.path)  # changed: watched again, then claimed as new work
    assert task.path in d2.watcher.tracker
    again = d2.scheduler.prepare(task.path)
    assert again is not None and again.fp.sha256 == fingerprint(task.path).sha256 != task.fp.sha256


def test_the_daemon_is_its_three_parts():
    cfg = WatchConfig(in_dir="/", out_dir="/tmp/x", settings={"mode": "correct"})
    d = Daemon(cfg)
    assert d.watcher.recorder is d.recorder and d.scheduler.recorder is d.recorder
    assert d.scheduler.watcher is d.watcher and d.stats is d.recorder.stats
    d.scheduler.inflight["/p.png"] = None  # type: ignore[assignment]
    assert d.watcher.busy("/p.png") and not d.watcher.busy("/q.png")  # the watcher asks the scheduler


def test_the_done_line_says_when_a_frame_was_not_corrected(make, caplog):
    """A next step watching OUT must be able to tell the original from a correction (issue 38)."""
    from vigproc.frontends.daemon.worker import _summary

    d = make()
    side = {"output": "/out/c.corrected.png", "applied": False, "source": "estimate",
            "not_applied": "a phone's JPEG (Apple iPhone 5s): its image processor already corrected the lens shading"}
    summary = _summary(side, Path("/out/c.png.vigproc.json"))
    assert summary["not_applied"] == side["not_applied"]
    task = _claimed(d, "c.png")
    with caplog.at_level("INFO", logger="vigproc.watch"):
        d.recorder.done(task, summary, "worker-0")
    done = [r for r in caplog.records if r.getMessage().startswith("done ")]
    assert done and done[-1].getMessage().endswith("not corrected: " + side["not_applied"] + ")")
    assert done[-1].fields["not_applied"] == side["not_applied"]
    task = _claimed(d, "d.png")
    with caplog.at_level("INFO", logger="vigproc.watch"):
        d.recorder.done(task, _summary({"output": "/out/d.corrected.png", "applied": True}, Path("/x.json")), "w")
    assert "not corrected" not in [r for r in caplog.records if r.getMessage().startswith("done ")][-1].getMessage()


class _DeadWorker:
    """A worker process that is gone (what _worker_gone asks of one)."""

    pid = None
    exitcode = 3

    def join(self, timeout=None):
        pass

    def kill(self):
        pass

    def close(self):
        pass


def test_files_open_together_when_their_worker_died_run_alone_after_a_restart(make):
    """A worker reading ahead dies with two files open: neither is charged, both are to
    run alone (nothing read ahead beside them), where a crash names its file.  That holds
    after a restart of the daemon too (the journal says it), else a poison file read ahead
    again beside a good one gets another uncharged death at each start; and a file that
    has crashed a worker before runs alone from the start."""
    from vigproc.frontends.daemon.scheduler import _Worker

    class _Conn:
        def close(self):
            pass

    d = make()
    a, b = _claimed(d, "a.png", b"\x89PNG a"), _claimed(d, "b.png", b"\x89PNG b")
    c = _claimed(d, "c.png", b"\x89PNG c")
    for t in (a, b, c):
        d.journal.start(t.path, t.fp)
    d.journal.crashed(c.path, c.fp, "died (worker exit code 3)", max_crashes=3, now=0.0)  # due at once
    a.started, b.ahead = 1.0, True
    d.scheduler.workers = [_Worker("worker-0", _DeadWorker(), _Conn(), ready=True, tasks=[a, b])]
    d.flags.stop = "SIGTERM"  # no new worker started here
    d.scheduler._worker_gone(0, "died")
    assert d.scheduler.alone == {a.path, b.path}
    for t in (a, b):
        e = d.journal.lookup(t.path)
        assert e.state == "pending" and e.crashes == 0 and e.attempts == 0, e
    d2 = make()  # the daemon restarted before they were tried again
    for t in (a, b, c):
        assert d2.scheduler.prepare(t.path) is not None
    assert d2.scheduler.alone == {a.path, b.path, c.path}
