"""Rendering a height map under near point lamps (Eq. (1) of the paper), cast shadows, the lamps'
and lens's nuisances (black level, vignetting, beams, stray light, noise), the dark frame and the
grey card.

Part of :mod:`uvps.testing.synthetic`, which exposes every public name; import from there.
"""
from __future__ import annotations

import math
import zlib
from dataclasses import dataclass
from typing import Optional

import numpy as np

from ..errors import UVPSInputError
from ..core.irradiance import irradiance
from .synthetic_spec import Nuisances, SyntheticCapture


# --------------------------------------------------------------------------------------------
# Geometry and rendering
# --------------------------------------------------------------------------------------------


def normals_from_height(height_um, *, pixel_size_um) -> np.ndarray:
    """Unit normals of a height map by fourth-order central differences.

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
        ``q = -dz/d(row) / pixel size``). Fourth-order central differences, ``(-z[i+2] + 8 z[i+1]
        - 8 z[i-1] + z[i-2]) / 12``, two pixels in from the border; second-order ones (``np.gradient``)
        on the two outer rows and columns.

    Notes
    -----
    The normals are those of the continuous surface the height map samples. The plain central
    difference ``(z[i+1] - z[i-1]) / 2`` is the derivative of that surface smoothed over two pixels
    (frequency response ``sin(w) / w``): on a Gaussian bump 100 um wide at 15 um per pixel it makes
    the steep slopes 3.8 % shallow (median), and every height integrated from those normals came out
    ~2.5 % low against the height map, also with the true lamps (measured by
    ``scripts/analysis_lamp_elevation.py heights ROW SEED`` on such normals). The
    fourth-order difference (response ``(8 sin w - sin 2w) / 6w``) is within 0.25 % there (a test).
    """
    h = np.asarray(height_um, dtype=np.float64)
    if h.ndim != 2 or min(h.shape) < 2:
        raise UVPSInputError(f"height_um must be a 2-D array of at least 2 x 2; "
                             f"got shape {h.shape}")
    if not pixel_size_um > 0:
        raise UVPSInputError(f"pixel_size_um must be > 0; got {pixel_size_um}")
    return _normals64(h, float(pixel_size_um)).astype(np.float32)


def _derivative4(h, axis: int, spacing: float) -> np.ndarray:
    """d h / d axis by fourth-order central differences (second order on the two outer lines)."""
    d = np.gradient(h, spacing, axis=axis)
    if h.shape[axis] >= 5:
        z, dz = np.moveaxis(h, axis, 0), np.moveaxis(d, axis, 0)     # views: dz writes into d
        dz[2:-2] = (z[:-4] - 8.0 * z[1:-3] + 8.0 * z[3:-1] - z[4:]) / (12.0 * spacing)
    return d


def _normals64(h, pixel_size_um):
    d_row = _derivative4(h, 0, pixel_size_um)
    d_col = _derivative4(h, 1, pixel_size_um)
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


def _shading(normals, height_um, pixel_size_um, positions, directions, intensities, *,
             beam_axes=None, beam_exponent=0.0, shadowed=None):
    """Yield, per light, ``E_k * fall-off * max(0, n . l) [* beam] [* lit]`` as (M, N) float64
    (:func:`uvps.core.irradiance.irradiance`)."""
    x, y = pixel_centres_mm(height_um.shape, pixel_size_um)
    z = np.asarray(height_um, dtype=np.float64) / 1000.0
    return irradiance(normals, x, y, z, intensities=intensities, positions_mm=positions,
                      directions=directions, beam_axes=beam_axes, beam_exponent=beam_exponent,
                      shadowed=shadowed)


