"""Lamp directions and positions from spheres photographed under every lamp (``uvps calibrate``).

A sphere of known shape pins what the painting cannot: each lamp's direction at the sphere, and, from
two or more spheres, its 3-D position (the bas-relief ambiguity of a sphere-free run is then gone).

- **Matte white sphere**: every pixel of the disc has a known normal, so its shading is
  ``I = n . b + c`` with ``b = rho E_k l_k`` (Lambert; ``c`` the additive term: black level, stray
  light). ``b`` and ``c`` are one linear least squares over the lit, unsaturated part of the disc,
  trimmed of what does not follow the model (a stand hiding part of the sphere, specks, the
  terminator): ``l_k = b / |b|``. It holds behind a UV-blocking filter (the sphere's own
  fluorescence or the visible light reflected by it are both Lambertian enough).
- **Mirror (chrome) sphere**: the lamp's own small image, usually saturated with a flare star
  around it: the centre of its saturated core (:func:`_fit_mirror`: the core's median normal, or for
  a core of a few pixels the mean with its edge's partly lit pixels weighted by how lit they are),
  its flare spikes and a scratch's streak opened off; what every image shows (a window, a lit object
  the sphere reflects) is not the highlight (:func:`_static_part`).
- **Glossy black sphere**: the lamp's mirror highlight. Its centre is the intensity-weighted mean
  of the normals under the highlight, weighted per unit of solid angle (``1 / n_z`` per pixel), so
  the foreshortening near the limb does not pull it; a saturated highlight counts as a disc, and thin
  flare spikes are opened away first. ``l = 2 (n . v) n - v`` from the highlight's surface point, ``v``
  the view: (0, 0, 1) for an orthographic camera (the default), or toward a pinhole camera's centre
  ``camera_distance_mm`` above the image centre (:mod:`uvps.core.sphere_view`: each pixel's normal is
  then where its ray meets the sphere, for matte spheres too; a sphere off the lens's axis read
  orthographically is about its off-axis angle off, decisions/spheres.md).

Each sphere gives each lamp a ray (a point in mm and a direction). One sphere gives far-light
directions (the RTI case); two or more give the lamp's position as the point closest to every ray
(weighted least squares, each ray weighted by its direction's uncertainty times its length), with
its covariance.

Spheres are found by circle detection (OpenCV's gradient Hough transform, ``HOUGH_GRADIENT_ALT``,
on a reduced maximum projection of the capture), their rims then located along 720 rays at full
resolution and fitted by a RANSAC circle (``skimage.measure.ransac``): a stand, a flare spike or a
highlight crossing the rim are outliers. A dark sphere on a dark ground is sought in the logarithm of
the mean and the median too, and when the Hough transform proposes nothing, by a RANSAC circle on
their edge points (:func:`_ransac_circle`). A circle cut by the frame is left out (all of them: the
capture is refused). The kind (matte, glossy, mirror) is told from the images (:func:`_kind_of`) or
given. Each candidate must then behave as a sphere (a highlight in every image, or a shading that
Lambert's law fits). A wrong or missed detection is overridden by given circles
(:func:`read_sphere_circles`, ``--sphere-circles``).

Frames follow docs/architecture.md: pixel centre ``(r, c)`` at ``X = (c - (N - 1) / 2) px``,
``Y = ((M - 1) / 2 - r) px`` (mm); a sphere's normal at ``(r, c)`` is
``((c - c0) / R, (r0 - r) / R, n_z)``. Each sphere is taken to rest on the plane of the painting
(its centre one radius above z = 0): a sphere on a taller stand puts the lamps' positions that much
too low (a few mm in 300).

References
----------
Woodham, R. J. (1980), photometric stereo with a calibration sphere; Mudge, M. et al. (2006),
highlight RTI with reflective spheres; relight (cnr-isti-vclab) computes 3-D lamps from two or more
spheres the same way (intersection of the reflected rays).
"""
from __future__ import annotations

import csv
import logging
import math
import os
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from typing import Optional, Sequence

import numba
import numpy as np
from scipy import ndimage

from ..errors import UVPSInputError
from .progress import Progress, report
from .sphere_find import (DETECT_LONG_SIDE, MIN_RADIUS_PX, MIN_RADIUS_RATIO,  # noqa: F401 (re-exported)
                          MIN_RIM_FRACTION, RANSAC_RIM_FRACTION, REFERENCE_RIM_FRACTION, Sphere,
                          _crop_box, _grey, _mean_image, _median_over_images, _projections,
                          _refine_circle, _to8, detect_spheres)
from .sphere_view import pixel_normals, sphere_from_outline, view_at

log = logging.getLogger(__name__)

__all__ = ["Sphere", "SphereFit", "LampCalibration", "detect_spheres", "read_sphere_circles", "fit_sphere",
           "triangulate", "calibrate_spheres"]

KINDS = ("matte", "glossy", "mirror")
#: A specular sphere whose highlight's core (its saturated samples, or those above half its peak when
#: none saturates) is under this angular radius in the sphere's normals is a mirror (a chrome or
#: steel ball: the lamp's own image, 0.5-2 deg); above it a glossy sphere's lobe (a black ball's
#: polish spreads it: 3-10 deg). The PSBox mirror sphere's saturated cores: 0.9-1.4 deg.
MIRROR_CORE_DEG = 2.5
#: A highlight's samples at or above this fraction of the saturation level are its saturated core.
SATURATED_CORE = 0.955
#: A saturated core under this many pixels is placed with its edge's partly lit pixels (:func:`_fit_mirror`).
SMALL_CORE_PX = 200
#: Matte fit: samples with a predicted ``n . l`` below this are left out (the terminator, where the
#: attached shadow's clip and a lamp's finite size bend the law).
MATTE_MIN_COS = 0.2
#: Matte fit: the near lamp's and the beam's terms (:func:`_near_column`, :func:`_beam_columns`) are
#: first-order corrections, each at most this fraction of ``|b|`` (a lamp ~7 radii away; a beam whose
#: gain changes by 15 % per radius across the sphere). A fit that needs more has taken something else
#: for them (a ball's veins or sheen under a lamp near the view, which lights the whole disc: the
#: offset, ``b_z`` and the near term are then all nearly functions of ``n_z``), and :func:`_fit_matte`
#: fits ``n . b + c`` alone. Without this bound the UW/Seitz grey ball's per-lamp fits did not settle
#: (beam terms up to 1.2 ``|b|``; decisions/spheres.md).
MATTE_TERM_MAX = 0.15
#: A matte sphere's additive term (black level, the room's light) is read in its attached shadow: the
#: samples whose ``n . l`` under a lamp's first fit is below ``-MATTE_SHADOW_COS`` (clear of the
#: terminator's penumbra), where a lamp shows at least :data:`MATTE_SHADOW_MIN` of the disc's samples.
MATTE_SHADOW_COS = 0.1
MATTE_SHADOW_MIN = 0.01
#: ... and is held in the fits only where the lamps that show their terminator best fit their lit
#: part with it within this fraction of ``|b|`` (:func:`_shadow_offsets`: where holding it stops
#: helping on rendered rough balls).
MATTE_SHADOW_AGREE = 0.05
#: A matte sphere's circle and gain (:func:`_refine_matte_circle`) are fitted on this many of its
#: samples in all, shared among the lamps.
MATTE_CIRCLE_SAMPLES = 60000
#: The shading moves a matte sphere's circle by at most this fraction of its radius.
MATTE_CIRCLE_MOVE = 0.03
#: ... and when its fit runs to those bounds, the rim is kept (:func:`_refine_matte_circle`).
MATTE_KEEP_RIM = True
#: ... and each lamp's beam terms join that fit (:func:`_beams_significant`) where they explain the
#: shading beyond its noise at this significance (the F test of the two nested least squares).
MATTE_BEAM_P = 1e-3
#: ... and where, with them, the shading is Lambert's to within this factor of its noise's variance
#: (:func:`_picks_noise`): a rough ball's flatter shading is not a beam. The robustness benchmark's beams
#: 1.09-1.13; rendered Oren-Nayar balls 1.07 (0.1 rad, 25.8 F) and 1.66 (0.2 rad, there 7.4 deg off with them).
MATTE_BEAM_FIT = 1.25
#: Terms of the gain across a matte sphere's disc (:func:`_gain`: to third order).
GAIN_TERMS = 9
#: Relative position uncertainty above which two or more spheres are said not to give positions
#: (the rays are too nearly parallel: far lamps, or spheres too close together).
MAX_DISTANCE_UNCERTAINTY = 0.25


@dataclass
class SphereFit:
    """One sphere under every lamp: a ray per lamp.

    Attributes
    ----------
    sphere : Sphere
        With its kind decided.
    points_mm : (K, 3)
        Where each ray starts: the sphere's centre (matte) or the highlight's surface point (glossy).
    directions : (K, 3)
        Unit vectors toward each lamp.
    sigma_deg : (K,)
        Standard uncertainty of each direction.
    strength : (K,)
        Matte: ``|b|`` (counts per unit ``n . l``); glossy: the highlight's peak above the sphere.
    n_pixels : (K,)
        Samples used.
    residual : (K,)
        Matte: rms residual over ``|b|``; glossy: 0.
    """

    sphere: Sphere
    points_mm: np.ndarray
    directions: np.ndarray
    sigma_deg: np.ndarray
    strength: np.ndarray
    n_pixels: np.ndarray
    residual: np.ndarray


