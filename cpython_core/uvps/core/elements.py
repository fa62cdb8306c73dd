"""XRF element maps against the run: registration onto the albedo, resampling, per-area and
per-protrusion element values, and their rank correlation with protrusion density.

The paper's conclusion rests on one comparison (Salvant et al., Sec. 4 and Fig. 5b): protrusions
are abundant in the light, lead-white-rich colour areas and nearly absent in the dark ones, shown by
registering XRF element maps (Pb, Cr, Fe, Cd; 250 um step, 1 mm spot) onto the UV albedo with the
protrusions overlaid. This module is that comparison's numeric side; reading the maps' files is in
:mod:`uvps.commands.elements`.

Frames. A map pixel ``(col, row)`` and a run pixel ``(col, row)`` are pixel centres (OpenCV's and
scikit-image's convention). :class:`ElementRegistration` holds ``map_to_run``, the 3 x 3 matrix of
the similarity that takes the first to the second (homogeneous, last row ``0 0 1``).

Registration (:func:`register_maps`). The maps are 15-20x coarser than the run, rotated and shifted
against the camera, and an element's counts relate to the paint colour area by area, not by one
intensity law. Each map is modelled as a mixture of the run's colour areas blurred by the XRF spot
and sampled where the similarity sends its pixels; a coarse search by normalised cross-correlation
(``cv2.matchTemplate``, sign-free) gives the start and ``scipy.optimize.least_squares`` refines the
four parameters. The residual of an automatic registration is how far each quarter of the overlap,
registered alone by translation, moves from the whole: rms in map pixels.
"""
from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field
from typing import Optional, Sequence

import cv2
import numpy as np
from scipy import linalg, ndimage, optimize

from ..errors import UVPSInputError
from .progress import Progress, report

log = logging.getLogger(__name__)

#: Rotations (deg) and scales tried by the coarse search, around the nominal scale step / pixel.
COARSE_ROTATIONS_DEG = tuple(np.arange(-4.0, 4.01, 1.0))
COARSE_SCALES = (0.94, 0.97, 1.0, 1.03, 1.06)


@dataclass
class ElementMaps:
    """Element maps of one XRF scan, on one grid.

    Attributes
    ----------
    names : list of str
        One name per map (e.g. ``"Pb_L"``), from the file names or a header.
    data : (E, H, W) float64
        Counts (or fitted peak areas) per map pixel; NaN where the scan has no value.
    step_um : float
        The scan's step (map pixel size) in micrometres.
    sources : list of str
        The file each map was read from.
    """

    names: list
    data: np.ndarray
    step_um: float
    sources: list = field(default_factory=list)

    @property
    def shape(self) -> tuple:
        return tuple(self.data.shape[1:])


@dataclass
class ElementRegistration:
    """A map-to-run similarity.

    Attributes
    ----------
    map_to_run : (3, 3) float64
        Map pixel (col, row, 1) -> run pixel (col, row, 1).
    method : str
        ``"automatic"``, ``"control points"`` or ``"control points, refined"``.
    residual_map_px : float
        Rms residual in map pixels: of the control points under the final similarity, or (automatic)
        of the quarters' own translations against the whole.
    residual_of : str
        ``"control points"`` or ``"quarters"``.
    reference : list of str
        The elements the registration was fitted on.
    explained : float
        Fraction of the (standardised) maps' variance that the colour areas' mixture explains at
        the result: near 1 where composition follows the colour areas.
    overlap : float
        Fraction of the run's field that the map covers.
    """

    map_to_run: np.ndarray
    method: str
    residual_map_px: float
    residual_of: str
    reference: list
    explained: float
    overlap: float

    @property
    def scale(self) -> float:
        """Run pixels per map pixel."""
        return float(math.sqrt(abs(np.linalg.det(self.map_to_run[:2, :2]))))

    @property
    def rotation_deg(self) -> float:
        return float(np.degrees(np.arctan2(self.map_to_run[1, 0], self.map_to_run[0, 0])))

    def to_json(self) -> dict:
        return {"map_to_run": [[float(v) for v in row] for row in self.map_to_run],
                "from": "map pixel (col, row, 1)", "to": "run pixel (col, row, 1)",
                "method": self.method, "residual_map_px": round(float(self.residual_map_px), 4),
                "residual_of": self.residual_of, "reference": list(self.reference),
                "explained_by_areas": round(float(self.explained), 4),
                "overlap": round(float(self.overlap), 4),
                "scale_run_px_per_map_px": round(self.scale, 5), "rotation_deg": round(self.rotation_deg, 4)}


