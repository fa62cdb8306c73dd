"""Protrusion commands of the CLI and the bridge: detect, wand, regions, stats/report, compare.

Each is ``cmd(inputs, params, output_dir, *, progress=None) -> CommandResult`` (see the command
table in ``docs/architecture.md``); ``output_dir`` is the run folder. They read the run's
``albedo.tif``, ``depth.tif`` (height, um) and ``normals.tif`` with :func:`uvps.io.read_tiff`
and write every output atomically (a temporary folder moved into place, or temporary files
renamed). :data:`PROTRUSION_COMMANDS` is merged into ``uvps.commands.COMMANDS``.
"""
from __future__ import annotations

import dataclasses
import logging
from pathlib import Path
from typing import Optional

import numpy as np

from .errors import UVPSInputError
from .outputs import CommandResult, OutputSpec, Progress, atomic_output_dir, report

log = logging.getLogger(__name__)


# ---------------------------------------------------------------------------------------------
# reading the run folder


@dataclasses.dataclass
class RunImages:
    """What a run folder holds for protrusion work (None when the file is absent)."""

    albedo: Optional[np.ndarray]  # (M, N) or (M, N, 3)
    height_um: Optional[np.ndarray]  # (M, N)
    normals: Optional[np.ndarray]  # (M, N, 3)
    pixel_size_um: Optional[float]
    shape: Optional[tuple]


def _yxc(arr: np.ndarray) -> np.ndarray:
    if arr.ndim == 3 and arr.shape[0] == 3:
        return np.moveaxis(arr, 0, -1)
    return arr


def read_run(run_dir: Path, *, need=("albedo", "depth"), pixel_size_um=None) -> RunImages:
    """Read ``albedo.tif``, ``depth.tif`` and ``normals.tif`` of a run folder.

    Parameters
    ----------
    run_dir : Path
    need : tuple of str
        Files that must exist ("albedo", "depth", "normals"); a missing one raises
        UVPSInputError naming the command that makes it.
    pixel_size_um : float, optional
        Overrides the TIFFs' calibration (required when they have none).
    """
    from .io import read_tiff

    made_by = {"albedo": "normals", "normals": "normals", "depth": "integrate"}
    out = {}
    px_found = []
    for name in ("albedo", "depth", "normals"):
        path = run_dir / f"{name}.tif"
        if not path.is_file():
            if name in need:
                raise UVPSInputError(f"run folder {run_dir} has no {name}.tif; run the "
                                     f"'{made_by[name]}' command first")
            out[name] = None
            continue
        data, px = read_tiff(path)
        out[name] = np.asarray(data)
        if px:
            px_found.append(px)
    albedo = _yxc(out["albedo"]) if out["albedo"] is not None else None
    normals = _yxc(out["normals"]).astype(np.float32) if out["normals"] is not None else None
    height = out["depth"].astype(np.float32) if out["depth"] is not None else None
    shapes = {a.shape[:2] for a in (albedo, height, normals) if a is not None}
    if len(shapes) > 1:
        raise UVPSInputError(f"run folder {run_dir}: albedo.tif, depth.tif and normals.tif differ "
                             f"in size: {sorted(shapes)}")
    px = _pixel_size(pixel_size_um, px_found[0] if px_found else None, run_dir)
    return RunImages(albedo, height, normals, px, shapes.pop() if shapes else None)


def _pixel_size(param, found, where) -> float:
    if param is not None:
        try:
            px = float(param)
        except (TypeError, ValueError):
            raise UVPSInputError(f"pixel_size_um must be a positive number; "
                                 f"got {param!r}") from None
        if not (np.isfinite(px) and px > 0):
            raise UVPSInputError(f"pixel_size_um must be a positive number; got {param!r}")
        return px
    if found is None:
        raise UVPSInputError(f"{where}: no pixel size in the TIFFs; give params.pixel_size_um")
    return float(found)


