"""Benchmark pieces: the radial-gradient-symmetry peer and the benches' scene-prior option."""

import json
import shutil

import numpy as np
import pytest

from benchmarks.peers import estimate_rgs, radial_polynomial
from benchmarks.synthetic import table1_model
from vigproc.io.images import write_image
from vigproc.stores.lensfun import diverse_lenses, pa_field

from conftest import run_cli, textured


def _gain_free_ev(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.std(np.log2(a / b)))


def test_rgs_recovers_a_centred_real_lens():
    """A real lens's centred radial fall-off on a texture without fall-off of its own."""
    h, w = 320, 480
    _, pa = diverse_lenses(1)[0]
    truth = pa_field((h, w), pa.k1, pa.k2, pa.k3)
    base = textured(h, w, seed=3, contrast=0.05)
    m = estimate_rgs(base * truth)
    assert m.method == "rgs"
    assert m.center == (0.0, 0.0) or np.hypot(*m.center) < 1.0  # centred by construction
    err = _gain_free_ev(m.field((h, w)), truth)
    assert err < 0.25 * _gain_free_ev(np.ones_like(truth), truth), err


def test_rgs_sees_no_fall_off_in_a_flat_texture():
    base = textured(320, 480, seed=4, contrast=0.05)
    m = estimate_rgs(base)
    assert float(np.sqrt(np.mean(np.log2(m.field((320, 480))) ** 2))) < 0.05


def test_rgs_polynomial_fits_an_exact_radial_field():
    """log φ = −0.4 r² − 0.1 r⁴ (r in half-diagonals): the fitted even polynomial
    matches it over the frame to within 5 % of its range."""
    h, w = 200, 300
    radius = 0.5 * np.hypot(w, h)
    y, x = np.mgrid[0:h, 0:w]
    r2 = ((x - (w - 1) / 2) ** 2 + (y - (h - 1) / 2) ** 2) / radius**2
    true_log = -0.4 * r2 - 0.1 * r2 * r2
    a = radial_polynomial(np.exp(true_log) * textured(h, w, seed=5, contrast=0.02), work_size=100)
    fit_log = sum(a[i] * r2 ** (i + 1) for i in range(len(a)))
    assert np.max(np.abs(fit_log - true_log)) < 0.05 * np.ptp(true_log)


def test_rgs_cannot_follow_off_centre_vignetting():
    """Its documented limit: Table 1 setting 2 (off-centre, elliptical) is returned centred."""
    truth = table1_model(2)
    m = estimate_rgs(textured(320, 480, seed=6, contrast=0.05) * truth.field())
    assert np.hypot(*m.center) < 0.2 * np.hypot(*truth.center)


def _bench(*args):
    """``vigproc bench ARGS`` in this process (not about the process: main() gives the same
    exit codes and output; a bench through a new process: test_bench_entry)."""
    return run_cli("bench", *args)


def _texture_folder(d, n: int, seed: int):
    """``n`` 16-bit PNG textures without fall-off of their own, in a new folder ``d``."""
    d.mkdir()
    for i in range(n):
        g = textured(160, 240, seed=seed + i, contrast=0.05)
        write_image(d / f"t{i}.png", np.repeat(g[..., None], 3, axis=2).astype(np.float32), bit_depth="uint16")
    return d


@pytest.fixture
def image_folder(tmp_path):
    return _texture_folder(tmp_path / "imgs", 3, seed=10)


def test_bench_lensfun_scene_prior_and_peer(image_folder, tmp_path):
    out = tmp_path / "bench-out" / "lf.json"  # a folder that does not exist yet is made
    r = _bench("lensfun", "--images", image_folder, "--lenses", "2", "--frames-per-lens", "1",
               "--input-transfer", "linear", "--scene-prior", "none", "--methods", "default", "rgs",
               "--json", out)
    assert r.returncode == 0, r.stderr
    assert "scene prior none" in r.stdout and "input transfer linear" in r.stdout
    rows = json.loads(out.read_text())
    assert [row["method"] for row in rows] == ["default", "rgs", "default", "rgs"]


