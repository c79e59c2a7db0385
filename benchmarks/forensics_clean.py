"""Lens mismatch and lens identification on the clean protocol (``vigproc bench forensics-clean``).

Bases: the vignetting-free camera crops of :mod:`benchmarks.clean` (480×320, linear).
Frames: a base × the lensfun ``pa`` field of a lens A. The test is the one ``vigproc
check`` runs (:mod:`vigproc.forensics.lensmatch`): the frame's data-only lens-family fit against
the claimed lens's coefficients, by a Mahalanobis distance whose null is calibrated on
vignetting-free frames.

* **No circular evidence.** The bases are split into ``folds`` (2: even/odd): the
  calibration (μ, Σ and the null) is made on the other folds' bases (× a lensfun field
  of a *calibration* lens, or none) and the frames of one fold are tested, each fold in
  turn. With 2 folds a calibration holds half the bases; with more, nearly all of them,
  as the shipped one does. A claimed lens's
  reference is its lensfun calibration projected into the family, never frames.
* **No test lens in the family.** The family the fits are made in is built without the
  test lenses (mismatch and identification) and without the calibration lenses' being
  needed (they are ordinary lensfun lenses, not tested).
* **Lens mismatch**: genuine = base × A claiming A; forged = the same frames claiming
  another test lens B. AUC of D², by the RMS (about the mean, EV) difference of A's and
  B's fields; from one frame and from ``frames`` frames of distinct bases tested together
  (coordinate-wise median, :func:`vigproc.forensics.lensmatch.pooled_d2`).
* **Undecided single frames**: a frame whose fit no lens explains
  (:func:`vigproc.forensics.lensmatch.scene_d2` above the calibration's ``scene_limit``)
  is left undecided, as ``vigproc check`` leaves it; the AUC is over the decided frames,
  with the undecided shares and the AUC of every frame by its D² beside it.
* **False alarms** at ``alpha``: the share of genuine frames (and groups) called
  inconsistent (an undecided frame is no alarm).
* **Lens identification** among ``id_lenses`` lensfun lenses whose fields differ
  pairwise by at least ``min_separation`` EV: the claim with the smallest statistic.
"""

from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass, field
from typing import Callable, Sequence

import numpy as np

from benchmarks.clean import HEIGHT, WIDTH

log = logging.getLogger(__name__)

#: Buckets of the RMS field difference of the true and the claimed lens (EV).
SEPARATION_BUCKETS = (0.0, 0.15, 0.3, math.inf)
_LN2 = math.log(2.0)


@dataclass(frozen=True)
class BenchLens:
    """A lensfun lens at its benchmark calibration (shortest focal, widest aperture)."""

    maker: str
    model: str
    k: tuple[float, float, float]

    @property
    def name(self) -> str:
        return f"{self.maker} {self.model}"

    def log_field(self) -> np.ndarray:
        from vigproc.stores.lensfun import pa_field

        return np.log(pa_field((HEIGHT, WIDTH), *self.k))

    def kw_model(self):
        """The Kang-Weiss model ``vigproc check`` compares with (lensfun_io.kw_from_pa)."""
        from vigproc.stores.lensfun_io import kw_from_pa

        return kw_from_pa(*self.k, WIDTH, HEIGHT)


def field_difference(a: BenchLens, b: BenchLens) -> float:
    """RMS over the frame of log2(φ_A/φ_B) about its mean, EV."""
    return float(np.std(a.log_field() - b.log_field()) / _LN2)


def _bench(n: int) -> list[BenchLens]:
    from vigproc.stores.lensfun import diverse_lenses

    return [BenchLens(lens.maker, lens.model, (pa.k1, pa.k2, pa.k3)) for lens, pa in diverse_lenses(n)]


