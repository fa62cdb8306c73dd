"""Render the recovered surface under a virtual distant raking light.

Frame (docs/architecture.md): x toward increasing column, y UP (toward decreasing row), z toward
the camera; normals are ``(M, N, 3)`` unit ``(nx, ny, nz)`` in that frame. The light azimuth is
measured counter-clockwise from +x as seen by the camera: 0 = light from the right of the image,
90 = from the top, 180 = from the left, 270 = from the bottom. The elevation is the angle above
the canvas plane (90 = straight down the camera axis).
"""

from __future__ import annotations

import numpy as np

from ..errors import UVPSInputError

__all__ = ["light_direction", "relight", "hillshade"]


def _check_angle(name, value, low=None, high=None) -> float:
    try:
        value = float(value)
    except (TypeError, ValueError):
        raise UVPSInputError(f"{name} must be a number of degrees; got {value!r}") from None
    if not np.isfinite(value) or (low is not None and not low <= value <= high):
        bounds = "" if low is None else f" in [{low:g}, {high:g}]"
        raise UVPSInputError(f"{name} must be a finite number of degrees{bounds}; got {value!r}")
    return value


def light_direction(azimuth_deg: float, elevation_deg: float) -> np.ndarray:
    """Unit vector from the surface toward a distant light.

    Parameters
    ----------
    azimuth_deg : float
        Counter-clockwise from +x (0 = from the right, 90 = from the image top).
    elevation_deg : float
        Above the canvas plane, in [0, 90].

    Returns
    -------
    ndarray, shape (3,), float64
        ``(cos(el) cos(az), cos(el) sin(az), sin(el))``.
    """
    az = np.radians(_check_angle("azimuth_deg", azimuth_deg))
    el = np.radians(_check_angle("elevation_deg", elevation_deg, 0.0, 90.0))
    return np.array([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)])


def relight(
    normals,
    albedo,
    *,
    azimuth_deg: float = 315.0,
    elevation_deg: float = 15.0,
    ambient: float = 0.0,
) -> np.ndarray:
    """The surface lit by a virtual distant raking light (Lambertian).

    Parameters
    ----------
    normals : ndarray, shape (M, N, 3)
        Normals ``(nx, ny, nz)`` (x right, y up, z toward the camera); they are normalised here,
        so small departures from unit length (e.g. after a TIFF round trip) do not change the
        brightness. Not modified.
    albedo : ndarray, shape (M, N) or (M, N, C), or None
        Reflectance (grey or colour). None renders a grey image with albedo 1. Not modified.
    azimuth_deg : float, optional
        Light azimuth, counter-clockwise from +x: 0 = from the right, 90 = from the image top.
        Default 315 (from the lower right).
    elevation_deg : float, optional
        Light elevation above the canvas plane, in [0, 90]. Default 15 (raking).
    ambient : float, optional
        Ambient (uniform) light added to the direct term, >= 0, in units of the direct light's
        irradiance on a surface facing it. Default 0.

    Returns
    -------
    ndarray, float32, shape of ``albedo`` (``(M, N)`` when ``albedo`` is None)
        ``albedo * (max(0, n . l) + ambient)`` with ``l`` from :func:`light_direction`. NaN
        where the normal is not finite or has zero length.

    Notes
    -----
    Far-light Lambertian image model of docs/architecture.md with unit irradiance, plus an
    ambient term; attached shadows (``n . l < 0``) are black apart from the ambient light, cast
    shadows are not modelled. A flat surface renders as ``albedo * sin(elevation)``.

    Examples
    --------
    >>> import numpy as np
    >>> flat = np.zeros((2, 3, 3), np.float32); flat[..., 2] = 1
    >>> img = relight(flat, np.full((2, 3), 0.5, np.float32), elevation_deg=30)
    >>> bool(np.allclose(img, 0.25))
    True
    """
    normals = np.asarray(normals)
    if normals.ndim != 3 or normals.shape[2] != 3:
        raise UVPSInputError(
            f"normals must be an (M, N, 3) array (components last); got {normals.shape}"
        )
    if not np.issubdtype(normals.dtype, np.floating):
        raise UVPSInputError(f"normals must be a floating-point array; got dtype {normals.dtype}")
    shape = normals.shape[:2]
    if albedo is not None:
        albedo = np.asarray(albedo)
        if albedo.shape[:2] != shape or albedo.ndim not in (2, 3):
            raise UVPSInputError(
                f"albedo must be (M, N) or (M, N, C) with (M, N) = {shape}; got {albedo.shape}"
            )
        kind = albedo.dtype
        if not (np.issubdtype(kind, np.floating) or np.issubdtype(kind, np.integer)):
            raise UVPSInputError(f"albedo must be a real numeric array; got dtype {albedo.dtype}")
    try:
        ambient = float(ambient)
    except (TypeError, ValueError):
        raise UVPSInputError(f"ambient must be a number >= 0; got {ambient!r}") from None
    if not np.isfinite(ambient) or ambient < 0:
        raise UVPSInputError(f"ambient must be a number >= 0; got {ambient!r}")
    light = light_direction(azimuth_deg, elevation_deg).astype(np.float32)

    n = normals.astype(np.float32, copy=False)  # read only: no copy needed
    with np.errstate(invalid="ignore", divide="ignore"):
        length = np.sqrt(np.einsum("ijk,ijk->ij", n, n))
        shading = (n @ light) / length  # NaN for non-finite or zero-length normals
    np.maximum(shading, 0, out=shading, where=~np.isnan(shading))
    shading += np.float32(ambient)
    if albedo is None:
        return shading.astype(np.float32, copy=False)
    if albedo.ndim == 3:
        shading = shading[:, :, None]
    return albedo.astype(np.float32, copy=False) * shading


def hillshade(
    normals, *, azimuth_deg: float = 315.0, elevation_deg: float = 15.0, ambient: float = 0.0
) -> np.ndarray:
    """Grey rendering of the surface shape alone: :func:`relight` with albedo 1.

    Parameters
    ----------
    normals : ndarray, shape (M, N, 3)
        Normals in the world frame.
    azimuth_deg, elevation_deg, ambient : float, optional
        As in :func:`relight`.

    Returns
    -------
    ndarray, shape (M, N), float32
        ``max(0, n . l) + ambient``; NaN where the normal is not finite.
    """
    return relight(
        normals, None, azimuth_deg=azimuth_deg, elevation_deg=elevation_deg, ambient=ambient
    )
