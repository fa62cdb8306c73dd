"""``uvps elements``: XRF element maps registered onto a run, per colour area and per protrusion.

Reads element maps as PyMCA and XRF scanners write them (a TIFF or EDF per element, a multi-page
TIFF with the element names as slice labels, or a text table of row, column and one column per
element), registers them onto the run's albedo (:mod:`uvps.core.elements`), and writes
``registration.json``, ``elements.tif`` (the maps in the run's frame, one calibrated ImageJ stack,
element names as slice labels), ``elements_by_area.csv``, ``elements_by_protrusion.csv``,
``element_correlation.csv``, ``report.html`` with its figures, and ``run.json``. See docs/elements.md.
"""
from __future__ import annotations

import csv
import io
import math
import re
import time
from pathlib import Path
from typing import Optional

import numpy as np
import tifffile

from ..core.elements import (ElementMaps, area_elements, protrusion_elements, rank_correlations, register_maps,
                       resample_to_run)
from ..errors import UVPSInputError
from ..files.io import read_text, sha256_file, write_imagej_tiff
from ..files.tables import atomic_write_text, read_protrusions_csv, table_to_csv_text
from ..files.outputs import CommandResult, OutputSpec, Progress, atomic_output_dir, report
from ..core.regions import region_statistics, bin_names
from ..files.tables import load_regions
from ..files.runfolder import FILES, RunLog, read_run
from ..spec import CommandSpec, Param

#: File endings read as element maps.
TIFF_SUFFIXES = (".tif", ".tiff")
EDF_SUFFIXES = (".edf",)
TABLE_SUFFIXES = (".csv", ".txt", ".dat", ".tsv")
#: Column names a text table may give its grid position by (lower case).
ROW_NAMES = ("row", "rows", "y", "r", "i")
COL_NAMES = ("col", "column", "columns", "x", "c", "j")
#: Least fraction of the (standardised) maps' variance the colour areas must explain once registered:
#: 0.92-1.00 on the benchmark's maps (with composition varying +-30 % inside the areas, a flat-topped
#: spot and line jitter), under 0.01 for maps of another region (tests/test_elements.py).
MIN_EXPLAINED = 0.2
#: Fewest map pixels (each way) of a map: a smaller one is not a map.
MIN_MAP_PIXELS = 4


# ------------------------------------------------------------------------------------------------
# reading element maps
# ------------------------------------------------------------------------------------------------

def element_name(path: Path) -> str:
    """An element's name from its file name: ``scan1_Pb L.tif`` -> ``Pb_L`` when the name ends with
    an element symbol and line, else the file's stem with spaces as underscores."""
    stem = Path(path).stem
    m = re.search(r"([A-Z][a-z]?)[ _-]?(K|L|M|Ka|Kb|La|Lb|Ma)$", stem)
    if m:
        return f"{m.group(1)}_{m.group(2)}"
    return re.sub(r"\s+", "_", stem.strip())


def _tiff_step_um(tif: tifffile.TiffFile) -> Optional[float]:
    """The pixel size (um) a TIFF's resolution tags and ImageJ unit give, or None."""
    page = tif.pages[0]
    ij = tif.imagej_metadata or {}
    unit = str(ij.get("unit", "")).lower().replace("\\u00b5", "u").replace("µ", "u")
    tag = page.tags.get("XResolution")
    if tag is None or unit not in ("um", "micron", "microns", "mm"):
        return None
    num, den = tag.value
    if not num:
        return None
    step = den / num
    return step * 1000.0 if unit == "mm" else step


