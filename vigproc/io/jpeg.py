"""JPEG specifics: a JPEG's IJG quality, read from its quantisation table, and the default
quality of the JPEGs vigproc writes."""

from __future__ import annotations

import functools

import numpy as np

from vigproc.io.formats import PathLike

#: JPEG quality when the source's cannot be read (:func:`jpeg_quality`).
DEFAULT_JPEG_QUALITY = 95

# IJG's (libjpeg's) luminance quantisation table at quality 50 (ITU-T T.81, Annex K.1),
# in zig-zag order as a DQT segment stores it.
_IJG_LUMA_ZIGZAG = (
    16, 11, 12, 14, 12, 10, 16, 14, 13, 14, 18, 17, 16, 19, 24, 40, 26, 24, 22, 22, 24, 49, 35, 37,
    29, 40, 58, 51, 61, 60, 57, 51, 56, 55, 64, 72, 92, 78, 64, 68, 87, 69, 55, 56, 80, 109, 81, 87,
    95, 98, 103, 104, 103, 62, 77, 113, 121, 112, 100, 120, 92, 101, 103, 99,
)


def jpeg_quality(path: PathLike, max_bytes: int = 1 << 20) -> int | None:
    """The IJG quality (1–100) whose luminance table is closest to the JPEG's own.

    Reads the first DQT segment's table 0 (the first ``max_bytes`` bytes at most) and
    compares it with IJG's standard table scaled to every quality (libjpeg's
    ``jpeg_quality_scaling``). Encoders with their own tables (cameras) get the
    closest IJG quality.

    Returns
    -------
    int or None
        None when the file is not a JPEG or its table cannot be found.
    """
    try:
        with open(path, "rb") as fh:
            data = fh.read(max_bytes)
    except (OSError, TypeError, ValueError):
        return None
    return _jpeg_quality_of(data)


def _jpeg_quality_of(data: bytes) -> int | None:
    """:func:`jpeg_quality` of a JPEG's first bytes (None: not a JPEG, or no table in them)."""
    if not data.startswith(b"\xff\xd8"):
        return None
    i = 2
    table = None
    while i + 4 <= len(data) and data[i] == 0xFF:
        marker = data[i + 1]
        if marker in (0xD8, 0x01) or 0xD0 <= marker <= 0xD7:
            i += 2
            continue
        size = int.from_bytes(data[i + 2:i + 4], "big")
        if marker == 0xDB:  # DQT: [Pq/Tq][64 or 128 bytes]...
            seg = data[i + 4:i + 2 + size]
            j = 0
            while j < len(seg):
                pq, tq = seg[j] >> 4, seg[j] & 15
                n = 128 if pq else 64
                vals = seg[j + 1:j + 1 + n]
                if len(vals) < n:
                    break
                if tq == 0:
                    table = ([int.from_bytes(vals[k:k + 2], "big") for k in range(0, n, 2)] if pq
                             else list(vals))
                    break
                j += 1 + n
            if table is not None:
                break
        if marker == 0xDA:  # start of scan: no table before it
            break
        i += 2 + size
    if table is None or len(table) != 64:
        return None
    q_table = np.asarray(table, dtype=np.float64)
    err = np.sum(np.abs(_log_ijg_tables() - np.log(np.maximum(q_table, 1))), axis=1)
    return int(np.argmin(err)) + 1  # the first of equal errors: the lowest quality, as a loop finds it


@functools.lru_cache(maxsize=1)
def _log_ijg_tables() -> np.ndarray:
    """log of the IJG luminance table at each quality 1..100 (100×64, zig-zag order): one
    array for all qualities (a loop over them took 40 ms a file on a loaded machine)."""
    base = np.asarray(_IJG_LUMA_ZIGZAG, dtype=np.float64)
    q = np.arange(1, 101, dtype=np.float64)[:, None]
    scale = np.where(q < 50, 5000.0 / q, 200.0 - 2.0 * q)
    t = np.log(np.clip(np.floor((base * scale + 50.0) / 100.0), 1, 255))
    t.setflags(write=False)
    return t
