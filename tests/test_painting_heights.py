"""The painting-wide height of tiles taken under a rig: each tile's height is the painting's plus a
constant, its own small tilt error and one error surface shared by every tile (the lamps move with the
camera). Aligned with a free plane per tile, the shared curvature chains across the painting; aligned
with per-tile offsets, the shared surface and the tilts the tiles measured, it does not."""
import dask
import numpy as np
import pytest

from uvps.core.level import level_height
from uvps.core.mosaic import PairShift, align_heights, align_rig_heights, overlap_box
from uvps.files.io import write_imagej_tiff
from uvps.painting_maps import MapContext, PlacedTile, painting_array
from uvps.testing.painting import make_painting, score_height

#: Each tile's tilt error (um, Legendre u and v terms: 1 um is 0.8 um/mm over a 2.4 mm tile, 0.05 deg; the
#: generator's tiles under beams are off by 0.3-3 um): without it the aligned height is 0.04 um rms off.
TILT_SD = 1.0


@pytest.fixture(scope="module")
def painting():
    """A 4 x 3 painting of 120 x 160 px tiles with a 60 um bow."""
    return make_painting(grid=(4, 3), tile_shape=(120, 160), overlap=0.25, stage_error_px=10, seed=5, bow_um=60.0,
                         protrusion_density=50.0)


def _rig_tiles(p, folder, shared_um):
    """Each tile's height as a rig integrates it: the truth + 20 um offsets + tilts of +-``TILT_SD`` um
    (Legendre) + E = ``shared_um`` x (2 u^2 - 1.5 u v + 3 v^2) in the tile's frame, then levelled (its best
    plane removed, recorded) as `uvps run` writes depth.tif."""
    rng = np.random.default_rng(3)
    M, N = p.tile_shape
    rr, cc = np.mgrid[0:M, 0:N].astype(float)
    u, v = 2 * cc / (N - 1) - 1, 1 - 2 * rr / (M - 1)
    shared = shared_um * (2.0 * u ** 2 - 1.5 * u * v + 3.0 * v ** 2)
    depths, levels = {}, {}
    for t in p.tiles:
        raw = t.capture.height_um + shared + rng.normal(0, 20) + TILT_SD * (rng.normal(0, 1.0) * u + rng.normal(0, 1.0) * v)
        depths[t.name], lev = level_height(raw.astype(np.float32), pixel_size_um=15.0)
        levels[t.name] = lev.coeffs
        (folder / t.name).mkdir()
        write_imagej_tiff(folder / t.name / "depth.tif", depths[t.name], axes="YX", pixel_size_um=15.0)
    corners = p.true_corners()
    names = list(corners)
    pairs = [PairShift(a, b, used=True) for i, a in enumerate(names) for b in names[i + 1:]
             if overlap_box(corners[a], (M, N), corners[b], (M, N)) is not None]
    return depths, levels, pairs


@pytest.fixture(scope="module")
def rig_tiles(painting, tmp_path_factory):
    folder = tmp_path_factory.mktemp("rig")
    return (painting, folder) + _rig_tiles(painting, folder, 1.0)


def _painting_height(p, folder, planes, forms):
    corners = p.true_corners()
    x0, y0 = min(c[0] for c in corners.values()), min(c[1] for c in corners.values())
    M, N = p.tile_shape
    shape = (int(np.ceil(max(c[1] for c in corners.values()) + M - y0)),
             int(np.ceil(max(c[0] for c in corners.values()) + N - x0)))
    ctx = MapContext([PlacedTile(k, str(folder / k), c[0] - x0, c[1] - y0, (M, N), 1.0, planes[k], None, forms[k])
                      for k, c in corners.items()], (x0, y0), shape)
    with dask.config.set(scheduler="synchronous"):
        h = painting_array("height", ctx, chunk_px=128).compute()
    return score_height(h, (x0, y0), p.whole.height_um, corners, p.tile_shape)


def test_a_shared_error_surface_is_measured_on_the_overlaps_and_the_bow_kept(rig_tiles):
    p, folder, depths, levels, pairs = rig_tiles
    rig = align_rig_heights(depths, p.true_corners(), pairs, levels)
    # E in Legendre terms: u^2 = (2 L2(u) + 1) / 3, so 2 u^2 -> 4/3 L2(u), 3 v^2 -> 2 L2(v), u v -> L1 L1; the part
    # of E a free tilt per tile would absorb is set by the tiles' measured tilts (here off by +-1 um each)
    np.testing.assert_allclose([rig.shared[2, 0], rig.shared[1, 1], rig.shared[0, 2]], [4 / 3, -1.5, 2.0], atol=0.25)
    s = _painting_height(p, folder, rig.planes, rig.forms)
    print("rig", s)
    # (0.69 and 0.55 um: what is left is the tilts' error in the part only they set)
    assert s["rms_um"] < 1.0 and s["overlap_rms_um"] < 1.0


