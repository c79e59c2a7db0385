"""One suffix table: what read_image reads is what the folder scans (batch, watch) pick up,
and what the hook accepts as an output file is what write_image writes."""

from __future__ import annotations

import numpy as np
import pytest

from vigproc.frontends.batch import collect_dir
from vigproc.frontends.commands.hook import _output_suffixes
from vigproc.frontends.daemon.config import is_candidate_name
from vigproc.io import image_read, images
from vigproc.io.formats import IMAGE_SUFFIXES, RAW_SUFFIXES, READ_SUFFIXES, WRITE_EXT_FORMAT, WRITE_SUFFIXES, suffix_kind
from vigproc.pipeline.processor import OUTPUT_FORMATS

#: Suffixes that read_image read but the scans used to skip.
ONCE_SKIPPED = (".nrw", ".crw", ".3fr")
#: Suffixes vigproc does not read.
NOT_IMAGES = (".gif", ".bmp", ".txt", ".xmp", ".json", ".heic", "")


def _reads(path, monkeypatch) -> str:
    """Which reader read_image uses for ``path``: ``raw`` (LibRaw, stubbed: no RAW file
    of every make is at hand) or the format OpenImageIO read."""
    def fake_raw(*args, **kwargs):
        return np.zeros((2, 2, 3), np.float32), "raw"

    monkeypatch.setattr(image_read, "_read_raw", fake_raw)  # where read_image looks it up
    _, info = images.read_image(path)
    return "raw" if info == "raw" else info.format


@pytest.fixture()
def every_suffix(tmp_path):
    """A folder with a file of each suffix read_image reads (real images for the
    OpenImageIO kinds, junk for RAW), in both cases, and files it does not read."""
    img = np.linspace(0.1, 0.9, 8 * 8 * 3, dtype=np.float32).reshape(8, 8, 3)
    names = []
    for i, suffix in enumerate(sorted(IMAGE_SUFFIXES | {s.upper() for s in IMAGE_SUFFIXES})):
        p = tmp_path / f"f{i}{suffix}"
        if suffix.lower() in RAW_SUFFIXES:
            p.write_bytes(b"\0" * 64)
        elif suffix.lower() == ".exr":
            images.write_image(p, img)
        else:
            images.write_image(p, img, bit_depth="uint8", transfer="srgb")
        names.append(p.name)
    for i, suffix in enumerate(NOT_IMAGES):
        (tmp_path / f"n{i}{suffix}").write_bytes(b"\0" * 64)
    return tmp_path, names


def test_read_image_reads_every_scanned_suffix(every_suffix, monkeypatch):
    folder, names = every_suffix
    for name in names:
        kind = suffix_kind("." + name.rsplit(".", 1)[1])
        assert _reads(folder / name, monkeypatch) == kind, name
    assert set(ONCE_SKIPPED) <= IMAGE_SUFFIXES


def test_batch_scan_takes_exactly_the_readable_suffixes(every_suffix):
    folder, names = every_suffix
    assert sorted(item.rel for item in collect_dir(folder)) == sorted(names)


def test_watch_takes_exactly_the_readable_suffixes(every_suffix):
    folder, names = every_suffix
    assert sorted(p.name for p in folder.iterdir() if is_candidate_name(p.name)) == sorted(names)
    for suffix in ONCE_SKIPPED:
        assert is_candidate_name("x" + suffix) and is_candidate_name("x" + suffix.upper())


def test_hook_output_suffixes_are_the_writers(tmp_path):
    img = np.full((4, 4, 3), 0.5, np.float32)
    assert set(_output_suffixes("auto")) == set(WRITE_EXT_FORMAT)
    for name, fixed in OUTPUT_FORMATS.items():
        if fixed is None or fixed.format == "dng":
            continue
        assert set(_output_suffixes(name)) == set(WRITE_SUFFIXES[fixed.format]), name
        for suffix in _output_suffixes(name):  # each is one write_image writes as that format
            p = tmp_path / f"{name}{suffix}"
            images.write_image(p, img, format=fixed.format, bit_depth=fixed.depth, transfer=fixed.transfer)
            assert images.read_image(p)[1].format == fixed.format
    assert _output_suffixes("dng") == (".dng",)


def test_jpe_is_a_jpeg_suffix_everywhere(tmp_path):
    """``.jpe`` (a JPEG suffix cameras and OSes use) is read, scanned and checked for an
    in-camera correction alike: io/incamera takes its JPEG suffixes from the one table."""
    from vigproc.io.incamera import JPEG_SUFFIXES
    from vigproc.pipeline.processor import images_in

    assert JPEG_SUFFIXES == set(READ_SUFFIXES["jpeg"]) and ".jpe" in JPEG_SUFFIXES
    p = tmp_path / "IMG_1.jpe"
    images.write_image(p, np.full((8, 8, 3), 0.5, np.float32), transfer="srgb", bit_depth="uint8")
    assert images.read_image(p)[1].format == "jpeg"
    assert images_in(tmp_path) == [p] and is_candidate_name(p.name)
