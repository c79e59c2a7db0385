"""Forensics benchmark: lens identification (Lyu 2010, Fig. 6) and the consistency check.

Protocol
--------
* **Lens classes** (:func:`vigproc.forensics.calibration_frames.lens_classes`): the first ``n_lenses`` lenses of
  :func:`vigproc.stores.lensfun.diverse_lenses` that have two calibrated apertures at their
  shortest focal length at least one stop apart with different fall-off (corner
  attenuation differing by ≥ 0.05; some compact-camera entries repeat one
  calibration for every aperture, and such "classes" could not be told apart by
  anything): the widest aperture and the calibrated one nearest two stops down.
  Each (lens, aperture) is a class, as the paper's Fig. 6 rows are.
* **Frames**: natural photographs (480×320, linearised luminance, as in
  :mod:`benchmarks.lensfun`) multiplied by each class's lensfun "pa" field.
  The photographs are split in two halves at random (``seed``): the *training*
  half trains the classifiers and calibrates the check, the *test* half is
  measured.  No photograph is in both.
* **Identification**: the paper's nearest neighbour on (p1, p2, p3, α1..α7) and
  vigproc's classifier (:mod:`vigproc.forensics.identify`), one frame and ``frames`` frames
  (distinct test photographs of one class) at a time.  Lens-level accuracy counts a
  prediction right when the lens is right whatever the aperture.
* **Consistency check**, with the calibration fitted on the training frames:
  - *null*: a test frame checked against its own class's lensfun model;
  - *mislabelled*: the same frame checked against every class of the other lenses
    (and, separately, against the same lens's other aperture);
  - *cropped*: the vignetted frame cropped off-centre to κ = 0.9, 0.8, 0.7 or 0.6
    of its width and height at a corner (cycling) and resized back to 480×320
    (area filter), so the optical centre moves by (1 − κ)/2 of the frame,
    checked against its own class.

  ROC AUC is of the statistic D² over every frame (weak ones included, with
  their rejected fits); the false-alarm and detection rates at the threshold
  (false-alarm probability < ``alpha``) are of the frames that get a verdict, and
  the share of frames called "insufficient-signal" is given beside them.
"""

from __future__ import annotations

import logging
import math
import time
from dataclasses import asdict, dataclass, field
from typing import Callable, Sequence

import numpy as np

from vigproc.core.model import VignettingModel
from vigproc.forensics.calibration_frames import LensClass, calibration_residuals, lens_classes  # noqa: F401  (re-exported)

log = logging.getLogger(__name__)

WIDTH, HEIGHT = 480, 320
CROP_FRACTIONS = (0.9, 0.8, 0.7, 0.6)
#: Bins of the true fall-off difference between two classes (EV RMS over the frame).
SEPARATION_BINS = (0.0, 0.1, 0.25, 0.5, math.inf)


def crop_frame(frame: np.ndarray, kappa: float, corner: int) -> np.ndarray:
    """Crop ``kappa`` of the width and height at a corner (0 top-left, 1 top-right,
    2 bottom-left, 3 bottom-right) and resize back to the frame's size (area filter)."""
    from vigproc.core.resample import resize_area

    h, w = frame.shape
    ch, cw = max(2, round(h * kappa)), max(2, round(w * kappa))
    y0 = 0 if corner in (0, 1) else h - ch
    x0 = 0 if corner in (0, 2) else w - cw
    return resize_area(frame[y0 : y0 + ch, x0 : x0 + cw], h, w)


