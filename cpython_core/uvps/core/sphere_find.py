"""Finding the spheres of a sphere capture: circles in the images (:func:`detect_spheres`), the
:class:`Sphere` record, and the grey values they are found on; :mod:`uvps.core.spheres` fits and
calibrates them (and re-exports these names).

Spheres are found by circle detection (OpenCV's gradient Hough transform, ``HOUGH_GRADIENT_ALT``,
on a reduced maximum projection of the capture), their rims then located along 720 rays at full
resolution in each view (median, maximum; mean and logarithms for dark spheres) and fitted by a RANSAC
circle (``skimage.measure.ransac``) whose band is the rim's own scatter, then one circle through the
rim points of every linear view that found the sphere; see :mod:`uvps.core.spheres`.
"""
from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from typing import Optional

import numpy as np
from scipy import ndimage

from .progress import Progress, report
from .threads import default_threads, map_bands

log = logging.getLogger("uvps.core.spheres")   # one logger for finding and fitting spheres

#: The reduced projection for detection is at most this many pixels on its long side.
DETECT_LONG_SIDE = 1000
#: A sphere's radius at least this many pixels of the full image (smaller ones cannot give a direction
#: to a fraction of a degree).
MIN_RADIUS_PX = 12
#: A circle is a sphere's rim when at least this fraction of the 720 rays from its centre meet the rim on
#: it (spheres of the benchmark: 0.94-0.99, with a stand and flare spikes 0.75; round paint features
#: the Hough transform proposes: 0.31-0.49).
MIN_RIM_FRACTION = 0.6
#: The same on a room-lit reference picture of the spheres in place (``uvps calibrate --sphere-reference``),
#: taken to show them: a stand and a dark background behind one side may hide half a rim there (the
#: PSBox mirror sphere's ``ref.JPG``: 0.51), so the circle in spheres.png is the check.
REFERENCE_RIM_FRACTION = 0.45
#: The same for a circle found by :func:`_ransac_circle` when the Hough transform found none (a dark
#: sphere on a dark ground crossed by flare spikes, a holder below it: 0.37 of its rays on the rim).
RANSAC_RIM_FRACTION = 0.33
#: A detected circle under this fraction of the largest one's radius is not a calibration sphere
#: (spheres of one capture are of one size or close; on a painting's relief a 14 px bump beside two
#: 90 px spheres was found as a third, and the lamps came 29 deg off). Give unequal spheres with
#: ``--sphere-circles``.
MIN_RADIUS_RATIO = 0.4


@dataclass(frozen=True)
class Sphere:
    """A sphere in the image: centre ``(col, row)`` and radius in pixels; ``kind`` matte, glossy or
    auto (decided from the images); ``source`` detected or given."""

    centre_px: tuple
    radius_px: float
    kind: str = "auto"
    source: str = "detected"

    def to_json(self) -> dict:
        return {"centre_px": [float(self.centre_px[0]), float(self.centre_px[1])], "radius_px": float(self.radius_px),
                "kind": self.kind, "source": self.source}




def _grey(img) -> np.ndarray:
    a = np.asarray(img, dtype=np.float32)
    return a.mean(axis=-1) if a.ndim == 3 else a




# ------------------------------------------------------------------------------------------------
# detection
# ------------------------------------------------------------------------------------------------

def _in_two_bands(fn, M, step=1):
    """``[fn(r0, r1), ...]`` over two bands of ``M`` rows, side by side in :func:`uvps.core.threads.default_threads`
    (2) threads (numpy's reading, median and sums release the GIL); the second band starts on the grid of
    every ``step``-th row, so a band's ``r0:r1:step`` rows are the whole's."""
    return map_bands(lambda rows: fn(rows.start, rows.stop), M, parts=2, step=step, threads=default_threads(2))


def _projections(images, step):
    """Median, maximum and mean over the images of the grey image sampled every ``step`` pixels,
    in two bands of rows side by side: the median over 64 images of a 1000 x 750 projection is
    about a second of a sphere capture's detection, and the three took 1.5 s in one thread, 0.56 s so."""
    K = images.shape[0]

    def band(r0, r1):
        first = _grey(images[0, r0:r1:step, ::step])
        stack = np.empty((K,) + first.shape, np.float32)
        stack[0] = first
        for k in range(1, K):
            stack[k] = _grey(images[k, r0:r1:step, ::step])
        return np.median(stack, axis=0), stack.max(axis=0), stack.mean(axis=0)

    parts = _in_two_bands(band, images.shape[1], step)
    return tuple(np.concatenate([p[i] for p in parts]) for i in range(3))


