"""A frame's outputs: their formats, names and folders, and the rules that keep them safe.

The ``--output-format`` choices and how ``auto`` resolves for one input; the name every
output of an input carries (hostile names percent-encoded, long ones cut), where it goes
(sub-folders mirrored, never outside the output folder), the sweep of dead writers'
temporaries; no output may replace an input of its run; the original kept when nothing
is applied; a corrected frame checked against what its format holds.
"""

from __future__ import annotations

import contextlib
import errno
import hashlib
import logging
import os
import shutil
from dataclasses import dataclass
from pathlib import Path, PurePath
from typing import TYPE_CHECKING, Any, Container, Iterable, Sequence

from vigproc.atomic import TEMP_KEY, atomic_path, replacing, temporary_keys
from vigproc.errors import (CONTROL_ESCAPES, ImageWriteError, OutputFormatError, OutputRefusedError,
                            OutputSettingsError, VigprocError, write_error)
from vigproc.io.formats import WRITE_EXT_FORMAT

if TYPE_CHECKING:  # annotations only
    import numpy as np

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class OutputFormat:
    """How a corrected frame is written (:func:`vigproc.io.metadata.write_corrected`).

    Attributes
    ----------
    suffix : str
        File name suffix of the output.
    format : str
        Writer format: ``jpeg``, ``png``, ``tiff``, ``openexr`` or ``dng`` (a copy of a DNG
        input, the correction as an opcode: :func:`vigproc.io.dng_vignette.write_dng_correction`).
    depth : str
        Sample type: ``uint8``, ``uint16``, ``half`` or ``float``.
    transfer : str
        ``srgb`` (display-ready, what JPEG/PNG viewers expect) or ``linear``.
    quality : int or None
        JPEG quality.
    """

    suffix: str
    format: str
    depth: str
    transfer: str = "linear"
    quality: int | None = None

    @property
    def integer(self) -> bool:
        return self.depth in ("uint8", "uint16")


#: --output-format choices. ``auto`` (the default): the input's own kind back
#: (:func:`output_format_for`); the others for linear work or a fixed format.
OUTPUT_FORMATS: dict[str, OutputFormat | None] = {
    "auto": None,
    "jpeg": OutputFormat(".jpg", "jpeg", "uint8", "srgb"),
    "png": OutputFormat(".png", "png", "uint16", "srgb"),
    "tiff16": OutputFormat(".tif", "tiff", "uint16"),
    "tiff-float": OutputFormat(".tif", "tiff", "float"),
    "exr-half": OutputFormat(".exr", "openexr", "half"),
    "exr-float": OutputFormat(".exr", "openexr", "float"),
    "dng": OutputFormat(".dng", "dng", "float"),  # DNG inputs only: raw pixels kept, correction as an opcode
}
#: An ``auto`` JPEG output is saved at the source's own quality (IJG scale), but never
#: below this: a second lossy pass at a low quality would show.
MIN_AUTO_JPEG_QUALITY = 90


def output_format_for(name: str, path: str | os.PathLike[str], info: Any = None,
                      like: str | os.PathLike[str] | None = None) -> OutputFormat:
    """The output format ``name`` (:data:`OUTPUT_FORMATS`) resolved for one input.

    ``auto`` gives the input's own kind back: a JPEG as a JPEG (sRGB, at the source's
    quality, at least :data:`MIN_AUTO_JPEG_QUALITY`; the suffix as the input spells
    it), a PNG as a PNG (8-bit sRGB from 8-bit sRGB, else 16-bit), a TIFF as a linear
    16-bit or float TIFF, an EXR as a half or float EXR (as stored), a RAW as a
    linear 16-bit TIFF. ``info`` (:class:`vigproc.io.images.ImageInfo`, once the input is
    read) refines the sample type; without it the suffix is already final. ``like``:
    resolve ``auto`` by this file name's suffix instead (an output file a host named).
    """
    from vigproc.io.jpeg import DEFAULT_JPEG_QUALITY, jpeg_quality  # numpy: not at start-up

    path = Path(path)
    fixed = OUTPUT_FORMATS.get(name, "missing")
    if fixed == "missing":
        raise VigprocError(f"unknown output format {name!r}")
    src_suffix = Path(like).suffix.lower() if like is not None else path.suffix.lower()
    if fixed is not None and fixed.format == "dng" and src_suffix != ".dng":
        raise OutputFormatError(f"--output-format dng needs a DNG input, not {path.name!r}")
    if fixed is not None and fixed.format != "jpeg":
        return fixed
    kind = "jpeg" if fixed is not None else WRITE_EXT_FORMAT.get(src_suffix)  # RAW and others: tiff16
    depth = getattr(info, "bit_depth", None)
    transfer = getattr(info, "transfer", None)
    if kind == "jpeg":  # at the source's own quality when it is a JPEG
        # the quality read with the pixels, else a look at the file's head
        q = (getattr(info, "quality", None) or jpeg_quality(path)) if getattr(info, "format", None) == "jpeg" else None
        return OutputFormat(fixed.suffix if fixed is not None else src_suffix, "jpeg", "uint8", "srgb",
                            max(q or DEFAULT_JPEG_QUALITY, MIN_AUTO_JPEG_QUALITY))
    if kind == "png":
        eight = depth in (None, "uint8") and transfer != "linear"
        return OutputFormat(src_suffix, "png", "uint8" if eight else "uint16",
                            "linear" if transfer == "linear" else "srgb")
    if kind == "tiff":
        return OutputFormat(src_suffix, "tiff", "float" if depth in ("half", "float", "double") else "uint16")
    if kind == "openexr":
        return OutputFormat(".exr", "openexr", "half" if depth == "half" else "float")
    return OUTPUT_FORMATS["tiff16"]  # a RAW: linear 16 bits, what raw editors take

