#!/usr/bin/env python3
"""Measure what the Fiji <-> CPython file bridge costs next to the core's own work.

Two measurements, printed as Markdown tables:

1. A large capture (default 4000 x 3000 grey, 16 lights, uint16; about 384 MB): the time to
   write it as one TIFF stack into a request folder (what the Fiji side does for an unsaved
   stack), to start CPython and import uvps, the wall time of ``python -m uvps bridge
   request.json`` against the core's own ``elapsed_s`` from ``response.json`` (the difference is
   process start, imports, request parsing and response writing), and the time to read the
   outputs back.
2. A menu item's round trip on a small capture in the real ImageJ 1.x (Debian's ij.jar + Jython,
   under Xvfb, with the test harness's launcher): the wall time of a batch macro running
   ``Integrate Height`` against the core's ``elapsed_s``, and an empty macro for the JVM start.

Usage::

    .venv/bin/python scripts/benchmark_bridge.py [--shape 3000 4000] [--lights 16]
        [--command run] [--skip-imagej]
"""
import argparse
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import tifffile

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "jython_lib"))
sys.path.insert(0, str(REPO / "tests" / "imagej"))

from uvps_fiji import bridge_logic  # noqa: E402
from xvfb_display import start_xvfb, stop_xvfb  # noqa: E402  (the test harness's Xvfb)

IJ_JAR = "/usr/share/java/ij.jar"
JYTHON_JAR = "/usr/share/java/jython.jar"


def timed(func, *args, **kwargs):
    start = time.perf_counter()
    value = func(*args, **kwargs)
    return time.perf_counter() - start, value


def make_grey_capture(shape, n_lights, seed=0):
    """A grey near-light capture of a gently bumpy canvas in two paints, rendered by uvps.synthetic.

    Two paints (albedo 0.7 and 0.3 in a checker of ~140 px squares), not one: ``uvps run`` measures
    the additive term (black level) from how bright and dark paint change between lamps, which a
    uniform canvas leaves undetermined (the run then stops).
    """
    from uvps.testing.synthetic import light_positions, render_images

    rng = np.random.default_rng(seed)
    m, n = shape
    yy, xx = np.mgrid[0:m, 0:n].astype(np.float32)
    height = (3.0 * np.sin(xx / 30.0) * np.sin(yy / 30.0)).astype(np.float32)
    albedo = np.where(np.sin(xx / 47.0) * np.sin(yy / 39.0) > 0, 0.7, 0.3).astype(np.float32)
    pos = light_positions(rng, n_lights=n_lights, elevation_deg=(20.0, 60.0),
                          distance_mm=(250.0, 500.0))
    images = render_images(height, albedo, pixel_size_um=15.0, light_positions_mm=pos,
                           rng=rng, noise=False)
    return images


def run_bridge(python, command, inputs, params, out_dir, request_dir):
    request = bridge_logic.build_request(command, inputs, params, str(out_dir))
    request_path = bridge_logic.write_request(request, str(request_dir))
    args = bridge_logic.build_command(python, request_path)
    start = time.perf_counter()
    # cwd = the request folder, as the Fiji side (runner.call) runs the core.
    proc = subprocess.run(args, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                          universal_newlines=True, cwd=str(request_dir))
    wall = time.perf_counter() - start
    response = bridge_logic.finish_call(proc.returncode, request_path, command=command,
                                        stderr=proc.stderr)
    return wall, response


