"""Learning onto an imported profile beside learning where its frames are.

Store A learns 4 frames of a synthetic lens, exports the profile, store B imports it; both
then learn a fifth frame. Prints each store's σ, B's field against A's, and B without its
prior (the import's information dropped, as before store schema v16).

    PYTHONPATH=. python scripts/import_then_learn.py
"""

from __future__ import annotations

import sys
import tempfile
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))

import test_profile_prior as T  # noqa: E402 - the tests' synthetic frames and helpers

import vigproc.stores.profile_store as ps  # noqa: E402
from vigproc.stores.profile_file import export_profile  # noqa: E402
from vigproc.stores.profiles import ProfileStore  # noqa: E402


def main() -> None:
    real = ps.read_prior
    for seed in (50, 150, 250):
        ev = T._evidence(T._frames(5, seed))
        d = Path(tempfile.mkdtemp())
        with ProfileStore(d / "a.sqlite") as a:
            for i, e in enumerate(ev[:4]):
                a.learn(T._key(), T._model_of(e), frame_id=f"f{i}", evidence=e)
            exported = a.get(T._key())
            here = a.learn(T._key(), T._model_of(ev[4]), frame_id="f4", evidence=ev[4])
        export_profile(exported, d / "lens.json")
        row = [f"seed {seed}: A (5 frames) σ {here.field_sigma_ev:.4f} EV"]
        for label, reader in (("B", real), ("B without its prior", lambda con, rid: None)):
            ps.read_prior = reader
            with ProfileStore(d / f"{len(row)}.sqlite") as b:
                b.import_file(d / "lens.json")
                there = b.learn(T._key(), T._model_of(ev[4]), frame_id="f4", evidence=ev[4])
            diff = T._field_ev(here.model(T.W, T.H), there.model(T.W, T.H))
            row.append(f"{label} σ {there.field_sigma_ev:.4f}, field vs A {diff:.4f} EV")
        ps.read_prior = real
        print("; ".join(row))


if __name__ == "__main__":
    main()
