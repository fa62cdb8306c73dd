"""The run report: ``report.html`` and PNG figures in ``figures/``.

Figures follow the paper (Salvant et al.): lamp positions (Fig. 1), normal map and albedo
(Fig. 2), the height map with the protrusions outlined and a shaded 3-D detail of the largest one
(Fig. 2e), per-area densities by width bin (Fig. 4a) and the two-method comparison (Fig. 4c).
Every figure is optional: a missing input skips its figure and the report says why. The HTML is
self-contained apart from the PNGs, linked relatively, so the run folder can be moved or zipped.
"""
from __future__ import annotations

import dataclasses
import html
import json
import logging
import os
import re
import shutil
import subprocess
import tempfile
from dataclasses import dataclass, field
from datetime import datetime, timezone
from pathlib import Path
from typing import Optional

import numpy as np
from scipy import ndimage as ndi
from skimage.measure import block_reduce

from .. import __version__
from ..core.compare import compare_detections
from ..files.comparison import read_comparison_csv
from ..errors import UVPSInputError
from ..files.io import read_tiff
from ..files.tables import atomic_write_text, read_protrusions_csv
from ..files.outputs import Progress, atomic_path, report
from ..core.regions import bin_names, region_statistics, whole_image
from ..core.threads import concurrently
from ..files.tables import load_regions
from ..files.runfolder import earlier_work, read_run
from .text import (Facts, Raw, area_table_html, cm2, density, facts_of, height,
                          largest_table_html, methods_html, protrusion_definition,
                          provenance_html, sig, summary_html, width as width_fmt,
                          width_table_html)
from .text import table_html as text_table

log = logging.getLogger(__name__)

# matplotlib is imported inside the plotting functions, not here, so that importing this module
# stays cheap (the commands import it at start-up of the CLI and the Fiji bridge): matplotlib costs
# about 0.3 s that only a run drawing figures should pay.

_MAX_DISPLAY_PX = 1600  # longest side of an image drawn into a figure
_MAX_LAMP_LABELS = 24  # more lamps are coloured by number, not labelled one by one


# ---------------------------------------------------------------------------------------------
# helpers


#: Dots per inch of every figure (:func:`figure`): a figure ``w`` inches wide is a PNG of ``w * FIGURE_DPI`` px.
FIGURE_DPI = 100


def figure(figsize, layout="constrained"):
    # Figure objects without pyplot: no global state, always the Agg canvas. Image figures pass
    # layout=None (a fixed margin): the constrained layout costs a second draw.
    from matplotlib.figure import Figure

    fig = Figure(figsize=figsize, dpi=FIGURE_DPI, layout=layout)
    if layout is None:
        fig.subplots_adjust(left=0.1, right=0.95, bottom=0.1, top=0.92)
    return fig


