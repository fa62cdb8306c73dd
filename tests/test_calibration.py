"""`uvps calibrate` and `uvps run --calibration` through the real command (a subprocess) and in process:
the calibration folder, its reuse, relight's .dome round trip, and every bad input (one line, exit 1,
nothing written)."""
import json
from pathlib import Path
import subprocess
import sys

import numpy as np
import pytest
import tifffile

from uvps.commands.batch import _side_files
from uvps.files.calibration import calibration_of_run, read_calibration, read_dome, write_dome
from uvps.files.io import sha256_file
from uvps.commands import COMMANDS
from uvps.errors import UVPSInputError
from uvps.testing.synthetic import make_capture, write_capture
from uvps.testing.synthetic_spheres import SphereSpec, make_sphere_capture, write_sphere_capture

PX = 60.0     # 400 x 300 px of 60 um: a 24 x 18 mm field


def uvps(*args, cwd=None):
    return subprocess.run([sys.executable, "-m", "uvps", *map(str, args)], capture_output=True, text=True,
                          timeout=600, cwd=cwd)


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    """A painting capture (black level 200, a dark frame) and a sphere capture under its lamps."""
    root = tmp_path_factory.mktemp("cal")
    cap = make_capture(shape=(300, 400), n_lights=6, seed=4, pixel_size_um=PX, rgb=False, black_level=200.0)
    write_capture(cap, root / "cap", dark_frame=True)
    sc = make_sphere_capture(cap, [SphereSpec("glossy", (0.15, 0.2), 3.0), SphereSpec("glossy", (0.85, 0.8), 3.0)])
    write_sphere_capture(sc, root / "spheres")
    return root, cap, sc


def _angles(a, b):
    a = np.asarray(a, float)
    b = np.asarray(b, float)
    c = (a * b).sum(-1) / np.linalg.norm(a, axis=-1) / np.linalg.norm(b, axis=-1)
    return np.degrees(np.arccos(np.clip(c, -1, 1)))


def test_calibrate_then_run_with_the_calibration(scene):
    root, cap, sc = scene
    cal = root / "CAL"
    r = uvps("calibrate", "--spheres", root / "spheres", "--dark", root / "cap" / "dark" / "dark.tif", "-o", cal)
    assert r.returncode == 0, r.stderr
    doc = json.loads((cal / "calibration.json").read_text())
    assert doc["format"] == "uvps-calibration" and doc["version"] == 1 and doc["route"] == "spheres"
    assert doc["n_lamps"] == 6 and doc["image_shape"] == [300, 400] and doc["pixel_size_um"] == PX
    assert [s["kind"] for s in doc["spheres"]] == ["glossy", "glossy"]
    assert all(s["source"] == "detected" for s in doc["spheres"])
    assert doc["dark"] is True and doc["card"] is None
    # provenance: every sphere image and the dark frame, by SHA-256
    assert len(doc["inputs"]) == 7 and all(len(h) == 64 for h in doc["inputs"].values())
    lights = json.loads((cal / "lights.json").read_text())
    assert lights["mode"] == "near" and all(lp["file"] is None for lp in lights["lights"])
    L = cap.light_positions_mm
    assert _angles([lp["direction"] for lp in lights["lights"]], L).max() < 0.5
    P = np.array([lp["position_mm"] for lp in lights["lights"]])
    assert (np.linalg.norm(P - L, axis=1) / np.linalg.norm(L, axis=1)).max() < 0.15
    for lamp in doc["lamps"]:
        assert lamp["direction_sigma_deg"] > 0 and lamp["distance_sigma_pct"] > 0
    assert (cal / "dark.tif").is_file() and (cal / "spheres.png").is_file() and (cal / "rig.dome").is_file()
    np.testing.assert_array_equal(tifffile.imread(cal / "dark.tif"), tifffile.imread(root / "cap/dark/dark.tif"))

    run = root / "RUN"
    r = uvps("run", root / "cap", "--calibration", cal, "-o", run)
    assert r.returncode == 0, r.stderr
    rj = json.loads((run / "run.json").read_text())
    assert rj["params"]["calibration"] == str(cal)
    assert rj["diagnostics"]["calibration"]["route"] == "spheres"
    assert len(rj["diagnostics"]["calibration"]["sha256"]) == 64
    assert rj["diagnostics"]["additive"]["source"] == "dark frame"     # the calibration's dark frame
    run_lights = json.loads((run / "lights.json").read_text())
    assert run_lights["source"] == "positions"
    assert _angles([lp["direction"] for lp in run_lights["lights"]], L).max() < 0.5
    nrm = np.moveaxis(tifffile.imread(run / "normals.tif"), 0, -1)
    assert np.nanmean(_angles(nrm, cap.normals)) < 1.0
    # what `uvps changes` records of each date, and what makes `uvps batch` runs stale
    rec = calibration_of_run(run)
    assert rec["lamps"] == "calibration" and rec["calibration"]["sha256"] == sha256_file(cal / "calibration.json")
    assert calibration_of_run(tmp_missing := root / "nothing")["calibration"] is None and not tmp_missing.exists()
    assert _side_files({"calibration": str(cal)})["calibration"]["sha256"] == rec["calibration"]["sha256"]


