"""Tests of uvps.core.regions: loading areas, the automatic proposal, per-area statistics."""
import csv

import numpy as np
import pytest

from uvps.errors import UVPSInputError
from uvps.files.io import write_imagej_tiff
from uvps.core.regions import RegionMap, propose_regions, region_statistics
from uvps.files.tables import load_regions, write_regions_csv

PX = 50.0  # um per pixel: 200 px = 1 cm


def _two_areas():
    """A 200 x 300 px capture = 1 cm x 1.5 cm; area 1 = left 100 columns (0.5 cm^2), area 2 = the
    rest (1 cm^2)."""
    labels = np.zeros((200, 300), np.int32)
    labels[:, :100] = 1
    labels[:, 100:] = 2
    return RegionMap(labels, {1: "light red", 2: "dark green"})


def _table(points):
    pts = np.array(points, dtype=float).reshape(-1, 3)
    return {"x_px": pts[:, 0], "y_px": pts[:, 1], "width_um": pts[:, 2]}


def test_densities_and_histogram_per_area():
    regions = _two_areas()
    # area 1 (x < 100): widths 50, 150, 150, 420 -> 4 / 0.5 cm^2 = 8 per cm^2
    # area 2: widths 99.9, 100 -> 2 / 1 cm^2
    t = _table([[10, 10, 50], [20, 50, 150], [99, 199, 150], [50, 100, 420],
                [150, 10, 99.9], [299, 0, 100]])
    s = region_statistics(t, regions, pixel_size_um=PX, bins_um=100.0)
    np.testing.assert_allclose(s.edges_um, [0, 100, 200, 300, 400, 500])
    a1, a2, tot = s.rows
    assert (a1.label, a1.name, a2.label, tot.label) == (1, "light red", 2, "all")
    assert a1.area_cm2 == pytest.approx(0.5) and a2.area_cm2 == pytest.approx(1.0)
    assert tot.area_cm2 == pytest.approx(1.5)
    assert (a1.count, a2.count, tot.count) == (4, 2, 6)
    assert a1.density_per_cm2 == pytest.approx(8.0) and a2.density_per_cm2 == pytest.approx(2.0)
    np.testing.assert_array_equal(a1.counts, [1, 2, 0, 0, 1])
    np.testing.assert_array_equal(a2.counts, [1, 1, 0, 0, 0])
    np.testing.assert_allclose(a1.densities, [2, 4, 0, 0, 2])
    np.testing.assert_allclose(tot.densities, np.array([2, 3, 0, 0, 1]) / 1.5)
    assert s.outside == 0


def test_custom_bins_and_outside_points(tmp_path):
    regions = _two_areas()
    regions.labels[:, 250:] = 0  # area 2 shrinks to 150 columns = 0.75 cm^2
    t = _table([[10, 10, 30], [20, 20, 75], [30, 30, 250], [150, 10, 600], [280, 5, 40],
                [-5, 3, 40]])
    s = region_statistics(t, regions, pixel_size_um=PX, bins_um=[0, 50, 100, 300, np.inf])
    a1, a2, tot = s.rows
    np.testing.assert_array_equal(a1.counts, [1, 1, 1, 0])
    np.testing.assert_array_equal(a2.counts, [0, 0, 0, 1])
    assert a2.area_cm2 == pytest.approx(0.75) and a2.density_per_cm2 == pytest.approx(1 / 0.75)
    assert tot.count == 4 and s.outside == 2
    path = tmp_path / "regions.csv"
    write_regions_csv(path, s)
    with open(path, newline="") as fh:
        rows = list(csv.DictReader(fh))
    assert [r["label"] for r in rows] == ["1", "2", "all"]
    assert rows[0]["name"] == "light red"
    assert list(rows[0])[:5] == ["label", "name", "area_cm2", "count", "density_per_cm2"]
    assert rows[0]["count_100-300um"] == "1" and rows[1]["count_300-infum"] == "1"
    assert float(rows[0]["density_0-50um"]) == pytest.approx(2.0)


def test_no_protrusions_gives_zero_counts():
    s = region_statistics(_table([]), _two_areas(), pixel_size_um=PX)
    assert [r.count for r in s.rows] == [0, 0, 0]
    np.testing.assert_allclose(s.edges_um, [0, 100])


