"""Statistics and Report: protrusions per cm^2 by width for each colour area, and report.html.

Opens the report in the browser when run from the menu (in a macro only its path is logged) and
the "Regions" table; writes regions.csv, report.html and figures/*.png.

Macro: run("Statistics and Report", "run=[/data/run] bins=100");
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

TITLE = "Statistics and Report"
COMMAND = "stats"


def main():
    dlg = dialogs.UVPSDialog(TITLE, __doc__)
    dialogs.add_run_field(dlg)
    dialogs.add_param(dlg, (COMMAND, "bins_um"), key="bins")
    values = dlg.show()
    if values is not None:
        menus.statistics_and_report(values)


runner.run_menu(TITLE, main)
