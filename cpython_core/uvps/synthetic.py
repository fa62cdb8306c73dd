"""Synthetic UV-fluorescence photometric-stereo captures of a painting detail, with ground truth.

A capture is K 16-bit images of one painted area lit by K near point lamps. The scene imitates the
details of Pedernal shown in the paper (Figs. 2 and 3): 5 to 8 large colour areas with their own
fluorescence colour (light, lead-white-rich areas bright; dark areas weak), a canvas weave, brush
stroke ridges, flat whitish primer spots and metal-soap protrusions (domes 30-600 um wide, some with
a central "caldera"), crowded in the light areas and rare in the dark ones.

Frames and units follow ``docs/architecture.md``: x toward increasing column, y up (toward
decreasing row), z toward the camera; heights and widths in um, light positions in mm from the
image centre. The image model is the near-light Lambertian model of the paper, Eq. (1), with
inverse-square fall-off and attached shadows::

    I_k(x) = albedo(x) * E_k * (|L_k| / |L_k - X|)^2 * max(0, n(x) . (L_k - X) / |L_k - X|)

Ground truth (height, normals, albedo, colour areas, the protrusion list) is returned beside the
images and written to ``truth/`` by :func:`write_capture`; the pipeline never reads it.
"""
from __future__ import annotations

import csv
import dataclasses
import logging
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Optional

import numpy as np
import tifffile
from scipy import ndimage

from .errors import UVPSInputError
from .outputs import Progress, atomic_output_dir, report, write_json_atomic

logger = logging.getLogger(__name__)

#: Fluorescence colours (linear RGB, relative) of the colour areas. Light (lead-white-rich)
#: areas fluoresce brightly, dark areas weakly (paper, Sec. "Detection of protrusions").
LIGHT_AREA_COLOURS = {
    "beige": (0.80, 0.73, 0.58),
    "light green": (0.58, 0.76, 0.52),
    "light red": (0.84, 0.55, 0.49),
    "yellow": (0.86, 0.80, 0.42),
    "yellow green": (0.70, 0.80, 0.40),
}
DARK_AREA_COLOURS = {
    "dark green": (0.15, 0.27, 0.15),
    "dark red": (0.29, 0.12, 0.10),
    "orange": (0.44, 0.26, 0.10),
}
#: Whitish-yellow fluorescence of lead-soap protrusions and bluish-white of the chalk primer.
PROTRUSION_COLOUR = (1.0, 0.95, 0.76)
PRIMER_COLOUR = (0.90, 0.92, 0.97)
#: Rec. 709 luminance weights, used for grey captures.
LUMINANCE = np.array([0.2126, 0.7152, 0.0722])

_UM2_PER_CM2 = 1e8


@dataclass
class SyntheticSpec:
    """What to synthesise. Every option has a physically sensible default (a 18 x 24 mm detail).

    Densities are per cm^2 of the field; widths and heights in um; distances in mm.
    ``n_ridges`` / ``n_primer_spots`` = None means 4 ridges and 3 primer spots per cm^2.
    Each image's irradiance at the centre is 1 +- ``intensity_jitter`` (as if the exposure were reset
    per image); ``fixed_exposure`` instead models one lamp at one exposure: that drift times
    (median distance / distance)^2, so a lamp at 500 mm gives an image 4x darker than at 250 mm.
    """

    shape: tuple = (1200, 1600)
    n_lights: int = 12
    pixel_size_um: float = 15.0
    rgb: bool = True
    elevation_deg: tuple = (20.0, 60.0)
    distance_mm: tuple = (250.0, 500.0)
    intensity_jitter: float = 0.1
    fixed_exposure: bool = False
    n_regions: Optional[int] = None
    protrusion_density_light: float = 45.0
    protrusion_density_dark: float = 5.0
    width_um: tuple = (30.0, 600.0)
    weak_fraction: float = 0.2
    crater_fraction: float = 0.3
    n_ridges: Optional[int] = None
    n_primer_spots: Optional[int] = None
    weave_period_um: float = 450.0
    weave_amplitude_um: float = 3.0
    bow_um: float = 15.0
    exposure_fraction: float = 0.75
    full_well_e: float = 60000.0
    read_noise: float = 4.0
    noise: bool = True
    seed: int = 0


@dataclass
class SyntheticCapture:
    """A synthetic capture and its ground truth (see the module docstring for the frames).

    ``protrusions`` holds equal-length numpy columns: ``id``, ``x_px`` (column), ``y_px`` (row),
    ``width_um`` (equivalent-circle diameter of the footprint), ``height_um`` (peak above the
    surrounding surface), ``crater``, ``weak``, ``region``, ``aspect``, ``angle_deg``.
    """

    images: np.ndarray
    light_positions_mm: np.ndarray
    intensities: np.ndarray
    height_um: np.ndarray
    normals: np.ndarray
    albedo: np.ndarray
    regions: np.ndarray
    region_names: list
    region_light: list
    protrusions: dict
    spec: SyntheticSpec
    exposure: float = 1.0
    gain: float = 1.0


# --------------------------------------------------------------------------------------------
# Geometry and rendering
# --------------------------------------------------------------------------------------------


