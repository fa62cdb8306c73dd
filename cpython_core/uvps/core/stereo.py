"""Photometric stereo: per-pixel least squares with per-pixel near-light vectors.

Lambertian model (paper Eq. 1; Woodham 1978), near point lights (Huang et al. 2015)::

    I_k(x) = albedo(x) * n(x) . v_k(x),   v_k(x) = E_k (|L_k| / d)^2 (L_k - X) / d,  d = |L_k - X|

For each pixel, ``b = albedo * n`` solves the weighted normal equations ``(sum w V V^T) b = sum w V I``
on the grey (channel-mean) intensities; ``n = b / |b|``. The RGB albedo (the fluorescence colour) is
then fitted per channel with the normal fixed. Shadowed (attached shadow or too dark) and saturated
samples are left out per pixel (unless :data:`EVERY_SAMPLE` turns the rules off: plain least squares, which
the pipeline uses where the model does not hold, :func:`uvps.core.pipeline.sample_mode`); a pixel with fewer
than three usable lights is NaN and counted.
``robust=True`` is rank-trimmed least squares: each pixel keeps only its samples ranked between the
25th and 90th percentile of its brightness (relative to each light's irradiance there), so cast
shadows and dimmed samples at the bottom and specular highlights at the top no longer pull the
normal; for captures with many lights (RTI domes, visible light). Work proceeds in bands of rows so
that memory stays proportional to one band (the stack may be memory-mapped, :class:`uvps.files.io.MappedStack`);
each pixel is solved in one compiled pass over its samples (:func:`_solve_pixels`; without rank trimming
:func:`_solve_lanes`, the same arithmetic for 128 pixels side by side).
"""
from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import NamedTuple

import numba
import numpy as np

from ..errors import UVPSInputError
from .irradiance import LightModel, near_scale_compiled, pixel_coordinates_mm
from .progress import Progress, report
from .stack import float_band
from .threads import default_threads, map_bands

log = logging.getLogger(__name__)

__all__ = ["StereoResult", "solve_normals", "EVERY_SAMPLE"]


@dataclass
class StereoResult:
    """Normals, albedo and per-pixel diagnostics of :func:`solve_normals`."""

    normals: np.ndarray        # (M, N, 3) float32, NaN where unsolved
    albedo: np.ndarray         # (M, N) or (M, N, C) float32, in image counts per unit irradiance
    n_used: np.ndarray         # (M, N) uint8: lights used per pixel
    n_invalid: int             # pixels with fewer than 3 usable lights (inside the mask)
    residual_rms: float        # rms residual over the used samples / rms of their pixels' mean brightness


#: :func:`solve_normals`'s sample rules off: plain least squares over every sample (no saturation, dark or
#: attached-shadow test; samples of 0 counts kept). Pass as ``**EVERY_SAMPLE``.
EVERY_SAMPLE = {"saturation": None, "dark_fraction": -1.0, "shadow_cos": float("-inf")}


#: Pixels per band of :func:`solve_normals`: a band in flight holds its samples as float32
#: (K x 65536 x C x 4 bytes: 12.6 MB for 16 RGB images); smaller bands add per-band overhead.
CHUNK_PIXELS = 65536


_JIT = dict(nogil=True, cache=True, fastmath=False)
#: :func:`_solve_lanes`: a float division by 0 gives inf / NaN (numpy's rule) instead of raising, which spares
#: each division a test and branch that keeps its lane loops out of SIMD registers (15-20 % of that kernel).
_JIT_LANES = dict(_JIT, error_model="numpy")


@numba.njit(inline="always", **_JIT)
def _grey_and_bright(band, p, grey, bright):  # pragma: no cover - compiled
    """Each sample's grey level (mean of the channels) and brightest channel; returns the largest grey."""
    K, _, C = band.shape
    gmax = np.float32(-np.inf)
    for k in range(K):
        g = band[k, p, 0]
        br = g
        for c in range(1, C):
            v = band[k, p, c]
            g += v
            if v > br:
                br = v
        g = g / np.float32(C)
        grey[k] = g
        bright[k] = br
        if g > gmax:
            gmax = g
    return gmax


