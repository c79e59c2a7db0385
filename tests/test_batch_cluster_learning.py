"""Learning as it goes on a Dask cluster (issue 38): the workers cannot share the profile
store, so they return each frame's pooled material and the batch client pools it, once per
file content, applies the series rule and hands the applied revision to the tasks it
submits next (vigproc.frontends.batch.Handout)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from vigproc.core.model import VignettingModel
from vigproc.frontends import backends as BK
from vigproc.frontends import batch as B
from vigproc.pipeline.processor import Settings
from vigproc.stores.profiles import ProfileStore

from conftest import photo_like

distributed = pytest.importorskip("distributed", reason="dask.distributed is not installed")

#: A Nikon D70 with its kit zoom at 70 mm (an interchangeable-lens body with its lens named).
D70_EXIF = {"Make": "NIKON CORPORATION", "Model": "NIKON D70", "LensMake": "Nikon",
            "LensModel": "AF-S DX Zoom-Nikkor 18-70mm f/3.5-4.5G IF-ED",
            "FocalLength": 70, "FNumber": 4.5, "FocalLengthIn35mmFormat": 105}
H, W = 256, 384
N = 10


@pytest.fixture(scope="module")
def series(tmp_path_factory) -> list[Path]:
    """``N`` DNG frames of one lens setting, a minute apart (one series), carrying a
    lensfun lens's fall-off."""
    from dngfixture import make_dngs

    from vigproc.stores.lensfun import diverse_lenses, pa_field

    folder = tmp_path_factory.mktemp("series")
    _, pa = diverse_lenses(1)[0]
    field = pa_field((H, W), pa.k1, pa.k2, pa.k3)
    paths = [folder / f"frame {i:02d}.dng" for i in range(N)]
    make_dngs([(p, dict(width=W, height=H, field=field, scene=photo_like(H, W, seed=20 + i),
                        exif={"DateTimeOriginal": f"2024:05:06 07:{i:02d}:00", **D70_EXIF})) for i, p in enumerate(paths)])
    return paths


@pytest.fixture(scope="module")
def cluster():
    cl = distributed.LocalCluster(n_workers=1, processes=False, threads_per_worker=1, dashboard_address=":0")
    client = distributed.Client(cl, set_as_default=False)
    yield client
    client.close()
    cl.close()


def _job(series, out: Path, db: Path, cluster, **kw) -> B.BatchSummary:
    """One correct job that learns as it goes on the cluster, as ``vigproc batch
    --scheduler`` sets it up: the client's store, its snapshot shipped to the workers."""
    items, _ = B.collect(series[0].parent, out)
    out.mkdir(parents=True, exist_ok=True)
    with ProfileStore(db) as store:
        spec = B.JobSpec(settings=Settings(learn=True), outdir=str(out.resolve()), numba_threads=1,
                         store_snapshot=B.Shipped.of("profiles.sqlite", B.snapshot_store(store)), client_learns=True)
        return B.run_batch(items, spec, BK.dask_backend(cluster, numba_threads=1), journal_path=out / B.JOURNAL_NAME,
                           job="test", progress=False, store=store, **kw)


def _records(out: Path) -> list[dict]:
    return [json.loads(p.read_text()) for p in sorted(out.glob("*.vigproc.json"))]


def _pooled_frames(db: Path) -> list[str]:
    with ProfileStore(db) as store:
        return [r[0] for r in store.con.execute("SELECT frame FROM pooled_frames")]


def _log2_field(rec: dict) -> np.ndarray:
    m = VignettingModel.from_dict(rec["model"])
    return m.log_field((m.height, m.width)) / np.log(2.0)


