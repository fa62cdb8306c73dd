"""Estimate Lights: each lamp's azimuth, elevation and position from the capture itself.

Fits a Legendre polynomial to every image's light drop-off, reads the azimuth off the fit and the
elevation from the drop-off's strength (near-light model, paper figure 1b-f). Opens a top view of
the lamps, a "Lights" table and the drop-off fits; writes lights.json, dropoff.tif and
figures/lights.png into the run folder.

Macro: run("Estimate Lights", "capture=[Folder or files] images=[/data/capture] run=[/data/run] degree=4");
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

TITLE = "Estimate Lights"
COMMAND = "lights"


def main():
    dlg = dialogs.UVPSDialog(TITLE, __doc__)
    dialogs.add_capture_fields(dlg, COMMAND)
    dialogs.add_run_field(dlg)
    dialogs.add_light_fields(dlg, COMMAND)
    dlg.help("<html><b>Estimate Lights</b>: each lamp's azimuth from the polar drop-off fit, and its "
             "position from the near-light model (Salvant et al., Fig. 1b-f). Leave <i>Lights file</i> "
             "empty to estimate; see docs/fiji/Estimate_Lights.md in the uvps folder.</html>")
    values = dlg.show()
    if values is not None:
        menus.estimate_lights(values)


runner.run_menu(TITLE, main)
