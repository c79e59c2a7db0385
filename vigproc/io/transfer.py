"""Transfer curves: how stored values decode to linear light and encode back.

Transfer functions (``transfer="auto"``)
----------------------------------------
Observed with OpenImageIO 3.2 (``oiio:ColorSpace`` as reported on read):

=========================  =======================================================
file                       reported colour space
=========================  =======================================================
JPEG (any)                 ``srgb_rec709_scene``
PNG 8/16-bit, no chunk     ``srgb_rec709_scene`` (also with an ``sRGB`` chunk)
PNG with ``gAMA`` 1/2.2    ``g22_rec709_scene`` and ``oiio:Gamma`` = 2.2
PNG with ``gAMA`` 1.0      ``lin_rec709_scene``
TIFF (int or float)        nothing, unless EXIF ColorSpace = 1 -> ``srgb_rec709_scene``
OpenEXR half/float         nothing unless written with a colour space
=========================  =======================================================

Rules: float formats (EXR, float TIFF) are linear; integer files whose colour
space is missing or sRGB are sRGB-encoded; a gamma (``oiio:Gamma`` or a
``gNN_`` colour-space name) is honoured as a pure power law; a linear colour
space (``lin_*``, ``linear``, ACES...) means linear.  A TIFF written by
:func:`write_image` with ``transfer="linear"`` carries the marker
:data:`LINEAR_TIFF_MARKER` in its ``ImageDescription`` (TIFF has no standard tag
OpenImageIO maps to "linear"); once the source's metadata is copied in, the description is
the source's caption and the XMP property ``vigproc:Transfer`` says ``linear``
(:func:`recorded_transfer`).  Either is read back as linear.
"""

from __future__ import annotations

import functools
import logging
import re
from typing import TYPE_CHECKING, Callable

import numpy as np

from vigproc.errors import ImageWriteError, InvalidImageError

if TYPE_CHECKING:  # annotations only: the curves need no image library
    import OpenImageIO as oiio

logger = logging.getLogger("vigproc.io.images")  # the name it always logged under

#: Written into the ImageDescription of linear integer/float TIFFs by :func:`write_image`.
LINEAR_TIFF_MARKER = "vigproc:transfer=linear"


def _as_float(x: np.ndarray | float) -> np.ndarray:
    a = np.asarray(x)
    if not np.issubdtype(a.dtype, np.floating):
        a = a.astype(np.float64)
    return a


def srgb_to_linear(x: np.ndarray | float) -> np.ndarray:
    """Decode sRGB-encoded values to linear light (IEC 61966-2-1).

    Parameters
    ----------
    x : array_like
        Encoded values, nominally in ``[0, 1]``.  Values outside are extended
        symmetrically (``f(-v) = -f(v)``) and by the power segment above 1.

    Returns
    -------
    numpy.ndarray
        Linear values, same shape; float dtype of the input is kept (integers
        become float64).
    """
    a = _as_float(x)
    v = np.abs(a)
    lin = np.where(v <= 0.04045, v / 12.92, ((v + 0.055) / 1.055) ** 2.4)
    return np.copysign(lin, a).astype(a.dtype, copy=False)


def linear_to_srgb(x: np.ndarray | float) -> np.ndarray:
    """Encode linear light with the sRGB curve (inverse of :func:`srgb_to_linear`).

    Parameters
    ----------
    x : array_like
        Linear values, nominally in ``[0, 1]``.

    Returns
    -------
    numpy.ndarray
        sRGB-encoded values, same shape and float dtype rules as :func:`srgb_to_linear`.
    """
    a = _as_float(x)
    v = np.abs(a)
    enc = np.where(v <= 0.0031308, v * 12.92, 1.055 * v ** (1.0 / 2.4) - 0.055)
    return np.copysign(enc, a).astype(a.dtype, copy=False)


