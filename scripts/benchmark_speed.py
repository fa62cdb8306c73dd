"""Speed and memory of a whole run against the time to merely read the stack.

Makes (once, cached in ``--work``) a synthetic capture with :func:`uvps.testing.synthetic.make_capture`
(default 4000 x 3000, 16 lights, RGB uint16 TIFFs, one file per light) or, with ``--tile``, with
:func:`make_tiled` (the same generator in tiles and bands, for a capture it cannot hold in memory),
then measures, each in a fresh process whose peak resident memory is taken from ``os.wait4``'s
rusage:

- reading the stack with tifffile alone (``tifffile.imread`` of each file into one preallocated
  array; file by file into one image buffer when the stack exceeds a quarter of the memory): the
  floor every run is compared with;
- ``uvps run FOLDER -o OUT`` (lights estimated, flat-field, normals, albedo, height), its stages
  from ``run.json``'s ``timings_s``;
- the same with ``--regions auto`` (colour areas, detection, statistics, report);
- the calibrated route, ``uvps run FOLDER --calibration CAL --dark DARK`` (CAL made once by ``uvps
  calibrate --lights`` from the capture's lamp file: positions, no intensities, as a sphere
  calibration gives; DARK the capture's dark frame), alone and with ``--regions auto``;
- ``uvps demo`` (its default 600 x 800 capture, 12 lights);

and optionally (``--profile``) a cProfile of :func:`uvps.core.pipeline.run` in this process, whose top
lines go with the table. Each process's CPU use is its user + system CPU time over its wall time (``os.wait4``'s rusage:
2.0 = both cores busy throughout). The table is printed with the machine (cores, RAM, load) and the
command line. ``--doc`` (the default 4000 x 3000 x 16 capture) also writes docs/benchmarks.md's first
speed table (section ``speed``: :func:`render_doc`: the read, ``uvps run``, the calibrated route, each
with ``--regions auto`` when measured, and ``uvps demo``; each row's CPU / wall and load kept in the JSON) and
docs/benchmarks/speed.json (scripts/benchdoc.py); with ``--shape 1500 2000`` it writes the second
(section ``speed_load``: :func:`render_load_doc`), each row the best (-worst) of the last 3 invocations that
measured it, all kept in docs/benchmarks/speed_load.json. ``--no-md`` is accepted and does nothing (the
commands recorded in docs/benchmarks.md carry it).

Example::

    .venv/bin/python scripts/benchmark_speed.py                      # 4000 x 3000 x 16, ~5 min
    .venv/bin/python scripts/benchmark_speed.py --shape 750 1000 --profile
    # 10000 x 8000 x 16 RGB (7.2 GiB raw, made in tiles), the run alone:
    .venv/bin/python scripts/benchmark_speed.py --shape 8000 10000 --tile 2000 2500 --skip regions demo
"""
from __future__ import annotations

import argparse
import cProfile
import io
import json
import math
import os
import pstats
import shlex
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "cpython_core"))   # the code of this tree (also for --profile)
UVPS = [sys.executable, "-m", "uvps"]   # the command as installed (uvps._entry: its BLAS threads)


DOC_SECTION = "speed"
#: The doc's rows (run_child names) and their labels in docs/benchmarks.md's table.
DOC_ROWS = {"read the stack with tifffile": "read the stack with tifffile", "uvps run": "`uvps run`",
            "uvps run --regions auto": "`uvps run --regions auto`",
            "uvps run --calibration --dark": "`uvps run --calibration CAL --dark DARK`",
            "uvps run --calibration --dark --regions auto": "the same `--regions auto`",
            "uvps demo (600 x 800, 12 lights)": "`uvps demo` (600 x 800, 12 lamps)"}


@dataclass
class Measure:
    name: str
    wall_s: float
    maxrss_gib: float
    returncode: int
    inner_s: float = float("nan")     # time measured inside the child (reading only)
    cpu_s: float = float("nan")       # user + system CPU time of the child
    stages: dict = None
    load_before: str = ""
    stderr_tail: str = ""


def load_line() -> str:
    a, b, c = os.getloadavg()
    return f"{a:.2f} / {b:.2f} / {c:.2f}"


def machine() -> str:
    cpu = "?"
    with open("/proc/cpuinfo", encoding="utf-8") as fh:
        for line in fh:
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    with open("/proc/meminfo", encoding="utf-8") as fh:
        mem_kb = int(fh.readline().split()[1])
    return f"{os.cpu_count()} cores ({cpu}), {mem_kb / 2 ** 20:.1f} GiB RAM"


