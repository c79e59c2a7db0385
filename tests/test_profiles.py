"""Tests of the per-lens profile store (vigproc.stores.profiles)."""

from __future__ import annotations

import functools
import json
import math
import multiprocessing
import os
import sqlite3
import time
from pathlib import Path

import numpy as np
import pytest
from scipy.stats import chi2

from vigproc.io.exif import LensKey
from vigproc.stores.lensfun import diverse_lenses, pa_field
from vigproc.core.model import VignettingModel
from vigproc.stores.profiles import (
    ANY,
    DB_ENV,
    SCHEMA_VERSION,
    TRUSTED_MIN_FRAMES,
    TRUSTED_SIGMA_EV,
    Profile,
    ProfileKey,
    ProfileStore,
    ProfileStoreError,
    aperture_bin,
    aspect_label,
    default_db_path,
    denormalise,
    export_profile,
    fit_model_to_field,
    focal_bin,
    frame_information,
    import_profile,
    normalise,
    pool_information,
    pool_mean,
)

EXAMPLES = Path(__file__).resolve().parents[1] / "profiles" / "examples"

# A realistic normalised truth: centre slightly off, near-circular P (f ≈ 1.07 R), mild G.
THETA_TRUE = np.array([0.02, -0.01, 0.9, 0.02, 0.85, 0.05, 0.1, -0.05, 0.02, 0.0, 0.0, 0.0])
_SIG = np.array([0.01, 0.01, 0.02, 0.01, 0.02, 0.02, 0.03, 0.03, 0.02, 0.01, 0.005, 0.005])


def _cov(scale: float = 1.0) -> np.ndarray:
    # fixed, mildly correlated covariance
    rng = np.random.default_rng(123)
    a = rng.normal(size=(12, 12))
    s = a @ a.T + 24 * np.eye(12)
    corr = s / np.sqrt(np.outer(np.diag(s), np.diag(s)))
    return scale * corr * np.outer(_SIG, _SIG)


COV = _cov()
KEY = ProfileKey("canon|canon eos 5d mark ii|ef24-105mm f/4l is usm", focal_bin(24.0), aperture_bin(4.0), "3:2")


def synthetic_model(seed: int, scale: float = 1.0) -> VignettingModel:
    """One frame's estimate: truth + N(0, Σ) noise, at alternating resolutions."""
    rng = np.random.default_rng(seed)
    cov = COV * scale
    theta = THETA_TRUE + np.linalg.cholesky(cov) @ rng.normal(size=12)
    w, h = ((6000, 4000), (3000, 2000), (1500, 1000))[seed % 3]
    return denormalise(theta, cov, w, h, method="robust")


def _learn_worker(path: str, worker: int, n: int, barrier) -> None:
    barrier.wait(timeout=120)  # start together: maximal contention
    with ProfileStore(path) as store:
        for i in range(n):
            store.learn(KEY, synthetic_model(1000 * worker + i))


# ----------------------------------------------------------------------------- binning


def test_focal_bins():
    assert focal_bin(24.0) == focal_bin(25.0) == "f=23.6mm"
    assert focal_bin(24.0) != focal_bin(35.0)
    assert focal_bin(35.0) != focal_bin(50.0)
    # one bin is a quarter octave; values inside ±1/8 octave of a centre share it
    assert focal_bin(23.6 * 2 ** (0.12)) == focal_bin(23.6 * 2 ** (-0.12)) == "f=23.6mm"
    assert focal_bin(None) == ANY
    with pytest.raises(ProfileStoreError):
        focal_bin(-3.0)
    with pytest.raises(ProfileStoreError):
        focal_bin(float("nan"))


def test_aperture_bins():
    assert aperture_bin(4.0) == "N=4.0"
    assert aperture_bin(4.5) == "N=4.5"
    assert aperture_bin(4.0) != aperture_bin(4.5)
    assert aperture_bin(5.6) == aperture_bin(5.66) == "N=5.6"
    assert aperture_bin(7.1) == "N=7.1" and aperture_bin(11) == "N=11.0" and aperture_bin(22) == "N=22.0"
    assert aperture_bin(None) == ANY
    with pytest.raises(ProfileStoreError):
        aperture_bin(0.0)


def test_aspect_labels():
    assert aspect_label(6000 / 4000) == aspect_label(6024 / 4024) == aspect_label(3000 / 2000) == "3:2"
    assert aspect_label(4000 / 6000) == "2:3"
    assert aspect_label(5184 / 3888) == "4:3"
    assert aspect_label(1.5 * 1.03) != "3:2"  # a 3 % crop is another key component
    assert aspect_label(1.1).startswith("a=") and aspect_label(1.234) == "5:4"  # 1.234: its grid cell is 5:4's
    # every label reads back as itself, so every frame can be keyed: a ratio between 1 %
    # and 2 % off a named one fell in a grid cell whose label was refused (3000x2030)
    for k in range(-120, 121):
        for a in (1.02**k * 0.995, 1.02**k, 1.02**k * 1.005):
            label = aspect_label(a)
            assert aspect_label(ProfileKey("x", "f=23.6mm", "N=4.0", label).aspect_ratio) == label
    lk = LensKey(make="a", model="b", lens="c", focal_mm=20.0, fnumber=4.0)
    assert ProfileKey.from_lens(lk, 3000, 2030).aspect == "3:2" and ProfileKey.from_lens(lk, 4000, 2962).aspect == "4:3"


def test_key_from_lens_and_missing_fields():
    lk = LensKey(make="nikon", model="nikon d800", lens="af-s nikkor 24-70mm f/2.8g ed", focal_mm=24.0, fnumber=4.0)
    k = ProfileKey.from_lens(lk, 7360, 4912)
    assert (k.focal_bin, k.aperture_bin, k.aspect) == ("f=23.6mm", "N=4.0", "3:2")
    assert k.lens_id == "nikon|nikon d800|af-s nikkor 24-70mm f/2.8g ed"
    k_any = ProfileKey.from_lens(LensKey(make="nikon", model="nikon d800", lens=lk.lens, fnumber=4.0), 7360, 4912)
    assert k_any.focal_bin == ANY and k_any != k
    with pytest.raises(ProfileStoreError):
        ProfileKey.from_lens(LensKey(make="nikon", model=None, lens=None, focal_mm=24.0), 100, 100)
    for bad in (("x", "f=24mm", "N=4.0", "3:2"), ("x", "f=23.6mm", "N=4", "3:2"), ("x", "f=23.6mm", "N=4.0", "3x2")):
        with pytest.raises(ProfileStoreError):
            ProfileKey(*bad)


