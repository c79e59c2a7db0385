"""The grid field (issue 41): a lens's per-channel fall-off measured from flat frames as a
bilinear grid, for fields no parametric model holds."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from vigproc.core.gridfield import GridField, correct_with_grid, fit_grid, flat_grid
from vigproc.core.model import frame_coords
from vigproc.errors import InvalidImageError, ModelError

W, H = 300, 200


def lopsided(width: int = W, height: int = H) -> np.ndarray:
    """ln φ_c of a field no even polynomial holds: a fall-off stronger on the left and
    at the top, per channel, with a bump off the axis (H×W×3)."""
    x = frame_coords(width)[None, :] / width
    y = frame_coords(height)[:, None] / height
    base = -1.2 * (x * x + y * y) - 0.4 * np.maximum(-x, 0) ** 2 - 0.3 * np.maximum(-y, 0) ** 3
    bump = 0.05 * np.exp(-((x - 0.25) ** 2 + (y + 0.2) ** 2) / 0.01)
    return np.stack([1.2 * base + bump, base, 0.8 * base - bump], axis=-1)


def test_grid_fit_holds_a_field_no_polynomial_holds():
    lf = lopsided()
    yy, xx = np.mgrid[1:H:4, 1:W:4]  # a point in every 4×4 block, as a flat frame's block means
    g = fit_grid(lf[yy, xx].reshape(-1, 3), ((xx + 0.5) / W).ravel(), ((yy + 0.5) / H).ravel(), 33, 22, W, H)
    d = (g.log_fields() - lf) / math.log(2)
    d -= d.mean(axis=(0, 1))
    assert np.sqrt(np.mean(d * d, axis=(0, 1))).max() < 0.003
    # another resolution of the frame: the same field
    half = g.log_fields(W // 2, H // 2)
    np.testing.assert_allclose(half[10, 20], g.log_fields()[21, 41], atol=0.01)


def test_flat_grid_of_unevenly_lit_frames():
    """Three flat frames with gradients: the field's shape beyond a plane is recovered (a
    plane is the part a wall's gradient and the lens's own tilt share; the field above is
    even about no point, so no centre separates them)."""
    lf = lopsided()
    rng = np.random.default_rng(0)
    frames = []
    for g in [(0.06, 0.0), (0.0, -0.05), (-0.04, 0.03)]:
        ramp = g[0] * frame_coords(W)[None, :] / W + g[1] * frame_coords(H)[:, None] / H
        img = 0.4 * np.exp(lf + ramp[..., None]) * np.array([0.9, 1.0, 0.8])
        frames.append(img * (1 + 0.01 * rng.standard_normal(img.shape)))
    grid = flat_grid(frames, [(0.0, 0.0)] * 3)
    # the frames' gradients and the field's own odd linear part go together: compare without a plane
    d = (grid.log_fields() - lf) / math.log(2)
    X = np.stack([np.ones(W * H), np.tile(frame_coords(W), H), np.repeat(frame_coords(H), W)], 1)
    for c in range(3):
        r = d[..., c].ravel()
        r = r - X @ np.linalg.lstsq(X, r, rcond=None)[0]
        assert np.sqrt(np.mean(r * r)) < 0.005
    assert grid.sigma is not None and float(grid.sigma.max()) < 0.02


def test_correct_with_grid_divides_each_channel_and_round_trips():
    lf = lopsided()
    yy, xx = np.mgrid[1:H:4, 1:W:4]
    g = fit_grid(lf[yy, xx].reshape(-1, 3), ((xx + 0.5) / W).ravel(), ((yy + 0.5) / H).ravel(), 33, 22, W, H,
                 source="test")
    scene = np.full((H, W, 3), 0.3)
    out = correct_with_grid(scene * np.exp(lf), g)
    r = np.log(out / scene)
    r -= r.mean(axis=(0, 1))
    assert np.abs(r).max() < 0.02
    back = GridField.from_dict(json.loads(json.dumps(g.to_dict())))
    np.testing.assert_array_equal(back.log_field, g.log_field)
    assert back.source == "test"


@pytest.mark.parametrize("bad", [
    {"schema": "vigproc.grid/9", "width": 3, "height": 2, "log_field": [[[0, 0, 0]] * 2] * 2},
    {"schema": "vigproc.grid/1", "width": 3, "height": 2, "log_field": [[0, 0, 0]]},
    {"schema": "vigproc.grid/1", "width": 3, "height": 2, "log_field": [[[0, 0, float("nan")]] * 2] * 2},
    {"schema": "vigproc.grid/1", "width": 3, "height": 2, "log_field": [[[0, 0, 0], [0, 0, 50]]] * 2},
    {"schema": "vigproc.grid/1", "width": 0, "height": 2, "log_field": [[[0, 0, 0]] * 2] * 2},
    "not an object",
])
def test_bad_grid_fields_are_model_errors(bad):
    with pytest.raises(ModelError):
        GridField.from_dict(bad)


def test_correct_with_grid_needs_three_channels():
    g = GridField(W, H, np.zeros((2, 2, 3)))
    with pytest.raises(InvalidImageError):
        correct_with_grid(np.ones((H, W)), g)
