"""``vigproc hook``: the language-neutral entry point for non-Python hosts.

A host (darktable's Lua, a digiKam script, a shell, any program) runs::

    vigproc hook [--mode correct|check|estimate] [-o OUTDIR] [options] [--request FILE|-] [--] FILES...

and reads **one JSON document on stdout** (nothing else is ever printed there;
messages go to stderr).  File names are taken as they are: pass them as separate
arguments (never through a shell without quoting) after ``--``, or inside the
request.

Request (optional, ``--request FILE``, ``-`` = stdin; UTF-8; values override the
options)::

    {"mode": "check", "output_dir": "/out", "profile": "auto", "profile_db": "/p.sqlite",
     "method": "default", "strength": 1.0, "output_format": "auto", "input_transfer": "auto",
     "unapplied": "skip",
     "files": ["/in/a.jpg",
               {"path": "/in/b.tif", "output": "/out/b-fixed.tif",
                "lens": {"make": "Canon", "model": "Canon EOS 5D", "lens": "EF50mm f/1.8",
                         "focal_mm": 50, "fnumber": 2.8}}]}

``output`` (or ``--output-file PATH`` for a single input) writes that file
exactly, also when nothing is applied (correct mode; no sidecar; its suffix must
match ``output_format``, e.g. ``.tif`` for ``tiff16``; with ``auto`` the suffix picks
the format: ``.jpg``, ``.png``, ``.tif``, ``.exr``); ``lens`` replaces
the lens metadata read from the file (see :func:`vigproc.frontends.api.lens_key`).
With an output folder (``-o`` or ``output_dir``), a relative ``output`` is taken
inside it and no ``output`` may lead out of it (``..``, an absolute path
elsewhere, a symbolic link): that file fails with exit code 2.  ``--output-file``
and an output folder exclude each other.

With ``-o``, outputs are named as in every front end
(:func:`vigproc.pipeline.processor.output_name`): ``a.tif`` gives ``a.corrected.tif`` (``a.tif.
corrected.exr`` when ``output_format`` changes the format; ``auto``: the input's own
kind) and ``a.tif.vigproc.json`` (when nothing is applied, ``unapplied`` says what is
written: by default the original under the output's name); control characters, ``%`` and a leading ``-``
or ``.`` are percent-encoded, and a later input of an earlier one's name gets
``a-2.tif``.  No output ever replaces an
input of the same call: that file fails with exit code 5.

Answer::

    {"protocol": 1, "vigproc": "0.1.0", "mode": "correct", "ok": 1, "failed": 1, "exit_code": 1,
     "results": [{"file": "/in/a.jpg", "status": "ok", "summary": "0.42 EV fall-off removed (...)",
                  "applied": true, "falloff_ev": 0.42, "removed_ev": 0.42, "confidence": 0.97, "verdict": null,
                  "output": "/out/a.corrected.tif", "sidecar": "/out/a.tif.vigproc.json", ...},
                 {"file": "/in/b.tif", "status": "error", "type": "ImageReadError",
                  "exit_code": 4, "error": "..."}]}

Exit codes (:data:`EXIT_CODES`): 0 every file done; 1 some files failed; when
*every* file failed with the same error, that error's code (3 invalid image, 4
unreadable file, 5 output not writable, 6 model, 7 prior, 8 profile store,
11 forensics, 12 plugin, 70 internal); 2 usage (bad options or request: the answer carries only
``error``; for option-parsing errors stdout is empty and the message is on
stderr); 70 an internal error outside any file; 130 interrupted.
"""

from __future__ import annotations

import argparse
import dataclasses
import datetime
import json
import logging
import shutil
import sys
from pathlib import Path
from typing import Any

from vigproc._version import __version__
from vigproc.atomic import publish
from vigproc.errors import EXIT_CODES, OutputSettingsError, VigprocError, one_line, write_error
from vigproc.frontends.commands._options import add_processing, files_exit_code
from vigproc.io.formats import WRITE_EXT_FORMAT, WRITE_SUFFIXES
from vigproc.pipeline.processor import (OUTPUT_FORMATS, SIDECAR_SUFFIX, InputFiles, Processor, Settings, output_folder,
                                        output_stems, safe_output)
