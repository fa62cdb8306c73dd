"""uvps elements: XRF element maps registered onto a run, per colour area and per protrusion.

Known answers come from :func:`uvps.testing.synthetic.render_element_maps`: each colour area holds each
element at a known abundance, the scan is a known similarity of the camera's view, and the maps
carry Poisson counting noise (and, where said, what the registration does not model).
"""
import csv
import json
import subprocess
import sys

import numpy as np
import pytest
import tifffile

from uvps.commands.elements import read_control_points, read_edf, read_element_maps
from uvps.core.elements import area_elements, register_maps, registration_error_map_px, resample_to_run
from uvps.errors import UVPSInputError
from uvps.files.tables import write_label_tiff
from uvps.core.regions import RegionMap, region_statistics
from uvps.files.tables import write_regions_csv
from uvps.testing.synthetic import SyntheticSpec, make_capture, render_element_maps, write_truth_run

PX = 15.0
STEP = 250.0


@pytest.fixture(scope="module")
def capture():
    return make_capture(SyntheticSpec(shape=(600, 800), n_lights=4, seed=2, protrusion_density_light=120.0))


@pytest.fixture(scope="module")
def run_dir(capture, tmp_path_factory):
    """A run folder of the capture's truth, with its colour areas (as ``uvps run --regions`` writes)."""
    folder = write_truth_run(capture, tmp_path_factory.mktemp("elements") / "run")
    write_label_tiff(folder / "regions_labels.tif", capture.regions, pixel_size_um=PX)
    names = {i: f"area {i}" for i in range(1, int(capture.regions.max()) + 1)}
    stats = region_statistics({k: capture.protrusions[k] for k in ("x_px", "y_px", "width_um")},
                              RegionMap(capture.regions, names), pixel_size_um=PX)
    write_regions_csv(folder / "regions.csv", stats)
    return folder


def _write_tiffs(folder, truth, *, calibrated=True):
    folder.mkdir(parents=True, exist_ok=True)
    paths = []
    for name, m in zip(truth.maps.names, truth.maps.data):
        p = folder / f"scan_{name}.tif"
        kw = dict(resolution=(1.0 / STEP, 1.0 / STEP), metadata={"unit": "um"}) if calibrated else {}
        tifffile.imwrite(p, m.astype(np.float32), imagej=True, **kw)
        paths.append(p)
    return paths


def _uvps(*args):
    return subprocess.run([sys.executable, "-m", "uvps", *map(str, args)], capture_output=True, text=True,
                          timeout=300)


# ------------------------------------------------------------------------------------------------
# registration and statistics (numeric)
# ------------------------------------------------------------------------------------------------

@pytest.mark.parametrize("rotation, scale, shift", [(3.0, 1.05, (2.0, -1.5)), (-2.5, 0.95, (-1.8, 1.2))])
def test_automatic_registration_within_half_a_map_pixel(capture, rotation, scale, shift):
    truth = render_element_maps(capture, rotation_deg=rotation, scale=scale, shift_mm=shift, seed=1)
    reg = register_maps(capture.albedo, truth.maps, labels=capture.regions, pixel_size_um=PX)
    err = registration_error_map_px(reg.map_to_run, truth.map_to_run, truth.maps.shape, capture.regions.shape)
    assert err < 0.5, err
    assert reg.method == "automatic" and reg.residual_map_px < 0.5
    assert reg.overlap == pytest.approx(1.0)
    assert reg.rotation_deg == pytest.approx(rotation, abs=0.2)


def test_registration_holds_on_composition_that_does_not_follow_the_colour_areas(capture):
    """Abundance varying by +-30 % inside each area, a flat-topped spot and a scanner's line jitter
    (none of which the registration models): still within half a map pixel."""
    truth = render_element_maps(capture, rotation_deg=2.0, scale=1.03, shift_mm=(1.0, 1.0), seed=4,
                                within_area=0.3, spot_shape="disc", line_jitter_px=0.2)
    reg = register_maps(capture.albedo, truth.maps, labels=capture.regions, pixel_size_um=PX)
    err = registration_error_map_px(reg.map_to_run, truth.map_to_run, truth.maps.shape, capture.regions.shape)
    assert err < 0.5, err


