"""Profiles that travel (issue 36): a learned profile exported through the command line is
used as it is by ``correct --profile FILE`` and by ``profile import`` into another store."""

import json
import math
import subprocess

import numpy as np
import pytest

from vigproc.core.model import PARAM_NAMES, VignettingModel
from vigproc.stores.profiles import ProfileStore, import_profile

from conftest import photo_like, run_cli

#: What a Nikon D70 with its kit zoom writes at 70 mm (the issue's camera), spelt as the camera spells it.
D70_EXIF = {"Make": "NIKON CORPORATION", "Model": "NIKON D70", "LensMake": "Nikon",
            "LensModel": "AF-S DX Zoom-Nikkor 18-70mm f/3.5-4.5G IF-ED",
            "FocalLength": 70, "FNumber": 4.5, "FocalLengthIn35mmFormat": 105}
H, W = 256, 384


def run(*args):
    """``vigproc ARGS``, in this process (what is tested is not the process boundary)."""
    return run_cli(*args)


@pytest.fixture(scope="module")
def learned(tmp_path_factory):
    """Four DNG frames of one lens carrying a lensfun calibration's fall-off, learned into a
    store through the command line: (folder, store, frames, the field's pa coefficients)."""
    d = tmp_path_factory.mktemp("travel")
    return (d, *_learn(d, "d70", D70_EXIF, seed=20))


def _learn(d, name: str, exif: dict, seed: int):
    """Four DNG frames ``d/<name>_<i>.dng`` of one lens with ``exif``, carrying a lensfun
    calibration's fall-off, learned into ``d/<name>.sqlite`` through the command line:
    (store, frames, the field's pa coefficients)."""
    from dngfixture import make_dngs

    from vigproc.stores.lensfun import diverse_lenses, pa_field

    _, pa = diverse_lenses(1)[0]
    frames = [d / f"{name}_{i}.dng" for i in range(4)]
    make_dngs([(p, dict(width=W, height=H, field=pa_field((H, W), pa.k1, pa.k2, pa.k3),
                        scene=photo_like(H, W, seed=seed + i), exif=exif)) for i, p in enumerate(frames)])
    store = d / f"{name}.sqlite"
    r = run("profile", "--profile-db", store, "learn", *frames)
    assert r.returncode == 0, r.stderr
    return store, frames, pa


def _lensfun_applies(xml, crop: float, focal: float, aperture: float, w: int, h: int) -> np.ndarray:
    """log2 of the field lensfunpy applies from the lensfun file ``xml`` (its one lens) to a
    ``w`` x ``h`` frame of crop factor ``crop``: a host's view."""
    import lensfunpy

    db = lensfunpy.Database(paths=[str(xml)], load_common=False, load_bundled=False)
    [lens] = db.lenses
    mod = lensfunpy.Modifier(lens, crop, w, h)
    mod.initialize(focal, aperture, 1000.0, pixel_format=np.float64, flags=lensfunpy.ModifyFlags.VIGNETTING,
                   reverse=True)
    img = np.ones((h, w, 3))
    assert mod.apply_color_modification(img)
    return np.log2(img[..., 1])


def _field(model: VignettingModel) -> np.ndarray:
    return model.log_field((model.height, model.width)) / math.log(2.0)


