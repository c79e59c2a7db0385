"""DNG opcode lists: parsing, round trips, hostile input (vigproc.io.dng_opcodes)."""

from __future__ import annotations

import struct
import time

import numpy as np
import pytest

from vigproc.io.dng_opcodes import (
    DNG_VERSION_1_3,
    AreaSpec,
    DngOpcodeError,
    FixVignetteRadial,
    GainMap,
    Opcode,
    OpcodeList,
    parse_opcode_list,
)
from vigproc.errors import ImageReadError, VigprocError

from conftest import SHARED

BLOBS = SHARED / "raw" / "dng_opcodes"


# ---------------------------------------------------------------- synthetic blobs
# written with struct here, not with the module's writer: a shared mistake would pass
def opcode(oid: int, params: bytes, version: int = DNG_VERSION_1_3, flags: int = 0) -> bytes:
    return struct.pack(">IIII", oid, version, flags, len(params)) + params


def fvr_params(k=(0.3, 0.1, 0.0, 0.0, 0.0), cx=0.5, cy=0.5) -> bytes:
    return struct.pack(">7d", *k, cx, cy)


def gainmap_params(gains: np.ndarray, area=(0, 0, 400, 600), plane=0, planes=1, pitch=(1, 1),
                   spacing=None, origin=(0.0, 0.0)) -> bytes:
    g = np.asarray(gains, dtype=np.float64)
    if g.ndim == 2:
        g = g[:, :, None]
    pv, ph, mp = g.shape
    sv, sh = spacing or (1.0 / max(pv - 1, 1), 1.0 / max(ph - 1, 1))
    return (struct.pack(">iiiiIIII", *area, plane, planes, *pitch)
            + struct.pack(">IIddddI", pv, ph, sv, sh, origin[0], origin[1], mp)
            + g.astype(">f4").tobytes())


def listing(*ops: bytes) -> bytes:
    return struct.pack(">I", len(ops)) + b"".join(ops)


def radial_gains(pv: int = 5, ph: int = 7, planes: int = 1) -> np.ndarray:
    v = np.linspace(-1, 1, pv)[:, None]
    h = np.linspace(-1, 1, ph)[None, :]
    g = 1.0 + 0.8 * (v * v + h * h) / 2
    return np.stack([g * (1 + 0.05 * p) for p in range(planes)], axis=-1)


def synthetic_blobs() -> dict[str, bytes]:
    return {
        "empty": listing(),
        "fvr": listing(opcode(3, fvr_params())),
        "fvr_offcentre": listing(opcode(3, fvr_params((0.5, -0.1, 0.05, 0, 0), 0.42, 0.61), flags=1)),
        "gainmap_rgb": listing(opcode(9, gainmap_params(radial_gains(5, 7, 3), planes=3))),
        "gainmap_cfa": listing(*(opcode(9, gainmap_params(radial_gains(4, 6), area=(t, l, 400, 600),
                                                            pitch=(2, 2)))
                                 for t in (0, 1) for l in (0, 1))),
        "mixed": listing(opcode(6, struct.pack(">iiii", 0, 0, 400, 600)),  # TrimBounds
                         opcode(3, fvr_params()),
                         opcode(200, b"\x01\x02\x03", version=0x01060000, flags=1),  # unknown id
                         opcode(9, gainmap_params(np.ones((1, 1))))),
    }


# ---------------------------------------------------------------- framing and round trips
@pytest.mark.parametrize("name", sorted(synthetic_blobs()))
def test_synthetic_lists_round_trip_byte_for_byte(name: str) -> None:
    blob = synthetic_blobs()[name]
    lst = parse_opcode_list(blob, name)
    assert lst.to_bytes() == blob
    # decoded vignetting opcodes re-encode to their own bytes too
    for i, op in lst.decoded(name):
        assert op.to_opcode().to_bytes() == lst.opcodes[i].to_bytes()


def test_shared_blobs_parse_round_trip_and_decode() -> None:
    if not BLOBS.is_dir():
        pytest.skip(f"shared data not present at {BLOBS} (../shared/data/raw/dng_opcodes)")
    files = sorted(BLOBS.glob("*.bin"))
    assert files, "no opcode blobs in the shared data"
    kinds = set()
    for f in files:
        blob = f.read_bytes()
        lst = parse_opcode_list(blob, str(f))
        assert lst.to_bytes() == blob, f.name
        for i, op in lst.decoded(str(f)):
            assert op.to_opcode().to_bytes() == lst.opcodes[i].to_bytes()
            kinds.add(type(op).__name__)
    assert {"FixVignetteRadial", "GainMap"} <= kinds


