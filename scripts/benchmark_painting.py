"""Benchmark of a painting in tiles: registration, one set of counts, the painting-wide height.

For each seed, the generator (:func:`uvps.testing.painting.make_painting`) renders a painting as
COLUMNS x ROWS overlapping tiles under a moving rig (stage off by up to 30 px per axis, exposure
drifting by up to 15 % between tiles, the lamps fixed to the rig); ``uvps batch TILES --mosaic
layout.csv --regions auto`` runs it as a user would (a real subprocess, a local Dask cluster of
``--workers`` processes) and the painting is scored against the generator's truth: the refined
corners' error, detection F1 for protrusions >= 60 um, protrusions counted twice, the count's ratio
to the truth, the painting-wide height's rms error after one plane (all of it and the overlap
bands), and the times (the batch, the sum of the tiles' run times, the stitching's parts, and the batch's
ratio to the tiles' sum / workers). The worst seed is the figure quoted in docs/benchmarks.md, "Painting in
tiles".

The tiles are 600 x 800 px by default: a tile there took 11-15 s (docs/benchmarks.md), against ~1.4 s at
the generator's own 200 x 240 px, where the cluster's start and its processes' imports (~2.5 s, paid once
per batch, not by the stitching) outweigh the tiles and the ratio measures them (docs/decisions/painting.md,
"The benchmark's tiles: 600 x 800 px").

    OMP_NUM_THREADS=1 python scripts/benchmark_painting.py --seeds 1 2 3
    OMP_NUM_THREADS=1 python scripts/benchmark_painting.py --grid 4 3 --tile 300 400 --seeds 1

``--doc`` writes the table into docs/benchmarks.md's section ``painting`` and the raw results into
docs/benchmarks/painting.json (scripts/benchdoc.py).
"""
from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import tifffile

DOC_SECTION = "painting"
_HEAD = ("| seed | corner error (px) | largest pair residual (px) | F1 >= 60 um | counted twice | count / truth | "
         "height rms (um) | on overlaps (um) | batch (s) | tiles' sum / {w} workers (s) | ratio | stitching (s) |\n"
         "|---|---|---|---|---|---|---|---|---|---|---|---|\n")


def run(seed, args, root: Path) -> dict:
    import zarr
    from uvps.testing.painting import (make_painting, painting_truth, read_table, read_truth_layout,
                                       score_height, score_painting, write_painting)

    p = make_painting(grid=tuple(args.grid), tile_shape=tuple(args.tile), overlap=args.overlap,
                      stage_error_px=args.stage_error, seed=seed, **rig_overrides(args))
    src = write_painting(p, root / f"painting{seed}")
    out = root / f"out{seed}"
    cmd = [sys.executable, "-m", "uvps", "batch", str(src / "tiles"), "-o", str(out), "--lights",
           "lights_positions_mm.csv", "--regions", "auto", "--mosaic", str(src / "layout.csv"),
           "--workers", str(args.workers)]
    t0 = time.perf_counter()
    done = subprocess.run(cmd, capture_output=True, text=True)
    elapsed = time.perf_counter() - t0
    if done.returncode:
        raise SystemExit(done.stderr)
    truth = painting_truth(src)
    refined = read_truth_layout(out / "painting" / "layout.csv")
    err = [float(np.hypot(*np.subtract(refined[k], truth["layout"][k]))) for k in refined]
    nominal_err = [float(np.hypot(*np.subtract(t.nominal, t.true))) for t in p.tiles]
    s = score_painting(read_table(src / "truth" / "protrusions.csv"),
                       read_table(out / "painting" / "painting_protrusions.csv"), truth["layout"],
                       truth["tile_shape"], pixel_size_um=truth["pixel_size_um"])
    meta = json.loads((out / "painting" / "painting.json").read_text())
    h = np.asarray(zarr.open_group(str(out / "painting" / "height.ome.zarr"), mode="r")["0"])
    hs = score_height(h, meta["origin_px"], tifffile.imread(src / "truth" / "height_um.tif"), truth["layout"],
                      truth["tile_shape"])
    log = json.loads((out / "batch.json").read_text())
    tiles_s = sum(c["elapsed_s"] for c in log["captures"])
    row = {"seed": seed, "nominal_err_px": max(nominal_err), "corner_err_px": max(err),
           "max_residual_px": meta["max_residual_px"], **s, **{f"height_{k}": v for k, v in hs.items()},
           "batch_s": elapsed, "tiles_sum_s": tiles_s, "workers": args.workers,
           **{f"stitch_{k}": v for k, v in meta["timings"].items()}}
    return {**row, "ratio_to_ideal": _ratio(row)}


