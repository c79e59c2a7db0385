"""Adobe lens profiles (LCP): their vignetting as vigproc profiles.

Adobe Camera Raw, Lightroom and the DNG Converter correct lenses with *lens correction
profiles*, XMP/RDF files (``.lcp``) made with Adobe Lens Profile Creator.  A file holds
one or more calibration *entries* (``rdf:li`` of ``photoshop:CameraProfiles``), each for
one focal length, aperture and focus distance of one camera + lens, with the camera and
lens it names (``stCamera:Make``, ``Model``, ``Lens``, ``LensPrettyName``...).  An entry's
``stCamera:PerspectiveModel`` may hold a ``stCamera:VignetteModel``:

    L(r) = 1 + α1 r² + α2 r⁴ + α3 r⁶       (``VignetteModelParam1..3``)

the recorded brightness relative to the ideal one (an attenuation: I = I_ideal · L), at

    r² = ((u − u0) / fx)² + ((v − v0) / fy)²

with (u, v) the pixel position, the optical centre u0 = ``ImageXCenter`` · W,
v0 = ``ImageYCenter`` · H (default ½), and the focal length in pixels fx =
``FocalLengthX`` · max(W, H), fy = ``FocalLengthY`` · max(W, H) (the focal length is
normalised by the image's larger dimension, the centre by each dimension; RawTherapee's
``LCPModelCommon::prepareParams`` notes that Adobe's technical paper gets this wrong).
The VignetteModel may give its own FocalLengthX/Y and centre; otherwise the
PerspectiveModel's apply; without any, fx = fy = 35-mm-equivalent focal length / 36 mm
(the long side of a 35-mm frame).  ``ApertureValue`` is the APEX value Av = 2 log2 N,
``FocusDistance`` metres.

:func:`read_lcp` reads a file's vignetting entries (:class:`LcpVignette`), accepting both
layouts in use: properties as attributes of ``rdf:Description`` elements (files since
2010) and as child elements under ``rdf:parseType="Resource"`` (older files), and
identity fields given once in the first entry.  :func:`import_lcp` fits each entry's
field with the Kang-Weiss model (:func:`vigproc.io.dng_vignette.fit_log_field`, error in EV)
and turns it into a :class:`vigproc.stores.profiles.Profile` keyed like the profile of a frame
with that camera and lens in its EXIF (``make|model|lens``, normalised as
:mod:`vigproc.io.exif` normalises EXIF; the focal length and aperture bins; the aspect ratio
of the calibration images, or 3:2).  Several entries in one bin (focus distances, a
focal length and its neighbour): the farthest focus distance, then the focal length and
aperture nearest the bin's centre, win.  Raw profiles (``CameraRawProfile="True"``) are
preferred over JPEG ones for the same bin.

LCP files are treated as hostile input: at most :data:`MAX_FILE_BYTES`, no DTD or
entities (refused before parsing), at most :data:`MAX_ENTRIES` entries, every number
checked finite and within physical bounds.

References
----------
.. [1] Adobe, "Adobe Camera Model", technical report in the documentation of Adobe Lens
   Profile Creator (2011): the geometric and vignette models of LCP files.
.. [2] RawTherapee ``rtengine/lcp.cc`` (``LCPModelCommon::prepareParams``,
   ``LCPMapper::calcVignetteFac``): centre and focal-length normalisation, the vignette
   polynomial as an attenuation.
.. [3] lensfun ``apps/lensfun-convert-lcp``: the file structure (attribute and element
   layouts, identity in the first entry, Make/Model/Lens/LensPrettyName, unusable lens
   names such as "Sigma Lens").
"""

from __future__ import annotations

import logging
import math
import os
import xml.etree.ElementTree as ET
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Iterable

import numpy as np

from vigproc.errors import SETTINGS, ModelError, VigprocError, one_line
from vigproc.io.lenskey import LensKey, _dedupe_model, _lens_text, normalise_text
from vigproc.stores.xmlsafe import parse_xml, read_capped

__all__ = [
    "LcpError",
    "LcpImport",
    "LcpVignette",
    "MAX_ENTRIES",
    "MAX_FILE_BYTES",
    "import_lcp",
    "read_lcp",
]

logger = logging.getLogger(__name__)

