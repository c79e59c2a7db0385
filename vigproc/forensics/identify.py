"""Lens identification from estimated vignetting (Lyu 2010, Section 4.3 and Fig. 6).

The paper's classifier: each frame's estimate gives the feature vector
(p1, p2, p3, α1..α7) -- the shape matrix and the geometric factor of the
Kang-Weiss model -- and a frame is given the class of its nearest training vector
(Euclidean).  Here P is taken in frame-normalised units (P·R², R the
half-diagonal), so frames of any resolution compare; that is the only change.

vigproc's variant (``kind="gaussian"``, ``features="falloff"``), chosen by
measurement (README, "Forensics"):

* **features** -- the mean fall-off on four rings (:func:`vigproc.forensics.check.ring_falloff`)
  instead of the parameters: the parameters trade off against each other (a wider
  P with a stronger α gives the same field), the field does not;
* **normalised** -- each feature standardised by its training spread;
* **class spread** -- a Gaussian per class with the covariance of the training
  frames around their class means, pooled over classes (``shrinkage=1``) or per
  class (``shrinkage=0``) or a blend; pooled measured best (the spread is the
  photographs' own shading, common to all lenses);
* **multi-frame evidence** -- frames known to share a lens add their
  log-likelihoods (the nearest-neighbour classifier votes instead).

References
----------
S. Lyu, "Estimating Vignetting Function from a Single Image for Image
Authentication", ACM MM&Sec 2010, Section 4.3, Fig. 6.
J. H. Friedman, "Regularized discriminant analysis", JASA 84(405), 1989 (the
covariance blend).
"""

from __future__ import annotations

import json
import logging
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from vigproc.atomic import atomic_write_text
from vigproc.core.normalised import normalise
from vigproc.forensics.check import ForensicsError, read_json, ring_falloff
from vigproc.core.model import VignettingModel

log = logging.getLogger(__name__)

__all__ = ["FEATURE_SETS", "KINDS", "LensClassifier", "accuracy", "confusion_matrix", "feature_vector",
           "format_confusion", "train_classifier"]

#: Feature sets: name -> number of entries.
FEATURE_SETS = {"lyu2010": 10, "falloff": 4}
#: Classifier kinds.
KINDS = ("nn", "gaussian")
SCHEMA = "vigproc.lens-classifier/1"


def feature_vector(model: VignettingModel, features: str = "falloff") -> np.ndarray:
    """Identification features of one frame's estimate.

    Parameters
    ----------
    model : VignettingModel
        The estimate; a fall-back's rejected fit (``candidate``) is used when there is one.
    features : {"falloff", "lyu2010"}
        ``lyu2010``: (p1, p2, p3, α1..α7) with P in half-diagonal units (the paper's);
        ``falloff``: mean fall-off in EV on the rings of :data:`vigproc.forensics.check.RING_RADII`.

    Returns
    -------
    ndarray
    """
    m = model.candidate if model.candidate is not None else model
    if features == "lyu2010":
        theta, _, _ = normalise(m)
        return theta[2:].copy()
    if features == "falloff":
        return ring_falloff(m)
    raise ForensicsError(f"unknown feature set {features!r} (choose from {', '.join(FEATURE_SETS)})")


