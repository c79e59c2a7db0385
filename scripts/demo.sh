#!/usr/bin/env bash
# The main job on the bundled sample images with the embedded defaults: estimate and
# correct each one, writing the corrected image in its own format (the samples are
# JPEGs), a picture of each estimated vignetting and a JSON record into
# ${1:-vigproc-demo}/.
set -euo pipefail
root="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
bash "$root/scripts/bootstrap.sh"
exec "$root/.venv/bin/vigproc" demo -o "${1:-vigproc-demo}"
