"""ImageJ-style wand (magic wand) with a tolerance, for the manual protrusion count.

The paper's manual method (Salvant et al., "Manual Protrusion Detection") clicks each protrusion on
the albedo image with ImageJ's wand tool: the contiguous pixels whose value lies within a tolerance
of the clicked pixel are selected. :func:`wand_select` reproduces ImageJ 1.x ``ij.gui.Wand``
(``autoOutline(x, y, tolerance, mode)``, version 2009-06-01 and later) for a list of clicks, so a
point list exported from ImageJ gives the same selections here.

ImageJ's rules, as implemented in ``ij/gui/Wand.java``:

- Inclusion: with seed value ``v0`` a pixel is inside when ``v0 - tol <= v <= v0 + tol`` (both
  bounds inclusive). NaN pixels are never inside; a click on a NaN pixel selects nothing.
- RGB: with ``tolerance > 0`` ImageJ compares the *grey value* of the colour pixel
  (``ColorProcessor.getPixelValue``: ``(r + g + b) / 3`` with the default unweighted conversion);
  with ``tolerance == 0`` it requires the exact same RGB triple. ``rgb="mean"`` (default) does
  exactly that. ``rgb="channels"`` instead requires every channel to lie within the tolerance of
  the seed's channel (a stricter, colour-aware rule; the two agree at ``tolerance == 0``).
- Connectivity: "4-connected" or "8-connected" trace the outline of the 4- or 8-connected region.
  "Legacy" mode is 8-connected when ``tolerance > 0``; with ``tolerance == 0`` it is 4-connected
  unless the region looks like a thin line (fewer than 25 % inside pixels in an 11 x 11 window to
  the right of the seed's run, ImageJ's ``isLine``), then 8-connected.
- Holes: the wand traces the *outer outline* only, so interior holes (a caldera's crater whose
  pixels fail the tolerance) are part of the selection. We fill them with
  :func:`scipy.ndimage.binary_fill_holes`, using the background connectivity dual to the region's
  (a hole of an 8-connected region is 4-connected background and vice versa).
"""
from __future__ import annotations

import csv
import logging
from dataclasses import dataclass
from pathlib import Path
from typing import Union

import numpy as np
from scipy import ndimage as ndi
from skimage.segmentation import flood

from ..errors import UVPSInputError

logger = logging.getLogger(__name__)

__all__ = ["wand_select", "contrast_select", "judge_clicks", "WandClicks", "read_seeds", "read_seed_file", "SeedFile",
           "CONTRAST_FRACTION", "MAX_WIDTH_UM", "RAISED_RATIO"]

_CONNECTIVITY = {4: 4, 8: 8, "4": 4, "8": 8, "4-connected": 4, "8-connected": 8, "legacy": "legacy"}


def _is_line(inside: np.ndarray, row: int, border_col: int) -> bool:
    """ImageJ's ``Wand.isLine``: few inside pixels in an 11 x 11 window right of the border."""
    m, n = inside.shape
    win = inside[max(row - 5, 0):min(row + 5, m - 1) + 1, border_col:min(border_col + 10, n - 1) + 1]
    return win.size > 0 and win.mean() < 0.25


def _check_seed(i: int, x: int, y: int, finite: np.ndarray) -> None:
    """A click must fall inside the image, on a pixel with a value (both wands)."""
    m, n = finite.shape
    if not (0 <= x < n and 0 <= y < m):
        raise UVPSInputError(f"click {i + 1} at (x={x}, y={y}) px is outside the image of {n} x {m} pixels (x, y); "
                             "are the points in another unit? (a points file's header names it: x_px, x_um or x_mm)")
    if not finite[y, x]:
        raise UVPSInputError(f"click {i + 1} at (x={x}, y={y}) px falls on a pixel without a value (NaN: masked "
                             "or not measured); click inside the measured area")