def test_the_client_pools_each_frame_once_and_hands_out_one_revision(series, tmp_path, cluster):
    db, out = tmp_path / "p.sqlite", tmp_path / "out"
    s = _job(series, out, db, cluster)
    assert s.processed == N and s.failed == 0
    with ProfileStore(db) as store:
        [prof] = store.list()
        applied = store.applied_revision(prof.key)
    assert prof.n_frames == N and prof.trusted
    assert len(_pooled_frames(db)) == N
    recs = _records(out)
    # each record says what the store did with its frame (the client rewrote the worker's)
    assert sorted(r["learned"]["frames"] for r in recs) == list(range(1, N + 1))
    assert all(r["learned"]["pooled"] and r["profile"] == str(prof.key) for r in recs)
    assert s.profiles == {str(prof.key): {"n_frames": N, "trusted": True,
                                          "field_sigma_ev": round(prof.field_sigma_ev, 5)}}
    # after trust, the later tasks got the applied revision: one field for all of them
    later = [r for r in recs if r["source"] == "stored-profile"]
    assert len(later) >= 3, [r["source"] for r in recs]
    assert all(r["applied"] for r in later)
    assert {r["profile_applied"]["revision"] for r in later} == {applied[0]}
    first = _log2_field(later[0])
    for r in later[1:]:
        np.testing.assert_array_equal(_log2_field(r), first)
    # frames before trust were estimated alone (or by the profile so far)
    assert {r["source"] for r in recs} <= {"estimate", "profile-evidence", "stored-profile"}
    assert recs[0]["source"] == "estimate"


def test_an_interrupted_job_resumed_pools_no_frame_twice(series, tmp_path, cluster):
    db, out = tmp_path / "p.sqlite", tmp_path / "out"
    seen = []

    def stop_after_four(summary, task, outcome):
        seen.append(task.path)
        if len(seen) == 4:
            raise KeyboardInterrupt

    s = _job(series, out, db, cluster, on_result=stop_after_four)
    assert s.interrupted and 4 <= s.processed < N
    s2 = _job(series, out, db, cluster)
    assert s.processed + s2.processed + s2.skipped == N + s.processed  # the rerun skips what is done
    assert len(_pooled_frames(db)) == N and len(set(_pooled_frames(db))) == N
    with ProfileStore(db) as store:
        [prof] = store.list()
    assert prof.n_frames == N


def test_a_crash_between_the_store_and_the_journal_does_not_pool_twice(series, tmp_path, cluster):
    """The store pooled every frame but the journal lost them (a crash between the two
    commits; here: the journal deleted): the rerun redoes every frame, pools none, and
    each record says the content was pooled already."""
    db, out = tmp_path / "p.sqlite", tmp_path / "out"
    _job(series, out, db, cluster)
    with ProfileStore(db) as store:
        [before] = store.list()
    (out / B.JOURNAL_NAME).unlink()
    s = _job(series, out, db, cluster)
    assert s.processed == N
    with ProfileStore(db) as store:
        [after] = store.list()
    assert after.n_frames == before.n_frames == N and len(_pooled_frames(db)) == N
    np.testing.assert_array_equal(after.theta, before.theta)
    recs = _records(out)
    assert all(not r["learned"]["pooled"] and "already pooled" in r["learned"]["reason"] for r in recs)
    assert all("profile" not in r for r in recs)
    # the series goes on: the trusted profile's revision corrects the redone frames
    assert sum(r["source"] == "stored-profile" for r in recs) >= N - 2


def test_the_client_pools_for_a_cluster_backend_only(tmp_path):
    """Local workers pool into the store themselves: a spec asking the client to pool for
    them is a typed error before anything runs (no journal, no outputs)."""
    spec = B.JobSpec(settings=Settings(learn=True), outdir=str(tmp_path), client_learns=True)
    with pytest.raises(B.BatchError, match="cluster backend only"):
        B.run_batch([], spec, BK.local_backend(1), journal_path=tmp_path / "j.sqlite", job="t", store=object())
    with pytest.raises(B.BatchError, match="client's profile store"):
        B.run_batch([], spec, BK.local_backend(1), journal_path=tmp_path / "j.sqlite", job="t")
    assert list(tmp_path.iterdir()) == []