def rig_overrides(args) -> dict:
    """The generator's painting fields ``--bow`` and ``--beam`` set (none: the generator's defaults)."""
    out = {}
    if args.bow is not None:
        out["bow_um"] = args.bow
    if args.beam is not None:
        out["beam_exponent"], out["beam_aim_error_deg"] = args.beam
    return out


def worst_of(rows: list) -> dict:
    """The worst over the seeds: largest errors and times, smallest F1, the count ratio farthest from 1."""
    return {"corner_err_px": max(r["corner_err_px"] for r in rows), "f1": min(r["f1"] for r in rows),
            "max_residual_px": max(r["max_residual_px"] for r in rows), "twice": max(r["twice"] for r in rows),
            "count_ratio": max((r["count_ratio"] for r in rows), key=lambda c: abs(c - 1)),
            "count_off": max(abs(r["count_ratio"] - 1) for r in rows),
            "height_rms_um": max(r["height_rms_um"] for r in rows),
            "height_overlap_rms_um": max(r["height_overlap_rms_um"] for r in rows),
            "ratio_to_ideal": max(_ratio(r) for r in rows)}


def _ratio(r: dict) -> float:
    """The batch's time over the tiles' sum / workers (from the row's times: a row kept before the ratio was
    recorded has them too)."""
    return r["batch_s"] / (r["tiles_sum_s"] / r["workers"])


def render_doc(results: dict) -> str:
    """docs/benchmarks.md's table: a row per seed and the worst (bold where a target applies).

    Parameters
    ----------
    results : dict
        ``{"rows": [run(...) per seed], ...}``, as ``--doc`` keeps it in docs/benchmarks/painting.json.
    """
    rows = results["rows"]
    lines = [_HEAD.format(w=rows[0]["workers"])]
    for r in rows:
        lines.append(f"| {r['seed']} | {r['corner_err_px']:.2f} | {r['max_residual_px']:.2f} | {r['f1']:.3f} | "
                     f"{r['twice']} | {r['count_ratio']:.3f} | {r['height_rms_um']:.2f} | "
                     f"{r['height_overlap_rms_um']:.2f} | {r['batch_s']:.0f} | {r['tiles_sum_s'] / r['workers']:.0f} | "
                     f"{_ratio(r):.2f} | {r['stitch_total_s']:.0f} (maps {r['stitch_maps_s']:.0f}) |\n")
    w = worst_of(rows)
    lines.append(f"| **worst** | **{w['corner_err_px']:.2f}** | {w['max_residual_px']:.2f} | **{w['f1']:.3f}** | "
                 f"**{w['twice']}** | **{w['count_ratio']:.3f}** | **{w['height_rms_um']:.2f}** | "
                 f"**{w['height_overlap_rms_um']:.2f}** | | | **{w['ratio_to_ideal']:.2f}** | |\n")
    return "".join(lines)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, nargs="+", default=[1, 2, 3])
    ap.add_argument("--grid", type=int, nargs=2, default=[3, 2], metavar=("COLUMNS", "ROWS"))
    ap.add_argument("--tile", type=int, nargs=2, default=[600, 800], metavar=("ROWS", "COLUMNS"),
                    help="each tile's shape (default 600 800: see the module's docstring)")
    ap.add_argument("--overlap", type=float, default=0.4)
    ap.add_argument("--stage-error", type=float, default=30.0)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--bow", type=float, default=None, help="the canvas's bow over the painting (um; default 15)")
    ap.add_argument("--beam", type=float, nargs=2, default=None, metavar=("EXPONENT", "AIM_DEG"),
                    help="the rig's lamps' beams (cos^EXPONENT, aimed within AIM_DEG of the centre): the same in every "
                         "tile and not in the light file")
    ap.add_argument("--keep", type=Path, default=None, help="render and run into this folder and keep it")
    ap.add_argument("--doc", action="store_true",
                    help="write the table into docs/benchmarks.md (section painting) and docs/benchmarks/painting.json")
    args = ap.parse_args(argv)
    rows = []
    with tempfile.TemporaryDirectory(prefix="uvps_painting_") as tmp:
        for seed in args.seeds:
            r = run(seed, args, args.keep or Path(tmp))
            rows.append(r)
            print(json.dumps({k: round(v, 4) if isinstance(v, float) else v for k, v in r.items()}), flush=True)
    worst = worst_of(rows)
    print("worst", json.dumps({k: round(v, 4) if isinstance(v, float) else v for k, v in worst.items()}))
    results = {"argv": list(sys.argv[1:] if argv is None else argv), "rows": rows}
    print(render_doc(results))
    if args.doc:
        from benchdoc import write_doc
        print("wrote", write_doc(DOC_SECTION, results, render_doc(results), source="scripts/benchmark_painting.py"))


if __name__ == "__main__":
    main()
