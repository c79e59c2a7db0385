"""Readable reports of forensic checks: one self-contained HTML file or a PNG.

For every frame the report shows the frame itself with the estimated (red) and
expected (green) vignetting centres and iso-attenuation ellipses, the fall-off
curves (mean EV on circles around the frame centre, against the radius in
half-diagonals) of the estimate, of the claimed lens, and of what frames truly
taken with that lens give (the lens plus the image bias, ±1 σ), the verdict and
the numbers behind it.  HTML embeds one figure per frame as base64 JPEG, so the file can be
mailed or archived alone; every string from a file name or EXIF is escaped.
"""

from __future__ import annotations

import base64
import html
import json
import math
import shlex
import struct
import zlib
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from vigproc._version import __version__
from vigproc.atomic import atomic_write_bytes
from vigproc.core.resample import resize_area
from vigproc.errors import ImageWriteError
from vigproc.io.lensident import display_lens_id
from vigproc.forensics.check import RING_RADII, Verdict, ring_falloff
from vigproc.io.picture import _text as draw
from vigproc.scratch import scratch

__all__ = ["ReportItem", "jpeg_bytes", "png_bytes", "report_figure", "thumbnail", "write_report"]

#: Long side of the frame thumbnail in the figure, px.
THUMB = 320
#: JPEG quality of the figures an HTML report embeds (a figure with a photograph in it
#: is ~6x smaller than as PNG; a 48-frame report was 19 MB).
HTML_JPEG_QUALITY = 85
_EST = (1.0, 0.25, 0.2)
_EXP = (0.2, 0.9, 0.3)
_BIAS = (0.55, 0.75, 0.55)
_VERDICT_COLOURS = {"consistent": (0.3, 0.85, 0.35), "inconsistent": (1.0, 0.3, 0.25),
                    "unknown-lens": (0.7, 0.7, 0.7), "insufficient-signal": (1.0, 0.8, 0.2),
                    "unlike-any-lens": (1.0, 0.55, 0.2)}


@dataclass(frozen=True)
class ReportItem:
    """One frame of a report.

    Attributes
    ----------
    name : str
        What to call the frame (its file name).
    verdict : Verdict
    thumb : ndarray or None
        H×W×3 linear thumbnail (:func:`thumbnail`); None for pooled verdicts.
    provenance : Provenance or None
        The file's hash, capture date, camera, lens as read and metadata conflicts
        (:func:`vigproc.io.provenance.read_provenance`); None for pooled verdicts.
    crop : CropEvidence or None
        The crop test's answer (:func:`vigproc.forensics.crops.check_crop`).
    """

    name: str
    verdict: Verdict
    thumb: np.ndarray | None = None
    provenance: Any = None
    crop: Any = None


