"""Tests of uvps.report.page: the HTML report and its figures on hand-made run folders."""
import json
import re
from pathlib import Path

import numpy as np
import pytest
from matplotlib.image import imread

from uvps.core.detect import REJECTION_WORDS
from uvps.errors import UVPSInputError
from uvps.files.io import write_imagej_tiff
from uvps.core.measure import measure_protrusions
from uvps.files.tables import write_label_tiff, write_protrusions_csv
from uvps.report.page import write_report

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
    # summary, methods in words, warnings, the stats and comparison tables
    assert "Frankot" in text and "light 3 is partly saturated" in text
    assert "3 protrusions</b>" in text and "3 by relief alone" in text
    assert "regions.csv" in text and "Two methods" in text and "93" in text
    assert not list(tmp_path.glob("figures/.*")) and not list(tmp_path.glob(".*"))


def test_partial_run_folder(tmp_path):
    _run_folder(tmp_path, lights=False, normals=False, albedo=False)
    (tmp_path / "run.json").unlink()
    text = write_report(tmp_path).read_text()
    figs = {p.name for p in (tmp_path / "figures").glob("*.png")}
    assert figs == {"height.png", "detail3d.png", "histograms.png"}
    assert "lights.png: lights.json missing" in text
    assert "normals.png: normals.tif missing" in text
    assert "run summary: run.json missing" in text
    assert "lights.png" not in re.findall(r"src='figures/([^']+)'", text)


def test_height_only_without_protrusions(tmp_path):
    height, _ = _domes()
    write_imagej_tiff(tmp_path / "depth.tif", height, axes="YX", pixel_size_um=PX)
    text = write_report(tmp_path).read_text()
    assert "the highest point (no protrusions)" in text.lower()
    assert "not counted (no protrusion table" in text
    _check_png(tmp_path / "figures" / "detail3d.png")


def test_missing_run_folder(tmp_path):
    with pytest.raises(UVPSInputError, match="does not exist"):
        write_report(tmp_path / "nope")


def test_far_lights_figure_shows_elevations(tmp_path):
    """Far lights have no position: the second panel gives each lamp's elevation instead."""
    from uvps.report.page import plot_lights

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
    assert "3 protrusions</b>" in text


def test_images_of_different_sizes_are_refused(tmp_path):
    _run_folder(tmp_path)
    write_imagej_tiff(tmp_path / "depth.tif", np.zeros((10, 12), np.float32), axes="YX", pixel_size_um=PX)
    with pytest.raises(UVPSInputError, match="differ in size"):
        write_report(tmp_path)


# ---------------------------------------------------------------------------------------------
# the report as a conservator reads it: summary first, numbers rounded, relative heights unitless


def _visible_text(fragment: str) -> str:
    """The text a reader sees in an HTML fragment (tags dropped, entities decoded, spaces joined)."""
    import html as _html

    text = re.sub(r"<style>.*?</style>", " ", fragment, flags=re.S)
    text = re.sub(r"</?(?:code|b|i|span|a)\b[^>]*>", "", text)     # inline: no space
    return " ".join(_html.unescape(re.sub(r"<[^>]+>", " ", text)).split())


def _realistic_run_json(path, **extra):
    """run.json as `uvps run` writes it, with the unrounded floats it holds."""
    run = {"version": "0.1.0", "command": "run",
           "params": {"lights": None, "pixel_size_um": PX, "degree": 4, "robust": False,
                      "integration": "fc", "regions": "auto", "detect": False, "bins_um": 100.0,
                      "image_shape": [SHAPE[0], SHAPE[1], 3], "bit_depth": "uint16"},
           "inputs": [{"path": f"/captures/uv_{k:02d}.tif", "sha256": "ab" * 32} for k in range(6)],
           "timings_s": {"lights": 50.393, "normals": 1.222},
           "warnings": ["light 3 is partly saturated"],
           "diagnostics": {
               "lights": {"source": "estimated", "n_lights": 6, "m_mm": 80.00000003505616,
                          "final_cost": 2.982970558600815e-05, "height_uncertainty_relative": 0.06734,
                          "direction_uncertainty_deg_max": 2.0067},
               "normals": {"n_invalid": 0, "residual_rms": 0.0054685792293333825},
               "integration": {"method": "fc", "residual_rms": 0.010371931019860229,
                               "height_range_um": [-11.931466102600098, 177.9402313232422]},
               "detect": {"n_protrusions": 3, "by_source": {"height": 3}, "n_craters": 0,
                          "rejected": {"too_small": 0, "ridge": 5, "weave": 2},
                          "noise_um": 0.12617194652557373}}}
    run.update(extra)
    (path / "run.json").write_text(json.dumps(run))


