#!/usr/bin/env python
"""Benchmark uvps.core.detect on synthetic captures: precision / recall / F1 by width class, width error,
timing. Prints a Markdown table.

Detection runs on the synthetic ground-truth albedo and height with noise added (height: white
Gaussian, ``--height-noise`` um; albedo: multiplicative Gaussian, ``--albedo-noise``), at each
noise level given. A detection matches a true protrusion when their centroids are within
``max(2 px, 0.5 * true width)`` (greedy, closest pairs first, one-to-one). Widths are
equivalent-circle diameters (as ``uvps.core.measure``). A detection is counted in the width class of
its matched truth, an unmatched one in the class of its own width.

With ``--pipeline``, end to end: the albedo and height come from :func:`uvps.core.pipeline.run` on the
rendered capture with ``RunOptions()`` (what ``uvps run`` does by default), the lights estimated from
the images or given (the true lamp positions); detection then runs with ``DetectionParams()`` on
them as above (without colour areas; the truth's areas count the density per area).

With ``--wand``, the manual method instead: a click at the centre of every true protrusion of at
least 100 um on the albedo that ``uvps run`` computes with the true lamps (``--pipeline true``'s
maps; ``--pipeline estimated`` for estimated lamps), outlined by ``uvps wand``'s default (the
relative wand, :func:`uvps.core.wand.contrast_select`) and by ImageJ's wand at fixed tolerances (in the
albedo's counts); the share of clicks outlined within 0.5-2x the true footprint's area. The
relative wand's row counts a click only where ``uvps wand`` counts it (:func:`uvps.core.wand.judge_clicks`).

With ``--wand-off``, clicks off every protrusion, none of which ``uvps wand`` may count: on bare paint
at least 1 mm from any protrusion (the true albedo within 12 % of its colour area's paint), and on
bumps in the height alone (domes added to the height at other such points, the albedo unchanged,
the capture rendered again).

Example::

    .venv/bin/python scripts/benchmark_protrusions.py --seeds 0 1 2 --levels 0.3,0.01 1.0,0.03
    .venv/bin/python scripts/benchmark_protrusions.py --wand --seeds 0 1 2 [--doc]

With ``--wand``, ``--doc`` writes docs/benchmarks.md's wand table (section ``wand``) and the table's
figures at full precision, with every click's area ratio, into docs/benchmarks/wand.json
(scripts/benchdoc.py); detection and ``--wand-off`` are not written.
"""
from __future__ import annotations

import argparse
import sys
import time

import cv2
import numpy as np
from scipy.spatial import cKDTree
from skimage.measure import regionprops_table

from uvps.core.detect import DetectionParams, detect_protrusions
from uvps.core.measure import measure_protrusions
from uvps.testing.synthetic import make_capture

CLASSES = [(0, 60), (60, 100), (100, 200), (200, 400), (400, 10000)]
DOC_SECTION = "wand"


def _class_name(lo, hi):
    return f">= {lo} um" if hi >= 10000 else f"{lo}-{hi} um"


def match(true_xy, true_w_px, det_xy):
    """Greedy one-to-one matching by centroid distance <= max(2, 0.5 * true width) px."""
    if len(true_xy) == 0 or len(det_xy) == 0:
        return np.full(len(true_xy), -1), np.full(len(det_xy), -1)
    tree = cKDTree(det_xy)
    radius = np.maximum(2.0, 0.5 * true_w_px)
    pairs = []
    for i, (xy, r) in enumerate(zip(true_xy, radius)):
        for j in tree.query_ball_point(xy, r):
            pairs.append((float(np.hypot(*(det_xy[j] - xy))), i, j))
    pairs.sort()
    t2d = np.full(len(true_xy), -1)
    d2t = np.full(len(det_xy), -1)
    for _, i, j in pairs:
        if t2d[i] < 0 and d2t[j] < 0:
            t2d[i], d2t[j] = j, i
    return t2d, d2t


