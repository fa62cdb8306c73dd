"""Polynomial flat-field: the lamp's drop-off map of each image (paper Fig. 1c).

Each image is fitted with a 2-D Legendre polynomial (normalised to its mean), the light drop-off map;
the flat-fielded image is image / fit. The fit is made on a reduced grid of block means, so its cost
depends on the grid, not on the megapixels.

The painting's own colour areas are large and sharp-edged: fitting the intensities directly would let
a light area on one side pass for a lamp on that side (and a smooth variation of the paint's
fluorescence is indistinguishable from drop-off in any single image). The albedo is the same in every
image of a capture, so each image is fitted *relative to the geometric mean of the stack*, which
cancels the albedo exactly; the part of the drop-off common to all images is taken from the fitted
light model (see :func:`fit_dropoffs` and :func:`with_common`).
"""
from __future__ import annotations

import dataclasses
import logging
from dataclasses import dataclass
from typing import Optional

import numpy as np
from numpy.polynomial import legendre as L

from ..errors import UVPSInputError
from .stack import StackView, raw_parts
from .offset import corrected_band, each_image, image_block_stats

log = logging.getLogger(__name__)

__all__ = ["BlockGrid", "DropoffFit", "GainCorrected", "block_grid", "divided_grid", "fit_dropoffs", "fit_log_grid",
           "with_common", "flatfield", "to_unit"]


@dataclass
class BlockGrid:
    """Block means of a stack on a reduced grid.

    Attributes
    ----------
    values : ndarray, (K, R, C) float64
        Block means of the grey images.
    valid : ndarray, (K, R, C) bool
        Blocks whose pixels are all usable (inside the mask, not shadowed, not saturated).
    rows, cols : ndarray
        Pixel coordinates (row, col) of the block centres.
    shape : tuple
        Full image shape (M, N).
    block : int
        Block size in pixels.
    """

    values: np.ndarray
    valid: np.ndarray
    rows: np.ndarray
    cols: np.ndarray
    shape: tuple
    block: int


@dataclass
class DropoffFit:
    """A Legendre polynomial fit of the log drop-off of one image.

    ``log F(u, v) = sum_ij coeffs[i, j] P_i(v) P_j(u)`` with ``u`` (columns) and ``v`` (rows) mapped to
    [-1, 1]; the constant is chosen so that F has mean 1 over the image.
    """

    coeffs: np.ndarray
    degree: int
    shape: tuple
    level: float  # median log intensity of the image minus log F: the image's overall level
    n_blocks: int
    gradient_rms: float  # rms of the albedo-free drop-off gradient per pixel (1/px)
    ratio_coeffs: Optional[np.ndarray] = None  # fit of log(I_k / geometric mean of the stack)
    log_bounds: Optional[tuple] = None  # log F is clamped to the range it takes where it was fitted

    def log_evaluate(self, rows=None, cols=None, *, dtype=np.float64) -> np.ndarray:
        """log F at the given pixel rows and columns (a separable grid).

        ``dtype=np.float32``: one (rows, n) x (n, cols) float32 product (the (rows, n) factor in
        float64), clamped in place: it differs from the float64 map by float32 rounding, and makes
        no (rows, cols) float64 temporary (what :func:`flatfield` needs, band by band).
        """
        M, N = self.shape
        rows = np.arange(M) if rows is None else np.asarray(rows, dtype=float)
        cols = np.arange(N) if cols is None else np.asarray(cols, dtype=float)
        Vv = L.legvander(to_unit(rows, M), self.degree)
        Vu = L.legvander(to_unit(cols, N), self.degree)
        if np.dtype(dtype) == np.float64:
            return self.clamp(Vv @ self.coeffs @ Vu.T)
        logF = (Vv @ self.coeffs).astype(dtype) @ Vu.T.astype(dtype)
        return self.clamp(logF, out=logF)

    def clamp(self, logF, *, out=None):
        """Clamp log F to the range it takes over the fitted (lit, unmasked) blocks: a polynomial
        extrapolated beyond a masked object would otherwise explode."""
        return logF if self.log_bounds is None else np.clip(logF, *self.log_bounds, out=out)

    def evaluate(self, rows=None, cols=None) -> np.ndarray:
        """The drop-off map F (mean 1 over the full image) at the given rows and columns."""
        return np.exp(self.log_evaluate(rows, cols))


