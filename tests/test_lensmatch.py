"""Tests of the lens-family mismatch test (vigproc.forensics.lensmatch) and of ``vigproc check``'s
default verdicts, which come from it."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from vigproc.forensics.calibration_frames import lens_classes
from vigproc.io.exif import LensKey
from vigproc.core.family_fit import profile_to_model
from vigproc.forensics.check import forensic_check, load_calibration, pool_verdicts
from vigproc.core.lensfamily import default_family
from vigproc.forensics.lensmatch import (
    MatchCalibration,
    MatchCalibrationError,
    default_match_calibration,
    family_fingerprint,
    fit_match_calibration,
    whiten,
    luminance_family_fit,
    pooled_d2,
    pooled_null,
    reference_coefficients,
)

from conftest import textured

W, H = 240, 160


@pytest.fixture(scope="module")
def classes():
    # [4] Sigma 105 mm at f/1.4 vignettes strongly (0.7 EV RMS), [5] the same at f/2.8 mildly
    return lens_classes(3)


def key_of(c) -> LensKey:
    return LensKey(make=c.maker, model="test camera", lens=c.model, focal_mm=c.focal, fnumber=c.aperture)


@pytest.fixture(scope="module")
def calibration(classes):
    """The scenes' scatter of the data-only fit on synthetic textures × no field and two
    lenses other than the tested ones (enough rows for p < 0.01)."""
    fam = default_family()
    # each lens's model and reference once (a least-squares fit each), not once per scene
    lenses = [(1.0, reference_coefficients(_identity(), W, H, fam))] + \
        [(c.field(H, W), reference_coefficients(c.true_model(W, H), W, H, fam)) for c in classes[:2]]
    rows, groups = [], []
    for i in range(40):
        base = textured(H, W, seed=300 + i, contrast=0.15)
        for field, reference in lenses:
            fc = luminance_family_fit(base * field, fam)
            rows.append(fc.coefficients - reference)
            groups.append(i)
    return fit_match_calibration(np.array(rows), groups, fam, source="test")


def _identity():
    from vigproc.core.model import VignettingModel

    return VignettingModel.identity(W, H)


def test_reference_coefficients_recover_a_family_member():
    fam = default_family()
    c = np.array([-3.0, 1.5])
    model, _ = profile_to_model(fam.mean + c @ fam.components, fam.radii, W, H)
    assert np.allclose(reference_coefficients(model, W, H, fam), c, atol=0.05)


def test_frame_fit_is_equivariant():
    # a family field multiplied onto a frame moves the data-only fit by its coefficients
    fam = default_family()
    img = textured(H, W, seed=3, contrast=0.15)
    c = np.array([-4.0, 1.0])
    model, _ = profile_to_model(fam.mean + c @ fam.components, fam.radii, W, H)
    c0 = luminance_family_fit(img, fam).coefficients
    c1 = luminance_family_fit(img * np.exp(model.log_field((H, W))), fam).coefficients
    c_id = reference_coefficients(_identity(), W, H, fam)
    assert np.allclose(c1 - c0, c - c_id, atol=0.3)


def test_calibration_p_values_and_files(tmp_path):
    rng = np.random.default_rng(0)
    fam = default_family()
    r = rng.normal(size=(240, 2)) * [2.0, 0.7] + [0.1, -0.1]
    cal = fit_match_calibration(r, np.repeat(np.arange(60), 4), fam, source="gaussian")
    null = cal.null_d2(1)
    assert 1.5 < null.mean() < 2.6  # held-out whitened 2-d Gaussian: chi2(2)
    assert 1.3 < cal.null_d2(5).mean() < 4.5  # n |median|^2: about pi/2 chi2(2)
    ps = [cal.p_value(d) for d in (0.0, 2.0, 6.0, 1e9)]
    assert ps[0] == pytest.approx(1.0) and all(a >= b for a, b in zip(ps, ps[1:]))
    assert ps[-1] == pytest.approx(1.0 / (null.size + 1))
    cal.save(tmp_path / "c.json")
    back = load_calibration(tmp_path / "c.json")
    assert isinstance(back, MatchCalibration) and back.family == family_fingerprint(fam)
    assert np.allclose(back.null_d2(1), null, atol=1e-3)
    with pytest.raises(MatchCalibrationError):
        fit_match_calibration(r[:8], np.arange(8), fam)  # too few photographs
    bad = cal.to_dict() | {"family": [2.0, 0.0, 0.0, 0.0, 0.0]}
    with pytest.raises(MatchCalibrationError):
        MatchCalibration.from_dict(bad).check_family(fam)


def test_pooled_false_alarms_hold_when_the_centre_is_estimated():
    # Frames of new photographs against a calibration of 25 others: the calibration's
    # centre is off by its sampling error, which all five frames of a set share. Without
    # that error in the 5-frame null, 1.7 % of genuine sets fall below alpha = 0.01.
    fam = default_family()
    rng = np.random.default_rng(3)
    alarms = []
    for _ in range(60):
        cal = fit_match_calibration(rng.normal(size=(25 * 4, 2)), np.repeat(np.arange(25), 4), fam)
        null = cal.null_d2(5)
        for _ in range(40):
            z = np.array([whiten(r, cal) for r in rng.normal(size=(5, 2))])
            k = null.size - np.searchsorted(null, pooled_d2(z))
            alarms.append((k + 1) / (null.size + 1) < 0.01)
    assert np.mean(alarms) <= 0.011, np.mean(alarms)  # measured: 0.005 with it, 0.017 without


def test_pooled_statistic_is_a_median():
    z = np.array([[0.1, 0.0], [0.2, -0.1], [0.0, 0.1], [0.1, 0.0], [40.0, 40.0]])
    assert pooled_d2(z) < 0.2  # one fooled frame moves the median by one rank, not by its error
    assert pooled_d2(z[:1]) == pytest.approx(0.01)


def _pooled_null_set_by_set(z, g, n, statistic, seed, draws, shift_spread):
    """pooled_null's definition, one set at a time: the stream its p-values were made with."""
    uniq = np.unique(g)
    by_group = [np.flatnonzero(g == u) for u in uniq]
    rng, shifts = np.random.default_rng(seed), np.random.default_rng(seed + 1)
    out = []
    for _ in range(draws):
        picks = rng.choice(uniq.size, n, replace=False)
        sample = z[[by_group[p][rng.integers(by_group[p].size)] for p in picks]]
        if shift_spread > 0:
            sample = sample + shifts.normal(0.0, shift_spread, sample.shape[1])
        out.append(statistic(sample))
    return np.sort(out)


