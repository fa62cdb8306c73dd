""":func:`make_capture`: a synthetic capture from a :class:`SyntheticSpec`, composed of the surface
and its rendering.

Part of :mod:`uvps.testing.synthetic`, which exposes every public name; import from there.
"""
from __future__ import annotations

import dataclasses
from typing import Optional

import numpy as np
from scipy import ndimage

from ..errors import UVPSInputError
from ..files.outputs import Progress, report
from .synthetic_spec import (
    LUMINANCE,
    Nuisances,
    PROTRUSION_KINDS,
    SyntheticCapture,
    SyntheticSpec,
    _UM2_PER_CM2,
    _checked_overrides,
    logger,
)
from .synthetic_render import (
    _add_stray_light,
    _black_levels,
    _lamp_and_lens_nuisances,
    _normalised,
    _peak,
    _shading,
    _substream,
    light_positions,
    normals_from_height,
    pixel_centres_mm,
    render_images,
    shadow_masks,
)
from .synthetic_surface import (
    _Impasto,
    _colour_areas,
    _cracks,
    _primer_spots,
    _protrusions,
    _region_palette,
    _ridges,
    _weave,
    _weave_scales,
)


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
    if not (np.isfinite(spec.width_median_um) and spec.width_median_um > 0):
        raise UVPSInputError(f"width_median_um must be a finite width > 0 um (moved into width_um when "
                             f"outside it); got {spec.width_median_um}")
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
