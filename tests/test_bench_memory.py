"""``vigproc bench memory`` reads a process's own peak resident set (not the fork's)."""

from __future__ import annotations

import os
import sys

import pytest

from benchmarks.memory import cli_code, peak_of
from vigproc.errors import VigprocError

pytestmark = pytest.mark.skipif(not os.path.exists("/proc/self/status"), reason="needs Linux's /proc")


def test_the_peak_is_the_processs_own_and_sees_a_large_buffer():
    big = bytearray(300_000_000)  # the bench's own memory: not the child's (ru_maxrss would inherit it)
    small = peak_of("x = 1", "small")
    touched = peak_of("import numpy as np\na = np.ones(200_000_000, np.uint8)\ndel a", "200 MB")
    del big
    assert small.peak_mb < 150
    assert 190 < touched.peak_mb - small.peak_mb < 260


def test_a_failing_command_is_an_error(tmp_path):
    with pytest.raises(VigprocError, match=r"exited [1-9].*file not found"):
        peak_of(cli_code(["correct", "-o", str(tmp_path), "--", str(tmp_path / "missing.jpg")]) + "\n", "missing",
                env={**os.environ, "PYTHONPATH": os.pathsep.join(sys.path)})