@numba.njit(inline="always", **_JIT)
def _light_vectors(near, L, E, dirs, x, y, V, vn):  # pragma: no cover - compiled
    """Each lamp's irradiance vector at the pixel (x, y) mm (:mod:`uvps.core.irradiance`): near lamps with
    inverse square and their direction from the pixel, far ones as given; ``vn`` their lengths."""
    for k in range(V.shape[0]):
        if near:
            d0 = np.float32(L[k, 0]) - x
            d1 = np.float32(L[k, 1]) - y
            d2 = np.float32(L[k, 2])
            f = near_scale_compiled(d0, d1, d2, np.float32(E[k] * (L[k, 0] ** 2 + L[k, 1] ** 2 + L[k, 2] ** 2)))
            V[k, 0] = d0 * f
            V[k, 1] = d1 * f
            V[k, 2] = d2 * f
        else:
            V[k, 0] = dirs[k, 0]
            V[k, 1] = dirs[k, 1]
            V[k, 2] = dirs[k, 2]
        vn[k] = np.sqrt(V[k, 0] * V[k, 0] + V[k, 1] * V[k, 1] + V[k, 2] * V[k, 2])


@numba.njit(inline="always", **_JIT)
def _usable_samples(grey, bright, vn, thr, use_p, sat, lo, hi, ratio, w):  # pragma: no cover - compiled
    """``w[k]`` 1 for a sample that is lit (above ``thr``, and above 0 unless ``thr`` < 0), not saturated and, with ranks (``hi`` > 0),
    within the kept brightness ranks ``lo .. hi - 1``; else 0."""
    K = grey.shape[0]
    for k in range(K):
        # thr < 0 (every sample, :data:`EVERY_SAMPLE`): a sample of 0 counts is kept like any other
        ok = grey[k] > thr and (thr < 0 or grey[k] > 0) and use_p
        if sat > 0 and bright[k] >= sat:
            ok = False
        w[k] = 1.0 if ok else 0.0
    if hi > 0:
        for k in range(K):
            ratio[k] = grey[k] / vn[k]
        srt = np.sort(ratio)
        a_lo = srt[lo]
        a_hi = srt[hi - 1]
        for k in range(K):
            if not (ratio[k] >= a_lo and ratio[k] <= a_hi):
                w[k] = 0.0


@numba.njit(inline="always", **_JIT)
def _weighted_solve(V, grey, w):  # pragma: no cover - compiled
    """``b`` minimising sum_k w_k (V_k . b - grey_k)^2: the 3 x 3 normal equations in float64, solved
    in closed form (adjugate); NaN when singular."""
    a00 = a01 = a02 = a11 = a12 = a22 = 0.0
    y0 = y1 = y2 = 0.0
    for k in range(V.shape[0]):
        if w[k] == 0.0:
            continue
        v0, v1, v2 = V[k, 0], V[k, 1], V[k, 2]
        a00 += v0 * v0
        a01 += v0 * v1
        a02 += v0 * v2
        a11 += v1 * v1
        a12 += v1 * v2
        a22 += v2 * v2
        y0 += v0 * grey[k]
        y1 += v1 * grey[k]
        y2 += v2 * grey[k]
    return _closed_form(a00, a01, a02, a11, a12, a22, y0, y1, y2)


@numba.njit(inline="always", **_JIT)
def _closed_form(a00, a01, a02, a11, a12, a22, y0, y1, y2):  # pragma: no cover - compiled
    """The symmetric 3 x 3 system ``A b = y`` solved by its adjugate (float64); NaN when singular."""
    c00 = a11 * a22 - a12 * a12
    c01 = a02 * a12 - a01 * a22
    c02 = a01 * a12 - a02 * a11
    c11 = a00 * a22 - a02 * a02
    c12 = a01 * a02 - a00 * a12
    c22 = a00 * a11 - a01 * a01
    det = a00 * c00 + a01 * c01 + a02 * c02
    tr = a00 + a11 + a22
    if abs(det) > 1e-12 * max(tr ** 3, 1e-30):
        inv = 1.0 / det
        return ((c00 * y0 + c01 * y1 + c02 * y2) * inv, (c01 * y0 + c11 * y1 + c12 * y2) * inv,
                (c02 * y0 + c12 * y1 + c22 * y2) * inv)
    return np.nan, np.nan, np.nan


