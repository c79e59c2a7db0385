"""Issue 36: the right lens, or "unknown".

Fixtures are JPEGs whose EXIF is written here with the ``exiftool`` program (argv lists, no
shell); the Canon LensType/LensID disagreement needs a real Canon maker note, copied from
ExifTool's own test image in the shared data (skipped when absent).
"""

from __future__ import annotations

import json
import shutil
import subprocess
from pathlib import Path

import numpy as np
import OpenImageIO as oiio
import pytest

from vigproc.errors import ModelError
from vigproc.io.exif import ExifReader, LensKey, lens_key_from_metadata
from vigproc.io.lensident import display_lens_id, generic_description, lens_spec, strip_make_prefix

pytestmark = pytest.mark.skipif(shutil.which("exiftool") is None, reason="exiftool program not installed")

ROOT = Path(__file__).resolve().parents[1]


def write_jpeg(path: Path, w: int = 360, h: int = 240) -> Path:
    """A textured JPEG with a mild radial fall-off (enough signal for an estimate)."""
    rng = np.random.default_rng(7)
    y, x = np.mgrid[0:h, 0:w]
    r2 = ((x - w / 2) ** 2 + (y - h / 2) ** 2) / ((w / 2) ** 2 + (h / 2) ** 2)
    base = 0.55 + 0.25 * rng.random((h, w, 1)) + 0.1 * np.sin(x / 7.0)[..., None]
    arr = np.clip(255 * base * (1 - 0.35 * r2)[..., None], 0, 255).astype(np.uint8).repeat(3, axis=2)
    out = oiio.ImageOutput.create(str(path))
    assert out.open(str(path), oiio.ImageSpec(w, h, 3, "uint8")), out.geterror()
    assert out.write_image(arr) and out.close()
    return path


def tag(path: Path, *assignments: str) -> Path:
    proc = subprocess.run(["exiftool", "-q", "-m", "-overwrite_original", *assignments, str(path)],
                          capture_output=True)
    assert proc.returncode == 0, proc.stderr
    return path


def read(path: Path) -> LensKey:
    with ExifReader() as r:
        (key,) = r.read_many([path])
    assert isinstance(key, LensKey), key
    return key


@pytest.fixture(scope="module")
def frames(tmp_path_factory) -> dict[str, Path]:
    d = tmp_path_factory.mktemp("lenses")
    base = write_jpeg(d / "base.jpg")
    specs = {
        # a lens the shot cannot be from: 31 mm on a 70-200
        "out_of_range": ["-Make=Canon", "-Model=Canon EOS 5D Mark II", "-LensModel=EF70-200mm f/2.8L IS II USM",
                         "-FocalLength=31", "-FNumber=4"],
        "in_range": ["-Make=Canon", "-Model=Canon EOS 5D Mark II", "-LensModel=EF70-200mm f/2.8L IS II USM",
                     "-FocalLength=100", "-FNumber=4"],
        # wider open than the lens opens
        "too_open": ["-Make=Canon", "-Model=Canon EOS 5D Mark II", "-LensModel=EF70-200mm f/2.8L IS II USM",
                     "-FocalLength=100", "-FNumber=1.4"],
        # only a description of the lens
        "generic": ["-Make=NIKON CORPORATION", "-Model=NIKON D70", "-LensModel=18.0-55.0mm f/3.5-5.6",
                    "-FocalLength=35", "-FNumber=5.6"],
        # ExifTool's name of a Nikon lens (no brand) ...
        "nikon_plain": ["-Make=NIKON CORPORATION", "-Model=NIKON D70",
                        "-LensModel=AF-S DX Zoom-Nikkor 18-70mm f/3.5-4.5G IF-ED", "-FocalLength=18", "-FNumber=3.5"],
        # ... and exiv2's (darktable, digiKam): the brand first
        "nikon_prefixed": ["-Make=NIKON CORPORATION", "-Model=NIKON D70",
                           "-LensModel=Nikon AF-S DX Zoom-Nikkor 18-70mm f/3.5-4.5G IF-ED", "-FocalLength=18",
                           "-FNumber=3.5"],
        "sony_d": ["-Make=SONY", "-Model=DSLR-A200", "-LensModel=Minolta/Sony AF DT 18-70mm F3.5-5.6 (D)",
                   "-FocalLength=26", "-FNumber=5.6"],
    }
    out = {}
    for name, assignments in specs.items():
        p = d / f"{name}.jpg"
        shutil.copyfile(base, p)
        out[name] = tag(p, *assignments)
    return out