from vigproc.scratch import scratch_folder
from vigproc.stores.opening import open_profile_store

log = logging.getLogger(__name__)

#: Version of the request/answer format.
PROTOCOL = 1
#: Modes the hook offers.
HOOK_MODES = ("correct", "check", "estimate")
# exit codes of ``vigproc hook``: vigproc.errors.EXIT_CODES (stable)
#: Largest request accepted (bytes).
MAX_REQUEST_BYTES = 16 * 1024 * 1024
_REQUEST_KEYS = frozenset({"mode", "output_dir", "profile", "profile_db", "method", "strength", "output_format",
                           "input_transfer", "unapplied", "files"})
_FILE_KEYS = frozenset({"path", "output", "lens"})


def _output_suffixes(output_format: str) -> tuple[str, ...]:
    """The suffixes an explicit output file may have for ``output_format`` (``auto``: any
    a writer writes, the file's suffix then says the format)."""
    fixed = OUTPUT_FORMATS[output_format]
    return tuple(WRITE_EXT_FORMAT) if fixed is None else WRITE_SUFFIXES.get(fixed.format, (fixed.suffix,))


class UsageError(VigprocError):
    """The call or request is malformed (exit code 2)."""

    exit_code = 2


# ------------------------------------------------------------------ request
def _read_request(source: str) -> dict[str, Any]:
    try:
        if source == "-":
            data = sys.stdin.buffer.read(MAX_REQUEST_BYTES + 1)
        else:
            with open(source, "rb") as f:
                data = f.read(MAX_REQUEST_BYTES + 1)
    except OSError as exc:
        raise UsageError(f"cannot read the request {source!r}: {exc.strerror or exc}") from None
    if len(data) > MAX_REQUEST_BYTES:
        raise UsageError(f"request larger than {MAX_REQUEST_BYTES} bytes")
    try:
        # surrogateescape: a file name that is not UTF-8 survives as the same bytes
        req = json.loads(data.decode("utf-8", "surrogateescape"))
    except ValueError as exc:
        raise UsageError(f"request is not valid JSON: {exc}") from None
    except RecursionError:  # hostile nesting exhausts the decoder's stack
        raise UsageError("request is not valid JSON: nested too deeply") from None
    if not isinstance(req, dict):
        raise UsageError("request must be a JSON object")
    unknown = set(req) - _REQUEST_KEYS
    if unknown:
        raise UsageError(f"unknown request fields {sorted(unknown)} (known: {', '.join(sorted(_REQUEST_KEYS))})")
    if not isinstance(req.get("files", []), list):
        raise UsageError("request 'files' must be a list")
    for k in ("mode", "output_dir", "profile", "profile_db", "method", "output_format", "input_transfer",
              "unapplied"):
        if k in req and req[k] is not None and not isinstance(req[k], str):
            raise UsageError(f"request '{k}' must be a string")
    if "strength" in req and (isinstance(req["strength"], bool) or not isinstance(req["strength"], (int, float))):
        raise UsageError("request 'strength' must be a number")
    return req


def _job(entry: Any) -> dict[str, Any]:
    """One file of the request as {"path", "output", "lens"}; raises UsageError for a bad entry."""
    if isinstance(entry, str):
        entry = {"path": entry}
    if not isinstance(entry, dict):
        raise UsageError(f"a request file must be a path or an object, got {type(entry).__name__}")
    unknown = set(entry) - _FILE_KEYS
    if unknown:
        raise UsageError(f"unknown file fields {sorted(unknown)} (known: {', '.join(sorted(_FILE_KEYS))})")
    for k in ("path", "output"):
        v = entry.get(k)
        if k == "path" and not (isinstance(v, str) and v):
            raise UsageError("a request file needs a non-empty 'path'")
        if v is not None and (not isinstance(v, str) or "\x00" in v or not v):
            raise UsageError(f"file '{k}' must be a non-empty path without NUL characters")
    return {"path": entry["path"], "output": entry.get("output"), "lens": entry.get("lens")}


