"""Hand-offs between commands, tools and files, as users make them: each test is a bug
found by using vigproc from its README and docs, fixed, and kept from coming back."""

from __future__ import annotations

import numpy as np
import pytest

from vigproc.io.exif import lens_key_from_metadata


# ------------------------------------------------------------------ the right lens
def test_a_described_lens_never_pools_into_the_profile_of_unknown_lenses(tmp_path) -> None:
    """A lens EXIF only describes ("24-70mm") is keyed by that description; the profile
    of the body's undescribed lenses ("?": any lens, frames of several) is not its own,
    in a new store or an old one, so it neither learns into it nor is corrected by it."""
    from vigproc.core.normalised import denormalise
    from vigproc.stores.profiles import ProfileKey, ProfileStore

    body = {"EXIF:Make": "Canon", "EXIF:Model": "Canon EOS 5D", "EXIF:FocalLength": 50, "EXIF:FNumber": 2.8}
    unknown = lens_key_from_metadata({**body, "EXIF:LensModel": "----"})
    described = lens_key_from_metadata({**body, "EXIF:LensModel": "24-70mm"})
    assert unknown.lens is None and described.lens == "24-70mm"
    theta = np.array([0.02, -0.01, 0.9, 0.02, 0.85, 0.05, 0.1, -0.05, 0.02, 0.0, 0.0, 0.0])
    with ProfileStore(tmp_path / "p.sqlite") as store:
        key = store.key_for(unknown, 3000, 2000)
        assert key.lens_id.endswith("|?")
        for _ in range(4):
            store.learn(key, denormalise(theta, np.diag(np.full(12, 1e-6)), 3000, 2000, method="robust"))
        assert store.lookup(unknown, 3000, 2000) is not None
        assert store.key_for(described, 3000, 2000).lens_id == described.lens_id()
        assert store.lookup(described, 3000, 2000) is None


def _textured_jpeg(path, w: int = 360, h: int = 240, *tags: str, seed: int = 3):
    """A textured JPEG with a radial fall-off, its EXIF written by the exiftool program."""
    import subprocess

    import OpenImageIO as oiio

    rng = np.random.default_rng(seed)
    y, x = np.mgrid[0:h, 0:w]
    r2 = ((x - w / 2) ** 2 + (y - h / 2) ** 2) / ((w / 2) ** 2 + (h / 2) ** 2)
    base = 0.55 + 0.25 * rng.random((h, w, 1)) + 0.1 * np.sin(x / 7.0)[..., None]
    arr = np.clip(255 * base * (1 - 0.35 * r2)[..., None], 0, 255).astype(np.uint8).repeat(3, axis=2)
    out = oiio.ImageOutput.create(str(path))
    assert out.open(str(path), oiio.ImageSpec(w, h, 3, "uint8")), out.geterror()
    assert out.write_image(arr) and out.close()
    if tags:
        subprocess.run(["exiftool", "-q", "-m", "-overwrite_original", *tags, str(path)], check=True,
                       capture_output=True)
    return path


def _tag(paths, *tags: str) -> list[str]:
    """TAGS written into every one of PATHS by one exiftool run (one start, not one a file)."""
    import subprocess

    paths = [str(p) for p in paths]
    subprocess.run(["exiftool", "-q", "-m", "-overwrite_original", *tags, *paths], check=True, capture_output=True)
    return paths


def _tag_each(*jobs, config=None) -> None:
    """Each job's (PATHS, TAGS) written by one exiftool run for all the jobs (``-execute``
    between them), CONFIG its tag definitions."""
    import subprocess

    args = ["exiftool", *(["-config", str(config)] if config else [])]
    for i, (paths, tags) in enumerate(jobs):
        args += [*(["-execute"] if i else []), *tags, *map(str, paths)]
    subprocess.run([*args, "-common_args", "-q", "-m", "-overwrite_original"], check=True, capture_output=True)


