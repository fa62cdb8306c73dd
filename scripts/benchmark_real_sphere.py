#!/usr/bin/env python3
"""The glossy-sphere route on a real capture, against the directions its authors computed.

    .venv/bin/python scripts/benchmark_real_sphere.py [--data ../shared/data/sphere_mirror_psbox]

The data: a dark mirror sphere under 12 lamp positions (PSBox, ``LightProbe-2``; 950 x 950 sRGB JPEGs),
its circle (``circle_data.txt``: centre x, centre y, radius in px, y counted from the image's bottom edge:
read as it stands it is 20 px below the rim seen in the room-lit ``ref.JPG``) and the lamps' directions
(``light_directions.txt``, 3 x 12, x right, y up, z toward the camera). The sphere fills the frame and
sits on a stand; under the lamps it is dark on a dark ground and shows no rim, so the circle is given
(``uvps calibrate --sphere-circles``) or found on the room-lit ``ref.JPG`` (``--sphere-reference``);
uvps's directions are compared with the file's for each circle.
"""
import argparse
import sys
from pathlib import Path

import numpy as np

from uvps.core.spheres import REFERENCE_RIM_FRACTION, Sphere, _grey, _refine_circle, calibrate_spheres, detect_spheres
from uvps.files.io import read_image

DEFAULT = Path(__file__).resolve().parents[2] / "shared" / "data" / "sphere_mirror_psbox"


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", default=str(DEFAULT))
    data = Path(ap.parse_args(argv).data)
    if not data.is_dir():
        print(f"{data}: not found (the real captures live in ../shared/data)", file=sys.stderr)
        return 1
    files = sorted(data.glob("Image_*.JPG"))
    images = np.stack([read_image(f) for f in files])
    M = images.shape[1]
    x, y, r = np.loadtxt(data / "circle_data.txt")
    truth = np.loadtxt(data / "light_directions.txt")
    truth = (truth.T if truth.shape[0] == 3 else truth)
    truth = truth / np.linalg.norm(truth, axis=1, keepdims=True)
    ref = _grey(read_image(data / "ref.JPG"))
    (cx, cy), cr = _refine_circle(ref, (x, M - 1 - y), r)[:2]
    found = detect_spheres(read_image(data / "ref.JPG")[None], min_rim_fraction=REFERENCE_RIM_FRACTION)
    circles = {"circle_data.txt, y from the bottom": (x, M - 1 - y, r),
               "circle_data.txt, y read as a row": (x, y, r),
               "fitted on ref.JPG at the file's circle": (cx, cy, cr)}
    print(f"found on ref.JPG (uvps calibrate --sphere-reference): {len(found)} circle(s)")
    if found:
        s = max(found, key=lambda s: s.radius_px)
        circles["found on ref.JPG (--sphere-reference)"] = (s.centre_px[0], s.centre_px[1], s.radius_px)
    print(f"{len(files)} images {images.shape[2]} x {M}; angle (deg) between uvps's and the file's directions")
    for name, (c, row, rad) in circles.items():
        cal = calibrate_spheres(images, pixel_size_um=15.0, spheres=[Sphere((c, row), rad, "glossy", "given")],
                                saturation=255)
        ang = np.degrees(np.arccos(np.clip(np.sum(cal.directions * truth, axis=1), -1, 1)))
        print(f"  {name} ({c:.1f}, {row:.1f}) r {rad:.1f}: median {np.median(ang):.2f}, max {ang.max():.2f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
