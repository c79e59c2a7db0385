#!/usr/bin/env bash
# Set up and run the whole test suite. Extra arguments go to pytest.
set -euo pipefail
root="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
bash "$root/scripts/bootstrap.sh" --tests
cd "$root"
# in parallel on every core (pytest-xdist); VIGPROC_TEST_WORKERS=0 runs in one process.
# worksteal: a worker that runs out takes half of the other's queue, so a run of long
# tests (the daemon's, a few minutes in all) queued on one worker does not end the run alone
exec .venv/bin/python -m pytest -n "${VIGPROC_TEST_WORKERS:-auto}" --dist worksteal "$@"
