"""Tests of uvps.core.measure on hand-checkable layouts (discs, a dome, a caldera crater)."""
import numpy as np
import pytest

from uvps.errors import UVPSInputError
from uvps.core.measure import COLUMNS, MeasureOptions, measure_protrusions
from uvps.files.tables import read_protrusions_csv, write_protrusions_csv

PX = 10.0  # um per pixel


def _disc(shape, centre, radius):
    rr, cc = np.mgrid[: shape[0], : shape[1]]
    return (rr - centre[0]) ** 2 + (cc - centre[1]) ** 2 <= radius**2


def _layout():
    """Two discs (r = 10 and 20 px) on a 120 x 160 canvas; a dome of 30 um on the larger one."""
    shape = (120, 160)
    labels = np.zeros(shape, np.int32)
    d1 = _disc(shape, (30, 40), 10)
    d2 = _disc(shape, (70, 110), 20)
    labels[d1] = 1
    labels[d2] = 2
    rr, cc = np.mgrid[: shape[0], : shape[1]]
    r2 = ((rr - 70) ** 2 + (cc - 110) ** 2) / 20.0**2
    height = np.where(r2 <= 1, 30.0 * (1 - r2), 0.0) + 5.0  # flat surround at 5 um
    return labels, height, d1, d2


def test_width_area_centroid_and_height_of_discs():
    labels, height, d1, d2 = _layout()
    albedo = np.full(labels.shape, 0.25)
    albedo[d2] = 0.75
    t = measure_protrusions(labels, albedo=albedo, height_um=height, pixel_size_um=PX,
                            source="albedo")
    assert list(t) == list(COLUMNS)
    np.testing.assert_array_equal(t["id"], [1, 2])
    # centroid: x = column, y = row
    np.testing.assert_allclose(t["x_px"], [40, 110], atol=1e-9)
    np.testing.assert_allclose(t["y_px"], [30, 70], atol=1e-9)
    # area = pixel count * px^2; equivalent diameter = 2 r within a pixel's digitisation
    np.testing.assert_allclose(t["area_um2"], [d1.sum() * PX**2, d2.sum() * PX**2])
    np.testing.assert_allclose(t["width_um"], [20 * PX, 40 * PX], rtol=0.03)
    np.testing.assert_allclose(t["width_um"], 2 * np.sqrt(t["area_um2"] / np.pi))
    # dome peak 30 um above a flat 5 um surround; flat disc 1 has no relief
    assert t["height_um"][1] == pytest.approx(30.0, abs=0.2)
    assert t["height_um"][0] == pytest.approx(0.0, abs=1e-9)
    # grey albedo -> r == g == b
    np.testing.assert_allclose(t["r"], [0.25, 0.75])
    np.testing.assert_array_equal(t["r"], t["g"])
    np.testing.assert_array_equal(t["r"], t["b"])
    assert list(t["source"]) == ["albedo", "albedo"]
    np.testing.assert_array_equal(t["crater"], [0, 0])


def test_rgb_albedo_regions_and_sources():
    labels, height, d1, d2 = _layout()
    albedo = np.zeros((3,) + labels.shape)
    albedo[0][d1], albedo[1][d1], albedo[2][d1] = 0.9, 0.5, 0.1
    regions = np.zeros(labels.shape, np.int32)
    regions[:, 80:] = 3
    t = measure_protrusions(labels, albedo=albedo, height_um=height, pixel_size_um=PX,
                            regions=regions, source={1: "height", 2: "albedo+height"})
    np.testing.assert_allclose([t["r"][0], t["g"][0], t["b"][0]], [0.9, 0.5, 0.1])
    np.testing.assert_array_equal(t["region"], [0, 3])
    assert list(t["source"]) == ["height", "albedo+height"]


def test_crater_detected_and_dome_not():
    shape = (100, 100)
    rr, cc = np.mgrid[: shape[0], : shape[1]]
    rad = np.hypot(rr - 50, cc - 50)
    R = 20.0
    # caldera: rim at 0.7 R reaching 20 um, a central depression down to 4 um
    caldera = np.where(rad <= R, 20.0 * np.exp(-((rad - 0.7 * R) / (0.25 * R)) ** 2), 0.0)
    caldera = np.where(rad <= R, np.maximum(caldera, 4.0 * (rad <= 0.3 * R)), 0.0)
    dome = np.where(rad <= R, 20.0 * (1 - (rad / R) ** 2), 0.0)
    labels = (rad <= R).astype(np.int32)
    rng = np.random.default_rng(1)
    for surface, expected in ((caldera, 1), (dome, 0)):
        h = surface + rng.normal(0, 0.3, shape)
        t = measure_protrusions(labels, albedo=np.ones(shape), height_um=h, pixel_size_um=PX)
        assert t["crater"][0] == expected
    # a tiny protrusion cannot resolve a crater
    small = (rad <= 2).astype(np.int32)
    t = measure_protrusions(small, albedo=np.ones(shape), height_um=caldera, pixel_size_um=PX,
                            options=MeasureOptions(crater_min_width_px=6))
    assert t["crater"][0] == 0


