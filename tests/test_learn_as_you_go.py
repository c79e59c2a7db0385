"""Learn as you go (issue 38): a correct run also pools each frame into its lens's profile,
exactly once per file content; once the profile is trusted it corrects the series with one
field; frames that would mix lenses are not pooled, and the record says why."""

import json
import shutil
import subprocess
import sys
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
import pytest

from vigproc.core.model import FitQuality, VignettingModel
from vigproc.errors import VigprocError
from vigproc.io.exif import LensKey
from vigproc.pipeline.learning import SERIES_GAP_S, SteadyProfiles, field_change_ev, pooling_refusal
from vigproc.pipeline.processor import Processor, Settings
from vigproc.stores.profiles import ProfileStore

from conftest import photo_like, run_cli

VIGPROC = [sys.executable, "-m", "vigproc.frontends.cli"]
#: A Nikon D70 with its kit zoom at 70 mm: an interchangeable-lens body (lensfun: "Nikon F AF").
D70_EXIF = {"Make": "NIKON CORPORATION", "Model": "NIKON D70", "LensMake": "Nikon",
            "LensModel": "AF-S DX Zoom-Nikkor 18-70mm f/3.5-4.5G IF-ED",
            "FocalLength": 70, "FNumber": 4.5, "FocalLengthIn35mmFormat": 105}
#: The same body with no lens named (an adapted manual lens, say).
D70_NO_LENS = {"Make": "NIKON CORPORATION", "Model": "NIKON D70", "FocalLength": 50, "FNumber": 2.8}
H, W = 256, 384


def _frames(folder: Path, n: int, exif=D70_EXIF, seed: int = 20, power: float = 1.0) -> tuple[list[Path], np.ndarray]:
    """``n`` DNG frames of one lens setting carrying a lensfun lens's fall-off (to the
    ``power``: a stronger one): the paths and the true log2 field."""
    from dngfixture import make_dngs

    from vigproc.stores.lensfun import diverse_lenses, pa_field

    _, pa = diverse_lenses(1)[0]
    field = pa_field((H, W), pa.k1, pa.k2, pa.k3) ** power
    folder.mkdir(parents=True, exist_ok=True)
    paths = [folder / f"frame {i:02d}.dng" for i in range(n)]
    # one shoot: a frame a minute (a series of its lens setting, pipeline.learning)
    make_dngs([(p, dict(width=W, height=H, field=field, scene=photo_like(H, W, seed=seed + i),
                        exif={"DateTimeOriginal": f"2024:05:06 07:{i:02d}:00", **exif})) for i, p in enumerate(paths)])
    return paths, np.log2(field)


def _out(path: Path) -> Path:
    path.mkdir(parents=True, exist_ok=True)
    return path


def _log2_field(rec: dict) -> np.ndarray:
    m = VignettingModel.from_dict(rec["model"])
    return m.log_field((m.height, m.width)) / np.log(2.0)


@pytest.fixture(scope="module")
def series(tmp_path_factory):
    return _frames(tmp_path_factory.mktemp("series"), 7)


def _later_copy(path: Path, folder: Path, *, days: int) -> Path:
    """A copy of a fixture frame whose DateTimeOriginal is ``days`` later (another series)."""
    if shutil.which("exiftool") is None:
        pytest.skip("rewriting a frame's capture time needs exiftool")
    folder.mkdir(parents=True, exist_ok=True)
    out = folder / path.name
    shutil.copyfile(path, out)
    subprocess.run(["exiftool", "-q", "-overwrite_original", f"-DateTimeOriginal+=0:0:{days} 0:0:0", "--", str(out)],
                   check=True, capture_output=True)
    return out


# ------------------------------------------------------------------ which frames pool
@dataclass
class _InCamera:
    reason: str
    evidence: str = "CanonCustom:PeripheralIlluminationCorr"


def _key(**kw) -> LensKey:
    base = dict(make="nikon corporation", model="nikon d70", lens="af-s dx zoom-nikkor 18-70mm f/3.5-4.5g if-ed",
                lens_serial=None, focal_mm=70.0, fnumber=4.5, focus_distance_m=None)
    base.update(kw)
    return LensKey(**base)


