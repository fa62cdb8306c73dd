#!/usr/bin/env python
"""Benchmark uvps.core.detect on protrusions and surfaces it was not tuned to. Prints Markdown tables.

Each capture is ``SyntheticSpec.realistic("top")``: every nuisance of a real capture at the top of
its realistic range (``uvps.testing.synthetic.NUISANCE_TOP``), among them protrusions of every kind
(``MIXED_SHAPES``: domes, craters, mesas, irregular outlines, touching clusters, non-fluorescing
ones; 40-500 um wide, 5-150 um high), a weave of two scales, strokes 60-1500 um wide, cupping with
cracks, cast shadows, black level, stray light, vignetting, lamp beams. Detection runs either on
the generator's true albedo, height and normals (default; ``--height-noise`` adds white noise) or,
with ``--pipeline``, end to end: the capture is written with ``uvps.testing.synthetic.write_capture`` and
the real command ``uvps run CAPTURE -o RUN --detect --lights CAPTURE/lights_positions_mm.csv
--black-level B`` computes everything from the images given the measured lamp positions (as the
README advises) and the camera's black level (``--uncalibrated`` leaves both out), then
``protrusions.csv`` is scored.

Scores per capture, then the worst over the seeds: precision, recall and F1 for protrusions
>= 60 um wide, recall above 200 um, median absolute width error (matched, >= 60 um), and recall
per kind (``shape`` column of the truth; ``cluster`` = members of touching clusters, ``dark`` =
non-fluorescing). Matching to the truth is ``benchmark_protrusions.match`` (centroids within
max(2 px, half the true width), one to one); a detection is counted in the width class of its
matched truth, an unmatched one in that of its own width.

``--doc`` (true maps, no detector option changed) writes this scene's row of docs/benchmarks.md's table
"Detection on other shapes and surfaces" (section ``detection``: :func:`render_doc`) and keeps it in
docs/benchmarks/detection.json with the other scenes' rows (scripts/benchdoc.py).

Example::

    OMP_NUM_THREADS=1 .venv/bin/python scripts/benchmark_detection.py --seeds 0 1 2
    OMP_NUM_THREADS=1 .venv/bin/python scripts/benchmark_detection.py --seeds 0 1 2 --pipeline
"""
from __future__ import annotations

import argparse
import ast
import re
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from scipy.stats import binomtest
from skimage.measure import regionprops_table

from benchmark_protrusions import match
from uvps.core.detect import DetectionParams, detect_protrusions
from uvps.files.tables import read_protrusions_csv
from uvps.testing.synthetic import IMPASTO, SyntheticSpec, make_capture, write_capture

DOC_SECTION = "detection"
#: The targets (worst seed) docs/benchmarks.md's table marks **x** when missed: key -> (bound, "min"/"max").
DOC_TARGETS = {"f1": (0.95, "min"), "recall_200": (0.97, "min"), "recall_60_100": (0.9, "min"),
               "width_err": (0.10, "max")}
KINDS = ("dome", "crater", "mesa", "irregular", "cluster", "dark", "weak", "on_stroke")
#: Width classes (um) of the per-bin precision and recall.
BINS = ((60.0, 100.0), (100.0, 200.0), (200.0, 500.0))
#: Scenes: ``top`` every nuisance at the top of its range; ``impasto`` that and paint as real
#: impasto (``uvps.testing.synthetic.IMPASTO``: strokes up to 40 um high at twice the density, blunt ends
#: with piled paint, ripples, bristle grooves, crossings; protrusions on strokes, weak ones,
#: primer spots); the others one impasto morphology alone on top of ``top``.
SCENES = {
    "top": {},
    "impasto": dict(IMPASTO),
    "strokes_40um_x2": {k: IMPASTO[k] for k in ("ridge_width_um", "ridge_height_um",
                                                "ridge_density")},
    "blunt_ends": {"ridge_blunt_fraction": 1.0, "ridge_height_um": (5.0, 40.0)},
    "ripples": {"ridge_ripple": IMPASTO["ridge_ripple"], "ridge_height_um": (5.0, 40.0)},
    "grooves_crossings": {"ridge_groove_um": IMPASTO["ridge_groove_um"],
                          "ridge_crossing_fraction": 0.5, "ridge_height_um": (5.0, 40.0)},
    "on_strokes": {"on_stroke_fraction": 0.5, "ridge_height_um": (5.0, 40.0),
                   "ridge_density": 8.0},
    "primer_weak": {"primer_density": 9.0, "weak_fraction": 0.25},
}


