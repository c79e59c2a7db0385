"""The stable pipeline API (vigproc.frontends.api) and the entry-point extensions (vigproc.core.extensions)."""

from __future__ import annotations

import json
import subprocess
import sys
import textwrap
import threading
from pathlib import Path

import numpy as np
import pytest

from vigproc.frontends import api
from benchmarks.synthetic import table1_model
from vigproc.errors import InvalidImageError, VigprocError
from vigproc.core.estimate import estimate
from vigproc.core.extensions import (
    ESTIMATORS,
    PROFILE_SOURCES,
    ExtensionError,
    UnknownMethodError,
    discover,
    method_names,
)
from vigproc.core.model import VignettingModel

from conftest import textured

W, H = 240, 160
LENS = {"make": "Canon", "model": "Canon EOS 5D Mark II", "lens": "EF24-105mm f/4L IS USM",
        "focal_mm": 24, "fnumber": "f/4"}


def truth() -> VignettingModel:
    return table1_model(2).rescale(W, H)


def real_lens() -> VignettingModel:
    """An off-centre fall-off as deep as real lenses' (1.1 EV at the far corner): Table 1
    setting 2 is 6.7 EV deep there, beyond any lens, and the pipeline does not apply it."""
    return VignettingModel(W, H, center=(-30.0, -20.0), p=(1 / 130**2, 0.0, 1 / 130**2))


def vignetted(seed: int = 1, channels: int = 3, field: VignettingModel | None = None) -> np.ndarray:
    img = (textured(H, W, seed=seed, contrast=0.05) * (field or truth()).field()).astype(np.float32)
    return np.repeat(img[..., None], channels, axis=2) if channels else img


# ------------------------------------------------------------------ lens data
def test_lens_dict_is_cleaned_like_exif():
    key = api.lens_key(LENS)
    assert key.lens_id() == "canon|canon eos 5d mark ii|ef24-105mm f/4l is usm"
    assert key.focal_mm == 24 and key.fnumber == 4.0
    # aliases and ExifTool names mean the same
    same = api.lens_key({"Maker": "Canon", "camera": "Canon EOS 5D Mark II",
                         "EXIF:LensModel": "EF24-105mm f/4L IS USM", "focal_length": "24 mm", "aperture": 4})
    assert same.key_string() == key.key_string()
    assert api.lens_key(key) is key and api.lens_key(None) is None
    assert api.lens_key(key.to_dict()).key_string() == key.key_string()


def test_hostile_lens_strings_are_normalised_not_trusted():
    key = api.lens_key({"make": "Ca\u202enon\x00\n", "lens": "EF 50mm $(rm -rf ~) 'q' \"dq\"\n;",
                        "focal_mm": -5, "fnumber": 1e9})
    assert "\n" not in key.lens_id() and "\u202e" not in key.lens_id()
    assert key.lens == "ef 50mm $(rm -rf ~) 'q' \"dq\" ;"  # data, kept as text
    assert key.focal_mm is None and key.fnumber is None  # absurd numbers dropped
    assert {"focal_mm", "fnumber"} <= set(key.missing)


@pytest.mark.parametrize("bad", [["canon"], {"colour": "red"}, {"make": ["a"]}, {"make": True}, {1: "x"}])
def test_bad_lens_data_is_a_request_error(bad):
    with pytest.raises(api.RequestError) as e:
        api.lens_key(bad)
    assert e.value.exit_code == 2 and isinstance(e.value, VigprocError)


