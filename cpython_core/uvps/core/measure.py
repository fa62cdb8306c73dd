"""Per-protrusion measurements: position, width, area, height above the surround, crater, colour.

One row per protrusion of an int32 label image (0 = background), written as ``protrusions.csv``
(columns :data:`COLUMNS`, in that order) beside the label TIFF ``protrusions_labels.tif``.

Frames and units follow ``docs/architecture.md``: ``x_px`` is the column and ``y_px`` the row of
the centroid (as ImageJ reports them), widths and heights in micrometres, areas in um^2.
"""
from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import Mapping, Optional

import numpy as np
from scipy import ndimage as ndi
from skimage.measure import regionprops_table

from ..errors import UVPSInputError, check_pixel_size

log = logging.getLogger(__name__)

#: Columns of protrusions.csv, in order.
COLUMNS = ("id", "x_px", "y_px", "width_um", "area_um2", "height_um", "crater",
           "r", "g", "b", "region", "source")
#: The column that replaces ``height_um`` in a run whose relief has no scale (run.json ``relief``
#: "relative": lamps estimated from images that do not pin their elevation): the same measure, no unit.
RELATIVE_HEIGHT = "relative_height"
_INT_COLUMNS = ("id", "crater", "region")
_STR_COLUMNS = ("source",)


@dataclass
class MeasureOptions:
    """Options of :func:`measure_protrusions`.

    Attributes
    ----------
    ring_factor : float
        Width of the surround ring, as a fraction of the protrusion width (the paper's
        protrusions sit on a flat-ish paint layer; 0.5 x width reaches clear of the slope).
    crater_fraction : float
        A crater needs its centre at least this fraction of the relief below the rim.
    crater_min_depth_um : float
        ... and at least this many micrometres below it (noise on low protrusions).
    crater_min_width_px : float
        Protrusions narrower than this (in pixels) are too small to resolve a crater: crater = 0.
    """

    ring_factor: float = 0.5
    crater_fraction: float = 0.10
    crater_min_depth_um: float = 1.0
    crater_min_width_px: float = 8.0


def empty_table() -> dict:
    """A protrusion table with no rows (the columns of :data:`COLUMNS`)."""
    return {c: np.zeros(0, dtype=_dtype(c)) for c in COLUMNS}


def _dtype(column):
    if column in _INT_COLUMNS:
        return np.int64
    if column in _STR_COLUMNS:
        return object
    return np.float64


def albedo_rgb(albedo: np.ndarray, shape) -> np.ndarray:
    """Return the albedo as ``(M, N, 3)`` float64 from ``(M, N)``, ``(3, M, N)`` or ``(M, N, 3)``.

    A grey albedo is repeated in the three channels, so grey gives r == g == b.
    """
    albedo = np.asarray(albedo)
    shape = tuple(shape)
    if albedo.shape == shape:
        return np.repeat(albedo[..., None].astype(np.float64), 3, axis=-1)
    if albedo.ndim == 3 and albedo.shape[1:] == shape and albedo.shape[0] == 3:
        return np.moveaxis(albedo, 0, -1).astype(np.float64)
    if albedo.ndim == 3 and albedo.shape[:2] == shape and albedo.shape[2] == 3:
        return albedo.astype(np.float64)
    raise UVPSInputError(f"albedo must be (M, N), (3, M, N) or (M, N, 3) with (M, N) == {shape}; "
                         f"got {albedo.shape}")


def _check_labels(labels) -> np.ndarray:
    labels = np.asarray(labels)
    if labels.ndim != 2 or not np.issubdtype(labels.dtype, np.integer):
        raise UVPSInputError(f"labels must be a 2-D integer label image; got {labels.ndim}-D "
                             f"{labels.dtype}")
    if labels.size and labels.min() < 0:
        raise UVPSInputError(f"labels must be >= 0 (0 = background); got minimum {labels.min()}")
    return labels


def _sources(source, ids: np.ndarray) -> np.ndarray:
    """Source per label id from None, one string, a mapping id -> str or a sequence (one per id)."""
    out = np.empty(len(ids), dtype=object)
    if source is None or isinstance(source, str):
        out[:] = source or ""
        return out
    if isinstance(source, Mapping):
        for i, lab in enumerate(ids):
            out[i] = str(source.get(int(lab), ""))
        return out
    source = list(source)
    if len(source) != len(ids):
        raise UVPSInputError(f"source must have one entry per label ({len(ids)} labels); "
                             f"got {len(source)}")
    out[:] = [str(s) for s in source]
    return out