def to_unit(coord, size):
    """Map pixel coordinates 0 .. size - 1 to [-1, 1], the domain of the Legendre fits."""
    return (2.0 * np.asarray(coord, dtype=float) - (size - 1)) / max(size - 1, 1)


def block_grid(images, *, mask=None, saturation=None, target=96) -> BlockGrid:
    """Block means of each image on a grid of about ``target`` blocks along the longer side.

    Parameters
    ----------
    images : ndarray, (K, M, N) or (K, M, N, C)
        Linear intensities.
    mask : ndarray of bool, (M, N), optional
        True where the pixel may be used.
    saturation : float, optional
        Counts at or above which a sample is saturated.
    target : int
        About this many blocks along the longer side.
    """
    K, M, N = images.shape[:3]
    b = max(1, int(np.ceil(max(M, N) / target)))
    R, C = M // b, N // b
    r0 = (M - R * b) // 2
    c0 = (N - C * b) // 2
    values = np.empty((K, R, C))
    valid = np.ones((K, R, C), bool)
    if mask is not None:
        mblk = mask[r0:r0 + R * b, c0:c0 + C * b].reshape(R, b, C, b).all(axis=(1, 3))
        valid &= mblk[None]

    def one(k):
        # a view (dark frame, beams) read as stored, each sample corrected as read; mapped files in place
        st = image_block_stats(images, k, slice(r0, r0 + R * b), slice(c0, c0 + C * b), b, saturation)
        values[k] = st.means.mean(axis=-1) if st.means.ndim == 3 else st.means
        # a block is unusable when any of its pixels is dark (shadow) or saturated
        valid[k] &= (st.grey_min > 0) & ~st.saturated

    # the kernel, the file reads and a view's correction (numpy) release the GIL, so both cores are busy;
    # each image's values are its own, whatever the order
    each_image(one, K)
    rows = r0 + b * np.arange(R) + (b - 1) / 2.0
    cols = c0 + b * np.arange(C) + (b - 1) / 2.0
    return BlockGrid(values, valid, rows, cols, (M, N), b)


def _design(rows, cols, shape, degree):
    """Legendre design matrices (rows, cols) on the unit square."""
    M, N = shape
    return L.legvander(to_unit(rows, M), degree), L.legvander(to_unit(cols, N), degree)


def _irls(A, y, n_iter, gram=None):
    """Weighted least squares with Cauchy weights and a MAD scale (robust to colour edges, spots);
    ``gram(w)``: ``A^T diag(w) A`` (default that product itself)."""
    w = np.ones_like(y)
    coef = np.zeros(A.shape[1])
    for _ in range(n_iter):
        # normal equations: the Legendre basis is well conditioned on the block grid, and a
        # (n^2 x n^2) solve is 7x faster than lstsq's SVD of the tall matrix
        G = A.T @ (A * w[:, None]) if gram is None else gram(w)
        coef = np.linalg.solve(G, A.T @ (w * y))
        r = y - A @ coef
        scale = 1.4826 * np.median(np.abs(r - np.median(r))) + 1e-12
        w = 1.0 / (1.0 + (r / (2.385 * scale)) ** 2)
    return coef


def _separable_gram(Vv, Vu, use):
    """``gram(w)`` = ``A^T diag(w) A`` for the blocks ``use`` (flat, raster order) of the grid whose design
    ``A`` has the rows ``Vv[r] (x) Vu[c]`` (:func:`_fit_values`), by the separable sums
    ``sum_r Vv[r, i] Vv[r, i'] sum_c w[r, c] Vu[c, j] Vu[c, j']``: 0.03 ms a product where ``A^T (A * w)`` took
    0.36 ms (degree 4, 6745 blocks; the two fits of the calibrated route on ``scripts/benchmark_speed.py``'s
    4000 x 3000 x 16 capture make 1024 of them: 0.64 s -> 0.30 s of CPU, ``python -m cProfile``). The sums
    are taken in another order (those fits agree to 1.1e-14). Hand-written: no library call forms a weighted
    Gram matrix of a Kronecker-structured design."""
    R, C, n = len(Vv), len(Vu), Vv.shape[1]
    vv = (Vv[:, :, None] * Vv[:, None, :]).reshape(R, n * n)
    uu = (Vu[:, :, None] * Vu[:, None, :]).reshape(C, n * n)
    flat = np.flatnonzero(use)

    def gram(w):
        W = np.zeros(R * C)
        W[flat] = w
        G = vv.T @ (W.reshape(R, C) @ uu)                # ((i, i'), (j, j'))
        return G.reshape(n, n, n, n).transpose(0, 2, 1, 3).reshape(n * n, n * n)
    return gram


