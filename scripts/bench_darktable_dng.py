"""Does darktable apply the calibrations vigproc reads and writes? (docs/benchmarks/dng.md)

Synthetic Bayer DNGs (``tests/dngfixture.py``: one textured scene, darktable's rawspeed
and LibRaw both decode them) are exported headless with ``darktable-cli`` to linear
Rec.2020 float TIFFs, in a fresh config folder, workflow "none" (no filmic, no base curve,
no exposure), with an XMP whose history enables the lens correction module in its
"embedded metadata" mode (params v6 of darktable 4.2: method 0, vignetting only,
``modified`` set).  What darktable applied is the ratio of two exports that differ only
in the calibration the file carries; what vigproc applies is the ratio of its own TIFF
correction (``vigproc correct --output-format tiff-float``) to its uncorrected development
(``--strength 0 --unapplied write``).  Each pair is compared as log2 ratios per pixel, the
channel mean, pixels with a channel at ≤ 1e-4 or ≥ 0.95 in any export left out; the
figure is the RMS of their difference about its mean, EV, over the whole frame.

Cases:

* ``opcode3-gain2``: an OpcodeList3 FixVignetteRadial k = (1, 0, 0, 0, 0) (gain 2 in the
  corners), against the same file without it: does darktable apply it at all?
* ``opcode3-vigproc``: the FixVignetteRadial ``vigproc correct --output-format dng`` writes
  for an estimated fall-off, against vigproc's own TIFF correction of that frame;
* ``opcode2-gainmap``: four CFA GainMaps in OpcodeList2 (gain 1 + r², the same in every
  phase), against ``vigproc correct --profile embedded``;
* ``sony-makernote``: Sony's ``VignettingCorrParams`` in the raw SubIFD (what an ARW
  carries), against ``vigproc correct --profile embedded`` (vigproc.makernotes).

Run from the repository root:  .venv/bin/python scripts/bench_darktable_dng.py [--keep DIR]
Skips (exit 0, a message) when darktable-cli is not installed.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import struct
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests"))

from dngfixture import make_dng, smooth_scene, sony_vignetting_tags  # noqa: E402

from vigproc.io.dng_opcodes import AreaSpec, FixVignetteRadial, GainMap, OpcodeList  # noqa: E402
from vigproc.io.images import read_image  # noqa: E402

W, H = 1536, 1024
#: Sony VignettingCorrParams values of the fixture (16 knots, up to ~0.6 EV in the corners).
SONY_VALUES = [round(6000 * (i / 15) ** 2.5) for i in range(16)]
CLIP = 0.95


def lens_xmp(method: int = 0, flags: int = 2, *, crop: float = 1.0, focal: float = 0.0, aperture: float = 0.0,
             camera: bytes = b"", lens: bytes = b"") -> str:
    """An XMP sidecar whose history enables darktable 4.2's lens module (params v6), by
    default in "embedded metadata" mode (``method`` 0; 1: lensfun, for ``camera`` and
    ``lens`` at ``crop``, ``focal``, ``aperture``), correcting vignetting only (``flags``
    2; 0: nothing)."""
    params = struct.pack("<iiifffffi128s128siffffi",
                         method,  # 0: DT_IOP_LENS_METHOD_EMBEDDED_METADATA, 1: lensfun
                         flags,  # 2: DT_IOP_LENS_MODIFY_FLAG_VIGNETTING
                         0, 1.0, crop, focal, aperture, 1000.0, 1,  # lensfun: inverse, scale, crop, focal, f, dist, geom
                         camera, lens, 0, 1.0, 1.0,  # camera, lens, tca_override, tca_r, tca_b
                         1.0, 1.0,  # cor_dist_ft, cor_vig_ft
                         1)  # modified: use these params, not the module's defaults
    return f"""<?xml version="1.0" encoding="UTF-8"?>
<x:xmpmeta xmlns:x="adobe:ns:meta/" x:xmptk="XMP Core 4.4.0-Exiv2">
 <rdf:RDF xmlns:rdf="http://www.w3.org/1999/02/22-rdf-syntax-ns#">
  <rdf:Description rdf:about="" xmlns:darktable="http://darktable.sf.net/"
   darktable:xmp_version="4" darktable:history_end="1">
   <darktable:history>
    <rdf:Seq>
     <rdf:li darktable:num="0" darktable:operation="lens" darktable:enabled="1" darktable:modversion="6"
      darktable:params="{params.hex()}" darktable:multi_name="" darktable:multi_priority="0"/>
    </rdf:Seq>
   </darktable:history>
  </rdf:Description>
 </rdf:RDF>
