"""Tests of uvps.core.integrate on analytic surfaces with exact normals.

Frame (docs/architecture.md): x = column direction, y UP (decreasing row), z toward the camera,
p = dz/dx, q = dz/dy, n = (-p, -q, 1) / norm. Surfaces are defined in pixel units on the pixel
centres and scaled by the pixel size, so the expected height in um is known exactly.
"""

import numpy as np
import pytest

from uvps.errors import UVPSInputError
from uvps.core.integrate import (
    Gradients,
    IntegrationResult,
    dct_poisson,
    frankot_chellappa,
    gradients_from_normals,
    integrate_normals,
)

PX_UM = 3.0
SOLVERS = {"fc": frankot_chellappa, "dct": dct_poisson}
# Largest error allowed, as a fraction of the height range, on smooth non-periodic surfaces:
# (interior = more than 5 px from the borders, whole image). FC uses the spectral derivative
# and rings slightly where the mirrored surface has a kink at a border; DCT-Poisson is exact
# for quadratics up to float32 rounding.
TOL = {"fc": (0.005, 0.01), "dct": (0.0005, 0.0005)}


def _xy(shape):
    """x (toward increasing column) and y (toward decreasing row) of pixel centres, in px."""
    M, N = shape
    r, c = np.mgrid[:M, :N].astype(float)
    return c - (N - 1) / 2, (M - 1) / 2 - r


def tilted_plane(shape):
    x, y = _xy(shape)
    return 0.3 * x + 0.5 * y, np.full(shape, 0.3), np.full(shape, 0.5)


def tilted_paraboloid(shape):
    """A dome-shaped paraboloid on a tilted plane: non-periodic, slope not zero at the borders."""
    x, y = _xy(shape)
    z = 0.2 * x - 0.1 * y + 12.0 * (1 - (x**2 + y**2) / 50.0**2)
    return z, 0.2 - 24.0 * x / 50.0**2, -0.1 - 24.0 * y / 50.0**2


def sphere_dome(shape, radius=150.0):
    """The top of a sphere of radius 150 px covering the whole image."""
    x, y = _xy(shape)
    s = np.sqrt(radius**2 - x**2 - y**2)
    return s, -x / s, -y / s


def sphere_cap_on_flat(shape, base_radius=25.0, cap_height=8.0):
    """A spherical cap (a bump) on a flat canvas; the slope jumps at its rim."""
    x, y = _xy(shape)
    R = (base_radius**2 + cap_height**2) / (2 * cap_height)
    rho2 = x**2 + y**2
    inside = rho2 < base_radius**2
    s = np.sqrt(np.maximum(R**2 - rho2, 1e-12))
    z = np.where(inside, s - (R - cap_height), 0.0)
    return z, np.where(inside, -x / s, 0.0), np.where(inside, -y / s, 0.0)


def normals_from_gradients(p, q):
    n = np.stack([-p, -q, np.ones_like(p)], axis=-1)
    return (n / np.linalg.norm(n, axis=-1, keepdims=True)).astype(np.float32)


def expected_um(z_px, valid=None):
    z = z_px * PX_UM
    return z - np.median(z if valid is None else z[valid])


SURFACES = {"plane": tilted_plane, "paraboloid": tilted_paraboloid, "sphere": sphere_dome}


@pytest.mark.parametrize("method", ["fc", "dct"])
@pytest.mark.parametrize("surface", sorted(SURFACES))
@pytest.mark.parametrize("shape", [(96, 128), (81, 67)])
def test_reconstructs_smooth_non_periodic_surfaces(method, surface, shape):
    z, p, q = SURFACES[surface](shape)
    result = integrate_normals(normals_from_gradients(p, q), pixel_size_um=PX_UM, method=method)
    assert isinstance(result, IntegrationResult)
    assert result.method == method
    assert result.height_um.shape == shape and result.height_um.dtype == np.float32
    err = np.abs(result.height_um - expected_um(z))
    span = np.ptp(z) * PX_UM
    tol_interior, tol_all = TOL[method]
    assert err[5:-5, 5:-5].max() < tol_interior * span
    assert err.max() < tol_all * span
    assert result.integrability < 1e-3
    assert result.residual_rms < 0.02


