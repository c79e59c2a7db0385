"""Regenerate the example profiles in this folder from lensfun calibrations.

Run from the repository root::

    .venv/bin/python profiles/examples/make_examples.py

Each example is a real lensfun ``pa`` vignetting calibration (the database bundled
with lensfunpy), converted to vigproc's Kang-Weiss parameters by a least-squares fit
of log φ over a 3:2 grid (:func:`vigproc.stores.profiles.fit_model_to_field`).
"""

from __future__ import annotations

import logging
import math
import sys
from pathlib import Path

import numpy as np

from vigproc.stores.lensfun import diverse_lenses, pa_field
from vigproc.io.exif import LensKey, normalise_text
from vigproc.stores.profiles import (
    Profile, ProfileKey, aperture_bin, aspect_label, export_profile, fit_model_to_field, focal_bin, normalise,
)

log = logging.getLogger("make_examples")

HERE = Path(__file__).resolve().parent
GRID = (200, 300)  # (H, W): 3:2; fine enough that the outer samples reach r = 0.997 (no extrapolation to speak of)

# (lensfun model substring, file name, camera make, camera model, lens name or None, comment on the body)
EXAMPLES = (
    (
        "Distagon T* 2/35 ZF.2", "zeiss-distagon-35mm-f2-nikon-d800.json",
        "NIKON CORPORATION", "NIKON D800", "Carl Zeiss Distagon T* 2/35 ZF.2",
        "lensfun calibrates the lens on a crop-factor-1.0 sensor; the Nikon D800 (full frame, 3:2) "
        "is an example body of that format: set lens.make/lens.model to your camera before importing.",
    ),
    (
        "DSC-RX100", "sony-rx100-10.4mm-f1.8.json",
        "SONY", "DSC-RX100", None,
        "Fixed-lens compact: lensfun's calibration is of this camera (crop factor 2.73, 3:2). Its EXIF "
        "names no lens model, so the lens part of the id is '?'.",
    ),
)


def main() -> int:
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    lenses = diverse_lenses(20)
    for needle, fname, make, model, lens_name, body_note in EXAMPLES:
        lens, entry = next((l, e) for l, e in lenses if needle in l.model)
        # pa_field puts r = 1 at the corner *pixel centre* (radius hypot(W-1, H-1)/2); vigproc's
        # frame radius is hypot(W, H)/2.  On a small grid that 1 % would bias the fit, so the
        # coefficients are rescaled to give lensfun's full-resolution field at our sample radii.
        h, w = GRID
        s = math.hypot(w - 1, h - 1) / math.hypot(w, h)
        k = [entry.k1 * s**2, entry.k2 * s**4, entry.k3 * s**6]
        log_field = np.log(pa_field(GRID, *k))
        m, rms_ev = fit_model_to_field(log_field, 6000, 4000)
        theta, _, aspect = normalise(m)
        theta[np.abs(theta) < 1e-12] = 0.0  # symmetric field: c and p2 are zero up to round-off
        lk = LensKey(make=normalise_text(make), model=normalise_text(model),
                     lens=normalise_text(lens_name) if lens_name else None)
        key = ProfileKey(lk.lens_id(), focal_bin(entry.focal), aperture_bin(entry.aperture), aspect_label(aspect))
        notes = (
            f"lensfun (lensfunpy bundled database) '{lens.maker} / {lens.model}', pa calibration "
            f"k1={entry.k1:g} k2={entry.k2:g} k3={entry.k3:g} at {entry.focal:g} mm f/{entry.aperture:g}, "
            f"distance {entry.distance:g} m, crop factor {lens.crop_factor:g}. Kang-Weiss parameters fitted "
            f"by least squares on log(phi) over a {GRID[1]}x{GRID[0]} 3:2 grid; fit residual RMS "
            f"{rms_ev:.2g} EV; corner attenuation {math.log2(entry.corner):.2f} EV. No uncertainty is "
            f"known (covariance null), so the profile is not trusted by the learning rule. {body_note}"
        )
        p = Profile(key=key, theta=theta, provenance="lensfun", n_frames=0, notes=notes,
                    created="2024-01-01T00:00:00.000Z")
        export_profile(p, HERE / fname)
        log.info("wrote %s (%s, fit RMS %.2g EV)", fname, key, rms_ev)
    return 0


if __name__ == "__main__":
    sys.exit(main())
