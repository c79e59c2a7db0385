"""A DNG's own vignetting opcodes in use: as a profile source (``--profile embedded`` and
``auto``), as a forensic reference (``vigproc check``) and as an output (``--output-format
dng``).  The DNGs are made here (tests/dngfixture.py) with their opcode lists."""

from __future__ import annotations

import hashlib
import json
import math
import shutil
import struct
import subprocess
from pathlib import Path

import numpy as np
import pytest

from vigproc.io.dng_opcodes import AreaSpec, GainMap, Opcode, OpcodeList
from vigproc.io.dng_vignette import model_to_radial, read_embedded, read_opcode_lists
from vigproc.errors import ModelError, VigprocError
from vigproc.io.images import read_image
from vigproc.core.model import VignettingModel
from vigproc.pipeline.processor import Processor, Settings

from conftest import photo_like, textured
from dngfixture import make_dng

rawpy = pytest.importorskip("rawpy")
pytestmark = pytest.mark.skipif(shutil.which("exiftool") is None, reason="exiftool program not installed")

W, H = 384, 256
#: An opcode the camera wrote before (any id vigproc does not know): appended to, never lost.
CAMERA_OPCODE = Opcode(77, 0x01040000, 1, b"camera's own")


def true_model(scale: float = 1.0) -> VignettingModel:
    f = 0.9 * math.hypot(W, H) / 2 / math.sqrt(scale)
    return VignettingModel(W, H, center=(12, -8), p=(f**-2, 0, f**-2), alpha=(0.02, 0.01, 0, 0, 0, 0, 0))


def tilted_gain_map() -> GainMap:
    """A GainMap the Kang-Weiss model cannot follow (a ripple across), one plane for all."""
    v = np.linspace(-1, 1, 9)[:, None]
    h = np.linspace(-1, 1, 13)[None, :]
    gains = 1.0 + 0.7 * (v * v + h * h) / 2 + 0.08 * np.cos(3 * np.pi * h)
    return GainMap(AreaSpec(0, 0, H, W, planes=3), gains, 1 / 8, 1 / 12)


def sha256(p: Path) -> str:
    return hashlib.sha256(p.read_bytes()).hexdigest()


def scene() -> np.ndarray:
    s = textured(H, W, seed=0, contrast=0.05)
    return s * (0.8 / s.max())


