"""Small synthetic Bayer DNGs with a known vignetting field, for RAW end-to-end tests.

:func:`make_dng` writes the TIFF/DNG structure directly (one uncompressed 16-bit
CFA strip in IFD0, the DNG colour tags LibRaw needs), then adds the camera and
lens EXIF with the ``exiftool`` program, the way a real file carries them.  No
third-party DNG writer is needed.

The raw values are built so that LibRaw's linear development
(:func:`vigproc.io.images.read_image`) gives back ``scene * field`` for every colour
channel: a grey scene is multiplied per CFA colour by ``AsShotNeutral`` (what a
camera with that white balance would record), and the camera colour matrix is
the XYZ -> linear sRGB matrix, so the camera-to-sRGB conversion is the identity
after white balance.
"""

from __future__ import annotations

import os
import shutil
import struct
import subprocess
from typing import Any, Mapping, Sequence

import numpy as np

__all__ = ["DEFAULT_EXIF", "EXIFTOOL", "make_dng", "smooth_scene", "sony_vignetting_tags"]

EXIFTOOL = shutil.which("exiftool")

#: Camera and lens EXIF written by default (exiftool tag names).
DEFAULT_EXIF: dict[str, Any] = {
    "Make": "Vigproc",
    "Model": "Synthetic DNG 1",
    "LensMake": "Vigproc Optics",
    "LensModel": "VP 35mm F2.0 Test",
    "LensSerialNumber": "LS-0042",
    "SerialNumber": "BODY-1234",
    "FocalLength": 35,
    "FocalLengthIn35mmFormat": 35,
    "FNumber": 2.0,
    "ExposureTime": "1/125",
    "ISO": 200,
    "DateTimeOriginal": "2024:05:06 07:08:09",
}

# TIFF field types
_BYTE, _ASCII, _SHORT, _LONG, _RATIONAL, _UNDEFINED, _SSHORT, _SRATIONAL = 1, 2, 3, 4, 5, 7, 8, 10
_TYPE_SIZE = {_BYTE: 1, _ASCII: 1, _SHORT: 2, _LONG: 4, _RATIONAL: 8, _UNDEFINED: 1, _SSHORT: 2, _SRATIONAL: 8}
#: Sony's lens-correction tags of an ARW's raw IFD (exiftool: SubIFD:...; int16s).
SONY_VIGNETTING_CORR_PARAMS, SONY_CA_CORR_PARAMS, SONY_DISTORTION_CORR_PARAMS = 0x7032, 0x7035, 0x7037
#: DNG opcode list tags (DNG 1.3): OpcodeList1, OpcodeList2, OpcodeList3.
OPCODE_LIST_TAGS = {1: 51008, 2: 51009, 3: 51022}

# XYZ(D65) -> linear sRGB: a camera whose native space is linear sRGB.
_XYZ_TO_SRGB = (
    (3.2406, -1.5372, -0.4986),
    (-0.9689, 1.8758, 0.0415),
    (0.0557, -0.2040, 1.0570),
)


def smooth_scene(height: int, width: int, seed: int = 0, contrast: float = 0.25) -> np.ndarray:
    """A positive, mildly textured grey scene (smooth 1/f noise around 0.4).

    Parameters
    ----------
    height, width : int
    seed : int
    contrast : float
        Standard deviation of the log texture.

    Returns
    -------
    numpy.ndarray
        ``HxW`` float64, values around 0.4 (roughly 0.15..0.9).
    """
    rng = np.random.default_rng(seed)
    f = np.fft.rfft2(rng.normal(size=(height, width)))
    fy = np.fft.fftfreq(height)[:, None]
    fx = np.fft.rfftfreq(width)[None, :]
    f /= np.maximum(np.hypot(fx, fy), 1.0 / max(height, width)) ** 1.2
    tex = np.fft.irfft2(f, s=(height, width))
    return 0.4 * np.exp(contrast * tex / tex.std())


def _rational(x: float) -> tuple[int, int]:
    den = 10000  # 4 decimals: enough for colour matrices and neutrals
    return int(round(x * den)), den