def _mean_image(images, step):
    """The mean over the images of the grey image sampled every ``step`` pixels (float64): a running
    sum, one image at a time, in two bands of rows side by side."""
    K = images.shape[0]

    def band(r0, r1):
        out = _grey(images[0, r0:r1:step, ::step]).astype(np.float64)
        for k in range(1, K):
            out += _grey(images[k, r0:r1:step, ::step])
        return out / K

    return np.concatenate(_in_two_bands(band, images.shape[1], step))


def _median_over_images(stack):
    """``np.median(stack, axis=0)`` of a (K, rows, cols) stack, in two bands of rows side by side."""
    return np.concatenate(_in_two_bands(lambda r0, r1: np.median(stack[:, r0:r1], axis=0), stack.shape[1]))


def _to8(img):
    lo, hi = np.percentile(img, (0.5, 99.8))
    if not hi > lo:
        return None
    return np.clip((img - lo) * (255.0 / (hi - lo)), 0, 255).astype(np.uint8)


def _hough(img, min_r, max_r):
    """Circles (x, y, r) in the reduced image by OpenCV's HOUGH_GRADIENT_ALT."""
    import cv2

    img8 = _to8(img)
    if img8 is None:
        return []
    img8 = cv2.GaussianBlur(img8, (0, 0), 1.5)
    found = []
    # the Canny threshold of the gradient Hough transform suits one contrast or another: the union of
    # three, each circle then checked at full resolution and against the images
    for edge in (200, 100, 50):
        c = cv2.HoughCircles(img8, cv2.HOUGH_GRADIENT_ALT, dp=1.5, minDist=max(2.0 * min_r, 4.0), param1=edge,
                             param2=0.8, minRadius=int(min_r), maxRadius=int(max_r))
        if c is not None:
            found += [tuple(map(float, v)) for v in c.reshape(-1, 3)]
    return found


def _crop_box(centre, radius, shape, margin=1.35):
    c, r = centre
    h = margin * radius
    r0, r1 = max(0, int(math.floor(r - h))), min(shape[0], int(math.ceil(r + h)) + 1)
    c0, c1 = max(0, int(math.floor(c - h))), min(shape[1], int(math.ceil(c + h)) + 1)
    return r0, r1, c0, c1


def _refine_circle(proj, centre, radius):
    """Centre (col, row) and radius of the rim near a coarse circle, at full resolution: the steepest
    radial step along 720 rays (sub-pixel), then a RANSAC circle (:func:`_robust_circle`); with the
    fraction of the rays that meet the rim on it, which ones, and the rim points it kept ((n, 2), col
    and row). None if the rim is not found."""

    sm = ndimage.gaussian_filter(proj.astype(np.float32), 1.0)
    theta = np.linspace(0, 2 * np.pi, 720, endpoint=False)
    rho = np.arange(0.75 * radius, 1.25 * radius, 0.5)
    cc = centre[0] + np.outer(np.cos(theta), rho)
    rr = centre[1] - np.outer(np.sin(theta), rho)
    inside = (cc >= 0) & (cc <= proj.shape[1] - 1) & (rr >= 0) & (rr <= proj.shape[0] - 1)
    prof = ndimage.map_coordinates(sm, [rr, cc], order=1, mode="nearest")
    grad = np.abs(np.gradient(prof, axis=1))
    grad[~inside] = 0
    grad[:, 0] = grad[:, -1] = 0
    j = grad.argmax(axis=1)
    ok = inside[np.arange(len(theta)), j] & (grad[np.arange(len(theta)), j] > 0)
    # sub-pixel: the parabola through the step and its neighbours
    jj = np.clip(j, 1, len(rho) - 2)
    g0, g1, g2 = (grad[np.arange(len(theta)), jj + o] for o in (-1, 0, 1))
    den = g0 - 2 * g1 + g2
    off = np.where(np.abs(den) > 1e-12, 0.5 * (g0 - g2) / np.where(den == 0, 1, den), 0.0)
    rad = rho[jj] + np.clip(off, -1, 1) * (rho[1] - rho[0])
    # strong steps only: a rim in the frame has a contrast well above the noise
    strength = grad[np.arange(len(theta)), j]
    ok &= strength > 0.25 * np.median(strength[ok]) if ok.any() else ok
    if ok.sum() < 30:
        return None
    pts = np.column_stack([centre[0] + rad * np.cos(theta), centre[1] - rad * np.sin(theta)])[ok]
    fitted, inl = _robust_circle(pts, rad[ok], radius, need=max(30, 0.3 * len(theta) * ok.mean()))
    if fitted is None:
        return None
    xc, yc, r = fitted
    # the rays on the rim: within the first consensus band of the circle (1 % of the radius, 1 px at least)
    on = np.abs(np.hypot(pts[:, 0] - xc, pts[:, 1] - yc) - r) < max(1.0, 0.01 * radius)
    rays = np.zeros(len(theta), bool)
    rays[np.flatnonzero(ok)[on]] = True
    return (xc, yc), r, float(on.sum() / len(theta)), rays, pts[inl]


