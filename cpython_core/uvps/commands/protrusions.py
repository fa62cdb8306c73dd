"""Protrusion commands of the CLI and the bridge: detect, wand, regions, stats/report, compare.

Each is declared once (:data:`SPECS`, registered by ``uvps.commands``) and runs as
``cmd(inputs, params, output_dir, *, progress=None) -> CommandResult`` on the coerced request;
``output_dir`` is the run folder. They read the run's images once through
:func:`uvps.files.runfolder.read_run` and write every output atomically (a temporary folder moved into
place, or temporary files renamed).
"""
from __future__ import annotations

import dataclasses
import math
import logging
import re
from pathlib import Path

import numpy as np

from ..core.compare import compare_detections
from ..files.comparison import write_comparison_csv
from ..core.detect import DetectionParams
from ..core.detect.rules import PARAM_RANGES, RULES
from ..errors import UVPSInputError
from ..core.measure import measure_protrusions
from ..files.tables import CLICK_COLUMNS, read_protrusions_csv, write_label_tiff, write_protrusions_csv
from ..files.outputs import CommandResult, OutputSpec, Progress, atomic_output_dir, report, sub_progress
from ..core.pipeline import find_protrusions, protrusion_diagnostics
from ..core.regions import propose_regions, whole_image
from ..files.tables import load_regions
from ..report.page import plot_comparison_map
from ..core.level import raw_height
from ..files.runfolder import (RECOUNTS, drop_comparison, is_relative, level_of, output_spec, read_run, relief_in,
                               set_aside_comparison, write_protrusions)
from ..spec import CommandSpec, Param
from ..workflow import _stats_and_csv, regions_for, statistics
from ..core.wand import (CONTRAST_FRACTION, MAX_WIDTH_UM, SeedFile, contrast_select, judge_clicks, read_seed_file,
                         read_seeds, wand_select)

log = logging.getLogger(__name__)


# ---------------------------------------------------------------------------------------------
# helpers


def _write_labels(path: Path, labels: np.ndarray, px: float, info: str) -> None:
    write_label_tiff(path, labels, pixel_size_um=px, metadata={"Info": info})


def _connectivity(value: str):
    return int(value) if value.isdigit() else value


# ---------------------------------------------------------------------------------------------
# commands


def _cmd_detect(inputs: dict, params: dict, output_dir, *, progress: Progress = None) -> CommandResult:
    """Automated detection (albedo colour + template, height blobs) and measurement.

    With colour areas, detection is restricted to them (the paper masks each area) and each
    protrusion gets its area. Writes ``protrusions.csv`` and ``protrusions_labels.tif`` (and, for
    ``regions="auto"``, ``regions_labels.tif`` and ``regions.csv``).
    """
    run_dir = Path(output_dir)
    det_params = DetectionParams(**{k: params[k] for k in _DETECTION_FIELDS if params[k] is not None})
    report(progress, 0.0, "reading the run folder")
    images = read_run(run_dir, need=("albedo", "depth"), pixel_size_um=params["pixel_size_um"])
    regions, proposed = regions_for(params["regions"], run_dir, images, n_areas=params["n_areas"],
                                     seed=params["seed"])
    # the heights as integrated, as `run`'s detection reads them (depth.tif + the levelled-out surface)
    height = raw_height(images.height_um, level) if (level := level_of(run_dir)) else images.height_um
    prot = find_protrusions(images.albedo, height, images.normals, pixel_size_um=images.pixel_size_um,
                            regions=regions, params=det_params, progress=sub_progress(progress, 0.1, 0.9))
    prot.proposed = proposed
    with atomic_output_dir(run_dir) as tmp:
        kept = set_aside_comparison(run_dir, tmp, step="detect")
        names = write_protrusions(tmp, prot, images.pixel_size_um, relief=relief_in(run_dir))
    outputs = [output_spec(run_dir, n) for n in names]
    report(progress, 1.0, f"{len(prot.table['id'])} protrusions")
    out = CommandResult(outputs, protrusion_diagnostics(prot, images.pixel_size_um), [])
    _comparison_kept(run_dir, kept, tmp, out, step="detect")
    return out


