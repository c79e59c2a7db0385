"""The ``vigproc`` command line.

Every user-facing failure is a :class:`~vigproc.errors.VigprocError` turned into one
line on stderr and its exit code; no traceback reaches the user.
"""

from __future__ import annotations

import argparse
import contextlib
import importlib
import io
import json
import logging
import math
import pkgutil
import signal
import sys
import threading
import warnings
from importlib import resources
from pathlib import Path
from typing import Sequence

from vigproc.frontends.commands._options import (JSON_HELP, add_learn, add_method, add_processing, add_transfer, failure_record,
                                                 files_exit_code, interrupted, learn_setting, number, print_json_results)
from vigproc.errors import EXIT_CODES, DiskFullError, VigprocError, one_line
from vigproc.io.lensident import display_lens_id

log = logging.getLogger("vigproc")

from vigproc.pipeline.processor import OUTPUT_FORMATS, images_in as _images_in, output_file  # noqa: E402  (re-exported names)
from vigproc.pipeline.processor import (InputFiles, Processor, Settings, file_sha256, lens_hint,  # noqa: E402
                                        output_folder, output_stems, read_lens)


class _AboveTheBar:
    """A stream whose whole lines are written above a tqdm bar (tqdm.write), so printed
    results and log lines never land on the bar's own line."""

    def __init__(self, target) -> None:
        self.target, self._part = target, ""

    def write(self, text: str) -> int:
        from tqdm import tqdm

        self._part += text
        *lines, self._part = self._part.split("\n")
        for line in lines:
            tqdm.write(line, file=self.target)
        return len(text)

    def flush(self) -> None:
        self.target.flush()

    def isatty(self) -> bool:
        return self.target.isatty()


def _progress(items: Sequence, what: str):
    """A tqdm progress bar on stderr for long interactive runs; the plain items otherwise
    (pipes, logs and --json output stay clean). While the bar shows, whatever the loop
    prints or logs goes above it."""
    if len(items) < 2 or not sys.stderr.isatty():
        yield from items
        return
    from tqdm import tqdm
    from tqdm.contrib.logging import logging_redirect_tqdm

    err = sys.stderr
    with logging_redirect_tqdm(), contextlib.redirect_stdout(_AboveTheBar(sys.stdout)), \
            contextlib.redirect_stderr(_AboveTheBar(err)):
        yield from tqdm(items, desc=what, unit="file", leave=False, file=err)


# ----------------------------------------------------------------- commands
def cmd_estimate(args: argparse.Namespace) -> int:
    """Each file in turn; the exit code is :func:`files_exit_code`'s. ``--json`` prints
    one JSON document at the end, for one file as for many (README, "--json")."""
    Settings(mode="estimate", method=args.method, transfer=args.input_transfer)  # a bad --method: one usage error
    from vigproc.io.exif import ExifReader

    results: list[dict] = []
    codes: list[int | None] = []
    with ExifReader() as reader:  # one exiftool process for all the files
        for f in args.files:
            try:
                results.append(_estimate_file(args, f, reader))
                codes.append(None)
            except VigprocError as exc:  # one line naming the file, as the multi-file commands do
                print(one_line(f"vigproc: {str(f)!r}: {exc}"), file=sys.stderr)
                results.append(failure_record(f, exc))
                codes.append(exc.exit_code)
    code = files_exit_code(codes)
    if args.json:
        print_json_results(results, code)
    return code


