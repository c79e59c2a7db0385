"""Learn as you go: a correct run also pools each frame into its lens's profile.

With :attr:`Settings.learn <vigproc.pipeline.processor.Settings>` (the default of
``watch`` and ``batch --mode correct`` with ``--profile auto``), each frame a correct run
handles is pooled into the stored profile of its lens setting exactly as
``--mode learn`` pools it (the same estimate and frame evidence, keyed by the file's
SHA-256, so a file is pooled once however often it is seen).  Once the profile is
trusted, ``--profile auto`` corrects the frames of that lens setting with it.

Three rules of this module:

* **Which frames are pooled** (:func:`pooling_refusal`): not a frame without lens data,
  not one whose EXIF names no lens on a body that takes interchangeable lenses (its
  frames would pool under ``?`` with other lenses' frames), not one whose named lens
  contradicts the shot (``LensKey.lens_problem``), and not a JPEG the camera already
  corrected (its fall-off is gone: it would pull the profile towards a flat field).
  A frame whose field the plausibility rules refuse, or whose fit is weak, *is*
  pooled, as learn mode pools it: the refusal is about dividing that field out of
  that frame; the profile pools the frames' evidence robustly (a multivariate-t
  centre of the lens-family fits, :mod:`vigproc.core.pooling`), where a frame a scene
  fooled is one outlier among many.
* **One field per series** (:class:`SteadyProfiles`): the store keeps, per lens
  setting, the revision of its trusted profile that correct runs apply, and the span of
  frame times of the series it corrects
  (:meth:`ProfileStore.series_revision <vigproc.stores.profiles.ProfileStore.series_revision>`).
  A frame's time is its capture time (EXIF ``DateTimeOriginal``, :func:`capture_time`),
  else the time it arrived. A frame within :data:`SERIES_GAP_S` of the span belongs to
  the series and gets that very revision; a frame further away starts a new series, and
  only there is the revision replaced by the stored profile as it is then (one worker
  writes it in one transaction, a compare-and-set; all follow). So every frame after
  trust of a series, of all workers, is corrected with one identical field, while the
  store keeps refining and the next series gets the better profile. ``vigproc profile
  apply`` starts a new series by hand. The revision is kept while the stored profile
  has lost its trust (later frames that disagree can raise its σ above the bound for a
  while): the series keeps its field instead of going back to single-frame estimates.
* **Fast once settled**: a frame corrected by its own lens setting's trusted profile
  that already pooled :data:`SETTLED_FRAMES` frames is not estimated nor pooled; the
  settled profile no longer moves and is applied from the next series on.
* **The profile's evidence before trust** (:func:`prefer_profile`): while the profile
  is not trusted yet, a frame's own estimate gives way to the profile pooled so far when
  that profile's field σ is already smaller than the frame's own.
"""

from __future__ import annotations

import calendar
import logging
import math
import re
import time
from dataclasses import dataclass, replace
from typing import Any

from vigproc.errors import ModelError, VigprocError

log = logging.getLogger(__name__)

__all__ = ["PRIOR_MARGIN", "PRIOR_MIN_FRAMES", "SERIES_GAP_S", "SETTLED_FRAMES", "Learned", "SteadyProfiles", "capture_time", "field_change_ev",
           "pooling_refusal", "prefer_profile"]

#: Seconds between two frames of one lens setting that end a series: the applied
#: revision is replaced only there. An hour: the frames of one shoot (a wedding's
#: ceremony, a product set) come minutes apart; the next shoot, hours or days later.
SERIES_GAP_S = 3600.0
#: Before trust, the profile so far replaces a frame's own estimate only once it pooled this
#: many frames (trust needs as many) and its field σ times :data:`PRIOR_MARGIN` is below the
#: frame's: a σ from the scatter of a few frames is itself uncertain (with 2 frames and no
#: margin, bench learn-series applied worse fields than the frames' own at frames 3 and 5).
PRIOR_MIN_FRAMES = 3
PRIOR_MARGIN = 2.0
#: Frames pooled into a trusted profile beyond which a frame it corrects is no longer
#: estimated (the figures of docs/benchmarks/profiles.md: 20 frames reach 0.009 EV).
SETTLED_FRAMES = 20


