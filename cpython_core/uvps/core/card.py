"""Per-lamp flat-field from a flat fluorescent card.

A flat fluorescent card laid on the painting and photographed under every lamp position holds,
per lamp and pixel, everything the lamp model does not: the lamp's beam and aim, its power, the
lens's vignetting (architecture.md, "Image model of a real capture")::

    C_k(x) = V(x) * a_c * B_k(X) * E_k * (|L_k| / |L_k - X|)^2 * n_c . (L_k - X) / |L_k - X|

With the lamps' positions (or directions) known, the card's **gain** is what it receives beyond
the model of a flat card facing the camera (``n_c = +z``, ``E_k = 1``)::

    G_k(x) = C_k(x) / (z . v_k(X)),   v_k from :mod:`uvps.core.irradiance`

and dividing each image of the painting by it leaves ``I_k / G_k = (albedo / a_c) n . v_k(X)``:
the model's irradiance with equal lamps, so the stereo solves the normals as if the lamps had no
beams, equal power and no vignetting (``I_k / C_k = (albedo / a_c) n . l_k / l_z,k``).
Stray light is additive, not a gain: it is removed by the dark frame, from the card's images as
from the painting's.

The gains are fitted per lamp as a smooth surface (Legendre, :data:`DEGREE`, in log) to the card's
block means: beams, vignetting and the inverse square are smooth across a field of a few cm, and
a smooth fit adds none of the card's own noise or texture to the painting. What the fit leaves,
per block, is split in two:

- the part every lamp shares: the card's own unevenness (its fluorescence varies across it),
  reported as :attr:`CardCalibration.unevenness` (RMS fraction) and left out of the gains;
- the part that differs between lamps: the card's **relief** (a card not lying flat shades
  differently under each lamp). It is read as a slope per block (``r_k = -s . l_xy,k / l_z,k``,
  least squares over the lamps) and a card whose RMS slope exceeds :data:`MAX_RELIEF_DEG` is
  refused: its ratio maps show relief, which the gains would carry into every normal.

**Tilt.** A card tilted by ``t`` multiplies each lamp's image by ``n_c . l_k / l_z,k`` ~ ``1 + t .
l_xy,k / l_z,k``, nearly a constant per lamp: from the card alone a tilt and lamps of unequal
power (or beams aimed off the centre) look the same. :attr:`CardCalibration.tilt_deg` is read from
the lamps' levels taking their powers as given (equal when the lights give none): it is right for
a rig of equal lamps, and is a check, not a correction. The run measures the card's tilt against
the painting instead (the mean surface plane is z = 0, architecture.md) and divides it out
(:meth:`CardCalibration.tilted`).
"""
from __future__ import annotations

import logging
from dataclasses import dataclass, field
from typing import Optional

import numpy as np
from numpy.polynomial import legendre as Lg

from ..errors import UVPSInputError
from .flatfield import GainCorrected, fit_log_grid, to_unit
from .irradiance import LightModel, lamp_vectors, pixel_coordinates_mm

log = logging.getLogger(__name__)

__all__ = ["CardCalibration", "calibrate_card", "apply_card", "DEGREE", "MAX_RELIEF_DEG",
           "MAX_SATURATED_FRACTION"]

#: Legendre degree of each lamp's log gain across the field.
DEGREE = 6
#: Block size target: about this many blocks along the longer side.
BLOCKS = 128
#: A card whose relief (RMS slope of its lamp-dependent shading beyond the smooth fit) exceeds this is
#: refused. A flat card's noise reads 0.01-0.03 deg on synthetic 16-bit cards (tests/test_card.py).
MAX_RELIEF_DEG = 0.5
#: A card image with more than this fraction of its pixels at or above saturation is refused.
MAX_SATURATED_FRACTION = 1e-4