def test_pooling_refusal_keeps_lenses_apart():
    assert pooling_refusal(_key()) is None
    assert "lens is unknown" in pooling_refusal(None)
    assert "interchangeable lenses" in pooling_refusal(_key(lens=None))
    # a compact's fixed lens needs no name: its frames are one lens
    assert pooling_refusal(_key(make="canon", model="canon powershot s95", lens=None)) is None
    assert "does not know the camera" in pooling_refusal(_key(make="acme", model="x1", lens=None))
    assert "already corrected" in pooling_refusal(_key(), _InCamera("Canon Peripheral Illumination Correction on"))
    assert "cannot have taken it" in pooling_refusal(_key(lens_problem="shot at 300 mm, outside the 18-70 mm"))


def test_learning_is_a_correct_mode_setting():
    with pytest.raises(VigprocError, match="correct mode"):
        Settings(mode="estimate", learn=True)
    assert Settings(learn=True).needs_store
    # settings that do not learn keep their dict (job ids, sidecars of earlier runs)
    assert "learn" not in Settings().to_dict() and Settings(learn=True).to_dict()["learn"] is True


# ------------------------------------------------------------------ the processor path
def test_a_series_is_pooled_once_and_corrected_by_one_field_after_trust(series, tmp_path):
    paths, _ = series
    db = tmp_path / "p.sqlite"
    recs = []
    with ProfileStore(db) as store, Processor(Settings(learn=True), store=store) as proc:
        for p in paths:
            recs.append(proc.process_file(p, _out(tmp_path / "out")).to_dict())
        # a rerun and a copy under another name: the same content, not pooled again
        again = proc.process_file(paths[0], _out(tmp_path / "again")).to_dict()
        copy = tmp_path / "copy.dng"
        shutil.copyfile(paths[1], copy)
        copied = proc.process_file(copy, _out(tmp_path / "again")).to_dict()
        [prof] = store.list()
    assert prof.n_frames == len(paths)
    assert [r["learned"]["frames"] for r in recs] == list(range(1, len(paths) + 1))
    assert all(r["learned"]["pooled"] and r["profile"] == str(prof.key) for r in recs)
    for r in (again, copied):
        assert not r["learned"]["pooled"] and "already pooled" in r["learned"]["reason"]
        assert r["learned"]["frames"] == len(paths)
    trusted_at = next(i for i, r in enumerate(recs) if r["learned"]["trusted"])
    assert trusted_at < len(paths) - 2, "the series must reach trust with frames to spare"
    # before trust: each frame estimated alone, or the profile so far where it is surer than the frame;
    # after it: the stored profile, one revision, one field
    assert recs[0]["source"] == "estimate"
    assert all(r["source"] in ("estimate", "profile-evidence") for r in recs[:trusted_at + 1])
    for r in recs[:trusted_at + 1]:
        if r["source"] == "profile-evidence":
            ev = r["profile_evidence"]
            assert 2 * ev["profile_sigma_ev"] < ev["frame_sigma_ev"] and ev["frames"] >= 3
            assert r["applied"] and "not_applied_rule" not in r, r  # the profile's field is applied
    after = recs[trusted_at + 1:]
    assert all(r["source"] == "stored-profile" and r["applied"] for r in after)
    assert len({json.dumps(r["profile_applied"], sort_keys=True) for r in after}) == 1
    first = _log2_field(after[0])
    for r in after[1:]:
        np.testing.assert_array_equal(_log2_field(r), first)
    assert "learned into profile" in recs[0]["learned"]["summary"] and "not yet trusted" in recs[0]["learned"][
        "summary"]


def test_a_settled_profile_corrects_without_pooling(series, tmp_path, monkeypatch):
    import vigproc.pipeline.learning as learning

    monkeypatch.setattr(learning, "SETTLED_FRAMES", 5)
    paths, _ = series
    with ProfileStore(tmp_path / "p.sqlite") as store, Processor(Settings(learn=True), store=store) as proc:
        recs = [proc.process_file(p, _out(tmp_path / "out")).to_dict() for p in paths]
        [prof] = store.list()
        # the next series (a day later) is corrected by the settled profile, still not pooled
        nxt = proc.process_file(_later_copy(paths[0], tmp_path / "next", days=1), _out(tmp_path / "next-out")).to_dict()
    assert prof.n_frames == 5
    settled = [r for r in recs if not r["learned"]["pooled"]]
    assert len(settled) == len(paths) - 5
    assert all(r["source"] == "stored-profile" and "settled (5 frames)" in r["learned"]["reason"] for r in settled)
    # within the series the revision applied at trust stays: one field for all its frames after trust
    after = [r for r in recs if r["source"] == "stored-profile"]
    assert len({r["profile_applied"]["revision"] for r in after}) == 1
    assert {r["profile_applied"]["frames"] for r in after} < {1, 2, 3, 4}
    assert nxt["profile_applied"]["frames"] == 5 and not nxt["learned"]["pooled"]


