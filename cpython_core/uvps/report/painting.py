"""The painting report: ``OUT/painting/report.html`` and its figures, for a mosaic batch.

Figures: the painting at overview with its protrusions (circles of their width) and colour areas,
the protrusions' density per cm^2 over the painting, the tile map (each tile at its refined corner,
each registered pair a line coloured by its residual, pairs not used dashed) and the width
distribution per colour area; tables: per area (count, area, density, median width, counts by
width) and per pair of tiles (shift, confidence, residual). Made from what the stitching already
holds (the overview albedo, at most 4 Mpx), never from the full-resolution maps.
"""
from __future__ import annotations

import html
from pathlib import Path

import numpy as np

from ..files.tables import atomic_write_text
from .page import FIGURE_DPI, as_yxc, display_albedo, figure, inner_boundaries, save_figure, table_html
from .text import plural

#: Width bins of the per-area table (um).
WIDTH_EDGES_UM = (0, 60, 100, 200, 400, np.inf)
#: The overview's and the density's figures' width in inches (their PNGs ``FIGURE_WIDTH_IN * FIGURE_DPI`` px).
FIGURE_WIDTH_IN = 9


def _extent(shape, step, origin, px_um):
    """imshow extent in mm of the layout's frame (x right, y down as the tables' x_px, y_px)."""
    m, n = shape
    x0, y0 = origin[0] * px_um / 1000, origin[1] * px_um / 1000
    w, h = n * step * px_um / 1000, m * step * px_um / 1000
    return (x0, x0 + w, y0 + h, y0)


def _at_most(img: np.ndarray, width: int) -> np.ndarray:
    """``img`` (M, N[, 3]) area-averaged down to at most ``width`` columns (``cv2.INTER_AREA``), or as it is;
    a boolean image (an outline) comes back set where any pixel it averages is, so the outline stays drawn."""
    import cv2

    m, n = img.shape[:2]
    if n <= width:
        return img
    small = cv2.resize(np.ascontiguousarray(img, dtype=np.float32), (width, max(1, int(round(m * width / n)))),
                       interpolation=cv2.INTER_AREA)
    # every weight of the area average is positive: above 0 exactly where any pixel averaged is set (a uint8
    # average rounds a pixel under half covered back to 0: a 1 px outline shrunk 3x vanished)
    return small > 0 if img.dtype == bool else small


def _overview(albedo, labels, kept, extent, px_um, path):
    m, n = labels.shape
    # an image figure: a fixed margin (layout=None), not the constrained layout's second draw; the albedo
    # and the areas' outlines at the figure's own width in pixels (its PNG's), which matplotlib's nearest
    # resampling of the whole overview drew no sharper (0.75 s of the figures' 5 s on a 1002 x 1766 overview)
    width = int(FIGURE_WIDTH_IN * FIGURE_DPI)
    fig = figure((FIGURE_WIDTH_IN, FIGURE_WIDTH_IN * m / max(n, 1) + 0.8), layout=None)
    ax = fig.add_subplot()
    ax.imshow(display_albedo(_at_most(as_yxc(albedo), width)), extent=extent, interpolation="nearest")
    edges = _at_most(inner_boundaries(labels), width)
    ax.imshow(np.ma.masked_where(~edges, edges), extent=extent, cmap="autumn", alpha=0.8, interpolation="nearest")
    if kept:
        x = np.array([r["X"] for r in kept]) * px_um / 1000
        y = np.array([r["Y"] for r in kept]) * px_um / 1000
        w = np.nan_to_num(np.array([float(r.get("width_um", 0) or 0) for r in kept])) / 1000
        from matplotlib.collections import EllipseCollection
        ax.add_collection(EllipseCollection(np.maximum(w, 0.05), np.maximum(w, 0.05), 0, units="xy",
                                            offsets=np.column_stack([x, y]), offset_transform=ax.transData,
                                            facecolors="none", edgecolors="cyan", linewidths=0.8))
    ax.set_xlabel("x (mm, layout frame)")
    ax.set_ylabel("y (mm, down)")
    ax.set_title(f"{len(kept)} protrusions; colour areas outlined")
    return save_figure(fig, path)


