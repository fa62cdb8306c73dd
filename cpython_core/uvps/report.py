"""The run report: ``report.html`` and PNG figures in ``figures/``.

Figures follow the paper (Salvant et al.): lamp positions (Fig. 1), normal map and albedo
(Fig. 2), the height map with the protrusions outlined and a shaded 3-D detail of the largest one
(Fig. 2e), per-area densities by width bin (Fig. 4a) and the two-method comparison (Fig. 4c).
Every figure is optional: a missing input skips its figure and the report says why. The HTML is
self-contained apart from the PNGs, linked relatively, so the run folder can be moved or zipped.
"""
from __future__ import annotations

import html
import json
import logging
from dataclasses import dataclass, field
from datetime import datetime, timezone
from pathlib import Path
from typing import Optional

import numpy as np
from scipy import ndimage as ndi
from skimage.measure import block_reduce
from skimage.segmentation import find_boundaries

from . import __version__
from .compare import COLUMNS, read_comparison_csv
from .errors import UVPSInputError
from .io import read_tiff
from .measure import atomic_write_text, read_protrusions_csv
from .outputs import Progress, atomic_path, report
from .regions import bin_names, load_regions, region_statistics, stats_columns, whole_image
from .runfolder import read_run

log = logging.getLogger(__name__)

# matplotlib is imported inside the plotting functions, not here, so that importing this module
# stays cheap (the commands import it at start-up of the CLI and the Fiji bridge): matplotlib costs
# about 0.3 s that only a run drawing figures should pay.

_MAX_DISPLAY_PX = 1600  # longest side of an image drawn into a figure


# ---------------------------------------------------------------------------------------------
# helpers


def figure(figsize, layout="constrained"):
    # Figure objects without pyplot: no global state, always the Agg canvas. Image figures pass
    # layout=None (a fixed margin): the constrained layout costs a second draw.
    from matplotlib.figure import Figure

    fig = Figure(figsize=figsize, dpi=100, layout=layout)
    if layout is None:
        fig.subplots_adjust(left=0.1, right=0.95, bottom=0.1, top=0.92)
    return fig