# ----------------------------------------------------------------------------- normalisation


def test_normalise_round_trip_across_resolutions():
    big = denormalise(THETA_TRUE, COV, 6000, 4000)
    small = big.rescale(3000, 2000)
    t_big, c_big, a_big = normalise(big)
    t_small, c_small, a_small = normalise(small)
    np.testing.assert_allclose(t_big, THETA_TRUE, rtol=1e-12, atol=1e-15)
    np.testing.assert_allclose(t_small, t_big, rtol=1e-12, atol=1e-15)
    np.testing.assert_allclose(c_small, c_big, rtol=1e-10, atol=1e-18)
    np.testing.assert_allclose(c_big, COV, rtol=1e-10, atol=1e-18)
    assert a_big == a_small == 1.5
    # the same field whatever resolution it was estimated at
    np.testing.assert_allclose(big.log_field((40, 60)), small.log_field((40, 60)), atol=1e-12)
    back = denormalise(t_small, c_small, 6000, 4000)
    np.testing.assert_allclose(back.as_vector(), big.as_vector(), rtol=1e-12, atol=1e-18)


# ----------------------------------------------------------------------------- learning


def test_learn_pools_and_trust_flips(tmp_path):
    n = 40
    with ProfileStore(tmp_path / "p.sqlite") as store:
        history = []
        thetas, covs = [], []
        for i in range(n):
            m = synthetic_model(i)
            p = store.learn(KEY, m)
            t, c, _ = normalise(m)
            thetas.append(t)
            covs.append(c)
            history.append((p.n_frames, p.trusted, p.field_sigma_ev, p.cov_sigma_ev, p.scatter_sigma_ev))
        assert [h[0] for h in history] == list(range(1, n + 1))
        for n_i, trusted, sigma, cov_sigma, scatter in history:
            assert trusted == (n_i >= TRUSTED_MIN_FRAMES and sigma < TRUSTED_SIGMA_EV)
            if n_i >= 2:
                assert sigma == pytest.approx(max(cov_sigma, scatter / math.sqrt(n_i)))
        assert not history[0][1] and history[-1][1], "trust must flip from False to True"
        flip = next(h[0] for h in history if h[1])
        assert flip >= TRUSTED_MIN_FRAMES

        p = store.get(KEY)
        assert p is not None and p.n_frames == n and p.provenance == "learned"
        # pooled θ within its expected error (χ² test at 99.9 %)
        d = p.theta - THETA_TRUE
        stat = d @ np.linalg.solve(COV / n, d)
        assert stat < chi2.ppf(0.999, 12)
        np.testing.assert_allclose(p.covariance, COV / n, rtol=1e-6, atol=1e-14)
        # same arithmetic as the database-free helper
        th, cv = pool_information(thetas, covs)
        np.testing.assert_allclose(p.theta, th, rtol=1e-9, atol=1e-12)
        np.testing.assert_allclose(p.theta_mean, pool_mean(thetas), rtol=1e-9, atol=1e-12)
        # frame-to-frame scatter matches the per-frame σ the noise was drawn with
        single = history[0][3]
        assert 0.6 * single < p.scatter_sigma_ev < 1.5 * single
        assert p.theta_scatter.shape == (12, 12)
        m = p.model(6000, 4000)
        assert m.covariance is not None and m.quality is not None and m.quality.confidence == 1.0
        assert store.check() == []


def test_trust_needs_three_frames(tmp_path):
    with ProfileStore(tmp_path / "p.sqlite") as store:
        got = [store.learn(KEY, synthetic_model(i, scale=1e-6)) for i in range(4)]
    assert [p.field_sigma_ev < TRUSTED_SIGMA_EV for p in got] == [True] * 4
    assert [p.trusted for p in got] == [False, False, True, True]


def test_learn_rejects_bad_frames(tmp_path):
    with ProfileStore(tmp_path / "p.sqlite") as store:
        with pytest.raises(ProfileStoreError, match="without covariance"):
            store.learn(KEY, VignettingModel.identity(6000, 4000))
        with pytest.raises(ProfileStoreError, match="cannot refine"):
            store.learn(KEY, denormalise(THETA_TRUE, COV, 4000, 4000))
        assert store.get(KEY) is None  # nothing half-written


def _lambda_from_frames(models) -> np.ndarray:
    lams = np.array([frame_information(m)[1] for m in models])
    return np.array([[math.fsum(lams[:, i, j]) for j in range(12)] for i in range(12)])


def test_concurrent_learners_lose_nothing(tmp_path):
    db = tmp_path / "shared.sqlite"
    ctx = multiprocessing.get_context("spawn")
    barrier = ctx.Barrier(4)
    procs = [ctx.Process(target=_learn_worker, args=(str(db), w, 25, barrier)) for w in range(4)]
    for pr in procs:
        pr.start()
    for pr in procs:
        pr.join(timeout=300)
    assert [pr.exitcode for pr in procs] == [0, 0, 0, 0]

    models = [synthetic_model(1000 * w + i) for w in range(4) for i in range(25)]
    with ProfileStore(db) as store:
        assert store.check() == []
        p = store.get(KEY)
        assert p.n_frames == 100
    # serial run, in another order: bit-identical sums (exact accumulation)
    with ProfileStore(tmp_path / "serial.sqlite") as serial:
        for m in reversed(models):
            q = serial.learn(KEY, m)
    assert q.n_frames == 100
    assert np.array_equal(p.info_matrix, q.info_matrix)
    assert np.array_equal(p.info_vector, q.info_vector)
    assert np.array_equal(p.theta, q.theta)
    # ... and equal to the correctly rounded sum of the frames' Λ_i
    assert np.array_equal(p.info_matrix, _lambda_from_frames(models))


# ----------------------------------------------------------------------------- robustness of the store


def test_corrupt_file_is_a_clear_error(tmp_path):
    db = tmp_path / "junk.sqlite"
    db.write_bytes(np.random.default_rng(0).bytes(16384))
    with pytest.raises(ProfileStoreError, match="corrupt or not an SQLite database") as ei:
        ProfileStore(db)
    assert str(db) in str(ei.value)
    # it says how to recover, and how to work without the store meanwhile
    assert "move it aside" in str(ei.value) and "--profile estimate" in str(ei.value)