def test_bench_result_file_that_cannot_be_written_is_refused_before_the_run(image_folder, tmp_path):
    r = _bench("synthetic", "--images", image_folder, "--methods", "ga", "--json", tmp_path)
    assert r.returncode == 5 and "it is a folder" in r.stderr and r.stdout == "", r.stderr
    (tmp_path / "file").write_text("")
    r = _bench("lensfun", "--images", image_folder, "--methods", "ga", "--json", tmp_path / "file" / "x.json")
    assert r.returncode == 5 and "cannot create output folder" in r.stderr and r.stdout == "", r.stderr


@pytest.mark.parametrize("content, message", [(None, "cannot read"), ("{", "not JSON"),
                                              ('{"schema": "x"}', "not a scene fall-off")])
def test_bench_bad_scene_prior_is_a_clear_error(image_folder, tmp_path, content, message):
    path = tmp_path / "scene.json"
    if content is not None:
        path.write_text(content)
    r = _bench("synthetic", "--images", image_folder, "--methods", "default", "--scene-prior", path)
    assert r.returncode != 0 and message in r.stderr and "Traceback" not in r.stderr
    assert r.stdout == ""  # refused before any figure is printed


def test_bench_profile_reports_when_profiles_become_trusted():
    from benchmarks import profile as P
    from vigproc.core.estimate import estimate

    ims = [textured(160, 240, seed=20 + i, contrast=0.05) for i in range(4)]
    rows, trust = P.run(ims, lambda v: estimate(v, "robust", channel_axis=None), n_lenses=2, counts=(1, 4), store=True)
    assert {r.pooling for r in rows} >= {"information", "store"}
    assert trust.n_lenses == 2 and trust.max_frames == 4 and 0 <= trust.n_trusted <= 2
    assert trust.single_frame_median_ev > 0
    if trust.n_trusted:  # trusted needs >= 3 frames
        assert 3 <= trust.median_frames <= 4


@pytest.fixture
def clean_folder(tmp_path):
    return _texture_folder(tmp_path / "clean", 10, seed=30)


def test_bench_profile_clean_learns_through_a_store(tmp_path):
    """``vigproc bench profile-clean`` on a folder of clean textures: a profile per lens
    through a real store, the single-frame estimate beside it, trust reported."""
    d = tmp_path / "bases"
    d.mkdir()
    for i in range(3):
        g = textured(320, 480, seed=40 + i, contrast=0.05)
        write_image(d / f"t{i}.png", np.repeat(g[..., None], 3, axis=2).astype(np.float32), bit_depth="uint16")
    out = tmp_path / "pc.json"
    r = _bench("profile-clean", "--images", d, "--min-long-side", "64", "--lenses", "2", "--counts", "1", "3",
               "--json", out)
    assert r.returncode == 0, r.stderr
    got = json.loads(out.read_text())
    rows = {(row["method"], row["n_frames"]): row for row in got["rows"]}
    assert set(rows) == {("single frame (default)", 1), ("store", 1), ("store", 3)}
    assert all(row["n_lenses"] == 2 and 0 <= row["median_ev"] < 0.5 for row in rows.values())
    assert got["trust"]["n_lenses"] == 2 and "trusted (2 sigma <" in r.stdout
    r = _bench("profile-clean", "--images", d, "--min-long-side", "64", "--counts", "5")
    assert r.returncode == 2 and "need as many bases" in r.stderr and "Traceback" not in r.stderr


def test_prior_fit_lens_family_writes_the_shipped_kind(tmp_path):
    from vigproc.core.lensfamily import LensFamily, profile_family

    out = tmp_path / "family.json"
    r = run_cli("prior", "fit-lens-family", "-o", out, "--components", "3")
    assert r.returncode == 0, r.stderr
    fam = LensFamily.from_dict(json.loads(out.read_text()))
    shipped = profile_family()
    assert fam.n_components == 3 and "reconstruction error by components" in r.stdout
    # the shipped family is this command's output on the bundled lensfun database
    np.testing.assert_allclose(fam.components, shipped.components, atol=1e-7)
    np.testing.assert_allclose(fam.reconstruction_by_k, shipped.reconstruction_by_k, atol=1e-6)


