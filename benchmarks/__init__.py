"""vigproc's benchmarks: timing benches and accuracy protocols, kept in the repository
beside the package and not installed with it (``vigproc bench ...`` finds them in a
source checkout, or through ``--benchmarks-dir`` or ``$VIGPROC_BENCHMARKS``).

Each module is importable on its own from the checkout's root
(``python -c "import benchmarks.clean"``); ``docs/benchmarks/`` holds the figures they
measured, each with the command that printed it.
"""

from __future__ import annotations

from pathlib import Path

#: The folder holding ``benchmarks/`` (a vigproc source checkout's root).
ROOT = Path(__file__).resolve().parent.parent


def child_code(code: str) -> str:
    """Python ``code`` for ``python -c`` in a child process that imports the benchmarks.

    The checkout's root goes at the end of the child's ``sys.path``, so the vigproc it
    already imports (installed, or by ``PYTHONPATH``) stays the one used.

    Parameters
    ----------
    code : str
        Python source run after the path is set.

    Returns
    -------
    str
    """
    return f"import sys\nsys.path.append({str(ROOT)!r})\n{code}"
