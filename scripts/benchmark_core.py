#!/usr/bin/env python
"""Accuracy, speed and memory benchmark of the photometric-stereo core.

What is measured is what users run: every result comes from :func:`uvps.core.pipeline.run` (in process,
on :meth:`uvps.testing.synthetic.SyntheticCapture.as_capture`, the capture a file read gives) or from the
``uvps run`` command (parts 2 and 3), with the options of ``uvps run``: ``RunOptions()`` defaults
(additive term measured, degree-4 drop-off fits, lamps refined, Frankot-Chellappa integration, not
robust), except what a row deliberately varies, said where it does. Stage times are the run's own
(``RunResult.timings_s``).

Part 1 (accuracy, synthetic captures with ground truth): ``run(stages=("normals", "height"))`` three
times per seed: lights estimated from the images (defaults), the paper's equidistant solution
(``RunOptions(refine_lights=False)``), and the true lamps (``as_capture(lights="positions")``, as a
calibrated positions file gives them); light direction error, normals' angular error, protrusion
heights from the run's height map.
Part 2 (``--big``, real size): a 4000 x 3000, 16-light RGB uint16 capture written as TIFFs; wall time
and peak RSS of reading it and of ``uvps run`` (estimated and known lights), each in a fresh process.
Part 3 (real data in /work/shared/data, skipped when absent): ``uvps run`` on the RTI and bust
captures, and the agreement of normals from disjoint halves of the lights (``run`` on the even-indexed
and on the odd-indexed images with their lights, as a user with half the images would).

Prints Markdown (one section per part, with the command line) and writes it to ``--out`` if given.
This script only measures; it does not change the core.

    .venv/bin/python scripts/benchmark_core.py                 # parts 1 and 3
    .venv/bin/python scripts/benchmark_core.py --big --parts 2 # part 2 only
    .venv/bin/python scripts/benchmark_core.py --quick         # smoke run
"""
from __future__ import annotations

import argparse
import json
import os
import shlex
import shutil
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from uvps.files.io import read_capture
from uvps.core.pipeline import RunOptions, run
from uvps.testing.synthetic import make_capture, write_capture

DATA = Path("/work/shared/data")
VENV_BIN = Path(sys.executable).parent


# --------------------------------------------------------------------------------------------
# helpers
# --------------------------------------------------------------------------------------------

def angle_deg(a, b):
    """Per-row angle (deg) between two arrays of vectors (..., 3); NaN where either is not finite."""
    a = np.asarray(a, np.float64)
    b = np.asarray(b, np.float64)
    na = np.linalg.norm(a, axis=-1)
    nb = np.linalg.norm(b, axis=-1)
    c = np.einsum("...i,...i->...", a, b) / (na * nb)
    return np.degrees(np.arccos(np.clip(c, -1.0, 1.0)))


def load_line():
    l1, l5, l15 = os.getloadavg()
    return f"load average {l1:.2f} / {l5:.2f} / {l15:.2f} (1/5/15 min), {os.cpu_count()} CPUs"


def command_line():
    return " ".join(shlex.quote(a) for a in [".venv/bin/python", "scripts/benchmark_core.py"] + sys.argv[1:])


def md_table(header, rows):
    out = ["| " + " | ".join(header) + " |", "|" + "|".join("---" for _ in header) + "|"]
    for r in rows:
        out.append("| " + " | ".join(str(v) for v in r) + " |")
    return "\n".join(out)


def uvps_cmd():
    exe = VENV_BIN / "uvps"
    return [str(exe)] if exe.exists() else [sys.executable, "-m", "uvps"]


@dataclass
class ProcStats:
    wall_s: float
    maxrss_mb: float
    returncode: int
    stderr_tail: str


