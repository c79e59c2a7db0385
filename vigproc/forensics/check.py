"""Forensic consistency check: does a frame's vignetting match the lens its EXIF names?

A photograph whose vignetting does not match the lens named in its metadata has
been cropped, edited or mislabelled (Lyu 2010, Section 1).  :func:`forensic_check`
estimates the frame's vignetting, looks up what the claimed lens should give (a
stored profile, else lensfun's calibration) and turns the difference into a
calibrated false-alarm probability and a verdict.

The check in three parts, each in its own module (re-exported here, the public path):

* :mod:`vigproc.forensics.rings`: the statistic (fall-off on rings, the vignetting centre)
  and its :class:`Calibration` on frames that truly match their lens;
* :mod:`vigproc.forensics.references`: what the claimed lens should give (a stored profile,
  else lensfun's calibration);
* :mod:`vigproc.forensics.verdicts`: the verdict of one frame (:func:`forensic_check`) and
  of several that claim the same lens (:func:`pool_verdicts`).

References
----------
S. Lyu, "Estimating Vignetting Function from a Single Image for Image
Authentication", ACM MM&Sec 2010.
"""

from __future__ import annotations

from vigproc.forensics.rings import (  # noqa: F401  (re-exported)
    CALIBRATION_SCHEMA, CENTRE, CENTRE_FALLOFF_EV, DEFAULT_ALPHA, FALLOFF, FAMILY_TEST_METHOD, FEATURE_NAMES,
    FORENSICS_METHOD, MIN_CONFIDENCE, NULL_DRAWS, PRIOR_FRAMES, RING_RADII, SHIPPED_CALIBRATION, Calibration,
    default_calibration, estimator_fingerprint, fit_calibration, forensic_method, ForensicsError,
    frame_features, frame_quality, load_calibration, read_json, ring_falloff,
)
from vigproc.forensics.references import (  # noqa: F401  (re-exported)
    Expected, expected_for, expected_from_field, find_reference, Reference, unknown_lens_reason,
)
from vigproc.forensics.verdicts import (  # noqa: F401  (re-exported)
    TESTS, VERDICTS, check_embedded, check_family, check_model, Evidence, forensic_check, is_weak,
    pool_verdicts, score, Verdict,
)

__all__ = [
    "Calibration",
    "Evidence",
    "ForensicsError",
    "Verdict",
    "VERDICTS",
    "check_embedded",
    "check_family",
    "forensic_check",
    "check_model",
    "default_calibration",
    "expected_for",
    "expected_from_field",
    "find_reference",
    "frame_quality",
    "load_calibration",
    "fit_calibration",
    "frame_features",
    "is_weak",
    "pool_verdicts",
    "score",
    "unknown_lens_reason",
]
