"""Tests of lens identification (vigproc.forensics.identify), ``vigproc forensics train|evaluate``
and the forensics benchmark's protocol (benchmarks.forensics)."""

from __future__ import annotations

import json
import re

import numpy as np
import pytest

from benchmarks.forensics import crop_frame, field_separation, roc_auc, split_images
from vigproc.forensics.calibration_frames import lens_classes
from vigproc.core.estimate import estimate
from vigproc.forensics.check import FORENSICS_METHOD, ForensicsError, ring_falloff
from vigproc.forensics.identify import (
    FEATURE_SETS,
    LensClassifier,
    accuracy,
    confusion_matrix,
    feature_vector,
    format_confusion,
    train_classifier,
)
from vigproc.core.normalised import normalise

from conftest import textured


def _clusters(seed=0, n=25, spread=0.3):
    """Three well separated Gaussian classes in the 4-d fall-off feature space."""
    rng = np.random.default_rng(seed)
    centres = np.array([[-0.1, -0.3, -0.6, -1.0], [-0.05, -0.15, -0.3, -0.5], [0.0, -0.05, -0.1, -0.2]])
    X = np.concatenate([c + spread * 0.2 * rng.normal(size=(n, 4)) for c in centres])
    y = [name for name in ("strong", "medium", "weak") for _ in range(n)]
    return X, y


# ------------------------------------------------------------------ features
def test_feature_vectors(tmp_path):
    from vigproc.stores.lensfun_io import kw_from_pa

    c = lens_classes(1)[0]
    m = kw_from_pa(c.k1, c.k2, c.k3, 300, 200)
    assert feature_vector(m, "lyu2010") == pytest.approx(normalise(m)[0][2:])
    assert feature_vector(m, "falloff") == pytest.approx(ring_falloff(m))
    assert {k: len(feature_vector(m, k)) for k in FEATURE_SETS} == FEATURE_SETS
    # a fall-back's rejected fit is what describes the frame
    from vigproc.core.model import VignettingModel

    weak = VignettingModel.identity(300, 200, candidate=m)
    assert feature_vector(weak, "falloff") == pytest.approx(ring_falloff(m))
    with pytest.raises(ForensicsError):
        feature_vector(m, "colour")


# ------------------------------------------------------------------ classifiers
@pytest.mark.parametrize("kind", ["nn", "gaussian"])
def test_classifier_separates_clear_classes(kind):
    X, y = _clusters(seed=1)
    clf = train_classifier(X, y, kind=kind, features="falloff")
    Xt, yt = _clusters(seed=2)
    pred = [clf.labels[i] for i in clf.predict(Xt)]
    assert np.mean([a == b for a, b in zip(pred, yt)]) > 0.9
    # noisier frames: one at a time often wrong, five together mostly right
    Xn, yn = _clusters(seed=3, spread=2.0)
    single = np.mean([clf.labels[i] == t for i, t in zip(clf.predict(Xn), yn)])
    groups = [(Xn[k : k + 5], yn[k]) for k in range(0, len(yn), 5)]
    pooled = np.mean([clf.labels[clf.predict_pooled(g)] == t for g, t in groups])
    assert pooled > single


def test_per_class_spread_and_shrinkage():
    rng = np.random.default_rng(4)
    # same means, very different spreads: only a per-class spread can tell them apart
    X = np.concatenate([0.01 * rng.normal(size=(60, 4)), 1.0 * rng.normal(size=(60, 4))])
    y = ["tight"] * 60 + ["wide"] * 60
    Xt = np.concatenate([0.01 * rng.normal(size=(60, 4)), 1.0 * rng.normal(size=(60, 4))])
    per = train_classifier(X, y, shrinkage=0.0)
    pooled = train_classifier(X, y, shrinkage=1.0)
    acc_per = np.mean(per.predict(Xt) == np.repeat([0, 1], 60))
    acc_pooled = np.mean(pooled.predict(Xt) == np.repeat([0, 1], 60))
    assert acc_per > 0.9 > acc_pooled


def test_classifier_file_round_trip_and_validation(tmp_path):
    X, y = _clusters()
    clf = train_classifier(X, y, kind="gaussian", source="test")
    p = tmp_path / "m.json"
    clf.save(p)
    back = LensClassifier.load(p)
    assert back.labels == clf.labels
    assert np.array_equal(back.predict(X), clf.predict(X))
    assert [x.name for x in tmp_path.iterdir()] == ["m.json"]
    d = json.loads(p.read_text())
    for bad in ("{", json.dumps({"schema": "x"}), json.dumps({**d, "kind": "svm"}),
                json.dumps({**d, "x": [[1.0, 2.0]] * len(d["y"])}), json.dumps({**d, "labels": ["a"]}),
                json.dumps({**d, "y": [9] * len(d["y"])})):
        p.write_text(bad)
        with pytest.raises(ForensicsError):
            LensClassifier.load(p)
    with pytest.raises(ForensicsError):  # a Gaussian class needs a spread
        train_classifier(X[:26], y[:26], kind="gaussian")
    with pytest.raises(ForensicsError):
        clf.scores(np.full((1, 4), np.nan))


