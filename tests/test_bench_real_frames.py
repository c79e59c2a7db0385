"""``vigproc bench real-frames`` part (a): real frames against lensfun's field, one frame and
a series through the profile store (benchmarks.real_frames_lensfun)."""

import math
import shutil
import subprocess
from types import SimpleNamespace

import numpy as np
import pytest

from benchmarks import real_frames_lensfun as rfl
from vigproc.io.images import write_image
from vigproc.stores.lensfun import pa_poly

from conftest import coloured_scene, run_cli

needs_exiftool = pytest.mark.skipif(shutil.which("exiftool") is None, reason="exiftool program not installed")

#: The Olympus PEN E-P3's lens (lensfun: Olympus M.Zuiko Digital 17mm f/1.8, crop 2), wide open.
E_P3 = dict(make="olympus imaging corp.", model="e-p3", lens="m.zuiko digital 17mm f1.8", focal_mm=17.0,
            focal_35mm=34.0, fnumber=1.8, focus_distance_m=None, lens_problem=None, lens_source=None,
            ambiguous=False, width=480, height=360)


def _key(**kw):
    from vigproc.io.exif import LensKey

    d = {**E_P3, **kw}
    d.pop("ambiguous")
    return LensKey(**d)


def test_truth_is_lensfuns_field_at_the_frames_corner():
    truth, why = rfl.lensfun_truth(_key())
    assert truth is not None, why
    assert truth.lens == "Olympus / Olympus M.Zuiko Digital 17mm f/1.8" and truth.corner_rho == pytest.approx(1.0)
    lf = truth.log_field((301, 401))
    k1, k2, k3 = truth.k
    assert lf[150, 200] == pytest.approx(0.0, abs=1e-12)  # the centre
    assert lf[0, 0] == pytest.approx(math.log(1 + k1 + k2 + k3))  # r = 1 at the corner
    assert truth.corner_ev == pytest.approx(-lf[0, 0] / math.log(2))
    # a camera with a smaller sensor than the calibration's sees its centre only: ρ = 2 / 4
    small, _ = rfl.lensfun_truth(_key(focal_35mm=68.0))
    assert small.corner_rho == pytest.approx(0.5)
    assert 0 < small.corner_ev < truth.corner_ev
    # mid-left edge: r² = 0.64 of the frame's, (ρr)² = 0.16 of the calibration's
    assert small.log_field((301, 401))[150, 0] == pytest.approx(
        math.log(pa_poly(np.array(0.25 * 0.64), k1, k2, k3)), rel=1e-3)
    none, why = rfl.lensfun_truth(_key(lens="some lens lensfun never heard of"))
    assert none is None and why


def _stub_processor(model, img):
    res = SimpleNamespace(model=model, applied=model is not None and not model.is_identity, extra={})
    return SimpleNamespace(_process_path=lambda path, fid, fmt: (None, res, img, None, None))


def test_frame_row_error_is_zero_for_the_truth_and_the_truth_for_nothing(tmp_path):
    from vigproc.core.model import VignettingModel
    from vigproc.stores.lensfun_io import kw_from_pa

    key = _key()
    truth, _ = rfl.lensfun_truth(key)
    img = np.zeros((360, 480, 3), np.float32)
    s = truth._scaled_k()
    exact = kw_from_pa(*s, 480, 360)  # lensfun's pa as the model family vigproc applies (misfit ~1e-3 EV)
    row = rfl.frame_row(tmp_path / "a.jpg", _stub_processor(exact, img), truth, key, {}, None)
    assert row.applied and row.truth_holds and row.why == "no in-camera flag recorded"
    assert row.error_ev < 0.01 and row.candidate_error_ev == row.error_ev
    assert row.applied_corner_ev == pytest.approx(truth.corner_ev, abs=0.02)
    assert row.uncorrected_ev > 0.2  # a 1.27 EV lens: far from the figure above
    none = rfl.frame_row(tmp_path / "a.jpg", _stub_processor(VignettingModel.identity(480, 360), img), truth, key,
                         {"ShadingCompensation": 0}, None)
    assert not none.applied and none.error_ev == pytest.approx(none.uncorrected_ev)
    assert none.why == "flags off: ShadingCompensation=0"
    half = kw_from_pa(*(0.5 * k for k in s), 480, 360)
    worse = rfl.frame_row(tmp_path / "a.jpg", _stub_processor(half, img), truth, key, {}, None)
    assert row.error_ev < worse.error_ev < none.error_ev