def _detections_from_truth(cap, height_noise, params=None):
    """Centroids (x, y px), widths (um), the Detection and the time of detect_protrusions on the
    generator's true albedo, height and normals (plus white height noise)."""
    px = cap.spec.pixel_size_um
    h = cap.height_um
    if height_noise > 0:
        rng = np.random.default_rng(1000 + cap.spec.seed)
        h = h + rng.normal(0, height_noise, h.shape).astype(np.float32)
    t0 = time.perf_counter()
    det = detect_protrusions(cap.albedo, h, pixel_size_um=px, normals=cap.normals, params=params)
    elapsed = time.perf_counter() - t0
    props = regionprops_table(det.labels, properties=("centroid", "area"))
    xy = np.column_stack([props["centroid-1"], props["centroid-0"]])
    return xy, np.sqrt(4 * props["area"] / np.pi) * px, det, elapsed


def miss_reasons(cap, det, xy, lo=60.0, hi=100.0):
    """Why each true protrusion ``lo``-``hi`` um wide was missed, read at its true centre in the
    detector's candidate labels: the rule that rejected the candidate there, ``merged`` (a kept
    candidate covers it: it was counted with a neighbour, or its centroid is off), or
    ``no candidate``. Returns {reason: count}."""
    pr = cap.protrusions
    px = cap.spec.pixel_size_um
    t2d, _ = match(np.column_stack([pr["x_px"], pr["y_px"]]), pr["width_um"] / px, xy)
    cl = det.diagnostics.get("candidate_labels")
    reasons = det.diagnostics.get("candidate_reasons")
    out = {}
    if cl is None:
        return out
    ids = np.unique(cl[cl > 0])
    for i in np.flatnonzero((t2d < 0) & (pr["width_um"] >= lo) & (pr["width_um"] < hi)):
        r = int(np.clip(np.rint(pr["y_px"][i]), 0, cl.shape[0] - 1))
        c = int(np.clip(np.rint(pr["x_px"][i]), 0, cl.shape[1] - 1))
        k = cl[r, c]
        why = "no candidate" if k == 0 else (str(reasons[np.searchsorted(ids, k)]) or "merged")
        out[why] = out.get(why, 0) + 1
    return out


def _checked(cmd):
    """``subprocess.run(cmd)``, its output captured; a failure raised with the end of its stderr."""
    done = subprocess.run(cmd, capture_output=True, text=True)
    if done.returncode != 0:
        raise RuntimeError(f"{' '.join(cmd)} failed ({done.returncode}): {done.stderr.strip()[-2000:]}")
    return done


def _detections_from_pipeline(cap, workdir: Path, uncalibrated: bool, again: list | None = None):
    """The same from ``uvps run CAPTURE -o RUN --detect`` on the written capture, given the
    lamp positions (``lights_positions_mm.csv``) and the camera's black level unless
    ``uncalibrated``; with ``again`` (options such as ``["--curl-k", "15"]``), detected again by
    ``uvps detect -o RUN`` with them."""
    capture_dir, run_dir = workdir / "capture", workdir / "run"
    write_capture(cap, capture_dir, truth=False)
    cmd = [sys.executable, "-m", "uvps", "run", str(capture_dir), "-o", str(run_dir), "--detect",
           "--pixel-size-um", str(cap.spec.pixel_size_um)]
    if not uncalibrated:
        black = cap.nuisances.black_level
        cmd += ["--lights", str(capture_dir / "lights_positions_mm.csv")]
        if black is not None:
            cmd += ["--black-level", ",".join(f"{float(b):g}" for b in np.atleast_1d(black))]
    t0 = time.perf_counter()
    done = _checked(cmd)
    elapsed = time.perf_counter() - t0
    if again:
        done = _checked([sys.executable, "-m", "uvps", "detect", "-o", str(run_dir), *again])
    table = read_protrusions_csv(run_dir / "protrusions.csv")
    # the rejection counts, from the detector's log line on stderr
    found = re.search(r"uvps\.core\.detect: detect: .*rejected (\{[^}]*\})", done.stderr)
    rejected = ast.literal_eval(found.group(1)) if found else {}
    return np.column_stack([table["x_px"], table["y_px"]]), table["width_um"], rejected, elapsed