def _entry(tag: int, typ: int, values: Any) -> tuple[int, int, int, bytes]:
    """Encode one IFD entry's value bytes (little-endian)."""
    if typ == _ASCII:
        raw = values.encode("ascii", "replace") + b"\0"
        return tag, typ, len(raw), raw
    if typ == _UNDEFINED:  # bytes as they are (an opcode list)
        return tag, typ, len(values), bytes(values)
    vals = list(values) if isinstance(values, (list, tuple)) else [values]
    if typ == _BYTE:
        raw = bytes(vals)
    elif typ == _SHORT:
        raw = struct.pack(f"<{len(vals)}H", *vals)
    elif typ == _SSHORT:
        raw = struct.pack(f"<{len(vals)}h", *vals)
    elif typ == _LONG:
        raw = struct.pack(f"<{len(vals)}I", *vals)
    elif typ in (_RATIONAL, _SRATIONAL):
        fmt = "i" if typ == _SRATIONAL else "I"
        raw = b"".join(struct.pack(f"<{fmt}{fmt}", *_rational(v)) for v in vals)
    else:  # pragma: no cover - only the types above are used
        raise ValueError(typ)
    return tag, typ, len(vals), raw


def _ifd_bytes(enc: list[tuple[int, int, int, bytes]], at: int) -> bytes:
    """One IFD (entries sorted by tag) placed at offset ``at``, its out-of-line values
    (over 4 bytes) right after it, word aligned."""
    enc = sorted(enc, key=lambda e: e[0])
    data_off = at + 2 + 12 * len(enc) + 4
    blobs = b""
    head = struct.pack("<H", len(enc))
    for tag, typ, cnt, raw in enc:
        if len(raw) > 4:
            if (data_off + len(blobs)) % 2:
                blobs += b"\0"
            head += struct.pack("<HHII", tag, typ, cnt, data_off + len(blobs))
            blobs += raw
        else:
            head += struct.pack("<HHI", tag, typ, cnt) + raw.ljust(4, b"\0")
    return head + struct.pack("<I", 0) + blobs  # no next IFD


def _write_tiff(path: str, ifds: list[tuple[list[tuple[int, int, Any]], bytes]]) -> None:
    """Write a little-endian TIFF: IFD0, then (when more are given) the others as its
    SubIFDs; each IFD has one strip (``(entries, strip)``; ``entries`` without
    StripOffsets/StripByteCounts/SubIFDs, which are added here)."""
    def encoded(i: int, strip_offsets: list[int], sub_offsets: list[int]) -> list[tuple[int, int, int, bytes]]:
        entries, strip = ifds[i]
        enc = [_entry(t, ty, v) for t, ty, v in entries]
        enc += [_entry(273, _LONG, strip_offsets[i]), _entry(279, _LONG, len(strip))]
        if i == 0 and len(ifds) > 1:
            enc.append(_entry(330, _LONG, sub_offsets))  # SubIFDs
        return enc

    # the layout's sizes do not depend on the offsets: measure with zeros, then place
    zeros = [0] * len(ifds)
    at, ifd_at = 8, []
    for i in range(len(ifds)):
        ifd_at.append(at)
        at += len(_ifd_bytes(encoded(i, zeros, zeros[1:]), at))
        at += at % 2
    strip_at = []
    for _entries, strip in ifds:
        at += (-at) % 8
        strip_at.append(at)
        at += len(strip)
    out = bytearray(b"II*\0" + struct.pack("<I", ifd_at[0]))
    for i in range(len(ifds)):
        out += b"\0" * (ifd_at[i] - len(out))
        out += _ifd_bytes(encoded(i, strip_at, ifd_at[1:]), ifd_at[i])
    for i, (_entries, strip) in enumerate(ifds):
        out += b"\0" * (strip_at[i] - len(out))
        out += strip
    with open(path, "wb") as fh:
        fh.write(out)


def sony_vignetting_tags(values: Sequence[int]) -> list[tuple[int, int, Any]]:
    """Sony's three lens-correction tags of an ARW's raw IFD as darktable needs them:
    ``VignettingCorrParams`` with ``values`` (after their count), zero distortion and
    chromatic aberration tables of the same count (darktable 4.2 reads the vignetting
    only when all three are present and their counts agree)."""
    n = len(values)
    return [(SONY_VIGNETTING_CORR_PARAMS, _SSHORT, [n, *values]),
            (SONY_CA_CORR_PARAMS, _SSHORT, [2 * n] + [0] * (2 * n)),
            (SONY_DISTORTION_CORR_PARAMS, _SSHORT, [n] + [0] * n)]


