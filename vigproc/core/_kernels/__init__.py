"""vigproc's Numba kernels; importing the package first drops their on-disk cache when
any kernel source changed.

Numba reuses a cached kernel while the kernel's *own* file is unchanged, so a kernel
calling one in another file (``gauss_newton`` → ``geometry``, ``irls``, ``bin_normal``;
``codes`` → ``correct`` → ``field``) kept the callee's old machine code after a pull
that changed only the callee: wrong answers and wrong timings.  A digest of every
``*.py`` here is kept beside Numba's cache files (:data:`STAMP`); when it differs, this
folder's ``*.nbi``/``*.nbc`` are deleted (the kernels recompile once).  Any failure is
logged at debug level and ignored: the guard must never break ``import vigproc``.
"""

from __future__ import annotations

import hashlib
import logging
import os
import types

from vigproc.atomic import atomic_write_text

try:  # an API change in Numba skips the guard (see numba_cache_dir)
    from numba.core import caching as _caching
except ImportError:  # pragma: no cover - Numba is a dependency
    _caching = None

log = logging.getLogger(__name__)

#: The digest's file, in the folder of Numba's cache files for these kernels.
STAMP = "vigproc-kernels.stamp"
#: Numba's cache files: the index of a function and its compiled code.
CACHE_SUFFIXES = (".nbi", ".nbc")
HERE = os.path.dirname(os.path.abspath(__file__))


def kernel_sources(folder: str) -> list[str]:
    """The ``*.py`` files of ``folder``, sorted (the digest and the order must not depend
    on the file system's)."""
    return sorted(os.path.join(folder, n) for n in os.listdir(folder) if n.endswith(".py"))


def sources_digest(sources: list[str]) -> str:
    """SHA-256 over each source's name and bytes (about 60 kB here)."""
    h = hashlib.sha256()
    for path in sources:
        with open(path, "rb") as fh:
            data = fh.read()
        h.update(f"{os.path.basename(path)}\0{len(data)}\0".encode())
        h.update(data)
    return h.hexdigest()


def _probe() -> None:
    """A Python function Numba's locators are asked about (only its file matters)."""


def numba_cache_dir(source: str) -> str | None:
    """The folder where Numba caches the kernels of the file ``source``, chosen by Numba's
    own locators in Numba's order (``NUMBA_CACHE_DIR``, then a writable ``__pycache__``
    beside the source, then the user-wide cache); None if Numba has none or its API
    changed."""
    if _caching is None:
        return None
    probe = types.FunctionType(_probe.__code__.replace(co_filename=source), {})
    try:
        return _caching.CompileResultCacheImpl(probe).locator.get_cache_path()
    except RuntimeError:  # no locator: Numba would not cache either
        return None


def flush_if_stale(folder: str, cache_dir: str) -> bool:
    """Delete ``cache_dir``'s Numba cache files and write the new stamp if ``folder``'s
    sources changed since the stamp; True if it flushed.  Raises OSError."""
    digest = sources_digest(kernel_sources(folder))
    stamp = os.path.join(cache_dir, STAMP)
    try:
        with open(stamp, "rb") as fh:  # bytes: no codec to look up at every import
            if fh.read().strip() == digest.encode():
                return False
    except FileNotFoundError:
        pass
    # Numba makes the folder at its first save; a stamp written before that spares the
    # kernels one needless recompilation at the next import
    os.makedirs(cache_dir, exist_ok=True)
    with os.scandir(cache_dir) as entries:
        stale = [e.path for e in entries if e.name.endswith(CACHE_SUFFIXES)]
    for path in stale:
        try:
            os.unlink(path)
        except FileNotFoundError:  # another process importing at the same time removed it
            pass
    # only after the deletions: a process killed in between deletes again next time
    atomic_write_text(stamp, digest + "\n")
    log.debug("kernel sources changed: %d Numba cache files removed from %s", len(stale), cache_dir)
    return True


def check_cache(folder: str = HERE, cache_dir: str | None = None) -> bool:
    """:func:`flush_if_stale` for ``folder`` in Numba's cache folder of it (or
    ``cache_dir``); never raises (False and a debug line on any failure)."""
    try:
        if cache_dir is None:
            sources = kernel_sources(folder)
            cache_dir = numba_cache_dir(sources[0]) if sources else None
            if cache_dir is None:
                log.debug("kernel cache guard skipped: no Numba cache folder for %s", folder)
                return False
        return flush_if_stale(folder, cache_dir)
    except Exception as exc:  # noqa: BLE001 - a guard of a cache must never stop an import
        log.debug("kernel cache guard skipped: %s: %s", type(exc).__name__, exc)
        return False


check_cache()