def _comparison_kept(run_dir: Path, kept, tmp: Path, out: CommandResult, *, step: str) -> None:
    """After :func:`~uvps.files.runfolder.set_aside_comparison`: the comparison leaves ``run_dir`` (kept
    under ``earlier/``), and the result says where, in one warning."""
    if kept is None:
        return
    drop_comparison(run_dir)
    where = run_dir / kept.relative_to(tmp)
    out.diagnostics["earlier_comparison"] = str(where)
    out.warnings.append(f"the comparison in {run_dir} was made with the earlier {RECOUNTS[step]}: kept with it in "
                        f"{where}; run compare again for one with the new count")


def _cmd_wand(inputs: dict, params: dict, output_dir, *,
             progress: Progress = None) -> CommandResult:
    """Manual protrusions: each clicked point outlined on the albedo, judged, and the protrusions measured.

    ``method="relative"`` (default): the region that keeps ``tolerance`` (default 0.5) of the
    click's own contrast against its surroundings (:func:`uvps.core.wand.contrast_select`);
    ``method="imagej"``: ImageJ's wand with ``tolerance`` in albedo units
    (:func:`uvps.core.wand.wand_select`). A click counts only where it outlined a protrusion
    (:func:`uvps.core.wand.judge_clicks`: an outline, its own, raised above the paint). Writes
    ``protrusions_manual.csv`` (one row per click: ``counted`` 1 or 0 and, for 0, why) and
    ``protrusions_manual_labels.tif`` (the counted outlines; never the automated ``protrusions.csv``).
    """
    run_dir = Path(output_dir)
    warnings = []
    tolerance = params["tolerance"]
    if params["method"] == "imagej" and tolerance is None:
        raise UVPSInputError("tolerance: method 'imagej' needs a tolerance in albedo units (the albedo's "
                             "counts, as ImageJ's wand tool); or use the default method 'relative'")
    if params["method"] != "imagej" and tolerance is not None and not 0 < tolerance < 1:
        raise UVPSInputError(f"tolerance: method 'relative' takes the fraction of the click's contrast to keep, "
                             f"between 0 and 1 (default {CONTRAST_FRACTION}); got {tolerance}")
    images = read_run(run_dir, need=("albedo", "depth"), pixel_size_um=params["pixel_size_um"])
    clicks = _clicks(inputs["points"], images, params["points_unit"])
    seeds = clicks.seeds
    regions, _ = regions_for(params["regions"], run_dir, images)
    report(progress, 0.2, f"wand at {len(seeds)} points")
    if params["method"] == "imagej":
        labels = wand_select(images.albedo, seeds, tolerance=tolerance,
                             connectivity=_connectivity(params["connectivity"]), rgb=params["rgb"])
    else:
        labels = contrast_select(images.albedo, seeds,
                                 fraction=CONTRAST_FRACTION if tolerance is None else tolerance,
                                 max_width_px=params["max_width_um"] / images.pixel_size_um)
    report(progress, 0.6, "judging the outlines")
    judged = judge_clicks(labels, seeds, height=images.height_um, albedo=images.albedo,
                          max_width_px=params["max_width_um"] / images.pixel_size_um)
    report(progress, 0.7, "measuring")
    table = _click_table(judged, seeds, images, regions)
    with atomic_output_dir(run_dir) as tmp:
        kept = set_aside_comparison(run_dir, tmp, step="wand")
        write_protrusions_csv(tmp / "protrusions_manual.csv", table, relative=is_relative(relief_in(run_dir)),
                              extra=CLICK_COLUMNS)
        _write_labels(tmp / "protrusions_manual_labels.tif", judged.labels, images.pixel_size_um,
                      "uvps wand: manual protrusion labels (id = the click's number in protrusions_manual.csv; "
                      "clicks not counted have no pixels)")
    summary = judged.summary(seeds)
    report(progress, 1.0, summary)
    single = [i for i, st in enumerate(judged.status) if st != "outlined" and st != "repeat"
              and not np.isfinite(judged.relief_ratio[i])]
    if single and params["method"] == "imagej":
        warnings.append(f"{len(single)} clicks selected only their own pixel "
                        f"({_click_list([(i, tuple(seeds[i])) for i in single])}): if they are protrusions, a "
                        f"tolerance of {tolerance:g} albedo units is below the albedo's pixel-to-pixel variation; "
                        "raise it, or use the default method 'relative'")
    n_counted = int(np.count_nonzero(judged.counted))
    out = CommandResult([output_spec(run_dir, "protrusions_manual"), output_spec(run_dir, "protrusions_manual_labels")],
                         {"n_points": int(len(seeds)), "n_protrusions": n_counted, "summary": summary,
                          "not_counted": [{"click": i + 1, "x_px": int(seeds[i][0]), "y_px": int(seeds[i][1]),
                                           "status": judged.status[i], "why": judged.note[i]}
                                          for i in range(len(seeds)) if not judged.counted[i]],
                          "repeated_clicks": [i + 1 for i, st in enumerate(judged.status) if st == "repeat"],
                          "not_outlined_clicks": [i + 1 for i, st in enumerate(judged.status)
                                                  if st in ("bare paint", "height only")],
                          "method": params["method"], "pixel_size_um": images.pixel_size_um,
                          "points_unit": clicks.unit, "points_unit_said": clicks.said,
                          "points_px": seeds.tolist()}, warnings, text=summary)
    _comparison_kept(run_dir, kept, tmp, out, step="wand")
    return out


