"""Reading images: any supported file as float32 *linear* light, or as its code values.

Reading
-------
:func:`read_image` returns an ``HxW`` (single channel) or ``HxWx3`` (colour)
``float32`` array whose values are proportional to scene light, plus an
:class:`ImageInfo` describing what was read and which transfer curve was assumed.

* JPEG, PNG, TIFF and OpenEXR go through OpenImageIO.  Integer formats come back
  nominally in ``[0, 1]``; float formats are returned as stored (no clipping).
* Camera RAW files (anything LibRaw decodes: DNG, CR2, NEF, ARW, KDC, RAF, ...) go
  through rawpy with a linear (gamma 1), non-auto-brightened, camera-white-balanced
  16-bit development, scaled to ``[0, 1]``.
* The format is decided by *content*: a PNG renamed ``.jpg`` is read as PNG, a
  text file renamed ``.jpg`` raises :class:`~vigproc.errors.UnsupportedFormatError`.
* Orientation is never applied (neither the EXIF ``Orientation`` tag nor the RAW
  flip): the pixel grid stays in sensor order, which is what a vignetting model
  centred on the optical axis needs, and keeps RAW and developed files consistent.

How stored values decode to linear light: :mod:`vigproc.io.transfer`.
"""

from __future__ import annotations

import contextlib
import dataclasses
import logging
import numbers
import os
import re
import stat
import struct
import tempfile
import threading
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import OpenImageIO as oiio

from vigproc.core.colour import cfa_rgb
from vigproc.core.pixels import reduce_codes
from vigproc.errors import ImageReadError, InvalidImageError, MemoryBudgetError, UnsupportedFormatError, VigprocError
from vigproc.io.formats import RAW_SUFFIXES, PathLike
from vigproc.io.jpeg import _jpeg_quality_of
from vigproc.io.transfer import LINEAR_TIFF_MARKER, _auto_transfer, _decode_lut, _decoder, _parse_transfer, recorded_transfer
from vigproc.scratch import scratch_folder

try:  # rawpy is optional at import time: without it RAW files are "unsupported".
    import rawpy
except ImportError:  # pragma: no cover - rawpy is installed in the project venv
    rawpy = None  # type: ignore[assignment]

logger = logging.getLogger("vigproc.io.images")  # the name it always logged under

#: OpenImageIO format names :func:`read_image` accepts (others, e.g. GIF, BMP, are rejected).
SUPPORTED_OIIO_FORMATS = frozenset({"jpeg", "png", "tiff", "openexr"})

#: Extensions tried with LibRaw *first* (content still decides: see :func:`read_image`).
RAW_EXTENSIONS = RAW_SUFFIXES

#: Default memory budget of one decoded image, in bytes (2 GiB): the float32 pixels
#: :func:`read_image` returns (width x height x channels x 4), so up to a 178-megapixel
#: colour frame.  A read peaks at about 1.25 times the decoded size, a whole correction
#: at about 3.5 times plus the process's own 0.3 GB (measured: docs/io.md, "Memory budget";
#: docs/benchmarks/speed.md, "Peak memory per worker").
DEFAULT_MEMORY_BUDGET = 2 * 2**30
#: Environment variable that sets the budget (bytes, or with a K/M/G/T suffix: powers of 1024).
MEMORY_BUDGET_ENV = "VIGPROC_MEMORY_BUDGET"
_SIZE_UNITS = {"": 1, "k": 2**10, "m": 2**20, "g": 2**30, "t": 2**40}

# Below this many bits per sensor pixel a RAW cannot hold its image (even lossy
# DNG needs ~2 bits/px; the 1996 Kodak DC50 KDC has ~1.9); such files are
# metadata stubs or badly truncated, and LibRaw would silently return zeros/garbage.
_RAW_MIN_BITS_PER_PIXEL = 0.25

_MAGIC: tuple[tuple[int, bytes, str], ...] = (
    (0, b"\x89PNG\r\n\x1a\n", "png"),
    (0, b"\xff\xd8\xff", "jpeg"),
    (0, b"II*\x00", "tiff"),
    (0, b"MM\x00*", "tiff"),
    (0, b"II+\x00", "tiff"),  # BigTIFF
    (0, b"MM\x00+", "tiff"),
    (0, b"v/1\x01", "openexr"),
    (0, b"GIF87a", "gif"),
    (0, b"GIF89a", "gif"),
    (8, b"WEBP", "webp"),
    (4, b"jP  ", "jpeg2000"),
    (0, b"\xff\x4f\xff\x51", "jpeg2000"),
)
# Content kinds that can never be a camera RAW (so no LibRaw attempt for them).
_NON_RAW_KINDS = frozenset({"png", "jpeg", "openexr", "gif", "webp", "jpeg2000"})

_FLOAT_FORMATS = frozenset({"half", "float", "double"})


