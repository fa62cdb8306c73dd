"""Benchmark of ``uvps changes`` (docs/benchmarks.md, "Monitoring over time") on synthetic pairs with the true lamps.

Per seed (0, 1, 2) one earlier capture A of 1200 x 900 px of 15 um
(``uvps.testing.synthetic.make_capture_pair``) and three later captures B, each under lamps placed
again (drawn anew):

- ``changed``: the camera moved 120 px, rotated 3 deg, scaled 0.98 or 1.02; 25 % of the lone
  protrusions grown 1.2-1.5x in width and 1.2-1.6x in height, new ones (5 per cm^2), a few gone;
- ``still``: the surface unchanged, the camera where it was;
- ``moved``: the surface unchanged, the camera moved as much as ``changed``'s.

Each capture goes through ``uvps run --detect --lights lights_positions_mm.csv`` (the true lamp
positions), then ``uvps changes A B``. With ``--lamps spheres`` each date is calibrated as a
conservator would: two glossy spheres rendered under that date's lamps
(:func:`uvps.testing.synthetic_spheres.make_sphere_capture`, 1.35 mm radius, in opposite corners),
``uvps calibrate --spheres`` on them, then ``uvps run --detect --calibration CAL``; the table then
also says whether ``uvps changes`` accepted the pair's height scales (B / A scale). Scored against the truth:

- new (true width >= 60 um): F1 of ``new``;
- grown (true change of width >= 20 um or of height >= 5 um): F1 of ``grown``; smaller growths
  count neither way;
- unchanged pairs: rows whose status is not ``unchanged`` (any of grown, shrunk, new, gone,
  merged, split), of all rows;
- registration error: rms over a 10-px grid of |true b_to_a - estimated|, px.

``--fit-noise`` fits :class:`uvps.core.changes.NoiseModel` (maximum likelihood of the changes of the
matched protrusions of the ``moved`` pairs, trimmed at 4 sd; every term, the exponents of the
few-pixel terms included) and prints it for ``uvps.core.changes.NOISE_MODEL``. The model is fitted
on other seeds than those it is scored on (other scenes, other poses, so other pixel phases)::

    .venv/bin/python scripts/benchmark_changes.py --work W --seeds 10 11 12 --variants small clean real \
        --kinds moved --fit-noise
    .venv/bin/python scripts/benchmark_changes.py --work W --variants mixed small clean real

``--noise-model fixed-peak`` decides with the model before its terms grew with the size in pixels
(to compare); ``--sigma-factors`` also decides each pair at other significances.

Usage::

    .venv/bin/python scripts/benchmark_changes.py [--seeds 0 1 2] [--work DIR] [--fit-noise]
    .venv/bin/python scripts/benchmark_changes.py --lamps spheres --work /tmp/uvps_bench_changes_spheres

Captures and run folders are kept in ``--work`` (default /tmp/uvps_bench_changes) and reused.
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import subprocess
import sys
import time
from pathlib import Path
from typing import Optional

import numpy as np
from scipy.optimize import minimize

from uvps.core.changes import NOISE_MODEL, NOISE_MODEL_FIXED_PEAK, NoiseModel, Registration, change_uncertainty
from uvps.commands.changes import compute_changes
from uvps.errors import UVPSInputError
from uvps.testing.synthetic import LaterSpec, SyntheticSpec, make_capture_pair, write_capture

UVPS = str(Path(sys.executable).parent / "uvps")
SHAPE = (900, 1200)
KINDS = ("changed", "still", "moved")
#: The captures' scenes: "clean" (the generator's defaults), "real": what the estimators do not
#: model, at both dates (a canvas bowed by 200 um, black level 200 counts given to the run,
#: vignetting, lamp beams aimed within 5 deg, brush strokes 5-30 um high, a two-scale weave), and
#: "small": the clean scene with protrusions 40-120 um wide (a few pixels: their heights repeat worst),
#: "mixed": 40-600 um wide about a median of 100 um (the few-pixel ones among big ones).
VARIANTS = {"clean": {},
            "real": {"bow_um": 200.0, "black_level": 200.0, "vignetting": 0.3, "beam_exponent": 15.0,
                     "beam_aim_error_deg": 5.0, "ridge_width_um": (60.0, 1000.0), "ridge_height_um": (5.0, 30.0),
                     "weave_period_um": (250.0, 800.0), "weave_amplitude_um": (3.0, 6.0)},
            # protrusions few pixels wide: 40-120 um (most 60-120 um, 4-8 px of 15 um), as many
            "small": {"width_um": (40.0, 120.0)},
            # big and small together, as on a painting: a third of them below 80 um, a fifth above 150 um
            "mixed": {"width_um": (40.0, 600.0), "width_median_um": 100.0}}


def later_spec(seed: int, kind: str) -> LaterSpec:
    """The later capture of one kind: the worst pose of the issue's bounds, in a seed's direction."""
    ang = np.random.default_rng(seed).uniform(0, 2 * np.pi)
    sign = (-1) ** seed
    if kind == "changed":
        return LaterSpec(seed=100 + seed, shift_px=(120 * np.cos(ang), 120 * np.sin(ang)), rotation_deg=3.0 * sign,
                         scale=1.02 if seed % 2 else 0.98, new_per_cm2=5.0)
    if kind == "still":
        return LaterSpec.unchanged(seed=200 + seed, shift_px=(0.0, 0.0), rotation_deg=0.0, scale=1.0)
    return LaterSpec.unchanged(seed=300 + seed, shift_px=(120 * np.cos(ang + 2), 120 * np.sin(ang + 2)),
                               rotation_deg=-3.0 * sign, scale=1.02 if seed % 2 == 0 else 0.98)


#: The calibration spheres of ``--lamps spheres`` (kind, centre as fractions of the frame, radius mm).
SPHERES = (("glossy", (0.15, 0.2), 1.35), ("glossy", (0.85, 0.8), 1.35))


def _write_spheres(capture, folder: Path) -> None:
    from uvps.testing.synthetic_spheres import SphereSpec, make_sphere_capture, write_sphere_capture

    write_sphere_capture(make_sphere_capture(capture, [SphereSpec(*s) for s in SPHERES]), folder, truth=False)


def _run(cap: Path, out: Path, variant: str, lamps: str = "truth") -> None:
    if not (out / "protrusions.csv").is_file():
        black = ["--black-level", str(VARIANTS[variant]["black_level"])] if "black_level" in VARIANTS[variant] else []
        if lamps == "spheres":
            cal = cap.parent / (cap.name + "_cal")
            if not (cal / "calibration.json").is_file():
                subprocess.run([UVPS, "calibrate", "--spheres", str(cap.parent / (cap.name + "_spheres")),
                                "--pixel-size-um", "15", "-o", str(cal)], check=True, stdout=subprocess.DEVNULL,
                               stderr=subprocess.DEVNULL)
            given = ["--calibration", str(cal)]
        else:
            given = ["--lights", str(cap / "lights_positions_mm.csv")]
        subprocess.run([UVPS, "run", str(cap), "--detect", *given, *black, "-o", str(out)], check=True,
                       stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)


def pair_dir(work: Path, seed: int, variant: str) -> Path:
    return work / (f"s{seed}" if variant == "clean" else f"s{seed}_{variant}")


def make_pair(work: Path, seed: int, kind: str, variant: str = "clean", lamps: str = "truth") -> dict:
    """Captures and run folders of one pair (A shared by the kinds of a seed); the truth."""
    d = pair_dir(work, seed, variant)
    kd = d / kind
    if not (kd / "truth.json").is_file():
        kd.mkdir(parents=True, exist_ok=True)
        spec = SyntheticSpec(shape=SHAPE, protrusion_density_light=90.0, protrusion_density_dark=15.0, seed=seed,
                             **VARIANTS[variant])
        pair = make_capture_pair(spec, later_spec(seed, kind))
        if not (d / "capA").is_dir():
            write_capture(pair.a, d / "capA", truth=False)
            if lamps == "spheres":
                _write_spheres(pair.a, d / "capA_spheres")
        write_capture(pair.b, kd / "capB", truth=False)
        if lamps == "spheres":
            _write_spheres(pair.b, kd / "capB_spheres")
        (kd / "truth.json").write_text(json.dumps({"b_to_a": pair.b_to_a.tolist(), "info": pair.info,
                                                   "changes": {k: v.tolist() for k, v in pair.changes.items()}}))
    _run(d / "capA", d / "runA", variant, lamps)
    _run(kd / "capB", kd / "runB", variant, lamps)
    return json.loads((kd / "truth.json").read_text())


def registration_error(truth_T, est_T) -> float:
    yy, xx = np.mgrid[0:SHAPE[0]:10, 0:SHAPE[1]:10]
    p = np.stack([xx.ravel(), yy.ravel(), np.ones(xx.size)])

    def ap(T):
        q = np.asarray(T) @ p
        return q[:2] / q[2]

    e = ap(truth_T) - ap(est_T)
    return float(np.sqrt(np.mean(np.sum(e * e, axis=0))))


def link_truth(rows: dict, truth: dict) -> np.ndarray:
    """Each found row's true protrusion (nearest within 8 px, by A's position, else B's), -1 if none."""
    t = {k: np.asarray(v, float) for k, v in truth["changes"].items() if k != "status"}
    out = np.full(len(rows["status"]), -1)
    for i in range(len(out)):
        if np.isfinite(rows["x_px_a"][i]):
            d = np.hypot(t["x_px_a"] - rows["x_px_a"][i], t["y_px_a"] - rows["y_px_a"][i])
        else:
            d = np.hypot(t["x_px_b"] - rows["x_px_b"][i], t["y_px_b"] - rows["y_px_b"][i])
        d = np.where(np.isfinite(d), d, np.inf)
        if d.size and d.min() < 8:
            out[i] = int(np.argmin(d))
    return out


