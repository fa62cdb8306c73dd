"""uvps: photometric stereo by UV-induced fluorescence for paintings.

Lights from the images themselves (no calibration sphere), normals, RGB fluorescence albedo,
height in micrometres, and metal-soap protrusion detection and statistics.

Method: Salvant, Walton, Cossairt et al., "Photometric Stereo by UV-Induced Fluorescence to
Detect Protrusions on Georgia O'Keeffe's Paintings".
"""
__version__ = "0.1.0"

from .errors import UVPSComputeError, UVPSError, UVPSInputError  # noqa: F401
