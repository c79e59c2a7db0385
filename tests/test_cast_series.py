"""A lens's colour cast pooled from its frames in the profile store (issue 41)."""

from __future__ import annotations

import json
import sqlite3
from types import SimpleNamespace

import numpy as np
import pytest

from vigproc.core.cast_series import SCENE_SCATTER, SeriesSettings, check_record, frame_record, pool_cast
from vigproc.core.colour_difference import grey_cast_de
from vigproc.core.model import VignettingModel
from vigproc.errors import ProfileStoreError
from vigproc.stores.profiles import ProfileKey, ProfileStore, aperture_bin, aspect_label, focal_bin

W, H = 300, 200
CAST = np.array([0.12, -0.12])  # a corner shift of about ΔE00 5 (ln R/G, ln B/G)


def _frames(rng, n, cast=CAST, tau=SCENE_SCATTER):
    """n frames' quadrant shifts: the lens's cast in every quadrant plus a scene's own,
    heavy-tailed (Student t, 3 dof) at scale τ, as the clean bases' are."""
    x = cast[None, None, :] + tau * rng.standard_t(3, size=(n, 4, 2))
    return x, np.full((n, 4, 2), 0.05)


def _record(x, se):
    return frame_record(SimpleNamespace(sector_shift=tuple(map(tuple, x)), sector_se=tuple(map(tuple, se))))


def _key():
    return ProfileKey("cam|lens", focal_bin(24.0), aperture_bin(2.8), aspect_label(W / H))


def _model():
    cov = np.diag([4.0, 4.0, 1e-13, 1e-14, 1e-13] + [1e-4] * 7)
    return VignettingModel(W, H, center=(0.0, 0.0), p=(1 / 250**2, 0.0, 1 / 250**2), method="robust",
                           covariance=tuple(map(tuple, cov)))


def test_a_cast_emerges_from_a_series_and_the_scene_averages_down():
    rng = np.random.default_rng(0)
    x, se = _frames(rng, 25)
    one = pool_cast(x[:1], se[:1])
    assert not one.detected  # one frame never establishes a lens's cast
    many = pool_cast(x, se)
    assert many.detected and many.n_frames == 25
    truth = float(grey_cast_de(*CAST))
    assert abs(many.delta_e - truth) < 3 * many.delta_e_se + 0.5
    assert np.dot(many.shift, CAST) > 0.9 * np.linalg.norm(many.shift) * np.linalg.norm(CAST)
    # the uncertainty falls as 1/sqrt(N)
    nine = pool_cast(x[:9], se[:9])
    assert nine.delta_e_se / many.delta_e_se == pytest.approx(np.sqrt(25 / 9), rel=0.25)
    d = many.to_dict()
    json.dumps(d)
    assert "25 frames" in d["summary"] and "corner cast" in d["summary"]


def test_clean_series_are_rarely_called_cast():
    rng = np.random.default_rng(1)
    calls = [pool_cast(*_frames(rng, 9, cast=np.zeros(2))).detected for _ in range(200)]
    assert np.mean(calls) <= 0.05
    s = SeriesSettings()
    decisive = [pool_cast(*_frames(rng, 25, cast=2 * CAST)).decisive for _ in range(20)]
    assert np.mean(decisive) > 0.5 and s.decisive_frames <= 25


def test_bad_shapes_and_records():
    with pytest.raises(ValueError):
        pool_cast(np.zeros((3, 4)), np.zeros((3, 4)))
    with pytest.raises(ValueError):
        check_record({"shift": [[0, 0]] * 3, "se": [[0, 0]] * 3})
    with pytest.raises(ValueError):
        check_record({"shift": [[0, float("nan")]] * 4, "se": [[0, 0]] * 4})
    assert frame_record(SimpleNamespace(sector_shift=(), sector_se=())) is None


def test_store_pools_each_frame_once_and_reports(tmp_path):
    rng = np.random.default_rng(2)
    x, se = _frames(rng, 12)
    with ProfileStore(tmp_path / "p.sqlite") as st:
        assert st.cast_report(_key()) is None
        for i in range(12):
            st.learn(_key(), _model(), frame_id=f"frame{i}", cast=_record(x[i], se[i]))
        rep = st.cast_report(_key())
        # the same frames offered again (a restarted hot folder): nothing changes
        for i in range(12):
            st.learn(_key(), _model(), frame_id=f"frame{i}", cast=_record(x[i] + 1.0, se[i]))
        again = st.cast_report(_key())
        with pytest.raises(ProfileStoreError):
            st.learn(_key(), _model(), frame_id="bad", cast={"shift": "no"})
    assert rep.n_frames == again.n_frames == 12
    assert again.shift == rep.shift
    # the store pools what pool_cast pools (records keep 6 decimals)
    np.testing.assert_allclose(rep.shift, pool_cast(x, se).shift, atol=1e-5)
    con = sqlite3.connect(tmp_path / "p.sqlite")
    assert con.execute("SELECT count(*) FROM cast_frames").fetchone()[0] == 12
    con.close()