def bench_large(args, work):
    rows = []
    t_make, images = timed(make_grey_capture, tuple(args.shape), args.lights)
    request_dir = Path(bridge_logic.make_request_dir(str(work)))
    stack = request_dir / "capture.tif"
    t_write, _ = timed(tifffile.imwrite, str(stack), images, imagej=True,
                       resolution=(1 / 15.0, 1 / 15.0), metadata={"unit": "um"})
    size_mb = stack.stat().st_size / 1e6
    del images
    t_start, _ = timed(subprocess.run, [args.python, "-c", "import uvps.commands"], check=True)
    wall, response = run_bridge(args.python, args.command, {"images": [str(stack)]}, {},
                                work / "large_run", request_dir)
    core = float(response.elapsed_s or 0.0)
    names = [o["path"] for o in response.outputs if o["path"].endswith(".tif")]
    t_read = 0.0
    for path in names:
        dt, _ = timed(tifffile.imread, path)
        t_read += dt
    m, n = args.shape
    rows.append(("capture (%d x %d grey, %d lights, uint16)" % (n, m, args.lights),
                 "%.0f MB" % size_mb, ""))
    rows.append(("synthesising the capture (not bridge)", "%.2f s" % t_make, ""))
    rows.append(("write the stack into the request folder", "%.2f s" % t_write, "bridge"))
    rows.append(("start CPython + import uvps.commands", "%.2f s" % t_start, "bridge"))
    rows.append(("`uvps bridge` wall time (%s)" % args.command, "%.2f s" % wall, ""))
    rows.append(("core's own time (response elapsed_s)", "%.2f s" % core, "core"))
    rows.append(("bridge process overhead (wall - core)", "%.2f s" % (wall - core), "bridge"))
    rows.append(("read %d output TIFFs back" % len(names), "%.2f s" % t_read, "bridge"))
    bridge = t_write + (wall - core) + t_read
    rows.append(("**bridge total / core**", "%.2f s / %.2f s (%.1f %%)"
                 % (bridge, core, 100.0 * bridge / max(core, 1e-9)), ""))
    return rows, stack


class ImageJ(object):
    """The real ImageJ 1.x with uvps installed, under a private Xvfb (the test harness's
    launcher, in test mode: a dialog or a Python exception ends the JVM with an error)."""

    def __init__(self, args, work):
        self.work = work
        self.build = work / "classes"
        self.build.mkdir()
        java_dir = REPO / "tests" / "imagej" / "java"
        cp = os.pathsep.join([IJ_JAR, JYTHON_JAR])
        subprocess.run(["javac", "-nowarn", "-d", str(self.build), "-cp", cp]
                       + [str(p) for p in java_dir.glob("*.java")], check=True)
        self.home = work / "ImageJ"
        (self.home / "plugins").mkdir(parents=True)
        subprocess.run([args.python, str(REPO / "scripts" / "install_fiji.py"), str(self.home),
                        "--python", args.python], check=True, stdout=subprocess.DEVNULL)
        self.xvfb, self.display = start_xvfb()

    def close(self):
        stop_xvfb(self.xvfb)

    def macro(self, text, timeout=7200):
        """Run a batch macro; return (wall seconds, stdout = ImageJ's Log)."""
        path = self.work / "m.ijm"
        path.write_text(text)
        cmd = ["java", "-Duvps.test=1", "-Duser.home=%s" % self.work, "-cp",
               os.pathsep.join([IJ_JAR, JYTHON_JAR, str(self.build)]), "UvpsTestLauncher",
               "-ijpath", str(self.home), "-batch", str(path), ""]
        start = time.perf_counter()
        proc = subprocess.run(cmd, env=dict(os.environ, DISPLAY=self.display),
                              stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                              universal_newlines=True, timeout=timeout)
        if proc.returncode != 0:
            raise SystemExit("ImageJ failed:\n%s\n%s" % (proc.stdout, proc.stderr))
        return time.perf_counter() - start, proc.stdout


def _logged(stdout, prefix, word):
    """The number after ``word`` on the last Log line starting with ``prefix``."""
    values = [float(line.split(word, 1)[1].split()[0]) for line in stdout.splitlines()
              if line.startswith(prefix)]
    if not values:
        raise SystemExit("no Log line starting with %r:\n%s" % (prefix, stdout))
    return values[-1]


