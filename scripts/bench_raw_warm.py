#!/usr/bin/env python
"""One RAW, warm, in one process: ``Processor.process_file`` (``correct``, ``--unapplied
write``) against rawpy's development with vigproc's settings, the same 16-bit TIFF written
by OpenImageIO and an exiftool EXIF copy (``bench throughput --raw``'s floor), interleaved.

Usage::

    python scripts/bench_raw_warm.py RAW [ROUNDS] [--profile]

Prints each round's seconds and ratio, the medians, and with ``--profile`` a cProfile of
one more ``process_file`` (cumulative and own time). Scratch files go to a temporary folder.
"""

from __future__ import annotations

import cProfile
import io
import pstats
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path


def main(argv: list[str]) -> int:
    args = [a for a in argv if a != "--profile"]
    if not args:
        print(__doc__, file=sys.stderr)
        return 2
    src, rounds, prof = Path(args[0]), int(args[1]) if len(args) > 1 else 3, "--profile" in argv

    import OpenImageIO as oiio
    import rawpy

    from vigproc.io.images import RAW_DEVELOP
    from vigproc.io.metadata import exiftool_path
    from vigproc.pipeline.processor import Processor, Settings

    with tempfile.TemporaryDirectory(prefix="vigproc-raw-warm-") as tmp:
        out = Path(tmp)

        def floor() -> None:
            with rawpy.imread(str(src)) as raw:
                rgb = raw.postprocess(**RAW_DEVELOP)
            h, w, c = rgb.shape
            t = out / (src.name + ".floor.tif")
            o = oiio.ImageOutput.create(str(t))
            if o is None or not o.open(str(t), oiio.ImageSpec(w, h, c, "uint16")) or not o.write_image(rgb):
                raise SystemExit(f"floor: cannot write {t}: {oiio.geterror()}")
            o.close()
            subprocess.run([exiftool_path(), "-q", "-q", "-overwrite_original", "-tagsFromFile", str(src),
                            "-all:all", "--", str(t)], check=True, stdin=subprocess.DEVNULL)

        with Processor(Settings(mode="correct", profile="estimate")) as proc:
            def vig():
                d = out / "v"
                shutil.rmtree(d, ignore_errors=True)
                d.mkdir()
                return proc.process_file(src, d, unapplied="write")

            vig()
            floor()  # warm: Numba's kernels, exiftool, the page cache
            tf, tv = [], []
            for i in range(rounds):
                t0 = time.perf_counter()
                floor()
                tf.append(time.perf_counter() - t0)
                t0 = time.perf_counter()
                r = vig()
                tv.append(time.perf_counter() - t0)
                print(f"round {i}: floor {tf[-1]:.2f} s, vigproc {tv[-1]:.2f} s, ratio {tv[-1] / tf[-1]:.3f}"
                      f"  applied={r.applied}", flush=True)
            mf, mv = statistics.median(tf), statistics.median(tv)
            print(f"median: floor {mf:.2f} s, vigproc {mv:.2f} s, ratio of medians {mv / mf:.3f}")
            if prof:
                pr = cProfile.Profile()
                pr.enable()
                vig()
                pr.disable()
                for key, n in (("cumulative", 45), ("tottime", 25)):
                    s = io.StringIO()
                    pstats.Stats(pr, stream=s).sort_stats(key).print_stats(n)
                    print(s.getvalue())
    return 0


if __name__ == "__main__":
    raise SystemExit(main(sys.argv[1:]))
