"""A sphere seen by a pinhole camera: its 3-D centre and radius from the circle it shows, and the normal
under each pixel (``uvps calibrate --camera-distance-mm``).

The camera's centre of projection is at ``C = (0, 0, D)`` mm above the image centre (the lens's axis
through the middle of the frame, the sensor parallel to the painting); a pixel is its point on the plane
of the painting (z = 0, docs/architecture.md). A sphere of radius ``R`` resting on that plane (centre
``S``, ``S_z = R``) is seen as the section of its tangent cone from ``C`` by the plane: an ellipse a
little larger than ``R`` (by ``R / D``), drawn out along the line from the image centre by ``1 / cos``
of the sphere's off-axis angle. The circle fitted to that outline is taken as the ellipse's centre and
mean semi-axis (:func:`outline`); :func:`sphere_from_outline` inverts it. The normal under a pixel is
where the ray from ``C`` through the pixel's point first meets the sphere (:func:`pixel_normals`), and
the view vector at a surface point ``X`` is ``(C - X) / |C - X|`` (:func:`view_at`).

Without ``D`` (None) the camera is orthographic (viewer along +z): the circle's centre is the sphere's,
its radius the sphere's, and the normal at ``(x, y)`` is ``((x - S_x) / R, (y - S_y) / R, n_z)``.
"""
from __future__ import annotations

import math
from typing import Optional

import numpy as np

__all__ = ["outline", "sphere_from_outline", "pixel_normals", "view_at"]


def outline(centre_mm, radius_mm: float, camera_distance_mm: float):
    """The outline of a sphere (centre ``centre_mm`` (3,), radius) seen from ``(0, 0, D)`` on the plane
    z = 0: (centre (2,), mean semi-axis, semi-axes (2,)) of the ellipse.

    Examples
    --------
    >>> c, r, ax = outline([0.0, 0.0, 2.5], 2.5, 300.0)      # on the axis: a circle of radius D tan(a)
    >>> np.allclose(c, 0), round(r, 4), bool(np.isclose(ax[0], ax[1]))
    (True, 2.5211, True)
    """
    S = np.asarray(centre_mm, float)
    D = float(camera_distance_mm)
    w = S - np.array([0.0, 0.0, D])
    dist = float(np.linalg.norm(w))
    u = w / dist
    c2 = 1.0 - (radius_mm / dist) ** 2
    # (x ux + y uy - D uz)^2 - c2 (x^2 + y^2 + D^2) = 0: a conic [x y 1] Q [x y 1]^T
    A = np.array([[u[0] * u[0] - c2, u[0] * u[1]], [u[0] * u[1], u[1] * u[1] - c2]])
    b = -D * u[2] * u[:2]
    f = (D * u[2]) ** 2 - c2 * D * D
    centre = np.linalg.solve(A, -b)
    f0 = f + float(b @ centre)
    lam = np.linalg.eigvalsh(A)
    axes = np.sqrt(-f0 / lam)
    return centre, float(axes.mean()), axes


def sphere_from_outline(centre_xy_mm, radius_mm: float, camera_distance_mm: Optional[float]):
    """The sphere resting on the painting's plane whose outline is the circle ``centre_xy_mm`` (2,),
    ``radius_mm``: (centre (3,), radius). Orthographic (None): the circle itself, one radius up.

    Examples
    --------
    >>> S, R = sphere_from_outline(*outline([12.0, -9.0, 2.5], 2.5, 300.0)[:2], 300.0)
    >>> np.round(S, 9).tolist(), round(R, 9)
    ([12.0, -9.0, 2.5], 2.5)
    """
    E = np.asarray(centre_xy_mm, float)
    if camera_distance_mm is None:
        return np.array([E[0], E[1], float(radius_mm)]), float(radius_mm)
    D = float(camera_distance_mm)
    # on the axis, tan(a) = rho / D and R = (D - R) sin(a): the start; then a fixed point on the outline
    sa = math.sin(math.atan2(radius_mm, D))
    R = D * sa / (1.0 + sa)
    xy = E * (D - R) / D
    for _ in range(30):
        c, r, _ = outline([xy[0], xy[1], R], R, D)
        step = (E - c) * (D - R) / D
        xy = xy + step
        R_new = R * radius_mm / r
        done = abs(R_new - R) < 1e-12 * R and float(np.abs(step).max()) < 1e-12 * D
        R = R_new
        if done:
            break
    return np.array([xy[0], xy[1], R]), float(R)


def pixel_normals(X, Y, centre_mm, radius_mm: float, camera_distance_mm: Optional[float]):
    """The sphere's normal under each pixel point ``(X, Y)`` (mm on the painting's plane) and ``rho``,
    the sine of the angle between that normal and the view (1 on the outline; above 1 off the sphere,
    where the normal is the outline's nearest). Returns (normals (..., 3), rho (...))."""
    S = np.asarray(centre_mm, float)
    R = float(radius_mm)
    X = np.asarray(X, float)
    Y = np.asarray(Y, float)
    if camera_distance_mm is None:
        nx, ny = (X - S[0]) / R, (Y - S[1]) / R
        rho2 = nx * nx + ny * ny
        nz = np.sqrt(np.clip(1 - rho2, 0, None))
        return np.stack([nx, ny, nz], axis=-1), np.sqrt(rho2)
    D = float(camera_distance_mm)
    w = np.stack([X, Y, np.full(X.shape, -D)], axis=-1)
    w /= np.linalg.norm(w, axis=-1, keepdims=True)                      # the ray from C, away from it
    SC = S - np.array([0.0, 0.0, D])
    q = (w @ SC)[..., None] * w - SC                                     # closest point of the ray, from S
    d = np.linalg.norm(q, axis=-1)
    rho = d / R
    back = np.sqrt(np.clip(R * R - d * d, 0, None))
    n = (q - back[..., None] * w) / R
    n /= np.linalg.norm(n, axis=-1, keepdims=True)
    return n, rho


def view_at(point_mm, camera_distance_mm: Optional[float]) -> np.ndarray:
    """The unit vector from ``point_mm`` (3,) toward the camera: +z when orthographic (None)."""
    if camera_distance_mm is None:
        return np.array([0.0, 0.0, 1.0])
    v = np.array([0.0, 0.0, float(camera_distance_mm)]) - np.asarray(point_mm, float)
    return v / np.linalg.norm(v)
