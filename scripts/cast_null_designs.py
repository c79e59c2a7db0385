"""Single-frame colour-cast designs with a scene null from the frame itself (issue 41;
docs/benchmarks/colour.md, "Cast detection from one photograph").

The detector (:func:`vigproc.core.colour_cast.detect_colour_cast`) fits the radial
derivative of log-chroma, A·d(r²), to neighbouring-pixel differences with a Cauchy loss,
per quadrant. Its z scores take every difference as independent. This script measures,
on the same frames as ``vigproc bench colour-detect --targets 5 --theta-max 40``, designs
whose σ comes from spatial blocks of the frame (a cluster-robust, i.e. linearised block
jackknife, standard error: the scene's coherent colour regions count as one sample each),
so that a threshold could be read as a false-alarm rate if the scene behaved as noise:

- ``detector``: the detector's own ``score`` (reference);
- ``block z (b px)``: the weakest quadrant's shift along the common direction over its
  block standard error (blocks of b×b px of the 240-px working copy);
- ``min(dE/2.5, block z/2)``: the detector's rule with the block z;
- ``block median``: per quadrant, the D-weighted median of the blocks' own slopes (what
  most blocks say), weakest quadrant's ΔE00;
- ``global z / √het``: one radial fit over the frame, its 2-D z with the block σ, divided
  by the root of the quadrants' heterogeneity (χ²/8 about the global fit, at least 1);
- ``quadrant-mean t``: the quadrants' mean shift over the between-quadrant spread.

Each design's threshold is set as the bench sets one: in sample (at most 2 of the 47
clean bases called), and split by base parity (≤ 5 % of one half's clean bases, rates on
the other half). It also prints the *scene ceiling*: how many clean bases have every
quadrant's own shift within a given ΔE00 (a ΔE00 5 cast adds about 5 to every quadrant,
so only those can be told from no cast at a few per cent false), the null's block-z
spread, and the ΔE00 of the rendered ΔE00 5 cast on 16×16 px grey corner patches.

Run (about 6 minutes of CPU): ``python scripts/cast_null_designs.py``
"""

from __future__ import annotations

import argparse
import math

import numpy as np

from benchmarks import clean as C
from benchmarks.colour_detect import cast_for, half_rate, half_threshold, threshold_at_false_rate
from vigproc.core.colour_cast import CastSettings, _cauchy_fit, _working_copy, detect_colour_cast
from vigproc.core.colour_difference import MID_GREY, grey_cast_de

BLOCKS = (12, 30)


def _samples(a: np.ndarray, s: CastSettings) -> dict:
    """The detector's differences (step, masks and flat-luminance half as in
    ``detect_colour_cast``) with their quadrant and working-copy position."""
    wc = _working_copy(a, s.work_long_side)
    h, w = wc.shape[:2]
    top, peak = float(np.percentile(wc.max(axis=2), 99.0)), float(wc.max())
    ok = (wc.min(axis=2) > s.dark_fraction * top) & (wc.max(axis=2) < s.clip_fraction * peak)
    lg = np.log(np.maximum(wc, 1e-12))
    u, v = lg[..., 0] - lg[..., 1], lg[..., 2] - lg[..., 1]
    lum = np.log(np.maximum(wc @ np.array([0.2126, 0.7152, 0.0722]), 1e-12))
    hd = 0.5 * math.hypot(w, h)
    X, Y = np.meshgrid((np.arange(w) - (w - 1) / 2) / hd, (np.arange(h) - (h - 1) / 2) / hd)
    PX, PY = np.meshgrid(np.arange(w), np.arange(h))
    r2 = X * X + Y * Y
    fields = {"du": u, "dv": v, "x": r2, "dl": lum, "q4": r2 * r2}
    out: dict[str, list] = {k: [] for k in (*fields, "quad", "px", "py")}
    for st in s.steps:
        for axis in (1, 0):
            a0 = (slice(None), slice(0, w - st)) if axis == 1 else (slice(0, h - st), slice(None))
            a1 = (slice(None), slice(st, w)) if axis == 1 else (slice(st, h), slice(None))
            m = ok[a0] & ok[a1]
            for k, f in fields.items():
                out[k].append((f[a1] - f[a0])[m])
            mx, my = 0.5 * (X[a0] + X[a1]), 0.5 * (Y[a0] + Y[a1])
            out["quad"].append(((mx >= 0).astype(int) + 2 * (my >= 0))[m])
            out["px"].append((0.5 * (PX[a0] + PX[a1]))[m])
            out["py"].append((0.5 * (PY[a0] + PY[a1]))[m])
    o = {k: np.concatenate(v) for k, v in out.items()}
    mad = max(1.4826 * float(np.median(np.abs(o["dl"] - np.median(o["dl"])))), 1e-4)
    b, _ = _cauchy_fit(np.stack([o["x"], o["q4"]], 1), o["dl"], mad, s.cauchy_c, s.iterations)
    dl = np.abs(o["dl"] - b[0] * o["x"] - b[1] * o["q4"])
    keep = dl <= np.quantile(dl, s.flat_quantile)
    return {k: v[keep] for k, v in o.items()}