def _click_table(judged, seeds, images, regions) -> dict:
    """``protrusions_manual.csv``: one row per click, in click order (``id`` = the click's number). A
    counted click's row is its outline measured (:func:`uvps.core.measure.measure_protrusions`); a click
    not counted keeps its position, ``counted`` 0 and why (``note``), and no measurement."""
    measured = measure_protrusions(judged.labels, albedo=images.albedo, height_um=images.height_um,
                                   pixel_size_um=images.pixel_size_um, regions=regions, source="wand")
    n = len(seeds)
    x, y = seeds[:, 0], seeds[:, 1]
    # a click not counted: its number, position and area, no measurement (NaN, crater 0)
    table = {c: np.full(n, np.nan) if measured[c].dtype.kind == "f" else np.zeros(n, measured[c].dtype)
             for c in measured}
    table["id"][:] = np.arange(1, n + 1)
    table["x_px"][:], table["y_px"][:] = x, y
    if regions is not None:
        table["region"][:] = regions.labels[y, x]
    table["source"][:] = "wand"
    # a counted click: its outline measured (the outline's label, its id, is the click's number)
    rows = np.asarray(measured["id"], np.int64) - 1
    for c in measured:
        table[c][rows] = measured[c]
    table["counted"] = np.array([1 if c else 0 for c in judged.counted], dtype=np.int64)
    table["note"] = np.array(judged.note, dtype=object)
    return table


def _clicks(points, images, unit: str) -> SeedFile:
    """The wand's clicks: a clicks file in the units its header names (:func:`uvps.core.wand.read_seed_file`),
    or, from the bridge or Python, an (S, 2) list of ``(x, y)`` pixels."""
    if isinstance(points, (list, tuple, np.ndarray)):
        return SeedFile(read_seeds(points), "px", True)
    return read_seed_file(points, pixel_size_um=images.pixel_size_um, units=unit, shape=images.shape)


def _click_list(items, limit=8) -> str:
    text = ", ".join(f"#{i + 1} at ({x}, {y}) px" for i, (x, y) in items[:limit])
    return text + (f" and {len(items) - limit} more" if len(items) > limit else "")


