"""Levelling a height map: the best plane (or a low-order form) removed, and recorded.

Photometric-stereo heights integrate the normals, and a mean bias of the normals of ``d`` degrees
(lamps placed or calibrated that far off, well within what any lamp calibration promises) is a
slope ``tan(d)``: 17.5 um per mm for each degree, a ramp of ``W tan(d)`` across a field ``W`` wide
(0.2 deg over 24 mm: 84 um, more than every protrusion is high). Surface metrology removes the
form before it shows a relief (ISO 25178-2 "F-operation"); uvps does the same by default:

- ``"plane"`` (default): the least-squares plane over the valid pixels removed;
- ``"form"``: a 2-D Legendre polynomial of total degree :data:`FORM_DEGREE` removed (a canvas's
  bow, a cupped field: for looking past the field-scale shape at the paint's own relief);
- ``"none"``: nothing removed (the relief as integrated).

Whatever is removed is recorded (:class:`Levelling`, ``run.json`` ``level``) so the heights as
integrated are rebuilt exactly: ``raw = levelled + surface`` (:meth:`Levelling.surface`,
:func:`raw_height`). The best plane's slopes are recorded whichever choice (for ``"none"`` they
say what the map still holds).

Frames: x toward increasing column, y up (toward decreasing row); slopes in um per mm; the
Legendre variables are ``u = 2 col / (N - 1) - 1`` (x) and ``v = 1 - 2 row / (M - 1)`` (y), both
in [-1, 1] over the pixel centres, and the surface is
``numpy.polynomial.legendre.legval2d(u, v, coeffs)`` with ``coeffs[i, j]`` the term
``L_i(u) L_j(v)``, ``i + j <= degree``.

Robust to protrusions: the fit is iteratively reweighted with Tukey's biweight (4.685 robust
standard deviations, 1.4826 MAD of the residuals): protrusions tens of micrometres high cluster
in some colour areas, and on one side of the field they would tilt a plain least-squares plane
toward them (150 domes 40 um high over the right third of a 1 um/mm plane: 2.13 um/mm, the reweighted
fit 1.00; on the demo the two differ by 0.01 um/mm); craters, masked-out edges and pixels integrated
through a zero gradient pull the same way. It costs a few extra solves on a sample of at most
:data:`FIT_SAMPLES` pixels (milliseconds), so it is always on.
"""
from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from typing import Optional

import numpy as np
from numpy.polynomial import legendre

from ..errors import UVPSInputError, check_pixel_size
from .stack import row_bands

log = logging.getLogger(__name__)

__all__ = ["LEVELS", "FORM_DEGREE", "Levelling", "level_height", "fit_surface", "legendre_surface", "legendre_uv",
           "raw_height", "tilt_slope_um_per_mm"]

#: What :func:`level_height` removes: nothing, the best plane (default), or a low-order form.
LEVELS = ("none", "plane", "form")
#: Total degree of the Legendre form removed by ``"form"``: a canvas's bow (quadratic) and its
#: asymmetry (cubic); far from the scale of a protrusion (a 24 mm field's cubic has no structure
#: finer than ~8 mm).
FORM_DEGREE = 3
#: Pixels the surface is fitted on at most (a regular grid of the valid pixels).
FIT_SAMPLES = 400_000
#: Tukey biweight tuning constant (in robust standard deviations) and iterations.
TUKEY_C = 4.685
ROBUST_ITERATIONS = 6


def tilt_slope_um_per_mm(bias_deg: float) -> float:
    """The slope (um per mm) a mean normal bias of ``bias_deg`` degrees gives the heights:
    ``1000 tan(bias)`` (17.45 um/mm per degree)."""
    return 1000.0 * math.tan(math.radians(float(bias_deg)))