def test_a_free_plane_per_tile_chains_the_shared_curvature_across_the_painting(rig_tiles):
    """What the rig's alignment replaces: each tile's free plane takes up its part of the shared
    surface's curvature, and the planes add up to a painting-wide bow of their own."""
    p, folder, depths, _, pairs = rig_tiles
    planes = align_heights(depths, p.true_corners(), pairs)
    s = _painting_height(p, folder, planes, {k: None for k in planes})
    print("free", s)
    assert s["rms_um"] > 2.0


def test_without_a_shared_error_the_tiles_keep_the_planes_the_overlaps_give(painting, tmp_path):
    """Lamps that hold (no shared error): the shared surface the tilts' noise suggests does not stand out
    of that noise, is taken as zero, and the painting is the free planes' (which are right then)."""
    depths, levels, pairs = _rig_tiles(painting, tmp_path, 0.0)
    rig = align_rig_heights(depths, painting.true_corners(), pairs, levels)
    assert np.abs(rig.shared).max() == 0
    s = _painting_height(painting, tmp_path, rig.planes, rig.forms)
    free = _painting_height(painting, tmp_path, align_heights(depths, painting.true_corners(), pairs),
                            {k: None for k in depths})
    print("rig", s, "free", free)
    # (0.10 against 0.04 um: the measured tilts, weighted a little, still pull the tilts' chain along the
    # painting, which the overlaps measure only by the curvature it leaves on them)
    assert s["rms_um"] < 0.2 and s["overlap_rms_um"] < 0.2


def test_two_tiles_share_no_error_surface_their_one_overlap_cannot_measure(painting, tmp_path):
    """One pair: the shared surface would be the two tiles' measured tilts' noise alone, nothing to test it
    against; it is taken as zero, and the pair's planes are the free ones'."""
    depths, levels, pairs = _rig_tiles(painting, tmp_path, 1.0)
    a, b = pairs[0].a, pairs[0].b
    two = {k: depths[k] for k in (a, b)}
    corners = {k: painting.true_corners()[k] for k in (a, b)}
    rig = align_rig_heights(two, corners, [pairs[0]], {k: levels[k] for k in (a, b)})
    assert np.abs(rig.shared).max() == 0
    assert np.isfinite(rig.rms_um)


def test_a_painting_of_one_tile_records_its_height_alignment_in_json(painting, tmp_path):
    """No overlap sampled (one tile, or no pair used): the alignment's rms is unknown, and painting.json
    (strict JSON, no NaN) records it as null instead of failing after the maps are written."""
    import json
    from types import SimpleNamespace

    from uvps.painting import _align_heights

    depths, levels, _ = _rig_tiles(painting, tmp_path, 1.0)
    name = next(iter(depths))
    (tmp_path / name / "run.json").write_text(json.dumps({"level": {"legendre_coeffs_um": np.asarray(
        levels[name]).tolist()}}), encoding="utf-8")
    planes, forms, record = _align_heights(tmp_path, [name], {name: (0.0, 0.0)}, SimpleNamespace(pairs=[]),
                                           pixel_size_um=15.0)
    assert record["model"].startswith("rig") and record["overlap_rms_um"] is None
    json.dumps(record, allow_nan=False)
    assert all(np.isfinite(planes[name]))


#: Tilts (um, Legendre u and v terms over a 150 x 200 px tile: 20 um is 13 um/mm, 0.76 deg) of the tiles of
#: :func:`test_a_tiles_tilt_taken_up_by_its_lamp_intensities_is_given_back`.
RIG_TILTS_UM = [(20.0, -10.0), (-15.0, 25.0), (5.0, 15.0), (-10.0, -20.0)]


#: The canvas's texture (um, two sinusoids of 0.35 and 0.5 mm).
TEXTURE_UM = 1.0


def _tilted_tile(tilt, rng, P, E):
    """A flat canvas tilted by ``tilt`` (Legendre um) with a faint texture (0.3 um), rendered under the rig's
    lamps ``P`` of intensities ``E`` (unknown to the light file) at its own exposure: the tile's ``Capture``."""
    from uvps.core.stack import Capture
    from uvps.testing.synthetic_render import render_images

    M, N = 150, 200
    rr, cc = np.mgrid[0:M, 0:N].astype(float)
    u, v = 2 * cc / (N - 1) - 1, 1 - 2 * rr / (M - 1)
    tex = TEXTURE_UM * (np.sin(2 * np.pi * cc / 23 + rng.uniform(0, 6)) + np.sin(2 * np.pi * (rr + 0.4 * cc) / 31 + rng.uniform(0, 6)))
    height = tilt[0] * u + tilt[1] * v + tex
    albedo = 0.5 * (1 + 0.02 * np.sin(2 * np.pi * (cc - rr) / 90))
    images = render_images(height, albedo, pixel_size_um=15.0, light_positions_mm=P, intensities=E, rng=rng,
                           exposure=rng.uniform(20000, 30000), dtype=np.uint16)
    return Capture(images=images, files=[f"uv_{k:02d}.tif" for k in range(len(P))], pixel_size_um=15.0, mask=None,
                   saturation=65535.0, light_directions=None, light_positions_mm=P, bit_depth="uint16",
                   light_intensities=None)


