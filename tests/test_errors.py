"""The exit codes of typed errors, wherever they are defined, agree with the one
table users read (vigproc.errors.EXIT_CODES), and no two kinds share a code."""

from __future__ import annotations

import importlib

import pytest

from vigproc.errors import EXIT_CODES


@pytest.mark.parametrize("module, name, key", [
    ("vigproc.stores.profiles", "ProfileStoreError", "profile_store"),
    ("vigproc.stores.journal", "JournalError", "journal"),
    ("vigproc.frontends.batch", "BatchError", "batch"),
    ("vigproc.forensics.check", "ForensicsError", "forensics"),
    ("vigproc.core.extensions", "ExtensionError", "plugin"),
    ("vigproc.errors", "InvalidImageError", "invalid_image"),
    ("vigproc.errors", "UnsupportedFormatError", "read"),
])
def test_error_classes_use_the_table(module, name, key):
    cls = getattr(importlib.import_module(module), name)
    assert cls.exit_code == EXIT_CODES[key]


def test_codes_are_distinct():
    codes = list(EXIT_CODES.values())
    assert len(codes) == len(set(codes))


def test_check_command_codes():
    from vigproc.frontends.commands import check

    assert (check.EXIT_INCONSISTENT, check.EXIT_UNDECIDED) == (EXIT_CODES["inconsistent"], EXIT_CODES["undecided"])


def test_numba_cache_falls_back_when_nothing_is_writable(tmp_path):
    """A service user with no writable home, on a read-only install: Numba would refuse
    to define vigproc's cached kernels (measured: 'vigproc --help' then died with a
    traceback), so vigproc points it at a private temporary folder; otherwise it keeps
    Numba's own choice."""
    from vigproc import _numba_cache_fallback

    nothing = lambda path, mode: False  # noqa: E731
    everything = lambda path, mode: True  # noqa: E731
    assert _numba_cache_fallback({"NUMBA_CACHE_DIR": "/x"}, nothing) is None
    assert _numba_cache_fallback({}, everything) is None
    d = _numba_cache_fallback({"XDG_CACHE_HOME": str(tmp_path / "no" / "such")}, nothing)
    assert d is not None and "vigproc-numba-" in d
    # the user's cache folder (its nearest existing parent) writable: Numba's own locator works
    home_ok = lambda path, mode: str(path).startswith(str(tmp_path))  # noqa: E731
    assert _numba_cache_fallback({"XDG_CACHE_HOME": str(tmp_path / "cache")}, home_ok) is None
