"""``uvps changes``: two run folders of one region, years apart (:mod:`uvps.core.changes` does the
numbers): the dates read, ``changes.csv``, ``registration.json``, ``height_change.tif``, the report.
"""
from __future__ import annotations

import html
import json
import logging
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Optional

import cv2
import numpy as np
from scipy import ndimage

from .. import __version__
from ..errors import UVPSInputError
from ..files.io import read_tiff, sha256_file, write_imagej_tiff
from ..files.tables import atomic_write_text, read_protrusions_csv, table_to_csv_text
from ..files.outputs import CommandResult, OutputSpec, Progress, atomic_output_dir, report, write_json_atomic
from ..files.tables import read_region_names
from ..report.page import CSS, display_albedo, display_step, extent_mm, figure, save_figure, table_html
from ..files.calibration import calibration_of_run
from ..files.runfolder import FILES, RunLog, read_run
from ..spec import CommandSpec, Param

from ..core.changes import (COLUMNS, NOISE_MODEL, STATUSES, NoiseModel, Registration, _overlap_mask, area_table,
                            classify_changes, level_heights, register, warp_to_a)

log = logging.getLogger(__name__)

def write_changes_csv(path, rows: dict) -> None:
    """``changes.csv`` (columns :data:`COLUMNS`; empty where a protrusion is absent), atomically."""
    out = {}
    for c in COLUMNS:
        v = rows[c]
        if c in ("id_a", "id_b"):
            out[c] = np.array(["" if x == 0 else str(int(x)) for x in v], dtype=object)
        else:
            out[c] = v
    atomic_write_text(path, table_to_csv_text(out, COLUMNS))


_MARK = {"unchanged": ("#f4f4f4", "o"), "shrunk": ("#fdae61", "s"), "gone": ("#2c7bb6", "x"),
         "merged": ("#7b3294", "D"), "split": ("#c51b7d", "D"), "grown": ("#d7191c", "o"),
         "new": ("#1a9641", "o")}


def _marks(ax, rows, pos, step, px_um, shape, *, statuses=("shrunk", "gone", "merged", "split", "grown", "new")):
    ext = extent_mm(shape, px_um)
    for s in statuses:
        colour, marker = _MARK[s]
        sel = rows["status"] == s
        if sel.any():
            x = ext[0] + (pos[sel, 0] + 0.5) * px_um / 1000.0
            y = ext[3] - (pos[sel, 1] + 0.5) * px_um / 1000.0
            ax.scatter(x, y, s=30, **({"c": colour} if marker == "x" else {"facecolors": "none", "edgecolors": colour}),
                       marker=marker, linewidths=1.0, label=f"{s} ({int(sel.sum())})")