def _cli(*args: str, env: dict | None = None):
    """``vigproc ARGS`` run in this process (conftest's ``run_cli``: its exit code, stdout and
    stderr as a subprocess's), ENV set for the call: these tests are about what the commands
    write and read, not about the process (a new one costs about a second of start-up); the
    one test about a killed process starts its own."""
    import os

    from conftest import run_cli

    env = {"VIGPROC_HOOK_SERVER": "off", **(env or {})}
    saved = {k: os.environ.get(k) for k in env}
    os.environ.update(env)
    try:
        return run_cli(*args)
    finally:
        for k, v in saved.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v


@pytest.mark.skipif(__import__("shutil").which("exiftool") is None, reason="exiftool program not installed")
def test_profile_learn_refuses_an_unnamed_lens_on_an_interchangeable_lens_body(tmp_path) -> None:
    """`profile learn` pooled frames whose EXIF names no lens on an EOS 6D under
    "canon|canon eos 6d|?", a profile of every lens that body wore, which `correct` then
    applied to any of them once trusted; the hot folder refuses such frames. Learn mode
    now refuses them too, with the reason, and pools nothing; a named lens still learns."""
    from vigproc.stores.profiles import ProfileStore

    body = ("-Make=Canon", "-Model=Canon EOS 6D", "-FocalLength=50", "-FNumber=2.8")
    bare = _textured_jpeg(tmp_path / "bare.jpg", 360, 240)
    named = _textured_jpeg(tmp_path / "named.jpg", 360, 240)
    _tag_each(([bare], body), ([named], (*body, "-LensModel=EF50mm f/1.8 STM")))
    db = tmp_path / "p.sqlite"
    p = _cli("profile", "--profile-db", str(db), "learn", str(bare), str(named))
    assert p.returncode == 1, p.stdout + p.stderr
    assert "interchangeable lenses" in p.stderr and "Traceback" not in p.stderr
    assert "1 frame learned, 1 failed" in p.stdout
    with ProfileStore(db) as store:
        ids = {pr.key.lens_id for pr in store.list()}
    assert ids == {"canon|canon eos 6d|ef50mm f/1.8 stm"}


# ------------------------------------------------------------------ profiles that travel
@pytest.mark.skipif(__import__("shutil").which("exiftool") is None, reason="exiftool program not installed")
def test_an_imported_trusted_profile_keeps_its_frames_when_it_learns_one_more(tmp_path) -> None:
    """A trusted profile exported from one store and imported into another is the prior
    of the frames learned there: one more frame of the lens left it as one frame's
    estimate (untrusted, σ of a single frame) because the pooled refit saw only the frames
    whose evidence the new store holds. It must learn as the original store learns."""
    from vigproc.stores.profiles import ProfileStore

    tags = ("-Make=Canon", "-Model=Canon EOS 6D", "-LensModel=EF50mm f/1.8 STM", "-FocalLength=50",
            "-FNumber=2.8")
    *frames, extra = _tag([_textured_jpeg(tmp_path / f"f{i}.jpg", 360, 240, seed=i) for i in range(4)]
                          + [_textured_jpeg(tmp_path / "extra.jpg", 360, 240, seed=99)], *tags)
    a, b, exported = tmp_path / "a.sqlite", tmp_path / "b.sqlite", tmp_path / "lens.json"
    assert _cli("profile", "--profile-db", str(a), "learn", *frames).returncode == 0
    with ProfileStore(a) as store:
        (before,) = store.list()
    assert before.trusted, before
    assert _cli("profile", "--profile-db", str(a), "export", "0", str(exported)).returncode == 0
    assert _cli("profile", "--profile-db", str(b), "import", str(exported)).returncode == 0
    for db in (a, b):
        p = _cli("profile", "--profile-db", str(db), "learn", extra)
        assert p.returncode == 0, p.stderr
    with ProfileStore(a) as sa, ProfileStore(b) as sb:
        (here,), (there,) = sa.list(), sb.list()
    assert here.n_frames == there.n_frames == 5
    assert there.trusted, there
    assert there.field_sigma_ev < 2 * here.field_sigma_ev


