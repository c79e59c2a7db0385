import json
import math

import numpy as np
import pytest

from vigproc.errors import ModelError
from vigproc.core.model import VignettingModel


def table2():
    return VignettingModel(480, 320, center=(-80.0, -60.0), p=(1e-4, 0.5e-4, 1.5e-4), alpha=(0.02, 0.01, 0, 0, 0, 0, 0))


def test_field_matches_formula():
    m = table2()
    phi = m.field()
    y, x = 10, 400
    dx = x - (480 - 1) / 2 - m.center[0]
    dy = y - (320 - 1) / 2 - m.center[1]
    r2 = 1e-4 * dx * dx + 2 * 0.5e-4 * dx * dy + 1.5e-4 * dy * dy
    r = np.sqrt(r2)
    expected = (1 + r2 / 4) ** -2 * (1 - 0.02 * r - 0.01 * r2)
    assert phi[y, x] == pytest.approx(expected, rel=1e-12)
    # 1.0 at the centre, smaller everywhere else
    assert phi.max() <= 1.0 and phi.max() > 0.999


def test_json_round_trip_and_rescale():
    m = table2()
    assert VignettingModel.from_json(m.to_json()) == m
    big = m.rescale(1920, 1280)
    assert big.center == (-320.0, -240.0)
    # the same frame at 4x: sampling the big field at the small grid's pixel centres
    small_again = big.rescale(480, 320)
    np.testing.assert_allclose(small_again.field(), m.field(), atol=1e-12)
    np.testing.assert_allclose(m.field((640, 960))[1::2, 1::2].mean(), m.field().mean(), rtol=0.01)


def test_quality_with_unknown_figures_is_strict_json():
    import math
    from dataclasses import replace

    from vigproc.core.model import FitQuality

    m = replace(table2(), quality=FitQuality(field_sigma_ev=math.nan, snr=math.inf, objective=math.nan))
    text = json.dumps(m.to_dict(), allow_nan=False)  # raises on NaN/Inf
    back = VignettingModel.from_dict(json.loads(text)).quality
    assert math.isnan(back.field_sigma_ev) and math.isnan(back.objective) and back.snr == math.inf


def test_rescale_refuses_aspect_change():
    with pytest.raises(ModelError, match="aspect"):
        table2().rescale(480, 480)


@pytest.mark.parametrize("bad", [
    {"p": [1, 2, 1]},                       # indefinite P
    {"p": [float("nan"), 0, 1]},
    {"alpha": [0.1] * 6},                   # wrong length
    {"center": ["a", 0]},
])
def test_absurd_values_are_rejected(bad):
    d = table2().to_dict()
    d.update(bad)
    with pytest.raises(ModelError):
        VignettingModel.from_json(json.dumps(d))


def test_field_refuses_model_that_blacks_out_the_frame():
    m = VignettingModel(100, 100, p=(1e-3, 0, 1e-3), alpha=(0.9, 0, 0, 0, 0, 0, 0))
    with pytest.raises(ModelError, match="geometric factor"):
        m.field()


def test_identity_is_flat():
    m = VignettingModel.identity(64, 48)
    assert m.is_identity
    assert np.all(m.field() == 1.0)


def test_log_field_at_points_matches_the_grid_kernel():
    m = table2()
    grid = m.log_field()
    ys, xs = np.mgrid[0:320:37, 0:480:41]
    pts = m.log_field_at(xs - (480 - 1) / 2, ys - (320 - 1) / 2)
    np.testing.assert_allclose(pts, grid[ys, xs], rtol=1e-12, atol=1e-12)
    with pytest.raises(ModelError, match="geometric factor"):
        VignettingModel(100, 100, p=(1e-3, 0, 1e-3), alpha=(0.9, 0, 0, 0, 0, 0, 0)).log_field_at(
            np.array([45.0]), np.array([45.0]))


# --------------------------------------------------------- input validation
def _with(**changes):
    d = table2().to_dict()
    d.update(changes)
    return d


