"""A painting in overlapping tiles: the generator, the tiles' registration, one set of counts.

Fast tests register and merge the generator's tiles directly; the slow one runs a 3 x 2 painting
through `uvps batch --mosaic` on a real Dask LocalCluster and scores it against the truth."""
import csv
import json

import numpy as np
import pytest
import tifffile

from uvps.core.mosaic import PairShift, _solve, register_tiles
from uvps.commands.painting import merge_protrusions
from uvps.testing.painting import make_painting, read_truth_layout, score_painting, write_painting


@pytest.fixture(scope="module")
def paintings():
    """Three seeds of a 3 x 2 painting of 200 x 240 px tiles, 40 % overlap, stage off by up to 30 px."""
    return {seed: make_painting(seed=seed) for seed in (1, 2, 3)}


def _tile_view(painting, t):
    """What the tile's albedo looks like to the registration: the mean of its images (the rig's
    lamps shade every tile alike, not the painting), exposure drift included."""
    return t.capture.images.astype(np.float32).mean(axis=0)


def test_the_generator_renders_tiles_of_one_painting_under_a_moving_rig(paintings, tmp_path):
    p = paintings[1]
    assert p.grid == (3, 2) and len(p.tiles) == 6 and p.tile_shape == (200, 240)
    err = np.array([np.subtract(t.true, t.nominal) for t in p.tiles])
    assert np.abs(err).max() <= 30 + 1e-9 and np.abs(err).max() > 10      # the stage is off, up to 30 px
    np.testing.assert_allclose(err.mean(axis=0), 0, atol=1e-9)            # the nominal layout's frame
    assert len({round(t.exposure, 3) for t in p.tiles}) == 6               # exposure drifts between tiles
    for t in p.tiles:                                                      # the lamps ride with the rig
        np.testing.assert_array_equal(t.capture.light_positions_mm, p.tiles[0].capture.light_positions_mm)
    # a tile shows the painting at its true corner, sub-pixel (checked with scipy's linear
    # interpolation, against the corner rounded: the true corner fits better)
    from scipy import ndimage
    t = p.tiles[4]
    rr, cc = np.mgrid[0:200, 0:240].astype(float)
    inner = np.s_[5:-5, 5:-5]
    at_true = ndimage.map_coordinates(p.whole.albedo[..., 1], [rr + t.true[1], cc + t.true[0]], order=1)
    at_round = ndimage.map_coordinates(p.whole.albedo[..., 1], [rr + round(t.true[1]), cc + round(t.true[0])],
                                       order=0)
    tile = t.capture.albedo[..., 1]
    assert np.abs(tile - at_true)[inner].mean() < 0.5 * np.abs(tile - at_round)[inner].mean()
    # the truth in painting pixels: each tile's protrusions are the painting's, moved by its corner
    ids = set(p.whole.protrusions["id"].tolist())
    for t in p.tiles:
        tp = t.capture.protrusions
        assert set(tp["id"].tolist()) <= ids
        k = np.searchsorted(p.whole.protrusions["id"], tp["id"])
        np.testing.assert_allclose(tp["x_px"] + t.true[0], p.whole.protrusions["x_px"][k])
    out = write_painting(p, tmp_path / "painting")
    assert sorted(q.name for q in (out / "tiles").iterdir()) == [t.name for t in p.tiles]
    nominal, true = read_truth_layout(out / "layout.csv"), read_truth_layout(out / "truth" / "layout.csv")
    assert nominal["r2c2"] == pytest.approx(p.tiles[4].nominal, abs=1e-4)
    assert true["r2c2"] == pytest.approx(p.tiles[4].true, abs=1e-4)
    assert tifffile.imread(out / "truth" / "height_um.tif").shape == p.whole.height_um.shape
    assert len(list((out / "tiles" / "r1c1").glob("uv_*.tif"))) == 8
    meta = json.loads((out / "truth" / "painting.json").read_text())
    assert meta["grid"] == [3, 2] and meta["stage_error_px"] == 30
