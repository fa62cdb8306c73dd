"""Integrate a normal field into a height map.

Frames and signs (docs/architecture.md; every sign in this module follows this block):

- Pixel ``(row, col)``, image shape ``(M, N)``. World **x** points toward increasing column,
  **y** points UP (toward decreasing row), **z** toward the camera.
- Normals are ``(M, N, 3)`` arrays of unit ``(nx, ny, nz)`` in that frame, ``nz > 0``.
- Gradients ``p = dz/dx`` and ``q = dz/dy`` are dimensionless, so
  ``n = (-p, -q, 1) / sqrt(1 + p**2 + q**2)`` and ``p = -nx / nz``, ``q = -ny / nz``.
- Along the array axes: ``dz/d(col) = p * px`` and ``dz/d(row) = -q * px`` with ``px`` the pixel
  size. The solvers work in pixel units on the array axes (gradient along rows ``-q``) and multiply
  the result by the pixel size, so heights come out in micrometres.
- Height is known up to a constant. uvps fixes it by setting the **median height over valid pixels
  to 0** (valid = inside the mask and with finite gradients).

Two solvers, named by method and boundary condition (as in Queau, Durou and Aujol 2018):

- :func:`frankot_chellappa`: projection onto integrable Fourier functions (FFT, periodic). To avoid
  wrap-around at the borders the gradient field is mirrored into a ``(2M, 2N)`` field that is
  periodic and integrable (the even extension of the height); that field's transform is computed
  from the ``(M, N)`` field by cosine and sine transforms (its symmetries), never built.
- :func:`dct_poisson`: the discrete least-squares / Poisson solution with Neumann boundary, solved
  exactly in the DCT-II domain; no padding.

Masks: both solvers work on the whole rectangle. Outside the mask (and where a gradient is not
finite) the gradient is taken as 0, i.e. the surface there is treated as flat, and the height is
reported as NaN outside the mask. That is right for a masked-out area of a nearly flat canvas; if
the surface around a masked-out area is steep, the heights near its edge are bent. Solving on the
masked domain itself would need a sparse least-squares solve (not done here).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import Optional

import numpy as np
import scipy.fft

from ..errors import UVPSInputError, check_pixel_size
from .stack import row_bands
from .threads import default_threads, map_bands

logger = logging.getLogger(__name__)

__all__ = [
    "Gradients",
    "IntegrationResult",
    "gradients_from_normals",
    "frankot_chellappa",
    "dct_poisson",
    "integrate_normals",
    "nonintegrable_patches",
    "curl_magnitude",
    "METHODS",
]

#: :func:`nonintegrable_patches`: a gradient is far from integrable where the field's curl exceeds this
#: many of its robust standard deviations (MAD over the image).
CURL_OUTLIER_MAD = 15.0

#: :func:`nonintegrable_patches`: and exceeds this much (slope per pixel) at least. A crack wall whose
#: normals are 5 deg off across 1-2 px has a curl of 0.04-0.09; a clean field (noise-free, or the
#: generator's true normals) has a robust spread near 1e-5, so without a floor the relative threshold
#: alone took 24-42 % of such an image for long non-integrable patches.
CURL_FLOOR = 0.02

#: Integration methods accepted by :func:`integrate_normals` (``"fc"``: Frankot-Chellappa,
#: ``"dct"``: DCT-Poisson).
METHODS = ("fc", "dct")

_PADS = ("reflect", "none")


@dataclass
class Gradients:
    """Surface gradients computed from normals.

    Attributes
    ----------
    p, q : ndarray, shape (M, N), float32
        ``p = dz/dx`` (x toward increasing column), ``q = dz/dy`` (y toward decreasing row);
        dimensionless. 0 where the normal was not finite.
    invalid : ndarray of bool, shape (M, N)
        True where the normal had a non-finite component or was degenerate (``nx = ny = 0``
        with ``nz <= 0``) inside the mask; the gradient there is set to 0.
    n_invalid : int
        ``invalid.sum()``.
    n_clamped : int
        Number of pixels whose slope ``sqrt(p**2 + q**2)`` exceeded ``max_slope`` (this includes
        every normal with ``nz <= 0``) and was scaled down to ``max_slope``.
    mask : ndarray of bool or None
        The mask they were computed with (boolean, as checked), None without one: whoever reuses
        them (a run's detection, :func:`uvps.core.pipeline.detection_height`) compares it.
    """

    p: np.ndarray
    q: np.ndarray
    invalid: np.ndarray
    n_invalid: int
    n_clamped: int
    mask: Optional[np.ndarray] = None


@dataclass
class IntegrationResult:
    """A height map and the diagnostics of its integration.

    Attributes
    ----------
    height_um : ndarray, shape (M, N), float32
        Height toward the camera in micrometres. The median over valid pixels is 0 (the constant
        of integration). NaN outside the mask; pixels inside the mask with non-finite gradients keep
        the value the solver gives them (integrated through a zero gradient).
    method : str
        ``"fc"`` or ``"dct"``.
    residual_rms : float
        Root mean square over valid pixels of ``|grad(z) - (p, q)|`` (dimensionless slope), with
        ``grad(z)`` taken by central differences (one-sided at the borders) of the result. A
        diagnostic of how far the input was from an integrable field and of the discretisation.
    integrability : float
        Root mean square over valid pixels of ``dp/dy - dq/dx`` of the input, in 1/pixel (0 for an
        exactly integrable field).
    n_invalid : int
        Number of pixels inside the mask with non-finite gradients (or normals), set to 0 before
        solving.
    gradients : Gradients or None
        :func:`integrate_normals` with ``keep_gradients``: the normals' gradients as
        :func:`gradients_from_normals` gave them; else None.
    """

    height_um: np.ndarray
    method: str
    residual_rms: float
    integrability: float
    n_invalid: int
    gradients: Optional[Gradients] = None


# ----------------------------------------------------------------------------- validation


def _check_mask(mask, shape) -> Optional[np.ndarray]:
    if mask is None:
        return None
    mask = np.asarray(mask)
    if mask.shape != tuple(shape):
        raise UVPSInputError(f"mask must have shape {tuple(shape)}; got {mask.shape}")
    if mask.dtype != bool:
        if not np.issubdtype(mask.dtype, np.number) or not np.all(np.isin(mask, (0, 1))):
            raise UVPSInputError(
                f"mask must be boolean (or 0/1), True = use; got dtype {mask.dtype}"
            )
        mask = mask.astype(bool)
    if not mask.any():
        raise UVPSInputError("mask must contain at least one True (valid) pixel; got none")
    return mask


def _check_gradients(p, q) -> tuple[np.ndarray, np.ndarray]:
    p = np.asarray(p)
    q = np.asarray(q)
    for name, arr in (("p", p), ("q", q)):
        if arr.ndim != 2 or min(arr.shape) < 2:
            raise UVPSInputError(
                f"{name} must be a 2-D (M, N) array with M, N >= 2; got {arr.shape}"
            )
        if not np.issubdtype(arr.dtype, np.floating) and not np.issubdtype(arr.dtype, np.integer):
            raise UVPSInputError(f"{name} must be a real numeric array; got dtype {arr.dtype}")
    if p.shape != q.shape:
        raise UVPSInputError(f"p and q must have the same shape; got {p.shape} and {q.shape}")
    return p, q


def _check_normals(normals) -> np.ndarray:
    normals = np.asarray(normals)
    if normals.ndim != 3 or normals.shape[2] != 3 or min(normals.shape[:2]) < 2:
        raise UVPSInputError(
            f"normals must be an (M, N, 3) array (components last, M, N >= 2); got {normals.shape}"
        )
    if not np.issubdtype(normals.dtype, np.floating):
        raise UVPSInputError(f"normals must be a floating-point array; got dtype {normals.dtype}")
    return normals


# ----------------------------------------------------------------------------- gradients


def gradients_from_normals(normals, *, mask=None, max_slope: float = 20.0) -> Gradients:
    """Surface gradients ``p = dz/dx``, ``q = dz/dy`` from unit normals.

    Parameters
    ----------
    normals : ndarray, shape (M, N, 3)
        ``(nx, ny, nz)`` in the world frame (x right, y up, z toward the camera). Need not be
        exactly unit: only ratios are used. Not modified.
    mask : ndarray of bool, shape (M, N), optional
        True = use. Gradients outside the mask are set to 0 (not counted as invalid).
    max_slope : float, optional
        Largest slope magnitude ``sqrt(p**2 + q**2)`` kept (default 20, i.e. 87 degrees from the
        canvas plane). Steeper gradients are scaled down to it, keeping their direction.

    Returns
    -------
    Gradients
        ``p``, ``q`` as float32 and the counts of invalid and clamped pixels.

    Notes
    -----
    ``p = -nx / nz`` and ``q = -ny / nz``. As ``nz -> 0`` (grazing normals, usually noise in a
    shadowed or saturated pixel) the gradients blow up and one such pixel would tilt the whole
    integrated surface, so the slope magnitude is clamped to ``max_slope``; this is the same as
    clamping ``nz`` to at least ``1 / sqrt(1 + max_slope**2)`` while keeping the normal's azimuth.
    A normal with ``nz <= 0`` (facing away from the camera, not physical) is clamped the same way.
    Non-finite normals, and ``(0, 0, nz <= 0)``, get a zero gradient and are counted in
    ``n_invalid`` (a warning is logged).
    """
    normals = _check_normals(normals)
    try:
        max_slope = float(max_slope)
    except (TypeError, ValueError):
        raise UVPSInputError(f"max_slope must be a positive number; got {max_slope!r}") from None
    if not np.isfinite(max_slope) or max_slope <= 0:
        raise UVPSInputError(f"max_slope must be a positive number; got {max_slope!r}")
    mask = _check_mask(mask, normals.shape[:2])

    M, N = normals.shape[:2]
    p = np.empty((M, N), np.float32)
    q = np.empty((M, N), np.float32)
    invalid = np.empty((M, N), bool)
    # band by band: a dozen (M, N) float32 temporaries otherwise (3.8 GB for 10000 x 8000); the bands
    # over GRADIENT_THREADS threads (numpy's elementwise steps release the GIL), each writing its own rows
    # and the clamped counts, integers, summed: the same to the bit whatever the threads. On the normals
    # of a 4000 x 3000 run (scripts/benchmark_speed.py's capture), 0.33-0.40 s wall in one thread, 0.19-0.29 s
    # in two (this function timed with UVPS_THREADS=1 and 2 alternated 8 times, load 1.6-1.8)
    slope = np.float32(max_slope)
    n_clamped = sum(map_bands(
        lambda rows: _gradients_band(normals[rows], None if mask is None else mask[rows], slope,
                                     p[rows], q[rows], invalid[rows]),
        M, size=max(1, BAND_PIXELS // N), threads=default_threads(GRADIENT_THREADS)))
    n_invalid = int(invalid.sum())
    if n_invalid:
        logger.warning(
            "%d pixel(s) with non-finite or degenerate normals: gradient set to 0", n_invalid
        )
    if n_clamped:
        logger.info("%d pixel(s) steeper than max_slope=%g clamped", n_clamped, max_slope)
    return Gradients(p=p, q=q, invalid=invalid, n_invalid=n_invalid, n_clamped=n_clamped, mask=mask)


#: Pixels per band of the per-pixel steps (gradients, diagnostics): a band's temporaries are a few
#: times 4 MB.
BAND_PIXELS = 1 << 20


#: Threads of :func:`gradients_from_normals`' bands (at most; :func:`uvps.core.threads.default_threads`).
GRADIENT_THREADS = 2


def _bands(M: int, N: int):
    """Row slices of about :data:`BAND_PIXELS` pixels covering ``M`` rows of ``N`` pixels."""
    return row_bands(M, N, BAND_PIXELS)


def _gradients_band(normals, mask, max_slope, p, q, invalid) -> int:
    """:func:`gradients_from_normals` on one band of rows, into ``p``, ``q``, ``invalid``;
    returns the number of clamped pixels."""
    nx = normals[..., 0].astype(np.float32)
    ny = normals[..., 1].astype(np.float32)
    nz = normals[..., 2].astype(np.float32)
    finite = np.isfinite(nx) & np.isfinite(ny) & np.isfinite(nz)
    lateral = np.hypot(nx, ny)
    # Slope magnitude is lateral / nz; it is too steep when lateral > max_slope * nz (this also
    # catches nz <= 0 without dividing by it).
    steep = finite & (lateral > max_slope * nz)
    bad = ~finite | (steep & (lateral == 0))
    steep &= ~bad
    use = finite & ~bad
    if mask is not None:
        use &= mask
        steep &= mask
        bad &= mask

    with np.errstate(divide="ignore", invalid="ignore"):
        # Steep pixels: scale (-nx, -ny) / lateral to length max_slope (the direction is kept).
        denom = np.where(steep, lateral / max_slope, nz)
        p[...] = np.where(use, -nx / denom, np.float32(0))
        q[...] = np.where(use, -ny / denom, np.float32(0))
    invalid[...] = bad
    return int(steep.sum())


# ----------------------------------------------------------------------------- solvers


def _prepare(p, q, mask, *, copy: bool = True, invalid=None) -> tuple[np.ndarray, np.ndarray, np.ndarray, int]:
    """Float32 p, q with non-finite values, ``invalid`` pixels (bool, counted as non-finite) and pixels
    outside the mask set to 0: copies, or (``copy`` False, for float32 arrays this module made) the
    arrays themselves, modified in place.

    Returns p, q, the valid-pixel map and the number of non-finite (or ``invalid``) pixels inside the mask.
    """
    p, q = _check_gradients(p, q)
    mask = _check_mask(mask, p.shape)
    p = p.astype(np.float32, copy=copy)
    q = q.astype(np.float32, copy=copy)
    valid = np.isfinite(p)
    valid &= np.isfinite(q)
    if invalid is not None:
        valid &= ~invalid
    n_invalid = int(p.size - np.count_nonzero(valid)) if mask is None else int(np.count_nonzero(mask & ~valid))
    if mask is not None:
        valid &= mask
    if n_invalid:
        logger.warning("%d pixel(s) with non-finite gradients: set to 0", n_invalid)
    p[~valid] = 0
    q[~valid] = 0
    if not valid.any():
        raise UVPSInputError("p and q have no finite value inside the mask")
    return p, q, valid, n_invalid


def _sum_squares(values_of_band, valid, M, N) -> float:
    """Sum over ``valid`` pixels of ``values_of_band(rows) ** 2`` (float64), band by band."""
    total = 0.0
    for rows in _bands(M, N):
        v = values_of_band(rows)[valid[rows]].astype(np.float64)
        total += float(np.dot(v, v))
    return total


def _rows_gradient(a, rows):
    """``np.gradient(a, axis=0)[rows]`` from the band and its neighbouring rows only."""
    lo, hi = max(rows.start - 1, 0), min(rows.stop + 1, a.shape[0])
    return np.gradient(a[lo:hi], axis=0)[rows.start - lo:rows.stop - lo]


def _finish(z_px, p, q, valid, mask, pixel_size_um, method, n_invalid) -> IntegrationResult:
    """Fix the offset (median over valid pixels = 0), scale to um, compute the diagnostics.

    The diagnostics go band by band (each band's central differences take the rows beside it, so
    they are those of the whole map): no (M, N) temporary beyond one band.
    """
    z_px = z_px.astype(np.float32, copy=False)
    z_px -= np.float32(np.median(z_px[valid], overwrite_input=True))
    M, N = z_px.shape
    n_valid = int(np.count_nonzero(valid))
    # Diagnostics on the array axes: d/dx = d/d(col), d/dy = -d/d(row).
    # -d z/d(row) - q = -(dz/d(row) + q)
    sq = _sum_squares(lambda r: np.gradient(z_px[r], axis=1) - p[r], valid, M, N)
    sq += _sum_squares(lambda r: _rows_gradient(z_px, r) + q[r], valid, M, N)
    residual = float(np.sqrt(sq / n_valid))
    # dp/dy - dq/dx = -dp/d(row) - dq/d(col); its rms is that of dp/d(row) + dq/d(col).
    sq = _sum_squares(lambda r: _rows_gradient(p, r) + np.gradient(q[r], axis=1), valid, M, N)
    integrability = float(np.sqrt(sq / n_valid))
    z_px *= np.float32(pixel_size_um)
    if mask is not None:
        z_px[~mask] = np.nan
    return IntegrationResult(
        height_um=z_px,
        method=method,
        residual_rms=residual,
        integrability=integrability,
        n_invalid=n_invalid,
    )


def frankot_chellappa(p, q, *, pixel_size_um, pad: str = "reflect", mask=None) -> IntegrationResult:
    """Height from gradients by the Frankot-Chellappa projection (FFT).

    Parameters
    ----------
    p, q : ndarray, shape (M, N)
        ``p = dz/dx`` (x toward increasing column) and ``q = dz/dy`` (y toward decreasing row),
        dimensionless. Non-finite values are treated as 0. Not modified.
    pixel_size_um : float
        Pixel size in micrometres; the height is returned in micrometres.
    pad : {"reflect", "none"}, optional
        ``"reflect"`` (default): mirror the gradient field into a ``(2M, 2N)`` periodic, integrable
        field before the FFT, so nothing wraps around at the borders. ``"none"``: the classic
        periodic FC on the ``(M, N)`` field, only right for periodic surfaces.
    mask : ndarray of bool, shape (M, N), optional
        True = use. Gradients outside are set to 0 (flat; see the module notes on masks) and the
        height there is NaN.

    Returns
    -------
    IntegrationResult
        ``method="fc"``; median height over valid pixels is 0.

    Notes
    -----
    Frankot and Chellappa (1988) project the measured gradient field onto the integrable
    functions of the Fourier basis. With ``G_c = p`` and ``G_r = -q`` the gradients along columns
    and rows and ``w_c``, ``w_r`` the angular frequencies (rad/pixel), the least-squares height is::

        Z(w) = (-i w_c G_c(w) - i w_r G_r(w)) / (w_c**2 + w_r**2),   Z(0) = 0

    and the height is the **real part** of the inverse transform (the imaginary part is rounding
    noise; it is never the answer). The derivative is the continuous (spectral) one, ``i w``.

    The FFT assumes a periodic surface; a tilted or curved canvas is not, and the jump between
    opposite borders would spread across the whole map. With ``pad="reflect"`` the height is
    implicitly extended by even mirror symmetry into a ``(2M, 2N)`` tile: ``p`` is mirrored with
    a sign flip across the vertical borders (odd in x) and without across the horizontal ones
    (even in y), and ``q`` the other way round, so the extended field is integrable and
    periodic; that tile is never built: its transform is computed from the ``(M, N)`` field by
    cosine and sine transforms (``_fc_mirrored``). Where the slope at a border is not zero
    the extended surface has a kink there, which the spectral derivative resolves with a small
    ringing: the height error is of order 0.1-0.2 pixel x the border slope at the border and
    decays inward (a pixel-to-pixel ripple of the local slope of about ``slope / (pi d)`` at
    ``d`` pixels from the border). :func:`dct_poisson` has no such ringing.

    Cost: two pairs of cosine/sine transforms and one inverse pair on ``(M, N)`` float32
    arrays (:func:`_fc_mirrored`), O(MN log MN) time. Measured for 4000 x 3000 on 2 cores via
    :func:`integrate_normals`: 0.22 GiB peak extra memory (the gradients and two transforms),
    0.55 s; the FFT of the (2M, 2N) mirrored field took 0.86 GiB and 1.8 s.

    References
    ----------
    R. T. Frankot and R. Chellappa, "A method for enforcing integrability in shape from shading
    algorithms", IEEE TPAMI 10(4):439-451, 1988.
    Y. Queau, J.-D. Durou and J.-F. Aujol, "Normal integration: a survey", J. Math. Imaging Vis.
    60:576-593, 2018 (sec. 3, boundary handling).

    Examples
    --------
    >>> import numpy as np
    >>> p = np.full((32, 40), 0.5, np.float32); q = np.zeros((32, 40), np.float32)
    >>> z = frankot_chellappa(p, q, pixel_size_um=10.0).height_um  # rises 39 * 0.5 * 10 um
    >>> bool(abs(float(z[0, -1] - z[0, 0]) - 195.0) < 2.0)
    True
    """
    return _frankot_chellappa(p, q, pixel_size_um=pixel_size_um, pad=pad, mask=mask, copy=True)


def _frankot_chellappa(p, q, *, pixel_size_um, pad, mask, copy, invalid=None) -> IntegrationResult:
    pixel_size_um = check_pixel_size(pixel_size_um)
    if pad not in _PADS:
        raise UVPSInputError(f"pad must be one of {_PADS}; got {pad!r}")
    p, q, valid, n_invalid = _prepare(p, q, mask, copy=copy, invalid=invalid)
    M, N = p.shape
    z = _fc_mirrored(p, q) if pad == "reflect" else _fc_periodic(p, q)
    logger.debug("frankot_chellappa on (%d, %d), pad=%s", M, N, pad)
    return _finish(z, p, q, valid, mask, pixel_size_um, "fc", n_invalid)


def _fc_mirrored(p, q) -> np.ndarray:
    """Frankot-Chellappa on the mirrored ``(2M, 2N)`` field, computed on the ``(M, N)`` field.

    The mirrored field's Fourier transform is fixed by its symmetries: the height (even across
    both borders) by its DCT-II, ``p`` (odd across columns, even across rows) by a DST-II along
    the columns and a DCT-II along the rows, ``-q`` the other way round (Makhoul 1980). On those
    coefficients the projection ``Z = (-i w_c G_c - i w_r G_r) / (w_c**2 + w_r**2)`` reads, with
    ``w_c = pi k / N``, ``w_r = pi l / M`` (the phase factors of the half-sample shifts cancel)::

        Zc[l, k] = -(w_c Pt[l, k - 1] + w_r Rt[l - 1, k]) / (w_c**2 + w_r**2),   Zc[0, 0] = 0

    (index j of a DST-II is frequency j + 1; the highest frequency of each DST, N or M, is that
    of a sine that is 0 at every even-extended pixel and drops out), and the height is the
    inverse DCT-II of ``Zc``. This is the real part of the inverse FFT of the mirrored field's
    projection to float rounding, in four (M, N) float32 arrays instead of 2M x 2N complex ones
    (16x less memory). It differs from the ``irfft2`` of the mirrored field (uvps's earlier
    implementation) by that transform's row-Nyquist term: taking the real part of only the
    non-negative column frequencies keeps a pattern alternating in sign from row to row (1e-5 of
    the height range on a real capture's normals) that the full inverse transform cancels.
    """
    M, N = p.shape
    z = scipy.fft.dst(p, type=2, axis=1, workers=-1)                   # Pt, in place from here on
    z = scipy.fft.dct(z, type=2, axis=0, workers=-1, overwrite_x=True)
    t = scipy.fft.dct(q, type=2, axis=1, workers=-1)                   # Qt = -Rt
    t = scipy.fft.dst(t, type=2, axis=0, workers=-1, overwrite_x=True)
    wc = (np.pi / N * np.arange(N)).astype(np.float32)
    wr = (np.pi / M * np.arange(M)).astype(np.float32)
    for rows in _bands(M, N):
        l0, l1 = rows.start, rows.stop
        zc = np.empty((l1 - l0, N), np.float32)
        zc[:, 0] = 0
        np.multiply(z[rows, :-1], -wc[1:], out=zc[:, 1:])            # -w_c Pt[l, k - 1]
        lo = max(l0, 1)
        zc[lo - l0:] += wr[lo:l1, None] * t[lo - 1:l1 - 1]           # +w_r Qt[l - 1, k]
        denom = wc[None, :] ** 2 + wr[rows, None] ** 2
        if l0 == 0:
            denom[0, 0] = 1.0
        zc /= denom
        z[rows] = zc
    del t
    z[0, 0] = 0
    z = scipy.fft.idct(z, type=2, axis=0, workers=-1, overwrite_x=True)
    return scipy.fft.idct(z, type=2, axis=1, workers=-1, overwrite_x=True)


def _fc_periodic(p, q) -> np.ndarray:
    """Frankot-Chellappa on the (M, N) field taken as periodic (real FFTs)."""
    M, N = p.shape
    gc_hat = scipy.fft.rfft2(p, workers=-1)
    gr_hat = scipy.fft.rfft2(-q, workers=-1)
    wc = (2 * np.pi * scipy.fft.rfftfreq(N)).astype(np.float32)[None, :]
    wr = (2 * np.pi * scipy.fft.fftfreq(M)).astype(np.float32)[:, None]
    denom = wc**2 + wr**2
    denom[0, 0] = 1.0
    # Z = (-i wc Gc - i wr Gr) / denom, built in place in gc_hat to keep memory down.
    gc_hat *= wc
    gr_hat *= wr
    gc_hat += gr_hat
    del gr_hat
    gc_hat *= np.complex64(-1j)
    gc_hat /= denom
    gc_hat[0, 0] = 0
    # irfft2 returns the real part of the inverse transform of the Hermitian spectrum; the
    # height is this real part (never the imaginary part).
    return scipy.fft.irfft2(gc_hat, s=(M, N), workers=-1).astype(np.float32, copy=False)


def dct_poisson(p, q, *, pixel_size_um, mask=None) -> IntegrationResult:
    """Height from gradients by the DCT solution of the Poisson equation, Neumann boundary.

    Parameters
    ----------
    p, q : ndarray, shape (M, N)
        ``p = dz/dx`` (x toward increasing column) and ``q = dz/dy`` (y toward decreasing row),
        dimensionless. Non-finite values are treated as 0. Not modified.
    pixel_size_um : float
        Pixel size in micrometres; the height is returned in micrometres.
    mask : ndarray of bool, shape (M, N), optional
        True = use. Gradients outside are set to 0 (flat; see the module notes on masks) and the
        height there is NaN.

    Returns
    -------
    IntegrationResult
        ``method="dct"``; median height over valid pixels is 0.

    Notes
    -----
    Least squares on the pixel grid: each pair of neighbours must differ by the mean of their two
    gradients (trapezoid rule), ``z[r, c+1] - z[r, c] = (p[r, c] + p[r, c+1]) / 2`` and
    ``z[r+1, c] - z[r, c] = -(q[r, c] + q[r+1, c]) / 2``. Its normal equations are the discrete
    Poisson equation ``lap z = div(p, q)`` with the natural (Neumann) boundary condition
    ``dz/dn = (p, q) . n`` (Simchony, Chellappa and Shao 1990). The 5-point Neumann Laplacian is
    diagonal in the DCT-II basis with eigenvalues
    ``-(4 sin^2(pi k / 2M) + 4 sin^2(pi l / 2N))``, so the solution is one forward DCT, a division
    and one inverse DCT (the constant term, undetermined, is set to 0). The result is exact for
    any quadratic surface; no padding is needed and the borders are handled by the boundary
    condition, not by periodicity.

    Cost: two DCTs on ``(M, N)`` float32, no padding. Measured for 4000 x 3000 on 2 cores via
    :func:`integrate_normals`: 0.26 GiB peak extra memory (mostly the gradients), 0.54 s.

    References
    ----------
    T. Simchony, R. Chellappa and M. Shao, "Direct analytical methods for solving Poisson
    equations in computer vision problems", IEEE TPAMI 12(5):435-446, 1990.
    Y. Queau, J.-D. Durou and J.-F. Aujol, "Normal integration: a survey", J. Math. Imaging Vis.
    60:576-593, 2018 (sec. 4, DCT solution of the Neumann problem).

    Examples
    --------
    >>> import numpy as np
    >>> p = np.full((4, 5), 0.5, np.float32); q = np.zeros((4, 5), np.float32)
    >>> z = dct_poisson(p, q, pixel_size_um=10.0).height_um
    >>> bool(np.allclose(np.diff(z, axis=1), 5.0, atol=1e-3))
    True
    """
    return _dct_poisson(p, q, pixel_size_um=pixel_size_um, mask=mask, copy=True)


def _dct_poisson(p, q, *, pixel_size_um, mask, copy, invalid=None) -> IntegrationResult:
    pixel_size_um = check_pixel_size(pixel_size_um)
    p, q, valid, n_invalid = _prepare(p, q, mask, copy=copy, invalid=invalid)
    M, N = p.shape

    # Right-hand side b = D^T h of the normal equations D^T D z = D^T h, where h holds the
    # half-pixel gradients (mean of two neighbours) and D the forward differences. D^T h at a
    # pixel is (h entering) - (h leaving); h = 0 beyond the borders (Neumann).
    b = np.zeros((M, N), np.float32)
    hc = 0.5 * (p[:, 1:] + p[:, :-1])  # z[:, c+1] - z[:, c]
    b[:, 1:] += hc
    b[:, :-1] -= hc
    del hc
    hr = -0.5 * (q[1:, :] + q[:-1, :])  # z[r+1, :] - z[r, :]  (rows go down, y goes up)
    b[1:, :] += hr
    b[:-1, :] -= hr
    del hr
    # D^T D = -lap (the Neumann 5-point Laplacian, sign flipped) has the eigenvalues
    # 4 sin^2(pi k / 2M) + 4 sin^2(pi l / 2N) >= 0 in the DCT-II basis; b = D^T h = -div(p, q).
    b_hat = scipy.fft.dctn(b, type=2, norm="ortho", workers=-1)
    del b
    lam_r = (4 * np.sin(np.pi * np.arange(M) / (2 * M)) ** 2).astype(np.float32)[:, None]
    lam_c = (4 * np.sin(np.pi * np.arange(N) / (2 * N)) ** 2).astype(np.float32)[None, :]
    denom = lam_r + lam_c
    denom[0, 0] = 1.0
    b_hat /= denom
    b_hat[0, 0] = 0
    z = scipy.fft.idctn(b_hat, type=2, norm="ortho", workers=-1).astype(np.float32, copy=False)
    del b_hat
    return _finish(z, p, q, valid, mask, pixel_size_um, "dct", n_invalid)


def integrate_normals(
    normals, *, pixel_size_um, method: str = "fc", mask=None, keep_gradients: bool = False
) -> IntegrationResult:
    """Height in micrometres from a normal map.

    Parameters
    ----------
    normals : ndarray, shape (M, N, 3)
        Unit normals ``(nx, ny, nz)`` (x right, y up, z toward the camera). Not modified.
    pixel_size_um : float
        Pixel size in micrometres.
    method : {"fc", "dct"}, optional
        ``"fc"``: :func:`frankot_chellappa` with mirror padding (the paper's method, default);
        ``"dct"``: :func:`dct_poisson`.
    mask : ndarray of bool, shape (M, N), optional
        True = use; the height is NaN outside.
    keep_gradients : bool
        Keep the normals' gradients, unchanged, in the result's ``gradients``: a run that detects
        reuses them for its detection's height instead of computing them again (gradients.tif's
        writer computes its own: held to the writing they raised a large run's peak).

    Returns
    -------
    IntegrationResult
        ``n_invalid`` counts the non-finite normals inside the mask.

    Notes
    -----
    :func:`gradients_from_normals` (default ``max_slope``) followed by the chosen solver. Pixels
    with non-finite normals are integrated through a zero gradient, keep a finite height and are
    left out of the median and the diagnostics.
    """
    if method not in METHODS:
        raise UVPSInputError(f"method must be one of {METHODS}; got {method!r}")
    pixel_size_um = check_pixel_size(pixel_size_um)
    grads = gradients_from_normals(normals, mask=mask)
    # the gradients are this function's own: solved in place, not copied (0.64 GB at 10000 x 8000). The
    # solver writes into them only the 0 of its left-out pixels: the invalid ones (excluded from the
    # median/diagnostics) and those outside the mask, already 0, and non-finite ones (a (0, 0, 0) normal's
    # gradient is NaN), which kept gradients keep: they are solved on copies then.
    p, q = grads.p, grads.q
    if keep_gradients and not (np.isfinite(p).all() and np.isfinite(q).all()):
        p, q = p.copy(), q.copy()
    invalid = grads.invalid if grads.n_invalid else None
    if method == "fc":
        res = _frankot_chellappa(p, q, pixel_size_um=pixel_size_um, pad="reflect", mask=mask, copy=False,
                                 invalid=invalid)
    else:
        res = _dct_poisson(p, q, pixel_size_um=pixel_size_um, mask=mask, copy=False, invalid=invalid)
    res.gradients = grads if keep_gradients else None
    return res


def nonintegrable_patches(p, q, *, min_extent_px: float, k: float = CURL_OUTLIER_MAD, floor: float = CURL_FLOOR,
                          mask=None) -> np.ndarray:
    """Where a gradient field is far from any surface's over a long patch: the walls of cracks.

    A surface's gradients have no curl, ``dp/dy = dq/dx``; photometric-stereo gradients lose that
    where the model fails, and most where the lamps graze narrow grooves (a crack's walls are shadowed
    under most lamps and their normals came out 5 deg off at the median on the detection benchmark's
    captures). Integrated, such gradients spread a relief of their own around each crack. Agrawal,
    Raskar and Chellappa (2006) find unreliable gradients by the curl and integrate without them; here
    the pixels whose curl exceeds ``k`` robust standard deviations of the field's curl, and ``floor``, are
    taken where they form a connected patch (8-neighbours, grown by one pixel) longer than ``min_extent_px`` on its
    bounding box's long side. A protrusion's rim, where the curl of a steep dome's discretised
    gradients is high too, is no longer than the protrusion is wide, so ``min_extent_px`` is the
    widest protrusion (``DetectionParams.max_width_um``); a crack network runs for millimetres.

    Parameters
    ----------
    p, q : ndarray, shape (M, N)
        ``p = dz/dx`` (x toward increasing column), ``q = dz/dy`` (y toward decreasing row).
    min_extent_px : float
        Patches shorter than this (pixels) are kept.
    k : float
        Threshold in robust standard deviations (1.4826 MAD) of the curl.
    floor : float
        Least threshold (slope per pixel): on a clean field the robust spread is near zero.
    mask : ndarray of bool, optional
        True = use; the scale is measured inside it, and nothing outside is flagged.

    Returns
    -------
    ndarray of bool, shape (M, N)
        True where the gradients are to be left out.

    References
    ----------
    A. Agrawal, R. Raskar and R. Chellappa, "What is the range of surface reconstructions from a
    gradient field?", ECCV 2006, LNCS 3951, pp. 578-591 (sec. 4: curl to find the gradients to drop).
    """
    import cv2

    p = np.asarray(p, np.float32)
    q = np.asarray(q, np.float32)
    curl = curl_magnitude(p, q)
    inside = None if mask is None else np.asarray(mask, bool)
    if inside is None:
        scale = 1.4826 * float(np.median(curl))
    else:
        scale = 1.4826 * float(np.median(curl[inside])) if inside.any() else 0.0
    threshold = max(k * scale, floor)
    if not threshold > 0:
        return np.zeros(p.shape, bool)
    high = curl > threshold
    del curl
    if inside is not None:
        high &= inside
    # OpenCV's connected components (8-neighbours, int32 labels, each one's bounding box) instead of
    # scikit-image's label + regionprops_table: the same components and boxes, without the int64 label
    # image (96 MB at 4000 x 3000) and the per-region properties
    n_lab, lab, stats, _ = cv2.connectedComponentsWithStats(high.view(np.uint8), connectivity=8, ltype=cv2.CV_32S)
    if n_lab <= 1:
        return np.zeros(p.shape, bool)
    extent = np.maximum(stats[:, cv2.CC_STAT_WIDTH], stats[:, cv2.CC_STAT_HEIGHT])
    long = extent >= min_extent_px
    long[0] = False                     # the background
    if not long.any():
        return np.zeros(p.shape, bool)
    # grown by one pixel (a 3 x 3 square; nothing beyond the image: scipy's binary_dilation with
    # border_value 0, as cv2.dilate leaves pixels outside out of the maximum)
    out = cv2.dilate(long[lab].view(np.uint8), np.ones((3, 3), np.uint8)).view(bool)
    if inside is not None:
        out &= inside
    return out


def curl_magnitude(p, q, *, rows: int = 256) -> np.ndarray:
    """``|dp/dy - dq/dx|`` (y up) of a gradient field, NaN taken as 0, by ``np.gradient``'s differences.

    The same values, to the bit, as ``np.abs(-np.gradient(np.nan_to_num(p), axis=0) -
    np.gradient(np.nan_to_num(q), axis=1))``, made ``rows`` rows at a time (each band with one row
    of ``p`` either side), in threads (:func:`uvps.core.threads.map_bands`): the whole-image form holds
    five float32 images besides its output (240 MB at 4000 x 3000). Called inside another parallel
    part (:func:`uvps.core.threads.concurrently`: the run's detection height beside its colour areas),
    its bands run one after another in that thread.
    """
    p = np.asarray(p, np.float32)
    q = np.asarray(q, np.float32)
    if p.ndim != 2 or q.shape != p.shape:
        raise UVPSInputError(f"p and q must be two images of one shape; got {p.shape} and {q.shape}")
    M = p.shape[0]
    if M < 2 or p.shape[1] < 2:
        raise UVPSInputError(f"a curl needs at least 2 x 2 gradients; got {p.shape}")
    out = np.empty(p.shape, np.float32)

    def band(rr):
        r0, r1 = rr.start, rr.stop
        a0, a1 = max(r0 - 1, 0), min(r1 + 1, M)
        dpdy = np.gradient(np.nan_to_num(p[a0:a1]), axis=0)[r0 - a0: r0 - a0 + r1 - r0]
        dqdx = np.gradient(np.nan_to_num(q[r0:r1]), axis=1)
        np.abs(-dpdy - dqdx, out=out[r0:r1])

    map_bands(band, M, size=max(2, int(rows)), threads=default_threads(2))
    return out
