"""Colour fields in the profile store and its files; lensfun export (issue 41)."""

from __future__ import annotations

import json
import logging
import math

import numpy as np
import pytest

from vigproc.core.colour import ColourField
from vigproc.core.model import VignettingModel
from vigproc.stores.profiles import (FILE_SCHEMA, FILE_SCHEMA_COLOUR, ProfileKey, ProfileStore, aspect_label,
                                     profile_from_dict, profile_to_dict)

W, H = 300, 200
TINT = np.array([[0.12, 0.05, 0.0], [0.0, 0.0, 0.0], [-0.15, 0.0, 0.02]])


def _frame(rng, colour=True):
    cov = np.diag([4.0, 4.0, 1e-13, 1e-14, 1e-13] + [1e-4] * 7)
    cf = None
    if colour:
        cf = ColourField(W, H, (6.0, -4.0), TINT + 0.005 * rng.standard_normal(TINT.shape) * [[1], [0], [1]],
                         sigma=np.full((3, 3), 0.005), source="flat-field")
    return VignettingModel(W, H, center=(6.0, -4.0), p=(1 / 250**2, 0.0, 1 / 250**2), method="flat-field",
                           covariance=tuple(map(tuple, cov)), colour=cf)


def _key():
    from vigproc.stores.profiles import aperture_bin, focal_bin

    return ProfileKey("cam|lens", focal_bin(50.0), aperture_bin(2.8), aspect_label(W / H))


def test_profiles_pool_colour_and_round_trip_through_store_and_file(tmp_path):
    rng = np.random.default_rng(0)
    with ProfileStore(tmp_path / "p.sqlite") as st:
        for i in range(3):
            p = st.learn(_key(), _frame(rng), frame_id=f"f{i}")
        assert p.colour is not None and p.colour.n == 3
        again = st.get(_key())
    assert again.colour is not None and again.colour.n == 3
    m = again.model(2 * W, 2 * H)
    assert m.colour is not None and m.colour.size == (2 * W, 2 * H)
    # pooled: within the frames' noise of the true tint, in EV over the frame
    truth = ColourField(W, H, (6.0, -4.0), TINT)
    d = (m.colour.log_ratios(W, H) - truth.log_ratios()) / math.log(2)
    assert np.sqrt(np.mean(d * d)) < 0.003
    d = profile_to_dict(again)
    assert d["schema"] == FILE_SCHEMA_COLOUR and "colour" in d
    back = profile_from_dict(json.loads(json.dumps(d)))
    np.testing.assert_allclose(back.model(W, H).colour.ratios(), again.model(W, H).colour.ratios())


def test_colourless_profiles_stay_schema_2_and_old_files_load_colourless(tmp_path):
    rng = np.random.default_rng(1)
    with ProfileStore(tmp_path / "p.sqlite") as st:
        p = st.learn(_key(), _frame(rng, colour=False), frame_id="f0")
    assert p.colour is None
    d = profile_to_dict(p)
    assert d["schema"] == FILE_SCHEMA and "colour" not in d
    assert profile_from_dict(d).model(W, H).colour is None
    # an old file (schema /2) cannot carry a colour field
    with pytest.raises(Exception) as exc:
        profile_from_dict({**d, "colour": {"info": [[1] * 3] * 3, "weighted": [[0] * 3] * 3, "n": 1}})
    assert "vigproc.profile/3" in str(exc.value)


def test_lensfun_export_warns_that_colour_is_not_expressed(tmp_path, caplog):
    from vigproc.stores import lensfun_io

    rng = np.random.default_rng(2)
    with ProfileStore(tmp_path / "p.sqlite") as st:
        for i in range(3):
            st.learn(_key(), _frame(rng), frame_id=f"f{i}")
        profiles = st.list()
    notes = lensfun_io.colour_notes(profiles)
    assert notes and "colour" in notes[0]
    with caplog.at_level(logging.WARNING, logger="vigproc.stores.lensfun_io"):
        lensfun_io.warn_colour(profiles)
    assert any("colour" in r.getMessage() for r in caplog.records)


def test_a_v10_store_migrates_and_pools_colour(tmp_path):
    import sqlite3

    from vigproc.stores.profiles import SCHEMA_VERSION

    rng = np.random.default_rng(3)
    db = tmp_path / "p.sqlite"
    with ProfileStore(db) as st:
        st.learn(_key(), _frame(rng, colour=False), frame_id="a")
    con = sqlite3.connect(db)  # as vigproc before schema v11 left it
    con.execute("ALTER TABLE profiles DROP COLUMN colour")
    con.execute("DELETE FROM schema_version WHERE version > 10")
    con.commit()
    con.close()
    with ProfileStore(db) as st:
        assert st.schema_version == SCHEMA_VERSION >= 11
        assert st.get(_key()).colour is None
        p = st.learn(_key(), _frame(rng), frame_id="b")
        assert p.colour is not None and p.colour.n == 1 and st.get(_key()).colour.n == 1