def test_damaged_store_is_detected(tmp_path, monkeypatch):
    db = tmp_path / "p.sqlite"
    with ProfileStore(db) as store:
        for i in range(200):  # enough rows to span several pages
            store.put(Profile(key=ProfileKey(f"lens {i}", "f=23.6mm", "N=4.0", "3:2"), theta=THETA_TRUE,
                              covariance=COV, notes="x" * 200))
    raw = bytearray(db.read_bytes())
    assert len(raw) > 5 * 4096
    raw[2 * 4096 : 4 * 4096] = np.random.default_rng(1).bytes(2 * 4096)
    db.write_bytes(bytes(raw))
    with pytest.raises(ProfileStoreError, match="corrupt") as ei:  # refused on open (PRAGMA quick_check)
        ProfileStore(db)
    assert str(db) in str(ei.value) and "move it aside" in str(ei.value)
    monkeypatch.setattr(ProfileStore, "check_on_open", False)
    with ProfileStore(db) as store:  # the header is intact: without the check opening works...
        assert store.check(), "check() must report the damage"
        with pytest.raises(ProfileStoreError, match="corrupt") as ei:  # ...reading the damage does not
            store.list()
        assert str(db) in str(ei.value)


def test_foreign_and_newer_databases_are_refused(tmp_path):
    other = tmp_path / "other.sqlite"
    con = sqlite3.connect(other)
    con.execute("CREATE TABLE photos (x)")
    con.commit()
    con.close()
    with pytest.raises(ProfileStoreError, match="not a vigproc profile store"):
        ProfileStore(other)
    db = tmp_path / "p.sqlite"
    ProfileStore(db).close()
    con = sqlite3.connect(db)
    con.execute("INSERT INTO schema_version VALUES (99, 'future')")
    con.commit()
    con.close()
    with pytest.raises(ProfileStoreError, match="newer"):
        ProfileStore(db)


def test_locked_store_errors_instead_of_hanging(tmp_path):
    db = tmp_path / "p.sqlite"
    store = ProfileStore(db, timeout=0.2)
    store.put(Profile(key=KEY, theta=THETA_TRUE))
    other = sqlite3.connect(db, timeout=0.1, isolation_level=None)
    other.execute("BEGIN EXCLUSIVE")
    try:
        t0 = time.monotonic()
        with pytest.raises(ProfileStoreError, match="locked"):
            store.learn(KEY, synthetic_model(0))
        with pytest.raises(ProfileStoreError, match="locked"):
            store.put(Profile(key=KEY, theta=THETA_TRUE))
        assert time.monotonic() - t0 < 10
        assert store.get(KEY) is not None  # WAL: readers are not blocked by the writer
    finally:
        other.execute("ROLLBACK")
        other.close()
    assert store.learn(KEY, synthetic_model(0)).n_frames == 1  # usable again
    store.close()

    # a database in rollback-journal mode, exclusively locked before we open it
    plain = tmp_path / "plain.sqlite"
    holder = sqlite3.connect(plain, isolation_level=None)
    holder.execute("CREATE TABLE t (x)")
    holder.execute("BEGIN EXCLUSIVE")
    try:
        t0 = time.monotonic()
        with pytest.raises(ProfileStoreError, match="locked"):
            ProfileStore(plain, timeout=0.2)
        assert time.monotonic() - t0 < 10
    finally:
        holder.execute("ROLLBACK")
        holder.close()


def test_schema_version_and_idempotent_migration(tmp_path):
    db = tmp_path / "p.sqlite"
    with ProfileStore(db) as s:
        assert s.schema_version == SCHEMA_VERSION
        s.learn(KEY, synthetic_model(0))
    with ProfileStore(db) as s:
        assert s.schema_version == SCHEMA_VERSION
        assert s.get(KEY).n_frames == 1
    con = sqlite3.connect(db)
    rows = con.execute("SELECT version FROM schema_version ORDER BY version").fetchall()
    mode = con.execute("PRAGMA journal_mode").fetchone()[0]
    con.close()
    assert rows == [(v,) for v in range(1, SCHEMA_VERSION + 1)]
    assert mode == "wal"


def test_frame_id_pools_each_frame_once(tmp_path):
    with ProfileStore(tmp_path / "p.sqlite") as s:
        first = s.learn(KEY, synthetic_model(0), frame_id="sha-a")
        again = s.learn(KEY, synthetic_model(1), frame_id="sha-a")  # same frame, offered again
        assert again.n_frames == first.n_frames == 1
        np.testing.assert_array_equal(again.theta, first.theta)
        assert s.learn(KEY, synthetic_model(1), frame_id="sha-b").n_frames == 2
        assert s.learn(KEY, synthetic_model(2)).n_frames == 3  # no id: always pooled
        other = ProfileKey(KEY.lens_id, KEY.focal_bin, aperture_bin(8.0), KEY.aspect)
        assert s.learn(other, synthetic_model(0), frame_id="sha-a").n_frames == 1  # per profile
        s.put(s.get(KEY))  # replaced evidence forgets which frames it held
        assert s.learn(KEY, synthetic_model(0), frame_id="sha-a").n_frames == 4
        with pytest.raises(ProfileStoreError, match="frame_id"):
            s.learn(KEY, synthetic_model(0), frame_id="")


def test_migration_from_schema_1_keeps_profiles(tmp_path):
    db = tmp_path / "p.sqlite"
    with ProfileStore(db) as s:
        s.learn(KEY, synthetic_model(0))
    con = sqlite3.connect(db)  # turn it back into a v1 store, as a previous release wrote it
    con.execute("DROP TABLE pooled_frames")
    con.execute("DELETE FROM schema_version WHERE version > 1")
    con.commit()
    con.close()
    with ProfileStore(db) as s:
        assert s.schema_version == SCHEMA_VERSION >= 2
        assert s.get(KEY).n_frames == 1
        assert s.learn(KEY, synthetic_model(1), frame_id="x").n_frames == 2
        assert s.learn(KEY, synthetic_model(1), frame_id="x").n_frames == 2
        assert s.check() == []


def test_default_location_from_environment(tmp_path, monkeypatch):
    target = tmp_path / "deep" / "er" / "profiles.sqlite"
    monkeypatch.setenv(DB_ENV, str(target))
    assert default_db_path() == target
    with ProfileStore() as s:
        assert s.path == target
    assert target.exists()
    monkeypatch.delenv(DB_ENV)
    assert default_db_path().name == "profiles.sqlite"


