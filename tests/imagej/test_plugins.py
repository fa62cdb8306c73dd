"""The uvps menu items in the real ImageJ 1.x (Debian's ij.jar + Jython) under Xvfb.

Every test runs batch macros in a fresh JVM with uvps installed by scripts/install_fiji.py (see
conftest.py): a modal dialog halts the JVM (status 3), a failing menu item raises in Jython
(status 4). The capture is a small synthetic one with known protrusions (uvps.testing.synthetic).
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
#: One bridge call on the small capture takes seconds, the ten-step macro about 2 minutes on 2
#: cores; the margin is for a loaded machine.
TIMEOUT = 900


def q(path):
    """A path as an ImageJ macro option value (brackets keep spaces)."""
    return "[%s]" % path


@pytest.fixture(scope="module")
def capture_dir(tmp_path_factory):
    """A synthetic 240 x 320, 8-light RGB capture with ground truth, in a folder with a space."""
    from uvps.testing.synthetic import make_capture, write_capture

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


# --------------------------------------------------------------------------- whole runs


def _assert_same_image(path_a, path_b, atol):
    a, b = tifffile.imread(str(path_a)), tifffile.imread(str(path_b))
    assert a.shape == b.shape
    # rtol: float32 albedos of ~3.5e4 counts differ by their last bit (4e-3) between two runs
    np.testing.assert_allclose(a, b, atol=atol, rtol=1e-6, equal_nan=True)


#: A menu command that prints what only a person sees of the open height map, albedo and
#: normals of the run folder called "run folder".
PROBE = """from ij import IJ, WindowManager
depth = (WindowManager.getImage("height (um) - run folder")
         or WindowManager.getImage("relative height - run folder"))
print("depth title %s" % depth.getTitle())
lut = depth.getProcessor().getLut()
print("depth unit %s" % depth.getCalibration().getValueUnit().encode("ascii", "replace"))
print("depth lut %d,%d,%d %d,%d,%d" % (lut.getRed(0), lut.getGreen(0), lut.getBlue(0),
                                       lut.getRed(255), lut.getGreen(255), lut.getBlue(255)))
items = [depth.getOverlay().get(i) for i in range(depth.getOverlay().size())]
names = [r.getName() for r in items]
print("depth overlay %d protrusions, bar %s" % (
    len([n for n in names if n and n.startswith("auto ") and n.endswith(" - run folder")]),
    "calibration bar" in names))
print("bar unit %s" % [r.getText() for r in items
                       if r.getName() == "calibration bar unit"][0].encode("ascii", "replace"))
print("albedo type %d" % WindowManager.getImage("albedo - run folder").getType())
print("normals type %d" % WindowManager.getImage("normals - run folder").getType())
"""


def test_whole_pipeline_writes_flatfield_images_and_ome_zarr_when_ticked(run_macro, capture_dir, tmp_path):
    """The dialog's "flatfield" and "zarr" boxes reach the core: flatfield/ and the OME-Zarr stores
    are written, and run.json records both."""
    out = tmp_path / "run"
    run_macro('run("Run Whole Pipeline", "capture=[Folder or files] images=%s run=%s degree=4 flatfield zarr");\n'
              % (q(capture_dir), q(out)), timeout=TIMEOUT).check()
    assert len(list((out / "flatfield").glob("*.tif"))) == N_LIGHTS
    assert sorted(p.name for p in out.glob("*.ome.zarr")) == ["albedo.ome.zarr", "depth.ome.zarr",
                                                             "normals.ome.zarr"]
    params = json.loads((out / "run.json").read_text())["params"]
    assert params["ome_zarr"] is True and params["flatfield_images"] is True


def test_whole_pipeline_from_a_batch_macro(run_macro, capture_dir, reference_run, tmp_path,
                                           imagej_home, write_plugin):
    """Regions set, detect not ticked: the core detects anyway, and the protrusions it listed
    are shown (table, ROIs, overlay on the RGB albedo and on the height map, which has its value
    unit, a viridis LUT and a calibration bar); the core's warnings and detection counts are in
    the Log in the dialog's words."""
    write_plugin(imagej_home, "Test/Probe_Display.py", PROBE)
    out = tmp_path / "run folder"
    result = run_macro(
        'run("Run Whole Pipeline", "capture=[Folder or files] images=%s run=%s degree=4 '
        'integration=[Frankot-Chellappa (FFT)] regions=auto");\n'
        'print("rois " + roiManager("count"));\n'
        'print("rows " + Table.size("Protrusions - run folder"));\n'
        'print("lights " + Table.size("Lights - run folder"));\n'
        'selectImage("albedo - run folder");\n'
        'n = 0; a = 0; t = 0; for (i = 0; i < Overlay.size; i++) {Overlay.activateSelection(i); name = Roi.getName;\n'
        '  if (startsWith(name, "auto ")) n++; else if (endsWith(name, " tag")) t++; else if (startsWith(name, "area ")) a++;}\n'
        'run("Select None");\n'
        'print("overlay " + n);\nprint("areas " + a + " tags " + t);\n'
        'print("regions table " + Table.size("Regions - run folder"));\n'
        'getPixelSize(unit, pw, ph);\n'
        'print("pixel " + unit + " " + pw);\n'
        'run("Probe Display");\n' % (q(capture_dir), q(out)),
        timeout=TIMEOUT).check()
    lines = _log_lines(result)
    # What the core said reaches the Log, in the dialog's words (no CLI flag).
    diag = json.loads((out / "run.json").read_text()).get("diagnostics", {}).get("detect", {})
    kept = len(_read_csv(out / "protrusions.csv"))
    candidates = [ln for ln in lines
                  if ln.startswith("uvps Run Whole Pipeline detection: ") and "candidates" in ln]
    assert len(candidates) == 1, lines
    assert "%d protrusions kept" % kept in candidates[0]
    if diag:
        assert "%d candidates" % (kept + sum(diag["rejected"].values())) in candidates[0]
    assert any(ln.startswith("uvps Run Whole Pipeline lights: 8 lamps estimated from the images")
               for ln in lines), lines
    warnings = [ln for ln in lines if ln.startswith("uvps Run Whole Pipeline warning: ")]
    assert warnings and all("--" not in ln for ln in warnings), warnings
    assert any('field "Lights file"' in ln for ln in warnings), warnings
    # The height map and the albedo as a person sees them (the files are unchanged: below). Lamps
    # estimated on this small field leave the heights' scale open: run.json says relative, and the
    # window says so instead of um.
    relief = json.loads((out / "run.json").read_text())["relief"]["scale"]
    if relief == "relative":
        assert "depth title relative height - run folder" in lines, lines
        assert "depth unit relative" in lines and "bar unit relative height (no unit)" in lines, lines
    else:
        assert "depth title height (um) - run folder" in lines, lines
        assert "depth unit ?m" in lines or "depth unit um" in lines, lines
        assert "bar unit height (?m)" in lines, lines           # the unit on the colour bar
    assert "depth lut 68,1,84 253,231,37" in lines            # viridis, dark purple to yellow
    level = json.loads((out / "run.json").read_text())["level"]
    assert level["method"] == "plane"                           # levelled by default, and the Log says so
    assert ("uvps: height levelled: its best plane removed (x %+.3g, y %+.3g um/mm (x right, y up)); raw "
            "height = depth.tif + that plane (run.json level)"
            % (level["slope_x_um_per_mm"], level["slope_y_um_per_mm"])) in lines, lines
    assert "albedo type 4" in lines                             # ImagePlus.COLOR_RGB
    assert "normals type 4" in lines                            # colour, not 3 grey slices
    for name in ("normals.tif", "albedo.tif", "depth.tif", "lights.json", "protrusions.csv",
                 "regions_labels.tif", "run.json"):
        assert (out / name).is_file(), name
    n = len(_read_csv(out / "protrusions.csv"))
    assert n > 0
    assert "rois %d" % n in lines and "rows %d" % n in lines and "overlay %d" % n in lines
    assert "depth overlay %d protrusions, bar True" % n in lines
    # the colour areas the report names ("area 5") outlined and tagged on the albedo, and the
    # Regions table (one row per area and "all")
    areas = [r for r in _read_csv(out / "regions.csv") if r["label"] != "all"]
    assert areas and "areas %d tags %d" % (len(areas), len(areas)) in lines, lines
    assert "regions table %d" % (len(areas) + 1) in lines
    assert "lights %d" % N_LIGHTS in lines
    assert any(line.split() in (["pixel", unit, "15"] for unit in ("micron", "microns", u"\u00b5m"))
               for line in lines), lines
    # The bridge passed the same request as a direct call: same numbers.
    _assert_same_image(out / "albedo.tif", reference_run / "albedo.tif", atol=1e-5)
    _assert_same_image(out / "depth.tif", reference_run / "depth.tif", atol=1e-3)
    assert n == len(_read_csv(reference_run / "protrusions.csv"))
    assert not any(p.exists() for p in _request_dirs(result)), "request folders left behind"


