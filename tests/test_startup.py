"""What a new process pays before its first frame (issue 39): the profile store's
import loads no Numba, exiftool launched early answers its first command (and one
that cannot run is reported there, as a start would), Numba's set-up preloads in a
thread, and ``Processor.prepare`` changes nothing of what a file gets."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from vigproc.errors import VigprocError

ROOT = Path(__file__).resolve().parents[1]
needs_exiftool = pytest.mark.skipif(shutil.which("exiftool") is None, reason="exiftool is not installed")


def _fresh(code: str) -> str:
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, timeout=120)
    assert out.returncode == 0, out.stderr
    return out.stdout.strip()


def test_store_import_loads_no_numba():
    # the store and the model it reads are needed before any kernel (and by commands with none)
    assert _fresh("import sys, vigproc.stores.profiles, vigproc.core.model; print('numba' in sys.modules)") == "False"


def test_model_field_still_computed_after_lazy_kernel_import():
    from vigproc.core.model import VignettingModel

    m = VignettingModel(width=64, height=48, p=(1 / 1600, 0.0, 1 / 1600), alpha=(0.2,) + (0.0,) * 6)
    f = m.log_field()
    assert f.shape == (48, 64) and f[24, 32] > f[0, 0]  # brightest at the centre, darkest in a corner


def test_preload_numba_one_thread_and_kernels_run():
    code = (
        "import sys\n"
        "from vigproc.core.preload import preload_numba\n"
        "t = preload_numba(); assert preload_numba() is t\n"
        "t.join(120)\n"
        "from numba.core.registry import cpu_target\n"
        "from vigproc.core.model import VignettingModel\n"
        "print(not t.is_alive(), 'scipy.linalg' in sys.modules,"
        " round(float(VignettingModel(width=8, height=8, p=(0.1, 0.0, 0.1), alpha=(0.2,) + (0.0,) * 6).log_field()[0, 0]), 6) < 0)\n"
    )
    # finished, and what it did is the target context's refresh (which imports Numba's LAPACK: scipy.linalg)
    assert _fresh(code) == "True True True"


def test_preload_takes_numbas_locks_in_numbas_order():
    """A kernel imported while the preload runs: the importing thread holds the lock that
    creates Numba's target context, then wants the compiler lock.  The preloader, blocked
    on that creation, must not be holding the compiler lock (it did: `vigproc correct`
    hung for ever, one time in a few under load).  Made deterministic: this thread holds
    the creation lock until the preloader waits on it, then asks for the compiler lock."""
    code = (
        "import sys, time\n"
        "from numba.core.compiler_lock import global_compiler_lock\n"
        "from numba.core.registry import CPUTarget\n"
        "creation = CPUTarget.__dict__['_toplevel_target_context']._lock\n"
        "creation.acquire()\n"
        "from vigproc.core.preload import preload_numba\n"
        "t = preload_numba()\n"
        "def waiting():\n"
        "    f = sys._current_frames().get(t.ident)\n"
        "    while f is not None:\n"
        "        if f.f_code.co_name == '__get__' and f.f_code.co_filename.endswith('utils.py'):\n"
        "            return True\n"
        "        f = f.f_back\n"
        "    return False\n"
        "deadline = time.monotonic() + 100\n"
        "while not waiting() and t.is_alive() and time.monotonic() < deadline:\n"
        "    time.sleep(0.01)\n"
        "assert waiting(), 'the preloader never asked for the target context'\n"
        "got = global_compiler_lock._lock.acquire(timeout=5)\n"
        "if got:\n"
        "    global_compiler_lock._lock.release()\n"
        "creation.release()\n"
        "t.join(100)\n"
        "print(got, not t.is_alive())\n"
    )
    assert _fresh(code) == "True True"


def test_kernels_imported_while_the_preload_imports_numba_leave_numba_whole():
    """The caller's thread imports the kernels (and so Numba) while the preloader is inside
    Numba's own imports: the two threads' imports must not interleave (they did: the
    preloader's import failed on a partially initialised module, was undone, and left a
    ``numba`` without ``numba.core``; the first `vigproc correct` of a fresh install then
    failed compiling a kernel: "internal error (AttributeError: module 'numba' has no
    attribute 'core')")."""
    code = (
        "import logging, sys, time\n"
        "failed = []\n"
        "class H(logging.Handler):\n"
        "    def emit(self, r): failed.append(r.getMessage())\n"
        "lg = logging.getLogger('vigproc.core.preload'); lg.setLevel(logging.DEBUG); lg.addHandler(H())\n"
        "from vigproc.core.preload import preload_numba\n"
        "t = preload_numba()\n"
        "deadline = time.monotonic() + 60\n"
        "while 'numba.core' not in sys.modules and t.is_alive() and time.monotonic() < deadline:\n"
        "    time.sleep(0.0005)\n"
        "import vigproc.core._kernels\n"
        "t.join(120)\n"
        "import numba\n"
        "print(failed, hasattr(numba, 'core'))\n"
    )
    assert _fresh(code) == "[] True"