def _named_run_folder(path, **run_extra):
    """The run folder of `_run_folder` with realistic run.json and the areas named in regions.csv
    (the file a user edits): area 1 (left, two domes) "light red", area 2 (right, one) "dark green"."""
    _run_folder(path)
    _realistic_run_json(path, **run_extra)
    (path / "regions.csv").write_text("label,name\n1,light red\n2,dark green\n")


def test_first_section_says_how_many_where_how_sure(tmp_path):
    _named_run_folder(tmp_path)
    text = write_report(tmp_path).read_text()
    # the first section after the title is the summary
    first = re.search(r"</h1>.*?<section id='summary'>(.*?)</section>", text, re.S)
    assert first is not None and "<h2>" not in text[text.index("</h1>"):first.start(1) - 30]
    summary = _visible_text(first.group(1))
    # what was captured: 6 lamps, 120 x 90 px of 20 um = 2.4 x 1.8 mm
    assert "6 UV images" in summary and "20 \u00b5m per pixel" in summary
    assert "2.4 \u00d7 1.8 mm" in summary
    # how many: 3 domes
    assert "3 protrusions" in summary
    # where: the left area holds two of them in half the field, the names from regions.csv
    assert re.search(r"Densest: light red \(93 \u00b1 65 per cm\u00b2\)", summary), summary
    assert "least dense: dark green (46 \u00b1 46 per cm\u00b2)" in summary
    # how sure: the lamps' route, the heights' uncertainty, what was excluded, the warnings
    assert "estimated from the images alone" in summary
    assert "\u00b17 %" in summary
    assert (f"7 of 10 candidate features rejected (5 {REJECTION_WORDS['ridge']}, "
            f"2 {REJECTION_WORDS['weave']})") in summary
    assert "light 3 is partly saturated" in summary
    assert "What counts as a protrusion" in summary
    # methods in words, not a dump of parameters; provenance last
    assert "robust False" not in text and "lights None" not in text and "detect False" not in text
    assert text.index("Appendix A") < text.index("Appendix C") and "abab" in text[text.index("Appendix C"):]


def _significant_digits(token: str) -> int:
    digits = token.lstrip("-\u2212").replace(".", "").lstrip("0")
    return len(digits)


def test_no_number_shows_more_digits_than_it_holds(tmp_path, monkeypatch):
    """Every decimal number in the report's text and in its figures' text has at most 3
    significant digits (hashes and the date in the provenance aside)."""
    import uvps.report.page as rep
    from matplotlib.text import Text

    texts = []
    original = rep.save_figure

    def recording(fig, path):
        texts.extend(t.get_text() for t in fig.findobj(Text))
        return original(fig, path)

    monkeypatch.setattr(rep, "save_figure", recording)
    _named_run_folder(tmp_path)
    lights = json.loads((tmp_path / "lights.json").read_text())
    lights["m_mm"] = 80.00000003505616
    (tmp_path / "lights.json").write_text(json.dumps(lights))
    text = write_report(tmp_path).read_text()
    assert "80.00000003505616" not in text and "0.0054685792293333825" not in text
    body = text[:text.index("<section class='appendix' id='provenance'>")]
    body = body[body.index("</h1>") + 5:]
    body = body[body.index("</p>"):]          # the line with the date and version
    words = _visible_text(body) + " " + " ".join(texts)
    numbers = re.findall(r"(?<![\w.])[-\u2212]?\d+\.\d+", words)
    assert numbers, "no decimal number found: the test reads the wrong text"
    too_long = [n for n in numbers if _significant_digits(n) > 3]
    assert not too_long, too_long
    assert not any("80.000" in t for t in texts)