def _inside(outdir: Path, output: str) -> Path:
    """Where a file's ``output`` goes with an output folder: relative to it, and never out
    of it (the request comes from a host plugin: ``..``, an absolute path elsewhere or a
    symbolic link must not let it write anywhere else)."""
    target = outdir / output  # an absolute output stays absolute
    try:
        root, parent = outdir.resolve(), target.parent.resolve()
    except (OSError, RuntimeError) as exc:  # e.g. a symbolic link loop
        raise UsageError(f"file 'output' {output!r}: {getattr(exc, 'strerror', None) or exc}") from None
    if target.name in ("", "..") or (parent != root and root not in parent.parents):
        raise UsageError(f"file 'output' {output!r} is not a file inside the output folder {str(outdir)!r}")
    return parent / target.name


class _HostLens:
    """An EXIF reader that answers with the host's lens data where the host gave some."""

    def __init__(self, given: dict[str, Any]) -> None:
        self.given = given  # str(path) -> LensKey
        self._reader = None

    @property
    def exif(self):
        """The ExifTool reader (started on first use): a check's provenance reads the file
        whatever lens the host gave."""
        if self._reader is None:
            from vigproc.io.exif import ExifReader

            self._reader = ExifReader().start()
        return self._reader

    def read(self, path):
        key = self.given.get(str(path))
        if key is None:
            return self.exif.read(path)
        if key.focal_35mm is not None:
            return key
        try:  # the frame's crop factor is the file's: lensfun's ρ and the lens-family prior read it
            return with_files_35mm(key, self.exif.read(path))
        except VigprocError as exc:
            log.debug("%s: no 35-mm focal length from the file: %s", path, exc)
            return key

    def read_tags(self, path, tags):
        """Other tags (in-camera correction flags) from the file itself."""
        return self.exif.read_tags(path, tags)

    def close(self) -> None:
        if self._reader is not None:
            self._reader.close()
            self._reader = None


def with_files_35mm(host, own):
    """The host's lens key with the 35-mm focal length of the file's own EXIF (``own``)
    where the host gave none and the file is the same shot (its camera and focal length):
    hosts send the lens, camera, focal length and f-number, and without the 35-mm focal
    length a frame of a crop mode (a DX crop on an FX body) would be read as the sensor's."""
    same = ((host.make, host.model) == (own.make, own.model) and host.focal_mm is not None
            and own.focal_mm is not None and abs(host.focal_mm - own.focal_mm) <= 0.01 * own.focal_mm)
    if host.focal_35mm is not None or own.focal_35mm is None or not same:
        return host
    return dataclasses.replace(host, focal_35mm=own.focal_35mm)


# ------------------------------------------------------------------ one file
def _process(proc, job: dict[str, Any], outdir: Path | None, stem: str, inputs) -> dict[str, Any]:
    from vigproc.frontends.api import Result

    path = Path(job["path"])
    s = proc.settings
    out: dict[str, Any] = {"file": job["path"], "status": "ok"}
    if job["output"] is not None:
        target = Path(job["output"])
        if s.mode != "correct":
            raise UsageError(f"an output file is only written in correct mode (mode is {s.mode})")
        if target.suffix.lower() not in _output_suffixes(s.output_format):
            raise UsageError(f"output {job['output']!r}: format {s.output_format} writes "
                         f"{' or '.join(_output_suffixes(s.output_format))} files")
        if target.exists() and (target.resolve() == path.resolve() or target in inputs):
            raise OutputSettingsError(f"refusing to overwrite the input {job['output']!r}")
        # the pipeline writes into a private folder beside the target; one rename publishes it
        try:
            work = scratch_folder("hook", target.parent)  # a killed call's folder goes with the next call here
        except OSError as exc:
            raise write_error(f"cannot write beside {job['output']!r}: {exc.strerror or exc}", exc) from None
        try:
            # the host asked for this file: it is written even when nothing is applied
            res = proc.process_file(path, work, "out", unapplied="write", like=target)
            publish(res.output, target)
        finally:
            shutil.rmtree(work, ignore_errors=True)
        out.update(Result.from_frame(res).to_dict(), output=str(target))
        return out
    if outdir is not None:
        res = proc.process_file(path, outdir, stem, protect=inputs)
        out.update(Result.from_frame(res).to_dict(), output=res.output,
                   sidecar=str(safe_output(outdir, stem, SIDECAR_SUFFIX)))
        if "provenance" in res.extra:
            out["provenance"] = res.extra["provenance"]
        if res.picture:
            out["picture"] = res.picture
        return out
    if s.mode == "correct":
        raise UsageError("correct mode needs an output folder (-o) or an output file per input")
    # check/estimate without an output folder: nothing is written, the answer is the result
    res = proc.process_unwritten(path)
    out.update(Result.from_frame(res).to_dict())
    if "provenance" in res.extra:  # check mode: the file's hash, capture date, camera, conflicts
        out["provenance"] = res.extra["provenance"]
    return out