def pipeline_maps(cap, *, true_lights):
    """Albedo and height as ``uvps run`` computes them from the rendered capture (12 lamps, noise).

    :func:`uvps.core.pipeline.run` with ``RunOptions()`` (the defaults of ``uvps run``: additive term
    measured, lamps refined, Frankot-Chellappa); the lights estimated from the images, or the true
    ones as a calibrated positions file gives them (``as_capture(lights="positions")``).
    """
    from uvps.core.pipeline import RunOptions, run

    res = run(cap.as_capture(lights="positions" if true_lights else "estimate"), RunOptions(),
              stages=("normals", "height"))
    return res.stereo.albedo, res.height.height_um


def run_one(seed, shape, height_noise, albedo_noise, params, pipeline=None):
    if pipeline:
        cap = make_capture(shape=shape, seed=seed, n_lights=12)
        alb, h = pipeline_maps(cap, true_lights=(pipeline == "true"))
    else:
        cap = make_capture(shape=shape, seed=seed, n_lights=3, noise=False)
        rng = np.random.default_rng(1000 + seed)
        h = cap.height_um + rng.normal(0, height_noise, cap.height_um.shape).astype(np.float32)
        alb = cap.albedo * (1 + rng.normal(0, albedo_noise, cap.albedo.shape)).astype(np.float32)
    px = cap.spec.pixel_size_um
    t0 = time.perf_counter()
    det = detect_protrusions(alb, h, pixel_size_um=px, params=params)
    t1 = time.perf_counter()
    measure_protrusions(det.labels, albedo=alb, height_um=h, pixel_size_um=px, regions=cap.regions,
                        source=det.source)
    elapsed_measure = time.perf_counter() - t1
    elapsed = t1 - t0
    props = regionprops_table(det.labels, properties=("label", "centroid", "area"))
    det_xy = np.column_stack([props["centroid-1"], props["centroid-0"]])
    det_w = np.sqrt(4 * props["area"] / np.pi) * px
    pr = cap.protrusions
    true_xy = np.column_stack([pr["x_px"], pr["y_px"]])
    t2d, d2t = match(true_xy, pr["width_um"] / px, det_xy)
    # density per colour area (the truth's areas, as a user's hand-drawn ones): counts by centroid
    dens = []
    reg = cap.regions
    det_reg = reg[np.clip(np.round(props["centroid-0"]).astype(int), 0, reg.shape[0] - 1),
                  np.clip(np.round(props["centroid-1"]).astype(int), 0, reg.shape[1] - 1)]
    for lab in np.unique(reg):
        n_true = int(np.sum(pr["region"] == lab))
        if n_true >= 10:
            dens.append((np.sum(det_reg == lab) - n_true) / n_true)
    return dict(true_w=pr["width_um"], weak=pr["weak"], t2d=t2d, d2t=d2t, det_w=det_w, dens=dens,
                time=elapsed, time_measure=elapsed_measure, rejected=det.rejected, source=det.source)


def wand_one(seed, shape, pipeline, tolerances):
    """Area ratios (outlined / true footprint) of the clicks at the true centres of protrusions
    >= 100 um: the relative wand's default and ImageJ's wand at each of ``tolerances``."""
    from uvps.core.wand import MAX_WIDTH_UM, contrast_select, judge_clicks, wand_select

    cap = make_capture(shape=shape, seed=seed, n_lights=12)
    alb, _h = pipeline_maps(cap, true_lights=(pipeline != "estimated"))
    pr = cap.protrusions
    big = pr["width_um"] >= 100
    px = cap.spec.pixel_size_um
    clicks = np.column_stack([pr["x_px"][big], pr["y_px"][big]])
    true_area = np.pi * (pr["width_um"][big] / px / 2) ** 2
    out = {}

    def ratios(labels):
        ids = labels[np.floor(clicks[:, 1]).astype(int), np.floor(clicks[:, 0]).astype(int)]
        area = np.bincount(labels.ravel(), minlength=int(labels.max()) + 1)
        return np.where(ids > 0, area[ids], 0) / true_area

    judged = judge_clicks(contrast_select(alb, clicks, max_width_px=MAX_WIDTH_UM / px), clicks, height=_h, albedo=alb,
                          max_width_px=MAX_WIDTH_UM / px)
    out["relative 0.5 (default)"] = ratios(judged.labels)
    for tol in tolerances:
        out[f"ImageJ {tol:g}"] = ratios(wand_select(alb, clicks, tolerance=tol))
    return out