def split_images(n: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Disjoint random halves (train, test) of ``n`` photographs."""
    order = np.random.default_rng(seed).permutation(n)
    return np.sort(order[: n // 2]), np.sort(order[n // 2 :])


def field_separation(a: LensClass, b: LensClass, width: int = WIDTH, height: int = HEIGHT) -> float:
    """RMS over the frame of log2(φ_a/φ_b), EV: how different two classes really are."""
    la = np.log2(a.field(height // 4, width // 4))
    lb = np.log2(b.field(height // 4, width // 4))
    return float(np.sqrt(np.mean((la - lb) ** 2)))


@dataclass
class Frame:
    """One estimated benchmark frame."""

    image: int
    cls: int
    crop: float  # 1 = not cropped
    estimate: VignettingModel
    features: np.ndarray  # forensic features (frame_features of the fit)
    weak: bool


def estimate_frames(
    images: Sequence[np.ndarray], which: Sequence[int], classes: Sequence[LensClass],
    estimate: Callable[[np.ndarray], VignettingModel], *, crops: bool = False,
    progress: Callable[[str], None] | None = None,
) -> list[Frame]:
    """Estimate photograph ``i`` × class ``c`` for every ``i`` in ``which`` and every
    class; with ``crops``, one off-centre crop per (photograph, class) instead
    (κ and corner cycling)."""
    from vigproc.forensics.check import frame_features, is_weak

    out = []
    for ci, c in enumerate(classes):
        t0 = time.perf_counter()
        for j, i in enumerate(which):
            im = images[i]
            frame = im * c.field(*im.shape)
            kappa = 1.0
            if crops:
                kappa = CROP_FRACTIONS[(j + ci) % len(CROP_FRACTIONS)]
                frame = crop_frame(frame, kappa, (j // len(CROP_FRACTIONS) + ci) % 4)
            m = estimate(frame)
            fit = m.candidate if m.candidate is not None else m
            out.append(Frame(int(i), ci, kappa, m, frame_features(fit), is_weak(m)))
        if progress is not None:
            progress(f"  {'crops of ' if crops else ''}{c.label}: {len(which)} frames, "
                     f"{(time.perf_counter() - t0) / max(len(which), 1) * 1000:.0f} ms each")
    return out


# ------------------------------------------------------------------ metrics
def roc_auc(negatives: Sequence[float], positives: Sequence[float]) -> float:
    """Area under the ROC curve of a score that should be higher for positives
    (Mann-Whitney U / (n_neg·n_pos), ties counted half)."""
    from scipy.stats import rankdata

    neg = np.asarray(negatives, dtype=np.float64)
    pos = np.asarray(positives, dtype=np.float64)
    if neg.size == 0 or pos.size == 0:
        return math.nan
    r = rankdata(np.concatenate([neg, pos]))
    return float((r[neg.size :].sum() - pos.size * (pos.size + 1) / 2.0) / (neg.size * pos.size))


@dataclass
class CheckRow:
    """Consistency-check figures for one kind of alternative."""

    case: str
    n_frames: int  # frames per decision
    n_null: int
    n_alt: int
    auc: float
    auc_decided: float  # frames with a verdict only
    false_alarm: float  # decided null frames called inconsistent
    detection: float  # decided alternative frames called inconsistent
    null_undecided: float  # share of null frames with "insufficient-signal"
    alt_undecided: float


def _rates(p_null, weak_null, p_alt, weak_alt, alpha) -> tuple[float, float, float, float]:
    p_null, weak_null = np.asarray(p_null), np.asarray(weak_null, dtype=bool)
    p_alt, weak_alt = np.asarray(p_alt), np.asarray(weak_alt, dtype=bool)
    fa = float(np.mean(p_null[~weak_null] < alpha)) if (~weak_null).any() else math.nan
    det = float(np.mean(p_alt[~weak_alt] < alpha)) if (~weak_alt).any() else math.nan
    return fa, det, float(weak_null.mean()), float(weak_alt.mean())


@dataclass
class IdentRow:
    classifier: str
    n_frames: int
    n_tests: int
    accuracy: float  # lens + aperture classes
    mean_class_accuracy: float
    lens_accuracy: float  # lens right, aperture ignored
    confusion: list = field(default_factory=list)  # counts, single frame only


@dataclass
class ForensicsBenchResult:
    classes: list
    n_train_images: int
    n_test_images: int
    alpha: float
    calibration_frames: int
    identification: list
    check: list
    separation: list
    seconds: float


def _groups(rng: np.random.Generator, idx: np.ndarray, n: int) -> list[np.ndarray]:
    """Disjoint random groups of ``n`` from ``idx``."""
    idx = rng.permutation(idx)
    return [idx[k : k + n] for k in range(0, len(idx) - n + 1, n)]


def run(
    images: Sequence[np.ndarray], estimate: Callable[[np.ndarray], VignettingModel], *,
    n_lenses: int = 8, frames: int = 5, seed: int = 0, alpha: float = 0.05,
    progress: Callable[[str], None] | None = None,
    joint: Callable[[list[np.ndarray]], VignettingModel] | None = None,
) -> ForensicsBenchResult:
    """The whole benchmark (see the module docstring).

    Parameters
    ----------
    images : sequence of H×W linear luminance arrays (480×320 protocol frames)
    estimate : callable
        Frame → VignettingModel (the estimator under test).
    n_lenses : int
        Lenses (two apertures each).
    frames : int
        Frames per multi-frame decision.
    seed : int
        Train/test split and multi-frame groups.
    alpha : float
        False-alarm probability threshold of the check.
    joint : callable, optional
        Frames → one VignettingModel (a joint multi-frame fit); adds identification
        rows that classify each group of ``frames`` by the features of its joint fit.
    """
    from vigproc.forensics.check import expected_from_field, fit_calibration, frame_features, score
    from vigproc.forensics.identify import accuracy, confusion_matrix, feature_vector, train_classifier

    t_start = time.perf_counter()
    say = progress or (lambda s: None)
    classes = lens_classes(n_lenses)
    train, test = split_images(len(images), seed)
    h, w = images[0].shape
    say(f"{len(classes)} classes; {len(train)} training and {len(test)} test photographs")
    say("training frames:")
    tr = estimate_frames(images, train, classes, estimate, progress=progress)
    say("test frames:")
    te = estimate_frames(images, test, classes, estimate, progress=progress)
    say("cropped test frames:")
    cr = estimate_frames(images, test, classes, estimate, crops=True, progress=progress)
    rng = np.random.default_rng(seed + 1)

    # ---- identification
    lens_of = np.array([sorted({c.lens for c in classes}).index(c.lens) for c in classes])
    ident = []
    y_tr = np.array([f.cls for f in tr])
    y_te = np.array([f.cls for f in te])
    labels = [c.label for c in classes]
    for name, kind, feats in (("lyu2010 (nearest neighbour, p1..p3, α1..α7)", "nn", "lyu2010"),
                              ("vigproc (Gaussian, ring fall-off)", "gaussian", "falloff")):
        X_tr = np.array([feature_vector(f.estimate, feats) for f in tr])
        X_te = np.array([feature_vector(f.estimate, feats) for f in te])
        clf = train_classifier(X_tr, [labels[i] for i in y_tr], kind=kind, features=feats)
        order = [clf.labels.index(lb) for lb in labels]  # class index -> classifier index
        back = np.argsort(order)
        pred = back[clf.predict(X_te)]
        cm = confusion_matrix(y_te, pred, len(classes))
        acc, mean_acc = accuracy(cm)
        ident.append(IdentRow(name, 1, len(y_te), acc, mean_acc, float(np.mean(lens_of[pred] == lens_of[y_te])),
                              cm.tolist()))
        if frames > 1:
            ok, lens_ok = [], []
            for c in range(len(classes)):
                for g in _groups(rng, np.flatnonzero(y_te == c), frames):
                    p = back[clf.predict_pooled(X_te[g])]
                    ok.append(p == c)
                    lens_ok.append(lens_of[p] == lens_of[c])
            per = np.array(ok, dtype=float)
            ident.append(IdentRow(name, frames, len(ok), float(per.mean()), float(per.mean()), float(np.mean(lens_ok))))
            if joint is not None:
                # the same groups, decided on one joint fit of their frames (same rng state)
                grng = np.random.default_rng(seed + 2)
                ok, lens_ok = [], []
                for c in range(len(classes)):
                    for g in _groups(grng, np.flatnonzero(y_te == c), frames):
                        m = joint([images[te[k].image] * classes[c].field(h, w) for k in g])
                        p = back[clf.predict(feature_vector(m, feats)[None, :])][0]
                        ok.append(p == c)
                        lens_ok.append(lens_of[p] == lens_of[c])
                per = np.array(ok, dtype=float)
                ident.append(IdentRow(name + ", joint fit", frames, len(ok), float(per.mean()), float(per.mean()),
                                      float(np.mean(lens_ok))))

    # ---- consistency check
    # each class's lensfun model once (a least-squares fit each), not once per frame
    truths = [c.true_model(w, h) for c in classes]
    truth_features = [frame_features(m) for m in truths]
    resid = np.array([f.features - truth_features[f.cls] for f in tr])
    cal = fit_calibration(resid, [f.image for f in tr], weak=[f.weak for f in tr], alpha=alpha,
                          source="vigproc bench forensics (training half)")
    expected = [expected_from_field(m, cal, profile=c.label) for m, c in zip(truths, classes)]
    sep = np.array([[field_separation(a, b) for b in classes] for a in classes])

    def claims(fr: list[Frame], against: Callable[[int], Sequence[int]]):
        """(D², p, weak, z, frame index, claimed class) per (frame, claim)."""
        rows = []
        for k, f in enumerate(fr):
            for b in against(f.cls):
                d2, z = score(f.features, expected[b])
                rows.append((d2, cal.p_value(d2, decided=not f.weak), f.weak, z, k, b))
        return rows

    null = claims(te, lambda c: [c])
    other = claims(te, lambda c: [b for b in range(len(classes)) if lens_of[b] != lens_of[c]])
    same = claims(te, lambda c: [b for b in range(len(classes)) if lens_of[b] == lens_of[c] and b != c])
    crop = claims(cr, lambda c: [c])

    def row(case: str, alt, null_rows=null) -> CheckRow:
        d0 = [r[0] for r in null_rows]
        d1 = [r[0] for r in alt]
        fa, det, u0, u1 = _rates([r[1] for r in null_rows], [r[2] for r in null_rows],
                                 [r[1] for r in alt], [r[2] for r in alt], alpha)
        auc_dec = roc_auc([r[0] for r in null_rows if not r[2]], [r[0] for r in alt if not r[2]])
        return CheckRow(case, 1, len(d0), len(d1), roc_auc(d0, d1), auc_dec, fa, det, u0, u1)

    check = [row("lens A labelled as another lens B", other), row("same lens, other aperture", same),
             row("cropped off-centre (all κ)", crop)]
    for kappa in CROP_FRACTIONS:
        check.append(row(f"cropped off-centre, κ = {kappa:g}", [r for r in crop if cr[r[4]].crop == kappa]))
    separation = []
    for lo, hi in zip(SEPARATION_BINS[:-1], SEPARATION_BINS[1:]):
        alt = [r for r in other + same if lo <= sep[te[r[4]].cls, r[5]] < hi]
        if alt:
            rr = row(f"A labelled B, true difference {lo:g}-{hi:g} EV RMS", alt)
            separation.append(rr)

    # ---- several frames of one claimed lens
    if frames > 1:
        def pooled(fr: list[Frame], pick: Callable[[int], Sequence[int]]):
            rows = []
            for c in range(len(classes)):
                for g in _groups(rng, np.array([k for k, f in enumerate(fr) if f.cls == c]), frames):
                    for b in pick(c):
                        zs = [score(fr[k].features, expected[b])[1] for k in g]
                        zm = np.mean(zs, axis=0)
                        d2 = float(frames * zm @ zm)
                        rows.append((d2, cal.p_value(d2, frames), all(fr[k].weak for k in g), zm, int(g[0]), b))
            return rows

        null_n = pooled(te, lambda c: [c])
        other_n = pooled(te, lambda c: [b for b in range(len(classes)) if lens_of[b] != lens_of[c]])
        crop_n = pooled(cr, lambda c: [c])
        for case, alt in ((f"lens A labelled as another lens B, {frames} frames", other_n),
                          (f"cropped off-centre, {frames} frames", crop_n)):
            r = row(case, alt, null_n)
            r.n_frames = frames
            check.append(r)
    return ForensicsBenchResult(
        classes=[asdict(c) | {"label": c.label} for c in classes], n_train_images=len(train),
        n_test_images=len(test), alpha=alpha, calibration_frames=cal.n_frames, identification=ident, check=check,
        separation=separation, seconds=time.perf_counter() - t_start,
    )