def test_a_profile_that_moved_is_applied_only_at_a_series_boundary(series, tmp_path):
    """SteadyProfiles (a store without applied revisions: held per processor) keeps a
    revision for the whole series however far the stored profile moves, and takes the
    stored one at the next series (a gap in the frames' times beyond SERIES_GAP_S)."""
    paths, _ = series
    with ProfileStore(tmp_path / "p.sqlite") as store, Processor(Settings(learn=True), store=store) as proc:
        for p in paths[:4]:
            proc.process_file(p, _out(tmp_path / "out"))
        steady = SteadyProfiles(store)
        key = LensKey.__new__(LensKey)  # not used: lookups go through a stub below
        [prof] = store.list()

        class Stub:
            def __init__(self, p):
                self.p = p

            def lookup(self, *a, trusted_only=False):
                return None if trusted_only and not self.p.trusted else self.p

        def at(t, stub):
            steady.store = stub
            steady.at(t)
            return steady.lookup(key, W, H, trusted_only=True)

        t0 = 1.0e9
        assert at(t0, Stub(prof)) is prof and steady.new_series
        moved = replace(prof, theta=prof.theta * 1.5)
        assert field_change_ev(prof, moved) > 0.05
        # within the series, however far the stored profile moved: the same revision
        assert at(t0 + 60, Stub(moved)) is prof and not steady.new_series
        assert at(t0 + 60 + SERIES_GAP_S, Stub(moved)) is prof  # a gap of exactly the limit: still the series
        # frames that disagree took the stored profile's trust away: the series keeps its field
        assert at(t0 + 90 + SERIES_GAP_S, Stub(replace(moved, trusted=False))) is prof
        # a gap beyond the limit: a new series, with the profile as stored now
        t1 = t0 + 91 + 2 * SERIES_GAP_S + 1
        assert at(t1, Stub(moved)) is moved and steady.new_series
        assert at(t1 + 5, Stub(prof)) is moved
        # a frame of the other clock (no capture time) neither ends nor extends the series
        assert at(None, Stub(prof)) is moved
        # a bin never applied here that is not trusted: no profile, as the store says
        fresh = SteadyProfiles(Stub(replace(prof, trusted=False)))
        fresh.at(t0)
        assert fresh.lookup(key, W, H, trusted_only=True) is None



def _trusted_then_one_more(paths, db, out):
    """Learn the first 3 frames into the store ``db`` (the profile is then trusted), then
    a 4th: the stored profile after each step."""
    with ProfileStore(db) as store, Processor(Settings(mode="learn"), store=store) as proc:
        for p in paths[:3]:
            proc.process_file(p, _out(out))
        [p3] = store.list()
        proc.process_file(paths[3], _out(out))
        [p4] = store.list()
    return p3, p4

def test_the_store_replaces_the_applied_revision_only_at_a_series_boundary(series, tmp_path):
    """ProfileStore.series_revision: one transaction per boundary; frames inside the
    series' span write nothing; two stores (two workers) agree."""
    paths, _ = series
    db = tmp_path / "p.sqlite"
    p3, p4 = _trusted_then_one_more(paths, db, tmp_path / "out")
    assert p3.trusted and p4.trusted
    g = 100.0
    with ProfileStore(db) as s1, ProfileStore(db) as s2:
        r3, got, new = s1.series_revision(p3, p3.key, at=0.0, clock="capture", gap=g)
        assert new and got.n_frames == 3
        # worker 2 finds p4 stored, in the same series: it follows r3 and extends the span
        assert s2.series_revision(p4, p4.key, at=50.0, clock="capture", gap=g)[:3:2] == (r3, False)
        assert s2.series_revision(p4, p4.key, at=149.0, clock="capture", gap=g)[:3:2] == (r3, False)
        assert s1.series_revision(p4, p4.key, at=-100.0, clock="capture", gap=g)[:3:2] == (r3, False)
        # an arrival-clock frame is not compared with capture times
        assert s1.series_revision(p4, p4.key, at=1e12, clock="arrival", gap=g)[:3:2] == (r3, False)
        # past the span [-100, 149] by more than the gap: a new series, the stored profile now
        r4, got, new = s2.series_revision(p4, p4.key, at=250.0, clock="capture", gap=g)
        assert new and r4 != r3 and got.n_frames == 4
        # worker 1, a frame of that new series with its older read of the store: follows
        assert s1.series_revision(p3, p3.key, at=260.0, clock="capture", gap=g)[:3:2] == (r4, False)
        # an untrusted stored profile at a boundary: the revision stays, the series restarts
        r, got, new = s1.series_revision(replace(p4, trusted=False), p4.key, at=1000.0, clock="capture", gap=g)
        assert (r, new) == (r4, True)
        # the explicit command (apply_revision) opens a series at the next frame
        r3b, _ = s1.apply_revision(p3, replaces=r4)
        assert r3b == r3
        assert s2.series_revision(p4, p4.key, at=5000.0, clock="capture", gap=g)[:3:2] == (r3, False)
        with pytest.raises(VigprocError):
            s1.series_revision(p4, p4.key, at=float("nan"), clock="capture", gap=g)