def normals_from_height(height_um, *, pixel_size_um) -> np.ndarray:
    """Unit normals of a height map by central differences.

    Parameters
    ----------
    height_um : (M, N) array
        Height toward the camera in um.
    pixel_size_um : float
        Pixel size in um.

    Returns
    -------
    normals : (M, N, 3) float32
        ``n = (-p, -q, 1) / sqrt(1 + p^2 + q^2)`` with ``p = dz/dx``, ``q = dz/dy`` (y up, so
        ``q = -dz/d(row) / pixel size``). One-sided differences on the border.
    """
    h = np.asarray(height_um, dtype=np.float64)
    if h.ndim != 2 or min(h.shape) < 2:
        raise UVPSInputError(f"height_um must be a 2-D array of at least 2 x 2; "
                             f"got shape {h.shape}")
    if not pixel_size_um > 0:
        raise UVPSInputError(f"pixel_size_um must be > 0; got {pixel_size_um}")
    return _normals64(h, float(pixel_size_um)).astype(np.float32)


def _normals64(h, pixel_size_um):
    d_row, d_col = np.gradient(h, pixel_size_um)
    p = d_col
    q = -d_row                                   # y is up: rows grow downward
    norm = np.sqrt(1.0 + p * p + q * q)
    return np.stack([-p / norm, -q / norm, 1.0 / norm], axis=-1)


def pixel_centres_mm(shape, pixel_size_um):
    """World x (1, N) and y (M, 1) of the pixel centres in mm (architecture.md)."""
    m, n = shape
    px_mm = pixel_size_um / 1000.0
    x = ((np.arange(n) - (n - 1) / 2.0) * px_mm)[None, :]
    y = (((m - 1) / 2.0 - np.arange(m)) * px_mm)[:, None]
    return x, y


def _shading(normals, height_um, pixel_size_um, positions, directions, intensities):
    """Yield, per light, ``E_k * fall-off * max(0, n . l)`` as an (M, N) float64 array."""
    nx, ny, nz = (normals[..., i].astype(np.float64) for i in range(3))
    if directions is not None:
        for e, d in zip(intensities, directions):
            yield e * np.maximum(nx * d[0] + ny * d[1] + nz * d[2], 0.0)
        return
    x, y = pixel_centres_mm(height_um.shape, pixel_size_um)
    z = np.asarray(height_um, dtype=np.float64) / 1000.0
    for e, lk in zip(intensities, positions):
        dx = lk[0] - x
        dy = lk[1] - y
        dz = lk[2] - z
        dist2 = dx * dx + dy * dy + dz * dz
        inv = 1.0 / np.sqrt(dist2)
        cos = (nx * dx + ny * dy + nz * dz) * inv
        yield e * (float(lk @ lk) / dist2) * np.maximum(cos, 0.0)


