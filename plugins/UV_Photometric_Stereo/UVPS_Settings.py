"""UVPS Settings: choose the CPython that has uvps installed, and check that it works.

Runs `python -c "import uvps"` and shows the version, or a clear message when it fails. An empty
field clears the setting; then the UVPS_PYTHON environment variable, uvps_fiji.cfg (written by
the installer) or python3 apply, in that order.

Macro: run("UVPS Settings", "python=[/opt/uvps/.venv/bin/python]");
"""
import os
import sys

from ij import IJ

sys.dont_write_bytecode = True
for _root in (IJ.getDirectory("imagej"), IJ.getDirectory("plugins")):
    _lib = os.path.join(_root or "", "jars", "Lib")
    if _root and os.path.isdir(_lib) and _lib not in sys.path:
        sys.path.insert(0, _lib)

from ij import Prefs
from uvps_fiji import dialogs, menus, runner

TITLE = "UVPS Settings"


def main():
    previous = Prefs.get(runner.PYTHON_PREF, "")
    python, source = runner.python_command()
    dlg = dialogs.UVPSDialog(TITLE, __doc__)
    dlg.message("Now: %s (from %s)" % (python, source))
    dlg.file("Python with uvps installed (empty = automatic)", "")
    dlg.describe("Python with uvps installed (empty = automatic)",
                 "the CPython program that runs the uvps core (e.g. /opt/uvps/.venv/bin/python); "
                 "empty: the UVPS_PYTHON environment variable, else the one the installer wrote "
                 "into uvps_fiji.cfg, else python3")
    values = dlg.show()
    if values is not None:
        text = menus.settings(values, previous)
        if runner.is_interactive():
            IJ.showMessage("uvps", text)


runner.run_menu(TITLE, main)
