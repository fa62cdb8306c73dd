"""Tests of uvps.core.wand on hand-made images with known selections."""
import numpy as np
import pytest

from uvps.errors import UVPSInputError
from uvps.core.wand import contrast_select, read_seeds, wand_select


def diagonal_image():
    # two 2x2 bright squares touching only at a corner (diagonal contact)
    img = np.zeros((8, 8), np.float32)
    img[1:3, 1:3] = 10.0
    img[3:5, 3:5] = 10.0
    return img


def test_diagonal_contact_joins_in_8_not_in_4():
    img = diagonal_image()
    lab8 = wand_select(img, [[1, 1]], tolerance=1.0, connectivity=8)
    lab4 = wand_select(img, [[1, 1]], tolerance=1.0, connectivity=4)
    assert (lab8 == 1).sum() == 8
    assert (lab4 == 1).sum() == 4
    assert lab4[3, 3] == 0 and lab8[3, 3] == 1


def test_legacy_mode_with_tolerance_is_8_connected():
    img = diagonal_image()
    lab = wand_select(img, [[1, 1]], tolerance=1.0, connectivity="legacy")
    assert (lab == 1).sum() == 8


def test_legacy_mode_exact_match_uses_imagej_isline_rule():
    # Two areas of 5 split by a 2-pixel wall of 0 with a diagonal-only passage.
    img = np.full((11, 15), 5.0)
    img[:, 4:6] = 0.0
    img[5, 4] = 5.0
    img[6, 5] = 5.0
    # Many inside pixels right of the seed's run (ImageJ's isLine is false): 4-connected.
    lab = wand_select(img, [[1, 2]], tolerance=0.0, connectivity="legacy")
    assert (lab == 1).sum() == 11 * 4 + 1
    assert (wand_select(img, [[1, 2]], tolerance=0.0, connectivity=8) == 1).sum() == 11 * 13 + 2
    # A small blob has few inside pixels right of its run (isLine true): 8-connected.
    lab_blob = wand_select(diagonal_image(), [[1, 1]], tolerance=0.0, connectivity="legacy")
    assert (lab_blob == 1).sum() == 8


def test_tolerance_bounds_are_inclusive():
    row = np.array([[10.0, 11.0, 12.0, 12.5, 8.0, 7.5]], np.float32)
    img = np.repeat(row, 3, axis=0)
    lab = wand_select(img, [[0, 1]], tolerance=2.0)
    # 12.0 (= v0 + tol) included, 12.5 excluded, so the run stops before 8.0
    np.testing.assert_array_equal(lab[1], [1, 1, 1, 0, 0, 0])
    img2 = np.repeat(np.array([[10.0, 8.0, 7.9]], np.float32), 2, axis=0)
    lab2 = wand_select(img2, [[0, 0]], tolerance=2.0)
    np.testing.assert_array_equal(lab2[0], [1, 1, 0])


def test_caldera_hole_is_filled_like_imagej_outline():
    # bright ring (dome rim) with a dark crater: the crater fails the tolerance but is enclosed
    yy, xx = np.mgrid[:21, :21]
    r = np.hypot(yy - 10, xx - 10)
    img = np.where(r <= 7, 100.0, 20.0)
    img[r <= 3] = 40.0
    lab = wand_select(img, [[10, 3]], tolerance=10.0)
    np.testing.assert_array_equal(lab == 1, r <= 7)


def test_hole_open_to_outside_is_not_filled():
    img = np.zeros((9, 9))
    img[1:8, 1:8] = 50.0
    img[3:6, 3:6] = 0.0
    img[4, 1:4] = 0.0  # a channel from the hole to the outside
    lab = wand_select(img, [[2, 2]], tolerance=1.0, connectivity=4)
    assert lab[4, 4] == 0
    assert (lab == 1).sum() == 49 - 9 - 3 + 1  # the channel overlaps one hole pixel


def test_seed_inside_earlier_region_reuses_label_and_order():
    img = np.zeros((10, 20))
    img[2:6, 2:6] = 5.0
    img[2:6, 12:16] = 9.0
    lab = wand_select(img, [[3, 3], [4, 4], [13, 3]], tolerance=1.0)
    assert set(np.unique(lab)) == {0, 1, 3}
    assert (lab == 1).sum() == 16 and (lab == 3).sum() == 16
    assert lab.dtype == np.int32


