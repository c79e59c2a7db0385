"""``vigproc estimate FILES...``: each frame's vignetting, printed (nothing is written)."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

from vigproc.core.colour_cast import CastSettings, detect_colour_cast
from vigproc.core.estimate import estimate
from vigproc.errors import VigprocError, one_line
from vigproc.frontends.commands._options import failure_record, files_exit_code, print_json_results
from vigproc.io.exif import ExifReader
from vigproc.io.images import EncodedImage, read_encoded
from vigproc.io.incamera import read_in_camera
from vigproc.io.lensident import display_lens_id
from vigproc.pipeline.encoded import check_encoded, estimate_encoded
from vigproc.pipeline.guard import guard
from vigproc.pipeline.processor import Settings, lens_hint, read_lens


def cmd_estimate(args: argparse.Namespace) -> int:
    """Each file in turn; the exit code is :func:`files_exit_code`'s. ``--json`` prints
    one JSON document at the end, for one file as for many (README, "--json")."""
    Settings(mode="estimate", method=args.method, transfer=args.input_transfer)  # a bad --method: one usage error
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
    # RAW: estimate on LibRaw's half-size development (the fast path) and report the
    # model for the full frame; a JPEG's or PNG's codes from a reduced copy; others as they are
    img, info = read_encoded(file, transfer=args.input_transfer, raw_half_size=True)
    reader = reader.read_file(Path(file))  # one exiftool read: the lens and the in-camera flags
    key, lens = read_lens(reader, Path(file))
    cfa = None
    if info.format == "raw" and args.method == "flat-field":  # a RAW flat frame: per CFA plane
        from vigproc.pipeline.cfa_flat import cfa_flat_field

        cfa = cfa_flat_field(file, info.width, info.height)
    if cfa is not None:
        m = cfa
    elif isinstance(img, EncodedImage):
        m = estimate_encoded(check_encoded(img), args.method, hint=lens_hint(key, args.method), seed=args.seed)
    else:
        m = estimate(img, args.method, channel_axis=-1 if img.ndim == 3 else None, seed=args.seed,
                     hint=lens_hint(key, args.method))
    # "applied" says what correct would do: the same harm rules (vigproc.pipeline.guard)
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
    if img.ndim != 3 or img.shape[2] < 3:
        return {"detected": False, "reason": "a grey frame has no colour"}
    usable, settings = None, CastSettings()
    if isinstance(img, EncodedImage):
        long_side = max(img.shape[:2])
        if img.codes.dtype == np.uint8:
            # 8-bit codes quantise the chroma of dark pixels, which pulls the fit towards no
            # cast: each working pixel averages at least 5x5 of them
            settings = CastSettings(work_long_side=int(max(48, min(settings.work_long_side, long_side / 5))))
        img, usable = img.reduced(max(1, long_side // 480))
    return detect_colour_cast(img, luminance_model=m, usable=usable, settings=settings).to_dict()
