"""The exit codes of typed errors, wherever they are defined, agree with the one
table users read (vigproc.errors.EXIT_CODES), and no two kinds share a code."""

from __future__ import annotations

import importlib

import pytest

from vigproc.errors import EXIT_CODES


@pytest.mark.parametrize("module, name, key", [
    ("vigproc.profiles", "ProfileStoreError", "profile_store"),
    ("vigproc.journal", "JournalError", "journal"),
    ("vigproc.batch", "BatchError", "batch"),
    ("vigproc.forensics", "ForensicsError", "forensics"),
    ("vigproc.extensions", "ExtensionError", "plugin"),
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
    from vigproc.commands import check

    assert (check.EXIT_INCONSISTENT, check.EXIT_UNDECIDED) == (EXIT_CODES["inconsistent"], EXIT_CODES["undecided"])