def test_rgb_mean_rule_and_channels_rule():
    img = np.zeros((5, 6, 3))
    img[:, :3] = [100, 100, 100]
    img[:, 3:] = [130, 100, 70]  # same grey mean (100), different colour
    lab_mean = wand_select(img, [[0, 0]], tolerance=5.0)
    lab_chan = wand_select(img, [[0, 0]], tolerance=5.0, rgb="channels")
    assert (lab_mean == 1).sum() == 30  # ImageJ compares the grey value
    assert (lab_chan == 1).sum() == 15  # every channel within 5
    # tolerance 0 is ImageJ's exact RGB match in both rules
    assert (wand_select(img, [[0, 0]], tolerance=0.0) == 1).sum() == 15


def test_input_image_not_modified():
    img = diagonal_image()
    before = img.copy()
    wand_select(img, [[1, 1]], tolerance=1.0)
    np.testing.assert_array_equal(img, before)


@pytest.mark.parametrize("seeds,tol,match", [
    ([[8, 0]], 1.0, "outside the image"),
    ([[-1, 2]], 1.0, "outside the image"),
    ([[1, 1]], -0.5, "tolerance"),
    ([[1, 1]], 11.0, "tolerance"),
    ([[1, 1, 1]], 1.0, r"\(S, 2\)"),
])
def test_bad_input_one_line(seeds, tol, match):
    with pytest.raises(UVPSInputError, match=match) as err:
        wand_select(diagonal_image(), seeds, tolerance=tol)
    assert "\n" not in str(err.value)


def test_nan_seed_rejected_and_nan_never_selected():
    img = np.ones((4, 4))
    img[0, 3] = np.nan
    with pytest.raises(UVPSInputError, match="NaN"):
        wand_select(img, [[3, 0]], tolerance=0.0)
    lab = wand_select(img, [[0, 0]], tolerance=0.0)
    assert (lab == 1).sum() == 15


def test_read_seeds_formats(tmp_path):
    p1 = tmp_path / "pts.csv"
    p1.write_text("id,x_px,y_px\n1,3,4\n2,10.7,2.2\n")
    np.testing.assert_array_equal(read_seeds(p1), [[3, 4], [10, 2]])
    p2 = tmp_path / "ij.csv"
    p2.write_text(" ,X,Y\n1,5,6\n2,7.5,8.5\n")
    np.testing.assert_array_equal(read_seeds(p2), [[5, 6], [7, 8]])
    np.testing.assert_array_equal(read_seeds([[1, 2]]), [[1, 2]])
    assert read_seeds(np.zeros((0, 2))).shape == (0, 2)


def test_read_seeds_bad_files(tmp_path):
    p = tmp_path / "bad.csv"
    p.write_text("a,b\n1,2\n")
    with pytest.raises(UVPSInputError, match="x_px,y_px .or x_um,y_um, x_mm,y_mm, X,Y."):
        read_seeds(p)
    p.write_text("x_px,y_px\n1,oops\n")
    with pytest.raises(UVPSInputError, match="line 2"):
        read_seeds(p)
    with pytest.raises(UVPSInputError, match="cannot read"):
        read_seeds(tmp_path / "missing.csv")


def test_read_seeds_tab_separated_and_headerless(tmp_path):
    p = tmp_path / "xy.txt"
    p.write_text("12\t7\n3.5\t4.9\n")
    np.testing.assert_array_equal(read_seeds(p), [[12, 7], [3, 4]])
    p.write_text(" \tX\tY\n1\t5\t6\n")
    np.testing.assert_array_equal(read_seeds(p), [[5, 6]])