def test_two_workers_apply_one_revision_after_trust_and_follow_a_refresh(series, tmp_path):
    """Two processors (as two workers would be) over one store file, frames interleaved:
    after trust both apply the store's applied revision (same id, identical parameters);
    when one finds the stored profile moved beyond its tolerance it replaces the
    revision and the other, and a restarted worker, follow."""
    paths, _ = series
    db = tmp_path / "p.sqlite"
    with ProfileStore(db) as s1, ProfileStore(db) as s2, \
            Processor(Settings(learn=True), store=s1) as a, Processor(Settings(learn=True), store=s2) as b:
        recs = [(a, b)[i % 2].process_file(p, _out(tmp_path / "out")).to_dict() for i, p in enumerate(paths)]
        trusted_at = next(i for i, r in enumerate(recs) if r["learned"]["trusted"])
        after = recs[trusted_at + 1:]
        assert len(after) >= 2, "the series must reach trust with a frame to spare for each worker"
        assert all(r["source"] == "stored-profile" for r in after)
        [rev] = {r["profile_applied"]["revision"] for r in after}
        first = _log2_field(after[0])
        for r in after[1:]:
            np.testing.assert_array_equal(_log2_field(r), first)
        [prof] = s1.list()
        rev_now, applied = s2.applied_revision(prof.key)
        assert rev_now == rev and applied.n_frames < prof.n_frames  # the store moved on; the series did not
        # a frame of the next series (its capture time a day later): worker a replaces the
        # revision by the stored profile; b, with a frame of that series, follows
        ra = a.process_file(_later_copy(paths[0], tmp_path / "next", days=1), _out(tmp_path / "again")).to_dict()
        rb = b.process_file(_later_copy(paths[1], tmp_path / "next", days=1), _out(tmp_path / "again")).to_dict()
    with ProfileStore(db) as s3, Processor(Settings(learn=True), store=s3) as c:  # a restart
        rc = c.process_file(_later_copy(paths[2], tmp_path / "next", days=1), _out(tmp_path / "again")).to_dict()
    new = {r["profile_applied"]["revision"] for r in (ra, rb, rc)}
    assert len(new) == 1 and rev not in new
    assert {r["profile_applied"]["frames"] for r in (ra, rb, rc)} == {len(paths)}
    np.testing.assert_array_equal(_log2_field(ra), _log2_field(rb))
    np.testing.assert_array_equal(_log2_field(ra), _log2_field(rc))
    assert np.any(_log2_field(ra) != first)
    assert ra["model"] == rb["model"] == rc["model"]  # identical parameters, not only fields


