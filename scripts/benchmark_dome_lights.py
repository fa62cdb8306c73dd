"""Lamps estimated without a light file on a real dome capture whose low lamps leave parts of the field dark,
compared with the capture's published directions (its RTI .lp file).

    OMP_NUM_THREADS=1 python scripts/benchmark_dome_lights.py ../shared/data/lion_relief_rti --pixel-size-um 100

Prints the angle (and the azimuth difference) between each estimated lamp direction (from the image centre) and the .lp direction:
the median and 90th percentile over all lamps and over those below 15 deg of elevation, and the
photometric residual the estimate leaves.
"""
import argparse
from pathlib import Path

import numpy as np

from uvps.core.pipeline import RunOptions, estimate_capture_lights, remove_additive
from uvps.files.io import read_capture


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("folder", type=Path, help="capture folder holding jpg/ and dirs.lp")
    ap.add_argument("--pixel-size-um", type=float, default=100.0)
    a = ap.parse_args(argv)
    cap = read_capture(str(a.folder / "jpg"), pixel_size_um=a.pixel_size_um)
    opts = RunOptions()
    cap, offset = remove_additive(cap, options=opts)[:2]
    lights = estimate_capture_lights(cap, options=opts)
    D = np.array([ln.split()[1:4] for ln in (a.folder / "dirs.lp").read_text().splitlines()[1:] if ln.strip()], float)
    D /= np.linalg.norm(D, axis=1, keepdims=True)
    P = lights.model.positions_mm
    P = P / np.linalg.norm(P, axis=1, keepdims=True)
    err = np.degrees(np.arccos(np.clip((P * D).sum(1), -1, 1)))
    el = np.degrees(np.arcsin(D[:, 2]))
    low = el < 15
    daz = np.degrees(np.arctan2(P[:, 1], P[:, 0]) - np.arctan2(D[:, 1], D[:, 0]))
    daz = np.abs((daz + 180) % 360 - 180)
    rms = float(np.sqrt(lights.estimate.residual_history[-1]["cost"]))
    print(f"{len(D)} lamps ({int(low.sum())} below 15 deg): direction error median {np.median(err):.2f} deg, "
          f"90th percentile {np.percentile(err, 90):.2f} deg; below 15 deg: median {np.median(err[low]):.2f}, "
          f"90th percentile {np.percentile(err[low], 90):.2f} deg; azimuth error median {np.median(daz):.2f} "
          f"(below 15 deg {np.median(daz[low]):.2f}) deg; residual {100 * rms:.1f} %")
    return err, daz, el, rms


if __name__ == "__main__":
    main()
