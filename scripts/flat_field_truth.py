"""Is lensfun's field the truth of a frame? Read it off flat-field frames (issue 38, part a).

A flat-field frame (a plain, evenly lit surface filling the frame) is the lens's fall-off
times the surface's own unevenness: read as ``vigproc`` reads any JPEG
(:func:`vigproc.io.read_image`, the sRGB transfer), its log luminance, box-averaged onto
the bench's grid, is a direct measurement of the field ``bench real-frames`` part (a)
takes from lensfun. Per frame whose lens lensfun calibrated
(:func:`benchmarks.real_frames_lensfun.lensfun_frames`): lensfun's corner fall-off, the
frame's own (the mean over r ≥ 0.95 of the half-diagonal against r ≤ 0.1, EV), the RMS
of their difference over the frame about its mean (``bench clean``'s metric), and the frame's
left eighth against its right and its top eighth against its bottom (EV; a centred lens
field gives 0: lighting that falls across the surface does not).

    NUMBA_NUM_THREADS=1 python scripts/flat_field_truth.py DIR_OR_FILES...
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from benchmarks.real_frames_lensfun import _ev, grid_shape, lensfun_frames  # noqa: E402


def frame_log_field(path: Path) -> np.ndarray:
    """log (natural) of the frame's linear luminance, box-averaged onto the bench's grid."""
    from vigproc.io import read_image

    img, _info = read_image(path)
    lum = img[..., :3] @ np.array([0.2126, 0.7152, 0.0722], dtype=np.float32) if img.ndim == 3 else img
    h, w = lum.shape
    gh, gw = grid_shape(w, h)
    rows = np.linspace(0, h, gh + 1).astype(int)
    cols = np.linspace(0, w, gw + 1).astype(int)
    sums = np.add.reduceat(np.add.reduceat(lum.astype(np.float64), rows[:-1], axis=0), cols[:-1], axis=1)
    return np.log(sums / np.outer(np.diff(rows), np.diff(cols)))


def corner_ev(log_field: np.ndarray) -> float:
    """Centre minus corner (r ≥ 0.95 of the half-diagonal against r ≤ 0.1), EV."""
    h, w = log_field.shape
    y, x = np.mgrid[0:h, 0:w]
    r = np.hypot((y + 0.5 - h / 2) / (h / 2), (x + 0.5 - w / 2) / (w / 2)) / np.sqrt(2)
    return float((log_field[r <= 0.1].mean() - log_field[r >= 0.95].mean()) / np.log(2))


def sides_ev(log_field: np.ndarray) -> tuple[float, float]:
    """(left − right, top − bottom): mean log2 of the outer eighths, EV."""
    h, w = log_field.shape
    lr = log_field[:, : w // 8].mean() - log_field[:, -(w // 8):].mean()
    tb = log_field[: h // 8].mean() - log_field[-(h // 8):].mean()
    return float(lr / np.log(2)), float(tb / np.log(2))


def main(argv: list[str]) -> int:
    files = sorted(p for a in argv for p in (Path(a).iterdir() if Path(a).is_dir() else [Path(a)])
                   if p.suffix.lower() in (".jpg", ".jpeg"))
    found, _other = lensfun_frames(files)
    print(f"{'file':34} {'lens':28} {'mm':>5} {'f/':>5} {'rho':>5} {'lensfun':>8} {'frame':>6} {'RMS diff':>8} {'L-R':>6} {'T-B':>6}")
    for path, _key, truth, _tags, _ic in found:
        own = frame_log_field(path)
        true = truth.log_field(own.shape)
        print(f"{path.name[:34]:34} {truth.lens[:28]:28} {truth.focal_mm:5.0f} {truth.fnumber:5.1f} "
              f"{truth.corner_rho:5.2f} {truth.corner_ev:8.2f} {corner_ev(own):6.2f} {_ev(own - true):8.3f} "
              f"{sides_ev(own)[0]:+6.2f} {sides_ev(own)[1]:+6.2f}")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
