"""Does darktable apply the per-plane GainMaps vigproc writes? (docs/benchmarks/colour.md)

A copy of ``../shared/data/raw/tinydng/colorchart.dng`` (a real Bayer DNG) with its
ActiveArea set to the whole raw image (darktable 4.2's ``_check_gain_maps`` takes
OpcodeList2 GainMaps only when they span its whole raw image, margins included; the DNG
specification puts them on the active area; with no margins the two agree) gets two
corrections written by :func:`vigproc.io.dng_vignette.write_dng_correction`: ``lum``, a
fall-off with the same gain in every CFA phase, and ``col``, the same with a colour field
(R falls faster, B slower: four per-phase maps of different gains), and ``grid``, a
profile's measured grid field (:class:`vigproc.core.gridfield.GridFieldModel`: a lopsided
per-channel field no radial model holds, 33×22 nodes). Each is exported
headless with ``darktable-cli`` (workflow "none", linear Rec.709 float TIFF), as is the
file without opcodes; what darktable applied is the ratio of the two exports, in 16×16 px
blocks where both are exposed (0.01..0.9) and unclipped.

* ``lum``: the exports' ratio per channel against the written gain (EV).
* ``col`` and ``grid``: darktable's output is a linear mix of camera RGB (its camera matrix, white
  balance), so the per-plane gains are compared in camera space: N = M⁻¹ is the 3×3 that
  makes each row's ratio n_i·B / n_i·A equal gain g_i (the null vector of the stacked
  B − g_i·A over all blocks: six unknowns against thousands of blocks); the figure is the
  per-channel difference of that ratio from the written gain (EV).

Run from the repository root:  .venv/bin/python scripts/bench_darktable_colour.py [--keep DIR]
Skips (exit 0, a message) when darktable-cli, exiftool or the DNG is missing.
"""

from __future__ import annotations

import argparse
import json
import math
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

DNG = Path(__file__).resolve().parents[2] / "shared" / "data" / "raw" / "tinydng" / "colorchart.dng"


def export(dt: str, src: Path, dst: Path, cfg: Path) -> np.ndarray:
    import OpenImageIO as oiio

    subprocess.run([dt, str(src), str(dst), "--icc-type", "LIN_REC709", "--apply-custom-presets", "false",
                    "--core", "--configdir", str(cfg), "--conf", "plugins/darkroom/workflow=none",
                    "--conf", "plugins/imageio/format/tiff/bpp=32"], check=True, capture_output=True, timeout=900)
    return oiio.ImageBuf(str(dst)).get_pixels(oiio.FLOAT)[..., :3].astype(np.float64)


def blocks(x: np.ndarray, k: int = 16) -> np.ndarray:
    h, w = x.shape[0] // k, x.shape[1] // k
    return x[: h * k, : w * k].reshape(h, k, w, k, -1).mean(axis=(1, 3))


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--keep", help="keep the DNGs and exports in this folder")
    args = ap.parse_args()
    dt, et = shutil.which("darktable-cli"), shutil.which("exiftool")
    if not dt or not et or not DNG.exists():
        print("skipped: darktable-cli, exiftool or the test DNG is missing")
        return 0
    from vigproc.core.colour import ColourField
    from vigproc.core.gridfield import GridField, GridFieldModel
    from vigproc.core.model import VignettingModel
    from vigproc.io.dng_vignette import write_dng_correction

    work = Path(args.keep) if args.keep else Path(tempfile.mkdtemp(prefix="vigproc-dt-colour-"))
    work.mkdir(parents=True, exist_ok=True)
    full = work / "full.dng"
    shutil.copyfile(DNG, full)
    subprocess.run([et, "-q", "-overwrite_original", "-IFD0:ActiveArea=0 0 1182 1888",
                    "-IFD0:DefaultCropSize=1888 1182", "--", str(full)], check=True)
    W, H = 1888, 1182
    lum = VignettingModel(W, H, center=(60, -30), p=(1 / 1100**2, 0, 1 / 1100**2), method="flat-field",
                          colour=ColourField(W, H, (0, 0), [[1e-4, 0, 0], [0, 0, 0], [0, 0, 0]]))
    col = VignettingModel(W, H, center=(60, -30), p=(1 / 1100**2, 0, 1 / 1100**2), method="flat-field",
                          colour=ColourField(W, H, (0, 0), [[0.3, 0, 0], [0, 0, 0], [-0.3, 0, 0]]))
    # a lopsided fall-off, stronger to the left and the bottom, R faster and B slower
    ny, nx = 22, 33
    x, y = np.meshgrid(np.linspace(-0.5, 0.5, nx), np.linspace(-0.5, 0.5, ny))
    base = -1.2 * (x * x + y * y) - 0.6 * np.maximum(-x, 0) ** 2 - 0.4 * np.maximum(y, 0) ** 2
    grid = GridFieldModel(W, H, method="flat-field",
                          grid=GridField(W, H, np.stack([1.3 * base, base, 0.7 * base], axis=-1)))
    cfg = work / "cfg"
    a = export(dt, full, work / "full.tif", cfg)
    out = {}
    for name, m in (("lum", lum), ("col", col), ("grid", grid)):
        write_dng_correction(full, work / f"{name}.dng", m)
        b = export(dt, work / f"{name}.dng", work / f"{name}.tif", cfg)
        A, B = blocks(a), blocks(b)
        lf = m.grid.log_fields(W, H) if name == "grid" else m.channel_log_fields((H, W))
        G = np.exp(blocks(-lf))
        ok = np.all((A > 0.01) & (A < 0.9) & (B > 0.01) & (B < 0.95), axis=2)
        A, B, G = A[ok], B[ok], G[ok]
        if name in ("col", "grid"):
            rows = []
            for i in range(3):
                x = (B - G[:, i:i + 1] * A) / np.linalg.norm(A, axis=1, keepdims=True)
                rows.append(np.linalg.svd(x, full_matrices=False)[2][-1])
            n = np.array(rows)
            A, B = A @ n.T, B @ n.T
        d = (np.log(B / A) - np.log(G)) / math.log(2)
        out[name] = {"blocks": int(ok.sum()), "share": float(ok.mean()),
                     "rms_ev": np.sqrt(np.mean(d * d, axis=0)).tolist(),
                     "p99_ev": np.percentile(np.abs(d), 99, axis=0).tolist(),
                     "gain_ev_max": (np.log2(G).max(axis=0)).tolist()}
        print(f"{name}: {out[name]['blocks']} blocks ({out[name]['share']:.0%}); darktable vs written gain, "
              f"RMS EV R G B {' '.join(f'{v:.4f}' for v in out[name]['rms_ev'])}, p99 "
              f"{' '.join(f'{v:.4f}' for v in out[name]['p99_ev'])} (gains up to "
              f"{' '.join(f'{v:.2f}' for v in out[name]['gain_ev_max'])} EV)")
    print(json.dumps(out))
    if not args.keep:
        shutil.rmtree(work, ignore_errors=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
