"""One frame through vigproc, the way every front end runs it.

file → linear image + lens key → model (stored profile, profile file, lensfun or a
fresh estimate) → correction, profile update or verdict → output file + JSON sidecar.

The command line (``correct``, ``demo``), the watch-folder daemon, batch jobs and the
pipeline hook all call :class:`Processor`, so a frame is handled identically whoever
asks.  A :class:`Processor` owns (or borrows) one exiftool process and one profile
store; it is not shared between threads (make one per worker).
"""

from __future__ import annotations

import errno
import hashlib
import json
import logging
import math
import os
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Container, Iterable, Sequence

from vigproc.errors import (CONTROL_ESCAPES, ImageReadError, ImageWriteError, ModelError, OutputFormatError, OutputRefusedError,
                            OutputSettingsError, VigprocError, write_error)
from vigproc.io.formats import IMAGE_SUFFIXES, WRITE_EXT_FORMAT  # noqa: F401  (IMAGE_SUFFIXES: re-exported)

log = logging.getLogger(__name__)

#: What a frame can be processed for.
MODES = ("correct", "check", "learn", "estimate")
#: ``profile`` values that say where a frame's model comes from; any other value is
#: ``source:NAME`` (a profile-source plugin) or the path of a profile file.
PROFILE_CHOICES = ("auto", "estimate", "lensfun", "embedded")
#: ``profile="source:NAME"``: the profile-source plugin NAME only.
SOURCE_PREFIX = "source:"


def names_profile_file(profile: str) -> bool:
    """Whether a ``profile`` setting is the path of a profile file (not one of
    :data:`PROFILE_CHOICES` nor ``source:NAME``): the one place that tells them apart."""
    return profile not in PROFILE_CHOICES and not profile.startswith(SOURCE_PREFIX)



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
#: When nothing is applied (weak evidence, a refused field, strength 0), what a correct run
#: writes: ``keep`` (the default: every photo comes out) the original under the output's
#: name, its bytes when the output is the input's own kind (else the frame as read, in the
#: output format); ``skip`` only the sidecar (saying why), ``copy`` the original's bytes as
#: ``STEM.uncorrected.EXT``, ``link`` a hard link of the original under that name
#: (a copy across file systems), ``write`` the frame as read, in the output format,
#: under the output's name (an explicit output file a host asked for).
UNAPPLIED_POLICIES = ("keep", "skip", "copy", "link", "write")
#: ``in_camera``: leave a JPEG the camera already corrected alone (``respect``) or not.
IN_CAMERA_POLICIES = ("respect", "ignore")


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
    from vigproc.io.images import DEFAULT_JPEG_QUALITY, jpeg_quality

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


#: Why nothing was applied to a frame whose estimate is weak: one wording for every front end.
WEAK_EVIDENCE = "weak evidence: the estimate is not clearly above its uncertainty"


def not_applied_reason(model) -> str:
    """Why an estimate that fell back was not applied: its quality's own reason (a
    glow-shaped fall-off, say), else :data:`WEAK_EVIDENCE`."""
    q = getattr(model, "quality", None)
    return q.reason if q is not None and q.reason else WEAK_EVIDENCE

#: Sidecar suffix: the sidecar is written last, so its presence means the frame is done.
SIDECAR_SUFFIX = ".vigproc.json"


