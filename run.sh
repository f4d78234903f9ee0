#!/usr/bin/env bash
# One entry point for a fresh machine: creates .venv on first use (Python 3.11, the pinned
# versions in requirements.lock), then runs what you ask for.
#   ./run.sh rally [ARGS]   the main job (ace-drake rally)
#   ./run.sh test [ARGS]    the test suite (pytest); installs Debian's chromium for the browser
#                           tests when it is missing (as root, with apt-get; else they are skipped)
#   ./run.sh ace-drake ...  any other ace-drake command
set -euo pipefail
cd "$(dirname "$0")"
venv=.venv
stamp="$venv/.installed-$(sha256sum requirements.lock pyproject.toml | sha256sum | cut -c1-16)"
if [ ! -f "$stamp" ]; then
    python=${PYTHON:-python3.11}
    command -v "$python" >/dev/null || python=python3
    echo "setting up $venv with $($python --version) (first run only)" >&2
    "$python" -m venv "$venv"
    "$venv/bin/python" -m pip install --quiet --upgrade pip >&2
    "$venv/bin/python" -m pip install --quiet -r requirements.lock >&2
    "$venv/bin/python" -m pip install --quiet --no-deps -e . >&2
    rm -f "$venv"/.installed-*
    touch "$stamp"
fi
# The browser tests (tests/test_match_replay.py) drive /usr/bin/chromium through Playwright; they
# are skipped with a reason when it is absent, so a machine without apt-get or root still runs the rest.
ensure_chromium() {
    [ -x /usr/bin/chromium ] && return 0
    if [ "$(id -u)" != 0 ] || ! command -v apt-get >/dev/null; then
        echo "run.sh: /usr/bin/chromium is missing and cannot be installed here (needs root and apt-get); the browser tests will be skipped" >&2
        return 0
    fi
    echo "run.sh: installing Debian's chromium for the browser tests (apt-get update; apt-get install -y chromium)" >&2
    if ! { apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq --no-install-recommends chromium; } >&2; then
        echo "run.sh: apt-get could not install chromium; the browser tests will be skipped" >&2
    fi
}
cmd=${1:-rally}
shift || true
case "$cmd" in
    rally) exec "$venv/bin/ace-drake" rally "$@" ;;
    test) ensure_chromium; exec "$venv/bin/python" -m pytest "$@" ;;
    ace-drake) exec "$venv/bin/ace-drake" "$@" ;;
    *) echo "usage: ./run.sh {rally|test|ace-drake} [ARGS]" >&2; exit 2 ;;
esac
