"""Height cue: the compact relief's peaks, the weak splits and the shoulders, and their
compact footprints (module docstring of :mod:`uvps.core.detect`, step 3)."""
from __future__ import annotations

import math

import cv2
import numpy as np
from scipy import ndimage as ndi
from skimage.morphology import h_maxima, reconstruction
from skimage.segmentation import watershed

from ..threads import concurrently
from ._common import (Thresholds, _edt, _label_max, _label_mean, _on_long_structure, _packed_h_maxima,
                      _shelves, _touching)
from .params import DetectionParams


def _peak_markers(t: np.ndarray, th: Thresholds, p: DetectionParams) -> tuple:
    """Peaks of the compact relief: at least ``relief_um`` high, and ``split_fraction`` above
    the saddle to any higher peak (``h_maxima`` of ``log(t + relief_um)``: a relative dynamic,
    so a crater's rim or a mesa's rippled top stays one peak and touching protrusions split).
    Per raised area (a path to a higher peak over a saddle above half the threshold stays
    inside it), which is much cheaper than the full-image reconstruction. With
    ``weak_split_fraction`` below ``split_fraction``, the peaks whose dynamic lies between the
    two are returned too, flagged weak (:func:`_weak_splits` decides on them).
    Returns (markers, n, weak: per id 1..n whether the peak is weak, index 0 unused)."""
    m, n = t.shape
    low = t >= 0.5 * th.relief_um
    comp, ncomp = ndi.label(low, structure=np.ones((3, 3)))
    markers = np.zeros((m, n), np.int32)
    weak = [False]
    if not ncomp:
        return markers, 0, np.asarray(weak)
    top = _label_max(t, comp, ncomp)
    dyn = -math.log(1.0 - p.split_fraction)
    use_weak = 0 < p.weak_split_fraction < p.split_fraction
    dyn_w = -math.log(1.0 - p.weak_split_fraction) if use_weak else 0.0
    k_all = 0
    slices = ndi.find_objects(comp)
    todo = np.flatnonzero(top >= th.relief_um)
    owns = [comp[slices[k]] == k + 1 for k in todo]
    subs = [np.where(own, np.log(t[slices[k]].astype(np.float64) + th.relief_um), -1.0)
            for k, own in zip(todo, owns)]
    packed = _packed_h_maxima(subs, owns, -1.0, (dyn, dyn_w) if dyn_w else (dyn,))
    for j, (k_comp, inside, sub) in enumerate(zip(todo, owns, subs)):
        sl = slices[k_comp]
        hm = (packed[j][0] if packed[j] else h_maxima(sub, dyn)).astype(bool) & inside & (t[sl] >= th.relief_um)
        lab, k = ndi.label(hm, structure=np.ones((3, 3)))
        n_w = 0
        if dyn_w:                                   # the weak peaks: numbered after the strong
            hw = (packed[j][1] if packed[j] else h_maxima(sub, dyn_w)).astype(bool) & inside & (t[sl] >= th.relief_um)
            lw, kw = ndi.label(hw, structure=np.ones((3, 3)))
            strong = np.zeros(kw + 1, bool)
            strong[lw[hm]] = True                   # the strong peaks' own components
            strong[0] = True
            n_w = kw + 1 - int(np.count_nonzero(strong))
            lut = np.zeros(kw + 1, np.int32)
            lut[~strong] = np.arange(k + 1, k + 1 + n_w)
            lab = np.where(strong[lw], lab, lut[lw])
        weak.extend([False] * k + [True] * n_w)
        k += n_w
        if k:
            markers[sl][lab > 0] = lab[lab > 0] + k_all
            k_all += k
    return markers, k_all, np.asarray(weak)