@pytest.mark.parametrize("method", ["fc", "dct"])
def test_bump_is_positive_toward_the_camera(method):
    shape = (80, 90)
    z, p, q = sphere_cap_on_flat(shape)
    result = SOLVERS[method](p, q, pixel_size_um=PX_UM)
    h = result.height_um
    apex = h[shape[0] // 2, shape[1] // 2]
    # Flat canvas around the bump is at the median (0): the apex is +8 px * 3 um high.
    assert apex == pytest.approx(8.0 * PX_UM, rel=0.03)
    assert abs(h[0, 0]) < 0.03 * 8.0 * PX_UM
    # The slope jumps at the rim, so the error there is larger, but bounded (5 % of the height).
    assert np.abs(h - expected_um(z)).max() < 0.05 * 8.0 * PX_UM


def test_gradients_sign_convention():
    shape = (60, 30)
    # A plane rising toward the image top (decreasing row) by 0.4 um per um.
    n_up = normals_from_gradients(np.zeros(shape), np.full(shape, 0.4))
    assert n_up[..., 1].max() < 0  # normal leans toward -y (down the image)
    g = gradients_from_normals(n_up)
    assert isinstance(g, Gradients)
    assert g.p.dtype == np.float32 and g.q.dtype == np.float32
    np.testing.assert_allclose(g.q, 0.4, rtol=1e-5)
    np.testing.assert_allclose(g.p, 0.0, atol=1e-6)
    h = frankot_chellappa(g.p, g.q, pixel_size_um=PX_UM).height_um
    assert np.all(np.diff(h, axis=0) < 0)  # higher at row 0 (image top)
    drop = h[0] - h[-1]  # FC rings near the borders (of the slope), not of the total drop
    np.testing.assert_allclose(drop, 0.4 * PX_UM * (shape[0] - 1), rtol=0.01)
    # A plane rising toward increasing column: p > 0, height grows with column.
    g = gradients_from_normals(normals_from_gradients(np.full(shape, 0.25), np.zeros(shape)))
    np.testing.assert_allclose(g.p, 0.25, rtol=1e-5)
    h = dct_poisson(g.p, g.q, pixel_size_um=PX_UM).height_um
    np.testing.assert_allclose(np.diff(h, axis=1), 0.25 * PX_UM, rtol=1e-3)


def test_gradients_clamp_steep_and_flag_invalid_normals(caplog):
    shape = (6, 7)
    n = normals_from_gradients(np.full(shape, 0.1), np.zeros(shape))
    n[1, 1] = [1.0, 0.0, 0.0]  # grazing: slope infinite
    n[2, 2] = [0.0, 0.6, -0.8]  # facing away from the camera
    n[3, 3] = [np.nan, 0.0, 1.0]
    n[4, 4] = [0.0, 0.0, -1.0]  # no direction at all
    before = n.copy()
    g = gradients_from_normals(n, max_slope=5.0)
    np.testing.assert_array_equal(n, before)
    assert g.n_clamped == 2 and g.n_invalid == 2
    assert g.invalid[3, 3] and g.invalid[4, 4] and g.invalid.sum() == 2
    assert g.p[1, 1] == pytest.approx(-5.0) and g.q[1, 1] == pytest.approx(0.0)
    assert g.p[2, 2] == pytest.approx(0.0) and g.q[2, 2] == pytest.approx(-5.0)
    assert g.p[3, 3] == 0 and g.q[3, 3] == 0 and g.p[4, 4] == 0
    assert np.all(np.isfinite(g.p)) and np.all(np.isfinite(g.q))
    np.testing.assert_allclose(g.p[0], 0.1, rtol=1e-5)  # untouched pixels: p = -nx/nz
    assert "non-finite or degenerate" in caplog.text


@pytest.mark.parametrize("method", ["fc", "dct"])
def test_nan_normals_are_zero_gradient_and_counted(method):
    shape = (64, 72)
    z, p, q = tilted_paraboloid(shape)
    n = normals_from_gradients(p, q)
    rng = np.random.default_rng(7)
    holes = rng.choice(n.shape[0] * n.shape[1], size=12, replace=False)
    n.reshape(-1, 3)[holes] = np.nan
    g = gradients_from_normals(n)
    assert g.n_invalid == 12 and g.invalid.sum() == 12
    assert np.all(g.p.reshape(-1)[holes] == 0) and np.all(g.q.reshape(-1)[holes] == 0)
    result = integrate_normals(n, pixel_size_um=PX_UM, method=method)
    assert result.n_invalid == 12
    assert np.all(np.isfinite(result.height_um))
    ok = np.ones(shape, bool)
    ok.reshape(-1)[holes] = False
    assert np.median(result.height_um[ok]) == pytest.approx(0.0, abs=1e-4)
    # A few isolated holes integrated as flat leave the shape within 2 % of its range.
    err = np.abs(result.height_um - expected_um(z))
    assert np.median(err) < 0.02 * np.ptp(z) * PX_UM


@pytest.mark.parametrize("method", ["fc", "dct"])
def test_median_is_zero_and_nan_outside_mask(method):
    shape = (60, 70)
    z, p, q = sphere_dome(shape)
    result = SOLVERS[method](p, q, pixel_size_um=PX_UM)
    assert np.median(result.height_um) == pytest.approx(0.0, abs=1e-4)

    # A bump on a flat canvas; the mask leaves out a band of wild gradients on the right.
    z, p, q = sphere_cap_on_flat(shape, base_radius=15.0, cap_height=6.0)
    rng = np.random.default_rng(11)
    p[:, 55:] = rng.normal(0, 3, size=(shape[0], 15))
    q[:, 55:] = np.nan
    mask = np.ones(shape, bool)
    mask[:, 55:] = False
    masked = SOLVERS[method](p, q, pixel_size_um=PX_UM, mask=mask)
    assert masked.n_invalid == 0  # the NaNs are outside the mask
    h = masked.height_um
    assert np.all(np.isnan(h[~mask])) and np.all(np.isfinite(h[mask]))
    assert np.median(h[mask]) == pytest.approx(0.0, abs=1e-4)
    err = np.abs(h[mask] - expected_um(z, mask)[mask])
    assert err.max() < 0.05 * 6.0 * PX_UM


def test_reflect_padding_avoids_wrap_around():
    shape = (64, 80)
    z, p, q = tilted_plane(shape)
    span = np.ptp(z) * PX_UM
    good = frankot_chellappa(p, q, pixel_size_um=PX_UM, pad="reflect")
    periodic = frankot_chellappa(p, q, pixel_size_um=PX_UM, pad="none")
    assert np.abs(good.height_um - expected_um(z)).max() < 0.01 * span
    # Without padding, a plane is not periodic: its mean slope is lost to the DC term.
    assert np.abs(periodic.height_um - expected_um(z)).max() > 0.3 * span


@pytest.mark.parametrize("method", ["fc", "dct"])
def test_height_scales_with_pixel_size(method):
    z, p, q = tilted_paraboloid((40, 50))
    h1 = SOLVERS[method](p, q, pixel_size_um=1.0).height_um
    h15 = SOLVERS[method](p, q, pixel_size_um=15.0).height_um
    np.testing.assert_allclose(h15, 15.0 * h1, rtol=1e-4, atol=1e-3)


def test_inputs_not_modified_and_float64_accepted():
    z, p, q = tilted_paraboloid((30, 40))
    p[0, 0] = np.nan
    p_before, q_before = p.copy(), q.copy()
    for solver in SOLVERS.values():
        result = solver(p, q, pixel_size_um=PX_UM)
        assert result.n_invalid == 1
    np.testing.assert_array_equal(p, p_before)
    np.testing.assert_array_equal(q, q_before)


def test_diagnostics_detect_non_integrable_field():
    shape = (48, 64)
    z, p, q = tilted_paraboloid(shape)
    clean = dct_poisson(p, q, pixel_size_um=PX_UM)
    noise = np.random.default_rng(3).normal(0, 0.2, size=(2,) + shape)
    noisy = dct_poisson(p + noise[0], q + noise[1], pixel_size_um=PX_UM)
    assert clean.integrability < 1e-6
    assert noisy.integrability > 0.1
    assert clean.residual_rms < 0.01
    # Least squares keeps the integrable part: about half the noise power stays in the residual.
    assert 0.1 < noisy.residual_rms < 0.3


def test_fc_and_dct_agree():
    z, p, q = sphere_dome((70, 90))
    n = normals_from_gradients(p, q)
    fc = integrate_normals(n, pixel_size_um=PX_UM, method="fc").height_um
    dct = integrate_normals(n, pixel_size_um=PX_UM, method="dct").height_um
    assert np.abs(fc - dct).max() < 0.01 * np.ptp(z) * PX_UM


@pytest.mark.parametrize(
    "call, match",
    [
        (lambda p, n: frankot_chellappa(p, p, pixel_size_um=0), "pixel_size_um"),
        (lambda p, n: dct_poisson(p, p, pixel_size_um="abc"), "pixel_size_um"),
        (lambda p, n: frankot_chellappa(p, p[:, :-1], pixel_size_um=1), "same shape"),
        (lambda p, n: frankot_chellappa(p, p, pixel_size_um=1, pad="zero"), "pad"),
        (lambda p, n: dct_poisson(p[0], p[0], pixel_size_um=1), "2-D"),
        (lambda p, n: dct_poisson(p, p, pixel_size_um=1, mask=np.ones((3, 3), bool)), "mask"),
        (lambda p, n: dct_poisson(p, p, pixel_size_um=1, mask=np.zeros(p.shape, bool)), "mask"),
        (lambda p, n: integrate_normals(n, pixel_size_um=1, method="poisson"), "method"),
        (lambda p, n: integrate_normals(n[..., :2], pixel_size_um=1), "normals"),
        (lambda p, n: gradients_from_normals(n, max_slope=-1), "max_slope"),
    ],
)
def test_bad_input_raises_clear_error(call, match):
    p = np.zeros((8, 9), np.float32)
    n = normals_from_gradients(p, p)
    with pytest.raises(UVPSInputError, match=match):
        call(p, n)


def _mirrored(p, q):
    """The gradients' (2M, 2N) even extension of the height, float64 (frankot_chellappa's notes)."""
    M, N = p.shape
    gc = np.empty((2 * M, 2 * N))
    gc[:M, :N], gc[:M, N:] = p, -p[:, ::-1]
    gc[M:] = gc[M - 1::-1]
    gr = np.empty((2 * M, 2 * N))
    gr[:M, :N], gr[:M, N:] = -q, -q[:, ::-1]
    gr[M:] = -gr[M - 1::-1]
    return gc, gr


def _fc_fft64(p, q, *, half_spectrum):
    """Frankot-Chellappa on the mirrored field by FFT in float64: the real part of the full inverse
    transform, or (``half_spectrum``) the irfft2 of the non-negative column frequencies, as uvps
    computed it before the cosine-transform form."""
    import scipy.fft

    M, N = p.shape
    gc, gr = _mirrored(p.astype(np.float64), q.astype(np.float64))
    fwd, inv, colfreq = ((scipy.fft.rfft2, lambda Z: scipy.fft.irfft2(Z, s=(2 * M, 2 * N)), scipy.fft.rfftfreq)
                         if half_spectrum else (scipy.fft.fft2, lambda Z: scipy.fft.ifft2(Z).real, scipy.fft.fftfreq))
    wc = 2 * np.pi * colfreq(2 * N)[None, :]
    wr = 2 * np.pi * scipy.fft.fftfreq(2 * M)[:, None]
    denom = wc ** 2 + wr ** 2
    denom[0, 0] = 1
    Z = (-1j * wc * fwd(gc) - 1j * wr * fwd(gr)) / denom
    Z[0, 0] = 0
    return inv(Z)[:M, :N]


def _row_nyquist_term(q):
    """What the irfft2 of the half spectrum adds to the full transform's real part: the rows'
    Nyquist frequency (-1)^r, whose column spectrum the half spectrum takes as Hermitian."""
    import scipy.fft

    M, N = q.shape
    sign = (-1.0) ** np.arange(M)
    D = scipy.fft.dct(2 * (sign[:, None] * -q.astype(np.float64)).sum(axis=0), type=2)
    k = np.arange(1, N)
    wc = np.pi * k / N
    S = (D[1:] * np.pi / (np.pi ** 2 + wc ** 2)) @ np.sin(np.pi * k[:, None] * (np.arange(N)[None, :] + 0.5) / N)
    return -sign[:, None] * S[None, :] / (2 * M * N)


@pytest.mark.parametrize("shape", [(40, 56), (33, 47), (2, 5), (7, 2)])
def test_fc_equals_the_fft_of_the_mirrored_field_in_float64(shape):
    """The cosine-transform form is the mirrored field's FFT projection (float32 against float64);
    the earlier irfft2 form is that plus its row-Nyquist term, and nothing else. Worst case for
    float32: white-noise gradients (no smooth surface to hide the rounding)."""
    rng = np.random.default_rng(7)
    p, q = rng.normal(size=(2,) + shape).astype(np.float32)
    new = frankot_chellappa(p, q, pixel_size_um=1.0).height_um
    full = _fc_fft64(p, q, half_spectrum=False)
    np.testing.assert_allclose(new, full - np.median(full), rtol=0, atol=1e-6 * np.ptp(full))
    earlier = _fc_fft64(p, q, half_spectrum=True)
    np.testing.assert_allclose(earlier, full + _row_nyquist_term(q), rtol=0, atol=1e-12 * np.ptp(full))


def test_fc_on_a_relief_equals_the_earlier_float64_result():
    """On a relief (dome, tilt and noise, 1 % of the normals NaN) the height equals the earlier
    float64 irfft2 result within float32 precision once its row-Nyquist term is set aside, and
    the term itself is below 1e-4 of the height range."""
    z, p, q = sphere_dome((90, 120))
    rng = np.random.default_rng(2)
    p = p + 0.3 + rng.normal(0, 0.05, p.shape)
    q = q - 0.1 + rng.normal(0, 0.05, q.shape)
    n = normals_from_gradients(p, q)
    n[rng.random(p.shape) < 0.01] = np.nan
    res = integrate_normals(n, pixel_size_um=1.0, method="fc")
    g = gradients_from_normals(n)
    earlier = _fc_fft64(g.p, g.q, half_spectrum=True) - _row_nyquist_term(g.q)
    earlier -= np.median(earlier[~g.invalid])
    np.testing.assert_allclose(res.height_um, earlier, rtol=0, atol=1e-6 * np.ptp(earlier))
    assert np.abs(_row_nyquist_term(g.q)).max() < 1e-4 * np.ptp(earlier)


@pytest.mark.parametrize("method", ["fc", "dct"])
def test_bands_change_nothing(method, monkeypatch):
    """Gradients, heights and diagnostics computed in bands of one row = in one band."""
    import uvps.core.integrate

    z, p, q = sphere_dome((30, 41))
    rng = np.random.default_rng(4)
    n = normals_from_gradients(p + rng.normal(0, 0.1, p.shape), q + rng.normal(0, 0.1, q.shape))
    n[3, 4] = np.nan
    n[5, 6] = (0.999, 0, -0.01)                              # steep: clamped
    mask = np.ones(p.shape, bool)
    mask[:, :3] = False
    whole = integrate_normals(n, pixel_size_um=PX_UM, method=method, mask=mask)
    g_whole = gradients_from_normals(n, mask=mask)
    monkeypatch.setattr(uvps.core.integrate, "BAND_PIXELS", 1)
    banded = integrate_normals(n, pixel_size_um=PX_UM, method=method, mask=mask)
    g = gradients_from_normals(n, mask=mask)
    for a, b in ((g.p, g_whole.p), (g.q, g_whole.q), (g.invalid, g_whole.invalid),
                 (banded.height_um, whole.height_um)):
        np.testing.assert_array_equal(a, b)
    assert (g.n_invalid, g.n_clamped) == (g_whole.n_invalid, g_whole.n_clamped) == (1, 1)
    assert banded.residual_rms == pytest.approx(whole.residual_rms, rel=1e-12)
    assert banded.integrability == pytest.approx(whole.integrability, rel=1e-12)


def _domes_and_a_crack(seed=0, shape=(240, 320), px=15.0):
    """Gaussian domes 40-160 um wide on a flat canvas, noisy gradients, and a wavy crack across the field whose
    gradients are wrong (as photometric stereo's are on a crack's grazed walls): (p, q, true
    height um, dome mask, crack mask)."""
    rng = np.random.default_rng(seed)
    M, N = shape
    rr, cc = np.mgrid[0:M, 0:N].astype(float)
    h = np.zeros(shape)
    domes = np.zeros(shape, bool)
    crack_row = M / 2 + 12 * np.sin(cc / 37.0)
    crack = np.abs(rr - crack_row) <= 1.0
    for _ in range(25):
        r0, c0 = rng.uniform(10, M - 10), rng.uniform(10, N - 10)
        if np.abs(r0 - (M / 2 + 12 * np.sin(c0 / 37.0))) < 20:
            continue
        s = rng.uniform(40, 160) / px / 4
        bump = rng.uniform(8, 30) * np.exp(-((rr - r0) ** 2 + (cc - c0) ** 2) / (2 * s * s))
        h += bump
        domes |= bump > 0.1 * bump.max()
    dz_dc = np.gradient(h, axis=1) / px
    dz_dr = np.gradient(h, axis=0) / px
    p, q = dz_dc + rng.normal(0, 0.005, shape), -dz_dr + rng.normal(0, 0.005, shape)    # normals' noise ~0.3 deg
    p[crack] += rng.normal(0, 0.6, crack.sum())
    q[crack] += rng.normal(0, 0.6, crack.sum())
    return p.astype(np.float32), q.astype(np.float32), h, domes, crack


@pytest.mark.parametrize("seed", [0, 1])
def test_nonintegrable_patches_find_a_crack_and_leave_the_domes(seed):
    """The crack's wrong gradients (curl far above the field's) form one patch across the field; the
    domes' rims, whose discrete curl is not zero either, are shorter than the widest protrusion. Left
    out, the domes' heights come back where the crack's spread relief had moved them."""
    from uvps.core.integrate import nonintegrable_patches

    px = 15.0
    p, q, h, domes, crack = _domes_and_a_crack(seed, px=px)
    out = nonintegrable_patches(p, q, min_extent_px=1000.0 / px)
    assert out[crack].mean() > 0.75
    assert out[domes].mean() < 0.01
    assert not nonintegrable_patches(p, q, min_extent_px=1e4).any()        # nothing that long

    def dome_error(pp, qq):
        z = frankot_chellappa(pp, qq, pixel_size_um=px).height_um
        z = z - np.median(z[~domes & ~crack]) + np.median(h[~domes & ~crack])
        return np.median(np.abs(z - h)[domes])

    # the error of the true gradients' own height (central differences) is the floor
    floor = dome_error(np.gradient(h, axis=1) / px, -np.gradient(h, axis=0) / px)
    left_out, kept = dome_error(np.where(out, 0, p), np.where(out, 0, q)), dome_error(p, q)
    assert left_out - floor < 0.35 * (kept - floor), (floor, left_out, kept)


def test_nonintegrable_patches_leave_a_clean_field_alone():
    """On a noise-free field the curl's robust spread is near zero, so the relative threshold alone
    would take the discretisation curl of any sharp feature for a non-integrable patch: the floor
    (``CURL_FLOOR``, slope per pixel) leaves a clean field's gradients, long ridges included, alone,
    while the crack's wrong gradients still stand far above it."""
    from uvps.core.integrate import CURL_FLOOR, nonintegrable_patches

    px = 15.0
    rr, cc = np.mgrid[0:240, 0:320].astype(float)
    # a long wavy ridge (a stroke 20 um high, 8 px wide) across the field and a steep dome, their
    # exact slopes (as a renderer's normals are): the discrete curl is not zero where they bend
    u = rr - 120 - 10 * np.sin(cc / 30.0)
    ridge = 20.0 * np.exp(-u ** 2 / (2 * 4.0 ** 2))
    dome = 40.0 * np.exp(-((rr - 60) ** 2 + (cc - 80) ** 2) / (2 * 3.0 ** 2))
    dz_dr = -u / 16.0 * ridge - (rr - 60) / 9.0 * dome
    dz_dc = u / 16.0 * ridge * (10 / 30.0) * np.cos(cc / 30.0) - (cc - 80) / 9.0 * dome
    p, q = dz_dc / px, -dz_dr / px
    curl = np.abs(-np.gradient(p, axis=0) - np.gradient(q, axis=1))
    assert 1.4826 * np.median(curl) < 1e-3 * CURL_FLOOR < curl.max()    # what the floor is for
    assert not nonintegrable_patches(p, q, min_extent_px=1000.0 / px).any()
    assert nonintegrable_patches(p, q, min_extent_px=1000.0 / px, floor=0.0).any()   # without it
    p2, q2, _, _, crack = _domes_and_a_crack(0, px=px)
    assert nonintegrable_patches(p2, q2, min_extent_px=1000.0 / px)[crack].mean() > 0.75


def _patches_by_scikit_image(p, q, *, min_extent_px, k=None, floor=None, mask=None):
    """nonintegrable_patches as its docstring states it, by np.gradient on whole images and
    scikit-image's label and regionprops_table: the reference for the banded, OpenCV form."""
    from scipy import ndimage
    from skimage.measure import label, regionprops_table
    from uvps.core.integrate import CURL_FLOOR, CURL_OUTLIER_MAD

    k = CURL_OUTLIER_MAD if k is None else k
    floor = CURL_FLOOR if floor is None else floor
    p, q = np.nan_to_num(np.asarray(p, np.float32)), np.nan_to_num(np.asarray(q, np.float32))
    curl = np.abs(-np.gradient(p, axis=0) - np.gradient(q, axis=1))
    inside = np.ones(p.shape, bool) if mask is None else mask
    threshold = max(k * 1.4826 * float(np.median(curl[inside])), floor)
    lab = label((curl > threshold) & inside, connectivity=2)
    if lab.max() == 0:
        return np.zeros(p.shape, bool), curl
    props = regionprops_table(lab, properties=("label", "bbox"))
    extent = np.maximum(props["bbox-2"] - props["bbox-0"], props["bbox-3"] - props["bbox-1"])
    long = np.zeros(lab.max() + 1, bool)
    long[props["label"][extent >= min_extent_px]] = True
    return ndimage.binary_dilation(long[lab], structure=np.ones((3, 3), bool)) & inside, curl


def test_nonintegrable_patches_are_the_whole_image_form_to_the_bit():
    """The curl is made in bands of rows in threads, and the patches found by OpenCV's connected
    components: the same curl to the bit as np.gradient's on the whole images (NaN taken as 0, the
    image's first and last rows and columns one-sided), and the same patches as scikit-image's
    labels and boxes, with a mask, NaNs, bands of every remainder, and images of 2 rows."""
    from uvps.core.integrate import curl_magnitude, nonintegrable_patches

    rng = np.random.default_rng(8)
    p, q, _, _, crack = _domes_and_a_crack(1, px=15.0)
    cases = [(p, q, None, 1000.0 / 15.0, {}), (p, q, rng.random(p.shape) > 0.05, 20.0, {}),
             (p, q, None, 3.0, {"k": 2.0, "floor": 0.0})]
    for shape in ((2, 9), (3, 3), (257, 31), (513, 40), (600, 5)):
        a = rng.normal(size=shape).astype(np.float32)
        b = rng.normal(size=shape).astype(np.float32)
        a[rng.random(shape) < 0.05] = np.nan
        b[0, -1] = np.nan
        cases += [(a, b, None, 2.0, {"k": 1.5}), (a, b, rng.random(shape) > 0.3, 1.0, {"k": 1.0, "floor": 0.5})]
    found = 0
    for i, (a, b, mask, extent, kw) in enumerate(cases):
        want, curl = _patches_by_scikit_image(a, b, min_extent_px=extent, mask=mask, **kw)
        assert np.array_equal(curl_magnitude(a, b), curl), i
        assert np.array_equal(curl_magnitude(a, b, rows=7), curl), i
        got = nonintegrable_patches(a, b, min_extent_px=extent, mask=mask, **kw)
        assert got.dtype == bool and np.array_equal(got, want), i
        found += int(got.any())
    assert found >= 5                     # patches found, not only empty answers compared
    assert nonintegrable_patches(p, q, min_extent_px=1000.0 / 15.0)[crack].mean() > 0.75


def test_the_detections_height_leaves_the_crack_out_and_the_runs_height_is_kept():
    """``find_protrusions`` reads :func:`uvps.core.pipeline.detection_height`: with ``curl_k`` the normals
    integrated again without the crack's gradients (closer to the truth on the domes than the run's
    height, which keeps them; ``curl_k`` 15 is the default); the run's height itself without normals or
    with ``curl_k`` 0."""
    from uvps.core.detect import DetectionParams
    from uvps.core.pipeline import detection_height

    px = 15.0
    p, q, h, domes, crack = _domes_and_a_crack(1, px=px)
    n = np.stack([-p, -q, np.ones_like(p)], -1)
    n /= np.linalg.norm(n, axis=-1, keepdims=True)
    run_height = frankot_chellappa(p, q, pixel_size_um=px).height_um
    for normals, params in ((None, DetectionParams(curl_k=15)), (n, DetectionParams(curl_k=0))):  # none, off
        got = detection_height(run_height, normals, pixel_size_um=px, params=params)
        assert got.height_um is run_height and got.left_out is None
    assert DetectionParams().curl_k == 15
    clean = np.stack([-p * 0, -q * 0, np.ones_like(p)], -1)             # a flat field: nothing to leave out
    got = detection_height(run_height, clean, pixel_size_um=px, params=DetectionParams())
    assert got.height_um is run_height and got.left_out is None

    def dome_error(z):
        z = z - np.median(z[~domes & ~crack])
        return np.median(np.abs(z - h)[domes])

    got, left_out = detection_height(run_height, n, pixel_size_um=px, params=DetectionParams(curl_k=15))
    assert dome_error(got) < 0.5 * dome_error(run_height), (dome_error(got), dome_error(run_height))
    assert left_out[crack].mean() > 0.75 and not left_out[domes].any()


def test_find_protrusions_hands_the_left_out_patches_to_the_detector(monkeypatch):
    """A run's detection reads the height integrated without the crack's gradients and is told
    which pixels those are (``detect_protrusions(left_out=)``: the ``artefact`` rule's mismatch is
    measured away from them); without normals it is told nothing."""
    from uvps.core import pipeline
    from uvps.core.detect import DetectionParams

    px = 15.0
    p, q, h, domes, crack = _domes_and_a_crack(1, px=px)
    n = np.stack([-p, -q, np.ones_like(p)], -1)
    n /= np.linalg.norm(n, axis=-1, keepdims=True)
    run_height = frankot_chellappa(p, q, pixel_size_um=px).height_um
    seen = []
    real = pipeline.detect_protrusions

    def spy(albedo, height_um, **kwargs):
        seen.append((height_um, kwargs.get("left_out")))
        return real(albedo, height_um, **kwargs)

    monkeypatch.setattr(pipeline, "detect_protrusions", spy)
    albedo = np.ones(h.shape, np.float32)
    want = pipeline.detection_height(run_height, n, pixel_size_um=px, params=DetectionParams())
    pipeline.find_protrusions(albedo, run_height, n, pixel_size_um=px)
    pipeline.find_protrusions(albedo, run_height, None, pixel_size_um=px)
    (got_h, got_out), (plain_h, plain_out) = seen
    np.testing.assert_array_equal(got_out, want.left_out)
    np.testing.assert_allclose(got_h, want.height_um)
    assert got_out[crack].mean() > 0.75
    assert plain_h is run_height and plain_out is None


def test_the_detections_height_from_kept_gradients_is_the_same_and_leaves_them_unchanged(monkeypatch):
    """:func:`uvps.core.pipeline.detection_height` given the normals' gradients (a run's height stage keeps
    them): with their mask the one it computes with (none, or the finite heights'), the same height and
    left-out pixels to the bit, the gradients not computed again and left unchanged (the left-out pixels are
    zeroed in copies); with another mask, computed again."""
    from uvps.core import pipeline
    from uvps.core.detect import DetectionParams

    px = 15.0
    p, q, _, _, crack = _domes_and_a_crack(1, px=px)
    n = np.stack([-p, -q, np.ones_like(p)], -1)
    n /= np.linalg.norm(n, axis=-1, keepdims=True)
    inside = np.ones(p.shape, bool)
    inside[:12, :40] = False
    calls = []
    real = pipeline.gradients_from_normals
    monkeypatch.setattr(pipeline, "gradients_from_normals", lambda *a, **kw: (calls.append(1), real(*a, **kw))[1])
    for mask in (None, inside):
        run_height = frankot_chellappa(p, q, pixel_size_um=px, mask=mask).height_um
        want = pipeline.detection_height(run_height, n, pixel_size_um=px, params=DetectionParams())
        assert want.left_out[crack].mean() > 0.75
        kept = integrate_normals(n, pixel_size_um=px, mask=mask, keep_gradients=True).gradients
        before = kept.p.copy(), kept.q.copy()
        calls.clear()
        got = pipeline.detection_height(run_height, n, pixel_size_um=px, params=DetectionParams(), gradients=kept)
        assert calls == []
        np.testing.assert_array_equal(got.height_um, want.height_um)
        np.testing.assert_array_equal(got.left_out, want.left_out)
        np.testing.assert_array_equal(kept.p, before[0])
        np.testing.assert_array_equal(kept.q, before[1])
    other = integrate_normals(n, pixel_size_um=px, keep_gradients=True).gradients     # no mask; the height has one
    got = pipeline.detection_height(run_height, n, pixel_size_um=px, params=DetectionParams(), gradients=other)
    assert calls == [1]
    np.testing.assert_array_equal(got.height_um, want.height_um)


@pytest.mark.parametrize("method, zero", [("fc", False), ("dct", False), ("fc", True)])
def test_kept_gradients_are_the_normals_and_change_no_height(method, zero):
    """``integrate_normals(keep_gradients=True)``: the same height and diagnostics to the bit, and the kept
    gradients those :func:`gradients_from_normals` gives (invalid normals at 0; a (0, 0, 0) normal's NaN,
    which the solver sets to 0 in its own copies), with the mask they were computed with."""
    rng = np.random.default_rng(5)
    n = np.dstack([rng.normal(0, 0.2, (40, 50)), rng.normal(0, 0.2, (40, 50)), np.ones((40, 50))])
    n[3, 4] = np.nan                                    # an invalid normal: left out by the solver, 0 kept
    if zero:
        n[7, 8] = 0.0                                   # a NaN gradient, not counted invalid
    mask = np.ones((40, 50), bool)
    mask[30:, :10] = False
    for m in (None, mask):
        plain = integrate_normals(n, pixel_size_um=PX_UM, method=method, mask=m)
        kept = integrate_normals(n, pixel_size_um=PX_UM, method=method, mask=m, keep_gradients=True)
        assert plain.gradients is None and kept.n_invalid == plain.n_invalid == 1 + zero
        np.testing.assert_array_equal(kept.height_um, plain.height_um)
        assert (kept.residual_rms, kept.integrability) == (plain.residual_rms, plain.integrability)
        g = gradients_from_normals(n, mask=m)
        np.testing.assert_array_equal(kept.gradients.p, g.p)
        np.testing.assert_array_equal(kept.gradients.q, g.q)
        assert kept.gradients.p[3, 4] == 0 and (kept.gradients.mask is None) == (m is None)
        assert np.isnan(kept.gradients.p[7, 8]) == zero
        pn, qn = g.p.copy(), g.q.copy()                 # the invalid pixels marked NaN for the solver
        pn[g.invalid] = np.nan
        qn[g.invalid] = np.nan
        ref = SOLVERS[method](pn, qn, pixel_size_um=PX_UM, mask=m)
        np.testing.assert_array_equal(plain.height_um, ref.height_um)
        assert (plain.residual_rms, plain.integrability, plain.n_invalid) == (ref.residual_rms, ref.integrability,
                                                                              ref.n_invalid)


def test_gradients_are_the_same_whatever_the_threads(monkeypatch):
    """:func:`gradients_from_normals`' bands over two threads (``UVPS_THREADS`` 2) give the one thread's
    gradients, invalid map and counts to the bit (bands of 4 rows here: 10 of them)."""
    import uvps.core.integrate as integrate

    rng = np.random.default_rng(6)
    n = np.dstack([rng.normal(0, 1.0, (40, 50)), rng.normal(0, 1.0, (40, 50)), rng.uniform(-0.1, 1, (40, 50))])
    n[5, 5] = np.nan
    monkeypatch.setattr(integrate, "BAND_PIXELS", 200)
    got = {}
    for threads in ("1", "2"):
        monkeypatch.setenv("UVPS_THREADS", threads)
        got[threads] = gradients_from_normals(n, mask=(np.arange(40 * 50) % 7 > 0).reshape(40, 50))
    a, b = got["1"], got["2"]
    assert a.n_clamped == b.n_clamped > 100 and a.n_invalid == b.n_invalid == 1
    for name in ("p", "q", "invalid"):
        assert getattr(a, name).tobytes() == getattr(b, name).tobytes(), name
