"""Synthetic XRF element maps for a synthetic capture, with their ground truth (re-exported by
:mod:`uvps.testing.synthetic`).

An XRF scanner moves a spot of about 1 mm over the painting on a grid of 250 um steps and records, per
grid point, the counts of each element's line. :func:`render_element_maps` renders that for a
:class:`uvps.testing.synthetic.SyntheticCapture`: each colour area holds each element at its own abundance
(counts per dwell), the field is seen through a Gaussian spot, sampled on a grid rotated, scaled and
shifted against the camera (covering the run's field and a margin around it), and every value gets
Poisson counting noise. The truth is the map-to-run similarity and each area's abundance.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Optional, Sequence

import cv2
import numpy as np
from scipy import ndimage

from ..core.elements import ElementMaps, similarity, spot_sigma_px

#: Elements of the paper's Fig. 5b, with the lines PyMCA names them by.
DEFAULT_ELEMENTS = ("Pb_L", "Cr_K", "Fe_K", "Cd_L")


@dataclass
class ElementTruth:
    """Element maps and what they were made of.

    Attributes
    ----------
    maps : ElementMaps
    map_to_run : (3, 3) float64
        Map pixel (col, row, 1) -> run pixel (col, row, 1).
    abundance : (R + 1, E) float64
        Counts per dwell of each element in each colour area (row 0: pixels in no area).
    """

    maps: ElementMaps
    map_to_run: np.ndarray
    abundance: np.ndarray


def render_element_maps(capture, *, elements: Sequence[str] = DEFAULT_ELEMENTS, step_um: float = 250.0,
                        spot_um: float = 1000.0, margin_mm: float = 2.5, rotation_deg: float = 0.0,
                        scale: float = 1.0, shift_mm=(0.0, 0.0), abundance: Optional[np.ndarray] = None,
                        within_area: float = 0.0, spot_shape: str = "gaussian", line_jitter_px: float = 0.0,
                        seed: int = 0) -> ElementTruth:
    """Render element maps of a synthetic capture's colour areas.

    Parameters
    ----------
    capture : uvps.testing.synthetic.SyntheticCapture
        Its ``regions`` (labels 1..R) and ``region_light`` (light areas lead-white rich) are used.
    elements : sequence of str
        Element names; the first is lead (abundant in the light areas), the others drawn at random.
    step_um : float
        The scan's step.
    spot_um : float
        The spot's FWHM.
    margin_mm : float
        How far the scan reaches beyond the run's field on every side.
    rotation_deg, scale, shift_mm
        The scan's grid against the camera: rotation, scale error (the step really is
        ``step_um * scale`` on the painting) and shift of its centre (x right, y up, mm).
    abundance : (R + 1, E) array, optional
        Counts per dwell per area and element (default drawn from ``seed``).
    within_area : float
        What the registration does not model: each element's abundance varies inside every area by
        a smooth random factor of up to ``1 +- within_area`` (over 2-6 mm), so composition no
        longer follows the colour areas exactly. The truth's ``abundance`` stays the areas' nominal
        values (the area means are then off by the factor's mean over the area).
    spot_shape : str
        ``"gaussian"`` (FWHM ``spot_um``) or ``"disc"`` (a flat-topped spot of diameter ``spot_um``,
        as a polycapillary's is nearer to; the registration assumes a Gaussian).
    line_jitter_px : float
        Standard deviation (map pixels) of each scan line's shift along x (a scanner's stage
        backlash), which no similarity holds.
    seed : int

    Returns
    -------
    ElementTruth
    """
    rng = np.random.default_rng(seed)
    labels = np.asarray(capture.regions)
    px = float(capture.spec.pixel_size_um)
    M, N = labels.shape
    R = int(labels.max())
    E = len(elements)
    if abundance is None:
        abundance = np.empty((R + 1, E))
        light = [bool(v) for v in capture.region_light]
        for r in range(R + 1):
            is_light = light[r - 1] if 1 <= r <= len(light) else False
            abundance[r, 0] = rng.uniform(3000, 6000) if is_light else rng.uniform(300, 1500)
            abundance[r, 1:] = rng.uniform(100, 2500, E - 1)
    abundance = np.asarray(abundance, float)
    # the abundance field beyond the run's field: the colour areas mirrored (as the scan sees paint
    # there too); padded far enough for the margin, the shift and the spot
    pad = int(math.ceil((margin_mm * 1000.0 + max(abs(shift_mm[0]), abs(shift_mm[1])) * 1000.0
                         + 3.0 * spot_um) / px * max(scale, 1.0) * 1.2)) + 8
    lab = np.pad(labels, pad, mode="symmetric")
    sigma = spot_sigma_px(spot_um, px)
    # the grid: map pixel (col, row) -> run pixel (col, row); the map covers the field and the margin
    f = step_um * scale / px
    W = int(math.ceil((N * px / 1000.0 + 2 * margin_mm) * 1000.0 / step_um))
    H = int(math.ceil((M * px / 1000.0 + 2 * margin_mm) * 1000.0 / step_um))
    centre_run = np.array([(N - 1) / 2 + shift_mm[0] * 1000.0 / px, (M - 1) / 2 - shift_mm[1] * 1000.0 / px])
    rot = similarity(f, rotation_deg, 0.0, 0.0)
    c_map = np.array([(W - 1) / 2, (H - 1) / 2])
    t = centre_run - rot[:2, :2] @ c_map
    map_to_run = similarity(f, rotation_deg, float(t[0]), float(t[1]))
    rr, cc = np.mgrid[0:H, 0:W]
    x = map_to_run[0, 0] * cc + map_to_run[0, 1] * rr + map_to_run[0, 2] + pad
    y = map_to_run[1, 0] * cc + map_to_run[1, 1] * rr + map_to_run[1, 2] + pad
    if line_jitter_px:
        jitter = rng.normal(0.0, line_jitter_px, H)[:, None]
        x = x + jitter * map_to_run[0, 0]
        y = y + jitter * map_to_run[1, 0]
    if spot_shape not in ("gaussian", "disc"):
        raise ValueError(f"spot_shape must be 'gaussian' or 'disc'; got {spot_shape!r}")
    data = np.empty((E, H, W))
    for e in range(E):
        field = abundance[lab, e].astype(np.float32)
        if within_area:
            vary = _smooth_field(rng, lab.shape, px)
            field *= (1.0 + within_area * vary).astype(np.float32)
        if spot_shape == "gaussian":
            blurred = cv2.GaussianBlur(field, (0, 0), sigma, borderType=cv2.BORDER_REFLECT)
        else:
            r = spot_um / 2.0 / px
            k = int(math.ceil(r))
            yy, xx = np.mgrid[-k:k + 1, -k:k + 1]
            disc = (np.hypot(xx, yy) <= r).astype(np.float32)
            blurred = cv2.filter2D(field, -1, disc / disc.sum(), borderType=cv2.BORDER_REFLECT)
        lam = ndimage.map_coordinates(blurred, [y, x], order=1, mode="nearest")
        data[e] = rng.poisson(np.maximum(lam, 0)).astype(float)
    maps = ElementMaps(list(elements), data, float(step_um), [f"{n}.tif" for n in elements])
    return ElementTruth(maps, map_to_run, abundance)


def _smooth_field(rng, shape, px) -> np.ndarray:
    """A smooth random field in -1..1 varying over 2-6 mm (a few random waves)."""
    M, N = shape
    yy, xx = np.mgrid[0:M, 0:N].astype(np.float32) * (px / 1000.0)
    out = np.zeros(shape, np.float32)
    for _ in range(4):
        period = rng.uniform(2.0, 6.0)
        theta = rng.uniform(0, np.pi)
        phase = rng.uniform(0, 2 * np.pi)
        out += np.cos(2 * np.pi / period * (xx * np.cos(theta) + yy * np.sin(theta)) + phase)
    return out / max(float(np.abs(out).max()), 1e-6)