def _cmd_regions(inputs: dict, params: dict, output_dir, *,
                progress: Progress = None) -> CommandResult:
    """Colour areas: load a label TIFF or masks, or propose them from the albedo colour.

    Exactly one of ``labels``, ``masks`` or ``auto``. Writes ``regions_labels.tif`` and ``regions.csv`` (names, areas, and the
    statistics of ``protrusions.csv`` when present).
    """
    run_dir = Path(output_dir)
    warnings = []
    labels_in, masks_in, auto = inputs["labels"], inputs["masks"], params["auto"]
    given = sum(x is not None and x is not False for x in (labels_in, masks_in)) + auto
    if given != 1:
        raise UVPSInputError("regions: give exactly one of inputs.labels, inputs.masks or "
                             f"params.auto=true; got {given}")
    images = read_run(run_dir, need=("albedo",) if auto else (),
                      pixel_size_um=params["pixel_size_um"])
    if images.shape is None:
        raise UVPSInputError(f"run folder {run_dir} has no albedo.tif or depth.tif to size the "
                             "colour areas; run the 'normals' command first")
    report(progress, 0.1, "colour areas")
    if auto:
        regions = propose_regions(images.albedo, pixel_size_um=images.pixel_size_um,
                                  n_areas=params["n_areas"], seed=params["seed"],
                                  progress=sub_progress(progress, 0.1, 0.8))
    elif masks_in is not None:
        masks = [masks_in] if isinstance(masks_in, str) else list(masks_in)
        regions = load_regions([Path(m) for m in masks], shape=images.shape)
    else:
        regions = load_regions(Path(labels_in), shape=images.shape)
    report(progress, 0.85, "statistics")
    with atomic_output_dir(run_dir) as tmp:
        _write_labels(tmp / "regions_labels.tif", regions.labels, images.pixel_size_um,
                      "uvps: colour areas (0 = none; names in regions.csv)")
        stats = _stats_and_csv(tmp, run_dir, regions, images.pixel_size_um,
                               params["bins_um"], warnings)
    report(progress, 1.0, f"{len(regions.ids)} areas")
    outputs = [output_spec(run_dir, "regions_labels"), output_spec(run_dir, "regions")]
    diagnostics = {"n_areas": len(regions.ids),
                   "names": {str(k): v for k, v in regions.names.items()},
                   "area_cm2": {str(r.label): r.area_cm2 for r in stats.rows}}
    return CommandResult(outputs, diagnostics, warnings)


def _cmd_stats(inputs: dict, params: dict, output_dir, *, progress: Progress = None) -> CommandResult:
    """Per-area statistics (``regions.csv``) and the report (:func:`uvps.workflow.statistics`)."""
    return statistics(output_dir, table=params["table"], regions=params["regions"], bins_um=params["bins_um"],
                      pixel_size_um=params["pixel_size_um"], pdf=params["pdf"], progress=progress)


def _cmd_compare(inputs: dict, params: dict, output_dir, *,
                progress: Progress = None) -> CommandResult:
    """Compare two protrusion tables per colour area (paper Fig. 4c).

    ``a`` is the reference (e.g. ``protrusions_manual.csv``), ``b`` the other (e.g.
    ``protrusions.csv``); ``regions`` as for ``stats``. Writes ``comparison.csv`` and, when the run has an albedo,
    ``figures/comparison_map.png`` (``b`` circled in red, ``a``'s missed ones in yellow).
    """
    run_dir = Path(output_dir)
    warnings = []
    a_path, b_path = Path(inputs["a"]), Path(inputs["b"])
    a, b = read_protrusions_csv(a_path), read_protrusions_csv(b_path)
    images = read_run(run_dir, need=(), pixel_size_um=params["pixel_size_um"])
    if images.pixel_size_um is None:
        # the output folder holds no run (e.g. a truth table against a run's): the pixel size of
        # the run folder either table lies in
        for folder in (b_path.parent, a_path.parent):
            found = read_run(folder, need=(), require_pixel_size=False).pixel_size_um if folder.is_dir() else None
            if found:
                images = dataclasses.replace(images, pixel_size_um=found)
                warnings.append(f"pixel size {found:g} um from the run folder {folder}")
                break
        else:
            raise UVPSInputError(f"compare: no pixel size: {run_dir} and the tables' folders hold no run; give "
                                 "pixel_size_um (--pixel-size-um), or -o the run folder of one of the tables")
    regions = None
    if images.shape is not None:
        regions, _ = regions_for(params["regions"], run_dir, images)
        if regions is None:
            regions = whole_image(images.shape)
    else:
        warnings.append("no image in the run folder: comparison without areas or densities")
    report(progress, 0.3, "matching")
    comp = compare_detections(a, b, regions=regions, pixel_size_um=images.pixel_size_um,
                              match_radius_um=params["match_radius_um"],
                              name_a=a_path.stem, name_b=b_path.stem)
    outputs = [OutputSpec("comparison", str(run_dir / "comparison.csv"), kind="table",
                          units="cm^-2")]
    with atomic_output_dir(run_dir) as tmp:
        write_comparison_csv(tmp / "comparison.csv", comp)
        if images.albedo is not None:
            report(progress, 0.6, "comparison map")
            plot_comparison_map(images.albedo, a, b, comp, tmp / "figures" / "comparison_map.png",
                                pixel_size_um=images.pixel_size_um)
            outputs.append(OutputSpec("figure_comparison_map",
                                      str(run_dir / "figures" / "comparison_map.png"),
                                      kind="image", axes="YXS", dtype="uint8"))
    report(progress, 1.0, f"{len(comp.pairs)} matched")
    total = comp.rows[-1]
    return CommandResult(outputs,
                         {"matched": total["matched"], "missed": total["missed"],
                          "extra": total["extra"], "a": str(a_path), "b": str(b_path)}, warnings)



