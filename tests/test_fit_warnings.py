"""A fit that does not hold says so, once, with the cause and the next step: in the run, run.json and
`uvps info` (real subprocess), and the thresholds on analytic normals."""
import json
import subprocess
import sys
from types import SimpleNamespace

import numpy as np
import pytest

from uvps.core import pipeline
from uvps.testing.synthetic import make_capture, write_capture


def _stereo(tilt_deg=0.0, residual=0.005, invalid=0, shape=(100, 120)):
    t = np.radians(tilt_deg)
    normals = np.zeros(shape + (3,), np.float32)
    normals[..., 0], normals[..., 2] = -np.sin(t), np.cos(t)       # a plane rising to +x
    return SimpleNamespace(normals=normals, residual_rms=residual, n_invalid=invalid)


def test_a_good_fit_gives_no_warning_and_each_cause_is_named():
    n = 100 * 120
    ok = pipeline.fit_checks(_stereo(tilt_deg=1.0), n, lights_source="positions", pixel_size_um=15.0)
    assert ok["warnings"] == [] and ok["diagnostics"]["mean_tilt_deg"] == pytest.approx(1.0, abs=0.01)
    bad = pipeline.fit_checks(_stereo(tilt_deg=16.0, residual=0.8), n, lights_source="directions",
                              pixel_size_um=100.0)
    assert len(bad["warnings"]) == 1
    w = bad["warnings"][0]
    assert w.startswith("the fit does not hold: the lamps and a matte surface leave 80 % of the signal unexplained")
    # 12 mm field, tan 16 deg: a 3.44 mm ramp
    assert "the heights ramp by about 3.44 mm across the field (mean normal tilted 16 deg" in w
    assert "check that the light file belongs to these images" in w
    est = pipeline.fit_checks(_stereo(residual=0.2), n, lights_source="estimated", pixel_size_um=15.0)
    assert est["warnings"][0].endswith("give measured lamp positions (--lights); for gloss or cast shadows, --robust "
                                       "leaves out each pixel's brightest and darkest samples")
    holes = pipeline.fit_checks(_stereo(), n, lights_source="positions", pixel_size_um=15.0)
    assert holes["warnings"] == []
    holes = pipeline.fit_checks(_stereo(invalid=int(0.05 * n)), n, lights_source="positions", pixel_size_um=15.0)
    assert len(holes["warnings"]) == 1 and holes["warnings"][0].startswith("5 % of the pixels have no normal")


def test_wrong_lamp_directions_are_named_in_the_run_run_json_and_info(tmp_path):
    """An .lp file whose directions are turned 15 deg about y (a lamp arc measured from a tilted
    reference): the heights ramp across the field and the run says the fit does not hold; the same
    capture with its own .lp is warning-free. (A mirrored or rotated set is a symmetry of the
    images: nothing in them tells it.)"""
    write_capture(make_capture(shape=(200, 260), n_lights=8, seed=6), tmp_path / "cap")
    lp = (tmp_path / "cap" / "lights.lp").read_text().splitlines()
    c, s = np.cos(np.radians(15)), np.sin(np.radians(15))
    flipped = [lp[0]] + [" ".join([f, str(c * float(x) + s * float(z)), y, str(-s * float(x) + c * float(z))])
                         for f, x, y, z in (line.split() for line in lp[1:])]
    (tmp_path / "flipped.lp").write_text("\n".join(flipped) + "\n")

    def run(lights, out):
        r = subprocess.run([sys.executable, "-m", "uvps", "run", str(tmp_path / "cap"), "-o", str(tmp_path / out),
                            "--lights", str(lights)], capture_output=True, text=True, timeout=600)
        assert r.returncode == 0, r.stderr
        return r

    good = run(tmp_path / "cap" / "lights.lp", "good")
    assert "warning:" not in good.stderr
    bad = run(tmp_path / "flipped.lp", "bad")
    warned = [line for line in bad.stderr.splitlines() if line.startswith("warning: the fit does not hold")]
    assert len(warned) == 1 and "check that the light file belongs to these images" in warned[0]
    log = json.loads((tmp_path / "bad" / "run.json").read_text())
    assert any(w.startswith("the fit does not hold") for w in log["warnings"])
    info = subprocess.run([sys.executable, "-m", "uvps", "info", str(tmp_path / "bad")], capture_output=True,
                          text=True, timeout=120)
    assert "warning:    the fit does not hold" in info.stdout
