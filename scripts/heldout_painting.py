"""A held-out painting in tiles, rendered without ``uvps.testing``, run through ``uvps batch --mosaic`` and scored.

The renderer here shares no code, no parameters and no file with the project's generator
(``uvps.testing``): it imports numpy, scipy and tifffile only, and its scene is analytic in painting
coordinates, so a tile at a sub-pixel stage position is sampled from the same painting as every other.

The scene (painting pixels of ``PIXEL_UM`` = 15 um, x to the right, y down):

- **Canvas**: a bow (a smooth dome, ``BOW_UM`` at its middle falling to 0 at the painting's edges,
  plus a slight twist) and a brushwork texture (a few sinusoids, about 1 um, 0.6-3 mm wavelength).
- **Paints**: ``N_PAINTS`` colour areas, a warped Voronoi partition of the painting into about twice as
  many patches, each paint with its own RGB albedo and a 3 % mottle.
- **Protrusions**: widths log-uniform over 30-400 um, heights 10-30 % of the width, three shapes in equal
  share (dome: cos^2 of the radius; crater: a ring sin^2(pi rho) with a collapsed centre; flat-topped:
  flat to 60 % of the radius, then a cos^2 edge), a third of them elliptical (aspect up to 1.6, any
  angle: the width is the footprint's equivalent diameter), none overlapping; half of them a little
  lighter or darker (albedo x 0.9-1.2 across the footprint).
- **The rig**: a camera orthogonal to the canvas with ``TILE`` = 900 x 1200 px fields, 12 UV lamps at
  280-420 mm from the field's centre, 25-55 deg above the canvas, spread around it, fixed to the camera
  (their positions, mm from each tile's centre, are written as ``lights_positions_mm.csv``, the file
  ``uvps batch --lights`` reads). Each lamp: a point source (inverse square, Lambert), its beam cos^30 of the
  angle to its aim (a few mm off the field's centre), a power within 3 % of the others (not in the file);
  the lens vignettes 6 % to the corners.
- **The stage**: a 4 x 3 grid at 20 % overlap; each tile's true corner is the nominal one plus an error of up to
  ``STAGE_PX`` = 30 px per axis (sub-pixel, zero mean: the painting's frame is the nominal layout's, as
  registration can only recover relative positions). Exposure drifts 5 % between tiles.
- **Noise**: shot noise (gain 1 count per electron) and 3 counts of read noise; 16-bit RGB TIFFs at 15 um
  (XResolution tags, as a converter writes them).

Not rendered: cast shadows, inter-reflections, a black level, rotation between tiles.

Truth (``truth/``): ``height_um.tif`` (painting-wide, float32), ``paints.tif`` (paint label map, uint8,
1..N_PAINTS), ``protrusions.csv`` (painting x_px, y_px, width_um, height_um, shape, paint), ``layout.csv`` (true
corners), ``painting.json``. Painting pixel (0, 0) of the truth images is the layout's (0, 0).

Scored as ``scripts/benchmark_painting.py`` scores the generator's paintings, with a matcher of its own
(one to one, closest first, centres within 2 px or half the larger width): the refined corners' largest error,
detection F1 for protrusions >= 60 um (the truth is what some tile's field holds; a protrusion cut by the
painting's edge counts neither way), detections counted twice, the count over the truth, the height's rms error
after one plane over the painting and over the overlap bands (4 px in from the painting's edge), and the batch's
time against the tiles' sum over the workers::

    OMP_NUM_THREADS=1 python scripts/heldout_painting.py render /tmp/heldout --seed 7
    OMP_NUM_THREADS=1 python scripts/heldout_painting.py run /tmp/heldout -o /tmp/heldout_out --workers 2 [--doc]
    OMP_NUM_THREADS=1 python scripts/heldout_painting.py score /tmp/heldout -o /tmp/heldout_out

``run`` into a finished output folder runs only the stitching again (``uvps batch`` skips done tiles: its times are
then the stitching's, not a batch's); ``score`` scores an output folder as it is, running nothing.

The registration alone, re-run on a finished run's tile folders (prints the corner errors and each pair's)::

    OMP_NUM_THREADS=1 python scripts/heldout_painting.py register /tmp/heldout -o /tmp/heldout_out

``--doc`` writes the result into docs/benchmarks.md's section ``heldout`` and docs/benchmarks/heldout.json.
"""
from __future__ import annotations

import argparse
import csv
import json
import os
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import tifffile
from scipy import ndimage
from scipy.spatial import cKDTree