def wand_select(image, seeds, *, tolerance, connectivity=8, rgb="mean") -> np.ndarray:
    """Select the region around each seed the way ImageJ's wand tool does.

    Parameters
    ----------
    image : (M, N) or (M, N, 3) array
        Grey or RGB image (usually the albedo). Not modified.
    seeds : (S, 2) array_like
        Clicks as ``(x_px, y_px)`` = ``(col, row)``, as ImageJ reports them. Fractional coordinates
        are floored (ImageJ's pixel containing the point).
    tolerance : float
        ImageJ's wand tolerance, in the image's units; ``0 <= tolerance <= max - min`` of the data.
    connectivity : {8, 4, "legacy"}
        ImageJ's mode: "8-connected", "4-connected" or "Legacy" (see module notes).
    rgb : {"mean", "channels"}
        RGB inclusion rule: ImageJ's grey value (default) or every channel within the tolerance.

    Returns
    -------
    labels : (M, N) int32
        0 = not selected; seed ``i`` (0-based) gets label ``i + 1``. A seed that falls inside the
        region of an earlier seed reuses that label (the click would select the same region in
        ImageJ). Where two regions overlap, the earlier seed keeps the pixels.

    Raises
    ------
    UVPSInputError
        Bad image shape, seeds outside the image or on NaN, tolerance negative or beyond the data
        range, unknown connectivity.

    Notes
    -----
    One :func:`skimage.segmentation.flood` per seed on the inclusion mask, then the region's
    interior holes are filled, as ImageJ's traced outline encloses them. Cost: one flood over the
    image per seed (a few ms at 1600 x 1200).
    """
    img = np.asarray(image)
    if img.ndim == 3 and img.shape[2] == 3:
        colour = True
    elif img.ndim == 2:
        colour = False
    else:
        raise UVPSInputError(f"`image` must be (M, N) or (M, N, 3); got shape {img.shape}")
    if not np.issubdtype(img.dtype, np.number) or np.issubdtype(img.dtype, np.complexfloating):
        raise UVPSInputError(f"`image` must be real numeric; got dtype {img.dtype}")
    if rgb not in ("mean", "channels"):
        raise UVPSInputError(f"`rgb` must be 'mean' or 'channels'; got {rgb!r}")
    key = connectivity.lower() if isinstance(connectivity, str) else connectivity
    if key not in _CONNECTIVITY:
        raise UVPSInputError(f"`connectivity` must be 4, 8 or 'legacy'; got {connectivity!r}")
    mode = _CONNECTIVITY[key]
    pts = _as_seed_array(seeds, "seeds")
    m, n = img.shape[:2]

    data = img.astype(np.float64)
    # ImageJ's comparison value: grey (mean of R, G, B) for RGB with tolerance > 0.
    grey = data.mean(axis=2) if colour else data
    finite = np.isfinite(data) if not colour else np.isfinite(data).all(axis=2)
    try:
        tol = float(tolerance)
    except (TypeError, ValueError):
        raise UVPSInputError(f"`tolerance` must be a number; got {tolerance!r}") from None
    span = float(np.ptp(data[finite])) if finite.any() else 0.0
    if not np.isfinite(tol) or tol < 0 or tol > span:
        raise UVPSInputError(f"`tolerance` must be within [0, {span:g}] (the data range); got {tolerance!r}")

    labels = np.zeros((m, n), np.int32)
    for i, (x, y) in enumerate(pts):
        _check_seed(i, x, y, finite)
        if labels[y, x]:
            continue  # inside an earlier seed's selection: same region, same label
        if colour and (rgb == "channels" or tol == 0):
            inside = (np.abs(data - data[y, x]) <= tol).all(axis=2)
        else:
            v0 = grey[y, x]
            # float32 bounds, as ImageJ computes them ((float)(startValue -/+ tolerance))
            lo, hi = np.float32(v0 - tol), np.float32(v0 + tol)
            inside = (grey >= lo) & (grey <= hi)
        conn = mode
        if mode == "legacy":
            if tol > 0:
                conn = 8
            else:
                run_end = x + int(np.argmin(np.append(inside[y, x:], False)))
                conn = 8 if _is_line(inside, y, run_end) else 4
        region = flood(inside, (y, x), connectivity=1 if conn == 4 else 2)
        # ImageJ selects the traced outline: fill holes (background dual to the region's connectivity)
        hole_structure = ndi.generate_binary_structure(2, 1 if conn == 8 else 2)
        region = ndi.binary_fill_holes(region, structure=hole_structure)
        labels[region & (labels == 0)] = i + 1
    logger.debug("wand: %d seeds, %d labels", len(pts), len(np.unique(labels)) - 1)
    return labels


