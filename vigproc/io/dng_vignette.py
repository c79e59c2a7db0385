"""A DNG's own vignetting calibration (its opcodes) as vigproc models, and back.

Cameras, phones and raw converters store the vignetting correction of a frame in
the DNG's opcode lists (:mod:`vigproc.io.dng_opcodes`): a ``FixVignetteRadial`` (a radial
gain polynomial around an optical centre) or ``GainMap`` grids (any shape, per colour
plane, often per Bayer phase).  Both are *gains*: the correction multiplies the raw
values by g, so the vignetting they describe is an attenuation φ = 1/g.

This module

* reads the opcode lists of a DNG with exiftool (:func:`read_opcode_lists`,
  :func:`read_embedded`) -- only those of the raw image's IFD, the ones a raw
  converter applies to the frame vigproc develops;
* turns them into a field on any frame (:meth:`EmbeddedCalibration.log_gain`): per
  colour plane for an RGB GainMap, the mean of the Bayer phases for a CFA GainMap;
* fits the Kang-Weiss model to that field by least squares
  (:meth:`EmbeddedCalibration.fit`, :func:`vigproc.core.normalised.fit_model_to_field`) and
  states the fit error in EV (RMS and largest over the frame);
* gives the model a frame is corrected with (:meth:`EmbeddedCalibration.model`): the
  fit for a FixVignetteRadial (the model expresses it to ~1e-3 EV), the field itself
  for a GainMap (:class:`GainFieldModel`: a model whose parameters are the fit, for
  records and pictures, but whose correction divides out the map exactly);
* converts a vigproc model back to a FixVignetteRadial (:func:`model_to_radial`) and
  writes it into a copy of a DNG's OpcodeList3 (:func:`write_dng_correction`), pixels
  untouched, for raw converters to apply.

Frame
-----
The opcodes' coordinates are those of the image at the stage of their list: the
active area for OpcodeList2 and OpcodeList3, the frame LibRaw develops (vigproc reads
DNGs with rawpy, which crops the active area and ignores DefaultCrop).  OpcodeList1
works on the stored raw data, margins included; a vignetting opcode there is read the
same way (on the developed frame), a sub-pixel difference when the margins are thin.
Pixel aspect ratios other than 1 are not supported (the SDK scales rows by it).

References
----------
.. [1] Adobe, *Digital Negative (DNG) Specification* 1.4.0.0, Chapter 7 "Opcode List
   Processing" (FixVignetteRadial, GainMap) and the tags OpcodeList1-3.
.. [2] Adobe DNG SDK 1.4: ``dng_opcode_FixVignetteRadial::Prepare`` (centre and
   maximum radius), ``dng_gain_map_interpolator`` (GainMap interpolation).
.. [3] S. Lyu, ACM MM&Sec 2010, Eq. (2); S. B. Kang and R. Weiss, ECCV 2000 (the model).
"""

from __future__ import annotations

import base64
import binascii
import contextlib
import json
import logging
import math
import os
import shutil
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from vigproc.atomic import publish, temporary_name
from vigproc.io.dng_opcodes import (
    AreaSpec,
    DngOpcodeError,
    FIX_VIGNETTE_RADIAL,
    GAIN_MAP,
    FixVignetteRadial,
    GainMap,
    OpcodeList,
    parse_opcode_list,
)
from vigproc.errors import (ImageReadError, ImageWriteError, InvalidImageError, ModelError, OutputSettingsError,
                            VigprocError, one_line, write_error)
from vigproc.io.exiftool_process import ExiftoolDied
from vigproc.scratch import scratch
from vigproc.core.colour import ColourField, fit_gain_planes
from vigproc.core.model import FitQuality, VignettingModel, frame_coords
from vigproc.core.normalised import fit_model_to_field
from vigproc.core.pixels import as_channels_last, finish_corrected

__all__ = [
    "EmbeddedCalibration",
    "GainFieldModel",
    "RadialFit",
    "model_to_gain_maps",
    "model_to_radial",
    "opcode_to_model",
    "read_embedded",
    "read_opcode_lists",
    "write_dng_correction",
]

logger = logging.getLogger(__name__)

#: Samples along the long side of the frame for the least-squares fits.
FIT_GRID = 64
#: Samples along the long side on which fit errors are measured (finer than the fit's).
CHECK_GRID = 256
#: A conversion error (RMS over the frame, EV) above which a warning is logged.
WARN_RMS_EV = 0.02
#: Gains outside this range are no vignetting correction (a corrupt or hostile map).
GAIN_RANGE = (1.0 / 64.0, 256.0)
#: PhotometricInterpretation of raw IFDs: CFA, LinearRaw.
_RAW_PHOTOMETRIC = (32803, 34892)
_LISTS = ("OpcodeList1", "OpcodeList2", "OpcodeList3")
_LN2 = math.log(2.0)


# --------------------------------------------------------------------------- #
# fitting
# --------------------------------------------------------------------------- #


def _grid_shape(width: int, height: int, n: int) -> tuple[int, int]:
    """(h, w) of a grid of ``n`` samples on the long side, the frame's aspect."""
    s = n / max(width, height)
    return max(4, round(height * s)), max(4, round(width * s))


def _fit_positions(width: int, height: int, w: int, h: int) -> tuple[np.ndarray, np.ndarray]:
    """Relative positions (down, across) of the w×h samples that
    :func:`vigproc.core.normalised.fit_model_to_field` takes as the frame: it measures them
    in the grid's half-diagonals, and the returned model in the frame's, so sample
    (i, j) stands for the frame point at the same normalised position (exactly, even
    when the grid's aspect ratio is only close to the frame's)."""
    scale = math.hypot(width, height) / math.hypot(w, h)
    x = frame_coords(w) * scale  # frame-centred frame pixels
    y = frame_coords(h) * scale
    return (y + height / 2.0) / height, (x + width / 2.0) / width


