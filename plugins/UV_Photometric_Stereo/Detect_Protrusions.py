"""Detect Protrusions: the automated method (albedo colour + template, height blobs, union).

Needs albedo, normals and depth in the run folder. Opens a "Protrusions" table, one ROI per
protrusion in the ROI Manager and the outlines as an overlay on the albedo; writes
protrusions.csv and protrusions_labels.tif.

Macro: run("Detect Protrusions", "run=[/data/run] regions=auto");
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

TITLE = "Detect Protrusions"
COMMAND = "detect"


def main():
    dlg = dialogs.UVPSDialog(TITLE)
    dialogs.add_run_field(dlg)
    dialogs.add_param(dlg, (COMMAND, "regions"), key="regions")
    values = dlg.show()
    if values is not None:
        menus.detect_protrusions(values)


runner.run_menu(TITLE, main)
