"""Monitoring over time: two captures of one region, protrusion by protrusion (``uvps changes``).

A is the earlier run folder, B the later one; each made by ``uvps run`` with detection. Steps:

1. **Registration** of B onto A from the albedo (:func:`register`): SIFT features, Lowe's ratio
   test, RANSAC for a similarity, an affine map and a homography; the model is chosen by the data
   (the Bayesian information criterion of each least-squares fit on the common inliers), then
   refined to sub-pixel by ECC (:func:`cv2.findTransformECC`) on the high-passed log albedo
   (a similarity stays one: the ECC affine is projected back). Its residual is measured by phase
   correlation on tiles of the overlap. Too few consistent matches stop the command (exit 1):
   no alignment is invented.
2. **Heights** of B brought into A's frame (cubic), **levelled** against A's: the smooth
   difference (block medians off the protrusions, smoothed; a canvas relaxing, the integration's
   low-frequency error) is removed and reported, and the two dates' height scales are matched
   on the common relief (the estimated lamps leave the heights' scale uncertain by a few %).
0. **The dates' scales**: each run's ``run.json`` (its lamps, calibration and relief scale) is
   recorded (:func:`date_record`); a relative relief (lamps not pinned) refuses height growth
   (:func:`check_height_scales`) unless ``widths_only``.
3. **Matching** one to one (:func:`uvps.core.compare.match_protrusions`) of A's protrusions with B's
   mapped into A's frame; then neighbours that ``merged`` or ``split``; what is left alone is
   ``new`` or ``gone``. A pair is ``grown`` / ``shrunk`` when its change of width or height
   exceeds ``sigma_factor`` x that change's standard uncertainty (:func:`change_uncertainty`:
   :data:`NOISE_MODEL` fitted to unchanged pairs, scaled by :func:`pair_inflation` when this
   pair repeats worse), else ``unchanged``. Protrusions that either date does not see whole are
   left out (counted in ``run.json``).

Outputs (``docs/monitoring.md``): ``registration.json``,
``changes.csv`` (:data:`COLUMNS`), ``height_change.tif`` (A's frame, um), ``report.html`` with
``figures/``, ``run.json``.
"""
from __future__ import annotations

import dataclasses
import logging
from dataclasses import dataclass, field
from typing import NamedTuple, Optional

import cv2
import numpy as np
from skimage.registration import phase_cross_correlation
from scipy import ndimage

from .compare import match_protrusions
from .level import FORM_DEGREE, fit_surface, legendre_surface
from ..errors import UVPSInputError
from .progress import Progress, report
from .regions import UM2_PER_CM2, bin_edges, bin_names

log = logging.getLogger(__name__)

#: Columns of ``changes.csv``, in order (the output contract). ``d_width_sd_um`` and
#: ``d_height_sd_um`` are the changes' standard uncertainties (:func:`change_uncertainty`),
#: ``significance`` the larger of ``|d_width_um| / d_width_sd_um`` and ``|d_height_um| /
#: d_height_sd_um`` (in standard deviations; a status other than unchanged needs ``sigma_factor``).
COLUMNS = ("id_a", "id_b", "x_px_a", "y_px_a", "x_px_b", "y_px_b", "status", "width_um_a",
           "width_um_b", "height_um_a", "height_um_b", "d_width_um", "d_height_um", "d_width_sd_um",
           "d_height_sd_um", "significance", "region")
STATUSES = ("new", "grown", "shrunk", "unchanged", "gone", "merged", "split")


@dataclass(frozen=True)
class NoiseModel:
    """The standard uncertainty of one date's width and height of a protrusion, whose terms are
    what makes a measurement differ between two captures of an unchanged surface; the
    coefficients are fitted to unchanged pairs (another camera pose, the lamps placed again).

    Per date, for a protrusion of width ``w`` and height ``h`` (um) at pixel size ``p`` (um), with
    ``s`` the robust sd of the levelled height change around it (um, the pair's own surface
    noise) and ``q = p / w`` (one over its width in pixels)::

        sd_width^2  = (width_px * p)^2 + (width_rel * w)^2 + (rim * p * q^rim_exponent)^2
        sd_height^2 = (peak * h * q^peak_exponent)^2 + (height_rel * h)^2 + (surface * s)^2

    ``width_px``: the outline's quantisation on the pixel grid (a camera move puts other pixels on
    the edge); ``width_rel``: the footprint threshold's share of the width; ``rim``: the outline
    of a protrusion few pixels wide drawn on few pixels (its area counts a handful of edge pixels
    in or out, and its footprint threshold follows a peak that repeats worse), in pixels at one
    pixel wide, falling as ``q^rim_exponent``; ``peak``: the relief sampled at another pixel
    phase (the sub-pixel position of the protrusion differs between the dates; a dome a few
    pixels wide, its normals sampled on a few pixels and integrated, loses another share of its
    height at each phase), a share of the height at one pixel wide falling as
    ``q^peak_exponent`` (a smooth dome's top sampled off its peak alone gives 2; fitted, 2.7: the
    fewer pixels a dome spans, the more of its relief its few normals, integrated, miss as the
    phase moves); ``height_rel``: the scale (the lamps placed again);
    ``surface``: the heights' own noise. A change's variance is the sum of the two dates'.
    The defaults of the added terms (``rim`` 0, ``peak_exponent`` 2) are the model without them.
    """

    width_px: float
    width_rel: float
    peak: float
    height_rel: float
    surface: float
    n: int = 0
    source: str = ""
    peak_exponent: float = 2.0
    rim: float = 0.0
    rim_exponent: float = 0.5


#: The model before its terms grew with the protrusion's size in pixels (``peak`` at a fixed
#: exponent 2, no ``rim`` term): kept to show what it flags (tests, ``scripts/benchmark_changes.py``).
NOISE_MODEL_FIXED_PEAK = NoiseModel(width_px=0.130, width_rel=0.0, peak=0.635, height_rel=0.0014, surface=1.33,
                                    n=476, source="476 protrusions of 3 moved unchanged pairs (clean scenes), "
                                    "trimmed at 4 sd")

