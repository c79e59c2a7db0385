#!/usr/bin/env bash
# Set up everything vigproc needs on a fresh machine: the exiftool program and a
# virtualenv (.venv) with vigproc and its Python dependencies. Safe to run again:
# it only reinstalls when pyproject.toml changed. `bootstrap.sh --tests` also installs
# what only the test suite uses (darktable, for the darktable adapter's test).
set -euo pipefail
with_tests=0
if [ "${1:-}" = "--tests" ]; then with_tests=1; fi
root="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
cd "$root"

sudo_cmd=""
if [ "$(id -u)" -ne 0 ]; then sudo_cmd="sudo"; fi
if ! command -v exiftool >/dev/null 2>&1; then
    echo "bootstrap: installing exiftool (Debian package libimage-exiftool-perl)" >&2
    $sudo_cmd apt-get update -qq >/dev/null
    DEBIAN_FRONTEND=noninteractive $sudo_cmd apt-get install -y -qq libimage-exiftool-perl >/dev/null
fi
# darktable (Debian's 4.x, with Lua) runs the darktable plugin headless in the tests
# (tests/test_plugins_hosts.py); about 10 s and 117 MB. VIGPROC_NO_DARKTABLE=1 skips
# it (that test is then skipped); a failed install is not fatal.
if [ "$with_tests" = "1" ] && [ "${VIGPROC_NO_DARKTABLE:-0}" != "1" ] && ! command -v darktable-cli >/dev/null 2>&1 \
        && command -v apt-get >/dev/null 2>&1; then
    echo "bootstrap: installing darktable for the plugin test (VIGPROC_NO_DARKTABLE=1 skips this)" >&2
    { $sudo_cmd apt-get update -qq >/dev/null \
        && DEBIAN_FRONTEND=noninteractive $sudo_cmd apt-get install -y -qq --no-install-recommends darktable \
        >/dev/null; } || echo "bootstrap: darktable not installed; its test will be skipped" >&2
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
    # setuptools' "BuildBackendWarning: Editable installation ... folders with the same name as
    # your package" banner is about a layout this project has on purpose (vigproc/ is the
    # package): silenced by its message, every other warning still shows
    PYTHONWARNINGS="ignore:Editable installation" \
        .venv/bin/python -m pip install -q -e ".[test]" 2>&1 | grep -v "^WARNING: Location" >&2 || true
    .venv/bin/python -c "import vigproc, numba, rawpy, OpenImageIO, exiftool, watchdog, lensfunpy, distributed" \
        || { echo "bootstrap: installation failed" >&2; exit 1; }
    echo "$want" > "$stamp"
fi