def _robust_circle(pts, rad, radius, *, need, band=None):
    """The circle (x, y, r) of the rim points ``pts`` (one per ray, in the rays' order, ``rad`` their
    distances from the first centre) and which points it keeps; (None, None) when fewer than ``need``.

    A stand, a holder or the lit ground a mirror sphere's limb reflects moves the steepest step of a
    whole arc of rays off the rim by a few pixels, coherently: a band of 1 % of the radius (4 px on a
    400 px sphere) takes both arcs, and the circle between them has more points in it than the rim (a
    mirror sphere's lower third reflecting the ground 3.7 px inside the rim: 2.3 px up, 3 deg on every
    lamp). So the consensus band is the rim's own scatter: three robust standard deviations of the step
    from ray to ray (0.5 px at least, the first band at most), which a coherent arc off by more than it
    leaves out; then the circle is refitted to the points within 2.5 robust standard deviations of it
    until they stop changing."""
    from skimage.measure import CircleModel, ransac

    if band is None:
        band = _rim_band(rad, radius)
    model, inl = ransac(pts, CircleModel, min_samples=3, residual_threshold=band, max_trials=500,
                        stop_probability=0.9999, rng=0)
    if model is None or inl is None or inl.sum() < need:
        return None, None
    fitted = _circle(pts[inl])
    if fitted is None:
        return None, None
    for _ in range(5):
        d = np.hypot(pts[:, 0] - fitted[0], pts[:, 1] - fitted[1]) - fitted[2]
        s_ = 1.4826 * np.median(np.abs(d[inl])) + 1e-6
        keep = np.abs(d) < max(0.5, 2.5 * s_)
        if keep.sum() < need or np.array_equal(keep, inl):
            break
        refit = _circle(pts[keep])
        if refit is None:
            break
        inl, fitted = keep, refit
    return fitted, inl


def _rim_band(rad, radius):
    """The consensus band of a rim's points (px): three robust standard deviations of the step from ray to
    ray of their distances ``rad`` from the first centre (in the rays' order), 0.5 px at least, 1 % of
    the radius (1 px at least) at most."""
    jitter = 1.4826 * np.median(np.abs(np.diff(rad))) / math.sqrt(2.0) if len(rad) > 2 else 0.0
    return float(np.clip(3.0 * jitter, 0.5, max(1.0, 0.01 * radius)))


def _circle(points):
    """Least-squares circle (x, y, r) through points (skimage's CircleModel, either API)."""
    from skimage.measure import CircleModel

    if hasattr(CircleModel, "from_estimate"):
        model = CircleModel.from_estimate(points)
        if not model:
            return None
        return float(model.center[0]), float(model.center[1]), float(model.radius)
    model = CircleModel()
    if not model.estimate(points):
        return None
    return tuple(float(v) for v in model.params)