def _change_map_figure(path: Path, res: dict, step: int) -> None:
    """The change map: A's albedo in grey, every protrusion of either date drawn at its place and
    size (a circle of its width, B's for new ones) in its status's colour, with a legend of the
    counts; grown, new, gone and unchanged told apart at a glance."""
    from matplotlib.collections import PatchCollection
    from matplotlib.lines import Line2D
    from matplotlib.patches import Circle

    a = res["a"]
    rows, pos, px, shape = res["rows"], res["positions_a"], a.pixel_size_um, a.height.shape
    ext = extent_mm(shape, px)
    grey = display_albedo(a.albedo, step)
    if grey.ndim == 3:
        grey = grey.mean(axis=2)
    fig = figure((10, 8 * shape[0] / shape[1] + 0.8))
    ax = fig.add_subplot(1, 1, 1)
    ax.imshow(0.15 + 0.45 * grey, cmap="gray", vmin=0, vmax=1, extent=ext)
    width = np.where(np.isfinite(rows["width_um_a"]), rows["width_um_a"], rows["width_um_b"])
    handles = []
    for s in ("unchanged", "shrunk", "merged", "split", "gone", "grown", "new"):
        colour, _ = _MARK[s]
        sel = np.flatnonzero(rows["status"] == s)
        if sel.size == 0:
            continue
        x = ext[0] + (pos[sel, 0] + 0.5) * px / 1000.0
        y = ext[3] - (pos[sel, 1] + 0.5) * px / 1000.0
        r = np.maximum(np.nan_to_num(width[sel]) / 2000.0, 1.5 * px / 1000.0)
        filled = s in ("grown", "new")
        circles = [Circle((xi, yi), ri) for xi, yi, ri in zip(x, y, r)]
        ax.add_collection(PatchCollection(
            circles, facecolors=colour if filled else "none", edgecolors=colour,
            alpha=0.85 if filled else 1.0, linewidths=0.8 if s == "unchanged" else 1.6,
            linestyles="--" if s == "gone" else "-"))
        handles.append(Line2D([], [], marker="o", linestyle="none", markersize=9,
                              markerfacecolor=colour if filled else "none",
                              markeredgecolor="#777777" if s == "unchanged" else colour,
                              markeredgewidth=1.6, label=f"{s} ({sel.size})"))
    ax.set_xlim(ext[0], ext[1])
    ax.set_ylim(ext[2], ext[3])
    ax.set_xlabel("x (mm)")
    ax.set_ylabel("y (mm)")
    ax.set_title("changes B - A in A's frame (circles at each protrusion's width)")
    if handles:
        ax.legend(handles=handles, loc="upper left", bbox_to_anchor=(1.01, 1.0), fontsize=9, frameon=False)
    save_figure(fig, path)


def write_changes_report(folder: Path, res: dict) -> Path:
    """``report.html`` and ``figures/changes_*.png`` of :func:`compute_changes`'s result."""
    shape = res["a"].height.shape
    step = max(display_step(shape), int(np.ceil(max(shape) / 800)))   # figures of ~800 px: fast
    _change_map_figure(folder / "figures" / "changes_map.png", res, step)
    _dates_figure(folder / "figures" / "changes_dates.png", res, step)
    if res["diagnostics"]["uncertainty"]["heights"]:
        _height_change_figure(folder / "figures" / "changes_height.png", res, step)
    _registration_figure(folder / "figures" / "changes_registration.png", res, step)
    path = folder / "report.html"
    atomic_write_text(path, _report_page(res))
    return path


def _dates_figure(path: Path, res: dict, step: int) -> None:
    """The two dates side by side (B warped into A's frame), protrusions marked by status."""
    a, b, reg = res["a"], res["b"], res["registration"]
    rows, pos, px, shape = res["rows"], res["positions_a"], a.pixel_size_um, a.height.shape
    ext = extent_mm(shape, px)
    b_in_a = warp_to_a(b.albedo.astype(np.float32), reg.b_to_a, shape, interpolation=cv2.INTER_LINEAR,
                       fill=float("nan"))
    fig = figure((12, 5.2))
    for i, (img, title) in enumerate(((a.albedo, "A (earlier)"), (b_in_a, "B (later), in A's frame"))):
        ax = fig.add_subplot(1, 2, i + 1)
        ax.imshow(display_albedo(img, step), extent=ext)
        _marks(ax, rows, pos, step, px, shape)
        ax.set_title(title)
        ax.set_xlabel("x (mm)")
    if ax.get_legend_handles_labels()[0]:
        ax.legend(loc="upper right", fontsize=8)
    save_figure(fig, path)


def _height_change_figure(path: Path, res: dict, step: int) -> None:
    """The levelled height change B - A in um, protrusions marked by status."""
    a, lev = res["a"], res["levelling"]
    rows, pos, px, shape = res["rows"], res["positions_a"], a.pixel_size_um, a.height.shape
    fig = figure((8, 6))
    ax = fig.add_subplot(1, 1, 1)
    ch = lev.change_um[::step, ::step]
    lim = float(np.nanpercentile(np.abs(ch), 99.5)) if np.isfinite(ch).any() else 1.0
    im = ax.imshow(ch, cmap="RdBu_r", vmin=-lim, vmax=lim, extent=extent_mm(shape, px))
    _marks(ax, rows, pos, step, px, shape)
    fig.colorbar(im, ax=ax, label="height change B - A (um)")
    ax.set_title("height change (levelled)")
    if ax.get_legend_handles_labels()[0]:
        ax.legend(loc="upper right", fontsize=8)
    save_figure(fig, path)