#: The default of :func:`contrast_select`: a pixel belongs to the clicked protrusion when it keeps at
#: least half of the click's contrast against its surroundings (the half-contrast outline: the
#: footprint's edge for a protrusion whose fluorescence steps up at its rim).
CONTRAST_FRACTION = 0.5

#: The default widest protrusion of the relative wand, um (as :class:`uvps.core.detect.DetectionParams`).
MAX_WIDTH_UM = 1000.0


def contrast_select(image, seeds, *, fraction=CONTRAST_FRACTION, max_width_px=None) -> np.ndarray:
    """Outline the protrusion at each click by its own contrast against its surroundings.

    ImageJ's wand asks for a tolerance in the image's units, and no single value suits protrusions
    whose contrast varies tenfold (an albedo in raw counts of 6,000-42,000: 0.05 selects one pixel,
    1000 under-selects faint ones, 3000 leaks into the paint). Here each click sets its own. The
    surroundings' level ``b`` is the highest level at which the click's region (8-connected pixels
    at or above it) runs into the paint: wider than ``max_width_px``, or out to the edge of a
    window of that radius (found by bisection). Levels are read on the image's 3 x 3 median (a single noisy
    pixel neither bridges to the paint nor ends the region); with ``v0`` its value at the click and
    ``c = v0 - b`` the click's contrast, the selection is the region of the pixels that keep at
    least ``fraction`` of it (``v >= b + fraction c``), holes filled (as ImageJ's traced outline
    encloses a crater). A click darker than its window's median (a protrusion that does not
    fluoresce) is outlined the same way on the dark side. The region stays below the level at
    which it leaks, so it never spreads across the field.

    Parameters
    ----------
    image : (M, N) or (M, N, 3) array
        The albedo (RGB: the mean of R, G, B, as ImageJ's wand) or any image in which a protrusion
        stands out from its surroundings (the height). Not modified.
    seeds : (S, 2) array_like
        Clicks as ``(x_px, y_px)``, floored to the containing pixel.
    fraction : float
        In (0, 1): the share of the click's contrast a pixel must keep (0.5: half contrast).
    max_width_px : float, optional
        The largest protrusion expected, in pixels (default: a quarter of the smaller image side).

    Returns
    -------
    labels : (M, N) int32
        As :func:`wand_select`: seed ``i`` gets label ``i + 1``; a click inside an earlier click's
        selection reuses its label (a repeated click); a click with no contrast (``c`` within twice
        a pixel's noise, from the window's neighbouring-pixel differences) selects only its own
        pixel.

    Notes
    -----
    A half-contrast outline is the footprint of a protrusion whose fluorescence (or height) steps up
    at its rim; for a dome in height alone it is the width at half height. About 25
    :func:`skimage.segmentation.flood` calls per click on a window of ``2 max_width_px`` pixels.
    Measured on the generator's captures: ``scripts/benchmark_protrusions.py --wand``
    (docs/benchmarks.md, "The wand's default").

    Examples
    --------
    Two round protrusions, of 49 and 13 pixels, one eight times the other's contrast:

    >>> yy, xx = np.mgrid[:40, :40]
    >>> img = np.full((40, 40), 100.0)
    >>> img[(yy - 18) ** 2 + (xx - 13) ** 2 <= 16] = 180.0
    >>> img[(yy - 6) ** 2 + (xx - 31) ** 2 <= 4] = 110.0
    >>> lab = contrast_select(img, [[13, 18], [31, 6]])
    >>> int((lab == 1).sum()), int((lab == 2).sum())
    (49, 13)
    """
    img = np.asarray(image, dtype=np.float64)
    if img.ndim == 3 and img.shape[2] == 3:
        grey = img.mean(axis=2)
    elif img.ndim == 2:
        grey = img
    else:
        raise UVPSInputError(f"`image` must be (M, N) or (M, N, 3); got shape {img.shape}")
    try:
        frac = float(fraction)
    except (TypeError, ValueError):
        frac = float("nan")
    if not 0 < frac < 1:
        raise UVPSInputError(f"`tolerance` of the relative wand must be a fraction of the click's contrast in "
                             f"(0, 1); got {fraction!r}")
    pts = _as_seed_array(seeds, "seeds")
    m, n = grey.shape
    max_w = max(3.0, float(max_width_px) if max_width_px else min(m, n) / 4.0)
    finite = np.isfinite(grey)
    labels = np.zeros((m, n), np.int32)
    for i, (x, y) in enumerate(pts):
        _check_seed(i, x, y, finite)
        if labels[y, x]:
            continue  # inside an earlier click's selection: a repeated click
        region = _grow_by_contrast(grey, finite, y, x, frac, max_w)
        labels[region[0], region[1]] = np.where(labels[region[0], region[1]] == 0, i + 1,
                                                labels[region[0], region[1]])
    logger.debug("contrast wand: %d seeds, %d labels", len(pts), len(np.unique(labels)) - 1)
    return labels