def _f1(tp, fp, fn):
    return 2 * tp / max(2 * tp + fp + fn, 1), tp / max(tp + fp, 1), tp / max(tp + fn, 1)


def score_changed(rows: dict, truth: dict) -> dict:
    t = truth["changes"]
    status = np.asarray(t["status"])
    wa, wb = np.asarray(t["width_um_a"], float), np.asarray(t["width_um_b"], float)
    ha, hb = np.asarray(t["height_um_a"], float), np.asarray(t["height_um_b"], float)
    xa, ya = np.asarray(t["x_px_a"], float), np.asarray(t["y_px_a"], float)
    xb, yb = np.asarray(t["x_px_b"], float), np.asarray(t["y_px_b"], float)
    m, n = SHAPE
    in_a = (xa > 20) & (xa < n - 21) & (ya > 20) & (ya < m - 21)
    in_b = (xb > 20) & (xb < n - 21) & (yb > 20) & (yb < m - 21)
    common = in_a & in_b
    new_pos = common & (status == "new") & (wb >= 60)
    big = (status == "grown") & (((wb - wa) >= 20) | ((hb - ha) >= 5))
    grow_pos, grow_dc = common & big, common & (status == "grown") & ~big
    link = link_truth(rows, truth)
    found = rows["status"]
    hit_new = {j for s, j in zip(found, link) if s == "new" and j >= 0 and new_pos[j]}
    fp_new = sum(1 for s, j in zip(found, link) if s == "new" and not (j >= 0 and status[j] == "new"))
    hit_g = {j for s, j in zip(found, link) if s == "grown" and j >= 0 and grow_pos[j]}
    fp_g = sum(1 for s, j in zip(found, link) if s == "grown" and not (j >= 0 and (grow_pos[j] or grow_dc[j])))
    return {"new": _f1(len(hit_new), fp_new, int(new_pos.sum()) - len(hit_new)), "n_new": int(new_pos.sum()),
            "grown": _f1(len(hit_g), fp_g, int(grow_pos.sum()) - len(hit_g)), "n_grown": int(grow_pos.sum()),
            "n_grown_small": int(grow_dc.sum())}