@dataclass(frozen=True)
class Learned:
    """What learning did with one frame (the record's ``learned``).

    Attributes
    ----------
    pooled : bool
        Whether this run pooled the frame now.
    profile : str or None
        The profile key it was pooled into (or is already in).
    frames : int or None
        Frames in that profile afterwards.
    trusted : bool or None
        Whether that profile is trusted afterwards.
    field_sigma_ev : float or None
        The profile's pooled field uncertainty afterwards.
    reason : str or None
        Why the frame was not pooled now (None when it was).
    """

    pooled: bool
    profile: str | None = None
    frames: int | None = None
    trusted: bool | None = None
    field_sigma_ev: float | None = None
    reason: str | None = None
    #: the profile as people read it (:meth:`Profile.label`), for :meth:`describe`
    label: str | None = None

    @classmethod
    def of(cls, profile, *, pooled: bool, reason: str | None = None) -> Learned:
        sigma = profile.field_sigma_ev
        return cls(pooled, str(profile.key), int(profile.n_frames), bool(profile.trusted),
                   None if sigma is None or not math.isfinite(sigma) else round(float(sigma), 5), reason,
                   profile.label())

    def describe(self) -> str:
        """One phrase for the log: ``learned into profile K (5 frames, not yet trusted)``."""
        if self.profile is None:
            return f"not learned: {self.reason}"
        state = "trusted" if self.trusted else "not yet trusted"
        head = "learned into" if self.pooled else f"not learned ({self.reason}):"
        return f"{head} profile {self.label or self.profile} ({self.frames} frame{'' if self.frames == 1 else 's'}, {state})"

    def to_dict(self) -> dict[str, Any]:
        d = {"pooled": self.pooled, "profile": self.profile, "frames": self.frames, "trusted": self.trusted,
             "field_sigma_ev": self.field_sigma_ev, "reason": self.reason, "summary": self.describe()}
        return {k: v for k, v in d.items() if v is not None}


def pooling_refusal(lens_key, in_camera=None) -> str | None:
    """Why a frame must not be pooled into a profile (None: it may be).

    Parameters
    ----------
    lens_key : LensKey or None
        The frame's lens identity.
    in_camera : InCamera, optional
        :func:`vigproc.io.incamera.read_in_camera`'s answer: the camera corrected the
        frame's vignetting.

    Returns
    -------
    str or None
        One sentence for the record and the log.
    """
    if lens_key is None:
        return "the frame's lens is unknown (no usable EXIF)"
    if in_camera is not None:
        return (in_camera.reason if in_camera.evidence == "XMP-vigproc:Applied"
                else f"the camera already corrected its vignetting ({in_camera.reason})")
    if getattr(lens_key, "lens_problem", None):
        return f"the lens its EXIF names cannot have taken it ({lens_key.lens_problem})"
    if not lens_key.make or not lens_key.model:
        return "its EXIF names no camera"
    if lens_key.lens is None:
        body = _camera(lens_key.make, lens_key.model)
        if body is None:
            return ("its EXIF names no lens and lensfun does not know the camera as a fixed-lens one: "
                    "frames of different lenses would pool under one profile")
        if not body.fixed_lens:
            return (f"its EXIF names no lens and a {body.maker} {body.model} takes interchangeable lenses: "
                    "frames of different lenses would pool under one profile")
    return None


def _camera(make: str, model: str):
    from vigproc.stores.lensfun import find_camera

    try:
        return find_camera(make, model)
    except VigprocError as exc:  # no lensfun database: the body is unknown
        log.debug("lensfun camera lookup failed: %s", exc)
        return None


def field_change_ev(a, b) -> float:
    """RMS over the frame of the difference of two profiles' log2 fields (EV); both of
    one aspect ratio. ``inf`` when their aspects differ."""
    import numpy as np

    from vigproc.core.normalised import _field_and_jacobian  # the store's own field grid

    if a.key.aspect != b.key.aspect:
        return math.inf
    fa = _field_and_jacobian(np.asarray(a.theta), a.key.aspect_ratio)[0]
    fb = _field_and_jacobian(np.asarray(b.theta), b.key.aspect_ratio)[0]
    return float(np.sqrt(np.mean((fa - fb) ** 2)))


_DATE = re.compile(r"\s*(\d{4})[:-](\d\d)[:-](\d\d)[ T](\d\d):(\d\d):(\d\d)(\.\d+)?")


def parse_exif_date(text) -> float | None:
    """Seconds of an EXIF or XMP date (``2019:06:01 14:03:22``, sub-seconds and XMP's
    ``2019-06-01T14:03:22+02:00`` too) on the camera's own clock: its time zone is
    ignored, as the frames of one camera are compared with each other only. None when
    absent, unparsable or zero (``0000:00:00 00:00:00``)."""
    m = _DATE.match(str(text)) if text is not None else None
    if m is None:
        return None
    y, mo, d, hh, mm, ss = (int(g) for g in m.groups()[:6])
    try:
        return calendar.timegm((y, mo, d, hh, mm, ss, 0, 0, 0)) + float(m.group(7) or 0.0) \
            if y > 0 and 1 <= mo <= 12 and 1 <= d <= 31 else None
    except (OverflowError, ValueError):
        return None