def save_figure(fig, path) -> Path:
    """Save a matplotlib figure as PNG atomically (``uvps.outputs.atomic_path``)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_path(path, suffix=".png") as tmp:
        fig.savefig(tmp, format="png")
    return path


def display_step(shape) -> int:
    return max(1, int(np.ceil(max(shape[:2]) / _MAX_DISPLAY_PX)))


def _yxc(img: np.ndarray) -> np.ndarray:
    """(3, M, N) -> (M, N, 3); (M, N) and (M, N, 3) unchanged."""
    img = np.asarray(img)
    if img.ndim == 3 and img.shape[0] == 3 and img.shape[-1] != 3:
        return np.moveaxis(img, 0, -1)
    return img


def display_albedo(albedo: np.ndarray, step: int = 1) -> np.ndarray:
    """Every ``step``-th pixel of the albedo as (M', N[, 3]) in 0..1 (99.5th percentile = 1)."""
    a = _yxc(albedo)[::step, ::step].astype(np.float64)
    finite = a[np.isfinite(a)]
    scale = float(np.percentile(finite, 99.5)) if finite.size else 1.0
    return np.clip(np.nan_to_num(a / (scale or 1.0)), 0.0, 1.0)


def extent_mm(shape, px_um):
    """imshow extent in mm from the image centre (x right, y up: architecture frame)."""
    m, n = shape[:2]
    px = px_um / 1000.0
    return (-n / 2 * px, n / 2 * px, -m / 2 * px, m / 2 * px)


def _outline(labels: np.ndarray, step: int) -> np.ndarray:
    """Protrusion outlines at display resolution (max-pooled so thin lines survive)."""
    b = find_boundaries(labels, mode="outer")
    return block_reduce(b, (step, step), np.max) if step > 1 else b


# ---------------------------------------------------------------------------------------------
# figures (each takes arrays/dicts and a path, and returns the path)


def plot_lights(lights: dict, path) -> Path:
    """Lamp positions: a polar top view (azimuth, elevation) and the height of each lamp.

    The polar view puts azimuth counter-clockwise from +x (image right), as in ``lights.json``,
    and 90 - elevation as the radius (the centre is straight above the canvas). The bar chart
    gives each lamp's height above the canvas (z of ``position_mm``) for near lights, else its
    elevation.
    """
    entries = lights.get("lights") or []
    if not entries:
        raise UVPSInputError("lights.json has no 'lights' entries")
    az = np.array([float(e.get("azimuth_deg", np.nan)) for e in entries])
    el = np.array([float(e.get("elevation_deg", np.nan)) for e in entries])
    pos = [e.get("position_mm") for e in entries]
    fig = figure((9, 4.2))
    ax = fig.add_subplot(1, 2, 1, projection="polar")
    ax.scatter(np.radians(az), 90.0 - el, c=el, cmap="viridis", vmin=0, vmax=90, s=60,
               edgecolors="k")
    for k, (a, r) in enumerate(zip(az, 90.0 - el), start=1):
        ax.annotate(str(k), (np.radians(a), r), textcoords="offset points", xytext=(6, 6),
                    fontsize=8)
    ax.set_rlim(0, 90)
    ax.set_rticks([30, 60, 90], labels=["60\u00b0", "30\u00b0", "0\u00b0"])
    ax.set_title(f"lamps seen from above ({lights.get('mode', '?')} lights)\n"
                 "azimuth from +x, radius = 90\u00b0 - elevation", fontsize=9)
    ax2 = fig.add_subplot(1, 2, 2)
    idx = np.arange(1, len(entries) + 1)
    if all(p is not None for p in pos):
        z = np.array([float(p[2]) for p in pos])
        ax2.bar(idx, z, color="tab:blue")
        ax2.set_ylabel("lamp height above canvas (mm)")
        ax2.set_title(f"height of each lamp (m = {lights.get('m_mm', '?')} mm)", fontsize=9)
    else:
        ax2.bar(idx, el, color="tab:blue")
        ax2.set_ylabel("elevation (\u00b0)")
        ax2.set_title("elevation of each lamp (far lights: no position)", fontsize=9)
    ax2.set_xlabel("lamp")
    ax2.set_xticks(idx)
    return save_figure(fig, path)


def plot_normals(normals: np.ndarray, path, *, pixel_size_um: float) -> Path:
    """Normal map in the usual RGB encoding ``(n + 1) / 2`` (x red, y green, z blue)."""
    n = _yxc(normals)
    step = display_step(n.shape)
    rgb = np.clip((np.nan_to_num(n[::step, ::step]) + 1.0) / 2.0, 0, 1)
    fig = figure((7, 7 * n.shape[0] / n.shape[1] + 0.6), layout=None)
    ax = fig.add_subplot()
    ax.imshow(rgb, extent=extent_mm(n.shape, pixel_size_um), interpolation="nearest")
    ax.set_xlabel("x (mm)")
    ax.set_ylabel("y (mm)")
    ax.set_title("normal map, RGB = (n + 1) / 2")
    return save_figure(fig, path)


def plot_albedo(albedo: np.ndarray, path, *, pixel_size_um: float) -> Path:
    """Albedo (fluorescence colour), scaled by its 99.5th percentile."""
    shape = _yxc(albedo).shape
    a = display_albedo(albedo, display_step(shape))
    fig = figure((7, 7 * shape[0] / shape[1] + 0.6), layout=None)
    ax = fig.add_subplot()
    ax.imshow(a, cmap="gray", vmin=0, vmax=1, extent=extent_mm(shape, pixel_size_um),
              interpolation="nearest")
    ax.set_xlabel("x (mm)")
    ax.set_ylabel("y (mm)")
    ax.set_title("albedo (UV fluorescence)")
    return save_figure(fig, path)


def plot_height(height_um: np.ndarray, path, *, pixel_size_um: float,
                labels: Optional[np.ndarray] = None) -> Path:
    """Height map (um) with the protrusion outlines in red (``find_boundaries``)."""
    step = display_step(height_um.shape)
    h = height_um[::step, ::step]
    finite = h[np.isfinite(h)]
    lo, hi = (np.percentile(finite, [1, 99]) if finite.size else (0.0, 1.0))
    fig = figure((7.6, 7 * h.shape[0] / h.shape[1] + 0.6), layout=None)
    ax = fig.add_subplot()
    ext = extent_mm(height_um.shape, pixel_size_um)
    im = ax.imshow(h, cmap="viridis", vmin=lo, vmax=hi, extent=ext, interpolation="nearest")
    fig.colorbar(im, ax=ax, label="height (\u00b5m)", shrink=0.8)
    title = "height map"
    if labels is not None and labels.any():
        edge = _outline(labels, step)[: h.shape[0], : h.shape[1]]
        overlay = np.zeros(edge.shape + (4,))
        overlay[edge] = (1.0, 0.0, 0.0, 1.0)
        ax.imshow(overlay, extent=ext, interpolation="nearest")
        title += f" with {int(len(np.unique(labels)) - 1)} protrusions outlined"
    ax.set_title(title)
    ax.set_xlabel("x (mm)")
    ax.set_ylabel("y (mm)")
    return save_figure(fig, path)


def plot_detail_3d(height_um: np.ndarray, path, *, pixel_size_um: float, centre_xy,
                   width_um: float, vert_exag: float = 1.0) -> Path:
    """Shaded 3-D rendering of the height around one protrusion (paper Fig. 2e).

    A square of 3 x its width (at least 32 pixels) around ``centre_xy`` = (x_px, y_px), drawn
    with ``plot_surface`` coloured by :class:`matplotlib.colors.LightSource` hill shading (light
    from the upper left, 315 deg, 45 deg elevation).
    """
    from matplotlib import cm
    from matplotlib.colors import LightSource
    import mpl_toolkits.mplot3d  # noqa: F401  (registers the 3-D projection)

    m, n = height_um.shape
    half = int(max(16, np.ceil(1.5 * width_um / pixel_size_um)))
    cx, cy = int(round(centre_xy[0])), int(round(centre_xy[1]))
    r0, r1 = max(cy - half, 0), min(cy + half + 1, m)
    c0, c1 = max(cx - half, 0), min(cx + half + 1, n)
    z = np.asarray(height_um[r0:r1, c0:c1], dtype=np.float64)
    fill = np.nanmedian(z) if np.isfinite(z).any() else 0.0
    z = np.where(np.isfinite(z), z, fill)
    stride = max(1, int(np.ceil(max(z.shape) / 100)))
    z = z[::stride, ::stride]
    rows = (np.arange(r0, r1, stride) - cy) * pixel_size_um
    cols = (np.arange(c0, c1, stride) - cx) * pixel_size_um
    x, y = np.meshgrid(cols, -rows)  # y up
    ls = LightSource(azdeg=315, altdeg=45)
    rgb = ls.shade(z, cmap=cm.copper, vert_exag=vert_exag, blend_mode="soft",
                   dx=pixel_size_um * stride, dy=pixel_size_um * stride)
    fig = figure((7, 5.5), layout=None)
    ax = fig.add_subplot(projection="3d")
    ax.plot_surface(x, y, z, facecolors=rgb, rstride=1, cstride=1, linewidth=0,
                    antialiased=False, shade=False)
    ax.set_xlabel("x (\u00b5m)")
    ax.set_ylabel("y (\u00b5m)")
    ax.set_zlabel("height (\u00b5m)")
    ax.set_title(f"detail around ({cx}, {cy}) px, width {width_um:.0f} \u00b5m", fontsize=10)
    return save_figure(fig, path)


def region_colours(regions, albedo: Optional[np.ndarray]) -> dict:
    """Display colour per area: the RegionMap's colours, else the mean albedo, else a colour map."""
    from matplotlib import colormaps

    cols = dict(getattr(regions, "colors", {}) or {})
    if albedo is not None:
        step = display_step(regions.labels.shape)
        a = display_albedo(albedo, step)
        if a.ndim == 2:
            a = np.repeat(a[..., None], 3, axis=-1)
        small = regions.labels[::step, ::step]
        for i in regions.ids:
            if i not in cols:
                sel = small == i
                cols[i] = a[sel].mean(axis=0) if sel.any() else np.array([0.5, 0.5, 0.5])
    tab = colormaps["tab10"]
    return {i: tuple(np.clip(cols.get(i, tab(k % 10)[:3]), 0, 1))
            for k, i in enumerate(regions.ids)}


def plot_regions(albedo: np.ndarray, regions, path, *, pixel_size_um: float) -> Path:
    """Albedo with the colour-area borders and numbers (to check a proposal before editing it)."""
    step = display_step(regions.labels.shape)
    a = display_albedo(albedo, step)
    fig = figure((7, 7 * a.shape[0] / a.shape[1] + 0.6), layout=None)
    ax = fig.add_subplot()
    ext = extent_mm(regions.labels.shape, pixel_size_um)
    ax.imshow(a, cmap="gray", vmin=0, vmax=1, extent=ext, interpolation="nearest")
    edge = find_boundaries(regions.labels, mode="inner")
    if step > 1:
        edge = block_reduce(edge, (step, step), np.max)
    edge = edge[: a.shape[0], : a.shape[1]]
    overlay = np.zeros(edge.shape + (4,))
    overlay[edge] = (1.0, 1.0, 0.0, 1.0)
    ax.imshow(overlay, extent=ext, interpolation="nearest")
    small = regions.labels[::step, ::step]
    m, n = regions.labels.shape
    for i in regions.ids:
        inside = small == i
        if not inside.any():
            continue
        d = ndi.distance_transform_edt(np.pad(inside, 1))[1:-1, 1:-1]
        r, c = np.unravel_index(np.argmax(d), d.shape)
        x = (c * step - n / 2) * pixel_size_um / 1000
        y = (m / 2 - r * step) * pixel_size_um / 1000
        ax.text(x, y, f"{i}: {regions.names[i]}", color="yellow", fontsize=8, ha="center",
                va="center", bbox=dict(facecolor="black", alpha=0.5, pad=1, edgecolor="none"))
    ax.set_title("colour areas")
    ax.set_xlabel("x (mm)")
    ax.set_ylabel("y (mm)")
    return save_figure(fig, path)


def plot_histograms(stats, path, *, colours: Optional[dict] = None) -> Path:
    """Protrusions per cm^2 by width bin, one panel per colour area (paper Fig. 4a)."""
    rows = [r for r in stats.rows if r.label != "all"]
    labels = bin_names(stats.edges_um)
    k = len(rows)
    ncols = min(4, max(k, 1))
    nrows = int(np.ceil(k / ncols)) if k else 1
    fig = figure((3.2 * ncols, 2.6 * nrows + 0.4))
    axes = fig.subplots(nrows, ncols, squeeze=False, sharey=True)
    x = np.arange(len(labels))
    for ax, r in zip(axes.ravel(), rows):
        colour = (colours or {}).get(r.label, (0.5, 0.5, 0.5))
        ax.bar(x, r.densities, color=colour, edgecolor="k", linewidth=0.5)
        ax.set_title(f"{r.label}: {r.name}\n{r.density_per_cm2:.1f} /cm\u00b2 "
                     f"({r.count} in {r.area_cm2:.3g} cm\u00b2)", fontsize=8)
        ax.set_xticks(x, [s.replace("um", "") for s in labels], rotation=60, fontsize=7)
    for ax in axes.ravel()[k:]:
        ax.set_visible(False)
    for ax in axes[:, 0]:
        ax.set_ylabel("protrusions / cm\u00b2")
    fig.suptitle("protrusion density by width (\u00b5m) per colour area", fontsize=10)
    return save_figure(fig, path)


def plot_comparison(rows: list, path, *, name_a: str = "a", name_b: str = "b") -> Path:
    """Densities of the two detections per area, side by side (paper Fig. 4c)."""
    rows = [r for r in rows if str(r["label"]) != "all"]
    x = np.arange(len(rows))
    da = [float(r["density_a"] or "nan") for r in rows]
    db = [float(r["density_b"] or "nan") for r in rows]
    fig = figure((max(5, 0.9 * len(rows) + 2), 3.8))
    ax = fig.add_subplot()
    ax.bar(x - 0.2, da, 0.4, label=name_a)
    ax.bar(x + 0.2, db, 0.4, label=name_b)
    ax.set_xticks(x, [f"{r['label']}: {r['name']}" for r in rows], rotation=30, ha="right",
                  fontsize=8)
    ax.set_ylabel("protrusions / cm\u00b2")
    ax.legend()
    ax.set_title("protrusion density per colour area: two methods")
    return save_figure(fig, path)


def plot_comparison_map(albedo: np.ndarray, a: dict, b: dict, comparison, path, *,
                        pixel_size_um: float) -> Path:
    """Albedo with ``b``'s protrusions circled in red and ``a``'s missed ones in yellow (Fig. 4b).

    Circles have the protrusion's width as diameter, at its centroid.
    """
    from matplotlib.patches import Circle

    m, n = _yxc(albedo).shape[:2]
    img = display_albedo(albedo, display_step((m, n)))
    fig = figure((7, 7 * m / n + 0.6), layout=None)
    ax = fig.add_subplot()
    ext = extent_mm((m, n), pixel_size_um)
    ax.imshow(img, cmap="gray", vmin=0, vmax=1, extent=ext,
              interpolation="nearest")
    to_mm = pixel_size_um / 1000.0

    def circles(table, rows, colour):
        for i in rows:
            x = (float(table["x_px"][i]) - (n - 1) / 2) * to_mm
            y = ((m - 1) / 2 - float(table["y_px"][i])) * to_mm
            r = max(float(np.nan_to_num(table["width_um"][i])) / 2000.0, 2 * to_mm)
            ax.add_patch(Circle((x, y), r * 1.3, fill=False, color=colour, linewidth=1.0))

    circles(b, range(len(b["x_px"])), "red")
    circles(a, comparison.missed, "yellow")
    ax.set_xlim(ext[0], ext[1])
    ax.set_ylim(ext[2], ext[3])
    ax.set_title(f"red: {comparison.name_b} ({len(b['x_px'])}); yellow: {comparison.name_a} "
                 f"missed by it ({len(comparison.missed)})", fontsize=9)
    ax.set_xlabel("x (mm)")
    ax.set_ylabel("y (mm)")
    return save_figure(fig, path)


# ---------------------------------------------------------------------------------------------
# the report


@dataclass
class _Page:
    """What the HTML holds, collected while the figures are drawn."""

    figures: list = field(default_factory=list)  # (file name, caption)
    skipped: list = field(default_factory=list)  # (figure, reason)
    sections: list = field(default_factory=list)  # HTML fragments


def _read_json(path: Path):
    try:
        return json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError) as exc:
        raise UVPSInputError(f"{path}: not valid JSON ({exc})") from None


