"""Light directions and near-light positions from the images themselves (no calibration sphere).

Frame (docs/architecture.md): x toward increasing column, y up, z toward the camera; positions in mm
from the image centre; the canvas is the plane z = 0. Image model of a near point light ``L_k``::

    I_k(X) = albedo(X) * E_k * (|L_k| / |L_k - X|)^2 * n(X) . (L_k - X) / |L_k - X|

Three steps, after Salvant et al. (Fig. 1b-e) and Huang et al. (2015):

1. **Azimuth** from the drop-off fit resampled in polar coordinates about the image centre: the angle of
   maximum intensity (paper Fig. 1d), taken as the phase of the first circular harmonic of the angular
   profile, which equals the argmax for a unimodal profile and is not quantised to the bin width.
2. **Equidistant near lights** (paper Eq. 2): every lamp at the same distance ``m`` from the centre.
   For a given ``m`` each light's azimuth and elevation are fitted to its drop-off map (a flat canvas
   under ``L`` gives ``log F = -3 log |L - X| + c``); ``m`` itself is refined with
   ``scipy.optimize.least_squares`` by minimising the photometric-stereo residual ``|L(m) . N - I|`` on
   a sample of pixels, the normals solved in closed form for each trial (variable projection).
3. **Per-light refinement** (beyond the paper): every light's position and intensity, by the same
   residual plus the drop-off residual as a prior, solved to convergence on tens of thousands of
   pixels. Lamps drift as they warm up and a hand-placed lamp is never exactly equidistant.
4. **Azimuths from integrability** (beyond the paper): the lamps turned so that the normals they
   give are a height field's (:func:`integrability_correction`): the prior's flat canvas lets a
   bowed one shear the azimuths.

The trap: over a field of a few cm with the lamp tens of cm away, the drop-off gradient
``3 cos(e) / |L|`` barely separates distance from elevation, and a bowed canvas biases it. The
photometric residual over the surface texture (weave, strokes, protrusions) is what pins them; samples
near attached shadow bias it and are left out. It pins them only weakly: lamps ~20 % too close and
correspondingly higher change the mean squared residual by about 1e-4 of itself (the near-light remnant
of the bas-relief ambiguity), so the refinement needs a large sample and must not be stopped early.
"""
from __future__ import annotations

import logging
import warnings
from dataclasses import dataclass, field
from typing import Optional

import numba
import numpy as np
from numpy.polynomial import legendre as Lg
from scipy.optimize import least_squares
from skimage.transform import warp_polar

from ..errors import UVPSInputError
from .flatfield import BlockGrid, DropoffFit, to_unit, with_common
from .irradiance import LightModel, lamp_vectors, near_scale, pixel_coordinates_mm
from .progress import Progress, report, sub_progress
from .threads import concurrently, default_threads, map_bands

log = logging.getLogger(__name__)

__all__ = [
    "LightModel", "LightEstimate", "PixelSample", "azimuth_from_dropoff", "pixel_coordinates_mm",
    "estimate_lights", "intensities_from_levels", "sample_pixels", "photometric_residual",
    "LightUncertainty", "light_uncertainty", "refine_intensities", "ratio_samples", "model_logs",
    "integrability_correction", "beyond_model",
]


@dataclass
class LightEstimate:
    """Result of :func:`estimate_lights`."""

    model: LightModel
    m_mm: float
    azimuth_polar_deg: np.ndarray
    residual_history: list = field(default_factory=list)  # dicts: stage, m_mm or iteration, cost
    equidistant: Optional[LightModel] = None  # the paper's equidistant solution before refinement
    uncertainty: Optional["LightUncertainty"] = None
    fits: Optional[list] = None   # the drop-off fits with the estimated lamps' common part


@dataclass
class PixelSample:
    """Grey intensities of a sample of pixels, for the photometric residual."""

    I: np.ndarray        # (K, P)
    X: np.ndarray        # (P, 3) mm
    rows: np.ndarray
    cols: np.ndarray
    #: (K, P) 1.0 where lamp k lights pixel p, 0.0 where it leaves it dark or saturated (``I`` is 0
    #: there); None when every lamp lights every sampled pixel. A zero row drops out of the pixel's
    #: least-squares normal and of the residual: weighted variable projection with 0/1 weights is
    #: plain variable projection on the lit rows (:func:`sample_pixels`).
    W: Optional[np.ndarray] = None

    def take(self, sel) -> "PixelSample":
        """The pixels ``sel`` (indices or a slice) of the sample, with their weights."""
        return PixelSample(self.I[:, sel], self.X[sel], np.asarray(self.rows)[sel], np.asarray(self.cols)[sel],
                           None if self.W is None else self.W[:, sel])


def _vectors(sample: "PixelSample", model) -> np.ndarray:
    """The lights' vectors (K, P, 3) at the sample's pixels, zero where the lamp does not light the pixel."""
    V = model.vectors(sample.X)
    return V if sample.W is None else V * sample.W[..., None]


def _mean_lit(sample: "PixelSample") -> np.ndarray:
    """Each pixel's mean intensity over the lamps that light it (P,): the residual's normalisation."""
    if sample.W is None:
        return sample.I.mean(axis=0)
    return sample.I.sum(axis=0) / sample.W.sum(axis=0)


