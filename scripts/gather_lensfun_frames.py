"""Gather full camera frames whose EXIF lens lensfun calibrated, for part (a) of
``vigproc bench real-frames --images OUT`` (issue 38): more truth frames than the 12
JPEGs of ``../shared`` and the held-out ``metadata-extractor-images`` snapshot.

Every file comes out of a public GitHub repository's snapshot, by path at a recorded
commit; ``OUT/manifest.csv`` lists repository, path, commit, blob, SHA-256, licence and
what the frame is. None of these images is committed to vigproc.

How they were found (one rule, fixed before any error was looked at): every JPEG of
200 kB or more in a repository snapshot's HEAD went through
``benchmarks.real_frames_lensfun.lensfun_frames`` (the matcher ``correct --profile lensfun``
uses); FRAMES holds every file it links to a lensfun ``pa`` calibration, byte-identical
copies once, but those an editor wrote (``Software``/``CreatorTool`` naming Lightroom,
Photoshop, Camera Raw …: part (a) gives them no truth) and those under 1000 px (the bench
skips them). The snapshots scanned and what each gave: docs/benchmarks/real-frames.md,
part (a). Snapshots lack files of 4 MiB and more (the corpus's RAW files and its largest
JPEGs among them); ``bench real-frames --images`` reads JPEGs only, so no RAW is listed.

Snapshots: a bare git directory or a work tree per repository, given as
``--snapshot owner/name=DIR`` (default: ``/work/.mirror/owner+name/repo`` when present,
where the session's ``fetch`` puts them). A blob a snapshot lacks is skipped and listed.

Run from the repository root:
    .venv/bin/python scripts/gather_lensfun_frames.py /tmp/h2/lf-more
"""

from __future__ import annotations

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from gather_real_frames import gather, parse_args  # noqa: E402

_DC = ("drewnoakes/digicam_corpus", "6385e5eacf2dd242ff71e5828ff56ed691bfdc77", "CC0-1.0 (the repository's LICENSE)")
_EX = ("ianare/exif-samples", "5332a9cf0220e9c6c93f88a187daa90808051e10",
       "CC BY-SA 4.0 for contributed images (README); this file came from a bug report")
_PR = ("polimi-ispl/prnu-python", "91e1585a39287e26f9e770b71cf9124c35d9248d",
       "repository MIT; the images are Dresden Image Database frames by their names "
       "(Gloe and Böhme 2010), no licence of their own stated")

#: (repository, commit, licence, path, what)
FRAMES = [
    # ColorChecker on a dark board; one session, Fine/Normal/Basic and two shutter speeds
    *[(*_DC, f"Nikon/D3100/DSC_000{i}.JPG", "D3100 + AF-S DX 18-55mm at 24 mm f/4, ColorChecker (one scene)")
      for i in (1, 3, 4, 6, 7, 8)],
    # ColorChecker on a wooden table; one session, three qualities and three image sizes
    *[(*_DC, f"Nikon/D90/DSC_00{i:02d}.JPG", "D90 + AF-S 50mm f/1.8G at f/1.8, ColorChecker (one scene)")
      for i in (1, 2, 3, 5, 10, 11)],
    # a street between two buildings; the pixels were rotated and the XMP written by an Adobe tool
    (*_EX, "jpg/tests/87_OSError.jpg", "D70s + AF-S DX 18-70mm at 60 mm f/29, street (portrait, re-saved)"),
    # one session, the camera's lens correction on (VignettingCorrection Auto): no truth, part (b)
    *[(*_DC, f"Sony/A6400/DSC0000{i}.JPG", "A6400 + FE 50mm F1.8 at f/1.8, corrected in camera")
      for i in (7, 8)],
    # Dresden Image Database natural scenes: two D70 and two D70s bodies, each with a Sigma 18-200mm DC
    *[(*_PR, f"test/data/nat-jpg/Nikon_{cam}.JPG", "D70/D70s + Sigma 18-200mm DC, natural scene (Dresden)")
      for cam in ("D70_0_19445", "D70_0_19593", "D70_1_20543", "D70_1_20585", "D70_1_20749", "D70_1_20891",
                  "D70s_0_21853", "D70s_0_21989", "D70s_0_22115", "D70s_1_22750", "D70s_1_22760",
                  "D70s_1_22824", "D70s_1_22928", "D70s_1_23136")],
    ("polimi-ispl/dip_prnu_anonymizer", "72912b8a249a4ce66f11646ad0aac197db4752ad",
     "no licence in the repository; its README: an example dataset based on Dresden Image Database",
     "dresden_sample/Nikon_D70_0/Nikon_D70_0_19639.JPG", "D70 + Sigma 18-200mm DC, natural scene (Dresden)"),
    # Dresden flat fields: a plain surface, ten frames a session at one setting (five sessions)
    *[(*_PR, f"test/data/ff-jpg/Nikon_{cam}_{n}.JPG", f"{what}, flat field (Dresden)")
      for cam, first, what in (("D200_1", 18178, "D200 + AF-S DX 18-135mm at 135 mm f/10"),
                               ("D70_0", 19929, "D70 + Sigma 18-200mm DC at 200 mm f/7.1"),
                               ("D70_1", 21015, "D70 + Sigma 18-200mm DC at 200 mm f/25"),
                               ("D70s_0", 22193, "D70s + Sigma 18-200mm DC at 200 mm f/7.1"),
                               ("D70s_1", 23220, "D70s + Sigma 18-200mm DC at 200 mm f/8"))
      for n in range(first, first + 20, 2)],
]


def main(argv: list[str] | None = None) -> int:
    return gather(*parse_args(__doc__, argv),
                  [(repo, commit, path, licence, what, "") for repo, commit, licence, path, what in FRAMES])


if __name__ == "__main__":
    sys.exit(main())