ODD_IDS = [
    "it's|o'brien|lens",
    'say "cheese"|model|lens',
    "semi;colon|a;b|c;",
    "'; DROP TABLE profiles; --",
    "x'); DELETE FROM profiles WHERE ('1'='1",
    "ünïcødé|カメラ|镜头 🔭 50mm",
    "back\\slash|%25|%7C?",
    "   spaces   inside  ",
]


def test_odd_lens_ids_round_trip(tmp_path):
    with ProfileStore(tmp_path / "p.sqlite") as store:
        for lid in ODD_IDS:
            store.put(Profile(key=ProfileKey(lid, "f=23.6mm", "N=4.0", "3:2"), theta=THETA_TRUE, provenance="user"))
        for lid in ODD_IDS:
            p = store.get(ProfileKey(lid, "f=23.6mm", "N=4.0", "3:2"))
            assert p is not None and p.key.lens_id == lid
        assert sorted(p.key.lens_id for p in store.list()) == sorted(ODD_IDS)
        assert len(store.list(lens_id=ODD_IDS[3])) == 1
        assert store.delete(ProfileKey(ODD_IDS[4], "f=23.6mm", "N=4.0", "3:2"))
        assert len(store.list()) == len(ODD_IDS) - 1
        assert store.check() == []
        # file round trip of an odd id
        prof = store.get(ProfileKey(ODD_IDS[5], "f=23.6mm", "N=4.0", "3:2"))
        export_profile(prof, tmp_path / "odd.json")
        assert import_profile(tmp_path / "odd.json").key == prof.key
    for bad in ("", "a\x00b", "line\nbreak", "lone \ud800 surrogate", "x" * 5000):
        with pytest.raises(ProfileStoreError):
            ProfileKey(bad, "f=23.6mm", "N=4.0", "3:2")


# ----------------------------------------------------------------------------- lookup


def test_lookup_exact_then_neighbouring_focal_bin(tmp_path):
    lens = dict(make="canon", model="canon eos 5d mark ii", lens="ef24-105mm f/4l is usm")
    with ProfileStore(tmp_path / "p.sqlite") as store:
        key35 = ProfileKey.from_lens(LensKey(**lens, focal_mm=35.0, fnumber=4.0), 5616, 3744)
        store.put(Profile(key=key35, theta=THETA_TRUE))
        hit = store.lookup(LensKey(**lens, focal_mm=35.0, fnumber=4.0), 5616, 3744)
        assert hit is not None and hit.key == key35
        near = store.lookup(LensKey(**lens, focal_mm=40.0, fnumber=4.0), 2808, 1872)  # next bin, half size
        assert near is not None and near.key == key35
        assert store.lookup(LensKey(**lens, focal_mm=50.0, fnumber=4.0), 5616, 3744) is None  # two bins away
        assert store.lookup(LensKey(**lens, focal_mm=35.0, fnumber=5.6), 5616, 3744) is None  # other aperture
        assert store.lookup(LensKey(**lens, focal_mm=35.0, fnumber=4.0), 3744, 5616) is None  # portrait frame
        assert store.lookup(LensKey(**lens, fnumber=4.0), 5616, 3744) is None  # no focal: only "any"
        assert store.lookup(LensKey(**lens, focal_mm=35.0, fnumber=4.0), 5616, 3744, trusted_only=True) is None


# ----------------------------------------------------------------------------- files


def test_export_import_round_trip(tmp_path):
    with ProfileStore(tmp_path / "p.sqlite") as store:
        for i in range(5):
            p = store.learn(KEY, synthetic_model(i))
    path = tmp_path / "out" / "profile.json"
    path.parent.mkdir()
    export_profile(p, path)
    q = import_profile(path)
    assert q.key == p.key and q.provenance == "learned" and q.n_frames == 5
    np.testing.assert_allclose(q.theta, p.theta, rtol=0, atol=0)
    np.testing.assert_allclose(q.covariance, p.covariance, rtol=1e-12)
    assert q.trusted == p.trusted
    # the imported covariance is prior evidence for further learning
    with ProfileStore(tmp_path / "q.sqlite") as store:
        store.put(q)
        r = store.learn(KEY, synthetic_model(99))
    assert r.n_frames == 6
    assert json.loads(path.read_text())["schema"] == "vigproc.profile/2"


def test_example_profiles_import_and_match_lensfun(tmp_path):
    files = sorted(EXAMPLES.glob("*.json"))
    assert len(files) >= 2
    lenses = {l.model: e for l, e in diverse_lenses(20)}
    with ProfileStore(tmp_path / "p.sqlite") as store:
        for f in files:
            p = store.import_file(f)
            assert p.provenance == "lensfun" and p.n_frames == 0 and not p.trusted
            assert store.get(p.key) is not None
        zeiss = store.lookup(
            LensKey(make="nikon corporation", model="nikon d800", lens="carl zeiss distagon t* 2/35 zf.2",
                    focal_mm=35.0, fnumber=2.0),
            7360, 4912,
        )
        assert zeiss is not None
    e = lenses["Carl Zeiss Distagon T* 2/35 ZF.2"]
    # compared at a resolution where lensfun's pixel-centre radius convention is ~0.03 % from ours
    ours = zeiss.model(3000, 2000).log_field((2000, 3000)) / math.log(2)
    theirs = np.log2(pa_field((2000, 3000), e.k1, e.k2, e.k3))
    assert np.max(np.abs(ours - theirs)) < 0.01  # EV
    assert np.sqrt(np.mean((ours - theirs) ** 2)) < 0.002


def test_fit_model_to_field_recovers_a_kang_weiss_field():
    truth = denormalise(THETA_TRUE, None, 600, 400)
    fitted, rms = fit_model_to_field(truth.log_field((40, 60)), 6000, 4000)
    assert rms < 1e-3
    np.testing.assert_allclose(fitted.log_field((40, 60)), truth.log_field((40, 60)), atol=3e-3)


def _example() -> dict:
    return json.loads(sorted(EXAMPLES.glob("*.json"))[0].read_text())


def _set(path: tuple, value):
    def mutate(d):
        cur = d
        for k in path[:-1]:
            cur = cur[k]
        cur[path[-1]] = value
    return mutate