#: The detection settings a Fiji dialog shows, in a conservator's words (the first word is the macro key).
_DETECTION_LABELS = {"dynamic_k": "Sensitivity (relief / height noise; lower finds more)",
                     "min_width_um": "Smallest width of a protrusion"}


def _detection_params() -> tuple:
    """Every field of :class:`uvps.core.detect.DetectionParams` as a parameter of ``detect`` (type and
    default from the dataclass, help from its numpydoc Attributes section, the rule that owns it and
    its bounds from the rules' declarations, :data:`uvps.core.detect.rules.PARAM_RANGES`)."""
    doc = DetectionParams.__doc__ or ""
    helps = {}
    for m in re.finditer(r"^    ([a-z_, ]+) : \w+\n((?:        .*\n)+)", doc, re.M):
        text = " ".join(m.group(2).split())
        for name in m.group(1).split(","):
            helps[name.strip()] = text.split(". ")[0].rstrip(".")
    owner = {k: r.name for r in RULES for k in r.params}
    out = []
    for f in dataclasses.fields(DetectionParams):
        kind = {bool: "bool", int: "int", float: "float"}.get(type(f.default), "float")
        rng = PARAM_RANGES[f.name]
        lo = rng.lo if not isinstance(rng.lo, str) and math.isfinite(rng.lo) else None
        hi = (rng.hi if not isinstance(rng.hi, str) and math.isfinite(rng.hi) and not rng.hi_open
              else None)
        text = helps.get(f.name, "detection option") + (f" (rule {owner[f.name]})" if f.name in owner else "")
        out.append(Param(f.name, kind, f.default, help=text, minimum=lo, maximum=hi,
                         exclusive_minimum=bool(lo is not None and rng.lo_open),
                         unit="um" if f.name.endswith("_um") else "", label=_DETECTION_LABELS.get(f.name, "")))
    return tuple(out)


_DETECTION = _detection_params()
_DETECTION_FIELDS = tuple(p.name for p in _DETECTION)
_PX = Param("pixel_size_um", "float", minimum=0, exclusive_minimum=True, unit="um",
            help="pixel size (default: the run's TIFF calibration)")
_REGIONS_FILE = Param("regions", "path", label="Regions (label TIFF, or empty)", help="colour-area label TIFF (default: the run's regions_labels.tif, "
                      "else the whole image)")
_BINS = Param("bins_um", "numbers", 100.0, unit="um", minimum=0, label="Bins of protrusion width",
              help="width bin of the histograms, or increasing bin edges")
_SEED = Param("seed", "int", 0, help="random seed of the automatic proposal (k-means)")
_N_AREAS = Param("n_areas", "int", minimum=1, label="Number of automatic areas (0 = choose)", help="number of colour areas for the proposal (default: chosen)")

SPEC_STATS = CommandSpec("stats", "per-area statistics and report.html", _cmd_stats, menu="Statistics and Report", aliases=("report",),
                         params=(_BINS, _REGIONS_FILE,
                                 Param("table", "path", help="the protrusion CSV to count (default protrusions.csv, "
                                       "else protrusions_manual.csv)"), _PX,
                                 Param("pdf", "bool", False, label="Also print the report to PDF (needs Chromium)",
                                       help="also write report.pdf, printed from report.html by a headless Chromium "
                                       "or Chrome found on PATH (none is downloaded)")))
