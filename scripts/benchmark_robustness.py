#!/usr/bin/env python
"""Robustness benchmark: ``uvps run`` on synthetic captures that hold a real capture's nuisances.

What is measured is what users run: each capture is written to disk with
:func:`uvps.testing.synthetic.write_capture` and the ``run`` command (``uvps.commands.COMMANDS["run"]``, the
function behind ``uvps run``) is called in-process on its folder; the run folder's outputs are then
scored against the generator's truth. Nothing of the pipeline is assembled by hand.

Rows: ``none`` (no nuisance), every nuisance of :data:`uvps.testing.synthetic.NUISANCE_TOP` alone at the top of
its range, and ``all`` (:meth:`SyntheticSpec.realistic` with ``level="top"``). Each row is run for every
seed, lamp count and lights mode: ``estimated`` (no ``--lights``), ``calibrated`` (``--lights`` with a
positions CSV ``file,x_mm,y_mm,z_mm`` written from the truth), ``dark`` (lamps estimated, with
``--dark`` a frame taken with the lamp off: :func:`uvps.testing.synthetic.render_dark_frame`, the remedy the
run's warnings name for stray light) and ``card`` (the true positions, the dark frame, and ``--card`` a
flat fluorescent card under every lamp: :func:`uvps.testing.synthetic.render_card` with
:data:`uvps.testing.synthetic.CARD_TYPICAL`, tilted toward an azimuth that changes with the seed). With detection on (the default) the run
gets ``--regions`` with the true colour areas (``truth/regions.tif``).

Metrics per run:

- lights: angle (deg) between each lamp's direction in the run's ``lights.json`` and the true position /
  |position| (both from the image centre); mean and max over lamps. With beams on, the truth's
  ``intensities`` are on the beam axis, so only directions are scored.
- normals: mean angular error (deg) of ``normals.tif`` over its finite pixels.
- heights: median relative error (%) over protrusions >= 100 um wide of the disc/ring height measure of
  ``scripts/benchmark_core.py`` (``protrusion_errors``) on ``depth.tif`` vs the same measure on the truth.
- detection (runs with ``--regions`` only): matching and summary of ``scripts/benchmark_protrusions.py``
  on ``protrusions_labels.tif``: F1 for protrusions >= 60 um, recall >= 200 um, median width error (%)
  >= 60 um.
- the heights' reported expanded uncertainty (``run.json`` ``height_uncertainty_relative_95``, estimated
  lamps) and whether it covers the true height error (1/0; the coverage over runs is the last line), and
  whether the run's relief is relative (``run.json`` ``relief``).
- wall time of the command; the additive term measured by the run (``run.json`` diagnostics
  ``additive.mean_counts``) vs the truth's (black level + mean stray light, counts); the run's warnings.

The table has one line per (row, lamps, mode): the worst value over seeds (mean in brackets), cells that
miss their target marked **x**, then a "worst row" line. Every run's numbers are cached as JSON in the
workdir (``results/``) and skipped when present, so an interrupted benchmark resumes; all of them are
also gathered in ``<workdir>/robustness_results.json``.

    .venv/bin/python scripts/benchmark_robustness.py                                  # the whole benchmark (long)
    .venv/bin/python scripts/benchmark_robustness.py --shape 300 400 --seeds 0 --lights-counts 8 \\
        --rows none black_level --modes estimated                                     # a small trial

``--doc`` (12 lamps) merges this invocation's runs into ``docs/benchmarks/robustness.json`` (modes
estimated, calibrated, dark) or ``spheres.json`` (spheres, spheres_card, matte_spheres), a run replacing the
kept one of its row, mode and seed, and rewrites docs/benchmarks.md's "Robustness table, 12 lamps" (section
``robustness``: :func:`render_doc`) or "Calibration and spheres" table (section ``spheres``:
:func:`render_spheres_doc`) from it (scripts/benchdoc.py).
"""
from __future__ import annotations

import argparse
import json
import math
import os
import platform
import shlex
import shutil
import subprocess
import sys
import tempfile
import time
import traceback
from concurrent.futures import ProcessPoolExecutor, as_completed
from pathlib import Path

import numpy as np

SCRIPTS = Path(__file__).resolve().parent
ROOT = SCRIPTS.parent
if str(SCRIPTS) not in sys.path:
    sys.path.insert(0, str(SCRIPTS))

from benchmark_core import protrusion_errors  # noqa: E402  (the disc/ring height measure)
from benchmark_protrusions import match, summarise  # noqa: E402  (detection matching and summary)

from uvps.testing.synthetic import (CARD_TYPICAL, NUISANCE_TOP, SyntheticSpec, make_capture, render_card,  # noqa: E402
                            write_capture)

ROWS = ["none"] + list(NUISANCE_TOP) + ["bow", "all"]
#: Modes whose runs are given the lamps (``--lamp-beams`` applies to them; the card divides the beams out).
KNOWN_LAMP_MODES = ("calibrated", "spheres", "matte_spheres")
MODES = ("estimated", "calibrated", "dark", "card", "spheres", "matte_spheres", "spheres_card")
#: The ``bow`` row: a canvas bowed by this much across the field (real canvases: 100-250 um).
BOW_UM = 250.0
SCHEMA = 2
DOC_SECTION = "robustness"