def measure(cmd, *, cwd=None) -> ProcStats:
    """Run ``cmd`` in a fresh process; wall time and its peak RSS.

    Through ``/usr/bin/time -v`` when present: ``os.wait4`` on a child forked from this (large)
    process would report this process's own high-water mark, which Linux carries across exec.
    """
    timer = shutil.which("time", path="/usr/bin:/bin")
    full = ([timer, "-v"] if timer else []) + list(cmd)
    t0 = time.perf_counter()
    with tempfile.TemporaryFile() as err:
        p = subprocess.Popen(full, cwd=cwd, stdout=subprocess.DEVNULL, stderr=err)
        _, status, ru = os.wait4(p.pid, 0)
        p.returncode = os.waitstatus_to_exitcode(status)
        wall = time.perf_counter() - t0
        err.seek(0)
        text = err.read().decode(errors="replace")
    rss_kb = ru.ru_maxrss  # Linux: KiB
    if timer:
        for line in text.splitlines():
            if "Maximum resident set size" in line:
                rss_kb = float(line.rsplit(":", 1)[1])
            if "Elapsed (wall clock)" in line:
                wall = _clock_s(line.rsplit(": ", 1)[1])
        text = text.split("\tCommand being timed")[0]
        if "Command exited with non-zero status" in text:
            text = text.split("Command exited with non-zero status")[0]
    return ProcStats(wall, rss_kb / 1024.0, p.returncode, text[-400:])


def _clock_s(s):
    parts = [float(v) for v in s.strip().split(":")]
    return sum(v * 60 ** i for i, v in enumerate(reversed(parts)))


# --------------------------------------------------------------------------------------------
# part 1: accuracy on synthetic captures
# --------------------------------------------------------------------------------------------

def _disc_ring_stat(depth, x, y, width_px):
    """max(depth in the footprint disc) - median(depth in the ring 0.5-1.0 widths outside its edge).

    Disc radius = width / 2; ring radii from width to 1.5 width (from the centre).
    """
    M, N = depth.shape
    R = 1.5 * width_px + 1
    r0, r1 = max(0, int(np.floor(y - R))), min(M, int(np.ceil(y + R)) + 1)
    c0, c1 = max(0, int(np.floor(x - R))), min(N, int(np.ceil(x + R)) + 1)
    rr, cc = np.mgrid[r0:r1, c0:c1]
    d = np.hypot(rr - y, cc - x)
    win = depth[r0:r1, c0:c1]
    disc = (d <= max(width_px / 2, 0.75)) & np.isfinite(win)
    ring = (d >= width_px) & (d <= 1.5 * width_px) & np.isfinite(win)
    if not disc.any() or ring.sum() < 5:
        return np.nan
    return float(win[disc].max() - np.median(win[ring]))


def protrusion_errors(depth, truth_height, prot, px_um, min_width_um=100.0):
    sel = np.flatnonzero(np.asarray(prot["width_um"]) >= min_width_um)
    ours, ref, rec = [], [], []
    for i in sel:
        x, y = float(prot["x_px"][i]), float(prot["y_px"][i])
        w = float(prot["width_um"][i]) / px_um
        ours.append(_disc_ring_stat(depth, x, y, w))
        ref.append(_disc_ring_stat(truth_height, x, y, w))
        rec.append(float(prot["height_um"][i]))
    ours, ref, rec = map(np.asarray, (ours, ref, rec))
    ok = np.isfinite(ours) & np.isfinite(ref) & (ref > 0) & (rec > 0)
    return {
        "n": int(ok.sum()),
        "rel_vs_measure": np.abs(ours[ok] - ref[ok]) / ref[ok],
        "rel_vs_recorded": np.abs(ours[ok] - rec[ok]) / rec[ok],
        "measure_vs_recorded": np.abs(ref[ok] - rec[ok]) / rec[ok],
    }


def normals_error(est, truth):
    a = angle_deg(est, truth)
    ok = np.isfinite(a)
    return float(a[ok].mean()), float(np.median(a[ok])), float(np.percentile(a[ok], 95)), int((~ok).sum())


#: Part 1's runs: name -> (RunOptions, lights of the capture). Only the lights vary; the rest is
#: what ``uvps run`` does by default.
PART1_VARIANTS = {
    "estimated (refined)": (RunOptions(), "estimate"),
    "estimated (equidistant, paper)": (RunOptions(refine_lights=False), "estimate"),
    "true lights": (RunOptions(), "positions"),
}