# ------------------------------------------------------------------ metadata kept
@pytest.mark.skipif(__import__("shutil").which("exiftool") is None, reason="exiftool program not installed")
@pytest.mark.parametrize("fmt, ext", [("auto", ".jpg"), ("tiff16", ".tif")])
def test_an_output_vigproc_corrected_is_not_corrected_again(tmp_path, fmt, ext) -> None:
    """An output of `correct` fed back in (a hot folder whose output lies in its input, a
    user correcting a folder twice) had its fall-off removed a second time: its own
    XMP-vigproc record says it was corrected, and is now read as the camera's flags are.
    lensfun's calibration of the sample's lens was applied twice (0.70 EV, then 0.70 EV)."""
    import json
    from pathlib import Path

    sample = Path(__file__).resolve().parents[1] / "vigproc/data/samples/kodim13_vignetted.jpg"
    first = _cli("correct", str(sample), "-o", str(tmp_path / "a"), "--output-format", fmt, "--profile", "lensfun",
                 env={"VIGPROC_PROFILE_DB": str(tmp_path / "p.sqlite")})
    assert first.returncode == 0 and "fall-off removed" in first.stdout, first.stdout + first.stderr
    (out,) = (tmp_path / "a").glob(f"*.corrected{ext}")
    again = _cli("correct", str(out), "-o", str(tmp_path / "b"), "--output-format", fmt, "--profile", "lensfun",
                 env={"VIGPROC_PROFILE_DB": str(tmp_path / "p.sqlite")})
    assert again.returncode == 0, again.stderr
    assert "not corrected: vigproc already corrected" in again.stdout, again.stdout
    (record,) = (tmp_path / "b").glob("*.vigproc.json")
    assert json.loads(record.read_text())["applied"] is False


def test_the_vigproc_record_is_read_like_a_cameras_flag() -> None:
    from vigproc.io.incamera import from_tags

    assert from_tags({"Make": "Canon", "XMP:Applied": True}).evidence == "XMP-vigproc:Applied"
    assert from_tags({"Make": "Canon", "XMP:Applied": False}) is None
    assert from_tags({"Make": "Canon"}) is None


@pytest.mark.skipif(__import__("shutil").which("exiftool") is None, reason="exiftool program not installed")
def test_profile_learn_refuses_frames_already_corrected(tmp_path) -> None:
    """`profile learn` pooled a phone's JPEG and an output vigproc had corrected (their
    fall-off is gone: they pull the profile towards a flat field), which the hot folder
    refuses; learn mode now refuses them too, with the reason."""
    from vigproc.io.exiftool_process import CONFIG_FILE
    from vigproc.stores.profiles import ProfileStore

    phone = _textured_jpeg(tmp_path / "phone.jpg", 360, 240)
    body = ("-Make=Canon", "-Model=Canon EOS 6D", "-LensModel=EF50mm f/1.8 STM", "-FocalLength=50", "-FNumber=2.8")
    done = _textured_jpeg(tmp_path / "done.jpg", 360, 240)
    fine = _textured_jpeg(tmp_path / "fine.jpg", 360, 240, seed=5)
    _tag_each(([phone], ("-Make=Apple", "-Model=iPhone 6", "-LensModel=iPhone 6 back camera 4.15mm f/2.2",
                         "-FocalLength=4.15", "-FNumber=2.2")),
              ([done], (*body, "-XMP-vigproc:Applied=True")),  # the record correct writes
              ([fine], body), config=CONFIG_FILE)
    db = tmp_path / "p.sqlite"
    p = _cli("profile", "--profile-db", str(db), "learn", str(phone), str(done), str(fine))
    assert p.returncode == 1, p.stdout + p.stderr
    assert "a phone's JPEG" in p.stderr and "vigproc already corrected it" in p.stderr, p.stderr
    assert "1 frame learned, 2 failed" in p.stdout
    with ProfileStore(db) as store:
        assert [pr.n_frames for pr in store.list()] == [1]