@dataclass(frozen=True)
class ImageInfo:
    """What :func:`read_image` read and how it decoded it.

    Attributes
    ----------
    path : str
        The path as given (``os.fspath``).
    format : str
        ``'jpeg'``, ``'png'``, ``'tiff'``, ``'openexr'`` or ``'raw'``.
    width, height : int
        Size of the returned array (after RAW half-size, if any).
    channels : int
        Channels of the returned array: 1 (``HxW``) or 3 (``HxWx3``); alpha is dropped.
    bit_depth : str
        Stored sample type: ``'uint8'``, ``'uint16'``, ``'half'``, ``'float'``...
        (``'uint16'`` for RAW: the LibRaw development depth).
    transfer : str
        Transfer curve that was inverted: ``'linear'``, ``'srgb'`` or ``'gamma<g>'``.
    colorspace : str or None
        Colour space the file declared as reported by OpenImageIO
        (``oiio:ColorSpace``), ``None`` if it declared none (always ``None`` for RAW).
    """

    path: str
    format: str
    width: int
    height: int
    channels: int
    bit_depth: str
    transfer: str
    colorspace: str | None
    #: A JPEG's IJG quality (:func:`jpeg_quality`), read from the bytes already read.
    quality: int | None = None


#: Rows per band where a count over a whole frame needs no whole-frame temporary.
COUNT_BAND = 256

@dataclass(frozen=True, eq=False)
class EncodedImage:
    """A display-encoded frame as its file stores it: integer code values and the
    transfer curve that decodes them to linear light (:func:`read_encoded`).

    Correcting it in its own domain (:func:`vigproc.core.correct.correct_codes`) and
    estimating from a reduced copy (:meth:`reduced`) spare a float frame; :meth:`linear`
    is what :func:`read_image` returns. :func:`write_image` writes one whose depth and
    transfer are those asked for as it is.

    Attributes
    ----------
    codes : numpy.ndarray
        ``HxW`` or ``HxWx3``, ``uint8`` or ``uint16``.
    transfer : str
        ``'srgb'``, ``'linear'`` or ``'gamma<g>'``.
    """

    codes: np.ndarray
    transfer: str
    # the last reduced copy (k, binned, usable): the estimate and the learning's evidence
    # read the same one, made once
    _reduced: list = field(default_factory=list, init=False, repr=False, compare=False)
    # what is counted over every code, once: "range" (lowest, highest), "top" (samples at the top code)
    _counts: dict = field(default_factory=dict, init=False, repr=False, compare=False)

    @property
    def shape(self) -> tuple[int, ...]:
        return self.codes.shape

    @property
    def ndim(self) -> int:
        return self.codes.ndim

    @property
    def size(self) -> int:
        return int(self.codes.size)

    @property
    def depth(self) -> str:
        return str(self.codes.dtype)

    def decode_table(self) -> np.ndarray:
        """float32 linear value of every code."""
        return _decode_lut(self.transfer, 256 if self.codes.dtype == np.uint8 else 65536)

    def linear(self) -> np.ndarray:
        """The frame as float32 linear light (what :func:`read_image` returns)."""
        return np.ascontiguousarray(self.decode_table()[self.codes])

    def reduced(self, k: int) -> tuple[np.ndarray, np.ndarray | None]:
        """The frame's linear light binned ``k``×``k`` (float32) and its usable blocks
        (:func:`vigproc.core.pixels.reduce_codes`).

        Made once per ``k``: the copy of the last ``k`` asked for is kept (read-only) and
        handed out again, so the estimate and the frame's evidence for its lens's
        profile read one reduction. :meth:`forget_reduced` drops it (codes overwritten
        in place)."""
        k = int(k)
        if self._reduced and self._reduced[0] == k:
            return self._reduced[1], self._reduced[2]
        small, usable = reduce_codes(self.codes, self.decode_table(), k)
        for a in (small, usable):
            if a is not None:
                a.setflags(write=False)
        self._reduced[:] = [k, small, usable]
        return small, usable

    def code_range(self) -> tuple[int, int]:
        """The lowest and highest code of the frame, counted once (kept, as :meth:`reduced`).

        Returns
        -------
        (int, int)
        """
        got = self._counts.get("range")
        if got is None:
            got = self._counts["range"] = (int(self.codes.min()), int(self.codes.max()))
        return got

    def top_count(self) -> int:
        """How many samples hold the top code of the frame's depth (its white point),
        counted once (kept, as :meth:`reduced`), in bands of rows: a full-frame boolean
        temporary would be a third of an 8-bit frame.

        Returns
        -------
        int
        """
        got = self._counts.get("top")
        if got is None:
            a, top = self.codes, np.iinfo(self.codes.dtype).max
            got = self._counts["top"] = sum(int(np.count_nonzero(a[r:r + COUNT_BAND] == top))
                                            for r in range(0, max(a.shape[0], 1), COUNT_BAND))
        return got

    def forget_reduced(self) -> None:
        """Drop the kept reduced copy (:meth:`reduced`) and counts (:meth:`code_range`,
        :meth:`top_count`): the codes are about to change."""
        self._reduced.clear()
        self._counts.clear()


def _q(path: str) -> str:
    # repr() keeps messages on one line even for names containing newlines.
    return repr(path)


def _fspath(path: PathLike, error: type[Exception] = ImageReadError) -> str:
    """``path`` as a str; anything that is not a path raises ``error`` (a typed error)."""
    try:
        p = os.fspath(path)
    except TypeError:
        verb = "read image" if issubclass(error, ImageReadError) else "write"
        raise error(f"cannot {verb}: path must be a str, bytes or os.PathLike, "
                    f"got {type(path).__name__}") from None
    return os.fsdecode(p) if isinstance(p, bytes) else p


