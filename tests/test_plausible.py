"""Physical plausibility as a rule of every path (issue 38): the gate every field passes
before it is divided out of a frame (vigproc.core.plausible, vigproc.pipeline.guard)."""

import math

import numpy as np
import pytest

from vigproc.core.model import FitQuality, VignettingModel
from vigproc.core.plausible import (BEYOND_REAL_LENSES, BRIGHTER_CORNERS, CLIPS_HIGHLIGHTS, LOW_CONFIDENCE, Rules,
                                    corner_ev, judge, new_white_share, outward_rise_ev, population_max_ev, refused)
from vigproc.io.exif import LensKey
from vigproc.pipeline.guard import guard
from vigproc.pipeline.processor import Processor, Settings, not_applied_reason

W, H = 360, 240
HALF_DIAG = math.hypot((W - 1) / 2, (H - 1) / 2)


def centred(corner_ev_: float, confidence: float = 0.95) -> VignettingModel:
    """A centred quadratic-G fall-off of ``corner_ev_`` EV at the corners (negative: the
    corners brighter)."""
    a2 = 1.0 - 2.0 ** -corner_ev_  # G = 1 - a2 r^2 with r = 1 at the corner (p tiny: A ~ 1)
    p = 1e-12
    r_corner = math.sqrt(p) * HALF_DIAG
    alpha = (0.0, a2 / r_corner**2, 0.0, 0.0, 0.0, 0.0, 0.0)
    return VignettingModel(W, H, p=(p, 0.0, p), alpha=alpha, method="lens-family",
                           quality=FitQuality(confidence=confidence, field_ev_rms=0.3, field_sigma_ev=0.05))


def grey(level: float) -> np.ndarray:
    rng = np.random.default_rng(0)
    return np.clip(level + 0.02 * rng.standard_normal((H, W, 3)), 0.01, 0.999).astype(np.float32)


def test_corner_ev_reads_a_centred_fall_off():
    brightest, depth = corner_ev(centred(1.0))
    assert depth == pytest.approx(1.0, abs=1e-6) and brightest == pytest.approx(-1.0, abs=1e-6)
    assert corner_ev(VignettingModel.identity(W, H)) == (0.0, 0.0)


def test_brighter_corners_are_refused_on_every_path():
    m = centred(-0.2)
    for calibrated in (False, True):  # a calibration too: no lens brightens its corners
        r = judge(m, grey(0.3), calibrated=calibrated)
        assert r is not None and r.rule == BRIGHTER_CORNERS and "+0.20 EV" in r.reason
    assert judge(centred(-0.01), grey(0.3)) is None or judge(centred(-0.01), grey(0.3)).rule != BRIGHTER_CORNERS


def bump(height: float) -> VignettingModel:
    """A centred field 1 + 4h u² − 4h u⁴ (u = 1 at the corner): 1 + h at mid-radius, back to
    1 at the corners (the Nikon D3100 snow frame's fit had this shape, +0.14 EV)."""
    p = 1e-12
    rc = math.sqrt(p) * HALF_DIAG
    alpha = (0.0, -4.0 * height / rc**2, 0.0, 4.0 * height / rc**4, 0.0, 0.0, 0.0)
    return VignettingModel(W, H, p=(p, 0.0, p), alpha=alpha, method="lens-family",
                           quality=FitQuality(confidence=0.95, field_ev_rms=0.05, field_sigma_ev=0.01))


def test_a_fit_that_brightens_on_its_way_to_the_corners_is_refused():
    m = bump(0.1)  # +0.1375 EV at mid-radius, the corners level with the centre
    assert abs(corner_ev(m)[0]) < 1e-6  # the corners alone do not show it
    assert outward_rise_ev(m) == pytest.approx(math.log2(1.1), abs=2e-3)
    r = judge(m, grey(0.3))
    assert r is not None and r.rule == BRIGHTER_CORNERS and "0.14 EV on its way out" in r.reason
    assert judge(m, grey(0.3), calibrated=True) is None  # a measured field is the lens's
    assert judge(bump(0.03), grey(0.3)) is None  # +0.04 EV: within real calibrations' spread
    assert outward_rise_ev(centred(1.0)) == 0.0 and outward_rise_ev(VignettingModel.identity(W, H)) == 0.0
    # off-centre: the lines start at the field's own centre, so a lens off the frame's
    # centre (its field rising towards it from the frame's centre) is not refused
    off = VignettingModel(W, H, center=(120.0, 40.0), p=(1 / 200**2, 0.0, 1 / 200**2), method="robust",
                          quality=FitQuality(confidence=0.95, field_ev_rms=0.3, field_sigma_ev=0.05))
    assert outward_rise_ev(off) < 1e-9


