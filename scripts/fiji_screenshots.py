#!/usr/bin/env python3
"""Screenshots of ImageJ as a user sees it after *Run Whole Pipeline*, *Wand Count*, *Compare
Captures* and *Element Maps*, for docs/fiji/ (``fiji_*.png``).

The real ImageJ 1.x (Debian's ij.jar, standing in for Fiji) runs with its windows on a private
Xvfb under openbox (tests/imagej/gui_session.py); each step is a macro queued as *Plugins >
Macros > Run* runs it, on small synthetic captures (uvps.testing.synthetic), then *Window > Tile*
arranges the windows and the screen is saved, scaled to 60 % (a few hundred KB).

Usage::

    .venv/bin/python scripts/fiji_screenshots.py [--out docs/fiji/img] [--keep WORK]
"""
import argparse
import os
import re
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "tests" / "imagej"))
from gui_session import GuiSession, missing_gui_tools, move_window, trace_lines  # noqa: E402

IJ_JAR = os.environ.get("UVPS_IJ_JAR", "/usr/share/java/ij.jar")
JYTHON_JAR = os.environ.get("UVPS_JYTHON_JAR", "/usr/share/java/jython.jar")
SCALE = "60%"


def build(work):
    """Compile the harness's Java classes and install uvps into a fresh ImageJ folder."""
    classes = work / "classes"
    classes.mkdir()
    subprocess.run(["javac", "-nowarn", "-d", str(classes), "-cp", os.pathsep.join([IJ_JAR, JYTHON_JAR])]
                   + [str(p) for p in (REPO / "tests" / "imagej" / "java").glob("*.java")]
                   + [str(REPO / "jython_lib" / "uvps_fiji" / "imagej1" / "Jython.java")], check=True)
    home = work / "ImageJ"
    (home / "plugins").mkdir(parents=True)
    subprocess.run([sys.executable, str(REPO / "scripts" / "install_fiji.py"), str(home), "--python",
                    sys.executable, "--no-interpreter"], check=True, stdout=subprocess.DEVNULL)
    return os.pathsep.join([IJ_JAR, JYTHON_JAR, str(classes)]), home


def data(work):
    """A capture; two dates of one region run by the core; element maps of a run with areas."""
    import numpy as np
    import tifffile
    from uvps.commands import COMMANDS
    from uvps.testing.synthetic import LaterSpec, make_capture, make_capture_pair, write_capture
    from uvps.testing.synthetic_elements import render_element_maps

    cap = make_capture(shape=(300, 400), n_lights=12, seed=3)
    write_capture(cap, work / "uv capture", truth=False)
    # clicks for Wand Count: the five widest true protrusions and one click on bare paint
    t = cap.protrusions
    order = np.argsort(-t["width_um"])[:5]
    rows = ["%.1f,%.1f" % (t["x_px"][i], t["y_px"][i]) for i in order]
    rows.append("20,280")   # a click on bare paint, far from every protrusion
    (work / "clicks.csv").write_text("x_px,y_px\n" + "\n".join(rows) + "\n")
    pair = make_capture_pair(shape=(300, 400), n_lights=8, protrusion_density_light=150.0,
                             later=LaterSpec(seed=3, shift_px=(12.0, 8.0), rotation_deg=1.0, scale=1.0,
                                             new_per_cm2=40.0))
    for name, c in (("2019", pair.a), ("2024", pair.b)):
        write_capture(c, work / ("capture " + name), truth=False)
        folder = work / ("capture " + name)
        # the lamps as placed (their positions pin the heights' scale: Compare Captures needs it)
        COMMANDS["run"]({"images": [str(folder)]}, {"regions": "auto", "detect": True,
                                                    "lights": str(folder / "lights_positions_mm.csv")},
                        work / ("run " + name))
    maps = render_element_maps(pair.a, step_um=100.0, spot_um=400.0, margin_mm=1.0, rotation_deg=2.0,
                               shift_mm=(0.4, -0.3), seed=2)
    (work / "xrf").mkdir()
    for name, m in zip(maps.maps.names, maps.maps.data):
        tifffile.imwrite(work / "xrf" / ("%s.tif" % name), m.astype(np.float32))