def residual_ev(out: np.ndarray, sc: np.ndarray, block: int = 8) -> float:
    """RMS fall-off left after a correction, EV: corrected / scene on 8×8 blocks (the
    demosaicing blurs the texture pixel by pixel; the fall-off is smooth)."""
    def blocks(a: np.ndarray) -> np.ndarray:
        return a.reshape(H // block, block, W // block, block).mean(axis=(1, 3))

    ratio = np.log2(blocks(out.mean(axis=2)) / blocks(sc))
    ratio -= np.median(ratio)
    return float(np.sqrt(np.mean(ratio**2)))


@pytest.fixture(scope="module")
def dngs(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    d = tmp_path_factory.mktemp("dng")
    sc = scene()
    truth = true_model()
    fvr = model_to_radial(truth).opcode
    out = {}
    out["radial"] = d / "radial.dng"  # the camera's calibration matches the lens
    make_dng(out["radial"], field=truth.field(), scene=sc, noise=0.001,
             opcode_lists={3: OpcodeList((CAMERA_OPCODE, fvr.to_opcode())).to_bytes()})
    gm = tilted_gain_map()
    out["gainmap"] = d / "gainmap.dng"
    make_dng(out["gainmap"], field=1.0 / gm.gain_field(W, H), scene=sc, noise=0.001,
             opcode_lists={3: OpcodeList((gm.to_opcode(),)).to_bytes()})
    out["plain"] = d / "plain.dng"  # no opcodes
    make_dng(out["plain"], field=truth.field(), scene=sc, noise=0.001)
    # for the forensic check: scenes like photographs (the estimator forensics uses expects
    # their average fall-off); the lens's fall-off and its calibration ...
    photo = photo_like(H, W, seed=1)
    photo *= 0.8 / photo.max()
    out["honest"] = d / "honest.dng"
    make_dng(out["honest"], field=truth.field(), scene=photo, noise=0.001,
             opcode_lists={3: OpcodeList((fvr.to_opcode(),)).to_bytes()})
    # ... and a frame cropped off-centre that still carries the calibration of the whole
    # frame: its fall-off is centred 150 px to the right of what its file claims
    out["lying"] = d / "lying.dng"
    cropped = VignettingModel(W, H, center=(150.0, 10.0), p=truth.p, alpha=truth.alpha)
    make_dng(out["lying"], field=cropped.field(), scene=photo, noise=0.001,
             opcode_lists={3: OpcodeList((fvr.to_opcode(),)).to_bytes()})
    return out


def test_opcode_lists_are_read_from_the_raw_ifd(dngs: dict[str, Path]) -> None:
    lists = read_opcode_lists(dngs["radial"])
    assert [n for n, _ in lists] == ["OpcodeList3"]
    assert lists[0][1].opcodes[0] == CAMERA_OPCODE
    cal = read_embedded(dngs["radial"])
    assert cal.kind == "FixVignetteRadial" and len(cal.opcodes) == 1
    m, rms, mx = cal.fit(W, H)
    assert rms < 2e-3 and mx < 0.02 and m.method == "dng:FixVignetteRadial"
    assert read_embedded(dngs["plain"]) is None and read_opcode_lists(dngs["plain"]) == []


def test_a_malformed_list_in_a_file_names_the_file(tmp_path: Path) -> None:
    from vigproc.io.dng_opcodes import DngOpcodeError

    bad = struct.pack(">I", 3) + b"\x00" * 20  # three opcodes declared, 20 bytes
    p = tmp_path / "bad list.dng"
    make_dng(p, opcode_lists={2: bad})
    with pytest.raises(DngOpcodeError, match="bad list.dng.*OpcodeList2"):
        read_embedded(p)
    # correcting with auto: said, not fatal (the frame is estimated instead)
    (tmp_path / "out").mkdir()
    with Processor(Settings(profile="auto", output_format="tiff-float")) as proc:
        res = proc.process_file(p, tmp_path / "out")
    assert res.source == "estimate"


def correct(path: Path, outdir: Path, **settings) -> tuple[dict, np.ndarray | None]:
    settings.setdefault("output_format", "tiff-float")
    outdir.mkdir(exist_ok=True)
    with Processor(Settings(mode="correct", **settings)) as proc:
        res = proc.process_file(path, outdir).to_dict()
    out = read_image(res["output"])[0] if res.get("output") and res["output"].endswith(".tif") else None
    return res, out


def test_profile_embedded_corrects_with_the_cameras_calibration(dngs: dict[str, Path], tmp_path: Path) -> None:
    res, out = correct(dngs["radial"], tmp_path, profile="embedded")
    assert res["source"] == "embedded" and res["applied"]
    assert res["embedded"]["kind"] == "FixVignetteRadial" and res["embedded"]["fit_rms_ev"] < 2e-3
    assert res["model"]["method"] == "dng:FixVignetteRadial"
    assert residual_ev(out, scene()) < 0.01 < float(np.sqrt(np.mean(np.log2(true_model().field()) ** 2)))
    # the sidecar says the same
    side = json.loads(next(tmp_path.glob("*.vigproc.json")).read_text())
    assert side["source"] == "embedded" and side["embedded"]["fit_max_ev"] < 0.02


def test_a_gain_map_is_divided_out_as_its_own_field(dngs: dict[str, Path], tmp_path: Path) -> None:
    res, out = correct(dngs["gainmap"], tmp_path, profile="embedded")
    assert res["source"] == "embedded" and res["model"]["method"] == "dng:GainMap"
    # exact up to noise and quantisation, though the Kang-Weiss fit misses the tilt
    assert residual_ev(out, scene()) < 0.01
    assert res["embedded"]["fit_rms_ev"] > 0.01


def test_profile_embedded_without_opcodes_is_an_error(dngs: dict[str, Path], tmp_path: Path) -> None:
    with pytest.raises(ModelError, match="no vignetting calibration of its own"):
        correct(dngs["plain"], tmp_path, profile="embedded")
    assert not any(tmp_path.iterdir())


def test_auto_order_trusted_profile_then_embedded_then_estimate(dngs: dict[str, Path], tmp_path: Path) -> None:
    from vigproc.io.exif import read_lens_key
    from vigproc.stores.profiles import Profile, ProfileKey, ProfileStore, normalise

    for d in "abc":
        (tmp_path / d).mkdir()
    with ProfileStore(tmp_path / "p.sqlite") as store:
        with Processor(Settings(profile="auto", output_format="tiff-float"), store=store) as proc:
            assert proc.process_file(dngs["radial"], tmp_path / "a").source == "embedded"
            assert proc.process_file(dngs["plain"], tmp_path / "b").source == "estimate"
        key = ProfileKey.from_lens(read_lens_key(dngs["radial"]), W, H)
        store.put(Profile(key=key, theta=normalise(true_model(0.5))[0], provenance="user", trusted=True))
        with Processor(Settings(profile="auto", output_format="tiff-float"), store=store) as proc:
            res = proc.process_file(dngs["radial"], tmp_path / "c")
    assert res.source == "stored-profile"
    assert res.extra["embedded"]["kind"] == "FixVignetteRadial"  # recorded, not used (no fit was paid for)
    assert "fit_rms_ev" not in res.extra["embedded"]


def test_output_dng_carries_the_correction_as_an_opcode(dngs: dict[str, Path], tmp_path: Path) -> None:
    src = dngs["radial"]
    before = sha256(src)
    res, _ = correct(src, tmp_path, profile="estimate", output_format="dng")
    dst = Path(res["output"])
    assert dst.parent == tmp_path and dst.suffix == ".dng" and ".corrected" in dst.name and sha256(src) == before
    names = sorted(p.name for p in tmp_path.iterdir())  # the copy and its sidecar, no temporaries left
    assert len(names) == 2 and dst.name in names and any(n.endswith(".vigproc.json") for n in names)
    # our parser: the camera's other opcodes first, unchanged, then ours in place of the
    # camera's FixVignetteRadial (LibRaw's pixels, which the estimate saw, keep the fall-off)
    lst = dict(read_opcode_lists(dst))["OpcodeList3"]
    old = dict(read_opcode_lists(src))["OpcodeList3"]
    assert lst.opcodes[0] == old.opcodes[0] == CAMERA_OPCODE and len(lst) == 2
    ((_, f_new),) = lst.decoded()
    est = VignettingModel.from_dict(res["model"])
    assert f_new.cx == pytest.approx(0.5 + est.center[0] / W)
    # the opcode undoes the estimate within the error it states
    info = res["dng_opcode"]["opcode"]
    assert info["fit_rms_ev"] < 0.01 and list(f_new.k) == info["k"]
    d = (-np.log(f_new.gain_field(W, H)) - est.log_field()) / math.log(2)
    assert float(np.sqrt(np.mean(d * d))) == pytest.approx(info["fit_rms_ev"], abs=1e-3)
    # exiftool reads it, and the file declares the DNG version opcodes need
    t = json.loads(subprocess.run(["exiftool", "-j", "-a", "-G1", "-OpcodeList3", "-DNGBackwardVersion", "-LensModel",
                                   "--", str(dst)], capture_output=True, check=True).stdout)[0]
    assert t["IFD0:OpcodeList3"] == "[opcode 77], FixVignetteRadial"
    assert t["IFD0:DNGBackwardVersion"] == "1.3.0.0" and t["ExifIFD:LensModel"] == "VP 35mm F2.0 Test"
    # LibRaw still decodes it, to the same pixels (it does not apply OpcodeList3)
    with rawpy.imread(str(dst)) as raw, rawpy.imread(str(src)) as raw0:
        assert np.array_equal(raw.raw_image, raw0.raw_image)
    a, _ = read_image(src)
    b, _ = read_image(dst)
    assert np.array_equal(a, b)


def test_output_dng_of_the_embedded_calibration_adds_nothing(dngs: dict[str, Path], tmp_path: Path) -> None:
    res, _ = correct(dngs["radial"], tmp_path, profile="embedded", output_format="dng")
    assert res["dng_opcode"]["opcode"] is None and "own calibration" in res["dng_opcode"]["note"]
    assert read_opcode_lists(res["output"]) == read_opcode_lists(dngs["radial"])


def test_output_dng_needs_a_dng_input(tmp_path: Path) -> None:
    from vigproc.io.images import write_image

    tif = tmp_path / "in.tif"
    write_image(tif, np.full((32, 48, 3), 0.5, np.float32), bit_depth="uint16")
    with pytest.raises(VigprocError, match="needs a DNG input"):
        correct(tif, tmp_path / "out", profile="estimate", output_format="dng")
    assert not any((tmp_path / "out").iterdir())


def check(path: Path, capsys) -> tuple[int, dict]:
    from vigproc.frontends.cli import main

    code = main(["check", "--json", "--no-store", "--method", "robust", str(path)])
    return code, json.loads(capsys.readouterr().out)["results"][0]


def test_check_compares_a_frame_with_its_own_calibration(dngs: dict[str, Path], capsys) -> None:
    code, rec = check(dngs["honest"], capsys)
    emb = rec["embedded"]
    assert emb["expected_source"] == "embedded" and emb["verdict"] == "consistent", emb["reason"]
    assert emb["profile"] == "the DNG's own FixVignetteRadial" and "estimate" not in emb
    code, rec = check(dngs["lying"], capsys)
    assert rec["embedded"]["verdict"] == "inconsistent", rec["embedded"]["reason"]
    assert "centre" in rec["embedded"]["reason"]
    assert code == 20
    code, rec = check(dngs["plain"], capsys)
    assert "embedded" not in rec


def test_output_dng_of_a_real_camera_dng(shared_data: Path, tmp_path: Path) -> None:
    """A DNG 1.1 written by a camera (Magic Lantern on a Canon 550D): the correction goes
    into its raw IFD, the version is raised to 1.3, LibRaw decodes the same raw data."""
    from vigproc.io.dng_vignette import write_dng_correction

    src = shared_data / "raw" / "tinydng" / "colorchart.dng"
    if not src.is_file():
        pytest.skip(f"shared data not present at {src}")
    before = sha256(src)
    with rawpy.imread(str(src)) as raw0:
        w, h = raw0.sizes.width, raw0.sizes.height
        raw_before = raw0.raw_image.copy()
    q = 6.0 / (w * w + h * h)  # about 0.5 EV in the corners
    model = VignettingModel(w, h, center=(20.0, -10.0), p=(q, 0.0, q), alpha=(0.02,) + (0.0,) * 6)
    dst = tmp_path / "colorchart.corrected.dng"
    info = write_dng_correction(src, dst, model)
    assert sha256(src) == before
    assert info["ifd"] == "IFD0" and info["dng_backward_version"] == "1.3.0.0" and info["opcodes_in_list"] == 1
    (_, fvr), = dict(read_opcode_lists(dst))["OpcodeList3"].decoded()
    assert info["opcode"]["fit_rms_ev"] < 0.01 and list(fvr.k) == info["opcode"]["k"]
    with rawpy.imread(str(dst)) as raw:
        assert np.array_equal(raw.raw_image, raw_before)
    t = json.loads(subprocess.run(["exiftool", "-j", "-OpcodeList3", "-Model", "--", str(dst)],
                                  capture_output=True, check=True).stdout)[0]
    assert t["OpcodeList3"] == "FixVignetteRadial" and t["Model"] == "Canon EOS Kiss X4"


def test_opcodes_are_read_and_written_through_the_one_persistent_exiftool(dngs: dict[str, Path],
                                                                          tmp_path: Path, monkeypatch) -> None:
    """No new exiftool per call: reads and the OpcodeList3 write go through the process's
    stay-open one; a name the argument protocol cannot carry (a line break) goes through
    an alias, and the source is not touched."""
    from vigproc.io import metadata
    from vigproc.io.dng_vignette import write_dng_correction

    proc = metadata._process()
    read_opcode_lists(dngs["radial"])
    launches = proc.launches
    started = []
    popen = subprocess.Popen

    def spy(*a, **k):
        started.append(a[0] if a else k.get("args"))
        return popen(*a, **k)

    monkeypatch.setattr(subprocess, "Popen", spy)
    hostile = tmp_path / "new\nline -x.dng"
    shutil.copyfile(dngs["radial"], hostile)
    before = sha256(hostile)
    dst = tmp_path / "out\nput.dng"
    for _ in range(3):
        assert read_opcode_lists(hostile) == read_opcode_lists(dngs["radial"])
    info = write_dng_correction(hostile, dst, true_model())
    assert started == [] and proc.launches == launches and proc.running  # not one process more
    assert sha256(hostile) == before
    assert len(dict(read_opcode_lists(dst))["OpcodeList3"]) == info["opcodes_in_list"] == 2  # the camera's radial replaced
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted([hostile.name, dst.name])  # no temporaries left
