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
