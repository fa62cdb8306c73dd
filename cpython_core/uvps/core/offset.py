"""The additive term of a real capture: camera black level and stray light, measured from the images.

Image model (docs/architecture.md, "Image model of a real capture")::

    I_k(x) = a(x) * S_k(x) + c(x)

``a`` is everything common to all images and multiplicative (albedo, vignetting), ``S_k`` the
irradiance and shading of lamp k, and ``c`` an additive term that is the same in every image: the
black level the camera or the raw converter left in the files, and stray light (veiling glare)
that is smooth across the field. ``c`` is small (about 1 % of the signal), but the lamps' elevation
is decided by a residual that changes by about 1e-4 of itself between the true lamps and lamps 20
degrees off (the near-light remnant of the bas-relief ambiguity, :mod:`uvps.core.lights`): left in the
images, a 1 % black level sends the estimated lamps 20-30 degrees off, and 0.2 % still 5 degrees.
The photometric residual itself cannot measure ``c``: a constant offset and the lamps' elevations
are nearly confounded in it (both change the images' contrast). So ``c`` is measured by a cue of
its own.

The cue: **the painting's colour areas must cancel in the ratio of two images.** Without ``c``,
``log I_k - mean_j log I_j`` is free of the albedo (flat-field stage, :mod:`uvps.core.flatfield`), a
smooth map plus the shading of the texture. With ``c`` left in, it carries the colour areas
themselves, dark paint most: to first order ``c * (1 / I_k - mean_j 1 / I_j)``, large where the
paint is dark and of opposite sign for bright and dim lamps. ``c`` is the value for which the
high-pass part of those log-ratio maps (what a Legendre polynomial of the drop-off's degree does
not fit) has no component along that predicted pattern. It is a linear regression solved by a few
Gauss-Newton steps on block means (16 x 16 px: cheap, and the texture's shading averages out), per
colour channel, with ``c`` constant or a low-order polynomial across the field (stray light). It
needs paint of different brightness in the field (it is a painting: it nearly always has); its
standard error (a jackknife over tiles of the field, and the difference between the measures on
blocks of two sizes: the texture's shading within a block biases it) says how well it was pinned.

What it assumes: dark and bright paint have the same mean surface orientation (the canvas plane),
so that their shading does not differ systematically. Ambient light that *reflects off the
painting* is not an offset but a light (it is multiplied by the albedo); it cannot be told from the
lamps by any image cue: take a frame with the UV lamp off and pass it as the dark frame.
"""
from __future__ import annotations

import logging
import threading
from dataclasses import dataclass, field
from typing import NamedTuple, Optional

import numba
import numpy as np
from numpy.polynomial import legendre as Lg

from ..errors import UVPSInputError
from .stack import StackView, raw_parts
from .threads import default_threads, map_bands

log = logging.getLogger(__name__)

__all__ = ["AdditiveTerm", "OffsetImages", "estimate_additive", "known_additive"]