def make(folder: Path, shape, n_lights: int, seed: int, tile=None) -> float:
    """The synthetic capture in ``folder`` (made once); returns the raw stack's size in bytes."""
    import numpy as np
    import tifffile

    files = sorted(folder.glob("uv_*.tif"))
    if len(files) != n_lights or not (tile or (folder / "dark" / "dark.tif").is_file()):
        from uvps.testing.synthetic import make_capture, write_capture

        t0 = time.perf_counter()
        if tile:
            make_tiled(folder, tuple(shape), n_lights, seed, tuple(tile))
        else:
            cap = make_capture(shape=tuple(shape), n_lights=n_lights, seed=seed)
            write_capture(cap, folder, truth=False, dark_frame=True)     # dark/dark.tif: the calibrated route's
            del cap
        print(f"made {shape} x {n_lights} in {time.perf_counter() - t0:.0f} s", file=sys.stderr)
        files = sorted(folder.glob("uv_*.tif"))
    with tifffile.TiffFile(files[0]) as tif:
        page = tif.pages[0]
        return float(np.prod(page.shape) * np.dtype(page.dtype).itemsize * len(files))


def render_band(height, albedo, r0: int, r1: int, *, pixel_size_um, light_positions_mm, intensities, **kw):
    """``synthetic.render_images`` of rows ``r0:r1`` of a field lit by lamps at ``light_positions_mm``
    from the whole field's centre: the band with one row each side (the normals' central differences),
    the lamps moved by the band's offset from the field's centre and their intensities scaled by
    ``|L|^2 / |L - offset|^2`` (render_images' inverse square is relative to the centre it is given)."""
    import numpy as np
    from uvps.testing.synthetic import render_images

    M = height.shape[0]
    h0, h1 = max(0, r0 - 1), min(M, r1 + 1)
    dy = ((M - 1) / 2.0 - h0 - (h1 - h0 - 1) / 2.0) * pixel_size_um / 1000.0    # the band's centre, mm
    P = np.asarray(light_positions_mm, float)
    L = P - np.array([0.0, dy, 0.0])
    E = np.asarray(intensities, float) * np.sum(P ** 2, axis=1) / np.sum(L ** 2, axis=1)
    out = render_images(height[h0:h1], albedo[h0:h1], pixel_size_um=pixel_size_um, light_positions_mm=L,
                        intensities=E, **kw)
    return out[:, r0 - h0:r1 - h0]


