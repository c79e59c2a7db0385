"""DNG opcode lists (``OpcodeList1``/``2``/``3``): parse, decode, build and serialise.

A DNG carries processing steps the raw converter is to apply at three stages of
development as *opcode lists* (DNG Specification 1.3.0.0 and later, Chapter 7,
"Opcode List Processing"; tags ``OpcodeList1`` 51008 on the stored raw data,
``OpcodeList2`` 51009 after linearisation, ``OpcodeList3`` 51022 after
demosaicing).  An opcode list is big-endian whatever the file's byte order::

    uint32  count                      number of opcodes
    count times:
      uint32  opcode id                (Chapter 7, "Opcode List": 1..14)
      uint32  DNG version              the minimum DNG version that knows the opcode
                                       (1.3.0.0 = bytes 01 03 00 00)
      uint32  flags                    bit 0: optional (a reader that cannot apply it
                                       may skip it); bit 1: may be skipped for a
                                       preview-quality render
      uint32  parameter byte count N
      N bytes parameters               (the opcode's own layout)

vigproc decodes the two opcodes that describe vignetting:

* ``FixVignetteRadial`` (id 3, DNG 1.3): five doubles k0..k4 and the optical centre
  (cx, cy) as doubles in relative coordinates (0.5 = the middle of the image).  The
  gain applied to a pixel is ``g = 1 + k0 r² + k1 r⁴ + k2 r⁶ + k3 r⁸ + k4 r¹⁰`` with r
  the distance from the optical centre divided by the largest distance from the
  optical centre to a corner of the image, so r = 1 at the farthest corner.  (There
  is no constant term: k0 multiplies r².  The Adobe DNG SDK evaluates exactly this,
  ``dng_vignette_radial_function::Evaluate`` in ``dng_lens_correction.cpp``, as does
  DngOpcodesEditor.)  See :class:`FixVignetteRadial`.
* ``GainMap`` (id 9, DNG 1.3): an area (top, left, bottom, right as int32; plane,
  planes, row pitch, column pitch as uint32), then the map: points vertical and
  horizontal (uint32), spacing vertical and horizontal, origin vertical and horizontal
  (doubles, relative image coordinates), map planes (uint32) and
  ``points_v × points_h × map_planes`` float32 gains, row by row, planes innermost.
  Pixels between map points get the bilinear interpolation of the four nearest
  gains; beyond the outermost points the edge value is held.  See :class:`GainMap`.

Every other opcode is kept as its raw bytes (:class:`Opcode`) and skipped by its
declared size, so a list round-trips byte for byte: ``parse(b).to_bytes() == b``.

Hostile input
-------------
An opcode list comes from a file and is treated as hostile: every declared count and
size is checked against the bytes that remain *before* anything is allocated or
looped over (a count cannot exceed ``remaining / 16``; a gain map's point counts must
account for exactly its parameter bytes), so a truncated, inflated or otherwise
malformed list gives :class:`DngOpcodeError` (naming the file), never a crash, a hang
or a huge allocation.  ``scripts/fuzz_dng_opcodes.py`` mutates real and synthetic
lists and checks this (docs/benchmarks/dng.md).

References
----------
.. [1] Adobe, *Digital Negative (DNG) Specification*, version 1.4.0.0 (June 2012),
   Chapter 7 "Opcode List Processing": "Opcode List Format", "FixVignetteRadial",
   "GainMap"; Chapter 4 tags OpcodeList1 (51008), OpcodeList2 (51009), OpcodeList3
   (51022).  First published in version 1.3.0.0 (June 2009).
.. [2] Adobe DNG SDK 1.4, ``dng_lens_correction.cpp`` (``dng_vignette_radial_params``,
   ``dng_opcode_FixVignetteRadial::Prepare``: optical centre and maximum radius),
   ``dng_gain_map.cpp`` (``dng_gain_map::GetStream``, ``dng_gain_map_interpolator``),
   ``dng_misc_opcodes.cpp`` (``dng_area_spec::GetData``) -- the reference reader.
"""

from __future__ import annotations

import logging
import math
import struct
from dataclasses import dataclass, field
from typing import Iterable

import numpy as np

from vigproc.errors import ImageReadError, one_line

