"""Photometric stereo: per-pixel least squares with per-pixel near-light vectors.

Lambertian model (paper Eq. 1; Woodham 1978), near point lights (Huang et al. 2015)::

    I_k(x) = albedo(x) * n(x) . v_k(x),   v_k(x) = E_k (|L_k| / d)^2 (L_k - X) / d,  d = |L_k - X|

For each pixel, ``b = albedo * n`` solves the weighted normal equations ``(sum w V V^T) b = sum w V I``
on the grey (channel-mean) intensities; ``n = b / |b|``. The RGB albedo (the fluorescence colour) is
then fitted per channel with the normal fixed. Shadowed (attached shadow or too dark) and saturated
samples are always left out per pixel; a pixel with fewer than three usable lights is NaN and counted.
``robust=True`` is rank-trimmed least squares: each pixel keeps only its samples ranked between the
25th and 90th percentile of its brightness (relative to each light's irradiance there), so cast
shadows and dimmed samples at the bottom and specular highlights at the top no longer pull the
normal; for captures with many lights (RTI domes, visible light). Work proceeds in bands of rows so
that memory stays proportional to one band, never to lights x pixels x channels in float64.
"""
from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

from .errors import UVPSInputError
from .lights import LightModel, pixel_coordinates_mm
from .outputs import Progress, report

log = logging.getLogger(__name__)

__all__ = ["StereoResult", "solve_normals"]


@dataclass
class StereoResult:
    """Normals, albedo and per-pixel diagnostics of :func:`solve_normals`."""

    normals: np.ndarray        # (M, N, 3) float32, NaN where unsolved
    albedo: np.ndarray         # (M, N) or (M, N, C) float32, in image counts per unit irradiance
    n_used: np.ndarray         # (M, N) uint8: lights used per pixel
    n_invalid: int             # pixels with fewer than 3 usable lights (inside the mask)
    residual_rms: float        # rms relative residual over solved pixels


def _solve3(A, y):
    """Batched 3x3 solve; singular systems give NaN (np.linalg.solve would raise for the batch)."""
    det = np.linalg.det(A)
    good = np.abs(det) > 1e-12 * np.maximum(np.einsum("pii->p", A) ** 3, 1e-30)
    out = np.full(y.shape, np.nan, dtype=np.float64)
    if good.any():
        out[good] = np.linalg.solve(A[good], y[good][..., None])[..., 0]
    return out


def _rank_range(K, trim):
    """Ranks ``lo .. hi - 1`` (0 = darkest of K samples) that the trimmed solve keeps, at least 3."""
    lo_q, hi_q = (float(t) for t in trim)
    if not 0.0 <= lo_q < hi_q <= 1.0:
        raise UVPSInputError(f"trim must be two fractions 0 <= low < high <= 1; got {tuple(trim)!r}")
    lo, hi = int(np.floor(lo_q * K)), int(np.ceil(hi_q * K))
    hi = min(K, max(hi, lo + 3))
    return max(0, min(lo, hi - 3)), hi


def _within_ranks(values, lo, hi):
    """True where a sample's rank along axis 0 is in ``lo .. hi - 1`` (ties at the ends are kept).

    ``np.partition`` finds the two order statistics per pixel in O(K) without a (K, P) index array.
    """
    part = np.partition(values, (lo, hi - 1), axis=0)
    return (values >= part[lo]) & (values <= part[hi - 1])