def _estimate_file(args: argparse.Namespace, file: str, reader) -> dict:
    from vigproc.core.estimate import estimate
    from vigproc.io.images import EncodedImage, read_encoded
    from vigproc.pipeline.encoded import check_encoded, estimate_encoded

    # RAW: estimate on LibRaw's half-size development (the fast path) and report the
    # model for the full frame; a JPEG's or PNG's codes from a reduced copy; others as they are
    img, info = read_encoded(file, transfer=args.input_transfer, raw_half_size=True)
    reader = reader.read_file(Path(file))  # one exiftool read: the lens and the in-camera flags
    key, lens = read_lens(reader, Path(file))
    if isinstance(img, EncodedImage):
        m = estimate_encoded(check_encoded(img), args.method, hint=lens_hint(key, args.method), seed=args.seed)
    else:
        m = estimate(img, args.method, channel_axis=-1 if img.ndim == 3 else None, seed=args.seed,
                     hint=lens_hint(key, args.method))
    # "applied" says what correct would do: the same harm rules (vigproc.pipeline.guard)
    from vigproc.io.incamera import read_in_camera
    from vigproc.pipeline.guard import guard

    m, refusal = guard(m, "estimate", img, key, clips=info.bit_depth not in ("half", "float", "double"),
                       in_camera=read_in_camera(Path(file), reader), where=str(file))
    cast = _colour_cast(img, m)  # a report only: never applied (colour fields come from flat frames/profiles/DNGs)
    if info.format == "raw":
        m = m.rescale(2 * m.width, 2 * m.height)
    doc = {"file": str(file), "lens": lens, "model": m.to_dict(), "colour_cast": cast,
           **({"not_applied_rule": refusal.rule} if refusal is not None else {})}
    if not args.json:
        q = m.quality
        # the frame the model is for: a RAW's full frame, though estimated at half size
        half = f", estimated on its {info.width}x{info.height} half-size development" if info.format == "raw" else ""
        print(one_line(f"{file}: {m.width}x{m.height} {info.format} ({info.transfer}{half})"))
        print(f"  lens        {display_lens_id(lens['lens_id']) if lens['lens_id'] else 'unknown (' + lens['error'] + ')'}")
        print(f"  method      {m.method}")
        print(f"  centre      ({m.center[0]:.1f}, {m.center[1]:.1f}) px from the frame centre")
        print(f"  P (px^-2)   p1={m.p[0]:.4g} p2={m.p[1]:.4g} p3={m.p[2]:.4g}")
        print(f"  alpha       {', '.join(f'{a:.4g}' for a in m.alpha)}")
        if q is not None and q.fallback and m.candidate is not None:
            # the model is no correction; its quality (and the JSON's field_ev_rms) is the
            # rejected fit's: say that figure, under that name
            print(f"  fall-off    none applied; the rejected fit: {m.candidate.field_ev_rms():.3f} EV RMS over the frame")
        else:
            print(f"  fall-off    {m.field_ev_rms():.3f} EV RMS over the frame")
        if q is not None and m.method in ("robust", "real-lens", "flat-field", "lens-family", "lens-family-off-centre"):
            why = q.reason or ("weak evidence or not a real lens's shape" if m.method == "real-lens" else "weak evidence")
            state = f"NOT applied ({why})" if q.fallback else "applied"
            print(f"  confidence  {q.confidence:.2f} (SNR {q.snr:.1f}, ±{q.field_sigma_ev:.3f} EV): {state}")
        if "delta_e" in cast:
            print(f"  colour cast {'detected' if cast['detected'] else 'not detected'} (corner dE2000 "
                  f"{cast['delta_e']:.1f}, confidence {cast['confidence']:.2f}; reported, not corrected)")
    return doc