def test_truth_does_not_hold_where_the_camera_or_a_converter_corrected():
    from vigproc.io.incamera import from_tags

    tags = {"Make": "Canon", "PeripheralLighting": 1}
    assert rfl._truth_holds(tags, from_tags(tags)) == (False, "corrected in camera (PeripheralLighting=1)")
    assert rfl._truth_holds({}, None, corner_rho=1.26) == (False, "beyond lensfun's calibrated corner (ρ = 1.26)")
    holds, why = rfl._truth_holds({"LensProfileEnable": 1, "Software": "Adobe Lightroom"}, None)
    assert not holds and "LensProfileEnable=1" in why
    assert rfl._truth_holds({"VignetteControl": 0}, None) == (True, "flags off: VignetteControl=0")
    assert rfl._truth_holds({"Software": "Ver.1.00"}, None)[0]  # a camera's firmware
    assert rfl._truth_holds({"Software": "Adobe Photoshop CC 2017 (Macintosh)", "LensProfileEnable": 0},
                            None) == (False, "edited (Software=Adobe Photoshop CC 2017 (Macintosh))")
    assert rfl._truth_holds({"PostCropVignetteAmount": -5}, None) == (
        False, "an editor's own vignette (PostCropVignetteAmount=-5)")


def test_truth_does_not_hold_on_a_crop_or_a_picasa_edit():
    # the exif-py A200 frame: 1391x2463 of the camera's 3872x2592, XMP dc:Creator Picasa
    cam = {"RelatedImageWidth": 3872, "RelatedImageHeight": 2592}
    assert rfl._truth_holds(cam, None, size=(1391, 2463)) == (False, "cropped (1391x2463 of the camera's 3872x2592)")
    # turned to portrait, or resized in camera (same aspect): not a crop
    assert rfl._truth_holds(cam, None, size=(2592, 3872))[0]
    assert rfl._truth_holds(cam, None, size=(1536, 1024))[0]
    assert rfl._truth_holds({}, None, size=(1391, 2463))[0]  # nothing to compare with
    assert rfl._truth_holds({"XMP-dc:Creator": "Picasa"}, None) == (False, "edited (Creator=Picasa)")


def test_crop_to_keeps_the_centre_at_the_asked_aspect():
    a = np.arange(40 * 60, dtype=np.float64).reshape(40, 60)
    c = rfl.crop_to(a, 12, 9, frac=0.5)
    assert c.shape == (9, 12)
    assert c.mean() == pytest.approx(a[10:30, 17:43].mean(), rel=0.02)  # centred
    assert rfl.crop_to(np.stack([a] * 3, -1), 9, 12).shape == (12, 9, 3)  # portrait asked: turned


def test_series_pools_through_the_store_towards_the_truth():
    key = _key(width=480, height=360)
    truth, _ = rfl.lensfun_truth(key)
    bases = [coloured_scene(900, 1200, seed=s) for s in range(4)]
    out = rfl.run_series([(None, key, truth, {}, None)], bases, n=4, long_side=480, counts=(1, 4), family=None)
    (row,) = out.rows
    assert row.frames == 4 and set(row.profile_ev) == {1, 4} and out.median_ev == row.profile_ev
    unc = rfl._ev(truth.log_field(rfl.grid_shape(480, 360)))
    # the profile recovers most of a 1.27 EV lens (leaving it alone costs `unc`)
    assert row.profile_ev[4] < 0.3 * unc
    assert math.isnan(row.corner_spread_after_trust_ev) == (row.trusted_at is None)


