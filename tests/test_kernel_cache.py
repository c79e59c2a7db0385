"""The guard of the Numba kernels' on-disk cache (vigproc/core/_kernels/__init__.py):
Numba reuses a cached kernel while its own file is unchanged, so a caller would keep a
changed callee's old code; the guard drops the cache when any kernel source changed."""

from __future__ import annotations

import logging
import os
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

from vigproc.core import _kernels as guard

ROOT = Path(__file__).resolve().parents[1]
CACHE_FILES = ("a.a-3.py311.nbi", "a.a-3.py311.1.nbc", "b.b-2.py311.nbi", "b.b-2.py311.1.nbc")


def _folders(tmp_path: Path) -> tuple[Path, Path]:
    """Fake kernel sources and a cache folder holding fake Numba files and the stamp of
    the sources as they are."""
    src, cache = tmp_path / "kernels", tmp_path / "cache"
    src.mkdir()
    cache.mkdir()
    (src / "a.py").write_text("from b import b\ndef a(x):\n    return b(x) * 10\n")
    (src / "b.py").write_text("def b(x):\n    return x + 1\n")
    assert guard.flush_if_stale(str(src), str(cache))  # no stamp yet: flushes, stamps
    for name in CACHE_FILES:
        (cache / name).write_bytes(b"compiled")
    (cache / "a.cpython-311.pyc").write_bytes(b"bytecode")
    return src, cache


def test_a_changed_callee_flushes_the_cache_and_writes_the_new_stamp(tmp_path):
    src, cache = _folders(tmp_path)
    (src / "b.py").write_text("def b(x):\n    return x + 2\n")
    assert guard.check_cache(str(src), str(cache))
    assert sorted(p.name for p in cache.iterdir()) == ["a.cpython-311.pyc", guard.STAMP]
    new = guard.sources_digest(guard.kernel_sources(str(src)))
    assert (cache / guard.STAMP).read_text().strip() == new
    (cache / CACHE_FILES[0]).write_bytes(b"compiled")  # recompiled: the new stamp holds
    assert not guard.check_cache(str(src), str(cache)) and (cache / CACHE_FILES[0]).exists()


def test_unchanged_sources_keep_the_cache(tmp_path):
    src, cache = _folders(tmp_path)
    assert not guard.check_cache(str(src), str(cache))
    assert all((cache / n).read_bytes() == b"compiled" for n in CACHE_FILES)


def test_a_new_kernel_file_counts_as_a_change(tmp_path):
    src, cache = _folders(tmp_path)
    (src / "c.py").write_text("")
    assert guard.check_cache(str(src), str(cache)) and not (cache / CACHE_FILES[0]).exists()


def test_a_cache_folder_not_made_yet_gets_the_stamp(tmp_path):
    # a fresh install: Numba makes its folder at its first save, after the guard ran;
    # without a stamp then, the next import would flush what the first one compiled
    src, _ = _folders(tmp_path)
    cache = tmp_path / "not-yet" / "__pycache__"
    assert guard.check_cache(str(src), str(cache))
    assert (cache / guard.STAMP).read_text().strip() == guard.sources_digest(guard.kernel_sources(str(src)))
    assert not guard.check_cache(str(src), str(cache))


def test_an_unwritable_cache_folder_does_not_raise(tmp_path, monkeypatch, caplog):
    src, cache = _folders(tmp_path)
    (src / "b.py").write_text("def b(x):\n    return x + 2\n")
    old = (cache / guard.STAMP).read_text()

    def refused(path, *a, **k):
        raise PermissionError(13, "Permission denied", path)

    monkeypatch.setattr(guard.os, "unlink", refused)  # the tests run as root: chmod would not stop them
    with caplog.at_level(logging.DEBUG, logger=guard.__name__):
        assert guard.check_cache(str(src), str(cache)) is False
    assert "PermissionError" in caplog.text
    assert (cache / guard.STAMP).read_text() == old  # not stamped: the next import tries again
    monkeypatch.undo()
    assert guard.check_cache(str(src), str(cache))


def test_unexpected_errors_and_a_changed_numba_api_do_not_raise(tmp_path, monkeypatch, caplog):
    src, _ = _folders(tmp_path)
    with caplog.at_level(logging.DEBUG, logger=guard.__name__):
        assert guard.check_cache(str(tmp_path / "no such folder")) is False
        monkeypatch.setattr(guard._caching, "CompileResultCacheImpl", None)  # gone in a later Numba
        assert guard.check_cache(str(src)) is False
        monkeypatch.setattr(guard, "_caching", None)
        assert guard.check_cache(str(src)) is False
    assert "FileNotFoundError" in caplog.text and "TypeError" in caplog.text
    assert "no Numba cache folder" in caplog.text


def test_the_cache_folder_is_numbas(tmp_path, monkeypatch):
    from numba.core import config

    src, _ = _folders(tmp_path)
    source = guard.kernel_sources(str(src))[0]
    monkeypatch.setattr(config, "CACHE_DIR", "")
    assert guard.numba_cache_dir(source) == str(src / "__pycache__")
    monkeypatch.setattr(config, "CACHE_DIR", str(tmp_path / "numba"))  # NUMBA_CACHE_DIR
    where = guard.numba_cache_dir(source)
    assert Path(where).parent == tmp_path / "numba" and Path(where).name.startswith("kernels_")


A = """
from numba import njit
from kp.b import b

@njit(cache=True)
def a(x):
    return b(x) * 10
"""
B = """
from numba import njit

@njit(cache=True)
def b(x):
    return x + {}
"""
GUARD = "import os\nfrom vigproc.core._kernels import check_cache\ncheck_cache(os.path.dirname(__file__))\n"


def _run(root: Path) -> str:
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(root), str(ROOT)])}
    out = subprocess.run([sys.executable, "-c", "from kp.a import a; print(a(1))"], capture_output=True,
                         text=True, env=env, timeout=300, cwd=root)
    assert out.returncode == 0, out.stderr
    return out.stdout.strip()


@pytest.mark.parametrize("guarded", [False, True])
def test_a_caller_sees_its_changed_callee(tmp_path, guarded):
    """End to end, a kernel calling a kernel of another file, in fresh processes.  Without
    the guard Numba runs the caller's stale code (Numba 0.68: 20 after b changed to x + 22);
    should that assertion fail, Numba tracks callees itself and the guard can go.  The new
    b is longer than the old: Python's own bytecode cache checks a source's size and its
    mtime in whole seconds, and took a same-size b rewritten within the second for the old
    one (CI once printed 20 with the guard on: Numba had compiled the old bytecode)."""
    pkg = tmp_path / "kp"
    pkg.mkdir()
    (pkg / "__init__.py").write_text(GUARD if guarded else "")
    (pkg / "a.py").write_text(A)
    (pkg / "b.py").write_text(B.format(1))
    assert _run(tmp_path) == "20"
    (pkg / "b.py").write_text(B.format(22))
    assert _run(tmp_path) == ("230" if guarded else "20")
    assert _run(tmp_path) == ("230" if guarded else "20")  # and from the new cache