def _unencodable(path: str) -> bool:
    # Names that are not valid UTF-8 on disk (surrogate-escaped by Python) cannot
    # be passed to OpenImageIO, whose binding only takes UTF-8 strings.
    try:
        path.encode("utf-8")
    except UnicodeEncodeError:
        return True
    return False


def _check_regular_file(path: str) -> int:
    """Stat ``path``; return its size or raise a typed error."""
    try:
        st = os.stat(path)
    except FileNotFoundError:
        raise ImageReadError(f"cannot read image {_q(path)}: file not found") from None
    except PermissionError:
        raise ImageReadError(f"cannot read image {_q(path)}: permission denied") from None
    except (OSError, ValueError) as exc:  # ValueError: embedded NUL byte
        raise ImageReadError(f"cannot read image {_q(path)}: {exc}") from None
    if stat.S_ISDIR(st.st_mode):
        # `vigproc correct FOLDER`: say how a folder is given (the README's "Correct a folder")
        raise ImageReadError(f"cannot read image {_q(path)}: is a directory (give its photos, "
                             f"{os.path.join(str(path), '*')}, or run 'vigproc batch' on it)")
    if not stat.S_ISREG(st.st_mode):
        # FIFOs/devices would block or stream forever.
        raise ImageReadError(f"cannot read image {_q(path)}: not a regular file")
    if st.st_size == 0:
        raise ImageReadError(f"cannot read image {_q(path)}: file is empty (0 bytes)")
    return st.st_size


@contextlib.contextmanager
def _utf8_alias(path: str):
    """A UTF-8 name for the file ``path`` names in bytes that are not UTF-8 (OpenImageIO's
    binding takes UTF-8 only): a symbolic link, with the same extension, in a private
    temporary folder removed afterwards. The file itself is neither moved nor modified."""
    ext = os.path.splitext(path)[1]
    ext = ext if ext and not _unencodable(ext) and ext.isprintable() else ""
    folder = scratch_folder("name")  # after a kill: removed by the next process's sweep
    alias = os.path.join(folder, "image" + ext)
    try:
        os.symlink(os.fsencode(os.path.abspath(path)), alias)
        yield alias
    finally:
        with contextlib.suppress(OSError):
            os.unlink(alias)
        with contextlib.suppress(OSError):
            os.rmdir(folder)


#: Bytes of a file read before decoding: enough for a JPEG's quantisation table after
#: its EXIF segment (at most 64 KiB) in most camera files (:func:`jpeg_quality`).
HEAD_BYTES = 1 << 17


def _read_head(path: str, n: int = HEAD_BYTES) -> bytes:
    try:
        with open(path, "rb") as fh:
            return fh.read(n)
    except OSError as exc:
        err = ImageReadError(f"cannot read image {_q(path)}: {exc.strerror or exc}")
        err.errno = exc.errno  # EIO/ESTALE of a network share: a retry may help (vigproc.pipeline.faults)
        raise err from None


def _sniff(head: bytes) -> str | None:
    for offset, magic, kind in _MAGIC:
        if head[offset : offset + len(magic)] == magic:
            return kind
    return None


class _RawUnsupported(Exception):
    """LibRaw does not recognise the file (internal: lets the caller try OpenImageIO)."""


def memory_budget() -> int:
    """The memory budget of one decoded image in bytes: ``$VIGPROC_MEMORY_BUDGET``
    (``2G``, ``1500M``, ``800MiB``, ``3000000000``) or :data:`DEFAULT_MEMORY_BUDGET`.

    Raises
    ------
    InvalidImageError
        The variable is set but is not a positive size.
    """
    text = os.environ.get(MEMORY_BUDGET_ENV, "").strip()
    if not text:
        return DEFAULT_MEMORY_BUDGET
    m = re.fullmatch(r"(\d+(?:\.\d*)?)\s*([kmgt]?)(?:i?b)?", text.lower())
    value = float(m.group(1)) * _SIZE_UNITS[m.group(2)] if m else 0.0
    if not value >= 1:
        raise InvalidImageError(f"{MEMORY_BUDGET_ENV}={text!r} is not a memory size (e.g. 2G, 1500M or bytes)")
    return int(value)


def _check_budget(path: str, width: int, height: int, channels: int, budget: int) -> None:
    """Refuse, from the header alone, an image whose decoded float32 pixels exceed ``budget``."""
    need = width * height * channels * 4
    if need > budget:
        raise MemoryBudgetError(
            f"cannot read image {_q(path)}: its {width}x{height}x{channels} pixels need {need / 2**30:.2f} GiB "
            f"as float32, over the memory budget of {budget / 2**30:.2f} GiB ({MEMORY_BUDGET_ENV}); "
            "refused before decoding (possible decompression bomb)")


def read_encoded(path: PathLike, *, transfer: str = "auto", raw_half_size: bool = False,
                 max_pixels: int = 200_000_000,
                 max_bytes: int | None = None) -> tuple[EncodedImage | np.ndarray, ImageInfo]:
    """:func:`read_image`, but an 8- or 16-bit file (JPEG, PNG, integer TIFF) comes back
    as its code values (:class:`EncodedImage`), not decoded to float; float files and
    RAW as :func:`read_image` returns them. Parameters and errors as :func:`read_image`."""
    return read_image(path, transfer=transfer, raw_half_size=raw_half_size, max_pixels=max_pixels,
                      max_bytes=max_bytes, _codes=True)