@dataclass(frozen=True)
class LensClassifier:
    """A trained lens classifier (kept as its training vectors; fitted on load).

    Attributes
    ----------
    kind : {"nn", "gaussian"}
    features : {"lyu2010", "falloff"}
    labels : tuple of str
        Class names (e.g. training subfolder names).
    x : tuple of tuple of float
        Training feature vectors.
    y : tuple of int
        Their class indices into ``labels``.
    shrinkage : float
        Gaussian only: 1 = one pooled covariance, 0 = one per class.
    method : str
        Estimator the features came from (use the same one to classify).
    source : str
        How it was made.
    """

    kind: str
    features: str
    labels: tuple[str, ...]
    x: tuple[tuple[float, ...], ...]
    y: tuple[int, ...]
    shrinkage: float = 1.0
    method: str = "default"
    source: str = ""
    _fit: dict = field(default_factory=dict, init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        if self.kind not in KINDS:
            raise ForensicsError(f"unknown classifier kind {self.kind!r} (choose from {', '.join(KINDS)})")
        if self.features not in FEATURE_SETS:
            raise ForensicsError(f"unknown feature set {self.features!r}")
        k = len(self.labels)
        if k < 2 or len(set(self.labels)) != k:
            raise ForensicsError("a classifier needs at least two distinct classes")
        X = np.asarray(self.x, dtype=np.float64)
        y = np.asarray(self.y)
        if X.ndim != 2 or X.shape[1] != FEATURE_SETS[self.features] or len(y) != len(X) or not np.all(np.isfinite(X)):
            raise ForensicsError(f"training vectors must be finite, {FEATURE_SETS[self.features]} per frame, one label each")
        if len(y) and (y.min() < 0 or y.max() >= k):
            raise ForensicsError("training labels out of range")
        counts = np.bincount(y, minlength=k)
        need = 2 if self.kind == "gaussian" else 1
        if counts.min() < need:
            empty = [self.labels[i] for i in np.flatnonzero(counts < need)]
            raise ForensicsError(f"classes with fewer than {need} training frames: {', '.join(empty)}")
        if not 0.0 <= float(self.shrinkage) <= 1.0:
            raise ForensicsError(f"shrinkage must be within [0, 1], got {self.shrinkage}")

    # -- fitting --------------------------------------------------------------
    def _params(self) -> dict:
        if self._fit:
            return self._fit
        X = np.asarray(self.x, dtype=np.float64)
        y = np.asarray(self.y)
        p: dict[str, Any] = {"X": X, "y": y}
        if self.kind == "gaussian":
            mu0, sd = X.mean(axis=0), X.std(axis=0)
            sd = np.where(sd > 0, sd, 1.0)
            A = (X - mu0) / sd
            k, d = len(self.labels), X.shape[1]
            means = np.array([A[y == c].mean(axis=0) for c in range(k)])
            centred = A - means[y]
            pooled = centred.T @ centred / max(len(A) - k, 1)
            ridge = 1e-6 * np.eye(d)
            precisions, logdets = [], []
            for c in range(k):
                own = np.cov(A[y == c].T).reshape(d, d) if (y == c).sum() > 1 else pooled
                s = self.shrinkage * pooled + (1.0 - self.shrinkage) * own + ridge
                precisions.append(np.linalg.inv(s))
                logdets.append(np.linalg.slogdet(s)[1])
            p.update(mu0=mu0, sd=sd, means=means, precisions=np.array(precisions), logdets=np.array(logdets))
        self._fit.update(p)
        return self._fit

    # -- use --------------------------------------------------------------------
    def scores(self, X: np.ndarray) -> np.ndarray:
        """Per-frame, per-class scores (higher = more likely): log-likelihoods for
        ``gaussian``, minus the distance to the class's nearest training vector for ``nn``.

        Parameters
        ----------
        X : ndarray (n, d)
        """
        X = np.atleast_2d(np.asarray(X, dtype=np.float64))
        if X.shape[1] != FEATURE_SETS[self.features] or not np.all(np.isfinite(X)):
            raise ForensicsError(f"expected finite {FEATURE_SETS[self.features]}-entry feature vectors")
        p = self._params()
        k = len(self.labels)
        if self.kind == "nn":
            d = np.sqrt(((X[:, None, :] - p["X"][None, :, :]) ** 2).sum(axis=-1))
            return -np.stack([d[:, p["y"] == c].min(axis=1) for c in range(k)], axis=1)
        A = (X - p["mu0"]) / p["sd"]
        out = np.empty((len(A), k))
        for c in range(k):
            r = A - p["means"][c]
            out[:, c] = -0.5 * np.einsum("ij,jk,ik->i", r, p["precisions"][c], r) - 0.5 * p["logdets"][c]
        return out

    def predict(self, X: np.ndarray) -> np.ndarray:
        """Class index of each frame."""
        return np.argmax(self.scores(X), axis=1)

    def predict_pooled(self, X: np.ndarray) -> int:
        """One class for several frames known to come from the same lens.

        ``gaussian`` adds the frames' log-likelihoods; ``nn`` takes a majority vote
        of the frames' nearest neighbours (ties: the smaller summed distance).
        """
        s = self.scores(X)
        if self.kind == "gaussian":
            return int(np.argmax(s.sum(axis=0)))
        votes = np.bincount(np.argmax(s, axis=1), minlength=len(self.labels))
        best = np.flatnonzero(votes == votes.max())
        return int(best[np.argmax(s[:, best].sum(axis=0))])

    def classify(self, models: Sequence[VignettingModel]) -> np.ndarray:
        """Class index of each estimate."""
        return self.predict(np.array([feature_vector(m, self.features) for m in models]))

    # -- files ------------------------------------------------------------------
    def to_dict(self) -> dict[str, Any]:
        return {"schema": SCHEMA, "kind": self.kind, "features": self.features, "labels": list(self.labels),
                "shrinkage": self.shrinkage, "method": self.method, "source": self.source,
                "y": list(self.y), "x": [[round(v, 8) for v in r] for r in self.x]}

    @classmethod
    def from_dict(cls, d: Any) -> LensClassifier:
        if not isinstance(d, dict) or d.get("schema") != SCHEMA:
            raise ForensicsError(f"not a lens classifier (schema {SCHEMA!r} expected)")
        try:
            return cls(kind=str(d["kind"]), features=str(d["features"]), labels=tuple(str(v) for v in d["labels"]),
                       x=tuple(tuple(float(v) for v in r) for r in d["x"]), y=tuple(int(v) for v in d["y"]),
                       shrinkage=float(d.get("shrinkage", 1.0)), method=str(d.get("method", "default")),
                       source=str(d.get("source", "")))
        except (KeyError, TypeError, ValueError) as exc:
            raise ForensicsError(f"invalid lens classifier: {exc!r}") from None

    def save(self, path: str | Path) -> None:
        """Write as JSON, atomically."""
        atomic_write_text(Path(path), json.dumps(self.to_dict(), separators=(",", ":")) + "\n")

    @classmethod
    def load(cls, path: str | Path) -> LensClassifier:
        return cls.from_dict(read_json(path, "classifier"))


def train_classifier(
    X: np.ndarray, labels: Sequence[str], *, kind: str = "gaussian", features: str = "falloff",
    shrinkage: float = 1.0, method: str = "default", source: str = "",
) -> LensClassifier:
    """Train a classifier from feature vectors and their class names.

    Parameters
    ----------
    X : ndarray (n, d)
        :func:`feature_vector` of each training frame.
    labels : sequence of str
        Class of each frame; classes are sorted by name.
    kind, features, shrinkage, method, source
        See :class:`LensClassifier`.

    Returns
    -------
    LensClassifier

    Raises
    ------
    ForensicsError
        Fewer than two classes, too few frames, bad vectors.
    """
    X = np.atleast_2d(np.asarray(X, dtype=np.float64))
    if len(labels) != len(X):
        raise ForensicsError("one label per training frame is needed")
    names = tuple(sorted(set(labels)))
    index = {n: i for i, n in enumerate(names)}
    return LensClassifier(kind=kind, features=features, labels=names, x=tuple(tuple(float(v) for v in r) for r in X),
                          y=tuple(index[v] for v in labels), shrinkage=shrinkage, method=method, source=source)


def confusion_matrix(true: Sequence[int], predicted: Sequence[int], n_classes: int) -> np.ndarray:
    """Counts, rows = true class, columns = predicted class."""
    cm = np.zeros((n_classes, n_classes), dtype=np.int64)
    for t, p in zip(true, predicted):
        cm[int(t), int(p)] += 1
    return cm


def format_confusion(cm: np.ndarray, labels: Sequence[str], *, width: int = 6) -> str:
    """A confusion matrix in percent of each true class, as in Lyu 2010 Fig. 6.

    Rows are the true classes (with their frame counts), columns the predicted
    ones, numbered; a legend maps numbers to names.  Rows without frames show "-".
    """
    k = len(labels)
    lines = ["rows: true class, columns: predicted (percent of the row)"]
    lines += [f"  [{i + 1}] {name}" for i, name in enumerate(labels)]
    lines.append(" " * 12 + "".join(f"[{j + 1}]".rjust(width) for j in range(cm.shape[1])) + "    n")
    for i in range(k):
        n = int(cm[i].sum())
        cells = "".join((f"{100.0 * c / n:.0f}" if n else "-").rjust(width) for c in cm[i])
        lines.append(f"  [{i + 1}]".ljust(12) + cells + f"{n:>5}")
    return "\n".join(lines)


def accuracy(cm: np.ndarray) -> tuple[float, float]:
    """(overall accuracy, mean per-class accuracy over classes with frames)."""
    total = cm.sum()
    rows = cm.sum(axis=1)
    per = np.diag(cm)[rows > 0] / rows[rows > 0]
    return (float(np.trace(cm) / total) if total else math.nan, float(per.mean()) if per.size else math.nan)