@dataclass
class CardCalibration:
    """A card's per-lamp flat-field (:func:`calibrate_card`).

    Attributes
    ----------
    coeffs : (K, n, n) array
        Legendre coefficients of each lamp's log gain (rows and columns mapped to [-1, 1] as in
        :class:`uvps.core.flatfield.DropoffFit`), the gains' median over every lamp and pixel 1.
    shape : (M, N)
    tilt_deg, tilt_azimuth_deg : float
        The card's tilt from the lamps' levels, their powers taken as given (module docstring), and
        the azimuth (deg, counter-clockwise from +x) toward which it rises.
    unevenness : float
        RMS fraction of the card's brightness that every lamp shares and that is not smooth.
    relief_deg : float
        RMS slope (deg) of the card's relief beyond the smooth fit.
    diagnostics : dict
        Per-lamp levels, the fit's residual, saturation, what the tilt assumes.
    """

    coeffs: np.ndarray
    shape: tuple
    tilt_deg: float
    tilt_azimuth_deg: float
    unevenness: float
    relief_deg: float
    diagnostics: dict = field(default_factory=dict)

    @property
    def n_lamps(self) -> int:
        return int(self.coeffs.shape[0])

    @property
    def gains(self) -> np.ndarray:
        """(K, M, N) float32 per-lamp gain maps (median 1 over every lamp and pixel)."""
        M, N = self.shape
        deg = self.coeffs.shape[1] - 1
        Vv = Lg.legvander(to_unit(np.arange(M), M), deg)
        Vu = Lg.legvander(to_unit(np.arange(N), N), deg)
        return np.stack([np.exp(Vv @ c @ Vu.T).astype(np.float32) for c in self.coeffs])

    def tilted(self, slope, lights, *, pixel_size_um) -> "CardCalibration":
        """This calibration for a card whose surface has gradient ``slope = (dz/dx, dz/dy)``: each
        gain divided by ``n_c . v_k / z . v_k`` (the tilt's share of what the card received).
        ``lights`` as for :func:`calibrate_card`."""
        p, q = float(slope[0]), float(slope[1])
        n_c = np.array([-p, -q, 1.0]) / np.sqrt(1.0 + p * p + q * q)
        rows, cols, X = _grid(self.shape, pixel_size_um, BLOCKS)
        V = _vectors(_as_lights(lights, self.n_lamps), X)
        factor = np.log(V[..., 2] / np.einsum("kmni,i->kmn", V, n_c))
        coeffs = self.coeffs + fit_log_grid(factor, rows, cols, self.shape, self.coeffs.shape[1] - 1)
        out = CardCalibration(coeffs, self.shape, self.tilt_deg, self.tilt_azimuth_deg, self.unevenness,
                              self.relief_deg, dict(self.diagnostics))
        out.diagnostics["tilt_corrected_deg"] = float(np.degrees(np.arctan(np.hypot(p, q))))
        return out

    def to_json(self) -> dict:
        """The card's figures (no maps): for run.json and calibration.json."""
        return {"n_lamps": self.n_lamps, "image_shape": list(self.shape), "degree": int(self.coeffs.shape[1] - 1),
                "tilt_deg": round(self.tilt_deg, 4), "tilt_azimuth_deg": round(self.tilt_azimuth_deg, 2),
                "unevenness": round(self.unevenness, 5), "relief_deg": round(self.relief_deg, 4),
                **self.diagnostics}


def _as_lights(lights, k) -> LightModel:
    """A LightModel from a LightModel or a (K, 3) array (unit rows: directions; else positions, mm)."""
    if isinstance(lights, LightModel):
        model = lights
    else:
        a = np.asarray(lights, dtype=float)
        if a.ndim != 2 or a.shape[1] != 3 or not np.all(np.isfinite(a)):
            raise UVPSInputError(f"lights must be ({k}, 3) lamp positions (mm) or directions, one per card image; "
                                 f"got shape {a.shape}")
        unit = np.allclose(np.linalg.norm(a, axis=1), 1.0, atol=1e-6)
        model = LightModel.from_directions(a) if unit else LightModel.from_positions(a)
    if len(model.directions) != k:
        raise UVPSInputError(f"the card has {k} images and the lights {len(model.directions)} lamps; "
                             "take one card image per lamp position, in the capture's order")
    if np.any(model.directions[:, 2] <= 0.0):
        raise UVPSInputError("lights: every lamp must be above the card (z > 0)")
    return model


def _vectors(lights: LightModel, X) -> np.ndarray:
    """Each lamp's irradiance vector with E = 1 at X: (K, ..., 3)."""
    return lamp_vectors(X, intensities=np.ones(len(lights.directions)), positions_mm=lights.positions_mm,
                        directions=None if lights.near else lights.directions)


