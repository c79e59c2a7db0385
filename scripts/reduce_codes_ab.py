#!/usr/bin/env python3
"""CPU of the reduced copy's kernel (``vigproc/core/_kernels/codes.py: reduce_codes``) in two
source trees, on the decoded codes of the photos ``vigproc bench throughput`` selects.

Each tree's kernel module is loaded from its own file; the frames are decoded once (by this
tree's reader) and handed to both kernels in turn, round by round, so that a loaded machine
slows both alike. Checks that both give the same bits, then prints the time per frame with
Numba's default threads and with one thread, and their ratio (second / first)::

    python scripts/reduce_codes_ab.py /work/main /work/h3 --images ../shared/data/jpeg_exif --limit 26
"""

from __future__ import annotations

import argparse
import importlib.util
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks.throughput import select_photos  # noqa: E402
from vigproc.core.estimate import reduction_factor  # noqa: E402
from vigproc.io.images import read_encoded  # noqa: E402


def _kernel(tree: str, name: str):
    spec = importlib.util.spec_from_file_location(name, Path(tree) / "vigproc/core/_kernels/codes.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod.reduce_codes


def _run(kernel, frames):
    out = []
    for codes, lut, k in frames:
        h, w, c = codes.shape
        small = np.empty((h // k, w // k, c), np.float32)
        hot = np.zeros((h // k, w // k), np.int64)
        dark = np.zeros_like(hot)
        kernel(codes, lut, k, 254, small, hot, dark)
        out.append((small, hot, dark))
    return out


def main() -> int:
    import numba

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("before")
    ap.add_argument("after")
    ap.add_argument("--images", required=True)
    ap.add_argument("--min-mp", type=float, default=0.75)
    ap.add_argument("--limit", type=int, default=26)
    ap.add_argument("--rounds", type=int, default=10)
    a = ap.parse_args()
    kernels = [_kernel(a.before, "codes_before"), _kernel(a.after, "codes_after")]
    photos, _ = select_photos(Path(a.images), a.min_mp, a.limit)
    frames = []
    for p in photos:
        enc = read_encoded(p.path)[0]
        h, w = enc.codes.shape[:2]
        frames.append((enc.codes, np.ascontiguousarray(enc.decode_table(), dtype=np.float32), reduction_factor(w, h)))
    got = [_run(k, frames) for k in kernels]
    same = all(np.array_equal(x[0].view(np.uint32), y[0].view(np.uint32)) and np.array_equal(x[1], y[1])
               and np.array_equal(x[2], y[2]) for x, y in zip(*got))
    print(f"{len(frames)} frames, {sum(c.shape[0] * c.shape[1] for c, _, _ in frames) / 1e6:.1f} MP; same bits: {same}")
    for threads in dict.fromkeys((numba.get_num_threads(), 1)):
        numba.set_num_threads(threads)
        times = [[], []]
        for _ in range(a.rounds):
            for i, k in enumerate(kernels):
                t = time.perf_counter()
                _run(k, frames)
                times[i].append((time.perf_counter() - t) / len(frames) * 1e3)
        b, c = (float(np.median(t)) for t in times)
        print(f"threads {threads}: before {b:.2f} ms a frame, after {c:.2f} ms, ratio {c / b:.2f} (medians of {a.rounds})")
    return 0 if same else 1


if __name__ == "__main__":
    sys.exit(main())