def _request_dirs(result):
    """The request folders of the bridge calls the Log shows (``uvps: python -m uvps bridge``)."""
    marker = " -m uvps bridge "
    return [Path(line.split(marker, 1)[1].strip('"')).parent for line in _log_lines(result)
            if line.startswith("uvps: ") and marker in line]


# --------------------------------------------------------------------------- run info


def test_run_info_writes_the_run_folder_description_to_the_log(run_macro, reference_run,
                                                               tmp_path):
    """Run Info: one new menu script over the generic menus.run_command; the core's answer
    (``uvps info``) goes to the Log, and the run folder is left as it was."""
    before = sorted(p.name for p in reference_run.iterdir())
    n = len(_read_csv(reference_run / "protrusions.csv"))
    result = run_macro('run("Run Info", "run=%s");\nprint("went on");\n' % q(reference_run),
                       timeout=TIMEOUT).check()
    lines = _log_lines(result)
    assert "went on" in lines
    assert sorted(p.name for p in reference_run.iterdir()) == before
    assert not any(p.exists() for p in _request_dirs(result))
    assert "made by:    uvps run (version" in result.stdout, result.stdout
    # The run's own counts, once (not "N candidates, N kept, 0 rejected" from the row count).
    rejected = sum(json.loads((reference_run / "run.json").read_text())["diagnostics"]["detect"]
                   ["rejected"].values())
    assert ("protrusions: %d kept of %d candidates (%d rejected by the detection's rules)"
            % (n, n + rejected, rejected)) in lines, result.stdout
    assert not [ln for ln in lines if "detection:" in ln], result.stdout


def test_run_info_on_a_folder_that_is_no_run_fails_with_the_core_message(run_macro, tmp_path):
    empty = tmp_path / "not a run"
    empty.mkdir()
    result = run_macro('run("Run Info", "run=%s");\n' % q(empty), timeout=TIMEOUT)
    assert result.returncode == PYTHON_EXCEPTION_STATUS, result.stdout + result.stderr
    assert ("uvps Run Info failed (UVPSInputError): %s is not a run folder: it has no run.json"
            % empty) in result.stdout


