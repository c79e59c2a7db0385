"""vigproc: lens vignetting estimation, correction, per-lens profiles and forensics.

>>> import vigproc
>>> m = vigproc.estimate(img)            # img: H×W or H×W×C linear float
>>> phi = m.field((H, W))                # attenuation, 1.0 at the vignetting centre
>>> out = vigproc.correct(img, m)

Photo pipelines: :class:`vigproc.Pipeline` (:mod:`vigproc.api`, the stable interface).
"""

from vigproc.api import Pipeline, Result
from vigproc.correct import correct
from vigproc.errors import (
    ImageReadError,
    ImageWriteError,
    InvalidImageError,
    ModelError,
    PriorError,
    UnsupportedFormatError,
    VigprocError,
)
from vigproc.estimate import METHODS, estimate
from vigproc.model import FitQuality, VignettingModel
from vigproc.robust import RobustSettings

__version__ = "0.1.0"

__all__ = [
    "METHODS", "FitQuality", "ImageReadError", "ImageWriteError", "InvalidImageError",
    "ModelError", "Pipeline", "PriorError", "Result", "RobustSettings", "UnsupportedFormatError",
    "VignettingModel", "VigprocError", "correct", "estimate",
]
