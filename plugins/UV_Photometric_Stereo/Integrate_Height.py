"""Integrate Height: height map in micrometres from the run's normals.

Frankot-Chellappa (FFT, the paper's choice) or a DCT Poisson solver (Neumann boundary). The height
is known up to a constant: the median over valid pixels is set to 0. Levelled by default: the best
plane removed (a mean bias of the normals of 0.1-0.2 deg ramps the heights by tens of um across the
field), recorded in run.json so the raw height is depth.tif + that plane; form also removes a bow,
none keeps the heights as integrated. Opens and writes depth.tif.

Macro: run("Integrate Height", "run=[/data/run] integration=[Frankot-Chellappa (FFT)] level=plane");
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

TITLE = "Integrate Height"
COMMAND = "integrate"


def main():
    dlg = dialogs.UVPSDialog(TITLE, __doc__)
    dialogs.add_run_field(dlg)
    dialogs.add_param(dlg, (COMMAND, "integration"), key="integration")
    dialogs.add_param(dlg, (COMMAND, "level"), key="level")
    values = dlg.show()
    if values is not None:
        menus.integrate_height(values)


runner.run_menu(TITLE, main)