@dataclass
class Levelling:
    """What :func:`level_height` removed from a height map, and the best plane's slopes.

    Attributes
    ----------
    method : str
        One of :data:`LEVELS`.
    degree : int
        Total degree of the removed surface (0 for ``"none"``: only the median offset).
    coeffs : ndarray, shape (degree + 1, degree + 1)
        Legendre coefficients of the removed surface (um), ``coeffs[i, j]`` of ``L_i(u) L_j(v)``
        (module notes); ``raw = levelled + surface``.
    shape : tuple
        (M, N) of the height map.
    pixel_size_um : float
    slope_x_um_per_mm, slope_y_um_per_mm : float
        The best plane's slopes (dz/dx, dz/dy; x right, y up), whatever was removed.
    removed_rms_um : float
        RMS over the valid pixels of the removed surface minus its median (what levelling took).
    """

    method: str
    degree: int
    coeffs: np.ndarray
    shape: tuple
    pixel_size_um: float
    slope_x_um_per_mm: float
    slope_y_um_per_mm: float
    removed_rms_um: float = 0.0

    @property
    def tilt_deg(self) -> float:
        """The best plane's tilt from the camera's image plane (deg)."""
        return math.degrees(math.atan(math.hypot(self.slope_x_um_per_mm, self.slope_y_um_per_mm) / 1000.0))

    def surface(self, rows: slice = slice(None)) -> np.ndarray:
        """The removed surface (um, float32) on the rows ``rows`` of the map (all by default)."""
        return legendre_surface(self.coeffs, self.shape, rows)

    def why(self) -> str:
        """What a tilt of the lamps does to the plane, with this map's figures (run.json ``level.why``)."""
        width_mm = max(self.shape) * self.pixel_size_um / 1000.0
        return (f"a mean bias of the normals of d deg (the lamps' directions off by that much on average; a "
                f"calibration leaves a few tenths of a degree) is a slope of tan(d), {tilt_slope_um_per_mm(1.0):.1f} "
                f"um/mm per deg: over this field's {width_mm:.3g} mm a ramp of {width_mm:.3g} tan(d) mm. This best "
                f"plane is tilted {self.tilt_deg:.3g} deg ({width_mm * math.tan(math.radians(self.tilt_deg)) * 1000:.3g}"
                " um across the field): such a bias, or the painting's own tilt against the camera; "
                + ("removed, so the relief shows" if self.method != "none" else "not removed (level none)"))

    def to_json(self) -> dict:
        """``run.json``'s ``level``."""
        return {"method": self.method, "degree": int(self.degree),
                "slope_x_um_per_mm": round(float(self.slope_x_um_per_mm), 4),
                "slope_y_um_per_mm": round(float(self.slope_y_um_per_mm), 4),
                "tilt_deg": round(self.tilt_deg, 5),
                "removed_rms_um": round(float(self.removed_rms_um), 4),
                "shape": [int(s) for s in self.shape], "pixel_size_um": float(self.pixel_size_um),
                "legendre_coeffs_um": [[float(c) for c in row] for row in self.coeffs],
                "why": self.why(),
                "raw": "raw height = depth.tif + this surface: numpy.polynomial.legendre.legval2d(u, v, "
                       "legendre_coeffs_um), u = 2 col / (N - 1) - 1, v = 1 - 2 row / (M - 1) "
                       "(uvps.core.level.raw_height)"}

    @classmethod
    def from_json(cls, d: dict) -> "Levelling":
        """The :class:`Levelling` a ``run.json`` ``level`` records."""
        try:
            coeffs = np.asarray(d["legendre_coeffs_um"], float)
            return cls(str(d["method"]), int(d["degree"]), coeffs, tuple(int(s) for s in d["shape"]),
                       float(d["pixel_size_um"]), float(d["slope_x_um_per_mm"]), float(d["slope_y_um_per_mm"]),
                       float(d.get("removed_rms_um", 0.0)))
        except (KeyError, TypeError, ValueError) as exc:
            raise UVPSInputError(f"run.json level: not a levelling record ({exc})") from None


def legendre_uv(rows, cols, shape) -> tuple:
    """The Legendre variables ``(u, v)`` (module notes: ``u`` from the columns, ``v`` up from the rows, both
    in [-1, 1]) of an ``(M, N)`` map at its pixels ``rows`` and ``cols`` (any shape, sub-pixel allowed)."""
    m, n = shape
    return (2.0 * np.asarray(cols, np.float64) / max(n - 1, 1) - 1.0,
            1.0 - 2.0 * np.asarray(rows, np.float64) / max(m - 1, 1))


