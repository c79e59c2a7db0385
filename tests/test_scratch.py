"""Private temporary folders do not pile up: not even a process killed with SIGKILL leaves one
for longer than until the next vigproc process makes one (vigproc.scratch)."""

from __future__ import annotations

import os
import shutil
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import pytest

import vigproc
from vigproc import scratch
from vigproc.io.exiftool_process import CONFIG_FILE
from vigproc.io.metadata import XMP_NAMESPACE

ROOT = Path(vigproc.__file__).resolve().parents[1]
needs_exiftool = pytest.mark.skipif(shutil.which("exiftool") is None, reason="exiftool program not installed")
needs_proc = pytest.mark.skipif(not os.path.isdir("/proc/self"), reason="no /proc: process start times unknown")


def run_killed(code: str, tmpdir: Path) -> str:
    """Run ``code`` in a new Python with TMPDIR=``tmpdir``; it ends by killing itself with SIGKILL
    (no finally, no atexit). Returns what it printed."""
    tmpdir.mkdir(exist_ok=True)
    env = dict(os.environ, TMPDIR=str(tmpdir), PYTHONPATH=str(ROOT))
    code = textwrap.dedent(code) + "\nimport os, signal, sys\nsys.stdout.flush()\nos.kill(os.getpid(), signal.SIGKILL)\n"
    res = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=300)
    assert res.returncode == -signal.SIGKILL, res.stderr
    return res.stdout


def test_a_killed_metadata_writer_leaves_no_folder(tmp_path: Path) -> None:
    """The path that left 243 folders in /tmp: a process that wrote metadata made a folder for
    exiftool's config, removed only at exit; a killed worker never got there."""
    if shutil.which("exiftool") is None:
        pytest.skip("exiftool program not installed")
    work = tmp_path / "work"
    work.mkdir()
    out = run_killed(f"""
        import numpy as np
        from vigproc.core.model import VignettingModel
        from vigproc.io.images import write_image
        from vigproc.io.metadata import make_record, read_record, write_corrected
        img = np.full((24, 32, 3), 0.25, np.float32)
        write_image({str(work / 'src.tif')!r}, img, bit_depth="uint16")
        dst = {str(work / 'out.tif')!r}
        write_corrected(dst, img, {str(work / 'src.tif')!r},
                        make_record(VignettingModel(32, 24, alpha=(0.01, 0, 0, 0, 0, 0, 0))), bit_depth="uint16")
        print(read_record(dst)["method"])
    """, tmp_path / "tmp")
    assert out.strip()  # the record was written with the shipped namespace and read back
    assert sorted(os.listdir(tmp_path / "tmp")) == []


@needs_exiftool
@needs_proc
def test_a_killed_process_s_alias_folder_goes_with_the_next_process(tmp_path: Path) -> None:
    """A name exiftool's argument protocol cannot carry is passed through an alias in a private
    folder; killed while it exists, the next vigproc process that needs one removes it."""
    hostile = tmp_path / "line\nbreak.jpg"
    hostile.write_bytes(b"\xff\xd8\xff\xd9")
    out = run_killed(f"""
        from vigproc.io.metadata import _Exiftool
        et = _Exiftool().__enter__()
        print(et.source_name({str(hostile)!r}))
    """, tmp_path / "tmp")
    folder = Path(out.strip()).parent
    assert folder.parent == tmp_path / "tmp" and folder.is_dir()  # left by the kill
    env = dict(os.environ, TMPDIR=str(tmp_path / "tmp"), PYTHONPATH=str(ROOT))
    subprocess.run([sys.executable, "-c", "from vigproc.scratch import scratch\nwith scratch('name'): pass"],
                   env=env, check=True, timeout=120)
    assert not folder.exists()
    assert sorted(os.listdir(tmp_path / "tmp")) == []
    assert hostile.read_bytes() == b"\xff\xd8\xff\xd9"


@needs_proc
def test_a_killed_batch_worker_s_shipped_files_are_swept(tmp_path: Path) -> None:
    """A batch worker writes the files the client ships (a profile file) into a folder it
    removed only at exit."""
    out = run_killed("""
        from vigproc.frontends.batch_worker import Shipped, _materialise
        print(_materialise(Shipped.of("profile.json", b"{}")))
    """, tmp_path / "tmp")
    folder = Path(out.strip()).parent
    assert folder.parent == tmp_path / "tmp" and folder.is_dir()
    assert scratch.sweep(str(tmp_path / "tmp")) == 1
    assert not folder.exists()


