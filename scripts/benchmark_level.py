#!/usr/bin/env python3
"""What levelling does to a run's heights against a ground truth (docs/benchmarks.md, "Levelling").

For each run folder: the plane slope (um/mm, x right, y up) of ``depth.tif`` (levelled) and of the
raw height (``depth.tif`` + the surface run.json ``level`` records, ``uvps.core.level.raw_height``)
against the truth's, and the Pearson correlation of each with the true height (over the pixels
where both are finite). The truth is ``<capture>/truth/height_um.tif`` of a synthetic capture
(``uvps demo`` writes it to ``<run>/capture/truth/``), or ``--truth``.

Usage::

    .venv/bin/uvps demo -o /tmp/demo
    .venv/bin/python scripts/benchmark_level.py /tmp/demo [--truth /tmp/demo/capture/truth/height_um.tif]
"""
import argparse
import json
import sys
from pathlib import Path

import numpy as np
import tifffile

from uvps.core.level import fit_surface, raw_height


def plane_slopes(h, px):
    """dz/dx, dz/dy (um/mm) of the plain least-squares plane (no reweighting) over the finite pixels."""
    c = fit_surface(h, degree=1, robust=False)
    m, n = h.shape
    return c[1, 0] * 2 / ((n - 1) * px / 1000), c[0, 1] * 2 / ((m - 1) * px / 1000)


def corr(a, b):
    ok = np.isfinite(a) & np.isfinite(b)
    return float(np.corrcoef(a[ok].astype(np.float64), b[ok].astype(np.float64))[0, 1])


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("runs", nargs="+", type=Path)
    ap.add_argument("--truth", type=Path)
    a = ap.parse_args(argv)
    print("| run | level | truth plane (um/mm) | raw plane | depth.tif plane | corr raw | corr depth.tif |")
    print("|---|---|---|---|---|---|---|")
    for run in a.runs:
        truth_path = a.truth or run / "capture" / "truth" / "height_um.tif"
        truth = tifffile.imread(truth_path).astype(np.float32)
        depth = tifffile.imread(run / "depth.tif").astype(np.float32)
        log = json.loads((run / "run.json").read_text())
        px = float(log["params"]["pixel_size_um"])
        raw = raw_height(depth, log["level"])

        def fmt(h):
            sx, sy = plane_slopes(h, px)
            return f"{sx:+.2f}, {sy:+.2f}"

        print(f"| {run} | {log['level']['method']} | {fmt(truth)} | {fmt(raw)} | {fmt(depth)} | "
              f"{corr(raw, truth):.3f} | {corr(depth, truth):.3f} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
