"""Smoke tests of the ImageJ harness itself: macros, Jython menu commands, failures that must be
loud (Python exceptions, modal dialogs), GenericDialog macro options, screenshots, and the layout
written by scripts/install_fiji.py as seen from inside ImageJ."""
import subprocess
import sys
import time

import pytest

from conftest import DIALOG_STATUS, INSTALLER, PYTHON_EXCEPTION_STATUS

pytestmark = pytest.mark.imagej

DIALOG_PLUGIN = '''from ij.gui import GenericDialog
gd = GenericDialog("Fit Options")
gd.addNumericField("Degree of the polynomial", 4, 0)
gd.addStringField("Output folder", "default-out", 30)
gd.addChoice("Integration method", ["fc", "dct"], "fc")
gd.addCheckbox("Robust fit", True)
gd.showDialog()
if gd.wasCanceled():
    print("canceled")
else:
    print("degree=%d" % int(gd.getNextNumber()))
    print("output=%s" % gd.getNextString())
    print("integration=%s" % gd.getNextChoice())
    print("robust=%s" % gd.getNextBoolean())
'''


def test_macro_print_reaches_log(run_macro, bare_imagej_home):
    result = run_macro('a = 6 * 7;\nprint("answer " + a);\n', home=bare_imagej_home).check()
    assert "answer 42" in result.log_text.splitlines()


def test_jython_plugin_runs_as_menu_command(run_macro, bare_imagej_home, write_plugin):
    path = write_plugin(bare_imagej_home, "Test_Menu/Say_Hello.py",
                        'import sys\nprint("hello %d %s" % (6 * 7, sys.argv[0]))\n'
                        'print("file " + __file__)\n')
    started = time.monotonic()
    result = run_macro('run("Say Hello");\nprint("macro done");\n', home=bare_imagej_home)
    elapsed = time.monotonic() - started
    result.check()
    lines = result.stdout.splitlines()
    assert "hello 42 %s" % path in lines
    assert "file %s" % path in lines
    assert lines.index("macro done") > lines.index("file %s" % path)
    # JVM start + first Jython interpreter: about 2 s on 2 cores; a stall would show here.
    assert elapsed < 60


def test_java_exception_from_jython_fails_too(run_macro, bare_imagej_home, write_plugin):
    write_plugin(bare_imagej_home, "Test_Menu/Parse_Number.py",
                 'from java.lang import Integer\nInteger.parseInt("twelve")\n')
    result = run_macro('run("Parse Number");\n', home=bare_imagej_home)
    assert result.returncode == PYTHON_EXCEPTION_STATUS
    assert "NumberFormatException" in result.stderr and "twelve" in result.stderr


def test_a_macro_abort_inside_jython_is_a_cancel_not_a_trace(run_macro, bare_imagej_home, write_plugin):
    """ImageJ signals a macro's abort by throwing "Macro canceled" (a cancelled dialog, IJ.error in
    a macro) and Esc by stopping the thread (ThreadDeath): the interpreter class reports neither
    (no traceback, no status 4); a user did it on purpose."""
    write_plugin(bare_imagej_home, "Test_Menu/Abort_Macro.py",
                 'from java.lang import RuntimeException\nprint("before")\n'
                 'raise RuntimeException("Macro canceled")\n')
    write_plugin(bare_imagej_home, "Test_Menu/Stop_Thread.py",
                 'from java.lang import ThreadDeath\nraise ThreadDeath()\n')
    result = run_macro('run("Abort Macro");\nrun("Stop Thread");\nprint("macro done");\n',
                       home=bare_imagej_home).check()
    assert "before" in result.stdout and "macro done" in result.stdout
    for text in (result.stdout, result.stderr):
        assert "Traceback" not in text and "Exception" not in text and "ThreadDeath" not in text


def test_stalled_macro_is_killed_at_the_timeout(run_macro, bare_imagej_home):
    started = time.monotonic()
    with pytest.raises(pytest.fail.Exception, match="did not finish within 3 s"):
        run_macro('print("waiting");\nwait(600000);\n', home=bare_imagej_home, timeout=3)
    assert time.monotonic() - started < 15


def test_python_exception_fails_with_traceback(run_macro, bare_imagej_home, write_plugin):
    write_plugin(bare_imagej_home, "Test_Menu/Raise_Error.py",
                 'def inner():\n    raise ValueError("lamp 7 is missing")\n'
                 'print("before")\ninner()\nprint("after")\n')
    result = run_macro('run("Raise Error");\nprint("macro went on");\n', home=bare_imagej_home)
    assert result.returncode == PYTHON_EXCEPTION_STATUS
    assert "ValueError: lamp 7 is missing" in result.stderr
    assert "Raise_Error.py" in result.stderr
    assert "before" in result.stdout
    assert "after" not in result.stdout and "macro went on" not in result.stdout


def test_sys_exit_in_plugin_ends_only_the_script(run_macro, bare_imagej_home, write_plugin):
    write_plugin(bare_imagej_home, "Test_Menu/Exit_Early.py",
                 'import sys\nprint("one")\nsys.exit(0)\nprint("two")\n')
    result = run_macro('run("Exit Early");\nprint("macro went on");\n',
                       home=bare_imagej_home).check()
    assert result.stdout.splitlines()[-2:] == ["one", "macro went on"]