#: Fitted by ``.venv/bin/python scripts/benchmark_changes.py --seeds 10 11 12 --variants small clean real
#: --kinds moved --fit-noise`` on the unchanged pairs with the camera moved and the lamps placed again
#: (the true lamp positions; protrusions from 40 um wide; ``rim_exponent`` held at 0.5 and ``surface``
#: at 1.33: ``benchmark_changes.FIT_FIXED`` says why), seeds other than the benchmark's scored ones
#: (docs/monitoring.md, docs/benchmarks.md "Monitoring over time").
NOISE_MODEL = NoiseModel(width_px=0.0, width_rel=0.004218, peak=2.244, height_rel=0.004724, surface=1.33,
                         peak_exponent=2.735, rim=0.4218, rim_exponent=0.5, n=1044,
                         source="1044 of 1053 protrusions of 9 moved unchanged pairs (small clean real scenes, "
                                "seeds 10 11 12), trimmed at 4 sd; rim_exponent and surface held")


def change_uncertainty(width_a, width_b, height_a, height_b, *, pixel_size_um_a: float,
                       pixel_size_um_b: float, surface_um=0.0, model: NoiseModel = NOISE_MODEL):
    """Standard uncertainties ``(sd_d_width_um, sd_d_height_um)`` of the changes of width and
    height between two dates (arrays), by :class:`NoiseModel`: each date's variance at its own
    width, height and pixel size, summed. NaN widths or heights count as the other date's."""
    wa, wb = np.asarray(width_a, float), np.asarray(width_b, float)
    ha, hb = np.abs(np.asarray(height_a, float)), np.abs(np.asarray(height_b, float))
    wa, wb = np.where(np.isfinite(wa), wa, wb), np.where(np.isfinite(wb), wb, wa)
    ha, hb = np.where(np.isfinite(ha), ha, hb), np.where(np.isfinite(hb), hb, ha)
    s = np.nan_to_num(np.asarray(surface_um, float))

    def q(w, p):        # one over the width in pixels, at most 1
        return np.clip(p / np.maximum(w, p), 0, 1)

    def var_w(w, p):
        return ((model.width_px * p) ** 2 + (model.width_rel * w) ** 2
                + (model.rim * p * q(w, p) ** model.rim_exponent) ** 2)

    def var_h(w, h, p):
        return ((model.peak * h * q(w, p) ** model.peak_exponent) ** 2 + (model.height_rel * h) ** 2
                + (model.surface * s) ** 2)

    sd_w = np.sqrt(var_w(wa, pixel_size_um_a) + var_w(wb, pixel_size_um_b))
    sd_h = np.sqrt(var_h(wa, ha, pixel_size_um_a) + var_h(wb, hb, pixel_size_um_b))
    return sd_w, sd_h


def pair_inflation(z, *, cut: float = 2.5, floor: float = 1.0) -> float:
    """How much noisier this pair's changes are than the model says: the robust sd of the
    z-scores of the pairs that look unchanged (iterated: those within ``cut`` x the current
    scale; 1.4826 x the median of |z| about zero), never below ``floor``. The changes that grew
    lie beyond the cut, so they do not steer it while most protrusions are unchanged."""
    z = np.abs(np.asarray(z, float))
    z = z[np.isfinite(z)]
    if z.size < 20:
        return floor
    s = floor
    for _ in range(10):
        sel = z[z < cut * s]
        if sel.size < 10:
            break
        new = max(floor, 1.4826 * float(np.median(sel)) / _truncated_mad(cut))
        if abs(new - s) < 1e-3:
            s = new
            break
        s = new
    return float(s)


def _truncated_mad(cut: float) -> float:
    """The median of |z| of a standard normal truncated at |z| < cut, over the untruncated one."""
    from scipy.stats import norm

    return float(norm.ppf(0.5 + (norm.cdf(cut) - 0.5) / 2) / norm.ppf(0.75))


# ------------------------------------------------------------------------------------------------
# registration
# ------------------------------------------------------------------------------------------------

@dataclass
class Registration:
    """B registered onto A. ``b_to_a`` takes B pixel ``(x=col, y=row, 1)`` to A's."""

    b_to_a: np.ndarray
    model: str                 # similarity | affine | homography
    matches: int               # consistent feature matches (RANSAC inliers of the chosen model)
    candidates: int            # matches passing the ratio test
    rms_px: float              # residual: rms of the tiles' phase-correlation shifts after refinement
    feature_rms_px: float      # rms of the inliers' residuals (feature positions' noise included)
    refinement: str            # "ecc" or why not
    scores: dict = field(default_factory=dict)       # BIC of each model
    tiles: list = field(default_factory=list)        # [x, y, dx, dy] per tile (A pixels)

    @property
    def scale(self) -> float:
        return float(np.sqrt(abs(np.linalg.det(self.b_to_a[:2, :2]))))

    @property
    def rotation_deg(self) -> float:
        return float(np.degrees(np.arctan2(self.b_to_a[1, 0] - self.b_to_a[0, 1],
                                           self.b_to_a[0, 0] + self.b_to_a[1, 1])))

    def to_json(self) -> dict:
        return {"b_to_a": self.b_to_a.tolist(), "model": self.model, "matches": int(self.matches),
                "rms_px": round(float(self.rms_px), 4),
                "frame": "b_to_a takes B pixel (x=col, y=row, 1) to A pixel coordinates",
                "candidates": int(self.candidates), "feature_rms_px": round(float(self.feature_rms_px), 4),
                "refinement": self.refinement, "scale": round(self.scale, 6),
                "rotation_deg": round(self.rotation_deg, 4),
                "model_bic": {k: round(v, 2) for k, v in self.scores.items()},
                "tile_shifts_px": self.tiles}


def _grey(albedo: np.ndarray) -> np.ndarray:
    a = np.asarray(albedo, dtype=np.float32)
    return a.mean(axis=2) if a.ndim == 3 else a


def structure_image(albedo: np.ndarray, *, sigma_px: float = 20.0) -> np.ndarray:
    """The albedo's structure, free of the lamps' smooth errors: high-passed log of the grey albedo
    (float32, robust unit scale; NaN and non-positive pixels set to 0)."""
    g = _grey(albedo)
    ok = np.isfinite(g) & (g > 0)
    floor = float(np.percentile(g[ok], 1)) if ok.any() else 1.0
    lg = np.log(np.where(ok, np.maximum(g, floor), floor)).astype(np.float32)
    hp = lg - cv2.GaussianBlur(lg, (0, 0), sigma_px)
    s = float(np.median(np.abs(hp[ok]))) * 1.4826 if ok.any() else 1.0
    return np.where(ok, hp / (s or 1.0), 0.0).astype(np.float32)