def _regions_for(spec, run_dir: Path, images: RunImages, *, params: dict, seed=0):
    """Colour areas from ``params.regions``: a label TIFF path, "auto", or None (the run's
    ``regions_labels.tif`` when present, else None). Returns (RegionMap or None, proposed?)."""
    from .regions import load_regions, propose_regions

    if spec is None:
        spec = run_dir / "regions_labels.tif"
        if not spec.is_file():
            return None, False
    if isinstance(spec, str) and spec == "auto":
        if images.albedo is None:
            raise UVPSInputError("regions='auto' needs the run's albedo.tif")
        return propose_regions(images.albedo, pixel_size_um=images.pixel_size_um,
                               n_areas=params.get("n_areas"), seed=seed), True
    if isinstance(spec, (list, tuple)):
        return load_regions([Path(p) for p in spec], shape=images.shape), False
    if not isinstance(spec, (str, Path)):
        raise UVPSInputError(f"regions must be a label TIFF path, 'auto' or null; got {spec!r}")
    return load_regions(Path(spec), shape=images.shape), False


def _tiff_dtype(path: Path) -> str:
    import tifffile

    with tifffile.TiffFile(path) as tif:
        return str(tif.series[0].dtype)


def _unknown(params: dict, known) -> list:
    return [f"parameter '{k}' ignored (unknown to this command)"
            for k in sorted(set(params) - set(known))]


def _write_labels(path: Path, labels: np.ndarray, px: float, info: str) -> None:
    from .measure import write_label_tiff

    write_label_tiff(path, labels, pixel_size_um=px, metadata={"Info": info})


def _table_outputs(final: Path, stem: str, labels_name: str) -> list:
    return [OutputSpec(stem, str(final / f"{stem}.csv"), kind="table", units="um"),
            OutputSpec(labels_name, str(final / f"{labels_name}.tif"), kind="image", axes="YX",
                       dtype=_tiff_dtype(final / f"{labels_name}.tif"), units="label")]


def _source_counts(table) -> dict:
    src, n = np.unique(np.asarray(table["source"], dtype=str), return_counts=True)
    return {str(s): int(c) for s, c in zip(src, n)}


# ---------------------------------------------------------------------------------------------
# commands


def cmd_detect(inputs: dict, params: dict, output_dir, *,
               progress: Progress = None) -> CommandResult:
    """Automated detection (albedo colour + template, height blobs) and measurement.

    Params: ``regions`` (label TIFF, "auto" or null = the run's ``regions_labels.tif`` if any),
    ``n_areas`` and ``seed`` (for "auto"), ``pixel_size_um`` (override), and any field of
    :class:`uvps.detect.DetectionParams`. With colour areas, detection is restricted to them
    (the paper masks each area) and each protrusion gets its area. Writes ``protrusions.csv``
    and ``protrusions_labels.tif`` (and ``regions_labels.tif`` for "auto").
    """
    from .detect import DetectionParams, detect_protrusions
    from .measure import measure_protrusions, write_protrusions_csv

    run_dir = Path(output_dir)
    det_fields = {f.name for f in dataclasses.fields(DetectionParams)}
    warnings = _unknown(params, det_fields | {"regions", "n_areas", "seed", "pixel_size_um"})
    try:
        det_params = DetectionParams(**{k: v for k, v in params.items() if k in det_fields})
    except TypeError as exc:
        raise UVPSInputError(f"detection parameters: {exc}") from None
    report(progress, 0.0, "reading the run folder")
    images = read_run(run_dir, need=("albedo", "depth"), pixel_size_um=params.get("pixel_size_um"))
    regions, proposed = _regions_for(params.get("regions"), run_dir, images, params=params,
                                     seed=int(params.get("seed") or 0))
    mask = regions.labels > 0 if regions is not None else None
    sub = None if progress is None else (lambda f, m: progress(0.1 + 0.7 * f, m))
    det = detect_protrusions(images.albedo, images.height_um, pixel_size_um=images.pixel_size_um,
                             normals=images.normals, mask=mask, params=det_params, progress=sub)
    report(progress, 0.85, "measuring")
    source = {i + 1: str(s) for i, s in enumerate(det.source)}
    table = measure_protrusions(det.labels, albedo=images.albedo, height_um=images.height_um,
                                pixel_size_um=images.pixel_size_um, regions=regions, source=source)
    with atomic_output_dir(run_dir) as tmp:
        write_protrusions_csv(tmp / "protrusions.csv", table)
        _write_labels(tmp / "protrusions_labels.tif", det.labels, images.pixel_size_um,
                      "uvps detect: protrusion labels (0 = background; id as in protrusions.csv)")
        if proposed:
            _write_labels(tmp / "regions_labels.tif", regions.labels, images.pixel_size_um,
                          "uvps: proposed colour areas (edit in ImageJ, then run regions)")
    outputs = _table_outputs(run_dir, "protrusions", "protrusions_labels")
    if proposed:
        outputs.append(OutputSpec("regions_labels", str(run_dir / "regions_labels.tif"),
                                  kind="image", axes="YX", units="label",
                                  dtype=_tiff_dtype(run_dir / "regions_labels.tif")))
    report(progress, 1.0, f"{len(table['id'])} protrusions")
    diagnostics = {"n_protrusions": int(len(table["id"])), "by_source": _source_counts(table),
                   "n_craters": int(np.sum(table["crater"])), "rejected": dict(det.rejected),
                   "noise_um": float(det.noise_um) if np.isfinite(det.noise_um) else None,
                   "n_areas": len(regions.ids) if regions is not None else None,
                   "pixel_size_um": images.pixel_size_um}
    return CommandResult(outputs, diagnostics, warnings)


