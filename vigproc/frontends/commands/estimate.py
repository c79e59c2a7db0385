"""``vigproc estimate FILES...``: each frame's vignetting, printed (nothing is written)."""

from __future__ import annotations

import argparse
import sys

from vigproc.errors import VigprocError, one_line
from vigproc.frontends.commands._options import failure_record, files_exit_code, print_json_results
from vigproc.io.lensident import display_lens_id
from vigproc.pipeline.cast import frame_cast
from vigproc.pipeline.processor import Processor, Settings


def cmd_estimate(args: argparse.Namespace) -> int:
    """Each file in turn through the processor's per-frame path (estimate mode); the exit
    code is :func:`files_exit_code`'s. ``--json`` prints one JSON document at the end, for
    one file as for many (README, "--json")."""
    # always the frame's own estimate (no profile), judged as correct would judge it
    settings = Settings(mode="estimate", profile="estimate", method=args.method, transfer=args.input_transfer)
    results: list[dict] = []
    codes: list[int | None] = []
    with Processor(settings, seed=args.seed, judge_estimates=True) as proc:  # one exiftool for all the files
        for f in args.files:
            try:
                results.append(_estimate_file(args, f, proc))
                codes.append(None)
            except VigprocError as exc:  # one line naming the file, as the multi-file commands do
                print(one_line(f"vigproc: {str(f)!r}: {exc}"), file=sys.stderr)
                results.append(failure_record(f, exc))
                codes.append(exc.exit_code)
    code = files_exit_code(codes)
    if args.json:
        print_json_results(results, code)
    return code


def _estimate_file(args: argparse.Namespace, file: str, proc: Processor) -> dict:
    # RAW: estimate on LibRaw's half-size development (the fast path) and report the
    # model for the full frame; a JPEG's or PNG's codes from a reduced copy; others as they are
    frame = proc.read_frame(file, raw_half_size=True)
    _, res = proc.process_frame(frame)
    img, info, lens, m = frame.img, frame.info, frame.lens, res.model
    refusal = res.extra.get("not_applied_rule")  # "applied" says what correct would do (pipeline.guard)
    cast = _colour_cast(img, m)  # a report only: never applied (colour fields come from flat frames/profiles/DNGs)
    if info.format == "raw":
        m = m.rescale(2 * m.width, 2 * m.height)
    doc = {"file": str(file), "lens": lens, "model": m.to_dict(), "colour_cast": cast,
           **({"not_applied_rule": refusal} if refusal is not None else {})}
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
    """The frame's colour-cast report (:func:`vigproc.pipeline.cast.frame_cast`)."""
    ev = frame_cast(img, m)
    return {"detected": False, "reason": "a grey frame has no colour"} if ev is None else ev.to_dict()
