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
