"""The painting of a mosaic batch: its tiles registered, one set of counts, written to ``OUT/painting/``.

After ``uvps batch --mosaic LAYOUT`` has run every tile, :func:`stitch_painting`

1. registers the tiles on their albedo (:func:`uvps.core.mosaic.register_tiles`: pairwise phase
   correlation of the overlaps, one global least squares that drops inconsistent pairs), from the
   layout's nominal corners to refined ones: the pairs' shifts as tasks of the current ``distributed``
   client when there is one (the batch's cluster), each reading its two overlap windows from the run
   folders; the least squares in this process;
2. evens out the tiles' exposures (one gain per tile, from the overlaps' albedo ratios, one least
   squares over the log-gains) and blends their albedo into an overview of the painting (feathered:
   each tile weighted by its pixels' distance to its edge);
3. takes the colour areas from that overview (``regions="auto"``: proposed once for the painting,
   so an area is the same paint in every tile) or from a painting-wide label TIFF in the layout's
   frame;
4. merges the tiles' protrusion tables in painting pixels (each protrusion of an overlap once: the
   detection farther from its tile's edge kept) and counts them per area.

Everything is written into a temporary folder and swapped into ``OUT/painting/`` at the end, so
``OUT/painting/`` is at every moment all old or all new. See docs/painting.md.
"""
from __future__ import annotations

import contextlib
import contextvars
import csv
import logging
import math
import sys
import time
from concurrent.futures import ThreadPoolExecutor
from concurrent.futures import wait as futures_wait
from dataclasses import dataclass
from io import StringIO
from pathlib import Path
from typing import Optional

import numpy as np

from .core.measure import COLUMNS
from .core.mosaic import (Registration, align_heights, align_rig_heights, intensity_tilts, overlap_box,
                          register_tiles)
from .core.regions import UM2_PER_CM2, _as_label_image, propose_regions
from .errors import UVPSInputError
from .files.omezarr import (CHUNK_PX, LABELS, StoreBatch, ZarrImage, open_tiff, write_dask_ome_labels,
                            write_dask_ome_zarr)
from .files.outputs import new_output_dir, report, write_json_atomic
from .files.paintingfolder import (PAINTING_DIR, PAINTING_LABELS, PAINTING_LAYOUT,  # noqa: F401 - re-exported
                                  PAINTING_PROTRUSIONS, PAINTING_REGIONS)
from .files.tables import _names_beside, atomic_write_text, read_protrusions_csv, write_label_tiff
from .painting_maps import MapContext, PlacedTile, painting_array

log = logging.getLogger(__name__)

#: Largest overview the colour areas are proposed on (pixels); a larger painting is block-averaged.
OVERVIEW_MAX_PX = 4_000_000


@dataclass
class PaintingResult:
    """What :func:`stitch_painting` did (JSON-ready through :meth:`as_dict`)."""

    registration: Registration
    gains: dict
    origin: tuple
    shape: tuple
    n_protrusions: int
    tile_protrusions: int
    areas: dict
    pixel_size_um: float
    overview_step: int
    warnings: list
    heights: Optional[dict] = None
    timings: Optional[dict] = None

    def as_dict(self) -> dict:
        return {
            "tiles": len(self.registration.corners), "tile_protrusions": self.tile_protrusions,
            "duplicates_removed": self.tile_protrusions - self.n_protrusions, "n_protrusions": self.n_protrusions,
            "pixel_size_um": self.pixel_size_um, "origin_px": list(self.origin), "shape_px": list(self.shape),
            "overview_step": self.overview_step,
            "corners": {k: [round(v[0], 3), round(v[1], 3)] for k, v in self.registration.corners.items()},
            "gains": {k: round(v, 5) for k, v in self.gains.items()},
            "pairs": [{"a": p.a, "b": p.b, "dx_px": round(p.dx, 3), "dy_px": round(p.dy, 3),
                       "confidence": round(p.confidence, 4), "overlap_px": p.overlap_px, "used": p.used,
                       "residual_px": None if p.residual_px is None else round(p.residual_px, 3),
                       "why_not_used": p.why or None} for p in self.registration.pairs],
            "max_residual_px": round(self.registration.max_residual_px, 3),
            "height_alignment": self.heights, "timings": self.timings, "areas": self.areas}


def _channels_last(a: np.ndarray) -> np.ndarray:
    a = np.asarray(a)
    return np.moveaxis(a, 0, -1) if a.ndim == 3 and a.shape[0] in (3, 4) and a.shape[-1] not in (3, 4) else a


