"""The robust estimator's scene prior (vigproc.core.scene): the mean fall-off of photographs."""

import numpy as np
import pytest

from vigproc.errors import PriorError
from vigproc.core.model import VignettingModel
from vigproc.core.scene import NONE, SceneFalloff, default_scene_falloff, fit_scene_falloff, frame_grid

from conftest import textured


def test_a_fall_off_round_trips_and_is_one_at_its_centre():
    s = default_scene_falloff()
    again = SceneFalloff.from_dict(s.to_dict())
    assert again == s
    xs, ys, w, h = frame_grid(1.5)
    lf = s.log_field(xs, ys)
    assert lf.shape == (h, w) and float(lf.max()) <= 1e-9  # a fall-off: nothing brighter than its centre
    m = s.model(480, 320)
    assert 0.99 < m.field((320, 480)).max() <= 1.0  # 1 at its centre, which lies between pixels
    np.testing.assert_allclose(NONE.log_field(xs, ys), 0.0)


@pytest.mark.parametrize("bad, message", [({"schema": "x"}, "not a scene fall-off"),
                                          ({"theta": [0.0] * 3}, "12 finite")])
def test_a_bad_file_is_a_prior_error(bad, message):
    d = dict(default_scene_falloff().to_dict(), **bad) if "theta" in bad else bad
    with pytest.raises(PriorError, match=message):
        SceneFalloff.from_dict(d)


def test_the_fit_is_the_mean_of_what_the_estimator_reads():
    """With an 'estimator' that reads every photo as the same field, the fitted fall-off
    is that field; fewer than ten photos or mixed aspect ratios are refused."""
    truth = VignettingModel(48, 32, p=(2e-3, 0.0, 2e-3), alpha=(0.1,) + (0.0,) * 6)
    ims = [textured(32, 48, seed=i) for i in range(10)]
    got = fit_scene_falloff(ims, lambda im, prior: truth.rescale(im.shape[1], im.shape[0]), iterations=1)
    xs, ys, w, h = frame_grid(1.5)
    want = truth.rescale(w, h).log_field((h, w))
    assert np.sqrt(np.mean((got.log_field(xs, ys) - want) ** 2)) / np.log(2) < 0.01
    assert got.n_images == 10 and got.field_ev_rms > 0.05
    with pytest.raises(PriorError, match="at least 10"):
        fit_scene_falloff(ims[:9], lambda im, prior: truth)
    with pytest.raises(PriorError, match="one aspect ratio"):
        fit_scene_falloff(ims[:9] + [textured(48, 48)], lambda im, prior: truth)