def part1(shape, seeds, n_lights=12, px=15.0, fixed_exposure=False):
    rows_l, rows_n, rows_h, rows_t = [], [], [], []
    agg = {}
    for seed in seeds:
        t0 = time.perf_counter()
        cap = make_capture(shape=shape, n_lights=n_lights, seed=seed, pixel_size_um=px,
                           fixed_exposure=fixed_exposure)
        t_make = time.perf_counter() - t0
        P = cap.light_positions_mm
        D_true = P / np.linalg.norm(P, axis=1, keepdims=True)
        t_lights = {}
        for name, (options, lights) in PART1_VARIANTS.items():
            res = run(cap.as_capture(lights=lights), options, stages=("normals", "height"))
            t_lights[name] = res.timings_s["lights"]
            model = res.lights.model
            dir_err = angle_deg(model.directions, D_true)
            pos_err = (np.linalg.norm(model.positions_mm - P, axis=1) if model.positions_mm is not None
                       else np.full(len(P), np.nan))
            E_rel = model.intensities / np.median(model.intensities)
            E_true = cap.intensities / np.median(cap.intensities)
            if name != "true lights":
                rows_l.append([seed, name, f"{dir_err.mean():.2f}", f"{dir_err.max():.2f}",
                               f"{np.median(pos_err):.1f}", f"{np.abs(E_rel / E_true - 1).mean() * 100:.1f}"])
            mean, med, p95, n_nan = normals_error(res.stereo.normals, cap.normals)
            rows_n.append([seed, name, f"{mean:.3f}", f"{med:.3f}", f"{p95:.2f}", n_nan,
                           f"{res.timings_s['normals']:.1f}"])
            pe = protrusion_errors(res.height.height_um, cap.height_um, cap.protrusions, px)
            rows_h.append([seed, name, pe["n"], f"{np.median(pe['rel_vs_measure']) * 100:.1f}",
                           f"{np.median(pe['rel_vs_recorded']) * 100:.1f}",
                           f"{np.median(pe['measure_vs_recorded']) * 100:.1f}"])
            a = agg.setdefault(name, {"dir": [], "nrm": [], "h_meas": [], "h_rec": []})
            a["dir"].append(dir_err.mean())
            a["nrm"].append(mean)
            a["h_meas"].append(pe["rel_vs_measure"])
            a["h_rec"].append(pe["rel_vs_recorded"])
            del res
        rows_t.append([seed, f"{t_make:.1f}", f"{t_lights['estimated (refined)']:.1f}",
                       f"{t_lights['estimated (equidistant, paper)']:.1f}"])
        del cap
    summary = []
    for name, a in agg.items():
        hm = np.median(np.concatenate(a["h_meas"])) * 100
        hr = np.median(np.concatenate(a["h_rec"])) * 100
        d = "-" if name == "true lights" else f"{np.mean(a['dir']):.2f}"
        nt = "< 0.5" if name == "true lights" else "< 1"
        summary.append([name, d, "< 2" if name != "true lights" else "-", f"{np.mean(a['nrm']):.3f}", nt,
                        f"{hm:.1f}", f"{hr:.1f}", "15"])
    M, N = shape
    txt = [f"## Part 1: accuracy on synthetic captures ({N} x {M}, {n_lights} lights, {px:g} um/px, "
           f"seeds {', '.join(map(str, seeds))}"
           + ("; one lamp at one exposure, irradiance at the centre ~ 1/distance^2" if fixed_exposure else "")
           + ")", "",
           "Summary over seeds (light direction error: angle between estimated and true unit vectors from "
           "the image centre, mean over lights; normals: mean angular error over all solved pixels; "
           "protrusion height: median relative error over protrusions >= 100 um wide of all seeds, "
           "height = max of the depth in the footprint disc (radius width/2) - median of the depth in the "
           "ring 1.0-1.5 widths from the centre, compared with the same statistic on the true height map "
           "and with the recorded height_um):", "",
           md_table(["lights", "light dir. err (deg)", "target", "normals mean err (deg)", "target",
                     "height err vs same measure on truth (%)", "height err vs recorded height (%)",
                     "target (%)"], summary), "",
           "Lights per seed (position error: median |P_est - P_true| in mm; intensity: mean |E_est/E_true - 1| "
           "after normalising both to median 1):", "",
           md_table(["seed", "lights", "dir. err mean (deg)", "dir. err max (deg)", "pos. err median (mm)",
                     "intensity err (%)"], rows_l), "",
           "Normals per seed (last column: the run's normals stage, `timings_s[\"normals\"]`):", "",
           md_table(["seed", "lights", "mean (deg)", "median (deg)", "95th pct (deg)", "NaN px",
                     "solve_normals (s)"], rows_n), "",
           "Protrusion heights per seed (median relative error, %; last column: the measure itself on the "
           "true height map vs the recorded height, for reference):", "",
           md_table(["seed", "lights", "n (>= 100 um)", "vs measure on truth", "vs recorded", "measure vs recorded"],
                    rows_h), "",
           "Times (s): make_capture, estimate lights refined, estimate lights equidistant only (the run's "
           "lights stage, `timings_s[\"lights\"]`):", "",
           md_table(["seed", "make_capture", "lights refined", "lights equidistant"], rows_t), ""]
    return "\n".join(txt)


