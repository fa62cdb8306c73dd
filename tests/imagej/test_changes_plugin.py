"""Compare Captures (uvps changes) from a batch macro in a real ImageJ."""
import csv
import json

import pytest
import tifffile

from conftest import PYTHON_EXCEPTION_STATUS
from uvps.testing.synthetic import write_truth_run

pytestmark = pytest.mark.imagej

TIMEOUT = 600


def q(path):
    return "[%s]" % path


def _truth_run(folder, cap, px):
    return write_truth_run(cap, folder, pixel_size_um=px)


@pytest.fixture(scope="module")
def two_dates(tmp_path_factory):
    from uvps.testing.synthetic import LaterSpec, make_capture_pair

    d = tmp_path_factory.mktemp("two dates")
    pair = make_capture_pair(shape=(300, 400), n_lights=4, protrusion_density_light=150.0,
                             later=LaterSpec(seed=3, shift_px=(30.0, 20.0), rotation_deg=2.0, scale=1.0,
                                             new_per_cm2=40.0))
    return _truth_run(d / "run 2019", pair.a, 15.0), _truth_run(d / "run 2024", pair.b, 15.0)


def test_compare_captures_from_a_batch_macro(run_macro, two_dates, tmp_path):
    a, b = two_dates
    out = tmp_path / "changes out"
    result = run_macro('run("Compare Captures", "earlier=%s later=%s run=%s");\n'
                       'print("title: " + getTitle());\n'
                       'print("size " + getWidth() + " " + getHeight());\n'
                       'print("pixel " + getPixel(100, 100));\n'
                       'getLut(r, g, b); print("lut " + r[0] + "," + g[0] + "," + b[0] + " " + r[255] + "," + g[255] + "," + b[255]);\n'
                       'getMinAndMax(lo, hi); print("symmetric " + (lo == -hi));\n'
                       'n = 0; bar = 0; for (i = 0; i < Overlay.size; i++) {Overlay.activateSelection(i);\n'
                       '  name = Roi.getName; if (startsWith(name, "calibration bar")) bar++; else if (endsWith(name, "(earlier)")) n++;}\n'
                       'print("outlines " + n + " bar " + (bar > 0));\n'
                       'print("rows " + Table.size("Changes - changes out"));\n'
                       'print("dates " + isOpen("albedo (earlier) - run 2019") + " " + isOpen("albedo (later) - run 2024"));\n'
                       'print("went on");\n' % (q(a), q(b), q(out)),
                       timeout=TIMEOUT).check()
    lines = result.stdout.splitlines()
    assert "went on" in lines
    assert "title: height change (um) - changes out" in lines
    # colour-mapped (blue - white - red, symmetric about 0), the bar beside the image: the canvas
    # is wider than the file by the bar's margin, and the pixels inside are the file's
    change = tifffile.imread(str(out / "height_change.tif"))
    size = [ln for ln in lines if ln.startswith("size ")][0].split()
    assert int(size[2]) == change.shape[0] and int(size[1]) > change.shape[1]
    assert float([ln for ln in lines if ln.startswith("pixel ")][0].split()[1]) == pytest.approx(
        float(change[100, 100]), abs=1e-4)
    assert "lut 33,102,172 178,24,43" in lines and "symmetric 1" in lines
    # one outline per earlier protrusion of the change table, coloured by status; the table open
    with open(out / "changes.csv", newline="") as fh:
        rows = list(csv.DictReader(fh))
    assert "outlines %d bar 1" % sum(1 for r in rows if r["id_a"]) in lines, lines
    assert "rows %d" % len(rows) in lines and "dates 1 1" in lines
    assert any(ln.startswith("uvps Compare Captures: ") and "outlines coloured by status" in ln
               for ln in lines), lines
    assert any(line.startswith("registration: similarity") for line in lines), result.stdout
    for name in ("registration.json", "changes.csv", "height_change.tif", "report.html", "run.json"):
        assert (out / name).is_file(), name
    reg = json.loads((out / "registration.json").read_text())
    assert reg["model"] == "similarity" and reg["rms_px"] < 0.3


def test_compare_captures_on_a_run_without_detection_fails_with_the_core_message(run_macro, two_dates,
                                                                                 tmp_path):
    a, _ = two_dates
    b = tmp_path / "no detection"
    b.mkdir()
    for f in ("albedo.tif", "depth.tif"):
        (b / f).write_bytes((a / f).read_bytes())
    result = run_macro('run("Compare Captures", "earlier=%s later=%s run=%s");\n'
                       % (q(a), q(b), q(tmp_path / "out")), timeout=TIMEOUT)
    assert result.returncode == PYTHON_EXCEPTION_STATUS, result.stdout + result.stderr
    assert "uvps Compare Captures failed (UVPSInputError)" in result.stdout
    assert "has no protrusions.csv" in result.stdout