def _grow_by_contrast(grey, finite, y, x, frac, max_w):
    """Rows and columns of the region around (y, x) keeping ``frac`` of its contrast (see
    :func:`contrast_select`)."""
    m, n = grey.shape
    h = int(np.ceil(max_w))
    r0, r1, c0, c1 = max(y - h, 0), min(y + h + 1, m), max(x - h, 0), min(x + h + 1, n)
    ok = finite[r0:r1, c0:c1]
    raw = np.where(ok, grey[r0:r1, c0:c1], np.nan)
    noise = 1.4826 * float(np.nanmedian(np.abs(np.diff(raw, axis=1)))) / np.sqrt(2)
    # grown on the 3 x 3 median: a single noisy pixel neither bridges to the paint nor ends the region
    win = ndi.median_filter(np.where(ok, raw, np.nanmedian(raw)), size=3)
    seed = (y - r0, x - c0)
    v0 = float(win[seed])
    # a bright protrusion, or a dark one (one that does not fluoresce): work on the bright side
    sign = 1.0 if v0 >= np.nanmedian(win) else -1.0
    g = np.where(ok, sign * win, -np.inf)
    v = sign * v0
    max_area = np.pi * (max_w / 2) ** 2
    inner = (slice(1, -1), slice(1, -1))

    def grow(t):
        inside = g >= t
        inside[seed] = True
        return flood(inside, seed, connectivity=2)

    def leaks(region):
        # wider than the largest protrusion, or out to the window's edge (inside the image)
        edge = ~np.zeros_like(region)
        edge[inner] = False
        if r0 == 0:
            edge[0] = False
        if r1 == m:
            edge[-1] = False
        if c0 == 0:
            edge[:, 0] = False
        if c1 == n:
            edge[:, -1] = False
        return region.sum() > max_area or (region & edge).any()

    lo, hi = float(np.min(g[ok])), v
    if leaks(grow(lo)):
        # the surroundings' level: the highest level at which the click's region runs into the
        # paint (hand-written bisection: each step is one flood of the window)
        for _ in range(24):
            mid = 0.5 * (lo + hi)
            if leaks(grow(mid)):
                lo = mid
            else:
                hi = mid
    contrast = v - lo
    if not contrast > 2 * noise:     # the 3 x 3 median's noise is a third of a pixel's: 6 of its sigma
        return np.array([y]), np.array([x])
    level = lo + frac * contrast
    region = grow(level)
    # the rim is read on the pixels themselves: the 3 x 3 median cuts an outline's one-pixel tips
    raw_g = np.where(ok, sign * np.nan_to_num(raw, nan=-np.inf), -np.inf)
    region |= ndi.binary_dilation(region, structure=np.ones((3, 3), bool)) & (raw_g >= level)
    region = ndi.binary_fill_holes(region, structure=ndi.generate_binary_structure(2, 1))
    rr, cc = np.nonzero(region)
    return rr + r0, cc + c0


#: An outline is counted as a protrusion when it stands above the paint around it: the 90th percentile of its
#: height above a plane through the ring around it is at least this many times the ring's own spread about
#: that plane (1.4826 MAD). Measured by ``scripts/benchmark_protrusions.py --wand-off`` (docs/decisions/wand.md,
#: "Clicks judged before they count"): outlines of the paint's texture reach 5.7, outlines of
#: protrusions start at 9.7.
RAISED_RATIO = 8.0