def _registration_figure(path: Path, res: dict, step: int) -> None:
    """The smooth difference the levelling removed, and the registration's residual per tile."""
    a, reg, lev = res["a"], res["registration"], res["levelling"]
    px = a.pixel_size_um
    ext = extent_mm(a.height.shape, px)
    fig = figure((12, 4.8))
    ax = fig.add_subplot(1, 2, 1)
    im = ax.imshow(lev.smooth_um[::step, ::step], cmap="viridis", extent=ext)
    fig.colorbar(im, ax=ax, label="um")
    ax.set_title("smooth difference removed (levelling)")
    ax = fig.add_subplot(1, 2, 2)
    ax.imshow(display_albedo(a.albedo, step), extent=ext, alpha=0.5)
    if reg.tiles:
        t = np.array(reg.tiles)
        ax.quiver(ext[0] + t[:, 0] * px / 1000, ext[3] - t[:, 1] * px / 1000, t[:, 2], -t[:, 3],
                  color="r", angles="xy", scale_units="xy", scale=1000.0 / (100.0 * px))
    ax.set_title(f"registration residual per tile (x100), rms {reg.rms_px:.3f} px")
    save_figure(fig, path)


def _registration_rows(a, b, reg, lev, d: dict) -> list:
    """The report's registration table: the model, its matches and residuals, scales, the common field."""
    return [("model (chosen by BIC)", reg.model), ("consistent matches", reg.matches),
                ("candidate matches", reg.candidates), ("residual rms (tiles)", f"{reg.rms_px:.3f} px"),
                ("feature residual rms", f"{reg.feature_rms_px:.3f} px"), ("refinement", reg.refinement),
                ("scale B -> A", f"{reg.scale:.5f}"), ("rotation", f"{reg.rotation_deg:.3f} deg"),
                ("pixel size A / B", f"{a.pixel_size_um:g} / {b.pixel_size_um:g} um"),
                ("B's heights / A's (divided out)", f"{lev.height_scale:.4f}"),
                ("smooth difference removed (p2..p98)",
                 f"{d['levelling']['smooth_difference_um']['p2']:.2f} .. "
                 f"{d['levelling']['smooth_difference_um']['p98']:.2f} um"),
                ("common field", f"{100 * d['common_field_fraction_of_a']:.1f} % of A"),
                ("left out (outside the common field)",
                 f"A {d['left_out_outside_common_field']['a']}, B {d['left_out_outside_common_field']['b']}")]


