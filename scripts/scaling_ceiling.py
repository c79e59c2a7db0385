#!/usr/bin/env python3
"""What this machine gives two independent copies of the scaling bench's work: the ceiling
of ``vigproc watch --workers 2`` against one worker (issue 39).

For each kind, rounds interleaved (the order rotates each round) on the photographs and
copies ``vigproc bench scaling`` stages:

- ``watch``: one ``vigproc watch --workers 1`` daemon given all the photographs, against
  two independent one-worker daemons (their own in, out and journal folders) each given
  half, dropped at once (both warmed first, as the bench does); timed from the drop to the
  last ``done`` in the journals;
- ``correct``: one ``vigproc correct --unapplied copy`` process on all the photographs,
  against two on a half each started at once (start-up included, paid twice in parallel);
- ``numba`` / ``numpy``: the VM's raw ceiling: one process running two units of a scalar
  Numba loop (or of a NumPy pass over 64 MB, which also shares the memory bus), against two
  processes running one unit each at once (timed inside them, compiled and warmed first).

The ratio one / two of each round's wall is what two independent copies of exactly this
work gain over one on this machine: the most any two-worker daemon can show here. It also
prints CPU seconds and the load average around each round (other work on the machine)::

    python scripts/scaling_ceiling.py --images ../shared/data/jpeg_exif/metadata-extractor-images \\
        --min-mp 4 --limit 12 --copies 3 --rounds 5
"""

from __future__ import annotations

import argparse
import logging
import os
import resource
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Callable, Sequence

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks.scaling import _cli, distinct_copy, exported, private_profile_db, stage_copies, watch_daemons  # noqa: E402
from benchmarks.throughput import Photo, select_photos  # noqa: E402

log = logging.getLogger("scaling_ceiling")

#: Cores other processes may keep busy during both runs of a round for it to count as quiet.
QUIET = 0.15

#: A child that compiles and warms its loop, says "ready", waits for a line on stdin and
#: then runs ``units`` units of it, printing its start and end (epoch seconds).
_CPU_CHILD = r"""
import sys, time
import numpy as np
kind, units = sys.argv[1], int(sys.argv[2])
if kind == "numba":
    import numba
    @numba.njit(cache=False)
    def unit(n):
        x, s = 1, 0.0
        for i in range(n):
            x = (x * 6364136223846793005 + 1442695040888963407) & 0xFFFFFFFFFFFF
            s += (x >> 20) * 1e-9
        return s
    unit(10)
    run = lambda: unit(900_000_000)
else:
    a = np.random.default_rng(0).random(16_000_000, dtype=np.float32)
    b = np.empty_like(a)
    def run():
        for _ in range(40):
            np.sqrt(a, out=b)
            np.multiply(b, 1.0001, out=a)
    np.sqrt(a[:1000])
print("ready", flush=True)
sys.stdin.readline()
t0 = time.time()
for _ in range(units):
    run()
print(t0, time.time(), flush=True)
"""


def _children_cpu() -> float:
    r = resource.getrusage(resource.RUSAGE_CHILDREN)
    return r.ru_utime + r.ru_stime


def machine_busy() -> float:
    """CPU seconds every core of the machine has been busy since boot (``/proc/stat``:
    all but idle and iowait)."""
    f = [int(v) for v in Path("/proc/stat").read_text().split("\n", 1)[0].split()[1:8]]
    return (sum(f) - f[3] - f[4]) / os.sysconf("SC_CLK_TCK")


def _own_cpu() -> float:
    """CPU seconds of this process and of its reaped children."""
    return _children_cpu() + time.process_time()


def cpu_round(kind: str, copies: int) -> tuple[float, float]:
    """``copies`` processes of the ``kind`` loop at once, two units of work shared
    among them: (wall from the first start to the last end, their CPU seconds)."""
    units = 2 // copies
    cpu0 = _children_cpu()
    procs = [subprocess.Popen([sys.executable, "-c", _CPU_CHILD, kind, str(units)], stdin=subprocess.PIPE,
                              stdout=subprocess.PIPE, text=True) for _ in range(copies)]
    for p in procs:
        if p.stdout.readline().strip() != "ready":
            raise RuntimeError(f"the {kind} child did not start")
    for p in procs:
        p.stdin.write("go\n")
        p.stdin.flush()
    spans = [tuple(map(float, p.stdout.readline().split())) for p in procs]
    for p in procs:
        p.wait()
    return max(s[1] for s in spans) - min(s[0] for s in spans), _children_cpu() - cpu0


def correct_round(parts: Sequence[Sequence[Path]], root: Path) -> tuple[float, float]:
    """One ``vigproc correct --unapplied copy`` per part, started at once: (wall until
    the last exits, their CPU seconds)."""
    cpu0, t0 = _children_cpu(), time.perf_counter()
    procs = [subprocess.Popen([*_cli(), "correct", *map(str, files), "-o", str(root / f"out{i}"),
                               "--unapplied", "copy"], stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL,
                              stderr=subprocess.PIPE) for i, files in enumerate(parts)]
    errors = [p.communicate()[1] for p in procs]
    wall = time.perf_counter() - t0
    for p, err in zip(procs, errors):
        if p.returncode != 0:
            raise RuntimeError(f"vigproc correct exited {p.returncode}: {err.decode()[-400:]}")
    return wall, _children_cpu() - cpu0


