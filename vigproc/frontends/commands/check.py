"""``vigproc check FILES...``: does each frame's vignetting match the lens its EXIF names?

A DNG that carries its own vignetting calibration (FixVignetteRadial or GainMap opcodes,
:mod:`vigproc.io.dng_vignette`), or a raw file its maker's (Sony's or Fujifilm's tags,
:mod:`vigproc.io.makernotes`), is also compared with it (``embedded`` in the JSON, a second
line in the text output); its verdict counts like the others in the exit code.

Every frame also gets the crop test (:mod:`vigproc.forensics.crops`: is the vignetting centred on
the frame?), as ``crop`` in the JSON and at the end of the frame's line (``crop test:
not-shown-off-centre | off-centre | insufficient-signal``, with the centre, its distance and
its calibrated false-alarm probability; it never says "centred": its power on one frame is low). It is reported, not counted in the exit code: its power on
single natural frames is low (``vigproc bench crops``, docs/benchmarks/forensics.md).

Exit codes (documented in ``vigproc check --help``):

* 0 -- every frame is consistent with its lens;
* :data:`EXIT_INCONSISTENT` (20) -- at least one frame (or pooled group) is inconsistent;
* 1 -- some files could not be checked (and none was inconsistent); when *every* file
  failed with the same error, that error's code (3-12), as ``estimate`` says it;
* :data:`EXIT_UNDECIDED` (21) -- no inconsistency and no error, but some frames got
  "unknown-lens", "insufficient-signal" or "unlike-any-lens" (a fall-off no lens makes:
  the claimed lens is not judged).
"""

from __future__ import annotations

import argparse
import dataclasses
import datetime
import logging
import sys
from pathlib import Path

from vigproc._version import __version__
from vigproc.errors import EXIT_CODES, VigprocError, one_line
from vigproc.io.lensident import display_lens_id
from vigproc.frontends.commands._options import (JSON_HELP, add_method, add_profile_db, add_transfer, failure_record,
                                                 files_exit_code, interrupted, number, print_json_results)
from vigproc.io.provenance import read_provenance
from vigproc.pipeline.processor import InputFiles, Processor, Settings, file_sha256, output_file, read_lens, refuse_input
from vigproc.stores.opening import open_profile_store

log = logging.getLogger(__name__)

#: Exit code when a frame is inconsistent with its claimed lens.
EXIT_INCONSISTENT = EXIT_CODES["inconsistent"]
#: Exit code when nothing is inconsistent but some frames could not be decided.
EXIT_UNDECIDED = EXIT_CODES["undecided"]

_EPILOG = f"""exit codes:
  0   every frame consistent
  {EXIT_INCONSISTENT}  at least one frame (or pooled group) inconsistent
  {EXIT_UNDECIDED}  some frames undecided (unknown lens, insufficient signal, or a fall-off
      unlike any lens's), none inconsistent, no failures
  1   some files failed, none inconsistent (when every file failed alike: that
      error's code, 3-12)"""

_DESCRIPTION = """Estimate each frame's vignetting and compare it with the profile of the lens its
metadata claims (a stored profile, else lensfun) and, for a DNG that carries one, with
its own embedded calibration (FixVignetteRadial/GainMap opcodes): consistent,
inconsistent, unknown-lens, insufficient-signal or unlike-any-lens, with a calibrated
false-alarm probability."""


def add_arguments(sp: argparse.ArgumentParser) -> None:
    """``vigproc check``'s arguments (its summary: :data:`vigproc.frontends.cli.COMMANDS`)."""
    sp.description, sp.epilog, sp.formatter_class = _DESCRIPTION, _EPILOG, argparse.RawDescriptionHelpFormatter
    sp.add_argument("files", nargs="+", metavar="FILE",
                    help="images to check against the lens their EXIF names")
    store = sp.add_mutually_exclusive_group()  # a store that is then not read is a mistake
    add_profile_db(store)
    store.add_argument("--no-store", action="store_true", help="compare with lensfun only, not with stored profiles")
    sp.add_argument("--report", help="write a readable report: PATH.html (self-contained) or PATH.png")
    sp.add_argument("--json", action="store_true", help=JSON_HELP + "; also pooled and counts")
    sp.add_argument("--pool", action="store_true",
                    help="also pool the evidence of all frames that claim the same lens profile")
    sp.add_argument("--calibration", help="a calibration of the check: the lens-family test's ('vigproc bench "
                                          "forensics-clean --calibrate') or the ring test's ('vigproc forensics "
                                          "calibrate'), on photographs like yours (default: the shipped one)")
    sp.add_argument("--alpha", type=number(0.0, 0.5, open_lo=True),
                    help="false-alarm probability below which a frame is inconsistent "
                                                "(default: the calibration's, 0.01 for the shipped one)")
    add_method(sp)
    add_transfer(sp)
    sp.set_defaults(fn=cmd_check)