def _drop(path: tuple):
    def mutate(d):
        cur = d
        for k in path[:-1]:
            cur = cur[k]
        del cur[path[-1]]
    return mutate


NON_PSD_COV = (1e-4 * (1.5 * np.eye(12) - 0.5 * np.ones((12, 12)))).tolist()  # correlation −0.5 everywhere

BAD_FILES = [
    (_drop(("model",)), "missing field 'model'"),
    (_drop(("model", "alpha")), "model.alpha"),
    (_drop(("lens",)), "missing field 'lens'"),
    (_set(("schema",), "vigproc.profile/9"), "schema"),
    (_set(("provenance",), "stolen"), "provenance"),
    (_set(("n_frames",), -1), "n_frames"),
    (_set(("n_frames",), 2.5), "n_frames"),
    (_set(("focal_bin",), [24]), "focal_bin"),
    (_set(("focal_bin",), "wide"), "focal_bin"),
    (_set(("focal_bin",), 1e9), "absurd"),
    (_set(("aperture_bin",), "f/0"), "aperture_bin"),
    (_set(("aspect",), "3:0"), "aspect"),
    (_set(("model", "center"), [10.0, 0.0]), "model.center"),
    (_set(("model", "center"), [0.0]), "model.center"),
    (_set(("model", "p"), [1.0, 2.0, 1.0]), "positive semi-definite"),
    (_set(("model", "p"), ["1", 0, 1]), "model.p"),
    (_set(("model", "alpha"), [5.0, 0, 0, 0, 0, 0, 0]), "geometric factor G"),
    (_set(("model", "alpha"), [1e6, 0, 0, 0, 0, 0, 0]), "absurd"),
    (_set(("model",), {"coordinates": "half-diagonal", "center": [0, 0], "p": [200.0, 0, 200.0], "alpha": [0] * 7}),
     "EV inside the frame"),  # A alone: −11 EV in the corners
    (_set(("model", "coordinates"), "pixels"), "coordinates"),
    (_set(("covariance",), [[1.0] * 3] * 3), "covariance"),
    (_set(("covariance",), NON_PSD_COV), "positive semi-definite"),
    # was accepted, then listed as "±1.9e150 EV"
    (_set(("covariance",), [[1e300 if i == j else 0.0 for j in range(12)] for i in range(12)]),
     "use null for an unknown uncertainty"),
    (_set(("lens", "lens_id"), "someone|else|entirely"), "does not match"),
    (_set(("trusted",), "yes"), "trusted"),
    (_set(("created",), "yesterday"), "created"),
    (_set(("notes",), 42), "notes"),
]


@pytest.mark.parametrize("mutate,message", BAD_FILES, ids=[m for _, m in BAD_FILES])
def test_profile_file_validation(tmp_path, mutate, message):
    d = _example()
    mutate(d)
    path = tmp_path / "bad.json"
    path.write_text(json.dumps(d))
    with pytest.raises(ProfileStoreError) as ei:
        import_profile(path)
    assert str(path) in str(ei.value)
    assert message in str(ei.value)


@pytest.mark.parametrize(
    "text,message",
    [
        ("{not json", "not valid profile JSON"),
        ('{"schema": "vigproc.profile/1", "schema": "x"}', "duplicate field"),
        (None, "NaN"),
        (b"\xff\xfe\x00garbage", "not UTF-8"),
    ],
)
def test_profile_file_syntax_errors(tmp_path, text, message):
    path = tmp_path / "bad.json"
    if text is None:  # NaN literal (Python's json writes it) in an otherwise valid profile
        d = _example()
        d["model"]["alpha"][0] = float("nan")
        text = json.dumps(d)
    if isinstance(text, bytes):
        path.write_bytes(text)
    else:
        path.write_text(text)
    with pytest.raises(ProfileStoreError) as ei:
        import_profile(path)
    assert str(path) in str(ei.value) and message in str(ei.value)


def test_oversized_and_missing_files(tmp_path):
    big = tmp_path / "big.json"
    big.write_bytes(b" " * (2 << 20))
    with pytest.raises(ProfileStoreError, match="too large"):
        import_profile(big)
    with pytest.raises(ProfileStoreError, match="cannot read"):
        import_profile(tmp_path / "nope.json")


def test_learning_onto_import_without_uncertainty(tmp_path):
    with ProfileStore(tmp_path / "p.sqlite") as store:
        imp = import_profile(sorted(EXAMPLES.glob("*.json"))[0])
        store.put(imp)
        p = store.learn(imp.key, synthetic_model(0))
    assert p.provenance == "learned" and p.n_frames == 1
    assert "superseded a lensfun profile" in p.notes


def test_pooled_fits_are_cached_by_evidence_not_by_frame_id(tmp_path):
    """Two lenses whose frames a caller names alike: each profile is pooled from its own
    frames' evidence (the store's fit cache must not hand one lens the other's fits)."""
    from conftest import photo_like

    from vigproc.core.estimate import estimate, frame_evidence
    from vigproc.core.pooling import frame_fit, pool_family
    from vigproc.core.robust import evidence_copy

    h, w = 160, 240
    with ProfileStore(tmp_path / "p.sqlite") as store:
        for li, (_lens, pa) in enumerate(diverse_lenses(2)):
            frames = [photo_like(h, w, seed=40 + i) * pa_field((h, w), pa.k1, pa.k2, pa.k3) for i in range(2)]
            key = ProfileKey(f"vigproc|test|lens{li}", focal_bin(24.0), aperture_bin(2.8), aspect_label(w / h))
            for i, f in enumerate(frames):
                m = estimate(f, "robust", channel_axis=None)
                p = store.learn(key, m.candidate or m, frame_id=f"frame{i}", evidence=frame_evidence(f, channel_axis=None))
            own = pool_family([frame_fit(evidence_copy(frame_evidence(f, channel_axis=None))) for f in frames], w, h)
            np.testing.assert_allclose(p.model(w, h).log_field(), own.log_field(), atol=1e-6)