@dataclass(frozen=True)
class Settings:
    """How frames are processed.

    Attributes
    ----------
    mode : str
        ``correct`` (write a corrected image), ``learn`` (pool the estimate into the
        lens's stored profile), ``estimate`` (model only) or ``check`` (forensic
        verdict: does the vignetting match the lens the EXIF names?).
    profile : str
        ``auto`` (a trusted stored profile of the frame's lens, else a DNG's own
        calibration (its vignetting opcodes), else the first installed profile-source
        plugin that has one, else estimate), ``estimate``, ``lensfun``, ``embedded``
        (the DNG's own opcodes only), ``source:NAME`` (that profile-source plugin only)
        or the path of a profile file.
    method : str
        Estimator for frames without a profile (see :data:`vigproc.core.estimate.METHODS`,
        or an installed estimator plugin, :mod:`vigproc.core.extensions`).
    transfer : str
        How stored values decode to linear light: ``auto``, ``linear`` or ``srgb``.
    output_format : str
        One of :data:`OUTPUT_FORMATS` (``auto``: each input's own kind back).
    unapplied : str
        Correct mode, when nothing is applied: one of :data:`UNAPPLIED_POLICIES`.
    strength : float
        Fraction of the fall-off removed (1 = all of it).
    picture : bool
        Also write a PNG of the fall-off.
    in_camera : str
        Correct mode: ``respect`` (a JPEG whose camera corrected its vignetting,
        :mod:`vigproc.io.incamera`, is left alone) or ``ignore``.
    learn : bool
        Correct mode: also pool each frame into its lens's stored profile, as learn
        mode does (learn as you go, :mod:`vigproc.pipeline.learning`); needs a store.
    """

    mode: str = "correct"
    profile: str = "auto"
    method: str = "default"
    transfer: str = "auto"
    output_format: str = "auto"
    strength: float = 1.0
    picture: bool = False
    unapplied: str = "keep"
    in_camera: str = "respect"
    learn: bool = False

    def __post_init__(self) -> None:
        from vigproc.core.methods import METHODS

        if self.mode not in MODES:
            raise VigprocError(f"unknown mode {self.mode!r} (choose from {', '.join(MODES)})")
        if self.method not in METHODS:
            from vigproc.core.extensions import UnknownMethodError, method_names

            if self.method not in method_names():
                raise UnknownMethodError(f"unknown method {self.method!r} (choose from {', '.join(method_names())})")
        if self.output_format not in OUTPUT_FORMATS:
            raise VigprocError(f"unknown output format {self.output_format!r}")
        if self.unapplied not in UNAPPLIED_POLICIES:
            raise VigprocError(f"unknown policy for frames not corrected {self.unapplied!r} "
                               f"(choose from {', '.join(UNAPPLIED_POLICIES)})")
        if self.in_camera not in IN_CAMERA_POLICIES:
            raise VigprocError(f"unknown in-camera policy {self.in_camera!r} (choose from {', '.join(IN_CAMERA_POLICIES)})")
        if self.learn and self.mode != "correct":
            raise VigprocError(f"learning as you go is for correct mode, not {self.mode!r} (learn mode pools anyway)")
        if self.transfer not in ("auto", "linear", "srgb"):
            raise VigprocError(f"unknown input transfer {self.transfer!r}")
        if not (math.isfinite(self.strength) and 0.0 <= self.strength <= 2.0):
            raise VigprocError(f"strength must be within [0, 2], got {self.strength}")

    @property
    def profile_is_file(self) -> bool:
        """Whether ``profile`` is the path of a profile file (:func:`names_profile_file`)."""
        return names_profile_file(self.profile)

    @property
    def needs_store(self) -> bool:
        """Whether processing uses the profile store: learn mode pools into it, check mode
        takes its reference from it and ``profile="auto"`` looks there first."""
        return self.mode in ("learn", "check") or self.profile == "auto" or self.learn

    def to_dict(self) -> dict[str, Any]:
        # learn only when set: the settings of runs that do not learn keep their job ids and sidecars
        return {k: getattr(self, k) for k in self.__dataclass_fields__ if k != "learn" or self.learn}


@dataclass
class FrameResult:
    """What was done to one frame (the JSON sidecar's content)."""

    file: str
    mode: str
    lens: dict[str, Any]
    source: str | None = None  # where the model came from
    model: Any = None  # VignettingModel applied (or estimated), None if none
    applied: bool = False  # whether a correction was divided out
    output: str | None = None
    picture: str | None = None
    profile: str | None = None  # the profile updated in learn mode
    verdict: dict[str, Any] | None = None  # check mode
    strength: float | None = None  # correct mode: the fraction of the fall-off divided out
    seconds: float = 0.0
    extra: dict[str, Any] = field(default_factory=dict)

    def to_dict(self) -> dict[str, Any]:
        d = {k: getattr(self, k) for k in self.__dataclass_fields__ if k != "extra"}
        if self.model is not None:
            d["model"] = self.model.to_dict()
        d.update(self.extra)
        return {k: v for k, v in d.items() if v is not None}


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
    from pathlib import PurePath

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
    from vigproc.atomic import TEMP_KEY

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
    from vigproc.atomic import temporary_keys

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
    import shutil

    from vigproc.atomic import atomic_path, replacing

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
    from vigproc.io.images import FLOAT_MAX

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
    from vigproc.pipeline.encoded import white_samples

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


def images_in(folder: Path, limit: int | None = None) -> list[Path]:
    """Image files under ``folder`` (recursive, sorted)."""
    if not folder.is_dir():
        raise VigprocError(f"not a folder: {folder}")
    files = sorted(p for p in folder.rglob("*") if p.is_file() and p.suffix.lower() in IMAGE_SUFFIXES)
    if not files:
        raise VigprocError(f"no images found under {folder}")
    return files[:limit] if limit else files


