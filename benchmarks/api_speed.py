"""The estimator's time through its public API beside the published peer (``vigproc bench speed --api``).

Frames: the clean protocol's bases (:mod:`benchmarks.clean`: central crops of full-size
camera frames, 480×320, linear, colour), each through three fields:

- ``lens``: a lensfun lens's ``pa`` field, centred (the 20 bench lenses in turn);
- ``table1-2``: Lyu's Table 1 setting 2 (off-centre, elliptical);
- ``none``: no vignetting.

Each frame goes through ``vigproc.estimate(frame)`` (the default method, colour, as a
caller of the library calls it) and, when given, the published C++ peer of Zheng et al.
(:func:`benchmarks.peers.published_rgs`: its process start, the 8-bit PGM written
and the PFM read back included) in the same round, so that their ratio holds on a
loaded machine. The peer's **floor** (the same call on a 16×16 grey frame: process
start and file I/O with almost no estimate) is timed in each round too. Wall-clock and
CPU time (the peer's from ``getrusage`` of its child process) are both kept: on a busy
machine the scheduler moves the first, less the second.
"""

from __future__ import annotations

import resource
import time
from dataclasses import dataclass, field
from typing import Callable, Sequence

import numpy as np

CASES = ("lens", "table1-2", "none")
#: Side of the frame the peer's floor is timed on.
FLOOR_SIDE = 16


@dataclass
class CaseTiming:
    """Medians (ms) of one case over every frame and round."""

    case: str
    n: int
    vigproc_ms: float
    peer_ms: float = float("nan")
    #: vigproc / peer
    ratio: float = float("nan")
    #: vigproc / (peer − the peer's floor): against the peer's estimate alone
    ratio_net: float = float("nan")
    #: the same medians in CPU time (vigproc's process; the peer's child process, from
    #: ``getrusage``): on a machine other processes share, less moved by the scheduler
    vigproc_cpu_ms: float = float("nan")
    peer_cpu_ms: float = float("nan")
    ratio_cpu: float = float("nan")
    #: how many frames the estimate left uncorrected (fall-back) / took off-centre (first round)
    fallbacks: int = 0
    off_centre: int = 0


@dataclass
class ApiSpeed:
    n_frames: int
    rounds: int
    peer_floor_ms: float = float("nan")
    peer_floor_cpu_ms: float = float("nan")
    cases: list[CaseTiming] = field(default_factory=list)


def case_fields(n_lenses: int = 20) -> dict[str, list[np.ndarray]]:
    """The natural-log fields of each case on the 480×320 frame (``lens``: one per bench lens)."""
    from benchmarks.clean import HEIGHT, WIDTH, lens_fields
    from benchmarks.synthetic import table1_model

    lenses, _ = lens_fields(n_lenses)
    return {"lens": [f.log_field for f in lenses],
            "table1-2": [table1_model(2).log_field((HEIGHT, WIDTH))],
            "none": [np.zeros((HEIGHT, WIDTH))]}


def api_speed(bases: Sequence[np.ndarray], peer: Callable | None = None, rounds: int = 3,
              cases: Sequence[str] = CASES, estimate: Callable | None = None) -> ApiSpeed:
    """Time ``vigproc.estimate`` (or ``estimate``) and ``peer`` on every base × case, interleaved.

    Parameters
    ----------
    bases : sequence of ndarray
        480×320×3 linear vignetting-free frames (:func:`benchmarks.clean.load_clean_bases`).
    peer : callable, optional
        lum -> anything (:func:`benchmarks.peers.published_rgs`); None: vigproc alone.
    rounds : int
        Each base × case is timed this many times; the figures are medians over all.
    cases : sequence of str
        Of :data:`CASES`.
    estimate : callable, optional
        img -> VignettingModel (default: ``vigproc.estimate``, the public API).

    Returns
    -------
    ApiSpeed
    """
    from vigproc.core.estimate import estimate as public  # what ``vigproc.estimate`` names
    from vigproc.core.pixels import luminance
    from vigproc.io.protocol import vignetted

    est = estimate or public
    fields = case_fields()
    frames = {c: [vignetted(b, fields[c][i % len(fields[c])]) for i, b in enumerate(bases)] for c in cases}
    lums = {c: [luminance(f) for f in frames[c]] for c in cases}
    tiny = np.random.default_rng(0).uniform(0.2, 0.8, (FLOOR_SIDE, FLOOR_SIDE))
    est(frames[cases[0]][0])  # Numba's kernels loaded, imports done
    if peer is not None:
        peer(tiny)
    t_v = {c: [] for c in cases}
    t_p = {c: [] for c in cases}
    c_v = {c: [] for c in cases}
    c_p = {c: [] for c in cases}
    floor: list[float] = []
    floor_cpu: list[float] = []
    fallbacks = {c: 0 for c in cases}
    off = {c: 0 for c in cases}
    for r in range(rounds):
        for i in range(len(bases)):
            for c in cases:
                t0, u0 = time.perf_counter(), time.process_time()
                m = est(frames[c][i])
                t_v[c].append(time.perf_counter() - t0)
                c_v[c].append(time.process_time() - u0)
                if r == 0:
                    fallbacks[c] += bool(m.quality.fallback)
                    off[c] += bool(abs(m.center[0]) + abs(m.center[1]) > 1)  # centre relative to the frame's
                if peer is not None:
                    t0, u0 = time.perf_counter(), _children_cpu()
                    peer(lums[c][i])
                    t_p[c].append(time.perf_counter() - t0)
                    c_p[c].append(_children_cpu() - u0)
            if peer is not None:
                t0, u0 = time.perf_counter(), _children_cpu()
                peer(tiny)
                floor.append(time.perf_counter() - t0)
                floor_cpu.append(_children_cpu() - u0)
    res = ApiSpeed(len(bases), rounds, _ms(floor), _ms(floor_cpu))
    for c in cases:
        v, p, vc, pc = _ms(t_v[c]), _ms(t_p[c]), _ms(c_v[c]), _ms(c_p[c])
        net = p - res.peer_floor_ms
        res.cases.append(CaseTiming(c, len(t_v[c]), v, p, _ratio(v, p), _ratio(v, net), vc, pc, _ratio(vc, pc),
                                    fallbacks[c], off[c]))
    return res


def _ms(seconds: list[float]) -> float:
    """Median in ms (NaN for none)."""
    return 1000 * float(np.median(seconds)) if seconds else float("nan")


def _ratio(a: float, b: float) -> float:
    """a / b, NaN when b is not a positive time."""
    return a / b if b > 0 else float("nan")


def _children_cpu() -> float:
    """User and system CPU seconds of the finished child processes."""
    r = resource.getrusage(resource.RUSAGE_CHILDREN)
    return r.ru_utime + r.ru_stime