#: Metric key -> (column header, target, "max" if lower is better / "min" if higher, format).
METRICS = {
    "light_mean_deg": ("lights mean (deg, <= 1)", 1.0, "max", "{:.2f}"),
    "light_max_deg": ("lights max (deg)", None, "max", "{:.2f}"),
    "normals_mean_deg": ("normals (deg, <= 0.5)", 0.5, "max", "{:.3f}"),
    "height_median_pct": ("heights (%, <= 5)", 5.0, "max", "{:.1f}"),
    "f1_60": ("F1 >= 60 um (>= 0.93)", 0.93, "min", "{:.3f}"),
    "recall_200": ("recall >= 200 um (>= 0.97)", 0.97, "min", "{:.3f}"),
    "width_err_pct": ("widths (%, <= 10)", 10.0, "max", "{:.1f}"),
    "height_unc95_pct": ("reported height unc. (%, 95 %)", None, "min", "{:.1f}"),
    "unc_covers": ("unc. covers height err (>= 90 % of runs)", None, "min", "{:.0f}"),
    "relative": ("relief relative (1/0)", None, "max", "{:.0f}"),
    "cal_light_max_deg": ("calibration lamps max (deg, <= 0.5)", 0.5, "max", "{:.2f}"),
    "cal_position_max_pct": ("calibration positions max (%, <= 5)", 5.0, "max", "{:.1f}"),
    "additive_err_counts": ("additive err (counts)", None, "max", "{:.0f}"),
    "wall_s": ("wall (s)", None, "max", "{:.1f}"),
    "n_warnings": ("warnings (n)", None, "max", "{:.0f}"),
}


# --------------------------------------------------------------------------------------------
# one run
# --------------------------------------------------------------------------------------------

def spec_for(row, *, shape, pixel_size_um, seed, n_lights):
    """The synthetic spec of a row: no nuisance, one at the top of its range, or all of them."""
    common = dict(shape=tuple(shape), pixel_size_um=float(pixel_size_um), seed=int(seed), n_lights=int(n_lights))
    if row == "none":
        return SyntheticSpec(**common)
    if row == "all":
        return SyntheticSpec.realistic(level="top", **common)
    if row == "bow":
        return SyntheticSpec(bow_um=BOW_UM, **common)
    if row not in NUISANCE_TOP:
        raise ValueError(f"unknown row {row!r}; expected some of {ROWS}")
    return SyntheticSpec.realistic(level="top", only=[row], **common)


def _angle_deg(a, b):
    a = np.asarray(a, np.float64)
    b = np.asarray(b, np.float64)
    c = np.einsum("...i,...i->...", a, b) / (np.linalg.norm(a, axis=-1) * np.linalg.norm(b, axis=-1))
    return np.degrees(np.arccos(np.clip(c, -1.0, 1.0)))


def truth_additive(cap):
    """The truth's additive term per channel (counts): black level + mean stray light."""
    info = cap.nuisances.info
    channels = 3 if cap.images.ndim == 4 else 1
    total = np.zeros(channels)
    if "black_level_counts" in info:
        total = total + np.asarray(info["black_level_counts"], float)
    stray = info.get("stray_light", {}).get("mean_counts")
    if stray is not None:
        total = total + np.asarray(stray, float)
    return total


def score_run(run_dir: Path, cap, *, detect: bool) -> dict:
    """Every metric of one run folder against the capture's truth."""
    import tifffile
    from skimage.measure import regionprops_table

    out = {}
    px = float(cap.spec.pixel_size_um)
    # lights: direction from the image centre, matched by file name
    lj = json.loads((run_dir / "lights.json").read_text())
    names = [f"uv_{i:0{max(2, len(str(len(cap.light_positions_mm) - 1)))}d}.tif"
             for i in range(len(cap.light_positions_mm))]
    truth_dir = {n: p / np.linalg.norm(p) for n, p in zip(names, cap.light_positions_mm)}
    errs = []
    for lamp in lj["lights"]:
        name = Path(str(lamp.get("file", ""))).name.split("#")[0]
        d = lamp.get("direction")
        if name in truth_dir and d is not None:
            errs.append(float(_angle_deg(d, truth_dir[name])))
    errs = np.asarray(errs)
    out["light_errors_deg"] = errs.tolist()
    out["light_mean_deg"] = float(errs.mean()) if errs.size == len(names) else float("nan")
    out["light_max_deg"] = float(errs.max()) if errs.size == len(names) else float("nan")
    out["lights_mode"] = lj.get("mode")
    out["m_mm"] = lj.get("m_mm")
    # normals
    nrm = np.moveaxis(tifffile.imread(run_dir / "normals.tif"), 0, -1)
    ang = _angle_deg(nrm, cap.normals)
    ok = np.isfinite(ang)
    out["normals_nan_px"] = int((~ok).sum())
    out["normals_mean_deg"] = float(ang[ok].mean()) if ok.any() else float("nan")
    out["normals_median_deg"] = float(np.median(ang[ok])) if ok.any() else float("nan")
    out["normals_p95_deg"] = float(np.percentile(ang[ok], 95)) if ok.any() else float("nan")
    # protrusion heights (>= 100 um wide), disc/ring measure vs the same on the truth
    depth = tifffile.imread(run_dir / "depth.tif").astype(np.float64)
    pe = protrusion_errors(depth, cap.height_um, cap.protrusions, px)
    out["height_n"] = pe["n"]
    out["height_median_pct"] = float(np.median(pe["rel_vs_measure"]) * 100) if pe["n"] else None
    out["height_vs_recorded_pct"] = float(np.median(pe["rel_vs_recorded"]) * 100) if pe["n"] else None
    # detection (only when the run had --regions)
    labels_path = run_dir / "protrusions_labels.tif"
    if detect and labels_path.exists():
        labels = np.asarray(tifffile.imread(labels_path)).squeeze().astype(np.int64)
        props = regionprops_table(labels, properties=("label", "centroid", "area"))
        det_xy = np.column_stack([props["centroid-1"], props["centroid-0"]]).reshape(-1, 2)
        det_w = np.sqrt(4 * np.asarray(props["area"], float) / np.pi) * px
        pr = cap.protrusions
        true_xy = np.column_stack([pr["x_px"], pr["y_px"]]).astype(float)
        t2d, d2t = match(true_xy, pr["width_um"] / px, det_xy)
        with np.errstate(divide="ignore", invalid="ignore"):
            rows = summarise([dict(true_w=pr["width_um"], weak=pr["weak"], t2d=t2d, d2t=d2t, det_w=det_w)])
        by = {r[0]: r for r in rows}
        a60, a200 = by["all >= 60 um"], by["all >= 200 um"]
        out["n_true_60"], out["n_detected_60"] = int(a60[1]), int(a60[2])
        out["precision_60"], out["recall_60"] = _or_none(a60[3]), _or_none(a60[4])
        out["f1_60"] = _or_none(a60[5]) if a60[1] else None      # None: nothing to find (not a miss)
        out["n_true_200"] = int(a200[1])
        out["recall_200"] = _or_none(a200[4]) if a200[1] else None
        out["width_err_pct"] = _or_none(a60[7] * 100)            # None: nothing matched
        out["width_bias_pct"] = _or_none(a60[8] * 100)
        out["n_detected"] = int(labels.max()) if labels.size else 0
    # run.json: additive term, warnings, timings
    rj = json.loads((run_dir / "run.json").read_text())
    diag = rj.get("diagnostics", {})
    add = diag.get("additive")
    truth_add = truth_additive(cap)
    out["additive_truth_counts"] = truth_add.tolist()
    if isinstance(add, dict) and add.get("mean_counts") is not None:
        meas = np.asarray(add["mean_counts"], float)
        out["additive_counts"] = meas.tolist()
        out["additive_source"] = add.get("source")
        out["additive_stderr_counts"] = add.get("stderr_counts")
        if add.get("source") == "dark frame":
            pass                         # nothing measured: the dark frame was subtracted on reading
        elif meas.size == truth_add.size or meas.size == 1 or truth_add.size == 1:
            out["additive_err_counts"] = float(np.abs(meas.mean() - truth_add.mean()))
    out["warnings"] = list(rj.get("warnings", []))
    out["n_warnings"] = len(out["warnings"])
    out["timings_s"] = rj.get("timings_s", {})
    lights_diag = diag.get("lights", {})
    out["refinement_converged"] = lights_diag.get("refinement_converged")
    # the heights' reported expanded uncertainty against their true error (estimated lamps only)
    unc = lights_diag.get("height_uncertainty_relative_95")
    if unc is not None and out.get("height_median_pct") is not None:
        out["height_unc95_pct"] = 100.0 * float(unc)
        out["unc_covers"] = float(out["height_unc95_pct"] >= out["height_median_pct"])
    out["relative"] = float((rj.get("relief") or {}).get("scale") == "relative")
    return out


