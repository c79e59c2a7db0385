"""vigproc.atomic.replacing: the one temp-then-rename every writer goes through."""

from __future__ import annotations

import os
import stat

import pytest

from vigproc.atomic import replacing, temporary_keys
from vigproc.errors import ImageWriteError
from vigproc.pipeline.processor import keep_original


def test_publishes_whole_file_with_the_old_mode(tmp_path):
    dst = tmp_path / "out.tif"
    dst.write_bytes(b"old")
    os.chmod(dst, 0o640)
    with replacing(dst, suffix=".tif") as tmp:
        assert os.path.dirname(tmp) == str(tmp_path) and tmp.endswith(".tif")
        assert dst.read_bytes() == b"old"  # untouched until the block ends
        with open(tmp, "wb") as fh:
            fh.write(b"new")
    assert dst.read_bytes() == b"new"
    assert stat.S_IMODE(dst.stat().st_mode) == 0o640
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out.tif"]


def test_failure_removes_temporary_and_leftovers_and_keeps_old(tmp_path):
    dst = tmp_path / "out.jpg"
    dst.write_bytes(b"old")
    with pytest.raises(RuntimeError), replacing(dst, leftovers=("_exiftool_tmp",)) as tmp:
        open(tmp + "_exiftool_tmp", "wb").close()
        raise RuntimeError("writer failed")
    assert dst.read_bytes() == b"old"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out.jpg"]


def test_temporary_inside_a_temporary_is_swept_by_its_output_name(tmp_path):
    dst = tmp_path / ("IMG_0001.corrected." + "x" * 240 + ".tif")[:250]
    with replacing(dst, keep=60) as outer, replacing(outer, suffix=".tif") as inner:
        for t in (outer, inner):
            name = os.path.basename(t)
            assert len(name.encode()) <= 255
            assert "IMG_0001.cor" in temporary_keys(name), name
        open(inner, "wb").close()
    assert dst.exists() and len(list(tmp_path.iterdir())) == 1


def test_no_room_for_a_temporary_is_a_typed_error(tmp_path):
    with pytest.raises(ImageWriteError, match="cannot write x: cannot create a temporary file"):
        with replacing(tmp_path / "missing" / "out.tif", what="cannot write x"):
            pass
    with pytest.raises(OSError):  # no ``what``: the caller's OSError
        with replacing(tmp_path / "missing" / "out.tif"):
            pass


def test_status_like_write_unsynced_with_fixed_mode(tmp_path):
    dst = tmp_path / "status.json"
    with replacing(dst, prefix=".status.json.", suffix=".tmp", mode=0o644, sync=False) as tmp:
        assert os.path.basename(tmp).startswith(".status.json.") and tmp.endswith(".tmp")
        with open(tmp, "w") as fh:
            fh.write("{}")
    assert dst.read_text() == "{}" and stat.S_IMODE(dst.stat().st_mode) == 0o644


@pytest.mark.parametrize("link", [True, False])
def test_keep_original_link_or_copy(tmp_path, link):
    src = tmp_path / "in.jpg"
    src.write_bytes(b"jpeg bytes")
    os.chmod(src, 0o604)
    dst = tmp_path / "out" / "in.jpg"
    dst.parent.mkdir()
    keep_original(src, dst, link=link)
    assert dst.read_bytes() == b"jpeg bytes"
    assert os.path.samefile(src, dst) is link
    assert stat.S_IMODE(src.stat().st_mode) == 0o604  # a hard link's mode is never changed
    assert [p.name for p in dst.parent.iterdir()] == ["in.jpg"]