def select_lenses(n_test: int = 20, n_id: int = 8, min_separation: float = 0.15,
                  n_calibration: int = 20) -> tuple[list[BenchLens], list[BenchLens], list[BenchLens]]:
    """The mismatch lenses (the first ``n_test`` of :func:`vigproc.stores.lensfun.diverse_lenses`, as
    ``bench clean``), the identification lenses (greedy in the same order: each lens's
    field differs from every one already taken by at least ``min_separation`` EV) and
    the calibration lenses (the next ``n_calibration`` lenses in that order that are in
    neither set).

    Raises
    ------
    ValueError
        Fewer than ``n_id`` lenses are that far apart.
    """
    pool = _bench(200)
    test = pool[:n_test]
    ident: list[BenchLens] = []
    fields: list[np.ndarray] = []
    for lens in pool:
        f = lens.log_field()
        if all(np.std(f - g) / _LN2 >= min_separation for g in fields):
            ident.append(lens)
            fields.append(f)
        if len(ident) == n_id:
            break
    if len(ident) < n_id:
        raise ValueError(f"only {len(ident)} lensfun lenses differ pairwise by {min_separation} EV")
    used = {(lens.maker, lens.model) for lens in test + ident}
    calib = [lens for lens in pool if (lens.maker, lens.model) not in used][:n_calibration]
    return test, ident, calib


@dataclass
class MismatchRow:
    frames: int
    bucket: str
    n_genuine: int
    n_forged: int
    auc: float  # over the frames the test decides (one frame: those within the scene limit)
    detection: float  # share of all forged claims called inconsistent at alpha
    undecided_genuine: float = 0.0  # share left undecided: no lens explains the frame's fit
    undecided_forged: float = 0.0
    auc_ungated: float = math.nan  # every frame by its D², none left undecided


@dataclass
class CleanForensics:
    n_bases: int
    test_lenses: list[str]
    id_lenses: list[str]
    calibration_lenses: list[str]
    alpha: float
    frames: int
    mismatch: list[MismatchRow] = field(default_factory=list)
    false_alarm: dict[str, float] = field(default_factory=dict)  # "1" / "5" frames -> share of genuine
    n_genuine: dict[str, int] = field(default_factory=dict)
    identification: dict[str, float] = field(default_factory=dict)  # "1" / "5" frames -> accuracy
    n_identification: dict[str, int] = field(default_factory=dict)
    id_min_separation_ev: float = 0.0
    ms_per_frame: float = 0.0


def frame_coefficients_table(bases: Sequence[np.ndarray], lenses: Sequence[BenchLens | None], family,
                             progress: Callable[[str], None] | None = None) -> tuple[np.ndarray, list[float]]:
    """Data-only family coefficients of every base (H×W, or H×W×3) × lens field (None: no field), shape
    (lenses, bases, K), NaN where a frame has too few usable pixels; and the seconds per fit."""
    from vigproc.io.protocol import vignetted
    from vigproc.core.family_fit import colour_of
    from vigproc.core.pixels import luminance
    from vigproc.forensics.lensmatch import luminance_family_fit

    out = np.full((len(lenses), len(bases), family.n_components), np.nan)
    secs = []
    for i, lens in enumerate(lenses):
        for j, im in enumerate(bases):
            t0 = time.perf_counter()
            frame = vignetted(im, lens.log_field()) if lens is not None else im
            r = luminance_family_fit(luminance(frame), family, colour=colour_of(frame))
            secs.append(time.perf_counter() - t0)
            if r is not None:
                out[i, j] = r.coefficients
        if progress:
            progress(f"  fitted {lens.name if lens else 'no field'} ({i + 1}/{len(lenses)})")
    return out, secs


def references(lenses: Sequence[BenchLens | None], family) -> np.ndarray:
    """Each lens's lensfun model projected into the family (no field: the identity)."""
    from vigproc.forensics.lensmatch import reference_coefficients
    from vigproc.core.model import VignettingModel

    return np.array([reference_coefficients(lens.kw_model() if lens else VignettingModel.identity(WIDTH, HEIGHT),
                                            WIDTH, HEIGHT, family) for lens in lenses])