def make_dng(
    path: str | os.PathLike[str],
    *,
    width: int = 384,
    height: int = 256,
    field: np.ndarray | None = None,
    scene: np.ndarray | None = None,
    exif: Mapping[str, Any] | None = None,
    neutral: tuple[float, float, float] = (0.5, 1.0, 0.7),
    black: int = 512,
    white: int = 16383,
    noise: float = 0.0,
    seed: int = 0,
    opcode_lists: Mapping[int, bytes] | None = None,
    raw_tags: Sequence[tuple[int, int, Any]] = (),
    subifd: bool = False,
    _untagged: bool = False,
) -> np.ndarray:
    """Write a small RGGB Bayer DNG of ``scene * field`` that LibRaw decodes.

    Parameters
    ----------
    path : str or os.PathLike
        Output file (``.dng``).
    width, height : int
        Sensor size in pixels; both must be even.
    field : numpy.ndarray, optional
        ``HxW`` attenuation (1 = no fall-off) sampled at the sensor pixels;
        default all ones.
    scene : numpy.ndarray, optional
        ``HxW`` grey scene radiance in ``[0, 1)`` of the raw range; default
        :func:`smooth_scene`.
    exif : mapping, optional
        Tags written by exiftool (tag name -> value); default :data:`DEFAULT_EXIF`.
        Pass ``{}`` for none.
    neutral : (float, float, float)
        ``AsShotNeutral``: the camera's raw response to grey, per R, G, B.
    black, white : int
        ``BlackLevel`` and ``WhiteLevel`` of the 16-bit samples.
    noise : float
        Standard deviation of additive Gaussian noise, as a fraction of the
        ``white - black`` range.
    seed : int
        Seed of the default scene and of the noise.
    opcode_lists : mapping, optional
        ``{1|2|3: bytes}``: DNG opcode lists written as OpcodeList1/2/3 of the raw IFD
        (IFD0, or the raw SubIFD with ``subifd``), as a camera writes them (see
        :mod:`vigproc.io.dng_opcodes`).
    raw_tags : sequence of (tag, type, values)
        More tags of the raw IFD (e.g. Sony's ``VignettingCorrParams``, type 8: int16s).
    subifd : bool
        Write the raw image as the first SubIFD of IFD0, which holds an 8×8 preview and
        the DNG's colour tags (the layout of camera DNGs and of ARWs, where exiftool
        names the raw IFD's tags ``SubIFD:``); default the raw image in IFD0.
    _untagged : bool
        Leave ``exif`` to the caller (:func:`make_dngs`, which writes many files' in one run).

    Returns
    -------
    numpy.ndarray
        ``HxW`` float64: the linear image LibRaw's development should give back
        (``scene * field`` without noise and quantisation).
    """
    if width % 2 or height % 2 or width < 16 or height < 16:
        raise ValueError(f"width and height must be even and >= 16, got {width}x{height}")
    if scene is None:
        scene = smooth_scene(height, width, seed)
    if field is None:
        field = np.ones((height, width))
    scene = np.asarray(scene, dtype=np.float64)
    field = np.asarray(field, dtype=np.float64)
    if scene.shape != (height, width) or field.shape != (height, width):
        raise ValueError(f"scene {scene.shape} and field {field.shape} must be {(height, width)}")
    truth = scene * field
    if truth.max() * max(neutral) >= 1.0 or truth.min() < 0:
        raise ValueError("scene * field * neutral must stay within [0, 1) of the raw range")

    # RGGB: the raw value a camera with this white balance records for grey
    gain = np.empty((height, width))
    gain[0::2, 0::2] = neutral[0]
    gain[0::2, 1::2] = neutral[1]
    gain[1::2, 0::2] = neutral[1]
    gain[1::2, 1::2] = neutral[2]
    rng = np.random.default_rng(seed + 1)
    sig = truth * gain + (rng.normal(scale=noise, size=truth.shape) if noise > 0 else 0.0)
    raw = np.clip(np.rint(black + sig * (white - black)), 0, white).astype("<u2")

    tags = _exif_tags(exif)
    make = str(tags.get("Make", "Vigproc"))
    model = str(tags.get("Model", "Synthetic DNG"))
    entries: list[tuple[int, int, Any]] = [
        (254, _LONG, 0),  # NewSubfileType: main image
        (256, _LONG, width),
        (257, _LONG, height),
        (258, _SHORT, 16),  # BitsPerSample
        (259, _SHORT, 1),  # Compression: none
        (262, _SHORT, 32803),  # PhotometricInterpretation: CFA
        (274, _SHORT, 1),  # Orientation
        (277, _SHORT, 1),  # SamplesPerPixel
        (278, _LONG, height),  # RowsPerStrip
        (284, _SHORT, 1),  # PlanarConfiguration
        (33421, _SHORT, (2, 2)),  # CFARepeatPatternDim
        (33422, _BYTE, (0, 1, 1, 2)),  # CFAPattern: RGGB
        (50706, _BYTE, (1, 4, 0, 0)),  # DNGVersion
        (50707, _BYTE, (1, 1, 0, 0)),  # DNGBackwardVersion
        (50708, _ASCII, f"{make} {model}"),  # UniqueCameraModel
        (50710, _BYTE, (0, 1, 2)),  # CFAPlaneColor
        (50711, _SHORT, 1),  # CFALayout: rectangular
        (50714, _LONG, black),  # BlackLevel
        (50717, _LONG, white),  # WhiteLevel
        (50721, _SRATIONAL, [v for row in _XYZ_TO_SRGB for v in row]),  # ColorMatrix1
        (50728, _RATIONAL, neutral),  # AsShotNeutral
        (50778, _SHORT, 21),  # CalibrationIlluminant1: D65
    ]
    for n, blob in (opcode_lists or {}).items():
        entries.append((OPCODE_LIST_TAGS[n], _UNDEFINED, blob))
    entries += list(raw_tags)
    fspath = os.fspath(path)
    if not subifd:
        _write_tiff(fspath, [(entries, raw.tobytes())])
    else:
        # DNG: the camera's colour tags in IFD0, the raw image's own in its IFD
        ifd0_tags = {50706, 50707, 50708, 50721, 50728, 50778}
        preview = [(254, _LONG, 1), (256, _LONG, 8), (257, _LONG, 8), (258, _SHORT, (8, 8, 8)), (259, _SHORT, 1),
                   (262, _SHORT, 2), (274, _SHORT, 1), (277, _SHORT, 3), (278, _LONG, 8), (284, _SHORT, 1)]
        preview += [e for e in entries if e[0] in ifd0_tags]
        rawifd = [e for e in entries if e[0] not in ifd0_tags and e[0] != 274]
        _write_tiff(fspath, [(preview, bytes(8 * 8 * 3)), (rawifd, raw.tobytes())])

    if tags and not _untagged:
        write_exif([(fspath, tags)])
    return truth


