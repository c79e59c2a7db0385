"""I/O benchmark: time to read a frame per format, and EXIF per file in batch.

Each decode is printed next to the time to read the same file's bytes from disk
(the floor any decoder pays, measured in the same run).
"""

from __future__ import annotations

import math
import os
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Sequence

import numpy as np

from vigproc.errors import VigprocError
from vigproc.io.exif import ExifReader, read_lens_key
from vigproc.io.images import read_image, write_image

#: (label, file suffix, write_image bit depth) of the synthetic frames.
FORMATS = (
    ("TIFF 16-bit", ".tif", "uint16"),
    ("TIFF float", ".tif", "float"),
    ("EXR half", ".exr", "half"),
    ("EXR float", ".exr", "float"),
    ("PNG 16-bit", ".png", "uint16"),
)


@dataclass
class ReadTiming:
    label: str
    path: str
    megapixels: float
    megabytes: float
    read_ms: float
    bytes_ms: float


def _best(fn: Callable[[], object], repeat: int) -> float:
    best = float("inf")
    for _ in range(max(1, repeat)):
        t0 = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t0)
    return 1000.0 * best


def time_file(label: str, path: Path, repeat: int, **read_kw) -> ReadTiming:
    img, _ = read_image(path, **read_kw)
    mp = img.shape[0] * img.shape[1] / 1e6
    del img
    return ReadTiming(
        label=label, path=str(path), megapixels=mp, megabytes=path.stat().st_size / 1e6,
        read_ms=_best(lambda: read_image(path, **read_kw), repeat),
        bytes_ms=_best(path.read_bytes, repeat),
    )


def synthetic_frame(height: int, width: int, seed: int = 0) -> np.ndarray:
    """A smooth-plus-noise linear RGB frame in [0, 1] (compresses like a photo, not like zeros)."""
    rng = np.random.default_rng(seed)
    y = np.linspace(0, 1, height, dtype=np.float32)[:, None, None]
    x = np.linspace(0, 1, width, dtype=np.float32)[None, :, None]
    base = 0.25 + 0.2 * np.sin(6 * x + 3 * y + np.array([0, 1, 2], dtype=np.float32))
    return np.clip(base + rng.normal(0, 0.01, (height, width, 3)).astype(np.float32), 0, 1)


def bench_formats(height: int, width: int, repeat: int, workdir: Path | None = None) -> list[ReadTiming]:
    """Write one synthetic frame in each of :data:`FORMATS` and time reading it back."""
    out = []
    with tempfile.TemporaryDirectory(dir=workdir) as tmp:
        frame = synthetic_frame(height, width)
        for label, suffix, depth in FORMATS:
            p = Path(tmp) / f"frame-{depth}{suffix}"
            write_image(p, frame, bit_depth=depth)
            out.append(time_file(label, p, repeat))
            p.unlink()
    return out


def bench_raw(paths: Sequence[Path], repeat: int) -> list[ReadTiming]:
    """Full-size and half-size (fast path) RAW reads of every decodable file."""
    out = []
    for p in paths:
        try:
            out.append(time_file(f"RAW {p.suffix.lower()} full", p, repeat))
            out.append(time_file(f"RAW {p.suffix.lower()} half", p, repeat, raw_half_size=True))
        except VigprocError:
            continue  # metadata-only stubs and unsupported files
    return out


def bench_exif(paths: Sequence[str | os.PathLike[str]], repeat: int = 1) -> dict[str, float]:
    """Time EXIF reading: one persistent process vs one process per file.

    Parameters
    ----------
    paths : sequence of path-like
    repeat : int
        Batch timings are the best of ``repeat`` runs.

    Returns
    -------
    dict
        ``n_files``; ``startup_ms`` (starting the process); ``batch_ms_per_file``
        (one :meth:`ExifReader.read_many` call, process already running);
        ``batch_total_ms_per_file`` (including the start-up);
        ``per_process_ms_per_file`` (:func:`read_lens_key` per file: a new
        process each); ``speedup`` (per-process / batch-including-start-up).
    """
    paths = list(paths)
    n = len(paths)
    if n == 0:
        raise ValueError("bench_exif needs at least one path")
    best_batch = math.inf
    startup = math.inf
    for _ in range(max(1, repeat)):
        t0 = time.perf_counter()
        with ExifReader() as reader:
            t1 = time.perf_counter()
            reader.read_many(paths)
            t2 = time.perf_counter()
        startup = min(startup, t1 - t0)
        best_batch = min(best_batch, t2 - t1)
    t0 = time.perf_counter()
    for p in paths:
        try:
            read_lens_key(p)
        except VigprocError:
            pass
    per_process = time.perf_counter() - t0
    batch_total = (startup + best_batch) / n
    return {
        "n_files": float(n),
        "startup_ms": startup * 1e3,
        "batch_ms_per_file": best_batch / n * 1e3,
        "batch_total_ms_per_file": batch_total * 1e3,
        "per_process_ms_per_file": per_process / n * 1e3,
        "speedup": (per_process / n) / batch_total if batch_total > 0 else math.inf,
    }
