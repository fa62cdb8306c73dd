"""The card flat-field (uvps.core.card): synthetic cards under lamps with beams, vignetting, unequal power and
stray light (uvps.testing.synthetic.render_card), against the known normals and the card's known tilt."""
import dataclasses
import json
import subprocess
import sys

import numpy as np
import pytest
import tifffile

from uvps.core.card import apply_card, calibrate_card
from uvps.errors import UVPSInputError
from uvps.files.cards import read_card, write_card
from uvps.core.lights import LightModel
from uvps.core.pipeline import RunOptions, run
from uvps.testing.synthetic import SyntheticSpec, make_capture, render_card, render_dark_frame, write_capture

#: Beams aimed off (cos^30, 5 deg), 40 % vignetting, lamps +-15 % in power, stray light: what a card
#: is for (the top of each nuisance's range, uvps.testing.synthetic.NUISANCE_TOP).
NUISANCES = ["beams", "vignetting", "unequal_lamps", "stray_light"]


def _angle(a, b):
    c = np.sum(a * b, -1) / np.linalg.norm(a, axis=-1) / np.linalg.norm(b, axis=-1)
    return np.degrees(np.arccos(np.clip(c, -1, 1)))


@pytest.fixture(scope="module")
def beamed():
    spec = SyntheticSpec.realistic(level="top", only=NUISANCES, shape=(240, 320), n_lights=10, seed=4)
    return make_capture(spec)


def _dark_subtracted(cap, dark):
    """The capture as read with ``--lights`` positions and ``--dark``: the dark frame subtracted."""
    c = cap.as_capture(lights="positions")
    return dataclasses.replace(c, images=cap.images.astype(np.float32) - dark.astype(np.float32))


def test_card_divides_out_beams_vignetting_power_and_stray_light(beamed):
    dark = render_dark_frame(beamed)
    card = calibrate_card(render_card(beamed, tilt_deg=0.6, tilt_azimuth_deg=120.0, unevenness=0.01),
                          lights=beamed.light_positions_mm, pixel_size_um=beamed.spec.pixel_size_um, dark=dark)
    capture = _dark_subtracted(beamed, dark)
    plain = run(capture, RunOptions(), stages=("normals",), dark_given=True)
    carded = run(capture, RunOptions(), stages=("normals",), dark_given=True, card=card)
    err_plain = np.nanmean(_angle(plain.stereo.normals, beamed.normals))
    err_card = np.nanmean(_angle(carded.stereo.normals, beamed.normals))
    assert err_plain > 1.0                      # the beams tilt the known-position normals by degrees
    assert err_card < 0.3 and err_card < err_plain / 5
    d = carded.diagnostics["card"]
    # the card's tilt against the painting is measured and divided out
    assert d["tilt_to_painting_deg"] == pytest.approx(0.6, abs=0.05)
    assert abs((d["tilt_to_painting_azimuth_deg"] - 120.0 + 180) % 360 - 180) < 5
    assert d["tilt_left_deg"] < 0.02
    assert carded.diagnostics["lights"]["card"] is True


def test_tilt_from_the_levels_with_known_lamp_powers():
    cap = make_capture(shape=(200, 260), n_lights=10, seed=2)
    lights = LightModel.from_positions(cap.light_positions_mm, cap.intensities)
    for tilt, az in ((1.0, 30.0), (0.3, 200.0)):
        card = calibrate_card(render_card(cap, tilt_deg=tilt, tilt_azimuth_deg=az), lights=lights,
                              pixel_size_um=cap.spec.pixel_size_um)
        assert card.tilt_deg == pytest.approx(tilt, abs=0.02)
        assert abs((card.tilt_azimuth_deg - az + 180) % 360 - 180) < 2
        assert card.relief_deg < 0.1
    flat = calibrate_card(render_card(cap), lights=lights, pixel_size_um=cap.spec.pixel_size_um)
    assert flat.tilt_deg < 0.02


def test_unevenness_is_measured_and_gains_have_median_one(beamed):
    even = calibrate_card(render_card(beamed), lights=beamed.light_positions_mm, pixel_size_um=15.0,
                          dark=render_dark_frame(beamed))
    uneven = calibrate_card(render_card(beamed, unevenness=0.02), lights=beamed.light_positions_mm,
                            pixel_size_um=15.0, dark=render_dark_frame(beamed))
    assert even.unevenness < 0.004 < uneven.unevenness < 0.02
    g = uneven.gains
    assert g.shape == (10, 240, 320) and g.dtype == np.float32
    assert np.median(g) == pytest.approx(1.0, abs=0.02)


