"""The names in a mosaic batch's painting folder, ``OUT/painting/`` (written by :mod:`uvps.painting`).

Apart from the painting itself: ``uvps batch`` names them (cleaning an interrupted batch's staging
folder, its outputs) without importing the painting's numeric code before its cluster has started
(:mod:`uvps.commands.batch`).
"""

PAINTING_DIR = "painting"
PAINTING_PROTRUSIONS, PAINTING_REGIONS, PAINTING_LAYOUT = "painting_protrusions.csv", "painting_regions.csv", \
    "layout.csv"
#: The painting's label images (protrusions: the painting's ids; regions: the colour areas), an OME-Zarr of their own.
PAINTING_LABELS = "labels.ome.zarr"