def _to_uint8(img: np.ndarray) -> np.ndarray:
    return np.clip(img * 32.0 + 128.0, 0, 255).astype(np.uint8)


def _apply(T: np.ndarray, xy: np.ndarray) -> np.ndarray:
    h = np.column_stack([xy, np.ones(len(xy))]) @ T.T
    return h[:, :2] / h[:, 2:3]


def _fit(model: str, src: np.ndarray, dst: np.ndarray) -> np.ndarray:
    """Least-squares fit of ``model`` taking ``src`` to ``dst`` (3 x 3)."""
    n = len(src)
    T = np.eye(3)
    if model == "homography":
        H, _ = cv2.findHomography(src.astype(np.float64), dst.astype(np.float64), 0)
        return H / H[2, 2]
    x, y = src[:, 0], src[:, 1]
    if model == "similarity":       # x' = a x - b y + tx, y' = b x + a y + ty
        A = np.zeros((2 * n, 4))
        A[0::2] = np.column_stack([x, -y, np.ones(n), np.zeros(n)])
        A[1::2] = np.column_stack([y, x, np.zeros(n), np.ones(n)])
        p = np.linalg.lstsq(A, dst.reshape(-1), rcond=None)[0]
        T[:2] = [[p[0], -p[1], p[2]], [p[1], p[0], p[3]]]
        return T
    A = np.column_stack([x, y, np.ones(n)])
    T[:2] = np.linalg.lstsq(A, dst, rcond=None)[0].T
    return T


_DOF = {"similarity": 4, "affine": 6, "homography": 8}


def _ransac_inliers(src, dst, ransac_px) -> dict:
    """Each model's RANSAC inliers (OpenCV) among the matches ``src`` -> ``dst``: {model: bool mask}; the
    largest consistent set is the common ground on which the models are then compared."""
    ransac = {}
    _, inl = cv2.estimateAffinePartial2D(src, dst, method=cv2.RANSAC, ransacReprojThreshold=ransac_px,
                                         maxIters=5000, confidence=0.999)
    ransac["similarity"] = inl
    _, inl = cv2.estimateAffine2D(src, dst, method=cv2.RANSAC, ransacReprojThreshold=ransac_px,
                                  maxIters=5000, confidence=0.999)
    ransac["affine"] = inl
    if len(src) >= 8:
        _, inl = cv2.findHomography(src, dst, cv2.RANSAC, ransac_px, maxIters=5000, confidence=0.999)
        ransac["homography"] = inl
    return {k: (v.ravel().astype(bool) if v is not None else np.zeros(len(src), bool)) for k, v in ransac.items()}


def register(albedo_a: np.ndarray, albedo_b: np.ndarray, *, min_matches: int = 25,
             ransac_px: float = 3.0, refine: bool = True, exclude_a: Optional[np.ndarray] = None,
             exclude_b: Optional[np.ndarray] = None, progress: Progress = None) -> Registration:
    """Register B's albedo onto A's.

    Parameters
    ----------
    albedo_a, albedo_b : (M, N) or (M, N, C) arrays
        The two albedos (any linear scale; their smooth shading errors are filtered out).
    min_matches : int
        Fewest RANSAC-consistent feature matches accepted; fewer raise :class:`UVPSInputError`
        (two different regions, or one too changed to be recognised).
    ransac_px : float
        RANSAC's inlier distance (A pixels).
    refine : bool
        ECC refinement to sub-pixel.
    exclude_a, exclude_b : (M, N) bool arrays, optional
        Pixels the refinement leaves out (the protrusions: their albedo carries the lamps'
        shading errors, which differ between the dates).

    Returns
    -------
    Registration

    Notes
    -----
    Features: SIFT (``cv2.SIFT_create``) on the high-passed log albedo (:func:`structure_image`),
    matched B -> A with Lowe's ratio test (0.75). RANSAC (``cv2.estimateAffinePartial2D``,
    ``estimateAffine2D``, ``findHomography``) gives each model's inliers; on the largest
    consistent set each model is refitted by least squares and scored by BIC
    ``n ln(RSS / n) + k ln(n)`` (n = 2 x matches residuals, k its degrees of freedom); the
    lowest wins, so a homography is chosen only when the data need it. ECC (affine or
    homography) on the same structure images then refines it; a similarity is projected back to
    one. ECC runs twice, on the log albedo high-passed at 8 px then at 3 px (measured on synthetic
pairs: the broader the high-pass, the more the two dates' different lamp errors bias it; 0.2 px
at 20 px, 0.04 px at 3 px). ``rms_px``: the phase correlation (:func:`skimage.registration.phase_cross_correlation`,
    1/20 px) of B warped into A against A on a 4 x 4 grid of tiles; the rms of their shifts.
    Cost on 1600 x 1200 px: about 3-5 s (SIFT ~2 s, ECC ~1-2 s).
    """
    sa, sb = structure_image(albedo_a), structure_image(albedo_b)
    report(progress, 0.0, "features")
    sift = cv2.SIFT_create(nfeatures=6000, contrastThreshold=0.02)
    kpa, da = sift.detectAndCompute(_to_uint8(sa), None)
    kpb, db = sift.detectAndCompute(_to_uint8(sb), None)
    if da is None or db is None or len(kpa) < min_matches or len(kpb) < min_matches:
        raise UVPSInputError(f"too few features to register the two captures ({len(kpa)} in A, "
                             f"{len(kpb)} in B; at least {min_matches} needed)")
    report(progress, 0.3, "matching features")
    knn = cv2.FlannBasedMatcher({"algorithm": 1, "trees": 4}, {"checks": 64}).knnMatch(db, da, k=2)
    good = [m[0] for m in knn if len(m) == 2 and m[0].distance < 0.75 * m[1].distance]
    src = np.array([kpb[m.queryIdx].pt for m in good], np.float64).reshape(-1, 2)
    dst = np.array([kpa[m.trainIdx].pt for m in good], np.float64).reshape(-1, 2)
    if len(good) < min_matches:
        raise UVPSInputError(f"too few consistent matches between the two albedos ({len(good)} "
                             f"candidates, at least {min_matches} needed): not captures of one region?")
    ransac = _ransac_inliers(src, dst, ransac_px)
    best = max(ransac, key=lambda k: ransac[k].sum())
    inliers = ransac[best]
    n_in = int(inliers.sum())
    if n_in < min_matches:
        raise UVPSInputError(f"too few consistent matches between the two albedos ({n_in} of "
                             f"{len(good)}; at least {min_matches} needed): not captures of one region?")
    scores, fits = {}, {}
    for model in ransac:
        T = _fit(model, src[inliers], dst[inliers])
        r = _apply(T, src[inliers]) - dst[inliers]
        rss = max(float(np.sum(r * r)), 1e-12)
        n = 2 * n_in
        scores[model] = n * np.log(rss / n) + _DOF[model] * np.log(n)
        fits[model] = T
    model = min(scores, key=scores.get)
    T = fits[model]
    resid = _apply(T, src[inliers]) - dst[inliers]
    feature_rms = float(np.sqrt(np.mean(np.sum(resid ** 2, axis=1))))
    _check_plausible(T, sa.shape, sb.shape)
    refinement = "none"
    if refine:
        report(progress, 0.6, "sub-pixel refinement (ECC)")
        T, refinement = _refine_ecc(albedo_a, albedo_b, T, model, exclude_a, exclude_b)
    report(progress, 0.9, "registration residual")
    rms, tiles = _tile_residual(structure_image(albedo_a, sigma_px=3.0),
                                structure_image(albedo_b, sigma_px=3.0), T)
    reg = Registration(T, model, n_in, len(good), rms, feature_rms, refinement,
                       {k: float(v) for k, v in scores.items()}, tiles)
    log.info("registration: %s, %d matches, rms %.3f px, scale %.4f, rotation %.3f deg", model, n_in,
             rms, reg.scale, reg.rotation_deg)
    return reg


