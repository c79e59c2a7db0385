"""A flat frame's measured grid field, for its lens's profile.

``--method flat-field`` in learn mode pools, beside the frame's Kang-Weiss estimate and
colour field, its grid field (:func:`vigproc.core.gridfield.flat_grid`): ln φ_c per channel
on 33 nodes along the long side, the wall's planar gradient removed about the optical
centre the estimate found (the tint's centre, else the fall-off's). The profile pools the
frames' grids node by node (:mod:`vigproc.stores.profile_grid`) and corrects by them.

The frame is first averaged down to at most :data:`WORK_SIDE` px on its long side (in
bands of rows: one float64 copy of a camera frame would be half a gigabyte); the grid
averages blocks of about 1/64 of the long side anyway, so nothing it uses is lost.
A RAW's flat frame is measured on its CFA planes (:func:`vigproc.pipeline.cfa_flat.cfa_flat_field`
with ``with_grid``), its grid in relative coordinates like the developed frame's.

References
----------
Adobe, *Digital Negative (DNG) Specification* 1.4.0.0, "GainMap".
"""

from __future__ import annotations

import logging
import math

import numpy as np

from vigproc.core.gridfield import GridField, flat_grid
from vigproc.core.model import VignettingModel
from vigproc.errors import InvalidImageError

log = logging.getLogger(__name__)

#: The method whose frames give a grid field.
METHOD = "flat-field"
#: Long side of the averaged copy the grid is measured on (px).
WORK_SIDE = 512


def _binned(img: np.ndarray, k: int) -> np.ndarray:
    """``img`` (H×W×C) averaged over k×k blocks (float64), in bands of rows."""
    h, w = img.shape[0] // k, img.shape[1] // k
    out = np.empty((h, w, 3))
    band = max(1, 256 // k)
    for r in range(0, h, band):
        r1 = min(h, r + band)
        blk = np.asarray(img[r * k:r1 * k, :w * k, :3], dtype=np.float64)
        out[r:r1] = blk.reshape(r1 - r, k, w, k, 3).mean(axis=(1, 3))
    return out


def frame_grid(img: np.ndarray, model: VignettingModel, *, source: str = "flat-field:grid") -> GridField | None:
    """The grid field of one flat frame, for the frame's full size.

    Parameters
    ----------
    img : ndarray
        H×W or H×W×C linear flat frame (channels last; a grey frame's grid has its one
        field in every channel).
    model : VignettingModel
        Its flat-field estimate (any resolution of the frame): the optical centre is the
        colour field's where it has one, else the luminance model's.

    Returns
    -------
    GridField or None
        None for a frame too small for a grid (logged).
    """
    a = np.asarray(img)
    if a.ndim == 2:
        a = a[..., None]
    if a.ndim != 3 or a.shape[2] < 1:
        return None
    h, w = a.shape[:2]
    if a.shape[2] < 3:  # a grey frame (or grey and alpha): one field, the same in every channel
        a = np.broadcast_to(a[..., :1], (h, w, 3))
    k = max(1, math.ceil(max(h, w) / WORK_SIDE))
    small = _binned(a, k) if k > 1 else np.asarray(a[..., :3], dtype=np.float64)
    sh, sw = small.shape[:2]
    m = model.rescale(w, h) if (model.width, model.height) != (w, h) else model
    cx, cy = m.colour.center if m.colour is not None else m.center
    # the binned copy covers the frame's first sw·k × sh·k px: its centre in its own px
    ox, oy = (w - sw * k) / 2.0, (h - sh * k) / 2.0
    try:
        g = flat_grid([small], [((cx + ox) / k, (cy + oy) / k)], source=source)
    except InvalidImageError as exc:
        log.info("no grid field from this flat frame: %s", exc)
        return None
    return GridField(w, h, g.log_field, g.sigma, g.source)
