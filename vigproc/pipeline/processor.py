"""One frame through vigproc, the way every front end runs it.

file → linear image + lens key → model (stored profile, profile file, lensfun or a
fresh estimate) → correction, profile update or verdict → output file + JSON sidecar.

The command line (``correct``, ``demo``, ``estimate``, ``profile learn``), the
watch-folder daemon, batch jobs and the pipeline hook all call :class:`Processor`, so a
frame is handled identically whoever asks: :meth:`Processor.read_frame` reads a file
once (pixels, lens key, content id), :meth:`Processor.process_frame` takes it on.  A :class:`Processor` owns (or borrows) one exiftool process and one profile
store; it is not shared between threads (make one per worker).
"""

from __future__ import annotations

import json
import logging
import os
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Container

from vigproc.atomic import atomic_write_text
from vigproc.core.preload import numba_ready, preload_numba
from vigproc.errors import ImageReadError, MetadataError, ModelError, VigprocError
from vigproc.io.incamera import read_in_camera
from vigproc.io.provenance import read_provenance
from vigproc.pipeline import learning
from vigproc.pipeline.learning import (Learned, SteadyProfiles, capture_time, pooled_of, pooling_refusal,
                                       prefer_profile)
from vigproc.io.formats import IMAGE_SUFFIXES, WRITE_EXT_FORMAT  # noqa: F401  (IMAGE_SUFFIXES: re-exported)
# the pieces a frame's path uses, in their own modules; re-exported here, where callers import them
from vigproc.pipeline.choice import WEAK_EVIDENCE, choose_model, lens_hint, not_applied_reason  # noqa: F401
from vigproc.pipeline.outputs import (MAX_STEM_BYTES, MIN_AUTO_JPEG_QUALITY, OUTPUT_FORMATS,  # noqa: F401
                                      SIDECAR_SUFFIX, InputFiles, OutputFormat, _check_range, _format_label,
                                      _image_base, _note_clipping, corrected_name, keep_original, output_file,
                                      output_folder, output_format_for, output_location, output_name,
                                      output_stems, percent_encode, refuse_input, safe_output, shorten_stem,
                                      sweep_temporaries, temp_key)
from vigproc.pipeline.settings import (IN_CAMERA_POLICIES, MODES, PROFILE_CHOICES, SOURCE_PREFIX,  # noqa: F401
                                       UNAPPLIED_POLICIES, Settings, names_profile_file)

log = logging.getLogger(__name__)


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


@dataclass
class Frame:
    """One input file as the per-frame path read it (:meth:`Processor.read_frame`): the
    pixels and what the file's one metadata read says of them.

    Attributes
    ----------
    path : Path
    img : ndarray or EncodedImage
        Linear float32 (H×W or H×W×C, channels last), or a JPEG's or PNG's code values
        in correct and estimate modes (:class:`vigproc.io.images.EncodedImage`).
    info : ImageInfo
        Format, size, bit depth and transfer as read.
    tags : FileTags or reader
        The file's one exiftool read (a host's stand-in reader itself).
    lens_key : LensKey or None
        The lens identity, None when the EXIF does not give one.
    lens : dict
        The record's ``lens``: the lens id and key, or why it is unknown.
    frame_id : str or None
        The content id (SHA-256 hex) where learning or a check needs it.
    embedded : object or None
        The file's own calibration (:func:`vigproc.io.makernotes.calibration_for`).
    in_camera : InCamera or None
        The camera already corrected the frame (:func:`vigproc.io.incamera.read_in_camera`).
    captured : float or None
        Capture time, seconds on the camera's clock (learning as it goes only).
    """

    path: Path
    img: Any
    info: Any
    tags: Any
    lens_key: Any
    lens: dict[str, Any]
    frame_id: str | None = None
    embedded: Any = None
    in_camera: Any = None
    captured: float | None = None


def _identity(path: str) -> tuple[int, int, int, int]:
    """What says a file is still the one read ahead: device, inode, size, modification time."""
    st = os.stat(path)
    return st.st_dev, st.st_ino, st.st_size, st.st_mtime_ns