def test_relative_relief_shows_no_heights_in_micrometres(tmp_path, monkeypatch):
    import uvps.report.page as rep
    from matplotlib.text import Text

    texts = {}
    original = rep.save_figure

    def recording(fig, path):
        texts[Path(path).name] = [t.get_text() for t in fig.findobj(Text)]
        return original(fig, path)

    monkeypatch.setattr(rep, "save_figure", recording)
    _named_run_folder(tmp_path, relief={"scale": "relative", "lamps": "estimated",
                                        "reason": "No sphere and no measured lamp positions "
                                                  "pin the lamps' elevation."})
    text = write_report(tmp_path).read_text()
    visible = _visible_text(text)
    assert "relative only" in visible and "No sphere and no measured lamp positions" in visible
    assert "Height (\u00b5m)" not in visible and "height noise" not in visible
    assert "\u00b17 %" not in visible       # no height scale uncertainty: there is no scale
    assert not re.search(r"heights reach [^.]*\u00b5m", visible)
    # the figures: no micrometres on the height map's bar or the 3-D detail's vertical axis
    assert not any("\u00b5m" in t for t in texts["height.png"] if "height" in t.lower())
    assert any("relative height" in t for t in texts["height.png"])
    assert any("vertical scale relative" in t for t in texts["detail3d.png"])
    # widths are still micrometres
    assert "Width (\u00b5m)" in visible


def _captured(monkeypatch):
    import uvps.report.page as rep

    figs = []
    monkeypatch.setattr(rep, "save_figure", lambda fig, path: figs.append(fig) or Path(path))
    return figs


def test_many_lamps_are_not_labelled_one_by_one(tmp_path, monkeypatch):
    """72 lamps (an RTI dome): coloured by number, at most ~12 tick labels on the bar chart."""
    from uvps.report.page import plot_lights

    figs = _captured(monkeypatch)
    entries = [{"file": f"l{k}.tif", "direction": None, "position_mm": [0.0, 0.0, 100.0 + k],
                "azimuth_deg": 5.0 * k, "elevation_deg": 20.0 + k % 40, "intensity": 1.0}
               for k in range(72)]
    plot_lights({"mode": "near", "lights": entries, "m_mm": 80.00000003505616}, tmp_path / "l.png")
    polar, bars = figs[0].axes[0], figs[0].axes[-1]
    assert polar.name == "polar" and not polar.texts
    labels = [t.get_text() for t in bars.get_xticklabels() if t.get_text()]
    assert 2 <= len(labels) <= 13
    assert "100\u2013170 mm" in bars.get_title()


def test_3d_detail_states_its_vertical_exaggeration(tmp_path, monkeypatch):
    from uvps.report.page import plot_detail_3d

    figs = _captured(monkeypatch)
    height, _ = _domes()
    plot_detail_3d(height, tmp_path / "d.png", pixel_size_um=PX, centre_xy=(90, 45),
                   width_um=28 * PX, what="protrusion 3")
    ax = figs[0].axes[0]
    title = ax.get_title()
    m = re.search(r"vertical exaggeration \u00d7(\d+)", title)
    assert m, title
    stated = float(m.group(1))
    # drawn: the box's height over its width, against the data's height over its width
    bx, _, bz = ax.get_box_aspect()
    xr = np.ptp(ax.get_xlim3d())
    zr = np.ptp(ax.get_zlim3d())
    drawn = (bz / zr) / (bx / xr)
    assert abs(drawn / stated - 1) < 0.15, (drawn, stated)
    assert "\u00b5m" in ax.get_xlabel() and "\u00b5m" in ax.get_zlabel()


def test_height_colour_bar_says_where_it_clips(tmp_path, monkeypatch):
    from uvps.report.page import height_scale, plot_height
    from uvps.report.text import height as height_fmt

    figs = _captured(monkeypatch)
    height, labels = _domes()
    plot_height(height, tmp_path / "h.png", pixel_size_um=PX, labels=labels)
    cbar_ax = figs[0].axes[-1]
    label = cbar_ax.get_ylabel()
    sc = height_scale(height)
    assert sc.clips and sc.max == pytest.approx(height.max())
    assert "clipped" in label and "all heights" in label
    assert height_fmt(height.max()) in label     # the real top: the 40 um dome on its tilt
    assert "beyond the bar" in sc.words()


