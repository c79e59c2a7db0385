"""The one way a front end opens the profile store (the CLI, check, the hook, batch and
its workers, the watch folder's workers, the Python API).

A command that only reads the store (``correct --profile auto``, ``check``, the hook)
goes on without it when it does not exist and cannot be created (a read-only home, no
user data folder): a store that does not exist holds no profile.  One that exists but
cannot be opened is an error, as is any failure of a command that writes (``learn``,
``profile ...``): its profiles would be missed or lost.
"""

from __future__ import annotations

import logging
import os
from pathlib import Path
from typing import TYPE_CHECKING

if TYPE_CHECKING:  # the store module loads SQLite and the profile maths: only when opened
    from vigproc.stores.profiles import ProfileStore

__all__ = ["open_profile_store"]

log = logging.getLogger(__name__)


def open_profile_store(path: str | os.PathLike[str] | None = None, *, write: bool = False) -> ProfileStore | None:
    """Open the profile store.

    Parameters
    ----------
    path : str, os.PathLike or None
        ``--profile-db``; None: ``$VIGPROC_PROFILE_DB``, else the user data folder's
        (:func:`vigproc.stores.profiles.default_db_path`).
    write : bool
        The caller writes profiles (learn mode, ``profile import``...): any failure raises.

    Returns
    -------
    ProfileStore or None
        None only for a reader whose store does not exist and cannot be created (said
        once, as a warning).

    Raises
    ------
    ProfileStoreError
        The store cannot be opened (for a reader: an existing one, corrupt, locked or
        unreadable).
    """
    from vigproc.stores.profiles import ProfileStore, ProfileStoreError, default_db_path

    try:
        return ProfileStore(path)
    except ProfileStoreError as exc:
        if write:
            raise
        target = Path(path).expanduser() if path is not None else default_db_path()
        try:
            present = target.exists()
        except OSError:  # cannot even look: nothing can be read from it either
            present = False
        if present:
            raise
        log.warning("no profile store (%s); going on without stored profiles", exc)
        return None
