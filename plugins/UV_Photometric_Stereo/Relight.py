"""Relight: render the surface under a virtual raking light from the run's normals and albedo.

Azimuth in degrees counter-clockwise from the image's right (+x), elevation above the canvas.
Opens and writes relight.tif.

Macro: run("Relight", "run=[/data/run] azimuth=315 elevation=15");
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

TITLE = "Relight"
COMMAND = "relight"


def main():
    dlg = dialogs.UVPSDialog(TITLE, __doc__)
    dialogs.add_run_field(dlg)
    dialogs.add_param(dlg, (COMMAND, "azimuth_deg"), key="azimuth", decimals=1)
    dialogs.add_param(dlg, (COMMAND, "elevation_deg"), key="elevation", decimals=1)
    values = dlg.show()
    if values is not None:
        menus.relight(values)


runner.run_menu(TITLE, main)
