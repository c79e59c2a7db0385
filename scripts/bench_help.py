"""Start-up of ``vigproc --help`` and ``vigproc correct --help`` from two source trees,
beside a bare ``python -c pass``: interleaved runs, medians of wall and CPU time.

Usage (from anywhere; the children run in an empty folder, so that ``python -m`` does not
import a vigproc from the current folder)::

    python scripts/bench_help.py --before TREE --after TREE [--runs 20]

Each command runs twice per round: with compiled bytecode (in a private
``PYTHONPYCACHEPREFIX``, warmed first; what an installed copy has) and without it
(``PYTHONDONTWRITEBYTECODE``, sources compiled at every start).
"""

from __future__ import annotations

import argparse
import os
import resource
import statistics
import subprocess
import sys
import tempfile
import time


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--before", required=True, help="source tree (the folder holding vigproc/)")
    ap.add_argument("--after", required=True, help="source tree (the folder holding vigproc/)")
    ap.add_argument("--runs", type=int, default=20, help="rounds (default %(default)s)")
    args = ap.parse_args()
    with tempfile.TemporaryDirectory() as empty, tempfile.TemporaryDirectory() as pycache:
        def env(tree: str, compiled: bool) -> dict[str, str]:
            e = dict(os.environ, PYTHONPATH=tree)
            e.pop("PYTHONDONTWRITEBYTECODE", None)
            e.pop("PYTHONPYCACHEPREFIX", None)
            if compiled:
                e["PYTHONPYCACHEPREFIX"] = pycache
            else:
                e["PYTHONDONTWRITEBYTECODE"] = "1"
            return e

        runs = {}
        for compiled in (True, False):
            runs[("python -c pass", "", compiled)] = ([sys.executable, "-c", "pass"], env("", compiled))
            for label, tree in (("before", args.before), ("after", args.after)):
                for argv in (["--help"], ["correct", "--help"]):
                    runs[("vigproc " + " ".join(argv), label, compiled)] = (
                        [sys.executable, "-m", "vigproc.frontends.cli", *argv], env(tree, compiled))
        for cmd, e in runs.values():  # warm the bytecode and the file cache
            subprocess.run(cmd, env=e, cwd=empty, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, check=True)
        wall: dict = {k: [] for k in runs}
        cpu: dict = {k: [] for k in runs}
        load = os.getloadavg()[0]
        for _ in range(args.runs):
            for k, (cmd, e) in runs.items():
                r0 = resource.getrusage(resource.RUSAGE_CHILDREN)
                t0 = time.perf_counter()
                subprocess.run(cmd, env=e, cwd=empty, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
                wall[k].append(time.perf_counter() - t0)
                r1 = resource.getrusage(resource.RUSAGE_CHILDREN)
                cpu[k].append(r1.ru_utime - r0.ru_utime + r1.ru_stime - r0.ru_stime)
    print(f"{args.runs} interleaved rounds; load average {load:.1f} before, {os.getloadavg()[0]:.1f} after")
    print(f"{'bytecode':<10}{'command':<24}{'tree':<8}{'wall s':>8}{'CPU s':>8}")
    for k in runs:
        print(f"{'yes' if k[2] else 'no':<10}{k[0]:<24}{k[1]:<8}{statistics.median(wall[k]):>8.3f}"
              f"{statistics.median(cpu[k]):>8.3f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