def _read_optional_tiff(path: Path):
    if not path.is_file():
        return None, None
    data, px = read_tiff(path)
    return np.asarray(data), px


def table_html(header, rows) -> str:
    head = "".join(f"<th>{html.escape(str(h))}</th>" for h in header)
    body = "".join("<tr>" + "".join(f"<td>{html.escape(_cell(v))}</td>" for v in row) + "</tr>"
                   for row in rows)
    return f"<table><thead><tr>{head}</tr></thead><tbody>{body}</tbody></table>"


def _cell(v) -> str:
    if isinstance(v, (float, np.floating)):
        return "" if not np.isfinite(v) else f"{float(v):.4g}"
    if isinstance(v, (dict, list)):
        return json.dumps(v)
    return str(v)


def _figure_step(page: _Page, name: str, caption: str, fn, *args, **kwargs) -> None:
    try:
        fn(*args, **kwargs)
    except UVPSInputError as exc:
        page.skipped.append((name, str(exc)))
        return
    page.figures.append((name, caption))


CSS = """body{font-family:sans-serif;max-width:1100px;margin:1em auto;padding:0 1em;color:#222}
table{border-collapse:collapse;margin:0.5em 0;font-size:0.9em}
td,th{border:1px solid #bbb;padding:2px 6px;text-align:right}th{background:#eee}
td:first-child,th:first-child{text-align:left}figure{margin:1em 0}img{max-width:100%}
.warn{color:#a40}pre{background:#f6f6f6;padding:0.5em;overflow-x:auto}"""