@needs_exiftool
def test_spawned_exiftool_answers_its_first_command():
    from vigproc.io.exiftool_process import ExiftoolProcess

    proc = ExiftoolProcess().spawn()
    try:
        assert proc.running and proc.launches == 1
        res = proc.execute(["-ver"])
        assert res.status == 0 and res.stdout.decode().strip() == proc.version
        assert proc.spawn() is proc and proc.launches == 1  # running: a no-op
    finally:
        proc.close()


def test_spawn_of_a_program_that_cannot_run_is_reported_by_the_first_command(tmp_path):
    from vigproc.io.exiftool_process import ExiftoolProcess

    # launches (the file exists and runs) but exits without answering: what start() reports, at first use
    exe = tmp_path / "not-exiftool"
    exe.write_text("#!/bin/sh\nsleep 0.5\nexit 3\n")
    exe.chmod(0o755)
    proc = ExiftoolProcess(str(exe))
    proc.spawn()  # does not wait: no error yet
    with pytest.raises(VigprocError, match="cannot run exiftool"):
        proc.execute(["-ver"])
    with pytest.raises(VigprocError, match="cannot run exiftool"):
        ExiftoolProcess(str(tmp_path / "no-such-exiftool")).spawn()  # cannot even be launched


@needs_exiftool
def test_prepare_changes_nothing_a_file_gets(tmp_path):
    import OpenImageIO as oiio

    from vigproc.pipeline.processor import Processor, Settings

    rng = np.random.default_rng(3)
    yy, xx = np.mgrid[0:240, 0:320]
    r2 = ((xx - 160) ** 2 + (yy - 120) ** 2) / (200.0 ** 2)
    img = np.clip((0.25 + 0.5 * rng.random((240, 320, 1))) * (1 - 0.5 * r2)[..., None], 0, 1)
    codes = (np.repeat(img, 3, axis=-1) * 255).astype(np.uint8)
    src = tmp_path / "in.jpg"
    out = oiio.ImageOutput.create(str(src))
    assert out.open(str(src), oiio.ImageSpec(320, 240, 3, "uint8")) and out.write_image(codes)
    out.close()
    before = src.read_bytes()
    records = []
    for prepare in (False, True):
        settings = Settings(mode="correct", profile="estimate", unapplied="copy")
        outdir = tmp_path / f"out{int(prepare)}"
        outdir.mkdir()
        with Processor(settings) as proc:
            if prepare:
                proc.prepare()
            rec = proc.process_file(src, outdir, "in").to_dict()
            assert proc.reader._proc.launches == 1
        records.append(rec)
        assert Path(rec["output"]).is_file()
    a, b = records
    assert a["applied"] == b["applied"] and a.get("not_applied") == b.get("not_applied")
    fit = ("center", "p", "alpha", "method", "width", "height")
    assert json.dumps({k: a["model"][k] for k in fit}) == json.dumps({k: b["model"][k] for k in fit})
    from vigproc.io.images import read_encoded

    pa, pb = (read_encoded(r["output"])[0] for r in (a, b))  # the pixels (the metadata holds times)
    assert np.array_equal(pa.codes, pb.codes)
    assert src.read_bytes() == before