# --------------------------------------------------------------------------------------------
# part 2: real-size speed and memory
# --------------------------------------------------------------------------------------------

def part2(workdir: Path, shape=(3000, 4000), n_lights=16, keep=False):
    folder = workdir / "capture"
    t0 = time.perf_counter()
    scene = "make_capture"
    cap = make_capture(shape=shape, n_lights=n_lights, seed=0)
    t_make = time.perf_counter() - t0
    t0 = time.perf_counter()
    write_capture(cap, folder, truth=False)
    t_write = time.perf_counter() - t0
    raw_bytes = cap.images.nbytes
    del cap
    files = sorted(folder.glob("uv_*.tif"))
    disk = sum(f.stat().st_size for f in files)
    read_code = f"from uvps.files.io import read_capture; read_capture({str(folder)!r})"
    runs = {
        "(a) read_capture(folder)": [sys.executable, "-c", read_code],
        "(b) uvps run folder -o out (estimated lights)": uvps_cmd() + ["run", str(folder), "-o",
                                                                        str(workdir / "out_est")],
        "(c) uvps run folder -o out --lights lights_positions_mm.csv": uvps_cmd() + [
            "run", str(folder), "-o", str(workdir / "out_known"), "--lights",
            str(folder / "lights_positions_mm.csv")],
    }
    rows, stats, loads = [], {}, []
    for name, cmd in runs.items():
        loads.append(f"{name}: before, {load_line()}")
        st = measure(cmd)
        stats[name] = st
        timings = ""
        run_json = None
        if "out_est" in " ".join(cmd):
            run_json = workdir / "out_est" / "run.json"
        elif "out_known" in " ".join(cmd):
            run_json = workdir / "out_known" / "run.json"
        if run_json is not None and run_json.exists():
            t = json.loads(run_json.read_text()).get("timings_s", {})
            timings = ", ".join(f"{k} {v:.0f}" for k, v in t.items())
        read_wall = stats["(a) read_capture(folder)"].wall_s
        rows.append([name, "ok" if st.returncode == 0 else f"exit {st.returncode}", f"{st.wall_s:.1f}",
                     f"{st.maxrss_mb / 1024:.2f}", f"{st.maxrss_mb * 2 ** 20 / raw_bytes:.2f}",
                     f"{st.wall_s / read_wall:.1f}", timings])
        if st.returncode != 0:
            rows[-1][-1] += " stderr: " + st.stderr_tail.replace("\n", " ").replace("|", "/")[-200:]
    loads.append(f"after: {load_line()}")
    M, N = shape
    txt = [f"## Part 2: real-size speed and memory ({N} x {M}, {n_lights} lights, RGB uint16)", "",
           f"Scene: `{scene}(shape=({M}, {N}), n_lights={n_lights}, seed=0)` in {t_make:.0f} s, written as "
           f"{len(files)} uncompressed RGB uint16 TIFFs in {t_write:.1f} s (into the page cache, so the read below is warm); raw stack {raw_bytes / 2 ** 30:.3f} GiB "
           f"({raw_bytes / 1e9:.2f} GB), {disk / 1e9:.2f} GB on disk. Each line is a fresh process; peak RSS is "
           "that process's maximum resident set size from `/usr/bin/time -v`. The float32 stack alone is 2x the "
           "raw stack.", "",
           md_table(["process", "status", "wall (s)", "peak RSS (GiB)", "peak RSS / raw stack (target < 3)",
                     "wall / read wall", "stage timings from run.json (s)"], rows), "",
           "Load while measuring:", ""] + [f"- {s}" for s in loads] + [""]
    if not keep:
        shutil.rmtree(workdir, ignore_errors=True)
    return "\n".join(txt)


