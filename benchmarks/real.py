"""Photographs vignetted by someone else: pairs with a known field, and real lenses.

Two kinds of input, found in one folder tree (``../shared/data/vignetted`` is such a
tree; see its README):

* **Pairs** ``NAME_vig.EXT`` with the photograph before vignetting, ``NAME.EXT`` (any
  extension; ``NAME`` without trailing digits when ``NAME`` itself is missing, so
  ``sea2_vig.png`` pairs with ``sea.jpg`` and ``white3_vig.png`` with ``white.jpg``).
  The true field is the ratio of the two frames in linear light, block-averaged on the
  estimator's scale (:data:`BLOCK` px blocks, blocks darker than 2 % of the clean
  frame's median left out).  The error is the RMS over the blocks of log2(φ̂/φ)
  about its mean (gain-free: a correction is defined up to one exposure gain), in EV,
  next to the same figure for no correction.
* **Photographs** with real lens vignetting and no ground truth (every other image).
  Reported: whether the estimator corrects the photograph at all (sensitivity, beside
  the false corrections of ``vigproc bench lensfun``'s "do no harm" rows), the
  fall-off it applies at the corners, and a crude reference: the mean log2
  luminance of the four corner blocks (10 % of each side) minus that of the central
  third, which a lens's fall-off and the scene's own shading both make negative.

The estimator runs on the luminance of each whole frame (no resizing), as the
commands do.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Iterable

import numpy as np

from vigproc.core.model import VignettingModel

#: Side of the blocks on which the true and estimated fields are compared (px).
BLOCK = 8
_VIG = re.compile(r"^(?P<name>.+)_vig$", re.IGNORECASE)
_LN2 = math.log(2.0)


@dataclass(frozen=True)
class PairResult:
    name: str
    method: str
    error_ev: float  # gain-free RMS of log2(estimated / true), over the blocks
    uncorrected_ev: float  # the same for no correction
    true_corner_ev: float  # the true field at the corner blocks (mean log2, about the mean)
    fallback: bool


@dataclass(frozen=True)
class PhotoResult:
    name: str
    method: str
    corrected: bool
    corner_ev: float  # applied fall-off at the frame corners, log2 (≤ 0 for a darkening)
    crude_corner_ev: float  # log2 mean luminance of the corner blocks minus the central third


def find_inputs(folder: Path, suffixes: Iterable[str]) -> tuple[list[tuple[Path, Path]], list[Path]]:
    """(pairs (vignetted, clean), photographs) in the tree below ``folder``.

    Frames that are the clean half of a pair, and ground-truth field images
    (``*_Est_truth*``), are neither.
    """
    sfx = {s.lower() for s in suffixes}
    files = sorted(p for p in Path(folder).rglob("*") if p.is_file() and p.suffix.lower() in sfx)
    by_stem: dict[tuple[Path, str], Path] = {}
    for p in files:
        by_stem.setdefault((p.parent, p.stem.lower()), p)
    pairs, clean = [], set()
    for p in files:
        m = _VIG.match(p.stem)
        if not m:
            continue
        name = m.group("name").lower()
        c = by_stem.get((p.parent, name)) or by_stem.get((p.parent, name.rstrip("0123456789")))
        if c is not None:
            pairs.append((p, c))
            clean.add(c)
    paired = {v for v, _ in pairs}
    photos = [p for p in files if p not in paired and p not in clean and not _VIG.match(p.stem)
              and "_est_truth" not in p.stem.lower()]
    return pairs, photos


def _blocks(lum: np.ndarray) -> np.ndarray:
    h, w = (lum.shape[0] // BLOCK) * BLOCK, (lum.shape[1] // BLOCK) * BLOCK
    return lum[:h, :w].reshape(h // BLOCK, BLOCK, w // BLOCK, BLOCK).mean(axis=(1, 3))


def _corner_mask(shape: tuple[int, int], frac: float) -> np.ndarray:
    h, w = shape
    ch, cw = max(1, int(round(frac * h))), max(1, int(round(frac * w)))
    m = np.zeros(shape, dtype=bool)
    for ys in (slice(0, ch), slice(h - ch, h)):
        for xs in (slice(0, cw), slice(w - cw, w)):
            m[ys, xs] = True
    return m


def run_pair(vig: np.ndarray, clean: np.ndarray, name: str, method: str,
             estimate: Callable[[np.ndarray], VignettingModel]) -> PairResult:
    """One pair (linear luminance frames of one size)."""
    if vig.shape != clean.shape:
        raise ValueError(f"{name}: the vignetted and clean frames differ in size ({vig.shape} and {clean.shape})")
    m = estimate(vig)
    bv, bc = _blocks(vig), _blocks(clean)
    ok = (bc > 0.02 * np.median(bc)) & (bv > 0)
    true = np.log2(np.where(ok, bv, 1.0) / np.where(ok, bc, 1.0))
    est = _blocks(m.field(vig.shape))
    d = np.log2(np.maximum(est, 1e-12))[ok] - true[ok]
    t = true[ok] - true[ok].mean()
    corners = _corner_mask(true.shape, 0.1) & ok
    return PairResult(
        name=name, method=method, error_ev=float(np.sqrt(np.mean((d - d.mean()) ** 2))),
        uncorrected_ev=float(np.sqrt(np.mean(t * t))),
        true_corner_ev=float(true[corners].mean() - true[ok].mean()),
        fallback=bool(m.quality is not None and m.quality.fallback))


def run_photo(lum: np.ndarray, name: str, method: str,
              estimate: Callable[[np.ndarray], VignettingModel]) -> PhotoResult:
    """One photograph without ground truth (linear luminance)."""
    m = estimate(lum)
    h, w = lum.shape
    hx, hy = (w - 1) / 2, (h - 1) / 2  # the corner pixels' centres
    corners = m.log_field_at(np.array([-hx, hx, -hx, hx]), np.array([-hy, -hy, hy, hy])) / _LN2
    centre = np.zeros((h, w), dtype=bool)
    centre[h // 3: h - h // 3, w // 3: w - w // 3] = True
    cm = _corner_mask((h, w), 0.1)
    pos = lum > 0
    crude = math.log2(max(float(lum[cm & pos].mean()), 1e-12)) - math.log2(max(float(lum[centre & pos].mean()), 1e-12))
    return PhotoResult(name=name, method=method,
                       corrected=not (m.quality is not None and m.quality.fallback) and not m.is_identity,
                       corner_ev=float(np.mean(corners)), crude_corner_ev=crude)
