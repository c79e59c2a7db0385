"""Gather real photographs the ../shared set lacks (fisheye, action-camera and sky frames)
for ``vigproc bench real-frames --images OUT`` (issue 38's harm part, extended).

Every file comes out of a public GitHub repository's snapshot, by path at a recorded
commit; the manifest ``OUT/manifest.csv`` lists repository, path, commit, blob, SHA-256,
licence and what the frame is. None of these images is committed to vigproc: the
repositories' licences cover their code, and the photographs carry no licence of their
own (or another's, as noted), so they stay outside the tree.

Snapshots: a bare git directory or a work tree per repository, given as
``--snapshot owner/name=DIR`` (default: ``/work/.mirror/owner+name/repo`` when present,
where the session's ``fetch`` puts them). A blob a partial snapshot lacks is skipped and
listed as missing. Side-by-side stereo files are cut to their left half (one camera's
frame), written as JPEG quality 95 (the bench reads JPEGs); their EXIF is not carried over.

Run from the repository root:
    .venv/bin/python scripts/gather_real_frames.py /tmp/h2/frames
"""

from __future__ import annotations

import argparse
import csv
import hashlib
import subprocess
import sys
from pathlib import Path

#: (repository, commit, path, licence, what; "left" cuts the left half of a side-by-side file)
FRAMES = [
    # a real circular-fisheye photograph (OCamCalib's sample, University of Zurich)
    ("JarnoRalli/python_camera_library", "8e484063920fc9c96cb7886af0a9440e6041c8c2",
     "test_data/fish_eye_camera/test_fisheye.jpg",
     "repository BSD-3-Clause; the image is OCamCalib's (Scaramuzza, ETH/UZH) sample, no licence stated",
     "circular fisheye", ""),
    # action camera and VR180 frames, side by side (left half kept)
    ("steren/stereo-img", "bbd3e31aee7c2dcff8ff05f1299adaeaec3e77b4", "examples/GOPR0.left-right.jpg",
     "repository Apache-2.0; a personal photograph of the author (sources.md)", "GoPro frame (left of a pair)", "left"),
    ("steren/stereo-img", "bbd3e31aee7c2dcff8ff05f1299adaeaec3e77b4", "examples/calf-left-right.jpg",
     "repository Apache-2.0; donated to the repository (sources.md)", "VR180 fisheye camera (left of a pair)", "left"),
    ("steren/stereo-img", "bbd3e31aee7c2dcff8ff05f1299adaeaec3e77b4", "examples/Panasonic-DMC-GX8-left.jpg",
     "repository Apache-2.0; donated to the repository (sources.md)", "Panasonic GX8 with the H-FT012 3D lens", ""),
    # street and landscape frames with open skies (OpenSfM's sample data sets)
    *[("mapillary/OpenSfM", "238744cdf3b5d50149c50d136a87f7fea25ad5cd", f"data/berlin/images/{i:02d}.jpg",
       "repository BSD-2-Clause; the data sets carry no licence of their own", "street, sky (phone)", "")
      for i in range(1, 4)],
    *[("mapillary/OpenSfM", "238744cdf3b5d50149c50d136a87f7fea25ad5cd", f"data/lund/images/{i:02d}.jpg",
       "repository BSD-2-Clause; the data sets carry no licence of their own", "cathedral, sky (one camera)", "")
      for i in range(1, 30)],
]


def _snapshot(repo: str, given: dict[str, str]) -> Path | None:
    if repo in given:
        return Path(given[repo])
    p = Path("/work/.mirror") / repo.replace("/", "+") / "repo"
    return p if p.is_dir() else None


def _blob(gitdir: Path, commit: str, path: str) -> tuple[str, bytes] | None:
    """(blob id, bytes) of ``path`` at ``commit`` (HEAD when the commit is absent), or None."""
    for rev in (commit, "HEAD"):
        r = subprocess.run(["git", "-C", str(gitdir), "rev-parse", "--verify", "--quiet", f"{rev}:{path}"],
                           capture_output=True, text=True)
        if r.returncode == 0:
            oid = r.stdout.strip()
            b = subprocess.run(["git", "-C", str(gitdir), "cat-file", "blob", oid], capture_output=True)
            return (oid, b.stdout) if b.returncode == 0 and b.stdout else None
    return None


def _left_half(data: bytes, dest: Path) -> None:
    import OpenImageIO as oiio
    import tempfile

    with tempfile.NamedTemporaryFile(suffix=".jpg") as tmp:
        tmp.write(data)
        tmp.flush()
        buf = oiio.ImageBuf(tmp.name)
        w, h = buf.spec().width, buf.spec().height
        half = oiio.ImageBufAlgo.cut(buf, oiio.ROI(0, w // 2, 0, h))
        half.specmod().attribute("Compression", "jpeg:95")
        if not half.write(str(dest)):
            raise OSError(half.geterror())


def parse_args(doc: str, argv: list[str] | None) -> tuple[Path, dict[str, str]]:
    """The gather scripts' command line: the folder to fill and the ``--snapshot`` map."""
    ap = argparse.ArgumentParser(description=doc.split("\n\n")[0])
    ap.add_argument("out", type=Path, help="folder to fill (never inside the repository)")
    ap.add_argument("--snapshot", action="append", default=[], metavar="OWNER/NAME=DIR",
                    help="a repository's snapshot (bare git dir or work tree)")
    args = ap.parse_args(argv)
    return args.out, dict(s.split("=", 1) for s in args.snapshot)


def gather(out: Path, given: dict[str, str], frames) -> int:
    """Take each of ``frames`` — (repository, commit, path, licence, what, cut) — out of its
    snapshot into ``out`` (``cut == "left"``: the left half, re-encoded) and write
    ``out/manifest.csv``; returns the exit status (1 when nothing was gathered)."""
    out.mkdir(parents=True, exist_ok=True)
    rows, missing = [], 0
    for repo, commit, path, licence, what, cut in frames:
        snap = _snapshot(repo, given)
        got = _blob(snap, commit, path) if snap else None
        if got is None:
            print(f"missing: {repo}:{path} (no snapshot or blob)", file=sys.stderr)
            missing += 1
            continue
        oid, data = got
        name = f"{repo.split('/')[1]}__{path.replace('/', '_')}"
        dest = out / (name.rsplit(".", 1)[0] + ".left.jpg" if cut == "left" else name)
        if cut == "left":
            _left_half(data, dest)
        else:
            tmp = dest.with_name(dest.name + ".part")
            tmp.write_bytes(data)
            tmp.replace(dest)
        rows.append({"file": dest.name, "repository": f"https://github.com/{repo}", "path": path, "commit": commit,
                     "blob": oid, "sha256": hashlib.sha256(data).hexdigest(), "licence": licence, "what": what,
                     "derived": "left half, re-encoded JPEG q95, no EXIF" if cut else ""})
    with (out / "manifest.csv").open("w", newline="", encoding="utf-8") as fh:
        wr = csv.DictWriter(fh, fieldnames=list(rows[0]) if rows else ["file"])
        wr.writeheader()
        wr.writerows(rows)
    print(f"{len(rows)} frames in {out} ({missing} missing); manifest {out / 'manifest.csv'}")
    return 0 if rows else 1


def main(argv: list[str] | None = None) -> int:
    return gather(*parse_args(__doc__, argv), FRAMES)


if __name__ == "__main__":
    sys.exit(main())
