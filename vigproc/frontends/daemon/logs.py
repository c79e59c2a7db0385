"""The daemon's log lines (JSON lines or one escaped text line a record, each with its
``event`` field) and its word to systemd (``sd_notify``)."""

from __future__ import annotations

import contextlib
import json
import logging
import os
import socket
import sys
from datetime import datetime, timezone
from typing import Any

from vigproc.errors import one_line

log = logging.getLogger("vigproc.watch")


class JsonLogFormatter(logging.Formatter):
    """One JSON object per line: ts, level, logger, msg and the record's ``fields``."""

    def format(self, record: logging.LogRecord) -> str:
        d = {"ts": datetime.fromtimestamp(record.created, timezone.utc).isoformat(timespec="milliseconds")
             .replace("+00:00", "Z"),
             "level": record.levelname.lower(), "logger": record.name, "pid": record.process,
             "msg": record.getMessage()}
        d.update(getattr(record, "fields", None) or {})
        if record.exc_info:
            d["exc"] = self.formatException(record.exc_info)
        return json.dumps(d, default=str, ensure_ascii=True)


class TextLogFormatter(logging.Formatter):
    """``time level process: message``, one line per record: control characters of
    hostile file names are escaped, so a name cannot forge log lines."""

    def __init__(self) -> None:
        super().__init__("%(asctime)s %(levelname)s %(processName)s: %(message)s")

    def format(self, record: logging.LogRecord) -> str:
        return one_line(super().format(record))


def configure_logging(json_lines: bool, level: int) -> None:
    """Log to stderr: JSON lines or ``time level message``; replaces earlier handlers."""
    handler = logging.StreamHandler(sys.stderr)
    handler.setFormatter(JsonLogFormatter() if json_lines else TextLogFormatter())
    logging.basicConfig(level=level, handlers=[handler], force=True)


def _ev(event: str, **fields: Any) -> dict[str, Any]:
    return {"fields": {"event": event, **{k: v for k, v in fields.items() if v is not None}}}


# ------------------------------------------------------------------ systemd
def _sd_notify(message: str) -> None:
    """Tell systemd (Type=notify) how we are; no-op outside systemd."""
    addr = os.environ.get("NOTIFY_SOCKET")
    if not addr:
        return
    if addr.startswith("@"):
        addr = "\0" + addr[1:]
    with contextlib.suppress(OSError), socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM) as s:
        s.connect(addr)
        s.sendall(message.encode("utf-8", "replace"))


