"""Grid fields in profiles (issue 41): flat frames' measured per-channel grids pooled into
a profile, stored, carried by ``vigproc.profile/4`` files, and applied by the profile's
model wherever a profile corrects."""

from __future__ import annotations

import json
import math
import sqlite3
from pathlib import Path

import numpy as np
import pytest

from vigproc.core.gridfield import GridField, GridFieldModel
from vigproc.core.model import frame_coords
from vigproc.errors import ModelError
from vigproc.frontends.api import Pipeline, lens_key
from vigproc.pipeline.processor import Processor
from vigproc.pipeline.settings import Settings
from vigproc.stores.profile_grid import GridPool
from vigproc.stores.profiles import (FILE_SCHEMA_COLOUR, FILE_SCHEMA_GRID, SCHEMA_VERSION, ProfileStore,
                                     export_profile, import_profile, profile_from_dict, profile_to_dict)

W, H = 300, 200
LENS = {"make": "Cam", "model": "X1", "lens": "Wide 24mm", "focal_mm": 24, "fnumber": 2.8}
DATA = Path(__file__).resolve().parent / "data"


def lens_field(width: int = W, height: int = H) -> np.ndarray:
    """ln φ_c (H×W×3) no even polynomial holds: stronger in the lower left, a bump off the
    axis, R falling faster than G, B slower."""
    x = frame_coords(width)[None, :] / width
    y = frame_coords(height)[:, None] / height
    r2 = x * x + y * y
    base = -1.6 * r2 - 0.5 * r2 * r2 - np.maximum(-x, 0) ** 2 * np.maximum(y, 0)
    bump = 0.04 * np.exp(-((x - 0.25) ** 2 + (y + 0.2) ** 2) / 0.01)
    return np.stack([1.25 * base + bump, base, 0.8 * base - bump], axis=-1)


def flat_frames(seed: int = 0) -> list[np.ndarray]:
    lf = lens_field()
    rng = np.random.default_rng(seed)
    out = []
    for g in [(0.06, 0.0), (0.0, -0.05), (-0.04, 0.03)]:
        ramp = g[0] * frame_coords(W)[None, :] / W + g[1] * frame_coords(H)[:, None] / H
        img = 0.4 * np.exp(lf + ramp[..., None]) * np.array([0.9, 1.0, 0.8])
        out.append((img * (1 + 0.01 * rng.standard_normal(img.shape))).astype(np.float32))
    return out


def residual_ev(out: np.ndarray, scene: np.ndarray, without_plane: bool = True) -> np.ndarray:
    """Per channel RMS of log2(out / scene) about its mean (and, by default, without a
    plane: a flat frame cannot tell a lens's own tilt from the wall's gradient), EV."""
    d = np.log(out.astype(np.float64) / scene) / math.log(2)
    h, w = d.shape[:2]
    cols = [np.ones(h * w)] + ([np.tile(frame_coords(w), h), np.repeat(frame_coords(h), w)] if without_plane else [])
    X = np.stack(cols, 1)
    r = []
    for c in range(3):
        v = d[..., c].ravel()
        v = v - X @ np.linalg.lstsq(X, v, rcond=None)[0]
        r.append(math.sqrt(float(np.mean(v * v))))
    return np.array(r)


def learn(db: Path, frames=None) -> None:
    with ProfileStore(db) as st, Processor(Settings(mode="learn", method="flat-field"), store=st) as proc:
        for f in frames if frames is not None else flat_frames():
            proc.process_image(f, lens_key(LENS), where="flat")


@pytest.fixture(scope="module")
def learned(tmp_path_factory) -> Path:
    db = tmp_path_factory.mktemp("grid") / "p.sqlite"
    learn(db)
    return db


