"""Whose fault a failure is (vigproc.pipeline.faults), and what each front end does about it.

Issue 22: with the output on a full tmpfs, healthy photos were quarantined.  Issue 37:
the classifier read words ("no space left on device", "refusing") in messages that
carry file names, so a file's name could make a corrupt file a full disk or a write
failure the photo's.  Faults are now classified by type and errno; the errors here
are the real ones (real writers, real SQLite, a real /dev/full, a real read-only or
full tmpfs where mounting is permitted), never copies of their messages.
"""

from __future__ import annotations

import errno
import importlib
import os
import pkgutil
import shutil
import sqlite3
import subprocess
from collections import namedtuple
from pathlib import Path

import numpy as np
import pytest

import vigproc
from conftest import textured
from vigproc.errors import (INPUT, OUTPUT_SIDE, SETTINGS, DiskFullError, ImageReadError, ImageWriteError,
                            OutputFormatError, OutputRefusedError, OutputSettingsError, VigprocError, write_error)
from vigproc.pipeline.faults import (CRASH, DISK_FULL, OUTPUT, PERMANENT, TRANSIENT, DiskSpace, attempt_limit,
                                     classify_error, disk_space, output_trouble)

REPO = Path(__file__).resolve().parents[1]
PROFILE = REPO / "profiles" / "examples" / "sony-rx100-10.4mm-f1.8.json"  # 3:2 frames
#: Words an earlier classifier read in messages; here they are only ever in file names.
HOSTILE = ("IMG no space left on device", "refusing to pose", "disk quota exceeded", "database is locked",
           "Input output error", "cannot read the source")

Usage = namedtuple("Usage", "total used free")


def _stub_disk(monkeypatch, free: int, total: int = 20_000_000) -> None:
    """The output file system as ``shutil.disk_usage`` reports it."""
    monkeypatch.setattr(shutil, "disk_usage", lambda p: Usage(total, total - free, free))


def _can_mount() -> str | None:
    from benchmarks.faults import why_not

    return why_not()


needs_tmpfs = pytest.mark.skipif(_can_mount() is not None, reason=f"needs a tmpfs of its own: {_can_mount()}")


@pytest.fixture
def tmpfs(tmp_path):
    """A factory of small tmpfs mounts under ``tmp_path``, unmounted afterwards."""
    mounted: list[Path] = []

    def make(name: str, kb: int, ro: bool = False) -> Path:
        mnt = tmp_path / name
        mnt.mkdir()
        subprocess.run(["mount", "-t", "tmpfs", "-o", f"size={kb}k", "tmpfs", str(mnt)], check=True)
        mounted.append(mnt)
        return mnt

    yield make
    for mnt in reversed(mounted):
        subprocess.run(["umount", "-l", str(mnt)], check=False, capture_output=True)


def _img(h: int = 64, w: int = 96, seed: int = 0) -> np.ndarray:
    return np.clip(np.stack([textured(h, w, seed=seed + c) for c in range(3)], -1), 0, 1).astype(np.float32)


# ------------------------------------------------------------------ by type, never by words
def _error_classes() -> list[type]:
    for m in pkgutil.walk_packages(vigproc.__path__, "vigproc."):
        if ".bench" in m.name or m.name.endswith("__main__"):
            continue
        with pytest.MonkeyPatch.context():
            try:
                importlib.import_module(m.name)
            except Exception:  # noqa: BLE001 - optional back ends (dask...) may be missing
                continue
    seen, todo = [], [VigprocError]
    while todo:
        c = todo.pop()
        seen.append(c)
        todo += c.__subclasses__()
    return seen


def test_every_error_class_says_whose_fault_it_is():
    classes = _error_classes()
    assert len(classes) > 20
    for c in classes:
        assert c.blame in (INPUT, OUTPUT_SIDE, SETTINGS), c
    assert (ImageWriteError.blame, DiskFullError.blame, OutputSettingsError.blame, OutputFormatError.blame,
            OutputRefusedError.blame, ImageReadError.blame) == (OUTPUT_SIDE, OUTPUT_SIDE, SETTINGS, SETTINGS, INPUT,
                                                                 INPUT)
    from vigproc.stores.profiles import ProfileStoreError

    assert ProfileStoreError.blame == SETTINGS and all(c.exit_code == 5 for c in classes
                                                        if issubclass(c, ImageWriteError))


