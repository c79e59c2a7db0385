"""``vigproc correct`` overlaps its stages: the next file is decoded ahead
(:meth:`Processor.read_ahead`) and the previous one written (:meth:`Processor.begin_file`'s
second step) in threads. What a file gets, the order of lines and records, typed
errors per file and Ctrl-C must be as when the files are taken one at a time."""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np
import pytest

from tests.conftest import textured

REPO = Path(__file__).resolve().parents[1]
PROFILE = REPO / "profiles" / "examples" / "sony-rx100-10.4mm-f1.8.json"  # 3:2 frames


def _photo(path: Path, seed: int, *, gain: float = 1.0) -> Path:
    from vigproc.io.images import write_image

    img = np.stack([textured(64, 96, seed=seed + c) for c in range(3)], -1) * gain
    write_image(path, np.clip(img, 0, 1).astype(np.float32), bit_depth="uint8", transfer="srgb")
    return path


def _settings(**kw):
    from vigproc.pipeline.processor import Settings

    return Settings(mode="correct", profile=str(PROFILE), **kw)


def test_a_frame_read_ahead_is_the_frame_read(tmp_path):
    from vigproc.pipeline.processor import Processor

    a = _photo(tmp_path / "a.png", 1)
    with Processor(_settings()) as proc:
        plain = proc.read_frame(a)
        proc.read_ahead(a)
        ahead = proc.read_frame(a)
        assert not proc._ahead  # taken
    assert np.array_equal(np.asarray(plain.img.codes), np.asarray(ahead.img.codes))


def test_a_file_changed_after_its_read_ahead_is_read_again(tmp_path):
    from vigproc.pipeline.processor import Processor

    a = _photo(tmp_path / "a.png", 1)
    with Processor(_settings()) as proc:
        proc.read_ahead(a)
        proc._ahead[0][2].result()  # decoded before the file changes
        _photo(tmp_path / "b.png", 7, gain=0.5)
        os.replace(tmp_path / "b.png", a)  # another file under the same name
        got = proc.read_frame(a)
    with Processor(_settings()) as proc:
        fresh = proc.read_frame(a)
    assert np.array_equal(np.asarray(got.img.codes), np.asarray(fresh.img.codes))


def test_a_read_ahead_that_fails_raises_where_the_file_is_read(tmp_path):
    from vigproc.errors import ImageReadError
    from vigproc.pipeline.processor import Processor

    bad = tmp_path / "bad.png"
    bad.write_bytes(b"\x89PNG\r\n\x1a\n not a png")
    with Processor(_settings()) as proc:
        proc.read_ahead(bad)
        with pytest.raises(ImageReadError):
            proc.read_frame(bad)


def test_read_ahead_holds_at_most_two_files(tmp_path):
    from vigproc.pipeline.processor import Processor

    files = [_photo(tmp_path / f"{i}.png", i) for i in range(4)]
    with Processor(_settings()) as proc:
        for f in files:
            proc.read_ahead(f)
        assert [p for p, _, _ in proc._ahead] == [os.fspath(f) for f in files[-Processor.AHEAD:]]


def test_correct_overlapped_gives_each_file_what_one_at_a_time_gives(tmp_path, capsys):
    """Outputs, records and lines in order, a bad file's typed error in its place."""
    from vigproc.frontends.cli import main
    from vigproc.pipeline.processor import Processor, output_stems

    files = [_photo(tmp_path / f"{n}.png", i) for i, n in enumerate("abcd")]
    bad = tmp_path / "c.png"
    bad.write_bytes(b"not an image")
    rc = main(["correct", "-o", str(tmp_path / "lap"), "--profile", str(PROFILE), "--json", *map(str, files)])
    cap = capsys.readouterr()
    assert rc != 0 and "Traceback" not in cap.err and "c.png" in cap.err
    doc = json.loads(cap.out)
    recs = doc["results"] if isinstance(doc, dict) else doc
    assert [Path(r["file"]).name for r in recs] == ["a.png", "b.png", "c.png", "d.png"]
    assert "error" in recs[2] and all(r.get("applied") for r in recs[:2] + recs[3:])
    one = tmp_path / "one"
    one.mkdir()
    with Processor(_settings()) as proc:  # one file at a time, no threads
        for f, stem in zip(files, output_stems(files)):
            if f != bad:
                proc.process_file(f, one, stem)
    made = sorted(p.name for p in (tmp_path / "lap").iterdir())
    assert made == sorted(p.name for p in one.iterdir()) and any(n.endswith(".corrected.png") for n in made)
    for n in made:
        if not n.endswith(".json"):
            assert (tmp_path / "lap" / n).read_bytes() == (one / n).read_bytes(), n


