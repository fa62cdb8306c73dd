#!/usr/bin/env python
"""Speed of ``uvps calibrate`` on a large sphere capture (target: under 10 s for 64 lamps at 4000 x 3000).

The capture: K grey 16-bit TIFFs (uncompressed, as a camera converter writes them) of a flat painting
(albedo 0.3) lit by K near lamps at 250-500 mm, with two glossy (``--kind matte``: matte white) spheres
of 2.5 mm radius in opposite corners, rendered by :func:`uvps.testing.synthetic_spheres.make_sphere_capture`
inside each sphere's box (the lamps shifted to the box's frame) and pasted into the frame; photon and
read noise. ``uvps calibrate`` is then run as a user runs it (a subprocess: start-up, reading,
detection, fits, writing) and its wall time, the lamps' errors against the truth and the machine's
load are printed.

    .venv/bin/python scripts/benchmark_calibrate_speed.py                       # 64 lamps, 4000 x 3000
    .venv/bin/python scripts/benchmark_calibrate_speed.py --lamps 8 --shape 600 800   # a quick trial
    .venv/bin/python scripts/benchmark_calibrate_speed.py --kind matte                # matte spheres
"""
from __future__ import annotations

import argparse
import json
import os
import resource
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import tifffile

from uvps.testing.synthetic import Nuisances, SyntheticCapture, SyntheticSpec, light_positions, pixel_centres_mm
from uvps.testing.synthetic_spheres import SphereSpec, make_sphere_capture


def render(shape, lamps, px, folder: Path, seed=0, kind="glossy"):
    """Write the capture; returns the true lamp positions (K, 3) mm."""
    rng = np.random.default_rng(seed)
    M, N = shape
    L = light_positions(rng, n_lights=lamps, elevation_deg=(20.0, 60.0), distance_mm=(250.0, 500.0))
    E = 1 + rng.uniform(-0.1, 0.1, lamps)
    exposure = 0.75 * 65535 / 0.6
    gain = 65535 / 60000
    x, y = pixel_centres_mm(shape, px)
    x = x.astype(np.float32)
    y = y.astype(np.float32)
    boxes = []
    r_mm = 2.5
    for fx, fy in ((0.13, 0.17), (0.87, 0.83)):
        c0, r0 = fx * (N - 1), fy * (M - 1)
        h = int(1.4 * r_mm * 1000 / px)
        ra, rb, ca, cb = int(r0) - h, int(r0) + h, int(c0) - h, int(c0) + h
        bm, bn = rb - ra, cb - ca
        # the box's own frame: its centre is the origin, so the lamps move by the box centre
        off = np.array([((ca + cb - 1) / 2 - (N - 1) / 2) * px / 1000, ((M - 1) / 2 - (ra + rb - 1) / 2) * px / 1000, 0])
        spec = SyntheticSpec(shape=(bm, bn), pixel_size_um=px, seed=seed, n_lights=lamps, rgb=False)
        cap = SyntheticCapture(images=np.broadcast_to(np.zeros((), np.uint16), (lamps, bm, bn)),
                               light_positions_mm=L - off, intensities=E, height_um=np.zeros((bm, bn), np.float32),
                               normals=None, albedo=np.full((bm, bn), 0.3, np.float32), regions=None,
                               region_names=[], region_light=[], protrusions={}, spec=spec, exposure=exposure,
                               gain=gain, nuisances=Nuisances())
        sc = make_sphere_capture(cap, [SphereSpec(kind, ((c0 - ca) / (bn - 1), (r0 - ra) / (bm - 1)), r_mm)])
        boxes.append((ra, rb, ca, cb, sc.images))
    folder.mkdir(parents=True, exist_ok=True)
    for k in range(lamps):
        dx, dy, dz = L[k, 0] - x, L[k, 1] - y, np.float32(L[k, 2])
        d2 = dx * dx + dy * dy + dz * dz
        img = (exposure * 0.3 * E[k] * float(L[k] @ L[k])) * dz / d2 ** 1.5
        img = img + rng.standard_normal(img.shape, dtype=np.float32) * np.sqrt(gain * img + 16)
        for ra, rb, ca, cb, sub in boxes:
            img[ra:rb, ca:cb] = sub[k]
        tifffile.imwrite(folder / f"sphere_{k:03d}.tif", np.clip(np.rint(img), 0, 65535).astype(np.uint16),
                         resolution=(1 / px, 1 / px), resolutionunit="NONE", description="ImageJ=1.54f\nunit=micron\n",
                         metadata=None)
    return L


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--shape", type=int, nargs=2, default=[3000, 4000], metavar=("ROWS", "COLS"))
    ap.add_argument("--lamps", type=int, default=64)
    ap.add_argument("--pixel-size-um", type=float, default=15.0)
    ap.add_argument("--workdir", default=None)
    ap.add_argument("--kind", choices=("glossy", "matte"), default="glossy", help="the spheres' kind")
    args = ap.parse_args(argv)
    work = Path(args.workdir or tempfile.mkdtemp(prefix="uvps_cal_speed_"))
    cap_dir, cal_dir = work / "spheres", work / "CAL"
    t0 = time.perf_counter()
    L = render(tuple(args.shape), args.lamps, args.pixel_size_um, cap_dir, kind=args.kind)
    t_make = time.perf_counter() - t0
    shutil.rmtree(cal_dir, ignore_errors=True)
    cmd = [sys.executable, "-m", "uvps", "calibrate", "--spheres", str(cap_dir), "-o", str(cal_dir)]
    t0 = time.perf_counter()
    ru0 = resource.getrusage(resource.RUSAGE_CHILDREN)
    r = subprocess.run(cmd, capture_output=True, text=True)
    wall = time.perf_counter() - t0
    ru1 = resource.getrusage(resource.RUSAGE_CHILDREN)
    # CPU time: what the command costs when it has the machine to itself (wall time counts the waits
    # of a loaded machine; the command runs one thread, so unloaded its wall time is about its CPU time)
    cpu = (ru1.ru_utime - ru0.ru_utime) + (ru1.ru_stime - ru0.ru_stime)
    if r.returncode != 0:
        print(r.stderr, file=sys.stderr)
        return 1
    lights = json.loads((cal_dir / "lights.json").read_text())["lights"]
    D = np.array([lp["direction"] for lp in lights])
    ang = np.degrees(np.arccos(np.clip((D * L).sum(1) / np.linalg.norm(L, axis=1), -1, 1)))
    P = np.array([lp["position_mm"] for lp in lights], float)
    pos = np.linalg.norm(P - L, axis=1) / np.linalg.norm(L, axis=1) * 100
    print(f"uvps calibrate: {args.lamps} lamps, {args.kind} spheres, {args.shape[1]} x {args.shape[0]} px grey uint16: "
          f"{wall:.1f} s wall, {cpu:.1f} s CPU, peak memory {ru1.ru_maxrss / 2 ** 20:.2f} GiB "
          f"(capture written in {t_make:.0f} s); lamps max {ang.max():.3f} deg, positions max {pos.max():.2f} %; "
          f"load average {os.getloadavg()[0]:.1f} on {os.cpu_count()} CPUs")
    if not args.workdir:
        shutil.rmtree(work, ignore_errors=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