@pytest.mark.parametrize("key,value,message", [
    ("center", "12", "center"),                 # was read as (1.0, 2.0)
    ("alpha", "0000000", "alpha"),              # was read as seven zeros
    ("p", "000", "p must be"),
    ("center", [True, 0], "center"),            # bool is not a number
    ("center", [10**400, 0], "center"),         # was OverflowError
    ("center", {"x": 0, "y": 0}, "center"),
])
def test_from_dict_refuses_parameters_that_are_not_lists_of_numbers(key, value, message):
    with pytest.raises(ModelError, match=message):
        VignettingModel.from_dict(_with(**{key: value}))


@pytest.mark.parametrize("quality,message", [
    ({"fallback": "false"}, "fallback"),        # was stored as a truthy string
    ({"fallback": 0}, "fallback"),
    ({"confidence": "high"}, "confidence"),
    ({"snr": True}, "snr"),
    ({"seconds": 10**400}, "seconds"),
    ({"iterations": 2.5}, "iterations"),
    ({"iterations": "3"}, "iterations"),
    ({"iterations": -1}, "iterations"),
    ({"reason": 3}, "reason"),
    ({"conf": 1.0}, "unknown quality field"),  # was TypeError from FitQuality(**q)
    ([["confidence", 1.0]], "quality"),         # was accepted through dict(q)
])
def test_from_dict_type_checks_quality(quality, message):
    with pytest.raises(ModelError, match=message):
        VignettingModel.from_dict(_with(quality=quality))


def test_quality_round_trip_keeps_types_and_null_figures():
    from dataclasses import replace

    from vigproc.core.model import FitQuality

    q = FitQuality(confidence=0.25, snr=math.inf, fallback=True, objective=math.nan, iterations=12, seconds=0.5,
                   reason="a glow")
    m = replace(table2(), quality=q)
    back = VignettingModel.from_json(m.to_json(allow_nan=False)).quality
    assert back.fallback is True and back.iterations == 12 and back.snr == math.inf and math.isnan(back.objective)
    assert back.reason == "a glow"
    # a model written before quality had a reason reads as none given
    assert VignettingModel.from_dict(_with(quality={"fallback": True})).quality.reason == ""
    # an integral float (how some JSON writers put counts) is a count
    d = _with(quality={"iterations": 12.0})
    assert VignettingModel.from_dict(d).quality.iterations == 12


@pytest.mark.parametrize("cov,message", [
    (-np.eye(12), "positive semi-definite"),
    (np.diag([1.0] * 11 + [-1e-12]), "negative variance"),   # tiny, but a variance is never negative
    (np.eye(12) + np.triu(np.ones((12, 12)), 1), "symmetric"),
    (1.5 * np.eye(12) - 0.5 * np.ones((12, 12)), "positive semi-definite"),  # correlation -0.5 everywhere
    ([["1"] * 12] * 12, "covariance"),
    ([[1.0] * 12] * 11 + [[1.0] * 11], "covariance"),        # ragged
])
def test_from_dict_refuses_covariance_that_is_not_symmetric_psd(cov, message):
    cov = cov.tolist() if isinstance(cov, np.ndarray) else cov
    with pytest.raises(ModelError, match=message):
        VignettingModel.from_dict(_with(covariance=cov))


def test_from_dict_tolerates_rounding_in_a_covariance():
    rng = np.random.default_rng(1)
    a = rng.standard_normal((12, 12))
    c = a @ np.diag([1e4] * 2 + [1e-12] * 3 + [1e-2] * 7) @ a.T  # pixel units: widely spread scales
    c[0, 1] *= 1 + 1e-12  # asymmetric in the last bits
    m = VignettingModel.from_dict(_with(covariance=c.tolist()))
    assert VignettingModel.from_json(m.to_json()) == m
    # singular (a fixed parameter) is still semi-definite
    c0 = np.diag([1.0] * 11 + [0.0])
    assert VignettingModel.from_dict(_with(covariance=c0.tolist())).covariance[11][11] == 0.0


