#!/usr/bin/env python3
"""The default estimator's off-centre path (issue 39): where its CPU time goes, and what
cheaper designs of it cost in accuracy.

Three measurements, each of the tree first on ``PYTHONPATH``:

``stages``: per-stage CPU time (``time.process_time``) of ``vigproc.estimate`` on the frames
of ``vigproc bench speed --api`` (the clean bases of ``--images`` through one case's
fields: ``table1-2`` by default), after one warm-up round; each stage is a function of
:mod:`vigproc.core.estimate` or :mod:`vigproc.core.family_fit` timed around its calls
(nested stages are counted in their callers too).

``accuracy``: the clean protocol (``vigproc bench clean``'s bases × its 20 lensfun fields
and Lyu's Table 1 settings 1–3, the default method, colour) with, per family of fields,
the median / p90 error (EV), the fall-backs, which method each estimate chose (the
off-centre choices on centred real lenses) and the median CPU time per estimate.

``centre-tests``: cheaper luminance centre tests (fewer steps, smaller copies) against the
estimator's, on the clean protocol's frames that reach the test (:func:`centre_tests`).

``stages`` and ``accuracy`` take a design (the estimator's off-centre path changed in place, in this process
only): ``--centre-size`` (long side of the centre tests' working copy, 60 in the
estimator), ``--centre-steps`` (their Gauss-Newton steps, 12), ``--offcentre-size``
(the off-centre fit's and the comparison's working copy, 96), ``--sigma-factor``
(their Cauchy scale times this), ``--fit-size`` (the off-centre fit alone on its own
copy), ``--compare-colour-fit`` (the comparison reads the centred colour fit instead of
refitting the luminance), ``--select-margin`` (the comparison's margin, 0.01) and
``--colour-test-steps`` (``OffCentreRule.colour_test_steps``, 8; 0: the circular colour
centre test, then the full off-centre fit). Run from outside the tree, e.g.::

    OMP_NUM_THREADS=1 NUMBA_NUM_THREADS=1 PYTHONPATH=TREE python TREE/scripts/offcentre_designs.py \\
        accuracy --images ../shared/data/jpeg_exif ../shared/data/natural --centre-size 32 --json out.json
"""

from __future__ import annotations

import argparse
import collections
import json
import math
import sys
import time
from dataclasses import replace

import numpy as np


def apply_design(centre_size: int, centre_steps: int, offcentre_size: int, sigma_factor: float,
                 fit_size: int | None = None, compare_colour_fit: bool = False,
                 select_margin: float | None = None, colour_test_steps: int | None = None) -> None:
    """Change the default estimator's off-centre path in this process: the centre tests'
    copy and steps, the off-centre fit's (and the comparison's) copy and Cauchy scale;
    ``fit_size``: the off-centre family fit alone on its own copy; ``compare_colour_fit``:
    the comparison reads the centred colour fit's field instead of refitting the
    luminance; ``select_margin``: the comparison's margin (0.01 in the estimator);
    ``colour_test_steps``: ``OffCentreRule.colour_test_steps`` (0: the colour-weighted
    pairs' circular centre test, then the full off-centre fit)."""
    from vigproc.core import estimate as E
    from vigproc.core import family_fit as F

    if fit_size is not None:
        off_centre_fit = E.off_centre_fit

        def off(lum, c, settings, mask, family, hint, colour, copy=None):
            return off_centre_fit(lum, c, replace(settings, work_size=fit_size), mask, family, hint, colour, None)

        E.off_centre_fit = off
    if compare_colour_fit:
        fit_family, kept = E.fit_family, {}

        def family(*args, **kw):
            if kw.get("start") is not None:  # the comparison's refit: the centred colour fit instead
                return kept["fit"]
            kept["fit"] = fit_family(*args, **kw)
            return kept["fit"]

        E.fit_family = family

    E.CENTRE_WORK_SIZE = centre_size  # read at call time by _off_centre_choice
    fit_centre = F.fit_centre

    def centre(*args, **kw):
        kw.setdefault("iterations", centre_steps)  # a caller naming its steps keeps them
        return fit_centre(*args, **kw)

    F.fit_centre = centre  # the estimator calls it through the module
    rule = E.OffCentreRule()
    s = rule.settings
    s = replace(s, work_size=offcentre_size, sigma=s.sigma * sigma_factor, grey_sigma=s.grey_sigma * sigma_factor,
                select_margin=s.select_margin if select_margin is None else select_margin)
    defaults = list(E.estimate_default.__defaults__)
    steps = rule.colour_test_steps if colour_test_steps is None else colour_test_steps
    defaults[-1] = replace(rule, settings=s, colour_test_steps=steps)
    E.estimate_default.__defaults__ = tuple(defaults)