# ------------------------------------------------------------------ corrected files opened by the next tool
def _vignetting_opcodes(path) -> list[tuple[str, str]]:
    from vigproc.io.dng_vignette import read_opcode_lists

    return [(name, type(op).__name__) for name, lst in read_opcode_lists(path) for _, op in lst.decoded()]


@pytest.mark.skipif(__import__("shutil").which("exiftool") is None, reason="exiftool program not installed")
def test_a_dng_output_carries_one_vignetting_correction_not_the_cameras_and_ours(tmp_path) -> None:
    """`correct --output-format dng` appended its correction to the DNG's own opcodes: a
    camera's FixVignetteRadial stayed beside the stored profile's GainMaps, and an output fed
    back in got a second set of GainMaps (8, then 12: a raw converter applies every one),
    while the TIFF of the same frame is corrected once (LibRaw ignores the opcodes). The
    new correction now replaces the file's vignetting opcodes; the camera's others stay."""
    import sys
    from pathlib import Path

    sys.path.insert(0, str(Path(__file__).resolve().parent))
    from dngfixture import make_dng

    from vigproc.core.model import VignettingModel
    from vigproc.io.dng_opcodes import Opcode, OpcodeList
    from vigproc.io.dng_vignette import model_to_radial, read_opcode_lists

    w, h = 256, 192
    f = 0.9 * np.hypot(w, h) / 2
    lens = VignettingModel(w, h, center=(6, -4), p=(f**-2, 0, f**-2), alpha=(0.02, 0.01, 0, 0, 0, 0, 0))
    y, x = np.mgrid[0:h, 0:w] / max(w, h)
    for i, g in enumerate([(0.05, 0.0), (0.0, -0.04), (-0.03, 0.03)]):  # three walls, lit a little unevenly
        make_dng(tmp_path / f"wall{i}.dng", width=w, height=h, field=lens.field(), noise=0.001, seed=i,
                 scene=np.full((h, w), 0.55) * (1 + g[0] * (x - 0.5) + g[1] * (y - 0.4)))
    camera = Opcode(77, 0x01040000, 1, b"camera's own")  # an opcode vigproc does not know: kept
    shot = tmp_path / "shot.dng"
    make_dng(shot, width=w, height=h, field=lens.field(), noise=0.001, seed=7, opcode_lists={
        3: OpcodeList((camera, model_to_radial(lens).opcode.to_opcode())).to_bytes()})
    db = tmp_path / "p.sqlite"
    p = _cli("profile", "--profile-db", str(db), "learn", "--method", "flat-field", *map(str, sorted(tmp_path.glob("wall*.dng"))))
    assert p.returncode == 0, p.stdout + p.stderr
    out = _cli("correct", str(shot), "-o", str(tmp_path / "a"), "--profile-db", str(db), "--no-learn",
               "--output-format", "dng")
    assert out.returncode == 0 and "stored-profile" in out.stdout, out.stdout + out.stderr
    (first,) = (tmp_path / "a").glob("*.dng")
    ops = _vignetting_opcodes(first)
    assert ops == [("OpcodeList2", "GainMap")] * 4, ops  # the profile's per-plane maps, and nothing else
    assert camera.to_bytes() in [o.to_bytes() for o in dict(read_opcode_lists(first))["OpcodeList3"]]
    again = _cli("correct", str(first), "-o", str(tmp_path / "b"), "--profile-db", str(db), "--no-learn",
                 "--output-format", "dng")
    assert again.returncode == 0, again.stdout + again.stderr
    (second,) = (tmp_path / "b").glob("*.dng")
    assert _vignetting_opcodes(second) == ops