def test_run_refuses_another_lamp_count_or_size(scene, tmp_path):
    root, cap, _ = scene
    cal = tmp_path / "CAL"
    COMMANDS["calibrate"]({"spheres": [str(root / "spheres")]}, {}, cal)
    few = tmp_path / "few"
    few.mkdir()
    for k in range(5):
        (few / f"uv_{k:02d}.tif").write_bytes((root / "cap" / f"uv_{k:02d}.tif").read_bytes())
    r = uvps("run", few, "--calibration", cal, "-o", tmp_path / "RUN")
    assert r.returncode == 1
    assert r.stderr.strip().splitlines()[-1].endswith("has 6 lamps; the capture has 5 images (lamps are matched "
                                                      "to the images by order)")
    assert not (tmp_path / "RUN").exists()
    small = tmp_path / "small"
    small.mkdir()
    for k in range(6):
        img = tifffile.imread(root / "cap" / f"uv_{k:02d}.tif")[:200, :300]
        tifffile.imwrite(small / f"uv_{k:02d}.tif", img)
    r = uvps("run", small, "--calibration", cal, "-o", tmp_path / "RUN")
    assert r.returncode == 1 and "was made on 400 x 300 px images; the capture is 300 x 200 px" in r.stderr
    assert not (tmp_path / "RUN").exists()
    r = uvps("run", root / "cap", "--calibration", cal, "--lights", root / "cap" / "lights.lp", "-o", tmp_path / "R")
    assert r.returncode == 1 and "give calibration or lights, not both" in r.stderr


def test_calibrate_bad_inputs_write_nothing(scene, tmp_path):
    root, _, _ = scene
    out = tmp_path / "CAL"
    # a dark frame of another size
    tifffile.imwrite(tmp_path / "dark.tif", np.zeros((100, 100), np.uint16))
    r = uvps("calibrate", "--spheres", root / "spheres", "--dark", tmp_path / "dark.tif", "-o", out)
    assert r.returncode == 1 and "dark frame" in r.stderr and "expected (300, 400)" in r.stderr
    assert len(r.stderr.strip().splitlines()) == 1 and not out.exists()
    # no sphere in the images (the painting capture given as the sphere capture): names the image
    r = uvps("calibrate", "--spheres", root / "cap", "-o", out)
    assert r.returncode == 1 and "no sphere found in the sphere capture" in r.stderr and "uv_00.tif" in r.stderr
    assert not out.exists()
    # every sphere cut by the frame: one line naming the capture and its first image, nothing written
    _, cap, _ = scene
    write_sphere_capture(make_sphere_capture(cap, [SphereSpec("glossy", (0.98, 0.5), 3.0)]), tmp_path / "cut",
                         truth=False)
    r = uvps("calibrate", "--spheres", tmp_path / "cut", "-o", out)
    errors = [ln for ln in r.stderr.splitlines() if not ln.startswith("INFO ")]
    assert r.returncode == 1 and len(errors) == 1, r.stderr
    last = errors[0]
    assert "every sphere found is cut by the frame" in last and str(tmp_path / "cut") in last and "sphere_00.tif" in last
    assert not out.exists()
    # neither spheres nor a rig
    r = uvps("calibrate", "-o", out)
    assert r.returncode == 1 and "needs exactly one of spheres" in r.stderr
    # an existing folder that is not a calibration is not replaced
    other = tmp_path / "other"
    other.mkdir()
    (other / "keep.txt").write_text("mine")
    r = uvps("calibrate", "--spheres", root / "spheres", "-o", other)
    assert r.returncode == 1 and "is not a calibration folder" in r.stderr
    assert (other / "keep.txt").read_text() == "mine"