def test_an_exported_learned_profile_is_used_elsewhere_with_the_same_field_and_trust(learned, tmp_path):
    d, store, frames, _ = learned
    with ProfileStore(store) as st:
        [orig] = st.list()
    # the lens-family fit holds the centre and the shape fixed: the case that failed
    assert orig.covariance is not None and not np.all(np.diag(orig.covariance) > 0)
    out = tmp_path / "lens.json"
    r = run("profile", "--profile-db", store, "export", "0", out)
    assert r.returncode == 0, r.stderr
    doc = json.loads(out.read_text())
    assert doc["schema"] == "vigproc.profile/2"
    assert doc["fixed"] == ["cx", "cy", "p1", "p2", "p3"]
    n_free = len(PARAM_NAMES) - len(doc["fixed"])
    assert len(doc["covariance"]) == n_free and all(v > 0 for v in np.diag(doc["covariance"]))

    # the very file corrects a frame, with the stored profile's field
    r = run("correct", "--profile", out, frames[0], "-o", tmp_path / "out", "--json")
    assert r.returncode == 0, r.stderr
    rec = json.loads(r.stdout)["results"][0]
    assert rec["source"] == "profile-file"
    used = VignettingModel.from_dict(rec["model"])
    np.testing.assert_allclose(_field(used), _field(orig.model(W, H)), atol=1e-9)

    # ... and imports into another store with the same field, σ and trust
    other = tmp_path / "other.sqlite"
    r = run("profile", "--profile-db", other, "import", out)
    assert r.returncode == 0, r.stderr
    with ProfileStore(other) as st:
        [moved] = st.list()
    assert moved.key == orig.key and moved.n_frames == orig.n_frames
    assert moved.trusted == orig.trusted
    np.testing.assert_array_equal(moved.theta, orig.theta)
    assert moved.field_sigma_ev == pytest.approx(orig.field_sigma_ev, rel=1e-12)
    np.testing.assert_allclose(moved.covariance, orig.covariance, rtol=1e-12, atol=0)
    # and travels on: exported again from there, the same file content
    again = tmp_path / "again.json"
    assert run("profile", "--profile-db", other, "export", "0", again).returncode == 0
    a, b = json.loads(out.read_text()), json.loads(again.read_text())
    assert a["scatter_sigma_ev"] is not None  # four frames: their spread is known
    for k in ("model", "fixed", "covariance", "trusted", "field_sigma_ev", "scatter_sigma_ev", "n_frames"):
        assert a[k] == b[k], k
    assert a.get("cast") == b.get("cast")


def test_a_learned_profile_exported_as_schema_1_still_loads(learned, tmp_path):
    """Files written before schema /2 wrote a fixed parameter as an all-zero row and
    column of a 12×12 covariance: read as fixed, not refused."""
    d, store, _, _ = learned
    with ProfileStore(store) as st:
        [orig] = st.list()
    out = tmp_path / "v2.json"
    assert run("profile", "--profile-db", store, "export", "0", out).returncode == 0
    doc = json.loads(out.read_text())
    doc["schema"] = "vigproc.profile/1"
    del doc["fixed"]
    doc["covariance"] = orig.covariance.tolist()
    old = tmp_path / "v1.json"
    old.write_text(json.dumps(doc))
    p = import_profile(old)
    assert p.trusted == orig.trusted
    np.testing.assert_array_equal(p.theta, orig.theta)
    # a fixed parameter given a zero variance in a /2 file is refused: /2 names it in 'fixed'
    doc2 = json.loads(out.read_text())
    doc2["fixed"] = doc2["fixed"][:-1]
    doc2["covariance"] = [[0.0] + r for r in doc2["covariance"]]
    doc2["covariance"].insert(0, [0.0] * len(doc2["covariance"][0]))
    bad = tmp_path / "bad.json"
    bad.write_text(json.dumps(doc2))
    r = run("profile", "--profile-db", tmp_path / "x.sqlite", "import", bad)
    assert r.returncode == 8 and "belongs in 'fixed'" in r.stderr and "Traceback" not in r.stderr, r.stderr