@pytest.mark.parametrize("bins", [[0, 100, 100], [200, 100], [5], 0.0, -10, np.nan])
def test_bad_bins(bins):
    with pytest.raises(UVPSInputError, match="bins_um"):
        region_statistics(_table([[1, 1, 10]]), _two_areas(), pixel_size_um=PX, bins_um=bins)


def test_load_label_tiff_with_names_beside(tmp_path):
    labels = np.zeros((40, 60), np.int32)
    labels[:20] = 1
    labels[20:, 30:] = 4
    path = tmp_path / "regions_labels.tif"
    write_imagej_tiff(path, labels, axes="YX", pixel_size_um=PX)
    (tmp_path / "regions.csv").write_text("label,name,area_cm2\n1,beige,0.1\n4,yellow,0.2\n"
                                          "all,all areas,0.3\n")
    r = load_regions(path, shape=(40, 60))
    np.testing.assert_array_equal(r.labels, labels)
    assert r.names == {1: "beige", 4: "yellow"}
    assert load_regions(labels, shape=(40, 60)).names == {1: "area 1", 4: "area 4"}
    # float label images (ImageJ 32-bit) are accepted when whole-numbered
    assert load_regions(labels.astype(np.float32), shape=(40, 60)).ids == [1, 4]


def test_load_masks(tmp_path):
    shape = (30, 40)
    m1 = np.zeros(shape, np.uint8)
    m1[:15] = 255
    m2 = np.zeros(shape, np.uint8)
    m2[10:] = 255  # overlaps m1 on rows 10..14: m1 keeps them
    paths = []
    for name, m in (("light_green", m1), ("orange", m2)):
        p = tmp_path / f"{name}.tif"
        write_imagej_tiff(p, m, axes="YX", pixel_size_um=PX)
        paths.append(p)
    r = load_regions(paths, shape=shape)
    assert r.names == {1: "light_green", 2: "orange"}
    assert r.area_px() == {1: 15 * 40, 2: 15 * 40}
    empty = tmp_path / "empty.tif"
    write_imagej_tiff(empty, np.zeros(shape, np.uint8), axes="YX", pixel_size_um=PX)
    with pytest.raises(UVPSInputError, match="empty.tif is empty"):
        load_regions(paths + [empty], shape=shape)


@pytest.mark.parametrize("arg, match", [
    (np.ones((30, 41), np.int32), "expected the capture's 30 x 40"),
    (np.zeros((30, 40), np.int32), "no area"),
    (np.full((30, 40), 1.5), "whole-number"),
    ([np.zeros((30, 40), bool)], "mask 1 is empty"),
    ([np.ones((31, 40), bool)], "31 x 40"),
    ([], "empty list"),
])
def test_load_bad_input(arg, match):
    with pytest.raises(UVPSInputError, match=match) as exc:
        load_regions(arg, shape=(30, 40))
    assert "\n" not in str(exc.value)


def test_load_missing_file(tmp_path):
    with pytest.raises(UVPSInputError, match="does not exist"):
        load_regions(tmp_path / "nope.tif", shape=(3, 3))


def _patches(rgb=True, seed=0):
    """Three flat colour patches (beige top-left, green right, red bottom-left), noise and
    bright protrusion discs, at 15 um per pixel."""
    rng = np.random.default_rng(seed)
    M, N = 240, 320
    truth = np.zeros((M, N), int)
    truth[:, 200:] = 1
    truth[140:, :200] = 2
    colours = np.array([(0.8, 0.7, 0.5), (0.2, 0.5, 0.2), (0.6, 0.1, 0.1)])
    alb = np.moveaxis(colours[truth], -1, 0) + rng.normal(0, 0.03, (3, M, N))
    rr, cc = np.mgrid[:M, :N]
    for y, x in rng.integers(0, (M, N), size=(30, 2)):
        alb[:, (rr - y) ** 2 + (cc - x) ** 2 <= 16] = 1.0
    return (alb if rgb else alb[0]), truth