# --------------------------------------------------------------------------------------------
# part 3: real captures
# --------------------------------------------------------------------------------------------

def light_subset(cap, idx):
    """The capture of the images ``idx`` only, with their lights (what a user with those images reads)."""
    idx = np.asarray(idx)
    pick = lambda a: None if a is None else np.asarray(a)[idx]   # noqa: E731
    return replace(cap, images=np.stack([np.asarray(cap.images[int(k)]) for k in idx]),
                   files=[cap.files[int(k)] for k in idx], light_directions=pick(cap.light_directions),
                   light_positions_mm=pick(cap.light_positions_mm), light_intensities=pick(cap.light_intensities))


def half_agreement(images_arg, lp, px, saturation_ok=True):
    """Normals of ``run`` on the even- and odd-indexed images (far lights from the .lp) vs each other and
    vs all of them."""
    cap = read_capture(images_arg, lights=lp, pixel_size_um=px)
    K = cap.images.shape[0]
    out = {}
    for name, idx in (("all", np.arange(K)), ("even", np.arange(0, K, 2)), ("odd", np.arange(1, K, 2))):
        sub = cap if name == "all" else light_subset(cap, idx)
        out[name] = run(sub, RunOptions(), stages=("normals",)).stereo.normals
    valid = np.isfinite(out["all"]).all(-1) & np.isfinite(out["even"]).all(-1) & np.isfinite(out["odd"]).all(-1)
    r = {"K": K, "shape": cap.images.shape[1:3], "valid": int(valid.sum())}
    for a, b in (("even", "odd"), ("even", "all"), ("odd", "all")):
        ang = angle_deg(out[a][valid], out[b][valid])
        r[f"{a}-{b}"] = (float(ang.mean()), float(np.median(ang)))
    return r


