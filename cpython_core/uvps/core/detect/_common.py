"""Small measurements shared by the detector's stages: per-label maxima and means, distances,
label growth, holes, the thresholds' record and the long-structure test."""
from __future__ import annotations

import math
from typing import NamedTuple

import cv2
import numpy as np
from scipy import ndimage as ndi
from skimage.morphology import h_maxima
from skimage.segmentation import expand_labels


#: Below this Gaussian sigma (px) the height and the brightness are not smoothed: the kernel
#: would be nearly a single tap (at 7.5 um, above 25 um per pixel).
MIN_SMOOTH_PX = 0.3
#: An object stands on a long structure when the disc top-hat exceeds the compact relief under
#: it by the relief threshold and this share of its own relief (:func:`_on_long_structure`): a
#: protrusion's own foot lifts the disc top-hat a little above its compact relief, a stroke
#: under a bump lifts it by a good part of the bump's height.
LONG_UNDER_SHARE = 0.25


class Thresholds(NamedTuple):
    relief_um: float            # least relief of a protrusion (and of a peak over a saddle)
    slope_min: float            # least flank slope relief / (width / 2)
    min_w: float                # px
    max_w: float                # px


def _label_max(values: np.ndarray, labels: np.ndarray, n: int) -> np.ndarray:
    """Maximum of ``values`` per label 1..n (-inf for an empty label), via ``np.maximum.at``.

    ``scipy.ndimage.maximum`` with an index sorts every labelled pixel; this is O(pixels).
    """
    out = np.full(n + 1, -np.inf)
    sel = labels > 0
    np.maximum.at(out, labels[sel], values[sel])
    return out[1:]


def _label_mean(values: np.ndarray, labels: np.ndarray, n: int, default: float = 0.0) -> np.ndarray:
    """Mean of ``values`` per label 1..n (``default`` for an empty label), via ``np.bincount``."""
    sel = labels > 0
    cnt = np.bincount(labels[sel], minlength=n + 1)[1:n + 1]
    tot = np.bincount(labels[sel], weights=values[sel].astype(np.float64, copy=False), minlength=n + 1)[1:n + 1]
    return np.where(cnt > 0, tot / np.maximum(cnt, 1), default)


