#!/usr/bin/env python3
"""Screenshot every uvps menu item's dialog in the real ImageJ 1.x under Xvfb, for docs/fiji/.

Uses the test harness's launcher (tests/imagej/java/UvpsTestLauncher.java) in screenshot mode:
each dialog is saved as PNG and then cancelled, so nothing runs. The dialogs are pre-filled with
example values through ij.Prefs (the values a user would see after a first run).

Then *Run Whole Pipeline* runs on a small synthetic capture and the height map (viridis LUT,
calibration bar, protrusion outlines) and the albedo (RGB, outlines) are saved as ImageJ shows
them (*Image > Overlay > Flatten*): ``uvps_height.png``, ``uvps_albedo.png``. ``--no-results``
skips this part.

Usage::

    .venv/bin/python scripts/fiji_dialog_screenshots.py [--out docs/fiji/img]
"""
import argparse
import os
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "tests" / "imagej"))
from xvfb_display import start_xvfb, stop_xvfb  # noqa: E402  (the test harness's Xvfb)
IJ_JAR = "/usr/share/java/ij.jar"
JYTHON_JAR = "/usr/share/java/jython.jar"

sys.path.insert(0, str(REPO / "scripts"))
from install_fiji import menu_items  # noqa: E402  (the installed menu, in its order)

#: Every menu item, in the installed menu's order: one dialog screenshot each.
MENU_ITEMS = menu_items(REPO / "plugins" / "UV_Photometric_Stereo")

#: Example values shown in the screenshots (ij.Prefs keys uvps.<macro key>).
EXAMPLES = {"run": "/data/okeeffe/run1", "images": "/data/okeeffe/uv capture",
            "capture": "Folder or files", "first": "/data/okeeffe/run1/protrusions_manual.csv",
            "second": "/data/okeeffe/run1/protrusions.csv"}


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", default=str(REPO / "docs" / "fiji" / "img"))
    parser.add_argument("--no-results", action="store_true",
                        help="only the dialogs, not the height map and albedo")
    args = parser.parse_args(argv)
    out = Path(args.out).resolve()
    out.mkdir(parents=True, exist_ok=True)
    work = Path(tempfile.mkdtemp(prefix="uvps-shots-"))
    xvfb = None
    try:
        build = work / "classes"
        build.mkdir()
        subprocess.run(["javac", "-nowarn", "-d", str(build), "-cp",
                        os.pathsep.join([IJ_JAR, JYTHON_JAR])]
                       + [str(p) for p in (REPO / "tests" / "imagej" / "java").glob("*.java")]
                       + [str(REPO / "jython_lib" / "uvps_fiji" / "imagej1" / "Jython.java")],
                       check=True)
        home = work / "ImageJ"
        (home / "plugins").mkdir(parents=True)
        subprocess.run([sys.executable, str(REPO / "scripts" / "install_fiji.py"), str(home),
                        "--python", sys.executable, "--no-interpreter"], check=True, stdout=subprocess.DEVNULL)
        macro = "".join('call("ij.Prefs.set", "uvps.%s", "%s");\n' % kv for kv in EXAMPLES.items())
        macro += "".join('run("%s");\n' % item for item in MENU_ITEMS)
        (work / "shots.ijm").write_text(macro)
        # the launcher never overwrites (it adds _2): replace the earlier screenshots
        for item in MENU_ITEMS:
            old = out / ("uvps_%s.png" % item.replace(" ", "_"))
            if old.exists():
                old.unlink()
        xvfb, display = start_xvfb()
        cmd = ["java", "-Duser.home=%s" % work, "-Duvps.screenshot.dir=%s" % out,
               "-Duvps.screenshot.button=Cancel", "-Duvps.screenshot.delay_ms=3000", "-cp",
               os.pathsep.join([IJ_JAR, JYTHON_JAR, str(build)]), "UvpsTestLauncher",
               "-ijpath", str(home), "-batch", str(work / "shots.ijm"), ""]
        proc = subprocess.run(cmd, env=dict(os.environ, DISPLAY=display),
                              stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                              universal_newlines=True, timeout=600)
        shots = [line.split(": ", 1)[1] for line in proc.stderr.splitlines()
                 if line.startswith("UVPS-SCREENSHOT: /")]
        for shot in shots:
            print(shot)
        if proc.returncode != 0 or len(shots) != len(MENU_ITEMS):
            print(proc.stdout, proc.stderr, file=sys.stderr)
            return 1
        if not args.no_results and results(work, home, build, display, out) != 0:
            return 1
    finally:
        if xvfb is not None:
            stop_xvfb(xvfb)
        shutil.rmtree(work, ignore_errors=True)
    return 0


def results(work, home, build, display, out):
    """Run the whole pipeline on a synthetic capture and save the height map and the albedo as
    ImageJ shows them (overlays flattened)."""
    from uvps.testing.synthetic import make_capture, write_capture

    capture = work / "capture"
    write_capture(make_capture(shape=(300, 400), n_lights=12, seed=3), capture, truth=False)
    macro = ('run("Run Whole Pipeline", "capture=[Folder or files] images=[%s] run=[%s] '
             'regions=auto");\n' % (capture, work / "run"))
    for title, name in (("height (um) - run", "uvps_height.png"), ("albedo - run", "uvps_albedo.png"),
                        ("normals - run", "uvps_normals.png")):
        macro += ('selectImage("%s");\nrun("Flatten");\nsaveAs("PNG", "%s");\nprint("saved %s");\n'
                  % (title, out / name, out / name))
    (work / "results.ijm").write_text(macro)
    cmd = ["java", "-Duvps.test=1", "-Duser.home=%s" % work, "-cp",
           os.pathsep.join([IJ_JAR, JYTHON_JAR, str(build)]), "UvpsTestLauncher",
           "-ijpath", str(home), "-batch", str(work / "results.ijm"), ""]
    proc = subprocess.run(cmd, env=dict(os.environ, DISPLAY=display), stdout=subprocess.PIPE,
                          stderr=subprocess.PIPE, universal_newlines=True, timeout=1200)
    saved = [line[len("saved "):] for line in proc.stdout.splitlines() if line.startswith("saved ")]
    for path in saved:
        print(path)
    if proc.returncode != 0 or len(saved) != 3:
        print(proc.stdout, proc.stderr, file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
