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
"""
from __future__ import annotations

import csv
import dataclasses
import logging
import math
import zlib
from dataclasses import dataclass
from pathlib import Path
from typing import Optional

import numpy as np
import tifffile
from scipy import ndimage
from scipy.spatial import cKDTree

from ..errors import UVPSInputError
from ..core.stack import Capture
from ..files.io import write_imagej_tiff
from ..core.irradiance import irradiance
from ..files.outputs import Progress, atomic_output_dir, report, write_json_atomic
from .synthetic_elements import ElementTruth, render_element_maps  # noqa: F401  (element maps: uvps elements)

logger = logging.getLogger(__name__)

#: Fluorescence colours (linear RGB, relative) of the colour areas. Light (lead-white-rich)
#: areas fluoresce brightly, dark areas weakly (paper, Sec. "Detection of protrusions").
LIGHT_AREA_COLOURS = {
    "beige": (0.80, 0.73, 0.58),
    "light green": (0.58, 0.76, 0.52),
    "light red": (0.84, 0.55, 0.49),
    "yellow": (0.86, 0.80, 0.42),
    "yellow green": (0.70, 0.80, 0.40),
}
DARK_AREA_COLOURS = {
    "dark green": (0.15, 0.27, 0.15),
    "dark red": (0.29, 0.12, 0.10),
    "orange": (0.44, 0.26, 0.10),
}
#: Whitish-yellow fluorescence of lead-soap protrusions and bluish-white of the chalk primer.
PROTRUSION_COLOUR = (1.0, 0.95, 0.76)
PRIMER_COLOUR = (0.90, 0.92, 0.97)
#: Rec. 709 luminance weights, used for grey captures.
LUMINANCE = np.array([0.2126, 0.7152, 0.0722])

_UM2_PER_CM2 = 1e8


@dataclass
class Nuisances:
    """What a real capture holds beyond the image model, as rendered: the realised values.

    :func:`render_images` applies them; :func:`make_capture` draws them from the
    :class:`SyntheticSpec` and returns them as truth (``SyntheticCapture.nuisances``). Every
    attribute's default means "absent", and then the renderer does exactly what it did without.

    Attributes
    ----------
    black_level : (C,) array or None
        Counts added to every image after the noise and before quantisation (a pedestal left in
        the files); C = 1 for grey.
    stray_light : (M, N) or (M, N, C) array or None
        Light added at the sensor, the same in every image, in the units of ``albedo * E`` (so
        the exposure scales it like the signal and it gets photon noise). Not multiplied by the
        albedo, the lamps' fall-off or the vignetting.
    vignetting : (M, N) array or None
        Fall-off of the image-forming light (1 at the optical centre), multiplying the direct
        signal of every image.
    beam_axes : (K, 3) array or None
        Unit vector of each lamp's beam axis, from the lamp toward its aim point (near lights
        only). The irradiance is multiplied by ``max(0, cos(angle to the axis))**beam_exponent``.
    beam_exponent : float
        See ``beam_axes``.
    cast_shadows : bool
        Zero direct irradiance where the relief hides the lamp (see :func:`shadow_masks`).
    shadowed : (K, M, N) bool array or None
        The cast-shadow masks; computed by the renderer when ``cast_shadows`` and None.
    cracks : (M, N) bool array or None
        Truth only (the renderer ignores it): the crack grooves, whose relief is in the height.
    strokes : (M, N) float32 array or None
        Truth only: the brush strokes' relief (um), part of the height; set with impasto.
    info : dict
        How they were drawn (JSON-ready), written to ``truth.json`` by :func:`write_capture`.
    """

    black_level: Optional[np.ndarray] = None
    stray_light: Optional[np.ndarray] = None
    vignetting: Optional[np.ndarray] = None
    beam_axes: Optional[np.ndarray] = None
    beam_exponent: float = 0.0
    cast_shadows: bool = False
    shadowed: Optional[np.ndarray] = None
    cracks: Optional[np.ndarray] = None
    strokes: Optional[np.ndarray] = None
    info: dict = dataclasses.field(default_factory=dict)


@dataclass
class SyntheticSpec:
    """What to synthesise. Every option has a physically sensible default (a 18 x 24 mm detail).

    Densities are per cm^2 of the field; widths and heights in um; distances in mm.
    Protrusion widths are log-normal about ``width_median_um`` (150; sigma 0.45) within
    ``width_um``: 100 puts a third of them below 80 um (a few pixels of 15 um).
    ``n_ridges`` / ``n_primer_spots`` = None means ``ridge_density`` (4) ridges and
    ``primer_density`` (3) primer spots per cm^2.
    Each image's irradiance at the centre is 1 +- ``intensity_jitter`` (as if the exposure were reset
    per image); ``fixed_exposure`` instead models one lamp at one exposure: that drift times
    (median distance / distance)^2, so a lamp at 500 mm gives an image 4x darker than at 250 mm.
    ``weave_period_um`` and ``weave_amplitude_um`` take one value or one per weave scale (e.g.
    ``(250, 800)`` and ``(3, 8)``: a fine and a coarse weave; artists' canvases have about 10-40
    threads per cm, and the weave shows through the paint by a few um); ``ridge_width_um`` and
    ``ridge_height_um`` are the ranges of the brush-stroke ridges (e.g. 60-1500 um wide, 5-40 um
    high for strokes from a fine brush to a broad one).

    **Nuisances of a real capture.** The fields after ``seed`` put into the images what the
    estimators do not model. Their defaults leave them out, and then a capture is the very same,
    bit for bit, as before they existed (new random numbers come from separate streams,
    ``default_rng((seed, tag))``, so switching one on leaves the scene, the lamps and the noise
    of the others as they were; ``protrusion_shapes``, ``height_um``, ``ridge_*`` and
    ``cupping_um`` change the placement of protrusions and hence the main stream). The realistic
    ranges below are where a careful capture lands; :data:`NUISANCE_TOP` holds the top of each.

    - ``black_level`` (counts, 0): a pedestal left in the files, added to every image after the
      noise and before quantisation; a scalar or one value per channel. Realistic 0-500 counts:
      a residual of imperfect or per-channel black subtraction in 16-bit files, up to ~3 % of
      the median signal of a well-exposed capture. (Files written with no black subtraction at
      all hold the whole raw pedestal, e.g. 2048 counts on 14-bit Canon bodies, more if scaled
      to 16 bit; a dark frame (``run``'s ``dark`` parameter) removes that.)
    - ``stray_light`` (fraction of the median noise-free signal, 0): veiling glare and stray
      light, additive at the sensor (not multiplied by the albedo), the same in every image,
      smooth across the field (a broad gaussian veil on a tilted floor), coloured like the
      median signal. Realistic 0-0.03: the veiling glare index of photographic lenses (measured
      as in ISO 9358) is typically a few per cent; a lamp's visible leak or room light adds to
      it.
    - ``vignetting`` (fractional fall-off at the image corners, 0): lens vignetting common to
      all images, multiplying the direct signal: ``1 / (1 + (r / f)^2)^2`` (the cos^4 law) about
      an optical centre up to 5 % of the half-diagonal off the image centre, ``f`` set so the
      fall-off at the half-diagonal is this fraction. Realistic 0-0.4 (0 to ~0.7 EV): lens tests
      of 90-105 mm macro lenses on full frame report on the order of 1 EV wide open and a few
      tenths of an EV stopped down; a crop of the frame has less.
    - ``beam_exponent`` (dimensionless n, 0 = isotropic point source): the irradiance is
      multiplied by ``cos^n`` of the angle between the lamp's beam axis and the ray to the
      surface point; a beam of half-angle (at half maximum) t has ``n = -ln 2 / ln cos t``: 45
      at 10 deg, 20 at 15 deg, 11 at 20 deg, 4.8 at 30 deg. Realistic 0-30 for UV LED torches
      of 12-30 deg.
    - ``beam_aim_error_deg`` (deg, 0): each lamp is aimed at a point off the image centre, its
      axis within this angle of the ray to the centre (uniform over that cone). Realistic 0-5
      for hand-aimed lamps (5 deg at 250-500 mm moves the beam centre by 22-44 mm).
    - ``azimuth_jitter`` (fraction of the even spacing 360 / K, 0.25): lamp azimuths are evenly
      spread, each moved by up to this fraction. Realistic up to 0.45 for lamps placed by hand.
      With ``intensity_jitter`` (0.1; up to 0.2 for battery LED torches that fade during a
      session) and ``distance_mm`` the lamps are unequal.
    - ``cupping_um`` (um, 0): craquelure: a network of cracks (Voronoi cells of
      ``crack_cell_mm``, wavy), each paint island cupped (a dish raised toward its edges by up to
      ``cupping_um``) and each crack a narrow groove (25-50 um wide at half depth) down to
      ``cupping_um / 2`` below the flat paint. Protrusions avoid the grooves. Realistic 0-50 for
      a sound 20th-century painting (old paintings reach hundreds of um).
    - ``crack_cell_mm`` ((low, high) mm, (1, 4)): spacing of the cracks (island sizes).
    - ``cast_shadows`` (bool, False): cast shadows of the relief (a 150 um protrusion under a
      lamp at 20 deg elevation shades ~28 px of 15 um): zero direct irradiance where the
      surface hides the lamp (:func:`shadow_masks`); stray light and black level still apply.
    - ``protrusion_shapes`` (None or {kind: weight}, None = the paper's domes, ``crater_fraction``
      of them with a caldera): the fraction of placements of each kind, among ``dome``,
      ``crater``, ``mesa`` (flat plateau), ``irregular`` (lumpy outline), ``cluster`` (2-4
      touching protrusions) and ``dark`` (not fluorescing: the albedo of the paint around it, or
      down to half of it); clusters and dark ones take their geometry from the first four
      weights. ``crater_fraction`` is then unused. :data:`MIXED_SHAPES` is a mix.
    - ``height_um`` (None or (low, high) um): heights are clipped into this range (today's height
      is 0.15-0.35 x the width). With ``protrusion_shapes`` realistic widths are 40-500 um and
      heights 5-150 um.

    **Impasto** (:data:`IMPASTO` holds the top of each range). The defaults give smooth strokes
    tapered over 15 % of their length at both ends, laid by their maximum where they meet.

    - ``ridge_density`` (strokes per cm^2, 4; used when ``n_ridges`` is None): 8 for paint worked
      with a loaded brush.
    - ``ridge_blunt_fraction`` (0): the fraction of stroke ends that are blunt: the stroke runs
      at full height to a rounded end, with the paint the brush leaves piled there (a mound
      20-50 % above the stroke, about one stroke width long).
    - ``ridge_ripple`` ((low, high), relative, (0, 0)): ripples along the stroke, the height
      modulated by ``1 + r sin(2 pi s / lambda)``, r drawn in this range, lambda 200-800 um.
    - ``ridge_groove_um`` ((low, high) um, (0, 0)): bristle grooves along the stroke, 1-4 um
      deep in real impasto, 40-120 um apart.
    - ``ridge_crossing_fraction`` (0): the fraction of strokes laid at any angle across the
      others and added on top of them (paint over dry paint), not merged by the maximum.
    - ``on_stroke_fraction`` (0): the fraction of protrusions placed on a stroke or against its
      flank (their relief adds to the stroke's); truth column ``on_stroke``.
    - ``primer_density`` (spots per cm^2, 3; used when ``n_primer_spots`` is None): bare primer,
      flat and bright (a weakly fluorescing protrusion's albedo is 5-20 % above its paint).
    """

    shape: tuple = (1200, 1600)
    n_lights: int = 12
    pixel_size_um: float = 15.0
    rgb: bool = True
    elevation_deg: tuple = (20.0, 60.0)
    distance_mm: tuple = (250.0, 500.0)
    intensity_jitter: float = 0.1
    fixed_exposure: bool = False
    n_regions: Optional[int] = None
    protrusion_density_light: float = 45.0
    protrusion_density_dark: float = 5.0
    width_um: tuple = (30.0, 600.0)
    width_median_um: float = 150.0
    weak_fraction: float = 0.2
    crater_fraction: float = 0.3
    n_ridges: Optional[int] = None
    n_primer_spots: Optional[int] = None
    weave_period_um: float | tuple = 450.0
    weave_amplitude_um: float | tuple = 3.0
    bow_um: float = 15.0
    exposure_fraction: float = 0.75
    full_well_e: float = 60000.0
    read_noise: float = 4.0
    noise: bool = True
    seed: int = 0
    # Nuisances of a real capture (see the docstring); the defaults leave them out.
    black_level: float | tuple = 0.0
    stray_light: float = 0.0
    vignetting: float = 0.0
    beam_exponent: float = 0.0
    beam_aim_error_deg: float = 0.0
    azimuth_jitter: float = 0.25
    cupping_um: float = 0.0
    crack_cell_mm: tuple = (1.0, 4.0)
    cast_shadows: bool = False
    protrusion_shapes: Optional[dict] = None
    height_um: Optional[tuple] = None
    ridge_width_um: tuple = (100.0, 300.0)
    ridge_height_um: tuple = (5.0, 20.0)
    # Impasto (see the docstring); the defaults give today's smooth strokes.
    ridge_density: float = 4.0
    ridge_blunt_fraction: float = 0.0
    ridge_ripple: tuple = (0.0, 0.0)
    ridge_groove_um: tuple = (0.0, 0.0)
    ridge_crossing_fraction: float = 0.0
    on_stroke_fraction: float = 0.0
    primer_density: float = 3.0

    @classmethod
    def realistic(cls, level: str = "top", *, only=None, **fields) -> "SyntheticSpec":
        """A spec with every nuisance (or those in ``only``) at ``level`` of its range.

        Parameters
        ----------
        level : {"top", "typical"}
            ``"top"``: :data:`NUISANCE_TOP`; ``"typical"``: :data:`NUISANCE_TYPICAL` (half-way).
        only : iterable of str, optional
            Keys of :data:`NUISANCE_TOP` to switch on (default: all).
        **fields
            Other :class:`SyntheticSpec` fields, e.g. ``shape=(300, 400)``; they win.

        Examples
        --------
        >>> spec = SyntheticSpec.realistic(only=["black_level", "vignetting"], seed=3)
        >>> spec.black_level, spec.vignetting, spec.stray_light
        (500.0, 0.4, 0.0)
        """
        table = {"top": NUISANCE_TOP, "typical": NUISANCE_TYPICAL}.get(level)
        if table is None:
            raise UVPSInputError(f"level must be 'top' or 'typical'; got {level!r}")
        names = list(table) if only is None else list(only)
        unknown = sorted(set(names) - set(table))
        if unknown:
            raise UVPSInputError(f"unknown nuisance(s) {unknown}; expected some of {sorted(table)}")
        values = {}
        for name in names:
            values.update({key: dict(val) if isinstance(val, dict) else val
                           for key, val in table[name].items()})
        values.update(_checked_overrides(fields))
        return cls(**values)


#: Kinds of protrusion for :attr:`SyntheticSpec.protrusion_shapes`: four geometries, then
#: touching clusters and non-fluorescing ones (which take a geometry from the first four).
PROTRUSION_GEOMETRIES = ("dome", "crater", "mesa", "irregular")
PROTRUSION_KINDS = PROTRUSION_GEOMETRIES + ("cluster", "dark")
#: A mix of every kind, for benchmarks.
MIXED_SHAPES = {"dome": 0.30, "crater": 0.15, "mesa": 0.15, "irregular": 0.20, "cluster": 0.10,
                "dark": 0.10}

#: Every nuisance at the top of its realistic range (see :class:`SyntheticSpec`), one entry per
#: nuisance, each a dict of SyntheticSpec fields: ``make_capture(**NUISANCE_TOP["black_level"])``
#: switches one on alone, :meth:`SyntheticSpec.realistic` all of them.
NUISANCE_TOP = {
    "black_level": {"black_level": 500.0},
    "stray_light": {"stray_light": 0.03},
    "vignetting": {"vignetting": 0.4},
    "beams": {"beam_exponent": 30.0, "beam_aim_error_deg": 5.0},
    "unequal_lamps": {"azimuth_jitter": 0.45, "intensity_jitter": 0.2},
    "cupping": {"cupping_um": 50.0},
    "cast_shadows": {"cast_shadows": True},
    "protrusion_shapes": {"protrusion_shapes": MIXED_SHAPES, "width_um": (40.0, 500.0),
                          "height_um": (5.0, 150.0)},
    "weave": {"weave_period_um": (250.0, 800.0), "weave_amplitude_um": (3.0, 8.0)},
    "strokes": {"ridge_width_um": (60.0, 1500.0), "ridge_height_um": (5.0, 40.0)},
}
#: Half-way up each realistic range (switches, shapes and scales as in :data:`NUISANCE_TOP`).
NUISANCE_TYPICAL = {
    "black_level": {"black_level": 250.0},
    "stray_light": {"stray_light": 0.015},
    "vignetting": {"vignetting": 0.2},
    "beams": {"beam_exponent": 15.0, "beam_aim_error_deg": 2.5},
    "unequal_lamps": {"azimuth_jitter": 0.35, "intensity_jitter": 0.15},
    "cupping": {"cupping_um": 25.0},
    "cast_shadows": {"cast_shadows": True},
    "protrusion_shapes": NUISANCE_TOP["protrusion_shapes"],
    "weave": {"weave_period_um": (250.0, 800.0), "weave_amplitude_um": (2.0, 4.0)},
    "strokes": {"ridge_width_um": (80.0, 800.0), "ridge_height_um": (5.0, 30.0)},
}

#: Paint as real impasto at the top of each range (see :class:`SyntheticSpec`, "Impasto"):
#: strokes up to 40 um high at twice the default density, half their ends blunt, ripples,
#: bristle grooves, 30 % crossing the others; a fifth of the protrusions on or against a stroke,
#: a quarter weakly fluorescing, and 40 bare primer spots on a 24 x 18 mm field (9 per cm^2).
IMPASTO = {"ridge_width_um": (60.0, 1500.0), "ridge_height_um": (5.0, 40.0),
           "ridge_density": 8.0, "ridge_blunt_fraction": 0.5, "ridge_ripple": (0.1, 0.35),
           "ridge_groove_um": (1.0, 4.0), "ridge_crossing_fraction": 0.3,
           "on_stroke_fraction": 0.2, "weak_fraction": 0.25, "primer_density": 9.0}


@dataclass
class SyntheticCapture:
    """A synthetic capture and its ground truth (see the module docstring for the frames).

    ``protrusions`` holds equal-length numpy columns: ``id``, ``x_px`` (column), ``y_px`` (row),
    ``width_um`` (equivalent-circle diameter of the footprint), ``height_um`` (peak above the
    surrounding surface), ``crater``, ``weak``, ``region``, ``aspect``, ``angle_deg``, ``shape``
    (one of :data:`PROTRUSION_GEOMETRIES`), ``cluster`` (0 alone, else the id shared by touching
    members) and ``dark`` (not fluorescing). ``nuisances`` holds what the images hold beyond the
    image model (black level, stray light, vignetting, beams, cast shadows, cracks) with how they
    were drawn in ``nuisances.info``; ``intensities`` are the lamps' ``E_k`` (on the beam axis
    when the lamps have beams; ``nuisances.info["lamps"]`` has the irradiance at the centre).
    """

    images: np.ndarray
    light_positions_mm: np.ndarray
    intensities: np.ndarray
    height_um: np.ndarray
    normals: np.ndarray
    albedo: np.ndarray
    regions: np.ndarray
    region_names: list
    region_light: list
    protrusions: dict
    spec: SyntheticSpec
    exposure: float = 1.0
    gain: float = 1.0
    nuisances: Nuisances = dataclasses.field(default_factory=Nuisances)

    def as_capture(self, *, lights: str = "estimate"):
        """This capture as :func:`uvps.files.io.read_capture` would return it from the written files.

        ``lights``: "estimate" (no light file), or "positions" (the true lamp positions and
        intensities, as a calibrated positions file gives them).
        """

        K = self.images.shape[0]
        known = lights == "positions"
        return Capture(images=self.images, files=[f"uv_{k:02d}.tif" for k in range(K)],
                       pixel_size_um=self.spec.pixel_size_um, mask=None,
                       saturation=float(np.iinfo(self.images.dtype).max) if self.images.dtype.kind == "u" else None,
                       light_directions=None, light_positions_mm=self.light_positions_mm if known else None,
                       bit_depth=str(self.images.dtype), light_intensities=self.intensities if known else None)


# --------------------------------------------------------------------------------------------
# Geometry and rendering
# --------------------------------------------------------------------------------------------


def normals_from_height(height_um, *, pixel_size_um) -> np.ndarray:
    """Unit normals of a height map by fourth-order central differences.

    Parameters
    ----------
    height_um : (M, N) array
        Height toward the camera in um.
    pixel_size_um : float
        Pixel size in um.

    Returns
    -------
    normals : (M, N, 3) float32
        ``n = (-p, -q, 1) / sqrt(1 + p^2 + q^2)`` with ``p = dz/dx``, ``q = dz/dy`` (y up, so
        ``q = -dz/d(row) / pixel size``). Fourth-order central differences, ``(-z[i+2] + 8 z[i+1]
        - 8 z[i-1] + z[i-2]) / 12``, two pixels in from the border; second-order ones (``np.gradient``)
        on the two outer rows and columns.

    Notes
    -----
    The normals are those of the continuous surface the height map samples. The plain central
    difference ``(z[i+1] - z[i-1]) / 2`` is the derivative of that surface smoothed over two pixels
    (frequency response ``sin(w) / w``): on a Gaussian bump 100 um wide at 15 um per pixel it makes
    the steep slopes 3.8 % shallow (median), and every height integrated from those normals came out
    ~2.5 % low against the height map, also with the true lamps (measured by
    ``scripts/analysis_lamp_elevation.py heights ROW SEED`` on such normals). The
    fourth-order difference (response ``(8 sin w - sin 2w) / 6w``) is within 0.25 % there (a test).
    """
    h = np.asarray(height_um, dtype=np.float64)
    if h.ndim != 2 or min(h.shape) < 2:
        raise UVPSInputError(f"height_um must be a 2-D array of at least 2 x 2; "
                             f"got shape {h.shape}")
    if not pixel_size_um > 0:
        raise UVPSInputError(f"pixel_size_um must be > 0; got {pixel_size_um}")
    return _normals64(h, float(pixel_size_um)).astype(np.float32)


def _derivative4(h, axis: int, spacing: float) -> np.ndarray:
    """d h / d axis by fourth-order central differences (second order on the two outer lines)."""
    d = np.gradient(h, spacing, axis=axis)
    if h.shape[axis] >= 5:
        z, dz = np.moveaxis(h, axis, 0), np.moveaxis(d, axis, 0)     # views: dz writes into d
        dz[2:-2] = (z[:-4] - 8.0 * z[1:-3] + 8.0 * z[3:-1] - z[4:]) / (12.0 * spacing)
    return d


def _normals64(h, pixel_size_um):
    d_row = _derivative4(h, 0, pixel_size_um)
    d_col = _derivative4(h, 1, pixel_size_um)
    p = d_col
    q = -d_row                                   # y is up: rows grow downward
    norm = np.sqrt(1.0 + p * p + q * q)
    return np.stack([-p / norm, -q / norm, 1.0 / norm], axis=-1)


def pixel_centres_mm(shape, pixel_size_um):
    """World x (1, N) and y (M, 1) of the pixel centres in mm (architecture.md)."""
    m, n = shape
    px_mm = pixel_size_um / 1000.0
    x = ((np.arange(n) - (n - 1) / 2.0) * px_mm)[None, :]
    y = (((m - 1) / 2.0 - np.arange(m)) * px_mm)[:, None]
    return x, y


def _shading(normals, height_um, pixel_size_um, positions, directions, intensities, *,
             beam_axes=None, beam_exponent=0.0, shadowed=None):
    """Yield, per light, ``E_k * fall-off * max(0, n . l) [* beam] [* lit]`` as (M, N) float64
    (:func:`uvps.core.irradiance.irradiance`)."""
    x, y = pixel_centres_mm(height_um.shape, pixel_size_um)
    z = np.asarray(height_um, dtype=np.float64) / 1000.0
    return irradiance(normals, x, y, z, intensities=intensities, positions_mm=positions,
                      directions=directions, beam_axes=beam_axes, beam_exponent=beam_exponent,
                      shadowed=shadowed)


def shadow_masks(height_um, *, pixel_size_um, light_positions_mm=None, light_directions=None,
                 tile=128) -> np.ndarray:
    """Cast shadows of a relief: where the surface hides each lamp.

    Parameters
    ----------
    height_um : (M, N) array
        Height toward the camera in um.
    pixel_size_um : float
        Pixel size in um.
    light_positions_mm : (K, 3) array, optional
        Near point lights, mm from the image centre in the world frame.
    light_directions : (K, 3) array, optional
        Far lights: vectors toward the lights. Exactly one of the two.
    tile : int
        Side of the tiles (pixels) that share one marching direction.

    Returns
    -------
    shadowed : (K, M, N) bool
        True where the segment from the surface point to the lamp passes below the surface.

    Notes
    -----
    A horizon test: from every pixel, march in the image plane toward the foot of the lamp, one
    pixel per step along the major axis, the height interpolated linearly across the other axis,
    and compare the surface with the ray's height ``z + t * tan(elevation)`` (the elevation of
    the lamp seen from that pixel, exact for near lights). The march stops once the ray is above
    every height within reach. Within a ``tile`` x ``tile`` block the direction is the one from
    the block's centre (for a lamp 250 mm away the ray then wanders less than 0.2 px over a 40 px
    shadow); outside the image nothing occludes. Cost: about ``6 * K * M * N * T`` flops, T the
    longest shadow in pixels (a 150 um step under a lamp at 20 deg elevation: 28 px at 15 um).

    Examples
    --------
    A 100 um step (x > 0 high) under a lamp low on the +x side shades the foot of the step over
    ``100 um / tan(20 deg) = 275 um`` (18 px of 15 um):

    >>> import numpy as np
    >>> h = np.zeros((8, 80)); h[:, 40:] = 100.0
    >>> el = np.radians(20.0)
    >>> lamp = [[np.cos(el), 0.0, np.sin(el)]]
    >>> int(shadow_masks(h, pixel_size_um=15.0, light_directions=lamp)[0, 4].sum())
    18
    """
    h = np.asarray(height_um, dtype=np.float64)
    if h.ndim != 2 or min(h.shape) < 2 or not pixel_size_um > 0:
        raise UVPSInputError(f"height_um must be (M, N) with M, N >= 2 and pixel_size_um > 0; "
                             f"got shape {h.shape}, pixel_size_um={pixel_size_um}")
    if (light_positions_mm is None) == (light_directions is None):
        raise UVPSInputError("give exactly one of light_positions_mm and light_directions")
    far = light_directions is not None
    lamps = np.asarray(light_directions if far else light_positions_mm, dtype=np.float64)
    if lamps.ndim != 2 or lamps.shape[1] != 3:
        raise UVPSInputError(f"{'light_directions' if far else 'light_positions_mm'} must be "
                             f"(K, 3); got shape {lamps.shape}")
    if int(tile) != tile or tile < 8:
        raise UVPSInputError(f"tile must be an integer >= 8; got {tile}")
    return np.stack([_shadow_mask(h, float(pixel_size_um), lamp, far, int(tile))
                     for lamp in lamps])


def _shadow_mask(h, px, lamp, far, tile):
    """One lamp's cast shadow (M, N) bool; see :func:`shadow_masks`."""
    m, n = h.shape
    x, y = pixel_centres_mm((m, n), px)
    if far:
        horiz = math.hypot(lamp[0], lamp[1])
        tan = np.full((m, n), lamp[2] / horiz if horiz > 0 else np.inf)
    else:
        with np.errstate(divide="ignore"):
            tan = (lamp[2] - h / 1000.0) / np.hypot(lamp[0] - x, lamp[1] - y)
    out = np.zeros((m, n), dtype=bool)
    if np.all(tan <= 0):
        out[:] = True                                   # the lamp is below the canvas
        return out
    tan = np.clip(tan, 1e-6, None)
    hmin, hmax = float(h.min()), float(h.max())
    if hmax - hmin <= 0:
        return out
    # the farthest any pixel can be shaded from (in pixels): the global height range at the
    # lowest elevation, and never farther than the image
    reach = int(min(math.ceil((hmax - hmin) / (float(tan.min()) * px)) + 2, m + n))
    big = np.float32(-1e30)
    pad = np.full((m + 2 * reach, n + 2 * reach), big, dtype=np.float32)
    pad[reach:reach + m, reach:reach + n] = h
    h32 = h.astype(np.float32)
    tol = np.float32(1e-4 * max(abs(hmin), abs(hmax)) + 1e-3)
    for r0 in range(0, m, tile):
        r1 = min(r0 + tile, m)
        for c0 in range(0, n, tile):
            c1 = min(c0 + tile, n)
            hz = h32[r0:r1, c0:c1]
            tz = tan[r0:r1, c0:c1]
            lo, tmin = float(hz.min()), float(tz.min())
            near = pad[r0:r1 + 2 * reach, c0:c1 + 2 * reach]
            high = float(near.max())
            if far:
                ux, uy = lamp[0], lamp[1]
            else:
                row_c, col_c = (r0 + r1 - 1) / 2.0, (c0 + c1 - 1) / 2.0     # tile centre
                ux = lamp[0] - (col_c - (n - 1) / 2.0) * px / 1000.0
                uy = lamp[1] - ((m - 1) / 2.0 - row_c) * px / 1000.0
            norm = math.hypot(ux, uy)
            if norm == 0 or high <= lo:
                continue
            d_col, d_row = ux / norm, -uy / norm        # y up: rows grow downward
            major = max(abs(d_col), abs(d_row))
            step_um = px / major
            steps = min(int(math.ceil((high - lo) / (tmin * step_um))), reach - 1)
            if steps < 1:
                continue
            rise = (tz * step_um).astype(np.float32)
            ray = np.zeros_like(hz)
            acc = np.full_like(hz, big)
            buf = np.empty_like(hz)
            buf2 = np.empty_like(hz)
            for j in range(1, steps + 1):
                fr, fc = j * d_row / major, j * d_col / major
                if abs(d_col) >= abs(d_row):         # march along columns, rows in between
                    k = math.floor(fr)
                    w = fr - k
                    dc = int(round(fc))
                    a0 = (reach + r0 + k, reach + c0 + dc)
                    a1 = (a0[0] + 1, a0[1])
                else:                                # march along rows, columns in between
                    k = math.floor(fc)
                    w = fc - k
                    dr = int(round(fr))
                    a0 = (reach + r0 + dr, reach + c0 + k)
                    a1 = (a0[0], a0[1] + 1)
                s0 = pad[a0[0]:a0[0] + r1 - r0, a0[1]:a0[1] + c1 - c0]
                np.multiply(s0, np.float32(1.0 - w), out=buf)
                if w > 0:
                    s1 = pad[a1[0]:a1[0] + r1 - r0, a1[1]:a1[1] + c1 - c0]
                    np.multiply(s1, np.float32(w), out=buf2)
                    buf += buf2
                ray += rise
                buf -= ray
                np.maximum(acc, buf, out=acc)
            out[r0:r1, c0:c1] = acc > hz + tol
    return out


def render_images(height_um, albedo, *, pixel_size_um, light_positions_mm=None,
                  light_directions=None, intensities=None, rng=None, noise=True, gain=1.0,
                  read_noise=4.0, exposure=None, dtype=np.uint16,
                  nuisances: Optional[Nuisances] = None) -> np.ndarray:
    """Render a photometric-stereo stack of a height map under near or far lights.

    Parameters
    ----------
    height_um : (M, N) array
        Height toward the camera in um.
    albedo : (M, N) or (M, N, C) array
        Fluorescence albedo (linear).
    pixel_size_um : float
        Pixel size in um.
    light_positions_mm : (K, 3) array, optional
        Near point lights, mm from the image centre in the world frame.
    light_directions : (K, 3) array, optional
        Far lights: unit vectors toward the lights (normalised here). Exactly one of the two.
    intensities : (K,) array, optional
        ``E_k``, the irradiance at the image centre (default 1).
    rng : numpy Generator or int, optional
        Noise source (an int seeds a new Generator).
    noise : bool
        Add photon noise (Poisson, via ``gain`` counts per electron) and Gaussian read noise
        (``read_noise`` counts).
    exposure : float, optional
        Counts per unit of ``albedo * E``. None: 1 when ``dtype`` is None or floating, else
        chosen so that the brightest noise-free sample (black level aside) is 75 % of the
        dtype's full scale.
    dtype : numpy dtype or None
        Integer: rounded and clipped to the dtype range. None: float64 (exact model values when
        ``noise`` is False and ``exposure`` is 1).
    nuisances : Nuisances, optional
        Beams, cast shadows, vignetting, stray light and black level (see :class:`Nuisances`).
        If ``cast_shadows`` is set and ``shadowed`` is None, the masks are computed here and
        stored into it.

    Returns
    -------
    images : (K, M, N) or (K, M, N, C) array

    Notes
    -----
    Image model of the paper, Eq. (1), with near lights (architecture.md)::

        I_k = albedo * E_k * (|L_k| / |L_k - X|)^2 * max(0, n . (L_k - X) / |L_k - X|)

    X is the surface point (pixel centre and height, in mm). Normals come from
    :func:`normals_from_height`. Far lights: ``I_k = albedo * E_k * max(0, n . l_k)``. With
    ``nuisances``, in counts (``exposure`` as ``c``)::

        I_k = c * (albedo * direct_k * beam_k * lit_k * vignetting + stray) + noise + black

    with ``beam_k = max(0, a_k . (X - L_k) / |X - L_k|)^n`` and ``lit_k`` 0 in cast shadows.
    Photon
    noise uses the Gaussian approximation of the Poisson law above 50 electrons (exact Poisson
    below); it matches mean and variance and is ~5x faster than ``Generator.poisson``.

    Examples
    --------
    A flat canvas under one lamp 300 mm away at 35 deg elevation: the centre pixel is
    ``albedo * E * sin(35 deg)``.

    >>> import numpy as np
    >>> el = np.radians(35.0)
    >>> lamp = 300.0 * np.array([[np.cos(el), 0.0, np.sin(el)]])
    >>> img = render_images(np.zeros((5, 5)), np.full((5, 5), 0.5), pixel_size_um=15.0,
    ...                     light_positions_mm=lamp, noise=False, dtype=None)
    >>> bool(np.isclose(img[0, 2, 2], 0.5 * np.sin(el)))
    True
    """
    h = np.asarray(height_um, dtype=np.float64)
    if h.ndim != 2:
        raise UVPSInputError(f"height_um must be (M, N); got shape {h.shape}")
    alb = np.asarray(albedo, dtype=np.float64)
    if alb.shape[:2] != h.shape or alb.ndim not in (2, 3):
        raise UVPSInputError(f"albedo must be (M, N) or (M, N, C) with (M, N) = {h.shape}; "
                             f"got shape {alb.shape}")
    if (light_positions_mm is None) == (light_directions is None):
        raise UVPSInputError("give exactly one of light_positions_mm and light_directions")
    positions = directions = None
    if light_positions_mm is not None:
        positions = np.asarray(light_positions_mm, dtype=np.float64)
        if positions.ndim != 2 or positions.shape[1] != 3:
            raise UVPSInputError(f"light_positions_mm must be (K, 3); got shape {positions.shape}")
        k = positions.shape[0]
    else:
        directions = np.asarray(light_directions, dtype=np.float64)
        if directions.ndim != 2 or directions.shape[1] != 3:
            raise UVPSInputError(f"light_directions must be (K, 3); got shape {directions.shape}")
        norms = np.linalg.norm(directions, axis=1, keepdims=True)
        if np.any(norms == 0):
            raise UVPSInputError("light_directions contains a zero vector")
        directions = directions / norms
        k = directions.shape[0]
    e = np.ones(k) if intensities is None else np.asarray(intensities, dtype=np.float64)
    if e.shape != (k,):
        raise UVPSInputError(f"intensities must be ({k},); got shape {e.shape}")
    integer = dtype is not None and np.issubdtype(np.dtype(dtype), np.integer)
    if h.ndim != 2 or min(h.shape) < 2 or not pixel_size_um > 0:
        raise UVPSInputError(f"height_um must be (M, N) with M, N >= 2 and pixel_size_um > 0; "
                             f"got shape {h.shape}, pixel_size_um={pixel_size_um}")
    nz = nuisances if nuisances is not None else Nuisances()
    _check_nuisances(nz, k, alb.shape, far=directions is not None)
    if nz.cast_shadows and nz.shadowed is None:
        nz.shadowed = shadow_masks(h, pixel_size_um=pixel_size_um, light_positions_mm=positions,
                                   light_directions=directions)
    normals = _normals64(h, float(pixel_size_um))

    def shading():
        return _shading(normals, h, pixel_size_um, positions, directions, e,
                        beam_axes=nz.beam_axes, beam_exponent=nz.beam_exponent,
                        shadowed=nz.shadowed if nz.cast_shadows else None)

    if exposure is None:
        if integer:
            peak = _peak(shading(), alb if alb.ndim == 2 else alb.max(axis=2), nz)
            exposure = 0.75 * np.iinfo(dtype).max / peak if peak > 0 else 1.0
        else:
            exposure = 1.0
    rng = np.random.default_rng(rng)
    out = np.empty((k,) + alb.shape, dtype=np.float64 if dtype is None else dtype)
    # float64 for exact model values (dtype None), float32 is plenty below 16-bit quantisation.
    work = np.float64 if dtype is None or np.dtype(dtype) == np.float64 else np.float32
    alb_w = alb.astype(work)
    stray = None
    if nz.stray_light is not None:
        stray = np.asarray(nz.stray_light, dtype=np.float64)
        stray = (exposure * (stray if stray.ndim == alb.ndim else stray[..., None])).astype(work)
    black = None if nz.black_level is None else np.asarray(nz.black_level, dtype=work)
    if black is not None and alb.ndim == 2:
        black = black[0]
    for i, s in enumerate(shading()):
        if nz.vignetting is not None:
            s = s * nz.vignetting
        s = (exposure * s).astype(work)
        counts = alb_w * (s if alb.ndim == 2 else s[..., None])
        if stray is not None:
            counts += stray
        if noise:
            counts = _add_noise(counts, rng, gain=gain, read_noise=read_noise)
        if black is not None:
            counts += black
        if integer:
            info = np.iinfo(dtype)
            counts = np.clip(np.rint(counts), info.min, info.max)
        out[i] = counts
    return out


def _peak(shading, amax, nuisances):
    """Brightest noise-free sample (black level aside) over all lights, in ``albedo * E``
    units; with stray light an upper bound (its maximum added to the direct maximum)."""
    vig = nuisances.vignetting
    peak = max(float(np.max((s if vig is None else s * vig) * amax)) for s in shading)
    if nuisances.stray_light is not None:
        peak += float(np.max(nuisances.stray_light))
    return peak


def _check_nuisances(nz, k, albedo_shape, *, far):
    """Shapes of a Nuisances against K lights and the albedo (M, N[, C])."""
    mn = albedo_shape[:2]
    c = albedo_shape[2] if len(albedo_shape) == 3 else 1
    if nz.black_level is not None and np.shape(nz.black_level) != (c,):
        raise UVPSInputError(f"nuisances.black_level must be ({c},) for {c} channel(s); got "
                             f"shape {np.shape(nz.black_level)}")
    if nz.stray_light is not None and np.shape(nz.stray_light) not in (mn, tuple(albedo_shape)):
        raise UVPSInputError(f"nuisances.stray_light must be {mn} or {tuple(albedo_shape)}; got "
                             f"shape {np.shape(nz.stray_light)}")
    if nz.vignetting is not None and np.shape(nz.vignetting) != mn:
        raise UVPSInputError(f"nuisances.vignetting must be {mn}; got shape "
                             f"{np.shape(nz.vignetting)}")
    if nz.beam_axes is not None:
        if far:
            raise UVPSInputError("nuisances.beam_axes needs near lights (light_positions_mm)")
        if np.shape(nz.beam_axes) != (k, 3):
            raise UVPSInputError(f"nuisances.beam_axes must be ({k}, 3); got shape "
                                 f"{np.shape(nz.beam_axes)}")
        if not nz.beam_exponent >= 0:
            raise UVPSInputError(f"nuisances.beam_exponent must be >= 0; got {nz.beam_exponent}")
    if nz.shadowed is not None and np.shape(nz.shadowed) != (k,) + mn:
        raise UVPSInputError(f"nuisances.shadowed must be {(k,) + mn}; got shape "
                             f"{np.shape(nz.shadowed)}")


def _add_noise(counts, rng, *, gain, read_noise):
    """Photon (Poisson in electrons) and Gaussian read noise, in counts."""
    noisy = rng.standard_normal(counts.shape, dtype=counts.dtype)
    noisy *= np.sqrt(gain * counts + read_noise * read_noise).astype(counts.dtype)
    noisy += counts
    low = counts < 50.0 * gain
    if low.any():
        noisy[low] = (rng.poisson(counts[low] / gain) * gain
                      + read_noise * rng.standard_normal(int(low.sum())))
    return noisy


def light_positions(rng, *, n_lights, elevation_deg, distance_mm,
                    azimuth_jitter=0.25) -> np.ndarray:
    """Lamp positions (K, 3) in mm: azimuths evenly spread, each moved by up to
    ``azimuth_jitter`` of the spacing, elevation and distance uniform in their ranges. Azimuth
    counted from +x toward +y."""
    step = 2 * np.pi / n_lights
    az = rng.uniform(0, 2 * np.pi) + step * np.arange(n_lights)
    az = az + rng.uniform(-azimuth_jitter, azimuth_jitter, n_lights) * step
    el = np.radians(rng.uniform(*elevation_deg, n_lights))
    d = rng.uniform(*distance_mm, n_lights)
    return np.stack([d * np.cos(el) * np.cos(az), d * np.cos(el) * np.sin(az),
                     d * np.sin(el)], axis=1)


# --------------------------------------------------------------------------------------------
# Nuisances of a real capture (drawn from their own random streams)
# --------------------------------------------------------------------------------------------


def _substream(seed, tag):
    """A Generator of its own for one nuisance: ``default_rng((seed, crc32(tag)))``, so that
    drawing it leaves the main stream (scene, lamps, noise) as it was."""
    if seed is None:
        return np.random.default_rng()
    return np.random.default_rng((int(seed), zlib.crc32(tag.encode())))


def _black_levels(value, channels):
    """The black level per channel, (C,) float64, or None when it is 0 everywhere."""
    arr = np.atleast_1d(np.asarray(value, dtype=np.float64))
    if arr.ndim != 1 or arr.size not in (1, channels):
        raise UVPSInputError(f"black_level must be a number or {channels} numbers (one per "
                             f"channel); got {value!r}")
    if not np.all(np.isfinite(arr)) or np.any(arr < 0):
        raise UVPSInputError(f"black_level must be >= 0 counts; got {value!r}")
    return None if not np.any(arr) else np.broadcast_to(arr, (channels,)).copy()


def _vignetting_map(rng, shape, falloff):
    """cos^4-law vignetting (M, N) float32 with ``falloff`` at the half-diagonal, and its
    parameters: the optical centre drawn within 5 % of the half-diagonal of the image centre."""
    m, n = shape
    half_diag = math.hypot((m - 1) / 2.0, (n - 1) / 2.0)
    off = 0.05 * half_diag * math.sqrt(rng.uniform())
    ang = rng.uniform(0, 2 * np.pi)
    cr, cc = (m - 1) / 2.0 + off * math.sin(ang), (n - 1) / 2.0 + off * math.cos(ang)
    f = half_diag / math.sqrt((1.0 - falloff) ** -0.5 - 1.0)
    r2 = (np.arange(m)[:, None] - cr) ** 2 + (np.arange(n)[None, :] - cc) ** 2
    vig = (1.0 / (1.0 + r2 / (f * f)) ** 2).astype(np.float32)
    info = {"corner_falloff": float(falloff), "centre_px": [cr, cc], "f_px": f,
            "profile": "1 / (1 + (r / f_px)^2)^2, r in pixels from centre_px (row, col)",
            "min": float(vig.min()), "max": float(vig.max())}
    return vig, info


def _stray_shape(rng, shape):
    """A smooth positive field of mean 1: a broad gaussian veil on a floor, tilted."""
    m, n = shape
    half_diag = math.hypot(m / 2.0, n / 2.0)
    cr, cc = rng.uniform([0.2 * m, 0.2 * n], [0.8 * m, 0.8 * n])
    sigma = rng.uniform(0.5, 1.0) * half_diag
    tilt = rng.uniform(-0.3, 0.3, 2)
    rows = np.arange(m)[:, None]
    cols = np.arange(n)[None, :]
    veil = np.exp(-((rows - cr) ** 2 + (cols - cc) ** 2) / (2 * sigma * sigma))
    ramp = (1 + tilt[0] * (cols - (n - 1) / 2.0) / (n / 2.0)
            + tilt[1] * (rows - (m - 1) / 2.0) / (m / 2.0))
    field = (0.5 + veil) * ramp
    info = {"veil_centre_px": [float(cr), float(cc)], "veil_sigma_px": float(sigma),
            "tilt": tilt.tolist()}
    return field / field.mean(), info


def _beam_axes(rng, positions, aim_error_deg):
    """Beam axes (K, 3): the ray from each lamp to the image centre turned by up to
    ``aim_error_deg`` (uniform over the cone), and each lamp's error in degrees."""
    k = positions.shape[0]
    to_centre = -positions / np.linalg.norm(positions, axis=1, keepdims=True)
    err = np.radians(aim_error_deg) * np.sqrt(rng.uniform(0, 1, k))
    psi = rng.uniform(0, 2 * np.pi, k)
    axes = np.empty((k, 3))
    for i, (a0, e, p) in enumerate(zip(to_centre, err, psi)):
        e1 = np.cross(a0, [0.0, 0.0, 1.0])
        if np.linalg.norm(e1) < 1e-9:
            e1 = np.array([1.0, 0.0, 0.0])
        e1 /= np.linalg.norm(e1)
        e2 = np.cross(a0, e1)
        axes[i] = math.cos(e) * a0 + math.sin(e) * (math.cos(p) * e1 + math.sin(p) * e2)
    return axes / np.linalg.norm(axes, axis=1, keepdims=True), np.degrees(err)


def _weave(spec, theta, xu, yu):
    """Plain weave (um) of one or several scales: ``A sin(2 pi u / P) sin(2 pi v / P)`` in axes
    turned by ``theta``; further scales turned a little more, with random phases."""
    periods, amps = _weave_scales(spec)
    u = xu * math.cos(theta) + yu * math.sin(theta)
    v = -xu * math.sin(theta) + yu * math.cos(theta)
    k = 2 * np.pi / periods[0]
    height = amps[0] * np.sin(k * u) * np.sin(k * v)
    if len(periods) > 1:
        rng = _substream(spec.seed, "weave")
        for period, amp in zip(periods[1:], amps[1:]):
            th = theta + rng.uniform(-0.05, 0.05)
            ph = rng.uniform(0, 2 * np.pi, 2)
            u = xu * math.cos(th) + yu * math.sin(th)
            v = -xu * math.sin(th) + yu * math.cos(th)
            k = 2 * np.pi / period
            height = height + amp * np.sin(k * u + ph[0]) * np.sin(k * v + ph[1])
    return height


def _weave_scales(spec):
    """Weave periods and amplitudes as equal-length lists of floats."""
    periods = [float(p) for p in np.atleast_1d(spec.weave_period_um)]
    amps = [float(a) for a in np.atleast_1d(spec.weave_amplitude_um)]
    if len(amps) == 1:
        amps = amps * len(periods)
    if not periods or len(amps) != len(periods):
        raise UVPSInputError(f"weave_amplitude_um must be one number or one per weave period "
                             f"({len(periods)}); got {spec.weave_amplitude_um!r}")
    if any(not p > 0 for p in periods) or any(not a >= 0 for a in amps):
        raise UVPSInputError(f"weave_period_um must be > 0 and weave_amplitude_um >= 0; got "
                             f"{spec.weave_period_um!r}, {spec.weave_amplitude_um!r}")
    return periods, amps


def _crack_seeds(rng, shape, spacing_px):
    """Seeds of the crack network (rows, cols) and each one's spacing: dart throwing, every
    seed with its own spacing drawn in ``spacing_px`` = (low, high), over the image and a
    border one high-spacing wide (so the border cells are whole)."""
    m, n = shape
    lo, hi = spacing_px
    box_lo, box_hi = np.array([-hi, -hi]), np.array([m + hi, n + hi])
    seeds = np.empty((0, 2))
    radii = np.empty(0)
    failures = 0
    while failures < 300:
        cand = rng.uniform(box_lo, box_hi)
        r = rng.uniform(lo, hi)
        if seeds.size and np.any(np.hypot(*(seeds - cand).T) < 0.5 * (radii + r)):
            failures += 1
            continue
        seeds = np.vstack([seeds, cand])
        radii = np.append(radii, r)
        failures = 0
    return seeds, radii


def _cracks(rng, shape, px, cupping_um, cell_mm):
    """Craquelure: cupped paint islands between narrow crack grooves.

    Returns the height layer (um, (M, N)), the groove mask (M, N) bool and the parameters.
    The islands are Voronoi cells of seeds ``cell_mm`` apart, in coordinates warped by smooth
    noise so the cracks wander. At distance ``e`` from the edge of its cell (the nearest
    bisector with a neighbouring seed), island i is ``c_i * (1 - e / R_i)^2`` high (``c_i`` up
    to ``cupping_um``, ``R_i`` half its spacing), and the groove brings every crack down to a
    common ``-cupping_um / 2`` over a gaussian of 15-30 um 1/e half-width (25-50 um wide at
    half depth).
    """

    m, n = shape
    lo, hi = (c * 1000.0 / px for c in cell_mm)
    seeds, spacing = _crack_seeds(rng, shape, (lo, hi))
    amp = 0.08 * lo
    sigma = max(lo / 4.0, 1.0)
    warp = [amp * _normalised(ndimage.gaussian_filter(rng.standard_normal(shape), sigma))
            for _ in range(2)]
    rr = (np.arange(m, dtype=np.float32)[:, None] + warp[0]).ravel()
    cc = (np.arange(n, dtype=np.float32)[None, :] + warp[1]).ravel()
    # distance to the cell's edge: to the nearest bisector with one of the next seeds (exact
    # for a convex cell whose neighbours are among them)
    dist, idx = cKDTree(seeds).query(np.stack([rr, cc], axis=1), k=min(6, len(seeds)))
    d0 = dist[:, 0] ** 2
    twice_gap = 2.0 * np.hypot(*(seeds[:, None, :] - seeds[None, :, :]).transpose(2, 0, 1))
    edge = np.full(d0.shape, np.inf)
    for j in range(1, idx.shape[1]):
        np.minimum(edge, (dist[:, j] ** 2 - d0) / twice_gap[idx[:, 0], idx[:, j]], out=edge)
    edge = edge.reshape(shape)                                                  # px
    cup = cupping_um * rng.uniform(0.4, 1.0, len(seeds))
    half = 0.5 * spacing
    own = idx[:, 0].reshape(shape)
    dish = cup[own] * np.clip(1.0 - edge / half[own], 0.0, None) ** 2
    groove_w = rng.uniform(15.0, 30.0) / px            # gaussian 1/e half-width (FWHM 25-50 um)
    depth = 0.5 * cupping_um
    g = np.exp(-(edge / groove_w) ** 2)
    layer = dish * (1.0 - g) - depth * g
    mask = edge < max(0.83 * groove_w, 0.71)       # below half depth, at least a pixel wide
    in_view = np.all((seeds > -0.5) & (seeds < np.array([m, n]) - 0.5), axis=1)
    info = {"cupping_um": float(cupping_um), "cell_mm": list(cell_mm),
            "n_islands": int(np.unique(own).size), "n_seeds_in_view": int(in_view.sum()),
            "groove_depth_um": depth, "groove_half_width_um": float(groove_w * px),
            "groove_fraction": float(mask.mean())}
    return layer, mask, info


# --------------------------------------------------------------------------------------------
# Scene
# --------------------------------------------------------------------------------------------


def _smooth_warp(rng, shape, amplitude, n_waves=4):
    """A smooth random displacement (pixels): a sum of a few long plane waves."""
    m, n = shape
    r = np.arange(m)[:, None]
    c = np.arange(n)[None, :]
    out = np.zeros(shape)
    size = max(m, n)
    for _ in range(n_waves):
        wavelength = rng.uniform(0.25, 0.8) * size
        theta = rng.uniform(0, np.pi)
        k = 2 * np.pi / wavelength
        out += np.sin(k * (np.cos(theta) * c + np.sin(theta) * r) + rng.uniform(0, 2 * np.pi))
    return out * amplitude / math.sqrt(n_waves)


def _colour_areas(rng, shape, n_regions):
    """Irregular colour areas: Voronoi cells of random seeds in warped coordinates."""
    m, n = shape
    seeds = []
    min_d = 0.6 * math.sqrt(m * n / n_regions)
    for _ in range(2000):
        if len(seeds) == n_regions:
            break
        s = rng.uniform([0.05 * m, 0.05 * n], [0.95 * m, 0.95 * n])
        if all(np.hypot(*(s - t)) > min_d for t in seeds):
            seeds.append(s)
        else:
            min_d *= 0.995
    amp = 0.08 * min(m, n)
    rr = np.arange(m, dtype=np.float32)[:, None] + _smooth_warp(rng, shape, amp)
    cc = np.arange(n, dtype=np.float32)[None, :] + _smooth_warp(rng, shape, amp)
    best = np.full(shape, np.inf, dtype=np.float32)
    labels = np.zeros(shape, dtype=np.int32)
    for i, (sr, sc) in enumerate(seeds):
        d = (rr - sr) ** 2 + (cc - sc) ** 2
        closer = d < best
        best[closer] = d[closer]
        labels[closer] = i + 1
    # Relabel 1..R in case a warped cell vanished.
    present = np.unique(labels)
    lut = np.zeros(labels.max() + 1, dtype=np.int32)
    lut[present] = np.arange(1, len(present) + 1)
    return lut[labels]


def _region_palette(rng, n_regions):
    """Names, light flags and colours for R areas (2-5 light, 1-3 dark)."""
    n_dark = int(rng.integers(max(1, n_regions - len(LIGHT_AREA_COLOURS)),
                              min(len(DARK_AREA_COLOURS), n_regions - 1) + 1))
    light = list(rng.permutation(list(LIGHT_AREA_COLOURS)))[: n_regions - n_dark]
    dark = list(rng.permutation(list(DARK_AREA_COLOURS)))[:n_dark]
    names = light + dark
    order = rng.permutation(n_regions)
    names = [str(names[i]) for i in order]
    is_light = [nm in LIGHT_AREA_COLOURS for nm in names]
    colours = np.array([{**LIGHT_AREA_COLOURS, **DARK_AREA_COLOURS}[nm] for nm in names])
    return names, is_light, colours


@dataclass
class _Impasto:
    """The impasto options of :class:`SyntheticSpec` and their own random stream."""

    blunt: float = 0.0
    ripple: tuple = (0.0, 0.0)
    groove_um: tuple = (0.0, 0.0)
    crossing: float = 0.0
    rng: Optional[np.random.Generator] = None

    @classmethod
    def of(cls, spec):
        imp = cls(spec.ridge_blunt_fraction, tuple(spec.ridge_ripple), tuple(spec.ridge_groove_um),
                  spec.ridge_crossing_fraction)
        if imp.blunt > 0 or imp.ripple[1] > 0 or imp.groove_um[1] > 0 or imp.crossing > 0:
            imp.rng = _substream(spec.seed, "impasto")
        return imp


def _stroke_relief(imp, tn, dist, prof, length, width, h, px):
    """One stroke's height (um) in its box: ``tn`` the position along it (0..1) of the nearest
    centreline pixel, ``dist`` the distance to it (px), ``prof`` the cross profile (0..1).
    Without impasto: ``h prof`` tapered by a smoothstep over 15 % of the length at both ends.
    Returns (height, its shape relative to ``h`` clipped to 1, which tints the albedo)."""
    def smooth(x):
        x = np.clip(x, 0, 1)
        return x * x * (3 - 2 * x)
    if imp.rng is None:
        shape_k = prof * smooth(np.minimum(tn, 1 - tn) / 0.15)
        return h * shape_k, shape_k
    r = imp.rng
    mound = np.ones_like(tn)
    ends = []
    for s_end in (tn * length, (1 - tn) * length):          # px from each end along the path
        if r.random() < imp.blunt:
            # full height to a rounded end (the cap), and the paint piled where the brush lifts
            ends.append(np.ones_like(tn))
            pile = r.uniform(0.2, 0.5)
            mound = mound + pile * np.exp(-((s_end - 0.5 * width) / (0.5 * width)) ** 2)
        else:
            ends.append(smooth(s_end / (0.15 * length)))
    rel = np.minimum(*ends) * mound
    amp = r.uniform(*imp.ripple)
    if amp > 0:
        wave = r.uniform(200.0, 800.0) / px
        rel = rel * (1 + amp * np.sin(2 * np.pi * tn * length / wave + r.uniform(0, 2 * np.pi)))
    z = h * prof * rel
    depth = r.uniform(*imp.groove_um)
    if depth > 0:
        period = r.uniform(40.0, 120.0) / px
        grooves = 0.5 * (1 + np.cos(2 * np.pi * dist / period + r.uniform(0, 2 * np.pi)))
        z = np.maximum(z - depth * grooves * np.minimum(3 * prof, 1) * np.minimum(rel, 1), 0)
    return z, np.minimum(z / h, 1)


def _ridges(rng, shape, px, count, albedo_factor, occupied, *, width_um=(100.0, 300.0),
            height_um=(5.0, 20.0), impasto=None):
    """Brush-stroke ridges: curved, several mm long, ``width_um`` wide, ``height_um`` high.

    Distance to each stroke's centreline comes from ``scipy.ndimage.distance_transform_edt``
    (with the indices of the nearest centreline pixel, to taper the stroke ends);
    ``impasto`` (:class:`_Impasto`) adds blunt ends, ripples, bristle grooves and crossings.
    """
    m, n = shape
    imp = impasto if impasto is not None else _Impasto()
    layer = np.zeros(shape)
    base_angle = rng.uniform(0, np.pi)
    for _ in range(count):
        length = rng.uniform(3000.0, 10000.0) / px           # pixels
        width = rng.uniform(*width_um) / px
        h = rng.uniform(*height_um)
        angle = base_angle + rng.uniform(-0.5, 0.5)
        crossing = imp.rng is not None and imp.rng.random() < imp.crossing
        if crossing:
            angle = imp.rng.uniform(0, np.pi)
        start = rng.uniform([0, 0], [m, n])
        direc = np.array([np.sin(angle), np.cos(angle)])
        end = start + length * direc
        bend = rng.uniform(-0.15, 0.15) * length
        ctrl = (start + end) / 2 + bend * np.array([-direc[1], direc[0]])
        t = np.linspace(0, 1, int(2 * length) + 2)[:, None]
        path = (1 - t) ** 2 * start + 2 * t * (1 - t) * ctrl + t ** 2 * end
        pad = int(width) + 2
        r0 = max(int(path[:, 0].min()) - pad, 0)
        r1 = min(int(path[:, 0].max()) + pad + 1, m)
        c0 = max(int(path[:, 1].min()) - pad, 0)
        c1 = min(int(path[:, 1].max()) + pad + 1, n)
        if r1 - r0 < 2 or c1 - c0 < 2:
            continue
        pr = np.rint(path[:, 0]).astype(int) - r0
        pc = np.rint(path[:, 1]).astype(int) - c0
        inside = (pr >= 0) & (pr < r1 - r0) & (pc >= 0) & (pc < c1 - c0)
        if not inside.any():
            continue
        line = np.ones((r1 - r0, c1 - c0), dtype=bool)
        tval = np.zeros(line.shape)
        line[pr[inside], pc[inside]] = False
        tval[pr[inside], pc[inside]] = t[inside, 0]
        dist, (ir, ic) = ndimage.distance_transform_edt(line, return_indices=True)
        half = width / 2
        prof = np.where(dist < half, 0.5 * (1 + np.cos(np.pi * dist / half)), 0.0)
        tn = tval[ir, ic]
        z, shape_k = _stroke_relief(imp, tn, dist, prof, length, width, h, px)
        if crossing:
            layer[r0:r1, c0:c1] += z                         # laid over dry paint
        else:
            layer[r0:r1, c0:c1] = np.maximum(layer[r0:r1, c0:c1], z)
        albedo_factor[r0:r1, c0:c1] *= 1 + rng.uniform(-0.06, 0.04) * shape_k
    occupied |= layer > 1.0
    return layer


def _primer_spots(rng, shape, px, count, albedo, occupied):
    """Flat whitish primer spots (paint missing): albedo toward the primer colour, height 0 to
    3 um below the paint. Returns the height layer (<= 0)."""
    m, n = shape
    layer = np.zeros(shape)
    primer = np.array(PRIMER_COLOUR)[: albedo.shape[2]]
    for _ in range(count):
        w = rng.uniform(100.0, 400.0) / px
        aspect = rng.uniform(1.0, 1.6)
        a, b = w / 2 * math.sqrt(aspect), w / 2 / math.sqrt(aspect)
        phi = rng.uniform(0, np.pi)
        cr, cc = rng.uniform([a + 2, a + 2], [m - a - 2, n - a - 2])
        r0, r1 = int(cr - a - 2), int(cr + a + 3)
        c0, c1 = int(cc - a - 2), int(cc + a + 3)
        rows = np.arange(r0, r1)[:, None] - cr
        cols = np.arange(c0, c1)[None, :] - cc
        u = cols * np.cos(phi) + rows * np.sin(phi)
        v = -cols * np.sin(phi) + rows * np.cos(phi)
        theta = np.arctan2(v, u)
        wobble = 1 + sum(rng.uniform(-0.08, 0.08) * np.cos(j * theta + rng.uniform(0, 6.3))
                         for j in (2, 3, 5))
        rho = np.sqrt((u / a) ** 2 + (v / b) ** 2) / wobble
        wgt = np.clip((1 - rho) * a / 1.5, 0, 1)
        depth = rng.uniform(0.0, 3.0)
        layer[r0:r1, c0:c1] = np.minimum(layer[r0:r1, c0:c1], -depth * wgt)
        sub = albedo[r0:r1, c0:c1]
        sub[:] = sub * (1 - wgt[..., None]) + primer * rng.uniform(0.95, 1.05) * wgt[..., None]
        occupied[r0:r1, c0:c1] |= rho < 1.3
    return layer


def _protrusion_widths(rng, count, width_range, median_um=150.0):
    """Widths (um) skewed to 100-200 um: log-normal (median ``median_um``, 150 um by default,
    sigma 0.45) truncated to ``width_range``."""
    lo, hi = width_range
    median = min(max(median_um, lo), hi)
    out = np.empty(0)
    while out.size < count:
        w = rng.lognormal(math.log(median), 0.45, 2 * count + 10)
        out = np.concatenate([out, w[(w >= lo) & (w <= hi)]])
    return out[:count]


def _dome_profile(rho, gamma, crater):
    """Normalised dome height at elliptical radius rho (0 outside the footprint rho >= 1)."""
    f = np.where(rho < 1, np.clip(1 - rho * rho, 0, None) ** gamma, 0.0)
    if crater is not None:
        depth, rc = crater
        inner = np.clip(1 - (rho / rc) ** 2, 0, None) ** 2
        f = f - depth * inner
    return f


def _profile(rho, gamma, crater, plateau):
    """Dome/crater profile, or a mesa: flat out to ``plateau``, then a smoothstep to rho = 1."""
    if plateau is None:
        return _dome_profile(rho, gamma, crater)
    t = np.clip((1 - rho) / (1 - plateau), 0, 1)
    return t * t * (3 - 2 * t)


class _Shapes:
    """Draws of :attr:`SyntheticSpec.protrusion_shapes` (kinds, outlines, cluster members)
    from their own random stream."""

    def __init__(self, spec):
        weights = spec.protrusion_shapes
        self.rng = _substream(spec.seed, "protrusion shapes")
        self.kinds = [k for k in PROTRUSION_KINDS if weights.get(k, 0) > 0]
        p = np.array([float(weights[k]) for k in self.kinds])
        self.p = p / p.sum()
        geo = np.array([float(weights.get(k, 0.0)) for k in PROTRUSION_GEOMETRIES])
        self.geo_p = geo / geo.sum() if geo.sum() > 0 else np.array([1.0, 0, 0, 0])

    def kind(self):
        return self.kinds[self.rng.choice(len(self.kinds), p=self.p)]

    def geometry(self):
        return PROTRUSION_GEOMETRIES[self.rng.choice(len(PROTRUSION_GEOMETRIES), p=self.geo_p)]

    def wobble(self):
        """A lumpy outline: harmonics 2, 3, 5 of 8-20 %, 5-12 % and 2-6 %; the footprint scale
        that keeps the area (mean of w^2 = 1 + sum amp^2 / 2) and the outline's reach (max w)."""
        amps = (self.rng.uniform([0.08, 0.05, 0.02], [0.2, 0.12, 0.06])
                * self.rng.choice([-1.0, 1.0], 3))
        phases = self.rng.uniform(0, 2 * np.pi, 3)
        theta = np.linspace(0, 2 * np.pi, 721)
        w = 1 + sum(a * np.cos(j * theta + ph) for a, j, ph in zip(amps, (2, 3, 5), phases))
        return {"amps": amps, "phases": phases,
                "scale": 1.0 / math.sqrt(1.0 + float(np.sum(amps ** 2)) / 2.0),
                "reach": float(w.max())}


def _protrusions(rng, spec, labels, region_light, px, height, albedo, occupied, ridge_mask=None):
    """Place non-overlapping protrusions per colour area and add them to height and albedo
    (``on_stroke_fraction`` of them on or against a stroke of ``ridge_mask``)."""
    m, n = labels.shape
    on_f = spec.on_stroke_fraction if ridge_mask is not None and ridge_mask.any() else 0.0
    if on_f > 0:
        srng = _substream(spec.seed, "on stroke")
        near_stroke = ndimage.binary_dilation(ridge_mask, iterations=4).ravel()
        prot_occ = np.zeros((m, n), bool)
    keys = ("y_px", "x_px", "width_um", "height_um", "crater", "weak", "region", "aspect",
            "angle_deg", "shape", "cluster", "dark")
    table = {key: [] for key in keys + (("on_stroke",) if on_f > 0 else ())}
    colour = np.array(PROTRUSION_COLOUR)[: albedo.shape[2]]
    flat = labels.ravel()
    shapes = None if spec.protrusion_shapes is None else _Shapes(spec)
    h_range = spec.height_um
    scratch = np.zeros((m, n)) if shapes is not None and "cluster" in shapes.kinds else None
    n_clusters = 0

    def stamp(cr, cc, a, b, margin, phi, h_dome, gamma, crater, plateau, wobble, col, layer):
        """Add one protrusion to ``layer`` (height, or the cluster's scratch by max) and blend
        its colour into the albedo; returns its peak height above the surface."""
        r0, r1 = int(cr) - margin, int(cr) + margin + 1
        c0, c1 = int(cc) - margin, int(cc) + margin + 1
        rr = np.arange(r0, r1)[:, None] - cr
        ccs = np.arange(c0, c1)[None, :] - cc
        u = ccs * np.cos(phi) + rr * np.sin(phi)
        v = -ccs * np.sin(phi) + rr * np.cos(phi)
        rho = np.sqrt((u / a) ** 2 + (v / b) ** 2)
        if wobble is not None:
            t = np.arctan2(v / b, u / a)
            rho = rho / (1 + sum(amp * np.cos(j * t + ph) for amp, j, ph
                                 in zip(wobble["amps"], (2, 3, 5), wobble["phases"])))
        fine = np.linspace(0, 1, 2001)
        peak = float(_profile(fine, gamma, crater, plateau).max())
        if layer is height:
            height[r0:r1, c0:c1] += h_dome * _profile(rho, gamma, crater, plateau)
        else:
            np.maximum(layer[r0:r1, c0:c1], h_dome * _profile(rho, gamma, crater, plateau),
                       out=layer[r0:r1, c0:c1])
        sub = albedo[r0:r1, c0:c1]
        wgt = np.clip((1 - rho) * a, 0, 1)[..., None]
        sub[:] = sub * (1 - wgt) + col * wgt
        return h_dome * peak

    def occupy(cr, cc, a_reach, margin):
        r0, r1 = int(cr) - margin, int(cr) + margin + 1
        c0, c1 = int(cc) - margin, int(cc) + margin + 1
        rr = np.arange(r0, r1)[:, None] - cr
        ccs = np.arange(c0, c1)[None, :] - cc
        occupied[r0:r1, c0:c1] |= rr ** 2 + ccs ** 2 <= (a_reach + 1.0) ** 2
        if on_f > 0:
            prot_occ[r0:r1, c0:c1] |= rr ** 2 + ccs ** 2 <= (a_reach + 1.0) ** 2

    def record(cr, cc, w_um, peak, geometry, weak, dark, region, aspect, phi, cluster):
        for key, val in zip(keys, (cr, cc, w_um, peak, geometry == "crater", weak, region,
                                   aspect, math.degrees(phi), geometry, cluster, dark)):
            table[key].append(val)
        if on_f > 0:
            table["on_stroke"].append(bool(on_now))

    def clip_height(h):
        return h if h_range is None else min(max(h, h_range[0]), h_range[1])

    for reg in range(1, labels.max() + 1):
        idx = np.flatnonzero(flat == reg)
        area_cm2 = idx.size * px * px / _UM2_PER_CM2
        density = (spec.protrusion_density_light if region_light[reg - 1]
                   else spec.protrusion_density_dark)
        count = int(rng.poisson(density * area_cm2))
        if count == 0:
            continue
        idx_near = idx[near_stroke[idx]] if on_f > 0 else idx[:0]
        for w_um in np.sort(_protrusion_widths(rng, count, spec.width_um, spec.width_median_um))[::-1]:
            kind, geometry, wobble, plateau = None, None, None, None
            if shapes is not None:
                kind = shapes.kind()
                geometry = kind if kind in PROTRUSION_GEOMETRIES else shapes.geometry()
                wobble = shapes.wobble() if geometry == "irregular" else None
                plateau = shapes.rng.uniform(0.4, 0.7) if geometry == "mesa" else None
            aspect = rng.uniform(1.0, 1.35)
            a = w_um / 2 * math.sqrt(aspect) / px                # semi-axes in pixels, area of
            b = w_um / 2 / math.sqrt(aspect) / px                # a circle of diameter w
            a_reach = a
            if wobble is not None:
                a, b = a * wobble["scale"], b * wobble["scale"]
                a_reach = a * wobble["reach"]
            margin = int(math.ceil(a_reach)) + 2
            on_now = on_f > 0 and idx_near.size > 0 and srng.random() < on_f
            for _ in range(40):
                if on_now:      # on or against a stroke: only protrusions and the rest block it
                    j = idx_near[srng.integers(idx_near.size)]
                else:
                    j = idx[rng.integers(idx.size)]
                cr = j // n + rng.uniform(-0.5, 0.5)
                cc = j % n + rng.uniform(-0.5, 0.5)
                if not (margin <= cr < m - margin and margin <= cc < n - margin):
                    continue
                r0, r1 = int(cr) - margin, int(cr) + margin + 1
                c0, c1 = int(cc) - margin, int(cc) + margin + 1
                rr = np.arange(r0, r1)[:, None] - cr
                ccs = np.arange(c0, c1)[None, :] - cc
                busy = occupied[r0:r1, c0:c1]
                if on_now:
                    busy = (busy & ~ridge_mask[r0:r1, c0:c1]) | prot_occ[r0:r1, c0:c1]
                if np.any(busy & (rr ** 2 + ccs ** 2 <= (a_reach + 1.5) ** 2)):
                    continue
                break
            else:
                continue
            phi = rng.uniform(0, np.pi)
            h_dome = clip_height(rng.uniform(0.15, 0.35) * w_um)
            gamma = rng.uniform(1.0, 1.6)
            has_crater = rng.random() < spec.crater_fraction
            if shapes is not None:
                has_crater = geometry == "crater"
            else:
                geometry = "crater" if has_crater else "dome"
            crater = (rng.uniform(0.3, 0.6), rng.uniform(0.3, 0.5)) if has_crater else None
            weak = rng.random() < spec.weak_fraction
            dark = kind == "dark"
            paint = albedo[int(cr), int(cc)]
            if dark:
                weak = False
                col = paint * shapes.rng.uniform(0.5, 1.0)
            elif weak:
                col = paint * rng.uniform(1.05, 1.2)
            else:
                col = colour * rng.uniform(0.92, 1.05)
            if kind != "cluster":
                peak = stamp(cr, cc, a, b, margin, phi, h_dome, gamma, crater, plateau, wobble,
                             col, height)
                occupy(cr, cc, a_reach, margin)
                record(cr, cc, w_um, peak, geometry, weak, dark, reg, aspect, phi, 0)
                continue
            # a cluster: this one and 1-3 more touching it, added to the height by their maximum
            n_clusters += 1
            peak = stamp(cr, cc, a, b, margin, phi, h_dome, gamma, crater, plateau, wobble, col,
                         scratch)
            members = [(cr, cc, w_um / 2 / px, a_reach, margin)]
            record(cr, cc, w_um, peak, geometry, weak, False, reg, aspect, phi, n_clusters)
            for _ in range(int(shapes.rng.integers(1, 4))):
                placed = _cluster_member(shapes, spec, members, occupied, px, (m, n))
                if placed is None:
                    continue
                (cr2, cc2, w2, aspect2, phi2, a2, b2, a_reach2, margin2, geometry2, wobble2,
                 plateau2, crater2, gamma2) = placed
                h2 = clip_height(shapes.rng.uniform(0.15, 0.35) * w2)
                weak2 = shapes.rng.random() < spec.weak_fraction
                paint2 = albedo[int(cr2), int(cc2)]
                col2 = (paint2 * shapes.rng.uniform(1.05, 1.2) if weak2
                        else colour * shapes.rng.uniform(0.92, 1.05))
                peak2 = stamp(cr2, cc2, a2, b2, margin2, phi2, h2, gamma2, crater2, plateau2,
                              wobble2, col2, scratch)
                members.append((cr2, cc2, w2 / 2 / px, a_reach2, margin2))
                record(cr2, cc2, w2, peak2, geometry2, weak2, False,
                       labels[int(round(cr2)), int(round(cc2))], aspect2, phi2, n_clusters)
            if len(members) == 1:                  # no room for another: a lone protrusion
                table["cluster"][-1] = 0
                n_clusters -= 1
            r0 = min(int(c[0]) - c[4] for c in members)
            r1 = max(int(c[0]) + c[4] + 1 for c in members)
            c0 = min(int(c[1]) - c[4] for c in members)
            c1 = max(int(c[1]) + c[4] + 1 for c in members)
            height[r0:r1, c0:c1] += scratch[r0:r1, c0:c1]
            scratch[r0:r1, c0:c1] = 0.0
            for cr_, cc_, _, a_reach_, margin_ in members:
                occupy(cr_, cc_, a_reach_, margin_)
    rows, cols = table["y_px"], table["x_px"]
    order = np.lexsort((np.asarray(cols), np.asarray(rows))) if rows else np.zeros(0, int)
    cols_ = {
        "x_px": np.asarray(cols, dtype=np.float64), "y_px": np.asarray(rows, dtype=np.float64),
        "width_um": np.asarray(table["width_um"], dtype=np.float64),
        "height_um": np.asarray(table["height_um"], dtype=np.float64),
        "crater": np.asarray(table["crater"], dtype=bool),
        "weak": np.asarray(table["weak"], dtype=bool),
        "region": np.asarray(table["region"], dtype=np.int32),
        "aspect": np.asarray(table["aspect"], dtype=np.float64),
        "angle_deg": np.asarray(table["angle_deg"], dtype=np.float64),
        "shape": np.asarray(table["shape"], dtype="<U9"),
        "cluster": np.asarray(table["cluster"], dtype=np.int32),
        "dark": np.asarray(table["dark"], dtype=bool),
        **({"on_stroke": np.asarray(table["on_stroke"], dtype=bool)} if on_f > 0 else {}),
    }
    out = {"id": np.arange(1, len(rows) + 1, dtype=np.int32)}
    out.update({k: v[order] for k, v in cols_.items()})
    return out


def _cluster_member(shapes, spec, members, occupied, px, shape):
    """Draw and place one more member touching a random member of a cluster: its centre
    0.7-0.85 x the sum of the two equivalent radii away (so the footprints overlap), off every
    other protrusion, ridge and primer spot. Returns its parameters, or None after 20 tries."""
    m, n = shape
    srng = shapes.rng
    w_um = min(max(members[0][2] * 2 * px * srng.uniform(0.5, 1.0), spec.width_um[0]),
               spec.width_um[1])
    geometry = shapes.geometry()
    wobble = shapes.wobble() if geometry == "irregular" else None
    plateau = srng.uniform(0.4, 0.7) if geometry == "mesa" else None
    crater = (srng.uniform(0.3, 0.6), srng.uniform(0.3, 0.5)) if geometry == "crater" else None
    gamma = srng.uniform(1.0, 1.6)
    aspect = srng.uniform(1.0, 1.35)
    phi = srng.uniform(0, np.pi)
    a = w_um / 2 * math.sqrt(aspect) / px
    b = w_um / 2 / math.sqrt(aspect) / px
    a_reach = a
    if wobble is not None:
        a, b = a * wobble["scale"], b * wobble["scale"]
        a_reach = a * wobble["reach"]
    margin = int(math.ceil(a_reach)) + 2
    radius = w_um / 2 / px
    for _ in range(20):
        cr0, cc0, r_eq, _, _ = members[srng.integers(len(members))]
        psi = srng.uniform(0, 2 * np.pi)
        d = (r_eq + radius) * srng.uniform(0.7, 0.85)
        cr, cc = cr0 + d * math.sin(psi), cc0 + d * math.cos(psi)
        if not (margin <= cr < m - margin and margin <= cc < n - margin):
            continue
        if any(math.hypot(cr - c[0], cc - c[1]) < 0.7 * (c[2] + radius) for c in members):
            continue
        r0, r1 = int(cr) - margin, int(cr) + margin + 1
        c0, c1 = int(cc) - margin, int(cc) + margin + 1
        rr = np.arange(r0, r1)[:, None] - cr
        ccs = np.arange(c0, c1)[None, :] - cc
        if np.any(occupied[r0:r1, c0:c1] & (rr ** 2 + ccs ** 2 <= (a_reach + 1.5) ** 2)):
            continue
        return (cr, cc, w_um, aspect, phi, a, b, a_reach, margin, geometry, wobble, plateau,
                crater, gamma)
    return None


def _validate(spec: SyntheticSpec) -> None:
    shape = tuple(spec.shape)
    if len(shape) != 2 or any(int(s) != s or s < 16 for s in shape):
        raise UVPSInputError(f"shape must be two integers >= 16 (rows, cols); got {spec.shape}")
    if int(spec.n_lights) != spec.n_lights or spec.n_lights < 3:
        raise UVPSInputError(f"n_lights must be an integer >= 3; got {spec.n_lights}")
    if not spec.pixel_size_um > 0:
        raise UVPSInputError(f"pixel_size_um must be > 0; got {spec.pixel_size_um}")
    for name, lo_min, hi_max in (("elevation_deg", 0.0, 90.0), ("distance_mm", 0.0, np.inf),
                                 ("width_um", 0.0, np.inf)):
        rng_ = tuple(getattr(spec, name))
        if len(rng_) != 2 or not (lo_min < rng_[0] <= rng_[1] <= hi_max):
            raise UVPSInputError(f"{name} must be (low, high) with {lo_min} < low <= high <= "
                                 f"{hi_max}; got {getattr(spec, name)}")
    for name in ("intensity_jitter", "weak_fraction", "crater_fraction"):
        if not 0 <= getattr(spec, name) < 1:
            raise UVPSInputError(f"{name} must be in [0, 1); got {getattr(spec, name)}")
    if not 0 < spec.exposure_fraction <= 1:
        raise UVPSInputError(f"exposure_fraction must be in (0, 1]; got {spec.exposure_fraction}")
    if spec.n_regions is not None and not 2 <= spec.n_regions <= 8:
        raise UVPSInputError(f"n_regions must be None or 2..8; got {spec.n_regions}")
    for name in ("protrusion_density_light", "protrusion_density_dark", "bow_um", "read_noise"):
        if getattr(spec, name) < 0:
            raise UVPSInputError(f"{name} must be >= 0; got {getattr(spec, name)}")
    if not spec.full_well_e > 0:
        raise UVPSInputError(f"full_well_e must be > 0; got {spec.full_well_e}")
    _weave_scales(spec)
    _black_levels(spec.black_level, 3 if spec.rgb else 1)
    for name, hi in (("stray_light", 1.0), ("vignetting", 0.95), ("azimuth_jitter", 1.0)):
        if not 0 <= getattr(spec, name) < hi:
            raise UVPSInputError(f"{name} must be in [0, {hi}); got {getattr(spec, name)}")
    if not 0 <= spec.beam_exponent <= 1000:
        raise UVPSInputError(f"beam_exponent must be in [0, 1000]; got {spec.beam_exponent}")
    if not 0 <= spec.beam_aim_error_deg <= 45:
        raise UVPSInputError(f"beam_aim_error_deg must be in [0, 45]; got "
                             f"{spec.beam_aim_error_deg}")
    if not spec.cupping_um >= 0:
        raise UVPSInputError(f"cupping_um must be >= 0; got {spec.cupping_um}")
    ranges = [("crack_cell_mm", 0.0), ("ridge_width_um", 0.0), ("ridge_height_um", 0.0)]
    if spec.height_um is not None:
        ranges.append(("height_um", 0.0))
    for name, lo_min in ranges:
        rng_ = tuple(getattr(spec, name))
        if len(rng_) != 2 or not (lo_min < rng_[0] <= rng_[1] < np.inf):
            raise UVPSInputError(f"{name} must be (low, high) with {lo_min} < low <= high; got "
                                 f"{getattr(spec, name)}")
    for name in ("ridge_density", "primer_density"):
        if not 0 <= getattr(spec, name) < np.inf:
            raise UVPSInputError(f"{name} must be >= 0 (per cm^2); got {getattr(spec, name)}")
    for name in ("ridge_blunt_fraction", "ridge_crossing_fraction", "on_stroke_fraction"):
        if not 0 <= getattr(spec, name) <= 1:
            raise UVPSInputError(f"{name} must be in [0, 1]; got {getattr(spec, name)}")
    for name in ("ridge_ripple", "ridge_groove_um"):
        rng_ = tuple(getattr(spec, name))
        if len(rng_) != 2 or not (0 <= rng_[0] <= rng_[1] < (1 if name == "ridge_ripple" else 1e3)):
            raise UVPSInputError(f"{name} must be (low, high) with 0 <= low <= high"
                                 f"{' < 1' if name == 'ridge_ripple' else ''}; got {getattr(spec, name)}")
    shapes = spec.protrusion_shapes
    if shapes is not None:
        if (not isinstance(shapes, dict) or set(shapes) - set(PROTRUSION_KINDS)
                or any(not (np.isfinite(w) and w >= 0) for w in shapes.values())
                or not sum(shapes.values()) > 0):
            raise UVPSInputError(f"protrusion_shapes must be None or a dict of weights >= 0 (not "
                                 f"all 0) over {list(PROTRUSION_KINDS)}; got {shapes!r}")


def make_capture(spec: Optional[SyntheticSpec] = None, *, progress: Progress = None,
                 **overrides) -> SyntheticCapture:
    """Synthesise a UV photometric-stereo capture of a painting detail with ground truth.

    Parameters
    ----------
    spec : SyntheticSpec, optional
        What to make (defaults: 1200 x 1600 pixels of 15 um, 12 lights, RGB).
    progress : callable, optional
        ``progress(fraction, message)``.
    **overrides
        Fields of :class:`SyntheticSpec` replacing those of ``spec``, e.g. ``shape=(240, 320)``.

    Returns
    -------
    SyntheticCapture

    Notes
    -----
    Height = canvas bow (a quadratic of peak-to-valley ``bow_um``) + plain weave
    (``A sin(2 pi u / P) sin(2 pi v / P)`` in slightly rotated axes) + brush ridges - primer spot
    depressions + protrusion domes ``H (1 - rho^2)^gamma`` (rho the elliptical radius, minus a
    central crater for ``crater_fraction`` of them); the median is then set to 0. Protrusions are
    placed largest first, as a Poisson number per area (densities per cm^2 as in the paper,
    Fig. 4), rejecting any placement that overlaps another protrusion, a ridge or a primer spot.
    The exposure puts the brightest noise-free sample at ``exposure_fraction`` of 65535; noise is
    photon noise with ``gain = 65535 / full_well_e`` counts per electron plus read noise.

    The nuisances of a real capture (see :class:`SyntheticSpec`) come on top: cracks and cupping
    join the height before the protrusions are placed (they avoid the grooves), then the lamps'
    beams, the cast shadows (:func:`shadow_masks`) and the vignetting shape the direct signal,
    which sets the exposure (the stray light's maximum counted in); stray light is added before
    the noise and the black level after it (:func:`render_images`). Their realised values are
    in ``SyntheticCapture.nuisances``.

    Cost: about 2.5-4 s for the default 1200 x 1600 x 12 RGB capture, 5-9 s with every
    nuisance at the top of its range (:meth:`SyntheticSpec.realistic`; cast shadows ~1.5 s,
    cracks ~1.5 s), 0.1 s for 240 x 320 x 8.

    Examples
    --------
    >>> cap = make_capture(shape=(240, 320), n_lights=8, seed=1)
    >>> cap.images.shape, cap.images.dtype
    ((8, 240, 320, 3), dtype('uint16'))
    >>> sorted(cap.protrusions)[:3]
    ['angle_deg', 'aspect', 'cluster']
    """
    spec = dataclasses.replace(spec or SyntheticSpec(), **_checked_overrides(overrides))
    spec.shape = tuple(int(s) for s in spec.shape)
    _validate(spec)
    rng = np.random.default_rng(spec.seed)
    m, n = spec.shape
    px = float(spec.pixel_size_um)
    area_cm2 = m * n * px * px / _UM2_PER_CM2
    report(progress, 0.0, "colour areas")

    n_regions = spec.n_regions or int(rng.integers(5, 9))
    labels = _colour_areas(rng, (m, n), n_regions)
    n_regions = int(labels.max())
    names, is_light, colours = _region_palette(rng, n_regions)
    albedo = colours[labels - 1]
    albedo = ndimage.gaussian_filter(albedo, sigma=(1.2, 1.2, 0))
    texture = (1 + 0.05 * _normalised(ndimage.gaussian_filter(rng.standard_normal((m, n)), 12))
               + 0.015 * _normalised(ndimage.gaussian_filter(rng.standard_normal((m, n)), 1.0)))
    albedo *= texture[..., None]

    report(progress, 0.1, "surface")
    x, y = pixel_centres_mm((m, n), px)
    xu, yu = x * 1000.0, y * 1000.0
    height = _weave(spec, rng.uniform(-0.05, 0.05), xu, yu)
    xn, yn = x / max(abs(x).max(), 1e-9), y / max(abs(y).max(), 1e-9)
    bow = -(rng.uniform(0.5, 1) * xn ** 2 + rng.uniform(0.5, 1) * yn ** 2
            + rng.uniform(-0.3, 0.3) * xn * yn)
    height = height + spec.bow_um * (bow - bow.min()) / max(np.ptp(bow), 1e-12)

    occupied = np.zeros((m, n), dtype=bool)
    factor = np.ones((m, n))
    n_ridges = round(spec.ridge_density * area_cm2) if spec.n_ridges is None else int(spec.n_ridges)
    ridge_layer = _ridges(rng, (m, n), px, n_ridges, factor, occupied,
                          width_um=spec.ridge_width_um, height_um=spec.ridge_height_um,
                          impasto=_Impasto.of(spec))
    height += ridge_layer
    albedo *= factor[..., None]
    n_spots = round(spec.primer_density * area_cm2) if spec.n_primer_spots is None else int(spec.n_primer_spots)
    height += _primer_spots(rng, (m, n), px, n_spots, albedo, occupied)
    nz = Nuisances()
    if _Impasto.of(spec).rng is not None or spec.on_stroke_fraction > 0:
        nz.strokes = ridge_layer.astype(np.float32)
    if spec.cupping_um > 0:
        layer, nz.cracks, nz.info["cupping"] = _cracks(_substream(spec.seed, "cracks"), (m, n),
                                                       px, spec.cupping_um, spec.crack_cell_mm)
        height += layer
        occupied |= ndimage.binary_dilation(nz.cracks, iterations=2)   # they erupt in between

    report(progress, 0.3, "protrusions")
    prot = _protrusions(rng, spec, labels, is_light, px, height, albedo, occupied,
                        ridge_mask=ridge_layer > 1.0)
    height -= np.median(height)
    if not spec.rgb:
        albedo = albedo @ LUMINANCE
    albedo = albedo.astype(np.float32)
    height32 = height.astype(np.float32)
    normals = normals_from_height(height32, pixel_size_um=px)

    report(progress, 0.4, "lights")
    positions = light_positions(rng, n_lights=spec.n_lights, elevation_deg=spec.elevation_deg,
                                distance_mm=spec.distance_mm, azimuth_jitter=spec.azimuth_jitter)
    drift = 1 + rng.uniform(-spec.intensity_jitter, spec.intensity_jitter, spec.n_lights)
    if spec.fixed_exposure:
        # one lamp moved around at one exposure: the irradiance at the centre falls as 1/distance^2
        d = np.linalg.norm(positions, axis=1)
        intensities = drift * (np.median(d) / d) ** 2
    else:
        intensities = drift   # as if the exposure were reset for every image
    _lamp_and_lens_nuisances(spec, nz, positions, intensities, (m, n))
    if spec.cast_shadows:
        report(progress, 0.45, "cast shadows")
        nz.cast_shadows = True
        nz.shadowed = shadow_masks(height32, pixel_size_um=px, light_positions_mm=positions)
        nz.info["cast_shadows"] = {"shadowed_fraction": nz.shadowed.mean(axis=(1, 2)).tolist()}

    def shading():
        return _shading(normals, height32, px, positions, None, intensities,
                        beam_axes=nz.beam_axes, beam_exponent=nz.beam_exponent,
                        shadowed=nz.shadowed)

    amax = albedo if albedo.ndim == 2 else albedo.max(axis=2)
    if spec.stray_light > 0:
        _add_stray_light(spec, nz, shading(), albedo)
    peak = _peak(shading(), amax, nz)
    exposure = spec.exposure_fraction * 65535.0 / peak
    gain = 65535.0 / spec.full_well_e
    if nz.stray_light is not None:
        axes = (0, 1)
        nz.info["stray_light"]["mean_counts"] = (exposure * nz.stray_light.mean(axis=axes)).tolist()
        nz.info["stray_light"]["max_counts"] = (exposure * nz.stray_light.max(axis=axes)).tolist()
    report(progress, 0.5, "rendering")
    images = render_images(height32, albedo, pixel_size_um=px, light_positions_mm=positions,
                           intensities=intensities, rng=rng, noise=spec.noise, gain=gain,
                           read_noise=spec.read_noise, exposure=exposure, dtype=np.uint16,
                           nuisances=nz)
    logger.info("synthetic capture %dx%d, %d lights, %d areas, %d protrusions, %d ridges, "
                "%d primer spots", m, n, spec.n_lights, n_regions, prot["id"].size, n_ridges,
                n_spots)
    report(progress, 1.0, "done")
    return SyntheticCapture(images=images, light_positions_mm=positions, intensities=intensities,
                            height_um=height32, normals=normals, albedo=albedo, regions=labels,
                            region_names=names, region_light=is_light, protrusions=prot,
                            spec=spec, exposure=float(exposure), gain=float(gain), nuisances=nz)


def render_dark_frame(capture: SyntheticCapture) -> np.ndarray:
    """The frame a user takes with the UV lamp off: the capture's stray light and black level.

    ``run``'s ``dark`` parameter subtracts such a frame from every image. It holds what is the
    same in every image without the lamp: the black level and the stray light, as
    :func:`render_images` adds them (``stray_light`` stands for room light and a lamp's
    visible leak here; veiling glare of the lamp's own fluorescence would vanish with the lamp,
    and is not in a real dark frame), with the capture's photon and read noise drawn from a
    stream of its own (one frame, not an average: its noise is then common to every corrected
    image).

    Returns
    -------
    (M, N) or (M, N, C) array of the images' dtype.
    """
    spec, nz = capture.spec, capture.nuisances
    shape = capture.images.shape[1:]
    counts = np.zeros(shape, dtype=np.float32)
    if nz.stray_light is not None:
        stray = capture.exposure * np.asarray(nz.stray_light, dtype=np.float32)
        counts += stray if stray.ndim == counts.ndim else stray[..., None]
    if spec.noise:
        counts = _add_noise(counts, _substream(spec.seed, "dark frame"), gain=capture.gain,
                            read_noise=spec.read_noise)
    if nz.black_level is not None:
        black = np.asarray(nz.black_level, dtype=np.float32)
        counts += black if counts.ndim == 3 else black[0]
    info = np.iinfo(capture.images.dtype) if capture.images.dtype.kind in "ui" else None
    if info is not None:
        counts = np.clip(np.rint(counts), info.min, info.max)
    return counts.astype(capture.images.dtype)


#: A card as real ones are: tilted by up to 1 deg on the painting, its fluorescence uneven by 1 %
#: RMS (:func:`render_card`'s defaults in the benchmark's ``card`` mode).
CARD_TYPICAL = {"tilt_deg": 1.0, "unevenness": 0.01}


def render_card(capture: SyntheticCapture, *, tilt_deg: float = 0.0, tilt_azimuth_deg: float = 0.0,
                unevenness: float = 0.0, relief_um: float = 0.0, relief_period_mm: float = 2.0,
                peak_fraction: float = 0.75, colour=(0.85, 0.88, 0.80)) -> np.ndarray:
    """A flat fluorescent card on the painting, photographed under each of the capture's lamps.

    The same lamps (positions, ``E_k``, beams), lens (vignetting), stray light, black level and
    camera (exposure, gain, read noise) as ``capture``, so that :func:`render_dark_frame` of the
    capture is the card's dark frame too (:mod:`uvps.core.card`). The card's brightness sets its
    fluorescence: the brightest noise-free sample is ``peak_fraction`` of full scale (above 1 it
    saturates).

    Parameters
    ----------
    capture : SyntheticCapture
    tilt_deg, tilt_azimuth_deg : float
        The card's plane rises by ``tan(tilt)`` toward the azimuth (deg, counter-clockwise from +x).
    unevenness : float
        RMS fraction of the card's fluorescence varying across it (wavelengths 0.3-6 mm).
    relief_um, relief_period_mm : float
        A card not lying flat: ``relief_um * sin(2 pi x / P) * sin(2 pi y / P)`` on its plane.
    peak_fraction : float
        Brightest sample over full scale.
    colour : 3 floats
        The card's fluorescence colour (RGB captures).

    Returns
    -------
    (K, M, N) or (K, M, N, C) uint16 array, the capture's shape.
    """
    spec, nz = capture.spec, capture.nuisances
    K, M, N = capture.images.shape[:3]
    px = float(spec.pixel_size_um)
    x, y = pixel_centres_mm((M, N), px)
    az = math.radians(tilt_azimuth_deg)
    height = 1000.0 * math.tan(math.radians(tilt_deg)) * (x * math.cos(az) + y * math.sin(az))
    if relief_um:
        w = 2 * np.pi / relief_period_mm
        height = height + relief_um * np.sin(w * x) * np.sin(w * y)
    height = np.broadcast_to(height, (M, N)).astype(np.float64)
    rng = _substream(spec.seed, "card")
    field = np.zeros((M, N))
    if unevenness:
        for _ in range(12):
            wl = math.exp(rng.uniform(math.log(0.3), math.log(6.0)))
            th, ph = rng.uniform(0, 2 * np.pi, 2)
            field += np.cos(2 * np.pi / wl * (x * math.cos(th) + y * math.sin(th)) + ph)
        field *= unevenness / field.std()
    tone = np.clip(1.0 + field, 0.05, None)
    albedo = tone[..., None] * np.asarray(colour, float) if capture.images.ndim == 4 else tone
    card_nz = Nuisances(black_level=nz.black_level, stray_light=nz.stray_light, vignetting=nz.vignetting,
                        beam_axes=nz.beam_axes, beam_exponent=nz.beam_exponent)
    normals = _normals64(height, px)
    shading = _shading(normals, height, px, capture.light_positions_mm, None, capture.intensities,
                       beam_axes=nz.beam_axes, beam_exponent=nz.beam_exponent)
    amax = albedo if albedo.ndim == 2 else albedo.max(axis=2)
    direct = _peak(shading, amax, Nuisances(vignetting=nz.vignetting))
    stray = 0.0 if nz.stray_light is None else float(np.max(nz.stray_light))
    scale = (peak_fraction * 65535.0 / capture.exposure - stray) / direct
    if not scale > 0:
        raise UVPSInputError(f"peak_fraction {peak_fraction} leaves no room for the card above the stray light")
    return render_images(height, albedo * scale, pixel_size_um=px, light_positions_mm=capture.light_positions_mm,
                         intensities=capture.intensities, rng=rng, noise=spec.noise, gain=capture.gain,
                         read_noise=spec.read_noise, exposure=capture.exposure, dtype=np.uint16,
                         nuisances=card_nz)


def _lamp_and_lens_nuisances(spec, nz, positions, intensities, shape):
    """Black level, vignetting and beams of ``spec`` into ``nz`` (and the lamps' truth)."""
    channels = 3 if spec.rgb else 1
    nz.black_level = _black_levels(spec.black_level, channels)
    if nz.black_level is not None:
        nz.info["black_level_counts"] = nz.black_level.tolist()
    if spec.vignetting > 0:
        nz.vignetting, nz.info["vignetting"] = _vignetting_map(
            _substream(spec.seed, "vignetting"), shape, spec.vignetting)
    centre = np.ones(len(positions))
    if spec.beam_exponent > 0:
        nz.beam_axes, err = _beam_axes(_substream(spec.seed, "beams"), positions,
                                       spec.beam_aim_error_deg)
        nz.beam_exponent = float(spec.beam_exponent)
        to_centre = -positions / np.linalg.norm(positions, axis=1, keepdims=True)
        centre = np.clip(np.sum(nz.beam_axes * to_centre, axis=1), 0, None) ** nz.beam_exponent
        t = -positions[:, 2] / nz.beam_axes[:, 2]
        nz.info["beams"] = {"exponent": nz.beam_exponent,
                            "aim_error_deg": err.tolist(),
                            "axes": nz.beam_axes.tolist(),
                            "aim_points_mm": (positions + t[:, None] * nz.beam_axes).tolist(),
                            "centre_factor": centre.tolist()}
    nz.info["lamps"] = {"positions_mm": positions.tolist(), "intensities": intensities.tolist(),
                        "centre_irradiance": (intensities * centre).tolist()}


def _add_stray_light(spec, nz, shading, albedo, step=4):
    """Stray light of ``spec.stray_light`` x the median noise-free signal (per channel, over
    every image, sampled 1 pixel in ``step`` x ``step``), shaped by :func:`_stray_shape`."""
    alb = albedo[::step, ::step]
    samples = []
    for s in shading:
        s = s if nz.vignetting is None else s * nz.vignetting
        sub = s[::step, ::step]
        samples.append(sub * alb if alb.ndim == 2 else sub[..., None] * alb)
    samples = np.stack(samples)
    median = np.median(samples.reshape(-1, 1 if albedo.ndim == 2 else albedo.shape[2]), axis=0)
    field, info = _stray_shape(_substream(spec.seed, "stray light"), albedo.shape[:2])
    stray = spec.stray_light * (field * median[0] if albedo.ndim == 2
                                else field[..., None] * median)
    nz.stray_light = stray.astype(np.float32)
    nz.info["stray_light"] = {"fraction": float(spec.stray_light),
                              "median_signal": median.tolist(), **info}


def _normalised(a):
    s = a.std()
    return (a - a.mean()) / s if s > 0 else a * 0


def _checked_overrides(overrides):
    known = {f.name for f in dataclasses.fields(SyntheticSpec)}
    unknown = sorted(set(overrides) - known)
    if unknown:
        raise UVPSInputError(f"unknown SyntheticSpec option(s) {unknown}; expected some of "
                             f"{sorted(known)}")
    return overrides


# --------------------------------------------------------------------------------------------
# Writing
# --------------------------------------------------------------------------------------------


def write_truth_run(capture: SyntheticCapture, folder, *, pixel_size_um=None) -> Path:
    """A run folder made of the capture's truth: ``albedo.tif``, ``depth.tif`` and ``protrusions.csv``
    (id, x_px, y_px, width_um, height_um), as ``uvps run --detect`` would write them with no error
    of its own: for testing what reads run folders (``changes``, ``stats``) apart from the pipeline.
    """
    folder = Path(folder)
    folder.mkdir(parents=True)
    px = capture.spec.pixel_size_um if pixel_size_um is None else float(pixel_size_um)
    write_imagej_tiff(folder / "albedo.tif", np.moveaxis(capture.albedo, -1, 0), axes="CYX", pixel_size_um=px)
    write_imagej_tiff(folder / "depth.tif", capture.height_um, axes="YX", pixel_size_um=px)
    t = capture.protrusions
    with open(folder / "protrusions.csv", "w", newline="", encoding="utf-8") as fh:
        w = csv.writer(fh)
        w.writerow(["id", "x_px", "y_px", "width_um", "height_um"])
        for i in range(t["id"].size):
            w.writerow([int(t["id"][i]), t["x_px"][i], t["y_px"][i], t["width_um"][i], t["height_um"][i]])
    return folder


#: The black and white levels of the DNG files :func:`write_dng` writes (a 14-bit sensor).
DNG_BLACK, DNG_WHITE = 512, 16383


def write_dng(path, rgb, *, black=DNG_BLACK, white=DNG_WHITE):
    """A minimal CFA DNG of the linear scene ``rgb`` (M, N, 3) counts above ``black``: the RGGB mosaic
    plus ``black``, 16-bit, with the tags LibRaw needs (CFA layout, DNG version, camera model, black
    and white levels, an identity colour matrix, a neutral white balance)."""
    rgb = np.asarray(rgb, dtype=np.float64)
    M, N = rgb.shape[:2]
    pattern = np.array([[0, 1], [1, 2]])                      # R G / G B
    ch = pattern[np.arange(M)[:, None] % 2, np.arange(N)[None, :] % 2]
    mosaic = np.take_along_axis(rgb, ch[..., None], axis=2)[..., 0] + black
    mosaic = np.clip(np.rint(mosaic), 0, white).astype(np.uint16)

    def rational(values, den=10000):
        return tuple(x for v in values for x in (int(round(v * den)), den))

    extratags = [
        (33421, "H", 2, (2, 2), True),                         # CFARepeatPatternDim
        (33422, "B", 4, (0, 1, 1, 2), True),                   # CFAPattern: R G G B
        (50706, "B", 4, (1, 4, 0, 0), True),                   # DNGVersion
        (50707, "B", 4, (1, 1, 0, 0), True),                   # DNGBackwardVersion
        (50708, "s", 0, "uvps test camera", True),             # UniqueCameraModel
        (50714, "H", 1, (int(black),), True),                  # BlackLevel
        (50717, "H", 1, (int(white),), True),                  # WhiteLevel
        (50721, "2i", 9, rational([1, 0, 0, 0, 1, 0, 0, 0, 1]), True),   # ColorMatrix1
        (50728, "2I", 3, rational([1, 1, 1]), True),           # AsShotNeutral
        (50778, "H", 1, (21,), True),                          # CalibrationIlluminant1: D65
    ]
    tifffile.imwrite(path, mosaic, photometric=32803, extratags=extratags, metadata=None, subfiletype=0)
    return path



def write_raw_capture(capture: SyntheticCapture, folder) -> list:
    """Write a capture as camera raw files: ``uv_NN.dng`` (:func:`write_dng`, counts / 4: the mosaic's
    14 bits) and ``lights.csv`` (``file,x_mm,y_mm,z_mm``). Returns the paths written."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=False)
    paths = []
    for k, img in enumerate(capture.images):
        rgb = np.asarray(img, np.float64)
        rgb = rgb if rgb.ndim == 3 else np.repeat(rgb[..., None], 3, axis=2)
        paths.append(write_dng(folder / f"uv_{k:02d}.dng", rgb / 4.0))
    lines = ["file,x_mm,y_mm,z_mm"] + [f"uv_{k:02d}.dng," + ",".join(f"{v:.6f}" for v in p)
                                       for k, p in enumerate(capture.light_positions_mm)]
    (folder / "lights.csv").write_text("\n".join(lines) + "\n")
    return paths + [folder / "lights.csv"]



def write_capture(capture: SyntheticCapture, folder, *, truth: bool = True, dark_frame: bool = False,
                  card: Optional[np.ndarray] = None) -> list:
    """Write a capture as a folder of 16-bit TIFFs, light files and (optionally) ground truth.

    Parameters
    ----------
    capture : SyntheticCapture
    folder : path
        Created if missing (its parent must exist); files are moved in atomically.
    truth : bool
        Also write ``truth/``.
    dark_frame : bool
        Also write ``dark/dark.tif`` (:func:`render_dark_frame`), for ``run``'s ``dark``
        parameter (in a folder of its own, so that the folder's images stay the lamps' ones).
    card : (K, M, N[, C]) array, optional
        A card's images (:func:`render_card`), written as ``card/`` with the images' names (``run``'s
        ``card`` parameter).

    Returns
    -------
    paths : list of Path
        Every file written, images first.

    Notes
    -----
    Images: ``uv_00.tif``... 16-bit RGB (interleaved, as a camera converter writes them) or grey,
    with XResolution = YResolution = 1 / pixel size (pixels per um) and an ImageJ description
    ``unit=micron`` so that ImageJ's calibration is right. ``lights_positions_mm.csv``
    (file,x_mm,y_mm,z_mm) and ``lights.lp`` (RTI format: K, then ``file x y z``, the unit
    direction from the image centre to each light). ``truth/``: ``height_um.tif``,
    ``normals.tif`` (3, M, N) CYX, ``albedo.tif``, ``regions.tif`` (labels, uint16 as ImageJ has
    no 32-bit integers), ``protrusions.csv`` (columns as ``uvps.core.measure``'s, plus ``weak``,
    ``aspect``, ``angle_deg``, ``region_name``, ``shape``, ``cluster``, ``dark``),
    ``truth.json`` (with ``nuisances``: black level per channel, stray light's fraction and mean
    counts per channel, vignetting parameters, each lamp's beam axis, aim point and factor at
    the centre, each lamp's position, ``E_k`` and irradiance at the centre, cast-shadow
    fractions, crack parameters: whichever are present) and, when present, ``vignetting.tif``,
    ``stray_light_counts.tif``, ``shadows.tif`` (K planes, 1 = shadowed) and ``cracks.tif``.
    Truth TIFFs are ImageJ hyperstacks written by :func:`uvps.files.io.write_imagej_tiff`.
    """
    px = float(capture.spec.pixel_size_um)
    k = capture.images.shape[0]
    digits = max(2, len(str(k - 1)))
    names = [f"uv_{i:0{digits}d}.tif" for i in range(k)]
    folder = Path(folder)
    with atomic_output_dir(folder) as tmp:
        written = []
        for name, img in zip(names, capture.images):
            _write_camera_tiff(tmp / name, img, px)
            written.append(name)
        pos = capture.light_positions_mm
        with open(tmp / "lights_positions_mm.csv", "w", newline="", encoding="utf-8") as fh:
            wr = csv.writer(fh)
            wr.writerow(["file", "x_mm", "y_mm", "z_mm"])
            for name, p in zip(names, pos):
                wr.writerow([name] + [f"{v:.6f}" for v in p])
        directions = pos / np.linalg.norm(pos, axis=1, keepdims=True)
        with open(tmp / "lights.lp", "w", encoding="utf-8") as fh:
            fh.write(f"{k}\n")
            for name, d in zip(names, directions):
                fh.write(f"{name} {d[0]:.8f} {d[1]:.8f} {d[2]:.8f}\n")
        written += ["lights_positions_mm.csv", "lights.lp"]
        if dark_frame:
            (tmp / "dark").mkdir()
            _write_camera_tiff(tmp / "dark" / "dark.tif", render_dark_frame(capture), px)
            written.append("dark/dark.tif")
        if card is not None:
            (tmp / "card").mkdir()
            for name, img in zip(names, card):
                _write_camera_tiff(tmp / "card" / name, img, px)
                written.append(f"card/{name}")
        if truth:
            written += _write_truth(capture, tmp / "truth", names)
    return [folder / w for w in written]


def _write_camera_tiff(path, img, px, **tiff_options):
    """One image as a camera converter writes it (interleaved RGB or grey), calibrated in um;
    ``tiff_options`` go to ``tifffile.imwrite`` (e.g. ``compression``, ``byteorder``)."""
    tifffile.imwrite(path, img, photometric="rgb" if img.ndim == 3 else "minisblack",
                     resolution=(1 / px, 1 / px), resolutionunit="NONE",
                     description="ImageJ=1.54f\nunit=micron\n", metadata=None, **tiff_options)


def _write_truth(capture, folder, image_names):
    folder.mkdir()
    px = float(capture.spec.pixel_size_um)
    # Truth TIFFs are ImageJ hyperstacks through the shared writer (atomic, calibrated in um).

    def imagej(name, data, axes, labels=None):
        write_imagej_tiff(folder / name, data, axes=axes, pixel_size_um=px, labels=labels)

    imagej("height_um.tif", capture.height_um.astype(np.float32), "YX")
    imagej("normals.tif", np.moveaxis(capture.normals, -1, 0).astype(np.float32), "CYX",
           ["nx", "ny", "nz"])
    alb = capture.albedo.astype(np.float32)
    if alb.ndim == 3:
        imagej("albedo.tif", np.moveaxis(alb, -1, 0), "CYX", ["R", "G", "B"])
    else:
        imagej("albedo.tif", alb, "YX")
    imagej("regions.tif", capture.regions.astype(np.int32), "YX")
    # Same leading columns as uvps.core.measure's protrusions.csv, so `compare` takes it as is.
    prot = dict(capture.protrusions)
    prot["area_um2"] = np.pi * prot["width_um"] ** 2 / 4
    columns = ["id", "x_px", "y_px", "width_um", "area_um2", "height_um", "crater", "region",
               "weak", "aspect", "angle_deg"]
    extra = [c for c in ("shape", "cluster", "dark", "on_stroke") if c in prot]
    with open(folder / "protrusions.csv", "w", newline="", encoding="utf-8") as fh:
        wr = csv.writer(fh)
        wr.writerow(columns + ["region_name"] + extra)
        for i in range(prot["id"].size):
            row = []
            for c in columns:
                v = prot[c][i]
                row.append(int(v) if v.dtype.kind in "biu" else f"{float(v):.4f}")
            row.append(capture.region_names[int(prot["region"][i]) - 1])
            row += [str(prot[c][i]) if prot[c].dtype.kind == "U" else int(prot[c][i])
                    for c in extra]
            wr.writerow(row)
    nz = capture.nuisances
    files = ["height_um.tif", "normals.tif", "albedo.tif", "regions.tif"]
    if nz.vignetting is not None:
        imagej("vignetting.tif", nz.vignetting.astype(np.float32), "YX")
        files.append("vignetting.tif")
    if nz.stray_light is not None:
        stray = (capture.exposure * nz.stray_light).astype(np.float32)   # counts
        if stray.ndim == 3:
            imagej("stray_light_counts.tif", np.moveaxis(stray, -1, 0), "CYX", ["R", "G", "B"])
        else:
            imagej("stray_light_counts.tif", stray, "YX")
        files.append("stray_light_counts.tif")
    if nz.shadowed is not None:
        imagej("shadows.tif", nz.shadowed.astype(np.uint8), "ZYX", image_names)
        files.append("shadows.tif")
    if nz.cracks is not None:
        imagej("cracks.tif", nz.cracks.astype(np.uint8), "YX")
        files.append("cracks.tif")
    spec = dataclasses.asdict(capture.spec)
    write_json_atomic(folder / "truth.json", {
        "schema_version": 1,
        "pixel_size_um": px,
        "image_shape": list(capture.height_um.shape),
        "files": image_names,
        "light_positions_mm": capture.light_positions_mm,
        "intensities": capture.intensities,
        "exposure": capture.exposure,
        "gain": capture.gain,
        "region_names": capture.region_names,
        "region_light": [bool(b) for b in capture.region_light],
        "n_protrusions": int(prot["id"].size),
        "spec": {key: list(val) if isinstance(val, tuple) else val for key, val in spec.items()},
        "nuisances": nz.info,
        "frames": "x right, y up, z toward camera; positions in mm from the image centre; "
                  "heights in um (median 0); normals.tif channels nx, ny, nz",
    })
    return [f"truth/{f}" for f in files + ["protrusions.csv", "truth.json"]]


# --------------------------------------------------------------------------------------------
# A later capture of the same surface (monitoring over time; uvps changes)
# --------------------------------------------------------------------------------------------


@dataclass
class LaterSpec:
    """How a later capture differs from the first (:func:`make_capture_pair`).

    The camera: B's pixel ``(x=col, y=row)`` maps to A's by a similarity about the image centre,
    ``x_a = scale R(rotation_deg) (x_b - c) + c + shift_px``; None draws each within its bound
    (shift up to ``max_shift_px`` in a random direction, rotation within +-``max_rotation_deg``,
    scale within 1 +- ``max_scale_change``). One B pixel spans ``scale`` A pixels, so B's pixel
    size is ``scale`` x A's. The lamps are drawn anew (another session). The surface:
    ``grown_fraction`` of the lone protrusions (domes, craters, mesas with room around them)
    grow by a factor of ``width_growth`` in width and ``height_growth`` in height,
    ``new_per_cm2`` new domes of ``new_width_um`` erupt where there is room, and
    ``gone_fraction`` of them are gone (flattened to the paint around them). :meth:`unchanged`
    is the same surface, only another pose and other lamps.
    """

    shift_px: Optional[tuple] = None
    rotation_deg: Optional[float] = None
    scale: Optional[float] = None
    max_shift_px: float = 200.0
    max_rotation_deg: float = 3.0
    max_scale_change: float = 0.02
    grown_fraction: float = 0.25
    width_growth: tuple = (1.2, 1.5)
    height_growth: tuple = (1.2, 1.6)
    new_per_cm2: float = 4.0
    new_width_um: tuple = (40.0, 400.0)
    gone_fraction: float = 0.04
    seed: int = 1

    @classmethod
    def unchanged(cls, **fields) -> "LaterSpec":
        """Another pose and other lamps, the surface as it was (the repeatability pair)."""
        return cls(**{"grown_fraction": 0.0, "new_per_cm2": 0.0, "gone_fraction": 0.0, **fields})


@dataclass
class CapturePair:
    """Two captures of one surface and the truth of what changed (:func:`make_capture_pair`).

    ``b_to_a`` (3, 3) takes B pixel coordinates ``(x=col, y=row, 1)`` to A's. ``changes`` holds
    equal-length columns, one row per protrusion in A's or B's field: ``id_a``, ``id_b`` (1-based
    rows of ``a.protrusions`` / ``b.protrusions``, 0 where absent), ``x_px_a``, ``y_px_a``,
    ``x_px_b``, ``y_px_b``, ``status`` (new, grown, unchanged, gone), ``width_um_a``,
    ``width_um_b``, ``height_um_a``, ``height_um_b`` (NaN where absent).
    """

    a: SyntheticCapture
    b: SyntheticCapture
    b_to_a: np.ndarray
    changes: dict
    later: LaterSpec
    info: dict


def similarity_matrix(shape, *, shift_px=(0.0, 0.0), rotation_deg=0.0, scale=1.0) -> np.ndarray:
    """The 3 x 3 matrix ``b_to_a`` of a camera rotated and scaled about the centre of a
    ``shape`` (M, N) image and shifted by ``shift_px`` (x, y) pixels.

    >>> T = similarity_matrix((100, 200), shift_px=(5.0, -2.0))
    >>> (T @ [10.0, 10.0, 1.0]).tolist()
    [15.0, 8.0, 1.0]
    """
    m, n = shape
    c = np.array([(n - 1) / 2.0, (m - 1) / 2.0])
    t = math.radians(rotation_deg)
    lin = scale * np.array([[math.cos(t), -math.sin(t)], [math.sin(t), math.cos(t)]])
    out = np.eye(3)
    out[:2, :2] = lin
    out[:2, 2] = c - lin @ c + np.asarray(shift_px, float)
    return out


def _ellipse(prot, i, px, shape, grow=1.0, reach=1.6):
    """Window, coordinates and elliptical radius of protrusion ``i`` (grown ``grow`` x)."""
    w, asp, phi = prot["width_um"][i], prot["aspect"][i], math.radians(prot["angle_deg"][i])
    a = w / 2 * math.sqrt(asp) / px
    b = w / 2 / math.sqrt(asp) / px
    cr, cc = prot["y_px"][i], prot["x_px"][i]
    margin = int(math.ceil(a * grow * reach)) + 3
    r0, r1 = max(int(cr) - margin, 0), min(int(cr) + margin + 1, shape[0])
    c0, c1 = max(int(cc) - margin, 0), min(int(cc) + margin + 1, shape[1])
    rr = np.arange(r0, r1)[:, None] - cr
    ccs = np.arange(c0, c1)[None, :] - cc
    u = ccs * np.cos(phi) + rr * np.sin(phi)
    v = -ccs * np.sin(phi) + rr * np.cos(phi)
    rho = np.sqrt((u / a) ** 2 + (v / b) ** 2)
    return (slice(r0, r1), slice(c0, c1)), rr, ccs, rho, a


def _own_relief(height, win, rr, ccs, rho):
    """A protrusion's own relief in its window (zero outside its footprint) and the surface
    under it: a plane fitted to the ring just outside the footprint (the weave under it is lost)."""
    h = height[win]
    ring = (rho > 1.05) & (rho < 1.6)
    design = np.column_stack([np.ones(ring.sum()), rr.repeat(ccs.shape[1], 1)[ring],
                              ccs.repeat(rr.shape[0], 0)[ring]])
    coef = np.linalg.lstsq(design, h[ring], rcond=None)[0]
    base = coef[0] + coef[1] * rr + coef[2] * ccs
    return np.where(rho < 1.0, h - base, 0.0)


def _change_surface(rng, later, prot, height, albedo, px):
    """Grow, remove and add protrusions on the world surface, in place. Returns the world table
    after the change (ids of ``prot``, then the new ones) and each row's status."""
    n = prot["id"].size
    shape = height.shape
    rad = prot["width_um"] * np.sqrt(prot["aspect"]) / 2 / px
    xy = np.column_stack([prot["x_px"], prot["y_px"]])
    tree = cKDTree(xy) if n else None
    status = np.array(["unchanged"] * n, dtype="<U9")
    after = {k: np.array(v, copy=True) for k, v in prot.items() if k != "id"}
    lone = np.flatnonzero((prot["cluster"] == 0) & np.isin(prot["shape"], ("dome", "crater", "mesa")))
    order = rng.permutation(lone)
    n_grow = int(round(later.grown_fraction * lone.size))
    n_gone = int(round(later.gone_fraction * lone.size))
    # growth needs room: the grown footprint must stay clear of every neighbour's
    grown = []
    for i in order:
        if len(grown) >= n_grow:
            break
        sw = rng.uniform(*later.width_growth)
        near = tree.query_ball_point(xy[i], sw * rad[i] + rad.max() + 4)
        if any(j != i and np.hypot(*(xy[j] - xy[i])) < sw * rad[i] + rad[j] + 4 for j in near):
            continue
        win, rr, ccs, rho, a = _ellipse(prot, i, px, shape, grow=sw)
        if rho.shape != rr.shape[:1] + ccs.shape[1:] or win[0].start == 0 or win[1].start == 0 \
                or win[0].stop == shape[0] or win[1].stop == shape[1]:
            continue
        sh = rng.uniform(*later.height_growth)
        own = _own_relief(height, win, rr, ccs, rho)
        # the relief and colour drawn again sw x wider (sampled at the shrunk coordinates)
        r_src = rr / sw + (prot["y_px"][i] - win[0].start)
        c_src = ccs / sw + (prot["x_px"][i] - win[1].start)
        rr_b, cc_b = np.broadcast_arrays(r_src, c_src)
        grown_own = ndimage.map_coordinates(own, [rr_b, cc_b], order=1, mode="constant")
        height[win] += sh * grown_own - own
        inside = rho / sw < 1.0 + 1.0 / a
        sub = albedo[win]
        for ch in range(sub.shape[2]):
            src = ndimage.map_coordinates(sub[..., ch], [rr_b, cc_b], order=1, mode="nearest")
            sub[..., ch] = np.where(inside, src, sub[..., ch])
        status[i] = "grown"
        after["width_um"][i] *= sw
        after["height_um"][i] *= sh
        grown.append(i)
    for i in [j for j in order if status[j] == "unchanged"][:n_gone]:
        win, rr, ccs, rho, a = _ellipse(prot, i, px, shape)
        height[win] -= _own_relief(height, win, rr, ccs, rho)
        sub = albedo[win]
        ring = (rho > 1.2) & (rho < 1.6)
        paint = np.median(sub[ring], axis=0)
        sub[rho < 1.0 + 1.0 / a] = paint
        status[i] = "gone"
    # new domes where there is room (off every protrusion, inside the field)
    area_cm2 = shape[0] * shape[1] * px * px / _UM2_PER_CM2
    n_new = int(rng.poisson(later.new_per_cm2 * area_cm2)) if later.new_per_cm2 > 0 else 0
    colour = np.array(PROTRUSION_COLOUR)[: albedo.shape[2]]
    new_rows = []
    for w_um in _protrusion_widths(rng, n_new, later.new_width_um) if n_new else []:
        r = w_um / 2 / px
        for _ in range(60):
            cr, cc = rng.uniform(r + 8, shape[0] - r - 8), rng.uniform(r + 8, shape[1] - r - 8)
            if tree is not None and np.any(np.hypot(*(xy - (cc, cr)).T) < r + rad + 6):
                continue
            if any(np.hypot(cc - x, cr - y) < r + rn + 6 for x, y, rn in new_rows):
                continue
            break
        else:
            continue
        h_dome = rng.uniform(0.15, 0.35) * w_um
        gamma = rng.uniform(1.0, 1.6)
        m_ = int(math.ceil(r)) + 2
        win = (slice(int(cr) - m_, int(cr) + m_ + 1), slice(int(cc) - m_, int(cc) + m_ + 1))
        rr = np.arange(win[0].start, win[0].stop)[:, None] - cr
        ccs = np.arange(win[1].start, win[1].stop)[None, :] - cc
        rho = np.sqrt(rr ** 2 + ccs ** 2) / r
        height[win] += h_dome * _dome_profile(rho, gamma, None)
        wgt = np.clip((1 - rho) * r, 0, 1)[..., None]
        albedo[win] = albedo[win] * (1 - wgt) + colour * rng.uniform(0.92, 1.05) * wgt
        new_rows.append((cc, cr, r))
        new_row = {"x_px": cc, "y_px": cr, "width_um": w_um, "height_um": h_dome, "aspect": 1.0,
                   "angle_deg": 0.0, "shape": "dome", "crater": False, "weak": False, "dark": False,
                   "cluster": 0, "region": 0}
        for key in after:
            after[key] = np.append(after[key], np.asarray(new_row[key], dtype=after[key].dtype))
        status = np.append(status, "new")
    return after, status


def _view_table(world, status, keep, to_view, shape, region_of):
    """The protrusion table of one view: world rows ``keep`` whose centre lands in the field."""
    world_xy = np.column_stack([world["x_px"], world["y_px"]])
    xy = to_view(world_xy)
    m, n = shape
    inside = keep & (xy[:, 0] >= 0) & (xy[:, 0] <= n - 1) & (xy[:, 1] >= 0) & (xy[:, 1] <= m - 1)
    idx = np.flatnonzero(inside)
    order = idx[np.lexsort((xy[idx, 0], xy[idx, 1]))]
    table = {"id": np.arange(1, order.size + 1, dtype=np.int32)}
    table.update({k: v[order] for k, v in world.items()})
    table.update({"x_px": xy[order, 0], "y_px": xy[order, 1], "status": status[order],
                  "region": region_of(world_xy[order]).astype(np.int32)})
    ids = np.zeros(len(status), np.int32)
    ids[order] = table["id"]
    return table, ids, xy


def _render_view(height, albedo, regions, spec, px, rng, world_like):
    """A capture of ``height``/``albedo`` (already in the view's pixel grid) under lamps from ``rng``."""
    height = (height - np.median(height)).astype(np.float32)
    albedo = albedo.astype(np.float32)
    normals = normals_from_height(height, pixel_size_um=px)
    positions = light_positions(rng, n_lights=spec.n_lights, elevation_deg=spec.elevation_deg,
                                distance_mm=spec.distance_mm, azimuth_jitter=spec.azimuth_jitter)
    intensities = 1 + rng.uniform(-spec.intensity_jitter, spec.intensity_jitter, spec.n_lights)
    nz = Nuisances()
    # the spec's lamp and lens nuisances (black level, vignetting, beams; none by default), the
    # same camera and lamp models at both dates
    _lamp_and_lens_nuisances(spec, nz, positions, intensities, height.shape)
    amax = albedo if albedo.ndim == 2 else albedo.max(axis=2)
    peak = _peak(_shading(normals, height, px, positions, None, intensities, beam_axes=nz.beam_axes,
                          beam_exponent=nz.beam_exponent), amax, nz)
    exposure = spec.exposure_fraction * 65535.0 / peak
    gain = 65535.0 / spec.full_well_e
    images = render_images(height, albedo, pixel_size_um=px, light_positions_mm=positions,
                           intensities=intensities, rng=rng, noise=spec.noise, gain=gain,
                           read_noise=spec.read_noise, exposure=exposure, dtype=np.uint16,
                           nuisances=nz)
    view_spec = dataclasses.replace(spec, pixel_size_um=px)
    return SyntheticCapture(images=images, light_positions_mm=positions, intensities=intensities,
                            height_um=height, normals=normals, albedo=albedo, regions=regions,
                            region_names=world_like.region_names,
                            region_light=world_like.region_light, protrusions={}, spec=view_spec,
                            exposure=float(exposure), gain=float(gain), nuisances=nz)


def make_capture_pair(spec: Optional[SyntheticSpec] = None, later: Optional[LaterSpec] = None, *,
                      progress: Progress = None, **overrides) -> CapturePair:
    """Two captures of one painted surface, years apart: A, and B from another camera pose
    under other lamps after some protrusions grew, erupted or went.

    Parameters
    ----------
    spec : SyntheticSpec, optional
        The scene and camera of A (its ``shape`` and ``pixel_size_um``). Of the nuisances of a
        real capture, the canvas bow (``bow_um``), black level, vignetting and lamp beams are
        drawn (the same camera and lamp models at both dates, the lamps placed again); stray
        light, cast shadows and cracks are not.
    later : LaterSpec, optional
        How B differs (default :class:`LaterSpec()`; :meth:`LaterSpec.unchanged` for the
        repeatability pair).
    **overrides
        Fields of :class:`SyntheticSpec`.

    Returns
    -------
    CapturePair
        ``a``, ``b`` (:class:`SyntheticCapture`; ``protrusions`` of each view: the columns of
        :func:`make_capture`'s in the view's pixels, plus ``status``), ``b_to_a``, ``changes``
        (the truth, one row per protrusion of either field) and ``info`` (shift, rotation, scale,
        counts).

    Notes
    -----
    One world surface (:func:`make_capture`'s scene on a field wide enough for both views) is
    seen by A as a crop and by B through the similarity (cubic interpolation of the height,
    linear of the albedo, nearest of the colour areas); the changes are made on the world
    between the two renders: a grown protrusion's own relief (the height above a plane fitted
    around it) is redrawn ``s_w`` x wider and ``s_h`` x higher, a gone one's is removed and its
    colour set to the paint's around it. Cost: about 2x :func:`make_capture` of the same shape.

    Examples
    --------
    >>> pair = make_capture_pair(shape=(120, 160), n_lights=4, protrusion_density_light=0,
    ...                          protrusion_density_dark=0, later=LaterSpec(shift_px=(10.0, 0.0),
    ...                          rotation_deg=0.0, scale=1.0))
    >>> pair.b_to_a[:2, 2].tolist(), pair.b.images.shape
    ([10.0, 0.0], (4, 120, 160, 3))
    """
    spec = dataclasses.replace(spec or SyntheticSpec(), **_checked_overrides(overrides))
    spec.shape = tuple(int(s) for s in spec.shape)
    later = later or LaterSpec()
    rng = np.random.default_rng((int(later.seed), zlib.crc32(b"later capture")))
    m, n = spec.shape
    px = float(spec.pixel_size_um)
    if later.shift_px is None:
        ang, mag = rng.uniform(0, 2 * np.pi), rng.uniform(0.5, 1.0) * later.max_shift_px
        shift = (mag * math.cos(ang), mag * math.sin(ang))
    else:
        shift = tuple(float(s) for s in later.shift_px)
    rot = (rng.uniform(-1, 1) * later.max_rotation_deg if later.rotation_deg is None
           else float(later.rotation_deg))
    scale = (1 + rng.uniform(-1, 1) * later.max_scale_change if later.scale is None
             else float(later.scale))
    b_to_a = similarity_matrix((m, n), shift_px=shift, rotation_deg=rot, scale=scale)
    # the world: wide enough for both fields, and for any pose within the bounds (so that A is
    # the same capture for every later capture of one spec: one A, several B)
    corners = np.array([[0, 0, 1], [n - 1, 0, 1], [0, m - 1, 1], [n - 1, m - 1, 1]], float)
    reach = (b_to_a @ corners.T)[:2]
    bound = (later.max_shift_px + math.hypot(m, n) / 2
             * (math.radians(later.max_rotation_deg) + later.max_scale_change))
    margin = int(math.ceil(max(bound, -reach.min(), reach[0].max() - (n - 1),
                               reach[1].max() - (m - 1)))) + 8
    report(progress, 0.0, "the surface")
    world = make_capture(spec, shape=(m + 2 * margin, n + 2 * margin), n_lights=3, noise=False)
    height, albedo = world.height_um.astype(np.float64), world.albedo.astype(np.float64)
    if albedo.ndim == 2:
        albedo = albedo[..., None]
    region_w = world.regions

    def region_of(xy_world):
        r = np.clip(np.rint(xy_world[:, 1]).astype(int), 0, region_w.shape[0] - 1)
        c = np.clip(np.rint(xy_world[:, 0]).astype(int), 0, region_w.shape[1] - 1)
        return region_w[r, c]

    crop = (slice(margin, margin + m), slice(margin, margin + n))
    alb_a = albedo[crop] if world.albedo.ndim == 3 else albedo[crop][..., 0]
    report(progress, 0.3, "capture A")
    a = _render_view(height[crop], alb_a, region_w[crop], spec, px,
                     np.random.default_rng((int(spec.seed), zlib.crc32(b"view a"))), world)
    report(progress, 0.5, "the changes")
    after, status = _change_surface(rng, later, world.protrusions, height, albedo, px)
    # B's grid in world pixels: world = A + margin = b_to_a (x_b) + margin
    yy, xx = np.mgrid[0:m, 0:n].astype(np.float64)
    wx = b_to_a[0, 0] * xx + b_to_a[0, 1] * yy + b_to_a[0, 2] + margin
    wy = b_to_a[1, 0] * xx + b_to_a[1, 1] * yy + b_to_a[1, 2] + margin
    h_b = ndimage.map_coordinates(height, [wy, wx], order=3, mode="nearest")
    alb_b = np.stack([ndimage.map_coordinates(albedo[..., c], [wy, wx], order=1, mode="nearest")
                      for c in range(albedo.shape[2])], axis=-1)
    if world.albedo.ndim == 2:
        alb_b = alb_b[..., 0]
    reg_b = ndimage.map_coordinates(region_w, [wy, wx], order=0, mode="nearest").astype(region_w.dtype)
    report(progress, 0.7, "capture B")
    b = _render_view(h_b, alb_b, reg_b, spec, px * scale,
                     np.random.default_rng((int(later.seed), zlib.crc32(b"view b"))), world)
    a_to_b = np.linalg.inv(b_to_a)
    n_before = world.protrusions["id"].size

    def to_a(xy):
        return xy - margin

    def to_b(xy):
        h = np.column_stack([xy - margin, np.ones(len(xy))]) @ a_to_b.T
        return h[:, :2]

    present_a = np.arange(len(status)) < n_before
    present_b = status != "gone"
    world_a = {k: np.concatenate([world.protrusions[k], after[k][n_before:]]) for k in after}
    a.protrusions, ids_a, xy_a = _view_table(world_a, status, present_a, to_a, (m, n), region_of)
    b.protrusions, ids_b, xy_b = _view_table(after, status, present_b, to_b, (m, n), region_of)
    rows = np.flatnonzero((ids_a > 0) | (ids_b > 0))
    nan = np.full(len(status), np.nan)
    changes = {"id_a": ids_a[rows], "id_b": ids_b[rows],
               "x_px_a": xy_a[rows, 0], "y_px_a": xy_a[rows, 1],
               "x_px_b": xy_b[rows, 0], "y_px_b": xy_b[rows, 1], "status": status[rows],
               "width_um_a": np.where(present_a, world_a["width_um"], nan)[rows],
               "width_um_b": np.where(present_b, after["width_um"], nan)[rows],
               "height_um_a": np.where(present_a, world_a["height_um"], nan)[rows],
               "height_um_b": np.where(present_b, after["height_um"], nan)[rows]}
    counts = {s: int(np.sum(changes["status"] == s)) for s in ("unchanged", "grown", "new", "gone")}
    info = {"shift_px": list(shift), "rotation_deg": rot, "scale": scale, "margin_px": margin,
            "pixel_size_um_a": px, "pixel_size_um_b": px * scale, "counts": counts}
    logger.info("capture pair: shift %s px, rotation %.2f deg, scale %.4f; %s", shift, rot, scale, counts)
    report(progress, 1.0, "done")
    return CapturePair(a, b, b_to_a, changes, later, info)