#: A raised outline counts when it is a clear step in the albedo (its median differs from the ring's around it by
#: at least this many times the ring's spread, 1.4826 MAD) ...
CLEAR_CONTRAST = 3.0
#: ... or else agrees with the bump in the height at the click (intersection over union of the albedo outline and
#: the half-height outline of the height at least this): the paint's texture outlined over a bump in the height
#: alone is raised by the bump, not by itself. Measured by ``scripts/benchmark_protrusions.py --wand-off``: such
#: outlines 1.9-2.4 and 0.07-0.22; outlines of protrusions >= 100 um 2 % below 2.65 and 2 % below 0.41.
MATCH_IOU = 0.3

#: Why a click is not counted (the ``status`` of :class:`WandClicks`), in words.
NOT_COUNTED = {"bare paint": "no protrusion outlined: bare paint",
               "height only": "no contrast in the albedo the wand outlines on: a bump in the height only",
               "repeat": "inside an earlier click's outline"}


@dataclass
class WandClicks:
    """What each click of the wand outlined, from :func:`judge_clicks`.

    Attributes
    ----------
    labels : (M, N) int32
        The counted outlines only: click ``i`` (0-based) has label ``i + 1``; clicks not counted
        have no pixels.
    counted : (S,) bool
        The click outlined a protrusion (it is a row of the count).
    status : list of str
        ``"outlined"``, or why not: ``"bare paint"`` (no contrast in the albedo, or an outline not
        raised above the paint around it: the paint's own texture), ``"height only"`` (no contrast
        in the albedo, but a bump in the height) or ``"repeat"`` (inside an earlier click's outline).
    note : list of str
        The reason in words ("" for a counted click), without commas (a CSV cell ImageJ's
        ResultsTable reads as one).
    repeats : (S,) int
        For a repeat, the 1-based number of the earlier click; else 0.
    relief_ratio : (S,) float
        The outline's relief over its surroundings' spread (NaN where nothing was outlined).
    """

    labels: np.ndarray
    counted: np.ndarray
    status: list
    note: list
    repeats: np.ndarray
    relief_ratio: np.ndarray

    def summary(self, seeds) -> str:
        """``"7 clicks: 5 outlined, 2 not (bare paint at (412, 300) px; height only at (80, 95) px)"``."""
        seeds = np.asarray(seeds).reshape(-1, 2)
        n, k = len(self.counted), int(np.count_nonzero(self.counted))
        text = f"{n} click{'s' if n != 1 else ''}: {k} outlined"
        missed = [i for i in range(n) if not self.counted[i]]
        if missed:
            items = [(f"click {i + 1} repeats click {self.repeats[i]}" if self.status[i] == "repeat"
                      else self.status[i]) + f" at ({int(seeds[i][0])}, {int(seeds[i][1])}) px" for i in missed[:8]]
            more = f"; and {len(missed) - 8} more" if len(missed) > 8 else ""
            text += f", {len(missed)} not ({'; '.join(items)}{more})"
        return text


def _ring(labels, lab, sl, *, gap=0.0):
    """The outline ``labels == lab`` (bounding box ``sl``) and the ring around it, clear of other labels, on a
    crop of the map: ``(box, inside, ring)``, ``box`` the crop's slices. The ring is the outline's radius wide
    (at least 3 px), ``gap`` ring widths out from the outline."""
    m, n = labels.shape
    area = int(np.count_nonzero(labels[sl] == lab))
    radius = max(3.0, 0.5 * np.sqrt(area / np.pi))
    pad = int(np.ceil((1 + gap) * radius)) + 1
    box = (slice(max(sl[0].start - pad, 0), min(sl[0].stop + pad, m)),
           slice(max(sl[1].start - pad, 0), min(sl[1].stop + pad, n)))
    crop = labels[box]
    inside = crop == lab
    dist = ndi.distance_transform_edt(~inside)
    ring = (dist > gap * radius) & (dist <= (1 + gap) * radius) & (crop == 0)
    return box, inside, ring


