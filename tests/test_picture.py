import numpy as np
import pytest

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


@pytest.mark.parametrize("x, y, size, text", [
    (10, 40, 13, "contours:"), (-30, 12, 15, "NOT APPLIED: the evidence was too weak"),
    (250, 118, 24, "gjpqy 写真"), (5, 3, 13, "a\nb"), (290, 60, 40, "W" * 20), (400, 400, 13, "off the picture"),
])
def test_text_draws_the_pixels_it_draws_into_the_whole_picture(x, y, size, text):
    # _text renders only the text's box: the same pixels as rendering into the whole array
    import OpenImageIO as oiio

    from vigproc.io.picture import _text

    img = np.random.default_rng(size).random((120, 300, 3)).astype(np.float32)
    whole = oiio.ImageBuf(np.ascontiguousarray(img))
    oiio.ImageBufAlgo.render_text(whole, x, y, text, size, "", (0.9, 0.2, 0.4))
    got = img.copy()
    _text(got, x, y, text, size, (0.9, 0.2, 0.4))
    assert np.array_equal(got, whole.get_pixels(oiio.FLOAT).reshape(img.shape))
