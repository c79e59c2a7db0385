#!/usr/bin/env bash
# Set up everything vigproc needs on a fresh machine: the exiftool program and a
# virtualenv (.venv) with vigproc and its Python dependencies. Safe to run again:
# it only reinstalls when pyproject.toml changed.
set -euo pipefail
root="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
cd "$root"

if ! command -v exiftool >/dev/null 2>&1; then
    echo "bootstrap: installing exiftool (Debian package libimage-exiftool-perl)" >&2
    sudo_cmd=""
    if [ "$(id -u)" -ne 0 ]; then sudo_cmd="sudo"; fi
    $sudo_cmd apt-get update -qq >/dev/null
    DEBIAN_FRONTEND=noninteractive $sudo_cmd apt-get install -y -qq libimage-exiftool-perl >/dev/null
fi

py="${PYTHON:-python3}"
if ! "$py" -c 'import sys; sys.exit(sys.version_info < (3, 10))'; then
    echo "bootstrap: vigproc needs Python >= 3.10 ($py is $("$py" --version 2>&1))" >&2
    exit 1
fi
if [ ! -x .venv/bin/python ]; then
    echo "bootstrap: creating .venv" >&2
    "$py" -m venv .venv
fi
stamp=.venv/.vigproc-installed
want="$(sha256sum pyproject.toml | cut -d' ' -f1)"
if [ "$(cat "$stamp" 2>/dev/null)" != "$want" ]; then
    echo "bootstrap: installing vigproc and its dependencies into .venv" >&2
    .venv/bin/python -m pip install -q --upgrade pip >/dev/null 2>&1 || true
    .venv/bin/python -m pip install -q -e ".[test]" 2>&1 | grep -v "^WARNING: Location" >&2 || true
    .venv/bin/python -c "import vigproc, numba, rawpy, OpenImageIO, exiftool, watchdog, lensfunpy" \
        || { echo "bootstrap: installation failed" >&2; exit 1; }
    echo "$want" > "$stamp"
fi