def test_the_applied_revision_is_a_compare_and_set(series, tmp_path):
    paths, _ = series
    db = tmp_path / "p.sqlite"
    p3, p4 = _trusted_then_one_more(paths, db, tmp_path / "out")
    with ProfileStore(db) as s1, ProfileStore(db) as s2:
        assert s1.applied_revision(p3.key) is None
        r3, got = s1.apply_revision(p3)
        np.testing.assert_array_equal(got.theta, p3.theta)
        assert got.n_frames == 3
        assert s2.apply_revision(p4)[0] == r3  # one is there already: INSERT only if absent
        r4, got = s2.apply_revision(p4, replaces=r3)  # compare-and-set: it still was r3
        assert r4 != r3 and got.n_frames == 4
        assert s1.apply_revision(p3, replaces=r3)[0] == r4  # lost the race: follows the winner
        assert s1.applied_revision(p3.key)[0] == r4
        s1.put(p3)  # a profile replaced by hand: its applied revision goes with it
        assert s2.applied_revision(p3.key) is None
        assert s2.apply_revision(p4)[0] == r4
        assert s2.delete(p4.key) and s1.applied_revision(p4.key) is None
        s1.put(p3)
        r3, _ = s1.apply_revision(p3)
    # a damaged applied revision is not fatal: it reads as none and the next worker replaces it
    import sqlite3

    con = sqlite3.connect(db)
    con.execute("UPDATE applied_profiles SET profile = '{\"schema\": 1'")
    con.commit()
    con.close()
    with ProfileStore(db) as s1:
        assert s1.applied_revision(p3.key) is None
        assert s1.apply_revision(p3)[0] == r3 and s1.applied_revision(p3.key)[0] == r3


def test_a_store_from_before_applied_revisions_opens_and_migrates(series, tmp_path):
    import sqlite3

    from vigproc.stores.profiles import SCHEMA_VERSION

    paths, _ = series
    db = tmp_path / "p.sqlite"
    with ProfileStore(db) as store, Processor(Settings(mode="learn"), store=store) as proc:
        for p in paths[:3]:
            proc.process_file(p, _out(tmp_path / "out"))
    con = sqlite3.connect(db)
    con.execute("DROP TABLE applied_profiles")
    con.execute("DELETE FROM schema_version WHERE version > 11")
    con.commit()
    con.close()
    with ProfileStore(db) as store:
        assert store.schema_version == SCHEMA_VERSION >= 13
        [prof] = store.list()
        assert prof.n_frames == 3 and store.applied_revision(prof.key) is None
        rev, _ = store.apply_revision(prof)
        assert store.applied_revision(prof.key)[0] == rev


def test_frames_of_an_unnamed_lens_on_an_interchangeable_body_are_corrected_not_pooled(tmp_path):
    paths, _ = _frames(tmp_path / "in", 2, exif=D70_NO_LENS, seed=40)
    with ProfileStore(tmp_path / "p.sqlite") as store, Processor(Settings(learn=True), store=store) as proc:
        recs = [proc.process_file(p, _out(tmp_path / "out")).to_dict() for p in paths]
        assert store.list() == []
    for r in recs:
        assert r["learned"]["pooled"] is False and "interchangeable lenses" in r["learned"]["reason"]
        assert r["source"] == "estimate" and "profile" not in r


# ------------------------------------------------------------------ front ends
def test_batch_learns_by_default_with_two_workers_and_a_rerun_pools_nothing(series, tmp_path, monkeypatch):
    paths, _ = series
    # the command in this process (its two workers are processes of their own)
    monkeypatch.setenv("VIGPROC_PROFILE_DB", str(tmp_path / "p.sqlite"))
    out = tmp_path / "out"
    r = run_cli("batch", paths[0].parent, "--mode", "correct", "-o", out, "--workers", "2", "--no-progress", "--json")
    assert r.returncode == 0, r.stderr
    summary = json.loads(r.stdout)
    assert summary["processed"] == len(paths)
    [(key, prof)] = summary["profiles"].items()
    assert prof["n_frames"] == len(paths) and prof["trusted"]
    recs = [json.loads(p.read_text()) for p in sorted(out.glob("*.vigproc.json"))]
    assert sorted(r["learned"]["frames"] for r in recs) == list(range(1, len(paths) + 1))  # concurrent, none lost
    assert any(r["source"] == "stored-profile" for r in recs)
    # every revision a worker applied is within the stated tolerance of the final profile
    with ProfileStore(tmp_path / "p.sqlite") as store:
        [final] = store.list()
    for rec in recs:
        if rec["source"] == "stored-profile":
            used = _log2_field(rec)
            now = final.model(W, H)
            assert np.sqrt(np.mean((used - now.log_field((H, W)) / np.log(2.0)) ** 2)) < 0.04
    # a new job over the same files (other output folder): every content is pooled already (the
    # store keys frames by content, whichever worker asks: one here, no pool of processes again)
    r = run_cli("batch", paths[0].parent, "--mode", "correct", "-o", tmp_path / "out2", "--workers", "1",
                "--no-progress")
    assert r.returncode == 0, r.stderr
    with ProfileStore(tmp_path / "p.sqlite") as store:
        assert [p.n_frames for p in store.list()] == [len(paths)]
    # --no-learn: nothing pooled, nothing said about it
    monkeypatch.setenv("VIGPROC_PROFILE_DB", str(tmp_path / "q.sqlite"))
    r = run_cli("batch", paths[0].parent, "--mode", "correct", "-o", tmp_path / "out3", "--workers", "1",
                "--no-progress", "--no-learn")
    assert r.returncode == 0, r.stderr
    with ProfileStore(tmp_path / "q.sqlite") as store:
        assert store.list() == []
    assert all("learned" not in json.loads(p.read_text()) for p in (tmp_path / "out3").glob("*.vigproc.json"))


