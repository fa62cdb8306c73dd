"""The options of the photometric-stereo stages (:class:`RunOptions`), apart from the stages themselves.

The commands declare these options (``uvps.workflow.OPTION_PARAMS``, with their defaults from here) when
their command line is parsed; this module imports numpy and nothing of the numeric core, so that parsing
``uvps run`` does not import numba and scipy (0.8 s) before the command can start its own work
(``python -X importtime -m uvps run --help``). :mod:`uvps.core.pipeline` re-exports all of it.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

import numpy as np

from ..errors import UVPSInputError
from .level import LEVELS


#: ``lamp_beams``: auto, all, none (see :func:`uvps.core.lights.beyond_model`).
LAMP_BEAMS = ("auto", "all", "none")
#: ``samples``: auto, screened, all (see :func:`uvps.core.pipeline.sample_mode`).
SAMPLE_MODES = ("auto", "screened", "all")


@dataclass
class RunOptions:
    """Options of the photometric-stereo stages (everything else is read from the capture).

    Checked here (a value out of range raises :class:`~uvps.errors.UVPSInputError` naming the
    option); the commands declare the same options, with their help and Fiji labels, in
    :data:`uvps.workflow.OPTION_PARAMS`, whose defaults are these fields' (one place).
    """

    degree: int = 4                       #: Legendre degree of each image's drop-off fit, 1-8
    robust: bool = False                  #: rank-trimmed stereo
    integration: str = "fc"               #: "fc" (Frankot-Chellappa) or "dct" (Poisson, Neumann)
    refine_lights: bool = True            #: refine each lamp after the paper's equidistant solution
    sample_pixels: int = 30000            #: pixels sampled by the photometric residual, >= 500
    estimate_intensities: bool = False    #: known lights: each lamp's intensity from the images
    black_level: Optional[object] = None  #: counts, one number or one per channel (>= 0)
    offset: str = "auto"                  #: "auto", "measure" or "none"
    offset_degree: int = 0                #: 0 constant; 1-2 also stray light across the field
    lamp_beams: str = "auto"              #: known positions: the drop-off beyond the model divided out (LAMP_BEAMS)
    card: Optional[str] = None            #: the card the caller loaded (recorded; the card itself is ``run(card=)``)
    level: str = "plane"                  #: what is removed from the height (uvps.core.level.LEVELS)
    samples: str = "auto"                 #: which samples the normals use (SAMPLE_MODES, :func:`sample_mode`)

    def __post_init__(self):
        # the ranges uvps.workflow.OPTION_PARAMS declares (tests/test_spec.py holds the two together)
        for name, lo, hi in (("degree", 1, 8), ("sample_pixels", 500, None), ("offset_degree", 0, 2)):
            setattr(self, name, _whole(name, getattr(self, name), lo, hi))
        for name, choices in (("integration", ("fc", "dct")), ("offset", ("auto", "measure", "none")),
                              ("lamp_beams", LAMP_BEAMS + (True, False)), ("level", LEVELS),
                              ("samples", SAMPLE_MODES)):    # true / false: older run folders
            if getattr(self, name) not in choices or (name != "lamp_beams" and isinstance(getattr(self, name), bool)):
                shown = ", ".join(c for c in choices if isinstance(c, str))
                raise UVPSInputError(f"{name} must be one of {shown}; got {getattr(self, name)!r}")
        if self.black_level is not None:
            levels = [float(v) for v in np.atleast_1d(np.asarray(self.black_level, dtype=float))]
            if not levels or not all(np.isfinite(v) and v >= 0 for v in levels):
                raise UVPSInputError(f"black_level must be a number or comma-separated numbers >= 0; "
                                     f"got {self.black_level!r}")
            self.black_level = levels[0] if len(levels) == 1 else levels


def _whole(name: str, v, lo: int, hi: Optional[int]) -> int:
    """``v`` as an int in ``lo..hi`` (a whole float too), else the one-line error the commands give."""
    expected = f"an integer from {lo} to {hi}" if hi is not None else f"an integer >= {lo}"
    try:
        ok = not isinstance(v, bool) and float(v) == int(float(v)) and lo <= float(v) and (hi is None or float(v) <= hi)
    except (TypeError, ValueError, OverflowError):
        ok = False
    if not ok:
        raise UVPSInputError(f"{name} must be {expected}; got {v!r}")
    return int(float(v))