def _lens_jpeg(path, key):
    truth, _ = rfl.lensfun_truth(key)
    img = coloured_scene(360, 480, seed=7) * np.exp(truth.log_field((360, 480)))[..., None]
    write_image(path, (0.8 * img / img.max()).astype(np.float32), transfer="srgb", quality=92)
    subprocess.run(["exiftool", "-q", "-overwrite_original", "-Make=OLYMPUS IMAGING CORP.", "-Model=E-P3",
                    "-LensModel=M.Zuiko Digital 17mm F1.8", "-FocalLength=17", "-FNumber=1.8",
                    "-FocalLengthIn35mmFormat=34", str(path)], check=True)
    return truth


@needs_exiftool
def test_run_lensfun_finds_the_lens_of_a_real_jpeg_and_the_cli_prints_it(tmp_path):
    frames = tmp_path / "frames"
    frames.mkdir()
    truth = _lens_jpeg(frames / "P1.jpg", _key())
    write_image(frames / "other.jpg", coloured_scene(360, 480, seed=2).astype(np.float32), transfer="srgb")
    found, other = rfl.lensfun_frames(sorted(frames.glob("*.jpg")))
    assert [p.name for p, *_ in found] == ["P1.jpg"] and [p.name for p, _ in other] == ["other.jpg"]
    s = rfl.run_lensfun([frames / "P1.jpg"])
    (row,) = s.rows
    assert row.lens == truth.lens and row.truth_holds and s.truth_frames == 1
    assert row.truth_corner_ev == pytest.approx(truth.corner_ev)
    assert row.uncorrected_ev == pytest.approx(rfl._ev(truth.log_field(rfl.grid_shape(480, 360))))
    out = run_cli("bench", "real-frames", "--images", frames, "--min-long-side", "300", "--no-harm", "--json",
                  tmp_path / "r.json")  # in this process
    assert out.returncode == 0, out.stderr
    assert "lensfun-known lenses: 1 frames, the truth holds on 1" in out.stdout
    import json

    data = json.loads((tmp_path / "r.json").read_text())
    assert data["lensfun"]["rows"][0]["file"] == "P1.jpg" and "on" not in data


def test_cli_refuses_a_folder_without_frames(tmp_path):
    out = run_cli("bench", "real-frames", "--images", tmp_path)
    assert out.returncode == 2 and "no JPEG" in out.stdout and "Traceback" not in out.stderr


def test_a_frame_row_counts_the_pixels_its_correction_pushes_past_white(tmp_path):
    """The row compares the frame as read with its correction: the frame must not be
    corrected in place (else before and after are one array and nothing is ever new white)."""
    from pathlib import Path

    from benchmarks.real_frames import _row
    from vigproc.core.plausible import Rules
    from vigproc.pipeline.processor import Processor, Settings

    profile = Path(__file__).resolve().parents[1] / "profiles" / "examples" / "sony-rx100-10.4mm-f1.8.json"
    h, w = 320, 480
    yy, xx = np.mgrid[0:h, 0:w]
    corner = np.hypot((yy - h / 2) / (h / 2), (xx - w / 2) / (w / 2)) > 1.1
    img = np.full((h, w, 3), 0.3, np.float32)
    img[corner] = 0.8  # bright corners: the profile's gain there (up to 2.3) pushes them past white
    path = tmp_path / "bright corners.jpg"
    write_image(path, img, format="jpeg", bit_depth="uint8", transfer="srgb", quality=95)
    settings = Settings(mode="correct", profile=str(profile), in_camera="ignore")
    with Processor(settings, plausibility=False) as proc:
        row = _row(path, proc, Rules())
    assert row.applied
    assert 0.5 * corner.mean() < row.new_white <= corner.mean() + 0.01