def _quantise(data: np.ndarray, depth: str, srgb: bool) -> np.ndarray:
    """Linear float32 ``data`` as ``depth`` integer codes (sRGB-encoded first when ``srgb``),
    rounded half up and clipped here rather than by OpenImageIO's conversion.

    A band of rows at a time: on the whole frame the curve and the scaling make about five
    float temporaries the size of the frame, the largest part of a correction's peak memory
    (the budget's multiple, ``DEFAULT_MEMORY_BUDGET``); per band they are a few MB.
    """
    top = np.float32(255.0 if depth == "uint8" else 65535.0)
    out = np.empty(data.shape, depth)
    step = max(1, (1 << 20) // max(1, data[:1].size))  # rows of about 1 M samples
    for y in range(0, data.shape[0], step):
        band = data[y:y + step]
        if srgb:
            band = linear_to_srgb(band)
        out[y:y + step] = np.floor(np.clip(band, 0.0, 1.0) * top + np.float32(0.5))
    return out


def _gamma_to_linear(x: np.ndarray, gamma: float) -> np.ndarray:
    a = _as_float(x)
    return np.copysign(np.abs(a) ** gamma, a).astype(a.dtype, copy=False)


_GAMMA_RE = re.compile(r"^gamma\s*([0-9]*\.?[0-9]+)$")


def _parse_transfer(transfer: str, *, allow_auto: bool) -> str:
    """Normalise a user transfer name; ``'gamma2.2'`` style names are accepted.

    Raises
    ------
    InvalidImageError
        Not a string, or not a known curve (a ``ValueError`` too).
    """
    if not isinstance(transfer, str):
        raise InvalidImageError(f"transfer must be a string, got {transfer!r}")
    t = transfer.strip().lower()
    if t in ("linear", "srgb") or (allow_auto and t == "auto"):
        return t
    m = _GAMMA_RE.match(t)
    if m and float(m.group(1)) > 0:
        return _gamma_name(float(m.group(1)))
    allowed = "'auto', 'linear', 'srgb' or 'gamma<g>'" if allow_auto else "'linear' or 'srgb'"
    raise InvalidImageError(f"unknown transfer {transfer!r}: expected {allowed}")


def _gamma_name(g: float) -> str:
    if abs(g - 1.0) < 1e-3:
        return "linear"
    return f"gamma{g:.4g}"


def _decoder(transfer: str) -> Callable[[np.ndarray], np.ndarray]:
    if transfer == "linear":
        return lambda v: _as_float(v)
    if transfer == "srgb":
        return srgb_to_linear
    g = float(transfer[len("gamma"):])
    return lambda v: _gamma_to_linear(v, g)


@functools.lru_cache(maxsize=16)
def _decode_lut(transfer: str, levels: int) -> np.ndarray:
    # Computed in float64 so 8/16-bit codes decode exactly (to float32 rounding).
    codes = np.arange(levels, dtype=np.float64) / (levels - 1)
    lut = _decoder(transfer)(codes).astype(np.float32)
    lut.setflags(write=False)
    return lut


def recorded_transfer(spec: oiio.ImageSpec) -> str | None:
    """The transfer vigproc recorded in a TIFF it wrote, or None.

    :func:`write_image` puts :data:`LINEAR_TIFF_MARKER` in ``ImageDescription``;
    :func:`vigproc.io.metadata.copy_metadata` moves it to the XMP property
    ``vigproc:Transfer`` (the description is the source's caption then).  Files written
    before that carry only the marker, and both are read.

    Parameters
    ----------
    spec : OpenImageIO.ImageSpec
        The file's header (OpenImageIO decodes its XMP into ``vigproc:*`` attributes).

    Returns
    -------
    str or None
        ``"linear"`` when recorded.
    """
    recorded = spec.get_string_attribute("vigproc:Transfer", "").strip().lower()
    if recorded == "linear" or LINEAR_TIFF_MARKER in spec.get_string_attribute("ImageDescription", ""):
        return "linear"
    return None


def _auto_transfer(is_float: bool, colorspace: str | None, gamma: float, description: str) -> str:
    """Decide the transfer curve from file metadata (rules in the module docstring).

    ``description``: the ImageDescription, or :data:`LINEAR_TIFF_MARKER` when
    :func:`recorded_transfer` says linear."""
    if is_float:
        if colorspace and not _is_linear_name(colorspace.lower()):
            logger.warning(
                "float image declares colour space %r; float data is treated as linear",
                colorspace,
            )
        return "linear"
    if LINEAR_TIFF_MARKER in description:
        return "linear"
    cs = (colorspace or "").strip().lower()
    if not cs:
        return _gamma_name(gamma) if gamma > 0 else "srgb"
    if _is_linear_name(cs):
        return "linear"
    if cs.startswith("srgb") or cs == "rec709":  # OIIO maps legacy "Rec709" to sRGB too
        return "srgb"
    if gamma > 0:
        return _gamma_name(gamma)
    m = re.match(r"^g(\d)(\d)_", cs) or re.match(r"^gamma\s*([0-9])\.?([0-9]*)", cs)
    if m:
        return _gamma_name(float(f"{m.group(1)}.{m.group(2) or 0}"))
    logger.warning("unknown colour space %r on an integer image; assuming sRGB", colorspace)
    return "srgb"


def _is_linear_name(cs: str) -> bool:
    return cs.startswith("lin") or "linear" in cs or cs.startswith("aces") or cs == "raw"


@functools.lru_cache(maxsize=8)
def encode_steps(transfer: str, depth: str) -> np.ndarray:
    """The linear values from which an output code steps up: entry c is where
    ``depth``'s code c + 1 begins under ``transfer`` (round half up, as
    :func:`write_image` quantises), float32, read-only.

    Raises
    ------
    ImageWriteError
        ``depth`` is not uint8 or uint16, or ``transfer`` not 'linear' or 'srgb'.
    """
    if depth not in ("uint8", "uint16") or transfer not in ("linear", "srgb"):
        raise ImageWriteError(f"no code steps for {depth} {transfer}")
    top = 255 if depth == "uint8" else 65535
    steps = _decoder(transfer)((np.arange(top, dtype=np.float64) + 0.5) / top).astype(np.float32)
    steps.setflags(write=False)
    return steps
