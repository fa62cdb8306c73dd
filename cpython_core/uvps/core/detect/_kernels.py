"""The detector's compiled kernels (numba) with their numpy twins.

Each kernel is hand-written because no library computes it at the needed cost; each has a
reference it is tested against in ``tests/test_detect.py``: the diameter opening's filter
against :func:`skimage.morphology.diameter_opening`, the floods beside long structures against
the exact diameter opening, the robust plane against :func:`_robust_plane_numpy`."""
from __future__ import annotations

import heapq

import numba
import numpy as np

from ._common import _median


@numba.njit(nogil=True, cache=True)
def _diameter_filter(flat, parent, order, ncols, threshold):  # pragma: no cover - compiled
    """The diameter opening on a max-tree (``parent``, ``order`` of
    :func:`skimage.morphology.max_tree`): each node's bounding box gathered from its children
    in one pass up the tree, then each pixel keeps its level when its node's extension
    (largest side of the box) reaches ``threshold``, else its parent's output."""
    n = flat.size
    rmin = np.empty(n, np.int32)
    rmax = np.empty(n, np.int32)
    cmin = np.empty(n, np.int32)
    cmax = np.empty(n, np.int32)
    for i in range(n):
        r = i // ncols
        rmin[i] = r
        rmax[i] = r
        cmin[i] = i - r * ncols
        cmax[i] = i - r * ncols
    for k in range(n - 1, 0, -1):              # children before their parents
        i = order[k]
        q = parent[i]
        rmin[q] = min(rmin[q], rmin[i])
        rmax[q] = max(rmax[q], rmax[i])
        cmin[q] = min(cmin[q], cmin[i])
        cmax[q] = max(cmax[q], cmax[i])
    out = np.empty_like(flat)
    out[order[0]] = flat[order[0]]
    for k in range(1, n):                      # parents before their children
        i = order[k]
        q = parent[i]
        if flat[i] == flat[q]:                 # a pixel of its parent's level component
            out[i] = out[q]
        elif max(rmax[i] - rmin[i], cmax[i] - cmin[i]) + 1 >= threshold:
            out[i] = flat[i]
        else:
            out[i] = out[q]
    return out


@numba.njit(nogil=True, cache=True)
def _flood_beside(h, t, seeds, need, length, width, max_area, floor, out):  # pragma: no cover - compiled
    """:func:`_beside_long`'s floods, in place on ``out`` (a copy of ``t``). Returns how many
    seeds were raised.

    From each seed (flat indices, highest first), a priority flood (4-connected, highest
    boundary pixel first) visits the level sets of ``h`` containing it in decreasing level. It
    gives up on the seed when the visited set is ``width`` wide before it lies ``need`` below
    the seed (texture, a crest: not a small compact object), or when it covers ``max_area``
    (larger than any protrusion) before it is long. It stops when the visited set's extent
    (mirrored at the image borders, as :func:`_compact_relief` pads the image) reaches
    ``length``: the level it has fallen to, ``lam``, is where the seed's level set becomes
    long, the exact diameter opening at the seed. The seed's own hill is what the flood visited
    before it first climbed, over a saddle, above the seed or more than ``floor`` above that
    saddle. When the seed stands ``need`` above ``lam`` and the block maxima gave its hill no
    relief (``t`` below ``floor`` wherever the hill stands ``floor`` above ``lam``), those pixels
    of the hill get ``h - lam``: the exact compact relief (tested against
    :func:`skimage.morphology.diameter_opening`); not when a pixel of the hill that high lies on
    the image's border."""
    m, n = h.shape
    hf = h.ravel()
    tf = t.ravel()
    of = out.ravel()
    region = np.empty(max_area + 1, np.int64)
    stamp = np.full(m * n, -1, np.int32)
    done = np.zeros(m * n, np.bool_)
    raised = 0
    for s in range(seeds.size):
        p0 = seeds[s]
        if done[p0]:
            continue
        lam, cnt, own = _flood_one(hf, m, n, p0, s, need[s], length, width, max_area, floor,
                                   region, stamp)
        if lam != lam or hf[p0] - lam < need[s]:
            continue
        if own >= 0:
            cnt = own
        if not _hill_hidden(hf, tf, region, cnt, lam, floor, m, n):
            continue
        raised += 1
        for q in range(cnt):
            j = region[q]
            if hf[j] - lam >= floor:
                of[j] = max(of[j], hf[j] - lam)
                done[j] = True
    return raised