SPECS = (
    CommandSpec("detect", "automated protrusion detection on a run folder", _cmd_detect, menu="Detect Protrusions", params=(
        Param("regions", "path", choices=("auto",), label="Regions: colour areas (auto = from the colours, a label image, or empty = the run's own)", help="colour-area label TIFF, or 'auto' (proposed from the "
              "albedo); default: the run's regions_labels.tif, else the whole image"),
        _N_AREAS, _SEED, _PX) + _DETECTION),
    CommandSpec("wand", "the manual method: outline each clicked protrusion; only the outlined are counted", _cmd_wand, menu="Wand Count", params=(
        Param("points", "path", where="inputs", positional=True, required=True,
              label="Points CSV (x_px,y_px; empty = current point selection)",
              help="CSV of the clicks: x_px,y_px (pixels), x_um,y_um or x_mm,y_mm, or X,Y as ImageJ's "
              "Measure exports them"),
        Param("points_unit", "choice", "auto", choices=("auto", "px", "um"), label="Units of the points file",
              help="unit of X,Y columns (a header x_px, x_um or x_mm says its own): auto = pixels unless "
              "the clicks fit the image only in um (Measure on the calibrated albedo)"),
        Param("method", "choice", "relative", choices=("relative", "imagej"),
              label="Method (relative = by each click's own contrast; imagej = ImageJ's wand)",
              help="relative: the region keeping a share of the click's own contrast against its surroundings; "
                   "imagej: ImageJ's wand, the pixels within a tolerance of the click's albedo"),
        Param("tolerance", "float", minimum=0,
              label="Tolerance (relative: share of the click's contrast, 0 = 0.5; imagej: albedo units)",
              help=f"relative: the share of the click's contrast a pixel keeps, in (0, 1); {CONTRAST_FRACTION} when "
                   "not given; imagej: required, in albedo units (counts) as ImageJ's wand tool"),
        Param("max_width_um", "float", MAX_WIDTH_UM, minimum=0, exclusive_minimum=True, unit="um",
              label="Widest protrusion (relative)",
              help="relative: the widest protrusion; a region that would grow wider has reached the paint"),
        Param("connectivity", "choice", "8", choices=("8", "4", "legacy"), label="Connectivity (imagej)",
              help="imagej: 8-connected, 4-connected, or ImageJ's 'Legacy' mode"),
        Param("rgb", "choice", "mean", choices=("mean", "channels"),
              help="imagej, RGB albedo: compare the mean of R, G, B (ImageJ), or every channel"),
        _REGIONS_FILE, _PX)),
    CommandSpec("regions", "colour areas: from labels/masks or an automatic proposal", _cmd_regions, menu="Colour Areas", params=(
        Param("labels", "path", where="inputs", label="Label image (for source Label image)", help="label TIFF (0 = none)"),
        Param("masks", "paths", where="inputs", help="one mask TIFF per area"),
        Param("auto", "bool", False, help="propose areas by clustering the albedo colour"),
        _N_AREAS, _SEED, _BINS, _PX)),
    SPEC_STATS,
    CommandSpec("compare", "compare two protrusion tables (e.g. manual vs automated)", _cmd_compare, menu="Compare Counts", params=(
        Param("a", "path", where="inputs", positional=True, required=True,
              label="First protrusion table (e.g. protrusions_manual.csv)", help="the reference table (e.g. "
              "protrusions_manual.csv)"),
        Param("b", "path", where="inputs", positional=True, required=True,
              label="Second protrusion table (e.g. protrusions.csv)", help="the other table"),
        Param("match_radius_um", "float", minimum=0, exclusive_minimum=True, unit="um",
              label="Match radius (0 = automatic)",
              help="largest centre distance of a match (default max(2 px, half the larger width))"),
        _REGIONS_FILE, _PX)),
)

SPECS_BY_NAME = {s.name: s for s in SPECS}
# the commands as callables that check their request first (``cmd_detect(inputs, params, run_dir)``)
cmd_detect, cmd_wand, cmd_regions, cmd_stats, cmd_compare = (
    SPECS_BY_NAME[n] for n in ("detect", "wand", "regions", "stats", "compare"))