def _or_none(v):
    """A finite float, or None (a metric with no sample: not applicable, not a miss)."""
    v = float(v)
    return v if math.isfinite(v) else None


def write_positions_csv(cap, path: Path):
    """The truth's lamp positions as ``file,x_mm,y_mm,z_mm`` (the calibrated mode's --lights)."""
    k = len(cap.light_positions_mm)
    digits = max(2, len(str(k - 1)))
    lines = ["file,x_mm,y_mm,z_mm"]
    for i, p in enumerate(cap.light_positions_mm):
        lines.append(f"uv_{i:0{digits}d}.tif," + ",".join(f"{v:.6f}" for v in p))
    path.write_text("\n".join(lines) + "\n", encoding="utf-8")


#: Sphere routes: the spheres of the calibration capture (kind, centre as fractions of the frame, radius mm).
SPHERE_MODES = {
    "spheres": [("glossy", (0.13, 0.17), 2.5), ("glossy", (0.87, 0.83), 2.5)],
    "matte_spheres": [("matte", (0.13, 0.17), 2.5), ("matte", (0.87, 0.83), 2.5)],
    # the glossy spheres, and the card under every lamp stored in the calibration (uvps calibrate --card)
    "spheres_card": [("glossy", (0.13, 0.17), 2.5), ("glossy", (0.87, 0.83), 2.5)],
}


def _has_additive(cap) -> bool:
    """The capture holds a black level or stray light: a conservator's calibration takes a dark frame."""
    nz = cap.nuisances
    return nz.black_level is not None or nz.stray_light is not None


def calibrate_from_spheres(cap, sphere_dir: Path, cal_dir: Path, spheres, *, dark=None, card=None) -> dict:
    """Render the sphere capture of ``cap``'s lamps, run ``uvps calibrate`` on it (spheres detected), and
    score the calibration's lamps against the truth: max direction error (deg) and max position error
    (% of the lamp's distance)."""
    from uvps.commands import COMMANDS
    from uvps.testing.synthetic_spheres import SphereSpec, make_sphere_capture, write_sphere_capture

    sc = make_sphere_capture(cap, [SphereSpec(*s) for s in spheres])
    shutil.rmtree(sphere_dir, ignore_errors=True)
    write_sphere_capture(sc, sphere_dir, truth=False)
    shutil.rmtree(cal_dir, ignore_errors=True)
    t0 = time.perf_counter()
    inputs = {"spheres": [str(sphere_dir)]}
    if dark is not None:
        # the sphere capture's own dark frame (another exposure than the painting's); the run is given the
        # painting's (--dark), as a conservator who took the two at two exposures does. With a card (taken at
        # the painting's exposure) the painting's: calibrate subtracts one dark frame from both, and a glossy
        # sphere's highlight does not see the smooth remainder
        own = sphere_dir / "dark" / "dark.tif"
        inputs["dark"] = str(own if own.is_file() and card is None else dark)
    if card is not None:
        inputs["card"] = str(card)
    COMMANDS["calibrate"](inputs, {"pixel_size_um": float(cap.spec.pixel_size_um)}, cal_dir)
    out = {"calibrate_s": time.perf_counter() - t0}
    lj = json.loads((cal_dir / "lights.json").read_text())
    L = cap.light_positions_mm
    D = np.array([lp["direction"] for lp in lj["lights"]])
    out["cal_light_errors_deg"] = _angle_deg(D, L).tolist()
    out["cal_light_max_deg"] = float(np.max(out["cal_light_errors_deg"]))
    P = [lp.get("position_mm") for lp in lj["lights"]]
    if all(p is not None for p in P):
        err = np.linalg.norm(np.array(P) - L, axis=1) / np.linalg.norm(L, axis=1) * 100
        out["cal_position_errors_pct"] = err.tolist()
        out["cal_position_max_pct"] = float(err.max())
    shutil.rmtree(sphere_dir, ignore_errors=True)
    return out


