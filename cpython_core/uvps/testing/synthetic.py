"""Synthetic UV-fluorescence photometric-stereo captures of a painting detail, with ground truth.

A capture is K 16-bit images of one painted area lit by K near point lamps. The scene imitates the
details of Pedernal shown in the paper (Figs. 2 and 3): 5 to 8 large colour areas with their own
fluorescence colour (light, lead-white-rich areas bright; dark areas weak), a canvas weave, brush
stroke ridges, flat whitish primer spots and metal-soap protrusions (domes 30-600 um wide, some with
a central "caldera"), crowded in the light areas and rare in the dark ones.

Frames and units follow ``docs/architecture.md``: x toward increasing column, y up (toward
decreasing row), z toward the camera; heights and widths in um, light positions in mm from the
image centre. The image model is the near-light Lambertian model of the paper, Eq. (1), with
inverse-square fall-off and attached shadows::

    I_k(x) = albedo(x) * E_k * (|L_k| / |L_k - X|)^2 * max(0, n(x) . (L_k - X) / |L_k - X|)

Ground truth (height, normals, albedo, colour areas, the protrusion list) is returned beside the
images and written to ``truth/`` by :func:`write_capture`; the pipeline never reads it.

On request the images also hold what a real capture holds and the estimators do not model
(:class:`SyntheticSpec`, :class:`Nuisances`, :data:`NUISANCE_TOP`): a black level, stray
light, vignetting, lamps with beams aimed off the centre and uneven azimuths, cracks with
cupped paint islands, cast shadows, protrusions of several shapes (mesas, lumpy outlines,
touching clusters, non-fluorescing ones) and weaves and strokes of several scales. Left at their
defaults, a capture is the same, bit for bit, as before they existed.

The code is split by part, its public names re-exported here (import from here): the description
(:mod:`.synthetic_spec`), the surface (:mod:`.synthetic_surface`), its rendering under the lamps with
their nuisances (:mod:`.synthetic_render`), :func:`make_capture` (:mod:`.synthetic_capture`), writing
to files (:mod:`.synthetic_files`) and pairs of captures over time (:mod:`.synthetic_pair`).
"""
from __future__ import annotations

from .synthetic_elements import ElementTruth, render_element_maps  # noqa: F401  (element maps: uvps elements)
from .synthetic_spec import (  # noqa: F401
    LIGHT_AREA_COLOURS,
    DARK_AREA_COLOURS,
    PROTRUSION_COLOUR,
    PRIMER_COLOUR,
    LUMINANCE,
    Nuisances,
    SyntheticSpec,
    PROTRUSION_GEOMETRIES,
    PROTRUSION_KINDS,
    MIXED_SHAPES,
    NUISANCE_TOP,
    NUISANCE_TYPICAL,
    IMPASTO,
    SyntheticCapture,
)
from .synthetic_render import (  # noqa: F401
    normals_from_height,
    pixel_centres_mm,
    shadow_masks,
    render_images,
    light_positions,
    render_dark_frame,
    CARD_TYPICAL,
    render_card,
)
from .synthetic_capture import (  # noqa: F401
    make_capture,
)
from .synthetic_files import (  # noqa: F401
    write_truth_run,
    DNG_BLACK,
    DNG_WHITE,
    write_dng,
    write_raw_capture,
    write_capture,
    _write_camera_tiff,  # tests/test_speed.py writes a camera TIFF with it
)
from .synthetic_pair import (  # noqa: F401
    LaterSpec,
    CapturePair,
    similarity_matrix,
    make_capture_pair,
)
