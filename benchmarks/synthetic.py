"""The synthetic protocol of Lyu 2010, Section 4.1 (Tables 1–3).

Images are centre-cropped to 3:2 (portrait frames turned to landscape first),
resized to 480×320, their luminance (stored values / max code) taken as linear in
[0, 1], and vignetted with the three Table 1 settings and α = (0.02, 0.01, 0, …).
Each method's estimate restores the image; we report PSNR after the best scalar
gain, r_P, r_c, r_α and seconds per image, as in Tables 2–3. PSNR is of the model
the estimator returns (the identity when it falls back); r_P, r_c, r_α are of its
fit (``candidate`` when it fell back).
"""

from __future__ import annotations

import json
import math
import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Callable, Iterable, Sequence

import numpy as np

from vigproc.core.model import VignettingModel
from vigproc.io.protocol import HEIGHT, WIDTH, protocol_image, read_protocol_images, vignetted  # noqa: F401  (re-exported)

TABLE1_ALPHA = (0.02, 0.01, 0.0, 0.0, 0.0, 0.0, 0.0)
#: Lyu 2010, Table 1: (centre (cx, cy) px from the image centre, P in px⁻²).
TABLE1 = {
    1: ((0.0, 0.0), (1e-4, 0.0, 1e-4)),
    2: ((-80.0, -60.0), (1e-4, 0.5e-4, 1.5e-4)),
    3: ((0.0, -130.0), (1e-4, 0.6e-4, 1e-4)),
}


def table1_model(setting: int) -> VignettingModel:
    """The ground-truth model of a Table 1 setting for a 480×320 frame."""
    c, p = TABLE1[setting]
    return VignettingModel(WIDTH, HEIGHT, center=c, p=p, alpha=TABLE1_ALPHA, method="table1")


def psnr_best_gain(restored: np.ndarray, original: np.ndarray) -> float:
    """PSNR (peak 1) of ``restored`` against ``original`` after the best scalar gain."""
    r = restored.ravel()
    o = original.ravel()
    g = float(r @ o) / max(float(r @ r), 1e-300)
    mse = float(np.mean((g * r - o) ** 2))
    return 10.0 * math.log10(1.0 / max(mse, 1e-20))


def relative_errors(est: VignettingModel, truth: VignettingModel) -> tuple[float, float, float]:
    """r_P, r_c, r_α of Lyu 2010, Section 4.1 (as fractions)."""
    rp = np.linalg.norm(est.shape_matrix - truth.shape_matrix) / np.linalg.norm(truth.shape_matrix)
    tc = np.array(truth.center)
    ec = np.array(est.center)
    rc = np.linalg.norm(ec - tc) / np.linalg.norm(tc) if np.linalg.norm(tc) > 0 else math.nan
    ta = np.array(truth.alpha)
    ra = np.linalg.norm(np.array(est.alpha) - ta) / np.linalg.norm(ta)
    return float(rp), float(rc), float(ra)


@dataclass
class Row:
    method: str
    setting: int
    n: int
    psnr_mean: float
    psnr_median: float
    rp_median: float
    rc_median: float
    ra_median: float
    rp_mean: float
    rc_mean: float
    ra_mean: float
    seconds_per_image: float
    fallbacks: int


def run(
    images: Sequence[np.ndarray],
    methods: dict[str, Callable[[np.ndarray], VignettingModel]],
    settings: Iterable[int] = (1, 2, 3),
    quantize: bool = False,
    progress: Callable[[str], None] | None = None,
) -> list[Row]:
    """Evaluate each method on each image and setting.

    Parameters
    ----------
    images : sequence of ndarray
        Protocol images (480×320 gray, or 480×320×3, from :func:`protocol_image`).
    methods : dict
        name → callable(vignetted gray image) → VignettingModel for that frame.
    quantize : bool
        Round the vignetted image to 8 bits, as a JPEG-sourced photo would be.
    """
    rows = []
    for s in settings:
        truth = table1_model(s)
        phi = truth.field((HEIGHT, WIDTH))
        vig = [vignetted(im, np.log(phi)) for im in images]
        vig = [np.round(v * 255.0) / 255.0 if quantize else v for v in vig]
        for name, fn in methods.items():
            ps, rp, rc, ra, secs, fb = [], [], [], [], [], 0
            for im, v in zip(images, vig):
                t0 = time.perf_counter()
                m = fn(v)
                secs.append(time.perf_counter() - t0)
                est_phi = m.field((HEIGHT, WIDTH))
                ps.append(psnr_best_gain(v / (est_phi[..., None] if v.ndim == 3 else est_phi), im))
                # parameters of the fit itself; PSNR above is of what would be applied
                e = relative_errors(m.candidate if m.candidate is not None else m, truth)
                rp.append(e[0]); rc.append(e[1]); ra.append(e[2])
                fb += bool(m.quality and m.quality.fallback)
            row = Row(name, s, len(images), float(np.mean(ps)), float(np.median(ps)),
                      float(np.median(rp)), float(np.median(rc)), float(np.median(ra)),
                      float(np.mean(rp)), float(np.mean(rc)), float(np.mean(ra)),
                      float(np.mean(secs)), fb)
            rows.append(row)
            if progress:
                progress(format_row(row))
    return rows


HEADER = f"{'method':<14}{'set':>4}{'n':>5}{'PSNR dB':>9}{'med r_P%':>10}{'med r_c%':>10}{'med r_a%':>10}{'s/img':>9}{'fallbk':>7}"


def format_row(r: Row) -> str:
    return (f"{r.method:<14}{r.setting:>4}{r.n:>5}{r.psnr_mean:>9.2f}{100 * r.rp_median:>10.1f}"
            f"{100 * r.rc_median:>10.1f}{100 * r.ra_median:>10.1f}{r.seconds_per_image:>9.4f}{r.fallbacks:>7}")


def write_json(rows: list[Row], path: Path, meta: dict) -> None:
    from vigproc.atomic import atomic_write_text

    atomic_write_text(path, json.dumps({"meta": meta, "rows": [asdict(r) for r in rows]}, indent=1) + "\n")
