"""``vigproc batch``: a whole archive, resumable, on local cores or a Dask cluster.

The job itself is :mod:`vigproc.frontends.batch`; this module parses options, reads the
optional TOML config file and prints the summary (its benchmark: ``vigproc bench batch``,
in the checkout's ``benchmarks/cli``).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import logging
import os
import sys
from pathlib import Path
from typing import Any

from vigproc.errors import DiskFullError, one_line
from vigproc.frontends.commands._options import add_learn, add_processing, learn_setting, number
from vigproc.pipeline.processor import MODES, Settings
from vigproc.stores.opening import open_profile_store

log = logging.getLogger(__name__)

#: Keys allowed in the ``[batch]`` table of ``--config`` (name -> type).
CONFIG_KEYS: dict[str, type] = {"scheduler": str, "workers": int, "journal": str, "retries": int,
                                "numba_threads": int, "connect_timeout": float, "profile_db": str}


def read_config(path: str | os.PathLike[str]) -> dict[str, Any]:
    """The ``[batch]`` table of a TOML config file, type-checked.

    Raises
    ------
    BatchError
        Unreadable file, TOML syntax error, unknown key or wrong type.
    """
    import tomllib

    from vigproc.frontends.batch import BatchError

    try:
        with open(path, "rb") as fh:
            doc = tomllib.load(fh)
    except OSError as exc:
        raise BatchError(f"cannot read config file {path}: {exc.strerror or exc}") from None
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
        raise BatchError(f"config file {path} is not valid TOML: {exc}") from None
    table = doc.get("batch", {})
    if not isinstance(table, dict):
        raise BatchError(f"config file {path}: [batch] must be a table")
    out: dict[str, Any] = {}
    for k, v in table.items():
        want = CONFIG_KEYS.get(k)
        if want is None:
            raise BatchError(f"config file {path}: unknown key batch.{k} (known: {', '.join(sorted(CONFIG_KEYS))})")
        if want is float and isinstance(v, int) and not isinstance(v, bool):
            v = float(v)
        if not isinstance(v, want) or isinstance(v, bool):
            what = {str: "a string", int: "an integer", float: "a number"}[want]
            raise BatchError(f"config file {path}: batch.{k} must be {what}, got {v!r}")
        out[k] = v
    return out


def _option(args: argparse.Namespace, config: dict[str, Any], name: str, default: Any = None) -> Any:
    v = getattr(args, name, None)
    return v if v is not None else config.get(name, default)


def cmd_batch(args: argparse.Namespace) -> int:
    from vigproc.frontends import backends as BK
    from vigproc.frontends import batch as B

    config = read_config(args.config) if args.config else {}
    learn = learn_setting(args, default=True)
    settings = Settings(mode=args.mode, profile=args.profile, method=args.method, transfer=args.input_transfer,
                        output_format=args.output_format, strength=args.strength, picture=args.picture,
                        unapplied=args.unapplied, in_camera=args.in_camera, learn=learn)
    outdir = Path(args.output).resolve()
    items, missing = B.collect(args.source, outdir)

    profile_file = None
    if settings.profile_is_file:
        from vigproc.stores.profiles import import_profile

        import_profile(settings.profile)  # validate here: one clear error, not one per file
        profile_file = B.Shipped.of(Path(settings.profile).name, Path(settings.profile).read_bytes())
    if settings.mode == "check":
        try:
            from vigproc.forensics.check import default_calibration
        except ImportError:
            raise B.BatchError("check mode is not available in this vigproc installation (no vigproc.forensics.check)") \
                from None
        default_calibration()  # missing: one clear error now, not one per file

    job = B.job_id(args.source, outdir, settings, profile_file.digest if profile_file else None)
    journal = Path(_option(args, config, "journal") or outdir / B.JOURNAL_NAME)
    B.check_local_disk(journal, "journal")

    scheduler = _option(args, config, "scheduler")
    retries = int(_option(args, config, "retries", 2))
    if retries < 0:
        raise B.BatchError(f"retries must be >= 0, got {retries}")
    if scheduler:
        _quiet_dask()
        if args.workers is not None:
            log.warning("--workers is ignored with --scheduler (the cluster decides)")
        client = BK.connect(scheduler, timeout=float(_option(args, config, "connect_timeout", 20.0)))
        backend = BK.dask_backend(client, retries=retries, numba_threads=int(_option(args, config, "numba_threads", 1)),
                                 owns_client=True)
    else:
        backend = BK.local_backend(_option(args, config, "workers"))

    store = snapshot = store_path = None
    client_learns = False
    profile_db = _option(args, config, "profile_db")
    try:
        if settings.needs_store:
            store = open_profile_store(profile_db, write=settings.mode == "learn" or settings.learn)
            fs = B.filesystem_type(store.path) if settings.learn else None
            if fs in B.NETWORK_FS:  # every worker would write it: SQLite's locks need a local disk
                why = f"profile store {store.path} is on a {fs} network filesystem; learning as it goes needs a local disk"
                if args.learn:
                    raise B.BatchError(f"{why} (--profile-db, or --no-learn)")
                log.warning("%s: not learning (pass --profile-db on a local disk)", why)
                settings = dataclasses.replace(settings, learn=False)
            if settings.learn and scheduler:
                # a cluster's workers read a snapshot and what the client hands out; the
                # client pools their frames into the store (its one writer)
                log.info("learning as it goes on a cluster: this client pools every frame into %s", store.path)
                snapshot = B.Shipped.of("profiles.sqlite", B.snapshot_store(store))
                client_learns = True
            elif settings.learn:  # local workers pool into the store itself, and read it as profiles become trusted
                store_path = str(store.path.resolve())
                store.close()
                store = None
            elif store is not None and settings.mode != "learn":  # workers read a snapshot; only learn writes, here
                snapshot = B.Shipped.of("profiles.sqlite", B.snapshot_store(store))
                store.close()
                store = None
            elif store is not None:
                fs = B.filesystem_type(store.path)
                if fs in B.NETWORK_FS:
                    log.warning("profile store %s is on a %s network filesystem; SQLite wants a local disk",
                                store.path, fs)
        # created only now: a bad source, option, cluster or store leaves no empty output folder behind
        try:
            outdir.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise B.BatchError(f"cannot create output folder {outdir}: {exc.strerror or exc}") from None
        spec = B.JobSpec(settings=settings, outdir=str(outdir), numba_threads=getattr(backend, "numba_threads", 1),
                         profile_file=profile_file, store_snapshot=snapshot, store_path=store_path,
                         client_learns=client_learns)
        summary = B.run_batch(items, spec, backend, journal_path=journal, job=job, store=store, retries=retries,
                              missing=missing, progress=None if not args.no_progress else False,
                              retry_quarantined=args.retry_quarantined)
    finally:
        backend.close()  # idempotent: also when the job failed before it started
        if store is not None:
            store.close()
    print_summary(summary, outdir, as_json=args.json)
    if summary.interrupted:
        return 130
    if summary.disk_full is not None:
        raise DiskFullError(f"batch stopped: {summary.disk_full}; {summary.not_started} file(s) not started, none "
                            f"quarantined for it: free space on {outdir} and rerun the same command to resume")
    return 0 if summary.failed == 0 else 1


def _quiet_dask() -> None:
    """dask configures its loggers at INFO (when imported); vigproc's own -v decides
    what is shown."""
    try:
        import distributed  # noqa: F401  (its import sets the levels overridden here)
    except ImportError:
        return
    level = max(logging.WARNING, logging.getLogger().getEffectiveLevel())
    for name in ("distributed", "dask"):
        logging.getLogger(name).setLevel(level)


def print_summary(summary, outdir: Path, *, as_json: bool = False) -> None:
    """The job's summary on stdout (text, or one JSON object)."""
    if as_json:
        d = summary.to_dict()
        d["output"] = str(outdir)
        print(json.dumps(d, indent=1))
        return
    s = summary
    state = "interrupted" if s.interrupted else "finished"
    print(f"vigproc batch {s.mode} {state}: {s.total} files; {s.processed} processed, {s.skipped} done earlier, "
          f"{s.quarantined} failed for good, {s.retry_later} to retry, {s.missing} missing "
          f"in {s.seconds:.1f} s ({s.files_per_second:.2f} files/s) on {s.backend}")
    if s.redone:
        print(f"  {s.redone} done files had lost their outputs: written again")
    if s.resubmitted:
        print(f"  {s.resubmitted} tasks resubmitted after a worker died or a transient failure")
    if s.disk_full is not None:
        print(f"  stopped handing out files: the output disk is full ({s.not_started} not started)")
    if s.sources:
        print("  model source: " + ", ".join(f"{k} {v}" for k, v in sorted(s.sources.items())))
    for key, p in sorted(s.profiles.items()):
        sigma = "±?" if p["field_sigma_ev"] is None else f"±{p['field_sigma_ev']:.3f} EV"
        print(f"  profile {key}: {p['n_frames']} frames, {sigma}, {'trusted' if p['trusted'] else 'learning'}")
    for e in s.errors[:20]:  # names and errors escaped: a file name cannot forge a line
        print(one_line(f"  failed: {e['file']}: {e['error']}"), file=sys.stderr)
    if len(s.errors) > 20 or s.failed > len(s.errors):
        print(f"  ... {s.failed - min(20, len(s.errors))} more failures (see the journal or --json)", file=sys.stderr)
    print(f"outputs in {outdir}; journal {s.journal}" + ("; rerun the same command to resume" if s.interrupted
                                                           or s.retry_later else ""))