def _check_plausible(T, shape_a, shape_b):
    scale = float(np.sqrt(abs(np.linalg.det(T[:2, :2]))))
    m, n = shape_b
    corners = np.array([[0, 0], [n - 1, 0], [n - 1, m - 1], [0, m - 1]], float)
    quad = _apply(T, corners).astype(np.float32)
    inter, _ = cv2.intersectConvexConvex(quad, np.array([[0, 0], [shape_a[1] - 1, 0],
                                                         [shape_a[1] - 1, shape_a[0] - 1],
                                                         [0, shape_a[0] - 1]], np.float32))
    overlap = inter / float(shape_a[0] * shape_a[1])
    if not (0.25 < scale < 4.0) or overlap < 0.1:
        raise UVPSInputError(f"the matches give no usable alignment (scale {scale:.3g}, overlap "
                             f"{100 * overlap:.0f} % of A): not captures of one region?")


def _refine_ecc(albedo_a, albedo_b, T, model, exclude_a=None, exclude_b=None):
    """ECC on the structure images (high-passed at 8 px, then 3 px), started from ``T``;
    returns (b_to_a, what was done)."""
    motion = cv2.MOTION_HOMOGRAPHY if model == "homography" else cv2.MOTION_AFFINE
    a_to_b = np.linalg.inv(T)
    warp = (a_to_b / a_to_b[2, 2]).astype(np.float32)
    if motion == cv2.MOTION_AFFINE:
        warp = warp[:2].copy()
    shape_a, shape_b = albedo_a.shape[:2], albedo_b.shape[:2]
    mask = _overlap_mask(T, shape_b, shape_a, erode=16)
    if exclude_a is not None:
        mask &= ~exclude_a
    if exclude_b is not None:
        mask &= ~(warp_to_a(exclude_b.astype(np.uint8), T, shape_a, interpolation=cv2.INTER_NEAREST) > 0)
    crit = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 100, 1e-6)
    try:
        for sigma in (8.0, 3.0):
            cc, warp = cv2.findTransformECC(structure_image(albedo_a, sigma_px=sigma),
                                            structure_image(albedo_b, sigma_px=sigma), warp, motion,
                                            crit, mask.astype(np.uint8), 1)
    except cv2.error as exc:
        log.warning("ECC refinement failed (%s); the feature estimate is kept", str(exc).splitlines()[-1])
        return T, "ecc failed; feature estimate kept"
    full = np.eye(3)
    full[:warp.shape[0]] = warp
    out = np.linalg.inv(full)
    if model == "similarity":
        a = (out[0, 0] + out[1, 1]) / 2
        b = (out[1, 0] - out[0, 1]) / 2
        out[:2, :2] = [[a, -b], [b, a]]
    corners = np.array([[0.0, 0.0], [shape_b[1], shape_b[0]]])
    step = float(np.max(np.abs(_apply(out, corners) - _apply(T, corners))))
    if step > 5.0:      # ECC wandered off: keep the features' answer
        log.warning("ECC moved the corners by %.1f px; the feature estimate is kept", step)
        return T, f"ecc moved {step:.1f} px; feature estimate kept"
    return out / out[2, 2], f"ecc (correlation {cc:.3f})"


def _overlap_mask(T, shape_b, shape_a, *, erode=0) -> np.ndarray:
    """A's pixels (M_a, N_a) that ``T`` (B -> A) covers with B's field, eroded by ``erode`` px."""
    ones = np.full(shape_b, 255, np.uint8)
    m = warp_to_a(ones, T, shape_a, interpolation=cv2.INTER_NEAREST) > 0
    if erode:
        m = ndimage.binary_erosion(m, iterations=erode)
    return m


def warp_to_a(image: np.ndarray, b_to_a: np.ndarray, shape_a, *, interpolation=cv2.INTER_CUBIC,
              fill=0.0) -> np.ndarray:
    """B's ``image`` (M_b, N_b) resampled in A's frame (M_a, N_a); ``fill`` outside B's field."""
    dsize = (int(shape_a[1]), int(shape_a[0]))
    img = np.ascontiguousarray(image)
    if np.allclose(b_to_a[2], [0, 0, 1]):
        return cv2.warpAffine(img, b_to_a[:2].astype(np.float64), dsize, flags=interpolation,
                              borderMode=cv2.BORDER_CONSTANT, borderValue=fill)
    return cv2.warpPerspective(img, b_to_a.astype(np.float64), dsize, flags=interpolation,
                               borderMode=cv2.BORDER_CONSTANT, borderValue=fill)