@pytest.mark.parametrize("macro, title, text", [
    ('waitForUser("Click on the lamp");', "Action Required", "Click on the lamp"),
    ('run("No Such Command At All");', "Macro Error", 'Unrecognized command: "No Such Command'),
    ('x = ;', "Macro Error", "Number or numeric function expected"),
])
def test_modal_dialog_fails_fast_with_its_text(run_macro, bare_imagej_home, macro, title, text):
    started = time.monotonic()
    result = run_macro(macro + '\nprint("not reached");\n', home=bare_imagej_home, timeout=60)
    assert time.monotonic() - started < 30
    assert result.returncode == DIALOG_STATUS
    assert 'dialog opened: title="%s"' % title in result.stderr
    assert text in result.stderr
    assert "not reached" not in result.stdout


def test_ij_error_in_plugin_is_a_dialog_failure(run_macro, bare_imagej_home, write_plugin):
    write_plugin(bare_imagej_home, "Test_Menu/Report_Error.py",
                 'from ij import IJ\nIJ.error("UVPS", "no images in /data/empty")\n')
    result = run_macro('run("Report Error");\n', home=bare_imagej_home, timeout=60)
    assert result.returncode == DIALOG_STATUS
    assert "no images in /data/empty" in result.stderr


def test_generic_dialog_takes_macro_options(run_macro, bare_imagej_home, write_plugin):
    write_plugin(bare_imagej_home, "Test_Menu/Fit_Options.py", DIALOG_PLUGIN)
    result = run_macro('run("Fit Options", "degree=7 output=[/tmp/with space/out] '
                       'integration=dct");\n', home=bare_imagej_home).check()
    lines = result.stdout.splitlines()
    assert lines[-4:] == ["degree=7", "output=/tmp/with space/out", "integration=dct",
                          "robust=False"]  # a missing checkbox key means false
    result = run_macro('run("Fit Options", "robust");\n', home=bare_imagej_home).check()
    assert result.stdout.splitlines()[-4:] == ["degree=4", "output=default-out",
                                               "integration=fc", "robust=True"]


def test_generic_dialog_without_options_is_a_dialog_failure(run_macro, bare_imagej_home,
                                                             write_plugin):
    write_plugin(bare_imagej_home, "Test_Menu/Fit_Options.py", DIALOG_PLUGIN)
    result = run_macro('run("Fit Options");\n', home=bare_imagej_home, timeout=60)
    assert result.returncode == DIALOG_STATUS
    assert 'title="Fit Options"' in result.stderr
    assert "label: Degree of the polynomial" in result.stderr
    assert "checkbox: Robust fit = true" in result.stderr


def test_screenshot_mode_saves_dialog_and_presses_ok(run_macro, bare_imagej_home, write_plugin,
                                                     tmp_path):
    write_plugin(bare_imagej_home, "Test_Menu/Fit_Options.py", DIALOG_PLUGIN)
    shots = tmp_path / "shots"
    result = run_macro('run("Fit Options");\nprint("macro went on");\n', home=bare_imagej_home,
                       screenshot_dir=shots).check()
    assert result.screenshots == [shots.resolve() / "Fit_Options.png"]
    data = result.screenshots[0].read_bytes()
    assert data[:8] == b"\x89PNG\r\n\x1a\n"
    import imageio.v3 as iio
    image = iio.imread(result.screenshots[0])
    assert image.shape[0] > 50 and image.shape[1] > 100
    assert image.std() > 10  # a drawn dialog, not a blank frame
    assert result.stdout.splitlines()[-5:] == ["degree=4", "output=default-out",
                                               "integration=fc", "robust=True", "macro went on"]


def test_installed_layout_is_importable_inside_imagej(run_macro, tmp_path, write_plugin):
    """install_fiji.py into a plain ImageJ folder: the menu script finds uvps_fiji via
    IJ.getDirectory("plugins") + "jars/Lib" and reads the python recorded in uvps_fiji.cfg."""
    source = tmp_path / "source"
    menu = source / "plugins" / "UV_Photometric_Stereo"
    lib = source / "jython_lib" / "uvps_fiji"
    menu.mkdir(parents=True)
    lib.mkdir(parents=True)
    (lib / "__init__.py").write_text("")
    (lib / "probe.py").write_text(
        "import os\n"
        "def configured_python():\n"
        "    here = os.path.dirname(os.path.abspath(__file__))\n"
        "    for line in open(os.path.join(here, 'uvps_fiji.cfg')):\n"
        "        if line.startswith('python'):\n"
        "            return line.split('=', 1)[1].strip()\n")
    (menu / "Probe_Install.py").write_text(
        "import sys\nfrom ij import IJ\n"
        "for d in (IJ.getDirectory('imagej') + 'jars/Lib',\n"
        "          IJ.getDirectory('plugins') + 'jars/Lib'):\n"
        "    if d not in sys.path:\n        sys.path.append(d)\n"
        "from uvps_fiji import probe\n"
        "print('python=' + probe.configured_python())\n")
    home = tmp_path / "ImageJ"
    (home / "plugins").mkdir(parents=True)
    proc = subprocess.run([sys.executable, str(INSTALLER), str(home), "--source-root", str(source)],
                          stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                          universal_newlines=True, timeout=120)
    assert proc.returncode == 0, proc.stdout
    assert (home / "plugins" / "jars" / "Lib" / "uvps_fiji" / "probe.py").is_file()
    result = run_macro('run("Probe Install");\n', home=home).check()
    assert "python=%s" % sys.executable in result.stdout.splitlines()
    assert not list(home.rglob("*$py.class"))  # dont_write_bytecode keeps the install clean
