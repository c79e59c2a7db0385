import json

import numpy as np
import pytest

from vigproc.errors import ModelError
from vigproc.model import VignettingModel


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

    from vigproc.model import FitQuality

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
