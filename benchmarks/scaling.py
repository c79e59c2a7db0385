"""``vigproc bench scaling``: the hot folder and ``vigproc batch`` with 1 and 2 workers.

What a studio feels of more cores: photographs per second through ``vigproc watch IN
-o OUT --workers N`` (the daemon running, warm, a folder of full-size JPEGs dropped
in) and through ``vigproc batch`` (the whole command, start-up included), for each
worker count, rounds interleaved so a busy machine weighs on every count alike.

Watch: the daemon is started per round and per worker count; one photo per worker is
dropped first and waited for (worker start-up, the Numba cache load and exiftool's
start are paid there, once per worker), then the photographs are renamed into the
folder at once and the round is timed from the drop to the last ``done`` in the
daemon's journal (its records, polled: no sleeping for a guessed time).  The
*steady* rate leaves the first file per worker out (from the N-th done to the last).

*Cores busy*: the CPU seconds of the daemon's whole process tree (the daemon, its workers,
their exiftool processes and threads; ``/proc``) over the timed window, per second of it;
for batch, the command's children's (``getrusage``). One worker already keeps more than
one core busy (exiftool runs beside it, decode and encode overlap in threads), so N
workers on a machine of C cores can gain at most about C / (one worker's cores busy).

Batch: ``vigproc batch IN --mode correct -o OUT --workers N`` as a new process,
timed whole (its pool's start-up included: what a user waits).
"""

from __future__ import annotations

import contextlib
import logging
import os
import resource
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass, field
from datetime import datetime
from pathlib import Path
from typing import Iterator, Sequence

import numpy as np

from benchmarks.throughput import Photo, stage
from vigproc.errors import VigprocError

log = logging.getLogger(__name__)

#: Seconds a round may take per photograph before the bench gives up.
PER_PHOTO_TIMEOUT = 120.0


@dataclass
class Rounds:
    """Seconds per round of one front end at one worker count."""

    frontend: str
    workers: int
    wall: list[float] = field(default_factory=list)
    steady: list[float] = field(default_factory=list)  # photos per second, first per worker left out
    cores: list[float] = field(default_factory=list)  # CPU seconds per second of the round, its processes'

    @property
    def median_wall(self) -> float:
        return float(np.median(self.wall)) if self.wall else float("nan")

    @property
    def median_steady(self) -> float:
        return float(np.median(self.steady)) if self.steady else float("nan")

    @property
    def median_cores(self) -> float:
        return float(np.median(self.cores)) if self.cores else float("nan")


@dataclass
class ScalingResult:
    """What :func:`run_scaling` measured (``vigproc bench scaling --json``)."""

    photos: int
    megapixels: float
    rounds: int
    cores: int
    load_before: tuple[float, float, float]
    load_after: tuple[float, float, float]
    runs: list[Rounds]

    def rate(self, frontend: str, workers: int) -> float:
        """Photos per second (median round, drop or start to the last done)."""
        r = next(r for r in self.runs if r.frontend == frontend and r.workers == workers)
        return self.photos / r.median_wall


def distinct_copy(src: Path, dst: Path, n: int) -> Path:
    """Copy the JPEG ``src`` to ``dst`` with a comment segment (``COM``, "vigproc bench
    copy n") after its application segments: the same pixels and tags, other bytes, so
    the copy is a frame of its own to every content hash (the journal, learning's frame
    ids) and the work per copy is the original's.

    Raises
    ------
    VigprocError
        ``src`` is not a JPEG whose segments can be walked.
    """
    data = src.read_bytes()
    if data[:2] != b"\xff\xd8":
        raise VigprocError(f"bench scaling: {src} is not a JPEG")
    at = 2
    while at + 4 <= len(data) and data[at] == 0xFF and 0xE0 <= data[at + 1] <= 0xEF:  # APP0..APP15
        at += 2 + int.from_bytes(data[at + 2:at + 4], "big")
    if at + 2 > len(data) or data[at] != 0xFF:
        raise VigprocError(f"bench scaling: cannot walk the segments of {src}")
    text = f"vigproc bench copy {n}".encode()
    dst.write_bytes(data[:at] + b"\xff\xfe" + (len(text) + 2).to_bytes(2, "big") + text + data[at:])
    return dst