@pytest.fixture(scope="module")
def canon_251(tmp_path_factory) -> Path:
    """A Canon frame whose maker-note LensType (251) names a 70-200 while the camera reports
    a 16-35 mm lens: ExifTool's LensID says ``Unknown (251) 16-35mm``."""
    from conftest import SHARED

    stub = SHARED / "jpeg_exif" / "exiftool-stubs" / "Canon.jpg"
    if not stub.is_file():
        pytest.skip("ExifTool's Canon test image absent")
    p = write_jpeg(tmp_path_factory.mktemp("canon") / "crw_like.jpg")
    tag(p, "-tagsFromFile", str(stub), "-MakerNotes", "-Make", "-Model")
    tag(p, "-Canon:LensType#=251", "-Canon:MinFocalLength=16", "-Canon:MaxFocalLength=35", "-FocalLength=31",
        "-FNumber=4")
    got = subprocess.run(["exiftool", "-s3", "-Composite:LensID", "-MakerNotes:LensType", str(p)],
                         capture_output=True, text=True).stdout.splitlines()
    assert got[0].startswith("Unknown (251)") and "70-200" in got[1], got  # the disagreement, as ExifTool reads it
    return p


# ------------------------------------------------------------------ the rule
def test_lens_id_beats_a_disagreeing_lens_type(canon_251: Path) -> None:
    key = read(canon_251)
    assert key.lens == "16-35mm"  # keyed by ExifTool's description, never the 70-200
    assert key.lens_id() == "canon|canon eos digital rebel|16-35mm"
    assert "70-200" not in key.lens_id()
    assert key.lens_range == (16.0, 35.0) and key.lens_problem is None
    assert any("LensType" in p and "not the mounted lens" in p for p in key.problems)


def test_out_of_range_focal_length_is_a_lens_problem(frames) -> None:
    key = read(frames["out_of_range"])
    assert key.lens == "ef70-200mm f/2.8l is ii usm"
    assert key.lens_problem is not None and "31 mm" in key.lens_problem and "70-200 mm" in key.lens_problem
    assert read(frames["in_range"]).lens_problem is None
    too_open = read(frames["too_open"]).lens_problem
    assert too_open is not None and "f/1.4" in too_open


def test_reported_range_contradicting_the_name() -> None:
    meta = {"EXIF:Make": "Canon", "EXIF:Model": "Canon EOS 5D", "EXIF:LensModel": "EF70-200mm f/2.8L IS II USM",
            "MakerNotes:MinFocalLength": 16, "MakerNotes:MaxFocalLength": 35, "EXIF:FocalLength": 100}
    key = lens_key_from_metadata(meta)
    # the only name disagrees with the camera's range: not the lens, a description instead
    assert key.lens is None or "70-200" not in key.lens
    meta["Composite:LensID"] = "Canon EF 70-200mm f/2.8L IS II USM"  # a LensID agreeing with nothing
    key = lens_key_from_metadata(meta)
    assert key.lens_problem is not None and "16-35" in key.lens_problem


def test_generic_description_is_a_key(frames) -> None:
    key = read(frames["generic"])
    assert key.lens == "18-55mm f/3.5-5.6"
    assert key.lens_id() == "nikon corporation|nikon d70|18-55mm f/3.5-5.6"
    # Earlier versions keyed it "?", the id every undescribed lens of the body shares: not
    # its profile (tests/test_handoffs.py).
    assert key.legacy_ids == ()


@pytest.mark.parametrize("text, described", [
    ("unknown (251) 16-35mm", "16-35mm"), ("unknown 18-55mm", "18-55mm"), ("18.0-55.0 mm", "18-55mm"),
    ("18.0-55.0mm f/3.5-5.6", "18-55mm f/3.5-5.6"), ("100.0mm f/2.8", "100mm f/2.8"), ("15-45mm f/0", "15-45mm"),
    ("unknown ( )", None), ("ef 16-35mm f/2.8l ii usm", None), (None, None)])
def test_generic_description(text, described) -> None:
    assert generic_description(text) == described


def test_lens_spec_from_names() -> None:
    s = lens_spec("canon ef 70-200mm f/2.8l is ii usm")
    assert (s.focal_min, s.focal_max, s.aperture_min) == (70, 200, 2.8)
    s = lens_spec("m.zuiko digital 17mm f1.8")
    assert (s.focal_min, s.focal_max, s.aperture_min) == (17, 17, 1.8)
    assert lens_spec("ef 70-200mm f/2.8l is ii usm + 1.4x") is None  # a converter changes the focal length
    assert lens_spec("digital ixus 80 is & compatibles (standard)") is None


