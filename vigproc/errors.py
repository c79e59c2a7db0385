"""Typed errors raised by vigproc.

Every error a user can provoke with bad input derives from :class:`VigprocError`;
the command line turns these into a one-line message and a non-zero exit code
(see :data:`EXIT_CODES`), never a traceback.
"""

from __future__ import annotations


class VigprocError(Exception):
    """Base class of all errors vigproc raises on purpose."""

    exit_code = 1


class InvalidImageError(VigprocError, ValueError):
    """The pixel data cannot be used (wrong shape, too small, NaN/Inf, constant...)."""

    exit_code = 3


class ImageReadError(VigprocError, OSError):
    """A file could not be read as an image (missing, corrupt, truncated, unsupported)."""

    exit_code = 4


class UnsupportedFormatError(ImageReadError):
    """The file's format is not one vigproc reads."""

    exit_code = 4


class FileNameError(ImageReadError):
    """A file name cannot be passed to a helper program (exiftool) without being misread."""


class MetadataError(ImageReadError):
    """Metadata cannot identify the camera/lens, or a required field is missing."""


class ImageWriteError(VigprocError, OSError):
    """An output could not be written."""

    exit_code = 5


class ModelError(VigprocError, ValueError):
    """Vignetting model parameters are missing, absurd or inconsistent."""

    exit_code = 6


class PriorError(VigprocError, ValueError):
    """The natural-image prior could not be fitted or loaded."""

    exit_code = 7


#: Every exit code of the ``vigproc`` command, stable across releases.  Errors
#: defined in other modules carry theirs as ``exit_code``; the tests check that
#: they agree with this table.
EXIT_CODES = {
    "ok": 0,
    "error": 1,  # some files failed, or an error without a more specific code
    "usage": 2,
    "invalid_image": InvalidImageError.exit_code,
    "read": ImageReadError.exit_code,
    "write": ImageWriteError.exit_code,
    "model": ModelError.exit_code,
    "prior": PriorError.exit_code,
    "profile_store": 8,  # vigproc.profiles.ProfileStoreError
    "journal": 9,  # vigproc.journal.JournalError
    "batch": 10,  # vigproc.batch.BatchError
    "forensics": 11,  # vigproc.forensics.ForensicsError
    "plugin": 12,  # vigproc.extensions.ExtensionError
    "inconsistent": 20,  # vigproc check: a frame does not match its claimed lens
    "undecided": 21,  # vigproc check: unknown lens or too little signal, nothing inconsistent
    "internal": 70,  # a bug (EX_SOFTWARE): a one-line message; vigproc hook reports it as JSON
    "interrupted": 130,  # Ctrl-C (128 + SIGINT)
}