def test_correct_learns_into_a_store_it_is_given_only(series, tmp_path, monkeypatch):
    paths, _ = series
    monkeypatch.setenv("VIGPROC_PROFILE_DB", str(tmp_path / "default.sqlite"))
    r = run_cli("correct", paths[0], "-o", tmp_path / "a", "--json")  # in this process: not about the process
    assert r.returncode == 0, r.stderr
    assert "learned" not in json.loads(r.stdout)["results"][0]
    db = tmp_path / "given.sqlite"
    r = run_cli("correct", *paths[:2], "-o", tmp_path / "b", "--profile-db", db, "--json")
    assert r.returncode == 0, r.stderr
    assert [x["learned"]["frames"] for x in json.loads(r.stdout)["results"]] == [1, 2]


@pytest.mark.skipif(shutil.which("exiftool") is None, reason="the DNG fixture needs exiftool for its EXIF")
def test_watch_learns_by_default_and_a_frame_pooled_before_a_crash_is_not_pooled_again(series, tmp_path):
    """A frame pooled by a worker that died before its outputs and journal entry were
    written (simulated: pooled here first) is retried by the daemon: corrected, and said to
    be pooled already; two workers pool the others concurrently, each once."""
    import signal
    import time

    paths, _ = series
    in_dir, out_dir, db = tmp_path / "in", tmp_path / "out", tmp_path / "p.sqlite"
    in_dir.mkdir()
    n = 5
    for p in paths[:n]:
        shutil.copyfile(p, in_dir / p.name)
    with ProfileStore(db) as store, Processor(Settings(learn=True), store=store) as proc:
        proc.process_file(in_dir / paths[0].name, _out(tmp_path / "crashed"))
    log = tmp_path / "watch.log"
    with open(log, "wb") as fh:
        d = subprocess.Popen([*VIGPROC, "watch", str(in_dir), "-o", str(out_dir), "--workers", "2", "--settle", "0.2",
                              "--log-json", "--profile-db", str(db), "--output-format", "tiff16"],
                             stdout=subprocess.DEVNULL, stderr=fh)
        try:
            deadline = time.monotonic() + 600
            while len(list(out_dir.glob("*.vigproc.json"))) < n and time.monotonic() < deadline and d.poll() is None:
                time.sleep(0.2)
            time.sleep(0.5)  # the journal entry of the last one
        finally:
            d.send_signal(signal.SIGTERM)
            assert d.wait(timeout=120) == 0
    recs = {p.name: json.loads(p.read_text()) for p in out_dir.glob("*.vigproc.json")}
    assert len(recs) == n, log.read_text()[-3000:]
    with ProfileStore(db) as store:
        assert [p.n_frames for p in store.list()] == [n]  # each content pooled once
    first = recs[f"{paths[0].name}.vigproc.json"]
    assert first["learned"]["pooled"] is False and "already pooled" in first["learned"]["reason"]
    pooled = sorted(r["learned"]["frames"] for r in recs.values() if r["learned"]["pooled"])
    assert pooled == list(range(2, n + 1))  # two workers, one store: no frame lost, none twice
    events = [json.loads(x) for x in log.read_text().splitlines() if x.startswith("{")]
    done = [e for e in events if e.get("event") == "done"]
    assert len(done) == n and all(e.get("learned") for e in done)
    assert sum("learned into profile" in e["msg"] for e in done) == n - 1
    assert any("already pooled" in e["msg"] for e in done)


