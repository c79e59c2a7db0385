"""``vigproc bench throughput``: full-size photographs end to end, beside the floor.

What a user feels is ``vigproc correct`` on a folder of photographs. This bench runs it
as a subprocess (``--unapplied copy``: every input yields an image) and, in the same
run, the *floor* any such tool pays: each file decoded and re-encoded by OpenImageIO at
its own JPEG quality, and the source's EXIF copied into the outputs by one exiftool
batch call; and ``darktable-cli`` exporting the same folder when it is installed.
Every timing is a whole new process on the same copied folder; rounds interleave the
tools so a busy machine weighs on all of them alike.

With ``raw=True`` (``vigproc bench throughput --raw DIR``) the photographs are camera
RAW files: vigproc's ``correct`` writes each as its linear 16-bit TIFF (``--unapplied
write``: a frame not corrected is written too, as developed), and the floor is rawpy's
own development with vigproc's settings (:data:`vigproc.io.images.RAW_DEVELOP`), the
same 16-bit TIFF written by OpenImageIO, and the sources' EXIF copied by one exiftool
batch call.

``python -m benchmarks.throughput floor IN OUT`` runs the floor on its own
(``rawfloor IN OUT``: the RAW floor).
"""

from __future__ import annotations

import logging
import os
import shutil
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Sequence

import numpy as np

from benchmarks import child_code
from vigproc.errors import VigprocError
from vigproc.io.formats import READ_SUFFIXES

log = logging.getLogger(__name__)

#: The suffixes the bench takes (the floor re-encodes JPEGs at their own quality).
JPEG_SUFFIXES = READ_SUFFIXES["jpeg"]
#: A tool's run may take at most this long (seconds) before the bench gives up on it.
TIMEOUT = 3600.0


@dataclass(frozen=True)
class Photo:
    """One photograph of the bench: its path and size."""

    path: Path
    width: int
    height: int

    @property
    def megapixels(self) -> float:
        return self.width * self.height / 1e6


@dataclass
class ToolTiming:
    """One tool's wall-clock seconds per round, and how many outputs its last round made."""

    name: str
    command: list[str]
    seconds: list[float] = field(default_factory=list)
    outputs: int = 0
    #: another source tree whose vigproc runs (its folder on PYTHONPATH), or None
    tree: str | None = None

    @property
    def median(self) -> float:
        return float(np.median(self.seconds)) if self.seconds else float("nan")


@dataclass
class ThroughputResult:
    """What :func:`run_throughput` measured (``vigproc bench throughput --json``)."""

    photos: list[str]
    megapixels: float
    rounds: int
    tools: list[ToolTiming]
    skipped: dict[str, str]

    def rows(self) -> list[tuple[str, float, float, float, int, float]]:
        """(tool, median seconds, MP/s, ratio to the floor, outputs, ratio to the
        overlapped floor or NaN) per tool."""
        floor = next(t.median for t in self.tools if t.name == "floor")
        lap = next((t.median for t in self.tools if t.name == "floor-overlap"), float("nan"))
        return [(t.name, t.median, self.megapixels / t.median, t.median / floor, t.outputs, t.median / lap)
                for t in self.tools]


def select_photos(folder: Path, min_megapixels: float = 0.75, limit: int | None = None) -> tuple[list[Photo], dict]:
    """The JPEGs under ``folder`` of at least ``min_megapixels`` that decode whole.

    Returns
    -------
    (photos, skipped)
        The photographs (sorted by path) and ``{path: reason}`` for JPEGs left out.
    """
    from vigproc.io.images import read_image

    if not folder.is_dir():
        raise VigprocError(f"not a folder: {folder}")
    photos, skipped = [], {}
    for p in sorted(q for q in folder.rglob("*") if q.is_file() and q.suffix.lower() in JPEG_SUFFIXES):
        try:
            img, info = read_image(p)
        except VigprocError as exc:  # truncated and stub JPEGs: no image to time
            skipped[str(p)] = str(exc)
            continue
        constant = float(img.max()) == float(img.min())
        del img
        if constant:  # a stub whose pixels are all one value: vigproc refuses it, the floor would not
            skipped[str(p)] = "constant frame (nothing to estimate vignetting from)"
            continue
        photo = Photo(p, info.width, info.height)
        if photo.megapixels < min_megapixels:
            continue
        photos.append(photo)
        if limit and len(photos) >= limit:
            break
    if not photos:
        raise VigprocError(f"no decodable JPEG of at least {min_megapixels} MP under {folder}")
    return photos, skipped


