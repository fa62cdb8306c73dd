"""Surface: the height's noise, its weave removed (:mod:`.weave`), its compact relief and the
disc top-hat (module docstring of :mod:`uvps.core.detect`, steps 1-2)."""
from __future__ import annotations

import logging
import math
from dataclasses import dataclass

import cv2
import numpy as np
from skimage.morphology import max_tree

from ..threads import concurrently
from ._common import MIN_SMOOTH_PX, Thresholds
from ._kernels import _diameter_filter, _flood_beside
from .params import DetectionParams
from .weave import WeaveEstimate, _remove_weave

logger = logging.getLogger(__name__)


#: The compact relief's length ``L = 1.3 x max_width_um`` (+ 2 px): a level set of the height is
#: surface when it reaches ``L``. Above ``max_width_um`` so that the widest protrusion sought,
#: its foot blurred by the smoothing and enlarged by the block maxima (a block each side), still
#: stays compact; a stroke, a crack lip or the bow runs on far beyond it.
COMPACT_LENGTH_FACTOR = 1.3
COMPACT_LENGTH_PAD_PX = 2


@dataclass
class Surface:
    """The height prepared for the cues (see :func:`_surface`)."""

    raw: np.ndarray             # the height with invalid pixels filled (um)
    height: np.ndarray          # smoothed, weave removed, invalid pixels filled (um)
    relief: np.ndarray          # compact relief t >= 0 (um)
    disc: np.ndarray            # height over its opening by a disc L wide (um)
    noise_um: float
    noise_smoothed_um: float
    weave: WeaveEstimate
    length_px: float


def _noise_sigma(h: np.ndarray, valid: np.ndarray) -> float:
    """Robust white-noise sigma of the height: MAD of its high-pass (second differences).

    A second difference cancels planes and slopes; for white noise its variance is 6 sigma^2.
    """
    if valid.all():     # both written into one array: the same operations, no temporaries
        shapes = (h[:, 2:].shape, h[2:].shape)
        d = np.empty(sum(math.prod(s) for s in shapes), np.result_type(h, 2))
        cut = math.prod(shapes[0])
        for diff, (a, b, c) in ((d[:cut].reshape(shapes[0]), (h[:, 2:], h[:, 1:-1], h[:, :-2])),
                                (d[cut:].reshape(shapes[1]), (h[2:], h[1:-1], h[:-2]))):
            np.multiply(b, 2, out=diff)
            np.subtract(a, diff, out=diff)
            np.add(diff, c, out=diff)
    else:
        # one difference map at a time (each dropped once its valid pixels are taken): this runs beside
        # the weave and the albedo cue, at the run's peak of memory
        across = h[:, 2:] - 2 * h[:, 1:-1] + h[:, :-2]
        across = across[valid[:, 2:] & valid[:, 1:-1] & valid[:, :-2]]
        along = h[2:] - 2 * h[1:-1] + h[:-2]
        along = along[valid[2:] & valid[1:-1] & valid[:-2]]
        d = np.concatenate([across, along])
        del across, along
    if d.size == 0:
        return 0.0
    # d is ours: both medians partition it in place (the same multiset, the same medians)
    mad = np.median(np.abs(np.subtract(d, np.median(d, overwrite_input=True), out=d), out=d), overwrite_input=True)
    return float(1.4826 * mad / math.sqrt(6.0))