def make_tiled(folder: Path, shape, n_lights: int, seed: int, tile, band_rows: int = 200) -> None:
    """A capture too large for :func:`uvps.testing.synthetic.make_capture` to hold (it needs about 270 bytes
    a pixel: 22 GB for 10000 x 8000), made with the same generator in pieces.

    The painting: ``make_capture`` of each ``tile`` (rows, cols) with its own seed (``seed * 1000 +
    tile index``) and no bow, put side by side (their colour areas, ridges and weave meet at the
    seams, which show as lines of relief), plus one bow over the whole field drawn as
    ``make_capture`` draws it (a quadratic of ``SyntheticSpec.bow_um`` peak to valley). The lamps:
    ``synthetic.light_positions`` and the intensity drift with ``SyntheticSpec``'s defaults. The
    images: ``synthetic.render_images`` band by band (``band_rows`` rows plus one row each side for
    the normals' central differences), each band's lamps moved by the band's offset from the image
    centre and its intensities scaled by ``|L|^2 / |L - offset|^2``, so that every pixel sees the
    lamps of the whole field; the exposure puts the brightest noise-free sample at
    ``exposure_fraction`` of 65535 (a first, noise-free pass); photon and read noise from one
    random stream per band. Written as ``write_capture`` writes (16-bit RGB TIFFs, one per lamp,
    the pixel size in their tags, ``lights_positions_mm.csv``) straight into memory-mapped files.
    Peak memory about the painting's float32 height and albedo (16 bytes a pixel) plus one tile.
    """
    import csv
    import shutil

    import numpy as np
    import tifffile
    from uvps.files.io import release
    from uvps.testing.synthetic import SyntheticSpec, light_positions, make_capture, pixel_centres_mm

    spec = SyntheticSpec()
    M, N = shape
    px = float(spec.pixel_size_um)
    tm, tn = (min(M, int(tile[0])), min(N, int(tile[1])))
    height = np.empty((M, N), np.float32)
    albedo = np.empty((M, N, 3), np.float32)
    for i, r0 in enumerate(range(0, M, tm)):
        for j, c0 in enumerate(range(0, N, tn)):
            r1, c1 = min(M, r0 + tm), min(N, c0 + tn)
            t = make_capture(shape=(r1 - r0, c1 - c0), n_lights=3, seed=seed * 1000 + i * 100 + j, noise=False,
                             bow_um=0.0)
            height[r0:r1, c0:c1] = t.height_um
            albedo[r0:r1, c0:c1] = t.albedo
            del t
    rng = np.random.default_rng(seed)
    x, y = pixel_centres_mm((M, N), px)
    xn, yn = x / np.abs(x).max(), y / np.abs(y).max()
    a, b, c = rng.uniform(0.5, 1), rng.uniform(0.5, 1), rng.uniform(-0.3, 0.3)
    corners = [-(a * u * u + b * v * v + c * u * v) for u in (-1, 0, 1) for v in (-1, 0, 1)]
    lo, span = min(corners), max(corners) - min(corners)     # the quadratic's range over the field
    for r0 in range(0, M, 1000):
        bow = -(a * xn ** 2 + b * yn[r0:r0 + 1000] ** 2 + c * xn * yn[r0:r0 + 1000])
        height[r0:r0 + 1000] += (spec.bow_um * (bow - lo) / span).astype(np.float32)
    positions = light_positions(rng, n_lights=n_lights, elevation_deg=spec.elevation_deg,
                                distance_mm=spec.distance_mm, azimuth_jitter=spec.azimuth_jitter)
    intensities = 1 + rng.uniform(-spec.intensity_jitter, spec.intensity_jitter, n_lights)

    def band(r0, r1, **kw):
        return render_band(height, albedo, r0, r1, pixel_size_um=px, light_positions_mm=positions,
                           intensities=intensities, **kw)

    # the exposure from a noise-free float64 pass (bands of 64 rows: 16 x 66 x N x 3 float64 each)
    peak = max(float(band(r0, min(M, r0 + 64), noise=False, dtype=None, exposure=1.0).max())
               for r0 in range(0, M, 64))
    bands = [(r0, min(M, r0 + band_rows)) for r0 in range(0, M, band_rows)]
    exposure = spec.exposure_fraction * 65535.0 / peak
    tmp = folder.with_name(folder.name + ".tmp")
    shutil.rmtree(tmp, ignore_errors=True)
    tmp.mkdir(parents=True)
    names = [f"uv_{k:02d}.tif" for k in range(n_lights)]
    maps = [tifffile.memmap(tmp / nm, shape=(M, N, 3), dtype=np.uint16, photometric="rgb",
                            resolution=(1 / px, 1 / px), resolutionunit="NONE",
                            description="ImageJ=1.54f\nunit=micron\n", metadata=None) for nm in names]
    for i, (r0, r1) in enumerate(bands):
        imgs = band(r0, r1, rng=np.random.default_rng((seed, i)), noise=spec.noise, gain=65535.0 / spec.full_well_e,
                    read_noise=spec.read_noise, exposure=exposure, dtype=np.uint16)
        for k, mm in enumerate(maps):
            mm[r0:r1] = imgs[k]
            release(mm)
    for mm in maps:
        mm.flush()
    del maps
    with open(tmp / "lights_positions_mm.csv", "w", newline="", encoding="utf-8") as fh:
        wr = csv.writer(fh)
        wr.writerow(["file", "x_mm", "y_mm", "z_mm"])
        for nm, pos in zip(names, positions):
            wr.writerow([nm] + [f"{v:.6f}" for v in pos])
    shutil.rmtree(folder, ignore_errors=True)
    tmp.rename(folder)


def compressed_copy(folder: Path) -> Path:
    """The capture's images re-written Deflate-compressed (tags and light files kept), made once."""
    import shutil

    import tifffile

    out = folder.with_name(folder.name + "_deflate")
    files = sorted(folder.glob("uv_*.tif"))
    if len(sorted(out.glob("uv_*.tif"))) != len(files):
        tmp = folder.with_name(folder.name + "_deflate.part")
        shutil.rmtree(tmp, ignore_errors=True)
        tmp.mkdir()
        for f in files:
            with tifffile.TiffFile(f) as tif:
                page = tif.pages[0]
                res = (page.tags["XResolution"].value, page.tags["YResolution"].value)
                desc = page.description
                data = page.asarray()
            tifffile.imwrite(tmp / f.name, data, compression="zlib", photometric="rgb" if data.ndim == 3 else "minisblack",
                             resolution=(res[0][0] / res[0][1], res[1][0] / res[1][1]), resolutionunit="NONE",
                             description=desc, metadata=None)
        for f in folder.iterdir():
            if f.is_file() and not f.name.startswith("uv_"):
                shutil.copy2(f, tmp / f.name)
        shutil.rmtree(out, ignore_errors=True)
        tmp.rename(out)
    return out


