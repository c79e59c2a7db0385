"""Hand-offs between commands, tools and files, as users make them: each test is a bug
found by using vigproc from its README and docs, fixed, and kept from coming back."""

from __future__ import annotations

import numpy as np
import pytest

from vigproc.io.exif import lens_key_from_metadata


# ------------------------------------------------------------------ the right lens
def test_a_described_lens_never_pools_into_the_profile_of_unknown_lenses(tmp_path) -> None:
    """A lens EXIF only describes ("24-70mm") is keyed by that description; the profile
    of the body's undescribed lenses ("?": any lens, frames of several) is not its own,
    in a new store or an old one, so it neither learns into it nor is corrected by it."""
    from vigproc.core.normalised import denormalise
    from vigproc.stores.profiles import ProfileKey, ProfileStore

    body = {"EXIF:Make": "Canon", "EXIF:Model": "Canon EOS 5D", "EXIF:FocalLength": 50, "EXIF:FNumber": 2.8}
    unknown = lens_key_from_metadata({**body, "EXIF:LensModel": "----"})
    described = lens_key_from_metadata({**body, "EXIF:LensModel": "24-70mm"})
    assert unknown.lens is None and described.lens == "24-70mm"
    theta = np.array([0.02, -0.01, 0.9, 0.02, 0.85, 0.05, 0.1, -0.05, 0.02, 0.0, 0.0, 0.0])
    with ProfileStore(tmp_path / "p.sqlite") as store:
        key = store.key_for(unknown, 3000, 2000)
        assert key.lens_id.endswith("|?")
        for _ in range(4):
            store.learn(key, denormalise(theta, np.diag(np.full(12, 1e-6)), 3000, 2000, method="robust"))
        assert store.lookup(unknown, 3000, 2000) is not None
        assert store.key_for(described, 3000, 2000).lens_id == described.lens_id()
        assert store.lookup(described, 3000, 2000) is None
