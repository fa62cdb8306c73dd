"""Tables and label images of a run on disk: ``protrusions.csv`` and ``protrusions_labels.tif``
(:mod:`uvps.core.measure`'s table), colour areas read from label images, masks and names files, and
``regions.csv`` (:mod:`uvps.core.regions`). Every file is written atomically."""
from __future__ import annotations

import csv
import json
import logging
from io import StringIO
from pathlib import Path
from typing import Mapping, Optional, Sequence

import numpy as np

from ..core.measure import _INT_COLUMNS, _STR_COLUMNS, COLUMNS, RELATIVE_HEIGHT, _dtype
from ..core.regions import RegionMap, RegionStats, _as_label_image, _check_shape, _mask_of, stats_columns
from ..errors import UVPSInputError
from .io import read_image, read_text, read_tiff, write_imagej_tiff
from .outputs import atomic_path

log = logging.getLogger(__name__)


def _fmt(value) -> str:
    if isinstance(value, (float, np.floating)):
        return "" if not np.isfinite(value) else f"{float(value):.10g}"
    return str(value)


def atomic_write_text(path, text: str) -> None:
    """Write text to ``path`` atomically (``uvps.files.outputs.atomic_path``)."""
    with atomic_path(path) as tmp:
        with open(tmp, "w", encoding="utf-8", newline="") as fh:
            fh.write(text)


def table_to_csv_text(table: Mapping, columns: Sequence[str]) -> str:
    """CSV text of the given columns of a column table (NaN written as an empty cell)."""
    buf = StringIO()
    writer = csv.writer(buf, lineterminator="\n")
    writer.writerow(columns)
    n = len(table[columns[0]]) if columns else 0
    for i in range(n):
        writer.writerow([_fmt(table[c][i]) for c in columns])
    return buf.getvalue()


#: The wand's table (``protrusions_manual.csv``) holds one row per click: ``counted`` says whether the click
#: outlined a protrusion (1) or not (0), ``note`` why not. Only counted rows are protrusions.
CLICK_COLUMNS = ("counted", "note")


def write_protrusions_csv(path, table: Mapping, *, relative: bool = False, extra: Sequence[str] = ()) -> None:
    """Write a protrusion table as CSV (columns :data:`COLUMNS`, in order), atomically.

    Parameters
    ----------
    path : str or Path
        Output file, e.g. ``<run>/protrusions.csv``.
    table : dict of str -> array
        As returned by :func:`measure_protrusions`.
    relative : bool
        The run's relief has no scale (``uvps.files.runfolder.relief_of``): the ``height_um`` column is
        written as :data:`RELATIVE_HEIGHT` (no unit), so no table says micrometres it does not have.
    extra : sequence of str
        Further columns written after :data:`COLUMNS` (the wand's :data:`CLICK_COLUMNS`).
    """
    columns = tuple(COLUMNS) + tuple(extra)
    missing = [c for c in columns if c not in table]
    if missing:
        raise UVPSInputError(f"protrusion table lacks columns {missing}")
    lengths = {len(table[c]) for c in columns}
    if len(lengths) > 1:
        raise UVPSInputError(f"protrusion table columns differ in length: {sorted(lengths)}")
    if relative:
        table = {**table, RELATIVE_HEIGHT: table["height_um"]}
        atomic_write_text(path, table_to_csv_text(table, [RELATIVE_HEIGHT if c == "height_um" else c
                                                          for c in columns]))
        return
    atomic_write_text(path, table_to_csv_text(table, columns))


def not_counted(cell: str) -> bool:
    """A ``counted`` cell of the wand's table (:data:`CLICK_COLUMNS`) that says the click is not counted."""
    return cell.strip().lower() in ("0", "no", "false")