# ------------------------------------------------------------------------------------------------
# the similarity
# ------------------------------------------------------------------------------------------------

def similarity(scale: float, rotation_deg: float, tx: float, ty: float) -> np.ndarray:
    """The 3 x 3 matrix ``[[s cos, -s sin, tx], [s sin, s cos, ty], [0, 0, 1]]`` (pixel (col, row))."""
    t = math.radians(rotation_deg)
    c, s = scale * math.cos(t), scale * math.sin(t)
    return np.array([[c, -s, tx], [s, c, ty], [0.0, 0.0, 1.0]])


def apply(matrix: np.ndarray, cols, rows) -> tuple:
    """Points (cols, rows) through a 3 x 3 affine matrix."""
    cols, rows = np.asarray(cols, float), np.asarray(rows, float)
    return (matrix[0, 0] * cols + matrix[0, 1] * rows + matrix[0, 2],
            matrix[1, 0] * cols + matrix[1, 1] * rows + matrix[1, 2])


def registration_error_map_px(estimated: np.ndarray, truth: np.ndarray, map_shape, run_shape) -> float:
    """Rms distance (map pixels) between two map-to-run similarities over the map pixels that fall in
    the run's field under ``truth`` (the benchmark's and the tests' measure)."""
    H, W = map_shape
    rr, cc = np.mgrid[0:H, 0:W]
    x, y = apply(truth, cc.ravel(), rr.ravel())
    inside = (x >= 0) & (x <= run_shape[1] - 1) & (y >= 0) & (y <= run_shape[0] - 1)
    xe, ye = apply(estimated, cc.ravel()[inside], rr.ravel()[inside])
    d = np.hypot(xe - x[inside], ye - y[inside])
    scale = math.sqrt(abs(np.linalg.det(truth[:2, :2])))
    return float(np.sqrt(np.mean(d ** 2)) / scale)


# ------------------------------------------------------------------------------------------------
# the reference: the colour areas as the XRF scanner would see them
# ------------------------------------------------------------------------------------------------

def spot_sigma_px(spot_um: float, pixel_size_um: float) -> float:
    """Gaussian sigma (run pixels) of a spot of FWHM ``spot_um``."""
    return spot_um / (2.0 * math.sqrt(2.0 * math.log(2.0))) / pixel_size_um


@dataclass
class _Reference:
    """The run's field as the scanner sees it, at a reduced resolution (the spot blurs far more
    than the reduction loses): ``channels`` (C, m, n), run pixel = ``factor`` x reduced pixel."""

    channels: np.ndarray
    factor: float
    run_shape: tuple


def _blurred(stack: np.ndarray, sigma_px: float, factor: int) -> np.ndarray:
    """Each image reduced by ``factor`` (area means), then blurred by the spot (its sigma in reduced
    pixels): the same as blurring first where the spot is several reduced pixels wide, and about
    ``factor^2`` times cheaper."""
    out = []
    for ch in stack:
        ch = ch.astype(np.float32)
        if factor > 1:
            # cropped to whole blocks first, so reduced pixel i is exactly run pixels f*i .. f*i + f - 1
            m, n = ch.shape[0] // factor, ch.shape[1] // factor
            ch = cv2.resize(ch[:m * factor, :n * factor], (n, m), interpolation=cv2.INTER_AREA)
        out.append(cv2.GaussianBlur(ch, (0, 0), sigma_px / factor, borderType=cv2.BORDER_REFLECT))
    return np.stack(out)