def detect_spheres(images, *, min_rim_fraction: float = MIN_RIM_FRACTION, progress: Progress = None,
                   clipped_out: Optional[list] = None) -> list:
    """Find the spheres of a sphere capture: circles of the capture's maximum projection.

    Parameters
    ----------
    images : (K, M, N[, C]) array-like
        The sphere capture (counts), or a room-lit reference picture as a stack of one.
    min_rim_fraction : float
        The fraction of the rays from a circle's centre that must meet the rim on it
        (:data:`MIN_RIM_FRACTION`; :data:`REFERENCE_RIM_FRACTION` for a reference picture); for a
        circle cut by the frame, of the rays whose rim lies in the frame.
    clipped_out : list, optional
        Receives the circles found cut by the frame (left out of the result: a sphere's disc must be
        whole for its normals, and its rim on one side only leaves its centre loose).

    Returns
    -------
    list of Sphere
        ``kind`` "auto"; ``source`` "detected"; sorted by row, then column. Empty when none is found.

    Notes
    -----
    The projection is reduced to at most :data:`DETECT_LONG_SIDE` pixels on its long side (every
    n-th pixel) for the Hough transform; each circle is then refined at full resolution
    (:func:`_refine_circle`). The median projection shows a glossy sphere as a dark disc on the
    lit background and a matte one as a shaded disc, without the highlights and flare spikes (whose
    ring in the maximum projection is a circle too, inside a sphere already found); then the maximum
    (a mirror sphere on black, only its highlights; a matte sphere whose shading matches the ground
    in the median) and the mean add the circles the median missed, and the logarithm of the mean and
    the median a dark sphere's rim on a dark ground (a ratio, a few counts); the largest circles are
    tried first. When none of them is a rim, a RANSAC circle on the edges of the logarithms
    (:func:`_ransac_circle`) is tried with :data:`RANSAC_RIM_FRACTION` of the rim.
    """
    K, M, N = images.shape[:3]
    step = max(1, int(math.ceil(max(M, N) / DETECT_LONG_SIDE)))
    projections = _projections(images, step)
    report(progress, 0.4, "sphere detection: projections")
    min_r = max(4.0, MIN_RADIUS_PX / step)
    max_r = 0.55 * min(projections[0].shape)
    # the logarithm of the mean and the median besides: a dark sphere on a dark ground (a black or mirror
    # sphere on black cloth) differs from it by a ratio, not by counts, and its rim, a few counts in the
    # linear projections under the highlights' range, is an edge like any other in the logarithm (the
    # PSBox mirror sphere's: found only so)
    logs = [_log_view(p) for p in (projections[2], projections[0])]
    # the largest circles first: a highlight's or a reflection's small ring inside a sphere would
    # otherwise stand for it
    circles = sorted((c for proj in list(projections) + logs for c in _hough(proj, min_r, max_r)),
                     key=lambda c: -c[2])
    found = []
    clipped = []
    for (x, y, r) in circles:
        _consider(images, x, y, r, step=step, found=found, clipped=clipped, need=min_rim_fraction,
                  min_rim_fraction=min_rim_fraction)
    if not found and not clipped:
        # nothing the Hough transform proposed is a rim: a dark sphere on a dark ground crossed by a
        # flare's spikes, whose rim is a broken arc among straight edges; a RANSAC circle on the edge
        # points of the logarithm of the median and of the mean; its rim need only be a third of the rays
        # (the fit then asks a highlight in every image, or Lambert's shading)
        for proj in logs[::-1]:
            c = _ransac_circle(proj, min_r, max_r)
            if c is not None:
                _consider(images, *c, step=step, found=found, clipped=clipped,
                          need=min(min_rim_fraction, RANSAC_RIM_FRACTION), min_rim_fraction=min_rim_fraction)
    found = _without_small(found)
    if clipped:
        log.info("sphere detection: %d circle(s) cut by the frame left out: %s", len(clipped),
                 ", ".join(f"({s.centre_px[0]:.0f}, {s.centre_px[1]:.0f}) r {s.radius_px:.0f} px" for s in clipped))
    if clipped_out is not None:
        clipped_out.extend(sorted(clipped, key=lambda s: (s.centre_px[1], s.centre_px[0])))
    report(progress, 0.5, f"sphere detection: {len(found)} circle(s)")
    return sorted(found, key=lambda s: (s.centre_px[1], s.centre_px[0]))