@numba.njit(inline="always", **_JIT)
def _solve_with_shadows(V, vn, grey, w, pred, f_shadow):  # pragma: no cover - compiled
    """Solve, drop the samples the solution puts in attached shadow (n . l below ``f_shadow``), solve
    again; ``pred`` holds the last prediction. Returns (b0, b1, b2, |b|)."""
    b0 = b1 = b2 = nb = np.nan
    for it in range(2):
        b0, b1, b2 = _weighted_solve(V, grey, w)
        f0, f1, f2 = np.float32(b0), np.float32(b1), np.float32(b2)
        nb = np.sqrt(b0 * b0 + b1 * b1 + b2 * b2)
        for k in range(V.shape[0]):
            pred[k] = V[k, 0] * f0 + V[k, 1] * f1 + V[k, 2] * f2
        if it == 0:
            nbf = np.float32(nb)
            for k in range(V.shape[0]):
                if not (pred[k] > f_shadow * max(vn[k] * nbf, np.float32(1e-30))):
                    w[k] = 0.0
    return b0, b1, b2, nb


@numba.njit(inline="always", **_JIT)
def _colour_albedo(band, p, V, w, n0, n1, n2, num, albedo):  # pragma: no cover - compiled
    """The albedo of each channel with the normal fixed: sum_k s_k I_kc / sum_k s_k^2 (s = V . n)."""
    den = 0.0
    num[:] = 0.0
    for k in range(V.shape[0]):
        if w[k] == 0.0:
            continue
        ws = V[k, 0] * n0 + V[k, 1] * n1 + V[k, 2] * n2
        den += np.float64(ws) * np.float64(ws)
        for c in range(band.shape[2]):
            num[c] += ws * band[k, p, c]
    for c in range(band.shape[2]):
        albedo[p, c] = num[c] / den if den > 0 else np.nan


@numba.njit(**_JIT)
def _solve_pixels(band, colour, L, E, dirs, near, xs, ys, use, sat, dark_fraction, shadow_cos, lo, hi,
                  normals, albedo, n_used):  # pragma: no cover - compiled
    """Normals, albedo and lights used of the P pixels of ``band`` (K, P, C) float32, written into
    ``normals`` (P, 3), ``albedo`` (P, C, or P, 1 for grey) and ``n_used`` (P,).

    One pass over the samples, everything per pixel in registers: no (K, P) temporaries. Samples and
    products are float32 (as the images), sums and the 3 x 3 solve float64. ``colour``: the albedo
    per channel with the normal fixed (else ``|b|``); ``xs``, ``ys``: each pixel's position in mm
    (float32); ``L`` (K, 3) and ``E`` (K,) near lamps, or ``dirs`` (K, 3) far ones (times E) when
    not ``near``; ``sat`` <= 0: no saturation test; ``hi`` > 0: keep brightness ranks lo .. hi - 1.
    Returns (sum of squared residuals over the used samples, the same samples' sum of their pixel's squared
    mean brightness, invalid pixels inside ``use``): their ratio, pooled over the image, is the share of the
    signal left unexplained (a pixel's misfit relative to its own brightness would let a few near-black
    pixels, e.g. where a dark frame or stray light was subtracted, dominate it: 1e13 % was reported).
    Hand-written (numba): no library solves millions of tiny weighted least-squares problems, each
    with its own sample selection, without K x P temporaries (numpy's passes took 10-19 s where this
    takes 2.6 s at 4000 x 3000 x 16: ``scripts/benchmark_speed.py``).
    """
    K, P, C = band.shape
    grey = np.empty(K, np.float32)
    bright = np.empty(K, np.float32)
    vn = np.empty(K, np.float32)
    w = np.empty(K, np.float32)
    pred = np.empty(K, np.float32)
    ratio = np.empty(K, np.float32)
    V = np.empty((K, 3), np.float32)
    num = np.empty(max(C, 1))
    sq_sum, sq_n, n_bad = 0.0, 0.0, 0
    for p in range(P):
        gmax = _grey_and_bright(band, p, grey, bright)
        _light_vectors(near, L, E, dirs, xs[p], ys[p], V, vn)
        _usable_samples(grey, bright, vn, np.float32(dark_fraction) * gmax, use[p], sat, lo, hi, ratio, w)
        b0, b1, b2, nb = _solve_with_shadows(V, vn, grey, w, pred, np.float32(shadow_cos))
        cnt = 0
        for k in range(K):
            if w[k] != 0.0:
                cnt += 1
        n_used[p] = min(cnt, 255)
        bad = cnt < 3 or not (np.isfinite(b0) and np.isfinite(b1) and np.isfinite(b2))
        if bad and use[p]:
            n_bad += 1
        if bad or not use[p]:
            continue
        n0, n1, n2 = np.float32(b0 / nb), np.float32(b1 / nb), np.float32(b2 / nb)
        normals[p, 0] = n0
        normals[p, 1] = n1
        normals[p, 2] = n2
        gsum, e2, nk = 0.0, 0.0, 0
        for k in range(K):
            gsum += grey[k]
            if w[k] != 0.0:
                r = np.float64(grey[k] - pred[k])
                e2 += r * r
                nk += 1
        mean = gsum / K
        sq_sum += e2
        sq_n += nk * mean * mean
        if colour:
            _colour_albedo(band, p, V, w, n0, n1, n2, num, albedo)
        else:
            albedo[p, 0] = nb
    return sq_sum, sq_n, n_bad