def part3(workdir: Path):
    if not DATA.is_dir():
        return "## Part 3: real captures\n\nSkipped: /work/shared/data is not present.\n"
    rows, rows_h, notes = [], [], []
    jobs = []
    icon = DATA / "painted_icon_rti"
    if icon.is_dir():
        jobs.append(("painted_icon_rti", [str(icon)], ["--lights", str(icon / "dirs.lp"), "--pixel-size-um", "100"],
                     (str(icon), str(icon / "dirs.lp"), 100.0)))
    lion = DATA / "lion_relief_rti"
    if lion.is_dir():
        jobs.append(("lion_relief_rti", [str(lion / "jpg")], ["--lights", str(lion / "dirs.lp"),
                                                               "--pixel-size-um", "100"],
                     (str(lion / "jpg"), str(lion / "dirs.lp"), 100.0)))
    bust = DATA / "bust_3lights"
    bust_json = None
    if bust.is_dir():
        S = np.loadtxt(bust / "S_xright_yup.txt")
        bust_json = workdir / "bust_lights.json"
        names = [f"image_{i + 1}.png" for i in range(len(S))]
        bust_json.write_text(json.dumps({"mode": "far", "lights": [
            {"file": n, "direction": [float(v) for v in s], "position_mm": None,
             "intensity": float(np.linalg.norm(s))} for n, s in zip(names, S)]}, indent=1))
        jobs.append(("bust_3lights", [str(bust / n) for n in names],
                     ["--lights", str(bust_json), "--mask", str(bust / "mask.png"), "--pixel-size-um", "100"],
                     None))
        # degree 2: the default degree-4 drop-off fit on a masked object extrapolates wildly outside it
        jobs.append(("bust_3lights_degree2", [str(bust / n) for n in names],
                     ["--lights", str(bust_json), "--mask", str(bust / "mask.png"), "--pixel-size-um", "100",
                      "--degree", "2"], None))
    cmds = []
    for name, imgs, opts, half in jobs:
        out = workdir / f"run_{name}"
        cmd = uvps_cmd() + ["run"] + imgs + ["-o", str(out)] + opts
        cmds.append(" ".join(shlex.quote(c) for c in ["uvps"] + cmd[len(uvps_cmd()):]))
        st = measure(cmd)
        info = ""
        if st.returncode == 0 and (out / "run.json").exists():
            rj = json.loads((out / "run.json").read_text())
            n_img = len(rj.get("inputs", []))
            warn = "; ".join(rj.get("warnings", []))[:120]
            info = f"{n_img} inputs; lights: {rj.get('diagnostics', {}).get('lights', {}).get('source')}; {warn}"
            import tifffile
            nrm = tifffile.imread(out / "normals.tif")
            dep = tifffile.imread(out / "depth.tif")
            fin = np.isfinite(nrm).all(axis=0)
            info += f"; normals shape {nrm.shape}, {fin.mean() * 100:.1f} % solved, mean nz {np.nanmean(nrm[2]):.3f}"
            info += f"; depth range {np.nanpercentile(dep, 1):.0f}..{np.nanpercentile(dep, 99):.0f} um (1-99 %)"
        else:
            info = st.stderr_tail.replace("\n", " ").replace("|", "/")[-200:]
        rows.append([name, "ok" if st.returncode == 0 else f"exit {st.returncode}", f"{st.wall_s:.1f}",
                     f"{st.maxrss_mb:.0f}", info])
        if half is not None:
            try:
                r = half_agreement(*half)
                rows_h.append([name, r["K"], f"{r['shape'][1]} x {r['shape'][0]}", r["valid"]]
                              + [f"{r[k][0]:.2f} / {r[k][1]:.2f}" for k in ("even-odd", "even-all", "odd-all")])
            except Exception as exc:  # report and carry on: this is a benchmark, not the core
                rows_h.append([name, "-", "-", "-", f"failed: {exc}", "", ""])
    if bust_json is not None:
        # the lights file gives |S_k| as each lamp's intensity; the pipeline can also measure them from
        # the image levels (--estimate-intensities). Compare those with the intensities folded into S.
        import tifffile
        S = np.loadtxt(bust / "S_xright_yup.txt")
        cap = read_capture([str(bust / f"image_{i + 1}.png") for i in range(3)], mask=str(bust / "mask.png"),
                           pixel_size_um=100.0, lights=str(bust_json))
        E_pipe = run(cap, RunOptions(estimate_intensities=True), stages=()).lights.model.intensities
        E_s = np.linalg.norm(S, axis=1)
        # the run with S's own intensities (as a light file giving them would): only the lights differ
        res = run(replace(cap, light_intensities=E_s), RunOptions(), stages=("normals",)).stereo
        ok_s = np.isfinite(res.normals).all(-1) & cap.mask
        notes.append(f"bust_3lights: intensities measured by the pipeline from the image levels "
                     f"(`--estimate-intensities`) {np.array2string(E_pipe / E_pipe[0], precision=3)} (relative "
                     f"to light 1) vs |S_k| {np.array2string(E_s / E_s[0], precision=3)}. In-process `run` with "
                     f"S's own intensities solves {ok_s.sum()} of {cap.mask.sum()} masked pixels "
                     f"({ok_s.sum() / cap.mask.sum() * 100:.1f} %), mean nz {np.nanmean(res.normals[..., 2][ok_s]):.3f}.")
        for run_name in ("run_bust_3lights", "run_bust_3lights_degree2"):
            cli_path = workdir / run_name / "normals.tif"
            if not cli_path.exists():
                notes[-1] += f" No normals from {run_name[4:]}."
                continue
            cli = np.moveaxis(tifffile.imread(cli_path), 0, -1)
            ang = angle_deg(cli, res.normals)
            ok = np.isfinite(ang)
            notes[-1] += (f" The CLI's normals ({run_name[4:]}) differ from these by {ang[ok].mean():.2f} deg mean, "
                          f"{np.median(ang[ok]):.2f} deg median over {ok.sum()} pixels.")
    txt = ["## Part 3: real captures (/work/shared/data)", "",
           "Commands (run folders in a temp folder):", ""] + [f"    {c}" for c in cmds] + ["",
           md_table(["capture", "status", "wall (s)", "peak RSS (MiB)", "result"], rows), "",
           "Disjoint halves of the lights (in-process `run` with `RunOptions()` on all images, on the "
           "even-indexed and on the odd-indexed ones, far lights from dirs.lp); mean / median angular "
           "difference in degrees over pixels valid in all three solutions:", "",
           md_table(["capture", "lights", "size", "valid px", "even vs odd", "even vs all", "odd vs all"], rows_h),
           ""] + notes + [""]
    return "\n".join(txt)