def stack_copy(folder: Path, *, compress: bool) -> Path:
    """The capture's images as ONE multi-page RGB TIFF (``<folder>_stack[_deflate]/stack.tif``, the
    first file's calibration kept), written page by page, made once; returns the stack's path."""
    import shutil

    import tifffile

    files = sorted(folder.glob("uv_*.tif"))
    out = folder.with_name(folder.name + "_stack" + ("_deflate" if compress else ""))
    path = out / "stack.tif"
    if not path.is_file():
        tmp = out.with_name(out.name + ".part")
        shutil.rmtree(tmp, ignore_errors=True)
        tmp.mkdir()
        with tifffile.TiffFile(files[0]) as tif:
            page = tif.pages[0]
            res = (page.tags["XResolution"].value, page.tags["YResolution"].value)
            desc, shape, dtype = page.description, page.shape, page.dtype
        tifffile.imwrite(tmp / "stack.tif", (tifffile.imread(f) for f in files), shape=(len(files),) + shape,
                         dtype=dtype, photometric="rgb", compression="zlib" if compress else None,
                         resolution=(res[0][0] / res[0][1], res[1][0] / res[1][1]), resolutionunit="NONE",
                         description=desc, metadata=None, bigtiff=len(files) * math.prod(shape) * 2 > 2 ** 31)
        shutil.rmtree(out, ignore_errors=True)
        tmp.rename(out)
    return path


#: Reading a one-file stack: into one preallocated array, page by page (a stack above a quarter of
#: the memory: each page into one reused buffer).
READ_STACK_CODE = """
import sys, time, numpy as np, tifffile
each = sys.argv[2] == '1'
t0 = time.perf_counter()
with tifffile.TiffFile(sys.argv[1]) as tif:
    pages = tif.pages
    buf = np.empty(pages[0].shape, pages[0].dtype)
    stack = None if each else np.empty((len(pages),) + pages[0].shape, pages[0].dtype)
    for k, page in enumerate(pages):
        page.asarray(out=buf if each else stack[k])
print('READ_S', time.perf_counter() - t0)
"""


def run_child(name: str, cmd: list, env=None) -> Measure:
    """Run ``cmd``; its wall time and peak RSS (this child only, from ``os.wait4``)."""
    load = load_line()
    t0 = time.perf_counter()
    p = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, env=env, cwd=REPO)
    # read the pipes before waiting (a full pipe would block the child); wait4 gives its rusage
    out, err = p.stdout.read(), p.stderr.read()
    _, status, ru = os.wait4(p.pid, 0)
    wall = time.perf_counter() - t0
    p.returncode = os.waitstatus_to_exitcode(status)
    m = Measure(name, wall, ru.ru_maxrss / 2 ** 20, p.returncode, load_before=load,
                stderr_tail=err.decode(errors="replace")[-400:], cpu_s=ru.ru_utime + ru.ru_stime)
    for line in out.decode(errors="replace").splitlines():
        if line.startswith("READ_S "):
            m.inner_s = float(line.split()[1])
    return m


READ_CODE = """
import sys, time, glob, numpy as np, tifffile
files = sorted(glob.glob(sys.argv[1] + '/uv_*.tif'))
t0 = time.perf_counter()
first = tifffile.imread(files[0])
stack = np.empty((len(files),) + first.shape, first.dtype)
stack[0] = first
for k, f in enumerate(files[1:], 1):
    stack[k] = tifffile.imread(f)
print('READ_S', time.perf_counter() - t0)
"""

#: Reading a stack larger than a quarter of the memory: each file into one reused image buffer (the
#: same bytes read, without holding the stack).
READ_EACH_CODE = """
import sys, time, glob, numpy as np, tifffile
files = sorted(glob.glob(sys.argv[1] + '/uv_*.tif'))
t0 = time.perf_counter()
buf = tifffile.imread(files[0])
for f in files[1:]:
    tifffile.imread(f, out=buf)
print('READ_S', time.perf_counter() - t0)
"""


#: The first touch of memory this process has not used before (GB/s), and the same memory written again:
#: a run's arrays and the files it writes are memory first touched, which the warm read of the stack (into
#: memory its previous read just freed) hardly is. On a virtual machine whose host takes back the memory
#: its guest leaves free for a few seconds the two differ by up to 100x (docs/decisions/speed.md,
#: "Memory first touched").
FIRST_TOUCH_CODE = """
import time, numpy as np
a = np.empty(2 ** 28, np.float32)
t0 = time.perf_counter(); a.fill(1); t1 = time.perf_counter(); a.fill(2); t2 = time.perf_counter()
print('TOUCH_GBPS', 2 ** 30 / 1e9 / (t1 - t0), 2 ** 30 / 1e9 / (t2 - t1))
"""


