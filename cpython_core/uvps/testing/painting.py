"""A synthetic painting photographed as overlapping tiles under a moving rig, with its truth.

One painting (height, albedo, colour areas, protrusions: :func:`uvps.testing.synthetic.make_capture`
over the whole canvas) is photographed as a grid of overlapping tiles by a rig that carries the
camera and its lamps together (a copy stand or an XY stage): every tile is lit by the same lamps at
the same positions relative to the tile's centre, the stage puts each tile off its nominal corner
by up to ``stage_error_px`` (sub-pixel, per axis), and the exposure drifts between tiles by up to
``exposure_drift`` (relative). The user knows the nominal corners only (``layout.csv``); the truth
(the true corners, the painting-wide maps and protrusion list in painting pixels) is written apart.

Frames: painting pixel ``(row, column)``; a tile's pixel ``(r, c)`` is the painting's
``(y0 + r, x0 + c)`` with ``(x0, y0)`` its true corner. The tiles are sampled from the painting's
maps shifted by the corners' fractional parts (cubic splines), then rendered with the image model
of :func:`uvps.testing.synthetic.render_images` (near lamps, noise).
"""
from __future__ import annotations

import csv
import dataclasses
from dataclasses import dataclass
from pathlib import Path
from typing import Optional

import numpy as np
from scipy import ndimage

from ..errors import UVPSInputError
from ..files.io import write_imagej_tiff
from ..files.outputs import atomic_output_dir, write_json_atomic
from .synthetic_spec import Nuisances
from .synthetic import SyntheticCapture, make_capture, normals_from_height, render_images, write_capture


@dataclass
class PaintingTile:
    """One tile: its name, grid cell, nominal and true corners (painting pixels) and its capture."""

    name: str
    row: int
    col: int
    nominal: tuple          # (x0, y0) as the stage reports it (layout.csv)
    true: tuple             # (x0, y0) where the tile really is
    exposure: float         # counts per unit of albedo * E (drifts between tiles)
    capture: SyntheticCapture


@dataclass
class SyntheticPainting:
    """A painting (``whole``: its maps and protrusions in painting pixels) and its tiles."""

    whole: SyntheticCapture
    tiles: list
    tile_shape: tuple
    grid: tuple             # (columns, rows)
    overlap: float
    stage_error_px: float

    def true_corners(self) -> dict:
        return {t.name: t.true for t in self.tiles}

    def nominal_corners(self) -> dict:
        return {t.name: t.nominal for t in self.tiles}


def _sample(a: np.ndarray, x0: float, y0: float, shape, order: int = 3) -> np.ndarray:
    """``a`` sampled at ``(y0 + r, x0 + c)`` for the tile's pixels (cubic spline on a crop)."""
    M, N = shape
    ix, iy = int(np.floor(x0)), int(np.floor(y0))
    fx, fy = x0 - ix, y0 - iy
    pad = 4
    r0, c0 = max(iy - pad, 0), max(ix - pad, 0)
    crop = np.asarray(a[r0:iy + M + pad, c0:ix + N + pad], dtype=np.float64)
    shift = (-fy, -fx) + (0,) * (crop.ndim - 2)
    moved = ndimage.shift(crop, shift, order=order, mode="nearest", prefilter=order > 1) if fx or fy else crop
    return moved[iy - r0:iy - r0 + M, ix - c0:ix - c0 + N]


