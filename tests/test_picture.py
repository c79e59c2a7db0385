import numpy as np

from vigproc.bench.synthetic import table1_model
from vigproc.model import VignettingModel
from vigproc.picture import _AXIS_COLOURS, falloff_figure, vignetting_picture


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