def _jpeg(path: Path, model: str) -> Path:
    import OpenImageIO as oiio

    spec = oiio.ImageSpec(32, 24, 3, "uint8")
    spec.attribute("Make", "Testmaker")
    spec.attribute("Model", model)
    out = oiio.ImageOutput.create(str(path))
    assert out.open(str(path), spec) and out.write_image(np.full((24, 32, 3), 128, np.uint8))
    out.close()
    return path


def _counting(reader):
    calls = []
    execute = reader._proc.execute

    def counted(args, **kw):
        calls.append(list(args))
        return execute(args, **kw)

    reader._proc.execute = counted
    return calls


@needs_exiftool
def test_prefetched_exif_is_the_same_record_and_no_second_read(tmp_path):
    from vigproc.io.exif import ExifReader

    a, b = _jpeg(tmp_path / "a.jpg", "Alpha 1"), _jpeg(tmp_path / "b b.jpg", "Beta 2")
    with ExifReader() as plain:
        want = {p: plain.read_file(p).record for p in (a, b)}
    with ExifReader() as reader:
        calls = _counting(reader)
        reader.prefetch(a)
        reader.prefetch(b)
        got_a = reader.read_file(a)
        got_b = reader.read_file(b)
        assert calls == []  # both answers came from the prefetch
        assert got_a.record == want[a] and got_b.record == want[b]
        assert got_a.read().model == "alpha 1" and got_b.read().model == "beta 2"
        # asked ahead but skipped (the file before it failed, say): read again when its turn comes
        reader.prefetch(a)
        reader.prefetch(b)
        assert reader.read_file(b).record == want[b] and calls == []
        assert reader.read_file(a).record == want[a] and len(calls) == 1


@needs_exiftool
def test_prefetch_of_a_file_changed_since_is_not_used(tmp_path):
    from vigproc.io.exif import ExifReader

    a = _jpeg(tmp_path / "a.jpg", "Before")
    with ExifReader() as reader:
        calls = _counting(reader)
        reader.prefetch(a)
        _jpeg(tmp_path / "new.jpg", "After 2").replace(a)  # another file under the same name
        assert reader.read_file(a).read().model == "after 2" and len(calls) == 1


@needs_exiftool
def test_submitted_answers_come_back_in_order_and_a_death_is_reported(tmp_path):
    import signal

    from vigproc.io.exiftool_process import ExiftoolDied, ExiftoolProcess

    proc = ExiftoolProcess().start()
    try:
        p1 = proc.submit(["-echo", "first"])
        p2 = proc.submit(["-echo", "second"])
        time.sleep(1.0)  # both answered: one read of the pipe brings both
        assert proc.result(p1).stdout == b"first"
        p3 = proc.submit(["-echo", "third"])
        assert proc.execute(["-echo", "fourth"]).stdout == b"fourth"  # reads those before it first
        assert proc.result(p3).stdout == b"third" and proc.result(p2).stdout == b"second"
        os.kill(proc.pid, signal.SIGSTOP)  # stopped: the next command is sent but never answered
        p5 = proc.submit(["-echo", "lost"])
        os.kill(proc.pid, signal.SIGKILL)
        with pytest.raises(ExiftoolDied):
            proc.result(p5)
        assert proc.execute(["-echo", "again"]).stdout == b"again" and proc.launches == 2
    finally:
        proc.close()


def test_an_answer_read_together_with_the_next_is_split_at_its_marker():
    from vigproc.io.exiftool_process import _marker_line

    buf = b'[{"A": "x {ready12} y"}]\n{ready12}\n[{"B": 1}]\n{ready34}\n'
    cut = _marker_line(buf, b"{ready12}")
    assert buf[:cut] == b'[{"A": "x {ready12} y"}]\n{ready12}\n'  # the quoted one is not the end
    assert _marker_line(buf[cut:], b"{ready34}") == len(buf) - cut
    assert _marker_line(b"=0=post7", b"post7") == 8 and _marker_line(b"=0=pos", b"post7") == -1