def _consider(images, x, y, r, *, step, found, clipped, need, min_rim_fraction):
    """Refine one proposed circle (reduced pixels) and keep it, into ``found`` (whole in the frame)
    or ``clipped`` (cut by it), if ``need`` of its rays meet its rim; skipped when far smaller than
    a sphere found or on one already found."""
    K, M, N = images.shape[:3]
    centre, radius = (x * step, y * step), r * step
    if found and radius < MIN_RADIUS_RATIO * max(o.radius_px for o in found):
        return                    # left out below anyway: not worth its crops
    if any(math.hypot(centre[0] - o.centre_px[0], centre[1] - o.centre_px[1]) < 0.8 * (radius + o.radius_px)
           for o in found + clipped):
        return
    fitted = _fit_rim(images, centre, radius, min_rim_fraction)
    if fitted is None:
        return
    s, rim = fitted
    rr = s.radius_px
    # a sphere cut by the frame: its rim is sought on the rays whose rim lies in the frame
    theta = np.linspace(0, 2 * np.pi, 720, endpoint=False)
    in_frame = _rim_in_frame(s, theta, (M, N))
    if rim[in_frame].sum() < need * max(in_frame.sum(), 0.5 * len(theta)):
        return
    if rr < MIN_RADIUS_PX or any(math.hypot(s.centre_px[0] - o.centre_px[0], s.centre_px[1] - o.centre_px[1])
                                 < 0.8 * (rr + o.radius_px) for o in found + clipped):
        return
    (found if in_frame.all() else clipped).append(s)


def _fit_rim(images, centre, radius, min_rim_fraction):
    """The circle refined at full resolution near ``centre``, ``radius`` (px) and which of 720 rays
    meet its rim (None: no rim there), where the rim is sharpest: the maximum shows a matte sphere's
    limb lit all round, the median a glossy sphere's dark disc; the fit with more rim points wins."""
    K, M, N = images.shape[:3]
    box = _crop_box(centre, radius, (M, N))
    crops = np.stack([_grey(images[k, box[0]:box[1], box[2]:box[3]]) for k in range(K)])
    at = (centre[0] - box[2], centre[1] - box[0])
    refs = [r_ for r_ in (_refine_circle(crop, at, radius) for crop in (_median_over_images(crops),
                                                                        crops.max(axis=0))) if r_ is not None]
    linear = len(refs)
    if not refs or max(r_[2] for r_ in refs) < min_rim_fraction:
        # a dark sphere on a dark ground: its rim in the mean and the mean's logarithm, where the
        # median and the maximum find too little of it
        mean = crops.mean(axis=0)
        more = [_refine_circle(crop, at, radius) for crop in (mean, _log_view(mean),
                                                              _log_view(_median_over_images(crops)))]
        linear += more[0] is not None
        refs = refs + [r_ for r_ in more if r_ is not None]
    if not refs:
        return None
    best = max(refs, key=lambda r_: r_[2])
    ref = _linear_rim(refs[:linear], best)
    # a matte sphere's rim is sharp in the median on some sides and in the maximum on the others:
    # where the two find the same circle, a ray on the rim in either counts
    rim = np.logical_or.reduce([r_[3] for r_ in refs if _same_circle(r_, ref, 1.0)])
    if ref is not best:
        rim |= best[3]
    (xc, yc), rr = _pooled_rim(refs[:linear], ref, radius)
    return Sphere((xc + box[2], yc + box[0]), rr, "auto", "detected"), rim


def _pooled_rim(linear, ref, radius):
    """The circle of the rim points of every linear view that found the same sphere as ``ref`` (within
    10 % of its radius): each view sees the rim where it is sharp (a mirror sphere's median its dark
    disc against the ground, where the highlights' glow leaves the upper limb soft; the maximum the
    upper limb lit, where a stand hides the lower one), and one view's circle rests on its arcs alone
    (PSBox's two mirror spheres: the median's and the maximum's circles 2.3 px apart in their rows).
    Fitted robustly with the views' own consensus band (:func:`_robust_circle`); ``ref``'s circle when
    only it found the sphere or the pooled fit keeps too little."""
    views = [r_ for r_ in linear if _same_circle(r_, ref, 0.1 * ref[1])]
    if len(views) < 2:
        return ref[:2]
    pts = np.concatenate([r_[4] for r_ in views])
    band = max(_rim_band(np.hypot(r_[4][:, 0] - r_[0][0], r_[4][:, 1] - r_[0][1]), radius) for r_ in views)
    fitted, _ = _robust_circle(pts, None, radius, need=max(len(r_[4]) for r_ in views), band=band)
    return ref[:2] if fitted is None else ((fitted[0], fitted[1]), fitted[2])


def _same_circle(a, b, tol):
    """Whether two refined circles (centre, radius, ...) agree within ``tol`` px in centre and radius."""
    return math.hypot(a[0][0] - b[0][0], a[0][1] - b[0][1]) < tol and abs(a[1] - b[1]) < tol