def azimuth_from_dropoff(fit: DropoffFit, *, n_angles=360, size=256) -> float:
    """Azimuth (degrees, counter-clockwise from +x) of the light from its drop-off map (paper Fig. 1d).

    The fit is evaluated on a square grid (isotropic in mm), resampled into polar coordinates about the
    image centre with ``skimage.transform.warp_polar`` and averaged over radii; the azimuth is the phase
    of the first circular harmonic of that angular profile (its maximum, without bin quantisation).
    """
    M, N = fit.shape
    side = min(M, N)
    rows = np.linspace((M - side) / 2, (M + side) / 2 - 1, size)
    cols = np.linspace((N - side) / 2, (N + side) / 2 - 1, size)
    F = fit.evaluate(rows, cols)
    polar = warp_polar(F, center=((size - 1) / 2, (size - 1) / 2), radius=(size - 1) / 2,
                       output_shape=(n_angles, size // 2))
    prof = polar[:, size // 8:].mean(axis=1)  # rows of warp_polar: angle from +col, clockwise on screen
    ang = np.linspace(0, 2 * np.pi, n_angles, endpoint=False)
    h = np.sum((prof - prof.mean()) * np.exp(1j * ang))
    screen = np.angle(h)  # measured toward increasing row = toward -y
    return float(np.degrees(-screen) % 360.0)


#: Total Legendre degree of the ratio maps the lamps are fitted to (the drop-off fits have
#: ``--degree``, 4 by default). A lamp's drop-off over the field is nearly a plane and a bowl; the
#: relief's large-scale shading (cupped paint, strokes, crowded protrusions) spreads over every
#: degree. Worst mean direction error over seeds 0-2 (12 lamps, RGB) at total degree 4 / 3: cupping
#: 1.76 / 1.37 deg, strokes 1.42 / 1.45, cast shadows 1.21 / 1.24, every other row within 0.03;
#: clean grey captures (seeds 3-5) of 8 lamps 1.31 / 1.45, 12-64 lamps within 0.01; worst case
#: over all 1.76 / 1.45. Degree 2 left cupping at 1.49 (seed 0). Measured by
#: ``scripts/benchmark_robustness.py --seeds 0 1 2 --modes estimated --no-detect`` and
#: ``scripts/benchmark_lights.py --lamps 8 12 16 32 64 --seeds 3 4 5`` with the degree edited.
PRIOR_DEGREE = 3


def ratio_samples(fits, shape, n=24, max_degree=None):
    """The albedo-free log ratio maps ``log(I_k / G)`` on an n x n grid, each centred to mean 0;
    with ``max_degree``, only the fits' terms of total Legendre degree up to it."""
    M, N = shape
    rows = np.linspace(0, M - 1, n)
    cols = np.linspace(0, N - 1, n)
    Vv = Lg.legvander(to_unit(rows, M), fits[0].degree)
    Vu = Lg.legvander(to_unit(cols, N), fits[0].degree)
    i, j = np.indices(fits[0].ratio_coeffs.shape)
    keep = (i + j <= max_degree) if max_degree is not None else np.ones(i.shape, bool)
    R = np.stack([Vv @ (f.ratio_coeffs * keep) @ Vu.T for f in fits])
    return rows, cols, R - R.mean(axis=(1, 2), keepdims=True)


def model_logs(P, X):
    """Model log drop-offs of all lights on the flat canvas, each centred: (K, ...).

    The X-dependent part of log irradiance on the flat canvas from a point light is ``-3 log |L - X|``.
    """
    P = np.asarray(P, dtype=float)
    V = P.reshape((len(P),) + (1,) * (X.ndim - 1) + (3,)) - X[None]
    h = -1.5 * np.log(np.einsum("...i,...i->...", V, V))
    return h - h.mean(axis=tuple(range(1, h.ndim)), keepdims=True)


def beyond_model(fits, P, shape, pixel_size_um, *, keep_relief=True):
    """What each image's drop-off holds beyond the point-light model of known positions ``P``.

    Parameters
    ----------
    fits : list of DropoffFit
    P : (K, 3) lamp positions (mm)
    shape : (M, N)
    pixel_size_um : float
    keep_relief : bool
        Leave out of the result the part a smooth tilt of the canvas (its bow) explains.

    Returns
    -------
    rows, cols : (n,) grid coordinates (px)
    delta : (K, n, n)
        Log gains beyond the model on the grid, each centred over the lamps at every grid point
        and over the field for every lamp: a lamp's beam, its aim.

    Notes
    -----
    A smooth tilt of the canvas by slopes ``(p, q)`` at ``X`` changes lamp k's log shading by
    ``log(l_z - p l_x - q l_y) - log l_z ~ -p t_x - q t_y`` with ``t = (l_x, l_y) / l_z`` the lamp's
    direction at ``X`` (to first order in the slopes; 250 um of bow across 24 mm: slopes under 0.04,
    the second-order term under 1 % of the first). That part is linear in ``t_k``; a beam's gain,
    which depends on where each lamp is aimed, is not. With ``keep_relief`` the part of ``delta`` at
    each grid point that is linear in the lamps' ``t`` (two numbers per point, K lamps) is left to the
    relief: a beam keeps all but its projection on those two patterns, the bow's shading none.
    """
    rows, cols, R = ratio_samples(fits, shape)
    X = pixel_coordinates_mm(rows[:, None], cols[None, :], shape, pixel_size_um)
    h = model_logs(P, X)
    delta = R - h + h.mean(axis=0)
    delta -= delta.mean(axis=0)
    if keep_relief:
        V = np.asarray(P, float)[:, None, None, :] - X[None]
        t = V[..., :2] / V[..., 2:3]                                 # (K, n, n, 2)
        t = t - t.mean(axis=0)
        A = np.einsum("knmi,knmj->nmij", t, t)
        b = np.einsum("knmi,knm->nmi", t, delta)
        coef = np.linalg.solve(A + 1e-12 * np.eye(2), b[..., None])[..., 0]
        delta = delta - np.einsum("knmi,nmi->knm", t, coef)
        delta -= delta.mean(axis=(1, 2), keepdims=True)
    return rows, cols, delta


def _equidistant_positions(R, X, m, start, n_outer=3):
    """Positions at distance m whose drop-offs, relative to their mean, match the ratio maps R.

    The ratio maps see each light's drop-off minus the mean over lights; the mean is taken from the
    current positions, and all lights' (azimuth, elevation) are refitted in one least-squares problem.
    Each light's residuals depend on its own two angles only, so the normal equations are block-
    diagonal (2 x 2 per lamp, from the analytic Jacobian) and :func:`levenberg_marquardt` solves all
    lamps at once for the cost of one (scipy's sparse trust region took 25-30 iterations of an
    iterative solver per fit: 0.4 s at 64 lamps, this 0.03 s). A few alternations converge, the mean
    being small for lights spread around the region.
    """
    K = len(start)
    P = np.asarray(start, dtype=float)
    az = np.arctan2(P[:, 1], P[:, 0])
    el = np.clip(np.arcsin(np.clip(P[:, 2] / np.linalg.norm(P, axis=1), -1, 1)), np.radians(3), np.radians(89))
    Xf = X.reshape(-1, 3)

    def params(t):
        return np.column_stack([t[0::2], t[1::2], np.full(K, np.log(m))])

    t = np.ravel(np.column_stack([az, el]))
    lb = np.ravel(np.column_stack([az - np.pi, np.full(K, np.radians(2))]))
    ub = np.ravel(np.column_stack([az + np.pi, np.full(K, np.radians(89.5))]))
    for _ in range(n_outer):
        target = (R + model_logs(_lamp_positions(params(t)), X).mean(axis=0)).reshape(K, -1)

        def resid(tt):
            return (model_logs(_lamp_positions(params(tt)), X).reshape(K, -1) - target).ravel()

        def normal_equations(tt, f):
            J = _dropoff_derivatives(params(tt), Xf, 2)[1]       # azimuth and elevation: (K, points, 2)
            JtJ = np.zeros((2 * K, 2 * K))
            for k, blk in enumerate(np.einsum("kpi,kpj->kij", J, J)):
                JtJ[2 * k:2 * k + 2, 2 * k:2 * k + 2] = blk
            return JtJ, np.einsum("kpi,kp->ki", J, f.reshape(K, -1)).ravel()

        t, *_ = levenberg_marquardt(resid, normal_equations, np.clip(t, lb + 1e-9, ub - 1e-9), lb=lb, ub=ub,
                                    max_nfev=200, ftol=1e-12, xtol=1e-10)
    return _lamp_positions(params(t))


def intensities_from_levels(levels, positions_mm, shape, pixel_size_um, *, directions=None):
    """Relative lamp intensities ``E_k`` (median 1) from each image's overall level.

    ``levels[k]`` is the mean log intensity of image k above its mean-1 drop-off map; the albedo is the
    same in every image, so ``E_k`` is ``exp(level_k)`` over the mean model irradiance of a flat canvas.
    """
    M, N = shape
    rows = np.linspace(0, M - 1, 32)
    cols = np.linspace(0, N - 1, 32)
    X = pixel_coordinates_mm(rows[:, None], cols[None, :], shape, pixel_size_um)
    E = np.empty(len(levels))
    for k, lev in enumerate(levels):
        if positions_mm is not None:
            S = lamp_vectors(X, intensities=[1.0], positions_mm=positions_mm[k:k + 1])[0, ..., 2]
            E[k] = np.exp(lev) / np.exp(np.log(S).mean())
        else:
            E[k] = np.exp(lev) / max(directions[k][2], 1e-3)
    return E / np.median(E)


def sample_pixels(images, fits, *, mask=None, saturation=None, pixel_size_um, n=30000, seed=0) -> PixelSample:
    """A random sample of pixels, for the photometric residual.

    Pixels where some image is saturated, or dim relative to what the flat-fielded stack predicts
    (attached or cast shadow), are left out: they bias the residual. When at least 100 sampled pixels
    are lit by every lamp, the sample holds only those (``W`` None). Otherwise (a dome's low lamps
    leave parts of the field dark) it holds the pixels lit by at least :data:`MIN_LAMPS_PER_PIXEL`
    lamps with a per-sample weight ``W`` (1 lit, 0 not) that drops the others from each pixel's
    normal and residual; refused when too few pixels are lit by enough lamps, or some lamp lights too
    few of them (:data:`MIN_PIXELS_PER_LAMP`), naming those lamps.
    """
    K, M, N = images.shape[:3]
    rng = np.random.default_rng(seed)
    cand = rng.choice(M * N, size=min(M * N, 4 * n), replace=False)
    r, c = np.unravel_index(cand, (M, N))
    I = images[:, r, c]
    if I.ndim == 3:
        sat = (I >= saturation).any(axis=-1) if saturation is not None else np.zeros(I.shape[:2], bool)
        I = I.mean(axis=-1)
    else:
        sat = I >= saturation if saturation is not None else np.zeros(I.shape, bool)
    I = I.astype(float)
    F = np.stack([np.exp(_eval_points(f, r, c)) for f in fits])
    q = I / F
    q /= np.median(q, axis=1, keepdims=True)
    med = np.median(q, axis=0)
    lit = (~sat) & (I > 0) & (q > 0.55 * med) & (q < 1.8 * med)          # (K, candidates)
    ok = lit.all(axis=0)
    if mask is not None:
        ok &= mask[r, c]
    idx = np.flatnonzero(ok)[:n]
    if idx.size >= 100:
        X = pixel_coordinates_mm(r[idx], c[idx], (M, N), pixel_size_um)
        return PixelSample(I[:, idx], X, r[idx], c[idx])
    return _partly_lit_sample(I, sat, q, r, c, (M, N), mask=mask, pixel_size_um=pixel_size_um, n=n)


#: Lamps a pixel must be lit by to enter a partly-lit sample (:func:`sample_pixels`): three fit its
#: normal exactly, so the residual needs a fourth; one more keeps a single misjudged lamp from
#: deciding a pixel's normal.
MIN_LAMPS_PER_PIXEL = 5

#: Sampled pixels each lamp must light in a partly-lit sample: fewer leave its position unconstrained.
MIN_PIXELS_PER_LAMP = 50


def _partly_lit_sample(I, sat, q, r, c, shape, *, mask, pixel_size_um, n) -> PixelSample:
    """:func:`sample_pixels` when too few pixels are lit by every lamp: the pixels lit by enough lamps,
    with each lamp's lit samples in ``W``.

    The screen of :func:`sample_pixels` normalises each image by its median and each pixel by its
    median over lamps, which a lamp lighting half the field or a pixel lit by half the lamps pulls
    into the dark: here both medians are taken over the samples that pass the screen, starting from
    the unsaturated non-zero ones, and the screen is repeated (twice).
    """
    M, N = shape
    inside = np.ones(r.size, bool) if mask is None else mask[r, c]
    base = (~sat) & (I > 0) & inside[None]
    lit = base
    for _ in range(2):
        qn = q.copy()
        for k in range(len(q)):
            if lit[k].sum() >= 10:
                qn[k] /= np.median(qn[k, lit[k]])
        with np.errstate(all="ignore"), warnings.catch_warnings():
            # a pixel lit by no lamp has no median (NaN, and numpy's "All-NaN slice" warning): it fails
            # the screen below, as it should
            warnings.simplefilter("ignore", RuntimeWarning)
            med = np.nanmedian(np.where(lit, qn, np.nan), axis=0)
        lit = base & (qn > 0.55 * med) & (qn < 1.8 * med)
    count = lit.sum(axis=0)
    need = min(MIN_LAMPS_PER_PIXEL, len(I))      # fewer lamps than that: a pixel must be lit by them all
    ok = (count >= need) & inside
    idx = np.flatnonzero(ok)[:n]
    per_lamp = lit[:, idx].sum(axis=1)
    weak = np.flatnonzero(per_lamp < MIN_PIXELS_PER_LAMP)
    if idx.size < 100 or weak.size:
        if idx.size < 100:
            what = (f"too few pixels lit by enough lights to refine the light positions ({idx.size} of {r.size} "
                    f"sampled are unsaturated and lit by at least {need} images, 100 needed"
                    f"{_unlit_lamps(lit[:, inside])})")
        else:
            shown = ", ".join(f"{k + 1} ({per_lamp[k]})" for k in weak[:8])
            more = f" and {weak.size - 8} more" if weak.size > 8 else ""
            what = (f"too few pixels lit by some lights to refine their positions (image (lit pixels of "
                    f"{idx.size} sampled): {shown}{more}; {MIN_PIXELS_PER_LAMP} needed)")
        raise UVPSInputError(f"{what}: check the images' exposure (dark or saturated images) and the mask, or "
                             "give measured lamp positions (--lights)")
    W = lit[:, idx].astype(float)
    X = pixel_coordinates_mm(r[idx], c[idx], (M, N), pixel_size_um)
    return PixelSample(I[:, idx] * W, X, r[idx], c[idx], W)


def _unlit_lamps(lit: np.ndarray, most: int = 8) -> str:
    """Which lamps leave the sampled pixels dark or saturated, for a refusal: ``lit`` (K, P) bool.
    The lamps (1-based, in the capture's order) leaving more than a quarter of them unlit, else the worst."""
    if lit.size == 0:
        return ""
    unlit = 1.0 - lit.mean(axis=1)
    if not unlit.any():
        return ""                                 # every lamp lights every pixel: none to name
    order = np.argsort(-unlit, kind="stable")
    bad = [k for k in order if unlit[k] > 0.25] or [int(order[0])]
    shown = ", ".join(f"{k + 1} ({100 * unlit[k]:.0f} %)" for k in bad[:most])
    more = f" and {len(bad) - most} more" if len(bad) > most else ""
    return f"; lamps leaving the most of them dark or saturated: image {shown}{more}"


def _eval_points(fit: DropoffFit, r, c):
    """log F at scattered points (r[i], c[i])."""
    M, N = fit.shape
    Vv = Lg.legvander(to_unit(r, M), fit.degree)
    Vu = Lg.legvander(to_unit(c, N), fit.degree)
    return fit.clamp(np.einsum("pi,ij,pj->p", Vv, fit.coeffs, Vu))


#: At most this many threads for the lamp refinement's per-pixel work (:func:`photometric_residual`,
#: :func:`_vp_normal_equations`, :func:`_assemble`) when none is given (:func:`lamp_threads`). Each
#: part's pixels are computed as in one thread, so the result is the same to the bit.
MAX_LAMP_THREADS = 2

#: Sampled pixels below which :func:`photometric_residual` stays in one thread (a thread's start costs
#: more than the work; the refinement's first stage has ~4000).
MIN_PIXELS_PER_THREAD = 2000


def lamp_threads(workers=None) -> int:
    """Threads for the lamp estimate's per-pixel work: ``workers`` when given, else
    :func:`uvps.core.threads.default_threads` (the usable CPUs, ``UVPS_THREADS``) at most
    :data:`MAX_LAMP_THREADS`."""
    return max(1, int(workers)) if workers is not None else default_threads(MAX_LAMP_THREADS)


def photometric_residual(sample: PixelSample, model: LightModel, *, workers=None) -> np.ndarray:
    """Relative photometric-stereo residual ``(I - L . b) / mean(I)`` with per-pixel least-squares b.

    This is paper Eq. 2's ``|L(m) . N - I|`` with the normals (times albedo) ``b`` solved in closed form
    for the given lights (variable projection). Returns the (K * P,) residual vector.

    ``workers`` (default :func:`lamp_threads`): threads over bands of pixels (numpy releases the GIL);
    every pixel's arithmetic is the one-thread arithmetic, so the residual is the same to the bit
    (``tests/test_lights.py::test_lamp_refinement_same_in_one_and_two_threads``).
    """
    K, n = sample.I.shape
    parts = max(1, min(lamp_threads(workers), n // MIN_PIXELS_PER_THREAD))
    if parts == 1:
        return _residual_rows(sample, model, fallback=True).ravel()
    out = np.empty((K, n))

    def part(pixels):
        out[:, pixels] = _residual_rows(sample.take(pixels), model, fallback=False)

    try:
        map_bands(part, n, parts=parts, threads=parts)
    except np.linalg.LinAlgError:
        # a singular pixel: the whole sample by the pseudo-inverse, as in one thread
        return _residual_rows(sample, model, fallback=True).ravel()
    return out.ravel()


def _residual_rows(sample: PixelSample, model: LightModel, *, fallback: bool) -> np.ndarray:
    """:func:`photometric_residual` of a sample (its pixels), (K, P); ``fallback``: a singular pixel
    turns the whole sample to the pseudo-inverse (else the error is raised)."""
    V = _vectors(sample, model)                # (K, P, 3)
    A = np.einsum("kpi,kpj->pij", V, V)
    rhs = np.einsum("kpi,kp->pi", V, sample.I)
    try:
        b = np.linalg.solve(A, rhs[..., None])[..., 0]
    except np.linalg.LinAlgError:
        if not fallback:
            raise
        b = np.einsum("pij,pj->pi", np.linalg.pinv(A), rhs)
    pred = np.einsum("kpi,pi->kp", V, b)
    if sample.W is not None:
        pred *= sample.W
    return (sample.I - pred) / _mean_lit(sample)


def estimate_lights(grid: BlockGrid, fits, sample: Optional[PixelSample], *, pixel_size_um,
                    refine=True, m_bounds=(80.0, 3000.0), offset_stderr=None, normals_of=None,
                    progress: Progress = None) -> LightEstimate:
    """Estimate near-light positions from the drop-off fits and the photometric residual.

    Parameters
    ----------
    grid : BlockGrid
        Block means of the capture (for each image's overall level).
    fits : list of DropoffFit
        One per image, from :func:`uvps.core.flatfield.fit_dropoffs` (their albedo-free ratio part is used).
        Not changed: :attr:`LightEstimate.fits` are these completed with the estimated lamps' common
        part (:func:`uvps.core.flatfield.with_common`).
    sample : PixelSample or None
        Pixels for the photometric residual (:func:`sample_pixels`; 30000 recommended: the scan of
        ``m`` uses the first 5000, the per-light refinement all of them); None keeps ``m`` at the
        drop-off-only optimum and skips the per-light refinement.
    pixel_size_um : float
    refine : bool
        Refine each light's position and intensity after the equidistant solution.
    m_bounds : (float, float)
        Range of the shared distance ``m`` in mm.
    offset_stderr : float, optional
        Standard error (grey counts) of the additive term removed from the images, for the
        lights' uncertainty (:func:`light_uncertainty`).
    normals_of : callable, optional
        ``normals_of(model) -> (m, n, 3)`` unit normals of a contiguous patch about the image centre
        solved under ``model`` (the pipeline solves a central crop): the refined lamps are then
        corrected so that those normals are integrable (:func:`integrability_correction`).

    Returns
    -------
    LightEstimate

    Notes
    -----
    Paper Eq. 2: ``argmin_{N, m} |L(m) . N - I|``. For each trial ``m`` the lights' azimuths and
    elevations are fitted to the drop-off ratio maps, the normals solved in closed form, and the
    residual evaluated on the pixel sample; ``m`` is scanned on a log grid and then refined with
    ``scipy.optimize.least_squares``. The per-light refinement minimises the same residual over all
    ``L_k`` and ``E_k`` with the drop-off misfit as a prior, first on a subset (:func:`first_stage_pixels`,
    the prior at full weight), then on the whole sample (at :data:`FINAL_DROP_WEIGHT`), each to convergence.
    With ``normals_of`` the lamps' azimuths are then those that make the normals integrable
    (:func:`integrability_correction`).
    """
    shape = grid.shape
    K = len(fits)
    weak = [k for k, f in enumerate(fits) if f.gradient_rms * max(shape) < 0.005]
    if len(weak) == K:
        raise UVPSInputError(
            "no measurable light drop-off in any image (less than 0.5 % across the field): the lights "
            "cannot be estimated from the images; pass calibrated lights with --lights")
    rows, cols, R = ratio_samples(fits, shape, max_degree=PRIOR_DEGREE)
    X = pixel_coordinates_mm(rows[:, None], cols[None, :], shape, pixel_size_um)
    history = []
    # start: azimuth from the polar resampling of each ratio map, elevation 40 degrees
    az_ratio = np.radians([azimuth_from_dropoff(f) for f in fits])
    start = np.stack([np.cos(np.radians(40)) * np.cos(az_ratio), np.cos(np.radians(40)) * np.sin(az_ratio),
                      np.full(K, np.sin(np.radians(40)))], axis=1)
    cache = {}
    # the paper's one-parameter scan needs no more than a few thousand pixels
    scan_sample = None if sample is None else _subset(sample, 5000)

    def equidistant(m):
        key = round(float(m), 6)
        if key not in cache:
            near = min(cache, key=lambda q: abs(np.log(q / m))) if cache else None
            P = _equidistant_positions(R, X, m, cache[near].positions_mm if near else start)
            levels = [f.level for f in with_common(fits, grid, dropoff_common(P, shape, pixel_size_um))]
            E = intensities_from_levels(levels, P, shape, pixel_size_um)
            cache[key] = LightModel.from_positions(P, E)
        return cache[key]

    def cost(m):
        model = equidistant(m)
        if sample is None:
            r = (model_logs(model.positions_mm, X) - (R + model_logs(model.positions_mm, X).mean(axis=0))).ravel()
        else:
            r = photometric_residual(scan_sample, model)
        c = float(np.mean(r ** 2))
        # A shared m further than the steepest drop-off allows puts that lamp at grazing incidence
        # (the elevation bound); such a start leads the refinement into a degenerate valley of flat
        # lamps (seen on an 8-light capture: 31 deg off), so those m count as infeasible.
        n_grazing = int(np.sum(model.directions[:, 2] < np.sin(np.radians(_GRAZING_DEG))))
        history.append({"stage": "equidistant", "m_mm": float(m), "cost": c, "grazing_lights": n_grazing})
        return c * (1 + n_grazing)

    m = _shared_distance(cost, m_bounds, progress)
    eq = equidistant(m)
    model, unc = eq, None
    if sample is not None:
        model, unc = _beyond_equidistant(sample, eq, R, X, history, refine=refine, normals_of=normals_of,
                                         offset_stderr=offset_stderr, progress=progress)
    fits = with_common(fits, grid, dropoff_common(model.positions_mm, shape, pixel_size_um))
    az_polar = np.array([azimuth_from_dropoff(f) for f in fits])
    report(progress, 1.0, "lights: done")
    return LightEstimate(model=model, m_mm=m, azimuth_polar_deg=az_polar, residual_history=history,
                         equidistant=eq, uncertainty=unc, fits=fits)


def _shared_distance(cost, m_bounds, progress):
    """The paper's one parameter: the shared lamp distance ``m`` (mm) that minimises ``cost(m)`` (Eq. 2),
    scanned on 9 log-spaced values of ``m_bounds`` and then refined between the best one's neighbours."""
    report(progress, 0.02, "lights: scanning the shared distance m")
    grid_m = np.geomspace(m_bounds[0], m_bounds[1], 9)
    costs = []
    for j, m_j in enumerate(grid_m):
        costs.append(cost(m_j))
        report(progress, 0.02 + 0.33 * (j + 1) / len(grid_m), f"lights: scanning m {j + 1}/{len(grid_m)}")
    i = int(np.argmin(costs))
    lo, hi = grid_m[max(i - 1, 0)], grid_m[min(i + 1, len(grid_m) - 1)]
    report(progress, 0.35, "lights: refining m (paper Eq. 2)")
    n_eval = [0]

    def cost_refining(t):
        n_eval[0] += 1
        report(progress, 0.35 + 0.15 * min(n_eval[0] / 12, 1.0), f"lights: refining m ({n_eval[0]})")
        return [np.sqrt(cost(float(np.exp(t[0]))))]

    sol = least_squares(cost_refining, [np.log(grid_m[i])],
                        bounds=([np.log(lo)], [np.log(hi) + 1e-9]), diff_step=1e-3, max_nfev=10)
    return float(np.exp(sol.x[0]))


def _beyond_equidistant(sample, eq, R, X, history, *, refine, normals_of, offset_stderr, progress):
    """From the equidistant lamps on: each lamp's own position and intensity, their level, the
    normals' integrability and the lamps' uncertainty (``refine``), else the level alone: (model,
    uncertainty or None)."""
    model, unc = eq, None
    if refine:
        report(progress, 0.5, "lights: refining each light's position and intensity")
        model = _refine_each(sample, eq, R, X, history, progress=sub_progress(progress, 0.5, 0.92))
    model = _level(sample, model, history)
    if refine and normals_of is not None:
        report(progress, 0.92, "lights: integrability of the normals")
        model = _integrable(sample, model, history, normals_of)
    if refine:
        report(progress, 0.93, "lights: their uncertainty")
        unc = light_uncertainty(sample, model, R, X, w_drop=_last_drop_weight(history), offset_stderr=offset_stderr)
    return model, unc


def dropoff_common(positions_mm, shape, pixel_size_um):
    """``log_common(rows, cols)`` for :func:`uvps.core.flatfield.with_common`: the mean log drop-off
    of near lamps at ``positions_mm`` over the pixels of a separable grid."""
    def log_common(rows, cols):
        X = pixel_coordinates_mm(np.asarray(rows)[:, None], np.asarray(cols)[None, :], shape, pixel_size_um)
        return model_logs(positions_mm, X).mean(axis=0)
    return log_common


#: Pixels whose solved slope exceeds this (|dh/dx| or |dh/dy|) are left out of the integrability fit
#: (shadowed or saturated samples give such normals, and their curl is noise).
_MAX_SLOPE = 1.0


def integrability_correction(model: LightModel, normals, history=None) -> LightModel:
    """Correct near lights so that the normals they give are integrable (a height field's gradient).

    Unknown lights are determined by the pixels only up to a linear map ``A`` of the light vectors
    (normals ``A^-T n``); normals of a surface must have a curl-free gradient field, which leaves
    of ``A`` only the generalized bas-relief (GBR) family (Belhumeur, Kriegman and Yuille 1999;
    Yuille and Snow 1997), which does not move the lamps' azimuths. The drop-off prior and the
    near-light geometry pin the rest, but the prior assumes the canvas is flat at large scale:
    a bowed canvas (15 um across the benchmark's 24 mm field) shears the lamps' azimuths by up to
    1.7 deg and a 60 um bow by 6.6 deg, and nothing in the photometric residual notices. The
    non-GBR part of ``A`` is ``[[Q, t], [0, 1]]`` with ``Q`` near the identity up to scale (a
    rotation and two shears of the lamps' x, y) and ``t`` a shift of x, y by ``t * z``; to first
    order each moves the normals' gradients ``g = (p, q)`` along a known field (``B g`` for the
    three matrices of Q, ``-(p^2, pq)`` and ``-(pq, q^2)`` for t), so the five parameters that make
    ``curl(g)`` smallest over the patch are one linear least-squares solve. The lamps are then
    ``A P``. Written here because no library does it.

    Parameters
    ----------
    model : LightModel
        Near lights (positions).
    normals : ndarray (m, n, 3)
        Unit normals solved under ``model`` on a patch centred on the image centre (NaN where not
        solved), rows downward (y up).
    history : list, optional
        Gets one entry with the correction and the curl before and after.

    Returns
    -------
    LightModel
        The corrected positions, the same intensities; ``model`` itself if the patch is too small
        or too flat to tell.
    """
    N = np.asarray(normals, dtype=np.float64)
    with np.errstate(divide="ignore", invalid="ignore"):
        p, q = -N[..., 0] / N[..., 2], -N[..., 1] / N[..., 2]
    bad = ~(np.isfinite(p) & np.isfinite(q) & (np.abs(p) < _MAX_SLOPE) & (np.abs(q) < _MAX_SLOPE) & (N[..., 2] > 0))
    p, q = np.where(bad, np.nan, p), np.where(bad, np.nan, q)

    def curl(a, b):                               # da/dy - db/dx with y up (rows down)
        return (-np.gradient(a, axis=0) - np.gradient(b, axis=1)).ravel()

    fields = [(-q, p), (p, -q), (q, p), (-p * p, -p * q), (-p * q, -q * q)]   # J g, S1 g, S2 g, then t
    c0 = curl(p, q)
    G = np.stack([curl(a, b) for a, b in fields], axis=1)
    ok = np.isfinite(c0) & np.isfinite(G).all(axis=1)
    if ok.sum() < 1000 or not np.any(G[ok]):
        return model
    theta = np.linalg.lstsq(G[ok], -c0[ok], rcond=None)[0]
    r, s1, s2, tx, ty = theta
    M = np.array([[1 + s1, s2 - r], [s2 + r, 1 - s1]])     # the normals' gradients map g -> M g
    A = np.eye(3)
    A[:2, :2] = np.linalg.inv(M).T                        # lights: l -> A l keeps n . l
    A[:2, 2] = (tx, ty)
    P = model.positions_mm @ A.T
    out = LightModel.from_positions(P, model.intensities)
    if history is not None:
        before = float(np.sqrt(np.mean(c0[ok] ** 2)))
        after = float(np.sqrt(np.mean((c0[ok] + G[ok] @ theta) ** 2)))
        history.append({"stage": "integrability", "rotation_deg": float(np.degrees(r)), "shear": [float(s1), float(s2)],
                        "tilt": [float(tx), float(ty)], "curl_rms_before": before, "curl_rms_after": after,
                        "pixels": int(ok.sum())})
    return out


def _integrable(sample: PixelSample, model: LightModel, history, normals_of) -> LightModel:
    """Each lamp turned to the azimuth :func:`integrability_correction` gives it, its elevation,
    distance and intensity kept, then all levelled again (:func:`_level`).

    Only the azimuths are taken: the corrected positions as they come (``A P``, right for far
    lights) move the lamps' distances off the near-light geometry the pixels hold (on the
    benchmark's clean capture the photometric residual rose 2.7x and every normal tilted 0.5 deg),
    and refining elevation and distance again with the azimuths held hands the drop-off prior's bias
    to the elevations (a 60 um bow: 2.8 -> 5.1 deg). Clean capture (15 um bow), seed 0: 0.86 ->
    0.45 deg, normals 0.187 -> 0.182 deg; a 60 um bow: 2.84 -> 1.35 deg.
    """
    corrected = integrability_correction(model, normals_of(model), history)
    if corrected is model:
        return model
    az = np.arctan2(corrected.positions_mm[:, 1], corrected.positions_mm[:, 0])
    P = model.positions_mm
    rxy = np.hypot(P[:, 0], P[:, 1])
    turned = LightModel.from_positions(np.column_stack([rxy * np.cos(az), rxy * np.sin(az), P[:, 2]]),
                                       model.intensities)
    return _level(sample, turned, history)


def _last_drop_weight(history) -> float:
    """The drop-off prior's weight in the objective last minimised (the covariance is that objective's)."""
    return next((h["drop_weight"] for h in reversed(history) if h["stage"] == "per-light"), 1.0)


#: Equidistant fits (elevations within [2, 89.5] deg) that put a lamp below this elevation count as
#: grazing. At 3 deg a clean 8-lamp capture's scan chose m = 821 mm with every lamp at 3.0-3.1 deg,
#: just above the line, and the refinement stayed in the flat valley, 30 deg off (heights reported
#: "not determined"); at 5 deg it chose m = 80 mm and ended 0.37 deg off. No other benchmark capture
#: changed (12-lamp rows, 8 and 16 lamps, grey 8-16 lamps: ``scripts/analysis_lamp_elevation.py sweep
#: --grazing 3|5 --lamps 8 12 16 --grey``).
_GRAZING_DEG = 5.0


def _ratio_resid(P, R, X):
    h = model_logs(P, X)
    return (h - h.mean(axis=0) - R).ravel()


def _vp_residual_and_jacobian(sample: PixelSample, P, E, scale, *, out=None, factor=1.0, intensities_only=False):
    """Photometric residual and its Jacobian in (P / scale, log E), by variable projection.

    The Jacobian is exact (Golub and Pereyra): the derivative of the residual with the per-pixel
    ``b`` held fixed, projected on the orthogonal complement of each pixel's light matrix (Kaufman's
    approximation), plus the change of ``b`` driven by the residual itself. Written out here because no library does variable projection with per-pixel 3-vectors; it turns each
    iteration of ``least_squares`` from 4K + 1 residual evaluations into one. ``out`` (K * P, 4K),
    if given, receives the Jacobian times ``factor``. ``intensities_only``: the (K * P, K) columns of
    log E alone (known positions).
    """
    K = len(P)
    model = LightModel.from_positions(P, E)
    V = _vectors(sample, model)                          # (K, Pn, 3)
    A = np.einsum("kpi,kpj->pij", V, V)
    Ainv = np.linalg.inv(A)
    b = np.einsum("pij,kpj,kp->pi", Ainv, V, sample.I)
    mu = _mean_lit(sample)
    rk = (sample.I - np.einsum("kpi,pi->kp", V, b)) / mu   # (K, Pn)
    r = rk.ravel()
    per = 1 if intensities_only else 4
    J = (np.empty((r.size, per * K)) if out is None else out).reshape(K, r.size // K, per * K)
    h = 1e-6 * scale
    for k in range(K):
        cols = []
        for j in range(0 if intensities_only else 3):
            Lp = P[k].copy()
            Lp[j] += h
            Vk = LightModel.from_positions(Lp[None], E[k:k + 1]).vectors(sample.X)[0]
            if sample.W is not None:
                Vk = Vk * sample.W[k][:, None]
            cols.append((Vk - V[k]) / h * scale)           # d V_k / d (L_kj / scale)
        cols.append(V[k])                                 # d V_k / d log E_k
        for j, dV in enumerate(cols):
            d = -np.einsum("pi,pi->p", dV, b) / mu           # residual change of light k, b fixed
            # the normals' response: the part of d they absorb (Kaufman) plus the change of b through
            # the residual itself (Golub-Pereyra's second term; Kaufman's alone is off by tens of per
            # cent where the lights leave a large residual, tests/test_lights.py)
            c = np.einsum("pij,pj->pi", Ainv, V[k] * d[:, None] + dV * rk[k][:, None])
            col = -np.einsum("kpi,pi->kp", V, c)
            col[k] += d
            J[:, :, per * k + (per - 1 if intensities_only else j)] = col * factor if factor != 1.0 else col
    return r, J.reshape(r.size, per * K)


def _level(sample: PixelSample, model: LightModel, history) -> LightModel:
    """Rotate all lights about the image centre so that the mean recovered normal is +z.

    The camera is orthogonal to the canvas, so the mean surface plane is z = 0 (docs/architecture.md).
    A common tilt of every lamp tilts every normal by the same rotation and leaves the residual
    unchanged; the drop-off pins it only weakly on a small field. This removes it.
    """
    V = _vectors(sample, model)
    b = np.linalg.solve(np.einsum("kpi,kpj->pij", V, V), np.einsum("kpi,kp->pi", V, sample.I)[..., None])[..., 0]
    n = b / np.linalg.norm(b, axis=1, keepdims=True)
    nbar = n.mean(axis=0)
    nbar /= np.linalg.norm(nbar)
    axis = np.cross(nbar, [0.0, 0.0, 1.0])
    s, c = np.linalg.norm(axis), nbar[2]
    if s < 1e-12:
        return model
    k = axis / s
    Kx = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    R = np.eye(3) + s * Kx + (1 - c) * Kx @ Kx   # Rodrigues: takes nbar to +z
    out = LightModel.from_positions(model.positions_mm @ R.T, model.intensities)
    history.append({"stage": "level", "tilt_deg": float(np.degrees(np.arctan2(s, c))),
                    "cost": float(np.mean(photometric_residual(sample, out) ** 2))})
    return out


def _subset(sample: PixelSample, n: int) -> PixelSample:
    """The first n pixels of a sample (the sample is in random order, so this is a random subset)."""
    return sample.take(slice(n))


def _refine_each(sample: PixelSample, start: LightModel, R, X, history, *, stages=None,
                 progress: Progress = None):
    """All positions and log-intensities by least squares on the photometric + drop-off residuals.

    The drop-off term is a weak prior: a bowed canvas biases it (its shading is smooth and different
    under every lamp), while the photometric residual over the texture is unbiased.

    The problem has one very shallow direction: every lamp a little closer and higher (or further and
    lower) is the near-light remnant of the bas-relief ambiguity, and only the residual over tens of
    thousands of textured pixels tells it from the truth. The optimiser must run to convergence on
    such a sample: with 5000 pixels and 25 evaluations the lamps stopped ~20 % too close and the
    directions 6.6 deg off on the benchmark; with 30000 pixels to convergence, 0.5-0.6 deg
    (``scripts/benchmark_core.py --parts 1``, the stages edited).
    ``stages`` ((pixels, max_nfev, drop-off prior weight), ...) first solves on a
    subset (cheap, reaches the valley; :func:`first_stage_pixels` by default), then on the whole
    sample (None). Each stage stops at MINPACK's tolerances (a looser ``ftol`` = 1e-5 stopped an
    8-light capture 7 deg off) or after ``max_nfev`` evaluations: on
    a field too small for the near-light geometry to resolve the valley (under ~1 cm at 15 um/px)
    the solver only crawls along it.
    """
    model = start
    if stages is None:
        # the first stage may crawl along the valley (100 evaluations on a 12-lamp capture whose whole-
        # sample stage then converged in 15; capped at 60 it stopped 3.8 deg off): evaluations there are
        # cheap. It keeps the drop-off prior at full weight, which holds the lamps in the valley's right
        # basin; the whole-sample stage then weakens it (FINAL_DROP_WEIGHT) to shed its bias.
        stages = ((first_stage_pixels(len(start.intensities)), 150, 1.0), (None, 40, FINAL_DROP_WEIGHT))
    # each stage's share of the bar: its evaluations times its pixels (an evaluation costs ~ pixels)
    work = [max_nfev * min(n or sample.I.shape[1], sample.I.shape[1]) for n, max_nfev, _ in stages]
    done = 0.0
    for (n, max_nfev, w_drop), w in zip(stages, work):
        sub = sample if n is None or n >= sample.I.shape[1] else _subset(sample, n)
        part = sub_progress(progress, done / sum(work), (done + w) / sum(work))
        done += w
        model = _refine_lsq(sub, model, R, X, history, w_drop=w_drop, max_nfev=max_nfev,
                            callback=_evaluations(part, max_nfev, sub.I.shape[1]))
        if sub is sample:
            break
    return LightModel.from_positions(model.positions_mm, model.intensities / np.median(model.intensities))


#: Weight of the drop-off prior in the refinement's whole-sample stage (1 in the first). The ratio maps
#: carry the shading of the relief's large-scale shape (cupped islands, strokes, protrusions), which
#: biases them; the photometric residual does not, but without the prior the lamps drift along the
#: valley. Worst mean direction error over 3 seeds at weights 1 / 0.6 / 0.3 (``scripts/benchmark_robustness.py
#: --modes estimated --no-detect`` and ``scripts/benchmark_lights.py --seeds 3 4 5``, the weight edited):
#: robustness rows (RGB, 12 lamps) cupping 3.22 / 1.76 / 0.97 deg, protrusion shapes 1.37 / 0.93 /
#: 0.66, strokes 1.62 / 1.42 / 1.27, vignetting 0.96 / 1.10 / 1.24, cast shadows 1.03 / 1.21 / 1.33;
#: clean grey captures of 8 lamps 0.59 / 1.31 / 2.49, 16: 0.50 / 0.73 / 0.98, 64: 0.57 / 0.70 / 0.80.
#: 0.6 has the smallest worst case (1.76). Weakened from the start instead (both stages), a clean
#: capture fell into another basin, 39 deg off, at 0.5 and 0.3.
FINAL_DROP_WEIGHT = 0.6

#: Residuals (lamps x pixels) of the refinement's first stage: it only has to reach the valley, and an
#: evaluation costs lamps x pixels, so more lamps take fewer pixels (5000 up to 12 lamps, as before).
FIRST_STAGE_RESIDUALS = 60000


def first_stage_pixels(n_lamps: int) -> int:
    """Pixels of the refinement's first stage for ``n_lamps`` lamps (:data:`FIRST_STAGE_RESIDUALS`)."""
    return int(min(5000, max(1000, FIRST_STAGE_RESIDUALS // max(n_lamps, 1))))


def _evaluations(progress: Progress, max_nfev: int, pixels: int):
    """A :func:`levenberg_marquardt` callback reporting evaluations as a fraction of ``max_nfev``."""
    if progress is None:
        return None
    return lambda nfev: progress(nfev / max_nfev, f"lights: refining on {pixels} px, evaluation {nfev}")


def _lamp_positions(th):
    """Positions (K, 3) from rows (azimuth, elevation, log distance, ...)."""
    az, el, D = th[:, 0], th[:, 1], np.exp(th[:, 2])
    return D[:, None] * np.stack([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)], axis=1)


def _lamp_axes(th):
    """Lamp positions L (K, 3) and ``dL`` along azimuth, elevation and log distance: (3, K, 3)."""
    az, el, D = th[:, 0], th[:, 1], np.exp(th[:, 2])
    ca, sa, ce, se = np.cos(az), np.sin(az), np.cos(el), np.sin(el)
    L = D[:, None] * np.stack([ce * ca, ce * sa, se], axis=1)
    return L, np.stack([D[:, None] * np.stack([-ce * sa, ce * ca, np.zeros_like(az)], axis=1),
                        D[:, None] * np.stack([-se * ca, -se * sa, ce], axis=1), L])


def _lamp_vectors(th, X):
    """Each lamp's vector ``v`` at every point X (P, 3), components first: (K, 3, P), and its
    derivatives in (azimuth, elevation, log distance, log intensity): (K, 4, 3, P).

    Analytic: ``v = E D^2 u / |u|^3`` with ``u = L - X``; along ``dL = a``,
    ``dv = E D^2 (a - 3 u (u.a) / |u|^2) / |u|^3``; log distance also doubles ``D^2``.
    """
    L, along = _lamp_axes(th)
    u = L[:, :, None] - X.T[None]
    d2 = u[:, 0] ** 2 + u[:, 1] ** 2 + u[:, 2] ** 2
    s = near_scale(u[:, 0], u[:, 1], u[:, 2], np.exp(th[:, 3] + 2 * th[:, 2])[:, None])
    V = u * s[:, None, :]
    W = np.empty((len(th), 4) + V.shape[1:])
    for j, a in enumerate(along):
        ua = (u[:, 0] * a[:, 0, None] + u[:, 1] * a[:, 1, None] + u[:, 2] * a[:, 2, None]) / d2
        W[:, j] = s[:, None, :] * (a[:, :, None] - 3.0 * u * ua[:, None, :])
    W[:, 2] += 2.0 * V
    W[:, 3] = V
    return V, W


@numba.njit(nogil=True, cache=True)
def _inverse_cholesky3(A00, A01, A02, A11, A12, A22):
    """``C = G^-1`` (lower triangular) of the Cholesky factor ``A = G G^T`` of a symmetric positive
    definite 3 x 3 matrix, so ``A^-1 = C^T C``: (c00, c10, c11, c20, c21, c22). In :func:`_vp_rows`'s
    per-pixel loop, where numpy's batched routines would need (P, 3, 3) temporaries."""
    g00 = np.sqrt(A00)
    g10 = A01 / g00
    g20 = A02 / g00
    g11 = np.sqrt(A11 - g10 * g10)
    g21 = (A12 - g20 * g10) / g11
    g22 = np.sqrt(A22 - g20 * g20 - g21 * g21)
    c00 = 1.0 / g00
    c11 = 1.0 / g11
    c22 = 1.0 / g22
    c10 = -g10 * c00 / g11
    c21 = -g21 * c11 / g22
    c20 = -(g20 * c00 + g21 * c10) / g22
    return c00, c10, c11, c20, c21, c22


@numba.njit(nogil=True, cache=True)
def _vp_rows(L, along, scale, X, I, wt, r, e, Zq, Zu, p0, p1):
    """Pixels ``p0:p1`` of :func:`_vp_normal_equations`: the residual ``r`` (K, P), ``e`` (K, 4, P) and
    the whitened rows ``Zq``, ``Zu`` (4K, 3P), column ``m * P + p`` (its numpy form is
    :func:`_vp_normal_equations_numpy`).

    Hand-written (numba): per pixel the K x 4 x 3 lamp derivatives, a 3 x 3 Cholesky factor and its
    inverse, and four short sums over lamps (``wt`` (K, P): 1 where the lamp lights the pixel, else 0); numpy made a dozen (K, 4, 3, P) float64 temporaries of
    them, 5 of the 11 s of a 64-lamp estimate.
    """
    K = L.shape[0]
    P = X.shape[0]
    v = np.empty((K, 3))
    w = np.empty((K, 4, 3))
    u = np.empty(3)
    for p in range(p0, p1):
        A00 = A01 = A02 = A11 = A12 = A22 = 0.0
        h0 = h1 = h2 = 0.0
        mu = 0.0
        lit = 0.0
        for k in range(K):
            d2 = 0.0
            for i in range(3):
                u[i] = L[k, i] - X[p, i]
                d2 += u[i] * u[i]
            s = scale[k] / (d2 * np.sqrt(d2)) * wt[k, p]
            for i in range(3):
                v[k, i] = u[i] * s
            for j in range(3):
                ua = (u[0] * along[j, k, 0] + u[1] * along[j, k, 1] + u[2] * along[j, k, 2]) / d2
                for i in range(3):
                    w[k, j, i] = s * (along[j, k, i] - 3.0 * u[i] * ua)
            for i in range(3):
                w[k, 2, i] += 2.0 * v[k, i]
                w[k, 3, i] = v[k, i]
            A00 += v[k, 0] * v[k, 0]
            A01 += v[k, 0] * v[k, 1]
            A02 += v[k, 0] * v[k, 2]
            A11 += v[k, 1] * v[k, 1]
            A12 += v[k, 1] * v[k, 2]
            A22 += v[k, 2] * v[k, 2]
            h0 += v[k, 0] * I[k, p]
            h1 += v[k, 1] * I[k, p]
            h2 += v[k, 2] * I[k, p]
            mu += I[k, p]
            lit += wt[k, p]
        mu /= lit
        c00, c10, c11, c20, c21, c22 = _inverse_cholesky3(A00, A01, A02, A11, A12, A22)
        # b = C^T C h
        t0 = c00 * h0
        t1 = c10 * h0 + c11 * h1
        t2 = c20 * h0 + c21 * h1 + c22 * h2
        b0 = c00 * t0 + c10 * t1 + c20 * t2
        b1 = c11 * t1 + c21 * t2
        b2 = c22 * t2
        for k in range(K):
            rk = (I[k, p] - (v[k, 0] * b0 + v[k, 1] * b1 + v[k, 2] * b2)) / mu
            r[k, p] = rk
            for j in range(4):
                ekj = -(w[k, j, 0] * b0 + w[k, j, 1] * b1 + w[k, j, 2] * b2) / mu
                e[k, j, p] = ekj
                row = 4 * k + j
                q0, q1, q2 = rk * w[k, j, 0], rk * w[k, j, 1], rk * w[k, j, 2]
                Zq[row, p] = c00 * q0
                Zq[row, P + p] = c10 * q0 + c11 * q1
                Zq[row, 2 * P + p] = c20 * q0 + c21 * q1 + c22 * q2
                y0, y1, y2 = ekj * v[k, 0], ekj * v[k, 1], ekj * v[k, 2]
                Zu[row, p] = c00 * y0
                Zu[row, P + p] = c10 * y0 + c11 * y1
                Zu[row, 2 * P + p] = c20 * y0 + c21 * y1 + c22 * y2


def _vp_normal_equations(sample: PixelSample, th, *, workers=None):
    """The photometric residual's Gauss-Newton normal equations, as :func:`_vp_normal_equations_numpy`
    states them, with the per-pixel work compiled (:func:`_vp_rows`, in ``workers`` threads over
    pixel bands, default :func:`lamp_threads`) and the two (4K x 3P) symmetric products by BLAS (one
    per thread, :func:`_assemble`).

    Returns ``(r (K, P), e (K, 4, P), JtJ (4K, 4K), Jtr (4K,))``, unscaled.
    """
    workers = lamp_threads(workers)
    K, n = sample.I.shape
    L, along = _lamp_axes(th)
    scale = np.exp(th[:, 3] + 2 * th[:, 2])
    X = np.ascontiguousarray(sample.X, dtype=np.float64)
    I = np.ascontiguousarray(sample.I, dtype=np.float64)
    wt = np.ones((K, n)) if sample.W is None else np.ascontiguousarray(sample.W, dtype=np.float64)
    r = np.empty((K, n))
    e = np.empty((K, 4, n))
    Zq = np.empty((4 * K, 3 * n))
    Zu = np.empty((4 * K, 3 * n))
    args = (np.ascontiguousarray(L), np.ascontiguousarray(along), scale, X, I, wt, r, e, Zq, Zu)
    # the first band alone on the kernel's first call in this process (numba compiles, or loads from its cache,
    # then); after it, both bands at once (first_alone always left the second band alone on 2 threads)
    map_bands(lambda pixels: _vp_rows(*args, pixels.start, pixels.stop), n, parts=workers, threads=workers,
              first_alone=not _vp_rows.signatures)
    return _assemble(r, e, Zq, Zu, workers=workers)


def _vp_normal_equations_numpy(sample: PixelSample, th):
    """The photometric residual's Gauss-Newton normal equations ``J^T J`` and ``J^T r`` in (azimuth,
    elevation, log distance, log intensity) per lamp, without forming ``J``.

    Per pixel, with ``V`` its K x 3 light matrix, ``A = V^T V``, ``b`` the solved normal times albedo
    and ``r = P_perp I / mu`` its residual, the exact variable-projection Jacobian (Golub and Pereyra)
    of lamp k's parameter j is ``e_kj P_perp 1_k - r_k V A^-1 w_kj`` (``w_kj = dv_k/dj``,
    ``e_kj = -w_kj . b / mu``). ``P_perp V = 0`` removes the cross terms, so
    ``J^T J = diag_k(e e^T) - U A^-1 U^T + Q A^-1 Q^T`` with ``U_kj = e_kj v_k`` and
    ``Q_kj = r_k w_kj`` (3-vectors per pixel), and ``J^T r = sum e_kj r_k`` (``P_perp r = r``,
    ``V^T r = 0``). With ``A^-1 = C^T C`` (C the inverse of A's Cholesky factor) the two sums over
    pixels are two (4K x 3P) symmetric products. Written out because no library exploits this
    structure; the dense Jacobian's ``J^T J`` costs lamps^3 x pixels (64 lamps: 1.5 s per step).

    Returns ``(r (K, P), e (K, 4, P), JtJ (4K, 4K), Jtr (4K,))``, unscaled.
    """
    K, n = sample.I.shape
    V, W = _lamp_vectors(th, sample.X)
    if sample.W is not None:
        V, W = V * sample.W[:, None], W * sample.W[:, None, None]
    A = np.empty((n, 3, 3))
    for i in range(3):
        for j in range(i, 3):
            A[:, i, j] = A[:, j, i] = np.einsum("kp,kp->p", V[:, i], V[:, j])
    C = np.linalg.inv(np.linalg.cholesky(A))          # lower triangular, A^-1 = C^T C
    Ainv = np.einsum("pki,pkj->pij", C, C)
    rhs = [np.einsum("kp,kp->p", V[:, i], sample.I) for i in range(3)]
    b = [sum(Ainv[:, i, j] * rhs[j] for j in range(3)) for i in range(3)]
    mu = _mean_lit(sample)
    r = (sample.I - sum(V[:, i] * b[i] for i in range(3))) / mu
    e = -sum(W[:, :, i] * b[i] for i in range(3)) / mu

    def whitened(Y):                                   # Y (K, 4, 3, P) -> Y_p C_p^T as (4K, 3P)
        Z = np.empty_like(Y)
        for j in range(3):
            Z[:, :, j] = sum(Y[:, :, i] * C[:, j, i] for i in range(j + 1))
        return Z.reshape(4 * K, 3 * n)

    Zq = whitened(r[:, None, None, :] * W)
    Zu = whitened(e[:, :, None, :] * V[:, None])
    return _assemble(r, e, Zq, Zu)


def _assemble(r, e, Zq, Zu, *, workers=1):
    """``(r, e, J^T J, J^T r)`` from the residual, ``e`` and the whitened rows of
    :func:`_vp_normal_equations_numpy`'s statement: ``J^T J = Zq Zq^T - Zu Zu^T + diag_k(e e^T)``.

    ``workers`` > 1: ``Zu Zu^T`` and the blocks in a second thread while this one forms ``Zq Zq^T``
    (:func:`uvps.core.threads.concurrently`, so not with ``UVPS_THREADS=1``; BLAS and einsum release the
    GIL; with one BLAS thread, ``uvps._entry``, the refinement's products otherwise keep one core busy);
    each product is the one-thread product, to the bit."""
    if workers > 1:
        JtJ, (ZuZu, blocks) = concurrently(lambda: Zq @ Zq.T, lambda: (Zu @ Zu.T, np.einsum("kjp,klp->kjl", e, e)))
        JtJ -= ZuZu
        _add_blocks(JtJ, blocks)
        return r, e, 0.5 * (JtJ + JtJ.T), np.einsum("kjp,kp->kj", e, r).ravel()
    JtJ = Zq @ Zq.T
    JtJ -= Zu @ Zu.T
    _add_blocks(JtJ, np.einsum("kjp,klp->kjl", e, e))
    return r, e, 0.5 * (JtJ + JtJ.T), np.einsum("kjp,kp->kj", e, r).ravel()


def _add_blocks(M, blocks):
    """Add (K, 4, 4) blocks to the diagonal of M (4K, 4K) in place."""
    for k, blk in enumerate(blocks):
        M[4 * k:4 * k + 4, 4 * k:4 * k + 4] += blk


def _dropoff_derivatives(th, Xf, n):
    """Lamp positions and the derivatives of each lamp's centred log drop-off ``-3 log |L - X|`` at the
    points Xf (P, 3) along its first ``n`` of (azimuth, elevation, log distance): (K, P, n).

    Analytic: along ``dL = a``, ``dg = -3 (u.a) / |u|^2`` with ``u = L - X``, centred over the points.
    """
    L, along = _lamp_axes(th)
    u = L[:, None, :] - Xf[None]
    d2 = np.einsum("kpi,kpi->kp", u, u)
    out = np.empty((len(th), len(Xf), n))
    for j in range(n):
        dg = -3.0 * np.einsum("kpi,ki->kp", u, along[j]) / d2
        out[..., j] = dg - dg.mean(axis=1, keepdims=True)
    return L, out


def _drop_normal_equations(th, R, X, scale):
    """``J^T J`` and ``J^T f`` of the drop-off prior ``f = scale * _ratio_resid`` in the same parameters.

    Lamp k's parameters move only its own centred log drop-off ``g_k`` (:func:`_dropoff_derivatives`)
    and, through the mean over lamps, every map by ``-dg_k / K``; so ``J^T J =
    scale^2 (diag_k(G_k^T G_k) - G^T G / K)`` with ``G`` the (points x 4K) matrix of the ``dg`` (none
    for the intensity, which does not enter the shape).
    """
    K = len(th)
    Xf = X.reshape(-1, 3)
    L, dg = _dropoff_derivatives(th, Xf, 3)
    G = np.zeros((len(Xf), K, 4))
    G[:, :, :3] = dg.transpose(1, 0, 2)
    f = scale * _ratio_resid(L, R, X).reshape(K, -1)
    Jtf = scale * np.einsum("xkj,kx->kj", G, f - f.mean(axis=0)).ravel()
    G = G.reshape(len(Xf), 4 * K)
    GtG = G.T @ G
    JtJ = -GtG / K
    _add_blocks(JtJ, [GtG[4 * k:4 * k + 4, 4 * k:4 * k + 4] for k in range(K)])
    return scale ** 2 * JtJ, Jtf


def _params(model: LightModel) -> np.ndarray:
    """(K, 4) rows (azimuth, elevation, log distance, log intensity) of near lights."""
    P = model.positions_mm
    D = np.linalg.norm(P, axis=1)
    return np.column_stack([np.arctan2(P[:, 1], P[:, 0]), np.arcsin(np.clip(P[:, 2] / D, -1, 1)), np.log(D),
                            np.log(model.intensities)])


class _Problem:
    """The per-light refinement's residual and its exact Gauss-Newton normal equations in (azimuth,
    elevation, log distance, log intensity) per lamp: photometric residual / sqrt(n), drop-off prior,
    and the mean log intensity held at 0 (the overall scale is the albedo's)."""

    def __init__(self, sample: PixelSample, R, X, *, w_drop):
        self.sample, self.R, self.X, self.w_drop = sample, R, X, w_drop
        self.n_res, self.n_dr = sample.I.size, R.size

    def unpack(self, t):
        th = t.reshape(-1, 4)
        return _lamp_positions(th), np.exp(th[:, 3])

    def drop(self, t):
        return self.w_drop * _ratio_resid(self.unpack(t)[0], self.R, self.X) / np.sqrt(self.n_dr)

    def fun(self, t):
        P, E = self.unpack(t)
        r_ph = photometric_residual(self.sample, LightModel.from_positions(P, E))
        return np.concatenate([r_ph / np.sqrt(self.n_res), self.drop(t), [np.mean(t.reshape(-1, 4)[:, 3])]])

    def photometric_terms(self, t):
        """``(e, JtJ, Jtr)`` of the photometric rows (scaled like :meth:`fun`): :func:`_vp_normal_equations`."""
        _, e, JtJ, Jtr = _vp_normal_equations(self.sample, t.reshape(-1, 4))
        return e / np.sqrt(self.n_res), JtJ / self.n_res, Jtr / self.n_res

    def normal_equations(self, t, f=None):
        """``(J^T J, J^T f)`` of :meth:`fun`, without forming J (:func:`levenberg_marquardt`; ``f`` is
        not needed: the residual comes with the normal equations)."""
        th = t.reshape(-1, 4)
        K = len(th)
        _, JtJ, Jtf = self.photometric_terms(t)
        Jd, fd = _drop_normal_equations(th, self.R, self.X, self.w_drop / np.sqrt(self.n_dr))
        JtJ += Jd
        Jtf += fd
        last = np.zeros(t.size)
        last[3::4] = 1.0 / K
        return JtJ + np.outer(last, last), Jtf + last * np.mean(th[:, 3])


def levenberg_marquardt(fun, normal_equations, x0, *, lb=None, ub=None, max_nfev=100, ftol=1e-8, xtol=1e-8,
                        callback=None):
    """Levenberg-Marquardt on the normal equations, with Jacobian scaling and bounds by projection.

    ``normal_equations(x, f)`` returns ``(J^T J, J^T f)`` at x, whose residual ``f = fun(x)`` it is
    given. Written here because the refinement's Jacobian is very tall and narrow (K * P rows, 4K
    columns: 600000 x 256 at 64 lamps) and its normal equations have a structure that gives them
    without it (:func:`_vp_normal_equations`): ``scipy.optimize.least_squares`` needs J itself and
    factorises it every iteration (an SVD in 'trf'; an unblocked QR in MINPACK's 'lm'). Steps and
    stopping follow MINPACK (Moré 1978): the damping is scaled by ``diag(J^T J)`` (``x_scale='jac'``),
    raised until the cost falls, lowered by the gain ratio; it stops when both the actual and the
    predicted relative reductions are below ``ftol`` or the scaled step is below ``xtol``.

    ``callback(nfev)``, if given, is called after every evaluation (progress).

    Returns
    -------
    (x, f, nfev, converged)
    """
    x = np.asarray(x0, dtype=float).copy()
    lb = np.full(x.size, -np.inf) if lb is None else np.asarray(lb, float)
    ub = np.full(x.size, np.inf) if ub is None else np.asarray(ub, float)
    f = fun(x)
    cost = float(f @ f)
    nfev, mu, converged = 1, None, False
    scale = None
    while nfev < max_nfev and not converged:
        A, g = normal_equations(x, f)
        d2 = np.diag(A).copy()
        scale = d2 if scale is None else np.maximum(scale, d2)
        scale = np.where(scale > 0, scale, 1.0)
        if mu is None:
            mu = 1e-3 * float(scale.max())
        while nfev < max_nfev:
            try:
                step = -np.linalg.solve(A + mu * np.diag(scale), g)
            except np.linalg.LinAlgError:
                mu *= 10.0
                continue
            x_new = np.clip(x + step, lb, ub)
            step = x_new - x
            f_new = fun(x_new)
            nfev += 1
            if callback is not None:
                callback(nfev)
            cost_new = float(f_new @ f_new)
            predicted = -(2 * g @ step + step @ A @ step)
            actual = cost - cost_new
            if cost_new < cost:
                rho = actual / predicted if predicted > 0 else 0.0
                mu *= max(1.0 / 3.0, 1.0 - (2.0 * rho - 1.0) ** 3)
                small_step = np.sqrt(np.sum(scale * step ** 2)) <= xtol * (np.sqrt(np.sum(scale * x ** 2)) + xtol)
                converged = (actual <= ftol * cost and predicted <= ftol * cost) or small_step
                x, f, cost = x_new, f_new, cost_new
                break
            mu *= 4.0
            if predicted <= ftol * cost * 1e-3:   # no step can lower the cost: at the minimum
                converged = True
                break
    return x, f, nfev, converged


def _refine_lsq(sample: PixelSample, start: LightModel, R, X, history, *, w_drop, max_nfev, callback=None):
    """One ``least_squares`` solve of :func:`_refine_each` on the given sample.

    Each light is parametrised by azimuth, elevation, log distance and log intensity: the shallow
    valley (closer and higher) is nearly straight in these coordinates and curved in Cartesian ones.
    """
    K = len(start.intensities)
    prob = _Problem(sample, R, X, w_drop=w_drop)
    x0 = _params(start).ravel()
    lb = np.tile([-np.inf, np.radians(1.0), np.log(20.0), -2.0], K)
    ub = np.tile([np.inf, np.radians(89.9), np.log(20000.0), 2.0], K)
    c0 = float(np.sum(prob.fun(x0) ** 2))
    x, f, nfev, converged = levenberg_marquardt(prob.fun, prob.normal_equations, np.clip(x0, lb + 1e-6, ub - 1e-6),
                                                lb=lb, ub=ub, max_nfev=max_nfev, callback=callback)
    history.append({"stage": "per-light", "pixels": int(sample.I.shape[1]), "iterations": int(nfev),
                    "converged": bool(converged), "cost_start": c0, "cost": float(np.sum(f ** 2)),
                    "drop_weight": float(w_drop)})
    P, E = prob.unpack(x)
    return LightModel.from_positions(P, E / np.exp(np.mean(np.log(E))))


#: Coverage factor of the heights' expanded uncertainty (:attr:`LightUncertainty.height_rel_95`).
COVERAGE_FACTOR = 2.0


@dataclass
class LightUncertainty:
    """Standard uncertainties of estimated near lights (docs/architecture.md, "Confidence").

    ``direction_deg``, ``distance_mm`` and ``intensity`` are per lamp; ``height_rel`` is the relative
    standard uncertainty of heights that follows (the shared change of the lamps' elevations, as
    ``d log h = -mean_k d log tan(e_k)``). Each combines the residual's noise (Gauss-Newton
    covariance, ``sigma^2 (J^T J)^-1``) and the additive term's own uncertainty carried through the
    solution (``-(J^T J)^-1 J^T dr/dc * se_c``). ``height_rel`` also holds ``height_rel_misfit``,
    what the lamp model leaves out (a bow, beams, cupping) moving the lamps along the bas-relief
    direction (:func:`_tile_misfit`), which the noise term does not see: it dominates wherever the
    estimated lamps are far off.
    """

    direction_deg: np.ndarray
    distance_mm: np.ndarray
    intensity: np.ndarray
    height_rel: float
    height_rel_noise: float
    height_rel_offset: float
    height_rel_misfit: float = 0.0

    @property
    def height_rel_95(self) -> float:
        """The heights' expanded relative uncertainty, coverage factor 2 (about 95 %; GUM 6.2)."""
        return COVERAGE_FACTOR * float(self.height_rel)

    def to_json(self) -> dict:
        return {"direction_deg": [round(float(v), 4) for v in self.direction_deg],
                "height_relative_95": round(self.height_rel_95, 5),
                "distance_mm": [round(float(v), 3) for v in self.distance_mm],
                "intensity": [round(float(v), 5) for v in self.intensity],
                "height_relative": round(float(self.height_rel), 5),
                "height_relative_from_noise": round(float(self.height_rel_noise), 5),
                "height_relative_from_offset": round(float(self.height_rel_offset), 5),
                "height_relative_from_misfit": round(float(self.height_rel_misfit), 5)}


def light_uncertainty(sample: PixelSample, model: LightModel, R, X, *, w_drop=1.0,
                      offset_stderr: Optional[float] = None) -> LightUncertainty:
    """Standard uncertainties of near lights estimated by :func:`estimate_lights`.

    Parameters
    ----------
    sample : PixelSample
        The photometric sample the lights were refined on (intensities with the additive term removed).
    model : LightModel
        The estimated lights.
    R, X
        The drop-off ratio maps and their points (as in the refinement).
    offset_stderr : float, optional
        Standard error of the removed additive term (grey counts), carried through the solution.
    """
    K = len(model.intensities)
    prob = _Problem(sample, R, X, w_drop=w_drop)
    t = _params(model).ravel()
    f = prob.fun(t)
    n = f.size
    JtJ, _ = prob.normal_equations(t)
    cov = np.linalg.pinv(JtJ) * float(np.sum(f ** 2)) / max(n - t.size, 1)
    th = t.reshape(K, 4)
    el = th[:, 1]
    w_h = np.zeros(t.size)
    w_h[1::4] = -1.0 / (K * np.sin(el) * np.cos(el))      # d log h / d e_k (the relief scale)
    var_noise = np.diag(cov)
    h_noise = float(np.sqrt(max(w_h @ cov @ w_h, 0.0)))
    shift = np.zeros(t.size)
    if offset_stderr is not None and np.isfinite(offset_stderr) and offset_stderr > 0:
        # d r / d c: the residual of every pixel when its samples all drop by 1 count, after its
        # normal (times albedo) re-fits: the part of the ones vector its lights cannot explain. It is
        # orthogonal to each pixel's lights, so J^T dr is the e-terms' sum alone (as J^T r).
        V = _vectors(sample, model)
        A = np.einsum("kpi,kpj->pij", V, V)
        b1 = np.linalg.solve(A, np.einsum("kpi->pi", V)[..., None])[..., 0]
        ones = 1.0 if sample.W is None else sample.W
        dr = -(ones - np.einsum("kpi,pi->kp", V, b1)) / _mean_lit(sample) / np.sqrt(prob.n_res)
        e, _, _ = prob.photometric_terms(t)
        shift = -np.linalg.pinv(JtJ) @ np.einsum("kjp,kp->kj", e, dr).ravel() * offset_stderr
    h_off = float(abs(w_h @ shift))
    Hinv = np.linalg.pinv(JtJ)
    # the misfit's spatial scale is unknown (a bow: the field; cupping: a few mm): the largest over
    # tilings of 4, 8 and 16 tiles a side
    misfits = [_tile_misfit(sample, th, Hinv, w_h, prob.n_res, tiles=n) for n in MISFIT_TILES]
    h_misfit = float(np.nanmax(misfits)) if np.any(np.isfinite(misfits)) else 0.0
    var = var_noise + shift ** 2
    cos_el = np.cos(el)
    dir_rad = np.sqrt(var[1::4] + cos_el ** 2 * var[0::4])
    D = np.exp(th[:, 2])
    total = float(np.sqrt(h_noise ** 2 + h_off ** 2 + h_misfit ** 2))
    return LightUncertainty(np.degrees(dir_rad), D * np.sqrt(var[2::4]), np.exp(th[:, 3]) * np.sqrt(var[3::4]),
                            total, h_noise, h_off, h_misfit)


#: Tilings of the field (tiles a side) for the heights' misfit term (:func:`_tile_misfit`).
MISFIT_TILES = (4, 8, 16)


def _tile_misfit(sample: PixelSample, th, Hinv, w_h, n_res, tiles: int = 8) -> float:
    """Relative height uncertainty from what the lamp model leaves out, by tiles of the field.

    The noise term assumes independent residuals; what the model leaves out (a bowed canvas's
    shading, beams, cupping) is spatially coherent, and it moves the lamps along the bas-relief
    direction. Each tile's share of the photometric gradient ``J_g^T r_g`` differs from the others'
    by that coherent misfit; their spread through ``(J^T J)^-1`` (the cluster-robust sandwich, a
    linearised jackknife over the tiles) is the heights' scale's uncertainty from it.
    """
    rows, cols = np.asarray(sample.rows), np.asarray(sample.cols)
    M, N = float(rows.max()) + 1.0, float(cols.max()) + 1.0
    tile = (rows * tiles // M).astype(int) * tiles + (cols * tiles // N).astype(int)
    scores = []
    for g in np.unique(tile):
        sel = np.nonzero(tile == g)[0]
        if sel.size < 8:
            continue
        scores.append(_vp_normal_equations(sample.take(sel), th, workers=1)[3] / n_res)
    if len(scores) < 3:
        return float("nan")
    S = np.asarray(scores)
    S = S - S.mean(axis=0)
    G = len(S)
    proj = S @ (Hinv @ w_h)                                   # each tile's pull on log h
    return float(np.sqrt(G / (G - 1) * np.sum(proj ** 2)))


def _intensity_jacobian(sample: PixelSample, P, E, scale, *, out, factor, workers=None) -> None:
    """:func:`_vp_residual_and_jacobian`'s log E columns (``intensities_only``) times ``factor`` into ``out``
    (K * pixels, K), in bands of pixels over :func:`lamp_threads` threads as :func:`photometric_residual`:
    each pixel's rows are its own arithmetic (its light matrix, its inverse, its residual), so the Jacobian
    is the one-thread one to the bit (``tests/test_lights.py::test_lamp_refinement_same_in_one_and_two_threads``)."""
    K, n = sample.I.shape
    parts = max(1, min(lamp_threads(workers), n // MIN_PIXELS_PER_THREAD))
    if parts == 1:
        _vp_residual_and_jacobian(sample, P, E, scale, out=out, factor=factor, intensities_only=True)
        return
    J = out.reshape(K, n, K)

    def part(pixels):
        band = np.empty((K * (pixels.stop - pixels.start), K))
        _vp_residual_and_jacobian(sample.take(pixels), P, E, scale, out=band, factor=factor, intensities_only=True)
        J[:, pixels] = band.reshape(K, -1, K)

    map_bands(part, n, parts=parts, threads=parts)


def refine_intensities(sample: PixelSample, positions_mm, intensities=None) -> np.ndarray:
    """Relative lamp intensities (median 1) for KNOWN positions, by the photometric residual.

    The levels of the images tell the intensities only if the surface is flat and facing the camera;
    on a cupped or textured painting they are off by several per cent, which tilts every normal
    (1.2 deg mean on a cupped benchmark capture). Here the intensities minimise paper Eq. 2's
    residual with the positions held (variable projection, :func:`photometric_residual`).
    """
    P = np.asarray(positions_mm, dtype=float)
    K = len(P)
    E0 = np.ones(K) if intensities is None else np.asarray(intensities, dtype=float)
    scale = np.linalg.norm(P, axis=1).mean()
    n = sample.I.size

    def fun(logE):
        r = photometric_residual(sample, LightModel.from_positions(P, np.exp(logE)))
        return np.concatenate([r / np.sqrt(n), [np.mean(logE)]])

    def jac(logE):
        J = np.empty((n + 1, K))
        _intensity_jacobian(sample, P, np.exp(logE), scale, out=J[:n], factor=1.0 / np.sqrt(n))
        J[-1] = 1.0 / K
        return J

    sol = least_squares(fun, np.log(E0) - np.mean(np.log(E0)), jac=jac, method="lm", x_scale="jac")
    E = np.exp(sol.x)
    return E / np.median(E)
