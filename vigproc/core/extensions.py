"""Third-party extensions of vigproc through Python entry points.

A package adds an estimator or a profile source to vigproc without touching it, by
declaring an entry point in its own ``pyproject.toml``::

    [project.entry-points."vigproc.estimators"]
    flatfield = "my_package.vignetting:estimate_flatfield"

    [project.entry-points."vigproc.profile_sources"]
    studio-db = "my_package.profiles:lookup"

Once the package is installed, ``vigproc plugins`` lists both, ``--method flatfield``
(or ``estimate(img, "flatfield")``) uses the estimator, and ``--profile auto``
consults the profile source (``--profile source:studio-db`` uses it alone).

Contracts
---------
``vigproc.estimators``: ``fn(img, *, channel_axis, seed) -> VignettingModel``
    ``img`` is the validated linear image (float, H×W, or H×W×C with
    ``channel_axis=-1``); ``seed`` is an int or None.  The model must describe the
    full H×W frame.  Raising :class:`~vigproc.errors.VigprocError` reports a
    problem with the input; any other exception is reported as a plugin failure.
``vigproc.profile_sources``: ``fn(lens_key, width, height) -> VignettingModel | None``
    ``lens_key`` is a :class:`~vigproc.io.exif.LensKey`; return the lens's model for a
    ``width``×``height`` frame, or None when the source has no profile for it.

Names are lower-case (``[a-z0-9][a-z0-9._-]*``, at most 64 characters).  A name
that is invalid, shadows a built-in method, or is declared by two installed
distributions is *broken*: listed with the reason, never used.  Loading is lazy
(a plugin's module is imported only when it is used or listed) and nothing is
cached between calls: an installed or removed plugin is seen by the next call.
"""

from __future__ import annotations

import logging
import re
from dataclasses import dataclass, field
from importlib.metadata import EntryPoint, entry_points
from typing import Any, Callable

import numpy as np

from vigproc.core.methods import METHODS
from vigproc.errors import EXIT_CODES, SETTINGS, VigprocError

log = logging.getLogger(__name__)

ESTIMATORS = "vigproc.estimators"
PROFILE_SOURCES = "vigproc.profile_sources"
#: Entry-point groups vigproc reads, with what each provides.
GROUPS = {ESTIMATORS: "estimator", PROFILE_SOURCES: "profile source"}

_NAME = re.compile(r"^[a-z0-9][a-z0-9._-]{0,63}$")
# Built-in --profile values a profile source must not be named like.
_RESERVED_PROFILES = frozenset({"auto", "estimate", "lensfun"})


class ExtensionError(VigprocError):
    """An installed plugin is broken: it cannot be loaded, or misbehaved when called."""

    exit_code = EXIT_CODES["plugin"]
    blame = SETTINGS


class UnknownMethodError(VigprocError, ValueError):
    """No built-in or installed estimator has the requested name."""

    exit_code = 2
    blame = SETTINGS


@dataclass(frozen=True)
class Extension:
    """One declared entry point of a vigproc group.

    Attributes
    ----------
    group : str
        ``vigproc.estimators`` or ``vigproc.profile_sources``.
    name : str
        The method / source name users type.
    target : str
        ``module:attribute`` the entry point refers to.
    distribution, version : str or None
        The installed distribution that declares it.
    problem : str or None
        Why the extension cannot be used (invalid or conflicting name), else None.
    """

    group: str
    name: str
    target: str
    distribution: str | None = None
    version: str | None = None
    problem: str | None = None
    _entry_point: EntryPoint | None = field(default=None, repr=False, compare=False)

    @property
    def origin(self) -> str:
        dist = f"{self.distribution} {self.version}" if self.distribution else "unknown distribution"
        return f"{self.target} from {dist}"

    def load(self) -> Callable[..., Any]:
        """Import the plugin's object.

        Raises
        ------
        ExtensionError
            The extension is broken, its module fails to import, or the object
            is not callable.
        """
        what = GROUPS.get(self.group, self.group)
        if self.problem is not None:
            raise ExtensionError(f"{what} plugin {self.name!r} ({self.origin}) is unusable: {self.problem}")
        try:
            obj = self._entry_point.load() if self._entry_point is not None else None
        except Exception as exc:  # any import-time failure of third-party code
            log.debug("loading %s plugin %s failed", what, self.name, exc_info=True)
            raise ExtensionError(f"{what} plugin {self.name!r} ({self.origin}) failed to load: "
                                 f"{type(exc).__name__}: {_one_line(exc)}") from None
        if not callable(obj):
            raise ExtensionError(f"{what} plugin {self.name!r} ({self.origin}) is not callable "
                                 f"(got {type(obj).__name__})")
        return obj

    def to_dict(self) -> dict[str, Any]:
        return {"group": self.group, "name": self.name, "target": self.target,
                "distribution": self.distribution, "version": self.version, "problem": self.problem}


def _one_line(exc: BaseException) -> str:
    return " ".join(str(exc).split())[:300]