def make_painting(*, grid=(3, 2), tile_shape=(200, 240), overlap: float = 0.4, stage_error_px: float = 30.0,
                  exposure_drift: float = 0.15, n_lights: int = 8, seed: int = 0,
                  protrusion_density: float = 400.0, **overrides) -> SyntheticPainting:
    """Render a painting as ``grid`` = (columns, rows) overlapping tiles under a moving rig.

    Parameters
    ----------
    grid : (int, int)
        Columns and rows of tiles, row by row (``r1c1``, ``r1c2``, ...).
    tile_shape : (int, int)
        Each tile's (rows, columns).
    overlap : float
        Nominal overlap of neighbours, as a fraction of the tile's size (0.2 = 20 %).
    stage_error_px : float
        The stage puts each tile off its nominal corner by up to this, per axis (uniform,
        sub-pixel); the errors' mean is zero, so the painting's frame is the nominal layout's.
    exposure_drift : float
        Each tile's exposure is the first's times ``1 + u``, ``u`` uniform in +-``exposure_drift``.
    n_lights : int
        Lamps on the rig (fixed relative to the camera: the same positions for every tile).
    protrusion_density : float
        Protrusions per cm^2 in light and dark areas alike (enough to score a small painting).
    **overrides
        Further :class:`uvps.testing.synthetic.SyntheticSpec` fields of the painting: ``bow_um``
        (the canvas's bow over the whole painting), ``beam_exponent`` and ``beam_aim_error_deg`` (the
        rig's lamps' beams, the same relative to every tile: an irradiance the light file does not
        give, so a bias of the normals common to every tile).

    Returns
    -------
    SyntheticPainting
    """
    cols, rows = (int(v) for v in grid)
    M, N = (int(v) for v in tile_shape)
    if cols < 1 or rows < 1 or cols * rows < 2:
        raise UVPSInputError(f"grid must be at least 2 tiles; got {grid}")
    if not 0 < overlap < 0.9:
        raise UVPSInputError(f"overlap must be in (0, 0.9); got {overlap}")
    step_x, step_y = round(N * (1 - overlap)), round(M * (1 - overlap))
    margin = int(np.ceil(stage_error_px)) + 2
    shape = (2 * margin + M + (rows - 1) * step_y, 2 * margin + N + (cols - 1) * step_x)
    rng = np.random.default_rng(np.random.SeedSequence([seed, 42]))
    whole = make_capture(shape=shape, n_lights=n_lights, seed=seed, protrusion_density_light=protrusion_density,
                         protrusion_density_dark=protrusion_density, **overrides)
    err = rng.uniform(-stage_error_px, stage_error_px, (rows * cols, 2)) if stage_error_px > 0 \
        else np.zeros((rows * cols, 2))
    err -= err.mean(axis=0)
    if stage_error_px > 0:
        err *= min(1.0, stage_error_px / np.abs(err).max())
    drift = 1 + rng.uniform(-exposure_drift, exposure_drift, rows * cols)
    drift[0] = 1.0
    px = whole.spec.pixel_size_um
    # the lamps' beams (``beam_exponent``, ``beam_aim_error_deg``) ride with the rig: the same axes for every
    # tile, so the irradiance's fall-off the light file does not give is the same in every tile
    rig = Nuisances(beam_axes=whole.nuisances.beam_axes, beam_exponent=whole.nuisances.beam_exponent) \
        if whole.nuisances.beam_axes is not None else None
    tiles = []
    for k in range(rows * cols):
        r, c = divmod(k, cols)
        nominal = (float(margin + c * step_x), float(margin + r * step_y))
        true = (nominal[0] + float(err[k, 0]), nominal[1] + float(err[k, 1]))
        height = _sample(whole.height_um, *true, (M, N)).astype(np.float32)
        albedo = np.clip(_sample(whole.albedo, *true, (M, N)), 0, None).astype(np.float32)
        exposure = whole.exposure * float(drift[k])
        images = render_images(height, albedo, pixel_size_um=px, light_positions_mm=whole.light_positions_mm,
                               intensities=whole.intensities, rng=np.random.default_rng([seed, k]),
                               noise=whole.spec.noise, gain=whole.gain, read_noise=whole.spec.read_noise,
                               exposure=exposure, dtype=np.uint16, nuisances=rig)
        regions = _sample(whole.regions, *true, (M, N), order=0).astype(whole.regions.dtype)
        cap = dataclasses.replace(whole, images=images, height_um=height, albedo=albedo, regions=regions,
                                  normals=normals_from_height(height, pixel_size_um=px), exposure=exposure,
                                  spec=dataclasses.replace(whole.spec, shape=(M, N)), protrusions=_inside(
                                      whole.protrusions, true, (M, N)))
        tiles.append(PaintingTile(f"r{r + 1}c{c + 1}", r, c, nominal, true, exposure, cap))
    return SyntheticPainting(whole, tiles, (M, N), (cols, rows), float(overlap), float(stage_error_px))


def _inside(prot: dict, corner, shape) -> dict:
    """The painting's protrusions whose centre falls in the tile, in the tile's pixels."""
    x0, y0 = corner
    x, y = prot["x_px"] - x0, prot["y_px"] - y0
    keep = (x >= 0) & (x <= shape[1] - 1) & (y >= 0) & (y <= shape[0] - 1)
    out = {k: np.asarray(v)[keep] for k, v in prot.items()}
    out["x_px"], out["y_px"] = x[keep], y[keep]
    return out


def write_layout(path, corners: dict) -> None:
    """``capture,x_px,y_px`` rows, one per tile."""
    with open(path, "w", newline="", encoding="utf-8") as fh:
        wr = csv.writer(fh, lineterminator="\n")
        wr.writerow(["capture", "x_px", "y_px"])
        for name, (x, y) in corners.items():
            wr.writerow([name, f"{x:.4f}", f"{y:.4f}"])