@dataclass
class AdditiveTerm:
    """The additive term ``c(x)`` of every image, per colour channel, in the files' counts.

    Attributes
    ----------
    coeffs : ndarray, (C, n, n)
        Legendre coefficients of ``c`` over the image (rows, cols mapped to [-1, 1]) per channel;
        n = degree + 1 (degree 0: a constant per channel).
    source : str
        ``"estimated"``, ``"black level"`` (given), ``"dark frame"`` (subtracted on reading) or
        ``"none"``.
    shape : tuple
        Image shape (M, N).
    stderr : ndarray, (C,) or None
        Standard error of the mean of ``c`` per channel (estimated terms only).
    median_signal : float
        Median of the images above ``c`` (grey), to judge the size of ``c``.
    """

    coeffs: np.ndarray
    source: str
    shape: tuple
    stderr: Optional[np.ndarray] = None
    median_signal: float = float("nan")
    diagnostics: dict = field(default_factory=dict)

    @property
    def channels(self) -> int:
        return self.coeffs.shape[0]

    @property
    def mean(self) -> np.ndarray:
        """Mean of ``c`` over the image, per channel (the constant Legendre term)."""
        return self.coeffs[:, 0, 0].copy()

    @property
    def is_zero(self) -> bool:
        return not np.any(self.coeffs)

    def band(self, r0: int, r1: int, *, grey=False) -> np.ndarray:
        """``c`` on rows r0..r1: (r1 - r0, N, C) float32, (r1 - r0, N) with ``grey``; broadcastable
        (1, 1, C) when constant."""
        M, N = self.shape
        deg = self.coeffs.shape[1] - 1
        if deg == 0:
            v = self.coeffs[:, 0, 0].astype(np.float32)
            return np.float32(v.mean()).reshape(1, 1) if grey else v.reshape(1, 1, -1)
        Vv = Lg.legvander(_unit(np.arange(r0, r1), M), deg)
        Vu = Lg.legvander(_unit(np.arange(N), N), deg)
        out = np.einsum("ri,cij,nj->rnc", Vv, self.coeffs, Vu).astype(np.float32)
        return out.mean(axis=-1) if grey else out

    def at(self, rows, cols) -> np.ndarray:
        """Grey ``c`` (channel mean) at scattered pixels: (P,)."""
        M, N = self.shape
        deg = self.coeffs.shape[1] - 1
        Vv = Lg.legvander(_unit(rows, M), deg)
        Vu = Lg.legvander(_unit(cols, N), deg)
        return np.einsum("pi,ij,pj->p", Vv, self.coeffs.mean(axis=0), Vu)

    def evaluate(self, rows, cols) -> np.ndarray:
        """``c`` per channel at pixels (rows[i], cols[i]) (arrays of one shape): (..., C)."""
        M, N = self.shape
        deg = self.coeffs.shape[1] - 1
        rows, cols = np.broadcast_arrays(np.asarray(rows, float), np.asarray(cols, float))
        Vv = Lg.legvander(_unit(rows, M), deg)
        Vu = Lg.legvander(_unit(cols, N), deg)
        return np.einsum("...i,cij,...j->...c", Vv, self.coeffs, Vu)

    def to_json(self) -> dict:
        out = {"source": self.source, "mean_counts": [round(float(v), 3) for v in self.mean],
               "subtracted": bool(not self.is_zero and self.diagnostics.get("used", True)),
               "degree": int(self.coeffs.shape[1] - 1),
               "fraction_of_median_signal": (round(float(self.mean.mean() / self.median_signal), 6)
                                             if np.isfinite(self.median_signal) and self.median_signal > 0 else None)}
        if self.coeffs.shape[1] > 1:
            out["legendre_coeffs"] = self.coeffs.tolist()
        if self.stderr is not None:
            out["stderr_counts"] = [round(float(v), 3) if np.isfinite(v) else None for v in self.stderr]
        out.update(self.diagnostics)
        return out


class OffsetImages(StackView):
    """A capture's stack seen with its additive term removed, computed on access.

    Indexing returns float32 ``images[key] - c`` for the pixels indexed; the stack itself is never
    copied or modified (a 22 MP x 16 uint16 capture stays 1.15 GB, not 2.3 GB as float32). Supports
    the access patterns of the stages: ``[k]``, ``[k, rows, cols]`` and ``[:, rows, cols]`` with
    slices, and ``[:, r, c]`` with two index arrays of the same shape (scattered pixels).
    Values may fall below 0 where the noise is larger than the signal; the stages treat them as dark.
    """

    def __init__(self, images, term: "AdditiveTerm"):
        super().__init__(images)
        self.term = term

    def correct(self, out, kk, rk, ck):
        M, N = self.shape[1:3]
        colour = self.ndim == 4
        if self.term.coeffs.shape[1] == 1:   # a constant per channel: no coordinates needed
            c = self.term.coeffs[:, 0, 0].astype(np.float32)
            return out - (c if colour else np.float32(c.mean()))
        rows, cols = np.arange(M)[rk], np.arange(N)[ck]
        if np.ndim(rows) == 1 and np.ndim(cols) == 1 and (isinstance(rk, slice) or isinstance(ck, slice)):
            c = self.term.evaluate(rows[:, None], cols[None, :])      # a rectangle: (m, n, C)
        else:
            c = self.term.evaluate(rows, cols)                          # points, or a line: (..., C)
        c = c if colour else c.mean(axis=-1)
        return out - c.astype(np.float32)


def _unit(coord, size):
    return (2.0 * np.asarray(coord, dtype=float) - (size - 1)) / max(size - 1, 1)


def known_additive(value, *, shape, channels, source="black level", median_signal=float("nan")) -> AdditiveTerm:
    """An additive term the user gave: one number, or one per channel (counts)."""
    v = np.atleast_1d(np.asarray(value, dtype=float))
    if v.ndim != 1 or v.size not in (1, channels) or not np.all(np.isfinite(v)):
        raise UVPSInputError(f"black_level must be one number or {channels} (one per channel); got {value!r}")
    if np.any(v < 0):
        raise UVPSInputError(f"black_level must be >= 0 counts; got {value!r}")
    v = np.broadcast_to(v, (channels,)).astype(float)
    return AdditiveTerm(v.reshape(-1, 1, 1).copy(), source, tuple(shape), None, median_signal)