def _relief_ratio(height, labels, lab, sl, *, gap=0.0):
    """The relief of ``labels == lab`` (bounding box ``sl``) over the spread of the ring around it,
    clear of other labels (see :data:`RAISED_RATIO`); 0 when the ring is too small to tell. ``gap``
    (in units of the ring's width) leaves the flanks of an outline drawn at half height out of the ring."""
    from .measure import _surround_plane

    box, inside, ring = _ring(labels, lab, sl, gap=gap)
    h = height[box]
    finite = np.isfinite(h)
    ring &= finite
    inside &= finite
    if ring.sum() < 8 or not inside.any():
        return 0.0
    ri, ci = np.nonzero(ring)
    plane = _surround_plane(ri, ci, h[ring])
    resid = h[ring] - plane(ri, ci)
    spread = 1.4826 * float(np.median(np.abs(resid - np.median(resid))))
    ii, jj = np.nonzero(inside)
    relief = float(np.percentile(h[inside] - plane(ii, jj), 90))
    if not spread > 0:
        return float("inf") if relief > 0 else 0.0
    return relief / spread


def _contrast_and_match(grey, height, labels, lab, sl, x, y, max_width_px):
    """The outline's albedo contrast over its ring's spread, and its IoU with the height's outline at the click."""
    box, inside, ring = _ring(labels, lab, sl)
    g = grey[box]
    ring &= np.isfinite(g)
    contrast = 0.0
    if ring.sum() >= 8:
        vals = g[ring]
        spread = 1.4826 * float(np.median(np.abs(vals - np.median(vals))))
        step = abs(float(np.nanmedian(g[inside])) - float(np.median(vals)))
        contrast = step / spread if spread > 0 else float("inf")
    iou = 0.0
    if height is not None and np.isfinite(height[y, x]):
        bump = contrast_select(height, [(x, y)], max_width_px=max_width_px) == 1
        # the outline lies in its box ``sl``: the intersection is counted there, not over the whole map
        both = int(np.count_nonzero(bump[sl] & (labels[sl] == lab)))
        either = int(np.count_nonzero(bump)) + int(np.count_nonzero(inside)) - both
        iou = float(both) / max(1, either)
    return contrast, iou


def judge_clicks(labels, seeds, *, height=None, albedo=None, max_width_px=None, min_ratio=RAISED_RATIO) -> WandClicks:
    """Decide which clicks of the wand outlined a protrusion: only those are counted.

    A click is counted when the wand outlined more than its own pixel around it (it had a contrast in
    the albedo), the outline is its own (not an earlier click's) and, with a ``height``, the outline
    stands above the paint around it (:data:`RAISED_RATIO`): a protrusion is raised, the outline of
    the paint's own texture or of a bare primer spot is not. With the ``albedo`` too, a raised
    outline must also be a clear step in the albedo (:data:`CLEAR_CONTRAST`) or agree with the bump
    in the height at the click (:data:`MATCH_IOU`): the paint's texture outlined over a bump that
    shows in the height alone is not counted. A click without contrast in the albedo
    is "height only" when the height shows a raised bump there (outlined on the height as
    :func:`contrast_select` does on the albedo), else "bare paint".

    Parameters
    ----------
    labels : (M, N) int
        The wand's labels (:func:`contrast_select` or :func:`wand_select`): click ``i`` has ``i + 1``.
    seeds : (S, 2) array_like
        The clicks ``(x_px, y_px)``.
    height : (M, N) array, optional
        The height map (micrometres, or relative: only ratios are used).
    albedo : (M, N) or (M, N, 3) array, optional
        The image the wand outlined on (RGB: the mean of R, G, B).
    max_width_px : float, optional
        The widest protrusion, for outlining a bump in the height.
    min_ratio : float
        :data:`RAISED_RATIO`.

    Returns
    -------
    WandClicks
    """
    labels = np.asarray(labels)
    pts = _as_seed_array(seeds, "seeds")
    h = None if height is None else np.asarray(height, dtype=np.float64)
    grey = None if albedo is None else np.asarray(albedo, dtype=np.float64)
    if grey is not None and grey.ndim == 3:
        grey = grey.mean(axis=2)
    n = len(pts)
    out = np.zeros(labels.shape, np.int32)
    counted = np.zeros(n, bool)
    status, note = [""] * n, [""] * n
    repeats = np.zeros(n, np.int64)
    ratio = np.full(n, np.nan)
    area = np.bincount(labels.ravel(), minlength=n + 1)
    slices = ndi.find_objects(labels)
    for i, (x, y) in enumerate(pts):
        lab = int(labels[y, x])
        if lab and lab != i + 1:
            status[i], repeats[i] = "repeat", lab
            note[i] = f"inside the outline of click {lab}: not counted again"
            continue
        if not lab or area[lab] <= 1:
            status[i] = "bare paint"
            note[i] = "no contrast in the albedo: nothing outlined"
            if h is not None and np.isfinite(h[y, x]):
                bump = contrast_select(h, [(x, y)], max_width_px=max_width_px)
                box = ndi.find_objects(bump)[0]
                if np.count_nonzero(bump[box]) > 1 and _relief_ratio(h, bump, 1, box, gap=2.0) >= min_ratio:
                    status[i] = "height only"
                    note[i] = ("no contrast in the albedo the wand outlines on: a bump in the height only "
                               "(the manual count is of the albedo)")
            continue
        sl = slices[lab - 1]
        if h is not None:
            ratio[i] = _relief_ratio(h, labels, lab, sl)
            if not ratio[i] >= min_ratio:
                status[i] = "bare paint"
                note[i] = (f"the albedo outline ({int(area[lab])} px) is not raised above the paint around it "
                           f"(relief {ratio[i]:.1f} x its spread; below {min_ratio:g}): the paint's texture")
                continue
            if grey is not None:
                contrast, iou = _contrast_and_match(grey, h, labels, lab, sl, x, y, max_width_px)
                if contrast < CLEAR_CONTRAST and iou < MATCH_IOU:
                    status[i] = "height only"
                    note[i] = (f"the albedo outline ({int(area[lab])} px) is faint ({contrast:.1f} x the paint's "
                               f"spread) and does not match the bump in the height (overlap {iou:.2f}): the bump "
                               "shows in the height only; if it is a protrusion click its brightest part or use "
                               "method imagej with a tolerance")
                    continue
        status[i], counted[i] = "outlined", True
        out[sl][labels[sl] == lab] = lab
    return WandClicks(out, counted, status, note, repeats, ratio)


