"""Tests of the protrusion commands on run folders built from a synthetic capture."""
import csv
import json
import pathlib
import shutil

import numpy as np
import pytest
import tifffile

from uvps.core.compare import compare_detections
from uvps.errors import UVPSInputError
from uvps.files.io import read_tiff, write_imagej_tiff
from uvps.files.tables import read_protrusions_csv
from uvps.commands import COMMANDS
from uvps.commands.protrusions import cmd_compare, cmd_detect, cmd_regions, \
    cmd_stats, cmd_wand
from uvps.testing.synthetic import make_capture


@pytest.fixture(scope="module")
def capture():
    return make_capture(shape=(240, 320), n_lights=8, seed=3)


@pytest.fixture(scope="module")
def template(tmp_path_factory, capture):
    """A run folder as the core writes it: albedo (CYX), depth (um), normals (CYX)."""
    d = tmp_path_factory.mktemp("template")
    px = capture.spec.pixel_size_um
    write_imagej_tiff(d / "albedo.tif", np.moveaxis(capture.albedo, -1, 0), axes="CYX",
                      pixel_size_um=px)
    write_imagej_tiff(d / "depth.tif", capture.height_um, axes="YX", pixel_size_um=px)
    write_imagej_tiff(d / "normals.tif", np.moveaxis(capture.normals, -1, 0), axes="CYX",
                      pixel_size_um=px)
    return d


@pytest.fixture
def run(tmp_path, template):
    d = tmp_path / "run"
    shutil.copytree(template, d)
    return d


def _truth_table(capture):
    p = capture.protrusions
    return {"x_px": p["x_px"], "y_px": p["y_px"], "width_um": p["width_um"]}


def _bridge_ready(res):
    """The bridge writes outputs and diagnostics as strict JSON."""
    json.dumps({"outputs": [o.to_dict() for o in res.outputs], "diagnostics": res.diagnostics,
                "warnings": res.warnings}, allow_nan=False)
    for o in res.outputs:
        assert o.path and pathlib.Path(o.path).is_file()


def test_registry():
    assert {"detect", "wand", "regions", "stats", "report", "compare"} <= set(COMMANDS)
    assert COMMANDS["report"] is COMMANDS["stats"]


