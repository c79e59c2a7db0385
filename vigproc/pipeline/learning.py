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
* **The same field for a series** (:class:`SteadyProfiles`): the store keeps, per lens
  setting, the revision of its trusted profile that correct runs apply
  (:meth:`ProfileStore.apply_revision <vigproc.stores.profiles.ProfileStore.apply_revision>`).
  The first worker that finds the profile trusted writes it; every worker (and a
  restarted one) applies that very revision to every later frame of the setting until
  the stored profile has moved more than :data:`REFRESH_EV` (RMS over the frame, in EV)
  from it; then one worker replaces it (compare-and-set on its id) and all follow. The
  store keeps refining meanwhile. So the frames after trust, of all workers, are
  corrected with one identical field until such a move; the record's
  ``profile_applied.revision`` names it. The revision is kept while the stored profile
  has lost its trust (later frames that disagree can raise its σ above the bound for a
  while): the series keeps its field instead of going back to single-frame estimates.
* **Fast once settled**: a frame corrected by its own lens setting's trusted profile
  that already pooled :data:`SETTLED_FRAMES` frames is not estimated nor pooled. The
  settled profile no longer moves; the applied revision is replaced by it once, and
  from there on the frames of all workers share that field.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from typing import Any

from vigproc.errors import VigprocError

log = logging.getLogger(__name__)

__all__ = ["REFRESH_EV", "SETTLED_FRAMES", "Learned", "SteadyProfiles", "field_change_ev", "pooling_refusal"]

#: A trusted profile in use is replaced by the stored one only once their fields differ
#: by more than this (RMS of log2 φ over the frame, EV): a quarter of the trust bound
#: (:data:`vigproc.stores.profiles.TRUSTED_BOUND_EV`), 1.4 % in brightness, invisible
#: between two frames of a series. A profile just trusted still moves by about 0.01 EV
#: per frame for its first frames (a tighter tolerance would change the field every
#: few frames; docs/benchmarks/profiles.md, "learn as you go").
REFRESH_EV = 0.02
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

    @classmethod
    def of(cls, profile, *, pooled: bool, reason: str | None = None) -> Learned:
        sigma = profile.field_sigma_ev
        return cls(pooled, str(profile.key), int(profile.n_frames), bool(profile.trusted),
                   None if sigma is None or not math.isfinite(sigma) else round(float(sigma), 5), reason)

    def describe(self) -> str:
        """One phrase for the log: ``learned into profile K (5 frames, not yet trusted)``."""
        if self.profile is None:
            return f"not learned: {self.reason}"
        state = "trusted" if self.trusted else "not yet trusted"
        head = "learned into" if self.pooled else f"not learned ({self.reason}):"
        return f"{head} profile {self.profile} ({self.frames} frame{'' if self.frames == 1 else 's'}, {state})"

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
        return f"the camera already corrected its vignetting ({in_camera.reason})"
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


class SteadyProfiles:
    """A profile store as :func:`vigproc.pipeline.processor.choose_model` reads it, that
    hands out one revision of a trusted profile for a lens setting, the same to every
    worker, until the stored one moved more than ``refresh_ev`` from it (see the
    module's docstring).

    The revision applied is kept in the store (:meth:`ProfileStore.apply_revision`): the
    first worker that finds the profile trusted writes it, the others (and a restarted
    one) read it, and when the stored profile has moved beyond ``refresh_ev`` (or has
    settled, :data:`SETTLED_FRAMES`) one worker replaces it and all follow. A store
    without applied revisions (a stand-in without a database) is held per processor.

    Parameters
    ----------
    store : ProfileStore
        Borrowed.
    refresh_ev : float
        :data:`REFRESH_EV` by default.

    Attributes
    ----------
    last : Profile or None
        The profile the last :meth:`lookup` returned (None: none).
    revision : str or None
        The applied revision's id when ``last`` is one (None otherwise).
    latest : Profile or None
        The stored profile as that lookup found it (``last`` may be an earlier revision).
    """

    def __init__(self, store, refresh_ev: float = REFRESH_EV) -> None:
        self.store = store
        self.refresh_ev = refresh_ev
        self._held: dict[str, Any] = {}  # only for a store without applied revisions
        self.last = self.latest = self.revision = None

    def _applied(self, key):
        """(revision id, profile) applied for ``key``, or None."""
        read = getattr(self.store, "applied_revision", None)
        if read is None:
            return self._held.get(str(key))
        return read(key)

    def _apply(self, hit, replaces: str | None):
        write = getattr(self.store, "apply_revision", None)
        if write is None:
            self._held[str(hit.key)] = held = (None, hit)
            return held
        return write(hit, replaces=replaces)

    def lookup(self, lens_key, width: int, height: int, *, trusted_only: bool = False):
        """:meth:`ProfileStore.lookup`, but a lens setting whose profile is applied keeps
        that revision while the stored one stays within ``refresh_ev`` of it, and also
        while the stored one has lost its trust (frames that disagree raised its σ): the
        series keeps its field rather than going back to single-frame estimates."""
        self.last = self.revision = None
        hit = self.latest = self.store.lookup(lens_key, width, height, trusted_only=False)
        if hit is None:
            return None
        applied = self._applied(hit.key)
        if not hit.trusted:
            if applied is not None:
                self.revision, self.last = applied
                return self.last
            # nothing applied for this bin: a trusted neighbour or interpolation, as the store gives it
            hit = self.latest = self.store.lookup(lens_key, width, height, trusted_only=True) if trusted_only else hit
            if hit is None or not hit.trusted:
                return hit
            applied = self._applied(hit.key)
        if applied is None:
            applied = self._apply(hit, None)  # the first worker to find it trusted writes it; the others read it
        else:
            moved = field_change_ev(applied[1], hit)
            # once settled the stored profile stops moving (its frames are no longer pooled): the
            # revision applied from there on is the settled one, replaced once
            settling = hit.n_frames >= SETTLED_FRAMES and applied[1].n_frames < SETTLED_FRAMES
            if moved > self.refresh_ev or settling:
                was = applied[0]
                applied = self._apply(hit, was)
                if applied[0] != was:
                    log.info("profile %s moved %.4f EV from its applied revision%s: now its %d-frame revision %s",
                             hit.key, moved, " and settled" if settling else "", applied[1].n_frames,
                             applied[0] or "")
        self.revision, self.last = applied
        return self.last