def test_each_menu_item_from_a_batch_macro(run_macro, capture_dir, reference_run, tmp_path):
    out = tmp_path / "steps"
    points = tmp_path / "clicks.csv"
    manual = _read_csv(reference_run / "protrusions.csv")[:3]
    points.write_text("x_px,y_px\n" + "".join("%s,%s\n" % (r["x_px"], r["y_px"]) for r in manual))
    steps = [
        ('Estimate Lights', 'capture=[Folder or files] images=%s run=%s degree=4'
         % (q(capture_dir), q(out)), ["lights.json", "dropoff.tif"]),
        ('Flat Field', 'capture=[Folder or files] images=%s run=%s degree=4'
         % (q(capture_dir), q(out)), ["flatfield"]),
        ('Normals and Albedo', 'capture=[Folder or files] images=%s run=%s degree=4'
         % (q(capture_dir), q(out)), ["normals.tif", "albedo.tif", "gradients.tif"]),
        ('Integrate Height', 'run=%s integration=[DCT Poisson (Neumann)] level=form' % q(out),
         ["depth.tif"]),
        ('Colour Areas', 'run=%s source=Automatic number=0' % q(out),
         ["regions_labels.tif", "regions.csv"]),
        ('Detect Protrusions', 'run=%s regions=%s sensitivity=5 smallest=30'
         % (q(out), q(out / "regions_labels.tif")),
         ["protrusions.csv", "protrusions_labels.tif"]),
        ('Wand Count', 'run=%s points=%s method=imagej tolerance=0.05 connectivity=8' % (q(out), q(points)),
         ["protrusions_manual.csv", "protrusions_manual_labels.tif"]),
        ('Compare Counts', 'run=%s first=%s second=%s match=0'
         % (q(out), q(out / "protrusions_manual.csv"), q(out / "protrusions.csv")),
         ["comparison.csv"]),
        ('Statistics and Report', 'run=%s bins=100' % q(out), ["report.html", "regions.csv"]),
        ('Relight', 'run=%s azimuth=315 elevation=15' % q(out), ["relight.tif"]),
    ]
    macro = "".join('run("%s", "%s");\nprint("done %s");\n' % (cmd, opts.replace('"', '\\"'), cmd)
                    for cmd, opts, _ in steps)
    macro += 'print("tables " + Table.size("Lights - steps") + " " + Table.size("Comparison - steps"));\n'
    macro += 'selectImage("relight az315 el15 - steps");\nprint("relight " + bitDepth());\n'
    result = run_macro(macro, timeout=TIMEOUT).check()
    lines = _log_lines(result)
    for cmd, _, files in steps:
        assert "done %s" % cmd in lines
        for name in files:
            assert (out / name).exists(), (cmd, name)
    assert "tables %d %d" % (N_LIGHTS, len(_read_csv(out / "comparison.csv"))) in lines
    assert "relight 24" in lines                                # an RGB image, not 3 grey slices
    # the Level field reached the core, which recorded what it removed, and the Log says so
    assert json.loads((out / "run.json").read_text())["level"]["method"] == "form"
    assert any(ln.startswith("uvps: height levelled: a Legendre form of degree 3 removed (best plane x ")
               for ln in lines), lines
    # Steps after Estimate Lights reuse its lamps, and say so.
    for title in ("Flat Field", "Normals and Albedo"):
        assert ("uvps %s lights: %d lamps from the run folder's %s (not estimated again; give a "
                "Lights file to use others)" % (title, N_LIGHTS, out / "lights.json")) in lines
    assert any(ln.startswith("uvps Detect Protrusions detection: ") and "candidates" in ln
               for ln in lines), lines
    lights = json.loads((out / "lights.json").read_text())
    assert len(lights["lights"]) == N_LIGHTS
    assert tifffile.imread(str(out / "relight.tif")).shape[-2:] == SHAPE
    assert tifffile.imread(str(out / "depth.tif")).shape == SHAPE
    # Estimated azimuths follow the lamps of the synthetic capture (the right images were sent).
    truth = json.loads((capture_dir / "truth" / "truth.json").read_text())
    pos = np.asarray(truth["light_positions_mm"])
    az_true = np.degrees(np.arctan2(pos[:, 1], pos[:, 0]))
    az = np.asarray([light["azimuth_deg"] for light in lights["lights"]])
    diff = (az - az_true + 180.0) % 360.0 - 180.0
    # A 3.6 x 4.8 mm field pins each lamp to within ~20 degrees (scripts/benchmark_core.py measures
    # the real-size accuracy); images sent out of order or the wrong stack would be off by 45-180.
    assert np.abs(diff).mean() < 12.0 and np.all(np.abs(diff) < 30.0), diff


# --------------------------------------------------------------------------- failures


def _core_error(command, inputs, params, out):
    """The message the core itself gives for this bad input (run in-process)."""
    from uvps.commands import COMMANDS
    from uvps.errors import UVPSInputError

    with pytest.raises(UVPSInputError) as info:
        COMMANDS[command](inputs, params, out)
    return str(info.value).splitlines()[0]


def test_a_folder_with_two_images_fails_the_macro_with_the_core_message(
        run_macro, capture_dir, tmp_path):
    bad = tmp_path / "two images"
    bad.mkdir()
    for name in ("uv_00.tif", "uv_01.tif"):
        (bad / name).write_bytes((capture_dir / name).read_bytes())
    message = _core_error("run", {"images": [str(bad)]}, {}, tmp_path / "direct")
    out = tmp_path / "run"
    result = run_macro('run("Run Whole Pipeline", "capture=[Folder or files] images=%s run=%s");\n'
                       'print("macro went on");\n' % (q(bad), q(out)), timeout=TIMEOUT)
    assert result.returncode == PYTHON_EXCEPTION_STATUS, result.stdout + result.stderr
    assert message in result.stdout
    assert "uvps Run Whole Pipeline failed (UVPSInputError): " + message in result.stdout
    assert "macro went on" not in result.stdout
    assert not (out / "normals.tif").exists()
    # A failed call's request folder is deleted too (unless UVPS_KEEP_FAILED_REQUESTS is set).
    dirs = _request_dirs(result)
    assert len(dirs) == 1 and not dirs[0].exists()
    assert "request folder kept" not in result.stdout


def test_a_light_file_with_the_wrong_count_fails_with_the_core_message(
        run_macro, capture_dir, tmp_path, monkeypatch):
    lines = (capture_dir / "lights.lp").read_text().splitlines()
    lp = tmp_path / "seven lights.lp"
    lp.write_text("\n".join([str(len(lines) - 2)] + lines[1:-1]) + "\n")
    message = _core_error("normals", {"images": [str(capture_dir)]}, {"lights": str(lp)},
                          tmp_path / "direct")
    # With UVPS_KEEP_FAILED_REQUESTS=1 a failed call keeps its request folder and logs it.
    monkeypatch.setenv("UVPS_KEEP_FAILED_REQUESTS", "1")
    result = run_macro('run("Normals and Albedo", "capture=[Folder or files] images=%s run=%s '
                       'lights=%s");\n' % (q(capture_dir), q(tmp_path / "run"), q(lp)),
                       timeout=TIMEOUT)
    assert result.returncode == PYTHON_EXCEPTION_STATUS, result.stdout + result.stderr
    assert "uvps Normals and Albedo failed (UVPSInputError): " + message in result.stdout
    dirs = _request_dirs(result)
    assert len(dirs) == 1 and (dirs[0] / "request.json").is_file()
    assert "uvps: request folder kept for inspection: %s" % dirs[0] in result.stdout
    (dirs[0] / "request.json").unlink()
    (dirs[0] / "response.json").unlink()
    dirs[0].rmdir()


# --------------------------------------------------------------------------- manual method


@pytest.fixture
def truth_run(capture_dir, tmp_path):
    """A run folder holding the capture's true albedo and height (what the wand works on)."""
    run = tmp_path / "truth run"
    run.mkdir()
    (run / "albedo.tif").write_bytes((capture_dir / "truth" / "albedo.tif").read_bytes())
    (run / "depth.tif").write_bytes((capture_dir / "truth" / "height_um.tif").read_bytes())
    rows = sorted(_read_csv(capture_dir / "truth" / "protrusions.csv"),
                  key=lambda r: -float(r["width_um"]))
    return run, rows[:5]


