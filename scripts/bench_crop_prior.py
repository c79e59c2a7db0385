#!/usr/bin/env python
"""Part (a) of ``vigproc bench real-frames`` with a crop-aware EXIF prior (issue 38; a design
measured in docs/benchmarks/real-frames.md, not adopted).

The default's EXIF prior is the spread of the lensfun calibrations nearest the frame's 35-mm
focal length and f-number, each over its own whole frame: every frame is read as if its lens
were made for its sensor. A body of crop c also carries lenses made for larger sensors, whose
field it sees out to ρ = lens crop / c only. Here the prior of a frame whose EXIF gives its
crop (:func:`vigproc.stores.lensfun_match.frame_crop`) is drawn from every calibration whose
lens covers the sensor (lens crop ≤ c × 1.02), each cut at ρ = lens crop / c and projected
onto the family's components, at 35-mm focal length (focal × c) and f-number: the fields that
sensor sees from lensfun's lenses. The lenses measured are left out, as the bench's family
leaves them out. Everything else is the bench's (:func:`benchmarks.real_frames_lensfun.run_lensfun`).

Usage (from /tmp, the repository on PYTHONPATH)::

    NUMBA_NUM_THREADS=1 python scripts/bench_crop_prior.py {on|off} DIR
"""

from __future__ import annotations

import argparse
import logging
import math
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))
sys.path.insert(0, str(Path(__file__).resolve().parent))
import benchmarks.real_frames_lensfun as rfl  # noqa: E402
from benchmarks.real_frames import full_frames  # noqa: E402
from lensfun_frame_profiles import family_floor, rho_grid  # noqa: E402
from vigproc.core import lensfamily  # noqa: E402

log = logging.getLogger("bench_crop_prior")
#: A lens covers a sensor whose crop is at least its own over this (rounded crops).
COVER_SLACK = 1.02


def cut_coefficients(family, lenses, crop: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Coefficients (M, K), 35-mm focal lengths and f-numbers of every plausible calibration of
    ``lenses`` that covers a sensor of ``crop``, its field cut at ρ = lens crop / ``crop``."""
    from vigproc.stores.lensfun import pa_poly

    r2 = family.radii**2
    lo, hi = lensfamily.PLAUSIBLE
    rows, f35, fno = [], [], []
    for lens in lenses:
        if lens.crop_factor > crop * COVER_SLACK:
            continue
        t2 = min(lens.crop_factor / crop, 1.0) ** 2
        for v in lens.vignetting:
            g = pa_poly(r2, v.k1, v.k2, v.k3)
            if g.min() <= lo or g.max() > hi:
                continue
            rows.append(family.components @ (np.log(pa_poly(r2 * t2, v.k1, v.k2, v.k3)) - family.mean))
            f35.append(v.focal * crop)
            fno.append(v.aperture)
    return np.array(rows), np.array(f35), np.array(fno)


def crop_prior(table, focal35: float, fnumber: float, k: int, neighbours: int = lensfamily.NEIGHBOURS):
    """Mean and covariance of the first ``k`` coefficients of the ``neighbours`` rows of
    ``table`` (:func:`cut_coefficients`) nearest in (log focal, log f-number), as
    :meth:`~vigproc.core.lensfamily.LensFamily.prior` forms its own."""
    c, f, n = table
    near = c[np.argsort(np.hypot(np.log(f / focal35), np.log(n / fnumber)), kind="stable")[:neighbours], :k]
    mean = near.mean(axis=0)
    dev = near - mean
    return mean, dev.T @ dev / (near.shape[0] - 1) + 1e-6 * np.eye(k)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("mode", choices=("on", "off"))
    ap.add_argument("images")
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.WARNING)
    from vigproc.stores.lensfun import load_lenses
    from vigproc.stores.lensfun_match import frame_crop

    files = full_frames([args.images])
    found, _ = rfl.lensfun_frames(files)
    measured = {tuple(t.lens.split(" / ", 1)) for _p, _k, t, _tg, _ic in found}
    lenses = [lz for lz in load_lenses() if (lz.maker, lz.model) not in measured]
    state: dict = {"crop": None, "family": None, "tables": {}, "distances": {}}
    shipped_prior, frame_row, without = lensfamily.LensFamily.prior, rfl.frame_row, rfl.without_lenses

    def prior(self, focal35=None, fnumber=None, neighbours=lensfamily.NEIGHBOURS):
        crop, fam = state["crop"], state["family"]
        if crop is None or fam is None or not (focal35 and fnumber):
            return shipped_prior(self, focal35, fnumber, neighbours)
        key = round(crop, 3)
        if key not in state["tables"]:
            state["tables"][key] = cut_coefficients(fam, lenses, crop)
        return crop_prior(state["tables"][key], focal35, fnumber, self.n_components, neighbours)

    def row(path, proc, truth, lens_key, tags, ic):
        state["crop"] = frame_crop(lens_key)
        try:
            r = frame_row(path, proc, truth, lens_key, tags, ic)
            state["distances"][path.name] = prior_distances(truth, lens_key)
            return r
        finally:
            state["crop"] = None

    def prior_distances(truth, lens_key) -> tuple[float, float]:
        # the truth's Mahalanobis distance from the shipped-style prior and from this one
        fam, f35, fno = state["family"], lens_key.focal_35mm, lens_key.fnumber
        if fam is None or not (f35 and fno):
            return math.nan, math.nan
        shape = (160, 240)
        _, c = family_floor(truth.log_field(shape), rho_grid(shape), fam, fam.n_components)
        return tuple(float(np.sqrt((c - m) @ np.linalg.solve(v, c - m)))
                     for m, v in (shipped_prior(fam, f35, fno), prior(fam, f35, fno)))

    def family_without(found_):
        state["family"] = without(found_)
        return state["family"]

    if args.mode == "on":
        lensfamily.LensFamily.prior, rfl.frame_row, rfl.without_lenses = prior, row, family_without
    s = rfl.run_lensfun(files)
    for r in s.rows:
        d = state["distances"].get(r.file, (math.nan, math.nan))
        print(f"{r.file[:40]:40s} rho {r.corner_rho:.2f} truth {r.truth_corner_ev:.2f} cand {r.candidate_corner_ev:5.2f} "
              f"err {r.error_ev:.3f} cand {r.candidate_error_ev:.3f} {'truth' if r.truth_holds else 'no truth'}"
              f"  truth's distance (s.d.) from the shipped / crop-aware prior {d[0]:.2f} / {d[1]:.2f}")
    print(f"{args.mode}: median over the {s.truth_frames} truth frames, EV: applied {s.median_error_ev:.3f}, "
          f"candidate {s.median_candidate_ev:.3f}, uncorrected {s.median_uncorrected_ev:.3f}")
    return 0 if math.isfinite(s.median_error_ev) else 1


if __name__ == "__main__":
    sys.exit(main())
