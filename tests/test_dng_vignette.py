"""DNG vignetting opcodes as vigproc models and back (vigproc.io.dng_vignette)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from vigproc.io.dng_opcodes import AreaSpec, FixVignetteRadial, GainMap, OpcodeList, parse_opcode_list
from vigproc.io.dng_vignette import (
    EmbeddedCalibration,
    GainFieldModel,
    model_to_radial,
    opcode_to_model,
)
from vigproc.errors import ModelError
from vigproc.core.model import VignettingModel

W, H = 600, 400
LN2 = math.log(2.0)


def lens_like_radial(cx: float = 0.5, cy: float = 0.5) -> FixVignetteRadial:
    """A FixVignetteRadial fitted to a cos^4-like fall-off of ~1.2 EV in the corners."""
    r = np.linspace(0, 1, 200)
    g = (1 + (0.9 * r) ** 2) ** 2 * (1 + 0.15 * r**4)  # gain = 1/phi
    basis = np.stack([r ** (2 * i + 2) for i in range(5)], axis=1)
    return FixVignetteRadial(tuple(np.linalg.lstsq(basis, g - 1, rcond=None)[0]), cx, cy)


def kw_model() -> VignettingModel:
    f = 0.9 * math.hypot(W, H) / 2
    return VignettingModel(W, H, center=(12.0, -8.0), p=(f**-2, 0.0, f**-2), alpha=(0.02, 0.01, 0, 0, 0, 0, 0))


def rms_ev(a: np.ndarray, b: np.ndarray) -> float:
    d = (a - b) / LN2
    return float(np.sqrt(np.mean(d * d)))


@pytest.mark.parametrize("centre", [(0.5, 0.5), (0.44, 0.57)])
def test_fix_vignette_radial_as_kang_weiss(centre: tuple[float, float]) -> None:
    fvr = lens_like_radial(*centre)
    m, rms, mx = opcode_to_model(fvr, W, H)
    # the stated error is the error: measured here at every pixel
    true = -np.log(fvr.gain_field(W, H))
    err = rms_ev(m.log_field((H, W)), true)
    assert rms < 2e-3 and err == pytest.approx(rms, rel=0.25, abs=2e-4)
    assert mx < 0.05
    assert m.quality.objective == rms and m.method == "dng:FixVignetteRadial"
    # the model's centre is the opcode's optical centre
    ox, oy = fvr.centre_px(W, H)
    assert math.hypot(m.center[0] - ox, m.center[1] - oy) < 1.0
    assert m.field_ev_rms() > 0.3


def test_model_to_radial_and_back() -> None:
    truth = kw_model()
    fit = model_to_radial(truth)
    assert (fit.opcode.cx, fit.opcode.cy) == pytest.approx((0.5 + 12 / W, 0.5 - 8 / H))
    assert fit.rms_ev < 2e-3 and fit.max_ev < 0.02
    # the opcode's gain undoes the model at every pixel, within the stated error
    assert rms_ev(-np.log(fit.opcode.gain_field(W, H)), truth.log_field()) == pytest.approx(fit.rms_ev, abs=5e-4)
    back, rms, _ = opcode_to_model(fit.opcode, W, H)
    assert rms_ev(back.log_field(), truth.log_field()) < 3e-3


def test_model_to_radial_strength_and_identity() -> None:
    truth = kw_model()
    half = model_to_radial(truth, strength=0.5)
    g_half = np.log(half.opcode.gain_field(W, H))
    assert rms_ev(g_half, -0.5 * truth.log_field()) < 2e-3
    none = model_to_radial(VignettingModel.identity(W, H))
    assert none.opcode.is_identity and none.rms_ev == 0.0
    assert model_to_radial(truth, strength=0.0).opcode.is_identity
    with pytest.raises(ModelError):
        model_to_radial(truth, strength=3.0)


def test_elliptical_model_states_what_a_radial_opcode_loses() -> None:
    f = 0.9 * math.hypot(W, H) / 2
    ell = VignettingModel(W, H, center=(0.0, 0.0), p=(f**-2, 0.0, 1.6 * f**-2), alpha=(0.02,) + (0,) * 6)
    fit = model_to_radial(ell)
    actual = rms_ev(-np.log(fit.opcode.gain_field(W, H)), ell.log_field())
    assert fit.rms_ev > 0.02 and actual == pytest.approx(fit.rms_ev, rel=0.2)


def gain_map(planes: int = 3, pitch: int = 1, top: int = 0, left: int = 0) -> GainMap:
    v = np.linspace(-1, 1, 9)[:, None]
    h = np.linspace(-1, 1, 13)[None, :]
    base = 1.0 + 0.9 * (v * v + h * h) / 2 + 0.1 * h  # not radial: tilted
    gains = np.stack([base * (1 + 0.1 * p) for p in range(planes)], axis=-1)
    return GainMap(AreaSpec(top, left, H, W, planes=planes, row_pitch=pitch, col_pitch=pitch), gains,
                   1 / 8, 1 / 12)


def test_gain_map_is_applied_as_its_own_field_per_plane() -> None:
    gm = gain_map()
    cal = EmbeddedCalibration.from_lists([("OpcodeList3", OpcodeList((gm.to_opcode(),)))], "x.dng")
    m = cal.model(W, H)
    assert isinstance(m, GainFieldModel) and isinstance(m, VignettingModel)
    assert m.method == "dng:GainMap" and m.quality.objective > 0  # the fit's error, stated
    rng = np.random.default_rng(0)
    scene = rng.uniform(0.1, 0.5, (H, W, 3)).astype(np.float32)
    gains = np.stack([gm.gain_field(W, H, p) for p in range(3)], axis=-1)
    vignetted = (scene / gains).astype(np.float32)
    out = m.correct_image(vignetted, channel_axis=-1)
    assert out.dtype == np.float32 and np.allclose(out, scene, rtol=1e-5)
    # the grey field is the mean of the planes' log gains
    assert np.allclose(cal.log_gain(W, H), np.mean(np.log(gains), axis=-1))
    # strength and clipping as for any correction; a rescaled model keeps its map
    half = m.correct_image(vignetted, strength=0.5, clip=0.2)
    assert half.max() <= 0.2
    small = m.rescale(W // 2, H // 2)
    assert isinstance(small, GainFieldModel) and small.calibration is cal
    assert np.allclose(small.correct_image(vignetted[::2, ::2]), scene[::2, ::2], rtol=0.02)


def test_cfa_gain_maps_average_their_phases() -> None:
    ops = [gain_map(planes=1, pitch=2, top=t, left=l) for t in (0, 1) for l in (0, 1)]
    ops[3] = GainMap(ops[3].area, ops[3].gains * 1.2, ops[3].spacing_v, ops[3].spacing_h)
    cal = EmbeddedCalibration.from_lists([("OpcodeList2", OpcodeList(tuple(o.to_opcode() for o in ops)))], "x")
    expect = np.mean([np.log(o.gain_field(W, H)) for o in ops], axis=0)
    assert np.allclose(cal.log_gain(W, H), expect) and np.allclose(cal.log_gain(W, H, 2), expect)
    assert cal.kind == "GainMap"


def test_gain_map_fit_states_its_error() -> None:
    gm = gain_map()
    m, rms, mx = opcode_to_model(gm, W, H)
    true = -np.mean([np.log(gm.gain_field(W, H, p)) for p in range(3)], axis=0)
    assert rms_ev(m.log_field(), true) == pytest.approx(rms, rel=0.3, abs=1e-3)
    assert mx >= rms


def test_shared_gain_map_converts_with_its_error(shared_data) -> None:
    f = shared_data / "raw" / "dng_opcodes" / "GainMap.bin"
    (_, gm), = parse_opcode_list(f.read_bytes(), str(f)).decoded()
    m, rms, mx = opcode_to_model(gm, 4056, 3040)
    # measured: 0.015 EV RMS, 0.15 EV at most (the map is not quite Kang-Weiss): applied as a field
    assert rms < 0.03 and mx < 0.3
    assert 0.4 < m.field_ev_rms() < 0.9


def test_absurd_gains_and_no_ops() -> None:
    zero = GainMap(AreaSpec(0, 0, H, W), np.array([[1.0, 0.0]]), 1.0, 1.0)
    cal = EmbeddedCalibration.from_lists([("OpcodeList3", OpcodeList((zero.to_opcode(),)))], "bad.dng")
    with pytest.raises(ModelError, match="no vignetting correction"):
        cal.fit(W, H)
    noop = FixVignetteRadial((0.0,) * 5)
    assert EmbeddedCalibration.from_lists([("OpcodeList3", OpcodeList((noop.to_opcode(),)))], "x") is None
    darkening = FixVignetteRadial((-2.0, 0, 0, 0, 0))  # g = 1 - 2 r^2 reaches 0 inside the frame
    with pytest.raises(ModelError):
        opcode_to_model(darkening, W, H)