# ------------------------------------------------------------------ discovery
def discover(group: str) -> list[Extension]:
    """Every extension declared for ``group`` by the installed distributions, by name.

    Parameters
    ----------
    group : str
        One of :data:`GROUPS`.

    Returns
    -------
    list of Extension
        Sorted by name; broken ones carry their ``problem``.
    """
    if group not in GROUPS:
        raise ValueError(f"unknown extension group {group!r}")
    found: dict[str, list[Extension]] = {}
    for ep in entry_points(group=group):
        dist = getattr(ep, "dist", None)
        ext = Extension(group, ep.name, ep.value, getattr(dist, "name", None), getattr(dist, "version", None),
                        None, ep)
        found.setdefault(ep.name, []).append(ext)
    out = []
    for name in sorted(found):
        exts = found[name]
        problem = None
        if not _NAME.match(name):
            problem = "invalid name (use lower-case letters, digits, '.', '_', '-'; at most 64 characters)"
        elif group == ESTIMATORS and name in METHODS:
            problem = f"the name shadows the built-in method {name!r}"
        elif group == PROFILE_SOURCES and name in _RESERVED_PROFILES:
            problem = f"the name shadows the built-in --profile value {name!r}"
        elif len(exts) > 1:
            problem = "declared more than once (" + "; ".join(e.origin for e in exts) + ")"
        for e in exts if problem else exts[:1]:
            out.append(Extension(e.group, e.name, e.target, e.distribution, e.version, problem, e._entry_point))
    return out


def find(group: str, name: str) -> Extension | None:
    """The extension named ``name`` in ``group`` (the first one when broken by a duplicate)."""
    return next((e for e in discover(group) if e.name == name), None)


def estimator_names() -> tuple[str, ...]:
    """Names of the installed, not broken, estimator extensions."""
    return tuple(e.name for e in discover(ESTIMATORS) if e.problem is None)


def method_names() -> tuple[str, ...]:
    """Built-in methods followed by the installed estimator extensions."""
    return (*METHODS, *estimator_names())


# ------------------------------------------------------------------ estimators
def estimator(name: str) -> Callable[..., Any]:
    """The installed estimator ``name``, wrapped so that its result is validated.

    Returns
    -------
    callable
        ``fn(img, *, channel_axis, seed) -> VignettingModel`` (``img`` already
        validated by :func:`vigproc.core.pixels.check_image`).

    Raises
    ------
    UnknownMethodError
        No built-in method or installed estimator has that name.
    ExtensionError
        The plugin is broken.
    """
    ext = find(ESTIMATORS, name)
    if ext is None:
        raise UnknownMethodError(f"unknown method {name!r}; choose one of {', '.join(method_names())}")
    fn = ext.load()

    def run(img: np.ndarray, *, channel_axis: int | None, seed: int | None):
        return call_estimator(ext, fn, img, channel_axis=channel_axis, seed=seed)

    return run


def call_estimator(ext: Extension, fn: Callable[..., Any], img: np.ndarray, *,
                   channel_axis: int | None, seed: int | None):
    """Call an estimator plugin and check that it returned a model of the frame.

    Raises
    ------
    VigprocError
        What the plugin raised on purpose (bad input).
    ExtensionError
        Any other exception, or a result that is not a model of the H×W frame.
    """
    from vigproc.core.model import VignettingModel

    try:
        m = fn(img, channel_axis=channel_axis, seed=seed)
    except VigprocError:
        raise
    except Exception as exc:
        log.debug("estimator plugin %s failed", ext.name, exc_info=True)
        raise ExtensionError(f"estimator plugin {ext.name!r} ({ext.origin}) failed: "
                             f"{type(exc).__name__}: {_one_line(exc)}") from None
    return _checked_model(m, img.shape[1], img.shape[0], f"estimator plugin {ext.name!r} ({ext.origin})",
                          VignettingModel)


def _checked_model(m: Any, width: int, height: int, who: str, model_type: type):
    if not isinstance(m, model_type):
        raise ExtensionError(f"{who} returned {type(m).__name__}, not a VignettingModel")
    if (m.width, m.height) != (width, height):
        raise ExtensionError(f"{who} returned a model of a {m.width}x{m.height} frame for a "
                             f"{width}x{height} one")
    return m


# ------------------------------------------------------------------ profile sources
@dataclass(frozen=True)
class ProfileSource:
    """A loaded profile-source plugin (see the module docstring for the contract)."""

    extension: Extension
    fn: Callable[..., Any]

    @property
    def name(self) -> str:
        return self.extension.name

    def lookup(self, lens_key, width: int, height: int):
        """The source's model of ``lens_key`` for a ``width``×``height`` frame, or None.

        Raises
        ------
        ExtensionError
            The plugin raised, or returned something other than None or a model of
            that frame.
        """
        from vigproc.core.model import VignettingModel

        who = f"profile source {self.name!r} ({self.extension.origin})"
        try:
            m = self.fn(lens_key, int(width), int(height))
        except VigprocError:
            raise
        except Exception as exc:
            log.debug("%s failed", who, exc_info=True)
            raise ExtensionError(f"{who} failed: {type(exc).__name__}: {_one_line(exc)}") from None
        return None if m is None else _checked_model(m, int(width), int(height), who, VignettingModel)


def load_profile_sources(*, strict: bool = False) -> dict[str, ProfileSource]:
    """The installed profile sources, by name.

    Parameters
    ----------
    strict : bool
        Raise on a broken source instead of logging a warning and leaving it out.

    Raises
    ------
    ExtensionError
        With ``strict``, for the first broken source.
    """
    out = {}
    for ext in discover(PROFILE_SOURCES):
        try:
            out.setdefault(ext.name, ProfileSource(ext, ext.load()))
        except ExtensionError as exc:
            if strict:
                raise
            log.warning("%s", exc)
    return out


def profile_source(name: str) -> ProfileSource:
    """The installed profile source ``name``.

    Raises
    ------
    ExtensionError
        No such source, or it is broken.
    """
    ext = find(PROFILE_SOURCES, name)
    if ext is None:
        names = ", ".join(e.name for e in discover(PROFILE_SOURCES)) or "none installed"
        raise ExtensionError(f"unknown profile source {name!r} ({names})")
    return ProfileSource(ext, ext.load())