#: Sidecar suffix: the sidecar is written last, so its presence means the frame is done.
SIDECAR_SUFFIX = ".vigproc.json"


# ------------------------------------------------------------------ naming
def safe_output(outdir: Path, stem: str, suffix: str) -> Path:
    """Output path inside ``outdir`` named ``stem + suffix``; never escapes ``outdir``.

    ``stem`` may come from a hostile file name: separators are flattened and leading
    dots dropped, and the result is checked to resolve inside ``outdir``.
    """
    name = stem.replace(os.sep, "_").replace("/", "_").replace("\x00", "_").lstrip(".") or "image"
    out = (outdir / f"{name}{suffix}").resolve()
    if out.parent != outdir.resolve():
        raise OutputRefusedError(f"refusing to write outside {outdir}: {out}")
    return out


#: Longest output stem in bytes: with the longest suffix (``.corrected.tif``,
#: ``.vigproc.json``, ``.vignetting.png``) a name stays well within the usual 255.
MAX_STEM_BYTES = 180


def shorten_stem(stem: str, identity: bytes) -> str:
    """``stem`` cut to :data:`MAX_STEM_BYTES` (UTF-8) if longer, with ``~`` and 16 hex
    digits of the SHA-256 of ``identity`` (the full name) appended, so two long names
    that share a prefix still differ; shorter stems are returned unchanged."""
    if len(stem.encode("utf-8")) <= MAX_STEM_BYTES:
        return stem
    digest = hashlib.sha256(identity).hexdigest()[:16]
    cut = stem
    while len(cut.encode("utf-8")) > MAX_STEM_BYTES - 17:
        cut = cut[:-1]
    if "%" in cut[-2:]:  # do not leave half an escape
        cut = cut[:cut.rindex("%")]
    return f"{cut}~{digest}"


def percent_encode(name: str, *, also: str = "", leading: str = "") -> str:
    """``name`` with control characters (bidi controls too, as their UTF-8 bytes),
    separators, bytes that are not UTF-8 (surrogate escapes), the characters in ``also`` anywhere and those in ``leading`` as the first
    character written as ``%XX``; everything else (spaces, letters of any script) kept."""
    out = []
    for i, ch in enumerate(name):
        o = ord(ch)
        if o < 0x20 or o == 0x7F or ch in ("/", os.sep) or ch in also or (i == 0 and ch in leading):
            out.append(f"%{o:02X}")
        elif 0xDC80 <= o <= 0xDCFF:  # a byte that is not UTF-8 (surrogate escape)
            out.append(f"%{o - 0xDC00:02X}")
        elif o > 0x7F and o in CONTROL_ESCAPES:  # C1 and bidi controls (an RLO turns a name around)
            out.append("".join(f"%{b:02X}" for b in ch.encode("utf-8")))
        else:
            out.append(ch)
    return "".join(out)


def output_name(name: str) -> str:
    """The name every output of an input named ``name`` carries, for every front end
    (``correct``, ``hook``, ``watch``, ``batch``): the file name with its extension
    (``x.jpg`` and ``x.png`` differ), ``%``, control characters, bytes that are not
    UTF-8 and separators percent-encoded, and a leading ``-`` or ``.`` too, so the map
    is one-to-one and no output is hidden or read as an option; over
    :data:`MAX_STEM_BYTES` it is cut and given a hash of the full name.

    Examples
    --------
    >>> output_name("IMG_1.jpg"), output_name("100%.jpg"), output_name(".x.png")
    ('IMG_1.jpg', '100%25.jpg', '%2Ex.png')
    """
    return shorten_stem(percent_encode(name, also="%", leading="-.") or "image", os.fsencode(name))


