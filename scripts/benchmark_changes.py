"""Benchmark of ``uvps changes`` (issue 10, "Numbers it must reach") on synthetic pairs.

Pairs of 1600 x 1200 px (``uvps.synthetic.make_capture_pair``): one earlier capture A, later
captures B from another camera pose (shift up to 200 px, rotation up to 3 deg, scale within 2 %)
under other lamps, with protrusions grown, new and gone; and unchanged pairs (same surface, other
pose and lamps). Each capture goes through ``uvps run --detect`` with the lamps **estimated from
the images** (no lights file), then ``uvps changes A B``. Measured against the truth:

- registration error: rms over a 10-px grid of the field of |true b_to_a - estimated|, px;
- new protrusions (true width >= 60 um): F1 of ``new``;
- growth (true change of width >= 20 um or of height >= 5 um): F1 of ``grown``; grown ones
  below both thresholds count neither way;
- unchanged pairs: share of matched protrusions flagged changed (grown or shrunk), and new/gone;
- ``changes``' own time;
- the repeatability: robust sd (1.4826 MAD) of the change of width and height per width class on
  the unchanged pairs (what ``uvps.changes.NOISE_FLOOR`` holds).

Usage::

    .venv/bin/python scripts/benchmark_changes.py [--work DIR] [--append docs/benchmarks.md]
    .venv/bin/python scripts/benchmark_changes.py --repeatability-only

Run folders are kept in ``--work`` (default /tmp/uvps_bench_changes) and reused when present.
"""
from __future__ import annotations

import argparse
import csv
import json
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

from uvps.synthetic import LaterSpec, SyntheticSpec, make_capture_pair, write_capture

ROOT = Path(__file__).resolve().parents[1]
UVPS = str(Path(sys.executable).parent / "uvps")
SHAPE = (1200, 1600)
SPEC = dict(shape=SHAPE, protrusion_density_light=90.0, protrusion_density_dark=15.0, seed=0)
# the worst case of the bounds, and milder poses
CHANGED = [LaterSpec(seed=11, shift_px=(200.0 * np.cos(0.6), 200.0 * np.sin(0.6)), rotation_deg=3.0,
                     scale=1.02, new_per_cm2=8.0),
           LaterSpec(seed=12, new_per_cm2=8.0)]
UNCHANGED = [LaterSpec.unchanged(seed=21, shift_px=(-200.0, 0.0), rotation_deg=-3.0, scale=0.98),
             LaterSpec.unchanged(seed=22), LaterSpec.unchanged(seed=23)]
WIDTH_CLASSES = (0.0, 100.0, 200.0, 400.0, float("inf"))


