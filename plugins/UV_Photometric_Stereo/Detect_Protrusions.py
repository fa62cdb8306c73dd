"""Detect Protrusions: the automated method (albedo colour + template, height blobs, union).

Needs albedo, normals and depth in the run folder. Opens a "Protrusions" table, one ROI per
protrusion in the ROI Manager and the outlines as an overlay on the albedo; writes
protrusions.csv and protrusions_labels.tif.

Sensitivity: a candidate must rise this many times the height noise above its surround (the Log
gives the noise, the candidates and why each rejected one was rejected); Smallest width: narrower
candidates are left out.

Macro: run("Detect Protrusions", "run=[/data/run] regions=auto sensitivity=5 smallest=30");
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
    dlg = dialogs.UVPSDialog(TITLE, __doc__)
    dialogs.add_run_field(dlg)
    dialogs.add_param(dlg, (COMMAND, "regions"), key="regions")
    dialogs.add_param(dlg, (COMMAND, "dynamic_k"), key="sensitivity", decimals=1)
    dialogs.add_param(dlg, (COMMAND, "min_width_um"), key="smallest", decimals=0)
    values = dlg.show()
    if values is not None:
        menus.detect_protrusions(values)


runner.run_menu(TITLE, main)
