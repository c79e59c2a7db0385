"""A picture of an estimated vignetting function, for people who would rather look."""

from __future__ import annotations

import math

import numpy as np

from vigproc.model import VignettingModel

#: Iso-attenuation contours drawn, in EV below the centre.
CONTOUR_EV = (0.25, 0.5, 1.0, 2.0, 3.0, 4.0)


def vignetting_picture(model: VignettingModel, long_side: int = 480) -> np.ndarray:
    """Render φ as an RGB float image in [0, 1] (to be stored sRGB-encoded).

    Gray level is the attenuation φ itself (white = no fall-off); coloured lines are
    the iso-attenuation contours at :data:`CONTOUR_EV` EV, a red cross marks the
    vignetting centre when it lies inside the frame.
    """
    s = long_side / max(model.width, model.height)
    h, w = max(2, round(model.height * s)), max(2, round(model.width * s))
    lf = model.log_field((h, w)) / math.log(2.0)
    rgb = np.repeat(np.exp2(lf)[..., None], 3, axis=2)
    colours = np.array([[0.2, 0.8, 1.0], [0.2, 1.0, 0.4], [1.0, 0.9, 0.2], [1.0, 0.5, 0.1], [1.0, 0.2, 0.6], [0.7, 0.3, 1.0]])
    for ev, col in zip(CONTOUR_EV, colours):
        below = lf < -ev
        edge = np.zeros_like(below)
        edge[:, 1:] |= below[:, 1:] != below[:, :-1]
        edge[1:, :] |= below[1:, :] != below[:-1, :]
        rgb[edge] = col
    m = model.rescale(w, h) if not model.is_identity else model
    cx = m.center[0] + (w - 1) / 2
    cy = m.center[1] + (h - 1) / 2
    if 0 <= cx < w and 0 <= cy < h:
        x, y = int(round(cx)), int(round(cy))
        arm = max(3, w // 40)
        rgb[max(0, y - 1) : y + 2, max(0, x - arm) : x + arm + 1] = (1.0, 0.0, 0.0)
        rgb[max(0, y - arm) : y + arm + 1, max(0, x - 1) : x + 2] = (1.0, 0.0, 0.0)
    return rgb.astype(np.float32)
