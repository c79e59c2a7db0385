"""A plain Python photo pipeline that calls vigproc: rawpy -> vigproc -> OpenImageIO.

Each RAW file is developed to linear RGB with rawpy, corrected (or checked) in memory
through the stable API :mod:`vigproc.api`, and written as a half-float OpenEXR with
OpenImageIO; the vigproc result travels in the EXR header (``vigproc:result``).

    python plugins/examples/rawpy_pipeline.py RAW... -o OUTDIR [--mode correct|check]
        [--profile-db DB]

Exit status: 0 all done, 1 some files failed (one line each on stderr).

The three steps are deliberately separate functions: a real pipeline replaces
``develop`` and ``write_exr`` with its own and keeps the two lines in ``main`` that
talk to vigproc.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
from pathlib import Path

import numpy as np
import OpenImageIO as oiio
import rawpy

from vigproc.api import Pipeline
from vigproc.errors import VigprocError
from vigproc.io.exif import ExifReader


def develop(path: Path) -> np.ndarray:
    """Linear (gamma 1) camera-white-balanced sRGB-primaries float32 image in [0, 1].

    Raises OSError saying what is wrong with the file (LibRaw says b'Input/output error'
    alike for a missing file, a text file and a truncated RAW)."""
    if not path.is_file():
        raise FileNotFoundError("no such file" if not path.exists() else "not a file")
    try:
        with rawpy.imread(str(path)) as raw:
            rgb = raw.postprocess(gamma=(1.0, 1.0), no_auto_bright=True, use_camera_wb=True,
                                  output_bps=16, user_flip=0)
    except rawpy.LibRawError as exc:
        said = exc.args[0] if exc.args else ""
        said = said.decode("utf-8", "replace") if isinstance(said, bytes) else str(said)
        raise OSError(f"not a RAW file LibRaw can develop ({type(exc).__name__}: {said})") from None
    return rgb.astype(np.float32) / np.float32(65535.0)


def write_exr(path: Path, img: np.ndarray, result: dict) -> None:
    """Write ``img`` as half-float EXR via a temporary file renamed into place."""
    h, w = img.shape[:2]
    c = 1 if img.ndim == 2 else img.shape[2]
    spec = oiio.ImageSpec(w, h, c, oiio.HALF)
    spec.attribute("vigproc:result", json.dumps(result))
    fd, tmp = tempfile.mkstemp(prefix=f".{path.stem[:40]}.", suffix=".tmp.exr", dir=path.parent)
    os.close(fd)
    try:
        out = oiio.ImageOutput.create(tmp)
        if out is None or not out.open(tmp, spec) or not out.write_image(img) or not out.close():
            raise OSError(oiio.geterror() or "OpenImageIO could not write the file")
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("raws", nargs="+", type=Path)
    ap.add_argument("-o", "--output", type=Path, required=True)
    ap.add_argument("--mode", choices=("correct", "check"), default="correct")
    ap.add_argument("--profile-db", help="vigproc profile store (stored lens profiles; check mode)")
    args = ap.parse_args(argv)
    args.output.mkdir(parents=True, exist_ok=True)
    failed = 0
    # one Pipeline for the run (it may also be shared by worker threads), one exiftool
    with Pipeline(args.mode, store=args.profile_db) as vp, ExifReader() as exif:
        for raw in args.raws:
            try:
                img = develop(raw)
                try:  # or a dict the pipeline already has: {"make": ..., "lens": ..., "focal_mm": ...}
                    lens = exif.read(raw)
                except VigprocError as exc:  # no usable EXIF: vigproc still estimates from the pixels
                    print(f"{raw}: lens unknown ({exc})", file=sys.stderr)
                    lens = None
                out, res = vp.process(img, lens)
                # Path(...).name: an output name never leaves the output folder
                write_exr(args.output / (Path(raw.name).stem + ".exr"), out, res.to_dict())
                print(f"{raw}: {res.summary}")
            except (VigprocError, OSError) as exc:
                failed += 1
                print(f"{raw}: failed: {exc}", file=sys.stderr)
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