@pytest.mark.parametrize("n, shift_spread", [(2, 0.0), (5, 0.3), (8, 0.1)])
def test_pooled_null_is_the_set_by_set_null_bit_for_bit(n, shift_spread):
    # the sets are drawn in one stack: the same draws and the same statistics as one
    # set at a time (uneven photographs, unsorted groups), so shipped p-values stay put
    from vigproc.forensics.rings import _mean_d2

    rng = np.random.default_rng(n)
    g = np.repeat(rng.permutation(90)[:30], rng.integers(1, 6, 30))
    rng.shuffle(g)
    z = rng.normal(size=(g.size, 3))
    for stat in (pooled_d2, _mean_d2):
        got = pooled_null(z, g, n, stat, seed=11 * n, draws=300, shift_spread=shift_spread)
        want = _pooled_null_set_by_set(z, g, n, stat, 11 * n, 300, shift_spread)
        assert got.shape == (300,) and np.array_equal(got, want)
        stack = z[rng.integers(0, g.size, (7, n))]
        assert np.array_equal(stat(stack), [stat(s) for s in stack])


@pytest.mark.parametrize("photos, n, most", [(30, 30, 1), (7, 2, 1), (200, 5, 6), (10_000, 9, 3), (10_001, 4, 2)])
def test_the_draw_kernel_gives_numpys_choice_and_integers(photos, n, most):
    # the kernel follows NumPy's Generator.choice (Floyd, then a shuffle) and integers
    # (Lemire) on the raw stream; above 10 000 photographs NumPy's own calls are used
    from vigproc.forensics.lensmatch import _distinct_group_rows

    rs = np.random.default_rng(photos + n)
    sizes = rs.integers(1, most + 1, photos).astype(np.int64)
    first = np.concatenate([[0], np.cumsum(sizes)[:-1]]).astype(np.int64)
    members = rs.permutation(int(sizes.sum())).astype(np.int64)
    rng = np.random.default_rng(7)
    want = np.empty((150, n), np.int64)
    for i in range(150):
        picks = rng.choice(photos, n, replace=False)
        want[i] = members[first[picks] + rng.integers(sizes[picks])]
    assert np.array_equal(_distinct_group_rows(sizes, first, members, n, 7, 150), want)


