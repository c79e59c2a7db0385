"""``vigproc bench scaling``'s staging: copies of a photograph are distinct files with
the original's pixels and tags (``--copies``)."""

from __future__ import annotations

import hashlib
import subprocess

import numpy as np
import pytest

from vigproc.errors import VigprocError
from vigproc.io.metadata import exiftool_path


def _jpeg(path, seed=0):
    import OpenImageIO as oiio

    px = np.random.default_rng(seed).integers(0, 255, (48, 64, 3), dtype=np.uint8)
    out = oiio.ImageOutput.create(str(path))
    spec = oiio.ImageSpec(64, 48, 3, "uint8")
    spec.attribute("Make", "Bench Maker")
    assert out.open(str(path), spec) and out.write_image(px)
    out.close()
    return path


def test_a_distinct_copy_has_the_pixels_and_tags_and_other_bytes(tmp_path):
    from benchmarks.scaling import distinct_copy, stage_copies
    from benchmarks.throughput import Photo
    from vigproc.io.images import read_encoded

    src = _jpeg(tmp_path / "a.jpg")
    copy = distinct_copy(src, tmp_path / "b.jpg", 3)
    assert hashlib.sha256(copy.read_bytes()).digest() != hashlib.sha256(src.read_bytes()).digest()
    assert np.array_equal(read_encoded(copy)[0].codes, read_encoded(src)[0].codes)
    tags = [subprocess.run([exiftool_path(), "-s3", "-Make", "-Comment", str(p)], capture_output=True,
                           text=True).stdout.split("\n") for p in (src, copy)]
    assert tags[0][0] == tags[1][0] == "Bench Maker" and tags[1][1] == "vigproc bench copy 3"
    staged = stage_copies([Photo(src, 64, 48)], tmp_path / "s", 3)
    assert len(staged) == 3 and len({hashlib.sha256(p.read_bytes()).digest() for p in staged}) == 3


def test_a_file_that_is_not_a_jpeg_is_refused(tmp_path):
    from benchmarks.scaling import distinct_copy

    (tmp_path / "x.jpg").write_bytes(b"GIF89a")
    with pytest.raises(VigprocError):
        distinct_copy(tmp_path / "x.jpg", tmp_path / "y.jpg", 1)


def test_a_process_trees_cpu_counts_its_grandchildren(tmp_path):
    """The daemon's CPU is its workers' and their exiftool's too: a grandchild that
    burns 0.3 s of CPU is counted, a process outside the tree is not."""
    import sys
    import time

    from benchmarks.scaling import tree_cpu_seconds

    burn = "import time\nt = time.process_time()\nwhile time.process_time() - t < 0.3: pass\ntime.sleep(30)"
    parent = subprocess.Popen([sys.executable, "-c", f"import subprocess, sys, time\n"
                               f"subprocess.Popen([sys.executable, '-c', {burn!r}])\ntime.sleep(30)"])
    outside = subprocess.Popen([sys.executable, "-c", burn.replace("0.3", "2.0")])
    try:
        deadline = time.time() + 30
        while (tree_cpu_seconds(parent.pid) < 0.3 or tree_cpu_seconds(outside.pid) < 2.0) and time.time() < deadline:
            time.sleep(0.1)
        got = tree_cpu_seconds(parent.pid)
        # the grandchild's 0.3 s and two interpreters' start-up, not the outsider's 2 s
        assert 0.3 <= got < 0.3 + 1.5
        assert tree_cpu_seconds(outside.pid) >= 2.0
    finally:
        for p in (parent, outside):
            p.kill()
            p.wait()


def test_the_table_bounds_n_workers_by_one_workers_cores():
    from benchmarks.scaling import Rounds, ScalingResult, format_result

    runs = [Rounds("watch", 1, wall=[10.0], steady=[1.0], cores=[1.25]),
            Rounds("watch", 2, wall=[6.5], steady=[1.6], cores=[1.9])]
    lines = format_result(ScalingResult(10, 100.0, 1, 2, (0.1, 0.1, 0.1), (0.2, 0.2, 0.2), runs))
    assert "cores busy" in lines[1] and "at most" in lines[1]
    one, two = lines[2].split(), lines[3].split()
    assert one[-2:] == ["1.25", "1.00"]
    assert two[-2:] == ["1.90", "1.60"]  # 2 cores / 1.25 cores of one worker