def test_the_report_follows_the_records_another_connection_adds(tmp_path):
    """Each corrected frame of a trusted lens asks for the cast: the report is kept until
    the lens's records change, here or in another process (a second store object)."""
    rng = np.random.default_rng(5)
    x, se = _frames(rng, 8)
    db = tmp_path / "p.sqlite"
    with ProfileStore(db) as reader, ProfileStore(db) as writer:
        for i in range(5):
            writer.learn(_key(), _model(), frame_id=f"f{i}", cast=_record(x[i], se[i]))
        first = reader.cast_report(_key())
        assert reader.cast_report(_key()) is first  # unchanged records: not pooled again
        writer.learn(_key(), _model(), frame_id="f5", cast=_record(x[5], se[5]))
        assert reader.cast_report(_key()).n_frames == first.n_frames + 1 == 6
        plan = reader.con.execute("EXPLAIN QUERY PLAN SELECT frame, record FROM cast_frames WHERE profile_id = 1 "
                                  "ORDER BY frame").fetchall()
        assert any("cast_frames_by_profile" in str(row) for row in plan), plan


def test_an_import_replacing_the_profile_drops_its_frames_casts(tmp_path):
    """An import replaces the profile and drops its pooled frames: their cast records go
    with them (a cast reported beside a profile none of its frames made is wrong)."""
    from vigproc.stores.profile_file import profile_from_dict, profile_to_dict

    rng = np.random.default_rng(6)
    x, se = _frames(rng, 3)
    with ProfileStore(tmp_path / "p.sqlite") as st:
        for i in range(3):
            st.learn(_key(), _model(), frame_id=f"f{i}", cast=_record(x[i], se[i]))
        assert st.cast_report(_key()).n_frames == 3
        st.put(profile_from_dict(profile_to_dict(st.get(_key()))))
        assert st.cast_report(_key()) is None
        st.learn(_key(), _model(), frame_id="f0", cast=_record(x[0], se[0]))  # learned again: counted again
        assert st.cast_report(_key()).n_frames == 1


def test_the_cast_travels_with_an_exported_profile(tmp_path):
    """`profile export` then `profile import` in another store: the lens reports the same
    cast there, and frames learned later pool with the imported records (each once)."""
    rng = np.random.default_rng(7)
    x, se = _frames(rng, 14)
    with ProfileStore(tmp_path / "a.sqlite") as a:
        for i in range(12):
            a.learn(_key(), _model(), frame_id=f"f{i}", cast=_record(x[i], se[i]))
        rep_a = a.cast_report(_key())
        a.export_file(_key(), tmp_path / "lens.json")
    d = json.loads((tmp_path / "lens.json").read_text())
    assert len(d["cast"]["frames"]) == 12
    with ProfileStore(tmp_path / "b.sqlite") as b:
        b.import_file(tmp_path / "lens.json")
        rep_b = b.cast_report(_key())
        assert rep_b is not None and rep_b.n_frames == 12 and rep_b.detected == rep_a.detected
        np.testing.assert_allclose(rep_b.shift, rep_a.shift, atol=1e-9)
        assert rep_b.delta_e == pytest.approx(rep_a.delta_e, abs=1e-9)
        b.import_file(tmp_path / "lens.json")  # imported again: replaced, not doubled
        assert b.cast_report(_key()).n_frames == 12
        for i in (12, 13):
            b.learn(_key(), _model(), frame_id=f"f{i}", cast=_record(x[i], se[i]))
        b.learn(_key(), _model(), frame_id="f13", cast=_record(x[13], se[13]))
        assert b.cast_report(_key()).n_frames == 14


@pytest.mark.parametrize("bad", [{"frames": "x"}, [], {"frames": [{"shift": [[0, 0]] * 3, "se": [[0, 0]] * 3}]},
                                 {"frames": [{"shift": [[0, 0]] * 4, "se": [[-1, 0]] * 4}]}])
def test_a_profile_file_with_a_damaged_cast_is_refused(tmp_path, bad):
    with ProfileStore(tmp_path / "a.sqlite") as a:
        x, se = _frames(np.random.default_rng(8), 1)
        a.learn(_key(), _model(), frame_id="f0", cast=_record(x[0], se[0]))
        a.export_file(_key(), tmp_path / "lens.json")
    d = json.loads((tmp_path / "lens.json").read_text())
    d["cast"] = bad
    (tmp_path / "bad.json").write_text(json.dumps(d))
    with ProfileStore(tmp_path / "b.sqlite") as b:
        with pytest.raises(ProfileStoreError, match="cast"):
            b.import_file(tmp_path / "bad.json")
        assert b.get(_key()) is None  # nothing stored


