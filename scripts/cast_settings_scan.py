"""The single-frame colour-cast detector with one :class:`CastSettings` change, on the frames of
``vigproc bench colour-detect --targets 5 --theta-max 40`` (docs/benchmarks/colour.md,
"Detector settings"; issue 41).

Prints the fixed rule's counts (``score`` ≥ 1), the in-sample rates (threshold calling at most
2 of the 47 clean bases) and both split folds (threshold from one half's clean bases at ≤ 5 %,
rates on the other half). Run, e.g.::

    python scripts/cast_settings_scan.py '{"work_long_side": 120}' --lenses 5
"""

from __future__ import annotations

import argparse
import json
import math
from dataclasses import replace

import numpy as np

from benchmarks import clean as C
from benchmarks.colour_detect import cast_for, half_rate, half_threshold, threshold_at_false_rate
from vigproc.core.colour_cast import CastSettings, detect_colour_cast


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("settings", help="JSON object of CastSettings fields to change")
    ap.add_argument("--images", nargs="+", default=["../shared/data/jpeg_exif", "../shared/data/natural"])
    ap.add_argument("--lenses", type=int, default=5)
    args = ap.parse_args()
    kw = {k: tuple(v) if isinstance(v, list) else v for k, v in json.loads(args.settings).items()}
    s = replace(CastSettings(), **kw)
    bases, _ = C.load_clean_bases(args.images, colour=True)
    bases = [b for b in bases if np.ptp(b[..., 0] - b[..., 1]) > 1e-6 or np.ptp(b[..., 2] - b[..., 1]) > 1e-6]
    fields = [f.log_field for f in C.lens_fields(args.lenses)[0]] if args.lenses else []

    def score(frame: np.ndarray) -> float:
        e = detect_colour_cast(frame, settings=s)
        return e.score if math.isfinite(e.score) else -math.inf

    idx = np.arange(len(bases))
    cl = np.array([score(b) for b in bases])
    lu = np.array([score(b * np.exp(f)[..., None]) for f in fields for b in bases])
    c5 = np.array([score(b * t) for j in range(8)
                   for t in [np.exp(cast_for(5.0, 45.0 * j, 40.0).log_transmission(bases[0].shape[:2]))]
                   for b in bases])
    li, ki = np.tile(idx, len(fields)), np.tile(idx, 8)
    thr = threshold_at_false_rate(cl)
    out = (f"{args.settings}: fixed (score >= 1) clean {int((cl >= 1).sum())}/{cl.size}, luminance only "
           f"{int((lu >= 1).sum())}/{lu.size}, dE 5 {int((c5 >= 1).sum())}/{c5.size} ({np.mean(c5 >= 1):.1%}) | "
           f"in sample (score >= {thr:.3g}): luminance only {np.mean(lu >= thr):.1%}, dE 5 {np.mean(c5 >= thr):.1%} |")
    for cal in (0, 1):
        t = half_threshold(cl, idx, cal)
        ev = 1 - cal
        out += (f" {'even' if cal == 0 else 'odd'} half's threshold {t:.3g}: clean {half_rate(cl, idx, ev, t):.1%}, "
                f"luminance only {half_rate(lu, li, ev, t):.1%}, dE 5 {half_rate(c5, ki, ev, t):.1%};")
    print(out)


if __name__ == "__main__":
    main()