__all__ = [
    "DNG_VERSION_1_3",
    "FLAG_OPTIONAL",
    "FLAG_PREVIEW_SKIP",
    "MAX_OPCODE_LIST_BYTES",
    "OPCODE_NAMES",
    "AreaSpec",
    "DngOpcodeError",
    "FixVignetteRadial",
    "GainMap",
    "Opcode",
    "OpcodeList",
    "parse_opcode_list",
]

logger = logging.getLogger(__name__)

#: The DNG version field of opcodes defined in DNG 1.3.0.0 (bytes 01 03 00 00).
DNG_VERSION_1_3 = 0x01030000
#: Flag bit: the opcode may be skipped by a reader that cannot apply it.
FLAG_OPTIONAL = 1
#: Flag bit: the opcode may be skipped when rendering a preview.
FLAG_PREVIEW_SKIP = 2
#: Opcode ids and names (DNG 1.4 Chapter 7; WarpRectilinear2 is DNG 1.6).
OPCODE_NAMES = {
    1: "WarpRectilinear", 2: "WarpFisheye", 3: "FixVignetteRadial", 4: "FixBadPixelsConstant",
    5: "FixBadPixelsList", 6: "TrimBounds", 7: "MapTable", 8: "MapPolynomial", 9: "GainMap",
    10: "DeltaPerRow", 11: "DeltaPerColumn", 12: "ScalePerRow", 13: "ScalePerColumn",
    14: "WarpRectilinear2",
}
FIX_VIGNETTE_RADIAL = 3
GAIN_MAP = 9
#: Largest opcode list read (bytes).  A phone's lens-shading GainMaps take tens of KB;
#: 64 MiB bounds what a hostile file can make us hold.
MAX_OPCODE_LIST_BYTES = 64 << 20

_HEADER = struct.Struct(">IIII")  # id, version, flags, parameter bytes
_FVR = struct.Struct(">7d")  # k0..k4, cx, cy
_AREA = struct.Struct(">iiiiIIII")  # top, left, bottom, right, plane, planes, row pitch, col pitch
_MAP_HEAD = struct.Struct(">IIddddI")  # points v/h, spacing v/h, origin v/h, map planes
_U32_MAX = 0xFFFFFFFF


class DngOpcodeError(ImageReadError):
    """A DNG opcode list (or one of its vignetting opcodes) is malformed: truncated,
    sizes that do not add up, or parameters the DNG specification does not allow.
    The message names the file (or "opcode list" for bare bytes)."""


def _fail(source: str, what: str) -> DngOpcodeError:
    return DngOpcodeError(one_line(f"{source}: {what}"))


def _u32(name: str, v: int) -> int:
    if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or not 0 <= int(v) <= _U32_MAX:
        raise ValueError(f"{name} must be an unsigned 32-bit integer, got {v!r}")
    return int(v)


# --------------------------------------------------------------------------- #
# the list and its raw opcodes
# --------------------------------------------------------------------------- #


@dataclass(frozen=True)
class Opcode:
    """One opcode as stored: its header fields and parameter bytes, uninterpreted.

    Attributes
    ----------
    opcode_id : int
        1..14 for the opcodes of DNG 1.3-1.6 (:data:`OPCODE_NAMES`); any uint32 is kept.
    dng_version : int
        The stored version field (uint32, 1.3.0.0 = ``0x01030000``), kept as is.
    flags : int
        :data:`FLAG_OPTIONAL`, :data:`FLAG_PREVIEW_SKIP`; other bits kept as stored.
    params : bytes
        The parameter bytes.
    """

    opcode_id: int
    dng_version: int
    flags: int
    params: bytes

    def __post_init__(self) -> None:
        _u32("opcode_id", self.opcode_id)
        _u32("dng_version", self.dng_version)
        _u32("flags", self.flags)
        if not isinstance(self.params, (bytes, bytearray, memoryview)) or len(self.params) > _U32_MAX:
            raise ValueError("params must be bytes (at most 4 GiB)")
        object.__setattr__(self, "params", bytes(self.params))

    @property
    def name(self) -> str:
        """The opcode's name, or ``Unknown(ID)``."""
        return OPCODE_NAMES.get(self.opcode_id, f"Unknown({self.opcode_id})")

    @property
    def optional(self) -> bool:
        return bool(self.flags & FLAG_OPTIONAL)

    @property
    def preview_skip(self) -> bool:
        return bool(self.flags & FLAG_PREVIEW_SKIP)

    @property
    def version_text(self) -> str:
        """The version field as ``a.b.c.d`` (byte by byte, as the DNG tags write versions)."""
        return ".".join(str(b) for b in self.dng_version.to_bytes(4, "big"))

    def to_bytes(self) -> bytes:
        """Header and parameters, big-endian, as in a list."""
        return _HEADER.pack(self.opcode_id, self.dng_version, self.flags, len(self.params)) + self.params

    def decode(self, source: str = "opcode list") -> FixVignetteRadial | GainMap | None:
        """The vignetting opcode this is (:class:`FixVignetteRadial`, :class:`GainMap`),
        or None for any other opcode.

        Raises
        ------
        DngOpcodeError
            A FixVignetteRadial or GainMap whose parameters are malformed.
        """
        if self.opcode_id == FIX_VIGNETTE_RADIAL:
            return FixVignetteRadial.from_opcode(self, source)
        if self.opcode_id == GAIN_MAP:
            return GainMap.from_opcode(self, source)
        return None