@needs_proc
def test_the_sweep_keeps_live_owners_and_other_folders(tmp_path: Path, monkeypatch) -> None:
    monkeypatch.setattr("tempfile.tempdir", str(tmp_path))
    with scratch.scratch("exiftool") as mine:
        # a process that has ended (reaped): its folder goes
        gone = subprocess.Popen([sys.executable, "-c", "pass"])
        gone.wait()
        dead = tmp_path / f"vigproc-exiftool-{gone.pid}.1-abcdefgh"
        dead.mkdir()
        # this process's id with another start time: a recycled id, not the owner
        recycled = tmp_path / f"vigproc-batch-{os.getpid()}.1-abcdefgh"
        recycled.mkdir()
        others = [tmp_path / "vigproc-bench-watch-abcdefgh", tmp_path / "vigproc-exiftool-young123",
                  tmp_path / "vigproc-exiftool-notonly1", tmp_path / "unrelated"]
        for o in others:
            o.mkdir()
        (tmp_path / "vigproc-exiftool-young123" / "vigproc.config").write_text("1;\n")
        (tmp_path / "vigproc-exiftool-notonly1" / "source.jpg").write_text("")
        os.utime(tmp_path / "vigproc-exiftool-notonly1", (time.time() - 7200,) * 2)
        # a folder of the earlier form holding only its config, older than an hour: goes
        legacy = tmp_path / "vigproc-exiftool-oldform1"
        legacy.mkdir()
        (legacy / "vigproc.config").write_text("1;\n")
        os.utime(legacy, (time.time() - 7200,) * 2)
        assert scratch.sweep() == 3
        assert Path(mine).is_dir() and all(o.is_dir() for o in others)
        assert not dead.exists() and not recycled.exists() and not legacy.exists()
    assert not Path(mine).exists()
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted(o.name for o in others)


def test_a_scratch_kind_is_letters_only() -> None:
    with pytest.raises(ValueError):
        scratch.scratch_folder("../x")


def test_the_shipped_exiftool_config_declares_the_record_s_namespace() -> None:
    text = Path(CONFIG_FILE).read_text(encoding="utf-8")
    assert f"'vigproc' => '{XMP_NAMESPACE}'" in text
    for tag in ("Model", "Method", "Version", "Applied", "Strength", "Transfer"):
        assert f"    {tag} => {{" in text


@needs_proc
def test_a_killed_hook_call_s_folder_beside_its_output_goes_with_the_next_call(tmp_path: Path) -> None:
    """``vigproc hook --output-file`` writes into a hidden folder beside the target (one rename
    publishes it); killed mid-write, the folder stays until the next hook call writing there."""
    import numpy as np

    from vigproc.io.images import write_image

    src, out = tmp_path / "src.tif", tmp_path / "out"
    out.mkdir()
    write_image(src, np.full((24, 32, 3), 0.25, np.float32), bit_depth="uint16")
    before = src.read_bytes()
    printed = run_killed(f"""
        import os, signal, sys
        from vigproc.pipeline.processor import Processor
        def killed(self, path, work, *args, **kwargs):
            print(work)
            sys.stdout.flush()
            os.kill(os.getpid(), signal.SIGKILL)
        Processor.process_file = killed
        from vigproc.frontends.cli import main
        main(["hook", "--output-file={out / 'a.tif'}", "--", {str(src)!r}])
    """, tmp_path / "tmp")
    left = Path(printed.strip())
    assert left.parent == out and left.is_dir() and left.name.startswith(".vigproc-hook-")
    env = dict(os.environ, TMPDIR=str(tmp_path / "tmp"), PYTHONPATH=str(ROOT))
    subprocess.run([sys.executable, "-m", "vigproc.frontends.cli", "hook", f"--output-file={out / 'b.tif'}",
                    "--", str(src)], env=env, capture_output=True, text=True, timeout=300)
    assert not left.exists()
    assert not [p for p in out.iterdir() if p.name.startswith(".vigproc-hook-")]  # nor the second call's
    assert src.read_bytes() == before


@needs_proc
def test_a_killed_report_writer_s_folder_is_swept(tmp_path: Path) -> None:
    """A report's figures go through a scratch folder: a writer killed inside it leaves a
    folder the next process sweeps."""
    printed = run_killed("""
        import os, signal, sys
        import numpy as np
        import vigproc.io.images as images
        from vigproc.forensics.report import jpeg_bytes
        write = images.write_image
        def killed(path, *args, **kwargs):
            write(path, *args, **kwargs)
            print(path)
            sys.stdout.flush()
            os.kill(os.getpid(), signal.SIGKILL)
        images.write_image = killed
        jpeg_bytes(np.full((16, 16, 3), 0.5, np.float32))
    """, tmp_path / "tmp")
    folder = Path(printed.strip()).parent
    assert folder.parent == tmp_path / "tmp" and folder.is_dir() and folder.name.startswith("vigproc-report-")
    assert scratch.sweep(str(tmp_path / "tmp")) == 1
    assert not folder.exists()
