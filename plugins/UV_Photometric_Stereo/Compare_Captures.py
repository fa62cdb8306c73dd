"""Compare Captures: two captures of one region at two dates (uvps changes).

Registers the later run folder (B) onto the earlier one (A) from the albedo, levels the heights
and gives every protrusion its status (new, grown, shrunk, unchanged, gone, merged, split). Writes
registration.json, changes.csv, height_change.tif, report.html and run.json into the output
folder. Opens the height change (um, A's frame) in blue (lower) - white - red (higher) with
its calibration bar beside it, both dates' albedos, every protrusion outlined in the colour of its
status (new green, grown red, shrunk orange, unchanged grey, gone blue, merged purple, split
magenta) on the height change and on both albedos, and the change table (changes.csv).

Macro: run("Compare Captures", "earlier=[/data/2019/run] later=[/data/2024/run] run=[/data/changes]");
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

TITLE = "Compare Captures"
COMMAND = "changes"


def main():
    dlg = dialogs.UVPSDialog(TITLE, __doc__)
    dialogs.add_param(dlg, (COMMAND, "run_a"), key="earlier")
    dialogs.add_param(dlg, (COMMAND, "run_b"), key="later")
    dialogs.add_run_field(dlg)
    values = dlg.show()
    if values is not None:
        menus.compare_captures(values)


runner.run_menu(TITLE, main)
