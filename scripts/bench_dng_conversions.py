"""Measure the DNG opcode conversions on real lenses' fall-offs (docs/benchmarks/dng.md).

For each of the 20 lenses of :func:`vigproc.stores.lensfun.diverse_lenses` (lensfun's calibration
at its shortest focal length, widest aperture, farthest distance):

* model -> FixVignetteRadial: the lens's Kang-Weiss model (:func:`vigproc.stores.lensfun_io.kw_from_pa`)
  written as the opcode (:func:`vigproc.io.dng_vignette.model_to_radial`), error stated;
* FixVignetteRadial -> model: an opcode that removes the lens's pa fall-off (k0..k4 by
  least squares on the gain 1/pa over r in [0, 1]) read back as a Kang-Weiss model
  (:func:`vigproc.io.dng_vignette.opcode_to_model`), error stated, centred and 5 % off-centre.

Also the shared GainMap blob (when ../shared is present) as a Kang-Weiss model.  Run from
the repository root:  .venv/bin/python scripts/bench_dng_conversions.py
"""

from __future__ import annotations

import json
import logging
import statistics
import sys
import time
from pathlib import Path

import numpy as np

from vigproc.io.dng_opcodes import FixVignetteRadial, parse_opcode_list
from vigproc.io.dng_vignette import model_to_radial, opcode_to_model
from vigproc.errors import ModelError
from vigproc.stores.lensfun import diverse_lenses
from vigproc.stores.lensfun_io import kw_from_pa

log = logging.getLogger("bench_dng_conversions")
W, H = 6000, 4000
SHARED = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "raw" / "dng_opcodes"


def radial_for_pa(k1: float, k2: float, k3: float, cx: float = 0.5, cy: float = 0.5) -> FixVignetteRadial:
    """The FixVignetteRadial whose gain best undoes pa (least squares over r in [0, 1])."""
    r = np.linspace(0.0, 1.0, 400)
    gain = 1.0 / (1.0 + k1 * r**2 + k2 * r**4 + k3 * r**6)
    basis = np.stack([r ** (2 * i + 2) for i in range(5)], axis=1)
    return FixVignetteRadial(tuple(np.linalg.lstsq(basis, gain - 1.0, rcond=None)[0]), cx, cy)


def summary(values: list[float]) -> dict[str, float]:
    values = [v for v in values if v == v]  # NaN: a refused conversion
    return {"median": statistics.median(values), "max": max(values), "n": len(values)}


def main() -> int:
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    logging.getLogger("vigproc").setLevel(logging.WARNING)  # the per-fit lines are this script's
    rows: list[dict] = []
    refused: list[str] = []
    t0 = time.perf_counter()
    for lens, pa in diverse_lenses(20):
        m = kw_from_pa(pa.k1, pa.k2, pa.k3, W, H)
        to = model_to_radial(m)
        try:
            _, rms_c, max_c = opcode_to_model(radial_for_pa(pa.k1, pa.k2, pa.k3), W, H)
            _, rms_o, max_o = opcode_to_model(radial_for_pa(pa.k1, pa.k2, pa.k3, 0.45, 0.55), W, H)
        except ModelError as exc:  # refused, typed: counted, not a crash
            log.info("%s %s: FixVignetteRadial -> model refused: %s", lens.maker, lens.model, exc)
            refused.append(f"{lens.maker} {lens.model}")
            rms_c = max_c = rms_o = max_o = float("nan")
        rows.append({"lens": f"{lens.maker} {lens.model}", "falloff_ev": m.field_ev_rms(),
                     "to_radial_rms": to.rms_ev, "to_radial_max": to.max_ev,
                     "from_radial_rms": rms_c, "from_radial_max": max_c,
                     "from_radial_offcentre_rms": rms_o, "from_radial_offcentre_max": max_o})
        log.info("%-50s fall-off %.3f EV | model->FVR %.1e (%.1e) | FVR->model %.1e (%.1e), off-centre %.1e (%.1e)",
                 rows[-1]["lens"][:50], rows[-1]["falloff_ev"], to.rms_ev, to.max_ev, rms_c, max_c, rms_o, max_o)
    out = {k: summary([r[k] for r in rows]) for k in rows[0] if k != "lens"}
    out["lenses"] = len(rows)
    out["refused"] = refused
    out["seconds"] = round(time.perf_counter() - t0, 1)
    f = SHARED / "GainMap.bin"
    if f.is_file():
        (_, gm), = parse_opcode_list(f.read_bytes(), str(f)).decoded()
        m, rms, mx = opcode_to_model(gm, 4056, 3040)
        out["shared_gainmap"] = {"rms_ev": rms, "max_ev": mx, "falloff_ev": m.field_ev_rms()}
    print(json.dumps(out, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
