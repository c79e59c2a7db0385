"""The embedded SQLite profile store (:class:`ProfileStore`) and its migrations.

SQLite in WAL mode: readers never block the (single) writer and vice versa;
:meth:`ProfileStore.learn` is a read-modify-write inside ``BEGIN IMMEDIATE``, so
concurrent learners (daemon workers, CLI runs) serialise on the write lock and no
update is lost.  Every change is one transaction: the store is never half-written.
The revision of each trusted profile that correct runs apply (:meth:`ProfileStore.apply_revision`)
is kept here too, so every worker applies the same one.

Why one module over the house's 1000 lines: one class whose methods are each one transaction
of the same SQLite file, and its numbered migrations, which must stay beside it.

References
----------
SQLite, "Write-Ahead Logging", https://www.sqlite.org/wal.html and
"Isolation in SQLite", https://www.sqlite.org/isolation.html.
"""

from __future__ import annotations

import builtins
import hashlib
import json
import logging
import math
import numbers
import os
import sqlite3
import time
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any, Callable, Sequence

import numpy as np

from vigproc.core.cast_series import check_record
from vigproc.core.colour import ColourPool
from vigproc.core.gridfield import GridField
from vigproc.core.information import _Exact, _Welford, _check_covariance, _scaled_pinv, frame_information
from vigproc.core.lensfamily import profile_family
from vigproc.core.model import VignettingModel
from vigproc.core.normalised import FIELD_GRID, N_PARAMS, _field_and_jacobian, normalise
from vigproc.errors import ModelError, ProfileStoreError, VigprocError
from vigproc.io.exif import LensKey, unescape_key_part
from vigproc.stores.cast_store import (cast_records, migration_cast_frames, read_cast, record_cast,
                                      record_imported_casts)
from vigproc.stores.db import SQLiteFile
from vigproc.stores.profile import (
    Profile,
    Shots,
    _is_trusted,
    _profile_stats,
    _valid_theta,
    interpolate_profiles,
)
from vigproc.stores.profile_grid import GridPool, grid_from_column, grid_to_column, migration_grid
from vigproc.stores.profile_prior import migration_profile_priors, read_prior, write_prior
from vigproc.stores.profile_file import export_profile, profile_from_dict, profile_to_dict, read_profile_file
from vigproc.stores.profile_key import (
    DB_ENV,
    DEFAULT_TIMEOUT,
    MAX_NOTES,
    ProfileKey,
    _check_key,
    _focal_index,
    _focal_label,
    _now,
    aspect_label,
)

logger = logging.getLogger(__name__)

# --------------------------------------------------------------------------- #
# the store
# --------------------------------------------------------------------------- #


def default_db_path() -> Path:
    """``$VIGPROC_PROFILE_DB``, else ``<user data dir>/vigproc/profiles.sqlite`` (platformdirs)."""
    env = os.environ.get(DB_ENV, "").strip()
    if env:
        return Path(env).expanduser()
    import platformdirs

    return Path(platformdirs.user_data_dir("vigproc", appauthor=False)) / "profiles.sqlite"


_COLUMNS = (
    "lens_id", "focal_bin", "aperture_bin", "aspect", "theta", "covariance", "info_exact",
    "info_matrix", "info_vector", "n_frames", "n_scatter", "theta_mean", "theta_m2",
    "field_mean", "field_m2", "provenance", "created", "updated", "trusted",
    "field_sigma_ev", "cov_sigma_ev", "scatter_sigma_ev", "notes", "shots", "colour", "grid",
)


def _migration_1(con: sqlite3.Connection) -> None:
    """v1: the profiles table."""
    con.execute(
        """
        CREATE TABLE profiles (
            id               INTEGER PRIMARY KEY,
            lens_id          TEXT NOT NULL,
            focal_bin        TEXT NOT NULL,
            aperture_bin     TEXT NOT NULL,
            aspect           TEXT NOT NULL,
            theta            BLOB NOT NULL,          -- 12 float64 LE, normalised units
            covariance       BLOB,                   -- 144 float64 LE or NULL
            info_exact       TEXT,                   -- JSON exact sums of Λ (144) and η (12)
            info_matrix      BLOB,                   -- Λ rounded to float64 (for reading)
            info_vector      BLOB,                   -- η rounded to float64
            n_frames         INTEGER NOT NULL CHECK (n_frames >= 0),
            n_scatter        INTEGER NOT NULL DEFAULT 0 CHECK (n_scatter >= 0),
            theta_mean       BLOB,                   -- Welford state across frames
            theta_m2         BLOB,
            field_mean       BLOB,
            field_m2         BLOB,
            provenance       TEXT NOT NULL CHECK (provenance IN ('learned', 'lensfun', 'user')),
            created          TEXT NOT NULL,
            updated          TEXT NOT NULL,
            trusted          INTEGER NOT NULL CHECK (trusted IN (0, 1)),
            field_sigma_ev   REAL,
            cov_sigma_ev     REAL,
            scatter_sigma_ev REAL,
            notes            TEXT NOT NULL DEFAULT '',
            UNIQUE (lens_id, focal_bin, aperture_bin, aspect)
        )
        """
    )


def _migration_2(con: sqlite3.Connection) -> None:
    """v2: the frames pooled into each profile, by content id, so that a frame offered
    again (a restarted daemon, a resumed batch, the same file under another name) is
    not pooled twice.  Recorded in the same transaction as the profile update."""
    con.execute(
        """
        CREATE TABLE pooled_frames (
            frame      TEXT NOT NULL,
            profile_id INTEGER NOT NULL REFERENCES profiles (id) ON DELETE CASCADE,
            pooled     TEXT NOT NULL,
            PRIMARY KEY (frame, profile_id)
        )
        """
    )


def _migration_3(con: sqlite3.Connection) -> None:
    """v3: each pooled frame may keep its evidence for a refit of the profile
    (:func:`vigproc.core.robust.luminance_evidence`, ≈ 25 KB a frame)."""
    con.execute("ALTER TABLE pooled_frames ADD COLUMN evidence BLOB")


def _migration_4(con: sqlite3.Connection) -> None:
    """v4: each frame's centred fit (:func:`vigproc.core.pooling.centred_fit`) is kept with
    its evidence, so that pooling every frame of a profile costs no refit.  Frames
    stored by v3 get theirs the first time their profile is pooled."""
    con.execute("ALTER TABLE pooled_frames ADD COLUMN fit BLOB")


def _migration_5(con: sqlite3.Connection) -> None:
    """v5: each frame's lens-family fit (:func:`vigproc.core.pooling.frame_fit`), what a
    profile now pools; the v4 centred fits are no longer read.  Frames stored before
    get theirs from their evidence the first time their profile is pooled."""
    con.execute("ALTER TABLE pooled_frames ADD COLUMN family BLOB")


def _migration_6(con: sqlite3.Connection) -> None:
    """v6: the frames' lens-family fits are made again from their evidence the first
    time their profile is pooled: fits stored before weighed no pair by its colour and
    carried the σ scale of their day (:mod:`vigproc.core.family_fit` before store v6), and a
    profile must not pool fits of two kinds."""
    con.execute("UPDATE pooled_frames SET family = NULL")


def _migration_7(con: sqlite3.Connection) -> None:
    """v7: the frames' lens-family fits are made again from their evidence the first
    time their profile is pooled: a frame's fit for pooling now follows the gradients'
    mode more closely (:data:`vigproc.core.pooling.FRAME_SETTINGS` from v7 on), and a
    profile must not pool fits of two kinds."""
    con.execute("UPDATE pooled_frames SET family = NULL")


def _migration_8(con: sqlite3.Connection) -> None:
    """v8: the same again: a frame's fit for pooling weighs colour with the single-frame
    fit's chroma scale from v8 on (:data:`vigproc.core.pooling.FRAME_SETTINGS`), and
    the shipped scene scatter was measured for such fits."""
    con.execute("UPDATE pooled_frames SET family = NULL")


def _migration_9(con: sqlite3.Connection) -> None:
    """v9: the same again: a frame's fit for pooling reads each pair's chroma change as
    covariates from v9 on (:data:`vigproc.core.pooling.FRAME_SETTINGS`), and the
    shipped scene scatter was measured for such fits."""
    con.execute("UPDATE pooled_frames SET family = NULL")


