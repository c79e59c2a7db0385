"""The stable pipeline API: correct or check an in-memory linear image.

This is the interface photo pipelines program against; the names below keep their
meaning across vigproc releases (:data:`API_VERSION` changes when they do not).

>>> import numpy as np
>>> from vigproc.frontends.api import Pipeline
>>> img = 0.5 + 0.05 * np.random.default_rng(0).random((160, 240, 3))  # a linear image (here: noise)
>>> with Pipeline("correct") as vp:  # store="~/.local/share/vigproc/profiles.sqlite": stored profiles
...     out, res = vp.process(img, lens={"make": "Canon", "model": "Canon EOS 5D Mark II",
...                                      "lens": "EF24-105mm f/4L IS USM", "focal_mm": 24,
...                                      "fnumber": 4.0})
>>> res.applied, res.fallback, res.lens["lens_id"]  # no fall-off to correct in noise
(False, True, 'canon|canon eos 5d mark ii|ef24-105mm f/4l is usm')

One-off calls: :func:`process` (same arguments, no store unless given).

Threads
-------
A :class:`Pipeline` may be shared by any number of threads: its settings are
immutable, each call runs on its own :class:`vigproc.pipeline.processor.Processor`, and the
profile store (SQLite, whose connections are per thread) is opened once per thread
that uses it.  There is no module-level state.  The Numba kernels are compiled once
and cached on disk (``cache=True``); inputs are converted to one dtype and layout
(C-contiguous float32, channels last) so no call triggers a new specialisation.

References
----------
S. Lyu, "Estimating vignetting function from a single image for image authentication",
ACM MM&Sec 2010.
"""

from __future__ import annotations

import math
import os
import threading
from dataclasses import dataclass
from typing import Any, Mapping

import numpy as np

from vigproc.core.pixels import check_image
from vigproc.errors import MetadataError, VigprocError
from vigproc.stores.opening import open_profile_store

__all__ = ["API_VERSION", "MODES", "Pipeline", "RequestError", "Result", "lens_key", "process"]

#: Version of this interface (the names and meanings in this module).
API_VERSION = 1
#: What :meth:`Pipeline.process` can do to an image.
MODES = ("correct", "check", "estimate")

# Friendly lens-field names -> the ExifTool tag they stand for.
_LENS_FIELDS = {
    "make": "Make", "maker": "Make", "camera_make": "Make",
    "model": "Model", "camera": "Model", "camera_model": "Model",
    "lens": "LensModel", "lens_model": "LensModel",
    "lens_serial": "LensSerialNumber", "lens_serial_number": "LensSerialNumber",
    "focal_mm": "FocalLength", "focal_length": "FocalLength", "focal": "FocalLength",
    "fnumber": "FNumber", "f_number": "FNumber", "aperture": "FNumber",
    "focus_distance_m": "FocusDistance", "focus_distance": "FocusDistance",
}
_MAX_LENS_FIELDS = 64


class RequestError(VigprocError, ValueError):
    """A caller's arguments are unusable (unknown mode, malformed lens data...)."""

    exit_code = 2