def _exif_tags(exif: Mapping[str, Any] | None) -> Mapping[str, Any]:
    """The tags a DNG of :func:`make_dng` gets: ``exif``, or :data:`DEFAULT_EXIF` when None."""
    return DEFAULT_EXIF if exif is None else exif


def make_dngs(frames: Sequence[tuple[str | os.PathLike[str], Mapping[str, Any]]]) -> list[np.ndarray]:
    """:func:`make_dng` of each ``(path, keyword arguments)``, their EXIF written by one
    exiftool run (:func:`write_exif`): one exiftool start, not one a frame (about 0.2 CPU s
    each).  The same files; returns each frame's linear truth, as :func:`make_dng` does."""
    truths = [make_dng(path, **kw, _untagged=True) for path, kw in frames]
    write_exif([(path, _exif_tags(kw.get("exif"))) for path, kw in frames])
    return truths


def write_exif(files: Sequence[tuple[str | os.PathLike[str], Mapping[str, Any]]]) -> None:
    """Each ``(path, tags)``'s tags (tag name -> value) written into its file by one exiftool
    run, ``-execute`` between the files; files with no tags are left alone.  A warning
    of exiftool's is an error (a tag it did not write)."""
    files = [(os.path.abspath(os.fspath(path)), tags) for path, tags in files if tags]
    if not files:
        return
    if EXIFTOOL is None:
        raise RuntimeError("the exiftool program is needed to write the DNG's EXIF")
    args = [EXIFTOOL]
    for i, (path, tags) in enumerate(files):
        # absolute paths: a name starting with '-' cannot look like an option
        args += [*(["-execute"] if i else []), *(f"-{k}={v}" for k, v in tags.items()), path]
    res = subprocess.run([*args, "-common_args", "-q", "-overwrite_original"], capture_output=True, text=True)
    if res.returncode != 0 or "Warning" in res.stderr:
        raise RuntimeError(f"exiftool failed on {[p for p, _ in files]!r}: {res.stderr.strip()}")