def _report_page(res: dict) -> str:
    """The HTML of the report: the dates, the height change, per-area tables, the registration."""
    a, b, reg, lev = res["a"], res["b"], res["registration"], res["levelling"]
    d = res["diagnostics"]
    reg_rows = _registration_rows(a, b, reg, lev, d)
    areas = res["areas"]
    classes = list(areas[-1]["grown_by_width"]) if areas else []
    area_rows = [[r["name"], r["area_cm2"]] + [r[s] for s in STATUSES] + [r["new_per_cm2"]] for r in areas]
    growth_rows = [[r["name"]] + [f"{g}/{m}" for g, m in r["grown_by_width"].values()] for r in areas]
    unc = d["uncertainty"]
    m = unc["model"]
    model_rows = [("outline on the pixel grid (width_px)", f"{m['width_px']:g} px"),
                  ("footprint threshold (width_rel)", f"{100 * m['width_rel']:.2g} % of the width"),
                  ("outline on few pixels (rim)", f"{m['rim']:.3g} px x (pixel / width)^{m['rim_exponent']:.3g}"),
                  ("pixel phase of the relief (peak)",
                   f"{m['peak']:.3g} x height x (pixel / width)^{m['peak_exponent']:.3g}"),
                  ("height scale (height_rel)", f"{100 * m['height_rel']:.2g} % of the height"),
                  ("surface noise (surface)", f"{m['surface']:g} x the height change's robust sd around it "
                                              f"(median {unc['surface_noise_um_median']} um)"),
                  ("this pair against the model (widths, heights)",
                   f"x {unc['inflation_width']:.2f}, x {unc['inflation_height']:.2f}")]
    date_rows = []
    for what, date in (("A", d["dates"]["a"]), ("B", d["dates"]["b"])):
        lamps = date.get("lamps", "unknown")
        given = date.get("calibration") or date.get("lights_file") or ""
        unc_h = date.get("height_uncertainty_relative")
        date_rows.append([what, lamps, html.escape(str(given)), date.get("n_lights") or "",
                          date["relief"]["scale"], f"+-{100 * unc_h:.1f} %" if unc_h is not None else ""])
    height_fig = ("" if not unc["heights"] else
                  '<h2>Height change</h2><figure><img src="figures/changes_height.png"></figure>')
    warn = "".join(f"<p class='warn'>{html.escape(w)}</p>" for w in res["warnings"])
    return f"""<!DOCTYPE html><html><head><meta charset="utf-8"><title>uvps changes</title>
<style>{CSS}</style></head><body>
<h1>Changes between two captures</h1>
<p>A (earlier): <code>{html.escape(str(a.path))}</code><br>B (later): <code>{html.escape(str(b.path))}</code><br>
uvps {__version__}; per protrusion: <a href="changes.csv">changes.csv</a>; registration:
<a href="registration.json">registration.json</a>{"; height change: height_change.tif (um, A's frame)" if unc["heights"] else ""}.</p>
{warn}
<h2>Change map</h2><figure><img src="figures/changes_map.png"></figure>
<h2>The two dates: lamps and calibration</h2>
{table_html(["date", "lamps", "calibration / lights file", "lamps (n)", "relief", "heights (lamps)"], date_rows)}
<figure><img src="figures/changes_dates.png"></figure>
{height_fig}
<h2>Change per colour area</h2>
{table_html(["area", "area (cm^2)"] + list(STATUSES) + ["new per cm^2"], area_rows)}
<h3>Grown / matched, by width class (um)</h3>
{table_html(["area"] + classes, growth_rows)}
<p>A protrusion counts as grown (shrunk) when its width or height changed by more than
{d['sigma_factor']:g} x that change's standard uncertainty (changes.csv <code>d_width_sd_um</code>,
<code>d_height_sd_um</code>; <code>significance</code> in standard deviations). The uncertainty of each
date's measurement, fitted to unchanged pairs ({html.escape(m['source'])}), and this pair's own
repeatability against it:</p>
{table_html(["term", "value"], model_rows)}
<h2>Registration</h2>
{table_html(["", ""], reg_rows)}
<figure><img src="figures/changes_registration.png"></figure>
</body></html>
"""


# ------------------------------------------------------------------------------------------------
# the command
# ------------------------------------------------------------------------------------------------

@dataclass
class _Run:
    path: Path
    albedo: np.ndarray
    height: np.ndarray
    table: dict
    pixel_size_um: float
    labels: Optional[np.ndarray]
    regions: Optional[np.ndarray]
    region_names: dict
    date: dict = field(default_factory=dict)     # what its run.json says of its lamps (date_record)


def _relief_of(log_: dict) -> dict:
    """The run's relief scale (docs/architecture.md; contract of ``run.json``'s ``relief``): a
    missing key is an older folder, read as absolute."""
    try:
        from ..files.runfolder import relief_of      # the one reader, where the run folder module has it
    except ImportError:
        relief = log_.get("relief") or {}
    else:
        relief = relief_of(log_) or {}
    return {"scale": relief.get("scale") or "absolute", "lamps": relief.get("lamps"),
            "reason": relief.get("reason")}