def first_touch(env, idle_s: float) -> tuple:
    """(first touch, again) in GB/s of 1 GiB in a fresh process started after ``idle_s`` seconds of
    nothing run by this script."""
    time.sleep(idle_s)
    out = subprocess.run([sys.executable, "-c", FIRST_TOUCH_CODE], capture_output=True, text=True, env=env).stdout
    line = next((x for x in out.splitlines() if x.startswith("TOUCH_GBPS ")), None)
    return (float("nan"), float("nan")) if line is None else tuple(float(v) for v in line.split()[1:3])


def profile_run(folder: Path, top: int) -> str:
    """cProfile of read_capture + pipeline.run (the default stages) in this process: the top lines."""
    from uvps.files.io import read_capture
    from uvps.core.pipeline import RunOptions, run

    pr = cProfile.Profile()
    pr.enable()
    cap = read_capture(folder)
    res = run(cap, RunOptions())
    pr.disable()
    s = io.StringIO()
    pstats.Stats(pr, stream=s).sort_stats("tottime").print_stats(top)
    lines = [ln for ln in s.getvalue().splitlines() if ln.strip()]
    start = next(i for i, ln in enumerate(lines) if ln.lstrip().startswith("ncalls"))
    head = [ln for ln in lines[:start] if "function calls" in ln]
    return "\n".join(head + lines[start:start + top + 1]) + "\n\nstages (s): " + json.dumps(res.timings_s)


def table(ms: list, read_s: float, raw: float) -> str:
    rows = ["| process | status | wall (s) | / read | CPU / wall | peak RSS (GiB) | / raw stack | stages (s, run.json) "
            "| load before |",
            "|---|---|---|---|---|---|---|---|---|"]
    for m in ms:
        st = ", ".join(f"{k} {v:.1f}" for k, v in (m.stages or {}).items())
        status = "ok" if m.returncode == 0 else f"exit {m.returncode}"
        rows.append(f"| {m.name} | {status} | {m.wall_s:.1f} | {m.wall_s / read_s:.1f} | {m.cpu_s / m.wall_s:.2f} | "
                    f"{m.maxrss_gib:.2f} | "
                    f"{m.maxrss_gib * 2 ** 30 / raw:.2f} | {st} | {m.load_before} |")
    return "\n".join(rows)


def doc_rows(ms: list, read_s: float, raw: float) -> list:
    """The doc's rows of this invocation: wall (the read's own time inside its process), / read, peak RSS
    over the raw stack (the demo, another capture: its peak RSS in GiB), run.json's stages."""
    out = []
    for m in ms:
        if m.name not in DOC_ROWS or m.returncode:
            continue
        read = m.name == "read the stack with tifffile"
        row = {"name": m.name, "wall_s": read_s if read else m.wall_s,     # stages in run order: a list of pairs
               "stages": [[k, v] for k, v in (m.stages or {}).items()],
               "cpu_ratio": m.cpu_s / m.wall_s, "load_before": m.load_before}
        if m.name.startswith("uvps demo"):
            row["rss_gib"] = m.maxrss_gib
        else:
            row.update(read_ratio=1.0 if read else m.wall_s / read_s, rss_ratio=m.maxrss_gib * 2 ** 30 / raw)
        out.append(row)
    return out


#: The second table's rows (1500 x 2000, under load) and their labels.
LOAD_ROWS = {"read the stack with tifffile": "read the stack with tifffile",
             "uvps run": "`uvps run` (lamps estimated)", "uvps run --regions auto": "`uvps run --regions auto`",
             "uvps run --calibration --dark": "`uvps run --calibration CAL --dark DARK`",
             "uvps run --calibration --dark --regions auto": "the same `--regions auto`"}
#: Invocations a row of the second table keeps (best and worst of them).
LOAD_KEEP = 3


def load_summary(runs: list) -> dict:
    """A row of the second table from its invocations' measures: the fastest's wall, / read, CPU / wall and
    stages, the slowest's wall and CPU / wall, the range of peak RSS (GiB and over the raw stack)."""
    best = min(runs, key=lambda r: r["wall_s"])
    worst = max(runs, key=lambda r: r["wall_s"])
    return {"wall_s": [best["wall_s"], worst["wall_s"]], "read_ratio": best["read_ratio"],
            "cpu_ratio": [best["cpu_ratio"], worst["cpu_ratio"]],
            "rss_gib": [min(r["rss_gib"] for r in runs), max(r["rss_gib"] for r in runs)],
            "rss_ratio": [min(r["rss_ratio"] for r in runs), max(r["rss_ratio"] for r in runs)],
            "stages": best.get("stages", [])}