#: Pixels :func:`_solve_lanes` solves side by side: its per-sample arrays are (K, LANES), 7 of float32 (57 KB at
#: 16 lamps, in the core's L2 cache).
LANES = 128


@numba.njit(**_JIT_LANES)
def _solve_lanes(band, colour, L, E, dirs, near, xs, ys, use, sat, dark_fraction, shadow_cos,
                 normals, albedo, n_used):  # pragma: no cover - compiled
    """:func:`_solve_pixels` without rank trimming, :data:`LANES` pixels side by side.

    Every per-pixel step is a loop over the lanes inside a loop over the samples, which the compiler runs
    in SIMD registers; each pixel's arithmetic is :func:`_solve_pixels`'s, in its order (a sample left out
    adds +0.0 to a sum instead of being skipped: the same sums, which start at +0.0 and so never hold -0.0),
    and the image's sums of squares are added pixel by pixel in pixel order: the same outputs to the bit
    (``tests/test_speed.py::test_normals_in_lanes_same_as_one_pixel_at_a_time``), in about half the time
    (one thread, 800000 pixels of the 4000 x 3000 x 16 RGB capture: 172-183 against 340-375 ns a pixel).
    Hand-written for :func:`_solve_pixels`'s reason; its loops over one pixel's samples cannot run in SIMD
    registers without reordering their sums.
    """
    K, P, C = band.shape
    W = LANES
    grey, bright = np.empty((K, W), np.float32), np.empty((K, W), np.float32)
    V0, V1, V2 = np.empty((K, W), np.float32), np.empty((K, W), np.float32), np.empty((K, W), np.float32)
    vn, w, pred = np.empty((K, W), np.float32), np.empty((K, W), np.float32), np.empty((K, W), np.float32)
    acc, b, nb, gmax = np.empty((9, W)), np.empty((3, W)), np.empty(W), np.empty(W, np.float32)
    num, den, nrm, res = np.empty((max(C, 1), W)), np.empty(W), np.empty((3, W), np.float32), np.empty((3, W))
    good = np.empty(W, np.uint8)
    LT = _lamp_terms(L, E)
    sq_sum, sq_n, n_bad = 0.0, 0.0, 0
    for p0 in range(0, P, W):
        nw = min(W, P - p0)
        _lanes_samples(band, p0, nw, use, sat, np.float32(dark_fraction), grey, bright, gmax, w)
        _lanes_vectors(LT, dirs, near, xs, ys, p0, nw, V0, V1, V2, vn)
        _lanes_shadows(V0, V1, V2, vn, grey, w, pred, acc, b, nb, nrm, nw, np.float32(shadow_cos))
        if colour:
            _lanes_albedo(band, p0, nw, V0, V1, V2, w, nrm, num, den)
        _lanes_residual(grey, pred, w, res, nw)
        _lanes_write(p0, nw, res, b, nb, nrm, num, den, colour, use, normals, albedo, n_used, good)
        for l in range(nw):      # the image's sums, pixel by pixel in pixel order
            if good[l] == 1:
                mean = res[1, l] / K
                sq_sum += res[2, l]
                sq_n += int(res[0, l]) * mean * mean
            elif good[l] == 2:
                n_bad += 1
    return sq_sum, sq_n, n_bad