def read_protrusions_csv(path, *, clicks: bool = False) -> dict:
    """Read ``protrusions.csv`` back into a column table.

    A table with a ``counted`` column (the wand's ``protrusions_manual.csv``: one row per click) gives
    its counted rows only, the protrusions; ``clicks=True`` gives every row (the clicks, counted or not).

    Only ``x_px``, ``y_px`` and ``width_um`` are required (so a table from another tool can be
    compared); the other columns of :data:`COLUMNS` get defaults (``id`` = 1..n, NaN, 0, "").
    Extra columns are kept as strings, but for :data:`RELATIVE_HEIGHT` (a number; ``height_um`` is
    then NaN: a relative run's table has no heights in micrometres).

    Raises
    ------
    UVPSInputError
        If the file is missing, unreadable or lacks a required column or holds a non-number.
    """
    path = Path(path)
    if not path.is_file():
        raise UVPSInputError(f"protrusion table {path} does not exist")
    rows = list(csv.reader(read_text(path, "protrusion table", "a CSV with columns x_px,y_px,width_um")
                           .splitlines()))
    if not rows:
        raise UVPSInputError(f"protrusion table {path} is empty; expected a header with "
                             "x_px,y_px,width_um")
    header = [h.strip() for h in rows[0]]
    body = [r for r in rows[1:] if any(cell.strip() for cell in r)]
    if "counted" in header and not clicks:
        k = header.index("counted")
        body = [r for r in body if not (k < len(r) and not_counted(r[k]))]
    missing = [c for c in ("x_px", "y_px", "width_um") if c not in header]
    if missing:
        raise UVPSInputError(f"protrusion table {path} lacks columns {missing}; got {header}")
    n = len(body)
    table = {}
    for j, name in enumerate(header):
        cells = [(r[j].strip() if j < len(r) else "") for r in body]
        if name in _STR_COLUMNS or (name not in COLUMNS and name != RELATIVE_HEIGHT):
            table[name] = np.array(cells, dtype=object)
            continue
        try:
            values = [float(c) if c else np.nan for c in cells]
        except ValueError:
            bad = next(c for c in cells if c and not _is_float(c))
            raise UVPSInputError(f"protrusion table {path}: column {name} holds {bad!r}; "
                                 "expected a number") from None
        arr = np.array(values, dtype=np.float64)
        if name in _INT_COLUMNS:
            arr = np.nan_to_num(arr, nan=0.0).astype(np.int64)
        table[name] = arr
    defaults = {"id": np.arange(1, n + 1, dtype=np.int64)}
    for c in COLUMNS:
        if c not in table:
            table[c] = defaults.get(c, np.zeros(n, dtype=_dtype(c)) if c in _INT_COLUMNS else
                                    np.array([""] * n, dtype=object) if c in _STR_COLUMNS else
                                    np.full(n, np.nan))
    ordered = {c: table[c] for c in COLUMNS}
    ordered.update({k: v for k, v in table.items() if k not in ordered})
    return ordered


def _is_float(text: str) -> bool:
    try:
        float(text)
    except ValueError:
        return False
    return True


def write_label_tiff(path, labels: np.ndarray, *, pixel_size_um: float,
                     metadata: Optional[dict] = None) -> None:
    """Write an int32 label image as an ImageJ TIFF (calibrated in um) with ``uvps.files.io``."""
    write_imagej_tiff(path, np.asarray(labels).astype(np.int32, copy=False), axes="YX",
                      pixel_size_um=pixel_size_um, metadata=metadata)


def check_region_files(paths) -> None:
    """Refuse a region file that does not exist, in one line (before a run reads its images)."""
    for path in [paths] if isinstance(paths, (str, Path)) else paths:
        if not Path(path).is_file():
            raise UVPSInputError(f"region file {path} does not exist (or give auto: colour areas proposed "
                                 "from the albedo)")


def _read_array(path: Path) -> np.ndarray:
    check_region_files(path)
    if path.suffix.lower() in (".tif", ".tiff"):
        return np.asarray(read_tiff(path).data)
    return np.asarray(read_image(path))


def read_region_names(path) -> dict:
    """Read area names from a CSV (columns ``label,name``) or JSON (``{"1": "light red"}``) file.

    Rows whose label is not a whole number (e.g. the "all" row of ``regions.csv``) are skipped.
    """
    path = Path(path)
    if path.suffix.lower() == ".json":
        try:
            raw = json.loads(path.read_text(encoding="utf-8"))
        except (OSError, ValueError) as exc:
            raise UVPSInputError(f"region names file {path}: not valid JSON ({exc})") from None
        if isinstance(raw, dict) and "names" in raw:
            raw = raw["names"]
        if not isinstance(raw, dict):
            raise UVPSInputError(f"region names file {path}: expected an object label -> name")
        items = raw.items()
    else:
        rows = list(csv.DictReader(read_text(path, "region names file", "a CSV with columns label,name")
                                   .splitlines()))
        if rows and not {"label", "name"} <= set(rows[0]):
            raise UVPSInputError(f"region names file {path}: header must contain label,name")
        items = [(r["label"], r["name"]) for r in rows]
    names = {}
    for lab, name in items:
        try:
            names[int(str(lab).strip())] = str(name)
        except ValueError:
            continue
    return names


def _names_beside(path: Path) -> dict:
    for cand in (path.with_suffix(".json"), path.with_suffix(".csv"),
                 path.parent / (path.stem + "_names.csv"), path.parent / "regions.csv"):
        if cand.is_file():
            # every candidate lies beside the label image: its name says which, and a run building its folder
            # in a staging folder (files.outputs.new_output_dir) does not name that folder
            log.info("area names from %s (beside %s)", cand.name, path.name)
            return read_region_names(cand)
    return {}