def legendre_surface(coeffs, shape, rows: slice = slice(None)) -> np.ndarray:
    """The surface of the Legendre ``coeffs`` (module notes; :func:`fit_surface`) on the rows ``rows``
    of an ``(M, N)`` map, float32."""
    m, n = shape
    degree = coeffs.shape[0] - 1
    u, v = legendre_uv(np.arange(m)[rows], np.arange(n), shape)
    # separable: S[r, c] = sum_ij c_ij L_i(u_c) L_j(v_r) = (Lv @ C^T @ Lu^T)[r, c]
    lu = legendre.legvander(u, degree)           # (N, d + 1)
    lv = legendre.legvander(v, degree)           # (rows, d + 1)
    return (lv @ coeffs.T @ lu.T).astype(np.float32)


def _sample(height_um, valid, n_max):
    """Rows, columns and heights of a regular grid of the valid pixels (at most about ``n_max``)."""
    m, n = height_um.shape
    step = max(1, int(math.ceil(math.sqrt(int(np.count_nonzero(valid)) / n_max))))
    sub = valid[::step, ::step]
    r, c = np.nonzero(sub)
    return r * step, c * step, height_um[::step, ::step][sub].astype(np.float64)


def _terms(degree):
    return [(i, j) for i in range(degree + 1) for j in range(degree + 1 - i)]


def fit_surface(height_um, *, degree: int, mask=None, robust: bool = True) -> np.ndarray:
    """Legendre coefficients (module notes) of the surface of total ``degree`` best fitting the
    finite heights inside ``mask``: least squares, Tukey-reweighted when ``robust``.

    Returns the ``(degree + 1, degree + 1)`` coefficient array (0 beyond the total degree).
    """
    h = np.asarray(height_um)
    valid = np.isfinite(h) if mask is None else (np.isfinite(h) & np.asarray(mask, bool))
    terms = _terms(degree)
    coeffs = np.zeros((degree + 1, degree + 1))
    if np.count_nonzero(valid) < 4 * len(terms):
        log.warning("levelling: %d valid pixels, too few to fit a surface of degree %d: nothing removed",
                    int(np.count_nonzero(valid)), degree)
        return coeffs
    r, c, z = _sample(h, valid, FIT_SAMPLES)
    u, v = legendre_uv(r, c, h.shape)
    full = legendre.legvander2d(u, v, [degree, degree])        # columns: i * (d + 1) + j
    A = full[:, [i * (degree + 1) + j for i, j in terms]]
    w = np.ones_like(z)
    for _ in range(ROBUST_ITERATIONS if robust else 1):
        sw = np.sqrt(w)
        sol = np.linalg.lstsq(A * sw[:, None], z * sw, rcond=None)[0]
        res = z - A @ sol
        s = 1.4826 * float(np.median(np.abs(res - np.median(res))))
        if not robust or not s > 0:
            break
        w_new = np.clip(1.0 - (res / (TUKEY_C * s)) ** 2, 0.0, None) ** 2
        if np.allclose(w_new, w, atol=1e-4):
            break
        w = w_new
    for (i, j), value in zip(terms, sol):
        coeffs[i, j] = value
    return coeffs


def _plane_slopes(coeffs, shape, pixel_size_um):
    """dz/dx and dz/dy (um per mm) of the degree-1 part of ``coeffs``."""
    m, n = shape
    mm = pixel_size_um / 1000.0
    sx = coeffs[1, 0] * 2.0 / (max(n - 1, 1) * mm)
    sy = coeffs[0, 1] * 2.0 / (max(m - 1, 1) * mm)
    return float(sx), float(sy)