def cmd_wand(inputs: dict, params: dict, output_dir, *,
             progress: Progress = None) -> CommandResult:
    """Manual protrusions: ImageJ's wand at each clicked point on the albedo, then measurement.

    Inputs: ``points`` (CSV with ``x_px,y_px`` or ImageJ's ``X,Y``, or a list of [x, y]).
    Params: ``tolerance`` (required, albedo units), ``connectivity`` (8), ``rgb`` ("mean"),
    ``regions``, ``pixel_size_um``. Writes ``protrusions_manual.csv`` and
    ``protrusions_manual_labels.tif``.
    """
    from .measure import measure_protrusions, write_protrusions_csv
    from .wand import read_seeds, wand_select

    run_dir = Path(output_dir)
    warnings = _unknown(params, {"tolerance", "connectivity", "rgb", "regions", "pixel_size_um"})
    if "points" not in inputs:
        raise UVPSInputError("wand: inputs.points is required (a CSV of x_px,y_px or a list "
                             "of [x, y])")
    if params.get("tolerance") is None:
        raise UVPSInputError("wand: params.tolerance is required (in albedo units, as "
                             "ImageJ's wand)")
    seeds = read_seeds(inputs["points"])
    images = read_run(run_dir, need=("albedo", "depth"), pixel_size_um=params.get("pixel_size_um"))
    regions, _ = _regions_for(params.get("regions"), run_dir, images, params=params)
    report(progress, 0.2, f"wand at {len(seeds)} points")
    labels = wand_select(images.albedo, seeds, tolerance=params["tolerance"],
                         connectivity=params.get("connectivity", 8), rgb=params.get("rgb", "mean"))
    report(progress, 0.7, "measuring")
    table = measure_protrusions(labels, albedo=images.albedo, height_um=images.height_um,
                                pixel_size_um=images.pixel_size_um, regions=regions, source="wand")
    with atomic_output_dir(run_dir) as tmp:
        write_protrusions_csv(tmp / "protrusions_manual.csv", table)
        _write_labels(tmp / "protrusions_manual_labels.tif", labels, images.pixel_size_um,
                      "uvps wand: manual protrusion labels (id as in protrusions_manual.csv)")
    report(progress, 1.0, f"{len(table['id'])} protrusions")
    n_dup = len(seeds) - len(table["id"])
    if n_dup > 0:
        warnings.append(f"{n_dup} points fell in a region already selected (or on NaN) and add "
                        "no protrusion")
    return CommandResult(_table_outputs(run_dir, "protrusions_manual", "protrusions_manual_labels"),
                         {"n_points": int(len(seeds)), "n_protrusions": int(len(table["id"])),
                          "pixel_size_um": images.pixel_size_um}, warnings)


def _stats_and_csv(tmp: Path, run_dir: Path, regions, px: float, bins_um, warnings: list,
                   path: Optional[Path] = None):
    from .measure import empty_table, read_protrusions_csv
    from .regions import region_statistics, write_regions_csv

    path = path or run_dir / "protrusions.csv"
    if path.is_file():
        table = read_protrusions_csv(path)
    else:
        table = empty_table()
        warnings.append("no protrusions.csv in the run folder: counts are 0 (run detect first)")
    stats = region_statistics(table, regions, pixel_size_um=px, bins_um=bins_um)
    write_regions_csv(tmp / "regions.csv", stats)
    return stats