def test_given_circles_override_detection(scene, tmp_path):
    root, cap, sc = scene
    circles = tmp_path / "circles.csv"
    t = sc.spheres[0]
    circles.write_text(f"col,row,radius_px,kind\n{t['centre_px'][0]},{t['centre_px'][1]},{t['radius_px']},glossy\n")
    COMMANDS["calibrate"]({"spheres": [str(root / "spheres")], "sphere_circles": str(circles)}, {}, tmp_path / "C")
    doc = json.loads((tmp_path / "C" / "calibration.json").read_text())
    assert len(doc["spheres"]) == 1 and doc["spheres"][0]["source"] == "given"
    assert doc["lamps"][0]["position_mm"] is None          # one sphere: far directions
    assert str(circles) in doc["inputs"]


def test_dome_round_trip_and_rig_routes(scene, tmp_path):
    root, cap, _ = scene
    cal = tmp_path / "CAL"
    COMMANDS["calibrate"]({"spheres": [str(root / "spheres")]}, {}, cal)
    rig = read_dome(cal / "rig.dome")
    lights = json.loads((cal / "lights.json").read_text())
    P = np.array([lp["position_mm"] for lp in lights["lights"]])
    np.testing.assert_allclose(rig.positions, P, rtol=1e-6)
    assert rig.image_width == pytest.approx(400 * PX / 1000)
    raw = json.loads((cal / "rig.dome").read_text())
    assert raw["lightConfiguration"] == "lights3d" and set(raw["positions3d"][0]) == {"x", "y", "z"}
    # the dome read back gives the same lamps
    again = tmp_path / "CAL2"
    COMMANDS["calibrate"]({"dome": str(cal / "rig.dome")}, {"pixel_size_um": PX}, again)
    lights2 = json.loads((again / "lights.json").read_text())
    np.testing.assert_allclose([lp["position_mm"] for lp in lights2["lights"]], P, rtol=1e-6)
    assert read_calibration(again).doc["route"] == "dome"
    # a dome in another unit, scaled by its imageWidth to the field's width
    write_dome(tmp_path / "cm.dome", directions=P, positions_mm=P / 10, image_width_mm=2.4)
    COMMANDS["calibrate"]({"dome": str(tmp_path / "cm.dome")}, {"pixel_size_um": PX, "image_width_mm": 24.0},
                          tmp_path / "CAL3")
    lights3 = json.loads((tmp_path / "CAL3" / "lights.json").read_text())
    np.testing.assert_allclose([lp["position_mm"] for lp in lights3["lights"]], P, rtol=1e-6)
    # an .lp rig: directions only
    COMMANDS["calibrate"]({"lights": str(root / "cap" / "lights.lp")}, {"pixel_size_um": PX}, tmp_path / "CAL4")
    doc4 = read_calibration(tmp_path / "CAL4").doc
    assert doc4["route"] == "lp" and doc4["image_shape"] is None and doc4["lamps"][0]["position_mm"] is None
    with pytest.raises(UVPSInputError, match="pixel_size_um is required"):
        COMMANDS["calibrate"]({"lights": str(root / "cap" / "lights.lp")}, {}, tmp_path / "CAL5")


def test_read_dome_errors(tmp_path):
    p = tmp_path / "bad.dome"
    p.write_text("[1, 2]")
    with pytest.raises(UVPSInputError, match="expected relight's JSON dome format"):
        read_dome(p)
    p.write_text(json.dumps({"lightConfiguration": "directional", "directions": [{"x": 0, "y": 0, "z": -1}]}))
    with pytest.raises(UVPSInputError, match="light 1 points away from the camera"):
        read_dome(p)
    p.write_text(json.dumps({"directions": []}))
    with pytest.raises(UVPSInputError, match="has no directions or positions"):
        read_dome(p)
    with pytest.raises(UVPSInputError, match="expected a folder written by `uvps calibrate`"):
        read_calibration(tmp_path)


