#!/usr/bin/env python
"""The detector's outputs pinned: labels, candidate labels, rejection reasons and diagnostics of
:func:`uvps.core.detect.detect_protrusions` on fixed scenes, written to (or checked against)
``tests/golden/``. A restructuring of the detector must reproduce them bit for bit
(``tests/test_detect_golden.py``); a change of behaviour regenerates them, in its own commit, with

    OMP_NUM_THREADS=1 .venv/bin/python scripts/detect_golden.py            # the quick set
    OMP_NUM_THREADS=1 .venv/bin/python scripts/detect_golden.py --full     # and the full-size one

Scenes: the analytic scenes of ``tests/test_detect.py`` (its builders: domes, craters, mesas,
touching pairs, strokes with ripples, cracks, weaves, holes in the measurement, ``left_out``
bands; a few with non-default options so that each switch's branch runs), and the benchmark's
``top``, ``impasto`` and ``on_strokes`` scenes (``scripts/benchmark_detection.py``), seeds 0-2,
on the generator's true albedo, height and normals: 400 x 500 px in the quick set, the
benchmark's 1200 x 1600 px in the full set (``tests/golden/detect_full.npz``, a slow test).
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
for _p in (ROOT / "tests", ROOT / "scripts"):
    if str(_p) not in sys.path:
        sys.path.insert(0, str(_p))

GOLDEN = ROOT / "tests" / "golden"
QUICK = GOLDEN / "detect_quick.npz"
FULL = GOLDEN / "detect_full.npz"
BENCH_SCENES = ("top", "impasto", "on_strokes")
SEEDS = (0, 1, 2)
QUICK_SHAPE = (400, 500)
FULL_SHAPE = (1200, 1600)


def unit_scenes() -> dict:
    """name -> callable returning (albedo, height, keyword arguments of detect_protrusions)."""
    import test_detect as td
    from uvps.core.detect import DetectionParams

    px = 15.0
    out = {}

    def add(name):
        def deco(fn):
            out[name] = fn
            return fn
        return deco

    @add("dome_and_crater")
    def _():
        alb, h = td.scene()
        td.add_dome(alb, h, (50, 50), 300.0, px)
        td.add_dome(alb, h, (110, 115), 200.0, px, crater=True)
        return alb, h, {}

    @add("small_60_90")
    def _():
        alb, h = td.scene()
        td.add_dome(alb, h, (50, 50), 60.0, px)
        td.add_dome(alb, h, (110, 110), 90.0, px)
        return alb, h, {}

    for seed, angle in ((0, 0.0), (1, 2.0)):
        @add(f"own_glow_{seed}")
        def _(seed=seed, angle=angle):
            alb, h = td.scene(seed=seed)
            spot = td.rho_map(h.shape, (80, 60), 10.0) < 1
            alb[spot] = td.SOAP
            td.add_dome(alb, h, (80, 60), 120.0, px)
            centre = (80 + 15 * np.sin(angle), 60 + 15 * np.cos(angle))
            td.add_dome(alb, h, centre, 90.0, px, weak=True)
            return alb, h, {}

    @add("brush_ridge_and_primer")
    def _():
        alb, h = td.scene(seed=2)
        yy, xx = np.mgrid[:160, :160]
        dist = np.abs(yy - 0.3 * xx - 40) / np.hypot(1, 0.3)
        along = (xx > 10) & (xx < 150)
        h += np.where(along & (dist < 6), 12.0 * 0.5 * (1 + np.cos(np.pi * dist / 6)), 0).astype(np.float32)
        rho = td.rho_map((160, 160), (120, 40), 12)
        alb[rho < 1] = td.PRIMER
        h[rho < 1] -= 1.5
        return alb, h, {}

    @add("weave_and_dome")
    def _():
        alb, h = td.scene((240, 240), seed=4)
        yy, xx = np.mgrid[:240, :240] * px
        k = 2 * np.pi / 450.0
        h += (3.0 * np.sin(k * xx) * np.sin(k * yy)).astype(np.float32)
        td.add_dome(alb, h, (120, 120), 150.0, px, weak=True)
        return alb, h, {}

    @add("two_scale_weave")
    def _():
        alb, h = td.scene((240, 240), seed=14)
        yy, xx = np.mgrid[:240, :240] * px
        u = xx * np.cos(0.35) + yy * np.sin(0.35)
        v = -xx * np.sin(0.35) + yy * np.cos(0.35)
        k1, k2 = 2 * np.pi / 1100.0, 2 * np.pi / 210.0
        h += (8.0 * np.sin(k1 * u) * np.sin(k1 * v) + 2.0 * np.sin(k2 * u + 1) * np.sin(k2 * v)).astype(np.float32)
        td.add_profile(h, (120, 120), 150.0, px, 30.0, "dome")
        return alb, h, {}

    for pmode in ("default", "off"):
        @add(f"holes_in_measurement_{pmode}")
        def _(pmode=pmode):
            alb, h = td.scene((160, 200), seed=3)
            td.add_dome(alb, h, (50, 50), 150.0, px)
            td.add_dome(alb, h, (110, 50), 150.0, px)
            yy, xx = np.mgrid[:160, :200]
            h += (10.0 * np.exp(-((yy - 100) ** 2 + (xx - 140) ** 2) / (2 * 1.5 ** 2))).astype(np.float32)
            normals = td.normals_of(h, px)
            hole = np.zeros((160, 200), bool)
            hole[100, 130:150] = True
            hole[50, 55:57] = True
            alb[hole] = np.nan
            normals[hole] = np.nan
            mask = np.ones((160, 200), bool)
            mask[90:130, :51] = False
            p = DetectionParams(max_mismatch=np.inf) if pmode == "off" else None
            return alb, h, dict(normals=normals, mask=mask, params=p)

    for col in (84.0, 82.0):
        @add(f"dome_at_crack_{int(col)}")
        def _(col=col):
            alb, h, normals, band = td.dome_at_a_crack(0, col, px)
            yy, xx = np.mgrid[:160, :160]
            h += (10.0 * np.exp(-((yy - 30) ** 2 + (xx - 84) ** 2) / (2 * 1.5 ** 2))).astype(np.float32)
            return alb, h, dict(normals=normals, left_out=band)

    @add("crater_mesa_dark")
    def _():
        alb, h = td.scene((200, 300), seed=11)
        td.add_profile(h, (60, 60), 360.0, px, 70.0, "crater")
        td.add_profile(h, (60, 200), 360.0, px, 70.0, "mesa")
        rho = td.add_profile(h, (150, 120), 240.0, px, 50.0, "dome")
        alb[rho < 1] *= 0.55
        return alb, h, {}

    @add("touching_pair")
    def _():
        alb, h = td.scene((200, 200), seed=13)
        w1, w2 = 300.0, 210.0
        d = 0.75 * (w1 + w2) / 2 / px
        big, small = np.zeros_like(h), np.zeros_like(h)
        td.add_profile(big, (100, 100 - d / 2), w1, px, 75.0, "dome")
        td.add_profile(small, (100, 100 + d / 2), w2, px, 50.0, "dome")
        h += np.maximum(big, small)
        return alb, h, {}

    for seed, off, shoulder in ((0, 0.0, True), (2, 0.5, False)):
        @add(f"dome_on_flank_{seed}_{'shoulder' if shoulder else 'weak'}")
        def _(seed=seed, off=off, shoulder=shoulder):
            alb, h, *_ = td.dome_on_a_flank(seed, off)
            return alb, h, {} if shoulder else dict(params=DetectionParams(shoulder_width_um=0))

    @add("lumpy_crater")
    def _():
        alb, h = td.scene((100, 100), seed=1)
        td.lumpy_crater(h, (50.4, 50.28), 150.0, px)
        return alb, h, {}

    @add("rippled_pile")
    def _():
        alb, h = td.scene((100, 100), seed=0)
        td.rippled_pile(h, (50.2, 50.4), px, angle=0.8)
        return alb, h, {}

    @add("cluster_on_cupped_paint_shapes")
    def _():
        alb, h, big_c, sc = td.shouldered_dome(1, 0.75, 20.0)
        td.add_profile(h, (40, 180), 300.0, px, 40.0, "mesa")
        return alb, h, {}

    for k in ("default", "no_stroke_rule"):
        @add(f"rippled_stroke_with_domes_{k}")
        def _(k=k):
            shape = (200, 520)
            alb, h = td.scene(shape)
            h += td.rippled_stroke(shape, px, row=100)
            td.add_dome(alb, h, (100, 260), 150.0, px, weak=True)
            td.add_dome(alb, h, (40, 100), 150.0, px, weak=True)
            return alb, h, {} if k == "default" else dict(params=DetectionParams(stroke_slope_k=0))

    for seed, col, normals in ((0, 200, False), (2, 300, True)):
        @add(f"bump_on_stroke_{seed}_{col}")
        def _(seed=seed, col=col, normals=normals):
            shape = (200, 520)
            alb, h = td.scene(shape, seed=seed)
            h += td.rippled_stroke(shape, px, row=100, width_um=180.0, height_um=20.0, ripple=0.2)
            stroke_normals = td.normals_of(h, px)
            td.add_profile(h, (102, col), 100.0, px, 25.0, "dome")
            return alb, h, dict(normals=stroke_normals) if normals else {}

    @add("bump_on_stroke_among_holes")
    def _():
        shape, col = (200, 520), 300
        alb, h = td.scene(shape, seed=1)
        h += td.rippled_stroke(shape, px, row=100, width_um=180.0, height_um=20.0, ripple=0.2)
        td.add_profile(h, (102, col), 100.0, px, 25.0, "dome")
        for t in np.radians(np.arange(0, 360, 45)):
            alb[int(round(102 + 4 * np.sin(t))), int(round(col + 4 * np.cos(t)))] = np.nan
        return alb, h, {}

    @add("steep_ripples")
    def _():
        shape = (200, 520)
        alb, h = td.scene(shape, seed=5)
        h += td.rippled_stroke(shape, px, row=100, width_um=300.0, height_um=40.0, ripple=0.35)
        return alb, h, {}

    @add("dome_and_segment_on_stroke_flank")
    def _():
        shape = (200, 520)
        alb, h = td.scene(shape, seed=1)
        h += td.rippled_stroke(shape, px, row=100, width_um=400.0, height_um=40.0, ripple=0.0)
        td.add_dome(alb, h, (90, 200), 90.0, px)
        td.glowing_segment(alb, h, (90, 380), px, width_um=90.0, length_um=300.0, height_um=22.5)
        return alb, h, {}

    @add("dome_on_stroke_cut_by_crack")
    def _():
        shape = (200, 520)
        alb, h = td.scene(shape, seed=0)
        h += td.rippled_stroke(shape, px, row=120, width_um=300.0, height_um=30.0, ripple=0.0)
        td.cracked_paint(h, px, col=260, row=120)
        td.add_dome(alb, h, (120, 265), 200.0, px)
        return alb, h, {}

    @add("pocket_between_touching_and_cut_bump")
    def _():
        shape = (200, 400)
        alb, h = td.scene(shape, seed=1)
        td.cracked_paint(h, px, col=300, row=100)
        centres = [(100, 100.5), (96, 94.5), (99, 106.5)]
        widths, heights = [90.0, 135.0, 150.0], [18.0, 25.0, 45.0]
        rhos = [td.rho_map(shape, c, w / 2 / px) for c, w in zip(centres, widths)]
        h += np.max([z * np.where(rho < 1, np.clip(1 - rho ** 2, 0, None) ** 1.2, 0)
                     for rho, z in zip(rhos, heights)], axis=0).astype(np.float32)
        for rho, w in zip(rhos, widths):
            wgt = np.clip((1 - rho) * w / 2 / px, 0, 1)[..., None]
            alb[:] = alb * (1 - wgt) + td.SOAP * wgt
        rho = td.rho_map(shape, (150, 350), 200.0 / 2 / px)
        h += (30.0 * np.where(rho < 1, np.clip(1 - rho ** 2, 0, None) ** 1.2, 0)).astype(np.float32)
        return alb, h, {}

    for seed, gap, col in ((0, 2, 200), (1, 3, 12)):
        @add(f"mesa_beside_steep_stroke_{seed}")
        def _(seed=seed, gap=gap, col=col):
            shape = (200, 400)
            alb, h = td.scene(shape, seed=seed)
            h += td.steep_stroke(shape, row=100, width_px=16, height_um=40.0, flank_px=3)
            td.add_profile(h, (100 + 8 + gap + 3, col), 90.0, px, 22.0, "mesa")
            return alb, h, {}

    @add("small_image_other_pixel_size")
    def _():
        alb, h = td.scene((64, 80), seed=7)
        td.add_dome(alb, h, (30, 40), 200.0, 5.0)
        return alb, h, dict(pixel_size_um=5.0)

    return out


def bench_scene(name: str, seed: int, shape) -> tuple:
    """The benchmark's scene on the generator's truth (as ``benchmark_detection.run_seed``)."""
    from benchmark_detection import SCENES
    from uvps.testing.synthetic import SyntheticSpec, make_capture

    spec = SyntheticSpec.realistic("top", shape=tuple(shape), seed=seed, **SCENES[name])
    cap = make_capture(spec, n_lights=3, noise=False, cast_shadows=False)
    return cap.albedo, cap.height_um, dict(normals=cap.normals, pixel_size_um=spec.pixel_size_um)


def _plain(v):
    """A diagnostics value as JSON (floats by repr: exact)."""
    if isinstance(v, dict):
        return {k: _plain(x) for k, x in v.items()}
    if isinstance(v, (list, tuple)):
        return [_plain(x) for x in v]
    if isinstance(v, (np.integer,)):
        return int(v)
    if isinstance(v, (np.floating, float)):
        return float(v)
    return v


def outputs(albedo, height, kwargs) -> dict:
    """What is pinned of one detection: arrays, and one JSON text of the rest (the rejection
    table's prose is documentation and left out; its names, in order, are pinned)."""
    from uvps.core.detect import detect_protrusions

    kw = dict(kwargs)
    kw.setdefault("pixel_size_um", 15.0)
    det = detect_protrusions(albedo, height, **kw)
    diag = dict(det.diagnostics)
    cl = diag.pop("candidate_labels", np.zeros(det.labels.shape, np.int32))
    reasons = diag.pop("candidate_reasons", np.zeros(0, "<U13"))
    diag["rejection_rules"] = [r["name"] for r in diag.get("rejection_rules", [])]
    rest = {"diagnostics": _plain(diag), "rejected": _plain(det.rejected),
            "noise_um": float(det.noise_um)}
    return {"labels": det.labels, "candidate_labels": np.asarray(cl),
            "candidate_reasons": np.asarray(reasons, dtype="<U13"),
            "source": np.asarray(det.source, dtype="<U13"),
            "mask_albedo": np.packbits(det.mask_albedo), "mask_height": np.packbits(det.mask_height),
            "rest": np.asarray(json.dumps(rest, sort_keys=True))}


def all_scenes(full: bool) -> dict:
    """name -> builder: the unit scenes and the benchmark's (quick size), or the full-size
    benchmark scenes alone."""
    scenes = {} if full else {f"unit/{k}": v for k, v in unit_scenes().items()}
    shape = FULL_SHAPE if full else QUICK_SHAPE
    for name in BENCH_SCENES:
        for seed in SEEDS:
            scenes[f"bench/{name}/{seed}"] = (lambda n=name, s=seed: bench_scene(n, s, shape))
    return scenes


def compute(full: bool, only=None) -> dict:
    out = {}
    for name, build in all_scenes(full).items():
        if only is not None and name not in only:
            continue
        for key, value in outputs(*build()).items():
            out[f"{name}::{key}"] = value
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--full", action="store_true", help="also the full-size benchmark scenes")
    args = ap.parse_args(argv)
    GOLDEN.mkdir(parents=True, exist_ok=True)
    for full, path in ((False, QUICK), (True, FULL)):
        if full and not args.full:
            continue
        data = compute(full)
        tmp = path.with_name(path.stem + ".tmp.npz")
        np.savez_compressed(tmp, **data)
        tmp.replace(path)
        print(f"{path.relative_to(ROOT)}: {len(data)} arrays, {path.stat().st_size / 1e3:.0f} kB")
    return 0


if __name__ == "__main__":
    sys.exit(main())