def solve_normals(images, lights: LightModel, *, pixel_size_um, mask=None, saturation=None,
                  robust=False, trim=(0.25, 0.90), shadow_cos=0.05, dark_fraction=0.02,
                  chunk_pixels=250_000, progress: Progress = None) -> StereoResult:
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
        Samples darker than this fraction of the pixel's brightest sample are left out (shadow).
    chunk_pixels : int
        Pixels per band (peak memory measured: ``K * chunk_pixels`` times 51 bytes for far lights,
        59 for near ones, the same with ``robust``).

    Returns
    -------
    StereoResult

    Notes
    -----
    Shadowed samples (darker than ``dark_fraction`` of the pixel's brightest, or whose predicted
    ``n . l`` is below ``shadow_cos``: the attached-shadow test, after a first solve) and saturated
    samples are always left out; ``robust`` adds the rank trimming before both solves. Cost: two
    3x3 solves per pixel, plus one ``np.partition`` along K per band with ``robust``.

    References
    ----------
    Woodham (1978); Salvant et al., Eq. 1 and Sec. "Calculating surface normal, depth, and albedo maps";
    Huang, Walton, Bearman, Cossairt (2015), near-light correction.
    """
    K, M, N = images.shape[:3]
    if robust:
        lo, hi = _rank_range(K, trim)
    C = images.shape[3] if images.ndim == 4 else 0
    normals = np.full((M, N, 3), np.nan, np.float32)
    albedo = np.full((M, N, C) if C else (M, N), np.nan, np.float32)
    n_used = np.zeros((M, N), np.uint8)
    rows_per = max(1, chunk_pixels // N)
    sq_sum, sq_n, n_invalid = 0.0, 0, 0
    for r0 in range(0, M, rows_per):
        r1 = min(M, r0 + rows_per)
        band = np.asarray(images[:, r0:r1], dtype=np.float32).reshape(K, (r1 - r0) * N, *([C] if C else []))
        grey = band.mean(axis=-1) if C else band
        rr, cc = np.mgrid[r0:r1, 0:N]
        X = pixel_coordinates_mm(rr.ravel(), cc.ravel(), (M, N), pixel_size_um)
        V = lights.vectors(X).astype(np.float32) if lights.near else lights.vectors(X)   # (K, P, 3)
        use = np.ones(grey.shape[1], bool) if mask is None else mask[r0:r1].ravel()
        w = (grey > dark_fraction * grey.max(axis=0, keepdims=True)) & (grey > 0)
        if saturation is not None:
            w &= ~((band >= saturation).any(axis=-1) if C else band >= saturation)
        w &= use[None]
        vn = np.linalg.norm(V, axis=2)    # (K, P): each light's irradiance at each pixel
        if robust:
            w &= _within_ranks(np.divide(grey, vn, dtype=np.float32), lo, hi)
        w = w.astype(np.float32)
        b = None
        for it in range(2):
            A = np.einsum("kp,kpi,kpj->pij", w, V, V, dtype=np.float64)
            y = np.einsum("kp,kpi,kp->pi", w, V, grey, dtype=np.float64)
            b = _solve3(A, y)
            pred = np.einsum("kpi,pi->kp", V, b)
            nb = np.linalg.norm(b, axis=1)
            if it == 0:
                # attached shadow: where the light grazes or is behind the surface the sample is 0
                cosv = pred / np.maximum(vn * nb[None], 1e-30)
                w *= (cosv > shadow_cos)
        cnt = (w > 0).sum(axis=0)
        bad = (cnt < 3) | ~np.isfinite(b).all(axis=1)
        n_invalid += int((bad & use).sum())
        nb = np.linalg.norm(b, axis=1)
        n = b / np.where(nb > 0, nb, np.nan)[:, None]
        n[bad | ~use] = np.nan
        good = ~(bad | ~use)
        res = np.where(w > 0, grey - pred, 0.0)[:, good] / np.maximum(grey[:, good].mean(axis=0), 1e-12)
        sq_sum += float(np.sum(res ** 2))
        sq_n += int((w[:, good] > 0).sum())
        sl = slice(r0, r1)
        normals[sl] = n.reshape(r1 - r0, N, 3)
        n_used[sl] = np.minimum(cnt, 255).reshape(r1 - r0, N)
        if C:
            s = np.einsum("kpi,pi->kp", V, np.nan_to_num(n))  # shading per light with the normal fixed
            num = np.einsum("kp,kp,kpc->pc", w, s, band, dtype=np.float64)
            den = np.einsum("kp,kp,kp->p", w, s, s, dtype=np.float64)
            alb = num / np.where(den > 0, den, np.nan)[:, None]
            alb[~good] = np.nan
            albedo[sl] = alb.reshape(r1 - r0, N, C)
        else:
            a = nb.copy()
            a[~good] = np.nan
            albedo[sl] = a.reshape(r1 - r0, N)
        report(progress, r1 / M, f"normals: rows {r1}/{M}")
    if n_invalid:
        log.warning("%d pixels had fewer than 3 usable lights and are NaN", n_invalid)
    return StereoResult(normals, albedo, n_used, n_invalid, float(np.sqrt(sq_sum / max(sq_n, 1))))
