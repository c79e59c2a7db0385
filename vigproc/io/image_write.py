"""Writing images atomically: TIFF, PNG, OpenEXR and JPEG from linear light.

Writing
-------
:func:`write_image` writes TIFF (8/16-bit or float), OpenEXR (half or float) and
PNG (8/16-bit) atomically: a temporary file in the destination directory is
written, fsync'ed and renamed over the destination with :func:`os.replace`.
"""

from __future__ import annotations

import errno
import logging
import os
import shutil

import numpy as np
import OpenImageIO as oiio

from vigproc.atomic import replacing
from vigproc.errors import (DiskFullError, ImageWriteError, InvalidImageError, OutputRefusedError, OutputSettingsError,
                            write_error)
from vigproc.io.formats import WRITE_EXT_FORMAT, WRITE_FORMAT_ALIASES, WRITE_FORMAT_EXT, PathLike
from vigproc.io.icc import linear_srgb_profile
from vigproc.io.image_read import EncodedImage, _fspath, _one_line, _q, _unencodable
from vigproc.io.jpeg import DEFAULT_JPEG_QUALITY
from vigproc.io.transfer import LINEAR_TIFF_MARKER, _parse_transfer, _quantise

logger = logging.getLogger("vigproc.io.images")  # the name it always logged under

_EXT_FORMAT, _FORMAT_ALIASES, _FORMAT_EXT = WRITE_EXT_FORMAT, WRITE_FORMAT_ALIASES, WRITE_FORMAT_EXT
_FORMAT_DEPTHS = {
    "tiff": ("uint16", "uint8", "float"),
    "png": ("uint16", "uint8"),
    "openexr": ("half", "float"),
    "jpeg": ("uint8",),
}


#: Largest finite value of each float bit depth (IEEE half and single precision).
FLOAT_MAX = {"half": 65504.0, "float": float(np.finfo(np.float32).max)}