def _read_counted(path: str, transfer: str, method: str | None):
    """:func:`vigproc.io.images.read_encoded` of ``path`` for a thread that reads ahead:
    a JPEG's or PNG's codes come with the passes the frame's path makes over them already
    made and kept (:func:`vigproc.pipeline.encoded.prepare_encoded`: their range, the
    white samples and, with ``method``, the reduced copy the estimate reads), once Numba
    is ready (:func:`vigproc.core.preload.numba_ready`: a read ahead does not wait for its
    set-up). What cannot be counted here is counted, and reported, where the frame is
    processed.

    Returns
    -------
    (EncodedImage or ndarray, ImageInfo)
    """
    from vigproc.io.images import EncodedImage, read_encoded

    img, info = read_encoded(path, transfer=transfer)
    if isinstance(img, EncodedImage):
        from vigproc.pipeline.encoded import prepare_encoded

        try:
            prepare_encoded(img, method if numba_ready() else None)
        except VigprocError as exc:  # met again where the frame is processed
            log.debug("%s: not counted ahead: %s", path, exc)
    return img, info


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
    if reader is None:
        return None, {"lens_id": None, "error": "EXIF not read"}
    try:
        key = reader.read(path)
    except ImageReadError as exc:
        return None, {"lens_id": None, "error": str(exc)}
    return key, {"lens_id": key.lens_id(), "key": key.to_dict()}


