"""Any ``vigproc`` command line with the EXIF-population fall-back standing in for the default
estimate's identity (issue 38, part a's designs; docs/benchmarks/real-frames.md; not adopted).

The design: where :func:`vigproc.core.estimate.estimate_default` leaves a frame alone for
weak evidence alone (an identity with ``quality.fallback`` and no ``reason``: not the glow
test's refusal) and the EXIF gives a 35-mm focal length and an f-number, the frame gets the
EXIF population's mean field instead (the prior mean of the calibrations nearest that focal
length and f-number, :meth:`vigproc.core.lensfamily.LensFamily.prior`), applied with
confidence 1 (the population's, not the pixels'); the harm rules of the pipeline still run.
Everything else is the default's.

Usage (from the repository root):
    NUMBA_NUM_THREADS=1 python scripts/bench_population_fallback.py on bench real-frames --images DIR --no-harm
    NUMBA_NUM_THREADS=1 python scripts/bench_population_fallback.py on bench clean --methods default+exif --no-table1
``off`` runs the command line unchanged (the baseline).
"""

from __future__ import annotations

import logging
import sys
from dataclasses import replace

import vigproc.core.estimate as E
from vigproc.core.family_fit import family_for, profile_to_model
from vigproc.core.lensfamily import profile_family
from vigproc.core.model import VignettingModel
from vigproc.errors import ModelError
from vigproc.frontends.cli import main as cli

log = logging.getLogger("bench_population_fallback")


def population_fallback(orig):
    """``orig`` (the default estimator) with the fall-back above; returns the wrapper and
    a counter of estimates made and replaced."""
    count = {"estimates": 0, "replaced": 0}

    def estimate(lum, mask=None, hint=None, family=None, colour=None):
        m = orig(lum, mask, hint, family, colour)
        count["estimates"] += 1
        q = m.quality
        weak = m.is_identity and q is not None and q.fallback and not q.reason
        if not weak or hint is None or not hint.focal35 or not hint.fnumber:
            return m
        h, w = lum.shape
        fam = family_for(family or profile_family(), colour is not None)
        mean, _ = fam.prior(hint.focal35, hint.fnumber)
        try:
            field, _ = profile_to_model(fam.mean + mean @ fam.components, fam.radii, w, h)
        except ModelError:
            return m
        count["replaced"] += 1
        nq = replace(q, fallback=False, confidence=1.0, field_ev_rms=field.field_ev_rms())
        return VignettingModel(w, h, center=field.center, p=field.p, alpha=field.alpha, method=m.method,
                               quality=nq)

    return estimate, count


def main(argv: list[str]) -> int:
    if len(argv) < 2 or argv[0] not in ("on", "off"):
        log.error("%s", __doc__)
        return 2
    count = None
    if argv[0] == "on":
        E.estimate_default, count = population_fallback(E.estimate_default)
    rc = cli(argv[1:])
    if count is not None:
        log.warning("population fall-back: %d of %d estimates replaced", count["replaced"], count["estimates"])
    return rc


if __name__ == "__main__":
    logging.basicConfig(format="%(message)s")
    sys.exit(main(sys.argv[1:]))
