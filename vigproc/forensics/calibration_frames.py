"""The frames ``vigproc forensics calibrate`` fits the check's calibration on: lensfun
lens classes, and the feature residuals of photographs vignetted by them.

* **Lens classes** (:func:`lens_classes`): the first ``n_lenses`` lenses of
  :func:`vigproc.stores.lensfun.diverse_lenses` that have two calibrated apertures at
  their shortest focal length at least one stop apart with different fall-off (corner
  attenuation differing by >= 0.05; some compact-camera entries repeat one calibration
  for every aperture, and such "classes" could not be told apart by anything): the widest
  aperture and the calibrated one nearest two stops down. Each (lens, aperture) is a
  class, as the rows of Lyu 2010's Fig. 6 are.
* **Residuals** (:func:`calibration_residuals`): each photograph multiplied by the
  fields of a few classes, estimated, and its forensic features less those of the
  class's true field: the image bias and spread
  :func:`vigproc.forensics.check.fit_calibration` models.

The forensics benchmark (``benchmarks/forensics.py``) measures the check on the same
classes.

References
----------
Lyu, S. (2010). Estimating vignetting function from a single image for image
authentication. ACM MM&Sec, Section 4.3 and Fig. 6.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Callable, Sequence

import numpy as np

from vigproc.core.model import VignettingModel
from vigproc.errors import ModelError
from vigproc.forensics.check import frame_features, is_weak
from vigproc.stores.lensfun import diverse_lenses, interpolate_pa, pa_field
from vigproc.stores.lensfun_io import kw_from_pa

__all__ = ["LensClass", "calibration_residuals", "lens_classes"]


@dataclass(frozen=True)
class LensClass:
    """One (lens, aperture) class with its lensfun "pa" coefficients."""

    maker: str
    model: str
    focal: float
    aperture: float
    k1: float
    k2: float
    k3: float

    @property
    def lens(self) -> str:
        return f"{self.maker} {self.model}"

    @property
    def label(self) -> str:
        return f"{self.lens} f/{self.aperture:g}"

    def field(self, height: int, width: int) -> np.ndarray:
        return pa_field((height, width), self.k1, self.k2, self.k3)

    def true_model(self, width: int, height: int) -> VignettingModel:
        """The lensfun model a check of this lens compares with (:func:`kw_from_pa`)."""
        return kw_from_pa(self.k1, self.k2, self.k3, width, height)


def lens_classes(n_lenses: int = 8, *, min_corner_change: float = 0.05) -> list[LensClass]:
    """``2 * n_lenses`` classes: two apertures of each of ``n_lenses`` lensfun lenses
    (see the module docstring).

    Parameters
    ----------
    n_lenses : int
        Lenses taken, in :func:`~vigproc.stores.lensfun.diverse_lenses`' order.
    min_corner_change : float
        Smallest difference of corner attenuation (linear, 0-1) between a lens's two
        apertures.

    Returns
    -------
    list of LensClass
        The wide and the stopped-down class of each lens, in that order.

    Raises
    ------
    ModelError
        If the database has too few suitable lenses.
    """
    out: list[LensClass] = []
    for lens, _ in diverse_lenses(200):
        focal = lens.focal_range[0]
        apertures = sorted({v.aperture for v in lens.vignetting if v.focal == focal})
        wide = apertures[0]
        stopped = [a for a in apertures if a >= wide * math.sqrt(2) * 0.99]
        if not stopped:
            continue
        second = min(stopped, key=lambda a: (abs(math.log(a / (2.0 * wide))), a))
        pa1, pa2 = interpolate_pa(lens, focal, wide), interpolate_pa(lens, focal, second)
        if abs(pa1.corner - pa2.corner) < min_corner_change:
            continue
        for a, pa in ((wide, pa1), (second, pa2)):
            out.append(LensClass(lens.maker, lens.model, focal, a, pa.k1, pa.k2, pa.k3))
        if len(out) >= 2 * n_lenses:
            return out
    raise ModelError(f"only {len(out) // 2} lensfun lenses have two distinct calibrated apertures, {n_lenses} asked")


def calibration_residuals(
    images: Sequence[np.ndarray], estimate: Callable[[np.ndarray], VignettingModel], classes: Sequence[LensClass],
    *, per_image: int = 4, progress: Callable[[str], None] | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Feature residuals f(estimate) − f(true field) of photographs × lens fields, for
    :func:`vigproc.forensics.check.fit_calibration`: photograph i gets ``per_image`` classes
    (cycling through ``classes``).

    Parameters
    ----------
    images : sequence of ndarray (H, W)
        Vignetting-free photographs, linear luminance.
    estimate : callable
        Frame -> :class:`~vigproc.core.model.VignettingModel` (its ``candidate``, when
        set, is the fit the features are read from).
    classes : sequence of LensClass
    per_image : int
        Lens fields each photograph is multiplied by.
    progress : callable, optional
        Told every 25 photographs.

    Returns
    -------
    residuals : ndarray (N, 6)
    groups : ndarray (N,)
        The photograph of each frame.
    weak : ndarray of bool (N,)
        Whether the frame's estimate was too weak for a verdict.
    """
    res, groups, weak = [], [], []
    truth: dict[tuple[int, int, int], np.ndarray] = {}
    for i, im in enumerate(images):
        h, w = im.shape
        for j in range(per_image):
            ci = (i * per_image + j) % len(classes)
            c = classes[ci]
            m = estimate(im * c.field(h, w))
            fit = m.candidate if m.candidate is not None else m
            key = (ci, w, h)
            if key not in truth:
                truth[key] = frame_features(c.true_model(w, h))
            res.append(frame_features(fit) - truth[key])
            groups.append(i)
            weak.append(is_weak(m))
        if progress is not None and (i + 1) % 25 == 0:
            progress(f"  {i + 1}/{len(images)} photographs")
    return np.array(res), np.array(groups), np.array(weak, dtype=bool)
