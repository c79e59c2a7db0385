"""How frames are processed: the :class:`Settings` of a run and the choices they take.

The modes, the ``profile`` choices, the policies for frames nothing is applied to and
for JPEGs the camera already corrected; :class:`Settings` checks a combination once, when
it is made. Used by :class:`vigproc.pipeline.processor.Processor` and by every front end
that builds one.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

from vigproc.core.methods import METHODS
from vigproc.errors import VigprocError
from vigproc.pipeline.outputs import OUTPUT_FORMATS


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
        if self.mode not in MODES:
            raise VigprocError(f"unknown mode {self.mode!r} (choose from {', '.join(MODES)})")
        if self.method not in METHODS:
            # only for a name that is not built in: the plugin scan loads numpy and the entry points
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
