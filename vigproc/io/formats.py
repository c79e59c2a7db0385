"""The one table of image file suffixes: what vigproc reads, by kind, and what it writes.

Every reader, writer and folder scan takes its suffixes from here, so a suffix that
:func:`vigproc.io.images.read_image` reads is one that batch, watch and the hook pick up.
Pure data: importing it loads nothing else.
"""

from __future__ import annotations

from typing import Union

__all__ = [
    "CALIBRATED_RAW_SUFFIXES",
    "PathLike",
    "IMAGE_SUFFIXES",
    "RAW_SUFFIXES",
    "READ_SUFFIXES",
    "WRITE_EXT_FORMAT",
    "WRITE_FORMAT_ALIASES",
    "WRITE_FORMAT_EXT",
    "WRITE_SUFFIXES",
    "suffix_kind",
]

#: What the image readers and writers take as a file name.
PathLike = Union[str, "os.PathLike[str]", bytes]

#: Suffixes tried with LibRaw *first* (the content still decides: see ``read_image``).
RAW_SUFFIXES = frozenset(
    {
        ".3fr", ".ari", ".arw", ".bay", ".cap", ".cr2", ".cr3", ".crw", ".dcr", ".dcs",
        ".dng", ".drf", ".eip", ".erf", ".fff", ".gpr", ".iiq", ".k25", ".kdc", ".mdc",
        ".mef", ".mos", ".mrw", ".nef", ".nrw", ".orf", ".pef", ".ptx", ".pxn", ".r3d",
        ".raf", ".raw", ".rw2", ".rwl", ".rwz", ".sr2", ".srf", ".srw", ".sti", ".x3f",
    }
)

#: Suffixes ``read_image`` reads, by kind (OpenImageIO format name, or ``raw``).
READ_SUFFIXES: dict[str, tuple[str, ...]] = {
    "jpeg": (".jpg", ".jpeg", ".jpe"),
    "png": (".png",),
    "tiff": (".tif", ".tiff"),
    "openexr": (".exr",),
    "raw": tuple(sorted(RAW_SUFFIXES)),
}

#: Every suffix vigproc reads: what folder scans (batch, watch, ``bench``) pick up.
IMAGE_SUFFIXES = frozenset(s for suffixes in READ_SUFFIXES.values() for s in suffixes)

#: Suffixes ``write_image`` writes, by format; the first is the one it names new files with.
WRITE_SUFFIXES: dict[str, tuple[str, ...]] = {k: READ_SUFFIXES[k] for k in ("tiff", "png", "openexr", "jpeg")}
#: The writers' formats by file suffix.
WRITE_EXT_FORMAT = {s: fmt for fmt, suffixes in WRITE_SUFFIXES.items() for s in suffixes}
#: The writers' formats by the names a caller may give them.
WRITE_FORMAT_ALIASES = {"tif": "tiff", "tiff": "tiff", "png": "png", "exr": "openexr", "openexr": "openexr",
                        "jpg": "jpeg", "jpeg": "jpeg"}
#: The suffix a writer gives a file of each format (temporary names keep it).
WRITE_FORMAT_EXT = {fmt: suffixes[0] for fmt, suffixes in WRITE_SUFFIXES.items()}

#: RAW suffixes whose metadata may carry a maker's vignetting calibration (Sony, Fujifilm, DNG).
CALIBRATED_RAW_SUFFIXES = frozenset({".arw", ".sr2", ".srf", ".raf", ".dng"})
assert CALIBRATED_RAW_SUFFIXES <= RAW_SUFFIXES


def suffix_kind(suffix: str) -> str | None:
    """The kind (a key of :data:`READ_SUFFIXES`) a file suffix such as ``".JPG"`` names,
    or ``None`` for one vigproc does not read.

    Examples
    --------
    >>> suffix_kind(".JPG"), suffix_kind(".nrw"), suffix_kind(".gif")
    ('jpeg', 'raw', None)
    """
    low = suffix.lower()
    return next((k for k, suffixes in READ_SUFFIXES.items() if low in suffixes), None)