def _check_positions(width: int, height: int) -> tuple[np.ndarray, np.ndarray]:
    """Pixel centres of the frame, about :data:`CHECK_GRID` along the long side,
    spread over the whole frame (its corner pixels included)."""
    h, w = _grid_shape(width, height, min(CHECK_GRID, max(width, height)))
    rows = np.unique(np.round(np.linspace(0, height - 1, min(h, height))))
    cols = np.unique(np.round(np.linspace(0, width - 1, min(w, width))))
    return rows, cols


def fit_log_field(log_phi_at, width: int, height: int, method: str) -> tuple[VignettingModel, float, float]:
    """The Kang-Weiss model closest to a field ``log_phi_at(rel_v, rel_h) -> grid`` (ln φ at
    relative positions of a ``width``×``height`` frame).

    Least squares on ln φ over a :data:`FIT_GRID` grid of the frame
    (:func:`vigproc.core.normalised.fit_model_to_field`: free centre, elliptical P, α1..α7);
    the error is then measured at pixel centres spread over the frame, corners included.

    Returns
    -------
    (model, rms_ev, max_ev)
        RMS and largest |log2 φ_model − log2 φ|, EV; ``model.quality.objective`` and
        ``field_sigma_ev`` hold ``rms_ev``.
    """
    t0 = time.perf_counter()
    rows, cols = _check_positions(width, height)
    X, Y = np.meshgrid(cols - (width - 1) / 2.0, rows - (height - 1) / 2.0)
    target = log_phi_at((rows + 0.5) / height, (cols + 0.5) / width)
    for n in (FIT_GRID, 2 * FIT_GRID):
        h, w = _grid_shape(width, height, n)
        lf = log_phi_at(*_fit_positions(width, height, w, h))
        if not np.any(np.abs(lf) > 1e-12):
            return VignettingModel.identity(width, height, method=method, quality=FitQuality()), 0.0, 0.0
        m, _ = fit_model_to_field(lf, width, height)
        try:
            d = (m.log_field_at(X, Y) - target) / _LN2
            break
        except ModelError:
            # G > 0 on the fit's samples, not out to the frame's corner pixels: a steep
            # fall-off extrapolated; a finer grid samples closer to the corners
            continue
    else:
        raise ModelError(f"no Kang-Weiss model with G > 0 over the whole {width}x{height} frame fits this "
                         "fall-off (steeper in the corners than the model can follow)")
    rms, mx = float(np.sqrt(np.mean(d * d))), float(np.max(np.abs(d)))
    ev = m.field_ev_rms()
    q = FitQuality(confidence=1.0, field_ev_rms=ev, field_sigma_ev=rms, snr=ev / rms if rms > 0 else math.inf,
                   objective=rms, seconds=time.perf_counter() - t0)
    return VignettingModel(m.width, m.height, m.center, m.p, m.alpha, method=method, quality=q), rms, mx


# --------------------------------------------------------------------------- #
# the embedded calibration
# --------------------------------------------------------------------------- #


def cached_fit(calibration, width: int, height: int, method: str, what: str) -> tuple[VignettingModel, float, float]:
    """A calibration's gain field (``calibration.log_gain(width, height, rel=...)``) as
    its closest Kang-Weiss model on a ``width``×``height`` frame (:func:`fit_log_field`),
    fitted once per frame size (kept in ``calibration._fits``) and logged with its error:
    a warning above :data:`WARN_RMS_EV`. Shared by a DNG's opcodes and a maker's
    calibration (:mod:`vigproc.io.makernotes`)."""
    key = (width, height)
    hit = calibration._fits.get(key)
    if hit is None:
        hit = fit_log_field(lambda rv, rh: -calibration.log_gain(width, height, rel=(rv, rh)), width, height, method)
        calibration._fits[key] = hit
        m, rms, mx = hit
        (logger.warning if rms > WARN_RMS_EV else logger.info)(
            "%s: %s as a Kang-Weiss model: %.2e EV RMS, %.2e EV at most over the frame",
            calibration.source, what, rms, mx)
    return hit


@dataclass(frozen=True)
class EmbeddedOpcode:
    """One vignetting opcode of a DNG: the list it is in, its index there, the opcode."""

    list_name: str
    index: int
    opcode: FixVignetteRadial | GainMap

    def describe(self) -> str:
        op = self.opcode
        if isinstance(op, FixVignetteRadial):
            k = ", ".join(f"{v:.4g}" for v in op.k)
            return (f"{self.list_name}[{self.index}] FixVignetteRadial k=({k}) centre ({op.cx:.3f}, {op.cy:.3f}), "
                    f"corner gain {float(op.gain(1.0)):.3f}")
        pv, ph = op.points
        a = op.area
        return (f"{self.list_name}[{self.index}] GainMap {pv}x{ph}x{op.map_planes} on rows {a.top}-{a.bottom} "
                f"cols {a.left}-{a.right} planes {a.plane}+{a.planes} pitch {a.row_pitch}x{a.col_pitch}, "
                f"gains {float(op.gains.min()):.3f}-{float(op.gains.max()):.3f}")