def write_image(
    path: PathLike,
    img: np.ndarray,
    *,
    format: str | None = None,
    bit_depth: str | None = None,
    transfer: str = "linear",
    quality: int | None = None,
) -> None:
    """Write a linear image atomically.

    Parameters
    ----------
    path : str or os.PathLike
        Destination.  Replaced atomically (temporary file in the same directory,
        fsync, :func:`os.replace`); never left partially written.
    img : numpy.ndarray
        ``HxW``, ``HxWx1`` or ``HxWx3`` linear values (any real dtype), finite.
        Integer outputs clip to ``[0, 1]`` (with a warning when more than 1 % of the
        values are above 1, the sign of integer codes passed instead of ``[0, 1]``
        floats); float outputs are written as given and must fit the format
        (``|v| <= 65504`` for half, float32's range for float).
    format : {'tiff', 'png', 'openexr', 'jpeg'}, optional
        Defaults to the extension (``.tif``/``.tiff``, ``.png``, ``.exr``,
        ``.jpg``/``.jpeg``).
    bit_depth : {'uint8', 'uint16', 'half', 'float'}, optional
        Defaults to ``'uint16'`` for TIFF/PNG, ``'half'`` for EXR and ``'uint8'`` for
        JPEG.  TIFF takes uint8/uint16/float, PNG uint8/uint16, EXR half/float, JPEG
        uint8.
    transfer : {'linear', 'srgb'}
        Encoding of the stored values; ``'srgb'`` is for integer depths only, and
        JPEG takes only ``'srgb'`` (8 bits cannot hold linear shadows).  The file is
        tagged so that :func:`read_image` decodes it back to ``img``.
    quality : int, optional
        JPEG quality 1–100 (default :data:`DEFAULT_JPEG_QUALITY`); other formats
        refuse it.

    Raises
    ------
    InvalidImageError
        ``img`` has an unusable shape or dtype, or NaN/Inf.
    ImageWriteError
        ``path`` is not a path, bad format/depth/transfer combination, values
        beyond the range of a float output, or any I/O failure.  Nothing is
        created on disk when the arguments or the values are refused.
    """
    fspath = _fspath(path, ImageWriteError)
    q = _q(fspath)
    if _unencodable(fspath):
        raise OutputRefusedError(f"cannot write {q}: file name is not valid UTF-8")
    ext = os.path.splitext(fspath)[1].lower()
    if format is None:
        fmt = _EXT_FORMAT.get(ext)
        if fmt is None:
            raise OutputSettingsError(f"cannot write {q}: unknown extension {ext!r} (use .tif, .png, .exr or .jpg, "
                                  "or pass format=)")
    else:
        fmt = _FORMAT_ALIASES.get(str(format).lower())
        if fmt is None:
            raise OutputSettingsError(f"cannot write {q}: unsupported format {format!r} (tiff, png, openexr, jpeg)")
    depth = bit_depth or _FORMAT_DEPTHS[fmt][0]
    if depth not in _FORMAT_DEPTHS[fmt]:
        raise OutputSettingsError(f"cannot write {q}: {fmt} does not take bit_depth={depth!r} (allowed: {_FORMAT_DEPTHS[fmt]})")
    try:
        tr = _parse_transfer(transfer, allow_auto=False)
    except ValueError as exc:
        raise OutputSettingsError(f"cannot write {q}: {exc}") from None
    if tr not in ("linear", "srgb"):  # no portable tag to read a pure gamma back
        raise OutputSettingsError(f"cannot write {q}: transfer must be 'linear' or 'srgb', got {transfer!r}")
    is_int = depth in ("uint8", "uint16")
    if tr == "srgb" and not is_int:
        raise OutputSettingsError(f"cannot write {q}: transfer='srgb' needs an integer bit_depth (float data is linear)")
    if fmt == "jpeg" and tr != "srgb":
        raise OutputSettingsError(f"cannot write {q}: JPEG stores sRGB-encoded values (pass transfer='srgb')")
    if quality is not None and (fmt != "jpeg" or isinstance(quality, bool) or not isinstance(quality, (int, np.integer))
                                or not 1 <= int(quality) <= 100):
        raise OutputSettingsError(f"cannot write {q}: quality must be an integer 1-100 and is for JPEG only, "
                              f"got {quality!r}")

    if isinstance(img, EncodedImage):  # code values already in the output's encoding
        if (img.depth, img.transfer) != (depth, tr):
            raise ImageWriteError(f"cannot write {q}: its codes are {img.depth} {img.transfer}, "
                                  f"not the {depth} {tr} asked for")
        arr = img.codes
    else:
        arr = np.asarray(img)
    if arr.ndim == 3 and arr.shape[2] == 1:
        arr = arr[..., 0]
    if arr.ndim not in (2, 3) or (arr.ndim == 3 and arr.shape[2] != 3) or arr.size == 0:
        raise InvalidImageError(f"cannot write {q}: image must be HxW or HxWx3 and non-empty, got shape {arr.shape}")
    if not (np.issubdtype(arr.dtype, np.floating) or np.issubdtype(arr.dtype, np.integer) or arr.dtype == bool):
        raise InvalidImageError(f"cannot write {q}: unsupported array dtype {arr.dtype}")
    h, w = arr.shape[:2]
    nch = 1 if arr.ndim == 2 else 3
    data = arr if isinstance(img, EncodedImage) else _stored_values(arr, fmt, depth, tr, q)
    # Always HxWxC: OIIO's Python binding takes a 2-D array as (width, height)
    # or scanline-major depending on version, which silently transposes gray images.
    data = np.ascontiguousarray(data.reshape(h, w, nch))

    spec = oiio.ImageSpec(w, h, nch, depth)
    spec.attribute("Software", "vigproc")
    if fmt == "tiff":
        spec.attribute("compression", "zip")
        if tr == "srgb":
            spec.attribute("oiio:ColorSpace", "srgb_rec709_scene")  # -> EXIF ColorSpace = sRGB
        else:
            # TIFF has no tag OIIO reads back as linear: use our marker; EXIF
            # ColorSpace "uncalibrated" (also avoids a spurious libtiff EXIF error).
            spec.attribute("ImageDescription", LINEAR_TIFF_MARKER)
            spec.attribute("Exif:ColorSpace", 65535)
            if nch == 3:
                # what editors and viewers go by: without it they take the values for
                # sRGB-encoded and show a linear frame far too dark
                icc = linear_srgb_profile()
                spec.attribute("ICCProfile", oiio.TypeDesc(f"uint8[{len(icc)}]"), np.frombuffer(icc, dtype=np.uint8))
    else:
        spec.attribute("oiio:ColorSpace", "srgb_rec709_scene" if tr == "srgb" else "lin_rec709_scene")
    if fmt == "jpeg":
        spec.attribute("Compression", f"jpeg:{int(quality or DEFAULT_JPEG_QUALITY)}")

    directory = os.path.dirname(os.path.abspath(fspath))
    # Encoded in memory first: a native writer that fails on a full disk may end the
    # process (libjpeg's "Output file write error --- out of disk space?" calls exit()),
    # and none gives an errno.  The bytes then go out by Python I/O, where a full disk is
    # ENOSPC.  No look at the free space then: it can say 0 where root may still write
    # (reserved blocks), and the write itself says ENOSPC when it is full.
    encoded = _encode_in_memory(spec, data, fmt, q)
    if encoded is None:  # the native writer will write the file itself: only if it fits
        _check_room(directory, size_bound(w, h, nch, depth), q)
    # Temp name keeps a format extension so OIIO picks the right writer; the
    # basename is shortened so prefix+suffix stay within NAME_MAX.
    try:
        with replacing(fspath, what=f"cannot write {q}", suffix=_FORMAT_EXT[fmt]) as tmp:
            if encoded is not None:
                with open(tmp, "wb") as fh:
                    encoded.seek(0)
                    shutil.copyfileobj(encoded, fh, 1 << 20)
            else:  # no in-memory file here (not Linux): the native writer writes the file itself
                _oiio_write(tmp, spec, data, q)
    except ImageWriteError:
        raise
    except OSError as exc:
        raise write_error(f"cannot write {q}: {exc.strerror or exc}", exc) from None
    finally:
        if encoded is not None:
            encoded.close()
    logger.debug("wrote %s (%s, %s, %s, %dx%dx%d)", fspath, fmt, depth, tr, w, h, nch)


