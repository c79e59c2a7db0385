#!/usr/bin/env bash
# Set up and run the whole test suite. Extra arguments go to pytest.
set -euo pipefail
root="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
bash "$root/scripts/bootstrap.sh" --tests
cd "$root"
# in parallel on every core (pytest-xdist); VIGPROC_TEST_WORKERS=0 runs in one process.
# worksteal: a worker that runs out takes half of the other's queue, so a run of long
# tests (the daemon's, a few minutes in all) queued on one worker does not end the run alone
# compiled bytecode, cached in the venv: with PYTHONDONTWRITEBYTECODE set (as some shells and
# containers do) every process the tests start (CLI runs, daemons, workers: 0.3-0.4 CPU s each) compiled
# vigproc's sources again, and each xdist worker rewrote every test module's asserts (about 4 CPU s)
unset PYTHONDONTWRITEBYTECODE
export PYTHONPYCACHEPREFIX="${PYTHONPYCACHEPREFIX:-$root/.venv/pycache}"
exec .venv/bin/python -m pytest -n "${VIGPROC_TEST_WORKERS:-auto}" --dist worksteal "$@"
