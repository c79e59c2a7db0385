"""Crop and shift detection: is the vignetting centred on the frame?

A lens's fall-off is centred on its optical axis, which sits at the centre of the
frame the camera recorded. A crop of a larger frame, a shifted lens or a stitched
image moves that centre off the frame's: the forensic use Lyu (2010, Section 5)
proposes for the vignetting centre.

The test: the lens-family fit with a free centre (:func:`vigproc.core.family_fit.fit_centre`)
gives the fall-off's centre; the statistic is its distance from the frame's centre in
half-diagonals (``shift``). Its p-value is *calibrated*, not assumed: the shifts of
uncropped frames (vignetting-free camera frames × real lensfun fields,
``vigproc bench crops --calibrate``) are shipped as ``vigproc/data/crop_calibration.json``,
and the false-alarm probability of a frame is the share of those uncropped frames whose
shift is at least as large. (The Mahalanobis distance by the centre's jackknife
covariance was measured too: four blocks make that covariance too unsteady, AUC lower.)

The frame's own EXIF never shapes the estimate (a check must not be told what it checks).

References
----------
S. Lyu, "Estimating vignetting function from a single image for image authentication",
ACM MM&Sec 2010, Section 5 (the vignetting centre as evidence of cropping).
"""

from __future__ import annotations

import functools
import json
import math
from dataclasses import dataclass, replace
from importlib import resources
from pathlib import Path
from typing import Any

import numpy as np

from vigproc.atomic import atomic_write_text
from vigproc.core.lensfamily import default_family
from vigproc.core.pixels import check_image, luminance
from vigproc.errors import VigprocError
from vigproc.forensics.lensmatch import empirical_p

#: A frame is called off-centre below this false-alarm probability.
DEFAULT_ALPHA = 0.01
#: The fall-off must be this many times its uncertainty for its centre to mean anything.
MIN_SNR = 1.0
#: Long side of the free-centre fit's working copy (the default estimator's trigger uses 60).
CENTRE_WORK_SIZE = 60
#: What the test can answer. It never says "centred": a fall-off whose centre the test
#: cannot tell from the frame's may still be far from it (its power on one frame is low,
#: ``vigproc bench crops``), so the answer is "not-shown-off-centre", with the offset.
CROP_VERDICTS = ("not-shown-off-centre", "off-centre", "insufficient-signal")


class CropCalibrationError(VigprocError):
    """The crop test's calibration is missing or unusable (exit code 11, as forensics)."""

    exit_code = 11


@dataclass(frozen=True)
class CropEvidence:
    """The crop test's answer for one frame.

    Attributes
    ----------
    verdict : str
        One of :data:`CROP_VERDICTS`.
    offset_px : tuple of float
        The fall-off's centre, (x, y) px from the frame's centre.
    covariance_px : tuple of tuple of float
        Its 2×2 covariance (px²): the uncertainty ellipse.
    shift : float
        |offset| in half-diagonals.
    z : float
        Mahalanobis distance of the offset from the frame's centre.
    p_false_alarm : float or None
        Share of calibration frames (uncropped) with a shift at least this large.
    alpha : float
    snr : float
        The fall-off's strength over its uncertainty (the centre of a flat field is
        undefined).
    """

    verdict: str
    offset_px: tuple[float, float]
    covariance_px: tuple[tuple[float, float], tuple[float, float]]
    shift: float
    z: float
    p_false_alarm: float | None
    alpha: float
    snr: float

    def to_dict(self) -> dict[str, Any]:
        return {"verdict": self.verdict, "offset_px": list(self.offset_px),
                "covariance_px": [list(r) for r in self.covariance_px], "shift": self.shift, "z": self.z,
                "p_false_alarm": self.p_false_alarm, "alpha": self.alpha, "snr": self.snr}

    def reason(self) -> str:
        if self.verdict == "insufficient-signal":
            return f"the fall-off is too weak to place its centre (SNR {self.snr:.1f})"
        where = f"centre ({self.offset_px[0]:+.0f}, {self.offset_px[1]:+.0f}) px, {self.shift:.2f} half-diagonals"
        p = f"p = {self.p_false_alarm:.3g}" if self.p_false_alarm is not None else "uncalibrated"
        if self.verdict == "off-centre":
            return f"vignetting centre off the frame's ({where}, {p}): a crop, a shift or a stitch"
        # not shown off-centre is not "centred": a far centre with p above the threshold
        # is a loosely placed one, which the test cannot tell from a crop either
        return f"the test cannot tell it from a centred fall-off at p < {self.alpha:g} ({where}, {p})"