def render_images(height_um, albedo, *, pixel_size_um, light_positions_mm=None,
                  light_directions=None, intensities=None, rng=None, noise=True, gain=1.0,
                  read_noise=4.0, exposure=None, dtype=np.uint16) -> np.ndarray:
    """Render a photometric-stereo stack of a height map under near or far lights.

    Parameters
    ----------
    height_um : (M, N) array
        Height toward the camera in um.
    albedo : (M, N) or (M, N, C) array
        Fluorescence albedo (linear).
    pixel_size_um : float
        Pixel size in um.
    light_positions_mm : (K, 3) array, optional
        Near point lights, mm from the image centre in the world frame.
    light_directions : (K, 3) array, optional
        Far lights: unit vectors toward the lights (normalised here). Exactly one of the two.
    intensities : (K,) array, optional
        ``E_k``, the irradiance at the image centre (default 1).
    rng : numpy Generator or int, optional
        Noise source (an int seeds a new Generator).
    noise : bool
        Add photon noise (Poisson, via ``gain`` counts per electron) and Gaussian read noise
        (``read_noise`` counts).
    exposure : float, optional
        Counts per unit of ``albedo * E``. None: 1 when ``dtype`` is None or floating, else
        chosen so that the brightest noise-free sample is 75 % of the dtype's full scale.
    dtype : numpy dtype or None
        Integer: rounded and clipped to the dtype range. None: float64 (exact model values when
        ``noise`` is False and ``exposure`` is 1).

    Returns
    -------
    images : (K, M, N) or (K, M, N, C) array

    Notes
    -----
    Image model of the paper, Eq. (1), with near lights (architecture.md)::

        I_k = albedo * E_k * (|L_k| / |L_k - X|)^2 * max(0, n . (L_k - X) / |L_k - X|)

    X is the surface point (pixel centre and height, in mm). Normals come from
    :func:`normals_from_height`. Far lights: ``I_k = albedo * E_k * max(0, n . l_k)``. Photon
    noise uses the Gaussian approximation of the Poisson law above 50 electrons (exact Poisson
    below); it matches mean and variance and is ~5x faster than ``Generator.poisson``.

    Examples
    --------
    A flat canvas under one lamp 300 mm away at 35 deg elevation: the centre pixel is
    ``albedo * E * sin(35 deg)``.

    >>> import numpy as np
    >>> el = np.radians(35.0)
    >>> lamp = 300.0 * np.array([[np.cos(el), 0.0, np.sin(el)]])
    >>> img = render_images(np.zeros((5, 5)), np.full((5, 5), 0.5), pixel_size_um=15.0,
    ...                     light_positions_mm=lamp, noise=False, dtype=None)
    >>> bool(np.isclose(img[0, 2, 2], 0.5 * np.sin(el)))
    True
    """
    h = np.asarray(height_um, dtype=np.float64)
    if h.ndim != 2:
        raise UVPSInputError(f"height_um must be (M, N); got shape {h.shape}")
    alb = np.asarray(albedo, dtype=np.float64)
    if alb.shape[:2] != h.shape or alb.ndim not in (2, 3):
        raise UVPSInputError(f"albedo must be (M, N) or (M, N, C) with (M, N) = {h.shape}; "
                             f"got shape {alb.shape}")
    if (light_positions_mm is None) == (light_directions is None):
        raise UVPSInputError("give exactly one of light_positions_mm and light_directions")
    positions = directions = None
    if light_positions_mm is not None:
        positions = np.asarray(light_positions_mm, dtype=np.float64)
        if positions.ndim != 2 or positions.shape[1] != 3:
            raise UVPSInputError(f"light_positions_mm must be (K, 3); got shape {positions.shape}")
        k = positions.shape[0]
    else:
        directions = np.asarray(light_directions, dtype=np.float64)
        if directions.ndim != 2 or directions.shape[1] != 3:
            raise UVPSInputError(f"light_directions must be (K, 3); got shape {directions.shape}")
        norms = np.linalg.norm(directions, axis=1, keepdims=True)
        if np.any(norms == 0):
            raise UVPSInputError("light_directions contains a zero vector")
        directions = directions / norms
        k = directions.shape[0]
    e = np.ones(k) if intensities is None else np.asarray(intensities, dtype=np.float64)
    if e.shape != (k,):
        raise UVPSInputError(f"intensities must be ({k},); got shape {e.shape}")
    integer = dtype is not None and np.issubdtype(np.dtype(dtype), np.integer)
    if h.ndim != 2 or min(h.shape) < 2 or not pixel_size_um > 0:
        raise UVPSInputError(f"height_um must be (M, N) with M, N >= 2 and pixel_size_um > 0; "
                             f"got shape {h.shape}, pixel_size_um={pixel_size_um}")
    normals = _normals64(h, float(pixel_size_um))

    def shading():
        return _shading(normals, h, pixel_size_um, positions, directions, e)

    if exposure is None:
        if integer:
            peak = max(float(np.max(s * (alb if alb.ndim == 2 else alb.max(axis=2))))
                       for s in shading())
            exposure = 0.75 * np.iinfo(dtype).max / peak if peak > 0 else 1.0
        else:
            exposure = 1.0
    rng = np.random.default_rng(rng)
    out = np.empty((k,) + alb.shape, dtype=np.float64 if dtype is None else dtype)
    # float64 for exact model values (dtype None), float32 is plenty below 16-bit quantisation.
    work = np.float64 if dtype is None or np.dtype(dtype) == np.float64 else np.float32
    alb_w = alb.astype(work)
    for i, s in enumerate(shading()):
        s = (exposure * s).astype(work)
        counts = alb_w * (s if alb.ndim == 2 else s[..., None])
        if noise:
            counts = _add_noise(counts, rng, gain=gain, read_noise=read_noise)
        if integer:
            info = np.iinfo(dtype)
            counts = np.clip(np.rint(counts), info.min, info.max)
        out[i] = counts
    return out


def _add_noise(counts, rng, *, gain, read_noise):
    """Photon (Poisson in electrons) and Gaussian read noise, in counts."""
    noisy = rng.standard_normal(counts.shape, dtype=counts.dtype)
    noisy *= np.sqrt(gain * counts + read_noise * read_noise).astype(counts.dtype)
    noisy += counts
    low = counts < 50.0 * gain
    if low.any():
        noisy[low] = (rng.poisson(counts[low] / gain) * gain
                      + read_noise * rng.standard_normal(int(low.sum())))
    return noisy


def light_positions(rng, *, n_lights, elevation_deg, distance_mm) -> np.ndarray:
    """Lamp positions (K, 3) in mm: azimuths evenly spread with jitter, elevation and distance
    uniform in their ranges. Azimuth counted from +x toward +y."""
    step = 2 * np.pi / n_lights
    az = rng.uniform(0, 2 * np.pi) + step * np.arange(n_lights)
    az = az + rng.uniform(-0.25, 0.25, n_lights) * step
    el = np.radians(rng.uniform(*elevation_deg, n_lights))
    d = rng.uniform(*distance_mm, n_lights)
    return np.stack([d * np.cos(el) * np.cos(az), d * np.cos(el) * np.sin(az),
                     d * np.sin(el)], axis=1)


# --------------------------------------------------------------------------------------------
# Scene
# --------------------------------------------------------------------------------------------


def _smooth_warp(rng, shape, amplitude, n_waves=4):
    """A smooth random displacement (pixels): a sum of a few long plane waves."""
    m, n = shape
    r = np.arange(m)[:, None]
    c = np.arange(n)[None, :]
    out = np.zeros(shape)
    size = max(m, n)
    for _ in range(n_waves):
        wavelength = rng.uniform(0.25, 0.8) * size
        theta = rng.uniform(0, np.pi)
        k = 2 * np.pi / wavelength
        out += np.sin(k * (np.cos(theta) * c + np.sin(theta) * r) + rng.uniform(0, 2 * np.pi))
    return out * amplitude / math.sqrt(n_waves)