def test_the_frame_pooled_is_the_one_read_not_its_correction(series, tmp_path):
    """A frame the processor read is corrected in place (its codes become the output's):
    learning as you go pools it first, so the profile is the one learn mode makes of the
    same file, not one of a corrected (flat) frame."""
    paths, _ = series
    with ProfileStore(tmp_path / "a.sqlite") as store, Processor(Settings(learn=True), store=store) as proc:
        rec = proc.process_file(paths[0], _out(tmp_path / "out")).to_dict()
        [going] = store.list()
    with ProfileStore(tmp_path / "b.sqlite") as store, Processor(Settings(mode="learn"), store=store) as proc:
        proc.process_unwritten(paths[0])
        [learned] = store.list()
    assert rec["learned"]["pooled"], rec["learned"]
    a, b = going.model(W, H), learned.model(W, H)
    fa, fb = a.log_field((H, W)) / np.log(2.0), b.log_field((H, W)) / np.log(2.0)
    assert fb.min() < -0.1  # the lens's fall-off, pooled from the uncorrected frame
    np.testing.assert_allclose(fa, fb, atol=0.01)


def _count_estimates(monkeypatch) -> dict[str, int]:
    """Count the frame fits: the default estimate and the robust fit with evidence that
    learning used to make of the same frame."""
    import vigproc.core.estimate as est
    import vigproc.core.robust as rob

    calls = {"default": 0, "robust-with-evidence": 0}

    def counted(name, fn):
        def wrapper(*a, **kw):
            calls[name] += 1
            return fn(*a, **kw)
        return wrapper

    monkeypatch.setattr(est, "estimate_default", counted("default", est.estimate_default))
    monkeypatch.setattr(rob, "estimate_robust_with_evidence",
                        counted("robust-with-evidence", rob.estimate_robust_with_evidence))
    return calls


def test_a_frame_is_estimated_once_while_learning(series, tmp_path, monkeypatch):
    """Before trust, the correction's estimate is the one pooled (with the frame's
    evidence, binned, not fitted again): one fit a frame, DNG and JPEG alike; a frame the
    profile corrects is estimated once, for its pooling."""
    from vigproc.io.images import read_image, write_image

    paths, _ = series
    calls = _count_estimates(monkeypatch)
    jpg = tmp_path / "frame.jpg"
    img, _ = read_image(paths[5])
    write_image(jpg, np.clip(img / img.max(), 0, 1).astype(np.float32), bit_depth="uint8", transfer="srgb", quality=95)
    if shutil.which("exiftool") is None:
        pytest.skip("writing the JPEG's EXIF needs exiftool")
    subprocess.run(["exiftool", "-q", "-overwrite_original", "-tagsFromFile", str(paths[5]), "-all:all", "--",
                    str(jpg)], check=True, capture_output=True)
    with ProfileStore(tmp_path / "p.sqlite") as store, Processor(Settings(learn=True), store=store) as proc:
        per_frame = []
        for p in [paths[0], jpg, *paths[1:5]]:
            before = dict(calls)
            rec = proc.process_file(p, _out(tmp_path / "out")).to_dict()
            per_frame.append((rec["source"], rec["learned"]["pooled"],
                              sum(calls.values()) - sum(before.values()), calls["default"] - before["default"]))
    assert per_frame[1][1], "the JPEG is pooled"
    for source, pooled, fits, default in per_frame:
        assert pooled and fits == 1, per_frame
        # estimated alone (or the profile so far chosen over it): the correction's default estimate,
        # pooled as it is; corrected by the trusted profile: one fit, for the pooling
        assert default == (0 if source == "stored-profile" else 1), per_frame
    assert {s for s, *_ in per_frame} & {"estimate", "profile-evidence"}


def test_profile_apply_starts_a_new_series_by_hand(series, tmp_path):
    paths, _ = series
    db = tmp_path / "p.sqlite"
    with ProfileStore(db) as store, Processor(Settings(mode="learn"), store=store) as proc:
        proc.process_file(paths[0], _out(tmp_path / "out"))
    r = run_cli("profile", "--profile-db", db, "apply", "0")
    assert r.returncode != 0 and "not trusted" in r.stderr and "Traceback" not in r.stderr
    with ProfileStore(db) as store, Processor(Settings(mode="learn"), store=store) as proc:
        for p in paths[1:4]:
            proc.process_file(p, _out(tmp_path / "out"))
        [prof] = store.list()
        assert prof.trusted
        old, _, _ = store.series_revision(prof, prof.key, at=0.0, clock="capture", gap=SERIES_GAP_S)
        proc.process_file(paths[4], _out(tmp_path / "out"))  # the store moves on; the series keeps its revision
        [moved] = store.list()
        assert store.series_revision(moved, moved.key, at=60.0, clock="capture", gap=SERIES_GAP_S)[0] == old
    r = run_cli("profile", "--profile-db", db, "apply", "0")
    assert r.returncode == 0, r.stderr
    with ProfileStore(db) as store:
        rev, got, new = store.series_revision(moved, moved.key, at=120.0, clock="capture", gap=SERIES_GAP_S)
    assert rev != old and got.n_frames == moved.n_frames == 5 and rev in r.stdout


