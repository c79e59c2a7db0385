"""A linear-light sRGB ICC profile for vigproc's linear outputs.

vigproc's 16-bit and float TIFFs hold linear light in sRGB (Rec. 709) primaries. A
file without a profile is taken for sRGB-encoded by most editors and viewers, so a
linear one looks far too dark. This module builds the small ICC v2 display profile
that says what the values are: sRGB primaries (Bradford-adapted to the D50 profile
connection space, as the sRGB v2 profiles do), D65 white, and an identity tone curve
(gamma 1.0) for each channel.

References
----------
International Color Consortium, "File Format for Color Profiles", ICC.1:2001-04
(version 2.4): the header (section 6.1), tag table (6.2), ``curveType`` (6.5.3),
``XYZType`` (6.5.26), ``textDescriptionType`` (6.5.17), ``textType`` (6.5.18).
IEC 61966-2-1 (sRGB): the primaries and white point.
"""

from __future__ import annotations

import functools
import struct

#: sRGB primaries' XYZ, Bradford-adapted from D65 to D50 (the colorants of sRGB v2 profiles).
_COLORANTS = {
    b"rXYZ": (0.4360747, 0.2225045, 0.0139322),
    b"gXYZ": (0.3850649, 0.7168786, 0.0971045),
    b"bXYZ": (0.1430804, 0.0606169, 0.7141733),
}
_D65 = (0.9504559, 1.0, 1.0890578)  # media white point (the display's white)
_D50 = (0.9642, 1.0, 0.8249)  # the profile connection space's illuminant
DESCRIPTION = "vigproc linear sRGB (gamma 1.0)"


def _s15f16(v: float) -> bytes:
    return struct.pack(">i", round(v * 65536))


def _xyz(xyz: tuple[float, float, float]) -> bytes:
    return b"XYZ " + bytes(4) + b"".join(_s15f16(v) for v in xyz)


def _desc(text: str) -> bytes:
    ascii_ = text.encode("ascii") + b"\0"
    # ASCII part, then empty Unicode and ScriptCode parts (ICC.1:2001-04 6.5.17)
    return (b"desc" + bytes(4) + struct.pack(">I", len(ascii_)) + ascii_
            + struct.pack(">II", 0, 0) + struct.pack(">HB", 0, 0) + bytes(67))


@functools.lru_cache(maxsize=1)
def linear_srgb_profile() -> bytes:
    """The ICC v2 profile of linear-light sRGB (identity tone curves), as bytes."""
    linear = b"curv" + bytes(4) + struct.pack(">I", 1) + struct.pack(">H", 0x0100)  # one entry: gamma 1.0
    tags = [
        (b"desc", _desc(DESCRIPTION)),
        (b"cprt", b"text" + bytes(4) + b"No copyright, use freely\0"),
        (b"wtpt", _xyz(_D65)),
        *((sig, _xyz(v)) for sig, v in _COLORANTS.items()),
        (b"rTRC", linear), (b"gTRC", linear), (b"bTRC", linear),
    ]
    table_size = 4 + 12 * len(tags)
    offset = 128 + table_size
    entries, data = [], b""
    for sig, body in tags:
        pad = (-len(body)) % 4
        entries.append(struct.pack(">4sII", sig, offset + len(data), len(body)))
        data += body + bytes(pad)
    size = 128 + table_size + len(data)
    header = (struct.pack(">I", size) + bytes(4) + bytes([2, 0x10, 0, 0]) + b"mntr" + b"RGB " + b"XYZ "
              + struct.pack(">6H", 2026, 1, 1, 0, 0, 0) + b"acsp" + bytes(4) + struct.pack(">I", 0) + bytes(8)
              + bytes(8) + struct.pack(">I", 0) + b"".join(_s15f16(v) for v in _D50) + bytes(4) + bytes(44))
    assert len(header) == 128
    return header + struct.pack(">I", len(tags)) + b"".join(entries) + data
