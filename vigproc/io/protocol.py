"""The frames of Lyu 2010's experimental protocol (Section 4.1): 480×320 gray.

Photographs are centre-cropped to 3:2 (portrait frames turned to landscape first) and
resized to 480×320 by area; their luminance is kept as stored, scaled to [0, 1]. The
benchmarks (:mod:`benchmarks.synthetic`) and the commands that fit priors and
calibrations on folders of photographs read frames this way.

References
----------
S. Lyu, "Estimating Vignetting Function from a Single Image for Image
Authentication", ACM MM&Sec 2010, Section 4.1.
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Iterable

import numpy as np

from vigproc.core.pixels import luminance
from vigproc.core.resample import resize_area
from vigproc.errors import VigprocError

log = logging.getLogger(__name__)

#: The protocol frame (landscape).
WIDTH, HEIGHT = 480, 320


def protocol_image(img: np.ndarray, colour: bool = False) -> np.ndarray:
    """Centre-crop to 3:2 landscape and resize to 480×320 (area filter); gray float64,
    or with ``colour`` 480×320×3 (R, G, B; a grey file in each channel).

    ``img`` holds stored values scaled to [0, 1] (not linearised: the paper's
    protocol takes them as linear), H×W or H×W×C.
    """
    a = np.asarray(img, dtype=np.float64)
    if colour:
        rgb = rgb_of(a)
        return np.stack([protocol_image(rgb[..., c]) for c in range(3)], axis=-1)
    g = luminance(a)
    if g.shape[0] > g.shape[1]:
        g = np.rot90(g)
    h, w = g.shape
    if w * 2 > h * 3:  # too wide: crop width
        nw = int(round(h * 1.5))
        x0 = (w - nw) // 2
        g = g[:, x0 : x0 + nw]
    else:
        nh = int(round(w / 1.5))
        y0 = (h - nh) // 2
        g = g[y0 : y0 + nh, :]
    return resize_area(g, HEIGHT, WIDTH)


def rgb_of(img: np.ndarray) -> np.ndarray:
    """The R, G, B of an H×W or H×W×C frame: its first three channels, or its luminance
    in each of three (a grey file)."""
    a = np.asarray(img)
    return a[..., :3] if a.ndim == 3 and a.shape[-1] >= 3 else np.repeat(luminance(a)[..., None], 3, axis=-1)


def vignetted(im: np.ndarray, log_field: np.ndarray) -> np.ndarray:
    """A frame (H×W, or H×W×C with channels last) through a field (H×W, natural log):
    every channel divided alike, as a lens does."""
    gain = np.exp(log_field)
    return im * (gain[..., None] if im.ndim == 3 else gain)


def read_protocol_images(files: Iterable[Path], transfer: str = "linear", colour: bool = False) -> list[np.ndarray]:
    """:func:`protocol_image` of each readable file (decoded with ``transfer``); a file
    that cannot be read is skipped with a warning."""
    from vigproc.io.images import read_image

    ims = []
    for f in files:
        try:
            ims.append(protocol_image(read_image(f, transfer=transfer)[0], colour))
        except VigprocError as exc:
            log.warning("skipping %s", exc)
    return ims
