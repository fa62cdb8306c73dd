"""Run Info: what a run folder holds (files, the command and parameters that made it, lights,
protrusion count, warnings), written to the Log. Nothing is written into the run folder.

Macro: run("Run Info", "run=[/data/run]");
"""
import os
import sys

from ij import IJ

sys.dont_write_bytecode = True
for _root in (IJ.getDirectory("imagej"), IJ.getDirectory("plugins")):
    _lib = os.path.join(_root or "", "jars", "Lib")
    if _root and os.path.isdir(_lib) and _lib not in sys.path:
        sys.path.insert(0, _lib)

from uvps_fiji import dialogs, menus, runner

TITLE = "Run Info"
COMMAND = "info"


def main():
    dlg = dialogs.UVPSDialog(TITLE, __doc__)
    dialogs.add_param(dlg, (COMMAND, "run"), key="run")
    values = dlg.show()
    if values is not None:
        menus.run_command(COMMAND, values)


runner.run_menu(TITLE, main)