def calibrate(coef: np.ndarray, refs: np.ndarray, bases: np.ndarray, family, *, alpha: float, source: str = ""):
    """A :class:`~vigproc.forensics.lensmatch.MatchCalibration` from the rows ``coef[:, bases]``
    (calibration fields × the chosen bases) against their references."""
    from vigproc.forensics.lensmatch import fit_match_calibration

    own = coef[:, bases].reshape(-1, coef.shape[2])
    res = (coef[:, bases] - refs[:, None, :]).reshape(-1, coef.shape[2])
    groups = np.tile(np.asarray(bases), coef.shape[0])
    ok = np.all(np.isfinite(res), axis=1)
    return fit_match_calibration(res[ok], groups[ok], family, alpha=alpha, source=source, coefficients=own[ok])


def _groups(rng: np.random.Generator, idx: np.ndarray, n: int, draws: int) -> list[np.ndarray]:
    out = []
    for _ in range(draws):
        p = rng.permutation(idx)
        out += [p[k:k + n] for k in range(0, len(p) - n + 1, n)]
    return out


def run(bases: Sequence[np.ndarray], *, alpha: float = 0.01, frames: int = 5, seed: int = 0, draws: int = 4, folds: int = 2,
        n_test: int = 20, n_id: int = 8, min_separation: float = 0.15,
        progress: Callable[[str], None] | None = None) -> CleanForensics:
    """The benchmark (module docstring)."""
    if not 2 <= folds <= len(bases) // frames:
        raise ValueError(f"folds must be within 2..{len(bases) // frames} (a fold holds at least {frames} bases)")
    from vigproc.forensics.crops import auc
    from vigproc.stores.lensfun import lensfun_family
    from vigproc.forensics.lensmatch import beyond_scene_limit, pooled_d2, scene_d2, whiten

    test, ident, calib = select_lenses(n_test, n_id, min_separation)
    family = lensfun_family(exclude={(lens.maker, lens.model) for lens in test + ident})
    named = {lens.name: lens for lens in test + ident}
    tested = list(named.values())
    if progress:
        progress(f"{len(bases)} bases; {len(tested)} tested lenses, {len(calib)} calibration lenses; family of "
                 f"{family.lenses} other lenses")
    c_test, secs = frame_coefficients_table(bases, tested, family, progress)
    cal_fields: list[BenchLens | None] = [None, *calib]
    c_cal, _ = frame_coefficients_table(bases, cal_fields, family, progress)
    r_test, r_cal = references(tested, family), references(cal_fields, family)
    idx = {lens.name: i for i, lens in enumerate(tested)}
    ti = [idx[lens.name] for lens in test]
    ii = [idx[lens.name] for lens in ident]
    diff = {(a, b): field_difference(tested[a], tested[b]) for a in ti for b in ti}
    seps = [field_difference(tested[a], tested[b]) for a in ii for b in ii if a < b]
    nb = len(bases)
    parts = [np.arange(k, nb, folds) for k in range(folds)]
    rng = np.random.default_rng(seed)
    # stat[frames][(a, b)] -> list of statistics; pv: their p-values
    stat: dict[int, dict[tuple[int, int], list[float]]] = {1: {}, frames: {}}
    pv: dict[int, dict[tuple[int, int], list[float]]] = {1: {}, frames: {}}
    # a single frame whose fit no lens explains is undecided (lensmatch.scene_d2); sets
    # of frames are pooled by their median, which one such frame moves by one rank
    decided: dict[int, dict[tuple[int, int], list[bool]]] = {1: {}, frames: {}}
    id_hits = {1: [], frames: []}
    for h in range(folds):
        held = parts[(h + 1) % folds]  # 2 folds: the odd bases first, as the halves ran
        cal = calibrate(c_cal, r_cal, np.setdiff1d(np.arange(nb), held), family, alpha=alpha)
        for a in sorted(set(ti + ii)):
            ok = held[np.all(np.isfinite(c_test[a, held]), axis=1)]
            claims = sorted(set(ti + ii))
            z = {b: np.array([whiten(c_test[a, j] - r_test[b], cal) for j in ok]) for b in claims}
            inside = [not beyond_scene_limit(scene_d2(c_test[a, j], cal, family), cal.scene_limit) for j in ok]
            pos = {j: k for k, j in enumerate(ok)}
            single = {b: np.einsum("ij,ij->i", z[b], z[b]) for b in claims}
            groups = [np.array([pos[j] for j in g]) for g in _groups(rng, ok, frames, draws)]
            pooled = {b: np.array([pooled_d2(z[b][g]) for g in groups]) for b in claims}
            for n, s in ((1, single), (frames, pooled)):
                if a in ti:
                    for b in ti:
                        stat[n].setdefault((a, b), []).extend(s[b])
                        pv[n].setdefault((a, b), []).extend(cal.p_value(v, n) for v in s[b])
                        decided[n].setdefault((a, b), []).extend(inside if n == 1 else [True] * len(s[b]))
                if a in ii:
                    m = np.array([s[b] for b in ii])  # claims × frames
                    id_hits[n].extend(np.asarray(ii)[np.argmin(m, axis=0)] == a)
    res = CleanForensics(nb, [lens.name for lens in test], [lens.name for lens in ident],
                         [lens.name for lens in calib], alpha, frames,
                         id_min_separation_ev=float(min(seps)), ms_per_frame=1000 * float(np.median(secs)))
    for n in (1, frames):
        gen = np.concatenate([stat[n][(a, a)] for a in ti])
        gen_p = np.concatenate([pv[n][(a, a)] for a in ti])
        gen_in = np.concatenate([decided[n][(a, a)] for a in ti]).astype(bool)
        # an undecided frame is no alarm and no detection
        res.false_alarm[str(n)] = float(np.mean((gen_p < alpha) & gen_in))
        res.n_genuine[str(n)] = int(gen.size)
        for lo, hi in zip(SEPARATION_BUCKETS[:-1], SEPARATION_BUCKETS[1:]):
            keys = [(a, b) for a in ti for b in ti if a != b and lo <= diff[(a, b)] < hi]
            if not keys:
                continue
            forged = np.concatenate([stat[n][k] for k in keys])
            forged_p = np.concatenate([pv[n][k] for k in keys])
            forged_in = np.concatenate([decided[n][k] for k in keys]).astype(bool)
            label = f"{lo:g}-{hi:g} EV" if math.isfinite(hi) else f">= {lo:g} EV"
            res.mismatch.append(MismatchRow(
                n, label, int(gen.size), int(forged.size), auc(forged[forged_in], gen[gen_in]),
                float(np.mean((forged_p < alpha) & forged_in)), undecided_genuine=float(1.0 - gen_in.mean()),
                undecided_forged=float(1.0 - forged_in.mean()), auc_ungated=auc(forged, gen)))
        res.identification[str(n)] = float(np.mean(id_hits[n]))
        res.n_identification[str(n)] = len(id_hits[n])
    return res