def date_record(run_dir) -> dict:
    """What a run folder's ``run.json`` says of the date's lamps and calibration: where the lamps
    came from (``lamps``: the lights' source; ``lights_file``, ``calibration``: the parameters
    given), their count, the heights' relative uncertainty where the lamps were estimated, and
    the relief's scale (``relief``: absolute or relative). A folder without ``run.json`` (made by
    another tool) gives ``run_json: False`` and an absolute scale."""
    path = Path(run_dir) / FILES["run"][0]
    try:
        log_ = json.loads(path.read_text(encoding="utf-8")) if path.is_file() else None
    except (UnicodeDecodeError, json.JSONDecodeError):
        log_ = None
    if not isinstance(log_, dict):
        return {"run_json": False, "lamps": "unknown", "relief": _relief_of({})}
    params = log_.get("params") or {}
    lights = (log_.get("diagnostics") or {}).get("lights") or {}
    rec = {"run_json": True, "command": log_.get("command"), "version": log_.get("version"),
           "lamps": lights.get("source", "unknown"), "n_lights": lights.get("n_lights"),
           "lights_file": params.get("lights"), "calibration": params.get("calibration"),
           "relief": _relief_of(log_)}
    if "height_uncertainty_relative" in lights:
        rec["height_uncertainty_relative"] = lights["height_uncertainty_relative"]
    return rec


def check_height_scales(date_a: dict, date_b: dict, paths) -> None:
    """Height growth between dates needs both reliefs on a pinned (absolute) scale: a relative
    run raises :class:`UVPSInputError` naming the calibration to add."""
    for what, date, path in (("A", date_a, paths[0]), ("B", date_b, paths[1])):
        relief = date["relief"]
        if relief["scale"] == "relative":
            why = f" ({relief['reason'].rstrip('.')})" if relief.get("reason") else ""
            raise UVPSInputError(
                f"run folder {what} {path} has a relative relief{why}: height growth between dates needs "
                "a pinned scale; re-run that capture with --calibration CAL (made by 'uvps calibrate "
                "--spheres DIR') or --lights POSITIONS, or compare widths and counts alone with --widths-only")


def _read_dated_run(path, what: str) -> _Run:
    path = Path(path)
    if not path.is_dir():
        raise UVPSInputError(f"run folder {what} {path} does not exist")
    table_path = path / FILES["protrusions"][0]
    if not table_path.is_file():
        raise UVPSInputError(f"run folder {what} {path} has no {table_path.name}; run 'uvps run' with "
                             "detection (--detect or --regions) or 'uvps detect' first")
    images = read_run(path, need=("albedo", "depth"))
    labels = None
    lab_path = path / FILES["protrusions_labels"][0]
    if lab_path.is_file():
        labels = np.asarray(read_tiff(lab_path)[0])
    regions, names = None, {}
    reg_path = path / FILES["regions_labels"][0]
    if reg_path.is_file():
        regions = np.asarray(read_tiff(reg_path)[0]).astype(np.int32)
        csv_path = path / FILES["regions"][0]
        if csv_path.is_file():
            names = read_region_names(csv_path)
    return _Run(path, images.albedo, images.height_um, read_protrusions_csv(table_path),
                images.pixel_size_um, labels, regions, names, date_record(path))


def _footprints(labels, grow=4):
    return None if labels is None else ndimage.binary_dilation(labels > 0, iterations=grow)


def _hashes(run: _Run) -> list:
    return [{"path": str(run.path / FILES[n][0]), "sha256": sha256_file(run.path / FILES[n][0])}
            for n in ("albedo", "depth", "protrusions")]