class BlockStats(NamedTuple):
    """One image's ``block`` x ``block`` statistics (:func:`block_stats`)."""

    means: np.ndarray        # (R, Cb) grey, (R, Cb, C) colour, float64
    grey_min: np.ndarray     # (R, Cb): the smallest sum over channels of a pixel in the block
    sample_min: np.ndarray   # (R, Cb): the smallest sample (any channel) in the block
    saturated: np.ndarray    # (R, Cb) bool: a sample at or above ``saturation`` in the block


def block_stats(img, block: int, saturation=None) -> BlockStats:
    """Block means, minima and saturation of an (R * block, Cb * block[, C]) image in one pass.

    The drop-off's block grid and the additive term's blocks need all four; computed with numpy they
    were four passes over the image (the block grid took 1.5 s of a 4000 x 3000 x 16 RGB capture's
    light estimate, ~10 s at 10000 x 8000). A compiled loop reads each sample once (numba, as the
    normals kernel). The means are summed in float64, rows first, then columns: the same values as
    ``img.reshape(R, block, Cb, block, C).mean(axis=(1, 3))`` (exactly for integer images, to
    float64 rounding otherwise).
    """
    a = np.asarray(img)
    grey = a.ndim == 2
    a3 = a[..., None] if grey else a
    sat = np.inf if saturation is None else float(saturation)
    none = np.zeros((1, 1, 1), np.float32)
    means, gmin, smin, satd = _first_call(_block_stats_kernel, a3, none, none[..., 0], False, False, False,
                                          int(block), sat)
    return BlockStats(means[..., 0] if grey else means, gmin, smin, satd)


@numba.njit(inline="always", nogil=True, cache=True)
def _view_sample(a, d, f, has_dark, has_factor, i, j, c):  # pragma: no cover - compiled
    # one sample as a view computes it, in its float32 arithmetic: float32(raw), minus the dark frame
    # (float32, or integer counts as stored: converted exactly) and clipped at 0, times the beam's factor
    x = np.float32(a[i, j, c])
    if has_dark:
        x = x - np.float32(d[i, j, c])
        if x < np.float32(0.0):
            x = np.float32(0.0)
    if has_factor:
        x = x * f[i, j]
    return x


