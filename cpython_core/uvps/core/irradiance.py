"""The lamp irradiance model, written once: every estimator and the generator call it.

Frame and units as in ``docs/architecture.md``: X the surface point in mm from the image centre,
x toward increasing column, y up, z toward the camera. Lamp k is either

- a **near point lamp** at ``L_k`` (mm): its irradiance vector at X is::

      v_k(X) = E_k * B_k(X) * |L_k|^2 * (L_k - X) / |L_k - X|^3

  (inverse square, normalised so that ``|v_k(0)| = E_k``: ``E_k`` is the irradiance at the image
  centre on a plane facing the lamp), with the optional beam ``B_k(X) = max(0, a_k . (X - L_k) /
  |X - L_k|)^n`` of a lamp aimed along the unit axis ``a_k`` (``B_k = 1`` without one); or
- a **far lamp** of direction ``l_k`` (unit, toward the lamp): ``v_k = E_k l_k`` everywhere.

A Lambertian surface of normal n receives ``max(0, n . v_k(X))`` (cosine law, attached shadow
at 0): paper Eq. (1) with the near-light fall-off of Huang et al. (2015).

:func:`near_scale` is the model's one formula, ``E_k |L_k|^2 / |L_k - X|^3`` of the offset
``L_k - X``; it is written in arithmetic only so that the same source runs on numpy arrays and,
compiled (:data:`near_scale_compiled`), inside the per-pixel kernels of :mod:`uvps.core.stereo`.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Iterator, Optional

import numba
import numpy as np

__all__ = ["pixel_coordinates_mm", "LightModel", "near_scale", "near_scale_compiled", "beam_factor", "lamp_vectors",
           "irradiance"]


def near_scale(dx, dy, dz, e_ll):
    """``e_ll / d^3`` with ``d^2 = dx^2 + dy^2 + dz^2``: the factor that turns the offset
    ``(dx, dy, dz) = L_k - X`` (mm) into the lamp's irradiance vector, for ``e_ll = E_k |L_k|^2``.

    Scalars or arrays (numpy broadcasting); the arithmetic is done in the arguments' precision.
    """
    dd = dx * dx + dy * dy + dz * dz
    return e_ll / (dd * np.sqrt(dd))


#: :func:`near_scale` compiled for numba kernels (the same source, inlined).
near_scale_compiled = numba.njit(inline="always", cache=True)(near_scale)


def beam_factor(axis, dx, dy, dz, exponent):
    """``max(0, cos)^n`` of the angle between the lamp's beam ``axis`` (unit, from the lamp toward
    where it is aimed) and the ray from the lamp to the point; ``(dx, dy, dz) = L_k - X``."""
    inv = 1.0 / np.sqrt(dx * dx + dy * dy + dz * dz)
    return np.maximum(-(axis[0] * dx + axis[1] * dy + axis[2] * dz) * inv, 0.0) ** exponent


def lamp_vectors(X, *, intensities, positions_mm=None, directions=None) -> np.ndarray:
    """Irradiance vectors ``v_k(X)`` of every lamp at points X (..., 3) mm: (K, ..., 3).

    Exactly one of ``positions_mm`` (near lamps, (K, 3) mm) and ``directions`` (far lamps, (K, 3)
    unit) is given. Near lamps are computed in X's precision (float32 X gives float32 vectors);
    far lamps return a broadcast (read-only) view of ``E_k l_k``.
    """
    E = np.asarray(intensities, dtype=float)
    if positions_mm is None:
        D = np.asarray(directions, dtype=float)
        v = D * E[:, None]
        return np.broadcast_to(v.reshape((len(v),) + (1,) * (X.ndim - 1) + (3,)), (len(v),) + X.shape)
    P = np.asarray(positions_mm, dtype=float)
    out = np.empty((len(P),) + X.shape, dtype=np.float32 if X.dtype == np.float32 else float)
    for k, (Lk, Ek) in enumerate(zip(P, E)):
        V = Lk - X
        out[k] = V * near_scale(V[..., 0], V[..., 1], V[..., 2], Ek * float(Lk @ Lk))[..., None]
    return out


def irradiance(normals, x, y, z, *, intensities, positions_mm=None, directions=None,
               beam_axes: Optional[np.ndarray] = None, beam_exponent: float = 0.0,
               shadowed=None) -> Iterator[np.ndarray]:
    """Yield, lamp by lamp, the irradiance ``max(0, n . v_k(X)) [* B_k(X)]`` received at X.

    Parameters
    ----------
    normals : (..., 3) array
        Unit surface normals (a single (3,) normal for a plane).
    x, y, z : arrays broadcasting to the normals' (...) shape
        Surface points in mm (e.g. x (1, N), y (M, 1), z (M, N)); ignored for far lamps.
    intensities : (K,) array
        ``E_k``.
    positions_mm, directions : (K, 3) array
        Near lamps or far lamps (exactly one).
    beam_axes : (K, 3) array, optional
        Near lamps' beam axes (unit, from the lamp toward its aim); with ``beam_exponent`` n.
    shadowed : (K, ...) bool array, optional
        Cast shadows: 0 there.

    Yields
    ------
    (...) float64 array per lamp.
    """
    n = np.asarray(normals)
    nx, ny, nz = (n[..., i].astype(np.float64) for i in range(3))
    E = np.asarray(intensities, dtype=float)
    if positions_mm is None:
        for k, (e, d) in enumerate(zip(E, np.asarray(directions, dtype=float))):
            s = e * np.maximum(nx * d[0] + ny * d[1] + nz * d[2], 0.0)
            if shadowed is not None:
                s[shadowed[k]] = 0.0
            yield s
        return
    for k, (e, lk) in enumerate(zip(E, np.asarray(positions_mm, dtype=float))):
        dx, dy, dz = lk[0] - x, lk[1] - y, lk[2] - z
        f = near_scale(dx, dy, dz, e * float(lk @ lk))
        s = np.maximum((nx * dx + ny * dy + nz * dz) * f, 0.0)
        if beam_axes is not None:
            s = s * beam_factor(beam_axes[k], dx, dy, dz, beam_exponent)
        if shadowed is not None:
            s[shadowed[k]] = 0.0
        yield s


# ------------------------------------------------------------------------------------------------
# the frame (pixel -> mm) and the lamps
# ------------------------------------------------------------------------------------------------

def pixel_coordinates_mm(rows, cols, shape, pixel_size_um, z_mm=None) -> np.ndarray:
    """World coordinates (mm) of pixel centres; rows/cols broadcast. Returns (..., 3)."""
    M, N = shape
    px = pixel_size_um / 1000.0
    rows, cols = np.broadcast_arrays(np.asarray(rows, float), np.asarray(cols, float))
    X = np.empty(rows.shape + (3,))
    X[..., 0] = (cols - (N - 1) / 2.0) * px
    X[..., 1] = ((M - 1) / 2.0 - rows) * px
    X[..., 2] = 0.0 if z_mm is None else z_mm
    return X


@dataclass
class LightModel:
    """Lights of a capture: near point lights (positions) or far lights (directions).

    Attributes
    ----------
    positions_mm : ndarray (K, 3) or None
        Near point lights, mm from the image centre.
    directions : ndarray (K, 3)
        Unit vectors from the image centre toward each light.
    intensities : ndarray (K,)
        Relative lamp irradiance at the image centre ``E_k`` (median 1).
    """

    directions: np.ndarray
    intensities: np.ndarray
    positions_mm: Optional[np.ndarray] = None

    @property
    def near(self) -> bool:
        return self.positions_mm is not None

    @classmethod
    def from_positions(cls, positions_mm, intensities=None):
        P = np.asarray(positions_mm, dtype=float)
        E = np.ones(len(P)) if intensities is None else np.asarray(intensities, dtype=float)
        return cls(P / np.linalg.norm(P, axis=1, keepdims=True), E, P)

    @classmethod
    def from_directions(cls, directions, intensities=None):
        D = np.asarray(directions, dtype=float)
        D = D / np.linalg.norm(D, axis=1, keepdims=True)
        E = np.ones(len(D)) if intensities is None else np.asarray(intensities, dtype=float)
        return cls(D, E, None)

    def vectors(self, X) -> np.ndarray:
        """Per-point light vectors ``E_k (|L_k|/d)^2 (L_k - X)/d`` for points X (..., 3) mm
        (:func:`uvps.core.irradiance.lamp_vectors`).

        Returns (K, ..., 3); far lights give ``E_k l_k`` everywhere.
        """
        return lamp_vectors(X, intensities=self.intensities, positions_mm=self.positions_mm,
                            directions=None if self.near else self.directions)

    def to_json(self, files, *, extra=None) -> dict:
        lights = []
        for k, f in enumerate(files):
            d = self.directions[k]
            lights.append({
                "file": str(f),
                "direction": [float(x) for x in d],
                "position_mm": None if not self.near else [float(x) for x in self.positions_mm[k]],
                "azimuth_deg": float(np.degrees(np.arctan2(d[1], d[0])) % 360.0),
                "elevation_deg": float(np.degrees(np.arcsin(np.clip(d[2], -1, 1)))),
                "intensity": float(self.intensities[k]),
            })
        out = {"mode": "near" if self.near else "far", "lights": lights}
        if extra:
            out.update(extra)
        return out