def result_path(workdir: Path, row, seed, lamps, mode) -> Path:
    return workdir / "results" / f"{row}__seed{seed}__k{lamps}__{mode}.json"


def _config(args_like) -> dict:
    out = {"shape": list(args_like["shape"]), "pixel_size_um": float(args_like["pixel_size_um"]),
           "detect": bool(args_like["detect"])}
    if args_like.get("lamp_beams"):
        out["lamp_beams"] = args_like["lamp_beams"]
    return out


def load_cached(path: Path, config: dict, retry_failed=False):
    if not path.exists():
        return None
    try:
        r = json.loads(path.read_text())
    except (OSError, ValueError):
        return None
    if r.get("schema") != SCHEMA or r.get("config") != config:
        return None
    if retry_failed and r.get("error"):
        return None
    return r


def _json_default(o):
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, np.generic):
        return o.item()
    if isinstance(o, Path):
        return str(o)
    raise TypeError(f"not JSON serialisable: {type(o).__name__}")


def _write_json(path: Path, obj):
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(".json.tmp")
    tmp.write_text(json.dumps(obj, indent=1, default=_json_default), encoding="utf-8")
    os.replace(tmp, path)


def run_group(row, seed, lamps, modes, workdir, config, *, keep=False, retry_failed=False, code=None):
    """One capture (row, seed, lamps), every mode not yet cached; returns the mode results."""
    from uvps.commands import COMMANDS

    workdir = Path(workdir)
    todo = [m for m in modes
            if load_cached(result_path(workdir, row, seed, lamps, m), config, retry_failed) is None]
    results = {m: load_cached(result_path(workdir, row, seed, lamps, m), config) for m in modes if m not in todo}
    if not todo:
        return results
    key = f"{row}__seed{seed}__k{lamps}"
    cap_dir = workdir / "captures" / key
    run_root = workdir / "runs"
    run_root.mkdir(parents=True, exist_ok=True)
    shutil.rmtree(cap_dir, ignore_errors=True)
    cap_dir.parent.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    spec = spec_for(row, shape=config["shape"], pixel_size_um=config["pixel_size_um"], seed=seed, n_lights=lamps)
    cap = make_capture(spec)
    t_make = time.perf_counter() - t0
    card = None
    if "card" in todo or "spheres_card" in todo:
        card = render_card(cap, tilt_azimuth_deg=(137.5 * seed) % 360.0, **CARD_TYPICAL)
    cap_has_dark = ("dark" in todo or "card" in todo or "spheres_card" in todo
                    or (any(m in SPHERE_MODES for m in todo) and _has_additive(cap)))
    write_capture(cap, cap_dir, dark_frame=cap_has_dark, card=card)
    dark_path = cap_dir / "dark" / "dark.tif"
    lights_csv = workdir / "captures" / f"{key}__lights_truth.csv"
    write_positions_csv(cap, lights_csv)
    regions_tif = cap_dir / "truth" / "regions.tif"
    try:
        for mode in todo:
            run_dir = run_root / f"{key}__{mode}"
            shutil.rmtree(run_dir, ignore_errors=True)
            params = {}
            argv = ["uvps", "run", str(cap_dir), "-o", str(run_dir)]
            if mode in ("calibrated", "card"):
                params["lights"] = str(lights_csv)
                argv += ["--lights", str(lights_csv)]
            if mode in ("dark", "card"):
                params["dark"] = str(cap_dir / "dark" / "dark.tif")
                argv += ["--dark", params["dark"]]
            if mode == "card":
                params["card"] = str(cap_dir / "card")
                argv += ["--card", params["card"]]
            cal_score = {}
            if mode in SPHERE_MODES:
                # the lamps from a sphere capture under the same lamps (uvps calibrate), then the run
                cal_dir = run_root / f"{key}__{mode}__cal"
                try:
                    cal_score = calibrate_from_spheres(cap, workdir / "captures" / f"{key}__{mode}", cal_dir,
                                                       SPHERE_MODES[mode], dark=dark_path if cap_has_dark else None,
                                                       card=cap_dir / "card" if mode == "spheres_card" else None)
                    params["calibration"] = str(cal_dir)
                    argv += ["--calibration", str(cal_dir)]
                    if cap_has_dark:
                        params["dark"] = str(dark_path)
                        argv += ["--dark", params["dark"]]
                except Exception as exc:  # reported as the run's failure below
                    cal_score = {"calibrate_error": f"{type(exc).__name__}: {exc}".splitlines()[0][:300]}
            if config.get("lamp_beams") and mode in KNOWN_LAMP_MODES:
                params["lamp_beams"] = config["lamp_beams"]
                argv += ["--lamp-beams", config["lamp_beams"]]
            if config["detect"]:
                params["regions"] = str(regions_tif)
                argv += ["--regions", str(regions_tif)]
            res = {"schema": SCHEMA, "config": config, "row": row, "seed": seed, "lamps": lamps, "mode": mode,
                   "command": " ".join(shlex.quote(a) for a in argv), "make_capture_s": t_make,
                   "truth_nuisances": cap.nuisances.info, "code": code}
            res.update(cal_score)
            t1 = time.perf_counter()
            try:
                if "calibrate_error" in cal_score:
                    raise RuntimeError(cal_score["calibrate_error"])
                COMMANDS["run"]({"images": [str(cap_dir)]}, params, run_dir)
                res["wall_s"] = time.perf_counter() - t1
                res.update(score_run(run_dir, cap, detect=config["detect"]))
                res["error"] = None
            except Exception as exc:  # a benchmark reports failures, it does not stop on them
                res["wall_s"] = time.perf_counter() - t1
                res["error"] = f"{type(exc).__name__}: {exc}".splitlines()[0][:300]
                res["traceback"] = traceback.format_exc()[-3000:]
            _write_json(result_path(workdir, row, seed, lamps, mode), res)
            results[mode] = res
            if not keep:
                shutil.rmtree(run_dir, ignore_errors=True)
                shutil.rmtree(run_root / f"{key}__{mode}__cal", ignore_errors=True)
    finally:
        if not keep:
            shutil.rmtree(cap_dir, ignore_errors=True)
            lights_csv.unlink(missing_ok=True)
    return results


