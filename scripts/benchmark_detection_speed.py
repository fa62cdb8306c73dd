#!/usr/bin/env python
"""Time uvps.core.detect.detect_protrusions alone at a given size (default 4000 x 3000).

The scene is ``make_capture(shape=(ROWS, COLS), n_lights=3, seed=SEED, noise=False)``'s true
albedo, height and normals (the detector's input in a run, without the run around it). Prints the
wall time and the process's CPU time (on a loaded machine the CPU time is the one to compare),
the number of protrusions and the rejection counts. ``--profile N`` prints the N costliest calls
(cProfile, CPU time). The first call of a fresh install also compiles (numba, cached after).

Example::

    OMP_NUM_THREADS=1 .venv/bin/python scripts/benchmark_detection_speed.py
"""
from __future__ import annotations

import argparse
import cProfile
import pstats
import sys
import time

from uvps.core.detect import detect_protrusions
from uvps.testing.synthetic import make_capture


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--shape", type=int, nargs=2, default=(3000, 4000), metavar=("ROWS", "COLS"))
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--profile", type=int, default=0, metavar="N")
    args = ap.parse_args(argv)
    cap = make_capture(shape=tuple(args.shape), n_lights=3, seed=args.seed, noise=False)
    detect_protrusions(cap.albedo[:64, :64], cap.height_um[:64, :64],   # compile, if needed
                       pixel_size_um=cap.spec.pixel_size_um)
    prof = cProfile.Profile(time.process_time) if args.profile else None
    t0, c0 = time.perf_counter(), time.process_time()
    if prof:
        prof.enable()
    det = detect_protrusions(cap.albedo, cap.height_um, pixel_size_um=cap.spec.pixel_size_um,
                             normals=cap.normals)
    if prof:
        prof.disable()
    wall, cpu = time.perf_counter() - t0, time.process_time() - c0
    print(f"detection {args.shape[0]} x {args.shape[1]}: wall {wall:.1f} s, CPU {cpu:.1f} s; "
          f"{int(det.labels.max())} protrusions; rejected {det.rejected}")
    if prof:
        pstats.Stats(prof).sort_stats("cumulative").print_stats(args.profile)
    return 0


if __name__ == "__main__":
    sys.exit(main())