def shadow_masks(height_um, *, pixel_size_um, light_positions_mm=None, light_directions=None,
                 tile=128) -> np.ndarray:
    """Cast shadows of a relief: where the surface hides each lamp.

    Parameters
    ----------
    height_um : (M, N) array
        Height toward the camera in um.
    pixel_size_um : float
        Pixel size in um.
    light_positions_mm : (K, 3) array, optional
        Near point lights, mm from the image centre in the world frame.
    light_directions : (K, 3) array, optional
        Far lights: vectors toward the lights. Exactly one of the two.
    tile : int
        Side of the tiles (pixels) that share one marching direction.

    Returns
    -------
    shadowed : (K, M, N) bool
        True where the segment from the surface point to the lamp passes below the surface.

    Notes
    -----
    A horizon test: from every pixel, march in the image plane toward the foot of the lamp, one
    pixel per step along the major axis, the height interpolated linearly across the other axis,
    and compare the surface with the ray's height ``z + t * tan(elevation)`` (the elevation of
    the lamp seen from that pixel, exact for near lights). The march stops once the ray is above
    every height within reach. Within a ``tile`` x ``tile`` block the direction is the one from
    the block's centre (for a lamp 250 mm away the ray then wanders less than 0.2 px over a 40 px
    shadow); outside the image nothing occludes. Cost: about ``6 * K * M * N * T`` flops, T the
    longest shadow in pixels (a 150 um step under a lamp at 20 deg elevation: 28 px at 15 um).

    Examples
    --------
    A 100 um step (x > 0 high) under a lamp low on the +x side shades the foot of the step over
    ``100 um / tan(20 deg) = 275 um`` (18 px of 15 um):

    >>> import numpy as np
    >>> h = np.zeros((8, 80)); h[:, 40:] = 100.0
    >>> el = np.radians(20.0)
    >>> lamp = [[np.cos(el), 0.0, np.sin(el)]]
    >>> int(shadow_masks(h, pixel_size_um=15.0, light_directions=lamp)[0, 4].sum())
    18
    """
    h = np.asarray(height_um, dtype=np.float64)
    if h.ndim != 2 or min(h.shape) < 2 or not pixel_size_um > 0:
        raise UVPSInputError(f"height_um must be (M, N) with M, N >= 2 and pixel_size_um > 0; "
                             f"got shape {h.shape}, pixel_size_um={pixel_size_um}")
    if (light_positions_mm is None) == (light_directions is None):
        raise UVPSInputError("give exactly one of light_positions_mm and light_directions")
    far = light_directions is not None
    lamps = np.asarray(light_directions if far else light_positions_mm, dtype=np.float64)
    if lamps.ndim != 2 or lamps.shape[1] != 3:
        raise UVPSInputError(f"{'light_directions' if far else 'light_positions_mm'} must be "
                             f"(K, 3); got shape {lamps.shape}")
    if int(tile) != tile or tile < 8:
        raise UVPSInputError(f"tile must be an integer >= 8; got {tile}")
    return np.stack([_shadow_mask(h, float(pixel_size_um), lamp, far, int(tile))
                     for lamp in lamps])


def _shadow_mask(h, px, lamp, far, tile):
    """One lamp's cast shadow (M, N) bool; see :func:`shadow_masks`."""
    m, n = h.shape
    x, y = pixel_centres_mm((m, n), px)
    if far:
        horiz = math.hypot(lamp[0], lamp[1])
        tan = np.full((m, n), lamp[2] / horiz if horiz > 0 else np.inf)
    else:
        with np.errstate(divide="ignore"):
            tan = (lamp[2] - h / 1000.0) / np.hypot(lamp[0] - x, lamp[1] - y)
    out = np.zeros((m, n), dtype=bool)
    if np.all(tan <= 0):
        out[:] = True                                   # the lamp is below the canvas
        return out
    tan = np.clip(tan, 1e-6, None)
    hmin, hmax = float(h.min()), float(h.max())
    if hmax - hmin <= 0:
        return out
    # the farthest any pixel can be shaded from (in pixels): the global height range at the
    # lowest elevation, and never farther than the image
    reach = int(min(math.ceil((hmax - hmin) / (float(tan.min()) * px)) + 2, m + n))
    big = np.float32(-1e30)
    pad = np.full((m + 2 * reach, n + 2 * reach), big, dtype=np.float32)
    pad[reach:reach + m, reach:reach + n] = h
    horizon = _Horizon(pad, h.astype(np.float32), tan, reach, big,
                       np.float32(1e-4 * max(abs(hmin), abs(hmax)) + 1e-3), px, lamp, far)
    for r0 in range(0, m, tile):
        r1 = min(r0 + tile, m)
        for c0 in range(0, n, tile):
            c1 = min(c0 + tile, n)
            shaded = horizon.tile(r0, r1, c0, c1)
            if shaded is not None:
                out[r0:r1, c0:c1] = shaded
    return out