def test_the_real_lens_population_bounds_a_fit_not_a_calibration():
    everything = population_max_ev()
    phone = population_max_ev(29.0, 2.2)
    assert 1.0 < phone < everything < 6.0  # lenses like it fall off less than the deepest of all
    assert population_max_ev(None, None) == everything
    deep = centred(phone + Rules().margin_ev + 0.3)
    r = judge(deep, None, focal35=29.0, fnumber=2.2)
    assert r is not None and r.rule == BEYOND_REAL_LENSES and "29 mm" in r.reason
    assert judge(deep, None) is None  # no EXIF: the population's overall deepest
    assert judge(deep, None, calibrated=True, focal35=29.0, fnumber=2.2) is None
    assert judge(centred(phone - 0.2), None, focal35=29.0, fnumber=2.2) is None
    # half the strength removes half the fall-off
    assert judge(deep, None, focal35=29.0, fnumber=2.2, strength=0.5) is None


def test_a_fit_below_its_confidence_threshold_is_refused():
    r = judge(centred(0.5, confidence=0.07), grey(0.3))
    assert r is not None and r.rule == LOW_CONFIDENCE and "0.07" in r.reason
    assert judge(centred(0.5, confidence=0.6), grey(0.3)) is None
    assert judge(centred(0.5, confidence=0.07), grey(0.3), calibrated=True) is None
    no_quality = VignettingModel(W, H, p=centred(0.5).p, alpha=centred(0.5).alpha)  # a plugin stating none
    assert judge(no_quality, grey(0.3)) is None


def test_highlights_pushed_past_white_are_refused_when_the_output_clips():
    bright, dark = grey(0.85), grey(0.2)
    m = centred(0.6)
    assert new_white_share(bright, m) > 0.05 and new_white_share(dark, m) == 0.0
    r = judge(m, bright)
    assert r is not None and r.rule == CLIPS_HIGHLIGHTS
    assert judge(m, bright, clips=False) is None  # a float output keeps them
    assert judge(m, dark) is None
    # a source's own clipped highlights are not the correction's doing
    own = dark.copy()
    own[:, :, :] = np.where(np.arange(W)[None, :, None] < W // 3, 1.0, own)
    assert new_white_share(own, m) == 0.0


def test_refused_keeps_the_field_as_the_candidate_with_its_reason():
    m = centred(-0.3)
    r = judge(m, None)
    out = refused(m, r)
    assert out.is_identity and out.candidate == m and out.quality.fallback
    assert not_applied_reason(out) == r.reason


def test_guard_in_camera_first_and_even_of_a_fit_that_fell_back():
    class Flag:
        reason = "the camera already corrected its vignetting (VignetteControl is on)"

    m = centred(0.5)
    out, r = guard(m, "estimate", grey(0.3), in_camera=Flag())
    assert r.rule == "in-camera" and out.candidate == m and out.is_identity
    fell = VignettingModel.identity(W, H, candidate=m, quality=FitQuality(fallback=True, confidence=0.3))
    out, r = guard(fell, "estimate", grey(0.3), in_camera=Flag())
    assert r.rule == "in-camera" and out.candidate == m and not_applied_reason(out) == Flag.reason
    assert guard(fell, "estimate", grey(0.3)) == (fell, None)  # the estimator's own fall-back stands
    assert guard(m, "estimate", grey(0.3), check=False) == (m, None)


class _Source:
    """A profile-source plugin answering with a fixed model."""

    def __init__(self, model):
        self.model = model

    def lookup(self, lens_key, width, height):
        return self.model.rescale(width, height)


@pytest.mark.parametrize("corner, rule", [(-0.25, BRIGHTER_CORNERS), (0.4, None)])
def test_the_pipeline_asks_the_gate_of_a_plugin_profile(corner, rule):
    key = LensKey(make="Canon", model="Canon EOS 600D", lens="EF 50mm", focal_mm=50.0, fnumber=2.8,
                  focal_35mm=80.0)
    with Processor(Settings(profile="auto"), sources={"x": _Source(centred(corner))}) as proc:
        out, res = proc.process_image(grey(0.3), key)
    assert res.source == "source:x"
    if rule is None:
        assert res.applied and "not_applied_rule" not in res.extra
        assert float(out[0, 0].mean()) > 0.3 * 1.2  # the corners lifted
    else:
        assert not res.applied and res.extra["not_applied_rule"] == rule
        assert res.model.candidate is not None and np.allclose(out, grey(0.3))  # the pixels as read
    with Processor(Settings(profile="auto"), sources={"x": _Source(centred(corner))}, plausibility=False) as proc:
        _, res = proc.process_image(grey(0.3), key)
    assert res.applied  # the rules off: what vigproc did before them


def test_the_gate_reads_a_display_encoded_frame_as_its_linear_light():
    """The processor hands the gate a JPEG's codes (an EncodedImage): the highlight rule
    must judge the light they decode to, as it judges the float frame."""
    from vigproc.io.images import EncodedImage

    m = centred(0.6)
    for level, refused_ in ((0.85, True), (0.2, False)):
        lin = grey(level)
        codes = np.floor(np.clip(lin, 0, 1) * 255 + 0.5).astype(np.uint8)  # linear codes
        enc = EncodedImage(codes, "linear")
        out, refusal = guard(m, "estimate", enc)
        assert (refusal is not None and refusal.rule == CLIPS_HIGHLIGHTS) is refused_
        assert (refusal is not None) is (guard(m, "estimate", enc.linear())[1] is not None)
