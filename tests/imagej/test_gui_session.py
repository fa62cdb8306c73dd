"""The menu items as a user meets them: ImageJ with its windows (not -batch) under Xvfb and
openbox, macros run as Plugins > Macros > Run runs them, dialogs answered with xdotool
(gui_session.py). A user's mistake ends in one dialog and one Log line, a cancel says
"cancelled", and the Log never holds a stack trace ("Traceback", "Exception", "at java.")."""
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from conftest import _unavailable
from gui_session import GuiSession, missing_gui_tools, trace_lines

pytestmark = pytest.mark.imagej

HERE = Path(__file__).resolve().parent
INSTALLER = HERE.parent.parent / "scripts" / "install_fiji.py"


def q(path):
    return "[%s]" % path


@pytest.fixture(scope="module")
def session(imagej_env, tmp_path_factory):
    """One ImageJ session for the module (a fresh JVM costs seconds; each test clears the Log)."""
    missing = missing_gui_tools()
    if missing:
        _unavailable("the GUI session needs %s (scripts/install_imagej_deps.sh installs them: "
                     "openbox xdotool x11-apps imagemagick)" % ", ".join(missing))
    work = tmp_path_factory.mktemp("gui")
    home = work / "ImageJ"
    (home / "plugins").mkdir(parents=True)
    subprocess.run([sys.executable, str(INSTALLER), str(home), "--python", sys.executable,
                    "--no-interpreter"], check=True, stdout=subprocess.DEVNULL)
    with GuiSession(imagej_env.java, imagej_env.classpath, home, work / "session") as s:
        yield s


@pytest.fixture(scope="module")
def places(tmp_path_factory):
    """A folder with no images, a folder that is not a run, a CSV that is not a table."""
    d = tmp_path_factory.mktemp("bad inputs")
    empty = d / "no images"
    empty.mkdir()
    notrun = d / "not a run"
    notrun.mkdir()
    (notrun / "notes.txt").write_text("not a run folder\n")
    return {"empty": empty, "notrun": notrun, "out": d / "out", "csv": d / "missing.csv"}


#: Each menu item with a user's mistake (options; %(name)s from ``places``).
BAD_INPUTS = [
    ("Run Whole Pipeline", "capture=[Folder or files] images=%(empty)s run=%(out)s"),
    ("Estimate Lights", "capture=[Folder or files] images=%(empty)s run=%(out)s"),
    ("Flat Field", "capture=[Folder or files] images=%(empty)s run=%(out)s"),
    ("Normals and Albedo", "capture=[Folder or files] images=%(empty)s run=%(out)s"),
    ("Integrate Height", "run=%(notrun)s"),
    ("Colour Areas", "run=%(notrun)s source=Automatic"),
    ("Detect Protrusions", "run=%(notrun)s"),
    ("Wand Count", "run=%(notrun)s points=%(csv)s"),
    ("Compare Counts", "run=%(out)s first=%(csv)s second=%(csv)s"),
    ("Statistics and Report", "run=%(notrun)s"),
    ("Relight", "run=%(notrun)s"),
    ("Compare Captures", "earlier=%(notrun)s later=%(notrun)s run=%(out)s"),
    ("Element Maps", "source=%(notrun)s element=%(empty)s scan=100 run=%(out)s"),
    ("Run Info", "run=%(notrun)s"),
    ("Calibrate Lamps", "spheres=%(empty)s calibration=%(out)s"),
]


def _quoted(places):
    return dict((k, q(v)) for k, v in places.items())


@pytest.mark.parametrize("item,options", BAD_INPUTS, ids=[i for i, _ in BAD_INPUTS])
def test_a_mistake_ends_in_one_dialog_and_one_log_line(session, places, item, options):
    session.clear_log()
    answered = session.run('run("%s", "%s");\nprint("went on");\n'
                           % (item, (options % _quoted(places)).replace('"', '\\"')),
                           answers=[("^uvps: %s$" % item, "Return")], timeout=300)
    assert answered == ["uvps: %s" % item]
    log = session.log()
    status = session.status()      # after one more step: ImageJ's "Macro aborted" came and went
    lines = [ln for ln in log.splitlines() if ln.strip()]
    assert not trace_lines(log), log
    failed = [ln for ln in lines if ln.startswith("uvps %s failed" % item)]
    assert len(failed) == 1, log
    assert "went on" not in lines, log                  # the macro stopped at the error
    assert "uvps: %s failed" % item in status


CANCEL_ITEMS = ["Run Whole Pipeline", "Wand Count", "Compare Captures", "Element Maps", "Run Info",
                "Colour Areas", "Relight"]