def test_shared_gainmap_contents() -> None:
    f = BLOBS / "GainMap.bin"
    if not f.is_file():
        pytest.skip(f"shared data not present at {f}")
    (i, gm), = parse_opcode_list(f.read_bytes(), str(f)).decoded()
    assert isinstance(gm, GainMap)
    assert (gm.area.bottom, gm.area.right, gm.area.planes) == (3040, 4056, 3)
    assert gm.points == (32, 32) and gm.map_planes == 3 and gm.spacing_v == pytest.approx(1 / 32)
    # README of the data: corners ~2.81 (R) / 2.45 (G) / 2.39 (B), centre ~1
    corner = gm.gains[0, 0]
    assert corner[0] == pytest.approx(2.81, abs=0.02) and corner[2] == pytest.approx(2.39, abs=0.02)
    f = gm.gain_field(507, 380, plane=1)
    assert f[190, 253] == pytest.approx(1.0, abs=0.02) and f.max() > 2.0


def test_shared_fix_vignette_radial_is_the_template() -> None:
    f = BLOBS / "FixVignetteRadial.bin"
    if not f.is_file():
        pytest.skip(f"shared data not present at {f}")
    lst = parse_opcode_list(f.read_bytes(), str(f))
    (_, fvr), = lst.decoded()
    assert fvr.k == (1.0, 0.0, 0.0, 0.0, 0.0) and (fvr.cx, fvr.cy) == (0.5, 0.5)
    # its version field is byte-swapped (0.0.1.3): kept as stored, not "fixed"
    assert lst.opcodes[0].version_text == "0.0.1.3"
    # k0 multiplies r^2 (DNG SDK): this template brightens the corners by 1 EV, it is no identity
    assert fvr.gain(1.0) == pytest.approx(2.0)


def test_unknown_opcodes_are_kept_and_skipped() -> None:
    lst = parse_opcode_list(synthetic_blobs()["mixed"])
    assert [op.name for op in lst] == ["TrimBounds", "FixVignetteRadial", "Unknown(200)", "GainMap"]
    assert lst.opcodes[2].params == b"\x01\x02\x03" and lst.opcodes[2].optional
    assert lst.opcodes[2].version_text == "1.6.0.0"
    assert [type(d).__name__ for _, d in lst.decoded()] == ["FixVignetteRadial", "GainMap"]


def test_writer_builds_what_the_parser_reads() -> None:
    fvr = FixVignetteRadial((0.4, 0.2, -0.05, 0.0, 0.001), cx=0.45, cy=0.55, flags=2)
    gm = GainMap(AreaSpec(0, 0, 40, 60, planes=3), radial_gains(3, 4, 3), 0.5, 1 / 3)
    blob = OpcodeList().appended(fvr.to_opcode(), gm.to_opcode()).to_bytes()
    assert blob == listing(opcode(3, fvr_params(fvr.k, 0.45, 0.55), flags=2),
                           opcode(9, gainmap_params(radial_gains(3, 4, 3), area=(0, 0, 40, 60), planes=3,
                                                    spacing=(0.5, 1 / 3))))
    (_, f2), (_, g2) = parse_opcode_list(blob).decoded()
    assert f2 == fvr
    assert np.array_equal(g2.gains, gm.gains.astype(np.float32)) and g2.area == gm.area


# ---------------------------------------------------------------- semantics
def test_fix_vignette_radial_gain_and_geometry() -> None:
    fvr = FixVignetteRadial((0.5, 0.25, 0.0, 0.0, 0.0), cx=0.25, cy=0.5)
    # 1 + k0 r^2 + k1 r^4: r = 1 at the farthest corner
    assert fvr.gain(1.0) == pytest.approx(1.75)
    assert fvr.gain(0.0) == 1.0
    w, h = 400, 300
    assert fvr.centre_px(w, h) == (-100.0, 0.0)
    assert fvr.max_radius(w, h) == pytest.approx(np.hypot(300, 150))
    g = fvr.gain_field(w, h)
    # the farthest pixel centre (the right-hand corners) is half a pixel inside r = 1
    assert g.max() == pytest.approx(1.75, abs=0.01) and g[:, -1].max() == g.max()
    assert g[150, 100] == pytest.approx(1.0, abs=1e-4)  # pixel 100 spans the centre at x = 100 (edge coordinates)