def test_part_a_prior_holds_no_calibration_of_the_lens_measured():
    """The default estimate of part (a) takes its prior from lensfun's family without the
    measured lens (the shipped family holds its calibrations); inside the block the
    pipeline's estimate is the one given that family, outside it the shipped one's."""
    from vigproc.core.estimate import estimate_checked
    from vigproc.core.family_fit import LensHint
    from vigproc.core.lensfamily import profile_family, shipped_family_replaced
    from vigproc.stores.lensfun import lensfun_family, load_lenses

    truth, _ = rfl.lensfun_truth(_key())
    found = [(None, _key(), truth, {}, None)]
    fam = rfl.without_lenses(found)
    everyone = lensfun_family(n_components=fam.n_components)
    maker, model = truth.lens.split(" / ", 1)
    (lens,) = [lz for lz in load_lenses() if (lz.maker, lz.model) == (maker, model)]
    assert fam.lenses == everyone.lenses - 1
    assert 0 < everyone.coefficients.shape[0] - fam.coefficients.shape[0] <= len(lens.vignetting)
    assert fam.n_components == profile_family().n_components

    shipped = profile_family()
    img = coloured_scene(240, 320, seed=5)
    h, w = img.shape[:2]
    yy, xx = np.mgrid[0:h, 0:w]
    r2 = ((yy - (h - 1) / 2) ** 2 + (xx - (w - 1) / 2) ** 2) / (((h - 1) / 2) ** 2 + ((w - 1) / 2) ** 2)
    img = (img * pa_poly(r2, *truth.k)[..., None]).astype(np.float64)
    hint = LensHint(34.0, 1.8)
    with shipped_family_replaced(fam):
        assert profile_family() is fam
        inside = estimate_checked(img, "default", hint=hint)
    assert profile_family() is shipped
    given = estimate_checked(img, "default", hint=hint, family=fam)
    outside = estimate_checked(img, "default", hint=hint)
    field = lambda m: (m.candidate or m).log_field((24, 32))  # noqa: E731
    assert np.allclose(field(inside), field(given))
    assert not np.allclose(field(inside), field(outside))


@needs_exiftool
def test_ambiguity_shrink_scores_the_experiment_and_then_restores_the_default(tmp_path, monkeypatch):
    import vigproc.core.ambiguity as A
    import vigproc.core.estimate as E

    frames = tmp_path / "frames"
    frames.mkdir()
    _lens_jpeg(frames / "P1.jpg", _key())
    calls = []
    real = A.estimate_shrunk

    def counted(*a, **kw):
        calls.append(kw.get("base"))
        return real(*a, **kw)

    monkeypatch.setattr(A, "estimate_shrunk", counted)
    orig = E.estimate_default
    s = rfl.run_lensfun([frames / "P1.jpg"], shrink="scene")
    assert len(s.rows) == 1 and math.isfinite(s.rows[0].candidate_error_ev)
    # the pipeline's estimate went through the experiment, told the real default as its base
    assert calls and all(b is orig for b in calls)
    assert E.estimate_default is orig


def test_the_truths_corner_is_where_profile_lensfun_puts_it():
    # a D70 (lensfun 1.525) behind its DX kit lens, calibrated at 1.528: one sensor, rho = 1,
    # as --profile lensfun applies it; a full-frame D800 frame behind it lies past the
    # calibration (rho = 1.53), which the truth says (_truth_holds refuses it)
    from vigproc.io.exif import LensKey

    lens = "af-s dx zoom-nikkor 18-70mm f/3.5-4.5g if-ed"
    d70, _ = rfl.lensfun_truth(LensKey(make="nikon corporation", model="nikon d70", lens=lens, focal_mm=18.0,
                                       fnumber=3.5, focal_35mm=27.0))
    assert d70.corner_rho == 1.0
    d800, _ = rfl.lensfun_truth(LensKey(make="nikon corporation", model="nikon d800", lens=lens, focal_mm=18.0,
                                        fnumber=3.5, focal_35mm=18.0))
    assert d800.corner_rho == pytest.approx(1.528)