@dataclass(frozen=True, eq=False)
class EmbeddedCalibration:
    """The vignetting opcodes of one DNG, in the order a raw converter applies them.

    Attributes
    ----------
    source : str
        The file (for messages and records).
    opcodes : tuple of EmbeddedOpcode
    """

    source: str
    opcodes: tuple[EmbeddedOpcode, ...]
    _fits: dict = field(default_factory=dict, repr=False)
    #: Colour (0 R, 1 G, 2 B) of each phase of the raw image's CFA, rows of the
    #: repeat pattern (``CFAPattern2``); None when unknown or not a CFA image.
    cfa_pattern: tuple[tuple[int, ...], ...] | None = None

    @classmethod
    def from_lists(cls, lists: Sequence[tuple[str, OpcodeList]], source: str,
                   cfa_pattern: tuple[tuple[int, ...], ...] | None = None) -> EmbeddedCalibration | None:
        """The vignetting opcodes of ``lists`` (``(name, list)`` in application order),
        or None when there is none; ``cfa_pattern``: see the attribute.

        Raises
        ------
        DngOpcodeError
            A vignetting opcode is malformed.
        """
        ops = []
        for name, lst in lists:
            for i, op in lst.decoded(f"{source} {name}"):
                if isinstance(op, FixVignetteRadial) and op.is_identity:
                    continue  # a no-op (the SDK's IsNOP): nothing calibrated
                ops.append(EmbeddedOpcode(name, i, op))
        return cls(source, tuple(ops), cfa_pattern=cfa_pattern) if ops else None

    @property
    def kind(self) -> str:
        """``FixVignetteRadial``, ``GainMap`` or both joined by ``+``."""
        return "+".join(dict.fromkeys(type(o.opcode).__name__ for o in self.opcodes))

    @property
    def label(self) -> str:
        """How a verdict names this reference."""
        return f"the DNG's own {self.kind}"

    @property
    def has_gain_map(self) -> bool:
        return any(isinstance(o.opcode, GainMap) for o in self.opcodes)

    def describe(self) -> list[str]:
        return [o.describe() for o in self.opcodes]

    def log_gain(self, width: int, height: int, channel: int | None = None, *,
                 rel: tuple[np.ndarray, np.ndarray] | None = None) -> np.ndarray:
        """ln g of a ``width``×``height`` frame for image plane ``channel``, or (None) the
        mean over the colour planes.

        Parameters
        ----------
        width, height : int
            The frame the opcodes apply to (their areas are in its pixels).
        channel : int or None
        rel : (ndarray, ndarray), optional
            Relative positions (down, across) to evaluate at; default the frame's pixel
            centres (an H×W result).  A half-size development passes its own pixel
            centres here with the full frame's size.

        The opcodes multiply: their log gains add.  CFA GainMaps (pitch > 1, one per
        Bayer phase; several of one phase multiply) give each channel the mean of the
        phases of its colour (two greens in a Bayer pattern) when the CFA pattern is
        known, else the mean of all phases; an RGB GainMap gives each channel its plane.

        Raises
        ------
        ModelError
            A gain outside :data:`GAIN_RANGE` (no correction of vignetting).
        """
        rv, rh = rel if rel is not None else ((np.arange(height) + 0.5) / height, (np.arange(width) + 0.5) / width)

        def lg(eo: EmbeddedOpcode, plane: int) -> np.ndarray:
            return np.log(self._checked(eo.opcode.gain_grid(rv, rh, width, height, plane), eo))

        out = np.zeros((np.size(rv), np.size(rh)))
        cfa = []
        for eo in self.opcodes:
            op = eo.opcode
            if isinstance(op, FixVignetteRadial):
                out += lg(eo, 0)
            elif op.cfa:
                colour = self.phase_colour(op)
                if channel is None or colour is None or channel == colour:
                    cfa.append(eo)
            elif channel is not None:
                out += lg(eo, channel)
            else:
                # the mean over the colour planes the map covers (of the first three)
                a = op.area
                planes = [p for p in range(a.plane, a.plane + a.planes) if p < 3] or [a.plane]
                out += sum(lg(eo, p) for p in planes) / len(planes)
        phases: dict[tuple[int, int, int], np.ndarray] = {}  # maps of a phase multiply; phases average
        for eo in cfa:
            a = eo.opcode.area
            k = (a.top % a.row_pitch, a.left % a.col_pitch, a.plane)
            phases[k] = phases.get(k, 0.0) + lg(eo, a.plane)
        for v in phases.values():
            out += v / len(phases)
        return out

    def phase_colour(self, op: GainMap) -> int | None:
        """The colour (0 R, 1 G, 2 B) of the CFA phase a pitch > 1 GainMap covers, by
        :attr:`cfa_pattern`; None when unknown (no pattern, or pitches that are not
        the pattern's)."""
        pat = self.cfa_pattern
        a = op.area
        if not pat or (a.row_pitch, a.col_pitch) != (len(pat), len(pat[0])):
            return None
        c = pat[a.top % a.row_pitch][a.left % a.col_pitch]
        return c if 0 <= c <= 2 else None

    @property
    def per_plane(self) -> bool:
        """The opcodes give the colour planes fields of their own (an RGB GainMap of
        several map planes, or CFA GainMaps whose phases' colours are known)."""
        for eo in self.opcodes:
            op = eo.opcode
            if isinstance(op, GainMap):
                if not op.cfa and op.map_planes > 1 and op.area.planes > 1:
                    return True
                if op.cfa and self.phase_colour(op) is not None:
                    return True
        return False

    def colour(self, width: int, height: int, center: tuple[float, float]) -> tuple[ColourField | None, float]:
        """The per-plane maps as a :class:`~vigproc.core.colour.ColourField` about
        ``center`` (the luminance fit's), with its fit error (EV, RMS over the frame
        and channels); (None, 0) when the planes share one field (within 1e-3 EV).

        The correction of a frame (:class:`GainFieldModel`) divides out the maps
        themselves; this field is what a model carries into records, profiles and a
        written DNG or lensfun file.
        """
        if not self.per_plane:
            return None, 0.0
        key = ("colour", width, height)
        hit = self._fits.get(key)
        if hit is None:
            gh, gw = _grid_shape(width, height, FIT_GRID)
            rv, rh = (np.arange(gh) + 0.5) / gh, (np.arange(gw) + 0.5) / gw
            lg = np.stack([self.log_gain(width, height, c, rel=(rv, rh)) for c in range(3)], axis=-1)
            spread = float(np.abs(lg - lg[..., 1:2]).max()) / _LN2
            if spread < 1e-3:
                hit = (None, 0.0)
            else:
                X, Y = np.meshgrid(rh * width - width / 2.0, rv * height - height / 2.0)
                cf, rms = fit_gain_planes(lg, X, Y, width, height, center, f"dng:{self.kind}")
                hit = (cf, float(np.sqrt(np.mean(rms[[0, 2]] ** 2))))
                (logger.warning if hit[1] > WARN_RMS_EV else logger.info)(
                    "%s: per-plane %s as a colour field: %.2e EV RMS", self.source, self.kind, hit[1])
            self._fits[key] = hit
        return hit

    @staticmethod
    def _checked(g: np.ndarray, eo: EmbeddedOpcode) -> np.ndarray:
        lo, hi = float(np.min(g)), float(np.max(g))
        if not (GAIN_RANGE[0] <= lo and hi <= GAIN_RANGE[1]):
            raise ModelError(one_line(f"{eo.list_name}[{eo.index}] {type(eo.opcode).__name__}: gains "
                                      f"{lo:.3g}..{hi:.3g} inside the frame are no vignetting correction "
                                      f"(allowed {GAIN_RANGE[0]:g}..{GAIN_RANGE[1]:g})"))
        return g

    def fit(self, width: int, height: int) -> tuple[VignettingModel, float, float]:
        """The Kang-Weiss model closest to the calibration's fall-off (φ = 1/g, the mean
        of the colour planes) on a ``width``×``height`` frame, with its error.

        Returns
        -------
        (model, rms_ev, max_ev)
            RMS and largest |log2 φ_model − log2 φ| over the frame, EV.

        Raises
        ------
        ModelError
            Gains outside :data:`GAIN_RANGE`, or no model fits.
        """
        return cached_fit(self, width, height, f"dng:{self.kind}", f"embedded {self.kind}")

    def model(self, width: int, height: int) -> VignettingModel:
        """The model a ``width``×``height`` frame is corrected with.

        A FixVignetteRadial alone: its Kang-Weiss fit (``method`` ``dng:FixVignetteRadial``,
        ``quality.objective`` = the fit's RMS error in EV).  With a GainMap: a
        :class:`GainFieldModel` whose parameters are that fit (and, for maps of
        their own per colour plane, a colour field fitted to them: :meth:`colour`) but
        whose correction divides out the maps themselves, each plane its own.
        """
        m, _, _ = self.fit(width, height)
        if not self.has_gain_map:
            return m
        colour, _ = self.colour(width, height, m.center)
        return GainFieldModel(m.width, m.height, m.center, m.p, m.alpha, method=m.method, quality=m.quality,
                              colour=colour, calibration=self)

    def to_dict(self, width: int | None = None, height: int | None = None) -> dict[str, Any]:
        """JSON-able summary (the fit's error when a frame size is given)."""
        d: dict[str, Any] = {"source": self.source, "kind": self.kind, "opcodes": self.describe()}
        if width and height:
            _, rms, mx = self.fit(width, height)
            d.update(fit_rms_ev=rms, fit_max_ev=mx)
        return d