# ------------------------------------------------------------------ pixels
def thumbnail(img: np.ndarray, long_side: int = THUMB) -> np.ndarray:
    """A small linear RGB copy of ``img`` (H×W or H×W×C, channels last) for display,
    scaled so its 99.5th percentile is 1."""
    a = np.asarray(img, dtype=np.float32)
    if a.ndim == 2:
        a = a[..., None]
    a = a[..., :3] if a.shape[2] >= 3 else np.repeat(a[..., :1], 3, axis=2)
    h, w = a.shape[:2]
    s = long_side / max(h, w)
    th, tw = max(2, round(h * s)), max(2, round(w * s))
    k = max(1, min(h // th, w // tw))
    if k > 1:  # block means first: cheap, and resize_area then works on a small array
        hb, wb = h // k, w // k
        a = a[: hb * k, : wb * k].reshape(hb, k, wb, k, 3).mean(axis=(1, 3))
    out = np.stack([resize_area(np.nan_to_num(a[..., c]), th, tw) for c in range(3)], axis=-1)
    peak = float(np.percentile(out, 99.5)) if out.size else 1.0
    return np.clip(out / peak if peak > 0 else out, 0.0, 1.0).astype(np.float32)


def _srgb(lin: np.ndarray) -> np.ndarray:
    lin = np.clip(lin, 0.0, 1.0)
    return np.where(lin <= 0.0031308, 12.92 * lin, 1.055 * np.power(lin, 1 / 2.4) - 0.055)


def png_bytes(rgb: np.ndarray) -> bytes:
    """8-bit sRGB PNG of a linear RGB float image in [0, 1] (no external encoder)."""
    a = np.round(_srgb(np.asarray(rgb, dtype=np.float64)) * 255.0).astype(np.uint8)
    if a.ndim != 3 or a.shape[2] != 3:
        raise ImageWriteError(f"a PNG figure must be H×W×3, got {a.shape}")
    h, w = a.shape[:2]
    raw = b"".join(b"\x00" + a[y].tobytes() for y in range(h))  # filter type 0 per row

    def chunk(tag: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + tag + data + struct.pack(">I", zlib.crc32(tag + data) & 0xFFFFFFFF)

    return (b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", struct.pack(">IIBBBBB", w, h, 8, 2, 0, 0, 0))
            + chunk(b"sRGB", b"\x00") + chunk(b"IDAT", zlib.compress(raw, 6)) + chunk(b"IEND", b""))


def jpeg_bytes(rgb: np.ndarray, quality: int = HTML_JPEG_QUALITY) -> bytes:
    """8-bit sRGB JPEG of a linear RGB float image in [0, 1]."""
    from vigproc.io.images import write_image

    with scratch("report") as d:  # swept by the next process when this one is killed
        path = Path(d) / "figure.jpg"
        write_image(path, np.clip(np.asarray(rgb, dtype=np.float32), 0.0, 1.0), format="jpeg", bit_depth="uint8",
                    transfer="srgb", quality=quality)
        return path.read_bytes()


def _put(img: np.ndarray, xs: np.ndarray, ys: np.ndarray, colour, width: int = 1) -> None:
    h, w = img.shape[:2]
    xs = np.round(xs).astype(int)
    ys = np.round(ys).astype(int)
    for dx in range(width):
        for dy in range(width):
            x, y = xs + dx, ys + dy
            ok = (x >= 0) & (x < w) & (y >= 0) & (y < h)
            img[y[ok], x[ok]] = colour


def _polyline(img: np.ndarray, xs: Sequence[float], ys: Sequence[float], colour, width: int = 2,
              dashed: bool = False) -> None:
    xs, ys = np.asarray(xs, dtype=float), np.asarray(ys, dtype=float)
    for i in range(len(xs) - 1):
        if dashed and i % 2:
            continue
        n = int(max(abs(xs[i + 1] - xs[i]), abs(ys[i + 1] - ys[i]), 1)) * 2
        t = np.linspace(0.0, 1.0, n)
        _put(img, xs[i] + t * (xs[i + 1] - xs[i]), ys[i] + t * (ys[i + 1] - ys[i]), colour, width)


def _cross(img: np.ndarray, x: float, y: float, colour, arm: int = 9) -> None:
    _polyline(img, [x - arm, x + arm], [y, y], colour, 3)
    _polyline(img, [x, x], [y - arm, y + arm], colour, 3)


def _contour(img: np.ndarray, x0: int, y0: int, model, shape: tuple[int, int], level_ev: float, colour) -> None:
    """Draw the iso-attenuation line log2 φ = −level of ``model`` over a thumbnail."""
    h, w = shape
    try:
        lf = model.log_field((h, w)) / math.log(2.0)
    except Exception:  # noqa: BLE001 - a model that blacks out the frame: no contour, the numbers say it
        return
    below = lf < -level_ev
    edge = np.zeros_like(below)
    edge[:, 1:] |= below[:, 1:] != below[:, :-1]
    edge[1:, :] |= below[1:, :] != below[:-1, :]
    ys, xs = np.nonzero(edge)
    _put(img, xs + x0, ys + y0, colour, 2)


#: Characters the built-in font of OpenImageIO lacks, spelled out for the PNG figure.
_PLAIN = str.maketrans({"≥": ">=", "≤": "<=", "ρ": "r", "σ": "sd", "α": "alpha", "…": "...", "–": "-",
                        "—": "-", "±": "+/-", "μ": "mu"})


def _text(img: np.ndarray, x: int, y: int, text: str, size: int = 14, colour=(0.9, 0.9, 0.9)) -> None:
    draw(img, x, y, text.translate(_PLAIN), size, colour)


def _wrap(line: str, width: int) -> list[str]:
    """Split ``line`` at spaces into pieces of at most ``width`` characters."""
    out, cur = [], ""
    for word in line.split(" "):
        if cur and len(cur) + 1 + len(word) > width:
            out.append(cur)
            cur = "   " + word
        else:
            cur = f"{cur} {word}" if cur else word
    return out + [cur] if cur else out


# ------------------------------------------------------------------ the figure
def _curves(v: Verdict):
    """(ρ, estimated EV, expected-lens EV or None) along the radius."""
    rho = np.linspace(0.02, 1.0, 50)
    est = exp = None
    if v.estimate is not None:
        fit = v.estimate.candidate if v.estimate.candidate is not None else v.estimate
        est = ring_falloff(fit, rho)
    if v.expected is not None:
        exp = ring_falloff(v.expected, rho)
    return rho, est, exp


def report_figure(item: ReportItem, *, numbers: bool = True) -> np.ndarray:
    """The figure of one frame: thumbnail with centres and ellipses, fall-off curves,
    verdict and (``numbers``; the HTML report has them as a table instead) numbers.

    Returns
    -------
    ndarray, float32, H×W×3 linear RGB in [0, 1]
    """
    v = item.verdict
    pad, plot_w, plot_h = 16, 430, 300
    th = item.thumb if item.thumb is not None else np.full((200, 300, 3), 0.08, dtype=np.float32)
    t_h, t_w = th.shape[:2]
    top = 44
    width = pad + t_w + 90 + plot_w + pad
    chars = int((width - 2 * pad) / 7.6)  # the built-in font at size 14
    text = _summary_lines(v) + _provenance_lines(item.provenance) + _crop_lines(item.crop)
    lines = [piece for line in text for piece in _wrap(line.translate(_PLAIN), chars)] if numbers else []
    height = top + max(t_h + 40, plot_h + 60) + 30 + 19 * len(lines)
    fig = np.full((height, width, 3), 0.1, dtype=np.float32)
    fig[top : top + t_h, pad : pad + t_w] = th
    col = _VERDICT_COLOURS.get(v.verdict, (0.9, 0.9, 0.9))
    _text(fig, pad, 28, f"{item.name[:70]}: {v.verdict.upper()}", 18, col)
    fit = None
    if v.estimate is not None:
        fit = v.estimate.candidate if v.estimate.candidate is not None else v.estimate
    # centres and ellipses, at the level where the lens (else the estimate) loses half its corner fall-off
    ref = v.expected if v.expected is not None else fit
    level = 0.25
    if ref is not None and not ref.is_identity:
        try:
            level = max(0.1, -0.5 * float(ring_falloff(ref, (0.9,))[0]))
        except Exception:  # noqa: BLE001 - keep the default level
            pass
    for model, colour in ((v.expected, _EXP), (fit, _EST)):
        if model is None:
            continue
        if item.thumb is not None and not model.is_identity:
            _contour(fig, pad, top, model, (t_h, t_w), level, colour)
        s = t_w / model.width
        cx = pad + ((model.width - 1) / 2 + model.center[0]) * s
        cy = top + ((model.height - 1) / 2 + model.center[1]) * s
        _cross(fig, cx, cy, colour)
    _text(fig, pad, top + t_h + 18, f"red: estimated, green: {v.profile or 'no lens'}"[:60], 13)
    _text(fig, pad, top + t_h + 34, f"centres (+) and the {level:.2f} EV iso-line", 13)
    # fall-off curves
    px0, py0 = pad + t_w + 80, top
    rho, est, exp = _curves(v)
    values = [c for c in (est, exp) if c is not None]
    if v.evidence is not None and v.evidence.expected_falloff_ev is not None:
        e = np.asarray(v.evidence.expected_falloff_ev)
        sd = np.asarray(v.evidence.falloff_sigma_ev)
        values += [e - sd, e + sd]
    # the EV range shown: from 0 down to at least -1, and up too when a fit brightens the
    # corners (a data-only fit can: it was drawn flat at 0 EV while the numbers said +1.2)
    lo = min([-1.0] + [float(np.min(c)) for c in values])
    hi = max([0.0] + [float(np.max(c)) for c in values])
    step = 0.5 if hi - lo <= 3 else 1.0
    lo, hi = -math.ceil(-lo / step - 1e-9) * step, math.ceil(hi / step - 1e-9) * step
    fig[py0 : py0 + plot_h, px0] = 0.7
    fig[py0 + plot_h, px0 : px0 + plot_w] = 0.7

    def xy(r, ev):
        return px0 + np.asarray(r) * (plot_w - 1), py0 + np.clip((hi - np.asarray(ev)) / (hi - lo), 0, 1) * (plot_h - 1)

    for ev in np.arange(hi, lo - 1e-9, -step):
        y = int(round(py0 + (hi - ev) / (hi - lo) * (plot_h - 1)))
        fig[y, px0 : px0 + plot_w : 3] = 0.55 if abs(ev) < 1e-9 else 0.35  # 0 EV brighter
        _text(fig, px0 - 62, y + 5, f"{ev:+.1f} EV", 13)
    for r in (0.0, 0.5, 1.0):
        _text(fig, int(px0 + r * (plot_w - 1)) - 8, py0 + plot_h + 18, f"{r:g}", 13)
    _text(fig, px0 + plot_w // 2 - 120, py0 + plot_h + 36, "radius (half-diagonals from the frame centre)", 13)
    if exp is not None:
        _polyline(fig, *xy(rho, exp), _EXP, 2)
    if est is not None:
        _polyline(fig, *xy(rho, est), _EST, 2)
    if v.evidence is not None and v.evidence.expected_falloff_ev is not None:
        e = np.asarray(v.evidence.expected_falloff_ev)
        sd = np.asarray(v.evidence.falloff_sigma_ev)
        for r, m, s in zip(RING_RADII, e, sd):
            x, (y1, y2) = xy(r, m)[0], xy([r, r], [m - s, m + s])[1]
            _polyline(fig, [x, x], [y1, y2], _BIAS, 2)
            _polyline(fig, [x - 5, x + 5], [xy(r, m)[1]] * 2, _BIAS, 2)
    # the legend below the axis, off the curves
    ly = py0 + plot_h + 56
    _text(fig, px0 + 12, ly, "estimated", 13, _EST)
    _text(fig, px0 + 112, ly, "claimed lens", 13, _EXP)
    _text(fig, px0 + 232, ly, "matching frames, 1 sd", 13, _BIAS)
    # numbers
    y = top + max(t_h + 40, plot_h + 60) + 22
    for line in lines:
        _text(fig, pad, y, line, 14)
        y += 19
    return fig


def _fmt(x, spec: str = ".3g") -> str:
    return "–" if x is None else format(x, spec)


def _summary_lines(v: Verdict) -> list[str]:
    lines = [v.reason, f"lens (EXIF): {display_lens_id(v.lens_id)};  compared with: "
             f"{(v.expected_source or '-') + ' ' + (v.profile or '')}"]
    lines.append(f"D² = {_fmt(v.score)}, false-alarm probability = {_fmt(v.p_false_alarm)} "
                 f"(inconsistent below {v.alpha:g}); frames: {v.n_frames}; confidence {_confidence(v)}")
    e = v.evidence
    if e is not None:
        lines.append("fall-off (EV) at ρ = " + ", ".join(f"{r:g}" for r in e.ring_radii) + ":  estimated "
                     + ", ".join(f"{x:+.2f}" for x in e.falloff_ev)
                     + ("" if e.expected_falloff_ev is None else
                        "; matching frames " + ", ".join(f"{x:+.2f}" for x in e.expected_falloff_ev)
                        + " (±" + ", ".join(f"{x:.2f}" for x in e.falloff_sigma_ev) + ")"))
        lines.append(f"centre: estimated ({e.centre_px[0]:.0f}, {e.centre_px[1]:.0f}) px"
                     + ("" if e.expected_centre_px is None else
                        f", lens ({e.expected_centre_px[0]:.0f}, {e.expected_centre_px[1]:.0f}) px, offset "
                        f"{e.centre_offset:.2f} half-diagonals")
                     + f";  shape (minor/major axis) {e.shape_ratio:.2f}"
                     + ("" if e.expected_shape_ratio is None else f" vs {e.expected_shape_ratio:.2f}"))
        if e.falloff_d2 is not None:
            lines.append(f"parts of D²: fall-off {e.falloff_d2:.2f} (4 d.o.f.), centre {e.centre_d2:.2f} (2 d.o.f.);"
                         f"  field difference {_fmt(e.field_diff_ev, '.2f')} EV RMS")
        if e.scene_d2 is not None:
            lines.append(f"unlike any lens (scene D²): {_scene_value(e)}")
    return lines


def _provenance_lines(p) -> list[str]:
    """The file as its metadata states it, for the PNG figure (the HTML has rows)."""
    if p is None:
        return []
    return [f"{name}: {value}" for name, value in _provenance_rows(p)]


def _provenance_rows(p) -> list[tuple[str, str]]:
    """(name, value) of a file's provenance (:class:`vigproc.io.provenance.Provenance`)."""
    rows = [("file SHA-256", p.sha256), ("file size", f"{p.size_bytes} bytes"),
            ("captured (DateTimeOriginal)", (p.captured or "not stated")
             + (f" {p.captured_offset}" if p.captured_offset else " (no time zone stated)" if p.captured else "")),
            ("camera", " ".join(x for x in (p.make, p.model) if x) or "not stated"),
            ("camera serial", p.serial or "not stated"),
            ("lens (as written)", (p.lens or "not stated") + (f", serial {p.lens_serial}" if p.lens_serial else ""))]
    found = list(p.conflicts) + list(p.problems)
    rows.append(("metadata conflicts", "; ".join(found) if found else "none found"))
    if p.unread:
        rows.append(("metadata not read", p.unread))
    return rows


def _crop_lines(crop) -> list[str]:
    return [] if crop is None else [f"crop test: {crop.verdict}: {crop.reason()}"]


def _confidence(v: Verdict) -> str:
    """The frame's one confidence figure (its estimate's, :func:`~vigproc.forensics.check.frame_quality`)."""
    if v.confidence is None:
        return "–"
    return f"{v.confidence:.2f}" + ("" if v.snr is None else f" (SNR {v.snr:.1f})")


def _scene_value(e) -> str:
    """How unlike any lens's the frame's fit is (the lens-family test's scene gate)."""
    limit = "no limit" if e.scene_limit is None else f"undecided above {e.scene_limit:.1f}"
    return f"{e.scene_d2:.1f} ({limit})"


# ------------------------------------------------------------------ HTML
_CSS = """body{font-family:system-ui,sans-serif;background:#1b1b1b;color:#ddd;margin:2em}
section{border-top:1px solid #444;padding:1em 0}img{max-width:100%}
table{border-collapse:collapse}td,th{padding:2px 10px;text-align:left;vertical-align:top}
th{color:#aaa;font-weight:normal}.v{font-weight:bold;padding:2px 8px;border-radius:4px;color:#111}
.consistent{background:#5c5}.inconsistent{background:#f54}.unknown-lens{background:#aaa}
.insufficient-signal{background:#fc3}.unlike-any-lens{background:#f93}"""


def _row(name: str, value) -> str:
    return f"<tr><th>{html.escape(name)}</th><td>{html.escape(str(value))}</td></tr>"


def _html_section(item: ReportItem) -> str:
    v = item.verdict
    fig = base64.b64encode(jpeg_bytes(report_figure(item, numbers=False))).decode("ascii")
    rows = [_row("verdict", v.verdict), _row("why", v.reason), _row("lens (EXIF)", display_lens_id(v.lens_id)),
            _row("compared with", f"{v.expected_source or '–'} {v.profile or ''}"),
            _row(f"D² ({len(v.whitened) if v.whitened else '-'} d.o.f., {v.test} test)", _fmt(v.score)), _row("false-alarm probability", _fmt(v.p_false_alarm)),
            _row("threshold", f"inconsistent when below {v.alpha:g}"), _row("frames", v.n_frames),
            _row("confidence (of the frame's estimate, as 'vigproc estimate' gives it)", _confidence(v))]
    e = v.evidence
    if e is not None:
        radii = ", ".join(f"{r:g}" for r in e.ring_radii)
        rows.append(_row(f"fall-off at ρ = {radii} (EV), estimated", ", ".join(f"{x:+.2f}" for x in e.falloff_ev)))
        if e.expected_falloff_ev is not None:
            rows.append(_row("… frames of the claimed lens", ", ".join(
                f"{m:+.2f} ± {s:.2f}" for m, s in zip(e.expected_falloff_ev, e.falloff_sigma_ev))))
            rows.append(_row("… difference", ", ".join(f"{x:+.2f}" for x in e.falloff_diff_ev)))
        rows.append(_row("vignetting centre (px from the frame centre)", f"({e.centre_px[0]:.1f}, {e.centre_px[1]:.1f})"))
        if e.expected_centre_px is not None:
            rows.append(_row("… of the claimed lens", f"({e.expected_centre_px[0]:.1f}, {e.expected_centre_px[1]:.1f})"))
            rows.append(_row("centre offset (half-diagonals)", f"{e.centre_offset:.3f}"))
        rows.append(_row("shape (minor/major axis)", f"{e.shape_ratio:.2f}" + (
            "" if e.expected_shape_ratio is None else f" (lens {e.expected_shape_ratio:.2f})")))
        if e.falloff_d2 is not None:
            rows.append(_row("parts of D²", f"fall-off {e.falloff_d2:.2f}, centre {e.centre_d2:.2f}"))
            rows.append(_row("field difference (EV RMS, raw)", _fmt(e.field_diff_ev, ".3f")))
        if e.scene_d2 is not None:
            rows.append(_row("unlike any lens (scene D²)", _scene_value(e)))
    if item.crop is not None:
        rows.append(_row("crop test", f"{item.crop.verdict}: {item.crop.reason()}"))
    if item.provenance is not None:
        rows += [_row(name, value) for name, value in _provenance_rows(item.provenance)]
    return (f'<section><h2>{html.escape(item.name)} <span class="v {html.escape(v.verdict)}">'
            f"{html.escape(v.verdict)}</span></h2>"
            f'<img alt="vignetting of {html.escape(item.name, quote=True)}" src="data:image/jpeg;base64,{fig}">'
            f"<table>{''.join(rows)}</table></section>")


def _run_rows(run: dict[str, Any]) -> list[tuple[str, str]]:
    """(name, value) of a run record (``vigproc check``'s :func:`run_record`)."""
    rows = [("analysed (UTC)", str(run.get("analysed_utc", "–"))), ("vigproc", str(run.get("vigproc", "–")))]
    if run.get("argv") is not None:
        rows.append(("command line", shlex.join(str(a) for a in run["argv"])))
    for key, label in (("settings", "settings"), ("references", "references")):
        if run.get(key) is not None:
            rows.append((label, json.dumps(run[key], ensure_ascii=False, sort_keys=True)))
    return rows


def report_html(items: Sequence[ReportItem], *, title: str = "vigproc forensic check", notes: str = "",
                run: dict[str, Any] | None = None) -> str:
    """The whole report as one self-contained HTML document; ``run``: when, which vigproc,
    the command line and settings (a table at its head; every value escaped)."""
    counts: dict[str, int] = {}
    for it in items:
        counts[it.verdict.verdict] = counts.get(it.verdict.verdict, 0) + 1
    summary = ", ".join(f"{n} {html.escape(k)}" for k, n in sorted(counts.items()))
    head = (f"<!DOCTYPE html><html lang=\"en\"><head><meta charset=\"utf-8\"><title>{html.escape(title)}</title>"
            f"<style>{_CSS}</style></head><body><h1>{html.escape(title)}</h1>"
            f"<p>{len(items)} checks: {summary}. vigproc {html.escape(str(__version__))}.</p>"
            "<p>Each frame's vignetting is estimated and compared with the lens its metadata names "
            "(a stored profile, else lensfun's calibration). The statistic D² is the squared distance, in "
            "units of the spread of frames truly taken with that lens, of the fall-off on four circles and "
            "the vignetting centre; the false-alarm probability is the share of such frames that score at "
            "least as high. Natural photographs darken outward on their own and the estimator reads part of "
            "that as vignetting: single frames separate lenses only weakly (see the README's measured "
            "figures).</p>")
    if notes:
        head += f"<p>{html.escape(notes)}</p>"
    if run:
        head += "<table>" + "".join(_row(n, v) for n, v in _run_rows(run)) + "</table>"
    return head + "".join(_html_section(it) for it in items) + "</body></html>\n"


def _run_figure(run: dict[str, Any], width: int, notes: str = "") -> np.ndarray:
    """The run record (and ``notes``) as lines of text, the head of a PNG report."""
    chars = int((width - 32) / 7.6)
    texts = [f"{n}: {v}" for n, v in _run_rows(run)] + ([notes] if notes else [])
    lines = [piece for t in texts for piece in _wrap(t.translate(_PLAIN), chars)]
    fig = np.full((30 + 19 * len(lines), width, 3), 0.1, dtype=np.float32)
    for i, line in enumerate(lines):
        _text(fig, 16, 24 + 19 * i, line, 14)
    return fig


def write_report(path: str | Path, items: Sequence[ReportItem], *, notes: str = "",
                 run: dict[str, Any] | None = None) -> Path:
    """Write a report atomically: ``.html``/``.htm`` (self-contained) or ``.png``
    (the frames' figures stacked).

    Raises
    ------
    ImageWriteError
        Unknown suffix, nothing to report, or the file cannot be written.
    """
    path = Path(path)
    suffix = path.suffix.lower()
    if not items:
        raise ImageWriteError("nothing to report")
    if suffix in (".html", ".htm"):
        data = report_html(items, notes=notes, run=run).encode("utf-8")
    elif suffix == ".png":
        figs = [report_figure(it) for it in items]
        if run or notes:
            figs.insert(0, _run_figure(run or {}, max(f.shape[1] for f in figs), notes))
        width = max(f.shape[1] for f in figs)
        figs = [np.pad(f, ((0, 4), (0, width - f.shape[1]), (0, 0)), constant_values=0.05) for f in figs]
        data = png_bytes(np.concatenate(figs, axis=0))
    else:
        raise ImageWriteError(f"report {path}: use a .html or .png file name")
    if not path.parent.is_dir():
        raise ImageWriteError(f"cannot write report {path}: no folder {path.parent}")
    atomic_write_bytes(path, data)
    return path
