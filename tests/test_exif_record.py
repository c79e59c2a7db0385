"""Each input's metadata read once (issue 39): one exiftool command gives the lens key,
the in-camera flags, a raw file's maker calibration and a check's provenance
(vigproc.io.exif.FileTags), answering as the separate reads did."""

import shutil
import subprocess

import numpy as np
import pytest

from vigproc.errors import ImageReadError, VigprocError
from vigproc.io import incamera, makernotes, provenance
from vigproc.io.exif import RECORD_TAGS, ExifReader, FileTags
from vigproc.io.images import write_image
from vigproc.pipeline.processor import Processor, Settings

from conftest import photo_like

needs_exiftool = pytest.mark.skipif(shutil.which("exiftool") is None, reason="exiftool program not installed")

#: every tag group the pipeline reads besides the lens key
GROUPS = (provenance._EXIF_TAGS, provenance._XMP_TAGS, provenance._MAKERNOTE_TAGS, incamera.TAGS,
          makernotes.MAKERNOTE_TAGS)


def _jpeg(path, *args):
    write_image(path, np.repeat(photo_like(120, 180, seed=3)[..., None], 3, axis=2), transfer="srgb", quality=90)
    subprocess.run(["exiftool", "-q", "-overwrite_original", *args, str(path)], check=True)
    return path


class Counting(ExifReader):
    """An ExifReader counting the exiftool commands that read a file."""

    def __init__(self):
        super().__init__()
        self.commands = 0

    def _execute(self, args, tags=()):
        self.commands += 1
        return super()._execute(args, tags) if tags else super()._execute(args)


def test_every_tag_the_pipeline_reads_is_in_the_one_command():
    assert all(t in RECORD_TAGS for group in GROUPS for t in group)


@needs_exiftool
def test_the_record_answers_as_separate_reads_do(tmp_path):
    f = _jpeg(tmp_path / "a b.jpg", "-Make=NIKON CORPORATION", "-Model=NIKON D70", "-EXIF:LensModel=18-70mm",
              "-XMP:LensModel=AF-S 24-120mm", "-EXIF:DateTimeOriginal=2019:06:01 14:03:22",
              "-XMP:DateTimeOriginal=2020:01:01 00:00:00", "-EXIF:SerialNumber=0012345", "-XMP:SerialNumber=999",
              "-FocalLength=18", "-FNumber=4", "-ISO=200")
    with ExifReader() as reader:
        tags = reader.read_file(f)
        assert isinstance(tags, FileTags)
        for group in GROUPS:
            assert tags.read_tags(f, group) == reader.read_tags(f, group)
        assert tags.read_tags(f, ["EXIF:ISO"]) == reader.read_tags(f, ["EXIF:ISO"]) == {"EXIF:ISO": 200}  # asked
        assert tags.read(f) == reader.read(f)
        one, three = provenance.read_provenance(f, tags), provenance.read_provenance(f, reader)
        assert one == three
        assert len(one.conflicts) == 3  # the date, the lens and the serial disagree
        other = _jpeg(tmp_path / "b.jpg", "-Make=Apple", "-Model=iPhone 5s")
        assert tags.read(other).make == "apple"  # another file is read, not answered from the record
        assert incamera.read_in_camera(other, tags).evidence == "phone"


@needs_exiftool
def test_a_failed_read_is_kept_not_repeated(tmp_path):
    bad = tmp_path / "notes.jpg"
    bad.write_text("not an image")
    reader = Counting()
    try:
        tags = reader.read_file(bad)
        assert reader.commands == 1 and isinstance(tags.error, VigprocError)
        with pytest.raises(ImageReadError):
            tags.read(bad)
        with pytest.raises(ImageReadError):
            tags.read_tags(bad, incamera.TAGS)
        assert incamera.read_in_camera(bad, tags) is None
        assert provenance.read_provenance(bad, tags).unread
        assert reader.commands == 1
    finally:
        reader.close()


@needs_exiftool
@pytest.mark.parametrize("mode", ["correct", "check"])
def test_one_exiftool_read_per_file(tmp_path, mode):
    """main read a JPEG twice in correct (lens, in-camera flags), four times in check
    (lens and three for the provenance)."""
    f = _jpeg(tmp_path / "IMG_1.jpg", "-Make=Apple", "-Model=iPhone 5s", "-FocalLength=4.15", "-FNumber=2.2",
              "-XMP:DateTimeOriginal=2020:01:01 00:00:00")
    reader = Counting()
    try:
        with Processor(Settings(mode=mode, profile="estimate"), reader=reader) as proc:
            if mode == "correct":
                (tmp_path / "out").mkdir()
                res = proc.process_file(f, tmp_path / "out")
                assert res.extra.get("not_applied_rule") == "in-camera"  # the flags were read
            else:
                res = proc.process_unwritten(f)
                assert res.extra["provenance"]["captured"] == "2020:01:01 00:00:00"
            assert res.lens["lens_id"] and reader.commands == 1
    finally:
        reader.close()


def test_shared_files_answer_alike(shared_data):
    """Real maker notes (exiftool's test files, camera JPEGs): the one record and the
    separate reads agree on every group."""
    if shutil.which("exiftool") is None:
        pytest.skip("exiftool program not installed")
    files = sorted(p for d in ("raw/exiftool-stubs", "jpeg_exif/exiftool-stubs") for p in (shared_data / d).glob("*")
                   if p.is_file())
    if not files:
        pytest.skip("no exiftool test files in the shared data")
    with ExifReader() as reader:
        for f in files:
            tags = reader.read_file(f)
            if tags.error is not None:
                continue
            for group in GROUPS:
                assert tags.read_tags(f, group) == reader.read_tags(f, group), (f.name, group)