def stage_copies(photos: Sequence[Photo], into: Path, copies: int) -> list[Path]:
    """:func:`benchmarks.throughput.stage`, and ``copies - 1`` more of each photograph
    under distinct names and bytes (:func:`distinct_copy`), so that a run has enough
    work for the workers' steady state to show."""
    out = stage(photos, into)
    for c in range(1, max(1, copies)):
        out += [distinct_copy(p, into / f"c{c}-{p.name}", c) for p in out[:len(photos)]]
    return out


def _wait_done(journal: Path, job: str, n: int, proc: subprocess.Popen, timeout: float) -> list[float]:
    """Poll the daemon's journal until ``n`` entries are done; their completion times
    (epoch seconds, the journal's own timestamps), sorted.

    Raises
    ------
    VigprocError
        The daemon exited, quarantined a file, or did not finish in time.
    """
    from vigproc.stores.journal import Journal

    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if proc.poll() is not None:
            raise VigprocError(f"bench scaling: the daemon exited early (code {proc.returncode})")
        if journal.exists():
            with Journal(journal, job=job) as j:
                c = j.counts()
                if c["quarantined"]:
                    raise VigprocError("bench scaling: the daemon quarantined files: "
                                       f"{[e.reason for e in j.entries('quarantined')][:3]}")
                if c["done"] >= n:
                    return sorted(datetime.fromisoformat(e.updated.replace("Z", "+00:00")).timestamp()
                                  for e in j.entries("done"))
        time.sleep(0.05)
    raise VigprocError(f"bench scaling: the daemon did not finish {n} files within {timeout:.0f} s")


def tree_cpu_seconds(pid: int) -> float:
    """CPU seconds (user + system) used so far by process ``pid`` and all its descendants,
    the children they reaped included (Linux ``/proc``; ``proc(5)``, stat fields 14-17)."""
    tick = os.sysconf("SC_CLK_TCK")
    stats: dict[int, tuple[int, float]] = {}
    for d in Path("/proc").iterdir():
        if not d.name.isdigit():
            continue
        try:
            fields = (d / "stat").read_text().rsplit(")", 1)[1].split()
        except OSError:  # gone meanwhile
            continue
        stats[int(d.name)] = (int(fields[1]), sum(int(v) for v in fields[11:15]) / tick)
    mine, grown = {pid}, True
    while grown:
        more = {p for p, (ppid, _) in stats.items() if ppid in mine and p not in mine}
        mine |= more
        grown = bool(more)
    return sum(stats[p][1] for p in mine if p in stats)


def _cli() -> list[str]:
    return [sys.executable, "-m", "vigproc.frontends.cli"]


def watch_command(in_dir: Path, out_dir: Path, journal: Path, workers: int) -> list[str]:
    """The daemon the bench times: ``vigproc watch IN -o OUT --workers N`` with a short
    settle, its own journal and no rescans."""
    return [*_cli(), "watch", str(in_dir), "-o", str(out_dir), "--workers", str(workers), "--settle", "0.2",
            "--journal", str(journal), "--job", "bench", "--unapplied", "copy", "--rescan", "3600"]