def test_control_points_fix_the_registration(capture):
    truth = render_element_maps(capture, rotation_deg=-3.0, scale=0.96, shift_mm=(-2.0, 0.5), seed=3)
    H, W = truth.maps.shape
    rng = np.random.default_rng(0)
    mp = np.array([[8.0, 9.0], [W - 9.0, 10.0], [W - 12.0, H - 8.0], [10.0, H - 11.0]])
    x, y = truth.map_to_run[:2, :2] @ mp.T + truth.map_to_run[:2, 2:3]
    run_pts = np.column_stack([x, y]) + rng.normal(0, 2.0, (4, 2))      # clicks 2 run px off
    cp = np.column_stack([mp, run_pts])
    inside = (run_pts[:, 0] > 0) & (run_pts[:, 0] < 799) & (run_pts[:, 1] > 0) & (run_pts[:, 1] < 599)
    cp = cp[inside] if inside.sum() >= 2 else cp
    for refine in (False, True):
        reg = register_maps(capture.albedo, truth.maps, labels=capture.regions, pixel_size_um=PX,
                            control_points=cp, refine=refine)
        err = registration_error_map_px(reg.map_to_run, truth.map_to_run, truth.maps.shape, capture.regions.shape)
        assert err < 0.3, (refine, err)
        assert reg.residual_of == "control points"
    assert reg.method == "control points, refined"


def test_area_means_within_five_percent_of_the_truth(capture):
    truth = render_element_maps(capture, rotation_deg=1.0, scale=1.0, shift_mm=(0.5, 0.5), seed=5)
    reg = register_maps(capture.albedo, truth.maps, labels=capture.regions, pixel_size_um=PX)
    resampled = resample_to_run(truth.maps, reg, capture.regions.shape)
    names = {i: str(i) for i in range(1, int(capture.regions.max()) + 1)}
    areas = area_elements(resampled, capture.regions, names, pixel_size_um=PX, step_um=STEP, spot_um=1000.0)
    big = areas.n_map_pixels > 10
    assert big.sum() >= 3
    rel = np.abs(areas.mean[big] - truth.abundance[areas.labels][big]) / truth.abundance[areas.labels][big]
    assert rel.max() < 0.05, rel


# ------------------------------------------------------------------------------------------------
# formats
# ------------------------------------------------------------------------------------------------