DOC_SECTION = "heldout"
PIXEL_UM = 15.0
TILE = (900, 1200)           # rows, columns
GRID = (4, 3)                # columns, rows
OVERLAP = 0.2
STAGE_PX = 30.0
PAD = 40                     # the nominal layout starts here, so every true corner is >= 0
N_LAMPS = 12
N_PAINTS = 7
N_PROTRUSIONS = 1400
BOW_UM = 120.0
PALETTE = np.array([[0.85, 0.83, 0.78], [0.66, 0.20, 0.13], [0.22, 0.27, 0.62], [0.72, 0.56, 0.26],
                    [0.16, 0.46, 0.36], [0.38, 0.27, 0.19], [0.80, 0.52, 0.57]])
SHAPES = ("dome", "crater", "flat")


# ------------------------------------------------------------------------------------------------
# the scene: analytic in painting pixels (X right, Y down)
# ------------------------------------------------------------------------------------------------

class Scene:
    """The painting: canvas, paints, protrusions; every field evaluated at any (Y, X) in painting pixels."""

    def __init__(self, seed: int):
        rng = np.random.default_rng(seed)
        cols, rows = GRID
        M, N = TILE
        self.step = (round(N * (1 - OVERLAP)), round(M * (1 - OVERLAP)))       # x, y
        self.shape = (2 * PAD + (rows - 1) * self.step[1] + M, 2 * PAD + (cols - 1) * self.step[0] + N)
        H, W = self.shape
        # canvas texture: sinusoids of 0.6-3 mm
        k = 6
        lam = rng.uniform(40, 200, k)
        ang = rng.uniform(0, np.pi, k)
        self.tex = (rng.uniform(0.4, 1.0, k), 2 * np.pi / lam * np.cos(ang), 2 * np.pi / lam * np.sin(ang),
                    rng.uniform(0, 2 * np.pi, k))
        self.twist = rng.uniform(-0.15, 0.15)
        # paints: a warped Voronoi partition, each patch one paint, every paint used
        n_seeds = 2 * N_PAINTS
        self.seeds = np.column_stack([rng.uniform(0, W, n_seeds), rng.uniform(0, H, n_seeds)])
        paint = np.concatenate([np.arange(N_PAINTS), rng.integers(0, N_PAINTS, n_seeds - N_PAINTS)])
        self.seed_paint = rng.permutation(paint)
        self.warp = (rng.uniform(50, 90, 2), rng.uniform(250, 500, 2), rng.uniform(0, 2 * np.pi, 2))
        self.mottle = (rng.uniform(15, 60, 4), rng.uniform(0, np.pi, 4), rng.uniform(0, 2 * np.pi, 4))
        # protrusions, none overlapping
        prot = []
        tree_pts: list = []
        tries = 0
        while len(prot) < N_PROTRUSIONS and tries < 50 * N_PROTRUSIONS:
            tries += 1
            w = float(np.exp(rng.uniform(np.log(30), np.log(400))))
            x, y = rng.uniform(5, W - 5), rng.uniform(5, H - 5)
            aspect = rng.uniform(1.0, 1.6) if rng.random() < 1 / 3 else 1.0
            r = 0.5 * w * np.sqrt(aspect) / PIXEL_UM                           # the long semi-axis
            if any(np.hypot(x - q[0], y - q[1]) < r + q[2] + 2 for q in tree_pts
                   if abs(x - q[0]) < 40 and abs(y - q[1]) < 40):
                continue
            prot.append({"x_px": x, "y_px": y, "width_um": w, "height_um": w * rng.uniform(0.10, 0.30),
                         "shape": SHAPES[len(prot) % 3], "aspect": aspect, "angle": rng.uniform(0, np.pi),
                         "albedo": rng.uniform(0.9, 1.2) if rng.random() < 0.5 else 1.0})
            tree_pts.append((x, y, r))
        self.protrusions = prot

    # -- fields ---------------------------------------------------------------------------------
    def canvas_um(self, Y, X):
        H, W = self.shape
        u, v = 2 * X / W - 1, 2 * Y / H - 1
        bow = BOW_UM * (1 - u ** 2) * (1 - v ** 2) * (1 + self.twist * u * v)
        a, kx, ky, ph = self.tex
        tex = sum(a[i] * np.sin(kx[i] * X + ky[i] * Y + ph[i]) for i in range(len(a)))
        return bow + tex

    def paint(self, Y, X):
        """Paint index (0-based) at each point."""
        amp, lam, ph = self.warp
        Xw = X + amp[0] * np.sin(Y / lam[0] + ph[0])
        Yw = Y + amp[1] * np.sin(X / lam[1] + ph[1])
        best = np.full(np.shape(X), np.inf)
        lab = np.zeros(np.shape(X), np.int16)
        for i, (sx, sy) in enumerate(self.seeds):
            d = (Xw - sx) ** 2 + (Yw - sy) ** 2
            closer = d < best
            best = np.where(closer, d, best)
            lab = np.where(closer, self.seed_paint[i], lab)
        return lab

    def albedo(self, Y, X, lab):
        lam, ang, ph = self.mottle
        m = sum(np.sin(2 * np.pi / lam[i] * (np.cos(ang[i]) * X + np.sin(ang[i]) * Y) + ph[i]) for i in range(4))
        return PALETTE[lab] * (1 + 0.015 * m)[..., None]

    def protrusions_in(self, y0, x0, M, N):
        """Add every protrusion's height and albedo factor over the box rows y0..y0+M-1, columns x0..x0+N-1
        (x0, y0 may be fractional). Returns (height_um, albedo_factor)."""
        h = np.zeros((M, N))
        f = np.ones((M, N))
        for p in self.protrusions:
            a = 0.5 * p["width_um"] / PIXEL_UM * np.sqrt(p["aspect"])      # semi-axes (px), a*b = r^2
            b = 0.5 * p["width_um"] / PIXEL_UM / np.sqrt(p["aspect"])
            c0, c1 = int(np.floor(p["x_px"] - a - x0)) - 1, int(np.ceil(p["x_px"] + a - x0)) + 2
            r0, r1 = int(np.floor(p["y_px"] - a - y0)) - 1, int(np.ceil(p["y_px"] + a - y0)) + 2
            c0, r0, c1, r1 = max(c0, 0), max(r0, 0), min(c1, N), min(r1, M)
            if c0 >= c1 or r0 >= r1:
                continue
            yy, xx = np.mgrid[r0:r1, c0:c1].astype(np.float64)
            dx, dy = xx + x0 - p["x_px"], yy + y0 - p["y_px"]
            ca, sa = np.cos(p["angle"]), np.sin(p["angle"])
            u, v = (ca * dx + sa * dy) / a, (-sa * dx + ca * dy) / b
            rho = np.sqrt(u ** 2 + v ** 2)
            inside = rho < 1
            if p["shape"] == "dome":
                z = np.cos(0.5 * np.pi * rho) ** 2
            elif p["shape"] == "crater":
                z = np.sin(np.pi * rho) ** 2 * np.where(rho < 0.5, 0.5 + rho, 1.0)
            else:
                z = np.where(rho < 0.6, 1.0, np.cos(0.5 * np.pi * (rho - 0.6) / 0.4) ** 2)
            z = np.where(inside, z, 0.0)
            h[r0:r1, c0:c1] += p["height_um"] * z
            if p["albedo"] != 1.0:
                f[r0:r1, c0:c1] *= np.where(inside, 1 + (p["albedo"] - 1) * np.minimum(1.0, 2 * (1 - rho)), 1.0)
        return h, f

    def height_box(self, y0, x0, M, N):
        yy, xx = np.mgrid[0:M, 0:N].astype(np.float64)
        Y, X = yy + y0, xx + x0
        hp, fp = self.protrusions_in(y0, x0, M, N)
        return self.canvas_um(Y, X) + hp, fp, Y, X