def select_raws(folder: Path, limit: int | None = None) -> tuple[list[Photo], dict]:
    """The camera RAW files under ``folder`` LibRaw develops (by path).

    Returns
    -------
    (photos, skipped)
        The RAW files (sorted by path, their developed size) and ``{path: reason}`` for
        RAW-named files left out.
    """
    from vigproc.io.images import RAW_EXTENSIONS, read_image

    if not folder.is_dir():
        raise VigprocError(f"not a folder: {folder}")
    photos, skipped = [], {}
    for p in sorted(q for q in folder.rglob("*") if q.is_file() and q.suffix.lower() in RAW_EXTENSIONS):
        try:
            img, info = read_image(p, raw_half_size=True)  # is it a RAW LibRaw develops?
        except VigprocError as exc:  # stubs whose image data was stripped
            skipped[str(p)] = str(exc)
            continue
        del img
        if info.format != "raw":
            skipped[str(p)] = f"not developed by LibRaw (read as {info.format})"
            continue
        import rawpy

        with rawpy.imread(str(p)) as raw:  # the full development's size (never rotated)
            photos.append(Photo(p, int(raw.sizes.width), int(raw.sizes.height)))
        if limit and len(photos) >= limit:
            break
    if not photos:
        raise VigprocError(f"no RAW file LibRaw develops under {folder}")
    return photos, skipped


def stage(photos: Sequence[Photo], into: Path) -> list[Path]:
    """Copy the photographs into ``into`` under plain distinct names (``000_NAME.jpg``),
    so every tool reads the same bytes and no name is taken for an option."""
    into.mkdir(parents=True, exist_ok=True)
    out = []
    for i, ph in enumerate(photos):
        safe = "".join(c if c.isascii() and (c.isalnum() or c in "._-") else "_" for c in ph.path.name)
        dst = into / f"{i:03d}_{safe}"
        shutil.copyfile(ph.path, dst)
        out.append(dst)
    return out


def floor_run(src: Path, dst: Path, overlap: bool = False) -> int:
    """The floor: every JPEG in ``src`` decoded and re-encoded by OpenImageIO at its own
    quality into ``dst`` (same name), then the sources' EXIF copied into them by one
    exiftool call. Returns the number of images written.

    ``overlap``: the next file is decoded in one thread and the previous one encoded in
    another while the current one is handed on, as ``vigproc correct`` overlaps its
    stages (the floor such a design has to be compared with)."""
    from concurrent.futures import ThreadPoolExecutor

    dst.mkdir(parents=True, exist_ok=True)
    files = [p for p in sorted(src.iterdir()) if p.suffix.lower() in JPEG_SUFFIXES]
    if overlap:
        with ThreadPoolExecutor(1) as reading, ThreadPoolExecutor(1) as writing:
            ahead = [reading.submit(_floor_decode, p) for p in files[:2]]  # two frames held at most
            writes = []
            for k, p in enumerate(files):
                spec, pixels = ahead.pop(0).result()
                if k + 2 < len(files):
                    ahead.append(reading.submit(_floor_decode, files[k + 2]))
                if writes:
                    writes.pop(0).result()  # one frame being encoded at most
                writes.append(writing.submit(_floor_encode, p, dst, spec, pixels))
            for w in writes:
                w.result()
    else:
        for p in files:
            _floor_encode(p, dst, *_floor_decode(p))
    # one batch call: each output takes the tags of the source of its own name
    from vigproc.io.metadata import exiftool_path

    subprocess.run([exiftool_path(), "-q", "-q", "-overwrite_original", "-tagsFromFile", f"{src}/%f.%e",
                    "-all:all", "--", str(dst)], check=True, stdin=subprocess.DEVNULL)
    return len(files)


def _floor_decode(p: Path):
    import OpenImageIO as oiio

    inp = oiio.ImageInput.open(str(p))
    if inp is None:
        raise VigprocError(f"floor: cannot open {p}: {oiio.geterror()}")
    spec = inp.spec()
    pixels = inp.read_image(0, 0, 0, spec.nchannels, "uint8")
    inp.close()
    return spec, pixels


