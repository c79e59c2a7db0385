#!/usr/bin/env python
"""Why a part (a) frame misses (issue 38; docs/benchmarks/real-frames.md): its fields along
the diagonal, the lens family's own floor on it, and what the estimate reads from its scene.

For each frame of ``vigproc bench real-frames`` part (a) (a file whose lens lensfun
calibrated; :func:`benchmarks.real_frames_lensfun.lensfun_frames`), with the bench's prior
(lensfun's family without the lenses measured, :func:`~benchmarks.real_frames_lensfun.without_lenses`):

* *profiles*: log2 of the field along the frame's diagonal, 0 at the centre, at ρ = 0 … 1
  (half-diagonals): lensfun's (``truth``, the bench's: corner at ρ = calibration crop /
  camera crop), the default's fit before the gate (``cand``, through the pipeline as the
  bench runs it) and ``floor2``/``floor3``: the truth projected onto the family's first 2 /
  3 components with a free gain (least squares over the frame's grid): the best field the
  default's model can express there, its error the model's own floor on that frame;
* *prior*: the Mahalanobis distance of the truth's 3 coefficients from the EXIF prior the
  default fits with (:meth:`vigproc.core.lensfamily.LensFamily.prior` at the frame's 35-mm
  focal length and f-number), and the error of that prior's mean field (the population
  alone);
* *--profile lensfun*: the field ``correct --profile lensfun`` applies, and lensfun's whole
  field stretched over the frame (ρ = 1 at its corner): corner fall-off and error of each;
* *scene*: ``vigproc.estimate`` (the public API on the linear frame, box-averaged to a long
  side of at most 1500 px, with the frame's EXIF hint) of the frame as it is and of the frame
  with lensfun's field divided out. The second sees the scene alone: its field (RMS about the
  mean, corner fall-off; negative: brighter corners) is what the estimator reads from the
  scene, and where the first's error against lensfun equals it, the miss is the scene's.

Errors are the bench's: RMS over the frame of log2(φ̂/φ) about its mean, EV.

Usage (from /tmp, the repository on PYTHONPATH; DIR as for the bench's ``--images``)::

    NUMBA_NUM_THREADS=1 python scripts/lensfun_frame_profiles.py DIR [--only SUBSTRING ...]
"""

from __future__ import annotations

import argparse
import logging
import math
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))
from benchmarks.real_frames import full_frames  # noqa: E402
from benchmarks.real_frames_lensfun import (  # noqa: E402
    _ev, candidate_of, corrected, grid_shape, lensfun_frames, without_lenses)

log = logging.getLogger("lensfun_frame_profiles")
_LN2 = math.log(2.0)
#: ρ at which the profiles are printed.
RADII = (0.0, 0.2, 0.4, 0.5, 0.6, 0.7, 0.8, 0.9, 1.0)
#: Long side (px) the frame is box-averaged to before the scene fits (the estimator bins far coarser).
SCENE_SIDE = 1500


def rho_grid(shape: tuple[int, int]) -> np.ndarray:
    """ρ (half-diagonals from the centre) on an H×W grid of a frame."""
    h, w = shape
    ys, xs = np.mgrid[0:h, 0:w].astype(np.float64)
    return np.hypot(xs - (w - 1) / 2, ys - (h - 1) / 2) / math.hypot((w - 1) / 2, (h - 1) / 2)


def family_floor(true_log: np.ndarray, rho: np.ndarray, family, k: int) -> tuple[np.ndarray, np.ndarray]:
    """The field of the family's first ``k`` components nearest ``true_log`` (natural log,
    on the grid ``rho``) with a free gain, by least squares: (its log field, the
    coefficients)."""
    fam = family.truncated(k)
    mean, basis = fam.profiles(rho)
    a = np.concatenate([basis.reshape(-1, k), np.ones((rho.size, 1))], axis=1)
    c, *_ = np.linalg.lstsq(a, (true_log - mean).ravel(), rcond=None)
    return mean + basis @ c[:k], c[:k]


def diagonal(log_field: np.ndarray) -> np.ndarray:
    """log2 of a grid's field at :data:`RADII` along its diagonal to the bottom-right corner,
    0 at the centre."""
    h, w = log_field.shape
    v = np.array([log_field[int(round((h - 1) / 2 * (1 + r))), int(round((w - 1) / 2 * (1 + r)))]
                  for r in RADII]) / _LN2
    return v - v[0]


def box_reduced(img: np.ndarray, side: int = SCENE_SIDE) -> np.ndarray:
    """``img`` (H×W×C) box-averaged by the smallest whole factor that brings its long side to ``side`` or less."""
    s = max(1, math.ceil(max(img.shape[:2]) / side))
    h, w = img.shape[0] // s, img.shape[1] // s
    return img[:h * s, :w * s].reshape(h, s, w, s, -1).mean(axis=(1, 3)).astype(np.float32)


