"""Element Maps: XRF element maps registered onto a run (uvps elements).

Reads element maps as PyMCA and XRF scanners write them (a TIFF or EDF per element, a multi-page
TIFF with element names as slice labels, or a row/column text table), registers them onto the
source run's colour areas (automatically, or from a control-points CSV), and writes
registration.json, elements.tif (the maps in the run's frame), elements_by_area.csv,
elements_by_protrusion.csv, element_correlation.csv, report.html and run.json into the output
folder. The summary goes to the Log; the registered maps open as a stack, and three of them as a
colour composite: lead (Pb, the metal of the soaps) in red by default, the next maps in green and
blue; the Red, Green and Blue element fields choose others (an element such as Zn, or a map's name).

Macro: run("Element Maps", "source=[/data/run] element=[/data/xrf] scan=250 run=[/data/elements] red=Pb green=Zn blue=auto");
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

TITLE = "Element Maps"
COMMAND = "elements"


def main():
    dlg = dialogs.UVPSDialog(TITLE, __doc__)
    dialogs.add_param(dlg, (COMMAND, "run"), key="source")
    dialogs.add_param(dlg, (COMMAND, "maps"), key="element")
    dialogs.add_param(dlg, (COMMAND, "step_um"), key="scan", decimals=1)
    dialogs.add_param(dlg, (COMMAND, "spot_um"), key="spot", decimals=0)
    dialogs.add_param(dlg, (COMMAND, "control_points"), key="control")
    dialogs.add_run_field(dlg)
    dialogs.add_composite_fields(dlg)
    values = dlg.show()
    if values is not None:
        menus.element_maps(values)


runner.run_menu(TITLE, main)