def test_export_lensfun_is_applied_by_lensfun_at_the_cameras_crop_factor_as_vigproc_applies_it(learned, tmp_path):
    """The issue: crop factor 1.0, mount "Generic", lowercase names, the bin label as focal
    length; a host applying it at the D70's crop factor (1.525) got a third of the fall-off."""
    import xml.etree.ElementTree as ET

    pytest.importorskip("lensfunpy")
    d, store, _, _ = learned
    out = tmp_path / "lens.xml"
    r = run("profile", "--profile-db", store, "export-lensfun", out)
    assert r.returncode == 0, r.stderr
    [el] = ET.parse(out).getroot().iter("lens")
    assert el.findtext("maker") == "Nikon"  # EXIF LensMake, as spelt
    assert el.findtext("model") == D70_EXIF["LensModel"]
    assert el.findtext("mount") == "Nikon F AF"  # lensfun's D70
    crop = float(el.findtext("cropfactor"))
    assert crop == pytest.approx(1.525)
    [cal] = el.iter("vignetting")
    assert float(cal.get("focal")) == 70.0 and float(cal.get("aperture")) == 4.5  # not the bin's 66.8 mm

    with ProfileStore(store) as st:
        [p] = st.list()
    w, h = 600, 400
    ours = _field(p.model(w, h))
    theirs = _lensfun_applies(out, 1.525, 70.0, 4.5, w, h)  # a host's view: the D70's real crop factor
    corners = [(0, 0), (0, -1), (-1, 0), (-1, -1)]
    print(f"corner fall-off: vigproc {ours[0, 0]:.3f} EV, lensfun at crop 1.525 {theirs[0, 0]:.3f} EV")
    assert ours[0, 0] < -0.3  # a fall-off worth comparing
    for c in corners:
        assert abs(theirs[c] - ours[c]) < 0.02, c
    assert np.sqrt(np.mean((theirs - ours) ** 2)) < 0.01

    # profile list names the focal length the frames were shot at, not the bin
    r = run("profile", "--profile-db", store, "list")
    assert r.returncode == 0 and "@ 70 mm N=4.5 3:2" in r.stdout and "66.8" not in r.stdout, r.stdout


def test_a_profile_file_of_another_lens_is_applied_with_a_warning_naming_both(learned, tmp_path):
    from dngfixture import make_dng

    d, store, frames, _ = learned
    out = tmp_path / "lens.json"
    assert run("profile", "--profile-db", store, "export", "0", out).returncode == 0
    other = tmp_path / "canon.dng"
    make_dng(other, width=W, height=H, scene=photo_like(H, W, seed=3),
             exif={"Make": "Canon", "Model": "Canon EOS 5D", "LensModel": "EF24-105mm f/4L IS USM",
                   "FocalLength": 70, "FNumber": 4.5})
    r = run("correct", "--profile", out, other, "-o", tmp_path / "o1", "--json")
    assert r.returncode == 0, r.stderr
    mine, theirs = "nikon corporation|nikon d70|af-s dx zoom-nikkor", "canon|canon eos 5d|ef24-105mm f/4l is usm"
    assert mine in r.stderr and theirs in r.stderr, r.stderr
    rec = json.loads(r.stdout)["results"][0]
    assert rec["source"] == "profile-file" and len(rec["warnings"]) == 1
    assert mine in rec["warnings"][0] and theirs in rec["warnings"][0]
    sidecar = json.loads((tmp_path / "o1" / "canon.dng.vigproc.json").read_text())
    assert sidecar["warnings"] == rec["warnings"]
    # the lens's own frame: no warning
    r = run("correct", "--profile", out, frames[1], "-o", tmp_path / "o2", "--json")
    assert r.returncode == 0 and "warnings" not in json.loads(r.stdout)["results"][0] and mine not in r.stderr