def _check_manual(run, clicked):
    found = [r for r in _read_csv(run / "protrusions_manual.csv") if r["counted"] == "1"]
    assert len(found) == len(clicked)
    for truth in clicked:
        x, y, w = float(truth["x_px"]), float(truth["y_px"]), float(truth["width_um"])
        near = [r for r in found if (float(r["x_px"]) - x) ** 2 + (float(r["y_px"]) - y) ** 2
                < (w / 15.0 / 2) ** 2]
        assert len(near) == 1, (truth, found)
        assert abs(float(near[0]["width_um"]) - w) < 0.3 * w


def test_wand_count_from_a_point_selection(run_macro, truth_run):
    run, clicked = truth_run
    xs = [float(r["x_px"]) for r in clicked]
    ys = [float(r["y_px"]) for r in clicked]
    # One protrusion clicked twice: still one protrusion.
    xs.append(xs[0] + 1.0)
    ys.append(ys[0])
    result = run_macro(
        'open("%s");\n'
        'makeSelection("point", newArray(%s), newArray(%s));\n'
        'run("Wand Count", "run=%s method=imagej tolerance=0.05 connectivity=8");\n'
        'print("rois " + roiManager("count"));\n'
        'print("rows " + Table.size("Manual protrusions - truth run"));\n'
        'selectImage("albedo - truth run");\nroiManager("select", 0);\n'
        'print("type " + selectionType() + " " + Roi.getName);\n'
        % (run / "albedo.tif", ",".join("%.2f" % v for v in xs), ",".join("%.2f" % v for v in ys),
           q(run)), timeout=TIMEOUT).check()
    lines = _log_lines(result)
    assert "uvps Wand Count: %d protrusions" % len(clicked) in lines
    # the repeated click stays in the table as a click (counted 0), with no outline
    assert "rois %d" % len(clicked) in lines and "rows %d" % (len(clicked) + 1) in lines
    # Outlines traced in the label image (4 = traced), not circles.
    assert "type 4 manual 1 - truth run" in lines
    _check_manual(run, clicked)


#: A menu command that prints the title and value unit of every open image.
PROBE_UNITS = """from ij import WindowManager
for i in WindowManager.getIDList():
    imp = WindowManager.getImage(i)
    print("image %s: %s" % (imp.getTitle(), imp.getCalibration().getValueUnit().encode("ascii", "replace")))
"""


def test_wand_count_from_a_points_csv(run_macro, truth_run, tmp_path, imagej_home, write_plugin):
    """A user's ROI stays in the ROI Manager; a re-run replaces the earlier run's outlines; a
    second run folder gets its own table, ROIs and windows (named by run, never mixed); a run
    whose height scale is relative (run.json relief.scale) shows "relative height", no um."""
    import shutil

    run, clicked = truth_run
    other = run.parent / "other run"
    shutil.copytree(str(run), str(other))
    (other / "run.json").write_text(json.dumps({"command": "run", "relief": {
        "scale": "relative", "lamps": "estimated", "reason": "the lamps' elevation is not pinned"}}))
    points = tmp_path / "my clicks.csv"
    points.write_text("x_px,y_px\n" + "".join("%s,%s\n" % (r["x_px"], r["y_px"]) for r in clicked[:3]))
    points.write_text(points.read_text() + "".join("%s,%s\n" % (r["x_px"], r["y_px"]) for r in clicked[3:]))
    write_plugin(imagej_home, "Test/Probe_Units.py", PROBE_UNITS)
    wand = 'run("Wand Count", "run=%s points=%s method=imagej tolerance=0.05 connectivity=4");\n'
    result = run_macro('newImage("user", "8-bit black", 320, 240, 1);\n'
                       'makeRectangle(1, 1, 20, 20);\nroiManager("add");\n'
                       + wand % (q(run), q(points)) + wand % (q(run), q(points))
                       + wand % (q(other), q(points)) +
                       'print("rois " + roiManager("count"));\n'
                       'print("tables " + Table.size("Manual protrusions - truth run") + " "'
                       ' + Table.size("Manual protrusions - other run"));\n'
                       'run("Probe Units");\n',
                       timeout=TIMEOUT).check()
    lines = _log_lines(result)
    assert "uvps Wand Count: %d protrusions" % len(clicked) in lines
    assert "rois %d" % (2 * len(clicked) + 1) in lines, lines
    assert "tables %d %d" % (len(clicked), len(clicked)) in lines, lines
    images = sorted(ln for ln in lines if ln.startswith("image "))
    assert images == sorted([
        "image user: Gray Value",
        "image albedo - truth run: Gray Value", "image albedo - other run: Gray Value",
        "image height (um) - truth run: ?m", "image relative height - other run: relative",
        "image albedo (R+G+B)/3 - truth run: Gray Value",
        "image albedo (R+G+B)/3 - other run: Gray Value"]), images
    _check_manual(run, clicked)


def test_wand_points_in_mm_are_read_by_the_cores_parser(run_macro, truth_run, tmp_path):
    """x_mm, y_mm are millimetres (Fiji's own parser read them as um: 1000x off, outside the
    image); the core's wand.read_seed_file reads them, the same as the CLI."""
    run, clicked = truth_run
    points = tmp_path / "clicks mm.csv"
    points.write_text("x_mm,y_mm\n" + "".join(
        "%.6f,%.6f\n" % ((float(r["x_px"]) + 0.5) * 0.015, (float(r["y_px"]) + 0.5) * 0.015)
        for r in clicked))
    result = run_macro('run("Wand Count", "run=%s points=%s method=imagej tolerance=0.05 connectivity=8");\n'
                       % (q(run), q(points)), timeout=TIMEOUT).check()
    assert ("uvps Wand Count: %d clicks from the file %s, read in mm (the albedo's pixel size is "
            "15 um) as the file's header says" % (len(clicked), points)) in _log_lines(result)
    _check_manual(run, clicked)


def test_wand_count_without_points_fails_clearly(run_macro, truth_run):
    run, _ = truth_run
    result = run_macro('run("Wand Count", "run=%s method=imagej tolerance=0.05 connectivity=8");\n' % q(run),
                       timeout=TIMEOUT)
    assert result.returncode == PYTHON_EXCEPTION_STATUS
    assert "uvps Wand Count failed (BridgeError): no points: click the protrusions" in result.stdout