def watch_daemons(parts: Sequence[tuple[Sequence[Path], Sequence[Path]]], workers: int,
                  root: Path) -> tuple[list[float], float, float, float]:
    """Daemons started side by side, one per ``(files, warm)`` part (each its own in,
    out and journal under ``root / f"d{i}"``): every daemon is warmed with its ``warm``
    files and waited for, then every part's ``files`` are renamed in at once.

    Returns
    -------
    (done, t_drop, cpu, t_cpu)
        The completion times of the dropped files (epoch seconds, the journals' own,
        sorted, all daemons together), the epoch second of the drop, the CPU seconds the
        daemons' process trees used from the drop until all were seen done, and the
        epoch second that CPU was read.
    """
    procs: list[subprocess.Popen] = []
    dirs = []
    try:
        for i, (_files, warm) in enumerate(parts):
            d = root / f"d{i}" if len(parts) > 1 else root
            in_dir, journal = d / "in", d / "journal.sqlite"
            in_dir.mkdir(parents=True)
            with open(d / "daemon.log", "wb") as logf:
                procs.append(subprocess.Popen(watch_command(in_dir, d / "out", journal, workers),
                                              stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=logf))
            dirs.append((in_dir, journal))
            for f in warm:
                os.rename(f, in_dir / f.name)
        for (_files, warm), (_in, journal), proc in zip(parts, dirs, procs):
            _wait_done(journal, "bench", len(warm), proc, timeout=600 + PER_PHOTO_TIMEOUT * len(warm))
        cpu0, t_drop = sum(tree_cpu_seconds(p.pid) for p in procs), time.time()
        for (files, _warm), (in_dir, _j) in zip(parts, dirs):
            for f in files:
                os.rename(f, in_dir / f.name)
        done: list[float] = []
        for (files, warm), (_in, journal), proc in zip(parts, dirs, procs):
            k, n = len(warm), len(files)
            done += _wait_done(journal, "bench", n + k, proc, timeout=600 + PER_PHOTO_TIMEOUT * n)[k:]
        cpu, t_cpu = sum(tree_cpu_seconds(p.pid) for p in procs) - cpu0, time.time()
        for proc in procs:
            proc.send_signal(signal.SIGTERM)
        for proc in procs:
            proc.wait(timeout=120)
    finally:
        for proc in procs:
            if proc.poll() is None:
                proc.kill()
                proc.wait()
    return sorted(done), t_drop, cpu, t_cpu


def watch_round(files: Sequence[Path], warm: Sequence[Path], workers: int,
                root: Path) -> tuple[float, float, float]:
    """One timed round of the daemon: (seconds from the drop to the last done, steady
    photos per second, cores busy). ``files`` and ``warm`` are moved into its folder
    (renames)."""
    mine, t_drop, cpu, t_cpu = watch_daemons([(files, warm)], workers, root)
    n = len(files)
    wall = mine[-1] - t_drop
    steady = (n - workers) / (mine[-1] - mine[workers - 1]) if n > workers and mine[-1] > mine[workers - 1] \
        else float("nan")
    return wall, steady, cpu / max(t_cpu - t_drop, 1e-9)


def batch_round(src: Path, n: int, workers: int, root: Path) -> tuple[float, float]:
    """One timed ``vigproc batch`` of the folder ``src`` (``n`` photographs): seconds and
    cores busy."""
    out = root / "out"
    cmd = [*_cli(), "batch", str(src), "--mode", "correct", "-o", str(out), "--workers", str(workers),
           "--unapplied", "copy", "--no-progress"]
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.perf_counter()
    res = subprocess.run(cmd, stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
                         timeout=600 + PER_PHOTO_TIMEOUT * n)
    seconds = time.perf_counter() - t0
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    made = sum(1 for p in out.rglob("*.vigproc.json"))
    if res.returncode != 0 or made < n:
        tail = " / ".join(res.stderr.decode("utf-8", "replace").strip().splitlines()[-3:])
        raise VigprocError(f"bench scaling: batch --workers {workers} exited {res.returncode} with {made} of {n} "
                           f"sidecars: {tail}")
    return seconds, cpu / max(seconds, 1e-9)


@contextlib.contextmanager
def exported(name: str, value: str | None) -> Iterator[None]:
    """The environment variable ``name`` set to ``value`` for the commands started
    meanwhile (None: left as it is), restored after."""
    old = os.environ.get(name)
    if value is not None:
        os.environ[name] = value
    try:
        yield
    finally:
        if old is None:
            os.environ.pop(name, None)
        else:
            os.environ[name] = old


