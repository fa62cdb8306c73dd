#!/usr/bin/env python3
"""Time and accuracy of the light estimate against the number of lamps (target: <= 10 s up to 64).

Usage::

    .venv/bin/python scripts/benchmark_lights.py [--lamps 8 16 32 64] [--shape 1200 1600] [--seeds 3 4 5] [--doc]

Renders a grey synthetic capture per lamp count (``uvps.testing.synthetic.make_capture``), runs the additive
term and the light estimate of ``uvps run`` (:func:`uvps.core.pipeline.run` with ``RunOptions()`` and no
stage beyond the lights, on ``as_capture()``) and prints, per lamp count and seed: the time of each
(the run's ``timings_s``), the mean and max direction error against the truth, the heights' relative
scale error (mean log tan-elevation ratio) and the reported height uncertainty; then, per lamp count,
the worst over the seeds. ``--doc`` writes the worst figures into docs/benchmarks.md's section ``lights`` (its
paragraph) and the rows into docs/benchmarks/lights.json (scripts/benchdoc.py).
"""
from __future__ import annotations

import argparse
import datetime
import os
import platform
import sys

import numpy as np

from uvps.core import pipeline
from uvps.core.pipeline import RunOptions
from uvps.testing.synthetic import make_capture

DOC_SECTION = "lights"


def _machine():
    with open("/proc/cpuinfo", encoding="utf-8") as fh:
        cpu = next((l.split(":", 1)[1].strip() for l in fh if l.startswith("model name")), "?")
    return f"{os.cpu_count()} cores, {cpu}, Python {platform.python_version()}, load {os.getloadavg()[0]:.1f}"


def run(K, shape, seed):
    cap = make_capture(shape=tuple(shape), n_lights=K, seed=seed, rgb=False)
    res = pipeline.run(cap.as_capture(), RunOptions(), stages=())
    lr = res.lights
    P = cap.light_positions_mm
    D = P / np.linalg.norm(P, axis=1, keepdims=True)
    E = lr.model.directions
    err = np.degrees(np.arccos(np.clip(np.sum(D * E, axis=1), -1, 1)))

    def tane(v):
        return v[:, 2] / np.hypot(v[:, 0], v[:, 1])

    scale = float(np.exp(np.mean(np.log(tane(E) / tane(D)))))
    return [K, seed, res.timings_s["additive"], res.timings_s["lights"], err.mean(), err.max(),
            100 * abs(1 / scale - 1), 100 * lr.estimate.uncertainty.height_rel]


_FMT = ["{}", "{}", "{:.1f}", "{:.1f}", "{:.2f}", "{:.2f}", "{:.1f}", "{:.1f}"]


def _fmt(row):
    return [f.format(v) for f, v in zip(_FMT, row)]


def worst_rows(rows: list) -> list:
    """Per lamp count, the worst over the seeds: the largest time and error, the smallest reported uncertainty."""
    out = []
    for K in dict.fromkeys(r[0] for r in rows):
        per = [r for r in rows if r[0] == K]
        out.append([K, "worst"] + [max(r[i] for r in per) for i in range(2, 7)] + [min(r[7] for r in per)])
    return out


def render_doc(results: dict) -> str:
    """docs/benchmarks.md's paragraph: per lamp count, the worst seed's light-estimate time (s), directions' max
    and mean error (deg), height scale off and reported (%); one line, like a table's row.

    Parameters
    ----------
    results : dict
        ``{"argv": [...], "load": float, "rows": [[K, seed, additive_s, lights_s, mean, max, scale %, reported %],
        ...]}``, as ``--doc`` keeps it in docs/benchmarks/lights.json.
    """
    w = worst_rows(results["rows"])

    def col(i, fmt):
        return " / ".join(fmt.format(r[i]) for r in w)
    cmd = " ".join([".venv/bin/python", "scripts/benchmark_lights.py"] + [a for a in results["argv"] if a != "--doc"])
    text = (f"**Light estimate with {col(0, '{}')} lamps** (`{cmd}`, "
            f"grey clean, load ~{results['load']:.0f}): **{col(3, '{:.1f}')} s**; "
            f"directions max {col(5, '{:.2f}')} deg "
            f"(mean {col(4, '{:.2f}')}); height scale {col(6, '{:.1f}')} % off, reported {col(7, '{:.1f}')} %.")
    return text + "\n"


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--lamps", type=int, nargs="+", default=[8, 16, 32, 64])
    ap.add_argument("--shape", type=int, nargs=2, default=[1200, 1600])
    ap.add_argument("--seeds", type=int, nargs="+", default=[3])
    ap.add_argument("--doc", action="store_true",
                    help="write the worst figures into docs/benchmarks.md (section lights) and "
                         "docs/benchmarks/lights.json")
    a = ap.parse_args(argv)
    head = ["lamps", "seed", "additive (s)", "lights (s)", "dir. err mean (deg)", "max (deg)", "height scale err (%)",
            "reported height unc. (%)"]
    rows = []
    for K in a.lamps:
        per = [run(K, a.shape, seed) for seed in a.seeds]
        for r in per:
            print(" | ".join(_fmt(r)), flush=True)
        if len(per) > 1:   # the worst over seeds: the largest time, error and the smallest reported uncertainty
            worst = [K, "worst"] + [max(r[i] for r in per) for i in range(2, 7)] + [min(r[7] for r in per)]
            rows += per + [worst]
        else:
            rows += per
    table = "\n".join(["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
                      + ["| " + " | ".join(_fmt(r) if r[1] != "worst" else ["**" + x + "**" for x in _fmt(r)]) + " |"
                         for r in rows])
    text = (f"\n## Light estimate against the number of lamps\n\n`{' '.join(['.venv/bin/python'] + sys.argv)}` "
            f"({datetime.date.today()}, {_machine()}); grey {a.shape[1]} x {a.shape[0]} capture of 15 um, "
            f"seeds {' '.join(map(str, a.seeds))}:\n\n{table}\n")
    print(text)
    if a.doc:
        from benchdoc import write_doc
        results = {"argv": list(sys.argv[1:] if argv is None else argv), "load": os.getloadavg()[0],
                   "machine": _machine(), "rows": [r for r in rows if r[1] != "worst"]}
        print("wrote", write_doc(DOC_SECTION, results, render_doc(results), source="scripts/benchmark_lights.py"))


if __name__ == "__main__":
    main()
