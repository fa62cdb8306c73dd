#!/usr/bin/env bash
# Set up everything the test suite needs on a fresh machine, then run it:
#   - ./.venv with uvps and pytest (scripts/setup.sh --test)
#   - Debian's ImageJ 1.x, Jython, Xvfb and a JDK for the real-ImageJ tests (as root or with sudo;
#     scripts/install_imagej_deps.sh is a no-op when they are present)
# Extra arguments go to pytest.
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh --test
# Without root or sudo the real-ImageJ tests cannot be set up: in CI that is a failure, elsewhere
# they are skipped with the reason (the rest of the suite still runs).
if ! bash scripts/install_imagej_deps.sh; then
  [ "${CI:-}" = "true" ] && exit 1
  echo "test_all.sh: ImageJ dependencies missing: the tests in tests/imagej will be skipped" >&2
fi
exec .venv/bin/python -m pytest -q "$@"