class AlbedoTile:
    """A tile's ``albedo.tif`` on disk (memory-mapped): read window by window, or whole for one
    tile at a time; never all tiles at once."""

    def __init__(self, run_dir: Path):
        path = Path(run_dir) / "albedo.tif"
        if not path.is_file():
            raise UVPSInputError(f"mosaic: tile {Path(run_dir).name} has no albedo.tif to register on")
        self.path = path
        data = self._data()
        self.channels = data.shape[0] if data.ndim == 3 else 1
        self.shape = tuple(data.shape[-2:])

    def _data(self):
        return open_tiff(self.path)

    def window(self, r0: int, r1: int, c0: int, c1: int) -> np.ndarray:
        """Grey (mean of the channels) float64 of rows r0:r1, columns c0:c1."""
        w = np.asarray(self._data()[..., r0:r1, c0:c1], np.float64)
        return w.mean(axis=0) if w.ndim == 3 else w

    def full(self) -> np.ndarray:
        """(M, N) or (M, N, C) float32."""
        return _channels_last(np.asarray(self._data())).astype(np.float32)


def _win(img, r0, r1, c0, c1) -> np.ndarray:
    if hasattr(img, "window"):
        return img.window(r0, r1, c0, c1)
    w = np.asarray(img[r0:r1, c0:c1], np.float64)
    return w.mean(axis=2) if w.ndim == 3 else w


def tile_gains(albedo: dict, reg: Registration) -> dict:
    """One gain per tile (mean of the logs zero) from the used pairs' median albedo ratio on their
    overlap: the exposure drift between tiles, so the blended albedo has no steps."""
    names = list(albedo)
    idx = {n: i for i, n in enumerate(names)}
    rows, rhs = [], []
    for p in reg.pairs:
        if not p.used:
            continue
        ca, cb = reg.corners[p.a], reg.corners[p.b]
        ra, rb = (round(ca[0]), round(ca[1])), (round(cb[0]), round(cb[1]))
        box = overlap_box(ra, albedo[p.a].shape[:2], rb, albedo[p.b].shape[:2])
        if box is None:
            continue
        x_lo, y_lo, x_hi, y_hi = box
        ga = _win(albedo[p.a], y_lo - ra[1], y_hi - ra[1], x_lo - ra[0], x_hi - ra[0])
        gb = _win(albedo[p.b], y_lo - rb[1], y_hi - rb[1], x_lo - rb[0], x_hi - rb[0])
        ok = (ga > 0) & (gb > 0) & np.isfinite(ga) & np.isfinite(gb)
        if ok.sum() < 100:
            continue
        row = np.zeros(len(names))
        row[idx[p.b]], row[idx[p.a]] = 1.0, -1.0
        rows.append(row)
        rhs.append(float(np.median(np.log(gb[ok] / ga[ok]))))
    rows.append(np.full(len(names), 1.0 / len(names)))
    rhs.append(0.0)
    sol, *_ = np.linalg.lstsq(np.array(rows), np.array(rhs), rcond=None)
    return {n: float(np.exp(sol[idx[n]])) for n in names}


def feather(shape) -> np.ndarray:
    """(M, N) blending weight of a tile: 1 + the pixel's distance to the tile's nearest edge."""
    M, N = shape
    r = np.minimum(np.arange(M), M - 1 - np.arange(M))[:, None]
    c = np.minimum(np.arange(N), N - 1 - np.arange(N))[None, :]
    return (1.0 + np.minimum(r, c)).astype(np.float32)