def reference_of(labels: np.ndarray, albedo: Optional[np.ndarray], *, sigma_px: float) -> tuple:
    """The two references of the registration: each colour area's indicator blurred by the spot
    (an element's counts are their mixture, weighted by its abundance in each area) and the
    albedo's channels blurred alike (for the coarse search)."""
    labels = np.asarray(labels)
    factor = max(1, int(sigma_px // 3))
    ids = np.unique(labels)
    ind = _blurred(np.stack([(labels == i) for i in ids]), sigma_px, factor).astype(np.float64)
    areas = _Reference(ind, float(factor), labels.shape)
    if albedo is None:
        return areas, None
    a = np.asarray(albedo, dtype=np.float32)
    a = a[..., None] if a.ndim == 2 else a
    col = _blurred(np.moveaxis(np.nan_to_num(a), -1, 0), sigma_px, factor).astype(np.float64)
    return areas, _Reference(np.concatenate([col, ind]), float(factor), labels.shape)


def _sample(ref: _Reference, matrix: np.ndarray, grid) -> np.ndarray:
    """Reference channels at the map pixels ``grid`` sent into the run: (C, P), clamped at the
    field's edge."""
    x, y = apply(matrix, *grid)
    f = ref.factor
    # reduced pixel centre i covers run pixels f*i .. f*i + f - 1: its centre is f*i + (f - 1)/2
    xr, yr = (x - (f - 1) / 2) / f, (y - (f - 1) / 2) / f
    return np.stack([ndimage.map_coordinates(ch, [yr, xr], order=1, mode="nearest") for ch in ref.channels])


def _inside(matrix, grid, run_shape, margin_px: float = 0.0) -> np.ndarray:
    x, y = apply(matrix, *grid)
    M, N = run_shape
    return (x >= margin_px) & (x <= N - 1 - margin_px) & (y >= margin_px) & (y <= M - 1 - margin_px)


def _mixing_residual(maps_z: np.ndarray, ref: _Reference, matrix: np.ndarray, grid) -> np.ndarray:
    """Each element map (standardised) less its best mixture of the blurred colour areas at the
    sampled places (one least-squares projection shared by every element)."""
    # the areas' indicators sum to 1 (label 0 is an area too), so they hold the constant term
    X = _sample(ref, matrix, grid).T
    # normal equations of a few columns (a tiny ridge for an area no sample reaches): LAPACK's
    # lstsq on the tall matrix took 50 times as long
    XtX = X.T @ X
    XtX[np.diag_indices_from(XtX)] += 1e-9 * np.trace(XtX) + 1e-12
    coef = linalg.solve(XtX, X.T @ maps_z.T, assume_a="pos", check_finite=False)
    return (maps_z.T - X @ coef).ravel()


# ------------------------------------------------------------------------------------------------
# registration
# ------------------------------------------------------------------------------------------------

def _coarse(maps: np.ndarray, ref: _Reference, nominal: float) -> np.ndarray:
    """Best similarity of the coarse search: each reference channel (the blurred albedo's channels
    and colour areas) brought to the map's step, rotated and scaled, is matched against each map by
    normalised cross-correlation (absolute value: an element may be poor where the paint is
    bright)."""
    M, N = ref.run_shape
    f = ref.factor
    best = (-1.0, None)
    H, W = maps.shape[1:]
    filled = [np.where(np.isfinite(m), m, np.nanmedian(m)).astype(np.float32) for m in maps]
    m_c, n_c = ref.channels.shape[1:]
    for s in COARSE_SCALES:
        k = f / (nominal * s)   # map pixels per reduced pixel
        for rot in COARSE_ROTATIONS_DEG:
            # reduced run -> template (map-step) frame: rotate by -rot about the centre, scale by k;
            # the template is the largest axis-aligned box inside the rotated field
            A = cv2.getRotationMatrix2D(((n_c - 1) / 2, (m_c - 1) / 2), rot, k)
            tw, th = int(n_c * k), int(m_c * k)
            A[0, 2] += (tw - 1) / 2 - (n_c - 1) / 2
            A[1, 2] += (th - 1) / 2 - (m_c - 1) / 2
            cut = int(math.ceil(abs(math.sin(math.radians(rot))) * max(tw, th))) + 1
            if th - 2 * cut < 8 or tw - 2 * cut < 8 or th - 2 * cut > H or tw - 2 * cut > W:
                continue
            for ch in ref.channels:
                tmpl = cv2.warpAffine(ch.astype(np.float32), A, (tw, th), flags=cv2.INTER_LINEAR,
                                      borderMode=cv2.BORDER_REFLECT)
                tmpl = tmpl[cut:th - cut, cut:tw - cut]
                if float(tmpl.std()) == 0.0:
                    continue
                for m in filled:
                    r = np.abs(np.nan_to_num(cv2.matchTemplate(m, tmpl, cv2.TM_CCOEFF_NORMED)))
                    j = int(np.argmax(r))
                    if float(r.flat[j]) > best[0]:
                        oy, ox = divmod(j, r.shape[1])
                        best = (float(r.flat[j]), (A.copy(), ox - cut, oy - cut))
    if best[1] is None:
        raise UVPSInputError("element maps: the maps are smaller than the run's field at their step; "
                             "check --step-um, or give control points")
    A, ox, oy = best[1]
    # template pixel (u, v) = map pixel (u + ox, v + oy) = A (reduced run pixel); reduced pixel
    # (i, j) has the run pixel centre f*i + (f - 1)/2
    red_from_t = np.vstack([cv2.invertAffineTransform(A), [0, 0, 1]])
    t_from_map = np.array([[1.0, 0, -ox], [0, 1.0, -oy], [0, 0, 1]])
    run_from_red = np.array([[f, 0, (f - 1) / 2], [0, f, (f - 1) / 2], [0, 0, 1]])
    return run_from_red @ red_from_t @ t_from_map


def _params_of(matrix: np.ndarray) -> np.ndarray:
    s = math.sqrt(abs(np.linalg.det(matrix[:2, :2])))
    rot = math.degrees(math.atan2(matrix[1, 0], matrix[0, 0]))
    return np.array([matrix[0, 2], matrix[1, 2], rot, math.log(s)])


def _matrix_of(p) -> np.ndarray:
    return similarity(math.exp(p[3]), p[2], p[0], p[1])


def _standardised(maps: np.ndarray) -> np.ndarray:
    """Each map less its mean over its standard deviation (so every element weighs alike)."""
    m = maps - np.nanmean(maps, axis=1, keepdims=True)
    sd = np.nanstd(m, axis=1, keepdims=True)
    return np.nan_to_num(m / np.where(sd > 0, sd, 1.0))


def _refine(maps_z, ref, start: np.ndarray, grid, *, translation_only=False) -> np.ndarray:
    """Least squares of the mixing residual over the similarity (``scipy.optimize.least_squares``,
    variable projection: the areas' abundances are solved inside each evaluation). Parameters are
    scaled so that one unit moves the field's edge by about one map pixel."""
    p0 = _params_of(start)
    s = math.exp(p0[3])
    half = max(ref.run_shape) / s / 2.0          # half the field in map pixels
    unit = np.array([s, s, math.degrees(1.0 / half), 1.0 / half])
    free = 2 if translation_only else 4

    def f(z):
        p = p0.copy()
        p[:free] += z * unit[:free]
        return _mixing_residual(maps_z, ref, _matrix_of(p), grid)

    def jac(z):
        # forward differences with an absolute step of 0.05 map px: least_squares' own steps are
        # relative to x, and x starts at 0, where it falls back to 1e-8, below the bilinear
        # interpolation's smoothness
        f0 = f(z)
        cols = []
        for i in range(free):
            e = z.copy()
            e[i] += 0.05
            cols.append((f(e) - f0) / 0.05)
        return np.column_stack(cols)

    res = optimize.least_squares(f, np.zeros(free), jac=jac, xtol=1e-3, ftol=1e-6, max_nfev=40)
    p = p0.copy()
    p[:free] += res.x * unit[:free]
    return _matrix_of(p)


def _grid_inside(matrix, map_shape, run_shape, margin_px) -> tuple:
    H, W = map_shape
    rr, cc = np.mgrid[0:H, 0:W]
    grid = (cc.ravel().astype(float), rr.ravel().astype(float))
    keep = _inside(matrix, grid, run_shape, margin_px)
    return (grid[0][keep], grid[1][keep]), keep


def register_maps(albedo: Optional[np.ndarray], maps: ElementMaps, *, labels: np.ndarray, pixel_size_um: float,
                  spot_um: float = 1000.0, reference: Optional[Sequence[str]] = None,
                  control_points: Optional[np.ndarray] = None, refine: bool = False,
                  progress: Progress = None) -> ElementRegistration:
    """Register element maps onto a run.

    An element's counts at a scan point are the spot-weighted mean of its abundance in the paint
    under the spot. Where the paint's composition follows its colour areas, every element map is
    therefore a mixture of the areas' indicators blurred by the spot, sampled where the similarity
    sends the map's pixels: ``E_e(u) = sum_a c_ea B_a(T(u)) + c_e0``. The similarity ``T`` minimises
    what no mixture explains (least squares over T, the mixtures solved inside each evaluation:
    variable projection), from the start a coarse search by normalised cross-correlation gives, or
    from the control points. Unlike a fixed intensity relation (correlation) it holds for an
    element poor in the bright paint as well as one rich in it, and unlike a histogram measure
    (mutual information) it is smooth in T, so least squares reach a fraction of a map pixel.

    Parameters
    ----------
    albedo : (M, N) or (M, N, C) array, optional
        The run's albedo (the coarse search also matches its channels); None: areas only.
    maps : ElementMaps
    labels : (M, N) int array
        The run's colour areas (0 = in none, itself a class).
    pixel_size_um : float
        The run's pixel size.
    spot_um : float
        The XRF spot's width (FWHM, um).
    reference : sequence of str, optional
        The elements to register on (default all).
    control_points : (P, 4) array, optional
        Rows ``map_col, map_row, run_col, run_row`` (pixel centres); two or more fix the similarity
        (least squares, :class:`skimage.transform.SimilarityTransform`).
    refine : bool
        With control points: refine their similarity by the mixing residual (kept when it moves the
        points by less than 2 map pixels rms). Off by default: where composition varies inside the
        areas the mixture's optimum lies 0.3 map px off (docs/benchmarks.md, "Element maps"),
        farther than 4 careful clicks.

    Returns
    -------
    ElementRegistration
    """
    names = list(maps.names) if reference is None else list(reference)
    unknown = [n for n in names if n not in maps.names]
    if unknown:
        raise UVPSInputError(f"reference element {unknown[0]!r} is not among the maps ({', '.join(maps.names)})")
    sel = np.stack([maps.data[maps.names.index(n)] for n in names])
    M, N = np.asarray(labels).shape
    H, W = maps.shape
    nominal = maps.step_um / pixel_size_um
    report(progress, 0.05, "colour areas at the spot's width")
    areas, coarse_ref = reference_of(labels, albedo, sigma_px=spot_sigma_px(spot_um, pixel_size_um))
    flat = sel.reshape(sel.shape[0], -1)
    margin = 2.0 * nominal

    def fit(start, **kw):
        grid, keep = _grid_inside(start, (H, W), (M, N), margin)
        if keep.sum() < 16:
            raise UVPSInputError("element maps: fewer than 16 map pixels fall in the run's field; check "
                                 "--step-um and that the maps show this region")
        return _refine(_standardised(flat[:, keep]), areas, start, grid, **kw)

    if control_points is not None:
        from skimage.transform import SimilarityTransform
        cp = np.asarray(control_points, float)
        if hasattr(SimilarityTransform, "from_estimate"):      # scikit-image >= 0.26
            tf = SimilarityTransform.from_estimate(cp[:, :2], cp[:, 2:4])
            ok = bool(tf)
        else:
            tf = SimilarityTransform()
            ok = tf.estimate(cp[:, :2], cp[:, 2:4])
        if not ok:
            raise UVPSInputError("control points: no similarity fits them (are they all on one point?)")
        start = np.asarray(tf.params, float)
        matrix, method = start, "control points"
        if refine:
            report(progress, 0.4, "refining by the colour areas")
            cand = fit(start)
            moved = registration_error_map_px(cand, start, maps.shape, (M, N))
            if moved < 2.0:
                matrix, method = cand, "control points, refined"
            else:
                log.warning("element maps: the colour areas would move the control points' registration "
                            "by %.2f map px; the control points' similarity is kept", moved)
        resid, residual_of = _control_residual(matrix, cp), "control points"
    else:
        report(progress, 0.1, "coarse search")
        ref = coarse_ref if coarse_ref is not None else areas
        start = _coarse(sel, ref, nominal)
        report(progress, 0.3, "refining by the colour areas")
        matrix = fit(start)
        report(progress, 0.7, "checking quarter by quarter")
        resid = _quarter_residual(flat, areas, matrix, (H, W), (M, N), margin)
        method, residual_of = "automatic", "quarters"
    grid, keep = _grid_inside(matrix, (H, W), (M, N), 0.0)
    explained = _explained(_standardised(flat[:, keep]), areas, matrix, grid) if keep.sum() >= 16 else 0.0
    overlap = _overlap(matrix, (H, W), (M, N))
    report(progress, 1.0, "registered")
    return ElementRegistration(matrix, method, resid, residual_of, names, explained, overlap)


def _explained(maps_z, ref, matrix, grid) -> float:
    """Fraction of the standardised maps' variance the colour areas' mixture explains."""
    r = _mixing_residual(maps_z, ref, matrix, grid)
    return float(1.0 - np.mean(r ** 2) / max(np.mean(maps_z ** 2), 1e-12))


def _control_residual(matrix: np.ndarray, cp: np.ndarray) -> float:
    inv = np.linalg.inv(matrix)
    x, y = apply(inv, cp[:, 2], cp[:, 3])
    return float(np.sqrt(np.mean((x - cp[:, 0]) ** 2 + (y - cp[:, 1]) ** 2)))


def _quarter_residual(flat, areas, matrix, map_shape, run_shape, margin) -> float:
    """Each quarter of the map's overlap with the run, registered alone by translation from the
    whole's similarity: the rms of those translations (map pixels). A similarity that holds moves
    them by about its own noise; one caught on a wrong optimum, or a scan that is not a similarity
    of the camera's view, moves them by pixels."""
    grid, keep = _grid_inside(matrix, map_shape, run_shape, margin)
    if keep.sum() < 64:
        return float("inf")
    cols, rows = grid
    cx, cy = np.median(cols), np.median(rows)
    shifts = []
    for qx in (cols < cx, cols >= cx):
        for qy in (rows < cy, rows >= cy):
            q = qx & qy
            moved = _refine(_standardised(flat[:, keep][:, q]), areas, matrix, (cols[q], rows[q]),
                            translation_only=True)
            shifts.append(registration_error_map_px(moved, matrix, map_shape, run_shape))
    return float(np.sqrt(np.mean(np.square(shifts))))


def _overlap(matrix, map_shape, run_shape) -> float:
    """Fraction of the run's field inside the map."""
    M, N = run_shape
    H, W = map_shape
    inv = np.linalg.inv(matrix)
    rr, cc = np.mgrid[0:M:8, 0:N:8]
    u, v = apply(inv, cc.ravel(), rr.ravel())
    return float(np.mean((u >= -0.5) & (u <= W - 0.5) & (v >= -0.5) & (v <= H - 0.5)))


# ------------------------------------------------------------------------------------------------
# into the run's frame, and the statistics
# ------------------------------------------------------------------------------------------------

def resample_to_run(maps: ElementMaps, registration: ElementRegistration, run_shape) -> np.ndarray:
    """(E, M, N) float32: each map in the run's frame (bilinear), NaN outside the scan."""
    M, N = run_shape
    run_to_map = np.linalg.inv(registration.map_to_run)[:2]
    out = np.empty((len(maps.names), M, N), np.float32)
    H, W = maps.shape
    for e in range(len(maps.names)):
        m = maps.data[e].astype(np.float32)
        ok = np.isfinite(m).astype(np.float32)
        v = cv2.warpAffine(np.nan_to_num(m), run_to_map, (N, M), flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
                           borderMode=cv2.BORDER_CONSTANT, borderValue=0)
        w = cv2.warpAffine(ok, run_to_map, (N, M), flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
                           borderMode=cv2.BORDER_CONSTANT, borderValue=0)
        out[e] = np.where(w > 0.999, v / np.maximum(w, 1e-6), np.nan)
    return out


@dataclass
class AreaElements:
    """Element values per colour area (``elements_by_area.csv``)."""

    labels: list
    names: list
    n_map_pixels: np.ndarray      # (A,) interior map pixels per area
    mean: np.ndarray              # (A, E)
    sd: np.ndarray                # (A, E)


def area_elements(resampled: np.ndarray, labels: np.ndarray, names: dict, *, pixel_size_um: float,
                  step_um: float, spot_um: float) -> AreaElements:
    """Element means over each colour area's interior: the pixels at least the spot's width from
    the area's border (nearer, the spot sees the neighbouring paint) where the scan has a value."""
    ids = sorted(int(i) for i in names)
    E = resampled.shape[0]
    finite = np.all(np.isfinite(resampled), axis=0)
    reach = spot_um / pixel_size_um
    n = np.zeros(len(ids))
    mean = np.full((len(ids), E), np.nan)
    sd = np.full((len(ids), E), np.nan)
    for a, i in enumerate(ids):
        inside = labels == i
        if not inside.any():
            continue
        # distance to the nearest pixel outside the area (the field's edge counts as a border too);
        # OpenCV's exact transform, 10x scipy's here
        padded = np.pad(inside, 1, constant_values=False).astype(np.uint8)
        dist = cv2.distanceTransform(padded, cv2.DIST_L2, cv2.DIST_MASK_PRECISE)[1:-1, 1:-1]
        core = (dist >= reach) & finite
        n[a] = core.sum() * (pixel_size_um / step_um) ** 2
        if core.any():
            vals = resampled[:, core]
            mean[a] = vals.mean(axis=1)
            sd[a] = vals.std(axis=1, ddof=1) if core.sum() > 1 else 0.0
    return AreaElements(ids, [names[i] for i in ids], n, mean, sd)


def protrusion_elements(resampled: np.ndarray, x_px, y_px, *, pixel_size_um: float, spot_um: float) -> tuple:
    """Each protrusion's element values at its site (bilinear at its centre) and in a ring around it
    (the mean between one and two spot widths from its centre, where the spot no longer sees it).

    Returns (site (P, E), ring (P, E)).
    """
    x = np.asarray(x_px, float)
    y = np.asarray(y_px, float)
    E, M, N = resampled.shape
    site = np.full((x.size, E), np.nan)
    ring = np.full((x.size, E), np.nan)
    r1, r2 = spot_um / pixel_size_um, 2.0 * spot_um / pixel_size_um
    R = int(math.ceil(r2))
    dy, dx = np.mgrid[-R:R + 1, -R:R + 1]
    d = np.hypot(dx, dy)
    annulus = (d >= r1) & (d <= r2)
    ay, ax = dy[annulus], dx[annulus]
    for e in range(E):
        filled = np.nan_to_num(resampled[e], nan=0.0)
        ok = np.isfinite(resampled[e])
        vals = ndimage.map_coordinates(filled, [y, x], order=1, mode="nearest")
        good = ndimage.map_coordinates(ok.astype(np.float32), [y, x], order=1, mode="constant") > 0.999
        site[:, e] = np.where(good, vals, np.nan)
        for p in range(x.size):
            yy = np.rint(y[p]).astype(int) + ay
            xx = np.rint(x[p]).astype(int) + ax
            keep = (yy >= 0) & (yy < M) & (xx >= 0) & (xx < N)
            v = resampled[e, yy[keep], xx[keep]]
            v = v[np.isfinite(v)]
            if v.size:
                ring[p, e] = v.mean()
    return site, ring


@dataclass
class Correlation:
    """Spearman's rank correlation of protrusion density with one element across colour areas."""

    element: str
    n_areas: int
    rho: float
    ci_low: float
    ci_high: float
    p_value: float


def rank_correlations(density: np.ndarray, elements: AreaElements, element_names: Sequence[str], *,
                      min_map_pixels: float = 10.0, confidence: float = 0.95) -> list:
    """Spearman's rho of density against each element's area mean, over the areas with at least
    ``min_map_pixels`` interior map pixels, with a confidence interval from Fisher's z and the
    standard error ``sqrt(1.06 / (n - 3))`` (Fieller, Hartley and Pearson 1957); NaN below 4 areas."""
    out = []
    use = elements.n_map_pixels >= min_map_pixels
    from scipy import stats       # 1 s to import: only where the statistics are computed

    zq = stats.norm.ppf(0.5 + confidence / 2)
    for e, name in enumerate(element_names):
        m = elements.mean[:, e]
        ok = use & np.isfinite(m) & np.isfinite(density)
        n = int(ok.sum())
        rho = lo = hi = p = float("nan")
        if n >= 4 and np.ptp(m[ok]) > 0 and np.ptp(density[ok]) > 0:
            res = stats.spearmanr(m[ok], density[ok])
            rho, p = float(res.statistic), float(res.pvalue)
            if n > 3 and abs(rho) < 1:
                z, se = np.arctanh(rho), math.sqrt(1.06 / (n - 3))
                lo, hi = float(np.tanh(z - zq * se)), float(np.tanh(z + zq * se))
            else:
                lo = hi = rho
        out.append(Correlation(name, n, rho, lo, hi, p))
    return out