def _linear_rim(linear, best):
    """The circle to keep of the views' refined circles: the linear views' (median, maximum, mean) one
    with the most rim near ``best`` (the view with the most rim), else ``best``. A logarithm's steepest
    step lies on the dark side of a blurred rim (``d log I = dI / I``): a mirror sphere's rim blurred
    by 1.5 / 3 px sits 1.2-1.8 / 2.3-4.0 px inside in the logarithm of the mean of a rendered capture
    (80 px radius); the linear views' step at the rim itself. A linear view's circle is kept when it
    is the same sphere as ``best``'s (refined from the same proposal, within 10 % of the radius in
    centre and radius) and on :data:`RANSAC_RIM_FRACTION` of its rays at least, though with less of the
    rim than ``best`` (a mirror sphere's lower limb reflecting the lit ground: 0.57 of the rays in the
    median, 0.67 in the logarithm)."""
    near = [r_ for r_ in linear if r_[2] >= RANSAC_RIM_FRACTION and _same_circle(r_, best, 0.1 * best[1])]
    return max(near, key=lambda r_: r_[2]) if near else best


def _without_small(found: list) -> list:
    """The circles of ``found`` not under :data:`MIN_RADIUS_RATIO` of the largest: calibration
    spheres are of one size or close; a circle far smaller is the painting's own (a protrusion,
    a blob of paint) and would pull every lamp's position with a wrong ray."""
    if not found:
        return found
    largest = max(s.radius_px for s in found)
    small = [s for s in found if s.radius_px < MIN_RADIUS_RATIO * largest]
    for s in small:
        log.info("sphere detection: the circle at (%.0f, %.0f) px of radius %.1f px is under %.0f %% of the "
                 "largest (%.1f px): left out", s.centre_px[0], s.centre_px[1], s.radius_px,
                 100 * MIN_RADIUS_RATIO, largest)
    return [s for s in found if s not in small]


def _ransac_circle(img, min_r, max_r):
    """The circle (x, y, r) through most edge points of a view (Canny at Otsu's threshold) by RANSAC
    (``skimage.measure.ransac`` with ``CircleModel``, 3000 trials), when at least a third of its
    perimeter is edge; else None."""
    import cv2
    from skimage.measure import CircleModel, ransac

    img8 = _to8(img)
    if img8 is None:
        return None
    img8 = cv2.GaussianBlur(img8, (0, 0), 1.5)
    hi, _ = cv2.threshold(img8, 0, 255, cv2.THRESH_BINARY + cv2.THRESH_OTSU)
    y, x = np.nonzero(cv2.Canny(img8, 0.5 * hi, hi))
    if x.size < 30:
        return None
    pts = np.column_stack([x, y]).astype(np.float64)
    if len(pts) > 20000:
        pts = pts[np.random.default_rng(0).choice(len(pts), 20000, replace=False)]

    def radius(m):
        return float(m.radius) if hasattr(m, "radius") else float(m.params[2])

    def valid(m, *_):
        return min_r <= radius(m) <= max_r

    model, inl = ransac(pts, CircleModel, min_samples=3, residual_threshold=1.5, max_trials=3000,
                        is_model_valid=valid, rng=0)
    if model is None or inl is None:
        return None
    r = radius(model)
    if inl.sum() < 2 * math.pi * r / 3:
        return None
    centre = model.center if hasattr(model, "center") else model.params[:2]
    return float(centre[0]), float(centre[1]), r


def _log_view(img):
    """The logarithm of a projection, offset by a tenth of its first quartile (at least 1e-3 of its
    range): dark grounds' and dark spheres' ratios as edges, the noise of the darkest counts kept down."""
    img = np.maximum(np.asarray(img, np.float32), 0)
    q1, top = np.percentile(img, (25, 99.9))
    return np.log(img + max(0.1 * float(q1), 1e-3 * float(top), 1e-6))


def _rim_in_frame(sphere: Sphere, theta, shape):
    """Which rays' rim points (angles ``theta``, counter-clockwise from +x, y up) lie in the frame."""
    M, N = shape
    c = sphere.centre_px[0] + sphere.radius_px * np.cos(theta)
    r = sphere.centre_px[1] - sphere.radius_px * np.sin(theta)
    return (c >= -0.5) & (c <= N - 0.5) & (r >= -0.5) & (r <= M - 0.5)
