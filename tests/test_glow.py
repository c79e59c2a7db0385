"""The light-source glow test (vigproc.core.glow) and the default estimator's use of it."""

from __future__ import annotations

import math

import numpy as np

from vigproc.core.estimate import OffCentreRule, estimate_default
from vigproc.core.family_fit import FamilySettings, corner_radius, luminance_copy
from vigproc.core.glow import GlowTest, glow_advantage
from vigproc.core.lensfamily import profile_family
from vigproc.stores.lensfun import pa_field

from conftest import textured

H, W = 320, 480


def _rho() -> np.ndarray:
    y, x = np.mgrid[0:H, 0:W]
    return np.hypot(x - (W - 1) / 2, y - (H - 1) / 2) / corner_radius(W, H)


def _glow(k: float = -1.5, rho0: float = 0.25) -> np.ndarray:
    """The light scattered around a source at the frame centre: k·log(ρ² + ρ0²)."""
    g = k * np.log(_rho() ** 2 + rho0**2)
    return np.exp(g - g.max())


def _advantage(img: np.ndarray) -> float:
    copy = luminance_copy(img, FamilySettings(), None)
    return glow_advantage(copy, W, H, profile_family())


def test_a_light_source_glow_is_told_from_a_lens():
    lens = pa_field((H, W), -0.55, 0.05, 0.0)
    for seed in range(2):
        scene = textured(H, W, seed=seed, contrast=0.1)
        glowing, vignetted = _advantage(scene * _glow()), _advantage(scene * lens)
        assert glowing > GlowTest().margin > vignetted, (seed, glowing, vignetted)


def test_lyus_strong_fields_are_not_taken_for_a_glow():
    # the Kang-Weiss illumination of a short focal length has a glow's form near the
    # centre, but its fall-off keeps steepening to the corners (module doc)
    from benchmarks.synthetic import table1_model

    field = table1_model(1).field((H, W))
    assert _advantage(textured(H, W, seed=3, contrast=0.1) * field) < GlowTest().margin


def test_the_default_leaves_a_glow_alone_and_says_so(caplog):
    img = textured(H, W, seed=1, contrast=0.1) * _glow()
    with caplog.at_level("INFO", logger="vigproc.core.estimate"):
        m = estimate_default(img)
    assert m.is_identity and m.quality.fallback and m.candidate is not None
    assert "glow" in caplog.text
    # without the test the same frame is corrected: the glow test made the decision
    untested = estimate_default(img, rule=OffCentreRule(glow=GlowTest(min_ev=math.inf)))
    assert not untested.is_identity
    # a lens's fall-off on the same scene is corrected
    lens = estimate_default(textured(H, W, seed=1, contrast=0.1) * pa_field((H, W), -0.55, 0.05, 0.0))
    assert not lens.is_identity


def test_a_copy_without_pairs_has_no_advantage():
    copy = luminance_copy(textured(H, W), FamilySettings(), None)
    empty = copy._replace(valid=np.zeros_like(copy.valid))
    assert math.isnan(glow_advantage(empty, W, H, profile_family()))


def test_the_cli_and_the_sidecar_say_a_glow_was_left_alone(tmp_path):
    import json

    from vigproc.io.images import write_image

    frame = textured(H, W, seed=1, contrast=0.1) * _glow()
    src = tmp_path / "sunset.tif"
    write_image(src, np.repeat(frame[..., None], 3, axis=2).astype(np.float32), bit_depth="float")

    from conftest import run_cli as vigproc  # in this process: the messages, not the process, are tested

    est = vigproc("estimate", src)
    assert est.returncode == 0, est.stderr
    assert "NOT applied (the fall-off is shaped like the light around a source" in est.stdout
    out = tmp_path / "out"
    cor = vigproc("correct", src, "-o", out)
    assert cor.returncode == 0, cor.stderr
    [side] = out.glob("*.vigproc.json")
    assert json.loads(side.read_text())["not_applied"].startswith("the fall-off is shaped like the light around")