def _grid(shape, pixel_size_um, target):
    """Block size, block-centre rows and cols, and their world points (R, C, 3) mm."""
    M, N = shape
    b = max(1, int(np.ceil(max(M, N) / target)))
    rows = np.arange(M // b) * b + (b - 1) / 2.0
    cols = np.arange(N // b) * b + (b - 1) / 2.0
    X = pixel_coordinates_mm(rows[:, None], cols[None, :], shape, pixel_size_um)
    return rows, cols, X


def _block_means(img, b):
    m, n = img.shape[0] // b, img.shape[1] // b
    return img[:m * b, :n * b].reshape(m, b, n, b).mean(axis=(1, 3))


def _log_block_means(imgs, dark, saturation, rows, cols):
    """Each card image's log block means on the grid ``rows`` x ``cols`` (grey, dark subtracted) and its
    saturated fraction; a saturated image or one without signal is refused, naming it."""
    K = imgs.shape[0]
    b = int(round(rows[1] - rows[0])) if len(rows) > 1 else 1
    logs = np.empty((K, len(rows), len(cols)))
    sat_frac = []
    for k in range(K):
        raw = np.asarray(imgs[k])
        if saturation is not None:
            hot = raw >= saturation
            frac = float((hot.any(axis=-1) if raw.ndim == 3 else hot).mean())
            sat_frac.append(frac)
            if frac > MAX_SATURATED_FRACTION:
                raise UVPSInputError(
                    f"card image {k + 1} is saturated ({100 * frac:.2g} % of its pixels at or above "
                    f"{saturation:g} counts): take the card with a shorter exposure")
        img = raw.astype(np.float32)
        if dark is not None:
            img -= dark
        grey = img.mean(axis=-1) if img.ndim == 3 else img
        means = _block_means(grey, b)
        if not np.all(means > 0):
            raise UVPSInputError(f"card image {k + 1} has no signal in {int(np.sum(means <= 0))} blocks "
                                 "(dark, or the dark frame is brighter): the card must fill the field, lit")
        logs[k] = np.log(means)
    return logs, sat_frac


def calibrate_card(card_images, *, lights, pixel_size_um: float, dark=None, saturation: Optional[float] = None,
                   degree: int = DEGREE, max_relief_deg: float = MAX_RELIEF_DEG) -> CardCalibration:
    """Per-lamp flat-field gains from images of a flat fluorescent card under each lamp position.

    Parameters
    ----------
    card_images : (K, M, N) or (K, M, N, C) array
        The card under each lamp, in the capture's order and camera settings (counts, not rescaled).
    lights : LightModel or (K, 3) array
        The lamps: positions in mm from the image centre, or unit directions (far lamps). Their
        intensities, when the model holds them, only serve the tilt read from the levels.
    pixel_size_um : float
        Pixel size on the card (um).
    dark : (M, N) or (M, N, C) array, optional
        A frame with the lamps off (black level, stray light), subtracted from every card image.
    saturation : float, optional
        Counts at or above which a sample is saturated (default: the images' integer maximum).
    degree : int
        Legendre degree of each lamp's log gain (:data:`DEGREE`).
    max_relief_deg : float
        Refuse a card whose relief's RMS slope exceeds this (:data:`MAX_RELIEF_DEG`).

    Returns
    -------
    CardCalibration

    Raises
    ------
    UVPSInputError
        Shapes that do not match, a saturated card image, one without signal, or a card that is
        not flat (its ratio maps show relief).

    Notes
    -----
    Per lamp: block means of the grey card (dark subtracted) over the model irradiance of a flat
    card with equal lamps (:mod:`uvps.core.irradiance`), their log fitted by a Legendre surface; the
    residuals give the unevenness (shared by the lamps) and the relief (lamp-dependent), see the
    module docstring. Cost: one pass over the card images.

    Examples
    --------
    >>> from uvps.testing.synthetic import make_capture, render_card
    >>> cap = make_capture(shape=(120, 160), n_lights=6, beam_exponent=30.0, beam_aim_error_deg=5.0)
    >>> card = calibrate_card(render_card(cap), lights=cap.light_positions_mm, pixel_size_um=cap.spec.pixel_size_um)
    >>> card.gains.shape
    (6, 120, 160)
    """
    imgs = card_images
    if imgs.ndim not in (3, 4) or imgs.shape[0] < 1:
        raise UVPSInputError(f"card images must be (K, M, N) or (K, M, N, C); got shape {imgs.shape}")
    K, M, N = imgs.shape[:3]
    if min(M, N) < 16:
        raise UVPSInputError(f"card images must be at least 16 x 16 px; got {M} x {N}")
    if not pixel_size_um > 0:
        raise UVPSInputError(f"pixel_size_um must be > 0; got {pixel_size_um}")
    model = _as_lights(lights, K)
    if dark is not None:
        dark = np.asarray(dark, dtype=np.float32)
        if dark.shape != tuple(imgs.shape[1:]):
            raise UVPSInputError(f"the dark frame is {dark.shape} and the card images {tuple(imgs.shape[1:])}; "
                                 "take the dark frame with the same camera and settings")
    dtype = np.dtype(getattr(imgs, "dtype", np.float32))
    if saturation is None and dtype.kind in "ui":
        saturation = float(np.iinfo(dtype).max)
    rows, cols, X = _grid((M, N), pixel_size_um, BLOCKS)
    logs, sat_frac = _log_block_means(imgs, dark, saturation, rows, cols)
    V = _vectors(model, X)
    logs -= np.log(V[..., 2])                    # over a flat card's model irradiance, equal lamps
    coeffs = fit_log_grid(logs, rows, cols, (M, N), int(degree))
    Vv = Lg.legvander(to_unit(rows, M), int(degree))
    Vu = Lg.legvander(to_unit(cols, N), int(degree))
    smooth = np.einsum("ri,kij,cj->krc", Vv, coeffs, Vu)
    resid = logs - smooth
    common = resid.mean(axis=0)
    unevenness = float(np.sqrt(np.mean(common ** 2)))
    # relief: r_k - mean_k r_k = -s . (a_k - mean a), a_k = l_xy,k / l_z,k at the centre; per block
    A = model.directions[:, :2] / model.directions[:, 2:3]
    Ac = -(A - A.mean(axis=0))
    slope = np.linalg.lstsq(Ac, (resid - common).reshape(K, -1), rcond=None)[0] if K >= 3 else np.zeros((2, 1))
    relief_deg = float(np.degrees(np.arctan(np.sqrt(np.mean(np.sum(slope ** 2, axis=0))))))
    if relief_deg > max_relief_deg:
        raise UVPSInputError(
            f"the card is not flat: its images under the lamps differ by relief of {relief_deg:.2f} deg RMS slope "
            f"(at most {max_relief_deg:g}); lay the card flat on the painting (or use a stiffer card)")
    # the tilt from the levels at the centre, the lamps' powers as given
    E = np.asarray(model.intensities, dtype=float)
    p0 = Lg.legvander(np.zeros(1), int(degree))[0]
    centre = np.einsum("i,kij,j->k", p0, coeffs, p0) - np.log(E)      # each lamp's log gain at the centre
    tilt = np.linalg.lstsq(np.column_stack([np.ones(K), -A]), centre, rcond=None)[0][1:] if K >= 3 else np.zeros(2)
    tilt_deg = float(np.degrees(np.arctan(np.hypot(*tilt))))
    tilt_az = float(np.degrees(np.arctan2(tilt[1], tilt[0])) % 360.0)
    # median 1 over every lamp and block (the lamps' relative powers stay in the gains)
    med = float(np.median(smooth))
    coeffs[:, 0, 0] -= med
    levels = np.exp(centre - np.median(centre))
    diagnostics = {
        "lamp_levels": [round(float(v), 5) for v in levels],
        "fit_residual_rms": round(float(np.sqrt(np.mean((resid - common) ** 2))), 6),
        "saturated_fraction_max": round(max(sat_frac), 8) if sat_frac else None,
        "dark": dark is not None,
        "lights": "positions" if model.near else "directions",
        "tilt_assumes": "lamp powers as given" if not np.allclose(E, E[0]) else "equal lamp powers",
    }
    log.info("card: %d lamps, tilt %.2f deg (from levels), unevenness %.2f %%, relief %.3f deg",
             K, tilt_deg, 100 * unevenness, relief_deg)
    return CardCalibration(coeffs, (M, N), tilt_deg, tilt_az, unevenness, relief_deg, diagnostics)


def apply_card(images, calibration: CardCalibration):
    """``images`` seen divided by the card's gains, lamp by lamp, computed on access (the stack is never
    copied: :class:`uvps.core.flatfield.GainCorrected` with the card's coefficients)."""
    K, M, N = images.shape[:3]
    if (K, M, N) != (calibration.n_lamps,) + tuple(calibration.shape):
        raise UVPSInputError(f"the card was taken for {calibration.n_lamps} lamps at {calibration.shape[0]} x "
                             f"{calibration.shape[1]} px; the capture has {K} images of {M} x {N} px")
    return GainCorrected(images, calibration.coeffs)
