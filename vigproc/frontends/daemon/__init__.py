"""The watch-folder daemon: every complete image dropped into a folder is processed exactly once.

How a file goes through
-----------------------
1. *Seen*: a file system event (watchdog's native observer, or its polling observer
   for network shares) or a rescan of the folder (at start, every ``rescan``
   seconds, on SIGHUP) names a path.  Temporary names of common writers
   (:func:`is_temporary_name`), non-image suffixes, symbolic links, and our own
   output, quarantine and archive folders are ignored.
2. *Settled*: its size, mtime and inode did not change for ``settle`` seconds
   (:class:`SettleTracker`: two looks that far apart).
3. *Claimed*: the main process fingerprints it (size, mtime, SHA-256) and claims it
   in the :class:`~vigproc.stores.journal.Journal`; a path whose content is already done
   or quarantined is skipped, so duplicate events, rescans and restarts are
   harmless.
4. *Processed* by a worker process (:func:`.worker._worker_main`, one
   :class:`~vigproc.pipeline.processor.Processor` each) with deterministic output names
   (:func:`vigproc.pipeline.processor.output_location`: the input's sub-folders mirrored under
   the output folder, its name kept); outputs and the JSON sidecar are published
   atomically.
5. *Recorded*: ``done`` (then optionally moved to the archive folder), ``retry``
   after a transient error (locked file: exponential backoff), or ``quarantined``
   with the reason (optionally moved to the quarantine folder; a file that fails to
   decode while it is still young gets one more look first: a writer that paused
   longer than ``settle`` leaves an incomplete, not a corrupt, file).  If the file
   changed while it was processed, it is simply seen again.

Whose fault (:mod:`vigproc.pipeline.faults`, shared with batch runs and ``vigproc correct``):
only what is wrong with the photo quarantines it.  A failure to write an output is
the output side's: retried without limit, never quarantined or moved.  A full output
disk (ENOSPC/EDQUOT, or a write failure -- OpenImageIO's ``TIFFWriteScanline failed``,
exiftool's ``Error writing image data`` -- while the output file system is under
``min_free``) *pauses* the daemon: the file goes back without an attempt counted,
nothing more is handed out, the status says ``paused`` (output disk full) and the log
``disk-full``; it resumes as soon as the free space has grown, or when a probe (one
file, after a backoff that doubles up to ``retry_cap``) is written.

Crash safety
------------
The journal is updated in one fsynced transaction per step (one that fails, e.g. on
a full disk, is retried until it succeeds).  After a kill -9 the next start calls
:meth:`~vigproc.stores.journal.Journal.recover`: files left running become pending *without*
a crash charge -- the daemon's own death is not the files' fault, and decoding
happens in workers, never in the daemon -- then it removes the temporary files of
the unfinished files and rescans the folder, so files dropped while the daemon was
down are found.  A worker that crashes or hangs while the daemon lives charges its
file a crash (:meth:`~vigproc.stores.journal.Journal.crashed`; quarantined at
``max_crashes``); its process group (exiftool included) is killed and its
temporaries removed.  Workers raise their OOM score, so that a file exhausting
memory takes its worker, not the daemon.  A sidecar
that already records the same input content and settings (a crash after the sidecar
but before the journal) is taken as the result instead of processing the file again.
In ``learn`` mode each frame content is pooled at most once: the input's SHA-256 is
the ``frame_id`` of :meth:`~vigproc.stores.profiles.ProfileStore.learn`, recorded in the
store's own transaction.

Workers are processes (``spawn``), not threads: a decoder crash on a hostile file
kills one worker, not the daemon, and the GIL is not shared.  Each leads a process
group of its own (a terminal's Ctrl-C does not reach it or its exiftool), ignores
SIGINT/SIGTERM (the main process drains them) and dies with the main process
(``PR_SET_PDEATHSIG`` on Linux; they also exit when their pipe closes), and so does
its exiftool.  An exiftool failure while the daemon stops gives the file back
without an attempt: a stop signal may have killed it.

The package
-----------
:class:`Daemon` (:mod:`.service`: the job's lock, its signals and its loop) composes
three parts, each in a module of its own:

* what watches, :class:`~.watcher.Watcher`: the observer, rescans, candidate
  filtering, :class:`SettleTracker` (steps 1 and 2);
* what schedules, :class:`~.scheduler.Scheduler`: the fingerprint and claim of step 3,
  the worker processes (:mod:`.worker`), dispatch, results, retries, timeouts, the
  pause for a full disk (step 4);
* what records, :class:`~.recorder.Recorder`: every journal write, the archive and
  quarantine moves, the status file (step 5, and the clean-up at start).

:mod:`.config` holds :class:`WatchConfig` and the names the daemon takes or ignores,
:mod:`.logs` its log formats.
"""

from __future__ import annotations

from vigproc.pipeline.faults import CRASH, DISK_FULL, PERMANENT, TRANSIENT, classify_error, disk_space
from vigproc.stores.journal import Journal  # noqa: F401 - where tests and callers found it

from .config import (IGNORED_DIRS, REASON_SUFFIX, TEMP_SUFFIXES, RunFlags, WatchConfig, WatchError, _Task,
                     is_candidate_name, is_temporary_name, output_stem)
from .logs import JsonLogFormatter, TextLogFormatter, configure_logging
from .recorder import Recorder, _move, read_status
from .scheduler import Scheduler, _DiskPause, _Worker
from .service import Daemon
from .watcher import SettleTracker, Watcher
from .worker import _worker_main

__all__ = [
    "CRASH",
    "DISK_FULL",
    "Daemon",
    "IGNORED_DIRS",
    "JsonLogFormatter",
    "PERMANENT",
    "REASON_SUFFIX",
    "Recorder",
    "RunFlags",
    "Scheduler",
    "SettleTracker",
    "TEMP_SUFFIXES",
    "TRANSIENT",
    "TextLogFormatter",
    "WatchConfig",
    "WatchError",
    "Watcher",
    "classify_error",
    "configure_logging",
    "is_candidate_name",
    "is_temporary_name",
    "output_stem",
    "read_status",
]