def bench_imagej_large(args, ij, stack):
    """The large stack opened in ImageJ, duplicated (unsaved, so the bridge writes it) and run
    through Normals and Albedo (or the command chosen) as the current stack."""
    item = {"run": "Run Whole Pipeline", "normals": "Normals and Albedo",
            "lights": "Estimate Lights"}[args.command]
    out = ij.work / "large_ij_run"
    t_open, _ = ij.macro('open("%s");\nrun("Duplicate...", "title=copy duplicate");\n' % stack)
    t_all, stdout = ij.macro(
        'open("%s");\nrun("Duplicate...", "title=copy duplicate");\n'
        'run("%s", "capture=[Current stack] run=[%s] degree=4");\n' % (stack, item, out))
    write = _logged(stdout, "uvps: wrote the stack", " in ")
    core = _logged(stdout, "uvps: %s done; core" % args.command, "core")
    item_time = t_all - t_open
    return [
        ("`%s` on the unsaved %d-image stack, menu item wall time" % (item, args.lights),
         "%.2f s" % item_time, ""),
        ("write the stack (ij.io.TiffEncoder) into the request folder", "%.2f s" % write,
         "bridge"),
        ("core's own time (response elapsed_s)", "%.2f s" % core, "core"),
        ("rest: CPython start, request/response, opening the outputs in ImageJ",
         "%.2f s" % (item_time - write - core), "bridge"),
        ("**bridge total / core**", "%.2f s / %.2f s (%.1f %%)"
         % (item_time - core, core, 100.0 * (item_time - core) / max(core, 1e-9)), ""),
    ]


def bench_imagej(args, ij):
    """Round trip of one small menu item in the real ImageJ."""
    from uvps.commands import COMMANDS
    from uvps.testing.synthetic import make_capture, write_capture

    work = ij.work
    cap = make_capture(shape=(240, 320), n_lights=8, seed=1)
    write_capture(cap, work / "small", truth=False)
    run_dir = work / "small_run"
    COMMANDS["normals"]({"images": [str(work / "small")]}, {}, run_dir)
    rows = []
    item = 'run("Integrate Height", "run=[%s] integration=[Frankot-Chellappa (FFT)]");\n' % run_dir
    t_empty, _ = ij.macro('print("hi");\n')
    t_item, _ = ij.macro(item)
    t_item2, stdout = ij.macro(item + item)
    # runner.call logs "uvps: integrate done; core 0.12 s" after each call.
    core = _logged(stdout, "uvps: integrate done; core", "core")
    rows.append(("ImageJ JVM start + empty batch macro", "%.2f s" % t_empty, ""))
    rows.append(("`Integrate Height` (320 x 240) batch macro, wall", "%.2f s" % t_item, ""))
    rows.append(("same, menu item alone (minus empty macro)", "%.2f s" % (t_item - t_empty), ""))
    rows.append(("second call in the same JVM", "%.2f s" % (t_item2 - t_item), ""))
    rows.append(("core's own time (response elapsed_s)", "%.2f s" % core, "core"))
    rows.append(("bridge round trip overhead (second call - core)",
                 "%.2f s" % (t_item2 - t_item - core), "bridge"))
    return rows


def print_table(title, rows):
    print("\n### %s\n" % title)
    print("| step | time | counted as |")
    print("|---|---|---|")
    for row in rows:
        print("| %s | %s | %s |" % row)


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--shape", type=int, nargs=2, default=[3000, 4000], metavar=("M", "N"))
    parser.add_argument("--lights", type=int, default=16)
    parser.add_argument("--command", default="run", choices=["run", "normals", "lights"])
    parser.add_argument("--python", default=sys.executable)
    parser.add_argument("--skip-imagej", action="store_true")
    parser.add_argument("--skip-large", action="store_true")
    args = parser.parse_args(argv)
    # the command table (uvps spec) from the python being measured, as the Fiji side asks its own
    # python when no installed commands.json is there (a source tree): otherwise bridge_logic asks
    # "python3", which need not have uvps
    bridge_logic.load_spec(python=args.python)
    work = Path(tempfile.mkdtemp(prefix="uvps-bench-"))
    ij = None
    try:
        stack = None
        if not args.skip_large:
            rows, stack = bench_large(args, work)
            print_table("Bridge vs core, large capture (CPython side)", rows)
        if not args.skip_imagej:
            if shutil.which("Xvfb") is None or shutil.which("javac") is None:
                print("\n(ImageJ round trip skipped: Xvfb or javac missing)")
            else:
                ij = ImageJ(args, work)
                print_table("Menu item round trip in ImageJ 1.53t, small capture",
                            bench_imagej(args, ij))
                if stack is not None:
                    print_table("Menu item in ImageJ 1.53t, large capture as the current stack",
                                bench_imagej_large(args, ij, stack))
    finally:
        if ij is not None:
            ij.close()
        shutil.rmtree(work, ignore_errors=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