def _grid_design(grid, degree) -> tuple:
    """``(Vv, Vu, A)``: the block grid's Legendre design matrices and their Kronecker rows ``A`` (blocks in
    raster order, n^2), made once for all the lamps' fits (made per fit: 128 times in the calibrated route's two
    fits, 0.1 s of their 0.42 s under ``python -m cProfile``)."""
    n = degree + 1
    Vv, Vu = _design(grid.rows, grid.cols, grid.shape, degree)
    return Vv, Vu, np.einsum("ri,cj->rcij", Vv, Vu).reshape(-1, n * n)


def _fit_values(logv, ok, grid, degree, n_iter, design=None):
    """Robust Legendre fit of log values on the block grid (value domain); ``design``: :func:`_grid_design`."""
    n = degree + 1
    Vv, Vu, A = _grid_design(grid, degree) if design is None else design
    use = ok.ravel() & np.isfinite(logv.ravel())
    return _irls(A[use], logv.ravel()[use], n_iter, gram=_separable_gram(Vv, Vu, use)).reshape(n, n)


def _normalise(C, grid, ok, degree):
    """Set the constant so that exp(poly) has mean 1 over the fitted blocks; -> (C, log bounds)."""
    Vv, Vu = _design(grid.rows, grid.cols, grid.shape, degree)
    logF = (Vv @ C @ Vu.T)[ok]
    C = C.copy()
    shift = np.log(np.exp(logF).mean())
    C[0, 0] -= shift
    # image corners lie half a block beyond the block centres: leave a margin for them
    margin = 0.05 + 0.25 * float(logF.max() - logF.min())
    return C, (float(logF.min() - shift - margin), float(logF.max() - shift + margin))


def fit_dropoffs(grid: BlockGrid, *, degree=4, n_iter=8) -> list:
    """Fit the albedo-free part of every image's log drop-off on a block grid.

    Parameters
    ----------
    grid : BlockGrid
        From :func:`block_grid`.
    degree : int
        Legendre degree in each direction (paper: "an orthogonal polynomial"; 2 to 6 is sensible).
    n_iter : int
        Reweighting iterations.

    Returns
    -------
    list of DropoffFit
        With ``ratio_coeffs`` set and ``coeffs`` = the ratio fit alone (normalised to mean 1); call
        :func:`with_common` with the part common to all images (from the light model) to complete them.

    Notes
    -----
    The albedo (and so every colour area and its smooth variations) is the same in every image. Each
    image is divided by the geometric mean of the stack, ``R_k = I_k / G``, which cancels the albedo
    exactly, and ``log R_k`` is fitted with a robust (Cauchy-weighted) least-squares Legendre
    polynomial. What the ratio cannot see is the part of the drop-off common to all images; no image
    can separate it from a smooth albedo variation, so it is taken from the light model
    (:func:`uvps.core.lights.estimate_lights`). Reference: Salvant et al., Sec. "Calculating the
    illumination vector" (polynomial fit normalised to the mean).
    """
    K = grid.values.shape[0]
    ok_all = grid.valid.all(axis=0)
    support = grid.valid.sum(axis=0) >= min(K, PARTLY_LIT_LAMPS)
    if ok_all.sum() < PARTLY_LIT_SHARE * support.sum() and support.sum() >= 3 * (degree + 1) ** 2:
        return _fit_partly_lit(grid, support, degree, n_iter)
    if ok_all.sum() < 3 * (degree + 1) ** 2:
        raise UVPSInputError(
            f"only {int(ok_all.sum())} blocks are lit and unsaturated in every image; the drop-off fit "
            f"needs at least {3 * (degree + 1) ** 2} (check exposure, the mask, or lower --degree)")
    with np.errstate(divide="ignore", invalid="ignore"):
        logv = np.log(np.where(ok_all[None], grid.values, np.nan))
    logG = logv.mean(axis=0)
    design = _grid_design(grid, degree)
    fits = []
    for k in range(K):
        ratio = _fit_values(logv[k] - logG, ok_all, grid, degree, n_iter, design)
        fits.append(_ratio_fit(ratio, grid, ok_all, degree, int(ok_all.sum())))
    _set_levels(fits, grid)
    return fits


