"""Element Maps (uvps elements) from a batch macro in a real ImageJ."""
import json

import numpy as np
import pytest
import tifffile

from conftest import PYTHON_EXCEPTION_STATUS
from uvps.core.elements import registration_error_map_px
from uvps.files.tables import write_label_tiff
from uvps.testing.synthetic import SyntheticSpec, make_capture, render_element_maps, write_truth_run

pytestmark = pytest.mark.imagej

TIMEOUT = 600
PX = 15.0


def q(path):
    return "[%s]" % path


@pytest.fixture(scope="module")
def run_and_maps(tmp_path_factory):
    d = tmp_path_factory.mktemp("element maps")
    cap = make_capture(SyntheticSpec(shape=(300, 400), n_lights=4, seed=1, n_regions=4))
    run = write_truth_run(cap, d / "run with areas", pixel_size_um=PX)
    write_label_tiff(run / "regions_labels.tif", cap.regions, pixel_size_um=PX)
    truth = render_element_maps(cap, step_um=100.0, spot_um=400.0, margin_mm=1.0, rotation_deg=2.0,
                                shift_mm=(0.4, -0.3), seed=2)
    maps = d / "xrf maps"
    maps.mkdir()
    for name, m in zip(truth.maps.names, truth.maps.data):
        tifffile.imwrite(maps / ("%s.tif" % name), m.astype(np.float32))
    return cap, run, maps, truth


def test_element_maps_from_a_batch_macro(run_macro, run_and_maps, tmp_path):
    cap, run, maps, truth = run_and_maps
    out = tmp_path / "elements out"
    result = run_macro('run("Element Maps", "source=%s element=%s scan=100 spot=400 run=%s");\n'
                       'print("front: " + getTitle() + " " + nSlices + " " + is("composite"));\n'
                       'selectImage("element maps (run frame)");\n'
                       'print("title: " + getTitle());\nprint("slices: " + nSlices);\n'
                       'for (i = 1; i <= nSlices; i++) {setSlice(i); print("label " + i + ": " + getInfo("slice.label"));}\n'
                       '\nprint("went on");\n'
                       % (q(run), q(maps), q(out)), timeout=TIMEOUT).check()
    lines = result.stdout.splitlines()
    assert "went on" in lines
    assert "title: element maps (run frame)" in lines
    # the composite in front: lead (the soaps' metal) in red, then the next maps of the stack
    names = sorted(truth.maps.names)
    lead = [n for n in names if n.startswith("Pb")][0]
    rest = [n for n in names if n != lead][:2]
    assert "front: element maps (run frame) (%s) 3 1" % "/".join([lead] + rest) in lines, lines
    assert "uvps Element Maps: composite red %s, green %s, blue %s (choose with Red, Green, Blue element)" \
        % tuple([lead] + rest) in lines
    assert "slices: 4" in lines
    assert [ln for ln in lines if ln.startswith("label ")] == ["label %d: %s" % (i + 1, n) for i, n in
                                                              enumerate(sorted(truth.maps.names))]  # a folder: by name
    assert any(line.startswith("registration: automatic") for line in lines), result.stdout
    for name in ("registration.json", "elements.tif", "elements_by_area.csv", "elements_by_protrusion.csv",
                 "element_correlation.csv", "report.html", "run.json"):
        assert (out / name).is_file(), name
    reg = json.loads((out / "registration.json").read_text())
    err = registration_error_map_px(np.array(reg["map_to_run"]), truth.map_to_run, truth.maps.shape,
                                    cap.regions.shape)
    assert err < 0.5


def test_element_maps_without_a_step_fail_with_the_core_message(run_macro, run_and_maps, tmp_path):
    _, run, maps, _ = run_and_maps
    result = run_macro('run("Element Maps", "source=%s element=%s run=%s");\n'
                       % (q(run), q(maps), q(tmp_path / "out")), timeout=TIMEOUT)
    assert result.returncode == PYTHON_EXCEPTION_STATUS, result.stdout + result.stderr
    assert "uvps Element Maps failed (UVPSInputError)" in result.stdout
    assert "give the scan's step" in result.stdout
    assert not (tmp_path / "out").exists()
