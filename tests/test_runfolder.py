"""The run folder: reading it back, and `uvps info` (what a run folder holds), through the CLI and
the bridge."""
import json
import subprocess
import sys

import numpy as np
import pytest

from uvps.commands import COMMANDS
from uvps.errors import UVPSInputError
from uvps.files.io import write_imagej_tiff
from uvps.files.runfolder import describe, read_run
from uvps.testing.synthetic import make_capture, write_capture


@pytest.fixture(scope="module")
def run_dir(tmp_path_factory):
    cap = make_capture(shape=(160, 200), n_lights=8, seed=2)
    d = tmp_path_factory.mktemp("info")
    write_capture(cap, d / "cap")
    COMMANDS["run"]({"images": [str(d / "cap")]}, {"regions": "auto", "lights": str(d / "cap" / "lights_positions_mm.csv")},
                    d / "run")
    return d / "run"


def test_info_describes_the_run_on_the_command_line(run_dir):
    r = subprocess.run([sys.executable, "-m", "uvps", "info", str(run_dir)], capture_output=True, text=True,
                       timeout=120)
    assert r.returncode == 0, r.stderr
    log = json.loads((run_dir / "run.json").read_text())
    n = len((run_dir / "protrusions.csv").read_text().splitlines()) - 1
    assert "made by:    uvps run" in r.stdout
    assert "160 x 200 px x 3 channels of 15.0 um, 8 lights (positions)" in r.stdout
    rejected = sum(log["diagnostics"]["detect"]["rejected"].values())
    assert n > 0 and rejected > 0
    # the run's counts: kept, candidates and rejected as the detection gave them
    assert (f"protrusions: {n} kept of {n + rejected} candidates ({rejected} rejected by the "
            "detection's rules)") in r.stdout.splitlines()
    # every warning the run gave is repeated, or "none"
    assert all(w in r.stdout for w in log["warnings"]) and (log["warnings"] or "warnings:   none" in r.stdout)
    assert not list(run_dir.parent.glob(".run.tmp-*"))     # info writes nothing


def test_info_through_the_bridge_returns_the_same_facts(run_dir, tmp_path):
    req = tmp_path / "request.json"
    req.write_text(json.dumps({"schema_version": 1, "command": "info", "inputs": {"run": str(run_dir)},
                               "params": {}, "output_dir": str(tmp_path / "unused")}))
    r = subprocess.run([sys.executable, "-m", "uvps", "bridge", str(req)], capture_output=True, text=True,
                       timeout=120)
    assert r.returncode == 0, r.stderr
    resp = json.loads((tmp_path / "response.json").read_text())
    assert resp["status"] == "ok" and resp["diagnostics"] == json.loads(json.dumps(describe(run_dir)))
    assert resp["diagnostics"]["lights"]["source"] == "positions"


def test_info_on_a_folder_that_is_not_a_run(tmp_path):
    r = subprocess.run([sys.executable, "-m", "uvps", "info", str(tmp_path)], capture_output=True, text=True,
                       timeout=120)
    assert r.returncode == 1 and r.stdout == ""
    assert r.stderr.strip() == f"uvps info: error: {tmp_path} is not a run folder: it has no run.json (made by " \
                               "uvps run, lights, flatfield or normals)"


def test_read_run_reads_channel_last_and_checks_sizes(tmp_path):
    write_imagej_tiff(tmp_path / "albedo.tif", np.ones((3, 20, 30), np.float32), axes="CYX", pixel_size_um=15.0)
    write_imagej_tiff(tmp_path / "depth.tif", np.zeros((20, 30), np.float32), axes="YX", pixel_size_um=15.0)
    r = read_run(tmp_path)
    assert r.albedo.shape == (20, 30, 3) and r.shape == (20, 30) and r.pixel_size_um == 15.0
    with pytest.raises(UVPSInputError, match="has no normals.tif; run the 'normals' command first"):
        read_run(tmp_path, need=("normals",))
    write_imagej_tiff(tmp_path / "normals.tif", np.zeros((3, 21, 30), np.float32), axes="CYX", pixel_size_um=15.0)
    with pytest.raises(UVPSInputError, match="differ in size"):
        read_run(tmp_path)
    (tmp_path / "normals.tif").unlink()
    with pytest.raises(UVPSInputError, match=r"pixel_size_um must be a positive number \(micrometres\); got -1"):
        read_run(tmp_path, need=(), pixel_size_um=-1)