@dataclass(frozen=True)
class CropCalibration:
    """The statistic (``shift``) of uncropped frames, sorted: its null distribution."""

    null_z: np.ndarray
    source: str = ""

    def p_value(self, z: float) -> float:
        return empirical_p(self.null_z, z)

    def to_dict(self) -> dict[str, Any]:
        return {"kind": "vigproc-crop-calibration", "version": 1, "source": self.source,
                "null_z": [round(float(v), 4) for v in self.null_z]}

    @classmethod
    def from_dict(cls, d: Any) -> CropCalibration:
        try:
            if d.get("kind") != "vigproc-crop-calibration":
                raise ValueError("not a crop calibration")
            z = np.sort(np.asarray(d["null_z"], dtype=np.float64))
            if z.ndim != 1 or z.size < 20 or not np.all(np.isfinite(z)):
                raise ValueError("null_z must hold at least 20 finite values")
            return cls(z, str(d.get("source", "")))
        except (AttributeError, KeyError, TypeError, ValueError) as exc:
            raise CropCalibrationError(f"unusable crop calibration: {exc}") from None

    def save(self, path: str | Path) -> None:
        atomic_write_text(Path(path), json.dumps(self.to_dict()) + "\n")

    @classmethod
    def load(cls, path: str | Path) -> CropCalibration:
        try:
            d = json.loads(Path(path).read_text(encoding="utf-8"))
        except (OSError, ValueError) as exc:
            raise CropCalibrationError(f"cannot read crop calibration {str(path)!r}: {exc}") from None
        return cls.from_dict(d)


@functools.lru_cache(maxsize=1)
def default_crop_calibration() -> CropCalibration | None:
    """The shipped calibration, or None when this installation has none."""
    f = resources.files("vigproc.data").joinpath("crop_calibration.json")
    if not f.is_file():
        return None
    return CropCalibration.from_dict(json.loads(f.read_text(encoding="utf-8")))


def crop_statistic(lum: np.ndarray, family=None,
                   colour: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, float, float, float]:
    """The free-centre fit of an H×W linear luminance frame (``colour``, H×W×3: its
    pairs weighted by how alike their channels change).

    Returns
    -------
    offset_px : ndarray (2,)
    covariance_px : ndarray (2, 2)
    z : float
    shift : float
    snr : float
        The centred fit's fall-off over its uncertainty.
    """
    from vigproc.core.family_fit import EVIDENCE_SETTINGS, fit_centre, fit_family

    # the jackknife its shipped null was made with; the test decides on its own evidence below
    s = replace(EVIDENCE_SETTINGS, min_snr=0.0, grey_min_snr=0.0)
    family = family or default_family()  # the components its shipped null was made in
    model, coef, _ = fit_family(lum, s, family=family, colour=colour)
    snr = float(model.quality.snr) if model.quality is not None and model.quality.snr is not None else 0.0
    if coef is None:
        return np.zeros(2), np.eye(2), 0.0, 0.0, 0.0
    c = fit_centre(lum, coef, s, family=family, work_size=CENTRE_WORK_SIZE, colour=colour)
    return np.asarray(c.offset, dtype=np.float64), np.asarray(c.covariance), c.z, c.shift, snr


def check_crop(img: np.ndarray, *, channel_axis: int | None = -1, calibration: CropCalibration | None = None,
               alpha: float = DEFAULT_ALPHA, family=None) -> CropEvidence:
    """Is the vignetting of ``img`` centred on it? (Lyu 2010, Section 5.)

    Parameters
    ----------
    img : ndarray
        H×W or H×W×C linear image.
    channel_axis : int or None
    calibration : CropCalibration, optional
        Default: the shipped one; without any, ``p_false_alarm`` is None and the
        verdict rests on the jackknife ``z ≥ 3``.
    alpha : float
        False-alarm probability below which the frame is ``off-centre``.

    Returns
    -------
    CropEvidence
    """
    from vigproc.core.family_fit import colour_of

    a = check_image(img, channel_axis)
    lum = luminance(a)
    off, cov, z, shift, snr = crop_statistic(lum, family, colour_of(a))
    cal = calibration if calibration is not None else default_crop_calibration()
    p = cal.p_value(shift) if cal is not None else None
    if snr < MIN_SNR:
        verdict = "insufficient-signal"
    elif (p is not None and p < alpha) or (p is None and z >= 3.0):
        verdict = "off-centre"
    else:
        verdict = "not-shown-off-centre"
    return CropEvidence(verdict, (float(off[0]), float(off[1])),
                        ((float(cov[0, 0]), float(cov[0, 1])), (float(cov[1, 0]), float(cov[1, 1]))),
                        float(shift), float(z), p, float(alpha), float(snr))


def auc(positives: np.ndarray, negatives: np.ndarray) -> float:
    """Area under the ROC curve: P(a positive scores above a negative), ties half
    (the Mann-Whitney U statistic over n_pos·n_neg)."""
    pos = np.asarray(positives, dtype=np.float64)
    neg = np.asarray(negatives, dtype=np.float64)
    if pos.size == 0 or neg.size == 0:
        return math.nan
    from scipy.stats import rankdata

    ranks = rankdata(np.concatenate([pos, neg]))  # ties get their average rank
    u = ranks[:pos.size].sum() - pos.size * (pos.size + 1) / 2.0
    return float(u / (pos.size * neg.size))