def test_manual_and_automated_counts_are_compared_when_both_exist(tmp_path):
    """protrusions_manual.csv (the wand) beside protrusions.csv, no comparison.csv: the report
    compares them (map, densities, table) without writing comparison.csv."""
    table = _run_folder(tmp_path)
    manual = {k: np.asarray(v)[:2] for k, v in table.items()}    # the wand found two of three
    write_protrusions_csv(tmp_path / "protrusions_manual.csv", manual)
    text = write_report(tmp_path).read_text()
    linked = set(re.findall(r"src='figures/([a-z_0-9]+)\.png'", text))
    assert {"comparison_map", "comparison"} <= linked
    visible = _visible_text(text)
    assert "Table 4. Two methods: manual (wand) and automated" in visible
    # every manual one matched, one automated extra
    row = re.search(r"all areas [\d.]+ (\d+) (\d+) [\d.]+ [\d.]+ (\d+) (\d+) (\d+)", visible)
    assert row and row.groups() == ("2", "3", "2", "0", "1"), visible[-2000:]
    assert not (tmp_path / "comparison.csv").exists()


@pytest.mark.slow
def test_pdf_printed_by_a_headless_browser(tmp_path):
    """`print_pdf` with the browser on PATH (Debian's chromium when installed): a PDF of the report
    beside it; without one, the one-line message saying what to install."""
    import shutil

    from uvps.report.page import PDF_BROWSERS, print_pdf

    _named_run_folder(tmp_path)
    html_path = write_report(tmp_path)
    if any(shutil.which(b) for b in PDF_BROWSERS):
        pdf = print_pdf(html_path)
        assert pdf == tmp_path / "report.pdf"
        data = pdf.read_bytes()
        assert data[:5] == b"%PDF-" and len(data) > 20000          # the figures are in it
        assert len(re.findall(rb"/Type\s*/Page\b", data)) >= 3
    else:
        with pytest.raises(UVPSInputError, match="apt-get install chromium"):
            print_pdf(html_path)
    assert not list(tmp_path.glob(".report.pdf*"))


def test_pdf_without_a_browser_says_what_to_do(tmp_path, monkeypatch):
    from uvps.report.page import print_pdf

    _run_folder(tmp_path)
    html_path = write_report(tmp_path)
    monkeypatch.setenv("PATH", str(tmp_path / "no-browsers-here"))
    with pytest.raises(UVPSInputError, match=r"^pdf: no Chromium or Chrome on PATH.*apt-get install chromium"):
        print_pdf(html_path)
    # a browser that prints nothing: one line, and no PDF left behind
    fake = tmp_path / "chromium"
    fake.write_text("#!/bin/sh\nexit 3\n")
    fake.chmod(0o755)
    with pytest.raises(UVPSInputError, match=r"printed no PDF of report.html \(exit 3\)"):
        print_pdf(html_path, browser=str(fake))
    assert not (tmp_path / "report.pdf").exists() and not list(tmp_path.glob(".report.pdf*"))


def test_lamps_from_a_calibration_folder_name_its_route(tmp_path):
    """A run with --calibration CAL (contract B): the summary names the folder and how it measured
    the lamps; no scale uncertainty from an estimate is claimed."""
    cal = tmp_path / "cal_2024"
    cal.mkdir()
    (cal / "calibration.json").write_text(json.dumps({"format": "uvps-calibration", "version": 1,
                                                      "route": "spheres"}))
    run_dir = tmp_path / "run"
    run_dir.mkdir()
    _named_run_folder(run_dir, relief={"scale": "absolute", "lamps": "calibration", "reason": ""})
    run = json.loads((run_dir / "run.json").read_text())
    run["params"]["calibration"] = str(cal)
    del run["diagnostics"]["lights"]["height_uncertainty_relative"]
    (run_dir / "run.json").write_text(json.dumps(run))
    summary = _visible_text(re.search(r"<section id='summary'>(.*?)</section>",
                                      write_report(run_dir).read_text(), re.S).group(1))
    assert "Lamps: from a calibration folder (uvps calibrate) (cal_2024: reference spheres " \
           "photographed under each lamp)" in summary
    assert "scale set by the given lamps" in summary