def cmd_regions(inputs: dict, params: dict, output_dir, *,
                progress: Progress = None) -> CommandResult:
    """Colour areas: load a label TIFF or masks, or propose them from the albedo colour.

    Inputs: ``labels`` (TIFF) or ``masks`` (list of mask files, one area each). Params: ``auto``
    (false; true = propose), ``n_areas`` (null = choose), ``seed`` (0), ``bins_um`` (100),
    ``pixel_size_um``. Writes ``regions_labels.tif`` and ``regions.csv`` (names, areas, and the
    statistics of ``protrusions.csv`` when present).
    """
    from .regions import load_regions, propose_regions

    run_dir = Path(output_dir)
    warnings = _unknown(params, {"auto", "n_areas", "seed", "bins_um", "pixel_size_um",
                                 "labels", "masks", "regions"})
    labels_in = inputs.get("labels") or params.get("labels")
    masks_in = inputs.get("masks") or params.get("masks")
    auto = bool(params.get("auto", False))
    given = sum(x is not None and x is not False for x in (labels_in, masks_in)) + auto
    if given != 1:
        raise UVPSInputError("regions: give exactly one of inputs.labels, inputs.masks or "
                             f"params.auto=true; got {given}")
    images = read_run(run_dir, need=("albedo",) if auto else (),
                      pixel_size_um=params.get("pixel_size_um"))
    if images.shape is None:
        raise UVPSInputError(f"run folder {run_dir} has no albedo.tif or depth.tif to size the "
                             "colour areas; run the 'normals' command first")
    report(progress, 0.1, "colour areas")
    if auto:
        sub = None if progress is None else (lambda f, m: progress(0.1 + 0.7 * f, m))
        regions = propose_regions(images.albedo, pixel_size_um=images.pixel_size_um,
                                  n_areas=params.get("n_areas"), seed=int(params.get("seed") or 0),
                                  progress=sub)
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
                               params.get("bins_um", 100.0), warnings)
    report(progress, 1.0, f"{len(regions.ids)} areas")
    labels_path = run_dir / "regions_labels.tif"
    outputs = [OutputSpec("regions_labels", str(labels_path), kind="image", axes="YX",
                          units="label", dtype=_tiff_dtype(labels_path)),
               OutputSpec("regions", str(run_dir / "regions.csv"), kind="table", units="cm^-2")]
    diagnostics = {"n_areas": len(regions.ids),
                   "names": {str(k): v for k, v in regions.names.items()},
                   "area_cm2": {str(r.label): r.area_cm2 for r in stats.rows}}
    return CommandResult(outputs, diagnostics, warnings)