def test_gain_map_interpolation_follows_the_sdk() -> None:
    # a 2x2 map spanning the image: bilinear between the four corner gains
    gains = np.array([[1.0, 2.0], [3.0, 4.0]])
    gm = GainMap(AreaSpec(0, 0, 10, 10), gains, 1.0, 1.0)
    f = gm.gain_field(10, 10)
    x = (np.arange(10) + 0.5) / 10
    expect = 1 + 1.0 * x[None, :] + 2.0 * x[:, None]
    assert np.allclose(f, expect)
    # held beyond the outermost points: a map from 0.25 to 0.75
    gm = GainMap(AreaSpec(0, 0, 8, 8), gains, 0.5, 0.5, origin_v=0.25, origin_h=0.25)
    f = gm.gain_field(8, 8)
    assert f[0, 0] == 1.0 and f[-1, -1] == 4.0 and f[0, -1] == 2.0
    # outside the area the gain is 1; other planes use the last map plane
    gm = GainMap(AreaSpec(2, 3, 6, 8, plane=1, planes=2), np.full((2, 2, 1), 2.0), 1.0, 1.0)
    assert np.all(gm.gain_field(10, 10, plane=0) == 1.0)
    f = gm.gain_field(10, 10, plane=2)
    assert np.all(f[2:6, 3:8] == 2.0) and f.sum() == 100 + 20
    # the pitch: only every second row/column of the area when asked for the exact opcode
    gm = GainMap(AreaSpec(1, 0, 10, 10, row_pitch=2, col_pitch=2), np.full((1, 1), 3.0), 1.0, 1.0)
    f = gm.gain_field(10, 10, ignore_pitch=False)
    assert f[1, 0] == 3.0 and f[1, 1] == 1.0 and f[2, 0] == 1.0 and f[3, 2] == 3.0
    assert gm.cfa


def test_single_point_axis_uses_spacing_one_origin_zero() -> None:
    # the SDK overrides a one-point axis's spacing and origin; the stored bytes still round-trip
    blob = listing(opcode(9, gainmap_params(np.full((1, 3), 2.0), spacing=(0.0, 0.5), origin=(7.0, 0.0))))
    (_, gm), = parse_opcode_list(blob).decoded()
    assert gm.spacing_v == 1.0 and gm.origin_v == 0.0
    assert gm.to_opcode().to_bytes() == parse_opcode_list(blob).opcodes[0].to_bytes()


# ---------------------------------------------------------------- hostile input
BAD = {
    "no count": b"\x00\x00",
    "count beyond the bytes": struct.pack(">I", 1000),
    "huge count": struct.pack(">I", 0xFFFFFFFF) + b"\x00" * 32,
    "truncated header": listing(opcode(3, fvr_params()))[:14],
    "size beyond the bytes": struct.pack(">I", 1) + struct.pack(">IIII", 3, 0, 0, 0xFFFFFFF0) + b"\x00" * 8,
    "trailing bytes": listing(opcode(3, fvr_params())) + b"\x00",
    "short list (count 2, one opcode)": struct.pack(">I", 2) + opcode(3, fvr_params()),
}
BAD_DECODE = {
    "FixVignetteRadial of 48 bytes": listing(opcode(3, fvr_params()[:48])),
    "FixVignetteRadial with NaN": listing(opcode(3, fvr_params((float("nan"), 0, 0, 0, 0)))),
    "FixVignetteRadial centre outside the image": listing(opcode(3, fvr_params(cx=1.5))),
    "GainMap header truncated": listing(opcode(9, gainmap_params(np.ones((2, 2)))[:60])),
    "GainMap points beyond its bytes": listing(opcode(9, gainmap_params(np.ones((2, 2)))[:-4])),
    "GainMap with absurd point counts": listing(opcode(9, struct.pack(">iiiiIIII", 0, 0, 9, 9, 0, 1, 1, 1)
                                                      + struct.pack(">IIddddI", 0xFFFFFFFF, 0xFFFFFFFF,
                                                                    0.1, 0.1, 0, 0, 0xFFFFFFFF))),
    "GainMap with zero planes": listing(opcode(9, struct.pack(">iiiiIIII", 0, 0, 9, 9, 0, 0, 1, 1)
                                               + struct.pack(">IIddddI", 1, 1, 1, 1, 0, 0, 1) + b"\0\0\0\0")),
    "GainMap with zero pitch": listing(opcode(9, gainmap_params(np.ones((2, 2)), pitch=(0, 1)))),
    "GainMap with negative spacing": listing(opcode(9, gainmap_params(np.ones((2, 2)), spacing=(-1.0, 1.0)))),
    "GainMap with Inf gain": listing(opcode(9, gainmap_params(np.array([[1.0, np.inf]])))),
}