def test_read_seed_file_reads_the_unit_its_header_names(tmp_path):
    """One parser for the CLI and Fiji: x_mm is millimetres (Fiji's own parser read it as um,
    1000x off), x_um micrometres, X,Y pixels unless they only fit the image in um."""
    from uvps.core.wand import read_seed_file

    p = tmp_path / "mm.csv"
    p.write_text("x_mm,y_mm\n0.15,0.30\n1.5,0.045\n")
    got = read_seed_file(p, pixel_size_um=15.0)
    np.testing.assert_array_equal(got.seeds, [[10, 20], [100, 3]])
    assert (got.unit, got.said) == ("mm", True)
    p.write_text("x_um,y_um\n150,300\n")
    np.testing.assert_array_equal(read_seeds(p, pixel_size_um=15.0), [[10, 20]])
    # ImageJ's Measure on the calibrated albedo (320 x 240 px of 15 um): X,Y in um
    p.write_text(" ,X,Y\n1,4500,3000\n2,150,300\n")
    got = read_seed_file(p, pixel_size_um=15.0, shape=(240, 320))
    np.testing.assert_array_equal(got.seeds, [[300, 200], [10, 20]])
    assert (got.unit, got.said) == ("um", False)
    # the same numbers inside the image in pixels are pixels, unless told
    p.write_text(" ,X,Y\n1,45,30\n")
    assert read_seed_file(p, pixel_size_um=15.0, shape=(240, 320)).unit == "px"
    np.testing.assert_array_equal(read_seeds(p, pixel_size_um=15.0, units="um"), [[3, 2]])
    # a header's own unit wins over the choice
    p.write_text("x_px,y_px\n45,30\n")
    np.testing.assert_array_equal(read_seeds(p, pixel_size_um=15.0, units="um"), [[45, 30]])
    p.write_text("x_mm,y_mm\n1,2\n")
    with pytest.raises(UVPSInputError, match="a pixel size is needed"):
        read_seeds(p)


# --------------------------------------------------------------------------- the relative wand


def _painting(rng):
    """Paint at 20,000 counts (2 % noise) with a brighter area to the right; three protrusions of
    other contrasts: a bright dome (+20,000 at its top, falling to its rim), a faint one (+1,500)
    3 px from the brighter area and one that does not fluoresce (-8,000)."""
    img = 20000 * (1 + 0.02 * rng.standard_normal((160, 200)))
    img[:, 120:] += 3000
    yy, xx = np.mgrid[:160, :200]
    discs = {"bright": (40, 40, 8, 20000.0), "faint": (100, 110, 6, 1500.0), "dark": (120, 50, 7, -8000.0)}
    truth = {}
    for name, (cy, cx, r, c) in discs.items():
        rho2 = ((yy - cy) ** 2 + (xx - cx) ** 2) / (r * r)
        inside = rho2 <= 1
        img[inside] += c * (np.sqrt(1 - rho2[inside]) if name == "bright" else 1)
        truth[name] = ((cx, cy), int(inside.sum()))
    return img, truth


def test_the_relative_wand_outlines_protrusions_of_any_contrast_where_no_tolerance_does():
    img, truth = _painting(np.random.default_rng(0))
    clicks = [xy for xy, _ in truth.values()]
    lab = contrast_select(img, clicks, max_width_px=40)
    for i, (name, (_, area)) in enumerate(truth.items()):
        assert 0.7 <= (lab == i + 1).sum() / area <= 1.25, name
    # ImageJ's wand: one tolerance in counts cannot serve the faint and the bright one
    for tol in (500.0, 1000.0, 3000.0, 10000.0):
        w = wand_select(img, clicks, tolerance=tol)
        ratios = [(w == i + 1).sum() / area for i, (_, area) in enumerate(truth.values())]
        assert not all(0.5 <= r <= 2 for r in ratios), (tol, ratios)


def test_the_relative_wand_catches_repeated_clicks_and_refuses_what_has_no_contrast():
    img, truth = _painting(np.random.default_rng(1))
    (x, y), area = truth["dark"]
    lab = contrast_select(img, [(x, y), (x + 2, y - 1), (170, 20)], max_width_px=40)
    assert (lab == 1).sum() == pytest.approx(area, rel=0.25)
    assert lab[y - 1, x + 2] == 1 and not (lab == 2).any()       # the second click repeats the first
    assert (lab == 3).sum() == 1                                  # plain paint: the click's pixel only
    with pytest.raises(UVPSInputError, match=r"tolerance.*\(0, 1\)"):
        contrast_select(img, [(x, y)], fraction=1.5)


def test_the_relative_wand_does_not_depend_on_the_albedos_units():
    img, truth = _painting(np.random.default_rng(2))
    clicks = [xy for xy, _ in truth.values()]
    np.testing.assert_array_equal(contrast_select(img, clicks, max_width_px=40),
                                  contrast_select(img / 65535.0 + 3.0, clicks, max_width_px=40))
