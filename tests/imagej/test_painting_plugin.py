"""Stitch Painting (uvps batch with a mosaic) from a batch macro in a real ImageJ."""
import csv

import pytest

pytestmark = pytest.mark.imagej

TIMEOUT = 900


def q(path):
    return "[%s]" % path


@pytest.fixture(scope="module")
def painting(tmp_path_factory):
    """The generator's 3 x 2 painting (tiles of 200 x 240 px, stage off by up to 30 px)."""
    from uvps.testing.painting import make_painting, write_painting

    return write_painting(make_painting(seed=1), tmp_path_factory.mktemp("painting") / "p 1")


def test_stitch_painting_from_a_batch_macro_opens_the_overview_and_the_painting_tables(run_macro, painting,
                                                                                       tmp_path):
    out = tmp_path / "painting run"
    # the rig's lamps: one file for every tile (the generator writes the same one into each tile)
    lights = painting / "tiles" / "r1c1" / "lights_positions_mm.csv"
    result = run_macro('run("Stitch Painting", "captures=%s mosaic=%s lights=%s '
                       'regions=auto detect run=%s");\n'
                       'print("title: " + getTitle());\n'
                       'print("size " + getWidth() + " " + getHeight());\n'
                       'print("areas " + Table.size("Painting areas - painting run"));\n'
                       'print("protrusions " + Table.size("Painting protrusions - painting run"));\n'
                       'print("went on");\n' % (q(painting / "tiles"), q(painting / "layout.csv"), q(lights), q(out)),
                       timeout=TIMEOUT).check()
    lines = result.stdout.splitlines()
    assert "went on" in lines, result.stdout
    assert "title: painting overview - painting run" in lines, lines
    size = [ln for ln in lines if ln.startswith("size ")][0].split()
    assert int(size[1]) > 300 and int(size[2]) > 200
    with open(out / "painting" / "painting_protrusions.csv", newline="") as fh:
        kept = list(csv.DictReader(fh))
    with open(out / "painting" / "painting_regions.csv", newline="") as fh:
        areas = list(csv.DictReader(fh))
    assert len(kept) > 100 and "protrusions %d" % len(kept) in lines, lines
    assert "areas %d" % len(areas) in lines and areas[-1]["name"] == "all areas"
    assert any(ln.startswith("uvps Stitch Painting: ") and "report.html" in ln for ln in lines), lines
    assert (out / "painting" / "view" / "openseadragon.min.js").is_file()


def test_stitch_painting_without_a_layout_fails_with_one_line_naming_the_key(run_macro, painting, tmp_path):
    result = run_macro('run("Stitch Painting", "captures=%s run=%s");\n'
                       'print("went on");\n' % (q(painting / "tiles"), q(tmp_path / "no layout")), timeout=300)
    assert "went on" not in result.stdout.splitlines()
    assert "no layout: choose the tiles' layout CSV (key mosaic=)" in result.stdout + result.stderr
    assert not (tmp_path / "no layout" / "painting").exists()