def test_every_format_reads_the_same_maps(capture, tmp_path):
    truth = render_element_maps(capture, seed=6)
    data, names = truth.maps.data, truth.maps.names
    # one calibrated TIFF per element: names from the file names, step from the calibration
    per_file = read_element_maps(_write_tiffs(tmp_path / "tiffs", truth))
    assert per_file.names == names and per_file.step_um == pytest.approx(STEP)
    np.testing.assert_allclose(per_file.data, data, rtol=1e-6)
    # a multi-page TIFF with the element names as ImageJ slice labels
    stack = tmp_path / "stack.tif"
    tifffile.imwrite(stack, data.astype(np.float32), imagej=True, metadata={"Labels": names})
    got = read_element_maps([stack], step_um=STEP)
    assert got.names == names
    np.testing.assert_allclose(got.data, data, rtol=1e-6)
    # EDF as PyMCA writes it, here written by the field's own library (fabio)
    fabio = pytest.importorskip("fabio")
    from fabio.edfimage import EdfImage
    edfs = []
    for n, m in zip(names, data):
        p = tmp_path / f"map_{n}.edf"
        EdfImage(data=m.astype(np.float32)).write(str(p))
        edfs.append(p)
    np.testing.assert_allclose(read_edf(edfs[0]), data[0], rtol=1e-6)
    got = read_element_maps(edfs, step_um=STEP)
    assert got.names == names
    np.testing.assert_allclose(got.data, data, rtol=1e-6)
    # a text table of row, column and one column per element (PyMCA's ROI imaging export)
    H, W = data.shape[1:]
    rr, cc = np.mgrid[0:H, 0:W]
    table = tmp_path / "maps.csv"
    with open(table, "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["row", "column"] + [n.replace("_", " ") for n in names])
        for r, c in zip(rr.ravel(), cc.ravel()):
            w.writerow([r, c] + [f"{v:g}" for v in data[:, r, c]])
    got = read_element_maps([table], step_um=STEP)
    assert got.names == names
    np.testing.assert_allclose(got.data, data, rtol=1e-5)


@pytest.mark.parametrize("case, message", [
    ("sizes", "differ in size"), ("no step", "--step-um"), ("tiny", "is not a map"),
    ("format", "unknown format"), ("unnamed stack", "without element names"), ("twice", "given twice")])
def test_bad_maps_are_one_line_errors(capture, tmp_path, case, message):
    truth = render_element_maps(capture, seed=7)
    paths = _write_tiffs(tmp_path, truth, calibrated=case != "no step")
    step = None if case == "no step" else STEP
    if case == "sizes":
        tifffile.imwrite(paths[1], truth.maps.data[1][:-3].astype(np.float32))
    elif case == "tiny":
        tifffile.imwrite(paths[0], np.ones((2, 50), np.float32))
    elif case == "format":
        paths[0] = paths[0].with_suffix(".h5")
        paths[0].write_bytes(b"\x89HDF\r\n")
    elif case == "unnamed stack":
        tifffile.imwrite(paths[0], truth.maps.data.astype(np.float32), photometric="minisblack")
        paths = paths[:1]
    elif case == "twice":
        paths.append(paths[0])
    with pytest.raises(UVPSInputError, match=message) as err:
        read_element_maps(paths, step_um=step)
    assert "\n" not in str(err.value)


def test_control_points_outside_an_image_are_refused(tmp_path):
    p = tmp_path / "cp.csv"
    p.write_text("map_col,map_row,run_col,run_row\n1,1,10,10\n200,5,300,20\n")
    with pytest.raises(UVPSInputError, match="line 3: map point .* outside the map"):
        read_control_points(p, map_shape=(80, 100), run_shape=(600, 800))


# ------------------------------------------------------------------------------------------------
# the command, end to end
# ------------------------------------------------------------------------------------------------

def test_uvps_elements_writes_the_registration_tables_and_report(capture, run_dir, tmp_path):
    truth = render_element_maps(capture, rotation_deg=2.0, scale=1.02, shift_mm=(1.0, -0.5), seed=8)
    maps = _write_tiffs(tmp_path / "maps", truth)
    out = tmp_path / "out"
    r = _uvps("elements", run_dir, *maps, "-o", out)
    assert r.returncode == 0, r.stderr
    reg = json.loads((out / "registration.json").read_text())
    err = registration_error_map_px(np.array(reg["map_to_run"]), truth.map_to_run, truth.maps.shape,
                                    capture.regions.shape)
    assert err < 0.5 and reg["method"] == "automatic"
    with tifffile.TiffFile(out / "elements.tif") as tif:
        assert tif.imagej_metadata["Labels"] == truth.maps.names
        assert tif.series[0].shape == (4, 600, 800)
    with open(out / "elements_by_area.csv", newline="") as fh:
        rows = list(csv.DictReader(fh))
    assert {"area", "n_map_pixels", "Pb_L_mean", "Pb_L_sd", "Cd_L_mean", "density_per_cm2"} <= set(rows[0])
    assert any(k.startswith("share_") for k in rows[0])
    with open(out / "elements_by_protrusion.csv", newline="") as fh:
        prot = list(csv.DictReader(fh))
    assert len(prot) == capture.protrusions["id"].size and "Pb_L_site" in prot[0] and "Pb_L_ring" in prot[0]
    with open(out / "element_correlation.csv", newline="") as fh:
        corr = {row["element"]: row for row in csv.DictReader(fh)}
    # lead is abundant in the light areas, where protrusions are denser: a positive rank correlation
    assert float(corr["Pb_L"]["spearman_rho"]) > 0.5
    assert (out / "report.html").is_file() and (out / "figures" / "elements_composite.png").is_file()
    assert "Spearman" in (out / "report.html").read_text()
    assert "registration: automatic" in r.stdout


def test_uvps_elements_refuses_maps_of_another_region_and_writes_nothing(capture, run_dir, tmp_path):
    rng = np.random.default_rng(0)
    other = tmp_path / "other"
    other.mkdir()
    paths = []
    for n in ("Pb_L", "Fe_K"):
        p = other / f"{n}.tif"
        tifffile.imwrite(p, rng.poisson(500, (92, 116)).astype(np.float32))
        paths.append(p)
    out = tmp_path / "out"
    r = _uvps("elements", run_dir, *paths, "--step-um", STEP, "-o", out)
    assert r.returncode == 1, r.stderr
    errors = [ln for ln in r.stderr.splitlines() if "error" in ln]
    assert len(errors) == 1 and "does not hold" in errors[0]
    assert not out.exists()


def test_uvps_elements_needs_the_run_s_colour_areas(capture, tmp_path):
    bare = write_truth_run(capture, tmp_path / "bare")
    truth = render_element_maps(capture, seed=9)
    r = _uvps("elements", bare, *_write_tiffs(tmp_path / "maps", truth), "-o", tmp_path / "out")
    assert r.returncode == 1 and "no colour areas" in r.stderr
