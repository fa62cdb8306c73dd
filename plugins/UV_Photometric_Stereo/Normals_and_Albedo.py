"""Normals and Albedo: per-pixel photometric stereo under near point lights.

Uses the lights of the run folder (lights.json from Estimate Lights) unless a lights file is given;
estimates them when there are none. Opens the normals (3 channels nx, ny, nz) and the RGB
fluorescence albedo; writes normals.tif, albedo.tif and gradients.tif.

Macro: run("Normals and Albedo", "capture=[Folder or files] images=[/data/capture] run=[/data/run] degree=4 robust");
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

TITLE = "Normals and Albedo"
COMMAND = "normals"


def main():
    dlg = dialogs.UVPSDialog(TITLE, __doc__)
    dialogs.add_capture_fields(dlg, COMMAND)
    dialogs.add_run_field(dlg)
    dialogs.add_light_fields(dlg, COMMAND)
    dialogs.add_param(dlg, (COMMAND, "robust"), key="robust")
    values = dlg.show()
    if values is not None:
        menus.normals_and_albedo(values)


runner.run_menu(TITLE, main)