@pytest.mark.parametrize("rgb", [True, False])
def test_propose_recovers_three_patches(rgb):
    alb, truth = _patches(rgb)
    r = propose_regions(alb, pixel_size_um=15.0, seed=0)
    assert len(r.ids) == 3
    # each true patch maps to one proposed area over >= 95 % of its pixels, all different
    found = []
    for k in range(3):
        got = r.labels[truth == k]
        mode = np.bincount(got).argmax()
        assert (got == mode).mean() > 0.95
        found.append(mode)
    assert sorted(found) == [1, 2, 3]
    # lightest first: the beige patch is area 1
    assert found[0] == 1
    if rgb:
        np.testing.assert_allclose(r.colors[found[1]], [0.2, 0.5, 0.2], atol=0.05)


def test_propose_with_n_areas_and_mask():
    alb, truth = _patches()
    mask = np.ones(truth.shape, bool)
    mask[:, :40] = False
    r = propose_regions(alb, pixel_size_um=15.0, n_areas=2, mask=mask)
    assert len(r.ids) == 2
    assert (r.labels[~mask] == 0).all() and (r.labels[mask] > 0).all()


def test_propose_bad_input():
    alb, _ = _patches()
    with pytest.raises(UVPSInputError, match="n_areas"):
        propose_regions(alb, pixel_size_um=15.0, n_areas=0)
    with pytest.raises(UVPSInputError, match="mask"):
        propose_regions(alb, pixel_size_um=15.0, mask=np.ones((5, 5), bool))
    with pytest.raises(UVPSInputError, match="albedo"):
        propose_regions(np.ones((2, 5, 5)), pixel_size_um=15.0)


def test_propose_refuses_a_pixel_size_that_makes_the_image_smaller_than_an_area():
    """0.1 typed as mm into the um field: 320 px of 0.1 um are 0.032 mm, one smoothing block;
    a one-line message naming the pixel size, not a scipy error from the clustering."""
    alb, _ = _patches()
    with pytest.raises(UVPSInputError) as info:
        propose_regions(alb, pixel_size_um=0.1)
    message = str(info.value)
    assert "\n" not in message
    assert message.startswith("pixel_size_um 0.1 makes the 320 x 240 px image 0.032 mm wide")
    assert "micrometres" in message


def test_statistics_reject_an_area_without_pixels():
    regions = _two_areas()
    regions.names[3] = "ghost"
    with pytest.raises(UVPSInputError, match=r"colour area 3 \(ghost\) has no pixels"):
        region_statistics(_table([[1, 1, 10]]), regions, pixel_size_um=PX)


def test_statistics_bad_table_and_regions():
    with pytest.raises(UVPSInputError, match="width_um"):
        region_statistics({"x_px": [1.0], "y_px": [1.0]}, _two_areas(), pixel_size_um=PX)
    with pytest.raises(UVPSInputError, match="RegionMap"):
        region_statistics(_table([]), np.ones((3, 3), int), pixel_size_um=PX)


def test_the_cli_refuses_a_pixel_size_in_mm_with_automatic_areas_in_one_line(tmp_path):
    """`uvps run --pixel-size-um 0.1 --regions auto` (0.1 meant as mm): exit 1 and one line, not a
    traceback from the clustering."""
    import subprocess
    import sys

    from uvps.testing.synthetic import make_capture, write_capture

    write_capture(make_capture(shape=(120, 160), n_lights=8, seed=1), tmp_path / "cap", truth=False)
    r = subprocess.run([sys.executable, "-m", "uvps", "run", str(tmp_path / "cap"), "-o", str(tmp_path / "run"),
                        "--pixel-size-um", "0.1", "--regions", "auto", "--lights", str(tmp_path / "cap" / "lights.lp")],
                       capture_output=True, text=True, timeout=600)
    assert r.returncode == 1, r.stderr
    errors = [ln for ln in r.stderr.splitlines() if not ln.startswith(("INFO", "WARNING"))]
    # refused as typed, before any work (uvps.errors.PIXEL_SIZE_RANGE_UM); a library call with such
    # a size meets propose_regions' own one-line refusal (the test above)
    assert errors == ["uvps run: error: pixel_size_um 0.1 um is not a pixel size on a painting (1-1000 um); "
                      "give it in micrometres (0.1 mm = 100 um)"], r.stderr