# ------------------------------------------------------------------ lens data
def lens_key(lens: Any):
    """A :class:`~vigproc.io.exif.LensKey` from what a pipeline knows about the lens.

    Parameters
    ----------
    lens : LensKey, mapping or None
        A :class:`~vigproc.io.exif.LensKey`; the output of ``LensKey.to_dict()``; or a
        mapping of EXIF-like fields: ``make``, ``model``, ``lens``, ``lens_serial``,
        ``focal_mm``, ``fnumber``, ``focus_distance_m`` (aliases ``maker``,
        ``camera``, ``lens_model``, ``focal_length``, ``f_number``/``aperture``,
        ``focus_distance``), and/or ExifTool ``GROUP:Tag`` keys
        (``"EXIF:LensModel"``).  Values are cleaned exactly as EXIF read from a file
        (hostile strings are normalised, absurd numbers dropped).

    Returns
    -------
    LensKey or None
        None for ``lens=None``.

    Raises
    ------
    RequestError
        Not a mapping, unknown field names, or values that are not text/numbers.
    """
    from vigproc.io.exif import LensKey, lens_key_from_metadata

    if lens is None or isinstance(lens, LensKey):
        return lens
    if not isinstance(lens, Mapping):
        raise RequestError(f"lens must be a LensKey, a mapping or None, got {type(lens).__name__}")
    if len(lens) > _MAX_LENS_FIELDS:
        raise RequestError(f"lens data has {len(lens)} fields (at most {_MAX_LENS_FIELDS})")
    if "missing" in lens:  # LensKey.to_dict() output
        try:
            return LensKey.from_dict(lens)
        except MetadataError as exc:
            raise RequestError(str(exc)) from None
    meta: dict[str, Any] = {}
    for k, v in lens.items():
        if not isinstance(k, str):
            raise RequestError(f"lens field names must be text, got {k!r}")
        if isinstance(v, (np.integer, np.floating)):  # pipelines often hold numpy scalars
            v = v.item()
        if v is not None and (isinstance(v, (bool, np.bool_)) or not isinstance(v, (str, int, float))):
            raise RequestError(f"lens field {k!r} must be text, a number or null, got {type(v).__name__}")
        if ":" in k:
            meta[k] = v
            continue
        tag = _LENS_FIELDS.get(k.strip().lower().replace("-", "_").replace(" ", "_"))
        if tag is None:
            raise RequestError(f"unknown lens field {k!r} (use {', '.join(sorted(set(_LENS_FIELDS)))} "
                               "or ExifTool GROUP:Tag names)")
        if tag == "FNumber" and isinstance(v, str):  # "f/2.8" as hosts print it
            v = v.strip().lower().removeprefix("f/").removeprefix("f")
        meta[f"EXIF:{tag}"] = v
    return lens_key_from_metadata(meta, source="lens data")


# ------------------------------------------------------------------ result
@dataclass(frozen=True)
class Result:
    """What :meth:`Pipeline.process` did to one image.

    Attributes
    ----------
    mode : str
        ``correct``, ``check`` or ``estimate``.
    applied : bool
        Whether a correction was divided out of the returned image.
    source : str or None
        Where the model came from: ``estimate``, ``stored-profile``, ``lensfun``,
        ``profile-file`` or ``source:NAME`` (a profile-source plugin).
    model : VignettingModel or None
        The model applied (correct), estimated (estimate, check) or None.
    falloff_ev : float or None
        RMS over the frame of log2 of the model's attenuation, in EV (0 = none).
    removed_ev : float or None
        Correct mode: the part of it divided out of the returned image, in EV
        (``falloff_ev`` × strength when applied, else 0); None in other modes.
    confidence, snr : float or None
        The estimate's support in the image (estimates of the default method); in check
        mode the verdict's, i.e. the frame's estimate with these settings
        (:func:`vigproc.forensics.check.frame_quality`), not the test's own fit.
    fallback : bool
        The estimate was too weak to apply: the image is returned uncorrected.
    verdict : dict or None
        Check mode: the forensic verdict (:func:`vigproc.forensics.check.forensic_check`).
    lens : dict
        The lens key used (``lens_id`` None when unknown).
    seconds : float
    """

    mode: str
    applied: bool
    source: str | None
    model: Any
    falloff_ev: float | None
    removed_ev: float | None
    confidence: float | None
    snr: float | None
    fallback: bool
    verdict: dict[str, Any] | None
    lens: dict[str, Any]
    seconds: float

    @classmethod
    def from_frame(cls, res) -> Result:
        """Build from a :class:`vigproc.pipeline.processor.FrameResult`."""
        m = res.model
        q = getattr(m, "quality", None)
        falloff = None if m is None else float(m.field_ev_rms())
        removed = None
        if res.mode == "correct":
            removed = round(falloff * res.strength, 4) if res.applied and falloff is not None else 0.0
        conf = None if q is None else _finite(q.confidence)
        snr = None if q is None else _finite(q.snr)
        if res.mode == "check" and res.verdict is not None:
            # the verdict states the frame's estimate's (the model is the test's own fit):
            # the figures `vigproc estimate` and `check` give
            conf, snr = (None if res.verdict.get(k) is None else _finite(res.verdict[k]) for k in ("confidence", "snr"))
        return cls(
            mode=res.mode, applied=bool(res.applied), source=res.source, model=m,
            falloff_ev=None if falloff is None else round(falloff, 4), removed_ev=removed,
            confidence=conf, snr=snr,
            fallback=bool(q is not None and q.fallback),
            verdict=res.verdict, lens=res.lens, seconds=res.seconds,
        )

    @property
    def summary(self) -> str:
        """One line for a host's status bar or log."""
        conf = f", confidence {self.confidence:.2f}" if self.confidence is not None else ""
        if self.mode == "check":
            v = self.verdict or {}
            return f"check: {v.get('verdict', 'no verdict')}"
        if self.fallback:
            from vigproc.pipeline.processor import not_applied_reason

            return f"not corrected: {not_applied_reason(self.model)}{conf}"
        ev = self.falloff_ev or 0.0
        if self.mode == "correct":
            return f"{self.removed_ev or 0.0:.2f} EV fall-off removed ({self.source}{conf})" if self.applied else \
                f"not corrected ({self.source})"
        return f"{ev:.2f} EV fall-off estimated ({self.source}{conf})"

    def to_dict(self) -> dict[str, Any]:
        """JSON-able record (the model as :meth:`VignettingModel.to_dict`)."""
        return {"mode": self.mode, "applied": self.applied, "source": self.source,
                "falloff_ev": self.falloff_ev, "removed_ev": self.removed_ev, "confidence": self.confidence, "snr": self.snr,
                "fallback": self.fallback, "verdict": self.verdict, "lens": self.lens,
                "summary": self.summary, "seconds": self.seconds,
                "model": None if self.model is None else self.model.to_dict()}