@dataclass(frozen=True)
class OpcodeList:
    """An opcode list: its opcodes in order of application.

    Build one with :meth:`parse` (from a tag's bytes) or from opcodes
    (``OpcodeList((FixVignetteRadial(...).to_opcode(),))``); :meth:`to_bytes` gives
    the tag's bytes.
    """

    opcodes: tuple[Opcode, ...] = ()

    def __post_init__(self) -> None:
        ops = tuple(self.opcodes)
        if not all(isinstance(op, Opcode) for op in ops):
            raise ValueError("an OpcodeList holds Opcode records (use .to_opcode() of a decoded opcode)")
        object.__setattr__(self, "opcodes", ops)

    def __len__(self) -> int:
        return len(self.opcodes)

    def __iter__(self):
        return iter(self.opcodes)

    @classmethod
    def parse(cls, data: bytes, source: str = "opcode list") -> OpcodeList:
        """Parse an opcode list (see :func:`parse_opcode_list`)."""
        return parse_opcode_list(data, source)

    def to_bytes(self) -> bytes:
        """The list as stored in an ``OpcodeListN`` tag (big-endian)."""
        return struct.pack(">I", len(self.opcodes)) + b"".join(op.to_bytes() for op in self.opcodes)

    def appended(self, *ops: Opcode) -> OpcodeList:
        """A new list with ``ops`` applied after the existing opcodes."""
        return OpcodeList(self.opcodes + tuple(ops))

    def decoded(self, source: str = "opcode list") -> list[tuple[int, FixVignetteRadial | GainMap]]:
        """``(index, opcode)`` of every FixVignetteRadial and GainMap, decoded.

        Raises
        ------
        DngOpcodeError
            One of them is malformed.
        """
        out = []
        for i, op in enumerate(self.opcodes):
            d = op.decode(f"{source}, opcode {i + 1} ({op.name})")
            if d is not None:
                out.append((i, d))
        return out

    def summary(self) -> list[str]:
        """One short line per opcode (name, version, flags, size)."""
        return [f"{op.name} (DNG {op.version_text}, flags {op.flags:#x}, {len(op.params)} bytes)"
                for op in self.opcodes]