def _pixel_sizes(a, b, reg, warnings: list) -> dict:
    """The two dates' pixel sizes against the registration's scale (``run.json`` ``pixel_size``);
    a warning when they differ or disagree."""
    ratio = b.pixel_size_um / a.pixel_size_um
    pixel = {"pixel_size_um_a": a.pixel_size_um, "pixel_size_um_b": b.pixel_size_um,
             "ratio_b_over_a": round(ratio, 6), "registration_scale": round(reg.scale, 6),
             "rescaled": bool(abs(ratio - 1) > 1e-6 or abs(reg.scale - 1) > 1e-3)}
    if abs(ratio - 1) > 1e-6:
        warnings.append(f"pixel sizes differ (A {a.pixel_size_um:g} um, B {b.pixel_size_um:g} um): B is "
                        f"rescaled by {reg.scale:.4f} into A's frame")
    if abs(reg.scale / ratio - 1) > 0.01:
        warnings.append(f"the registration's scale ({reg.scale:.4f}) and the pixel sizes' ratio B / A "
                        f"({ratio:.4f}) differ by more than 1 %: is one run's pixel size wrong? "
                        "Widths of B are taken at B's calibration")
    return pixel


def _off_protrusions(a, b, reg, shape_a) -> np.ndarray:
    """A's pixels away from both dates' protrusions (3 px), in A's frame: where the levelling looks."""
    off = np.ones(shape_a, bool)
    if a.labels is not None:
        off &= ~ndimage.binary_dilation(a.labels > 0, iterations=3)
    if b.labels is not None:
        lb = warp_to_a((b.labels > 0).astype(np.uint8), reg.b_to_a, shape_a, interpolation=cv2.INTER_NEAREST)
        off &= ~ndimage.binary_dilation(lb > 0, iterations=3)
    return off


def compute_changes(run_a, run_b, *, sigma_factor=4.5, match_radius_um=None, min_matches=25,
                    level_mm=1.0, match_height_scale=True, bins_um=100.0, widths_only=False,
                    registration: Optional[Registration] = None, noise_model: Optional[NoiseModel] = None,
                    progress: Progress = None):
    """Everything ``uvps changes`` computes, in memory (see the module docstring).

    ``registration``: B onto A as an earlier call found it (the same two runs), to decide again
    with other options without registering again. ``noise_model``: the repeatability model
    (default :data:`uvps.core.changes.NOISE_MODEL`; another one to compare, as the benchmark does).

    Returns a dict: ``a``, ``b`` (the runs read), ``registration``, ``levelling``, ``rows``,
    ``positions_a``, ``common`` (A's pixels both dates see), ``areas``, ``diagnostics``,
    ``warnings``, ``timings_s``.
    """
    t0 = time.perf_counter()
    timings, warnings = {}, []
    report(progress, 0.0, "reading the run folders")
    a = _read_dated_run(run_a, "A")
    b = _read_dated_run(run_b, "B")
    heights = not widths_only
    if heights:
        check_height_scales(a.date, b.date, (a.path, b.path))
    elif "relative" not in (a.date["relief"]["scale"], b.date["relief"]["scale"]):
        warnings.append("--widths-only: heights not compared although both runs have an absolute relief")
    timings["read"] = round(time.perf_counter() - t0, 3)
    t = time.perf_counter()
    reg = registration or register(a.albedo, b.albedo, min_matches=min_matches, exclude_a=_footprints(a.labels),
                                   exclude_b=_footprints(b.labels),
                                   progress=lambda f, msg: report(progress, 0.05 + 0.45 * f, msg))
    timings["registration"] = round(time.perf_counter() - t, 3)
    t = time.perf_counter()
    pixel = _pixel_sizes(a, b, reg, warnings)
    shape_a, shape_b = a.height.shape, b.height.shape
    report(progress, 0.55, "heights into A's frame")
    hb = warp_to_a(b.height.astype(np.float32), reg.b_to_a, shape_a, interpolation=cv2.INTER_CUBIC)
    common = _overlap_mask(reg.b_to_a, shape_b, shape_a, erode=3) & np.isfinite(a.height) & np.isfinite(hb)
    off = _off_protrusions(a, b, reg, shape_a)
    block = max(8, int(round(level_mm * 1000.0 / a.pixel_size_um)))
    lev = level_heights(a.height, hb, common, off, block_px=block, match_scale=match_height_scale)
    if heights and abs(lev.height_scale - 1) > 0.02:
        warnings.append(f"B's relief is {lev.height_scale:.3f} x A's on the common field; B's heights are "
                        "divided by it (are both dates' lamps calibrated?)")
    timings["heights"] = round(time.perf_counter() - t, 3)
    t = time.perf_counter()
    report(progress, 0.7, "matching protrusions")
    rows, pos, left_out, unc = classify_changes(
        a.table, b.table, reg.b_to_a, shape_a=shape_a, shape_b=shape_b, pixel_size_um=a.pixel_size_um,
        pixel_size_um_b=b.pixel_size_um, height_scale=lev.height_scale, sigma_factor=sigma_factor,
        match_radius_um=match_radius_um, regions_a=a.regions, change_um=lev.change_um,
        off_protrusions=off, heights=heights, model=noise_model or NOISE_MODEL)
    for what, f in (("widths", unc["inflation_width"]), ("heights", unc["inflation_height"])):
        if f > 1.5:
            warnings.append(f"the {what} of this pair repeat {f:.1f} x worse than the repeatability model "
                            "(measured on unchanged pairs): the uncertainties are widened by it; are the "
                            "two captures comparable (lamps, exposure, focus)?")
    areas = area_table(rows, a.regions, a.region_names, common, a.pixel_size_um, bins_um)
    timings["matching"] = round(time.perf_counter() - t, 3)
    counts = {s: int(np.sum(rows["status"] == s)) for s in STATUSES}
    diagnostics = {"registration": {k: v for k, v in reg.to_json().items() if k != "tile_shifts_px"},
                   "dates": {"a": a.date, "b": b.date},
                   "pixel_size": pixel, "levelling": lev.diagnostics, "counts": counts,
                   "left_out_outside_common_field": left_out,
                   "common_field_fraction_of_a": round(float(common.mean()), 4),
                   "sigma_factor": sigma_factor, "uncertainty": unc, "areas": areas}
    return {"a": a, "b": b, "registration": reg, "levelling": lev, "rows": rows, "positions_a": pos,
            "common": common, "areas": areas, "diagnostics": diagnostics, "warnings": warnings,
            "timings_s": timings, "b_in_a_albedo": None}


