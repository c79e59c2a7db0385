"""Whose fault a failure is (vigproc.pipeline.faults), and what each front end does about it.

Issue 22: with the output on a full 20 MB tmpfs, healthy photos were quarantined
for good, because OpenImageIO's ``TIFFWriteScanline failed ... Write error`` and
exiftool's ``Error writing image data`` carry neither an errno nor "no space left".
A full disk is simulated here by a writer that raises those messages (or ENOSPC)
and a ``shutil.disk_usage`` stub; nothing is mounted.
"""

from __future__ import annotations

import errno
import os
import shutil
from collections import namedtuple
from pathlib import Path

import numpy as np
import pytest

from conftest import textured
from vigproc.errors import DiskFullError, ImageReadError, ImageWriteError, InvalidImageError
from vigproc.pipeline.faults import (CRASH, DISK_FULL, OUTPUT, PERMANENT, TRANSIENT, DiskSpace, attempt_limit, classify_error,
                            disk_space)

REPO = Path(__file__).resolve().parents[1]
PROFILE = REPO / "profiles" / "examples" / "sony-rx100-10.4mm-f1.8.json"  # 3:2 frames

OIIO_FULL = ("cannot write '{out}/a.png.corrected.tif': TIFFWriteScanline failed: "
             "{out}/.a.png.corrected.tif.tmp-x.tif: Write error at scanline 12")
EXIFTOOL_FULL = "cannot copy metadata into '{out}/a.png.corrected.tif': exiftool failed: Error writing image data"

Usage = namedtuple("Usage", "total used free")


def _stub_disk(monkeypatch, free: int, total: int = 20_000_000) -> None:
    """The output file system as ``shutil.disk_usage`` reports it."""
    monkeypatch.setattr(shutil, "disk_usage", lambda p: Usage(total, total - free, free))


# ------------------------------------------------------------------ the policy
def test_a_write_failure_on_a_nearly_full_output_disk_is_the_disks_fault(tmp_path, monkeypatch):
    out = str(tmp_path)
    _stub_disk(monkeypatch, free=3_000_000)  # 3 MB left of 20: what the audit's tmpfs showed
    for text in (OIIO_FULL, EXIFTOOL_FULL):
        f = classify_error(ImageWriteError(text.format(out=out)), out)
        assert f.kind == DISK_FULL and f.output_side and not f.photo_fault, f
        assert f.reason.startswith("output disk full (3.0 MB free of 20.0 MB") and text.split(": ")[-1] in f.reason
        assert f.max_attempts(5) is None and f.space.free_bytes == 3_000_000
    # the errno says so whatever the free space (a quota, or space freed since)
    _stub_disk(monkeypatch, free=10**12, total=2 * 10**12)
    for code in (errno.ENOSPC, errno.EDQUOT):
        assert classify_error(OSError(code, os.strerror(code)), out).kind == DISK_FULL
    assert classify_error(ImageWriteError("cannot write 'x.tif': No space left on device")).kind == DISK_FULL


def test_only_output_side_failures_are_retried_without_limit():
    """One rule for the daemon, batch and Fault: a photo is given up after ``limit``
    failed attempts, but never for a failure to write an output."""
    assert [attempt_limit(k, 5) for k in (PERMANENT, TRANSIENT, CRASH, DISK_FULL, OUTPUT)] == [5, 5, 5, None, None]


def test_a_write_failure_with_room_left_is_still_not_the_photos(tmp_path, monkeypatch):
    out = str(tmp_path)
    _stub_disk(monkeypatch, free=10**12, total=2 * 10**12)
    f = classify_error(ImageWriteError(OIIO_FULL.format(out=out)), out)
    assert f.kind == OUTPUT and f.output_side and f.max_attempts(5) is None
    assert "not the photo's fault" in f.reason and "1000.0 GB free" in f.reason
    # an OS error on a file of the output folder (an I/O error of that disk) likewise
    eio = OSError(errno.EIO, "Input/output error", str(tmp_path / "a.corrected.tif"))
    assert classify_error(eio, out).kind == OUTPUT
    # ... but on the input side an I/O error is a device that may come back: transient
    assert classify_error(OSError(errno.EIO, "Input/output error", "/in/a.jpg"), out).kind == TRANSIENT


