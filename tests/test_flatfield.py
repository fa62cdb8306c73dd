"""Drop-off fits: known Legendre coefficients recovered despite large colour areas."""
import numpy as np
import pytest
from numpy.polynomial import legendre as L

from uvps.errors import UVPSInputError
from uvps.core.flatfield import block_grid, fit_dropoffs, flatfield, with_common

M, N, DEG = 240, 320, 3


def _poly(C, rows, cols):
    v = (2 * rows - (M - 1)) / (M - 1)
    u = (2 * cols - (N - 1)) / (N - 1)
    return L.legvander(v, DEG) @ C @ L.legvander(u, DEG).T


def _capture(seed=0, K=5):
    rng = np.random.default_rng(seed)
    # sharp colour areas that cover a third and a quarter of the field, plus texture
    albedo = np.ones((M, N))
    albedo[:, : N // 3] = 0.25
    albedo[M // 4: M // 2, N // 2:] = 3.0
    albedo *= 1 + 0.02 * rng.standard_normal((M, N))
    C = 0.15 * rng.standard_normal((K, DEG + 1, DEG + 1))
    C[:, 0, 0] = 0
    rows, cols = np.arange(M, dtype=float), np.arange(N, dtype=float)
    images = np.stack([albedo * np.exp(_poly(C[k], rows, cols)) * 1000 for k in range(K)]).astype(np.float32)
    return images, C


def test_ratio_fit_recovers_known_coefficients_despite_colour_areas():
    images, C = _capture()
    fits = fit_dropoffs(block_grid(images), degree=DEG)
    mean_C = C.mean(axis=0)
    for k, fit in enumerate(fits):
        expect = C[k] - mean_C
        got = fit.ratio_coeffs.copy()
        got[0, 0] = expect[0, 0] = 0  # the constant is not observable
        assert np.abs(got - expect).max() < 2e-3


def test_separable_gram_is_the_weighted_product_of_the_design():
    """The drop-off fits' normal matrices by separable sums over the grid's rows and columns are
    ``A^T diag(w) A`` of the Kronecker design over the used blocks (to 1e-12 relative: sums in another order)."""
    from uvps.core.flatfield import _grid_design, _separable_gram

    grid = block_grid(_capture(seed=3)[0])
    rng = np.random.default_rng(0)
    Vv, Vu, A = _grid_design(grid, DEG)
    use = rng.random(A.shape[0]) > 0.3
    w = rng.uniform(0.01, 1.0, int(use.sum()))
    want = A[use].T @ (A[use] * w[:, None])
    got = _separable_gram(Vv, Vu, use)(w)
    np.testing.assert_allclose(got, want, rtol=1e-12, atol=1e-12 * np.abs(want).max())
    assert np.array_equal(got, got.T)


def test_with_common_completes_the_maps_normalised_to_mean_one_leaving_the_fits_as_they_were():
    images, C = _capture(seed=1)
    grid = block_grid(images)
    ratio_only = fit_dropoffs(grid, degree=DEG)
    before = [(f.coeffs.copy(), f.level) for f in ratio_only]
    mean_C = C.mean(axis=0)
    fits = with_common(ratio_only, grid, lambda r, c: _poly(mean_C, np.asarray(r), np.asarray(c)))
    for f, (coeffs, level) in zip(ratio_only, before):     # values: the given fits are not changed
        assert np.array_equal(f.coeffs, coeffs) and f.level == level
    rows, cols = np.arange(M, dtype=float), np.arange(N, dtype=float)
    for k, fit in enumerate(fits):
        F = fit.evaluate()
        truth = np.exp(_poly(C[k], rows, cols))
        truth /= truth.mean()
        assert abs(F.mean() - 1) < 1e-3
        assert np.abs(F / truth - 1).max() < 3e-3


def test_flatfield_divides_by_the_map_rgb():
    images, C = _capture(seed=2, K=3)
    grid = block_grid(images)
    fits = fit_dropoffs(grid, degree=DEG)
    rgb = np.stack([images[0], 0.5 * images[0], 0.1 * images[0]], axis=-1)
    full = flatfield(rgb, fits[0])
    F = fits[0].evaluate()
    np.testing.assert_allclose(full[..., 1], rgb[..., 1] / F, rtol=1e-5)
    assert full.dtype == np.float32


def test_too_few_usable_blocks_is_a_clear_error():
    images, _ = _capture(K=3)
    images[:, :, : int(N * 0.97)] = 0  # almost everything dark
    with pytest.raises(UVPSInputError, match="blocks are lit"):
        fit_dropoffs(block_grid(images), degree=6)


def test_divided_grid_is_the_gain_corrected_stacks_grid():
    """The blocks of a stack with smooth gains divided out (:class:`GainCorrected`) made from the stack's own
    blocks without a pass over it (:func:`divided_grid`): within the gains' variation across a block times the
    block's contrast (here, with gains far steeper than a lamp's beam, 3.5e-3 of the means in the blocks that
    hold a sharp colour edge, median 8e-5), the same validity; a gain of 1 changes nothing."""
    from uvps.core.flatfield import GainCorrected, divided_grid

    images, _ = _capture(seed=3)
    images[1, 100, 150] = 0.0                                   # a dark pixel: its block stays invalid
    gains = 0.1 * np.random.default_rng(4).standard_normal((5, 5, 5))
    grid = block_grid(images)
    want = block_grid(GainCorrected(images, gains))
    got = divided_grid(grid, gains)
    rel = np.abs(got.values / want.values - 1)
    assert rel.max() < 5e-3 and np.median(rel) < 1e-4, (rel.max(), np.median(rel))
    np.testing.assert_array_equal(got.valid, want.valid)
    assert not got.valid[1].all()
    assert np.abs(got.values / grid.values - 1).max() > 0.1     # the gains were there to divide out
    np.testing.assert_array_equal(divided_grid(grid, np.zeros((5, 5, 5))).values, grid.values)
    with pytest.raises(UVPSInputError):
        divided_grid(grid, gains[:3])
