"""The painting-wide maps of a mosaic: albedo, normals, height and labels, chunk by chunk on Dask.

Each map is a Dask array over the painting (pixel (0, 0) at the refined layout's smallest corner)
whose every chunk is computed from the tiles that cover it only, reading just their windows
(memory-mapped TIFFs of the tiles' run folders), so neither the painting nor a whole level is ever
in memory; the chunks are written into OME-Zarr stores (:func:`uvps.files.omezarr.write_dask_ome_zarr`)
by the cluster's workers. A tile is placed at its registered corner, sub-pixel (bilinear
interpolation; labels: nearest pixel), and the overlaps are feathered: each tile weighted by
1 + its pixel's distance to the tile's nearest edge. The albedo is divided by the tile's gain
(its exposure relative to the others), the height takes the tile's offset, plane and form
(:func:`uvps.core.mosaic.align_rig_heights`: what levelling removed, less the tiles' shared error), the normals are renormalised after blending. Labels are
not blended: each pixel takes the label of the tile it is most central in, the protrusion labels
renumbered to the painting's ids (a duplicate of an overlap takes the id of the copy kept), the
colour areas from the painting's overview.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Optional

import numpy as np
from scipy import ndimage

from .core.level import legendre_uv
from .core.mosaic import PLANE_SCALE_PX
from .files.omezarr import open_tiff


@dataclass
class PlacedTile:
    """A tile as the maps need it: its run folder, corner (painting pixels from the origin), shape,
    gain, height plane ``(a, b, c)`` (painting pixels), height form (Legendre coefficients in the tile's
    frame, :mod:`uvps.core.level`, added to its ``depth.tif``; None: none) and protrusion-label lookup
    (tile id -> painting id)."""

    name: str
    run_dir: str
    x: float
    y: float
    shape: tuple
    gain: float = 1.0
    plane: tuple = (0.0, 0.0, 0.0)
    lut: Optional[np.ndarray] = None
    form: Optional[np.ndarray] = None


@dataclass
class MapContext:
    """Everything a chunk needs (pickled to the workers once per task)."""

    tiles: list
    origin: tuple                 # (x, y) of painting pixel (0, 0) in the layout's frame
    shape: tuple                  # (rows, cols)
    regions: Optional[np.ndarray] = None   # the overview's colour-area labels
    step: int = 1
    channels: int = 3


#: Each map's TIFF in a tile's run folder and how it is placed.
SOURCES = {"albedo": "albedo.tif", "normals": "normals.tif", "height": "depth.tif",
           "protrusions": "protrusions_labels.tif"}


def render_chunk(kind: str, ctx: MapContext, r0: int, r1: int, c0: int, c1: int) -> np.ndarray:
    """One chunk ``[r0:r1, c0:c1]`` of a painting map (``kind`` one of :data:`SOURCES` or ``"regions"``)."""
    R, C = r1 - r0, c1 - c0
    rows = np.arange(r0, r1, dtype=np.float64)[:, None]
    cols = np.arange(c0, c1, dtype=np.float64)[None, :]
    label = kind in ("protrusions", "regions")
    nch = ctx.channels if kind == "albedo" else 3 if kind == "normals" else 1
    acc = np.zeros((nch, R, C))
    wsum = np.zeros((R, C))
    best = np.zeros((R, C))
    out_label = np.zeros((R, C), np.uint32)
    for t in ctx.tiles:
        M, N = t.shape
        # the chunk's box this tile can cover (a pixel wider than where its weight is >= 1): the
        # work of a tile is its part of the chunk, not the whole chunk for every tile that touches it
        i0, i1 = max(r0, int(np.floor(t.y))), min(r1, int(np.ceil(t.y + M - 1)) + 1)
        j0, j1 = max(c0, int(np.floor(t.x))), min(c1, int(np.ceil(t.x + N - 1)) + 1)
        if i0 >= i1 or j0 >= j1:
            continue
        box = (slice(i0 - r0, i1 - r0), slice(j0 - c0, j1 - c0))
        brows, bcols = rows[box[0]], cols[:, box[1]]
        ty, tx = brows - t.y, bcols - t.x
        w = 1.0 + np.minimum(np.minimum(ty, M - 1 - ty), np.minimum(tx, N - 1 - tx))
        w = np.where(w >= 1.0, w, 0.0) * np.ones((i1 - i0, j1 - j0))
        if not w.any():
            continue
        if kind == "regions":
            wsum[box] += w
            continue
        win, rr, cc = _tile_window(kind, t, (i0, i1, j0, j1), ty, tx)
        if label:
            vals = ndimage.map_coordinates(win[0], [rr, cc], order=0, mode="nearest").astype(np.int64)
            vals = t.lut[np.clip(vals, 0, len(t.lut) - 1)] if t.lut is not None else vals
            take = w > best[box]
            out_label[box][take] = vals[take]
            best[box] = np.maximum(best[box], w)
            continue
        for ch in range(min(nch, win.shape[0])):
            v = ndimage.map_coordinates(win[ch], [rr, cc], order=1, mode="nearest")
            if kind == "albedo":
                v = v / t.gain
            elif kind == "height":
                a, b, c = t.plane
                v = v + a + b * (bcols + ctx.origin[0]) / PLANE_SCALE_PX + c * (brows + ctx.origin[1]) / PLANE_SCALE_PX
                if t.form is not None:
                    v = v + _form(t.form, ty, tx, t.shape)
            acc[ch][box] += np.nan_to_num(v) * w
        wsum[box] += w
    if kind == "protrusions":
        return out_label
    return _finish_chunk(kind, ctx, acc, wsum, (r0, r1, c0, c1))


def _form(coeffs, ty, tx, shape) -> np.ndarray:
    """The Legendre surface ``coeffs`` of a tile of ``shape`` (:mod:`uvps.core.level`'s variables) at its
    rows ``ty`` (column vector) and columns ``tx`` (row vector), separably."""
    from numpy.polynomial import legendre

    degree = coeffs.shape[0] - 1
    u, v = legendre_uv(np.ravel(ty), np.ravel(tx), shape)
    return legendre.legvander(v, degree) @ np.asarray(coeffs).T @ legendre.legvander(u, degree).T


def _tile_window(kind: str, t: PlacedTile, box, ty, tx):
    """The window of tile ``t``'s map ``kind`` under the chunk's box ``(i0, i1, j0, j1)`` it covers
    (one pixel more each side for the interpolation), read from its run folder, as (channels, rows,
    cols) float64, and the box's pixels in the window's coordinates (``ty``, ``tx``: in the tile's)."""
    i0, i1, j0, j1 = box
    M, N = t.shape
    wr0, wc0 = max(0, int(np.floor(i0 - t.y)) - 1), max(0, int(np.floor(j0 - t.x)) - 1)
    wr1, wc1 = min(M, int(np.ceil(i1 - t.y)) + 2), min(N, int(np.ceil(j1 - t.x)) + 2)
    data = open_tiff(Path(t.run_dir) / SOURCES[kind])
    win = np.asarray(data[..., wr0:wr1, wc0:wc1], np.float64)
    if win.ndim == 2:
        win = win[None]
    shape = (i1 - i0, j1 - j0)
    rr = np.broadcast_to(ty - wr0, shape)
    cc = np.broadcast_to(tx - wc0, shape)
    return win, rr, cc


def _finish_chunk(kind: str, ctx: MapContext, acc, wsum, chunk) -> np.ndarray:
    """A blended chunk from the tiles' weighted sums: the colour areas (the overview's labels,
    ``ctx.step`` px a pixel) where a tile covers it, or the weighted mean (normals renormalised),
    0 (albedo) or NaN where no tile does."""
    r0, r1, c0, c1 = chunk
    covered = wsum > 0
    if kind == "regions":
        lab = ctx.regions
        ri = np.clip((np.arange(r0, r1) // ctx.step), 0, lab.shape[0] - 1)
        ci = np.clip((np.arange(c0, c1) // ctx.step), 0, lab.shape[1] - 1)
        out = lab[np.ix_(ri, ci)].astype(np.uint32)
        out[~covered] = 0
        return out
    with np.errstate(invalid="ignore", divide="ignore"):
        out = (acc / wsum).astype(np.float32)
    if kind == "normals":
        norm = np.sqrt((out ** 2).sum(axis=0))
        out = out / np.where(norm > 0, norm, 1)
    out[:, ~covered] = 0.0 if kind == "albedo" else np.nan
    return out if kind in ("albedo", "normals") else out[0]


def painting_array(kind: str, ctx: MapContext, *, chunk_px: int):
    """The painting map ``kind`` as a lazy Dask array (chunks of ``chunk_px`` a side)."""
    import dask.array as da

    M, N = ctx.shape
    nch = ctx.channels if kind == "albedo" else 3 if kind == "normals" else 0
    dtype = np.uint32 if kind in ("protrusions", "regions") else np.float32
    lead = (nch,) if nch else ()
    template = da.zeros(lead + (M, N), chunks=lead + (chunk_px, chunk_px), dtype=dtype)

    def block(_, block_info=None):
        loc = block_info[None]["array-location"]
        return render_chunk(kind, ctx, loc[-2][0], loc[-2][1], loc[-1][0], loc[-1][1])

    return template.map_blocks(block, dtype=dtype)
