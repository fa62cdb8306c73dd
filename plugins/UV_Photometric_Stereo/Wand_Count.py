"""Wand Count: the paper's manual method, one wand selection per clicked protrusion.

Click each protrusion on the albedo with the multi-point tool (or add point selections to the ROI
Manager), then run this: every click grows a region of similar albedo (ImageJ's wand with a
tolerance) and the regions are counted and measured. In a macro, the points come from a CSV with
x_px,y_px columns (key points; x_um,y_um or x_mm,y_mm are read in their unit, X,Y as Analyze >
Measure exports them in pixels or um: key units)
or from makeSelection("point", xs, ys) on the open albedo. Clicks inside an earlier click's
selection are listed in the Log. The grey image the wand works on, (R+G+B)/3 of the albedo,
opens as "albedo (R+G+B)/3" to try the wand by hand.
Opens a "Manual protrusions" table and ROIs; writes protrusions_manual.csv and
protrusions_manual_labels.tif.

Macro: run("Wand Count", "run=[/data/run] points=[/data/clicks.csv] tolerance=0.05 connectivity=8");
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

TITLE = "Wand Count"
COMMAND = "wand"


def main():
    dlg = dialogs.UVPSDialog(TITLE, __doc__)
    dialogs.add_run_field(dlg)
    dialogs.add_param(dlg, (COMMAND, "points"), key="points")
    dialogs.add_param(dlg, (COMMAND, "points_unit"), key="units")
    # The core declares no default tolerance (a required value): this is ImageJ's usual start.
    dialogs.add_param(dlg, (COMMAND, "tolerance"), key="tolerance", default=0.05, decimals=4)
    dialogs.add_param(dlg, (COMMAND, "connectivity"), key="connectivity")
    dialogs.add_param(dlg, (COMMAND, "regions"), key="regions")
    values = dlg.show()
    if values is not None:
        menus.wand_count(values)


runner.run_menu(TITLE, main)