def test_shipped_calibration_is_for_the_shipped_family():
    cal = default_match_calibration()
    cal.check_family(default_family())
    assert cal.alpha == 0.01 and cal.n_images >= 40 and "forensics-clean" in cal.source


def test_mismatched_lens_is_caught_and_the_true_one_is_not(classes, calibration):
    strong, mild = classes[4], classes[5]
    img = textured(H, W, seed=11, contrast=0.15) * strong.field(H, W)
    right = forensic_check(img, key_of(strong), calibration=calibration)
    wrong = forensic_check(img, key_of(mild), calibration=calibration)
    assert right.test == wrong.test == "lens-family"
    assert right.verdict == "consistent" and wrong.verdict == "inconsistent"
    assert wrong.score > 10 * right.score
    # the verdict names its reference and its false-alarm probability
    assert "lensfun's calibration of" in wrong.reason and f"{wrong.p_false_alarm:.3g}" in wrong.reason
    assert wrong.to_dict()["test"] == "lens-family" and len(wrong.to_dict()["whitened"]) == 2
    # the report's evidence: ring fall-offs of the fit against what frames of the lens give
    e = wrong.evidence
    assert e.falloff_diff_ev[-1] < 0  # more fall-off than the mild lens gives


def test_pooled_family_verdicts(classes, calibration):
    strong, mild = classes[4], classes[5]
    frames = [textured(H, W, seed=20 + i, contrast=0.15) * strong.field(H, W) for i in range(5)]
    vs = [forensic_check(f, key_of(mild), calibration=calibration) for f in frames]
    pv = pool_verdicts(vs, calibration=calibration)
    assert pv.test == "lens-family" and pv.n_frames == 5 and pv.verdict == "inconsistent"
    z = np.array([v.whitened for v in vs])
    assert pv.score == pytest.approx(5 * float(np.median(z, axis=0) @ np.median(z, axis=0)))
    ok = pool_verdicts([forensic_check(f, key_of(strong), calibration=calibration) for f in frames],
                       calibration=calibration)
    assert ok.verdict == "consistent"


def test_a_fit_no_model_can_hold_is_insufficient_signal(classes, calibration, monkeypatch):
    """The data-only fit of a frame without usable structure can land on coefficients no
    lens has, whose model would black out part of the frame: that is no evidence (a
    camera JPEG made `vigproc check` fail with exit 6 where estimate and correct went on)."""
    import vigproc.forensics.verdicts as verdicts  # where the check looks the lens-match fit up
    from vigproc.core.family_fit import FrameCoefficients

    monkeypatch.setattr(verdicts, "luminance_family_fit", lambda lum, fam=None, settings=None, colour=None: FrameCoefficients(
        np.array([5e3, -4e3]), np.eye(2), 1000))
    img = textured(H, W, seed=6, contrast=0.15) * classes[4].field(H, W)
    v = forensic_check(img, key_of(classes[4]), calibration=calibration)
    assert v.verdict == "insufficient-signal", v.reason


def test_unknown_lens_and_explicit_method(classes, calibration):
    from vigproc.forensics.check import ForensicsError

    img = textured(H, W, seed=5, contrast=0.15)
    assert forensic_check(img, None, calibration=calibration).verdict == "unknown-lens"
    with pytest.raises(ForensicsError):
        forensic_check(img, key_of(classes[4]), method="robust", calibration=calibration)


