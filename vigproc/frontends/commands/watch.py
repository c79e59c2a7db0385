"""``vigproc watch``: the watch-folder daemon (its benchmarks, ``vigproc bench watch`` and
``vigproc bench faults``, are in the checkout's ``benchmarks/``).

The daemon itself is :mod:`vigproc.frontends.daemon`; the journal :mod:`vigproc.stores.journal`.
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import logging
import os
from pathlib import Path
from typing import Any

from vigproc.frontends.commands._options import add_learn, add_processing, learn_setting, number
from vigproc.pipeline.faults import DEFAULT_MIN_FREE
from vigproc.pipeline.processor import Settings, names_profile_file
from vigproc.stores.opening import open_profile_store
from vigproc.stores.retry import DEFAULT_MAX_ATTEMPTS, DEFAULT_MAX_CRASHES, DEFAULT_RETRY_BASE, DEFAULT_RETRY_CAP

log = logging.getLogger("vigproc.watch")


def _default_workers() -> int:
    return max(1, (os.cpu_count() or 2) // 2)


def _config(args: argparse.Namespace):
    from vigproc.frontends.daemon import WatchConfig

    profile = args.profile
    if names_profile_file(profile):
        profile = str(Path(profile).expanduser().resolve())  # workers must find it whatever their cwd
    settings = {"mode": args.mode, "profile": profile, "method": args.method, "transfer": args.input_transfer,
                "output_format": args.output_format, "picture": bool(args.picture), "strength": args.strength,
                "unapplied": args.unapplied, "in_camera": args.in_camera}

    if learn_setting(args, default=True):  # a hot folder learns each lens as its photos arrive
        settings["learn"] = True
    level = logging.DEBUG if args.verbose else logging.INFO
    return WatchConfig(
        in_dir=Path(args.in_dir), out_dir=Path(args.output), settings=settings, workers=args.workers, poll=args.poll,
        settle=args.settle, journal=args.journal, job=args.job, quarantine_dir=args.quarantine,
        archive_dir=args.archive, profile_db=args.profile_db, status_file=args.status_file, rescan=args.rescan,
        timeout=args.timeout, max_attempts=args.max_attempts, max_crashes=args.max_crashes,
        retry_base=args.retry_base, retry_cap=args.retry_cap, retry_quarantined=args.retry_quarantined,
        min_free=int(args.min_free * 1e6), log_json=args.log_json, log_level=level)


def _check_settings(cfg) -> None:
    """Fail at start, not once per file, on settings that cannot work."""
    settings = Settings(**cfg.settings)
    if settings.mode == "correct" and settings.profile_is_file:
        from vigproc.stores.profiles import import_profile

        import_profile(settings.profile)
    if settings.needs_store:
        store = open_profile_store(cfg.profile_db, write=settings.mode == "learn")
        if store is not None:
            store.close()
    if cfg.settings["mode"] == "check" and importlib.util.find_spec("vigproc.forensics.check") is None:
        log.warning("check mode needs vigproc.forensics.check, which this installation lacks: every file will be "
                    "quarantined with that reason (requeue them later with --retry-quarantined)")


def _print_status(st: dict[str, Any]) -> None:
    d = st.get("daemon") or {}
    c = st.get("journal_counts") or {}
    state = "running" if st["running"] else "not running"
    print(f"vigproc watch {st['in_dir']} -> {st['out_dir']}: {state}"
          + (f", pid {d.get('pid')}, {d.get('workers')} worker(s), {d.get('mode')} mode" if st["running"] and d else ""))
    if d:
        q = d.get("queue") or {}
        print(f"  status file updated {st.get('age_s', '?')} s ago (daemon state: {d.get('state')})")
        p = d.get("paused")
        if st["running"] and p:
            free = p.get("free_bytes")
            print(f"  PAUSED: {p.get('why')} since {p.get('since')}"
                  + (f" ({free / 1e6:.1f} MB free)" if isinstance(free, (int, float)) else "")
                  + f"; {p.get('files_waiting', 0)} file(s) waiting, next try in {p.get('next_try_s', 0):.0f} s "
                  "or as soon as space is freed; nothing is quarantined for it")
        if st["running"]:
            print(f"  queue {q.get('settling', 0) + q.get('ready', 0) + q.get('dispatched', 0)} "
                  f"(settling {q.get('settling', 0)}, ready {q.get('ready', 0)}, dispatched {q.get('dispatched', 0)}), "
                  f"running {len(d.get('running') or [])}, waiting to retry {q.get('retry_wait', 0)}, "
                  f"{d.get('files_per_min', 0)} files in the last minute")
        t = d.get("this_run") or {}
        print(f"  this run: {t.get('done', 0)} done, {t.get('quarantined', 0)} quarantined, "
              f"{t.get('failed_attempts', 0)} failed attempts, {t.get('retried', 0)} retries")
    if c:
        print(f"  journal: {c.get('done', 0)} done, {c.get('failed', 0)} failed (will retry), "
              f"{c.get('quarantined', 0)} quarantined, {c.get('pending', 0)} pending, {c.get('running', 0)} running")
    else:
        print("  no journal yet (never started with these folders)")
    for q in st.get("quarantined") or []:
        print(f"  quarantined: {q['path']!r}: {q['reason']}")


def cmd_watch(args: argparse.Namespace) -> int:
    from vigproc.frontends.daemon import Daemon, configure_logging, read_status

    cfg = _config(args)
    if args.status:
        st = read_status(cfg)
        if args.json:
            print(json.dumps(st, indent=1))
        else:
            _print_status(st)
        return 0 if st["running"] else 3  # LSB: 3 = not running
    configure_logging(cfg.log_json, cfg.log_level)
    cfg.validate()
    _check_settings(cfg)
    return Daemon(cfg).run()


def add_arguments(sp: argparse.ArgumentParser) -> None:
    """``vigproc watch``'s arguments (its summary: :data:`vigproc.frontends.cli.COMMANDS`)."""
    sp.description = ("Watch IN_DIR and process every complete image that appears in it (correct, check or learn), "
                      "exactly once across restarts and crashes. Stop with SIGTERM or Ctrl-C (work in progress is "
                      "finished first).")
    sp.add_argument("in_dir", metavar="IN_DIR", help="folder to watch")
    sp.add_argument("-o", "--output", required=True, metavar="OUT_DIR", help="outputs and JSON sidecars")
    sp.add_argument("--mode", choices=("correct", "check", "learn"), default="correct",
                    help="correct (default), check or learn")
    sp.add_argument("--workers", type=number(1, 1024, integer=True), default=_default_workers(),
                    help=f"worker processes (default: half the cores, here {_default_workers()})")
    sp.add_argument("--poll", type=float, metavar="SECONDS",
                    help="poll the folder every SECONDS instead of native file events (network shares)")
    sp.add_argument("--settle", type=float, default=2.0, metavar="SECONDS",
                    help="a file is complete once its size and mtime were unchanged this long (default 2)")
    sp.add_argument("--journal", metavar="PATH", help="journal database (default OUT_DIR/.vigproc-watch.sqlite)")
    sp.add_argument("--job", help="job name in the journal (default: from the mode and the folders)")
    sp.add_argument("--quarantine", metavar="DIR", help="move files that fail for good here, with a .reason.json")
    sp.add_argument("--archive", metavar="DIR", help="move inputs here once done (mirroring their sub-folders)")
    sp.add_argument("--retry-quarantined", action="store_true", help="try quarantined files once more on start")
    add_processing(sp)
    add_learn(sp, "on in correct mode with --profile auto")
    sp.add_argument("--log-json", action="store_true", help="log JSON lines (one object per event) on stderr")
    sp.add_argument("--status", action="store_true",
                    help="print the status of the daemon on these folders and exit (0 running, 3 not running)")
    sp.add_argument("--json", action="store_true", help="with --status: JSON")
    sp.add_argument("--status-file", metavar="PATH", help="status file the daemon rewrites every second "
                    "(default OUT_DIR/.vigproc-watch-<tag>.status.json, <tag> a short hash of the job)")
    sp.add_argument("--rescan", type=float, default=300.0, metavar="SECONDS",
                    help="full rescan period, for events a file system did not deliver (default 300)")
    sp.add_argument("--timeout", type=float, default=900.0, metavar="SECONDS",
                    help="stop a worker stuck on one file this long (default 900)")
    sp.add_argument("--max-attempts", type=int, default=DEFAULT_MAX_ATTEMPTS, help="quarantine after this many transient failures")
    sp.add_argument("--max-crashes", type=int, default=DEFAULT_MAX_CRASHES,
                    help="quarantine a file that crashed or hung its worker this many times (a kill of the daemon "
                         "itself is not charged to the files in progress)")
    sp.add_argument("--retry-base", type=float, default=DEFAULT_RETRY_BASE, metavar="SECONDS", help="first retry delay (doubles)")
    sp.add_argument("--retry-cap", type=float, default=DEFAULT_RETRY_CAP, metavar="SECONDS", help="longest retry delay")
    sp.add_argument("--min-free", type=number(0, 1e9), default=DEFAULT_MIN_FREE / 1e6, metavar="MB",
                    help="a failure to write an output with less free space than this on the output disk is a full "
                         "disk: the daemon pauses (nothing quarantined) and resumes once the free space has grown "
                         "(default %(default).0f)")
    sp.set_defaults(fn=cmd_watch)
