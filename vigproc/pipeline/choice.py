"""Which model a frame is corrected with, and why none was applied.

:func:`choose_model` walks the ``profile`` setting's sources in order (a profile file,
a plugin, the DNG's own calibration, lensfun, a trusted stored profile) and estimates
when none has the lens; :func:`lens_hint` is what the EXIF tells the estimators.
"""

from __future__ import annotations

import logging
from typing import TYPE_CHECKING

from vigproc.errors import ModelError, VigprocError
from vigproc.pipeline.settings import SOURCE_PREFIX, Settings

if TYPE_CHECKING:  # annotations only
    import numpy as np

log = logging.getLogger(__name__)

# The imports inside the functions wait for a call: the processor imports this module at
# start-up (``vigproc --help`` goes through it), and the estimators, the stores and the
# image readers load numpy, Numba and OpenImageIO.


#: Why nothing was applied to a frame whose estimate is weak: one wording for every front end.
WEAK_EVIDENCE = "weak evidence: the estimate is not clearly above its uncertainty"


def not_applied_reason(model) -> str:
    """Why an estimate that fell back was not applied: its quality's own reason (a
    glow-shaped fall-off, say), else :data:`WEAK_EVIDENCE`."""
    q = getattr(model, "quality", None)
    return q.reason if q is not None and q.reason else WEAK_EVIDENCE


def choose_model(img: np.ndarray, lens_key, settings: Settings, store, *, where: str = "frame",
                 sources=None, embedded=None, warnings: list[str] | None = None, seed: int | None = None,
                 estimated=None):
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
    ``seed``: the random start of an estimator that draws one (``lyu2010-rand``).
    ``estimated``: the frame's estimate when it was made elsewhere (a RAW flat frame
    measured on its CFA planes, :mod:`vigproc.pipeline.cfa_flat`), returned as ``estimate``.

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
    if estimated is not None:
        return estimated, "estimate"
    from vigproc.io.images import EncodedImage

    if isinstance(img, EncodedImage):  # from a copy binned straight from the codes
        from vigproc.pipeline.encoded import estimate_encoded

        return estimate_encoded(img, settings.method, hint=lens_hint(lens_key, settings.method), seed=seed), "estimate"
    return estimate_checked(img, settings.method, hint=lens_hint(lens_key, settings.method), seed=seed), "estimate"


def lens_hint(lens_key, method: str):
    """What the frame's EXIF says of its lens for the lens-family prior (35-mm focal
    length and f-number, never the lens's identity), for the estimators that use it."""
    from vigproc.core.estimate import exif_hint  # one rule for every command and the check

    return exif_hint(lens_key, method)