def test_a_real_enospc_is_a_full_disk_whatever_the_free_space(tmp_path, monkeypatch):
    """/dev/full answers every write with ENOSPC: a real OSError, typed at the write."""
    with pytest.raises(OSError) as e:
        with open("/dev/full", "wb") as fh:
            fh.write(b"x" * 8192)
            fh.flush()
    assert e.value.errno == errno.ENOSPC
    err = write_error("cannot write 'x.jpg'", e.value)
    assert isinstance(err, DiskFullError) and err.errno == errno.ENOSPC and err.exit_code == 5
    _stub_disk(monkeypatch, free=10**12, total=2 * 10**12)  # a quota, or space freed since
    for exc in (err, e.value, OSError(errno.EDQUOT, os.strerror(errno.EDQUOT))):
        f = classify_error(exc, str(tmp_path))
        assert f.kind == DISK_FULL and f.output_side and not f.photo_fault and f.max_attempts(5) is None, f
        assert f.reason.startswith("output disk full (1000.0 GB free of 2000.0 GB on "), f


def test_a_name_saying_disk_full_does_not_make_a_corrupt_file_one(tmp_path, monkeypatch):
    """Issue 37.2: the error text carries the path, and the path said "no space left on
    device": a corrupt file became a full disk that never ends."""
    from vigproc.io.images import read_image

    _stub_disk(monkeypatch, free=1000)  # even with the output disk full
    for name in HOSTILE:
        bad = tmp_path / f"{name}.jpg"
        bad.write_bytes(os.urandom(5000))
        with pytest.raises(ImageReadError) as e:
            read_image(bad)
        assert name in str(e.value)
        f = classify_error(e.value, str(tmp_path / "out"))
        assert f.kind == PERMANENT and f.photo_fault, (name, f)


def test_a_write_failure_with_a_hostile_name_is_the_output_sides(tmp_path, monkeypatch):
    """Issue 37.3: "refusing" in a name made an output failure the photo's.  A real
    failure to write (the output folder a file: ENOTDIR) for each hostile name:
    the output side's, judged by the free space, never the photo's."""
    from vigproc.io.images import write_image

    (tmp_path / "out").write_bytes(b"not a folder")
    for name in HOSTILE:
        with pytest.raises(ImageWriteError) as e:
            write_image(tmp_path / "out" / f"{name}.tif", _img())
        assert type(e.value) is ImageWriteError and e.value.errno == errno.ENOTDIR
        _stub_disk(monkeypatch, free=10**12, total=2 * 10**12)
        f = classify_error(e.value, str(tmp_path / "out"))
        assert f.kind == OUTPUT and f.max_attempts(3) is None and "not the photo's fault" in f.reason, f
        _stub_disk(monkeypatch, free=10_000)
        assert classify_error(e.value, str(tmp_path / "out")).kind == DISK_FULL
        monkeypatch.undo()


def test_what_is_the_inputs_or_the_settings_stays_permanent(tmp_path, monkeypatch):
    """Real errors of the writers that name the frame or the settings, not the disk."""
    from vigproc.io.images import write_image
    from vigproc.io.metadata import copy_metadata
    from vigproc.pipeline.processor import output_location

    out = tmp_path / "out"
    out.mkdir()
    errors = []
    for call in (lambda: write_image(out / "a.exr", _img() * 1e6, bit_depth="half"),  # beyond half's range
                 lambda: write_image(out / "a.bmp", _img()),  # no such output format
                 lambda: write_image(out / "a.tif", _img(), bit_depth="uint8", quality=50),
                 lambda: output_location(out, "sub/x.jpg") if (out / "sub").symlink_to("/") is None else None,
                 lambda: output_location(out, "../escape.jpg")):
        with pytest.raises(ImageWriteError) as e:
            call()
        errors.append(e.value)
    junk = tmp_path / "refusing to pose.jpg"
    junk.write_bytes(os.urandom(3000))
    write_image(out / "b.tif", _img())
    with pytest.raises(ImageWriteError) as e:  # exiftool cannot read the source
        copy_metadata(junk, out / "b.tif", None)
    errors.append(e.value)
    _stub_disk(monkeypatch, free=1000)  # even on a full disk
    kinds = [(type(x).__name__, classify_error(x, str(out)).kind) for x in errors]
    assert all(k == PERMANENT for _n, k in kinds), kinds
    assert [type(x) for x in errors] == [OutputRefusedError, OutputSettingsError, OutputSettingsError,
                                         OutputRefusedError, OutputRefusedError, OutputRefusedError]
    assert not [p for p in out.iterdir() if ".tmp" in p.name]  # nothing left behind
    assert classify_error(ZeroDivisionError("x")).reason.startswith("internal error (ZeroDivisionError")