def test_with_evidence_sigma_is_the_pooled_medians(tmp_path):
    """With evidence, the profile's σ is the median's (vigproc.core.pooling), robust to a
    frame the scene fooled; the scatter reported is that of what the profile pools
    (the frames' lens-family fits), not of the frames' single-frame estimates."""
    from conftest import photo_like

    from vigproc.core.estimate import estimate, frame_evidence
    from vigproc.core.normalised import _field_and_jacobian, normalise
    from vigproc.core.pooling import coefficients_model, frame_fit, pool_family, pooled_coefficients
    from vigproc.core.robust import evidence_copy

    _lens, pa = diverse_lenses(1)[0]
    h, w = 160, 240
    frames = [photo_like(h, w, seed=50 + i) * pa_field((h, w), pa.k1, pa.k2, pa.k3) for i in range(3)]
    key = ProfileKey("vigproc|test|scatter", focal_bin(24.0), aperture_bin(2.8), aspect_label(w / h))
    with ProfileStore(tmp_path / "p.sqlite") as store:
        for i, f in enumerate(frames):
            m = estimate(f, "robust", channel_axis=None)
            p = store.learn(key, m.candidate or m, frame_id=f"f{i}", evidence=frame_evidence(f, channel_axis=None))
    fits = [frame_fit(evidence_copy(frame_evidence(f, channel_axis=None))) for f in frames]
    fields = [_field_and_jacobian(normalise(coefficients_model(fit.coefficients, w, h))[0], w / h)[0] for fit in fits]
    expected = float(np.sqrt(np.mean(np.var(fields, axis=0, ddof=1))))
    assert p.scatter_sigma_ev == pytest.approx(expected, rel=1e-6)
    assert p.field_sigma_ev == pytest.approx(pool_family(fits, w, h).quality.field_sigma_ev, rel=1e-9)
    assert p.field_sigma_ev > 0 and pooled_coefficients(fits)[0].size == 3


def test_learning_with_evidence_pools_the_frames_family_fits(tmp_path):
    """With each frame's evidence the profile is the median of the frames' lens-family
    fits (vigproc.core.pooling), whatever order the frames arrive in."""
    from conftest import photo_like

    from vigproc.core.estimate import estimate, frame_evidence
    from vigproc.core.pooling import frame_fit, pool_family
    from vigproc.core.robust import evidence_copy

    lens, pa = diverse_lenses(1)[0]
    h, w = 160, 240
    truth = pa_field((h, w), pa.k1, pa.k2, pa.k3)
    frames = [photo_like(h, w, seed=60 + i) * truth for i in range(3)]
    key = ProfileKey("vigproc|test|joint", focal_bin(24.0), aperture_bin(2.8), aspect_label(w / h))
    expected = pool_family([frame_fit(evidence_copy(frame_evidence(f, channel_axis=None))) for f in frames], w, h)
    for order in ((0, 1, 2), (2, 0, 1)):
        with ProfileStore(tmp_path / f"p{order[0]}.sqlite") as store:
            for i in order:
                m = estimate(frames[i], "robust", channel_axis=None)
                p = store.learn(key, m.candidate or m, frame_id=f"f{i}",
                                evidence=frame_evidence(frames[i], channel_axis=None))
            assert p.n_frames == 3
            np.testing.assert_allclose(p.model(w, h).log_field(), expected.log_field(), atol=1e-6)
    with ProfileStore(tmp_path / "p0.sqlite") as store:
        # the same frame again changes nothing; bad evidence is refused
        again = store.learn(key, m.candidate or m, frame_id="f2", evidence=frame_evidence(frames[2], channel_axis=None))
        assert again.n_frames == 3
        with pytest.raises(ProfileStoreError, match="evidence"):
            store.learn(key, m.candidate or m, frame_id="f9", evidence=b"not evidence")
        wc = evidence_copy(frame_evidence(frames[0], channel_axis=None))
        assert wc.L.shape == (wc.ys.size, wc.xs.size) and (wc.width, wc.height) == (w, h)



def test_profile_file_that_is_not_a_regular_file(tmp_path):
    """A FIFO used to block the import forever."""
    fifo = tmp_path / "p.json"
    os.mkfifo(fifo)
    with pytest.raises(ProfileStoreError, match="not a regular file"):
        import_profile(fifo)



def _learn_frames(store, key, frames, first=0):
    from vigproc.core.estimate import estimate, frame_evidence

    p = None
    for i, f in enumerate(frames, start=first):
        m = estimate(f, "robust", channel_axis=None)
        p = store.learn(key, m.candidate or m, frame_id=f"f{i:03d}", evidence=frame_evidence(f, channel_axis=None))
    return p


def _lens_frames(name: str, seed: int, n: int = 4, h: int = 120, w: int = 180):
    """``n`` photo-like frames through one lensfun lens, and a profile key for them."""
    from conftest import photo_like

    _lens, pa = diverse_lenses(1)[0]
    frames = [photo_like(h, w, seed=seed + i) * pa_field((h, w), pa.k1, pa.k2, pa.k3) for i in range(n)]
    return frames, ProfileKey(f"vigproc|test|{name}", focal_bin(24.0), aperture_bin(2.8), aspect_label(w / h))


def _fits_stored(db) -> tuple[int, int]:
    con = sqlite3.connect(db)
    try:
        return con.execute("SELECT COUNT(family), COUNT(*) FROM pooled_frames").fetchone()
    finally:
        con.close()


def test_every_frame_keeps_its_fit_and_an_older_store_gets_them_once(tmp_path):
    """Frames keep their lens-family fit (schema v5), so pooling costs no refit; a store
    written before v5 gets its frames' fits on the next pooling, with the same profile."""
    frames, key = _lens_frames("fits", seed=70)
    h, w = frames[0].shape
    with ProfileStore(tmp_path / "fresh.sqlite") as store:
        fresh = _learn_frames(store, key, frames)
    assert _fits_stored(tmp_path / "fresh.sqlite") == (4, 4)

    db = tmp_path / "old.sqlite"
    with ProfileStore(db) as store:
        _learn_frames(store, key, frames[:3])
    con = sqlite3.connect(db)  # back to a v3 store, as an older release wrote it
    con.execute("ALTER TABLE pooled_frames DROP COLUMN family")
    con.execute("ALTER TABLE pooled_frames DROP COLUMN fit")
    con.execute("DELETE FROM schema_version WHERE version > 3")
    con.commit()
    con.close()
    with ProfileStore(db) as store:
        assert store.schema_version == SCHEMA_VERSION
        assert _fits_stored(db) == (0, 3)
        p = _learn_frames(store, key, frames[3:], first=3)  # fits the three older frames, once
    assert _fits_stored(db) == (4, 4)
    assert p.n_frames == 4
    np.testing.assert_allclose(p.model(w, h).log_field(), fresh.model(w, h).log_field(), atol=1e-9)


