"""``vigproc bench memory``: the peak memory of one worker on a 24 MP frame.

A frame of ``width`` × ``height`` (6000×4000 by default) is written as a JPEG and a
16-bit TIFF; each is run through ``vigproc correct`` (the per-frame path of a
``watch`` or ``batch`` worker, a :class:`~vigproc.pipeline.processor.Processor` in
correct mode) as a new process, which writes its own peak resident set (``VmHWM`` of
``/proc/self/status``, Linux) as it exits.  (Not ``ru_maxrss`` from ``wait4``: it
keeps the high-water mark of the forked copy of the parent, the bench itself, across
``exec``.)  The same is read of a process that
only imports what such a worker imports: the difference is what the frame costs.
The sizes are also stated in frames: one 8-bit RGB copy of the frame (width × height
× 3 bytes) is the least any decode holds.
"""

from __future__ import annotations

import os
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

import numpy as np

from benchmarks import child_code
from vigproc.errors import VigprocError

#: What a worker imports before its first frame (the baseline).
_IMPORTS = ("import vigproc.pipeline.processor, vigproc.core.correct, vigproc.core.estimate, "
            "vigproc.frontends.cli, OpenImageIO")


@dataclass(frozen=True)
class MemoryRun:
    """One process's peak memory.

    Attributes
    ----------
    label : str
    peak_mb : float
        Peak resident set size (VmHWM), MB (10^6 bytes).
    seconds : float
        Wall-clock time of the process.
    """

    label: str
    peak_mb: float
    seconds: float


@dataclass
class MemoryResult:
    """What :func:`run_memory` measured (``vigproc bench memory --json``)."""

    width: int
    height: int
    baseline: MemoryRun
    runs: list[MemoryRun]

    @property
    def frame_mb(self) -> float:
        """One 8-bit RGB copy of the frame, MB."""
        return self.width * self.height * 3 / 1e6


def make_fixtures(folder: Path, width: int = 6000, height: int = 4000) -> dict[str, Path]:
    """A vignetted frame of ``width`` × ``height`` as a JPEG (quality 92) and a 16-bit TIFF.

    Returns
    -------
    dict
        ``{"jpeg": path, "tiff16": path}``.
    """
    from benchmarks.io import synthetic_frame
    from benchmarks.synthetic import table1_model
    from vigproc.io.images import write_image

    folder.mkdir(parents=True, exist_ok=True)
    frame = synthetic_frame(height, width)
    frame *= table1_model(1).rescale(width, height).field((height, width)).astype(np.float32)[..., None]
    out = {"jpeg": folder / "frame24.jpg", "tiff16": folder / "frame24.tif"}
    write_image(out["jpeg"], frame, bit_depth="uint8", transfer="srgb", quality=92)
    write_image(out["tiff16"], frame, bit_depth="uint16")
    return out


def _report_hwm(out: str) -> None:
    """Write this process's peak resident set (kB, ``VmHWM``) to ``out`` (at exit)."""
    with open("/proc/self/status", encoding="ascii") as fh:
        kb = next(int(ln.split()[1]) for ln in fh if ln.startswith("VmHWM:"))
    with open(out, "w", encoding="ascii") as fh:
        fh.write(str(kb))


def peak_of(code: str, label: str, *, env: dict[str, str] | None = None) -> MemoryRun:
    """Run the Python ``code`` in a new process; its peak resident set as it exits.

    Raises
    ------
    VigprocError
        The process failed, or this system has no ``/proc/self/status``.
    """
    if not os.path.exists("/proc/self/status"):
        raise VigprocError("bench memory needs Linux's /proc/self/status")
    with tempfile.TemporaryDirectory(prefix="vigproc-hwm-") as tmp:
        out = os.path.join(tmp, "hwm")
        wrapped = child_code(f"import atexit\nfrom benchmarks.memory import _report_hwm\n"
                             f"atexit.register(_report_hwm, {out!r})\n{code}")
        t0 = time.perf_counter()
        res = subprocess.run([sys.executable, "-c", wrapped], stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL,
                             stderr=subprocess.PIPE, env=env)
        seconds = time.perf_counter() - t0
        if res.returncode != 0 or not os.path.exists(out):
            tail = " / ".join(res.stderr.decode("utf-8", "replace").strip().splitlines()[-3:])
            raise VigprocError(f"bench memory: {label} exited {res.returncode}: {tail}")
        with open(out, encoding="ascii") as fh:
            kb = int(fh.read())
    return MemoryRun(label, kb * 1024 / 1e6, seconds)


def cli_code(args: Sequence[str]) -> str:
    """Python code that runs ``vigproc ARGS`` (the CLI's ``__main__``) in the process."""
    return (f"import runpy, sys\nsys.argv = ['vigproc', *{list(args)!r}]\n"
            "runpy.run_module('vigproc.frontends.cli', run_name='__main__')")


def run_memory(width: int = 6000, height: int = 4000, *, workdir: Path | None = None,
               formats: Sequence[str] = ("jpeg", "tiff16")) -> MemoryResult:
    """Peak memory of ``vigproc correct`` (``--unapplied copy``, its default output
    format) on each fixture, and of the imports alone.

    Returns
    -------
    MemoryResult
    """
    env = dict(os.environ)
    with tempfile.TemporaryDirectory(prefix="vigproc-memory-", dir=workdir) as tmp:
        root = Path(tmp)
        env.setdefault("VIGPROC_PROFILE_DB", str(root / "profiles.sqlite"))
        files = make_fixtures(root / "in", width, height)
        base = peak_of(_IMPORTS, "imports only", env=env)
        runs = []
        for fmt in formats:
            cmd = ["correct", "--unapplied", "copy", "-o", str(root / f"out-{fmt}"), "--", str(files[fmt])]
            runs.append(peak_of(cli_code(cmd), f"vigproc correct, {fmt} in", env=env))
    return MemoryResult(width, height, base, runs)


def format_result(r: MemoryResult) -> list[str]:
    """The printed table."""
    lines = [f"{r.width}x{r.height} ({r.width * r.height / 1e6:.0f} MP); one 8-bit RGB frame = {r.frame_mb:.0f} MB",
             f"{'process':<34}{'peak MB':>9}{'- imports':>11}{'frames':>8}{'seconds':>9}",
             f"{r.baseline.label:<34}{r.baseline.peak_mb:>9.0f}{'':>11}{'':>8}{r.baseline.seconds:>9.1f}"]
    for m in r.runs:
        extra = m.peak_mb - r.baseline.peak_mb
        lines.append(f"{m.label:<34}{m.peak_mb:>9.0f}{extra:>11.0f}{extra / r.frame_mb:>8.1f}{m.seconds:>9.1f}")
    return lines