def _far_from_protrusions(capture_dir, n):
    """``n`` points of the capture's bare paint, each as far as the field allows from any protrusion."""
    from scipy import ndimage as ndi

    rows = _read_csv(capture_dir / "truth" / "protrusions.csv")
    far = np.ones(SHAPE, bool)
    for r in rows:
        far[int(float(r["y_px"])), int(float(r["x_px"]))] = False
    dist = ndi.distance_transform_edt(far)
    dist[:10], dist[-10:], dist[:, :10], dist[:, -10:] = 0, 0, 0, 0
    out = []
    for _ in range(n):
        y, x = np.unravel_index(np.argmax(dist), dist.shape)
        out.append((int(x), int(y)))
        yy, xx = np.mgrid[:SHAPE[0], :SHAPE[1]]
        dist[(yy - y) ** 2 + (xx - x) ** 2 < 40 ** 2] = 0
    return out


def test_wand_count_counts_only_what_it_outlines(run_macro, truth_run, capture_dir):
    """Clicks on bare paint stay in the table as clicks (counted 0, and why), get no outline and are
    not counted; the Log says "7 clicks: 5 outlined, 2 not (bare paint at (x, y) px; ...)"."""
    run, clicked = truth_run
    bare = _far_from_protrusions(capture_dir, 2)
    xs = [float(r["x_px"]) for r in clicked] + [x for x, _ in bare]
    ys = [float(r["y_px"]) for r in clicked] + [y for _, y in bare]
    result = run_macro(
        'open("%s");\n'
        'makeSelection("point", newArray(%s), newArray(%s));\n'
        'run("Wand Count", "run=%s");\n'
        'print("rois " + roiManager("count"));\n'
        'print("rows " + Table.size("Manual protrusions - truth run"));\n'
        % (run / "albedo.tif", ",".join("%.2f" % v for v in xs), ",".join("%.2f" % v for v in ys), q(run)),
        timeout=TIMEOUT).check()
    lines = _log_lines(result)
    summary = ("uvps Wand Count: %d clicks: %d outlined, 2 not (bare paint at (%d, %d) px; bare paint at (%d, %d) px)"
               % (len(xs), len(clicked), bare[0][0], bare[0][1], bare[1][0], bare[1][1]))
    assert summary in lines, lines
    assert "uvps Wand Count: %d protrusions" % len(clicked) in lines
    assert "rois %d" % len(clicked) in lines and "rows %d" % len(xs) in lines, lines
    rows = _read_csv(run / "protrusions_manual.csv")
    assert [r["counted"] for r in rows] == ["1"] * len(clicked) + ["0", "0"]
    assert all(r["note"] and r["width_um"] == "" for r in rows[len(clicked):])
    _check_manual(run, clicked)


def _snapshot(folder):
    import hashlib

    return dict((str(p.relative_to(folder)), hashlib.sha256(p.read_bytes()).hexdigest())
                for p in sorted(folder.rglob("*")) if p.is_file())


@pytest.fixture
def run_with_manual_work(reference_run, capture_dir, tmp_path):
    """A run folder made by the core, with a wand count (real clicks) and its comparison made on it."""
    import shutil

    from uvps.commands import COMMANDS

    run = tmp_path / "my run"
    shutil.copytree(str(reference_run), str(run))
    rows = sorted(_read_csv(capture_dir / "truth" / "protrusions.csv"), key=lambda r: -float(r["width_um"]))[:4]
    COMMANDS["wand"]({"points": [[float(r["x_px"]), float(r["y_px"])] for r in rows]}, {}, run)
    COMMANDS["compare"]({"a": str(run / "protrusions_manual.csv"), "b": str(run / "protrusions.csv")}, {}, run)
    return run


@pytest.mark.parametrize("answer", ["Keep it and run", "Do not run"])
def test_run_whole_pipeline_asks_before_replacing_a_folder_with_manual_work(run_macro, run_with_manual_work,
                                                                            capture_dir, tmp_path, answer):
    """The question names the manual work; "Keep it and run" runs and keeps it, byte for byte, with
    the run it was measured on in earlier/; "Do not run" changes nothing and says cancelled."""
    run = run_with_manual_work
    before = _snapshot(run)
    shots = tmp_path / "shots"
    result = run_macro('run("Run Whole Pipeline", "capture=[Folder or files] images=%s run=%s degree=4 '
                       'regions=auto");\nprint("went on");\n' % (q(capture_dir), q(run)),
                       screenshot_dir=shots, props={"uvps.screenshot.button": answer}, timeout=TIMEOUT)
    lines = _log_lines(result)
    assert [p.name for p in result.screenshots] == ["Run_Whole_Pipeline_manual_work_in_the_run_folder.png"], \
        result.stderr
    if answer == "Do not run":
        # a cancel is no failure: one "cancelled" Log line, the macro stops there, ImageJ exits 0
        assert result.returncode == 0 and "went on" not in lines, result.stdout + result.stderr
        assert any(ln.startswith("uvps Run Whole Pipeline: cancelled: %s is unchanged" % run)
                   for ln in lines), lines
        assert _snapshot(run) == before
        return
    assert result.returncode == 0, result.stdout + result.stderr
    assert "went on" in lines
    (kept,) = sorted((run / "earlier").iterdir())
    for name in ("protrusions_manual.csv", "protrusions_manual_labels.tif", "comparison.csv", "run.json",
                 "albedo.tif", "depth.tif", "protrusions.csv"):
        assert _snapshot(kept)[name] == before[name], name
    assert not (run / "protrusions_manual.csv").exists()
    assert any("kept with that run in %s" % kept in ln for ln in lines), lines


def test_colour_areas_from_rois_in_the_roi_manager(run_macro, truth_run):
    run, _ = truth_run
    result = run_macro(
        'open("%s");\n'
        'makeRectangle(0, 0, 100, 240);\nroiManager("add");\n'
        'makeOval(150, 60, 120, 100);\nroiManager("add");\n'
        'run("Colour Areas", "run=%s source=[ROI Manager]");\n'
        'print("areas " + Table.size("Regions - truth run"));\n' % (run / "albedo.tif", q(run)),
        timeout=TIMEOUT).check()
    labels = tifffile.imread(str(run / "regions_labels.tif"))
    assert labels.shape == SHAPE
    assert set(np.unique(labels)) == {0, 1, 2}
    assert np.all(labels[:, :100] == 1)
    assert labels[110, 210] == 2 and labels[5, 300] == 0
    assert abs(np.sum(labels == 2) - np.pi * 60 * 50) < 0.03 * np.pi * 60 * 50
    assert "areas" in result.stdout


# --------------------------------------------------------------------------- the current stack


@pytest.fixture(scope="module")
def grey_capture_dir(tmp_path_factory):
    from uvps.testing.synthetic import make_capture, write_capture

    cap = make_capture(shape=SHAPE, n_lights=N_LIGHTS, rgb=False, seed=4)
    folder = tmp_path_factory.mktemp("grey") / "grey capture"
    write_capture(cap, folder, truth=False)
    return folder


