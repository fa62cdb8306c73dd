"""``report.html`` and figures of ``uvps elements``: the false-colour composite of three elements
with the protrusions outlined (the paper's Fig. 5b) and protrusion density against each element per
colour area, with the rank correlations in words."""
from __future__ import annotations

import html
import math
from pathlib import Path

import cv2
import numpy as np

from ..files.tables import atomic_write_text
from ..files.outputs import atomic_path

#: Longest side of a figure's image in pixels (larger runs are shown every n-th pixel).
MAX_DISPLAY_PX = 900


def _figure(figsize, **margins):
    # no pyplot: no global state, always the Agg canvas; fixed margins (the constrained layout
    # drew every figure twice: half of the command's time on a 1600 x 1200 run)
    from matplotlib.figure import Figure

    fig = Figure(figsize=figsize, dpi=100)
    fig.subplots_adjust(**{"left": 0.1, "right": 0.97, "bottom": 0.08, "top": 0.93, **margins})
    return fig


def _save(fig, path: Path) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_path(path, suffix=".png") as tmp:
        fig.savefig(tmp, format="png")


def _stretch(img: np.ndarray) -> np.ndarray:
    """0..1 between the 1st and 99th percentiles of the finite values."""
    v = img[np.isfinite(img)]
    if v.size == 0:
        return np.zeros_like(img)
    lo, hi = np.percentile(v, (1, 99))
    return np.clip((np.nan_to_num(img, nan=lo) - lo) / max(hi - lo, 1e-12), 0, 1)


def _outlines(run_dir: Path, shape, step):
    """The protrusions' label image (every ``step``-th pixel) when the run folder has one."""
    path = Path(run_dir) / "protrusions_labels.tif"
    if not path.is_file():
        return None
    import tifffile

    lab = tifffile.imread(path)
    return lab[::step, ::step] if lab.shape[:2] == tuple(shape[:2]) else None


def composite_figure(path: Path, resampled, names, composite, run_dir, table, *, px: float) -> None:
    """Three elements as red, green and blue over the run's field, protrusions outlined in white
    (or marked by circles of their width when the run has no label image)."""
    M, N = resampled.shape[1:]
    step = max(1, int(math.ceil(max(M, N) / MAX_DISPLAY_PX)))
    rgb = np.dstack([_stretch(resampled[names.index(n)][::step, ::step]) for n in composite])
    ext = (-(N - 1) / 2 * px / 1000, (N - 1) / 2 * px / 1000, -(M - 1) / 2 * px / 1000, (M - 1) / 2 * px / 1000)
    fig = _figure((8, 8 * M / N + 0.8))
    ax = fig.add_subplot(1, 1, 1)
    lab = _outlines(run_dir, (M, N), step)
    if lab is not None and lab.max() > 0:
        # each outline as white pixels: its footprint less its erosion (a contour plot of the
        # labels took 2 s of a 1600 x 1200 run's 6)
        inside = (lab > 0).astype(np.uint8)
        rgb[(inside > 0) & (cv2.erode(inside, np.ones((3, 3), np.uint8)) == 0)] = 1.0
    else:
        # no label image: a circle of each protrusion's width, drawn into the picture
        rgb = np.ascontiguousarray(rgb, dtype=np.float32)
        for x, y, w in zip(table["x_px"], table["y_px"], table["width_um"]):
            r = max(1, int(round(float(w) / px / 2 / step)))
            cv2.circle(rgb, (int(round(x / step)), int(round(y / step))), r, (1.0, 1.0, 1.0), 1)
    ax.imshow(rgb, extent=ext)
    ax.set_xlabel("x (mm)")
    ax.set_ylabel("y (mm)")
    ax.set_title(f"red {composite[0]}, green {composite[1]}, blue {composite[2]}; protrusions outlined")
    _save(fig, path)


def density_figure(path: Path, areas, density, corr, names) -> None:
    """Protrusions per cm^2 against each element's mean, one point per colour area."""
    n = len(names)
    cols = min(n, 3)
    rows = int(math.ceil(n / cols))
    fig = _figure((4.2 * cols, 3.6 * rows), wspace=0.35, hspace=0.45, bottom=0.12 / rows)
    use = areas.n_map_pixels >= 10
    for e, name in enumerate(names):
        ax = fig.add_subplot(rows, cols, e + 1)
        ax.errorbar(areas.mean[use, e], density[use], xerr=areas.sd[use, e], fmt="o", ms=4, capsize=2)
        for a in np.flatnonzero(use):
            ax.annotate(areas.names[a], (areas.mean[a, e], density[a]), fontsize=7, xytext=(3, 3),
                        textcoords="offset points")
        c = corr[e]
        rho = "n/a" if not math.isfinite(c.rho) else f"{c.rho:.2f}"
        ax.set_title(f"{name}: Spearman rho {rho} ({c.n_areas} areas)", fontsize=9)
        ax.set_xlabel(f"{name} (counts, area mean)")
        ax.set_ylabel("protrusions per cm$^2$")
    _save(fig, path)