def parse_opcode_list(data: bytes | bytearray | memoryview, source: str = "opcode list") -> OpcodeList:
    """Split an ``OpcodeListN`` tag's bytes into its opcodes.

    Only the framing is read here: every opcode is kept as an :class:`Opcode` (its
    header and parameter bytes), so ``parse_opcode_list(b).to_bytes() == b`` for every
    list this accepts.  Decode the vignetting opcodes with :meth:`Opcode.decode` or
    :meth:`OpcodeList.decoded`.

    Parameters
    ----------
    data : bytes
        The tag's value.
    source : str
        Named in error messages (the file, and the tag).

    Returns
    -------
    OpcodeList

    Raises
    ------
    DngOpcodeError
        Shorter than its count, a count or parameter size larger than the bytes that
        remain, bytes left over after the last opcode (the DNG SDK refuses those
        too), or more than :data:`MAX_OPCODE_LIST_BYTES`.

    References
    ----------
    DNG Specification 1.4.0.0, Chapter 7, "Opcode List Format".
    """
    if not isinstance(data, (bytes, bytearray, memoryview)):
        raise TypeError(f"an opcode list is bytes, got {type(data).__name__}")
    buf = memoryview(data).cast("B")
    n = len(buf)
    if n > MAX_OPCODE_LIST_BYTES:
        raise _fail(source, f"opcode list of {n} bytes is larger than the {MAX_OPCODE_LIST_BYTES >> 20} MiB allowed")
    if n < 4:
        raise _fail(source, f"opcode list is truncated: {n} bytes, not even its 4-byte count")
    (count,) = struct.unpack_from(">I", buf, 0)
    # every opcode has a 16-byte header: a larger count cannot be true (and must not drive a loop)
    if count > (n - 4) // _HEADER.size:
        raise _fail(source, f"opcode list declares {count} opcodes but its {n} bytes hold at most "
                            f"{(n - 4) // _HEADER.size}")
    ops = []
    pos = 4
    for i in range(count):
        if n - pos < _HEADER.size:
            raise _fail(source, f"opcode {i + 1} of {count} is truncated: {n - pos} bytes left for its "
                                f"16-byte header")
        oid, version, flags, size = _HEADER.unpack_from(buf, pos)
        pos += _HEADER.size
        if size > n - pos:
            raise _fail(source, f"opcode {i + 1} of {count} ({OPCODE_NAMES.get(oid, f'id {oid}')}) declares "
                                f"{size} parameter bytes but only {n - pos} remain")
        ops.append(Opcode(oid, version, flags, bytes(buf[pos:pos + size])))
        pos += size
    if pos != n:
        raise _fail(source, f"{n - pos} bytes follow the last of the {count} opcodes")
    return OpcodeList(tuple(ops))


# --------------------------------------------------------------------------- #
# FixVignetteRadial
# --------------------------------------------------------------------------- #