def read_image(
    path: PathLike,
    *,
    transfer: str = "auto",
    raw_half_size: bool = False,
    max_pixels: int = 200_000_000,
    max_bytes: int | None = None,
    _codes: bool = False,
) -> tuple[np.ndarray, ImageInfo]:
    """Read an image as float32 linear light.

    Parameters
    ----------
    path : str or os.PathLike
        Image file (JPEG, PNG, TIFF, OpenEXR or a camera RAW LibRaw decodes).
        The format is decided by content; the extension only decides whether
        LibRaw is tried first.  The file is never modified.
    transfer : {'auto', 'linear', 'srgb', 'gamma<g>'}
        Transfer curve to invert.  ``'auto'`` follows the file's metadata (see the
        module docstring); the others force a curve for OpenImageIO formats.
        RAW files are always developed linearly and ignore this argument.
    raw_half_size : bool
        Develop RAW files at half resolution (each 2x2 Bayer block -> one pixel,
        no demosaicing).  Ignored for other formats.
    max_pixels : int
        Refuse images with more than this many pixels (width * height) before any
        pixel is decoded, to defuse decompression bombs.  Must be positive.
    max_bytes : int, optional
        Memory budget: refuse, from the header and before any pixel is decoded,
        an image whose float32 result (width * height * channels * 4 bytes) would
        be larger.  Default :func:`memory_budget` (``$VIGPROC_MEMORY_BUDGET``, else
        :data:`DEFAULT_MEMORY_BUDGET`, 2 GiB).

    Returns
    -------
    pixels : numpy.ndarray
        ``float32``, ``HxW`` for single-channel images, ``HxWx3`` for colour
        (alpha and extra channels dropped).  Integer formats and RAW are nominally
        in ``[0, 1]``; float formats are returned as stored.
    info : ImageInfo
        What was read and how it was decoded.

    Raises
    ------
    ImageReadError
        Missing, unreadable, empty, truncated or corrupt file, or ``path`` is not a path.
    UnsupportedFormatError
        Content is not a supported image format (or a RAW LibRaw cannot decode).
    InvalidImageError
        Zero or absurd dimensions, or no usable channels; also an unknown
        ``transfer`` name or a ``max_pixels`` that is not a positive number (this
        error is a ``ValueError`` too).
    MemoryBudgetError
        The decoded image would exceed the memory budget (an ``InvalidImageError``).
    """
    fspath = _fspath(path)
    want = _parse_transfer(transfer, allow_auto=True)
    # bool is an int, but max_pixels=True would refuse every image; NaN fails "> 0".
    budget = memory_budget() if max_bytes is None else max_bytes
    for name, v in (("max_pixels", max_pixels), ("max_bytes", budget)):
        if not isinstance(v, numbers.Real) or isinstance(v, bool) or not v > 0:
            raise InvalidImageError(f"{name} must be a positive integer, got {v!r}")
    budget = int(budget)
    size = _check_regular_file(fspath)
    if _unencodable(fspath):  # a name in bytes that are not UTF-8: read through a UTF-8 alias
        with _utf8_alias(fspath) as alias:
            try:
                img, info = read_image(alias, transfer=transfer, raw_half_size=raw_half_size,
                                       max_pixels=max_pixels, max_bytes=budget, _codes=_codes)
            except VigprocError as exc:  # the message names the file, not its alias
                raise type(exc)(str(exc).replace(_q(alias), _q(fspath))) from None
        return img, dataclasses.replace(info, path=fspath)
    head = _read_head(fspath)
    kind = _sniff(head)
    ext = os.path.splitext(fspath)[1].lower()

    raw_first = ext in RAW_EXTENSIONS and kind not in _NON_RAW_KINDS
    raw_note = ""
    if raw_first:
        try:
            return _read_raw(fspath, size, want, raw_half_size, max_pixels, budget, codes=_codes)
        except _RawUnsupported as exc:
            raw_note = str(exc)
            logger.debug("%s: LibRaw does not recognise it (%s); trying OpenImageIO", fspath, exc)

    if kind == "png":
        # libpng prints its errors (``libpng error: IDAT: Read error``) straight to the C
        # stderr, outside OpenImageIO, whose own message already holds them: kept off the
        # terminal and out of --log-json's one object per line, logged at debug level
        said: list[str] = []
        try:
            with _c_stderr_into(said):
                return _read_through_oiio(fspath, size, kind, head, want, raw_first, raw_note, raw_half_size,
                                          max_pixels, budget, _codes)
        finally:
            if said:
                logger.debug("%s: libpng said: %s", fspath, "; ".join(said)[:500])
    return _read_through_oiio(fspath, size, kind, head, want, raw_first, raw_note, raw_half_size, max_pixels,
                              budget, _codes)


