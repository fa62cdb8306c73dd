#!/usr/bin/env python
"""Time a run's detection at a given size (default 4000 x 3000).

The scene is ``make_capture(shape=(ROWS, COLS), n_lights=3, seed=SEED, noise=False)``'s true
albedo, height and normals (the detector's input in a run, without the run around it). A run's
detection is :func:`uvps.core.pipeline.detection_height` (the normals integrated again without
the cracks' gradients, ``DetectionParams.curl_k``) then :func:`uvps.core.detect.detect_protrusions`
on it; each is timed (on these clean maps nothing is left out, so the height costs the curl only;
where cracks are, it also costs one integration). Prints the wall time and the process's CPU time
(on a loaded machine the CPU time is the one to compare), the number of protrusions and the
rejection counts. ``--profile N`` prints the N costliest calls (cProfile, CPU time). The first
call of a fresh install also compiles (numba, cached after).

``--ps K`` then times the photometric stereo the detection follows, the same way (the process's
CPU time, all its threads): :func:`uvps.core.pipeline.run` with its default stages (additive term,
flat field, lamps estimated, normals, height) on ``make_capture(shape=(ROWS, COLS),
n_lights=K, seed=SEED)`` (noise on, as ``scripts/benchmark_speed.py`` makes it), after one run on
a 300 x 400 crop (compiled kernels loaded); it prints that CPU time, the wall time and
``timings_s`` (wall, per stage).

Example::

    OMP_NUM_THREADS=1 .venv/bin/python scripts/benchmark_detection_speed.py --ps 16
"""
from __future__ import annotations

import argparse
import cProfile
import pstats
import sys
import time

from uvps.core.detect import DetectionParams, detect_protrusions
from uvps.core.pipeline import detection_height
from uvps.testing.synthetic import make_capture


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--shape", type=int, nargs=2, default=(3000, 4000), metavar=("ROWS", "COLS"))
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--profile", type=int, default=0, metavar="N")
    ap.add_argument("--ps", type=int, default=0, metavar="K",
                    help="also time the photometric stereo on a capture of K lamps")
    args = ap.parse_args(argv)
    cap = make_capture(shape=tuple(args.shape), n_lights=3, seed=args.seed, noise=False)
    detect_protrusions(cap.albedo[:64, :64], cap.height_um[:64, :64],   # compile, if needed
                       pixel_size_um=cap.spec.pixel_size_um)
    px = cap.spec.pixel_size_um
    t0, c0 = time.perf_counter(), time.process_time()
    height, left_out = detection_height(cap.height_um, cap.normals, pixel_size_um=px, params=DetectionParams())
    wall_h, cpu_h = time.perf_counter() - t0, time.process_time() - c0
    prof = cProfile.Profile(time.process_time) if args.profile else None
    t0, c0 = time.perf_counter(), time.process_time()
    if prof:
        prof.enable()
    det = detect_protrusions(cap.albedo, height, pixel_size_um=px, normals=cap.normals, left_out=left_out)
    if prof:
        prof.disable()
    wall, cpu = time.perf_counter() - t0, time.process_time() - c0
    print(f"detection {args.shape[0]} x {args.shape[1]}: wall {wall_h + wall:.1f} s, CPU {cpu_h + cpu:.1f} s "
          f"(its height {wall_h:.1f} s wall, {cpu_h:.1f} s CPU; the detector {wall:.1f} s wall, {cpu:.1f} s CPU); "
          f"{int(det.labels.max())} protrusions; rejected {det.rejected}")
    if prof:
        pstats.Stats(prof).sort_stats("cumulative").print_stats(args.profile)
    if args.ps:
        del cap, det
        time_photometric_stereo(tuple(args.shape), args.ps, args.seed)
    return 0


def time_photometric_stereo(shape, n_lights: int, seed: int) -> None:
    """CPU and wall time of :func:`uvps.core.pipeline.run` (default stages) on a synthetic capture."""
    from uvps.core.pipeline import run

    run(make_capture(shape=(300, 400), n_lights=n_lights, seed=seed).as_capture())
    cap = make_capture(shape=shape, n_lights=n_lights, seed=seed).as_capture()
    t0, c0 = time.perf_counter(), time.process_time()
    res = run(cap)
    wall, cpu = time.perf_counter() - t0, time.process_time() - c0
    print(f"photometric stereo {shape[0]} x {shape[1]} x {n_lights}: wall {wall:.1f} s, "
          f"CPU {cpu:.1f} s; stages (wall, s) {res.timings_s}")


if __name__ == "__main__":
    sys.exit(main())