def _run(capture_dir: Path, run_dir: Path) -> float:
    if (run_dir / "protrusions.csv").is_file():
        return float("nan")
    t = time.perf_counter()
    subprocess.run([UVPS, "run", str(capture_dir), "--detect", "-o", str(run_dir)], check=True,
                   stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    return time.perf_counter() - t


def make_pair(work: Path, name: str, later: LaterSpec) -> dict:
    """Captures and run folders of one pair (A shared by every pair of the spec)."""
    d = work / name
    if not (d / "truth.json").is_file():
        d.mkdir(parents=True, exist_ok=True)
        pair = make_capture_pair(SyntheticSpec(**SPEC), later)
        if not (work / "capA").is_dir():
            write_capture(pair.a, work / "capA", truth=False)
        write_capture(pair.b, d / "capB", truth=False)
        (d / "truth.json").write_text(json.dumps({"b_to_a": pair.b_to_a.tolist(), "info": pair.info,
                                                  "changes": {k: v.tolist() for k, v in pair.changes.items()}}))
    _run(work / "capA", work / "runA")
    _run(d / "capB", d / "runB")
    return json.loads((d / "truth.json").read_text())


def run_changes(work: Path, name: str) -> tuple:
    out = work / name / "changes"
    t = time.perf_counter()
    subprocess.run([UVPS, "changes", str(work / "runA"), str(work / name / "runB"), "-o", str(out)],
                   check=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    return out, time.perf_counter() - t


def registration_error(truth_T, est_T) -> float:
    yy, xx = np.mgrid[0:SHAPE[0]:10, 0:SHAPE[1]:10]
    p = np.stack([xx.ravel(), yy.ravel(), np.ones(xx.size)])

    def ap(T):
        q = np.asarray(T) @ p
        return q[:2] / q[2]

    e = ap(truth_T) - ap(est_T)
    return float(np.sqrt(np.mean(np.sum(e * e, axis=0))))


def _rows(out: Path) -> list:
    with open(out / "changes.csv", newline="", encoding="utf-8") as fh:
        return list(csv.DictReader(fh))


def _f(x):
    return float(x) if x not in ("", None) else np.nan


def link_truth(rows: list, truth: dict) -> list:
    """Each found row's true status (nearest true protrusion within 8 px, by A or B position)."""
    t = {k: np.asarray(v, float) if k != "status" else np.asarray(v) for k, v in truth["changes"].items()}
    out = []
    for r in rows:
        if r["x_px_a"]:
            d = np.hypot(t["x_px_a"] - _f(r["x_px_a"]), t["y_px_a"] - _f(r["y_px_a"]))
        else:
            d = np.hypot(t["x_px_b"] - _f(r["x_px_b"]), t["y_px_b"] - _f(r["y_px_b"]))
        d = np.where(np.isfinite(d), d, np.inf)
        j = int(np.argmin(d)) if len(d) else -1
        out.append(j if j >= 0 and d[j] < 8 else -1)
    return out


def _f1(tp, fp, fn):
    return 2 * tp / max(2 * tp + fp + fn, 1), tp / max(tp + fp, 1), tp / max(tp + fn, 1)


def score_changed(rows, truth, shape_b) -> dict:
    t = truth["changes"]
    status = np.asarray(t["status"])
    wa, wb = np.asarray(t["width_um_a"], float), np.asarray(t["width_um_b"], float)
    ha, hb = np.asarray(t["height_um_a"], float), np.asarray(t["height_um_b"], float)
    link = link_truth(rows, truth)
    # truth restricted to the common field: protrusions both views see (ids in both, or new/gone inside)
    T = np.asarray(truth["b_to_a"])
    inv = np.linalg.inv(T)
    xa, ya = np.asarray(t["x_px_a"], float), np.asarray(t["y_px_a"], float)
    xb, yb = np.asarray(t["x_px_b"], float), np.asarray(t["y_px_b"], float)
    in_a = (xa > 20) & (xa < SHAPE[1] - 21) & (ya > 20) & (ya < SHAPE[0] - 21)
    in_b = (xb > 20) & (xb < shape_b[1] - 21) & (yb > 20) & (yb < shape_b[0] - 21)
    common = in_a & in_b
    new_pos = common & (status == "new") & (wb >= 60)
    big_growth = (status == "grown") & (((wb - wa) >= 20) | ((hb - ha) >= 5))
    grow_pos = common & big_growth
    grow_dontcare = common & (status == "grown") & ~big_growth
    found = [r["status"] for r in rows]
    # new
    hit_new = {j for s, j in zip(found, link) if s == "new" and j >= 0 and new_pos[j]}
    fp_new = sum(1 for s, j in zip(found, link) if s == "new" and not (j >= 0 and (status[j] == "new")))
    res = {"new": _f1(len(hit_new), fp_new, int(new_pos.sum()) - len(hit_new)),
           "n_new_true": int(new_pos.sum())}
    hit_g = {j for s, j in zip(found, link) if s == "grown" and j >= 0 and grow_pos[j]}
    fp_g = sum(1 for s, j in zip(found, link) if s == "grown" and not (j >= 0 and (grow_pos[j] or grow_dontcare[j])))
    res["grown"] = _f1(len(hit_g), fp_g, int(grow_pos.sum()) - len(hit_g))
    res["n_grown_true"] = int(grow_pos.sum())
    res["n_grown_small"] = int(grow_dontcare.sum())
    res["found"] = {s: found.count(s) for s in ("new", "grown", "shrunk", "unchanged", "gone")}
    return res


def score_unchanged(rows) -> dict:
    found = [r["status"] for r in rows]
    matched = [s for s in found if s in ("grown", "shrunk", "unchanged")]
    changed = sum(s in ("grown", "shrunk") for s in matched)
    return {"n": len(found), "matched": len(matched), "flagged": changed,
            "flagged_share": changed / max(len(matched), 1),
            "new": found.count("new"), "gone": found.count("gone"),
            "any_share": (len(found) - len(matched) + changed) / max(len(found), 1)}


def repeatability(all_rows: list) -> list:
    """Robust sd of d_width and d_height per width class, over the unchanged pairs' matched rows
    (with the noise floor switched off: every matched row is kept whatever its status)."""
    w, dw, dh = [], [], []
    for rows in all_rows:
        for r in rows:
            if r["status"] in ("grown", "shrunk", "unchanged"):
                w.append((_f(r["width_um_a"]) + _f(r["width_um_b"])) / 2)
                dw.append(_f(r["d_width_um"]))
                dh.append(_f(r["d_height_um"]))
    w, dw, dh = map(np.asarray, (w, dw, dh))
    out = []
    for lo, hi in zip(WIDTH_CLASSES[:-1], WIDTH_CLASSES[1:]):
        sel = (w >= lo) & (w < hi) & np.isfinite(dw) & np.isfinite(dh)

        def rsd(x):
            return float(1.4826 * np.median(np.abs(x - np.median(x)))) if x.size >= 3 else float("nan")

        out.append((lo, hi, rsd(dw[sel]), rsd(dh[sel]), int(sel.sum()),
                    float(np.median(dw[sel])) if sel.any() else float("nan"),
                    float(np.median(dh[sel])) if sel.any() else float("nan")))
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--work", default="/tmp/uvps_bench_changes")
    ap.add_argument("--append", default=None, help="append the results to this Markdown file")
    ap.add_argument("--repeatability-only", action="store_true")
    ap.add_argument("--pairs", type=int, default=2, help="at most this many changed pairs")
    ap.add_argument("--unchanged-pairs", type=int, default=3, help="at most this many unchanged pairs")
    args = ap.parse_args(argv)
    work = Path(args.work)
    work.mkdir(parents=True, exist_ok=True)
    t_all = time.perf_counter()
    changed = []
    if not args.repeatability_only:
        for i, later in enumerate(CHANGED[:args.pairs]):
            name = f"changed{i}"
            truth = make_pair(work, name, later)
            out, secs = run_changes(work, name)
            changed.append((name, truth, out, secs))
            print(name, "done", round(secs, 1), "s", flush=True)
    unchanged = []
    for i, later in enumerate(UNCHANGED[:args.unchanged_pairs]):
        name = f"unchanged{i}"
        truth = make_pair(work, name, later)
        out, secs = run_changes(work, name)
        reg = json.loads((out / "registration.json").read_text())
        unchanged.append({"name": name, "rows": _rows(out), "truth": truth, "secs": secs, "reg": reg,
                          "reg_err": registration_error(truth["b_to_a"], reg["b_to_a"])})
        print(name, "done", round(secs, 1), "s", flush=True)
    rep = repeatability([u["rows"] for u in unchanged])
    lines = ["", "## Monitoring over time (`uvps changes`, issue 10)", "",
             f"`.venv/bin/python scripts/benchmark_changes.py {' '.join(argv if argv is not None else sys.argv[1:])}`"
             f" ({time.strftime('%Y-%m-%d')}): synthetic pairs of {SHAPE[1]} x {SHAPE[0]} px of 15 um "
             "(`make_capture_pair`, one A, later captures B from another camera pose and other lamps), each "
             "capture through `uvps run --detect` with the lamps estimated from the images, then "
             "`uvps changes A B`.", "",
             "**Repeatability** (unchanged pairs: the same surface, another pose, other lamps; robust sd "
             "of the change between the dates of matched protrusions; `uvps.changes.NOISE_FLOOR`):", "",
             "| width class (um) | sd width (um) | sd height (um) | median d width (um) | median d height (um) | pairs |",
             "|---|---|---|---|---|---|"]
    for lo, hi, sw, sh, n, mw, mh in rep:
        cls = f"{lo:g}-{hi:g}" if np.isfinite(hi) else f">= {lo:g}"
        lines.append(f"| {cls} | {sw:.2f} | {sh:.2f} | {mw:+.2f} | {mh:+.2f} | {n} |")
    print("\n".join(lines[-6:]), flush=True)
    if not args.repeatability_only:
        lines += ["", "| pair | pose (shift px, rot deg, scale) | model | matches | rms_px (reported) | "
                  "registration error px (true) | new F1 (P / R, n) | grown F1 (P / R, n) | flagged changed "
                  "(unchanged pair) | changes time s |", "|---|---|---|---|---|---|---|---|---|---|"]
        for name, truth, out, secs in changed:
            reg = json.loads((out / "registration.json").read_text())
            s = score_changed(_rows(out), truth, SHAPE)
            inf = truth["info"]
            pose = f"({np.hypot(*inf['shift_px']):.0f}, {inf['rotation_deg']:+.2f}, {inf['scale']:.4f})"
            lines.append(f"| {name} | {pose} | {reg['model']} | {reg['matches']} | {reg['rms_px']:.3f} | "
                         f"{registration_error(truth['b_to_a'], reg['b_to_a']):.3f} | "
                         f"{s['new'][0]:.3f} ({s['new'][1]:.2f} / {s['new'][2]:.2f}, {s['n_new_true']}) | "
                         f"{s['grown'][0]:.3f} ({s['grown'][1]:.2f} / {s['grown'][2]:.2f}, {s['n_grown_true']}; "
                         f"{s['n_grown_small']} smaller growths not counted) | - | {secs:.1f} |")
            print(lines[-1], s["found"], flush=True)
        for u in unchanged:
            sc = score_unchanged(u["rows"])
            inf = u["truth"]["info"]
            pose = f"({np.hypot(*inf['shift_px']):.0f}, {inf['rotation_deg']:+.2f}, {inf['scale']:.4f})"
            lines.append(f"| {u['name']} | {pose} | {u['reg']['model']} | {u['reg']['matches']} | "
                         f"{u['reg']['rms_px']:.3f} | {u['reg_err']:.3f} | - | - | "
                         f"{sc['flagged']} of {sc['matched']} matched ({100 * sc['flagged_share']:.1f} %); "
                         f"{sc['new']} new, {sc['gone']} gone | {u['secs']:.1f} |")
            print(lines[-1], flush=True)
        lines += ["", "Issue's numbers: registration <= 0.3 px; new >= 60 um F1 >= 0.9; growth >= 20 um width or "
                  ">= 5 um height F1 >= 0.9; unchanged pair <= 2 % flagged changed; `changes` < 20 s. "
                  f"Whole benchmark {time.perf_counter() - t_all:.0f} s (captures and runs cached in --work)."]
    if args.append:
        with open(args.append, "a", encoding="utf-8") as fh:
            fh.write("\n".join(lines) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