def _as_seed_array(arr, name: str) -> np.ndarray:
    a = np.asarray(arr, dtype=float)
    if a.size == 0:
        return np.zeros((0, 2), np.int64)
    if a.ndim != 2 or a.shape[1] != 2:
        raise UVPSInputError(f"`{name}` must be (S, 2) as (x_px, y_px); got shape {a.shape}")
    if not np.isfinite(a).all():
        raise UVPSInputError(f"`{name}` must be finite (x_px, y_px) coordinates; got NaN or inf")
    return np.floor(a).astype(np.int64)


def _is_number(text: str) -> bool:
    try:
        float(text)
    except ValueError:
        return False
    return True


#: Micrometres per unit of the coordinates a seeds file's header can name (``x_um``, ``x_mm``).
SEED_UNITS_UM = {"um": 1.0, "mm": 1000.0}

#: Header columns (x, y) and the unit they name; ``""``: not said (ImageJ's ``X``, ``Y``).
_SEED_COLUMNS = ((("x_px", "y_px"), "px"), (("x_um", "y_um"), "um"), (("x_mm", "y_mm"), "mm"),
                 (("x", "y"), ""))


@dataclass
class SeedFile:
    """Clicks read by :func:`read_seed_file`.

    Attributes
    ----------
    seeds : (S, 2) int64
        ``(x_px, y_px)`` floored to the containing pixel.
    unit : str
        What the coordinates were read as: ``px``, ``um`` or ``mm``.
    said : bool
        Whether the file's header named that unit (else the ``units`` argument decided).
    """

    seeds: np.ndarray
    unit: str
    said: bool


