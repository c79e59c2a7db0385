"""Gather full camera frames whose EXIF lens lensfun calibrated, for part (a) of
``vigproc bench real-frames --images OUT`` (issue 38): more truth frames than the 12
JPEGs of ``../shared`` and the held-out ``metadata-extractor-images`` snapshot.

Every file comes out of a public GitHub repository's snapshot, by path at a recorded
commit; ``OUT/manifest.csv`` lists repository, path, commit, blob, SHA-256, licence and
what the frame is. None of these images is committed to vigproc.

How they were found: every JPEG of 200 kB or more in the snapshots of
drewnoakes/digicam_corpus, ianare/exif-samples and OpenImageIO/oiio-images went through
``benchmarks.real_frames_lensfun.lensfun_frames`` (the matcher ``correct --profile lensfun``
uses); these are all the files it links to a lensfun ``pa`` calibration. Snapshots lack
files of 4 MiB and more (the corpus's RAW files and its largest JPEGs among them).

Snapshots: a bare git directory or a work tree per repository, given as
``--snapshot owner/name=DIR`` (default: ``/work/.mirror/owner+name/repo`` when present,
where the session's ``fetch`` puts them). A blob a snapshot lacks is skipped and listed.

Run from the repository root:
    .venv/bin/python scripts/gather_lensfun_frames.py /tmp/h5/lf-more
"""

from __future__ import annotations

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from gather_real_frames import gather, parse_args  # noqa: E402

_DC = ("drewnoakes/digicam_corpus", "6385e5eacf2dd242ff71e5828ff56ed691bfdc77", "CC0-1.0 (the repository's LICENSE)")
_EX = ("ianare/exif-samples", "5332a9cf0220e9c6c93f88a187daa90808051e10",
       "CC BY-SA 4.0 for contributed images (README); this file came from a bug report")

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
]


def main(argv: list[str] | None = None) -> int:
    return gather(*parse_args(__doc__, argv),
                  [(repo, commit, path, licence, what, "") for repo, commit, licence, path, what in FRAMES])


if __name__ == "__main__":
    sys.exit(main())
