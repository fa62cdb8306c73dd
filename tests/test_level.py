"""Levelling (uvps.core.level): the best plane (or a form) removed from depth.tif by default, what was
removed recorded in run.json so the raw height is rebuilt, the flag through the CLI, integrate, the
report and the Fiji side's Log line."""
import csv
import json
import math
import sys
from pathlib import Path

import numpy as np
import pytest
import tifffile

from uvps.commands import COMMANDS
from uvps.core.level import LEVELS, Levelling, fit_surface, level_height, raw_height, tilt_slope_um_per_mm
from uvps.core.pipeline import RunOptions, run
from uvps.errors import UVPSInputError
from uvps.testing.synthetic import make_capture, write_capture

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "jython_lib"))
from uvps_fiji import bridge_logic  # noqa: E402

PX = 30.0


def _plane(h, px=PX):
    """Slopes (um/mm, x right, y up) of the plain least-squares plane over the finite pixels."""
    c = fit_surface(h, degree=1, robust=False)
    m, n = h.shape
    return c[1, 0] * 2 / ((n - 1) * px / 1000), c[0, 1] * 2 / ((m - 1) * px / 1000)


def _grid(shape=(200, 300)):
    rows, cols = np.mgrid[0:shape[0], 0:shape[1]]
    return cols * PX / 1000.0, (shape[0] - 1 - rows) * PX / 1000.0     # x right, y up (mm)


def test_a_known_plane_is_found_in_the_projects_frame_and_the_raw_is_rebuilt_exactly():
    x, y = _grid()
    h = (2.8 * x - 0.6 * y + 5.0).astype(np.float32)
    h[10:20, 30:40] = np.nan                                           # outside the field
    for method in LEVELS:
        out, lev = level_height(h, method=method, pixel_size_um=PX)
        assert lev.slope_x_um_per_mm == pytest.approx(2.8, abs=1e-6)
        assert lev.slope_y_um_per_mm == pytest.approx(-0.6, abs=1e-6)   # y up: rises toward row 0
        assert np.isnan(out[15, 35]) and np.nanmedian(out) == pytest.approx(0.0, abs=1e-5)
        # raw = levelled + the recorded surface, also through run.json's JSON
        back = raw_height(out, json.loads(json.dumps(lev.to_json())))
        np.testing.assert_allclose(back, h, atol=1e-4)
        if method == "none":
            assert np.nanmax(out) - np.nanmin(out) > 25                 # the ramp kept (28.8 um)
        else:
            assert np.nanmax(np.abs(out)) < 1e-3
    assert tilt_slope_um_per_mm(1.0) == pytest.approx(17.455, abs=1e-3)


def test_the_plane_is_robust_to_protrusions_crowded_on_one_side():
    """Protrusions 40 um high covering a quarter of the field's right third: a plain least-squares
    plane tilts toward them; the reweighted fit keeps the canvas's own slope."""
    x, y = _grid()
    h = (1.0 * x).astype(np.float32)
    rng = np.random.default_rng(0)
    rows, cols = np.mgrid[0:200, 0:300]
    for r, c in rng.integers([0, 200], [200, 300], size=(150, 2)):
        h += (40.0 * np.clip(1 - ((rows - r) ** 2 + (cols - c) ** 2) / 16.0, 0, None)).astype(np.float32)
    plain_sx, _ = _plane(h)
    _, lev = level_height(h, method="plane", pixel_size_um=PX)
    assert abs(plain_sx - 1.0) > 0.3                                    # the plain fit is pulled
    assert lev.slope_x_um_per_mm == pytest.approx(1.0, abs=0.05)


def test_form_removes_a_bow_that_plane_keeps():
    x, y = _grid()
    bow = 200.0 * (((x - x.mean()) / 4.5) ** 2 + ((y - y.mean()) / 3.0) ** 2) / 2
    h = (bow + 0.5 * x).astype(np.float32)
    h[100:104, 150:154] += 30.0                                         # a protrusion stays whole
    plane, _ = level_height(h, method="plane", pixel_size_um=PX)
    form, lev = level_height(h, method="form", pixel_size_um=PX)
    assert np.ptp(plane) > 150                                          # the bow still there
    assert np.percentile(np.abs(form), 99) < 1.0 and form[101, 151] > 29
    assert lev.removed_rms_um > 30


def test_bad_level_is_one_clear_line():
    with pytest.raises(UVPSInputError, match="level must be one of none, plane, form; got 'tilt'"):
        level_height(np.zeros((4, 4), np.float32), method="tilt", pixel_size_um=PX)
    with pytest.raises(UVPSInputError, match="level must be one of"):
        RunOptions(level="tilt")
    with pytest.raises(UVPSInputError, match="not a levelling record"):
        raw_height(np.zeros((4, 4), np.float32), {"method": "plane"})