@dataclass
class _Horizon:
    """One lamp's horizon test over a height map: the heights padded by ``reach`` pixels of
    ``big`` (outside the image nothing occludes), float32 heights, the tangent of the lamp's
    elevation per pixel, the tolerance above the surface that counts as shaded, the pixel size
    and the lamp (a position, or a direction when ``far``)."""

    pad: np.ndarray
    h32: np.ndarray
    tan: np.ndarray
    reach: int
    big: np.float32
    tol: np.float32
    px: float
    lamp: np.ndarray
    far: bool

    def tile(self, r0, r1, c0, c1):
        """The shadow of the block ``[r0:r1, c0:c1]`` marching toward the lamp's foot from the
        block's centre, or None when nothing within reach can rise above the block."""
        m, n = self.h32.shape
        hz = self.h32[r0:r1, c0:c1]
        tz = self.tan[r0:r1, c0:c1]
        lo, tmin = float(hz.min()), float(tz.min())
        near = self.pad[r0:r1 + 2 * self.reach, c0:c1 + 2 * self.reach]
        high = float(near.max())
        lamp, px = self.lamp, self.px
        if self.far:
            ux, uy = lamp[0], lamp[1]
        else:
            row_c, col_c = (r0 + r1 - 1) / 2.0, (c0 + c1 - 1) / 2.0     # tile centre
            ux = lamp[0] - (col_c - (n - 1) / 2.0) * px / 1000.0
            uy = lamp[1] - ((m - 1) / 2.0 - row_c) * px / 1000.0
        norm = math.hypot(ux, uy)
        if norm == 0 or high <= lo:
            return None
        d_col, d_row = ux / norm, -uy / norm        # y up: rows grow downward
        major = max(abs(d_col), abs(d_row))
        step_um = px / major
        steps = min(int(math.ceil((high - lo) / (tmin * step_um))), self.reach - 1)
        if steps < 1:
            return None
        acc = self.march(r0, r1, c0, c1, (tz * step_um).astype(np.float32), d_row, d_col, steps)
        return acc > hz + self.tol

    def march(self, r0, r1, c0, c1, rise, d_row, d_col, steps):
        """The highest (surface - ray) over ``steps`` one-pixel steps along the major axis of
        ``(d_row, d_col)``, the height interpolated linearly across the other axis (float32
        buffers in place: this loop is the generator's cost with cast shadows)."""
        pad, reach = self.pad, self.reach
        major = max(abs(d_col), abs(d_row))
        hz = self.h32[r0:r1, c0:c1]
        ray = np.zeros_like(hz)
        acc = np.full_like(hz, self.big)
        buf = np.empty_like(hz)
        buf2 = np.empty_like(hz)
        for j in range(1, steps + 1):
            fr, fc = j * d_row / major, j * d_col / major
            if abs(d_col) >= abs(d_row):         # march along columns, rows in between
                k = math.floor(fr)
                w = fr - k
                dc = int(round(fc))
                a0 = (reach + r0 + k, reach + c0 + dc)
                a1 = (a0[0] + 1, a0[1])
            else:                                # march along rows, columns in between
                k = math.floor(fc)
                w = fc - k
                dr = int(round(fr))
                a0 = (reach + r0 + dr, reach + c0 + k)
                a1 = (a0[0], a0[1] + 1)
            s0 = pad[a0[0]:a0[0] + r1 - r0, a0[1]:a0[1] + c1 - c0]
            np.multiply(s0, np.float32(1.0 - w), out=buf)
            if w > 0:
                s1 = pad[a1[0]:a1[0] + r1 - r0, a1[1]:a1[1] + c1 - c0]
                np.multiply(s1, np.float32(w), out=buf2)
                buf += buf2
            ray += rise
            buf -= ray
            np.maximum(acc, buf, out=acc)
        return acc