def test_shots_keep_real_focal_lengths_and_refuse_hostile_values(tmp_path):
    from vigproc.io.exif import LensKey
    from vigproc.stores.profiles import ProfileStoreError, Shots

    k = LensKey(make="nikon", model="nikon d70", lens="x", focal_mm=67.0, focal_35mm=100.5,
                spelling=("NIKON", "NIKON D70", "X", None))
    s = Shots.of_frame(k)
    for f in (70.0, 70.0):
        s = s.add(Shots.of_frame(LensKey(make="nikon", model="nikon d70", lens="x", focal_mm=f, focal_35mm=105.0)))
    assert s.focal_mm == ((67.0, 1), (70.0, 2)) and s.focal_median == 70.0 and s.crop_factor == 1.5
    assert s.describe_focal() == "67-70 mm (median 70)" and s.names[:2] == ("NIKON", "NIKON D70")
    assert Shots.from_json(s.to_json(), "f") == s
    # an absurd 35-mm focal length (an EXIF mistake seen in real files) gives no crop factor
    assert Shots.of_frame(LensKey(make="a", model="b", lens=None, focal_mm=23.1, focal_35mm=11113.0)).crop == ()
    for bad in ({"make": "a\nb"}, {"lens": "x" * 300}, {"focal_mm": [[-1, 1]]}, {"focal_mm": [[50, 0]]},
                {"crop": [[99.0, 1]]}, {"focal_mm": "70"}, {"model": 5}):
        with pytest.raises(ProfileStoreError, match="shots"):
            Shots.from_json({**s.to_json(), **bad}, "f")


def _darktable_lens_xmp(camera: bytes, lens: bytes, flags: int) -> str:
    """The XMP of darktable's lens module in lensfun mode for ``camera`` and ``lens`` at
    70 mm f/4.5, crop 1.525 (scripts/bench_darktable_dng.py's); ``flags`` 2: vignetting,
    0: nothing (the reference export)."""
    import importlib.util
    from pathlib import Path

    path = Path(__file__).resolve().parents[1] / "scripts" / "bench_darktable_dng.py"
    spec = importlib.util.spec_from_file_location("bench_darktable_dng", path)
    bench = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(bench)
    return bench.lens_xmp(1, flags, crop=1.525, focal=70.0, aperture=4.5, camera=camera, lens=lens)


def test_darktable_applies_the_exported_lensfun_profile_as_vigproc_does(learned, tmp_path):
    """darktable 4.2's lens module, in lensfun mode, given the exported database in the
    user's lensfun folder: the gain it applies (its export with vignetting correction over
    one without) is vigproc's profile, corners included."""
    import os
    import shutil

    from vigproc.io.images import read_image

    exe = shutil.which("darktable-cli")
    if exe is None:
        pytest.skip("darktable-cli is not installed (scripts/test.sh installs it unless VIGPROC_NO_DARKTABLE=1)")
    d, store, frames, _ = learned
    home = tmp_path / "home"
    lensfun_dir = home / ".local" / "share" / "lensfun"  # where lensfun looks for a user's own profiles
    lensfun_dir.mkdir(parents=True)
    r = run("profile", "--profile-db", store, "export-lensfun", lensfun_dir / "vigproc.xml")
    assert r.returncode == 0, r.stderr
    env = dict(os.environ, HOME=str(home), XDG_DATA_HOME=str(home / ".local" / "share"))

    def export(name: str, flags: int) -> np.ndarray:
        xmp, out, cfg = tmp_path / f"{name}.xmp", tmp_path / f"{name}.tif", tmp_path / f"cfg-{name}"
        xmp.write_text(_darktable_lens_xmp(b"Nikon D70", D70_EXIF["LensModel"].encode(), flags))
        res = subprocess.run([exe, str(frames[0]), str(xmp), str(out), "--icc-type", "LIN_REC2020", "--core",
                              "--configdir", str(cfg), "--library", ":memory:",
                              "--conf", "plugins/imageio/format/tiff/bpp=32",
                              "--conf", "plugins/darkroom/workflow=none", "-d", "perf"],
                             capture_output=True, text=True, env=env, timeout=600)
        assert res.returncode == 0 and out.exists(), res.stdout[-500:] + res.stderr[-500:]
        assert "lens correction" in res.stdout + res.stderr  # the module ran
        img, _ = read_image(out, transfer="linear")
        return np.asarray(img, dtype=np.float64)[..., :3].mean(axis=-1)

    gain = np.log2(export("on", 2) / export("off", 0))
    with ProfileStore(store) as st:
        [p] = st.list()
    ours = -_field(p.model(gain.shape[1], gain.shape[0]))
    diff = gain - ours
    print(f"darktable corner gain {gain[0, 0]:.3f} EV, vigproc {ours[0, 0]:.3f} EV; "
          f"RMS difference {np.sqrt(np.mean(diff ** 2)):.4f} EV")
    assert ours[0, 0] > 0.3
    for c in [(0, 0), (0, -1), (-1, 0), (-1, -1)]:
        assert abs(diff[c]) < 0.02, c
    assert np.sqrt(np.mean(diff ** 2)) < 0.01


