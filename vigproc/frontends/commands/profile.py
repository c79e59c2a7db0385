"""``vigproc profile SUBCOMMAND``: the per-lens profile store (list, show, learn, import,
export, lensfun and Adobe LCP interop); one handler per subcommand (:data:`SUBCOMMANDS`)."""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path

from vigproc.errors import VigprocError, one_line
from vigproc.frontends.commands._progress import _progress
from vigproc.io.exif import LensKey, casefold_lens_id, escape_key_part, unescape_key_part
from vigproc.io.images import write_image
from vigproc.io.lensident import display_lens_id
from vigproc.io.picture import falloff_figure
from vigproc.pipeline.processor import Processor, Settings
from vigproc.stores.lcp import import_lcp, lcp_files
from vigproc.stores.lensfun_io import (colour_notes, export_lensfun_xml, find_lens, frame_crop_for, import_lensfun,
                                      lensfun_entries)
from vigproc.stores.lensfun_match import frame_crop
from vigproc.stores.opening import open_profile_store
from vigproc.stores.profiles import (Profile, ProfileKey, ProfileStoreError, _aspect_value, _canonical_aspect,
                                     aperture_bin, aspect_label, focal_bin, normalise)


def _profile_text(p) -> str:
    """A profile as ``profile list`` describes it, without its index."""
    t = "trusted" if p.trusted else "learning"
    sigma = "±?" if p.field_sigma_ev is None else f"±{p.field_sigma_ev:.3f} EV"
    return f"{p.label()}  frames={p.n_frames}  {sigma}  {t}  ({p.provenance}, updated {p.updated})"


def _profile_line(i: int, p) -> str:
    return f"[{i}] {_profile_text(p)}"


def _pick_profile(store, ident: str):
    """A stored profile by its index in ``profile list``, its exact key text, or its lens
    id (as ``estimate`` and ``check`` print it) when that lens has one profile."""
    profiles = store.list()
    if ident.isdigit() and int(ident) < len(profiles):
        return profiles[int(ident)]
    for p in profiles:
        if ident in (str(p.key), p.label()):
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
    aspect = None
    if args.aspect:
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


def _list(args: argparse.Namespace, store) -> int:
    """``profile list``: every stored profile, one line each, numbered for ``show`` and ``export``."""
    profiles = store.list()
    for i, p in enumerate(profiles):
        print(_profile_line(i, p))
    if not profiles:  # say so: an empty output reads like a failure
        print(f"no profiles in {store.path} (vigproc profile learn FILES..., or import one)")
    return 0


def _show(args: argparse.Namespace, store) -> int:
    """``profile show ID``: one profile as a model for a frame size (a summary, or the JSON
    record with ``--json``), and a picture of its fall-off with ``--plot``."""
    p = _pick_profile(store, args.id)
    width, height = _profile_frame(p.key.aspect_ratio, args.width, args.height)
    m = p.model(width, height)
    cast = store.cast_report(p.key)  # pooled from the lens's learned frames; reported, never applied
    # ...unless the profile has a per-channel field (flat frames' colour or grid): correct divides it out
    per_channel = p.colour is not None or p.grid is not None
    if args.json:  # the profile's record, its model for the frame inside
        sigma = p.field_sigma_ev
        print(json.dumps({
            "key": str(p.key), "lens_id": p.key.lens_id, "focal_bin": p.key.focal_bin,
            "aperture_bin": p.key.aperture_bin, "aspect": p.key.aspect, "frames": p.n_frames,
            "trusted": bool(p.trusted), "field_sigma_ev": sigma if sigma is None or math.isfinite(sigma) else None,
            "provenance": p.provenance, "updated": p.updated, "width": width, "height": height,
            "model": m.to_dict(),
            **({"colour_cast": {**cast.to_dict(), "corrected": per_channel}} if cast is not None else {})}, indent=1))
    else:
        q = m.quality
        print(_profile_text(p))
        print(f"  frame       {width}x{height}")
        print(f"  centre      ({m.center[0]:.1f}, {m.center[1]:.1f}) px from the frame centre")
        print(f"  fall-off    {m.field_ev_rms():.3f} EV RMS over the frame"
              + (f", ±{q.field_sigma_ev:.3f} EV" if q and math.isfinite(q.field_sigma_ev) else ""))
        if cast is not None:
            print(f"  colour cast {cast.describe()}; "
                  + ("corrected by the profile's per-channel field" if per_channel else "reported, not corrected"))
        print("  (--json prints the whole model)")
    if args.plot:
        write_image(args.plot, falloff_figure(m, title=str(p.key)), bit_depth="uint8", transfer="srgb")
        print(f"picture -> {args.plot}", file=sys.stderr if args.json else sys.stdout)
    return 0


def _learn(args: argparse.Namespace, store) -> int:
    """``profile learn FILES...``: estimate each frame and pool it into its lens's profile,
    keyed by content (a file learned again is pooled once); exit 1 when a file failed."""
    files = [Path(f) for f in args.files]
    done = failed = again = 0
    settings = Settings(mode="learn", transfer=args.input_transfer, method=args.method)
    with Processor(settings, store=store) as proc:
        for f in _progress(files, "learning"):
            try:
                # read, lens and content id as every front end reads a frame; keyed by
                # content: learning a file again does not pool it twice
                frame = proc.read_frame(f)
                if frame.lens_key is None:
                    raise VigprocError(f"cannot learn, lens unknown ({frame.lens['error']})")
                key = store.key_for(frame.lens_key, frame.img.shape[1], frame.img.shape[0])
                known = store.holds_frame(key, frame.frame_id)
                proc.process_frame(frame)
                p = store.get(key)
                done += not known
                again += known
                note = "  (this content was already learned: counted once)" if known else ""
                print(one_line(f"{f} -> {_profile_text(p)}{note}"))
            except VigprocError as exc:
                failed += 1
                print(one_line(f"vigproc: {str(f)!r}: {exc}"), file=sys.stderr)
    print(f"{done} frame{'' if done == 1 else 's'} learned"
          + (f", {again} already learned before" if again else "") + f", {failed} failed")
    return 0 if failed == 0 else 1


