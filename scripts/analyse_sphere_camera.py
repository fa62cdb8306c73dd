#!/usr/bin/env python3
"""What the camera's distance does to a sphere calibration: two spheres in opposite corners of the field, rendered
by the generator under a pinhole camera ``D`` mm above the image centre (``make_sphere_capture(...,
camera_distance_mm=D)``), read by ``calibrate_spheres`` orthographically (no ``--camera-distance-mm``), with the
true ``D``, and with ``D`` 3 % and 10 % too long and too short. The figures of docs/decisions/spheres.md's
"A camera at a working distance".

    OMP_NUM_THREADS=1 .venv/bin/python scripts/analyse_sphere_camera.py [--distances 300,500] [--kinds glossy,matte]

The field is the project's (60 x 45 mm; 1600 x 1200 px of 37.5 um, 0.4 of the 15 um pixels' resolution, which
the geometry does not depend on), 6 lamps of the generator's default capture, two 2.5 mm spheres 29 mm off the
axis (fractions 0.1, 0.12 and 0.9, 0.88 of the frame). Per row: each sphere's worst lamp direction (deg, from
that sphere), the worst direction from the image centre (deg) and the worst lamp position (% of its distance;
"-" where the rays are too nearly parallel to place the lamps and the calibration keeps directions).
"""
import argparse
import math

import numpy as np

from uvps.core.spheres import calibrate_spheres
from uvps.testing.synthetic import make_capture
from uvps.testing.synthetic_spheres import SphereSpec, make_sphere_capture

PX = 37.5
SHAPE = (1200, 1600)
CORNERS = ((0.1, 0.12), (0.9, 0.88))
RADIUS_MM = 2.5


def _angles(a, b):
    a = np.asarray(a, float) / np.linalg.norm(a, axis=-1, keepdims=True)
    b = np.asarray(b, float) / np.linalg.norm(b, axis=-1, keepdims=True)
    return np.degrees(np.arccos(np.clip((a * b).sum(-1), -1, 1)))


def errors(sc, kind, distance):
    """(per-sphere worst direction deg, worst direction from the centre deg, worst position % or None)."""
    L = sc.light_positions_mm
    cal = calibrate_spheres(sc.images, pixel_size_um=PX, saturation=65535, kind=kind, camera_distance_mm=distance)
    per = [float(_angles(f.directions, L - f.points_mm).max()) for f in cal.fits]
    pos = None
    if cal.positions_mm is not None:
        pos = float((np.linalg.norm(cal.positions_mm - L, axis=1) / np.linalg.norm(L, axis=1)).max() * 100)
    return per, float(_angles(cal.directions, L).max()), pos


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--distances", default="300,500", help="camera distances to render, mm")
    ap.add_argument("--kinds", default="glossy,matte", help="sphere kinds")
    args = ap.parse_args()
    cap = make_capture(shape=SHAPE, n_lights=6, seed=4, pixel_size_um=PX, rgb=False)
    print("| kind | camera (mm) | off-axis (deg) | read with | per sphere (deg) | from the centre (deg) "
          "| positions (%) |")
    print("|---|---|---|---|---|---|---|")
    for kind in args.kinds.split(","):
        for D in (float(v) for v in args.distances.split(",")):
            sc = make_sphere_capture(cap, [SphereSpec(kind, c, RADIUS_MM) for c in CORNERS], camera_distance_mm=D)
            off = max(math.degrees(math.atan2(math.hypot(*s["centre_mm"][:2]), D - RADIUS_MM)) for s in sc.spheres)
            for label, d in (("orthographic", None), ("D", D), ("1.03 D", 1.03 * D), ("0.97 D", 0.97 * D),
                             ("1.1 D", 1.1 * D), ("0.9 D", 0.9 * D)):
                per, centre, pos = errors(sc, kind, d)
                print(f"| {kind} | {D:.0f} | {off:.1f} | {label} | {' / '.join(f'{v:.2f}' for v in per)} | "
                      f"{centre:.2f} | {'-' if pos is None else f'{pos:.1f}'} |", flush=True)


if __name__ == "__main__":
    main()