def write_report(run_dir, *, table=None, bins_um=100.0, stats=None, regions=None, comparison=None,
                 warnings: Optional[list] = None, title: Optional[str] = None, images=None,
                 progress: Progress = None) -> Path:
    """Write ``report.html`` and ``figures/*.png`` for a run folder.

    Parameters
    ----------
    run_dir : path
        The run folder (see ``docs/architecture.md``). Read if present: ``run.json``,
        ``lights.json``, ``normals.tif``, ``albedo.tif``, ``depth.tif``, ``protrusions.csv``,
        ``protrusions_labels.tif``, ``regions_labels.tif``, ``comparison.csv``.
    table : path, optional
        The protrusion CSV to summarise and outline (default ``<run_dir>/protrusions.csv``; e.g.
        ``protrusions_manual.csv`` for the wand count, then with its ``*_labels.tif``).
    bins_um : float or sequence of float
        Width bins of the histograms when ``stats`` is not given.
    stats : RegionStats, optional
        Per-area statistics; otherwise computed from ``protrusions.csv`` and the colour areas.
    regions : RegionMap, optional
        Colour areas; otherwise ``regions_labels.tif`` or the whole image.
    comparison : Comparison, optional
        A two-method comparison; otherwise ``comparison.csv`` when present.
    warnings : list of str, optional
        Warnings to list (besides those in ``run.json``).
    title : str, optional
    images : RunImages, optional
        The run folder's images when the caller has read them already (:func:`uvps.runfolder.read_run`).
    progress : callable(fraction, message), optional

    Returns
    -------
    Path
        ``<run_dir>/report.html``.

    Notes
    -----
    Every figure is optional; a figure whose input is missing is listed as skipped with the
    reason. PNGs and the HTML are written atomically (temporary file + ``os.replace``).
    """
    run_dir = Path(run_dir)
    if not run_dir.is_dir():
        raise UVPSInputError(f"run folder {run_dir} does not exist")
    figdir = run_dir / "figures"
    figdir.mkdir(exist_ok=True)
    page = _Page()
    run, warn = _run_summary(run_dir, page, warnings)
    report(progress, 0.05, "reading the run folder")
    inputs = _read_inputs(run_dir, run, table, images)

    report(progress, 0.15, "lights")
    _lights_figure(page, run_dir, figdir)
    px = inputs.pixel_size_um
    if px is None:
        page.skipped.append(("image figures", "no pixel size (no calibrated TIFF, run.json)"))
        px = float("nan")
    report(progress, 0.3, "normals and albedo")
    _normals_and_albedo_figures(page, inputs, figdir, px)
    protrusions = read_protrusions_csv(inputs.table_path) if inputs.table_path.is_file() else None
    report(progress, 0.45, "height map")
    _height_figures(page, inputs, protrusions, figdir, px, progress)

    report(progress, 0.7, "statistics")
    _area_statistics(page, run_dir, inputs, protrusions, figdir, px, regions=regions, stats=stats,
                     bins_um=bins_um)
    report(progress, 0.85, "comparison")
    _comparison_section(page, run_dir, figdir, comparison)

    text = _html(run_dir, run, protrusions, inputs.table_path, page, warn, title)
    out = run_dir / "report.html"
    atomic_write_text(out, text)
    report(progress, 1.0, "report written")
    log.info("report: %d figures, %d skipped", len(page.figures), len(page.skipped))
    return out