def test_cli_check_json_says_which_test(tmp_path, classes):
    from vigproc.frontends.cli import main
    from vigproc.io.images import write_image

    img = textured(H, W, seed=7, contrast=0.15) * classes[4].field(H, W)
    f = tmp_path / "frame.tif"
    write_image(f, np.repeat(img[..., None], 3, axis=2), bit_depth="uint16")
    import contextlib
    import io

    out = io.StringIO()
    with contextlib.redirect_stdout(out):
        code = main(["check", str(f), "--no-store", "--json"])
    d = json.loads(out.getvalue())
    assert d["results"][0]["test"] == "lens-family" and d["results"][0]["verdict"] == "unknown-lens"
    assert code == 21
    assert math.isfinite(d["results"][0]["evidence"]["falloff_ev"][-1])


def test_the_clean_forensics_bench_refuses_folds_too_small_for_a_set():
    # bench forensics-clean --folds K: every fold must hold a multi-frame set of bases
    from benchmarks import forensics_clean as F

    bases = [np.ones((32, 48))] * 20
    for folds in (1, 5):
        with pytest.raises(ValueError, match="folds must be within 2..4"):
            F.run(bases, frames=5, folds=folds)


def test_a_grey_frame_is_judged_by_the_scatter_of_grey_fits(classes, calibration, tmp_path):
    """A grey frame's fit has no colour to weigh its pairs by, so scenes scatter it more:
    its residual is whitened by Σ × ``grey_inflate`` (a colour frame's by Σ). The factor
    is kept in the calibration's file; a file without it reads as 1."""
    from dataclasses import replace

    strong, mild = classes[4], classes[5]
    img = textured(H, W, seed=11, contrast=0.15) * mild.field(H, W)
    plain = forensic_check(img, key_of(strong), calibration=calibration)
    wider = forensic_check(img, key_of(strong), calibration=replace(calibration, grey_inflate=4.0))
    assert wider.score == pytest.approx(plain.score / 4.0, rel=1e-9)
    rgb = img[..., None] * np.array([0.9, 1.0, 0.7])  # channels alike: the same fit, but a colour frame
    colour = forensic_check(rgb, key_of(strong), calibration=replace(calibration, grey_inflate=4.0))
    assert colour.score == pytest.approx(plain.score, rel=1e-6)
    assert wider.evidence.grey is True and colour.evidence.grey is False
    # the check against the file's own calibration reads the same: a grey frame's Σ is wider
    from vigproc.forensics.check import check_embedded

    inflated = replace(calibration, grey_inflate=4.0)
    emb = [check_embedded(wider.estimate, mild.true_model(W, H), calibration=inflated, grey=g) for g in (False, True)]
    assert emb[1].score == pytest.approx(emb[0].score / 4.0, rel=1e-9) and emb[1].evidence.grey
    cal = replace(calibration, grey_inflate=1.5)
    cal.save(tmp_path / "c.json")
    assert load_calibration(tmp_path / "c.json").grey_inflate == 1.5
    d = cal.to_dict()
    del d["grey_inflate"]
    assert MatchCalibration.from_dict(d).grey_inflate == 1.0
    with pytest.raises(MatchCalibrationError):
        replace(calibration, grey_inflate=0.0)
    assert default_match_calibration().grey_inflate > 1.0  # the shipped one was made on colour frames