def _azimuths(path):
    return np.asarray([light["azimuth_deg"] for light in json.loads(path.read_text())["lights"]])


def test_an_unsaved_stack_is_written_to_the_request_folder(run_macro, grey_capture_dir,
                                                           tmp_path):
    from uvps.commands import COMMANDS

    direct = tmp_path / "direct"
    COMMANDS["lights"]({"images": [str(grey_capture_dir)]}, {"degree": 4}, direct)
    out = tmp_path / "from stack"
    result = run_macro(
        'File.openSequence("%s/", " filter=uv_");\n'
        'print("slices " + nSlices);\n'
        'run("Estimate Lights", "capture=[Current stack] run=%s degree=4");\n'
        % (grey_capture_dir, q(out)), timeout=TIMEOUT).check()
    lines = _log_lines(result)
    assert "slices %d" % N_LIGHTS in lines
    written = [line.split("capture ", 1)[1] for line in lines if line.startswith("uvps: capture ")]
    assert len(written) == 1 and "uvps-request-" in written[0], lines
    # The copy of the stack went with its request folder once the response was read.
    assert not Path(written[0]).parent.exists()
    # Same pixels as the folder: the same lamps (the estimate samples pixels, so not bit-equal).
    diff = (_azimuths(out / "lights.json") - _azimuths(direct / "lights.json") + 180) % 360 - 180
    assert np.all(np.abs(diff) < 2.0), diff


def test_a_saved_stack_is_passed_by_its_file(run_macro, grey_capture_dir, tmp_path):
    stack = np.stack([tifffile.imread(str(p)) for p in sorted(grey_capture_dir.glob("uv_*.tif"))])
    # Not in ImageJ's working folder (tmp_path): a relative path must not work by chance.
    (tmp_path / "stacks").mkdir()
    path = tmp_path / "stacks" / "saved stack.tif"
    tifffile.imwrite(str(path), stack, imagej=True, resolution=(1 / 15.0, 1 / 15.0),
                     metadata={"unit": "um"})
    out = tmp_path / "run"
    result = run_macro('open("%s");\n'
                       'run("Estimate Lights", "capture=[Current stack] run=%s degree=4");\n'
                       % (path, q(out)), timeout=TIMEOUT).check()
    assert "uvps: capture %s" % path in _log_lines(result)
    assert len(json.loads((out / "lights.json").read_text())["lights"]) == N_LIGHTS


def _rgb_sequence_macro(capture_dir):
    """Open the RGB capture as File > Import > Image Sequence does: R, G, B as grey slices."""
    return 'File.openSequence("%s/", " filter=uv_");\nrename("seq");\n' % capture_dir


def test_an_rgb_image_sequence_as_grey_slices_is_refused_with_the_way_out(run_macro, capture_dir,
                                                                           tmp_path):
    """36 grey slices from 12 RGB files are not 36 lamps: refused before any long work."""
    result = run_macro(_rgb_sequence_macro(capture_dir) + 'print("slices " + nSlices);\n'
                       'run("Normals and Albedo", "capture=[Current stack] run=%s");\n'
                       % q(tmp_path / "run"), timeout=TIMEOUT)
    assert result.returncode == PYTHON_EXCEPTION_STATUS, result.stdout + result.stderr
    assert "slices %d" % (3 * N_LIGHTS) in result.stdout
    assert ("holds %d grey slices that are the R, G, B of %d RGB images" % (3 * N_LIGHTS, N_LIGHTS)
            in result.stdout)
    assert "Image > Hyperstacks > Stack to Hyperstack, channels=3" in result.stdout
    assert " -m uvps bridge " not in result.stdout            # the core never started


def test_the_current_stack_as_rgb_sequence_composite_or_rgb(run_macro, capture_dir, tmp_path):
    """The shapes users get from ImageJ give the albedo of the folder itself (known lamps)."""
    from uvps.commands import COMMANDS

    lp = capture_dir / "lights.lp"
    direct = tmp_path / "direct"
    COMMANDS["normals"]({"images": [str(capture_dir)]}, {"lights": str(lp)}, direct)
    opts = 'capture=[Current stack] lights=%s run=%s' % (q(lp), "%s")
    macro = _rgb_sequence_macro(capture_dir)
    # 1. the user says 3 channels; 2. the lights file lists a third as many lamps
    macro += ('run("Normals and Albedo", "%s channels=[3 (R, G, B per lamp)]");\n'
              % (opts % q(tmp_path / "said")))
    macro += 'selectImage("seq");\nrun("Normals and Albedo", "%s");\n' % (opts % q(tmp_path / "lp"))
    # 3. a composite (Stack to Hyperstack, channels=3); 4. an RGB stack
    macro += ('selectImage("seq");\nrun("Stack to Hyperstack...", "order=xyczt(default) channels=3 '
              'slices=%d frames=1 display=Composite");\n' % N_LIGHTS)
    macro += 'run("Normals and Albedo", "%s");\n' % (opts % q(tmp_path / "composite"))
    macro += ('selectImage("seq");\nrun("RGB Color", "slices keep");\nrename("rgb");\n'
              'run("Normals and Albedo", "%s");\n' % (opts % q(tmp_path / "rgb")))
    result = run_macro(macro, timeout=TIMEOUT).check()
    stacks = [ln for ln in _log_lines(result) if ln.startswith("uvps: current stack ")]
    assert stacks == [
        "uvps: current stack 'seq': 8 lamps, 3 channels, 16-bit, 320 x 240 pixels "
        "(Channels per lamp = 3)",
        "uvps: current stack 'seq': 8 lamps, 3 channels, 16-bit, 320 x 240 pixels "
        "(lights.lp lists 8 lamps)",
        "uvps: current stack 'seq': 8 lamps, 3 channels, 16-bit, 320 x 240 pixels "
        "(3 channels (composite or hyperstack))",
        "uvps: current stack 'rgb': 8 lamps, 3 channels, 8-bit RGB, 320 x 240 pixels "
        "(RGB image)"], stacks
    for name in ("said", "lp", "composite"):
        _assert_same_image(tmp_path / name / "albedo.tif", direct / "albedo.tif", atol=1e-6)
    assert tifffile.imread(str(tmp_path / "rgb" / "albedo.tif")).shape == (3,) + SHAPE


