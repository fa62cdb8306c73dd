#!/usr/bin/env bash
# Set up everything the test suite needs on a fresh machine, then run it:
#   - ./.venv with uvps and pytest (scripts/setup.sh --test)
#   - Debian's ImageJ 1.x, Jython, Xvfb and a JDK for the real-ImageJ tests (as root or with sudo;
#     scripts/install_imagej_deps.sh is a no-op when they are present)
# Extra arguments go to pytest.
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh --test
bash scripts/install_imagej_deps.sh
exec .venv/bin/python -m pytest -q "$@"
