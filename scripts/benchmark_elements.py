"""Benchmark of ``uvps elements``: registration of XRF element maps onto a run, per-area means, time.

Each seed renders a 1600 x 1200 capture at 15 um (uvps.testing.synthetic), writes a run folder of its truth
with its colour areas, and renders 4 element maps (250 um step, 1 mm spot, Poisson counts) rotated by
up to 3 deg, scaled by up to +-5 % and shifted by up to 2 mm, drawn per seed. Rows add what the
registration does not model: composition varying +-30 % inside each area, a flat-topped spot, scan
lines jittered by 0.2 map px, and all three. Each row is registered automatically and from 4 control
points clicked 2 run px (0.12 map px) off; the per-area means are compared with the areas' true
abundance for areas of more than 10 map pixels (the truth is the nominal abundance, so rows that
vary it inside the areas measure that variation too). The command's time is measured end to end
(``python -m uvps elements``, 4 map TIFFs), on the clean row.

    .venv/bin/python scripts/benchmark_elements.py --seeds 0 1 2 [--md] [--doc]

``--doc`` writes docs/benchmarks.md's table (section ``elements``: the worst seed per row) and every result
into docs/benchmarks/elements.json (scripts/benchdoc.py).
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import tifffile

from uvps.core.elements import area_elements, register_maps, registration_error_map_px, resample_to_run
from uvps.files.tables import write_label_tiff
from uvps.testing.synthetic import SyntheticSpec, make_capture, render_element_maps, write_truth_run

PX = 15.0
ROWS = {"clean": {}, "composition +-30 % in areas": {"within_area": 0.3},
        "flat-topped spot": {"spot_shape": "disc"}, "line jitter 0.2 map px": {"line_jitter_px": 0.2},
        "all three": {"within_area": 0.3, "spot_shape": "disc", "line_jitter_px": 0.2}}
DOC_SECTION = "elements"


def control_points(truth, shape, rng):
    """4 map pixels near the corners of the run's field, and where they fall in the run, 2 px off."""
    inv = np.linalg.inv(truth.map_to_run)
    M, N = shape
    run = np.array([[0.1 * N, 0.1 * M], [0.9 * N, 0.12 * M], [0.88 * N, 0.9 * M], [0.12 * N, 0.88 * M]])
    mp = (inv[:2, :2] @ run.T + inv[:2, 2:3]).T
    mp = np.round(mp)                                  # a click lands on a map pixel
    exact = (truth.map_to_run[:2, :2] @ mp.T + truth.map_to_run[:2, 2:3]).T
    return np.column_stack([mp, exact + rng.normal(0, 2.0, exact.shape)])


def one(seed: int, workdir: Path, time_command: bool) -> list:
    rng = np.random.default_rng(1000 + seed)
    cap = make_capture(SyntheticSpec(seed=seed, n_lights=4))
    rot, scale = rng.uniform(-3, 3), 1 + rng.uniform(-0.05, 0.05)
    shift = rng.uniform(-2, 2, 2)
    out = []
    names = {i: str(i) for i in range(1, int(cap.regions.max()) + 1)}
    for row, kw in ROWS.items():
        truth = render_element_maps(cap, rotation_deg=rot, scale=scale, shift_mm=tuple(shift), seed=seed, **kw)
        res = {"seed": seed, "row": row, "rotation_deg": rot, "scale": scale, "shift_mm": shift.tolist()}
        for how, cp in (("automatic", None), ("4 control points", control_points(truth, cap.regions.shape, rng))):
            t = time.perf_counter()
            reg = register_maps(cap.albedo, truth.maps, labels=cap.regions, pixel_size_um=PX, control_points=cp)
            res[f"{how} time_s"] = time.perf_counter() - t
            res[f"{how} error_map_px"] = registration_error_map_px(reg.map_to_run, truth.map_to_run,
                                                                   truth.maps.shape, cap.regions.shape)
            res[f"{how} residual_map_px"] = reg.residual_map_px
            if how == "automatic":
                areas = area_elements(resample_to_run(truth.maps, reg, cap.regions.shape), cap.regions, names,
                                      pixel_size_um=PX, step_um=truth.maps.step_um, spot_um=1000.0)
                big = areas.n_map_pixels > 10
                true = truth.abundance[areas.labels][big]
                res["area_mean_error_max"] = float(np.max(np.abs(areas.mean[big] - true) / true))
                res["areas"] = int(big.sum())
        out.append(res)
    if time_command:
        run = write_truth_run(cap, workdir / f"run{seed}")
        write_label_tiff(run / "regions_labels.tif", cap.regions, pixel_size_um=PX)
        truth = render_element_maps(cap, rotation_deg=rot, scale=scale, shift_mm=tuple(shift), seed=seed)
        maps = []
        for n, m in zip(truth.maps.names, truth.maps.data):
            p = workdir / f"maps{seed}" / f"{n}.tif"
            p.parent.mkdir(exist_ok=True)
            tifffile.imwrite(p, m.astype(np.float32))
            maps.append(str(p))
        t = time.perf_counter()
        r = subprocess.run([sys.executable, "-m", "uvps", "elements", str(run), *maps, "--step-um", "250",
                            "-o", str(workdir / f"out{seed}")], capture_output=True, text=True)
        out[0]["command_time_s"] = time.perf_counter() - t
        if r.returncode:
            raise SystemExit(r.stderr)
    return out