def _read_tiff_maps(path: Path) -> tuple:
    try:
        with tifffile.TiffFile(path) as tif:
            data = tif.asarray()
            step = _tiff_step_um(tif)
            ij = tif.imagej_metadata or {}
            labels = ij.get("Labels")
            if labels is None and len(tif.pages) > 1:
                names = [p.tags.get("PageName") for p in tif.pages]
                labels = [t.value for t in names] if all(t is not None for t in names) else None
    except Exception as exc:  # tifffile raises many kinds on a file that is not a TIFF
        raise UVPSInputError(f"element map {path}: not a readable TIFF ({exc.__class__.__name__}: {exc})") from None
    data = np.asarray(data)
    if data.ndim == 2:
        return [element_name(path)], data[None].astype(float), step
    if data.ndim == 3 and data.shape[-1] not in (3, 4):
        if not labels or len(labels) != data.shape[0]:
            raise UVPSInputError(f"element map {path}: a stack of {data.shape[0]} images without element names; "
                                 "give the slices labels (ImageJ: Image > Stacks > Set Label) or one file "
                                 "per element")
        return [re.sub(r"\s+", "_", str(s).strip()) for s in labels], data.astype(float), step
    raise UVPSInputError(f"element map {path}: an image of shape {data.shape} is not an element map "
                         "(expected one 2-D map, or a stack of maps with element names)")


def read_edf(path: Path) -> np.ndarray:
    """Read an ESRF data format (EDF) image, as PyMCA writes its element maps.

    A header of ``key = value ;`` lines between braces, padded to a multiple of 512 bytes, then the
    raw array (``Dim_1`` columns, ``Dim_2`` rows, ``DataType``, ``ByteOrder``). Hand-written: the
    field's reader (fabio) brings h5py and hdf5plugin with it for these few lines; tested against
    files fabio wrote (tests/test_elements.py).
    """
    raw = Path(path).read_bytes()
    end = raw.find(b"}")
    if not raw.lstrip().startswith(b"{") or end < 0:
        raise UVPSInputError(f"element map {path}: not an EDF file (no '{{...}}' header)")
    head = raw[:end].decode("latin-1")
    keys = {}
    for line in head.splitlines():
        if "=" in line:
            k, v = line.split("=", 1)
            keys[k.strip()] = v.strip().rstrip(";").strip()
    types = {"UnsignedByte": "u1", "SignedByte": "i1", "UnsignedShort": "u2", "SignedShort": "i2",
             "UnsignedInteger": "u4", "SignedInteger": "i4", "UnsignedLong": "u4", "SignedLong": "i4",
             "Unsigned64": "u8", "Signed64": "i8", "FloatValue": "f4", "FLOATVALUE": "f4", "Float": "f4",
             "DoubleValue": "f8", "Double": "f8"}
    try:
        w, h = int(keys["Dim_1"]), int(keys.get("Dim_2", 1))
        dt = types[keys.get("DataType", "FloatValue")]
    except (KeyError, ValueError):
        raise UVPSInputError(f"element map {path}: EDF header lacks Dim_1/Dim_2 or has an unknown DataType "
                             f"({keys.get('DataType')!r})") from None
    order = ">" if keys.get("ByteOrder", "LowByteFirst") == "HighByteFirst" else "<"
    start = end + 1
    while start < len(raw) and raw[start:start + 1] in (b"\n", b"\r"):
        start += 1
    size = int(keys.get("Size", w * h * np.dtype(dt).itemsize))
    body = raw[len(raw) - size:] if len(raw) - start >= size else None
    if body is None or size != w * h * np.dtype(dt).itemsize:
        raise UVPSInputError(f"element map {path}: EDF data shorter than its header says ({w} x {h} {dt})")
    return np.frombuffer(body, dtype=order + dt).reshape(h, w).astype(float)


