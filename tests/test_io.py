"""Tests for vigproc.io.images: linear-light reading, transfer curves, typed errors, atomic writing.

Every image is made here in ``tmp_path`` with OpenImageIO directly (not with the
module under test) so a reader bug cannot be hidden by a matching writer bug.
"""

from __future__ import annotations

import hashlib
import os
import stat
import struct
import zlib
from pathlib import Path

import numpy as np
import OpenImageIO as oiio
import pytest

from vigproc.errors import (
    ImageReadError,
    ImageWriteError,
    InvalidImageError,
    UnsupportedFormatError,
    VigprocError,
)
from vigproc.io.images import ImageInfo, linear_to_srgb, read_image, srgb_to_linear, write_image

RAW_DIR = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "raw"  # ../shared beside the repo
# The two RAWs README.md / files.csv list as decodable by rawpy.
DECODABLE_RAWS = ("rawpy/RAW_KODAK_DC50.KDC", "tinydng/colorchart.dng")


# --------------------------------------------------------------------------- #
# helpers
# --------------------------------------------------------------------------- #


def oiio_write(path: Path, arr: np.ndarray, fmt: str, **attrs: object) -> Path:
    """Write ``arr`` (HxW or HxWxC) with OpenImageIO as type ``fmt``."""
    h, w = arr.shape[:2]
    nch = 1 if arr.ndim == 2 else arr.shape[2]
    arr = arr.reshape(h, w, nch)  # OIIO's binding misreads 2-D arrays (transposes them)
    spec = oiio.ImageSpec(w, h, nch, fmt)
    for k, v in attrs.items():
        spec.attribute(k, v)
    out = oiio.ImageOutput.create(str(path))
    assert out is not None, oiio.geterror()
    assert out.open(str(path), spec), out.geterror()
    assert out.write_image(np.ascontiguousarray(arr)), out.geterror()
    assert out.close()
    return path


def png_chunk(kind: bytes, data: bytes) -> bytes:
    return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data) & 0xFFFFFFFF)


def make_png(path: Path, width: int, height: int, rows: bytes, extra: list[bytes] = (), color_type: int = 2) -> Path:
    """Hand-made 8-bit PNG (valid CRCs) so header fields can be anything."""
    ihdr = struct.pack(">IIBBBBB", width, height, 8, color_type, 0, 0, 0)
    path.write_bytes(
        b"\x89PNG\r\n\x1a\n"
        + png_chunk(b"IHDR", ihdr)
        + b"".join(extra)
        + png_chunk(b"IDAT", zlib.compress(rows))
        + png_chunk(b"IEND", b"")
    )
    return path


