"""The crop/shift test (vigproc.forensics.crops): a vignetting centre off the frame's is found and
placed; a centred one is not flagged; its calibration and AUC are what they say."""

import json
import math

import numpy as np
import pytest

from benchmarks.crops import shifted_field
from vigproc.forensics.crops import CropCalibration, CropCalibrationError, auc, check_crop
from vigproc.io.images import write_image

from conftest import photo_like, run_cli

#: A lensfun-like pa shape (Canon-ish wide angle): 1 - 0.6 r^2 + 0.1 r^4
K = (-0.6, 0.1, 0.0)


def _frame(offset, angle=0.6, ev=1.5, seed=4):
    scene = photo_like(320, 480, seed=seed, contrast=0.03)
    return scene * np.exp(shifted_field(K, ev, offset, angle))


def _cal():
    # a null distribution of shifts: uncropped frames rarely move the centre by 0.1
    return CropCalibration(np.linspace(0.0, 0.1, 200), "test")


def test_a_shifted_centre_is_found_and_placed():
    ev = check_crop(_frame(0.4), channel_axis=None, calibration=_cal())
    r = math.hypot(239.5, 159.5)
    true = np.array([0.4 * r * math.cos(0.6), 0.4 * r * math.sin(0.6)])
    assert ev.verdict == "off-centre", ev
    est = np.array(ev.offset_px)
    # placed in the right direction, at most 0.2 half-diagonals off (textured scenes pull it in)
    assert est @ true / (np.linalg.norm(est) * np.linalg.norm(true)) > 0.95
    assert np.linalg.norm(est - true) < 0.2 * r
    assert ev.p_false_alarm < 0.01 and "crop" in ev.reason()
    cov = np.array(ev.covariance_px)
    assert cov.shape == (2, 2) and np.all(np.linalg.eigvalsh(cov) > 0)


def test_a_centred_fall_off_is_not_flagged():
    ev = check_crop(_frame(0.0), channel_axis=None, calibration=_cal())
    assert ev.verdict == "not-shown-off-centre" and ev.shift < 0.1 and ev.p_false_alarm > 0.01, ev


def test_a_far_centre_the_test_cannot_flag_is_not_called_centred():
    """A user's frame was called "centred" with its centre 0.86 half-diagonals off: a
    loose null (scenes that move the centre far) leaves the shift unflagged, and the
    answer then says only that, with the offset."""
    loose = CropCalibration(np.linspace(0.0, 1.2, 200), "loose")
    ev = check_crop(_frame(0.4), channel_axis=None, calibration=loose)
    assert ev.shift > 0.25 and ev.p_false_alarm > 0.01, ev
    assert ev.verdict == "not-shown-off-centre", ev
    assert f"{ev.shift:.2f} half-diagonals" in ev.reason() and "centred fall-off" in ev.reason()


def test_no_fall_off_is_insufficient_signal():
    flat = 0.5 * np.exp(0.01 * np.random.default_rng(5).standard_normal((320, 480)))
    ev = check_crop(flat, channel_axis=None, calibration=_cal())
    assert ev.verdict == "insufficient-signal" and "too weak" in ev.reason()


def test_calibration_p_values_and_bad_files(tmp_path):
    cal = _cal()
    assert cal.p_value(1.0) == pytest.approx(1 / 201)  # beyond every null value
    assert cal.p_value(-1.0) == 1.0
    assert cal.p_value(0.05) < cal.p_value(0.02)
    cal.save(tmp_path / "c.json")
    assert np.allclose(CropCalibration.load(tmp_path / "c.json").null_z, cal.null_z, atol=1e-4)  # 4 decimals
    for bad in ({"kind": "other"}, {"kind": "vigproc-crop-calibration", "null_z": [1, 2]},
                {"kind": "vigproc-crop-calibration", "null_z": [float("nan")] * 30}, []):
        with pytest.raises(CropCalibrationError):
            CropCalibration.from_dict(bad)
    (tmp_path / "x.json").write_text("{", encoding="utf-8")
    with pytest.raises(CropCalibrationError):
        CropCalibration.load(tmp_path / "x.json")


def test_auc_is_the_mann_whitney_share():
    rng = np.random.default_rng(0)
    pos, neg = rng.normal(1, 1, 40), rng.normal(0, 1, 50)
    brute = np.mean([(p > n) + 0.5 * (p == n) for p in pos for n in neg])
    assert auc(pos, neg) == pytest.approx(brute)
    assert auc(np.array([1.0, 1.0]), np.array([1.0])) == 0.5
    assert math.isnan(auc(np.array([]), neg))


def test_check_reports_the_crop_test(tmp_path):
    p = tmp_path / "shifted.tif"
    write_image(p, np.repeat(_frame(0.4)[..., None], 3, axis=2).astype(np.float32), bit_depth="float")
    r = run_cli("check", "--no-store", "--json", p)  # not about the process: main() in this one
    doc = json.loads(r.stdout)
    crop = doc["results"][0]["crop"]
    assert crop["verdict"] in ("off-centre", "not-shown-off-centre") and crop["shift"] > 0.2, crop
    assert len(crop["offset_px"]) == 2 and len(crop["covariance_px"]) == 2
    r = run_cli("check", "--no-store", p)
    assert "; crop test: " in r.stdout.splitlines()[0]  # on the frame's own line


def test_a_known_profile_places_the_centre_of_its_own_lens():
    """bench crops --statistic known-profile fits the centre alone, in a family that is the
    lens's own profile: on a texture with little shading it finds a 40 % shift, and an
    uncropped frame stays near the centre."""
    from benchmarks.crops import known_profile_family
    from vigproc.core.pixels import luminance
    from vigproc.forensics.crops import crop_statistic

    fam = known_profile_family(K, 1.5)
    assert fam.n_components == 1 and np.allclose(fam.prior()[0], 0.0, atol=1e-9)
    shifted = crop_statistic(luminance(_frame(0.4)), fam)[3]
    centred = crop_statistic(luminance(_frame(0.0)), fam)[3]
    assert abs(shifted - 0.4) < 0.1 and centred < 0.1, (shifted, centred)


def test_bench_crops_calibrates_only_the_tests_own_statistic(tmp_path):
    r = run_cli("bench", "crops", "--statistic", "known-profile", "--calibrate", tmp_path / "c.json")
    assert r.returncode == 2 and "needs --statistic shift" in r.stderr and not (tmp_path / "c.json").exists()
