#!/usr/bin/env python3
"""What levelling does to a run's heights against a ground truth (docs/benchmarks.md, "Levelling").

For each run folder: the plane slope (um/mm, x right, y up) of ``depth.tif`` (levelled) and of the
raw height (``depth.tif`` + the surface run.json ``level`` records, ``uvps.core.level.raw_height``)
against the truth's, and the Pearson correlation of each with the true height (over the pixels
where both are finite). The truth is ``<capture>/truth/height_um.tif`` of a synthetic capture
(``uvps demo`` writes it to ``<run>/capture/truth/``), or ``--truth``.

With ``--synthetic``: captures of the generator (300 x 400 px of 60 um, an 18 x 24 mm field, 12
lamps) on canvases bowed by ``--bows`` um, run in memory with the true lamp positions tilted by
``--bias-deg`` (rotated about the y axis: every lamp direction off by that much toward +x, the mean
normal bias a calibration can leave), once per level: the plane slopes as above, and the
field-scale shape left (rms of the degree-3 Legendre part of the heights minus the truth's).
``--nuisances`` adds what the image model leaves out, each alone at the top of its range
(``uvps.testing.synthetic.NUISANCE_TOP``: black level, vignetting, beams, stray light, ...; ``none``:
the clean capture), on every bow.

Usage::

    .venv/bin/uvps demo -o /tmp/demo
    .venv/bin/python scripts/benchmark_level.py /tmp/demo [--truth /tmp/demo/capture/truth/height_um.tif]
    .venv/bin/python scripts/benchmark_level.py --synthetic [--bows 0 100 250] [--seeds 0 1 2] [--bias-deg 0.2]
        [--nuisances none black_level vignetting beams stray_light]
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


def tilted(positions, deg):
    t = np.radians(deg)
    p = np.array(positions, float)
    x, z = p[:, 0].copy(), p[:, 2].copy()
    p[:, 0], p[:, 2] = x * np.cos(t) + z * np.sin(t), -x * np.sin(t) + z * np.cos(t)
    return p


def field_shape(h, px):
    """The degree-3 Legendre surface through ``h`` (um), as an array."""
    from uvps.core.level import Levelling
    c = fit_surface(h, degree=3)
    return Levelling("form", 3, c, h.shape, px, 0.0, 0.0).surface()


def synthetic(bows, seeds, bias_deg, nuisances=("none",)):
    import dataclasses
    from uvps.core.pipeline import RunOptions, run
    from uvps.testing.synthetic import SyntheticSpec, make_capture
    px = 60.0
    print("| nuisance | bow (um) | seed | level | truth plane (um/mm) | depth.tif plane | depth.tif - truth plane | "
          "field-scale shape left (um rms) | corr with truth |")
    print("|---|---|---|---|---|---|---|---|---|")
    for nuisance, bow, seed in ((n, b, s) for n in nuisances for b in bows for s in seeds):
        common = dict(shape=(300, 400), n_lights=12, seed=seed, pixel_size_um=px, bow_um=float(bow))
        spec = (SyntheticSpec(**common) if nuisance == "none"
                else SyntheticSpec.realistic(level="top", only=[nuisance], **common))
        cap = make_capture(spec)
        capture = cap.as_capture(lights="positions")
        capture = dataclasses.replace(capture, light_positions_mm=tilted(capture.light_positions_mm, bias_deg))
        truth = cap.height_um.astype(np.float32)
        tx, ty = plane_slopes(truth, px)
        for level in ("none", "plane", "form"):
            h = run(capture, RunOptions(level=level), stages=("height",)).height.height_um
            sx, sy = plane_slopes(h, px)
            left = field_shape(h, px) - field_shape(truth, px)
            left -= left.mean()
            if level != "none":
                # what a levelled view is measured against: the truth levelled the same way
                from uvps.core.level import level_height
                t_lev, _ = level_height(truth, method=level, pixel_size_um=px)
                left = field_shape(h, px) - field_shape(t_lev, px)
                left -= left.mean()
            print(f"| {nuisance} | {bow:g} | {seed} | {level} | {tx:+.2f}, {ty:+.2f} | {sx:+.2f}, {sy:+.2f} | "
                  f"{np.hypot(sx - tx, sy - ty):.2f} | {np.sqrt(np.mean(left ** 2)):.2f} | {corr(h, truth):.3f} |",
                  flush=True)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("runs", nargs="*", type=Path)
    ap.add_argument("--truth", type=Path)
    ap.add_argument("--synthetic", action="store_true")
    ap.add_argument("--bows", type=float, nargs="+", default=[0.0, 100.0, 250.0])
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    ap.add_argument("--bias-deg", type=float, default=0.2)
    ap.add_argument("--nuisances", nargs="+", default=["none"], metavar="NAME",
                    help="with --synthetic: none and/or keys of uvps.testing.synthetic.NUISANCE_TOP, each alone at "
                         "the top of its range (default: none)")
    a = ap.parse_args(argv)
    if a.synthetic:
        synthetic(a.bows, a.seeds, a.bias_deg, a.nuisances)
        return 0
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