def write_painting(painting: SyntheticPainting, folder, *, tile_truth: bool = False) -> Path:
    """Write a painting's tiles, its nominal layout and its truth.

    ``folder/tiles/<name>/`` per tile (as :func:`uvps.testing.synthetic.write_capture` writes a
    capture: 16-bit TIFFs and ``lights_positions_mm.csv``, the rig's lamps, the same for all
    tiles), ``folder/layout.csv`` (the stage's nominal corners), ``folder/truth/``:
    ``layout.csv`` (the true corners), ``height_um.tif``, ``albedo.tif`` (C, Y, X),
    ``regions.tif``, ``protrusions.csv`` (painting pixels) and ``painting.json`` (grid, overlap,
    stage error, each tile's exposure).
    """
    folder = Path(folder)
    with atomic_output_dir(folder) as tmp:
        (tmp / "tiles").mkdir()
        for t in painting.tiles:
            write_capture(t.capture, tmp / "tiles" / t.name, truth=tile_truth)
        write_layout(tmp / "layout.csv", painting.nominal_corners())
        truth = tmp / "truth"
        truth.mkdir()
        write_layout(truth / "layout.csv", painting.true_corners())
        w = painting.whole
        px = w.spec.pixel_size_um
        write_imagej_tiff(truth / "height_um.tif", w.height_um, axes="YX", pixel_size_um=px)
        alb = np.moveaxis(w.albedo, -1, 0) if w.albedo.ndim == 3 else w.albedo
        write_imagej_tiff(truth / "albedo.tif", alb.astype(np.float32), axes="CYX" if alb.ndim == 3 else "YX",
                          pixel_size_um=px)
        write_imagej_tiff(truth / "regions.tif", w.regions.astype(np.uint16), axes="YX", pixel_size_um=px)
        p = w.protrusions
        with open(truth / "protrusions.csv", "w", newline="", encoding="utf-8") as fh:
            wr = csv.writer(fh, lineterminator="\n")
            wr.writerow(["id", "x_px", "y_px", "width_um", "height_um", "region"])
            for i in range(len(p["id"])):
                wr.writerow([int(p["id"][i]), f"{p['x_px'][i]:.3f}", f"{p['y_px'][i]:.3f}",
                             f"{p['width_um'][i]:.2f}", f"{p['height_um'][i]:.3f}", int(p["region"][i])])
        write_json_atomic(truth / "painting.json", {
            "grid": list(painting.grid), "tile_shape": list(painting.tile_shape), "overlap": painting.overlap,
            "stage_error_px": painting.stage_error_px, "pixel_size_um": px, "shape": list(w.height_um.shape),
            "region_names": list(w.region_names),
            "tiles": [{"name": t.name, "row": t.row, "col": t.col, "nominal": list(t.nominal),
                       "true": list(t.true), "exposure": t.exposure} for t in painting.tiles]})
    return folder


def read_truth_layout(path) -> dict:
    """``{capture: (x_px, y_px)}`` of a layout CSV."""
    with open(path, newline="", encoding="utf-8") as fh:
        return {r["capture"]: (float(r["x_px"]), float(r["y_px"])) for r in csv.DictReader(fh)}


def painting_truth(folder) -> Optional[dict]:
    """The truth written by :func:`write_painting` (``painting.json`` and the true layout)."""
    import json
    folder = Path(folder)
    meta = json.loads((folder / "truth" / "painting.json").read_text(encoding="utf-8"))
    meta["layout"] = read_truth_layout(folder / "truth" / "layout.csv")
    return meta


def read_table(path) -> dict:
    """A CSV as ``{column: float array}`` (the numeric columns of a protrusion table)."""
    with open(path, newline="", encoding="utf-8") as fh:
        rows = list(csv.DictReader(fh))
    out = {}
    for c in ("x_px", "y_px", "width_um"):
        out[c] = np.array([float(r[c]) if r[c] not in ("", None) else np.nan for r in rows])
    return out