def _error(file: str, exc: BaseException) -> dict[str, Any]:
    if isinstance(exc, VigprocError):
        return {"file": file, "status": "error", "type": type(exc).__name__, "exit_code": exc.exit_code,
                "error": str(exc)}
    return {"file": file, "status": "error", "type": "InternalError", "exit_code": EXIT_CODES["internal"],
            "error": f"internal error ({type(exc).__name__}: {' '.join(str(exc).split())[:300]})"}


def overall_exit_code(results: list[dict[str, Any]]) -> int:
    """0 when every file is done; the shared code when every file failed alike; else 1."""
    return files_exit_code([None if r["status"] == "ok" else r["exit_code"] for r in results])


# ------------------------------------------------------------------ command
def run(args: argparse.Namespace) -> dict[str, Any]:
    """Run a hook call; returns the answer document (see the module docstring)."""
    from vigproc.frontends.api import RequestError, lens_key

    req = _read_request(args.request) if args.request else {}
    opt = {k: getattr(args, k) for k in ("mode", "profile", "profile_db", "method", "strength", "output_format",
                                         "input_transfer", "unapplied")}
    opt["output_dir"] = args.output
    opt.update({k: v for k, v in req.items() if k != "files" and v is not None})
    if opt["mode"] not in HOOK_MODES:
        raise UsageError(f"unknown mode {opt['mode']!r} (choose from {', '.join(HOOK_MODES)})")
    try:
        settings = Settings(mode=opt["mode"], profile=opt["profile"], method=opt["method"],
                            transfer=opt["input_transfer"], output_format=opt["output_format"],
                            strength=float(opt["strength"]), unapplied=opt["unapplied"],
                            in_camera=getattr(args, "in_camera", "respect"))
    except VigprocError as exc:
        raise UsageError(str(exc)) from None
    entries = [*req.get("files", []), *args.files]
    if not entries:
        raise UsageError("no files given (arguments or the request's 'files')")
    if args.output_file is not None:
        if opt["output_dir"]:
            raise UsageError("--output-file and an output folder (-o or the request's 'output_dir') "
                             "cannot be used together")
        if len(entries) != 1:
            raise UsageError(f"--output-file needs exactly one input file, got {len(entries)}")
        e = entries[0]
        if isinstance(e, dict) and e.get("output") is not None:
            raise UsageError("--output-file and the request's 'output' both name the output")
        entries = [{**(e if isinstance(e, dict) else {"path": e}), "output": args.output_file}]
    outdir = output_folder(opt["output_dir"]) if opt["output_dir"] else None

    jobs: list[dict[str, Any]] = []
    given = {}
    for e in entries:
        try:
            j = _job(e)
            if outdir is not None and j["output"] is not None:
                j["output"] = str(_inside(outdir, j["output"]))
            if j["lens"] is not None:
                given[str(Path(j["path"]))] = lens_key(j["lens"])
        except (UsageError, RequestError) as exc:  # a bad entry fails alone
            path = e if isinstance(e, str) else e.get("path") if isinstance(e, dict) else None
            j = {"path": path if isinstance(path, str) else "", "failed": exc}
        jobs.append(j)
    stems = output_stems([Path(j["path"] or "x") for j in jobs])
    inputs = InputFiles(j["path"] for j in jobs if "failed" not in j)  # no output may replace one

    store = None
    if settings.needs_store:  # the hook's modes only read it
        store = open_profile_store(opt["profile_db"])
    reader = _HostLens(given)
    results = []
    try:
        with Processor(settings, store=store, reader=reader) as proc:
            for j, stem in zip(jobs, stems):
                if "failed" in j:
                    results.append(_error(j["path"], j["failed"]))
                    continue
                try:
                    results.append(_process(proc, j, outdir, stem, inputs))
                except KeyboardInterrupt:
                    raise
                except Exception as exc:  # one bad file never stops the others
                    log.debug("hook: %s failed", j["path"], exc_info=True)
                    if not isinstance(exc, VigprocError):
                        log.warning("internal error on %r (rerun with -vv for details)", j["path"])
                    results.append(_error(j["path"], exc))
    finally:
        reader.close()
        if store is not None:
            store.close()
    ok = sum(r["status"] == "ok" for r in results)
    answer = {"protocol": PROTOCOL, "vigproc": __version__, "mode": settings.mode, "ok": ok,
              "failed": len(results) - ok, "exit_code": overall_exit_code(results), "results": results}
    if settings.mode == "check":  # when the verdicts were made, for the host's record
        answer["analysed_utc"] = datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds")
    return answer


