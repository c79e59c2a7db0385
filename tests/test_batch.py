"""vigproc batch: collection, naming, journal-based resume, learn pooling on the
client, and a real dask.distributed LocalCluster (equal results, a killed worker)."""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import time
from pathlib import Path

import numpy as np
import pytest
from conftest import textured

from vigproc.frontends import backends as BK
from vigproc.frontends import batch as B
from vigproc.frontends import batch_worker
from vigproc.frontends.cli import main
from vigproc.io.images import read_image, write_image
from vigproc.stores.journal import Journal
from vigproc.pipeline.processor import (SIDECAR_SUFFIX, Settings, corrected_name, output_location, output_name,
                              sweep_temporaries)

EXIFTOOL = shutil.which("exiftool")
H, W = 120, 180

#: Images of the test archive (relative paths); "broken.tif" is not an image.
GOOD = ["a/x.tif", "a/x.png", "b/x.tif", "c d/-dash ü.tif"] + [f"f{i}.tif" for i in range(6)]


def _out_rel(rel: str, what: str = "sidecar", suffix: str = ".tif") -> str:
    """Where the output of the input at ``rel`` goes, relative to the output folder (the
    one policy of every front end: sub-folders mirrored, the input's name kept)."""
    folder, stem = output_location(Path("."), rel, create=False)
    name = stem + SIDECAR_SUFFIX if what == "sidecar" else corrected_name(stem, Path(rel), suffix)
    return str(folder / name)


def _frame(seed: int) -> np.ndarray:
    yy, xx = np.mgrid[0:H, 0:W]
    r2 = ((xx - (W - 1) / 2) ** 2 + (yy - (H - 1) / 2) ** 2) / ((W / 2) ** 2 + (H / 2) ** 2)
    img = textured(H, W, seed=seed) * (1 - 0.45 * r2 - 0.1 * r2**2)
    return img[..., None] * np.array([1.0, 0.9, 0.8])