def _region_at(regions, rows, cols, shape) -> np.ndarray:
    """Colour-area label at each rounded centroid (0 = none)."""
    if regions is None:
        return np.zeros(len(rows), dtype=np.int64)
    reg = np.asarray(getattr(regions, "labels", regions))
    if reg.shape != tuple(shape):
        raise UVPSInputError(f"regions must have the labels' shape {tuple(shape)}; got {reg.shape}")
    r = np.clip(np.rint(rows).astype(int), 0, shape[0] - 1)
    c = np.clip(np.rint(cols).astype(int), 0, shape[1] - 1)
    return reg[r, c].astype(np.int64)


def _surround_plane(rows, cols, values):
    """Least-squares plane ``a + b*row + c*col`` through the surround ring (a callable).

    Falls back to the median (a constant) when the ring is too small or degenerate to fit a
    plane (fewer than 8 pixels, or all in one line)."""
    med = float(np.median(values))
    if len(values) >= 8:
        A = np.column_stack([np.ones(len(values)), rows, cols])
        coef, _, rank, _ = np.linalg.lstsq(A, values, rcond=None)
        if rank == 3:
            return lambda r, c: coef[0] + coef[1] * r + coef[2] * c
    return lambda r, c: np.full(np.shape(r), med)


def _height_and_crater(labels, height, ids, widths_px, opts: MeasureOptions):
    """Peak height above the surround, and the crater flag, per label.

    Hand-written because no library measures a local relief: for each protrusion the ring is the
    background pixels (label 0, finite height) within ``ring_factor * width`` of its outline (a
    Euclidean distance transform on a padded crop). A least-squares plane through the ring (its
    median when the ring is too small) is the local surface, so the canvas weave or bow under a
    protrusion does not bias it. The relief is the highest point inside above that plane.

    Crater (the paper's caldera-like craters): with heights taken above the surround plane, the
    body is the part of the label raised by at least 20 % of the relief (a label outline from the
    albedo may reach past the relief), its centre the relief-weighted centroid (for a ring-shaped
    rim still the crater's middle), the centre height the median within 0.2 x the body's
    equivalent radius (at least 1 px) of that centre, and the rim height the body's 98th
    percentile (a robust maximum). Crater = 1 when the centre lies below the rim by at least
    ``crater_fraction`` of the relief and by ``crater_min_depth_um``. A dome peaks at its centre,
    so it never qualifies; neither does a tilted surround (removed by the plane) nor noise below
    those thresholds.
    """
    n = len(ids)
    rel = np.full(n, np.nan)
    crater = np.zeros(n, dtype=np.int64)
    slices = ndi.find_objects(labels)
    M, N = labels.shape
    for i, lab in enumerate(ids):
        sl = slices[lab - 1]
        ring_px = max(2.0, opts.ring_factor * widths_px[i])
        pad = int(np.ceil(ring_px)) + 1
        r0, r1 = max(sl[0].start - pad, 0), min(sl[0].stop + pad, M)
        c0, c1 = max(sl[1].start - pad, 0), min(sl[1].stop + pad, N)
        lab_crop = labels[r0:r1, c0:c1]
        h_crop = height[r0:r1, c0:c1]
        finite = np.isfinite(h_crop)
        inside = (lab_crop == lab) & finite
        if not inside.any():
            continue
        dist_out = ndi.distance_transform_edt(lab_crop != lab)
        ring = (dist_out > 0) & (dist_out <= ring_px) & (lab_crop == 0) & finite
        if not ring.any():
            log.debug("label %d: no free surround ring; height left NaN", lab)
            continue
        rr, cc = np.nonzero(ring)
        plane = _surround_plane(rr, cc, h_crop[ring])
        ri, ci = np.nonzero(inside)
        above = h_crop[inside] - plane(ri, ci)
        rel[i] = float(above.max())
        if widths_px[i] < opts.crater_min_width_px or rel[i] <= 0:
            continue
        body = above >= 0.2 * rel[i]  # the raised body (a label may reach past it)
        wts = above[body]
        cr, cc_ = np.average(ri[body], weights=wts), np.average(ci[body], weights=wts)
        radius = max(1.0, 0.2 * np.sqrt(body.sum() / np.pi))
        core = body & ((ri - cr) ** 2 + (ci - cc_) ** 2 <= radius**2)
        if not core.any():
            continue
        rim_h = float(np.percentile(above[body], 98))
        centre_h = float(np.median(above[core]))
        depth = rim_h - centre_h
        if depth >= opts.crater_fraction * rel[i] and depth >= opts.crater_min_depth_um:
            crater[i] = 1
    return rel, crater