def test_a_truncated_raw_is_the_files_fault(tmp_path):
    """LibRaw's 'Input/output error' on a truncated RAW carries no errno: the file's."""
    from conftest import SHARED
    from vigproc.io.images import read_image

    raws = sorted((SHARED / "raw" / "rawpy").glob("*.*")) if (SHARED / "raw" / "rawpy").is_dir() else []
    raws = [p for p in raws if p.suffix.lower() in (".kdc", ".dng", ".nef", ".cr2", ".arw")]
    if not raws:
        pytest.skip("no decodable RAW in the shared data")
    cut = tmp_path / f"{HOSTILE[0]}{raws[0].suffix}"
    cut.write_bytes(raws[0].read_bytes()[: raws[0].stat().st_size // 3])
    with pytest.raises(ImageReadError) as e:
        read_image(cut)
    assert classify_error(e.value, str(tmp_path)).kind == PERMANENT


def test_only_output_side_failures_are_retried_without_limit():
    """One rule for the daemon, batch and Fault: a photo is given up after ``limit``
    failed attempts, but never for a failure to write an output."""
    assert [attempt_limit(k, 5) for k in (PERMANENT, TRANSIENT, CRASH, DISK_FULL, OUTPUT)] == [5, 5, 5, None, None]


def test_disk_space_reads_the_file_system_of_the_nearest_existing_folder(tmp_path):
    sp = disk_space(tmp_path / "not" / "yet")
    assert isinstance(sp, DiskSpace) and 0 <= sp.free_bytes <= sp.total_bytes
    assert DiskSpace(10, 100, 5).low(11) and not DiskSpace(10, 100, 5).low(10) and DiskSpace(10**9, 10**9, 0).low()


# ------------------------------------------------------------------ the write path
def test_without_an_in_memory_file_the_room_is_estimated_from_the_pixels(tmp_path, monkeypatch):
    """No memfd (not Linux): the native writer writes the file itself, after a look at
    the free space against a generous bound (uncompressed samples, twice, plus 1 MiB)."""
    from vigproc.io import images

    monkeypatch.delattr(os, "memfd_create")
    img = _img(120, 180)
    images.write_image(tmp_path / "a.tif", img)
    back, _ = images.read_image(tmp_path / "a.tif")
    assert np.abs(back - img).max() < 1e-4
    assert images.size_bound(180, 120, 3, "uint16") == 180 * 120 * 3 * 2 + 65536
    _stub_disk(monkeypatch, free=2 * (180 * 120 * 6 + 65536) + (1 << 20) - 1)  # one byte short
    with pytest.raises(DiskFullError) as e:
        images.write_image(tmp_path / "IMG refusing to pose.tif", img)
    assert "MB needed" in str(e.value) and e.value.errno == errno.ENOSPC
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.tif"]
    f = classify_error(e.value, str(tmp_path))
    assert f.kind == DISK_FULL and f.reason.startswith("output disk full (1.4 MB free of 20.0 MB on ")


@needs_tmpfs
def test_a_full_tmpfs_gives_typed_errors_and_leaves_no_temporary(tmp_path, tmpfs, monkeypatch):
    """Real ENOSPC on a real tmpfs: from the image's bytes (encoded in memory: libjpeg never
    meets the full disk), from an atomic text write, and from exiftool's metadata copy
    (no errno: judged by the room left).  Never a process exit, never a temporary left."""
    from vigproc.atomic import atomic_write_text
    from vigproc.io import images, metadata

    out = tmpfs("out", 64)
    with pytest.raises(DiskFullError) as e:
        images.write_image(out / "IMG no space left on device.jpg", _img(480, 720), bit_depth="uint8",
                           transfer="srgb", quality=100)
    assert e.value.errno == errno.ENOSPC and classify_error(e.value, str(out)).kind == DISK_FULL
    assert list(out.iterdir()) == []
    filler = out / "filler"
    filler.write_bytes(b"\0" * (shutil.disk_usage(out).free - 8192))
    with pytest.raises(DiskFullError):
        atomic_write_text(out / "x.vigproc.json", "{}" * 20_000)
    filler.unlink()
    src = tmp_path / "src.jpg"
    images.write_image(src, _img(240, 360), bit_depth="uint8", transfer="srgb")
    subprocess.run(["exiftool", "-q", "-overwrite_original", "-Comment=" + "x" * 60_000, str(src)], check=True)
    with pytest.raises(ImageWriteError) as e:
        metadata.write_corrected(out / "refusing to pose.jpg", _img(240, 360), src, None, bit_depth="uint8",
                                 transfer="srgb")
    f = classify_error(e.value, str(out), min_free=1 << 20)
    assert f.kind == DISK_FULL and f.output_side, (e.value, f)
    assert [p.name for p in out.iterdir()] == []


@needs_tmpfs
def test_a_read_only_output_is_the_output_sides(tmp_path, tmpfs):
    from vigproc.io.images import write_image

    out = tmpfs("out", 4096)
    subprocess.run(["mount", "-o", "remount,ro", str(out)], check=True)
    with pytest.raises(ImageWriteError) as e:
        write_image(out / "refusing to pose.tif", _img())
    assert e.value.errno == errno.EROFS
    f = classify_error(e.value, str(out), min_free=1)
    assert f.kind == OUTPUT and not f.photo_fault, f
    t = output_trouble(out, 1)
    assert t is not None and t.kind == OUTPUT and "read-only" in t.reason


@needs_tmpfs
def test_a_small_read_only_output_is_not_called_full(tmp_path, tmpfs):
    """EROFS on a file system with less free room than ``min_free`` (it was: `vigproc
    correct -o RO` on an empty 200 MB read-only mount said "output disk full (209.7 MB
    free of 209.7 MB ...)": free space on RO and run again)."""
    from vigproc.io.images import write_image

    out = tmpfs("out", 4096)
    subprocess.run(["mount", "-o", "remount,ro", str(out)], check=True)
    with pytest.raises(ImageWriteError) as e:
        write_image(out / "refusing to pose.tif", _img())
    f = classify_error(e.value, str(out))  # the default room: 256 MiB, more than the mount
    assert f.kind == OUTPUT and "Read-only file system" in f.reason and "full" not in f.reason, f
    # and a worker that died writing there (no exception to classify): the same answer
    t = output_trouble(out)
    assert t is not None and t.kind == OUTPUT and "read-only" in t.reason, t


def test_output_trouble_sees_a_full_a_vanished_and_a_healthy_output(tmp_path, monkeypatch):
    assert output_trouble(tmp_path, 1) is None
    t = output_trouble(tmp_path / "gone", 1)
    assert t is not None and t.kind == OUTPUT and "gone" in t.reason
    _stub_disk(monkeypatch, free=1000)
    t = output_trouble(tmp_path, 1 << 20)
    assert t is not None and t.kind == DISK_FULL and t.space.free_bytes == 1000


# ------------------------------------------------------------------ stores
def test_a_locked_and_a_full_profile_store_say_so_by_their_sqlite_codes(tmp_path, monkeypatch):
    from vigproc.stores.profiles import ProfileStore, ProfileStoreError

    db = tmp_path / "store" / "p.sqlite"
    with ProfileStore(db) as st:
        st.con.execute("PRAGMA max_page_count = " + str(st.con.execute("PRAGMA page_count").fetchone()[0] + 1))
        with pytest.raises(ProfileStoreError) as e:  # SQLITE_FULL, as on a full disk
            st._transact("fill", lambda con: con.execute("CREATE TABLE big AS SELECT randomblob(100000) AS b"))
    _stub_disk(monkeypatch, free=10**12, total=2 * 10**12)  # the output disk has room
    f = classify_error(e.value, str(tmp_path / "out"))
    assert f.kind == DISK_FULL and f.disk == "profile store disk", f
    assert f.reason.startswith(f"profile store disk full (1000.0 GB free of 2000.0 GB on {db.parent})"), f
    holder = sqlite3.connect(str(db), isolation_level=None)
    holder.execute("BEGIN IMMEDIATE")  # another process writing
    try:
        with ProfileStore(db, timeout=0.2) as st, pytest.raises(ProfileStoreError) as e:
            st._transact("write", lambda con: con.execute("CREATE TABLE t (x)"))
    finally:
        holder.close()
    assert classify_error(e.value, str(tmp_path)).kind == TRANSIENT, e.value


def test_a_corrupt_profile_store_is_refused_on_open(tmp_path, capsys, monkeypatch):
    """Issue 37.10: a flipped byte failed ``integrity_check`` but the store was used (rc 0)."""
    from vigproc.frontends.cli import main
    from vigproc.stores.profiles import ProfileStore, ProfileStoreError

    db = tmp_path / "p.sqlite"
    with ProfileStore(db) as st:
        st._transact("fill", lambda con: con.execute("CREATE TABLE pad AS SELECT randomblob(3000) AS b "
                                                     "FROM (WITH RECURSIVE n(i) AS (SELECT 1 UNION ALL SELECT i+1 "
                                                     "FROM n WHERE i < 40) SELECT i FROM n)"))
        page = st.con.execute("PRAGMA page_size").fetchone()[0]
        root = st.con.execute("SELECT rootpage FROM sqlite_master WHERE name = 'pad'").fetchone()[0]
    con = sqlite3.connect(str(db))
    con.execute("PRAGMA wal_checkpoint(TRUNCATE)")
    con.close()
    data = bytearray(db.read_bytes())
    off = (root - 1) * page  # the table's interior page: its cell count, flipped
    data[off + 3] ^= 0xFF
    db.write_bytes(bytes(data))
    with monkeypatch.context() as m:  # without the check it opens, and is used silently
        m.setattr(ProfileStore, "check_on_open", False)
        ProfileStore(db).close()
    with pytest.raises(ProfileStoreError) as e:
        ProfileStore(db)
    assert "corrupt" in str(e.value) and "move it aside" in str(e.value)
    assert main(["profile", "--profile-db", str(db), "list"]) == 8
    assert "Traceback" not in capsys.readouterr().err


# ------------------------------------------------------------------ the daemon's parts
def test_a_worker_death_while_the_output_fails_is_not_the_photos(tmp_path, monkeypatch):
    """A worker that died with the output disk full pauses the daemon (nothing charged);
    with the output folder gone it is an output failure (retried, never quarantined);
    with a healthy output it is a crash charged to the file."""
    from vigproc.frontends.daemon import Daemon, WatchConfig
    from vigproc.stores.journal import Journal

    (tmp_path / "in").mkdir()
    cfg = WatchConfig(in_dir=tmp_path / "in", out_dir=tmp_path / "out", settings={"mode": "correct"},
                      min_free=1 << 20)
    cfg.validate()
    d = Daemon(cfg)
    d.journal = Journal(cfg.journal, job=cfg.job)
    try:
        def died(name: str) -> tuple:
            p = cfg.in_dir / name
            p.write_bytes(name.encode())
            task = d.scheduler.prepare(str(p))
            d.journal.start(task.path, task.fp)
            d.scheduler._died_on(task, "died")
            e = d.journal.lookup(task.path)
            return e.state, e.attempts, e.crashes

        with monkeypatch.context() as m:
            _stub_disk(m, free=1000)
            assert died("a.jpg") == ("pending", 0, 0) and d.scheduler.disk is not None
            assert d.scheduler.pause_status()["why"] == "output disk full"
        d.scheduler.disk = None
        with monkeypatch.context() as m:
            m.setattr(d.scheduler.cfg, "out_dir", tmp_path / "gone")
            assert died("b.jpg")[1:] == (1, 0) and d.scheduler.disk is None
        assert died("c.jpg") == ("pending", 0, 1)  # a healthy output: the file's crash
    finally:
        d.journal.close()


# ------------------------------------------------------------------ vigproc correct
def _photo(path: Path, seed: int) -> Path:
    from vigproc.io.images import write_image

    img = np.stack([textured(64, 96, seed=seed + c) for c in range(3)], -1)
    write_image(path, np.clip(img, 0, 1).astype(np.float32), bit_depth="uint16")
    return path


def test_correct_on_a_full_disk_says_so_and_stops(tmp_path, monkeypatch, capsys):
    """Issue 22: `vigproc correct` must say the output disk is full (exit 5, a typed
    error, no traceback) and stop, rather than fail every further file the same way.
    The disk reports 0.2 MB free: the real write path refuses the 16-bit TIFF."""
    import vigproc.io.metadata
    from vigproc.frontends.cli import main

    out = tmp_path / "out"
    files = [_photo(tmp_path / f"{n}.png", i) for i, n in enumerate("abc")]
    calls = []
    real = vigproc.io.metadata.write_corrected
    monkeypatch.setattr(vigproc.io.metadata, "write_corrected", lambda dst, *a, **kw: (calls.append(dst),
                                                                                        real(dst, *a, **kw)))
    monkeypatch.delattr(os, "memfd_create")  # the write path that looks at the free space first
    _stub_disk(monkeypatch, free=200_000)
    rc = main(["correct", "-o", str(out), "--profile", str(PROFILE), "--output-format", "tiff16",
               *map(str, files)])
    cap = capsys.readouterr()
    err = cap.err
    assert rc == DiskFullError.exit_code == 5, err
    last = err.strip().splitlines()[-1]
    assert last.startswith("vigproc: output disk full (0.2 MB free") and "2 file(s) not started" in last, err
    assert "Traceback" not in err and len(calls) == 1  # stopped at the first full write
    assert "0 corrected, 0 not corrected, 3 failed" in cap.out


# ------------------------------------------------------------------ batch
def test_batch_stops_handing_out_files_on_a_full_disk_and_charges_none(tmp_path, monkeypatch):
    from vigproc.frontends import backends as BK
    from vigproc.frontends import batch as B
    from vigproc.stores.journal import Journal
    from vigproc.pipeline.processor import Settings

    src, out = tmp_path / "src", tmp_path / "out"
    src.mkdir()
    for i in range(4):
        _photo(src / f"f{i}.png", i)
    monkeypatch.delattr(os, "memfd_create")  # the write path that looks at the free space first
    _stub_disk(monkeypatch, free=100_000)  # ... refuses the outputs
    items, _ = B.collect(src, out)
    out.mkdir()
    spec = B.JobSpec(settings=Settings(mode="correct", profile=str(PROFILE), output_format="tiff16"),
                     outdir=str(out.resolve()), numba_threads=1)
    s = B.run_batch(items, spec, BK.local_backend(1), journal_path=out / B.JOURNAL_NAME, job="t", progress=False,
                    window=1)
    assert s.disk_full is not None and s.disk_full.startswith("output disk full")
    assert (s.quarantined, s.retry_later, s.not_started, s.resubmitted) == (0, 1, 3, 0)
    with Journal(out / B.JOURNAL_NAME, job="t") as j:
        (e,) = j.entries()
        assert e.state == "pending" and "output disk full" in e.reason
        for _ in range(10):  # later runs on a disk still full never quarantine it
            assert j.claim(e.path, e.fingerprint, worker="w", now=1e12)
            assert j.failed(e.path, e.fingerprint, e.reason, transient=True, max_attempts=None) == "retry"


# ------------------------------------------------------------------ the fault benchmark
def test_bench_faults_says_why_it_cannot_run(monkeypatch, capsys):
    """`vigproc bench faults` needs root to mount its tmpfs: without, one line saying so."""
    from vigproc.frontends.cli import main

    monkeypatch.setattr(os, "geteuid", lambda: 1000)
    assert main(["bench", "faults"]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert err == ["vigproc: bench faults cannot run here: it needs root, to mount the small tmpfs that fills "
                   "(mount -t tmpfs)"]


def test_an_output_format_the_input_cannot_have_is_given_up(tmp_path, monkeypatch):
    """--output-format dng of a JPEG is the settings' fault, not the output disk's: a
    watch folder or a batch gives the file up (it was retried without limit, and called a
    full disk on a nearly full one)."""
    from vigproc.errors import OutputFormatError
    from vigproc.pipeline.processor import output_format_for

    out = str(tmp_path)
    _stub_disk(monkeypatch, free=3_000_000)
    with pytest.raises(OutputFormatError) as e:
        output_format_for("dng", tmp_path / "a.jpg")
    f = classify_error(e.value, out)
    assert f.kind == PERMANENT and not f.output_side and f.max_attempts(3) == 3, f
    assert e.value.exit_code == 5