def _colour_areas(rng, shape, n_regions):
    """Irregular colour areas: Voronoi cells of random seeds in warped coordinates."""
    m, n = shape
    seeds = []
    min_d = 0.6 * math.sqrt(m * n / n_regions)
    for _ in range(2000):
        if len(seeds) == n_regions:
            break
        s = rng.uniform([0.05 * m, 0.05 * n], [0.95 * m, 0.95 * n])
        if all(np.hypot(*(s - t)) > min_d for t in seeds):
            seeds.append(s)
        else:
            min_d *= 0.995
    amp = 0.08 * min(m, n)
    rr = np.arange(m, dtype=np.float32)[:, None] + _smooth_warp(rng, shape, amp)
    cc = np.arange(n, dtype=np.float32)[None, :] + _smooth_warp(rng, shape, amp)
    best = np.full(shape, np.inf, dtype=np.float32)
    labels = np.zeros(shape, dtype=np.int32)
    for i, (sr, sc) in enumerate(seeds):
        d = (rr - sr) ** 2 + (cc - sc) ** 2
        closer = d < best
        best[closer] = d[closer]
        labels[closer] = i + 1
    # Relabel 1..R in case a warped cell vanished.
    present = np.unique(labels)
    lut = np.zeros(labels.max() + 1, dtype=np.int32)
    lut[present] = np.arange(1, len(present) + 1)
    return lut[labels]


def _region_palette(rng, n_regions):
    """Names, light flags and colours for R areas (2-5 light, 1-3 dark)."""
    n_dark = int(rng.integers(max(1, n_regions - len(LIGHT_AREA_COLOURS)),
                              min(len(DARK_AREA_COLOURS), n_regions - 1) + 1))
    light = list(rng.permutation(list(LIGHT_AREA_COLOURS)))[: n_regions - n_dark]
    dark = list(rng.permutation(list(DARK_AREA_COLOURS)))[:n_dark]
    names = light + dark
    order = rng.permutation(n_regions)
    names = [str(names[i]) for i in order]
    is_light = [nm in LIGHT_AREA_COLOURS for nm in names]
    colours = np.array([{**LIGHT_AREA_COLOURS, **DARK_AREA_COLOURS}[nm] for nm in names])
    return names, is_light, colours


def _ridges(rng, shape, px, count, albedo_factor, occupied):
    """Brush-stroke ridges: curved, several mm long, 100-300 um wide, 5-20 um high.

    Distance to each stroke's centreline comes from ``scipy.ndimage.distance_transform_edt``
    (with the indices of the nearest centreline pixel, to taper the stroke ends).
    """
    m, n = shape
    layer = np.zeros(shape)
    base_angle = rng.uniform(0, np.pi)
    for _ in range(count):
        length = rng.uniform(3000.0, 10000.0) / px           # pixels
        width = rng.uniform(100.0, 300.0) / px
        h = rng.uniform(5.0, 20.0)
        angle = base_angle + rng.uniform(-0.5, 0.5)
        start = rng.uniform([0, 0], [m, n])
        direc = np.array([np.sin(angle), np.cos(angle)])
        end = start + length * direc
        bend = rng.uniform(-0.15, 0.15) * length
        ctrl = (start + end) / 2 + bend * np.array([-direc[1], direc[0]])
        t = np.linspace(0, 1, int(2 * length) + 2)[:, None]
        path = (1 - t) ** 2 * start + 2 * t * (1 - t) * ctrl + t ** 2 * end
        pad = int(width) + 2
        r0 = max(int(path[:, 0].min()) - pad, 0)
        r1 = min(int(path[:, 0].max()) + pad + 1, m)
        c0 = max(int(path[:, 1].min()) - pad, 0)
        c1 = min(int(path[:, 1].max()) + pad + 1, n)
        if r1 - r0 < 2 or c1 - c0 < 2:
            continue
        pr = np.rint(path[:, 0]).astype(int) - r0
        pc = np.rint(path[:, 1]).astype(int) - c0
        inside = (pr >= 0) & (pr < r1 - r0) & (pc >= 0) & (pc < c1 - c0)
        if not inside.any():
            continue
        line = np.ones((r1 - r0, c1 - c0), dtype=bool)
        tval = np.zeros(line.shape)
        line[pr[inside], pc[inside]] = False
        tval[pr[inside], pc[inside]] = t[inside, 0]
        dist, (ir, ic) = ndimage.distance_transform_edt(line, return_indices=True)
        half = width / 2
        prof = np.where(dist < half, 0.5 * (1 + np.cos(np.pi * dist / half)), 0.0)
        tn = tval[ir, ic]
        taper = np.clip(np.minimum(tn, 1 - tn) / 0.15, 0, 1)
        taper = taper * taper * (3 - 2 * taper)               # smoothstep
        shape_k = prof * taper
        layer[r0:r1, c0:c1] = np.maximum(layer[r0:r1, c0:c1], h * shape_k)
        albedo_factor[r0:r1, c0:c1] *= 1 + rng.uniform(-0.06, 0.04) * shape_k
    occupied |= layer > 1.0
    return layer


