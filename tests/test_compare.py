"""Tests of uvps.core.compare: one-to-one matching and per-area matched / missed / extra."""

import numpy as np
import pytest

from uvps.core.compare import COLUMNS, compare_detections
from uvps.files.comparison import read_comparison_csv, write_comparison_csv
from uvps.errors import UVPSInputError
from uvps.core.regions import RegionMap

PX = 50.0  # um per pixel


def _table(points):
    pts = np.array(points, dtype=float).reshape(-1, 3)
    return {"x_px": pts[:, 0], "y_px": pts[:, 1], "width_um": pts[:, 2]}


def _regions():
    labels = np.zeros((200, 300), np.int32)
    labels[:, :100] = 1  # 0.5 cm^2
    labels[:, 100:] = 2  # 1.0 cm^2
    return RegionMap(labels, {1: "light red", 2: "dark green"})


def test_matched_missed_extra_per_area(tmp_path):
    # a (manual): three in area 1, two in area 2
    a = _table([[10, 10, 200], [40, 40, 200], [80, 150, 100], [150, 20, 300], [250, 180, 100]])
    # b (automated): near a0 at 1.5 px (radius 0.5 x 200 um = 2 px),
    # near a1 at 1 px, a stray one in area 1, near a3 at 2 px, and a far one in area 2
    b = _table([[11.5, 10, 200], [40, 41, 200], [60, 100, 100], [152, 20, 300], [200, 100, 80]])
    c = compare_detections(a, b, regions=_regions(), pixel_size_um=PX, name_a="manual",
                           name_b="automated")
    np.testing.assert_array_equal(c.pairs, [[0, 0], [1, 1], [3, 3]])
    np.testing.assert_allclose(c.distance_um, [75, 50, 100])
    np.testing.assert_array_equal(c.missed, [2, 4])
    np.testing.assert_array_equal(c.extra, [2, 4])
    r1, r2, tot = c.rows
    keys = ("count_a", "count_b", "matched", "missed", "extra")
    assert tuple(r1[k] for k in keys) == (3, 3, 2, 1, 1)
    assert tuple(r2[k] for k in keys) == (2, 2, 1, 1, 1)
    assert (tot["count_a"], tot["matched"], tot["missed"], tot["extra"]) == (5, 3, 2, 2)
    assert r1["density_a"] == pytest.approx(6.0) and r2["density_b"] == pytest.approx(2.0)
    path = tmp_path / "comparison.csv"
    write_comparison_csv(path, c)
    rows = read_comparison_csv(path)
    assert list(rows[0]) == list(COLUMNS) + ["table_a", "table_b"]
    assert rows[0]["table_a"] == "manual" and rows[2]["table_b"] == "automated"
    assert [r["label"] for r in rows] == ["1", "2", "all"]
    assert rows[2]["matched"] == "3" and float(rows[0]["density_a"]) == pytest.approx(6.0)


def test_one_to_one_prefers_more_matches():
    # a0 sits between b0 and b1; greedy nearest would pair a0-b0 and leave a1 alone.
    a = _table([[10, 10, 400], [16, 10, 400]])   # radius 200 um = 4 px
    b = _table([[13, 10, 400], [10.5, 10, 400]])
    c = compare_detections(a, b, regions=None, pixel_size_um=PX)
    assert len(c.pairs) == 2 and len(c.missed) == 0 and len(c.extra) == 0
    np.testing.assert_array_equal(c.pairs, [[0, 1], [1, 0]])
    assert np.isnan(c.rows[-1]["density_a"])


def test_radius_and_default_floor():
    a = _table([[0, 0, 10], [50, 50, 10]])
    b = _table([[1.9, 0, 10], [53, 50, 10]])
    # default: max(2 px, 0.5 x 10 um) = 100 um -> first pair (95 um) matches, second (150) not
    c = compare_detections(a, b, regions=None, pixel_size_um=PX)
    np.testing.assert_array_equal(c.pairs, [[0, 0]])
    c = compare_detections(a, b, regions=None, pixel_size_um=PX, match_radius_um=160.0)
    assert len(c.pairs) == 2
    c = compare_detections(a, b, regions=None, pixel_size_um=PX, match_radius_um=50.0)
    assert len(c.pairs) == 0 and list(c.missed) == [0, 1]


def test_empty_tables():
    c = compare_detections(_table([]), _table([[1, 1, 10]]), regions=_regions(), pixel_size_um=PX)
    assert c.rows[-1]["extra"] == 1 and c.rows[-1]["count_a"] == 0 and c.pairs.shape == (0, 2)


@pytest.mark.parametrize("kwargs, match", [
    (dict(pixel_size_um=-1.0), "pixel_size_um"),
    (dict(match_radius_um=0.0), "match_radius_um"),
    (dict(a={"x_px": [1.0], "y_px": [1.0]}), "width_um"),
    (dict(b={"x_px": [np.nan], "y_px": [1.0], "width_um": [1.0]}), "finite"),
])
def test_bad_input(kwargs, match):
    args = dict(a=_table([[1, 1, 10]]), b=_table([[1, 1, 10]]), regions=None, pixel_size_um=PX)
    args.update(kwargs)
    a, b = args.pop("a"), args.pop("b")
    with pytest.raises(UVPSInputError, match=match):
        compare_detections(a, b, **args)


def test_read_bad_comparison(tmp_path):
    p = tmp_path / "c.csv"
    p.write_text("label,name\n1,x\n")
    with pytest.raises(UVPSInputError, match="expected columns"):
        read_comparison_csv(p)