def _ratio_fit(ratio, grid, ok, degree, n_blocks) -> DropoffFit:
    """A :class:`DropoffFit` of a lamp's ratio coefficients: normalised over the blocks ``ok``, with its
    gradient's RMS over the grid."""
    C, bounds = _normalise(ratio, grid, ok, degree)
    fit = DropoffFit(C, degree, grid.shape, 0.0, n_blocks, 0.0, ratio, bounds)
    gr = np.gradient(fit.log_evaluate(grid.rows, grid.cols), grid.rows, grid.cols)
    fit.gradient_rms = float(np.sqrt(np.mean(gr[0] ** 2 + gr[1] ** 2)))
    return fit


#: A block enters the drop-off fits of a partly-lit capture when at least this many lamps light it.
PARTLY_LIT_LAMPS = 5

#: The fits treat a capture as partly lit (:func:`_fit_partly_lit`) when fewer than this share of the
#: blocks lit by :data:`PARTLY_LIT_LAMPS` lamps are lit by every lamp (a dome's low lamps leaving parts
#: of the field dark); otherwise they use the blocks lit by every lamp, as always.
PARTLY_LIT_SHARE = 0.9


def _fit_partly_lit(grid, support, degree, n_iter, rounds=4):
    """:func:`fit_dropoffs` when lamps leave parts of the field dark: each lamp's ratio fitted on the
    blocks it lights.

    ``log I_k(b) = a(b) + f_k(b)`` with ``a`` the albedo and common drop-off of block b (free) and
    ``f_k`` lamp k's smooth ratio (Legendre, mean 0 over lamps): alternating least squares, ``a``
    as the mean over the lamps lighting each block of ``log I_k - f_k``, then each ``f_k`` by the
    robust fit on its own lit blocks. With every block lit by every lamp the first round is the
    geometric-mean ratio of :func:`fit_dropoffs`. Hand-written: two-way (block x lamp) fixed effects
    with a smooth lamp term on a missing-data pattern is not a library call.
    """
    K = grid.values.shape[0]
    valid = grid.valid & support[None]
    design = _grid_design(grid, degree)
    Vv, Vu, A = design
    with np.errstate(divide="ignore", invalid="ignore"):
        logv = np.log(np.where(valid, grid.values, np.nan))
    need = 3 * (degree + 1) ** 2
    few = np.flatnonzero([valid[k].sum() < need or np.linalg.matrix_rank(A[valid[k].ravel()]) < A.shape[1]
                          for k in range(K)])
    if few.size:
        shown = ", ".join(f"{k + 1} ({int(valid[k].sum())})" for k in few[:8])
        more = f" and {few.size - 8} more" if few.size > 8 else ""
        raise UVPSInputError(f"too few blocks lit by some images for their drop-off fits (image (lit blocks): "
                             f"{shown}{more}; {need} needed, spread over the field): check those images' exposure, or "
                             "lower --degree")
    F = np.zeros_like(logv)
    C = np.zeros((K, degree + 1, degree + 1))
    n_lit = valid.sum(axis=0)
    for _ in range(rounds):
        # nanmean's arithmetic, without its "Mean of empty slice" warning for a block no lamp lights
        # (a masked one): NaN there, and no lamp's fit uses it
        with np.errstate(invalid="ignore", divide="ignore"):
            a = np.where(valid, logv - F, 0.0).sum(axis=0) / n_lit
        for k in range(K):
            C[k] = _fit_values(logv[k] - a, valid[k], grid, degree, n_iter, design)
        C -= C.mean(axis=0)
        F = np.einsum("ri,kij,cj->krc", Vv, C, Vu)
    fits = [_ratio_fit(C[k].copy(), grid, support, degree, int(valid[k].sum())) for k in range(K)]
    _set_levels(fits, grid)
    return fits


def _set_levels(fits, grid):
    with np.errstate(divide="ignore", invalid="ignore"):
        for k, fit in enumerate(fits):
            lv = np.log(np.where(grid.valid[k], grid.values[k], np.nan))
            fit.level = float(np.nanmedian(lv - fit.log_evaluate(grid.rows, grid.cols)))