# ------------------------------------------------------------------ hostile profile files
@pytest.fixture(scope="module")
def grid_profile_file(tmp_path_factory):
    """A `vigproc.profile/4` file of a lens learned from three flat frames, and a frame of it."""
    tmp_path = tmp_path_factory.mktemp("gridfile")
    import json

    import OpenImageIO as oiio
    from test_profile_grid import LENS, flat_frames, learn, lens_field

    from vigproc.stores.profiles import ProfileStore, export_profile

    db = tmp_path / "grid.sqlite"
    learn(db)
    with ProfileStore(db) as st:
        (p,) = st.list()
    f = tmp_path / "lens.json"
    export_profile(p, f)
    h, w = lens_field().shape[:2]
    frame = tmp_path / "frame.tif"
    out = oiio.ImageOutput.create(str(frame))
    assert out.open(str(frame), oiio.ImageSpec(w, h, 3, "float"))
    assert out.write_image((0.3 * np.exp(lens_field())).astype(np.float32)) and out.close()
    assert LENS and flat_frames
    return json.loads(f.read_text()), frame


@pytest.mark.parametrize("ny, nx, ok", [(22, 33, True), (21, 33, True), (33, 33, False), (33, 22, False),
                                        (2, 129, False)])
def test_a_profile_file_whose_grid_is_of_another_frame_shape_is_refused(grid_profile_file, tmp_path, ny, nx,
                                                                         ok) -> None:
    """A `/4` file of a 3:2 profile whose grid has the nodes of a square, a portrait or a strip
    frame was applied: the grid (nodes on the frame's edges) stretched over the 3:2 frame, a
    wrong correction written with exit 0. Such a file is now refused, by `correct --profile
    FILE` and by `profile import`, with the reason; a grid whose short side rounds one node
    differently (a frame of the same aspect) is still resampled and applied."""
    import json

    d, frame = grid_profile_file
    d = json.loads(json.dumps(d))  # this test's own copy
    assert d["aspect"] == "3:2" and np.shape(d["grid"]["info"]) == (22, 33, 3)
    for k in ("info", "weighted"):  # nearest node: the same field, other node counts
        a = np.asarray(d["grid"][k])
        d["grid"][k] = a[np.linspace(0, 21, ny).round().astype(int)][:, np.linspace(0, 32, nx).round().astype(int)].tolist()
    bad = tmp_path / "odd.json"
    bad.write_text(json.dumps(d))
    p = _cli("correct", str(frame), "-o", str(tmp_path / "out"), "--profile", str(bad),
             env={"VIGPROC_PROFILE_DB": str(tmp_path / "p.sqlite")})
    i = _cli("profile", "--profile-db", str(tmp_path / "b.sqlite"), "import", str(bad))
    if ok:
        assert p.returncode == 0 and "fall-off removed" in p.stdout, p.stdout + p.stderr
        assert i.returncode == 0, i.stderr
        return
    assert p.returncode != 0 and i.returncode != 0, p.stdout + p.stderr + i.stderr
    for r in (p, i):
        assert "grid" in r.stderr and "3:2" in r.stderr and "Traceback" not in r.stderr, r.stderr
    assert not list((tmp_path / "out").glob("*.tif"))


