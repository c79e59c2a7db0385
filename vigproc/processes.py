"""Child processes that die with their parent.

A daemon worker, a batch pool worker or an exiftool started by either must not outlive
the process that started it when that one is killed (SIGKILL included): it would wait
for work forever or keep writing into an output folder.  Linux's ``PR_SET_PDEATHSIG``
asks the kernel to kill it; elsewhere nothing is done.
"""

from __future__ import annotations

import ctypes
import os
import signal
import sys
from typing import Any

_PR_SET_PDEATHSIG = 1


def _libc_prctl() -> Any:
    # looked up at import, not in a forked child (no dlopen between fork and exec)
    if not sys.platform.startswith("linux"):
        return None
    try:
        return ctypes.CDLL(None, use_errno=True).prctl
    except (OSError, AttributeError):
        return None


_prctl = _libc_prctl()
#: Whether :func:`die_with_parent` can do anything on this system.
AVAILABLE = _prctl is not None


def die_with_parent(parent_pid: int | None = None) -> None:
    """Be killed (SIGKILL) when the parent process dies.  Safe as a ``preexec_fn``.

    ``parent_pid``: the expected parent; if it already died before the request took
    effect, exit at once.
    """
    if _prctl is None:
        return
    _prctl(_PR_SET_PDEATHSIG, int(signal.SIGKILL), 0, 0, 0)
    if parent_pid is not None and os.getppid() != parent_pid:
        os._exit(1)