@pytest.mark.parametrize("item", CANCEL_ITEMS)
def test_cancel_says_cancelled_without_a_trace(session, item):
    session.clear_log()
    session.run('run("%s");\nprint("went on");\n' % item,
                answers=[("^uvps: %s$" % item, "Escape")], timeout=120)
    log = session.log()
    status = session.status()      # after one more step: ImageJ's "Macro aborted" came and went
    assert not trace_lines(log), log
    assert "uvps %s: cancelled" % item in log.splitlines(), log
    assert "went on" not in log.splitlines(), log
    assert "uvps: %s cancelled" % item in status


@pytest.fixture(scope="module")
def capture(tmp_path_factory):
    from uvps.testing.synthetic import make_capture, write_capture

    folder = tmp_path_factory.mktemp("capture") / "uv capture"
    write_capture(make_capture(shape=(300, 400), n_lights=12, seed=3), folder, truth=False)
    return folder


def test_esc_while_the_core_runs_cancels_without_a_trace(session, capture, tmp_path):
    """Esc in ImageJ's window while Run Whole Pipeline runs from a macro: the core is stopped, the
    Log says cancelled (no ThreadDeath or "Macro canceled" trace), no run.json is left half
    written, the macro does not go on."""
    import time

    session.clear_log()
    out = tmp_path / "run"
    macro = ('run("Run Whole Pipeline", "capture=[Folder or files] images=%s run=%s regions=auto");\n'
             'print("went on");\n' % (q(capture), q(out)))
    # queue the step, press Esc in the ImageJ window once the core has started
    done = session.queue_step(macro)
    deadline = time.monotonic() + 120
    while time.monotonic() < deadline and not _core_of(session):
        time.sleep(0.5)
    assert _core_of(session), "the core did not start"
    time.sleep(3)
    wid = session.wait_window("^ImageJ$", time.monotonic() + 10)
    session._xdotool("windowactivate", "--sync", wid)
    session._xdotool("key", "Escape")
    while not done.exists() and time.monotonic() < deadline + 120:
        time.sleep(0.5)
    assert done.exists(), session.visible_windows()
    log = session.log()
    assert not trace_lines(log), log
    assert any(ln.startswith("uvps Run Whole Pipeline: cancelled") for ln in log.splitlines()), log
    assert "went on" not in log.splitlines()
    assert not (out / "run.json").exists()
    # the core was stopped: SIGTERM, then SIGKILL after 5 s at the latest (runner._stop); the
    # process table may list it for a moment after ImageJ's thread has returned
    end = time.monotonic() + 10
    while _core_of(session) and time.monotonic() < end:
        time.sleep(0.2)
    assert not _core_of(session)


def _core_of(session):
    """The ``uvps bridge`` processes ImageJ started."""
    out = subprocess.run(["ps", "-o", "args=", "--ppid", str(session.ij.pid)],
                         stdout=subprocess.PIPE, universal_newlines=True).stdout
    return [line for line in out.splitlines() if "uvps bridge" in line]


def test_windows_of_a_run_are_on_screen_and_tile(session, capture, tmp_path):
    """After Run Whole Pipeline (regions auto) every window lies on the screen, Window > Tile
    arranges them (no "Unfrozen plot windows cannot be tiled"), and the colour areas and the
    Regions table the report names are open."""
    session.run('close("*");')
    session.clear_log()
    out = tmp_path / "tiled run"
    session.run('run("Run Whole Pipeline", "capture=[Folder or files] images=%s run=%s regions=auto");\n'
                'run("Tile");\nprint("tiled");\n' % (q(capture), q(out)), timeout=600)
    log = session.log()
    assert "tiled" in log.splitlines() and not trace_lines(log), log
    visible = session.visible_windows()
    assert "Macro Error" not in visible, visible
    titles = ["normals - tiled run", "Lights (top view) - tiled run", "albedo - tiled run",
              "Regions - tiled run", "Protrusions - tiled run"]
    for title in titles + ["relative height - tiled run|height \\(um\\) - tiled run"]:
        # ImageJ adds the zoom to a reduced image's title: "albedo - tiled run (75%)"
        pattern = "^(%s)( \\([0-9.]+%%\\))?$" % (
            title if "|" in title else title.replace("(", "\\(").replace(")", "\\)"))
        x, y, w, h = session.window_geometry(pattern)
        assert x >= 0 and y >= 0 and x + w <= 1600 and y + h <= 1000, (title, x, y, w, h)
    assert any(ln.startswith("uvps: ") and "colour areas drawn with their names" in ln
               for ln in log.splitlines()), log