def render_images(height_um, albedo, *, pixel_size_um, light_positions_mm=None,
                  light_directions=None, intensities=None, rng=None, noise=True, gain=1.0,
                  read_noise=4.0, exposure=None, dtype=np.uint16,
                  nuisances: Optional[Nuisances] = None) -> np.ndarray:
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
        chosen so that the brightest noise-free sample (black level aside) is 75 % of the
        dtype's full scale.
    dtype : numpy dtype or None
        Integer: rounded and clipped to the dtype range. None: float64 (exact model values when
        ``noise`` is False and ``exposure`` is 1).
    nuisances : Nuisances, optional
        Beams, cast shadows, vignetting, stray light and black level (see :class:`Nuisances`).
        If ``cast_shadows`` is set and ``shadowed`` is None, the masks are computed here and
        stored into it.

    Returns
    -------
    images : (K, M, N) or (K, M, N, C) array

    Notes
    -----
    Image model of the paper, Eq. (1), with near lights (architecture.md)::

        I_k = albedo * E_k * (|L_k| / |L_k - X|)^2 * max(0, n . (L_k - X) / |L_k - X|)

    X is the surface point (pixel centre and height, in mm). Normals come from
    :func:`normals_from_height`. Far lights: ``I_k = albedo * E_k * max(0, n . l_k)``. With
    ``nuisances``, in counts (``exposure`` as ``c``)::

        I_k = c * (albedo * direct_k * beam_k * lit_k * vignetting + stray) + noise + black

    with ``beam_k = max(0, a_k . (X - L_k) / |X - L_k|)^n`` and ``lit_k`` 0 in cast shadows.
    Photon
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
    h, alb, positions, directions, e = _checked_render_inputs(
        height_um, albedo, light_positions_mm, light_directions, intensities, pixel_size_um)
    k = e.shape[0]
    integer = dtype is not None and np.issubdtype(np.dtype(dtype), np.integer)
    nz = nuisances if nuisances is not None else Nuisances()
    _check_nuisances(nz, k, alb.shape, far=directions is not None)
    if nz.cast_shadows and nz.shadowed is None:
        nz.shadowed = shadow_masks(h, pixel_size_um=pixel_size_um, light_positions_mm=positions,
                                   light_directions=directions)
    normals = _normals64(h, float(pixel_size_um))

    def shading():
        return _shading(normals, h, pixel_size_um, positions, directions, e,
                        beam_axes=nz.beam_axes, beam_exponent=nz.beam_exponent,
                        shadowed=nz.shadowed if nz.cast_shadows else None)

    if exposure is None:
        if integer:
            peak = _peak(shading(), alb if alb.ndim == 2 else alb.max(axis=2), nz)
            exposure = 0.75 * np.iinfo(dtype).max / peak if peak > 0 else 1.0
        else:
            exposure = 1.0
    return _counts(shading(), alb, nz, k=k, exposure=exposure, rng=np.random.default_rng(rng),
                   noise=noise, gain=gain, read_noise=read_noise, dtype=dtype)


def _checked_render_inputs(height_um, albedo, light_positions_mm, light_directions, intensities,
                           pixel_size_um):
    """:func:`render_images`'s inputs as float64 arrays, each checked with a one-line message:
    the height, the albedo, the lamps (positions, or directions normalised here) and their
    ``E_k`` (default 1)."""
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
    if h.ndim != 2 or min(h.shape) < 2 or not pixel_size_um > 0:
        raise UVPSInputError(f"height_um must be (M, N) with M, N >= 2 and pixel_size_um > 0; "
                             f"got shape {h.shape}, pixel_size_um={pixel_size_um}")
    return h, alb, positions, directions, e


def _counts(shadings, alb, nz, *, k, exposure, rng, noise, gain, read_noise, dtype):
    """The images from each lamp's shading: vignetting, exposure, albedo, stray light, noise
    (``rng``'s draws image by image), black level, then rounding and clipping to an integer
    ``dtype``. float64 for exact model values (dtype None), float32 is plenty below 16-bit
    quantisation."""
    integer = dtype is not None and np.issubdtype(np.dtype(dtype), np.integer)
    out = np.empty((k,) + alb.shape, dtype=np.float64 if dtype is None else dtype)
    work = np.float64 if dtype is None or np.dtype(dtype) == np.float64 else np.float32
    alb_w = alb.astype(work)
    stray = None
    if nz.stray_light is not None:
        stray = np.asarray(nz.stray_light, dtype=np.float64)
        stray = (exposure * (stray if stray.ndim == alb.ndim else stray[..., None])).astype(work)
    black = None if nz.black_level is None else np.asarray(nz.black_level, dtype=work)
    if black is not None and alb.ndim == 2:
        black = black[0]
    for i, s in enumerate(shadings):
        if nz.vignetting is not None:
            s = s * nz.vignetting
        s = (exposure * s).astype(work)
        counts = alb_w * (s if alb.ndim == 2 else s[..., None])
        if stray is not None:
            counts += stray
        if noise:
            counts = _add_noise(counts, rng, gain=gain, read_noise=read_noise)
        if black is not None:
            counts += black
        if integer:
            info = np.iinfo(dtype)
            counts = np.clip(np.rint(counts), info.min, info.max)
        out[i] = counts
    return out