@pytest.fixture(scope="module")
def archive(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("archive")
    files = []
    for i, rel in enumerate(GOOD):
        p = root / rel
        p.parent.mkdir(parents=True, exist_ok=True)
        write_image(p, _frame(i), bit_depth="uint16")
        files.append(p)
    (root / "broken.tif").write_bytes(b"II*\x00 this is not a TIFF")
    (root / ".hidden.tif").write_bytes(b"temporary file of a writer")
    (root / "notes.txt").write_text("not an image")
    if EXIFTOOL:  # camera and lens, so learn mode has a key (one exiftool run for all)
        subprocess.run([EXIFTOOL, "-q", "-overwrite_original", "-Make=Vigproc", "-Model=Batch 1",
                        "-LensModel=VP 35mm F2.0 Test", "-FocalLength=35", "-FNumber=2.0",
                        *[str(f) for f in files]], check=True, capture_output=True)
    return root


def _copy(archive: Path, dst: Path) -> Path:
    shutil.copytree(archive, dst)
    return dst


def _no_timings(d):
    if isinstance(d, dict):
        return {k: _no_timings(v) for k, v in d.items() if k != "seconds"}
    return [_no_timings(v) for v in d] if isinstance(d, list) else d


def _sidecars(out: Path) -> dict[str, dict]:
    """Sidecars by path relative to ``out``, minus what legitimately differs between
    runs (timings, absolute output paths)."""
    res = {}
    for p in sorted(out.rglob("*" + SIDECAR_SUFFIX)):
        d = _no_timings(json.loads(p.read_text()))
        for k in ("output", "picture"):
            if k in d:
                d[k] = str(Path(d[k]).relative_to(out))
        res[str(p.relative_to(out))] = d
    return res


def _run(items, settings, out: Path, backend, **kw) -> B.BatchSummary:
    out.mkdir(parents=True, exist_ok=True)
    spec = B.JobSpec(settings=settings, outdir=str(out.resolve()), numba_threads=getattr(backend, "numba_threads", 1),
                     store_snapshot=kw.pop("snapshot", None))
    return B.run_batch(items, spec, backend, journal_path=out / B.JOURNAL_NAME, job="test", progress=False, **kw)


# ------------------------------------------------------------ collection
def test_collect_folder_list_and_names(archive, tmp_path):
    out = archive / "out"  # an output folder inside the input folder is not input
    out.mkdir(exist_ok=True)
    write_image(out / "old.corrected.tif", np.ones((8, 8)), bit_depth="uint16")
    try:
        items, missing = B.collect(archive, out)
    finally:
        shutil.rmtree(out)
    assert missing == []
    assert sorted(i.rel for i in items) == sorted(GOOD + ["broken.tif"])
    assert all(Path(i.path).is_absolute() and Path(i.path).is_file() for i in items)

    listing = tmp_path / "list.txt"
    listing.write_text(f"# a comment\n\n{archive / 'f0.tif'}\n{os.path.relpath(archive / 'a/x.tif', tmp_path)}\n"
                       f"{archive / 'f0.tif'}\nnot/there.tif\n", encoding="utf-8")
    items, missing = B.collect(listing, tmp_path / "o")
    assert [i.path for i in items] == [str(archive / "f0.tif"), str(archive / "a/x.tif")]
    assert items[0].rel == str(archive / "f0.tif").lstrip("/") and missing == ["not/there.tif"]

    # links: not followed inside a folder; a listed link means its target
    links = tmp_path / "links"
    links.mkdir()
    os.symlink(archive / "f0.tif", links / "link.tif")
    with pytest.raises(B.BatchError, match="no images"):
        B.collect(links, tmp_path / "o")
    listing.write_text(str(links / "link.tif") + "\n")
    assert [i.path for i in B.collect(listing, tmp_path / "o")[0]] == [str(archive / "f0.tif")]

    with pytest.raises(B.BatchError):
        B.collect(tmp_path / "nowhere", tmp_path / "o")
    bad = tmp_path / "bad.txt"
    bad.write_bytes(b"\xff\xfe\x00")
    with pytest.raises(B.BatchError, match="UTF-8"):
        B.collect(bad, tmp_path / "o")


def test_output_folder_never_escapes(tmp_path):
    out = tmp_path / "out"
    (out / "a").mkdir(parents=True)
    spec = B.JobSpec(settings=Settings(mode="estimate", profile="estimate"), outdir=str(out))
    assert batch_worker._out_folder(spec, "a/b/x.jpg") == (out / "a" / "b", "x.jpg")
    os.symlink(tmp_path, out / "evil")  # planted link pointing outside the output folder
    for rel in ("evil/x.jpg", "../x.jpg", "/etc/x.jpg"):
        with pytest.raises(B.ImageWriteError):
            batch_worker._out_folder(spec, rel)


def test_sweep_removes_only_orphaned_temporaries(tmp_path):
    out = tmp_path / "out"
    (out / "a").mkdir(parents=True)
    keep = ["x.jpg.corrected.tif", "x.jpg.vigproc.json", ".other.tmp-1.tif", ".vigproc-batch.sqlite", "y.jpg.tmp"]
    gone = [".x.jpg.corrected.tif.tmp-abc.tif", ".x.jpg.vigproc.k2j3.tmp.json",
            ".x.jpg.corrected.tif.tmp-abc.tif_exiftool_tmp", ".x.jpg.corrected.tif.meta-q.exr",
            "..x.jpg.corrected.tif.tmp-abc.tif.tmp-def.tif"]  # a writer's temporary inside another's
    for n in keep + gone:
        (out / "a" / n).write_bytes(b"x")
    assert sweep_temporaries(out, ["a/x.jpg"], keep=["a/x.jpg"]) == 0  # a writer of x.jpg still runs
    assert sweep_temporaries(out, ["a/x.jpg", "b.jpg"]) == 5
    assert sorted(p.name for p in (out / "a").iterdir()) == sorted(keep)


def test_hostile_file_names(archive, tmp_path):
    src = tmp_path / "in"
    src.mkdir()
    names = ["new\nline.tif", "-rf.tif", "back\\slash.tif", "semi;$(touch pwned).tif", "tab\tq'uote\".tif"]
    for n in names:
        shutil.copy(archive / "f0.tif", src / n)
    shutil.copy(archive / "f0.tif", os.path.join(os.fsencode(src), b"latin1-\xe9.tif"))
    items, _ = B.collect(src, tmp_path / "out")
    s = _run(items, Settings(mode="estimate", profile="estimate"), tmp_path / "out", BK.local_backend(1))
    assert s.processed == len(names) + 1 and s.quarantined == 0  # the non-UTF-8 name too
    assert sorted(p.name for p in (tmp_path / "out").glob("*" + SIDECAR_SUFFIX)) == sorted(
        [*(output_name(n) + SIDECAR_SUFFIX for n in names), "latin1-%E9.tif" + SIDECAR_SUFFIX])
    assert not (tmp_path / "pwned").exists() and not Path("pwned").exists()


# ------------------------------------------------------------ local runs
def test_interrupted_run_resumes_without_redoing(archive, tmp_path):
    src = _copy(archive, tmp_path / "in")
    items, _ = B.collect(src, tmp_path / "out")
    settings = Settings(mode="estimate", profile="estimate")
    out = tmp_path / "out"

    def stop_after_4(summary, task, res):
        if summary.processed == 4:
            raise KeyboardInterrupt

    s1 = _run(items, settings, out, BK.local_backend(1), on_result=stop_after_4)
    assert s1.interrupted and s1.processed == 4
    first = {p: p.stat().st_mtime_ns for p in out.rglob("*" + SIDECAR_SUFFIX)}
    assert len(first) == 4

    s2 = _run(items, settings, out, BK.local_backend(1))
    assert not s2.interrupted
    assert (s2.skipped, s2.processed, s2.quarantined) == (4, len(GOOD) - 4, 1)
    assert all(p.stat().st_mtime_ns == t for p, t in first.items())  # done files were not redone
    assert sorted(_sidecars(out)) == sorted(_out_rel(r) for r in GOOD)
    assert s2.errors[0]["file"].endswith("broken.tif")

    with Journal(out / B.JOURNAL_NAME, job="test") as j:
        c = j.counts()
        assert (c["done"], c["quarantined"], c["running"]) == (len(GOOD), 1, 0)
        assert all(e.claims == 1 for e in j.entries("done"))

    # a changed file is new work; a touched one (same content) is not; the broken one stays quarantined
    write_image(src / "f1.tif", _frame(99), bit_depth="uint16")
    os.utime(src / "f2.tif", ns=(time.time_ns(), time.time_ns()))
    s3 = _run(items, settings, out, BK.local_backend(1))
    assert (s3.processed, s3.skipped, s3.quarantined) == (1, len(GOOD) - 1, 1)
    # the deleted outputs of a done file are written again
    (out / "f3.tif.vigproc.json").unlink()
    s4 = _run(items, settings, out, BK.local_backend(1))
    assert (s4.processed, s4.redone) == (1, 1) and (out / "f3.tif.vigproc.json").is_file()
    # quarantined files get another chance when asked (and fail again here)
    s5 = _run(items, settings, out, BK.local_backend(1), retry_quarantined=True)
    assert (s5.processed, s5.skipped, s5.quarantined) == (0, len(GOOD), 1)
    assert "quarantined by an earlier run" not in s5.errors[0]["error"]


def test_same_failure_everywhere_stops_before_quarantining(tmp_path):
    """A setup problem (here: learn mode on frames without lens EXIF) must not quarantine the archive."""
    src = tmp_path / "in"
    src.mkdir()
    for i in range(B.BREAKER_FILES + 2):
        write_image(src / f"n{i:02d}.tif", _frame(i), bit_depth="uint16")
    items, _ = B.collect(src, tmp_path / "out")
    with pytest.raises(B.BatchError, match=f"first {B.BREAKER_FILES} files all failed"):
        _run(items, Settings(mode="learn"), tmp_path / "out", BK.local_backend(1), store=object())
    with Journal(tmp_path / "out" / B.JOURNAL_NAME, job="test") as j:
        assert j.counts()["quarantined"] == 0


def test_pool_of_two_processes_matches_in_process(archive, tmp_path):
    items, _ = B.collect(archive, tmp_path)
    items = [i for i in items if i.rel != "broken.tif"][:4]
    settings = Settings(mode="estimate", profile="estimate")
    s1 = _run(items, settings, tmp_path / "one", BK.local_backend(1))
    s2 = _run(items, settings, tmp_path / "two", BK.local_backend(2))
    assert s1.processed == s2.processed == 4
    assert _sidecars(tmp_path / "one") == _sidecars(tmp_path / "two")


@pytest.mark.skipif(EXIFTOOL is None, reason="exiftool is needed to give the frames a lens")
def test_learn_pools_exactly_once_across_a_crash(archive, tmp_path):
    """A crash after the store pooled a frame but before the journal said done: the
    next run redoes the frame but does not pool it again (its content id is in the store)."""
    from vigproc.stores.journal import fingerprint
    from vigproc.stores.profiles import ProfileStore

    items, _ = B.collect(archive, tmp_path)
    items = [i for i in items if i.rel in ("f0.tif", "f1.tif")]
    out = tmp_path / "out"
    out.mkdir()
    jpath = out / B.JOURNAL_NAME
    settings = Settings(mode="learn")
    res = B.run_task(B.Task(items[0].path, items[0].rel), B.JobSpec(settings=settings, outdir=str(out)))
    assert res.status == "done" and len(res.evidence) == 1
    key, model, evidence, _, extra = res.evidence[0]
    cast = extra.get("cast")
    assert evidence is not None  # the default method ships the frame's data for the joint refit
    with ProfileStore(tmp_path / "p.sqlite") as store, Journal(jpath, job="test") as j:
        assert j.claim(items[0].path, res.fingerprint, worker="crashed")
        # ... and the client dies here
        store.learn(key, model, frame_id=res.fingerprint.sha256, evidence=evidence, cast=cast)
    with ProfileStore(tmp_path / "p.sqlite") as store:
        s = _run(items, settings, out, BK.local_backend(1), store=store)
        assert s.processed == 2
        assert store.get(key).n_frames == 2  # f0 once (not twice), f1 once
        assert cast is not None  # a colour frame: its colour-cast record travels with its evidence, pooled once too
        assert store.cast_report(key).n_frames == 2
    with Journal(jpath, job="test") as j:
        assert j.counts()["done"] == 2 and fingerprint(items[0].path).same_content(
            j.lookup(items[0].path).fingerprint)


def test_one_client_per_job(archive, tmp_path):
    items, _ = B.collect(archive, tmp_path)
    out = tmp_path / "out"
    out.mkdir()
    with B._job_lock(out / B.JOURNAL_NAME, "test"):  # another client is running this job
        with pytest.raises(B.BatchError, match="another 'vigproc batch'"):
            _run(items, Settings(mode="estimate", profile="estimate"), out, BK.local_backend(1))
    assert not list(out.glob("*" + SIDECAR_SUFFIX))


# ------------------------------------------------------------ command line
def test_cli_batch_list_json_and_errors(archive, tmp_path, capsys):
    listing = tmp_path / "list.txt"
    listing.write_text("\n".join(str(archive / r) for r in GOOD[:3]) + "\nmissing.tif\n")
    out = tmp_path / "out"
    rc = main(["batch", str(listing), "--mode", "estimate", "--profile", "estimate", "-o", str(out),
               "--workers", "1", "--json"])
    d = json.loads(capsys.readouterr().out)
    assert rc == 1 and (d["processed"], d["missing"], d["failed"]) == (3, 1, 1)
    # outputs mirror each input's absolute path under OUT
    for r in GOOD[:3]:
        assert (out / str(archive / r).lstrip("/")).with_name(Path(r).name + SIDECAR_SUFFIX).is_file()

    cfg = tmp_path / "cfg.toml"
    base = ["batch", str(archive), "--mode", "estimate", "-o", str(out)]
    for argv, config, code, text in [
        (["batch", str(tmp_path / "nowhere"), "--mode", "estimate", "-o", str(out)], "", 10, "no such folder"),
        (base + ["--scheduler", "tcp://a b;rm -rf"], "", 10, "not a scheduler address"),
        (base + ["--config", str(cfg)], 'scheduler = "tcp://127.0.0.1:9"\nconnect_timeout = 1', 10, "cannot reach"),
        (base + ["--config", str(cfg)], "workres = 2", 10, "unknown key batch.workres"),
        (base + ["--config", str(cfg)], "workers = 'two'", 10, "must be an integer"),
        (base + ["--config", str(cfg)], "workers = 0", 10, "at least 1"),  # --workers 0: a usage error (test_cli)
        (["batch", str(archive), "--mode", "correct", "-o", str(out), "--profile", str(listing)], "", 8, "profile"),
    ]:
        cfg.write_text("[batch]\n" + config + "\n")
        assert main(argv) == code, argv
        err = capsys.readouterr().err
        lines = [ln for ln in err.splitlines() if ln.startswith("vigproc:")]
        assert len(lines) == 1 and text in lines[0] and "Traceback" not in err, err


def test_cli_batch_outputs_are_never_inputs(archive, tmp_path, capsys):
    src = tmp_path / "in"
    src.mkdir()
    shutil.copy(archive / "f0.tif", src / "f0.tif")
    (src / "x\nvigproc: FAKE.tif").write_bytes(b"not an image")
    base = ["--mode", "estimate", "--profile", "estimate", "--workers", "1", "--no-progress"]
    # OUT == DIR: every rerun would process the outputs of the one before
    for out in (src, tmp_path / "in" / ".." / "in"):
        assert main(["batch", str(src), *base, "-o", str(out)]) == 10
        assert "cannot be the source folder" in capsys.readouterr().err
    assert sorted(p.name for p in src.iterdir()) == ["f0.tif", "x\nvigproc: FAKE.tif"]
    # a missing or empty source: an error, and no output folder left behind
    (tmp_path / "empty").mkdir()
    for source, text in ((tmp_path / "nowhere", "no such folder"), (tmp_path / "empty", "no images")):
        assert main(["batch", str(source), *base, "-o", str(tmp_path / "new")]) == 10
        assert text in capsys.readouterr().err and not (tmp_path / "new").exists()
    # OUT inside DIR: its subtree is not input, rerun after rerun; failures print one line each
    for _ in range(2):
        assert main(["batch", str(src), *base, "-o", str(src / "out")]) == 1
        err = capsys.readouterr().err.splitlines()
        failed = [ln for ln in err if "failed:" in ln]
        assert len(failed) == 1 and "x\\nvigproc: FAKE.tif" in failed[0], err
        assert not any(ln.startswith("vigproc: FAKE") for ln in err)
    assert sorted(p.name for p in (src / "out").iterdir() if not p.name.startswith(".")) == ["f0.tif" + SIDECAR_SUFFIX]
    # a list naming a file inside OUT: skipped, so outputs of an earlier run are never redone
    write_image(src / "out" / "old.tif", np.ones((8, 8)), bit_depth="uint16")
    listing = tmp_path / "list.txt"
    listing.write_text(f"{src / 'out' / 'old.tif'}\n{src / 'f0.tif'}\n")
    items, missing = B.collect(listing, src / "out")
    assert [i.path for i in items] == [str(src / "f0.tif")] and missing == []
    with pytest.raises(B.BatchError, match="no images"):
        B.collect(listing, src)


# ------------------------------------------------------------ dask.distributed
@pytest.fixture(scope="module")
def cluster():
    distributed = pytest.importorskip("distributed")
    # dashboard on a free port: None would still bind the scheduler's HTTP server to 8787
    cl = distributed.LocalCluster(n_workers=2, processes=True, threads_per_worker=1, dashboard_address=":0")
    client = distributed.Client(cl, set_as_default=False)
    yield client
    client.close()
    cl.close()


def _dask(client):
    return BK.dask_backend(client, numba_threads=1)


def test_localcluster_equals_single_process(archive, tmp_path, cluster):
    items, _ = B.collect(archive, tmp_path)
    items = [i for i in items if not i.rel.startswith("f")]  # the odd names (correcting costs ~0.5 s a file)
    good = [i.rel for i in items if i.rel != "broken.tif"]
    settings = Settings(mode="correct", profile="estimate", output_format="tiff-float")
    one = _run(items, settings, tmp_path / "one", BK.local_backend(1))
    dist = _run(items, settings, tmp_path / "dask", _dask(cluster))
    assert one.processed == dist.processed == len(good) == 4 and one.quarantined == dist.quarantined == 1
    assert "2 workers" in dist.backend
    a, b = _sidecars(tmp_path / "one"), _sidecars(tmp_path / "dask")
    assert a == b and len(a) == len(good)
    for rel in good:
        x = read_image(tmp_path / "one" / _out_rel(rel, "image"))[0]
        y = read_image(tmp_path / "dask" / _out_rel(rel, "image"))[0]
        assert np.array_equal(x, y), rel


@pytest.mark.skipif(EXIFTOOL is None, reason="exiftool is needed to give the frames a lens")
def test_localcluster_learn_pools_on_the_client(archive, tmp_path, cluster):
    """Workers return estimates; the client alone writes the store, and the pooled
    profile equals the one learned in a single process."""
    from vigproc.stores.profiles import ProfileStore

    items, _ = B.collect(archive, tmp_path)
    items = [i for i in items if i.rel != "broken.tif"]
    stores = []
    for name, backend in (("one", BK.local_backend(1)), ("dask", _dask(cluster))):
        with ProfileStore(tmp_path / f"{name}.sqlite") as store:
            s = _run(items, Settings(mode="learn"), tmp_path / name, backend, store=store)
            assert s.processed == len(items) and len(s.profiles) == 1
            stores.append(store.list())
    (p,), (q,) = stores
    assert p.key == q.key and p.n_frames == q.n_frames == len(items)
    assert np.array_equal(p.theta, q.theta) and np.array_equal(p.covariance, q.covariance)
    assert p.scatter_sigma_ev == pytest.approx(q.scatter_sigma_ev, rel=1e-9)  # Welford: order-dependent rounding


@pytest.mark.skipif(EXIFTOOL is None, reason="exiftool is needed to give the frames a lens")
def test_localcluster_profile_auto_reads_a_snapshot(archive, tmp_path, cluster):
    """--profile auto on workers uses the client's snapshot of the store (workers never
    open the client's database)."""
    from vigproc.io.exif import ExifReader
    from vigproc.stores.profiles import Profile, ProfileKey, ProfileStore, normalise

    items, _ = B.collect(archive, tmp_path)
    items = [i for i in items if i.rel.startswith("f")]
    with ExifReader() as reader:
        key = ProfileKey.from_lens(reader.read(items[0].path), W, H)
    model = B.run_task(B.Task(items[0].path, items[0].rel),
                       B.JobSpec(settings=Settings(mode="estimate", profile="estimate"), outdir=str(tmp_path))).record
    from vigproc.core.model import VignettingModel

    theta, _, _ = normalise(VignettingModel.from_dict(model["model"]))
    db = tmp_path / "p.sqlite"
    with ProfileStore(db) as store:
        store.put(Profile(key=key, theta=theta, provenance="user", trusted=True))
        snap = B.Shipped.of("profiles.sqlite", B.snapshot_store(store))
    before = db.read_bytes()
    s = _run(items, Settings(mode="estimate", profile="auto"), tmp_path / "out", _dask(cluster), snapshot=snap)
    assert s.processed == len(items) and s.sources == {"stored-profile": len(items)}
    assert db.read_bytes() == before


def test_localcluster_worker_killed_loses_and_repeats_nothing(archive, tmp_path, cluster):
    items, _ = B.collect(archive, tmp_path)
    out = tmp_path / "out"
    killed = []

    def kill_one_worker(summary, task, res):
        if summary.processed == 3 and not killed:  # kill a worker that is processing a file
            pids = cluster.run(os.getpid)
            busy = sorted((len(keys), addr) for addr, keys in cluster.processing().items())[-1]
            killed.append(busy)
            os.kill(pids[busy[1]], signal.SIGKILL)

    settings = Settings(mode="correct", profile="estimate", output_format="tiff16")
    s = _run(items, settings, out, _dask(cluster), on_result=kill_one_worker)
    assert killed and killed[0][0] >= 1, "the killed worker had no task"
    assert s.processed == len(GOOD) and s.quarantined == 1 and s.retry_later == 0
    outputs = sorted(str(p.relative_to(out)) for p in out.rglob("*") if p.is_file() and B.JOURNAL_NAME not in p.name)
    assert outputs == sorted([_out_rel(r, "image") for r in GOOD] + [_out_rel(r) for r in GOOD])
    with Journal(out / B.JOURNAL_NAME, job="test") as j:
        done = j.entries("done")
        assert len(done) == len(GOOD) and all(e.claims == 1 for e in done)
        assert sorted(Path(e.path).relative_to(archive).as_posix() for e in done) == sorted(GOOD)
    cluster.wait_for_workers(2, timeout=60)


def test_cli_batch_on_a_scheduler(archive, tmp_path, cluster, capsys):
    listing = tmp_path / "list.txt"
    listing.write_text("\n".join(str(archive / r) for r in GOOD[:3]) + "\n")
    out = tmp_path / "out"
    argv = ["batch", str(listing), "--mode", "estimate", "--profile", "estimate", "-o", str(out),
            "--scheduler", cluster.scheduler.address, "--json"]
    assert main(argv) == 0
    d = json.loads(capsys.readouterr().out)
    assert d["processed"] == 3 and d["backend"].startswith("dask cluster")
    assert main(argv) == 0  # resumed: nothing left to do
    assert json.loads(capsys.readouterr().out)["skipped"] == 3
