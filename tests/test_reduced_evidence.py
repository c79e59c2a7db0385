"""A frame's evidence for its lens's profile binned from the reduced copy its estimate
reads (vigproc.core.robust.reduced_working_copy): the same binned values and the full
frame's geometry, so the profile's frame fit and the pooled profile are those of the
full-frame evidence."""

from __future__ import annotations

import numpy as np
import pytest

from vigproc.core.estimate import (estimate_with_evidence, frame_evidence, reduced_estimate_with_evidence,
                                   reduced_evidence, reduction_factor)
from vigproc.core.pixels import check_image
from vigproc.core.pooling import frame_fit
from vigproc.core.robust import EVIDENCE_FORMAT, evidence_copy
from vigproc.errors import InvalidImageError
from vigproc.io.images import EncodedImage, _stored_values
from vigproc.stores.lensfun import diverse_lenses, pa_field
from vigproc.stores.profile_key import ProfileKey, aperture_bin, focal_bin
from vigproc.stores.profiles import ProfileStore

from conftest import coloured_scene

#: Not a multiple of the reduction (5) nor of the working bin (15): the reduced frame
#: drops 2 columns and 3 rows, so its own centre sits (−1, −1.5) px off the frame's.
W, H = 1447, 963
#: How far the reduced copy's frame fit may be from the full frame's (its coefficients,
#: lens-family units): float32 block means against float64 bins.
COEF_TOL = 1e-4
#: ... and the pooled profiles' fields (RMS of the log2 difference, EV).
FIELD_TOL = 1e-3


def _frame(seed: int, lens: int = 2) -> EncodedImage:
    """A colour scene times a lensfun lens's fall-off, as 8-bit sRGB codes."""
    _, pa = diverse_lenses(lens + 1)[lens]
    lin = coloured_scene(H, W, seed=seed) * pa_field((H, W), pa.k1, pa.k2, pa.k3)[..., None]
    return EncodedImage(_stored_values(np.clip(lin, 0, 1).astype(np.float32), "png", "uint8", "srgb", "x"), "srgb")


def _old_reduced(small: np.ndarray, usable) -> bytes:
    """The evidence of the reduced copy as a frame of its own (its own geometry)."""
    from vigproc.core.estimate import _robust_settings, colour_of, luminance
    from vigproc.core.robust import luminance_evidence as robust_evidence

    a = check_image(small)
    return robust_evidence(luminance(a), _robust_settings("default", None), usable, colour_of(a))


@pytest.fixture(scope="module")
def frames():
    return [_frame(seed) for seed in (11, 12, 13, 14)]