@pytest.mark.parametrize("what", sorted(BAD))
def test_malformed_lists_are_typed_errors_naming_the_file(what: str) -> None:
    t0 = time.process_time()  # this process's CPU time: a loaded machine does not inflate it
    with pytest.raises(DngOpcodeError) as exc:
        parse_opcode_list(BAD[what], "IMG 0001.dng OpcodeList3")
    assert "IMG 0001.dng OpcodeList3" in str(exc.value)
    assert isinstance(exc.value, ImageReadError) and isinstance(exc.value, VigprocError)
    assert time.process_time() - t0 < 0.5


@pytest.mark.parametrize("what", sorted(BAD_DECODE))
def test_malformed_vignetting_opcodes_are_typed_errors(what: str) -> None:
    lst = parse_opcode_list(BAD_DECODE[what], "x.dng")  # the framing is fine
    assert lst.to_bytes() == BAD_DECODE[what]
    with pytest.raises(DngOpcodeError, match="x.dng"):
        lst.decoded("x.dng")


def test_control_characters_in_the_source_are_escaped() -> None:
    with pytest.raises(DngOpcodeError) as exc:
        parse_opcode_list(b"", "a\nvigproc: all fine")
    assert "\n" not in str(exc.value)


def test_opcode_fields_are_checked_when_built() -> None:
    with pytest.raises(ValueError):
        Opcode(-1, 0, 0, b"")
    with pytest.raises(ValueError):
        FixVignetteRadial((0, 0, 0, 0), 0.5, 0.5)
    with pytest.raises(ValueError):
        AreaSpec(0, 0, 0, 0, row_pitch=2)
    with pytest.raises(TypeError):
        parse_opcode_list("not bytes")  # type: ignore[arg-type]


def test_large_gain_map_is_bounded_by_its_bytes() -> None:
    # a 1 x 200000 map (800 KB): its field on a frame allocates frame-sized arrays, not map x frame
    gm = GainMap(AreaSpec(0, 0, 300, 400), np.full((1, 200_000), 1.5, dtype=np.float32), 1.0, 1 / 199_999)
    t0 = time.process_time()  # CPU time, not wall time: the bound holds beside other work
    f = gm.gain_field(400, 300)
    assert time.process_time() - t0 < 2.0 and np.allclose(f, 1.5)


def test_cfa_gain_maps_cover_the_first_row_and_column() -> None:
    """Four pitch-2 maps (one per Bayer phase, the phases starting at rows/columns 0 and 1)
    averaged give the map's field on every pixel, row 0 and column 0 included (they belong
    to the first 2×2 cell of the phases starting at 1); the exact opcode still leaves them."""
    from vigproc.io.dng_opcodes import AreaSpec, GainMap

    gains = np.full((3, 3), 2.0)
    maps = [GainMap(AreaSpec(t, l, 8, 12, 0, 1, 2, 2), gains, 0.5, 0.5) for t in (0, 1) for l in (0, 1)]
    mean = sum(np.log(m.gain_field(12, 8)) for m in maps) / 4
    np.testing.assert_allclose(mean, np.log(2.0))
    exact = maps[3].gain_field(12, 8, ignore_pitch=False)  # phase (1, 1)
    assert exact[0, 0] == 1.0 and exact[1, 1] == 2.0 and exact[1, 0] == 1.0
