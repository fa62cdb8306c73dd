"""The commands (uvps.commands): the registry, step by step against the whole run, the demo."""
import json

import numpy as np
import pytest
import tifffile

from uvps import commands
from uvps.commands import COMMANDS, info
from uvps.commands import protrusions as protrusion_commands
from uvps.files.runfolder import read_run
from uvps.testing.synthetic import make_capture, write_capture


@pytest.fixture(scope="module")
def synthetic():
    return make_capture(shape=(200, 260), n_lights=8, seed=7)


def test_every_declared_command_is_registered_once_by_name_and_alias():
    declared = [s for specs in commands.MODULES for s in specs]
    assert len({s.name for s in declared}) == len(declared)
    for s in declared:
        assert COMMANDS[s.name] is s and all(COMMANDS[a] is s for a in s.aliases)
    assert {"run", "lights", "normals", "detect", "wand", "stats", "report", "info"} <= set(COMMANDS)
    assert COMMANDS["info"] in info.SPECS and COMMANDS["detect"] in protrusion_commands.SPECS


@pytest.mark.slow
def test_step_by_step_reuses_the_folders_lamps_and_matches_the_whole_run(synthetic, tmp_path):
    """`lights` then `normals` into one run folder: the normals step takes the folder's lights.json
    (no second estimate) and gives the normals `run` gives."""
    write_capture(synthetic, tmp_path / "cap")
    images = {"images": [str(tmp_path / "cap")]}
    whole, steps = tmp_path / "whole", tmp_path / "steps"
    COMMANDS["run"](images, {}, whole)
    COMMANDS["lights"](images, {}, steps)
    res = COMMANDS["normals"](images, {}, steps)
    assert res.diagnostics["lights_file"] == str(steps / "lights.json")
    assert res.diagnostics["lights"]["source"] == "positions"          # read, not estimated again
    a = read_run(whole, need=("normals",)).normals
    b = read_run(steps, need=("normals",)).normals
    assert np.nanmax(np.abs(a - b)) < 1e-5             # equal to float32 precision
    # asked to, the normals step estimates the lamps again
    again = COMMANDS["normals"](images, {"lights": "estimate"}, steps)
    assert again.diagnostics["lights"]["source"] == "estimated"


@pytest.mark.slow
def test_demo_makes_a_capture_and_runs_everything_on_it(tmp_path):
    """`uvps demo` (README's first command) on a small capture: the capture, its sphere capture and
    calibration (the calibrated route), the run with that calibration and its report."""
    out = tmp_path / "demo"
    result = COMMANDS["demo"]({}, {"shape": (300, 400), "n_lights": 8}, out)
    for f in ("capture", "spheres", "calibration/lights.json", "normals.tif", "depth.tif", "lights.json", "run.json",
              "protrusions.csv", "report.html"):
        assert (out / f).exists(), f
    run = json.loads((out / "run.json").read_text())
    assert run["relief"]["scale"] == "absolute" and run["relief"]["lamps"] == "calibration"
    assert run["diagnostics"]["calibration"]["route"] == "spheres" and not run["warnings"]
    lamps = np.array([lp["position_mm"] for lp in json.loads((out / "lights.json").read_text())["lights"]])
    truth = np.array(result.diagnostics["truth_light_positions_mm"])
    cos = np.sum(lamps * truth, axis=1) / np.linalg.norm(lamps, axis=1) / np.linalg.norm(truth, axis=1)
    # spheres of 30 px on this 300 x 400 frame: within 0.9 deg (the full-size demo's 60 px: see the README)
    assert np.degrees(np.arccos(np.clip(cos, -1, 1))).max() < 1.5
    assert run["diagnostics"]["additive"]["source"] == "estimated" and run["timings_s"]["lights"] > 0
    with tifffile.TiffFile(out / "depth.tif") as t:
        xres = t.pages[0].tags["XResolution"].value
        assert abs(xres[1] / xres[0] - 30.0) < 1e-6          # the demo's 30 um pixel: an 18 x 24 mm field at full size
    assert len(result.diagnostics["truth_light_positions_mm"]) == 8


def test_run_with_a_label_tiff_counts_in_those_areas(synthetic, tmp_path):
    """`run --regions labels.tif`: the run folder records the given areas (regions_labels.tif and
    regions.csv with their names), so statistics count per area, not over the whole image."""
    from uvps.files.io import write_imagej_tiff

    write_capture(synthetic, tmp_path / "cap")
    labels = np.zeros(synthetic.height_um.shape, np.uint8)
    labels[:, :130], labels[:, 130:] = 1, 2
    write_imagej_tiff(tmp_path / "areas.tif", labels, axes="YX", pixel_size_um=synthetic.spec.pixel_size_um)
    (tmp_path / "areas_names.csv").write_text("label,name\n1,left\n2,right\n")
    out = tmp_path / "run"
    COMMANDS["run"]({"images": [str(tmp_path / "cap")]},
                    {"regions": str(tmp_path / "areas.tif"), "lights": str(tmp_path / "cap" / "lights_positions_mm.csv")},
                    out)
    np.testing.assert_array_equal(tifffile.imread(out / "regions_labels.tif"), labels)
    rows = (out / "regions.csv").read_text().splitlines()
    assert rows[1].split(",")[1] == "left" and rows[2].split(",")[1] == "right", rows[:3]
    table = (out / "protrusions.csv").read_text().splitlines()
    header = table[0].split(",")
    in_area = [r.split(",")[header.index("region")] for r in table[1:]]
    assert set(in_area) <= {"1", "2", "left", "right"} and len(in_area) > 0


def test_a_command_imports_only_the_module_that_declares_it():
    """``uvps calibrate`` imports uvps.commands.calibrate, not the pipeline behind run or batch (1.4 s of
    every command when all were imported); the whole registry still builds and agrees with DECLARED_IN."""
    import subprocess
    import sys

    code = ("import sys\nfrom uvps.cli import main\ntry:\n    main(['calibrate', '--help'])\nexcept SystemExit:\n    pass\n"
            "print(sorted(m for m in sys.modules if m.startswith(('uvps.commands.', 'uvps.workflow', 'uvps.core.pipeline'))))")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert r.stdout.strip().splitlines()[-1] == "['uvps.commands.calibrate']"
    assert set(commands.DECLARED_IN) == set(COMMANDS)
    assert all(commands.DECLARED_IN[n] == COMMANDS[n].run.__module__.rsplit(".", 1)[-1]
               for n in COMMANDS if COMMANDS[n].run is not None and COMMANDS[n].run.__module__.startswith("uvps.commands."))