def cmd_changes(inputs: dict, params: dict, output_dir, *, progress: Progress = None) -> CommandResult:
    """``changes``: B (later) against A (earlier), protrusion by protrusion."""
    t_all = time.perf_counter()
    out = Path(output_dir)
    res = compute_changes(inputs["run_a"], inputs["run_b"], sigma_factor=params["sigma_factor"],
                          match_radius_um=params["match_radius_um"], min_matches=params["min_matches"],
                          level_mm=params["level_mm"], match_height_scale=params["match_height_scale"],
                          bins_um=params["bins_um"], widths_only=params["widths_only"],
                          progress=lambda f, m: report(progress, 0.9 * f, m))
    a, reg, lev = res["a"], res["registration"], res["levelling"]
    t = time.perf_counter()
    report(progress, 0.9, "writing")
    with atomic_output_dir(out) as tmp:
        write_json_atomic(tmp / "registration.json", reg.to_json())
        write_changes_csv(tmp / "changes.csv", res["rows"])
        if not params["widths_only"]:
            write_imagej_tiff(tmp / "height_change.tif", lev.change_um, axes="YX", pixel_size_um=a.pixel_size_um,
                              metadata={"Info": "uvps changes: height of B minus A in um, in A's frame, levelled "
                                                "(smooth difference removed); NaN outside the common field"})
        write_changes_report(tmp, res)
        res["timings_s"]["writing"] = round(time.perf_counter() - t, 3)
        res["timings_s"]["total"] = round(time.perf_counter() - t_all, 3)
        # each date's lamps: the calibration it used (uvps calibrate), else its light file or estimate
        res["diagnostics"]["calibrations"] = {d: calibration_of_run(inputs[f"run_{d}"]) for d in ("a", "b")}
        runlog = RunLog("changes", {**params, "run_a": str(inputs["run_a"]), "run_b": str(inputs["run_b"])},
                        inputs=_hashes(res["a"]) + _hashes(res["b"]), timings_s=res["timings_s"],
                        warnings=list(res["warnings"]), diagnostics=res["diagnostics"])
        runlog.write(tmp / "run.json")
    outputs = [OutputSpec("registration", str(out / "registration.json"), kind="json"),
               OutputSpec("changes", str(out / "changes.csv"), kind="table", units="um")]
    if not params["widths_only"]:
        outputs.append(OutputSpec("height_change", str(out / "height_change.tif"), kind="image", axes="YX",
                                  dtype="float32", units="um"))
    outputs += [OutputSpec("report", str(out / "report.html"), kind="html"),
                OutputSpec("run", str(out / "run.json"), kind="json")]
    c = res["diagnostics"]["counts"]
    text = (f"registration: {reg.model}, {reg.matches} matches, residual {reg.rms_px:.3f} px rms, "
            f"scale {reg.scale:.4f}, rotation {reg.rotation_deg:.2f} deg\n"
            f"protrusions: {c['new']} new, {c['grown']} grown, {c['shrunk']} shrunk, "
            f"{c['unchanged']} unchanged, {c['gone']} gone, {c['merged']} merged, {c['split']} split\n"
            f"written to {out}")
    report(progress, 1.0, "done")
    diag = {k: v for k, v in res["diagnostics"].items() if k != "areas"}
    return CommandResult(outputs, diag, list(res["warnings"]), text=text)