# ------------------------------------------------------------------ what `profile show` says
@pytest.mark.skipif(__import__("shutil").which("exiftool") is None, reason="exiftool program not installed")
def test_profile_show_says_a_flat_field_profile_corrects_the_cast_its_walls_show(tmp_path) -> None:
    """Three tinted wall frames learned with `--method flat-field`: `profile show` said
    "this lens shows a corner cast ...; reported, not corrected" while `correct` divides
    every channel by the profile's measured field, which removes that very cast (the
    corrected frame's corners are one colour with its centre). It now says the profile
    corrects it (`--json`: `colour_cast.corrected`)."""
    import json

    import OpenImageIO as oiio
    from test_profile_grid import flat_frames, lens_field

    tags = ("-Make=Canon", "-Model=Canon EOS 6D", "-LensModel=EF24mm f/2.8 IS USM", "-FocalLength=24", "-FNumber=2.8")

    def tif(path, arr):
        out = oiio.ImageOutput.create(str(path))
        assert out.open(str(path), oiio.ImageSpec(arr.shape[1], arr.shape[0], 3, "float"))
        assert out.write_image(arr.astype(np.float32)) and out.close()
        return path

    *walls, scene = _tag([tif(tmp_path / f"wall{i}.tif", f) for i, f in enumerate(flat_frames())]
                         + [tif(tmp_path / "scene.tif", 0.3 * np.exp(lens_field()))], *tags)
    db = str(tmp_path / "p.sqlite")
    assert _cli("profile", "--profile-db", db, "learn", "--method", "flat-field", *walls).returncode == 0
    show = _cli("profile", "--profile-db", db, "show", "0")
    assert show.returncode == 0 and "this lens shows a corner cast" in show.stdout, show.stdout + show.stderr
    p = _cli("correct", scene, "-o", str(tmp_path / "out"), "--profile-db", db, "--no-learn", "--output-format",
             "tiff-float")
    assert p.returncode == 0 and "stored-profile" in p.stdout, p.stdout + p.stderr
    out = oiio.ImageBuf(str(tmp_path / "out" / "scene.corrected.tif")).get_pixels(oiio.FLOAT).astype(np.float64)
    h, w = out.shape[:2]
    tint = np.log(out[:12, :12].mean((0, 1)) / out[h // 2 - 6:h // 2 + 6, w // 2 - 6:w // 2 + 6].mean((0, 1)))
    assert np.ptp(tint) < 0.01, tint  # the corner is the centre's colour: the cast was corrected
    assert "reported, not corrected" not in show.stdout and "corrected by the profile" in show.stdout, show.stdout
    js = json.loads(_cli("profile", "--profile-db", db, "show", "0", "--json").stdout)
    assert js["colour_cast"]["corrected"] is True


# ------------------------------------------------------------------ the writer thread, interrupted
def test_correct_run_again_after_a_kill_leaves_no_temporary_behind(tmp_path) -> None:
    """`correct` killed (SIGKILL) while its writer thread wrote a TIFF left the writer's
    hidden temporary (`.NAME.jpg.corrected.tif.tmp-XXXX.tif`, 0 bytes, seen on a real
    run), and running the same command again left it there for good (`batch` and `watch`
    sweep theirs). The rerun now removes its own files' temporaries, and no other file."""
    import os
    import signal
    import subprocess
    import sys
    import time
    from pathlib import Path

    srcs = [str(_textured_jpeg(tmp_path / f"f{i}.jpg", 600, 400, seed=i)) for i in range(6)]
    out = tmp_path / "out"
    root = Path(__file__).resolve().parents[1]
    env = {**os.environ, "PYTHONPATH": str(root), "VIGPROC_HOOK_SERVER": "off",
           "VIGPROC_PROFILE_DB": str(tmp_path / "p.sqlite")}
    args = [sys.executable, "-m", "vigproc.frontends.cli", "correct", *srcs, "-o", str(out), "--profile", "estimate",
            "--output-format", "tiff16", "--unapplied", "write"]
    left = []
    for _ in range(20):  # kill it until a writer's temporary is caught (a few ms of each file's write)
        p = subprocess.Popen(args, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, env=env)
        t0 = time.monotonic()
        while p.poll() is None and time.monotonic() - t0 < 120:
            left = [n for n in os.listdir(out)] if out.is_dir() else []
            left = [n for n in left if n.startswith(".") and ".tmp-" in n]
            if left:
                os.kill(p.pid, signal.SIGKILL)
                break
            time.sleep(0.002)
        p.wait()
        if left and all((out / n).exists() for n in left):
            break
    if not left:
        pytest.skip("no run was caught writing a temporary on this machine")
    stranger = out / ".someone-else.tmp-1234.tif"  # not a temporary of this run's inputs
    stranger.write_bytes(b"x")
    again = _cli("correct", *srcs, "-o", str(out), "--profile", "estimate", "--output-format", "tiff16",
                 "--unapplied", "write", env={"VIGPROC_PROFILE_DB": str(tmp_path / "p.sqlite")})
    assert again.returncode == 0, again.stdout + again.stderr
    names = sorted(os.listdir(out))
    assert [n for n in names if n.startswith(".")] == [stranger.name], names
    assert len([n for n in names if n.endswith(".corrected.tif")]) == 6


def test_profile_import_names_the_lens_as_profile_list_does(tmp_path) -> None:
    """A lens whose EXIF name holds a "|" ("EF | 24mm") is stored escaped ("ef %7C 24mm",
    so it cannot forge a key component); `profile list` shows it as the EXIF spells it,
    `profile import` printed the escape."""
    from vigproc.core.normalised import denormalise
    from vigproc.stores.profiles import ProfileStore, export_profile

    meta = {"EXIF:Make": "Canon", "EXIF:Model": "Canon EOS 6D", "EXIF:LensModel": "EF | 24mm", "EXIF:FocalLength": 24,
            "EXIF:FNumber": 2.8}
    theta = np.array([0.02, -0.01, 0.9, 0.02, 0.85, 0.05, 0.1, -0.05, 0.02, 0.0, 0.0, 0.0])
    with ProfileStore(tmp_path / "a.sqlite") as store:
        key = store.key_for(lens_key_from_metadata(meta), 3000, 2000)
        assert "%7C" in key.lens_id
        store.learn(key, denormalise(theta, np.diag(np.full(12, 1e-6)), 3000, 2000, method="robust"))
        (p,) = store.list()
        export_profile(p, tmp_path / "lens.json")
    i = _cli("profile", "--profile-db", str(tmp_path / "b.sqlite"), "import", str(tmp_path / "lens.json"))
    shown = _cli("profile", "--profile-db", str(tmp_path / "b.sqlite"), "list")
    assert i.returncode == 0 and shown.returncode == 0, i.stderr + shown.stderr
    assert "ef | 24mm" in shown.stdout and "ef | 24mm" in i.stdout and "%7C" not in i.stdout, i.stdout


def test_the_sweep_after_correct_keeps_another_runs_temporaries(tmp_path) -> None:
    """Phone names share long prefixes (IMG_20240101_...): a run's sweep must not take the
    temporary another run is writing into the same folder now."""
    from pathlib import Path

    from vigproc.pipeline.outputs import sweep_flat_temporaries

    mine = Path("IMG_20240101_101500.jpg")
    (tmp_path / ".IMG_20240101_101500.jpg.corrected.tif.tmp-ab12cd.tif").write_bytes(b"")  # a killed run's, of mine
    (tmp_path / "..IMG_20240101_101500.corrected.jpg.tmp-x.jpg.meta-y").write_bytes(b"")  # inside a temporary
    other = tmp_path / ".IMG_20240101_101501.jpg.corrected.tif.tmp-ef34gh.tif"  # another run's, being written
    other.write_bytes(b"")
    (tmp_path / "IMG_20240101_101500.jpg.corrected.tif").write_bytes(b"x")  # an output is never a temporary
    assert sweep_flat_temporaries(tmp_path, [mine], ["IMG_20240101_101500.jpg"]) == 2
    assert sorted(p.name for p in tmp_path.iterdir()) == [other.name, "IMG_20240101_101500.jpg.corrected.tif"]


def test_stacked_cfa_gain_maps_multiply_as_the_dng_specification_applies_them() -> None:
    """Two sets of per-phase GainMaps in one OpcodeList2 (what `correct --output-format dng`
    wrote for an output fed back in, before it replaced the file's maps) are applied one
    after the other by a raw converter: their gains multiply. vigproc's reader averaged
    every map of a colour, so it read two stacked corrections as one (0.51 EV for both)."""
    from vigproc.core.colour import ColourField
    from vigproc.core.model import VignettingModel
    from vigproc.io.dng_opcodes import OpcodeList
    from vigproc.io.dng_vignette import EmbeddedCalibration, model_to_gain_maps

    w, h = 240, 160
    f = 0.8 * np.hypot(w, h) / 2
    m = VignettingModel(w, h, center=(5, -3), p=(f**-2, 0, f**-2), alpha=(0.02, 0.01, 0, 0, 0, 0, 0))
    m = VignettingModel(w, h, center=m.center, p=m.p, alpha=m.alpha,
                        colour=ColourField(w, h, center=(5, -3), coeffs=np.array([[-0.1, 0.0, 0.1]] + [[0.0] * 3] * 2)))
    pattern = ((0, 1), (1, 2))
    maps = [g.to_opcode() for g in model_to_gain_maps(m, cfa_pattern=pattern)]
    one = EmbeddedCalibration.from_lists([("OpcodeList2", OpcodeList(tuple(maps)))], "one", cfa_pattern=pattern)
    two = EmbeddedCalibration.from_lists([("OpcodeList2", OpcodeList(tuple(maps * 2)))], "two", cfa_pattern=pattern)
    for c in (0, 1, 2, None):
        g1, g2 = one.log_gain(w, h, c), two.log_gain(w, h, c)
        assert np.abs(g1).max() > 0.1
        np.testing.assert_allclose(g2, 2 * g1, atol=1e-9)


def test_profile_delete_removes_a_profile_the_docs_say_it_removes(tmp_path) -> None:
    """docs/profiles.md tells the user to `profile delete` a profile (to drop its prior or
    its applied revision); there was no such command ("invalid choice: 'delete'"), and a
    profile learned from a bad frame could not be removed from the command line."""
    from vigproc.core.normalised import denormalise
    from vigproc.stores.profiles import ProfileStore

    meta = {"EXIF:Make": "Canon", "EXIF:Model": "Canon EOS 6D", "EXIF:LensModel": "EF | 24mm", "EXIF:FocalLength": 24,
            "EXIF:FNumber": 2.8}
    theta = np.array([0.02, -0.01, 0.9, 0.02, 0.85, 0.05, 0.1, -0.05, 0.02, 0.0, 0.0, 0.0])
    db = tmp_path / "a.sqlite"
    with ProfileStore(db) as store:
        for focal in (24, 50):
            key = store.key_for(lens_key_from_metadata({**meta, "EXIF:FocalLength": focal}), 3000, 2000)
            store.learn(key, denormalise(theta, np.diag(np.full(12, 1e-6)), 3000, 2000, method="robust"))
        kept = [str(p.key) for p in store.list()][1]
    gone = _cli("profile", "--profile-db", str(db), "delete", "0")
    assert gone.returncode == 0 and gone.stdout.startswith("deleted canon|canon eos 6d|ef | 24mm @ "), gone.stderr
    missing = _cli("profile", "--profile-db", str(db), "delete", "5")
    assert missing.returncode != 0 and "no stored profile '5'" in missing.stderr
    with ProfileStore(db) as store:
        assert [str(p.key) for p in store.list()] == [kept]


def test_the_learned_line_names_the_profile_as_profile_list_does(tmp_path) -> None:
    """`correct --profile-db`, `watch` and `batch` said "learned into profile sigma|...|105mm
    f1.4 dg hsm %7C art 018 @ f=112.4mm ..." for a frame shot at 105 mm: the storage escape and
    the focal bin's label; `profile list` shows "... | art 018 @ 105 mm"."""
    from vigproc.core.normalised import denormalise
    from vigproc.pipeline.learning import Learned
    from vigproc.stores.profiles import ProfileStore

    meta = {"EXIF:Make": "Canon", "EXIF:Model": "Canon EOS 6D", "EXIF:LensModel": "EF | 24mm", "EXIF:FocalLength": 24,
            "EXIF:FNumber": 2.8}
    theta = np.array([0.02, -0.01, 0.9, 0.02, 0.85, 0.05, 0.1, -0.05, 0.02, 0.0, 0.0, 0.0])
    lens = lens_key_from_metadata(meta)
    with ProfileStore(tmp_path / "a.sqlite") as store:
        key = store.key_for(lens, 3000, 2000)
        p = store.learn(key, denormalise(theta, np.diag(np.full(12, 1e-6)), 3000, 2000, method="robust"),
                        lens_key=lens)
    said = Learned.of(p, pooled=True).describe()
    assert said.startswith("learned into profile canon|canon eos 6d|ef | 24mm @ 24 mm N=2.8 3:2 (1 frame"), said
    assert Learned.of(p, pooled=True).to_dict()["profile"] == str(key)  # the record keeps the key