def test_a_card_that_is_not_flat_is_refused(beamed):
    with pytest.raises(UVPSInputError, match="the card is not flat") as exc:
        calibrate_card(render_card(beamed, relief_um=15.0), lights=beamed.light_positions_mm, pixel_size_um=15.0,
                       dark=render_dark_frame(beamed))
    assert "\n" not in str(exc.value)


def test_a_saturated_card_is_refused(beamed):
    with pytest.raises(UVPSInputError, match="card image .* is saturated"):
        calibrate_card(render_card(beamed, peak_fraction=1.4), lights=beamed.light_positions_mm, pixel_size_um=15.0)


def test_bad_shapes_are_refused(beamed):
    card = render_card(beamed)
    with pytest.raises(UVPSInputError, match="the card has 10 images and the lights 9 lamps"):
        calibrate_card(card, lights=beamed.light_positions_mm[:9], pixel_size_um=15.0)
    with pytest.raises(UVPSInputError, match="dark frame"):
        calibrate_card(card, lights=beamed.light_positions_mm, pixel_size_um=15.0, dark=np.zeros((10, 10)))
    cal = calibrate_card(card, lights=beamed.light_positions_mm, pixel_size_um=15.0)
    with pytest.raises(UVPSInputError, match="the card was taken for 10 lamps"):
        apply_card(beamed.images[:9], cal)


def test_write_read_round_trip(beamed, tmp_path):
    cal = calibrate_card(render_card(beamed, tilt_deg=0.5), lights=beamed.light_positions_mm, pixel_size_um=15.0)
    paths = write_card(cal, tmp_path / "cal", pixel_size_um=15.0)
    assert [p.name for p in paths] == ["card.tif", "card.json"]
    back = read_card(tmp_path / "cal")
    np.testing.assert_allclose(back.coeffs, cal.coeffs)
    assert back.tilt_deg == pytest.approx(cal.tilt_deg, abs=1e-4) and back.shape == cal.shape
    np.testing.assert_allclose(tifffile.imread(paths[0]), cal.gains, rtol=1e-6)
    # the gains divide each image
    view = apply_card(beamed.images, back)
    np.testing.assert_allclose(view[3], beamed.images[3] / cal.gains[3][..., None], rtol=1e-4)


def _uvps(*args):
    return subprocess.run([sys.executable, "-m", "uvps", *map(str, args)], capture_output=True, text=True,
                          timeout=600)


def test_cli_run_with_card_lights_and_dark(tmp_path):
    """`uvps run CAPTURE --card DIR --lights positions.csv --dark FILE`, the real command; a card of
    another lamp count is one line, exit 1, nothing written."""
    spec = SyntheticSpec.realistic(level="top", only=["beams", "vignetting"], shape=(160, 200), n_lights=8, seed=1)
    cap = make_capture(spec)
    folder = tmp_path / "cap"
    write_capture(cap, folder, dark_frame=True, card=render_card(cap, tilt_deg=0.5))
    out = tmp_path / "run"
    args = ["run", folder, "--lights", folder / "lights_positions_mm.csv", "--dark", folder / "dark" / "dark.tif"]
    r = _uvps(*args, "--card", folder / "card", "-o", out)
    assert r.returncode == 0, r.stderr
    log = json.loads((out / "run.json").read_text())
    assert log["params"]["card"].endswith("card")
    assert log["diagnostics"]["card"]["tilt_to_painting_deg"] == pytest.approx(0.5, abs=0.1)
    normals = np.moveaxis(tifffile.imread(out / "normals.tif"), 0, -1)
    assert np.nanmean(_angle(normals, cap.normals)) < 0.4
    other = tmp_path / "card7"
    other.mkdir()
    for p in sorted((folder / "card").glob("*.tif"))[:7]:
        (other / p.name).write_bytes(p.read_bytes())
    bad = tmp_path / "bad"
    r = _uvps(*args, "--card", other, "-o", bad)
    assert r.returncode == 1 and "the card has 7 images and the lights 8 lamps" in r.stderr
    assert len([line for line in r.stderr.splitlines() if "error" in line]) == 1 and not bad.exists()
