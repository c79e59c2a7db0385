"""An imported profile is the prior of the frames learned onto it (vigproc.stores.profile_prior,
vigproc.core.pooling.prior_coefficients / pool_family's ``prior``)."""

import sqlite3

import numpy as np
import pytest

from vigproc.core.estimate import frame_evidence
from vigproc.core.normalised import normalise
from vigproc.core.pooling import coefficients_model, frame_fit, pool_family, prior_coefficients
from vigproc.core.robust import evidence_copy
from vigproc.stores.lensfun import diverse_lenses, pa_field
from vigproc.stores.profile_file import export_profile, profile_from_dict, profile_to_dict
from vigproc.stores.profiles import (SCHEMA_VERSION, ProfileKey, ProfileStore, aperture_bin, aspect_label,
                                     focal_bin)

from conftest import textured

H, W = 160, 240


def _frames(n: int, seed: int) -> list[np.ndarray]:
    _, pa = diverse_lenses(1)[0]
    lens = pa_field((H, W), pa.k1, pa.k2, pa.k3)
    return [textured(H, W, seed=seed + i, contrast=0.05) * lens for i in range(n)]


def _evidence(frames):
    return [frame_evidence(f, channel_axis=None) for f in frames]


def _key() -> ProfileKey:
    return ProfileKey("test|body|lens", focal_bin(50.0), aperture_bin(2.8), aspect_label(W / H))


def _field_ev(a, b) -> float:
    d = a.log_field((H, W)) - b.log_field((H, W))
    return float(np.std(d) / np.log(2))


def test_a_pooled_profile_comes_back_as_its_coefficients():
    """vigproc's own export (a centred pool_family model) is a point of the family: its
    coefficients and their covariance come back, so an import weighs as its frames did."""
    fits = [frame_fit(evidence_copy(e)) for e in _evidence(_frames(4, 10))]
    from vigproc.core.pooling import pooled_coefficients, scene_scatter
    from vigproc.core.lensfamily import profile_family

    c, cov_c = pooled_coefficients(fits, scene_scatter(profile_family()))
    model = pool_family(fits, W, H)
    theta, cov, aspect = normalise(model)
    c2, cov2 = prior_coefficients(theta, cov, aspect)
    sd, sd2 = np.sqrt(np.diag(cov_c)), np.sqrt(np.diag(cov2))
    # the Kang-Weiss writing of the profile moves the coefficients a little, not the field
    assert np.all(np.abs(c2 - c) < 0.5 * sd), (c, c2, sd)
    assert _field_ev(coefficients_model(c2, W, H), model) < 0.005
    assert np.allclose(sd2, sd, rtol=0.15, atol=1e-4), (sd, sd2)


def test_a_prior_weighs_as_the_frames_it_came_from():
    """Four frames pooled elsewhere, then one here: the profile is close to all five
    pooled together, and as certain; without the prior it would be the one frame's."""
    ev = _evidence(_frames(5, 30))
    fits = [frame_fit(evidence_copy(e)) for e in ev]
    four, five, one = pool_family(fits[:4], W, H), pool_family(fits, W, H), pool_family(fits[4:], W, H)
    theta, cov, aspect = normalise(four)
    joined = pool_family(fits[4:], W, H, prior=prior_coefficients(theta, cov, aspect))
    assert _field_ev(joined, five) < 0.5 * _field_ev(one, five) + 1e-3
    assert joined.quality.field_sigma_ev < 0.6 * one.quality.field_sigma_ev
    assert joined.quality.field_sigma_ev < four.quality.field_sigma_ev


def test_the_store_keeps_an_imports_frames_when_it_learns(tmp_path):
    ev = _evidence(_frames(5, 50))
    with ProfileStore(tmp_path / "a.sqlite") as a:
        for i, e in enumerate(ev[:4]):
            a.learn(_key(), _model_of(e), frame_id=f"f{i}", evidence=e)
        exported = a.get(_key())
        for i, e in enumerate(ev[4:], 4):
            a.learn(_key(), _model_of(e), frame_id=f"f{i}", evidence=e)
        here = a.get(_key())
    export_profile(exported, tmp_path / "lens.json")  # the hand-off as `profile export` / `import` make it
    with ProfileStore(tmp_path / "b.sqlite") as b:
        b.import_file(tmp_path / "lens.json")
        there = b.learn(_key(), _model_of(ev[4]), frame_id="f4", evidence=ev[4])
        # what the import said stays when the store is opened again
        b.learn(_key(), _model_of(ev[4]), frame_id="f4", evidence=ev[4])  # the same frame: nothing changes
        assert b.get(_key()).field_sigma_ev == pytest.approx(there.field_sigma_ev)
    assert there.n_frames == here.n_frames == 5
    assert there.field_sigma_ev < 2 * here.field_sigma_ev
    assert there.trusted == here.trusted
    m_here = here.model(W, H)
    m_there = there.model(W, H)
    assert _field_ev(m_here, m_there) < 0.02


def test_an_import_without_uncertainty_is_no_prior_and_a_delete_forgets_it(tmp_path):
    ev = _evidence(_frames(2, 70))
    with ProfileStore(tmp_path / "p.sqlite") as st:
        st.learn(_key(), _model_of(ev[0]), frame_id="a", evidence=ev[0])
        d = profile_to_dict(st.get(_key()))
        st.put(profile_from_dict(d))
        assert _priors(st) == 1
        st.put(profile_from_dict({**d, "covariance": None}))
        assert _priors(st) == 0
        st.put(profile_from_dict(d))
        assert st.delete(_key()) and _priors(st) == 0


def test_a_store_from_before_priors_opens_and_migrates(tmp_path):
    db = tmp_path / "p.sqlite"
    with ProfileStore(db) as st:
        e = _evidence(_frames(1, 90))[0]
        st.learn(_key(), _model_of(e), frame_id="old", evidence=e)
    con = sqlite3.connect(db)  # as vigproc left it before the priors
    con.execute("DROP TABLE profile_priors")
    con.execute("DELETE FROM schema_version WHERE version > 15")
    con.commit()
    con.close()
    with ProfileStore(db) as st:
        assert st.schema_version == SCHEMA_VERSION >= 16
        assert st.get(_key()).n_frames == 1 and _priors(st) == 0


def _priors(st: ProfileStore) -> int:
    return st.con.execute("SELECT count(*) FROM profile_priors").fetchone()[0]


def _model_of(evidence: bytes):
    """The frame's lens-family estimate without a covariance, as a correction hands it
    to ``learn``: the evidence's own fit gives its information."""
    from dataclasses import replace

    return replace(pool_family([frame_fit(evidence_copy(evidence))], W, H), covariance=None)
