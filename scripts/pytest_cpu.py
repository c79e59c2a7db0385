"""A pytest plugin that appends each test's wall and CPU seconds to the file $CPUREC_OUT (JSON lines).

CPU is the test process's own (``getrusage(RUSAGE_SELF)``) plus that of the children it waited
for (``RUSAGE_CHILDREN``: the CLI processes and daemons a test starts, with their workers), which
a loaded machine does not inflate as it does wall time.  Usage::

    CPUREC_OUT=cpu.jsonl PYTHONPATH=.:scripts python -m pytest -p no:xdist -p pytest_cpu tests/test_x.py
"""

from __future__ import annotations

import json
import os
import resource
import time

import pytest


def _cpu() -> tuple[float, float]:
    own, children = resource.getrusage(resource.RUSAGE_SELF), resource.getrusage(resource.RUSAGE_CHILDREN)
    return own.ru_utime + own.ru_stime, children.ru_utime + children.ru_stime


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_protocol(item, nextitem):
    t0, (s0, c0) = time.monotonic(), _cpu()
    yield
    s1, c1 = _cpu()
    with open(os.environ["CPUREC_OUT"], "a", encoding="utf-8") as fh:
        fh.write(json.dumps({"id": item.nodeid, "wall": round(time.monotonic() - t0, 3),
                             "self": round(s1 - s0, 3), "children": round(c1 - c0, 3)}) + "\n")
