"""uvps: photometric stereo by UV-induced fluorescence for paintings.

Lights from the images themselves (no calibration sphere), normals, RGB fluorescence albedo,
height in micrometres, and metal-soap protrusion detection and statistics.

Method: Salvant, Walton, Cossairt et al., "Photometric Stereo by UV-Induced Fluorescence to
Detect Protrusions on Georgia O'Keeffe's Paintings".

Two layers (docs/architecture.md): :mod:`uvps.core`, the numeric library (arrays and dataclasses in
and out, no files); above it :mod:`uvps.files` (captures, run folders), :mod:`uvps.report`,
:mod:`uvps.commands` (every command, side by side) and the CLI and file bridge. The generator of
synthetic captures is :mod:`uvps.testing`.
"""
__version__ = "0.1.0"

from .errors import UVPSComputeError, UVPSError, UVPSInputError  # noqa: F401
