"""``python -m benchmarks NAME [OPTIONS]`` from a source checkout's root: the same as
``vigproc bench NAME [OPTIONS]`` (``python -m benchmarks --help`` lists them), these
benchmarks whatever vigproc is importable (installed, or the checkout's own)."""

from __future__ import annotations

import sys

from benchmarks import ROOT


def main(argv: list[str] | None = None) -> int:
    """Run ``vigproc bench`` on this folder's benchmarks.

    Parameters
    ----------
    argv : list of str, optional
        The benchmark's name and options (default: the command line's).

    Returns
    -------
    int
        ``vigproc``'s exit code.
    """
    from vigproc.frontends.cli import main as vigproc_main

    args = list(sys.argv[1:] if argv is None else argv)
    return vigproc_main(["bench", "--benchmarks-dir", str(ROOT / "benchmarks"), *args])


if __name__ == "__main__":
    sys.exit(main())
