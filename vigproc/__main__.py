"""``python -m vigproc ARGS``: the ``vigproc`` command (for an environment whose scripts
folder is not on PATH)."""

from vigproc.frontends.cli import run

raise SystemExit(run())