def cmd_hook(args: argparse.Namespace) -> int:
    try:
        answer = run(args)
    except VigprocError as exc:
        print(one_line(f"vigproc: {exc}"), file=sys.stderr)
        answer = {"protocol": PROTOCOL, "vigproc": __version__, "error": str(exc), "type": type(exc).__name__,
                  "exit_code": exc.exit_code, "results": []}
    except KeyboardInterrupt:
        raise
    except Exception as exc:
        log.debug("internal error", exc_info=True)
        print(one_line(f"vigproc: internal error ({type(exc).__name__}: {exc}); rerun with -vv for details"),
              file=sys.stderr)
        answer = {"protocol": PROTOCOL, "vigproc": __version__, "error": f"internal error ({type(exc).__name__})",
                  "type": "InternalError", "exit_code": EXIT_CODES["internal"], "results": []}
    for r in answer["results"]:
        if r["status"] != "ok":
            # the error may quote the file name: one line each, whatever the name holds
            print(one_line(f"vigproc: {r['file']!r}: {r['error']}"), file=sys.stderr)
    # ASCII JSON: any host can read it whatever its locale; one document, then a newline
    sys.stdout.write(json.dumps(answer, ensure_ascii=True) + "\n")
    sys.stdout.flush()
    return int(answer["exit_code"])


def add_arguments(sp: argparse.ArgumentParser) -> None:
    """``vigproc hook``'s arguments (its summary: :data:`vigproc.frontends.cli.COMMANDS`)."""
    sp.description = ("Process FILES (and/or the files of a JSON request) and print one JSON answer on "
                      "stdout. Exit codes: 0 ok, 1 some files failed, 2 usage, 3-12 every file failed with "
                      "that error, 70 internal.")
    sp.add_argument("files", nargs="*", help="input images (put them after --)")
    sp.add_argument("--mode", choices=HOOK_MODES, default="correct",
                    help="correct (write corrected images), estimate or check (default %(default)s)")
    sp.add_argument("-o", "--output", help="output folder (corrected images and JSON sidecars)")
    sp.add_argument("--output-file", metavar="PATH",
                    help="correct mode, one input: write the corrected image to exactly PATH (.tif/.tiff "
                         "or .exr as --output-format says; no sidecar); use --output-file=PATH")
    sp.add_argument("--request", metavar="FILE", help="JSON request ('-' reads standard input)")
    add_processing(sp, picture=False)
    sp.set_defaults(fn=cmd_hook, hook_call=True)  # run on the warm server when there is one