def _random_labels(seed: int, zero_fraction: float, trials: int = 300):
    """Small label images (1-29 px a side, up to 6 labels, a share of background) to hold OpenCV's
    morphology against scikit-image's."""
    rng = np.random.default_rng(seed)
    for trial in range(trials):
        m, n = (int(v) for v in rng.integers(1, 30, 2))
        labels = rng.integers(0, int(rng.integers(1, 7)), (m, n))
        labels[rng.random((m, n)) < zero_fraction] = 0
        yield trial, labels


def test_outlines_are_scikit_images_outer_boundaries_pixel_for_pixel():
    # the report draws protrusion outlines with OpenCV's morphology (0.07 against 0.34 s at
    # 3000 x 4000); they must be find_boundaries(mode="outer")'s, at the image's edges, where two
    # objects touch, and for every label type the pipeline writes
    from skimage.segmentation import find_boundaries
    from uvps.report.page import outer_boundaries

    for trial, labels in _random_labels(4, 0.4):
        want = find_boundaries(labels.astype(np.int32), mode="outer")
        for kind in (np.int32, np.uint16, np.uint32, np.int64):
            # against int32's: with int64 labels find_boundaries lifts the background to 2^63 - 1,
            # which ndimage's morphology does not hold exactly, and marks objects' own edges
            assert np.array_equal(outer_boundaries(labels.astype(kind)), want), (trial, kind)
    big = np.zeros((40, 50), np.int32)
    big[5:9, 5:9], big[5:9, 9:12] = 70000, 3          # a label above uint16, touching another
    assert np.array_equal(outer_boundaries(big), find_boundaries(big, mode="outer"))
    assert outer_boundaries(big).sum() > 0


def test_area_borders_are_scikit_images_inner_boundaries_pixel_for_pixel():
    # the colour-area figure, the painting overview and its deep-zoom layer draw area borders with
    # OpenCV's morphology; they must be find_boundaries(mode="inner")'s, at the image's edges, where
    # areas touch and for every label type (bool masks included)
    from skimage.segmentation import find_boundaries
    from uvps.errors import UVPSInputError
    from uvps.report.page import inner_boundaries

    for trial, labels in _random_labels(5, 0.3):
        want = find_boundaries(labels.astype(np.int32), mode="inner")
        for kind in (np.int32, np.uint8, np.uint16, np.uint32, np.int64):
            assert np.array_equal(inner_boundaries(labels.astype(kind)), want), (trial, kind)
        assert np.array_equal(inner_boundaries(labels > 0), find_boundaries(labels > 0, mode="inner"))
    big = np.zeros((40, 50), np.int32)
    big[5:9, 5:9], big[5:9, 9:12] = 70000, 3                              # above uint16: float32
    assert np.array_equal(inner_boundaries(big), find_boundaries(big, mode="inner"))
    big[20:, 30:] = 2 ** 25                                                 # above float32's: float64
    assert np.array_equal(inner_boundaries(big), find_boundaries(big, mode="inner"))
    assert inner_boundaries(big)[20:, 30:].sum() == 20 + 20 - 1   # its top row and left column: not the image's edges
    with pytest.raises(UVPSInputError, match="non-negative"):
        inner_boundaries(np.array([[0, -1], [2, 2]]))
    assert inner_boundaries(np.zeros((0, 5), np.int32)).shape == (0, 5)


