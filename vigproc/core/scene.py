"""The fall-off that photographs carry themselves: the scene prior of the default estimator.

Natural photographs are, on average, darker towards their borders even without any
lens vignetting: subjects are framed in the middle, skies and floors fill the edges,
and many were taken through lenses that vignette.  Measured on the 200 BSDS training
photos (480×320, linearised): their mean log image falls by ≈ 0.5 EV towards the left
and right borders, and a per-pixel fit of the vignetting model to a single
"vignetting-free" photo finds a field of 0.44 EV RMS in the median, most of it common
to all photos (the mean field alone is 0.48 EV RMS; frames scatter around it by
0.29 EV).  An estimator that takes every photo as flat on average charges that common
fall-off to the lens.

The scene prior is that common part, E[log φ_scene] over natural photos, stored as a
Kang-Weiss model in frame-normalised units (coordinates in half-diagonals, see
:func:`vigproc.stores.profiles.normalise`).  The default estimator divides it out of the
working image before fitting, so what it fits is the lens: φ_lens = φ̂ / φ_scene.

It is fitted by :func:`fit_scene_falloff` (``vigproc prior fit-scene FOLDER``) as a
fixed point: estimate every photo with the current prior, add the mean of the
estimated fields to the prior, refit the model to it, repeat.

References
----------
Y. Zheng, S. Lin, S. B. Kang, R. Xiao, J. Gee, C. Kambhamettu, "Single-image
vignetting correction from gradient distribution symmetries", IEEE TPAMI 35(6), 2013
(the symmetry of radial gradients is the same assumption, and the same bias).
"""

from __future__ import annotations

import functools
import json
import logging
import math
from dataclasses import dataclass
from importlib import resources
from typing import Any, Callable, Sequence

import numpy as np

from vigproc.core.model import frame_coords
from vigproc.core.normalised import denormalise, fit_model_to_field, normalise
from vigproc.errors import ModelError, PriorError

log = logging.getLogger(__name__)

SCHEMA = "vigproc.scene/1"
SHIPPED = "scene_falloff.json"
N_PARAMS = 12


@dataclass(frozen=True)
class SceneFalloff:
    """Mean log fall-off of natural photographs, as normalised Kang-Weiss parameters.

    Attributes
    ----------
    theta : tuple of 12 floats
        (c̃x, c̃y, p̃1, p̃2, p̃3, α1..α7) in half-diagonal units.
    n_images : int
        Photos it was fitted on.
    field_ev_rms : float
        RMS of its log2 field over a 3:2 frame.
    scatter_ev : float
        Median RMS (EV) of the single-photo fields around it, after fitting.
    source : str
        The command that produced it.
    """

    theta: tuple[float, ...]
    n_images: int = 0
    field_ev_rms: float = 0.0
    scatter_ev: float = 0.0
    source: str = ""

    def __post_init__(self) -> None:
        th = np.asarray(self.theta, dtype=np.float64)
        if th.shape != (N_PARAMS,) or not np.all(np.isfinite(th)):
            raise PriorError(f"a scene fall-off needs {N_PARAMS} finite parameters")

    def log_field(self, xs: np.ndarray, ys: np.ndarray) -> np.ndarray:
        """log φ_scene (natural log) on the grid of normalised coordinates ``xs`` × ``ys``."""
        from vigproc.core._kernels.field import log_field_grid

        th = np.asarray(self.theta, dtype=np.float64)
        out = np.empty((len(ys), len(xs)), dtype=np.float64)
        log_field_grid(np.ascontiguousarray(xs, dtype=np.float64), np.ascontiguousarray(ys, dtype=np.float64),
                       th[0], th[1], th[2], th[3], th[4], th[5:], out)
        return out

    def model(self, width: int, height: int):
        """The scene fall-off as a :class:`~vigproc.core.model.VignettingModel` of a frame."""
        return denormalise(np.asarray(self.theta), None, width, height, method="scene")

    def to_dict(self) -> dict[str, Any]:
        return {"schema": SCHEMA, "theta": list(self.theta), "n_images": self.n_images,
                "field_ev_rms": self.field_ev_rms, "scatter_ev": self.scatter_ev, "source": self.source}

    @classmethod
    def from_dict(cls, d: Any) -> SceneFalloff:
        if not isinstance(d, dict) or d.get("schema") != SCHEMA:
            raise PriorError(f"not a scene fall-off (schema {SCHEMA!r} expected)")
        try:
            return cls(theta=tuple(float(v) for v in d["theta"]), n_images=int(d.get("n_images", 0)),
                       field_ev_rms=float(d.get("field_ev_rms", 0.0)), scatter_ev=float(d.get("scatter_ev", 0.0)),
                       source=str(d.get("source", "")))
        except (KeyError, TypeError, ValueError) as exc:
            raise PriorError(f"bad scene fall-off: {exc}") from exc