def _peak(shading, amax, nuisances):
    """Brightest noise-free sample (black level aside) over all lights, in ``albedo * E``
    units; with stray light an upper bound (its maximum added to the direct maximum)."""
    vig = nuisances.vignetting
    peak = max(float(np.max((s if vig is None else s * vig) * amax)) for s in shading)
    if nuisances.stray_light is not None:
        peak += float(np.max(nuisances.stray_light))
    return peak


def _check_nuisances(nz, k, albedo_shape, *, far):
    """Shapes of a Nuisances against K lights and the albedo (M, N[, C])."""
    mn = albedo_shape[:2]
    c = albedo_shape[2] if len(albedo_shape) == 3 else 1
    if nz.black_level is not None and np.shape(nz.black_level) != (c,):
        raise UVPSInputError(f"nuisances.black_level must be ({c},) for {c} channel(s); got "
                             f"shape {np.shape(nz.black_level)}")
    if nz.stray_light is not None and np.shape(nz.stray_light) not in (mn, tuple(albedo_shape)):
        raise UVPSInputError(f"nuisances.stray_light must be {mn} or {tuple(albedo_shape)}; got "
                             f"shape {np.shape(nz.stray_light)}")
    if nz.vignetting is not None and np.shape(nz.vignetting) != mn:
        raise UVPSInputError(f"nuisances.vignetting must be {mn}; got shape "
                             f"{np.shape(nz.vignetting)}")
    if nz.beam_axes is not None:
        if far:
            raise UVPSInputError("nuisances.beam_axes needs near lights (light_positions_mm)")
        if np.shape(nz.beam_axes) != (k, 3):
            raise UVPSInputError(f"nuisances.beam_axes must be ({k}, 3); got shape "
                                 f"{np.shape(nz.beam_axes)}")
        if not nz.beam_exponent >= 0:
            raise UVPSInputError(f"nuisances.beam_exponent must be >= 0; got {nz.beam_exponent}")
    if nz.shadowed is not None and np.shape(nz.shadowed) != (k,) + mn:
        raise UVPSInputError(f"nuisances.shadowed must be {(k,) + mn}; got shape "
                             f"{np.shape(nz.shadowed)}")


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


def light_positions(rng, *, n_lights, elevation_deg, distance_mm,
                    azimuth_jitter=0.25) -> np.ndarray:
    """Lamp positions (K, 3) in mm: azimuths evenly spread, each moved by up to
    ``azimuth_jitter`` of the spacing, elevation and distance uniform in their ranges. Azimuth
    counted from +x toward +y."""
    step = 2 * np.pi / n_lights
    az = rng.uniform(0, 2 * np.pi) + step * np.arange(n_lights)
    az = az + rng.uniform(-azimuth_jitter, azimuth_jitter, n_lights) * step
    el = np.radians(rng.uniform(*elevation_deg, n_lights))
    d = rng.uniform(*distance_mm, n_lights)
    return np.stack([d * np.cos(el) * np.cos(az), d * np.cos(el) * np.sin(az),
                     d * np.sin(el)], axis=1)


# --------------------------------------------------------------------------------------------
# Nuisances of a real capture (drawn from their own random streams)
# --------------------------------------------------------------------------------------------


def _substream(seed, tag):
    """A Generator of its own for one nuisance: ``default_rng((seed, crc32(tag)))``, so that
    drawing it leaves the main stream (scene, lamps, noise) as it was."""
    if seed is None:
        return np.random.default_rng()
    return np.random.default_rng((int(seed), zlib.crc32(tag.encode())))


