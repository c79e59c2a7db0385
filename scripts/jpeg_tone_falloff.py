#!/usr/bin/env python
"""Does a camera's JPEG rendering shrink a lens's fall-off?  (issue 38, "is the truth clean?")

For each camera RAW file given, the camera's own JPEG of the same exposure (the preview the
RAW embeds, rawpy ``extract_thumb``) is compared with a linear development of the RAW
(rawpy: gamma (1, 1), no auto-brightening, 16 bits, camera white balance, sRGB primaries,
no flat-field or vignetting correction).  The JPEG is linearised as vigproc linearises any
JPEG (``vigproc.io.read_image``: the sRGB transfer).  Both are averaged in linear light onto
the same grid (the JPEG's aspect; the preview is taken to show the RAW's crop area), and
Rec. 709 luminance is compared:

1. *tone slope* s: the per-pixel mapping log2 L_jpeg against log2 L_raw, as medians in
   0.25-EV bins of L_raw; s(L) is the local slope (a line fitted over +-0.75 EV), i.e. how
   many JPEG-EV one RAW-EV becomes at that brightness.  Reported at the corners' median
   brightness (r > 0.8 of the half-diagonal), at the centre's (r < 0.2) and as one line over
   the 5-95 % range of L_raw.  *inj*: a 1-EV fall-off (2**-r**2) multiplied into the RAW and
   rendered through the measured curve: the JPEG-EV per RAW-EV it keeps at r = 0.8-1 (the
   curve's chord from each corner cell's brightness down by its fall-off), with the curve
   held at its end values beyond the measured range.
2. *radial ratio*: the same scene's radial profile in both (median log2 L by radius, 0 at
   r < 0.2) and, at r = 0.8-1.0, the JPEG's drop divided by the RAW's.
3. *vigproc's estimate*: ``vigproc.estimate`` (method ``--method``, no EXIF hint) of the
   linearised JPEG at its own size and of the linear RAW development box-averaged to that
   size; corner fall-off in EV (mean of the four corners of the field) and their ratio.

Clipped pixels (JPEG code above 250/255 in any channel, RAW above 98 % of the
development's maximum in any channel) and near-black ones (JPEG luminance code below 4/255)
are left out of 1 and 2.

Usage::

    python scripts/jpeg_tone_falloff.py RAW [RAW ...] [--grid 480] [--method default]

Prints one table row per file (and with ``--curves`` the binned mapping and profiles).
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile

import numpy as np

REC709 = np.array([0.2126, 0.7152, 0.0722])


def area_resize(img: np.ndarray, h: int, w: int) -> np.ndarray:
    """Box-average an H×W×C image onto h×w cells (fractional cell edges, integral image)."""
    H, W = img.shape[:2]
    cs = np.zeros((H + 1, W + 1) + img.shape[2:], dtype=np.float64)
    cs[1:, 1:] = np.cumsum(np.cumsum(img, axis=0, dtype=np.float64), axis=1)

    def at(ys: np.ndarray, xs: np.ndarray) -> np.ndarray:  # bilinear read of the integral image
        y0 = np.clip(np.floor(ys).astype(int), 0, H - 1)
        x0 = np.clip(np.floor(xs).astype(int), 0, W - 1)
        fy = (ys - y0)[:, None, None] if img.ndim == 3 else (ys - y0)[:, None]
        fx = (xs - x0)[None, :, None] if img.ndim == 3 else (xs - x0)[None, :]
        a = cs[y0][:, x0]
        b = cs[y0][:, x0 + 1]
        c = cs[y0 + 1][:, x0]
        d = cs[y0 + 1][:, x0 + 1]
        return (a * (1 - fy) * (1 - fx) + b * (1 - fy) * fx + c * fy * (1 - fx) + d * fy * fx)

    ye = np.linspace(0, H, h + 1)
    xe = np.linspace(0, W, w + 1)
    s = at(ye, xe)
    area = np.outer(np.diff(ye), np.diff(xe))
    if img.ndim == 3:
        area = area[..., None]
    return (s[1:, 1:] - s[:-1, 1:] - s[1:, :-1] + s[:-1, :-1]) / area


def develop(path: str):
    """The RAW's linear development (float, 0..1) and the embedded JPEG's bytes."""
    import rawpy

    with rawpy.imread(path) as raw:
        thumb = raw.extract_thumb()
        if thumb.format != rawpy.ThumbFormat.JPEG:
            raise ValueError("the embedded preview is not a JPEG")
        rgb = raw.postprocess(gamma=(1, 1), no_auto_bright=True, output_bps=16,
                              use_camera_wb=True, user_flip=0)
    return rgb.astype(np.float64) / 65535.0, bytes(thumb.data)


def read_jpeg(data: bytes):
    """The JPEG linearised as vigproc reads it, and its 8-bit codes (for the clip mask)."""
    from vigproc.io import read_image

    fd, tmp = tempfile.mkstemp(suffix=".jpg")
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(data)
        lin, _ = read_image(tmp)
        codes, _ = read_image(tmp, transfer="linear")
    finally:
        os.unlink(tmp)
    return np.asarray(lin, np.float64), np.asarray(codes, np.float64)


def radius(h: int, w: int) -> np.ndarray:
    y = (np.arange(h) + 0.5 - h / 2)[:, None]
    x = (np.arange(w) + 0.5 - w / 2)[None, :]
    return np.hypot(x, y) / np.hypot(w / 2, h / 2)


def tone_mapping(lr: np.ndarray, lj: np.ndarray, step: float = 0.25):
    """Binned medians of log2 L_jpeg against log2 L_raw: (bin centres, medians, counts)."""
    lo, hi = np.percentile(lr, [0.5, 99.5])
    edges = np.arange(np.floor(lo / step) * step, hi + step, step)
    idx = np.digitize(lr, edges) - 1
    cen, med, cnt = [], [], []
    for i in range(len(edges) - 1):
        sel = idx == i
        if sel.sum() >= 20:
            cen.append(edges[i] + step / 2)
            med.append(float(np.median(lj[sel])))
            cnt.append(int(sel.sum()))
    return np.array(cen), np.array(med), np.array(cnt)


def slope_at(cen: np.ndarray, med: np.ndarray, cnt: np.ndarray, at: float, half: float = 0.75) -> float:
    sel = np.abs(cen - at) <= half + 1e-9
    if sel.sum() < 3:
        return float("nan")
    return float(np.polyfit(cen[sel], med[sel], 1, w=np.sqrt(cnt[sel]))[0])


def best_shift(a: np.ndarray, b: np.ndarray, reach: int = 3) -> tuple[int, int, float]:
    """The whole-cell shift (dy, dx) of b against a, within +-reach, that best correlates them."""
    h, w = a.shape
    core = a[reach:h - reach, reach:w - reach]
    best = (0, 0, -2.0)
    for dy in range(-reach, reach + 1):
        for dx in range(-reach, reach + 1):
            c = np.corrcoef(core.ravel(), b[reach + dy:h - reach + dy, reach + dx:w - reach + dx].ravel())[0, 1]
            if c > best[2]:
                best = (dy, dx, float(c))
    return best


def corner_ev(model) -> float:
    phi = model.field()
    c = [phi[0, 0], phi[0, -1], phi[-1, 0], phi[-1, -1]]
    return float(-np.mean(np.log2(c)))


def measure(path: str, grid: int, method: str, curves: bool) -> dict:
    import vigproc

    raw_lin, jpeg_bytes = develop(path)
    jl, jcodes = read_jpeg(jpeg_bytes)
    jh, jw = jl.shape[:2]
    h = min(grid * jh // max(jh, jw), jh)
    w = min(grid * jw // max(jh, jw), jw)
    R = area_resize(raw_lin, h, w)
    J = area_resize(jl, h, w)
    Jc = area_resize(jcodes, h, w)  # 0..1 codes averaged: a cell with a clipped pixel sits near 1
    rmax = raw_lin.max()
    Rmax = area_resize(raw_lin.max(axis=2, keepdims=True), h, w)[..., 0]
    LR = R @ REC709
    LJ = J @ REC709
    ok = (Jc.max(axis=2) < 250 / 255) & (Rmax < 0.98 * rmax) & ((Jc @ REC709) > 4 / 255) & (LR > 0)
    r = radius(h, w)
    shift = best_shift(np.log2(np.maximum(LR, 1e-6)), np.log2(np.maximum(LJ, 1e-6)))
    lr, lj = np.log2(LR[ok]), np.log2(LJ[ok])
    cen, med, cnt = tone_mapping(lr, lj)
    corner = ok & (r > 0.8)
    centre = ok & (r < 0.2)
    L_corner = float(np.median(np.log2(LR[corner]))) if corner.any() else float("nan")
    L_centre = float(np.median(np.log2(LR[centre]))) if centre.any() else float("nan")
    p5, p95 = np.percentile(lr, [5, 95])
    mid = (lr >= p5) & (lr <= p95)
    s_all = float(np.polyfit(lr[mid], lj[mid], 1)[0])
    # a 1-EV corner fall-off (2**-r**2) added to the RAW and rendered through the global curve:
    # the JPEG-EV it becomes per RAW-EV, at r 0.8-1 (the curve's chord over each corner cell)
    rr = r[ok]
    outer = rr >= 0.8
    fall = -rr[outer] ** 2
    inj = float(np.median((np.interp(lr[outer] + fall, cen, med) - np.interp(lr[outer], cen, med)) / fall))
    # the global curve's prediction of each cell, and what is left: a spatial (local) rendering
    res = np.full(LR.shape, np.nan)
    res[ok] = lj - np.interp(lr, cen, med)
    prof = []
    for a, b in [(0.2, 0.4), (0.4, 0.6), (0.6, 0.8), (0.8, 1.01)]:
        sel = ok & (r >= a) & (r < b)
        dr = float(np.median(np.log2(LR[sel])) - np.median(np.log2(LR[centre]))) if sel.any() else np.nan
        dj = float(np.median(np.log2(LJ[sel])) - np.median(np.log2(LJ[centre]))) if sel.any() else np.nan
        dres = float(np.median(res[sel]) - np.median(res[centre])) if sel.any() else np.nan
        prof.append((a, b, dr, dj, dres))
    # the estimate on the JPEG as read, and on the RAW development box-averaged to the JPEG's size
    m_j = vigproc.estimate(jl.astype(np.float32), method)
    m_r = vigproc.estimate(area_resize(raw_lin, jh, jw).astype(np.float32), method)
    ev_j, ev_r = corner_ev(m_j), corner_ev(m_r)
    out = dict(file=os.path.basename(path), jpeg=f"{jw}x{jh}", raw=f"{raw_lin.shape[1]}x{raw_lin.shape[0]}",
               grid=f"{w}x{h}", shift=shift, used=float(ok.mean()), L_corner=L_corner - L_centre,
               s_corner=slope_at(cen, med, cnt, L_corner), s_centre=slope_at(cen, med, cnt, L_centre),
               s_all=s_all, inj=inj, prof=prof, est_jpeg=ev_j, est_raw=ev_r,
               est_ratio=ev_j / ev_r if abs(ev_r) > 0.02 else float("nan"))
    if curves:
        print(f"# {out['file']}: log2 L_raw bin, median log2 L_jpeg, count, local slope")
        for c, m, n in zip(cen, med, cnt):
            print(f"  {c:7.2f} {m:8.3f} {n:6d} {slope_at(cen, med, cnt, c):6.2f}")
        print("# radial profile: r range, RAW and JPEG log2 L minus the centre's (EV), ratio, JPEG minus the global curve's prediction (EV)")
        for a, b, dr, dj, dres in prof:
            print(f"  {a:.1f}-{min(b, 1.0):.1f} {dr:7.3f} {dj:7.3f} {dj / dr if abs(dr) > 0.02 else float('nan'):6.2f}"
                  f" {dres:7.3f}")
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("raws", nargs="+", help="camera RAW files with an embedded camera JPEG")
    ap.add_argument("--grid", type=int, default=480, help="long side of the common grid (px)")
    ap.add_argument("--method", default="default", help="vigproc.estimate method")
    ap.add_argument("--curves", action="store_true", help="also print the binned mapping and profiles")
    a = ap.parse_args(argv)
    rows = []
    for p in a.raws:
        try:
            rows.append(measure(p, a.grid, a.method, a.curves))
        except Exception as e:  # one bad file does not stop the table
            print(f"{p}: skipped ({type(e).__name__}: {e})", file=sys.stderr)
    print("# Lcorn: corners' log2 L_raw - centre's (EV); s_*: JPEG-EV per RAW-EV at the corners' /\n"
          "# centre's brightness / one line over 5-95 %; inj: a 1-EV corner fall-off added to the RAW,\n"
          "# rendered through the global curve, per RAW-EV (r 0.8-1); edge: log2 L(r 0.8-1) - log2 L(r < 0.2), EV;\n"
          "# local: the JPEG's edge minus what the global curve predicts from the RAW (a local operator), EV;\n"
          "# est: vigproc.estimate corner fall-off, EV; shift: best whole-cell offset of JPEG vs RAW, corr.")
    print("file                      jpeg      grid     shift      used  Lcorn  s_corn s_cent s_all  inj  "
          "| edge RAW edge JPEG ratio  local | est RAW est JPEG ratio")
    for o in rows:
        _, _, dr, dj, dres = o["prof"][-1]
        ratio = dj / dr if abs(dr) > 0.02 else float("nan")
        dy, dx, c = o["shift"]
        print(f"{o['file'][:25]:25s} {o['jpeg']:9s} {o['grid']:8s} {dy:+d},{dx:+d} {c:.3f} {o['used']:4.2f} {o['L_corner']:6.2f} "
              f"{o['s_corner']:6.2f} {o['s_centre']:6.2f} {o['s_all']:5.2f} {o['inj']:5.2f} | {dr:8.3f} {dj:9.3f} {ratio:5.2f} {dres:6.3f}"
              f" | {o['est_raw']:7.3f} {o['est_jpeg']:8.3f} {o['est_ratio']:5.2f}")
    return 0 if rows else 1


if __name__ == "__main__":
    sys.exit(main())
