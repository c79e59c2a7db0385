#!/usr/bin/env python3
"""CPU time of ``vigproc.estimate`` in two source trees, frame by frame in turn.

One worker process per tree (its tree first on ``sys.path``) is handed the same frames
in turn, so that a loaded machine slows both alike: the frames of ``vigproc bench speed
--api`` (the clean protocol's bases of ``--images`` through the lens, Table 1 setting 2
and no-vignetting fields). Prints each case's median CPU time per frame in each tree and
their ratio (second / first). Run it from outside both trees, e.g.::

    python scripts/estimate_ab.py /tmp/main-copy /work/h1 --images ../shared/data/jpeg_exif --limit 12
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

WORKER = r"""
import sys, time, numpy as np, vigproc
frames = np.load(sys.argv[1])
frames = {k: frames[k] for k in frames.files}
for f in frames.values():
    vigproc.estimate(f)  # kernels loaded, imports done
print("ready", flush=True)
for line in sys.stdin:
    u = time.process_time()
    vigproc.estimate(frames[line.strip()])
    print(time.process_time() - u, flush=True)
"""


def make_frames(tree: str, images: list[str], limit: int, out: Path) -> list[str]:
    """The bench's frames, made by ``tree``'s own benchmarks, saved to ``out`` (npz)."""
    code = (
        "import sys, numpy as np\n"
        "from benchmarks.clean import load_clean_bases\n"
        "from benchmarks.api_speed import case_fields\n"
        "from vigproc.io.protocol import vignetted\n"
        f"bases, _ = load_clean_bases({images!r}, limit={limit}, colour=True)\n"
        "f = case_fields()\n"
        "np.savez(sys.argv[1], **{f'{c}_{i}': vignetted(b, f[c][i % len(f[c])]) "
        "for c in f for i, b in enumerate(bases)})\n"
    )
    subprocess.run([sys.executable, "-c", code, str(out)], check=True, env=dict(os.environ, PYTHONPATH=tree))
    return list(np.load(out).files)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("before")
    ap.add_argument("after")
    ap.add_argument("--images", nargs="+", required=True)
    ap.add_argument("--limit", type=int, default=12)
    ap.add_argument("--rounds", type=int, default=2)
    a = ap.parse_args()
    trees = [str(Path(a.before).resolve()), str(Path(a.after).resolve())]
    with tempfile.TemporaryDirectory() as tmp:
        npz = Path(tmp) / "frames.npz"
        keys = make_frames(trees[0], a.images, a.limit, npz)
        workers = []
        for t in trees:
            p = subprocess.Popen([sys.executable, "-c", WORKER, str(npz)], stdin=subprocess.PIPE,
                                 stdout=subprocess.PIPE, text=True, env=dict(os.environ, PYTHONPATH=t))
            if p.stdout.readline().strip() != "ready":
                print(f"worker for {t} did not start", file=sys.stderr)
                return 1
            workers.append(p)
        times: dict[tuple[int, str], list[float]] = {}
        for _ in range(a.rounds):
            for k in keys:
                for i, p in enumerate(workers):
                    p.stdin.write(k + "\n")
                    p.stdin.flush()
                    times.setdefault((i, k.rsplit("_", 1)[0]), []).append(float(p.stdout.readline()))
        for p in workers:
            p.stdin.close()
            p.wait()
    print(f"{'case':10s} {'before ms':>10s} {'after ms':>9s} {'ratio':>6s}   (median CPU time per frame)")
    for case in dict.fromkeys(k.rsplit("_", 1)[0] for k in keys):
        b, c = (1000 * float(np.median(times[(i, case)])) for i in (0, 1))
        print(f"{case:10s} {b:10.1f} {c:9.1f} {c / b:6.3f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