def _block_max(img: np.ndarray, f: int) -> np.ndarray:
    """Maximum over f x f blocks (edge-padded to whole blocks)."""
    m, n = img.shape
    mb, nb = -(-m // f), -(-n // f)
    pad = np.pad(img, ((0, mb * f - m), (0, nb * f - n)), mode="edge")
    return pad.reshape(mb, f, nb, f).max(axis=(1, 3))


def _diameter_opening(image: np.ndarray, threshold: int) -> np.ndarray:
    """:func:`skimage.morphology.diameter_opening` (4-connected), the same values.

    Hand-written after the max-tree (which skimage builds): skimage's extension pass took 80 %
    of the opening's time (30 of 37 s on a 636 x 836 block image under load; this one 1 s), so
    the bounding boxes are gathered here in one compiled pass up the tree. Tested against
    skimage's in ``tests/test_detect.py``."""
    img = np.ascontiguousarray(image)
    parent, order = max_tree(img, connectivity=1)
    return _diameter_filter(img.ravel(), parent.ravel(), order, img.shape[1],
                            int(threshold)).reshape(img.shape)


def _block_factor(length_px: float) -> int:
    """The side ``f`` of the blocks :func:`_compact_relief` opens: ``length_px / f`` is 16-32 px
    (``f`` = 1 below 32 px)."""
    return max(1, int(length_px // 16))


def _compact_relief(hn: np.ndarray, valid: np.ndarray, length_px: float) -> np.ndarray:
    """Relief enclosed within ``length_px``: ``hn - min(hn, A)``, A the diameter opening.

    The diameter opening keeps every connected level set whose bounding box reaches
    ``length_px`` (Breen and Jones 1996, via :func:`skimage.morphology.diameter_opening`), so what
    remains above it is compact: protrusions, not strokes, lips or bow. It runs on f x f block
    maxima (f so that ``length_px / f`` is ~16 px; cost ~0.5 s for 1600 x 1200 pixels), mirrored
    by ``length_px`` at the borders (a stroke leaving the image stays long), and repeated back to
    full size: a block maximum is never below the pixels it covers, so long structures stay in
    ``A`` to the pixel and only compact ones lose it. (Closing cracks first, so that a crack does
    not cut a lip or a stroke into compact pieces, also joins crowded protrusions into long
    chains; the ``crack`` rule deals with such pieces instead.)
    """
    f = _block_factor(length_px)
    m, n = hn.shape
    pad = int(math.ceil(length_px / f))
    coarse = cv2.copyMakeBorder(_block_max(hn, f), pad, pad, pad, pad, cv2.BORDER_REFLECT)
    opened = _diameter_opening(coarse, pad)[pad:-pad, pad:-pad]
    up = np.repeat(np.repeat(opened, f, axis=0), f, axis=1)[:m, :n]
    t = (hn - np.minimum(hn, up)).astype(np.float32, copy=False)   # no second copy of a float32 difference
    t[~valid] = 0
    return t


def _disc_tophat(hn: np.ndarray, length_px: float) -> np.ndarray:
    """``hn`` minus its grey opening by a disc ``length_px`` wide (on an area-averaged copy, so
    that the disc is ~25 px; the opening brought back to full size and capped by ``hn``): the
    height over the paint's lowest envelope, for everything narrower than the disc (um)."""
    m, n = hn.shape
    f = max(1, int(length_px // 25))
    small = hn
    if f > 1:
        small = cv2.resize(hn, (max(n // f, 1), max(m // f, 1)), interpolation=cv2.INTER_AREA)
    d = max(3, int(round(length_px / f)) | 1)
    se = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (d, d))
    opened = cv2.morphologyEx(small, cv2.MORPH_OPEN, se, borderType=cv2.BORDER_REFLECT)
    if f > 1:
        opened = np.minimum(cv2.resize(opened, (n, m), interpolation=cv2.INTER_LINEAR), hn)
    return (hn - opened).astype(np.float32, copy=False)


def _beside_long(surf: Surface, valid: np.ndarray, th: Thresholds, p: DetectionParams) -> np.ndarray:
    """The compact relief with the small objects the block maxima joined to a long neighbour.

    :func:`_compact_relief` opens ``f x f`` block maxima (``f = L / 16``, 5 px at 15 um per
    pixel), so a protrusion in the block next to a stroke's or a crack lip's is joined to it and
    its level sets are taken as long: it gets no relief (a 90 um mesa 22 um high, 3 px from a
    stroke, gets 0.7 um). Here the exact level sets decide, around the objects the blocks can
    hide: the local maxima of the height (over 3 x 3 px: a dome within 2 px of a taller
    neighbour's flank is one, not over 5 x 5) with no compact relief (below the
    relief threshold) that stand ``need`` above the paint's lowest envelope (the disc top-hat,
    :func:`_disc_tophat`), ``need`` being ``beside_long_fraction`` of that height and at least
    twice the relief threshold. A priority flood from each (:func:`_flood_beside`) falls through
    the level sets containing it until they reach ``L``; a seed whose own hill stands ``need``
    above that level, and which the blocks gave no relief, gets its exact compact relief there.
    A bump on a stroke already has its relief from the blocks and is left alone; a stroke's
    crest or the paint's texture widens past ``3 f + 2`` px before it has fallen ``need``, which
    bounds the cost (0.17 s at 4000 x 3000 with 5 x 5 seeds at 0.3). A hill that reaches the
    image's edge is left as it was: cut by the edge, a ripple crest of a stroke that leaves the
    image is as compact as a protrusion (the edge of ``valid`` inside the image is not an edge).
    Hand-written: the exact diameter opening of a whole 1600 x 1200 image
    (:func:`skimage.morphology.max_tree`) takes 5 s, and no library floods from chosen seeds
    only. ``beside_long_fraction`` 0 leaves the compact relief as it is, as does ``f`` = 1 (the
    blocks are then the pixels: the relief is exact already)."""
    t = surf.relief
    f = _block_factor(surf.length_px)
    if p.beside_long_fraction <= 0 or f == 1:
        return t
    hn = np.ascontiguousarray(surf.height, dtype=np.float32)
    peak = hn >= cv2.dilate(hn, np.ones((3, 3), np.uint8), borderType=cv2.BORDER_REPLICATE)
    need_all = np.maximum(2.0 * th.relief_um, p.beside_long_fraction * surf.disc)
    seeds = np.flatnonzero(peak & valid & (t < th.relief_um) & (surf.disc >= need_all))
    if not seeds.size:
        return t
    seeds = seeds[np.argsort(-hn.ravel()[seeds], kind="stable")]
    out = t.copy()
    max_area = int(math.pi / 4 * th.max_w ** 2)
    n = _flood_beside(hn, t, seeds.astype(np.int64), need_all.ravel()[seeds].astype(np.float32),
                      int(math.ceil(surf.length_px)), 3 * f + 2, max_area, float(th.relief_um), out)
    out[~valid] = 0
    logger.debug("beside_long: %d of %d seeds raised", n, seeds.size)
    return out


def _surface(h: np.ndarray, valid: np.ndarray, px: float, p: DetectionParams) -> Surface:
    """Noise, weave and compact relief of the height (see the module docstring, steps 1-2)."""
    fill = float(np.median(h[valid])) if not valid.all() else 0.0    # no pixel to fill: 0.3 s
    h0 = np.where(valid, h, fill).astype(np.float32, copy=False)
    s = p.smooth_um / px

    def smoothed():
        hs = cv2.GaussianBlur(h0, (0, 0), s, borderType=cv2.BORDER_REFLECT) if s >= MIN_SMOOTH_PX else h0
        return _remove_weave(hs, px, p)

    # the noise (two medians) beside the smoothing and the weave; the relief beside the top-hat
    (hn, weave), noise = concurrently(smoothed, lambda: _noise_sigma(h0, valid))
    noise_s = noise
    if s >= MIN_SMOOTH_PX:
        k1 = cv2.getGaussianKernel(2 * int(math.ceil(4 * s)) + 1, s)
        noise_s = noise * float(np.sum(k1 ** 2))  # white noise through the separable kernel
    length = COMPACT_LENGTH_FACTOR * p.max_width_um / px + COMPACT_LENGTH_PAD_PX
    relief, disc = concurrently(lambda: _compact_relief(hn, valid, length), lambda: _disc_tophat(hn, length))
    return Surface(raw=h0, height=hn, relief=relief, disc=disc, noise_um=noise, noise_smoothed_um=noise_s,
                   weave=weave, length_px=length)


def _thresholds(surf: Surface, px: float, p: DetectionParams) -> Thresholds:
    relief = max(p.min_dynamic_um, p.dynamic_k * surf.noise_smoothed_um)
    slope = max(2 * p.min_relief_ratio, p.weave_slope_k * surf.weave.slope_rms)
    return Thresholds(relief, slope, p.min_width_um / px, p.max_width_um / px)


def _widths(px: float, p: DetectionParams) -> Thresholds:
    """:func:`_thresholds`' widths (px), known before the surface: its relief and slope NaN
    (what reads only the widths, the albedo cue, runs beside :func:`_surface`)."""
    return Thresholds(math.nan, math.nan, p.min_width_um / px, p.max_width_um / px)
