"""Stitch Painting: a painting photographed in overlapping tiles (uvps batch with a mosaic).

Runs every tile (a folder of capture folders, one per tile) as Run Whole Pipeline would, on a
local Dask cluster; registers the tiles on their overlaps from the layout of their nominal corners
(a CSV capture,x_px,y_px) or a grid (COLUMNS,ROWS,OVERLAP[,ORDER]); counts each protrusion of an
overlap once and writes the painting into RUN/painting/ (docs/painting.md). Opens the painting at
overview with its protrusions and colour areas, the painting's colour-area table and its
protrusion table; RUN/painting/report.html (its zoomable view in a web browser) is named in the Log.

Macro: run("Stitch Painting", "captures=[/data/painting/tiles] mosaic=[/data/painting/layout.csv] lights=[/data/painting/rig_lights_mm.csv] regions=auto detect run=[/data/painting_run]");
(or "grid=4,3,0.2" instead of a layout; "calibration=[/data/CAL]" for the rig's lamps)
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

TITLE = "Stitch Painting"
COMMAND = "batch"


def main():
    dlg = dialogs.UVPSDialog(TITLE, __doc__)
    dialogs.add_param(dlg, (COMMAND, "captures"), key="captures")
    dialogs.add_param(dlg, (COMMAND, "mosaic"), key="mosaic")
    dialogs.add_param(dlg, (COMMAND, "grid"), key="grid")
    dialogs.add_run_field(dlg)
    dialogs.add_param(dlg, (COMMAND, "lights"), key="lights")
    dialogs.add_param(dlg, (COMMAND, "calibration"), key="calibration")
    dialogs.add_param(dlg, (COMMAND, "dark"), key="dark")
    dialogs.add_param(dlg, (COMMAND, "regions"), key="regions")
    dialogs.add_param(dlg, (COMMAND, "detect"), key="detect")
    values = dlg.show()
    if values is not None:
        menus.stitch_painting(values)


runner.run_menu(TITLE, main)
