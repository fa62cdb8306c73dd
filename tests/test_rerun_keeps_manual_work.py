"""Nothing a user made is lost by a re-run: `uvps run` over a folder holding the wand's count and a
comparison keeps them, byte for byte, in earlier/<date>_<run id>/ with the run they were measured on,
and `uvps info` and the report name them as measured on the earlier run. Through the real CLI and the
real `uvps bridge` (subprocesses), on real files."""
import hashlib
import json
import subprocess
import sys
from pathlib import Path

import pytest

from uvps.files.runfolder import earlier_work
from uvps.testing.synthetic import make_capture, write_capture


def _uvps(*args):
    r = subprocess.run([sys.executable, "-m", "uvps", *map(str, args)], capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stderr
    return r


def _digest(path):
    return hashlib.sha256(Path(path).read_bytes()).hexdigest()


@pytest.fixture(scope="module")
def capture(tmp_path_factory):
    folder = tmp_path_factory.mktemp("cap")
    cap = make_capture(shape=(200, 260), n_lights=8, seed=3, pixel_size_um=30.0)
    write_capture(cap, folder)
    return folder, cap


def _run_args(capture_dir, run):
    return ["run", capture_dir, "-o", run, "--regions", "auto", "--pixel-size-um", 30,
            "--lights", capture_dir / "lights_positions_mm.csv"]


def _manual_work(run, cap):
    """The wand's count on the run (clicks on the three widest protrusions and one far from any) and
    its comparison with the automated count, as a user makes them."""
    p = cap.protrusions
    widest = sorted(range(len(p["width_um"])), key=lambda i: -p["width_um"][i])[:3]
    points = run.parent / "my clicks.csv"
    points.write_text("x_px,y_px\n" + "".join(f"{int(p['x_px'][i])},{int(p['y_px'][i])}\n" for i in widest)
                      + f"{int(p['x_px'][widest[0]]) + 1},{int(p['y_px'][widest[0]])}\n")
    _uvps("wand", points, "-o", run)
    _uvps("compare", run / "protrusions_manual.csv", run / "protrusions.csv", "-o", run)
    (run / "notes.txt").write_text("varnish lifting at lower left\n")     # a file uvps did not write
    names = ("protrusions_manual.csv", "protrusions_manual_labels.tif", "comparison.csv",
             "figures/comparison_map.png", "run.json", "albedo.tif", "depth.tif", "protrusions.csv")
    return {n: _digest(run / n) for n in names}


def _earlier(run):
    """The set-aside folders, oldest first, as `uvps info` lists them (two runs in one minute share the
    names' date, so the names alone do not give the order)."""
    return [run / item["folder"] for item in earlier_work(run)]


def test_a_rerun_keeps_the_manual_count_and_its_comparison_with_the_run_they_were_measured_on(capture, tmp_path):
    capture_dir, cap = capture
    run = tmp_path / "run"
    _uvps(*_run_args(capture_dir, run))
    before = _manual_work(run, cap)
    r = _uvps(*_run_args(capture_dir, run))
    # the new run has no manual work of its own; the earlier one is kept, byte for byte, with its run
    assert not (run / "protrusions_manual.csv").exists() and not (run / "comparison.csv").exists()
    (kept,) = _earlier(run)
    assert {n: _digest(kept / n) for n in before} == before
    assert (run / "notes.txt").read_text() == "varnish lifting at lower left\n"
    assert _digest(run / "run.json") != before["run.json"]                # a new run beside it
    record = json.loads((kept / "earlier.json").read_text())
    assert record["manual_files"] == ["protrusions_manual.csv", "protrusions_manual_labels.tif", "comparison.csv"]
    assert kept.name == f"{record['measured_on']['written_utc'].replace(' ', '_')}_{record['measured_on']['run_id']}"
    assert record["measured_on"]["run_id"] == before["run.json"][:8]
    # said at once, and not as a loss
    assert f"kept with that run in {kept}" in r.stderr and "not kept" not in r.stderr
    # uvps info lists it as measured on the earlier run
    info = _uvps("info", run).stdout
    line = [ln for ln in info.splitlines() if ln.startswith("earlier:")]
    assert line == [f"earlier:    earlier/{kept.name}/: protrusions_manual.csv (3 counted of 4 clicks), comparison.csv, "
                    f"measured on the run of {record['measured_on']['written_utc']} UTC (not on this run)"], info
    # the report too, and its own counts are not the earlier ones
    html = (run / "report.html").read_text()
    assert "Manual work measured on earlier runs" in html and f"earlier/{kept.name}/protrusions_manual.csv" in html
    # a manual count on the new run, then a third run: both earlier runs' work is there
    again = _manual_work(run, cap)
    _uvps(*_run_args(capture_dir, run))
    first, second = _earlier(run)
    assert first == kept and {n: _digest(first / n) for n in before} == before
    assert {n: _digest(second / n) for n in again} == again
    assert len([ln for ln in _uvps("info", run).stdout.splitlines() if ln.startswith("earlier:")]) == 2


def test_the_bridge_keeps_the_manual_work_the_same_way(capture, tmp_path):
    capture_dir, cap = capture
    run = tmp_path / "run"
    _uvps(*_run_args(capture_dir, run))
    before = _manual_work(run, cap)
    req = tmp_path / "request" / "request.json"
    req.parent.mkdir()
    req.write_text(json.dumps({"schema_version": 1, "command": "run", "inputs": {"images": [str(capture_dir)]},
                               "params": {"regions": "auto", "pixel_size_um": 30.0,
                                          "lights": str(capture_dir / "lights_positions_mm.csv")},
                               "output_dir": str(run)}))
    _uvps("bridge", req)
    resp = json.loads((req.parent / "response.json").read_text())
    assert resp["status"] == "ok", resp
    (kept,) = _earlier(run)
    assert resp["diagnostics"]["earlier_manual_work"] == str(kept)
    assert any(str(kept) in w for w in resp["warnings"])
    assert {n: _digest(kept / n) for n in before} == before
    assert (run / "notes.txt").is_file() and not (run / "protrusions_manual.csv").exists()


def test_a_step_that_rewrites_the_height_or_albedo_sets_the_manual_work_aside(capture, tmp_path):
    """`uvps integrate` writes a new depth.tif and `uvps normals` a new albedo.tif into the folder: the
    manual count measured on the old ones moves to earlier/ with them, byte for byte, as a whole run's
    does; it is not left beside images it was not measured on."""
    capture_dir, cap = capture
    run = tmp_path / "run"
    _uvps(*_run_args(capture_dir, run))
    before = _manual_work(run, cap)
    r = _uvps("integrate", "-o", run, "--level", "form")
    (kept,) = _earlier(run)
    assert {n: _digest(kept / n) for n in before} == before
    for name in ("protrusions_manual.csv", "protrusions_manual_labels.tif", "comparison.csv",
                 "figures/comparison_map.png"):
        assert not (run / name).exists(), name
    assert _digest(run / "depth.tif") != before["depth.tif"]               # the new height is there
    assert _digest(run / "albedo.tif") == before["albedo.tif"]             # integrate leaves the albedo
    assert json.loads((run / "run.json").read_text())["level"]["method"] == "form"
    assert (run / "notes.txt").read_text() == "varnish lifting at lower left\n"
    assert f"kept with the run it was measured on in {kept}" in r.stderr
    record = json.loads((kept / "earlier.json").read_text())
    assert record["measured_on"]["run_id"] == before["run.json"][:8] and "integrate" in record["reason"]
    assert len([ln for ln in _uvps("info", run).stdout.splitlines() if ln.startswith("earlier:")]) == 1
    # a count made on the new height, then `uvps normals` (a new albedo): kept too, beside the first
    again = _manual_work(run, cap)
    r = _uvps("normals", capture_dir, "-o", run, "--pixel-size-um", 30)
    (second,) = [f for f in _earlier(run) if f != kept]     # (names sort by minute, then run id)
    assert {n: _digest(kept / n) for n in before} == before
    assert {n: _digest(second / n) for n in again} == again
    assert not (run / "protrusions_manual.csv").exists() and f"in {second}" in r.stderr


def test_lights_and_flatfield_leave_the_manual_work_where_it_was_measured(capture, tmp_path):
    """`uvps lights` and `uvps flatfield` write lights.json and the flat-fielded images, not the albedo
    or height a manual count was measured on: the count stays in place, untouched."""
    capture_dir, cap = capture
    run = tmp_path / "run"
    _uvps(*_run_args(capture_dir, run))
    before = _manual_work(run, cap)
    _uvps("lights", capture_dir, "-o", run, "--pixel-size-um", 30)
    _uvps("flatfield", capture_dir, "-o", run, "--pixel-size-um", 30)
    assert not (run / "earlier").exists()
    for name in ("protrusions_manual.csv", "protrusions_manual_labels.tif", "comparison.csv", "albedo.tif",
                 "depth.tif"):
        assert _digest(run / name) == before[name], name


@pytest.mark.parametrize("step", ["detect", "wand"])
def test_a_new_count_sets_the_comparison_made_with_the_earlier_one_aside(capture, tmp_path, step):
    """`detect` (a new automated count) and `wand` (a new manual count) make a comparison stale: it moves,
    byte for byte, with the counts it was made with, into earlier/; the albedo and height are unchanged,
    so `detect` leaves the manual count where it was; the warning names where the comparison went."""
    capture_dir, cap = capture
    run = tmp_path / "run"
    _uvps(*_run_args(capture_dir, run))
    before = _manual_work(run, cap)
    if step == "detect":
        r = _uvps("detect", "-o", run, "--regions", "auto", "--min-width-um", 90)
    else:
        points = tmp_path / "new clicks.csv"
        p = cap.protrusions
        points.write_text(f"x_px,y_px\n{int(p['x_px'][0])},{int(p['y_px'][0])}\n")
        r = _uvps("wand", points, "-o", run)
    assert not (run / "comparison.csv").exists() and not (run / "figures" / "comparison_map.png").exists()
    (kept,) = _earlier(run)
    assert {n: _digest(kept / n) for n in before} == before
    record = json.loads((kept / "earlier.json").read_text())
    assert record["reason"].startswith(f"`uvps {step}` wrote a new ") and "comparison" in record["reason"]
    assert f"kept with it in {kept}" in r.stderr, r.stderr
    changed = "protrusions.csv" if step == "detect" else "protrusions_manual.csv"
    assert _digest(run / changed) != before[changed]
    if step == "detect":       # the manual count was measured on the albedo and height, which stay
        assert _digest(run / "protrusions_manual.csv") == before["protrusions_manual.csv"]
    # a second new count with no comparison in the folder sets nothing more aside
    r = _uvps("detect", "-o", run, "--regions", "auto")
    assert len(_earlier(run)) == 1 and "comparison" not in r.stderr