def _read_through_oiio(fspath: str, size: int, kind: str | None, head: bytes, want: str, raw_first: bool,
                       raw_note: str, raw_half_size: bool, max_pixels: int, budget: int,
                       codes: bool = False) -> tuple[np.ndarray, ImageInfo]:
    """The rest of :func:`read_image` once LibRaw did not take the file: OpenImageIO, or
    LibRaw after all for what turns out to be a TIFF-based RAW."""
    inp, err = _oiio_open(fspath)
    if inp is None:
        if err and (("exceeds the" in err and "limit" in err) or "claimed to be" in err):
            raise InvalidImageError(
                f"cannot read image {_q(fspath)}: declared size is absurd "
                f"(possible decompression bomb): {_one_line(err)}"
            )
        if kind in SUPPORTED_OIIO_FORMATS:
            raise ImageReadError(
                f"cannot read image {_q(fspath)}: corrupt or truncated {kind.upper()} file: "
                f"{_one_line(err)}"
            )
        if not raw_first and kind is None:
            try:
                # Content unknown and the name does not claim RAW: any LibRaw
                # failure to open means "not a RAW", not "broken RAW".
                return _read_raw(fspath, size, want, raw_half_size, max_pixels, budget, probing=True,
                                 codes=codes)
            except _RawUnsupported as exc:
                raw_note = str(exc)
        if kind is not None:
            raise UnsupportedFormatError(
                f"cannot read image {_q(fspath)}: {kind} files are not supported "
                "(JPEG, PNG, TIFF, OpenEXR and camera RAW are)"
            )
        start = head[:8]
        raise UnsupportedFormatError(
            f"cannot read image {_q(fspath)}: content is not a recognised image format "
            f"(JPEG, PNG, TIFF, OpenEXR or camera RAW; file starts with {start!r})"
            + (f"; OpenImageIO: {_one_line(err)}" if err else "")
        )

    try:
        spec = inp.spec()
        if raw_first and kind == "tiff" and _tiff_has_subifds(fspath):
            # named as a camera RAW, laid out like one (the sensor data in a SubIFD), and
            # LibRaw cannot decode it: OpenImageIO would read its embedded preview, not the
            # photograph (a plain TIFF merely named .nef has no SubIFDs and is read)
            raise UnsupportedFormatError(
                f"cannot read image {_q(fspath)}: camera RAW that LibRaw cannot decode"
                + (f" ({raw_note})" if raw_note else "")
                + "; its embedded preview is not used (rename the file if it is a plain TIFF)"
            )
        if kind == "tiff" and _tiff_looks_raw(head, spec):
            # OIIO would read IFD0 (usually a thumbnail, or the undemosaiced CFA).
            inp.close()
            inp = None
            if raw_first:
                raise UnsupportedFormatError(
                    f"cannot read image {_q(fspath)}: camera RAW that LibRaw cannot decode"
                    + (f" ({raw_note})" if raw_note else "")
                )
            try:
                return _read_raw(fspath, size, want, raw_half_size, max_pixels, budget, codes=codes)
            except _RawUnsupported as exc:
                raise UnsupportedFormatError(
                    f"cannot read image {_q(fspath)}: looks like a TIFF-based camera RAW "
                    f"but LibRaw cannot decode it ({exc})"
                ) from None
        return _read_oiio(inp, fspath, want, max_pixels, budget, codes, head)
    finally:
        if inp is not None:
            inp.close()


def _one_line(msg: str | None) -> str:
    return " / ".join(s.strip() for s in (msg or "unknown error").splitlines() if s.strip())


def _oiio_open(path: str) -> tuple[oiio.ImageInput | None, str]:
    oiio.geterror()  # clear stale global errors so the message is about this file
    config = oiio.ImageSpec()
    # Keep colour values as stored; OIIO would otherwise premultiply by alpha.
    config.attribute("oiio:UnassociatedAlpha", 1)
    try:
        inp = oiio.ImageInput.open(path, config)
    except Exception as exc:  # binding-level failures (e.g. unencodable path)
        return None, f"{type(exc).__name__}: {exc}"
    if inp is None:
        return None, oiio.geterror()
    return inp, ""


def _tiff_has_subifds(path: str, limit: int = 1 << 16) -> bool:
    """Whether a TIFF's first IFD has a SubIFDs tag (330): the layout of NEF, ARW, PEF,
    DNG... whose IFD0 is a preview and whose sensor data lives in a SubIFD."""
    try:
        with open(path, "rb") as fh:
            data = fh.read(limit)
        order = {b"II": "<", b"MM": ">"}.get(data[:2])
        if order is None:
            return False
        (ifd,) = struct.unpack_from(order + "I", data, 4)
        (n,) = struct.unpack_from(order + "H", data, ifd)
        for i in range(min(n, 4096)):
            (tag,) = struct.unpack_from(order + "H", data, ifd + 2 + 12 * i)
            if tag == 330:
                return True
    except (OSError, struct.error):
        return False
    return False


def _tiff_looks_raw(head: bytes, spec: oiio.ImageSpec) -> bool:
    """Whether a TIFF-structured file is really a camera RAW (DNG, CR2, NEF, KDC...)."""
    if head[8:10] == b"CR":  # Canon CR2 signature after the TIFF header
        return True
    photometric = spec.get_int_attribute("tiff:PhotometricInterpretation", -1)
    if photometric in (32803, 34892):  # CFA, LinearRaw (DNG)
        return True
    # NewSubfileType bit 0 on the first IFD: it is a reduced-resolution preview,
    # the real image lives in a SubIFD -- the layout of DNG/NEF/KDC/ARW...
    return bool(spec.get_int_attribute("tiff:subfiletype", 0) & 1)