def render_load_doc(results: dict) -> str:
    """docs/benchmarks.md's second speed table (1500 x 2000, under load): per row the fastest invocation's
    wall (s; the slowest's after a dash in brackets, where it differs), / read, CPU / wall (the slowest's
    likewise), peak RSS and its ratio to the raw stack (their range over the invocations), stages.

    Parameters
    ----------
    results : dict
        ``{"rows": [{"name", "summary": load_summary(...), "runs"?: [...]}]}`` as docs/benchmarks/speed_load.json
        keeps them.
    """
    def pair(v, fmt, sep):
        a, b = fmt.format(v[0]), fmt.format(v[1])
        return a if a == b else (f"{a} (-{b})" if sep == "dash" else f"{a}-{b}")

    lines = ["| process | wall (s) | / read | CPU / wall | peak RSS (GiB) | / raw stack | stages (s, run.json) |",
             "|---|---|---|---|---|---|---|"]
    for r in results["rows"]:
        s = r["summary"]
        read = r["name"].startswith("read ")
        wall = f"{s['wall_s'][0]:.2f} (in process)" if read else pair(s["wall_s"], "{:.1f}", "dash")
        cells = [LOAD_ROWS[r["name"]], wall, f"{s['read_ratio']:.0f}", pair(s["cpu_ratio"], "{:.2f}", "dash"),
                 pair(s["rss_gib"], "{:.2f}", "range"), pair(s["rss_ratio"], "{:.2f}", "range"),
                 ", ".join(f"{k} {v:.1f}" for k, v in s["stages"])]
        lines.append("|" + "|".join(f" {c} " if c else " " for c in cells) + "|")
    return "\n".join(lines) + "\n"


def write_load_doc(ms: list, read_s: float, raw: float, argv) -> Path:
    """``--doc`` at 1500 x 2000: this invocation's measures join each row's last invocations (at most
    :data:`LOAD_KEEP`); the rows are summarised again and the section rewritten."""
    import benchdoc
    path = benchdoc.json_path("speed_load", json_dir=benchdoc.JSON_DIR)
    old = json.loads(path.read_text(encoding="utf-8")) if path.is_file() else {"rows": []}
    kept = {r["name"]: r for r in old["rows"]}
    rows = []
    for name in LOAD_ROWS:
        m = next((m for m in ms if m.name == name and m.returncode == 0), None)
        runs = list(kept.get(name, {}).get("runs", []))
        if m is not None:
            read = name.startswith("read ")
            runs = (runs + [{"wall_s": read_s if read else m.wall_s, "read_ratio": 1.0 if read else m.wall_s / read_s,
                             "cpu_ratio": m.cpu_s / m.wall_s, "rss_gib": m.maxrss_gib,
                             "rss_ratio": m.maxrss_gib * 2 ** 30 / raw, "load_before": m.load_before,
                             "stages": [[k, v] for k, v in (m.stages or {}).items()]}])[-LOAD_KEEP:]
        if runs:
            rows.append({"name": name, "runs": runs, "summary": load_summary(runs)})
        elif name in kept:
            rows.append(kept[name])            # a row only transcribed so far: as it was
    doc = dict(old, rows=rows, argv=list(argv))
    return benchdoc.write_doc("speed_load", doc, render_load_doc(doc), source="scripts/benchmark_speed.py")


def render_doc(results: dict) -> str:
    """docs/benchmarks.md's first speed table (4000 x 3000 x 16): wall (s; bold: ``uvps run``'s, the figure
    of the target "within 10x the read"), / read, CPU / wall (user + system CPU time over wall: at most 2 on
    2 cores), peak RSS / raw stack (a process on another capture, the demo: its peak RSS in GiB, in
    brackets), run.json's stages (s).

    Parameters
    ----------
    results : dict
        ``{"rows": doc_rows(...)}`` as docs/benchmarks/speed.json keeps them.
    """
    lines = ["| process | wall (s) | / read | CPU / wall | peak RSS / raw stack | stages (s) |", "|---|---|---|---|---|---|"]
    for r in results["rows"]:
        wall = f"{r['wall_s']:.2f}" if r["name"].startswith("read ") else f"{r['wall_s']:.1f}"
        if r["name"] == "uvps run":
            wall = f"**{wall}**"
        ratio = f"{r['read_ratio']:.0f}" if "read_ratio" in r else ""
        rss = f"{r['rss_ratio']:.2f}" if "rss_ratio" in r else f"({r['rss_gib']:.2f} GiB)"
        stages = ", ".join(f"{k} {v:.1f}" for k, v in r.get("stages", []))
        cpu = f"{r['cpu_ratio']:.2f}" if math.isfinite(r.get("cpu_ratio", math.nan)) else ""   # NaN: not measured
        cells = [DOC_ROWS[r["name"]], wall, ratio, cpu, rss, stages]
        lines.append("|" + "|".join(f" {c} " if c else " " for c in cells) + "|")
    return "\n".join(lines) + "\n"