def _tilted_lamps(src: Path, dst: Path, deg: float):
    """The lamp positions file rotated about the y axis through the image centre by ``deg``: every
    lamp direction off by ``deg`` toward +x, the mean normal bias a calibration can leave."""
    t = math.radians(deg)
    with open(src, encoding="utf-8") as fh:
        rows = list(csv.DictReader(fh))
    with open(dst, "w", newline="", encoding="utf-8") as fh:
        w = csv.writer(fh)
        w.writerow(["file", "x_mm", "y_mm", "z_mm"])
        for r in rows:
            x, z = float(r["x_mm"]), float(r["z_mm"])
            w.writerow([r["file"], x * math.cos(t) + z * math.sin(t), r["y_mm"], -x * math.sin(t) + z * math.cos(t)])


@pytest.fixture(scope="module")
def biased_runs(tmp_path_factory):
    """A capture (18 x 24 mm field, canvas bow 15 um) run with lamps 0.2 deg off, levelled and not."""
    tmp = tmp_path_factory.mktemp("level")
    cap = make_capture(shape=(300, 400), n_lights=12, seed=3, pixel_size_um=60.0)
    write_capture(cap, tmp / "cap")
    _tilted_lamps(tmp / "cap" / "lights_positions_mm.csv", tmp / "biased.csv", 0.2)
    runs = {}
    for level in ("plane", "none"):
        COMMANDS["run"]({"images": [str(tmp / "cap")]}, {"lights": str(tmp / "biased.csv"), "level": level,
                                                          "detect": True}, tmp / level)
        runs[level] = tmp / level
    return cap, runs


def test_a_lamp_bias_ramps_the_raw_heights_and_depth_tif_is_level(biased_runs):
    cap, runs = biased_runs
    truth = _plane(cap.height_um.astype(np.float32), 60.0)
    raw = tifffile.imread(runs["none"] / "depth.tif")
    levelled = tifffile.imread(runs["plane"] / "depth.tif")
    bias = np.subtract(_plane(raw, 60.0), truth)
    assert np.hypot(*bias) > 2.0                        # 0.2 deg: about 3.5 um/mm of ramp
    left = np.subtract(_plane(levelled, 60.0), truth)
    assert np.hypot(*left) <= 0.3                       # the bar: <= 0.3 um/mm where the truth is level
    t = cap.height_um - np.median(cap.height_um)
    assert np.corrcoef(levelled.ravel(), t.ravel())[0, 1] > np.corrcoef(raw.ravel(), t.ravel())[0, 1] + 0.1
    # the raw is kept: the plane run.json records gives back the unlevelled run's depth.tif
    log = json.loads((runs["plane"] / "run.json").read_text())
    assert log["level"]["method"] == "plane" and log["params"]["level"] == "plane"
    assert "17.5 um/mm per deg" in log["level"]["why"] and "removed, so the relief shows" in log["level"]["why"]
    assert (log["level"]["slope_x_um_per_mm"], log["level"]["slope_y_um_per_mm"]) == pytest.approx(
        _plane(raw, 60.0), abs=0.3)
    np.testing.assert_allclose(raw_height(levelled, log["level"]), raw, atol=0.01)
    # the unlevelled run says so and still records the plane it holds
    log_none = json.loads((runs["none"] / "run.json").read_text())
    assert log_none["level"]["method"] == "none" and abs(log_none["level"]["slope_x_um_per_mm"]) > 2.0
    # depth.tif's own Info says it was levelled and how to get the raw back
    with tifffile.TiffFile(runs["plane"] / "depth.tif") as tif:
        info = tif.imagej_metadata["Info"]
    assert "Levelled: the best plane" in info and "raw = this + that plane" in info


def test_detection_reads_the_heights_as_integrated_so_levelling_changes_no_count(biased_runs, tmp_path):
    """Detection's rules were tuned on the heights as integrated (a field-wide plane moved 2 of 101
    protrusions across them): `run` detects before levelling, `uvps detect` on the levelled folder
    rebuilds those heights from run.json's level. Levelled or not, the same table."""
    import shutil
    _, runs = biased_runs
    a = (runs["plane"] / "protrusions.csv").read_bytes()
    assert a == (runs["none"] / "protrusions.csv").read_bytes() and a.count(b"\n") > 5
    folder = tmp_path / "run"
    shutil.copytree(runs["plane"], folder)
    COMMANDS["detect"]({}, {}, folder)
    assert (folder / "protrusions.csv").read_bytes().count(b"\n") == a.count(b"\n")