def _read_table_maps(path: Path) -> tuple:
    text = read_text(path, "element map", "a TIFF, an EDF file or a text table with row and column columns")
    lines = [ln for ln in text.splitlines() if ln.strip() and not ln.lstrip().startswith("#")]
    if len(lines) < 2:
        raise UVPSInputError(f"element map {path}: a table needs a header line and rows")
    first = lines[0]
    delim = "\t" if "\t" in first else ("," if "," in first else (";" if ";" in first else None))
    split = (lambda s: [c.strip() for c in s.split(delim)]) if delim else (lambda s: s.split())
    header = split(first)
    low = [h.strip().lower() for h in header]
    ri = next((low.index(n) for n in ROW_NAMES if n in low), None)
    ci = next((low.index(n) for n in COL_NAMES if n in low), None)
    if ri is None or ci is None:
        raise UVPSInputError(f"element map {path}: the table has no row and column columns "
                             f"(header {', '.join(header[:6])}...; expected e.g. 'row,column,Pb_L,...')")
    cols = [j for j in range(len(header)) if j not in (ri, ci)]
    if not cols:
        raise UVPSInputError(f"element map {path}: the table has no element columns")
    try:
        rows = np.array([[float(v) for v in split(ln)] for ln in lines[1:]])
    except ValueError as exc:
        raise UVPSInputError(f"element map {path}: a value is not a number ({exc})") from None
    if rows.ndim != 2 or rows.shape[1] != len(header):
        raise UVPSInputError(f"element map {path}: rows do not all have {len(header)} values")
    r = np.rint(rows[:, ri]).astype(int)
    c = np.rint(rows[:, ci]).astype(int)
    r -= r.min()
    c -= c.min()
    data = np.full((len(cols), r.max() + 1, c.max() + 1), np.nan)
    for k, j in enumerate(cols):
        data[k, r, c] = rows[:, j]
    return [re.sub(r"\s+", "_", header[j].strip()) for j in cols], data, None


def read_element_maps(paths, *, step_um: Optional[float] = None) -> ElementMaps:
    """Read element maps from files (one grid for all).

    Parameters
    ----------
    paths : list of path
        TIFF (one map, or a stack with element names as slice labels), EDF (one map) or a text table
        (``row``, ``column`` and one column per element; comma, tab, semicolon or space separated).
    step_um : float, optional
        The scan's step; otherwise each TIFF's calibration, which must then agree.

    Raises
    ------
    UVPSInputError
        Unknown format, a file that is not a map, maps of different sizes, steps that differ or
        are missing, an element named twice.
    """
    names, arrays, sources, steps = [], [], [], {}
    expanded = []
    for p in paths:
        # a folder (the Fiji dialog's choice) stands for the map files in it
        p = Path(p)
        if p.is_dir():
            found = sorted(f for f in p.iterdir() if f.is_file()
                           and f.suffix.lower() in TIFF_SUFFIXES + EDF_SUFFIXES + TABLE_SUFFIXES)
            if not found:
                raise UVPSInputError(f"element maps: folder {p} holds no TIFF, EDF or table files")
            expanded.extend(found)
        else:
            expanded.append(p)
    for p in expanded:
        path = Path(p)
        if not path.is_file():
            raise UVPSInputError(f"element map {path} does not exist")
        suffix = path.suffix.lower()
        if suffix in TIFF_SUFFIXES:
            n, d, s = _read_tiff_maps(path)
        elif suffix in EDF_SUFFIXES:
            n, d, s = [element_name(path)], read_edf(path)[None], None
        elif suffix in TABLE_SUFFIXES:
            n, d, s = _read_table_maps(path)
        else:
            raise UVPSInputError(f"element map {path}: unknown format {suffix or '(no ending)'}; expected "
                                 "TIFF, EDF or a text table (.csv, .txt, .dat, .tsv)")
        if min(d.shape[1:]) < MIN_MAP_PIXELS:
            raise UVPSInputError(f"element map {path}: {d.shape[2]} x {d.shape[1]} pixels is not a map "
                                 f"(at least {MIN_MAP_PIXELS} x {MIN_MAP_PIXELS})")
        if s is not None:
            steps[str(path)] = s
        for k in range(d.shape[0]):
            names.append(n[k])
            arrays.append(d[k])
            sources.append(str(path))
    shapes = {a.shape for a in arrays}
    if len(shapes) > 1:
        desc = ", ".join(f"{Path(s).name} {a.shape[1]} x {a.shape[0]}" for s, a in zip(sources, arrays))
        raise UVPSInputError(f"element maps differ in size ({desc}); all must share one scan grid")
    dup = sorted({n for n in names if names.count(n) > 1})
    if dup:
        raise UVPSInputError(f"element {dup[0]!r} is given twice; rename one of its files")
    if step_um is None:
        found = sorted(set(round(v, 6) for v in steps.values()))
        if len(found) != 1 or len(steps) != len(set(sources)):
            raise UVPSInputError("element maps: give the scan's step with --step-um (um per map pixel); "
                                 + ("the files' calibrations differ" if len(found) > 1 else
                                    "not every file records it"))
        step_um = found[0]
    return ElementMaps(names, np.stack(arrays).astype(float), float(step_um), sources)