def watch_pair_round(photos: Sequence[Photo], copies: int, daemons: int, root: Path) -> tuple[float, float]:
    """``daemons`` one-worker daemons sharing the staged photographs (alternate files:
    halves of like work): (wall from the drop to the last done, their trees' CPU)."""
    files = stage_copies(photos, root / "stage", copies)
    warm = [distinct_copy(files[i], root / "stage" / f"warm{i}.jpg", -1 - i) for i in range(daemons)]
    parts = [(files[i::daemons], [warm[i]]) for i in range(daemons)]
    done, t_drop, cpu, _ = watch_daemons(parts, 1, root / "run")
    return done[-1] - t_drop, cpu


def main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--images", required=True, help="folder of JPEGs (as vigproc bench scaling --images)")
    ap.add_argument("--min-mp", type=float, default=4.0)
    ap.add_argument("--limit", type=int, default=12)
    ap.add_argument("--copies", type=int, default=3)
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--kinds", default="watch,correct,numba,numpy",
                    help="comma-separated: watch, correct, numba, numpy (default %(default)s)")
    ap.add_argument("--tmp", help="folder for the staged files (default: the system's)")
    ap.add_argument("--pair-threads", type=int,
                    help="NUMBA_NUM_THREADS for each of the two daemons or processes (default: as they set "
                         "it, the cores each: two one-worker daemons then run twice the threads there are cores; "
                         "1 is what one daemon's two workers take)")
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(message)s", datefmt="%H:%M:%S")
    photos, _ = select_photos(Path(args.images), args.min_mp, args.limit)
    kinds = [k for k in args.kinds.split(",") if k]
    walls: dict[tuple[str, int], list[float]] = {(k, n): [] for k in kinds for n in (1, 2)}
    cpus: dict[tuple[str, int], list[float]] = {(k, n): [] for k in kinds for n in (1, 2)}
    other: dict[tuple[str, int], list[float]] = {(k, n): [] for k in kinds for n in (1, 2)}
    with tempfile.TemporaryDirectory(prefix="vigproc-ceiling-", dir=args.tmp) as tmp, \
            private_profile_db(Path(tmp) / "profiles.sqlite"):
        root = Path(tmp)
        master = stage_copies(photos, root / "master", args.copies)
        if "watch" in kinds:  # untimed: the shared profile store learns these frames once, as in the bench
            watch_pair_round(photos, args.copies, 1, root / "learn")
        runs: list[tuple[str, int, Callable[[Path], tuple[float, float]]]] = []
        for k in kinds:
            for n in (1, 2):
                if k == "watch":
                    runs.append((k, n, lambda here, n=n: watch_pair_round(photos, args.copies, n, here)))
                elif k == "correct":
                    runs.append((k, n, lambda here, n=n: correct_round([master[i::n] for i in range(n)], here)))
                else:
                    runs.append((k, n, lambda here, n=n, k=k: cpu_round(k, n)))
        for r in range(max(1, args.rounds)):
            order = runs[r % len(runs):] + runs[:r % len(runs)]
            for k, n, fn in order:
                here = root / f"r{r}-{k}-{n}"
                here.mkdir()
                load0, busy0, own0, t0 = os.getloadavg()[0], machine_busy(), _own_cpu(), time.monotonic()
                threads = args.pair_threads if n == 2 and k in ("watch", "correct") else None
                with exported("NUMBA_NUM_THREADS", None if threads is None else str(threads)):
                    wall, cpu = fn(here)
                # what else ran meanwhile: the machine's busy CPU less ours, per second
                others = (machine_busy() - busy0 - (_own_cpu() - own0)) / (time.monotonic() - t0)
                walls[(k, n)].append(wall)
                cpus[(k, n)].append(cpu)
                other[(k, n)].append(others)
                log.info("round %d: %s x%d: %.2f s wall, %.2f s CPU (load %.1f -> %.1f, other processes "
                         "%.2f cores)", r + 1, k, n, wall, cpu, load0, os.getloadavg()[0], others)
                shutil.rmtree(here, ignore_errors=True)
    print(f"{len(master)} photographs; {len(os.sched_getaffinity(0))} cores; rounds {args.rounds}; 'quiet': the rounds "
          f"in which other processes kept under {QUIET} core busy in both runs")
    print(f"{'kind':<9}{'one s':>8}{'two s':>8}{'one/two median':>16}{'min':>7}{'max':>7}{'CPU one':>9}{'CPU two':>9}"
          f"{'others max':>11}{'quiet rounds':>14} {'quiet one/two':>17}")
    for k in kinds:
        one, two = np.array(walls[(k, 1)]), np.array(walls[(k, 2)])
        ratio = one / two  # paired by round
        quiet = ratio[(np.array(other[(k, 1)]) < QUIET) & (np.array(other[(k, 2)]) < QUIET)]
        q = f"{np.median(quiet):.2f} ({quiet.min():.2f}-{quiet.max():.2f})" if quiet.size else "-"
        print(f"{k:<9}{np.median(one):>8.2f}{np.median(two):>8.2f}{np.median(ratio):>16.2f}{ratio.min():>7.2f}"
              f"{ratio.max():>7.2f}{np.median(cpus[(k, 1)]):>9.2f}{np.median(cpus[(k, 2)]):>9.2f}"
              f"{max(other[(k, 1)] + other[(k, 2)]):>11.2f}{quiet.size:>14} {q:>17}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
