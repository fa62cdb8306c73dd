"""scripts/analyse_sphere_pair.py's pinhole reading of a mirror sphere's highlight, on a known geometry: the
figures in docs/decisions/spheres.md ("Two spheres of one capture") rest on it."""
import math
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "scripts"))
import analyse_sphere_pair as asp  # noqa: E402
import benchmark_spheres_real as bsr  # noqa: E402

F = 6000.0
PRINCIPAL = np.array([2000.0, 1500.0])


def _image(x):
    return np.array([PRINCIPAL[0] + F * x[0] / -x[2], PRINCIPAL[1] - F * x[1] / -x[2]])


def _outline(centre):
    """The sphere's outline in the image: its centre (px) and radius along the radial line."""
    d = np.linalg.norm(centre)
    t, a = math.acos(-centre[2] / d), math.asin(1.0 / d)
    s = F * (math.tan(t + a) + math.tan(t - a)) / 2
    az = centre[:2] / max(np.linalg.norm(centre[:2]), 1e-12)
    return PRINCIPAL + s * np.array([az[0], -az[1]]), F * (math.tan(t + a) - math.tan(t - a)) / 2


def test_two_off_axis_spheres_rays_meet_at_the_lamp():
    # two spheres 2 x 7 radii apart, 60 radii from the camera (each about 6.7 deg off the lens axis), lamps
    # beside the camera: the pinhole rays start at the mirror points and point at the lamp
    spheres = [np.array([-7.0, 0.5, -60.0]), np.array([7.0, 0.3, -60.5])]
    lamps = [np.array([-15.0, 10.0, 2.0]), np.array([20.0, -5.0, -10.0]), np.array([3.0, 18.0, 5.0])]
    got, ortho, pts = [], [], []
    for C in spheres:
        centre, radius = _outline(C)
        px = np.array([_image(asp.mirror_point(C, P)) for P in lamps])
        d, C_fit, off, p = asp.pinhole_directions(px, centre, radius, PRINCIPAL, F)
        assert np.allclose(C_fit, C, atol=1e-3 * np.linalg.norm(C))
        truth = np.array([(P - x) / np.linalg.norm(P - x) for P, x in zip(lamps, p)])
        assert bsr._angles(d, truth).max() < 0.01
        got.append(d)
        pts.append(p)
        n = np.c_[(px - centre) * [1, -1] / radius, np.zeros(len(px))]
        n[:, 2] = np.sqrt(1 - (n[:, :2] ** 2).sum(axis=1))
        ortho.append(2 * n[:, 2:] * n - asp.Z)
    # the rays meet: nothing across the baseline; read orthographically they do not point at the lamps
    _, across = bsr.split_by_baseline(got[0], got[1], spheres[1] - spheres[0])
    assert np.abs(across).max() < 0.02
    assert bsr._angles(ortho[0], got[0]).min() > 3.0
