"""``vigproc bench clean --methods default+exif`` with the experiment of
:mod:`vigproc.core.ambiguity` standing in for the default estimate (issue 38, part a's
designs; docs/benchmarks/real-frames.md), or without it as the baseline.

Usage (from the repository root; further arguments go to ``bench clean``):
    NUMBA_NUM_THREADS=1 python scripts/bench_clean_ambiguity.py {base|all|scene|scene3} OUT.json [--limit 10]

``scene3``: the noise subtracted with ``noise_factor`` 3 (the independence bound).
"""

from __future__ import annotations

import sys


def main(argv: list[str]) -> int:
    if len(argv) < 2 or argv[0] not in ("base", "all", "scene", "scene3"):
        print(__doc__, file=sys.stderr)
        return 2
    mode, out, extra = argv[0], argv[1], argv[2:]
    if mode != "base":
        import vigproc.core.estimate as E
        from vigproc.core.ambiguity import estimate_shrunk

        orig = E.estimate_default

        def shrunk(lum, mask=None, hint=None, family=None, colour=None, rule=None):
            return estimate_shrunk(lum, mask, hint, family, colour, base=orig, subtract_noise=(mode != "all"),
                                   noise_factor=3.0 if mode == "scene3" else 1.0)

        E.estimate_default = shrunk
    from vigproc.frontends.cli import main as cli

    return cli(["bench", "clean", "--methods", "default+exif", "--no-table1", "--json", out, *extra])


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