</x:xmpmeta>
"""


def darktable_version(exe: str) -> str:
    out = subprocess.run([exe, "--version"], capture_output=True, text=True, timeout=60).stdout
    return out.splitlines()[0].strip() if out else "?"


def dt_export(exe: str, src: Path, xmp: Path, out: Path, work: Path) -> np.ndarray:
    """Export ``src`` with ``xmp`` to a linear float TIFF; its pixels (H×W×3)."""
    cfg = Path(tempfile.mkdtemp(prefix="dtcfg-", dir=work))
    try:
        cmd = [exe, str(src), str(xmp), str(out), "--icc-type", "LIN_REC2020", "--core", "--configdir", str(cfg),
               "--library", ":memory:", "--conf", "plugins/imageio/format/tiff/bpp=32",
               "--conf", "plugins/darkroom/workflow=none", "-d", "perf"]
        res = subprocess.run(cmd, capture_output=True, text=True, timeout=600)
        if res.returncode != 0 or not out.exists():
            raise RuntimeError(f"darktable-cli failed on {src.name}: {res.stdout[-500:]} {res.stderr[-500:]}")
        if "lens correction" not in res.stdout + res.stderr:
            raise RuntimeError(f"darktable did not run the lens module on {src.name}")
    finally:
        shutil.rmtree(cfg, ignore_errors=True)
    img, _ = read_image(out, transfer="linear")
    return np.asarray(img, dtype=np.float64)[..., :3]


def vigproc(*args: str) -> None:
    exe = Path(sys.executable).with_name("vigproc")
    cmd = [str(exe)] if exe.exists() else [sys.executable, "-c", "import sys; from vigproc.frontends.cli import main; "
                                                               "sys.exit(main())"]
    res = subprocess.run([*cmd, *args], capture_output=True, text=True, timeout=1200)
    if res.returncode != 0:
        raise RuntimeError(f"vigproc {' '.join(args)} failed: {res.stderr[-800:]}")


def vp_ratio(src: Path, work: Path, profile: str) -> tuple[np.ndarray, np.ndarray]:
    """vigproc's own correction of ``src`` over its uncorrected development (log2, per pixel)
    and the valid-pixel mask."""
    out, zero = work / f"vp-{src.stem}", work / f"vp0-{src.stem}"
    vigproc("correct", str(src), "-o", str(out), "--profile", profile, "--output-format", "tiff-float")
    vigproc("correct", str(src), "-o", str(zero), "--profile", profile, "--output-format", "tiff-float",
            "--strength", "0", "--unapplied", "write")
    a, _ = read_image(next(out.glob("*.tif")), transfer="linear")
    b, _ = read_image(next(zero.glob("*.tif")), transfer="linear")
    return log_ratio(np.asarray(b, dtype=np.float64), np.asarray(a, dtype=np.float64))


def log_ratio(a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    ok = (a.min(-1) > 1e-4) & (b.min(-1) > 1e-4) & (a.max(-1) < CLIP) & (b.max(-1) < CLIP)
    return np.log2(np.maximum(b.mean(-1), 1e-12) / np.maximum(a.mean(-1), 1e-12)), ok


def compare(dt: tuple[np.ndarray, np.ndarray], vp: tuple[np.ndarray, np.ndarray] | None) -> dict:
    r, ok = dt
    out = {"dt_ratio_ev_mean": float(r[ok].mean()), "dt_ratio_ev_min": float(r[ok].min()),
           "dt_ratio_ev_max": float(r[ok].max())}
    if vp is not None:
        v, ok2 = vp
        m = ok & ok2
        d = r[m] - v[m]
        e = np.abs(d - d.mean())
        out.update(vp_ratio_ev_min=float(v[m].min()), vp_ratio_ev_max=float(v[m].max()),
                   diff_mean_ev=float(d.mean()), diff_rms_ev=float(d.std()), diff_p99_ev=float(np.percentile(e, 99)),
                   diff_max_ev=float(e.max()), pixels=int(m.sum()), frame=int(m.size))
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--darktable", default=shutil.which("darktable-cli"), help="darktable-cli program")
    ap.add_argument("--keep", help="keep the files in this folder (default: a temporary one, removed)")
    args = ap.parse_args(argv)
    if not args.darktable or not Path(args.darktable).exists():
        print("skipped: darktable-cli not found (Debian/Ubuntu: apt-get install darktable; or --darktable PATH)")
        return 0
    t0 = time.perf_counter()
    work = Path(args.keep) if args.keep else Path(tempfile.mkdtemp(prefix="bench-dt-"))
    work.mkdir(parents=True, exist_ok=True)
    try:
        version = darktable_version(args.darktable)
        xmp = work / "lens-embedded.xmp"
        xmp.write_text(lens_xmp())
        scene = smooth_scene(H, W, 0) * 0.4
        y, x = np.mgrid[:H, :W]
        rr = np.hypot(x + 0.5 - W / 2, y + 0.5 - H / 2) / np.hypot(W / 2, H / 2)
        falloff = 1.0 / (1.0 + 0.8 * rr ** 2)  # ~0.85 EV in the corners, for vigproc to estimate
        files = {}

        def dng(name: str, **kw) -> Path:
            p = work / f"{name}.dng"
            make_dng(p, width=W, height=H, scene=scene, **kw)
            files[name] = p
            return p

        dng("base")
        fvr2 = OpcodeList((FixVignetteRadial((1.0, 0.0, 0.0, 0.0, 0.0), 0.5, 0.5).to_opcode(),))
        dng("opcode3-gain2", opcode_lists={3: fvr2.to_bytes()})
        n = 17
        v = np.arange(n) / (n - 1)
        gy, gx = (v[:, None] - 0.5) * H, (v[None, :] - 0.5) * W
        gains = (1.0 + (gx ** 2 + gy ** 2) / ((W / 2) ** 2 + (H / 2) ** 2)).astype(np.float32)
        gm = OpcodeList(tuple(GainMap(AreaSpec(t, l, H, W, 0, 1, 2, 2), gains, 1 / (n - 1), 1 / (n - 1)).to_opcode()
                              for t in (0, 1) for l in (0, 1)))
        dng("opcode2-gainmap", opcode_lists={2: gm.to_bytes()})
        dng("sony-base", subifd=True)
        dng("sony-makernote", subifd=True, raw_tags=sony_vignetting_tags(SONY_VALUES))
        p = work / "vignetted.dng"
        make_dng(p, width=W, height=H, scene=scene, field=falloff)
        vigproc("correct", str(p), "-o", str(work / "vp-dng"), "--profile", "estimate", "--output-format", "dng")
        files["opcode3-vigproc"] = next((work / "vp-dng").glob("*.dng"))
        files["vignetted"] = p

        ex = {name: dt_export(args.darktable, f, xmp, work / f"dt-{name}.tif", work) for name, f in files.items()}
        results = {
            "opcode3-gain2": compare(log_ratio(ex["base"], ex["opcode3-gain2"]), None)
            | {"identical_pixels": float(np.mean(ex["base"] == ex["opcode3-gain2"]))},
            "opcode3-vigproc": compare(log_ratio(ex["vignetted"], ex["opcode3-vigproc"]),
                                       vp_ratio(p, work, "estimate")),
            "opcode2-gainmap": compare(log_ratio(ex["base"], ex["opcode2-gainmap"]),
                                       vp_ratio(files["opcode2-gainmap"], work, "embedded")),
            "sony-makernote": compare(log_ratio(ex["sony-base"], ex["sony-makernote"]),
                                      vp_ratio(files["sony-makernote"], work, "embedded")),
        }
        print(f"{version}; {W}x{H} synthetic DNGs; {time.perf_counter() - t0:.0f} s")
        print(f"{'case':18} {'darktable log2 gain, mean (min..max)':40} {'vigproc (min..max)':22} "
              f"{'diff RMS EV':>11} {'p99':>7} {'max':>7}")
        for name, r in results.items():
            dtcol = f"{r['dt_ratio_ev_mean']:+.4f} ({r['dt_ratio_ev_min']:+.3f}..{r['dt_ratio_ev_max']:+.3f})"
            if "diff_rms_ev" in r:
                print(f"{name:18} {dtcol:40} {r['vp_ratio_ev_min']:+.3f}..{r['vp_ratio_ev_max']:+.3f}       "
                      f"{r['diff_rms_ev']:11.4f} {r['diff_p99_ev']:7.4f} {r['diff_max_ev']:7.3f}")
            else:
                print(f"{name:18} {dtcol:40} identical pixels {r['identical_pixels']:.4f}")
        print(json.dumps({"darktable": version, "results": results}))
    finally:
        if not args.keep:
            shutil.rmtree(work, ignore_errors=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