CAMERA_NS = "http://ns.adobe.com/photoshop/1.0/camera-profile"
RDF_NS = "http://www.w3.org/1999/02/22-rdf-syntax-ns#"
PHOTOSHOP_NS = "http://ns.adobe.com/photoshop/1.0/"
_C = f"{{{CAMERA_NS}}}"
_R = f"{{{RDF_NS}}}"
#: Largest LCP file read (Adobe's largest are a few hundred KB).
MAX_FILE_BYTES = 16 << 20
#: Most calibration entries read from one file.
MAX_ENTRIES = 10_000
#: FocusDistance at or beyond this is infinity (Adobe writes 999999995904 or 10000).
INFINITY_M = 1000.0
#: 35-mm frame's long side (mm): FocalLengthX when an entry gives none.
FRAME_35MM = 36.0
#: Identity fields an entry inherits from the entries before it.
_IDENTITY = ("Make", "Model", "Lens", "LensPrettyName", "CameraPrettyName", "CameraRawProfile",
             "SensorFormatFactor", "ImageWidth", "ImageLength", "Author", "ProfileName")


class LcpError(ModelError):
    """An LCP file cannot be used (unreadable, not an LCP, hostile, no usable entry);
    the message names the file."""

    blame = SETTINGS


@dataclass(frozen=True)
class LcpVignette:
    """One vignetting calibration of an LCP file.

    Attributes
    ----------
    source : str
        The file and the entry's index (``file.lcp#3``).
    make, model, lens, lens_pretty : str or None
        Camera make and model, the lens as the camera's EXIF names it, Adobe's name.
    raw : bool
        ``CameraRawProfile``: calibrated on raw data (else on the camera's JPEGs).
    crop_factor : float or None
        ``SensorFormatFactor``.
    focal_mm : float
    fnumber : float or None
        From the APEX ``ApertureValue``.
    distance_m : float or None
        ``FocusDistance``; ``math.inf`` beyond :data:`INFINITY_M`.
    fx, fy : float or None
        ``FocalLengthX``/``Y``: focal length over the image's larger dimension.
    cx, cy : float
        ``ImageXCenter``/``Y``: the optical centre relative to width and height.
    alpha : (float, float, float)
        ``VignetteModelParam1..3``.
    image_size : (int, int) or None
        ``ImageWidth``, ``ImageLength`` of the calibration images.
    residual : float or None
        ``ResidualMeanError`` of the vignette fit (Adobe's).
    """

    source: str
    make: str | None
    model: str | None
    lens: str | None
    lens_pretty: str | None
    raw: bool
    crop_factor: float | None
    focal_mm: float
    fnumber: float | None
    distance_m: float | None
    fx: float | None
    fy: float | None
    cx: float
    cy: float
    alpha: tuple[float, float, float]
    image_size: tuple[int, int] | None = None
    residual: float | None = None

    @property
    def aspect(self) -> float:
        """W/H of the calibration images (3:2 when the file does not say)."""
        if self.image_size:
            w, h = self.image_size
            return max(w, h) / min(w, h)  # the landscape frame: profiles are keyed by it
        return 1.5

    def focal_lengths_px(self, width: int, height: int) -> tuple[float, float]:
        """(fx, fy) in pixels of a ``width``×``height`` frame."""
        d = max(width, height)
        if self.fx is not None:
            return self.fx * d, (self.fy if self.fy is not None else self.fx) * d
        f35 = self.focal_mm * (self.crop_factor or 1.0)
        return f35 / FRAME_35MM * d, f35 / FRAME_35MM * d

    def log_phi_at(self, rel_v: np.ndarray, rel_h: np.ndarray, width: int, height: int) -> np.ndarray:
        """ln L at the grid of relative positions ``rel_v`` × ``rel_h`` of a ``width``×``height``
        frame (positions are pixel-centre fractions, 0..1 down and across).

        Raises
        ------
        ModelError
            L falls to 0 or below inside the frame (a profile used far outside its range).
        """
        fx, fy = self.focal_lengths_px(width, height)
        dx = (np.asarray(rel_h, dtype=np.float64) - self.cx) * width / fx
        dy = (np.asarray(rel_v, dtype=np.float64) - self.cy) * height / fy
        r2 = dx[None, :] ** 2 + dy[:, None] ** 2
        a1, a2, a3 = self.alpha
        lum = 1.0 + r2 * (a1 + r2 * (a2 + r2 * a3))
        if not np.all(lum > 0.0):
            raise ModelError(one_line(f"{self.source}: the LCP vignette 1 + a1 r² + a2 r⁴ + a3 r⁶ falls to "
                                      f"{float(np.min(lum)):.3g} inside the frame"))
        return np.log(lum)

    def describe(self) -> str:
        n = f"f/{self.fnumber:.3g}" if self.fnumber else "f/?"
        d = "inf" if self.distance_m == math.inf else (f"{self.distance_m:g} m" if self.distance_m else "? m")
        return f"{self.make or '?'} {self.model or '?'} + {self.lens or self.lens_pretty or '?'} at {self.focal_mm:g} mm {n} {d}"