@numba.njit(inline="always", **_JIT_LANES)
def _lamp_terms(L, E):  # pragma: no cover - compiled
    """(4, K) float32: each lamp's position and ``E_k |L_k|^2``, as :func:`_light_vectors` rounds them."""
    K = L.shape[0]
    LT = np.empty((4, K), np.float32)
    for k in range(K):
        LT[0, k] = np.float32(L[k, 0])
        LT[1, k] = np.float32(L[k, 1])
        LT[2, k] = np.float32(L[k, 2])
        LT[3, k] = np.float32(E[k] * (L[k, 0] ** 2 + L[k, 1] ** 2 + L[k, 2] ** 2))
    return LT


@numba.njit(inline="always", **_JIT_LANES)
def _lanes_samples(band, p0, nw, use, sat, dark_fraction, grey, bright, gmax, w):  # pragma: no cover - compiled
    """:func:`_grey_and_bright` and :func:`_usable_samples` (no ranks) of pixels ``p0 .. p0 + nw - 1``."""
    K, _, C = band.shape
    gmax[:nw] = -np.inf
    for k in range(K):
        for l in range(nw):
            p = p0 + l
            g = band[k, p, 0]
            br = g
            for c in range(1, C):
                v = band[k, p, c]
                g += v
                br = v if v > br else br
            g = g / np.float32(C)
            grey[k, l] = g
            bright[k, l] = br
            gmax[l] = g if g > gmax[l] else gmax[l]
    for k in range(K):
        for l in range(nw):
            thr = dark_fraction * gmax[l]
            ok = grey[k, l] > thr and (thr < 0 or grey[k, l] > 0) and use[p0 + l]
            if sat > 0 and bright[k, l] >= sat:
                ok = False
            w[k, l] = 1.0 if ok else 0.0


@numba.njit(inline="always", **_JIT_LANES)
def _lanes_vectors(LT, dirs, near, xs, ys, p0, nw, V0, V1, V2, vn):  # pragma: no cover - compiled
    """:func:`_light_vectors` of every lane (``LT``: :func:`_lamp_terms`)."""
    for k in range(LT.shape[1]):
        if near:
            for l in range(nw):
                d0 = LT[0, k] - xs[p0 + l]
                d1 = LT[1, k] - ys[p0 + l]
                d2 = LT[2, k]
                f = near_scale_compiled(d0, d1, d2, LT[3, k])
                V0[k, l] = d0 * f
                V1[k, l] = d1 * f
                V2[k, l] = d2 * f
        else:
            for l in range(nw):
                V0[k, l] = dirs[k, 0]
                V1[k, l] = dirs[k, 1]
                V2[k, l] = dirs[k, 2]
        for l in range(nw):
            vn[k, l] = np.sqrt(V0[k, l] * V0[k, l] + V1[k, l] * V1[k, l] + V2[k, l] * V2[k, l])


@numba.njit(inline="always", **_JIT_LANES)
def _lanes_shadows(V0, V1, V2, vn, grey, w, pred, acc, b, nb, nrm, nw, f_shadow):  # pragma: no cover - compiled
    """:func:`_solve_with_shadows` of every lane, then each lane's float32 unit normal into ``nrm``."""
    K = w.shape[0]
    for it in range(2):
        _lanes_solve(V0, V1, V2, grey, w, acc, b, nw)
        for l in range(nw):
            nb[l] = np.sqrt(b[0, l] * b[0, l] + b[1, l] * b[1, l] + b[2, l] * b[2, l])
        for k in range(K):
            for l in range(nw):
                pred[k, l] = (V0[k, l] * np.float32(b[0, l]) + V1[k, l] * np.float32(b[1, l])
                              + V2[k, l] * np.float32(b[2, l]))
        if it == 0:
            for k in range(K):
                for l in range(nw):
                    if not (pred[k, l] > f_shadow * max(vn[k, l] * np.float32(nb[l]), np.float32(1e-30))):
                        w[k, l] = 0.0
    for l in range(nw):
        nrm[0, l] = np.float32(b[0, l] / nb[l])
        nrm[1, l] = np.float32(b[1, l] / nb[l])
        nrm[2, l] = np.float32(b[2, l] / nb[l])