# --------------------------------------------------------------------------------------------
# table
# --------------------------------------------------------------------------------------------

def _misses(key, value):
    _, target, sense, _ = METRICS[key]
    if target is None or value is None:
        return False
    if not math.isfinite(value):
        return True                      # a failed run or NaN misses every target
    return value > target if sense == "max" else value < target


def aggregate(results: list, key: str):
    """Worst over seeds and mean; None when no run has the metric; NaN/failed counts as worst."""
    _, _, sense, _ = METRICS[key]
    vals = []
    for r in results:
        if r.get("error"):
            vals.append(float("nan"))
        elif key in r and r[key] is not None:
            vals.append(float(r[key]))
    if not vals:
        return None, None
    arr = np.asarray(vals)
    if not np.isfinite(arr).all():
        worst = float("nan")
    else:
        worst = float(arr.max() if sense == "max" else arr.min())
    fin = arr[np.isfinite(arr)]
    mean = float(fin.mean()) if fin.size else float("nan")
    return worst, mean


def _fmt(key, v):
    if v is None:
        return "-"
    if not math.isfinite(v):
        return "nan"
    return METRICS[key][3].format(v)


def _first_words(w, n=4):
    return " ".join(str(w).split()[:n])


def build_table(all_results: list, rows, lamps_list, modes):
    header = ["row", "lamps", "lights"]
    for k in METRICS:
        header.append(METRICS[k][0])
        if k == "additive_err_counts":
            header.append("truth additive (counts)")
    header += ["warnings (first words)", "failed"]
    lines = []
    worst_per_metric = {}
    for row in rows:
        for lamps in lamps_list:
            for mode in modes:
                rs = [r for r in all_results if r["row"] == row and r["lamps"] == lamps and r["mode"] == mode]
                if not rs:
                    continue
                cells = [row, str(lamps), mode]
                for key in METRICS:
                    worst, mean = aggregate(rs, key)
                    if key == "additive_err_counts":
                        ta = [np.mean(r["additive_truth_counts"]) for r in rs if r.get("additive_truth_counts")]
                        truth_cell = f"{np.mean(ta):.0f}" if ta else "-"
                    if worst is None:
                        cells.append("-")
                        if key == "additive_err_counts":
                            cells.append(truth_cell)
                        continue
                    cell = f"{_fmt(key, worst)} ({_fmt(key, mean)})"
                    if _misses(key, worst):
                        cell += " **x**"
                    cells.append(cell)
                    if key == "additive_err_counts":
                        cells.append(truth_cell)
                    sense = METRICS[key][2]
                    prev = worst_per_metric.get(key)
                    label = f"{row}, {lamps} lamps, {mode}"
                    if prev is None or _worse(worst, prev[0], sense):
                        worst_per_metric[key] = (worst, label)
                words = sorted({_first_words(w) for r in rs for w in r.get("warnings", [])})
                cells.append("; ".join(words).replace("|", "/") or "-")
                failed = [f"seed {r['seed']}: {r['error']}" for r in rs if r.get("error")]
                cells.append("; ".join(failed).replace("|", "/")[:200] or "-")
                lines.append(cells)
    worst_cells = ["**worst row**", "", ""]
    for key in METRICS:
        if key in worst_per_metric:
            v, label = worst_per_metric[key]
            cell = f"{_fmt(key, v)} ({label})"
            if _misses(key, v):
                cell += " **x**"
            worst_cells.append(cell)
        else:
            worst_cells.append("-")
        if key == "additive_err_counts":
            worst_cells.append("")
    worst_cells += ["", ""]
    lines.append(worst_cells)
    out = ["| " + " | ".join(header) + " |", "|" + "|".join("---" for _ in header) + "|"]
    out += ["| " + " | ".join(c) + " |" for c in lines]
    worst_lines = []
    for key in METRICS:
        if key in worst_per_metric:
            v, label = worst_per_metric[key]
            worst_lines.append(f"- worst row, {METRICS[key][0]}: {_fmt(key, v)} in {label}"
                               + (" **x**" if _misses(key, v) else ""))
    return "\n".join(out), worst_lines


def coverage_line(results) -> str:
    """How many runs' reported height uncertainty (95 %) covers their true height error."""
    cov = [r["unc_covers"] for r in results if not r.get("error") and r.get("unc_covers") is not None]
    failed = sum(1 for r in results if r.get("error") and r.get("mode") != "calibrated")
    if not cov:
        return "- coverage of the reported height uncertainty: no run with estimated lamps"
    return (f"- coverage of the reported height uncertainty (95 %): {int(sum(cov))} of {len(cov)} runs with "
            f"estimated lamps ({100 * sum(cov) / len(cov):.0f} %; target >= 90 %); {failed} run(s) stopped "
            "(no heights written)")