def _primer_spots(rng, shape, px, count, albedo, occupied):
    """Flat whitish primer spots (paint missing): albedo toward the primer colour, height 0 to
    3 um below the paint. Returns the height layer (<= 0)."""
    m, n = shape
    layer = np.zeros(shape)
    primer = np.array(PRIMER_COLOUR)[: albedo.shape[2]]
    for _ in range(count):
        w = rng.uniform(100.0, 400.0) / px
        aspect = rng.uniform(1.0, 1.6)
        a, b = w / 2 * math.sqrt(aspect), w / 2 / math.sqrt(aspect)
        phi = rng.uniform(0, np.pi)
        cr, cc = rng.uniform([a + 2, a + 2], [m - a - 2, n - a - 2])
        r0, r1 = int(cr - a - 2), int(cr + a + 3)
        c0, c1 = int(cc - a - 2), int(cc + a + 3)
        rows = np.arange(r0, r1)[:, None] - cr
        cols = np.arange(c0, c1)[None, :] - cc
        u = cols * np.cos(phi) + rows * np.sin(phi)
        v = -cols * np.sin(phi) + rows * np.cos(phi)
        theta = np.arctan2(v, u)
        wobble = 1 + sum(rng.uniform(-0.08, 0.08) * np.cos(j * theta + rng.uniform(0, 6.3))
                         for j in (2, 3, 5))
        rho = np.sqrt((u / a) ** 2 + (v / b) ** 2) / wobble
        wgt = np.clip((1 - rho) * a / 1.5, 0, 1)
        depth = rng.uniform(0.0, 3.0)
        layer[r0:r1, c0:c1] = np.minimum(layer[r0:r1, c0:c1], -depth * wgt)
        sub = albedo[r0:r1, c0:c1]
        sub[:] = sub * (1 - wgt[..., None]) + primer * rng.uniform(0.95, 1.05) * wgt[..., None]
        occupied[r0:r1, c0:c1] |= rho < 1.3
    return layer


def _protrusion_widths(rng, count, width_range):
    """Widths (um) skewed to 100-200 um: log-normal (median 150 um, sigma 0.45) truncated."""
    lo, hi = width_range
    median = min(max(150.0, lo), hi)
    out = np.empty(0)
    while out.size < count:
        w = rng.lognormal(math.log(median), 0.45, 2 * count + 10)
        out = np.concatenate([out, w[(w >= lo) & (w <= hi)]])
    return out[:count]


def _dome_profile(rho, gamma, crater):
    """Normalised dome height at elliptical radius rho (0 outside the footprint rho >= 1)."""
    f = np.where(rho < 1, np.clip(1 - rho * rho, 0, None) ** gamma, 0.0)
    if crater is not None:
        depth, rc = crater
        inner = np.clip(1 - (rho / rc) ** 2, 0, None) ** 2
        f = f - depth * inner
    return f


def _protrusions(rng, spec, labels, region_light, px, height, albedo, occupied):
    """Place non-overlapping domes per colour area and add them to height and albedo."""
    m, n = labels.shape
    rows, cols, widths, heights, craters, weaks, regs, aspects, angles = ([] for _ in range(9))
    colour = np.array(PROTRUSION_COLOUR)[: albedo.shape[2]]
    flat = labels.ravel()
    for reg in range(1, labels.max() + 1):
        idx = np.flatnonzero(flat == reg)
        area_cm2 = idx.size * px * px / _UM2_PER_CM2
        density = (spec.protrusion_density_light if region_light[reg - 1]
                   else spec.protrusion_density_dark)
        count = int(rng.poisson(density * area_cm2))
        if count == 0:
            continue
        for w_um in np.sort(_protrusion_widths(rng, count, spec.width_um))[::-1]:
            aspect = rng.uniform(1.0, 1.35)
            a = w_um / 2 * math.sqrt(aspect) / px                # semi-axes in pixels, area of
            b = w_um / 2 / math.sqrt(aspect) / px                # a circle of diameter w
            margin = int(math.ceil(a)) + 2
            for _ in range(40):
                j = idx[rng.integers(idx.size)]
                cr = j // n + rng.uniform(-0.5, 0.5)
                cc = j % n + rng.uniform(-0.5, 0.5)
                if not (margin <= cr < m - margin and margin <= cc < n - margin):
                    continue
                r0, r1 = int(cr) - margin, int(cr) + margin + 1
                c0, c1 = int(cc) - margin, int(cc) + margin + 1
                rr = np.arange(r0, r1)[:, None] - cr
                ccs = np.arange(c0, c1)[None, :] - cc
                if np.any(occupied[r0:r1, c0:c1] & (rr ** 2 + ccs ** 2 <= (a + 1.5) ** 2)):
                    continue
                break
            else:
                continue
            phi = rng.uniform(0, np.pi)
            u = ccs * np.cos(phi) + rr * np.sin(phi)
            v = -ccs * np.sin(phi) + rr * np.cos(phi)
            rho = np.sqrt((u / a) ** 2 + (v / b) ** 2)
            h_dome = rng.uniform(0.15, 0.35) * w_um
            gamma = rng.uniform(1.0, 1.6)
            has_crater = rng.random() < spec.crater_fraction
            crater = (rng.uniform(0.3, 0.6), rng.uniform(0.3, 0.5)) if has_crater else None
            fine = np.linspace(0, 1, 2001)
            peak = float(_dome_profile(fine, gamma, crater).max())
            height[r0:r1, c0:c1] += h_dome * _dome_profile(rho, gamma, crater)
            weak = rng.random() < spec.weak_fraction
            sub = albedo[r0:r1, c0:c1]
            if weak:
                col = albedo[int(cr), int(cc)] * rng.uniform(1.05, 1.2)
            else:
                col = colour * rng.uniform(0.92, 1.05)
            wgt = np.clip((1 - rho) * a, 0, 1)[..., None]
            sub[:] = sub * (1 - wgt) + col * wgt
            occupied[r0:r1, c0:c1] |= rr ** 2 + ccs ** 2 <= (a + 1.0) ** 2
            rows.append(cr)
            cols.append(cc)
            widths.append(w_um)
            heights.append(h_dome * peak)
            craters.append(has_crater)
            weaks.append(weak)
            regs.append(reg)
            aspects.append(aspect)
            angles.append(math.degrees(phi))
    order = np.lexsort((np.asarray(cols), np.asarray(rows))) if rows else np.zeros(0, int)
    cols_ = {
        "x_px": np.asarray(cols, dtype=np.float64), "y_px": np.asarray(rows, dtype=np.float64),
        "width_um": np.asarray(widths, dtype=np.float64),
        "height_um": np.asarray(heights, dtype=np.float64),
        "crater": np.asarray(craters, dtype=bool), "weak": np.asarray(weaks, dtype=bool),
        "region": np.asarray(regs, dtype=np.int32), "aspect": np.asarray(aspects),
        "angle_deg": np.asarray(angles),
    }
    out = {"id": np.arange(1, len(rows) + 1, dtype=np.int32)}
    out.update({k: v[order] for k, v in cols_.items()})
    return out