def _select_channels(spec: oiio.ImageSpec, path: str) -> list[int]:
    """The channels to read: [R, G, B], or [grey].

    Alpha and depth are dropped. Two colour-like channels are grey plus an extra
    sample only when the file says it is grey (TIFF photometric min-is-black/white,
    the usual grey + alpha without an alpha tag); otherwise they are neither grey nor
    RGB and the file is refused rather than silently read as its first channel.
    """
    names = [str(n) for n in spec.channelnames]
    upper = [n.upper() for n in names]
    alpha = spec.alpha_channel
    if all(c in upper for c in ("R", "G", "B")):
        return [upper.index("R"), upper.index("G"), upper.index("B")]
    if "Y" in upper:
        return [upper.index("Y")]
    usable = [i for i in range(spec.nchannels) if i != alpha and upper[i] not in ("A", "Z")]
    if len(usable) >= 3:
        if len(usable) > 3:
            logger.warning("%s: reading channels %s as RGB and ignoring %s", path,
                           [names[i] for i in usable[:3]], [names[i] for i in usable[3:]])
        return usable[:3]
    if len(usable) == 2:
        if spec.get_int_attribute("tiff:PhotometricInterpretation", -1) in (0, 1):
            logger.info("%s: grey TIFF with an extra sample; reading the grey channel", path)
            return usable[:1]
        raise UnsupportedFormatError(
            f"cannot read image {_q(path)}: two colour channels {[names[i] for i in usable]} "
            "are neither grey nor RGB"
        )
    return usable[:1]


#: Rows read at a time from a file stored in scanlines (:func:`_read_pixels`).
READ_BAND = 256


def _read_pixels(inp: oiio.ImageInput, spec: oiio.ImageSpec, read_as: str) -> np.ndarray | None:
    """The whole first subimage as an ``(h, w, nchannels)`` array of ``read_as``, or None
    when the decoder fails (its error is ``inp.geterror()``).

    The Python binding decodes into a buffer of its own and copies it into the array it
    returns: one ``read_image`` holds the frame twice.  A file stored in scanlines is read
    in bands of :data:`READ_BAND` rows into one array instead (the peak is one frame and
    a band); a tiled file whole.
    """
    h, w, n = int(spec.height), int(spec.width), int(spec.nchannels)
    if int(spec.tile_width) > 0 or h <= READ_BAND:
        data = inp.read_image(0, 0, 0, n, read_as)
        return None if data is None else np.asarray(data).reshape(h, w, n)
    out = np.empty((h, w, n), dtype=np.float32 if read_as == "float" else np.dtype(read_as))
    y0, z = int(spec.y), int(spec.z)
    for r in range(0, h, READ_BAND):
        e = min(r + READ_BAND, h)
        part = inp.read_scanlines(0, 0, y0 + r, y0 + e, z, 0, n, read_as)
        if part is None:
            return None
        out[r:e] = np.asarray(part).reshape(e - r, w, n)
        del part
    return out