def _touching_pairs(t: np.ndarray, ws: np.ndarray) -> tuple:
    """The pairs of basins of ``ws`` side by side (8-connected), each once (a < b), and the
    height of the pass between them: the highest, over the pixel pairs across their border, of
    the lower of the two. Returns (pairs (k, 2) int, passes (k,) float)."""
    n = int(ws.max())
    i, j = _touching(ws)
    a, b = ws.ravel()[i], ws.ravel()[j]
    keys = np.minimum(a, b).astype(np.int64) * (n + 1) + np.maximum(a, b)
    if not keys.size:
        return np.zeros((0, 2), np.int64), np.zeros(0)
    uniq, inv = np.unique(keys, return_inverse=True)
    passes = np.full(uniq.size, -np.inf)
    np.maximum.at(passes, inv, np.minimum(t.ravel()[i], t.ravel()[j]).astype(np.float64))
    return np.column_stack([uniq // (n + 1), uniq % (n + 1)]), passes


def _filled(t: np.ndarray, drain: np.ndarray) -> np.ndarray:
    """The level water poured on ``t`` stands at: the grey-level fill of holes
    (``skimage.morphology.reconstruction`` by erosion from the border) of ``t`` with the pixels
    of ``drain`` lowered below all of it (water runs off through them, and over the border)."""
    mask = np.where(drain, float(t.min()) - 1.0, t.astype(np.float64))
    fixed = drain.copy()
    fixed[[0, -1], :] = True
    fixed[:, [0, -1]] = True
    return reconstruction(np.where(fixed, mask, mask.max()), mask, method="erosion")


def _rim_merges(t: np.ndarray, ws: np.ndarray, th: Thresholds, p: DetectionParams) -> np.ndarray:
    """Basins of ``ws`` that are the two ends of one crater's rim, joined: per id 0..n of ``ws``
    the id of the group it belongs to (1..k, 0 kept for the background).

    A small elliptical crater's rim stands higher at the ends of its major axis than on its
    flanks (by ~16 % once integrated at 15 um per pixel), so ``split_fraction`` finds two peaks
    and the watershed cuts through the pit. Two touching basins are one crater's rim when their
    peaks are of a height (the lower at least :data:`WEAK_HOST_RATIO` of the higher: a rim's two
    ends are; a small cluster member whose foot closes a hollow against a taller one's flank is
    not) and together they enclose a pit that neither encloses alone: water poured on the two
    basins and the background, running off through every other basin and over the border,
    stands in it above the level it stands at with either basin alone by the larger of the
    relief threshold and ``split_fraction`` of its own level (the pit lies ``split_fraction``
    below the rim's lowest pass, as a peak stands above its saddle). Two touching domes, or two
    protrusions side by side, enclose nothing (the hollow between them opens outward), a ring of
    three domes encloses its hollow only with the third, and a crater beside a dome encloses its
    pit alone. Hand-written: the fill of holes is skimage's; pairing basins by a pit only the
    two enclose is in no library."""
    n = int(ws.max())
    group = np.arange(n + 1)
    pairs, _ = _touching_pairs(t, ws)
    boxes = ndi.find_objects(ws, max_label=n)

    def root(i):
        while group[i] != i:
            i = group[i]
        return i

    top = np.concatenate([[0.0], _label_max(t, ws, n)])
    for a, b in pairs:
        if min(top[a], top[b]) < WEAK_HOST_RATIO * max(top[a], top[b]):
            continue                                # a smaller protrusion beside a taller one
        sa, sb = boxes[a - 1], boxes[b - 1]
        crop = tuple(slice(max(min(x.start, y.start) - 1, 0), min(max(x.stop, y.stop) + 1, size))
                     for x, y, size in zip(sa, sb, ws.shape))
        w, tc = ws[crop], t[crop]
        bg = w == 0
        both = _filled(tc, ~(bg | (w == a) | (w == b)))
        if (both - tc).max() < th.relief_um:
            continue
        alone = np.maximum(_filled(tc, ~(bg | (w == a))), _filled(tc, ~(bg | (w == b))))
        if (both - alone >= np.maximum(p.split_fraction * both, th.relief_um)).any():
            group[root(b)] = root(a)
    roots = np.array([root(i) for i in range(n + 1)])
    return np.unique(roots, return_inverse=True)[1].astype(np.int32)


#: A weak peak (:func:`_weak_splits`) at most this fraction of the relief of the tallest peak it
#: touches stays its own protrusion: a small dome on a taller one's flank. Lumps of one object
#: (a crater's rim, a pile's ripples) are of about the same height and stay one. The shoulder
#: cue (:func:`_shoulder_markers`) holds a shoulder to the same fraction of its basin's peak.
WEAK_HOST_RATIO = 0.75


def _weak_splits(t: np.ndarray, ws: np.ndarray, weak: np.ndarray, p: DetectionParams) -> np.ndarray:
    """Which weak peaks (:func:`_peak_markers`) stay protrusions of their own.

    A weak peak stands between ``weak_split_fraction`` and ``split_fraction`` of its relief
    above the saddle to a higher one: a cluster member on a taller neighbour's flank (60-100 um
    wide, its saddle 1-2 um deep), or one of the lumps of a crater's rim or of the ripples of a
    pile of paint. It is kept when its relief is at most :data:`WEAK_HOST_RATIO` of the tallest
    basin of ``ws`` it touches (a small member on a taller one: the lumps of one object are of
    a height) and its basin and the tallest basin it touches are not elongated together (the
    minor axis of their second moments at least ``ridge_axis_ratio`` of the major: two touching
    domes are >= 0.5, a rippled pile is a ridge; a member between two neighbours in a row is
    judged with the taller one alone, the row of three being 3x longer than wide). Hand-written:
    no library splits on a dynamic under a shape condition. Returns a boolean per id 0..n
    (index 0 unused): kept."""
    keep = ~weak
    n = weak.size - 1
    if n < 1 or not weak.any():
        return keep
    i, j = _touching(ws)                        # basins side by side (8-connected), both ways
    a, b = ws.ravel()[i], ws.ravel()[j]
    pairs = [np.column_stack([a, b]), np.column_stack([b, a])]
    pairs = np.unique(np.concatenate(pairs), axis=0)        # sorted by the first basin
    start = np.searchsorted(pairs[:, 0], np.arange(n + 2))
    top = np.concatenate([[0.0], _label_max(t, ws, n)])
    boxes = ndi.find_objects(ws, max_label=n)
    is_g = np.zeros(n + 1, bool)
    for q in np.flatnonzero(weak[1:]) + 1:
        group = np.concatenate([[q], pairs[start[q]:start[q + 1], 1]])
        if boxes[q - 1] is None or top[q] > WEAK_HOST_RATIO * top[group].max():
            keep[q] = False
            continue
        group = np.array([q, group[1:][np.argmax(top[group[1:]])]]) if group.size > 1 else group
        sls = [boxes[g - 1] for g in group if boxes[g - 1] is not None]
        r0, r1 = min(s[0].start for s in sls), max(s[0].stop for s in sls)
        c0, c1 = min(s[1].start for s in sls), max(s[1].stop for s in sls)
        is_g[group] = True
        rr, cc = np.nonzero(is_g[ws[r0:r1, c0:c1]])
        is_g[group] = False
        ev = np.linalg.eigvalsh(np.cov(np.vstack([rr, cc]))) if rr.size > 2 else np.ones(2)
        keep[q] = ev[1] <= 0 or math.sqrt(max(ev[0], 0.0) / ev[1]) >= p.ridge_axis_ratio
    return keep


def _shoulder_markers(t: np.ndarray, ws: np.ndarray, markers: np.ndarray, th: Thresholds,
                      px: float, p: DetectionParams, disc: np.ndarray = None, *,
                      curvature: tuple = None) -> tuple:
    """Markers of small protrusions that are only a shoulder of a taller neighbour, and the
    curvature they were found on.

    A dome of width ``w`` on the flank of a taller protrusion has no maximum of the height of
    its own (or one with no saddle ``split_fraction`` below it), but its curvature does: minus
    the Laplacian of Gaussian of the compact relief at sigma ``w / (2 sqrt 2)`` (the scale at
    which a paraboloid of that width responds most) has a maximum on it. Kept: maxima whose
    dynamic (``h_maxima``: how far the curvature drops before a higher peak) exceeds
    ``shoulder_k`` x the curvature's noise (a robust MAD over the image) and the curvature
    ``4 relief_um / (w / 2)^2`` of a paraboloid ``w`` wide and the relief threshold high,
    where both eigenvalues of the Hessian are negative with a ratio >= ``shoulder_isotropy``
    (curved down all round: not a mesa's or a crater's rim, not a stroke's crest), at least
    the relief threshold high and ``w / 2 + 1`` px from every height marker, inside a basin; at most
    :data:`WEAK_HOST_RATIO` of the basin's peak high (a smaller protrusion on a taller one's
    flank: a lump of a crater's rim or of a mesa's edge stands near the peak's height), and,
    given the disc top-hat ``disc``, on no long structure (the mean of ``disc - t`` over it
    below the larger of the relief threshold and a quarter of its height: the measure of
    :func:`_stroke_slope`, though its height here is the compact relief at the curvature peak,
    the neighbour's flank under it included; a stroke's lump is no protrusion's shoulder). Hand-
    written because no library detects blobs inside another's footprint: skimage's
    ``blob_log`` finds scale-space maxima over the whole image, without the footprint, the
    isotropy or a dynamic. ``curvature``: :func:`_shoulder_curvature`'s of ``t`` when it was
    measured already. Returns (markers with the shoulders added, n, curvature)."""
    n_h = int(markers.max())
    if p.shoulder_width_um <= 0 or not n_h:
        return markers, n_h, None
    w = p.shoulder_width_um / px
    curv, noise = curvature if curvature is not None else _shoulder_curvature(t, px, p)
    dyn = max(p.shoulder_k * noise, 4.0 * th.relief_um / (0.5 * w) ** 2)
    inside = ws > 0
    if not inside.any():
        return markers, n_h, curv
    host = np.concatenate([[0.0], _label_max(t, ws, int(ws.max()))])
    hm, far = _curvature_maxima(t, ws, markers, curv, host, dyn, w, th)
    hm[hm] = _isotropy_at(curv, *np.nonzero(hm)) >= p.shoulder_isotropy
    lab, k = ndi.label(hm, structure=np.ones((3, 3)))
    if not k:
        return markers, n_h, curv
    ok = np.zeros(k + 1, bool)
    ok[np.unique(lab[hm & far])] = True
    touch = np.unique(lab[hm & ~far])
    ok[touch] = False
    ok[0] = False
    # a shoulder is a smaller protrusion on a taller one's flank: at most WEAK_HOST_RATIO of the
    # basin's peak (a lump of a crater's rim or of a mesa's edge stands near the peak's height)
    top = np.concatenate([[0.0], _label_max(t, lab, k)])
    host_of = np.zeros(k + 1)
    np.maximum.at(host_of, lab[hm], host[ws[hm]])
    ok &= top <= WEAK_HOST_RATIO * host_of
    if disc is not None:        # not on a long structure (a stroke's lump), as _stroke_slope's
        under = np.concatenate([[0.0], _label_mean(disc - t, lab, k)])
        ok &= ~_on_long_structure(under, top, th)
    keep = ok[lab]
    lut = np.zeros(k + 1, np.int32)
    lut[ok] = np.arange(n_h + 1, n_h + 1 + int(ok.sum()), dtype=np.int32)
    out = markers.copy()
    out[keep] = lut[lab[keep]]
    return out, int(out.max()), curv


def _shoulder_curvature(t: np.ndarray, px: float, p: DetectionParams) -> tuple:
    """The curvature :func:`_shoulder_markers` seeks shoulders on (minus the Laplacian of Gaussian
    of ``t`` at sigma ``w / (2 sqrt 2)``, :func:`_log_curvature`) and its noise (a MAD over the
    image); (None, None) without the shoulder cue."""
    if p.shoulder_width_um <= 0:
        return None, None
    curv = _log_curvature(t, p.shoulder_width_um / px / (2.0 * math.sqrt(2.0)))
    # one copy, partitioned in place by both medians (the same multisets, the same medians)
    d = curv.copy()
    med = np.median(d, overwrite_input=True)
    return curv, 1.4826 * float(np.median(np.abs(np.subtract(curv, med, out=d), out=d), overwrite_input=True))


def _curvature_maxima(t: np.ndarray, ws: np.ndarray, markers: np.ndarray, curv: np.ndarray,
                      host: np.ndarray, dyn: float, w: float, th: Thresholds) -> tuple:
    """:func:`_shoulder_markers`'s maxima of the curvature ``curv`` (dynamic ``dyn``, at least
    the relief threshold high) on the raised areas (touching basins of ``ws``) holding a basin
    whose peak (``host``, per basin id) can host a shoulder; and which pixels of those areas
    lie ``w / 2 + 1`` px from every height marker. Returns (maxima, far), boolean images.

    A shoulder stands at least relief_um high and at most WEAK_HOST_RATIO of its basin's
    peak, so only raised areas holding a basin that tall can have one: the curvature's maxima
    are sought on their crops alone and its Hessian is measured at those maxima alone (over
    the whole image the cue cost 17-21 s at 4000 x 3000, mostly h_maxima,
    docs/decisions/detection.md, "The shoulder cue, on by default"; so, 0.0-1.7 s,
    docs/benchmarks.md, "Detection on other shapes and surfaces"). Each crop's margin holds
    every marker within w / 2 + 1 px, and the pixels outside the raised area take the value they
    have on the whole image (the lowest curvature inside any basin), so the maxima and their
    dynamics are the whole image's (test_shoulder_markers_on_crops_are_the_whole_images)."""
    inside = ws > 0
    area, n_area = ndi.label(inside, structure=np.ones((3, 3)))
    able = np.zeros(n_area + 1, bool)
    able[area[(host >= th.relief_um / WEAK_HOST_RATIO)[ws] & inside]] = True
    fill = float(curv[inside].min())
    pad = int(math.ceil(w / 2.0 + 2.0))
    m, n = t.shape
    hm = np.zeros(t.shape, bool)
    far = np.zeros(t.shape, bool)
    boxes = [(i, sl) for i, sl in enumerate(ndi.find_objects(area)) if able[i + 1]]
    # the maxima at once on the areas' own boxes packed side by side: at an area's own pixels the
    # padded crop's, whose margin only adds pixels at ``fill`` (:func:`_packed_h_maxima`)
    owns = [area[sl] == i + 1 for i, sl in boxes]
    packed = _packed_h_maxima([np.where(own, curv[sl], fill) for (_, sl), own in zip(boxes, owns)],
                              owns, fill, (dyn,))
    for (i, sl), done in zip(boxes, packed):
        crop = (slice(max(sl[0].start - pad, 0), min(sl[0].stop + pad, m)),
                slice(max(sl[1].start - pad, 0), min(sl[1].stop + pad, n)))
        own = area[crop] == i + 1
        if done:
            maxima = np.zeros(own.shape, bool)
            maxima[sl[0].start - crop[0].start:sl[0].stop - crop[0].start,
                   sl[1].start - crop[1].start:sl[1].stop - crop[1].start] = done[0] > 0
        else:
            maxima = h_maxima(np.where(own, curv[crop], fill), dyn) > 0
        peaks = maxima & own & (t[crop] >= th.relief_um)
        hm[crop] |= peaks
        far[crop] |= own & (_edt(markers[crop] == 0) >= w / 2.0 + 1.0)
    return hm, far


def _gaussian_kernels(sigma: float) -> tuple:
    """The Gaussian and its first and second derivatives at ``sigma`` px, radius
    ``int(4 sigma + 0.5)``: the kernels of ``scipy.ndimage.gaussian_filter1d`` (orders 0-2,
    its default truncation), as 1-D float64 arrays."""
    r = int(4.0 * sigma + 0.5)
    x = np.arange(-r, r + 1, dtype=np.float64)
    g = np.exp(-0.5 * x * x / sigma ** 2)
    g /= g.sum()
    return g, -x / sigma ** 2 * g, (x * x / sigma ** 4 - 1.0 / sigma ** 2) * g


#: Rows per band of :func:`_log_curvature`.
LOG_BAND_ROWS = 256


def _log_curvature(t: np.ndarray, sigma: float) -> np.ndarray:
    """Minus the Laplacian of Gaussian of ``t`` (float64): ``-scipy.ndimage.gaussian_laplace(t,
    sigma)`` to rounding (its kernels and ``reflect`` border) by OpenCV's separable filter,
    ~4x faster (0.27 s against 1.0 s at 4000 x 3000)."""
    g, _, d2 = _gaussian_kernels(sigma)
    m = t.shape[0]
    r = g.size // 2
    out = np.empty(t.shape, np.float64)
    # in bands of rows, each filtered with its kernel's reach of rows on either side (reflected only at
    # the image's own edges): every output row is the whole image's, to the bit, without the three
    # float64 copies of the image (0.28 GB at 4000 x 3000) beside the peaks' watershed at the
    # detection's peak of memory (scripts/benchmark_speed.py; test_log_curvature_in_bands_is_the_whole_images)
    for r0 in range(0, m, LOG_BAND_ROWS):
        r1 = min(r0 + LOG_BAND_ROWS, m)
        a0, a1 = max(r0 - r, 0), min(r1 + r, m)
        t64 = t[a0:a1].astype(np.float64)
        band = cv2.sepFilter2D(t64, cv2.CV_64F, g, d2, borderType=cv2.BORDER_REFLECT)
        band += cv2.sepFilter2D(t64, cv2.CV_64F, d2, g, borderType=cv2.BORDER_REFLECT)
        np.negative(band[r0 - a0:r1 - a0], out=out[r0:r1])
    return out


def _isotropy_at(curv: np.ndarray, rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
    """At the given pixels, the ratio of the two eigenvalues of the Hessian of ``curv`` (its
    Gaussian derivatives at sigma 1 px, as ``scipy.ndimage.gaussian_filter(curv, 1, order=...)``
    with its ``reflect`` border and radius 4): ``lam_hi / lam_lo`` where both are negative
    (curved down all round: 1 for a round blob, near 0 for a crest), else 0. The blob of
    curvature a dome makes, whatever slope or curvature of its neighbour it sits on, is curved
    down all round; a rim or a crest only across. Hand-written as sums over each pixel's 9 x 9
    neighbourhood because only the curvature's maxima need it: the three filters over the
    whole image cost ~1.5 s at 4000 x 3000."""
    g, d1, d2 = _gaussian_kernels(1.0)
    def reflect(i, size):       # scipy's "reflect" border (d c b a | a b c d | d c b a), any size
        i = np.mod(i, 2 * size)
        return np.where(i >= size, 2 * size - 1 - i, i)

    off = np.arange(-(g.size // 2), g.size // 2 + 1)
    rr = reflect(rows[:, None] + off, curv.shape[0])
    cc = reflect(cols[:, None] + off, curv.shape[1])
    patch = curv[rr[:, :, None], cc[:, None, :]]
    hrr = np.einsum("pij,i,j->p", patch, d2, g)
    hcc = np.einsum("pij,i,j->p", patch, g, d2)
    hrc = np.einsum("pij,i,j->p", patch, d1, d1)   # both odd kernels flipped: the signs cancel
    half_tr, det_d = 0.5 * (hrr + hcc), np.sqrt(0.25 * (hrr - hcc) ** 2 + hrc ** 2)
    lam_hi, lam_lo = half_tr + det_d, half_tr - det_d          # lam_lo <= lam_hi
    return np.where(lam_hi < 0, lam_hi / np.minimum(lam_lo, -1e-12), 0.0)


def _height_cue(t: np.ndarray, th: Thresholds, px: float, p: DetectionParams,
                disc: np.ndarray = None) -> tuple:
    """Compact footprints of the compact-relief peaks: watershed of ``-t`` from the markers
    (splits touching clusters), then the part of each basin above ``footprint_fraction`` of its
    peak that is connected to the marker. A basin holding shoulder markers
    (:func:`_shoulder_markers`) is split again by a watershed of minus the curvature, so the
    shoulder gets the part of the basin its own curvature encloses; ``disc`` (the disc top-hat)
    goes to :func:`_shoulder_markers` for its long-structure test (None: no such test).
    Returns (labels, markers, n, n_peaks): labels above ``n_peaks`` are shoulders."""
    # the shoulders' curvature reads t alone: beside the peaks and their basins
    (markers, n_h, ws), curvature = concurrently(lambda: _peak_basins(t, th, p),
                                                 lambda: _shoulder_curvature(t, px, p))
    if not n_h:
        return np.zeros(t.shape, np.int32), markers, 0, 0
    n_peaks = n_h
    markers, n_h, curv = _shoulder_markers(t, ws, markers, th, px, p, disc, curvature=curvature)
    if n_h > n_peaks:
        split = np.zeros(n_peaks + 1, bool)
        split[np.unique(ws[markers > n_peaks])] = True
        split[0] = False
        region = split[ws]
        sub = watershed(-curv, np.where(region, markers, 0), mask=region)
        ws = np.where(region, sub, ws)
    peak = _label_max(t, ws, n_h)
    cut = np.concatenate([[np.inf], p.footprint_fraction * peak])
    return _seeded(ws, (t >= cut[ws]) & (ws > 0), markers), markers, n_h, n_peaks


def _peak_basins(t: np.ndarray, th: Thresholds, p: DetectionParams) -> tuple:
    """:func:`_height_cue`'s peaks (:func:`_peak_markers`, a crater's rim joined, the weak
    splits decided) and their watershed basins of ``-t``. Returns (markers, n, basins); no
    basins (None) without a peak."""
    markers, n_h, weak = _peak_markers(t, th, p)
    if not n_h:
        return markers, 0, None
    floor = p.footprint_fraction * th.relief_um
    ws = _basins(t, markers, floor)
    lut = _rim_merges(t, ws, th, p)                 # one crater's rim: its ends joined
    if lut.max() < n_h:
        markers, ws, n_h = lut[markers], lut[ws], int(lut.max())
        strong = np.zeros(n_h + 1, bool)
        strong[lut[1:][~weak[1:]]] = True
        weak = ~strong
        weak[0] = False
    if weak.any():
        keep = _weak_splits(t, ws, weak, p)
        if not keep[1:].all():                      # renumber the markers kept, 1..n
            markers = np.where(keep, np.cumsum(keep) - 1, 0).astype(np.int32)[markers]
            n_h = int(markers.max())
            ws = None           # the first basins released before the watershed's own full-size copies
            ws = _basins(t, markers, floor)
    return markers, n_h, ws


def _basins(t: np.ndarray, markers: np.ndarray, floor: float) -> np.ndarray:
    """``watershed(-t, markers, mask=(t >= floor) | (markers > 0))``, the same labels, from the
    mask's components that hold a marker, packed side by side into one small image.

    The flood (4-connected, as the watershed's) never leaves a component of the mask, and within
    one it pops its pixels in the order of (value, age of push), which no other component
    changes, once no two markers tie in value: the markers are all pushed at age 0, and a heap
    breaks such ties by its whole content. So with distinct marker values each component's
    basins are the whole image's; else the whole image is flooded. On a 4000 x 3000 run
    (``uvps run --regions auto``, 16 lamps) the mask was 1 % of the image and the boxes of its
    components 2 %: the whole-image call spent most of its 0.1-0.2 s (CPU) converting and padding
    the image, the packed one takes 0.08 s. Hand-written packing around
    skimage's watershed (no library floods a set of crops at once)."""
    mask = (t >= floor) | (markers > 0)
    at = markers > 0
    if np.unique(t[at]).size < np.count_nonzero(at):
        return watershed(-t, markers, mask=mask)
    comp, _ = ndi.label(mask)                       # the watershed's own connectivity
    slices = ndi.find_objects(comp)
    ids = np.unique(comp[at])
    ids = ids[ids > 0]
    out = np.zeros(t.shape, np.int32)
    if not ids.size:
        return out
    boxes = [slices[i - 1] for i in ids]
    place, shape = _shelves([(s[0].stop - s[0].start, s[1].stop - s[1].start) for s in boxes])
    img = np.zeros(shape, t.dtype)
    mk = np.zeros(shape, np.int32)
    inside = np.zeros(shape, bool)
    owns = []
    for i, sl, (r, c) in zip(ids, boxes, place):   # a 1-px gap of mask False between crops
        own = comp[sl] == i
        dst = (slice(r, r + own.shape[0]), slice(c, c + own.shape[1]))
        img[dst], mk[dst], inside[dst] = t[sl], np.where(own, markers[sl], 0), own
        owns.append((own, dst))
    flooded = watershed(-img, mk, mask=inside)
    for sl, (own, dst) in zip(boxes, owns):
        out[sl][own] = flooded[dst][own]
    return out


def _seeded(ws: np.ndarray, foot: np.ndarray, markers: np.ndarray) -> np.ndarray:
    """``ws`` where ``foot`` is connected to a marker pixel, else 0."""
    parts, n = ndi.label(foot, structure=np.ones((3, 3)))
    seeded = np.zeros(n + 1, bool)
    seeded[parts[markers > 0]] = True
    seeded[0] = False
    # written at the parts' pixels alone: on the whole image (a few % of it in parts) a full-size
    # np.where and its int32 copy cost ~0.1 s at 4000 x 3000 (line_profiler, `uvps run --regions auto`)
    out = np.zeros(ws.shape, np.int32)
    at = np.flatnonzero(parts)
    at = at[seeded[parts.ravel()[at]]]
    out.ravel()[at] = ws.ravel()[at]
    return out
