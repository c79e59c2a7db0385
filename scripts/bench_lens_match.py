"""How many real camera frames whose lens lensfun has calibrated are matched to it? (issue 36)

The frames: the full-size camera JPEGs of ``shared/data/jpeg_exif/metadata-extractor-images``
and ExifTool's RAW stubs in ``shared/data/raw/exiftool-stubs`` (set A), and the small
JPEGs with real camera EXIF of ``jpeg_exif/exif-py`` and ``jpeg_exif/exiftool-stubs`` (set B).
Each frame's lens key is read with :class:`vigproc.io.exif.ExifReader`; the lens lensfun
calibrated for vignetting is then looked up the way ``check`` and ``correct --profile
lensfun`` do (:func:`vigproc.stores.lensfun_match.match_lens`; on a tree without it, the
earlier ``find_lens`` of the lens name, which is what those commands did).

:data:`TRUTH` names, by hand, the frames whose lens lensfun (the database bundled with
lensfunpy) holds a ``pa`` vignetting calibration for, and which lens that is: found by
reading each frame's ExifTool LensID/LensType/LensModel and searching lensfun's lenses,
camera mounts and fixed-lens compacts.  Every other frame's lens is either unnamed (most
compacts and phones: lensfun holds their fixed lenses, if at all, for distortion only), or
named but not calibrated for vignetting (Nikon 28-300 VR, Olympus 14-54, Mamiya LS 80,
iPhone and Pixel cameras): for those a match is a false match.

Run from the repository root:  .venv/bin/python scripts/bench_lens_match.py [--data DIR] [-v]
"""

from __future__ import annotations

import argparse
import logging
import sys
from pathlib import Path

SETS = {
    "A (full-size camera JPEGs + RAW stubs)": ["jpeg_exif/metadata-extractor-images", "raw/exiftool-stubs"],
    "B (small JPEGs with camera EXIF)": ["jpeg_exif/exif-py", "jpeg_exif/exiftool-stubs"],
}

#: frame -> (lensfun maker, lensfun model) of the lens it was shot with, for the frames whose lens
#: lensfun has calibrated for vignetting.
TRUTH = {
    "jpeg_exif/metadata-extractor-images/Olympus_PEN_E-P3.jpg": ("Olympus", "Olympus M.Zuiko Digital 17mm f/1.8"),
    "jpeg_exif/metadata-extractor-images/Pentax_ist_D.jpg": ("Pentax", "smc Pentax-FA 77mm f/1.8 Limited"),
    "raw/exiftool-stubs/CanonRaw.cr3": ("Canon", "Canon EF-M 15-45mm f/3.5-6.3 IS STM"),
    "raw/exiftool-stubs/Nikon.nef": ("Nikon", "Nikon AF-S DX Zoom-Nikkor 18-70mm f/3.5-4.5G IF-ED"),
    "raw/exiftool-stubs/Sigma.x3f": ("Sigma", "Sigma 15-30mm f/3.5-4.5 EX DG Aspherical"),
    "jpeg_exif/exif-py/Sony_DSLR-A200.jpg": ("Sony", "Minolta/Sony AF DT 18-70mm f/3.5-5.6 (D)"),
    "jpeg_exif/exif-py/Sony_alpha_a58.JPG": ("Tamron", "Tamron SP 70-300mm f/4-5.6 Di USD"),
    "jpeg_exif/exiftool-stubs/Canon1DmkIII.jpg": ("Canon", "Canon EF 16-35mm f/2.8L II USM"),
    "jpeg_exif/exiftool-stubs/NikonD2Hs.jpg": ("Nikon", "Nikon AF Nikkor 50mm f/1.8D"),
    "jpeg_exif/exiftool-stubs/NikonD70.jpg": ("Nikon", "Nikon AF-S DX Zoom-Nikkor 18-70mm f/3.5-4.5G IF-ED"),
    # ExifTool: "Sigma AF 10-20mm F4-5.6 EX DC" on a Pentax K10D: lensfun's is the same optics with
    # the HSM motor Sigma added to every mount's version
    "jpeg_exif/exiftool-stubs/Pentax.jpg": ("Sigma", "Sigma 10-20mm f/4-5.6 EX DC HSM"),
}


def lensfun_lens(key) -> tuple[str, str] | None:
    """The lensfun lens ``correct --profile lensfun`` and ``check`` use for a key, or None."""
    try:
        from vigproc.stores.lensfun_match import match_lens
    except ImportError:  # a tree from before issue 36: the lens name as find_lens takes it
        from vigproc.errors import VigprocError
        from vigproc.stores.lensfun_io import find_lens

        if key.lens is None or key.focal_mm is None or key.fnumber is None:
            return None
        try:
            found = find_lens(None, key.lens)
        except VigprocError:
            return None
        return None if found is None else (found.maker, found.model)
    if key.focal_mm is None or key.fnumber is None:  # lensfun_model needs both
        return None
    found = match_lens(key).lens
    return None if found is None else (found.maker, found.model)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--data", type=Path, default=Path(__file__).resolve().parents[2] / "shared" / "data")
    ap.add_argument("-v", "--verbose", action="store_true", help="one line per frame")
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.ERROR)
    from vigproc.io.exif import ExifReader, LensKey

    if not args.data.is_dir():
        print(f"no shared data at {args.data}", file=sys.stderr)
        return 2
    status = 0
    with ExifReader() as reader:
        for title, folders in SETS.items():
            files = sorted(p for f in folders for p in (args.data / f).iterdir()
                           if p.is_file() and p.suffix.lower() not in (".md", ".csv"))
            keys = reader.read_many(files)
            has = matched = false = 0
            for path, key in zip(files, keys):
                rel = path.relative_to(args.data).as_posix()
                want = TRUTH.get(rel)
                got = lensfun_lens(key) if isinstance(key, LensKey) else None
                has += want is not None
                matched += want is not None and got == want
                false += got is not None and got != want
                if args.verbose:
                    lens = key.lens_id() if isinstance(key, LensKey) else type(key).__name__
                    mark = "ok" if got == want else "MISS" if want else "FALSE"
                    print(f"  {mark:5} {rel}: {lens} -> {got}")
            share = 100.0 * matched / has if has else float("nan")
            print(f"{title}: {len(files)} frames, {has} with a lens lensfun calibrated; "
                  f"{matched} matched ({share:.0f} %), {false} false matches")
            status |= matched < has or false > 0
    return int(status)


if __name__ == "__main__":
    sys.exit(main())
