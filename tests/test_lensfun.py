"""Tests for vigproc.stores.lensfun (lensfun pa vignetting data)."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from vigproc.errors import InvalidImageError, ModelError
from vigproc.stores.lensfun import (
    LensfunLens,
    PaVignetting,
    diverse_lenses,
    bundled_db_dir,
    interpolate_pa,
    load_lenses,
    pa_field,
)

KNOWN_MODEL = "Canon EF-S 10-22mm f/3.5-4.5 USM"  # slr-canon.xml


@pytest.fixture(scope="module")
def lenses() -> list[LensfunLens]:
    return load_lenses()


@pytest.fixture(scope="module")
def known(lenses: list[LensfunLens]) -> LensfunLens:
    matches = [lens for lens in lenses if lens.model == KNOWN_MODEL]
    assert len(matches) == 1
    return matches[0]


def _two_point_lens(k_wide: tuple[float, float, float], k_narrow: tuple[float, float, float]) -> LensfunLens:
    return LensfunLens(
        maker="Test",
        model="Test 50mm f/2",
        mounts=("Generic",),
        crop_factor=1.0,
        aspect_ratio=1.5,
        vignetting=(
            PaVignetting(50.0, 2.0, 1000.0, *k_wide),
            PaVignetting(50.0, 4.0, 1000.0, *k_narrow),
        ),
    )


# ---------------------------------------------------------------- loading


def test_bundled_db_is_found() -> None:
    assert len(list(bundled_db_dir().glob("*.xml"))) > 10


def test_at_least_20_lenses_with_vignetting(lenses: list[LensfunLens]) -> None:
    assert len(lenses) >= 20
    assert all(lens.vignetting for lens in lenses)
    keys = [(lens.maker, lens.model) for lens in lenses]
    assert keys == sorted(keys)
    for lens in lenses:
        assert lens.crop_factor > 0
        for v in lens.vignetting:
            assert v.focal > 0 and v.aperture > 0 and v.distance > 0
            assert all(math.isfinite(k) for k in (v.k1, v.k2, v.k3))


def test_untranslated_model_names_are_used(lenses: list[LensfunLens]) -> None:
    models = {lens.model for lens in lenses}
    assert "fixed lens" not in models and "festes Objektiv" not in models
    helios = [lens for lens in lenses if lens.model == "Helios-40 85mm f/1.5"]  # slr-ussr.xml, has ru names
    assert len(helios) == 1 and helios[0].maker == "KMZ"
    assert "DSC-RX100 & compatibles (Standard)" in models


def test_known_lens_round_trips(known: LensfunLens) -> None:
    assert known.maker == "Canon"
    assert known.mounts == ("Canon EF-S",)
    assert known.crop_factor == 1.613
    assert known.aspect_ratio is None
    assert known.focal_range == (10.0, 22.0)
    assert len(known.vignetting) == 70
    assert PaVignetting(10.0, 3.5, 1000.0, -2.1271, 2.6641, -1.2836) in known.vignetting
    assert PaVignetting(12.0, 4.0, 10.0, -0.5529, -0.2051, 0.2309) in known.vignetting
    assert known.widest_aperture(10.0) == 3.5
    assert known.widest_aperture(14.4) == 4.0
    assert known.widest_aperture(200.0) == 4.5


def test_aspect_ratio_is_parsed(lenses: list[LensfunLens]) -> None:
    iphone = [lens for lens in lenses if lens.model == "iPhone XS back camera 4.25mm f/1.8 & compatibles"]
    assert len(iphone) == 1
    assert iphone[0].aspect_ratio == pytest.approx(4.0 / 3.0, abs=1e-15)


def test_custom_xml_file(tmp_path: Path) -> None:
    xml = tmp_path / "custom.xml"
    xml.write_text(
        """<lensdatabase version="1">
    <lens>
        <maker>Zed</maker>
        <maker lang="de">Zett</maker>
        <model>Zed 35mm f/2</model>
        <model lang="en">Zed thirty-five</model>
        <mount>M1</mount>
        <mount>M2</mount>
        <cropfactor>1.5</cropfactor>
        <aspect-ratio>3:2</aspect-ratio>
        <calibration>
            <distortion model="ptlens" focal="30" a="0" b="0" c="0"/>
            <vignetting model="pa" focal="35" aperture="2" distance="1000" k1="-0.1" k2="0.2" k3="-0.3"/>
            <vignetting model="pa" focal="35" aperture="2" distance="1000" k1="-0.4" k2="0.5" k3="-0.6"/>
            <vignetting model="pa" focal="35" aperture="2.8" distance="10" k1="-0.25" k2="0" k3="0.125"/>
        </calibration>
    </lens>
    <lens>
        <maker>Alpha</maker>
        <model>Alpha no vignetting</model>
        <mount>M1</mount>
        <cropfactor>1</cropfactor>
        <calibration>
            <distortion model="ptlens" focal="30" a="0" b="0" c="0"/>
        </calibration>
    </lens>
