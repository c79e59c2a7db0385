"""Colour cast from one photograph: detected where the evidence holds, and only there."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

from benchmarks.colour_detect import Cast, cast_for, detection_rates, physical_casts
from vigproc.core.colour_cast import ColourCastEvidence, detect_colour_cast
from vigproc.core.colour_difference import grey_cast_de
from vigproc.errors import InvalidImageError

H, W = 320, 480


def scene(seed: int) -> np.ndarray:
    """Piecewise-constant coloured patches (random rectangles) with a luminance-only
    texture and 1 % noise: a stand-in for a photograph, linear RGB."""
    rng = np.random.default_rng(seed)
    img = np.empty((H, W, 3))
    img[:] = np.exp(rng.normal(0, 0.3, 3)) * 0.3
    for _ in range(40):
        h, w = rng.integers(20, 140, 2)
        y, x = rng.integers(0, H - h), rng.integers(0, W - w)
        img[y:y + h, x:x + w] = np.exp(rng.normal(0, 0.4, 3)) * rng.uniform(0.1, 0.5)
    yy, xx = np.mgrid[0:H, 0:W]
    shade = 1 + 0.3 * np.sin(xx / 37.0 + rng.uniform(0, 6)) * np.sin(yy / 23.0)
    img *= shade[..., None]
    img *= 1 + 0.01 * rng.standard_normal(img.shape)
    return np.clip(img, 1e-4, None)


def radial_log(theta_max: float = 40.0) -> np.ndarray:
    yy, xx = np.mgrid[0:H, 0:W]
    r = np.hypot(xx - (W - 1) / 2, yy - (H - 1) / 2) / (0.5 * math.hypot(W, H))
    return np.log(np.cos(np.arctan(r * math.tan(math.radians(theta_max)))))


def test_strong_radial_cast_is_detected():
    c = cast_for(10.0, 135.0, 40.0)  # corners lose red, gain blue: cyan-blue
    frame = scene(1) * np.exp(c.log_transmission((H, W)))
    ev = detect_colour_cast(frame)
    assert isinstance(ev, ColourCastEvidence)
    assert ev.detected, ev
    assert ev.confidence > 0.5
    # the estimated direction is the cast's, its size within a factor 2
    u, v = c.corner_shift()
    assert np.dot(ev.shift, (u, v)) > 0.8 * math.hypot(*ev.shift) * math.hypot(u, v)
    assert 5 < ev.delta_e < 20
    d = ev.to_dict()
    assert d["detected"] is True and d["delta_e"] == pytest.approx(ev.delta_e, abs=1e-3)
    json.dumps(d)


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_clean_frame_is_not_detected(seed):
    ev = detect_colour_cast(scene(seed))
    assert not ev.detected, ev
    assert ev.reason


@pytest.mark.parametrize("seed", [1, 2])
def test_luminance_only_falloff_is_not_a_cast(seed):
    frame = scene(seed) * np.exp(4.0 * radial_log(45.0))[..., None]  # 1.2 EV at the corner, all channels alike
    ev = detect_colour_cast(frame)
    assert not ev.detected, ev
    assert ev.delta_e < 2.0


def test_blue_sky_at_the_top_is_not_a_cast():
    img = scene(4)
    yy = np.arange(H)[:, None]
    sky = np.stack([0.25 + 0.1 * yy / H, 0.45 + 0.1 * yy / H, np.full((H, 1), 0.9)], axis=-1)[:, 0]
    top = H // 3
    img[:top] = sky[:top, None, :] * (1 + 0.01 * np.random.default_rng(5).standard_normal((top, W, 3)))
    ev = detect_colour_cast(img)
    assert not ev.detected, ev


def test_centre_from_the_luminance_model_and_bad_input():
    from vigproc.core.model import VignettingModel

    c = cast_for(10.0, 0.0, 40.0)
    frame = scene(2) * np.exp(c.log_transmission((H, W)))
    m = VignettingModel(W, H, center=(0.0, 0.0), p=(1e-6, 0.0, 1e-6))
    assert detect_colour_cast(frame, luminance_model=m).detected
    with pytest.raises(InvalidImageError):
        detect_colour_cast(frame[..., 0], channel_axis=None)
    with pytest.raises(InvalidImageError):
        detect_colour_cast(np.full((4, 4, 3), 0.5))
    # channels first
    assert detect_colour_cast(np.moveaxis(frame, -1, 0), channel_axis=0).detected


def test_cast_for_hits_its_target():
    for t, hue, th in [(5.0, 0.0, 40.0), (3.0, 200.0, 25.0)]:
        c = cast_for(t, hue, th)
        assert float(grey_cast_de(*c.corner_shift())) == pytest.approx(t, abs=1e-3)
        lt = c.log_transmission((H, W))
        assert lt[H // 2, W // 2].max() == pytest.approx(0.0, abs=1e-3)
        corner = lt[0, 0]
        assert corner[0] - corner[1] == pytest.approx(c.corner_shift()[0], abs=2e-3)
    assert len(physical_casts((5.0, 7.0), 4, (30.0,))) == 8


def test_detection_rates_count_right():
    bases = [scene(s) for s in (1, 2, 3)]
    casts = [cast_for(10.0, 90.0, 40.0), cast_for(1.0, 0.0, 40.0)]
    lum = [("cos4", 4.0 * radial_log(45.0))]
    r = detection_rates(bases, casts, names=["a", "b", "c"], luminance_fields=lum)
    # recount frame by frame
    want = {}
    for c in casts:
        flags = [detect_colour_cast(b * np.exp(c.log_transmission((H, W)))).detected for b in bases]
        want[c.target_de] = sum(flags)
    rows = {row.label: row for row in r.by_target}
    assert rows["dE 10"].n == 3 and rows["dE 10"].detected == want[10.0]
    assert rows["dE 1"].n == 3 and rows["dE 1"].detected == want[1.0]
    assert rows["dE 10"].rate == pytest.approx(want[10.0] / 3)
    assert r.rate_at_5 == pytest.approx(want[10.0] / 3)
    clean = [detect_colour_cast(b).detected for b in bases]
    assert r.clean.n == 3 and r.clean.detected == sum(clean)
    assert r.clean.hits == sorted(n for n, f in zip("abc", clean) if f)
    lumf = [detect_colour_cast(b * np.exp(lum[0][1])[..., None]).detected for b in bases]
    assert r.luminance_only.n == 3 and r.luminance_only.detected == sum(lumf)
    # the synthetic scenes: the strong cast is found in all, nothing else
    assert want[10.0] == 3 and sum(clean) == 0 and sum(lumf) == 0


REAL = Path(__file__).resolve().parents[2] / "shared" / "data" / "jpeg_exif"


def test_bench_cli_on_two_real_frames(tmp_path):
    if not REAL.is_dir():
        pytest.skip(f"real camera frames not present ({REAL})")
    from vigproc.frontends.cli import main

    out = tmp_path / "r.json"
    code = main(["bench", "colour-detect", "--images", str(REAL), "--limit", "2", "--targets", "10",
                 "--directions", "2", "--theta-max", "40", "--lenses", "1", "--json", str(out)])
    assert code == 0
    doc = json.loads(out.read_text())
    assert doc["n_bases"] == 2 and doc["by_target"][0]["n"] == 4 and doc["luminance_only"]["n"] == 2


def test_estimate_json_reports_the_cast_and_does_not_correct_it(tmp_path, capsys):
    from vigproc.frontends.cli import main
    from vigproc.io.images import write_image

    c = cast_for(10.0, 135.0, 40.0)
    frame = scene(1) * np.exp(c.log_transmission((H, W)))
    write_image(tmp_path / "cast.jpg", np.clip(frame / frame.max(), 0, 1).astype(np.float32), bit_depth="uint8",
                transfer="srgb", quality=95)
    write_image(tmp_path / "clean.jpg", np.clip(scene(1) / scene(1).max(), 0, 1).astype(np.float32),
                bit_depth="uint8", transfer="srgb", quality=95)
    write_image(tmp_path / "grey.png", scene(1)[..., 1] / scene(1)[..., 1].max(), bit_depth="uint16")
    capsys.readouterr()
    assert main(["estimate", "--json", str(tmp_path / "cast.jpg"), str(tmp_path / "clean.jpg"),
                 str(tmp_path / "grey.png")]) == 0
    recs = json.loads(capsys.readouterr().out)["results"]
    cast, clean, grey = (r["colour_cast"] for r in recs)
    assert cast["detected"] is True and cast["delta_e"] > 5 and 0.5 < cast["confidence"] <= 1
    assert clean["detected"] is False
    assert grey == {"detected": False, "reason": "a grey frame has no colour"}
    # the model stays a luminance field: nothing about colour is applied
    assert "colour" not in json.dumps(recs[0]["model"])


def test_score_is_the_decision_statistic():
    c = cast_for(10.0, 135.0, 40.0)
    for frame in (scene(1) * np.exp(c.log_transmission((H, W))), scene(2), scene(3) * np.exp(4.0 * radial_log(45.0))[..., None]):
        ev = detect_colour_cast(frame)
        assert math.isfinite(ev.score)
        assert ev.detected == (ev.score >= 1.0), ev
        assert ev.to_dict()["score"] == pytest.approx(ev.score, abs=1e-4)


def test_a_mask_that_leaves_nothing_is_a_verdict_not_a_crash():
    frame = scene(1)
    ev = detect_colour_cast(frame, usable=np.zeros((H, W), dtype=bool))
    assert not ev.detected and ev.reason and not math.isfinite(ev.score)
    assert "score" not in ev.to_dict()
    json.dumps(ev.to_dict())


def test_split_calibration_counts_out_of_sample():
    from benchmarks.colour_detect import DetectionResult, RateRow, split_calibrated

    # 40 bases: clean scores 0..39 (even bases calibrate fold 0: their scores 0, 2, .., 38)
    n = 40
    clean = RateRow("clean", n, 0, 0.0, scores=[float(i) for i in range(n)], base_index=list(range(n)))
    lum = RateRow("luminance only", n, 0, 0.0, scores=[-math.inf] * n, base_index=list(range(n)))
    cast = RateRow("dE 5", 2 * n, 0, 0.0, scores=[float(i) + 10 for i in range(n)] + [-1.0] * n,
                   base_index=list(range(n)) * 2)
    r = DetectionResult(n, [cast], clean, lum, math.nan, math.nan)
    f0, f1 = split_calibrated(r)
    # 20 calibration frames, 5 %: one may be called; the threshold sits just above the 2nd highest (36)
    assert f0["calibrated_on"] == "even" and 36 < f0["threshold"] < 36.001
    assert f0["clean_calibration"] == pytest.approx(1 / 20)
    # evaluation on the odd bases: clean 37, 39 are called (2 of 20); casts 27..49 odd of 40 frames
    assert f0["clean"] == pytest.approx(2 / 20)
    assert f0["luminance_only"] == 0.0
    want = sum(1 for i in range(1, n, 2) if i + 10 > 36.0001) / 40
    assert f0["by_target"]["dE 5"] == pytest.approx(want)
    assert f1["calibrated_on"] == "odd" and 37 < f1["threshold"] < 37.001