@numba.njit(inline="always", **_JIT_LANES)
def _lanes_solve(V0, V1, V2, grey, w, acc, b, nw):  # pragma: no cover - compiled
    """:func:`_weighted_solve` of every lane: the nine sums over the samples (+0.0 for one left out), then
    the closed form, into ``b`` (3, lanes)."""
    K, W = grey.shape
    acc[:, :nw] = 0.0
    for k in range(K):
        for l in range(nw):
            use = w[k, l] != 0.0
            v0, v1, v2, g = V0[k, l], V1[k, l], V2[k, l], grey[k, l]
            acc[0, l] += v0 * v0 if use else 0.0
            acc[1, l] += v0 * v1 if use else 0.0
            acc[2, l] += v0 * v2 if use else 0.0
            acc[3, l] += v1 * v1 if use else 0.0
            acc[4, l] += v1 * v2 if use else 0.0
            acc[5, l] += v2 * v2 if use else 0.0
            acc[6, l] += v0 * g if use else 0.0
            acc[7, l] += v1 * g if use else 0.0
            acc[8, l] += v2 * g if use else 0.0
    for l in range(nw):
        b[0, l], b[1, l], b[2, l] = _closed_form(acc[0, l], acc[1, l], acc[2, l], acc[3, l], acc[4, l], acc[5, l],
                                                 acc[6, l], acc[7, l], acc[8, l])


@numba.njit(inline="always", **_JIT_LANES)
def _lanes_albedo(band, p0, nw, V0, V1, V2, w, nrm, num, den):  # pragma: no cover - compiled
    """:func:`_colour_albedo`'s sums of every lane (the normal ``nrm`` fixed), into ``num`` (C, lanes) and ``den``."""
    K = w.shape[0]
    num[:, :nw] = 0.0
    den[:nw] = 0.0
    for k in range(K):
        for l in range(nw):
            ws = V0[k, l] * nrm[0, l] + V1[k, l] * nrm[1, l] + V2[k, l] * nrm[2, l]
            use = w[k, l] != 0.0
            den[l] += np.float64(ws) * np.float64(ws) if use else 0.0
            for c in range(band.shape[2]):
                num[c, l] += ws * band[k, p0 + l, c] if use else 0.0


@numba.njit(inline="always", **_JIT_LANES)
def _lanes_residual(grey, pred, w, res, nw):  # pragma: no cover - compiled
    """Each lane's samples used, sum of its grey samples, and its used samples' sum of squared residuals and
    count, into ``res`` (3, lanes): :func:`_solve_pixels`'s per-pixel sums, in its order."""
    K = grey.shape[0]
    res[:, :nw] = 0.0
    for k in range(K):
        for l in range(nw):
            use = w[k, l] != 0.0
            r = np.float64(grey[k, l] - pred[k, l])
            res[0, l] += 1.0 if use else 0.0
            res[1, l] += grey[k, l]
            res[2, l] += r * r if use else 0.0


@numba.njit(inline="always", **_JIT_LANES)
def _lanes_write(p0, nw, res, b, nb, nrm, num, den, colour, use, normals, albedo, n_used, good):  # pragma: no cover
    """Each lane's lights used, and its normal and albedo where it is solved (elsewhere the outputs keep their
    NaN), as :func:`_solve_pixels` writes them; ``good``: 1 solved, 2 unsolved inside ``use``, 0 else."""
    for l in range(nw):
        p = p0 + l
        cnt = int(res[0, l])
        n_used[p] = min(cnt, 255)
        bad = cnt < 3 or not (np.isfinite(b[0, l]) and np.isfinite(b[1, l]) and np.isfinite(b[2, l]))
        ok = use[p] and not bad
        good[l] = 1 if ok else (2 if use[p] else 0)
        for i in range(3):
            normals[p, i] = nrm[i, l] if ok else normals[p, i]
        if colour:
            for c in range(albedo.shape[1]):
                albedo[p, c] = (num[c, l] / den[l] if den[l] > 0 else np.nan) if ok else albedo[p, c]
        else:
            albedo[p, 0] = nb[l] if ok else albedo[p, 0]