def test_a_new_run_folder_gets_the_usual_mode_not_0700(run_dir):
    """The run folder is the temporary folder renamed: it must not keep mkdtemp's 0700 (others on
    a shared museum drive could not read the results)."""
    import os

    mask = os.umask(0)
    os.umask(mask)
    assert run_dir.stat().st_mode & 0o777 == 0o777 & ~mask
    assert (run_dir / "depth.tif").stat().st_mode & 0o777 == 0o666 & ~mask


def test_outputs_written_band_by_band_hold_the_whole_arrays(run_dir, tmp_path, monkeypatch):
    """Flat-fielded images written in bands of 7 rows from a memory-mapped capture hold each image
    divided by its drop-off map computed whole; normals, albedo and gradients written in bands of 5
    rows hold the run's arrays."""
    import tifffile

    import uvps.files.io
    import uvps.files.runfolder
    from uvps.core.flatfield import flatfield
    from uvps.core.integrate import gradients_from_normals
    from uvps.files.io import MappedStack, read_capture
    from uvps.core.pipeline import RunOptions, run
    from uvps.files.runfolder import write_flatfield, write_stereo

    cap_dir = run_dir.parent / "cap"
    cap = read_capture(cap_dir, lights=cap_dir / "lights_positions_mm.csv")
    assert isinstance(cap.images, MappedStack)
    res = run(cap, RunOptions(), stages=("flatfield", "normals"))
    K, M, N, C = cap.images.shape
    monkeypatch.setattr(uvps.files.runfolder, "BAND_BYTES", 7 * N * C * 4)
    write_flatfield(tmp_path, res.capture, res.lights)
    files = sorted((tmp_path / "flatfield").glob("*.tif"))
    assert len(files) == K
    for k, f in enumerate(files):
        whole = flatfield(np.asarray(res.capture.images[k]), res.lights.fits[k], channels_first=True)
        np.testing.assert_array_equal(tifffile.imread(f), whole)
    monkeypatch.setattr(uvps.files.io, "BAND_BYTES", 5 * N * 4)
    write_stereo(tmp_path, res.stereo, cap.pixel_size_um)
    st = res.stereo
    np.testing.assert_array_equal(tifffile.imread(tmp_path / "normals.tif"), np.moveaxis(st.normals, -1, 0))
    np.testing.assert_array_equal(tifffile.imread(tmp_path / "albedo.tif"), np.moveaxis(st.albedo, -1, 0))
    g = gradients_from_normals(st.normals)
    np.testing.assert_array_equal(tifffile.imread(tmp_path / "gradients.tif"), np.stack([g.p, g.q]))


# ------------------------------------------------------------------------------------------------
# the relief's scale (run.json "relief"): relative when the estimated lamps do not pin it
# ------------------------------------------------------------------------------------------------

@pytest.fixture(scope="module")
def relative_run(tmp_path_factory):
    """Lamps estimated from a 2.4 x 3 mm field: their elevation is not pinned (the heights' 95 %
    uncertainty is far above 20 %), so the run's relief is relative."""
    cap = make_capture(shape=(160, 200), n_lights=8, seed=2)
    d = tmp_path_factory.mktemp("relative")
    write_capture(cap, d / "cap")
    result = COMMANDS["run"]({"images": [str(d / "cap")]}, {"regions": "auto"}, d / "run")
    return d / "run", result


def test_relief_of_reads_run_json_defensively():
    from uvps.files.runfolder import relief_of

    assert relief_of({"relief": {"scale": "relative", "lamps": "estimated", "reason": "r"}}) == {
        "scale": "relative", "lamps": "estimated", "reason": "r"}
    for old in ({}, None, {"relief": None}, {"relief": "relative"}, {"relief": {"scale": "metres"}}):
        assert relief_of(old)["scale"] == "absolute"          # older folders: heights were in micrometres