def score(cap, det_xy, det_w):
    """Scores of one capture (see the module docstring)."""
    pr = cap.protrusions
    px = cap.spec.pixel_size_um
    true_w = pr["width_um"]
    t2d, d2t = match(np.column_stack([pr["x_px"], pr["y_px"]]), true_w / px, det_xy)
    big = true_w >= 60
    det_class_w = np.where(d2t >= 0, true_w[np.maximum(d2t, 0)], det_w)
    n_det = int(np.sum(det_class_w >= 60))
    tp_det = int(np.sum((det_class_w >= 60) & (d2t >= 0)))
    found = t2d >= 0
    rec = float(np.mean(found[big])) if big.any() else float("nan")
    prec = tp_det / n_det if n_det else float("nan")
    f1 = 2 * prec * rec / (prec + rec) if prec + rec > 0 else float("nan")
    ok = big & found
    err = np.abs(det_w[t2d[ok]] / true_w[ok] - 1)
    bias = det_w[t2d[ok]] / true_w[ok] - 1
    out = {"true": int(big.sum()), "detected": n_det, "precision": prec, "recall": rec, "f1": f1,
           "recall_200": float(np.mean(found[true_w > 200])) if np.any(true_w > 200) else float("nan"),
           "n_200": int(np.sum(true_w > 200)),
           "width_err": float(np.median(err)) if err.size else float("nan"),
           "width_bias": float(np.median(bias)) if bias.size else float("nan")}
    kind_of = {"cluster": pr["cluster"] > 0, "dark": pr["dark"].astype(bool),
               "weak": pr["weak"].astype(bool),
               "on_stroke": pr.get("on_stroke", np.zeros(true_w.size, bool)).astype(bool)}
    for kind in KINDS:
        sel = big & kind_of.get(kind, pr["shape"] == kind)
        out[f"n_{kind}"] = int(sel.sum())
        out[f"found_{kind}"] = int(np.sum(found[sel]))
    for lo, hi in BINS:
        t_sel = (true_w >= lo) & (true_w < hi)
        d_sel = (det_class_w >= lo) & (det_class_w < hi)
        out[f"bin_{lo:g}"] = (int(np.sum(found[t_sel])), int(t_sel.sum()),
                              int(np.sum(d_sel & (d2t >= 0))), int(d_sel.sum()))
    # where the false positives (>= 60 um) lie: on a stroke (> 1 um of stroke relief), else
    strokes = cap.nuisances.strokes
    fp = (d2t < 0) & (det_class_w >= 60)
    on = np.zeros(fp.size, bool)
    if strokes is not None and fp.any():
        r = np.clip(np.rint(det_xy[:, 1]).astype(int), 0, strokes.shape[0] - 1)
        c = np.clip(np.rint(det_xy[:, 0]).astype(int), 0, strokes.shape[1] - 1)
        on = strokes[r, c] > 1.0
    out["fp_stroke"], out["fp_other"] = int(np.sum(fp & on)), int(np.sum(fp & ~on))
    return out


def run_seed(seed, shape, args):
    spec = SyntheticSpec.realistic("top", shape=tuple(shape), seed=seed, **SCENES[args.scene])
    if args.pipeline:
        cap = make_capture(spec)
        with tempfile.TemporaryDirectory(prefix="uvps_bench_") as tmp:
            again = [a for name, value in args.params.items()
                     for a in ("--" + name.replace("_", "-"), str(value))]
            xy, w, rejected, elapsed = _detections_from_pipeline(cap, Path(tmp), args.uncalibrated, again)
    else:
        # the scene does not depend on the lamps: 3 noise-free images are enough for the truth
        cap = make_capture(spec, n_lights=3, noise=False, cast_shadows=False)
        params = DetectionParams(**args.params)
        xy, w, det, elapsed = _detections_from_truth(cap, args.height_noise, params)
        rejected = det.rejected
    res = score(cap, xy, w)
    res.update(seed=seed, time=elapsed, rejected=rejected)
    if getattr(args, "misses", False) and not args.pipeline:
        res["misses"] = miss_reasons(cap, det, xy)
    return res