def _density(kept, covered, extent, px_um, step, path):
    """Protrusions per cm^2 in square cells over the painting (cells mostly outside the tiles blank)."""
    m, n = covered.shape
    size_mm = max(extent[1] - extent[0], extent[2] - extent[3])
    cell_mm = max(1.0, size_mm / 40)
    cell_px = max(1, int(round(cell_mm * 1000 / (px_um * step))))
    gm, gn = -(-m // cell_px), -(-n // cell_px)
    counts = np.zeros((gm, gn))
    ox, oy = extent[0] * 1000 / px_um, extent[3] * 1000 / px_um
    for r in kept:
        i = int((r["Y"] - oy) / step // cell_px)
        j = int((r["X"] - ox) / step // cell_px)
        if 0 <= i < gm and 0 <= j < gn:
            counts[i, j] += 1
    cover = np.zeros((gm, gn))
    pad = np.zeros((gm * cell_px, gn * cell_px), bool)
    pad[:m, :n] = covered
    cover = pad.reshape(gm, cell_px, gn, cell_px).sum(axis=(1, 3)) * (px_um * step) ** 2 / 1e8
    with np.errstate(invalid="ignore", divide="ignore"):
        dens = np.where(cover > 0.5 * (cell_px * px_um * step) ** 2 / 1e8, counts / cover, np.nan)
    fig = figure((FIGURE_WIDTH_IN, FIGURE_WIDTH_IN * m / max(n, 1) + 0.8), layout=None)
    ax = fig.add_subplot()
    cell_mm = cell_px * step * px_um / 1000          # the grid overhangs the painting by < 1 cell
    grid_extent = (extent[0], extent[0] + gn * cell_mm, extent[3] + gm * cell_mm, extent[3])
    im = ax.imshow(dens, extent=grid_extent, cmap="magma", interpolation="nearest")
    fig.colorbar(im, ax=ax, label="protrusions per cm$^2$", shrink=0.8)
    ax.set_title(f"density in cells of {cell_mm:.2g} mm (cells less than half covered left blank)")
    ax.set_xlabel("x (mm)")
    ax.set_ylabel("y (mm, down)")
    return save_figure(fig, path)


def _tile_map(corners, shapes, pairs, px_um, path):
    from matplotlib.patches import Rectangle

    fig = figure((9, 6))
    ax = fig.add_subplot()
    s = px_um / 1000
    centre = {}
    for k, (x, y) in corners.items():
        M, N = shapes[k]
        ax.add_patch(Rectangle((x * s, y * s), N * s, M * s, fill=False, edgecolor="0.4"))
        centre[k] = ((x + N / 2) * s, (y + M / 2) * s)
        ax.text(*centre[k], k, ha="center", va="center", fontsize=9)
    import matplotlib

    cmap = matplotlib.colormaps["viridis"]
    worst = max([p.residual_px or 0 for p in pairs if p.used] + [0.5])
    for p in pairs:
        (xa, ya), (xb, yb) = centre[p.a], centre[p.b]
        if p.used:
            c = cmap(min(1.0, (p.residual_px or 0) / worst))
            ax.plot([xa, xb], [ya, yb], color=c, lw=2)
            ax.text((xa + xb) / 2, (ya + yb) / 2, f"{p.residual_px:.2f}", fontsize=7, color="k")
        else:
            ax.plot([xa, xb], [ya, yb], color="red", lw=1, ls="--")
    ax.autoscale()
    ax.set_aspect("equal")
    ax.invert_yaxis()
    ax.set_title(f"tiles at their refined corners; pairs by residual (px, largest {worst:.2f}); dashed: not used")
    ax.set_xlabel("x (mm)")
    ax.set_ylabel("y (mm, down)")
    return save_figure(fig, path)


def _widths(kept, areas, path):
    fig = figure((8, 4))
    ax = fig.add_subplot()
    bins = np.linspace(0, max([float(r.get("width_um") or 0) for r in kept] + [100]) * 1.05, 30)
    for name in areas:
        w = [float(r.get("width_um") or 0) for r in kept if r.get("area") == name]
        if w:
            ax.hist(w, bins=bins, histtype="step", label=f"{name} ({len(w)})")
    ax.set_xlabel("width (\u00b5m)")
    ax.set_ylabel("protrusions")
    ax.legend(fontsize=8)
    return save_figure(fig, path)


def write_painting_figures(folder, *, albedo, labels, covered, kept, areas, registration, shapes, origin, step,
                           pixel_size_um) -> Path:
    """Write the report's figures, ``folder/figures/*.png`` (matplotlib Figure objects, no pyplot: they
    may be drawn in a thread of their own, while the painting's maps are computed); returns the folder."""
    figs = Path(folder) / "figures"
    figs.mkdir(exist_ok=True)
    extent = _extent(labels.shape, step, origin, pixel_size_um)
    _overview(albedo, labels, kept, extent, pixel_size_um, figs / "painting_overview.png")
    _density(kept, covered, extent, pixel_size_um, step, figs / "painting_density.png")
    _tile_map(registration.corners, shapes, registration.pairs, pixel_size_um, figs / "painting_tiles.png")
    _widths(kept, areas, figs / "painting_widths.png")
    return figs


def write_painting_report(folder, *, albedo, labels, covered, kept, areas, registration, shapes, origin, step,
                          pixel_size_um, warnings=(), view=None, figures: bool = True) -> Path:
    """Write ``folder/report.html`` and ``folder/figures/*.png`` for a stitched painting; ``view``
    (:func:`uvps.report.deepzoom.write_view`'s result) adds the zoomable view of ``folder/view/``;
    ``figures=False``: the figures are there already (:func:`write_painting_figures`)."""
    folder = Path(folder)
    if figures:
        write_painting_figures(folder, albedo=albedo, labels=labels, covered=covered, kept=kept, areas=areas,
                               registration=registration, shapes=shapes, origin=origin, step=step,
                               pixel_size_um=pixel_size_um)
    rows = []
    for name, a in areas.items():
        w = np.array([float(r.get("width_um") or np.nan) for r in kept if r.get("area") == name])
        hist = np.histogram(w[np.isfinite(w)], bins=WIDTH_EDGES_UM)[0] if w.size else [0] * (len(WIDTH_EDGES_UM) - 1)
        rows.append([name, a["tiles"], a["area_cm2"], a["count"], a["density_per_cm2"],
                     float(np.nanmedian(w)) if np.isfinite(w).any() else float("nan"), *map(int, hist)])
    bins = [f"{lo:g}-{hi:g} \u00b5m" if np.isfinite(hi) else f"\u2265 {lo:g} \u00b5m"
            for lo, hi in zip(WIDTH_EDGES_UM[:-1], WIDTH_EDGES_UM[1:])]
    area_table = table_html(["area", "tiles", "area (cm\u00b2)", "count", "per cm\u00b2", "median width (\u00b5m)", *bins], rows)
    pair_table = table_html(["pair", "dx (px)", "dy (px)", "confidence", "residual (px)", "used", "why not"],
                            [[p.name, p.dx, p.dy, p.confidence, p.residual_px if p.residual_px is not None
                              else float("nan"), "yes" if p.used else "no", p.why] for p in registration.pairs])
    warn = "".join(f"<li>{html.escape(w)}</li>" for w in warnings) or "<li>none</li>"
    # every kept protrusion, as the overview's title, painting_protrusions.csv and painting_regions.csv's
    # "all areas" row count them; those the colour areas' labels leave out (a pixel in no area) said so
    total = len(kept)
    outside = total - sum(a["count"] for a in areas.values())
    outside_note = (f"<p>{plural(outside, 'protrusion')} lie{'s' if outside == 1 else ''} in no "
                    "colour area: not in this table's counts and densities ("
                    f"{'its' if outside == 1 else 'their'} <code>area</code> is empty in "
                    "painting_protrusions.csv).</p>" if outside else "")
    viewer = ""
    if view is not None:
        from .deepzoom import viewer_html
        viewer = viewer_html(view)
    page = f"""<!DOCTYPE html>
<html lang="en"><head><meta charset="utf-8"><title>uvps painting report</title>
<style>body{{font-family:sans-serif;max-width:1100px;margin:2em auto}}img{{max-width:100%}}
table{{border-collapse:collapse}}td,th{{border:1px solid #ccc;padding:2px 6px;text-align:right}}</style></head>
<body><h1>The painting: {plural(len(registration.corners), 'tile')}, {plural(total, 'protrusion')}</h1>
<p>Pixel size {pixel_size_um:g} \u00b5m; registered tiles (largest pair residual {registration.max_residual_px:.2f} px);
each protrusion of an overlap counted once. Maps: albedo.ome.zarr, normals.ome.zarr, height.ome.zarr, labels.ome.zarr.</p>
<h2>Warnings</h2><ul>{warn}</ul>
<h2>The painting and its protrusions</h2><img src="figures/painting_overview.png" alt="overview">
{viewer}
<h2>Density</h2><img src="figures/painting_density.png" alt="density">
<h2>Per colour area</h2>{area_table}{outside_note}<img src="figures/painting_widths.png" alt="widths">
<h2>Tiles and their registration</h2><img src="figures/painting_tiles.png" alt="tiles">{pair_table}
</body></html>
"""
    atomic_write_text(folder / "report.html", page)
    return folder / "report.html"