def test_one_key_whatever_the_front_end(frames) -> None:
    from vigproc.frontends.api import lens_key

    plain, prefixed = read(frames["nikon_plain"]), read(frames["nikon_prefixed"])
    assert plain.lens_id() == prefixed.lens_id() == "nikon corporation|nikon d70|af-s dx zoom-nikkor 18-70mm f/3.5-4.5g if-ed"
    # what the darktable plugin's lens_of() and a hook request send, through the API
    host = lens_key({"lens": "Nikon AF-S DX Zoom-Nikkor 18-70mm f/3.5-4.5G IF-ED", "make": "NIKON CORPORATION",
                     "model": "NIKON D70", "focal_mm": 18, "fnumber": 3.5})
    assert host.lens_id() == plain.lens_id()
    assert "nikon corporation|nikon d70|nikon af-s dx zoom-nikkor 18-70mm f/3.5-4.5g if-ed" in host.legacy_ids
    # a third-party brand is part of the name
    assert strip_make_prefix("nikon corporation", "sigma 10-20mm f/4-5.6 ex dc hsm") == "sigma 10-20mm f/4-5.6 ex dc hsm"
    assert strip_make_prefix("sony", "minolta/sony af dt 18-70mm f3.5-5.6 (d)").startswith("minolta/sony")


def test_lens_key_dict_round_trip_keeps_identity(frames) -> None:
    key = read(frames["out_of_range"])
    again = LensKey.from_dict(json.loads(json.dumps(key.to_dict())))
    assert again == key and again.lens_problem == key.lens_problem and again.legacy_ids == key.legacy_ids


# ------------------------------------------------------------------ lensfun
def test_lensfun_matches_names_spelt_differently() -> None:
    from vigproc.stores.lensfun_match import match_name

    for name, brand, want in [
        ("Minolta/Sony AF DT 18-70mm F3.5-5.6 (D)", "sony", "Minolta/Sony AF DT 18-70mm f/3.5-5.6 (D)"),
        ("EF70-200mm f/2.8L IS II USM", "canon", "Canon EF 70-200mm f/2.8L IS II USM"),
        ("ef 16-35mm f/2.8l ii usm", "canon", "Canon EF 16-35mm f/2.8L II USM"),
        ("af-s dx zoom-nikkor 18-70mm f/3.5-4.5g if-ed", "nikon", "Nikon AF-S DX Zoom-Nikkor 18-70mm f/3.5-4.5G IF-ED"),
        ("sigma af 10-20mm f4-5.6 ex dc", "pentax", "Sigma 10-20mm f/4-5.6 EX DC HSM"),
        ("digital ixus 80 is & compatibles (standard)", "canon", "Canon DIGITAL IXUS 80 IS & compatibles (Standard)"),
    ]:
        lenses, how = match_name(name, brand=brand)
        assert lenses and lenses[0].model == want, (name, how)


@pytest.mark.parametrize("name, brand", [
    ("ef-s 18-55mm f/3.5-5.6", "canon"),          # lensfun calibrated only the IS versions: "is" is not ignored
    ("ef 16-35mm f/2.8l iv usm", "canon"),        # no IV: neither the II nor the III
    ("ef 70-200mm f/2.8l is iii usm", "canon"),   # the III is not calibrated, the II is another lens
    ("ef 16-35mm f/2.8l is usm", "canon"),        # no IS version of the f/2.8
    ("minolta/sony af dt 18-70mm f3.5-5.6", "sony"),  # without the (D): not the (D) lens
    ("sigma 18-50mm", "canon"),                    # too little to tell lenses apart
])
def test_lensfun_rejects_weak_matches(name, brand) -> None:
    from vigproc.stores.lensfun_match import match_name

    lenses, how = match_name(name, brand=brand)
    assert lenses == [], (name, [lz.model for lz in lenses])