def read_control_points(path, *, map_shape, run_shape) -> np.ndarray:
    """Control points from a CSV with columns ``map_col, map_row, run_col, run_row`` (pixel centres,
    as ImageJ's multi-point tool reads them). At least two; each inside its image."""
    path = Path(path)
    if not path.is_file():
        raise UVPSInputError(f"control points {path} do not exist")
    text = read_text(path, "control points", "a CSV with columns map_col, map_row, run_col, run_row")
    with io.StringIO(text, newline="") as fh:
        reader = csv.DictReader(fh)
        need = ("map_col", "map_row", "run_col", "run_row")
        fields = [f.strip() for f in (reader.fieldnames or [])]
        if any(n not in fields for n in need):
            raise UVPSInputError(f"control points {path}: expected columns {', '.join(need)}; got "
                                 f"{', '.join(fields) or 'none'}")
        pts = []
        for i, row in enumerate(reader, start=2):
            row = {k.strip(): v for k, v in row.items() if k}
            try:
                pts.append([float(row[n]) for n in need])
            except (TypeError, ValueError):
                raise UVPSInputError(f"control points {path} line {i}: a value is not a number") from None
    cp = np.array(pts, float).reshape(-1, 4)
    if len(cp) < 2:
        raise UVPSInputError(f"control points {path}: at least 2 are needed; got {len(cp)}")
    H, W = map_shape
    M, N = run_shape
    for i, (mc, mr, rc, rr) in enumerate(cp, start=2):
        if not (-0.5 <= mc <= W - 0.5 and -0.5 <= mr <= H - 0.5):
            raise UVPSInputError(f"control points {path} line {i}: map point ({mc:g}, {mr:g}) is outside the "
                                 f"map ({W} x {H} px)")
        if not (-0.5 <= rc <= N - 0.5 and -0.5 <= rr <= M - 0.5):
            raise UVPSInputError(f"control points {path} line {i}: run point ({rc:g}, {rr:g}) is outside the "
                                 f"run ({N} x {M} px)")
    return cp


# ------------------------------------------------------------------------------------------------
# the command
# ------------------------------------------------------------------------------------------------

def _run_regions(run_dir: Path, shape):
    path = run_dir / FILES["regions_labels"][0]
    if not path.is_file():
        raise UVPSInputError(f"run folder {run_dir} has no colour areas ({path.name}); run 'uvps run' with "
                             "--regions (a label image, or auto) first")
    return load_regions(path, shape=shape)


def _run_protrusions(run_dir: Path):
    path = run_dir / FILES["protrusions"][0]
    if not path.is_file():
        raise UVPSInputError(f"run folder {run_dir} has no {path.name}; run 'uvps run' with --detect "
                             "(or --regions) first")
    return read_protrusions_csv(path)


def _names_list(text, what: str, known) -> Optional[list]:
    if text is None or str(text).strip() == "":
        return None
    out = [t.strip() for t in str(text).split(",") if t.strip()]
    bad = [t for t in out if t not in known]
    if bad:
        raise UVPSInputError(f"{what}: element {bad[0]!r} is not among the maps ({', '.join(known)})")
    return out


def _fmt(v, digits=3) -> str:
    """A number with ``digits`` significant digits (empty for NaN)."""
    if v is None or (isinstance(v, float) and not math.isfinite(v)):
        return ""
    return f"{float(v):.{digits}g}"