def output_location(root: str | os.PathLike[str], rel: str | os.PathLike[str], *,
                    create: bool = True) -> tuple[Path, str]:
    """Where the outputs of an input at ``rel`` (relative to the folder a run was given)
    go: the same sub-folders under ``root`` (each named by :func:`output_name`) and the
    input's :func:`output_name`. ``create`` makes the folders. Raises ImageWriteError for
    a path that would leave ``root`` (``..``, absolute) or a folder that resolves outside
    it (a planted symbolic link)."""
    parts = PurePath(rel).parts
    if not parts or PurePath(rel).is_absolute() or ".." in parts:
        raise OutputRefusedError(f"refusing output location {os.fspath(rel)!r}")
    root = Path(root)
    folder = root.joinpath(*(output_name(p) for p in parts[:-1]))
    if create:
        try:
            folder.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            # the output side's fault (a file in the way, a read-only or vanished disk): retried, never the photo's
            in_way = " (a file of that name is in the way)" if exc.errno in (errno.EEXIST, errno.ENOTDIR) else ""
            raise write_error(f"cannot create output folder {folder}: {exc.strerror or exc}{in_way}", exc) from None
        if not folder.resolve().is_relative_to(root.resolve()):
            raise OutputRefusedError(f"refusing to write outside {root}: {folder} resolves to {folder.resolve()}")
    return folder, output_name(parts[-1])


def _image_base(stem: str, source: Path) -> str:
    """``stem`` without the input's extension (``IMG_1.jpg`` → ``IMG_1``)."""
    ext = source.suffix
    return stem[: -len(ext)] if ext and stem.lower().endswith(ext.lower()) and len(stem) > len(ext) else stem


def temp_key(stem: str, source: str | os.PathLike[str]) -> str:
    """The prefix every output of an input (``stem``, from the file ``source``) starts
    with, cut to :data:`vigproc.atomic.TEMP_KEY`: ``IMG_1.`` covers ``IMG_1.jpg.vigproc.json``
    and ``IMG_1.corrected.jpg`` alike (sweeps of dead writers' temporaries match on it)."""
    return (_image_base(stem, Path(source)) + ".")[:TEMP_KEY]


def sweep_temporaries(root: str | os.PathLike[str], rels: Iterable[str | os.PathLike[str]], *,
                      keep: Iterable[str | os.PathLike[str]] = ()) -> int:
    """Remove the temporary files that killed writers left beside the outputs (under
    ``root``) of the inputs at ``rels`` (relative to the run's input folder).

    A killed writer cannot clean up: its half-written temporary (a hidden file next
    to the output, never the output itself) stays.  Only hidden names made from those
    inputs' :func:`temp_key` and carrying a temporary marker are removed (the output
    folder may be shared), none that could be a temporary of an input of ``keep``
    (still being written), and each folder is listed once.  Call it only when nothing
    writes the outputs of ``rels``; an input without a valid output location is
    skipped.

    Returns
    -------
    int
        Files removed.
    """
    def keys(inputs: Iterable[str | os.PathLike[str]]) -> dict[Path, set[str]]:
        by_folder: dict[Path, set[str]] = {}
        for rel in inputs:
            try:
                folder, stem = output_location(root, rel, create=False)
            except VigprocError:
                continue
            by_folder.setdefault(folder, set()).add(temp_key(stem, rel))
        return by_folder

    busy = keys(keep)
    removed = 0
    for folder, stems in keys(rels).items():
        try:
            entries = os.scandir(folder)
        except OSError:
            continue
        with entries:
            for e in entries:
                k = temporary_keys(e.name)
                if k & stems and not k & busy.get(folder, set()) and e.is_file(follow_symlinks=False):
                    try:
                        os.unlink(e.path)
                    except OSError:
                        continue
                    removed += 1
    return removed