def score_unchanged(rows: dict) -> dict:
    st = list(rows["status"])
    flagged = {s: st.count(s) for s in ("grown", "shrunk", "new", "gone", "merged", "split") if st.count(s)}
    n_flag = sum(flagged.values())
    return {"n": len(st), "flagged": n_flag, "share": n_flag / max(len(st), 1), "by_status": flagged}


def _pairs_for_fit(res) -> dict:
    r = res["rows"]
    sel = np.isin(r["status"], ("grown", "shrunk", "unchanged")) & np.isfinite(r["d_width_um"])
    out = {k: r[k][sel] for k in ("width_um_a", "width_um_b", "height_um_a", "height_um_b", "d_width_um",
                                  "d_height_um", "surface_noise_um")}
    out["px_a"] = np.full(sel.sum(), res["a"].pixel_size_um)
    out["px_b"] = np.full(sel.sum(), res["b"].pixel_size_um)
    return out


#: The fitted terms of :class:`NoiseModel`: coefficients (fitted on a log scale) and exponents.
FIT_COEFFICIENTS = ("width_px", "width_rel", "rim", "peak", "height_rel", "surface")
FIT_EXPONENTS = ("rim_exponent", "peak_exponent")
#: Held, not fitted: the outline's exponent 0.5, the area of a footprint counted on the pixel grid
#: (its edge pixels, about pi w / p of them, each in or out: the area's sd grows as sqrt(w / p) p^2,
#: the width's as p (p / w)^0.5). Freed, on the small and clean pairs it ran to the bound 4 at the same
#: likelihood (within 0.3): the few-pixel widths pin the term's size, not its slope. The surface term's coefficient is held
#: at 1.33, its fit on the clean moved pairs alone: freed, the pooled likelihood drops it to 0.24 and
#: one fit pair's heights (real scene, seed 10: its wide protrusions 2-4 % lower at B) then repeat
#: 1.9 x worse than the model, a warning; the likelihood pools protrusions, the warning judges pairs.
FIT_FIXED = {"rim_exponent": 0.5, "surface": 1.33}