@dataclass
class LcpImport:
    """One entry's conversion: the profile and what the Kang-Weiss model misses.

    Attributes
    ----------
    entry : LcpVignette
    profile : Profile
    rms_ev, max_ev : float
        RMS and largest |log2 φ_model − log2 L| over the frame, EV.
    falloff_ev : float
        RMS of log2 L over the frame (how much vignetting there is).
    """

    entry: LcpVignette
    profile: Any
    rms_ev: float
    max_ev: float
    falloff_ev: float
    superseded: list[LcpVignette] = field(default_factory=list)

    def to_dict(self) -> dict[str, Any]:
        return {"key": str(self.profile.key), "entry": self.entry.describe(), "source": self.entry.source,
                "fit_rms_ev": self.rms_ev, "fit_max_ev": self.max_ev, "falloff_ev": self.falloff_ev,
                "superseded": [e.source for e in self.superseded]}


# --------------------------------------------------------------------------- #
# reading
# --------------------------------------------------------------------------- #


def _local(tag: str) -> str:
    return tag.rsplit("}", 1)[-1]


def _described(node: ET.Element) -> ET.Element:
    """A property node's content: its ``rdf:Description`` child when it has one."""
    d = node.find(f"{_R}Description")
    return d if d is not None else node


def _prop(node: ET.Element | None, name: str) -> str | None:
    """``stCamera:name`` of a node: an attribute, or a child element's text (also of its
    ``rdf:Description``)."""
    if node is None:
        return None
    for n in (node, _described(node)):
        v = n.get(_C + name)
        if v is not None:
            return v.strip()
        child = n.find(_C + name)
        if child is not None and child.text is not None and len(child) == 0:
            return child.text.strip()
    return None


def _child_model(node: ET.Element | None, name: str) -> ET.Element | None:
    if node is None:
        return None
    for n in (node, _described(node)):
        m = n.find(_C + name)
        if m is not None:
            return _described(m)
    return None


def _number(text: str | None, what: str, where: str, lo: float, hi: float) -> float | None:
    if text is None or text == "":
        return None
    try:
        v = float(text)
    except ValueError:
        raise LcpError(one_line(f"{where}: {what} {text[:40]!r} is not a number")) from None
    if not (math.isfinite(v) and lo <= v <= hi):
        raise LcpError(one_line(f"{where}: {what} {v:g} is outside [{lo:g}, {hi:g}]"))
    return v