def opcode_to_model(op: FixVignetteRadial | GainMap, width: int, height: int) -> tuple[VignettingModel, float, float]:
    """One FixVignetteRadial or GainMap as the Kang-Weiss model of its fall-off (φ = 1/g;
    a GainMap's colour planes averaged in log) on the ``width``×``height`` frame it applies to.

    Returns
    -------
    (model, rms_ev, max_ev)
        The least-squares fit and its RMS and largest error over the frame, EV.

    Raises
    ------
    ModelError
        Gains outside :data:`GAIN_RANGE`, or no model fits.
    """
    return EmbeddedCalibration("opcode", (EmbeddedOpcode("opcode", 0, op),)).fit(width, height)


@dataclass(frozen=True)
class GainFieldModel(VignettingModel):
    """A DNG GainMap as a model: Kang-Weiss parameters (its least-squares fit, for
    records, pictures and comparisons) and the map itself (for correcting).

    :meth:`correct_image` divides the frame by the map's own field (per colour plane
    where the map has them), not by the fit; everything else sees an ordinary
    :class:`VignettingModel`.
    """

    calibration: EmbeddedCalibration | None = field(default=None, repr=False, compare=False)

    def correct_image(self, img: np.ndarray, *, channel_axis: int | None = -1, strength: float = 1.0,
                      clip: float | None = None) -> np.ndarray:
        """``img · g^strength`` with g the embedded gains (float32, ``img``'s layout).

        Raises
        ------
        InvalidImageError
            Bad strength, or the result is not finite.
        """
        from vigproc.core.correct import _check_clip, _check_strength  # its Numba kernels: only when used

        if self.calibration is None:
            raise ModelError("this gain-field model carries no calibration")
        s = _check_strength(strength)
        c = _check_clip(clip)
        a = np.asarray(img)
        x = as_channels_last(a, None if a.ndim == 2 else channel_axis)
        x = x[..., None] if x.ndim == 2 else x
        h, w, ch = x.shape
        # the calibration belongs to the model's frame; this image may be another
        # resolution of it (a half-size development): evaluated at its pixel centres
        rel = ((np.arange(h) + 0.5) / h, (np.arange(w) + 0.5) / w)
        out = np.empty(x.shape, dtype=np.float32)
        for k in range(ch):  # one plane's field at a time: memory of one H×W float64
            lg = self.calibration.log_gain(self.width, self.height, k if ch > 1 else None, rel=rel)
            np.multiply(x[..., k], np.exp(s * lg), out=out[..., k], casting="unsafe")
        return finish_corrected(out, a.ndim, c, channel_axis)


# --------------------------------------------------------------------------- #
# model -> FixVignetteRadial
# --------------------------------------------------------------------------- #


