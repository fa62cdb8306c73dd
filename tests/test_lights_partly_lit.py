"""Lamps that light part of the field (a dome's low lamps): the sphere-free light estimate uses, per pixel,
the lamps that light it (uvps.core.lights.PixelSample.W, uvps.core.flatfield._fit_partly_lit)."""
import numpy as np
import pytest

from uvps.core.flatfield import block_grid, fit_dropoffs
from uvps.core.lights import (LightModel, PixelSample, estimate_lights, photometric_residual, pixel_coordinates_mm,
                              refine_intensities, sample_pixels)
from uvps.core.stereo import solve_normals
from uvps.errors import UVPSInputError
from uvps.testing.synthetic import make_capture, render_images

PX = 80.0                      # a 24 x 32 mm field: wide enough for the near-light geometry to be resolved
LOW = [(10, 6, 300), (100, 9, 350), (190, 12, 280), (280, 14, 320)]       # azimuth, elevation (deg), mm


def _pos(az, el, d):
    a, e = np.radians(az), np.radians(el)
    return d * np.array([np.cos(e) * np.cos(a), np.cos(e) * np.sin(a), np.sin(e)])


def _angles(a, b):
    a = a / np.linalg.norm(a, axis=1, keepdims=True)
    b = b / np.linalg.norm(b, axis=1, keepdims=True)
    return np.degrees(np.arccos(np.clip((a * b).sum(1), -1, 1)))


@pytest.fixture(scope="module")
def dome():
    """8 lamps at 20-60 deg plus 4 at 6-14 deg; each low lamp leaves the fifth of the field farthest from it
    dark (0: the dome's rim hides it) and one saturates a corner, so no pixel is lit by every lamp."""
    cap = make_capture(shape=(300, 400), n_lights=8, seed=3, rgb=False, pixel_size_um=PX)
    P = np.concatenate([cap.light_positions_mm, np.stack([_pos(*lamp) for lamp in LOW])])
    images = render_images(cap.height_um, cap.albedo, pixel_size_um=PX, light_positions_mm=P,
                           rng=1).astype(np.float32)
    rows, cols = np.mgrid[0:300, 0:400]
    x, y = cols - 200, 150 - rows
    for k, (az, _, _) in zip(range(8, 12), LOW):
        a = np.radians(az)
        images[k][(x * np.cos(a) + y * np.sin(a)) < -110] = 0
    images[9][:120, :150] = 65535
    return cap, P, images


def test_no_pixel_is_lit_by_every_lamp_yet_the_lamps_and_normals_are_estimated(dome):
    cap, P, images = dome
    grid = block_grid(images, saturation=65535)
    fits = fit_dropoffs(grid, degree=4)
    sample = sample_pixels(images, fits, saturation=65535, pixel_size_um=PX, n=4000)
    assert sample.W is not None and sample.W.sum(axis=0).min() >= 5
    assert np.all(sample.I[sample.W == 0] == 0)
    est = estimate_lights(grid, fits, sample, pixel_size_um=PX)
    err = _angles(est.model.positions_mm, P)
    # measured 0.26-2.65 deg (low lamps 0.72-1.36); with every lamp's pixels required, refused; with the
    # drop-off fits on the blocks every lamp lights, 17-78 deg
    assert err.max() < 3.5, err
    assert err[8:].max() < 2.0, err
    n = solve_normals(images, est.model, pixel_size_um=PX, saturation=65535).normals
    nerr = np.degrees(np.arccos(np.clip((n * cap.normals).sum(-1), -1, 1)))
    assert np.nanmean(nerr) < 0.5                               # measured 0.26 deg


def test_a_masked_pixel_is_the_same_as_the_pixel_under_its_lit_lamps_alone():
    rng = np.random.default_rng(0)
    P = np.stack([_pos(az, el, 300) for az, el in zip(range(0, 360, 45), [20, 30, 40, 50, 25, 35, 45, 55])])
    model = LightModel.from_positions(P, 0.9 + 0.2 * rng.random(8))
    r, c = rng.integers(0, 200, 400), rng.integers(0, 300, 400)
    X = pixel_coordinates_mm(r, c, (200, 300), 50.0)
    n = rng.normal(size=(400, 3)) * [0.2, 0.2, 1] + [0, 0, 3]
    I = np.einsum("kpi,pi->kp", model.vectors(X), n) * (1 + 0.01 * rng.standard_normal((8, 400)))
    lit = [0, 2, 3, 5, 6]
    W = np.zeros((8, 400))
    W[lit] = 1
    masked = photometric_residual(PixelSample(I * W, X, r, c, W), model).reshape(8, 400)
    alone = photometric_residual(PixelSample(I[lit], X, r, c), LightModel.from_positions(P[lit], model.intensities[lit]))
    np.testing.assert_allclose(masked[lit], alone.reshape(5, 400), rtol=1e-9, atol=1e-12)
    assert np.all(masked[[1, 4, 7]] == 0)
    # the intensity estimate with the positions known recovers the intensities from each pixel's lit lamps
    W = (rng.random((8, 400)) < 0.7).astype(float)
    W[:5, W.sum(axis=0) < 5] = 1
    E = refine_intensities(PixelSample(I * W, X, r, c, W), P)
    np.testing.assert_allclose(E / np.median(E), model.intensities / np.median(model.intensities), rtol=0.03)


def test_an_image_lighting_too_little_of_the_field_is_named(dome):
    cap, P, images = dome
    images = images.copy()
    images[10][:, 12:] = 0                                      # lamp 11 lights only a sliver
    with pytest.raises(UVPSInputError, match=r"too few blocks lit by some images.*image \(lit blocks\): 11 \("):
        fit_dropoffs(block_grid(images, saturation=65535), degree=4)


def test_a_masked_partly_lit_capture_fits_its_dropoffs_without_a_warning(dome):
    """Blocks the mask leaves out are lit by no lamp in the partly-lit fits: no "Mean of empty slice" warning
    (an error under the suite's filters), and the fits on the rest agree with the unmasked capture's."""
    _, _, images = dome
    mask = np.ones(images.shape[1:], bool)
    mask[:, :30] = False
    grid = block_grid(images, saturation=65535, mask=mask)
    assert (grid.valid.sum(axis=0) == 0).any()            # blocks no lamp lights: the case in question
    fits = fit_dropoffs(grid, degree=4)
    whole = fit_dropoffs(block_grid(images, saturation=65535), degree=4)
    inside = grid.valid.any(axis=0)
    diff = max(np.abs(a.log_evaluate(grid.rows, grid.cols) - b.log_evaluate(grid.rows, grid.cols))[inside].max()
               for a, b in zip(fits, whole))
    assert diff < 0.05, diff                                  # measured 0.028 (the fits' edge, 30 px less field)