def _seed_table(path: Path):
    """The (S, 2) float coordinates of a seeds file and the unit its header names ("" if none)."""
    try:
        with open(path, newline="", encoding="utf-8-sig") as fh:
            text = fh.read()
    except (OSError, UnicodeDecodeError) as exc:
        raise UVPSInputError(f"cannot read seeds file {path}: {getattr(exc, 'strerror', None) or exc}") from None
    delim = "\t" if "\t" in text.split("\n", 1)[0] else ","
    rows = list(csv.reader(text.splitlines(), delimiter=delim))
    if not rows:
        raise UVPSInputError(f"seeds file {path} is empty; expected a header with x_px,y_px or X,Y")
    header = [h.strip() for h in rows[0]]
    if len(header) == 2 and all(_is_number(h) for h in header):
        # ImageJ's headerless "XY Coordinates" text: x <TAB> y per line
        header = ["X", "Y"]
        rows = [header] + rows
    lower = [h.lower() for h in header]
    for (cx, cy), unit in _SEED_COLUMNS:
        if cx in lower and cy in lower:
            ix, iy = lower.index(cx), lower.index(cy)
            break
    else:
        raise UVPSInputError(f"seeds file {path}: header must contain x_px,y_px (or x_um,y_um, x_mm,y_mm, "
                             f"X,Y); got {','.join(header)}")
    pts = []
    for k, row in enumerate(rows[1:], start=2):
        if not any(c.strip() for c in row):
            continue
        try:
            pts.append((float(row[ix]), float(row[iy])))
        except (ValueError, IndexError):
            raise UVPSInputError(f"seeds file {path} line {k}: expected numbers in columns "
                                 f"{header[ix]},{header[iy]}; got {','.join(row)}") from None
    return np.array(pts, float).reshape(-1, 2), unit


def read_seed_file(path: Union[str, Path], *, pixel_size_um=None, units: str = "auto",
                   shape=None) -> SeedFile:
    """Read wand clicks from a CSV file, in the units its header names.

    Parameters
    ----------
    path : str or Path
        A CSV (comma or tab separated) whose header has ``x_px``, ``y_px`` (pixels), ``x_um``,
        ``y_um`` (micrometres) or ``x_mm``, ``y_mm`` (millimetres) columns, or ``X``, ``Y`` as in
        ImageJ's Results of Measure on a point selection (pixels on an uncalibrated image, the
        calibrated unit on a calibrated one), or headerless two-column ``x y`` lines (File > Save
        As > XY Coordinates: pixels).
    pixel_size_um : float, optional
        Needed for coordinates in um or mm: they are divided by it.
    units : {"auto", "px", "um"}
        The unit of a header that names none (``X``, ``Y``): pixels, micrometres, or ``auto``:
        pixels unless some click lies outside an image of ``shape`` in pixels while all lie
        inside it in micrometres (Measure on the calibrated albedo). A header that names its
        unit is read in that unit.
    shape : (M, N), optional
        The image the clicks are on (for ``auto``).
    """
    if units not in ("auto", "px", "um"):
        raise UVPSInputError(f"units must be auto, px or um; got {units!r}")
    path = Path(path)
    xy, unit = _seed_table(path)
    said = bool(unit)
    if not said:
        unit = "px" if units == "auto" else units
        if units == "auto" and shape is not None and pixel_size_um and len(xy):
            def inside(a):
                return bool(np.all((a >= 0) & (a < np.array([shape[1], shape[0]]))))
            if not inside(xy) and inside(xy / pixel_size_um):
                unit = "um"
    if unit in SEED_UNITS_UM:
        if not pixel_size_um:
            raise UVPSInputError(f"seeds file {path} gives its clicks in {unit}; a pixel size is needed to "
                                 "turn them into pixels (give pixel_size_um)")
        xy = xy * (SEED_UNITS_UM[unit] / float(pixel_size_um))
    return SeedFile(_as_seed_array(xy, f"seeds file {path}"), unit, said)


def read_seeds(path_or_array: Union[str, Path, np.ndarray, list], *, pixel_size_um=None,
               units: str = "auto", shape=None) -> np.ndarray:
    """Read wand clicks from a CSV file (:func:`read_seed_file`) or pass an array through.

    Parameters
    ----------
    path_or_array : path or (S, 2) array_like
        A seeds file, or an (S, 2) array of ``(x_px, y_px)``.
    pixel_size_um, units, shape
        See :func:`read_seed_file`.

    Returns
    -------
    seeds : (S, 2) int64
        ``(x_px, y_px)`` floored to the containing pixel.
    """
    if isinstance(path_or_array, (str, Path)):
        return read_seed_file(path_or_array, pixel_size_um=pixel_size_um, units=units,
                              shape=shape).seeds
    return _as_seed_array(path_or_array, "seeds")

