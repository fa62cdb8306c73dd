"""Peak memory and time of a painting's stitching alone, at two painting sizes.

The generator's painting (:mod:`uvps.testing.painting`) at COLUMNS x ROWS tiles is written as the
run folders a batch would leave (each tile's true albedo times its exposure, its true height off by
its own offset and plane, levelled with its levelling in ``run.json``, its normals, its protrusions), then
:func:`uvps.painting.stitch_painting` runs on them in a fresh process with Dask's
synchronous scheduler (so the process holds every chunk it computes) and reports its peak resident
memory during the stitching (``VmHWM`` after the imports, the peak reset through
``/proc/self/clear_refs``) and time. The tiles' pipeline is not run: this measures the stitching.
With ``--workers N`` it stitches on N one-thread worker processes instead, on the cluster
``uvps batch`` starts (:class:`uvps.commands.batch._Cluster`, whose workers leave distributed's nanny
default ``MALLOC_TRIM_THRESHOLD_`` unset: with it, the registration's pair tasks took 3.4-3.7x their CPU).
The pairs' shifts and the maps' chunks are then its tasks, and the peak memory is this process's
alone (the workers' is not counted); ``timings`` has ``register_tasks`` and ``register_cpu_s`` (the
pair tasks' CPU seconds on the workers included).

    OMP_NUM_THREADS=1 python scripts/benchmark_painting_memory.py --grid 3 2 --tile 600 800
    OMP_NUM_THREADS=1 python scripts/benchmark_painting_memory.py --grid 6 4 --tile 600 800
    OMP_NUM_THREADS=1 python scripts/benchmark_painting_memory.py --grid 6 4 --tile 600 800 --no-maps --workers 2
"""
from __future__ import annotations

import argparse
import csv
import json
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np


def write_runs(args, root: Path) -> dict:
    from uvps.core.level import level_height
    from uvps.files.io import write_imagej_tiff
    from uvps.files.tables import write_label_tiff
    from uvps.testing.painting import make_painting

    p = make_painting(grid=tuple(args.grid), tile_shape=tuple(args.tile), overlap=args.overlap, n_lights=3,
                      seed=args.seed, protrusion_density=100.0)
    rng = np.random.default_rng(args.seed)
    M, N = p.tile_shape
    rr, cc = np.mgrid[0:M, 0:N]
    for t in p.tiles:
        d = root / t.name
        d.mkdir(parents=True)
        h = t.capture.height_um + rng.normal(0, 20) + rng.normal(0, 0.02) * cc + rng.normal(0, 0.02) * rr
        # levelled as `uvps run` writes it, the levelling in run.json (the stitching rebuilds the raw height)
        h, lev = level_height(h.astype(np.float32), pixel_size_um=15.0)
        (d / "run.json").write_text(json.dumps({"level": lev.to_json()}))
        write_imagej_tiff(d / "depth.tif", h.astype(np.float32), axes="YX", pixel_size_um=15.0)
        write_imagej_tiff(d / "albedo.tif", np.moveaxis(t.capture.albedo * t.exposure, -1, 0).astype(np.float32),
                          axes="CYX", pixel_size_um=15.0)
        write_imagej_tiff(d / "normals.tif", np.moveaxis(t.capture.normals, -1, 0).astype(np.float32), axes="CYX",
                          pixel_size_um=15.0)
        write_label_tiff(d / "protrusions_labels.tif", np.zeros((M, N), np.int32), pixel_size_um=15.0)
        pr = t.capture.protrusions
        with open(d / "protrusions.csv", "w", newline="") as fh:
            wr = csv.writer(fh)
            wr.writerow(["id", "x_px", "y_px", "width_um", "height_um"])
            for i in range(len(pr["id"])):
                wr.writerow([int(pr["id"][i]), pr["x_px"][i], pr["y_px"][i], pr["width_um"][i], pr["height_um"][i]])
    return {t.name: [t.nominal[0], t.nominal[1], list(p.tile_shape)] for t in p.tiles}


CHILD = """
import json, resource, sys, time
import dask, matplotlib.figure, skimage.registration, zarr
from uvps.painting import stitch_painting
import uvps.painting
import uvps.report.painting

def hwm_mb():
    for line in open("/proc/self/status"):
        if line.startswith("VmHWM:"):
            return int(line.split()[1]) / 1024

before = hwm_mb()
with open("/proc/self/clear_refs", "w") as fh:     # reset the peak (Linux >= 4.0): the stitching's own
    fh.write("5")
rss0 = hwm_mb()
tiles = {k: (v[0], v[1], tuple(v[2])) for k, v in json.loads(sys.argv[2]).items()}
# CPU seconds (this process, all its threads) beside the wall times: on a shared machine the wall
# time of a step varies with the load, its CPU time much less
write_maps, maps_cpu = uvps.painting._write_maps, []

def timed_maps(*a, **k):
    c = time.process_time()
    try:
        return write_maps(*a, **k)
    finally:
        maps_cpu.append(time.process_time() - c)

uvps.painting._write_maps = timed_maps
t0, c0 = time.perf_counter(), time.process_time()
n_workers = int(sys.argv[4])
if n_workers:      # the batch's own cluster (its workers' settings): the pairs' shifts and the maps' chunks its tasks
    from uvps.commands.batch import _Cluster
    cluster = _Cluster(n_workers=n_workers)
    try:
        t0, c0 = time.perf_counter(), time.process_time()
        with cluster.client.as_current():
            res = stitch_painting(sys.argv[1], tiles, pixel_size_um=15.0, regions="auto",
                                  maps=sys.argv[3] == "maps")
        elapsed, cpu = time.perf_counter() - t0, time.process_time() - c0
    finally:
        cluster.close()
else:
    with dask.config.set(scheduler="synchronous"):
        res = stitch_painting(sys.argv[1], tiles, pixel_size_um=15.0, regions="auto", maps=sys.argv[3] == "maps")
    elapsed, cpu = time.perf_counter() - t0, time.process_time() - c0
print(json.dumps({"elapsed_s": elapsed, "cpu_s": cpu, "workers": n_workers,
                  "maps_cpu_s": sum(maps_cpu), "peak_rss_mb": hwm_mb(), "rss_after_imports_mb": rss0,
                  "peak_during_imports_mb": before,
                  "shape": list(res.shape), "timings": res.timings, "n_protrusions": res.n_protrusions}))
"""


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--grid", type=int, nargs=2, default=[3, 2])
    ap.add_argument("--tile", type=int, nargs=2, default=[600, 800])
    ap.add_argument("--overlap", type=float, default=0.4)
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--no-maps", action="store_true", help="registration, counts and report only")
    ap.add_argument("--workers", type=int, default=0,
                    help="stitch on the batch's local cluster of this many one-thread worker processes "
                         "(default 0: Dask's synchronous scheduler, everything in this process)")
    args = ap.parse_args(argv)
    with tempfile.TemporaryDirectory(prefix="uvps_stitch_") as tmp:
        tiles = write_runs(args, Path(tmp))
        done = subprocess.run([sys.executable, "-c", CHILD, tmp, json.dumps(tiles),
                               "no-maps" if args.no_maps else "maps", str(args.workers)],
                              capture_output=True, text=True)
        if done.returncode:
            raise SystemExit(done.stderr)
        out = json.loads(done.stdout.strip().splitlines()[-1])
        out["grid"], out["tile"], out["maps"] = args.grid, args.tile, not args.no_maps
        print(json.dumps(out))


if __name__ == "__main__":
    main()