def with_common(fits, grid: BlockGrid, log_common) -> list:
    """The drop-off fits completed with the part common to all images: new fits, ``fits`` unchanged.

    ``log_common(rows, cols)`` gives that part on a separable grid (the mean log drop-off of a light
    model: :func:`uvps.core.lights.dropoff_common`); it is projected on the same Legendre basis and
    added to each ratio fit, each map is renormalised to mean 1 and each image's level measured again.
    """
    if not fits:
        return []
    degree, shape = fits[0].degree, fits[0].shape
    M, N = shape
    rows, cols = np.linspace(0, M - 1, 48), np.linspace(0, N - 1, 48)
    Vv, Vu = _design(rows, cols, shape, degree)
    n = degree + 1
    A = np.einsum("ri,cj->rcij", Vv, Vu).reshape(-1, n * n)
    common = np.linalg.lstsq(A, np.asarray(log_common(rows, cols)).ravel(), rcond=None)[0].reshape(n, n)
    ok_all = grid.valid.all(axis=0)
    out = []
    for fit in fits:
        coeffs, bounds = _normalise(fit.ratio_coeffs + common, grid, ok_all, degree)
        out.append(dataclasses.replace(fit, coeffs=coeffs, log_bounds=bounds))
    _set_levels(out, grid)
    return out


def flatfield(image, fit: DropoffFit, *, channels_first: bool = False, row0: int = 0) -> np.ndarray:
    """Divide an image (or a band of its rows) by its drop-off map.

    Parameters
    ----------
    image : ndarray, (M, N) or (M, N, C)
        Linear intensities: the whole fitted image, or the band of its rows starting at ``row0``.
    fit : DropoffFit
    channels_first : bool
        Return a colour image as (C, M, N) (the layout of the written ImageJ hyperstack) instead
        of (M, N, C), without an intermediate copy.
    row0 : int
        The first row of ``image`` in the fitted image (0: the whole image). Band by band gives
        the values of the whole image.

    Returns
    -------
    ndarray, float32
        ``image / F``: the image as if the lamp lit the whole field as it lights the average point.

    Notes
    -----
    ``log F`` is :meth:`DropoffFit.log_evaluate` in float32, exponentiated in place: the map differs
    from a float64 one by float32 rounding (< 4e-7 relative), as the result is float32 anyway; no
    (M, N) or (M, N, C) float64 temporary is made (0.3 s -> 0.05 s per 4000 x 3000 map).
    """
    M, N = fit.shape
    rows = image.shape[0]
    if image.shape[1] != N or not 0 <= row0 <= M - rows:
        raise UVPSInputError(f"flatfield: rows {row0}..{row0 + rows} x {image.shape[1]} columns are not a band of "
                             f"the fitted {M} x {N} image")
    F = fit.log_evaluate(np.arange(row0, row0 + rows), dtype=np.float32)
    np.exp(F, out=F)
    if image.ndim == 2:
        return np.divide(image, F, dtype=np.float32)
    if not channels_first:
        return np.divide(image, F[..., None], dtype=np.float32)
    out = np.empty((image.shape[2],) + image.shape[:2], np.float32)
    for c in range(image.shape[2]):
        np.divide(image[..., c], F, out=out[c], dtype=np.float32)
    return out