def _median(x: np.ndarray) -> float:
    """``np.median`` of a 1-D array by ``np.partition`` (the same value, without ``np.median``'s
    per-call overhead: the numpy plane fit calls it ~10 times per footprint)."""
    n = x.size
    part = np.partition(x, [(n - 1) // 2, n // 2])
    return 0.5 * (part[(n - 1) // 2] + part[n // 2])


def _edt(mask: np.ndarray) -> np.ndarray:
    """Euclidean distance of each True pixel to the nearest False one (float32): OpenCV's exact
    transform (``DIST_MASK_PRECISE``), the values of ``scipy.ndimage.distance_transform_edt``
    at a fraction of its cost; scipy's when there is no False pixel."""
    if mask.all():
        return ndi.distance_transform_edt(mask).astype(np.float32)
    return cv2.distanceTransform(mask.astype(np.uint8), cv2.DIST_L2, cv2.DIST_MASK_PRECISE)


def _expand_labels(lab: np.ndarray, distance: float) -> np.ndarray:
    """:func:`skimage.segmentation.expand_labels` (the same values) computed per group of labels
    in its own crop instead of one feature transform over the whole image.

    A pixel within ``distance`` of a label has all its labels within ``distance`` in the same
    group (labels whose ``distance``-neighbourhoods can touch: the components of the labels
    dilated by a square of side ``2 ceil(distance) + 1``), so each group's crop holds every
    label that can reach its pixels. At 4000 x 3000 with a few thousand small candidates the
    crops cover a tenth of the image (``scripts/benchmark_detection_speed.py --profile 40``:
    1.5 s per call over the whole image). Tested against skimage's in ``tests/test_detect.py``."""
    r = int(math.ceil(distance))
    if r < 1 or not lab.any():
        return lab.copy()
    side = 2 * r + 1
    reach = cv2.dilate((lab > 0).astype(np.uint8), np.ones((side, side), np.uint8),
                       borderType=cv2.BORDER_CONSTANT, borderValue=0)
    grp, _ = ndi.label(reach, structure=np.ones((3, 3)))
    out = np.zeros_like(lab)
    for g, sl in enumerate(ndi.find_objects(grp)):
        own = grp[sl] == g + 1
        out[sl][own] = expand_labels(np.where(own, lab[sl], 0), distance=distance)[own]
    return out


#: The steps to a pixel's right and lower neighbours (4-connected), and its two lower diagonal
#: ones as well (8-connected): each pair of neighbours once.
STEPS_4 = ((0, 1), (1, 0))
STEPS_8 = ((0, 1), (1, 0), (1, 1), (1, -1))


def _touching(lab: np.ndarray, steps=STEPS_8) -> tuple:
    """The pairs of neighbouring pixels (one ``steps`` apart) both labelled with different labels:
    (flat index of the first, flat index of the second), each pair of pixels once. The pairs of
    ``lab[:, :-1]`` against ``lab[:, 1:]`` and the like, found from the labelled pixels alone
    (a few % of a 4000 x 3000 image: the shifted comparisons scan it four times per step)."""
    m, n = lab.shape
    flat = lab.ravel()
    idx = np.flatnonzero(flat)
    row, col = np.divmod(idx, n)
    first, second = [], []
    for dr, dc in steps:
        i = idx[(row + dr < m) & (col + dc >= 0) & (col + dc < n)]
        j = i + (dr * n + dc)
        b = flat[j]
        sel = (b > 0) & (b != flat[i])
        first.append(i[sel])
        second.append(j[sel])
    return np.concatenate(first), np.concatenate(second)


def _shelves(sizes: list) -> tuple:
    """Places (row, column) for boxes of ``sizes`` (rows, columns) on shelves, tallest first,
    1 px apart, in an image about as wide as it is tall; returns (places, image shape)."""
    width = max(int(math.sqrt(sum((h + 1) * (w + 1) for h, w in sizes))) + 1,
                max(w for _, w in sizes) + 1)
    place = [None] * len(sizes)
    r = c = shelf = 0
    for k in sorted(range(len(sizes)), key=lambda k: -sizes[k][0]):
        h, w = sizes[k]
        if c + w > width:
            r, c, shelf = r + shelf + 1, 0, 0
        place[k] = (r, c)
        c, shelf = c + w + 1, max(shelf, h)
    return place, (r + shelf, width)


def _packed_h_maxima(images: list, owns: list, background: float, dyns: tuple) -> list:
    """``[[h_maxima(image, dyn) for dyn in dyns] for image in images]`` (``image`` float64, its
    pixels outside ``own`` all ``background``), from one call per ``dyn`` on the images packed
    side by side 1 px apart (:func:`_shelves`) on a ``background`` canvas; None in place of an
    image's list when its result could differ from its own call, which then has to be made.

    The h-maxima are ``image - R >= dyn``, R the reconstruction by dilation of ``image - dyn``
    (less skimage's rounding margin) under ``image``: the largest, over paths from any pixel,
    of the seed there and the image along the way; exact, whatever else the canvas holds, at an
    image's own pixels when every own pixel is at least ``background`` and the highest seed of
    its own pixels is too (a path through the background brings at most ``background``, which
    a path from the image's own top already gives), and when its own call would not return
    early on ``dyn`` above its range (it has a background pixel, and ``dyn`` is within its
    range). On a 4000 x 3000 run (``uvps run --regions auto``, 16 lamps; line_profiler) the raised
    areas' crops were ~800, each call ~0.1 ms of skimage's set-up for a few hundred pixels.
    Hand-written packing around skimage's h_maxima (no library runs it on a set of crops at once)."""
    out = [None] * len(images)
    ok = [k for k, (im, own) in enumerate(zip(images, owns)) if not own.all()]
    vals = [images[k][owns[k]] for k in ok]
    for dyn in dyns:                            # skimage's seed: image - h - resolution
        ok = [k for k, v in zip(ok, vals) if v.min() >= background
              and (v - dyn - 2 * np.finfo(np.float64).resolution * np.abs(v)).max() >= background
              and not dyn > v.max() - background]
        vals = [images[k][owns[k]] for k in ok]
    if not ok:
        return out
    place, shape = _shelves([images[k].shape for k in ok])
    canvas = np.full(shape, background, np.float64)
    spots = []
    for k, (r, c) in zip(ok, place):
        dst = (slice(r, r + images[k].shape[0]), slice(c, c + images[k].shape[1]))
        canvas[dst] = images[k]
        spots.append(dst)
    maxima = [h_maxima(canvas, dyn) for dyn in dyns]
    for k, dst in zip(ok, spots):
        out[k] = [m[dst] for m in maxima]
    return out


def _kept_components(comp: np.ndarray, keep: np.ndarray) -> tuple:
    """The components of ``comp`` (a ``scipy.ndimage.label`` image: numbered in raster order of
    their first pixel) whose ``keep`` (per id 0..n; 0 ignored) is True, labelled again: what
    ``ndi.label(keep[comp] & (comp > 0))`` with ``comp``'s structure numbers them (whole
    components, in the same order: 1..k by id), from a lookup at the labelled pixels instead of a
    second labelling of the whole image. Returns (flat indices of their pixels, their new ids, k)."""
    lut = np.zeros(keep.size, np.int32)
    kept = keep.copy()
    kept[0] = False
    k = int(np.count_nonzero(kept))
    lut[kept] = np.arange(1, k + 1, dtype=np.int32)
    at = np.flatnonzero(comp)
    new = lut[comp.ravel()[at]]
    return at[new > 0], new[new > 0], k


def _holes(mask: np.ndarray) -> tuple:
    """The holes of ``mask`` labelled 1..k, as ``ndimage.label(fill_holes(mask) & ~mask)``
    (4-connected, numbered in raster order of their first pixel): the background's components
    that do not reach the border, renumbered, from one labelling of the background."""
    bg, n_bg = ndi.label(~mask)
    inner = np.ones(n_bg + 1, bool)
    inner[np.concatenate([bg[0], bg[-1], bg[:, 0], bg[:, -1]])] = False
    inner[0] = False
    lut = np.zeros(n_bg + 1, np.int32)
    lut[inner] = np.arange(1, int(inner.sum()) + 1, dtype=np.int32)
    # renumbered in place, a band of rows at a time: no second full-size label image beside the
    # candidates' reliefs at the detection's peak of memory (lut[bg] makes one; np.take(..., out=bg)
    # makes a full-size int64 index copy first, twice that: tracemalloc on 3000 x 4000, 98 / 143 MiB
    # against 73 MiB in bands)
    if bg.dtype != lut.dtype:
        return lut[bg], int(inner.sum())
    for r0 in range(0, bg.shape[0], 256):
        bg[r0:r0 + 256] = lut[bg[r0:r0 + 256]]
    return bg, int(inner.sum())


def _on_long_structure(under: np.ndarray, relief: np.ndarray, th: Thresholds) -> np.ndarray:
    """Whether an object of ``relief`` stands on a long structure: the disc top-hat exceeds the
    compact relief under it (``under``, its mean) by the relief threshold and a quarter of its
    relief (the larger of the two)."""
    return under >= np.maximum(th.relief_um, LONG_UNDER_SHARE * relief)
