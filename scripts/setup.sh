#!/usr/bin/env bash
# Create ./.venv with Python 3.11 (or python3) and install uvps into it (editable), with the
# test extras when called with --test. Idempotent: a second run only checks.
set -euo pipefail
cd "$(dirname "$0")/.."
PY=${UVPS_SETUP_PYTHON:-$(command -v python3.11 || command -v python3)}
if [ ! -x .venv/bin/python ]; then
  "$PY" -m venv .venv
fi
extra=""
[ "${1:-}" = "--test" ] && extra="[test]"
.venv/bin/python -m pip install --quiet --upgrade pip >/dev/null
.venv/bin/python -m pip install --quiet -e ".${extra}"
