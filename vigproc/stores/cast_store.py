"""Each profile's colour-cast evidence: one record per frame, pooled when read.

:meth:`vigproc.stores.profile_store.ProfileStore.learn` records a frame's per-quadrant
corner shifts (:func:`vigproc.core.cast_series.frame_record`) in the ``cast_frames``
table inside the transaction that pools its luminance, keyed by the frame's content id
like ``pooled_frames``, so a frame offered again adds nothing. The profile's cast is
pooled from the records when read (:func:`vigproc.core.cast_series.pool_cast`): a few
hundred bytes a frame, and a robust pool needs the frames, not only their sums.

References
----------
SQLite, "CREATE TABLE", https://www.sqlite.org/lang_createtable.html (WITHOUT ROWID not
used: the records are small and read by profile).
"""

from __future__ import annotations

import hashlib
import json
import logging
import sqlite3
from typing import Sequence

import numpy as np

from vigproc.core.cast_series import SeriesCast, SeriesSettings, check_record, pool_cast

logger = logging.getLogger(__name__)

#: Frames pooled into a profile's cast at most: those with the smallest content ids (a
#: sample that does not depend on arrival order), as the luminance pooling does.
MAX_CAST_FRAMES = 1000


def migration_cast_frames(con: sqlite3.Connection) -> None:
    """v15: each pooled frame's colour-cast record (JSON), by frame and profile."""
    con.execute(
        """
        CREATE TABLE IF NOT EXISTS cast_frames (
            frame      TEXT NOT NULL,
            profile_id INTEGER NOT NULL REFERENCES profiles (id) ON DELETE CASCADE,
            pooled     TEXT NOT NULL,
            record     TEXT NOT NULL,          -- {"shift": 4x2, "se": 4x2}, natural-log chroma
            PRIMARY KEY (frame, profile_id)
        )
        """
    )


def record_cast(con: sqlite3.Connection, profile_id: int, frame_id: str, record: dict, now: str) -> bool:
    """Store a frame's cast record once; True when it was new.

    Parameters
    ----------
    con : sqlite3.Connection
        Inside the caller's write transaction.
    profile_id : int
        The profile's row id.
    frame_id : str
        The frame's content id.
    record : dict
        :func:`vigproc.core.cast_series.frame_record`'s.
    now : str
        ISO time.

    Returns
    -------
    bool
        False when the frame was already recorded for this profile.

    Raises
    ------
    ValueError
        ``record`` is not a frame's cast record.
    """
    check_record(record)
    cur = con.execute("INSERT OR IGNORE INTO cast_frames (frame, profile_id, pooled, record) VALUES (?, ?, ?, ?)",
                      (frame_id, profile_id, now, json.dumps(record, separators=(",", ":"))))
    return cur.rowcount > 0


def record_imported_casts(con: sqlite3.Connection, profile_id: int, records: Sequence[dict], now: str) -> int:
    """Store the cast records a profile file carried (``cast.frames``); returns how many.

    They have no content id (the file does not name its frames): each is keyed
    ``import:N:DIGEST``, so records of equal value stay distinct and never collide with
    a frame's content id (a later frame of the same photograph is pooled again, as its
    luminance is: the import replaced the stored evidence).
    """
    n = 0
    for i, rec in enumerate(records[:MAX_CAST_FRAMES]):
        text = json.dumps(rec, separators=(",", ":"), sort_keys=True)
        frame_id = f"import:{i:06d}:{hashlib.sha256(text.encode()).hexdigest()[:16]}"
        n += record_cast(con, profile_id, frame_id, rec, now)
    return n


def _valid_records(con: sqlite3.Connection, profile_id: int) -> list[tuple[np.ndarray, np.ndarray]]:
    """A profile's cast records as arrays, those pooled first (see :data:`MAX_CAST_FRAMES`);
    a damaged record is skipped with a warning."""
    rows = con.execute("SELECT frame, record FROM cast_frames WHERE profile_id = ? ORDER BY frame LIMIT ?",
                       (profile_id, MAX_CAST_FRAMES)).fetchall()
    out = []
    for frame, rec in rows:
        try:
            out.append(check_record(json.loads(rec)))
        except (ValueError, TypeError) as exc:
            logger.warning("profile row %d: skipping frame %s's cast record: %s", profile_id, str(frame)[:16], exc)
    return out


def cast_records(con: sqlite3.Connection, profile_id: int) -> list[dict]:
    """A profile's cast records as a profile file carries them (``{"shift", "se"}``, no frame ids)."""
    return [{"shift": a.tolist(), "se": b.tolist()} for a, b in _valid_records(con, profile_id)]


def read_cast(con: sqlite3.Connection, profile_id: int,
              settings: SeriesSettings = SeriesSettings()) -> SeriesCast | None:
    """The cast pooled from a profile's frames; None when none was recorded.

    A damaged record is skipped with a warning (the rest still pool).
    """
    recs = _valid_records(con, profile_id)
    if not recs:
        return None
    return pool_cast(np.stack([a for a, _ in recs]), np.stack([b for _, b in recs]), settings)
