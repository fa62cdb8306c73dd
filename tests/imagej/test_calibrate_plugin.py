"""Calibrate Lamps (uvps calibrate) and Run Whole Pipeline with its calibration, from batch
macros in a real ImageJ: the spheres found shown as circle overlays, the calibration reused."""
import json

import pytest

from conftest import PYTHON_EXCEPTION_STATUS
from uvps.testing.synthetic import make_capture, write_capture
from uvps.testing.synthetic_spheres import SphereSpec, make_sphere_capture, write_sphere_capture

pytestmark = pytest.mark.imagej

TIMEOUT = 600


def q(path):
    return "[%s]" % path


@pytest.fixture(scope="module")
def captures(tmp_path_factory):
    d = tmp_path_factory.mktemp("calibrate plugin")
    cap = make_capture(shape=(300, 400), n_lights=6, seed=4, pixel_size_um=60.0, rgb=False)
    write_capture(cap, d / "painting")
    sc = make_sphere_capture(cap, [SphereSpec("glossy", (0.15, 0.2), 3.0), SphereSpec("matte", (0.85, 0.8), 3.0)])
    write_sphere_capture(sc, d / "sphere capture")
    return d, sc


def test_calibrate_lamps_shows_the_spheres_and_run_uses_the_calibration(run_macro, captures, tmp_path):
    d, sc = captures
    cal = tmp_path / "my calibration"
    run_dir = tmp_path / "run"
    result = run_macro(
        'run("Calibrate Lamps", "spheres=%s calibration=%s");\n'
        'print("title: " + getTitle());\nprint("overlay: " + Overlay.size);\n'
        'run("Run Whole Pipeline", "capture=[Folder or files] images=%s run=%s degree=4 calibration=%s");\n'
        'print("went on");\n' % (q(d / "sphere capture"), q(cal), q(d / "painting"), q(run_dir), q(cal)),
        timeout=TIMEOUT).check()
    lines = result.stdout.splitlines()
    assert "title: sphere capture (detections)" in lines, result.stdout
    assert "overlay: 2" in lines
    assert "went on" in lines
    found = [ln for ln in lines if ln.startswith("uvps Calibrate Lamps: sphere ")]
    assert len(found) == 2 and "glossy, detected" in found[0] and "matte, detected" in found[1], found
    doc = json.loads((cal / "calibration.json").read_text())
    assert doc["route"] == "spheres" and doc["n_lamps"] == 6
    rj = json.loads((run_dir / "run.json").read_text())
    assert rj["params"]["calibration"] == str(cal)
    assert rj["diagnostics"]["calibration"]["route"] == "spheres"


def test_calibrate_lamps_without_spheres_fails_with_the_core_message(run_macro, captures, tmp_path):
    d, _ = captures
    result = run_macro('run("Calibrate Lamps", "spheres=%s calibration=%s");\n'
                       % (q(d / "painting"), q(tmp_path / "CAL")), timeout=TIMEOUT)
    assert result.returncode == PYTHON_EXCEPTION_STATUS, result.stdout + result.stderr
    assert "uvps Calibrate Lamps failed (UVPSInputError)" in result.stdout
    assert "no sphere found in the sphere capture" in result.stdout
    assert not (tmp_path / "CAL").exists()
