"""Photometric stereo on analytic shapes with known normals, near and far lights."""
import numpy as np
import pytest

from uvps.lights import LightModel, pixel_coordinates_mm
from uvps.stereo import solve_normals

M, N, PX = 160, 200, 15.0


def _pos(az_deg, el_deg, d):
    a, e = np.radians(az_deg), np.radians(el_deg)
    return d * np.array([np.cos(e) * np.cos(a), np.cos(e) * np.sin(a), np.sin(e)])


def _sphere(radius_mm=1.0):
    r, c = np.mgrid[0:M, 0:N]
    X = pixel_coordinates_mm(r, c, (M, N), PX)
    rho2 = X[..., 0] ** 2 + X[..., 1] ** 2
    inside = rho2 < (0.97 * radius_mm) ** 2
    z = np.where(inside, np.sqrt(np.maximum(radius_mm ** 2 - rho2, 0)), 0.0)
    n = np.dstack([np.where(inside, X[..., 0], 0), np.where(inside, X[..., 1], 0), np.where(inside, z, 1.0)])
    n /= np.linalg.norm(n, axis=2, keepdims=True)
    X[..., 2] = 0.0
    return n, X, inside


def _render(n, X, model, albedo):
    shade = np.maximum(np.einsum("kmni,mni->kmn", model.vectors(X), n), 0)
    return shade[..., None] * albedo[None] if albedo.ndim == 3 else shade * albedo


def _err(a, b):
    return np.degrees(np.arccos(np.clip(np.sum(a * b, -1), -1, 1)))


NEAR = LightModel.from_positions(np.stack([_pos(30 * k + 5, 25 + 3 * k, 250 + 20 * k) for k in range(12)]),
                                 np.linspace(0.85, 1.15, 12))


def test_sphere_near_lights_rgb_albedo():
    n, X, inside = _sphere()
    colour = np.array([1.0, 0.6, 0.2])
    albedo = np.where((X[..., 0] > 0)[..., None], 2 * colour, colour) * 1000
    images = _render(n, X, NEAR, albedo).astype(np.float32)
    res = solve_normals(images, NEAR, pixel_size_um=PX)
    e = _err(res.normals, n)
    assert np.nanmax(e) < 0.05
    assert res.n_invalid == 0
    np.testing.assert_allclose(res.albedo, albedo, rtol=1e-3)
    assert res.normals.dtype == np.float32 and res.albedo.shape == (M, N, 3)


def test_near_light_model_matters():
    """Solving near-light images with far lights (directions only) tilts the normals."""
    n, X, _ = _sphere()
    images = _render(n, X, NEAR, np.full((M, N), 500.0)).astype(np.float32)
    far = LightModel.from_directions(NEAR.directions, NEAR.intensities)
    e_far = np.nanmean(_err(solve_normals(images, far, pixel_size_um=PX).normals, n))
    e_near = np.nanmean(_err(solve_normals(images, NEAR, pixel_size_um=PX).normals, n))
    assert e_near < 0.05 < e_far


def test_attached_shadows_and_saturation_are_left_out():
    n, X, inside = _sphere()
    low = LightModel.from_directions([_pos(a, 20, 1) for a in range(0, 360, 45)])
    images = _render(n, X, low, np.full((M, N), 1000.0)).astype(np.float32)
    sat = 900.0
    images = np.minimum(images, sat)
    res = solve_normals(images, low, pixel_size_um=PX, saturation=sat)
    e = _err(res.normals, n)
    ok = np.isfinite(e)
    # steep sphere flanks see fewer than 3 lamps: NaN and counted, the rest exact
    assert res.n_invalid == int((~ok).sum()) > 0
    assert np.nanmax(e) < 0.05
    assert res.n_used[~inside].min() >= 3


def test_pixels_with_fewer_than_three_lights_are_nan_and_counted():
    n = np.zeros((M, N, 3))
    n[..., 2] = 1
    X = pixel_coordinates_mm(*np.mgrid[0:M, 0:N], (M, N), PX)
    images = _render(n, X, NEAR, np.full((M, N), 100.0)).astype(np.float32)
    images[3:, 10:20, 30:40] = 0  # only 3 lights see this patch... minus one more below
    images[2, 10:20, 30:40] = 0
    res = solve_normals(images, NEAR, pixel_size_um=PX)
    assert res.n_invalid == 100
    assert np.isnan(res.normals[10:20, 30:40]).all() and np.isnan(res.albedo[10:20, 30:40]).all()


def test_robust_rejects_highlights():
    n, X, inside = _sphere()
    far = LightModel.from_directions([_pos(a, 40, 1) for a in range(0, 360, 30)])
    images = _render(n, X, far, np.full((M, N), 1000.0)).astype(np.float32)
    rng = np.random.default_rng(0)
    spikes = rng.random(images.shape) < 0.04
    images[spikes] *= 3.0  # specular highlights
    plain = np.nanmean(_err(solve_normals(images, far, pixel_size_um=PX).normals, n))
    robust = np.nanmean(_err(solve_normals(images, far, pixel_size_um=PX, robust=True).normals, n))
    assert robust < 0.5 * plain


def test_mask_and_bands_do_not_change_the_result():
    n, X, inside = _sphere()
    images = _render(n, X, NEAR, np.full((M, N), 300.0)).astype(np.float32)
    mask = np.zeros((M, N), bool)
    mask[20:140, 30:170] = True
    a = solve_normals(images, NEAR, pixel_size_um=PX, mask=mask)
    b = solve_normals(images, NEAR, pixel_size_um=PX, mask=mask, chunk_pixels=777)
    assert np.isnan(a.normals[~mask]).all() and a.n_invalid == 0
    np.testing.assert_allclose(a.normals[mask], b.normals[mask], atol=1e-6)


def test_paraboloid_normals_and_height_near_lights():
    """A paraboloid cap rendered under near lights: exact normals, and FC integration gives its height."""
    from uvps.integrate import integrate_normals

    r, c = np.mgrid[0:M, 0:N]
    X = pixel_coordinates_mm(r, c, (M, N), PX)
    a = 0.08  # z = a (R^2 - x^2 - y^2), mm
    R2 = 1.0
    rho2 = X[..., 0] ** 2 + X[..., 1] ** 2
    inside = rho2 < R2
    z = np.where(inside, a * (R2 - rho2), 0.0)
    p = np.where(inside, -2 * a * X[..., 0], 0.0)
    q = np.where(inside, -2 * a * X[..., 1], 0.0)
    n = np.dstack([-p, -q, np.ones_like(p)])
    n /= np.linalg.norm(n, axis=2, keepdims=True)
    Xs = X.copy()
    Xs[..., 2] = z
    images = _render(n, Xs, NEAR, np.full((M, N), 800.0)).astype(np.float32)
    res = solve_normals(images, NEAR, pixel_size_um=PX)
    assert np.nanmean(_err(res.normals, n)) < 0.05
    h = integrate_normals(res.normals, pixel_size_um=PX).height_um
    truth = z * 1000 - np.median(z * 1000)
    assert np.abs((h - h[~inside].mean()) - (truth - truth[~inside].mean())).max() < 0.05 * 80