def test_prior_fit_scene_writes_a_loadable_falloff(clean_folder, tmp_path):
    from vigproc.core.scene import SceneFalloff

    command = "fit-scene"
    out = tmp_path / "out" / "falloff.json"
    out.parent.mkdir()
    r = run_cli("prior", command, clean_folder, "-o", out, "--input-transfer", "linear")
    assert r.returncode == 0, r.stderr
    f = SceneFalloff.from_dict(json.loads(out.read_text()))
    assert f.n_images == 10 and command in f.source and "--input-transfer linear" in f.source
    # textures without fall-off of their own: a weak mean fall-off
    assert f.field_ev_rms < 0.1


def test_prior_fit_needs_ten_photos(clean_folder, tmp_path):
    for p in sorted(clean_folder.iterdir())[:2]:
        p.unlink()
    r = run_cli("prior", "fit-scene", clean_folder, "-o", tmp_path / "b.json")
    assert r.returncode != 0 and "at least 10 photos" in r.stderr and "Traceback" not in r.stderr
    assert not (tmp_path / "b.json").exists()


def test_real_bench_pairs_and_photographs(tmp_path):
    """``vigproc bench real``: NAME_vig with NAME (or NAME without its digits) is a pair
    with a known field; other images are photographs; the field of a flat white frame
    is found, and a frame without vignetting of its own has no true fall-off."""
    from benchmarks.real import find_inputs, run_pair
    from vigproc.core.estimate import estimate
    from vigproc.core.model import VignettingModel
    from vigproc.pipeline.processor import IMAGE_SUFFIXES

    h, w = 160, 240
    truth = table1_model(1).rescale(w, h).field()
    white = np.full((h, w, 3), 0.8, dtype=np.float32)
    base = textured(h, w, seed=7, contrast=0.05)
    write_image(tmp_path / "white.tif", white, bit_depth="float")
    write_image(tmp_path / "white2_vig.tif", white * truth[..., None].astype(np.float32), bit_depth="float")
    write_image(tmp_path / "scene.tif", np.repeat(base[..., None], 3, 2).astype(np.float32), bit_depth="float")
    write_image(tmp_path / "scene_vig.tif", np.repeat((base * truth)[..., None], 3, 2).astype(np.float32),
                bit_depth="float")
    write_image(tmp_path / "photo.tif", np.repeat((base * truth)[::-1, :, None], 3, 2).astype(np.float32),
                bit_depth="float")
    write_image(tmp_path / "white2_Est_truth.tif", truth.astype(np.float32), bit_depth="float")
    pairs, photos = find_inputs(tmp_path, IMAGE_SUFFIXES)
    assert sorted((v.name, c.name) for v, c in pairs) == [("scene_vig.tif", "scene.tif"),
                                                          ("white2_vig.tif", "white.tif")]
    assert [p.name for p in photos] == ["photo.tif"]
    flat = run_pair(white[..., 0] * truth, white[..., 0], "white2_vig", "default",
                    lambda im: estimate(im, channel_axis=None))
    assert flat.uncorrected_ev > 0.3 and flat.true_corner_ev < -0.5
    # no correction scores exactly the uncorrected figure
    none = run_pair(base * truth, base, "scene_vig", "none", lambda im: VignettingModel.identity(w, h))
    assert none.error_ev == pytest.approx(none.uncorrected_ev)
    # the exact field scores (nearly) zero
    exact = run_pair(base * truth, base, "scene_vig", "truth", lambda im: table1_model(1).rescale(w, h))
    assert exact.error_ev < 0.01
    r = run_cli("bench", "real", "--images", tmp_path, "--methods", "default", "--json", tmp_path / "r.json")
    assert r.returncode == 0, r.stderr
    rows = json.loads((tmp_path / "r.json").read_text())
    assert len(rows) == 3 and "2 pairs and 1 photographs" in r.stdout