def _finite(x: Any) -> float | None:
    x = float(x)
    return round(x, 4) if math.isfinite(x) else None


# ------------------------------------------------------------------ pipeline
class Pipeline:
    """Reusable, thread-safe vigproc settings for a photo pipeline.

    Parameters
    ----------
    mode : {"correct", "check", "estimate"}
        ``correct`` returns the image with the vignetting removed; ``check`` returns
        it unchanged with a forensic verdict (does the vignetting match the lens?);
        ``estimate`` returns it unchanged with the estimated model.
    profile : str
        ``auto`` (a trusted stored profile of the lens, else a profile-source plugin
        that has one, else estimate), ``estimate``, ``lensfun``, ``source:NAME`` or
        the path of a profile file.
    method : str
        Estimator (:data:`vigproc.core.estimate.METHODS` or an installed plugin).
    strength : float
        Fraction of the fall-off removed (correct mode).
    store : str or os.PathLike, optional
        Profile store file (:class:`vigproc.stores.profiles.ProfileStore`; its default
        location is :func:`vigproc.stores.profiles.default_db_path`).  None: no store.
    channel_axis : int or None
        Axis of colour channels of the images passed to :meth:`process`; None for
        2-D images.  Returned images keep the layout.

    Raises
    ------
    RequestError
        Unknown mode.
    VigprocError
        Other invalid settings (unknown method, strength out of [0, 2]...).

    Examples
    --------
    A frame of a white wall through a lens with a known fall-off (0.25 EV RMS);
    "flat-field" is the estimator for frames of no scene:

    >>> import numpy as np
    >>> import vigproc
    >>> lens = vigproc.VignettingModel(240, 160, p=(1 / 150**2, 0.0, 1 / 150**2))
    >>> rng = np.random.default_rng(0)
    >>> img = 0.5 * lens.field()[..., None] * (1 + 0.01 * rng.standard_normal((160, 240, 3)))
    >>> with vigproc.Pipeline("correct", profile="estimate", method="flat-field") as vp:
    ...     out, res = vp.process(img)
    >>> res.applied, res.source, round(res.falloff_ev, 2), round(res.removed_ev, 2)
    (True, 'estimate', 0.25, 0.25)
    >>> out.shape, out.dtype, bool(out.std() / out.mean() < 0.02)  # flat again, up to the noise
    ((160, 240, 3), dtype('float32'), True)

    ``check`` returns the image itself, with a verdict:

    >>> with vigproc.Pipeline("check", profile="estimate") as vp:
    ...     same, res = vp.process(img)
    >>> same is img, res.verdict["verdict"]  # no lens named: nothing to compare with
    (True, 'unknown-lens')
    >>> vigproc.Pipeline("sharpen")
    Traceback (most recent call last):
    ...
    vigproc.frontends.api.RequestError: unknown mode 'sharpen' (choose from correct, check, estimate)
    """

    def __init__(self, mode: str = "correct", *, profile: str = "auto", method: str = "default",
                 strength: float = 1.0, store: str | os.PathLike[str] | None = None,
                 channel_axis: int | None = -1) -> None:
        from vigproc.core.extensions import load_profile_sources
        from vigproc.pipeline.processor import Settings

        if mode not in MODES:
            raise RequestError(f"unknown mode {mode!r} (choose from {', '.join(MODES)})")
        self.settings = Settings(mode=mode, profile=str(profile), method=method, strength=float(strength))
        self.channel_axis = channel_axis
        self.store_path = None if store is None else os.path.expanduser(os.fspath(store))
        # loaded once: a call must not re-import plugins; read-only afterwards
        self._sources = load_profile_sources() if self.settings.profile == "auto" else {}
        self._local = threading.local()
        self._lock = threading.Lock()
        self._stores: list[Any] = []

    def _store(self):
        if self.store_path is None:
            return None
        st = getattr(self._local, "store", None)
        if st is None:
            st = open_profile_store(self.store_path, write=self.settings.mode == "learn")  # one connection per thread
            if st is None:
                return None
            self._local.store = st
            with self._lock:
                self._stores.append(st)
        return st

    def process(self, img: np.ndarray, lens: Any = None) -> tuple[np.ndarray, Result]:
        """Correct or check one linear image.

        Parameters
        ----------
        img : ndarray
            Linear intensities (scene-referred: RAW development or a linear
            decoding, not display sRGB), H×W or with channels on ``channel_axis``;
            any numeric dtype.  Never modified.
        lens : LensKey, mapping or None
            The lens's metadata (see :func:`lens_key`); None when unknown (stored
            profiles and ``check`` then cannot identify the lens).

        Returns
        -------
        image : ndarray
            correct: a new float32 array, same layout, vignetting divided out (the
            input's values if the evidence was too weak); check/estimate: ``img``
            itself.
        result : Result

        Raises
        ------
        VigprocError
            Invalid image (:class:`~vigproc.errors.InvalidImageError`), lens data
            (:class:`RequestError`), profile or plugin failures.
        """
        from vigproc.pipeline.processor import Processor

        key = lens_key(lens)
        a = check_image(img, self.channel_axis)  # channels last, validated
        work = np.ascontiguousarray(a, dtype=np.float32)  # one dtype/layout: no new JIT specialisation
        proc = Processor(self.settings, store=self._store(), sources=self._sources)
        out, res = proc.process_image(work, key, where="image")
        result = Result.from_frame(res)
        if out is None:
            return img, result
        return _layout_like(out, np.ndim(img), self.channel_axis), result

    def close(self) -> None:
        """Close the profile stores this pipeline opened (idempotent)."""
        with self._lock:
            stores, self._stores = self._stores, []
        for st in stores:
            st.close()  # a connection of another thread is left to the garbage collector

    def __enter__(self) -> Pipeline:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def _layout_like(out: np.ndarray, ndim: int, channel_axis: int | None) -> np.ndarray:
    """Put a channels-last result back into the caller's layout."""
    if ndim == 3 and out.ndim == 2:  # a single channel check_image squeezed away
        return np.expand_dims(out, channel_axis if channel_axis is not None else -1)
    if out.ndim == 3 and channel_axis is not None:
        return np.moveaxis(out, -1, channel_axis)
    return out


def process(img: np.ndarray, lens: Any = None, *, mode: str = "correct", profile: str = "auto",
            method: str = "default", strength: float = 1.0, store: str | os.PathLike[str] | None = None,
            channel_axis: int | None = -1) -> tuple[np.ndarray, Result]:
    """One-off :meth:`Pipeline.process` (same parameters; see :class:`Pipeline`).

    Returns
    -------
    (ndarray, Result)
    """
    with Pipeline(mode, profile=profile, method=method, strength=strength, store=store,
                  channel_axis=channel_axis) as p:
        return p.process(img, lens)