def test_the_reduced_copy_bins_as_the_full_frame_with_its_geometry(frames):
    enc = frames[0]
    k = reduction_factor(W, H)
    assert k == 5  # the case this test is about: a real reduction with remainders
    small, usable = enc.reduced(k)
    full = evidence_copy(frame_evidence(enc.linear()))
    red = evidence_copy(reduced_evidence(small, k, W, H, usable=usable))
    old = evidence_copy(_old_reduced(small, usable))
    assert (red.width, red.height, red.radius) == (full.width, full.height, full.radius) == (W, H, full.radius)
    np.testing.assert_array_equal(red.xs, full.xs)
    np.testing.assert_array_equal(red.ys, full.ys)
    np.testing.assert_array_equal(red.valid, full.valid)
    assert np.max(np.abs(red.L - full.L)[full.valid]) < 1e-5
    assert np.max(np.abs(red.channels - full.channels)[full.channels_valid]) < 1e-5
    np.testing.assert_array_equal(red.channels_valid, full.channels_valid)
    # the old way: the same values, the reduced frame's own geometry
    assert np.max(np.abs(old.L - full.L)[full.valid]) < 1e-5
    assert (old.width, old.height) == (W // k, H // k)


def test_the_frame_fit_agrees_and_did_not_with_the_reduced_frames_own_geometry(frames):
    k = reduction_factor(W, H)
    moved_old = []
    for enc in frames:
        small, usable = enc.reduced(k)
        full = frame_fit(evidence_copy(frame_evidence(enc.linear()))).coefficients
        red = frame_fit(evidence_copy(reduced_evidence(small, k, W, H, usable=usable))).coefficients
        old = frame_fit(evidence_copy(_old_reduced(small, usable))).coefficients
        assert np.max(np.abs(red - full)) < COEF_TOL, (red, full)
        moved_old.append(float(np.max(np.abs(old - full))))
    # without the full frame's geometry the fit moved by more than the tolerance
    assert max(moved_old) > 3 * COEF_TOL, moved_old


def _pooled(tmp_path, name: str, blobs: list[bytes], fits):
    key = ProfileKey("vigproc|series 1|test lens", focal_bin(35.0), aperture_bin(4.0), "3:2")
    with ProfileStore(tmp_path / f"{name}.sqlite") as store:
        for i, (blob, m) in enumerate(zip(blobs, fits)):
            p = store.learn(key, m, frame_id=f"frame{i}", evidence=blob)
    return p


def test_a_profile_learned_from_reduced_copies_is_the_full_frames(frames, tmp_path):
    from vigproc.pipeline.learning import field_change_ev

    k = reduction_factor(W, H)
    full_blobs, red_blobs, old_blobs, fits = [], [], [], []
    for enc in frames:
        small, usable = enc.reduced(k)
        m, blob = estimate_with_evidence(enc.linear())
        fits.append(m.candidate if m.candidate is not None else m)
        full_blobs.append(blob)
        red_blobs.append(reduced_evidence(small, k, W, H, usable=usable))
        old_blobs.append(_old_reduced(small, usable))
    full = _pooled(tmp_path, "full", full_blobs, fits)
    red = _pooled(tmp_path, "reduced", red_blobs, fits)
    assert full.n_frames == red.n_frames == len(frames) and full.theta is not None
    assert field_change_ev(full, red) < FIELD_TOL
    # the field it learns is there to be learned (a tolerance of a tiny field proves nothing)
    assert full.model(W, H).field_ev_rms() > 0.1
    # the old evidence names a frame of another size: that profile is not the same
    old = _pooled(tmp_path, "old", old_blobs, [f.rescale(W // k, H // k) for f in fits])
    assert field_change_ev(full, old) > FIELD_TOL


def test_learn_modes_fit_from_the_reduced_copy_is_the_full_frames(frames):
    enc = frames[1]
    k = reduction_factor(W, H)
    small, usable = enc.reduced(k)
    m_full, _ = estimate_with_evidence(enc.linear())
    m_red, blob = reduced_estimate_with_evidence(small, k, W, H, usable=usable)
    assert (m_red.width, m_red.height) == (W, H)
    a, b = (x.candidate if x.candidate is not None else x for x in (m_full, m_red))
    diff = a.log_field((H // 8, W // 8)) - b.log_field((H // 8, W // 8))
    assert float(np.sqrt(np.mean(diff**2)) / np.log(2)) < 1e-3
    assert abs(a.center[0] - b.center[0]) < 0.5 and abs(a.center[1] - b.center[1]) < 0.5
    assert evidence_copy(blob).width == W


def test_the_blob_keeps_its_format_and_a_wrong_reduction_is_refused(frames):
    import io
    import json

    enc = frames[0]
    small, usable = enc.reduced(5)
    blob = reduced_evidence(small, 5, W, H, usable=usable)
    with np.load(io.BytesIO(blob)) as z:  # the format stored profiles hold: nothing new to read
        assert json.loads(bytes(z["meta"]).decode())["format"] == EVIDENCE_FORMAT
    with pytest.raises(InvalidImageError):  # a copy reduced by 3 stated as one reduced by 5
        reduced_evidence(enc.reduced(3)[0], 5, W, H)
    with pytest.raises(InvalidImageError):  # 4 does not divide the working bin (15): bins of other pixels
        reduced_evidence(enc.reduced(4)[0], 4, W, H)
    with pytest.raises(InvalidImageError):
        reduced_evidence(small, 5, W, H, "lyu2010")


def test_learning_as_you_go_bins_the_estimates_reduced_copy_once(frames, monkeypatch):
    """pooled_of reads the reduced copy the estimate made: no full-frame decode, no second reduction."""
    import vigproc.io.image_read as image_read
    from vigproc.pipeline.encoded import estimate_encoded
    from vigproc.pipeline.learning import pooled_of

    enc = EncodedImage(frames[2].codes.copy(), "srgb")
    calls = []
    real = image_read.reduce_codes
    monkeypatch.setattr(image_read, "reduce_codes", lambda *a, **kw: calls.append(a[2]) or real(*a, **kw))
    monkeypatch.setattr(EncodedImage, "linear", lambda self: pytest.fail("decoded the full frame"))
    own = estimate_encoded(enc, "default")
    fit, blob = pooled_of(own, enc, "default")
    assert calls == [5]
    small, usable = enc.reduced(5)
    assert blob == reduced_evidence(small, 5, W, H, usable=usable)
    assert evidence_copy(blob).width == W and fit.width == W