#: Section name -> renderer (scripts/benchmark_docs.py).
DOC_SECTIONS = {"speed": render_doc, "speed_load": render_load_doc}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--shape", type=int, nargs=2, default=(3000, 4000), metavar=("ROWS", "COLS"))
    ap.add_argument("--lights", type=int, default=16)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--work", type=Path, default=Path("/tmp/uvps_speed"))
    ap.add_argument("--no-md", action="store_true", help="accepted, does nothing: the table is printed only")
    ap.add_argument("--profile", action="store_true", help="also cProfile pipeline.run in this process")
    ap.add_argument("--top", type=int, default=25, help="profile lines kept")
    ap.add_argument("--skip", nargs="*", default=(), choices=("run", "zarr", "regions", "cal", "cal_regions", "demo"))
    ap.add_argument("--tile", type=int, nargs=2, metavar=("ROWS", "COLS"),
                    help="make the capture's painting in tiles of this size and render it in bands (make_tiled): "
                         "for captures make_capture cannot hold, e.g. --shape 8000 10000 --tile 2000 2500")
    ap.add_argument("--compress", action="store_true",
                    help="the capture's TIFFs re-written Deflate-compressed (as raw converters write them)")
    ap.add_argument("--stack", action="store_true",
                    help="the capture as ONE multi-page RGB TIFF (with --compress: Deflate) instead of a folder")
    ap.add_argument("--scratch-above", type=int, default=None, metavar="BYTES",
                    help="UVPS_SCRATCH_ABOVE_BYTES for the runs (compressed stacks above it go to scratch files)")
    ap.add_argument("--title", default="Speed and memory of a whole run")
    ap.add_argument("--note", default="", help="a sentence put under the table (what code was measured)")
    ap.add_argument("--doc", action="store_true",
                    help="write docs/benchmarks.md's first speed table (section speed, docs/benchmarks/speed.json; "
                         "the default 4000 x 3000 x 16 capture) or with --shape 1500 2000 its second (speed_load)")
    a = ap.parse_args(argv)
    load_doc = tuple(a.shape) == (1500, 2000)
    if a.doc and (tuple(a.shape) not in ((3000, 4000), (1500, 2000)) or a.lights != 16 or a.tile or a.compress
                  or a.stack or (not load_doc and {"run", "demo"} & set(a.skip))):
        ap.error("--doc: the tables are of a 4000 x 3000 x 16 capture in files, with `uvps run` and `uvps demo`, or of "
                 "--shape 1500 2000 (no other --shape, --lights, --tile, --compress or --stack)")
    M, N = a.shape
    folder = a.work / (f"capture_{M}x{N}x{a.lights}_s{a.seed}" + (f"_tiles{a.tile[0]}x{a.tile[1]}" if a.tile else ""))
    a.work.mkdir(parents=True, exist_ok=True)
    cached = len(list(folder.glob("uv_*.tif"))) == a.lights and (a.tile or (folder / "dark" / "dark.tif").is_file())
    raw = make(folder, (M, N), a.lights, a.seed, a.tile)
    if not cached:
        # this process now holds the generator's memory, and Linux counts a parent's resident set at fork
        # in every child's maximum (ru_maxrss survives exec): start again, the capture cached
        os.execv(sys.executable, [sys.executable, str(Path(__file__).resolve())] + list(argv or sys.argv[1:]))
    if a.stack:
        folder = stack_copy(folder, compress=a.compress)
    elif a.compress:
        folder = compressed_copy(folder)
    with open("/proc/meminfo", encoding="utf-8") as fh:
        each = raw > int(fh.readline().split()[1]) * 1024 / 4
    read_code, read_how = ((READ_EACH_CODE, "file by file into one image buffer") if each else
                           (READ_CODE, "into one preallocated array"))
    env = dict(os.environ, PYTHONPATH=str(REPO / "cpython_core"))
    if a.scratch_above is not None:
        env["UVPS_SCRATCH_ABOVE_BYTES"] = str(a.scratch_above)
    ms = []
    # four times, the fastest kept: the first warms the page cache (every later process reads from it
    # too), and a read of 0.3-0.9 s varies with what else runs; the floor is the fastest
    read_cmd = ([sys.executable, "-c", READ_STACK_CODE, str(folder), "1" if each else "0"] if a.stack else
                [sys.executable, "-c", read_code, str(folder)])
    touch_idle = first_touch(env, 10.0)       # memory left free for 10 s, as a run's later stages meet it
    touch_hot = first_touch(env, 0.0)          # memory the previous process has just freed
    reads = [run_child("read the stack with tifffile", read_cmd, env) for _ in range(4)]
    rd = min(reads[1:], key=lambda m: m.inner_s)
    ms.append(rd)
    read_s = rd.inner_s
    runs = {"run": ("uvps run", []), "zarr": ("uvps run --ome-zarr", ["--ome-zarr"]),
            "regions": ("uvps run --regions auto", ["--regions", "auto"])}
    dark = folder / "dark" / "dark.tif" if folder.is_dir() else folder.parent / "dark" / "dark.tif"
    if {"cal", "cal_regions"} - set(a.skip) and dark.is_file() and (folder / "lights_positions_mm.csv").is_file():
        cal = a.work / f"cal_{M}x{N}x{a.lights}"
        from uvps.testing.synthetic import SyntheticSpec
        c = run_child("uvps calibrate --lights (once)", UVPS + [
            "calibrate", "--lights", str(folder / "lights_positions_mm.csv"), "--dark", str(dark),
            "--pixel-size-um", str(SyntheticSpec().pixel_size_um), "-o", str(cal)], env)
        if c.returncode:
            print(f"calibrate: exit {c.returncode}: {c.stderr_tail}", file=sys.stderr)
        given = ["--calibration", str(cal), "--dark", str(dark)]
        runs.update({"cal": ("uvps run --calibration --dark", given),
                     "cal_regions": ("uvps run --calibration --dark --regions auto", given + ["--regions", "auto"])})
    for key, (name, extra) in runs.items():
        if key in a.skip:
            continue
        out = a.work / f"out_{key}_{M}x{N}"
        m = run_child(name, UVPS + ["run", str(folder), "-o", str(out)] + extra, env)
        if (out / "run.json").exists():
            m.stages = json.loads((out / "run.json").read_text()).get("timings_s", {})
        ms.append(m)
    if "demo" not in a.skip:
        ms.append(run_child("uvps demo (600 x 800, 12 lights)", UVPS + ["demo", "-o", str(a.work / "demo")], env))
    prof = profile_run(folder, a.top) if a.profile else ""
    tab = table(ms, read_s, raw)
    for m in ms:
        if m.returncode:
            print(f"{m.name}: exit {m.returncode}: {m.stderr_tail}", file=sys.stderr)
    cmd = " ".join(shlex.quote(x) for x in [".venv/bin/python", "scripts/benchmark_speed.py"] + list(argv or sys.argv[1:]))
    when = time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime())
    made = (f"`make_tiled(folder, ({M}, {N}), {a.lights}, seed={a.seed}, tile=({a.tile[0]}, {a.tile[1]}))` (make_capture's "
            "painting in tiles, rendered in bands: see its docstring)" if a.tile else
            f"`make_capture(shape=({M}, {N}), n_lights={a.lights}, seed={a.seed})`")
    text = [f"## {a.title}", "",
            f"{when}; {machine()}; load average {load_line()} (1/5/15 min) at the end; `{cmd}`.",
            f"Capture: {made}, {a.lights} {'Deflate-compressed' if a.compress else 'uncompressed'} "
            f"RGB uint16 {'pages of one multi-page TIFF' if a.stack else 'TIFFs'} (warm page cache); raw stack {raw / 2 ** 30:.2f} GiB. Reading it with tifffile ({read_how}) "
            f"took {read_s:.2f} s (the fastest of 3 warm reads, inside the process; '/ read' divides each wall time by it, the process's "
            "start and imports included). Peak RSS: each process's own maximum resident set (os.wait4); CPU / wall: "
            "its user + system CPU time over its wall time (2 cores: at most 2). "
            f"First touch of 1 GiB (FIRST_TOUCH_CODE): {touch_idle[0]:.2f} GB/s after 10 s idle, {touch_hot[0]:.2f} GB/s "
            f"just after another process freed it; written again {touch_hot[1]:.1f} GB/s.", "",
            tab, ""]
    if a.note:
        text += [a.note, ""]
    if prof:
        text += ["cProfile of read_capture + pipeline.run (default stages, in one process), by own time:", "",
                 "```", prof, "```", ""]
    text = "\n".join(text)
    print(text)
    if a.doc and load_doc:
        print("wrote", write_load_doc(ms, read_s, raw, argv or sys.argv[1:]))
    elif a.doc and all(m.returncode == 0 for m in ms):
        from benchdoc import write_doc
        doc = {"argv": list(argv or sys.argv[1:]), "load": load_line(), "read_s": read_s, "raw_gib": raw / 2 ** 30,
               "first_touch_gbps": {"idle_10s": touch_idle[0], "just_freed": touch_hot[0], "again": touch_hot[1]},
               "rows": doc_rows(ms, read_s, raw)}
        print("wrote", write_doc(DOC_SECTION, doc, render_doc(doc), source="scripts/benchmark_speed.py"))
    return 0 if all(m.returncode == 0 for m in ms) else 1


if __name__ == "__main__":
    sys.exit(main())