def test_a_run_with_given_lamps_has_an_absolute_relief_in_micrometres(run_dir):
    import tifffile

    from uvps.files.runfolder import height_unit, relief_in

    relief = relief_in(run_dir)
    assert relief["scale"] == "absolute" and relief["lamps"] == "positions"
    assert height_unit(run_dir / "depth.tif") == "um"
    assert (run_dir / "protrusions.csv").read_text().splitlines()[0].split(",")[5] == "height_um"
    with tifffile.TiffFile(run_dir / "depth.tif") as tif:
        assert "micrometres" in tif.imagej_metadata["Info"]


def test_a_relative_run_has_no_micrometre_heights(relative_run):
    import tifffile

    from uvps.files.tables import read_protrusions_csv
    from uvps.files.runfolder import height_unit

    run, result = relative_run
    log = json.loads((run / "run.json").read_text())
    assert log["relief"]["scale"] == "relative" and log["relief"]["lamps"] == "estimated"
    assert log["diagnostics"]["lights"]["height_uncertainty_relative_95"] > 0.20
    assert "calibrat" in log["relief"]["reason"]
    # depth.tif: ImageJ's value unit says relative (the TIFF's ImageJ description, vunit=relative)
    assert height_unit(run / "depth.tif") == "relative"
    with tifffile.TiffFile(run / "depth.tif") as tif:
        assert "vunit=relative" in tif.pages.first.description
        assert "NOT micrometres" in tif.imagej_metadata["Info"]
    # protrusions.csv: the heights are a unitless relative_height, no height_um column
    header = (run / "protrusions.csv").read_text().splitlines()[0].split(",")
    assert "relative_height" in header and "height_um" not in header
    table = read_protrusions_csv(run / "protrusions.csv")
    assert len(table["id"]) > 0 and np.isfinite(table["relative_height"]).any()
    assert np.isnan(table["height_um"]).all()
    # the run's one heights warning says so
    assert sum("heights are relative" in w or "not determined" in w for w in result.warnings) == 1
    # uvps info says it
    r = subprocess.run([sys.executable, "-m", "uvps", "info", str(run)], capture_output=True, text=True, timeout=120)
    assert r.returncode == 0 and "relief:     RELATIVE" in r.stdout


def test_detect_and_integrate_on_a_relative_run_keep_it_relative(relative_run):
    from uvps.files.runfolder import height_unit

    run, _ = relative_run
    COMMANDS["detect"]({}, {}, run)
    header = (run / "protrusions.csv").read_text().splitlines()[0].split(",")
    assert "relative_height" in header and "height_um" not in header
    COMMANDS["integrate"]({}, {}, run)
    assert height_unit(run / "depth.tif") == "relative"


@pytest.mark.parametrize("proc", [True, False])
def test_the_file_mode_is_read_without_changing_the_umask_whatever_the_threads(proc, monkeypatch):
    """Files written from several threads (the writer's, the report's figures) each get 0o666 minus the umask,
    and the umask stays what it was: read from /proc on Linux, and set and restored under a lock elsewhere (two
    threads interleaving os.umask(0) and its restore gave a file 0o666)."""
    import builtins
    import os
    import sys
    import threading

    from uvps.files import atomic

    if not proc:          # the platforms without /proc: the lock alone
        real_open = builtins.open
        monkeypatch.setattr(builtins, "open", lambda f, *a, **k: (_ for _ in ()).throw(OSError("no /proc"))
                            if str(f) == "/proc/self/status" else real_open(f, *a, **k))
    before = os.umask(0o027)
    switch = sys.getswitchinterval()
    sys.setswitchinterval(1e-6)       # threads switch between any two calls: the race shows when it is there
    try:
        modes = []

        def many():
            modes.extend({atomic.file_mode() for _ in range(20000)})

        threads = [threading.Thread(target=many) for _ in range(3)]
        for t in threads:
            t.start()
        for t in threads:
            t.join()
        assert set(modes) == {0o640}
        assert os.umask(0o027) == 0o027
    finally:
        sys.setswitchinterval(switch)
        os.umask(before)
