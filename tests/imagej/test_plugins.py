"""The uvps menu items in the real ImageJ 1.x (Debian's ij.jar + Jython) under Xvfb.

Every test runs batch macros in a fresh JVM with uvps installed by scripts/install_fiji.py (see
conftest.py): a modal dialog halts the JVM (status 3), a failing menu item raises in Jython
(status 4). The capture is a small synthetic one with known protrusions (uvps.synthetic).
"""
import csv
import json
import sys
from pathlib import Path

import numpy as np
import pytest
import tifffile

from conftest import PYTHON_EXCEPTION_STATUS

pytestmark = pytest.mark.imagej

SHAPE = (240, 320)
N_LIGHTS = 8
#: One bridge call on the small capture takes a few seconds; a whole macro well under a minute.
TIMEOUT = 300


def q(path):
    """A path as an ImageJ macro option value (brackets keep spaces)."""
    return "[%s]" % path


@pytest.fixture(scope="module")
def capture_dir(tmp_path_factory):
    """A synthetic 240 x 320, 8-light RGB capture with ground truth, in a folder with a space."""
    from uvps.synthetic import make_capture, write_capture

    cap = make_capture(shape=SHAPE, n_lights=N_LIGHTS, seed=3)
    folder = tmp_path_factory.mktemp("capture") / "uv capture"
    write_capture(cap, folder)
    return folder


@pytest.fixture(scope="module")
def reference_run(capture_dir, tmp_path_factory):
    """The same capture run by the CPython core directly (no ImageJ): the reference outputs."""
    from uvps.commands import COMMANDS

    out = tmp_path_factory.mktemp("reference") / "run"
    COMMANDS["run"]({"images": [str(capture_dir)]}, {"regions": "auto", "detect": True}, out)
    return out


def _read_csv(path):
    with open(path, newline="") as fh:
        return list(csv.DictReader(fh))


def _log_lines(result):
    return result.stdout.splitlines()


# --------------------------------------------------------------------------- settings


def test_settings_accepts_the_python_with_uvps(run_macro):
    import uvps

    result = run_macro('run("UVPS Settings", "python=%s");\n' % q(sys.executable)).check()
    assert any(line.startswith("uvps Settings: %s has uvps %s" % (sys.executable, uvps.__version__))
               for line in _log_lines(result)), result.stdout


def test_settings_rejects_a_python_without_uvps(run_macro, tmp_path):
    missing = tmp_path / "no such python"
    result = run_macro('run("UVPS Settings", "python=%s");\nprint("went on");\n' % q(missing))
    assert result.returncode == PYTHON_EXCEPTION_STATUS, result.stderr
    assert "uvps UVPS Settings failed (Configuration): cannot start %s" % missing in result.stdout
    assert "went on" not in result.stdout