def q(path):
    return "[%s]" % path


STEPS = [
    ("fiji_run_whole_pipeline.png",
     'run("Run Whole Pipeline", "capture=[Folder or files] images=%(capture)s run=%(run)s regions=auto");'),
    ("fiji_wand_count.png",
     'run("Wand Count", "run=%(run)s points=%(clicks)s method=relative tolerance=0.5");'),
    ("fiji_compare_captures.png",
     'run("Compare Captures", "earlier=%(a)s later=%(b)s run=%(changes)s");'),
    ("fiji_element_maps.png",
     'run("Element Maps", "source=%(a)s element=%(xrf)s scan=100 spot=400 run=%(elements)s");'),
]


#: Where the tables and the Log go after Window > Tile (which places image windows only).
BOTTOM_ROW = [(r"^(Protrusions|Manual protrusions|Changes) - ", 0, 560, 780, 300),
              (r"^Regions - ", 790, 560, 800, 300), (r"^Log$", 790, 560, 800, 300),
              (r"^Lights - ", 790, 870, 800, 120)]


def arrange(session):
    """Move the tables and the Log into the screen's free lower part, as a user would."""
    visible = session.visible_windows()
    used = set()
    for pattern, x, y, w, h in BOTTOM_ROW:
        if any(re.search(pattern, t) for t in visible) and (x, y) not in used:
            move_window(session, pattern, x, y, w, h)
            used.add((x, y))


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", default=str(REPO / "docs" / "fiji" / "img"))
    parser.add_argument("--keep", help="keep the work folder here (logs, runs)")
    parser.add_argument("--only", help="comma-separated PNG names to make (default: all)")
    args = parser.parse_args(argv)
    missing = missing_gui_tools()
    if missing:
        print("missing %s: apt-get install openbox xdotool x11-apps imagemagick" % ", ".join(missing),
              file=sys.stderr)
        return 2
    out = Path(args.out).resolve()
    out.mkdir(parents=True, exist_ok=True)
    work = Path(args.keep).resolve() if args.keep else Path(tempfile.mkdtemp(prefix="uvps-fiji-shots-"))
    work.mkdir(parents=True, exist_ok=True)
    status = 0
    try:
        classpath, home = build(work)
        data(work)
        names = {"capture": q(work / "uv capture"), "run": q(work / "run"), "clicks": q(work / "clicks.csv"),
                 "a": q(work / "run 2019"), "b": q(work / "run 2024"), "changes": q(work / "changes"),
                 "xrf": q(work / "xrf"), "elements": q(work / "elements")}
        only = set(args.only.split(",")) if args.only else None
        with GuiSession(shutil.which("java"), classpath, home, work / "session") as session:
            for png, macro in STEPS:
                if only and png not in only and png != STEPS[0][0]:
                    continue
                session.run('close("*");\nif (isOpen("ROI Manager")) {selectWindow("ROI Manager"); run("Close");}\n'
                            'list = getList("window.titles");\n'
                            'for (i = 0; i < list.length; i++) if (list[i] != "Log") {selectWindow(list[i]); run("Close");}\n'
                            'print("\\\\Clear");')
                session.run(macro % names + '\nrun("Tile");\n', timeout=900)
                arrange(session)
                log = session.log()
                print("--- %s\n%s" % (png, log))
                if trace_lines(log):
                    print("a stack trace in the Log after %s" % png, file=sys.stderr)
                    status = 1
                if only is None or png in only:
                    shot = session.screenshot(out / png, scale=SCALE)
                    print("saved %s (%d KB)" % (shot, shot.stat().st_size // 1024))
    finally:
        if not args.keep:
            shutil.rmtree(work, ignore_errors=True)
    return status


if __name__ == "__main__":
    sys.exit(main())