def test_lensfun_finds_the_sony_d_lens_and_checks_against_it(frames) -> None:
    from vigproc.forensics.check import forensic_check
    from vigproc.io.images import read_image
    from vigproc.stores.lensfun_io import lensfun_model
    from vigproc.stores.lensfun_match import match_lens

    key = read(frames["sony_d"])
    m = match_lens(key)
    assert m.lens is not None and m.lens.model == "Minolta/Sony AF DT 18-70mm f/3.5-5.6 (D)"
    assert lensfun_model(key, 360, 240).method == "lensfun"
    img, _ = read_image(frames["sony_d"])
    v = forensic_check(img, key)
    assert v.verdict != "unknown-lens" and v.expected_source == "lensfun"
    assert "Minolta/Sony AF DT 18-70mm f/3.5-5.6 (D)" in v.profile


def test_no_lensfun_calibration_for_a_lens_the_shot_cannot_be_from(frames) -> None:
    from vigproc.forensics.check import forensic_check
    from vigproc.io.images import read_image
    from vigproc.stores.lensfun_io import lensfun_model
    from vigproc.stores.lensfun_match import match_lens

    key = read(frames["out_of_range"])
    assert match_lens(key).lens is None
    with pytest.raises(ModelError, match="contradictory"):
        lensfun_model(key, 360, 240)
    ok = read(frames["in_range"])  # the same lens at a focal length it has: found
    assert match_lens(ok).lens is not None and match_lens(ok).lens.model == "Canon EF 70-200mm f/2.8L IS II USM"
    img, _ = read_image(frames["out_of_range"])
    v = forensic_check(img, key)
    assert v.verdict == "unknown-lens" and "contradictory" in v.reason and "31 mm" in v.reason
    assert v.expected_source is None and "31 mm" in v.to_dict()["lens_problem"]


def test_check_of_the_canon_251_frame_is_not_consistent(canon_251: Path) -> None:
    from vigproc.forensics.check import forensic_check
    from vigproc.io.images import read_image

    img, _ = read_image(canon_251)
    v = forensic_check(img, read(canon_251))
    assert v.verdict == "unknown-lens" and "70-200" not in (v.profile or "") and "describes" in v.reason


def test_lensfun_match_refuses_out_of_range_lens(frames) -> None:
    import dataclasses

    from vigproc.stores.lensfun_match import match_lens

    key = read(frames["in_range"])
    # a key built without the rule (a stored one): the found lens's range is still checked
    far = dataclasses.replace(key, focal_mm=31.0, lens_problem=None)
    got = match_lens(far)
    assert got.lens is None and "31 mm" in got.reason



@pytest.mark.parametrize("focal35, crop", [(200.0, 1.0), (256.3, 1.0), (320.0, 1.62), (324.0, 1.62)])
def test_lensfun_match_picks_a_calibration_that_covers_the_frame(focal35, crop) -> None:
    """lensfun holds the EF 70-200mm f/2.8L IS USM calibrated on full frame and on APS-C:
    an APS-H body (crop 1.28, a 1D Mark III) gets the full-frame one (its corner inside the
    calibrated radius), not the APS-C one whose crop is nearer in ratio but ends before the
    frame's corner (ρ = 1.26)."""
    from vigproc.io.lenskey import LensKey
    from vigproc.stores.lensfun_match import match_lens

    key = LensKey(make="canon", model="canon eos-1d mark iii", lens="canon ef 70-200mm f/2.8l is usm",
                  focal_mm=200.0, fnumber=5.6, focal_35mm=focal35)
    got = match_lens(key).lens
    assert got is not None and got.model == "Canon EF 70-200mm f/2.8L IS USM"
    assert got.crop_factor == pytest.approx(crop)
    assert got.crop_factor <= 1.02 * focal35 / 200.0

# ------------------------------------------------------------------ commands
def run_cli(*args: str, cwd: Path) -> subprocess.CompletedProcess:
    """``vigproc ARGS`` in this process (conftest.run_cli), from ``cwd``; the profile store
    is the test's own (conftest), as a HOME of ``cwd`` made it for a new process."""
    from conftest import run_cli as in_process

    return in_process(*args, cwd=cwd)


def test_correct_with_lensfun_estimates_a_contradictory_lens_and_says_why(frames, tmp_path: Path) -> None:
    out = tmp_path / "out"
    p = run_cli("correct", "--profile", "lensfun", "-o", str(out), str(frames["out_of_range"]), cwd=tmp_path)
    assert p.returncode == 0, p.stderr
    assert "not applied" in p.stderr and "31 mm" in p.stderr
    rec = json.loads((out / "out_of_range.jpg.vigproc.json").read_text())
    assert rec["source"] == "estimate"
    assert "31 mm" in rec["lensfun_not_applied"] and "31 mm" in rec["lens"]["key"]["lens_problem"]
    # the Sony (D) lens, which lensfun holds, is applied
    p = run_cli("correct", "--profile", "lensfun", "-o", str(out), str(frames["sony_d"]), cwd=tmp_path)
    assert p.returncode == 0, p.stderr
    assert json.loads((out / "sony_d.jpg.vigproc.json").read_text())["source"] == "lensfun"