def test_a_store_from_before_cast_records_opens_and_migrates(tmp_path):
    from vigproc.stores.profiles import SCHEMA_VERSION

    db = tmp_path / "p.sqlite"
    with ProfileStore(db) as st:
        st.learn(_key(), _model(), frame_id="old")
    con = sqlite3.connect(db)  # as vigproc left it before the cast records
    con.execute("DROP TABLE cast_frames")  # its index goes with it
    con.execute("DELETE FROM schema_version WHERE version > 14")
    con.commit()
    con.close()
    rng = np.random.default_rng(3)
    x, se = _frames(rng, 1)
    with ProfileStore(db) as st:
        assert st.schema_version == SCHEMA_VERSION >= 15
        assert st.get(_key()).n_frames == 1 and st.cast_report(_key()) is None
        st.learn(_key(), _model(), frame_id="new", cast=_record(x[0], se[0]))
        assert st.cast_report(_key()).n_frames == 1
        # deleting the profile deletes its frames' records
        assert st.delete(_key())
    con = sqlite3.connect(db)
    assert con.execute("SELECT count(*) FROM cast_frames").fetchone()[0] == 0
    con.close()


def test_profile_show_reports_the_pooled_cast(tmp_path, monkeypatch, capsys):
    from vigproc.frontends.cli import main

    rng = np.random.default_rng(4)
    x, se = _frames(rng, 15)
    db = tmp_path / "p.sqlite"
    with ProfileStore(db) as st:
        for i in range(15):
            st.learn(_key(), _model(), frame_id=f"f{i}", cast=_record(x[i], se[i]))
        want = st.cast_report(_key())
    monkeypatch.setenv("VIGPROC_PROFILE_DB", str(db))
    assert main(["profile", "show", "0", "--json"]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert doc["colour_cast"]["frames"] == 15
    assert doc["colour_cast"]["detected"] == want.detected
    assert doc["colour_cast"]["delta_e"] == pytest.approx(want.delta_e, abs=1e-3)
    assert main(["profile", "show", "0"]) == 0
    out = capsys.readouterr().out
    assert "colour cast" in out and "(15 frames)" in out


def test_learning_as_you_go_records_each_frame_and_the_corrected_record_reports(tmp_path):
    from test_learn_as_you_go import _frames as dng_frames
    from test_learn_as_you_go import _out

    from vigproc.pipeline.processor import Processor, Settings

    paths, _ = dng_frames(tmp_path / "in", 6, seed=60)
    db = tmp_path / "p.sqlite"
    with ProfileStore(db) as store, Processor(Settings(learn=True), store=store) as proc:
        recs = [proc.process_file(p, _out(tmp_path / "out")).to_dict() for p in paths]
        again = proc.process_file(paths[0], _out(tmp_path / "again")).to_dict()  # counted once
        [prof] = store.list()
        rep = store.cast_report(prof.key)
    pooled = sum(r["learned"]["pooled"] for r in recs)
    assert not again["learned"]["pooled"]
    assert rep is not None and rep.n_frames == pooled == prof.n_frames
    after = [r for r in recs if r["source"] == "stored-profile"]
    assert after, "the series must reach trust"
    for r in after:  # what the lens's frames say so far, next to the revision that corrected it
        assert 1 <= r["lens_colour_cast"]["frames"] <= pooled
        assert "summary" in r["lens_colour_cast"]


def test_bench_frames_counts_series_of_different_bases():
    from test_colour_cast import scene

    from benchmarks.colour_detect import cast_for, detection_rates, series_rates

    bases = [scene(s) for s in range(6)]
    casts = [cast_for(10.0, 135.0, 40.0), cast_for(10.0, 315.0, 40.0)]
    r = detection_rates(bases, casts, frames=(1, 3, 4), series_count=40)
    # 4 frames are more than the 3 bases of a half: left out, not drawn with repeats
    assert [s["frames"] for s in r.series] == [1, 3]
    one, three = r.series
    for s in r.series:
        assert set(s["fixed"]) == {"clean", "luminance_only", "dE 10"}
        assert len(s["split"]) == 2
        for f in s["split"]:
            assert 0 <= f["clean"] <= 1 and 0 <= f["by_target"]["dE 10"] <= 1
    # one frame never establishes a lens's cast; three frames of a strong one mostly do, clean ones not
    assert one["fixed"]["dE 10"]["detected"] == 0
    assert three["fixed"]["dE 10"]["detected"] > 0.5 > three["fixed"]["clean"]["detected"]
    assert np.isnan(r.luminance_only.rate) and three["fixed"]["luminance_only"]["series"] == 0
    # the series pool frames of one cast: the row's frames carry which
    assert set(r.by_target[0].cast_index) == {0, 1}
    with pytest.raises(ValueError):
        series_rates(r, 0)