def test_ctrl_c_while_a_file_is_written_finishes_and_counts_it(tmp_path, monkeypatch, capsys):
    from vigproc.frontends.cli import main
    from vigproc.pipeline.processor import Processor

    files = [_photo(tmp_path / f"{n}.png", i) for i, n in enumerate("abc")]
    real = Processor.begin_file
    calls = []

    def begin(self, path, *a, **kw):
        calls.append(path)
        if len(calls) == 2:  # the first file is being written now
            raise KeyboardInterrupt
        return real(self, path, *a, **kw)

    monkeypatch.setattr(Processor, "begin_file", begin)
    rc = main(["correct", "-o", str(tmp_path / "out"), "--profile", str(PROFILE), *map(str, files)])
    err = capsys.readouterr().err
    assert rc == 130 and "1 corrected, 0 not corrected, 0 failed, 2 not started" in err, err
    assert (tmp_path / "out" / "a.png.vigproc.json").exists() and (tmp_path / "out" / "a.corrected.png").exists()
    assert not list((tmp_path / "out").glob(".*tmp*"))  # nothing half-written


def test_a_slow_write_does_not_hold_back_the_next_files(tmp_path, capsys, monkeypatch):
    """Files are read and worked on while an earlier one is still being written (a queue
    of writes, :data:`WRITE_QUEUE`); lines and outputs still come in input order."""
    import threading

    from vigproc.frontends.cli import main
    from vigproc.frontends.commands import correct as C
    from vigproc.pipeline.processor import Processor

    files = [_photo(tmp_path / f"{n}.png", i) for i, n in enumerate("abcd")]
    third = threading.Event()
    waited = []
    real = Processor.begin_file

    def begin(self, path, *a, **kw):
        finish = real(self, path, *a, **kw)
        if Path(path).name == "c.png":
            third.set()
        if Path(path).name != "a.png":
            return finish

        def slow():  # a's write lasts until c has been worked on
            waited.append(third.wait(timeout=20))
            return finish()

        slow.encodes = finish.encodes
        return slow

    monkeypatch.setattr(Processor, "begin_file", begin)
    monkeypatch.setattr(C, "WRITE_FRAMES", 3)  # every file here is corrected: each holds a frame
    rc = main(["correct", "-o", str(tmp_path / "out"), "--profile", str(PROFILE), *map(str, files)])
    out = capsys.readouterr().out.splitlines()
    assert rc == 0 and waited == [True]
    assert [ln.split(" -> ")[0] for ln in out[:4]] == [str(f) for f in files]


def test_writes_wait_for_room_when_frames_are_held(tmp_path, monkeypatch):
    """At most WRITE_FRAMES queued writes hold a frame: with one, the file after the
    next is not worked on while the first is still being written."""
    import threading

    from vigproc.frontends.cli import main
    from vigproc.frontends.commands import correct as C
    from vigproc.pipeline.processor import Processor

    files = [_photo(tmp_path / f"{n}.png", i) for i, n in enumerate("abcd")]
    third = threading.Event()
    waited = []
    real = Processor.begin_file

    def begin(self, path, *a, **kw):
        if Path(path).name == "c.png":
            third.set()
        finish = real(self, path, *a, **kw)
        if Path(path).name != "a.png":
            return finish

        def slow():  # a's write: c must not be begun meanwhile
            waited.append(third.wait(timeout=1.5))
            return finish()

        slow.encodes = finish.encodes
        return slow

    monkeypatch.setattr(Processor, "begin_file", begin)
    monkeypatch.setattr(C, "WRITE_FRAMES", 1)
    assert main(["correct", "-o", str(tmp_path / "out"), "--profile", str(PROFILE), *map(str, files)]) == 0
    assert waited == [False]


