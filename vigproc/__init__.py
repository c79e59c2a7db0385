"""vigproc: lens vignetting estimation, correction, per-lens profiles and forensics.

>>> import numpy as np
>>> import vigproc
>>> lens = vigproc.VignettingModel(240, 160, p=(1 / 150**2, 0.0, 1 / 150**2))  # a known fall-off
>>> img = 0.5 * lens.field()[..., None] * (1 + 0.01 * np.random.default_rng(0).random((160, 240, 3)))
>>> m = vigproc.estimate(img, "flat-field")  # img: H×W or H×W×C linear float (here a white wall)
>>> phi = m.field((160, 240))               # attenuation, 1.0 at the vignetting centre
>>> out = vigproc.correct(img, m)
>>> round(m.field_ev_rms(), 2), bool(out.std() / out.mean() < 0.01)
(0.25, True)

Photo pipelines: :class:`vigproc.Pipeline` (:mod:`vigproc.frontends.api`, the stable interface).
"""

import os as _os


def _numba_cache_fallback(environ=_os.environ, access=_os.access) -> str | None:
    """Where Numba should cache compiled kernels when its own choices fail, else None.

    Numba caches next to the source or in the user's cache folder; when neither is
    writable (a system-wide install run by a service user without a home) it refuses
    to define cached functions at all, so importing vigproc would fail.  Then a private
    folder in the temporary directory is used instead.
    """
    import tempfile

    if environ.get("NUMBA_CACHE_DIR"):
        return None
    if access(_os.path.join(_os.path.dirname(__file__), "core", "_kernels"), _os.W_OK):
        return None
    home = environ.get("XDG_CACHE_HOME") or _os.path.join(_os.path.expanduser("~"), ".cache")
    probe = home
    while probe and not _os.path.exists(probe):  # the nearest existing folder decides
        probe = _os.path.dirname(probe)
    if probe and access(probe, _os.W_OK):
        return None
    return _os.path.join(tempfile.gettempdir(), f"vigproc-numba-{_os.getuid() if hasattr(_os, 'getuid') else 0}")


if (_cache := _numba_cache_fallback()) is not None:
    _os.environ["NUMBA_CACHE_DIR"] = _cache

# The public names are imported when first used (PEP 562): ``vigproc --help`` and a
# host's hook call must not pay for scipy and the Numba kernels they do not need.
_PUBLIC = {
    "Pipeline": "vigproc.frontends.api", "Result": "vigproc.frontends.api", "correct": "vigproc.core.correct",
    "ImageReadError": "vigproc.errors", "ImageWriteError": "vigproc.errors",
    "InvalidImageError": "vigproc.errors", "ModelError": "vigproc.errors", "PriorError": "vigproc.errors",
    "UnsupportedFormatError": "vigproc.errors", "VigprocError": "vigproc.errors",
    "METHODS": "vigproc.core.methods", "estimate": "vigproc.core.estimate",
    "FitQuality": "vigproc.core.model", "VignettingModel": "vigproc.core.model", "RobustSettings": "vigproc.core.robust",
    "LensHint": "vigproc.core.family_fit",
}



def __getattr__(name: str):
    if name in _PUBLIC:
        import importlib

        value = getattr(importlib.import_module(_PUBLIC[name]), name)
        globals()[name] = value  # later look-ups skip this function
        return value
    raise AttributeError(f"module 'vigproc' has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted([*globals(), *_PUBLIC])


from vigproc._version import __version__  # noqa: E402  (re-exported)

__all__ = [
    "METHODS", "FitQuality", "ImageReadError", "ImageWriteError", "InvalidImageError", "LensHint",
    "ModelError", "Pipeline", "PriorError", "Result", "RobustSettings", "UnsupportedFormatError",
    "VignettingModel", "VigprocError", "correct", "estimate",
]