class GainCorrected(StackView):
    """A stack seen with each image divided by a smooth gain map of its own, computed on access.

    ``log gain_k(row, col) = sum_ij coeffs[k, i, j] P_i(v) P_j(u)`` (Legendre, rows and columns mapped
    to [-1, 1] as in :class:`DropoffFit`). Used for known lamp positions: what each image's drop-off
    holds beyond the point-light model (a lamp's beam, its aim) is divided out, so that the relative
    irradiance of the lamps at every pixel is the model's; what all images share (a common beam
    shape, vignetting) stays and is absorbed in the albedo. The stack is never copied. Supports the
    stages' access patterns: ``[k]``, ``[k, rows, cols]``, ``[:, rows, cols]`` with slices or ints, and
    ``[:, r, c]`` with two index arrays of one shape.
    """

    def __init__(self, images, coeffs):
        super().__init__(images)
        self.coeffs = np.asarray(coeffs, dtype=float)

    def __getitem__(self, key):
        key = key if isinstance(key, tuple) else (key,)
        kk, rk, ck = (key + (slice(None),) * 3)[:3]
        if (len(key) <= 3 and isinstance(rk, slice) and isinstance(ck, slice)
                and isinstance(kk, (int, np.integer, slice))):
            # a band of one or more images (the normals' bands): the factors of all at once, as
            # correct() makes them, and each image's band read as stored and corrected in one pass
            ks = np.arange(self.shape[0])[kk]
            parts = [raw_parts(self.base, int(k), rk, ck) for k in np.atleast_1d(ks)]
            if parts and all(p is not None and p.factor is None for p in parts):
                f = self.factor(kk, rk, ck)
                f = f[None] if np.ndim(ks) == 0 else f
                out = np.empty((len(parts),) + parts[0].raw.shape, np.float32)
                for i, p in enumerate(parts):
                    corrected_band(dataclasses.replace(p, factor=f[i]), out=out[i])
                return out[0] if np.ndim(ks) == 0 else out
        return super().__getitem__(key)

    def correct(self, out, kk, rk, ck):
        f = self.factor(kk, rk, ck)
        return out * (f[..., None] if self.ndim == 4 else f)     # out may be the stack itself: not in place

    def raw_parts(self, k: int, rows: slice, cols: slice):
        """The band as stored (and a dark frame) with this view's factor (1 / the gain map) to multiply
        (:class:`uvps.core.stack.RawParts`)."""
        p = raw_parts(self.base, k, rows, cols)
        if p is None or p.factor is not None:
            return None
        return dataclasses.replace(p, factor=self.factor(k, rows, cols))

    def factor(self, kk, rk, ck) -> np.ndarray:
        """The float32 factor ``1 / gain`` the values indexed by ``(kk, rk, ck)`` are multiplied by."""
        K, M, N = self.shape[:3]
        ks, rows, cols = np.arange(K)[kk], np.arange(M)[rk], np.arange(N)[ck]
        deg = self.coeffs.shape[1] - 1
        C = self.coeffs[np.atleast_1d(ks)]
        Vv = L.legvander(to_unit(np.atleast_1d(rows), M), deg)
        Vu = L.legvander(to_unit(np.atleast_1d(cols), N), deg)
        if np.ndim(rows) == 1 and np.ndim(cols) == 1 and not (isinstance(rk, slice) or isinstance(ck, slice)):
            g = np.einsum("pi,kij,pj->kp", Vv, C, Vu)                  # scattered pixels
        else:
            # a rectangle: (Vv C_k) Vu^T, two matrix products (a three-operand einsum loops over
            # rows x cols x n^2 per image: 5.3 s of a 4000 x 3000 x 16 calibrated run's block grid)
            g = np.matmul(np.matmul(Vv, C), Vu.T)
            if np.ndim(cols) == 0:
                g = g[:, :, 0]
            if np.ndim(rows) == 0:
                g = g[:, 0]
        if np.ndim(ks) == 0:
            g = g[0]
        np.negative(g, out=g)
        return np.exp(g, out=g).astype(np.float32)


def divided_grid(grid: BlockGrid, coeffs) -> BlockGrid:
    """The block grid of ``GainCorrected(images, coeffs)`` made from the grid of ``images``, without a pass
    over them: each block's mean divided by its image's gain at the block's centre.

    The gains are smooth (degree-4 Legendre maps over the field) and a block is ~1 % of the field a side,
    so a block's mean of ``image / gain`` is its mean over the gain at its centre to within the gain's
    variation across the block times the block's texture (measured on
    ``make_capture(shape=(1000, 1300), n_lights=16, seed=1, beam_exponent=30, beam_aim_error_deg=5)``
    with a dark frame: the means within 2.9e-4 (rms 1.2e-5) of the second pass's, the fitted log drop-offs
    within 1.4e-5, the measured intensities within 2e-12). The blocks' validity is the grid's: a dark pixel
    stays dark, and saturation is judged on the counts before the beams are divided out (the second pass
    judged it after).
    """
    K = grid.values.shape[0]
    coeffs = np.asarray(coeffs, dtype=float)
    Vv, Vu = _design(grid.rows, grid.cols, grid.shape, coeffs.shape[1] - 1)
    if len(coeffs) != K:
        raise UVPSInputError(f"divided_grid: {len(coeffs)} gain maps for a grid of {K} images")
    log_gain = np.matmul(np.matmul(Vv, coeffs), Vu.T)          # (K, R, C)
    return dataclasses.replace(grid, values=grid.values * np.exp(-log_gain), valid=grid.valid.copy())


def fit_log_grid(values, rows, cols, shape, degree) -> np.ndarray:
    """Legendre coefficients (K, n, n) of log maps ``values`` (K, R, C) given on a separable grid."""
    Vv, Vu = _design(rows, cols, shape, degree)
    n = degree + 1
    A = np.einsum("ri,cj->rcij", Vv, Vu).reshape(-1, n * n)
    coef = np.linalg.lstsq(A, values.reshape(len(values), -1).T, rcond=None)[0]
    return coef.T.reshape(len(values), n, n)
