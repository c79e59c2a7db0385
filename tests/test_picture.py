import numpy as np

from benchmarks.synthetic import table1_model
from vigproc.core.model import VignettingModel
from vigproc.io.picture import _AXIS_COLOURS, falloff_figure, vignetting_picture


def _has_colour(img, col):
    return np.any(np.all(np.abs(img - np.asarray(col, np.float32)) < 1e-3, axis=-1))


def test_figure_draws_both_axis_curves_and_the_map():
    m = table1_model(2).rescale(1200, 800)
    fig = falloff_figure(m)
    assert fig.ndim == 3 and fig.shape[2] == 3 and fig.dtype == np.float32
    assert 0 <= fig.min() and fig.max() <= 1
    for col in _AXIS_COLOURS:
        assert _has_colour(fig, col)
    assert _has_colour(fig, (1.0, 0.0, 0.0))  # the centre cross


def test_identity_model_gives_flat_curves():
    fig = falloff_figure(VignettingModel.identity(600, 400))
    assert np.isfinite(fig).all()
    pic = vignetting_picture(VignettingModel.identity(600, 400))
    assert np.allclose(pic[100:110, 100:110], 1.0)  # no fall-off: white


def test_a_rejected_fit_is_shown_as_such_and_axes_need_a_centre_in_the_frame():
    m = table1_model(1).rescale(600, 400)
    applied, rejected = falloff_figure(m), falloff_figure(m, rejected=True)
    cross = (0.85, 0.2, 0.2)  # the red cross over a fit that was not applied
    assert _has_colour(rejected, cross) and not _has_colour(applied, cross)
    # the map is dimmed: its centre is no longer white
    assert applied[40 + 120, 10 + 180].min() > 0.9 > rejected[40 + 120, 10 + 180].max()
    # a centre outside the frame: no axis lines across the map (they came from nowhere)
    p = m.p[0]  # an ellipse at 45 degrees: its axes, drawn, would cross the map
    off = VignettingModel(600, 400, center=(-330.0, -230.0), p=(p, 0.5 * p, p), alpha=m.alpha)
    fig = falloff_figure(off)
    left = fig[40:40 + 280, 10:10 + 420]
    for col in _AXIS_COLOURS:
        assert not _has_colour(left, col)