def wand_off_one(seed, shape, pipeline, n_bare=100, n_bumps=30):
    """Clicks off every protrusion and how ``uvps wand``'s default judges them: ``{kind: (status per
    click, relief ratio per click)}``. Bare paint: points >= 1 mm from any protrusion's rim (the true
    albedo within 12 % of its colour area's paint). Height only: domes 100-300 um wide and 0.15-0.35 x
    as high added to the height at other such points, with the albedo unchanged, and the capture
    rendered again (:func:`uvps.testing.synthetic.render_images`, the capture's lamps, exposure and
    noise)."""
    import dataclasses

    from scipy import ndimage as ndi

    from uvps.core.wand import MAX_WIDTH_UM, contrast_select, judge_clicks
    from uvps.testing.synthetic import render_images

    cap = make_capture(shape=shape, seed=seed, n_lights=12)
    pr, px = cap.protrusions, cap.spec.pixel_size_um
    m, n = cap.height_um.shape
    far = np.ones((m, n), bool)
    far[np.floor(pr["y_px"]).astype(int), np.floor(pr["x_px"]).astype(int)] = False
    dist_um = ndi.distance_transform_edt(far) * px
    paint = np.zeros_like(cap.albedo)
    for lab in np.unique(cap.regions):
        sel = cap.regions == lab
        paint[sel] = np.median(cap.albedo[sel], axis=0)
    bare = (dist_um >= 1000.0 + pr["width_um"].max() / 2 + 300) \
        & np.all(np.abs(cap.albedo - paint) < 0.12 * np.abs(paint).max(), axis=-1)
    bare[:30], bare[-30:], bare[:, :30], bare[:, -30:] = False, False, False, False
    ys, xs = np.nonzero(bare)
    rng = np.random.default_rng(seed)
    spots = []
    for k in rng.permutation(len(xs)):                       # spots >= 0.6 mm apart
        if all(np.hypot(xs[k] - x, ys[k] - y) * px >= 600 for x, y in spots):
            spots.append((int(xs[k]), int(ys[k])))
        if len(spots) == n_bare + n_bumps:
            break
    bumps, plain = spots[:n_bumps], spots[n_bumps:]
    height = cap.height_um.astype(np.float64).copy()
    yy, xx = np.mgrid[:m, :n]
    for x, y in bumps:
        w = rng.uniform(100, 300) / px
        rho2 = ((xx - x) ** 2 + (yy - y) ** 2) / (w / 2) ** 2
        height += np.where(rho2 < 1, rng.uniform(0.15, 0.35) * w * px * (1 - rho2), 0.0)
    images = render_images(height, cap.albedo, pixel_size_um=px, light_positions_mm=cap.light_positions_mm,
                           intensities=cap.intensities, rng=seed, gain=cap.gain, exposure=cap.exposure, read_noise=cap.spec.read_noise,
                           dtype=cap.images.dtype)
    cap = dataclasses.replace(cap, images=images, height_um=height.astype(np.float32))
    alb, h = pipeline_maps(cap, true_lights=(pipeline != "estimated"))
    out = {}
    for kind, clicks in (("bare paint", np.array(plain).reshape(-1, 2)), ("height only", np.array(bumps).reshape(-1, 2))):
        labels = contrast_select(alb, clicks, max_width_px=MAX_WIDTH_UM / px)
        judged = judge_clicks(labels, clicks, height=h, albedo=alb, max_width_px=MAX_WIDTH_UM / px)
        out[kind] = (judged.status, judged.relief_ratio)
    return out


def wand_off_report(args) -> None:
    runs = [wand_off_one(s, tuple(args.shape), args.pipeline) for s in args.seeds]
    print(f"Synthetic captures {args.shape[0]}x{args.shape[1]} px at 15 um/px, 12 lamps, 30 domes added to the "
          f"height alone, seeds {args.seeds}; albedo and height from uvps run with {args.pipeline or 'true'} lights.\n")
    print("| clicks on | clicks | counted | worst seed | judged bare paint | judged height only | "
          "albedo outlines judged (largest relief ratio) |")
    print("|---|---|---|---|---|---|---|")
    for kind in ("bare paint", "height only"):
        st = [np.array(r[kind][0]) for r in runs]
        rat = np.concatenate([r[kind][1] for r in runs])
        allst = np.concatenate(st) if st else np.zeros(0)
        worst = max((np.count_nonzero(s == "outlined") for s in st), default=0)
        fin = rat[np.isfinite(rat)]
        print(f"| {kind} | {allst.size} | {np.count_nonzero(allst == 'outlined')} | {worst} | "
              f"{np.count_nonzero(allst == 'bare paint')} | {np.count_nonzero(allst == 'height only')} | "
              f"{fin.size} ({fin.max() if fin.size else float('nan'):.1f}) |")