def test_a_tiles_tilt_taken_up_by_its_lamp_intensities_is_given_back():
    """Tiles of a rig whose light file gives the lamps' positions, not their powers: each tile measures the
    intensities from its own images, and on a canvas with little texture they take up part of the tile's
    tilt (a tilt shades each lamp by a constant, as an intensity does). The tilt each tile's intensities
    gave it (against the tiles' mean, the rig's lamps being the same in every tile) is given back: the tiles'
    tilts within 1 um of the truth, up to one tilt common to all (a painting-wide plane), where the normals
    alone are off by several um."""
    from uvps.core.mosaic import intensity_tilts
    from uvps.core.pipeline import RunOptions, run

    rng = np.random.default_rng(7)
    az, el = np.linspace(0, 2 * np.pi, 8, endpoint=False) + 0.3, np.deg2rad(rng.uniform(30, 50, 8))
    d = rng.uniform(250, 350, 8)
    P = np.column_stack([d * np.cos(el) * np.cos(az), d * np.cos(el) * np.sin(az), d * np.sin(el)])
    E = rng.uniform(0.97, 1.03, 8)
    measured, intensities = {}, {}
    for i, tilt in enumerate(RIG_TILTS_UM):
        res = run(_tilted_tile(tilt, rng, P, E), RunOptions(), stages=("flatfield", "normals"))
        n = res.stereo.normals
        M, N = n.shape[:2]
        measured[i] = (np.nanmean(-n[..., 0] / n[..., 2]) * (N - 1) / 2 * 15.0,
                       np.nanmean(-n[..., 1] / n[..., 2]) * (M - 1) / 2 * 15.0)
        intensities[i] = res.lights.model.intensities
    taken = intensity_tilts({i: P for i in measured}, intensities, (150, 200), 15.0)
    before = np.array([measured[i] for i in measured]) - RIG_TILTS_UM
    after = before - np.array([taken[i] for i in measured])
    print("tilts' errors before", np.round(before, 2).tolist(), "after", np.round(after, 2).tolist())
    assert np.abs(before - before.mean(axis=0)).max() > 3.0
    assert np.abs(after - after.mean(axis=0)).max() < 1.0
    # not one rig: another tile's lamps elsewhere
    assert intensity_tilts({0: P, 1: P + 1.0}, {0: E, 1: E}, (150, 200), 15.0) is None
    assert intensity_tilts({0: P, 1: P}, {0: E, 1: np.r_[0.0, E[1:]]}, (150, 200), 15.0) is None
    # intensities given in the light file (the same in every tile, up to the exposure): nothing to give back
    same = intensity_tilts({0: P, 1: P}, {0: E, 1: 1.1 * E}, (150, 200), 15.0)
    assert np.abs(list(same.values())).max() < 1e-9


def test_intensity_tilts_none_for_intensities_not_one_per_lamp_or_too_few_lamps():
    """One rig's lamp positions, but intensities that cannot be one rig's lamps' (a tile's list one lamp short,
    a tile without any) or too few lamps to solve a normal from (two): no tilt to give back (None), not a
    crash of the painting's height alignment."""
    from uvps.core.mosaic import intensity_tilts

    rng = np.random.default_rng(3)
    P = np.column_stack([rng.uniform(-200, 200, 8), rng.uniform(-200, 200, 8), rng.uniform(200, 300, 8)])
    E = rng.uniform(0.9, 1.1, 8)
    assert intensity_tilts({0: P, 1: P}, {0: E, 1: E[:7]}, (150, 200), 15.0) is None
    assert intensity_tilts({0: P, 1: P}, {0: E}, (150, 200), 15.0) is None
    assert intensity_tilts({0: P[:2], 1: P[:2]}, {0: E[:2], 1: 1.1 * E[:2] * [1.0, 1.05]}, (150, 200), 15.0) is None
    # three lamps are enough: a finite tilt for each tile
    three = intensity_tilts({0: P[:3], 1: P[:3]}, {0: E[:3], 1: E[:3] * [1.0, 1.05, 1.0]}, (150, 200), 15.0)
    assert sorted(three) == [0, 1] and np.all(np.isfinite(list(three.values())))