def test_a_misspelt_macro_key_is_an_error_naming_the_valid_keys(run_macro, tmp_path):
    result = run_macro('run("Relight", "run=%s azimut=45");\nprint("went on");\n'
                       % q(tmp_path / "run"))
    assert result.returncode == PYTHON_EXCEPTION_STATUS, result.stdout + result.stderr
    assert ("uvps Relight failed (MacroOptions): unknown macro key 'azimut' for Relight; the "
            "valid keys are: azimuth, elevation, run") in result.stdout
    assert "went on" not in result.stdout


def test_plain_imagej_batch_exits_non_zero_after_a_failed_item(run_macro, tmp_path):
    """`java -cp ij.jar:jython.jar:<Jython class> ij.ImageJ -batch macro.ijm`, as a user runs
    it: ImageJ itself exits 0 after the aborted macro (UVPS_EXIT_ON_ERROR=0 shows it); the
    menu item makes it exit 1."""
    macro = 'run("Relight", "run=%s azimuth=45");\nprint("went on");\n' % q(tmp_path / "none")
    result = run_macro(macro, plain=True, timeout=TIMEOUT)
    assert result.returncode == 1, result.stdout + result.stderr
    assert "uvps Relight failed (BridgeError): " in result.stdout
    assert "went on" not in result.stdout
    result = run_macro(macro, plain=True, env={"UVPS_EXIT_ON_ERROR": "0"}, timeout=TIMEOUT)
    assert result.returncode == 0 and "went on" not in result.stdout, result.stdout


def test_wand_points_in_um_repeated_clicks_and_the_wand_image(run_macro, truth_run, tmp_path):
    """Points as Analyze > Measure exports them on the calibrated albedo (um), one click inside
    an earlier click's selection: it is reported by number and position; the grey (R+G+B)/3
    image the wand uses opens for wanding by hand."""
    run, clicked = truth_run
    px = 15.0
    xs = [float(r["x_px"]) for r in clicked] + [float(clicked[0]["x_px"]) + 1.0]
    ys = [float(r["y_px"]) for r in clicked] + [float(clicked[0]["y_px"])]
    points = tmp_path / "Results.csv"
    points.write_text(" ,Area,Mean,X,Y\n" + "".join(
        "%d,0.1,5,%.3f,%.3f\n" % (i + 1, (x + 0.5) * px, (y + 0.5) * px)
        for i, (x, y) in enumerate(zip(xs, ys))))
    ix, iy = int(xs[1]), int(ys[1])
    result = run_macro('run("Wand Count", "run=%s points=%s method=imagej tolerance=0.05 connectivity=8");\n'
                       'selectImage("albedo (R+G+B)/3 - truth run");\n'
                       'print("grey " + bitDepth() + " " + d2s(getPixel(%d, %d), 6));\n'
                       % (q(run), q(points), ix, iy), timeout=TIMEOUT).check()
    lines = _log_lines(result)
    assert ("uvps Wand Count: %d clicks from the file %s, read in um (the albedo's pixel size is "
            "15 um): its X, Y fit the image only in um" % (len(xs), points)) in lines, lines
    # the repeated click: one line naming it, nothing else about it
    about = [ln for ln in lines if "#%d " % len(xs) in ln or "click %d " % len(xs) in ln]
    assert about == ["uvps Wand Count: %d clicks: %d outlined, 1 not (click %d repeats click 1 at (%d, %d) px)"
                     % (len(xs), len(clicked), len(xs), int(xs[-1] + 0.5), int(ys[-1] + 0.5))], lines
    assert "uvps Wand Count: %d protrusions" % len(clicked) in lines
    _check_manual(run, clicked)
    albedo = tifffile.imread(str(run / "albedo.tif")).astype(np.float64)
    grey = [ln for ln in lines if ln.startswith("grey ")]
    assert grey and grey[0].split()[1] == "32"
    assert abs(float(grey[0].split()[2]) - albedo[:, iy, ix].mean()) < 1e-5


def test_plain_imagej_runs_the_menu_items_offline(imagej_env, tmp_path):
    """`java -jar ij.jar -batch` (nothing else on the classpath, no network) on a folder filled by
    scripts/install_fiji.py: its Jython interpreter runs the .py menu items."""
    import os
    import subprocess

    from conftest import INSTALLER, IJ_JAR, make_imagej_home

    home = make_imagej_home(tmp_path / "ImageJ")
    subprocess.run([sys.executable, str(INSTALLER), str(home), "--python", sys.executable],
                   check=True, timeout=300, stdout=subprocess.PIPE)
    macro = tmp_path / "settings.ijm"
    macro.write_text('run("UVPS Settings", "python=%s");\nprint("went on");\n' % q(sys.executable))
    proc = subprocess.run([imagej_env.java, "-Duser.home=%s" % tmp_path, "-jar", str(IJ_JAR),
                           "-ijpath", str(home), "-batch", str(macro)],
                          env=dict(os.environ, DISPLAY=imagej_env.display), cwd=str(tmp_path),
                          stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                          universal_newlines=True, timeout=120, start_new_session=True)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert "uvps Settings: %s has uvps" % sys.executable in proc.stdout
    assert "went on" in proc.stdout.splitlines()


def test_a_request_refused_before_it_runs_leaves_no_request_folder(run_macro, capture_dir, tmp_path):
    """An RGB image sequence as grey slices is refused before the core starts: the request folder
    made for it is deleted, also in a plain `ImageJ -batch` (which ends the JVM with status 1)."""
    temp = tmp_path / "temp"
    temp.mkdir()
    macro = (_rgb_sequence_macro(capture_dir) +
             'run("Normals and Albedo", "capture=[Current stack] run=%s");\n' % q(tmp_path / "run"))
    for plain in (False, True):
        result = run_macro(macro, plain=plain, env={"TMPDIR": str(temp)}, timeout=TIMEOUT)
        assert result.returncode in (1, PYTHON_EXCEPTION_STATUS), result.stdout + result.stderr
        assert "grey slices that are the R, G, B" in result.stdout
        assert sorted(p.name for p in temp.glob("uvps-request-*")) == [], plain


@pytest.mark.parametrize("typed,words", [
    ("0.1", "holds 0.1 um, not a pixel size on a painting (1-1000 um); give it in micrometres "
            "(0.1 mm = 100 um)"),
    ("-100", "holds -100 um; a pixel size is positive (0 = from the image file)")])