def test_surround_ring_ignores_neighbours_and_nan():
    shape = (60, 60)
    labels = np.zeros(shape, np.int32)
    labels[25:35, 25:35] = 1
    labels[25:35, 36:46] = 2  # a tall neighbour right beside it
    height = np.zeros(shape)
    height[labels == 1] = 10.0
    height[labels == 2] = 100.0
    height[:3, :] = np.nan
    t = measure_protrusions(labels, albedo=np.ones(shape), height_um=height, pixel_size_um=PX)
    np.testing.assert_allclose(t["height_um"], [10.0, 100.0])


def test_csv_round_trip(tmp_path):
    labels, height, _, _ = _layout()
    t = measure_protrusions(labels, albedo=np.ones(labels.shape), height_um=height,
                            pixel_size_um=PX, source=["albedo", "height"])
    path = tmp_path / "protrusions.csv"
    write_protrusions_csv(path, t)
    assert path.read_text().splitlines()[0] == ",".join(COLUMNS)
    back = read_protrusions_csv(path)
    assert list(back) == list(COLUMNS)
    for c in COLUMNS:
        if c == "source":
            assert list(back[c]) == list(t[c])
        else:
            np.testing.assert_allclose(back[c], t[c], rtol=1e-9)
    assert not list(tmp_path.glob(".*"))  # no temporary file left behind


def test_empty_labels_give_empty_table(tmp_path):
    t = measure_protrusions(np.zeros((8, 8), np.int32), albedo=np.ones((8, 8)),
                            height_um=np.zeros((8, 8)), pixel_size_um=PX)
    assert all(len(v) == 0 for v in t.values())
    write_protrusions_csv(tmp_path / "p.csv", t)
    assert all(len(v) == 0 for v in read_protrusions_csv(tmp_path / "p.csv").values())


def test_minimal_csv_gets_defaults(tmp_path):
    path = tmp_path / "m.csv"
    path.write_text("x_px,y_px,width_um,note\n1.5,2,30,a\n4,5,60,b\n")
    t = read_protrusions_csv(path)
    np.testing.assert_array_equal(t["id"], [1, 2])
    np.testing.assert_allclose(t["width_um"], [30, 60])
    assert np.isnan(t["height_um"]).all() and list(t["note"]) == ["a", "b"]


@pytest.mark.parametrize("kwargs, match", [
    (dict(labels=np.zeros((8, 8), float)), "integer"),
    (dict(labels=-np.ones((8, 8), np.int32)), ">= 0"),
    (dict(height_um=np.zeros((8, 9))), "height_um"),
    (dict(albedo=np.ones((2, 8, 8))), "albedo"),
    (dict(pixel_size_um=0.0), "pixel_size_um"),
    (dict(source=["a"]), "source"),
    (dict(regions=np.zeros((4, 4), np.int32)), "regions"),
])
def test_bad_input(kwargs, match):
    labels = np.zeros((8, 8), np.int32)
    labels[2:5, 2:5] = 1
    labels[6, 6] = 2
    args = dict(labels=labels, albedo=np.ones((8, 8)), height_um=np.zeros((8, 8)),
                pixel_size_um=PX)
    args.update(kwargs)
    labels = args.pop("labels")
    with pytest.raises(UVPSInputError, match=match) as exc:
        measure_protrusions(labels, **args)
    assert "\n" not in str(exc.value)


def test_bad_csv(tmp_path):
    with pytest.raises(UVPSInputError, match="does not exist"):
        read_protrusions_csv(tmp_path / "none.csv")
    p = tmp_path / "bad.csv"
    p.write_text("x_px,y_px\n1,2\n")
    with pytest.raises(UVPSInputError, match="width_um"):
        read_protrusions_csv(p)
    p.write_text("x_px,y_px,width_um\n1,two,3\n")
    with pytest.raises(UVPSInputError, match="'two'"):
        read_protrusions_csv(p)


def _profile(rho, crater):
    """Dome (1 - rho^2)^1.3, minus a central crater of depth 0.35 and radius 0.35 if asked."""
    f = np.where(rho < 1, np.clip(1 - rho**2, 0, None) ** 1.3, 0.0)
    if crater:
        f = f - 0.35 * np.clip(1 - (rho / 0.35) ** 2, 0, None) ** 2
    return f


@pytest.mark.parametrize("crater", [True, False])
def test_crater_and_relief_on_a_slope_with_a_loose_outline(crater):
    """A 40 um protrusion (radius 12 px) on a surface sloping 2 um per pixel; the label is a
    larger disc shifted by 3 px (as an albedo outline may be)."""
    shape = (80, 80)
    rr, cc = np.mgrid[: shape[0], : shape[1]]
    rho = np.hypot(rr - 40, cc - 40) / 12.0
    slope = 2.0 * cc + 0.5 * rr
    height = slope + 40.0 * _profile(rho, crater)
    peak = (40.0 * _profile(rho, crater)).max()
    labels = (np.hypot(rr - 37, cc - 42) <= 14).astype(np.int32)
    t = measure_protrusions(labels, albedo=np.ones(shape), height_um=height, pixel_size_um=PX)
    assert t["crater"][0] == int(crater)
    # relief above the local (sloping) surface, not above the ring's median
    assert t["height_um"][0] == pytest.approx(peak, rel=0.03)