def sweep_flat_temporaries(outdir: str | os.PathLike[str], files: Sequence[Path], stems: Sequence[str]) -> int:
    """Remove the temporaries killed writers left in ``outdir`` for the outputs of a flat
    run (``correct``: every output in one folder, named from ``stems``, :func:`output_stems`).

    Only hidden names carrying a temporary marker and starting with one of these inputs'
    output base (``IMG_1.``, its first 40 bytes: every writer's temporary keeps at least
    that much of the output's name) are removed, so another run's temporaries in a shared
    folder stay unless their inputs share that much of a name. Call it only when nothing
    writes these outputs.

    Returns
    -------
    int
        Files removed.
    """
    bases: dict[int, set[str]] = {}
    for f, stem in zip(files, stems):
        b = (_image_base(stem, Path(f)) + ".").encode("utf-8", "surrogateescape")[:40]
        b = b.decode("utf-8", "ignore")
        bases.setdefault(len(b), set()).add(b)
    removed = 0
    try:
        entries = os.scandir(outdir)
    except OSError:
        return 0
    with entries:
        for e in entries:
            ours = temporary_keys(e.name) and any(e.name[d:d + n] in bs for d in (1, 2) for n, bs in bases.items())
            if ours and e.is_file(follow_symlinks=False):
                with contextlib.suppress(OSError):
                    os.unlink(e.path)
                    removed += 1
    return removed


def corrected_name(stem: str, source: Path, suffix: str) -> str:
    """The corrected image's file name: ``IMG_1.corrected.jpg`` when the format is the
    input's own (``IMG_1.jpg``), ``IMG_1.nef.corrected.tif`` when it changes, so two
    inputs of one folder never share an output."""
    if source.suffix.lower() == suffix.lower():
        return f"{_image_base(stem, source)}.corrected{suffix}"
    return f"{stem}.corrected{suffix}"


def output_stems(files: Sequence[Path]) -> list[str]:
    """One distinct :func:`output_name` per input of a flat run (``correct``, ``hook
    -o``): two ``a.jpg`` from different folders must not overwrite each other's outputs.

    The first input of a name keeps it; a later one gets the first ``-2``, ``-3``...
    before its extension not taken by *any* input's own name, so ``x/a.tif y/a.tif
    a-2.tif`` give ``a.tif``, ``a-3.tif``, ``a-2.tif``.  Names are compared
    case-insensitively (such filesystems merge them); the same inputs in the same
    order always get the same names."""
    bases = [output_name(f.name) for f in files]
    taken = {b.casefold() for b in bases}
    first: set[str] = set()
    stems = []
    for f, base in zip(files, bases):
        key = base.casefold()
        if key not in first:
            first.add(key)
            stems.append(base)
            continue
        head = _image_base(base, f)
        tail = base[len(head):]
        n = 2
        while f"{head}-{n}{tail}".casefold() in taken:
            n += 1
        stem = f"{head}-{n}{tail}"
        taken.add(stem.casefold())
        stems.append(stem)
    return stems


class InputFiles:
    """The input files of one run (``correct``, ``hook``): no output of the run may
    replace one of them (``-o o`` with inputs ``o/a.tif`` and ``o/a.corrected.tif``
    would otherwise overwrite the second with the first's output).

    Pass it to :meth:`Processor.process_file` as ``protect``.  An input is matched by
    its resolved path and, when it exists, by its file identity (the same file under
    another spelling: a case-insensitive filesystem, a hard link)."""

    def __init__(self, files: Iterable[str | os.PathLike[str]]) -> None:
        self._paths: set[Path] = set()
        self._ids: set[tuple[int, int]] = set()
        for f in files:
            try:
                self._paths.add(Path(f).resolve())
                st = os.stat(f)
            except (OSError, RuntimeError, ValueError):  # missing or unusable: fails on its own later
                continue
            self._ids.add((st.st_dev, st.st_ino))

    def __contains__(self, path: object) -> bool:
        if not isinstance(path, (str, os.PathLike)):
            return False
        try:
            if Path(path).resolve() in self._paths:
                return True
            st = os.stat(path)
        except (OSError, RuntimeError, ValueError):
            return False
        return (st.st_dev, st.st_ino) in self._ids


def keep_original(src: Path, dst: Path, *, link: bool = False) -> None:
    """Put the original ``src`` at ``dst`` unchanged (a frame nothing was applied to):
    a hard link when ``link`` and the file systems allow it, else a copy of its bytes;
    atomically (temporary name, then rename), so ``dst`` is whole or absent."""
    try:
        if link:
            linked = False
            try:
                # a name only (os.link never overwrites); no chmod: a hard link's mode is the input's own
                with replacing(dst, create=False, chmod=False) as tmp:
                    os.link(src, tmp)
                    linked = True
                return
            except OSError as exc:  # another file system, or links not allowed: copy instead
                if linked:
                    raise
                log.debug("cannot link %s (%s); copying it", src, exc.strerror or exc)
        with atomic_path(dst) as tmp_path:  # a copy is an output like the others (mode, fsync)
            shutil.copyfile(src, tmp_path)
    except OSError as exc:
        raise write_error(f"cannot write {os.fspath(dst)!r}: {exc.strerror or exc}", exc) from None