def score_painting(truth: dict, found: dict, corners: dict, tile_shape, *, pixel_size_um: float,
                   min_width_um: float = 60.0) -> dict:
    """Painting-wide detection scores of ``found`` (painting pixels) against ``truth``.

    The truth is what the tiles saw: protrusions whose centre lies in a tile at its true corner
    (``corners``). Detections and truth are matched one to one
    (:func:`uvps.core.compare.match_protrusions`: centres within 2 px or half the larger width).
    Recall over the true protrusions >= ``min_width_um``; precision over the detections of that
    class (a matched detection takes its truth's width, an unmatched one its own). ``twice``: the
    unmatched detections within the match radius of a truth another detection matched (a
    protrusion counted twice). ``count_ratio``: detections of the class over true ones.
    """
    from ..core.compare import match_protrusions

    M, N = tile_shape
    tx, ty, tw = (np.asarray(truth[c], float) for c in ("x_px", "y_px", "width_um"))
    # inside: the centre in a tile; touching: the footprint reaches into one (a detection of a
    # protrusion cut by the painting's edge is neither a hit nor a false positive)
    inside, touching = np.zeros(tx.size, bool), np.zeros(tx.size, bool)
    half = 0.5 * tw / pixel_size_um + 1
    for x0, y0 in corners.values():
        inside |= (tx >= x0) & (tx <= x0 + N - 1) & (ty >= y0) & (ty <= y0 + M - 1)
        touching |= (tx >= x0 - half) & (tx <= x0 + N - 1 + half) & (ty >= y0 - half) & (ty <= y0 + M - 1 + half)
    edge_only = (touching & ~inside)[touching]
    tx, ty, tw = tx[touching], ty[touching], tw[touching]
    fx, fy = np.asarray(found["x_px"], float), np.asarray(found["y_px"], float)
    fw = np.nan_to_num(np.asarray(found["width_um"], float))
    pairs, _ = match_protrusions(np.column_stack([tx, ty]), tw, np.column_stack([fx, fy]), fw,
                                 pixel_size_um=pixel_size_um)
    t2f = np.full(tx.size, -1)
    f2t = np.full(fx.size, -1)
    if len(pairs):
        t2f[pairs[:, 0]], f2t[pairs[:, 1]] = pairs[:, 1], pairs[:, 0]
    cut = (f2t >= 0) & edge_only[np.maximum(f2t, 0)]
    f2t, fw, fx, fy = f2t[~cut], fw[~cut], fx[~cut], fy[~cut]
    t2f[edge_only] = -2
    big = (tw >= min_width_um) & ~edge_only
    cls = np.where(f2t >= 0, tw[np.maximum(f2t, 0)], fw) >= min_width_um
    rec = float(np.mean(t2f[big] >= 0)) if big.any() else float("nan")
    prec = float(np.mean(f2t[cls] >= 0)) if cls.any() else float("nan")
    f1 = 2 * prec * rec / (prec + rec) if prec + rec > 0 else float("nan")
    twice = 0
    for j in np.flatnonzero(f2t < 0):
        d = np.hypot(tx - fx[j], ty - fy[j]) * pixel_size_um
        near = np.flatnonzero(d <= np.maximum(2 * pixel_size_um, 0.5 * np.maximum(tw, fw[j])))
        twice += bool(np.any(t2f[near] >= 0))   # -2: cut by the edge
    return {"true": int(big.sum()), "detected": int(cls.sum()), "recall": rec, "precision": prec, "f1": f1,
            "twice": int(twice), "count_ratio": float(cls.sum() / big.sum()) if big.any() else float("nan")}


def score_height(height: np.ndarray, origin, truth_height: np.ndarray, corners: dict, tile_shape, *,
                 margin: int = 4) -> dict:
    """Height error of a painting-wide map (pixel (0, 0) at ``origin`` = (x, y) in the truth's
    frame) against the truth, after removing one least-squares plane from the difference: rms over
    the painting and over the overlap bands (pixels two or more tiles cover), ``margin`` pixels in
    from the painting's outer edge (where every tile's integration errs alike)."""
    M, N = height.shape
    rr, cc = np.mgrid[0:M, 0:N].astype(np.float64)
    Y, X = rr + origin[1], cc + origin[0]
    truth = ndimage.map_coordinates(np.asarray(truth_height, np.float64), [Y, X], order=1, mode="nearest")
    cover = np.zeros((M, N), int)
    inner = np.zeros((M, N), bool)
    tm, tn = tile_shape
    for x0, y0 in corners.values():
        inside = (X >= x0) & (X <= x0 + tn - 1) & (Y >= y0) & (Y <= y0 + tm - 1)
        cover += inside
    union = cover > 0
    inner = ndimage.binary_erosion(union, iterations=margin) & np.isfinite(height)
    d = (np.asarray(height, np.float64) - truth)[inner]
    A = np.column_stack([np.ones(d.size), X[inner], Y[inner]])
    coef, *_ = np.linalg.lstsq(A, d, rcond=None)
    res = np.full((M, N), np.nan)
    res[inner] = d - A @ coef
    band = inner & (cover >= 2)
    return {"rms_um": float(np.sqrt(np.nanmean(res[inner] ** 2))),
            "overlap_rms_um": float(np.sqrt(np.nanmean(res[band] ** 2))) if band.any() else float("nan"),
            "p99_abs_um": float(np.nanpercentile(np.abs(res[inner]), 99))}
