"""What a profile store knew of a lens before the frames it holds: an imported profile.

A profile the store pools from frames is refitted from those frames' evidence
(:meth:`vigproc.stores.profile_store.ProfileStore.learn`). A profile brought in whole (a
``vigproc.profile`` file exported by another store, an Adobe LCP or lensfun
calibration with an uncertainty) has no evidence here: without a record of it, the first
frame learned onto it replaced it with that one frame's estimate. The store keeps the
import's parameters and covariance (normalised units, as :meth:`ProfileStore.put` got
them) in the ``profile_priors`` table; the pooled refit joins them to the frames'
(:func:`vigproc.core.pooling.pool_family`'s ``prior``). Replacing the profile (another
import) replaces the prior; deleting it deletes the prior.

References
----------
SQLite, "FOREIGN KEY constraints", https://www.sqlite.org/foreignkeys.html (ON DELETE
CASCADE).
"""

from __future__ import annotations

import json
import sqlite3

import numpy as np

from vigproc.core.normalised import N_PARAMS


def migration_profile_priors(con: sqlite3.Connection) -> None:
    """v16: each imported profile's parameters and covariance, the prior of the frames
    learned onto it."""
    con.execute(
        """
        CREATE TABLE IF NOT EXISTS profile_priors (
            profile_id INTEGER PRIMARY KEY REFERENCES profiles (id) ON DELETE CASCADE,
            theta      TEXT NOT NULL,          -- JSON, 12 normalised parameters
            covariance TEXT NOT NULL,          -- JSON, 12x12
            n_frames   INTEGER NOT NULL CHECK (n_frames >= 0),
            provenance TEXT NOT NULL,
            stored     TEXT NOT NULL
        )
        """
    )


def write_prior(con: sqlite3.Connection, profile_id: int, theta: np.ndarray, covariance: np.ndarray | None,
                n_frames: int, provenance: str, now: str) -> None:
    """Record (or, with no covariance, forget) the prior of the profile at ``profile_id``,
    inside the caller's write transaction. A profile without an uncertainty is no prior:
    the frames learned onto it supersede it."""
    if covariance is None:
        con.execute("DELETE FROM profile_priors WHERE profile_id = ?", (profile_id,))
        return
    con.execute(
        "INSERT INTO profile_priors (profile_id, theta, covariance, n_frames, provenance, stored) "
        "VALUES (?, ?, ?, ?, ?, ?) ON CONFLICT (profile_id) DO UPDATE SET theta = excluded.theta, "
        "covariance = excluded.covariance, n_frames = excluded.n_frames, provenance = excluded.provenance, "
        "stored = excluded.stored",
        (profile_id, json.dumps([float(v) for v in np.ravel(theta)]),
         json.dumps([float(v) for v in np.ravel(covariance)]), int(n_frames), str(provenance), now),
    )


def read_prior(con: sqlite3.Connection, profile_id: int) -> tuple[np.ndarray, np.ndarray, int] | None:
    """The prior of the profile at ``profile_id`` as (θ̃, covariance, frames it was
    pooled from); None without one, or when the row cannot be read (it then adds nothing)."""
    row = con.execute("SELECT theta, covariance, n_frames FROM profile_priors WHERE profile_id = ?",
                      (profile_id,)).fetchone()
    if row is None:
        return None
    try:
        theta = np.asarray(json.loads(row[0]), dtype=np.float64)
        cov = np.asarray(json.loads(row[1]), dtype=np.float64).reshape(N_PARAMS, N_PARAMS)
    except (ValueError, TypeError):
        return None
    if theta.shape != (N_PARAMS,) or not (np.all(np.isfinite(theta)) and np.all(np.isfinite(cov))):
        return None
    return theta, cov, int(row[2])