def _black_levels(value, channels):
    """The black level per channel, (C,) float64, or None when it is 0 everywhere."""
    arr = np.atleast_1d(np.asarray(value, dtype=np.float64))
    if arr.ndim != 1 or arr.size not in (1, channels):
        raise UVPSInputError(f"black_level must be a number or {channels} numbers (one per "
                             f"channel); got {value!r}")
    if not np.all(np.isfinite(arr)) or np.any(arr < 0):
        raise UVPSInputError(f"black_level must be >= 0 counts; got {value!r}")
    return None if not np.any(arr) else np.broadcast_to(arr, (channels,)).copy()


def _vignetting_map(rng, shape, falloff):
    """cos^4-law vignetting (M, N) float32 with ``falloff`` at the half-diagonal, and its
    parameters: the optical centre drawn within 5 % of the half-diagonal of the image centre."""
    m, n = shape
    half_diag = math.hypot((m - 1) / 2.0, (n - 1) / 2.0)
    off = 0.05 * half_diag * math.sqrt(rng.uniform())
    ang = rng.uniform(0, 2 * np.pi)
    cr, cc = (m - 1) / 2.0 + off * math.sin(ang), (n - 1) / 2.0 + off * math.cos(ang)
    f = half_diag / math.sqrt((1.0 - falloff) ** -0.5 - 1.0)
    r2 = (np.arange(m)[:, None] - cr) ** 2 + (np.arange(n)[None, :] - cc) ** 2
    vig = (1.0 / (1.0 + r2 / (f * f)) ** 2).astype(np.float32)
    info = {"corner_falloff": float(falloff), "centre_px": [cr, cc], "f_px": f,
            "profile": "1 / (1 + (r / f_px)^2)^2, r in pixels from centre_px (row, col)",
            "min": float(vig.min()), "max": float(vig.max())}
    return vig, info


def _stray_shape(rng, shape):
    """A smooth positive field of mean 1: a broad gaussian veil on a floor, tilted."""
    m, n = shape
    half_diag = math.hypot(m / 2.0, n / 2.0)
    cr, cc = rng.uniform([0.2 * m, 0.2 * n], [0.8 * m, 0.8 * n])
    sigma = rng.uniform(0.5, 1.0) * half_diag
    tilt = rng.uniform(-0.3, 0.3, 2)
    rows = np.arange(m)[:, None]
    cols = np.arange(n)[None, :]
    veil = np.exp(-((rows - cr) ** 2 + (cols - cc) ** 2) / (2 * sigma * sigma))
    ramp = (1 + tilt[0] * (cols - (n - 1) / 2.0) / (n / 2.0)
            + tilt[1] * (rows - (m - 1) / 2.0) / (m / 2.0))
    field = (0.5 + veil) * ramp
    info = {"veil_centre_px": [float(cr), float(cc)], "veil_sigma_px": float(sigma),
            "tilt": tilt.tolist()}
    return field / field.mean(), info


def _beam_axes(rng, positions, aim_error_deg):
    """Beam axes (K, 3): the ray from each lamp to the image centre turned by up to
    ``aim_error_deg`` (uniform over the cone), and each lamp's error in degrees."""
    k = positions.shape[0]
    to_centre = -positions / np.linalg.norm(positions, axis=1, keepdims=True)
    err = np.radians(aim_error_deg) * np.sqrt(rng.uniform(0, 1, k))
    psi = rng.uniform(0, 2 * np.pi, k)
    axes = np.empty((k, 3))
    for i, (a0, e, p) in enumerate(zip(to_centre, err, psi)):
        e1 = np.cross(a0, [0.0, 0.0, 1.0])
        if np.linalg.norm(e1) < 1e-9:
            e1 = np.array([1.0, 0.0, 0.0])
        e1 /= np.linalg.norm(e1)
        e2 = np.cross(a0, e1)
        axes[i] = math.cos(e) * a0 + math.sin(e) * (math.cos(p) * e1 + math.sin(p) * e2)
    return axes / np.linalg.norm(axes, axis=1, keepdims=True), np.degrees(err)