def test_ctrl_c_cancels_the_writes_not_started(tmp_path, monkeypatch, capsys):
    """Ctrl-C: the file being written is finished and counted, those waiting for the
    writer are not started (nothing of them written)."""
    import threading

    from vigproc.frontends.cli import main
    from vigproc.frontends.commands import correct as C
    from vigproc.pipeline.processor import Processor

    files = [_photo(tmp_path / f"{n}.png", i) for i, n in enumerate("abcd")]
    release = threading.Event()
    real = Processor.begin_file

    def begin(self, path, *a, **kw):
        name = Path(path).name
        if name == "d.png":  # a is being written, b and c wait for the writer
            release.set()
            raise KeyboardInterrupt
        finish = real(self, path, *a, **kw)
        if name != "a.png":
            return finish

        def slow():
            release.wait(timeout=20)
            return finish()

        slow.encodes = finish.encodes
        return slow

    monkeypatch.setattr(Processor, "begin_file", begin)
    monkeypatch.setattr(C, "WRITE_FRAMES", 4)
    rc = main(["correct", "-o", str(tmp_path / "out"), "--profile", str(PROFILE), *map(str, files)])
    err = capsys.readouterr().err
    assert rc == 130
    done = sorted(p.name for p in (tmp_path / "out").iterdir())
    assert "a.corrected.png" in done and "a.png.vigproc.json" in done
    n = sum(f"{x}.corrected.png" in done for x in "bc")  # b, c: written or not started, never half
    assert f"{1 + n} corrected, 0 not corrected, 0 failed, {3 - n} not started" in err, err
    assert all((f"{x}.png.vigproc.json" in done) == (f"{x}.corrected.png" in done) for x in "bc")
    assert not list((tmp_path / "out").glob(".*tmp*"))


def test_a_frame_read_ahead_comes_with_its_reduced_copy_and_counts(tmp_path):
    """The read-ahead thread makes the passes over the codes the frame's path makes (the
    reduced copy the estimate reads, the code range, the white samples): the same values."""
    from vigproc.core.estimate import reduction_factor
    from vigproc.core.pixels import reduce_codes
    from vigproc.core.preload import preload_numba
    from vigproc.io.images import write_image
    from vigproc.pipeline.processor import Processor, Settings

    img = np.stack([textured(720, 1080, seed=c) for c in range(3)], -1)
    a = tmp_path / "big.png"
    write_image(a, np.clip(img, 0, 1).astype(np.float32), bit_depth="uint8", transfer="srgb")
    preload_numba().join()
    with Processor(Settings(mode="correct")) as proc:
        proc.read_ahead(a)
        enc = proc.read_frame(a).img
    k = reduction_factor(1080, 720)
    assert k > 1 and enc._reduced and enc._reduced[0] == k  # made in the reading thread
    small, usable = reduce_codes(enc.codes, enc.decode_table(), k)
    assert np.array_equal(enc._reduced[1], small)
    assert (usable is None and enc._reduced[2] is None) or np.array_equal(enc._reduced[2], usable)
    assert enc._counts == {"range": (int(enc.codes.min()), int(enc.codes.max())),
                           "top": int(np.count_nonzero(enc.codes == 255))}


def test_correct_with_a_writer_thread_starts_the_metadata_writer_only_to_write(tmp_path, monkeypatch, capsys):
    """With a writer thread, ``correct`` does not launch the metadata writer's exiftool up
    front (it would take a core from Numba's set-up): a run that corrects nothing never
    starts it; one file alone (written in the main thread) still launches it early."""
    import vigproc.io.metadata as M
    from vigproc.frontends.cli import main

    files = [_photo(tmp_path / f"{n}.png", i) for i, n in enumerate("ab")]
    spawned = []
    monkeypatch.setattr(M, "spawn_exiftool", lambda: spawned.append(1))
    assert main(["correct", "-o", str(tmp_path / "out"), "--profile", str(PROFILE), "--strength", "0",
                 "--unapplied", "copy", *map(str, files)]) == 0
    assert spawned == []
    assert main(["correct", "-o", str(tmp_path / "one"), "--profile", str(PROFILE), str(files[0])]) == 0
    assert spawned == [1]
