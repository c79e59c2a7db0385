"""A display-encoded frame (a JPEG's or PNG's code values) through the processor
without a full-frame float copy: the estimate reads a reduced copy binned straight
from the codes, and the correction stays in the codes' own domain.

:class:`~vigproc.pipeline.processor.Processor` hands an
:class:`~vigproc.io.images.EncodedImage` here; a float frame (EXR, float TIFF, RAW)
keeps the float path.
"""

from __future__ import annotations

import numpy as np

from vigproc.core.pixels import check_image
from vigproc.errors import InvalidImageError
from vigproc.io.image_read import COUNT_BAND as _BAND  # rows per band: no whole-frame temporary
from vigproc.io.images import EncodedImage, encode_steps


def check_encoded(enc: EncodedImage) -> EncodedImage:
    """What :func:`vigproc.core.pixels.check_image` refuses of a linear frame that code
    values can be: no positive pixel, or a constant frame (codes are finite and never
    negative). Returns ``enc``.

    Raises
    ------
    InvalidImageError
    """
    lo, hi = enc.code_range()
    if not enc.decode_table()[hi] > 0:
        raise InvalidImageError("image has no positive pixel: linear intensities must be > 0")
    if lo == hi:
        raise InvalidImageError("image is constant: there is nothing to estimate vignetting from")
    return enc


def _reduced_or_decoded(enc: EncodedImage, method: str, on_reduced, on_frame):
    """The one choice of every estimate of an encoded frame: from a copy binned in linear
    light straight from the codes (:meth:`EncodedImage.reduced`, kept for the next caller)
    when ``method`` reads binned copies only and the frame is large enough to be reduced,
    else from the decoded frame.

    Parameters
    ----------
    enc : EncodedImage
    method : str
    on_reduced : callable
        ``on_reduced(small, k, width, height, usable)``: the reduced copy, its factor, the
        full frame's size and the copy's usable-pixel mask.
    on_frame : callable
        ``on_frame(image, channel_axis)``: the decoded linear frame.

    Returns
    -------
    What the chosen callable returns.
    """
    k = _reduction(enc, method)
    if k is not None:
        small, usable = enc.reduced(k)
        h, w = enc.shape[:2]
        return on_reduced(small, k, w, h, usable)
    img = enc.linear()
    return on_frame(img, -1 if img.ndim == 3 else None)


def _reduction(enc: EncodedImage, method: str) -> int | None:
    """The factor by which an estimate by ``method`` reads ``enc`` reduced, or None
    when it reads the decoded frame (a method that reads more than binned copies, or
    a frame too small to be reduced)."""
    from vigproc.core.estimate import REDUCIBLE_METHODS, reduction_factor

    h, w = enc.shape[:2]
    k = reduction_factor(w, h)
    return k if method in REDUCIBLE_METHODS and k > 1 else None


def prepare_encoded(enc: EncodedImage, method: str | None) -> EncodedImage:
    """Count now, in the caller's thread, what the per-frame path asks of ``enc``'s
    codes: their range (:func:`check_encoded`), the samples at the white point
    (:func:`white_samples`) and, with ``method``, the reduced copy an estimate by it
    reads (:meth:`EncodedImage.reduced`). Each is kept on ``enc`` and read there, so
    what the frame gets is the same; a thread that reads frames ahead
    (:meth:`vigproc.pipeline.processor.Processor.read_ahead`) takes these passes over
    the frame off the thread that estimates and corrects. Returns ``enc``.

    Parameters
    ----------
    enc : EncodedImage
    method : str or None
        The estimator, or None when no estimate is expected (nothing reduced).

    Returns
    -------
    EncodedImage
    """
    enc.code_range()
    enc.top_count()
    k = _reduction(enc, method) if method is not None else None
    if k is not None and k <= min(enc.shape[:2]):
        enc.reduced(k)
    return enc


def estimate_encoded(enc: EncodedImage, method: str, *, hint=None, seed: int | None = None):
    """The frame's estimate by ``method``: from a copy binned in linear light straight
    from the codes (:func:`vigproc.core.estimate.estimate_reduced`) when the estimator
    reads binned copies only, else from the decoded frame (``seed``: the random start
    of ``lyu2010-rand``).

    Returns
    -------
    VignettingModel
        For the full frame.
    """
    from vigproc.core.estimate import estimate_checked, estimate_reduced

    return _reduced_or_decoded(
        enc, method,
        lambda small, k, w, h, usable: estimate_reduced(small, k, w, h, method, hint=hint, usable=usable),
        lambda img, axis: estimate_checked(check_image(img, axis), method, hint=hint, seed=seed))