from vigproc.io.provenance import file_sha256  # noqa: E402  (re-exported: a frame's content id)



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
    seed : int, optional
        The random start of estimators that draw one (``lyu2010-rand``).
    judge_estimates : bool
        Estimate mode: each estimate is judged by the rules correct mode applies
        (:func:`vigproc.pipeline.guard.guard`, the in-camera flags included), so the
        record says whether a correction would apply it (``vigproc estimate``).
    """

    def __init__(self, settings: Settings, *, store=None, reader=None, sources=None,
                 plausibility: bool = True, seed: int | None = None, judge_estimates: bool = False) -> None:
        self.settings = settings
        self.plausibility = plausibility
        self.seed = seed
        self.judge_estimates = judge_estimates
        #: The capture time (seconds, or None) of the last frame learning as it goes
        #: judged the series of: a cluster's batch client applies the series rule with it.
        self.captured: float | None = None
        self.store = store
        self._reader = reader
        self._own_reader = reader is None
        self._sources = sources
        self._steady = None  # learning as you go: the trusted profiles this processor applies
        self._reading = None  # the thread that decodes files ahead (read_ahead)
        self._ahead: list[tuple[str, tuple[int, int, int, int], Any]] = []  # (path, identity, future)

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

    def prepare(self, *, metadata_writer: bool = True) -> None:
        """Start now the one-off set-up the first file would otherwise wait for.

        The EXIF reader's exiftool and, when images are written, the metadata writer's
        are launched without waiting for them (Perl's start-up runs beside this
        process's work), then Numba's set-up starts in a background thread
        (:func:`vigproc.core.preload.preload_numba`). Optional, and nothing is decided
        here: a start that fails is met again, and reported, where the first file
        needs it.

        Parameters
        ----------
        metadata_writer : bool
            Launch the metadata writer's exiftool too. False for a caller that writes in
            a thread of its own (``vigproc correct``): the writer's exiftool then starts
            with the first corrected frame's write, in that thread, instead of taking a
            core from Numba's set-up, which the first estimate waits for (and not at all
            when no frame is corrected).
        """
        try:  # launched before the preloading thread runs: exiftool's launch forks
            if self._reader is None:
                from vigproc.io.exif import ExifReader

                self._reader = ExifReader().spawn()
            if self.settings.mode == "correct" and metadata_writer:
                from vigproc.io.metadata import spawn_exiftool

                spawn_exiftool()
        except VigprocError as exc:
            log.debug("early exiftool launch failed (retried on first use): %s", exc)
        preload_numba()

    def prefetch(self, path: str | os.PathLike[str]) -> None:
        """Have the EXIF reader's exiftool read ``path``'s metadata now, while this
        process works on the file before it (:meth:`vigproc.io.exif.ExifReader.prefetch`:
        used only if the file is unchanged when its turn comes). Nothing else is read
        ahead: the decisions and their order are the same."""
        self.reader.prefetch(path)

    #: Files :meth:`read_ahead` holds decoded or decoding at most (each one frame's codes).
    AHEAD = 2

    def read_ahead(self, path: str | os.PathLike[str]) -> None:
        """Decode ``path``'s pixels now, in a thread of this processor, while the caller
        works on the file before it (OpenImageIO's decode releases the GIL).

        Only a later :meth:`read_frame` of the same path takes them, and only if the file
        is still the one asked about (same device, inode, size and modification time);
        a decode that failed is done again there, so what a file gets, and the error
        it raises, are as without this. Bounded: at most :data:`AHEAD` files are held
        (the oldest unclaimed one is dropped). Correct, estimate and learn modes only
        (the modes that read a file's codes).
        """
        if self.settings.mode not in ("correct", "estimate", "learn"):
            return
        key = os.fspath(path)
        try:
            ident = _identity(key)
        except OSError:
            return  # read_frame reports it
        if self._reading is None:
            from concurrent.futures import ThreadPoolExecutor

            self._reading = ThreadPoolExecutor(1, thread_name_prefix="vigproc-read")
        while len(self._ahead) >= self.AHEAD:
            self._ahead.pop(0)[2].cancel()
        s = self.settings
        # the reduced copy an estimate reads, when one is expected (a stored profile may still answer)
        method = s.method if s.mode == "learn" or s.profile in ("auto", "estimate") else None
        self._ahead.append((key, ident, self._reading.submit(_read_counted, key, s.transfer, method)))

    def drop_read_ahead(self, path: str | os.PathLike[str]) -> None:
        """Forget what :meth:`read_ahead` holds or decodes for ``path``: its turn came and
        went without reading it (an earlier run's sidecar answered, or it failed before its
        read), and its frame would be held beside the next ones (a decode under way runs to
        its end, its pixels dropped)."""
        key = os.fspath(path)
        for i in reversed(range(len(self._ahead))):
            if self._ahead[i][0] == key:
                self._ahead.pop(i)[2].cancel()

    def _read_ahead_of(self, path: Path):
        """The pixels :meth:`read_ahead` decoded for ``path`` if the file is unchanged, else None."""
        key = os.fspath(path)
        for i, (p, ident, fut) in enumerate(self._ahead):
            if p != key:
                continue
            del self._ahead[i]
            try:
                got = fut.result()
                same = _identity(key) == ident
            except Exception:  # read again where it is needed: the same error, raised in order
                return None
            return got if same else None
        return None

    def close(self) -> None:
        self._ahead.clear()
        if self._reading is not None:
            self._reading.shutdown(wait=True, cancel_futures=True)
            self._reading = None
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
                      captured: float | None = None, raw_path: str | os.PathLike[str] | None = None):
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

        ``raw_path``: the RAW the frame was developed from: a ``flat-field`` estimate
        measures its CFA planes before demosaicing (:mod:`vigproc.pipeline.cfa_flat`).

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
        estimated = None  # a RAW flat frame's estimate, measured per CFA plane
        if raw_path is not None and s.method == "flat-field" and s.mode in ("correct", "estimate", "learn"):
            from vigproc.pipeline.cfa_flat import cfa_flat_field

            estimated = cfa_flat_field(raw_path, checked.shape[1], checked.shape[0], with_grid=s.mode == "learn")
        if s.mode == "check":
            from vigproc.forensics.check import forensic_check  # noqa: PLC0415 - only check mode needs it

            verdict = forensic_check(img, lens_key, store=self.store, method=s.method, frame_id=frame_id)
            res.verdict = verdict.to_dict()
            res.source = "estimate"
            res.model = getattr(verdict, "estimate", None)
        elif s.mode == "learn":
            if in_camera is not None:  # the hot folder's rule: its fall-off is gone, it would flatten the profile
                raise MetadataError(f"cannot learn: {in_camera.reason}")
            res.model, res.source, res.profile = self._learn(checked, lens_key, frame_id, estimated)
        else:
            warnings: list[str] = []
            steady = self._steady_profiles() if s.learn and s.profile == "auto" else None
            if steady is not None:
                steady.at(captured)
                self.captured = captured
            m, res.source = choose_model(checked, lens_key, s, steady or (self.store if s.profile == "auto" else None),
                                         where=where, sources=self.sources if s.profile == "auto" else None,
                                         embedded=embedded, warnings=warnings, seed=self.seed,
                                         estimated=estimated)
            own = m if s.learn and res.source == "estimate" else None  # pooled as it is: not estimated twice
            if own is not None and steady is not None:
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
                if res.applied and getattr(m, "grid", None) is not None:  # the record's θ is not what divided
                    res.extra["grid_field"] = {"nodes": list(m.grid.nodes), "source": m.grid.source}
                if used is not None and res.applied:  # which revision corrected it: one per series
                    res.extra["profile_applied"] = {"profile": str(used.key), "frames": used.n_frames,
                                                    "updated": used.updated}
                    if steady.revision is not None:  # the store's applied revision, shared by all workers
                        res.extra["profile_applied"]["revision"] = steady.revision
                    cast = self._profile_cast(used.key)
                    if cast is not None:  # reported, never applied; grows with the frames, unlike the revision
                        res.extra["lens_colour_cast"] = cast
        res.seconds = round(time.perf_counter() - t0, 4)
        return out, res

    def _learn(self, img: np.ndarray, lens_key, frame_id: str | None, estimated=None):
        from vigproc.core.estimate import EVIDENCE_METHODS, estimate_checked, estimate_with_evidence

        if self.store is None:
            raise VigprocError("learn mode needs a profile store")
        if lens_key is None:
            raise VigprocError("cannot learn: the frame's lens is unknown (no usable EXIF)")
        if lens_key.lens is None and lens_key.make and lens_key.model:
            # the hot folder's rule: an unnamed lens pools under "?" with the body's other lenses

            if why := pooling_refusal(lens_key):
                raise MetadataError(f"cannot learn: {why}")
        h, w = img.shape[:2]
        from vigproc.stores.profiles import ProfileKey

        # a lens learned under an earlier id keeps its profiles; a batch worker's stand-in
        # store (no database to ask) keys by the current rule
        key_for = getattr(self.store, "key_for", None)
        key = key_for(lens_key, w, h) if key_for is not None else ProfileKey.from_lens(lens_key, w, h)
        fit, evidence = self._pool_fit(img, checked=True, estimated=estimated)
        grid = None
        if self.settings.method == "flat-field":  # a flat frame measures its field: the profile keeps it
            from vigproc.pipeline.flat_grid import frame_grid

            if estimated is not None:  # a RAW's: measured on its CFA planes
                grid = getattr(estimated, "grid", None)
            else:
                grid = frame_grid(img.linear() if hasattr(img, "linear") else img, fit)
        p = self.store.learn(key, fit, frame_id=frame_id, evidence=evidence, lens_key=lens_key, grid=grid,
                             **self._cast_of(img, fit))
        return fit, "estimate", str(p.key)

    def _profile_cast(self, key) -> dict | None:
        """The colour cast pooled from the frames of the profile under ``key``
        (:meth:`ProfileStore.cast_report`) as a record reports it; None without one
        (or from a store that pools no casts: a batch worker's stand-in)."""
        cast_report = getattr(self.store, "cast_report", None)
        if cast_report is None:
            return None
        rep = cast_report(key)
        return None if rep is None else rep.to_dict()

    def _cast_of(self, img, fit) -> dict:
        """``learn``'s ``cast`` argument: the frame's colour-cast record for its profile's
        cast (:mod:`vigproc.stores.cast_store`), when the store records them (a profile
        store, or a batch worker's stand-in that hands it to the client) and the frame has one."""
        from vigproc.pipeline.cast import frame_cast_record

        if not getattr(self.store, "records_casts", False):
            return {}
        rec = frame_cast_record(img, fit)
        return {} if rec is None else {"cast": rec}

    def _pool_fit(self, img, *, checked: bool, estimated=None):
        """What learn mode pools of a frame: its estimate (the candidate of one too weak
        to apply alone: it still carries evidence for the lens) and, for the methods that
        give it, the frame's evidence (None otherwise). A JPEG's or PNG's codes
        (:class:`~vigproc.io.images.EncodedImage`) give both from their reduced copy
        (:func:`vigproc.pipeline.encoded.estimate_with_evidence_encoded`); other methods
        read them decoded. ``estimated``: the estimate made elsewhere (a RAW flat frame's
        CFA planes)."""
        from vigproc.core.estimate import EVIDENCE_METHODS, estimate, estimate_checked, estimate_with_evidence
        from vigproc.io.images import EncodedImage

        method, evidence = self.settings.method, None
        if estimated is not None:  # made elsewhere (a RAW flat frame's CFA planes)
            m = estimated
        elif isinstance(img, EncodedImage) and method in EVIDENCE_METHODS:
            from vigproc.pipeline.encoded import estimate_with_evidence_encoded

            m, evidence = estimate_with_evidence_encoded(img, method)
        else:
            if isinstance(img, EncodedImage):
                img, checked = img.linear(), False
            if method in EVIDENCE_METHODS:
                # with the frame's data, so the store can pool the lens's profile from all its frames
                m, evidence = estimate_with_evidence(img, -1 if img.ndim == 3 else None, method=method,
                                                     checked=checked)
            else:
                m = estimate_checked(img, method) if checked else estimate(
                    img, method, channel_axis=-1 if img.ndim == 3 else None)
        fit = m.candidate if m.candidate is not None else m
        if fit.covariance is None:
            raise ModelError("no usable fit to learn from (no uncertainty)")
        return fit, evidence

    def _steady_profiles(self):
        """The store as correct mode reads it while learning: one revision of a trusted
        profile per series (:class:`vigproc.pipeline.learning.SteadyProfiles`)."""
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
            if used is not None and used.key == key and used.n_frames >= learning.SETTLED_FRAMES:  # read when used
                return Learned.of(used, pooled=False, reason=f"the profile is settled ({used.n_frames} frames)")
            if frame_id is not None and self.store.holds_frame(key, frame_id):  # a rerun, a copy, a retry
                done = Learned.of(self.store.get(key), pooled=False, reason="this content is already pooled")
                log.info("%s: %s", where, done.describe())
                return done
            try:
                if own is not None:
                    fit, evidence = pooled_of(own, img, self.settings.method)
                else:  # corrected by a profile: the frame's one estimate is made here
                    fit, evidence = self._pool_fit(img, checked=True)
            except (ModelError, VigprocError) as exc:  # nothing to pool; the correction stands
                log.info("%s: not learned: %s", where, exc)
                return Learned(False, reason=f"no fit to pool: {exc}")
            p = self.store.learn(key, fit, frame_id=frame_id, evidence=evidence, lens_key=lens_key,
                                 **self._cast_of(img, fit))
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
        return self.begin_file(path, outdir, stem, extra=extra, frame_id=frame_id, protect=protect,
                               unapplied=unapplied, like=like)()

    def begin_file(self, path: str | os.PathLike[str], outdir: str | os.PathLike[str], stem: str | None = None,
                   *, extra: dict[str, Any] | None = None, frame_id: str | None = None,
                   protect: Container[Any] = (), unapplied: str | None = None,
                   like: str | os.PathLike[str] | None = None) -> Callable[[], FrameResult]:
        """:meth:`process_file` in two steps: read and process ``path`` now (every
        decision, and learning as you go, is made here), and return the step that writes
        its outputs (encode, metadata, sidecar) and returns the record.

        The writing step touches nothing this processor reads, so a caller may run it in
        another thread while the next file is read (``vigproc correct``); it must be
        called once, and before the next writing step of the same folder, to keep the
        outputs' order. Raises as :meth:`process_file` does, each step for its own part.

        Returns
        -------
        callable
            ``finish() -> FrameResult``; its attribute ``encodes`` says whether it
            encodes an image (it then holds the frame's codes until it runs; a step that
            only copies the input and writes the sidecar holds no pixels).
        """
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
        made = out is not None  # correct mode: an output frame was made (written or not)
        encodes = made and (res.applied or policy == "write" or (policy == "keep" and not as_is))
        if not encodes:
            out = None  # the frame is not written: a write waiting in a queue does not hold it

        def finish() -> FrameResult:
            if encodes:
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
            if made and not res.applied:  # said whatever was written
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

        finish.encodes = encodes  # type: ignore[attr-defined]  # holds a frame until it runs
        return finish

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

    def read_frame(self, path: str | os.PathLike[str], frame_id: str | None = None, *,
                   raw_half_size: bool = False) -> Frame:
        """Read one file the way every front end's frames are read: "file → linear image +
        lens key", once.

        The pixels (a JPEG's or PNG's code values as they are in correct and estimate
        modes, :mod:`vigproc.pipeline.encoded`), then one exiftool read of the file
        (:class:`vigproc.io.exif.FileTags`) answers the lens, the maker's calibration,
        the in-camera flags and the capture time; the content id is the file's SHA-256
        where learning or a check needs it.

        Parameters
        ----------
        path : path
        frame_id : str, optional
            The content id when the caller has it already (a batch worker's fingerprint).
        raw_half_size : bool
            A RAW is developed at half size (``vigproc estimate``'s fast path; the model
            is then for the half-size frame).

        Returns
        -------
        Frame

        Raises
        ------
        VigprocError
            The file cannot be read or is not a supported image.
        """
        from vigproc.io.images import read_encoded, read_image

        s = self.settings
        path = Path(path)
        # correct, estimate and learn take a JPEG's or PNG's code values as they are (pipeline.encoded)
        got = self._read_ahead_of(path) if self._ahead and not raw_half_size else None
        img, info = got if got is not None else (read_encoded if s.mode in ("correct", "estimate", "learn") else
                                                  read_image)(path, transfer=s.transfer, raw_half_size=raw_half_size)
        # a host's stand-in reader may not offer the one read of the whole file
        read_file = getattr(self.reader, "read_file", None)
        tags = read_file(path) if read_file is not None else self.reader
        lens_key, lens = read_lens(tags, path)
        embedded = None
        if s.mode in ("correct", "estimate"):
            from vigproc.io.makernotes import calibration_for

            embedded = calibration_for(path, s.profile, tags)
        in_camera = None
        if s.in_camera == "respect" and (s.mode in ("correct", "learn") or (s.mode == "estimate" and self.judge_estimates)):
            in_camera = read_in_camera(path, tags)
        if (s.mode in ("learn", "check") or s.learn) and frame_id is None and self.store is not None:
            frame_id = file_sha256(path)  # learn: pooled once; check: never its own reference
        captured = None
        if s.learn:  # where a series of the lens setting begins (pipeline.learning)

            captured = capture_time(path, tags)
        return Frame(path, img, info, tags, lens_key, lens, frame_id, embedded, in_camera, captured)

    def process_frame(self, frame: Frame, *, output: OutputFormat | None = None,
                      consume: bool = True) -> tuple[Any, FrameResult]:
        """Process a frame :meth:`read_frame` read: "model → correction, profile update,
        estimate or verdict" (:meth:`process_image`), its record completed with what the
        file says (the lens, a check's provenance, a DNG's own calibration).

        ``output``: the format the corrected frame will be written in (correct mode).
        ``consume``: the frame may be corrected in place (peak memory); ``frame.img`` is
        then the output's codes.

        Returns
        -------
        (ndarray or EncodedImage or None, FrameResult)
            The corrected frame in correct mode (None otherwise) and the record.
        """
        s = self.settings
        shape = frame.img.shape  # before a correction in place
        where = str(frame.path)
        out, res = self.process_image(frame.img, frame.lens_key, where=where, frame_id=frame.frame_id,
                                      output=output, embedded=frame.embedded, in_camera=frame.in_camera,
                                      consume=consume, captured=frame.captured,
                                      raw_path=frame.path if frame.info.format == "raw" else None)
        res.lens = frame.lens
        if s.mode == "estimate" and self.judge_estimates:  # what correct would do with this field
            from vigproc.pipeline.guard import guard

            res.model, refusal = guard(res.model, res.source, frame.img, frame.lens_key,
                                       clips=frame.info.bit_depth not in ("half", "float", "double"),
                                       in_camera=frame.in_camera, where=where, check=self.plausibility)
            if refusal is not None:
                res.extra["not_applied_rule"] = refusal.rule
        if s.mode == "check":  # what an examiner files beside the verdict (vigproc.io.provenance)

            whole = frame.tags is not self.reader  # else a host's stand-in reader
            res.extra["provenance"] = read_provenance(frame.path, frame.tags if whole else getattr(
                self.reader, "exif", self.reader), getattr(frame.lens_key, "problems", ()),
                sha256=frame.frame_id).to_dict()
        if frame.embedded is not None:
            res.extra["embedded"] = frame.embedded.to_dict(*shape[1::-1]) if res.source == "embedded" else \
                frame.embedded.to_dict()
        return out, res

    def _process_path(self, path: Path, frame_id: str | None, output_for, *, consume: bool = True):
        """Read ``path`` and process it: (corrected image or None, FrameResult, image, its
        ImageInfo, output format). ``output_for(info)``: the output format (None: none
        written). ``consume``: the frame read may be corrected in place (peak memory), and
        the image returned is then the output's codes; False keeps the frame as read."""
        frame = self.read_frame(path, frame_id)
        fmt = output_for(frame.info)
        out, res = self.process_frame(frame, output=fmt, consume=consume)
        return out, res, frame.img, frame.info, fmt

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
