"""The per-frame pipeline's settings (vigproc.pipeline.processor.Settings): the one predicate
every front end asks whether a ``profile`` names a file and whether a run needs the
profile store (issue 23: five copies disagreed, and watch took ``source:foo`` for a file)."""

from __future__ import annotations

import pytest

from vigproc.pipeline.processor import PROFILE_CHOICES, Settings, names_profile_file


@pytest.mark.parametrize("profile, is_file", [
    *((p, False) for p in PROFILE_CHOICES),
    ("source:foo", False), ("source:studio-db", False),
    ("lens.json", True), ("/profiles/sony.json", True), ("profiles/source:foo.json", True),
])
def test_a_profile_names_a_file_unless_it_is_a_choice_or_a_source(profile, is_file):
    assert names_profile_file(profile) is is_file
    assert Settings(profile=profile).profile_is_file is is_file


@pytest.mark.parametrize("mode, profile, needs", [
    ("correct", "auto", True), ("estimate", "auto", True),  # a trusted stored profile comes first
    ("correct", "estimate", False), ("correct", "lensfun", False), ("correct", "embedded", False),
    ("correct", "source:foo", False), ("correct", "lens.json", False), ("estimate", "estimate", False),
    ("learn", "estimate", True), ("check", "estimate", True), ("check", "lens.json", True),
])
def test_a_run_needs_the_store_to_learn_to_check_or_to_look_a_profile_up(mode, profile, needs):
    assert Settings(mode=mode, profile=profile).needs_store is needs


@pytest.mark.parametrize("method", ["default", "robust", "lens-family"])
def test_a_frame_is_validated_once_at_the_pipelines_door(monkeypatch, method):
    # issue 23: the door checks the pixels (NaN/Inf, range, size), then the checked
    # array goes inward; the estimator does not scan a 24 MP frame again.
    import numpy as np

    import vigproc.core.estimate as E
    import vigproc.core.pixels as P
    from vigproc.pipeline.processor import Processor

    from conftest import textured

    calls = []
    real = P.check_image

    def counting(*a, **k):
        calls.append(1)
        return real(*a, **k)

    monkeypatch.setattr(P, "check_image", counting)
    monkeypatch.setattr(E, "check_image", counting)
    img = np.repeat(textured(96, 144, seed=3)[..., None], 3, axis=2).astype(np.float32)
    with Processor(Settings(mode="estimate", profile="estimate", method=method)) as proc:
        _, res = proc.process_image(img)
    assert res.model is not None and len(calls) == 1
    with pytest.raises(Exception, match="too small"):  # the estimator's own minimum still holds
        with Processor(Settings(mode="estimate", profile="estimate", method=method)) as proc:
            proc.process_image(img[:5, :5])