def test_detect_writes_consistent_table_and_labels(run, capture):
    res = cmd_detect({}, {}, run)
    _bridge_ready(res)
    assert {o.name for o in res.outputs} == {"protrusions", "protrusions_labels"}
    table = read_protrusions_csv(run / "protrusions.csv")
    labels, px = read_tiff(run / "protrusions_labels.tif")
    assert px == pytest.approx(capture.spec.pixel_size_um)
    assert labels.shape == capture.height_um.shape
    np.testing.assert_array_equal(np.unique(labels[labels > 0]), table["id"])
    assert res.diagnostics["n_protrusions"] == len(table["id"]) > 0
    assert set(table["source"]) <= {"albedo", "height", "albedo+height"}
    # most detections lie on a true protrusion (synthetic ground truth; detect's own tests
    # measure its accuracy)
    comp = compare_detections(_truth_table(capture), table, regions=None,
                              pixel_size_um=capture.spec.pixel_size_um)
    assert len(comp.pairs) >= max(1, len(table["id"]) // 2)


def test_detect_with_auto_regions(run):
    res = cmd_detect({}, {"regions": "auto", "min_width_um": 40.0}, run)
    _bridge_ready(res)
    regions, _ = read_tiff(run / "regions_labels.tif")
    assert res.diagnostics["n_areas"] == len(np.unique(regions[regions > 0])) >= 2
    table = read_protrusions_csv(run / "protrusions.csv")
    rows = np.rint(table["y_px"]).astype(int)
    cols = np.rint(table["x_px"]).astype(int)
    np.testing.assert_array_equal(table["region"], regions[rows, cols])


def test_detect_unknown_param_is_warned(run):
    res = cmd_detect({}, {"min_widht_um": 3}, run)
    assert any("min_widht_um" in w for w in res.warnings)


def test_wand_at_true_centres(run, capture):
    p = capture.protrusions
    pts = np.column_stack([p["x_px"], p["y_px"]])
    seeds = run.parent / "points.csv"
    with open(seeds, "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["x_px", "y_px"])
        w.writerows(pts.tolist())
    res = cmd_wand({"points": str(seeds)}, {"method": "imagej", "tolerance": 0.08}, run)
    _bridge_ready(res)
    table = read_protrusions_csv(run / "protrusions_manual.csv")
    assert res.diagnostics["n_protrusions"] == len(table["id"]) == len(pts)
    assert list(set(table["source"])) == ["wand"]
    # each selection is centred on its protrusion and about as wide (albedo outline)
    comp = compare_detections(_truth_table(capture), table, regions=None,
                              pixel_size_um=capture.spec.pixel_size_um)
    assert len(comp.pairs) == len(pts)
    np.testing.assert_allclose(table["width_um"][comp.pairs[:, 1]],
                               p["width_um"][comp.pairs[:, 0]], rtol=0.35)
    assert read_tiff(run / "protrusions_manual_labels.tif").data.max() == len(pts)
    # statistics of the wand count (the paper's Fig. 4a is the manual method): only the wand
    # has run, so stats falls back to protrusions_manual.csv and says so
    res = cmd_stats({}, {}, run)
    assert any("protrusions_manual.csv" in w for w in res.warnings)
    with open(run / "regions.csv", newline="") as fh:
        assert list(csv.DictReader(fh))[-1]["count"] == str(len(pts))
    text = (run / "report.html").read_text()
    assert "href='protrusions_manual.csv'" in text and "protrusions_manual_labels.tif" in text


def test_regions_from_masks_and_stats_and_compare(run, capture):
    px = capture.spec.pixel_size_um
    shape = capture.height_um.shape
    masks = []
    for k, cols in enumerate([slice(0, 160), slice(160, 320)]):
        m = np.zeros(shape, np.uint8)
        m[:, cols] = 255
        path = run.parent / f"{['left', 'right'][k]}.tif"
        write_imagej_tiff(path, m, axes="YX", pixel_size_um=px)
        masks.append(str(path))
    res = cmd_regions({"masks": masks}, {}, run)
    _bridge_ready(res)
    assert res.diagnostics["names"] == {"1": "left", "2": "right"}
    # areas come before detection: counts of 0, no warning for the usual order
    assert res.warnings == []
    half_cm2 = 240 * 160 * px**2 / 1e8
    assert res.diagnostics["area_cm2"]["1"] == pytest.approx(half_cm2)
    cmd_detect({}, {}, run)
    res = cmd_stats({}, {"bins_um": [0, 100, 200, 1000]}, run)
    _bridge_ready(res)
    with open(run / "regions.csv", newline="") as fh:
        rows = list(csv.DictReader(fh))
    table = read_protrusions_csv(run / "protrusions.csv")
    n_left = int((np.rint(table["x_px"]) < 160).sum())
    assert [r["name"] for r in rows] == ["left", "right", "all areas"]
    assert int(rows[0]["count"]) == n_left
    assert float(rows[0]["density_per_cm2"]) == pytest.approx(n_left / half_cm2, rel=1e-6)
    assert "count_200-1000um" in rows[0]
    assert (run / "report.html").is_file() and (run / "figures" / "histograms.png").is_file()
    assert any(o.kind == "html" for o in res.outputs)
    # a table compared with itself: everything matched
    res = cmd_compare({"a": str(run / "protrusions.csv"), "b": str(run / "protrusions.csv")}, {},
                      run)
    _bridge_ready(res)
    assert res.diagnostics["matched"] == len(table["id"])
    assert res.diagnostics["missed"] == res.diagnostics["extra"] == 0
    with open(run / "comparison.csv", newline="") as fh:
        comp_rows = list(csv.DictReader(fh))
    assert [r["name"] for r in comp_rows] == ["left", "right", "all areas"]
    assert (run / "figures" / "comparison_map.png").is_file()
    # the report picks up the comparison
    cmd_stats({}, {}, run)
    text = (run / "report.html").read_text()
    assert "figures/comparison_map.png" in text and "figures/comparison.png" in text


def test_regions_auto_writes_imagej_label_tiff(run):
    res = cmd_regions({}, {"auto": True, "n_areas": 3}, run)
    with tifffile.TiffFile(run / "regions_labels.tif") as tif:
        assert tif.is_imagej
        data = tif.asarray()
    assert data.shape == (240, 320) and res.diagnostics["n_areas"] == len(np.unique(data)) <= 3


def test_wand_default_outlines_each_clicked_protrusion_and_names_repeated_clicks(run, capture):
    """The relative wand (no tolerance given) outlines every protrusion >= 100 um of the run's albedo
    within 0.5-2x its true area; a second click on one is named, not counted."""
    p = capture.protrusions
    big = p["width_um"] >= 100
    pts = np.column_stack([p["x_px"][big], p["y_px"][big]]).astype(int)
    seeds = run.parent / "points_relative.csv"
    rows = pts.tolist() + [pts[0].tolist()]                       # the first protrusion clicked twice
    seeds.write_text("x_px,y_px\n" + "".join(f"{x},{y}\n" for x, y in rows))
    res = cmd_wand({"points": str(seeds)}, {}, run)
    labels = read_tiff(run / "protrusions_manual_labels.tif").data
    area = np.bincount(labels.ravel())[labels[pts[:, 1], pts[:, 0]]]
    ratio = area * capture.spec.pixel_size_um ** 2 / (np.pi * (p["width_um"][big] / 2) ** 2)
    assert np.mean((ratio >= 0.5) & (ratio <= 2)) >= 0.9, ratio
    assert res.diagnostics["n_protrusions"] == len(pts) and res.diagnostics["repeated_clicks"] == [len(pts) + 1]
    assert res.text == (f"{len(pts) + 1} clicks: {len(pts)} outlined, 1 not (click {len(pts) + 1} repeats click 1 "
                        f"at ({pts[0][0]}, {pts[0][1]}) px)")
    # the repeat stays in the table as a click, not counted
    rows = read_protrusions_csv(run / "protrusions_manual.csv", clicks=True)
    assert rows["counted"].tolist() == ["1"] * len(pts) + ["0"] and "click 1" in rows["note"][-1]
    assert not (run / "protrusions.csv").exists() or "wand" not in (run / "protrusions.csv").read_text()


@pytest.mark.parametrize("cmd, inputs, params, match", [
    (cmd_regions, {}, {}, "exactly one of"),
    (cmd_regions, {"labels": "WRONG"}, {}, "expected the capture's 240 x 320"),
    (cmd_stats, {}, {}, "no protrusions.csv"),
    (cmd_stats, {}, {"table": "missing.csv"}, "missing.csv does not exist"),
    (cmd_wand, {"points": [[10, 10]]}, {"method": "imagej"}, "tolerance"),
    (cmd_wand, {"points": [[10, 10]]}, {"tolerance": 1.5}, "tolerance"),
    (cmd_wand, {}, {"tolerance": 0.1}, "points"),
    (cmd_compare, {"a": "x.csv"}, {}, "inputs.b"),
    (cmd_detect, {}, {"regions": "WRONG"}, "expected the capture's 240 x 320"),
    (cmd_detect, {}, {"pixel_size_um": -3}, "pixel_size_um"),
])
def test_bad_input(run, cmd, inputs, params, match):
    wrong = run.parent / "wrong.tif"
    write_imagej_tiff(wrong, np.ones((10, 10), np.uint8), axes="YX", pixel_size_um=15.0)
    inputs = {k: (str(wrong) if v == "WRONG" else v) for k, v in inputs.items()}
    params = {k: (str(wrong) if v == "WRONG" else v) for k, v in params.items()}
    before = sorted(p.name for p in run.iterdir())
    with pytest.raises(UVPSInputError, match=match) as exc:
        cmd(inputs, params, run)
    assert "\n" not in str(exc.value)
    assert sorted(p.name for p in run.iterdir()) == before  # nothing half-written


def test_detect_needs_depth(tmp_path, template):
    d = tmp_path / "run"
    d.mkdir()
    shutil.copy(template / "albedo.tif", d)
    with pytest.raises(UVPSInputError, match="no depth.tif; run the 'integrate' command"):
        cmd_detect({}, {}, d)


def test_imagej_wand_at_a_tolerance_below_the_noise_says_so(run, capture):
    """ImageJ's wand at Fiji's default tolerance (0.05 albedo units, raw counts of thousands):
    each click, and a second click beside the first on the same protrusion, selects its own pixel
    only; the one warning names those clicks and says to raise the tolerance (not to use method
    'imagej', which is the method used)."""
    albedo = np.moveaxis(capture.albedo, -1, 0) * 30000.0        # raw counts, as a real albedo
    albedo += np.random.default_rng(0).normal(0.0, 100.0, albedo.shape)   # with a camera's noise
    write_imagej_tiff(run / "albedo.tif", albedo.astype(np.float32), axes="CYX",
                      pixel_size_um=capture.spec.pixel_size_um)
    p = capture.protrusions
    big = np.argsort(-p["width_um"])[:3]
    pts = np.column_stack([p["x_px"][big], p["y_px"][big]]).astype(int).tolist()
    pts.append([pts[0][0] + 1, pts[0][1]])
    res = cmd_wand({"points": pts}, {"method": "imagej", "tolerance": 0.05}, run)
    assert res.diagnostics["not_outlined_clicks"] == [1, 2, 3, 4]
    lines = [w for w in res.warnings if "own pixel" in w]
    assert len(lines) == 1 and "4 clicks" in lines[0] and "tolerance of 0.05" in lines[0], res.warnings
    assert "raise it" in lines[0] and "use method 'imagej'" not in lines[0]