def _validate(spec: SyntheticSpec) -> None:
    shape = tuple(spec.shape)
    if len(shape) != 2 or any(int(s) != s or s < 16 for s in shape):
        raise UVPSInputError(f"shape must be two integers >= 16 (rows, cols); got {spec.shape}")
    if int(spec.n_lights) != spec.n_lights or spec.n_lights < 3:
        raise UVPSInputError(f"n_lights must be an integer >= 3; got {spec.n_lights}")
    if not spec.pixel_size_um > 0:
        raise UVPSInputError(f"pixel_size_um must be > 0; got {spec.pixel_size_um}")
    for name, lo_min, hi_max in (("elevation_deg", 0.0, 90.0), ("distance_mm", 0.0, np.inf),
                                 ("width_um", 0.0, np.inf)):
        rng_ = tuple(getattr(spec, name))
        if len(rng_) != 2 or not (lo_min < rng_[0] <= rng_[1] <= hi_max):
            raise UVPSInputError(f"{name} must be (low, high) with {lo_min} < low <= high <= "
                                 f"{hi_max}; got {getattr(spec, name)}")
    for name in ("intensity_jitter", "weak_fraction", "crater_fraction"):
        if not 0 <= getattr(spec, name) < 1:
            raise UVPSInputError(f"{name} must be in [0, 1); got {getattr(spec, name)}")
    if not 0 < spec.exposure_fraction <= 1:
        raise UVPSInputError(f"exposure_fraction must be in (0, 1]; got {spec.exposure_fraction}")
    if spec.n_regions is not None and not 2 <= spec.n_regions <= 8:
        raise UVPSInputError(f"n_regions must be None or 2..8; got {spec.n_regions}")
    for name in ("protrusion_density_light", "protrusion_density_dark", "weave_amplitude_um",
                 "bow_um", "read_noise"):
        if getattr(spec, name) < 0:
            raise UVPSInputError(f"{name} must be >= 0; got {getattr(spec, name)}")
    if not spec.weave_period_um > 0 or not spec.full_well_e > 0:
        raise UVPSInputError("weave_period_um and full_well_e must be > 0")