def _floor_encode(p: Path, dst: Path, spec, pixels) -> None:
    import OpenImageIO as oiio

    from vigproc.io.images import DEFAULT_JPEG_QUALITY, jpeg_quality

    out_spec = oiio.ImageSpec(spec.width, spec.height, spec.nchannels, "uint8")
    out_spec.attribute("Compression", f"jpeg:{jpeg_quality(p) or DEFAULT_JPEG_QUALITY}")
    out = oiio.ImageOutput.create(str(dst / p.name))
    if out is None or not out.open(str(dst / p.name), out_spec) or not out.write_image(pixels):
        raise VigprocError(f"floor: cannot write {dst / p.name}: {oiio.geterror()}")
    out.close()


def raw_floor_run(src: Path, dst: Path) -> int:
    """The RAW floor: every RAW in ``src`` developed by rawpy with vigproc's settings
    (:data:`vigproc.io.images.RAW_DEVELOP`) and written by OpenImageIO as the linear
    16-bit TIFF ``vigproc correct`` writes (``NAME.EXT.tif``), then the sources' EXIF
    copied into them by one exiftool call. Returns the number of images written."""
    import OpenImageIO as oiio
    import rawpy

    from vigproc.io.images import RAW_DEVELOP, RAW_EXTENSIONS
    from vigproc.io.metadata import exiftool_path

    dst.mkdir(parents=True, exist_ok=True)
    n = 0
    for p in sorted(src.iterdir()):
        if p.suffix.lower() not in RAW_EXTENSIONS:
            continue
        with rawpy.imread(str(p)) as raw:
            rgb = raw.postprocess(**RAW_DEVELOP)
        h, w, c = rgb.shape
        target = dst / (p.name + ".tif")
        out = oiio.ImageOutput.create(str(target))
        if out is None or not out.open(str(target), oiio.ImageSpec(w, h, c, "uint16")) or not out.write_image(rgb):
            raise VigprocError(f"raw floor: cannot write {target}: {oiio.geterror()}")
        out.close()
        n += 1
    # one batch call: NAME.EXT.tif takes the tags of NAME.EXT
    subprocess.run([exiftool_path(), "-q", "-q", "-overwrite_original", "-tagsFromFile", f"{src}/%f",
                    "-all:all", "--", str(dst)], check=True, stdin=subprocess.DEVNULL)
    return n


def _commands(indir: Path, outdir: Path, inputs: Sequence[Path], darktable: str | None,
              baseline: str | None = None, raw: bool = False) -> dict[str, list[str]]:
    cmds = {
        "floor": [sys.executable, "-c", child_code("from benchmarks.throughput import main\nsys.exit(main())"),
                  "rawfloor" if raw else "floor", str(indir), str(outdir / "floor")],
        # the same work with decode, hand-on and encode overlapped in threads (as vigproc correct)
        **({} if raw else {"floor-overlap": [sys.executable, "-c", child_code(
            "from benchmarks.throughput import main\nsys.exit(main())"), "floor-overlap", str(indir),
            str(outdir / "floor-overlap")]}),
        # a RAW not corrected is still developed and written (what the floor does)
        "vigproc": [sys.executable, "-m", "vigproc.frontends.cli", "correct", "--unapplied", "write" if raw else "copy",
                    "-o", str(outdir / "vigproc"), "--", *map(str, inputs)],
    }
    if baseline:  # the same command from another source tree (before/after in one run)
        cmds["vigproc-baseline"] = [*cmds["vigproc"][:-len(inputs) - 3], "-o", str(outdir / "vigproc-baseline"), "--",
                                    *map(str, inputs)]
    if darktable:
        # its default processing of each frame, exported as JPEG; a private configuration
        cmds["darktable-cli"] = [darktable, str(indir), str(outdir / "darktable" / "$(FILE_NAME)"), "--out-ext", "jpg",
                                 "--core", "--configdir", str(outdir / "darktable-config"), "--library", ":memory:"]
    return cmds


def _count_images(folder: Path, suffixes: Sequence[str] = JPEG_SUFFIXES) -> int:
    if not folder.is_dir():
        return 0
    return sum(1 for p in folder.iterdir() if p.suffix.lower() in suffixes and not p.name.startswith("."))


def _env(t: ToolTiming, root: Path | None = None) -> dict[str, str]:
    """The environment a tool runs in: this one, with its own source tree first; with a
    baseline in the run, each vigproc has a profile store of its own under ``root`` (an
    older checkout may not open a newer store's schema)."""
    env = dict(os.environ)
    if t.tree:
        env["PYTHONPATH"] = t.tree
    if root is not None and t.name.startswith("vigproc"):
        env["VIGPROC_PROFILE_DB"] = str(root / f"profiles-{t.name}.sqlite")
    return env