def level_height(height_um, *, method: str = "plane", pixel_size_um: float, mask=None,
                 form_degree: int = FORM_DEGREE, out: Optional[np.ndarray] = None) -> tuple:
    """The height map with its best plane (or form) removed, and what was removed.

    Parameters
    ----------
    height_um : ndarray, shape (M, N)
        Heights (um; NaN outside the field). Not modified.
    method : {"none", "plane", "form"}
        What to remove (:data:`LEVELS`; module notes).
    pixel_size_um : float
    mask : ndarray of bool, optional
        The pixels to fit on (True = use) besides the finite ones.
    form_degree : int
        Total degree of ``"form"``.
    out : ndarray, optional
        Where to write the levelled heights (float32, ``height_um`` itself to level in place).

    Returns
    -------
    (ndarray, Levelling)
        The levelled heights (float32, median 0 over the fitted pixels, NaN where ``height_um`` is)
        and the record, with which ``raw = levelled + record.surface()``.

    Examples
    --------
    >>> import numpy as np
    >>> rows, cols = np.mgrid[0:50, 0:80]
    >>> h = (0.5 * cols * 0.03 - 2.0 * (49 - rows) * 0.03).astype(np.float32)  # x: 0.5, y: -2 um/mm
    >>> flat, lev = level_height(h, pixel_size_um=30.0)
    >>> round(lev.slope_x_um_per_mm, 3), round(lev.slope_y_um_per_mm, 3), float(np.abs(flat).max()) < 1e-3
    (0.5, -2.0, True)
    """
    if method not in LEVELS:
        raise UVPSInputError(f"level must be one of {', '.join(LEVELS)}; got {method!r}")
    pixel_size_um = check_pixel_size(pixel_size_um)
    h = np.asarray(height_um)
    if h.ndim != 2 or min(h.shape) < 2:
        raise UVPSInputError(f"height_um must be a 2-D (M, N) array with M, N >= 2; got {h.shape}")
    valid = np.isfinite(h) if mask is None else (np.isfinite(h) & np.asarray(mask, bool))
    plane = fit_surface(h, degree=1, mask=valid)
    sx, sy = _plane_slopes(plane, h.shape, pixel_size_um)
    if method == "plane":
        coeffs, degree = plane, 1
    elif method == "form":
        degree = int(form_degree)
        coeffs = fit_surface(h, degree=degree, mask=valid)
    else:
        coeffs, degree = np.zeros((1, 1)), 0
    rec = Levelling(method, degree, coeffs, tuple(h.shape), pixel_size_um, sx, sy)
    if out is None:
        out = np.empty(h.shape, np.float32)
    m, n = h.shape
    # one pass: each band's surface removed, and kept on the valid pixels for the RMS removed
    removed = np.empty(int(np.count_nonzero(valid)) if degree else 0, np.float32)
    at = 0
    for rows in row_bands(m, n, 1 << 20):
        if degree:
            surf = rec.surface(rows)
            out[rows] = h[rows] - surf
            part = surf[valid[rows]]
            removed[at:at + part.size] = part
            at += part.size
        else:
            out[rows] = h[rows]
    if valid.any():
        med = float(np.median(out[valid]))
        out -= np.float32(med)
        rec.coeffs = rec.coeffs.copy()
        rec.coeffs[0, 0] += med        # the offset too: raw = levelled + surface, exactly
        if degree:
            rec.removed_rms_um = float(np.sqrt(np.mean((removed - np.median(removed)) ** 2.0)))
    log.info("levelling (%s): best plane %.3g, %.3g um/mm (x right, y up), %.3g um rms removed", method, sx, sy,
             rec.removed_rms_um)
    return out, rec


def raw_height(levelled_um, record) -> np.ndarray:
    """The height map as integrated, before levelling: ``levelled + record.surface()``.

    ``record``: a :class:`Levelling` or the ``level`` dict of a ``run.json``.
    """
    rec = record if isinstance(record, Levelling) else Levelling.from_json(record)
    h = np.asarray(levelled_um, np.float32)
    if tuple(h.shape) != tuple(rec.shape):
        raise UVPSInputError(f"the height map is {h.shape}, the levelling record {tuple(rec.shape)}: not the same "
                             "map")
    return h + rec.surface()