def _check_registration(reg, params: dict, *, control_points: bool) -> None:
    """Refuse a registration that does not hold: residual, explained variation, overlap (one line each)."""
    what = "the control points" if control_points else "the automatic registration"
    if not reg.residual_map_px <= params["max_residual_map_px"]:
        raise UVPSInputError(
            f"element maps: {what} does not hold (residual {reg.residual_map_px:.2f} map px, more than "
            f"{params['max_residual_map_px']:g}); check --step-um, or give control points "
            "(--control-points: map_col,map_row,run_col,run_row)")
    if reg.explained < MIN_EXPLAINED:
        raise UVPSInputError(
            f"element maps: the run's colour areas explain {100 * reg.explained:.0f} % of the maps' variation "
            f"(at least {100 * MIN_EXPLAINED:.0f} % expected once registered): they do not show this region, "
            "or the areas do not follow the paint; give control points (--control-points) or other areas")
    if reg.overlap < 0.5:
        raise UVPSInputError(f"element maps cover {100 * reg.overlap:.0f} % of the run's field (at least 50 % "
                             "needed); check that the maps show this region, and --step-um")


def _small_area_warnings(areas) -> list:
    """A warning naming the colour areas with too few map pixels to enter the correlation."""
    warnings = []
    small = [n for n, k in zip(areas.names, areas.n_map_pixels) if k < 10]
    if small:
        warnings.append(f"{len(small)} colour area(s) have fewer than 10 map pixels away from their border "
                        f"({', '.join(small[:4])}{', ...' if len(small) > 4 else ''}): their element means "
                        "are left out of the correlation")
    return warnings


def _outputs(out: Path) -> list:
    """What ``elements`` writes into ``out``."""
    return [OutputSpec("registration", str(out / "registration.json"), kind="json"),
               OutputSpec("elements", str(out / "elements.tif"), kind="image", axes="ZYX", dtype="float32",
                          units="counts"),
               OutputSpec("elements_by_area", str(out / "elements_by_area.csv"), kind="table"),
               OutputSpec("elements_by_protrusion", str(out / "elements_by_protrusion.csv"), kind="table"),
               OutputSpec("element_correlation", str(out / "element_correlation.csv"), kind="table"),
               OutputSpec("report", str(out / "report.html"), kind="html"),
               OutputSpec("run", str(out / "run.json"), kind="json")]


def _answer(reg, corr, out: Path) -> list:
    """The lines ``uvps elements`` prints: the registration, each element's correlation, the folder."""
    lines = [f"registration: {reg.method}, residual {reg.residual_map_px:.2f} map px ({reg.residual_of}), "
             f"{reg.scale:.3f} run px per map px, rotation {reg.rotation_deg:.2f} deg, "
             f"{100 * reg.overlap:.0f} % of the field covered"]
    for c in corr:
        lines.append(f"{c.element}: density against area mean, Spearman rho {_fmt(c.rho, 2) or 'n/a'} "
                     f"(95 % CI {_fmt(c.ci_low, 2) or '?'} to {_fmt(c.ci_high, 2) or '?'}, {c.n_areas} areas)")
    lines.append(f"written to {out}")
    return lines


def _write_run_json(path: Path, inputs: dict, params: dict, maps, reg, timings: dict, warnings: list) -> None:
    """``run.json`` of an ``elements`` folder: the request, every map file's SHA-256, timings, warnings."""
    hashes = [{"file": s, "sha256": sha256_file(s)} for s in sorted(set(maps.sources))]
    RunLog("elements", {**params, "run": str(Path(inputs["run"])), "maps": [str(p) for p in inputs["maps"]],
                        "control_points": str(inputs.get("control_points") or "")},
           inputs=hashes, timings_s=timings, warnings=warnings,
           diagnostics={"registration": reg.to_json()}).write(path)


def _read_maps(inputs, params, run_shape):
    """The element maps, the names to register on and to show in the composite, and the control points
    (or None)."""
    maps = read_element_maps(inputs["maps"], step_um=params["step_um"])
    reference = _names_list(params["reference"], "reference", maps.names)
    composite = _names_list(params["composite"], "composite", maps.names) or maps.names[:3]
    cp = (read_control_points(inputs["control_points"], map_shape=maps.shape, run_shape=run_shape)
          if inputs.get("control_points") else None)
    return maps, reference, composite, cp


