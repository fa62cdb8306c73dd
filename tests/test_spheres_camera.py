"""Spheres photographed by a pinhole camera (``uvps calibrate --camera-distance-mm``): rendered under a
camera 300 mm above a 24 x 18 mm field, two spheres in opposite corners (8 mm off the lens's axis, a
1.9 deg off-axis angle at their centres) read orthographically are 2 deg off; with the camera's distance
as good as the orthographic renders read orthographically (tests/test_calibration.py's tolerances)."""
import json
import subprocess
import sys

import numpy as np
import pytest

from uvps.core.sphere_view import outline, pixel_normals, sphere_from_outline
from uvps.core.spheres import calibrate_spheres
from uvps.errors import UVPSInputError
from uvps.files.calibration import read_calibration
from uvps.testing.synthetic import make_capture
from uvps.testing.synthetic_spheres import SphereSpec, make_sphere_capture, write_sphere_capture

PX = 60.0       # 400 x 300 px of 60 um: a 24 x 18 mm field
D = 300.0


def _angles(a, b):
    a = np.asarray(a, float) / np.linalg.norm(a, axis=-1, keepdims=True)
    b = np.asarray(b, float) / np.linalg.norm(b, axis=-1, keepdims=True)
    return np.degrees(np.arccos(np.clip((a * b).sum(-1), -1, 1)))


@pytest.fixture(scope="module")
def seen(tmp_path_factory):
    """Two spheres of each kind asked for, 3 mm, in opposite corners, under a camera 300 mm away."""
    cap = make_capture(shape=(300, 400), n_lights=6, seed=4, pixel_size_um=PX, rgb=False)
    out = {}

    def capture(kind):
        if kind not in out:
            spheres = [SphereSpec(kind, (0.15, 0.2), 3.0), SphereSpec(kind, (0.85, 0.8), 3.0)]
            out[kind] = make_sphere_capture(cap, spheres, camera_distance_mm=D)
        return out[kind]
    return capture


def test_outline_and_normals_known_answers():
    # on the axis: a circle of radius D tan(a), sin(a) = R / (D - R); the inversion returns the sphere
    c, r, axes = outline([0.0, 0.0, 2.5], 2.5, D)
    a = np.arcsin(2.5 / (D - 2.5))
    assert np.allclose(c, 0) and r == pytest.approx(D * np.tan(a), rel=1e-12)
    for S in ([12.0, -9.0, 2.5], [-20.0, 15.0, 1.0]):
        got, R = sphere_from_outline(*outline(S, S[2], 150.0)[:2], 150.0)
        np.testing.assert_allclose(got, S, atol=1e-9)
        assert R == pytest.approx(S[2], rel=1e-9)
    # off the axis the outline is drawn out along the line from the centre, by about 1 / cos of the angle
    _, _, axes = outline([20.0, 0.0, 2.5], 2.5, 150.0)
    assert axes.max() / axes.min() == pytest.approx(1 / np.cos(np.arctan2(20.0, 150.0 - 2.5)), rel=2e-3)
    # the ray through the centre's image meets the sphere where its normal points at the camera; the one
    # through the outline's centre (a conic's centre is not the centre's image) 0.13 deg from it
    S = np.array([20.0, 0.0, 2.5])
    C = np.array([0, 0, 150.0])
    A = C + (S - C) * 150.0 / (150.0 - 2.5)
    n, rho = pixel_normals(np.array([A[0]]), np.array([A[1]]), S, 2.5, 150.0)
    assert _angles(n[0], C - S) < 1e-6 and rho[0] < 1e-8
    c = outline(S, 2.5, 150.0)[0]
    assert 0.1 < _angles(pixel_normals(c[:1], c[1:], S, 2.5, 150.0)[0][0], C - S) < 0.15
    # a point on the outline is where the ray grazes the sphere
    e = c + [outline(S, 2.5, 150.0)[2].max(), 0.0]
    n, rho = pixel_normals(e[:1], e[1:], S, 2.5, 150.0)
    w = np.array([e[0], e[1], -150.0])
    assert rho[0] == pytest.approx(1.0, abs=1e-9) and abs(n[0] @ w / np.linalg.norm(w)) < 1e-6