@dataclass(frozen=True)
class FixVignetteRadial:
    """The DNG ``FixVignetteRadial`` opcode: a radial gain that corrects vignetting.

    The gain multiplied into a pixel is ``g(r) = 1 + k0 r² + k1 r⁴ + k2 r⁶ + k3 r⁸ +
    k4 r¹⁰``: positive k brighten the corners, so the vignetting it corrects is an
    attenuation of ``1 / g``.  r is the distance from the optical centre divided by
    the largest distance from the optical centre to a corner of the image (r = 1 at
    the farthest corner, whatever the centre).

    Attributes
    ----------
    k : tuple of 5 floats
        k0..k4.
    cx, cy : float
        Optical centre in relative coordinates, 0..1 across the image's width and
        height (0.5, 0.5 = the middle).
    dng_version, flags : int
        Header fields written by :meth:`to_opcode` (kept from a decoded opcode).

    References
    ----------
    DNG Specification 1.4.0.0, Chapter 7, "FixVignetteRadial" (opcode id 3);
    DNG SDK ``dng_opcode_FixVignetteRadial::Prepare``: the centre is interpolated
    between the image's edges (pixel j spans [j, j + 1)), and the maximum radius is
    the distance from it to the farthest corner.
    """

    k: tuple[float, float, float, float, float]
    cx: float = 0.5
    cy: float = 0.5
    dng_version: int = DNG_VERSION_1_3
    flags: int = 0

    PARAM_BYTES = _FVR.size

    def __post_init__(self) -> None:
        k = tuple(float(v) for v in self.k)
        if len(k) != 5 or not all(math.isfinite(v) for v in k):
            raise ValueError(f"FixVignetteRadial needs five finite coefficients k0..k4, got {self.k!r}")
        cx, cy = float(self.cx), float(self.cy)
        # the SDK's dng_vignette_radial_params::IsValid: the centre lies within the image
        if not (0.0 <= cx <= 1.0 and 0.0 <= cy <= 1.0):
            raise ValueError(f"FixVignetteRadial's optical centre must be within [0, 1], got ({cx!r}, {cy!r})")
        _u32("dng_version", self.dng_version)
        _u32("flags", self.flags)
        object.__setattr__(self, "k", k)
        object.__setattr__(self, "cx", cx)
        object.__setattr__(self, "cy", cy)

    @classmethod
    def from_opcode(cls, op: Opcode, source: str = "opcode list") -> FixVignetteRadial:
        """Decode a FixVignetteRadial opcode.

        Raises
        ------
        DngOpcodeError
            Not 56 parameter bytes, a non-finite coefficient, or a centre outside [0, 1].
        """
        if op.opcode_id != FIX_VIGNETTE_RADIAL:
            raise _fail(source, f"opcode {op.name} is not FixVignetteRadial")
        if len(op.params) != _FVR.size:
            raise _fail(source, f"FixVignetteRadial has {len(op.params)} parameter bytes, not {_FVR.size} "
                                "(k0..k4, cx, cy as doubles)")
        *k, cx, cy = _FVR.unpack(op.params)
        try:
            return cls(tuple(k), cx, cy, op.dng_version, op.flags)
        except ValueError as exc:
            raise _fail(source, str(exc)) from None

    def to_opcode(self) -> Opcode:
        """The opcode record (56 parameter bytes)."""
        return Opcode(FIX_VIGNETTE_RADIAL, self.dng_version, self.flags, _FVR.pack(*self.k, self.cx, self.cy))

    @property
    def is_identity(self) -> bool:
        """All coefficients zero: the gain is 1 everywhere."""
        return not any(self.k)

    def gain(self, r: np.ndarray | float) -> np.ndarray:
        """``g(r) = 1 + k0 r² + ... + k4 r¹⁰`` (Horner in r²)."""
        r2 = np.asarray(r, dtype=np.float64) ** 2
        acc = np.zeros_like(r2)
        for k in reversed(self.k):
            acc = r2 * (k + acc)
        return 1.0 + acc

    def centre_px(self, width: int, height: int) -> tuple[float, float]:
        """The optical centre in vigproc's pixel coordinates (pixels from the frame
        centre ((W-1)/2, (H-1)/2), x right, y down) for a ``width``×``height`` image.

        The SDK places the centre at ``cx · W`` between the image edges, where pixel
        j's centre is at j + ½: in frame-centred pixel coordinates that is
        ``(cx − ½) · W``.
        """
        return (self.cx - 0.5) * width, (self.cy - 0.5) * height

    def max_radius(self, width: int, height: int) -> float:
        """Distance (px) from the optical centre to the farthest image corner (r = 1)."""
        x, y = self.cx * width, self.cy * height
        return math.hypot(max(x, width - x), max(y, height - y))

    def radius_at(self, x: np.ndarray, y: np.ndarray, width: int, height: int) -> np.ndarray:
        """Normalised radius r at points ``(x, y)`` (frame-centred pixels)."""
        ox, oy = self.centre_px(width, height)
        return np.hypot(np.asarray(x, dtype=np.float64) - ox, np.asarray(y, dtype=np.float64) - oy) / \
            self.max_radius(width, height)

    def gain_grid(self, rel_v: np.ndarray, rel_h: np.ndarray, width: int, height: int,
                  plane: int = 0) -> np.ndarray:
        """The gain at the grid of relative positions ``rel_v`` × ``rel_h`` (0..1 down and
        across) of a ``width``×``height`` image (the radius is measured in its pixels).
        ``plane`` is accepted for symmetry with :meth:`GainMap.gain_grid` (all planes
        get the same gain)."""
        width, height = _size(width, height)
        dx = (np.asarray(rel_h, dtype=np.float64) - self.cx) * width
        dy = (np.asarray(rel_v, dtype=np.float64) - self.cy) * height
        return self.gain(np.hypot(dx[None, :], dy[:, None]) / self.max_radius(width, height))

    def gain_field(self, width: int, height: int) -> np.ndarray:
        """The gain at every pixel of a ``width``×``height`` image (H×W float64)."""
        width, height = _size(width, height)
        return self.gain_grid(_centres(height), _centres(width), width, height)


# --------------------------------------------------------------------------- #
# GainMap
# --------------------------------------------------------------------------- #