def test_messages_show_lens_names_unescaped(frames, tmp_path: Path) -> None:
    assert display_lens_id("sigma|vigproc sample|105mm f1.4 dg hsm %7C art 018") == \
        "sigma|vigproc sample|105mm f1.4 dg hsm | art 018"
    assert display_lens_id("a|b|0%3F %3F") == "a|b|0? ?"
    src = ROOT / "vigproc" / "data" / "samples" / "kodim13_vignetted.jpg"
    p = run_cli("estimate", str(src), cwd=tmp_path)
    assert p.returncode == 0, p.stderr
    assert "%7C" not in p.stdout and "105mm f1.4 dg hsm | art 018" in p.stdout


# ------------------------------------------------------------------ stored profiles
def test_profiles_of_an_earlier_key_stay_found_and_keep_learning(tmp_path: Path) -> None:
    from vigproc.core.normalised import denormalise
    from vigproc.stores.profiles import ProfileKey, ProfileStore, aperture_bin, focal_bin

    theta = np.array([0.02, -0.01, 0.9, 0.02, 0.85, 0.05, 0.1, -0.05, 0.02, 0.0, 0.0, 0.0])
    cov = np.diag(np.full(12, 1e-4))
    host = lens_key_from_metadata({"EXIF:Make": "NIKON CORPORATION", "EXIF:Model": "NIKON D70",
                                   "EXIF:LensModel": "Nikon AF-S DX Zoom-Nikkor 18-70mm f/3.5-4.5G IF-ED",
                                   "EXIF:FocalLength": 18, "EXIF:FNumber": 3.5})
    old_id = "nikon corporation|nikon d70|nikon af-s dx zoom-nikkor 18-70mm f/3.5-4.5g if-ed"
    assert host.lens_id() != old_id and old_id in host.legacy_ids
    with ProfileStore(tmp_path / "p.sqlite") as store:
        old = ProfileKey(old_id, focal_bin(18.0), aperture_bin(3.5), "3:2")
        store.learn(old, denormalise(theta, cov, 3000, 2000, method="robust"))
        hit = store.lookup(host, 3000, 2000)
        assert hit is not None and hit.key == old
        assert store.key_for(host, 3000, 2000) == old  # frames keep pooling into it
        other = lens_key_from_metadata({"EXIF:Make": "NIKON CORPORATION", "EXIF:Model": "NIKON D70",
                                        "EXIF:LensModel": "AF-S DX Zoom-Nikkor 18-55mm f/3.5-5.6G",
                                        "EXIF:FocalLength": 18, "EXIF:FNumber": 3.5})
        assert store.lookup(other, 3000, 2000) is None
        assert store.key_for(other, 3000, 2000).lens_id == other.lens_id()


def test_bench_lens_match_on_the_shared_frames(shared_data: Path, capsys) -> None:
    """scripts/bench_lens_match.py: every shared frame whose lens lensfun calibrated is
    matched to that lens, and no other frame to any (exit 0 only then)."""
    import importlib.util

    spec = importlib.util.spec_from_file_location("bench_lens_match", ROOT / "scripts" / "bench_lens_match.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    assert mod.main(["--data", str(shared_data)]) == 0
    out = capsys.readouterr().out
    assert "5 with a lens lensfun calibrated; 5 matched (100 %), 0 false matches" in out


def test_max_aperture_brighter_than_the_name_is_a_lens_problem() -> None:
    body = {"EXIF:Make": "Canon", "EXIF:Model": "Canon EOS 5D", "EXIF:LensModel": "EF70-200mm f/4L USM",
            "EXIF:FocalLength": 100, "EXIF:FNumber": 5.6}
    assert lens_key_from_metadata({**body, "EXIF:MaxApertureValue": 4.0}).lens_problem is None
    # a macro lens focused close reports a darker effective aperture: no problem
    assert lens_key_from_metadata({**body, "EXIF:MaxApertureValue": 5.0}).lens_problem is None
    problem = lens_key_from_metadata({**body, "EXIF:MaxApertureValue": 2.8}).lens_problem
    assert problem is not None and "f/2.8" in problem and "f/4" in problem
