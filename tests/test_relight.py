"""Tests of uvps.core.relight with planes whose rendering is known in closed form.

Frame (docs/architecture.md): x = column direction, y UP (decreasing row), z toward the camera.
Azimuth counter-clockwise from +x: 0 = light from the right, 90 = from the image top.
"""

import numpy as np
import pytest

from uvps.errors import UVPSInputError
from uvps.core.relight import hillshade, light_direction, relight

SHAPE = (12, 16)


def plane_normals(p, q, shape=SHAPE):
    """Normals of the plane z = p x + q y: n = (-p, -q, 1) / norm."""
    n = np.array([-p, -q, 1.0]) / np.sqrt(1 + p * p + q * q)
    return np.broadcast_to(n, shape + (3,)).astype(np.float32)


def normals_of_height(z):
    """Normals from a height map given on the pixel grid (rows down, y up), pixel = 1."""
    dz_drow, dz_dcol = np.gradient(z)
    p, q = dz_dcol, -dz_drow
    n = np.stack([-p, -q, np.ones_like(p)], axis=-1)
    return (n / np.linalg.norm(n, axis=-1, keepdims=True)).astype(np.float32)


@pytest.mark.parametrize("elevation", [5.0, 15.0, 45.0, 90.0])
@pytest.mark.parametrize("azimuth", [0.0, 137.0, 315.0])
def test_flat_surface_is_albedo_times_sin_elevation(elevation, azimuth):
    rng = np.random.default_rng(1)
    albedo = rng.uniform(0.1, 1.0, size=SHAPE + (3,)).astype(np.float32)
    img = relight(plane_normals(0.0, 0.0), albedo, azimuth_deg=azimuth, elevation_deg=elevation)
    assert img.shape == albedo.shape and img.dtype == np.float32
    np.testing.assert_allclose(img, albedo * np.sin(np.radians(elevation)), rtol=1e-5, atol=1e-7)
    grey = relight(plane_normals(0.0, 0.0), albedo[..., 0], elevation_deg=elevation)
    assert grey.shape == SHAPE
    np.testing.assert_allclose(grey, albedo[..., 0] * np.sin(np.radians(elevation)), rtol=1e-5)


def test_tilted_plane_matches_cosine_law():
    p, q = 0.3, -0.2
    img = hillshade(plane_normals(p, q), azimuth_deg=30.0, elevation_deg=20.0)
    n = np.array([-p, -q, 1.0]) / np.sqrt(1 + p * p + q * q)
    az, el = np.radians(30.0), np.radians(20.0)
    light = np.array([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)])
    np.testing.assert_allclose(img, n @ light, rtol=1e-5)
    np.testing.assert_allclose(light_direction(30.0, 20.0), light, atol=1e-12)


@pytest.mark.parametrize(
    "azimuth, toward",
    [
        (0.0, np.array([0.0, 1.0])),  # light from the right: faces whose height grows with column
        (90.0, np.array([-1.0, 0.0])),  # from the image top: height grows toward row 0
        (180.0, np.array([0.0, -1.0])),  # from the left
        (270.0, np.array([1.0, 0.0])),  # from the image bottom
    ],
)
def test_azimuth_convention_with_planes_built_from_heights(azimuth, toward):
    # A plane facing the light descends toward it: its height grows *away* from the light.
    # `toward` = (d row, d col) pointing to where the light is on the image.
    r, c = np.mgrid[: SHAPE[0], : SHAPE[1]].astype(float)
    facing = normals_of_height(-0.4 * (toward[0] * r + toward[1] * c))
    away = normals_of_height(+0.4 * (toward[0] * r + toward[1] * c))
    albedo = np.full(SHAPE, 0.8, np.float32)
    lit = relight(facing, albedo, azimuth_deg=azimuth, elevation_deg=15.0)
    dark = relight(away, albedo, azimuth_deg=azimuth, elevation_deg=15.0)
    flat = 0.8 * np.sin(np.radians(15.0))
    assert np.all(lit > flat) and np.all(dark < flat)
    # Tilt 0.4 toward a 15-degree light: n . l = (0.4 cos 15 + sin 15) / sqrt(1.16).
    expected = 0.8 * (0.4 * np.cos(np.radians(15)) + np.sin(np.radians(15))) / np.sqrt(1.16)
    np.testing.assert_allclose(lit, expected, rtol=1e-5)


def test_shadowed_faces_get_only_ambient():
    albedo = np.full(SHAPE, 0.5, np.float32)
    steep_away = plane_normals(2.0, 0.0)  # faces -x, light from +x at 10 degrees
    assert relight(steep_away, albedo, azimuth_deg=0.0, elevation_deg=10.0).max() == 0.0
    img = relight(steep_away, albedo, azimuth_deg=0.0, elevation_deg=10.0, ambient=0.1)
    np.testing.assert_allclose(img, 0.05, rtol=1e-6)
    flat = relight(plane_normals(0, 0), albedo, elevation_deg=30.0, ambient=0.1)
    np.testing.assert_allclose(flat, 0.5 * (0.5 + 0.1), rtol=1e-6)


def test_nan_normals_give_nan_and_inputs_unchanged():
    normals = plane_normals(0.1, 0.2).copy()
    normals[3, 4] = np.nan
    normals[5, 6] = 0.0  # zero length: no direction
    albedo = np.full(SHAPE + (3,), 0.7, np.float32)
    before_n, before_a = normals.copy(), albedo.copy()
    img = relight(normals, albedo, ambient=0.2)
    assert np.all(np.isnan(img[3, 4])) and np.all(np.isnan(img[5, 6]))
    assert np.isfinite(img).sum() == img.size - 6
    np.testing.assert_array_equal(normals, before_n)
    np.testing.assert_array_equal(albedo, before_a)


def test_non_unit_normals_are_normalised_and_hillshade_is_albedo_one():
    n = plane_normals(0.2, 0.1)
    a = hillshade(n, azimuth_deg=200.0, elevation_deg=25.0)
    b = hillshade(3.0 * n, azimuth_deg=200.0, elevation_deg=25.0)
    np.testing.assert_allclose(a, b, rtol=1e-6)
    c = relight(n, np.ones(SHAPE), azimuth_deg=200.0, elevation_deg=25.0)
    np.testing.assert_allclose(a, c, rtol=1e-6)


@pytest.mark.parametrize(
    "kwargs, albedo_shape, match",
    [
        ({"elevation_deg": 95.0}, SHAPE, "elevation_deg"),
        ({"elevation_deg": -1.0}, SHAPE, "elevation_deg"),
        ({"azimuth_deg": float("nan")}, SHAPE, "azimuth_deg"),
        ({"ambient": -0.1}, SHAPE, "ambient"),
        ({}, (SHAPE[0], SHAPE[1] + 1), "albedo"),
    ],
)
def test_bad_input_raises_clear_error(kwargs, albedo_shape, match):
    with pytest.raises(UVPSInputError, match=match):
        relight(plane_normals(0, 0), np.ones(albedo_shape), **kwargs)


def test_bad_normals_shape():
    with pytest.raises(UVPSInputError, match="normals"):
        hillshade(np.zeros((3,) + SHAPE, np.float32))


def test_integer_albedo_gives_float32_counts():
    albedo = np.full(SHAPE, 40000, np.uint16)
    img = relight(plane_normals(0, 0), albedo, elevation_deg=30.0)
    assert img.dtype == np.float32
    np.testing.assert_allclose(img, 20000.0, rtol=1e-6)