def _read_oiio(inp: oiio.ImageInput, path: str, want: str, max_pixels: int,
               budget: int = DEFAULT_MEMORY_BUDGET, codes: bool = False,
               head: bytes = b"") -> tuple[np.ndarray | EncodedImage, ImageInfo]:
    fmt = inp.format_name()
    spec = inp.spec()
    if fmt not in SUPPORTED_OIIO_FORMATS:
        raise UnsupportedFormatError(
            f"cannot read image {_q(path)}: {fmt} files are not supported "
            "(JPEG, PNG, TIFF, OpenEXR and camera RAW are)"
        )
    if spec.deep:
        raise UnsupportedFormatError(f"cannot read image {_q(path)}: deep images are not supported")
    w, h, d = int(spec.width), int(spec.height), int(spec.depth)
    if w <= 0 or h <= 0 or d <= 0:
        raise InvalidImageError(f"cannot read image {_q(path)}: zero dimension ({w}x{h})")
    if d > 1:
        raise UnsupportedFormatError(f"cannot read image {_q(path)}: volume images (depth {d}) are not supported")
    # Checked on the header only: no pixel has been decoded yet.
    if w * h > max_pixels:
        raise InvalidImageError(
            f"cannot read image {_q(path)}: declared size {w}x{h} = {w * h} pixels exceeds "
            f"the limit of {max_pixels} pixels (possible decompression bomb)"
        )
    chans = _select_channels(spec, path)
    if not chans:
        raise InvalidImageError(f"cannot read image {_q(path)}: no colour channel (channels {list(spec.channelnames)})")
    _check_budget(path, w, h, len(chans), budget)

    stored = str(spec.format)
    is_float = stored in _FLOAT_FORMATS
    colorspace = spec.get_string_attribute("oiio:ColorSpace", "") or None
    gamma = float(spec.get_float_attribute("oiio:Gamma", 0.0))
    description = LINEAR_TIFF_MARKER if recorded_transfer(spec) else spec.get_string_attribute("ImageDescription", "")
    tr = _auto_transfer(is_float, colorspace, gamma, description) if want == "auto" else want

    # 8/16-bit are read as integers and decoded through an exact float64 LUT.
    read_as = stored if stored in ("uint8", "uint16") else "float"
    try:
        data = _read_pixels(inp, spec, read_as)
    except Exception as exc:  # binding-level failure (e.g. MemoryError)
        raise ImageReadError(f"cannot read image {_q(path)}: {type(exc).__name__}: {exc}") from None
    err = inp.geterror()
    if data is None:
        raise ImageReadError(f"cannot read image {_q(path)}: corrupt or truncated {fmt.upper()} file: {_one_line(err)}")
    if err:
        if re.search(r"extraneous bytes before marker", err) and "Premature" not in err:
            # libjpeg skipped garbage between markers; the scan decoded completely.
            logger.warning("%s: %s", path, _one_line(err))
        else:
            raise ImageReadError(
                f"cannot read image {_q(path)}: corrupt or truncated {fmt.upper()} file: {_one_line(err)}"
            )
    if len(chans) == 1:
        data = data[..., chans[0]]
    elif chans != list(range(spec.nchannels)):  # avoid a copy for plain RGB
        data = data[..., chans]

    if codes and read_as in ("uint8", "uint16"):
        pixels = EncodedImage(np.ascontiguousarray(data), tr)
    elif read_as in ("uint8", "uint16"):
        levels = 256 if read_as == "uint8" else 65536
        pixels = np.ascontiguousarray(_decode_lut(tr, levels)[data], dtype=np.float32)
    else:
        pixels = np.ascontiguousarray(data, dtype=np.float32)
        if tr != "linear":
            pixels = _decoder(tr)(pixels).astype(np.float32, copy=False)
        pixels = np.ascontiguousarray(pixels, dtype=np.float32)

    info = ImageInfo(
        path=path,
        format=fmt,
        width=w,
        height=h,
        channels=1 if pixels.ndim == 2 else int(pixels.shape[2]),
        bit_depth=stored,
        transfer=tr,
        colorspace=colorspace,
        quality=_jpeg_quality_of(head) if fmt == "jpeg" else None,
    )
    logger.debug("read %s: %s", path, info)
    return pixels, info


#: One capture of the C-level stderr at a time (it is the process's, not a thread's).
_STDERR_LOCK = threading.RLock()  # re-entrant: a capture may nest (PNG, then LibRaw)


@contextlib.contextmanager
def _c_stderr_into(lines: list[str]):
    """Capture what C code writes to file descriptor 2 meanwhile into ``lines``.

    LibRaw prints some complaints (``FILE: Unexpected end of file``) straight to the C
    stderr, which would break a one-JSON-object-per-line log and say things twice; the
    caller routes them through logging or into its error instead.
    """
    with _STDERR_LOCK:
        try:
            saved = os.dup(2)
        except OSError:  # no stderr at all: nothing to capture
            yield
            return
        try:
            with tempfile.TemporaryFile() as tmp:
                os.dup2(tmp.fileno(), 2)
                try:
                    yield
                finally:
                    os.dup2(saved, 2)
                    tmp.seek(0)
                    text = tmp.read(1 << 16).decode("utf-8", "replace")
                    for line in text.splitlines():
                        line = " ".join(line.split())
                        if line and line not in lines:
                            lines.append(line)
        finally:
            os.close(saved)


#: LibRaw's development of a RAW (rawpy ``postprocess``), also what ``vigproc bench
#: throughput --raw`` times as the floor.
RAW_DEVELOP: dict[str, Any] = dict(
    gamma=(1.0, 1.0),  # linear output
    no_auto_bright=True,  # no data-dependent exposure scaling
    adjust_maximum_thr=0.0,  # keep the white level fixed (default lowers it per image)
    use_camera_wb=True,
    output_bps=16,
    # 0 = never rotate: sensor order, as OIIO does (it ignores EXIF Orientation).
    user_flip=0,
)


def _read_raw(path: str, *args, **kwargs) -> tuple[np.ndarray, ImageInfo]:
    """Develop a RAW linearly with LibRaw (:func:`_read_raw_libraw`); LibRaw's own
    messages go into the error when it fails and to the log (info) when it does not."""
    said: list[str] = []
    try:
        with _c_stderr_into(said):
            return _read_raw_libraw(path, *args, **kwargs)
    except (ImageReadError, InvalidImageError) as exc:
        if not said:
            raise
        shown = "; ".join(s.replace(path, "").strip(": ") or s for s in said)[:300]
        err = type(exc)(f"{exc} (LibRaw said: {shown})")
        err.__dict__.update(exc.__dict__)
        raise err from None
    finally:
        if said:
            logger.info("%s: LibRaw said: %s", path, "; ".join(said)[:500])