def load_regions(labels_or_masks, *, shape, names: Optional[dict] = None) -> RegionMap:
    """Read colour areas from a label image or from one mask per area.

    Parameters
    ----------
    labels_or_masks : path, (M, N) array, or list of paths/arrays
        A label TIFF (0 = no area; ImageJ may store it as 8/16-bit or float), a label array, or a
        list of masks (nonzero = inside), one area per mask, labelled 1, 2, ... in list order.
    shape : (M, N)
        The capture's image shape; every label image or mask must match it.
    names : dict of int -> str, optional
        Area names. Otherwise read from a names file beside the label TIFF (``<stem>.json``,
        ``<stem>.csv``, ``<stem>_names.csv`` or ``regions.csv``, columns ``label,name``), from
        the mask file names, else "area 1", "area 2", ...

    Returns
    -------
    RegionMap

    Raises
    ------
    UVPSInputError
        Wrong size, no area at all, or a listed mask that is empty.

    Notes
    -----
    Where masks overlap, the earlier mask keeps the pixel (so no protrusion is counted twice).
    """
    shape = tuple(int(s) for s in shape)
    found_names: dict = {}
    if isinstance(labels_or_masks, (list, tuple)):
        if not labels_or_masks:
            raise UVPSInputError("masks: got an empty list; expected one mask per colour area")
        labels = np.zeros(shape, np.int32)
        for i, item in enumerate(labels_or_masks, start=1):
            if isinstance(item, (str, Path)):
                what = f"mask {item}"
                mask = _mask_of(_read_array(Path(item)), shape, what)
                found_names[i] = Path(item).stem
            else:
                what = f"mask {i}"
                mask = _mask_of(item, shape, what)
            if not mask.any():
                raise UVPSInputError(f"{what} is empty; expected at least one pixel of its area")
            free = mask & (labels == 0)
            if free.sum() < mask.sum():
                log.warning("%s overlaps earlier masks; the earlier ones keep %d pixels", what,
                            int(mask.sum() - free.sum()))
            if not free.any():
                raise UVPSInputError(f"{what} lies entirely under earlier masks; its area has "
                                     "no pixels")
            labels[free] = i
        ids = list(range(1, len(labels_or_masks) + 1))
    else:
        if isinstance(labels_or_masks, (str, Path)):
            path = Path(labels_or_masks)
            what = f"region label image {path}"
            labels = _as_label_image(_read_array(path), what)
            found_names = _names_beside(path)
        else:
            what = "region label image"
            labels = _as_label_image(labels_or_masks, what)
        _check_shape(labels, shape, what)
        ids = [int(i) for i in np.unique(labels) if i != 0]
        if not ids:
            raise UVPSInputError(f"{what} has no area (all pixels are 0)")
    given = dict(found_names)
    given.update(names or {})
    absent = sorted(set(given) - set(ids))
    if absent and names:
        raise UVPSInputError(f"region names given for labels {absent} that have no pixels")
    if absent:
        log.warning("names for labels %s ignored: those areas have no pixels", absent)
    return RegionMap(labels, {i: given.get(i, f"area {i}") for i in ids})


def write_regions_csv(path, stats: RegionStats) -> None:
    """Write ``regions.csv`` atomically: one row per area then "all".

    Columns: ``label, name, area_cm2, count, density_per_cm2``, then ``count_<lo>-<hi>um`` per
    width bin, then ``density_<lo>-<hi>um`` (per cm^2) per bin.
    """
    cols = stats_columns(stats)
    atomic_write_text(path, table_to_csv_text(cols, list(cols)))


def read_counts(run_dir: Path) -> dict:
    """``n_protrusions`` (rows of ``protrusions.csv``) and the rows of ``regions.csv`` of a run
    folder (``areas``: name, area_cm2, count, density_per_cm2; the "all" row left out)."""
    out = {"n_protrusions": None, "areas": []}
    table = run_dir / "protrusions.csv"
    if table.is_file():
        with open(table, encoding="utf-8") as fh:
            out["n_protrusions"] = max(0, sum(1 for line in fh if line.strip()) - 1)
    regions = run_dir / "regions.csv"
    if regions.is_file():
        with open(regions, newline="", encoding="utf-8") as fh:
            out["areas"] = [{"name": r["name"], "area_cm2": float(r["area_cm2"]), "count": int(r["count"]),
                             "density_per_cm2": float(r["density_per_cm2"])}
                            for r in csv.DictReader(fh) if r["label"] != "all"]
    return out