def save_figure(fig, path) -> Path:
    """Save a matplotlib figure as PNG atomically (``uvps.files.outputs.atomic_path``)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_path(path, suffix=".png") as tmp:
        fig.savefig(tmp, format="png")
    return path


def _check_shown(name: str, shown: np.ndarray, shape, step: int) -> None:
    """A ``display`` or ``outline`` given to a figure must be of the image drawn at every ``step``-th pixel."""
    want = tuple(-(-int(v) // step) for v in shape[:2])
    if tuple(np.shape(shown)[:2]) != want:
        raise UVPSInputError(f"{name}: expected the image at every {step}-th pixel, {want[0]} x {want[1]}; "
                             f"got {' x '.join(map(str, np.shape(shown)[:2]))}")


def display_step(shape) -> int:
    return max(1, int(np.ceil(max(shape[:2]) / _MAX_DISPLAY_PX)))


def as_yxc(img: np.ndarray) -> np.ndarray:
    """(3, M, N) -> (M, N, 3); (M, N) and (M, N, 3) unchanged."""
    img = np.asarray(img)
    if img.ndim == 3 and img.shape[0] == 3 and img.shape[-1] != 3:
        return np.moveaxis(img, 0, -1)
    return img


def display_albedo(albedo: np.ndarray, step: int = 1) -> np.ndarray:
    """Every ``step``-th pixel of the albedo as (M', N[, 3]) in 0..1 (99.5th percentile = 1)."""
    a = as_yxc(albedo)[::step, ::step].astype(np.float64)
    finite = a[np.isfinite(a)]
    scale = float(np.percentile(finite, 99.5)) if finite.size else 1.0
    return np.clip(np.nan_to_num(a / (scale or 1.0)), 0.0, 1.0)


def extent_mm(shape, px_um):
    """imshow extent in mm from the image centre (x right, y up: architecture frame)."""
    m, n = shape[:2]
    px = px_um / 1000.0
    return (-n / 2 * px, n / 2 * px, -m / 2 * px, m / 2 * px)


def _morphology_labels(labels: np.ndarray):
    """Labels in a type OpenCV's dilation and erosion take, held exactly: (array, largest label).

    uint16 below 65535 labels, float32 below 2^24, else float64.
    """
    lab = np.asarray(labels)
    if lab.ndim != 2:
        raise UVPSInputError(f"labels must be a 2-D image; got shape {lab.shape}")
    if lab.size and lab.dtype != bool and int(lab.min()) < 0:
        raise UVPSInputError(f"labels must be non-negative integers; the smallest is {int(lab.min())}")
    top = int(lab.max()) if lab.size else 0
    kind = np.uint16 if top < 0xFFFF else np.float32 if top < 2 ** 24 - 1 else np.float64
    return lab.astype(kind), top


def _thick_boundaries(f: np.ndarray) -> np.ndarray:
    """Where a pixel's 4-neighbourhood holds two labels: scikit-image's "thick" boundaries (a 3 x 3
    cross, ``ndi.generate_binary_structure(2, 1)``, dilated against eroded)."""
    import cv2

    cross = cv2.getStructuringElement(cv2.MORPH_CROSS, (3, 3))
    return cv2.dilate(f, cross) != cv2.erode(f, cross)


def outer_boundaries(labels: np.ndarray) -> np.ndarray:
    """``skimage.segmentation.find_boundaries(labels, mode="outer")``, pixel for pixel, by OpenCV.

    The same 3 x 3 dilations and erosions (a cross, then a square) as scikit-image's, which runs
    them through ``scipy.ndimage``'s generic grey morphology: 0.34 s at 3000 x 4000 against
    0.07 s here (``tests/test_report.py`` checks the two agree, the image's edges included: OpenCV
    leaves pixels outside the image out of a minimum or maximum, as ndimage's reflection does).
    Labels are a 2-D image of non-negative integers of any width (scikit-image's own answer for
    int64 labels marks objects' edges too: the background it lifts to 2^63 - 1 is not held exactly).
    """
    import cv2

    f, top = _morphology_labels(labels)
    if not f.size:
        return np.zeros(f.shape, bool)
    square = np.ones((3, 3), np.uint8)
    edge = _thick_boundaries(f)
    background = f == 0
    # an object's own pixels stay only where an 8-neighbour is another object (touching
    # protrusions share an outline): scikit-image's test, the background lifted above every label
    lifted = f.copy()
    lifted[background] = top + 1
    keep = cv2.dilate(f, square) != cv2.erode(lifted, square)
    keep |= background
    edge &= keep
    return edge


def inner_boundaries(labels: np.ndarray) -> np.ndarray:
    """``skimage.segmentation.find_boundaries(labels, mode="inner")``, pixel for pixel, by OpenCV:
    the labelled pixels (not 0) whose 4-neighbourhood holds another label. As
    :func:`outer_boundaries`, ~10x faster than scikit-image's generic grey morphology
    (``tests/test_report.py`` checks the two agree). Labels: a 2-D image of non-negative integers
    (any integer type, whole-valued floats) or a bool mask."""
    f, _ = _morphology_labels(labels)
    if not f.size:
        return np.zeros(f.shape, bool)
    edge = _thick_boundaries(f)
    edge &= f != 0
    return edge


def _outline(labels: np.ndarray, step: int) -> np.ndarray:
    """Protrusion outlines at display resolution (max-pooled so thin lines survive)."""
    b = outer_boundaries(labels)
    return block_reduce(b, (step, step), np.max) if step > 1 else b


# ---------------------------------------------------------------------------------------------
# figures (each takes arrays/dicts and a path, and returns the path)


def plot_lights(lights: dict, path) -> Path:
    """Lamp positions: a polar top view (azimuth, elevation) and the height of each lamp.

    The polar view puts azimuth counter-clockwise from +x (image right), as in ``lights.json``,
    and 90 - elevation as the radius (the centre is straight above the canvas); lamps are numbered
    in image order when there are at most :data:`_MAX_LAMP_LABELS`, else coloured by their number.
    The bar chart gives each lamp's height above the canvas (z of ``position_mm``) for near
    lights, else its elevation.
    """
    from matplotlib.ticker import MaxNLocator

    entries = lights.get("lights") or []
    if not entries:
        raise UVPSInputError("lights.json has no 'lights' entries")
    az = np.array([float(e.get("azimuth_deg", np.nan)) for e in entries])
    el = np.array([float(e.get("elevation_deg", np.nan)) for e in entries])
    pos = [e.get("position_mm") for e in entries]
    k_all = len(entries)
    idx = np.arange(1, k_all + 1)
    fig = figure((9, 4.2))
    ax = fig.add_subplot(1, 2, 1, projection="polar")
    labelled = k_all <= _MAX_LAMP_LABELS
    sc = ax.scatter(np.radians(az), 90.0 - el, c=el if labelled else idx,
                    cmap="viridis", vmin=0 if labelled else 1, vmax=90 if labelled else k_all,
                    s=60 if labelled else 25, edgecolors="k", linewidths=0.5)
    if labelled:
        for k, (a, r) in enumerate(zip(az, 90.0 - el), start=1):
            ax.annotate(str(k), (np.radians(a), r), textcoords="offset points", xytext=(6, 6),
                        fontsize=8)
    else:
        fig.colorbar(sc, ax=ax, shrink=0.7, pad=0.12, label="lamp number")
    ax.set_rlim(0, 90)
    ax.set_rticks([30, 60, 90], labels=["60\u00b0", "30\u00b0", "0\u00b0"])
    ax.set_title(f"{k_all} lamps seen from above ({lights.get('mode', '?')} lights)\n"
                 "azimuth from +x, radius = 90\u00b0 - elevation", fontsize=9)
    ax2 = fig.add_subplot(1, 2, 2)
    if all(p is not None for p in pos):
        z = np.array([float(p[2]) for p in pos])
        ax2.bar(idx, z, color="tab:blue")
        ax2.set_ylabel("lamp height above canvas (mm)")
        ax2.set_title(f"height of each lamp: {sig(np.nanmin(z), 2)}\u2013{sig(np.nanmax(z), 2)} mm",
                      fontsize=9)
    else:
        ax2.bar(idx, el, color="tab:blue")
        ax2.set_ylabel("elevation (\u00b0)")
        ax2.set_title(f"elevation of each lamp (far lights): "
                      f"{sig(np.nanmin(el), 2)}\u2013{sig(np.nanmax(el), 2)}\u00b0", fontsize=9)
    ax2.set_xlabel("lamp")
    ax2.xaxis.set_major_locator(MaxNLocator(nbins=min(k_all, 12), integer=True))
    ax2.set_xlim(0.4, k_all + 0.6)
    return save_figure(fig, path)


def plot_normals(normals: np.ndarray, path, *, pixel_size_um: float) -> Path:
    """Normal map in the usual RGB encoding ``(n + 1) / 2`` (x red, y green, z blue)."""
    n = as_yxc(normals)
    step = display_step(n.shape)
    rgb = np.clip((np.nan_to_num(n[::step, ::step]) + 1.0) / 2.0, 0, 1)
    fig = figure((7, 7 * n.shape[0] / n.shape[1] + 0.6), layout=None)
    ax = fig.add_subplot()
    ax.imshow(rgb, extent=extent_mm(n.shape, pixel_size_um), interpolation="nearest")
    ax.set_xlabel("x (mm)")
    ax.set_ylabel("y (mm)")
    ax.set_title("normal map, RGB = (n + 1) / 2")
    return save_figure(fig, path)


def _draw_outlines(ax, labels, step, shape, ext, colour=(1.0, 0.0, 0.0, 1.0), outline=None) -> int:
    """Protrusion outlines over an image drawn at every ``step``-th pixel; returns their number.
    ``outline``: ``_outline(labels, step)`` when the caller has it."""
    if labels is None or not labels.any():
        return 0
    if outline is not None:
        _check_shown("outline", outline, labels.shape, step)
    edge = (_outline(labels, step) if outline is None else outline)[: shape[0], : shape[1]]
    overlay = np.zeros(edge.shape + (4,))
    overlay[edge] = colour
    ax.imshow(overlay, extent=ext, interpolation="nearest")
    return int(np.unique(labels[labels != 0]).size)


def plot_albedo(albedo: np.ndarray, path, *, pixel_size_um: float,
                labels: Optional[np.ndarray] = None, display: Optional[np.ndarray] = None,
                outline: Optional[np.ndarray] = None) -> Path:
    """Albedo (fluorescence colour), scaled by its 99.5th percentile, with the protrusions of
    ``labels`` (an (M, N) label image, 0 = none) outlined in red.

    ``display`` and ``outline``: ``display_albedo(albedo, display_step(shape))`` and the labels'
    outlines at that step, when the caller has them (the report draws them in several figures).
    """
    shape = as_yxc(albedo).shape
    step = display_step(shape)
    if display is not None:
        _check_shown("display", display, shape, step)
    a = display_albedo(albedo, step) if display is None else display
    fig = figure((7, 7 * shape[0] / shape[1] + 0.6), layout=None)
    ax = fig.add_subplot()
    ext = extent_mm(shape, pixel_size_um)
    ax.imshow(a, cmap="gray", vmin=0, vmax=1, extent=ext, interpolation="nearest")
    n = _draw_outlines(ax, labels, step, a.shape, ext, outline=outline) if labels is not None else 0
    ax.set_xlabel("x (mm)")
    ax.set_ylabel("y (mm)")
    ax.set_title("albedo (UV fluorescence)" + (f" with {n} protrusions outlined" if n else ""))
    return save_figure(fig, path)


@dataclass
class HeightScale:
    """The colour scale of a height map: where it clips and what the heights span."""

    lo: float
    hi: float
    min: float
    max: float
    unit: str        # "\u00b5m" or "" (relative heights)

    @property
    def clips(self) -> bool:
        return self.min < self.lo or self.max > self.hi

    def words(self) -> str:
        """One sentence for a caption: the colour range, and the real range when it clips."""
        u = f" {self.unit}" if self.unit else ""
        fmt = height if self.unit else (lambda v: sig(v, 2))
        s = f"Colours span {fmt(self.lo)} to {fmt(self.hi)}{u} (1st to 99th percentile)"
        if self.clips:
            s += (f"; the heights reach {fmt(self.min)} to {fmt(self.max)}{u}, beyond the bar's "
                  "ends (its arrows) in its end colours")
        return s + "."


def height_scale(height_um: np.ndarray, *, relative: bool = False) -> HeightScale:
    """The 1st-99th percentile colour range of a height map and its full range."""
    finite = np.asarray(height_um)[np.isfinite(height_um)]
    if not finite.size:
        return HeightScale(0.0, 1.0, 0.0, 1.0, "" if relative else "\u00b5m")
    lo, hi = np.percentile(finite, [1, 99])
    if hi <= lo:
        hi = lo + 1e-6
    return HeightScale(float(lo), float(hi), float(finite.min()), float(finite.max()),
                       "" if relative else "\u00b5m")


def plot_height(height_um: np.ndarray, path, *, pixel_size_um: float,
                labels: Optional[np.ndarray] = None, relative: bool = False,
                outline: Optional[np.ndarray] = None) -> Path:
    """Height map with the protrusion outlines in red (:func:`outer_boundaries`).

    The colours span the 1st-99th percentile of the heights (:func:`height_scale`); the colour
    bar says so and, when heights lie beyond it, gives their real range and ends in arrows.
    ``relative``: the heights' scale is not known (run.json ``relief.scale``): no unit.
    ``outline``: the labels' outlines at the display step, when the caller has them.
    """
    step = display_step(height_um.shape)
    h = height_um[::step, ::step]
    sc = height_scale(height_um, relative=relative)
    fig = figure((7.8, 7 * h.shape[0] / h.shape[1] + 0.6), layout=None)
    fig.subplots_adjust(right=0.86)
    ax = fig.add_subplot()
    ext = extent_mm(height_um.shape, pixel_size_um)
    im = ax.imshow(h, cmap="viridis", vmin=sc.lo, vmax=sc.hi, extent=ext, interpolation="nearest")
    what = "height (\u00b5m)" if not relative else "relative height (no unit)"
    label = what
    if sc.clips:
        fmt = height if not relative else (lambda v: sig(v, 2))
        label += f"\nclipped; all heights {fmt(sc.min)} to {fmt(sc.max)}"
    extend = {(True, True): "both", (True, False): "min", (False, True): "max"}.get(
        (sc.min < sc.lo, sc.max > sc.hi), "neither")
    fig.colorbar(im, ax=ax, label=label, shrink=0.8, extend=extend)
    n = _draw_outlines(ax, labels, step, h.shape, ext, outline=outline) if labels is not None else 0
    ax.set_title(("relative height map" if relative else "height map")
                 + (f" with {n} protrusions outlined" if n else ""))
    ax.set_xlabel("x (mm)")
    ax.set_ylabel("y (mm)")
    return save_figure(fig, path)


def _nice_at_most(x: float) -> float:
    """The largest of 1, 2, 5 x 10^k not above ``x`` (at least 1)."""
    if not np.isfinite(x) or x <= 1:
        return 1.0
    k = 10.0 ** np.floor(np.log10(x))
    return float(max(m * k for m in (1, 2, 5) if m * k <= x))


def _border_plane(x, y, z) -> np.ndarray:
    """The least-squares plane through the outer sixth of a patch on each side (the paint around
    the protrusion), evaluated over the patch: subtracted, the protrusion stands on level ground."""
    m, n = z.shape
    b = max(1, min(m, n) // 6)
    ring = np.ones((m, n), bool)
    ring[b:m - b, b:n - b] = False
    a = np.column_stack([x[ring], y[ring], np.ones(int(ring.sum()))])
    coef = np.linalg.lstsq(a, z[ring], rcond=None)[0]
    return coef[0] * x + coef[1] * y + coef[2]


def plot_detail_3d(height_um: np.ndarray, path, *, pixel_size_um: float, centre_xy,
                   width_um: float, what: str = "", relative: bool = False) -> Path:
    """Shaded 3-D rendering of the height around one protrusion (paper Fig. 2e), in um.

    A square of 3 x its width (at least 32 pixels) around ``centre_xy`` = (x_px, y_px), drawn
    with ``plot_surface`` coloured by :class:`matplotlib.colors.LightSource` hill shading (light
    from the upper left, 315 deg, 45 deg elevation), the plane through the patch's border (the
    paint around it) subtracted so that the protrusion stands level. The vertical axis is stretched by a round
    factor (1, 2, 5, 10, ...) so that the relief fills about half the width, and the title states
    it; heights are drawn without a unit when ``relative``.
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
    z = z - _border_plane(x, y, z)
    span_xy = max(np.ptp(cols), np.ptp(rows), pixel_size_um)
    span_z = max(float(np.ptp(z)), 1e-9)
    fig = figure((7, 5.5), layout=None)
    ax = fig.add_subplot(projection="3d")
    ls = LightSource(azdeg=315, altdeg=45)
    if relative:
        exag = None
        box_z = 0.5
        rgb = ls.shade(z / span_z * 0.5 * span_xy, cmap=cm.copper, blend_mode="soft",
                       dx=pixel_size_um * stride, dy=pixel_size_um * stride)
    else:
        exag = _nice_at_most(0.5 * span_xy / span_z)
        box_z = max(exag * span_z / span_xy, 0.02)
        rgb = ls.shade(z, cmap=cm.copper, vert_exag=exag, blend_mode="soft",
                       dx=pixel_size_um * stride, dy=pixel_size_um * stride)
    ax.plot_surface(x, y, z, facecolors=rgb, rstride=1, cstride=1, linewidth=0,
                    antialiased=False, shade=False)
    ax.set_box_aspect((np.ptp(cols) / span_xy, np.ptp(rows) / span_xy, box_z))
    ax.set_xlabel("x (\u00b5m from its centre)")
    ax.set_ylabel("y (\u00b5m)")
    ax.set_zlabel("relative height" if relative else "height (\u00b5m)")
    from matplotlib.ticker import MaxNLocator

    ax.xaxis.set_major_locator(MaxNLocator(nbins=4))
    ax.yaxis.set_major_locator(MaxNLocator(nbins=4))
    ax.zaxis.set_major_locator(MaxNLocator(nbins=max(2, int(6 * box_z))))
    head = what or "detail"
    scale = ("vertical scale relative (heights not in \u00b5m)" if relative else
             "true scale (no vertical exaggeration)" if exag == 1 else
             f"vertical exaggeration \u00d7{exag:g}")
    ax.set_title(f"{head}\n{scale}", fontsize=10)
    return save_figure(fig, path)


def region_colours(regions, albedo: Optional[np.ndarray], *, display: Optional[np.ndarray] = None) -> dict:
    """Display colour per area: the RegionMap's colours, else the mean albedo, else a colour map.
    ``display``: ``display_albedo(albedo, display_step(shape))`` when the caller has it."""
    from matplotlib import colormaps

    cols = dict(getattr(regions, "colors", {}) or {})
    if albedo is not None:
        step = display_step(regions.labels.shape)
        if display is not None:
            _check_shown("display", display, regions.labels.shape, step)
        a = display_albedo(albedo, step) if display is None else display
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


def plot_regions(albedo: np.ndarray, regions, path, *, pixel_size_um: float,
                 display: Optional[np.ndarray] = None) -> Path:
    """Albedo with the colour-area borders and numbers (to check a proposal before editing it).
    ``display``: ``display_albedo(albedo, display_step(shape))`` when the caller has it."""
    step = display_step(regions.labels.shape)
    if display is not None:
        _check_shown("display", display, regions.labels.shape, step)
    a = display_albedo(albedo, step) if display is None else display
    fig = figure((7, 7 * a.shape[0] / a.shape[1] + 0.6), layout=None)
    ax = fig.add_subplot()
    ext = extent_mm(regions.labels.shape, pixel_size_um)
    ax.imshow(a, cmap="gray", vmin=0, vmax=1, extent=ext, interpolation="nearest")
    edge = inner_boundaries(regions.labels)
    if step > 1:
        edge = block_reduce(edge, (step, step), np.max)
    edge = edge[: a.shape[0], : a.shape[1]]
    overlay = np.zeros(edge.shape + (4,))
    overlay[edge] = (1.0, 1.0, 0.0, 1.0)
    ax.imshow(overlay, extent=ext, interpolation="nearest")
    small = regions.labels[::step, ::step]
    m, n = regions.labels.shape
    boxes = ndi.find_objects(small)
    for i in regions.ids:
        box = boxes[i - 1] if 0 < i <= len(boxes) else np.s_[:, :]
        if box is None or not (inside := small[box] == i).any():
            continue
        # the deepest point of the area, searched in its bounding box: the box's ring of padding
        # is nearer to every inside pixel than any background beyond it, so the distances (and
        # the first maximum in row order) are those of the whole image
        d = ndi.distance_transform_edt(np.pad(inside, 1))[1:-1, 1:-1]
        r, c = np.unravel_index(np.argmax(d), d.shape)
        r, c = r + (box[0].start or 0), c + (box[1].start or 0)
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
        ax.set_title(f"{r.name}\n{sig(r.density_per_cm2, 2)} per cm\u00b2 "
                     f"({r.count} in {sig(r.area_cm2, 3)} cm\u00b2)", fontsize=8)
        ax.set_xticks(x, [s.replace("um", "") for s in labels], rotation=60, fontsize=7)
        ax.set_xlabel("width (\u00b5m)", fontsize=7)
    for ax in axes.ravel()[k:]:
        ax.set_visible(False)
    for ax in axes[:, 0]:
        ax.set_ylabel("protrusions per cm\u00b2")
    fig.suptitle("protrusions per cm\u00b2 by width, per colour area (as the paper's Fig. 4a)",
                 fontsize=10)
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
                        pixel_size_um: float, display: Optional[np.ndarray] = None) -> Path:
    """Albedo with ``b``'s protrusions circled in red and ``a``'s missed ones in yellow (Fig. 4b).

    Circles have the protrusion's width as diameter, at its centroid. ``display``:
    ``display_albedo(albedo, display_step(shape))`` when the caller has it.
    """
    from matplotlib.patches import Circle

    m, n = as_yxc(albedo).shape[:2]
    if display is not None:
        _check_shown("display", display, (m, n), display_step((m, n)))
    img = display_albedo(albedo, display_step((m, n))) if display is None else display
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

    figures: dict = field(default_factory=dict)  # file name -> caption (HTML)
    skipped: list = field(default_factory=list)  # (figure, reason)


#: The order of the figures in the report: where the protrusions are, then how high, how many per
#: area and width, the areas, the two methods, one in 3-D, then the inputs (normals, lamps).
FIGURE_ORDER = ("albedo.png", "height.png", "histograms.png", "regions.png", "comparison_map.png",
                "comparison.png", "detail3d.png", "normals.png", "lights.png")


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
    """A plain HTML table of values (floats to 4 significant figures; used by ``uvps changes``)."""
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
    page.figures[name] = caption


#: Screen and print styles. Print: the user's paper (A4 or Letter: no fixed @page size), 14 mm
#: margins, figures at most 170 mm wide (fits both), never split, headings kept with what follows,
#: table headers repeated on each page, colour swatches printed.
CSS = """body{font-family:system-ui,-apple-system,"Segoe UI",Roboto,sans-serif;max-width:1100px;
margin:1em auto;padding:0 1em;color:#222;line-height:1.4}
h1{font-size:1.6em;margin-bottom:0.2em}h2{border-bottom:1px solid #ccc;padding-bottom:2px;margin-top:1.6em}
.meta{color:#666;margin-top:0}
table{border-collapse:collapse;margin:0.5em 0;font-size:0.9em}
td,th{border:1px solid #bbb;padding:2px 6px;text-align:right;vertical-align:top}
th{background:#eee}td:first-child,th:first-child{text-align:left}
figure{margin:1.2em 0}img{max-width:100%}figcaption{font-size:0.92em;color:#333;max-width:900px}
.warn{color:#a40}pre{background:#f6f6f6;padding:0.5em;overflow-x:auto}
#summary{background:#f7f7f4;border:1px solid #ddd;padding:0.2em 1em 0.6em;border-radius:4px}
#summary h2{border:none;margin-top:0.5em}.big{font-size:1.15em}.src{color:#666;font-size:0.9em}
ul.sure{margin-top:0}.def{font-size:0.92em}
.sw{display:inline-block;width:0.9em;height:0.9em;border:1px solid #555;margin-right:0.4em;
vertical-align:-0.1em}
code.hash{font-size:0.8em;word-break:break-all}table.prov td,table.prov th{text-align:left}
table.lt td:nth-child(2){text-align:left}
.tcap{font-size:0.92em;color:#333;margin:0.2em 0 1em;max-width:900px}.tblock{margin-bottom:0.5em}
@page{margin:14mm 12mm}
@media print{body{max-width:none;margin:0;padding:0;font-size:10pt}
*{-webkit-print-color-adjust:exact;print-color-adjust:exact}
figure,table,.tcap{break-inside:avoid}h2,h3{break-after:avoid}
img{max-width:170mm;max-height:200mm}a{color:inherit;text-decoration:none}
thead{display:table-header-group}tr{break-inside:avoid}
#methods{break-before:page}.tblock{break-inside:avoid}#summary{border:1px solid #999}}"""


def write_report(run_dir, *, table=None, bins_um=100.0, stats=None, regions=None, comparison=None,
                 warnings: Optional[list] = None, title: Optional[str] = None, images=None,
                 progress: Progress = None) -> Path:
    """Write ``report.html`` and ``figures/*.png`` for a run folder.

    The report reads as a condition report: a summary (what was captured, how many protrusions,
    where, how sure), the figures, the tables (rounded to what is measured), then appendices:
    the methods and parameters in words, figures not drawn, and the provenance (input hashes).

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
        Colour areas (their names are the report's); otherwise ``regions_labels.tif`` with the
        names beside it (:func:`uvps.files.tables.load_regions`: the ``name`` column of
        ``regions.csv``) or the whole image.
    comparison : Comparison, optional
        A two-method comparison; otherwise ``comparison.csv`` when present.
    warnings : list of str, optional
        Warnings to list (besides those in ``run.json``).
    title : str, optional
    images : RunImages, optional
        The run folder's images when the caller has read them already (:func:`uvps.files.runfolder.read_run`).
    progress : callable(fraction, message), optional

    Returns
    -------
    Path
        ``<run_dir>/report.html``.

    Notes
    -----
    Every figure is optional; a figure whose input is missing is listed as not drawn with the
    reason. A run whose heights are relative (``run.json`` ``relief.scale``, docs/architecture.md)
    shows no height in micrometres. PNGs and the HTML are written atomically (temporary file +
    ``os.replace``).
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
    lights = _read_json(run_dir / "lights.json") if (run_dir / "lights.json").is_file() else None
    facts = facts_of(run, lights, pixel_size_um=inputs.pixel_size_um, shape=inputs.shape)

    px = inputs.pixel_size_um
    if px is None:
        px = float("nan")
    protrusions = read_protrusions_csv(inputs.table_path) if inputs.table_path.is_file() else None
    report(progress, 0.15, "statistics")
    regions, stats, colours = _area_data(run_dir, inputs, protrusions, px, regions=regions, stats=stats,
                                         bins_um=bins_um)
    report(progress, 0.25, "figures")
    _figures(page, inputs, lights, protrusions, figdir, px, facts, regions=regions, stats=stats, colours=colours)
    report(progress, 0.85, "comparison")
    if comparison is None and not (run_dir / "comparison.csv").is_file():
        comparison = _manual_vs_automated(run_dir, inputs, regions, px, figdir)
    comp_html = _comparison_section(page, run_dir, figdir, comparison)

    text = _html(run_dir, facts, protrusions, inputs.table_path, page, warn, title,
                 regions=regions, stats=stats, colours=colours, comparison_html=comp_html)
    out = run_dir / "report.html"
    atomic_write_text(out, text)
    report(progress, 1.0, "report written")
    log.info("report: %d figures, %d skipped", len(page.figures), len(page.skipped))
    return out


#: Browsers whose headless mode prints a page to PDF, tried in this order (Debian's ``chromium``
#: first). None is downloaded: one must be installed (``apt-get install chromium``).
PDF_BROWSERS = ("chromium", "chromium-browser", "google-chrome", "google-chrome-stable")


def print_pdf(html_path, *, browser: Optional[str] = None, timeout_s: float = 300.0) -> Path:
    """Print ``report.html`` to ``report.pdf`` beside it with a headless Chromium or Chrome.

    The browser lays the page out with the report's print styles (the default paper of the
    browser's locale, A4 or Letter; figures and tables never split), so the PDF holds the same
    text, searchable, as the HTML. ``browser``: its executable; default the first of
    :data:`PDF_BROWSERS` on ``PATH``. The PDF is written atomically; a browser that is missing,
    fails or prints no PDF is a one-line :class:`~uvps.errors.UVPSInputError` saying what to do.
    """
    html_path = Path(html_path)
    exe = browser or next((w for w in map(shutil.which, PDF_BROWSERS) if w), None)
    if exe is None:
        raise UVPSInputError("pdf: no Chromium or Chrome on PATH to print report.html; install "
                             "Debian's chromium (apt-get install chromium), or open report.html "
                             "in a browser and print it to PDF")
    out = html_path.with_suffix(".pdf")
    with tempfile.TemporaryDirectory(prefix="uvps-browser-") as profile, \
            atomic_path(out, suffix=".pdf") as tmp:
        cmd = [exe, "--headless", "--disable-gpu", "--no-first-run", "--disable-background-networking",
               "--disable-component-update", "--disable-sync", f"--user-data-dir={profile}",
               "--no-pdf-header-footer", f"--print-to-pdf={tmp}", html_path.resolve().as_uri()]
        if hasattr(os, "geteuid") and os.geteuid() == 0:
            cmd.insert(2, "--no-sandbox")          # Chromium refuses to run as root with its sandbox
        log.info("printing the report: %s", " ".join(cmd))
        try:
            proc = subprocess.run(cmd, capture_output=True, timeout=timeout_s, check=False)
        except (OSError, subprocess.TimeoutExpired) as exc:
            raise UVPSInputError(f"pdf: {Path(exe).name} could not print {html_path.name} "
                                 f"({type(exc).__name__}); open it in a browser and print it to "
                                 "PDF") from None
        if proc.returncode != 0 or tmp.read_bytes()[:5] != b"%PDF-":
            raise UVPSInputError(f"pdf: {Path(exe).name} printed no PDF of {html_path.name} (exit "
                                 f"{proc.returncode}); open it in a browser and print it to PDF")
    return out


def _run_summary(run_dir: Path, page: _Page, warnings: Optional[list]):
    """``run.json`` (None when missing: listed as skipped) and the warnings, its own first."""
    warn = list(warnings or [])
    run = _read_json(run_dir / "run.json") if (run_dir / "run.json").is_file() else None
    if run is None:
        page.skipped.append(("run summary", "run.json missing"))
    elif isinstance(run.get("warnings"), list):
        warn = [str(w) for w in run["warnings"]] + [w for w in warn if w not in run["warnings"]]
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
    _shown: dict = field(default_factory=dict, repr=False)

    def display(self) -> Optional[np.ndarray]:
        """The albedo as the figures draw it (:func:`display_albedo` at :func:`display_step`), made
        once for the albedo, area and comparison figures and the areas' colours."""
        if self.albedo is None:
            return None
        if "albedo" not in self._shown:
            self._shown["albedo"] = display_albedo(self.albedo, display_step(as_yxc(self.albedo).shape))
        return self._shown["albedo"]

    def outline(self) -> Optional[np.ndarray]:
        """The outlines of :func:`_protrusion_labels` at the display step (:func:`_outline`), made once
        for the albedo and the height figures."""
        labels = _protrusion_labels(self)
        if labels is None:
            return None
        if "outline" not in self._shown:
            self._shown["outline"] = _outline(labels, display_step(self.shape))
        return self._shown["outline"]


def _read_inputs(run_dir: Path, run, table, images=None) -> _RunInputs:
    """Read the run's images (:func:`uvps.files.runfolder.read_run`: its file names and layout) and the
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
    if plabels is not None and shape is not None and plabels.shape == tuple(shape[:2]):
        plabels = _checked_labels(plabels, _labels_path(table_path))
    return _RunInputs(images.normals, images.albedo, images.height_um, plabels, table_path, px, shape)


def _checked_labels(labels: np.ndarray, path: Path) -> np.ndarray:
    """A protrusion label image the figures outline: floats' NaN and infinities are no protrusion (0);
    a label below 0, or a float one past 2^53 (no longer an exact integer), is refused by the file's name."""
    if labels.dtype.kind == "f":
        labels = np.where(np.isfinite(labels), labels, 0)
    if labels.size and labels.dtype.kind in "if":
        low, high = float(labels.min()), float(labels.max())
        if low < 0 or (labels.dtype.kind == "f" and high >= 2.0 ** 53):
            raise UVPSInputError(f"{path}: protrusion labels must be integers from 0 (no protrusion) up; "
                                 f"found {low:g} to {high:g}")
    return labels


def _display_for(inputs: _RunInputs, shape) -> Optional[np.ndarray]:
    """The run's display albedo for a figure of ``shape`` (the colour areas'), when the albedo has it."""
    if inputs.albedo is None or tuple(shape[:2]) != as_yxc(inputs.albedo).shape[:2]:
        return None
    return inputs.display()


def _labels_path(table_path: Path) -> Path:
    """The label TIFF beside a protrusion table: ``<stem>_labels.tif``."""
    return table_path.with_name(table_path.stem + "_labels.tif")


def _figures(page: _Page, inputs: _RunInputs, lights, table, figdir: Path, px: float, facts: Facts, *, regions, stats,
             colours) -> None:
    """The report's figures into ``page``, drawn in two threads (:func:`uvps.core.threads.concurrently`): the lamps,
    normals, albedo and colour areas in this one, the height, its 3-D detail and the histograms in the other.

    Each figure is a matplotlib ``Figure`` of its own on its own Agg canvas (no pyplot, no global state; matplotlib
    keeps its fonts per thread), and what two figures share (the display albedo, the outlines) is made before the
    threads start: the same PNGs as one after the other, in about two thirds of the time (the drawing and the PNGs'
    compression release the GIL part of the time). Each group collects into a page of its own, merged in the
    order the figures were drawn one after the other, so the HTML (figures in :data:`FIGURE_ORDER`, the figures not
    drawn in that order) does not depend on the threads.
    """
    import matplotlib.figure  # noqa: F401  - before the threads (each thread's first figure imports the rest)

    if np.isfinite(px):          # what both threads' figures draw, made once before they start
        inputs.display()
        if inputs.albedo is not None or inputs.height is not None:
            inputs.outline()
    parts = [_Page() for _ in range(5)]
    if inputs.pixel_size_um is None:
        parts[1].skipped.append(("image figures", "no pixel size (no calibrated TIFF, run.json)"))

    def lamps_and_images():
        _lights_figure(parts[0], lights, figdir)
        _normals_and_albedo_figures(parts[1], inputs, figdir, px)
        _regions_figure(parts[3], inputs, figdir, px, regions)

    def height_and_histograms():
        _height_figures(parts[2], inputs, table, figdir, px, facts)
        _histograms_figure(parts[4], stats, figdir, colours, table)

    concurrently(lamps_and_images, height_and_histograms)
    for part in parts:
        page.figures.update(part.figures)
        page.skipped.extend(part.skipped)


def _lights_figure(page: _Page, lights: Optional[dict], figdir: Path) -> None:
    """The lamp positions from ``lights.json``."""
    if lights is not None:
        n = len(lights.get("lights") or [])
        _figure_step(page, "lights.png", f"The {n} lamp positions as the run used them, seen from "
                     "above (azimuth counter-clockwise from the image's right, radius 90\u00b0 "
                     "minus the elevation) and the height of each lamp above the canvas.",
                     plot_lights, lights, figdir / "lights.png")
    else:
        page.skipped.append(("lights.png", "lights.json missing"))


def _protrusion_labels(inputs: _RunInputs) -> Optional[np.ndarray]:
    """The protrusion label image when it matches the run's images."""
    plabels = inputs.protrusion_labels
    if plabels is not None and inputs.shape is not None and plabels.shape == tuple(inputs.shape[:2]):
        return plabels if plabels.dtype.kind in "ui" else plabels.astype(np.int64)
    return None


def _normals_and_albedo_figures(page: _Page, inputs: _RunInputs, figdir: Path, px: float) -> None:
    """The normal map and the albedo with the protrusion outlines, when read and calibrated."""
    images_ok = np.isfinite(px)
    if inputs.normals is not None and images_ok:
        _figure_step(page, "normals.png", "Normal map: the surface's orientation at each pixel "
                     "(red = facing right, green = facing up, blue = facing the camera).",
                     plot_normals, inputs.normals, figdir / "normals.png", pixel_size_um=px)
    elif inputs.normals is None:
        page.skipped.append(("normals.png", "normals.tif missing"))
    if inputs.albedo is not None and images_ok:
        lab = _protrusion_labels(inputs)
        _figure_step(page, "albedo.png", "Albedo: the UV fluorescence with the shading of the "
                     "relief removed" + (", with every counted protrusion outlined in red"
                                         if lab is not None and lab.any() else "")
                     + ". Axes in mm from the image centre.",
                     plot_albedo, inputs.albedo, figdir / "albedo.png", pixel_size_um=px,
                     labels=lab, display=inputs.display(), outline=inputs.outline())
    elif inputs.albedo is None:
        page.skipped.append(("albedo.png", "albedo.tif missing"))


def _height_figures(page: _Page, inputs: _RunInputs, table, figdir: Path, px: float, facts: Facts) -> None:
    """The height map with the protrusions outlined, and the 3-D detail of the largest one."""
    height = inputs.height
    if height is None:
        page.skipped.append(("height.png, detail3d.png", "depth.tif missing"))
        return
    if not np.isfinite(px):
        return
    rel = facts.relative
    lab = _protrusion_labels(inputs)
    scale = height_scale(height, relative=rel)
    what = "Relative height (no unit: the heights' scale is not known)" if rel else "Height (\u00b5m)"
    lev = facts.run.get("level") if isinstance(facts.run.get("level"), dict) else {}
    levelled = {"plane": ", levelled (its best plane removed: see How sure)",
                "form": ", levelled (a smooth form removed, the bow with it: see How sure)",
                "none": ", not levelled"}.get(str(lev.get("method")), "")
    _figure_step(page, "height.png", f"{what} from the normals{levelled}, median 0, with the counted "
                 f"protrusions outlined in red. {scale.words()}", plot_height, height,
                 figdir / "height.png", pixel_size_um=px, labels=lab, relative=rel,
                 outline=inputs.outline())
    centre, width_um, what = _detail_target(height, table, px)
    _figure_step(page, "detail3d.png", f"{what[0].upper() + what[1:]} in 3-D, hill-shaded "
                 "(light from the upper left; as the paper's Fig. 2e), on the plane through the "
                 "paint around it; distances in \u00b5m from its centre, the vertical stretch "
                 "stated in the title.", plot_detail_3d, height,
                 figdir / "detail3d.png", pixel_size_um=px, centre_xy=centre, width_um=width_um,
                 what=what, relative=rel)


def _detail_target(height: np.ndarray, table, px: float):
    """Centre (x_px, y_px), width (um) and description of what the 3-D detail shows: the largest
    protrusion, else the highest point."""
    if table is not None and len(table["width_um"]):
        big = int(np.nanargmax(np.nan_to_num(table["area_um2"], nan=-1.0)
                               if np.isfinite(table["area_um2"]).any() else table["width_um"]))
        centre, width_um = (table["x_px"][big], table["y_px"][big]), float(table["width_um"][big])
        return (centre, width_um,
                f"the largest protrusion (no. {table['id'][big]}, "
                f"{width_fmt(width_um, px)} \u00b5m wide)")
    r, c = np.unravel_index(np.nanargmax(np.nan_to_num(height, nan=-np.inf)), height.shape)
    return (c, r), 20 * px, "the highest point (no protrusions)"


def _area_data(run_dir: Path, inputs: _RunInputs, table, px: float, *, regions, stats, bins_um):
    """The colour areas (given, else ``regions_labels.tif``, else the whole image), the per-area statistics and the
    areas' colours: (regions, stats, colours)."""
    if regions is None and inputs.shape is not None:
        if (run_dir / "regions_labels.tif").is_file():
            regions = load_regions(run_dir / "regions_labels.tif", shape=inputs.shape)
        else:
            regions = whole_image(inputs.shape)
    if stats is None and table is not None and regions is not None and np.isfinite(px):
        stats = region_statistics(table, regions, pixel_size_um=px, bins_um=bins_um)
    colours = None
    if stats is not None and regions is not None:
        colours = region_colours(regions, inputs.albedo, display=_display_for(inputs, regions.labels.shape))
    return regions, stats, colours


def _regions_figure(page: _Page, inputs: _RunInputs, figdir: Path, px: float, regions) -> None:
    """The colour areas over the albedo, when there are several."""
    if regions is not None and inputs.albedo is not None and np.isfinite(px) and len(regions.ids) > 1:
        _figure_step(page, "regions.png", "The colour areas the densities are counted in "
                     "(borders in yellow, with their names).", plot_regions,
                     inputs.albedo, regions, figdir / "regions.png", pixel_size_um=px,
                     display=_display_for(inputs, regions.labels.shape))


def _histograms_figure(page: _Page, stats, figdir: Path, colours, table) -> None:
    """Protrusions per cm^2 by width, one panel per colour area."""
    if stats is None:
        page.skipped.append(("histograms.png", "protrusions.csv missing" if table is None
                             else "no image size or pixel size for the colour areas"))
        return
    edges = np.asarray(stats.edges_um, float)
    bw = np.diff(edges[np.isfinite(edges)])
    bins = (f"{sig(bw[0], 3)} \u00b5m" if bw.size and np.allclose(bw, bw[0]) else "the given")
    _figure_step(page, "histograms.png", "Protrusions per cm\u00b2 by width, one panel per "
                 f"colour area, in {bins} width bins (as the paper's Fig. 4a); the numbers "
                 "are in Table 2.", plot_histograms, stats, figdir / "histograms.png",
                 colours=colours)


def _manual_vs_automated(run_dir: Path, inputs: _RunInputs, regions, px: float, figdir: Path):
    """When the run folder holds both the wand's count (``protrusions_manual.csv``) and the
    automated one (``protrusions.csv``) but no ``comparison.csv``: their comparison
    (:func:`uvps.core.compare.compare_detections`, default match radius), with its map; else None."""
    manual, auto = run_dir / "protrusions_manual.csv", run_dir / "protrusions.csv"
    if not (manual.is_file() and auto.is_file() and np.isfinite(px)):
        return None
    a, b = read_protrusions_csv(manual), read_protrusions_csv(auto)
    comp = compare_detections(a, b, regions=regions, pixel_size_um=px,
                              name_a="manual (wand)", name_b="automated")
    if inputs.albedo is not None:
        plot_comparison_map(inputs.albedo, a, b, comp, figdir / "comparison_map.png",
                            pixel_size_um=px, display=inputs.display())
    return comp


def _comparison_section(page: _Page, run_dir: Path, figdir: Path, comparison) -> str:
    """The two-method comparison (given, else ``comparison.csv``): map, bar chart; its table's HTML."""
    name_a, name_b = "a", "b"
    rows = None
    if comparison is not None:
        rows, name_a, name_b = comparison.rows, comparison.name_a, comparison.name_b
    elif (run_dir / "comparison.csv").is_file():
        rows = read_comparison_csv(run_dir / "comparison.csv")
        if rows:
            name_a, name_b = rows[0].get("table_a") or "a", rows[0].get("table_b") or "b"
    if not rows:
        return ""
    if (figdir / "comparison_map.png").is_file():
        page.figures["comparison_map.png"] = (
            f"The protrusions of {html.escape(name_b)} circled in red, those of "
            f"{html.escape(name_a)} it missed in yellow (as the paper's Fig. 4b).")
    _figure_step(page, "comparison.png", f"Density per colour area by the two methods: "
                 f"{html.escape(name_a)} and {html.escape(name_b)} (as the paper's Fig. 4c).",
                 plot_comparison, rows, figdir / "comparison.png", name_a=name_a, name_b=name_b)
    return _comparison_html(rows, name_a, name_b)


def _comparison_html(rows, name_a, name_b) -> str:
    a, b = html.escape(name_a), html.escape(name_b)
    body = []
    for r in rows:
        total = str(r.get("label")) == "all"
        name = Raw("<b>all areas</b>" if total else html.escape(str(r.get("name", ""))))

        def num(key, fmt):
            v = r.get(key)
            try:
                return fmt(float(v))
            except (TypeError, ValueError):
                return ""
        body.append([name, num("area_cm2", cm2), num("count_a", lambda v: f"{v:.0f}"),
                     num("count_b", lambda v: f"{v:.0f}"), num("density_a", density),
                     num("density_b", density), num("matched", lambda v: f"{v:.0f}"),
                     num("missed", lambda v: f"{v:.0f}"), num("extra", lambda v: f"{v:.0f}")])
    header = ["Colour area", Raw("Area (cm\u00b2)"), Raw(f"Count, {a}"), Raw(f"Count, {b}"),
              Raw(f"Per cm\u00b2, {a}"), Raw(f"Per cm\u00b2, {b}"), "Matched",
              Raw(f"Missed by {b}"), Raw(f"Only in {b}")]
    return (f"<div class='tblock'><h3>Table 4. Two methods: {a} and {b}</h3>"
            + text_table(header, body, cls="num")
            + f"<p class='tcap'>Matched: pairs one-to-one within the match radius; missed: in "
            f"{a} only; only in {b}: not in {a}. All rows: "
            "<a href='comparison.csv'>comparison.csv</a>.</p></div>")


def _link(path: Path, run_dir: Path) -> str:
    """A relative link when ``path`` is inside the run folder, else its absolute file URI."""
    try:
        target = path.resolve().relative_to(run_dir.resolve()).as_posix()
    except ValueError:
        target = path.resolve().as_uri()
    return f"<a href='{html.escape(target)}'>{html.escape(path.name)}</a>"


def _region_source(facts: Facts, regions) -> str:
    reg = facts.params.get("regions")
    if reg == "auto":
        return "proposed automatically by clustering the albedo's colour (k-means, smoothed at about 1 mm)"
    if reg:
        return f"from the label image <code>{html.escape(Path(str(reg)).name)}</code>"
    if regions is not None and len(regions.ids) == 1:
        return "the whole image (no colour areas given)"
    return "from <code>regions_labels.tif</code>"


def _html(run_dir: Path, facts: Facts, table, table_path: Path, page: _Page, warn: list, title, *,
          regions, stats, colours, comparison_html: str) -> str:
    e = html.escape
    title = title or f"Protrusion report: {run_dir.name}"
    written = datetime.now(timezone.utc).strftime("%Y-%m-%d %H:%M UTC")
    parts = [f"<!DOCTYPE html><html lang='en'><head><meta charset='utf-8'>"
             f"<meta name='viewport' content='width=device-width, initial-scale=1'>"
             f"<title>{e(title)}</title><style>{CSS}</style></head><body>",
             f"<h1>{e(title)}</h1>",
             f"<p class='meta'>Run folder <code>{e(run_dir.name)}</code>; written {e(written)} by "
             f"uvps {e(__version__)} (photometric stereo under UV light, after Salvant et al.).</p>"]
    definition = protrusion_definition(facts, table, _detection_defaults())
    parts.append(summary_html(facts, table, stats, warn, table_name=table_path.name,
                              definition=definition))
    # figures, numbered in reading order
    drawn = [n for n in FIGURE_ORDER if n in page.figures]
    drawn += [n for n in page.figures if n not in FIGURE_ORDER]
    if drawn:
        parts.append("<section id='figures'><h2>Figures</h2>")
        for k, name in enumerate(drawn, start=1):
            cap = page.figures[name]
            alt = re.sub("<[^>]+>", "", cap)
            parts.append(f"<figure id='fig-{e(name[:-4])}'><img src='figures/{e(name)}' "
                         f"alt='{e(alt)}'><figcaption><b>Figure {k}.</b> {cap}</figcaption>"
                         "</figure>")
        parts.append("</section>")
    fignum = {name: k for k, name in enumerate(drawn, start=1)}
    parts.append(_tables_html(run_dir, facts, table, table_path, regions, stats, colours,
                              comparison_html, fignum))
    parts.append(_earlier_html(run_dir))
    parts.append(methods_html(facts, len(regions.ids) if regions is not None else None,
                              _region_source(facts, regions)))
    parts.append("<section class='appendix' id='not-drawn'><h2>Appendix B: figures not drawn"
                 "</h2>" + ("<ul>" + "".join(f"<li>{e(n)}: {e(r)}</li>" for n, r in page.skipped)
                            + "</ul>" if page.skipped else "<p>None: every figure was drawn.</p>")
                 + "</section>")
    parts.append(provenance_html(facts, run_dir, __version__, written))
    parts.append("</body></html>\n")
    return "\n".join(parts)


def _tables_html(run_dir, facts, table, table_path, regions, stats, colours, comparison_html,
                 fignum: dict) -> str:
    e = html.escape
    out = ["<section id='tables'><h2>Tables</h2>"]
    if stats is not None:
        names_note = ("Area names are the <code>name</code> column of "
                      "<a href='regions.csv'>regions.csv</a>: edit them there and run "
                      f"<code>uvps stats -o {e(run_dir.name)}</code> to redraw this report with them.")
        out.append("<div class='tblock'><h3>Table 1. Protrusions per colour area</h3>"
                   + area_table_html(stats, colours)
                   + "<p class='tcap'>Density = protrusions / area; \u00b1 its standard error "
                   "from the count (Poisson: \u221an / area). "
                   + (f"{stats.outside} protrusions lie in no colour area. " if stats.outside else "")
                   + names_note + "</p></div>")
        out.append("<div class='tblock'><h3>Table 2. Protrusions per cm\u00b2 by width</h3>"
                   + width_table_html(stats)
                   + "<p class='tcap'>Per cm\u00b2 of each colour area, by width (\u00b5m); the "
                   "count in brackets"
                   + (f"; the numbers of Figure {fignum['histograms.png']}"
                      if "histograms.png" in fignum else "")
                   + ". Every bin: <a href='regions.csv'>regions.csv</a>.</p></div>")
    if table is not None and len(table["width_um"]):
        names = dict(regions.names) if regions is not None else {}
        n = min(10, len(table["width_um"]))
        out.append(f"<div class='tblock'><h3>Table 3. The {n} widest protrusions</h3>"
                   + largest_table_html(table, facts, names, n)
                   + "<p class='tcap'>No. = the protrusion's number in "
                   f"{_link(table_path, run_dir)} and its label in "
                   f"<code>{e(_labels_path(table_path).name)}</code>; x, y of its centre from the "
                   "image's top-left corner (as ImageJ shows a calibrated image)"
                   + ("" if facts.relative else "; height = summit above a plane through the "
                      "paint around it") + ".</p></div>")
    out.append(comparison_html)
    out.append("</section>")
    return "\n".join(out)


def _earlier_html(run_dir: Path) -> str:
    """Manual work measured on earlier runs of this folder (``earlier/``), named as such: its counts
    are not this run's."""
    items = earlier_work(run_dir)
    if not items:
        return ""
    e = html.escape
    rows = []
    for it in items:
        files = ", ".join(f"<a href='{e(it['folder'])}/{e(f)}'>{e(f)}</a>" for f in it["manual_files"])
        count = (f"{it['counted']} counted of {it['clicks']} clicks" if "clicks" in it else "")
        rows.append(f"<li><code>{e(it['folder'])}/</code>: {files}"
                    + (f" ({e(count)})" if count else "")
                    + f", measured on the run of {e(it.get('measured_on') or 'an unknown date')} UTC"
                    + (f" (run id {e(it['run_id'])})" if it.get("run_id") else "") + "</li>")
    return ("<section id='earlier'><h2>Manual work measured on earlier runs</h2>"
            "<p>These were made on an earlier run of this folder (its albedo and height), kept with the "
            "files they were measured on; their counts are not this run's and are left out of the figures "
            "and tables above.</p><ul>" + "".join(rows) + "</ul></section>")


def _detection_defaults() -> dict:
    from ..core.detect import DetectionParams

    return dataclasses.asdict(DetectionParams())