def test_confusion_matrix_format():
    cm = confusion_matrix([0, 0, 1, 1, 1, 2], [0, 1, 1, 1, 0, 2], 4)
    assert cm.tolist() == [[1, 1, 0, 0], [1, 2, 0, 0], [0, 0, 1, 0], [0, 0, 0, 0]]
    acc, per = accuracy(cm)
    assert acc == pytest.approx(4 / 6) and per == pytest.approx((0.5 + 2 / 3 + 1) / 3)
    text = format_confusion(cm, ["A", "B", "C", "D"])
    rows = [ln for ln in text.splitlines() if re.match(r"\s+\[\d\]\s+[\d-]", ln)]
    assert len(rows) == 4
    assert rows[1].split()[1:4] == ["33", "67", "0"] and rows[3].split()[1] == "-"


# ------------------------------------------------------------------ the commands
def _folder(root, classes, n, seed0):
    from vigproc.io.images import write_image

    for name, c in classes.items():
        d = root / name
        d.mkdir(parents=True)
        for i in range(n):
            img = textured(120, 180, seed=seed0 + i, contrast=0.1)
            if c is not None:
                img = img * c.field(120, 180)
            write_image(d / f"{i:02d}.tif", img.astype(np.float32), bit_depth="float")


def test_train_and_evaluate_round_trip(tmp_path, capsys):
    from vigproc.frontends.cli import main

    strong = lens_classes(3)[4]  # Sigma 105 mm at f/1.4: 0.7 EV RMS
    classes = {"strong-lens": strong, "no-vignetting": None}
    _folder(tmp_path / "train", classes, 5, 0)
    _folder(tmp_path / "test", classes, 4, 50)
    model = tmp_path / "model.json"
    for kind in ("vigproc", "lyu2010"):
        assert main(["forensics", "train", str(tmp_path / "train"), "-o", str(model), "--classifier", kind]) == 0
        assert "2 classes, 10 frames" in capsys.readouterr().out
        assert main(["forensics", "evaluate", str(model), str(tmp_path / "test")]) == 0
        out = capsys.readouterr().out
        assert "[1] no-vignetting" in out and "[2] strong-lens" in out
        acc = float(re.search(r"accuracy ([\d.]+) %", out).group(1))
        assert acc >= 75.0, out
    assert main(["forensics", "evaluate", str(model), str(tmp_path / "test"), "--frames", "2", "--json"]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert np.array(doc["confusion"]).sum() == 4 and doc["frames_per_decision"] == 2
    # a folder without class subfolders, a model that is not one
    assert main(["forensics", "evaluate", str(model), str(tmp_path / "test" / "strong-lens")]) != 0
    bad = tmp_path / "bad.json"
    bad.write_text("[]")
    assert main(["forensics", "evaluate", str(bad), str(tmp_path / "test")]) == 11
    assert "not a lens classifier" in capsys.readouterr().err


def test_calibrate_command(tmp_path, capsys):
    from vigproc.frontends.cli import main
    from vigproc.forensics.check import Calibration
    from vigproc.io.images import write_image

    d = tmp_path / "photos"
    d.mkdir()
    for i in range(10):
        write_image(d / f"{i}.png", textured(160, 240, seed=200 + i, contrast=0.2).clip(0, 1), bit_depth="uint16")
    out = tmp_path / "cal.json"
    assert main(["forensics", "calibrate", "--images", str(d), "-o", str(out), "--lenses", "2",
                 "--per-image", "3", "--input-transfer", "linear"]) == 0
    cal = Calibration.load(out)
    assert cal.n_frames == 30 and cal.n_images == 10
    assert "vigproc forensics calibrate --images" in cal.source and cal.fingerprint is not None


# ------------------------------------------------------------------ benchmark protocol
def test_bench_protocol_pieces():
    classes = lens_classes(4)
    assert len(classes) == 8
    for a, b in zip(classes[::2], classes[1::2]):
        assert a.lens == b.lens and b.aperture >= a.aperture * 1.4
        assert abs((1 + a.k1 + a.k2 + a.k3) - (1 + b.k1 + b.k2 + b.k3)) >= 0.05
        assert field_separation(a, b) > 0.0
    assert field_separation(classes[0], classes[0]) == 0.0
    tr, te = split_images(11, seed=3)
    assert len(tr) == 5 and len(te) == 6 and not set(tr) & set(te)
    # a corner crop moves the optical centre: the field's brightest point leaves the middle
    f = classes[0].field(160, 240)
    c = crop_frame(f, 0.6, 0)
    assert c.shape == f.shape
    y, x = np.unravel_index(np.argmax(c), c.shape)
    assert x > 150 and y > 100
    rng = np.random.default_rng(0)
    neg, pos = rng.normal(size=40), rng.normal(0.8, 1.0, size=30)
    brute = np.mean([(p > n) + 0.5 * (p == n) for p in pos for n in neg])
    assert roc_auc(neg, pos) == pytest.approx(brute)
    assert roc_auc(neg, neg) == pytest.approx(0.5)


def test_bench_run_small():
    from benchmarks.forensics import run

    ims = [textured(96, 144, seed=300 + i, contrast=0.1) for i in range(20)]
    r = run(ims, lambda v: estimate(v, FORENSICS_METHOD, channel_axis=None), n_lenses=2, frames=2, seed=0)
    assert len(r.classes) == 4 and r.n_train_images == 10 and r.n_test_images == 10
    single = [row for row in r.identification if row.n_frames == 1]
    assert len(single) == 2
    for row in single:
        assert np.array(row.confusion).sum() == row.n_tests == 40
        assert 0.0 <= row.accuracy <= 1.0 and row.lens_accuracy >= row.accuracy
    cases = {row.case: row for row in r.check}
    assert cases["lens A labelled as another lens B"].n_alt == 40 * 2
    assert all(0.0 <= row.auc <= 1.0 for row in r.check)
