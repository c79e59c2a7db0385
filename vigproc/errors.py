"""Typed errors raised by vigproc.

Every error a user can provoke with bad input derives from :class:`VigprocError`;
the command line turns these into a one-line message and a non-zero exit code
(see :data:`EXIT_CODES`), never a traceback.
"""

from __future__ import annotations

import errno as _errno

#: Whose fault an error is, as every error class states in its ``blame``: the input
#: being processed, the output side (the disk and folder outputs go to), or the settings
#: (the options, a store or the installation).  :mod:`vigproc.pipeline.faults` decides by
#: this and by ``errno``, never by the words of a message (which can carry file names).
INPUT, OUTPUT_SIDE, SETTINGS = "input", "output", "settings"

#: Escapes of the characters that would end or rewrite a line of text (C0 and C1
#: controls, DEL, Unicode line and paragraph separators, bidirectional controls such as
#: RLO that reorder what follows): applied to messages that carry file names, so a
#: hostile name cannot forge lines on stderr or in a log.
CONTROL_ESCAPES = ({c: f"\\x{c:02x}" for c in (*range(0x20), *range(0x7F, 0xA0))}
                   | {10: "\\n", 13: "\\r", 9: "\\t", 0x2028: "\\u2028", 0x2029: "\\u2029"}
                   | {c: f"\\u{c:04x}" for c in (0x61C, 0x200E, 0x200F, *range(0x202A, 0x202F), *range(0x2066, 0x206A))})


def one_line(text: str) -> str:
    """``text`` with its control characters escaped (see :data:`CONTROL_ESCAPES`).

    >>> one_line("cannot read 'a\\nvigproc: all done'")
    "cannot read 'a\\\\nvigproc: all done'"
    """
    return text.translate(CONTROL_ESCAPES)


class VigprocError(Exception):
    """Base class of all errors vigproc raises on purpose."""

    exit_code = 1
    #: Whose fault: :data:`INPUT`, :data:`OUTPUT_SIDE` or :data:`SETTINGS`.
    blame = INPUT


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
    """An output could not be written: the output side's fault (its disk, its folder)
    unless a subclass says otherwise.  ``errno`` is the failed call's, where there was one."""

    exit_code = 5
    blame = OUTPUT_SIDE


class OutputSettingsError(ImageWriteError):
    """What was asked cannot be written, whatever the disk: an unknown output format or
    extension, a bit depth or transfer the format does not take, an output that would
    replace an input, a folder named as output file, no exiftool (exit code 5)."""

    blame = SETTINGS


class OutputFormatError(OutputSettingsError):
    """The output format asked for cannot be made from this input (``--output-format
    dng`` of a JPEG): the settings' fault, not the output disk's, so a watch folder or a
    batch gives the file up rather than retry it (exit code 5, as for any output that
    could not be written)."""


class OutputRefusedError(ImageWriteError):
    """This input cannot be written as asked: values beyond the output format's range, a
    name that would put its output outside the output folder, a source whose metadata
    exiftool cannot read.  The input's fault, not the disk's (exit code 5)."""

    blame = INPUT


class DiskFullError(ImageWriteError):
    """A disk is full (or over quota): the machine's fault, not the photo's.
    Free space and run again; nothing was charged to the files (exit code 5, as
    for any output that could not be written).  ``disk`` names which disk."""

    disk = "output disk"


#: errno values of a full disk or an exhausted quota.
DISK_FULL_ERRNOS = frozenset(getattr(_errno, n) for n in ("ENOSPC", "EDQUOT") if hasattr(_errno, n))


def write_error(message: str, exc: BaseException) -> ImageWriteError:
    """The typed error of a write that failed with ``exc``.

    Parameters
    ----------
    message : str
        What failed, for the user.
    exc : BaseException
        The failed call's error: its ``errno`` (an OSError's) is kept on the result.

    Returns
    -------
    ImageWriteError
        :class:`DiskFullError` on ENOSPC/EDQUOT, else :class:`ImageWriteError`.
    """
    code = getattr(exc, "errno", None)
    err = (DiskFullError if code in DISK_FULL_ERRNOS else ImageWriteError)(message)
    err.errno = code
    return err


class MemoryBudgetError(InvalidImageError):
    """Decoding the image would exceed the memory budget (``VIGPROC_MEMORY_BUDGET``,
    see :func:`vigproc.io.images.memory_budget`); decided from the file's header, before any
    pixel is decoded."""


class ModelError(VigprocError, ValueError):
    """Vignetting model parameters are missing, absurd or inconsistent."""

    exit_code = 6


class PriorError(VigprocError, ValueError):
    """The natural-image prior could not be fitted or loaded."""

    exit_code = 7
    blame = SETTINGS


class BenchmarksNotFoundError(VigprocError):
    """``vigproc bench`` found no benchmarks: they live in a source checkout's
    ``benchmarks/`` folder, which an installed copy does not ship."""

    blame = SETTINGS


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
    "profile_store": 8,  # vigproc.stores.profiles.ProfileStoreError
    "journal": 9,  # vigproc.stores.journal.JournalError
    "batch": 10,  # vigproc.frontends.batch.BatchError
    "forensics": 11,  # vigproc.forensics.check.ForensicsError
    "plugin": 12,  # vigproc.core.extensions.ExtensionError
    "inconsistent": 20,  # vigproc check: a frame does not match its claimed lens
    "undecided": 21,  # vigproc check: unknown lens or too little signal, nothing inconsistent
    "internal": 70,  # a bug (EX_SOFTWARE): a one-line message; vigproc hook reports it as JSON
    "interrupted": 130,  # Ctrl-C (128 + SIGINT)
    "terminated": 143,  # SIGTERM (128 + SIGTERM), handled as Ctrl-C
}


class ProfileStoreError(VigprocError):
    """The profile store or a profile file cannot be used (corrupt, locked, invalid)."""

    exit_code = EXIT_CODES["profile_store"]
    blame = SETTINGS