def test_bench_clean_scores_methods_on_crops_of_large_frames(tmp_path):
    from benchmarks.clean import HEIGHT, WIDTH, crop_base

    folder = tmp_path / "frames"
    folder.mkdir()
    for i in range(3):  # large vignetting-free frames (a linear TIFF each), and one too small to use
        write_image(folder / f"f{i}_linear.tif", textured(900, 1350, seed=40 + i, contrast=0.1).astype(np.float32),
                    bit_depth="float")
    write_image(folder / "small_linear.tif", textured(300, 450, seed=1).astype(np.float32), bit_depth="float")
    crop = crop_base(textured(1350, 900, seed=1))  # portrait turned landscape, 40 % of each side
    assert crop.shape == (HEIGHT, WIDTH)
    out = tmp_path / "clean.json"
    r = _bench("clean", "--images", folder, "--lenses", "2", "--methods", "lens-family", "lens-family+exif",
               "rgs", "--no-table1", "--json", out)
    assert r.returncode == 0, r.stderr
    doc = json.loads(out.read_text())
    assert len(doc["bases"]) == 3 and "small_linear.tif" not in doc["bases"]
    fields = {row["method"]: row for row in doc["results"] if "fields" in row}
    assert set(fields) == {"lens-family", "lens-family+exif", "rgs"}
    for row in fields.values():
        assert row["n_fields"] == 2 and row["n_frames"] == 6
        assert row["median_ev"] < row["uncorrected_ev"]
    assert 0.0 <= fields["lens-family"]["within_1sigma"] <= fields["lens-family"]["within_2sigma"] <= 1.0
    assert "no harm" in r.stdout and "rgs-c++" not in r.stdout


def test_bench_clean_base_falloff_scores_table1_against_bases_that_carry_a_lens(tmp_path):
    """``--base-falloff`` gives each base a test lens's fall-off (as BSDS's film scans carry
    their cameras'): only Table 1's fields are scored, each with the paper's PSNR, and the
    bases' own fall-off is now something a correction removes (no harm is no longer 0)."""
    folder = tmp_path / "frames"
    folder.mkdir()
    for i in range(2):
        write_image(folder / f"f{i}_linear.tif", textured(900, 1350, seed=50 + i, contrast=0.1).astype(np.float32),
                    bit_depth="float")
    runs = {}
    for flag in ((), ("--base-falloff",)):
        out = tmp_path / f"clean{len(flag)}.json"
        r = _bench("clean", "--images", folder, "--lenses", "2", "--grey", "--methods", "lens-family", *flag,
                   "--json", out)
        assert r.returncode == 0, r.stderr
        runs[flag] = json.loads(out.read_text())["results"]
    plain, carried = runs[()], runs[("--base-falloff",)]
    assert [row["fields"] for row in carried if "fields" in row] == ["table1-1", "table1-2", "table1-3"]
    assert {row["fields"] for row in plain if "fields" in row} == {"lensfun", "table1-1", "table1-2", "table1-3"}
    for row in (r for r in plain + carried if "fields" in r):
        assert 5.0 < row["psnr_db"] < 80.0, row
    def worst_harm(rows):
        return next(r for r in rows if "worst_ev" in r)["worst_ev"]

    assert worst_harm(carried) > worst_harm(plain)
    r = _bench("clean", "--images", folder, "--base-falloff", "--no-table1")
    assert r.returncode == 2 and "--base-falloff" in r.stderr and "Traceback" not in r.stderr


def test_bench_profile_flat_learns_a_white_wall(tmp_path):
    """``vigproc bench profile-flat``: three unevenly lit shots of a vignetted white frame
    give a trusted flat-field profile close to the field; no white pairs is a usage error."""
    from vigproc.stores.lensfun import diverse_lenses, pa_field

    d = tmp_path / "flat"
    d.mkdir()
    _, pa = diverse_lenses(1)[0]
    white = np.full((120, 180), 0.5)
    for name, img in (("white", white), ("white1_vig", white * pa_field((120, 180), pa.k1, pa.k2, pa.k3))):
        write_image(d / f"{name}.png", np.repeat(img[..., None], 3, axis=2).astype(np.float32), bit_depth="uint16")
    out = tmp_path / "flat.json"
    r = _bench("profile-flat", "--images", d, "--input-transfer", "linear", "--methods", "flat-field", "--json", out)
    assert r.returncode == 0, r.stderr
    (row,) = json.loads(out.read_text())
    assert row["method"] == "flat-field" and row["trusted"]
    assert row["error_ev"] < 0.1 * row["uncorrected_ev"], row
    r = _bench("profile-flat", "--images", tmp_path / "nowhere")
    assert r.returncode == 2 and "no white pairs" in r.stderr and "Traceback" not in r.stderr