def capture_time(path, tags) -> float | None:
    """A file's capture time (EXIF ``DateTimeOriginal``, else XMP's), seconds on the
    camera's clock (:func:`parse_exif_date`), from the one exiftool read of the file
    (``tags``: :class:`vigproc.io.exif.FileTags` or a reader with ``read_tags``); None
    when the file does not say or cannot be read."""
    read = getattr(tags, "read_tags", None)
    if read is None:
        return None
    for k in ("EXIF:DateTimeOriginal", "XMP:DateTimeOriginal"):  # one name a call (read_tags)
        try:
            t = parse_exif_date(read(path, (k,)).get(k))
        except (VigprocError, ValueError, OSError) as exc:  # the frame is read elsewhere; its time is a hint
            log.debug("%s: no capture time: %s", path, exc)
            return None
        if t is not None:
            return t
    return None


def pooled_of(estimate, img, method: str):
    """What learning as you go pools of a frame the correction estimated: that very
    estimate (its candidate when too weak to apply alone) and, for the methods that give
    it, the frame's evidence, binned from the frame without fitting it again.

    Parameters
    ----------
    estimate : VignettingModel
        The frame's own estimate, as :func:`~vigproc.pipeline.processor.choose_model` made it.
    img : ndarray or EncodedImage
        The frame as the pipeline's door accepted it. A JPEG's or PNG's codes are binned
        from the reduced copy its estimate read, the evidence stating the full frame's
        geometry (:func:`vigproc.pipeline.encoded.evidence_encoded`), not decoded whole.
    method : str
        The estimation method.

    Returns
    -------
    (VignettingModel, bytes or None)
        For :meth:`ProfileStore.learn <vigproc.stores.profiles.ProfileStore.learn>`.

    Raises
    ------
    ModelError
        Nothing to pool: no evidence and an estimate without uncertainty.
    """
    from vigproc.core.estimate import EVIDENCE_METHODS, _robust_settings, clipped_mask, colour_of, luminance
    from vigproc.core.robust import luminance_evidence
    from vigproc.io.images import EncodedImage
    from vigproc.pipeline.encoded import evidence_encoded

    fit = estimate.candidate if estimate.candidate is not None else estimate
    evidence = None
    if method in EVIDENCE_METHODS:
        if isinstance(img, EncodedImage):  # binned from the reduced copy the estimate read
            evidence = evidence_encoded(img, method)
        else:
            evidence = luminance_evidence(luminance(img), _robust_settings(method, None), clipped_mask(img),
                                      colour_of(img))
    if fit.covariance is None and evidence is None:
        raise ModelError("no usable fit to learn from (no uncertainty)")
    return fit, evidence


def prefer_profile(estimate, profile, width: int, height: int):
    """The frame's own estimate, or the lens's profile pooled so far (:data:`PRIOR_MIN_FRAMES`
    frames or more, not yet trusted) when that profile is already clearly surer than the
    frame: its field σ (EV, the pooled frames' scatter) times :data:`PRIOR_MARGIN` is below
    the frame's own field σ (``quality.field_sigma_ev``;
    the candidate's for a frame too weak to apply alone), and its fall-off is clear by the
    default estimator's own rule (at least ``FamilySettings.min_snr`` times that σ; the
    model states the matching confidence, so the plausibility rules judge it as a fit).

    Parameters
    ----------
    estimate : VignettingModel
        The frame's own estimate.
    profile : Profile or None
        The stored profile of the frame's lens setting, as looked up now.
    width, height : int
        The frame's size.

    Returns
    -------
    (VignettingModel, dict or None)
        The model to apply and, when the profile was chosen, what the record says of
        the choice (None: the frame's own estimate stands).
    """
    if profile is None or profile.trusted or profile.n_frames < PRIOR_MIN_FRAMES:
        return estimate, None
    own = estimate.candidate if estimate.candidate is not None else estimate
    frame_sigma = float(own.quality.field_sigma_ev) if own.quality is not None else math.nan
    pooled_sigma = profile.field_sigma_ev
    if pooled_sigma is None or not math.isfinite(pooled_sigma) or not pooled_sigma * PRIOR_MARGIN < frame_sigma:
        return estimate, None  # an unknown σ (NaN) is never "surer"
    try:
        m = profile.model(width, height)
        ev_rms = m.field_ev_rms()
    except VigprocError as exc:  # a profile of another aspect or an absurd one: the frame stands alone
        log.debug("profile %s not usable for this frame: %s", profile.key, exc)
        return estimate, None
    # an untrusted profile states confidence 0: here its own, by the default estimator's
    # do-no-harm rule (the fall-off min_snr times its σ), so the plausibility rules judge it
    # as they judge the frame's fit; a fall-off that is not clear leaves the frame alone
    from vigproc.core.family_fit import FamilySettings, _confidence

    min_snr = FamilySettings().min_snr
    snr = ev_rms / pooled_sigma if pooled_sigma > 0 else math.inf
    if not snr >= min_snr:
        return estimate, None
    m = replace(m, quality=replace(m.quality, confidence=_confidence(snr, min_snr), field_ev_rms=ev_rms,
                                   field_sigma_ev=float(pooled_sigma), snr=snr, fallback=False))
    return m, {"profile": str(profile.key), "frames": int(profile.n_frames),
               "profile_sigma_ev": round(float(pooled_sigma), 5), "frame_sigma_ev": round(frame_sigma, 5)}