def test_the_profile_pools_every_frame_up_to_the_cap(tmp_path, monkeypatch):
    """Every frame refines the profile (the store pooled only 40 before), up to
    MAX_POOLED_FRAMES, chosen by frame id whatever the order of arrival."""
    import vigproc.core.pooling as pooling
    import vigproc.stores.profile_store as profile_store
    import vigproc.stores.profiles as profiles

    seen = []
    real = pooling.pool_family

    def spy(fits, *a, **k):
        seen.append(len(fits))
        return real(fits, *a, **k)

    monkeypatch.setattr(pooling, "pool_family", spy)
    shipped_cap = profiles.MAX_POOLED_FRAMES
    monkeypatch.setattr(profile_store, "MAX_POOLED_FRAMES", 3)
    frames, key = _lens_frames("cap", seed=80)
    h, w = frames[0].shape
    with ProfileStore(tmp_path / "a.sqlite") as store:
        a = _learn_frames(store, key, frames)
    assert seen == [1, 2, 3, 3]
    with ProfileStore(tmp_path / "b.sqlite") as store:  # the first three ids, arriving last
        b = None
        for i in (3, 2, 1, 0):
            b = _learn_frames(store, key, frames[i:i + 1], first=i)
    np.testing.assert_allclose(a.model(w, h).log_field(), b.model(w, h).log_field(), atol=1e-9)
    assert shipped_cap >= 100  # far beyond the 40 frames that stopped refining profiles before


# ----------------------------------------------------------------------------- argument validation


@pytest.mark.parametrize("size", [(float("nan"), 10), ("a", 10), (10, 0), (0.5, 10), (100.5, 10), (True, 1), (10, None)])
def test_bad_frame_sizes_are_typed_errors(size):
    lk = LensKey(make="nikon", model="nikon d800", lens="af-s nikkor 24-70mm f/2.8g ed", focal_mm=24.0, fnumber=4.0)
    with pytest.raises(ProfileStoreError, match="frame size"):
        ProfileKey.from_lens(lk, *size)
    p = Profile(key=KEY, theta=THETA_TRUE)
    with pytest.raises(ProfileStoreError, match="frame size"):
        p.model(*size)
    with pytest.raises(ProfileStoreError, match="frame size"):
        p.model(128, 0)  # was a ZeroDivisionError
    assert p.model(np.int64(6000), 4000.0).width == 6000  # whole numbers of any type are fine


def test_from_lens_needs_a_lens_key():
    with pytest.raises(ProfileStoreError, match="LensKey"):
        ProfileKey.from_lens(None, 6000, 4000)


@pytest.mark.parametrize("kwargs", [{"timeout": "x"}, {"timeout": float("nan")}, {"timeout": float("inf")},
                                    {"timeout": -1}, {"timeout": None}])
def test_store_bad_timeout_is_a_typed_error(tmp_path, kwargs):
    with pytest.raises(ProfileStoreError, match="timeout"):
        ProfileStore(tmp_path / "p.sqlite", **kwargs)
    assert list(tmp_path.iterdir()) == []  # nothing created


@pytest.mark.parametrize("path", [5, 1.5, ["p.sqlite"], "", "a\0b.sqlite"])
def test_store_bad_path_is_a_typed_error(tmp_path, monkeypatch, path):
    monkeypatch.chdir(tmp_path)
    with pytest.raises(ProfileStoreError, match="path"):
        ProfileStore(path)
    assert list(tmp_path.iterdir()) == []


def test_store_methods_refuse_bad_arguments_before_touching_the_store(tmp_path):
    with ProfileStore(tmp_path / "p.sqlite") as store:
        first = store.learn(KEY, synthetic_model(0))
        for bad in (None, "x", ("a", "b", "c", "d")):
            with pytest.raises(ProfileStoreError, match="ProfileKey"):
                store.get(bad)
            with pytest.raises(ProfileStoreError, match="ProfileKey"):
                store.delete(bad)
            with pytest.raises(ProfileStoreError, match="ProfileKey"):
                store.learn(bad, synthetic_model(1))
        for bad in (None, "model", THETA_TRUE):
            with pytest.raises(ProfileStoreError, match="VignettingModel"):
                store.learn(KEY, bad)
        for bad in (5, b"notes", ["a"]):
            with pytest.raises(ProfileStoreError, match="notes"):
                store.learn(KEY, synthetic_model(1), notes=bad)
        with pytest.raises(ProfileStoreError, match="LensKey"):
            store.lookup("canon", 6000, 4000)
        after = store.get(KEY)
        assert after.n_frames == first.n_frames == 1 and after.notes == first.notes
        assert store.learn(KEY, synthetic_model(1), notes="ok").notes.endswith("ok")  # valid calls unchanged


def test_junk_evidence_is_named_as_such(tmp_path):
    with ProfileStore(tmp_path / "p.sqlite") as store:
        for junk in (b"junk", b"", b"PK\x03\x04 not an npz"):
            with pytest.raises(ProfileStoreError, match="not frame evidence") as ei:
                store.learn(KEY, synthetic_model(0), evidence=junk)
            assert "pickle" not in str(ei.value)
        assert store.get(KEY) is None


# ----------------------------------------------------------------------------- between bins


@functools.lru_cache(maxsize=None)
def _pa_theta(k1: float, w: int, h: int) -> tuple[float, ...]:
    """Normalised θ of lensfun's pa field with this k1 (a least-squares fit each: once
    per k1; on a 40×60 grid, which fit_model_to_field says is ample for a smooth field)."""
    from vigproc.stores.lensfun import pa_field
    from vigproc.core.normalised import fit_model_to_field, normalise

    m, _ = fit_model_to_field(np.log(pa_field((40, 60), k1, 0.0, 0.0)), w, h)
    return tuple(normalise(m)[0])


def _pa_profile(lens_key, focal, fnumber, k1, w=180, h=120, sigma=0.01):
    from dataclasses import replace

    key = ProfileKey.from_lens(replace(lens_key, focal_mm=focal, fnumber=fnumber), w, h)
    return Profile(key=key, theta=np.array(_pa_theta(k1, w, h)), n_frames=5, trusted=True, field_sigma_ev=sigma)