def cmd_stats(inputs: dict, params: dict, output_dir, *,
              progress: Progress = None) -> CommandResult:
    """Per-area statistics (``regions.csv``) and the report (``report.html``, ``figures/``).

    Params: ``bins_um`` (100, or a list of edges), ``regions`` (label TIFF; default the run's
    ``regions_labels.tif``, else the whole image), ``table`` (the protrusion CSV to count: a
    path or a file name in the run folder; default ``protrusions.csv``, else
    ``protrusions_manual.csv`` when only the wand has run), ``pixel_size_um``.
    """
    from .regions import whole_image
    from .report import write_report

    run_dir = Path(output_dir)
    warnings = _unknown(params, {"bins_um", "regions", "pixel_size_um", "table"})
    if params.get("table"):
        table_path = Path(params["table"])
        table_path = table_path if table_path.is_absolute() else run_dir / table_path
        if not table_path.is_file():
            raise UVPSInputError(f"table: protrusion CSV {table_path} does not exist")
    elif (run_dir / "protrusions.csv").is_file():
        table_path = run_dir / "protrusions.csv"
    elif (run_dir / "protrusions_manual.csv").is_file():
        table_path = run_dir / "protrusions_manual.csv"
        warnings.append("no protrusions.csv: statistics of the wand count "
                        "(protrusions_manual.csv)")
    else:
        raise UVPSInputError(f"run folder {run_dir} has no protrusions.csv; run the 'detect' or "
                             "'wand' command first")
    images = read_run(run_dir, need=(), pixel_size_um=params.get("pixel_size_um"))
    if images.shape is None:
        raise UVPSInputError(f"run folder {run_dir} has no albedo.tif or depth.tif to size the "
                             "colour areas")
    if params.get("regions") == "auto":
        raise UVPSInputError("stats: params.regions must be a label TIFF or null; run "
                             "'regions' with auto=true to propose areas")
    regions, _ = _regions_for(params.get("regions"), run_dir, images, params=params)
    if regions is None:
        regions = whole_image(images.shape)
        warnings.append("no colour areas (regions_labels.tif): statistics over the whole image")
    report(progress, 0.05, "statistics")
    with atomic_output_dir(run_dir) as tmp:
        stats = _stats_and_csv(tmp, run_dir, regions, images.pixel_size_um,
                               params.get("bins_um", 100.0), warnings, table_path)
    sub = None if progress is None else (lambda f, m: progress(0.1 + 0.9 * f, m))
    html = write_report(run_dir, stats=stats, regions=regions, warnings=list(warnings),
                        table=table_path, progress=sub)
    figures = sorted((run_dir / "figures").glob("*.png"))
    outputs = [OutputSpec("regions", str(run_dir / "regions.csv"), kind="table", units="cm^-2"),
               OutputSpec("report", str(html), kind="html")]
    outputs += [OutputSpec(f"figure_{p.stem}", str(p), kind="image", axes="YXS", dtype="uint8")
                for p in figures]
    diagnostics = {r.name: {"count": r.count, "area_cm2": r.area_cm2,
                            "density_per_cm2": r.density_per_cm2} for r in stats.rows}
    return CommandResult(outputs, {"areas": diagnostics, "outside": stats.outside,
                                   "table": str(table_path),
                                   "edges_um": [float(e) if np.isfinite(e) else None
                                                for e in stats.edges_um]}, warnings)


def cmd_compare(inputs: dict, params: dict, output_dir, *,
                progress: Progress = None) -> CommandResult:
    """Compare two protrusion tables per colour area (paper Fig. 4c).

    Inputs: ``a`` (reference, e.g. ``protrusions_manual.csv``), ``b`` (e.g. ``protrusions.csv``).
    Params: ``match_radius_um`` (null = max(2 px, 0.5 x the larger width)), ``regions`` (label
    TIFF; default the run's ``regions_labels.tif``, else the whole image), ``pixel_size_um``
    (default from the run's TIFFs). Writes ``comparison.csv`` and, when the run has an albedo,
    ``figures/comparison_map.png`` (``b`` circled in red, ``a``'s missed ones in yellow).
    """
    from .compare import compare_detections, write_comparison_csv
    from .measure import read_protrusions_csv
    from .regions import whole_image
    from .report import plot_comparison_map

    run_dir = Path(output_dir)
    warnings = _unknown(params, {"match_radius_um", "regions", "pixel_size_um"})
    for key in ("a", "b"):
        if not inputs.get(key):
            raise UVPSInputError(f"compare: inputs.{key} is required (a protrusion CSV)")
    a_path, b_path = Path(inputs["a"]), Path(inputs["b"])
    a, b = read_protrusions_csv(a_path), read_protrusions_csv(b_path)
    images = read_run(run_dir, need=(), pixel_size_um=params.get("pixel_size_um"))
    if params.get("regions") == "auto":
        raise UVPSInputError("compare: params.regions must be a label TIFF or null")
    regions = None
    if images.shape is not None:
        regions, _ = _regions_for(params.get("regions"), run_dir, images, params=params)
        if regions is None:
            regions = whole_image(images.shape)
    else:
        warnings.append("no image in the run folder: comparison without areas or densities")
    report(progress, 0.3, "matching")
    comp = compare_detections(a, b, regions=regions, pixel_size_um=images.pixel_size_um,
                              match_radius_um=params.get("match_radius_um"),
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


PROTRUSION_COMMANDS = {
    "detect": cmd_detect,
    "wand": cmd_wand,
    "regions": cmd_regions,
    "stats": cmd_stats,
    "report": cmd_stats,
    "compare": cmd_compare,
}
