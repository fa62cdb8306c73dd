"""Flat Field: divide every image by its own Legendre drop-off fit (uneven near-light lighting).

Opens the flat-fielded stack and the drop-off fits; writes flatfield/ (one TIFF per image),
dropoff.tif and lights.json into the run folder.

Macro: run("Flat Field", "capture=[Folder or files] images=[/data/capture] run=[/data/run] degree=4");
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

TITLE = "Flat Field"
COMMAND = "flatfield"


def main():
    dlg = dialogs.UVPSDialog(TITLE, __doc__)
    dialogs.add_capture_fields(dlg, COMMAND)
    dialogs.add_run_field(dlg)
    dialogs.add_light_fields(dlg, COMMAND, lights=False)
    values = dlg.show()
    if values is not None:
        menus.flat_field(values)


runner.run_menu(TITLE, main)