def test_lookup_interpolates_between_a_lenss_bins(tmp_path):
    """Profiles at 24 mm and 70 mm f/4 answer for 40 mm f/4 (linear in log focal
    length), and with a third at 70 mm f/8 for 50 mm f/5.6 (bilinear); never beyond."""
    from dataclasses import replace as dc_replace

    from vigproc.stores.lensfun import pa_field

    lk = LensKey(make="nikon", model="nikon d800", lens="af-s nikkor 24-70mm f/2.8g ed", focal_mm=40.0, fnumber=4.0)
    w, h = 180, 120
    with ProfileStore(tmp_path / "p.sqlite") as store:
        store.put(_pa_profile(lk, 24.0, 4.0, -0.5))
        store.put(_pa_profile(lk, 70.0, 4.0, -0.42))
        got = store.lookup(lk, w, h)
        assert got is not None and got.notes.startswith("interpolated from") and got.trusted
        assert got.key == ProfileKey.from_lens(lk, w, h)
        t = math.log(40 / 23.6) / math.log(66.8 / 23.6)  # the bins' centres
        k1 = (1 - t) * -0.5 + t * -0.42
        want = np.log(pa_field((h, w), k1, 0.0, 0.0))
        err = np.std(got.model(w, h).log_field((h, w)) - want) / np.log(2)
        assert err < 0.02, err
        assert 0.01 < got.field_sigma_ev < 0.04  # the bins' σ and how far apart they are
        # beyond the bins: no interpolation, no answer
        assert store.lookup(dc_replace(lk, focal_mm=105.0), w, h) is None
        # another aperture needs bins on both sides
        assert store.lookup(dc_replace(lk, focal_mm=50.0, fnumber=5.6), w, h) is None
        store.put(_pa_profile(lk, 24.0, 8.0, -0.3))
        store.put(_pa_profile(lk, 70.0, 8.0, -0.1))
        mid = store.lookup(dc_replace(lk, focal_mm=50.0, fnumber=5.6), w, h)
        assert mid is not None and mid.notes.count("(") == 4
        fields = [store.lookup(dc_replace(lk, focal_mm=50.0, fnumber=n), w, h).model(w, h).log_field((h, w))
                  for n in (4.0, 8.0)]
        lo, hi = sorted(float(np.mean(f)) for f in fields)
        assert lo <= float(np.mean(mid.model(w, h).log_field((h, w)))) <= hi
        # an untrusted bin makes the interpolation untrusted
        store.put(dc_replace(_pa_profile(lk, 24.0, 4.0, -0.5), trusted=False))
        assert not store.lookup(lk, w, h).trusted
        assert store.lookup(lk, w, h, trusted_only=True) is None


@pytest.mark.parametrize("old", [5, 6, 7, 8])
def test_migrations_6_to_9_refit_the_frames_from_their_evidence(tmp_path, old):
    """A v5 store's frame fits were made before the colour weights, a v6 store's with the
    single-frame Cauchy scale, a v7 store's with the earlier chroma scale, a v8 store's
    without the chroma covariates: v6 to v9 drop them, and the next pooling fits each frame
    again from its evidence, so a profile never pools fits of two kinds."""
    from conftest import photo_like

    from vigproc.core.estimate import estimate, frame_evidence
    from vigproc.core.pooling import frame_fit, pool_family
    from vigproc.core.robust import evidence_copy

    _lens, pa = diverse_lenses(1)[0]
    h, w = 160, 240
    frames = [photo_like(h, w, seed=80 + i) * pa_field((h, w), pa.k1, pa.k2, pa.k3) for i in range(3)]
    key = ProfileKey("vigproc|test|v6", focal_bin(24.0), aperture_bin(2.8), aspect_label(w / h))
    db = tmp_path / "p.sqlite"
    with ProfileStore(db) as store:
        for i, f in enumerate(frames[:2]):
            m = estimate(f, "robust", channel_axis=None)
            store.learn(key, m.candidate or m, frame_id=f"f{i}", evidence=frame_evidence(f, channel_axis=None))
    con = sqlite3.connect(db)  # as the old version left it: its own (here: wrong) fits stored
    stale = con.execute("SELECT family FROM pooled_frames").fetchall()
    assert all(b is not None for (b,) in stale)
    con.execute("UPDATE pooled_frames SET family = (SELECT family FROM pooled_frames WHERE frame = 'f0')")
    con.execute("DELETE FROM schema_version WHERE version > ?", (old,))
    con.commit()
    con.close()
    with ProfileStore(db) as store:
        assert store.schema_version == SCHEMA_VERSION >= 9
        m = estimate(frames[2], "robust", channel_axis=None)
        p = store.learn(key, m.candidate or m, frame_id="f2", evidence=frame_evidence(frames[2], channel_axis=None))
    expected = pool_family([frame_fit(evidence_copy(frame_evidence(f, channel_axis=None))) for f in frames], w, h)
    np.testing.assert_allclose(p.model(w, h).log_field((h, w)), expected.log_field((h, w)), atol=1e-6)


def test_a_frame_with_too_few_usable_pixels_says_so(tmp_path):
    """Issue 37: a real 16 MP frame of the full moon on a black sky (90 % of its pixels 0)
    failed to learn with "evidence is not frame evidence": the too-few-pixels error is a
    ValueError too and was caught as a decoding failure. It now says what is wrong."""
    from conftest import photo_like

    from vigproc.core.estimate import estimate, frame_evidence

    h, w = 192, 288
    frame = np.zeros((h, w))
    yy, xx = np.mgrid[:h, :w]
    moon = (yy - h / 2) ** 2 + (xx - w / 2) ** 2 < 14 ** 2
    frame[moon] = 0.2 + 0.05 * photo_like(h, w, seed=3)[moon]
    m = estimate(frame, "robust", channel_axis=None)
    key = ProfileKey("vigproc|test|moon", focal_bin(24.0), aperture_bin(2.8), aspect_label(w / h))
    with ProfileStore(tmp_path / "p.sqlite") as store:
        with pytest.raises(ProfileStoreError, match=r"nothing to learn from this frame: too few usable pixels .* bins"):
            store.learn(key, m.candidate or m, frame_id="moon", evidence=frame_evidence(frame, channel_axis=None))
        with pytest.raises(ProfileStoreError, match="is not frame evidence"):  # garbage is still garbage
            store.learn(key, m.candidate or m, frame_id="junk", evidence=b"\x93NUMPY junk")