def _run_summary(run_dir: Path, page: _Page, warnings: Optional[list]):
    """``run.json`` (None when missing: listed as skipped) and the warnings, its own first."""
    warn = list(warnings or [])
    run = _read_json(run_dir / "run.json") if (run_dir / "run.json").is_file() else None
    if run is None:
        page.skipped.append(("run summary", "run.json missing"))
    elif isinstance(run.get("warnings"), list):
        warn = [str(w) for w in run["warnings"]] + warn
    return run, warn


@dataclass
class _RunInputs:
    """The images of a run folder (None when missing), their pixel size and shape."""

    normals: Optional[np.ndarray]
    albedo: Optional[np.ndarray]
    height: Optional[np.ndarray]
    protrusion_labels: Optional[np.ndarray]
    table_path: Path
    pixel_size_um: Optional[float]
    shape: Optional[tuple]


def _read_inputs(run_dir: Path, run, table, images=None) -> _RunInputs:
    """Read the run's images (:func:`uvps.runfolder.read_run`: its file names and layout) and the
    protrusion labels; the pixel size from the TIFFs, else ``run.json``, else ``lights.json``.

    A folder whose TIFFs carry no pixel size is still read: its images give the shape and the
    table's areas, and the image figures are skipped when no pixel size is found at all.
    """
    table_path = Path(table) if table is not None else run_dir / "protrusions.csv"
    if table is not None and not table_path.is_file():
        raise UVPSInputError(f"protrusion table {table_path} does not exist")
    plabels, px_l = _read_optional_tiff(_labels_path(table_path))
    if images is None:
        images = read_run(run_dir, need=(), require_pixel_size=False)
    px = images.pixel_size_um
    if px is None:      # no pixel size in the TIFFs: the labels', run.json's or lights.json's
        px = px_l or None
        if px is None and run is not None:
            px = run.get("pixel_size_um") or (run.get("params") or {}).get("pixel_size_um")
        if px is None and (run_dir / "lights.json").is_file():
            px = _read_json(run_dir / "lights.json").get("pixel_size_um")
    shape = images.shape if images.shape is not None else (plabels.shape[-2:] if plabels is not None else None)
    return _RunInputs(images.normals, images.albedo, images.height_um, plabels, table_path, px, shape)