@dataclass(frozen=True)
class AreaSpec:
    """The pixels an area-based opcode (GainMap, MapTable, ...) applies to.

    Rows ``top, top + row_pitch, ... < bottom`` and columns ``left, left + col_pitch,
    ... < right`` of planes ``plane .. plane + planes − 1``.  A pitch of 2 with an odd
    or even start picks one phase of a Bayer pattern (a CFA GainMap in OpcodeList2).

    References
    ----------
    DNG Specification 1.4.0.0, Chapter 7, "GainMap" (the area parameters); DNG SDK
    ``dng_area_spec::GetData`` (planes ≥ 1, pitches ≥ 1, an empty area only with
    pitches of 1).
    """

    top: int
    left: int
    bottom: int
    right: int
    plane: int = 0
    planes: int = 1
    row_pitch: int = 1
    col_pitch: int = 1

    def __post_init__(self) -> None:
        for name in ("top", "left", "bottom", "right"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or not -2**31 <= int(v) < 2**31:
                raise ValueError(f"area {name} must be a signed 32-bit integer, got {v!r}")
            object.__setattr__(self, name, int(v))
        for name in ("plane", "planes", "row_pitch", "col_pitch"):
            object.__setattr__(self, name, _u32(f"area {name}", getattr(self, name)))
        if self.planes < 1:
            raise ValueError("area planes must be at least 1")
        if self.row_pitch < 1 or self.col_pitch < 1:
            raise ValueError(f"area pitches must be at least 1, got {self.row_pitch}, {self.col_pitch}")
        if self.empty and (self.row_pitch != 1 or self.col_pitch != 1):
            raise ValueError("an empty area must have pitches of 1")

    @property
    def empty(self) -> bool:
        return self.bottom <= self.top or self.right <= self.left

    def pack(self) -> bytes:
        return _AREA.pack(self.top, self.left, self.bottom, self.right, self.plane, self.planes,
                          self.row_pitch, self.col_pitch)


@dataclass(frozen=True, eq=False)
class GainMap:
    """The DNG ``GainMap`` opcode: a grid of gains multiplied into an area of the image.

    Attributes
    ----------
    area : AreaSpec
        The pixels and planes it applies to (coordinates of the image at the stage of
        the list: the active area for OpcodeList2 and 3).
    gains : ndarray, float32, (points_v, points_h, map_planes)
        The gains (read-only).  Image plane p uses map plane ``min(p, map_planes − 1)``
        (the SDK's rule).
    spacing_v, spacing_h : float
        Distance between map points in relative image coordinates (0..1 over the
        image's height and width).
    origin_v, origin_h : float
        Relative position of the first map point.
    dng_version, flags : int
        Header fields written by :meth:`to_opcode`.

    Notes
    -----
    Interpolation follows the DNG SDK (``dng_gain_map_interpolator``): pixel (row, col)
    of an H×W image sits at relative position ((row + ½)/H, (col + ½)/W); its map
    index is (position − origin)/spacing, clamped to the first and last point; the
    gain is the bilinear interpolation of the four map points around it.  A map of one
    point along an axis has spacing 1 and origin 0 there (the SDK overrides what is
    stored, and so does :meth:`gain_field`).

    References
    ----------
    DNG Specification 1.4.0.0, Chapter 7, "GainMap" (opcode id 9); DNG SDK
    ``dng_gain_map::GetStream``, ``dng_gain_map_interpolator``,
    ``dng_opcode_GainMap::ProcessArea``.
    """

    area: AreaSpec
    gains: np.ndarray
    spacing_v: float
    spacing_h: float
    origin_v: float = 0.0
    origin_h: float = 0.0
    dng_version: int = DNG_VERSION_1_3
    flags: int = 0
    _stored: tuple[float, float, float, float] | None = field(default=None, repr=False)

    def __post_init__(self) -> None:
        if not isinstance(self.area, AreaSpec):
            raise ValueError("area must be an AreaSpec")
        g = np.array(self.gains, dtype=">f4")  # a copy: the opcode owns its gains
        if g.ndim == 2:
            g = g[:, :, None]
        if g.ndim != 3 or 0 in g.shape:
            raise ValueError(f"gains must be points_v x points_h x map_planes, got shape {np.shape(self.gains)}")
        if any(s > _U32_MAX for s in g.shape):
            raise ValueError("too many gain map points")
        if not np.all(np.isfinite(g)):
            raise ValueError("gains must be finite")
        g.flags.writeable = False
        vals = [float(v) for v in (self.spacing_v, self.spacing_h, self.origin_v, self.origin_h)]
        if not all(math.isfinite(v) for v in vals):
            raise ValueError(f"map spacing and origin must be finite, got {vals}")
        pv, ph = g.shape[:2]
        # the SDK: a single point along an axis has spacing 1 and origin 0 there
        sv, sh, ov, oh = vals
        if pv == 1:
            sv, ov = 1.0, 0.0
        if ph == 1:
            sh, oh = 1.0, 0.0
        if not (sv > 0 and sh > 0):
            raise ValueError(f"map spacing must be positive, got {vals[0]!r}, {vals[1]!r}")
        _u32("dng_version", self.dng_version)
        _u32("flags", self.flags)
        object.__setattr__(self, "gains", g)
        # what to write back: the stored values (a round trip keeps a one-point axis's bytes)
        object.__setattr__(self, "_stored", tuple(vals) if self._stored is None else self._stored)
        object.__setattr__(self, "spacing_v", sv)
        object.__setattr__(self, "spacing_h", sh)
        object.__setattr__(self, "origin_v", ov)
        object.__setattr__(self, "origin_h", oh)

    @property
    def points(self) -> tuple[int, int]:
        """(points_v, points_h)."""
        return int(self.gains.shape[0]), int(self.gains.shape[1])

    @property
    def map_planes(self) -> int:
        return int(self.gains.shape[2])

    @property
    def cfa(self) -> bool:
        """Applies to one phase of a mosaic (a pitch above 1), not to every pixel."""
        return self.area.row_pitch > 1 or self.area.col_pitch > 1

    @classmethod
    def from_opcode(cls, op: Opcode, source: str = "opcode list") -> GainMap:
        """Decode a GainMap opcode.

        Raises
        ------
        DngOpcodeError
            Parameters shorter than the area and map header, point counts that do not
            account for exactly the remaining bytes, zero points or planes, a spacing
            that is not positive, or a non-finite value.
        """
        if op.opcode_id != GAIN_MAP:
            raise _fail(source, f"opcode {op.name} is not GainMap")
        p = op.params
        head = _AREA.size + _MAP_HEAD.size
        if len(p) < head:
            raise _fail(source, f"GainMap has {len(p)} parameter bytes, fewer than its {head}-byte header")
        t, lft, b, r, plane, planes, rp, cp = _AREA.unpack_from(p, 0)
        pv, ph, sv, sh, ov, oh, mp = _MAP_HEAD.unpack_from(p, _AREA.size)
        if pv < 1 or ph < 1 or mp < 1:
            raise _fail(source, f"GainMap has {pv}x{ph} points and {mp} planes: each must be at least 1")
        # checked in Python integers (no overflow) before anything is allocated
        need = pv * ph * mp * 4
        if need != len(p) - head:
            raise _fail(source, f"GainMap declares {pv}x{ph} points x {mp} planes ({need} bytes of gains) "
                                f"but holds {len(p) - head} bytes after its header")
        gains = np.frombuffer(p, dtype=">f4", count=pv * ph * mp, offset=head).reshape(pv, ph, mp)
        try:
            area = AreaSpec(t, lft, b, r, plane, planes, rp, cp)
            return cls(area, gains, sv, sh, ov, oh, op.dng_version, op.flags)
        except ValueError as exc:
            raise _fail(source, f"GainMap: {exc}") from None

    def to_opcode(self) -> Opcode:
        """The opcode record (76 + 4 · points_v · points_h · map_planes parameter bytes)."""
        pv, ph = self.points
        sv, sh, ov, oh = self._stored or (self.spacing_v, self.spacing_h, self.origin_v, self.origin_h)
        params = (self.area.pack() + _MAP_HEAD.pack(pv, ph, sv, sh, ov, oh, self.map_planes)
                  + np.ascontiguousarray(self.gains, dtype=">f4").tobytes())
        return Opcode(GAIN_MAP, self.dng_version, self.flags, params)

    def _axis(self, rel: np.ndarray, points: int, spacing: float, origin: float
              ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """For points at relative positions ``rel`` along an axis: the two map indices
        around each and the weight of the second (held at the outermost points)."""
        pos = np.clip((rel - origin) / spacing, 0.0, points - 1.0)
        i0 = np.minimum(np.floor(pos).astype(np.int64), points - 1)
        i1 = np.minimum(i0 + 1, points - 1)
        return i0, i1, pos - i0

    def gain_grid(self, rel_v: np.ndarray, rel_h: np.ndarray, width: int, height: int,
                  plane: int = 0) -> np.ndarray:
        """The gain at the grid of relative positions ``rel_v`` × ``rel_h`` (0..1 down and
        across) of a ``width``×``height`` image, for image plane ``plane``.

        A point inside the area (the pixel it falls in is one of the area's) gets the
        map's bilinear interpolation, any other point 1; the pitch is ignored (the
        smooth field, which is what a pitch-2 CFA map means for the colour its phase
        samples).  Image plane p uses map plane ``min(p, map_planes − 1)``; a plane the
        area does not cover gets 1.

        Returns
        -------
        ndarray, float64, len(rel_v) × len(rel_h)
        """
        width, height = _size(width, height)
        rel_v = np.asarray(rel_v, dtype=np.float64)
        rel_h = np.asarray(rel_h, dtype=np.float64)
        a = self.area
        out = np.ones((rel_v.size, rel_h.size), dtype=np.float64)
        if not (a.plane <= plane < a.plane + a.planes) or a.empty:
            return out
        row = np.floor(rel_v * height)
        col = np.floor(rel_h * width)
        # a pitch-p map (one phase of a CFA) stands for the p×p cells of the pattern its
        # pixels lie in: a cell's rows and columns before the phase's own (row 0 for a
        # phase starting at row 1) are in its field too
        iv = np.flatnonzero((row >= a.top - a.top % a.row_pitch) & (row < a.bottom))
        ih = np.flatnonzero((col >= a.left - a.left % a.col_pitch) & (col < a.right))
        if iv.size == 0 or ih.size == 0:
            return out
        g = self.gains[:, :, min(plane, self.map_planes - 1)].astype(np.float64)
        pv, ph = self.points
        i0, i1, f = self._axis(rel_v[iv], pv, self.spacing_v, self.origin_v)
        j0, j1, e = self._axis(rel_h[ih], ph, self.spacing_h, self.origin_h)
        # interpolation is separable; interpolate first along the axis that leaves the
        # smaller intermediate array (a hostile map can have millions of points on one axis)
        if iv.size * ph <= pv * ih.size:
            tmp = g[i0] * (1 - f)[:, None] + g[i1] * f[:, None]
            vals = tmp[:, j0] * (1 - e)[None, :] + tmp[:, j1] * e[None, :]
        else:
            tmp = g[:, j0] * (1 - e)[None, :] + g[:, j1] * e[None, :]
            vals = tmp[i0] * (1 - f)[:, None] + tmp[i1] * f[:, None]
        out[np.ix_(iv, ih)] = vals
        return out

    def gain_field(self, width: int, height: int, plane: int = 0, *, ignore_pitch: bool = True) -> np.ndarray:
        """The gain at every pixel of a ``width``×``height`` image for image plane ``plane``
        (H×W float64; see :meth:`gain_grid`).

        Parameters
        ----------
        width, height : int
            The image the opcode applies to (its relative coordinates span it, its area
            is in its pixels).
        plane : int
            Image plane.
        ignore_pitch : bool
            True (default): the smooth field at every pixel of the area.  False: only
            the rows and columns the pitch selects (counted from the area's corner) get
            the gain, the others 1 (the opcode exactly).
        """
        width, height = _size(width, height)
        out = self.gain_grid(_centres(height), _centres(width), width, height, plane)
        a = self.area
        if not ignore_pitch and (a.row_pitch > 1 or a.col_pitch > 1):
            keep_r = (np.arange(height) - a.top) % a.row_pitch == 0
            keep_c = (np.arange(width) - a.left) % a.col_pitch == 0
            out[~(keep_r[:, None] & keep_c[None, :])] = 1.0
        return out


def _centres(n: int) -> np.ndarray:
    """Relative positions of the centres of n pixels: (j + ½)/n."""
    return (np.arange(n, dtype=np.float64) + 0.5) / n


def _size(width: int, height: int) -> tuple[int, int]:
    w, h = int(width), int(height)
    if w < 1 or h < 1 or w != width or h != height:
        raise ValueError(f"image size must be positive integers, got {width!r} x {height!r}")
    return w, h


def vignetting_opcodes(lists: Iterable[tuple[str, OpcodeList]]) -> list[tuple[str, int, FixVignetteRadial | GainMap]]:
    """Every FixVignetteRadial and GainMap of several lists: ``(list name, index, opcode)``.

    Raises
    ------
    DngOpcodeError
        One of them is malformed (the message names the list and the opcode).
    """
    out = []
    for name, lst in lists:
        for i, op in lst.decoded(name):
            out.append((name, i, op))
    return out