def _stored_values(arr: np.ndarray, fmt: str, depth: str, tr: str, q: str) -> np.ndarray:
    """What :func:`write_image` stores of a linear array: float32 checked against the
    format's range, or integer codes (``tr``-encoded, round half up, clipped)."""
    is_int = depth in ("uint8", "uint16")
    # NaN/Inf of the caller's own: checked before the float32 cast, whose overflow
    # (float64 beyond 3.4e38) is reported below as out of range instead.  No mask:
    # NaN propagates to both extremes and ±Inf shows in one of them.
    if np.issubdtype(arr.dtype, np.floating) and not (np.isfinite(arr.max()) and np.isfinite(arr.min())):
        raise InvalidImageError(f"cannot write {q}: the image holds NaN/Inf, which cannot be stored as {depth}")
    with np.errstate(over="ignore"):  # overflow to Inf is detected right below
        data = arr.astype(np.float32, copy=False)

    if not is_int:
        # OIIO would store out-of-range values as Inf without a word.
        peak = max(float(data.max()), -float(data.min()))
        limit = FLOAT_MAX[depth]
        if not peak <= limit:
            shown = "beyond 3.4e38" if np.isinf(peak) else f"{peak:.4g}"
            wider = " (bit_depth='float' holds 3.4e38)" if depth == "half" else ""
            raise OutputRefusedError(
                f"cannot write {q}: values reach {shown}, beyond the {limit:.4g} that {fmt} {depth} "
                f"holds; they would be stored as Inf: scale the image down{wider}")
    if is_int:
        above = int(np.count_nonzero(data > 1.0))
        if above > 0.01 * data.size:
            # Integer outputs take [0, 1]; raw integer codes (0..65535) would turn white.
            logger.warning(
                "%s: %.1f %% of the values are above 1.0 (up to %.4g) and are clipped to white in %s; "
                "integer outputs take linear values in [0, 1], not integer codes",
                q, 100.0 * above / data.size, float(data.max()), depth)
        data = _quantise(data, depth, tr == "srgb")
    return data



#: Bytes of the file system kept beyond an output and the copy exiftool makes of it
#: (its metadata step writes a second file before renaming it onto the first).
ROOM_MARGIN = 1 << 20


def size_bound(w: int, h: int, nch: int, depth: str) -> int:
    """A generous bound of an output's bytes, from its pixels: the uncompressed samples
    plus 64 KiB of headers and metadata."""
    return w * h * nch * {"uint8": 1, "uint16": 2, "half": 2, "float": 4}[depth] + (64 << 10)


def _check_room(directory: str, size: int, q: str) -> None:
    """Raise :class:`DiskFullError` when ``directory``'s file system has no room for an
    output of ``size`` bytes, twice (the copy the metadata step writes), plus
    :data:`ROOM_MARGIN`; no check where the free space cannot be asked."""
    try:
        free = shutil.disk_usage(directory).free
    except OSError:
        return
    need = 2 * size + ROOM_MARGIN
    if free < need:
        err = DiskFullError(f"cannot write {q}: {free / 1e6:.1f} MB free on its disk, {need / 1e6:.1f} MB needed "
                            "(the image, the copy its metadata step writes, and a margin)")
        err.errno = errno.ENOSPC
        raise err


def _encode_in_memory(spec: oiio.ImageSpec, data: np.ndarray, fmt: str, q: str):
    """The encoded file in an in-memory file (``memfd``), rewound, or None where there is
    none (not Linux).  A native writer failing here fails on memory, never on a disk."""
    if not hasattr(os, "memfd_create") or not os.path.isdir("/proc/self/fd"):
        return None
    try:
        fd = os.memfd_create("vigproc-encode", os.MFD_CLOEXEC)
    except OSError:
        return None
    mem = os.fdopen(fd, "w+b")
    try:
        # the writer is chosen by extension; it opens the memfd by its /proc name
        _oiio_write(f"/proc/self/fd/{fd}", spec, data, q, kind=f"x{_FORMAT_EXT[fmt]}")
    except BaseException:
        mem.close()
        raise
    return mem


def _oiio_write(tmp: str, spec: oiio.ImageSpec, data: np.ndarray, q: str, kind: str | None = None) -> None:
    oiio.geterror()
    out = oiio.ImageOutput.create(kind or tmp)
    if out is None:
        raise ImageWriteError(f"cannot write {q}: {_one_line(oiio.geterror())}")
    ok = False
    try:
        ok = bool(out.open(tmp, spec)) and bool(out.write_image(data))
    except Exception as exc:  # binding-level failure
        out.close()
        raise ImageWriteError(f"cannot write {q}: {type(exc).__name__}: {exc}") from None
    ok = bool(out.close()) and ok
    err = out.geterror()
    if not ok:
        raise ImageWriteError(f"cannot write {q}: {_one_line(err or oiio.geterror())}")
    if err:  # success with a message: libtiff chatter, keep it out of the user's way
        logger.debug("%s: OpenImageIO reported while writing: %s", tmp, _one_line(err))