def worst_row(results: list, row: str) -> tuple:
    """The worst seed of a row: automatic error, residual, control points' error (map px), area means' error
    (fraction), the fewest areas."""
    rs = [r for r in results if r["row"] == row]
    return (max(r["automatic error_map_px"] for r in rs), max(r["automatic residual_map_px"] for r in rs),
            max(r["4 control points error_map_px"] for r in rs), max(r["area_mean_error_max"] for r in rs),
            min(r["areas"] for r in rs))


def render_doc(results: dict) -> str:
    """docs/benchmarks.md's table: per row, the worst seed's registration errors and area means' error.

    Parameters
    ----------
    results : dict
        ``{"results": [one(...) per seed, flattened], ...}`` as docs/benchmarks/elements.json keeps it.
    """
    lines = ["| row | automatic: error (map px) | residual reported | 4 control points: error | "
             "area means: worst error |", "|---|---|---|---|---|"]
    for row in dict.fromkeys(r["row"] for r in results["results"]):
        a, res, c, m, _ = worst_row(results["results"], row)
        lines.append(f"| {row} | {a:.3f} | {res:.3f} | {c:.3f} | {100 * m:.1f} % |")
    return "\n".join(lines) + "\n"


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    ap.add_argument("--md", action="store_true", help="print a Markdown table")
    ap.add_argument("--json", type=Path, help="write every result here")
    ap.add_argument("--doc", action="store_true",
                    help="write the table into docs/benchmarks.md (section elements) and docs/benchmarks/elements.json")
    args = ap.parse_args(argv)
    with tempfile.TemporaryDirectory() as tmp:
        results = [r for s in args.seeds for r in one(s, Path(tmp), time_command=True)]
    if args.json:
        args.json.write_text(json.dumps(results, indent=1))
    print(f"load average {os.getloadavg()[0]:.1f} on {os.cpu_count()} cores")
    if args.md:
        print("| row | automatic: error (map px), worst | residual reported | 4 control points: error | "
              "area means: worst error | areas > 10 map px |")
        print("|---|---|---|---|---|---|")
    for row in ROWS:
        a, res, c, m, n = worst_row(results, row)
        if args.md:
            print(f"| {row} | {a:.3f} | {res:.3f} | {c:.3f} | {100 * m:.1f} % | {n} |")
        else:
            print(f"{row:32s} auto {a:.3f}  resid {res:.3f}  cp {c:.3f}  means {100 * m:.1f} %  areas {n}")
    times = [r["command_time_s"] for r in results if "command_time_s" in r]
    reg_t = [r["automatic time_s"] for r in results]
    print(f"uvps elements (1600 x 1200, 4 maps), end to end: {min(times):.2f}-{max(times):.2f} s; "
          f"registration alone {min(reg_t):.2f}-{max(reg_t):.2f} s")
    if args.doc:
        from benchdoc import write_doc
        doc = {"argv": list(sys.argv[1:] if argv is None else argv), "load": os.getloadavg()[0], "results": results}
        print("wrote", write_doc(DOC_SECTION, doc, render_doc(doc), source="scripts/benchmark_elements.py"))


if __name__ == "__main__":
    main()