@numba.njit(nogil=True, cache=True)
def _flood_one(hf, m, n, p0, s, need_s, length, width, max_area, floor, region,
               stamp):  # pragma: no cover - compiled
    """One seed's priority flood of :func:`_flood_beside` (``stamp`` marks the pixels queued
    for seed ``s``; ``region`` receives the pixels visited, in order). Returns (``lam``: the
    level where the seed's level set reaches ``length``, NaN when the flood gave up; how many
    pixels were visited; how many before the flood first climbed over a saddle, -1 if never)."""
    top = hf[p0]
    heap = [(-np.float64(top), np.int64(p0))]      # heapq is a min-heap: minus the level
    stamp[p0] = s
    r0 = p0 // n
    c0 = p0 - r0 * n
    rmin, rmax, cmin, cmax = r0, r0, c0, c0
    cnt = 0
    own = -1
    run_min = top
    lam = np.nan
    while len(heap) > 0:
        negv, i = heapq.heappop(heap)
        v = -negv
        r = i // n
        c = i - r * n
        run_min = min(run_min, v)
        if own < 0 and (v > top or v > run_min + floor):
            own = cnt
        r_lo, r_hi, c_lo, c_hi = min(rmin, r), max(rmax, r), min(cmin, c), max(cmax, c)
        ext = _mirrored_extent(r_lo, r_hi, c_lo, c_hi, m, n)
        if ext >= length:
            lam = run_min
            break
        if ext >= width and top - run_min < need_s:
            break
        if cnt >= max_area:
            break
        region[cnt] = i
        cnt += 1
        rmin, rmax, cmin, cmax = r_lo, r_hi, c_lo, c_hi
        for d in range(4):
            if (d == 0 and r == 0) or (d == 1 and r == m - 1) or (d == 2 and c == 0) or \
                    (d == 3 and c == n - 1):
                continue
            j = i - n if d == 0 else (i + n if d == 1 else (i - 1 if d == 2 else i + 1))
            if stamp[j] != s:
                stamp[j] = s
                heapq.heappush(heap, (-np.float64(hf[j]), np.int64(j)))
    return lam, cnt, own


@numba.njit(nogil=True, cache=True)
def _mirrored_extent(r_lo, r_hi, c_lo, c_hi, m, n):  # pragma: no cover - compiled
    """The extent (px) of a set whose bounding box is rows ``r_lo..r_hi``, columns
    ``c_lo..c_hi`` with the image mirrored at its borders, as :func:`_compact_relief` pads it: a
    set touching a border is as long as itself and its mirror image."""
    er = r_hi - r_lo + 1
    if r_lo == 0:
        er = max(er, 2 * (r_hi + 1))
    if r_hi == m - 1:
        er = max(er, 2 * (m - r_lo))
    ec = c_hi - c_lo + 1
    if c_lo == 0:
        ec = max(ec, 2 * (c_hi + 1))
    if c_hi == n - 1:
        ec = max(ec, 2 * (n - c_lo))
    return max(er, ec)


@numba.njit(nogil=True, cache=True)
def _hill_hidden(hf, tf, region, cnt, lam, floor, m, n):  # pragma: no cover - compiled
    """Whether the seed's hill (the first ``cnt`` pixels of ``region``) got no relief from the
    block maxima (``tf`` below ``floor`` wherever it stands ``floor`` above ``lam``) and no
    pixel of it that high lies on the image's border (cut by the edge: a stroke leaving it?)."""
    for q in range(cnt):
        j = region[q]
        if hf[j] - lam < floor:
            continue
        r = j // n
        c = j - r * n
        if tf[j] >= floor or r == 0 or r == m - 1 or c == 0 or c == n - 1:
            return False
    return True