def _colour_cast(img, m) -> dict:
    """The frame's colour-cast report (:func:`vigproc.core.colour_cast.detect_colour_cast`)."""
    import numpy as np

    from vigproc.core.colour_cast import detect_colour_cast
    from vigproc.io.images import EncodedImage

    if img.ndim != 3 or img.shape[2] < 3:
        return {"detected": False, "reason": "a grey frame has no colour"}
    from vigproc.core.colour_cast import CastSettings

    usable, settings = None, CastSettings()
    if isinstance(img, EncodedImage):
        long_side = max(img.shape[:2])
        if img.codes.dtype == np.uint8:
            # 8-bit codes quantise the chroma of dark pixels, which pulls the fit towards no
            # cast: each working pixel averages at least 5x5 of them
            settings = CastSettings(work_long_side=int(max(48, min(settings.work_long_side, long_side / 5))))
        img, usable = img.reduced(max(1, long_side // 480))
    return detect_colour_cast(img, luminance_model=m, usable=usable, settings=settings).to_dict()


def _applied_ev(rec: dict) -> float:
    """The fall-off divided out of a corrected frame (the model's, times the strength)."""
    from vigproc.core.model import VignettingModel

    return VignettingModel.from_dict(rec["model"]).field_ev_rms() * rec.get("strength", 1.0)


def _open_store(args: argparse.Namespace):
    from vigproc.stores.opening import open_profile_store

    return open_profile_store(args.profile_db, write=True)


def _as_given(path: str, outdir: Path) -> str:
    """An output's path under ``outdir`` as the user wrote it (``-o out`` prints
    ``out/NAME``, not the absolute path the record keeps)."""
    try:
        return str(outdir / Path(path).relative_to(outdir.resolve()))
    except ValueError:
        return path


def cmd_correct(args: argparse.Namespace) -> int:
    from vigproc.stores.opening import open_profile_store
    from vigproc.pipeline.faults import DISK_FULL, classify_error

    made = not Path(args.output).exists()
    outdir = output_folder(args.output)
    files = [Path(f) for f in args.files]
    inputs = InputFiles(files)  # no output may replace an input of this run
    settings = Settings(mode="correct", profile=args.profile, method=args.method, transfer=args.input_transfer,
                        output_format=args.output_format, picture=args.picture, strength=args.strength,
                        unapplied=args.unapplied, in_camera=getattr(args, "in_camera", "respect"),
                        # a one-off correct learns only into a store it was given (or with --learn)
                        learn=learn_setting(args, default=args.profile_db is not None))
    failed = unapplied = 0
    results = []
    full = None  # the fault of the last failure (vigproc.pipeline.faults)
    if settings.learn:  # it writes: a store that cannot be opened is an error now, not per file
        store = open_profile_store(args.profile_db, write=True)
    else:
        store = open_profile_store(args.profile_db) if settings.needs_store else None  # reads only: may be absent
    try:
        with Processor(settings, store=store) as proc:  # one exiftool process for the whole batch
            for f, stem in _progress(list(zip(files, output_stems(files))), "correcting"):
                try:
                    rec = proc.process_file(f, outdir, stem, protect=inputs).to_dict()
                    results.append(rec)
                    unapplied += not rec.get("applied")
                    if not args.json:
                        lens = display_lens_id(rec["lens"]["lens_id"])
                        if rec.get("applied"):
                            tag = f"{rec['source']}: {_applied_ev(rec):.2f} EV fall-off removed"
                        else:
                            tag = f"not corrected: {rec.get('not_applied', 'nothing applied')}"
                        if rec.get("learned"):  # learning as you go: where the frame went
                            tag += f"; {rec['learned']['summary']}"
                        where = _as_given(rec["output"], outdir) if rec.get("output") else \
                            "no image written (see its .vigproc.json)"
                        print(one_line(f"{f} -> {where}  [{tag}; lens {lens}]"))
                except VigprocError as exc:
                    failed += 1
                    results.append(failure_record(f, exc))
                    print(one_line(f"vigproc: {str(f)!r}: {exc}"), file=sys.stderr)
                    full = classify_error(exc, outdir)
                    if full.kind == DISK_FULL:  # the machine's fault: every further file would fail the same way
                        break
    except KeyboardInterrupt:  # Ctrl-C (SIGTERM alike): what was done, in one line; exit 130 (143)
        return interrupted("correct", f"{len(results) - failed - unapplied} corrected, {unapplied} not corrected, "
                           f"{failed} failed, {len(files) - len(results)} not started; outputs in {outdir}")
    finally:
        if store is not None:
            store.close()
    not_started = len(files) - len(results)
    failed += not_started
    stop = None
    if full is not None and full.kind == DISK_FULL:
        where = outdir if full.disk == "output disk" else f"the {full.disk}"  # a store's disk names its folder
        stop = DiskFullError(f"{full.reason}; stopped with {not_started} file(s) not started: free space on "
                             f"{where} and run again")
        results += [failure_record(f, DiskFullError("not started: the output disk is full")) for f in files[len(results):]]
    if made and failed == len(files):  # nothing written: leave no empty folder behind
        with contextlib.suppress(OSError):
            outdir.rmdir()
    # every file failed alike: that error's code, as estimate, check and hook say it
    code = stop.exit_code if stop is not None else files_exit_code([r.get("exit_code") for r in results])
    if args.json:
        print_json_results(results, code)
    else:
        print(f"{len(files) - failed - unapplied} corrected, {unapplied} not corrected, {failed} failed; "
              + (f"outputs in {outdir}" if failed < len(files) else "nothing written"))
    if stop is not None:
        raise stop
    return code


def cmd_demo(args: argparse.Namespace) -> int:
    """Estimate and correct the bundled sample images with the embedded defaults."""
    samples = resources.files("vigproc.data").joinpath("samples")
    files = sorted(Path(str(samples)).glob("*.jpg"))
    if not files:
        raise VigprocError("the bundled samples are missing from this installation")
    ns = argparse.Namespace(files=[str(f) for f in files], output=args.output, method="default",
                            input_transfer=args.input_transfer, picture=True, json=False,
                            output_format="auto", profile="estimate", profile_db=None,
                            strength=1.0, unapplied="keep", in_camera="respect")
    return cmd_correct(ns)


def cmd_prior_fit(args: argparse.Namespace) -> int:
    from vigproc.io.images import read_image
    from vigproc.core.prior import fit_prior

    output_file(args.output)
    files = _images_in(Path(args.folder), args.limit)

    def images():
        for f in files:
            try:
                yield read_image(f, transfer=args.input_transfer)[0]
            except VigprocError as exc:
                log.warning("skipping %s", exc)

    source = args.source or f"vigproc prior fit {args.folder} --blocks-per-image {args.blocks_per_image} --seed {args.seed}"
    prior = fit_prior(images(), blocks_per_image=args.blocks_per_image, seed=args.seed, source=source)
    prior.save(args.output)
    print(f"fitted on {prior.n_blocks} blocks ({len(files)} images) -> {args.output}")
    return 0


def _fit_falloff(args: argparse.Namespace, what: str, source: str, estimate_with, iterations: int) -> int:
    """Fit a mean fall-off (:func:`vigproc.core.scene.fit_scene_falloff`) on a folder's photos
    in the benchmarks' framing (3:2 landscape, 480x320, linear luminance) and write it."""
    from vigproc.atomic import atomic_write_text
    from vigproc.io.protocol import read_protocol_images
    from vigproc.core.scene import fit_scene_falloff

    output_file(args.output)
    ims = read_protocol_images(_progress(_images_in(Path(args.folder), args.limit), "reading"), args.input_transfer)
    fitted = fit_scene_falloff(ims, estimate_with, iterations=iterations, source=source)
    atomic_write_text(Path(args.output), json.dumps(fitted.to_dict(), indent=1) + "\n")
    print(f"{what} from {fitted.n_images} photos: {fitted.field_ev_rms:.3f} EV RMS, "
          f"photos scatter {fitted.scatter_ev:.3f} EV around it -> {args.output}")
    return 0


def cmd_prior_fit_scene(args: argparse.Namespace) -> int:
    from vigproc.core.estimate import estimate
    from vigproc.core.robust import RobustSettings

    source = (f"vigproc prior fit-scene {args.folder} --iterations {args.iterations} "
              f"--input-transfer {args.input_transfer}")
    return _fit_falloff(args, "scene fall-off", source,
                        lambda im, sc: estimate(im, "robust", channel_axis=None, settings=RobustSettings(scene=sc)),
                        args.iterations)


def cmd_prior_fit_lens_family(args: argparse.Namespace) -> int:
    """The lens family (vigproc.core.lensfamily) from a lensfun database's calibrations."""
    from vigproc.stores.lensfun import lensfun_family

    fam = lensfun_family(n_components=args.components, db_paths=args.db or None)
    fam.save(Path(args.output))
    errs = ", ".join(f"{k + 1}: {e:.4f}" for k, e in enumerate(fam.reconstruction_by_k))
    print(f"wrote {args.output}: {fam.coefficients.shape[0]} calibrations of {fam.lenses} lenses; "
          f"median reconstruction error by components (EV) {errs}")
    return 0


def _profile_line(i: int, p) -> str:
    t = "trusted" if p.trusted else "learning"
    sigma = "±?" if p.field_sigma_ev is None else f"±{p.field_sigma_ev:.3f} EV"
    # the focal lengths the frames were shot at, not the bin's label, once the store knows them
    focal = p.shots.describe_focal() if p.shots is not None else None
    lens = display_lens_id(p.key.lens_id)  # escapes are for storage
    key = str(p.key).replace(p.key.lens_id, lens, 1) if focal is None else f"{lens} @ {focal} {p.key.aperture_bin} {p.key.aspect}"
    return f"[{i}] {key}  frames={p.n_frames}  {sigma}  {t}  ({p.provenance}, updated {p.updated})"


def _pick_profile(store, ident: str):
    """A stored profile by its index in ``profile list``, its exact key text, or its lens
    id (as ``estimate`` and ``check`` print it) when that lens has one profile."""
    from vigproc.stores.profiles import ProfileStoreError

    profiles = store.list()
    if ident.isdigit() and int(ident) < len(profiles):
        return profiles[int(ident)]
    for p in profiles:
        if ident in (str(p.key), _profile_line(0, p).split("] ", 1)[1].split("  ", 1)[0]):
            return p
    of_lens = [p for p in profiles if ident in (p.key.lens_id, display_lens_id(p.key.lens_id))]
    if len(of_lens) == 1:
        return of_lens[0]
    if of_lens:
        keys = "; ".join(str(p.key) for p in of_lens[:5]) + (" …" if len(of_lens) > 5 else "")
        raise ProfileStoreError(f"lens {ident!r} has {len(of_lens)} profiles (focal length, aperture, aspect): "
                                f"name one by its number in 'vigproc profile list' or its key ({keys})")
    raise ProfileStoreError(f"no stored profile {ident!r} (see 'vigproc profile list')")


def _profile_frame(aspect: float, width: int | None, height: int | None) -> tuple[int, int]:
    """The frame a profile is shown for: what is given, the rest from its aspect ratio
    (6000 px on the long side when neither is given)."""
    if width is None and height is None:
        if aspect >= 1:
            width = 6000
        else:
            height = 6000
    if width is None:
        width = max(2, round(height * aspect))
    if height is None:
        height = max(2, round(width / aspect))
    return int(width), int(height)


def _import_lcp(args: argparse.Namespace, store) -> int:
    """``profile import-lcp``: Adobe lens profiles' vignetting into the store (vigproc.stores.lcp)."""
    from vigproc.stores.lcp import import_lcp, lcp_files

    aspect = None
    if args.aspect:
        from vigproc.stores.profiles import _canonical_aspect, _aspect_value

        aspect = _aspect_value(_canonical_aspect(args.aspect, "--aspect"))
    imports, skipped = import_lcp(lcp_files(args.files), camera_model=args.camera_model, lens_id=args.lens_id,
                                  aspect=aspect, include_jpeg=args.include_jpeg)
    if not args.dry_run:
        for imp in imports:
            store.put(imp.profile)
    if args.json:
        print(json.dumps({"imported": [i.to_dict() for i in imports], "skipped": skipped,
                          "stored": not args.dry_run}, indent=1))
    else:
        for imp in imports:
            print(one_line(f"{imp.profile.key}  fit {imp.rms_ev:.1e} EV RMS ({imp.max_ev:.1e} at most), "
                           f"fall-off {imp.falloff_ev:.2f} EV  <- {imp.entry.describe()}"))
        for why in skipped:
            print(one_line(f"skipped: {why}"))
        print(f"{len(imports)} profiles {'found (dry run: nothing stored)' if args.dry_run else 'imported'}, "
              f"{len(skipped)} entries skipped")
    return 0


def cmd_profile(args: argparse.Namespace) -> int:
    from vigproc.stores.profiles import ProfileKey, export_profile

    with _open_store(args) as store:
        if args.profile_command == "list":
            profiles = store.list()
            for i, p in enumerate(profiles):
                print(_profile_line(i, p))
            if not profiles:  # say so: an empty output reads like a failure
                print(f"no profiles in {store.path} (vigproc profile learn FILES..., or import one)")
        elif args.profile_command == "show":
            p = _pick_profile(store, args.id)
            width, height = _profile_frame(p.key.aspect_ratio, args.width, args.height)
            m = p.model(width, height)
            if args.json:  # the profile's record, its model for the frame inside
                sigma = p.field_sigma_ev
                print(json.dumps({
                    "key": str(p.key), "lens_id": p.key.lens_id, "focal_bin": p.key.focal_bin,
                    "aperture_bin": p.key.aperture_bin, "aspect": p.key.aspect, "frames": p.n_frames,
                    "trusted": bool(p.trusted), "field_sigma_ev": sigma if sigma is None or math.isfinite(sigma) else None,
                    "provenance": p.provenance, "updated": p.updated, "width": width, "height": height,
                    "model": m.to_dict()}, indent=1))
            else:
                q = m.quality
                print(_profile_line(0, p).split("] ", 1)[1])
                print(f"  frame       {width}x{height}")
                print(f"  centre      ({m.center[0]:.1f}, {m.center[1]:.1f}) px from the frame centre")
                print(f"  fall-off    {m.field_ev_rms():.3f} EV RMS over the frame"
                      + (f", ±{q.field_sigma_ev:.3f} EV" if q and math.isfinite(q.field_sigma_ev) else ""))
                print("  (--json prints the whole model)")
            if args.plot:
                from vigproc.io.images import write_image
                from vigproc.io.picture import falloff_figure

                write_image(args.plot, falloff_figure(m, title=str(p.key)), bit_depth="uint8", transfer="srgb")
                print(f"picture -> {args.plot}", file=sys.stderr if args.json else sys.stdout)
        elif args.profile_command == "learn":
            from vigproc.io.images import read_image

            files = [Path(f) for f in args.files]
            done = failed = again = 0
            settings = Settings(mode="learn", transfer=args.input_transfer, method=args.method)
            with Processor(settings, store=store) as proc:
                for f in _progress(files, "learning"):
                    try:
                        img, _ = read_image(f, transfer=args.input_transfer)
                        lens_key, lens = read_lens(proc.reader, f)
                        if lens_key is None:
                            raise VigprocError(f"cannot learn, lens unknown ({lens['error']})")
                        # keyed by content: learning a file again does not pool it twice
                        fid = file_sha256(f)
                        key = store.key_for(lens_key, img.shape[1], img.shape[0])
                        known = store.holds_frame(key, fid)
                        proc.process_image(img, lens_key, where=str(f), frame_id=fid)
                        p = store.get(key)
                        done += not known
                        again += known
                        note = "  (this content was already learned: counted once)" if known else ""
                        print(one_line(f"{f} -> {_profile_line(0, p).split('] ', 1)[1]}{note}"))
                    except VigprocError as exc:
                        failed += 1
                        print(one_line(f"vigproc: {str(f)!r}: {exc}"), file=sys.stderr)
            print(f"{done} frame{'' if done == 1 else 's'} learned"
                  + (f", {again} already learned before" if again else "") + f", {failed} failed")
            return 0 if failed == 0 else 1
        elif args.profile_command == "apply":
            p = _pick_profile(store, args.id)
            if not p.trusted:
                raise VigprocError(f"profile {p.key} is not trusted ({p.n_frames} frames): it corrects no series")
            held = store.applied_revision(p.key)
            rev, got = store.apply_revision(p, replaces=held[0] if held is not None else None)
            print(f"profile {p.key}: revision {rev} ({got.n_frames} frames) applied from the next frame on "
                  f"(a new series){'' if held is None or held[0] != rev else '; it was applied already'}")
        elif args.profile_command == "import":
            p = store.import_file(args.file)
            print(f"imported {p.key}")
        elif args.profile_command == "export":
            export_profile(_pick_profile(store, args.id), args.file)
            print(f"exported -> {args.file}")
        elif args.profile_command == "import-lensfun":
            from vigproc.stores.lensfun_io import import_lensfun
            from vigproc.stores.profiles import Profile, aperture_bin, aspect_label, focal_bin, normalise

            m = import_lensfun(args.maker, args.model, args.focal, args.aperture, args.distance,
                               width=args.width, height=args.height, crop_factor=args.crop_factor)
            theta, _, aspect = normalise(m)
            from vigproc.io.exif import casefold_lens_id, escape_key_part

            # escaped as lens ids from EXIF are: a "|" in a name must not forge a component
            lens_id = args.lens_id or f"{escape_key_part(args.maker)}|{escape_key_part(args.model)}"
            key = ProfileKey(casefold_lens_id(lens_id), focal_bin(args.focal), aperture_bin(args.aperture), aspect_label(aspect))
            store.put(Profile(key=key, theta=theta, covariance=None, provenance="lensfun", trusted=True,
                                  notes=f"lensfun {args.maker} {args.model} at {args.focal} mm f/{args.aperture}"))
            print(f"imported from lensfun: {key}")
        elif args.profile_command == "import-lcp":
            return _import_lcp(args, store)
        elif args.profile_command == "export-lensfun":
            from vigproc.stores.lensfun_io import colour_notes, export_lensfun_xml, lensfun_entries

            entries, skipped = lensfun_entries(store.list(), crop_factor=args.crop_factor, mount=args.mount)
            for why in skipped:
                print(one_line(f"vigproc: not exported: {why}"), file=sys.stderr)
            for note in colour_notes(store.list()):
                print(one_line(f"vigproc: note: {note}"), file=sys.stderr)
            n = export_lensfun_xml(entries, args.file)
            print(f"{len(entries)} calibrations of {n} lenses -> {args.file}")
    return 0


# ------------------------------------------------------------------ parser
def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="vigproc", description="Lens vignetting: estimate, correct, learn, check.")
    p.add_argument("-v", "--verbose", action="count", default=0,
                   help="more log output (-v: info, -vv: debug and tracebacks)")
    sub = p.add_subparsers(dest="command", required=True)

    sp = sub.add_parser("estimate", help="estimate the vignetting of images (nothing is written)")
    sp.add_argument("files", nargs="+", metavar="FILE", help="images to estimate")
    add_method(sp)
    sp.add_argument("--json", action="store_true", help=JSON_HELP)
    sp.add_argument("--seed", type=int, default=0, help="random start of --method lyu2010-rand")
    add_transfer(sp)
    sp.set_defaults(fn=cmd_estimate)

    sp = sub.add_parser("correct", help="remove vignetting: a stored profile of the lens, else an estimate "
                                        "(each input's own format back by default)")
    sp.add_argument("files", nargs="+", metavar="FILE", help="images to correct (RAW, TIFF, EXR, JPEG, PNG)")
    sp.add_argument("-o", "--output", required=True, metavar="OUT_DIR",
                    help="folder for the corrected images and their JSON records")
    add_processing(sp)
    add_learn(sp, "on when --profile-db is given and --profile is auto")
    sp.add_argument("--json", action="store_true", help=JSON_HELP)
    sp.set_defaults(fn=cmd_correct)

    sp = sub.add_parser("demo", help="correct the bundled sample images (the README's first command)")
    sp.add_argument("-o", "--output", default="vigproc-demo", metavar="OUT_DIR",
                    help="output folder (default %(default)s)")
    add_transfer(sp)
    sp.set_defaults(fn=cmd_demo)

    # further commands live in their own modules under vigproc/commands (watch, check,
    # batch, hook, ...); each exposes register(subparsers)
    import vigproc.frontends.commands

    command_modules = [importlib.import_module(f"vigproc.frontends.commands.{m.name}")
                       for m in sorted(pkgutil.iter_modules(vigproc.frontends.commands.__path__), key=lambda m: m.name)
                       if not m.name.startswith("_")]
    for mod in command_modules:
        mod.register(sub)

    sp = sub.add_parser("profile", help="the per-lens profile store")
    sp.add_argument("--profile-db", help="profile store (default: $VIGPROC_PROFILE_DB or the user data folder)")
    psub = sp.add_subparsers(dest="profile_command", required=True)
    psub.add_parser("list", help="stored profiles").set_defaults(fn=cmd_profile)
    q = psub.add_parser("show", help="one profile as a model for a frame size, optionally as a picture")
    q.add_argument("id", help="index from 'profile list' or the key text")
    q.add_argument("--width", type=number(2, 1_000_000, integer=True),
                   help="frame width in px the model is shown for (default: 6000 px on the long side, "
                        "the profile's aspect ratio)")
    q.add_argument("--height", type=number(2, 1_000_000, integer=True),
                   help="frame height in px (default: from the width and the profile's aspect ratio)")
    q.add_argument("--plot", help="write a PNG picture of the fall-off")
    q.add_argument("--json", action="store_true", help="print the profile's model as JSON instead of a summary")
    q.set_defaults(fn=cmd_profile)
    q = psub.add_parser("learn", help="estimate frames and pool them into their lenses' profiles")
    q.add_argument("files", nargs="+", metavar="FILE", help="frames of one or more lenses (their EXIF names the lens)")
    add_transfer(q)
    add_method(q)
    q.set_defaults(fn=cmd_profile)
    q = psub.add_parser("apply", help="learning as you go: correct this lens setting's frames with the profile "
                        "as stored now, from the next frame on (a new series; docs/watch.md)")
    q.add_argument("id", help="index from 'profile list' or the key text")
    q.set_defaults(fn=cmd_profile)
    q = psub.add_parser("import", help="import a profile file (profiles/README.md)")
    q.add_argument("file", help="profile file (JSON) to import")
    q.set_defaults(fn=cmd_profile)
    q = psub.add_parser("export", help="export a stored profile to a file")
    q.add_argument("id", help="profile id (see 'vigproc profile list')")
    q.add_argument("file", help="file to write (JSON)")
    q.set_defaults(fn=cmd_profile)
    q = psub.add_parser("import-lensfun", help="store lensfun's calibration of a lens as a profile")
    q.add_argument("maker", help="lens maker as lensfun names it")
    q.add_argument("model", help="lens model as lensfun names it")
    q.add_argument("--focal", type=number(0.0, 10_000.0, open_lo=True), required=True, help="mm")
    q.add_argument("--aperture", type=number(0.0, 1_000.0, open_lo=True), required=True, help="f-number")
    q.add_argument("--distance", type=number(0.0, 1e6, open_lo=True), default=1000.0, help="m (1000: infinity)")
    q.add_argument("--width", type=number(2, 1_000_000, integer=True), default=6000,
                   help="frame width in px the model is made for (default %(default)s)")
    q.add_argument("--height", type=number(2, 1_000_000, integer=True), default=4000,
                   help="frame height in px (default %(default)s)")
    q.add_argument("--lens-id", help="store under this lens id: the 'lens' line that 'vigproc estimate' "
                   "prints for your camera (default: 'maker|model')")
    q.add_argument("--crop-factor", type=number(0.0, 100.0, open_lo=True),
                   help="the camera's crop factor (lenses calibrated on several sensors)")
    q.set_defaults(fn=cmd_profile)
    q = psub.add_parser("import-lcp", help="store the vignetting of Adobe lens profiles (.lcp) as profiles, keyed "
                                           "like the EXIF of the camera and lens they name")
    q.add_argument("files", nargs="+", metavar="FILE", help="LCP files, or folders of them")
    q.add_argument("--camera-model", help="key the profiles for this camera model (files made for a whole make "
                                          "name none)")
    q.add_argument("--lens-id", help="store under this lens id (the 'lens' line 'vigproc estimate' prints) "
                                     "instead of the camera and lens the file names")
    q.add_argument("--aspect", help="aspect ratio of your frames, e.g. 3:2 (default: the calibration images', "
                                    "else 3:2)")
    q.add_argument("--include-jpeg", action="store_true",
                   help="also consider profiles made on the camera's JPEGs where a raw one exists")
    q.add_argument("--dry-run", action="store_true", help="convert and report, store nothing")
    q.add_argument("--json", action="store_true", help="print the conversions as JSON")
    q.set_defaults(fn=cmd_profile)
    q = psub.add_parser("export-lensfun", help="write learned profiles as a lensfun XML database")
    q.add_argument("file", help="lensfun XML file to write")
    q.add_argument("--mount", help="lensfun mount written for cameras lensfun does not know (default Generic)")
    q.add_argument("--crop-factor", type=number(0.0, 100.0, open_lo=True),
                   help="crop factor for cameras neither lensfun nor the frames' EXIF give one for")
    q.set_defaults(fn=cmd_profile)

    sp = sub.add_parser("prior", help="natural-image prior of the paper's method")
    psub = sp.add_subparsers(dest="prior_command", required=True)
    fp = psub.add_parser("fit", help="fit the prior on a folder of vignetting-free images")
    fp.add_argument("folder", help="vignetting-free photographs")
    fp.add_argument("-o", "--output", required=True, help="prior file to write (JSON)")
    fp.add_argument("--blocks-per-image", type=int, default=4, help="random blocks drawn per image (default 4)")
    fp.add_argument("--seed", type=int, default=0, help="seed of the block draw")
    fp.add_argument("--limit", type=int, help="use at most this many images")
    fp.add_argument("--source", help="provenance text stored in the prior")
    add_transfer(fp)
    fp.set_defaults(fn=cmd_prior_fit)
    fp = psub.add_parser("fit-scene", help="fit the scene fall-off prior of the robust estimator on a folder "
                         "of vignetting-free photos")
    fp.add_argument("folder", help="vignetting-free photographs")
    fp.add_argument("-o", "--output", required=True, help="file to write (JSON)")
    fp.add_argument("--iterations", type=int, default=1, help="refits with the prior so far (default 1)")
    fp.add_argument("--limit", type=int, help="use at most this many images")
    add_transfer(fp)
    fp.set_defaults(fn=cmd_prior_fit_scene)
    fp = psub.add_parser("fit-lens-family", help="the family of real lens fall-offs (vigproc/data/lens_family.json) "
                         "from lensfun's calibrations")
    fp.add_argument("-o", "--output", required=True, help="file to write (JSON)")
    fp.add_argument("--components", type=number(1, 8, integer=True), default=3,
                    help="principal components kept (default %(default)s; single frames use the first 2)")
    fp.add_argument("--db", nargs="*", help="lensfun XML files or folders (default: lensfunpy's bundled database)")
    fp.set_defaults(fn=cmd_prior_fit_lens_family)

    sp = sub.add_parser("bench", help="benchmarks (print measured figures)")
    bsub = sp.add_subparsers(dest="bench_command", required=True)
    for mod in command_modules:  # the benchmarks live in the command modules (register_bench is optional)
        if hasattr(mod, "register_bench"):
            mod.register_bench(bsub)
    _list_in_order(bsub, _BENCH_ORDER)
    return p


#: ``vigproc bench --help`` lists these first, in this order (the order users know);
#: the command modules' other benchmarks follow in their registration order.
_BENCH_ORDER = ("synthetic", "lensfun", "clean", "crops", "real", "speed", "scene-scatter", "learn", "io",
                "throughput", "scaling", "memory", "profile", "profile-clean", "profile-interp",
                "profile-flat", "colour", "correct")


def _list_in_order(subparsers, first: Sequence[str]) -> None:
    """Put the subcommands named in ``first`` at the head of ``subparsers``'s help and
    choices, in that order (module discovery registers them by module name)."""
    rank = {name: i for i, name in enumerate(first)}
    key = lambda name: rank.get(name, len(first))  # noqa: E731 - stable sort: the others keep their order
    subparsers._choices_actions.sort(key=lambda a: key(a.dest))  # noqa: SLF001 - argparse keeps its help rows there
    ordered = sorted(subparsers.choices, key=key)
    subparsers.choices.update({name: subparsers.choices.pop(name) for name in ordered})


class _OneLineFormatter(logging.Formatter):
    """Log messages quote file names: one line per message whatever a name holds
    (a traceback at -vv keeps its lines)."""

    def formatMessage(self, record: logging.LogRecord) -> str:
        return one_line(super().formatMessage(record))


@contextlib.contextmanager
def _terminate_like_ctrl_c():
    """SIGTERM (a service manager, ``kill``) stops a command as Ctrl-C does: running
    work is finished or cleaned up (temporary files removed) instead of the process
    vanishing mid-write.  Commands with their own handlers (``watch``) replace it; the
    previous handler is restored on the way out.  Yields a function telling whether
    SIGTERM arrived (exit 143 = 128 + SIGTERM)."""
    got: list[int] = []
    if threading.current_thread() is not threading.main_thread() \
            or signal.getsignal(signal.SIGTERM) is not signal.SIG_DFL:
        yield lambda: False
        return

    def on_term(signum, frame):
        got.append(signum)
        raise KeyboardInterrupt

    signal.signal(signal.SIGTERM, on_term)
    try:
        yield lambda: bool(got)
    finally:
        signal.signal(signal.SIGTERM, signal.SIG_DFL)


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    argv = list(sys.argv[1:] if argv is None else argv)
    args, extra = parser.parse_known_args(argv)
    args.argv = argv  # as run: a report an examiner files states its command line
    if extra:  # said by the command's own parser (its usage line), not the top level's
        _command_parser(parser, args).error(f"unrecognized arguments: {' '.join(extra)}")
    handler = logging.StreamHandler()  # the current sys.stderr (the hook server swaps it per call)
    handler.setFormatter(_OneLineFormatter("%(levelname)s %(name)s: %(message)s"))
    logging.basicConfig(level=logging.WARNING - 10 * min(args.verbose, 2), handlers=[handler], force=True)
    logging.captureWarnings(True)  # libraries' warnings as one log line each, not raw stderr text
    # Ctrl-C reaches the exiftool child too; the reader restarts it when needed, and the
    # "died" warning it gave on closing was noise (with a virtualenv path)
    warnings.filterwarnings("ignore", "ExifTool process was previously running but died", UserWarning)
    if getattr(args, "hook_call", False):
        from vigproc.frontends import hookserver

        if hookserver.enabled() and not hookserver.serving():
            return _hook_via_server(args, argv, hookserver)
    with _terminate_like_ctrl_c() as terminated:
        return _run(args, terminated)


def _command_parser(parser: argparse.ArgumentParser, args: argparse.Namespace) -> argparse.ArgumentParser:
    """The (sub)parser of the command ``args`` are for: ``vigproc profile show``'s, say."""
    for action in parser._actions:  # noqa: SLF001 - argparse keeps its subcommands there
        if isinstance(action, argparse._SubParsersAction):  # noqa: SLF001
            name = getattr(args, action.dest, None)
            if name in action.choices:
                return _command_parser(action.choices[name], args)
    return parser


def _hook_via_server(args: argparse.Namespace, argv: list[str], hookserver) -> int:
    """A host's call: on the warm server when one runs (vigproc.frontends.hookserver), else here,
    starting one for the calls that follow."""
    stdin = None
    if args.request == "-":  # the server cannot read our stdin: pass its bytes (the hook's own limit)
        from vigproc.frontends.commands.hook import MAX_REQUEST_BYTES

        stdin = sys.stdin.buffer.read(MAX_REQUEST_BYTES + 1)
    code = hookserver.call(argv, stdin)
    if code is not None:
        return code
    if stdin is not None:
        sys.stdin = io.TextIOWrapper(io.BytesIO(stdin), encoding="utf-8")
    with _terminate_like_ctrl_c() as terminated:
        code = _run(args, terminated)
    hookserver.start_in_background()
    return code


def _run(args: argparse.Namespace, terminated) -> int:
    try:
        code = int(args.fn(args) or 0)
        return EXIT_CODES["terminated"] if terminated() and code == EXIT_CODES["interrupted"] else code
    except VigprocError as exc:
        print(one_line(f"vigproc: {exc}"), file=sys.stderr)
        return exc.exit_code
    except KeyboardInterrupt:
        print("vigproc: terminated" if terminated() else "vigproc: interrupted", file=sys.stderr)
        return EXIT_CODES["terminated" if terminated() else "interrupted"]
    except BrokenPipeError:  # output piped into e.g. head: nothing left to say
        sys.stderr.close()
        return 0
    except Exception as exc:  # a bug, not bad input: still no traceback unless asked (-vv)
        log.debug("internal error", exc_info=True)
        print(one_line(f"vigproc: internal error ({type(exc).__name__}: {exc}); rerun with -vv for details"),
              file=sys.stderr)
        return 70


if __name__ == "__main__":
    sys.exit(main())
