"""A progress bar for long interactive runs that keeps printed lines whole."""

from __future__ import annotations

import contextlib
import sys
from typing import Sequence


class _AboveTheBar:
    """A stream whose whole lines are written above a tqdm bar (tqdm.write), so printed
    results and log lines never land on the bar's own line."""

    def __init__(self, target) -> None:
        self.target, self._part = target, ""

    def write(self, text: str) -> int:
        from tqdm import tqdm

        self._part += text
        *lines, self._part = self._part.split("\n")
        for line in lines:
            tqdm.write(line, file=self.target)
        return len(text)

    def flush(self) -> None:
        self.target.flush()

    def isatty(self) -> bool:
        return self.target.isatty()


def _progress(items: Sequence, what: str):
    """A tqdm progress bar on stderr for long interactive runs; the plain items otherwise
    (pipes, logs and --json output stay clean). While the bar shows, whatever the loop
    prints or logs goes above it."""
    if len(items) < 2 or not sys.stderr.isatty():
        yield from items
        return
    from tqdm import tqdm
    from tqdm.contrib.logging import logging_redirect_tqdm

    err = sys.stderr
    with logging_redirect_tqdm(), contextlib.redirect_stdout(_AboveTheBar(sys.stdout)), \
            contextlib.redirect_stderr(_AboveTheBar(err)):
        yield from tqdm(items, desc=what, unit="file", leave=False, file=err)