# --------------------------------------------------------------------------------------------

def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", help="also write the Markdown to this file")
    ap.add_argument("--quick", action="store_true", help="600 x 800, one seed, no part 2")
    ap.add_argument("--big", action="store_true", help="run part 2 (4000 x 3000 x 16 RGB, ~1.2 GB on disk)")
    ap.add_argument("--parts", default=None, help="comma-separated subset of 1,2,3 (2 needs --big)")
    ap.add_argument("--seeds", default="0,1,2")
    ap.add_argument("--fixed-exposure", action="store_true",
                    help="part 1 with one lamp at one exposure (irradiance at the centre ~ 1/distance^2)")
    ap.add_argument("--tmp", default="/tmp", help="where part 2 writes its capture")
    args = ap.parse_args(argv)
    parts = {1, 3} | ({2} if args.big else set())
    if args.parts:
        parts = {int(p) for p in args.parts.split(",")}
        if 2 in parts and not args.big:
            parts.discard(2)
    if args.quick:
        parts.discard(2)
    shape = (600, 800) if args.quick else (1200, 1600)
    seeds = [int(s) for s in args.seeds.split(",")][: 1 if args.quick else None]

    head = ["# uvps photometric-stereo core benchmark", "",
            f"Command: `{command_line()}`", "",
            f"Date: {time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}; {load_line()} at start.", ""]
    sections = []
    t_all = time.perf_counter()
    if 1 in parts:
        sections.append(part1(shape, seeds, fixed_exposure=args.fixed_exposure) + f"\nProduced by: `{command_line()}`\n")
        print(sections[-1], flush=True)
    if 2 in parts:
        work = Path(tempfile.mkdtemp(prefix="uvps_bench_big_", dir=args.tmp))
        try:
            sections.append(part2(work) + f"\nProduced by: `{command_line()}`\n")
        finally:
            shutil.rmtree(work, ignore_errors=True)
        print(sections[-1], flush=True)
    if 3 in parts:
        work = Path(tempfile.mkdtemp(prefix="uvps_bench_real_"))
        try:
            sections.append(part3(work) + f"\nProduced by: `{command_line()}`\n")
        finally:
            shutil.rmtree(work, ignore_errors=True)
        print(sections[-1], flush=True)
    tail = [f"Total {time.perf_counter() - t_all:.0f} s; {load_line()} at the end.", ""]
    text = "\n".join(head + sections + tail)
    if args.out:
        Path(args.out).write_text(text, encoding="utf-8")
    print("\n".join(tail))
    return 0


if __name__ == "__main__":
    sys.exit(main())
