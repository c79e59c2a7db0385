"""``vigproc bench throughput``: vigproc correct beside the floor, on real files."""

from __future__ import annotations

import json
from dataclasses import asdict
import subprocess

import numpy as np
import pytest

from benchmarks import throughput as T
from vigproc.errors import VigprocError
from vigproc.io.images import jpeg_quality, write_image
from vigproc.io.metadata import exiftool_path

from conftest import coloured_scene


def _photo(path, seed, quality):
    write_image(path, np.clip(coloured_scene(120, 180, seed=seed), 0, 1), transfer="srgb", quality=quality)
    subprocess.run([exiftool_path(), "-q", "-overwrite_original", f"-Make=Maker{seed}", "-Model=Cam", str(path)],
                   check=True)


@pytest.fixture
def photos(tmp_path):
    src = tmp_path / "src"
    src.mkdir()
    _photo(src / "a.jpg", 1, 91)
    _photo(src / "b b.JPG", 2, 97)
    (src / "broken.jpg").write_bytes((src / "a.jpg").read_bytes()[:300])  # truncated: no image
    (src / "notes.txt").write_text("not a photograph")
    write_image(src / "flat.jpg", np.full((60, 90), 0.5, np.float32), transfer="srgb")  # vigproc refuses it
    return src


def test_photos_are_the_decodable_jpegs_large_enough(photos):
    chosen, skipped = T.select_photos(photos, min_megapixels=0.0)
    assert [p.path.name for p in chosen] == ["a.jpg", "b b.JPG"]
    assert chosen[0].megapixels == pytest.approx(180 * 120 / 1e6)
    assert sorted(skipped) == [str(photos / "broken.jpg"), str(photos / "flat.jpg")]
    assert "constant" in skipped[str(photos / "flat.jpg")]
    with pytest.raises(VigprocError):
        T.select_photos(photos, min_megapixels=1.0)


def test_the_floor_reencodes_at_each_files_quality_and_copies_its_exif(photos, tmp_path):
    chosen, _ = T.select_photos(photos, min_megapixels=0.0)
    staged = T.stage(chosen, tmp_path / "in")
    assert [p.name for p in staged] == ["000_a.jpg", "001_b_b.JPG"]
    assert T.floor_run(tmp_path / "in", tmp_path / "out") == 2
    assert T.floor_run(tmp_path / "in", tmp_path / "lap", overlap=True) == 2
    for p in staged:
        out = tmp_path / "out" / p.name
        assert jpeg_quality(out) == jpeg_quality(p)
        make = subprocess.run([exiftool_path(), "-s3", "-Make", str(out)], capture_output=True, text=True).stdout
        assert make.strip() == subprocess.run([exiftool_path(), "-s3", "-Make", str(p)], capture_output=True,
                                              text=True).stdout.strip()
        # the overlapped floor does the same work: the same pixels and file
        assert (tmp_path / "lap" / p.name).read_bytes() == out.read_bytes()


def test_a_run_times_every_tool_and_checks_their_outputs(photos, tmp_path):
    chosen, skipped = T.select_photos(photos, min_megapixels=0.0)
    r = T.run_throughput(chosen, rounds=1, darktable=False, workdir=tmp_path, skipped=skipped)
    assert [t.name for t in r.tools] == ["floor", "floor-overlap", "vigproc"]
    assert all(len(t.seconds) == 1 and t.seconds[0] > 0 and t.outputs == 2 for t in r.tools)
    rows = r.rows()
    assert rows[0][3] == 1.0 and rows[2][3] == pytest.approx(rows[2][1] / rows[0][1])
    assert rows[1][5] == 1.0 and rows[2][5] == pytest.approx(rows[2][1] / rows[1][1])
    lines = T.format_result(r)
    assert lines[2].startswith("floor") and lines[3].startswith("floor-overlap") and lines[4].startswith("vigproc")
    assert json.loads(json.dumps(asdict(r)))["photos"] == [str(p.path) for p in chosen]


def test_with_a_baseline_each_vigproc_has_a_store_of_its_own(tmp_path):
    tools = [T.ToolTiming("floor", []), T.ToolTiming("vigproc", []), T.ToolTiming("vigproc-baseline", [], tree="/x")]
    envs = [T._env(t, tmp_path) for t in tools]
    stores = [e.get("VIGPROC_PROFILE_DB") for e in envs[1:]]
    assert stores[0] != stores[1] and all(s.startswith(str(tmp_path)) for s in stores)
    assert envs[2]["PYTHONPATH"] == "/x"
    assert T._env(tools[1])["VIGPROC_PROFILE_DB"] == __import__("os").environ.get("VIGPROC_PROFILE_DB")


def test_the_cli_needs_a_folder(tmp_path):
    import sys

    res = subprocess.run([sys.executable, "-m", "vigproc.frontends.cli", "bench", "throughput"], capture_output=True,
                         text=True)
    assert res.returncode != 0 and "--images DIR or --raw DIR" in res.stderr and "Traceback" not in res.stderr
