"""Rebuild vigproc/data/samples: Kodak images with known synthetic vignetting.

The Kodak Lossless True Color Image Suite was released by Eastman Kodak for
unrestricted usage. Run from the repository root with ../shared beside it:
    .venv/bin/python scripts/make_samples.py
"""

import json
import subprocess
from pathlib import Path

import numpy as np
import OpenImageIO as oiio

from vigproc.io.images import linear_to_srgb, read_image
from vigproc.stores.lensfun import diverse_lenses, pa_field
from vigproc.core.model import VignettingModel

SRC = Path(__file__).resolve().parents[1].parent / "shared/data/natural/kodak"
DST = Path(__file__).resolve().parents[1] / "vigproc/data/samples"


def main() -> None:
    lenses = diverse_lenses(20)
    meta = []
    for name, kind, li in [("kodim05.png", "lensfun", 0), ("kodim23.png", "kw", None), ("kodim13.png", "lensfun", 3)]:
        img, _ = read_image(SRC / name)
        h, w = img.shape[:2]
        if kind == "lensfun":
            lens, pa = lenses[li]
            phi = pa_field((h, w), pa.k1, pa.k2, pa.k3)
            desc = f"lensfun pa field of {lens.maker} {lens.model} at {pa.focal} mm f/{pa.aperture}: k=({pa.k1}, {pa.k2}, {pa.k3})"
        else:
            m = VignettingModel(w, h, center=(-60.0, 40.0), p=(1.6e-6, 0.3e-6, 2.0e-6), alpha=(0.02, 0.01, 0, 0, 0, 0, 0))
            phi = m.field()
            desc = "Kang-Weiss model " + m.to_json()
        codes = np.clip(np.round(linear_to_srgb(np.clip(img * phi[..., None], 0, 1)) * 255), 0, 255).astype(np.uint8)
        out = DST / name.replace(".png", "_vignetted.jpg")
        spec = oiio.ImageSpec(w, h, 3, oiio.UINT8)
        spec.attribute("Compression", "jpeg:92")
        spec.attribute("ImageDescription", f"vigproc sample; {desc}")
        o = oiio.ImageOutput.create(str(out))
        o.open(str(out), spec)
        o.write_image(codes)
        o.close()
        if kind == "lensfun":
            # lens EXIF as a camera would write it (list arguments: no shell)
            subprocess.run(["exiftool", "-q", "-overwrite_original", f"-Make={lens.maker}", "-Model=vigproc sample",
                            f"-LensModel={lens.model}", f"-FocalLength={pa.focal}", f"-FNumber={pa.aperture}",
                            "--", str(out)], check=True)
        meta.append({"file": out.name, "source": f"Kodak Lossless True Color Image Suite, {name}",
                     "vignetting": desc, "corner_attenuation": round(float(phi[0, 0]), 4)})
    (DST / "samples.json").write_text(json.dumps(meta, indent=1) + "\n")


if __name__ == "__main__":
    main()
