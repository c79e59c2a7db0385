"""Typed errors raised by vigproc.

Every error a user can provoke with bad input derives from :class:`VigprocError`;
the command line turns these into a one-line message and a non-zero exit code
(see :data:`EXIT_CODES`), never a traceback.
"""

from __future__ import annotations

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


class OutputFormatError(ImageWriteError):
    """The output format asked for cannot be made from this input (``--output-format
    dng`` of a JPEG): the settings' fault, not the output disk's, so a watch folder or a
    batch gives the file up rather than retry it (exit code 5, as for any output that
    could not be written)."""

    output_side = False


class DiskFullError(ImageWriteError):
    """The output disk is full (or over quota): the machine's fault, not the photo's.
    Free space and run again; nothing was charged to the files (exit code 5, as
    for any output that could not be written)."""


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
