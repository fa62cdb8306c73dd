#!/usr/bin/env python3
"""Real sphere captures through ``uvps calibrate`` with nothing but the lamps' images: no circle, no kind,
no reference picture. Each capture's directions are compared with its published ones where it has them,
and the captures given as one capture's spheres with each other.

    OMP_NUM_THREADS=1 .venv/bin/python scripts/benchmark_spheres_real.py \\
        [--capture NAME=FOLDER[:LIGHTS]] ... [--same-lamps NAME,NAME] ...

Default: ``../shared/data/sphere_mirror_psbox`` (PSBox's LightProbe-2, MIT) with its
``light_directions.txt``. ``LIGHTS`` is a published directions file: 3 x K or K x 3 numbers, an optional
first line holding K alone (x right, y up, z toward the camera). ``--same-lamps A,B``: two spheres of one
capture (cropped from the same frames, e.g. PSBox's LightProbe-1 and -2), whose directions must agree.
Other public captures are not shipped with the project: fetch them yourself (docs/benchmarks.md,
"Calibration and spheres", names them and their sources).
"""
import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from uvps.commands import COMMANDS

DATA = next((p / "shared" / "data" for p in Path(__file__).resolve().parents if (p / "shared" / "data").is_dir()),
            Path("/work/shared/data"))


def _published(path):
    rows = [ln.split() for ln in Path(path).read_text().splitlines() if ln.strip()]
    if len(rows[0]) == 1:
        rows = rows[1:]
    a = np.array(rows, float)
    a = a.T if a.shape[0] == 3 and a.shape[1] != 3 else a
    return a / np.linalg.norm(a, axis=1, keepdims=True)


def _angles(a, b):
    return np.degrees(np.arccos(np.clip(np.sum(a * b, axis=1), -1, 1)))


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--capture", action="append", default=[], help="NAME=FOLDER[:LIGHTS]")
    ap.add_argument("--same-lamps", action="append", default=[], help="NAME,NAME")
    ap.add_argument("--pixel-size-um", type=float, default=100.0)
    args = ap.parse_args(argv)
    caps = args.capture or [f"psbox_lightprobe2={DATA / 'sphere_mirror_psbox'}:"
                            f"{DATA / 'sphere_mirror_psbox' / 'light_directions.txt'}"]
    dirs = {}
    print("| capture | found (centre, radius px) | kind | vs published: median / max (deg) | time (s) |")
    print("|---|---|---|---|---|")
    for spec in caps:
        name, rest = spec.split("=", 1)
        folder, _, lights = rest.partition(":")
        if not Path(folder).is_dir():
            print(f"| {name} | {folder}: not found | | | |")
            continue
        with tempfile.TemporaryDirectory() as tmp:
            t0 = time.perf_counter()
            try:
                COMMANDS["calibrate"]({"spheres": [folder]}, {"pixel_size_um": args.pixel_size_um}, Path(tmp) / "CAL")
            except Exception as e:          # a refusal is a result here
                print(f"| {name} | refused: {e} | | | |")
                continue
            dt = time.perf_counter() - t0
            doc = json.loads((Path(tmp) / "CAL" / "calibration.json").read_text())
        d = np.array([lamp["direction"] for lamp in doc["lamps"]])
        dirs[name] = d
        s = doc["spheres"][0]
        vs = ""
        if lights:
            ang = _angles(d, _published(lights))
            vs = f"{np.median(ang):.2f} / {ang.max():.2f}"
        print(f"| {name} | ({s['centre_px'][0]:.1f}, {s['centre_px'][1]:.1f}), {s['radius_px']:.1f} | {s['kind']} | "
              f"{vs} | {dt:.1f} |")
    for pair in args.same_lamps:
        a, b = pair.split(",")
        if a in dirs and b in dirs:
            ang = _angles(dirs[a], dirs[b])
            print(f"\n{a} against {b} (one capture's two spheres): median {np.median(ang):.2f}, max {ang.max():.2f} deg")
    return 0


if __name__ == "__main__":
    sys.exit(main())