def render_dark_frame(capture: SyntheticCapture) -> np.ndarray:
    """The frame a user takes with the UV lamp off: the capture's stray light and black level.

    ``run``'s ``dark`` parameter subtracts such a frame from every image. It holds what is the
    same in every image without the lamp: the black level and the stray light, as
    :func:`render_images` adds them (``stray_light`` stands for room light and a lamp's
    visible leak here; veiling glare of the lamp's own fluorescence would vanish with the lamp,
    and is not in a real dark frame), with the capture's photon and read noise drawn from a
    stream of its own (one frame, not an average: its noise is then common to every corrected
    image).

    Returns
    -------
    (M, N) or (M, N, C) array of the images' dtype.
    """
    spec, nz = capture.spec, capture.nuisances
    shape = capture.images.shape[1:]
    counts = np.zeros(shape, dtype=np.float32)
    if nz.stray_light is not None:
        stray = capture.exposure * np.asarray(nz.stray_light, dtype=np.float32)
        counts += stray if stray.ndim == counts.ndim else stray[..., None]
    if spec.noise:
        counts = _add_noise(counts, _substream(spec.seed, "dark frame"), gain=capture.gain,
                            read_noise=spec.read_noise)
    if nz.black_level is not None:
        black = np.asarray(nz.black_level, dtype=np.float32)
        counts += black if counts.ndim == 3 else black[0]
    info = np.iinfo(capture.images.dtype) if capture.images.dtype.kind in "ui" else None
    if info is not None:
        counts = np.clip(np.rint(counts), info.min, info.max)
    return counts.astype(capture.images.dtype)


#: A card as real ones are: tilted by up to 1 deg on the painting, its fluorescence uneven by 1 %
#: RMS (:func:`render_card`'s defaults in the benchmark's ``card`` mode).
CARD_TYPICAL = {"tilt_deg": 1.0, "unevenness": 0.01}


def render_card(capture: SyntheticCapture, *, tilt_deg: float = 0.0, tilt_azimuth_deg: float = 0.0,
                unevenness: float = 0.0, relief_um: float = 0.0, relief_period_mm: float = 2.0,
                peak_fraction: float = 0.75, colour=(0.85, 0.88, 0.80)) -> np.ndarray:
    """A flat fluorescent card on the painting, photographed under each of the capture's lamps.

    The same lamps (positions, ``E_k``, beams), lens (vignetting), stray light, black level and
    camera (exposure, gain, read noise) as ``capture``, so that :func:`render_dark_frame` of the
    capture is the card's dark frame too (:mod:`uvps.core.card`). The card's brightness sets its
    fluorescence: the brightest noise-free sample is ``peak_fraction`` of full scale (above 1 it
    saturates).

    Parameters
    ----------
    capture : SyntheticCapture
    tilt_deg, tilt_azimuth_deg : float
        The card's plane rises by ``tan(tilt)`` toward the azimuth (deg, counter-clockwise from +x).
    unevenness : float
        RMS fraction of the card's fluorescence varying across it (wavelengths 0.3-6 mm).
    relief_um, relief_period_mm : float
        A card not lying flat: ``relief_um * sin(2 pi x / P) * sin(2 pi y / P)`` on its plane.
    peak_fraction : float
        Brightest sample over full scale.
    colour : 3 floats
        The card's fluorescence colour (RGB captures).

    Returns
    -------
    (K, M, N) or (K, M, N, C) uint16 array, the capture's shape.
    """
    spec, nz = capture.spec, capture.nuisances
    K, M, N = capture.images.shape[:3]
    px = float(spec.pixel_size_um)
    x, y = pixel_centres_mm((M, N), px)
    az = math.radians(tilt_azimuth_deg)
    height = 1000.0 * math.tan(math.radians(tilt_deg)) * (x * math.cos(az) + y * math.sin(az))
    if relief_um:
        w = 2 * np.pi / relief_period_mm
        height = height + relief_um * np.sin(w * x) * np.sin(w * y)
    height = np.broadcast_to(height, (M, N)).astype(np.float64)
    rng = _substream(spec.seed, "card")
    field = np.zeros((M, N))
    if unevenness:
        for _ in range(12):
            wl = math.exp(rng.uniform(math.log(0.3), math.log(6.0)))
            th, ph = rng.uniform(0, 2 * np.pi, 2)
            field += np.cos(2 * np.pi / wl * (x * math.cos(th) + y * math.sin(th)) + ph)
        field *= unevenness / field.std()
    tone = np.clip(1.0 + field, 0.05, None)
    albedo = tone[..., None] * np.asarray(colour, float) if capture.images.ndim == 4 else tone
    card_nz = Nuisances(black_level=nz.black_level, stray_light=nz.stray_light, vignetting=nz.vignetting,
                        beam_axes=nz.beam_axes, beam_exponent=nz.beam_exponent)
    normals = _normals64(height, px)
    shading = _shading(normals, height, px, capture.light_positions_mm, None, capture.intensities,
                       beam_axes=nz.beam_axes, beam_exponent=nz.beam_exponent)
    amax = albedo if albedo.ndim == 2 else albedo.max(axis=2)
    direct = _peak(shading, amax, Nuisances(vignetting=nz.vignetting))
    stray = 0.0 if nz.stray_light is None else float(np.max(nz.stray_light))
    scale = (peak_fraction * 65535.0 / capture.exposure - stray) / direct
    if not scale > 0:
        raise UVPSInputError(f"peak_fraction {peak_fraction} leaves no room for the card above the stray light")
    return render_images(height, albedo * scale, pixel_size_um=px, light_positions_mm=capture.light_positions_mm,
                         intensities=capture.intensities, rng=rng, noise=spec.noise, gain=capture.gain,
                         read_noise=spec.read_noise, exposure=capture.exposure, dtype=np.uint16,
                         nuisances=card_nz)