def run_throughput(photos: Sequence[Photo], *, rounds: int = 3, darktable: bool = True,
                   workdir: Path | None = None, skipped: dict | None = None,
                   baseline: str | os.PathLike[str] | None = None, raw: bool = False) -> ThroughputResult:
    """Time vigproc, the floor and darktable-cli (when installed and ``darktable``) on
    copies of ``photos``, ``rounds`` times each, interleaved; with ``baseline`` (a
    source tree, e.g. another checkout's root) its ``vigproc correct`` too, each
    vigproc then with an empty profile store of its own. ``raw``: the photographs are
    camera RAW files (:func:`select_raws`, :func:`raw_floor_run`; darktable-cli is
    left out).

    Raises
    ------
    VigprocError
        A tool failed, or did not make one image per input.
    """
    dt = shutil.which("darktable-cli") if darktable and not raw else None
    made = (".tif",) if raw else JPEG_SUFFIXES
    with tempfile.TemporaryDirectory(prefix="vigproc-throughput-", dir=workdir) as tmp:
        root = Path(tmp)
        inputs = stage(photos, root / "in")
        base = os.fspath(Path(baseline).resolve()) if baseline else None
        tools = [ToolTiming(name, cmd, tree=base if name == "vigproc-baseline" else None)
                 for name, cmd in _commands(root / "in", root / "out", inputs, dt, base, raw).items()]
        stores = root if base else None
        for t in tools:  # untimed, on one photo: caches (Numba's compiled kernels) filled
            if t.name.startswith("vigproc"):
                warm = [*t.command[:t.command.index("-o")], "-o", str(root / "warm"), "--", str(inputs[0])]
                subprocess.run(warm, stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                               env=_env(t, stores), timeout=TIMEOUT, cwd=t.tree)
        for r in range(max(1, rounds)):
            order = tools[r % len(tools):] + tools[:r % len(tools)]
            for t in order:
                out = root / "out" / (t.name if t.name != "darktable-cli" else "darktable")
                shutil.rmtree(out, ignore_errors=True)
                shutil.rmtree(root / "out" / "darktable-config", ignore_errors=True)
                t0 = time.perf_counter()
                res = subprocess.run(t.command, stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL,
                                     stderr=subprocess.PIPE, env=_env(t, stores), timeout=TIMEOUT, cwd=t.tree)
                t.seconds.append(time.perf_counter() - t0)
                t.outputs = _count_images(out, made)
                if res.returncode != 0 or t.outputs < len(inputs):
                    tail = res.stderr.decode("utf-8", "replace").strip().splitlines()[-3:]
                    raise VigprocError(f"bench throughput: {t.name} exited {res.returncode} with {t.outputs} of "
                                       f"{len(inputs)} images: {' / '.join(tail)}")
                log.info("round %d: %s %.2f s", r + 1, t.name, t.seconds[-1])
    return ThroughputResult([str(p.path) for p in photos], sum(p.megapixels for p in photos), max(1, rounds),
                            tools, dict(skipped or {}))


def format_result(r: ThroughputResult) -> list[str]:
    """The printed table: one line per tool, the floor first."""
    lines = [f"{len(r.photos)} photographs, {r.megapixels:.1f} MP, median of {r.rounds} rounds (interleaved)",
             f"{'tool':<16}{'seconds':>9}{'MP/s':>8}{'x floor':>9}{'x overlapped floor':>20}"]
    for name, sec, mps, ratio, _, lap in r.rows():
        lines.append(f"{name:<16}{sec:>9.2f}{mps:>8.1f}{ratio:>9.2f}" + (f"{lap:>20.2f}" if lap == lap else ""))
    return lines


def main(argv: Sequence[str] | None = None) -> int:
    """``python -m benchmarks.throughput floor|rawfloor IN OUT``: the floor on its own."""
    args = list(sys.argv[1:] if argv is None else argv)
    if len(args) != 3 or args[0] not in ("floor", "floor-overlap", "rawfloor"):
        print("usage: python -m benchmarks.throughput floor|floor-overlap|rawfloor IN OUT", file=sys.stderr)
        return 2
    if args[0] == "rawfloor":
        raw_floor_run(Path(args[1]), Path(args[2]))
    else:
        floor_run(Path(args[1]), Path(args[2]), overlap=args[0] == "floor-overlap")
    return 0


if __name__ == "__main__":
    sys.exit(main())
