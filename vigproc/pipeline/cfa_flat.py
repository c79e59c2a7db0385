"""A RAW flat frame measured per CFA plane, before demosaicing.

A flat frame's colour shading is the sensor's: each colour plane of the mosaic is
attenuated by its own field. LibRaw's development mixes the planes (white balance, the
camera-to-sRGB matrix, demosaicing), so ``--method flat-field`` on a RAW measures the
planes themselves (:func:`vigproc.io.images.read_cfa_planes`: black-subtracted, the two
greens averaged, one pixel per 2×2 cell), and the model found there (luminance fall-off
and per-plane colour field, :func:`vigproc.core.estimate.estimate`) is scaled to the
developed frame, which LibRaw leaves in sensor order. In learn mode the planes' grid field
goes with it (``with_grid``).

References
----------
Adobe, *Digital Negative (DNG) Specification* 1.4.0.0, "GainMap" (per-plane gains, the
form a per-plane field takes in a DNG).
"""

from __future__ import annotations

import logging
import os
from dataclasses import fields, replace

from vigproc.core.gridfield import GridField, GridFieldModel
from vigproc.core.model import VignettingModel
from vigproc.errors import InvalidImageError, ModelError
from vigproc.pipeline.flat_grid import frame_grid

log = logging.getLogger(__name__)

#: The method whose RAW frames are measured per CFA plane.
METHOD = "flat-field"


def cfa_flat_field(path: str | os.PathLike[str], width: int, height: int, *,
                   with_grid: bool = False) -> VignettingModel | None:
    """The flat-field estimate of a Bayer RAW measured on its CFA planes, for its
    developed ``width``×``height`` frame.

    Parameters
    ----------
    path : str or os.PathLike
        The RAW (read again for its mosaic; the file is not modified).
    width, height : int
        The developed frame's size (LibRaw's, sensor order).
    with_grid : bool
        Also measure the planes' grid field (:func:`vigproc.pipeline.flat_grid.frame_grid`,
        for the developed frame's size): the model is then a
        :class:`vigproc.core.gridfield.GridFieldModel` (learn mode: the profile keeps it).

    Returns
    -------
    VignettingModel or None
        The model (``colour.source`` "flat-field:cfa" when a tint was measured); None
        when the file has no Bayer mosaic (X-Trans, four colours, a linear DNG) or its
        planes do not scale to the developed frame: the developed frame is estimated
        instead (logged).

    Raises
    ------
    InvalidImageError
        The planes are no image to estimate (constant, too small, no positive pixel).
    ImageReadError
        The RAW cannot be read.
    """
    from vigproc.core.estimate import estimate
    from vigproc.io.images import read_cfa_planes

    try:
        planes = read_cfa_planes(path)
    except InvalidImageError as exc:  # no 2×2 Bayer mosaic: the developed channels it is
        log.info("%s: flat field measured on the developed frame: %s", os.fspath(path), exc)
        return None
    m = estimate(planes, METHOD)
    try:
        out = m.rescale(width, height)
    except ModelError as exc:
        log.info("%s: flat field measured on the developed frame: the CFA planes (%dx%d) are not a resolution of "
                 "it (%s)", os.fspath(path), planes.shape[1], planes.shape[0], exc)
        return None
    if out.colour is not None:  # the record says the tint is the planes'
        cf = replace(out.colour, source="flat-field:cfa")
        cand = replace(out.candidate, colour=cf) if out.candidate is not None else None
        out = replace(out, colour=cf, candidate=cand)
    if with_grid:

        g = frame_grid(planes, m.candidate if m.candidate is not None else m, source="flat-field:cfa-grid")
        if g is not None:  # the planes' grid is the developed frame's, in relative coordinates
            kw = {f.name: getattr(out, f.name) for f in fields(VignettingModel)}
            out = GridFieldModel(**kw, grid=GridField(width, height, g.log_field, g.sigma, g.source))
    return out