def _lamp_and_lens_nuisances(spec, nz, positions, intensities, shape):
    """Black level, vignetting and beams of ``spec`` into ``nz`` (and the lamps' truth)."""
    channels = 3 if spec.rgb else 1
    nz.black_level = _black_levels(spec.black_level, channels)
    if nz.black_level is not None:
        nz.info["black_level_counts"] = nz.black_level.tolist()
    if spec.vignetting > 0:
        nz.vignetting, nz.info["vignetting"] = _vignetting_map(
            _substream(spec.seed, "vignetting"), shape, spec.vignetting)
    centre = np.ones(len(positions))
    if spec.beam_exponent > 0:
        nz.beam_axes, err = _beam_axes(_substream(spec.seed, "beams"), positions,
                                       spec.beam_aim_error_deg)
        nz.beam_exponent = float(spec.beam_exponent)
        to_centre = -positions / np.linalg.norm(positions, axis=1, keepdims=True)
        centre = np.clip(np.sum(nz.beam_axes * to_centre, axis=1), 0, None) ** nz.beam_exponent
        t = -positions[:, 2] / nz.beam_axes[:, 2]
        nz.info["beams"] = {"exponent": nz.beam_exponent,
                            "aim_error_deg": err.tolist(),
                            "axes": nz.beam_axes.tolist(),
                            "aim_points_mm": (positions + t[:, None] * nz.beam_axes).tolist(),
                            "centre_factor": centre.tolist()}
    nz.info["lamps"] = {"positions_mm": positions.tolist(), "intensities": intensities.tolist(),
                        "centre_irradiance": (intensities * centre).tolist()}


def _add_stray_light(spec, nz, shading, albedo, step=4):
    """Stray light of ``spec.stray_light`` x the median noise-free signal (per channel, over
    every image, sampled 1 pixel in ``step`` x ``step``), shaped by :func:`_stray_shape`."""
    alb = albedo[::step, ::step]
    samples = []
    for s in shading:
        s = s if nz.vignetting is None else s * nz.vignetting
        sub = s[::step, ::step]
        samples.append(sub * alb if alb.ndim == 2 else sub[..., None] * alb)
    samples = np.stack(samples)
    median = np.median(samples.reshape(-1, 1 if albedo.ndim == 2 else albedo.shape[2]), axis=0)
    field, info = _stray_shape(_substream(spec.seed, "stray light"), albedo.shape[:2])
    stray = spec.stray_light * (field * median[0] if albedo.ndim == 2
                                else field[..., None] * median)
    nz.stray_light = stray.astype(np.float32)
    nz.info["stray_light"] = {"fraction": float(spec.stray_light),
                              "median_signal": median.tolist(), **info}


def _normalised(a):
    s = a.std()
    return (a - a.mean()) / s if s > 0 else a * 0
