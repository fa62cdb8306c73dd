"""Calibrate Lamps: the lamps' directions (one sphere) or 3-D positions (two or more) from a capture
of spheres under the same lamp positions as the painting, into a calibration folder that Run Whole
Pipeline reuses for every capture taken with the lamps at the same marks.

Shows the sphere capture's first image with the spheres found drawn as circles (overlay and ROI
Manager): check them; a wrong or missed one is given by a CSV of circles (col,row,radius_px). A dark
sphere on a dark ground shows no rim under the lamps: a room-lit picture of the spheres in place
(Reference picture) is where they are found then.

Macro: run("Calibrate Lamps", "spheres=[/data/spheres] dark=[/data/dark.tif] calibration=[/data/CAL]");
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

TITLE = "Calibrate Lamps"
COMMAND = "calibrate"


def main():
    dlg = dialogs.UVPSDialog(TITLE, __doc__)
    dialogs.add_param(dlg, (COMMAND, "spheres"), key="spheres")
    dialogs.add_param(dlg, (COMMAND, "sphere_circles"), key="circles")
    dialogs.add_param(dlg, (COMMAND, "sphere_reference"), key="reference")
    dialogs.add_param(dlg, (COMMAND, "sphere_kind"), key="kind")
    dialogs.add_param(dlg, (COMMAND, "dark"), key="dark")
    dialogs.add_param(dlg, (COMMAND, "dome"), key="dome")
    dialogs.add_param(dlg, (COMMAND, "lights"), key="lights")
    dialogs.add_param(dlg, (COMMAND, "pixel_size_um"), key="pixel", decimals=3)
    dialogs.add_param(dlg, (COMMAND, "camera_distance_mm"), key="camera", decimals=1)
    dlg.directory("Calibration folder (outputs)", "")
    dlg.describe("Calibration folder (outputs)", "the folder of the calibration (calibration.json, "
                 "lights.json, rig.dome, dark.tif, spheres.png); give it to Run Whole Pipeline")
    dlg.help("<html><b>Calibrate Lamps</b>: one sphere gives the lamps' directions, two or more in "
             "opposite corners their positions, which pin the heights in um. See docs/capture.md "
             "and docs/fiji/Calibrate_Lamps.md in the uvps folder.</html>")
    values = dlg.show()
    if values is not None:
        menus.calibrate_lamps(values)


runner.run_menu(TITLE, main)