def _robust_plane(rows, cols, values):
    """Least-squares plane ``a + b row + c col`` refitted without the samples beyond 2.5 robust
    sigmas (a neighbouring bump or a crack in the surround); a constant (median) with fewer than
    8 samples. Returns a callable of (rows, cols).

    The fit is :func:`_robust_plane_kernel` (compiled); samples on one line (a singular system)
    go to :func:`_robust_plane_numpy`, whose least squares take the minimum-norm plane."""
    values = np.asarray(values, np.float64)
    if len(values) < 8:
        med = float(_median(values)) if len(values) else 0.0
        return lambda r, c: np.full(np.shape(r), med)
    rows, cols = np.asarray(rows, np.float64), np.asarray(cols, np.float64)
    coef, r0, c0, ok = _robust_plane_kernel(rows, cols, values)
    if not ok:
        return _robust_plane_numpy(rows, cols, values)
    return lambda r, c: coef[0] + coef[1] * (r - r0) + coef[2] * (c - c0)


def _robust_plane_numpy(rows, cols, values):
    """:func:`_robust_plane` in numpy (the reference of the compiled kernel, and its fallback for
    samples on one line): least squares in coordinates centred on the samples."""
    med = float(_median(values)) if len(values) else 0.0
    if len(values) < 8:
        return lambda r, c: np.full(np.shape(r), med)
    r0, c0 = float(np.mean(rows)), float(np.mean(cols))
    a = np.column_stack([np.ones(len(values)), rows - r0, cols - c0])
    keep = np.ones(len(values), bool)
    coef = np.array([med, 0.0, 0.0])
    for _ in range(3):
        if keep.sum() < 8:
            break
        coef, *_ = np.linalg.lstsq(a[keep], values[keep], rcond=None)
        res = values - a @ coef
        centre = _median(res[keep])
        spread = 1.4826 * _median(np.abs(res[keep] - centre)) + 1e-6
        new = np.abs(res - centre) <= 2.5 * spread
        if np.array_equal(new, keep):
            break
        keep = new
    return lambda r, c: coef[0] + coef[1] * (r - r0) + coef[2] * (c - c0)


@numba.njit(nogil=True, cache=True)
def _robust_plane_kernel(rows, cols, values):  # pragma: no cover - compiled
    """The robust plane fit of :func:`_robust_plane_numpy`, compiled.

    Hand-written because the fits are many and small (two per group of footprints, 1500 at
    4000 x 3000, a few hundred samples each), where numpy's per-call overhead (lstsq, medians,
    masks: ~0.6 ms per fit on a loaded core) was a quarter of the footprints' refinement. The
    normal equations in centred coordinates, solved by Gaussian elimination with partial
    pivoting. Returns (coefficients, row centre, column centre, ok); ok is False when the
    system is singular (samples on one line)."""
    n = values.size
    r0, c0 = rows.mean(), cols.mean()
    dr, dc = rows - r0, cols - c0
    coef = np.zeros(3)
    coef[0] = np.median(values)
    keep = np.ones(n, np.bool_)
    for _ in range(3):
        if keep.sum() < 8:
            break
        g = np.zeros((3, 4))                   # the normal equations, augmented
        for i in range(n):
            if keep[i]:
                x = (1.0, dr[i], dc[i])
                for j in range(3):
                    for k in range(3):
                        g[j, k] += x[j] * x[k]
                    g[j, 3] += x[j] * values[i]
        for j in range(3):                     # elimination with partial pivoting
            piv = j
            for k in range(j + 1, 3):
                if abs(g[k, j]) > abs(g[piv, j]):
                    piv = k
            if g[piv, j] == 0.0:
                return coef, r0, c0, False
            for k in range(4):
                g[j, k], g[piv, k] = g[piv, k], g[j, k]
            for k in range(j + 1, 3):
                f = g[k, j] / g[j, j]
                for q in range(j, 4):
                    g[k, q] -= f * g[j, q]
        for j in range(2, -1, -1):
            acc = g[j, 3]
            for k in range(j + 1, 3):
                acc -= g[j, k] * coef[k]
            coef[j] = acc / g[j, j]
        res = values - (coef[0] + coef[1] * dr + coef[2] * dc)
        centre = np.median(res[keep])
        spread = 1.4826 * np.median(np.abs(res[keep] - centre)) + 1e-6
        new = np.abs(res - centre) <= 2.5 * spread
        if np.array_equal(new, keep):
            break
        keep = new
    return coef, r0, c0, True