def test_candidate_must_match_the_frame_and_not_nest():
    fit = table2()
    m = VignettingModel.identity(480, 320, candidate=fit)
    assert VignettingModel.from_json(m.to_json()).candidate == fit
    with pytest.raises(ModelError, match="candidate"):
        VignettingModel.from_dict(_with(candidate=fit.rescale(960, 640).to_dict()))
    with pytest.raises(ModelError, match="candidate"):
        VignettingModel.identity(480, 320, candidate=fit.rescale(960, 640))
    with pytest.raises(ModelError, match="candidate"):
        VignettingModel.from_dict(_with(candidate=m.to_dict()))
    deep = None  # a 3000-deep chain was a RecursionError
    for _ in range(3000):
        deep = {"width": 4, "height": 4, "center": [0, 0], "p": [0, 0, 0], "alpha": [0] * 7, "candidate": deep}
    with pytest.raises(ModelError, match="candidate of its own"):
        VignettingModel.from_dict(deep)


@pytest.mark.parametrize("text,message", [
    ('{"width": 1e999, "height": 320}', "width"),           # was OverflowError
    ('{"width": 64.5, "height": 320}', "width"),
    ('{"width": "64", "height": 320}', "width"),
    ('{"width": true, "height": 320}', "width"),
    ('{"width": 64, "height": 0}', "height"),
    ('{"width": 64, "height": NaN}', "height"),
])
def test_from_json_refuses_bad_frame_size(text, message):
    d = json.loads(text)
    full = _with(**d)
    with pytest.raises(ModelError, match=message):
        VignettingModel.from_json(json.dumps(full))


def test_from_json_names_the_bad_size_before_missing_fields():
    with pytest.raises(ModelError, match="width must be a positive integer, got inf"):  # was OverflowError
        VignettingModel.from_json('{"width": 1e999}')


def test_from_json_accepts_integral_float_size():
    m = VignettingModel.from_dict(_with(width=480.0, height=320.0))
    assert m == table2() and type(m.width) is int


@pytest.mark.parametrize("text", [None, 42, b"\xff\xfe{"])
def test_from_json_refuses_what_is_not_json_text(text):
    with pytest.raises(ModelError):  # None was TypeError, undecodable bytes UnicodeDecodeError
        VignettingModel.from_json(text)


@pytest.mark.parametrize("w,h", [(64.7, 48.5), (math.inf, math.inf), (None, None), ("64", "48"), (True, True),
                                 (0, 0), (-64, -48), (10**400, 10**400)],
                         ids=["fraction", "inf", "None", "str", "bool", "zero", "negative", "huge"])
def test_rescale_requires_positive_integer_sizes(w, h):
    with pytest.raises(ModelError, match="width|height"):
        VignettingModel.identity(64, 48).rescale(w, h)


def test_rescale_accepts_integral_floats():
    assert table2().rescale(960.0, 640.0) == table2().rescale(960, 640)


@pytest.mark.parametrize("shape", [(47 / 2, 63 / 2), (48,), "ab", (48, 64, 3), 48, (0, 64), (math.nan, 64),
                                   (True, 64)])
def test_field_shape_must_be_two_positive_integers(shape):
    m = VignettingModel(64, 48, p=(1e-4, 0, 1e-4))
    with pytest.raises(ModelError, match="shape"):
        m.field(shape)
    with pytest.raises(ModelError, match="shape"):
        m.log_field(shape)


def test_field_accepts_integral_float_and_numpy_shapes():
    m = table2()
    np.testing.assert_array_equal(m.field((320.0, 480.0)), m.field())
    np.testing.assert_array_equal(m.field(np.array([160, 240])), m.field((160, 240)))


def test_models_written_before_the_package_move_still_load():
    # Persisted schema names are a file format, not module paths: a model JSON as
    # every earlier release wrote it must load (the move to vigproc.core once
    # rewrote the name the reader expects).
    text = ('{"schema": "vigproc.model/1", "width": 480, "height": 320, "center": [-80.0, -60.0], '
            '"p": [1e-4, 5e-5, 1.5e-4], "alpha": [0.02, 0.01, 0, 0, 0, 0, 0]}')
    m = VignettingModel.from_json(text)
    assert m.center == (-80.0, -60.0) and json.loads(m.to_json())["schema"] == "vigproc.model/1"