# ------------------------------------------------------------------ processing
def test_correct_is_estimate_then_correct_and_reports_it():
    from vigproc.core.correct import correct

    img = vignetted(field=real_lens())
    before = img.copy()
    out, res = api.process(img, LENS, profile="estimate")
    assert np.array_equal(img, before)  # input untouched
    assert out.shape == img.shape and out.dtype == np.float32 and out is not img
    assert res.mode == "correct" and res.applied and res.source == "estimate" and not res.fallback
    # exactly what the lower-level functions give (the API wraps, never re-implements)
    m = estimate(img)
    assert res.model.as_vector().tolist() == m.as_vector().tolist()
    np.testing.assert_array_equal(out, correct(img, m))
    assert res.falloff_ev == pytest.approx(m.field_ev_rms(), abs=1e-3)
    assert res.falloff_ev > 0.2  # the frame has 0.40 EV RMS of fall-off
    assert res.confidence == pytest.approx(m.quality.confidence, abs=1e-3)
    assert res.lens["lens_id"] == "canon|canon eos 5d mark ii|ef24-105mm f/4l is usm"
    # the far corner (the field's centre is up-left) brightened relative to the centre
    ratio = lambda a: a[-3, -3, 0] / a[H // 2, W // 2, 0]
    assert ratio(out) > 1.4 * ratio(img)  # 2.2 for the true field
    d = res.to_dict()
    json.dumps(d)
    assert d["summary"] == res.summary and "EV fall-off removed" in res.summary


def test_estimate_mode_returns_the_input_itself():
    img = vignetted()
    out, res = api.process(img, mode="estimate", profile="estimate")
    assert out is img and not res.applied and res.model is not None
    assert res.lens["lens_id"] is None


@pytest.mark.parametrize("layout", ["chw", "gray", "hw1"])
def test_layouts_are_kept(layout):
    rgb = vignetted()
    img, ca = {"chw": (np.moveaxis(rgb, -1, 0), 0), "gray": (rgb[..., 0], None),
               "hw1": (rgb[..., :1], -1)}[layout]
    out, res = api.process(img, channel_axis=ca, profile="estimate")
    assert out.shape == img.shape
    ref, _ = api.process(rgb, profile="estimate")
    np.testing.assert_allclose(np.moveaxis(out, 0, -1)[..., 0] if layout == "chw" else out.reshape(H, W),
                               ref[..., 0], rtol=1e-5)


def test_bad_inputs_are_typed_errors():
    with pytest.raises(api.RequestError):
        api.Pipeline("learn")
    with pytest.raises(InvalidImageError):
        api.process(np.full((H, W), np.nan))
    with pytest.raises(UnknownMethodError) as e:
        api.Pipeline(method="no-such-method")
    assert isinstance(e.value, ValueError) and e.value.exit_code == 2


def _trusted_store(path: Path, lens: dict, model: VignettingModel) -> None:
    from vigproc.stores.profiles import Profile, ProfileKey, ProfileStore, normalise

    theta, _, _ = normalise(model)
    with ProfileStore(path) as st:
        st.put(Profile(key=ProfileKey.from_lens(api.lens_key(lens), model.width, model.height), theta=theta,
                       provenance="lensfun", trusted=True))


def test_threads_share_one_pipeline(tmp_path):
    """Several threads, one Pipeline with a profile store: same results as one thread."""
    db = tmp_path / "p.sqlite"
    stored = VignettingModel(W, H, center=(5, -3), p=(2e-5, 0, 2e-5), alpha=(0.05, 0, 0, 0, 0, 0, 0))
    _trusted_store(db, LENS, stored)
    frames = [vignetted(seed=s) for s in range(6)]
    lenses = [LENS if i % 2 == 0 else None for i in range(6)]  # stored profile / estimate
    with api.Pipeline("correct", store=db) as vp:
        ref = [vp.process(f, lens) for f, lens in zip(frames, lenses)]
        got: dict[int, tuple] = {}
        errors: list[BaseException] = []

        def work(i: int) -> None:
            try:
                for _ in range(2):
                    got[i] = vp.process(frames[i], lenses[i])
            except BaseException as exc:  # surfaced below
                errors.append(exc)

        threads = [threading.Thread(target=work, args=(i,)) for i in range(6)]
        for t in threads:
            t.start()
        for t in threads:
            t.join()
    assert not errors, errors
    for i, (out, res) in enumerate(ref):
        assert got[i][1].source == res.source == ("stored-profile" if i % 2 == 0 else "estimate")
        np.testing.assert_array_equal(got[i][0], out)


# ------------------------------------------------------------------ JIT
def _overloads() -> dict[str, int]:
    from numba.core.registry import CPUDispatcher

    found = {}
    for name, mod in list(sys.modules.items()):
        if name.startswith("vigproc"):
            for obj in vars(mod).values():
                if isinstance(obj, CPUDispatcher):
                    found[obj.py_func.__module__ + "." + obj.py_func.__qualname__] = len(obj.overloads)
    return found


def test_later_calls_compile_nothing_new():
    rgb = vignetted()
    vp = api.Pipeline("correct", profile="estimate")
    vp.process(rgb)
    first = _overloads()
    assert sum(first.values()) > 0  # the kernels were found and used
    variants = [rgb.astype(np.float64), (rgb / rgb.max() * 65535).astype(np.uint16), np.asfortranarray(rgb),
                np.repeat(np.repeat(rgb, 2, 0), 2, 1)[::2, ::2], rgb[..., 0], rgb[20:-20, 10:-30],
                np.concatenate([rgb, np.ones_like(rgb[..., :1])], axis=2)]
    for v in variants:
        vp.process(v)
    assert _overloads() == first


_CACHE_PROBE = textwrap.dedent("""
    import json, sys
    import numpy as np
    from numba.core.registry import CPUDispatcher
    from vigproc.frontends.api import Pipeline
    rng = np.random.default_rng(0)
    img = np.exp(0.2 * rng.standard_normal((120, 180))).astype(np.float32)
    Pipeline("correct", profile="estimate", channel_axis=None).process(img)
    hits = misses = 0
    for name, mod in list(sys.modules.items()):
        if name.startswith("vigproc"):
            for d in vars(mod).values():
                if isinstance(d, CPUDispatcher):
                    hits += sum(d.stats.cache_hits.values())
                    misses += sum(d.stats.cache_misses.values())
    print(json.dumps({"hits": hits, "misses": misses}))
""")


def test_a_new_process_loads_the_kernels_from_the_cache():
    """cache=True: after one run has filled Numba's cache, a new process compiles nothing."""
    run = lambda: json.loads(subprocess.run([sys.executable, "-c", _CACHE_PROBE], capture_output=True,
                                            text=True, check=True, timeout=300).stdout)
    run()  # fills the cache if this checkout has never run
    second = run()
    assert second["hits"] > 0 and second["misses"] == 0, second


# ------------------------------------------------------------------ extensions
def install_plugin(root: Path, dist: str, module: str, code: str, entry_points: dict[str, dict[str, str]]) -> Path:
    """A fake installed distribution: ROOT/MODULE.py + ROOT/DIST-1.0.dist-info (add ROOT to sys.path)."""
    root.mkdir(parents=True, exist_ok=True)
    (root / f"{module}.py").write_text(textwrap.dedent(code))
    info = root / f"{dist.replace('-', '_')}-1.0.dist-info"  # as wheels name it
    info.mkdir()
    (info / "METADATA").write_text(f"Metadata-Version: 2.1\nName: {dist}\nVersion: 1.0\n")
    (info / "entry_points.txt").write_text("".join(
        f"[{group}]\n" + "".join(f"{k} = {v}\n" for k, v in eps.items()) for group, eps in entry_points.items()))
    return root


PLUGIN_CODE = """
    from vigproc.errors import InvalidImageError
    from vigproc.core.model import VignettingModel

    def centre_only(img, *, channel_axis, seed):
        h, w = img.shape[:2]
        if img.max() > 1e6:
            raise InvalidImageError("too bright for centre-only")
        return VignettingModel(w, h, center=(1.0, 2.0), p=(1e-5, 0, 1e-5), alpha=(0.1,) + (0,) * 6,
                               method="centre-only")

    def crashes(img, *, channel_axis, seed):
        raise RuntimeError("boom")

    def wrong_size(img, *, channel_axis, seed):
        return VignettingModel(10, 10)

    def not_a_model(img, *, channel_axis, seed):
        return {"p": 1}

    def studio(lens_key, width, height):
        if lens_key.lens and "studio" in lens_key.lens:
            return VignettingModel(width, height, center=(-4.0, 3.0), p=(3e-5, 0, 3e-5), alpha=(0.2,) + (0,) * 6,
                                   method="studio-db")
        return None
"""


@pytest.fixture
def plugins(tmp_path, monkeypatch):
    mod = f"vp_plugin_{tmp_path.name.replace('-', '_')}"  # unique: modules stay imported between tests
    root = install_plugin(tmp_path / "site", "vp-test-plugins", mod, PLUGIN_CODE, {
        ESTIMATORS: {"centre-only": f"{mod}:centre_only", "crashes": f"{mod}:crashes",
                     "wrong-size": f"{mod}:wrong_size", "not-a-model": f"{mod}:not_a_model",
                     "missing": f"{mod}_nope:fn", "default": f"{mod}:centre_only", "Bad Name": f"{mod}:centre_only"},
        PROFILE_SOURCES: {"studio": f"{mod}:studio", "auto": f"{mod}:studio"},
    })
    install_plugin(tmp_path / "site2", "vp-other", mod + "_b", PLUGIN_CODE, {ESTIMATORS: {"crashes": f"{mod}_b:crashes"}})
    monkeypatch.syspath_prepend(str(root))
    monkeypatch.syspath_prepend(str(tmp_path / "site2"))
    return mod


def test_estimator_plugin_is_used_by_name(plugins):
    img = vignetted()
    assert "centre-only" in method_names()
    m = estimate(img, "centre-only")
    assert m.method == "centre-only" and m.center == (1.0, 2.0) and (m.width, m.height) == (W, H)
    out, res = api.process(img, method="centre-only", profile="estimate")
    assert res.model.method == "centre-only" and res.applied
    with pytest.raises(InvalidImageError, match="too bright"):  # the plugin's own typed error
        estimate(img * 1e7, "centre-only")


@pytest.mark.parametrize("name, match", [
    ("wrong-size", "10x10 frame"), ("not-a-model", "not a VignettingModel"), ("missing", "failed to load"),
    ("crashes", "declared more than once"),
])
def test_broken_estimators_are_clear_errors(plugins, name, match):
    with pytest.raises(ExtensionError, match=match) as e:
        estimate(vignetted(), name)
    assert e.value.exit_code == 12 and "\n" not in str(e.value)


def test_plugin_names_are_validated(plugins):
    exts = {(e.name, e.distribution): e for e in discover(ESTIMATORS)}
    assert "shadows the built-in method" in exts[("default", "vp-test-plugins")].problem
    assert "invalid name" in exts[("Bad Name", "vp-test-plugins")].problem
    assert exts[("centre-only", "vp-test-plugins")].problem is None
    assert estimate(vignetted(), "default").method == "robust"  # the built-in still wins
    with pytest.raises(UnknownMethodError, match="centre-only"):  # the message lists what exists
        estimate(vignetted(), "nonexistent")
    srcs = {e.name: e for e in discover(PROFILE_SOURCES)}
    assert "shadows" in srcs["auto"].problem and srcs["studio"].problem is None


def test_profile_source_plugin(plugins):
    img = vignetted()
    lens = {**LENS, "lens": "Studio 85mm f/1.4"}
    _, res = api.process(img, lens)  # auto: no store, the plugin has it
    assert res.source == "source:studio" and res.model.method == "studio-db"
    _, res = api.process(img, LENS)  # the plugin has no profile of this lens: estimate
    assert res.source == "estimate"
    _, res = api.process(img, lens, profile="source:studio")
    assert res.source == "source:studio"
    with pytest.raises(VigprocError, match="no profile"):
        api.process(img, LENS, profile="source:studio")
    with pytest.raises(ExtensionError, match="unknown profile source"):
        api.process(img, lens, profile="source:nope")


def test_a_partial_correction_reports_what_it_removed():
    """--strength 0.5 divides out half the fall-off (in EV), and says so: the summary
    and ``removed_ev`` follow the strength, ``falloff_ev`` stays the model's."""
    rgb = vignetted(field=real_lens())
    _, full = api.Pipeline("correct", profile="estimate").process(rgb)
    _, half = api.Pipeline("correct", profile="estimate", strength=0.5).process(rgb)
    assert full.applied and half.applied
    assert half.falloff_ev == full.falloff_ev > 0.1
    assert full.removed_ev == full.falloff_ev
    assert half.removed_ev == pytest.approx(0.5 * full.falloff_ev, abs=1e-3)
    assert f"{half.removed_ev:.2f} EV fall-off removed" in half.summary
    assert half.to_dict()["removed_ev"] == half.removed_ev
    assert api.Pipeline("estimate").process(rgb)[1].removed_ev is None


def test_lens_data_takes_numpy_scalars_and_drops_absurd_numbers():
    img = vignetted()
    base = {"make": "Canon", "model": "Canon EOS 5D", "lens": "EF24-105mm f/4L IS USM"}
    _, plain = api.Pipeline("estimate").process(img, lens={**base, "focal_mm": 24.0, "fnumber": 4})
    _, numpy_ = api.Pipeline("estimate").process(img, lens={**base, "focal_mm": np.float32(24), "fnumber": np.int64(4)})
    assert numpy_.lens == plain.lens and plain.lens["key"]["focal_mm"] == 24.0
    _, huge = api.Pipeline("estimate").process(img, lens={**base, "focal_mm": 10**400})  # was OverflowError
    assert huge.lens["key"]["focal_mm"] is None and any("focal_mm" in p for p in huge.lens["key"]["problems"])


def test_the_papers_fits_state_their_fall_off_and_no_made_up_certainty():
    """ga and lyu2010 give no uncertainty: their quality measures the fall-off and leaves
    σ and SNR unknown, instead of an empty FitQuality's 0 EV at infinite SNR."""
    import math

    import vigproc
    from conftest import textured
    from benchmarks.synthetic import table1_model

    img = textured(320, 480, seed=3, contrast=0.05) * table1_model(1).field((320, 480))
    for method in ("ga", "lyu2010"):
        m = vigproc.estimate(img, method=method, channel_axis=None)
        q = m.quality
        assert q.field_ev_rms == pytest.approx(m.field_ev_rms()) and q.field_ev_rms > 0.1, method
        assert math.isnan(q.field_sigma_ev) and math.isnan(q.snr), method
        assert '"field_sigma_ev": null' in m.to_json()


def test_the_stable_api_keeps_its_name():
    # pipelines written against vigproc.api (its name before the package became layers)
    import vigproc
    import vigproc.api as old
    from vigproc.frontends import api as new

    assert old.Pipeline is new.Pipeline is vigproc.Pipeline and old.Result is new.Result
    assert set(old.__all__) == set(new.__all__) and all(hasattr(old, n) for n in new.__all__)


def test_reading_and_the_lens_hint_have_short_names():
    # the README's snippet: vigproc.LensHint and vigproc.io.read_image, as before the layers
    import sys

    import vigproc
    import vigproc.io
    from vigproc.core.family_fit import LensHint
    from vigproc.io.images import read_image

    assert vigproc.LensHint is LensHint and vigproc.io.read_image is read_image
    with pytest.raises(AttributeError):
        vigproc.io.no_such_name  # noqa: B018
    assert "LensHint" in vigproc.__all__ and "vigproc.io.images" in sys.modules
