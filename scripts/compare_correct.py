"""Run ``vigproc correct --unapplied copy --json`` from two source trees on the photos
``vigproc bench throughput`` selects, and compare what each file got: the decision
(applied, why not, profile source), the model (centre, shape, fall-off) and the output's
pixels (largest code-value difference; a speed-up may differ by at most 1).

    python scripts/compare_correct.py /work/main /work/h1 --images ../shared/data/jpeg_exif --limit 26 --work /tmp/cmp

Each tree runs with an empty profile store of its own under ``--work``. With ``--learn``
each run also pools its frames into that store (learning as you go), and the two stores'
profiles are compared too (the same keys and frames; their fields' RMS difference, EV).
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks.throughput import select_photos, stage  # noqa: E402
from vigproc.io.images import read_encoded  # noqa: E402


def run(tree: Path, files: list[str], work: Path, name: str, learn: bool = False) -> dict[str, dict]:
    out = work / f"out_{name}"
    shutil.rmtree(out, ignore_errors=True)
    db = work / f"{name}.sqlite"
    db.unlink(missing_ok=True)
    env = {**os.environ, "PYTHONPATH": str(tree), "VIGPROC_PROFILE_DB": str(db)}
    r = subprocess.run([sys.executable, "-m", "vigproc.frontends.cli", "correct", "--unapplied", "copy", "--json",
                        *(["--learn", "--profile-db", str(db)] if learn else []), "-o", str(out), *files],
                       capture_output=True, text=True, env=env, cwd=work)  # cwd: a source tree there would shadow PYTHONPATH
    data = json.loads(r.stdout)
    return {x["file"]: x for x in (data["results"] if isinstance(data, dict) else data)}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("before", type=Path)
    ap.add_argument("after", type=Path)
    ap.add_argument("--images", type=Path, required=True)
    ap.add_argument("--min-mp", type=float, default=0.75)
    ap.add_argument("--limit", type=int, default=26)
    ap.add_argument("--work", type=Path, required=True, help="scratch folder (created)")
    ap.add_argument("--learn", action="store_true", help="pool the frames as they are corrected; compare the stores")
    a = ap.parse_args()
    a.work.mkdir(parents=True, exist_ok=True)
    photos, _ = select_photos(a.images, a.min_mp, a.limit)
    ins = a.work / "in"
    shutil.rmtree(ins, ignore_errors=True)
    files = [str(p) for p in stage(photos, ins)]
    before = run(a.before, files, a.work, "before", a.learn)
    after = run(a.after, files, a.work, "after", a.learn)
    same = worst = 0
    for f in files:
        x, y = before[f], after[f]
        keys = ("applied", "not_applied", "source")
        fit = ("center", "p", "alpha")
        mx = {k: x["model"].get(k) for k in fit} if x.get("model") else None
        my = {k: y["model"].get(k) for k in fit} if y.get("model") else None
        d = 0
        if x.get("output") and y.get("output"):
            cx, cy = (read_encoded(r["output"])[0] for r in (x, y))
            cx, cy = (getattr(c, "codes", c) for c in (cx, cy))
            d = int(np.abs(np.asarray(cx, np.int64) - np.asarray(cy, np.int64)).max())
        worst = max(worst, d)
        ok = all(x.get(k) == y.get(k) for k in keys) and mx == my and d <= 1
        same += ok
        if not ok:
            print(f"differs: {Path(f).name}: {[x.get(k) for k in keys]} / {[y.get(k) for k in keys]}; {d} code values")
    print(f"{len(files)} photos: {same} the same decision, source and model, pixels within 1 code value; "
          f"largest code difference {worst}; applied {sum(bool(r.get('applied')) for r in after.values())}")
    return 0 if same == len(files) and (not a.learn or compare_stores(a.work)) else 1


def compare_stores(work: Path) -> bool:
    """The profiles the two runs learned: the same keys and frame counts; their fields'
    RMS difference over the frame (EV). True when they agree within 0.001 EV."""
    from vigproc.pipeline.learning import field_change_ev
    from vigproc.stores.profiles import ProfileStore

    with ProfileStore(work / "before.sqlite") as sb, ProfileStore(work / "after.sqlite") as sa:
        pb, pa = ({str(p.key): p for p in s.list()} for s in (sb, sa))
    if pb.keys() != pa.keys():
        print(f"the stores hold different profiles: {sorted(pb.keys() ^ pa.keys())}")
        return False
    moved = sorted(field_change_ev(pb[k], pa[k]) for k in pb)
    frames = all(pb[k].n_frames == pa[k].n_frames for k in pb)
    print(f"{len(pb)} profiles learned, frame counts {'the same' if frames else 'DIFFER'}; field change "
          f"median {np.median(moved) if moved else float('nan'):.5f} EV, largest {max(moved, default=0.0):.5f} EV")
    return frames and max(moved, default=0.0) < 1e-3


if __name__ == "__main__":
    raise SystemExit(main())