def test_what_is_proven_to_be_the_photos_stays_permanent(tmp_path, monkeypatch):
    out = str(tmp_path)
    _stub_disk(monkeypatch, free=1000)  # even on a full disk
    for exc in (
        ImageWriteError("cannot write 'a.exr': values reach 1e+06, beyond the 6.55e+04 that openexr half holds"),
        ImageWriteError("cannot copy metadata into 'a.tif': exiftool cannot read the source 'a.jpg': bad IFD"),
        ImageWriteError("refusing to overwrite 'a.jpg': it is an input of this run"),
        ImageReadError("cannot read image 'a.jpg': corrupt or truncated JPEG file"),
        ImageReadError("cannot read image 'a.dng': RAW decoding failed (LibRawIOError: Input/output error)"),
        InvalidImageError("cannot estimate: the image is constant"),
    ):
        f = classify_error(exc, out)
        assert f.kind == PERMANENT and f.photo_fault and f.max_attempts(5) == 5, (exc, f)
    assert classify_error(ZeroDivisionError("x")).reason.startswith("internal error (ZeroDivisionError")
    killed = ImageWriteError("cannot copy metadata into 'a.tif': exiftool was killed by SIGTERM")
    killed.transient = True
    assert classify_error(killed, out).kind == TRANSIENT  # limited retries: exiftool may die of the file


def test_disk_space_reads_the_file_system_of_the_nearest_existing_folder(tmp_path):
    sp = disk_space(tmp_path / "not" / "yet")
    assert isinstance(sp, DiskSpace) and 0 <= sp.free_bytes <= sp.total_bytes
    assert DiskSpace(10, 100, 5).low(11) and not DiskSpace(10, 100, 5).low(10) and DiskSpace(10**9, 10**9, 0).low()


# ------------------------------------------------------------------ vigproc correct
def _photo(path: Path, seed: int) -> Path:
    from vigproc.io.images import write_image

    img = np.stack([textured(64, 96, seed=seed + c) for c in range(3)], -1)
    write_image(path, np.clip(img, 0, 1).astype(np.float32), bit_depth="uint16")
    return path


def test_correct_on_a_full_disk_says_so_and_stops(tmp_path, monkeypatch, capsys):
    """Issue 22: `vigproc correct` must say the output disk is full (exit 5, a typed
    error, no traceback) and stop, rather than fail every further file the same way."""
    import vigproc.io.metadata
    from vigproc.frontends.cli import main

    out = tmp_path / "out"
    files = [_photo(tmp_path / f"{n}.png", i) for i, n in enumerate("abc")]
    calls = []

    def full_disk(dst, *a, **kw):  # what OpenImageIO says when the tmpfs fills mid-write
        calls.append(dst)
        raise ImageWriteError(OIIO_FULL.format(out=out))

    monkeypatch.setattr(vigproc.io.metadata, "write_corrected", full_disk)
    _stub_disk(monkeypatch, free=2_000_000)
    rc = main(["correct", "-o", str(out), "--profile", str(PROFILE), "--output-format", "tiff16",
               *map(str, files)])
    err = capsys.readouterr().err
    assert rc == DiskFullError.exit_code == 5, err
    last = err.strip().splitlines()[-1]
    assert last.startswith("vigproc: output disk full (2.0 MB free") and "2 file(s) not started" in last, err
    assert "Traceback" not in err and len(calls) == 1  # stopped at the first full write


# ------------------------------------------------------------------ batch
def test_batch_stops_handing_out_files_on_a_full_disk_and_charges_none(tmp_path, monkeypatch):
    import vigproc.io.metadata
    from vigproc.frontends import backends as BK
    from vigproc.frontends import batch as B
    from vigproc.stores.journal import Journal
    from vigproc.pipeline.processor import Settings

    src, out = tmp_path / "src", tmp_path / "out"
    src.mkdir()
    for i in range(4):
        _photo(src / f"f{i}.png", i)
    monkeypatch.setattr(vigproc.io.metadata, "write_corrected",
                        lambda dst, *a, **kw: (_ for _ in ()).throw(ImageWriteError(EXIFTOOL_FULL.format(out=out))))
    _stub_disk(monkeypatch, free=1_000_000)
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