def cmd_elements(inputs: dict, params: dict, output_dir, *, progress: Progress = None) -> CommandResult:
    """``elements``: register XRF element maps onto a run; element values per area and per protrusion."""
    t_all = time.perf_counter()
    run_dir = Path(inputs["run"])
    out = Path(output_dir)
    timings = {}
    t = time.perf_counter()
    images = read_run(run_dir, need=("albedo",))
    px = images.pixel_size_um
    shape = images.shape
    regions = _run_regions(run_dir, shape)
    table = _run_protrusions(run_dir)
    maps, reference, composite, cp = _read_maps(inputs, params, shape)
    timings["reading"] = round(time.perf_counter() - t, 3)
    t = time.perf_counter()
    spot = params["spot_um"]
    reg = register_maps(images.albedo, maps, labels=regions.labels, pixel_size_um=px, spot_um=spot,
                        reference=reference,
                        control_points=cp, refine=params["refine"],
                        progress=lambda f, m: report(progress, 0.7 * f, m))
    timings["registration"] = round(time.perf_counter() - t, 3)
    _check_registration(reg, params, control_points=cp is not None)
    t = time.perf_counter()
    report(progress, 0.75, "resampling into the run's frame")
    resampled = resample_to_run(maps, reg, shape)
    areas = area_elements(resampled, regions.labels, regions.names, pixel_size_um=px, step_um=maps.step_um,
                          spot_um=spot)
    stats = region_statistics(table, regions, pixel_size_um=px, bins_um=params["bins_um"])
    density = np.array([r.density_per_cm2 for r in stats.rows[:-1]], float)
    corr = rank_correlations(density, areas, maps.names)
    site, ring = protrusion_elements(resampled, table["x_px"], table["y_px"], pixel_size_um=px, spot_um=spot)
    timings["statistics"] = round(time.perf_counter() - t, 3)
    warnings = _small_area_warnings(areas)
    t = time.perf_counter()
    report(progress, 0.85, "writing")
    with atomic_output_dir(out) as tmp:
        from ..files.outputs import write_json_atomic
        write_json_atomic(tmp / "registration.json", {**reg.to_json(), "step_um": maps.step_um,
                                                      "run_pixel_size_um": px, "spot_um": spot,
                                                      "maps": maps.names})
        write_imagej_tiff(tmp / "elements.tif", resampled, axes="ZYX", pixel_size_um=px, labels=maps.names,
                          metadata={"Info": "uvps elements: XRF element maps in the run's frame (counts as "
                                            "the maps hold them); NaN outside the scan"})
        _write_area_csv(tmp / "elements_by_area.csv", areas, stats, maps.names)
        _write_protrusion_csv(tmp / "elements_by_protrusion.csv", table, regions, site, ring, maps.names)
        _write_correlation_csv(tmp / "element_correlation.csv", corr)
        from ..report.elements import write_elements_report
        write_elements_report(tmp, images.albedo, resampled, maps.names, composite, run_dir, table, areas,
                              density, corr, reg, px=px, warnings=warnings)
        timings["writing"] = round(time.perf_counter() - t, 3)
        timings["total"] = round(time.perf_counter() - t_all, 3)
        _write_run_json(tmp / "run.json", inputs, params, maps, reg, timings, warnings)
    outputs = _outputs(out)
    lines = _answer(reg, corr, out)
    report(progress, 1.0, "done")
    diag = {"registration": reg.to_json(), "timings_s": timings,
            "correlation": [{"element": c.element, "rho": c.rho, "n_areas": c.n_areas} for c in corr]}
    return CommandResult(outputs, diag, warnings, text="\n".join(lines))


def _write_area_csv(path, areas, stats, names) -> None:
    bins = bin_names(stats.edges_um)
    totals = np.array([sum(int(r.counts[j]) for r in stats.rows[:-1]) for j in range(len(bins))])
    cols = {"area": areas.names, "n_map_pixels": [round(float(v), 1) for v in areas.n_map_pixels]}
    for e, n in enumerate(names):
        cols[f"{n}_mean"] = [_fmt(v, 4) for v in areas.mean[:, e]]
        cols[f"{n}_sd"] = [_fmt(v, 3) for v in areas.sd[:, e]]
    rows = stats.rows[:-1]
    cols["density_per_cm2"] = [_fmt(r.density_per_cm2, 4) for r in rows]
    for j, b in enumerate(bins):
        cols[f"share_{b}"] = [_fmt(int(r.counts[j]) / totals[j], 3) if totals[j] else "" for r in rows]
    atomic_write_text(path, table_to_csv_text(cols, list(cols)))