# ------------------------------------------------------------------ steps
def read_lens(reader, path: Path):
    """The frame's LensKey (or None) and a JSON-able record of it; an unidentifiable
    lens is reported, not fatal (the frame can still be estimated)."""
    from vigproc.errors import ImageReadError

    if reader is None:
        return None, {"lens_id": None, "error": "EXIF not read"}
    try:
        key = reader.read(path)
    except ImageReadError as exc:
        return None, {"lens_id": None, "error": str(exc)}
    return key, {"lens_id": key.lens_id(), "key": key.to_dict()}


from vigproc.io.provenance import file_sha256  # noqa: E402  (re-exported: a frame's content id)


def choose_model(img: np.ndarray, lens_key, settings: Settings, store, *, where: str = "frame",
                 sources=None, embedded=None, warnings: list[str] | None = None):
    """Model to apply and where it came from: ``profile-file``, ``lensfun``,
    ``stored-profile`` (a trusted profile of the lens: no estimation), ``embedded``
    (the DNG's own vignetting opcodes), ``source:NAME`` (a profile-source plugin) or
    ``estimate``.

    ``sources`` are the loaded profile-source plugins ``{name: ProfileSource}``
    consulted by ``profile="auto"`` (default: none); ``embedded`` the frame's DNG
    calibration (its opcodes, else its maker's calibration:
    :func:`vigproc.io.makernotes.calibration_for`), used by ``embedded`` and,
    after a trusted stored profile, by ``auto``.  ``warnings``, when given, gets what
    the record should say (a profile file of another lens than the frame's EXIF names).

    ``img`` is the frame as the pipeline's door accepted it
    (:func:`vigproc.core.pixels.check_image`'s result): it is not validated again."""
    from vigproc.core.estimate import estimate_checked

    h, w = img.shape[:2]
    profile = settings.profile
    if profile.startswith(SOURCE_PREFIX):
        from vigproc.core.extensions import profile_source

        src = profile_source(profile[len(SOURCE_PREFIX):])
        m = src.lookup(lens_key, w, h) if lens_key is not None else None
        if m is None:
            raise ModelError(f"profile source {src.name!r} has no profile for the lens of {where}")
        return m, profile
    if profile == "embedded":
        if embedded is None:
            raise ModelError(f"{where} carries no vignetting calibration of its own (no FixVignetteRadial or "
                             "GainMap opcode in its DNG opcode lists, no Sony or Fujifilm vignetting tag)")
        return embedded.model(w, h), "embedded"
    if settings.profile_is_file:
        from vigproc.stores.profiles import import_profile

        prof = import_profile(profile)
        other = prof.mismatch(lens_key)
        if other is not None:  # applied as asked, but not silently
            log.warning("%s: profile %s: %s", where, profile, other)
            if warnings is not None:
                warnings.append(f"profile {profile}: {other}")
        return prof.model(w, h), "profile-file"
    if profile == "lensfun" and getattr(lens_key, "lens_problem", None):
        # the EXIF names a lens the frame cannot have been shot with: its calibration
        # would be a wrong lens's, so the frame's own vignetting is estimated
        log.warning("%s: lensfun's calibration is not applied, the vignetting is estimated instead: %s",
                    where, lens_key.lens_problem)
    elif profile == "lensfun":
        from vigproc.stores.lensfun_io import lensfun_model

        return lensfun_model(lens_key, w, h), "lensfun"
    if profile == "auto" and lens_key is not None and store is not None:
        try:
            hit = store.lookup(lens_key, w, h, trusted_only=True)
        except VigprocError as exc:  # an odd key or a busy store: estimate instead
            log.warning("profile lookup for %s failed: %s", where, exc)
            hit = None
        if hit is not None:
            return hit.model(w, h), "stored-profile"
    if profile == "auto" and embedded is not None:
        try:
            return embedded.model(w, h), "embedded"
        except VigprocError as exc:  # an absurd calibration: the frame is estimated instead
            log.warning("%s: its embedded vignetting calibration is not used: %s", where, exc)
    if profile == "auto" and lens_key is not None:
        for name, src in sorted((sources or {}).items()):
            try:
                m = src.lookup(lens_key, w, h)
            except VigprocError as exc:  # one broken plugin must not stop the frame
                log.warning("profile source %s for %s: %s", name, where, exc)
                continue
            if m is not None:
                return m, f"source:{name}"
    from vigproc.io.images import EncodedImage

    if isinstance(img, EncodedImage):  # from a copy binned straight from the codes
        from vigproc.pipeline.encoded import estimate_encoded

        return estimate_encoded(img, settings.method, hint=lens_hint(lens_key, settings.method)), "estimate"
    return estimate_checked(img, settings.method, hint=lens_hint(lens_key, settings.method)), "estimate"