def shipped_calibration(bases: Sequence[np.ndarray], *, alpha: float = 0.01, source: str = "",
                        progress: Callable[[str], None] | None = None):
    """The calibration ``vigproc check`` ships: every base × (no field and the calibration
    lenses), in the shipped family (:func:`vigproc.core.lensfamily.default_family`).

    With colour bases, also the scale of Σ for grey frames (``grey_inflate``): the mean
    D² of the same frames' luminance fits over that of their colour fits, so that a
    black-and-white photograph is judged by the scatter of fits like its own."""
    from dataclasses import replace

    from vigproc.core.lensfamily import default_family
    from vigproc.core.pixels import luminance
    from vigproc.forensics.lensmatch import whiten

    family = default_family()
    _, _, calib = select_lenses()
    fields: list[BenchLens | None] = [None, *calib]
    refs = references(fields, family)
    coef, _ = frame_coefficients_table(bases, fields, family, progress)
    cal = calibrate(coef, refs, np.arange(len(bases)), family, alpha=alpha, source=source)
    if bases[0].ndim != 3:
        return cal
    grey, _ = frame_coefficients_table([luminance(b) for b in bases], fields, family, progress)

    def mean_d2(c: np.ndarray) -> float:
        r = (c - refs[:, None, :]).reshape(-1, c.shape[2])
        z = np.array([whiten(v, cal) for v in r[np.all(np.isfinite(r), axis=1)]])
        return float(np.mean(np.einsum("ij,ij->i", z, z)))

    return replace(cal, grey_inflate=max(mean_d2(grey) / mean_d2(coef), 1.0))