def _import(args: argparse.Namespace, store) -> int:
    """``profile import FILE``: a profile file (JSON, profiles/README.md) into the store."""
    p = store.import_file(args.file)
    print(f"imported {str(p.key).replace(p.key.lens_id, display_lens_id(p.key.lens_id), 1)}")  # as list shows it
    return 0


def _apply(args: argparse.Namespace, store) -> int:
    """``profile apply ID``: learning as you go corrects this lens setting's frames with the
    profile as stored now, from the next frame on (a new series, docs/watch.md)."""
    p = _pick_profile(store, args.id)
    if not p.trusted:
        raise VigprocError(f"profile {p.key} is not trusted ({p.n_frames} frames): it corrects no series")
    held = store.applied_revision(p.key)
    rev, got = store.apply_revision(p, replaces=held[0] if held is not None else None)
    print(f"profile {p.key}: revision {rev} ({got.n_frames} frames) applied from the next frame on "
          f"(a new series){'' if held is None or held[0] != rev else '; it was applied already'}")
    return 0


def _delete(args: argparse.Namespace, store) -> int:
    """``profile delete ID``: a stored profile removed, with its pooled frames (they may be
    learned again), its prior and its applied revision."""
    p = _pick_profile(store, args.id)
    store.delete(p.key)
    print(f"deleted {_profile_text(p)}")
    return 0


def _export(args: argparse.Namespace, store) -> int:
    """``profile export ID FILE``: a stored profile as a profile file."""
    store.export_file(_pick_profile(store, args.id).key, args.file)  # with its frames' colour casts
    print(f"exported -> {args.file}")
    return 0


def _import_lensfun(args: argparse.Namespace, store) -> int:
    """``profile import-lensfun MAKER MODEL``: lensfun's calibration of a lens at one focal
    length and aperture, stored as a trusted profile."""
    # escaped as lens ids from EXIF are: a "|" in a name must not forge a component
    lens_id = args.lens_id or f"{escape_key_part(args.maker)}|{escape_key_part(args.model)}"
    # the profile serves the frames of the body its lens id names: the calibration ends where
    # that body's sensor ends (lensfun's rule, as --profile lensfun applies it), not stretched over its frame
    lens, crop = args.maker, args.crop_factor
    if crop is None and (body := _body_crop(lens_id, args.focal)) is not None:
        found = find_lens(args.maker, args.model, crop_factor=body)  # the calibration that covers the body
        lens, crop = (args.maker, body) if found is None else (found, frame_crop_for(found, body))
    m = import_lensfun(lens, args.model, args.focal, args.aperture, args.distance,
                       width=args.width, height=args.height, crop_factor=crop)
    theta, _, aspect = normalise(m)
    key = ProfileKey(casefold_lens_id(lens_id), focal_bin(args.focal), aperture_bin(args.aperture), aspect_label(aspect))
    store.put(Profile(key=key, theta=theta, covariance=None, provenance="lensfun", trusted=True,
                      notes=f"lensfun {args.maker} {args.model} at {args.focal} mm f/{args.aperture}"))
    print(f"imported from lensfun: {key}"
          + (f" (crop {crop:.4g})" if crop is not None else " (the calibration's own sensor)"))
    return 0


def _body_crop(lens_id: str, focal: float) -> float | None:
    """The crop factor of the camera a lens id (``make|model|lens``) names, as
    :func:`~vigproc.stores.lensfun_match.frame_crop` gives it; None for an id naming no
    body lensfun knows (``maker|model``, import-lensfun's default)."""
    parts = [unescape_key_part(v) for v in lens_id.split("|")]
    if len(parts) < 3:  # not a camera's id: no body to end at
        return None
    return frame_crop(LensKey(make=parts[0], model=parts[1], lens=parts[2], focal_mm=focal))


def _export_lensfun(args: argparse.Namespace, store) -> int:
    """``profile export-lensfun FILE``: the learned profiles as a lensfun XML database
    (profiles lensfun cannot hold are named on stderr)."""
    entries, skipped = lensfun_entries(store.list(), crop_factor=args.crop_factor, mount=args.mount)
    for why in skipped:
        print(one_line(f"vigproc: not exported: {why}"), file=sys.stderr)
    for note in colour_notes(store.list()):
        print(one_line(f"vigproc: note: {note}"), file=sys.stderr)
    n = export_lensfun_xml(entries, args.file)
    print(f"{len(entries)} calibrations of {n} lenses -> {args.file}")
    return 0


#: ``vigproc profile SUBCOMMAND``: the handler of each subcommand, given the parsed
#: arguments and the open store; it returns the exit code.
SUBCOMMANDS = {
    "list": _list,
    "show": _show,
    "learn": _learn,
    "apply": _apply,
    "delete": _delete,
    "import": _import,
    "export": _export,
    "import-lensfun": _import_lensfun,
    "import-lcp": _import_lcp,
    "export-lensfun": _export_lensfun,
}


def cmd_profile(args: argparse.Namespace) -> int:
    """``vigproc profile SUBCOMMAND``: open the store (for writing) and run the subcommand's
    handler (:data:`SUBCOMMANDS`)."""
    with open_profile_store(args.profile_db, write=True) as store:
        return SUBCOMMANDS[args.profile_command](args, store)
