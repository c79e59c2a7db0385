#!/usr/bin/env python
"""Write a full-size (default 6000×4000, 24 MP) Bayer DNG to time the RAW path on.

No licensed full-size RAW is at hand (``../shared/data/raw`` holds a 2.2 MP DNG and a
0.4 MP KDC), so this makes one with the test suite's DNG writer
(``tests/dngfixture.py``: an uncompressed 16-bit RGGB strip and the DNG colour tags
LibRaw needs, EXIF written by exiftool). The scene is a real camera JPEG's luminance,
linearised and up-sampled (bilinear) to the sensor size, times a lens-like fall-off
(cos⁴ law, about 0.9 EV at the corner) so the estimate has a field to find. Meant for
timing (``vigproc bench throughput --raw DIR``), not for accuracy: the up-sampled
scene has no detail finer than the JPEG's.

Usage::

    python scripts/make_full_size_dng.py OUT.dng [--jpeg FILE] [--width 6000 --height 4000]

References
----------
Adobe, *Digital Negative (DNG) Specification* 1.4 (CFA layout, BlackLevel, WhiteLevel).
"""

from __future__ import annotations

import argparse
import logging
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
DEFAULT_JPEG = ROOT.parent / "shared" / "data" / "jpeg_exif" / "exif-py" / "Sony_DSLR-A200.jpg"
log = logging.getLogger("make_full_size_dng")


def scene_from_jpeg(path: Path, height: int, width: int) -> np.ndarray:
    """The JPEG's linear luminance, up-sampled (bilinear) to ``height``×``width``,
    scaled into [0.01, 0.6] of the raw range (headroom for the white balance gains).

    Parameters
    ----------
    path : Path
        A camera JPEG (any size; turned to landscape when the sensor is).
    height, width : int
        Sensor size.

    Returns
    -------
    numpy.ndarray
        ``height``×``width`` float64.
    """
    from scipy.ndimage import zoom

    from vigproc.io.images import read_image
    from vigproc.io.protocol import rgb_of

    img, _ = read_image(path, transfer="auto")
    rgb = rgb_of(img)
    lum = rgb @ np.array([0.2126, 0.7152, 0.0722])
    if (lum.shape[0] > lum.shape[1]) != (height > width):
        lum = np.rot90(lum)
    up = zoom(lum.astype(np.float32), (height / lum.shape[0], width / lum.shape[1]), order=1, grid_mode=True,
              mode="nearest")[:height, :width]
    up = np.clip(up.astype(np.float64), 0.0, None)
    return 0.01 + 0.59 * up / max(float(up.max()), 1e-6)


def cos4_field(height: int, width: int, corner_ev: float = 0.9) -> np.ndarray:
    """A natural (cos⁴) fall-off of ``corner_ev`` EV at the corner."""
    y, x = np.mgrid[0:height, 0:width].astype(np.float64)
    r2 = ((x - (width - 1) / 2) ** 2 + (y - (height - 1) / 2) ** 2) / (((width - 1) / 2) ** 2 + ((height - 1) / 2) ** 2)
    # cos⁴θ with tan²θ = a r²: choose a so that the corner (r = 1) is 2^-corner_ev
    a = 2.0 ** (corner_ev / 2.0) - 1.0
    return 1.0 / (1.0 + a * r2) ** 2


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("out", type=Path)
    ap.add_argument("--jpeg", type=Path, default=DEFAULT_JPEG)
    ap.add_argument("--width", type=int, default=6000)
    ap.add_argument("--height", type=int, default=4000)
    ap.add_argument("--corner-ev", type=float, default=0.9)
    a = ap.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    sys.path.insert(0, str(ROOT / "tests"))
    from dngfixture import DEFAULT_EXIF, make_dng

    scene = scene_from_jpeg(a.jpeg, a.height, a.width)
    field = cos4_field(a.height, a.width, a.corner_ev)
    exif = dict(DEFAULT_EXIF, Model="Synthetic DNG 24MP")
    a.out.parent.mkdir(parents=True, exist_ok=True)
    make_dng(a.out, width=a.width, height=a.height, scene=scene, field=field, exif=exif, noise=0.002, seed=1)
    log.info("%s: %d×%d, %.1f MB", a.out, a.width, a.height, a.out.stat().st_size / 1e6)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