def _migration_10(con: sqlite3.Connection) -> None:
    """v10: how each profile's frames were shot (:class:`Shots`: their real focal
    lengths, crop factor and names as EXIF spelt them), for ``profile list`` and a
    lensfun export; profiles learned before have none until their next frame."""
    # a store whose recorded version was set back (tests do) may have the column already
    if "shots" not in {r[1] for r in con.execute("PRAGMA table_info(profiles)")}:
        con.execute("ALTER TABLE profiles ADD COLUMN shots TEXT")


def _migration_11(con: sqlite3.Connection) -> None:
    """v11: each profile's pooled colour field (:class:`vigproc.core.colour.ColourPool`,
    JSON), NULL for the colourless."""
    if "colour" not in {r[1] for r in con.execute("PRAGMA table_info(profiles)")}:
        con.execute("ALTER TABLE profiles ADD COLUMN colour TEXT")


def _migration_12(con: sqlite3.Connection) -> None:
    """v12: the revision of each trusted profile that correct runs apply (learning as
    you go, :meth:`ProfileStore.apply_revision`), shared by every worker: the profile
    file's JSON, its frame count and an id (SHA-256 of that JSON, 16 hex digits)."""
    con.execute(
        """
        CREATE TABLE IF NOT EXISTS applied_profiles (
            lens_id      TEXT NOT NULL,
            focal_bin    TEXT NOT NULL,
            aperture_bin TEXT NOT NULL,
            aspect       TEXT NOT NULL,
            revision     TEXT NOT NULL,
            n_frames     INTEGER NOT NULL,
            profile      TEXT NOT NULL,          -- vigproc.profile/2 or /3 JSON
            applied      TEXT NOT NULL,          -- ISO time it became the applied revision
            PRIMARY KEY (lens_id, focal_bin, aperture_bin, aspect)
        )
        """
    )


def _migration_13(con: sqlite3.Connection) -> None:
    """v13: the series an applied revision corrects (learning as you go,
    :meth:`ProfileStore.series_revision`): the first and last frame times it has seen
    (seconds), their clock (``capture``: EXIF DateTimeOriginal; ``arrival``) and when
    its last frame arrived (seconds since the epoch)."""
    have = {r[1] for r in con.execute("PRAGMA table_info(applied_profiles)")}
    for col, kind in (("series_first", "REAL"), ("series_last", "REAL"), ("series_clock", "TEXT"),
                      ("series_seen", "REAL")):
        if col not in have:
            con.execute(f"ALTER TABLE applied_profiles ADD COLUMN {col} {kind}")


def _migration_17(con: sqlite3.Connection) -> None:
    """v17: the frames and cast records of a profile found by its id (the pooled refit,
    the cast report and a profile's delete read them by profile; their primary keys
    start with the frame)."""
    con.execute("CREATE INDEX IF NOT EXISTS pooled_frames_by_profile ON pooled_frames (profile_id, frame)")
    con.execute("CREATE INDEX IF NOT EXISTS cast_frames_by_profile ON cast_frames (profile_id, frame)")


#: Numbered migrations: MIGRATIONS[i] brings the schema from version i to i + 1.
#: Append a function for the next version; never edit a released one.
MIGRATIONS: tuple[Callable[[sqlite3.Connection], None], ...] = (_migration_1, _migration_2, _migration_3,
                                                                 _migration_4, _migration_5, _migration_6,
                                                                 _migration_7, _migration_8, _migration_9,
                                                                 _migration_10, _migration_11, _migration_12,
                                                                 _migration_13, migration_grid,
                                                                 migration_cast_frames, migration_profile_priors,
                                                                 _migration_17)
#: A profile is pooled from at most this many frames (:mod:`vigproc.core.pooling`): those
#: with the smallest frame ids (content hashes, so a random sample that does not
#: depend on the order frames arrive in).  Every frame refines the profile up to
#: there: measured on the profile protocol, 0.074 EV after 40 frames and 0.035 after
#: 100 (README, "Profile accuracy versus frames"); the pooling runs inside the
#: learning transaction, from the stored fits.
MAX_POOLED_FRAMES = 1000
#: Frames' fits kept in memory per store object.
_FIT_CACHE_SIZE = 4096
#: Schema version this code writes.
SCHEMA_VERSION = len(MIGRATIONS)


def _blob(a: np.ndarray | None) -> bytes | None:
    return None if a is None else np.ascontiguousarray(a, dtype="<f8").tobytes()


def _fit_blob(fit: Any, size: tuple[int, int]) -> bytes:
    """A frame's lens-family fit as stored: K, frame (w, h), pairs, coefficients (K),
    covariance (K×K)."""
    k = fit.coefficients.size
    return _blob(np.concatenate([[k, size[0], size[1], fit.pairs], fit.coefficients, fit.covariance.ravel()]))


def _fit_from_blob(b: Any) -> tuple[Any, tuple[int, int]]:
    """Inverse of :func:`_fit_blob`. Raises ValueError for a damaged value."""
    from vigproc.core.family_fit import FrameCoefficients

    if not isinstance(b, bytes) or len(b) < 32 or len(b) % 8:
        raise ValueError("column family is not a fit")
    a = np.frombuffer(b, dtype="<f8").astype(np.float64)
    k = int(a[0]) if np.isfinite(a[0]) and 1 <= a[0] <= 16 else 0
    if k == 0 or a.size != 4 + k + k * k or not np.all(np.isfinite(a)) or np.any(a[1:4] < 1) \
            or np.any(a[:4] != np.round(a[:4])):
        raise ValueError("column family holds non-finite values or impossible sizes")
    fit = FrameCoefficients(a[4:4 + k].copy(), a[4 + k:].reshape(k, k).copy(), int(a[3]))
    return fit, (int(a[1]), int(a[2]))


def _unblob(b: Any, shape: tuple[int, ...], name: str) -> np.ndarray | None:
    if b is None:
        return None
    n = int(np.prod(shape))
    if not isinstance(b, bytes) or len(b) != 8 * n:
        raise ValueError(f"column {name} has {len(b) if isinstance(b, bytes) else type(b).__name__} bytes, expected {8 * n}")
    return np.frombuffer(b, dtype="<f8").reshape(shape).astype(np.float64)


@dataclass(frozen=True)
class _Frame:
    """What one frame adds to a profile (:meth:`ProfileStore.learn`), checked.

    ``theta`` and ``field`` (normalised θ and its log2 field on the FIELD_GRID² grid)
    feed the Welford moments: the frame's lens-family fit when it has evidence, else
    its estimate; ``lam`` and ``eta`` are its exact information sums."""

    theta: np.ndarray
    field: np.ndarray
    lam: _Exact
    eta: _Exact
    frame_id: str | None
    evidence: bytes | None
    fit: Any
    size: tuple[int, int] | None
    shots: Shots | None
    colour: Any  # the estimate's colour field (VignettingModel.colour), pooled as a ColourPool
    grid: Any = None  # the frame's grid field (a flat frame's GridField), pooled as a GridPool


