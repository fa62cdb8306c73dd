"""Tests of uvps.report: the HTML report and its figures on hand-made run folders."""
import json
import re

import numpy as np
import pytest
from matplotlib.image import imread

from uvps.errors import UVPSInputError
from uvps.io import write_imagej_tiff
from uvps.measure import measure_protrusions, write_label_tiff, write_protrusions_csv
from uvps.report import write_report

PX = 20.0
SHAPE = (90, 120)


def _domes():
    """Three domes (radius 6, 9, 14 px; 10, 20, 40 um high) on a tilted plane; labels = discs."""
    rr, cc = np.mgrid[: SHAPE[0], : SHAPE[1]]
    height = 0.02 * cc
    labels = np.zeros(SHAPE, np.int32)
    for k, (r, c, rad, h) in enumerate([(20, 25, 6, 10), (60, 40, 9, 20), (45, 90, 14, 40)], 1):
        rho2 = ((rr - r) ** 2 + (cc - c) ** 2) / rad**2
        height += np.where(rho2 < 1, h * (1 - rho2), 0)
        labels[rho2 <= 1] = k
    return height.astype(np.float32), labels


def _normals(height):
    gy, gx = np.gradient(height / PX)
    n = np.stack([-gx, gy, np.ones_like(gx)])  # y up: dz/dy = -dz/drow
    return (n / np.linalg.norm(n, axis=0)).astype(np.float32)


def _run_folder(path, *, lights=True, normals=True, albedo=True):
    height, labels = _domes()
    alb = np.stack([np.full(SHAPE, 0.6), np.full(SHAPE, 0.4), np.full(SHAPE, 0.2)])
    alb[:, labels > 0] = 0.9
    alb[:, :, 60:] *= 0.5  # a darker right half: a second colour area
    write_imagej_tiff(path / "depth.tif", height, axes="YX", pixel_size_um=PX)
    if albedo:
        write_imagej_tiff(path / "albedo.tif", alb.astype(np.float32), axes="CYX", pixel_size_um=PX)
    if normals:
        write_imagej_tiff(path / "normals.tif", _normals(height), axes="CYX", pixel_size_um=PX)
    if lights:
        az = np.arange(6) * 60.0
        el = np.full(6, 35.0)
        entries = [{"file": f"l{k}.tif", "direction": None,
                    "position_mm": [300 * np.cos(np.radians(a)), 300 * np.sin(np.radians(a)),
                                    300 * np.tan(np.radians(e))],
                    "azimuth_deg": a, "elevation_deg": e, "intensity": 1.0}
                   for k, (a, e) in enumerate(zip(az, el))]
        (path / "lights.json").write_text(json.dumps(
            {"mode": "near", "pixel_size_um": PX, "image_shape": list(SHAPE), "lights": entries,
             "m_mm": 300.0}))
    (path / "run.json").write_text(json.dumps(
        {"params": {"degree": 4, "integration": "fc", "pixel_size_um": PX},
         "warnings": ["light 3 is partly saturated"]}))
    regions = np.where(np.arange(SHAPE[1])[None, :] < 60, 1, 2) * np.ones(SHAPE, np.int32)
    write_imagej_tiff(path / "regions_labels.tif", regions.astype(np.int32), axes="YX",
                      pixel_size_um=PX)
    table = measure_protrusions(labels, albedo=alb, height_um=height, pixel_size_um=PX,
                                regions=regions, source="height")
    write_protrusions_csv(path / "protrusions.csv", table)
    write_label_tiff(path / "protrusions_labels.tif", labels, pixel_size_um=PX)
    return table


def _check_png(path):
    img = imread(path)
    assert img.ndim == 3 and min(img.shape[:2]) >= 200
    colours = np.unique((img[..., :3] * 255).astype(np.uint8).reshape(-1, 3), axis=0)
    assert len(colours) > 50, f"{path.name} looks blank"
    return img