def wand_rows(runs: list) -> list:
    """Per wand, over the seeds' clicks: the count, the shares within 0.5-2x the true area (all, worst seed),
    below 0.5x and above 2x, and the median area ratio."""
    rows = []
    for name in runs[0]:
        per = [np.asarray(r[name]) for r in runs]
        allr = np.concatenate(per)
        rows.append({"wand": name, "clicks": int(allr.size), "within": float(np.mean((allr >= 0.5) & (allr <= 2))),
                     "worst_seed": float(min(np.mean((r >= 0.5) & (r <= 2)) for r in per)),
                     "median_ratio": float(np.median(allr)), "below_half": float(np.mean(allr < 0.5)),
                     "above_twice": float(np.mean(allr > 2))})
    return rows


def render_doc(results: dict) -> str:
    """docs/benchmarks.md's wand table from ``{"rows": wand_rows(...), ...}`` (docs/benchmarks/wand.json)."""
    lines = ["| wand | clicks | within 0.5-2x the true area | worst seed | median area ratio | < 0.5x | > 2x |",
             "|---|---|---|---|---|---|---|"]
    for r in results["rows"]:
        lines.append(f"| {r['wand']} | {r['clicks']} | {100 * r['within']:.1f} % | {100 * r['worst_seed']:.1f} % | "
                     f"{r['median_ratio']:.2f} | {100 * r['below_half']:.1f} % | {100 * r['above_twice']:.1f} % |")
    return "\n".join(lines) + "\n"


def wand_report(args) -> None:
    tolerances = [float(t) for t in args.wand_tolerances]
    runs = [wand_one(s, tuple(args.shape), args.pipeline, tolerances) for s in args.seeds]
    print(f"Synthetic captures {args.shape[0]}x{args.shape[1]} px at 15 um/px, 12 lamps, seeds {args.seeds}; "
          f"albedo from uvps run with {args.pipeline or 'true'} lights; a click at the centre of every true "
          "protrusion >= 100 um.\n")
    results = {"argv": args.argv, "rows": wand_rows(runs),
               "ratios": {name: [np.round(r[name], 4).tolist() for r in runs] for name in runs[0]}}
    text = render_doc(results)
    print(text)
    if args.doc:
        from benchdoc import write_doc
        print("wrote", write_doc(DOC_SECTION, results, text, source="scripts/benchmark_protrusions.py"))


