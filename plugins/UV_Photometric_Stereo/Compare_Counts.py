"""Compare Counts: match two protrusion tables (e.g. the manual wand count and the detection).

A protrusion of the first table matches one of the second within the match radius; opens a
"Comparison" table (matched / missed / extra per area) and writes comparison.csv.

Macro: run("Compare Counts", "run=[/data/run] first=[/data/run/protrusions_manual.csv] second=[/data/run/protrusions.csv] match=0");
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

TITLE = "Compare Counts"
COMMAND = "compare"


def main():
    dlg = dialogs.UVPSDialog(TITLE, __doc__)
    dialogs.add_run_field(dlg)
    dialogs.add_param(dlg, (COMMAND, "a"), key="first")
    dialogs.add_param(dlg, (COMMAND, "b"), key="second")
    dialogs.add_param(dlg, (COMMAND, "match_radius_um"), key="match", decimals=1)
    values = dlg.show()
    if values is not None:
        menus.compare_counts(values)


runner.run_menu(TITLE, main)