def block_sums(a: np.ndarray, s: CastSettings = CastSettings()) -> dict:
    """Per channel and block size: each (block, quadrant) cell's quadrant, Σw·x·y and Σw·x²
    with the Cauchy weights of the detector's per-quadrant fits at convergence."""
    o = _samples(a, s)
    res = {}
    for ch, d in enumerate((o["du"], o["dv"])):
        scale = max(1.4826 * float(np.median(np.abs(d - np.median(d)))), 1e-4)
        wt = np.zeros_like(d)
        for qd in range(4):
            sel = o["quad"] == qd
            x, y, sl = o["x"][sel], d[sel], 0.0
            for _ in range(s.iterations + 1):
                wq = 1.0 / (1.0 + (y - sl * x) ** 2 / (s.cauchy_c * scale) ** 2)
                sl = float(np.dot(wq, x * y)) / float(np.dot(wq, x * x))
            wt[sel] = wq
        for bpx in BLOCKS:
            key = ((o["py"] // bpx).astype(int) * 1000 + (o["px"] // bpx).astype(int)) * 4 + o["quad"]
            uk, inv = np.unique(key, return_inverse=True)
            res[(ch, bpx)] = (uk % 4, np.bincount(inv, wt * o["x"] * d), np.bincount(inv, wt * o["x"] ** 2))
    return res


def _quads(bs: dict, bpx: int):
    est, se, glob, gse = np.zeros((4, 2)), np.zeros((4, 2)), np.zeros(2), np.zeros(2)
    for ch in range(2):
        q, n, d = bs[(ch, bpx)]
        for qd in range(4):
            k = q == qd
            est[qd, ch] = n[k].sum() / d[k].sum()
            se[qd, ch] = math.sqrt(((n[k] - est[qd, ch] * d[k]) ** 2).sum()) / d[k].sum()
        glob[ch] = n.sum() / d.sum()
        gse[ch] = math.sqrt(((n - glob[ch] * d) ** 2).sum()) / d.sum()
    return est, se, glob, gse


def _along(est: np.ndarray, se: np.ndarray):
    """Per quadrant: ΔE00 and z of the shift along the common direction."""
    w = 1.0 / np.maximum(se, 1e-12) ** 2
    shift = (w * est).sum(0) / w.sum(0)
    e = shift / max(float(np.hypot(*shift)), 1e-12)
    p, pse = est @ e, np.sqrt((se ** 2) @ (e ** 2))
    return np.sign(p) * grey_cast_de(np.abs(p) * e[0], np.abs(p) * e[1]), p / np.maximum(pse, 1e-12)


def _wmedian(v: np.ndarray, w: np.ndarray) -> float:
    o = np.argsort(v)
    c = np.cumsum(w[o])
    return float(v[o][np.searchsorted(c, 0.5 * c[-1])])


def designs(bs: dict) -> dict[str, float]:
    """Every design's statistic for one frame's block sums (higher: more cast-like)."""
    out = {}
    for bpx in BLOCKS:
        est, se, glob, gse = _quads(bs, bpx)
        de, z = _along(est, se)
        out[f"block z ({bpx} px)"] = float(z.min())
        out[f"min(dE/2.5, block z/2) ({bpx} px)"] = float(min(de.min() / 2.5, z.min() / 2))
        med = np.zeros((4, 2))
        for ch in range(2):
            q, n, d = bs[(ch, bpx)]
            for qd in range(4):
                k = (q == qd) & (d > 0)
                med[qd, ch] = _wmedian(n[k] / d[k], d[k])
        out[f"block median dE ({bpx} px)"] = float(_along(med, se)[0].min())
        het = float((((est - glob) / se) ** 2).sum())
        out[f"global z / sqrt(het) ({bpx} px)"] = math.hypot(*(glob / gse)) / math.sqrt(max(het / 8, 1.0))
        tau2 = np.maximum(est.var(0, ddof=1) - (se ** 2).mean(0), 0)
        out[f"quadrant-mean t ({bpx} px)"] = float(np.hypot(*(est.mean(0) / np.sqrt((se ** 2).mean(0) / 4 + tau2 / 4))))
    return out


def _rates(name: str, clean, lum, cast, ci, li, ki) -> str:
    cl = np.asarray(clean)
    thr = threshold_at_false_rate(cl)
    line = (f"| {name} | {thr:.3g} | {int((cl >= thr).sum())}/{cl.size} | {int((lum >= thr).sum())}/{lum.size} | "
            f"{int((cast >= thr).sum())}/{cast.size} = {np.mean(cast >= thr):.1%} |")
    for cal in (0, 1):
        t = half_threshold(cl, ci, cal)
        ev = 1 - cal
        line += (f" {t:.3g}: {half_rate(cl, ci, ev, t):.1%} / {half_rate(lum, li, ev, t):.1%} / "
                 f"{half_rate(cast, ki, ev, t):.1%} |")
    return line


def patch_de(target: float = 5.0, theta_max: float = 40.0, hues: int = 8, size: int = 16) -> list[float]:
    """ΔE00 (equal luminance) of the worst 16×16 px corner patch against the centre's, a
    mid grey under each hue's cast of corner ΔE00 ``target`` on a 480×320 frame."""
    h, w = 320, 480
    out = []
    for j in range(hues):
        img = MID_GREY * np.exp(cast_for(target, 360.0 * j / hues, theta_max).log_transmission((h, w)))
        c = img[h // 2 - size // 2:h // 2 + size // 2, w // 2 - size // 2:w // 2 + size // 2].reshape(-1, 3).mean(0)
        worst = 0.0
        for rs in (slice(0, size), slice(h - size, h)):
            for cs in (slice(0, size), slice(w - size, w)):
                p = img[rs, cs].reshape(-1, 3).mean(0)
                worst = max(worst, float(grey_cast_de(math.log(p[0] / p[1] * c[1] / c[0]),
                                                      math.log(p[2] / p[1] * c[1] / c[2]))))
        out.append(worst)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--images", nargs="+", default=["../shared/data/jpeg_exif", "../shared/data/natural"])
    ap.add_argument("--lenses", type=int, default=5)
    ap.add_argument("--limit", type=int, default=None, help="first N frames only (a smoke test)")
    args = ap.parse_args()
    bases, _ = C.load_clean_bases(args.images, limit=args.limit, colour=True)
    bases = [b for b in bases if np.ptp(b[..., 0] - b[..., 1]) > 1e-6 or np.ptp(b[..., 2] - b[..., 1]) > 1e-6]
    fields = [f.log_field for f in C.lens_fields(args.lenses)[0]] if args.lenses else []
    casts = [np.exp(cast_for(5.0, 45.0 * j, 40.0).log_transmission(bases[0].shape[:2])) for j in range(8)]
    rows: dict[str, dict[str, list]] = {"clean": {}, "lum": {}, "cast": {}}
    idx: dict[str, list[int]] = {"clean": [], "lum": [], "cast": []}
    ceiling = []
    frames = ([("clean", i, b) for i, b in enumerate(bases)]
              + [("lum", i, b * np.exp(f)[..., None]) for f in fields for i, b in enumerate(bases)]
              + [("cast", i, b * t) for t in casts for i, b in enumerate(bases)])
    for kind, i, frame in frames:
        ev = detect_colour_cast(frame)
        bs = block_sums(frame)
        stats = {"detector score": ev.score if math.isfinite(ev.score) else -math.inf, **designs(bs)}
        for k, v in stats.items():
            rows[kind].setdefault(k, []).append(v)
        idx[kind].append(i)
        if kind == "clean":
            est = _quads(bs, BLOCKS[0])[0]
            ceiling.append(max(float(grey_cast_de(*e)) for e in est))
    ci, li, ki = (np.asarray(idx[k]) for k in ("clean", "lum", "cast"))
    print(f"{len(bases)} colour bases, {len(fields)} luminance-only fields, ΔE00 5 casts at 8 hues, 40°")
    print("| design | threshold (in sample) | clean | luminance only | ΔE00 5 | even→odd: clean / lum. / ΔE00 5 "
          "| odd→even: clean / lum. / ΔE00 5 |")
    print("|---|---|---|---|---|---|---|")
    for name in rows["clean"]:
        print(_rates(name, np.asarray(rows["clean"][name]), np.asarray(rows["lum"].get(name, [])),
                     np.asarray(rows["cast"][name]), ci, li, ki))
    ceiling = np.asarray(ceiling)
    print("scene ceiling (clean bases whose every quadrant shift is within ΔE00 t): "
          + ", ".join(f"t {t:g}: {int((ceiling <= t).sum())}/{ceiling.size}" for t in (2.5, 5, 10)))
    rng = np.random.default_rng(0)
    noise = [designs(block_sums(MID_GREY * np.exp(rng.normal(0, 0.02, bases[0].shape))))[f"block z ({BLOCKS[0]} px)"]
             for _ in range(20)]
    z = np.asarray(rows["clean"][f"block z ({BLOCKS[0]} px)"])
    print(f"null: weakest-quadrant block z ({BLOCKS[0]} px), median / 95th percentile: clean bases "
          f"{np.median(z):.2f} / {np.percentile(z, 95):.2f}; 20 grey frames with 2 % noise "
          f"{np.median(noise):.2f} / {np.percentile(noise, 95):.2f}")
    p = patch_de()
    print(f"ΔE00 5 cast (40°) on 16x16 px grey corner patches: {min(p):.2f}-{max(p):.2f}")


if __name__ == "__main__":
    main()
