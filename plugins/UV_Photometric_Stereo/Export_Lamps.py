"""Export Lamps: the lamps of a run or calibration folder (its lights.json) for other tools, written
into that folder: lamps.lp (an RTI light file: the direction toward each lamp; RTI Builder and
relight read it) and, for lamps at known distances, lamps_mm.csv (file, x_mm, y_mm, z_mm,
intensity: mm from the image centre). uvps reads both back as a lights file.

Macro: run("Export Lamps", "run=[/data/run]");
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

TITLE = "Export Lamps"
COMMAND = "lamps"


def main():
    dlg = dialogs.UVPSDialog(TITLE, __doc__)
    dialogs.add_param(dlg, (COMMAND, "run"), key="run")
    values = dlg.show()
    if values is not None:
        menus.run_command(COMMAND, values)


runner.run_menu(TITLE, main)