def stages(images: list[str], limit: int, case: str, rounds: int) -> None:
    """Print each stage's CPU ms per frame on the api bench's frames of ``case``."""
    import vigproc
    from benchmarks.api_speed import case_fields
    from benchmarks.clean import load_clean_bases
    from vigproc.core import estimate as E
    from vigproc.core import family_fit as F
    from vigproc.io.protocol import vignetted

    bases, _ = load_clean_bases(images, limit=limit, colour=True)
    fields = case_fields()[case]
    frames = [vignetted(b, fields[i % len(fields)]) for i, b in enumerate(bases)]
    for fr in frames:  # kernels compiled, imports done
        vigproc.estimate(fr)
    spent, calls = collections.defaultdict(float), collections.Counter()

    def timed(owner, name):
        fn = getattr(owner, name)

        def run(*args, **kw):
            t = time.process_time()
            try:
                return fn(*args, **kw)
            finally:
                spent[name] += time.process_time() - t
                calls[name] += 1

        setattr(owner, name, run)

    for name in ("_off_centre_choice", "fit_family", "off_centre_fit", "luminance_copy", "with_colour",
                 "settings_index", "estimate_robust"):
        timed(E, name)
    for name in ("fit_centre", "pair_losses"):
        timed(F, name)
    timed(F.OffCentreFit, "with_uncertainty")
    per, chosen = [], collections.Counter()
    for r in range(rounds):
        for fr in frames:
            t = time.process_time()
            m = vigproc.estimate(fr)
            per.append(time.process_time() - t)
            chosen[m.method] += r == 0
    n = len(per)
    print(f"{case}: {len(frames)} frames x {rounds} rounds; vigproc.estimate CPU ms per frame: "
          f"mean {1000 * float(np.mean(per)):.1f}, median {1000 * float(np.median(per)):.1f}; chosen {dict(chosen)}")
    for name, s in sorted(spent.items(), key=lambda kv: -kv[1]):
        print(f"  {name:22s} {1000 * s / n:6.1f} ms per frame ({calls[name]} calls)")


def clean_frames(images: list[str]):
    """The default estimator (``vigproc bench clean``'s, the 20 test lenses left out of its
    family) and the clean protocol's frames: (family of fields, field, frame) in turn, the
    20 lensfun fields first, then Table 1 settings 1-3."""
    from benchmarks import clean as C
    from benchmarks.cli._common import estimator
    from vigproc.core.lensfamily import PROFILE_COMPONENTS
    from vigproc.stores.lensfun import lensfun_family

    bases, _ = C.load_clean_bases(images, colour=True)
    lens, excluded = C.lens_fields(20)
    fn = estimator("default", family=lensfun_family(exclude=excluded, n_components=PROFILE_COMPONENTS))

    def frames():
        for label, fields in [("lensfun", lens)] + [(f.name, [f]) for f in C.table1_fields()]:
            for f in fields:
                for im in bases:
                    yield label, f, im, C.vignetted(im, f.log_field)

    return fn, frames()


def accuracy(images: list[str], out: str | None) -> None:
    """Print (and with ``out`` write as JSON) the clean protocol's figures of the design."""
    from benchmarks.clean import gain_free_ev

    fn, frames = clean_frames(images)
    per_field, chosen, fallbacks, cpu = {}, {}, collections.Counter(), {}
    for label, f, im, v in frames:
        t = time.process_time()
        m = fn(v)
        cpu.setdefault(label, []).append(time.process_time() - t)
        fell = bool(m.quality and m.quality.fallback)
        fallbacks[label] += fell
        # a fall-back's method is its candidate's (the fit it turned down)
        chosen.setdefault(label, collections.Counter())[(m.candidate or m).method if fell else m.method] += 1
        per_field.setdefault(label, {}).setdefault(f.name, []).append(
            gain_free_ev(m.log_field(im.shape[:2]) - f.log_field))
    result = {}
    for label, fields in per_field.items():
        med = [float(np.median(e)) for e in fields.values()]
        result[label] = {"median_ev": float(np.median(med)), "p90_ev": float(np.percentile(med, 90)),
                         "fallbacks": fallbacks[label], "chosen": dict(chosen[label]),
                         "cpu_ms": 1000 * float(np.median(cpu[label]))}
        print(label, json.dumps(result[label]), flush=True)
    if out:
        from vigproc.atomic import atomic_write_text

        atomic_write_text(out, json.dumps(result, indent=1))


