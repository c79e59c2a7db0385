"""A frame's colour-cast evidence as the pipeline reads it: the report ``vigproc
estimate`` prints and the record a learned frame adds to its profile's cast
(:mod:`vigproc.stores.cast_store`)."""

from __future__ import annotations

import logging

import numpy as np

from vigproc.core.cast_series import frame_record
from vigproc.core.colour_cast import CastSettings, ColourCastEvidence, detect_colour_cast
from vigproc.errors import VigprocError
from vigproc.io.images import EncodedImage

log = logging.getLogger(__name__)


def frame_cast(img, model=None) -> ColourCastEvidence | None:
    """:func:`~vigproc.core.colour_cast.detect_colour_cast` on a frame as read (None for a
    grey frame).

    Parameters
    ----------
    img : numpy.ndarray or EncodedImage
        The frame; a JPEG's or PNG's codes are read from a copy binned from its codes.
    model : VignettingModel, optional
        The frame's luminance estimate (its optical centre is the cast's centre).

    Returns
    -------
    ColourCastEvidence or None
    """
    if img.ndim != 3 or img.shape[2] < 3:
        return None
    usable, settings = None, CastSettings()
    if isinstance(img, EncodedImage):
        long_side = max(img.shape[:2])
        if img.codes.dtype == np.uint8:
            # 8-bit codes quantise the chroma of dark pixels, which pulls the fit towards no
            # cast: each working pixel averages at least 5x5 of them
            settings = CastSettings(work_long_side=int(max(48, min(settings.work_long_side, long_side / 5))))
        img, usable = img.reduced(max(1, long_side // 480))
    return detect_colour_cast(img, luminance_model=model, usable=usable, settings=settings)


def frame_cast_record(img, model=None) -> dict | None:
    """What a learned frame adds to its profile's colour cast
    (:func:`vigproc.core.cast_series.frame_record`); None when the frame cannot be judged
    (grey, too little usable colour): learning goes on without it."""
    try:
        ev = frame_cast(img, model)
    except (VigprocError, ValueError) as exc:
        log.debug("no colour-cast record: %s", exc)
        return None
    return None if ev is None else frame_record(ev)
