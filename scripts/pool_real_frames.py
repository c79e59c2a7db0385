"""Pool the rows of several ``vigproc bench real-frames --json`` runs into one table of harm
counts (each file once, by name; the counts as :func:`benchmarks.real_frames.run` makes
them), for a set measured in parts.

Usage: python scripts/pool_real_frames.py RUN1.json RUN2.json ...
"""
import json
import math
import sys

import numpy as np
rows = {"off": {}, "on": {}}
for f in sys.argv[1:]:
    d = json.load(open(f))
    for k in rows:
        for r in d[k]["rows"]:
            rows[k].setdefault(r["file"], r)


def counts(rs, rules_on):
    from vigproc.core.plausible import Rules
    R = Rules()
    a = [r for r in rs if r["applied"]]
    ic = [abs(r["removed_ev"]) for r in rs if r["in_camera"]]
    w = [r["new_white"] for r in rs] or [0.0]
    return [len(rs), len(a), sum(r["brightest_ev"] > R.corner_tolerance_ev for r in a),
            sum(r["removed_ev"] > r["population_ev"] for r in a),
            sum(r["confidence"] < R.min_confidence for r in a if r["confidence"] is not None and math.isfinite(r["confidence"])),
            sum(r["removed_ev"] > 1.0 for r in a), f"{100*max(w):.2f}", f"{100*float(np.median(w)):.2f}", len(ic),
            f"{np.median(ic):.3f}" if ic else "-", f"{max(ic):.3f}" if ic else "-"]


names = ["frames", "fields applied", "applied with brighter corners", "applied beyond real lenses",
         "applied below confidence 0.5", "more than 1 EV removed at a corner", "pixels newly past white, max %",
         "pixels newly past white, median %", "in-camera corrected frames", "  EV removed there, median",
         "  EV removed there, max"]
c = {k: counts(list(v.values()), k == "on") for k, v in rows.items()}
print(f"{'':<44}{'rules off':>12}{'rules on':>12}")
for i, n in enumerate(names):
    print(f"{n:<44}{str(c['off'][i]):>12}{str(c['on'][i]):>12}")
