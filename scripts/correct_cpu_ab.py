#!/usr/bin/env python3
"""CPU time (user + system) and wall-clock of ``vigproc correct --unapplied copy`` in two source
trees, on copies of the photos ``vigproc bench throughput`` selects, a new process per run,
the trees in turn round by round (so that a loaded machine slows both alike); prints the
medians and their ratios (second / first)::

    python scripts/correct_cpu_ab.py /work/main /work/h3 --images ../shared/data/jpeg_exif --limit 26 --rounds 4
"""

from __future__ import annotations

import argparse
import os
import resource
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks.throughput import select_photos, stage  # noqa: E402


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("before")
    ap.add_argument("after")
    ap.add_argument("--images", required=True)
    ap.add_argument("--min-mp", type=float, default=0.75)
    ap.add_argument("--limit", type=int, default=26)
    ap.add_argument("--rounds", type=int, default=4)
    a = ap.parse_args()
    trees = [str(Path(a.before).resolve()), str(Path(a.after).resolve())]
    photos, _ = select_photos(Path(a.images), a.min_mp, a.limit)
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(tmp)
        inputs = [str(p) for p in stage(photos, work / "in")]
        cpu: list[list[float]] = [[], []]
        wall: list[list[float]] = [[], []]
        for _ in range(a.rounds):
            for i, tree in enumerate(trees):
                out, db = work / "out", work / "profiles.sqlite"
                shutil.rmtree(out, ignore_errors=True)
                db.unlink(missing_ok=True)
                env = {**os.environ, "PYTHONPATH": tree, "VIGPROC_PROFILE_DB": str(db)}
                u0, w0 = resource.getrusage(resource.RUSAGE_CHILDREN), time.perf_counter()
                subprocess.run([sys.executable, "-m", "vigproc.frontends.cli", "correct", "--unapplied", "copy",
                                "-o", str(out), "--", *inputs], check=True, env=env, cwd=tmp,
                               stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
                wall[i].append(time.perf_counter() - w0)
                u1 = resource.getrusage(resource.RUSAGE_CHILDREN)
                cpu[i].append(u1.ru_utime + u1.ru_stime - u0.ru_utime - u0.ru_stime)
    c0, c1, w0, w1 = (float(np.median(x)) for x in (cpu[0], cpu[1], wall[0], wall[1]))
    print(f"{len(inputs)} photos, medians of {a.rounds} rounds")
    print(f"CPU s: before {c0:.2f} after {c1:.2f} ratio {c1 / c0:.3f}")
    print(f"wall s: before {w0:.2f} after {w1:.2f} ratio {w1 / w0:.3f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