def _line(name: str, v: dict, crop=None) -> str:
    """One output line per frame: file names and EXIF strings are escaped (a newline in
    a name must not start a line of its own); the crop test's answer at its end."""
    p = v.get("p_false_alarm")
    tail = "" if p is None else f"  p={p:.3g}  D²={v['score']:.2f}"
    crop_tail = f"; crop test: {crop.verdict}: {crop.reason()}" if crop is not None else ""
    lens = display_lens_id(v["lens_id"]) if v.get("lens_id") else "no lens"
    return one_line(f"{name}: {v['verdict']}{tail}  [{lens}] {v['reason']}{crop_tail}")


def _embedded_verdict(path: Path, v, calibration, alpha, reader=None):
    """The frame against its file's own calibration (a DNG's opcodes, else its maker's
    tags), or None when it carries none (or it cannot be read: said as a warning, the
    lens check stands)."""
    from vigproc.forensics.check import check_embedded
    from vigproc.io.makernotes import calibration_for

    cal = calibration_for(path, "auto", reader)
    if cal is None or v.estimate is None:
        return None
    try:
        model = cal.model(v.estimate.width, v.estimate.height)
    except VigprocError as exc:
        log.warning("%s: its embedded calibration is not compared: %s", path, exc)
        return None
    ve = check_embedded(v.estimate, model, calibration=calibration, lens_id=v.lens_id, alpha=alpha,
                        profile=cal.label, grey=bool(v.evidence is not None and v.evidence.grey))
    return dataclasses.replace(ve, confidence=v.confidence, snr=v.snr)  # the frame's one confidence


def run_record(args: argparse.Namespace, calibration, store) -> dict:
    """What an examiner files about the run itself: when (UTC), which vigproc, the command
    line as run, its settings and the references the frames were compared with."""
    from vigproc.forensics.lensmatch import MatchCalibration

    argv = list(getattr(args, "argv", None) or sys.argv[1:])
    alpha = args.alpha if args.alpha is not None else calibration.alpha
    return {
        "analysed_utc": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
        "vigproc": __version__, "argv": ["vigproc", *argv],
        "settings": {"method": args.method, "input_transfer": args.input_transfer, "alpha": alpha,
                     "pool": bool(args.pool)},
        "references": {
            "calibration": {"file": args.calibration or "shipped",
                            "test": "lens-family" if isinstance(calibration, MatchCalibration) else "rings",
                            "source": calibration.source, "frames": calibration.n_frames},
            "profile_store": None if store is None else str(store.path),
            "lensfun": _version_of("lensfunpy")},
    }


def _version_of(package: str) -> str | None:
    from importlib.metadata import PackageNotFoundError, version

    try:
        return f"{package} {version(package)}"
    except PackageNotFoundError:
        return None