def _write_protrusion_csv(path, table, regions, site, ring, names) -> None:
    where = regions.at(table["x_px"], table["y_px"])
    cols = {"id": [int(v) for v in table["id"]], "x_px": [_fmt(v, 6) for v in table["x_px"]],
            "y_px": [_fmt(v, 6) for v in table["y_px"]], "width_um": [_fmt(v, 4) for v in table["width_um"]],
            "area": [regions.names.get(int(a), "") for a in where]}
    for e, n in enumerate(names):
        cols[f"{n}_site"] = [_fmt(v, 4) for v in site[:, e]]
        cols[f"{n}_ring"] = [_fmt(v, 4) for v in ring[:, e]]
    atomic_write_text(path, table_to_csv_text(cols, list(cols)))


def _write_correlation_csv(path, corr) -> None:
    cols = {"element": [c.element for c in corr], "n_areas": [c.n_areas for c in corr],
            "spearman_rho": [_fmt(c.rho, 3) for c in corr], "ci95_low": [_fmt(c.ci_low, 3) for c in corr],
            "ci95_high": [_fmt(c.ci_high, 3) for c in corr], "p_value": [_fmt(c.p_value, 2) for c in corr]}
    atomic_write_text(path, table_to_csv_text(cols, list(cols)))


SPECS = (
    CommandSpec("elements", "XRF element maps registered onto a run: element values per colour area and per "
                "protrusion, and their rank correlation with protrusion density", cmd_elements,
                menu="Element Maps", output="output folder",
                description="Read element maps (TIFF or EDF per element, a multi-page TIFF with element names, "
                "or a row/column text table, as PyMCA exports them), register them onto the run's albedo "
                "(mutual information, or control points), and write registration.json, elements.tif, "
                "elements_by_area.csv, elements_by_protrusion.csv, element_correlation.csv, report.html "
                "and run.json (docs/elements.md).",
                params=(
                    Param("run", "path", where="inputs", positional=True, required=True,
                          label="Source run folder (with colour areas)",
                          help="run folder with colour areas and protrusions (uvps run --regions ...)"),
                    Param("maps", "paths", where="inputs", positional=True, required=True,
                          label="Element maps (folder, or files separated by ;)",
                          help="element map files: TIFF/EDF per element, a labelled TIFF stack, or a table"),
                    Param("step_um", "float", minimum=0, exclusive_minimum=True, unit="um",
                          label="Scan step (um)",
                          help="the scan's step, um per map pixel (default: the TIFFs' calibration)"),
                    Param("spot_um", "float", 1000.0, minimum=0, exclusive_minimum=True, unit="um",
                          label="Spot width (um)", help="the XRF spot's width (FWHM); area means keep this far "
                          "from each area's border"),
                    Param("control_points", "path", where="inputs", label="Control points",
                          help="CSV map_col,map_row,run_col,run_row (2 or more) instead of automatic "
                               "registration"),
                    Param("refine", "bool", False, label="Refine control points",
                          help="refine the control points' registration by the colour areas (helps clicks "
                               "that are a pixel or more off; otherwise the points alone are nearer)"),
                    Param("reference", "str", label="Register on",
                          help="comma-separated elements to register on (default all)"),
                    Param("composite", "str", label="Composite elements",
                          help="three comma-separated elements for the false-colour figure (default the "
                               "first three)"),
                    Param("max_residual_map_px", "float", 1.0, minimum=0, exclusive_minimum=True,
                          label="Largest residual (map px)",
                          help="a registration whose residual exceeds this is refused"),
                    Param("bins_um", "numbers", 100.0, unit="um", minimum=0, label="Width classes",
                          help="width class of the per-area shares, or increasing edges"),
                )),
)