def read_cfa_planes(path: str | os.PathLike[str]) -> np.ndarray:
    """A Bayer RAW's colour planes before demosaicing (no white balance, no colour
    matrix): (H/2)×(W/2)×3 linear R, G, B of the visible area, black-subtracted and
    scaled by the white level (:func:`vigproc.core.colour.cfa_rgb`), for measuring a
    flat frame's colour shading per CFA plane.

    Raises
    ------
    ImageReadError
        The file cannot be read as a RAW.
    InvalidImageError
        Not a Bayer sensor (X-Trans, four colours, a linear DNG).
    """
    p = os.fspath(path)
    if rawpy is None:  # pragma: no cover
        raise ImageReadError(f"cannot read image {_q(p)}: rawpy is not installed")
    try:
        with rawpy.imread(p) as raw:
            pattern = raw.raw_pattern
            if pattern is None:
                raise InvalidImageError(f"{_q(p)} has no colour filter array (a linear or monochrome raw)")
            return cfa_rgb(raw.raw_image_visible, pattern, raw.color_desc.decode("ascii", "replace"),
                           raw.black_level_per_channel, float(raw.white_level))
    except (rawpy.LibRawError, OSError, ValueError, MemoryError) as exc:
        raise ImageReadError(f"cannot read image {_q(p)}: {_libraw_msg(exc) if isinstance(exc, rawpy.LibRawError) else exc}") from None


def _read_raw_libraw(
    path: str, size: int, want: str, half_size: bool, max_pixels: int, budget: int = DEFAULT_MEMORY_BUDGET, *,
    probing: bool = False, codes: bool = False
) -> tuple[np.ndarray | EncodedImage, ImageInfo]:
    """Develop a RAW linearly with LibRaw; ``codes``: LibRaw's linear 16-bit values as
    they are (:class:`EncodedImage`, :func:`read_encoded`), not a float32 copy.

    Raises ``_RawUnsupported`` if LibRaw does not recognise the file (with
    ``probing=True``: if LibRaw fails to open it for any reason).
    """
    if rawpy is None:  # pragma: no cover
        raise _RawUnsupported("rawpy is not installed")
    if want != "linear" and want != "auto":
        logger.warning("%s: transfer=%r ignored for RAW files (always developed linearly)", path, want)
    try:
        raw = rawpy.imread(path)
    except rawpy.LibRawFileUnsupportedError as exc:
        raise _RawUnsupported(_libraw_msg(exc)) from None
    except (rawpy.LibRawError, OSError, ValueError, UnicodeError) as exc:
        if probing:
            raise _RawUnsupported(_libraw_msg(exc)) from None
        if isinstance(exc, rawpy.LibRawTooBigError):
            raise InvalidImageError(
                f"cannot read image {_q(path)}: RAW dimensions are absurd ({_libraw_msg(exc)})"
            ) from None
        raise ImageReadError(f"cannot read image {_q(path)}: RAW file is truncated or corrupt ({_libraw_msg(exc)})") from None
    try:
        sizes = raw.sizes
        rw, rh = int(sizes.raw_width), int(sizes.raw_height)
        if rw <= 0 or rh <= 0 or sizes.width <= 0 or sizes.height <= 0:
            raise InvalidImageError(f"cannot read image {_q(path)}: RAW has zero dimension ({rw}x{rh})")
        if rw * rh > max_pixels:
            raise InvalidImageError(
                f"cannot read image {_q(path)}: RAW sensor size {rw}x{rh} exceeds the limit of "
                f"{max_pixels} pixels"
            )
        if size * 8 < _RAW_MIN_BITS_PER_PIXEL * rw * rh:
            raise ImageReadError(
                f"cannot read image {_q(path)}: RAW file is truncated or its image data was stripped "
                f"({size} bytes for a {rw}x{rh} sensor)"
            )
        ow, oh = int(sizes.width), int(sizes.height)  # the developed frame (user_flip=0: not rotated)
        if half_size:
            ow, oh = (ow + 1) // 2, (oh + 1) // 2
        _check_budget(path, ow, oh, 3, budget)
        rgb = raw.postprocess(**RAW_DEVELOP, half_size=half_size)
    except (InvalidImageError, ImageReadError):
        raise
    except rawpy.LibRawTooBigError as exc:
        raise InvalidImageError(f"cannot read image {_q(path)}: RAW dimensions are absurd ({_libraw_msg(exc)})") from None
    except (rawpy.LibRawError, OSError, ValueError, MemoryError) as exc:
        raise ImageReadError(f"cannot read image {_q(path)}: RAW decoding failed ({_libraw_msg(exc)})") from None
    finally:
        raw.close()

    if codes:
        pixels = np.asarray(rgb)
    else:
        pixels = np.asarray(rgb, dtype=np.float32)
        pixels *= np.float32(1.0 / 65535.0)
    if pixels.ndim == 3 and pixels.shape[2] == 1:
        pixels = pixels[..., 0]
    h, w = pixels.shape[:2]
    info = ImageInfo(
        path=path,
        format="raw",
        width=int(w),
        height=int(h),
        channels=1 if pixels.ndim == 2 else int(pixels.shape[2]),
        bit_depth="uint16",
        transfer="linear",
        colorspace=None,
    )
    logger.debug("read RAW %s: %s", path, info)
    if codes:  # linear codes: the estimate bins them, the correction stays in them (pipeline.encoded)
        return EncodedImage(np.ascontiguousarray(pixels, dtype=np.uint16), "linear"), info
    return pixels, info


def _libraw_msg(exc: BaseException) -> str:
    msg = exc.args[0] if exc.args else exc
    if isinstance(msg, bytes):
        msg = msg.decode("utf-8", "replace")
    return f"{type(exc).__name__}: {msg}"