class SteadyProfiles:
    """A profile store as :func:`vigproc.pipeline.processor.choose_model` reads it, that
    hands out one revision of a trusted profile per lens setting and series, the same to
    every worker (see the module's docstring).

    Before each frame, :meth:`at` says when it was taken. The revision applied and the
    span of its series are kept in the store (:meth:`ProfileStore.series_revision`); a
    store without them (a stand-in without a database) is held per processor.

    Parameters
    ----------
    store : ProfileStore
        Borrowed.
    gap_s : float
        :data:`SERIES_GAP_S` by default.

    Attributes
    ----------
    last : Profile or None
        The profile the last :meth:`lookup` returned (None: none).
    revision : str or None
        The applied revision's id when ``last`` is one (None otherwise).
    latest : Profile or None
        The stored profile as that lookup found it (``last`` may be an earlier revision).
    new_series : bool
        The last lookup's frame started a new series.
    """

    def __init__(self, store, gap_s: float = SERIES_GAP_S) -> None:
        self.store = store
        self.gap_s = gap_s
        self._held: dict[str, list] = {}  # only for a store without applied revisions
        self._time: tuple[float, str] | None = None
        self.last = self.latest = self.revision = None
        self.new_series = False

    def at(self, captured: float | None) -> None:
        """The next frame's time: its capture time (seconds, :func:`capture_time`), else
        (None) now, on the arrival clock."""
        self._time = (float(captured), "capture") if captured is not None else (time.time(), "arrival")
        self.last = self.latest = self.revision = None  # nothing of the previous frame's lookup
        self.new_series = False

    def _series(self, hit, t: float, clock: str):
        """(revision id, profile, new series) applied to ``hit.key`` for a frame at ``t``, or None."""
        series = getattr(self.store, "series_revision", None)
        if series is not None:
            return series(hit, hit.key, at=t, clock=clock, gap=self.gap_s)
        # the store's rule (ProfileStore.series_revision), held here: [profile, first, last, clock, seen]
        now, held = time.time(), self._held.get(str(hit.key))
        if held is not None:
            if held[3] == clock and held[1] - self.gap_s <= t <= held[2] + self.gap_s:
                held[1], held[2], held[4] = min(held[1], t), max(held[2], t), now
                return None, held[0], False
            if held[3] != clock and now - held[4] <= self.gap_s:
                held[4] = now
                if clock == "capture":
                    held[1:4] = [t, t, clock]
                return None, held[0], False
        if hit.trusted or held is not None:
            self._held[str(hit.key)] = [hit if hit.trusted else held[0], t, t, clock, now]
            return None, self._held[str(hit.key)][0], True
        return None

    def lookup(self, lens_key, width: int, height: int, *, trusted_only: bool = False):
        """:meth:`ProfileStore.lookup`, but a lens setting whose profile is applied keeps
        that revision for the whole series, also while the stored one has lost its trust
        (frames that disagree raised its σ): the series keeps its field rather than going
        back to single-frame estimates."""
        self.last = self.revision = None
        self.new_series = False
        t, clock = self._time or (time.time(), "arrival")
        self._time = None  # one frame's time, once
        hit = self.latest = self.store.lookup(lens_key, width, height, trusted_only=False)
        if hit is None:
            return None
        got = self._series(hit, t, clock)
        if got is None and not hit.trusted and trusted_only:
            # nothing applied for this bin: a trusted neighbour or interpolation, as the store gives it
            alt = self.store.lookup(lens_key, width, height, trusted_only=True)
            got = self._series(alt, t, clock) if alt is not None and alt.trusted else None
        if got is None:
            return None if trusted_only else hit
        self.revision, self.last, self.new_series = got
        if self.new_series:
            log.info("profile %s: a new series; applying its %d-frame revision %s", self.last.key,
                     self.last.n_frames, self.revision or "")
        return self.last