def test_bench_learn_times_one_more_frame_in_a_new_process():
    """The learn benchmark fills a store, learns one more frame warm and in a new
    process, and skips a frame that cannot be estimated instead of failing."""
    from benchmarks.learn import learn_speed
    from conftest import coloured_scene

    _, pa = diverse_lenses(1)[0]
    field = pa_field((160, 240), pa.k1, pa.k2, pa.k3)
    frames = [coloured_scene(160, 240, seed=s) * field[..., None] for s in range(3)]
    frames.insert(1, np.zeros((160, 240, 3)))  # blank: no positive pixel
    r = learn_speed(frames, stored=3, rounds=1)
    assert r.stored == 3 and r.rounds == 1
    assert 0 < r.warm_ms and 0 < r.new_process_learn_ms <= r.new_process_learn_ms_max
    assert r.new_process_import_ms > 0
    with pytest.raises(ValueError, match="no frame"):
        learn_speed([np.zeros((160, 240, 3))], stored=1, rounds=1)
    square = [coloured_scene(180, 240, seed=s) for s in range(2)]  # 4:3 frames learn into a 4:3 profile
    assert learn_speed(square, stored=1, rounds=1).new_process_learn_ms > 0


def test_bench_scene_scatter_writes_what_pooling_reads(tmp_path):
    """The scenes' scatter from vignetting-free frames, in the shipped form: pooling reads
    it in any family; fewer than 10 frames is a clear error."""
    from vigproc.core.lensfamily import profile_family

    folder = tmp_path / "frames"
    folder.mkdir()
    for i in range(10):
        write_image(folder / f"f{i}_linear.tif", textured(700, 1050, seed=60 + i, contrast=0.1).astype(np.float32),
                    bit_depth="float")
    out = tmp_path / "scatter.json"
    r = _bench("scene-scatter", "-o", out, "--images", folder)
    assert r.returncode == 0, r.stderr
    doc = json.loads(out.read_text())
    assert doc["frames"] == 10 and "bench scene-scatter" in doc["source"]
    fam = profile_family()
    S = np.asarray(doc["covariance"])
    C = np.asarray(doc["components"])
    np.testing.assert_allclose(C, fam.components, atol=1e-7)
    assert S.shape == (3, 3) and np.all(np.linalg.eigvalsh(S) > 0)
    (folder / "f9_linear.tif").unlink()
    r = _bench("scene-scatter", "-o", tmp_path / "few.json", "--images", folder)
    assert r.returncode != 0 and "at least 10" in r.stderr and "Traceback" not in r.stderr


def test_bench_learn_command_prints_and_writes_its_figures(tmp_path):
    out = tmp_path / "learn.json"
    r = _bench("learn", "--stored", "2", "--rounds", "1", "--json", out)
    assert r.returncode == 0, r.stderr
    assert "new process, the learn" in r.stdout
    doc = json.loads(out.read_text())
    assert doc["stored"] == 2 and doc["rounds"] == 1 and doc["new_process_learn_ms"] > 0


@pytest.mark.parametrize("method", ["default", "lens-family"])
def test_bench_estimators_are_the_products_own(method):
    """A bench scores what ``vigproc.estimate`` returns: clipped highlights masked the same
    way (a frame with a burnt-out patch), the same model to the bit."""
    import vigproc
    from benchmarks.cli._common import estimator

    frame = np.stack([textured(160, 240, seed=60 + k, contrast=0.1) for k in range(3)], axis=-1)
    frame = frame * pa_field((160, 240), -0.4, 0.1, 0.0)[..., None]
    frame[10:40, 150:200] = frame.max()  # 3.9 % of the frame burnt out, in every channel
    ours = estimator(method)(frame).log_field((160, 240))
    product = vigproc.estimate(frame, method, channel_axis=-1).log_field((160, 240))
    assert np.array_equal(ours, product)


@pytest.mark.skipif(shutil.which("exiftool") is None, reason="exiftool program not installed")
def test_bench_exif_returns_both_figures(shared_data) -> None:
    from benchmarks.io import bench_exif

    paths = sorted((shared_data / "jpeg_exif" / "exiftool-stubs").glob("*.jpg"))[:4]
    if not paths:
        pytest.skip("exiftool-stubs absent")
    res = bench_exif(paths)
    assert res["n_files"] == len(paths)
    assert res["batch_ms_per_file"] > 0 and res["per_process_ms_per_file"] > 0
    # A process per file pays the Perl start-up every time.
    assert res["per_process_ms_per_file"] > res["batch_ms_per_file"]