def test_the_scene_gate_is_a_chi2_limit(tmp_path):
    """A calibration made with its frames' own coefficients sets the scene limit (the χ²
    quantile of SCENE_GATE_P); its null keeps every row. Old calibrations (no limit) load
    with the gate off."""
    from scipy.stats import chi2

    from vigproc.forensics.lensmatch import SCENE_GATE_P, scene_d2

    rng = np.random.default_rng(5)
    fam = default_family()
    r = rng.normal(size=(240, 2)) * [2.0, 0.7]
    m, _ = fam.prior()
    own = m[:2] + rng.normal(size=(240, 2)) * 0.3
    own[:12] += [80.0, 0.0]  # twelve frames no lens explains (a sunset's glow, say)
    groups = np.repeat(np.arange(60), 4)
    cal = fit_match_calibration(r, groups, fam, coefficients=own)
    plain = fit_match_calibration(r, groups, fam)
    assert plain.scene_limit is None and plain.scene_share is None
    assert cal.scene_limit == pytest.approx(chi2.isf(SCENE_GATE_P, 2))
    assert cal.scene_share == pytest.approx(12 / 240)  # measured on its own frames, not assumed
    scene = np.array([scene_d2(c, cal, fam) for c in own])
    assert np.all(scene[:12] > cal.scene_limit) and np.all(scene[12:] <= cal.scene_limit)
    assert np.array_equal(cal.null_d2(1), plain.null_d2(1))
    assert scene_d2(m[:2] + cal.mean_vector, cal, fam) == pytest.approx(0.0)
    far = m[:2] + cal.mean_vector + [10.0, 0.0]
    assert scene_d2(far, cal, fam, inflate=4.0) < scene_d2(far, cal, fam)
    cal.save(tmp_path / "c.json")
    back = load_calibration(tmp_path / "c.json")
    assert back.scene_limit == pytest.approx(cal.scene_limit, abs=1e-4) and back.scene_share == cal.scene_share
    old = {k: v for k, v in cal.to_dict().items() if k not in ("scene_limit", "scene_share")}
    assert "scene_limit" not in plain.to_dict() and MatchCalibration.from_dict(old).scene_limit is None
    for bad in ({"scene_limit": -1.0}, {"scene_limit": float("nan")}, {"scene_limit": 0.0}, {"scene_share": 1.5}):
        with pytest.raises(MatchCalibrationError):
            MatchCalibration.from_dict(cal.to_dict() | bad)
    with pytest.raises(MatchCalibrationError):
        fit_match_calibration(r, groups, fam, coefficients=own[:10])


def test_a_frame_no_lens_explains_is_left_undecided(classes, calibration):
    """A scene that brightens towards its corners fits as no lens does: the check leaves
    it undecided (and says why) rather than accuse the lens it claims; a frame of the lens
    is decided as before. Its numbers stay, so a pool of frames still counts it."""
    from dataclasses import replace

    from vigproc.forensics.lensmatch import SCENE_GATE_P
    from scipy.stats import chi2

    strong, mild = classes[4], classes[5]
    gated = replace(calibration, scene_limit=float(chi2.isf(SCENE_GATE_P, 2)), scene_share=0.023)
    yy, xx = np.mgrid[0:H, 0:W]
    rho2 = ((xx - (W - 1) / 2) ** 2 + (yy - (H - 1) / 2) ** 2) / ((W - 1) ** 2 + (H - 1) ** 2) * 4
    glow = textured(H, W, seed=12, contrast=0.15) * np.exp(1.5 * rho2)  # +2.2 EV at the corners
    v = forensic_check(glow, key_of(mild), calibration=gated)
    # labelled as what the numbers say (it was 'insufficient-signal' beside a strong fall-off)
    assert v.verdict == "unlike-any-lens" and "unlike any lens" in v.reason, v.reason
    assert not v.decided
    assert "2.3 % of the calibration's genuine frames" in v.reason  # the measured share, not the Gaussian one
    assert v.evidence.scene_d2 > gated.scene_limit and v.whitened is not None
    ungated = forensic_check(glow, key_of(mild), calibration=calibration)
    assert ungated.verdict == "inconsistent" and ungated.evidence.scene_limit is None
    lens = textured(H, W, seed=11, contrast=0.15) * strong.field(H, W)
    right = forensic_check(lens, key_of(strong), calibration=gated)
    wrong = forensic_check(lens, key_of(mild), calibration=gated)
    assert (right.verdict, wrong.verdict) == ("consistent", "inconsistent")
    assert right.evidence.scene_d2 <= gated.scene_limit
    pv = pool_verdicts([v, wrong, wrong], calibration=gated)
    assert pv.n_frames == 3
    # a set of such frames is pooled by its median and decided, as the benchmark counts it
    glows = [forensic_check(textured(H, W, seed=30 + i, contrast=0.15) * np.exp(1.5 * rho2), key_of(mild),
                         calibration=gated) for i in range(3)]
    assert all(g.verdict == "unlike-any-lens" for g in glows)
    assert pool_verdicts(glows, calibration=gated).verdict == "inconsistent"
    # an examiner's report shows the number and the limit
    from vigproc.forensics.report import ReportItem, report_html

    page = report_html([ReportItem("glow.png", v, np.repeat(glow[..., None], 3, axis=-1))])
    assert f"{v.evidence.scene_d2:.1f} (undecided above {gated.scene_limit:.1f})" in page
