"""How long learning one more frame into a lens profile takes.

A store holds ``stored`` frames of one lens (each frame's estimate and evidence, learned
through :meth:`vigproc.stores.profiles.ProfileStore.learn` as ``vigproc profile learn``
does); then one more frame is learned, from a fresh copy of that store each round:

* **warm**: in this process, whose imports and caches are loaded;
* **new process**: in a new Python process that imports the store and learns the frame
  (the frame's estimate and evidence made beforehand, so the figure is the learn and
  nothing else), reported apart from its imports.

The frames are 480×320 crops of the given photographs (linearised) × a lensfun lens's
field; their content does not change the cost much (one lens-family fit of the new frame
and the pooling of the stored fits).
"""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

import numpy as np

#: The program a new process runs: import the store, learn one frame, print timings.
_CHILD = """
import json, sys, time
t0 = time.perf_counter()
from vigproc.core.model import VignettingModel
from vigproc.stores.profiles import ProfileKey, ProfileStore
t1 = time.perf_counter()
db, model_path, evidence_path, lens, aspect = sys.argv[1:6]
model = VignettingModel.from_json(open(model_path).read())
evidence = open(evidence_path, "rb").read()
with ProfileStore(db) as store:
    store.learn(ProfileKey(lens, "any", "any", aspect), model, frame_id="the-new-frame", evidence=evidence)
t2 = time.perf_counter()
print(json.dumps({"import_s": t1 - t0, "learn_s": t2 - t1}))
"""


@dataclass
class LearnSpeed:
    stored: int
    rounds: int
    warm_ms: float  # median
    new_process_learn_ms: float  # median, imports apart
    new_process_import_ms: float  # median
    new_process_learn_ms_max: float


def learn_speed(frames: Sequence[np.ndarray], stored: int = 50, rounds: int = 5) -> LearnSpeed:
    """Time learning one more frame into a profile of ``stored`` frames (module doc).

    Parameters
    ----------
    frames : sequence of ndarray (H, W, 3)
        Linear frames of one lens; the first ``stored`` (cycled if fewer) fill the store
        and the next one is the frame learned.
    """
    from vigproc.core.estimate import estimate_with_evidence
    from vigproc.stores.profiles import ProfileKey, ProfileStore, aspect_label

    from vigproc.errors import VigprocError

    usable = []
    for frame in frames:
        try:
            model, evidence = estimate_with_evidence(frame)
        except VigprocError:  # a blank crop, say: not a frame anybody learns
            continue
        usable.append((model.candidate or model, evidence))
    if not usable:
        raise ValueError("no frame could be estimated")
    lens = "bench|learn|lens"
    work = Path(tempfile.mkdtemp(prefix="vigproc-bench-learn-"))
    try:
        base = work / "base.sqlite"
        with ProfileStore(base) as store:
            for i in range(stored):
                model, evidence = usable[i % len(usable)]
                key = ProfileKey(lens, "any", "any", aspect_label(model.width / model.height))
                store.learn(key, model, frame_id=f"frame-{i}", evidence=evidence)
        model, evidence = usable[stored % len(usable)]
        (work / "model.json").write_text(model.to_json())
        (work / "evidence.bin").write_bytes(evidence)
        key = ProfileKey(lens, "any", "any", aspect_label(model.width / model.height))
        warm, learn, imports = [], [], []
        for r in range(rounds):
            db = work / f"warm{r}.sqlite"
            shutil.copy(base, db)
            with ProfileStore(db) as store:
                t0 = time.perf_counter()
                store.learn(key, model, frame_id="the-new-frame", evidence=evidence)
                warm.append(time.perf_counter() - t0)
            db = work / f"new{r}.sqlite"
            shutil.copy(base, db)
            out = subprocess.run([sys.executable, "-c", _CHILD, str(db), str(work / "model.json"),
                                  str(work / "evidence.bin"), lens, key.aspect],
                                 capture_output=True, text=True, check=True, timeout=300)
            t = json.loads(out.stdout.strip().splitlines()[-1])
            learn.append(t["learn_s"])
            imports.append(t["import_s"])
    finally:
        shutil.rmtree(work, ignore_errors=True)
    ms = lambda v: 1000.0 * float(np.median(v))
    return LearnSpeed(stored=stored, rounds=rounds, warm_ms=ms(warm), new_process_learn_ms=ms(learn),
                      new_process_import_ms=ms(imports), new_process_learn_ms_max=1000.0 * max(learn))