def fit_noise(samples: list, *, fixed: Optional[dict] = None, source: str = "the moved unchanged pairs"):
    """Maximum likelihood of the changes under :class:`NoiseModel` (normal, zero mean), trimmed:
    refitted on the changes within 4 sd until the set holds still. The terms in ``fixed`` keep
    their value; the others are fitted (coefficients on a log scale, exponents within 0-4).
    Returns the model and its negative log-likelihood on the kept changes."""
    d = {k: np.concatenate([s[k] for s in samples]) for k in samples[0]}
    fixed = dict(FIT_FIXED if fixed is None else fixed)
    # started from the model before the few-pixel terms (so a re-fit does not start from its own answer)
    start = dataclasses.replace(NOISE_MODEL_FIXED_PEAK, width_rel=1e-3, rim=0.3)
    coefs = [k for k in FIT_COEFFICIENTS if k not in fixed]
    expos = [k for k in FIT_EXPONENTS if k not in fixed]
    theta = np.concatenate([np.log([getattr(start, k) for k in coefs]), [getattr(start, k) for k in expos]])
    keep = np.isfinite(d["d_width_um"]) & np.isfinite(d["d_height_um"])
    nc = len(coefs)

    def model_of(th):
        return NoiseModel(**{**dataclasses.asdict(start), **dict(zip(coefs, np.exp(th[:nc]).tolist())),
                             **dict(zip(expos, np.clip(th[nc:], 0.0, 4.0).tolist())), **fixed})

    def sds(th, sel):
        return change_uncertainty(d["width_um_a"][sel], d["width_um_b"][sel], d["height_um_a"][sel],
                                  d["height_um_b"][sel], pixel_size_um_a=d["px_a"][sel], pixel_size_um_b=d["px_b"][sel],
                                  surface_um=d["surface_noise_um"][sel], model=model_of(th))

    def nll(th):
        sw, sh = sds(th, keep)
        return float(np.sum(np.log(sw) + 0.5 * (d["d_width_um"][keep] / sw) ** 2
                            + np.log(sh) + 0.5 * (d["d_height_um"][keep] / sh) ** 2))

    for _ in range(8):
        for _restart in range(3):      # Nelder-Mead restarted from its own answer (up to 8 parameters)
            theta = minimize(nll, theta, method="Nelder-Mead", options={"maxiter": 8000, "xatol": 1e-4,
                                                                         "fatol": 1e-6}).x
        sw, sh = sds(theta, np.ones(keep.size, bool))
        new_keep = (np.abs(d["d_width_um"] / sw) < 4) & (np.abs(d["d_height_um"] / sh) < 4)
        if np.array_equal(new_keep, keep):
            break
        keep = new_keep
    m = model_of(theta)
    m = dataclasses.replace(m, **{k: float(f"{getattr(m, k):.4g}") for k in FIT_COEFFICIENTS + FIT_EXPONENTS})
    m = dataclasses.replace(m, n=int(keep.sum()), source=f"{int(keep.sum())} of {keep.size} protrusions of "
                            f"{source}, trimmed at 4 sd")
    return m, nll(theta)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--work", default="/tmp/uvps_bench_changes")
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    ap.add_argument("--kinds", nargs="+", default=list(KINDS), choices=KINDS)
    ap.add_argument("--variants", nargs="+", default=["clean", "real"], choices=list(VARIANTS))
    ap.add_argument("--lamps", choices=("truth", "spheres"), default="truth",
                    help="each date's lamps: the true positions (--lights) or a sphere calibration (--calibration)")
    ap.add_argument("--fit-noise", action="store_true", help="fit the noise model on the moved pairs and print it")
    ap.add_argument("--noise-model", choices=("current", "fixed-peak"), default="current",
                    help="the repeatability model that decides: changes.NOISE_MODEL, or the one before its terms "
                         "grew with the size in pixels (changes.NOISE_MODEL_FIXED_PEAK), to compare")
    ap.add_argument("--save-samples", metavar="NPZ", help="write the moved pairs' matched protrusions (what "
                    "--fit-noise fits) to this .npz")
    ap.add_argument("--sigma-factors", type=float, nargs="+", default=[],
                    help="also decide each pair at these significances (worst new F1, grown F1, flagged share)")
    args = ap.parse_args(argv)
    work = Path(args.work)
    work.mkdir(parents=True, exist_ok=True)
    model = NOISE_MODEL_FIXED_PEAK if args.noise_model == "fixed-peak" else NOISE_MODEL
    t_all = time.perf_counter()
    results, samples, sweep, timed, refused = [], [], {}, [], []
    for variant, seed, kind in ((v, s, k) for v in args.variants for s in args.seeds for k in args.kinds
                                if not (v != "clean" and k == "still")):
        truth = make_pair(work, seed, kind, variant, args.lamps)
        d = pair_dir(work, seed, variant)
        t = time.perf_counter()
        cache = d / kind / "registration_cache.json"     # the registration does not depend on the decision
        reg = None
        if cache.is_file():
            fields = json.loads(cache.read_text())
            reg = Registration(**{**fields, "b_to_a": np.array(fields["b_to_a"])})
        try:
            res = compute_changes(d / "runA", d / kind / "runB", registration=reg, noise_model=model)
        except UVPSInputError as exc:        # a refused pair is a result: "no pair refused" is a target
            print(variant, seed, kind, "REFUSED:", exc, flush=True)
            refused.append(f"{variant} seed {seed} {kind}: {exc}")
            continue
        secs = time.perf_counter() - t
        if reg is None:
            cache.write_text(json.dumps({**dataclasses.asdict(res["registration"]),
                                         "b_to_a": res["registration"].b_to_a.tolist()}))
            timed.append(secs)
        reg_err = registration_error(truth["b_to_a"], res["registration"].b_to_a)
        score = score_changed(res["rows"], truth) if kind == "changed" else score_unchanged(res["rows"])
        unc = res["diagnostics"]["uncertainty"]
        results.append({"seed": seed, "kind": kind, "variant": variant, "score": score, "reg_err": reg_err, "secs": secs,
                        "info": truth["info"], "inflation": (unc["inflation_width"], unc["inflation_height"]),
                        "scale": res["levelling"].height_scale})
        if kind == "moved":
            samples.append(_pairs_for_fit(res))
        for k in args.sigma_factors:
            rk = compute_changes(d / "runA", d / kind / "runB", sigma_factor=k, registration=res["registration"],
                                 noise_model=model)
            sweep.setdefault(k, []).append((kind, score_changed(rk["rows"], truth) if kind == "changed"
                                            else score_unchanged(rk["rows"])))
        print(variant, seed, kind, f"reg {reg_err:.3f} px", score, f"x{unc['inflation_width']:.2f}/x{unc['inflation_height']:.2f}",
              f"{secs:.1f} s", flush=True)
    if args.save_samples and samples:
        np.savez(args.save_samples, **{k: np.concatenate([s[k] for s in samples]) for k in samples[0]})
    if args.fit_noise and samples:
        fitted, _ = fit_noise(samples, source=f"{len(samples)} moved unchanged pairs ({' '.join(args.variants)} "
                              f"scenes, seeds {' '.join(map(str, args.seeds))})")
        print(fitted, flush=True)
    for k, scores in sweep.items():
        ch = [s for kind, s in scores if kind == "changed"]
        un = [s for kind, s in scores if kind != "changed"]
        print(f"sigma_factor {k:g}: worst new F1 {min((c['new'][0] for c in ch), default=float('nan')):.3f}, "
              f"grown F1 {min((c['grown'][0] for c in ch), default=float('nan')):.3f}, unchanged flagged "
              f"{100 * max((u['share'] for u in un), default=float('nan')):.1f} % (worst)", flush=True)
    lines = ["| scene | seed | pair | pose (shift px, rot deg, scale) | registration error px | new F1 (P / R, n) | "
             "grown F1 (P / R, n) | flagged (unchanged pair) | inflation w / h | B / A height scale |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    for r in results:
        inf, s = r["info"], r["score"]
        pose = f"({np.hypot(*inf['shift_px']):.0f}, {inf['rotation_deg']:+.1f}, {inf['scale']:.2f})"
        if r["kind"] == "changed":
            new = f"{s['new'][0]:.3f} ({s['new'][1]:.2f} / {s['new'][2]:.2f}, {s['n_new']})"
            grown = (f"{s['grown'][0]:.3f} ({s['grown'][1]:.2f} / {s['grown'][2]:.2f}, {s['n_grown']}; "
                     f"{s['n_grown_small']} smaller)")
            flag = "-"
        else:
            new = grown = "-"
            detail = ", ".join(f"{v} {k}" for k, v in s["by_status"].items())
            flag = f"{s['flagged']} of {s['n']} ({100 * s['share']:.1f} %){'; ' + detail if detail else ''}"
        lines.append(f"| {r['variant']} | {r['seed']} | {r['kind']} | {pose} | {r['reg_err']:.3f} | {new} | {grown} | {flag} | "
                     f"{r['inflation'][0]:.2f} / {r['inflation'][1]:.2f} | {r['scale']:.3f} |")
    ch = [r["score"] for r in results if r["kind"] == "changed"]
    un = [r["score"] for r in results if r["kind"] != "changed"]
    if ch:
        lines.append(f"\nWorst: new F1 {min(c['new'][0] for c in ch):.3f}, grown F1 {min(c['grown'][0] for c in ch):.3f}")
    if un:
        lines.append(f"Worst unchanged pair: {100 * max(u['share'] for u in un):.1f} % flagged")
    lines.append(f"Pairs refused by `uvps changes`: {len(refused)}" + "".join(f"\n- {r}" for r in refused))
    if timed:
        lines.append(f"`changes` (registration included, where not cached) {min(timed):.0f}-{max(timed):.0f} s per pair")
    lines.append(f"Whole benchmark {time.perf_counter() - t_all:.0f} s (captures, runs and registrations cached in --work).")
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    sys.exit(main())