def read_lcp(path: str | os.PathLike[str]) -> tuple[list[LcpVignette], list[str]]:
    """The vignetting calibrations of an Adobe LCP file.

    Parameters
    ----------
    path : path-like

    Returns
    -------
    (entries, skipped)
        Every entry with a perspective VignetteModel, in file order; and one line per
        entry without one that says why (no vignette model, a fisheye model, missing
        focal length).

    Raises
    ------
    LcpError
        Unreadable, too large, a DTD or entity declaration, not XML, no
        ``photoshop:CameraProfiles`` entries, or a number that is not finite or
        outside its physical range.

    References
    ----------
    Adobe, "Adobe Camera Model" (Lens Profile Creator documentation); lensfun
    ``lensfun-convert-lcp``; RawTherapee ``rtengine/lcp.cc``.
    """
    where = os.fspath(path)
    # decoded before the DTD check (a UTF-16 file spells <!DOCTYPE with zero bytes between)
    raw = read_capped(path, MAX_FILE_BYTES, LcpError, "lens profile")
    root = parse_xml(raw, LcpError, where, "lens profile")
    seqs = [s for cp in root.iter(f"{{{PHOTOSHOP_NS}}}CameraProfiles") for s in cp.iter(f"{_R}Seq")]
    items = [li for s in seqs for li in s.findall(f"{_R}li")]
    if not items:
        raise LcpError(one_line(f"{where}: no photoshop:CameraProfiles entries (not an Adobe lens profile)"))
    if len(items) > MAX_ENTRIES:
        raise LcpError(one_line(f"{where}: {len(items)} entries, more than the {MAX_ENTRIES} allowed"))
    entries: list[LcpVignette] = []
    skipped: list[str] = []
    inherited: dict[str, str] = {}
    for i, li in enumerate(items):
        node = _described(li)
        here = f"{where}#{i}"
        for k in _IDENTITY:  # given once, in the first entry, by older files
            v = _prop(node, k)
            if v is not None:
                inherited[k] = v
        focal = _number(_prop(node, "FocalLength"), "FocalLength", here, 1e-3, 1e5)
        persp = _child_model(node, "PerspectiveModel")
        if persp is None:
            skipped.append(f"{here}: no PerspectiveModel"
                           + (" (a fisheye model: its vignetting is not read)"
                              if _child_model(node, "FisheyeModel") is not None else ""))
            continue
        vig = _child_model(persp, "VignetteModel")
        if vig is None:
            skipped.append(f"{here}: no VignetteModel")
            continue
        if focal is None:
            skipped.append(f"{here}: no FocalLength")
            continue
        alpha = tuple(_number(_prop(vig, f"VignetteModelParam{k}"), f"VignetteModelParam{k}", here, -1e6, 1e6)
                      or 0.0 for k in (1, 2, 3))
        av = _number(_prop(node, "ApertureValue"), "ApertureValue", here, -2.0, 40.0)
        dist = _number(_prop(node, "FocusDistance"), "FocusDistance", here, 0.0, 1e15)
        width = _number(inherited.get("ImageWidth"), "ImageWidth", here, 1, 1e6)
        length = _number(inherited.get("ImageLength"), "ImageLength", here, 1, 1e6)

        def geo(name: str, lo: float, hi: float) -> float | None:
            # the VignetteModel's own value, else the PerspectiveModel's
            v = _prop(vig, name)
            return _number(v if v is not None else _prop(persp, name), name, here, lo, hi)

        fx, fy = geo("FocalLengthX", 1e-4, 1e3), geo("FocalLengthY", 1e-4, 1e3)
        cx, cy = geo("ImageXCenter", -1.0, 2.0), geo("ImageYCenter", -1.0, 2.0)
        entries.append(LcpVignette(
            source=here,
            make=inherited.get("Make"), model=inherited.get("Model"), lens=inherited.get("Lens"),
            lens_pretty=inherited.get("LensPrettyName"),
            raw=inherited.get("CameraRawProfile", "True").strip().lower() == "true",
            crop_factor=_number(inherited.get("SensorFormatFactor"), "SensorFormatFactor", here, 0.01, 100.0),
            focal_mm=focal,
            fnumber=2.0 ** (av / 2.0) if av is not None else None,
            distance_m=None if dist is None else (math.inf if dist >= INFINITY_M else dist),
            fx=fx, fy=fy if fy is not None else fx,
            cx=0.5 if cx is None else cx, cy=0.5 if cy is None else cy,
            alpha=alpha,  # type: ignore[arg-type]
            image_size=(int(width), int(length)) if width and length else None,
            residual=_number(_prop(vig, "ResidualMeanError"), "ResidualMeanError", here, 0.0, 1e6),
        ))
    logger.debug("%s: %d vignetting entries, %d skipped", where, len(entries), len(skipped))
    return entries, skipped


# --------------------------------------------------------------------------- #
# importing
# --------------------------------------------------------------------------- #


def _lens_name(entry: LcpVignette) -> str | None:
    """The lens as a frame's EXIF key would name it: ``Lens`` (the camera's own lens tag),
    unless that is unusable (``Sigma Lens``, a bare ``18.0-55.0 mm`` spec, an ID),
    then Adobe's ``LensPrettyName``."""
    for v in (entry.lens, entry.lens_pretty):
        text = _lens_text(v)[0] if v else None
        if text:
            return text
    return None


def lens_id_for(entry: LcpVignette, *, camera_model: str | None = None) -> str:
    """The ``make|model|lens`` id a frame with this camera and lens gets from its EXIF.

    Raises
    ------
    LcpError
        Neither a camera model nor a usable lens name.
    """
    make = normalise_text(entry.make)
    model = _dedupe_model(make, normalise_text(camera_model or entry.model))
    lens = _lens_name(entry)
    if model is None and lens is None:
        raise LcpError(one_line(f"{entry.source}: names neither a camera model nor a usable lens"))
    return LensKey(make=make, model=model, lens=lens).lens_id()


def _rank(entry: LcpVignette, focal_centre: float, aperture_centre: float | None) -> tuple:
    """Which entry of a bin wins: raw first, the farthest focus, then the nearest focal
    length and aperture to the bin's centre, then file order."""
    d = entry.distance_m if entry.distance_m is not None else 0.0
    da = abs(math.log(entry.fnumber / aperture_centre)) if entry.fnumber and aperture_centre else 0.0
    return (not entry.raw, -d, round(abs(math.log(entry.focal_mm / focal_centre)), 9), round(da, 9))