def _format_label(fmt: OutputFormat) -> str:
    """The --output-format name of ``fmt``, or what it is ("8-bit JPEG")."""
    bits = {"uint8": "8-bit", "uint16": "16-bit", "half": "half-float", "float": "float"}[fmt.depth]
    kind = {"jpeg": "JPEG", "png": "PNG", "tiff": "TIFF", "openexr": "EXR", "dng": "DNG"}[fmt.format]
    return next((k for k, v in OUTPUT_FORMATS.items() if v == fmt), f"{bits} {kind}")


def _check_range(out: np.ndarray, fmt: OutputFormat) -> None:
    """A corrected frame must be representable in its output format: values beyond a
    float format's range would be written as Inf (HDR frames in absolute units in
    half-float EXR, say)."""
    from vigproc.io.image_write import FLOAT_MAX  # numpy and OpenImageIO: not at start-up

    limit = FLOAT_MAX.get(fmt.depth)
    if limit is None:  # integer formats are clipped to the white point by design
        return
    hi, lo = float(out.max()), float(out.min())
    if not (hi <= limit and lo >= -limit):  # also NaN
        wider = " (tiff-float and exr-float hold 3.4e38)" if fmt.depth == "half" else ""
        raise OutputRefusedError(
            f"corrected values reach {max(abs(hi), abs(lo)):.4g}, beyond the {limit:.4g} that "
            f"{_format_label(fmt)} holds: scale the input down or choose a wider output format{wider}")


def _note_clipping(img: np.ndarray | None, out: np.ndarray, where: str, fmt: OutputFormat, *,
                   source_white: int | None = None) -> None:
    """Say when samples end up above the white point of an integer output (clipped there
    by design): pushed there by the correction, or above it in a float source.  A source's
    own clipped highlights (exactly 1.0) are not counted (``source_white``: their number,
    counted before a correction in place; else counted in ``img``)."""
    from vigproc.pipeline.encoded import white_samples  # numpy: not at start-up

    if source_white is None:
        source_white = white_samples(img, source=True)
    lost = white_samples(out) - source_white
    if lost > 1e-3 * out.size:
        # lifted corners of a bright frame clip a little in any display format: worth a
        # warning from 1 % of the samples on, below that only a note
        (log.warning if lost > 1e-2 * out.size else log.info)(
            "%s: %.1f %% of the samples are above the white point and %s clips them "
            "(a float output format keeps them)", where, 100.0 * lost / out.size, _format_label(fmt))


def output_folder(path: str | os.PathLike[str]) -> Path:
    """Create (if needed) the output folder of a command.

    Raises
    ------
    ImageWriteError
        It cannot be created or is not a folder (a file, a read-only mount), or the path
        is empty.
    """
    if not os.fspath(path):
        raise ImageWriteError("the output folder is an empty path: name a folder ('.' for this one)")
    out = Path(path)
    if ".." in out.parts:
        # mkdir would make every folder the path names on its way, "x" of "x/../y" too
        real = os.path.realpath(out)
        out = Path(real) if out.is_absolute() else Path(os.path.relpath(real))
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise write_error(f"cannot create output folder {str(out)!r}: {exc.strerror or exc}", exc) from None
    return out


def output_file(path: str | os.PathLike[str] | None) -> Path | None:
    """Prepare a command's single output file before any work: create its folder if
    needed (a long benchmark must not fail only when it writes its result).

    Raises
    ------
    ImageWriteError
        The folder cannot be created, or ``path`` is a folder.
    """
    if path is None:
        return None
    out = Path(path)
    output_folder(out.parent)
    if out.is_dir():
        raise OutputSettingsError(f"cannot write {str(out)!r}: it is a folder")
    return out


def refuse_input(output: str | os.PathLike[str] | None, *inputs: Container[Any]) -> None:
    """Raise :class:`ImageWriteError` if ``output`` is in one of ``inputs`` (an
    :class:`InputFiles`, or the paths themselves): no output of a run replaces one of
    its inputs.  Checked before any work is done."""
    if output is not None and any(output in c for c in inputs):
        raise OutputSettingsError(f"refusing to overwrite {str(output)!r}: it is an input of this run")