NONE = SceneFalloff(theta=(0.0,) * N_PARAMS, source="none")


@functools.lru_cache(maxsize=4)
def shipped_falloff(name: str) -> SceneFalloff:
    """A mean fall-off shipped as package data (``vigproc/data/NAME``), read once;
    none (with a warning) when the file is missing."""
    try:
        text = resources.files("vigproc.data").joinpath(name).read_text()
    except FileNotFoundError:
        log.warning("the shipped fall-off %s is missing; working without it", name)
        return NONE
    return SceneFalloff.from_dict(json.loads(text))


def default_scene_falloff() -> SceneFalloff:
    """The scene prior shipped with vigproc (package data, read once)."""
    return shipped_falloff(SHIPPED)


def frame_grid(aspect: float, n: int = 48) -> tuple[np.ndarray, np.ndarray, int, int]:
    """Pixel-centre coordinates (half-diagonals) of an n-wide frame of aspect W/H:
    (xs, ys, width, height) of the small grid mean fall-offs are fitted and pooled on."""
    w, h = n, max(4, int(round(n / aspect)))
    r = 0.5 * math.hypot(w, h)
    return frame_coords(w) / r, frame_coords(h) / r, w, h


def fit_scene_falloff(
    images: Sequence[np.ndarray],
    estimate_with: Callable[[np.ndarray, SceneFalloff], Any],
    *,
    iterations: int = 3,
    source: str = "",
) -> SceneFalloff:
    """Fit the scene prior to vignetting-free photographs (fixed point, see module doc).

    Parameters
    ----------
    images : sequence of H×W linear luminance arrays, all of one aspect ratio
    estimate_with : callable (image, SceneFalloff) -> VignettingModel
        The estimator, run with a given scene prior (its candidate fit is used when
        it falls back).
    iterations : int
    source : str
        Recorded provenance (the command line).

    Returns
    -------
    SceneFalloff
    """
    if len(images) < 10:
        raise PriorError(f"fit the scene fall-off on at least 10 photos, got {len(images)}")
    h0, w0 = images[0].shape[:2]
    aspect = w0 / h0
    xs, ys, gw, gh = frame_grid(aspect)
    prior = NONE
    scatter = float("nan")
    for it in range(iterations):
        fields = []
        for im in images:
            if abs(math.log((im.shape[1] / im.shape[0]) / aspect)) > 0.02:
                raise PriorError("fit the scene fall-off on photos of one aspect ratio")
            m = estimate_with(im, prior)
            fit = m.candidate if m.candidate is not None else m
            fields.append(fit.log_field((gh, gw)))
        F = np.asarray(fields)
        mean = F.mean(axis=0)
        scatter = float(np.median(np.sqrt(np.mean((F - mean) ** 2, axis=(1, 2)))) / math.log(2))
        target = prior.log_field(xs, ys) + mean
        try:
            fitted, rms_ev = fit_model_to_field(target, gw, gh)
        except ModelError as exc:
            raise PriorError(f"could not fit the scene fall-off: {exc}") from exc
        theta, _, _ = normalise(fitted)
        prior = SceneFalloff(theta=tuple(float(v) for v in theta), n_images=len(images),
                             field_ev_rms=float(np.sqrt(np.mean(target**2)) / math.log(2)),
                             scatter_ev=scatter, source=source)
        log.info("scene fall-off iteration %d: mean residual field %.3f EV RMS, prior %.3f EV RMS "
                 "(model fit residual %.4f EV)", it + 1, float(np.sqrt(np.mean(mean**2)) / math.log(2)),
                 prior.field_ev_rms, rms_ev)
    return prior