def test_rendered_outline_is_the_cameras(seen):
    sc = seen("glossy")
    for s in sc.spheres:
        c, r, _ = outline(s["centre_mm"], 3.0, D)
        col, row = c[0] / (PX / 1000) + 199.5, 149.5 - c[1] / (PX / 1000)
        # the rendered pixels' cover (an 8 x 8 grid of rays per rim pixel) against the conic
        assert abs(s["centre_px"][0] - col) < 0.01 and abs(s["centre_px"][1] - row) < 0.01
        assert s["radius_px"] == pytest.approx(r / (PX / 1000), abs=0.01)


@pytest.mark.parametrize("kind", ["glossy", "matte"])
def test_camera_distance_reads_off_axis_spheres(seen, kind):
    sc = seen(kind)
    L = sc.light_positions_mm
    ortho = calibrate_spheres(sc.images, pixel_size_um=PX, saturation=65535, kind=kind)
    # orthographically each sphere's lamps are about its off-axis angle off (1.9 deg): the effect shown
    assert min(_angles(f.directions, L - f.points_mm).max() for f in ortho.fits) > 1.0
    cal = calibrate_spheres(sc.images, pixel_size_um=PX, saturation=65535, kind=kind, camera_distance_mm=D)
    assert cal.diagnostics["camera_distance_mm"] == D
    for f in cal.fits:      # orthographic renders read orthographically: 0.06-0.58 deg per sphere
        assert _angles(f.directions, L - f.points_mm).max() < (0.5 if kind == "glossy" else 0.15)
    assert _angles(cal.directions, L).max() < 0.5
    assert cal.positions_mm is not None
    assert (np.linalg.norm(cal.positions_mm - L, axis=1) / np.linalg.norm(L, axis=1)).max() < 0.15


def _uvps(*args):
    return subprocess.run([sys.executable, "-m", "uvps", *map(str, args)], capture_output=True, text=True,
                          timeout=600)


def test_calibrate_records_the_camera_and_refuses_bad_distances(seen, tmp_path):
    sc = seen("glossy")
    write_sphere_capture(sc, tmp_path / "spheres")
    cal = tmp_path / "CAL"
    r = _uvps("calibrate", "--spheres", tmp_path / "spheres", "--camera-distance-mm", D, "-o", cal)
    assert r.returncode == 0, r.stderr
    doc = json.loads((cal / "calibration.json").read_text())
    assert doc["camera_distance_mm"] == D and doc["diagnostics"]["camera_distance_mm"] == D
    lights = json.loads((cal / "lights.json").read_text())
    assert lights["mode"] == "near"
    assert _angles([lp["direction"] for lp in lights["lights"]], sc.light_positions_mm).max() < 0.5
    assert read_calibration(cal).summary()["camera_distance_mm"] == D      # what a run records of it
    for bad in ("0", "-300", "nan", "5"):      # 5 mm: below the 6 mm spheres' tops
        out = tmp_path / f"BAD{bad}"
        r = _uvps("calibrate", "--spheres", tmp_path / "spheres", "--camera-distance-mm", bad, "-o", out)
        assert r.returncode == 1, (bad, r.stderr)
        lines = [ln for ln in r.stderr.strip().splitlines() if "error" in ln]
        assert len(lines) == 1 and "camera_distance_mm" in lines[0] and bad in lines[0], (bad, r.stderr)
        assert not out.exists()
    with pytest.raises(UVPSInputError, match="camera_distance_mm"):
        calibrate_spheres(sc.images[:, :10, :10], pixel_size_um=PX, camera_distance_mm=float("inf"))
    # a light file's lamps are not read through the camera: the option is refused, not silently dropped
    lp = tmp_path / "lamps.lp"
    lp.write_text("2\nimg0.tif 0.5 0.0 0.866\nimg1.tif 0.0 0.5 0.866\n")
    out = tmp_path / "LP"
    r = _uvps("calibrate", "--lights", lp, "--camera-distance-mm", D, "-o", out)
    lines = [ln for ln in r.stderr.strip().splitlines() if "error" in ln]
    assert r.returncode == 1 and len(lines) == 1 and "camera_distance_mm applies to spheres" in lines[0], r.stderr
    assert not out.exists()
