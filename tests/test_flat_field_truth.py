"""scripts/flat_field_truth.py: a flat field's own fall-off read off the file, on the bench's grid."""

from __future__ import annotations

import numpy as np

from benchmarks.real_frames_lensfun import Truth, _ev
from scripts.flat_field_truth import corner_ev, frame_log_field, sides_ev
from vigproc.io import write_image
from vigproc.stores.lensfun import pa_field

K = (-0.45, 0.12, -0.03)


def _flat(tmp_path, field):
    path = tmp_path / "flat.tif"
    write_image(path, np.repeat((0.4 * field)[..., None], 3, axis=2).astype(np.float32), bit_depth="float")
    return path


def test_a_lens_field_is_read_back_as_itself(tmp_path):
    own = frame_log_field(_flat(tmp_path, pa_field((480, 720), *K)))
    true = Truth("test", 50.0, 4.0, 1000.0, 1.0, K).log_field(own.shape)
    assert own.shape == (160, 240)
    assert _ev(own - true) < 0.002
    assert abs(corner_ev(own) - corner_ev(true)) < 0.01
    assert 0.5 < corner_ev(own) < Truth("test", 50.0, 4.0, 1000.0, 1.0, K).corner_ev
    assert max(abs(v) for v in sides_ev(own)) < 0.005


def test_light_falling_across_the_surface_shows_left_to_right(tmp_path):
    x = np.linspace(0.0, 1.0, 720)[None, :] * np.ones((480, 1))
    own = frame_log_field(_flat(tmp_path, pa_field((480, 720), *K) * 2.0 ** (0.5 * x)))
    lr, tb = sides_ev(own)
    assert -0.5 < lr < -0.4 and abs(tb) < 0.005


def test_a_field_of_another_shape_is_not(tmp_path):
    # the same fall-off stretched along the long side only: the comparison must see it
    y, x = np.mgrid[0:480, 0:720]
    r2 = ((x + 0.5 - 360) / 360) ** 2 * 0.5 + ((y + 0.5 - 240) / 240) ** 2 * 0.05
    own = frame_log_field(_flat(tmp_path, 1 + K[0] * r2))
    true = Truth("test", 50.0, 4.0, 1000.0, 1.0, K).log_field(own.shape)
    assert _ev(own - true) > 0.02