def _pct(v):
    return f"{100 * v:.1f} %"


def print_tables(results, args):
    timed = "`uvps run` (s)" if args.pipeline else "detection (s)"
    print("| seed | true >= 60 um | detected | precision | recall | F1 | recall > 200 um (n) | "
          f"median abs width err | median width bias | {timed} |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    for r in results:
        print(f"| {r['seed']} | {r['true']} | {r['detected']} | {r['precision']:.3f} | "
              f"{r['recall']:.3f} | {r['f1']:.3f} | {r['recall_200']:.3f} ({r['n_200']}) | "
              f"{_pct(r['width_err'])} | {r['width_bias'] * 100:+.1f} % | {r['time']:.1f} |")
    worst = {"f1": min(r["f1"] for r in results), "recall_200": min(r["recall_200"] for r in results),
             "width_err": max(r["width_err"] for r in results)}
    print(f"| **worst** | | | {min(r['precision'] for r in results):.3f} | "
          f"{min(r['recall'] for r in results):.3f} | **{worst['f1']:.3f}** | "
          f"**{worst['recall_200']:.3f}** | **{_pct(worst['width_err'])}** | | |")
    print("\nRecall per kind (protrusions >= 60 um; found / true per seed, worst seed's recall):\n")
    print("| kind | " + " | ".join(f"seed {r['seed']}" for r in results) + " | worst recall |")
    print("|---|" + "---|" * (len(results) + 1))
    for kind in KINDS:
        cells = [f"{r['found_' + kind]} / {r['n_' + kind]}" for r in results]
        recs = [r["found_" + kind] / r["n_" + kind] for r in results if r["n_" + kind]]
        print(f"| {kind} | " + " | ".join(cells) + (f" | {min(recs):.3f} |" if recs else " | - |"))
    total = {}
    for r in results:
        for k, v in r["rejected"].items():
            total[k] = total.get(k, 0) + int(v)
    print("\nPer width class (found / true, right / detected; worst seed's recall and precision; the "
          "recall pooled over the seeds with its 95 % Wilson interval, scipy.stats.binomtest):\n")
    print("| width (um) | " + " | ".join(f"seed {r['seed']}" for r in results)
          + " | worst recall | worst precision | pooled recall (95 %) |")
    print("|---|" + "---|" * (len(results) + 3))
    worst_rec_60 = 1.0
    for lo, hi in BINS:
        cells = [r[f"bin_{lo:g}"] for r in results]
        recs = [c[0] / c[1] for c in cells if c[1]]
        precs = [c[2] / c[3] for c in cells if c[3]]
        if lo == 60.0 and recs:
            worst_rec_60 = min(recs)
        found, n = sum(c[0] for c in cells), sum(c[1] for c in cells)
        pooled = "-"
        if n:
            ci = binomtest(found, n).proportion_ci(confidence_level=0.95, method="wilson")
            pooled = f"{found / n:.3f} ({ci.low:.2f}-{ci.high:.2f})"
        print(f"| {lo:g}-{hi:g} | " + " | ".join(f"{c[0]} / {c[1]}, {c[2]} / {c[3]}" for c in cells)
              + f" | {min(recs) if recs else float('nan'):.3f} | "
                f"{min(precs) if precs else float('nan'):.3f} | {pooled} |")
    fps = ", ".join(f"seed {r['seed']}: {r['fp_stroke']} on strokes, {r['fp_other']} elsewhere"
                    for r in results)
    print(f"\nfalse positives >= 60 um: {fps}")
    print(f"\nrejected candidates (all seeds): {total}\n")
    if any("misses" in r for r in results):
        print("Misses 60-100 um by the detector's reason at the true centre: "
              + "; ".join(f"seed {r['seed']}: {r.get('misses', {})}" for r in results) + "\n")
    targets = [("F1 >= 0.95 for protrusions >= 60 um", worst["f1"] >= 0.95, f"{worst['f1']:.3f}"),
               ("recall >= 0.9 for 60-100 um", worst_rec_60 >= 0.9, f"{worst_rec_60:.3f}"),
               ("recall >= 0.97 above 200 um", worst["recall_200"] >= 0.97,
                f"{worst['recall_200']:.3f}"),
               ("widths within 10 % (median)", worst["width_err"] <= 0.10, _pct(worst["width_err"]))]
    print("| target (worst seed) | measured | met? |\n|---|---|---|")
    for name, met, value in targets:
        print(f"| {name} | {value} | {'yes' if met else 'no'} |")


def doc_row(results, scene: str) -> dict:
    """One scene's row of the doc's table from its seeds' scores: the worst seed per column, the 60-100 um
    recall pooled over the seeds with its 95 % Wilson interval, the false positives' range per capture."""
    cells = [r["bin_60"] for r in results]
    found, n = sum(c[0] for c in cells), sum(c[1] for c in cells)
    ci = binomtest(found, n).proportion_ci(confidence_level=0.95, method="wilson")
    fps = [r["fp_stroke"] + r["fp_other"] for r in results]
    on = sum(r["fp_stroke"] for r in results)
    return {"scene": scene, "seeds": [r["seed"] for r in results],
            "precision": min(r["precision"] for r in results), "recall": min(r["recall"] for r in results),
            "f1": min(r["f1"] for r in results), "recall_200": min(r["recall_200"] for r in results),
            "recall_60_100": min(c[0] / c[1] for c in cells if c[1]),
            "pooled_60_100": [found / n, ci.low, ci.high], "width_err": max(r["width_err"] for r in results),
            "false_positives": [min(fps), max(fps)],
            "fp_note": f"{on} of {sum(fps)} on strokes" if sum(fps) else ""}


def render_doc(results: dict) -> str:
    """docs/benchmarks.md's "Detection on other shapes and surfaces" table: one row per scene.

    Worst seed per column; bold: the columns of the detection targets (F1, recall above 200 um and
    60-100 um), **x** after a value missing its target (:data:`DOC_TARGETS`); the false positives' range over
    the captures with its note in brackets.

    Parameters
    ----------
    results : dict
        ``{"rows": [doc_row(...) per scene]}`` as docs/benchmarks/detection.json keeps it.
    """
    def cell(row, key, text, bold=False):
        bound, sense = DOC_TARGETS[key]
        v = row[key]
        miss = v < bound if sense == "min" else v > bound
        return (f"**{text}**" if bold else text) + (" **x**" if miss else "")

    lines = ["| scene | precision | recall >= 60 um | F1 | recall > 200 um | recall 60-100 um | 60-100 um pooled "
             "over the seeds (95 %) | median abs width err | false positives per capture |",
             "|---|---|---|---|---|---|---|---|---|"]
    for r in results["rows"]:
        lo, hi = r["false_positives"]
        fp = (f"{lo}" if lo == hi else f"{lo}-{hi}") + (f" ({r['fp_note']})" if r.get("fp_note") else "")
        p, plo, phi = r["pooled_60_100"]
        lines.append(f"| {r['scene']} | {r['precision']:.3f} | {r['recall']:.3f} | "
                     f"{cell(r, 'f1', format(r['f1'], '.3f'), True)} | "
                     f"{cell(r, 'recall_200', format(r['recall_200'], '.3f'), True)} | "
                     f"{cell(r, 'recall_60_100', format(r['recall_60_100'], '.3f'), True)} | "
                     f"{p:.3f} ({plo:.2f}-{phi:.2f}) | {cell(r, 'width_err', _pct(r['width_err']))} | {fp} |")
    return "\n".join(lines) + "\n"


def write_doc_section(results, scene: str, argv) -> Path:
    """``--doc``: this scene's row replaces the kept one (the other scenes' rows stay); the section is rewritten."""
    import json

    import benchdoc
    old = json.loads(benchdoc.json_path(DOC_SECTION, json_dir=benchdoc.JSON_DIR).read_text(encoding="utf-8"))
    row = doc_row(results, scene)
    rows = [row if r["scene"] == scene else r for r in old["rows"]]
    if row not in rows:
        rows.append(row)
    argvs = dict(old.get("argv_by_scene", {}), **{scene: list(argv)})
    doc = dict(old, rows=rows, argv_by_scene=argvs)
    return benchdoc.write_doc(DOC_SECTION, doc, render_doc(doc), source="scripts/benchmark_detection.py")


def _params(ap, items) -> dict:
    """``--param NAME=VALUE`` items as DetectionParams overrides (VALUE as the field's type)."""
    fields = DetectionParams.__dataclass_fields__
    out = {}
    for item in items:
        name, sep, value = item.partition("=")
        if not sep or name not in fields:
            ap.error(f"--param {item!r}: expected NAME=VALUE with NAME a DetectionParams field")
        try:
            out[name] = type(getattr(DetectionParams(), name))(value)
        except ValueError:
            ap.error(f"--param {item!r}: {value!r} is not a {type(getattr(DetectionParams(), name)).__name__}")
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    ap.add_argument("--shape", type=int, nargs=2, default=[1200, 1600], metavar=("ROWS", "COLS"))
    ap.add_argument("--scene", choices=sorted(SCENES), default="top",
                    help="top: every nuisance at the top of its range; impasto: that and real "
                         "impasto (uvps.testing.synthetic.IMPASTO); the others one impasto morphology")
    ap.add_argument("--height-noise", type=float, default=0.0,
                    help="white noise (um) added to the true height (truth mode only)")
    ap.add_argument("--shoulder-width-um", type=float, default=None,
                    help="DetectionParams.shoulder_width_um (the shoulder cue; 0 = off; with --pipeline, "
                         "then `uvps detect -o RUN --shoulder-width-um W`)")
    ap.add_argument("--misses", action="store_true",
                    help="(truth mode) why each missed 60-100 um protrusion was missed: the rule "
                         "that rejected the candidate at its centre, merged, or no candidate")
    ap.add_argument("--pipeline", action="store_true",
                    help="end to end through `uvps run CAPTURE -o RUN --detect --lights "
                         "CAPTURE/lights_positions_mm.csv --black-level B` on the written capture")
    ap.add_argument("--curl-k", type=float, default=None,
                    help="with --pipeline: then `uvps detect -o RUN --curl-k K` (DetectionParams.curl_k: the "
                         "detection's height without long non-integrable patches; 0 = off; default: the run's own)")
    ap.add_argument("--beside-long-fraction", type=float, default=None,
                    help="DetectionParams.beside_long_fraction (the exact level sets beside strokes; 0 = "
                         "off; with --pipeline, then `uvps detect -o RUN --beside-long-fraction F`)")
    ap.add_argument("--param", action="append", default=[], metavar="NAME=VALUE",
                    help="any other DetectionParams field, e.g. smooth_um=10 (repeatable; with --pipeline, "
                         "then `uvps detect -o RUN --NAME VALUE`)")
    ap.add_argument("--uncalibrated", action="store_true",
                    help="with --pipeline: leave out --lights and --black-level (both estimated "
                         "from the images)")
    ap.add_argument("--doc", action="store_true",
                    help="write this scene's row of docs/benchmarks.md's detection table (section detection) and "
                         "docs/benchmarks/detection.json (true maps, detector defaults only)")
    args = ap.parse_args(argv)
    # the named options are DetectionParams fields too: one dict of overrides for both modes
    named = {"shoulder_width_um": args.shoulder_width_um, "curl_k": args.curl_k,
             "beside_long_fraction": args.beside_long_fraction}
    args.params = {**{k: v for k, v in named.items() if v is not None}, **_params(ap, args.param)}
    if args.doc and (args.pipeline or args.params or args.height_noise):
        ap.error("--doc: the table is of the true maps with the detector's defaults (no --pipeline, "
                 "--height-noise or detector option)")
    if args.pipeline:
        mode = ("end to end (`uvps run CAPTURE -o RUN --detect`: lamps and black level estimated "
                "from the images)" if args.uncalibrated else "end to end (`uvps run CAPTURE -o RUN "
                "--detect --lights CAPTURE/lights_positions_mm.csv --black-level 500`: the lamp "
                "positions and the camera's black level given)")
    else:
        mode = f"true albedo, height and normals, height noise {args.height_noise} um"
    print(f"SyntheticSpec.realistic('top', **SCENES[{args.scene!r}]), {args.shape[0]} x {args.shape[1]} px at 15 um/px, "
          f"seeds {args.seeds}; {mode}; detect_protrusions defaults"
          + (f" but {args.params}" if args.params else "") + ".\n")
    results = [run_seed(s, args.shape, args) for s in args.seeds]
    print_tables(results, args)
    if args.doc:
        print("wrote", write_doc_section(results, args.scene, sys.argv[1:] if argv is None else argv))
    return 0


if __name__ == "__main__":
    sys.exit(main())