def test_the_report_info_and_fiji_log_state_the_plane_and_why(biased_runs):
    _, runs = biased_runs
    html = (runs["plane"] / "report.html").read_text(encoding="utf-8")
    log = json.loads((runs["plane"] / "run.json").read_text())
    assert "<b>Levelled</b>: the best plane removed (" in html
    assert f"slope {log['level']['slope_x_um_per_mm']:+.2f} \u00b5m/mm toward the right" in html
    assert "17.5 \u00b5m per mm for each degree" in html
    assert "<b>Not levelled</b>" in (runs["none"] / "report.html").read_text(encoding="utf-8")
    from uvps.commands.info import info_text
    from uvps.files.runfolder import describe
    assert "levelling:  Levelled: the best plane (x " in info_text(describe(runs["plane"]))
    line = bridge_logic.level_line(str(runs["plane"]))
    assert line.startswith("height levelled: its best plane removed (x ") and "run.json level" in line
    assert bridge_logic.level_line(str(runs["none"])).startswith("height not levelled")
    assert bridge_logic.level_line(str(runs["plane"] / "nowhere")) == ""


def test_integrate_levels_as_asked_and_records_it(biased_runs, tmp_path):
    _, runs = biased_runs
    import shutil
    folder = tmp_path / "run"
    shutil.copytree(runs["plane"], folder)
    res = COMMANDS["integrate"]({}, {"level": "none"}, folder)
    log = json.loads((folder / "run.json").read_text())
    assert log["level"]["method"] == "none" == res.diagnostics["level"]["method"]
    np.testing.assert_allclose(tifffile.imread(folder / "depth.tif"), tifffile.imread(runs["none"] / "depth.tif"),
                               atol=0.05)
    COMMANDS["integrate"]({}, {}, folder)                                  # default: plane
    log = json.loads((folder / "run.json").read_text())
    assert log["level"]["method"] == "plane"
    np.testing.assert_allclose(tifffile.imread(folder / "depth.tif"), tifffile.imread(runs["plane"] / "depth.tif"),
                               atol=0.05)
    with pytest.raises(UVPSInputError, match="level must be one of"):
        COMMANDS["integrate"]({}, {"level": "bow"}, folder)


def test_a_bowed_canvas_form_removes_the_bow_plane_keeps_it(tmp_path):
    """Through the pipeline: a canvas bowed by 200 um; plane keeps the bow, form takes it out and
    leaves the paint's relief."""
    cap = make_capture(shape=(240, 320), n_lights=12, seed=5, pixel_size_um=60.0, bow_um=200.0)
    capture = cap.as_capture(lights="positions")
    out = {lv: run(capture, RunOptions(level=lv), stages=("height",)).height.height_um for lv in ("plane", "form")}

    def bow_ptv(h):
        c = fit_surface(h, degree=3)
        return np.ptp(Levelling("form", 3, c, h.shape, 60.0, 0.0, 0.0).surface())

    assert bow_ptv(out["plane"]) > 100
    assert bow_ptv(out["form"]) < 5
    t = cap.height_um - cap.height_um.mean()
    t_flat, _ = level_height(t.astype(np.float32), method="form", pixel_size_um=60.0)
    assert np.corrcoef(out["form"].ravel(), t_flat.ravel())[0, 1] > 0.9


def test_uvps_changes_levels_itself_so_a_levelled_and_a_raw_date_compare_alike():
    """`uvps changes` removes the smooth difference of the two dates (block medians): a date levelled
    and one not give the same change map and height scale as two levelled ones."""
    from uvps.core.changes import level_heights
    cap = make_capture(shape=(200, 260), n_lights=8, seed=2, pixel_size_um=PX)
    a = (cap.height_um - np.median(cap.height_um)).astype(np.float32)
    x, y = _grid(a.shape)
    ramp = (3.3 * x + 0.4 * y).astype(np.float32)                       # the demo's plane
    b = a.copy()
    b[80:90, 100:110] += 12.0                                           # something grew
    valid = np.ones(a.shape, bool)
    off = np.ones(a.shape, bool)
    off[75:95, 95:115] = False
    both_levelled = level_heights(a, b, valid, off, block_px=34)
    one_raw = level_heights(a, b + ramp, valid, off, block_px=34)
    assert one_raw.height_scale == pytest.approx(both_levelled.height_scale, abs=0.01)
    inner = (slice(40, -40), slice(40, -40))                            # the bilinear block grid's edges aside
    np.testing.assert_allclose(one_raw.change_um[inner], both_levelled.change_um[inner], atol=0.3)
    assert one_raw.change_um[85, 105] == pytest.approx(12.0, abs=1.5)
