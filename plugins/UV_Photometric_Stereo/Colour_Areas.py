"""Colour Areas: the painting's colour areas as a label image, for per-area statistics.

Source "ROI Manager": one area selection per colour area, drawn by the user and added to the ROI
Manager (later ROIs lie on top of earlier ones). "Label image": an existing label TIFF.
"Automatic": the core proposes areas from the albedo colours. Opens regions_labels.tif and a
"Regions" table; writes regions_labels.tif and regions.csv.

Macro: run("Colour Areas", "run=[/data/run] source=Automatic number=0");
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

TITLE = "Colour Areas"
COMMAND = "regions"


def main():
    dlg = dialogs.UVPSDialog(TITLE, __doc__)
    dialogs.add_run_field(dlg)
    dlg.choice("Source of the areas", menus.AREA_SOURCES, menus.AREA_SOURCES[0])
    dlg.describe("Source of the areas", "ROI Manager: one area selection per colour area (later "
                 "ones on top); Automatic: proposed from the albedo's colours; Label image: a "
                 "TIFF whose pixel values number the areas (0 = none)")
    dialogs.add_param(dlg, (COMMAND, "labels"), key="label")
    dialogs.add_param(dlg, (COMMAND, "n_areas"), key="number")
    values = dlg.show()
    if values is not None:
        menus.colour_areas(values)


runner.run_menu(TITLE, main)