def sha256(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def gradient_codes(h: int = 32, w: int = 48, top: int = 255) -> np.ndarray:
    """Random codes in [0, top], including 0, top and (for 8-bit) every code."""
    rng = np.random.default_rng(1234)
    codes = rng.integers(0, top + 1, size=(h, w, 3))
    n = min(top + 1, codes.size)
    codes.flat[:n] = np.linspace(0, top, n).round().astype(int)
    return codes


def assert_names_file(excinfo: pytest.ExceptionInfo, path: Path) -> None:
    assert path.name in str(excinfo.value), f"message does not name the file: {excinfo.value}"


# --------------------------------------------------------------------------- #
# sRGB curve
# --------------------------------------------------------------------------- #


def test_srgb_known_values() -> None:
    assert float(srgb_to_linear(0.0)) == 0.0
    assert float(srgb_to_linear(1.0)) == pytest.approx(1.0, abs=1e-12)
    assert float(srgb_to_linear(0.5)) == pytest.approx(0.21404114048223255, abs=1e-12)
    # linear segment and the 0.04045 threshold
    assert float(srgb_to_linear(0.04)) == pytest.approx(0.04 / 12.92, abs=1e-15)
    assert float(srgb_to_linear(0.04045)) == pytest.approx(0.04045 / 12.92, abs=1e-12)
    assert float(srgb_to_linear(0.0405)) == pytest.approx(((0.0405 + 0.055) / 1.055) ** 2.4, abs=1e-15)
    assert float(linear_to_srgb(0.0031308)) == pytest.approx(0.0031308 * 12.92, abs=1e-12)
    assert float(linear_to_srgb(0.214041140482232)) == pytest.approx(0.5, abs=1e-12)
    assert float(linear_to_srgb(1.0)) == pytest.approx(1.0, abs=1e-12)


def test_srgb_inverse_roundtrip_and_dtypes() -> None:
    x = np.linspace(0.0, 1.0, 100_001)
    # 1e-7, not 1e-12: the standard's two thresholds (0.04045 and 0.0031308) are
    # not exactly consistent, a ~3e-8 step at the join is inherent to IEC 61966-2-1.
    np.testing.assert_allclose(linear_to_srgb(srgb_to_linear(x)), x, atol=1e-7, rtol=0)
    np.testing.assert_allclose(srgb_to_linear(linear_to_srgb(x)), x, atol=1e-7, rtol=0)
    # monotone, continuous at the threshold
    y = srgb_to_linear(x)
    assert np.all(np.diff(y) > 0)
    x32 = x.astype(np.float32)
    assert srgb_to_linear(x32).dtype == np.float32
    assert linear_to_srgb(x32).dtype == np.float32
    np.testing.assert_allclose(srgb_to_linear(x32), srgb_to_linear(x), atol=1e-6)
    # integer input becomes float64; negative values mirror
    assert srgb_to_linear(np.array([0, 1])).dtype == np.float64
    np.testing.assert_allclose(srgb_to_linear(-x), -y)
    # shape is kept
    assert srgb_to_linear(np.zeros((2, 3, 4))).shape == (2, 3, 4)


# --------------------------------------------------------------------------- #
# reading: round-trips per format
# --------------------------------------------------------------------------- #


def test_png8_srgb_decodes_exactly(tmp_path: Path) -> None:
    codes = gradient_codes()
    p = oiio_write(tmp_path / "a.png", codes.astype(np.uint8), "uint8")
    img, info = read_image(p)
    assert img.dtype == np.float32 and img.shape == codes.shape
    np.testing.assert_allclose(img, srgb_to_linear(codes / 255.0), atol=1e-6, rtol=0)
    assert info == ImageInfo(
        path=str(p), format="png", width=48, height=32, channels=3,
        bit_depth="uint8", transfer="srgb", colorspace="srgb_rec709_scene",
    )


def test_png16_srgb_decodes_exactly(tmp_path: Path) -> None:
    codes = gradient_codes(top=65535)
    p = oiio_write(tmp_path / "a16.png", codes.astype(np.uint16), "uint16")
    img, info = read_image(p)
    np.testing.assert_allclose(img, srgb_to_linear(codes / 65535.0), atol=1e-6, rtol=0)
    assert (info.bit_depth, info.transfer) == ("uint16", "srgb")


def test_png_without_colour_chunk_is_srgb_and_gamma_is_honoured(tmp_path: Path) -> None:
    rows = b"".join(b"\0" + bytes(range(r * 12, r * 12 + 12)) for r in range(4))
    codes = np.frombuffer(bytes(b for r in range(4) for b in range(r * 12, r * 12 + 12)), np.uint8).reshape(4, 4, 3)
    plain = make_png(tmp_path / "plain.png", 4, 4, rows)
    img, info = read_image(plain)
    assert info.transfer == "srgb"
    np.testing.assert_allclose(img, srgb_to_linear(codes / 255.0), atol=1e-6)

    g22 = make_png(tmp_path / "g22.png", 4, 4, rows, [png_chunk(b"gAMA", struct.pack(">I", 45455))])
    img, info = read_image(g22)
    assert info.transfer == "gamma2.2"
    np.testing.assert_allclose(img, (codes / 255.0) ** 2.2, atol=1e-6)

    lin = make_png(tmp_path / "g10.png", 4, 4, rows, [png_chunk(b"gAMA", struct.pack(">I", 100000))])
    img, info = read_image(lin)
    assert info.transfer == "linear"
    np.testing.assert_allclose(img, codes / 255.0, atol=1e-7)


def test_tiff16_and_8_untagged_is_srgb(tmp_path: Path) -> None:
    codes = gradient_codes(top=65535)
    p = oiio_write(tmp_path / "a.tif", codes.astype(np.uint16), "uint16")
    img, info = read_image(p)
    assert (info.format, info.bit_depth, info.transfer, info.colorspace) == ("tiff", "uint16", "srgb", None)
    np.testing.assert_allclose(img, srgb_to_linear(codes / 65535.0), atol=1e-6)

    c8 = gradient_codes()
    p8 = oiio_write(tmp_path / "a8.tiff", c8.astype(np.uint8), "uint8")
    img, info = read_image(p8)
    np.testing.assert_allclose(img, srgb_to_linear(c8 / 255.0), atol=1e-6)


def test_float_tiff_is_linear_as_stored(tmp_path: Path) -> None:
    rng = np.random.default_rng(5)
    data = (rng.random((20, 30, 3)) * 4 - 1).astype(np.float32)  # negatives and >1 kept
    p = oiio_write(tmp_path / "f.tif", data, "float")
    img, info = read_image(p)
    assert (info.bit_depth, info.transfer) == ("float", "linear")
    np.testing.assert_array_equal(img, data)


@pytest.mark.parametrize("depth", ["half", "float"])
def test_exr_is_linear_exact(tmp_path: Path, depth: str) -> None:
    rng = np.random.default_rng(6)
    data = (rng.random((17, 23, 3)) * 10).astype(np.float32)
    p = oiio_write(tmp_path / f"{depth}.exr", data, depth)
    img, info = read_image(p)
    expected = data.astype(np.float16).astype(np.float32) if depth == "half" else data
    np.testing.assert_array_equal(img, expected)
    assert (info.format, info.bit_depth, info.transfer) == ("openexr", depth, "linear")


def test_jpeg_within_tolerance(tmp_path: Path) -> None:
    yy, xx = np.mgrid[0:64, 0:96]
    codes = np.stack([xx * 255 // 95, yy * 255 // 63, (xx + yy) * 255 // 158], -1)
    p = oiio_write(tmp_path / "a.jpg", codes.astype(np.uint8), "uint8", CompressionQuality=100)
    img, info = read_image(p)
    assert (info.format, info.transfer, info.channels) == ("jpeg", "srgb", 3)
    ref = srgb_to_linear(codes / 255.0)
    err = np.abs(img - ref)
    assert err.max() < 0.03 and err.mean() < 0.003
    # it really was decoded: linear values are darker than the codes in mid-tones
    assert img.mean() < (codes / 255.0).mean() - 0.1


def test_transfer_override(tmp_path: Path) -> None:
    codes = gradient_codes()
    p = oiio_write(tmp_path / "a.png", codes.astype(np.uint8), "uint8")
    auto, _ = read_image(p)
    lin, info = read_image(p, transfer="linear")
    assert info.transfer == "linear"
    np.testing.assert_allclose(lin, codes / 255.0, atol=1e-7)
    assert not np.allclose(auto, lin, atol=1e-3)
    g, info = read_image(p, transfer="gamma2.2")
    assert info.transfer == "gamma2.2"
    np.testing.assert_allclose(g, (codes / 255.0) ** 2.2, atol=1e-6)
    # forcing sRGB on a float file decodes it too
    f = oiio_write(tmp_path / "f.exr", (codes / 255.0).astype(np.float32), "float")
    forced, info = read_image(f, transfer="srgb")
    assert info.transfer == "srgb"
    np.testing.assert_allclose(forced, srgb_to_linear((codes / 255.0).astype(np.float32)), atol=1e-6)
    with pytest.raises(ValueError):
        read_image(p, transfer="bogus")


def test_gray_and_alpha(tmp_path: Path) -> None:
    gray = (np.arange(20 * 10) % 256).reshape(20, 10).astype(np.uint8)
    p = oiio_write(tmp_path / "g.png", gray, "uint8")
    img, info = read_image(p)
    assert img.shape == (20, 10) and info.channels == 1
    np.testing.assert_allclose(img, srgb_to_linear(gray / 255.0), atol=1e-6)

    # RGBA: alpha dropped, colour as stored (not premultiplied by alpha)
    rgba = np.zeros((8, 8, 4), np.uint8)
    rgba[..., 0], rgba[..., 1], rgba[..., 2], rgba[..., 3] = 200, 100, 50, 64
    path = tmp_path / "rgba.png"
    rows = b"".join(b"\0" + rgba[r].tobytes() for r in range(8))
    make_png(path, 8, 8, rows, color_type=6)
    img, info = read_image(path)
    assert img.shape == (8, 8, 3) and info.channels == 3
    np.testing.assert_allclose(img[0, 0], srgb_to_linear(np.array([200, 100, 50]) / 255.0), atol=1e-6)

    # gray + alpha -> HxW
    ga = np.zeros((4, 4, 2), np.uint8)
    ga[..., 0], ga[..., 1] = 128, 10
    make_png(tmp_path / "ga.png", 4, 4, b"".join(b"\0" + ga[r].tobytes() for r in range(4)), color_type=4)
    img, _ = read_image(tmp_path / "ga.png")
    assert img.shape == (4, 4)
    np.testing.assert_allclose(img, srgb_to_linear(128 / 255.0), atol=1e-6)


# --------------------------------------------------------------------------- #
# reading: bad inputs -> typed errors naming the file
# --------------------------------------------------------------------------- #


@pytest.fixture()
def good_png(tmp_path: Path) -> Path:
    rng = np.random.default_rng(7)
    return oiio_write(tmp_path / "good.png", rng.integers(0, 256, (64, 64, 3)).astype(np.uint8), "uint8")


@pytest.fixture()
def good_jpg(tmp_path: Path) -> Path:
    rng = np.random.default_rng(8)
    return oiio_write(tmp_path / "good.jpg", rng.integers(0, 256, (64, 64, 3)).astype(np.uint8), "uint8")


@pytest.mark.parametrize("name", ["empty.png", "empty.jpg", "empty.exr", "empty.nef"])
def test_zero_byte(tmp_path: Path, name: str) -> None:
    p = tmp_path / name
    p.write_bytes(b"")
    with pytest.raises(ImageReadError, match="empty") as ei:
        read_image(p)
    assert_names_file(ei, p)


def test_truncated_png(tmp_path: Path, good_png: Path) -> None:
    data = good_png.read_bytes()
    for cut in (len(data) // 2, 30, 12):
        p = tmp_path / f"trunc{cut}.png"
        p.write_bytes(data[:cut])
        with pytest.raises(ImageReadError) as ei:
            read_image(p)
        assert not isinstance(ei.value, UnsupportedFormatError)  # it is a PNG, just broken
        assert_names_file(ei, p)


def test_truncated_jpeg(tmp_path: Path, good_jpg: Path) -> None:
    data = good_jpg.read_bytes()
    for cut in (len(data) // 2, 20):
        p = tmp_path / f"trunc{cut}.jpg"
        p.write_bytes(data[:cut])
        with pytest.raises(ImageReadError) as ei:
            read_image(p)
        assert_names_file(ei, p)


def test_random_bytes_named_jpg(tmp_path: Path) -> None:
    p = tmp_path / "random.jpg"
    p.write_bytes(np.random.default_rng(9).bytes(5000))
    with pytest.raises(UnsupportedFormatError) as ei:
        read_image(p)
    assert_names_file(ei, p)


def test_text_named_png(tmp_path: Path) -> None:
    p = tmp_path / "notes.png"
    p.write_text("this is not an image\n" * 20)
    with pytest.raises(UnsupportedFormatError, match="not a recognised image") as ei:
        read_image(p)
    assert_names_file(ei, p)


def test_png_renamed_jpg_is_read(tmp_path: Path, good_png: Path) -> None:
    p = tmp_path / "liar.jpg"
    p.write_bytes(good_png.read_bytes())
    img, info = read_image(p)
    ref, _ = read_image(good_png)
    assert info.format == "png"
    np.testing.assert_array_equal(img, ref)


def test_jpeg_renamed_tif_and_tiff_renamed_nef_are_read(tmp_path: Path, good_jpg: Path) -> None:
    p = tmp_path / "liar.tif"
    p.write_bytes(good_jpg.read_bytes())
    _, info = read_image(p)
    assert info.format == "jpeg"
    t = oiio_write(tmp_path / "plain.tif", np.full((8, 8, 3), 1000, np.uint16), "uint16")
    n = tmp_path / "plain.nef"
    n.write_bytes(t.read_bytes())
    img, info = read_image(n)
    assert info.format == "tiff" and img.shape == (8, 8, 3)


def test_unsupported_but_valid_format(tmp_path: Path) -> None:
    p = oiio_write(tmp_path / "pic.bmp", np.zeros((8, 8, 3), np.uint8), "uint8")
    with pytest.raises(UnsupportedFormatError, match="bmp") as ei:
        read_image(p)
    assert_names_file(ei, p)


def test_nonexistent_and_directory(tmp_path: Path) -> None:
    missing = tmp_path / "missing.png"
    with pytest.raises(ImageReadError, match="not found") as ei:
        read_image(missing)
    assert_names_file(ei, missing)
    d = tmp_path / "folder.png"
    d.mkdir()
    with pytest.raises(ImageReadError, match="directory") as ei:
        read_image(d)
    assert_names_file(ei, d)


@pytest.mark.parametrize(
    "name,width,height",
    [
        ("bomb_huge.png", 100_000, 100_000),  # OIIO's own size limit trips first
        ("bomb_300mp.png", 20_000, 15_000),  # under OIIO's limit: caught by max_pixels
    ],
)
def test_absurd_declared_dimensions(tmp_path: Path, name: str, width: int, height: int) -> None:
    # A few hundred bytes claiming a huge image; must fail on the header alone.
    p = make_png(tmp_path / name, width, height, b"\0" * 100)
    assert p.stat().st_size < 300
    with pytest.raises(InvalidImageError) as ei:
        read_image(p)
    assert_names_file(ei, p)


def test_max_pixels_and_zero_dimension(tmp_path: Path, good_png: Path) -> None:
    with pytest.raises(InvalidImageError, match="64x64 = 4096 pixels"):
        read_image(good_png, max_pixels=1000)
    read_image(good_png, max_pixels=64 * 64)  # exactly at the limit is fine
    zero = make_png(tmp_path / "zero.png", 0, 4, b"")
    with pytest.raises(VigprocError) as ei:
        read_image(zero)
    assert isinstance(ei.value, (ImageReadError, InvalidImageError))
    assert_names_file(ei, zero)


def test_fuzzed_files_only_raise_typed_errors(tmp_path: Path) -> None:
    """Truncations and byte flips of every format: success or a VigprocError, never anything else."""
    rng = np.random.default_rng(10)
    pix = rng.integers(0, 256, (24, 24, 3)).astype(np.uint8)
    seeds = [
        oiio_write(tmp_path / "s.png", pix, "uint8"),
        oiio_write(tmp_path / "s.jpg", pix, "uint8"),
        oiio_write(tmp_path / "s.tif", pix.astype(np.uint16) * 257, "uint16"),
        oiio_write(tmp_path / "s.exr", pix / np.float32(255), "half"),
    ]
    n = 0
    for seed in seeds:
        data = seed.read_bytes()
        variants = [data[:k] for k in (1, 4, 8, 16, len(data) // 3, len(data) - 1)]
        for _ in range(6):
            b = bytearray(data)
            for pos in rng.integers(0, len(b), 8):
                b[pos] ^= 0xFF
            variants.append(bytes(b))
        for i, v in enumerate(variants):
            p = tmp_path / f"fuzz{n}{seed.suffix}"
            n += 1
            p.write_bytes(v)
            try:
                img, _ = read_image(p)
            except VigprocError as exc:
                assert p.name in str(exc)
            else:
                assert img.dtype == np.float32


# --------------------------------------------------------------------------- #
# file names and input immutability
# --------------------------------------------------------------------------- #

WEIRD_NAMES = ["with space.png", "quote'single.png", 'quote"double.png', "new\nline.png", "ünïcødé 日本.png", "-dash.png"]


@pytest.mark.parametrize("name", WEIRD_NAMES)
def test_weird_file_names(tmp_path: Path, name: str) -> None:
    codes = gradient_codes(8, 8)
    src = oiio_write(tmp_path / "plain.png", codes.astype(np.uint8), "uint8")
    p = tmp_path / name
    p.write_bytes(src.read_bytes())
    img, info = read_image(p)
    assert info.path == str(p)
    np.testing.assert_allclose(img, srgb_to_linear(codes / 255.0), atol=1e-6)
    # str and Path both accepted; writing to such a name works too
    out = tmp_path / ("out " + name.replace(".png", ".tif"))
    write_image(out, img)
    back, _ = read_image(str(out))
    np.testing.assert_allclose(back, img, atol=1 / 65535)


def test_weird_name_error_message_is_one_line(tmp_path: Path) -> None:
    p = tmp_path / "bad\nname.png"
    p.write_text("nope")
    with pytest.raises(UnsupportedFormatError) as ei:
        read_image(p)
    assert "\n" not in str(ei.value) and "bad\\nname.png" in str(ei.value)


def test_input_bytes_unchanged(tmp_path: Path, good_png: Path, good_jpg: Path) -> None:
    files = [
        good_png,
        good_jpg,
        oiio_write(tmp_path / "t.tif", np.ones((8, 8, 3), np.uint16), "uint16"),
        oiio_write(tmp_path / "e.exr", np.ones((8, 8, 3), np.float32), "half"),
    ]
    raw = RAW_DIR / DECODABLE_RAWS[0]
    if raw.exists():
        files.append(raw)
    for f in files:
        before = (sha256(f), f.stat().st_mtime_ns, f.stat().st_size)
        read_image(f)
        read_image(f, transfer="linear")
        after = (sha256(f), f.stat().st_mtime_ns, f.stat().st_size)
        assert before == after, f
    # nothing else appeared next to the inputs
    assert sorted(x.name for x in tmp_path.iterdir()) == sorted(["good.png", "good.jpg", "t.tif", "e.exr"])


# --------------------------------------------------------------------------- #
# writing
# --------------------------------------------------------------------------- #


def _linear_test_image(h: int = 24, w: int = 40) -> np.ndarray:
    rng = np.random.default_rng(11)
    img = rng.random((h, w, 3)).astype(np.float32)
    img[0, :3] = [0.0, 1.0, 0.5]
    return img


@pytest.mark.parametrize(
    "name,depth,transfer,atol",
    [
        ("a.tif", "uint16", "linear", 0.5 / 65535 + 1e-7),
        ("a.tif", "uint16", "srgb", 1e-4),
        ("a.tif", "uint8", "linear", 0.5 / 255 + 1e-7),
        ("a.tif", "float", "linear", 0.0),
        ("a.png", "uint16", "srgb", 1e-4),
        ("a.png", "uint16", "linear", 0.5 / 65535 + 1e-7),
        ("a.png", "uint8", "srgb", 0.01),
        ("a.exr", "half", "linear", None),
        ("a.exr", "float", "linear", 0.0),
    ],
)
def test_write_read_roundtrip(tmp_path: Path, name: str, depth: str, transfer: str, atol: float | None) -> None:
    img = _linear_test_image()
    p = tmp_path / name
    write_image(p, img, bit_depth=depth, transfer=transfer)
    back, info = read_image(p)
    assert info.transfer == transfer and info.bit_depth == depth
    if atol is None:
        np.testing.assert_array_equal(back, img.astype(np.float16).astype(np.float32))
    elif atol == 0.0:
        np.testing.assert_array_equal(back, img)
    else:
        np.testing.assert_allclose(back, img, atol=atol, rtol=0)
    assert [x.name for x in tmp_path.iterdir()] == [name]


def test_write_srgb_png8_stores_encoded_codes(tmp_path: Path) -> None:
    lin = np.array([[0.0, 0.214041140482232, 1.0]], np.float32)
    p = tmp_path / "g.png"
    write_image(p, lin, bit_depth="uint8", transfer="srgb")
    inp = oiio.ImageInput.open(str(p))
    codes = inp.read_image("uint8").reshape(-1)
    inp.close()
    assert codes.tolist() == [0, 128, 255]  # 0.5 * 255 = 127.5 -> 128


def test_write_grayscale_clips_and_defaults(tmp_path: Path) -> None:
    g = np.linspace(-0.5, 1.5, 64, dtype=np.float32).reshape(8, 8)
    write_image(tmp_path / "g.png", g)  # default uint16 linear
    back, info = read_image(tmp_path / "g.png")
    assert back.shape == (8, 8) and info.bit_depth == "uint16" and info.transfer == "linear"
    np.testing.assert_allclose(back, np.clip(g, 0, 1), atol=1e-5)
    write_image(tmp_path / "g.exr", g[..., None])  # HxWx1 accepted, default half
    back, info = read_image(tmp_path / "g.exr")
    assert back.shape == (8, 8) and info.bit_depth == "half"
    np.testing.assert_array_equal(back, g.astype(np.float16).astype(np.float32))  # no clipping for float
    write_image(tmp_path / "noext", g, format="tiff")
    assert read_image(tmp_path / "noext")[1].format == "tiff"


def test_atomic_write_replaces_and_leaves_no_temp(tmp_path: Path) -> None:
    p = tmp_path / "out.tif"
    write_image(p, np.zeros((4, 4, 3), np.float32))
    write_image(p, np.ones((4, 4, 3), np.float32))
    assert [x.name for x in tmp_path.iterdir()] == ["out.tif"]
    np.testing.assert_allclose(read_image(p)[0], 1.0)
    umask = os.umask(0)
    os.umask(umask)
    assert stat.S_IMODE(p.stat().st_mode) == 0o666 & ~umask  # not mkstemp's 0600


def test_failed_replace_keeps_old_file_and_cleans_up(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    p = tmp_path / "keep.exr"
    write_image(p, np.full((4, 4, 3), 0.25, np.float32))
    before = sha256(p)

    def boom(src: str, dst: str) -> None:
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(os, "replace", boom)
    with pytest.raises(ImageWriteError, match="No space") as ei:
        write_image(p, np.full((4, 4, 3), 0.75, np.float32))
    assert_names_file(ei, p)
    assert sha256(p) == before
    assert [x.name for x in tmp_path.iterdir()] == ["keep.exr"]


def test_write_errors(tmp_path: Path) -> None:
    img = np.zeros((4, 4, 3), np.float32)
    bad_dir = tmp_path / "no" / "such" / "dir" / "x.tif"
    with pytest.raises(ImageWriteError) as ei:
        write_image(bad_dir, img)
    assert_names_file(ei, bad_dir)

    target_dir = tmp_path / "isdir.tif"
    target_dir.mkdir()
    with pytest.raises(ImageWriteError) as ei:
        write_image(target_dir, img)
    assert_names_file(ei, target_dir)
    assert [x.name for x in tmp_path.iterdir()] == ["isdir.tif"]
    assert list(target_dir.iterdir()) == []

    for kwargs in ({"bit_depth": "half"}, {"bit_depth": "float", "transfer": "srgb"}, {"transfer": "gamma9"}):
        with pytest.raises(ImageWriteError):
            write_image(tmp_path / "x.png", img, **kwargs)
    with pytest.raises(ImageWriteError, match="extension"):
        write_image(tmp_path / "x.jpg2", img)
    with pytest.raises(ImageWriteError):
        write_image(tmp_path / "x.exr", img, bit_depth="uint16")
    with pytest.raises(InvalidImageError):
        write_image(tmp_path / "x.tif", np.zeros((4, 4, 2)))
    with pytest.raises(InvalidImageError):
        write_image(tmp_path / "x.tif", np.zeros((0, 4)))
    nan = img.copy()
    nan[0, 0, 0] = np.nan
    with pytest.raises(InvalidImageError, match="NaN"):
        write_image(tmp_path / "x.tif", nan)
    assert not any(x.name.startswith(".x.") for x in tmp_path.iterdir())


# --------------------------------------------------------------------------- #
# RAW
# --------------------------------------------------------------------------- #


def _decodable_raws() -> list[Path]:
    return [RAW_DIR / r for r in DECODABLE_RAWS if (RAW_DIR / r).is_file()]


needs_raw = pytest.mark.skipif(
    not _decodable_raws(),
    reason=f"no decodable RAW files under {RAW_DIR} (see its README.md / files.csv)",
)


@needs_raw
@pytest.mark.parametrize("path", _decodable_raws() or [None], ids=lambda p: p and p.name)
def test_raw_full_and_half_size(path: Path) -> None:
    import rawpy

    full, info = read_image(path)
    half, hinfo = read_image(path, raw_half_size=True)
    assert (info.format, info.transfer, info.channels, info.colorspace) == ("raw", "linear", 3, None)
    assert full.dtype == np.float32 and full.ndim == 3 and full.shape[2] == 3
    assert (info.height, info.width) == full.shape[:2]
    assert 0.0 <= full.min() and full.max() <= 1.0
    assert abs(half.shape[0] - full.shape[0] / 2) <= 1 and abs(half.shape[1] - full.shape[1] / 2) <= 1
    assert (hinfo.height, hinfo.width) == half.shape[:2]
    # same exposure scaling at both sizes
    assert half.mean() == pytest.approx(full.mean(), rel=0.02)
    assert 0.005 < full.mean() < 0.9

    # Linearity: tile means of the output follow black-subtracted raw CFA tile
    # means with a log-log slope of 1 (a gamma-encoded output gives ~0.5-0.8).
    with rawpy.imread(str(path)) as r:
        cfa = r.raw_image_visible.astype(np.float64)
        cfa -= np.asarray(r.black_level_per_channel, float)[r.raw_colors_visible]
    h, w = full.shape[:2]
    t = 16
    cfa = cfa[: h // t * t, : w // t * t]
    out = full[: h // t * t, : w // t * t].astype(np.float64).sum(-1)
    cfa_t = cfa.reshape(h // t, t, w // t, t).mean(axis=(1, 3)).ravel()
    out_t = out.reshape(h // t, t, w // t, t).mean(axis=(1, 3)).ravel()
    ok = (out_t > 0.01) & (out_t < 2.5) & (cfa_t > 0)
    assert ok.sum() > 100
    slope = np.polyfit(np.log(cfa_t[ok]), np.log(out_t[ok]), 1)[0]
    assert 0.93 < slope < 1.07, slope


@needs_raw
def test_raw_with_weird_name_and_unchanged(tmp_path: Path) -> None:
    src = _decodable_raws()[0]
    p = tmp_path / f"ké 'x\"\n{src.name}"
    p.write_bytes(src.read_bytes())
    before = sha256(p)
    img, info = read_image(p, raw_half_size=True)
    assert info.format == "raw" and img.ndim == 3
    assert sha256(p) == before
    # RAW content behind a misleading extension is still found by content
    liar = tmp_path / "liar.jpg"
    liar.write_bytes(src.read_bytes())
    assert read_image(liar, raw_half_size=True)[1].format == "raw"


def test_raw_stubs_and_truncated_raw_raise_typed_errors(tmp_path: Path) -> None:
    stubs = sorted((RAW_DIR / "exiftool-stubs").glob("*")) if RAW_DIR.exists() else []
    if not stubs:
        pytest.skip(f"{RAW_DIR}/exiftool-stubs not available")
    for stub in stubs:  # real maker metadata, image data stripped
        with pytest.raises(ImageReadError) as ei:
            read_image(stub)
        assert_names_file(ei, stub)
    raws = _decodable_raws()
    if raws:
        data = raws[0].read_bytes()
        p = tmp_path / ("cut" + raws[0].suffix)
        p.write_bytes(data[: len(data) // 50])
        with pytest.raises(ImageReadError) as ei:
            read_image(p)
        assert_names_file(ei, p)


def _tiff_with_subifd(path: Path, w: int = 24, h: int = 16) -> Path:
    """A little-endian TIFF laid out like a NEF cut short: IFD0 an 8-bit RGB preview whose
    SubIFDs tag (330) points past the end of the file, where the sensor data was."""
    import struct

    pixels = (bytes(range(256)) * (w * h * 3 // 256 + 1))[: w * h * 3]
    tags = [(256, 3, 1, w), (257, 3, 1, h), (258, 3, 3, None), (259, 3, 1, 1), (262, 3, 1, 2),
            (273, 4, 1, None), (277, 3, 1, 3), (278, 3, 1, h), (279, 4, 1, len(pixels)), (330, 4, 1, 1 << 20)]
    bps = 8 + 2 + 12 * len(tags) + 4
    values = {258: bps, 273: bps + 6}
    ifd = struct.pack("<H", len(tags))
    for tag, typ, count, value in tags:
        value = values[tag] if value is None else value
        ifd += struct.pack("<HHI", tag, typ, count)
        ifd += struct.pack("<HH", value, 0) if typ == 3 and count == 1 else struct.pack("<I", value)
    path.write_bytes(b"II*\x00" + struct.pack("<I", 8) + ifd + struct.pack("<I", 0)
                     + struct.pack("<HHH", 8, 8, 8) + pixels)
    return path


def test_undecodable_raw_is_not_read_from_its_embedded_preview(tmp_path: Path) -> None:
    # laid out like a NEF, sensor data cut off: LibRaw cannot decode it, and OpenImageIO
    # would read its first image (the embedded preview), which is not the photograph
    p = _tiff_with_subifd(tmp_path / "DSC_0001.nef")
    as_tif = tmp_path / "same.tif"
    as_tif.write_bytes(p.read_bytes())
    assert read_image(as_tif)[1].width == 24  # the fixture is a readable TIFF
    with pytest.raises(UnsupportedFormatError, match="embedded preview is not used") as ei:
        read_image(p)
    assert_names_file(ei, p)


def test_non_utf8_file_name_is_read(tmp_path: Path, good_png: Path) -> None:
    """A name in bytes that are not UTF-8 (OpenImageIO takes UTF-8 only) is read through a
    UTF-8 alias: same pixels, the name as given in its info and in its errors."""
    raw_name = os.fsencode(tmp_path) + b"/bad\xffname.png"
    with open(raw_name, "wb") as fh:
        fh.write(good_png.read_bytes())
    img, info = read_image(os.fsdecode(raw_name))
    ref, _ = read_image(good_png)
    assert np.array_equal(img, ref) and info.path == os.fsdecode(raw_name)
    broken = os.fsencode(tmp_path) + b"/broken\xff.png"
    with open(broken, "wb") as fh:
        fh.write(good_png.read_bytes()[:60])
    with pytest.raises(ImageReadError) as ei:
        read_image(os.fsdecode(broken))
    assert repr(os.fsdecode(broken)) in str(ei.value) and "vigproc-name-" not in str(ei.value)
    with pytest.raises(ImageWriteError, match="UTF-8"):
        write_image(os.fsdecode(os.fsencode(tmp_path) + b"/out\xff.tif"), np.zeros((2, 2, 3)))


def test_exr_extra_channels_select_rgb(tmp_path: Path) -> None:
    data = np.zeros((4, 5, 5), np.float32)
    for c in range(5):
        data[..., c] = c + 1  # R=1 G=2 B=3 A=4 Z=5
    spec = oiio.ImageSpec(5, 4, 5, "float")
    spec.channelnames = ("R", "G", "B", "A", "Z")
    spec.alpha_channel = 3
    spec.z_channel = 4
    p = str(tmp_path / "multi.exr")
    out = oiio.ImageOutput.create(p)
    assert out.open(p, spec) and out.write_image(data) and out.close()
    img, info = read_image(p)
    assert img.shape == (4, 5, 3) and info.channels == 3
    np.testing.assert_array_equal(img[0, 0], [1.0, 2.0, 3.0])


def test_two_channels_are_grey_plus_extra_only_when_the_file_says_grey(tmp_path: Path) -> None:
    # A grey TIFF with an untagged extra sample (grey + alpha as many tools write it)
    ga = np.zeros((6, 4, 2), np.float32)
    ga[..., 0], ga[..., 1] = 0.25, 1.0
    img, info = read_image(oiio_write(tmp_path / "ga.tif", ga, "float"))
    assert img.shape == (6, 4) and info.channels == 1
    np.testing.assert_allclose(img, 0.25)

    # Two named channels that are neither grey nor RGB: refused, not read as the first
    spec = oiio.ImageSpec(4, 6, 2, "float")
    spec.channelnames = ("U", "V")
    p = str(tmp_path / "uv.exr")
    out = oiio.ImageOutput.create(p)
    assert out.open(p, spec) and out.write_image(ga) and out.close()
    with pytest.raises(UnsupportedFormatError, match="neither grey nor RGB"):
        read_image(p)


# --------------------------------------------------------------------------- #
# argument and range validation
# --------------------------------------------------------------------------- #


@pytest.mark.parametrize(
    ("name", "depth", "scale"),
    [
        ("h.exr", None, 1e6),  # default half: 65504 at most
        ("h.exr", "half", -2e5),  # -1e5
        ("f.exr", "float", 1e39),  # float64 input beyond float32
        ("f.tif", "float", -1e300),
    ],
)
def test_write_refuses_values_a_float_format_would_store_as_inf(
    tmp_path: Path, name: str, depth: str | None, scale: float
) -> None:
    img = np.full((4, 4, 3), 0.5) * scale  # float64, so 1e39 survives until the cast
    with pytest.raises(ImageWriteError, match="would be stored as Inf") as ei:
        write_image(tmp_path / name, img, bit_depth=depth)
    assert_names_file(ei, tmp_path / name)
    assert list(tmp_path.iterdir()) == []  # refused before any file was created


def test_write_half_takes_values_up_to_its_maximum(tmp_path: Path) -> None:
    img = np.array([[65504.0, -65504.0], [0.25, 0.0]], np.float32)
    write_image(tmp_path / "max.exr", img)
    np.testing.assert_array_equal(read_image(tmp_path / "max.exr")[0], img)
    big = np.full((2, 2), 1e6, np.float32)  # beyond half, fine as float
    write_image(tmp_path / "big.exr", big, bit_depth="float")
    np.testing.assert_array_equal(read_image(tmp_path / "big.exr")[0], big)


@pytest.mark.parametrize("bad", [np.nan, np.inf, -np.inf])
@pytest.mark.parametrize("depth", ["half", "float"])
def test_write_refuses_nan_and_inf_for_float_outputs(tmp_path: Path, bad: float, depth: str) -> None:
    img = np.zeros((4, 4, 3), np.float32)
    img[1, 2, 0] = bad
    with pytest.raises(InvalidImageError, match="NaN/Inf"):
        write_image(tmp_path / "x.exr", img, bit_depth=depth)
    assert list(tmp_path.iterdir()) == []


def test_integer_output_warns_when_it_clips_much_above_white(tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    codes = gradient_codes(top=65535).astype(np.uint16)  # integer codes, not [0, 1] floats
    with caplog.at_level("WARNING", logger="vigproc.io.images"):
        write_image(tmp_path / "codes.tif", codes)
    assert any("above 1.0" in r.getMessage() and "integer codes" in r.getMessage() for r in caplog.records)
    np.testing.assert_array_equal(read_image(tmp_path / "codes.tif")[0][codes > 0], 1.0)  # still clipped, as documented

    caplog.clear()
    few = np.full((10, 10), 0.5, np.float32)
    few[0, 0] = 3.0  # 1 % exactly: a highlight, not a unit mistake
    with caplog.at_level("WARNING", logger="vigproc.io.images"):
        write_image(tmp_path / "few.png", few)
    assert not caplog.records


@pytest.mark.parametrize(
    "kwargs",
    [{"transfer": "bogus"}, {"transfer": None}, {"max_pixels": None}, {"max_pixels": "many"},
     {"max_pixels": 0}, {"max_pixels": -5}, {"max_pixels": float("nan")}, {"max_pixels": True}],
)
def test_read_bad_arguments_are_typed_errors(good_png: Path, kwargs: dict) -> None:
    with pytest.raises(InvalidImageError) as ei:
        read_image(good_png, **kwargs)
    assert isinstance(ei.value, ValueError)  # still a ValueError for callers catching that
    assert next(iter(kwargs)) in str(ei.value)


@pytest.mark.parametrize("path", [None, 5, 1.5, ["a.png"]])
def test_non_path_arguments_are_typed_errors(tmp_path: Path, path: object) -> None:
    with pytest.raises(ImageReadError, match="path must be"):
        read_image(path)  # type: ignore[arg-type]
    with pytest.raises(ImageWriteError, match="path must be"):
        write_image(path, np.zeros((2, 2, 3)))  # type: ignore[arg-type]
    assert list(tmp_path.iterdir()) == []


def test_libraw_complaints_go_into_the_error_not_raw_stderr(tmp_path: Path) -> None:
    """LibRaw prints 'Unexpected end of file' straight to the C stderr; a command's stderr
    must hold one line per failed file (and --log-json one object per line)."""
    import subprocess
    import sys

    kdc = RAW_DIR / "rawpy" / "RAW_KODAK_DC50.KDC"
    if not kdc.exists():
        pytest.skip(f"{kdc} not available")
    data = kdc.read_bytes()
    cut = tmp_path / "cut.kdc"
    cut.write_bytes(data[: len(data) // 2])  # LibRaw decodes until the data ends, and says so
    r = subprocess.run([sys.executable, "-m", "vigproc.frontends.cli", "correct", str(cut), "-o", str(tmp_path / "o")],
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 4  # its only file unreadable
    lines = r.stderr.splitlines()
    assert len(lines) == 1 and lines[0].startswith("vigproc: ") and "cut.kdc" in lines[0], lines
    assert "LibRaw said: Unexpected end of file" in lines[0]
    # in-process too: the error carries LibRaw's words, and fd 2 is ours again afterwards
    with pytest.raises(ImageReadError, match="Unexpected end of file"):
        read_image(cut)
    os.write(2, b"")  # still a valid descriptor


def test_libpng_complaints_stay_off_stderr(tmp_path: Path) -> None:
    """libpng printed 'libpng error: IDAT: Read error: hit end of file in png reader' straight
    to the C stderr, beside vigproc's own line (a new user's truncated PNG): one line per
    failed file, whatever the decoder says on its own."""
    import subprocess
    import sys

    good = tmp_path / "good.png"
    rng = np.random.default_rng(1)
    write_image(good, rng.uniform(0.05, 1.0, (64, 96, 3)).astype(np.float32), bit_depth="uint8", transfer="srgb")
    data = good.read_bytes()
    cut = tmp_path / "cut.png"
    cut.write_bytes(data[: len(data) // 2])
    r = subprocess.run([sys.executable, "-m", "vigproc.frontends.cli", "estimate", str(cut)],
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 4
    lines = r.stderr.splitlines()
    assert len(lines) == 1 and lines[0].startswith("vigproc: ") and "cut.png" in lines[0], lines
    with pytest.raises(ImageReadError, match="PNG"):
        read_image(cut)
    os.write(2, b"")  # fd 2 is ours again
    assert read_image(good)[0].shape == (64, 96, 3)


def test_linear_tiffs_carry_a_linear_srgb_icc_profile(tmp_path: Path) -> None:
    """Editors take a TIFF without a profile for sRGB-encoded and show a linear one far
    too dark: a linear RGB TIFF says what it holds (sRGB primaries, gamma 1.0)."""
    import shutil
    import struct
    import subprocess

    from vigproc.io.icc import DESCRIPTION, linear_srgb_profile

    icc = linear_srgb_profile()
    assert struct.unpack(">I", icc[:4])[0] == len(icc) and icc[36:40] == b"acsp" and icc[12:20] == b"mntrRGB "
    n = struct.unpack(">I", icc[128:132])[0]
    tags = {icc[132 + 12 * i:136 + 12 * i]: struct.unpack(">II", icc[136 + 12 * i:144 + 12 * i]) for i in range(n)}
    assert {b"desc", b"wtpt", b"rXYZ", b"gXYZ", b"bXYZ", b"rTRC", b"gTRC", b"bTRC", b"cprt"} <= set(tags)
    for sig in (b"rTRC", b"gTRC", b"bTRC"):  # identity curves: gamma 1.0
        off, size = tags[sig]
        assert icc[off:off + 4] == b"curv" and icc[off + 8:off + 14] == struct.pack(">IH", 1, 0x0100)
        assert off % 4 == 0 and off + size <= len(icc)
    rgb = np.random.default_rng(0).uniform(0, 1, (16, 24, 3)).astype(np.float32)
    write_image(tmp_path / "lin.tif", rgb, bit_depth="uint16")
    write_image(tmp_path / "grey.tif", rgb[..., 0], bit_depth="uint16")
    write_image(tmp_path / "srgb.tif", rgb, bit_depth="uint16", transfer="srgb")
    back, info = read_image(tmp_path / "lin.tif")
    assert info.transfer == "linear" and np.allclose(back, rgb, atol=1e-4)  # the profile changes no reading
    if shutil.which("exiftool"):
        def desc(p):
            return subprocess.run(["exiftool", "-s3", "-ProfileDescription", str(p)], capture_output=True,
                                  text=True).stdout.strip()
        assert desc(tmp_path / "lin.tif") == DESCRIPTION
        assert desc(tmp_path / "grey.tif") == "" and desc(tmp_path / "srgb.tif") == ""


@pytest.mark.parametrize("depth,tiled", [("uint8", False), ("uint16", False), ("float", False), ("uint16", True)])
def test_a_frame_read_in_bands_of_rows_is_the_frame(tmp_path, depth, tiled):
    """Files stored in scanlines are read in bands of READ_BAND rows (the binding would
    hold a whole-frame read twice): the same pixels as one read of the whole frame."""
    import OpenImageIO as oiio

    from vigproc.io import images

    h, w = 2 * images.READ_BAND + 37, 50
    rng = np.random.default_rng(0)
    data = rng.uniform(0.01, 1, (h, w, 3)).astype(np.float32)
    p = tmp_path / f"x{depth}{tiled}.tif"
    spec = oiio.ImageSpec(w, h, 3, depth)
    if tiled:
        spec.tile_width = spec.tile_height = 64
    out = oiio.ImageOutput.create(str(p))
    assert out.open(str(p), spec) and out.write_image(data)
    out.close()
    inp = oiio.ImageInput.open(str(p))
    whole = np.asarray(inp.read_image(0, 0, 0, 3, depth)).reshape(h, w, 3)
    inp.close()
    inp = oiio.ImageInput.open(str(p))
    banded = images._read_pixels(inp, inp.spec(), depth)
    inp.close()
    assert banded.dtype == whole.dtype and banded.shape == (h, w, 3)
    np.testing.assert_array_equal(banded, whole)
    img, _ = images.read_image(p, transfer="linear")
    assert img.shape == (h, w, 3)


def test_a_truncated_jpeg_read_in_bands_is_a_read_error(tmp_path):
    from vigproc.io import images

    p = tmp_path / "t.jpg"
    img = np.random.default_rng(1).uniform(0.1, 0.9, (3 * images.READ_BAND, 120, 3)).astype(np.float32)
    write_image(p, img, bit_depth="uint8", transfer="srgb")
    data = p.read_bytes()
    p.write_bytes(data[: len(data) // 2])
    with pytest.raises(ImageReadError):
        read_image(p)