def test_a_series_keeps_its_field_however_far_the_stored_profile_moves(series, tmp_path):
    """After trust, frames of one series get one field even when another worker pools frames
    that move the stored profile far (here: frames of twice the fall-off); the refresh
    rule this replaced changed the field in mid-series at a 0.02 EV move."""
    paths, _ = series
    strong, _ = _frames(tmp_path / "strong", 7, seed=60, power=2.0)
    with ProfileStore(tmp_path / "p.sqlite") as store, Processor(Settings(learn=True), store=store) as proc, \
            Processor(Settings(mode="learn"), store=store) as other:
        recs = [proc.process_file(p, _out(tmp_path / "out")).to_dict() for p in paths[:5]]
        [rev] = {r["profile_applied"]["revision"] for r in recs if r["source"] == "stored-profile"}
        for p in strong:
            other.process_file(p, _out(tmp_path / "other"))
        [moved] = store.list()
        _, applied = store.applied_revision(moved.key)
        assert field_change_ev(applied, moved) > 0.04, "the stored profile must have moved far"
        recs += [proc.process_file(p, _out(tmp_path / "out")).to_dict() for p in paths[5:]]
    after = [r for r in recs if r["source"] == "stored-profile"]
    assert len(after) >= 3 and {r["profile_applied"]["revision"] for r in after} == {rev}
    for r in after[1:]:
        np.testing.assert_array_equal(_log2_field(r), _log2_field(after[0]))


def test_the_profile_so_far_is_chosen_only_where_it_is_surer_than_the_frame(series, tmp_path):
    from vigproc.pipeline.guard import guard
    from vigproc.pipeline.learning import prefer_profile

    paths, _ = series
    with ProfileStore(tmp_path / "p.sqlite") as store, Processor(Settings(mode="learn"), store=store) as proc:
        for p in paths[:2]:
            proc.process_file(p, _out(tmp_path / "out"))
        [two] = store.list()
    assert not two.trusted and two.n_frames == 2
    two = replace(two, n_frames=3)  # as if a third frame had not moved it
    own = VignettingModel(W, H, p=(1 / 300**2, 0.0, 1 / 300**2))
    sure = replace(two, field_sigma_ev=0.01)

    def frame(sigma):
        return replace(own, quality=FitQuality(confidence=0.9, field_sigma_ev=sigma))

    m, why = prefer_profile(frame(0.05), sure, W, H)
    assert why is not None and why["profile_sigma_ev"] == 0.01 and why["frame_sigma_ev"] == 0.05
    np.testing.assert_array_equal(m.log_field((H, W)), two.model(W, H).log_field((H, W)))
    assert m.quality.confidence > 0.5 and not m.quality.fallback
    assert guard(m, "profile-evidence", None, None, check=True, clips=False)[1] is None  # applied
    assert prefer_profile(frame(0.005), sure, W, H) == (frame(0.005), None)  # the frame is surer
    assert prefer_profile(frame(0.019), sure, W, H)[1] is None  # surer, but not clearly (PRIOR_MARGIN)
    assert prefer_profile(frame(0.05), replace(sure, trusted=True), W, H)[1] is None  # trusted: not before trust
    assert prefer_profile(frame(0.05), replace(sure, n_frames=2), W, H)[1] is None
    assert prefer_profile(frame(0.05), replace(sure, field_sigma_ev=float("nan")), W, H)[1] is None
    assert prefer_profile(frame(0.05), None, W, H)[1] is None
    # a profile whose fall-off is not clear (under min_snr times its sigma) leaves the frame alone
    flat = replace(sure, theta=two.theta * 1e-3)
    assert prefer_profile(frame(0.05), flat, W, H)[1] is None