def make_capture(spec: Optional[SyntheticSpec] = None, *, progress: Progress = None,
                 **overrides) -> SyntheticCapture:
    """Synthesise a UV photometric-stereo capture of a painting detail with ground truth.

    Parameters
    ----------
    spec : SyntheticSpec, optional
        What to make (defaults: 1200 x 1600 pixels of 15 um, 12 lights, RGB).
    progress : callable, optional
        ``progress(fraction, message)``.
    **overrides
        Fields of :class:`SyntheticSpec` replacing those of ``spec``, e.g. ``shape=(240, 320)``.

    Returns
    -------
    SyntheticCapture

    Notes
    -----
    Height = canvas bow (a quadratic of peak-to-valley ``bow_um``) + plain weave
    (``A sin(2 pi u / P) sin(2 pi v / P)`` in slightly rotated axes) + brush ridges - primer spot
    depressions + protrusion domes ``H (1 - rho^2)^gamma`` (rho the elliptical radius, minus a
    central crater for ``crater_fraction`` of them); the median is then set to 0. Protrusions are
    placed largest first, as a Poisson number per area (densities per cm^2 as in the paper,
    Fig. 4), rejecting any placement that overlaps another protrusion, a ridge or a primer spot.
    The exposure puts the brightest noise-free sample at ``exposure_fraction`` of 65535; noise is
    photon noise with ``gain = 65535 / full_well_e`` counts per electron plus read noise.
    Cost: about 4 s for the default 1200 x 1600 x 12 RGB capture, 0.1 s for 240 x 320 x 8.

    Examples
    --------
    >>> cap = make_capture(shape=(240, 320), n_lights=8, seed=1)
    >>> cap.images.shape, cap.images.dtype
    ((8, 240, 320, 3), dtype('uint16'))
    >>> sorted(cap.protrusions)[:3]
    ['angle_deg', 'aspect', 'crater']
    """
    spec = dataclasses.replace(spec or SyntheticSpec(), **_checked_overrides(overrides))
    spec.shape = tuple(int(s) for s in spec.shape)
    _validate(spec)
    rng = np.random.default_rng(spec.seed)
    m, n = spec.shape
    px = float(spec.pixel_size_um)
    area_cm2 = m * n * px * px / _UM2_PER_CM2
    report(progress, 0.0, "colour areas")

    n_regions = spec.n_regions or int(rng.integers(5, 9))
    labels = _colour_areas(rng, (m, n), n_regions)
    n_regions = int(labels.max())
    names, is_light, colours = _region_palette(rng, n_regions)
    albedo = colours[labels - 1]
    albedo = ndimage.gaussian_filter(albedo, sigma=(1.2, 1.2, 0))
    texture = (1 + 0.05 * _normalised(ndimage.gaussian_filter(rng.standard_normal((m, n)), 12))
               + 0.015 * _normalised(ndimage.gaussian_filter(rng.standard_normal((m, n)), 1.0)))
    albedo *= texture[..., None]

    report(progress, 0.1, "surface")
    x, y = pixel_centres_mm((m, n), px)
    xu, yu = x * 1000.0, y * 1000.0
    theta = rng.uniform(-0.05, 0.05)
    u = xu * math.cos(theta) + yu * math.sin(theta)
    v = -xu * math.sin(theta) + yu * math.cos(theta)
    k = 2 * np.pi / spec.weave_period_um
    height = spec.weave_amplitude_um * np.sin(k * u) * np.sin(k * v)
    xn, yn = x / max(abs(x).max(), 1e-9), y / max(abs(y).max(), 1e-9)
    bow = -(rng.uniform(0.5, 1) * xn ** 2 + rng.uniform(0.5, 1) * yn ** 2
            + rng.uniform(-0.3, 0.3) * xn * yn)
    height = height + spec.bow_um * (bow - bow.min()) / max(np.ptp(bow), 1e-12)

    occupied = np.zeros((m, n), dtype=bool)
    factor = np.ones((m, n))
    n_ridges = round(4 * area_cm2) if spec.n_ridges is None else int(spec.n_ridges)
    height += _ridges(rng, (m, n), px, n_ridges, factor, occupied)
    albedo *= factor[..., None]
    n_spots = round(3 * area_cm2) if spec.n_primer_spots is None else int(spec.n_primer_spots)
    height += _primer_spots(rng, (m, n), px, n_spots, albedo, occupied)

    report(progress, 0.3, "protrusions")
    prot = _protrusions(rng, spec, labels, is_light, px, height, albedo, occupied)
    height -= np.median(height)
    if not spec.rgb:
        albedo = albedo @ LUMINANCE
    albedo = albedo.astype(np.float32)
    height32 = height.astype(np.float32)
    normals = normals_from_height(height32, pixel_size_um=px)

    report(progress, 0.4, "lights")
    positions = light_positions(rng, n_lights=spec.n_lights, elevation_deg=spec.elevation_deg,
                                distance_mm=spec.distance_mm)
    drift = 1 + rng.uniform(-spec.intensity_jitter, spec.intensity_jitter, spec.n_lights)
    if spec.fixed_exposure:
        # one lamp moved around at one exposure: the irradiance at the centre falls as 1/distance^2
        d = np.linalg.norm(positions, axis=1)
        intensities = drift * (np.median(d) / d) ** 2
    else:
        intensities = drift   # as if the exposure were reset for every image
    amax = albedo if albedo.ndim == 2 else albedo.max(axis=2)
    peak = max(float(np.max(s * amax)) for s in
               _shading(normals, height32, px, positions, None, intensities))
    exposure = spec.exposure_fraction * 65535.0 / peak
    gain = 65535.0 / spec.full_well_e
    report(progress, 0.5, "rendering")
    images = render_images(height32, albedo, pixel_size_um=px, light_positions_mm=positions,
                           intensities=intensities, rng=rng, noise=spec.noise, gain=gain,
                           read_noise=spec.read_noise, exposure=exposure, dtype=np.uint16)
    logger.info("synthetic capture %dx%d, %d lights, %d areas, %d protrusions, %d ridges, "
                "%d primer spots", m, n, spec.n_lights, n_regions, prot["id"].size, n_ridges,
                n_spots)
    report(progress, 1.0, "done")
    return SyntheticCapture(images=images, light_positions_mm=positions, intensities=intensities,
                            height_um=height32, normals=normals, albedo=albedo, regions=labels,
                            region_names=names, region_light=is_light, protrusions=prot,
                            spec=spec, exposure=float(exposure), gain=float(gain))


def _normalised(a):
    s = a.std()
    return (a - a.mean()) / s if s > 0 else a * 0


def _checked_overrides(overrides):
    known = {f.name for f in dataclasses.fields(SyntheticSpec)}
    unknown = sorted(set(overrides) - known)
    if unknown:
        raise UVPSInputError(f"unknown SyntheticSpec option(s) {unknown}; expected some of "
                             f"{sorted(known)}")
    return overrides


# --------------------------------------------------------------------------------------------
# Writing
# --------------------------------------------------------------------------------------------