def _table(header, rows) -> str:
    head = "".join(f"<th>{html.escape(h)}</th>" for h in header)
    body = "".join("<tr>" + "".join(f"<td>{html.escape(str(v))}</td>" for v in r) + "</tr>" for r in rows)
    return f"<table><thead><tr>{head}</tr></thead><tbody>{body}</tbody></table>"


def _g(v, d=3) -> str:
    return "" if v is None or not math.isfinite(float(v)) else f"{float(v):.{d}g}"


def write_elements_report(folder: Path, albedo, resampled, names, composite, run_dir, table, areas, density,
                          corr, reg, *, px: float, warnings=()) -> Path:
    """Write ``figures/elements_composite.png``, ``figures/elements_density.png`` and ``report.html``."""
    folder = Path(folder)
    composite_figure(folder / "figures" / "elements_composite.png", resampled, names, composite, run_dir, table,
                     px=px)
    density_figure(folder / "figures" / "elements_density.png", areas, density, corr, names)
    lines = []
    for c in corr:
        if not math.isfinite(c.rho):
            lines.append(f"<li>{html.escape(c.element)}: too few colour areas to rank ({c.n_areas}).</li>")
            continue
        sense = "more" if c.rho > 0 else "fewer"
        sure = ("the 95 % interval excludes no correlation" if c.ci_low > 0 or c.ci_high < 0
                else "the 95 % interval includes no correlation")
        lines.append(f"<li><b>{html.escape(c.element)}</b>: areas richer in it have {sense} protrusions "
                     f"(Spearman rho {c.rho:.2f}, 95 % interval {c.ci_low:.2f} to {c.ci_high:.2f}, "
                     f"{c.n_areas} areas; {sure}).</li>")
    warn = "".join(f"<li>{html.escape(w)}</li>" for w in warnings)
    area_rows = [[areas.names[a], f"{areas.n_map_pixels[a]:.0f}", _g(density[a])]
                 + [_g(areas.mean[a, e]) for e in range(len(names))] for a in range(len(areas.names))]
    page = f"""<!DOCTYPE html>
<html lang="en"><head><meta charset="utf-8"><title>Element maps against protrusions</title>
<style>body{{font-family:sans-serif;max-width:60em;margin:2em auto;padding:0 1em;line-height:1.4}}
table{{border-collapse:collapse;font-size:0.9em}}td,th{{border:1px solid #bbb;padding:2px 6px;text-align:right}}
th{{background:#eee}}td:first-child{{text-align:left}}img{{max-width:100%}}
@media print{{body{{max-width:none;margin:0}}img{{page-break-inside:avoid}}}}</style></head><body>
<h1>Element maps against protrusions</h1>
<p>Run: {html.escape(str(run_dir))}. {len(names)} element maps ({html.escape(', '.join(names))}) registered
{html.escape(reg.method)}: residual {reg.residual_map_px:.2f} map pixel ({html.escape(reg.residual_of)}),
rotation {reg.rotation_deg:.1f} deg, {reg.scale:.2f} run pixels per map pixel,
{100 * reg.overlap:.0f} % of the field covered.</p>
<h2>Protrusion density against composition</h2><ul>{''.join(lines)}</ul>
{f'<h3>Warnings</h3><ul>{warn}</ul>' if warn else ''}
<img src="figures/elements_density.png" alt="protrusion density against element per area">
<h2>Composite</h2>
<img src="figures/elements_composite.png" alt="false-colour composite of three elements with protrusions">
<h2>Per colour area</h2>
<p>Element means over each area's interior (at least one spot width from its border), in the maps' counts.</p>
{_table(['area', 'map pixels', 'protrusions per cm²'] + [f'{n} mean' for n in names], area_rows)}
</body></html>
"""
    path = folder / "report.html"
    atomic_write_text(path, page)
    return path
