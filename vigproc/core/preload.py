"""Numba's once-per-process set-up, started early in a background thread.

The estimator's and the correction's kernels are compiled once and cached on disk
(``@njit(cache=True)``), and that cache is hit: a new process loads each kernel's
machine code in a few tens of milliseconds.  What a new process pays is Numba
itself: importing it, then, at the first call of any kernel, the target context's
``refresh`` (every typing and lowering registry of Numba is imported and installed,
``scipy.linalg`` among them for the LAPACK the least-squares solve calls).  That is
about a second of CPU, in one piece, before the first frame's estimate.

:func:`preload_numba` starts that work in a daemon thread, so that it runs while the
caller's own thread waits on I/O (exiftool's start, the first file's decode) instead
of after it.  It is only an earlier start of what the first kernel call would do:
it holds Numba's compiler lock for the refresh (the first dispatch then waits for it
and finds it done), takes Numba's locks in the order Numba takes them, loads no kernel and compiles nothing, and a failure is left to
the first kernel call to meet and report.
"""

from __future__ import annotations

import logging
import threading

logger = logging.getLogger(__name__)

_started: list[threading.Thread] = []
_lock = threading.Lock()


def _load() -> None:
    try:
        # Numba is imported through the kernels' package, the way the caller's thread imports
        # it: Python's lock on that one module then makes the two threads' imports of Numba
        # one after the other.  Two threads inside Numba's circular imports at once leave
        # one a partially initialised module; its failed import is undone, and the process
        # is left with a ``numba`` lacking ``numba.core`` (the first kernel compiled then
        # failed with "module 'numba' has no attribute 'core'")
        import vigproc.core._kernels  # noqa: F401
        from numba.core.compiler_lock import global_compiler_lock
        from numba.core.registry import cpu_target

        # the context is created first, outside the compiler lock: Numba creates it under the
        # lock of its cached property and then takes the compiler lock, so holding the compiler
        # lock while asking for it deadlocks with a thread that imports a kernel meanwhile
        context = cpu_target.target_context
        # what Numba's cache does before loading a kernel (caching.Cache.load_overload)
        with global_compiler_lock:
            context.refresh()
    except Exception:  # noqa: BLE001 - the first kernel call does it again and reports
        logger.debug("Numba preload failed", exc_info=True)


def numba_ready() -> bool:
    """Whether no preloading thread is still running (:func:`preload_numba` never
    started, or done): a kernel called now does not wait for Numba's set-up.

    Returns
    -------
    bool
    """
    with _lock:
        return not _started or not _started[0].is_alive()


def preload_numba() -> threading.Thread:
    """Start importing Numba and refreshing its target context in a daemon thread.

    Idempotent: one thread per process; later calls return it.

    Returns
    -------
    threading.Thread
        The (possibly finished) loading thread; joining it is optional.

    References
    ----------
    Numba's on-disk cache: https://numba.readthedocs.io/en/stable/developer/caching.html
    """
    with _lock:
        if not _started:
            t = threading.Thread(target=_load, name="vigproc-numba-preload", daemon=True)
            t.start()
            _started.append(t)
        return _started[0]