def rig(seed: int) -> dict:
    """The rig's lamps: positions (mm from the field's centre, world frame: x right, y up, z to the camera),
    beam aims (mm, on the canvas) and powers."""
    rng = np.random.default_rng(seed + 1000)
    az = np.linspace(0, 2 * np.pi, N_LAMPS, endpoint=False) + rng.uniform(-0.2, 0.2, N_LAMPS)
    el = np.deg2rad(rng.uniform(25, 55, N_LAMPS))
    dist = rng.uniform(280, 420, N_LAMPS)
    pos = np.column_stack([dist * np.cos(el) * np.cos(az), dist * np.cos(el) * np.sin(az), dist * np.sin(el)])
    aim = np.column_stack([rng.uniform(-4, 4, N_LAMPS), rng.uniform(-4, 4, N_LAMPS), np.zeros(N_LAMPS)])
    return {"positions_mm": pos, "aim_mm": aim, "power": rng.uniform(0.97, 1.03, N_LAMPS)}


def render_tile(scene: Scene, lamps: dict, x0: float, y0: float, exposure: float, rng) -> np.ndarray:
    """(K, M, N, 3) uint16 images of the tile whose pixel (0, 0) is painting (x0, y0)."""
    M, N = TILE
    h, fp, Y, X = scene.height_box(y0 - 1, x0 - 1, M + 2, N + 2)
    gx = (h[1:-1, 2:] - h[1:-1, :-2]) / (2 * PIXEL_UM)          # dh/dx, x right
    gy = -(h[2:, 1:-1] - h[:-2, 1:-1]) / (2 * PIXEL_UM)         # dh/dy, y up
    n = np.stack([-gx, -gy, np.ones_like(gx)], axis=-1)
    n /= np.linalg.norm(n, axis=-1, keepdims=True)
    Yc, Xc, hc = Y[1:-1, 1:-1], X[1:-1, 1:-1], h[1:-1, 1:-1]
    lab = scene.paint(Yc, Xc)
    alb = scene.albedo(Yc, Xc, lab) * fp[1:-1, 1:-1, None]
    rr, cc = np.mgrid[0:M, 0:N].astype(np.float64)
    P = np.stack([(cc - (N - 1) / 2) * PIXEL_UM / 1000, ((M - 1) / 2 - rr) * PIXEL_UM / 1000, hc / 1000], axis=-1)
    rad2 = ((cc - (N - 1) / 2) ** 2 + (rr - (M - 1) / 2) ** 2) / (((N - 1) / 2) ** 2 + ((M - 1) / 2) ** 2)
    vignette = 1 - 0.06 * rad2
    out = np.empty((N_LAMPS, M, N, 3), np.uint16)
    for k in range(N_LAMPS):
        L = lamps["positions_mm"][k]
        v = L - P
        d = np.linalg.norm(v, axis=-1)
        lam = np.maximum(np.einsum("ijk,ijk->ij", n, v) / d, 0)
        axis = lamps["aim_mm"][k] - L
        axis /= np.linalg.norm(axis)
        cosb = np.einsum("ijk,k->ij", -v, axis) / d
        beam = np.clip(cosb, 0, 1) ** 30
        E = 42000.0 * lamps["power"][k] * exposure * (np.linalg.norm(L) / d) ** 2 * beam * lam * vignette
        mean = alb * E[..., None]
        counts = rng.poisson(np.maximum(mean, 0)) + rng.normal(0, 3.0, mean.shape)
        out[k] = np.clip(np.rint(counts), 0, 65535).astype(np.uint16)
    return out