def add_arguments(sp: argparse.ArgumentParser) -> None:
    """``vigproc batch``'s arguments (its summary: :data:`vigproc.frontends.cli.COMMANDS`)."""
    sp.description = ("Process every image under DIR (recursive; hidden files skipped) or listed in LIST (one path "
                      "per line, relative to the list's folder). Outputs mirror the input tree under OUT (not DIR "
                      "itself; nothing inside OUT is ever taken as input). Interrupt "
                      "at any time and rerun the same command to resume: done files are not redone.")
    sp.add_argument("source", metavar="DIR|LIST", help="folder of images, or a text file listing them (one per line)")
    sp.add_argument("--mode", choices=MODES, required=True, help="correct, estimate, check or learn")
    sp.add_argument("-o", "--output", required=True, help="output folder (sidecars, corrected images)")
    sp.add_argument("--workers", type=number(1, 1024, integer=True), help="local worker processes (default: all cores)")
    sp.add_argument("--scheduler", help="run on a dask.distributed cluster: tcp://HOST:PORT of its scheduler")
    sp.add_argument("--config", help="TOML file with a [batch] table: scheduler, workers, journal, retries, "
                                     "numba_threads, connect_timeout, profile_db")
    sp.add_argument("--journal", help="journal database (default OUT/.vigproc-batch.sqlite; must be on a local disk)")
    sp.add_argument("--retries", type=int, help="resubmissions of a file whose worker died (default 2)")
    add_processing(sp)
    add_learn(sp, "on with --mode correct and --profile auto")
    sp.add_argument("--json", action="store_true", help="print the summary as JSON")
    sp.add_argument("--no-progress", action="store_true", help="no progress bar even on a terminal")
    sp.add_argument("--retry-quarantined", action="store_true",
                    help="process again the files earlier runs gave up on (after fixing the cause)")
    sp.set_defaults(fn=cmd_batch)