def private_profile_db(path: Path) -> contextlib.AbstractContextManager[None]:
    """``VIGPROC_PROFILE_DB`` set to ``path`` meanwhile: never the user's store."""
    return exported("VIGPROC_PROFILE_DB", str(path))


def run_scaling(photos: Sequence[Photo], *, workers: Sequence[int] = (1, 2), rounds: int = 2,
                frontends: Sequence[str] = ("watch", "batch"), workdir: Path | None = None,
                copies: int = 1) -> ScalingResult:
    """Time ``watch`` and ``batch`` on copies of ``photos`` at each worker count,
    ``rounds`` times, interleaved (the order rotates each round). ``copies``: each
    photograph is staged that many times (:func:`stage_copies`).

    Raises
    ------
    VigprocError
        A run failed or did not process every photograph.
    """
    if not photos:
        raise VigprocError("bench scaling: no photographs")
    load_before = os.getloadavg()
    runs = [Rounds(f, w) for f in frontends for w in workers]
    with tempfile.TemporaryDirectory(prefix="vigproc-scaling-", dir=workdir) as tmp:
        root = Path(tmp)
        with private_profile_db(root / "profiles.sqlite"):
            master = stage_copies(photos, root / "master", copies)
            for r in range(max(1, rounds)):
                order = runs[r % len(runs):] + runs[:r % len(runs)]
                for run in order:
                    here = root / f"r{r}-{run.frontend}-{run.workers}"
                    if run.frontend == "watch":
                        files = stage_copies(photos, here / "stage", copies)
                        # distinct bytes: a warm-up file is never the content of a timed one
                        warm = [distinct_copy(master[i % len(master)], here / "stage" / f"warm{i}.jpg", -1 - i)
                                for i in range(run.workers)]
                        wall, steady, cores = watch_round(files, [Path(p) for p in warm], run.workers,
                                                          here / "run")
                        run.steady.append(steady)
                    else:
                        wall, cores = batch_round(root / "master", len(master), run.workers, here)
                    run.wall.append(wall)
                    run.cores.append(cores)
                    log.info("round %d: %s --workers %d: %.2f s", r + 1, run.frontend, run.workers, wall)
                    shutil.rmtree(here, ignore_errors=True)
    return ScalingResult(len(master), max(1, copies) * sum(p.megapixels for p in photos), max(1, rounds),
                         len(os.sched_getaffinity(0)),
                         load_before,
                         os.getloadavg(), runs)


def format_result(r: ScalingResult) -> list[str]:
    """The printed table: photos/s per front end and worker count, and each count's
    ratio to one worker."""
    lines = [f"{r.photos} photographs, {r.megapixels:.1f} MP, median of {r.rounds} rounds (interleaved); "
             f"{r.cores} cores; load {r.load_before[0]:.1f} before, {r.load_after[0]:.1f} after",
             f"{'front end':<10}{'workers':>8}{'seconds':>9}{'photos/s':>10}{'x 1 worker':>12}{'steady/s':>10}"
             f"{'cores busy':>12}{'at most':>9}"]
    for run in r.runs:
        one = next((x for x in r.runs if x.frontend == run.frontend and x.workers == 1), None)
        ratio = one.median_wall / run.median_wall if one is not None else float("nan")
        steady = f"{run.median_steady:>10.2f}" if run.steady else f"{'':>10}"
        # what the cores allow: N workers busy N times one worker's cores, up to the machine's
        bound = (min(run.workers * one.median_cores, r.cores) / one.median_cores
                 if one is not None and one.median_cores > 0 else float("nan"))
        lines.append(f"{run.frontend:<10}{run.workers:>8}{run.median_wall:>9.2f}{r.photos / run.median_wall:>10.2f}"
                     f"{ratio:>12.2f}{steady}{run.median_cores:>12.2f}{bound:>9.2f}")
    return lines