def _labels_path(table_path: Path) -> Path:
    """The label TIFF beside a protrusion table: ``<stem>_labels.tif``."""
    return table_path.with_name(table_path.stem + "_labels.tif")


def _lights_figure(page: _Page, run_dir: Path, figdir: Path) -> None:
    """The lamp positions from ``lights.json``."""
    if (run_dir / "lights.json").is_file():
        _figure_step(page, "lights.png", "Lamp positions seen from above (azimuth, elevation) "
                     "and the height of each lamp.", plot_lights,
                     _read_json(run_dir / "lights.json"), figdir / "lights.png")
    else:
        page.skipped.append(("lights.png", "lights.json missing"))


def _normals_and_albedo_figures(page: _Page, inputs: _RunInputs, figdir: Path, px: float) -> None:
    """The normal map and the albedo, when read and calibrated."""
    images_ok = np.isfinite(px)
    if inputs.normals is not None and images_ok:
        _figure_step(page, "normals.png", "Normal map (RGB encoding).", plot_normals,
                     inputs.normals, figdir / "normals.png", pixel_size_um=px)
    elif inputs.normals is None:
        page.skipped.append(("normals.png", "normals.tif missing"))
    if inputs.albedo is not None and images_ok:
        _figure_step(page, "albedo.png", "Albedo (UV fluorescence colour).", plot_albedo,
                     inputs.albedo, figdir / "albedo.png", pixel_size_um=px)
    elif inputs.albedo is None:
        page.skipped.append(("albedo.png", "albedo.tif missing"))