#: (long side, Gauss-Newton steps) of the luminance centre tests compared by ``centre-tests``
CENTRE_VARIANTS = ((96, 1), (96, 2), (96, 3), (60, 1), (60, 2), (48, 12), (32, 12))


def centre_tests(images: list[str]) -> None:
    """How well cheaper luminance centre tests (:data:`CENTRE_VARIANTS`) tell Table 1's
    off-centre fields from centred real lenses, on the frames that reach the test: each
    variant's threshold passing as many lensfun frames as the estimator's (0.2
    half-diagonals after 12 steps on the 60-px copy), the Table 1 frames it then passes,
    and its agreement with the estimator's test."""
    from vigproc.core import family_fit as F

    fit_centre, shifts = F.fit_centre, []

    def centre(lum, c, settings, mask, family, hint, uncertainty=True, copy=None, **kw):
        fit = fit_centre(lum, c, settings, mask, family, hint, uncertainty=uncertainty, copy=copy, **kw)
        if copy is not None and copy.C is None:  # the luminance's test (the colour one follows it)
            row = {"estimator": fit.shift}
            for size, steps in CENTRE_VARIANTS:
                cp = F.luminance_copy(lum, replace(settings, work_size=size), mask)
                row[f"{size}px/{steps}"] = fit_centre(lum, c, settings, mask, family, hint, iterations=steps,
                                                      uncertainty=False, copy=cp).shift
            shifts.append(row)
        return fit

    F.fit_centre = centre
    fn, frames = clean_frames(images)
    rows = collections.defaultdict(list)
    for label, _, _, v in frames:
        shifts.clear()
        fn(v)
        if shifts:
            rows[label].append(shifts[0])
    print("frames reaching the centre test:", {k: len(v) for k, v in rows.items()})
    base = {k: np.array([r["estimator"] >= 0.2 for r in v]) for k, v in rows.items()}
    for name in ["estimator"] + [f"{s}px/{n}" for s, n in CENTRE_VARIANTS]:
        x = {k: np.array([r[name] for r in v]) for k, v in rows.items()}
        n_lens = int(base["lensfun"].sum())
        thr = float(np.sort(x["lensfun"])[::-1][n_lens - 1]) if n_lens else math.inf
        line = [f"{name:10s} threshold {thr:.3f}"]
        for k in rows:
            line.append(f"{k}: pass {int(np.sum(x[k] >= thr))} (estimator {int(base[k].sum())}) "
                        f"agree {float(np.mean((x[k] >= thr) == base[k])):.2f}")
        print("; ".join(line))


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("what", choices=("stages", "accuracy", "centre-tests"))
    ap.add_argument("--images", nargs="+", required=True)
    ap.add_argument("--limit", type=int, default=12, help="stages: frames (default %(default)s)")
    ap.add_argument("--case", default="table1-2", choices=("lens", "table1-2", "none"))
    ap.add_argument("--rounds", type=int, default=3, help="stages: rounds over the frames (default %(default)s)")
    ap.add_argument("--centre-size", type=int, default=60)
    ap.add_argument("--centre-steps", type=int, default=12)
    ap.add_argument("--offcentre-size", type=int, default=96)
    ap.add_argument("--sigma-factor", type=float, default=1.0)
    ap.add_argument("--fit-size", type=int, help="the off-centre family fit alone on a copy of this long side")
    ap.add_argument("--compare-colour-fit", action="store_true",
                    help="the comparison reads the centred colour fit instead of refitting the luminance")
    ap.add_argument("--select-margin", type=float, help="the comparison's margin (0.01 in the estimator)")
    ap.add_argument("--colour-test-steps", type=int,
                    help="OffCentreRule.colour_test_steps (0: a circular colour centre test, then the full fit)")
    ap.add_argument("--json", help="accuracy: write the figures here")
    a = ap.parse_args()
    apply_design(a.centre_size, a.centre_steps, a.offcentre_size, a.sigma_factor, a.fit_size, a.compare_colour_fit,
                 a.select_margin, a.colour_test_steps)
    if a.what == "stages":
        stages(a.images, a.limit, a.case, a.rounds)
    elif a.what == "accuracy":
        accuracy(a.images, a.json)
    else:
        centre_tests(a.images)
    return 0


if __name__ == "__main__":
    sys.exit(main())