def blend_overview(albedo: dict, corners: dict, gains: dict, origin, shape, step: int):
    """Feathered blend of the tiles' albedo (divided by their gains) at 1/``step`` of full size.

    Returns ``(albedo (m, n[, C]) float32, covered (m, n) bool)``; a tile lands at its corner
    rounded to the overview's pixels (``step`` >= 1: at full size, within half a pixel).
    """
    import cv2

    m, n = -(-shape[0] // step), -(-shape[1] // step)
    acc = wsum = None
    for name, a in albedo.items():
        a = a.full() if hasattr(a, "full") else np.asarray(a)      # one tile at a time
        if acc is None:
            acc = np.zeros((m, n) + a.shape[2:], np.float64)
            wsum = np.zeros((m, n), np.float64)
        w = feather(a.shape[:2])
        a = np.nan_to_num(a / gains[name])
        if step > 1:
            size = (max(1, a.shape[1] // step), max(1, a.shape[0] // step))
            a = cv2.resize(a, size, interpolation=cv2.INTER_AREA)
            w = cv2.resize(w, size, interpolation=cv2.INTER_AREA)
        r0 = int(round((corners[name][1] - origin[1]) / step))
        c0 = int(round((corners[name][0] - origin[0]) / step))
        r1, c1 = min(m, r0 + a.shape[0]), min(n, c0 + a.shape[1])
        a, w = a[:r1 - r0, :c1 - c0], w[:r1 - r0, :c1 - c0]
        acc[r0:r1, c0:c1] += a * (w[..., None] if a.ndim == 3 else w)
        wsum[r0:r1, c0:c1] += w
    covered = wsum > 0
    with np.errstate(invalid="ignore", divide="ignore"):
        out = acc / (wsum[..., None] if acc.ndim == 3 else wsum)
    out[~covered] = 0
    return out.astype(np.float32), covered


def _edge_distance(shape, x, y):
    M, N = shape
    x, y = np.asarray(x, float), np.asarray(y, float)
    return np.minimum(np.minimum(x, N - 1 - x), np.minimum(y, M - 1 - y))


def merge_protrusions(tables: dict, corners: dict, shapes: dict, *, pixel_size_um: float,
                      tolerance_px: float = 2.0) -> tuple:
    """The tiles' protrusion tables merged in painting pixels, each protrusion of an overlap once.

    Two detections of two overlapping tiles are one protrusion when their painting centres lie
    closer than half the larger width or ``tolerance_px`` (a small one's centroid moves by a pixel
    or two between tiles: noise), or, when one of the two is cut by its tile's edge (closer to it
    than half its width), when their footprints overlap; matched closest first, one to one per pair
    of tiles; of each match the detection farther from its own tile's edge is kept (the other tile
    saw it nearer its border, where it may be cut). A protrusion in three or four tiles (a corner)
    is compared pairwise and the most central survives.

    Returns ``(rows kept, rows of every tile)``: each row a dict of the tile table's columns plus
    ``tile``, ``X``, ``Y`` (painting pixels), ``edge_px`` and ``kept_as`` (the index, among every
    tile's rows, of the copy kept).
    """
    rows = []
    for name, t in tables.items():
        edge = _edge_distance(shapes[name], t["x_px"], t["y_px"])
        for i in range(len(t["id"])):
            rows.append({"tile": name, **{c: t[c][i] for c in COLUMNS if c in t},
                         "X": float(t["x_px"][i]) + corners[name][0], "Y": float(t["y_px"][i]) + corners[name][1],
                         "edge_px": float(edge[i])})
    keep = np.ones(len(rows), bool)
    into = np.arange(len(rows))
    if rows:
        tile_of = np.array([r["tile"] for r in rows])
        X, Y = np.array([r["X"] for r in rows]), np.array([r["Y"] for r in rows])
        W = np.nan_to_num(np.array([r.get("width_um", np.nan) for r in rows], float)) / pixel_size_um
        E = np.array([r["edge_px"] for r in rows])
        names = list(tables)
        for i_a, a in enumerate(names):
            for b in names[i_a + 1:]:
                if overlap_box(corners[a], shapes[a], corners[b], shapes[b]) is None:
                    continue
                ia, ib = np.flatnonzero(tile_of == a), np.flatnonzero(tile_of == b)
                if not len(ia) or not len(ib):
                    continue
                d = np.hypot(X[ia, None] - X[None, ib], Y[ia, None] - Y[None, ib])
                limit = np.maximum(0.5 * np.maximum(W[ia, None], W[None, ib]), tolerance_px)
                # a detection cut by its tile's edge has its centroid off the protrusion's centre,
                # by up to its own radius: matched when the two footprints overlap
                cut_a, cut_b = E[ia] < 0.5 * W[ia] + 1, E[ib] < 0.5 * W[ib] + 1
                cut = cut_a[:, None] | cut_b[None, :]
                limit = np.where(cut, np.maximum(limit, 0.5 * (W[ia, None] + W[None, ib]) + tolerance_px), limit)
                near = sorted(zip(*np.nonzero(d < limit)), key=lambda pq: d[pq])
                used_a, used_b = set(), set()
                for p, q in near:
                    if p in used_a or q in used_b:
                        continue
                    used_a.add(p)
                    used_b.add(q)
                    i, j = ia[p], ib[q]
                    lose, win = (j, i) if E[i] >= E[j] else (i, j)
                    keep[lose] = False
                    into[lose] = win
                _join_fragments(near, cut_a, cut_b, ia, ib, used_a, used_b, keep, into)
    for k, r in enumerate(rows):      # the copy each detection ended up as (corners: followed)
        root = k
        while into[root] != root:
            root = into[root]
        r["kept_as"] = int(root)
    return [r for r, k in zip(rows, keep) if k], rows


def _join_fragments(near, cut_a, cut_b, ia, ib, used_a, used_b, keep, into) -> None:
    """A tile's edge can split one protrusion's visible part into two detections, each cut by that
    edge; the one-to-one match pairs the closer with the other tile's whole copy and would leave the
    second counted again. A cut detection left unmatched whose footprint meets a matched detection
    of the other tile joins that match (closest first). An uncut one is never joined: the other tile
    saw that place away from its own edge, and two protrusions there would be two of its detections."""
    for p, q in near:
        if p in used_a and q not in used_b and cut_b[q]:
            lose, win = ib[q], ia[p]
            used_b.add(q)
        elif q in used_b and p not in used_a and cut_a[p]:
            lose, win = ia[p], ib[q]
            used_a.add(p)
        else:
            continue
        keep[lose] = False
        into[lose] = win


def _region_labels(regions, overview, covered, step, origin, *, pixel_size_um, n_areas):
    """Colour areas of the painting at overview scale: ``(labels (m, n) int, names)``."""
    if regions in (None, "", "auto"):
        if regions in (None, ""):
            return covered.astype(np.int32), {1: "whole painting"}
        rm = propose_regions(overview, pixel_size_um=pixel_size_um * step, n_areas=n_areas, mask=covered)
        return rm.labels.astype(np.int32), dict(rm.names)
    # a painting-wide label image in the layout's frame, sampled at the overview's pixels: memory-mapped
    # (uncompressed, as uvps and ImageJ write it), so only the sampled pixels are read, never the
    # painting's full-resolution image whole
    path = Path(regions)
    what = f"region label image {path}"
    if not path.is_file():
        raise UVPSInputError(f"region file {path} does not exist")
    lab = open_tiff(path)
    if lab.ndim > 2 and sum(k != 1 for k in lab.shape) == 2:
        lab = lab.reshape([k for k in lab.shape if k != 1])       # a single-plane stack
    m, n = covered.shape
    rr = (origin[1] + (np.arange(m) + 0.5) * step - 0.5).round().astype(int)
    cc = (origin[0] + (np.arange(n) + 0.5) * step - 0.5).round().astype(int)
    if lab.ndim == 2 and (rr.min() < 0 or cc.min() < 0 or rr.max() >= lab.shape[0] or cc.max() >= lab.shape[1]):
        raise UVPSInputError(f"painting regions: {path.name} ({lab.shape[1]} x {lab.shape[0]} px) does "
                             f"not cover the painting (x {origin[0]:.0f}..{origin[0] + n * step:.0f}, "
                             f"y {origin[1]:.0f}..{origin[1] + m * step:.0f} in the layout's frame)")
    # checked as uvps.files.tables.load_regions checks a label image (whole numbers >= 0), on the samples
    out = _as_label_image(lab[np.ix_(rr, cc)] if lab.ndim == 2 else lab, what)
    out[~covered] = 0
    ids = [int(k) for k in np.unique(out) if k]
    if not ids:
        raise UVPSInputError(f"painting regions: {path.name} has no area over the painting (all its pixels there are 0)")
    found = _names_beside(path)
    return out, {k: found.get(k, f"area {k}") for k in ids}


def stitch_painting(out_dir, tiles: dict, *, pixel_size_um: float, regions=None, n_areas: Optional[int] = None,
                    max_shift_px: Optional[float] = None, maps: bool = True, chunk_px: Optional[int] = None,
                    report_html: bool = True, progress=None) -> PaintingResult:
    """Register the tiles of ``out_dir`` (their run folders), merge them into one painting, write
    ``out_dir/painting/`` (all old or all new).

    Parameters
    ----------
    out_dir : path
        The batch folder, ``out_dir/<tile>/`` a finished run folder per tile.
    tiles : dict
        ``{name: (x_px, y_px, (M, N))}``: nominal corners (layout frame) and image shapes.
    pixel_size_um : float
        The tiles' common pixel size.
    regions : None, "auto" or path
        Colour areas: none (the painting is one area), proposed on the painting's albedo, or a
        painting-wide label TIFF in the layout's frame (names in a CSV beside it, as ``--regions``).
    n_areas : int, optional
        Areas to propose (``regions="auto"``).
    max_shift_px : float, optional
        Largest stage error between neighbours (default: a quarter of the smaller tile side).
    maps : bool
        Also write the painting-wide maps (OME-Zarr, chunk by chunk on Dask: on the current
        ``distributed`` client when there is one, :mod:`uvps.painting_maps`).
    chunk_px : int, optional
        The maps' chunk side (default :data:`uvps.files.omezarr.CHUNK_PX`).
    report_html : bool
        Also write ``report.html`` and ``figures/`` (:mod:`uvps.report.painting`).

    Returns
    -------
    PaintingResult
    """
    t0 = time.perf_counter()
    timings = {}
    out_dir = Path(out_dir)
    names = list(tiles)
    report(progress, 0.0, "painting: registering the tiles")
    albedo, shapes, reg = _register(out_dir, tiles, max_shift_px, timings)
    timings["register_s"] = round(time.perf_counter() - t0, 3)
    warnings = list(reg.warnings)
    for w in warnings:
        log.warning("%s", w)
    corners = reg.corners
    gains = tile_gains(albedo, reg)
    x_lo = min(c[0] for c in corners.values())
    y_lo = min(c[1] for c in corners.values())
    origin = (x_lo, y_lo)
    shape = (int(math.ceil(max(corners[k][1] + shapes[k][0] for k in names) - y_lo)),
             int(math.ceil(max(corners[k][0] + shapes[k][1] for k in names) - x_lo)))
    step = max(1, int(math.ceil(math.sqrt(shape[0] * shape[1] / OVERVIEW_MAX_PX))))
    report(progress, 0.3, "painting: the overview and its colour areas")
    overview, covered = blend_overview(albedo, corners, gains, origin, shape, step)
    labels, area_names = _region_labels(regions, overview, covered, step, origin, pixel_size_um=pixel_size_um,
                                        n_areas=n_areas)
    report(progress, 0.6, "painting: merging the protrusions")
    kept, every = _merged_protrusions(out_dir, names, corners, shapes, pixel_size_um=pixel_size_um)
    areas = _area_counts(kept, labels, area_names, corners, shapes, origin, step, pixel_size_um)
    result = PaintingResult(reg, gains, origin, shape, len(kept), len(every), areas, pixel_size_um, step, warnings)
    timings["merge_s"] = round(time.perf_counter() - t0 - timings["register_s"], 3)
    report(progress, 0.8, "painting: writing")
    cm2 = (pixel_size_um * step) ** 2 / UM2_PER_CM2
    # built whole in a new folder that replaces the old one in one step (uvps.files.outputs.new_output_dir)
    with new_output_dir(out_dir / PAINTING_DIR) as tmp:
        _write_layout(tmp / PAINTING_LAYOUT, corners)
        _write_protrusions(tmp / PAINTING_PROTRUSIONS, kept, origin)
        _write_regions(tmp / PAINTING_REGIONS, areas, len(kept), float(covered.sum()) * cm2, names)
        write_label_tiff(tmp / "regions_overview.tif", labels, pixel_size_um=pixel_size_um * step,
                         metadata={"origin_px": list(origin), "step": step})
        figures = dict(albedo=overview, labels=labels, covered=covered, kept=kept, areas=areas, registration=reg,
                       shapes=shapes, origin=origin, step=step, pixel_size_um=pixel_size_um)
        if maps:
            report(progress, 0.85, "painting: the painting-wide maps")
            t_maps = time.perf_counter()
            # the report's figures need nothing of the maps: drawn in a thread of this process while the
            # maps' chunks are computed (on the cluster's workers, or Dask's threads), not after them
            with _beside(_timed_figures if report_html else None, tmp, figures, timings) as drawn:
                result.heights = _write_maps(tmp, out_dir, every, corners, shapes, gains, reg, origin, shape,
                                             labels, step, pixel_size_um, chunk_px)
                timings["maps_s"] = round(time.perf_counter() - t_maps, 3)
                drawn()
        result.timings = timings
        if report_html:
            _write_view_and_report(tmp, result, overview=overview, labels=labels, covered=covered, kept=kept,
                                   shapes=shapes, maps=maps)
        timings["total_s"] = round(time.perf_counter() - t0, 3)
        write_json_atomic(tmp / "painting.json", result.as_dict())
    report(progress, 1.0, "painting: done")
    return result


def _register(out_dir: Path, tiles: dict, max_shift_px, timings: dict):
    """Each tile's albedo (read from its run folder, which gives its true shape) and the tiles'
    registration from their nominal corners, within ``max_shift_px`` (default: a quarter of the
    smaller tile side). The pairs' shifts are tasks of the current ``distributed`` client when there
    is one (:class:`_PairTasks`), else measured in this process; the global solution is this process's.
    ``timings`` gets ``register_tasks`` (pairs measured on the cluster, 0 here) and ``register_cpu_s``
    (CPU seconds of this process during the registration plus the pair tasks' on the workers)."""
    c0 = time.process_time()
    names = list(tiles)
    nominal = {k: (float(tiles[k][0]), float(tiles[k][1])) for k in names}
    albedo = {k: AlbedoTile(out_dir / k) for k in names}
    shapes = {k: tuple(albedo[k].shape) for k in names}
    if max_shift_px is None:
        max_shift_px = 0.25 * min(min(s) for s in shapes.values())
    tasks = _PairTasks.on_current_client()
    reg = register_tiles(albedo, nominal, max_shift_px=max_shift_px, map_pairs=tasks)
    timings["register_tasks"] = tasks.n_tasks if tasks else 0
    timings["register_cpu_s"] = round(time.process_time() - c0 + (tasks.cpu_s if tasks else 0.0), 3)
    return albedo, shapes, reg


def _cpu_timed(fn, job):
    """``(fn(job), CPU seconds of the thread that ran it)``: a pair task's result and its cost on its worker."""
    c0 = time.thread_time()
    out = fn(job)
    return out, time.thread_time() - c0


class _PairTasks:
    """The registration's pairs as tasks of a ``distributed`` client (``map_pairs`` of
    :func:`uvps.core.mosaic.register_tiles`): each task carries its :class:`uvps.core.mosaic.PairJob`
    (the two tiles' :class:`AlbedoTile`, a path each, and the overlap's box), reads just its two
    windows of the run folders' memory-mapped ``albedo.tif`` on its worker and returns the pair's
    :class:`uvps.core.mosaic.PairShift`; no tile goes through the scheduler. The same function as in
    one process, on the same windows: the same shifts, bit for bit (``tests/test_painting.py``)."""

    def __init__(self, client):
        self.client = client
        self.n_tasks = 0
        self.cpu_s = 0.0

    @classmethod
    def on_current_client(cls) -> Optional["_PairTasks"]:
        """On the current client (the batch's cluster: ``client.as_current()``; as Dask's own ``compute``
        finds it), or None without one or when Dask's ``scheduler`` setting names another (``synchronous``:
        everything in this process)."""
        if "distributed" not in sys.modules:      # no client without distributed imported
            return None
        import dask
        if dask.config.get("scheduler", None) not in (None, "dask.distributed", "distributed"):
            return None
        from distributed import Client
        try:
            return cls(Client.current())
        except ValueError:
            return None

    def __call__(self, fn, jobs: list) -> list:
        futures = self.client.map(_cpu_timed, [fn] * len(jobs), jobs, key="uvps-painting-pair", pure=False)
        done = self.client.gather(futures)
        self.n_tasks += len(jobs)
        self.cpu_s += sum(c for _, c in done)
        return [p for p, _ in done]


def _merged_protrusions(out_dir: Path, names, corners, shapes, *, pixel_size_um):
    """Every tile's protrusions merged into the painting's (those of the overlaps counted once,
    :func:`merge_protrusions`), numbered by row, then column; refuses a tile without a table."""
    tables = {}
    for k in names:
        path = out_dir / k / "protrusions.csv"
        if not path.is_file():
            raise UVPSInputError(f"mosaic: tile {k} has no protrusions.csv; run with --regions or --detect")
        tables[k] = read_protrusions_csv(path)
    kept, every = merge_protrusions(tables, corners, shapes, pixel_size_um=pixel_size_um)
    for k, r in enumerate(sorted(kept, key=lambda r: (r["Y"], r["X"])), 1):
        r["painting_id"] = k
    return kept, every


def _area_counts(kept, labels, area_names, corners, shapes, origin, step, pixel_size_um) -> dict:
    """Name each kept protrusion's colour area (from the overview's labels, ``step`` px a pixel)
    and count them per area: its label, the tiles it reaches, its area in cm^2, the count and
    the density per cm^2."""
    m, n = labels.shape
    for r in kept:
        rr = min(m - 1, max(0, int((r["Y"] - origin[1]) // step)))
        cc = min(n - 1, max(0, int((r["X"] - origin[0]) // step)))
        r["area"] = area_names.get(int(labels[rr, cc]), "")
    cm2 = (pixel_size_um * step) ** 2 / UM2_PER_CM2
    counts = np.bincount(labels.ravel(), minlength=max(area_names, default=0) + 1)
    areas = {}
    for lab, nm in area_names.items():
        seen = set()
        for k in corners:
            r0 = int(round((corners[k][1] - origin[1]) / step))
            c0 = int(round((corners[k][0] - origin[0]) / step))
            if np.any(labels[r0:r0 + shapes[k][0] // step, c0:c0 + shapes[k][1] // step] == lab):
                seen.add(k)
        c = sum(1 for r in kept if r["area"] == nm)
        a = float(counts[lab]) * cm2
        areas[nm] = {"label": int(lab), "tiles": len(seen), "area_cm2": a, "count": c,
                     "density_per_cm2": c / a if a else None}
    return areas


def _timed_figures(tmp: Path, figures: dict) -> float:
    """The painting report's figures into ``tmp/figures/``; returns the seconds they took."""
    from .report.painting import write_painting_figures
    t0 = time.perf_counter()
    write_painting_figures(tmp, **figures)
    return round(time.perf_counter() - t0, 3)


@contextlib.contextmanager
def _beside(fn, tmp: Path, figures: dict, timings: dict):
    """Run ``fn(tmp, figures)`` in a thread of its own beside the block (nothing when ``fn`` is None);
    ``timings["figures_s"]`` its seconds. The block gets a callable that waits for it and raises its
    error. Leaving the block always waits for it (it writes into the block's folder ``tmp``), and an
    error of the block wins over its own.

    Not a task of the cluster: with a worker a core, the maps' chunks queued behind it on its worker
    (the maps took as long as the figures: 6.4-7.3 s against 2.1-3.6 s alone, at load 9).
    """
    if fn is None:
        yield lambda: None
        return
    with ThreadPoolExecutor(1, thread_name_prefix="uvps-painting-report") as pool:
        # the caller's context (dask's config) as it is
        future = pool.submit(contextvars.copy_context().run, fn, tmp, figures)

        def done():
            timings["figures_s"] = future.result()
        try:
            yield done
        except BaseException:
            futures_wait([future])
            raise


def _write_view_and_report(tmp: Path, result: PaintingResult, *, overview, labels, covered, kept, shapes, maps):
    """The painting's zoomable view (Deep Zoom tiles of the maps, when they were written) and its
    ``report.html`` (with its figures, unless the maps' step drew them: ``figures_s`` in the timings),
    into the new painting folder ``tmp``."""
    from .report.painting import write_painting_report
    view = None
    if maps:
        from .report.deepzoom import write_view
        t_view = time.perf_counter()
        finite = overview[np.isfinite(overview) & (overview > 0)]
        view = write_view(tmp, albedo_scale=float(np.percentile(finite, 99.5)) if finite.size else None)
        result.timings["view_s"] = round(time.perf_counter() - t_view, 3)
    write_painting_report(tmp, albedo=overview, labels=labels, covered=covered, kept=kept, areas=result.areas,
                          registration=result.registration, shapes=shapes, origin=result.origin,
                          step=result.overview_step, pixel_size_um=result.pixel_size_um, warnings=result.warnings,
                          view=view, figures="figures_s" not in result.timings)


def _write_maps(tmp: Path, out_dir: Path, every: list, corners, shapes, gains, reg, origin, shape, labels, step,
                pixel_size_um, chunk_px) -> dict:
    """labels.ome.zarr (the protrusion and colour-area labels), albedo.ome.zarr (with the same labels
    attached), normals.ome.zarr and height.ome.zarr of the painting, chunk by chunk; returns each
    tile's height plane."""

    chunk_px = int(chunk_px or CHUNK_PX)
    names = list(corners)
    planes, forms, record = _align_heights(out_dir, names, corners, reg, pixel_size_um=pixel_size_um)
    luts = {}
    for k in names:
        mine = [r for r in every if r["tile"] == k]
        top = max([int(r["id"]) for r in mine], default=0)
        lut = np.zeros(top + 1, np.uint32)
        for r in mine:
            lut[int(r["id"])] = every[r["kept_as"]]["painting_id"]
        luts[k] = lut
    placed = [PlacedTile(k, str(out_dir / k), corners[k][0] - origin[0], corners[k][1] - origin[1], tuple(shapes[k]),
                         gains[k], planes[k], luts[k], forms[k]) for k in names]
    ctx = MapContext(placed, tuple(origin), tuple(shape), channels=AlbedoTile(out_dir / names[0]).channels)
    rctx = MapContext([PlacedTile(t.name, t.run_dir, t.x, t.y, t.shape) for t in placed], tuple(origin),
                      tuple(shape), regions=labels, step=step)
    origin_um = (origin[1] * pixel_size_um, origin[0] * pixel_size_um)
    alb = painting_array("albedo", ctx, chunk_px=chunk_px)
    if ctx.channels == 1:
        alb = alb[0]
    # every map's level k in one Dask graph (a StoreBatch): on a cluster each graph is a round trip
    batch = StoreBatch()
    # the labels once, as a store of their own (labels.ome.zarr), then attached to the albedo by copying
    # their files (napari and Fiji's readers overlay an image's labels/ on it), once they are written
    labels_zarr = write_dask_ome_labels(
        tmp / PAINTING_LABELS, [(LABELS[0], painting_array("protrusions", ctx, chunk_px=chunk_px)),
                                (LABELS[1], painting_array("regions", rctx, chunk_px=chunk_px))],
        pixel_size_um, image="../../albedo.ome.zarr", chunk_px=chunk_px, origin_um=origin_um, batch=batch)
    write_dask_ome_zarr(tmp / "albedo.ome.zarr", ZarrImage("albedo", "", ("R", "G", "B"), unit="counts"), alb,
                        pixel_size_um, chunk_px=chunk_px, labels=[(lb, labels_zarr / lb.name) for lb in LABELS],
                        origin_um=origin_um, batch=batch)
    write_dask_ome_zarr(tmp / "normals.ome.zarr", ZarrImage("normals", "", ("nx", "ny", "nz"), kind="normals"),
                        painting_array("normals", ctx, chunk_px=chunk_px), pixel_size_um, chunk_px=chunk_px,
                        origin_um=origin_um, batch=batch)
    write_dask_ome_zarr(tmp / "height.ome.zarr", ZarrImage("height", "", (), unit="micrometer"),
                        painting_array("height", ctx, chunk_px=chunk_px), pixel_size_um, chunk_px=chunk_px,
                        origin_um=origin_um, batch=batch)
    batch.run()
    return record


def _align_heights(out_dir: Path, names: list, corners: dict, reg, *, pixel_size_um: float) -> tuple:
    """Each tile's height plane and form (:class:`uvps.painting_maps.PlacedTile`) and what
    ``painting.json`` records of them. With every tile's levelling in its ``run.json`` (a ``uvps run``),
    its height as integrated is rebuilt, less the tilt its own lamp intensities gave it when the tiles'
    lamps are one rig's (:func:`uvps.core.mosaic.intensity_tilts`), and the tiles share one error surface
    (the lamps move with the camera: :func:`uvps.core.mosaic.align_rig_heights`); otherwise each tile takes
    a free plane (:func:`uvps.core.mosaic.align_heights`)."""
    import json

    heights = {k: open_tiff(out_dir / k / "depth.tif") for k in names}
    levels = {}
    for k in names:
        try:
            levels[k] = json.loads((out_dir / k / "run.json").read_text(encoding="utf-8"))["level"]["legendre_coeffs_um"]
        except (OSError, ValueError, KeyError, TypeError):
            break
    if len(levels) == len(names) and len({tuple(h.shape) for h in heights.values()}) == 1:
        tilts = _intensity_tilts(out_dir, names, next(iter(heights.values())).shape, pixel_size_um)
        if tilts is not None:
            for k in names:
                c = _pad_plane(levels[k])
                c[1, 0] -= tilts[k][0]
                c[0, 1] -= tilts[k][1]
                levels[k] = c
        rig = align_rig_heights(heights, corners, reg.pairs, levels)
        record = {"model": "rig: per-tile offset, the tilt measured, one shared error surface in the tile's frame",
                  "shared_legendre_um": [[round(float(v), 6) for v in row] for row in rig.shared],
                  # None when no overlap was sampled (one tile, no pair used): JSON has no NaN
                  "overlap_rms_um": round(rig.rms_um, 4) if math.isfinite(rig.rms_um) else None,
                  "intensity_tilts_um": None if tilts is None else {k: [round(v, 4) for v in tilts[k]] for k in names},
                  "planes": {k: [round(v, 6) for v in rig.planes[k]] for k in names}}
        return rig.planes, rig.forms, record
    planes = align_heights(heights, corners, reg.pairs)
    return planes, {k: None for k in names}, {"model": "free: per-tile offset and plane",
                                              "planes": {k: [round(v, 6) for v in planes[k]] for k in names}}


def _pad_plane(coeffs) -> np.ndarray:
    """Legendre coefficients as an array of at least 2 x 2 (a plane's terms)."""
    c = np.asarray(coeffs, np.float64)
    out = np.zeros((max(c.shape[0], 2), max(c.shape[1], 2)))
    out[:c.shape[0], :c.shape[1]] = c
    return out


def _intensity_tilts(out_dir: Path, names: list, shape, pixel_size_um: float) -> Optional[dict]:
    """:func:`uvps.core.mosaic.intensity_tilts` of the tiles' ``lights.json``; None when a tile has none or
    its lamps are not at positions (far lights)."""
    import json

    positions, intensities = {}, {}
    for k in names:
        try:
            lights = json.loads((out_dir / k / "lights.json").read_text(encoding="utf-8"))["lights"]
            positions[k] = [lt["position_mm"] for lt in lights]
            intensities[k] = [float(lt["intensity"]) for lt in lights]
        except (OSError, ValueError, KeyError, TypeError):
            return None
        if any(p is None for p in positions[k]):
            return None
    return intensity_tilts(positions, intensities, shape, pixel_size_um)


def _cell(v) -> str:
    if v is None:
        return ""
    if isinstance(v, np.generic):
        v = v.item()
    if isinstance(v, float):
        return f"{v:.8g}" if np.isfinite(v) else ""
    return str(v)


def _write_layout(path: Path, corners: dict) -> None:
    buf = StringIO()
    wr = csv.writer(buf, lineterminator="\n")
    wr.writerow(["capture", "x_px", "y_px"])
    for k, (x, y) in corners.items():
        wr.writerow([k, f"{x:.3f}", f"{y:.3f}"])
    atomic_write_text(path, buf.getvalue())


def _write_protrusions(path: Path, kept: list, origin) -> None:
    cols = ["painting_id", "tile", "tile_id", "x_px", "y_px", "x_tile_px", "y_tile_px", "edge_px", "area"]
    cols += [c for c in COLUMNS if c not in ("id", "x_px", "y_px", "region")]
    buf = StringIO()
    wr = csv.writer(buf, lineterminator="\n")
    wr.writerow(cols)
    for r in sorted(kept, key=lambda r: r["painting_id"]):
        vals = {"painting_id": r["painting_id"], "tile": r["tile"], "tile_id": int(r["id"]), "x_px": r["X"], "y_px": r["Y"],
                "x_tile_px": r["x_px"], "y_tile_px": r["y_px"], "edge_px": r["edge_px"], "area": r["area"]}
        wr.writerow([_cell(vals[c] if c in vals else r.get(c)) for c in cols])
    atomic_write_text(path, buf.getvalue())


def _write_regions(path: Path, areas: dict, total: int, total_cm2: float, names) -> None:
    buf = StringIO()
    wr = csv.writer(buf, lineterminator="\n")
    wr.writerow(["name", "tiles", "area_cm2", "count", "density_per_cm2"])
    for nm, a in areas.items():
        wr.writerow([nm, a["tiles"], _cell(a["area_cm2"]), a["count"], _cell(a["density_per_cm2"])])
    wr.writerow(["all areas", len(names), _cell(total_cm2), total, _cell(total / total_cm2 if total_cm2 else None)])
    atomic_write_text(path, buf.getvalue())