def test_float_protrusion_labels_with_nan_are_outlined_and_negative_ones_refused_by_name(tmp_path):
    # a float label TIFF (as some Fiji workflows save one) with NaN or infinite background is outlined
    # as its integer labels are; a label below 0 is refused naming the file, not outlined wrongly; a label
    # TIFF of another size than the run's images is left out, as before
    import re

    from uvps.errors import UVPSInputError

    _, labels = _domes()
    figures = {}
    for case, background in (("int", None), ("nan", np.nan), ("inf", np.inf)):
        d = tmp_path / case
        d.mkdir()
        _run_folder(d)
        if background is not None:
            f = labels.astype(np.float32)
            f[labels == 0] = background
            write_imagej_tiff(d / "protrusions_labels.tif", f, axes="YX", pixel_size_um=PX)
        html = write_report(d, bins_um=100.0).read_text()
        assert "albedo.png" in re.findall(r"src='figures/([a-z0-9]+\.png)'", html)
        figures[case] = {n: (d / "figures" / n).read_bytes() for n in ("albedo.png", "height.png")}
    assert figures["nan"] == figures["int"] and figures["inf"] == figures["int"]
    d = tmp_path / "negative"
    d.mkdir()
    _run_folder(d)
    bad = labels.astype(np.int32)
    bad[0, 0] = -2
    write_imagej_tiff(d / "protrusions_labels.tif", bad, axes="YX", pixel_size_um=PX)
    with pytest.raises(UVPSInputError, match=r"protrusions_labels\.tif: protrusion labels must be integers "
                                             r"from 0 .* found -2 to"):
        write_report(d, bins_um=100.0)
    write_imagej_tiff(d / "protrusions_labels.tif", bad[:-1], axes="YX", pixel_size_um=PX)
    assert write_report(d, bins_um=100.0).is_file()          # not the run's size: left out


def test_the_painting_overview_is_drawn_at_its_figures_width_and_keeps_thin_outlines():
    from skimage.segmentation import find_boundaries

    from uvps.report.page import FIGURE_DPI
    from uvps.report.painting import FIGURE_WIDTH_IN, _at_most

    width = FIGURE_WIDTH_IN * FIGURE_DPI
    for edge in range(1490, 1500):                      # wherever the edge falls in the 3.3 px a pixel averages
        labels = np.ones((300, 3000), np.int32)
        labels[:, edge:] = 2                            # one vertical paint edge, its outline 2 px wide
        labels[:, 2500:] = 0                            # and a paint beside no area: its outline 1 px wide
        edges = find_boundaries(labels, mode="inner")
        small = _at_most(edges, width)
        assert small.shape == (90, width) and small.dtype == bool
        assert (small.sum(axis=1) >= 2).all()           # every row still shows both outlines
        assert small.sum(axis=1).max() <= 4             # and neither widened beyond the pixels it falls in
    rgb = np.full((300, 3000, 3), 7.0)
    rgb[:, 1500:] = 21.0
    a = _at_most(rgb, width)
    assert a.shape == (90, width, 3)
    assert np.isclose(a.mean(), rgb.mean(), rtol=1e-4)  # area averaging: the levels are kept
    little = np.zeros((10, width))
    assert _at_most(little, width) is little            # an overview already that small is drawn as it is


def test_the_painting_report_counts_every_protrusion_and_names_those_in_no_area(tmp_path):
    from uvps.core.mosaic import Registration
    from uvps.report.painting import write_painting_report

    albedo = np.full((40, 60, 3), 100.0, np.float32)
    labels = np.zeros((40, 60), np.int32)
    labels[:, :30] = 1                                  # one paint on the left; the right in no area
    kept = [{"X": 5.0, "Y": 5.0, "width_um": 80.0, "area": "area 1"},
            {"X": 12.0, "Y": 30.0, "width_um": 120.0, "area": "area 1"},
            {"X": 50.0, "Y": 20.0, "width_um": 70.0, "area": ""}]
    areas = {"area 1": {"label": 1, "tiles": 1, "area_cm2": 0.0608, "count": 2, "density_per_cm2": 32.9}}
    page = write_painting_report(tmp_path, albedo=albedo, labels=labels, covered=np.ones((40, 60), bool),
                                 kept=kept, areas=areas, registration=Registration({"t": (0.0, 0.0)}, []),
                                 shapes={"t": (40, 60)}, origin=(0, 0), step=1, pixel_size_um=15.0).read_text()
    # the heading counts the 3 the overview draws and the tables list, not the 2 the areas hold
    assert "The painting: 1 tile, 3 protrusions</h1>" in page
    assert "<p>1 protrusion lies in no colour area" in page
    kept[2]["area"] = "area 1"
    areas["area 1"]["count"] = 3
    page = write_painting_report(tmp_path, albedo=albedo, labels=labels, covered=np.ones((40, 60), bool),
                                 kept=kept, areas=areas, registration=Registration({"t": (0.0, 0.0)}, []),
                                 shapes={"t": (40, 60)}, origin=(0, 0), step=1, pixel_size_um=15.0).read_text()
    assert "3 protrusions</h1>" in page and "in no colour area" not in page