def _tile_residual(sa, sb, T, grid=4):
    warped = warp_to_a(sb, T, sa.shape, interpolation=cv2.INTER_CUBIC)
    valid = _overlap_mask(T, sb.shape, sa.shape, erode=4)
    m, n = sa.shape
    tiles = []
    for i in range(grid):
        for j in range(grid):
            r0, r1 = i * m // grid, (i + 1) * m // grid
            c0, c1 = j * n // grid, (j + 1) * n // grid
            if valid[r0:r1, c0:c1].mean() < 0.98:
                continue
            shift, _, _ = phase_cross_correlation(sa[r0:r1, c0:c1], warped[r0:r1, c0:c1],
                                                  upsample_factor=20, normalization=None)
            # shift (rows, cols) that moves the warped tile onto A's
            tiles.append([round((c0 + c1 - 1) / 2, 1), round((r0 + r1 - 1) / 2, 1),
                          round(float(-shift[1]), 3), round(float(-shift[0]), 3)])
    if not tiles:
        return float("nan"), []
    d = np.array([t[2:] for t in tiles])
    return float(np.sqrt(np.mean(np.sum(d * d, axis=1)))), tiles


# ------------------------------------------------------------------------------------------------
# heights: into A's frame, levelled
# ------------------------------------------------------------------------------------------------

@dataclass
class Levelling:
    """The height difference B - A in A's frame after removing the smooth difference."""

    change_um: np.ndarray        # (M, N) float32, NaN outside the common field
    smooth_um: np.ndarray        # (M, N) float32, the smooth difference removed (NaN outside)
    height_scale: float          # B's relief / A's on the common relief (B's heights divided by it)
    diagnostics: dict