def import_lcp(paths: Iterable[str | os.PathLike[str]], *, camera_model: str | None = None,
               lens_id: str | None = None, aspect: float | None = None, include_jpeg: bool = False,
               frame_long_side: int = 3000) -> tuple[list[LcpImport], list[str]]:
    """Vigproc profiles from the vignetting of LCP files.

    Each kept entry's field (on a frame of its calibration aspect ratio) is fitted by the
    Kang-Weiss model; the profile is trusted (a calibration, not an estimate), of
    provenance ``user``, and its notes name the file, the entry and the fit error.

    Parameters
    ----------
    paths : iterable of path-like
    camera_model : str, optional
        Key the profiles for this camera model (files for a whole make name none).
    lens_id : str, optional
        Key every profile under this lens id (what ``vigproc estimate`` prints for a
        frame as ``lens``), instead of the one derived from the file.
    aspect : float, optional
        W/H of the frames the profiles are for (default: the calibration images', else 3:2).
    include_jpeg : bool
        Also import profiles calibrated on the camera's JPEGs where a raw one exists
        for the same bin (otherwise the raw one wins; a JPEG profile alone is kept).
    frame_long_side : int
        Pixels of the frame the fit is made on (the profile is resolution-independent).

    Returns
    -------
    (imports, skipped)
        One :class:`LcpImport` per profile key, and what was not imported and why.

    Raises
    ------
    LcpError
        A file cannot be read (see :func:`read_lcp`).
    """
    from vigproc.io.dng_vignette import fit_log_field
    from vigproc.io.exif import casefold_lens_id
    from vigproc.stores.profiles import (
        ANY, Profile, ProfileKey, _aperture_index, _focal_centre, _focal_index, aperture_bin, aspect_label,
        focal_bin, normalise,
    )

    skipped: list[str] = []
    by_key: dict[Any, list[LcpVignette]] = {}
    for path in paths:
        entries, why = read_lcp(path)
        skipped += why
        for e in entries:
            try:
                lid = casefold_lens_id(lens_id) if lens_id else lens_id_for(e, camera_model=camera_model)
                asp = aspect if aspect else e.aspect
                key = ProfileKey(lid, focal_bin(e.focal_mm), aperture_bin(e.fnumber), aspect_label(asp))
            except LcpError as exc:
                skipped.append(str(exc))
                continue
            except VigprocError as exc:  # a ProfileStoreError: a name or number no key can hold
                skipped.append(one_line(f"{e.source}: {exc}"))
                continue
            by_key.setdefault(key, []).append(e)
    out: list[LcpImport] = []
    for key, cands in by_key.items():
        fc = _focal_centre(_focal_index(cands[0].focal_mm))
        ac = 2.0 ** (_aperture_index(cands[0].fnumber) / 6.0) if key.aperture_bin != ANY else None
        cands.sort(key=lambda e: _rank(e, fc, ac))
        best = cands[0]
        if not include_jpeg and best.raw:
            cands = [c for c in cands if c.raw]
        w = int(frame_long_side)
        h = max(2, round(w / key.aspect_ratio))
        try:
            m, rms, mx = fit_log_field(lambda rv, rh, e=best: e.log_phi_at(rv, rh, w, h), w, h, "lcp")
        except ModelError as exc:
            skipped.append(one_line(f"{best.source}: {exc}"))
            continue
        theta = normalise(m)[0]
        notes = (f"Adobe LCP {best.describe()} ({best.source}); Kang-Weiss fit {rms:.2e} EV RMS, "
                 f"{mx:.2e} EV at most over the frame")
        profile = Profile(key=key, theta=theta, covariance=None, provenance="user", trusted=True, notes=notes)
        falloff = m.field_ev_rms()
        out.append(LcpImport(best, profile, rms, mx, falloff, superseded=cands[1:]))
        logger.info("%s -> %s: fit %.2e EV RMS (%.2e at most), fall-off %.3f EV", best.source, key, rms, mx, falloff)
    return out, skipped


def lcp_files(args: Iterable[str | os.PathLike[str]]) -> list[Path]:
    """Files named, and the ``*.lcp`` files inside named folders (recursive, sorted)."""
    out: list[Path] = []
    for a in args:
        p = Path(a)
        if p.is_dir():
            out += sorted(q for q in p.rglob("*") if q.is_file() and q.suffix.lower() == ".lcp")
        else:
            out.append(p)
    return out