def _report_case(folder: Path, case: str) -> None:
    if case == "partial":
        _run_folder(folder, lights=False, normals=False, albedo=False)
        (folder / "run.json").unlink()
    elif case == "no pixel size":
        _run_folder(folder, lights=False)
        _strip_calibration(folder)
        (folder / "protrusions_labels.tif").unlink()
        (folder / "run.json").unlink()
    elif case == "no images":
        _run_folder(folder, normals=False, albedo=False)
        (folder / "depth.tif").unlink()
    elif case == "no lamps, no height":
        _run_folder(folder, lights=False)
        (folder / "depth.tif").unlink()
        (folder / "protrusions.csv").unlink()
    else:
        _run_folder(folder)


#: Each case's figures as the HTML shows them and the figures not drawn, in order, as the report drew them one
#: figure after the other (before its figures were drawn in two threads).
_REPORT_CASES = {
    "full": (["albedo", "height", "histograms", "regions", "detail3d", "normals", "lights"], []),
    "partial": (["height", "histograms", "detail3d"],
                ["run summary: run.json missing", "lights.png: lights.json missing", "normals.png: normals.tif missing",
                 "albedo.png: albedo.tif missing"]),
    "no pixel size": ([], ["run summary: run.json missing", "lights.png: lights.json missing",
                           "image figures: no pixel size (no calibrated TIFF, run.json)",
                           "histograms.png: no image size or pixel size for the colour areas"]),
    "no images": (["histograms", "lights"], ["normals.png: normals.tif missing", "albedo.png: albedo.tif missing",
                                             "height.png, detail3d.png: depth.tif missing"]),
    "no lamps, no height": (["albedo", "regions", "normals"],
                            ["lights.png: lights.json missing", "height.png, detail3d.png: depth.tif missing",
                             "histograms.png: protrusions.csv missing"]),
}


@pytest.mark.parametrize("case", list(_REPORT_CASES))
def test_figures_drawn_in_two_threads_are_those_of_one(tmp_path, monkeypatch, case):
    """The figures are drawn in two threads: the HTML shows the figures and lists those not drawn in the order
    the report met them one after the other, and every PNG is the one-thread PNG byte for byte."""
    from concurrent.futures import ThreadPoolExecutor
    import os

    import uvps.core.threads as th

    pools = []
    monkeypatch.setattr(th, "ThreadPoolExecutor", lambda n, **kw: pools.append(n) or ThreadPoolExecutor(n, **kw))
    texts, pngs = {}, {}
    for threads in ("1", "2"):
        folder = tmp_path / threads / "run"
        folder.mkdir(parents=True)
        _report_case(folder, case)
        monkeypatch.setenv(th.THREADS_VARIABLE, threads)
        pools.clear()
        texts[threads] = write_report(folder, title="t").read_text().replace(str(folder), "F")
        pngs[threads] = {p.name: p.read_bytes() for p in sorted((folder / "figures").glob("*.png"))}
        assert pools == ([1] if threads == "2" and len(os.sched_getaffinity(0)) >= 2 else [])
        shown, skipped = _REPORT_CASES[case]
        assert re.findall(r"src='figures/([a-z0-9]+)\.png'", texts[threads]) == shown
        assert re.findall(r"<li>([^<]*(?:missing|no pixel size|no image size)[^<]*)</li>", texts[threads]) == skipped
    strip = lambda t: re.sub(r"written \S+ \S+ UTC", "", t)     # noqa: E731 - the minute it was written
    assert strip(texts["1"]) == strip(texts["2"])
    assert pngs["1"] == pngs["2"] and len(pngs["1"]) == len(_REPORT_CASES[case][0])