def _worse(a, b, sense):
    if not math.isfinite(a):
        return math.isfinite(b)
    if not math.isfinite(b):
        return False
    return a > b if sense == "max" else a < b


# --------------------------------------------------------------------------------------------
# docs/benchmarks.md's table (section "robustness")
# --------------------------------------------------------------------------------------------

#: The metrics a run keeps in docs/benchmarks/robustness.json (estimated lamps; calibrated runs keep the first three).
DOC_KEYS = ("normals_mean_deg", "height_median_pct", "light_mean_deg", "height_unc95_pct", "unc_covers", "relative")
#: Modes the doc's table shows: its per-seed columns (estimated), its last column (calibrated), a summary row (dark).
DOC_MODES = ("estimated", "calibrated", "dark")


def _x(missed: bool) -> str:
    return " **x**" if missed else ""


def _normals(v) -> str:
    """Normals' error with 3 significant digits (0.231, 1.92, 8.86)."""
    return f"{v:#.3g}"


def _doc_seeds(runs, key, fmt, *, stop=False):
    """A per-seed cell, ``a / b / c``; a stopped run reads ``stop`` (with its reason on the first one if asked)."""
    cells, said = [], False
    for r in runs:
        if r.get("error"):
            reason = r.get("stop") or _first_words(r["error"].split(":", 1)[-1])
            cells.append(f'stop ({reason})' if stop and not said else "stop")
            said = True
        else:
            cells.append(fmt.format(r[key]))
    return " / ".join(cells)


def _doc_worst(runs, key):
    vals = [r[key] for r in runs if not r.get("error")]
    return max(vals) if vals else None


def _doc_row(entry, runs) -> str:
    row, mode = entry["row"], entry.get("mode", "estimated")
    label = entry.get("label", row)
    mine = sorted((r for r in runs if r["row"] == row and r["mode"] == mode), key=lambda r: r["seed"])
    if mode != "estimated":            # a summary row: the worst seed (the mean in brackets), three columns
        if mine:
            ok = [r for r in mine if not r.get("error")]
            light = (max(r["light_mean_deg"] for r in ok), float(np.mean([r["light_mean_deg"] for r in ok])))
            normals, heights = _doc_worst(mine, "normals_mean_deg"), _doc_worst(mine, "height_median_pct")
        else:                          # kept as the table quoted it (its runs are not in the JSON)
            light = tuple(entry["summary"]["light_mean_deg"])
            normals, heights = entry["summary"]["normals_mean_deg"], entry["summary"]["height_median_pct"]
        return (f"| {label} | {light[0]:.2f} (mean {light[1]:.2f}){_x(_misses('light_mean_deg', light[0]))} | "
                f"{_normals(normals)}{_x(_misses('normals_mean_deg', normals))} | "
                f"{heights:.1f}{_x(_misses('height_median_pct', heights))} | | | | |")
    ok = [r for r in mine if not r.get("error")]
    stopped = len(ok) < len(mine)
    light_x = stopped or any(_misses("light_mean_deg", r["light_mean_deg"]) for r in ok)
    heights_x = stopped or any(_misses("height_median_pct", r["height_median_pct"]) for r in ok)
    normals = _doc_worst(mine, "normals_mean_deg")
    cal = [r for r in runs if r["row"] == row and r["mode"] == "calibrated"]
    cal_n, cal_h = _doc_worst(cal, "normals_mean_deg"), _doc_worst(cal, "height_median_pct")
    cal_cell = (f"{_normals(cal_n)}{_x(_misses('normals_mean_deg', cal_n))} / {cal_h:.1f}" if cal else "-")
    return (f"| {label} | {_doc_seeds(mine, 'light_mean_deg', '{:.2f}', stop=True)}{_x(light_x)} | "
            f"{_normals(normals)}{_x(_misses('normals_mean_deg', normals))} | "
            f"{_doc_seeds(mine, 'height_median_pct', '{:.1f}')}{_x(heights_x)} | "
            f"{_doc_seeds(mine, 'height_unc95_pct', '{:.0f}')} | "
            f"{sum(int(r['unc_covers']) for r in ok)} of {len(ok)} | "
            f"{sum(int(r['relative']) for r in ok)} of {len(ok)} | {cal_cell} |")


def render_doc(results: dict) -> str:
    """docs/benchmarks.md's "Robustness table, 12 lamps": one line per entry of ``results["rows"]``.

    Estimated lamps per seed (lights' mean error, heights' error, the reported uncertainty), the worst
    seed's normals, how many runs' reported uncertainty covers their error and how many are relative;
    the calibrated runs' worst normals / heights; a row of another mode (``dark``) gives the worst seed
    (the mean in brackets). **x**: a cell misses its target of :data:`METRICS` (a stopped run misses).

    Parameters
    ----------
    results : dict
        ``{"rows": [{"row", "label", "mode"?, "summary"?}], "runs": [{"row", "mode", "seed", metrics...
        or "error" (+ "stop": its reason as the table words it)}]}`` as docs/benchmarks/robustness.json keeps it.
    """
    lines = ["| row | lights (deg, <= 1), seeds 0 / 1 / 2 | normals (deg, <= 0.5) | heights off (%, <= 5) | "
             "reported (%, 95 %) | covered | relative | calibrated: normals (deg) / heights (%) |",
             "|---|---|---|---|---|---|---|---|"]
    lines += [_doc_row(e, results["runs"]) for e in results["rows"]]
    return "\n".join(lines) + "\n"