def _block_median(values, valid, block):
    m, n = values.shape
    gm, gn = -(-m // block), -(-n // block)
    med = np.full((gm, gn), np.nan)
    for i in range(gm):
        for j in range(gn):
            v = values[i * block:(i + 1) * block, j * block:(j + 1) * block]
            ok = valid[i * block:(i + 1) * block, j * block:(j + 1) * block]
            if ok.sum() >= 0.25 * ok.size:
                med[i, j] = np.median(v[ok])
    return med


def _smooth_field(values, valid, block):
    """A smooth surface through ``values`` over ``valid``: block medians, gaps filled and smoothed
    by normalised convolution, resized to the full grid (bilinear)."""
    med = _block_median(values, valid, block)
    w = np.isfinite(med).astype(float)
    if w.sum() == 0:
        return np.zeros(values.shape, np.float32)
    num = ndimage.gaussian_filter(np.nan_to_num(med), 1.0, mode="nearest")
    den = ndimage.gaussian_filter(w, 1.0, mode="nearest")
    far = den < 1e-3
    if far.any():   # blocks far from any data: the nearest smoothed value
        idx = ndimage.distance_transform_edt(far, return_distances=False, return_indices=True)
        num, den = num[tuple(idx)], den[tuple(idx)]
    grid = (num / den).astype(np.float32)
    m, n = values.shape
    big = cv2.resize(grid, (grid.shape[1] * block, grid.shape[0] * block), interpolation=cv2.INTER_LINEAR)
    return big[:m, :n]


def _without_form(height, where):
    """``height`` minus its field-scale form fitted over ``where`` (:func:`uvps.core.level.fit_surface`)."""
    h = np.asarray(height, np.float32)
    return h - legendre_surface(fit_surface(np.where(where, h, np.nan), degree=FORM_DEGREE), h.shape)


def level_heights(height_a, height_b_in_a, valid, off_protrusions, *, block_px: int,
                  match_scale: bool = True) -> Levelling:
    """Level B's height (in A's frame) against A's.

    The smooth difference is :func:`_smooth_field` of ``B - A`` over the valid pixels off the
    protrusions (block medians of ``block_px``), removed. The heights' scales are matched by a
    robust slope through the origin of B's relief against A's (both high-passed the same way;
    Tukey-reweighted, so protrusions that changed do not steer it). Returns the change map
    ``B / scale - A - smooth`` in um.

    Each date's field-scale form (a 2-D Legendre polynomial of degree
    :data:`uvps.core.level.FORM_DEGREE`, robust, off the protrusions) is removed first: the block grid's
    smoothing flattens a ramp near its borders (a 3.3 um/mm plane left 0.4 um over a 6 x 8 mm field), so
    a date levelled and one not (``run --level``, older run folders) would differ by that much.
    """
    ha = _without_form(height_a, valid & off_protrusions)
    hb = _without_form(height_b_in_a, valid & off_protrusions)
    ha = np.where(valid, ha, 0.0).astype(np.float32)
    hb = np.where(valid, hb, 0.0).astype(np.float32)
    scale = 1.0
    if match_scale:
        ra = ha - _smooth_field(ha, valid, block_px)
        rb = hb - _smooth_field(hb, valid, block_px)
        x, y = ra[valid].astype(np.float64), rb[valid].astype(np.float64)
        step = max(1, x.size // 400000)
        x, y = x[::step], y[::step]
        for _ in range(8):
            r = y - scale * x
            s = 1.4826 * np.median(np.abs(r)) + 1e-9
            wgt = np.clip(1 - (r / (4.685 * s)) ** 2, 0, None) ** 2
            scale = float(np.sum(wgt * x * y) / max(np.sum(wgt * x * x), 1e-12))
        if not 0.5 < scale < 2.0:
            raise UVPSInputError(f"the two dates' relief does not match (B / A height scale {scale:.3g}, 0.5-2 "
                                 "expected): check that both runs show the same region, and give both the same "
                                 "measured lamp positions (uvps run --lights) so that their heights share a scale")
    diff = hb / scale - ha
    smooth = _smooth_field(diff, valid & off_protrusions, block_px)
    change = np.where(valid, diff - smooth, np.nan).astype(np.float32)
    smooth_out = np.where(valid, smooth, np.nan).astype(np.float32)
    sv = smooth[valid]
    diag = {"height_scale_b_over_a": round(scale, 5), "block_px": int(block_px),
            "smooth_difference_um": {"p2": round(float(np.percentile(sv, 2)), 3),
                                     "p98": round(float(np.percentile(sv, 98)), 3),
                                     "rms": round(float(np.sqrt(np.mean(sv ** 2))), 3)},
            "change_rms_off_protrusions_um": round(float(np.sqrt(np.nanmean(
                change[valid & off_protrusions] ** 2))), 3)}
    return Levelling(change, smooth_out, scale, diag)


# ------------------------------------------------------------------------------------------------
# matching and status
# ------------------------------------------------------------------------------------------------

def _inside(xy, shape, margin):
    m, n = shape
    return ((xy[:, 0] >= margin) & (xy[:, 0] <= n - 1 - margin)
            & (xy[:, 1] >= margin) & (xy[:, 1] <= m - 1 - margin))


def _seen_whole(x, x_other, w, shape, shape_other, px, px_other):
    """Indices of the protrusions at ``x`` (px, this date), ``w`` um wide, that lie whole inside this
    date's frame and, mapped to ``x_other``, the other's (two pixels to spare)."""
    r = 0.5 * np.nan_to_num(w)
    return np.flatnonzero(_inside(x_other, shape_other, r / px_other + 2) & _inside(x, shape, r / px + 2))


def classify_changes(table_a: dict, table_b: dict, b_to_a: np.ndarray, *, shape_a, shape_b,
                     pixel_size_um: float, pixel_size_um_b: Optional[float] = None, height_scale: float = 1.0,
                     sigma_factor: float = 4.5, match_radius_um: Optional[float] = None,
                     regions_a: Optional[np.ndarray] = None, change_um: Optional[np.ndarray] = None,
                     off_protrusions: Optional[np.ndarray] = None, model: NoiseModel = NOISE_MODEL,
                     heights: bool = True, adapt: bool = True):
    """Match two protrusion tables across dates and give each protrusion its status.

    Parameters
    ----------
    table_a, table_b : dict
        Protrusion tables (``x_px``, ``y_px``, ``width_um``, ``height_um``) of A and B, each in
        its own pixel frame.
    b_to_a : (3, 3) array
    shape_a, shape_b : (M, N)
    pixel_size_um : float
        A's pixel size (the matching radius is in A's frame).
    pixel_size_um_b : float, optional
        B's (default: A's x the registration's scale).
    height_scale : float
        B's heights are divided by it (the levelling's relief scale).
    sigma_factor : float
        A pair is ``grown`` (``shrunk``) when its width or height changed by more than
        ``sigma_factor`` x its standard uncertainty (:func:`change_uncertainty`, times the pair's
        :func:`pair_inflation`).
    regions_a : (M, N) int array, optional
        A's colour areas: the ``region`` column.
    change_um : (M, N) array, optional
        The levelled height change in A's frame: its robust sd around each protrusion (off the
        protrusions, ``off_protrusions``) is the height model's surface noise, and a protrusion
        found at one date only stays ``new`` / ``gone`` only when the change over it says so
        (:func:`_confirm_unmatched`).
    model : NoiseModel
    heights : bool
        False: heights are not compared (a relative relief): the height columns stay empty and
        the status rests on the widths.
    adapt : bool
        Scale the uncertainties by :func:`pair_inflation` (never below the model).

    Returns
    -------
    rows : dict of columns :data:`COLUMNS`; positions in A's frame (P, 2); counts of protrusions
    left out (outside the common field); and a dict of the uncertainty's diagnostics.

    Notes
    -----
    One-to-one matching first (:func:`uvps.core.compare.match_protrusions`). Then neighbours that merged
    or split: a protrusion of A left without a partner whose centre lies inside (within half the
    width of) a B protrusion matched to another of A's merged into it (``merged``, both rows
    carrying that B's id); a B protrusion left without a partner inside an A protrusion matched
    to another of B's split from it (``split``). What is still alone is ``new`` or ``gone``.
    """
    xa = np.column_stack([table_a["x_px"], table_a["y_px"]]).astype(float).reshape(-1, 2)
    xb = np.column_stack([table_b["x_px"], table_b["y_px"]]).astype(float).reshape(-1, 2)
    wa, wb = np.asarray(table_a["width_um"], float), np.asarray(table_b["width_um"], float)
    ha = np.asarray(table_a.get("height_um", np.full(len(wa), np.nan)), float)
    hb = np.asarray(table_b.get("height_um", np.full(len(wb), np.nan)), float) / height_scale
    if not heights:
        ha, hb = np.full(len(wa), np.nan), np.full(len(wb), np.nan)
    a_to_b = np.linalg.inv(b_to_a)
    xa_in_b = _apply(a_to_b, xa) if len(xa) else xa
    xb_in_a = _apply(b_to_a, xb) if len(xb) else xb
    px_b = (pixel_size_um * float(np.sqrt(abs(np.linalg.det(b_to_a[:2, :2]))))
            if pixel_size_um_b is None else float(pixel_size_um_b))
    # only where both dates see the protrusion whole (a protrusion cut by either frame has its
    # centre and width biased at that date)
    ia = _seen_whole(xa, xa_in_b, wa, shape_a, shape_b, pixel_size_um, px_b)
    ib = _seen_whole(xb, xb_in_a, wb, shape_b, shape_a, px_b, pixel_size_um)
    pairs, _ = match_protrusions(xa[ia], np.nan_to_num(wa[ia]), xb_in_a[ib], np.nan_to_num(wb[ib]),
                                 pixel_size_um=pixel_size_um, match_radius_um=match_radius_um)
    pa, pb = ia[pairs[:, 0]], ib[pairs[:, 1]]
    gone = np.setdiff1d(ia, pa)
    new = np.setdiff1d(ib, pb)
    ra, rb, kind, gone, new = _regroup(pa, pb, gone, new, xa, xb_in_a, wa, wb, pixel_size_um)
    n_m, n_g, n_n = len(ra), len(gone), len(new)
    n_rows = n_m + n_g + n_n
    rows = _row_columns(table_a["id"], table_b["id"], (xa, wa, ha), (xb, wb, hb), ra, rb, gone, new)
    # position in A's frame of every row (B's mapped for new ones): the region, the figures
    pos = np.concatenate([xa[ra], xa[gone], xb_in_a[new]]).reshape(-1, 2)
    widths = np.where(np.isfinite(rows["width_um_a"]), rows["width_um_a"], rows["width_um_b"])
    surface = (_local_noise(change_um, pos, widths, pixel_size_um, off_protrusions)
               if change_um is not None else np.zeros(n_rows))
    sd_w, sd_h = change_uncertainty(rows["width_um_a"], rows["width_um_b"], rows["height_um_a"],
                                    rows["height_um_b"], pixel_size_um_a=pixel_size_um, pixel_size_um_b=px_b,
                                    surface_um=surface, model=model)
    zw, zh = rows["d_width_um"] / sd_w, rows["d_height_um"] / sd_h
    paired = np.zeros(n_rows, bool)
    paired[:n_m] = kind == "pair"
    infl_w = pair_inflation(zw[paired]) if adapt else 1.0
    infl_h = pair_inflation(zh[paired]) if adapt and heights else 1.0
    sd_w, sd_h = sd_w * infl_w, sd_h * infl_h
    zw, zh = rows["d_width_um"] / sd_w, rows["d_height_um"] / sd_h
    rows["surface_noise_um"] = surface       # not a column: the fit of the model reads it
    rows["d_width_sd_um"] = np.where(np.isfinite(rows["d_width_um"]), sd_w, np.nan)
    rows["d_height_sd_um"] = np.where(np.isfinite(rows["d_height_um"]), sd_h, np.nan)
    zw0, zh0 = np.nan_to_num(zw), np.nan_to_num(zh)
    rows["significance"] = np.where(np.isfinite(zw) | np.isfinite(zh), np.maximum(np.abs(zw0), np.abs(zh0)), np.nan)
    rows["status"] = _status(zw0, zh0, kind, n_g, sigma_factor)
    rows["region"] = _region_at(regions_a, pos)
    if change_um is not None and heights:
        _confirm_unmatched(rows, pos, change_um, pixel_size_um)
    order = np.lexsort((pos[:, 0], pos[:, 1])) if n_rows else np.zeros(0, int)
    rows = {k: v[order] for k, v in rows.items()}
    left_out = {"a": int(len(xa) - len(ia)), "b": int(len(xb) - len(ib))}
    surf = surface[paired] if n_rows else np.zeros(0)
    uncertainty = {"inflation_width": round(infl_w, 4), "inflation_height": round(infl_h, 4),
                   "surface_noise_um_median": round(float(np.median(surf)), 4) if surf.size else None,
                   "model": dataclasses.asdict(model), "sigma_factor": sigma_factor, "heights": bool(heights)}
    return rows, pos[order], left_out, uncertainty


class _Regrouped(NamedTuple):
    ra: np.ndarray      # A's row of each pair, merged or split row
    rb: np.ndarray      # B's
    kind: np.ndarray    # "pair", "merged" or "split"
    gone: np.ndarray    # A's protrusions still alone
    new: np.ndarray     # B's


def _regroup(pa, pb, gone, new, xa, xb_in_a, wa, wb, pixel_size_um: float) -> _Regrouped:
    """The one-to-one pairs ``pa``/``pb`` and the protrusions left alone, regrouped: an A protrusion
    alone inside a matched B one merged into it; a B one alone inside a matched A one split from it."""
    rad_b = 0.5 * np.nan_to_num(wb) / pixel_size_um        # B's radius in A pixels
    rad_a = 0.5 * np.nan_to_num(wa) / pixel_size_um
    merged_into = _inside_partner(gone, pb, xa, xb_in_a, rad_b)
    split_from = _inside_partner(new, pa, xb_in_a, xa, rad_a)
    ga = np.array(sorted(merged_into), int)
    gb = np.array([merged_into[g] for g in ga], int)
    sb = np.array(sorted(split_from), int)
    sa = np.array([split_from[j] for j in sb], int)
    gone = np.setdiff1d(gone, ga)
    new = np.setdiff1d(new, sb)
    # the rows: pairs, merged, split, gone, new
    ra = np.concatenate([pa, ga, sa]).astype(int)
    rb = np.concatenate([pb, gb, sb]).astype(int)
    kind = np.array(["pair"] * len(pa) + ["merged"] * len(ga) + ["split"] * len(sa), dtype="<U9")
    merged_b = set(gb.tolist())
    split_a = set(sa.tolist())
    kind[:len(pa)] = np.where(np.isin(pb, list(merged_b)), "merged",
                              np.where(np.isin(pa, list(split_a)), "split", "pair"))
    return _Regrouped(ra, rb, kind, gone, new)


def _inside_partner(alone, partners, x_alone, x_partners, radius) -> dict:
    """For each protrusion in ``alone`` (indices into ``x_alone``), the nearest of ``partners``
    (indices into ``x_partners``, ``radius`` each, all in A's pixels) whose disc holds its centre."""
    out = {}
    for g in alone:
        d = np.hypot(*(x_partners[partners] - x_alone[g]).T) if len(partners) else np.zeros(0)
        inside = np.flatnonzero(d <= radius[partners])
        if inside.size:
            out[int(g)] = int(partners[inside[np.argmin(d[inside])]])
    return out


def _row_columns(ids_a, ids_b, a: tuple, b: tuple, ra, rb, gone, new) -> dict:
    """The columns of ``changes.csv`` from both tables: the rows ``ra``/``rb`` (pairs, merged, split),
    then A's ``gone``, then B's ``new``; ``a``, ``b``: (positions (P, 2), widths, heights)."""
    (xa, wa, ha), (xb, wb, hb) = a, b
    n_g, n_n = len(gone), len(new)
    nan = np.full(len(ra) + n_g + n_n, np.nan)

    def col(va, vb):
        return (np.concatenate([va[ra], va[gone], nan[:n_n]]), np.concatenate([vb[rb], nan[:n_g], vb[new]]))

    rows = {"id_a": np.concatenate([np.asarray(ids_a)[ra], np.asarray(ids_a)[gone],
                                    np.zeros(n_n, int)]).astype(int),
            "id_b": np.concatenate([np.asarray(ids_b)[rb], np.zeros(n_g, int),
                                    np.asarray(ids_b)[new]]).astype(int)}
    rows["x_px_a"], rows["x_px_b"] = col(xa[:, 0], xb[:, 0])
    rows["y_px_a"], rows["y_px_b"] = col(xa[:, 1], xb[:, 1])
    rows["width_um_a"], rows["width_um_b"] = col(wa, wb)
    rows["height_um_a"], rows["height_um_b"] = col(ha, hb)
    rows["d_width_um"] = rows["width_um_b"] - rows["width_um_a"]
    rows["d_height_um"] = rows["height_um_b"] - rows["height_um_a"]
    return rows


def _status(zw0, zh0, kind, n_g: int, sigma_factor: float) -> np.ndarray:
    """Each row's status: a pair by its larger significant change (grown, shrunk, unchanged), the
    merged and split ones as ``kind`` says, then ``n_g`` gone and the rest new."""
    n_m = len(kind)
    up = (zw0 > sigma_factor) | (zh0 > sigma_factor)
    down = (zw0 < -sigma_factor) | (zh0 < -sigma_factor)
    zmax = np.where(np.abs(zw0) >= np.abs(zh0), zw0, zh0)
    status = np.where(up & ~down, "grown", np.where(down & ~up, "shrunk", "unchanged")).astype("<U9")
    both = up & down
    status[both] = np.where(zmax[both] > 0, "grown", "shrunk")
    status[:n_m] = np.where(kind == "pair", status[:n_m], kind)
    status[n_m:n_m + n_g] = "gone"
    status[n_m + n_g:] = "new"
    return status


def _region_at(regions_a, pos) -> np.ndarray:
    """A's colour area under each position (x, y in A's pixels), 0 without areas."""
    if regions_a is None or not len(pos):
        return np.zeros(len(pos), int)
    r = np.clip(np.rint(pos[:, 1]).astype(int), 0, regions_a.shape[0] - 1)
    c = np.clip(np.rint(pos[:, 0]).astype(int), 0, regions_a.shape[1] - 1)
    return regions_a[r, c].astype(int)


def _local_noise(change_um, pos, widths, px, off_protrusions=None) -> np.ndarray:
    """The robust sd (1.4826 MAD) of the levelled height change around each position: a square of
    half-side max(2 widths, 0.5 mm) off the protrusions (``off_protrusions``); NaN -> 0."""
    m, n = change_um.shape
    out = np.zeros(len(pos))
    for i, ((x, y), w) in enumerate(zip(pos, widths)):
        r = int(max(2.0 * np.nan_to_num(w), 500.0) / px)
        r0, r1 = max(int(y) - r, 0), min(int(y) + r + 1, m)
        c0, c1 = max(int(x) - r, 0), min(int(x) + r + 1, n)
        if r0 >= r1 or c0 >= c1:
            continue
        v = change_um[r0:r1, c0:c1]
        ok = np.isfinite(v)
        if off_protrusions is not None:
            ok &= off_protrusions[r0:r1, c0:c1]
        if ok.sum() >= 16:
            v = v[ok]
            out[i] = 1.4826 * float(np.median(np.abs(v - np.median(v))))
    return out


def _confirm_unmatched(rows, pos, change_um, px):
    """A protrusion found at one date only is ``new`` (``gone``) only if the height change over its
    centre (a disc of a quarter of its width) is at least half its height (minus half its height):
    else its relief is there at both dates and only one detection missed it, and it is
    ``unchanged`` with the other date's fields empty. In place."""
    m, n = change_um.shape
    for i, s in enumerate(rows["status"]):
        if s not in ("new", "gone"):
            continue
        w = rows["width_um_b"][i] if s == "new" else rows["width_um_a"][i]
        h = rows["height_um_b"][i] if s == "new" else rows["height_um_a"][i]
        if not (np.isfinite(w) and np.isfinite(h) and h > 0):
            continue
        r = max(1.0, 0.25 * w / px)
        x, y = pos[i]
        r0, r1 = max(int(y - r), 0), min(int(y + r) + 1, m)
        c0, c1 = max(int(x - r), 0), min(int(x + r) + 1, n)
        if r0 >= r1 or c0 >= c1:
            continue
        yy, xx = np.mgrid[r0:r1, c0:c1]
        disc = change_um[r0:r1, c0:c1][(yy - y) ** 2 + (xx - x) ** 2 <= r * r]
        disc = disc[np.isfinite(disc)]
        if disc.size == 0:
            continue
        d = float(np.mean(disc))
        if (s == "new" and d < 0.5 * h) or (s == "gone" and d > -0.5 * h):
            rows["status"][i] = "unchanged"


def area_table(rows: dict, regions_a, names: dict, common: np.ndarray, pixel_size_um: float,
               bins_um=100.0) -> list:
    """Per colour area of A (then "all"): area of the common field, counts by status, new per
    cm^2, and by width class (A's width; B's for new ones) the matched and grown counts."""
    widths = np.where(np.isfinite(rows["width_um_a"]), rows["width_um_a"], rows["width_um_b"])
    edges = bin_edges(bins_um, float(np.nanmax(widths)) if len(widths) else 100.0)
    classes = bin_names(edges)
    ids = sorted(set(np.unique(regions_a[common]).tolist()) - {0}) if regions_a is not None else []
    out = []
    for label in ids + ["all"]:
        sel = np.ones(len(widths), bool) if label == "all" else rows["region"] == label
        area_px = int(common.sum()) if label == "all" else int((common & (regions_a == label)).sum())
        area_cm2 = area_px * pixel_size_um ** 2 / UM2_PER_CM2
        row = {"label": label, "name": "all" if label == "all" else names.get(label, str(label)),
               "area_cm2": round(area_cm2, 5)}
        for s in STATUSES:
            row[s] = int(np.sum(sel & (rows["status"] == s)))
        row["new_per_cm2"] = round(row["new"] / area_cm2, 3) if area_cm2 > 0 else None
        k = np.clip(np.searchsorted(edges, np.nan_to_num(widths), side="right") - 1, 0, len(classes) - 1)
        matched = sel & np.isin(rows["status"], ("grown", "shrunk", "unchanged"))
        row["grown_by_width"] = {cls: [int(np.sum(matched & (k == i) & (rows["status"] == "grown"))),
                                       int(np.sum(matched & (k == i)))] for i, cls in enumerate(classes)}
        out.append(row)
    return out


# ------------------------------------------------------------------------------------------------
# the report
# ------------------------------------------------------------------------------------------------

#: Colour and marker of each status in the figures (colour-blind-safe where it matters: grown red,
#: new green filled, gone blue dashed, unchanged grey).