SPECS = (
    CommandSpec("changes", "two captures of one region at two dates: registration, height change, "
                "protrusions new / grown / shrunk / unchanged / gone", cmd_changes, menu="Compare Captures", output="output folder",
                description="Register run B (later) onto run A (earlier) from the albedo, bring B's heights "
                "into A's frame and level them, match the protrusions one to one and give each its status "
                "(docs/monitoring.md). Writes registration.json, changes.csv, height_change.tif, "
                "report.html and run.json.",
                params=(
                    Param("run_a", "path", where="inputs", positional=True, required=True,
                          label="Earlier run folder (A)", help="run folder of the earlier capture (with detection)"),
                    Param("run_b", "path", where="inputs", positional=True, required=True,
                          label="Later run folder (B)", help="run folder of the later capture (with detection)"),
                    Param("sigma_factor", "float", 4.5, minimum=0, exclusive_minimum=True,
                          label="Significance (x the uncertainty)",
                          help="a change of width or height counts beyond this many standard uncertainties "
                               "of that change (changes.csv d_width_sd_um, d_height_sd_um)"),
                    Param("match_radius_um", "float", minimum=0, exclusive_minimum=True, unit="um",
                          label="Match radius (0 = automatic)",
                          help="largest centre distance of a match (default max(2 px, half the larger width))"),
                    Param("min_matches", "int", 25, minimum=4, label="Fewest feature matches",
                          help="fewest consistent feature matches to accept a registration"),
                    Param("level_mm", "float", 1.0, minimum=0, exclusive_minimum=True, unit="mm",
                          label="Levelling scale",
                          help="height differences smoother than this (block size) are removed as levelling"),
                    Param("match_height_scale", "bool", True, label="Match the heights' scale",
                          help="divide B's heights by its relief's scale against A's (estimated lamps "
                               "leave it uncertain by a few %)"),
                    Param("bins_um", "numbers", 100.0, unit="um", minimum=0, label="Width classes",
                          help="width class of the growth table, or increasing edges"),
                    Param("widths_only", "bool", False, label="Widths only (a relative relief)",
                          help="compare positions and widths alone, heights left empty: for a run whose "
                               "relief is relative (lamps not calibrated), which is refused otherwise"),
                )),
)