def _height_figures(page: _Page, inputs: _RunInputs, table, figdir: Path, px: float,
                    progress: Progress) -> None:
    """The height map with the protrusions outlined, and the 3-D detail of the largest one."""
    height = inputs.height
    if height is None:
        page.skipped.append(("height.png, detail3d.png", "depth.tif missing"))
        return
    if not np.isfinite(px):
        return
    lab = None
    plabels = inputs.protrusion_labels
    if plabels is not None and plabels.shape == height.shape:
        lab = plabels.astype(np.int64)
    _figure_step(page, "height.png", "Height map (\u00b5m) with the detected protrusions "
                 "outlined in red.", plot_height, height, figdir / "height.png",
                 pixel_size_um=px, labels=lab)
    centre, width, what = _detail_target(height, table, px)
    report(progress, 0.55, "3-D detail")
    _figure_step(page, "detail3d.png", f"Shaded 3-D rendering of the height around {what} "
                 "(paper Fig. 2e).", plot_detail_3d, height, figdir / "detail3d.png",
                 pixel_size_um=px, centre_xy=centre, width_um=width)


def _detail_target(height: np.ndarray, table, px: float):
    """Centre (x_px, y_px), width (um) and description of what the 3-D detail shows: the largest
    protrusion, else the highest point."""
    if table is not None and len(table["width_um"]):
        big = int(np.nanargmax(np.nan_to_num(table["area_um2"], nan=-1.0)
                               if np.isfinite(table["area_um2"]).any() else table["width_um"]))
        centre, width = (table["x_px"][big], table["y_px"][big]), float(table["width_um"][big])
        return centre, width, f"the largest protrusion (id {table['id'][big]})"
    r, c = np.unravel_index(np.nanargmax(np.nan_to_num(height, nan=-np.inf)), height.shape)
    return (c, r), 20 * px, "the highest point (no protrusions)"


def _area_statistics(page: _Page, run_dir: Path, inputs: _RunInputs, table, figdir: Path,
                     px: float, *, regions, stats, bins_um) -> None:
    """The colour-area figure, the per-area histograms and the per-area table."""
    images_ok = np.isfinite(px)
    albedo = inputs.albedo
    if regions is None and inputs.shape is not None:
        if (run_dir / "regions_labels.tif").is_file():
            regions = load_regions(run_dir / "regions_labels.tif", shape=inputs.shape)
        else:
            regions = whole_image(inputs.shape)
    if regions is not None and albedo is not None and images_ok and len(regions.ids) > 1:
        _figure_step(page, "regions.png", "Colour areas (borders in yellow).", plot_regions,
                     albedo, regions, figdir / "regions.png", pixel_size_um=px)
    if stats is None and table is not None and regions is not None and images_ok:
        stats = region_statistics(table, regions, pixel_size_um=px, bins_um=bins_um)
    if stats is not None:
        colours = region_colours(regions, albedo) if regions is not None else None
        _figure_step(page, "histograms.png", "Protrusions per cm\u00b2 by width, per colour area "
                     "(paper Fig. 4a).", plot_histograms, stats, figdir / "histograms.png",
                     colours=colours)
        page.sections.append(_stats_html(stats))
    else:
        page.skipped.append(("histograms.png", "protrusions.csv missing" if table is None
                             else "no image size or pixel size for the colour areas"))


def _comparison_section(page: _Page, run_dir: Path, figdir: Path, comparison) -> None:
    """The two-method comparison (given, else ``comparison.csv``): map, bar chart and table."""
    name_a, name_b = "a", "b"
    rows = None
    if comparison is not None:
        rows, name_a, name_b = comparison.rows, comparison.name_a, comparison.name_b
    elif (run_dir / "comparison.csv").is_file():
        rows = read_comparison_csv(run_dir / "comparison.csv")
        if rows:
            name_a, name_b = rows[0].get("table_a") or "a", rows[0].get("table_b") or "b"
    if rows and (figdir / "comparison_map.png").is_file():
        page.figures.append(("comparison_map.png", "Protrusions of the second table circled in "
                             "red, those of the first it missed in yellow (paper Fig. 4b)."))
    if rows:
        _figure_step(page, "comparison.png", f"Density per area: {name_a} vs {name_b} "
                     "(paper Fig. 4c).", plot_comparison, rows, figdir / "comparison.png",
                     name_a=name_a, name_b=name_b)
        page.sections.append(_comparison_html(rows, name_a, name_b))
    else:
        page.skipped.append(("comparison", "no comparison.csv (run the compare command)"))