def evidence_encoded(enc: EncodedImage, method: str) -> bytes:
    """The frame's evidence for its lens's profile
    (:func:`vigproc.core.estimate.frame_evidence`), binned from the reduced copy
    :func:`estimate_encoded` read (the one :meth:`EncodedImage.reduced` keeps: not reduced
    twice), with the full frame's geometry (:func:`vigproc.core.estimate.reduced_evidence`);
    a frame too small to be reduced is decoded and binned whole.

    Raises
    ------
    InvalidImageError
        As :func:`vigproc.core.estimate.frame_evidence`.
    """
    from vigproc.core.estimate import _robust_settings, frame_evidence, reduced_evidence

    return _reduced_or_decoded(
        enc, method,
        lambda small, k, w, h, usable: reduced_evidence(small, k, w, h, method, usable=usable),
        lambda img, axis: frame_evidence(img, axis, _robust_settings(method, None)))


def estimate_with_evidence_encoded(enc: EncodedImage, method: str):
    """What learn mode pools of a frame (:func:`vigproc.core.estimate.estimate_with_evidence`:
    the robust fit and the frame's evidence, one working copy), from the reduced copy
    :meth:`EncodedImage.reduced` keeps, with the full frame's geometry; a frame too small to
    be reduced is decoded whole. ``method`` is one of
    :data:`~vigproc.core.estimate.EVIDENCE_METHODS`.

    Returns
    -------
    (VignettingModel, bytes)

    Raises
    ------
    InvalidImageError
    """
    from vigproc.core.estimate import estimate_with_evidence, reduced_estimate_with_evidence

    return _reduced_or_decoded(
        enc, method,
        lambda small, k, w, h, usable: reduced_estimate_with_evidence(small, k, w, h, method, usable=usable),
        lambda img, axis: estimate_with_evidence(img, axis, method=method))


def correct_encoded(enc: EncodedImage, model, fmt, strength: float, *, in_place: bool = False):
    """``enc`` corrected by ``model`` for the output format ``fmt``
    (:class:`~vigproc.pipeline.processor.OutputFormat`): an :class:`EncodedImage` in the
    output's depth and transfer, clipped at its white point, when ``fmt`` is an
    integer format (:func:`vigproc.core.correct.correct_codes`); else the float32 linear
    frame (:func:`vigproc.core.correct.correct`). A model that corrects with a field of
    its own (a DNG GainMap) goes the float way too.

    ``in_place``: the output's codes overwrite ``enc``'s when they have the same depth
    (one frame in memory instead of two; ``enc`` is then the corrected frame's codes).
    """
    from vigproc.core.correct import correct, correct_codes

    if not fmt.integer or hasattr(model, "correct_image"):
        img = enc.linear()
        how = dict(channel_axis=-1 if img.ndim == 3 else None, strength=strength, clip=1.0 if fmt.integer else None)
        return model.correct_image(img, **how) if hasattr(model, "correct_image") else correct(img, model, **how)
    if (model.is_identity or strength == 0) and (enc.depth, enc.transfer) == (fmt.depth, fmt.transfer):
        return enc  # nothing divided out: the codes as read
    steps = encode_steps(fmt.transfer, fmt.depth)
    codes = enc.codes
    out = codes if in_place and codes.dtype == np.dtype(fmt.depth) and codes.flags.c_contiguous \
        and codes.flags.writeable else None
    if out is not None:  # enc's codes become the output's: its reduced copy no longer holds
        enc.forget_reduced()
    return EncodedImage(correct_codes(codes, model, enc.decode_table(), steps, strength=strength, out=out),
                        fmt.transfer)


def white_samples(x, *, source: bool = False) -> int:
    """Samples at the white point: of a corrected frame (at or above 1.0, or the top
    code), or with ``source`` of the frame as read (exactly 1.0, or the top code)."""
    # in bands of rows: a full-frame boolean temporary is a third of an 8-bit frame
    if isinstance(x, EncodedImage):  # counted once per frame (EncodedImage.top_count)
        return x.top_count()
    a = np.asarray(x)
    if a.ndim == 0:
        return int(a == 1.0 if source else a >= 1.0)
    return sum(int(np.count_nonzero(b == 1.0 if source else b >= 1.0))
               for b in (a[r:r + _BAND] for r in range(0, max(a.shape[0], 1), _BAND)))