@dataclass
class LampCalibration:
    """The lamps from a sphere capture.

    ``positions_mm`` (K, 3) and ``position_sigma_mm`` (K, 3) when two or more spheres pin them,
    else None; ``directions`` (K, 3) from the image centre toward each lamp (``positions / |positions|``,
    or the spheres' mean direction); ``direction_sigma_deg`` (K,); ``distance_sigma_pct`` (K,) the
    position's uncertainty along the line of sight, over the distance; ``ray_miss_mm`` (K,) how far the
    rays pass from the position (rms); ``diagnostics`` what a reader checks.
    """

    directions: np.ndarray
    direction_sigma_deg: np.ndarray
    fits: list
    positions_mm: Optional[np.ndarray] = None
    position_sigma_mm: Optional[np.ndarray] = None
    distance_sigma_pct: Optional[np.ndarray] = None
    ray_miss_mm: Optional[np.ndarray] = None
    diagnostics: dict = field(default_factory=dict)

    @property
    def spheres(self) -> list:
        return [f.sphere for f in self.fits]

    def lamps_json(self) -> list:
        """One dict per lamp: direction, position (or None) and their uncertainties."""
        out = []
        for k, d in enumerate(self.directions):
            lamp = {"direction": [float(v) for v in d],
                    "direction_sigma_deg": float(self.direction_sigma_deg[k]),
                    "position_mm": None, "position_sigma_mm": None, "distance_sigma_pct": None,
                    "per_sphere_direction": [[float(v) for v in f.directions[k]] for f in self.fits]}
            if self.positions_mm is not None:
                lamp.update(position_mm=[float(v) for v in self.positions_mm[k]],
                            position_sigma_mm=[float(v) for v in self.position_sigma_mm[k]],
                            distance_sigma_pct=float(self.distance_sigma_pct[k]),
                            ray_miss_mm=float(self.ray_miss_mm[k]))
            out.append(lamp)
        return out


# ------------------------------------------------------------------------------------------------
# reading circles, grey values
# ------------------------------------------------------------------------------------------------

_COL_NAMES = ("col", "x", "centre_col", "center_col", "cx", "x_px")
_ROW_NAMES = ("row", "y", "centre_row", "center_row", "cy", "y_px")
_RAD_NAMES = ("radius_px", "radius", "r", "r_px")


def read_sphere_circles(path) -> list:
    """Spheres given by hand: a CSV with columns ``col,row,radius_px`` (centre column and row and
    radius, in pixels of the full image; ``x,y,radius`` also accepted) and optionally ``kind``
    (matte, glossy or mirror; empty or auto = decided from the images).

    Examples
    --------
    >>> import tempfile, pathlib
    >>> p = pathlib.Path(tempfile.mkdtemp()) / "c.csv"
    >>> _ = p.write_text("col,row,radius_px,kind\\n120.5,80,40,glossy\\n")
    >>> read_sphere_circles(p)[0]
    Sphere(centre_px=(120.5, 80.0), radius_px=40.0, kind='glossy', source='given')
    """
    path = Path(path)
    if not path.is_file():
        raise UVPSInputError(f"sphere circles file {path} does not exist")
    with open(path, newline="", encoding="utf-8") as fh:
        rows = list(csv.DictReader(fh))
    if not rows:
        raise UVPSInputError(f"sphere circles file {path} is empty; expected columns col,row,radius_px")
    keys = {k.strip().lower(): k for k in rows[0] if k is not None}

    def pick(names):
        for nm in names:
            if nm in keys:
                return keys[nm]
        raise UVPSInputError(f"sphere circles file {path}: expected columns col,row,radius_px; got "
                             f"{', '.join(keys) or 'none'}")

    kc, kr, kd = pick(_COL_NAMES), pick(_ROW_NAMES), pick(_RAD_NAMES)
    kk = keys.get("kind")
    out = []
    for i, row in enumerate(rows, start=2):
        try:
            c, r, rad = float(row[kc]), float(row[kr]), float(row[kd])
        except (TypeError, ValueError):
            raise UVPSInputError(f"sphere circles file {path} line {i}: col, row and radius_px must be numbers; "
                                 f"got {row[kc]!r}, {row[kr]!r}, {row[kd]!r}") from None
        if not (math.isfinite(c) and math.isfinite(r) and math.isfinite(rad) and rad > 0):
            raise UVPSInputError(f"sphere circles file {path} line {i}: radius_px must be > 0 and every value finite")
        kind = (row.get(kk) or "auto").strip().lower() if kk else "auto"
        if kind not in KINDS + ("auto", ""):
            raise UVPSInputError(f"sphere circles file {path} line {i}: kind must be matte, glossy, mirror or auto; "
                                 f"got {kind!r}")
        out.append(Sphere((c, r), rad, kind or "auto", "given"))
    return out


# ------------------------------------------------------------------------------------------------
# one sphere under every lamp
# ------------------------------------------------------------------------------------------------

_DISK2 = np.hypot(*np.mgrid[-2:3, -2:3]) <= 2.0


class _Disc:
    """The pixels of a sphere's disc inside ``shrink`` of its radius, with their normals."""

    def __init__(self, sphere: Sphere, shape, pixel_size_um, shrink=0.96, camera_distance_mm=None):
        M, N = shape
        self.box = _crop_box(sphere.centre_px, sphere.radius_px, shape, margin=1.0)
        r0, r1, c0, c1 = self.box
        rr, cc = np.mgrid[r0:r1, c0:c1]
        c_, r_ = sphere.centre_px
        R = sphere.radius_px
        px_mm = pixel_size_um / 1000.0
        self.frame, self.px_mm, self.camera_distance_mm = (M, N), px_mm, camera_distance_mm
        if camera_distance_mm is None:
            nx, ny = (cc - c_) / R, (r_ - rr) / R
            rho2 = nx * nx + ny * ny
            self.mask = rho2 < shrink * shrink
        else:       # a pinhole camera: each pixel's ray meets the sphere the circle outlines (sphere_view)
            self.centre_mm, self.radius_mm = self._sphere_mm(c_, r_, R)
            nrm, rho = pixel_normals((cc - (N - 1) / 2.0) * px_mm, ((M - 1) / 2.0 - rr) * px_mm, self.centre_mm,
                                     self.radius_mm, camera_distance_mm)
            self.mask = rho < shrink
        if self.mask.sum() < 50:
            raise UVPSInputError(f"sphere at ({c_:.0f}, {r_:.0f}) px: fewer than 50 pixels of its disc lie in the "
                                 f"{N} x {M} image; expected a circle inside the frame")
        if camera_distance_mm is None:
            nz = np.sqrt(np.clip(1 - rho2, 0, None))
            self.normals = np.stack([nx, ny, nz], axis=-1)[self.mask]          # (P, 3)
            R_mm = R * px_mm
            self.centre_mm = np.array([(c_ - (N - 1) / 2.0) * px_mm, ((M - 1) / 2.0 - r_) * px_mm, R_mm])
            self.radius_mm = R_mm
        else:
            self.normals = nrm[self.mask]
        self.centre_px = (float(c_), float(r_))
        self.radius_px = float(R)
        self.rows, self.cols = rr[self.mask] - r0, cc[self.mask] - c0
        # the disc and its normals laid out on the box, for the per-lamp highlight fits
        self.shape = (r1 - r0, c1 - c0)
        self.inside = np.zeros(self.shape, bool)
        self.inside[self.rows, self.cols] = True
        self.normal_map = np.zeros(self.shape + (3,), np.float32)
        self.normal_map[self.rows, self.cols] = self.normals

    def _sphere_mm(self, c, r, R):
        """The sphere (centre mm (3,), radius mm) whose outline is the circle at column ``c``, row ``r``,
        radius ``R`` px, seen by the camera (:func:`uvps.core.sphere_view.sphere_from_outline`)."""
        M, N = self.frame
        E = ((c - (N - 1) / 2.0) * self.px_mm, ((M - 1) / 2.0 - r) * self.px_mm)
        return sphere_from_outline(E, R * self.px_mm, self.camera_distance_mm)

    def view(self, normal) -> np.ndarray:
        """The unit vector toward the camera from the surface point of ``normal``: +z when orthographic."""
        if self.camera_distance_mm is None:
            return np.array([0.0, 0.0, 1.0])
        return view_at(self.centre_mm + self.radius_mm * np.asarray(normal), self.camera_distance_mm)


def _disc_values(crops, outer, disc: _Disc) -> np.ndarray:
    """The disc's samples under every lamp (K, P) float32, from the images' crops (K, rows, cols[, C])
    to the box ``outer`` that holds the disc's."""
    r0, _, c0, _ = disc.box
    rows, cols = disc.rows + (r0 - outer[0]), disc.cols + (c0 - outer[2])
    if rows.min() < 0 or cols.min() < 0 or rows.max() >= crops.shape[1] or cols.max() >= crops.shape[2]:
        raise ValueError("the disc lies outside the crops read for it")
    return _grey(crops[:, rows, cols])


def _static_part(vals) -> np.ndarray:
    """What every image of the disc shows (P,): the median over the images (the lowest of two), so
    that a reflection of the room, a window or a fixed lamp, the same under every lamp, is not taken
    for the lamp's highlight (the PSBox mirror sphere reflects a saturated spot and a lit figure in
    all twelve images). A highlight covers a sample in fewer than half the images."""
    return np.median(vals, axis=0) if len(vals) >= 3 else vals.min(axis=0)


def _kind_of(stack_vals, disc: "_Disc" = None, sat=None) -> str:
    """matte, glossy or mirror from the disc's values (K, P).

    Matte: a lit fraction of the disc that only shading gives (a hemisphere under each lamp: over 15 %
    of the disc above a quarter of its range in the median image); a specular sphere's lit part is
    its highlight, a few per cent at most. Then a mirror's highlight is the lamp's small image, a
    glossy sphere's a lobe: the median over the images of the highlight core's angular radius in the
    sphere's normals (:func:`_highlight_core`) under :data:`MIRROR_CORE_DEG` is a mirror.
    """
    fr = []
    for v in stack_vals:
        base = np.percentile(v, 5)
        peak = np.percentile(v, 99.9) - base
        fr.append(np.mean(v - base > 0.25 * peak) if peak > 0 else 0.0)
    if np.median(fr) > 0.15:
        return "matte"
    if disc is None:
        return "glossy"
    static = _static_part(stack_vals)
    radii = []
    for v in stack_vals:
        core = _highlight_core(v, v - static, disc, sat)
        if core is not None:
            radii.append(core[1])
    if not radii:
        return "glossy"
    return "mirror" if np.median(radii) < MIRROR_CORE_DEG else "glossy"