@numba.njit(inline="always", nogil=True, cache=True)
def _fold_block_row(acc, block, means, r):  # pragma: no cover - compiled
    # one block row's column sums added into its blocks' sums, in one order, and the sums cleared for the next
    for j in range(acc.shape[0]):
        for c in range(acc.shape[1]):
            means[r, j // block, c] += acc[j, c]
            acc[j, c] = 0.0


def block_stats_parts(parts, block: int, saturation=None) -> BlockStats:
    """:func:`block_stats` of the band a view yields, read from its :class:`uvps.core.stack.RawParts`:
    each sample converted, dark-subtracted and multiplied as it is read (one pass over the band as
    stored, no temporary), to the same float32 values the view yields, so the same statistics to the
    bit. ``parts.done()`` is called once the band is read."""
    a = parts.raw
    grey = a.ndim == 2
    a3 = a[..., None] if grey else a
    none = np.zeros((1, 1, 1), np.float32)
    d = none if parts.dark is None else (parts.dark[..., None] if grey else parts.dark)
    f = none[..., 0] if parts.factor is None else parts.factor
    sat = np.inf if saturation is None else float(saturation)
    try:
        means, gmin, smin, satd = _first_call(_block_stats_kernel, a3, d, f, True, parts.dark is not None,
                                              parts.factor is not None, int(block), sat)
    finally:
        parts.done()
    return BlockStats(means[..., 0] if grey else means, gmin, smin, satd)


@numba.njit(nogil=True, cache=True)
def _block_stats_kernel(a, d, f, as_view, has_dark, has_factor, block, sat):  # pragma: no cover - compiled
    # block means, minima and saturation of an array's own values (as_view False: float64 ones too,
    # which a float32 conversion would round), or of the samples a view computes, in its float32
    # arithmetic: the value float32(raw), minus the dark frame and clipped at 0, times the factor.
    # With a dark frame each row's values are made first (_dark_row), then summed: its clip in the
    # per-sample loop made that loop 12x slower (14 ns a sample against 1-2; the same sums in the same order)
    R, Cb, C = a.shape[0] // block, a.shape[1] // block, a.shape[2]
    # one block row's column sums at a time (all of them at once were R * Cb * block * C float64, 36 MB
    # an image on 8 px blocks at 4000 x 3000 RGB, memory touched for the first time on every call)
    acc = np.zeros((Cb * block, C))
    means = np.zeros((R, Cb, C))
    gmin = np.full((R, Cb), np.inf)
    smin = np.full((R, Cb), np.inf)
    satd = np.zeros((R, Cb), np.bool_)
    dark_rows = as_view and has_dark
    row = np.empty((Cb * block if dark_rows else 1, C), np.float32)
    for i in range(R * block):
        r = i // block
        if dark_rows:
            _dark_row(a, d, f, has_factor, i, row)
        for cb in range(Cb):
            lo_g, lo_s, hit = gmin[r, cb], smin[r, cb], satd[r, cb]
            for j in range(cb * block, (cb + 1) * block):
                g = 0.0
                for c in range(C):
                    if dark_rows:
                        v = float(row[j, c])
                    elif as_view:
                        v = float(_view_sample(a, d, f, False, has_factor, i, j, c))
                    else:
                        v = float(a[i, j, c])
                    acc[j, c] += v
                    g += v
                    lo_s = min(lo_s, v)
                    hit |= v >= sat
                lo_g = min(lo_g, g)
            gmin[r, cb], smin[r, cb], satd[r, cb] = lo_g, lo_s, hit
        if i % block == block - 1:
            _fold_block_row(acc, block, means, r)
    return means / (block * block), gmin, smin, satd


@numba.njit(inline="always", nogil=True, cache=True)
def _dark_row(a, d, f, has_factor, i, row):  # pragma: no cover - compiled
    # row i's first row.shape[0] samples as a dark-subtracted view yields them (_view_sample's arithmetic)
    for j in range(row.shape[0]):
        for c in range(row.shape[1]):
            row[j, c] = _view_sample(a, d, f, True, has_factor, i, j, c)


def corrected_band(parts, *, out: np.ndarray) -> np.ndarray:
    """The band a view yields, from its :class:`uvps.core.stack.RawParts`, written into ``out`` (float32,
    the band's shape): each sample converted, dark-subtracted and multiplied in one pass, in the view's
    own float32 arithmetic (the same values to the bit). ``parts.done()`` is called once it is read."""
    a = parts.raw
    grey = a.ndim == 2
    none = np.zeros((1, 1, 1), np.float32)
    d = none if parts.dark is None else (parts.dark[..., None] if grey else parts.dark)
    f = none[..., 0] if parts.factor is None else parts.factor
    try:
        _first_call(_corrected_band_kernel, a[..., None] if grey else a, d, f, parts.dark is not None,
                    parts.factor is not None, out[..., None] if grey else out)
    finally:
        parts.done()
    return out


@numba.njit(nogil=True, cache=True)
def _corrected_band_kernel(a, d, f, has_dark, has_factor, out):  # pragma: no cover - compiled
    for i in range(a.shape[0]):
        for j in range(a.shape[1]):
            for c in range(a.shape[2]):
                out[i, j, c] = _view_sample(a, d, f, has_dark, has_factor, i, j, c)


def image_block_stats(images, k: int, rows: slice, cols: slice, block: int, saturation=None) -> BlockStats:
    """:func:`block_stats` of ``images[k, rows, cols]``: a view of files or an array whose corrections are
    :class:`uvps.core.stack.RawParts` (a dark frame, the beams) read as stored and corrected as each sample is
    read (:func:`block_stats_parts`); memory-mapped files summed where they lie (no copy: their own values);
    anything else indexed."""
    parts = None if isinstance(images, np.ndarray) else raw_parts(images, k, rows, cols)
    if parts is None:
        return block_stats(images[k, rows, cols], block, saturation)
    if isinstance(images, StackView):
        return block_stats_parts(parts, block, saturation)
    try:
        return block_stats(parts.raw, block, saturation)
    finally:
        parts.done()


#: Threads :func:`each_image` runs a pass over the images in (the machine's 2 cores, at most
#: :func:`uvps.core.threads.default_threads`).
IMAGE_WORKERS = 2


def each_image(one, K: int) -> None:
    """``one(k)`` for every image: the first in this thread (numba types a kernel on its first call, never in
    two threads at once), the others in :data:`IMAGE_WORKERS` threads (one with ``UVPS_THREADS=1``)."""
    map_bands(lambda k: one(k.start), K, size=1, threads=default_threads(IMAGE_WORKERS), first_alone=True)


_COMPILING = threading.Lock()
_TYPED = set()


def _first_call(kernel, *args):
    """``kernel(*args)``; its first call with a signature under a lock: numba types a kernel on its first
    call with new argument types, and the stages call these from their threads."""
    sig = (kernel,) + tuple(map(_type_key, args))
    if sig in _TYPED:
        return kernel(*args)
    with _COMPILING:
        r = kernel(*args)
        _TYPED.add(sig)
    return r


def _type_key(a) -> tuple:
    """A key that tells apart what numba types differently, in 0.3 us where ``numba.typeof`` takes 7 us (the
    normals' bands call a kernel 3000 times at 4000 x 3000 x 16): an array by its dtype, dimensions, layout,
    writability (and alignment, which numba ignores); a bool, a float, an int numba holds in int64 by its type;
    anything else by ``numba.typeof`` itself."""
    if isinstance(a, np.ndarray):
        f = a.flags
        return (a.dtype, a.ndim, f.c_contiguous, f.f_contiguous, f.writeable, f.aligned)
    if isinstance(a, (bool, float, np.bool_, np.floating)) or (isinstance(a, (int, np.integer))
                                                               and -2**63 <= a < 2**63):
        return (type(a),)
    return (numba.typeof(a),)


def _grid(shape, block: int) -> tuple:
    """The centred grid of ``block`` px blocks of an (M, N) image: (R, Cb, r0, c0)."""
    M, N = shape
    R, Cb = M // block, N // block
    return R, Cb, (M - R * block) // 2, (N - Cb * block) // 2


def _channel_blocks(images, *, block, mask, saturation, blocks=None):
    """Per-channel block means (K, C, R, Cb) and the blocks usable in every image (R, Cb); ``blocks``: the
    means (K, C, R, Cb) and each image's usable blocks (K, R, Cb) when made already (:func:`_both_grids`),
    else a pass of its own makes them."""
    K, M, N = images.shape[:3]
    C = images.shape[3] if images.ndim == 4 else 1
    R, Cb, r0, c0 = _grid((M, N), block)
    if blocks is not None:
        out, usable = blocks
    else:
        out = np.empty((K, C, R, Cb))
        usable = np.empty((K, R, Cb), bool)

        def one(k):
            st = image_block_stats(images, k, slice(r0, r0 + R * block), slice(c0, c0 + Cb * block), block,
                                   saturation)
            out[k] = np.moveaxis(st.means, -1, 0) if st.means.ndim == 3 else st.means[None]
            usable[k] = ~st.saturated & (st.sample_min > 0)

        # the first image in this thread (numba types the kernel on its first call), the others in
        # default_threads(2) threads: the kernel and the file reads release the GIL; each image's own
        each_image(one, K)
    ok = usable.all(axis=0)
    if mask is not None:
        ok &= mask[r0:r0 + R * block, c0:c0 + Cb * block].reshape(R, block, Cb, block).all(axis=(1, 3))
    rows = r0 + block * np.arange(R) + (block - 1) / 2.0
    cols = c0 + block * np.arange(Cb) + (block - 1) / 2.0
    return out, ok, rows, cols


def _both_grids(images, small: int, large: int, saturation) -> Optional[dict]:
    """:func:`_channel_blocks`' means and usable blocks (``blocks``) of both of :func:`estimate_additive`'s
    block sizes from ONE pass over the stack: each image's statistics on ``b = small // 2`` px blocks, merged
    into both grids. The same values as a pass for each size: a block's sum of integer samples is exact in
    any order (below 2**53), and a fine block's mean times its area, a power of two, gives its sum back
    exactly. None for samples that are not integers or sizes other than ``large = 2 * small = 4 * b``: a pass
    for each size then."""
    K, M, N = images.shape[:3]
    b = small // 2
    dtype = np.dtype(getattr(images, "dtype", np.float64))
    if not (np.issubdtype(dtype, np.integer) and dtype.itemsize <= 4 and large == 2 * small == 4 * b
            and b & (b - 1) == 0):
        return None
    # the centred grids then fall on the fine one: the large grid starts where the small one does or b px
    # further, and ends inside it (every image side up to 5000 px: tests/test_offset.py)
    grids = {blk: _grid((M, N), blk) for blk in (small, large)}
    Rs, Cs, r0, c0 = grids[small]
    C = images.shape[3] if images.ndim == 4 else 1
    out = {blk: (np.empty((K, C, R, Cb)), np.empty((K, R, Cb), bool)) for blk, (R, Cb, _, _) in grids.items()}

    def one(k):
        st = image_block_stats(images, k, slice(r0, r0 + 2 * Rs * b), slice(c0, c0 + 2 * Cs * b), b, saturation)
        sums = (np.moveaxis(st.means, -1, 0) if st.means.ndim == 3 else st.means[None]) * (b * b)
        for blk, (R, Cb, r, c) in grids.items():
            f, i0, j0 = blk // b, (r - r0) // b, (c - c0) // b
            part = (slice(i0, i0 + R * f), slice(j0, j0 + Cb * f))
            means, usable = out[blk]
            means[k] = sums[(slice(None),) + part].reshape(C, R, f, Cb, f).sum(axis=(2, 4)) / (blk * blk)
            lowest = st.sample_min[part].reshape(R, f, Cb, f).min(axis=(1, 3))
            usable[k] = ~st.saturated[part].reshape(R, f, Cb, f).any(axis=(1, 3)) & (lowest > 0)

    each_image(one, K)
    return out


def estimate_additive(images, *, mask=None, saturation=None, degree=0, dropoff_degree=4, block=None,
                      n_iter=8, tiles=4, keep=0.8) -> AdditiveTerm:
    """Measure the additive term (black level + stray light) of a capture from its images.

    Parameters
    ----------
    images : ndarray, (K, M, N) or (K, M, N, C)
        The capture's counts as read (no offset removed).
    mask : ndarray of bool, (M, N), optional
        Pixels that may be used.
    saturation : float, optional
        Blocks holding a sample at or above this are left out.
    degree : int
        Legendre degree of ``c`` across the field: 0 (a constant: the black level) or 1-2 (stray
        light, smooth across the field).
    dropoff_degree : int
        Degree of the smooth part of each log-ratio map that is not evidence (the drop-off's).
    block : int, optional
        Block size in pixels. Default: measured on blocks of 32 px and of 16 (smaller for images under
        ~800 px, so that there are at least 8 blocks per Legendre coefficient), the larger blocks'
        measure reported and the two measures' difference added to its standard error.
    n_iter : int
        Gauss-Newton steps (the problem is nearly linear: 3-4 suffice).
    tiles : int
        The field is cut into ``tiles x tiles`` tiles for the jackknife standard error.

    Returns
    -------
    AdditiveTerm

    Notes
    -----
    Per channel, on block means ``I_k``: minimise over ``c`` the high-pass energy
    ``sum_k |P (log(I_k - c) - mean_j log(I_j - c))|^2`` along the direction the colour areas
    take, where P removes a Legendre polynomial of degree ``dropoff_degree`` per image. The
    Gauss-Newton direction uses ``z_k = (1 / G) (F / F_k - mean_j F / F_j)`` with ``G`` the
    geometric mean over lamps (the albedo) and ``F_k`` the smooth part of the ratio map, rather than
    the per-block ``1 / I_k``: the latter correlates with the texture's own shading and biases ``c``
    by about 0.05 % of the signal. Written here because no library fits an offset by this cue.
    Measured on the synthetic benchmark captures (1600 x 1200, 12 lamps): the true ``c`` within
    0.1 % of the median signal, 0.35 s.
    """
    images = np.asarray(images) if not hasattr(images, "shape") else images
    K, M, N = images.shape[:3]
    if degree not in (0, 1, 2):
        raise UVPSInputError(f"offset degree must be 0, 1 or 2; got {degree!r}")
    if block is not None:
        return _estimate_at(images, block, mask=mask, saturation=saturation, degree=degree,
                            dropoff_degree=dropoff_degree, n_iter=n_iter, tiles=tiles, keep=keep)
    # Two block sizes, the larger one's measure reported: a block's mean holds its texture's shading,
    # which correlates with the paint's brightness under each lamp and biases c; the larger blocks
    # average more of it out, and the two measures' difference is that bias's size, which the
    # jackknife over tiles (the same bias in every tile) does not see. 1600 x 1200 captures with a
    # 100-250 um bow and a black level of 200 (seeds 0-2, RGB): 16 px blocks 183-201 counts (red of
    # seed 1: 183 +- 4.7, 3.6 standard errors off), 32 px 199-200; reported 199.6 +- 17.6 there
    # (tests/test_offset.py).
    small = _default_block(M, N, dropoff_degree)
    large = 2 * small
    if M * N < 8.0 * (dropoff_degree + 1) ** 2 * large * large:
        large, small = small, max(2, small // 2)
    kw = dict(mask=mask, saturation=saturation, degree=degree, dropoff_degree=dropoff_degree, n_iter=n_iter,
              tiles=tiles, keep=keep)
    both = None if small == large else _both_grids(images, small, large, saturation)
    term = _estimate_at(images, large, blocks=both and both[large], **kw)
    if not np.all(np.isfinite(term.stderr)) or small == large:
        return term
    other = _estimate_at(images, small, blocks=both and both[small], **kw)
    if np.all(np.isfinite(other.stderr)):
        spread = np.abs(term.mean - other.mean)
        term.diagnostics["jackknife_stderr_counts"] = [round(float(v), 3) for v in term.stderr]
        term.diagnostics["block_spread_counts"] = [round(float(v), 3) for v in spread]
        term.diagnostics["block_px_compared"] = small
        term.stderr = np.hypot(term.stderr, spread)
        log.info("additive term: %s counts (+- %s with the block sizes' spread)", np.round(term.mean, 1),
                 np.round(term.stderr, 1))
    return term


def _estimate_at(images, block, *, mask, saturation, degree, dropoff_degree, n_iter, tiles, keep,
                 blocks=None) -> AdditiveTerm:
    """:func:`estimate_additive` on blocks of ``block`` px: the measure and its jackknife standard error."""
    K, M, N = images.shape[:3]
    blk, ok, rows, cols = _channel_blocks(images, block=block, mask=mask, saturation=saturation, blocks=blocks)
    C = blk.shape[1]
    n_ok = int(ok.sum())
    if n_ok < 4 * (dropoff_degree + 1) ** 2:
        # too few blocks lit and unsaturated in every image (deep shadows, highlights): not measurable,
        # which is no reason to stop a run (known lights do not need it); the run says so
        return _not_measured(C, degree, (M, N), float("nan"), n_ok, block,
                             f"not measurable: only {n_ok} blocks lit and unsaturated in every image")
    bases = _block_bases(rows, cols, ok, (M, N), degree=degree, dropoff_degree=dropoff_degree, tiles=tiles)
    coeffs = np.zeros((C, degree + 1, degree + 1))
    stderr = np.zeros(C)
    medians = []
    for ch in range(C):
        I = blk[:, ch].reshape(K, -1)[:, ok.ravel()]
        fit = _fit_channel(I, bases, n_iter=n_iter, keep=keep)
        if fit is None or isinstance(fit, str):
            # the images do not differ between lamps (no drop-off), or nothing else pins c
            return _not_measured(C, degree, (M, N), float(np.median(I)), n_ok, block,
                                 fit or "not measurable: the images do not differ between lamps")
        theta, A, Pr = fit
        coeffs[ch] = theta.reshape(degree + 1, degree + 1)
        stderr[ch] = _jackknife_stderr(A, Pr, bases.tile_id, tiles)
        medians.append(float(np.median(I - (bases.Phi @ theta)[None])))
    med = float(np.mean(medians))
    term = AdditiveTerm(coeffs, "estimated", (M, N), stderr, med, {"blocks": n_ok, "block_px": block})
    log.info("additive term: %s counts (+- %s), %.3f %% of the median signal", np.round(term.mean, 1),
             np.round(stderr, 1), 100 * term.mean.mean() / med)
    return term


def _default_block(M, N, dropoff_degree) -> int:
    """16 px, smaller for images under ~400 px: at least 8 blocks per Legendre coefficient."""
    return int(max(2, min(16, np.sqrt(M * N / (8.0 * (dropoff_degree + 1) ** 2)))))


def _not_measured(C, degree, shape, median_signal, n_blocks, block, note) -> AdditiveTerm:
    """A zero term with a note saying why it could not be measured (no reason to stop a run)."""
    return AdditiveTerm(np.zeros((C, degree + 1, degree + 1)), "estimated", shape, np.full(C, np.nan),
                        median_signal, {"blocks": n_blocks, "block_px": block, "note": note})


class _BlockBases(NamedTuple):
    """Bases on the usable blocks (P of them): the drop-off's and ``c``'s, and the jackknife tiles."""

    Q: np.ndarray  # (P, (dropoff_degree + 1)^2) orthonormal basis of the smooth part of a ratio map
    Phi: np.ndarray  # (P, (degree + 1)^2) Legendre basis of c
    tile_id: np.ndarray  # (P,) tile of each block, 0 .. tiles^2 - 1


def _block_bases(rows, cols, ok, shape, *, degree, dropoff_degree, tiles) -> _BlockBases:
    """:class:`_BlockBases` on the usable blocks ``ok`` of the grid ``rows`` x ``cols`` (block centres)."""
    M, N = shape
    Vv = Lg.legvander(_unit(rows, M), dropoff_degree)
    Vu = Lg.legvander(_unit(cols, N), dropoff_degree)
    B = np.einsum("ri,cj->rcij", Vv, Vu).reshape(len(rows) * len(cols), -1)[ok.ravel()]
    Q, _ = np.linalg.qr(B)
    Wv = Lg.legvander(_unit(rows, M), degree)
    Wu = Lg.legvander(_unit(cols, N), degree)
    Phi = np.einsum("ri,cj->rcij", Wv, Wu).reshape(len(rows) * len(cols), -1)[ok.ravel()]  # (P, n_c)
    rr, cc = np.nonzero(ok)
    tile_id = (rr * tiles // ok.shape[0]) * tiles + (cc * tiles // ok.shape[1])
    return _BlockBases(Q, Phi, tile_id)


def _high_pass(X, Q):
    """What the drop-off basis ``Q`` does not fit, per row of ``X``."""
    return X - (X @ Q) @ Q.T


def _ratio_system(J, pos, bases: _BlockBases):
    """High-passed log-ratio maps ``Pr`` (K, P) and their derivative ``A`` (K, P, n_c) along c's basis.

    ``J`` are the block means less the current ``c``; blocks not above 0 in every image (``~pos``)
    carry no ratio.
    """
    Lj = np.log(np.where(pos[None], J, 1.0))
    r = Lj - Lj.mean(axis=0)
    Pr = _high_pass(r, bases.Q)
    smooth = r - Pr
    h = np.exp(-smooth)
    h -= h.mean(axis=0)
    z = np.exp(-Lj.mean(axis=0))[None] * h                     # d r / d c, up to sign (K, P)
    Phi = bases.Phi
    A = np.stack([_high_pass(z * Phi[:, j][None], bases.Q) for j in range(Phi.shape[1])], axis=-1)  # (K, P, n_c)
    return Pr, A


def _fit_channel(I, bases: _BlockBases, *, n_iter, keep):
    """Gauss-Newton fit of ``c``'s coefficients to one channel's block means ``I`` (K, P).

    Returns ``(theta, A, Pr)``, the coefficients and the last weighted system (for the jackknife),
    None when the images do not differ between lamps, or a note when the fit runs away (nothing in
    the images pins ``c``).
    """
    theta = np.zeros(bases.Phi.shape[1])
    for it in range(n_iter):
        c = bases.Phi @ theta
        J = I - c[None]
        pos = np.all(J > 0, axis=0)
        if pos.mean() < 0.5 and it == 0:
            raise UVPSInputError(
                "the additive term (black level, stray light) cannot be measured: most of the paint is at "
                "the pedestal in some image; give the black level (black_level) or a dark frame (dark)")
        if pos.mean() < 0.5:
            # the fit ran away above the images: nothing in them pins c (one paint: no colour
            # areas to cancel); not measurable, which is no reason to stop a run
            return "not measurable: the field holds too few paints of different brightness"
        # blocks at the pedestal under some lamp (a narrow beam's dark side) carry no ratio: left out
        w = pos.astype(float)
        Pr, A = _ratio_system(J, pos, bases)
        if it >= 1 and keep < 1:
            # blocks whose log ratios vary most are shaded relief (protrusions, ridges): their
            # shading differs between lamps in a way that correlates with brightness; leave them out
            e = np.sum(Pr ** 2, axis=0)
            w *= e <= np.quantile(e[pos], keep)
        A *= np.sqrt(w)[None, :, None]
        Pr = Pr * np.sqrt(w)[None]
        # r(c + d) ~ r - z d: solve the normal equations for d
        AtA = np.einsum("kpi,kpj->ij", A, A)
        Atr = np.einsum("kpi,kp->i", A, Pr)
        if not np.all(np.isfinite(AtA)) or np.linalg.cond(AtA) > 1e12 or AtA[0, 0] <= 0:
            return None
        d = np.linalg.solve(AtA, Atr)
        theta = theta + d
        if it >= 2 and np.max(np.abs(d)) < 1e-4 * max(float(np.median(I)), 1.0):
            break
    return theta, A, Pr


def _jackknife_stderr(A, Pr, tile_id, tiles) -> float:
    """Standard error of the mean of ``c`` by a jackknife over tiles, linearised at the solution."""
    num_t = np.array([np.einsum("kpi,kp->i", A[:, tile_id == t], Pr[:, tile_id == t])
                      for t in range(tiles * tiles)])
    den_t = np.array([np.einsum("kpi,kpj->ij", A[:, tile_id == t], A[:, tile_id == t])
                      for t in range(tiles * tiles)])
    used = [t for t in range(tiles * tiles) if np.any(tile_id == t)]
    loo = []
    for t in used:
        try:
            loo.append(np.linalg.solve(den_t.sum(0) - den_t[t], num_t.sum(0) - num_t[t])[0])
        except np.linalg.LinAlgError:
            continue
    g = len(loo)
    return float(np.sqrt((g - 1) / g * np.sum((np.asarray(loo) - np.mean(loo)) ** 2))) if g > 2 else np.nan