def _pool_frame(old: Profile | None, key: ProfileKey, frame: _Frame, notes: str | None, now: str) -> Profile:
    """The profile ``old`` (None: none yet) with ``frame`` pooled in information form
    (no database).

    If the pooled θ is not a valid model, the plain mean of the frames is used, else
    the previous θ, else the frame's own.

    Parameters
    ----------
    old : Profile or None
    key : ProfileKey
    frame : _Frame
        From :meth:`ProfileStore._learn_inputs`.
    notes : str or None
        Appended to the profile's notes.
    now : str
        The update's timestamp.

    Returns
    -------
    Profile
        Provenance "learned".
    """
    aspect = key.aspect_ratio
    theta_i, field_i = frame.theta, frame.field
    add_lam, add_eta = frame.lam, frame.eta
    evidence = frame.evidence
    extra = ""
    if old is None:
        exact, welford, n_frames = (add_lam, add_eta), _Welford.empty(), 1
        created, old_notes, prev_theta = now, "", None
    elif old._exact is None:
        # an import without uncertainty carries no information to pool with
        exact, welford, n_frames = (add_lam, add_eta), _Welford.empty(), 1
        created, old_notes, prev_theta = old.created, old.notes, None
        extra = f"learned frames superseded a {old.provenance} profile without uncertainty ({now})"
        logger.warning("profile %s: %s", key, extra)
    else:
        exact = (old._exact[0].add(add_lam), old._exact[1].add(add_eta))
        welford = old._welford if old._welford is not None else _Welford.empty()
        n_frames = old.n_frames + 1
        created, old_notes, prev_theta = old.created, old.notes, old.theta
        if old.provenance != "learned":
            extra = f"seeded from a {old.provenance} profile"
    welford = welford.add(theta_i, field_i)
    lam = exact[0].to_array().reshape(N_PARAMS, N_PARAMS)
    eta = exact[1].to_array()
    # an import's fixed parameters carry no information: the frames decide them
    cov = _scaled_pinv(lam, f"pooled information of {key}", allow_fixed=True)
    theta = cov @ eta
    if not _valid_theta(theta, aspect):
        # with evidence the pooled refit usually replaces θ: no need to alarm anyone
        say = logger.warning if evidence is None else logger.debug
        fallback = welford.theta_mean
        if _valid_theta(fallback, aspect):
            say("profile %s: pooled θ is not a valid model; using the plain mean of the frames", key)
            theta = fallback
        elif prev_theta is not None:
            say("profile %s: pooled θ is not a valid model; keeping the previous θ", key)
            theta = prev_theta
        else:
            theta = theta_i
    pooled, cov_sigma, scatter = _profile_stats(theta, cov, aspect, welford)
    shots = old.shots if old is not None and old._exact is not None else None
    if frame.shots is not None:
        shots = frame.shots if shots is None else shots.add(frame.shots)
    note_parts = [s for s in (old_notes, extra if extra and extra not in old_notes else "", notes or "") if s]
    colour = old.colour if old is not None else None
    if frame.colour is not None:
        mine = ColourPool.of(frame.colour)
        colour = mine if colour is None else colour.add(mine)
    grid = old.grid if old is not None else None
    if frame.grid is not None:
        mine_g = GridPool.of(frame.grid)
        grid = mine_g if grid is None else grid.add(mine_g)
    return Profile(
        key=key, theta=theta, covariance=cov, info_matrix=lam, info_vector=eta,
        n_frames=n_frames, provenance="learned", created=created, updated=now,
        trusted=_is_trusted(n_frames, pooled), field_sigma_ev=pooled, cov_sigma_ev=cov_sigma,
        scatter_sigma_ev=scatter, notes="\n".join(note_parts)[:MAX_NOTES], shots=shots, colour=colour,
        grid=grid, _exact=exact, _welford=welford,
    )


def _with_refit(profile: Profile, refit: tuple[np.ndarray, np.ndarray, float, int]) -> Profile:
    """``profile`` with θ, covariance and σ from the robust pooling of its frames' fits
    (:meth:`ProfileStore._pooled_refit`).

    The pooled σ is the robust centre's (:mod:`vigproc.core.pooling`), robust to the
    frames a scene fooled; the plain scatter of the frames is kept for reports."""
    r_theta, r_cov, r_sigma, _ = refit
    _, cov_sigma, scatter = _profile_stats(r_theta, r_cov, profile.key.aspect_ratio, profile._welford)
    return replace(profile, theta=r_theta, covariance=r_cov, field_sigma_ev=r_sigma,
                   cov_sigma_ev=cov_sigma, scatter_sigma_ev=scatter,
                   trusted=_is_trusted(profile.n_frames, r_sigma))