SPHERE_DOC_MODES = ("spheres", "spheres_card", "matte_spheres")
#: Per sphere run: lamps max (deg), positions max (%), normals (deg), heights (%); the cell's formats.
SPHERE_KEYS = {"cal_light_max_deg": "{:.2f}", "cal_position_max_pct": "{:.1f}", "normals_mean_deg": "{:.3f}",
               "height_median_pct": "{:.2f}"}


def render_spheres_doc(results: dict) -> str:
    """docs/benchmarks.md's "Calibration and spheres" table: per row and sphere mode, the worst of the seeds'
    lamps max (deg) / positions max (%) / normals (deg) / heights (%); ``-`` where the mode was not run,
    **x** after a cell one of whose values misses its target of :data:`METRICS` (a failed run misses).

    Parameters
    ----------
    results : dict
        ``{"rows": [{"row", "label"}], "runs": [{"row", "mode", "seed", metrics... or "error"}]}`` as
        docs/benchmarks/spheres.json keeps it.
    """
    lines = ["| row | glossy spheres | glossy spheres + card | matte spheres |", "|---|---|---|---|"]
    for e in results["rows"]:
        cells = []
        for mode in SPHERE_DOC_MODES:
            rs = [r for r in results["runs"] if r["row"] == e["row"] and r["mode"] == mode]
            if not rs:
                cells.append("-")
                continue
            if any(r.get("error") for r in rs):
                cells.append("failed **x**")
                continue
            worst = {k: max(r[k] for r in rs) for k in SPHERE_KEYS}
            cells.append(" / ".join(f.format(worst[k]) for k, f in SPHERE_KEYS.items())
                         + _x(any(_misses(k, v) for k, v in worst.items())))
        lines.append(f"| {e.get('label', e['row'])} | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


#: Section name -> renderer (scripts/benchmark_docs.py).
DOC_SECTIONS = {DOC_SECTION: render_doc, "spheres": render_spheres_doc}


def write_doc_section(collected: list, argv: list) -> list:
    """``--doc``: merge the runs with 12 lamps into the kept JSON of their section (docs/benchmarks/robustness.json:
    estimated, calibrated, dark; spheres.json: spheres, spheres_card, matte_spheres), a run replacing the kept one
    of its row, mode and seed; rewrite each section concerned from its JSON. Returns the JSONs written."""
    import benchdoc
    written = []
    for section, modes in ((DOC_SECTION, DOC_MODES), ("spheres", SPHERE_DOC_MODES)):
        new = {}
        for r in collected:
            if r["lamps"] != 12 or r["mode"] not in modes:
                continue
            keep = {"row": r["row"], "mode": r["mode"], "seed": r["seed"]}
            if r.get("error"):
                keep["error"] = r["error"]
            elif section == "spheres":
                keep.update({k: r[k] for k in SPHERE_KEYS})
            else:
                keep.update({k: r[k] for k in (DOC_KEYS if r["mode"] != "calibrated" else DOC_KEYS[:2])})
            new[(r["row"], r["mode"], r["seed"])] = keep
        if not new:
            continue
        old = json.loads(benchdoc.json_path(section, json_dir=benchdoc.JSON_DIR).read_text(encoding="utf-8"))
        runs = [r for r in old["runs"] if (r["row"], r["mode"], r["seed"]) not in new] + list(new.values())
        runs.sort(key=lambda r: (r["row"], r["mode"], r["seed"]))
        doc = dict(old, runs=runs, commands=sorted(set(old.get("commands", [])) | {command_line(argv)}))
        written.append(benchdoc.write_doc(section, doc, DOC_SECTIONS[section](doc),
                                          source="scripts/benchmark_robustness.py"))
    if not written:
        raise SystemExit("benchmark_robustness.py: --doc needs runs with 12 lamps in mode "
                         + ", ".join(DOC_MODES + SPHERE_DOC_MODES))
    return written


# --------------------------------------------------------------------------------------------
# machine and command line
# --------------------------------------------------------------------------------------------

def machine_line():
    cpu = platform.processor() or "unknown CPU"
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    ram = "unknown RAM"
    try:
        for line in Path("/proc/meminfo").read_text().splitlines():
            if line.startswith("MemTotal"):
                ram = f"{int(line.split()[1]) / 2 ** 20:.1f} GiB RAM"
                break
    except OSError:
        pass
    try:
        nproc = subprocess.run(["nproc"], capture_output=True, text=True, check=True).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        nproc = str(os.cpu_count())
    l1, l5, l15 = os.getloadavg()
    return f"nproc {nproc}, {cpu}, {ram}; load average {l1:.2f} / {l5:.2f} / {l15:.2f} at the end"


def code_version():
    try:
        head = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=ROOT, capture_output=True, text=True,
                              check=True).stdout.strip()
        dirty = subprocess.run(["git", "status", "--porcelain", "--", "cpython_core"], cwd=ROOT,
                               capture_output=True, text=True, check=True).stdout.strip()
        return head + (" (core with uncommitted changes)" if dirty else "")
    except (OSError, subprocess.CalledProcessError):
        return "unknown"


def command_line(argv):
    return " ".join(shlex.quote(a) for a in [".venv/bin/python", "scripts/benchmark_robustness.py"] + list(argv))


# --------------------------------------------------------------------------------------------