def _stats_html(stats) -> str:
    cols = stats_columns(stats)
    header = list(cols)
    rows = list(zip(*cols.values()))
    note = f"<p>{stats.outside} protrusions lie in no colour area.</p>" if stats.outside else ""
    return ("<h2>Protrusions per colour area</h2>" + table_html(header, rows) + note
            + '<p>Table: <a href="regions.csv">regions.csv</a></p>')


def _comparison_html(rows, name_a, name_b) -> str:
    header = [c.replace("_a", f" ({name_a})").replace("_b", f" ({name_b})") for c in COLUMNS]
    body = [[r[c] for c in COLUMNS] for r in rows]
    return (f"<h2>Comparison: {html.escape(name_a)} vs {html.escape(name_b)}</h2>"
            "<p>matched = pairs one-to-one within the match radius; missed = in "
            f"{html.escape(name_a)} only; extra = in {html.escape(name_b)} only.</p>"
            + table_html(header, body)
            + '<p>Table: <a href="comparison.csv">comparison.csv</a></p>')


def _summary_rows(run: dict) -> list:
    params = run.get("params") if isinstance(run.get("params"), dict) else None
    src = params if params is not None else {k: v for k, v in run.items() if k != "warnings"}
    return [(k, v) for k, v in src.items()]


def _link(path: Path, run_dir: Path) -> str:
    """A relative link when ``path`` is inside the run folder, else its absolute file URI."""
    try:
        target = path.resolve().relative_to(run_dir.resolve()).as_posix()
    except ValueError:
        target = path.resolve().as_uri()
    return f"<a href='{html.escape(target)}'>{html.escape(path.name)}</a>"


def _html(run_dir: Path, run, table, table_path: Path, page: _Page, warn: list, title) -> str:
    e = html.escape
    title = title or f"uvps report: {run_dir.name}"
    parts = [f"<!DOCTYPE html><html><head><meta charset='utf-8'><title>{e(title)}</title>"
             f"<style>{CSS}</style></head><body><h1>{e(title)}</h1>",
             f"<p>uvps {e(__version__)}, written "
             f"{datetime.now(timezone.utc).strftime('%Y-%m-%d %H:%M UTC')}.</p>"]
    parts.append("<h2>Run summary</h2>")
    if run is not None:
        parts.append(table_html(["parameter", "value"], _summary_rows(run)))
        if isinstance(run.get("params"), dict):
            others = {k: v for k, v in run.items() if k not in ("params", "warnings")}
            if others:
                parts.append("<details><summary>run.json</summary><pre>"
                             + e(json.dumps(others, indent=2, default=str)) + "</pre></details>")
    else:
        parts.append("<p>No run.json in this folder.</p>")
    if table is not None:
        n = len(table["width_um"])
        src, counts = np.unique(np.asarray(table["source"], dtype=str), return_counts=True)
        by_src = ", ".join(f"{s or 'unknown'}: {c}" for s, c in zip(src, counts))
        craters = int(np.sum(table["crater"]))
        w = np.asarray(table["width_um"], float)
        wtxt = (f"; widths {np.nanmin(w):.0f} to {np.nanmax(w):.0f} \u00b5m (median "
                f"{np.nanmedian(w):.0f})") if n else ""
        labels_path = _labels_path(table_path)
        labels_link = f", labels: {_link(labels_path, run_dir)}" if labels_path.is_file() else ""
        parts.append(f"<p><b>{n}</b> protrusions ({e(by_src) if n else 'none'}), {craters} with "
                     f"a crater{wtxt}. Table: {_link(table_path, run_dir)}{labels_link}.</p>")
    else:
        parts.append("<p>No protrusions.csv: detection has not run.</p>")
    if warn:
        parts.append("<h2>Warnings</h2><ul>" + "".join(f"<li class='warn'>{e(w)}</li>"
                                                       for w in warn) + "</ul>")
    parts.extend(page.sections)
    parts.append("<h2>Figures</h2>")
    for name, caption in page.figures:
        parts.append(f"<figure><img src='figures/{e(name)}' alt='{e(caption)}'>"
                     f"<figcaption>{e(caption)}</figcaption></figure>")
    if page.skipped:
        parts.append("<h3>Not drawn</h3><ul>" + "".join(
            f"<li>{e(n)}: {e(r)}</li>" for n, r in page.skipped) + "</ul>")
    parts.append("</body></html>\n")
    return "\n".join(parts)