def cmd_check(args: argparse.Namespace) -> int:
    from vigproc.forensics.crops import check_crop
    from vigproc.forensics.check import forensic_check, default_calibration, load_calibration, pool_verdicts
    from vigproc.forensics.lensmatch import default_match_calibration
    from vigproc.io.images import read_image

    files = [Path(f) for f in args.files]
    refuse_input(args.report, InputFiles(files))
    output_file(args.report)
    settings = Settings(mode="check", method=args.method, transfer=args.input_transfer)
    # the lens-family test by default (vigproc.forensics.lensmatch); --method X: the ring test made with X
    calibration = load_calibration(args.calibration) if args.calibration else \
        default_match_calibration() if args.method == "default" else default_calibration()
    store = None
    if not args.no_store:
        store = open_profile_store(args.profile_db)  # a store that cannot exist holds no reference
    run = run_record(args, calibration, store)
    results, items, verdicts = [], [], []
    failed = 0
    try:
        with Processor(settings, store=store) as proc:  # one exiftool process for the whole batch
            for f in files:
                try:
                    img, _ = read_image(f, transfer=args.input_transfer)
                    tags = proc.reader.read_file(f)  # one exiftool read: lens, provenance, calibration
                    lens_key, lens = read_lens(tags, f)
                    # the pipeline's check step, with this run's calibration and threshold
                    # the frame's content id: a stored profile that pooled it is no reference
                    fid = file_sha256(f)
                    v = forensic_check(img, lens_key, store=proc.store, method=settings.method,
                                    calibration=calibration, alpha=args.alpha,
                                    frame_id=fid if proc.store is not None else None)
                    prov = read_provenance(f, tags, getattr(lens_key, "problems", ()), sha256=fid)
                except VigprocError as exc:
                    failed += 1
                    results.append(failure_record(f, exc))
                    print(one_line(f"vigproc: {str(f)!r}: {exc}"), file=sys.stderr)
                    continue
                rec = {"file": str(f), "lens": lens, "provenance": prov.to_dict(), **v.to_dict()}
                # is the vignetting centred on the frame? (a crop, a shift, a stitch; Lyu 2010 §5)
                crop = check_crop(img, channel_axis=-1 if img.ndim == 3 else None)
                rec["crop"] = crop.to_dict()
                ve = _embedded_verdict(f, v, calibration, args.alpha, tags)
                if ve is not None:  # disagreeing with its own calibration is evidence too
                    rec["embedded"] = {k: x for k, x in ve.to_dict().items() if k != "estimate"}
                results.append(rec)
                verdicts.append((f, v))
                if args.report:
                    from vigproc.forensics.report import ReportItem, thumbnail

                    items.append(ReportItem(f.name, v, thumbnail(img), prov, crop))
                del img
                if not args.json:
                    print(_line(str(f), rec, crop))
                    if "embedded" in rec:
                        print(_line(f"{f} (against its embedded calibration)", rec["embedded"]))
    except KeyboardInterrupt:  # Ctrl-C: what was checked, in one line; exit 130 (no report of a part)

        found = {}
        for v in (r.get("verdict") for r in results):
            if v is not None:
                found[v] = found.get(v, 0) + 1
        return interrupted("check", ", ".join([f"{n} {k}" for k, n in sorted(found.items())]
                                              + [f"{failed} failed", f"{len(files) - len(results)} not started"]))
    finally:
        if store is not None:
            store.close()
    pooled = []
    if args.pool:
        groups: dict[tuple, list] = {}
        for f, v in verdicts:
            if v.whitened is not None:
                groups.setdefault((v.expected_source, v.profile), []).append(v)
        for (source, profile), vs in sorted(groups.items(), key=lambda kv: str(kv[0])):
            if len(vs) < 2:
                continue
            pv = pool_verdicts(vs, calibration=calibration)
            d = pv.to_dict()
            pooled.append(d)
            if args.report:
                from vigproc.forensics.report import ReportItem

                items.append(ReportItem(f"{len(vs)} frames of {profile}", pv, None))
            if not args.json:
                print(_line(f"pooled, {len(vs)} frames of {profile}", d))
    counts: dict[str, int] = {}
    for r in results + pooled + [r["embedded"] for r in results if "embedded" in r]:
        if "verdict" in r:
            counts[r["verdict"]] = counts.get(r["verdict"], 0) + 1
    if counts.get("inconsistent"):
        code = EXIT_INCONSISTENT
    elif failed:  # every file failed alike: that error's code, as estimate, correct and hook say it; else 1
        code = files_exit_code([r.get("exit_code") for r in results])
    elif counts.get("unknown-lens") or counts.get("insufficient-signal") or counts.get("unlike-any-lens"):
        code = EXIT_UNDECIDED
    else:
        code = 0
    if args.report and items:
        from vigproc.forensics.report import write_report

        # a file given but not checked is part of the record an examiner files, with why
        unchecked = [r["error"] for r in results if "error" in r]
        notes = (f"{len(unchecked)} file(s) given could not be checked: " + "; ".join(unchecked)) if unchecked else ""
        out = write_report(args.report, items, notes=notes, run=run)
        if not args.json:
            print(f"report -> {out}")
    elif args.report:
        print(f"vigproc: no report written to {args.report}: no file could be checked", file=sys.stderr)
    if args.json:
        print_json_results(results, code, pooled=pooled, counts=counts, run=run)
    else:
        summary = ", ".join(f"{n} {k}" for k, n in sorted(counts.items()))
        print(f"{summary}; {failed} failed" if summary else f"{failed} failed")
    return code