def test_a_v9_store_migrates_and_learns_how_its_frames_were_shot(tmp_path):
    import sqlite3

    from vigproc.io.exif import LensKey
    from vigproc.stores.profiles import SCHEMA_VERSION, ProfileKey

    lens = LensKey(make="nikon corporation", model="nikon d70", lens="x", focal_mm=70.0, fnumber=4.5,
                   focal_35mm=105.0, spelling=("NIKON CORPORATION", "NIKON D70", "X", None))
    key = ProfileKey.from_lens(lens, 300, 200)
    m = VignettingModel(300, 200, p=(1 / 250.0**2, 0.0, 1 / 250.0**2),
                        covariance=tuple(map(tuple, (np.eye(12) * 1e-6).tolist())))
    db = tmp_path / "p.sqlite"
    with ProfileStore(db) as st:
        st.learn(key, m, frame_id="a")
    con = sqlite3.connect(db)  # as vigproc before schema v10 left it
    con.execute("ALTER TABLE profiles DROP COLUMN shots")
    con.execute("DELETE FROM schema_version WHERE version > 9")
    con.commit()
    con.close()
    with ProfileStore(db) as st:
        assert st.schema_version == SCHEMA_VERSION >= 10
        assert st.get(key).shots is None  # learned before: unknown until its next frame
        p = st.learn(key, m, frame_id="b", lens_key=lens)
        assert p.shots.focal_mm == ((70.0, 1),) and p.shots.names[1] == "NIKON D70"
        assert st.get(key).shots == p.shots and st.check() == []


def test_export_lensfun_of_frames_shot_in_a_crop_mode_is_written_at_the_frames_crop(tmp_path):
    """An FX body (lensfun: a D800, crop 1.0) shooting in its DX crop mode (EXIF 35-mm focal
    length 1.5 x): the frames are the sensor's inner 0.66, and a host applying the profile
    at their crop factor (darktable takes it from the EXIF) must get vigproc's field, not
    the inner 0.66 of it (the written crop factor the sensor's 1.0: ρ = 1 / 1.5 at the
    corner)."""
    import xml.etree.ElementTree as ET

    pytest.importorskip("lensfunpy")
    exif = {"Make": "NIKON CORPORATION", "Model": "NIKON D800", "LensMake": "Nikon",
            "LensModel": "AF-S Nikkor 50mm f/1.8G", "FocalLength": 50, "FNumber": 1.8,
            "FocalLengthIn35mmFormat": 75}
    store, _, _ = _learn(tmp_path, "d800dx", exif, seed=40)
    out = tmp_path / "lens.xml"
    r = run("profile", "--profile-db", store, "export-lensfun", out)
    assert r.returncode == 0, r.stderr
    [el] = ET.parse(out).getroot().iter("lens")
    assert float(el.findtext("cropfactor")) == pytest.approx(1.5)  # the frames', not the sensor's 1.0

    with ProfileStore(store) as st:
        [p] = st.list()
    w, h = 600, 400
    ours = _field(p.model(w, h))
    theirs = _lensfun_applies(out, 1.5, 50.0, 1.8, w, h)  # the frames' crop factor, as their EXIF gives it
    print(f"corner fall-off: vigproc {ours[0, 0]:.3f} EV, lensfun at crop 1.5 {theirs[0, 0]:.3f} EV")
    assert ours[0, 0] < -0.3  # a fall-off worth comparing
    assert np.sqrt(np.mean((theirs - ours) ** 2)) < 0.01