class ProfileStore(SQLiteFile):
    """SQLite store of lens profiles, safe for concurrent processes.

    Parameters
    ----------
    path : str or Path, optional
        Database file; default :func:`default_db_path` (``$VIGPROC_PROFILE_DB`` or
        the platform's user data folder).  Missing folders are created.
    timeout : float
        Seconds (finite, >= 0) to wait for another process's write lock before
        :class:`ProfileStoreError` (SQLite busy timeout).
    family : LensFamily, optional
        The lens family profiles pool in (:mod:`vigproc.core.pooling`); default the
        shipped one (:func:`vigproc.core.lensfamily.profile_family`).

    Notes
    -----
    ``journal_mode=WAL`` (readers and one writer proceed concurrently),
    ``synchronous=FULL`` (the WAL is fsynced at every commit, so a learned frame
    that was reported stored survives a power cut; the cost, one fsync per frame,
    is negligible next to estimating the frame; NORMAL would be corruption-safe
    too but could roll back the last commits), ``foreign_keys=ON``.  One store
    object per thread (sqlite3 connections are not shared between threads); each
    process opens its own.

    Raises
    ------
    ProfileStoreError
        When ``path`` is not a path or ``timeout`` not a number of seconds, or the
        file is not a (vigproc) database, is corrupt, is from a newer vigproc, or
        stays locked beyond ``timeout``.
    """

    error = ProfileStoreError
    what = "profile store"
    check_on_open = True
    recovery = ("move it aside (vigproc then starts an empty store there), restore a backup or re-import "
                "exported profiles with 'vigproc profile import FILE'; meanwhile '--profile estimate' or "
                "'--profile lensfun' correct without a store")

    #: :meth:`learn` takes a frame's colour-cast record (``cast``)
    records_casts = True

    def __init__(self, path: str | os.PathLike[str] | None = None, *, timeout: float = DEFAULT_TIMEOUT,
                 family: Any = None) -> None:
        # SHA-256 of a frame's evidence -> its lens-family fit: a long-lived learner fits each frame once
        self._fit_cache: dict[bytes, Any] = {}
        # profile row id -> (what its cast records were when pooled, the pooled cast)
        self._cast_cache: dict[int, tuple[tuple, Any]] = {}
        # the lens family profiles pool in (None: the shipped one); a benchmark passes
        # one without its test lenses
        self._family = family
        # Checked here: the base class would fail with TypeError/ValueError (or
        # OverflowError for an infinite timeout) from Path(), float() or SQLite.
        if path is not None:
            try:
                path = os.fspath(path)
            except TypeError:
                raise ProfileStoreError(
                    f"profile store path must be a str or os.PathLike, got {type(path).__name__}") from None
            path = os.fsdecode(path) if isinstance(path, bytes) else path
            if not path or "\0" in path:
                raise ProfileStoreError(f"profile store path {path!r} is empty or contains a NUL character")
        if (isinstance(timeout, bool) or not isinstance(timeout, numbers.Real)
                or not (math.isfinite(timeout) and timeout >= 0)):
            raise ProfileStoreError(f"timeout must be a finite number of seconds >= 0, got {timeout!r}")
        super().__init__(path if path is not None else default_db_path(), timeout=timeout)

    def _setup_schema(self) -> None:
        self._migrate()

    def _version(self) -> int | None:
        """Recorded schema version; None for an empty (new) database."""
        con = self.con
        # one statement = one snapshot: another process may be creating the schema right now
        names = {r[0] for r in con.execute("SELECT name FROM sqlite_master WHERE name NOT LIKE 'sqlite_%'")}
        if "schema_version" not in names:
            if names:
                raise ProfileStoreError(
                    f"profile store {self.path}: the database has tables but no schema_version: "
                    "not a vigproc profile store (refusing to modify it)"
                )
            return None
        v = con.execute("SELECT max(version) FROM schema_version").fetchone()[0]
        return int(v) if v is not None else 0

    def _migrate(self) -> None:
        """Bring the schema to :data:`SCHEMA_VERSION` (idempotent; safe when several
        processes open a new store at once: the version is re-read under the lock)."""
        current = self._version()
        if current is not None and current > SCHEMA_VERSION:
            raise ProfileStoreError(
                f"profile store {self.path} has schema v{current}, newer than this vigproc (v{SCHEMA_VERSION})"
            )
        if current == SCHEMA_VERSION:
            return
        with self._txn() as con:  # retried by the caller (_retry_busy)
            current = self._version()
            if current is None:
                con.execute(
                    "CREATE TABLE schema_version (version INTEGER PRIMARY KEY, applied TEXT NOT NULL)"
                )
                current = 0
            if current > SCHEMA_VERSION:
                raise ProfileStoreError(
                    f"profile store {self.path} has schema v{current}, newer than this vigproc (v{SCHEMA_VERSION})"
                )
            for version in range(current + 1, SCHEMA_VERSION + 1):
                MIGRATIONS[version - 1](con)
                con.execute("INSERT INTO schema_version (version, applied) VALUES (?, ?)", (version, _now()))
                logger.info("profile store %s: migrated to schema v%d", self.path, version)

    @property
    def schema_version(self) -> int:
        """Schema version recorded in the database."""
        with self._errors("reading the schema version"):
            return int(self._version() or 0)

    # ------------------------------------------------------------ rows
    def _row_to_profile(self, row: sqlite3.Row | tuple) -> Profile:
        d = dict(zip(_COLUMNS, row))
        try:
            key = ProfileKey(d["lens_id"], d["focal_bin"], d["aperture_bin"], d["aspect"])
            exact = None
            if d["info_exact"] is not None:
                ej = json.loads(d["info_exact"])
                exact = (_Exact.from_json(ej["matrix"], N_PARAMS**2), _Exact.from_json(ej["vector"], N_PARAMS))
            welford = None
            if d["n_scatter"]:
                welford = _Welford(
                    int(d["n_scatter"]),
                    _unblob(d["theta_mean"], (N_PARAMS,), "theta_mean"),
                    _unblob(d["theta_m2"], (N_PARAMS, N_PARAMS), "theta_m2"),
                    _unblob(d["field_mean"], (FIELD_GRID**2,), "field_mean"),
                    _unblob(d["field_m2"], (FIELD_GRID**2,), "field_m2"),
                )
                if any(a is None for a in (welford.theta_mean, welford.theta_m2, welford.field_mean, welford.field_m2)):
                    raise ValueError("incomplete scatter state")
            return Profile(
                key=key,
                theta=_unblob(d["theta"], (N_PARAMS,), "theta"),
                covariance=_unblob(d["covariance"], (N_PARAMS, N_PARAMS), "covariance"),
                info_matrix=_unblob(d["info_matrix"], (N_PARAMS, N_PARAMS), "info_matrix"),
                info_vector=_unblob(d["info_vector"], (N_PARAMS,), "info_vector"),
                n_frames=int(d["n_frames"]),
                provenance=str(d["provenance"]),
                created=str(d["created"]),
                updated=str(d["updated"]),
                trusted=bool(d["trusted"]),
                field_sigma_ev=None if d["field_sigma_ev"] is None else float(d["field_sigma_ev"]),
                cov_sigma_ev=None if d["cov_sigma_ev"] is None else float(d["cov_sigma_ev"]),
                scatter_sigma_ev=None if d["scatter_sigma_ev"] is None else float(d["scatter_sigma_ev"]),
                notes=str(d["notes"]),
                shots=None if d["shots"] is None else Shots.from_json(json.loads(d["shots"]), "shots"),
                colour=None if d["colour"] is None else ColourPool.from_json(json.loads(d["colour"])),
                grid=grid_from_column(d["grid"]),
                _exact=exact,
                _welford=welford,
            )
        except (ProfileStoreError, ModelError) as exc:
            raise ProfileStoreError(f"profile store {self.path}: corrupt profile row: {exc}") from None
        except (ValueError, TypeError, KeyError, json.JSONDecodeError) as exc:
            raise ProfileStoreError(
                f"profile store {self.path}: corrupt profile row for {d.get('lens_id')!r}: {exc}"
            ) from None

    def _profile_to_row(self, p: Profile) -> tuple:
        k = p.key
        exact = None
        if p._exact is not None:
            exact = json.dumps({"matrix": p._exact[0].to_json(), "vector": p._exact[1].to_json()}, separators=(",", ":"))
        w = p._welford
        return (
            k.lens_id, k.focal_bin, k.aperture_bin, k.aspect,
            _blob(p.theta), _blob(p.covariance), exact, _blob(p.info_matrix), _blob(p.info_vector),
            int(p.n_frames), int(w.n) if w is not None else 0,
            _blob(w.theta_mean) if w else None, _blob(w.theta_m2) if w else None,
            _blob(w.field_mean) if w else None, _blob(w.field_m2) if w else None,
            p.provenance, p.created, p.updated, int(bool(p.trusted)),
            p.field_sigma_ev, p.cov_sigma_ev, p.scatter_sigma_ev, p.notes,
            None if p.shots is None else json.dumps(p.shots.to_json(), ensure_ascii=False, separators=(",", ":")),
            None if p.colour is None else json.dumps(p.colour.to_json(), separators=(",", ":")),
            grid_to_column(p.grid),
        )

    def _select(self, where: str, args: tuple) -> builtins.list[Profile]:
        sql = f"SELECT {', '.join(_COLUMNS)} FROM profiles {where}"  # column names are constants
        rows = self.con.execute(sql, args).fetchall()
        return [self._row_to_profile(r) for r in rows]

    def _get(self, key: ProfileKey) -> Profile | None:
        found = self._select(
            "WHERE lens_id = ? AND focal_bin = ? AND aperture_bin = ? AND aspect = ?",
            (key.lens_id, key.focal_bin, key.aperture_bin, key.aspect),
        )
        return found[0] if found else None

    def _upsert(self, con: sqlite3.Connection, p: Profile) -> int:
        """Insert or update ``p``; returns its row id (kept across updates)."""
        cols = ", ".join(_COLUMNS)
        marks = ", ".join("?" for _ in _COLUMNS)
        updates = ", ".join(f"{c} = excluded.{c}" for c in _COLUMNS[4:])
        con.execute(
            f"INSERT INTO profiles ({cols}) VALUES ({marks}) "
            f"ON CONFLICT (lens_id, focal_bin, aperture_bin, aspect) DO UPDATE SET {updates}",
            self._profile_to_row(p),
        )
        return self._row_id(con, p.key)

    @staticmethod
    def _row_id(con: sqlite3.Connection, key: ProfileKey) -> int | None:
        row = con.execute(
            "SELECT id FROM profiles WHERE lens_id = ? AND focal_bin = ? AND aperture_bin = ? AND aspect = ?",
            (key.lens_id, key.focal_bin, key.aperture_bin, key.aspect),
        ).fetchone()
        return None if row is None else int(row[0])

    # ------------------------------------------------------------ API
    def get(self, key: ProfileKey) -> Profile | None:
        """The profile stored under exactly ``key``, or None.

        Raises
        ------
        ProfileStoreError
            ``key`` is not a :class:`ProfileKey`, or the store cannot be read.
        """
        _check_key(key, "get")
        with self._errors(f"reading {key}"):
            return self._get(key)

    def cast_report(self, key: ProfileKey):
        """The colour cast pooled from the frames of the profile under ``key``
        (:class:`vigproc.core.cast_series.SeriesCast`), or None when none was recorded.

        Raises
        ------
        ProfileStoreError
            ``key`` is not a :class:`ProfileKey`, or the store cannot be read.
        """
        _check_key(key, "cast_report")
        with self._errors(f"reading {key}'s colour cast"):
            row_id = self._row_id(self.con, key)
            if row_id is None:
                return None
            # every corrected frame of a trusted lens asks: pooled again only when its records changed
            seen = tuple(self.con.execute("SELECT count(*), max(pooled), max(frame) FROM cast_frames "
                                          "WHERE profile_id = ?", (row_id,)).fetchone())
            cached = self._cast_cache.get(row_id)
            if cached is not None and cached[0] == seen:
                return cached[1]
            report = read_cast(self.con, row_id)
            self._cast_cache[row_id] = (seen, report)
            return report

    def holds_frame(self, key: ProfileKey, frame_id: str) -> bool:
        """Whether the frame with content id ``frame_id`` was pooled into the profile
        stored under ``key`` (a forensic check must not use a frame's own evidence).

        Raises
        ------
        ProfileStoreError
            ``key`` is not a :class:`ProfileKey`, or the store cannot be read.
        """
        _check_key(key, "holds_frame")
        with self._errors(f"reading {key}"):
            row_id = self._row_id(self.con, key)
            if row_id is None:
                return False
            return self.con.execute("SELECT 1 FROM pooled_frames WHERE frame = ? AND profile_id = ?",
                                    (str(frame_id), row_id)).fetchone() is not None

    def key_for(self, lens_key: LensKey, width: int, height: int) -> ProfileKey:
        """The key a photograph's frames pool under: :meth:`ProfileKey.from_lens`, or, while
        only a lens id an earlier version gave this lens (``LensKey.legacy_ids``) has
        profiles, that id, so that a lens learned before keeps learning into its profiles.

        Raises
        ------
        ProfileStoreError
            As :meth:`ProfileKey.from_lens`, or the store cannot be read.
        """
        key = ProfileKey.from_lens(lens_key, width, height)
        legacy = getattr(lens_key, "legacy_ids", ())
        if not legacy:
            return key
        with self._errors(f"looking up {key}"):
            for lens_id in (key.lens_id, *legacy):
                if self.con.execute("SELECT 1 FROM profiles WHERE lens_id = ? LIMIT 1", (lens_id,)).fetchone():
                    return replace(key, lens_id=lens_id)
        return key

    def lookup(self, lens_key: LensKey, width: int, height: int, *, trusted_only: bool = False) -> Profile | None:
        """The profile to use for a photograph: :meth:`_lookup` of its lens id, else of the
        ids earlier versions gave the lens (``LensKey.legacy_ids``: stored profiles stay
        findable after a change of the lens-identity rule)."""
        hit = self._lookup(lens_key, width, height, trusted_only=trusted_only)
        for lens_id in getattr(lens_key, "legacy_ids", ()):
            if hit is not None:
                break
            make, model, lens = (unescape_key_part(p) for p in lens_id.split("|"))
            hit = self._lookup(replace(lens_key, make=make, model=model, lens=lens, legacy_ids=()), width, height,
                               trusted_only=trusted_only)
        return hit

    def _lookup(self, lens_key: LensKey, width: int, height: int, *, trusted_only: bool = False) -> Profile | None:
        """The profile to use for a photograph.

        1. The exact key (lens, focal bin, aperture bin, aspect).
        2. Else, with the focal length and f-number known, the lens's profiles at
           other bins interpolated to them (:func:`interpolate_profiles`: linear in
           log focal length and in stops, between the nearest bins on either side,
           never extrapolated), with the interpolated uncertainty.
        3. Else, for a known focal length, the neighbouring focal bin (±1 quarter
           octave) of the same lens, aperture bin and aspect whose centre is nearest
           the focal length (ties: trusted, then more frames).

        The aperture is never relaxed without a bin on either side (vignetting changes
        fastest with aperture near wide open), and ``"any"`` bins only match ``"any"``
        (a key without focal length is never merged with a real bin).

        Parameters
        ----------
        trusted_only : bool
            Ignore profiles that are not trusted (an interpolation is trusted when all
            the profiles it uses are and its uncertainty is below the bound).
        """
        key = ProfileKey.from_lens(lens_key, width, height)
        with self._errors(f"looking up {key}"):
            cands: builtins.list[Profile] = []
            exact = self._get(key)
            if exact is not None and (exact.trusted or not trusted_only):
                return exact
            if lens_key.focal_mm is None:
                return None
            if lens_key.fnumber is not None:
                same_lens = [p for p in self._select("WHERE lens_id = ? AND aspect = ?", (key.lens_id, key.aspect))
                             if p.trusted or not trusted_only]
                inter = interpolate_profiles(same_lens, key, float(lens_key.focal_mm), float(lens_key.fnumber))
                if inter is not None and (inter.trusted or not trusted_only):
                    return inter
            k = _focal_index(float(lens_key.focal_mm))
            for kk in (k - 1, k + 1):
                p = self._get(replace(key, focal_bin=_focal_label(kk)))
                if p is not None and (p.trusted or not trusted_only):
                    cands.append(p)
        if not cands:
            return None
        lf = math.log(float(lens_key.focal_mm))

        def rank(p: Profile) -> tuple[float, int, int]:
            centre = float(p.key.focal_bin[2:-2])
            return (round(abs(math.log(centre) - lf), 9), 0 if p.trusted else 1, -p.n_frames)

        best = min(cands, key=rank)
        logger.debug("no profile for %s; using neighbouring focal bin %s", key, best.key.focal_bin)
        return best

    def put(self, profile: Profile, cast_records: Sequence[dict] = ()) -> None:
        """Insert or replace ``profile`` (imports; replaces any profile under its key).

        ``cast_records``: the per-frame colour-cast records a profile file carried
        (:func:`vigproc.stores.profile_file.cast_records_from_dict`), stored as the
        profile's cast evidence in place of what the key held."""
        if not isinstance(profile, Profile):
            raise ProfileStoreError(f"put() needs a Profile, got {type(profile).__name__}")
        if not _valid_theta(profile.theta, profile.key.aspect_ratio):
            raise ProfileStoreError(
                f"profile {profile.key}: θ is not a valid model (P not positive semi-definite or G <= 0 in the frame)"
            )
        if profile.covariance is not None:
            _check_covariance(profile.covariance, f"profile {profile.key}", allow_fixed=True)

        def body(con: sqlite3.Connection) -> None:
            row_id = self._upsert(con, profile)
            # the stored evidence was replaced: no frame is pooled into it any more
            con.execute("DELETE FROM pooled_frames WHERE profile_id = ?", (row_id,))
            con.execute("DELETE FROM cast_frames WHERE profile_id = ?", (row_id,))  # their casts with them
            # ... and the file's own frames' casts in their place, so the lens reports the same cast here
            record_imported_casts(con, row_id, cast_records, _now())
            # ... but what it says of the lens is the prior of the frames learned next
            write_prior(con, row_id, profile.theta, profile.covariance, profile.n_frames, profile.provenance,
                        _now())
            _drop_applied(con, profile.key)

        self._transact(f"storing {profile.key}", body)

    def import_file(self, path: str | os.PathLike[str]) -> Profile:
        """:func:`read_profile_file` then :meth:`put` (with the file's cast records);
        returns the stored profile."""
        p, casts = read_profile_file(path)
        self.put(p, casts)
        return p

    def export_file(self, key: ProfileKey, path: str | os.PathLike[str]) -> Profile:
        """Write the profile under ``key`` as a profile file with its frames' cast
        records (:func:`export_profile`), so that :meth:`import_file` in another store
        gives the same profile and the same :meth:`cast_report`; returns the profile.

        Raises
        ------
        ProfileStoreError
            No profile under ``key``, or the store cannot be read.
        vigproc.errors.ImageWriteError
            The file cannot be written.
        """
        _check_key(key, "export_file")
        with self._errors(f"reading {key}"):
            p = self._get(key)
            row_id = self._row_id(self.con, key)
            casts = cast_records(self.con, row_id) if p is not None else []
        if p is None:
            raise ProfileStoreError(f"no profile under {key}")
        export_profile(p, path, casts)
        return p

    def learn(self, key: ProfileKey, model: VignettingModel, *, notes: str | None = None,
              frame_id: str | None = None, evidence: bytes | None = None,
              lens_key: LensKey | None = None, grid: GridField | None = None,
              cast: dict | None = None) -> Profile:
        """Pool one frame's estimate into the profile under ``key``; returns the new profile.

        The frame adds Λ_i = Σ_i⁻¹ and η_i = Λ_i θ_i (normalised units) to the
        profile's exact sums; θ = Λ⁻¹η, covariance Λ⁻¹.  The Welford moments of θ and
        of the log2 field across frames are updated, and the trust flag recomputed.
        All of it is one ``BEGIN IMMEDIATE`` transaction: concurrent learners
        serialise and no frame is lost.

        If the pooled θ is not a valid model (P not PSD or G ≤ 0 in the frame; rare:
        information weighting is not a convex combination), the plain mean of the
        frames is used, else the previous θ is kept; a warning is logged.

        Learning onto an imported profile: a profile with a covariance acts as prior
        evidence, in the information sums and in the pooled refit of the frames'
        evidence (:mod:`vigproc.stores.profile_prior`); one without (no information)
        is superseded by the learned frames (provenance becomes "learned"; the notes
        say so).

        Parameters
        ----------
        frame_id : str, optional
            The frame's content id (e.g. the file's SHA-256).  A frame already pooled
            into this profile is not pooled again: the profile is returned unchanged.
            The id is recorded in the same transaction as the update, so a crash
            between pooling a frame and recording elsewhere that it was done (the
            daemon's or a batch job's journal) cannot make a rerun pool it twice.
        evidence : bytes, optional
            The frame's data (:func:`vigproc.core.estimate.frame_evidence`), kept with the
            frame.  Once frames of the profile have evidence, the profile's θ,
            covariance and σ are a robust centre (a multivariate t location under the
            scenes' scatter) of their lens-family fits
            (:mod:`vigproc.core.pooling`, at most :data:`MAX_POOLED_FRAMES` frames), which
            measured better than pooling the per-frame estimates and than the centred
            Kang-Weiss fits pooled before (``vigproc bench profile --clean``).
            The information sums are still kept.
            Needs ``frame_id`` (default: the SHA-256 of the evidence).
            With evidence, ``model`` may state no covariance (the lens-family
            estimate a correction applied): the information sums then take the
            evidence's own lens-family fit's, so the frame is not estimated twice.
        lens_key : LensKey, optional
            The frame's EXIF: its focal length, crop factor and names as spelt are
            added to the profile's :attr:`Profile.shots`.
        grid : GridField, optional
            The frame's measured grid field (a flat frame's,
            :func:`vigproc.core.gridfield.flat_grid`), pooled node by node into the
            profile's :attr:`Profile.grid` (:mod:`vigproc.stores.profile_grid`).
        cast : dict, optional
            The frame's colour-cast record (:func:`vigproc.core.cast_series.frame_record`),
            pooled into the profile's cast (:meth:`cast_report`) with the frame, once.
            Needs ``frame_id`` (or ``evidence``).

        Raises
        ------
        ProfileStoreError
            Arguments of the wrong type, no covariance in ``model``, aspect ratio
            not the key's, evidence that is not frame evidence, invalid values,
            database locked or corrupt.
        """
        frame = self._learn_inputs(key, model, notes, frame_id, evidence, lens_key)
        if grid is not None:
            if not isinstance(grid, GridField):
                raise ProfileStoreError(f"grid must be a GridField, got {type(grid).__name__}")
            if aspect_label(grid.width / grid.height) != key.aspect:
                raise ProfileStoreError(f"a {grid.width}x{grid.height} grid field cannot refine the {key.aspect} "
                                        f"profile {key}")
            frame = replace(frame, grid=grid)
        if cast is not None:
            try:
                check_record(cast)
            except ValueError as exc:
                raise ProfileStoreError(f"cast: {exc}") from None

        def body(con: sqlite3.Connection) -> tuple[Profile | None, Profile]:
            old = self._get(key)
            if old is not None and frame.frame_id is not None:
                seen = con.execute("SELECT 1 FROM pooled_frames WHERE frame = ? AND profile_id = ?",
                                   (frame.frame_id, self._row_id(con, key))).fetchone()
                if seen is not None:
                    logger.info("profile %s: frame %s is already pooled; not again", key, frame.frame_id[:16])
                    return old, old
            now = _now()
            profile = _pool_frame(old, key, frame, notes, now)
            row_id = self._upsert(con, profile)
            if frame.frame_id is not None:
                con.execute("INSERT OR IGNORE INTO pooled_frames (frame, profile_id, pooled, evidence, family) "
                            "VALUES (?, ?, ?, ?, ?)", (frame.frame_id, row_id, now, frame.evidence,
                                                       None if frame.evidence is None else
                                                       _fit_blob(frame.fit, frame.size)))
                if cast is not None:
                    record_cast(con, row_id, frame.frame_id, cast, now)
            if frame.evidence is not None:
                refit = self._pooled_refit(con, row_id, key, frame.size)
                if refit is not None:
                    profile = _with_refit(profile, refit)
                    self._upsert(con, profile)
                    logger.debug("profile %s: pooled from %d frames' evidence", key, refit[3])
            return old, profile

        old, profile = self._transact(f"learning {key}", body)
        if profile.trusted and not (old is not None and old.trusted):
            logger.info("profile %s is now trusted (%d frames, σ = %.4f EV)", key, profile.n_frames,
                        profile.field_sigma_ev)
        return profile

    def _learn_inputs(self, key: ProfileKey, model: VignettingModel, notes: str | None, frame_id: str | None,
                      evidence: bytes | None, lens_key: LensKey | None) -> _Frame:
        """Check :meth:`learn`'s arguments and compute what the frame adds to a profile.

        Checked up front, outside the transaction: a bad argument must not surface as a
        raw error from inside it (``notes`` is only joined there).

        Returns
        -------
        _Frame

        Raises
        ------
        ProfileStoreError
            As :meth:`learn`.
        """
        _check_key(key, "learn")
        if not isinstance(model, VignettingModel):
            raise ProfileStoreError(f"learn() needs a VignettingModel, got {type(model).__name__}")
        if notes is not None and not isinstance(notes, str):
            raise ProfileStoreError(f"notes must be a string, got {type(notes).__name__}")
        frame_fit, frame_size = None, None
        if evidence is not None:
            if not isinstance(evidence, bytes):
                raise ProfileStoreError(f"evidence must be bytes, got {type(evidence).__name__}")
            try:
                # fitted before the transaction: the refit finds it in the cache
                frame_fit, frame_size = self._frame_fit(evidence)
            except VigprocError as exc:  # first: InvalidImageError (too few usable bins) is a ValueError too
                raise ProfileStoreError(f"nothing to learn from this frame: {exc}") from None
            except ValueError as exc:
                # the decoder's own wording (numpy's allow_pickle...) would only confuse
                logger.debug("evidence rejected: %s", exc)
                raise ProfileStoreError(
                    "evidence is not frame evidence (the bytes vigproc.core.estimate.frame_evidence returns)"
                ) from None
            if frame_id is None:
                frame_id = "evidence:" + hashlib.sha256(evidence).hexdigest()
        if lens_key is not None and not isinstance(lens_key, LensKey):
            raise ProfileStoreError(f"lens_key must be a LensKey, got {type(lens_key).__name__}")
        frame_shots = Shots.of_frame(lens_key) if lens_key is not None else None
        if frame_id is not None and (not isinstance(frame_id, str) or not frame_id or len(frame_id) > 256):
            raise ProfileStoreError(f"frame_id must be a non-empty string of at most 256 characters, got {frame_id!r}")
        if aspect_label(model.width / model.height) != key.aspect:
            raise ProfileStoreError(
                f"a {model.width}x{model.height} estimate ({aspect_label(model.width / model.height)}) "
                f"cannot refine the {key.aspect} profile {key}"
            )
        if model.covariance is None and evidence is not None:
            # an estimate that states no covariance (the lens-family fit a correction
            # applied): its information is that of the evidence's own fit, not a second estimate
            from vigproc.core.pooling import pool_family

            try:
                own = pool_family([frame_fit], *frame_size, family=self._family)
            except ModelError as exc:
                raise ProfileStoreError(f"unusable frame evidence: {exc}") from None
            # centred and circular by construction: those parameters are fixed, adding no information
            theta_i, cov_i, _ = normalise(own)
            lam_i = _scaled_pinv(_check_covariance(cov_i, "frame fit", allow_fixed=True), "frame fit",
                                 allow_fixed=True)
            eta_i = lam_i @ theta_i
        else:
            theta_i, lam_i, eta_i = frame_information(model)
        aspect = key.aspect_ratio
        field_i, _, gmin = _field_and_jacobian(theta_i, aspect)
        if not (gmin > 0 and np.all(np.isfinite(field_i))):
            raise ProfileStoreError(f"the estimate's geometric factor G falls to {gmin:.3g} inside the frame")
        add_lam, add_eta = _Exact.from_array(lam_i), _Exact.from_array(eta_i)
        if evidence is not None:
            # the scatter that matters is that of what the profile pools: the family fits
            from vigproc.core.pooling import coefficients_model

            try:
                theta_i = normalise(coefficients_model(frame_fit.coefficients, *frame_size, self._family))[0]
            except ModelError as exc:
                raise ProfileStoreError(f"unusable frame evidence: {exc}") from None
            field_i = _field_and_jacobian(theta_i, aspect)[0]
        return _Frame(theta=theta_i, field=field_i, lam=add_lam, eta=add_eta, frame_id=frame_id,
                      evidence=evidence, fit=frame_fit, size=frame_size, shots=frame_shots, colour=model.colour)

    def _frame_fit(self, blob: bytes) -> tuple[Any, tuple[int, int]]:
        """The lens-family fit of a frame's evidence (:func:`vigproc.core.pooling.frame_fit`)
        and the frame's size; cached by the evidence's SHA-256 (a caller's frame ids
        need not be unique across profiles).

        Raises
        ------
        ValueError
            Not frame evidence.
        VigprocError
            Too few usable bins for a fit.
        """
        from vigproc.core.pooling import frame_fit
        from vigproc.core.robust import evidence_copy

        digest = hashlib.sha256(blob).digest()
        cached = self._fit_cache.get(digest)
        if cached is None:
            wc = evidence_copy(blob)
            cached = (frame_fit(wc, self._family), (wc.width, wc.height))
            if len(self._fit_cache) >= _FIT_CACHE_SIZE:
                self._fit_cache.pop(next(iter(self._fit_cache)))
            self._fit_cache[digest] = cached
        return cached

    def _pooled_refit(self, con: sqlite3.Connection, row_id: int, key: ProfileKey,
                      frame_size: tuple[int, int]) -> tuple[np.ndarray, np.ndarray, float, int] | None:
        """θ, covariance (normalised) and field σ (EV) of the profile pooled from its
        frames' lens-family fits by :mod:`vigproc.core.pooling`, and how many frames it
        pooled; None when no frame's evidence gives a fit or the pooled model is not
        valid (the θ pooled from the frames' estimates stays)."""
        from vigproc.core.pooling import pool_family

        family = self._family or profile_family()
        fits = []
        # chosen in frame-id order: the same frames give the same profile whatever
        # order they came in (a batch job's workers finish in any order)
        rows = con.execute("SELECT frame, family FROM pooled_frames WHERE profile_id = ? AND evidence IS NOT NULL "
                           "ORDER BY frame LIMIT ?", (row_id, MAX_POOLED_FRAMES)).fetchall()
        missing = sum(blob is None for _, blob in rows)
        if missing > 10:
            logger.info("profile %s: fitting %d frames stored by an older vigproc (once)", key, missing)
        for frame, blob in rows:
            try:
                fit = _fit_from_blob(blob)[0] if blob is not None else None
                if fit is None or fit.coefficients.size != family.n_components:
                    # stored before v5 (or in another family): fit its evidence now, and keep the fit
                    (evidence,) = con.execute("SELECT evidence FROM pooled_frames WHERE frame = ? AND profile_id = ?",
                                              (frame, row_id)).fetchone()
                    fit, size = self._frame_fit(bytes(evidence))
                    con.execute("UPDATE pooled_frames SET family = ? WHERE frame = ? AND profile_id = ?",
                                (_fit_blob(fit, size), frame, row_id))
            except (ValueError, VigprocError) as exc:  # a damaged blob costs that frame, not the profile
                logger.warning("profile %s: skipping a frame's evidence: %s", key, exc)
                continue
            fits.append(fit)
        if not fits:
            return None
        prior = read_prior(con, row_id)
        if prior is not None:  # an imported profile: its frames are not here, its information is
            from vigproc.core.pooling import prior_coefficients

            try:
                prior = prior_coefficients(prior[0], prior[1], key.aspect_ratio, family)
            except ModelError as exc:
                logger.warning("profile %s: its imported profile cannot join the frames (%s)", key, exc)
                prior = None
        try:
            m = pool_family(fits, *frame_size, family=family, prior=prior)
        except ModelError as exc:
            logger.warning("profile %s: pooling the frames failed (%s); keeping the pooled estimate", key, exc)
            return None
        theta, cov, _ = normalise(m)
        if cov is None or not _valid_theta(theta, key.aspect_ratio):
            logger.warning("profile %s: the pooled fit is not a valid model; keeping the pooled estimate", key)
            return None
        return theta, cov, float(m.quality.field_sigma_ev), len(fits)

    def list(self, lens_id: str | None = None) -> builtins.list[Profile]:
        """All profiles (of one ``lens_id`` if given), ordered by key."""
        order = "ORDER BY lens_id, aspect, focal_bin, aperture_bin"
        with self._errors("listing profiles"):
            if lens_id is None:
                return self._select(order, ())
            return self._select(f"WHERE lens_id = ? {order}", (lens_id,))

    def delete(self, key: ProfileKey) -> bool:
        """Delete the profile under ``key``; True if there was one.

        Raises
        ------
        ProfileStoreError
            ``key`` is not a :class:`ProfileKey`, or the store cannot be written.
        """
        _check_key(key, "delete")

        def body(con: sqlite3.Connection) -> bool:
            cur = con.execute(
                "DELETE FROM profiles WHERE lens_id = ? AND focal_bin = ? AND aperture_bin = ? AND aspect = ?",
                (key.lens_id, key.focal_bin, key.aperture_bin, key.aspect),
            )
            _drop_applied(con, key)
            return cur.rowcount > 0

        return bool(self._transact(f"deleting {key}", body))

    def applied_revision(self, key: ProfileKey) -> tuple[str, Profile] | None:
        """The revision of the profile under ``key`` that correct runs apply (shared by
        every worker and kept across restarts), as ``(revision id, profile)``; None when
        none was applied yet (or the stored one cannot be read: it is then replaced).

        Raises
        ------
        ProfileStoreError
            ``key`` is not a :class:`ProfileKey`, or the store cannot be read.
        """
        _check_key(key, "applied_revision")
        with self._errors(f"reading the applied revision of {key}"):
            return self._read_applied(self.con, key)

    def apply_revision(self, profile: Profile, *, replaces: str | None = None) -> tuple[str, Profile]:
        """Make ``profile`` the applied revision of its key, if no other worker got there
        first; returns the revision applied now, ``(revision id, profile)``.

        One ``BEGIN IMMEDIATE`` transaction: with ``replaces=None`` ``profile`` is
        written only when the key has no applied revision (else the one there is
        returned); with ``replaces=ID`` it replaces the applied revision only while that
        is still ``ID`` (compare-and-set: of two workers that both found the stored
        profile moved, one replaces it and the other follows).

        Parameters
        ----------
        profile : Profile
            The stored profile as the caller read it.
        replaces : str, optional
            The revision id the caller found applied.

        Returns
        -------
        tuple of (str, Profile)
            The revision id (16 hex digits of the SHA-256 of its JSON) and the
            profile as read back from its JSON.

        Raises
        ------
        ProfileStoreError
            ``profile`` is not a :class:`Profile`, or the store cannot be written.
        """
        if not isinstance(profile, Profile):
            raise ProfileStoreError(f"apply_revision() needs a Profile, got {type(profile).__name__}")
        text = json.dumps(profile_to_dict(profile), sort_keys=True, ensure_ascii=False, allow_nan=False)
        rev = hashlib.sha256(text.encode("utf-8")).hexdigest()[:16]
        key = profile.key

        def body(con: sqlite3.Connection) -> tuple[str, Profile]:
            held = self._read_applied(con, key)
            if held is not None and held[0] != replaces:
                return held  # another worker wrote (or replaced) it first: follow
            con.execute(
                "INSERT INTO applied_profiles (lens_id, focal_bin, aperture_bin, aspect, revision, n_frames, profile, "
                "applied) VALUES (?, ?, ?, ?, ?, ?, ?, ?) ON CONFLICT (lens_id, focal_bin, aperture_bin, aspect) "
                "DO UPDATE SET revision = excluded.revision, n_frames = excluded.n_frames, "
                "profile = excluded.profile, applied = excluded.applied, "
                "series_first = NULL, series_last = NULL, series_clock = NULL, series_seen = NULL",  # opens a series
                (key.lens_id, key.focal_bin, key.aperture_bin, key.aspect, rev, int(profile.n_frames), text, _now()),
            )
            return rev, profile_from_dict(json.loads(text), f"applied revision {rev} of {key}")

        return self._transact(f"applying a revision of {key}", body)

    def series_revision(self, profile: Profile | None, key: ProfileKey, *, at: float, clock: str,
                        gap: float, now: float | None = None) -> tuple[str, Profile, bool] | None:
        """The applied revision of ``key`` for a frame taken at ``at``: replaced only at a
        series boundary, never within a series.

        The applied revision remembers the span of frame times of the series it corrects
        (on one clock: the first frame's) and when its last frame arrived. A frame within
        ``gap`` seconds of that span belongs to the series: it gets the revision and
        extends the span. A frame of the other clock (a file without a capture time in a
        series of files with one, or the reverse) is judged by its arrival instead:
        within ``gap`` of the series' last arrival it belongs to it (and a capture time
        then replaces an arrival-clock span). A frame further away starts a new series:
        ``profile`` (the stored profile as the caller read it), when trusted and not the
        applied revision already, replaces it, and the span restarts at ``at``. With no
        applied revision, a trusted ``profile`` becomes it. All of it is one ``BEGIN
        IMMEDIATE`` transaction (a compare-and-set on the revision held: of two workers at
        one boundary, one replaces it and the other finds the new series and follows); a
        frame inside the span writes nothing (but a minute's arrival time).

        Parameters
        ----------
        profile : Profile or None
            The stored profile of ``key`` as the caller read it (None: none).
        key : ProfileKey
        at : float
            The frame's time, seconds (its capture time, else its arrival).
        clock : str
            ``"capture"`` or ``"arrival"``.
        gap : float
            Seconds between frames that end a series.
        now : float, optional
            The frame's arrival, seconds since the epoch (default: now).

        Returns
        -------
        tuple of (str, Profile, bool) or None
            Revision id, the applied profile, and whether this frame started a new
            series; None when nothing is applied (and ``profile`` is not trusted).

        Raises
        ------
        ProfileStoreError
            Bad arguments, or the store cannot be read or written.
        """
        _check_key(key, "series_revision")
        if profile is not None and (not isinstance(profile, Profile) or profile.key != key):
            raise ProfileStoreError(f"series_revision() needs a Profile of {key}")
        now = time.time() if now is None else now
        if not (all(isinstance(x, (int, float)) and math.isfinite(x) for x in (at, gap, now)) and gap >= 0
                and clock in ("capture", "arrival")):
            raise ProfileStoreError(f"series_revision(): bad frame time {at!r}, clock {clock!r} or gap {gap!r}")
        at, now = float(at), float(now)
        slack = min(60.0, gap / 60.0)  # an arrival time this much newer is written; less is not worth a write

        def plan(row) -> tuple[bool, tuple | None]:
            """(in the series, the series columns to write or None)."""
            first, last, clk, seen = row[2:]
            fresh = seen is None or now > seen + slack
            if first is None:  # applied before series were kept, or by hand: this frame opens one
                return True, (at, at, clock, now)
            if clk == clock:
                if not first - gap <= at <= last + gap:
                    return False, None
                if first <= at <= last and not fresh:
                    return True, None
                return True, (min(first, at), max(last, at), clk, max(now, seen or now))
            if seen is not None and now - seen > gap:
                return False, None
            if clock == "capture":  # a capture time replaces an arrival-clock span
                return True, (at, at, clock, max(now, seen or now))
            return True, (first, last, clk, max(now, seen or now)) if fresh else None

        with self._errors(f"reading the applied revision of {key}"):
            row = self._read_series(self.con, key)
        if row is not None:
            inside, write = plan(row)
            if inside and write is None:
                return row[0], row[1], False
        text = rev = None
        if profile is not None and profile.trusted:
            text = json.dumps(profile_to_dict(profile), sort_keys=True, ensure_ascii=False, allow_nan=False)
            rev = hashlib.sha256(text.encode("utf-8")).hexdigest()[:16]
        where = (key.lens_id, key.focal_bin, key.aperture_bin, key.aspect)
        set_series = ("UPDATE applied_profiles SET series_first = ?, series_last = ?, series_clock = ?, "
                      "series_seen = ? WHERE lens_id = ? AND focal_bin = ? AND aperture_bin = ? AND aspect = ?")

        def body(con: sqlite3.Connection) -> tuple[str, Profile, bool] | None:
            held = self._read_series(con, key)
            if held is not None:
                inside, write = plan(held)
                if inside:
                    if write is not None:
                        con.execute(set_series, (*write, *where))
                    return held[0], held[1], False
            if rev is None or (held is not None and held[0] == rev):  # a new series, the same revision
                if held is None:
                    return None
                con.execute(set_series, (at, at, clock, now, *where))
                return held[0], held[1], True
            con.execute(
                "INSERT INTO applied_profiles (lens_id, focal_bin, aperture_bin, aspect, revision, n_frames, profile, "
                "applied, series_first, series_last, series_clock, series_seen) "
                "VALUES (?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?) "
                "ON CONFLICT (lens_id, focal_bin, aperture_bin, aspect) DO UPDATE SET revision = excluded.revision, "
                "n_frames = excluded.n_frames, profile = excluded.profile, applied = excluded.applied, "
                "series_first = excluded.series_first, series_last = excluded.series_last, "
                "series_clock = excluded.series_clock, series_seen = excluded.series_seen",
                (*where, rev, int(profile.n_frames), text, _now(), at, at, clock, now),
            )
            return rev, profile_from_dict(json.loads(text), f"applied revision {rev} of {key}"), True

        return self._transact(f"applying a revision of {key}", body)

    def _read_series(self, con: sqlite3.Connection, key: ProfileKey):
        """(revision, profile, series_first, series_last, series_clock, series_seen) of
        ``key``'s applied revision, or None (none, or unreadable: it is then replaced)."""
        held = self._read_applied(con, key)
        if held is None:
            return None
        row = con.execute("SELECT series_first, series_last, series_clock, series_seen FROM applied_profiles "
                          "WHERE lens_id = ? AND focal_bin = ? AND aperture_bin = ? AND aspect = ?",
                          (key.lens_id, key.focal_bin, key.aperture_bin, key.aspect)).fetchone()
        first, last, clock, seen = row if row is not None else (None, None, None, None)
        num = (lambda x: None if x is None else float(x))
        return held[0], held[1], num(first), num(last), clock, num(seen)

    def _read_applied(self, con: sqlite3.Connection, key: ProfileKey) -> tuple[str, Profile] | None:
        row = con.execute(
            "SELECT revision, profile FROM applied_profiles "
            "WHERE lens_id = ? AND focal_bin = ? AND aperture_bin = ? AND aspect = ?",
            (key.lens_id, key.focal_bin, key.aperture_bin, key.aspect),
        ).fetchone()
        if row is None:
            return None
        try:
            p = profile_from_dict(json.loads(row[1]), f"applied revision {row[0]} of {key}")
        except (ProfileStoreError, ValueError, TypeError) as exc:  # a damaged row is replaced, not fatal
            logger.warning("profile store %s: %s; it will be replaced", self.path, exc)
            return None
        if p.key != key:
            logger.warning("profile store %s: applied revision %s is of %s, not %s; it will be replaced",
                           self.path, row[0], p.key, key)
            return None
        return str(row[0]), p

    def check(self) -> builtins.list[str]:
        """``PRAGMA integrity_check`` and ``foreign_key_check``, plus decoding every
        row: the problems found (empty when the store is sound)."""
        problems: builtins.list[str] = []
        with self._errors("checking integrity"):
            rows = [str(r[0]) for r in self.con.execute("PRAGMA integrity_check(100)").fetchall()]
            if rows != ["ok"]:
                # damaged pages: reading the tables (the checks below) would fail on them
                return [line for r in rows for line in r.splitlines() if line.strip()]
            problems.extend(f"foreign key violation: {r}" for r in self.con.execute("PRAGMA foreign_key_check").fetchall())
            if not problems:
                for row in self.con.execute(f"SELECT {', '.join(_COLUMNS)} FROM profiles").fetchall():
                    try:
                        self._row_to_profile(row)
                    except ProfileStoreError as exc:
                        problems.append(str(exc))
        return problems

    def __repr__(self) -> str:
        return f"ProfileStore({str(self.path)!r})"


def _drop_applied(con: sqlite3.Connection, key: ProfileKey) -> None:
    """Forget the applied revision of ``key`` (its profile was replaced or deleted)."""
    con.execute("DELETE FROM applied_profiles WHERE lens_id = ? AND focal_bin = ? AND aperture_bin = ? AND aspect = ?",
                (key.lens_id, key.focal_bin, key.aperture_bin, key.aspect))