def _rank_range(K, trim):
    """Ranks ``lo .. hi - 1`` (0 = darkest of K samples) that the trimmed solve keeps, at least 3."""
    lo_q, hi_q = (float(t) for t in trim)
    if not 0.0 <= lo_q < hi_q <= 1.0:
        raise UVPSInputError(f"trim must be two fractions 0 <= low < high <= 1; got {tuple(trim)!r}")
    lo, hi = int(np.floor(lo_q * K)), int(np.ceil(hi_q * K))
    hi = min(K, max(hi, lo + 3))
    return max(0, min(lo, hi - 3)), hi


def solve_normals(images, lights: LightModel, *, pixel_size_um, mask=None, saturation=None,
                  robust=False, trim=(0.25, 0.90), shadow_cos=0.05, dark_fraction=0.02,
                  chunk_pixels=None, workers=None, progress: Progress = None) -> StereoResult:
    """Least-squares normals and albedo from a stack of images and their lights.

    Parameters
    ----------
    images : ndarray, (K, M, N) or (K, M, N, C)
        Linear intensities (any real dtype; converted band by band).
    lights : LightModel
        Near (positions, intensities) or far (directions) lights, K of them.
    pixel_size_um : float
        Pixel size, to place each pixel in mm for the near-light vectors.
    mask : ndarray of bool, (M, N), optional
        Pixels to solve; others are NaN (not counted as invalid).
    saturation : float, optional
        Samples at or above this value (any channel) are left out.
    robust : bool
        Rank-trimmed least squares: per pixel, keep only the samples ranked within ``trim`` of
        that pixel's brightness (at least 3), then solve as usual.
    trim : (float, float)
        With ``robust``: the lowest and highest brightness rank kept, as fractions of the number
        of images K (default the 25th and 90th percentile: K = 12 keeps ranks 3..10 of 0..11).
        Brightness is the grey sample over the light's irradiance at the pixel (``|v_k(x)|``), so
        a dim lamp is not taken for a shadow.
    shadow_cos : float
        Samples whose predicted ``n . l`` (unit vectors) is below this are treated as attached shadow.
    dark_fraction : float
        Samples darker than this fraction of the pixel's brightest sample are left out (shadow); a
        negative value keeps every sample, 0 counts too (:data:`EVERY_SAMPLE`).
    chunk_pixels : int, optional
        Pixels per band (default :data:`CHUNK_PIXELS`): each band in flight holds about ``K * chunk_pixels * (4 C + 40)`` bytes.
    workers : int, optional
        Bands solved at once, in threads (default: the CPUs available, at most 4 and ``UVPS_THREADS``;
        1: in this thread).
        The result does not depend on it.

    Returns
    -------
    StereoResult

    Notes
    -----
    Shadowed samples (darker than ``dark_fraction`` of the pixel's brightest, or whose predicted
    ``n . l`` is below ``shadow_cos``: the attached-shadow test, after a first solve) and saturated
    samples are always left out; ``robust`` adds the rank trimming before both solves. Cost: two
    closed-form 3x3 solves per pixel and one pass over the samples, in a compiled kernel
    (:func:`_solve_lanes`, numba; :func:`_solve_pixels` with ``robust``) that runs in threads over bands of
    rows: 2.6 s for 4000 x 3000 x 16 RGB on 2 cores before the lanes (docs/benchmarks.md, "Speed and
    memory"; docs/decisions/speed.md, "The normals in SIMD lanes"), against 46-49 s for a numpy version
    with (K, P, 3) float64 temporaries and 10-19 s for a float32 numpy version (each timed by
    ``scripts/benchmark_speed.py``; docs/decisions/speed.md, "The normals in a compiled kernel (numba)").
    ``robust`` sorts the K samples.

    References
    ----------
    Woodham (1978); Salvant et al., Eq. 1 and Sec. "Calculating surface normal, depth, and albedo maps";
    Huang, Walton, Bearman, Cossairt (2015), near-light correction.
    """
    K, M, N = images.shape[:3]
    ranks = _rank_range(K, trim) if robust else None
    C = images.shape[3] if images.ndim == 4 else 0
    # every band fills its own rows (NaN where unsolved) in its thread: no fill of the whole outputs first
    out = _Outputs(np.empty((M, N, 3), np.float32), np.empty((M, N, C) if C else (M, N), np.float32),
                   np.empty((M, N), np.uint8))

    def one(rows):
        return _solve_band(images, lights, rows.start, rows.stop, out, pixel_size_um=pixel_size_um, mask=mask,
                           saturation=saturation, ranks=ranks, shadow_cos=shadow_cos, dark_fraction=dark_fraction)

    # bands of fixed rows whatever the threads, their sums added in the bands' order: the same to the bit;
    # the first band alone (numba compiles, or loads from its cache, on a function's first call)
    sums = map_bands(one, M, size=max(1, int(chunk_pixels or CHUNK_PIXELS) // N), first_alone=True,
                     threads=default_threads(4) if workers is None else workers,
                     each=lambda rows, _: report(progress, rows.stop / M, f"normals: rows {rows.stop}/{M}"))
    sq_sum, sq_n, n_invalid = (sum(band[i] for band in sums) for i in range(3))
    if n_invalid:
        log.info("%d pixels had fewer than 3 usable lights and are NaN", n_invalid)
    return StereoResult(out.normals, out.albedo, out.n_used, n_invalid,
                        float(np.sqrt(sq_sum / sq_n)) if sq_n > 0 else 0.0)


class _Outputs(NamedTuple):
    normals: np.ndarray
    albedo: np.ndarray
    n_used: np.ndarray


def _solve_band(images, lights, r0, r1, out: _Outputs, *, pixel_size_um, mask, saturation, ranks, shadow_cos,
                dark_fraction) -> tuple:
    """Solve rows ``r0:r1`` into ``out``; -> (sum of squared residuals, the signal's sum of squares over the
    same samples, invalid pixels): :func:`_solve_pixels`.

    The band is read and converted to float32 here; :func:`_solve_lanes` (:func:`_solve_pixels` with ranks;
    compiled, GIL released) does the rest, so bands run in parallel threads.
    """
    K, M, N = images.shape[:3]
    C = images.shape[3] if images.ndim == 4 else 0
    P = (r1 - r0) * N
    band = float_band(images, slice(r0, r1)).reshape(K, P, max(C, 1))
    X = pixel_coordinates_mm(np.arange(r0, r1)[:, None], np.arange(N)[None, :], (M, N), pixel_size_um)
    xs = X[..., 0].astype(np.float32).ravel()
    ys = X[..., 1].astype(np.float32).ravel()
    use = np.ones(P, bool) if mask is None else np.ascontiguousarray(np.asarray(mask[r0:r1]).ravel(), dtype=bool)
    near = lights.near
    L = lights.positions_mm if near else np.zeros((K, 3))
    dirs = (lights.directions * lights.intensities[:, None]).astype(np.float32)
    lo, hi = ranks if ranks is not None else (0, 0)
    # the kernel writes into the outputs' rows themselves (contiguous views), NaN / 0 where it solves nothing
    normals = out.normals[r0:r1].reshape(P, 3)
    albedo = out.albedo[r0:r1].reshape(P, max(C, 1))
    n_used = out.n_used[r0:r1].reshape(P)
    normals.fill(np.nan)
    albedo.fill(np.nan)
    n_used.fill(0)
    args = (band, bool(C), np.ascontiguousarray(L, dtype=np.float64),
            np.ascontiguousarray(lights.intensities, dtype=np.float64), dirs, near, xs, ys, use,
            np.float32(saturation) if saturation is not None else np.float32(0), float(dark_fraction),
            float(shadow_cos))
    if hi > 0:      # rank trimming sorts each pixel's samples: one pixel at a time
        res = _solve_pixels(*args, int(lo), int(hi), normals, albedo, n_used)
    else:
        res = _solve_lanes(*args, normals, albedo, n_used)
    return float(res[0]), float(res[1]), int(res[2])
