"""When a file that failed is tried again, and how often: the one backoff and the one
attempt limit of the journal, batch runs, the watch folder and its full-disk pause.

Pure and light (no SQLite): the command-line parsers take their defaults from here.
"""

from __future__ import annotations

import random

__all__ = ["DEFAULT_MAX_ATTEMPTS", "DEFAULT_MAX_CRASHES", "DEFAULT_RETRY_BASE", "DEFAULT_RETRY_CAP", "retry_delay"]

#: First retry delay (seconds) after a transient failure; doubles per attempt ...
DEFAULT_RETRY_BASE = 5.0
#: ... up to this many seconds.
DEFAULT_RETRY_CAP = 600.0
#: Failed attempts (transient failures) after which a file is given up (quarantined).
DEFAULT_MAX_ATTEMPTS = 5
#: Crashes or hangs of its worker after which the watch folder gives a file up.
DEFAULT_MAX_CRASHES = 3


def retry_delay(attempts: int, base: float = DEFAULT_RETRY_BASE, cap: float = DEFAULT_RETRY_CAP, *,
                jitter: bool = False) -> float:
    """The wait before a file (or a full-disk probe) is tried again.

    Parameters
    ----------
    attempts : int
        Failed attempts so far (1 after the first failure).
    base, cap : float
        The first wait and the longest one, in seconds; the wait doubles per failure.
    jitter : bool
        Wait a random 80-100 % of it, so files that failed together do not all come back
        together.

    Returns
    -------
    float
        Seconds.

    Examples
    --------
    >>> [retry_delay(n) for n in (1, 2, 3, 9)]
    [5.0, 10.0, 20.0, 600.0]
    """
    delay = min(cap, base * 2.0 ** max(attempts - 1, 0))
    return delay * random.uniform(0.8, 1.0) if jitter else delay
