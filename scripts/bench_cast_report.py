"""What a corrected frame of a trusted lens pays for its record's colour-cast report:
``ProfileStore.cast_report`` on a profile holding 300 frames' cast records.

    PYTHONPATH=. python scripts/bench_cast_report.py
"""

from __future__ import annotations

import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))

import test_cast_series as T  # noqa: E402 - the tests' synthetic records

from vigproc.stores.cast_store import read_cast  # noqa: E402
from vigproc.stores.profiles import ProfileStore  # noqa: E402


def main(frames: int = 300, calls: int = 20) -> None:
    rng = np.random.default_rng(0)
    x, se = T._frames(rng, frames)
    with tempfile.TemporaryDirectory() as d, ProfileStore(Path(d) / "p.sqlite") as st:
        for i in range(frames):
            st.learn(T._key(), T._model(), frame_id=f"f{i}", cast=T._record(x[i], se[i]))
        st.cast_report(T._key())  # pooled once
        t = time.perf_counter()
        for _ in range(calls):
            st.cast_report(T._key())
        kept = (time.perf_counter() - t) / calls
        row_id = st.con.execute("SELECT id FROM profiles").fetchone()[0]
        t = time.perf_counter()
        for _ in range(calls):
            read_cast(st.con, row_id)
        pooled = (time.perf_counter() - t) / calls
    print(f"{frames} records: cast_report {kept * 1e3:.2f} ms a call (records unchanged), "
          f"pooling them again {pooled * 1e3:.1f} ms")


if __name__ == "__main__":
    main()