def measure_protrusions(labels, *, albedo, height_um, pixel_size_um: float, regions=None,
                        source=None, options: Optional[MeasureOptions] = None) -> dict:
    """Measure every labelled protrusion.

    Parameters
    ----------
    labels : (M, N) integer ndarray
        Protrusion labels, 0 = background (e.g. ``Detection.labels`` or the wand's labels).
    albedo : (M, N), (3, M, N) or (M, N, 3) ndarray
        Albedo (grey or RGB); the table's r, g, b are the mean albedo per protrusion.
    height_um : (M, N) ndarray
        Height map in micrometres (``depth.tif``); NaN pixels are ignored.
    pixel_size_um : float
        Pixel size in micrometres.
    regions : RegionMap or (M, N) integer ndarray, optional
        Colour areas; the region column is the area at the rounded centroid (0 = none).
    source : str, mapping label -> str, or sequence (one per label in increasing order), optional
        How each protrusion was found ("albedo", "height", "albedo+height", "wand" ...).
    options : MeasureOptions, optional
        Surround ring and crater criterion.

    Returns
    -------
    table : dict of str -> ndarray
        Columns :data:`COLUMNS`, one row per label in increasing label order: ``id`` (the label),
        ``x_px``/``y_px`` centroid (column/row), ``width_um`` equivalent-circle diameter,
        ``area_um2``, ``height_um`` peak height above the local surface (a plane through the
        ring of ``ring_factor x width`` around the protrusion; NaN if no free surround),
        ``crater`` (0/1), ``r``, ``g``, ``b``, ``region``, ``source``.

    Examples
    --------
    >>> import numpy as np
    >>> labels = np.zeros((40, 40), np.int32)
    >>> rr, cc = np.mgrid[:40, :40]
    >>> labels[(rr - 20) ** 2 + (cc - 15) ** 2 <= 64] = 1
    >>> t = measure_protrusions(labels, albedo=np.ones((40, 40)), height_um=10.0 * (labels > 0),
    ...                         pixel_size_um=15.0)
    >>> float(t["x_px"][0]), float(t["y_px"][0]), float(t["height_um"][0])
    (15.0, 20.0, 10.0)

    Notes
    -----
    Geometry and colour come from :func:`skimage.measure.regionprops_table`. The paper (Salvant
    et al., "Protrusion detection", Fig. 4a) bins protrusions by width; the equivalent-circle
    diameter is the width of a round protrusion and a fair one of an irregular outline.
    """
    labels = _check_labels(labels)
    opts = options or MeasureOptions()
    pixel_size_um = check_pixel_size(pixel_size_um)
    height = np.asarray(height_um, dtype=np.float64)
    if height.shape != labels.shape:
        raise UVPSInputError(f"height_um must have the labels' shape {labels.shape}; "
                             f"got {height.shape}")
    rgb = albedo_rgb(albedo, labels.shape)
    if not labels.any():
        return empty_table()
    props = regionprops_table(labels, intensity_image=rgb,
                              properties=("label", "centroid", "area",
                                          "equivalent_diameter_area", "intensity_mean"))
    ids = props["label"].astype(np.int64)
    widths_px = props["equivalent_diameter_area"].astype(np.float64)
    rel, crater = _height_and_crater(labels, height, ids, widths_px, opts)
    px = float(pixel_size_um)
    table = {
        "id": ids,
        "x_px": props["centroid-1"].astype(np.float64),
        "y_px": props["centroid-0"].astype(np.float64),
        "width_um": widths_px * px,
        "area_um2": props["area"].astype(np.float64) * px * px,
        "height_um": rel,
        "crater": crater,
        "r": props["intensity_mean-0"].astype(np.float64),
        "g": props["intensity_mean-1"].astype(np.float64),
        "b": props["intensity_mean-2"].astype(np.float64),
        "region": _region_at(regions, props["centroid-0"], props["centroid-1"], labels.shape),
        "source": _sources(source, ids),
    }
    log.info("measured %d protrusions", len(ids))
    return table