def summarise(runs):
    rows = []
    true_w = np.concatenate([r["true_w"] for r in runs])
    weak = np.concatenate([r["weak"] for r in runs])
    t2d_w = []  # matched detection width per truth (nan if missed)
    det_class_w = []  # width used to class each detection
    det_tp = []
    for r in runs:
        tw = np.full(len(r["t2d"]), np.nan)
        ok = r["t2d"] >= 0
        tw[ok] = r["det_w"][r["t2d"][ok]]
        t2d_w.append(tw)
        dw = r["det_w"].copy()
        m = r["d2t"] >= 0
        dw[m] = r["true_w"][r["d2t"][m]]
        det_class_w.append(dw)
        det_tp.append(m)
    t2d_w = np.concatenate(t2d_w)
    det_class_w = np.concatenate(det_class_w)
    det_tp = np.concatenate(det_tp)
    found = np.isfinite(t2d_w)
    for lo, hi in CLASSES + [(60, 10000), (200, 10000)]:
        tin = (true_w >= lo) & (true_w < hi)
        din = (det_class_w >= lo) & (det_class_w < hi)
        n_true, tp = int(tin.sum()), int((tin & found).sum())
        n_det, tp_d = int(din.sum()), int((din & det_tp).sum())
        rec = tp / n_true if n_true else float("nan")
        prec = tp_d / n_det if n_det else float("nan")
        f1 = 2 * prec * rec / (prec + rec) if prec + rec > 0 else float("nan")
        err = np.abs(t2d_w[tin & found] - true_w[tin & found]) / true_w[tin & found]
        bias = (t2d_w[tin & found] - true_w[tin & found]) / true_w[tin & found]
        wrec = (tin & found & weak).sum() / max((tin & weak).sum(), 1)
        rows.append((_class_name(lo, hi) if (lo, hi) not in [(60, 10000), (200, 10000)] else f"all >= {lo} um",
                     n_true, n_det, prec, rec, f1, wrec,
                     float(np.median(err)) if err.size else float("nan"),
                     float(np.median(bias)) if bias.size else float("nan")))
    return rows


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    ap.add_argument("--shape", type=int, nargs=2, default=[1200, 1600])
    ap.add_argument("--levels", nargs="+", default=["0.3,0.01", "1.0,0.03", "2.0,0.05"],
                    help="noise levels as HEIGHT_UM,ALBEDO_FRACTION")
    ap.add_argument("--pipeline", choices=["estimated", "true"],
                    help="end to end: detect on the albedo and height the core computes from the rendered "
                         "12-lamp capture, with lights estimated from the images or the true ones "
                         "(--levels is then ignored)")
    ap.add_argument("--wand", action="store_true", help="the manual method's outlines instead of detection")
    ap.add_argument("--wand-off", action="store_true",
                    help="clicks off every protrusion (bare paint, height-only bumps): how many the wand counts")
    ap.add_argument("--wand-tolerances", nargs="+", default=["0.05", "1000", "3000"],
                    help="ImageJ wand tolerances (albedo counts) compared with the relative wand")
    ap.add_argument("--doc", action="store_true",
                    help="with --wand: write its table into docs/benchmarks.md (section wand) and "
                         "docs/benchmarks/wand.json")
    args = ap.parse_args(argv)
    args.argv = list(sys.argv[1:] if argv is None else argv)
    if args.doc and not args.wand:
        ap.error("--doc writes the wand table only: give --wand too")
    if args.wand:
        wand_report(args)
        return 0
    if args.wand_off:
        wand_off_report(args)
        return 0
    if args.pipeline:
        args.levels = ["pipeline"]
    cv2.setNumThreads(1)  # the target is one core
    params = DetectionParams()
    print(f"Synthetic captures {args.shape[0]}x{args.shape[1]} px at 15 um/px, seeds {args.seeds}; "
          f"detect_protrusions defaults.\n")
    for level in args.levels:
        hn, an = (0.0, 0.0) if level == "pipeline" else (float(v) for v in level.split(","))
        runs = [run_one(s, tuple(args.shape), hn, an, params, pipeline=args.pipeline) for s in args.seeds]
        rows = summarise(runs)
        times = [r["time"] for r in runs]
        tm = [r["time"] + r["time_measure"] for r in runs]
        rej = {}
        for r in runs:
            for k, v in r["rejected"].items():
                rej[k] = rej.get(k, 0) + v
        if args.pipeline:
            print(f"### end to end: core albedo and height, {args.pipeline} lights\n")
        else:
            print(f"### height noise {hn} um, albedo noise {100 * an:.0f} %\n")
        print("| width class | true | detected | precision | recall | F1 | weak recall | median abs width err | median width bias |")
        print("|---|---|---|---|---|---|---|---|---|")
        for name, nt, nd, pr, rc, f1, wr, err, bias in rows:
            print(f"| {name} | {nt} | {nd} | {pr:.3f} | {rc:.3f} | {f1:.3f} | {wr:.2f} | {100 * err:.1f} % | {100 * bias:+.1f} % |")
        print(f"\ntime per capture (one core): detection median {np.median(times):.2f} s "
              f"(max {max(times):.2f} s); detection + uvps.core.measure statistics median "
              f"{np.median(tm):.2f} s (max {max(tm):.2f} s)\n\nrejected candidates: {rej}\n")
        dens = np.abs(np.concatenate([r["dens"] for r in runs]))
        if dens.size:
            print(f"density per colour area (areas with >= 10 true protrusions, n = {dens.size}): "
                  f"median abs error {100 * np.median(dens):.1f} %, max {100 * dens.max():.1f} %\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