def test_calibrate_stores_a_card_and_the_run_divides_it_out(tmp_path):
    """`uvps calibrate --lights positions --card DIR --dark FILE`: the card's gains are stored in the
    calibration folder (card.tif, card.json; calibration.json says so), and `uvps run --calibration`
    divides them out: lamp beams and vignetting no longer bend the normals. A card of another lamp
    count is one line, exit 1, nothing written."""
    from uvps.testing.synthetic import SyntheticSpec, render_card

    spec = SyntheticSpec.realistic(level="top", only=["beams", "vignetting"], shape=(160, 200), n_lights=8, seed=1)
    cap = make_capture(spec)
    folder = tmp_path / "cap"
    write_capture(cap, folder, dark_frame=True, card=render_card(cap, tilt_deg=0.5))
    cal = tmp_path / "cal"
    common = ["--lights", folder / "lights_positions_mm.csv", "--dark", folder / "dark" / "dark.tif",
              "--pixel-size-um", cap.spec.pixel_size_um]
    r = subprocess.run([sys.executable, "-m", "uvps", "calibrate", *map(str, common), "--card", str(folder / "card"),
                        "-o", str(cal)], capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stderr
    assert (cal / "card.tif").is_file() and (cal / "card.json").is_file()
    doc = json.loads((cal / "calibration.json").read_text())
    assert doc["card"]["n_lamps"] == 8
    assert any(k.endswith(".tif") and "card" in k for k in doc["inputs"])
    out = tmp_path / "run"
    r = subprocess.run([sys.executable, "-m", "uvps", "run", str(folder), "--calibration", str(cal), "-o", str(out)],
                       capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stderr
    log = json.loads((out / "run.json").read_text())
    assert "card" in log["diagnostics"]
    normals = np.moveaxis(tifffile.imread(out / "normals.tif"), 0, -1)
    cos = np.clip(np.sum(normals * cap.normals, axis=-1), -1, 1)
    assert np.nanmean(np.degrees(np.arccos(cos))) < 0.4
    seven = tmp_path / "card7"
    seven.mkdir()
    for p in sorted((folder / "card").glob("*.tif"))[:7]:
        (seven / p.name).write_bytes(p.read_bytes())
    bad = tmp_path / "bad"
    r = subprocess.run([sys.executable, "-m", "uvps", "calibrate", *map(str, common), "--card", str(seven),
                        "-o", str(bad)], capture_output=True, text=True, timeout=600)
    assert r.returncode == 1 and not bad.exists()
    assert len([ln for ln in r.stderr.splitlines() if "error" in ln]) == 1, r.stderr


def _mirror_rays(lamps, centre, radius):
    """The directions to each lamp from the point of a mirror sphere that reflects it toward the camera (+z)."""
    out = []
    for L in lamps:
        n = np.array([0.0, 0.0, 1.0])
        for _ in range(30):
            v = L - (centre + radius * n)
            h = v / np.linalg.norm(v) + (0.0, 0.0, 1.0)
            n = h / np.linalg.norm(h)
        out.append(L - (centre + radius * n))
    return np.array(out)


def test_a_dark_sphere_on_a_dark_ground_is_found_on_a_reference_picture(tmp_path):
    """A black sphere on a black ground shows little but its highlights and the flare's spikes under the
    lamps: a room-lit picture of it in place finds it (`--sphere-reference`), the lamps' images alone
    too, and a reference of another size is refused in one line."""
    import dataclasses

    cap = make_capture(shape=(300, 400), n_lights=6, seed=4, pixel_size_um=PX, rgb=False)
    spheres = [SphereSpec("glossy", (0.5, 0.5), 5.0)]
    dark = make_sphere_capture(dataclasses.replace(cap, albedo=np.full_like(cap.albedo, 0.005)), spheres, stand=True)
    write_sphere_capture(dark, tmp_path / "spheres")
    room = make_sphere_capture(dataclasses.replace(cap, albedo=np.full_like(cap.albedo, 0.6)), spheres, stand=True,
                               flare=False)
    tifffile.imwrite(tmp_path / "ref.tif", np.median(room.images, axis=0).astype(np.uint16))
    r = uvps("calibrate", "--spheres", tmp_path / "spheres", "-o", tmp_path / "A")
    # and without it: the rim in the logarithm of the median, found by a RANSAC circle on its edges among the
    # flare's spikes
    r = uvps("calibrate", "--spheres", tmp_path / "spheres", "-o", tmp_path / "A")
    assert r.returncode == 0, r.stderr
    (s,) = json.loads((tmp_path / "A" / "calibration.json").read_text())["spheres"]
    t = dark.spheres[0]
    assert s["source"] == "detected" and s["kind"] == "glossy"
    assert np.hypot(s["centre_px"][0] - t["centre_px"][0], s["centre_px"][1] - t["centre_px"][1]) < 0.5
    COMMANDS["calibrate"]({"spheres": [str(tmp_path / "spheres")], "sphere_reference": str(tmp_path / "ref.tif")},
                          {}, tmp_path / "C")
    doc = json.loads((tmp_path / "C" / "calibration.json").read_text())
    (s,) = doc["spheres"]
    t = dark.spheres[0]
    assert s["source"] == "reference" and s["kind"] == "glossy"
    assert np.hypot(s["centre_px"][0] - t["centre_px"][0], s["centre_px"][1] - t["centre_px"][1]) < 0.5
    assert abs(s["radius_px"] - t["radius_px"]) < 0.5
    D = np.array([lp["direction"] for lp in doc["lamps"]])
    assert _angles(D, _mirror_rays(cap.light_positions_mm, np.asarray(t["centre_mm"]), 5.0)).max() < 0.3
    assert str(tmp_path / "ref.tif") in doc["inputs"]
    tifffile.imwrite(tmp_path / "small.tif", np.zeros((100, 100), np.uint16))
    r = uvps("calibrate", "--spheres", tmp_path / "spheres", "--sphere-reference", tmp_path / "small.tif",
             "-o", tmp_path / "B")
    assert r.returncode == 1 and "small.tif is 100 x 100 px; expected 400 x 300" in r.stderr
    assert not (tmp_path / "B").exists()


#: The real captures (../shared/data beside the project, as docs/benchmarks.md writes it).
DATA = next((p / "shared" / "data" for p in Path(__file__).resolve().parents if (p / "shared" / "data").is_dir()),
            Path("/work/shared/data"))
PSBOX = DATA / "sphere_mirror_psbox"


@pytest.mark.skipif(not PSBOX.is_dir(), reason="the real captures of ../shared/data are not on this machine")
def test_a_real_mirror_sphere_with_no_circle_kind_or_reference(tmp_path):
    """PSBox's LightProbe-2 (MIT): a dark mirror sphere filling a 950 px frame, 12 JPEGs, saturated highlights
    with a flare and a scratch's streak, a lit figure and a saturated spot the sphere reflects in every
    image, its lower part behind a cork stand. Found and calibrated from the lamps' images alone, within
    1 deg of the directions its authors computed from it (light_directions.txt, their own circle)."""
    out = tmp_path / "CAL"
    r = uvps("calibrate", "--spheres", PSBOX, "--pixel-size-um", "100", "-o", out)
    assert r.returncode == 0, r.stderr
    doc = json.loads((out / "calibration.json").read_text())
    (s,) = doc["spheres"]
    assert s["kind"] == "mirror" and s["source"] == "detected"
    xc, yc, rad = np.loadtxt(PSBOX / "circle_data.txt")        # 1-based, y up from the bottom row
    assert np.hypot(s["centre_px"][0] - (xc - 1), s["centre_px"][1] - (950 - yc)) < 4.0
    assert abs(s["radius_px"] - rad) < 4.0
    published = np.loadtxt(PSBOX / "light_directions.txt").T
    err = _angles([lamp["direction"] for lamp in doc["lamps"]], published)
    assert err.max() < 1.0, err