def _write_layout(path: Path, corners: dict):
    with open(path, "w", newline="", encoding="utf-8") as fh:
        w = csv.writer(fh, lineterminator="\n")
        w.writerow(["capture", "x_px", "y_px"])
        for name, (x, y) in corners.items():
            w.writerow([name, f"{x:.3f}", f"{y:.3f}"])


def render(folder: Path, seed: int) -> None:
    """Write ``folder/tiles/<rRcC>/uv_NN.tif``, ``folder/lights_positions_mm.csv``, ``folder/layout.csv`` and
    ``folder/truth/``."""
    folder = Path(folder)
    (folder / "tiles").mkdir(parents=True, exist_ok=False)
    (folder / "truth").mkdir()
    scene = Scene(seed)
    lamps = rig(seed)
    rng = np.random.default_rng(seed + 2000)
    cols, rows = GRID
    names = [f"r{r + 1}c{c + 1}" for r in range(rows) for c in range(cols)]
    nominal = {nm: (PAD + (i % cols) * scene.step[0], PAD + (i // cols) * scene.step[1]) for i, nm in enumerate(names)}
    err = rng.uniform(-STAGE_PX, STAGE_PX, (len(names), 2))
    err -= err.mean(axis=0)
    err *= min(1.0, STAGE_PX / np.abs(err).max())
    true = {nm: (nominal[nm][0] + err[i, 0], nominal[nm][1] + err[i, 1]) for i, nm in enumerate(names)}
    exposure = rng.uniform(0.95, 1.05, len(names))
    files = [f"uv_{k:02d}.tif" for k in range(N_LAMPS)]
    with open(folder / "lights_positions_mm.csv", "w", newline="", encoding="utf-8") as fh:
        w = csv.writer(fh, lineterminator="\n")
        w.writerow(["file", "x_mm", "y_mm", "z_mm"])
        for f, p in zip(files, lamps["positions_mm"]):
            w.writerow([f, *(f"{v:.3f}" for v in p)])
    for i, nm in enumerate(names):
        t0 = time.perf_counter()
        imgs = render_tile(scene, lamps, *true[nm], exposure[i], rng)
        (folder / "tiles" / nm).mkdir()
        for f, img in zip(files, imgs):
            tifffile.imwrite(folder / "tiles" / nm / f, img, photometric="rgb", resolution=(1 / PIXEL_UM, 1 / PIXEL_UM),
                             resolutionunit="NONE", description="ImageJ=1.54f\nunit=micron\n", metadata=None)
        print(f"tile {nm} at ({true[nm][0]:.2f}, {true[nm][1]:.2f}) {time.perf_counter() - t0:.1f} s", flush=True)
    _write_layout(folder / "layout.csv", nominal)
    _write_layout(folder / "truth" / "layout.csv", true)
    H, W = scene.shape
    height = np.empty((H, W), np.float32)
    paints = np.empty((H, W), np.uint8)
    for y in range(0, H, 256):
        m = min(256, H - y)
        hh, _, Y, X = scene.height_box(y, 0, m, W)
        height[y:y + m] = hh
        paints[y:y + m] = scene.paint(Y, X) + 1
    tifffile.imwrite(folder / "truth" / "height_um.tif", height, imagej=True, resolution=(1 / PIXEL_UM, 1 / PIXEL_UM),
                     metadata={"unit": "micron"})
    tifffile.imwrite(folder / "truth" / "paints.tif", paints, imagej=True, resolution=(1 / PIXEL_UM, 1 / PIXEL_UM),
                     metadata={"unit": "micron"})
    with open(folder / "truth" / "protrusions.csv", "w", newline="", encoding="utf-8") as fh:
        w = csv.writer(fh, lineterminator="\n")
        w.writerow(["id", "x_px", "y_px", "width_um", "height_um", "shape", "aspect", "paint"])
        for i, p in enumerate(scene.protrusions):
            w.writerow([i + 1, f"{p['x_px']:.3f}", f"{p['y_px']:.3f}", f"{p['width_um']:.2f}", f"{p['height_um']:.3f}",
                        p["shape"], f"{p['aspect']:.3f}", int(paints[int(round(min(p['y_px'], H - 1))),
                                                                         int(round(min(p['x_px'], W - 1)))])])
    (folder / "truth" / "painting.json").write_text(json.dumps({
        "seed": seed, "grid": list(GRID), "tile_shape": list(TILE), "overlap": OVERLAP, "stage_error_px": STAGE_PX,
        "pixel_size_um": PIXEL_UM, "shape": [H, W], "lamps": N_LAMPS, "paints": N_PAINTS,
        "protrusions": len(scene.protrusions), "bow_um": BOW_UM,
        "tiles": [{"name": nm, "nominal": list(nominal[nm]), "true": list(true[nm]), "exposure": float(exposure[i])}
                  for i, nm in enumerate(names)]}, indent=1))


# ------------------------------------------------------------------------------------------------
# scoring (a matcher of its own: nothing from uvps)
# ------------------------------------------------------------------------------------------------

def read_csv(path) -> list:
    with open(path, newline="", encoding="utf-8") as fh:
        return list(csv.DictReader(fh))


def read_layout(path) -> dict:
    return {r["capture"]: (float(r["x_px"]), float(r["y_px"])) for r in read_csv(path)}


def match(tx, ty, tw, fx, fy, fw):
    """One-to-one pairs (truth, found), closest first, centres within max(2 px, half the larger width)."""
    if not len(tx) or not len(fx):
        return np.zeros((0, 2), int)
    tree = cKDTree(np.column_stack([fx, fy]))
    rmax = max(2.0, 0.5 * max(np.max(tw), np.max(fw)) / PIXEL_UM)
    cand = []
    for i, js in enumerate(tree.query_ball_point(np.column_stack([tx, ty]), rmax)):
        for j in js:
            d = np.hypot(tx[i] - fx[j], ty[i] - fy[j])
            if d <= max(2.0, 0.5 * max(tw[i], fw[j]) / PIXEL_UM):
                cand.append((d, i, j))
    cand.sort()
    ut, uf, pairs = set(), set(), []
    for d, i, j in cand:
        if i not in ut and j not in uf:
            ut.add(i), uf.add(j), pairs.append((i, j))
    return np.array(pairs, int).reshape(-1, 2)


def score_detection(truth: list, found: list, corners: dict, min_width_um=60.0) -> dict:
    M, N = TILE
    tx, ty, tw = (np.array([float(r[c]) for r in truth]) for c in ("x_px", "y_px", "width_um"))
    inside, touching = np.zeros(tx.size, bool), np.zeros(tx.size, bool)
    half = 0.5 * tw / PIXEL_UM + 1
    for x0, y0 in corners.values():
        inside |= (tx >= x0) & (tx <= x0 + N - 1) & (ty >= y0) & (ty <= y0 + M - 1)
        touching |= (tx >= x0 - half) & (tx <= x0 + N - 1 + half) & (ty >= y0 - half) & (ty <= y0 + M - 1 + half)
    edge_only = (touching & ~inside)[touching]
    tx, ty, tw = tx[touching], ty[touching], tw[touching]
    fx, fy = (np.array([float(r[c]) for r in found]) for c in ("x_px", "y_px"))
    fw = np.nan_to_num(np.array([float(r["width_um"] or "nan") for r in found]))
    pairs = match(tx, ty, tw, fx, fy, fw)
    t2f, f2t = np.full(tx.size, -1), np.full(fx.size, -1)
    if len(pairs):
        t2f[pairs[:, 0]], f2t[pairs[:, 1]] = pairs[:, 1], pairs[:, 0]
    cut = (f2t >= 0) & edge_only[np.maximum(f2t, 0)]
    f2t, fw, fx, fy = f2t[~cut], fw[~cut], fx[~cut], fy[~cut]
    t2f[edge_only] = -2
    big = (tw >= min_width_um) & ~edge_only
    cls = np.where(f2t >= 0, tw[np.maximum(f2t, 0)], fw) >= min_width_um
    rec = float(np.mean(t2f[big] >= 0))
    prec = float(np.mean(f2t[cls] >= 0))
    twice = 0
    for j in np.flatnonzero(f2t < 0):
        d = np.hypot(tx - fx[j], ty - fy[j]) * PIXEL_UM
        near = np.flatnonzero(d <= np.maximum(2 * PIXEL_UM, 0.5 * np.maximum(tw, fw[j])))
        twice += bool(np.any(t2f[near] >= 0))
    # recall by width class, for the report
    by = {}
    for lo, hi in ((60, 100), (100, 200), (200, 401)):
        sel = big & (tw >= lo) & (tw < hi)
        by[f"recall_{lo}_{hi}"] = float(np.mean(t2f[sel] >= 0)) if sel.any() else float("nan")
    return {"true": int(big.sum()), "detected": int(cls.sum()), "recall": rec, "precision": prec,
            "f1": 2 * prec * rec / (prec + rec) if prec + rec else 0.0, "twice": int(twice),
            "count_ratio": float(cls.sum() / big.sum()), **by}


def score_height(height, origin, truth_height, corners, margin=4) -> dict:
    """rms of (map - truth) after one least-squares plane, over the painting and its overlap bands."""
    M, N = height.shape
    tm, tn = TILE
    rr, cc = np.mgrid[0:M, 0:N].astype(np.float64)
    Y, X = rr + origin[1], cc + origin[0]
    truth = ndimage.map_coordinates(np.asarray(truth_height, np.float64), [Y, X], order=1, mode="nearest")
    cover = np.zeros((M, N), np.int16)
    for x0, y0 in corners.values():
        cover += (X >= x0) & (X <= x0 + tn - 1) & (Y >= y0) & (Y <= y0 + tm - 1)
    inner = ndimage.binary_erosion(cover > 0, iterations=margin) & np.isfinite(height)
    d = (np.asarray(height, np.float64) - truth)[inner]
    A = np.column_stack([np.ones(d.size), X[inner], Y[inner]])
    coef, *_ = np.linalg.lstsq(A, d, rcond=None)
    res = d - A @ coef
    band = (cover >= 2)[inner]
    return {"rms_um": float(np.sqrt(np.mean(res ** 2))), "overlap_rms_um": float(np.sqrt(np.mean(res[band] ** 2))),
            "p99_abs_um": float(np.percentile(np.abs(res), 99))}


class RSSSampler(threading.Thread):
    """Peak summed RSS of a process and its descendants (Linux /proc), sampled every 0.5 s."""

    def __init__(self, pid: int):
        super().__init__(daemon=True)
        self.pid, self.peak_mb, self.stop = pid, 0.0, threading.Event()

    def _tree(self):
        kids = {}
        for d in os.listdir("/proc"):
            if d.isdigit():
                try:
                    with open(f"/proc/{d}/stat") as fh:
                        ppid = int(fh.read().rsplit(")", 1)[1].split()[1])
                    kids.setdefault(ppid, []).append(int(d))
                except (OSError, ValueError, IndexError):
                    pass
        todo, seen = [self.pid], []
        while todo:
            p = todo.pop()
            seen.append(p)
            todo.extend(kids.get(p, []))
        return seen

    def run(self):
        while not self.stop.is_set():
            total = 0
            for p in self._tree():
                try:
                    with open(f"/proc/{p}/status") as fh:
                        for line in fh:
                            if line.startswith("VmRSS:"):
                                total += int(line.split()[1]) / 1024
                except OSError:
                    pass
            self.peak_mb = max(self.peak_mb, total)
            self.stop.wait(0.5)


def run(src: Path, out: Path, workers: int) -> dict:
    """``uvps batch --mosaic`` on the rendered painting ``src`` into ``out`` (a finished ``out``: its tiles
    skipped, the painting stitched again), timed, then :func:`score`."""
    cmd = [sys.executable, "-m", "uvps", "batch", str(src / "tiles"), "-o", str(out), "--lights",
           str(src / "lights_positions_mm.csv"), "--regions", "auto", "--mosaic", str(src / "layout.csv"),
           "--workers", str(workers)]
    load0 = os.getloadavg()[0]
    t0 = time.perf_counter()
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    sampler = RSSSampler(proc.pid)
    sampler.start()
    stdout, stderr = proc.communicate()
    elapsed = time.perf_counter() - t0
    sampler.stop.set()
    sampler.join()
    load1 = os.getloadavg()[0]
    if proc.returncode:
        raise SystemExit(stderr)
    warnings = [ln for ln in stderr.splitlines() if "warning" in ln.lower()]
    log = json.loads((out / "batch.json").read_text())
    tiles_s = sum(c["elapsed_s"] for c in log["captures"])
    return {**score(src, out), "batch_s": elapsed, "tiles_sum_s": tiles_s, "workers": workers,
            "ratio_to_ideal": elapsed / (tiles_s / workers), "peak_rss_mb": sampler.peak_mb,
            "load": [round(load0, 1), round(load1, 1)], "warnings": warnings,
            **{f"batch_{k}": v for k, v in log.get("timings", {}).items()}}


def score(src: Path, out: Path) -> dict:
    """The painting of a finished batch folder ``out`` scored against the truth of ``src`` (no run)."""
    import zarr
    truth_layout = read_layout(src / "truth" / "layout.csv")
    refined = read_layout(out / "painting" / "layout.csv")
    nominal = read_layout(src / "layout.csv")
    err = [float(np.hypot(*np.subtract(refined[k], truth_layout[k]))) for k in truth_layout]
    nominal_err = [float(np.hypot(*np.subtract(nominal[k], truth_layout[k]))) for k in truth_layout]
    s = score_detection(read_csv(src / "truth" / "protrusions.csv"),
                        read_csv(out / "painting" / "painting_protrusions.csv"), truth_layout)
    meta = json.loads((out / "painting" / "painting.json").read_text())
    h = np.asarray(zarr.open_group(str(out / "painting" / "height.ome.zarr"), mode="r")["0"])
    hs = score_height(h, meta["origin_px"], tifffile.imread(src / "truth" / "height_um.tif"), truth_layout)
    regions = read_csv(out / "painting" / "painting_regions.csv")
    return {"tiles": len(truth_layout), "tile_shape": list(TILE), "nominal_err_px": max(nominal_err),
            "corner_err_px": max(err), "max_residual_px": meta["max_residual_px"], **s,
            **{f"height_{k}": v for k, v in hs.items()}, "areas": len(regions) - 1, "paints": N_PAINTS,
            **{f"stitch_{k}": v for k, v in meta["timings"].items()}}


_HEAD = ("| painting | corner error (px) | F1 >= 60 um | counted twice | count / truth | height rms (um) | "
         "on overlaps (um) | colour areas / paints | batch (s) | tiles' sum / {w} workers (s) | ratio | peak RSS (MB) | load |\n"
         "|---|---|---|---|---|---|---|---|---|---|---|---|---|\n")


def register(src: Path, out: Path) -> dict:
    """The registration alone (``uvps.core.mosaic.register_tiles`` on the tiles' ``albedo.tif``, as the batch
    calls it, within a quarter of the smaller tile side) on a finished run's folders ``out/rNcM``, scored
    against the true corners: the worst and median corner error and each pair's error and use."""
    from uvps.core.mosaic import register_tiles
    from uvps.painting import AlbedoTile

    truth, nominal = read_layout(src / "truth" / "layout.csv"), read_layout(src / "layout.csv")
    albedo = {k: AlbedoTile(out / k) for k in nominal}
    t0 = time.perf_counter()
    reg = register_tiles(albedo, nominal, max_shift_px=0.25 * min(min(a.shape) for a in albedo.values()))
    elapsed = time.perf_counter() - t0
    err = {k: float(np.hypot(*np.subtract(reg.corners[k], truth[k]))) for k in truth}
    pairs = {p.name: {"err_px": round(float(np.hypot(p.dx - truth[p.b][0] + truth[p.a][0],
                                                     p.dy - truth[p.b][1] + truth[p.a][1])), 3),
                      "used": p.used, "residual_px": p.residual_px and round(p.residual_px, 3)} for p in reg.pairs}
    return {"corner_err_px": max(err.values()), "corner_err_median_px": float(np.median(list(err.values()))),
            "register_s": elapsed, "load": round(os.getloadavg()[0], 1), "pairs": pairs}


def render_doc(results: dict) -> str:
    """docs/benchmarks.md's ``heldout`` table: one row per held-out run kept in docs/benchmarks/heldout.json."""
    lines = [_HEAD.format(w=results["rows"][0]["workers"])]
    for r in results["rows"]:
        lines.append(f"| {r['label']} | {r['corner_err_px']:.2f} | {r['f1']:.3f} | {r['twice']} | "
                     f"{r['count_ratio']:.3f} | {r['height_rms_um']:.2f} | {r['height_overlap_rms_um']:.2f} | "
                     f"{r['areas']} / {r['paints']} | {r['batch_s']:.0f} | {r['tiles_sum_s'] / r['workers']:.0f} | "
                     f"{r['ratio_to_ideal']:.2f} | {r['peak_rss_mb']:.0f} | {r['load'][0]:.1f}-{r['load'][1]:.1f} |\n")
    return "".join(lines)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = ap.add_subparsers(dest="cmd", required=True)
    r = sub.add_parser("render", help="render the held-out painting into FOLDER (new)")
    r.add_argument("folder", type=Path)
    r.add_argument("--seed", type=int, default=7)
    s = sub.add_parser("run", help="run uvps batch --mosaic on a rendered painting and score it")
    s.add_argument("folder", type=Path)
    s.add_argument("-o", "--output", type=Path, required=True)
    s.add_argument("--workers", type=int, default=2)
    s.add_argument("--label", default=None, help="the row's name in the doc's table")
    s.add_argument("--doc", action="store_true",
                   help="add the row to docs/benchmarks/heldout.json and rewrite docs/benchmarks.md's section heldout")
    g = sub.add_parser("register", help="re-run the registration alone on a finished run's folders and score it")
    g.add_argument("folder", type=Path)
    g.add_argument("-o", "--output", type=Path, required=True, help="the run's output (its rNcM folders)")
    c = sub.add_parser("score", help="score the painting of a finished batch folder OUT (nothing run)")
    c.add_argument("folder", type=Path)
    c.add_argument("-o", "--output", type=Path, required=True)
    c.add_argument("--label", default=None, help="the row's name in the doc's table")
    c.add_argument("--doc", action="store_true",
                   help="replace the scores (not the batch's times, memory and load) of the row of that label in "
                        "docs/benchmarks/heldout.json, e.g. after `run` stitched a finished folder again, and rewrite "
                        "docs/benchmarks.md's section heldout")
    args = ap.parse_args(argv)
    if args.cmd == "render":
        render(args.folder, args.seed)
        return
    if args.cmd == "register":
        print(json.dumps(register(args.folder, args.output)), flush=True)
        return
    seed = json.loads((args.folder / "truth" / "painting.json").read_text())["seed"]
    label = args.label or f"held-out seed {seed}, 4 x 3 of 1200 x 900"
    if args.cmd == "score":
        row = {"label": label, "seed": seed, **score(args.folder, args.output)}
    else:
        row = {"label": label, "seed": seed, **run(args.folder, args.output, args.workers)}
    print(json.dumps({k: round(v, 4) if isinstance(v, float) else v for k, v in row.items()}), flush=True)
    if args.doc:
        sys.path.insert(0, str(Path(__file__).resolve().parent))
        from benchdoc import JSON_DIR, write_doc
        path = JSON_DIR / f"{DOC_SECTION}.json"
        old = json.loads(path.read_text())["rows"] if path.exists() else []
        if args.cmd == "score":   # the row's batch (times, memory, load) kept, its scores replaced
            kept = [o for o in old if o["label"] == row["label"]]
            if not kept:
                raise SystemExit(f"no row {row['label']!r} in {path} to score again")
            row = {**kept[0], **{k: v for k, v in row.items() if not k.startswith("stitch_")}, "rescored": True}
        results = {"argv": list(sys.argv[1:] if argv is None else argv),
                   "rows": [o if o["label"] != row["label"] else row for o in old]
                   + ([row] if row["label"] not in {o["label"] for o in old} else [])}
        print("wrote", write_doc(DOC_SECTION, results, render_doc(results), source="scripts/heldout_painting.py"))


if __name__ == "__main__":
    main()