@dataclass(frozen=True)
class RadialFit:
    """A vigproc model as a DNG FixVignetteRadial, and what is lost.

    Attributes
    ----------
    opcode : FixVignetteRadial
    rms_ev, max_ev : float
        RMS and largest |log2(1/g) − log2 φ^strength| over the frame, EV.
    strength : float
    """

    opcode: FixVignetteRadial
    rms_ev: float
    max_ev: float
    strength: float = 1.0

    def to_dict(self) -> dict[str, Any]:
        return {"k": list(self.opcode.k), "cx": self.opcode.cx, "cy": self.opcode.cy,
                "fit_rms_ev": self.rms_ev, "fit_max_ev": self.max_ev, "strength": self.strength}


def model_to_radial(model: VignettingModel, *, strength: float = 1.0) -> RadialFit:
    """The FixVignetteRadial closest to removing ``model``'s fall-off (``strength`` of it).

    The optical centre is the model's centre (clamped into the frame); k0..k4 are the
    least-squares fit of ``ln g(r)`` to ``−strength · ln φ`` over equal-area cells of the
    frame (Levenberg-Marquardt from the linearised solution).  An elliptical model is
    approximated by its radial average around the centre: the error says how much is
    lost.

    Parameters
    ----------
    model : VignettingModel
        For the frame the opcode is written for (the DNG's developed frame).
    strength : float
        Fraction of the fall-off to remove (0..2).

    Returns
    -------
    RadialFit

    Raises
    ------
    ModelError
        The model blacks out part of the frame, or no gain polynomial positive on
        [0, 1] fits.

    References
    ----------
    DNG Specification 1.4.0.0, Chapter 7, "FixVignetteRadial".
    """
    from scipy.optimize import least_squares

    strength = float(strength)
    if not (math.isfinite(strength) and 0.0 <= strength <= 2.0):
        raise ModelError(f"strength must be within [0, 2], got {strength!r}")
    w, h = model.width, model.height
    ox, oy = model.center
    cx = min(max(ox / w + 0.5, 0.0), 1.0)
    cy = min(max(oy / h + 0.5, 0.0), 1.0)
    if (cx, cy) != (ox / w + 0.5, oy / h + 0.5):
        logger.warning("the model's centre (%.0f, %.0f) px lies outside the frame: the opcode's optical centre "
                       "is clamped to its edge", ox, oy)
    probe = FixVignetteRadial((0.0,) * 5, cx, cy)
    gh, gw = _grid_shape(w, h, FIT_GRID)
    # cell centres of the frame in frame-centred pixels (every cell the same area)
    xs = ((np.arange(gw) + 0.5) * (w / gw) - w / 2.0)
    ys = ((np.arange(gh) + 0.5) * (h / gh) - h / 2.0)
    X, Y = np.meshgrid(xs, ys)
    target = -strength * model.log_field_at(X, Y).ravel()  # ln g wanted
    if model.is_identity or strength == 0.0 or not np.any(np.abs(target) > 1e-12):
        return RadialFit(FixVignetteRadial((0.0,) * 5, cx, cy), 0.0, 0.0, strength)
    r2 = (probe.radius_at(X, Y, w, h).ravel()) ** 2
    basis = np.stack([r2 ** (i + 1) for i in range(5)], axis=1)
    rc = np.linspace(0.0, 1.0, 129) ** 2
    basis_c = np.stack([rc ** (i + 1) for i in range(5)], axis=1)
    wc = 10.0 / math.sqrt(rc.size)
    floor = 1e-3

    def evaluate(k: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        g = 1.0 + basis @ k
        gs = np.maximum(g, 1e-12)
        gc = 1.0 + basis_c @ k
        act = gc < floor
        res = np.concatenate([(np.log(gs) - target) / math.sqrt(target.size), wc * np.where(act, floor - gc, 0.0)])
        jac = np.vstack([basis / gs[:, None] / math.sqrt(target.size), np.where(act[:, None], -wc * basis_c, 0.0)])
        return res, jac

    gt = np.exp(target)
    k0 = np.linalg.lstsq(basis / gt[:, None], (gt - 1.0) / gt, rcond=None)[0]  # first-order in ln g
    sol = least_squares(lambda k: evaluate(k)[0], k0, jac=lambda k: evaluate(k)[1], method="lm",
                        xtol=1e-15, ftol=1e-15, gtol=1e-15, max_nfev=2000)
    k = tuple(float(v) for v in sol.x)
    if (1.0 + basis_c @ sol.x).min() <= 0.0:
        raise ModelError("no FixVignetteRadial gain positive over the frame approximates this model")
    fvr = FixVignetteRadial(k, cx, cy)
    # measured at pixel centres spread over the frame (corners included), against the model itself
    rows, cols = _check_positions(w, h)
    X, Y = np.meshgrid(cols - (w - 1) / 2.0, rows - (h - 1) / 2.0)
    d = (-np.log(fvr.gain_grid((rows + 0.5) / h, (cols + 0.5) / w, w, h)) - strength * model.log_field_at(X, Y)) / _LN2
    rms, mx = float(np.sqrt(np.mean(d * d))), float(np.max(np.abs(d)))
    (logger.warning if rms > WARN_RMS_EV else logger.debug)(
        "model as FixVignetteRadial k=(%s) centre (%.3f, %.3f): %.2e EV RMS, %.2e EV at most",
        ", ".join(f"{v:.4g}" for v in k), cx, cy, rms, mx)
    return RadialFit(fvr, rms, mx, strength)


#: Map points along each axis of a written per-plane GainMap (spacing 1/(n − 1)).
WRITE_MAP_POINTS = 65


def model_to_gain_maps(model: VignettingModel, *, strength: float = 1.0,
                       cfa_pattern: tuple[tuple[int, ...], ...] | None = None,
                       points: int = WRITE_MAP_POINTS) -> list[GainMap]:
    """Per-plane DNG GainMaps that remove ``model``'s fall-off, each colour plane by its
    own field 1/(φ·ρ_c)^strength (:attr:`VignettingModel.colour`); a model with a measured
    grid (:class:`vigproc.core.gridfield.GridFieldModel`) by the grid's field, 1/φ_c^strength.

    With ``cfa_pattern`` (a CFA DNG): one map per phase of the pattern (pitch = the
    pattern's size), of its colour, for OpcodeList2 (before demosaicing, as phones
    write them). Without: one map of three planes over planes 0-2, for OpcodeList3
    (after demosaicing). Map points sit at relative positions i/(points − 1), the
    frame's pixel centres at ((row + ½)/H, (col + ½)/W) (the SDK's interpolation).

    Raises
    ------
    ModelError
        The model blacks out part of the frame, or a gain is outside :data:`GAIN_RANGE`.
    """
    strength = float(strength)
    if not (math.isfinite(strength) and 0.0 <= strength <= 2.0):
        raise ModelError(f"strength must be within [0, 2], got {strength!r}")
    w, h = model.width, model.height
    rel = np.linspace(0.0, 1.0, points)
    X, Y = np.meshgrid(rel * w - w / 2.0, rel * h - h / 2.0)
    grid = getattr(model, "grid", None)
    if grid is not None:  # a measured grid (a profile's, GridFieldModel): its own field, not the fit
        lg = grid.log_fields_rel(rel, rel)
    else:
        lr = model.colour.log_ratios_at(X, Y) if model.colour is not None else np.zeros(X.shape + (3,))
        lg = model.log_field_at(X, Y)[..., None] + lr
    gains = np.exp(-strength * lg)  # points × points × 3
    if gains.min() < GAIN_RANGE[0] or gains.max() > GAIN_RANGE[1]:
        raise ModelError(f"gains {gains.min():.3g}..{gains.max():.3g} are outside {GAIN_RANGE}")
    sp = 1.0 / (points - 1)
    if cfa_pattern:
        rp, cp = len(cfa_pattern), len(cfa_pattern[0])
        out = []
        for r in range(rp):
            for c in range(cp):
                colour = cfa_pattern[r][c]
                plane = gains[..., colour if 0 <= colour <= 2 else 1]
                out.append(GainMap(AreaSpec(r, c, h, w, 0, 1, rp, cp), plane, sp, sp))
        return out
    return [GainMap(AreaSpec(0, 0, h, w, 0, 3, 1, 1), gains, sp, sp)]


# --------------------------------------------------------------------------- #
# reading and writing DNG files (exiftool)
# --------------------------------------------------------------------------- #


def _run(args: list[str], what: str, error: type[Exception], *, read: str | None = None,
         rewrite: str | None = None) -> Any:
    """One exiftool command through this process's persistent exiftool
    (:mod:`vigproc.io.metadata`: ``-stay_open``, restarted once if it dies or hangs).

    ``read`` is a file the command reads, ``rewrite`` one it rewrites in place; both are
    appended last.  A name the argument protocol cannot carry (a line break, bytes that
    are not UTF-8) goes through a private alias, never a shell.

    Returns
    -------
    vigproc.io.exiftool_process.ExiftoolResult

    Raises
    ------
    error
        exiftool is missing, cannot start, or died twice during the command.
    """
    from vigproc.io.metadata import _Exiftool  # OpenImageIO: only when a DNG is read or written

    try:
        with _Exiftool() as et:
            tail, target = [], None
            if read is not None:
                tail.append(et.source_name(read))
            if rewrite is not None:
                target = et.target_name(rewrite)
                tail.append(target)
            def _no_leftover() -> None:  # a killed exiftool's half-written copy would refuse the retry
                if target is not None:
                    with contextlib.suppress(OSError):
                        os.unlink(target + "_exiftool_tmp")

            try:
                res = et.proc.execute([*args, *tail], before_retry=_no_leftover)
            except ExiftoolDied as exc:
                raise error(f"{what}: exiftool {exc}") from None
            if target is not None and res.status == 0:
                et.put_back(target, rewrite)
            return res
    except (ImageWriteError, OutputSettingsError) as exc:  # missing or not starting: the caller's kind
        if isinstance(exc, error):
            raise
        raise error(f"{what}: {exc}") from None
    except VigprocError as exc:
        if isinstance(exc, error):
            raise
        raise error(f"{what}: cannot run exiftool: {exc}") from None


def _abs(path: str | os.PathLike[str]) -> str:
    # absolute: a name starting with '-' is never an option to exiftool
    return os.path.abspath(os.fspath(path))


def _read_groups(path: str | os.PathLike[str]) -> tuple[dict[str, dict[str, Any]], str | None]:
    """Per IFD group (``IFD0``, ``SubIFD``...): its opcode lists (base64 text) and raw
    markers; and the group of the raw image."""
    p = _abs(path)
    what = f"cannot read the opcode lists of {p!r}"
    res = _run(["-j", "-b", "-a", "-G1", *(f"-{t}#" for t in _LISTS), "-SubfileType#", "-CFAPattern2#",
                "-CFARepeatPatternDim#",
                "-PhotometricInterpretation#", "-File:FileType"], what, ImageReadError, read=p)
    try:
        recs = json.loads(res.stdout.decode("utf-8", "replace") or "[]")
    except ValueError:
        recs = []
    if not (isinstance(recs, list) and recs and isinstance(recs[0], dict)):
        err = one_line(res.stderr.decode("utf-8", "replace").strip())[:300]
        raise ImageReadError(f"{what}: exiftool: {err or 'no output'}")
    groups: dict[str, dict[str, Any]] = {}
    for key, value in recs[0].items():
        if ":" not in key:
            continue
        group, tag = key.split(":", 1)
        groups.setdefault(group, {})[tag] = value
    ftype = groups.get("File", {}).get("FileType")
    if ftype not in ("DNG", None):
        raise ImageReadError(f"{what}: not a DNG (exiftool: file type {one_line(str(ftype))[:40]})")
    # the raw image: SubfileType 0 (the main image) with a raw photometric interpretation
    cands = [g for g, t in groups.items()
             if g.startswith(("IFD0", "SubIFD")) and t.get("SubfileType", 0) == 0]
    raw = next((g for g in cands if groups[g].get("PhotometricInterpretation") in _RAW_PHOTOMETRIC),
               cands[0] if cands else None)
    return groups, raw


def read_opcode_lists(path: str | os.PathLike[str], *, all_groups: bool = False) -> list[tuple[str, OpcodeList]]:
    """The opcode lists of a DNG's raw image, ``(name, list)`` in application order.

    Read with ``exiftool -b`` (binary values as base64 in JSON), never through a
    shell.  Only the lists of the raw image's IFD are returned (SubfileType 0 and CFA
    or LinearRaw data): a preview IFD's lists are not the frame's.

    Parameters
    ----------
    path : path-like
    all_groups : bool
        Every IFD's lists, named ``GROUP:OpcodeListN``.

    Returns
    -------
    list of (str, OpcodeList)
        Names ``OpcodeList1``..``3`` (or ``GROUP:OpcodeListN``); empty when the file has none.

    Raises
    ------
    ImageReadError
        exiftool cannot read the file, or it is not a DNG.
    DngOpcodeError
        A list is malformed (the message names the file, the IFD and the list).
    """
    groups, raw = _read_groups(path)
    return _lists_of(groups, raw, path, all_groups)


def _lists_of(groups: dict[str, dict[str, Any]], raw: str | None, path: str | os.PathLike[str],
              all_groups: bool = False) -> list[tuple[str, OpcodeList]]:
    """:func:`read_opcode_lists` of what :func:`_read_groups` read."""
    out = []
    for group, tags in groups.items():
        if not all_groups and group != raw:
            if any(t in tags for t in _LISTS):
                logger.debug("%s: opcode lists in %s (not the raw image's IFD) ignored", path, group)
            continue
        for name in _LISTS:
            value = tags.get(name)
            if value is None:
                continue
            where = f"{_abs(path)} {group}:{name}"
            if not (isinstance(value, str) and value.startswith("base64:")):
                raise DngOpcodeError(one_line(f"{where}: exiftool did not give the list's bytes"))
            try:
                blob = base64.b64decode(value[len("base64:"):], validate=True)
            except (binascii.Error, ValueError):
                raise DngOpcodeError(one_line(f"{where}: exiftool's base64 is malformed")) from None
            out.append((f"{group}:{name}" if all_groups else name, parse_opcode_list(blob, where)))
    return out


def read_embedded(path: str | os.PathLike[str]) -> EmbeddedCalibration | None:
    """The DNG's own vignetting calibration (its FixVignetteRadial/GainMap opcodes), or None.

    Raises
    ------
    ImageReadError
        exiftool cannot read the file, or it is not a DNG.
    DngOpcodeError
        An opcode list or a vignetting opcode in it is malformed.
    """
    groups, raw = _read_groups(path)
    pattern = _cfa_pattern(groups.get(raw, {})) if raw is not None else None
    return EmbeddedCalibration.from_lists(_lists_of(groups, raw, path), _abs(path), pattern)


def _cfa_pattern(tags: dict[str, Any]) -> tuple[tuple[int, ...], ...] | None:
    """The raw IFD's CFA pattern (``CFARepeatPatternDim`` rows × columns of colour
    indices 0 R, 1 G, 2 B from ``CFAPattern2``), or None when absent or malformed."""
    try:
        dims = [int(v) for v in str(tags.get("CFARepeatPatternDim", "")).split()]
        cols = [int(v) for v in str(tags.get("CFAPattern2", "")).split()]
    except ValueError:
        return None
    if len(dims) != 2 or not (1 <= dims[0] <= 8 and 1 <= dims[1] <= 8) or len(cols) != dims[0] * dims[1]:
        return None
    return tuple(tuple(cols[r * dims[1]:(r + 1) * dims[1]]) for r in range(dims[0]))


def _version_tuple(text: Any) -> tuple[int, ...]:
    try:
        return tuple(int(v) for v in str(text).split("."))
    except ValueError:
        return ()


def write_dng_correction(src: str | os.PathLike[str], dst: str | os.PathLike[str], model: VignettingModel, *,
                         strength: float = 1.0) -> dict[str, Any]:
    """Write a copy of the DNG ``src`` to ``dst`` whose OpcodeList3 carries ``model``'s
    correction as a FixVignetteRadial; the pixels and every other tag are untouched.
    A model with a colour field or a measured grid is written as per-plane GainMaps instead
    (:func:`model_to_gain_maps`): one per CFA phase in OpcodeList2 of a CFA DNG, one of
    three planes in OpcodeList3 otherwise.

    The opcode is appended to the raw IFD's list, after the camera's other opcodes; it
    *replaces* the file's own vignetting opcodes (in OpcodeList1-3): LibRaw, which vigproc
    develops with, ignores them, so the model corrects the whole fall-off (as in a TIFF);
    kept, a raw converter would correct twice.  A model that *is* the DNG's own
    calibration (``method`` ``dng:...``) adds nothing: the copy is written without a
    new opcode.  DNGBackwardVersion is raised to 1.3.0.0 when lower (the version that
    defines opcodes).  The copy is made in ``dst``'s folder, edited there by exiftool,
    read back and checked, then renamed onto ``dst``: ``dst`` is whole or absent, and
    ``src`` is never opened for writing.

    Parameters
    ----------
    src, dst : path-like
    model : VignettingModel
        The correction, for the DNG's developed frame.
    strength : float
        Fraction of the fall-off the opcode removes.

    Returns
    -------
    dict
        What was written: the opcode (k, centre), its fit error in EV, the IFD, and
        the number of opcodes in the new list.

    Raises
    ------
    ImageReadError, DngOpcodeError
        ``src`` is not a DNG exiftool reads, or its OpcodeList3 is malformed.
    ModelError
        No FixVignetteRadial approximates the model.
    ImageWriteError
        The copy cannot be written, or does not read back as written.
    """
    src_s, dst_s = _abs(src), _abs(dst)
    if os.path.exists(dst_s) and os.path.samefile(src_s, dst_s):
        raise OutputSettingsError(f"refusing to write {dst_s!r}: it is the input")
    groups, raw = _read_groups(src_s)
    if raw is None:
        raise ImageReadError(f"{src_s!r}: no raw image IFD found (SubfileType 0)")
    lists = dict(read_opcode_lists(src_s))
    info: dict[str, Any] = {"ifd": raw, "list": "OpcodeList3"}
    writes: dict[str, OpcodeList] = {}  # the lists that change
    if model.method.startswith("dng:"):
        info["opcode"] = None
        info["note"] = "the correction is the file's own calibration: nothing added"
        new = lists.get("OpcodeList3", OpcodeList())
    else:
        kept = {n: OpcodeList(tuple(op for op in lst if op.opcode_id not in (FIX_VIGNETTE_RADIAL, GAIN_MAP)))
                for n, lst in lists.items()}
        writes = {n: lst for n, lst in kept.items() if len(lst) != len(lists[n])}
        replaced = sum(len(lists[n]) - len(lst) for n, lst in writes.items())
        if replaced:
            info["replaced"] = replaced
        if model.colour is not None or getattr(model, "grid", None) is not None:
            # a colour field or a measured grid: per-plane GainMaps (a FixVignetteRadial has one gain for all planes)
            pattern = _cfa_pattern(groups.get(raw, {}))
            name = "OpcodeList2" if pattern else "OpcodeList3"
            maps = model_to_gain_maps(model, strength=strength, cfa_pattern=pattern)
            new = kept.get(name, OpcodeList()).appended(*(g.to_opcode() for g in maps))
            info["list"] = name
            info["opcode"] = {"kind": "GainMap", "maps": len(maps), "points": WRITE_MAP_POINTS,
                              "cfa_pattern": [list(r) for r in pattern] if pattern else None, "strength": strength}
        else:
            fit = model_to_radial(model, strength=strength)
            new = kept.get("OpcodeList3", OpcodeList()).appended(fit.opcode.to_opcode())
            info["opcode"] = fit.to_dict()
        writes[info["list"]] = new
    info["opcodes_in_list"] = len(new)
    try:
        tmp = temporary_name(dst_s, keep=60, suffix=".dng")
    except OSError as exc:
        raise write_error(f"cannot write {dst_s!r}: {exc.strerror or exc}", exc) from None
    leftovers = (tmp, tmp + "_exiftool_tmp")
    done = False
    try:
        shutil.copyfile(src_s, tmp)
        if writes:
            with scratch("dng") as td:  # after a kill: removed by the next process's sweep
                args = ["-q", "-q", "-m", "-overwrite_original"]
                for name, lst in sorted(writes.items()):
                    if not len(lst):  # emptied of the file's vignetting opcodes: the tag goes
                        args.append(f"-{raw}:{name}=")
                        continue
                    blob = os.path.join(td, f"{name}.bin")
                    with open(blob, "wb") as fh:
                        fh.write(lst.to_bytes())
                    args.append(f"-{raw}:{name}#<={blob}")
                backward = groups.get("IFD0", {}).get("DNGBackwardVersion")
                if _version_tuple(backward) < (1, 3):
                    args.append("-IFD0:DNGBackwardVersion=1.3.0.0")
                    info["dng_backward_version"] = "1.3.0.0"
                res = _run(args, f"cannot write {dst_s!r}", ImageWriteError, rewrite=tmp)
                if res.status != 0:
                    err = one_line(res.stderr.decode("utf-8", "replace").strip())[:300]
                    raise ImageWriteError(f"cannot write {dst_s!r}: exiftool failed: {err or res.status}")
            back = dict(read_opcode_lists(tmp))
            for name, lst in writes.items():
                if (back[name].to_bytes() if name in back else None) != (lst.to_bytes() if len(lst) else None):
                    raise ImageWriteError(f"cannot write {dst_s!r}: its {name} does not read back as written")
        publish(tmp, dst_s)
        done = True
    except (ImageReadError, DngOpcodeError) as exc:  # reading our own copy back failed
        raise ImageWriteError(str(exc).replace(tmp, dst_s)) from None
    except ImageWriteError:
        raise
    except OSError as exc:
        raise write_error(f"cannot write {dst_s!r}: {exc.strerror or exc}", exc) from None
    finally:
        if not done:
            for p in leftovers:
                with contextlib.suppress(OSError):
                    os.unlink(p)
    logger.debug("%s -> %s: %s", src_s, dst_s, info)
    return info


def is_dng(path: str | os.PathLike[str]) -> bool:
    """Whether ``path`` is named as a DNG (the suffix; the content is checked when read)."""
    return Path(path).suffix.lower() == ".dng"


def embedded_for(path: str | os.PathLike[str], profile: str) -> EmbeddedCalibration | None:
    """The DNG's own calibration when the profile choice can use it (``auto`` or
    ``embedded``) and ``path`` is a DNG; else None.

    With ``auto`` a DNG whose opcodes cannot be read is only logged (the frame is
    estimated instead); with ``embedded`` the error is raised.

    Raises
    ------
    ImageReadError, DngOpcodeError
        ``profile == "embedded"`` and the opcodes cannot be read.
    """
    if profile not in ("auto", "embedded") or not is_dng(path):
        return None
    try:
        return read_embedded(path)
    except ImageReadError as exc:  # DngOpcodeError too
        if profile == "embedded":
            raise
        logger.warning("%s: its embedded vignetting calibration is not used: %s", os.fspath(path), exc)
        return None
