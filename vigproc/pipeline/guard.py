"""Never do harm: the last word before a field is divided out of a frame.

:meth:`vigproc.pipeline.processor.Processor.process_image` asks :func:`guard` about
every field it is about to apply in correct mode, whatever chose it (an estimate, a
stored profile, lensfun, a DNG's own calibration, a plugin). A refused field becomes
the identity model with the field as its ``candidate`` and the refusal's sentence as
its ``quality.reason`` (what the sidecar's ``not_applied`` says); the rule's name goes
to the record as ``not_applied_rule``.

Two kinds of reason:

* the camera already corrected the frame (:mod:`vigproc.io.incamera`: a JPEG whose
  maker notes say so, or a phone's): rule ``in-camera``, whatever the field's source;
* the field is not physically plausible (:mod:`vigproc.core.plausible`): every rule for
  fields fitted to this frame (estimates, estimator plugins, profile-source plugins),
  only ``brighter-corners`` for measured calibrations (:data:`CALIBRATED_SOURCES`).
"""

from __future__ import annotations

import logging
from typing import Any

from vigproc.core.model import VignettingModel
from vigproc.core.plausible import Refusal, Rules, judge, refused

log = logging.getLogger(__name__)

__all__ = ["CALIBRATED_SOURCES", "IN_CAMERA", "guard"]

#: Model sources that are a measured calibration of the lens, not a fit to this frame.
CALIBRATED_SOURCES = frozenset({"stored-profile", "lensfun", "embedded", "profile-file"})
#: The rule name of a frame the camera corrected.
IN_CAMERA = "in-camera"


def guard(model: VignettingModel, source: str, img: Any, lens_key=None, *, strength: float = 1.0,
          clips: bool = True, in_camera=None, where: str = "frame", check: bool = True,
          rules: Rules = Rules()) -> tuple[VignettingModel, Refusal | None]:
    """The model to apply to ``img`` and, when a rule refused ``model``, the refusal.

    Parameters
    ----------
    model : VignettingModel
        The field chosen for the frame (an estimate that fell back is returned as is).
    source : str
        Where it came from (:func:`vigproc.pipeline.processor.choose_model`).
    img : ndarray
        The linear frame, channels last.
    lens_key : LensKey, optional
        Its 35-mm focal length and f-number choose the real-lens population.
    strength : float
    clips : bool
        Whether the output format clips at white.
    in_camera : InCamera, optional
        :func:`vigproc.io.incamera.read_in_camera`'s answer for the frame's file.
    where : str
        The frame's name, for the log.
    check : bool
        Ask the plausibility rules (False: only ``in_camera`` can refuse).

    Returns
    -------
    (VignettingModel, Refusal or None)
    """
    fitted = model.candidate if model.candidate is not None else model
    if fitted.is_identity or strength <= 0:
        return model, None
    if in_camera is not None:  # said even of a fit that fell back: it is the first reason
        refusal = Refusal(IN_CAMERA, in_camera.reason)
    elif check and model.candidate is None:
        refusal = judge(model, _linear_sample(img, rules.sample_long_side), calibrated=source in CALIBRATED_SOURCES,
                        focal35=getattr(lens_key, "focal_35mm", None), fnumber=getattr(lens_key, "fnumber", None),
                        strength=strength, clips=clips, rules=rules)
    else:
        refusal = None
    if refusal is None:
        return model, None
    log.info("%s: not corrected: %s (rule %s)", where, refusal.reason, refusal.rule)
    return refused(fitted, refusal), refusal


def _linear_sample(img: Any, long_side: int) -> Any:
    """``img`` as the rules read it: a display-encoded frame's codes (an
    :class:`~vigproc.io.images.EncodedImage`) decoded on a strided sample of about
    ``long_side`` on the long side (the rules sample that finely anyway); a float
    frame as it is."""
    from vigproc.io.images import EncodedImage

    if not isinstance(img, EncodedImage):
        return img
    k = max(1, -(-max(img.shape[:2]) // long_side))
    return img.decode_table()[img.codes[::k, ::k]]
