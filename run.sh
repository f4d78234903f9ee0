#!/usr/bin/env bash
# One entry point for a fresh machine: creates .venv on first use (Python 3.11, the pinned
# versions in requirements.lock), then runs what you ask for.
#   ./run.sh rally [ARGS]   the main job (ace-drake rally)
#   ./run.sh test [ARGS]    the test suite (pytest)
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
cmd=${1:-rally}
shift || true
case "$cmd" in
    rally) exec "$venv/bin/ace-drake" rally "$@" ;;
    test) exec "$venv/bin/python" -m pytest "$@" ;;
    ace-drake) exec "$venv/bin/ace-drake" "$@" ;;
    *) echo "usage: ./run.sh {rally|test|ace-drake} [ARGS]" >&2; exit 2 ;;
esac