def _open_core(core):
    """A highlight's core with a flare's thin spikes opened off (3 x 3; a core of over 12 pixels, when
    the opening leaves something), and its components: ``(core, labels, count)``."""
    if core.sum() > 12:
        opened = ndimage.binary_opening(core, structure=np.ones((3, 3), bool))
        core = opened if opened.any() else core
    lab, n = ndimage.label(core)
    return core, lab, n


def _highlight_core(v, w, disc: "_Disc", sat):
    """A highlight's core on the disc's box: (mask, angular radius in degrees, peak) or None.

    The core is the saturated samples that the static part does not explain (``w`` above half its
    peak), or, when none saturates, ``w`` above half its peak; opened by a disc of radius 2 px (a
    flare's spikes and a scratch's streak, a few pixels wide, come off; the lamp's image stays) and
    its largest component kept. Its angular radius is that of a disc of its area on the sphere, seen
    at its mean normal (foreshortening taken out)."""
    peak = float(w.max()) if w.size else 0.0
    sub = w[::4] if w.size >= 4000 else w
    noise = 1.4826 * float(np.median(np.abs(sub - np.median(sub)))) + 1e-6
    if not peak > 10 * noise:
        return None
    img = np.zeros(disc.shape, np.float32)
    img[disc.rows, disc.cols] = w
    core = np.zeros(disc.shape, bool)
    if sat is not None and np.any(v >= sat):
        # near saturation: a JPEG's blocks ring a clipped area down by a few counts (250 of 255 in sRGB
        # is 0.955 of the linear maximum)
        core[disc.rows, disc.cols] = (v >= SATURATED_CORE * sat) & (w > 0.5 * peak)
    if core.sum() < 3:
        core = img >= 0.5 * peak
    core, lab, n = _open_core(core)
    if n == 0:
        return None
    sizes = ndimage.sum(core, lab, index=np.arange(1, n + 1))
    best = lab == 1 + int(np.argmax(sizes))
    # a highlight split by a scratch's streak or a flare's dark ray is one highlight: the parts within
    # the largest part's own radius of it are kept with it; a speck or a reflection elsewhere is not
    reach = max(2, int(math.ceil(math.sqrt(best.sum() / math.pi))))
    group = ndimage.binary_dilation(best, structure=_DISK2, iterations=max(1, reach // 2))
    core = core & group
    nz = disc.normal_map[..., 2][core]
    area = float(np.sum(1.0 / np.maximum(nz, 0.05)))          # pixels on the sphere, foreshortening out
    # less half a pixel: a lamp's image a pixel across on a small sphere spreads over two or three
    ang = math.degrees(math.asin(min(1.0, max(0.0, math.sqrt(area / math.pi) - 0.5) / disc.radius_px)))
    return core, ang, peak


def _near_column(normals, b):
    """The near lamp's term of a sphere's shading, ``3 (n . l)^2 - 1`` for ``l = b / |b|``.

    A lamp at distance D from a sphere of radius R lights its near side closer: to first order in
    ``kappa = R / D`` the irradiance over ``n . l`` grows by ``2 kappa n . l`` (inverse square) and the
    local direction turns toward the limb by ``kappa (1 - (n . l)^2)``, together ``kappa (3 (n . l)^2 -
    1)``. Left out, it is taken for the additive term and for a sphere a fraction of a pixel larger or
    smaller: on a 5 mm sphere at 300 mm, 1 degree of the lamp's direction. ``b`` is one vector, or
    one per sample (``(P, 3)``: each sample's own image's, in the circle's joint fit).
    """
    b = np.asarray(b, float)
    if b.ndim == 1:
        nb = np.linalg.norm(b)
        if not nb > 0:
            return np.zeros(len(normals))
        c = normals @ (b / nb)
    else:
        c = np.einsum("ij,ij->i", normals, b) / np.maximum(np.linalg.norm(b, axis=1), 1e-300)
    return 3.0 * c * c - 1.0


def _across(l):
    """Two unit vectors across the unit vector ``l`` (``e1`` horizontal unless ``l`` is near vertical)."""
    e1 = np.cross(l, [0.0, 0.0, 1.0]) if abs(l[2]) < 0.99 else np.cross(l, [1.0, 0.0, 0.0])
    e1 /= np.linalg.norm(e1)
    return e1, np.cross(l, e1)


def _beam_columns(normals, l):
    """A lamp's beam across a sphere, ``(n . l)(n . e1)``, ``(n . l)(n . e2)`` with ``e1, e2`` across ``l``.

    A beam (or any irradiance that varies across the sphere's 5 mm beside the near lamp's inverse
    square) changes with the direction from the lamp, so across the sphere it is a gain ``1 + g . n``
    with ``g`` across ``l`` to first order; the shading ``(n . l)`` times it adds these two terms. Left
    out, a narrow lamp aimed 5 deg off reads as the lamp turned by up to 0.9 deg (matte spheres of the
    robustness benchmark's beams row), and vignetting's gradient as a fraction of that. The circle's
    fit (:func:`_refine_matte_circle`) takes them only where an F test finds them in the shading
    (:func:`_beams_significant`): there without beams they take up part of the common gain (lamps
    0.021 -> 0.048 deg, positions 0.9 -> 1.8 % on the robustness benchmark's vignetting row, seed 1).
    """
    e1, e2 = _across(l)
    nl = normals @ l
    return nl * (normals @ e1), nl * (normals @ e2)


def _solve(G, rhs):
    """The normal equations ``G x = rhs`` of a sphere's shading fit. Its columns are a handful of O(1)
    shading terms (on a 167 px disc the design's condition number is about 75, ``G``'s 5e3), so in
    float64 they lose nothing ``numpy.linalg.lstsq`` keeps, and need no copy of the rows in use."""
    try:
        return np.linalg.solve(G, rhs)
    except np.linalg.LinAlgError:
        return np.linalg.lstsq(G, rhs, rcond=None)[0]


def _fit_matte(v, normals, sat, offset=None):
    """``v = n . b + c + beta (3 (n . l)^2 - 1) + (n . l)(g1 n . e1 + g2 n . e2)`` (the near lamp's term
    :func:`_near_column`, the beam's :func:`_beam_columns`) over the lit, unsaturated samples, trimmed:
    (b, c, cov of b, n used, rms over |b|, the samples used).

    A first fit of ``n . b + c`` over the samples above 30 % of the range, then up to five rounds of
    the full model over the samples it predicts lit (``n . l`` above :data:`MATTE_MIN_COS`) within
    four robust standard deviations (a MAD over every fourth sample in use), until the samples in
    use stop changing. When the full model's near-lamp or beam term comes out above
    :data:`MATTE_TERM_MAX` of ``|b|`` (:func:`_matte_terms_plausible`), the same rounds are run with
    ``n . b + c`` alone. With ``offset`` given (the additive term read in the sphere's attached
    shadows, :func:`_shadow_offsets`) ``c`` is that value and is not fitted.
    Each round is three passes over the samples (:func:`_matte_gram`,
    :func:`_matte_update`, :func:`_matte_select`), compiled: a disc holds 10^4-10^5 samples and a sphere capture 64 lamps,
    and numpy's temporaries made the fits 6.5 of the 14.8 s ``uvps calibrate`` took on 64 lamps
    (``scripts/benchmark_calibrate_speed.py --kind matte``). Its statement in numpy:
    :func:`_fit_matte_numpy`.
    """
    v = np.ascontiguousarray(v)
    normals = np.ascontiguousarray(normals, dtype=np.float64)
    fit = _fit_matte_terms(v, normals, sat, 7, offset)
    if fit is not None and not _matte_terms_plausible(fit[6]):
        fit = _fit_matte_terms(v, normals, sat, 4, offset)
    return None if fit is None else fit[:6]


def _matte_terms_plausible(coef) -> bool:
    """Whether a matte fit's near-lamp term and beam terms (``coef[4]``, ``coef[5:7]``) are each within
    :data:`MATTE_TERM_MAX` of ``|b|`` (``coef[:3]``); a fit of four terms has none."""
    if len(coef) <= 4:
        return True
    nb = np.linalg.norm(coef[:3])
    return bool(abs(coef[4]) <= MATTE_TERM_MAX * nb and math.hypot(coef[5], coef[6]) <= MATTE_TERM_MAX * nb)


def _fit_matte_terms(v, normals, sat, terms, offset=None):
    """:func:`_fit_matte` with ``terms`` 7 (the full model) or 4 (``n . b + c``): its result and the
    coefficients, or None. ``offset`` given: ``c`` held at it (its column left out of the solve)."""
    ok = np.isfinite(v) if sat is None else v < sat
    if offset is not None:
        v = np.ascontiguousarray(v - np.float32(offset), dtype=v.dtype)
    lo, hi = np.percentile(v, (2, 99.5))
    sel = ok & (v > lo + 0.3 * (hi - lo))
    n_sel = int(sel.sum())
    P = len(v)
    A = np.zeros((P, 7))
    A[:, :3] = normals
    A[:, 3] = 1.0
    new = np.empty(P, bool)
    buf = np.empty(P // 4 + 1)
    coef = None
    cols = 4
    l = None
    for it in range(6):
        if n_sel < 20:
            return None
        coef = _solve_held(*_matte_gram(A, v, sel, cols), offset is not None)
        b = coef[:3]
        nb = np.linalg.norm(b)
        if not nb > 0:
            return None
        l = b / nb
        e1, e2 = _across(l)
        res, m = _matte_update(A, normals, v, coef, l, e1, e2, sel, buf)
        s = 1.4826 * np.median(buf[:m]) + 1e-9
        n_new, same = _matte_select(normals, l, res, ok, MATTE_MIN_COS, 4 * s, sel, new)
        if it > 0 and same:
            break
        sel, new = new, sel
        n_sel, cols = n_new, terms
    res, _ = _matte_update(A, normals, v, coef, l, e1, e2, sel, buf)
    dof = max(1, n_sel - cols + (offset is not None))
    s2 = float(np.sum(res[sel] ** 2)) / dof
    cov = s2 * _held_pinv(_matte_gram(A, v, sel, cols)[0], offset is not None)[:3, :3]
    c = float(coef[3]) if offset is None else float(offset)
    return coef[:3], c, cov, n_sel, math.sqrt(s2) / np.linalg.norm(coef[:3]), sel, coef


def _held(n, held):
    """The columns of a matte fit's ``n`` terms that are solved: all, or all but the offset's (3)."""
    return np.array([j for j in range(n) if not (held and j == 3)])


def _solve_held(G, rhs, held):
    """:func:`_solve` with the offset's column (3) held at zero when ``held``: the coefficients (``n``,)."""
    idx = _held(len(rhs), held)
    coef = np.zeros(len(rhs))
    coef[idx] = _solve(G[np.ix_(idx, idx)], rhs[idx])
    return coef


def _held_pinv(G, held):
    """The pseudo-inverse of a matte fit's normal matrix, the held offset's row and column zero."""
    idx = _held(len(G), held)
    out = np.zeros_like(G)
    out[np.ix_(idx, idx)] = np.linalg.pinv(G[np.ix_(idx, idx)])
    return out


def _matte_gram(A, v, sel, cols):
    """The normal equations of :func:`_fit_matte`'s least squares over the samples in use, ``G = sum
    a a^T`` and ``rhs = sum a v`` for ``a`` the first ``cols`` terms of a row of ``A`` (P, 7)."""
    g = _matte_gram7(A, v, sel)
    G = np.empty((7, 7))
    i, j = np.tril_indices(7)
    G[i, j] = G[j, i] = g[:28]
    return G[:cols, :cols], g[28:28 + cols]


@numba.njit(nogil=True, cache=True)
def _matte_gram7(A, v, sel):
    """:func:`_matte_gram` over all seven terms: the 28 sums of ``G``'s lower triangle row by row,
    then the 7 of ``rhs``. Each sum is a scalar of its own, held in a register through the pass
    (written as arrays, the sums went through memory: 2.1 ms a pass over 80 000 samples, 0.4 ms
    so); the first terms' sums do not depend on the later ones, so a fit of fewer terms takes the
    leading block."""
    g00 = g10 = g11 = g20 = g21 = g22 = g30 = g31 = g32 = g33 = 0.0
    g40 = g41 = g42 = g43 = g44 = g50 = g51 = g52 = g53 = g54 = g55 = 0.0
    g60 = g61 = g62 = g63 = g64 = g65 = g66 = 0.0
    r0 = r1 = r2 = r3 = r4 = r5 = r6 = 0.0
    for p in range(v.shape[0]):
        if sel[p]:
            a0, a1, a2, a3, a4, a5, a6 = A[p, 0], A[p, 1], A[p, 2], A[p, 3], A[p, 4], A[p, 5], A[p, 6]
            vp = np.float64(v[p])
            r0 += a0 * vp
            r1 += a1 * vp
            r2 += a2 * vp
            r3 += a3 * vp
            r4 += a4 * vp
            r5 += a5 * vp
            r6 += a6 * vp
            g00 += a0 * a0
            g10 += a1 * a0
            g11 += a1 * a1
            g20 += a2 * a0
            g21 += a2 * a1
            g22 += a2 * a2
            g30 += a3 * a0
            g31 += a3 * a1
            g32 += a3 * a2
            g33 += a3 * a3
            g40 += a4 * a0
            g41 += a4 * a1
            g42 += a4 * a2
            g43 += a4 * a3
            g44 += a4 * a4
            g50 += a5 * a0
            g51 += a5 * a1
            g52 += a5 * a2
            g53 += a5 * a3
            g54 += a5 * a4
            g55 += a5 * a5
            g60 += a6 * a0
            g61 += a6 * a1
            g62 += a6 * a2
            g63 += a6 * a3
            g64 += a6 * a4
            g65 += a6 * a5
            g66 += a6 * a6
    return np.array([g00, g10, g11, g20, g21, g22, g30, g31, g32, g33, g40, g41, g42, g43, g44,
                     g50, g51, g52, g53, g54, g55, g60, g61, g62, g63, g64, g65, g66,
                     r0, r1, r2, r3, r4, r5, r6])


@numba.njit(nogil=True, cache=True)
def _matte_update(A, normals, v, coef, l, e1, e2, sel, buf):
    """:func:`_fit_matte`'s terms from the lamp's new direction ``l`` (``A[:, 4:7]``: the near lamp's,
    the beam's two) and the residual of the fit ``coef`` (over its first ``len(coef)`` terms, the new
    ones included where it has seven): (residual (P,), m) with ``buf[:m]`` the residual's magnitude
    at every fourth sample in use."""
    P = v.shape[0]
    cols = coef.shape[0]
    res = np.empty(P)
    n_in = 0
    m = 0
    for p in range(P):
        n0, n1, n2 = normals[p, 0], normals[p, 1], normals[p, 2]
        c = n0 * l[0] + n1 * l[1] + n2 * l[2]
        A[p, 4] = 3.0 * c * c - 1.0
        A[p, 5] = c * (n0 * e1[0] + n1 * e1[1] + n2 * e1[2])
        A[p, 6] = c * (n0 * e2[0] + n1 * e2[1] + n2 * e2[2])
        r = np.float64(v[p])
        for j in range(cols):
            r -= coef[j] * A[p, j]
        res[p] = r
        if sel[p]:
            if n_in % 4 == 0:
                buf[m] = abs(r)
                m += 1
            n_in += 1
    return res, m


@numba.njit(nogil=True, cache=True)
def _matte_select(normals, l, res, ok, min_cos, limit, sel, new):
    """:func:`_fit_matte`'s next samples in use into ``new``: usable, predicted lit above ``min_cos``
    and with a residual under ``limit``: (how many, whether they are ``sel``'s)."""
    n = 0
    same = True
    for p in range(res.shape[0]):
        c = normals[p, 0] * l[0] + normals[p, 1] * l[1] + normals[p, 2] * l[2]
        x = ok[p] and c > min_cos and abs(res[p]) < limit
        new[p] = x
        n += x
        if x != sel[p]:
            same = False
    return n, same


def _fit_matte_numpy(v, normals, sat, offset=None):
    """:func:`_fit_matte` in numpy, its statement (the tests hold the compiled form to it): the design
    held column by column (``AT``, terms x samples), the samples in use as 0/1 weights."""
    fit = _fit_matte_numpy_terms(v, normals, sat, 7, offset)
    if fit is not None and not _matte_terms_plausible(fit[6]):
        fit = _fit_matte_numpy_terms(v, normals, sat, 4, offset)
    return None if fit is None else fit[:6]


def _fit_matte_numpy_terms(v, normals, sat, terms, offset=None):
    ok = np.isfinite(v) if sat is None else v < sat
    held = offset is not None
    if held:
        v = v - np.float32(offset)
    lo, hi = np.percentile(v, (2, 99.5))
    sel = ok & (v > lo + 0.3 * (hi - lo))
    AT = np.zeros((7, len(v)))
    AT[:3] = normals.T
    AT[3] = 1.0
    coef = None
    cols = 4
    for it in range(6):
        if sel.sum() < 20:
            return None
        Aw = AT[:cols] * sel
        coef = _solve_held(Aw @ AT[:cols].T, Aw @ v, held)
        b = coef[:3]
        nb = np.linalg.norm(b)
        if not nb > 0:
            return None
        AT[4] = _near_column(normals, b)
        AT[5], AT[6] = _beam_columns(normals, b / nb)
        res = v - coef @ AT[:cols]
        s = 1.4826 * np.median(np.abs(res[sel][::4])) + 1e-9      # a trim's scale: a quarter is plenty
        new = ok & (normals @ (b / nb) > MATTE_MIN_COS) & (np.abs(res) < 4 * s)
        if it > 0 and np.array_equal(new, sel):
            break
        sel, cols = new, terms
    res = (v - coef @ AT[:cols])[sel]
    dof = max(1, sel.sum() - cols + held)
    s2 = float(res @ res) / dof
    Aw = AT[:cols] * sel
    cov = s2 * _held_pinv(Aw @ AT[:cols].T, held)[:3, :3]
    return (coef[:3], float(coef[3]) if not held else float(offset), cov, int(sel.sum()), math.sqrt(s2) / np.linalg.norm(coef[:3]), sel,
            coef)


def _shadow_offsets(vals, normals, sat):
    """Each lamp's additive term (black level, the room's light) read in the sphere's attached shadow:
    (K,) or None when no lamp leaves a shadow on the disc.

    Lambert's law with an additive term, ``v = max(n . b, 0) + c``, shows ``c`` alone where the lamp
    does not reach (``n . l < 0``). Fitted with the lit part instead, ``c`` is nearly a function of
    ``n_z`` as ``b_z`` is when a lamp lights most of the disc, and takes up whatever makes the shading
    flatter or steeper than Lambert's law (a rough or translucent ball, a gain across the disc):
    on the UW/Seitz grey ball the fitted ``c`` grew from 0.5 % to 40 % of ``|b|`` as the lamps came
    toward the view, while its attached shadows read 0-2 counts of ~170, and the lamps near the view
    came 4-9 deg too high (decisions/spheres.md). A lamp's shadow is the samples below
    ``-MATTE_SHADOW_COS`` under its first fit's direction that some other lamp lights to half the
    disc's median peak or more (a holder or the ground inside the circle is dark under every lamp),
    read when it holds at least :data:`MATTE_SHADOW_MIN` of the disc (its median); a
    lamp near the view, whose shadow lies beyond the rim, takes the median of the others' (the black
    level and the room's light, the same in every picture of a darkroom capture).
    """
    K, P = vals.shape
    every = max(1, P // 20000)          # the first fits only point the lamp: 20 000 samples are plenty
    # the sphere's own samples: lit by some lamp (a holder, a stand or the ground seen inside the circle
    # stays dark under every lamp, and is no shadow of the sphere's)
    peak = vals.max(axis=0)
    seen = peak >= 0.5 * np.median(peak)
    levels = np.full(K, np.nan)
    fitted = np.full(K, np.nan)             # the lit part's own additive term, over |b|, less the shadow's
    shadow = np.zeros(K)
    for k in range(K):
        fit = _fit_matte(vals[k, ::every], normals[::every], sat)
        if fit is None:
            continue
        nb = np.linalg.norm(fit[0])
        dark = (normals @ (fit[0] / nb) < -MATTE_SHADOW_COS) & seen
        shadow[k] = dark.sum()
        if shadow[k] >= max(20, MATTE_SHADOW_MIN * P):
            levels[k] = float(np.median(vals[k][dark]))
            fitted[k] = (fit[1] - levels[k]) / nb
    if not np.isfinite(levels).any():
        return None
    # Lambert's law with the shadow's term must hold where it can be told: the lamps that show most of
    # their terminator (the quarter, at least one, with the largest shadows) fit the lit part with the
    # shadow's term. A rough ball (Oren-Nayar) or a translucent one lights its lit part beyond the
    # law, as an additive term the shadow does not show; its term is then left to each fit. Rendered
    # rough balls under lamps near the view: roughness 0.05-0.2 rad fit 1.3-3.2 % of |b| over the
    # shadow and the held term is the better; 0.25 rad 4.2 %, even; 0.3-0.35 rad 5.5-7 %, held 0.2-0.6
    # deg worse (scripts/analyse_matte_sphere.py --rough). The UW/Seitz grey ball: 3.9 %.
    tell = np.argsort(-shadow)[:max(1, int(np.isfinite(levels).sum()) // 4)]
    if not np.median(np.abs(fitted[tell])) <= MATTE_SHADOW_AGREE:
        return None
    levels[~np.isfinite(levels)] = np.median(levels[np.isfinite(levels)])
    return levels


def _refine_matte_circle(sphere: Sphere, disc: "_Disc", vals, sat, *, samples=MATTE_CIRCLE_SAMPLES,
                         offsets=None):
    """Centre and radius of a matte sphere, and the gain across its disc, that make Lambert's law fit
    its shading best: (Sphere, g) with the gain :func:`_gain`.

    The rim found in the images is a fraction of a pixel off (its last pixels are partly background,
    and a lamp's shading falls toward the limb); a radius 1 % off tilts every normal of the disc and
    the lamp's direction with it. Vignetting multiplies the shading by a gain that varies across the
    disc (on a sphere near a corner, 10 % per radius at a 40 % corner fall-off), which a per-lamp fit
    reads as every lamp turned toward the image centre by 2-3 deg; the gain is the same under every
    lamp and the shading's direction is not, so a joint fit tells them apart. Here the circle and
    ``g`` are the ones that leave the smallest residual in every image's linear fit (variable
    projection: each image's ``b``, ``c`` and near-lamp term are solved inside the residual;
    ``scipy.optimize.least_squares`` over the twelve parameters), on the samples each image's first fit
    kept (``samples`` in all, shared among the images, at least 500 each). The sampling sets the
    circle's spread: on the robustness benchmark's clean row the centre came 0.03-0.04 px off with
    1500 samples per image and 0.01 px with all of them (80 000); 60 000 in all keeps the fit of a
    sphere under 64 lamps to about 2 s. The first fits, which only choose the samples, read a
    regular subset of the disc where it is large. ``offsets`` (K,): each lamp's additive term read in
    the attached shadows (:func:`_shadow_offsets`), held in every image's fit; None: fitted. Each
    image's beam terms (:func:`_beam_columns`) join its fit where :func:`_beams_significant` finds them.
    """
    from scipy.optimize import least_squares

    picks, used, scale = _matte_picks(disc, vals, sat, samples, offsets)
    if len(picks) < 3:
        return sphere, np.zeros(GAIN_TERMS)
    c0, r0 = sphere.centre_px
    R0 = sphere.radius_px
    plain = _matte_circle_residuals(disc, vals, picks, used, scale, (c0, r0, R0), offsets)
    lim = MATTE_CIRCLE_MOVE * R0
    fit = dict(bounds=([-lim, -lim, -MATTE_CIRCLE_MOVE] + [-0.5] * GAIN_TERMS,
                       [lim, lim, MATTE_CIRCLE_MOVE] + [0.5] * GAIN_TERMS),
               x_scale=[1.0, 1.0, 1.0 / R0] + [0.05] * GAIN_TERMS, diff_step=1e-3)
    x = least_squares(plain, np.zeros(3 + GAIN_TERMS), **fit).x
    bounded = lambda x: np.any(np.abs(x[:3]) >= 0.98 * np.array([lim, lim, MATTE_CIRCLE_MOVE]))  # noqa: E731
    beams = _matte_circle_residuals(disc, vals, picks, used, scale, (c0, r0, R0), offsets, beam=True)
    if not bounded(x) and _beams_significant(plain(x), beams(x), len(picks), offsets is None,
                                             _picks_noise(disc, vals, picks, used, scale)):
        # each lamp's beam across the disc (a gradient the common gain cannot follow) pulled the circle:
        # under the robustness benchmark's beams 0.1-0.23 px, every lamp 0.1-0.27 deg (decisions/spheres.md).
        # Not asked where the shading already pulls the circle to its bounds: that ball is outside the
        # model (the UW/Seitz grey ball's veins: F 570, and with the terms its lamps 14 deg off)
        log.info("matte sphere at (%.0f, %.0f) px: its lamps' beams vary across it; the circle is fitted "
                 "with them", c0, r0)
        x = least_squares(beams, x, **fit).x
    if MATTE_KEEP_RIM and bounded(x):
        # the shading pulls the circle to the bounds: it is the ball, not the rim, that Lambert's law
        # does not describe there (a rough or translucent surface's flatter fall toward the limb and
        # the terminator; on the UW/Seitz grey ball 3 px off a rim the set's hand-drawn mask confirms
        # within 1 px). The rim is kept and the gain fitted on it alone.
        log.info("matte sphere at (%.0f, %.0f) px: its shading pulls the circle %s px off the rim (bounds); "
                 "the rim is kept", c0, r0, np.round([x[0], x[1], x[2] * R0], 1).tolist())
        res = least_squares(lambda g: plain(np.concatenate([[0.0, 0.0, 0.0], g])), np.zeros(GAIN_TERMS),
                            bounds=([-0.5] * GAIN_TERMS, [0.5] * GAIN_TERMS), x_scale=[0.05] * GAIN_TERMS,
                            diff_step=1e-3)
        x = np.concatenate([[0.0, 0.0, 0.0], res.x])
    return Sphere((c0 + x[0], r0 + x[1]), R0 * (1 + x[2]), sphere.kind, sphere.source), x[3:]


def _picks_noise(disc: "_Disc", vals, picks, used, scale) -> float:
    """The noise of the circle's fit's samples (its residuals' units: each image's first ``|b|``), their
    mean variance: from each pick's second difference along its row, ``v[c - 1] - 2 v[c] + v[c + 1]``
    (variance six times the noise's; the shading's curvature over a pixel is ``|b| / R^2``, far below),
    a robust spread (MAD) per image. NaN where no pick has both neighbours on the disc."""
    at = np.full(disc.shape, -1, np.int64)
    at[disc.rows, disc.cols] = np.arange(disc.rows.size)
    var = []
    for k, idx, sc in zip(used, picks, scale):
        r, c = disc.rows[idx], disc.cols[idx]
        ok = (c > 0) & (c < disc.shape[1] - 1)
        r, c, mid = r[ok], c[ok], idx[ok]
        left, right = at[r, c - 1], at[r, c + 1]
        ok = (left >= 0) & (right >= 0)
        if ok.sum() < 20:
            continue
        v = vals[k]
        d2 = v[left[ok]].astype(np.float64) - 2.0 * v[mid[ok]] + v[right[ok]]
        var.append((1.4826 * np.median(np.abs(d2 - np.median(d2))) / sc) ** 2 / 6.0 * len(idx))
    return float(np.sum(var) / sum(len(i) for i in picks)) if var else float("nan")


def _beams_significant(plain, beams, images, free_offset, noise=float("nan")) -> bool:
    """Whether each image's beam terms (:func:`_beam_columns`, two per image) explain a matte sphere's
    shading beyond its noise: the F test of the circle's fit with them (residuals ``beams``) against
    the fit without (``plain``), both at one circle and gain, at :data:`MATTE_BEAM_P`.

    A beam (or any irradiance varying across the sphere with the direction from its lamp) is a gradient
    across each lamp's direction of its own, which the gain common to every lamp cannot follow: left out,
    it pulls the circle. Kept in where there is none, the two terms per image take up part of the common
    gain (vignetting), which the circle then misses. On the robustness benchmark's 12-lamp spheres
    F is 0.5-1.1 without beams (vignetting among them), 47-290 under its beams. A shading outside
    Lambert's law (a rough ball's) is also explained better by more terms: they are taken only where
    the fit with them leaves the residual of the noise (``noise``, :func:`_picks_noise`, within
    :data:`MATTE_BEAM_FIT`)."""
    from scipy.special import fdtrc

    n = plain.size
    rss0, rss1 = float(plain @ plain), float(beams @ beams)
    dof = n - images * (6 + free_offset) - 3 - GAIN_TERMS
    if not (rss1 > 0 and dof > 0):
        return False
    F = (rss0 - rss1) / (2 * images) / (rss1 / dof)
    return bool(fdtrc(2 * images, dof, F) < MATTE_BEAM_P and rss1 / dof <= MATTE_BEAM_FIT * noise)


def _matte_picks(disc: "_Disc", vals, sat, samples, offsets=None):
    """The disc samples the circle's fit reads per image (those its first Lambert fit kept, ``samples``
    in all, >= 500 each), the images used and each one's first ``|b|``. A sample's fixed uniform number
    picks it: one sample more or less kept changes the picks by itself alone (drawn anew, a change in
    the last digit of one fit reshuffled them all)."""
    u = np.random.default_rng(0).random(disc.normals.shape[0])
    picks, used, scale = [], [], []
    per_image = max(500, int(samples) // max(1, len(vals)))
    # the first fits read every ``every``-th sample where the disc holds four times the picks or more
    every = max(1, min(8, disc.normals.shape[0] // (4 * per_image)))
    for k, v in enumerate(vals):
        fit = _fit_matte(v[::every], disc.normals[::every], sat, None if offsets is None else offsets[k])
        if fit is None:
            continue
        idx = np.flatnonzero(fit[5]) * every
        picks.append(idx if idx.size <= per_image else idx[u[idx] < per_image / idx.size])
        used.append(k)
        scale.append(np.linalg.norm(fit[0]))      # each image's residual in units of its first |b|, held
    return picks, used, scale


def _beam_columns_each(normals, b):
    """:func:`_beam_columns` with each sample's own lamp (``b`` (P, 3), its image's ``n . b``)."""
    l = b / np.maximum(np.linalg.norm(b, axis=1, keepdims=True), 1e-300)
    e1 = np.cross(l, [0.0, 0.0, 1.0])
    near_z = np.abs(l[:, 2]) >= 0.99
    e1[near_z] = np.cross(l[near_z], [1.0, 0.0, 0.0])
    e1 /= np.linalg.norm(e1, axis=1, keepdims=True)
    e2 = np.cross(l, e1)
    nl = np.einsum("ij,ij->i", normals, l)
    return nl * np.einsum("ij,ij->i", normals, e1), nl * np.einsum("ij,ij->i", normals, e2)


def _matte_circle_residuals(disc: "_Disc", vals, picks, used, scale, circle, offsets=None, beam=False):
    """``residuals(x)``: each pick's residual after its image's linear fit (variable projection) under
    ``circle`` (column, row, radius) moved by ``x[:3]``, gain ``x[3:]``; the picks laid out image by
    image (zero rows padding) so the per-image fits are solved together by batched normal equations.
    ``offsets`` (K,) given: each image's additive term held (``v - c = gain (n . b + near)``)."""
    c0, r0, R0 = circle
    rows = disc.rows + disc.box[0]
    cols = disc.cols + disc.box[2]
    pix = np.concatenate(picks)
    pr, pc = rows[pix].astype(float), cols[pix].astype(float)
    pX, pY = (pc - (disc.frame[1] - 1) / 2.0) * disc.px_mm, ((disc.frame[0] - 1) / 2.0 - pr) * disc.px_mm
    pv = np.concatenate([vals[k][idx] - (0.0 if offsets is None else offsets[k]) for k, idx in zip(used, picks)])
    sizes = np.array([idx.size for idx in picks])
    kid = np.repeat(np.arange(len(picks)), sizes)
    psc = np.asarray(scale)[kid]
    slot = np.arange(pix.size) - np.repeat(np.cumsum(sizes) - sizes, sizes)
    layout = np.full((len(picks), int(sizes.max())), pix.size)          # index pix.size: a zero row
    layout[kid, slot] = np.arange(pix.size)

    def per_image_fit(A, v):
        """Each image's least squares ``A x = v`` over its own rows, by its normal equations."""
        Av = np.concatenate([A, v[:, None]], axis=1)
        Av = np.concatenate([Av, np.zeros((1, Av.shape[1]))])[layout]        # (images, rows, m + 1)
        S = np.matmul(Av.transpose(0, 2, 1), Av)                              # (images, m + 1, m + 1)
        return np.linalg.solve(S[:, :-1, :-1], S[:, :-1, -1:])[..., 0]

    def residuals(x):
        c, r, R = c0 + x[0], r0 + x[1], R0 * (1 + x[2])
        if disc.camera_distance_mm is None:
            nx, ny = (pc - c) / R, (r - pr) / R
            nz = np.sqrt(np.clip(1 - nx * nx - ny * ny, 0, None))
            nrm = np.column_stack([nx, ny, nz])
        else:
            nrm = pixel_normals(pX, pY, *disc._sphere_mm(c, r, R), disc.camera_distance_mm)[0]
            nx, ny = nrm[:, 0], nrm[:, 1]
        gain = _gain(x[3:], nx, ny)
        A = np.column_stack([nrm, np.ones_like(nx), np.zeros_like(nx)]) * gain[:, None]
        if offsets is not None:         # the additive term held: no column of ones
            A = np.delete(A, 3, axis=1)
        m = A.shape[1] - 1
        coef = per_image_fit(A[:, :m], pv)
        A[:, m] = _near_column(nrm, coef[kid, :3]) * gain
        if beam:
            A = np.column_stack([A, *(t * gain for t in _beam_columns_each(nrm, coef[kid, :3]))])
        coef = per_image_fit(A, pv)
        return (pv - np.einsum("ij,ij->i", A, coef[kid])) / psc

    return residuals


def _gain(g, nx, ny):
    """The gain across a disc, ``1 + g0 nx + g1 ny + g2 nx^2 + g3 nx ny + g4 ny^2 + g5 nx^3 + g6 nx^2 ny
    + g7 nx ny^2 + g8 ny^3`` (a smooth fall-off such as vignetting, to third order over the sphere).

    The third order is needed: on a 5 mm sphere near a corner of the robustness benchmark's 40 %
    vignetting, the best second-order gain is 5e-4 off at worst, and the circle, fitted with it, took
    that up as 0.07-0.09 px of its centre (0.05-0.09 deg of every lamp's direction); to third order the
    gain is 3.5e-5 off and the centre 0.003-0.025 px.
    """
    g = np.asarray(g, float)
    out = 1.0 + g[0] * nx + g[1] * ny + g[2] * nx * nx + g[3] * nx * ny + g[4] * ny * ny
    if g.size > 5:          # GAIN_TERMS 5: the second-order gain alone
        out = out + nx * nx * (g[5] * nx + g[6] * ny) + ny * ny * (g[7] * nx + g[8] * ny)
    return out


def _fit_mirror(v, w, disc: _Disc, sat):
    """A mirror's highlight: the centre of its core (:func:`_highlight_core`) as a normal, its peak,
    sample count and centroid uncertainty in pixels; None when the disc shows no highlight.

    A saturated core is flat: each of its samples counts alike, and the samples of its edge (two pixels
    around it) by the fraction of the core's level they reach (the published PSBox directions take the
    position of the samples at or above 250 counts; a flare's spikes and a scratch's streak, opened
    off the core, do not pull it); an unsaturated one is weighted by its counts above the static part. Each sample counts per unit of solid angle (``1 / n_z``), so the limb's foreshortening does not
    pull the centre."""
    found = _highlight_core(v, w, disc, sat)
    if found is None:
        return None
    core, _, peak = found
    img = np.zeros(disc.shape, np.float32)
    img[disc.rows, disc.cols] = w
    flat = sat is not None and bool(np.any(v >= SATURATED_CORE * sat))
    nw = disc.normal_map
    if flat:
        # a flat core and its edge: each sample weighted by the fraction of the saturated level it reaches
        # (a pixel the lamp's image half covers counts half), so that a core of a few pixels is placed to
        # a fraction of one (by its pixels alone, 0.9 deg off on a 1.2 deg lamp image 80 px from a
        # sphere's centre)
        if core.sum() < SMALL_CORE_PX:
            edge = ndimage.binary_dilation(core, structure=np.ones((3, 3), bool), iterations=2) & disc.inside
            top = float(np.median(img[core]))
            wt = np.where(edge, np.clip(img / max(top, 1e-12), 0.0, 1.0), 0.0)
        else:
            wt = None
    else:
        wt = np.where(core, img, 0.0)
    if wt is None:
        # a large flat core: its median normal (a streak or a flare's glow left on one side moves it by a
        # part of their width at most; PSBox: 0.02-0.39 deg from the published directions on their
        # circle, its mean 0.19-1.07)
        nn = nw[core]
        nx, ny = float(np.median(nn[:, 0])), float(np.median(nn[:, 1]))
        nm = np.array([nx, ny, math.sqrt(max(0.0, 1.0 - nx * nx - ny * ny))])
    else:
        wn = wt / np.maximum(nw[..., 2], 0.05)
        nm = (wn[..., None] * nw).sum(axis=(0, 1)).astype(np.float64)
    if not np.linalg.norm(nm) > 0:
        return None
    nm /= np.linalg.norm(nm)
    n_used = int(core.sum())
    r_core = math.sqrt(n_used / math.pi)
    # the core's edge falls on the pixel grid: its centroid moves by about 0.3 px over sqrt(n) pixels of
    # edge; a floor of 0.05 px for the circle's own
    sigma_px = 0.05 + 0.3 * math.sqrt(max(r_core, 1.0)) / math.sqrt(max(n_used, 1))
    return nm, peak, n_used, sigma_px


def _fit_glossy(v, disc: _Disc, sat, static=None):
    """The highlight's centre as a normal, its peak, sample count and centroid uncertainty in pixels;
    None when the disc shows no highlight.

    The core (half the peak, or the saturated samples) is opened (thin flare spikes removed) and its
    largest component taken; the centre is then the weighted centroid of everything above 2 % of the
    peak within 2.5 core radii of it, recentred twice: the highlight's skirt, symmetric about its
    centre like the core, makes the centroid independent of where the pixel grid cuts the core.
    """
    # the background's level and spread from every 4th sample (a disc holds 10^4-10^5)
    sub = v[::4] if v.size >= 4000 else v
    base = np.median(sub)
    noise = 1.4826 * np.median(np.abs(sub - base)) + 1.0
    w = v - base
    peak = float(w.max())
    if peak < 10 * noise:
        return None
    shape = disc.shape
    img = np.zeros(shape, np.float32)
    img[disc.rows, disc.cols] = w
    core = img >= 0.5 * peak
    if sat is not None and (v >= sat).any():
        core = np.zeros(shape, bool)
        core[disc.rows, disc.cols] = v >= sat
        if static is not None:
            # with ``static`` (:func:`_static_part`), a saturated spot every image shows (a reflection of
            # the room) is not the lamp's; only the core's choice uses it: as the lobe's weights, the median
            # of a few lamps' images, which holds parts of their lobes and of the diffuse shading, moved the
            # lamps placed by two glossy spheres under 6 lamps from 9 % to 18 % of their distance
            ws = v - static
            core[disc.rows, disc.cols] &= ws > 0.5 * float(ws.max())
    _, lab, n = _open_core(core)
    if n == 0:
        return None
    sums = ndimage.sum(img, lab, index=np.arange(1, n + 1))
    best = 1 + int(np.argmax(sums))
    rc = np.array(ndimage.center_of_mass(img, lab, best))
    r_core = math.sqrt((lab == best).sum() / math.pi)
    inside, nrm = disc.inside, disc.normal_map
    # the work is done in a window around the core (the highlight is small beside the disc)
    reach = int(math.ceil(2.5 * r_core + 2.0 + 0.5 * (2.5 * r_core + 2.0))) + 3
    ra, rb = max(0, int(rc[0]) - reach), min(shape[0], int(rc[0]) + reach + 1)
    ca, cb = max(0, int(rc[1]) - reach), min(shape[1], int(rc[1]) + reach + 1)
    rr, cc = np.mgrid[ra:rb, ca:cb]
    # a grey opening takes out thin bright lines (flare spikes, 1-2 px wide) and keeps the lobe
    wt = np.clip(ndimage.grey_opening(img[ra:rb, ca:cb], footprint=_DISK2) - 0.02 * peak, 0, None)
    wt *= inside[ra:rb, ca:cb]
    for _ in range(3):
        win = (rr - rc[0]) ** 2 + (cc - rc[1]) ** 2 <= (2.5 * r_core + 2.0) ** 2
        ww = wt * win
        tot = ww.sum()
        if not tot > 0:
            return None
        rc = np.array([(ww * rr).sum() / tot, (ww * cc).sum() / tot])
    n_used = int((ww > 0).sum())
    # the mean normal per unit solid angle (a pixel holds 1 / n_z of it): foreshortening aside
    nw = nrm[ra:rb, ca:cb]
    wn = ww / np.maximum(nw[..., 2], 0.05)
    nm = (wn[..., None] * nw).sum(axis=(0, 1)).astype(np.float64)
    nm /= np.linalg.norm(nm)
    sigma_px = 0.02 + 0.5 / math.sqrt(max(n_used, 1)) * noise / max(peak, noise) + 0.05 / max(r_core, 1.0)
    return nm, peak, n_used, sigma_px


def _matte_disc(sphere: Sphere, disc: "_Disc", crops, outer, vals, sat, *, shape, pixel_size_um: float,
                where: str) -> tuple:
    """A matte sphere's refined circle and disc, its values with the attached shadows' additive term taken
    off and divided by the gain across the disc, and the saturation level to match: (sphere, disc, vals,
    sat, offsets), offsets zeros once taken off (None when not held).

    The circle and the gain across the disc (vignetting) are fitted together on the disc the lamps are
    read on: its outer tenth, where the normals turn fastest, pins the radius (on 0.9 of it the radius
    came 0.2 px off in the robustness benchmark, and every lamp's elevation 0.1 deg with it)."""
    offsets = _shadow_offsets(vals, disc.normals, sat)
    sphere, g = _refine_matte_circle(sphere, disc, vals, sat, offsets=offsets)
    log.debug("matte %s: gain across the disc %s, additive terms from the attached shadows %s", where,
              np.round(g, 4).tolist(), None if offsets is None else np.round(offsets, 2).tolist())
    disc = _Disc(sphere, shape, pixel_size_um, camera_distance_mm=disc.camera_distance_mm)
    gain = _gain(g, disc.normals[:, 0], disc.normals[:, 1])
    vals = _disc_values(crops, outer, disc)
    if offsets is not None:     # v = c + gain (n . b): the held term comes off before the gain
        sat = None if sat is None else sat - offsets[:, None]
        vals = vals - offsets[:, None].astype(np.float32)
    vals = vals / gain
    sat = None if sat is None else sat / gain
    return sphere, disc, vals, sat, None if offsets is None else np.zeros(len(offsets))


def fit_sphere(images, sphere: Sphere, *, pixel_size_um: float, saturation=None, files=None,
               camera_distance_mm: Optional[float] = None) -> SphereFit:
    """Every lamp's ray from one sphere (see the module notes).

    Parameters
    ----------
    images : (K, M, N[, C]) array-like
        The sphere capture (counts, dark frame removed if there is one).
    sphere : Sphere
        ``kind`` auto is decided from the images.
    pixel_size_um : float
    saturation : float, optional
        Counts at/above which a sample is saturated (left out of a matte fit; a glossy highlight's
        saturated samples are its disc).
    files : list of str, optional
        Image names for the messages.
    camera_distance_mm : float, optional
        The camera's centre of projection above the painting's plane (mm): each pixel's normal is where
        its ray meets the sphere, and a highlight reflects the view from its own surface point
        (:mod:`uvps.core.sphere_view`); None: orthographic (viewer along +z).

    Raises
    ------
    UVPSInputError
        When an image shows no highlight (glossy) or no lit part Lambert's law fits (matte), naming it.
    """
    K, M, N = images.shape[:3]
    disc = _Disc(sphere, (M, N), pixel_size_um, camera_distance_mm=camera_distance_mm)
    # the sphere's box under every lamp, read once in the files' own type: the refined circle's disc
    # (its centre and radius move by at most 3 %, _refine_matte_circle's bounds) is read from it too
    outer = _crop_box(sphere.centre_px, sphere.radius_px, (M, N), margin=1.08)
    crops = np.stack([images[k, outer[0]:outer[1], outer[2]:outer[3]] for k in range(K)])
    vals = _disc_values(crops, outer, disc)
    sat = None if saturation is None else 0.995 * float(saturation)
    kind = sphere.kind if sphere.kind in KINDS else _kind_of(vals, disc, sat)
    static = None if kind == "matte" else _static_part(vals)
    sphere = Sphere(tuple(sphere.centre_px), float(sphere.radius_px), kind, sphere.source)
    where = f"sphere at ({sphere.centre_px[0]:.0f}, {sphere.centre_px[1]:.0f}) px"
    offsets = None
    if kind == "matte":
        sphere, disc, vals, sat, offsets = _matte_disc(sphere, disc, crops, outer, vals, sat, shape=(M, N),
                                                       pixel_size_um=pixel_size_um, where=where)
    pts = np.empty((K, 3))
    dirs = np.empty((K, 3))
    sig = np.empty(K)
    strength = np.empty(K)
    npx = np.empty(K, np.int64)
    resid = np.zeros(K)
    for k in range(K):
        name = files[k] if files else f"image {k + 1}"
        if kind == "matte":
            fit = _fit_matte(vals[k], disc.normals, sat if sat is None or np.ndim(sat) < 2 else sat[k],
                             None if offsets is None else offsets[k])
            if fit is None or fit[4] > 0.2:
                raise UVPSInputError(f"sphere capture {name}: the matte {where} shows no lit part that Lambert's "
                                     "law fits (no sphere there, the lamp off, or the sphere not matte); "
                                     "give the kind with --sphere-kind (glossy or mirror for a highlight) or the "
                                     "circles with --sphere-circles")
            b, _, cov, n_used, rms, _ = fit
            nb = np.linalg.norm(b)
            d = b / nb
            P = np.eye(3) - np.outer(d, d)
            sig[k] = math.degrees(math.sqrt(max(np.trace(P @ cov @ P), 0.0)) / nb)
            dirs[k], pts[k], strength[k], npx[k], resid[k] = d, disc.centre_mm, nb, n_used, rms
        else:
            fit = (_fit_mirror(vals[k], vals[k] - static, disc, sat) if kind == "mirror"
                   else _fit_glossy(vals[k], disc, sat, static))
            if fit is None:
                raise UVPSInputError(f"sphere capture {name}: no highlight on the {kind} {where} (no sphere there, "
                                     "or the lamp off); give the kind with --sphere-kind (matte for a shaded "
                                     "sphere) or the circles with --sphere-circles")
            nm, peak, n_used, sigma_px = fit
            # the reflection law at the highlight's surface point: its view vector is exact there (across a
            # 5 mm ball under a camera 300 mm away the view turns by 0.95 deg, across a 0.25 mm lobe by 0.05)
            view = disc.view(nm)
            cos_v = nm @ view           # a numpy float (sigma_px may be float32: the division stays in float64)
            d = 2 * cos_v * nm - view
            dirs[k] = d / np.linalg.norm(d)
            pts[k] = disc.centre_mm + disc.radius_mm * nm
            sig[k] = math.degrees(2 * sigma_px / (sphere.radius_px * max(cos_v, 0.3)))
            strength[k], npx[k] = peak, n_used
    return SphereFit(sphere, pts, dirs, sig, strength, npx, resid)


# ------------------------------------------------------------------------------------------------
# rays -> positions
# ------------------------------------------------------------------------------------------------

def triangulate(points, directions, sigma_rad):
    """The point closest to several rays, weighted, and its covariance.

    Parameters
    ----------
    points, directions : (S, 3)
        Each ray's origin (mm) and unit direction.
    sigma_rad : (S,)
        Each direction's standard uncertainty (rad).

    Returns
    -------
    position : (3,) mm
    cov : (3, 3) mm^2
        ``(sum_i w_i (I - d_i d_i^T))^-1`` with ``w_i = 1 / (t_i sigma_i)^2``, ``t_i`` the distance along
        ray i: each ray pins the point across itself to ``t_i sigma_i``.
    miss : float
        The rms distance of the rays from the point (mm).

    Examples
    --------
    >>> import numpy as np
    >>> L = np.array([100.0, 50.0, 300.0])
    >>> P = np.array([[-10.0, 0, 0], [10.0, 0, 0]])
    >>> D = (L - P) / np.linalg.norm(L - P, axis=1, keepdims=True)
    >>> pos, cov, miss = triangulate(P, D, np.full(2, 1e-3))
    >>> np.allclose(pos, L), miss < 1e-9
    (True, True)
    """
    P = np.asarray(points, float)
    D = np.asarray(directions, float)
    s = np.maximum(np.asarray(sigma_rad, float), 1e-6)
    proj = np.eye(3)[None] - D[:, :, None] * D[:, None, :]
    w = np.ones(len(P))
    for _ in range(2):
        A = (w[:, None, None] * proj).sum(axis=0)
        rhs = (w[:, None, None] * proj @ P[:, :, None]).sum(axis=0)[:, 0]
        L = np.linalg.lstsq(A, rhs, rcond=None)[0]
        t = np.maximum(np.einsum("ij,ij->i", L - P, D), 1e-3)
        w = 1.0 / (t * s) ** 2
    A = (w[:, None, None] * proj).sum(axis=0)
    rhs = (w[:, None, None] * proj @ P[:, :, None]).sum(axis=0)[:, 0]
    L = np.linalg.lstsq(A, rhs, rcond=None)[0]
    miss = np.sqrt(np.mean(np.einsum("ijk,ik->ij", proj, L - P) ** 2 * 3))
    return L, np.linalg.pinv(A), float(miss)


def _from_rays(fits, dirs, sig, K, diag) -> LampCalibration:
    """Two or more spheres: each lamp's position where its rays meet (:func:`triangulate`), or far-light
    directions when the rays are too nearly parallel to place the lamps."""
    pos = np.empty((K, 3))
    psig = np.empty((K, 3))
    dsig = np.empty(K)
    miss = np.empty(K)
    pts = np.array([f.points_mm for f in fits])
    for k in range(K):
        L, cov, miss[k] = triangulate(pts[:, k], dirs[:, k], np.radians(sig[:, k]))
        pos[k] = L
        psig[k] = np.sqrt(np.diag(cov))
        u = L / np.linalg.norm(L)
        # the ray misses beyond their stated uncertainty widen it (a model error the covariance lacks)
        along = math.sqrt(float(u @ cov @ u))
        dsig[k] = 100.0 * along / np.linalg.norm(L)
    spread = [float(np.degrees(np.arccos(np.clip(dirs[0, k] @ dirs[1, k], -1, 1)))) for k in range(K)]
    diag["direction_spread_deg"] = spread
    if np.median(dsig) > 100 * MAX_DISTANCE_UNCERTAINTY or np.any(pos[:, 2] <= 0):
        diag["positions"] = (f"{len(fits)} spheres, but their rays are too nearly parallel to place the lamps "
                             f"(median distance uncertainty {np.median(dsig):.0f} %): far-light directions")
        d = dirs.mean(axis=0)
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        out = LampCalibration(d, sig.min(axis=0), fits, diagnostics=diag)
    else:
        diag["positions"] = f"{len(fits)} spheres: lamp positions from the intersection of their rays"
        d = pos / np.linalg.norm(pos, axis=1, keepdims=True)
        # the direction from the image centre: the position's uncertainty across the line of sight
        dir_sig = np.degrees(np.sqrt(np.maximum(psig ** 2 @ np.ones(3) - (dsig / 100 * np.linalg.norm(pos, axis=1)) ** 2,
                                                0)) / np.linalg.norm(pos, axis=1))
        out = LampCalibration(d, dir_sig, fits, pos, psig, dsig, miss, diagnostics=diag)
    return out


def _check_camera_distance(camera_distance_mm, sphere: Optional[Sphere], pixel_size_um: float) -> None:
    """One line naming the option when the camera's distance is not a distance above the sphere (or,
    without one, not a positive number)."""
    D = camera_distance_mm
    if D is None:
        return
    top = 0.0 if sphere is None else 2.0 * sphere.radius_px * pixel_size_um / 1000.0
    ok = isinstance(D, (int, float)) and not isinstance(D, bool) and math.isfinite(D) and D > top
    if not ok:
        where = "" if sphere is None else (f", above the spheres (the one at ({sphere.centre_px[0]:.0f}, "
                                           f"{sphere.centre_px[1]:.0f}) px is {top:.3g} mm tall)")
        raise UVPSInputError(f"camera_distance_mm must be the distance in mm from the painting to the lens's centre "
                             f"of projection{where}; got {D!r}")


def calibrate_spheres(images, *, pixel_size_um: float, spheres: Optional[Sequence[Sphere]] = None,
                      saturation=None, files=None, kind: str = "auto", capture: Optional[str] = None,
                      camera_distance_mm: Optional[float] = None, progress: Progress = None) -> LampCalibration:
    """Every lamp's direction, and with two or more spheres its position, from a sphere capture.

    Parameters
    ----------
    images : (K, M, N[, C]) array-like
        One image per lamp position, in the order of the painting capture's images.
    pixel_size_um : float
        The pixel on the plane of the painting (the spheres' radius in mm follows).
    spheres : sequence of Sphere, optional
        Given circles (override detection); None: :func:`detect_spheres`.
    saturation : float, optional
        Counts at/above which a sample is saturated.
    files : list of str, optional
        Image names for the messages.
    kind : {"auto", "matte", "glossy", "mirror"}
        The spheres' kind, for detected spheres and given ones without their own (before the fit);
        auto: from the images (:func:`_kind_of`).
    capture : str, optional
        The capture's name (folder or file) for the messages.
    camera_distance_mm : float, optional
        Its centre of projection above the painting, mm (:func:`fit_sphere`; in ``diagnostics``); None: orthographic.
    progress : callable, optional

    Returns
    -------
    LampCalibration

    Raises
    ------
    UVPSInputError
        No sphere found (naming the capture), or an image where a sphere shows nothing (naming it).

    Notes
    -----
    Cost: the detection reads every n-th pixel of each image (n = long side / 1000) and each sphere's
    box at full resolution; the fits are linear least squares over the disc (matte) or a centroid
    (glossy). Two or more spheres: :func:`triangulate` per lamp; when the rays are too nearly
    parallel to give a distance within :data:`MAX_DISTANCE_UNCERTAINTY` (median over lamps), the
    calibration keeps directions only and says so in ``diagnostics["positions"]``.
    """
    K, M, N = images.shape[:3]
    if kind not in KINDS + ("auto",):
        raise UVPSInputError(f"sphere kind must be auto, {', '.join(KINDS)}; got {kind!r}")
    _check_camera_distance(camera_distance_mm, None, pixel_size_um)
    given = spheres is not None
    first = files[0] if files else "the first image"
    first = f"{capture}, {first}" if capture else first
    if spheres is None:
        clipped = []
        spheres = detect_spheres(images, progress=progress, clipped_out=clipped)
        if not spheres and clipped:
            s = clipped[0]
            raise UVPSInputError(f"sphere capture {first}: every sphere found is cut by the frame (the one at "
                                 f"({s.centre_px[0]:.0f}, {s.centre_px[1]:.0f}) px, radius {s.radius_px:.0f} px, "
                                 f"in {N} x {M} images); expected at least one sphere whole in the frame: "
                                 "photograph it again with a margin around it")
        if not spheres:
            raise UVPSInputError(f"no sphere found in the sphere capture ({K} images from {first}); expected a "
                                 "matte, glossy or mirror sphere whole in the frame, or give the circles with "
                                 "--sphere-circles (col,row,radius_px) or a room-lit picture of them with "
                                 "--sphere-reference")
    if kind != "auto":
        spheres = [Sphere(s.centre_px, s.radius_px, kind if s.kind == "auto" else s.kind, s.source) for s in spheres]
    for s in spheres:
        c, r = s.centre_px
        if not (0 <= c < N and 0 <= r < M):
            raise UVPSInputError(f"sphere at ({c:g}, {r:g}) px lies outside the {N} x {M} images")
        _check_camera_distance(camera_distance_mm, s, pixel_size_um)
    fits = []
    # the spheres are fitted side by side, one thread each (their numpy and compiled work releases the
    # GIL): 64 lamps on two matte spheres took 10.0 s one after the other, 7.5 s side by side
    with ThreadPoolExecutor(max_workers=max(1, min(len(spheres), os.cpu_count() or 1))) as pool:
        futures = [pool.submit(fit_sphere, images, s, pixel_size_um=pixel_size_um, saturation=saturation,
                               files=files, camera_distance_mm=camera_distance_mm) for s in spheres]
        for i, (s, fut) in enumerate(zip(spheres, futures)):
            try:
                fits.append(fut.result())
            except (UVPSInputError, np.linalg.LinAlgError):
                if given or len(spheres) == 1:
                    for other in futures:
                        other.cancel()
                    raise
                log.info("detected circle at (%.0f, %.0f) r %.0f px is not a sphere under these lamps; left out",
                         s.centre_px[0], s.centre_px[1], s.radius_px)
            report(progress, 0.5 + 0.4 * (i + 1) / len(spheres), f"sphere {i + 1} of {len(spheres)}")
    if not fits:
        raise UVPSInputError(f"no sphere found in the sphere capture ({K} images from {first}): the circles found "
                             "show no highlight or Lambertian shading; give the kind with --sphere-kind or the "
                             "circles with --sphere-circles (col,row,radius_px)")
    diag = {"spheres": [f.sphere.to_json() for f in fits], "direction_spread_deg": None,
            "positions": "one sphere: far-light directions", "camera_distance_mm": camera_distance_mm}
    dirs = np.array([f.directions for f in fits])                        # (S, K, 3)
    sig = np.array([f.sigma_deg for f in fits])                          # (S, K)
    if len(fits) == 1:
        out = LampCalibration(dirs[0].copy(), sig[0].copy(), fits, diagnostics=diag)
        report(progress, 1.0, "spheres: done")
        return out
    out = _from_rays(fits, dirs, sig, K, diag)
    report(progress, 1.0, "spheres: done")
    return out
