"""Run Whole Pipeline: capture -> lights, flat-field, normals, albedo, height, and optionally
colour areas, protrusion detection and the report, in one call.

The height is levelled by default (its best plane removed, recorded in run.json so the raw height
is rebuilt; Level: form also removes a bow, none keeps the heights as integrated).
Opens the normals, the height, the lamps' top view and the albedo (with protrusion outlines when
detection ran); everything is written into the run folder (run.json records the parameters).

Macro: run("Run Whole Pipeline", "capture=[Folder or files] images=[/data/capture] run=[/data/run] degree=4 integration=[Frankot-Chellappa (FFT)] level=plane regions=auto detect");
(add "flatfield" to also write the flat-fielded images, "zarr" for OME-Zarr pyramids of the results,
"calibration=[/data/CAL]" for the lamps of Calibrate Lamps)
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

TITLE = "Run Whole Pipeline"
COMMAND = "run"


def main():
    dlg = dialogs.UVPSDialog(TITLE, __doc__)
    dialogs.add_capture_fields(dlg, COMMAND)
    dialogs.add_run_field(dlg)
    dialogs.add_light_fields(dlg, COMMAND)
    dialogs.add_param(dlg, (COMMAND, "calibration"), key="calibration")
    dialogs.add_param(dlg, (COMMAND, "robust"), key="robust")
    dialogs.add_param(dlg, (COMMAND, "integration"), key="integration")
    dialogs.add_param(dlg, (COMMAND, "level"), key="level")
    dialogs.add_param(dlg, (COMMAND, "regions"), key="regions")
    dialogs.add_param(dlg, (COMMAND, "detect"), key="detect")
    dialogs.add_param(dlg, (COMMAND, "flatfield_images"), key="flatfield")
    dialogs.add_param(dlg, (COMMAND, "ome_zarr"), key="zarr")
    values = dlg.show()
    if values is not None:
        menus.run_whole_pipeline(values)


runner.run_menu(TITLE, main)
