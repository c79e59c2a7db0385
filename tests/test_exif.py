"""Tests for vigproc.io.exif: lens keys from EXIF through one persistent ExifTool process.

Test images are written here with OpenImageIO and tagged with the ``exiftool``
*program* (list arguments, no shell), not with the module under test, so a
reader bug cannot hide behind a matching writer bug.  Files that must be told
apart carry distinct lens serial numbers: a misread (another file's metadata)
shows up as a wrong serial.
"""

from __future__ import annotations

import csv
import json
import logging
import math
import os
import re
import shutil
import subprocess
from pathlib import Path

import numpy as np
import OpenImageIO as oiio
import pytest

import exiftool.exiftool as et_module
from benchmarks.io import bench_exif
from vigproc.io import exif as vexif
from vigproc.io import lenskey
from vigproc.errors import ImageReadError, UnsupportedFormatError, VigprocError
from vigproc.io.exif import (
    ExifReader,
    FileNameError,
    LensKey,
    MetadataError,
    lens_key_from_metadata,
    normalise_text,
    read_lens_key,
)

pytestmark = pytest.mark.skipif(shutil.which("exiftool") is None, reason="exiftool program not installed")

CONTROL = re.compile(r"[\x00-\x1f\x7f-\x9f\u2028\u2029\u202a-\u202e\u200b-\u200f]")


# --------------------------------------------------------------------------- #
# helpers
# --------------------------------------------------------------------------- #


def write_image(path: Path) -> Path:
    """A 16x16 RGB image (format from the extension) written by OpenImageIO."""
    arr = np.linspace(0, 255, 16 * 16 * 3).reshape(16, 16, 3).astype(np.uint8)
    out = oiio.ImageOutput.create(str(path))
    assert out is not None, oiio.geterror()
    assert out.open(str(path), oiio.ImageSpec(16, 16, 3, "uint8")), out.geterror()
    assert out.write_image(arr), out.geterror()
    assert out.close()
    return path


def tag(path: Path, *assignments: str | bytes) -> Path:
    """Set tags with the exiftool program (argv list: no shell, no argfile)."""
    cmd: list[str | bytes] = ["exiftool", "-q", "-m", "-overwrite_original", *assignments, str(path)]
    proc = subprocess.run(cmd, capture_output=True)
    assert proc.returncode == 0, proc.stderr
    return path


def tag_many(jobs: list[tuple[Path, list[str]]]) -> None:
    """Tag several files with different values in ONE exiftool run (-execute)."""
    cmd = ["exiftool", "-q", "-m", "-overwrite_original"]
    for i, (path, assignments) in enumerate(jobs):
        if i:
            cmd.append("-execute")
        cmd += [*assignments, str(path)]
    proc = subprocess.run(cmd, capture_output=True)
    assert proc.returncode == 0, proc.stderr


CAMERA = ["-Make=Canon", "-Model=Canon EOS 5D Mark II", "-FocalLength=50", "-FNumber=8"]