def parse_args(argv):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--shape", type=int, nargs=2, default=[1200, 1600], metavar=("ROWS", "COLS"),
                    help="capture size in pixels (default 1200 1600: 24 x 18 mm at 15 um)")
    ap.add_argument("--pixel-size-um", type=float, default=15.0)
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    ap.add_argument("--lights-counts", type=int, nargs="+", default=[8, 12, 16])
    ap.add_argument("--rows", nargs="+", default=ROWS, choices=ROWS, metavar="ROW",
                    help=f"subset of {', '.join(ROWS)}")
    ap.add_argument("--modes", nargs="+", default=list(MODES), choices=MODES)
    ap.add_argument("--workdir", default=None,
                    help="captures, run folders and cached results (default: $TMPDIR/uvps_robustness_ROWSxCOLS)")
    ap.add_argument("--jobs", type=int, default=1, help="captures processed in parallel (processes)")
    ap.add_argument("--keep", action="store_true", help="keep the captures and run folders")
    ap.add_argument("--no-detect", action="store_true",
                    help="run without --regions (no detection metrics; faster)")
    ap.add_argument("--lamp-beams", choices=("auto", "all", "none"), default=None,
                    help="runs with known lamps (calibrated, spheres, matte_spheres): uvps run --lamp-beams (default: "
                         "the run's own default)")
    ap.add_argument("--retry-failed", action="store_true", help="re-run cached runs that failed")
    ap.add_argument("--doc", action="store_true",
                    help="merge the runs with 12 lamps into docs/benchmarks/robustness.json (estimated, calibrated, dark) "
                         "or spheres.json (the sphere modes) and rewrite docs/benchmarks.md's section from it")
    return ap.parse_args(argv)


def main(argv=None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    args = parse_args(argv)
    M, N = args.shape
    workdir = Path(args.workdir) if args.workdir else Path(tempfile.gettempdir()) / f"uvps_robustness_{M}x{N}"
    workdir.mkdir(parents=True, exist_ok=True)
    config = _config({"shape": args.shape, "pixel_size_um": args.pixel_size_um, "detect": not args.no_detect,
                      "lamp_beams": args.lamp_beams})
    code = code_version()
    groups = [(row, seed, lamps) for row in args.rows for lamps in args.lights_counts for seed in args.seeds]
    t_start = time.perf_counter()
    collected = []
    kw = dict(keep=args.keep, retry_failed=args.retry_failed, code=code)
    if args.jobs <= 1:
        for i, (row, seed, lamps) in enumerate(groups):
            res = run_group(row, seed, lamps, args.modes, workdir, config, **kw)
            collected += list(res.values())
            _progress(i + 1, len(groups), row, seed, lamps, res, t_start)
    else:
        with ProcessPoolExecutor(max_workers=args.jobs) as pool:
            futs = {pool.submit(run_group, row, seed, lamps, args.modes, str(workdir), config, **kw): (row, seed, lamps)
                    for row, seed, lamps in groups}
            for i, fut in enumerate(as_completed(futs)):
                res = fut.result()
                collected += list(res.values())
                _progress(i + 1, len(groups), *futs[fut], res, t_start)
    collected.sort(key=lambda r: (ROWS.index(r["row"]), r["lamps"], MODES.index(r["mode"]), r["seed"]))
    _write_json(workdir / "robustness_results.json", {
        "schema": SCHEMA, "command": command_line(argv), "config": config, "code": code,
        "date_utc": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()), "machine": machine_line(),
        "targets": {k: METRICS[k][1] for k in METRICS if METRICS[k][1] is not None},
        "results": collected})
    table, worst = build_table(collected, args.rows, args.lights_counts, args.modes)
    worst.append(coverage_line(collected))
    codes = sorted({str(r.get("code")) for r in collected})
    text = "\n".join([
        "## Robustness", "",
        f"Command: `{command_line(argv)}`", "",
        f"Date: {time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}; machine: {machine_line()}; "
        f"code: {', '.join(codes)}; {time.perf_counter() - t_start:.0f} s this invocation (cached runs skipped).", "",
        f"`uvps run` on synthetic captures of {N} x {M} px at {args.pixel_size_um:g} um "
        f"({N * args.pixel_size_um / 1000:g} x {M * args.pixel_size_um / 1000:g} mm), seeds "
        f"{' '.join(map(str, args.seeds))}; each nuisance of `NUISANCE_TOP` alone at the top of its range, "
        "then all of them (`all`), and none. lights: `estimated` (no --lights), `calibrated` (--lights with "
        "the true positions), `dark` (estimated, with --dark a frame taken with the lamp off) or `card` (the true "
        "positions, --dark, and --card a flat card under every lamp, tilted 1 deg, 1 % uneven). "
        + ("Detection with --regions (the true colour areas). " if config["detect"] else "No detection (--no-detect). ")
        + "Each cell: the worst value over seeds (the mean in brackets); **x**: misses its target. "
        "Lights: angle between the run's lights.json direction and the true one, mean / max over lamps; "
        "normals: mean angular error; heights: median relative error of the disc/ring measure over "
        "protrusions >= 100 um wide; F1 >= 60 um, recall >= 200 um and median width error >= 60 um with the "
        "matching of benchmark_protrusions.py; additive err: |run.json additive mean - truth (black level + "
        "mean stray light)| in counts.", "",
        table, "",
    ] + worst + [""])
    print(text, flush=True)      # the full table; docs/benchmarks.md's (--doc) has the doc's columns
    if args.doc:
        for path in write_doc_section(collected, argv):
            print("wrote", path, flush=True)
    return 0


def _progress(i, n, row, seed, lamps, res, t_start):
    parts = []
    for mode, r in res.items():
        if r is None:
            continue
        if r.get("error"):
            parts.append(f"{mode}: FAILED {r['error']}")
        else:
            parts.append(f"{mode}: lights {r.get('light_mean_deg', float('nan')):.2f} deg, normals "
                         f"{r.get('normals_mean_deg', float('nan')):.3f} deg, {r.get('wall_s', 0):.0f} s")
    print(f"[{i}/{n} {time.perf_counter() - t_start:.0f} s] {row} seed {seed} {lamps} lamps: " + "; ".join(parts),
          file=sys.stderr, flush=True)


if __name__ == "__main__":
    sys.exit(main())