def test_an_implausible_pixel_size_is_refused_naming_the_field(run_macro, capture_dir, tmp_path,
                                                              typed, words):
    """0.1 (mm typed into the um field) crashed the core; -100 was dropped and the core then
    asked for a CLI flag. Both are refused before the core starts, naming the dialog field, and
    a user's macro (not the test harness) gets one Log line, no Python or Java stack trace."""
    out = tmp_path / "run"
    result = run_macro('run("Run Whole Pipeline", "capture=[Folder or files] images=%s run=%s '
                       'pixel=%s regions=auto");\nprint("went on");\n' % (q(capture_dir), q(out), typed),
                       plain=True, env={"UVPS_EXIT_ON_ERROR": "0"}, timeout=TIMEOUT)
    assert ('uvps Run Whole Pipeline failed (BridgeError): the field "Pixel size on the painting" '
            + words) in result.stdout, result.stdout + result.stderr
    assert "went on" not in result.stdout
    assert " -m uvps bridge " not in result.stdout            # the core never started
    assert not out.exists()
    for trace in ("Traceback", "Exception in", "PluginError", "\tat "):
        assert trace not in result.stdout + result.stderr, trace


#: A menu command that prints the items of Plugins > UV Photometric Stereo, in order.
PROBE_MENU = """from ij import Menus
bar = Menus.getMenuBar()
for i in range(bar.getMenuCount()):
    if bar.getMenu(i).getLabel() == "Plugins":
        plugins = bar.getMenu(i)
        for j in range(plugins.getItemCount()):
            if plugins.getItem(j).getLabel() == "UV Photometric Stereo":
                menu = plugins.getItem(j)
                print("menu: " + " | ".join(menu.getItem(k).getLabel()
                                            for k in range(menu.getItemCount())))
"""


def test_the_menu_is_in_workflow_order(run_macro, imagej_home, write_plugin):
    """ImageJ sorts a plugins folder's scripts alphabetically ("Colour Areas" first); the
    installed plugins.config keeps the workflow order, with separators between the stages."""
    write_plugin(imagej_home, "Test/Probe_Menu.py", PROBE_MENU)
    result = run_macro('run("Probe Menu");\n').check()
    menus = [ln for ln in _log_lines(result) if ln.startswith("menu: ")]
    root = Path(__file__).resolve().parents[2]
    sys.path.insert(0, str(root / "scripts"))
    from install_fiji import menu_order     # the installed order, generated from the menu scripts

    scripts = [p.name for p in (root / "plugins" / "UV_Photometric_Stereo").glob("*.py")]
    expected = " | ".join(item.replace("_", " ") for item in menu_order(scripts))
    assert expected.startswith("Calibrate Lamps | Run Whole Pipeline | - | Estimate Lights")
    assert menus == ["menu: " + expected], result.stdout


#: A menu command that prints, for the ROI Manager and for the overlays of the albedo and height
#: windows of "truth run", how many protrusion outlines of each source and run they hold and in
#: which stroke colours.
PROBE_OUTLINES = """import re
from ij import WindowManager
from ij.plugin.frame import RoiManager

def tally(where, rois):
    counts, colours = {}, {}
    for roi in rois:
        m = re.match(r"^(auto|manual) [0-9]+ - (.+)$", roi.getName() or "")
        if m is None and where != "manager":
            continue  # the calibration bar
        key = "%s/%s" % (m.group(1), m.group(2)) if m else "other"
        counts[key] = counts.get(key, 0) + 1
        c = roi.getStrokeColor()
        colours.setdefault(key, set()).add("%d,%d,%d" % (c.getRed(), c.getGreen(), c.getBlue())
                                           if c is not None else "none")
    for key in sorted(counts):
        print("%s %s %d %s" % (where, key, counts[key], ";".join(sorted(colours[key]))))

tally("manager", (RoiManager.getInstance() or RoiManager()).getRoisAsArray())
for title in ("albedo - truth run", "height (um) - truth run"):
    imp = WindowManager.getImage(title)
    overlay = imp.getOverlay()
    tally(title.split(" ")[0], [overlay.get(i) for i in range(overlay.size())] if overlay else [])
print("probe done")
"""


def _probe_blocks(stdout):
    """The probe's lines, one set per run of the probe, in order."""
    blocks, current = [], set()
    for line in stdout.splitlines():
        if line == "probe done":
            blocks.append(current)
            current = set()
        elif line.split(" ")[0] in ("manager", "albedo", "height"):
            current.add(line)
    return blocks


def test_manual_and_automatic_outlines_are_kept_apart(run_macro, truth_run, tmp_path, imagej_home,
                                                       write_plugin):
    """Detect Protrusions then Wand Count on one run: the ROI Manager and the albedo's and height's
    overlays hold both kinds, named "auto N - <run>" / "manual N - <run>", red and yellow. Wand
    Count again replaces only the manual ones (their count does not double, the automatic ones
    stay); Wand Count on another run leaves this run's outlines alone; the user's ROI stays."""
    import shutil

    run, clicked = truth_run
    other = run.parent / "other run"
    shutil.copytree(str(run), str(other))
    points = tmp_path / "clicks.csv"
    points.write_text("x_px,y_px\n" + "".join("%s,%s\n" % (r["x_px"], r["y_px"]) for r in clicked))
    write_plugin(imagej_home, "Test/Probe_Outlines.py", PROBE_OUTLINES)
    wand = 'run("Wand Count", "run=%s points=%s");\n'
    result = run_macro('newImage("user", "8-bit black", 320, 240, 1);\n'
                       'makeRectangle(1, 1, 20, 20);\nroiManager("add");\n'
                       'run("Detect Protrusions", "run=%s");\n' % q(run)
                       + wand % (q(run), q(points)) + 'run("Probe Outlines");\n'
                       + wand % (q(run), q(points)) + wand % (q(other), q(points))
                       + 'run("Probe Outlines");\n'
                       + 'run("Detect Protrusions", "run=%s");\n' % q(run)
                       + 'run("Probe Outlines");\n',
                       timeout=TIMEOUT).check()
    n_auto = len(_read_csv(run / "protrusions.csv"))
    n_manual = len(_read_csv(run / "protrusions_manual.csv"))
    assert n_auto > 0 and n_manual == len(clicked) and n_auto != n_manual
    red, yellow = "255,0,0", "255,220,0"
    both = {"%s auto/truth run %d %s" % (w, n_auto, red) for w in ("manager", "albedo", "height")} \
        | {"%s manual/truth run %d %s" % (w, n_manual, yellow) for w in ("manager", "albedo", "height")}
    first, second, third = _probe_blocks(result.stdout)
    assert first == both | {"manager other 1 none"}, first          # and the user's rectangle
    # Wand Count again on the same run, and on another run: this run's outlines unchanged
    assert second - first == {"manager manual/other run %d %s" % (len(clicked), yellow)}, second
    assert first <= second
    # Detect again: only the automatic ones replaced
    assert third == second, third