@pytest.fixture(scope="module")
def template(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A tagged JPEG (camera + lens) to copy from."""
    d = tmp_path_factory.mktemp("template")
    path = write_image(d / "template.jpg")
    return tag(path, *CAMERA, "-LensModel=EF24-105mm f/4L IS USM")


@pytest.fixture(scope="module")
def reader() -> ExifReader:
    with ExifReader() as r:
        yield r


def with_serial(template: Path, dest: Path, serial: str) -> Path:
    """Copy ``template`` under a plain name, tag a distinct serial, then rename to ``dest``."""
    return with_serials(template, [(dest, serial)])[0]


def with_serials(template: Path, files: list[tuple[Path, str]]) -> list[Path]:
    """:func:`with_serial` for several (dest, serial) pairs, tagged in one exiftool run
    (an exiftool start costs about 0.3 CPU s)."""
    staged = [(dest.parent / f"_staging_{serial}.jpg", dest) for dest, serial in files]
    for tmp, _ in staged:
        shutil.copyfile(template, tmp)
    tag_many([(tmp, [f"-LensSerialNumber={serial}"]) for (tmp, _), (_, serial) in zip(staged, files)])
    for tmp, dest in staged:
        os.replace(tmp, dest)
    return [dest for _, dest in staged]


def no_control(s: str) -> bool:
    return CONTROL.search(s) is None


# --------------------------------------------------------------------------- #
# full / degraded keys from real files
# --------------------------------------------------------------------------- #


@pytest.mark.parametrize("ext", ["jpg", "tif"])
def test_full_key(tmp_path: Path, reader: ExifReader, ext: str) -> None:
    path = write_image(tmp_path / f"full.{ext}")
    tag(path, *CAMERA, "-LensModel=EF24-105mm f/4L IS USM", "-LensSerialNumber=0000123456",
        "-SubjectDistance=3.5", "-FocalLengthIn35mmFormat=50")
    key = reader.read(path)
    assert key.lens_id() == "canon|canon eos 5d mark ii|ef24-105mm f/4l is usm"
    assert key.make == "canon" and key.model == "canon eos 5d mark ii"
    assert key.lens_serial == "0000123456"
    assert key.focal_mm == 50 and key.fnumber == 8 and key.focus_distance_m == 3.5
    assert key.focal_35mm == 50
    assert key.missing == () and key.lens_candidates == () and not key.ambiguous
    assert (key.width, key.height) == (16, 16)
    assert key.source == str(path)
    assert key.lens_id(with_serial=True).endswith("|sn:0000123456")
    assert key.key_string() == "canon|canon eos 5d mark ii|ef24-105mm f/4l is usm|sn:0000123456|f:50|n:8|d:3.5"


def test_lens_fallback_to_xmp_aux_lens(tmp_path: Path, reader: ExifReader) -> None:
    # No EXIF:LensModel: the XMP-aux:Lens name (ExifTool also derives its LensID from it).
    path = tag(write_image(tmp_path / "xmp.jpg"), *CAMERA, "-XMP-aux:Lens=EF 70-200mm f/2.8L IS II USM")
    key = reader.read(path)
    assert key.lens == "ef 70-200mm f/2.8l is ii usm"
    assert key.lens_source in ("Composite:LensID", "XMP:Lens")
    # Without any Composite value the fallback itself is used.
    key = lens_key_from_metadata({"EXIF:Make": "Canon", "XMP:Lens": "EF 70-200mm f/2.8L IS II USM"})
    assert key.lens == "ef 70-200mm f/2.8l is ii usm" and key.lens_source == "XMP:Lens"


def test_missing_lens_degrades_explicitly(tmp_path: Path, reader: ExifReader) -> None:
    path = tag(write_image(tmp_path / "nolens.jpg"), *CAMERA)
    key = reader.read(path)
    assert key.lens is None
    assert key.missing == ("lens", "lens_serial", "focus_distance_m")
    assert key.lens_id() == "canon|canon eos 5d mark ii|?"
    assert key.key_string() == "canon|canon eos 5d mark ii|?|sn:?|f:50|n:8|d:?"


def test_placeholder_values_are_missing(tmp_path: Path, reader: ExifReader) -> None:
    path = tag(write_image(tmp_path / "placeholders.jpg"), "-Make=Canon", "-Model=----",
               "-LensModel=Unknown", "-LensSerialNumber=0000000000")
    key = reader.read(path)
    assert key.make == "canon"
    assert key.model is None and key.lens is None and key.lens_serial is None
    assert {"model", "lens", "lens_serial", "focal_mm", "fnumber"} <= set(key.missing)


def test_no_exif_at_all_is_a_typed_error(tmp_path: Path, reader: ExifReader) -> None:
    path = write_image(tmp_path / "bare.jpg")
    with pytest.raises(MetadataError, match=r"bare\.jpg.*no camera make, model or lens"):
        reader.read(path)


def test_contradictory_numbers_become_missing_with_warning(
    tmp_path: Path, reader: ExifReader, caplog: pytest.LogCaptureFixture
) -> None:
    path = tag(write_image(tmp_path / "contra.jpg"), "-Make=Canon", "-Model=Canon EOS 5D",
               "-FocalLength=0", "-FNumber=2.8", "-XMP-exif:FNumber=11")
    with caplog.at_level(logging.WARNING, logger="vigproc.io.exif"):
        key = reader.read(path)
    assert key.focal_mm is None and key.fnumber is None
    assert "focal_mm" in key.missing and "fnumber" in key.missing
    # FocalLength=0 is how cameras write "unknown" (manual lenses, DNGs): missing, no warning
    assert not any("focal_mm" in p for p in key.problems)
    assert any("contradictory" in p and "fnumber" in p for p in key.problems)
    logged = " ".join(r.getMessage() for r in caplog.records)
    assert "contra.jpg" in logged and "contradictory" in logged and "focal_mm" not in logged
    # Demanding the field turns the degradation into a typed error naming the cause.
    with ExifReader(require=("focal_mm", "fnumber")) as strict:
        res = strict.read_many([path])[0]
    assert isinstance(res, MetadataError)
    assert "contra.jpg" in str(res) and "focal_mm" in str(res) and "contradictory" in str(res)


def test_absurd_fnumber_rejected(tmp_path: Path, reader: ExifReader) -> None:
    path = tag(write_image(tmp_path / "absurd.jpg"), "-Make=Canon", "-FNumber=5000", "-FocalLength=20000")
    key = reader.read(path)
    assert key.fnumber is None and key.focal_mm is None
    assert len(key.problems) == 2


# --------------------------------------------------------------------------- #
# hostile strings
# --------------------------------------------------------------------------- #


def test_hostile_strings_in_tags(tmp_path: Path, reader: ExifReader, caplog: pytest.LogCaptureFixture) -> None:
    path = write_image(tmp_path / "hostile.jpg")
    tag(path,
        b"-Make=Can\x01on\x1b[31m\xff\xfe Inc|x?",  # control chars, invalid UTF-8, key separators
        "-Model=\u202eEOS\u200b  \t5D\r\nMark II",  # bidi override, zero-width, line breaks
        "-LensModel=" + "X" * 5000,  # absurd length
        "-LensSerialNumber=ab\"c'd",  # quotes
        "-FocalLength=35", "-FNumber=2")
    with caplog.at_level(logging.WARNING, logger="vigproc.io.exif"):
        key = reader.read(path)
    assert key.model == "eos 5d mark ii"
    assert key.make is not None and key.make.startswith("can on") and "|" in key.make
    assert key.lens is None and any("implausibly long" in p for p in key.problems)
    assert "implausibly long" in caplog.text
    assert key.lens_serial == "ab\"c'd"
    s = key.key_string()
    assert no_control(s)
    # '|' and '?' inside values are escaped: still exactly 3 components in lens_id.
    assert len(key.lens_id().split("|")) == 3
    assert "%7C" in key.lens_id() and "%3F" in key.lens_id()


@pytest.mark.parametrize(
    "raw, expected",
    [
        ("Canon", "canon"),
        ("  NIKON   CORPORATION ", "nikon corporation"),
        ("ＣＡＮＯＮ", "canon"),  # full-width -> NFKC
        ("Canon\x00\x00", "canon"),
        ("EOS\u200b5D", "eos5d"),  # zero-width removed
        ("a\u202eb", "ab"),  # bidi override removed
        ("a\nb\tc", "a b c"),
        ("Straße", "strasse"),
        ("Unknown", None), ("unknown", None), ("----", None), ("0", None), ("N/A", None),
        ("", None), ("   ", None), ("?", None), ("()", None),
        ("(Binary data 1234 bytes, use -b option to extract)", None),
        ("x" * 200, "x" * 200), ("x" * 201, None), ("x" * 100000, None),
        (None, None), (True, None), ({"a": 1}, None), ([None, "Sony"], "sony"), (3000, "3000"),
    ],
)
def test_normalise_text(raw: object, expected: str | None) -> None:
    assert normalise_text(raw) == expected


def test_make_prefix_duplicated_in_model() -> None:
    key = lens_key_from_metadata({"EXIF:Make": "Canon", "EXIF:Model": "Canon Canon EOS 10D"})
    assert key.model == "canon eos 10d"
    key = lens_key_from_metadata({"EXIF:Make": "NIKON CORPORATION", "EXIF:Model": "NIKON CORPORATION NIKON D70"})
    assert key.model == "nikon d70"
    # A model that merely starts with the make is left alone.
    assert lens_key_from_metadata({"EXIF:Make": "Canon", "EXIF:Model": "Canon EOS 10D"}).model == "canon eos 10d"
    assert lens_key_from_metadata({"EXIF:Make": "Jolla", "EXIF:Model": "Jolla"}).model == "jolla"


def test_contradictory_make_between_sources() -> None:
    key = lens_key_from_metadata({"EXIF:Make": "Canon", "MakerNotes:Make": "Nikon", "EXIF:Model": "X100"},
                                 source="f.jpg")
    assert key.make is None and "make" in key.missing
    assert any("contradictory" in p for p in key.problems)
    # A longer form of the same make is not a contradiction.
    key = lens_key_from_metadata({"EXIF:Make": "NIKON", "XMP:Make": "NIKON CORPORATION"})
    assert key.make == "nikon"


# --------------------------------------------------------------------------- #
# lens choice, ambiguous LensIDs (parsing unit tests)
# --------------------------------------------------------------------------- #

BODY = {"EXIF:Make": "Canon", "EXIF:Model": "Canon EOS 5D"}


def test_ambiguous_lens_id_without_tiebreak() -> None:
    key = lens_key_from_metadata({**BODY, "Composite:LensID": "Canon EF 17-40mm f/4L USM or Sigma 17-40mm f/4 EX"})
    # on a Canon, "canon ef ..." is keyed "ef ..." (the camera's brand is dropped)
    assert key.lens_candidates == ("ef 17-40mm f/4l usm", "sigma 17-40mm f/4 ex")
    assert key.lens == "ef 17-40mm f/4l usm or sigma 17-40mm f/4 ex"
    assert key.ambiguous
    assert any("ambiguous" in p for p in key.problems)
    # Order of alternatives does not change the key.
    swapped = lens_key_from_metadata({**BODY, "Composite:LensID": "Sigma 17-40mm f/4 EX or Canon EF 17-40mm f/4L USM"})
    assert swapped == key and swapped.lens_id() == key.lens_id()


def test_ambiguous_lens_id_resolved_by_lens_model() -> None:
    meta = {**BODY, "Composite:LensID": "Sigma 17-40mm f/4 EX or Canon EF 17-40mm f/4L USM",
            "EXIF:LensModel": "EF17-40mm f/4L USM"}
    key = lens_key_from_metadata(meta)
    assert key.lens == "ef 17-40mm f/4l usm"
    assert key.lens_candidates == ("ef 17-40mm f/4l usm", "sigma 17-40mm f/4 ex")
    assert not key.ambiguous
    assert key.lens_id() == "canon|canon eos 5d|ef 17-40mm f/4l usm"
    assert key.legacy_ids == ("canon|canon eos 5d|canon ef 17-40mm f/4l usm",)


def test_three_way_ambiguity_keeps_nameless_alternatives() -> None:
    meta = {**BODY, "Composite:LensID": "Sony 70-300mm F4.5-5.6 G SSM (SAL70300G) or G SSM II or Tamron Lens"}
    key = lens_key_from_metadata(meta)
    assert len(key.lens_candidates) == 3 and key.ambiguous


@pytest.mark.parametrize("lens_id, described", [
    ("65535", None), ("7A 02 3C 8E 24 24 02 02", None), ("Unknown 50mm", "50mm"), ("Unknown ( )", None),
    ("50.0 mm", "50mm"), ("50.0mm f/1.8", "50mm f/1.8"), ("n/a", None), ("", None)])
def test_unresolved_lens_ids_fall_back(lens_id: str, described: str | None) -> None:
    key = lens_key_from_metadata({**BODY, "Composite:LensID": lens_id, "EXIF:LensModel": "EF50mm f/1.8 II"})
    assert key.lens == "ef50mm f/1.8 ii" and key.lens_source == "EXIF:LensModel"
    # nothing names the lens: a description is its key (with the camera), else it is missing
    key = lens_key_from_metadata({**BODY, "Composite:LensID": lens_id, "MakerNotes:LensType": "G"})
    assert key.lens == described
    assert ("lens" in key.missing) == (described is None)


def test_numbers_from_metadata_dict() -> None:
    meta = {**BODY, "EXIF:FocalLength": 18, "MakerNotes:FocalLength": 18.34, "EXIF:FNumber": 3.5,
            "MakerNotes:FNumber": 3.56, "MakerNotes:FocusDistanceUpper": 1.42,
            "MakerNotes:FocusDistanceLower": 1.19}
    key = lens_key_from_metadata(meta)
    assert key.focal_mm == 18 and key.fnumber == 3.5
    assert key.focus_distance_m == pytest.approx(1.305)
    # Canon encodes infinity as 655.35 m.
    assert lens_key_from_metadata({**BODY, "MakerNotes:FocusDistanceUpper": 655.35}).focus_distance_m == math.inf
    # Lower bound above the upper one: contradiction.
    bad = lens_key_from_metadata({**BODY, "MakerNotes:FocusDistanceUpper": 1, "MakerNotes:FocusDistanceLower": 3})
    assert bad.focus_distance_m is None and bad.problems
    # Maker-note focal length 2x EXIF's: contradiction, not a silent pick.
    bad = lens_key_from_metadata({**BODY, "EXIF:FocalLength": 50, "MakerNotes:FocalLength": 100})
    assert bad.focal_mm is None and "contradictory" in bad.problems[0]
    # ApertureValue is only a fallback (Ricoh RR330 writes f/2.88 next to APEX 4).
    key = lens_key_from_metadata({**BODY, "EXIF:FNumber": 2.88, "EXIF:ApertureValue": 4})
    assert key.fnumber == 2.88
    assert lens_key_from_metadata({**BODY, "EXIF:ApertureValue": 4}).fnumber == 4
    # A bad primary is not replaced by a fallback (Magic Lantern: FNumber 0, ApertureValue 1).
    key = lens_key_from_metadata({**BODY, "EXIF:FNumber": 0, "EXIF:ApertureValue": 1})
    assert key.fnumber is None and "fnumber" in key.missing
    # Hostile types.
    key = lens_key_from_metadata({**BODY, "EXIF:FocalLength": "NaN", "EXIF:FNumber": [True],
                                  "EXIF:SubjectDistance": {"x": 1}, "Composite:ImageSize": "9" * 50})
    assert key.focal_mm is None and key.fnumber is None and key.focus_distance_m is None
    assert key.width is None


# --------------------------------------------------------------------------- #
# file names
# --------------------------------------------------------------------------- #

HARD_NAMES = [
    "with space.jpg",
    "quote'single.jpg",
    'quote"double.jpg',
    "é日本😀 μ.jpg",
    "new\nline.jpg",
    "carriage\rreturn.jpg",
    "endcr.jpg\r",
    "tab\tname.jpg",
    " leading space.jpg",
    "trailing space.jpg ",
    "-starts-with-dash.jpg",
    "#hash.jpg",
    "-execute",
    "$dollar @at.jpg",
    "back\\slash.jpg",
    "ctl\x01\x1bchar.jpg",
    "star*?.jpg",
    "%d%f.jpg",
    "line\u2028separator.jpg",
    "{ready}.jpg",
]


def test_hard_file_names_read_their_own_file(tmp_path: Path, template: Path) -> None:
    paths = with_serials(template, [(tmp_path / name, f"SN{i:03d}") for i, name in enumerate(HARD_NAMES)])
    with ExifReader() as r:
        results = r.read_many(paths)
        assert r.launches == 1
    for i, (path, res) in enumerate(zip(paths, results)):
        assert isinstance(res, LensKey), (path, res)
        assert res.lens_serial == f"sn{i:03d}", path  # its own metadata, not a neighbour's
        assert res.source == str(path)


def test_relative_names_with_leading_dash(tmp_path: Path, template: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    with_serials(template, [(tmp_path / "-n", "DASH"), (tmp_path / " sp", "SPACE")])
    monkeypatch.chdir(tmp_path)
    with ExifReader() as r:
        a, b = r.read_many(["-n", " sp"])
    assert a.lens_serial == "dash" and b.lens_serial == "space"


def test_newline_name_not_confused_with_decoys(tmp_path: Path, template: Path) -> None:
    # "a\nb.jpg" split at the newline would be the two files "a" and "b.jpg".
    *_, target = with_serials(template, [(tmp_path / "a", "DECOYA"), (tmp_path / "b.jpg", "DECOYB"),
                                         (tmp_path / "a\nb.jpg", "TARGET")])
    with ExifReader() as r:
        res = r.read_many([target, tmp_path / "b.jpg"])
    assert [k.lens_serial for k in res] == ["target", "decoyb"]


def test_newline_with_dollar_is_a_clear_error(tmp_path: Path, template: Path) -> None:
    path = with_serial(template, tmp_path / "bad$\nname.jpg", "X")
    with ExifReader() as r:
        res = r.read_many([path])[0]
        assert r.launches == 1
    assert isinstance(res, FileNameError)
    msg = str(res)
    assert "\n" not in msg and repr(str(path)) in msg and "line break" in msg
    assert res.path == str(path)


def test_non_utf8_file_name(tmp_path: Path, template: Path) -> None:
    raw = os.fsencode(tmp_path) + b"/bad\xff\xfe name.jpg"
    try:
        with_serial(template, Path(os.fsdecode(raw)), "LATIN")
    except (OSError, UnicodeError):  # pragma: no cover - file system refuses the name
        pytest.skip("file system does not accept non-UTF-8 names")
    with_serial(template, tmp_path / "bad?? name.jpg", "DECOY")  # what ExifTool would print
    with ExifReader() as r:
        res = r.read_many([raw, os.fsdecode(raw), tmp_path / "bad?? name.jpg"])
    assert [k.lens_serial for k in res] == ["latin", "latin", "decoy"]


# --------------------------------------------------------------------------- #
# bad files
# --------------------------------------------------------------------------- #


def test_bad_files_give_typed_errors_naming_the_file(tmp_path: Path, reader: ExifReader) -> None:
    text = tmp_path / "notes .jpg"
    text.write_text("just some text, not an image\n")
    zero = tmp_path / "zero 'byte'.jpg"
    zero.write_bytes(b"")
    junk = tmp_path / "junk.jpg"
    junk.write_bytes(bytes(range(256)) * 4)
    missing = tmp_path / "no such é.jpg"
    cases = [
        (text, UnsupportedFormatError, "not an image"),
        (zero, ImageReadError, "empty"),
        (junk, UnsupportedFormatError, "exiftool"),
        (missing, ImageReadError, "file not found"),
        (tmp_path, ImageReadError, "directory"),
    ]
    results = reader.read_many([c[0] for c in cases])
    for (path, cls, cause), res in zip(cases, results):
        assert isinstance(res, cls), (path, res)
        assert repr(str(path)) in str(res) and cause in str(res)
        assert res.path == str(path) and cause in res.cause
        with pytest.raises(cls, match=re.escape(cause)):
            reader.read(path)


def test_exiftool_error_for_a_vanished_file_names_it(tmp_path: Path, reader: ExifReader) -> None:
    # Bypass the pre-check: ExifTool's own "File not found" must map to this file.
    gone = str(tmp_path / "gone.jpg")
    res = reader._run_jobs([vexif._Job(gone, gone, gone)])[0]
    assert isinstance(res, ImageReadError)
    assert "gone.jpg" in str(res) and "File not found" in str(res)


def test_fifo_is_not_handed_to_exiftool(tmp_path: Path, reader: ExifReader) -> None:
    fifo = tmp_path / "pipe.jpg"
    os.mkfifo(fifo)
    res = reader.read_many([fifo])[0]
    assert isinstance(res, ImageReadError) and "not a regular file" in str(res)


# --------------------------------------------------------------------------- #
# batches: one process, failures isolated
# --------------------------------------------------------------------------- #


def test_batch_uses_one_process_and_continues_past_bad_files(
    tmp_path: Path, template: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    paths: list[Path] = []
    jobs = []
    for i in range(20):
        p = tmp_path / f"img {i:02d}.jpg"
        shutil.copyfile(template, p)
        jobs.append((p, [f"-LensSerialNumber=B{i:02d}", f"-FocalLength={10 + i}"]))
        paths.append(p)
    tag_many(jobs)
    bad_text = tmp_path / "bad.jpg"
    bad_text.write_text("not an image")
    batch: list[Path] = paths[:7] + [bad_text, tmp_path / "missing.jpg"] + paths[7:]

    launches = []
    real_popen = et_module.subprocess.Popen

    def counting_popen(*args, **kwargs):
        launches.append(args[0] if args else kwargs.get("args"))
        return real_popen(*args, **kwargs)

    monkeypatch.setattr(et_module.subprocess, "Popen", counting_popen)
    with ExifReader() as r:
        pid = r.pid
        results = r.read_many(batch)
        again = r.read_many(batch[:3])
        assert r.pid == pid and r.launches == 1
    assert len(launches) == 1, launches  # one exiftool process for everything

    assert len(results) == len(batch)
    assert isinstance(results[7], UnsupportedFormatError) and "bad.jpg" in str(results[7])
    assert isinstance(results[8], ImageReadError) and "missing.jpg" in str(results[8])
    good = [k for k in results if isinstance(k, LensKey)]
    assert [k.lens_serial for k in good] == [f"b{i:02d}" for i in range(20)]
    assert [k.focal_mm for k in good] == [10 + i for i in range(20)]
    assert [k.source for k in good] == [str(p) for p in paths]
    assert again == results[:3]

    # Contrast: the one-shot helper really starts a process per call.
    for p in paths[:3]:
        read_lens_key(p)
    assert len(launches) == 4


def test_duplicates_in_a_batch(tmp_path: Path, template: Path, reader: ExifReader) -> None:
    p = with_serial(template, tmp_path / "dup.jpg", "DUP")
    res = reader.read_many([p, p, str(p)])
    assert all(isinstance(k, LensKey) and k.lens_serial == "dup" for k in res)


def test_chunking_keeps_order(tmp_path: Path, template: Path) -> None:
    paths = with_serials(template, [(tmp_path / f"c{i}.jpg", f"C{i}") for i in range(5)])
    with ExifReader(chunk_size=2) as r:
        res = r.read_many(paths)
        assert r.launches == 1
    assert [k.lens_serial for k in res] == [f"c{i}" for i in range(5)]


def test_reader_survives_a_dead_exiftool(tmp_path: Path, template: Path) -> None:
    p = with_serial(template, tmp_path / "x.jpg", "ALIVE")
    with ExifReader() as r:
        assert r.read(p).lens_serial == "alive"
        os.kill(r.pid, 9)  # the process this reader started
        r._proc._et._process.wait()
        assert r.read(p).lens_serial == "alive"  # a new process, started on the way
        assert r.launches == 2


def test_reader_argument_validation() -> None:
    with pytest.raises(ValueError):
        ExifReader(require=("nonsense",))
    with pytest.raises(ValueError):
        ExifReader(chunk_size=0)


# --------------------------------------------------------------------------- #
# determinism and (de)serialisation
# --------------------------------------------------------------------------- #


def test_same_file_twice_same_key(tmp_path: Path, template: Path, reader: ExifReader) -> None:
    a = with_serial(template, tmp_path / "one.jpg", "S1")
    b = tmp_path / "copy with another name é.jpg"
    shutil.copyfile(a, b)
    k1 = reader.read(a)
    with ExifReader() as other:
        k2 = other.read(a)
    k3 = read_lens_key(b)
    assert k1 == k2 == k3  # source is not compared
    assert k1.lens_id() == k2.lens_id() == k3.lens_id()
    assert k1.key_string() == k3.key_string()
    assert k1.to_dict() == k2.to_dict()


def test_dict_round_trip(tmp_path: Path, reader: ExifReader) -> None:
    key = lens_key_from_metadata({**BODY, "Composite:LensID": "A 10mm or B 10mm", "EXIF:FocalLength": 10,
                                  "EXIF:FNumber": 4, "MakerNotes:FocusDistanceUpper": 700,
                                  "EXIF:LensSerialNumber": "X1"}, source="s.jpg")
    d = json.loads(json.dumps(key.to_dict(), allow_nan=False))
    assert d["focus_distance_m"] == "inf"
    back = LensKey.from_dict(d)
    assert back == key and back.to_dict() == key.to_dict()
    assert back.lens_id() == key.lens_id()


@pytest.mark.parametrize(
    "change",
    [
        {"make": "Canon"},  # not normalised
        {"make": "can\x1bon"},
        {"lens": 5},
        {"focal_mm": -1},
        {"fnumber": float("nan")},
        {"focus_distance_m": "far"},
        {"missing": []},  # lies about missing fields
        {"evil": 1},
        {"lens_candidates": "a"},
    ],
)
def test_from_dict_rejects_bad_input(change: dict) -> None:
    good = lens_key_from_metadata({**BODY, "EXIF:FocalLength": 10}).to_dict()
    with pytest.raises(MetadataError):
        LensKey.from_dict({**good, **change})
    with pytest.raises(MetadataError):
        LensKey.from_dict(["not", "a", "dict"])  # type: ignore[arg-type]


def test_missing_is_derived() -> None:
    key = LensKey(make="canon", model=None, lens="x 50mm", missing=("nothing",))
    assert key.missing == ("model", "lens_serial", "focal_mm", "fnumber", "focus_distance_m")


def test_profile_key_bins() -> None:
    key = lens_key_from_metadata({**BODY, "EXIF:FocalLength": 33, "EXIF:FNumber": 5.0})
    assert key.profile_key([24, 35, 50, 70], [2.8, 4, 5.6, 8]) == "canon|canon eos 5d|?|f:35|n:5.6"
    nofocal = lens_key_from_metadata(BODY)
    assert nofocal.profile_key([24], [4]) == "canon|canon eos 5d|?|f:?|n:?"
    with pytest.raises(ValueError):
        key.profile_key([], [4])


# --------------------------------------------------------------------------- #
# shared data
# --------------------------------------------------------------------------- #


def _csv_rows(folder: Path) -> list[dict[str, str]]:
    with open(folder / "files.csv", newline="", encoding="utf-8") as fh:
        return list(csv.DictReader(fh))


def _num(text: str) -> float | None:
    m = re.match(r"^\s*([0-9.]+)", text or "")
    return float(m.group(1)) if m else None


@pytest.mark.parametrize("sub", ["jpeg_exif", "raw"])
def test_shared_data_agrees_with_files_csv(shared_data: Path, sub: str) -> None:
    folder = shared_data / sub
    if not (folder / "files.csv").is_file():
        pytest.skip(f"{folder}/files.csv absent")
    rows = _csv_rows(folder)
    paths = [folder / r["path"] for r in rows]
    everything = sorted(p for p in folder.rglob("*") if p.is_file())
    with ExifReader() as r:
        results = r.read_many(paths)
        all_results = r.read_many(everything)  # README, csv, .bin: typed errors, never exceptions
        assert r.launches == 1
    assert all(isinstance(x, (LensKey, VigprocError)) for x in all_results)

    checked = {"make": 0, "model": 0, "focal": 0, "fnumber": 0}
    for row, path, key in zip(rows, paths, results):
        name = row["path"]
        if not row["type"]:  # not an image according to the inventory
            assert isinstance(key, UnsupportedFormatError), (name, key)
            continue
        if not (row["make"] or row["model"]):
            assert isinstance(key, MetadataError), (name, key)
            assert name.split("/")[-1] in str(key)
            continue
        assert isinstance(key, LensKey), (name, key)
        assert no_control(key.key_string())
        if row["make"]:
            assert key.make == normalise_text(row["make"]), name
            checked["make"] += 1
        if row["model"]:
            assert key.model == normalise_text(row["model"]), name
            checked["model"] += 1
        focal = _num(row["focal"])
        if focal is not None:
            if focal == 0:  # tinydng: FocalLength 0 says "unknown": missing, no problem to warn about
                assert key.focal_mm is None and "focal_mm" in key.missing
                assert not any("focal_mm" in p for p in key.problems)
            else:
                assert key.focal_mm == pytest.approx(focal, abs=0.051), name
            checked["focal"] += 1
        fnum = _num(row["fnumber"])
        if fnum is not None:
            if fnum == 0:
                assert key.fnumber is None and "fnumber" in key.missing
                assert not any("fnumber" in p for p in key.problems)
            else:
                assert key.fnumber == pytest.approx(fnum, abs=0.051), name
            checked["fnumber"] += 1
        # A lens the inventory names (not an unresolved placeholder) must give a lens.
        csv_lens, _ = lenskey._lens_text(row["lens"])
        if csv_lens is not None:
            assert key.lens is not None, name
    if sub == "jpeg_exif":
        assert min(checked.values()) >= 80, checked
    else:
        assert min(checked.values()) >= 10, checked


def test_shared_data_keys_deterministic(shared_data: Path) -> None:
    folder = shared_data / "jpeg_exif"
    if not folder.is_dir():
        pytest.skip("jpeg_exif absent")
    paths = sorted(folder.rglob("*.[jJ][pP]*[gG]"))
    with ExifReader() as r:
        first = r.read_many(paths)
    with ExifReader(chunk_size=7) as r:
        second = r.read_many(reversed(paths))[::-1]
    ids1 = [k.key_string() if isinstance(k, LensKey) else type(k).__name__ for k in first]
    ids2 = [k.key_string() if isinstance(k, LensKey) else type(k).__name__ for k in second]
    assert ids1 == ids2
    assert all(no_control(s) for s in ids1)
    keys = [k for k in first if isinstance(k, LensKey)]
    assert len(keys) >= 80
    assert sum(k.lens is not None for k in keys) >= 12


def test_a_typed_lens_id_keeps_its_escapes() -> None:
    """``import-lensfun --lens-id`` takes the id ``vigproc estimate`` printed: casefolding
    it must not turn ``%7C`` into ``%7c``, or the profile is stored under another key."""
    lens_id = LensKey(make="sigma", model="vigproc sample", lens="105mm f1.4 dg hsm | art 018").lens_id()
    assert "%7C" in lens_id
    assert vexif.casefold_lens_id(lens_id) == lens_id
    assert vexif.casefold_lens_id(lens_id.upper()) == lens_id
    assert vexif.casefold_lens_id("A%7cB|C%25") == "a%7Cb|c%25"


def test_35mm_focal_length_only_when_a_scale_factor_is_known() -> None:
    """exiftool's Composite:FocalLength35efl falls back to scale 1 when it cannot tell the
    sensor: an iPhone 4's 3.85 mm must not become a 3.85-mm-equivalent ultra-wide (it
    would narrow the lens-family prior to the wrong lenses)."""
    phone = {**BODY, "EXIF:FocalLength": 3.85, "Composite:FocalLength35efl": 3.85}
    assert lens_key_from_metadata(phone).focal_35mm is None
    assert lens_key_from_metadata({**phone, "Composite:FocalLength35efl": 28.0}).focal_35mm == 28.0
    assert lens_key_from_metadata({**phone, "EXIF:FocalLengthIn35mmFormat": 29}).focal_35mm == 29.0