</lensdatabase>
""",
        encoding="utf-8",
    )
    (lens,) = load_lenses([xml])
    assert (lens.maker, lens.model, lens.mounts) == ("Zed", "Zed 35mm f/2", ("M1", "M2"))
    assert lens.crop_factor == 1.5 and lens.aspect_ratio == 1.5
    # duplicated point: the later entry wins, as in lensfun's AddCalibVignetting
    assert lens.vignetting == (
        PaVignetting(35.0, 2.0, 1000.0, -0.4, 0.5, -0.6),
        PaVignetting(35.0, 2.8, 10.0, -0.25, 0.0, 0.125),
    )
    assert lens.focal_norm_range == (30.0, 35.0)
    assert load_lenses([tmp_path]) == [lens]


def test_missing_path_raises(tmp_path: Path) -> None:
    with pytest.raises(ModelError):
        load_lenses([tmp_path / "nope.xml"])


# ---------------------------------------------------------------- interpolation


def test_interpolation_at_calibrated_points(known: LensfunLens) -> None:
    for v in known.vignetting:
        got = interpolate_pa(known, v.focal, v.aperture, v.distance)
        assert (got.k1, got.k2, got.k3) == (v.k1, v.k2, v.k3)
        assert (got.focal, got.aperture, got.distance) == (v.focal, v.aperture, v.distance)


def test_interpolation_between_two_apertures_lies_between() -> None:
    lens = _two_point_lens((-0.8, 0.4, -0.2), (-0.3, 0.1, 0.05))
    got = interpolate_pa(lens, 50.0, 2.8)
    for k, lo, hi in zip((got.k1, got.k2, got.k3), (-0.8, 0.1, -0.2), (-0.3, 0.4, 0.05)):
        assert lo < k < hi
    # closer (in 4/N space) to f/4 than to f/2 -> nearer the f/4 values
    assert abs(got.k1 - (-0.3)) < abs(got.k1 - (-0.8))


def test_interpolation_is_a_weighted_mean_of_real_data(known: LensfunLens) -> None:
    # between f/8 (k1=-0.6733) and f/11 (k1=-0.6667) at 10 mm: every other
    # calibration point also gets some weight, so the result is only bound to
    # the hull of all calibrated values, and must differ from both neighbours.
    mid = interpolate_pa(known, 10.0, 9.5)
    for name in ("k1", "k2", "k3"):
        values = [getattr(v, name) for v in known.vignetting]
        assert min(values) <= getattr(mid, name) <= max(values)
    assert mid.k1 not in (-0.6733, -0.6667)
    assert abs(mid.k1 - (-0.67)) < 0.01


def test_interpolation_matches_lensfun_itself(lenses: list[LensfunLens]) -> None:
    lensfunpy = pytest.importorskip("lensfunpy")
    db = lensfunpy.Database()
    wanted = {KNOWN_MODEL, "Canon EF 16-35mm f/2.8L USM", "Sigma 8mm f/3.5 EX DG Circular"}
    ref = {lens.model: lens for lens in db.lenses if lens.model in wanted and lens.calib_vignetting}
    ours = {lens.model: lens for lens in lenses if lens.model in wanted}
    assert set(ref) == set(ours) == wanted
    rng = np.random.default_rng(1)
    for model in sorted(wanted):
        lo, hi = ours[model].focal_range
        for _ in range(10):
            # float32-representable inputs so both sides see the same point
            focal = float(np.float32(rng.uniform(lo, hi)))
            aperture = float(np.float32(rng.uniform(2.0, 16.0)))
            distance = float(np.float32(rng.choice([0.5, 2.0, 10.0, 1000.0])))
            expected = ref[model].interpolate_vignetting(focal, aperture, distance)
            got = interpolate_pa(ours[model], focal, aperture, distance)
            np.testing.assert_allclose((got.k1, got.k2, got.k3), expected.terms, rtol=1e-5, atol=1e-5)


def test_interpolation_errors(known: LensfunLens) -> None:
    empty = LensfunLens("X", "X 1mm", ("G",), 1.0, None, ())
    with pytest.raises(ModelError, match="no pa vignetting"):
        interpolate_pa(empty, 10.0, 4.0)
    with pytest.raises(ModelError):
        empty.focal_range
    with pytest.raises(ModelError, match="aperture"):
        interpolate_pa(known, 10.0, 0.0)
    with pytest.raises(ModelError, match="focal"):
        interpolate_pa(known, float("nan"), 4.0)
    with pytest.raises(ModelError, match="too far"):
        interpolate_pa(known, 60.0, 4.0)


# ---------------------------------------------------------------- pa field


@pytest.mark.parametrize("shape", [(101, 151), (64, 48), (7, 7), (1, 9)])
def test_pa_field_centre_corners_symmetry(shape: tuple[int, int]) -> None:
    k1, k2, k3 = -0.6724, 0.0578, 0.0247
    field = pa_field(shape, k1, k2, k3)
    assert field.shape == shape and field.dtype == np.float64
    corner = 1.0 + k1 + k2 + k3
    for y, x in ((0, 0), (0, -1), (-1, 0), (-1, -1)):
        assert abs(field[y, x] - corner) < 1e-12
    np.testing.assert_array_equal(field, field[::-1, :])
    np.testing.assert_array_equal(field, field[:, ::-1])
    h, w = shape
    if h % 2 and w % 2:
        assert field[h // 2, w // 2] == 1.0
    assert field.max() <= 1.0 and field.min() == pytest.approx(corner, abs=1e-12)


def test_pa_field_radius_is_half_diagonal() -> None:
    # k1 only: field = 1 + k1 r^2, so r^2 is recoverable exactly
    field = pa_field((5, 9), -1.0, 0.0, 0.0)
    r2 = 1.0 - field
    assert r2[2, 4] == 0.0
    assert r2[2, 0] == pytest.approx(16.0 / (16.0 + 4.0), abs=1e-15)  # (4 px)^2 / (4^2 + 2^2)
    assert r2[0, 4] == pytest.approx(4.0 / 20.0, abs=1e-15)


def test_pa_field_centre_offset() -> None:
    field = pa_field((41, 61), -0.5, 0.1, 0.0, center=(5.0, -3.0))
    assert field[20 - 3, 30 + 5] == 1.0
    assert np.unravel_index(np.argmax(field), field.shape) == (17, 35)
    assert field[0, 0] != pytest.approx(field[-1, -1])


def test_pa_field_matches_lensfun_modifier(known: LensfunLens) -> None:
    lensfunpy = pytest.importorskip("lensfunpy")
    db = lensfunpy.Database()
    (ref,) = [lens for lens in db.lenses if lens.model == KNOWN_MODEL]
    size = 65  # square: lensfun's and our pixel centre and half-diagonal coincide
    modifier = lensfunpy.Modifier(ref, ref.crop_factor, size, size)
    modifier.initialize(
        10.0, 3.5, 1000.0, pixel_format=np.float64, flags=lensfunpy.ModifyFlags.VIGNETTING, reverse=True
    )
    image = np.ones((size, size, 3))
    assert modifier.apply_color_modification(image)
    v = interpolate_pa(known, 10.0, 3.5, 1000.0)
    np.testing.assert_allclose(pa_field((size, size), v.k1, v.k2, v.k3), image[..., 0], atol=2e-5)


def test_pa_field_rejects_bad_input() -> None:
    with pytest.raises(InvalidImageError):
        pa_field((1, 1), -0.5, 0.0, 0.0)
    with pytest.raises(ModelError):
        pa_field((10, 10), float("inf"), 0.0, 0.0)


# ---------------------------------------------------------------- bench


def test_diverse_lenses_deterministic_and_distinct() -> None:
    first = diverse_lenses(20)
    second = diverse_lenses(20)
    assert first == second
    assert len(first) == 20
    assert len({(lens.maker, lens.model) for lens, _ in first}) == 20
    assert len({lens.maker for lens, _ in first}) >= 10
    for lens, entry in first:
        assert entry in lens.vignetting
        assert entry.focal == lens.focal_range[0]
        assert entry.aperture == lens.widest_aperture(entry.focal)
        at_point = [v.distance for v in lens.vignetting if (v.focal, v.aperture) == (entry.focal, entry.aperture)]
        assert entry.distance == max(at_point)
        assert entry.corner < 0.9
        field = pa_field((33, 49), entry.k1, entry.k2, entry.k3)
        assert 0.0 < field.min() and field.max() <= 1.0 + 1e-3


def test_diverse_lenses_too_many() -> None:
    with pytest.raises(ModelError, match="requested"):
        diverse_lenses(100_000)