def write_capture(capture: SyntheticCapture, folder, *, truth: bool = True) -> list:
    """Write a capture as a folder of 16-bit TIFFs, light files and (optionally) ground truth.

    Parameters
    ----------
    capture : SyntheticCapture
    folder : path
        Created if missing (its parent must exist); files are moved in atomically.
    truth : bool
        Also write ``truth/``.

    Returns
    -------
    paths : list of Path
        Every file written, images first.

    Notes
    -----
    Images: ``uv_00.tif``... 16-bit RGB (interleaved, as a camera converter writes them) or grey,
    with XResolution = YResolution = 1 / pixel size (pixels per um) and an ImageJ description
    ``unit=micron`` so that ImageJ's calibration is right. ``lights_positions_mm.csv``
    (file,x_mm,y_mm,z_mm) and ``lights.lp`` (RTI format: K, then ``file x y z``, the unit
    direction from the image centre to each light). ``truth/``: ``height_um.tif``,
    ``normals.tif`` (3, M, N) CYX, ``albedo.tif``, ``regions.tif`` (labels, uint16 as ImageJ has
    no 32-bit integers), ``protrusions.csv`` (columns as ``uvps.measure``'s, plus ``weak``,
    ``aspect``, ``angle_deg``, ``region_name``), ``truth.json``. Truth TIFFs are ImageJ
    hyperstacks written by :func:`uvps.io.write_imagej_tiff`.
    """
    px = float(capture.spec.pixel_size_um)
    k = capture.images.shape[0]
    digits = max(2, len(str(k - 1)))
    names = [f"uv_{i:0{digits}d}.tif" for i in range(k)]
    folder = Path(folder)
    with atomic_output_dir(folder) as tmp:
        written = []
        for name, img in zip(names, capture.images):
            tifffile.imwrite(tmp / name, img, photometric="rgb" if img.ndim == 3 else "minisblack",
                             resolution=(1 / px, 1 / px), resolutionunit="NONE",
                             description="ImageJ=1.54f\nunit=micron\n", metadata=None)
            written.append(name)
        pos = capture.light_positions_mm
        with open(tmp / "lights_positions_mm.csv", "w", newline="", encoding="utf-8") as fh:
            wr = csv.writer(fh)
            wr.writerow(["file", "x_mm", "y_mm", "z_mm"])
            for name, p in zip(names, pos):
                wr.writerow([name] + [f"{v:.6f}" for v in p])
        directions = pos / np.linalg.norm(pos, axis=1, keepdims=True)
        with open(tmp / "lights.lp", "w", encoding="utf-8") as fh:
            fh.write(f"{k}\n")
            for name, d in zip(names, directions):
                fh.write(f"{name} {d[0]:.8f} {d[1]:.8f} {d[2]:.8f}\n")
        written += ["lights_positions_mm.csv", "lights.lp"]
        if truth:
            written += _write_truth(capture, tmp / "truth", names)
    return [folder / w for w in written]


def _write_truth(capture, folder, image_names):
    folder.mkdir()
    px = float(capture.spec.pixel_size_um)
    # Truth TIFFs are ImageJ hyperstacks through the shared writer (atomic, calibrated in um).
    from .io import write_imagej_tiff

    def imagej(name, data, axes, labels=None):
        write_imagej_tiff(folder / name, data, axes=axes, pixel_size_um=px, labels=labels)

    imagej("height_um.tif", capture.height_um.astype(np.float32), "YX")
    imagej("normals.tif", np.moveaxis(capture.normals, -1, 0).astype(np.float32), "CYX",
           ["nx", "ny", "nz"])
    alb = capture.albedo.astype(np.float32)
    if alb.ndim == 3:
        imagej("albedo.tif", np.moveaxis(alb, -1, 0), "CYX", ["R", "G", "B"])
    else:
        imagej("albedo.tif", alb, "YX")
    imagej("regions.tif", capture.regions.astype(np.int32), "YX")
    # Same leading columns as uvps.measure's protrusions.csv, so `compare` takes it as is.
    prot = dict(capture.protrusions)
    prot["area_um2"] = np.pi * prot["width_um"] ** 2 / 4
    columns = ["id", "x_px", "y_px", "width_um", "area_um2", "height_um", "crater", "region",
               "weak", "aspect", "angle_deg"]
    with open(folder / "protrusions.csv", "w", newline="", encoding="utf-8") as fh:
        wr = csv.writer(fh)
        wr.writerow(columns + ["region_name"])
        for i in range(prot["id"].size):
            row = []
            for c in columns:
                v = prot[c][i]
                row.append(int(v) if v.dtype.kind in "biu" else f"{float(v):.4f}")
            row.append(capture.region_names[int(prot["region"][i]) - 1])
            wr.writerow(row)
    spec = dataclasses.asdict(capture.spec)
    write_json_atomic(folder / "truth.json", {
        "schema_version": 1,
        "pixel_size_um": px,
        "image_shape": list(capture.height_um.shape),
        "files": image_names,
        "light_positions_mm": capture.light_positions_mm,
        "intensities": capture.intensities,
        "exposure": capture.exposure,
        "gain": capture.gain,
        "region_names": capture.region_names,
        "region_light": [bool(b) for b in capture.region_light],
        "n_protrusions": int(prot["id"].size),
        "spec": {key: list(val) if isinstance(val, tuple) else val for key, val in spec.items()},
        "frames": "x right, y up, z toward camera; positions in mm from the image centre; "
                  "heights in um (median 0); normals.tif channels nx, ny, nz",
    })
    return [f"truth/{f}" for f in ("height_um.tif", "normals.tif", "albedo.tif", "regions.tif",
                                    "protrusions.csv", "truth.json")]