def test_full_report(tmp_path):
    _run_folder(tmp_path)
    (tmp_path / "comparison.csv").write_text(
        "label,name,area_cm2,count_a,count_b,density_a,density_b,matched,missed,extra\n"
        "1,area 1,0.0216,2,1,92.6,46.3,1,1,0\n2,area 2,0.0216,1,1,46.3,46.3,1,0,0\n"
        "all,all areas,0.0432,3,2,69.4,46.3,2,1,0\n")
    out = write_report(tmp_path, bins_um=100.0)
    assert out == tmp_path / "report.html"
    text = out.read_text()
    expected = {"lights", "normals", "albedo", "height", "detail3d", "regions", "histograms",
                "comparison"}
    linked = set(re.findall(r"src='figures/([a-z0-9]+)\.png'", text))
    assert linked == expected
    for name in expected:
        _check_png(tmp_path / "figures" / f"{name}.png")
    # the protrusion outlines are drawn in pure red on the height map
    img = _check_png(tmp_path / "figures" / "height.png")
    red = (img[..., 0] > 0.95) & (img[..., 1] < 0.05) & (img[..., 2] < 0.05)
    assert red.sum() > 50
    # summary: parameters, counts, warnings, the stats and comparison tables
    assert "integration" in text and "light 3 is partly saturated" in text
    assert "<b>3</b> protrusions" in text and "height: 3" in text
    assert "regions.csv" in text and "Comparison" in text and "92.6" in text
    assert not list(tmp_path.glob("figures/.*")) and not list(tmp_path.glob(".*"))


def test_partial_run_folder(tmp_path):
    _run_folder(tmp_path, lights=False, normals=False, albedo=False)
    (tmp_path / "run.json").unlink()
    text = write_report(tmp_path).read_text()
    figs = {p.name for p in (tmp_path / "figures").glob("*.png")}
    assert figs == {"height.png", "detail3d.png", "histograms.png"}
    assert "lights.png: lights.json missing" in text
    assert "normals.png: normals.tif missing" in text
    assert "No run.json" in text
    assert "lights.png" not in re.findall(r"src='figures/([^']+)'", text)


def test_height_only_without_protrusions(tmp_path):
    height, _ = _domes()
    write_imagej_tiff(tmp_path / "depth.tif", height, axes="YX", pixel_size_um=PX)
    text = write_report(tmp_path).read_text()
    assert "the highest point (no protrusions)" in text
    assert "No protrusions.csv" in text
    _check_png(tmp_path / "figures" / "detail3d.png")


def test_missing_run_folder(tmp_path):
    with pytest.raises(UVPSInputError, match="does not exist"):
        write_report(tmp_path / "nope")


def test_far_lights_figure_shows_elevations(tmp_path):
    """Far lights have no position: the second panel gives each lamp's elevation instead."""
    from uvps.report import plot_lights

    lights = {"mode": "far", "lights": [
        {"file": f"l{k}.tif", "direction": [0.5, 0.0, 0.866], "position_mm": None,
         "azimuth_deg": 45.0 * k, "elevation_deg": 20.0 + 5 * k, "intensity": 1.0}
        for k in range(8)]}
    _check_png(plot_lights(lights, tmp_path / "lights.png"))
    with pytest.raises(UVPSInputError, match="no 'lights'"):
        plot_lights({"mode": "far", "lights": []}, tmp_path / "x.png")


def _strip_calibration(path):
    """Rewrite the run folder's image TIFFs without a pixel size (as a plain TIFF writer leaves them)."""
    import tifffile

    for name in ("albedo.tif", "depth.tif", "normals.tif"):
        tifffile.imwrite(path / name, tifffile.imread(path / name), photometric="minisblack")


def test_uncalibrated_tiffs_take_the_pixel_size_from_run_json(tmp_path):
    """TIFFs without a pixel size: the report takes it from run.json and draws every figure."""
    _run_folder(tmp_path)
    _strip_calibration(tmp_path)
    (tmp_path / "protrusions_labels.tif").unlink()   # nor from the labels
    (tmp_path / "lights.json").unlink()              # nor from lights.json
    text = write_report(tmp_path).read_text()
    figs = {p.name for p in (tmp_path / "figures").glob("*.png")}
    assert {"normals.png", "albedo.png", "height.png", "detail3d.png", "histograms.png"} <= figs
    assert "image figures" not in text


def test_no_pixel_size_anywhere_skips_the_image_figures(tmp_path):
    """No pixel size in the TIFFs, run.json or lights.json: the report is written without the image
    figures and says why (no error)."""
    _run_folder(tmp_path, lights=False)
    _strip_calibration(tmp_path)
    (tmp_path / "protrusions_labels.tif").unlink()
    (tmp_path / "run.json").unlink()
    text = write_report(tmp_path).read_text()
    assert not list((tmp_path / "figures").glob("*.png"))
    assert "image figures: no pixel size" in text
    assert "<b>3</b> protrusions" in text


def test_images_of_different_sizes_are_refused(tmp_path):
    _run_folder(tmp_path)
    write_imagej_tiff(tmp_path / "depth.tif", np.zeros((10, 12), np.float32), axes="YX", pixel_size_um=PX)
    with pytest.raises(UVPSInputError, match="differ in size"):
        write_report(tmp_path)