def lens_hint(lens_key, method: str):
    """What the frame's EXIF says of its lens for the lens-family prior (35-mm focal
    length and f-number, never the lens's identity), for the estimators that use it."""
    from vigproc.core.estimate import exif_hint  # one rule for every command and the check

    return exif_hint(lens_key, method)


# ------------------------------------------------------------------ processor
class Processor:
    """Runs frames through vigproc with fixed :class:`Settings`.

    Parameters
    ----------
    settings : Settings
    store : ProfileStore, optional
        Needed by ``profile="auto"`` and by the learn and check modes; borrowed, not
        closed.
    reader : ExifReader, optional
        Borrowed if given; otherwise one is started on first use and closed by
        :meth:`close`.
    sources : dict, optional
        Loaded profile-source plugins for ``profile="auto"``
        (:func:`vigproc.core.extensions.load_profile_sources`); discovered on first use
        if not given.
    plausibility : bool
        Refuse implausible fields (:mod:`vigproc.pipeline.guard`); off only to measure
        what the rules prevent (``vigproc bench real-frames``).
    """

    def __init__(self, settings: Settings, *, store=None, reader=None, sources=None,
                 plausibility: bool = True) -> None:
        self.settings = settings
        self.plausibility = plausibility
        self.store = store
        self._reader = reader
        self._own_reader = reader is None
        self._sources = sources
        self._steady = None  # learning as you go: the trusted profiles this processor applies

    @property
    def sources(self) -> dict:
        if self._sources is None:
            from vigproc.core.extensions import load_profile_sources

            self._sources = load_profile_sources()
        return self._sources

    @property
    def reader(self):
        if self._reader is None:
            from vigproc.io.exif import ExifReader

            self._reader = ExifReader().start()
        return self._reader

    def close(self) -> None:
        if self._own_reader and self._reader is not None:
            self._reader.close()
            self._reader = None

    def __enter__(self) -> Processor:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # -- in memory --------------------------------------------------------
    def process_image(self, img: np.ndarray, lens_key=None, *, where: str = "image", frame_id: str | None = None,
                      output: OutputFormat | None = None, embedded=None, in_camera=None, consume: bool = False,
                      captured: float | None = None):
        """Process an in-memory linear image (H×W or H×W×C, channels last).

        ``output``: the format the corrected frame will be written in (integer formats
        clip at the white point); default the settings' fixed format, or float.

        ``embedded``: the frame's own DNG calibration (:func:`choose_model`).

        ``in_camera``: the camera already corrected the frame
        (:func:`vigproc.io.incamera.read_in_camera`): nothing is applied.

        ``consume``: the caller hands ``img`` over; a display-encoded frame may be
        corrected in place (its codes become the output's: one frame in memory, not two).

        ``captured``: the frame's capture time (seconds, :func:`vigproc.pipeline.learning.capture_time`;
        None: it arrived now): where a series of its lens setting begins, while learning.

        ``frame_id``: the frame's content id. Learn mode, and correct mode with
        ``settings.learn``: a frame already pooled into its lens's profile is not pooled
        again (:meth:`ProfileStore.learn`). Check mode:
        a stored profile that pooled the frame is not its reference.

        Returns
        -------
        (ndarray or None, FrameResult)
            The corrected float32 image in ``correct`` mode (None otherwise) and the
            record of what was done.  ``FrameResult.file`` is ``where``.
        """
        import numpy as np

        from vigproc.core.pixels import check_image as valid_image
        from vigproc.io.images import EncodedImage
        from vigproc.pipeline.encoded import check_encoded, correct_encoded

        s = self.settings
        t0 = time.perf_counter()
        # every mode, also a correction by a profile (which estimates nothing): NaN/Inf,
        # a constant frame or large negative values are bad input, not something to write
        encoded = isinstance(img, EncodedImage)  # a JPEG's or PNG's codes (pipeline.encoded)
        checked = check_encoded(img) if encoded else valid_image(img, -1 if np.ndim(img) == 3 else None, min_size=1)
        lens = ({"lens_id": lens_key.lens_id(), "key": lens_key.to_dict()} if lens_key is not None
                else {"lens_id": None, "error": "no lens data given"})
        res = FrameResult(file=where, mode=s.mode, lens=lens)
        out = None
        if s.mode == "check":
            from vigproc.forensics.check import forensic_check  # noqa: PLC0415 - only check mode needs it

            verdict = forensic_check(img, lens_key, store=self.store, method=s.method, frame_id=frame_id)
            res.verdict = verdict.to_dict()
            res.source = "estimate"
            res.model = getattr(verdict, "estimate", None)
        elif s.mode == "learn":
            res.model, res.source, res.profile = self._learn(checked, lens_key, frame_id)
        else:
            warnings: list[str] = []
            steady = self._steady_profiles() if s.learn and s.profile == "auto" else None
            if steady is not None:
                steady.at(captured)
            m, res.source = choose_model(checked, lens_key, s, steady or (self.store if s.profile == "auto" else None),
                                         where=where, sources=self.sources if s.profile == "auto" else None,
                                         embedded=embedded, warnings=warnings)
            own = m if s.learn and res.source == "estimate" else None  # pooled as it is: not estimated twice
            if own is not None and steady is not None:
                from vigproc.pipeline.learning import prefer_profile

                m, chosen = prefer_profile(m, steady.latest, checked.shape[1], checked.shape[0])
                if chosen is not None:  # before trust, the profile so far is surer than the frame
                    res.source, res.extra["profile_evidence"] = "profile-evidence", {**chosen, "own": own.to_dict()}
            if warnings:
                res.extra["warnings"] = warnings
            res.model = m
            if s.profile == "lensfun" and res.source == "estimate":
                res.extra["lensfun_not_applied"] = f"lens identity: {lens_key.lens_problem}"
            if s.mode == "correct":
                from vigproc.core.correct import correct

                fmt = output or OUTPUT_FORMATS[s.output_format] or OUTPUT_FORMATS["tiff-float"]
                if self.plausibility or in_camera is not None:  # the one gate every field passes
                    from vigproc.pipeline.guard import guard

                    m, refusal = guard(m, res.source, img, lens_key, strength=s.strength, clips=fmt.integer,
                                       in_camera=in_camera, where=where, check=self.plausibility)
                    if refusal is not None:
                        res.model, res.extra["not_applied_rule"] = m, refusal.rule
                # integer outputs cannot hold values above the white point: clip those
                how = dict(channel_axis=-1 if img.ndim == 3 else None, strength=s.strength,
                           clip=1.0 if fmt.integer else None)
                # a DNG GainMap is divided out as its own field, not as its Kang-Weiss fit
                used = steady.last if steady is not None and res.source == "stored-profile" else None
                if s.learn:  # before the correction, which may overwrite the frame's codes (consume)
                    learned = self._learn_as_you_go(checked, lens_key, frame_id, in_camera,
                                                    steady.latest if used is not None else None, where, own)
                    res.extra["learned"] = learned.to_dict()
                    res.profile = learned.profile if learned.pooled else res.profile
                source_white = None
                if encoded:
                    if consume and fmt.integer:  # counted before the codes are overwritten
                        from vigproc.pipeline.encoded import white_samples

                        source_white = white_samples(img, source=True)
                    out = correct_encoded(img, m, fmt, s.strength, in_place=consume)
                else:
                    out = m.correct_image(img, **how) if hasattr(m, "correct_image") else correct(img, m, **how)
                _check_range(out, fmt)
                if fmt.integer:
                    _note_clipping(img, out, where, fmt, source_white=source_white)
                res.applied = m.candidate is None and s.strength > 0
                res.strength = s.strength
                if used is not None and res.applied:  # which revision corrected it: one per series
                    res.extra["profile_applied"] = {"profile": str(used.key), "frames": used.n_frames,
                                                    "updated": used.updated}
                    if steady.revision is not None:  # the store's applied revision, shared by all workers
                        res.extra["profile_applied"]["revision"] = steady.revision
        res.seconds = round(time.perf_counter() - t0, 4)
        return out, res

    def _learn(self, img: np.ndarray, lens_key, frame_id: str | None):
        from vigproc.core.estimate import EVIDENCE_METHODS, estimate_checked, estimate_with_evidence

        if self.store is None:
            raise VigprocError("learn mode needs a profile store")
        if lens_key is None:
            raise VigprocError("cannot learn: the frame's lens is unknown (no usable EXIF)")
        h, w = img.shape[:2]
        from vigproc.stores.profiles import ProfileKey

        # a lens learned under an earlier id keeps its profiles; a batch worker's stand-in
        # store (no database to ask) keys by the current rule
        key_for = getattr(self.store, "key_for", None)
        key = key_for(lens_key, w, h) if key_for is not None else ProfileKey.from_lens(lens_key, w, h)
        fit, evidence = self._pool_fit(img, checked=True)
        p = self.store.learn(key, fit, frame_id=frame_id, evidence=evidence, lens_key=lens_key)
        return fit, "estimate", str(p.key)

    def _pool_fit(self, img, *, checked: bool):
        """What learn mode pools of a linear frame: its estimate (the candidate of one too
        weak to apply alone: it still carries evidence for the lens) and, for the methods
        that give it, the frame's evidence (None otherwise)."""
        from vigproc.core.estimate import EVIDENCE_METHODS, estimate, estimate_checked, estimate_with_evidence

        evidence = None
        if self.settings.method in EVIDENCE_METHODS:
            # with the frame's data, so the store can pool the lens's profile from all its frames
            m, evidence = estimate_with_evidence(img, -1 if img.ndim == 3 else None, method=self.settings.method,
                                                 checked=checked)
        else:
            m = estimate_checked(img, self.settings.method) if checked else estimate(
                img, self.settings.method, channel_axis=-1 if img.ndim == 3 else None)
        fit = m.candidate if m.candidate is not None else m
        if fit.covariance is None:
            raise ModelError("no usable fit to learn from (no uncertainty)")
        return fit, evidence

    def _steady_profiles(self):
        """The store as correct mode reads it while learning: one revision of a trusted
        profile per series (:class:`vigproc.pipeline.learning.SteadyProfiles`)."""
        from vigproc.pipeline.learning import SteadyProfiles

        if self.store is None:
            raise VigprocError("learning as you go needs a profile store")
        if self._steady is None or self._steady.store is not self.store:
            self._steady = SteadyProfiles(self.store)
        return self._steady

    def _learn_as_you_go(self, img, lens_key, frame_id: str | None, in_camera, used, where: str, own=None):
        """Pool a frame correct mode handles into its lens's profile, exactly once
        (:mod:`vigproc.pipeline.learning`); ``used``: the trusted profile that corrected it,
        as stored now (None: none); ``own``: the frame's own estimate when the correction
        made one (pooled as it is, :func:`~vigproc.pipeline.learning.pooled_of`).
        Returns a :class:`~vigproc.pipeline.learning.Learned`.

        A frame the store cannot pool (too few usable bins, an invalid fit) is recorded as
        not pooled; a locked store, or a full disk under it, raises (the frame is tried
        again, and a frame pooled before is not pooled twice: ``frame_id``)."""
        from vigproc.io.images import EncodedImage
        from vigproc.pipeline.learning import SETTLED_FRAMES, Learned, pooled_of, pooling_refusal
        from vigproc.stores.profiles import ProfileStoreError

        if self.store is None:
            raise VigprocError("learning as you go needs a profile store")
        why = pooling_refusal(lens_key, in_camera)
        if why is not None:
            log.info("%s: not learned: %s", where, why)
            return Learned(False, reason=why)
        h, w = img.shape[:2]
        try:
            key = self.store.key_for(lens_key, w, h)
            if used is not None and used.key == key and used.n_frames >= SETTLED_FRAMES:
                return Learned.of(used, pooled=False, reason=f"the profile is settled ({used.n_frames} frames)")
            if frame_id is not None and self.store.holds_frame(key, frame_id):  # a rerun, a copy, a retry
                done = Learned.of(self.store.get(key), pooled=False, reason="this content is already pooled")
                log.info("%s: %s", where, done.describe())
                return done
            try:
                if own is not None:
                    fit, evidence = pooled_of(own, img, self.settings.method)
                else:  # corrected by a profile: the frame's one estimate is made here
                    linear = img.linear() if isinstance(img, EncodedImage) else img
                    fit, evidence = self._pool_fit(linear, checked=not isinstance(img, EncodedImage))
            except (ModelError, VigprocError) as exc:  # nothing to pool; the correction stands
                log.info("%s: not learned: %s", where, exc)
                return Learned(False, reason=f"no fit to pool: {exc}")
            p = self.store.learn(key, fit, frame_id=frame_id, evidence=evidence, lens_key=lens_key)
        except ProfileStoreError as exc:
            if getattr(exc, "transient", False) or getattr(exc, "sqlite_errorcode", None) is not None:
                raise  # a locked store or its full disk: the frame is tried again
            log.warning("%s: not learned: %s", where, exc)
            return Learned(False, reason=str(exc))
        done = Learned.of(p, pooled=True)
        log.info("%s: %s", where, done.describe())
        return done

    # -- files ------------------------------------------------------------
    def process_file(self, path: str | os.PathLike[str], outdir: str | os.PathLike[str], stem: str | None = None,
                     *, extra: dict[str, Any] | None = None, frame_id: str | None = None,
                     protect: Container[Any] = (), unapplied: str | None = None,
                     like: str | os.PathLike[str] | None = None) -> FrameResult:
        """Read ``path``, process it, write its outputs into ``outdir``.

        Outputs, named from ``stem`` (default :func:`output_name` of the input: ``IMG_1.jpg``;
        all atomic; the input is never modified): in correct mode the corrected image
        (:func:`corrected_name`: ``IMG_1.corrected.jpg``, or ``IMG_1.nef.corrected.tif``
        when the format changes; :func:`output_format_for`), or when nothing is applied
        what ``unapplied`` (default the settings') says: the original under the output's
        name (``keep``), nothing, or the original as ``IMG_1.uncorrected.jpg``
        (:data:`UNAPPLIED_POLICIES`); ``STEM.vignetting.png``
        with ``picture``; and always the sidecar ``STEM.vigproc.json``, written last
        (``not_applied`` says why when nothing was). ``like``: an ``auto`` output
        format is resolved by this name's suffix.  No output may be ``path`` itself or
        in ``protect`` (the other inputs of the run, :class:`InputFiles`): then nothing
        is written.

        In learn mode the frame is pooled under ``frame_id``, by default the file's
        SHA-256, so learning the same file twice (a rerun, a copy under another
        name) refines the profile once.

        Raises
        ------
        VigprocError
            Unreadable or bad input, failed estimate, output not writable.
        ImageWriteError
            Also when an output would replace ``path`` or a protected file.
        """
        from vigproc.atomic import atomic_write_text

        s = self.settings
        t0 = time.perf_counter()
        path = Path(path)
        outdir = Path(outdir)
        stem = output_name(path.name) if stem is None else stem
        policy = unapplied or s.unapplied
        if policy not in UNAPPLIED_POLICIES:
            raise VigprocError(f"unknown policy for frames not corrected {policy!r}")
        fmt = output_format_for(s.output_format, path, like=like)  # the suffix is final before reading
        dst = safe_output(outdir, corrected_name(stem, path, fmt.suffix), "")
        kept = (safe_output(outdir, _image_base(stem, path), ".uncorrected" + path.suffix)
                if s.mode == "correct" and policy in ("copy", "link") else None)
        sidecar = safe_output(outdir, stem, SIDECAR_SUFFIX)
        # keep: the input's bytes when the output is its own kind (no second lossy pass)
        as_is = policy == "keep" and fmt.suffix.lower() == path.suffix.lower() and (
            s.output_format == "auto" or fmt.format in ("jpeg", "dng"))
        # checked before anything is written: a refused frame leaves no partial outputs
        try:
            own = path.resolve()
        except RuntimeError as exc:  # a symlink loop (Python < 3.13 raises RuntimeError)
            raise ImageReadError(f"cannot read {os.fspath(path)!r}: {exc}") from None
        for target in (dst if s.mode == "correct" else None, kept, sidecar,
                       safe_output(outdir, stem, ".vignetting.png") if s.picture else None):
            refuse_input(target, (own,), protect)
        out, res, img, info, fmt = self._process_path(path, frame_id, lambda info: output_format_for(
            s.output_format, path, info, like=like))
        del img  # not needed once processed: freed before the output is encoded (peak memory)
        if out is not None and (res.applied or policy == "write" or (policy == "keep" and not as_is)):
            from vigproc.io.metadata import make_record, write_corrected

            if fmt.format == "dng":  # the raw pixels untouched, the correction as an opcode
                from vigproc.io.dng_vignette import write_dng_correction

                res.extra["dng_opcode"] = write_dng_correction(path, dst, res.model, strength=s.strength)
            else:  # the source's EXIF/XMP plus an XMP record of the correction
                # display-encoded in, display-encoded out: the source's colour space stays true
                keep_colour = fmt.transfer == "srgb" and getattr(info, "transfer", None) == "srgb"
                write_corrected(dst, out, path, make_record(res.model, strength=s.strength), bit_depth=fmt.depth,
                                format=fmt.format, transfer=fmt.transfer, quality=fmt.quality,
                                keep_colour=keep_colour, source_read=True)  # decoded above, its EXIF read
            res.output = str(dst)
        if out is not None and not res.applied:  # said whatever was written
            res.extra["not_applied"] = "strength 0" if s.strength == 0 else not_applied_reason(res.model)
            res.extra.setdefault("not_applied_rule", "strength-0" if s.strength == 0 else "estimator")
            if as_is:
                keep_original(path, dst)
                res.output = str(dst)
            if kept is not None and policy in ("copy", "link"):
                keep_original(path, kept, link=policy == "link")
                res.output = str(kept)
        if s.picture and res.model is not None:
            self._picture(path, outdir, stem, res)
        if extra:
            res.extra.update(extra)
        res.seconds = round(time.perf_counter() - t0, 4)
        atomic_write_text(sidecar, json.dumps(res.to_dict(), indent=1) + "\n")
        return res

    def process_unwritten(self, path: str | os.PathLike[str], *, frame_id: str | None = None) -> FrameResult:
        """Check or estimate a file without writing anything (a host asking for the
        answer only): read, lens, DNG calibration and content id exactly as
        :meth:`process_file` (so a check never takes a profile that pooled this very
        file as its reference).

        Raises
        ------
        VigprocError
            In correct mode (a correction must be written somewhere).
        """
        if self.settings.mode == "correct":
            raise VigprocError("correct mode writes its result: use process_file")
        return self._process_path(Path(path), frame_id, lambda info: None)[1]

    def _process_path(self, path: Path, frame_id: str | None, output_for, *, consume: bool = True):
        """Read ``path`` and process it: (corrected image or None, FrameResult, image, its
        ImageInfo, output format). ``output_for(info)``: the output format (None: none
        written). ``consume``: the frame read may be corrected in place (peak memory), and
        the image returned is then the output's codes; False keeps the frame as read."""
        from vigproc.io.images import read_encoded, read_image

        s = self.settings
        # correct and estimate take a JPEG's or PNG's code values as they are (pipeline.encoded)
        img, info = (read_encoded if s.mode in ("correct", "estimate") else read_image)(path, transfer=s.transfer)
        # one exiftool read of the file answers the lens, the maker's calibration, the
        # in-camera flags and the provenance (io.exif.FileTags); a host's stand-in reader
        # may not offer it
        read_file = getattr(self.reader, "read_file", None)
        tags = read_file(path) if read_file is not None else self.reader
        lens_key, lens = read_lens(tags, path)
        embedded = None
        if s.mode in ("correct", "estimate"):
            from vigproc.io.makernotes import calibration_for

            embedded = calibration_for(path, s.profile, tags)
        in_camera = None
        if s.mode == "correct" and s.in_camera == "respect":
            from vigproc.io.incamera import read_in_camera

            in_camera = read_in_camera(path, tags)
        if (s.mode in ("learn", "check") or s.learn) and frame_id is None and self.store is not None:
            frame_id = file_sha256(path)  # learn: pooled once; check: never its own reference
        fmt = output_for(info)
        shape = img.shape
        # the frame read here is ours: corrected in place (peak memory)
        captured = None
        if s.learn:  # where a series of the lens setting begins (pipeline.learning)
            from vigproc.pipeline.learning import capture_time

            captured = capture_time(path, tags)
        out, res = self.process_image(img, lens_key, where=str(path), frame_id=frame_id, output=fmt,
                                      embedded=embedded, in_camera=in_camera, consume=consume, captured=captured)
        res.lens = lens
        if s.mode == "check":  # what an examiner files beside the verdict (vigproc.io.provenance)
            from vigproc.io.provenance import read_provenance

            res.extra["provenance"] = read_provenance(path, tags if read_file is not None else getattr(
                self.reader, "exif", self.reader), getattr(
                lens_key, "problems", ()), sha256=frame_id).to_dict()
        if embedded is not None:
            res.extra["embedded"] = embedded.to_dict(*shape[1::-1]) if res.source == "embedded" else \
                embedded.to_dict()
        return out, res, img, info, fmt

    @staticmethod
    def _picture(path: Path, outdir: Path, stem: str, res: FrameResult) -> None:
        from vigproc.io.images import write_image
        from vigproc.io.picture import falloff_figure

        m = res.model
        shown = m if m.candidate is None else m.candidate
        rule = res.extra.get("not_applied_rule")  # a harm rule, else the estimator's own fall-back
        why = rule if rule not in (None, "estimator") else "weak evidence"
        title = f"{path.name}: " + (f"not applied ({why}), " if m.candidate is not None else "") + \
            f"{shown.field_ev_rms():.2f} EV RMS"
        pic = safe_output(outdir, stem, ".vignetting.png")
        write_image(pic, falloff_figure(shown, title=title, rejected=m.candidate is not None), bit_depth="uint8",
                    transfer="srgb")
        res.picture = str(pic)