def test_flat_frames_learn_a_pooled_grid_that_the_profile_corrects_by(learned):
    with ProfileStore(learned) as st:
        (p,) = st.list()
    assert p.n_frames == 3 and p.grid is not None and p.grid.n == 3 and p.grid.nodes == (33, 22)
    m = p.model(W, H)
    assert isinstance(m, GridFieldModel) and m.grid is not None
    scene = np.full((H, W, 3), 0.3)
    vig = (scene * np.exp(lens_field())).astype(np.float32)
    with_grid = residual_ev(m.correct_image(vig), scene)
    from vigproc.core.correct import correct

    kang_weiss = residual_ev(correct(vig, m), scene)  # the same profile's θ and colour field
    assert with_grid.max() < 0.003, with_grid
    assert kang_weiss.min() > 2 * with_grid.max(), (kang_weiss, with_grid)
    # centred on the optical centre: the corrected centre keeps its level
    c = m.correct_image(np.ones((H, W, 3), np.float32))[H // 2, W // 2]
    np.testing.assert_allclose(c, 1.0, atol=0.01)
    # another resolution of the frame is corrected at its own pixel centres
    big = m.correct_image(np.full((2 * H, 2 * W, 3), 1.0, np.float32))
    np.testing.assert_allclose(big[1::2, 1::2][::2, ::2], m.correct_image(np.ones((H, W, 3), np.float32))[::2, ::2],
                               atol=0.02)


def test_the_api_and_correct_apply_the_stored_grid(learned, tmp_path):
    """The API's correct (the path `correct`, the hot folder and the hook share) applies the
    stored profile's grid."""
    scene = np.full((H, W, 3), 0.3)
    vig = (scene * np.exp(lens_field())).astype(np.float32)
    with Pipeline("correct", store=learned) as vp:
        out, res = vp.process(vig, LENS)
    assert res.source == "stored-profile" and res.applied
    with ProfileStore(learned) as st:
        (p,) = st.list()
    np.testing.assert_array_equal(out, p.model(W, H).correct_image(vig, channel_axis=-1, strength=1.0))
    assert residual_ev(out, scene).max() < 0.003


def test_export_import_round_trip_corrects_the_same_pixels(learned, tmp_path):
    with ProfileStore(learned) as st:
        (p,) = st.list()
    f = tmp_path / "lens.json"
    export_profile(p, f)
    d = json.loads(f.read_text())
    assert d["schema"] == FILE_SCHEMA_GRID and d["grid"]["schema"] == "vigproc.gridpool/1"
    with ProfileStore(tmp_path / "fresh.sqlite") as fresh:
        fresh.import_file(f)
        (q,) = fresh.list()
    assert q.grid is not None and q.grid.n == 3
    vig = (np.full((H, W, 3), 0.3) * np.exp(lens_field())).astype(np.float32)
    with Pipeline("correct", store=learned) as a, Pipeline("correct", store=tmp_path / "fresh.sqlite") as b:
        out_a, _ = a.process(vig, LENS)
        out_b, res_b = b.process(vig, LENS)
    assert res_b.source == "stored-profile"
    np.testing.assert_array_equal(out_a, out_b)
    # the file itself as the profile: the same pixels again
    with Pipeline("correct", profile=str(f)) as c:
        out_c, _ = c.process(vig, LENS)
    np.testing.assert_array_equal(out_a, out_c)


def test_profile_files_3_load_without_grid_and_4_needs_its_schema(learned):
    with ProfileStore(learned) as st:
        (p,) = st.list()
    d = profile_to_dict(p)
    old = {k: v for k, v in d.items() if k != "grid"}
    old["schema"] = FILE_SCHEMA_COLOUR  # as vigproc before grids wrote this profile
    q = profile_from_dict(json.loads(json.dumps(old)))
    assert q.grid is None and q.colour is not None and not isinstance(q.model(W, H), GridFieldModel)
    with pytest.raises(Exception, match="vigproc.profile/4"):  # a /3 file cannot carry a grid
        profile_from_dict({**old, "grid": d["grid"]})
    bad = json.loads(json.dumps(d))
    bad["grid"]["info"][0][0][0] = -1.0
    with pytest.raises(Exception, match="grid"):
        profile_from_dict(bad)


def test_a_store_written_by_vigproc_before_grids_migrates(tmp_path):
    """tests/data/profile_store_v13.sql: a store main's vigproc (schema v13) wrote, one
    colour profile of 3 frames; it opens, migrates, keeps its profile and pools a grid."""
    db = tmp_path / "old.sqlite"
    con = sqlite3.connect(db)
    con.executescript((DATA / "profile_store_v13.sql").read_text())
    con.close()
    con = sqlite3.connect(db)
    assert con.execute("SELECT max(version) FROM schema_version").fetchone()[0] == 13
    assert "grid" not in {r[1] for r in con.execute("PRAGMA table_info(profiles)")}
    con.close()
    with ProfileStore(db) as st:
        assert st.schema_version == SCHEMA_VERSION >= 14
        (p,) = st.list()
        assert p.n_frames == 3 and p.colour is not None and p.grid is None
        before = p.model(W, H)
        assert not isinstance(before, GridFieldModel)
    learn(db)  # the same lens (cam|x1|wide 24mm at 24 mm f/2.8): flat frames add a grid
    with ProfileStore(db) as st:
        (q,) = st.list()
    assert q.n_frames == 6 and q.grid is not None and q.grid.n == 3 and q.colour.n == 6


def test_grid_pool_information_form_and_interpolation():
    rng = np.random.default_rng(1)
    truth = lens_field(40, 27)[::3, ::3]  # any ny×nx×3 field
    grids = [GridField(W, H, truth + 0.01 * rng.standard_normal(truth.shape), np.full(truth.shape, s))
             for s in (0.01, 0.02, 0.04)]
    pool = GridPool.of(grids[0]).add(GridPool.of(grids[1])).add(GridPool.of(grids[2]))
    w = np.array([1 / 0.01**2, 1 / 0.02**2, 1 / 0.04**2])
    want = sum(wi * g.log_field for wi, g in zip(w, grids)) / w.sum()
    f = pool.field(W, H)
    np.testing.assert_allclose(f.log_field, want, atol=1e-12)
    np.testing.assert_allclose(f.sigma, 1 / math.sqrt(w.sum()), rtol=1e-12)
    back = GridPool.from_json(json.loads(json.dumps(pool.to_json())))
    np.testing.assert_array_equal(back.info, pool.info)
    # between two settings: nodewise, values and variances by the weights
    a, b = GridPool.of(grids[0]), GridPool.of(grids[2])
    mid = GridPool.blend([(a, 0.25), (b, 0.75)]).field(W, H)
    np.testing.assert_allclose(mid.log_field, 0.25 * grids[0].log_field + 0.75 * grids[2].log_field, atol=1e-12)
    np.testing.assert_allclose(mid.sigma, math.sqrt(0.25 * 0.01**2 + 0.75 * 0.04**2), rtol=1e-9)
    assert GridPool.blend([(a, 0.5), (None, 0.5)]) is None
    # a grid of other node counts (another frame size of the aspect bin) is resampled
    coarse = GridField(W, H, lens_field(40, 27)[::6, ::6], np.full((5, 7, 3), 0.01))
    both = a.add(GridPool.of(coarse))
    assert both.info.shape == a.info.shape and both.n == 2


@pytest.mark.parametrize("bad", [
    {"schema": "vigproc.gridpool/2", "info": [[[1, 1, 1]] * 2] * 2, "weighted": [[[0, 0, 0]] * 2] * 2, "n": 1},
    {"schema": "vigproc.gridpool/1", "info": [[[1, 1, 1]] * 2] * 2, "weighted": [[[0, 0, 0]] * 3] * 2, "n": 1},
    {"schema": "vigproc.gridpool/1", "info": [[[0, 1, 1]] * 2] * 2, "weighted": [[[0, 0, 0]] * 2] * 2, "n": 1},
    {"schema": "vigproc.gridpool/1", "info": [[[1, 1, 1]] * 2] * 2, "weighted": [[[0, 0, 99]] * 2] * 2, "n": 1},
    {"schema": "vigproc.gridpool/1", "info": [[[1, 1, 1]] * 2] * 2, "weighted": [[[0, 0, 0]] * 2] * 2, "n": 0},
    [1, 2],
])
def test_damaged_grid_pools_are_refused(bad):
    with pytest.raises(ModelError):
        GridPool.from_json(bad)


def test_grid_model_writes_per_plane_gain_maps_that_read_back():
    """``--output-format dng``: the profile's grid as per-plane GainMaps (each CFA phase its
    colour's plane; three planes otherwise), read back by vigproc's own opcode reader."""
    from vigproc.io.dng_opcodes import OpcodeList, parse_opcode_list
    from vigproc.io.dng_vignette import EmbeddedCalibration, model_to_gain_maps

    g = GridField(W, H, lens_field(W, H)[::9, ::9], None)
    m = GridFieldModel(W, H, grid=g)
    for pattern in (None, ((0, 1), (1, 2))):
        maps = model_to_gain_maps(m, cfa_pattern=pattern)
        raw = OpcodeList(tuple(x.to_opcode() for x in maps)).to_bytes()  # the bytes a DNG carries
        cal = EmbeddedCalibration.from_lists([("OpcodeList2" if pattern else "OpcodeList3",
                                               parse_opcode_list(raw, "written"))], "written", cfa_pattern=pattern)
        want = g.log_fields()
        for c in range(3):
            got = -cal.log_gain(W, H, c)
            assert np.abs(got - want[..., c]).max() / math.log(2) < 0.005


def test_dng_output_of_a_grid_profile_reads_back(tmp_path):
    """What ``correct --output-format dng`` writes for a profile with a grid
    (:func:`write_dng_correction` of the profile's model): per-phase GainMaps in
    OpcodeList2 that vigproc's DNG reader gives back as the grid, each colour its plane."""
    import shutil

    from test_colour_dng import CFA_DNG

    if not CFA_DNG.exists():
        pytest.skip(f"{CFA_DNG} is absent (the shared data set)")
    from vigproc.io.dng_vignette import read_embedded, write_dng_correction
    from vigproc.io.metadata import exiftool_path

    try:
        exiftool_path()
    except Exception as exc:  # noqa: BLE001 - any reason exiftool cannot run
        pytest.skip(f"exiftool unavailable: {exc}")
    w, h = 1734, 1156  # the frame rawpy develops
    grid = GridField(w, h, lens_field(w // 10, h // 10)[::4, ::4], None, "flat-field:grid")
    src = tmp_path / "in.dng"
    shutil.copyfile(CFA_DNG, src)
    before = src.read_bytes()
    info = write_dng_correction(src, tmp_path / "out.dng", GridFieldModel(w, h, grid=grid))
    assert src.read_bytes() == before
    assert info["list"] == "OpcodeList2" and info["opcode"]["maps"] == 4
    cal = read_embedded(tmp_path / "out.dng")
    rel = ((np.arange(h // 8) + 0.5) / (h // 8), (np.arange(w // 8) + 0.5) / (w // 8))
    want = grid.log_fields_rel(*rel)
    for c in range(3):
        got = -cal.log_gain(w, h, c, rel=rel)
        assert np.abs(got - want[..., c]).max() / math.log(2) < 0.005


def test_grey_flat_frames_give_a_grid_of_one_field(tmp_path):
    db = tmp_path / "grey.sqlite"
    learn(db, [f[..., 1].copy() for f in flat_frames(seed=4)])
    with ProfileStore(db) as st:
        (p,) = st.list()
    g = p.grid.field(W, H)
    np.testing.assert_array_equal(g.log_field[..., 0], g.log_field[..., 2])
    scene = np.full((H, W), 0.3)
    vig = (scene * np.exp(lens_field()[..., 1])).astype(np.float32)
    out = p.model(W, H).correct_image(vig, channel_axis=None)
    assert out.shape == (H, W)
    assert residual_ev(np.repeat(out[..., None], 3, 2), scene[..., None]).max() < 0.003


def test_correct_command_applies_a_grid_profile_file(learned, tmp_path):
    """``vigproc correct --profile FILE`` with a ``/4`` file: the output is the frame divided
    by the grid (the model's correct_image), not by the Kang-Weiss fit; the input untouched."""
    from conftest import run_cli

    from vigproc.io.image_write import write_image
    from vigproc.io.images import read_image

    with ProfileStore(learned) as st:
        (p,) = st.list()
    f = tmp_path / "lens.json"
    export_profile(p, f)
    scene = np.full((H, W, 3), 0.3)
    vig = (scene * np.exp(lens_field())).astype(np.float32)
    src = tmp_path / "in.tif"
    write_image(src, vig, bit_depth="float")
    before = src.read_bytes()
    r = run_cli("correct", src, "--profile", f, "--output-format", "tiff-float", "-o", tmp_path / "out", "--json")
    assert r.returncode == 0, r.stderr
    (doc,) = json.loads(r.stdout)["results"]
    assert doc["grid_field"] == {"nodes": [33, 22], "source": "flat-field:grid"}  # the record says what divided
    assert src.read_bytes() == before
    (out_path,) = (tmp_path / "out").glob("in*.tif")
    out = read_image(out_path)[0]
    want = p.model(W, H).correct_image(read_image(src)[0])
    np.testing.assert_allclose(out, want, rtol=1e-6, atol=1e-7)
    assert residual_ev(out, scene).max() < 0.003


def test_profiles_between_focal_lengths_interpolate_their_grids_and_lensfun_says_so(learned):
    from dataclasses import replace

    from vigproc.stores import lensfun_io
    from vigproc.stores.profiles import focal_bin, interpolate_profiles

    with ProfileStore(learned) as st:
        (p,) = st.list()
    wide = replace(p, key=replace(p.key, focal_bin=focal_bin(20.0)))
    other = GridPool.of(GridField(W, H, 0.5 * p.grid.field(W, H).log_field, np.full(p.grid.info.shape, 0.001)))
    tele = replace(p, key=replace(p.key, focal_bin=focal_bin(28.0)), grid=other)
    mid = interpolate_profiles([wide, tele], replace(p.key, focal_bin=focal_bin(24.0)), 23.5, 2.8)
    assert mid is not None and mid.grid is not None
    t = (math.log2(23.5) - math.log2(float(wide.key.focal_bin[2:-2]))) / \
        (math.log2(float(tele.key.focal_bin[2:-2])) - math.log2(float(wide.key.focal_bin[2:-2])))
    assert 0 < t < 1
    want = (1 - t) * p.grid.field(W, H).log_field + t * other.field(W, H).log_field
    np.testing.assert_allclose(mid.grid.field(W, H).log_field, want, atol=1e-9)
    assert isinstance(mid.model(W, H), GridFieldModel)
    # one bin without a grid: the interpolated profile has none
    assert interpolate_profiles([wide, replace(tele, grid=None)], mid.key, 23.5, 2.8).grid is None
    notes = lensfun_io.colour_notes([p])
    assert len(notes) == 1 and "grid field" in notes[0] and "cannot be expressed" in notes[0]


def test_batch_learn_carries_each_flat_frames_grid_to_the_store(tmp_path):
    """``vigproc batch --mode learn --method flat-field``: workers measure each frame's grid
    and the client pools it (the workers never write the store)."""
    import shutil
    import subprocess

    from vigproc.frontends import backends as BK
    from vigproc.frontends import batch as B
    from vigproc.io.image_write import write_image

    et = shutil.which("exiftool")
    if et is None:
        pytest.skip("exiftool is needed to give the frames a lens")
    root = tmp_path / "flats"
    root.mkdir()
    for i, f in enumerate(flat_frames(seed=7)):
        write_image(root / f"flat{i}.tif", f, bit_depth="float")
    subprocess.run([et, "-q", "-overwrite_original", "-Make=Cam", "-Model=X1", "-LensModel=Wide 24mm",
                    "-FocalLength=24", "-FNumber=2.8", *map(str, sorted(root.glob("*.tif")))], check=True)
    items, _ = B.collect(root, tmp_path)
    out = tmp_path / "out"
    out.mkdir()
    spec = B.JobSpec(settings=Settings(mode="learn", method="flat-field"), outdir=str(out))
    with ProfileStore(tmp_path / "p.sqlite") as store:
        s = B.run_batch(items, spec, BK.local_backend(1), journal_path=out / B.JOURNAL_NAME, job="t",
                        progress=False, store=store)
        assert s.processed == 3
        (p,) = store.list()
    assert p.n_frames == 3 and p.grid is not None and p.grid.n == 3


def test_raw_flat_frames_keep_their_cfa_planes_grid(tmp_path):
    """RAW flat frames learned per CFA plane: the profile's grid is the planes' fields."""
    import shutil

    pytest.importorskip("rawpy")
    if shutil.which("exiftool") is None:
        pytest.skip("exiftool program not installed")
    import test_cfa_flat as C

    paths = [C.flat_dng(tmp_path / f"flat{i}.dng", seed=20 + i, gradient=g)
             for i, g in enumerate([(0.08, 0.0), (-0.03, 0.07), (0.02, -0.06)])]
    with ProfileStore(tmp_path / "p.sqlite") as store, \
            Processor(Settings(mode="learn", method="flat-field"), store=store) as proc:
        for p in paths:
            proc.process_unwritten(p)
        (prof,) = store.list()
    assert prof.grid is not None and prof.grid.n == 3 and prof.grid.source == "flat-field:cfa-grid"
    m = prof.model(C.W, C.H)
    d = (m.grid.log_fields(C.W, C.H) - C.plane_log_fields()) / math.log(2)
    d -= d.mean(axis=(0, 1))
    assert np.sqrt(np.mean(d * d, axis=(0, 1))).max() < 0.002  # 0.0004-0.0008 EV measured


def test_grid_model_checks_its_input_and_without_a_grid_is_the_plain_model():
    from vigproc.core.correct import correct
    from vigproc.errors import InvalidImageError

    plain = GridFieldModel(W, H, p=(1 / 250**2, 0.0, 1 / 250**2))
    img = np.full((H, W, 3), 0.5, np.float32)
    np.testing.assert_array_equal(plain.correct_image(img), correct(img, plain))
    m = GridFieldModel(W, H, grid=GridField(W, H, lens_field()[::10, ::10]))
    for bad in (np.full((H, W, 3), "x"), np.full((H, W, 3), np.nan, np.float32)):
        with pytest.raises(InvalidImageError):
            m.correct_image(bad)
    with pytest.raises(Exception, match="strength"):
        m.correct_image(img, strength=5.0)
    # channels first, as the API allows: the same pixels
    np.testing.assert_array_equal(np.moveaxis(m.correct_image(np.moveaxis(img, -1, 0), channel_axis=0), 0, -1),
                                  m.correct_image(img))
