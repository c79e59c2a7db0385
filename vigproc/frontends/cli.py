"""The ``vigproc`` command line.

Every user-facing failure is a :class:`~vigproc.errors.VigprocError` turned into one
line on stderr and its exit code; no traceback reaches the user.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import logging
import math
import sys
import time
import warnings
from dataclasses import asdict
from importlib import resources
from pathlib import Path
from typing import Sequence

from vigproc.frontends.commands._options import JSON_HELP, failure_record, files_exit_code, print_json_results, write_json_result
from vigproc.errors import EXIT_CODES, DiskFullError, PriorError, VigprocError, one_line
from vigproc.io.lensident import display_lens_id

log = logging.getLogger("vigproc")

from vigproc.pipeline.processor import OUTPUT_FORMATS, images_in as _images_in, output_file  # noqa: E402  (re-exported names)


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
    import contextlib

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
    from vigproc.pipeline.processor import Settings

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
    from vigproc.pipeline.processor import lens_hint, read_lens

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
    from vigproc.frontends.commands._options import interrupted, learn_setting
    from vigproc.stores.opening import open_profile_store
    from vigproc.pipeline.faults import DISK_FULL, classify_error
    from vigproc.pipeline.processor import InputFiles, Processor, Settings, output_folder, output_stems

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


def cmd_bench_scene_scatter(args: argparse.Namespace) -> int:
    """How vignetting-free photographs scatter a frame's data-only lens-family fit
    (vigproc.core.pooling.scene_scatter), from the clean protocol's bases, fitted as the
    profile store fits a frame (its evidence, the profile family)."""
    import numpy as np

    from vigproc.atomic import atomic_write_text
    from vigproc.bench import clean as C
    from vigproc.core.estimate import frame_evidence
    from vigproc.core.lensfamily import profile_family
    from vigproc.core.pooling import frame_fit, scene_scatter_record
    from vigproc.core.robust import evidence_copy

    output_file(args.output)
    bases, names = C.load_clean_bases(args.images, args.min_long_side, args.limit, colour=not args.grey)
    family = profile_family()
    fits = []
    for b, name in zip(bases, names):
        try:
            fits.append(frame_fit(evidence_copy(frame_evidence(b)), family))
        except VigprocError as exc:  # a base with too few usable pixels: leave it out
            log.warning("skipping %s: %s", name, exc)
    record = scene_scatter_record(
        fits, family, source=f"vigproc bench scene-scatter -o FILE ({len(fits)} clean bases, "
                             f"{'luminance' if args.grey else 'colour'}, no field)")
    atomic_write_text(Path(args.output), json.dumps(record) + "\n")
    sd = np.sqrt(np.diag(record["covariance"]))
    print(f"wrote {args.output}: the scatter of {len(fits)} vignetting-free frames' fits; s.d. of the "
          f"{family.n_components} coefficients {', '.join(f'{v:.3f}' for v in sd)}")
    return 0


def _scene_settings(spec: str):
    """RobustSettings for a bench's ``--scene-prior``: "shipped", "none" or a file
    written by ``vigproc prior fit-scene``."""
    from vigproc.core.robust import RobustSettings
    from vigproc.core.scene import SceneFalloff

    if spec == "shipped":
        return RobustSettings()
    if spec == "none":
        return RobustSettings(scene_prior=False)
    try:
        text = Path(spec).read_text()
    except OSError as exc:
        raise PriorError(f"cannot read the scene prior {spec!r}: {exc.strerror or exc}") from exc
    try:
        data = json.loads(text)
    except (json.JSONDecodeError, RecursionError) as exc:  # RecursionError: absurdly nested
        raise PriorError(f"the scene prior {spec!r} is not JSON: {exc}") from exc
    try:
        return RobustSettings(scene=SceneFalloff.from_dict(data))
    except PriorError as exc:
        raise PriorError(f"{spec!r}: {exc}") from exc


def _estimator(method: str, seed: int = 0, settings=None, family=None):
    """A bench's estimator: ``vigproc.estimate`` on a frame (H×W grey, or H×W×3 with
    channels last), or the "rgs" peer (on its luminance).

    ``settings`` (``--scene-prior``) tune the robust Kang-Weiss estimators; the
    default and lens-family estimators have no scene prior. ``family``: the lens
    family they fit in (a bench whose fields are lensfun lenses leaves them out); they
    also take ``hint=`` (EXIF's focal length and f-number).
    """
    from vigproc.core.estimate import HINT_METHODS, estimate, estimate_checked
    from vigproc.core.pixels import luminance

    if method == "rgs":
        from vigproc.bench.peers import estimate_rgs

        return lambda v: estimate_rgs(luminance(v))
    if method in HINT_METHODS:
        # the product's own path (clipped highlights masked, colour read), in ``family``; a
        # bench's frames are float, channels last: what check_image would hand on
        return lambda v, hint=None: estimate_checked(v, method, hint=hint, family=family)
    return lambda v: estimate(v, method, channel_axis=-1 if v.ndim == 3 else None, seed=seed, settings=settings)


def cmd_bench_synthetic(args: argparse.Namespace) -> int:
    from vigproc.bench import synthetic as S
    from vigproc.io.images import read_image

    settings = _scene_settings(args.scene_prior)
    output_file(args.json)
    files = _images_in(Path(args.images), args.limit)
    ims = [S.protocol_image(read_image(f, transfer=args.input_transfer)[0], args.colour) for f in files]
    order = ("ga", "lyu2010-rand", "lyu2010", "robust", "lens-family", "default", "rgs")
    chosen = {k: _estimator(k, settings=settings) for k in order if k in args.methods}
    for fn in chosen.values():  # JIT warm-up outside the timings
        fn(ims[0])
    print(f"Lyu 2010 synthetic protocol: {len(ims)} images from {args.images}, "
          f"{'8-bit quantised' if args.quantize else 'float'}, input transfer {args.input_transfer}, "
          f"scene prior {args.scene_prior}")
    print(S.HEADER)
    rows = S.run(ims, chosen, quantize=args.quantize, progress=print)
    if args.json:
        meta = {"images": str(args.images), "n": len(ims), "quantize": args.quantize,
                "input_transfer": args.input_transfer, "scene_prior": args.scene_prior}
        S.write_json(rows, Path(args.json), meta)
    return 0


def cmd_bench_lensfun(args: argparse.Namespace) -> int:
    from vigproc.bench import lensfun as B
    from vigproc.bench.synthetic import protocol_image
    from vigproc.io.images import read_image

    settings = _scene_settings(args.scene_prior)
    output_file(args.json)
    files = _images_in(Path(args.images), args.limit)
    ims = [protocol_image(read_image(f, transfer=args.input_transfer)[0], args.colour) for f in files]
    results = []
    print(f"lensfun protocol: {args.lenses} lenses x {args.frames_per_lens} frames from {len(ims)} images "
          f"(input transfer {args.input_transfer}, 480x320, scene prior {args.scene_prior}); "
          "RMS of log2(estimated/true field)")
    print(f"{'method':<14}{'frames':>7}{'median EV':>11}{'p90 EV':>9}{'uncorr EV':>11}{'gain-free':>11}"
          f"{'uncorr gf':>11}{'differ. EV':>12}{'fallbk':>8}{'s/img':>8}")
    from vigproc.core.lensfamily import PROFILE_COMPONENTS
    from vigproc.stores.lensfun import lensfun_family
    from vigproc.stores.lensfun import bench_lenses

    # the lens-family fits never hold the lens they are scored on
    family = lensfun_family(exclude={(lens.maker, lens.model) for lens, _ in bench_lenses(args.lenses)},
                            n_components=PROFILE_COMPONENTS)
    for name in args.methods:
        fn = _estimator(name, settings=settings, family=family)
        fn(ims[0])
        r = B.run_lensfun(ims, name, fn, args.lenses, args.frames_per_lens)
        results.append(asdict(r))
        print(f"{r.method:<14}{r.n_frames:>7}{r.median_ev:>11.3f}{r.p90_ev:>9.3f}{r.uncorrected_median_ev:>11.3f}"
              f"{r.gain_free_median_ev:>11.3f}{r.gain_free_uncorrected_ev:>11.3f}"
              f"{r.differential_median_ev:>12.3f}{r.fallbacks:>8}{r.seconds_per_image:>8.3f}")
    print("do no harm (same images, no vignetting): RMS log2 of the applied field")
    print(f"{'method':<14}{'frames':>7}{'median EV':>11}{'worst EV':>10}{'cand. med':>11}{'fallbk':>8}")
    for name in args.methods:
        r = B.run_flat(ims, name, _estimator(name, settings=settings, family=family))
        results.append(asdict(r))
        print(f"{r.method:<14}{r.n_frames:>7}{r.median_ev:>11.3f}{r.worst_ev:>10.3f}{r.candidate_median_ev:>11.3f}{r.fallbacks:>8}")
    write_json_result(args.json, results)
    return 0


def cmd_bench_clean(args: argparse.Namespace) -> int:
    """Vignetting-free bases × lensfun and Table 1 fields, every method side by side."""
    import os

    from vigproc.bench import clean as C
    from vigproc.bench.peers import PEER_ENV, published_rgs
    from vigproc.core.lensfamily import PROFILE_COMPONENTS
    from vigproc.core.pixels import luminance
    from vigproc.stores.lensfun import lensfun_family

    output_file(args.json)
    bases, names = C.load_clean_bases(args.images, args.min_long_side, args.limit, args.crop, colour=not args.grey)
    if len(bases) < 2:
        print(f"vigproc: bench clean: {len(bases)} usable frames under {' '.join(args.images)}; need 2",
              file=sys.stderr)
        return 2
    lens, excluded = C.lens_fields(args.lenses)
    # never the lens an estimate is scored on; all the components a colour frame's fit uses
    family = lensfun_family(exclude=excluded, n_components=PROFILE_COMPONENTS)
    if args.base_falloff and (args.calibrate or args.no_table1):
        print("vigproc: bench clean: --base-falloff scores Table 1's fields; not with --calibrate or --no-table1",
              file=sys.stderr)
        return 2
    if args.base_falloff:  # the bases' own fall-off is then part of what is scored against
        bases = [C.vignetted(b, lens[i % len(lens)].log_field) for i, b in enumerate(bases)]
    if args.calibrate:
        cal = C.calibrate_sigma(bases, lens, family)
        print(f"lens-family sigma = hypot({cal.scale:g} x jackknife sigma, {cal.floor:g} EV), fitted on "
              f"{cal.n_frames // 2} frames (even bases x {len(lens)} lenses + none): within 1 sigma "
              f"{cal.train_within_1sigma:.2f}, 2 sigma {cal.train_within_2sigma:.2f}; on the other half: "
              f"{cal.test_within_1sigma:.2f}, {cal.test_within_2sigma:.2f}")
        return 0
    peer = args.peer or os.environ.get(PEER_ENV)
    methods = {}
    for name in args.methods:
        if name in ("rgs-c++", "rgs-c++-srgb"):
            if not peer:
                print(f"vigproc: bench clean: skipping {name}: no peer built (scripts/build_rgs_peer.sh; "
                      f"--peer or ${PEER_ENV})", file=sys.stderr)
                continue
            rgs = published_rgs(peer, "srgb" if name.endswith("srgb") else "linear")
            methods[name] = lambda v, f=None, rgs=rgs: rgs(luminance(v), f)  # it reads grey
        elif name.endswith("+exif"):  # told the field's focal length and f-number, as EXIF would
            base = name[: -len("+exif")]
            methods[name] = C.model_estimator(_estimator(base, family=family), exif=True)
        else:
            methods[name] = C.model_estimator(_estimator(name, family=family))
    print(f"clean protocol: {len(bases)} central {args.crop:.0%} crops (480x320, "
          f"{'luminance' if args.grey else 'colour'}, linear{', each with a test lens fall-off' if args.base_falloff else ''}) of frames >= "
          f"{args.min_long_side} px from {' '.join(args.images)}; error = RMS of log2(estimated/true) "
          "about its mean (EV); median per field, then median / p90 over fields")
    print(f"lens family for lens-family: {family.lenses} lensfun lenses, the {len(lens)} test lenses left out")
    head = (f"{'method':<18}{'fields':<9}{'median EV':>10}{'p90 EV':>8}{'frames med':>11}{'uncorr':>8}"
            f"{'<=1sd':>7}{'<=2sd':>7}{'fallbk':>8}{'ms/frame':>10}{'PSNR dB':>9}")
    results = []
    groups = ([] if args.base_falloff else [("lensfun", lens)]) + ([] if args.no_table1 else
                                    [(f"table1-{i + 1}", [f]) for i, f in enumerate(C.table1_fields())])
    print(head)
    for name, fn in methods.items():
        fn(bases[0], None)  # JIT warm-up outside the timings
        for label, fields in groups:
            r = C.run_fields(bases, name, fn, fields, label)
            results.append(asdict(r))
            print(f"{r.method:<18}{r.fields:<9}{r.median_ev:>10.3f}{r.p90_ev:>8.3f}{r.frame_median_ev:>11.3f}"
                  f"{r.uncorrected_ev:>8.3f}{r.within_1sigma:>7.2f}{r.within_2sigma:>7.2f}{r.fallbacks:>8}"
                  f"{r.ms_per_frame:>10.1f}{r.psnr_db:>9.2f}", flush=True)
    print("no harm (the same crops, no vignetting): RMS of log2 of the applied field about its mean")
    print(f"{'method':<18}{'frames':>7}{'median EV':>11}{'worst EV':>10}{'fallbk':>8}")
    for name, fn in methods.items():
        r = C.run_harm(bases, name, fn)
        results.append(asdict(r))
        print(f"{r.method:<18}{r.n_frames:>7}{r.median_ev:>11.3f}{r.worst_ev:>10.3f}{r.fallbacks:>8}")
    write_json_result(args.json, {"bases": names, "results": results})
    return 0


def cmd_bench_crops(args: argparse.Namespace) -> int:
    """The crop test's AUC by fall-off and offset, its false alarms and power, on clean bases."""
    import numpy as np

    from vigproc.bench import clean as C
    from vigproc.bench import crops as K
    from vigproc.stores.lensfun import lensfun_family
    from vigproc.stores.lensfun import bench_lenses

    if args.calibrate and args.statistic != "shift":
        print("vigproc: bench crops: --calibrate writes the test's own null: it needs --statistic shift",
              file=sys.stderr)
        return 2
    output_file(args.json)
    if args.calibrate:
        output_file(args.calibrate)
    bases, _ = C.load_clean_bases(args.images, args.min_long_side, args.limit, colour=not args.grey)
    if len(bases) < 4:
        print(f"vigproc: bench crops: {len(bases)} usable frames; need 4", file=sys.stderr)
        return 2
    chosen = bench_lenses(args.lenses)
    family = lensfun_family(exclude={(lens.maker, lens.model) for lens, _ in chosen})
    r = K.run(bases, [(pa.k1, pa.k2, pa.k3) for _, pa in chosen], family, alpha=args.alpha,
              statistic=args.statistic)
    print(f"crop test on {r.n_bases} clean bases x {r.n_lenses} lensfun lens shapes (480x320, {'luminance' if args.grey else 'colour'}, linear); "
          f"statistic: {args.statistic} of the free-centre fit's centre; {r.ms_per_frame:.1f} ms/frame")
    print("AUC (cropped vs uncropped frames of the same fall-off):")
    print(f"{'corner fall-off':<18}" + "".join(f"{f'offset {o:.0%}':>14}" for o in K.OFFSETS))
    for ev in K.FALLOFFS_EV:
        print(f"{f'{ev:g} EV':<18}" + "".join(f"{r.auc[f'{ev:g}EV/{o:.0%}']:>14.3f}" for o in K.OFFSETS))
    print(f"calibrated on the even bases, checked on the odd ones, at alpha {r.alpha:g}:")
    print(f"{'corner fall-off':<18}{'false alarms':>14}" + "".join(f"{f'found {o:.0%}':>12}" for o in K.OFFSETS))
    for ev in K.FALLOFFS_EV:
        print(f"{f'{ev:g} EV':<18}{r.false_alarm[f'{ev:g}EV']:>14.3f}"
              + "".join(f"{r.power[f'{ev:g}EV/{o:.0%}']:>12.2f}" for o in K.OFFSETS))
    if args.calibrate:
        from vigproc.forensics.crops import CropCalibration

        CropCalibration(np.asarray(r.null_z), f"vigproc bench crops: {r.n_bases} clean bases x {r.n_lenses} "
                        f"lenses x {len(K.FALLOFFS_EV)} fall-offs, uncropped").save(args.calibrate)
        print(f"calibration ({len(r.null_z)} uncropped frames) written to {args.calibrate}")
    write_json_result(args.json, asdict(r))
    return 0


def cmd_bench_real(args: argparse.Namespace) -> int:
    """Photographs vignetted by others: pairs with a known field, and real lenses."""
    import numpy as np

    from vigproc.bench import real as R
    from vigproc.core.pixels import luminance
    from vigproc.io.images import read_image
    from vigproc.pipeline.processor import IMAGE_SUFFIXES

    settings = _scene_settings(args.scene_prior)
    output_file(args.json)
    pairs, photos = R.find_inputs(Path(args.images), IMAGE_SUFFIXES)
    if not pairs and not photos:
        raise VigprocError(f"no images in {args.images}")

    def lum(f: Path):
        return luminance(read_image(f, transfer=args.input_transfer)[0])

    results: list[dict] = []
    print(f"{len(pairs)} pairs and {len(photos)} photographs from {args.images} (input transfer "
          f"{args.input_transfer}, full frames, scene prior {args.scene_prior})")
    fns = {name: _estimator(name, settings=settings) for name in args.methods}
    if pairs:
        print(f"pairs: gain-free RMS of log2(estimated/true field) over {R.BLOCK}px blocks, EV")
        print(f"{'pair':<22}{'true corner':>12}{'uncorr':>8}" + "".join(f"{m:>12}" for m in args.methods))
        errs: dict[str, list[float]] = {m: [] for m in args.methods}
        unc = []
        for v, c in pairs:
            try:
                lv, lc = lum(v), lum(c)
            except VigprocError as exc:
                log.warning("skipping %s", exc)
                continue
            rows = [R.run_pair(lv, lc, v.stem, m, fns[m]) for m in args.methods]
            results.extend(asdict(r) for r in rows)
            unc.append(rows[0].uncorrected_ev)
            for r in rows:
                errs[r.method].append(r.error_ev)
            print(f"{v.stem:<22}{rows[0].true_corner_ev:>12.2f}{rows[0].uncorrected_ev:>8.3f}"
                  + "".join(f"{r.error_ev:>11.3f}{'*' if r.fallback else ' '}" for r in rows))
        print(f"{'median':<22}{'':>12}{np.median(unc):>8.3f}" + "".join(f"{np.median(errs[m]):>11.3f} " for m in args.methods))
        print("(* fell back to no correction)")
    if photos:
        print("photographs with real vignetting: corner fall-off applied (log2 at the frame corners; "
              "'-' = no correction) and the crude corner-minus-centre log2 luminance")
        print(f"{'photograph':<22}{'crude':>8}" + "".join(f"{m:>12}" for m in args.methods))
        corrected = {m: 0 for m in args.methods}
        n = 0
        for f in photos:
            try:
                lf = lum(f)
            except VigprocError as exc:
                log.warning("skipping %s", exc)
                continue
            rows = [R.run_photo(lf, f.stem, m, fns[m]) for m in args.methods]
            results.extend(asdict(r) for r in rows)
            n += 1
            for r in rows:
                corrected[r.method] += r.corrected
            print(f"{f.stem:<22}{rows[0].crude_corner_ev:>8.2f}"
                  + "".join(f"{r.corner_ev:>12.2f}" if r.corrected else f"{'-':>12}" for r in rows))
        print(f"{'corrected':<22}{'':>8}" + "".join(f"{f'{corrected[m]}/{n}':>12}" for m in args.methods))
    write_json_result(args.json, results)
    return 0


def cmd_bench_speed(args: argparse.Namespace) -> int:
    """Per-image estimation time on 480×320 protocol frames (Table 1 setting 2)."""
    import numpy as np

    from vigproc.bench.synthetic import protocol_image, table1_model
    from vigproc.core.estimate import estimate
    from vigproc.io.images import read_image

    if args.api:
        return _bench_speed_api(args)
    folder = Path(args.images) if args.images else Path(str(resources.files("vigproc.data").joinpath("samples")))
    files = _images_in(folder, args.limit)
    phi = table1_model(2).field()
    frames = [protocol_image(read_image(f, transfer=args.input_transfer)[0]) * phi for f in files]
    print(f"{len(frames)} frames of 480x320 from {folder}, {args.repeat} rounds, one thread")
    for method in args.methods:
        estimate(frames[0], method, channel_axis=None)  # JIT warm-up
        ts = []
        for _ in range(args.repeat):
            for fr in frames:
                t0 = time.perf_counter()
                estimate(fr, method, channel_axis=None)
                ts.append(time.perf_counter() - t0)
        print(f"{method:<14} median {1000 * np.median(ts):8.2f} ms  p90 {1000 * np.percentile(ts, 90):8.2f} ms")
    return 0


def _bench_speed_api(args: argparse.Namespace) -> int:
    """``bench speed --api``: vigproc.estimate on clean-protocol crops beside the published peer."""
    from vigproc.bench.api_speed import api_speed
    from vigproc.bench.clean import load_clean_bases
    from vigproc.bench.peers import PEER_ENV, published_rgs

    if not args.images:
        print("vigproc: bench speed --api: give --images (full-size camera frames, e.g. ../shared/data/jpeg_exif)",
              file=sys.stderr)
        return 2
    bases, _ = load_clean_bases([args.images], limit=args.limit, colour=True)
    if not bases:
        print(f"vigproc: bench speed --api: no frame of at least 1000 px in {args.images}", file=sys.stderr)
        return 2
    exe = args.peer or os.environ.get(PEER_ENV)
    r = api_speed(bases, published_rgs(exe) if exe else None, rounds=args.repeat)
    print(f"vigproc.estimate on {r.n_frames} central crops (480x320, colour, linear) of {args.images}, "
          f"{r.rounds} rounds" + (f", interleaved with the published peer {exe}" if exe else " (no peer: --peer or "
                                  f"${PEER_ENV})"))
    if exe:
        print(f"peer floor (process start and file I/O, a 16x16 frame): {r.peer_floor_ms:.1f} ms, "
              f"{r.peer_floor_cpu_ms:.1f} ms CPU")
    print(f"{'case':<10}{'vigproc ms':>12}{'peer ms':>10}{'ratio':>8}{'net':>8}{'vigproc CPU':>13}{'peer CPU':>10}"
          f"{'ratio':>8}{'fall-backs':>12}{'off-centre':>12}")
    for c in r.cases:
        print(f"{c.case:<10}{c.vigproc_ms:>12.1f}{c.peer_ms:>10.1f}{c.ratio:>8.2f}{c.ratio_net:>8.2f}"
              f"{c.vigproc_cpu_ms:>13.1f}{c.peer_cpu_ms:>10.1f}{c.ratio_cpu:>8.2f}{c.fallbacks:>12}{c.off_centre:>12}")
    print("medians (ms); ratio: vigproc / peer; net: vigproc / (peer - its floor); CPU: process time (the peer's "
          "child process by getrusage), first-round fall-backs and off-centre fits of the frames")
    return 0


def cmd_bench_learn(args: argparse.Namespace) -> int:
    """Learning one more frame into a profile, warm and in a new process."""
    import numpy as np

    from vigproc.bench.learn import learn_speed
    from vigproc.io.protocol import read_protocol_images, vignetted
    from vigproc.stores.lensfun import bench_lenses, pa_field

    folder = Path(args.images) if args.images else Path(str(resources.files("vigproc.data").joinpath("samples")))
    ims = read_protocol_images(_images_in(folder, args.limit), args.input_transfer, colour=True)
    if not ims:
        print(f"vigproc: bench learn: no readable images in {folder}", file=sys.stderr)
        return 2
    lens, pa = bench_lenses(1)[0]
    log_field = np.log(pa_field(ims[0].shape[:2], pa.k1, pa.k2, pa.k3))
    frames = [vignetted(im, log_field) for im in ims]
    r = learn_speed(frames, stored=args.stored, rounds=args.rounds)
    print(f"{len(ims)} photographs from {folder} x {lens.maker} {lens.model} (lensfun); a profile of "
          f"{r.stored} frames learns one more, {r.rounds} rounds")
    print(f"{'warm process':<34} median {r.warm_ms:8.1f} ms")
    print(f"{'new process, the learn':<34} median {r.new_process_learn_ms:8.1f} ms  (largest "
          f"{r.new_process_learn_ms_max:.1f} ms)")
    print(f"{'new process, its imports':<34} median {r.new_process_import_ms:8.1f} ms")
    write_json_result(args.json, asdict(r))
    return 0


def cmd_bench_correct(args: argparse.Namespace) -> int:
    """Full-resolution correction against a plain copy and a numpy divide, in one run."""
    import numpy as np

    import numba

    from vigproc.bench.synthetic import table1_model
    from vigproc.core.correct import correct, gain_step
    from vigproc.stores.lensfun import bench_lenses
    from vigproc.stores.lensfun_io import kw_from_pa

    h, w = args.height, args.width
    img = np.random.default_rng(0).random((h, w, 3), dtype=np.float32)
    out = np.empty_like(img)
    lens, pa = bench_lenses(1)[0]
    fields = [
        (f"real lens ({lens.maker} {lens.model}, lensfun)", kw_from_pa(pa.k1, pa.k2, pa.k3, w, h)),
        ("Lyu Table 1 setting 2 (extreme)", table1_model(2).rescale(480, round(480 * h / w))),
    ]
    print(f"{w}x{h} RGB float32 ({img.nbytes / 1e6:.0f} MB), median of {args.repeat} after warm-up, "
          f"{numba.get_num_threads()} threads")

    def timed(fn) -> float:
        fn()
        ts = []
        for _ in range(args.repeat):
            t0 = time.perf_counter()
            fn()
            ts.append(time.perf_counter() - t0)
        return 1000 * float(np.median(ts))

    base = timed(lambda: np.copyto(out, img))
    print(f"{'copy (memory floor)':<50}{base:>9.1f} ms {1.0:>6.2f}x copy")
    for label, model in fields:
        field = model.field((h, w)).astype(np.float32)
        rows = [
            ("numpy divide by precomputed field", lambda: np.divide(img, field[..., None], out=out)),
            ("vigproc.correct, field on the fly", lambda: correct(img, model, out=out)),
            ("vigproc.correct, new output array", lambda: correct(img, model)),
        ]
        print(f"{label}: gain step {gain_step(model.rescale(w, h), w, h)} px")
        for name, fn in rows:
            ms = timed(fn)
            print(f"  {name:<48}{ms:>9.1f} ms {ms / base:>6.2f}x copy")
    return 0


def cmd_bench_profile(args: argparse.Namespace) -> int:
    """Profile accuracy after 1, 5, 20 frames of real lens fields, per pooling method."""
    from vigproc.bench import profile as B
    from vigproc.bench.synthetic import protocol_image
    from vigproc.io.images import read_image

    files = _images_in(Path(args.images), args.limit)
    if len(files) < max(args.counts):
        # a lens would see an image twice, and the store learns a repeated frame once
        print(f"vigproc: bench profile: {max(args.counts)} frames per lens need at least as many images; "
              f"{args.images!r} has {len(files)}", file=sys.stderr)
        return EXIT_CODES["usage"]
    ims = [protocol_image(read_image(f, transfer=args.input_transfer)[0]) for f in files]
    fn = _estimator("robust")  # the estimator whose fits the profile store pools (frame evidence)
    fn(ims[0])
    from vigproc.core.robust import estimate_robust_joint

    joint = None if args.no_joint else estimate_robust_joint
    rows, trust = B.run(ims, fn, args.lenses, args.counts, joint=joint, store=True)
    print(f"profile accuracy: {args.lenses} lensfun lenses, frames from {len(ims)} images (480x320); "
          "RMS of log2(pooled/true field)")
    print(f"{'pooling':<14}{'frames':>7}{'lenses':>8}{'median EV':>11}{'p90 EV':>9}")
    for r in rows:
        print(f"{r.pooling:<14}{r.n_frames:>7}{r.n_lenses:>8}{r.median_ev:>11.3f}{r.p90_ev:>9.3f}")
    print(f"trusted store profiles: {trust.n_trusted}/{trust.n_lenses} lenses within {trust.max_frames} frames, "
          f"after a median {trust.median_frames:.0f} frames, error then {trust.median_ev:.3f} EV median "
          f"(p90 {trust.p90_ev:.3f}); each frame estimated alone: {trust.single_frame_median_ev:.3f} EV median")
    return 0


def cmd_bench_profile_clean(args: argparse.Namespace) -> int:
    """Profiles learned through a real store on vignetting-free bases x lensfun fields."""
    import os

    from vigproc.bench import clean as C
    from vigproc.bench import profile as B
    from vigproc.bench.peers import PEER_ENV, published_rgs
    from vigproc.core.lensfamily import PROFILE_COMPONENTS
    from vigproc.stores.lensfun import lensfun_family

    output_file(args.json)
    bases, _ = C.load_clean_bases(args.images, args.min_long_side, args.limit, colour=not args.grey)
    if len(bases) < max(args.counts):
        print(f"vigproc: bench profile-clean: {max(args.counts)} frames per lens need as many bases; "
              f"{len(bases)} usable under {' '.join(args.images)}", file=sys.stderr)
        return EXIT_CODES["usage"]
    lens, excluded = C.lens_fields(args.lenses)
    # the store pools in a family without the test lenses: no profile holds the lens it is scored on
    family = lensfun_family(exclude=excluded, n_components=PROFILE_COMPONENTS)
    exe = args.peer or os.environ.get(PEER_ENV)
    peer = published_rgs(exe) if exe else None
    if peer is None:
        print(f"vigproc: bench profile-clean: no published peer (scripts/build_rgs_peer.sh; --peer or ${PEER_ENV}); "
              "its rows are left out", file=sys.stderr)
    rows, trust = B.run_clean(bases, lens, family, args.counts, peer=peer, seed=args.seed, orders=args.orders)
    print(f"profiles on the clean protocol: {len(lens)} lensfun lenses, each learning up to {max(args.counts)} of "
          f"{len(bases)} clean bases (480x320, {'luminance' if args.grey else 'colour'}, linear) in "
          f"{args.orders} order(s) of its own; error = RMS of log2(profile/true field) about its mean (EV), "
          "median / p90 over the lens x order runs")
    print(f"{'method':<24}{'frames':>7}{'lenses':>8}{'median EV':>11}{'p90 EV':>9}{'<=1sd':>7}{'<=2sd':>7}")
    for r in rows:
        print(f"{r.method:<24}{r.n_frames:>7}{r.n_lenses:>8}{r.median_ev:>11.3f}{r.p90_ev:>9.3f}"
              f"{r.within_1sigma:>7.2f}{r.within_2sigma:>7.2f}")
    print(f"trusted (2 sigma < {trust.bound_ev:g} EV): {trust.n_trusted}/{trust.n_lenses} lenses, after a median "
          f"{trust.median_frames:.0f} frames; error then below the bound on {trust.share_within_bound:.0%} of them, "
          f"and on {trust.share_within_bound_later:.0%} of trusted profiles at the counts above")
    write_json_result(args.json, {"rows": [asdict(r) for r in rows], "trust": asdict(trust)})
    return 0


def cmd_bench_profile_interp(args: argparse.Namespace) -> int:
    """A lens's profiles answering between their bins, on lensfun's held-out calibrations."""
    from vigproc.bench import profile as B

    output_file(args.json)
    rows = B.run_interpolation(max_points=args.points)
    print("between bins: lensfun zoom lenses' interior calibrations held out, the others stored as profiles; "
          "error = RMS of log2(answer/held-out calibration) about its mean (EV)")
    print(f"{'method':<24}{'between':<10}{'points':>7}{'median EV':>11}{'p90 EV':>9}{'<=1sd':>7}{'<=2sd':>7}")
    for r in rows:
        print(f"{r.method:<24}{r.axis:<10}{r.n_points:>7}{r.median_ev:>11.4f}{r.p90_ev:>9.4f}"
              f"{r.within_1sigma:>7.2f}{r.within_2sigma:>7.2f}")
    write_json_result(args.json, [asdict(r) for r in rows])
    return 0


def cmd_bench_colour(args: argparse.Namespace) -> int:
    """Colour shading: ``--part flat`` (flat frames and DNG gain maps, vigproc.bench.colour),
    ``detect`` (one photograph's cast, vigproc.bench.colour_detect), or ``all``."""
    output_file(args.json)
    data: dict = {}
    if args.part in ("flat", "all"):
        from vigproc.bench import colour as B
        from vigproc.bench.clean import load_clean_bases

        bases, _ = load_clean_bases(args.images, args.min_long_side, args.limit, colour=True)
        rows = B.run_flat(B.physical_fields() + B.gainmap_fields(), bases, frames=args.frames, seed=args.seed)
        dng = B.run_dng()
        print(B.report_flat(rows, dng, len(bases), args.frames))
        data["flat"] = [asdict(r) for r in rows]
        data["dng"] = [asdict(r) for r in dng]
    if args.part in ("detect", "all"):
        from vigproc.frontends.commands.colourdetect import bench_detect_report

        code, data["detect"] = bench_detect_report(args)  # its options at their defaults (see bench colour-detect)
        if code:
            return code
    write_json_result(args.json, data)
    return 0


def cmd_bench_profile_flat(args: argparse.Namespace) -> int:
    """Profiles learned from three shots of a flat field (Zheng et al.'s white pairs)."""
    from vigproc.bench import profile as B
    from vigproc.bench.real import find_inputs
    from vigproc.core.pixels import luminance
    from vigproc.io.images import read_image
    from vigproc.pipeline.processor import IMAGE_SUFFIXES

    output_file(args.json)
    pairs = [(v, c) for v, c in find_inputs(Path(args.images), IMAGE_SUFFIXES)[0]
             if c.stem.lower().startswith("white")]
    if not pairs:
        print(f"vigproc: bench profile-flat: no white pairs (white*_vig with white) under {args.images}",
              file=sys.stderr)
        return EXIT_CODES["usage"]
    frames = [(luminance(read_image(v, transfer=args.input_transfer)[0]),
               luminance(read_image(c, transfer=args.input_transfer)[0]), v.name) for v, c in pairs]
    rows = B.run_flat_field([f for f in frames if f[0].shape == f[1].shape], args.methods)
    print(f"flat-field profiles: {len(pairs)} white pairs under {args.images}, 3 unevenly lit shots of each "
          f"learned into a store (input transfer {args.input_transfer}); error = RMS of log2(profile/true field) "
          "about its mean (EV)")
    print(f"{'frame':<20}{'method':<12}{'error EV':>9}{'uncorr':>8}{'sigma':>7}{'trusted':>9}")
    for r in rows:
        print(f"{r.name:<20}{r.method:<12}{r.error_ev:>9.3f}{r.uncorrected_ev:>8.3f}{r.sigma_ev:>7.3f}"
              f"{'yes' if r.trusted else 'no':>9}")
    write_json_result(args.json, [asdict(r) for r in rows])
    return 0


def cmd_bench_io(args: argparse.Namespace) -> int:
    """Frame read times per format (vs reading the bytes) and EXIF per file in batch."""
    from vigproc.bench.io import bench_formats, bench_raw
    from vigproc.io.exif import bench_exif

    print(f"reading a {args.width}x{args.height} RGB frame (best of {args.repeat}); 'bytes' = reading the file's bytes")
    print(f"{'format':<20}{'MP':>7}{'MB':>9}{'read ms':>10}{'bytes ms':>10}{'ratio':>7}")
    rows = bench_formats(args.height, args.width, args.repeat)
    if args.raw:
        rows += bench_raw(sorted(p for p in Path(args.raw).rglob("*") if p.is_file()), args.repeat)
    for r in rows:
        print(f"{r.label:<20}{r.megapixels:>7.1f}{r.megabytes:>9.1f}{r.read_ms:>10.1f}{r.bytes_ms:>10.1f}"
              f"{r.read_ms / max(r.bytes_ms, 1e-9):>7.1f}")
    if args.exif:
        files = _images_in(Path(args.exif))
        e = bench_exif(files, repeat=args.repeat)
        print(f"EXIF lens key, {int(e['n_files'])} files: {e['batch_ms_per_file']:.1f} ms/file in one exiftool "
              f"process ({e['batch_total_ms_per_file']:.1f} with its {e['startup_ms']:.0f} ms start-up), "
              f"{e['per_process_ms_per_file']:.1f} ms/file with a process per file ({e['speedup']:.1f}x)")
    return 0


def cmd_bench_throughput(args: argparse.Namespace) -> int:
    """``vigproc correct`` on full-size photographs beside the floor (decode + encode +
    one exiftool batch) and darktable-cli, in one run (:mod:`vigproc.bench.throughput`)."""
    from vigproc.bench import throughput as T

    if not (args.images or args.raw):
        raise VigprocError("bench throughput needs --images DIR or --raw DIR")
    for raw, folder in ((False, args.images), (True, args.raw)):
        if folder is None:
            continue
        photos, skipped = (T.select_raws(Path(folder), args.limit) if raw else
                           T.select_photos(Path(folder), args.min_mp, args.limit))
        r = T.run_throughput(photos, rounds=args.rounds, darktable=not args.no_darktable, skipped=skipped,
                             baseline=args.baseline, raw=raw)
        print(("RAW: " if raw else "") + "\n".join(T.format_result(r)))
        write_json_result(args.json if not raw else (args.json and args.json + ".raw.json"), asdict(r))
    return 0


def cmd_bench_scaling(args: argparse.Namespace) -> int:
    """``vigproc watch`` and ``vigproc batch`` on full-size photographs with 1 and 2
    workers, interleaved (:mod:`vigproc.bench.scaling`)."""
    from vigproc.bench import scaling as S
    from vigproc.bench import throughput as T

    photos, _ = T.select_photos(Path(args.images), args.min_mp, args.limit)
    r = S.run_scaling(photos, workers=args.workers, rounds=args.rounds, frontends=args.frontends,
                      workdir=Path(args.tmp) if args.tmp else None)
    print("\n".join(S.format_result(r)))
    write_json_result(args.json, asdict(r))
    return 0


def cmd_bench_memory(args: argparse.Namespace) -> int:
    """Peak memory of one worker (``vigproc correct``) on a 24 MP JPEG and 16-bit TIFF
    (:mod:`vigproc.bench.memory`)."""
    from vigproc.bench import memory as M

    r = M.run_memory(args.width, args.height, workdir=Path(args.tmp) if args.tmp else None)
    print("\n".join(M.format_result(r)))
    write_json_result(args.json, asdict(r))
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
            from vigproc.pipeline.processor import Processor, Settings, file_sha256, read_lens

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
def _add_colour(bp: argparse.ArgumentParser) -> None:
    bp.add_argument("--colour", action="store_true",
                    help="give the estimators the images' R, G, B (the paper's protocol is grey: its luminance)")


def _add_clean_bases(bp: argparse.ArgumentParser) -> None:
    """The clean protocol's bases (vigproc.bench.clean), as bench clean and bench crops take them."""
    from vigproc.frontends.commands._options import add_clean_bases

    add_clean_bases(bp)


def build_parser() -> argparse.ArgumentParser:
    from vigproc.core.methods import METHODS

    p = argparse.ArgumentParser(prog="vigproc", description="Lens vignetting: estimate, correct, learn, check.")
    p.add_argument("-v", "--verbose", action="count", default=0,
                   help="more log output (-v: info, -vv: debug and tracebacks)")
    sub = p.add_subparsers(dest="command", required=True)

    from vigproc.frontends.commands._options import add_learn, add_method, add_processing, add_transfer, number

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
    import importlib
    import pkgutil

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
    bp = bsub.add_parser("synthetic", help="Lyu 2010 Tables 2-3 protocol")
    bp.add_argument("--images", required=True, help="folder of images (BSDS val, say)")
    bp.add_argument("--limit", type=int, help="use at most this many images")
    bp.add_argument("--quantize", action="store_true", help="quantise the vignetted frames to 8 bits, as a JPEG would")
    bp.add_argument("--input-transfer", choices=("auto", "linear", "srgb"), default="linear",
                    help="the paper's protocol takes stored values as linear (default)")
    bp.add_argument("--methods", nargs="+", default=["ga", "lyu2010-rand", "lyu2010", "default"],
                    choices=["ga", "lyu2010-rand", "lyu2010", "robust", "lens-family", "default", "rgs"],
                    help="rgs: the radial-gradient-symmetry peer (vigproc.bench.peers)")
    _add_colour(bp)
    _add_scene_prior(bp)
    bp.add_argument("--json", help="write the figures to this file")
    bp.set_defaults(fn=cmd_bench_synthetic)
    bp = bsub.add_parser("lensfun", help="real lens profiles from lensfun applied to natural images")
    bp.add_argument("--images", required=True, help="folder of images")
    bp.add_argument("--limit", type=int, help="use at most this many images")
    bp.add_argument("--lenses", type=int, default=20, help="lensfun lenses (default %(default)s)")
    bp.add_argument("--frames-per-lens", type=int, default=5, help="frames per lens (default %(default)s)")
    _add_colour(bp)
    _add_estimator_bench(bp)
    bp.set_defaults(fn=cmd_bench_lensfun)
    bp = bsub.add_parser("clean", help="vignetting-free bases (central crops of camera frames) x real lens "
                         "fields, with the published peer when built")
    _add_clean_bases(bp)
    bp.add_argument("--crop", type=number(0.05, 1.0), default=0.4,
                    help="side fraction of each frame kept about its centre (default %(default)s; the "
                         "camera lens's own fall-off inside the crop grows with it)")
    bp.add_argument("--lenses", type=number(1, 100, integer=True), default=20,
                    help="lensfun lenses (default %(default)s)")
    bp.add_argument("--methods", nargs="+", default=["default", "flat-field", "lens-family", "rgs", "rgs-c++"],
                    choices=["default", "default+exif", "robust", "real-lens", "flat-field", "lens-family",
                             "lens-family+exif", "lyu2010", "ga", "rgs", "rgs-c++", "rgs-c++-srgb"],
                    help="+exif: told each lens's 35-mm focal length and f-number (never the lens); rgs: "
                         "vigproc's reimplementation of Zheng et al.; rgs-c++: their published code "
                         "(built by scripts/build_rgs_peer.sh), given linear or sRGB-encoded 8-bit frames")
    bp.add_argument("--peer", help="the built rgs_peer executable (default: $VIGPROC_RGS_PEER)")
    bp.add_argument("--no-table1", action="store_true", help="only the lensfun fields")
    bp.add_argument("--base-falloff", action="store_true",
                    help="give each base a test lens's fall-off first (the lenses in turn), as a film scan "
                         "carries its camera's, and score Table 1's fields against the bases with it, as the "
                         "BSDS protocols do (Table 1's fields and no harm only)")
    bp.add_argument("--calibrate", action="store_true",
                    help="only fit the lens-family estimator's sigma scale and floor (even frames) and check "
                         "them (odd frames)")
    bp.add_argument("--json", help="write the figures to this file")
    bp.set_defaults(fn=cmd_bench_clean)
    bp = bsub.add_parser("crops", help="the crop/shift test's AUC by fall-off and offset on clean bases, "
                         "its false alarms and power; --calibrate writes its calibration")
    _add_clean_bases(bp)
    bp.add_argument("--lenses", type=number(1, 100, integer=True), default=10,
                    help="lensfun lens shapes (default %(default)s)")
    bp.add_argument("--alpha", type=number(0.0, 1.0, open_lo=True), default=0.01,
                    help="false-alarm probability of the test (default %(default)s)")
    bp.add_argument("--statistic", choices=["shift", "z", "known-profile"], default="shift",
                    help="shift: the free-centre fit's centre's distance from the frame's in half-diagonals (the "
                    "test's); z: its Mahalanobis distance by the jackknife covariance; known-profile: the shift "
                    "when the centre is fitted with the lens's own profile known exactly, how far any test of "
                    "the centre could go (default %(default)s)")
    bp.add_argument("--calibrate", metavar="FILE", help="write the null distribution (every uncropped frame's "
                    "statistic) as a crop calibration")
    bp.add_argument("--json", help="write the figures to this file")
    bp.set_defaults(fn=cmd_bench_crops)
    bp = bsub.add_parser("real", help="photographs vignetted by others: known-field pairs and real lenses")
    bp.add_argument("--images", required=True, help="folder tree, e.g. ../shared/data/vignetted")
    _add_estimator_bench(bp)
    bp.set_defaults(fn=cmd_bench_real)
    bp = bsub.add_parser("speed", help="estimator timings on 480x320 frames")
    bp.add_argument("--images", help="folder of images (default: the bundled samples)")
    bp.add_argument("--limit", type=int, default=10, help="use at most this many images (default %(default)s)")
    bp.add_argument("--repeat", type=int, default=5, help="timing rounds (default %(default)s)")
    bp.add_argument("--methods", nargs="+", default=["ga", "default"], choices=list(METHODS),
                    help="estimators to time (default: ga default)")
    bp.add_argument("--api", action="store_true", help="time vigproc.estimate (colour, default method) on central "
                    "crops of --images's camera frames with a lensfun lens, Lyu's Table 1 setting 2 and no fall-off, "
                    "interleaved with the published peer")
    bp.add_argument("--peer", help="with --api: the built rgs_peer (scripts/build_rgs_peer.sh; default $VIGPROC_RGS_PEER)")
    add_transfer(bp)
    bp.set_defaults(fn=cmd_bench_speed)
    bp = bsub.add_parser("scene-scatter", help="how vignetting-free photographs scatter a frame's lens-family fit, "
                         "from the clean protocol's bases: the profile store's pooling (vigproc/data/scene_scatter.json)")
    bp.add_argument("-o", "--output", required=True, help="file to write (JSON)")
    _add_clean_bases(bp)
    bp.set_defaults(fn=cmd_bench_scene_scatter)
    bp = bsub.add_parser("learn", help="learning one more frame into a lens profile, warm and in a new process")
    bp.add_argument("--images", help="folder of photographs (default: the bundled samples)")
    bp.add_argument("--limit", type=int, default=60, help="use at most this many images (default %(default)s)")
    bp.add_argument("--stored", type=int, default=50, help="frames already in the profile (default %(default)s)")
    bp.add_argument("--rounds", type=int, default=5, help="timing rounds (default %(default)s)")
    bp.add_argument("--json", help="write the figures as JSON")
    add_transfer(bp)
    bp.set_defaults(fn=cmd_bench_learn)
    bp = bsub.add_parser("io", help="frame read times per format and EXIF per file in batch")
    bp.add_argument("--width", type=int, default=6000, help="frame width in px (default %(default)s)")
    bp.add_argument("--height", type=int, default=4000, help="frame height in px (default %(default)s)")
    bp.add_argument("--repeat", type=int, default=3, help="timing rounds (default %(default)s)")
    bp.add_argument("--raw", help="folder of RAW files to time (full and half size)")
    bp.add_argument("--exif", help="folder of images to time EXIF reading on")
    bp.set_defaults(fn=cmd_bench_io)
    bp = bsub.add_parser("throughput", help="vigproc correct on full-size photographs beside the floor (decode, "
                         "encode, EXIF copy) and darktable-cli, in one run")
    bp.add_argument("--images", help="folder of JPEG photographs")
    bp.add_argument("--raw", metavar="DIR", help="folder of camera RAW files: vigproc correct beside rawpy's "
                    "development and the same TIFF written")
    bp.add_argument("--min-mp", type=float, default=0.75, help="smallest photograph, megapixels (default %(default)s)")
    bp.add_argument("--limit", type=int, help="use at most this many photographs")
    bp.add_argument("--rounds", type=int, default=3, help="timing rounds, interleaved (default %(default)s)")
    bp.add_argument("--no-darktable", action="store_true", help="leave darktable-cli out")
    bp.add_argument("--baseline", metavar="TREE", help="also time vigproc correct from this source tree "
                    "(another checkout's root): before and after in one run")
    bp.add_argument("--json", help="write the figures as JSON")
    bp.set_defaults(fn=cmd_bench_throughput)
    bp = bsub.add_parser("scaling", help="vigproc watch and vigproc batch on full-size photographs with 1 and 2 "
                         "workers, interleaved: photos/s and the ratio to one worker")
    bp.add_argument("--images", required=True, help="folder of JPEG photographs")
    bp.add_argument("--min-mp", type=float, default=0.75, help="smallest photograph, megapixels (default %(default)s)")
    bp.add_argument("--limit", type=number(1, 100_000, integer=True), help="use at most this many photographs")
    bp.add_argument("--workers", type=number(1, 64, integer=True), nargs="+", default=[1, 2],
                    help="worker counts (default 1 2)")
    bp.add_argument("--frontends", nargs="+", choices=["watch", "batch"], default=["watch", "batch"],
                    help="what to time (default both)")
    bp.add_argument("--rounds", type=number(1, 100, integer=True), default=2,
                    help="timing rounds, interleaved (default %(default)s)")
    bp.add_argument("--tmp", help="folder for the temporary files (default: the system's)")
    bp.add_argument("--json", help="write the figures as JSON")
    bp.set_defaults(fn=cmd_bench_scaling)
    bp = bsub.add_parser("memory", help="peak memory of one worker (vigproc correct) on a 24 MP JPEG and "
                         "16-bit TIFF")
    bp.add_argument("--width", type=number(64, 100_000, integer=True), default=6000,
                    help="frame width in px (default %(default)s)")
    bp.add_argument("--height", type=number(64, 100_000, integer=True), default=4000,
                    help="frame height in px (default %(default)s)")
    bp.add_argument("--tmp", help="folder for the temporary files (default: the system's)")
    bp.add_argument("--json", help="write the figures as JSON")
    bp.set_defaults(fn=cmd_bench_memory)
    bp = bsub.add_parser("profile", help="profile accuracy versus number of frames (lensfun lenses)")
    bp.add_argument("--images", required=True, help="folder of images")
    bp.add_argument("--limit", type=int, help="use at most this many images")
    bp.add_argument("--lenses", type=int, default=20, help="lensfun lenses (default %(default)s)")
    bp.add_argument("--counts", type=number(1, 100_000, integer=True), nargs="+", default=[1, 5, 20],
                    help="numbers of frames per lens to report (default 1 5 20)")
    bp.add_argument("--no-joint", action="store_true",
                    help="skip the joint multi-frame fit (its cost grows with the frames)")
    add_transfer(bp)
    bp.set_defaults(fn=cmd_bench_profile)
    bp = bsub.add_parser("profile-clean", help="profiles learned through a real store on vignetting-free bases x "
                         "lensfun fields, beside the published peer pooled the same way")
    _add_clean_bases(bp)
    bp.add_argument("--lenses", type=number(1, 100, integer=True), default=20,
                    help="lensfun lenses (default %(default)s)")
    bp.add_argument("--counts", type=number(1, 100_000, integer=True), nargs="+", default=[1, 5, 20, 50],
                    help="numbers of frames per lens to report (default 1 5 20 50)")
    bp.add_argument("--seed", type=int, default=0, help="seed of each lens's frame order (default 0)")
    bp.add_argument("--orders", type=number(1, 100, integer=True), default=1,
                    help="frame orders per lens, each into a new store (default %(default)s)")
    bp.add_argument("--peer", help="the built rgs_peer executable (default: $VIGPROC_RGS_PEER)")
    bp.add_argument("--json", help="write the figures to this file")
    bp.set_defaults(fn=cmd_bench_profile_clean)
    bp = bsub.add_parser("profile-interp", help="a lens's profiles answering between their focal and aperture "
                         "bins, on lensfun's held-out calibrations")
    bp.add_argument("--points", type=number(1, 100_000, integer=True), default=200,
                    help="held-out calibrations at most (default %(default)s)")
    bp.add_argument("--json", help="write the figures to this file")
    bp.set_defaults(fn=cmd_bench_profile_interp)
    bp = bsub.add_parser("profile-flat", help="profiles learned from a few shots of a flat field "
                         "(Zheng et al.'s white pairs), flat-field against the default")
    bp.add_argument("--images", default="../shared/data/vignetted", help="folder with white*_vig / white pairs "
                    "(default %(default)s)")
    bp.add_argument("--methods", nargs="+", default=["flat-field", "default"], choices=list(METHODS),
                    help="methods to learn with (default %(default)s)")
    add_transfer(bp)
    bp.add_argument("--json", help="write the figures to this file")
    bp.set_defaults(fn=cmd_bench_profile_flat)
    bp = bsub.add_parser("colour", help="colour shading: per-channel fields from flat frames and DNG gain maps "
                         "(flat), a single photograph's corner cast (detect)")
    bp.add_argument("--part", choices=["flat", "detect", "all"], default="flat",
                    help="which part to run (default %(default)s)")
    _add_clean_bases(bp)
    bp.add_argument("--frames", type=number(1, 100, integer=True), default=3,
                    help="flat frames per lens (default %(default)s)")
    bp.add_argument("--seed", type=number(0, 2**31, integer=True), default=0, help="random seed (default %(default)s)")
    bp.add_argument("--json", help="write the figures to this file")
    bp.set_defaults(fn=cmd_bench_colour)
    bp = bsub.add_parser("correct", help="full-resolution correction speed (24 MP by default)")
    bp.add_argument("--width", type=int, default=6000, help="frame width in px (default %(default)s)")
    bp.add_argument("--height", type=int, default=4000, help="frame height in px (default %(default)s)")
    bp.add_argument("--repeat", type=int, default=15, help="timing rounds (default %(default)s)")
    bp.set_defaults(fn=cmd_bench_correct)
    for mod in command_modules:  # benchmarks of the command modules (register_bench is optional)
        if hasattr(mod, "register_bench"):
            mod.register_bench(bsub)
    return p


def _add_estimator_bench(bp: argparse.ArgumentParser) -> None:
    """Options of a benchmark that runs estimators on photographs (lensfun, real)."""
    from vigproc.frontends.commands._options import add_transfer
    from vigproc.core.methods import METHODS

    add_transfer(bp)
    bp.add_argument("--methods", nargs="+", default=["default"], choices=[*METHODS, "rgs"],
                    help="rgs: the radial-gradient-symmetry peer (vigproc.bench.peers)")
    _add_scene_prior(bp)
    bp.add_argument("--json", help="write the figures to this file")


def _add_scene_prior(bp: argparse.ArgumentParser) -> None:
    bp.add_argument("--scene-prior", default="shipped", metavar="shipped|none|FILE",
                    help="scene prior of the default estimator: the shipped one (fitted on linearised "
                         "photos), none, or a file from 'vigproc prior fit-scene' (default: shipped)")


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
    import signal
    import threading

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
    import io

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