def scene_fits(path: Path, truth, lens_key) -> tuple[float, float, float, float]:
    """The API estimate's error against lensfun on the frame, and the field RMS, corner fall-off
    (EV) of its estimate on the frame with lensfun's field divided out (module doc), plus the
    frame estimate's corner fall-off."""
    from vigproc.core.estimate import estimate, exif_hint
    from vigproc.core.plausible import corner_ev
    from vigproc.io import read_image

    img = read_image(path)
    img = box_reduced(img[0] if isinstance(img, tuple) else img)
    h, w = img.shape[:2]
    hint = exif_hint(lens_key, "default")
    g = grid_shape(w, h)
    true_g = truth.log_field(g)
    scene = img / np.exp(truth.log_field((h, w)))[..., None].astype(np.float32)
    frame_m, scene_m = (candidate_of(estimate(x, hint=hint)) for x in (img, scene))
    log_of = lambda m: np.zeros(g) if m.is_identity else m.log_field(g)  # noqa: E731
    return (_ev(log_of(frame_m) - true_g), corner_ev(frame_m)[1], _ev(log_of(scene_m)), corner_ev(scene_m)[1])


def lensfun_applied(lens_key, truth, width: int, height: int) -> tuple[float, float, float, float]:
    """What ``correct --profile lensfun`` applies (:func:`vigproc.stores.lensfun_io.lensfun_model`)
    and lensfun's whole field stretched over the frame (ρ = 1 at its corner, whatever its
    sensor): corner fall-off (EV) and error against the truth of each."""
    from vigproc.core.plausible import corner_ev
    from vigproc.stores.lensfun_io import import_lensfun, lensfun_model
    from vigproc.stores.lensfun_match import match_lens

    g = grid_shape(width, height)
    true_log = truth.log_field(g)
    applied = lensfun_model(lens_key, width, height)
    whole = import_lensfun(match_lens(lens_key).lens, None, truth.focal_mm, truth.fnumber, truth.distance_m,
                           width=width, height=height)
    return (corner_ev(applied)[1], _ev(applied.log_field(g) - true_log),
            corner_ev(whole)[1], _ev(whole.log_field(g) - true_log))


def prior_check(family, true_c: np.ndarray, lens_key, rho: np.ndarray, true_log: np.ndarray) -> tuple[float, float]:
    """Mahalanobis distance of the truth's coefficients from the frame's EXIF prior, and the
    error of the prior mean's field (NaN without a 35-mm focal length and f-number)."""
    f35, fno = getattr(lens_key, "focal_35mm", None), getattr(lens_key, "fnumber", None)
    if not (f35 and fno):
        return math.nan, math.nan
    pm, pc = family.prior(f35, fno)
    d = true_c - pm
    mean, basis = family.profiles(rho)
    return float(np.sqrt(d @ np.linalg.solve(pc, d))), _ev(mean + basis @ pm - true_log)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("images", help="folder of frames (as bench real-frames --images)")
    ap.add_argument("--only", nargs="*", default=[""], help="file-name substrings to keep")
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.WARNING)
    from vigproc.core.lensfamily import shipped_family_replaced
    from vigproc.pipeline.processor import Processor, Settings

    found, _ = lensfun_frames(full_frames([args.images]))
    fam = without_lenses(found)
    head = "".join(f"{r:6.2f}" for r in RADII)
    with shipped_family_replaced(fam), Processor(Settings(mode="correct", profile="estimate"), plausibility=True) as proc:
        for p, k, truth, _tags, _ic in found:
            if not any(s in p.name for s in args.only):
                continue
            res, img = corrected(p, proc)
            shape = grid_shape(img.shape[1], img.shape[0])
            rho = rho_grid(shape)
            true_log = truth.log_field(shape)
            cand = candidate_of(res.model)
            cand_log = np.zeros(shape) if cand is None or cand.is_identity else cand.log_field(shape)
            floors = {n: family_floor(true_log, rho, fam, n) for n in (2, 3)}
            maha, prior_err = prior_check(fam, floors[3][1], k, rho, true_log)
            api_err, api_corner, scene_rms, scene_corner = scene_fits(p, truth, k)
            lf_corner, lf_err, whole_corner, whole_err = lensfun_applied(k, truth, img.shape[1], img.shape[0])
            print(f"\n{p.name}  rho {truth.corner_rho:.2f}  truth {truth.corner_ev:.2f} EV"
                  f"\n  error: cand {_ev(cand_log - true_log):.3f}  floor2 {_ev(floors[2][0] - true_log):.3f}"
                  f"  floor3 {_ev(floors[3][0] - true_log):.3f}  none {_ev(true_log):.3f}"
                  f"\n  prior: Mahalanobis {maha:.2f}, prior mean's error {prior_err:.3f}"
                  f"\n  API estimate: frame {api_corner:.2f} EV, error {api_err:.3f} | scene alone {scene_corner:.2f} EV,"
                  f" field RMS {scene_rms:.3f}"
                  f"\n  --profile lensfun: {lf_corner:.2f} EV, error {lf_err:.3f} | whole field over the frame"
                  f" {whole_corner:.2f} EV, error {whole_err:.3f}")
            print(f"  rho    {head}")
            for name, f in (("truth", true_log), ("cand", cand_log), ("floor2", floors[2][0]), ("floor3", floors[3][0])):
                print(f"  {name:6s} " + "".join(f"{v:6.2f}" for v in diagonal(f)))
    return 0


if __name__ == "__main__":
    sys.exit(main())
