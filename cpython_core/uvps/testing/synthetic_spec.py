"""The synthetic capture's description: colours, :class:`Nuisances`, :class:`SyntheticSpec` and its
presets, and :class:`SyntheticCapture` (the images and their ground truth).

Part of :mod:`uvps.testing.synthetic`, which exposes every public name; import from there.
"""
from __future__ import annotations

import dataclasses
import logging
from dataclasses import dataclass
from typing import Optional

import numpy as np

from ..errors import UVPSInputError
from ..core.stack import Capture

logger = logging.getLogger("uvps.testing.synthetic")  # the name the package has always logged under

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
    ``width_um`` (a median outside it is moved to its nearer end): 100 puts a third of them
    below 80 um (a few pixels of 15 um).
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


def _checked_overrides(overrides):
    known = {f.name for f in dataclasses.fields(SyntheticSpec)}
    unknown = sorted(set(overrides) - known)
    if unknown:
        raise UVPSInputError(f"unknown SyntheticSpec option(s) {unknown}; expected some of "
                             f"{sorted(known)}")
    return overrides
