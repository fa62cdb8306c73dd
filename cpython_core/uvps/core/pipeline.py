"""The whole run: capture -> additive term -> drop-off fits and lights -> normals/albedo -> height
-> (colour areas, protrusions).

:func:`run` computes it in memory and returns a :class:`RunResult`; :func:`uvps.files.runfolder.write_run`
puts that in a run folder (docs/architecture.md, "Output folder of a run"). The CLI, the file bridge,
the benchmarks and the tests all go through these two functions.

Example
-------
>>> from uvps.testing.synthetic import make_capture
>>> from uvps.core.pipeline import RunOptions, run
>>> cap = make_capture(shape=(120, 160), n_lights=8, seed=1).as_capture(lights="positions")
>>> res = run(cap, RunOptions(), stages=("normals", "height"))
>>> res.stereo.normals.shape, res.height.height_um.dtype, res.lights.source
((120, 160, 3), dtype('float32'), 'positions')
"""
from __future__ import annotations

import dataclasses
import functools
import logging
import time
from dataclasses import dataclass, field
from typing import NamedTuple, Optional

import numpy as np

from .card import CardCalibration, apply_card
from ..errors import UVPSInputError
from .flatfield import GainCorrected, block_grid, divided_grid, fit_dropoffs, fit_log_grid, with_common
from .integrate import (Gradients, IntegrationResult, _frankot_chellappa, gradients_from_normals, integrate_normals,
                        nonintegrable_patches)
from .stack import Capture, release_caches
from .lights import (LightEstimate, LightModel, beyond_model, dropoff_common, estimate_lights, intensities_from_levels,
                     refine_intensities, sample_pixels)
from .level import Levelling, level_height
from .measure import measure_protrusions
from .offset import AdditiveTerm, OffsetImages, estimate_additive, known_additive
from .options import LAMP_BEAMS, SAMPLE_MODES, RunOptions  # noqa: F401 - declared apart, re-exported
from .progress import Progress, report, sub_progress
from .regions import RegionMap, propose_regions
from .stereo import EVERY_SAMPLE, StereoResult, solve_normals
from .threads import concurrently, default_threads, map_bands

log = logging.getLogger(__name__)

__all__ = ["RunOptions", "SAMPLE_MODES", "SCREENED_RESIDUAL_MAX", "sample_mode", "LightsResult", "Protrusions", "RunResult", "run", "remove_additive",
           "relief_of_lights", "RELATIVE_RELIEF_ABOVE",
           "estimate_capture_lights", "find_protrusions", "given_lights", "detection_height", "DetectionHeight"]

#: Names of the detector imported on first use (:func:`__getattr__`): :mod:`uvps.core.detect` (its numba
#: kernels, scikit-image's morphology) was 1.2 of the 2.6 s ``uvps.core.pipeline`` took to import
#: (``python -X importtime -m uvps run --help``), paid by every run, with or without detection.
_LAZY_DETECT = ("DetectionParams", "detect_protrusions")


def __getattr__(name):
    """``DetectionParams`` and ``detect_protrusions``, imported from :mod:`uvps.core.detect` when first asked
    for (then module attributes like any other: a test may replace them)."""
    if name in _LAZY_DETECT:
        from . import detect
        for n in _LAZY_DETECT:
            globals().setdefault(n, getattr(detect, n))
        return globals()[name]
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def _detector(name):
    """The module's ``name`` of :data:`_LAZY_DETECT` (imported now if it was not)."""
    return globals()[name] if name in globals() else __getattr__(name)


@dataclass
class LightsResult:
    """Lights of a capture and how they were obtained."""

    model: LightModel
    fits: list
    source: str                          # "estimated", "positions" or "directions"
    estimate: Optional[LightEstimate] = None
    images: Optional[object] = None      # the stack as the lights see it (known positions: beams divided out)
    beam_rms: Optional[float] = None     # known positions: rms of the drop-off beyond the model (log units)
    card: Optional[CardCalibration] = None   # the card whose gains the images are divided by


@dataclass
class Protrusions:
    """Colour areas and detected protrusions of a run (:func:`find_protrusions`)."""

    table: dict                          # uvps.core.measure columns, one row per protrusion
    labels: np.ndarray                   # (M, N) protrusion labels, id as in the table
    regions: Optional[RegionMap]         # the colour areas (None: the whole image)
    proposed: bool                       # the areas were proposed from the albedo (regions="auto")
    rejected: dict                       # candidates rejected, by rule
    noise_um: float


@dataclass
class RunResult:
    """Everything one run computed (:func:`run`), before anything is written."""

    capture: Capture                     # as the stages saw it (additive term removed on access)
    options: RunOptions
    stages: tuple
    additive: AdditiveTerm
    lights: LightsResult
    stereo: Optional[StereoResult] = None
    height: Optional[IntegrationResult] = None
    protrusions: Optional[Protrusions] = None
    diagnostics: dict = field(default_factory=dict)
    warnings: list = field(default_factory=list)
    timings_s: dict = field(default_factory=dict)
    relief: dict = field(default_factory=dict)   # run.json "relief" (:func:`relief_of_lights`)
    level: Optional[Levelling] = None            # what was removed from the height (run.json "level")


#: Stages :func:`run` knows, in order. "flatfield" computes nothing in memory: the flat-fielded
#: images are written by :func:`uvps.files.runfolder.write_run` (one image at a time).
STAGES = ("flatfield", "normals", "height", "protrusions")
#: A run whose lamps leave more than this fraction of the pixels with fewer than 3 usable samples
#: stops: no model fits the images.
NO_MODEL_FRACTION = 0.5
#: Relative standard uncertainty of heights from the estimated lamps beyond which the run says the
#: heights' scale is not determined by the images (stray light the additive term misses, a small
#: field); between :data:`RELATIVE_RELIEF_ABOVE` (expanded, 95 %) and this the heights are relative.
HEIGHT_UNCERTAINTY_UNDETERMINED = 1.0
#: Residuals (lamps x sample pixels) the light estimate's refinement works on at most (the sample is
#: also at most ``sample_pixels``, one pixel in 16, and at least 2000 pixels). 600000 (9375 pixels at
#: 64 lamps, 30000 at 12): worst direction error over seeds 3-5 at 8-64 lamps 0.58-1.17 deg, where
#: 150000 gave 1.45-3.0, both with the drop-off prior at full weight (``scripts/benchmark_lights.py --lamps
#: 8 12 16 32 64 --seeds 3 4 5`` with the constant edited); an evaluation costs lamps x pixels since the refinement's
#: normal equations are built without J.
MAX_RESIDUALS = 600000
#: Relative RMS photometric residual (of the sample's mean intensity) beyond which lamps estimated from
#: the images explain nothing and the run stops: a Lambertian capture under point lamps leaves ~0.5 %
#: (benchmark captures: 0.57 % clean, 1.6 % with every nuisance at the top of its range); a real
#: gilded icon under visible-light RTI (JPEG) leaves 33 % with lamps 52 deg off (docs/decisions/normals.md,
#: "Rules that stop or warn"): the Jacobian's confidence means nothing when the model does not fit.
MAX_LAMP_RESIDUAL = 0.05
#: Largest disagreement (deg) between an estimated lamp's azimuth and the one read from its drop-off
#: beyond which a run warns (:func:`_azimuth_warnings`). 12 lamps, seeds 0-2, with the azimuths from
#: integrability: beams 29.5-142, all nuisances 129 (seed 1), cupped paint 2.7-4.0, strokes 0.7-2.5,
#: a clean capture 1.4 (docs/decisions/normals.md, "Rules that stop or warn").
AZIMUTH_DISAGREEMENT_WARN_DEG = 5.0
#: When the fit does not hold (:func:`fit_warnings`): the normals' rms relative residual (the demo
#: 0.0055; the benchmark's rows with given lamps 0.006, beams 0.030, all nuisances 0.034; lamps
#: estimated above 0.05 stop the run, :data:`MAX_LAMP_RESIDUAL`), the share of pixels left without
#: normals, and the tilt of the mean normal (a ramp of the heights across the field: a canvas's bow
#: of 250 um over 24 mm tilts no more than 1 deg). Measured: docs/benchmarks.md, "When a fit does not
#: hold" (real runs) and docs/decisions/normals.md, "Fit-check thresholds" (the synthetic rows).
FIT_RESIDUAL_WARN = 0.05
INVALID_FRACTION_WARN = 0.03
MEAN_TILT_WARN_DEG = 5.0
#: :data:`MAX_RESIDUALS` for known positions, whose intensities alone are refined (their results
#: unchanged by the larger sample of estimated lamps).
KNOWN_POSITIONS_RESIDUALS = 150000


def run(capture: Capture, options: RunOptions = None, *, stages=("flatfield", "normals", "height"),
        dark_given: bool = False, regions=None, n_areas=None, detection: DetectionParams = None,
        card: Optional[CardCalibration] = None, progress: Progress = None) -> RunResult:
    """Run the pipeline on a capture, in memory.

    Parameters
    ----------
    capture : Capture
        From :func:`uvps.files.io.read_capture` (or :func:`uvps.testing.synthetic.make_capture`).
    options : RunOptions, optional
        The photometric-stereo options (default: all defaults).
    stages : tuple of str
        Which of :data:`STAGES` to run; the lights always are. "height" implies "normals";
        "protrusions" implies both.
    dark_given : bool
        A dark frame was subtracted on reading: no additive term is measured.
    regions : None, "auto" or RegionMap
        Colour areas for the protrusions: none (the whole image), proposed from the albedo, or given
        (from files: :func:`uvps.files.tables.load_regions`).
    n_areas : int, optional
        Number of areas for ``regions="auto"`` (default: chosen from the albedo).
    detection : DetectionParams, optional
        Options of :func:`uvps.core.detect.detect_protrusions`.
    card : CardCalibration, optional
        A card's per-lamp flat-field (:mod:`uvps.core.card`; from files:
        :func:`uvps.files.cards.load_card`).
    progress : callable(fraction, message), optional

    Returns
    -------
    RunResult

    Raises
    ------
    UVPSInputError
        The images are mostly pedestal, or no lamp model fits them (more than
        :data:`NO_MODEL_FRACTION` of the pixels lit by fewer than 3 lamps, or lamps estimated from
        the images leave more than :data:`MAX_LAMP_RESIDUAL` of the signal unexplained).
    """
    options = options or RunOptions()
    stages = _closed_stages(stages)
    res = RunResult(capture, options, stages, additive=None, lights=None)
    span = _progress_spans(stages)
    t0 = time.perf_counter()
    report(progress, 0.0, "additive term")
    capture, res.additive, warn = remove_additive(capture, options=options, dark_given=dark_given)
    res.timings_s["additive"] = _since(t0)
    res.diagnostics["additive"] = res.additive.to_json()
    if getattr(capture, "raw", None) is not None:
        res.diagnostics["raw"] = capture.raw
    res.warnings += warn
    _run_lights(res, capture, sub_progress(progress, *span["lights"]), card=card)
    if "normals" in stages:
        _run_normals(res, sub_progress(progress, *span["normals"]))
    if "height" in stages:
        t0 = time.perf_counter()
        report(progress, span["height"][0], "integrating the height")
        # the normals' gradients kept for the detection's height (computed again they took 0.33-0.40 s wall in
        # one thread at 4000 x 3000), which drops them once it is made. Not for gradients.tif: held to the
        # writing they raised the peak of a 10000 x 8000 run by their 0.6 GB (3.49 -> 4.06 GiB), the writer
        # computes them again (0.19-0.29 s in two threads)
        res.height = integrate_normals(res.stereo.normals, pixel_size_um=res.capture.pixel_size_um,
                                       method=options.integration, mask=res.capture.mask,
                                       keep_gradients="protrusions" in stages)
        res.timings_s["integrate"] = _since(t0)
    # no stage below reads the stack: what its views keep to be read faster is not held by the detection
    release_caches(res.capture.images)
    if "protrusions" in stages:
        t0 = time.perf_counter()
        res.protrusions = find_protrusions(res.stereo.albedo, res.height.height_um, res.stereo.normals,
                                           pixel_size_um=res.capture.pixel_size_um, regions=regions,
                                           n_areas=n_areas, params=detection, gradients=_handed_over(res.height),
                                           progress=sub_progress(progress, *span["protrusions"]))
        res.timings_s["protrusions"] = _since(t0)
        res.diagnostics["detect"] = protrusion_diagnostics(res.protrusions, res.capture.pixel_size_um)
    if res.height is not None:
        # after the detection, which reads the heights as integrated (each protrusion over its own local
        # plane; its rules were tuned on them, uvps detect rebuilds them from run.json's level): the best
        # plane (or form) removed in place, and recorded. A mean normal bias below what any lamp
        # calibration promises ramps the heights across the field (uvps.core.level).
        t0 = time.perf_counter()
        _, res.level = level_height(res.height.height_um, method=options.level,
                                    pixel_size_um=res.capture.pixel_size_um, mask=res.capture.mask,
                                    out=res.height.height_um)
        res.timings_s["level"] = _since(t0)
        res.diagnostics["integration"] = integration_diagnostics(res.height)
    report(progress, 1.0, "done")
    return res


#: Relative time of each step, for the progress bar's fractions (and so its estimate of the time
#: left): measured on 4000 x 3000 x 16 RGB with estimated lamps by ``scripts/benchmark_speed.py``.
_STEP_WEIGHTS = {"additive": 1.5, "lights": 12.0, "normals": 2.5, "height": 2.0, "protrusions": 18.0}


def _progress_spans(stages) -> dict:
    """(start, stop) fraction of each step that runs, in proportion to :data:`_STEP_WEIGHTS`."""
    steps = ["additive", "lights"] + [s for s in stages if s in _STEP_WEIGHTS]
    total = sum(_STEP_WEIGHTS[s] for s in steps)
    spans, at = {}, 0.0
    for s in steps:
        spans[s] = (at / total, (at + _STEP_WEIGHTS[s]) / total)
        at += _STEP_WEIGHTS[s]
    return spans


def _closed_stages(stages) -> tuple:
    stages = set(stages)
    unknown = stages - set(STAGES)
    if unknown:
        raise UVPSInputError(f"stages: unknown {', '.join(sorted(unknown))}; expected some of {', '.join(STAGES)}")
    if "protrusions" in stages:
        stages |= {"height"}
    if "height" in stages:
        stages |= {"normals"}
    return tuple(s for s in STAGES if s in stages)


def _since(t0) -> float:
    return round(time.perf_counter() - t0, 3)


def given_lights(capture: Capture) -> LightModel:
    """The capture's given lamps (positions, else directions), as a card needs them; none is an error."""
    if capture.light_positions_mm is not None:
        return LightModel.from_positions(capture.light_positions_mm, capture.light_intensities)
    if capture.light_directions is not None:
        return LightModel.from_directions(capture.light_directions, capture.light_intensities)
    raise UVPSInputError("card: the card needs the lamps' positions or directions (--lights); "
                         "with lamps estimated from the images it cannot say which part of each image is the beam")


def _run_lights(res: RunResult, capture: Capture, progress: Progress, *, card=None) -> None:
    """The lights stage: fits, lights, their diagnostics and the heights' confidence."""
    t0 = time.perf_counter()
    se = res.additive.stderr
    offset_se = float(np.mean(se)) if se is not None and np.all(np.isfinite(se)) else None
    res.lights = estimate_capture_lights(capture, options=res.options, offset_stderr=offset_se, card=card,
                                         flatfield="flatfield" in res.stages, progress=progress)
    res.timings_s["lights"] = _since(t0)
    _check_lamp_residual(res.lights)
    res.diagnostics["lights"] = lights_diagnostics(res.lights)
    azimuth_warning = _azimuth_warnings(res.lights, res.diagnostics["lights"])
    if res.lights.images is not None:   # known lamps: the images with the beams (or the card) divided out
        capture = dataclasses.replace(capture, images=res.lights.images)
    res.capture = capture
    res.relief = relief_of_lights(res.lights)
    res.warnings += _height_confidence_warnings(res.lights, azimuth_warning)


#: Lamps estimated from the images pin the relief's scale when the heights' expanded uncertainty
#: (:attr:`uvps.core.lights.LightUncertainty.height_rel_95`: noise, additive term and the lamp model's
#: misfit along the bas-relief direction, coverage factor 2) is at most this; beyond it the run's relief
#: is *relative* (docs/architecture.md, "Relief scale").
RELATIVE_RELIEF_ABOVE = 0.20


def relief_of_lights(lights: LightsResult) -> dict:
    """``run.json``'s ``relief``: whether the heights have a scale in micrometres, and why.

    Known lamps (positions, directions, a calibration) pin the lamps' elevation and so the relief's
    depth scale: "absolute". Lamps estimated from the images pin it only as far as the images do
    (the near-light remnant of the bas-relief ambiguity, :mod:`uvps.core.lights`): "absolute" when the
    heights' uncertainty that follows is at most :data:`RELATIVE_RELIEF_ABOVE`, else "relative"
    (normals, albedo, counts and widths hold; heights are a shape without a scale).
    """
    lamps = {"estimated": "estimated", "positions": "positions", "directions": "directions"}.get(
        lights.source, str(lights.source))
    if lights.source != "estimated":
        return {"scale": "absolute", "lamps": lamps,
                "reason": f"the lamps were given ({lamps}), which fixes their elevation and so the heights' "
                          "scale"}
    unc = lights.estimate.uncertainty if lights.estimate is not None else None
    if unc is None:
        return {"scale": "relative", "lamps": lamps,
                "reason": "the lamps were estimated from the images and their elevation's uncertainty could not be "
                          "measured, so the heights have no scale; calibrate the lamps (uvps calibrate, "
                          "--calibration) or give their positions (--lights)"}
    pct = 100 * unc.height_rel_95
    if unc.height_rel_95 <= RELATIVE_RELIEF_ABOVE:
        return {"scale": "absolute", "lamps": lamps,
                "reason": f"the lamps were estimated from the images, which pin their elevation: heights uncertain "
                          f"by +-{pct:.0f} % (95 %)"}
    return {"scale": "relative", "lamps": lamps,
            "reason": f"the lamps were estimated from the images, which do not pin their elevation (heights "
                      f"uncertain by +-{pct:.0f} %, 95 %): the relief's shape holds, its scale in micrometres does "
                      "not; calibrate the lamps (uvps calibrate, --calibration) or give their positions (--lights)"}


def _azimuth_warnings(lights: LightsResult, diagnostics: dict) -> list:
    """Warn when the estimated lamps' azimuths and those read from the drop-off disagree.

    Each lamp's azimuth is read twice from the images: from its drop-off map in polar coordinates
    (paper Fig. 1d: the side the light comes from is the bright one) and, after the refinement and
    the integrability correction, from the shading of the texture. A lamp's beam or aim tilts its
    drop-off and not its shading, so they part (:data:`AZIMUTH_DISAGREEMENT_WARN_DEG` has the figures;
    a canvas's large-scale shape parts them too, by a few degrees). Recorded in ``diagnostics``.
    """
    est = lights.estimate
    if est is None or est.azimuth_polar_deg is None:
        return []
    D = lights.model.directions
    az = np.degrees(np.arctan2(D[:, 1], D[:, 0]))
    worst = float(np.max(np.abs((az - np.asarray(est.azimuth_polar_deg) + 180.0) % 360.0 - 180.0)))
    diagnostics["azimuth_disagreement_deg_max"] = round(worst, 3)
    if worst <= AZIMUTH_DISAGREEMENT_WARN_DEG:
        return []
    return [f"the lamps' azimuths read from the images' drop-off and from their shading disagree by up to "
            f"{worst:.0f} deg (a lamp's beam or aim, which the lamp model does not hold): the estimated lamps and "
            "the heights' scale may be far off; give measured lamp positions (--lights)"]


def _check_lamp_residual(lights: LightsResult) -> None:
    """Stop when lamps estimated from the images leave most of them unexplained (:data:`MAX_LAMP_RESIDUAL`)."""
    est = lights.estimate
    if est is None or not est.residual_history:
        return
    rms = float(np.sqrt(est.residual_history[-1]["cost"]))
    if rms > MAX_LAMP_RESIDUAL:
        raise UVPSInputError(
            f"no lamp model fits these images: the lamps estimated from them leave {100 * rms:.0f} % of the signal "
            "unexplained (a Lambertian capture under point lamps leaves about 1 %: glossy or gilded paint, a tone "
            "curve, or lights that are not point lamps?); give the lights (--lights: measured positions, or an RTI "
            ".lp file's directions)")


def _height_confidence_warnings(lights: LightsResult, azimuth_warning=()) -> list:
    """The run's one warning on its estimated lamps: heights whose scale is not determined say so (and
    name a dark frame for stray light); else the azimuths' disagreement (:func:`_azimuth_warnings`)
    names its cause, a lamp's beam; else a relative relief (:func:`relief_of_lights`) says that the
    heights carry no micrometres, naming the cause that dominates and what to do."""
    unc = lights.estimate.uncertainty if lights.estimate is not None else None
    undetermined = unc is not None and unc.height_rel > HEIGHT_UNCERTAINTY_UNDETERMINED
    if azimuth_warning and not undetermined:
        return list(azimuth_warning)
    if unc is None or unc.height_rel_95 <= RELATIVE_RELIEF_ABOVE:
        return []
    if undetermined:
        # the lamps are not determined by these images: the relief's shape may still serve (protrusions
        # show), its scale does not; said once, with what to do
        return [f"the heights' scale is not determined by these images (uncertain by +-{100 * unc.height_rel:.0f} %: "
                "a small field, or stray light or lamp beams the model does not hold): heights are relative; give "
                "measured lamp positions (--lights) or a calibration, and a dark frame (--dark) if there is stray light"]
    parts = {"offset": unc.height_rel_offset, "noise": unc.height_rel_noise, "misfit": unc.height_rel_misfit}
    cause = {"offset": "the black level could not be measured precisely enough; give the camera's black level or a "
                       "dark frame",
             "noise": "the field is too small (or the lamps too far) for the lamps' distance and elevation to be told "
                      "apart; give measured lamp positions (--lights) or a calibration",
             "misfit": "the canvas's shape or the lamps' beams move the estimated lamps' elevation; give measured "
                       "lamp positions (--lights) or a calibration"}[max(parts, key=parts.get)]
    return [f"heights are relative, not micrometres (uncertain by +-{100 * unc.height_rel_95:.0f} % at 95 %: the "
            f"images do not pin the estimated lamps' elevation): {cause}"]


def _run_normals(res: RunResult, progress: Progress) -> None:
    """Normals and albedo; stops the run when the lamps fit no pixel."""
    t0 = time.perf_counter()
    cap = res.capture
    rules = {"screened": {"saturation": cap.saturation}, "all": dict(EVERY_SAMPLE)}
    first = "all" if res.options.samples == "all" else "screened"
    st = solve_normals(cap.images, res.lights.model, pixel_size_um=cap.pixel_size_um, mask=cap.mask,
                       robust=res.options.robust, progress=progress, **rules[first])
    mode, reason = sample_mode(res.options.samples, st.residual_rms if res.options.samples == "auto" else None)
    if mode != first:   # the model does not hold: every sample (a second solve, only then)
        st = solve_normals(cap.images, res.lights.model, pixel_size_um=cap.pixel_size_um, mask=cap.mask,
                           robust=res.options.robust, progress=progress, **rules[mode])
    res.timings_s["normals"] = _since(t0)
    res.diagnostics["normals"] = {"n_invalid": st.n_invalid, "residual_rms": st.residual_rms,
                                  "samples": mode, "samples_reason": reason}
    n_px = int(cap.mask.sum()) if cap.mask is not None else int(np.prod(cap.images.shape[1:3]))
    if st.n_invalid > NO_MODEL_FRACTION * n_px:
        # the lamps explain the images nowhere: no heights rather than wrong ones
        raise UVPSInputError(
            f"no lamp model fits these images: {100 * st.n_invalid / n_px:.0f} % of the pixels are lit by fewer "
            f"than 3 lamps as {res.lights.source} (lamps with narrow beams or stray light the lamp model does not "
            "hold?); give measured lamp positions (--lights) or a dark frame (--dark)")
    if res.lights.card is not None:
        st = _level_card(res, st, progress)
    res.stereo = st
    fit = fit_checks(st, n_px, lights_source=res.lights.source, pixel_size_um=cap.pixel_size_um,
                     robust=res.options.robust)
    res.diagnostics["normals"].update(fit.pop("diagnostics"))
    res.warnings += fit["warnings"]


#: ``samples="auto"``: the screened solve's rms relative residual above which the lamps and a matte surface do not
#: hold and every sample is used instead (:func:`sample_mode`). Real photographs (``scripts/benchmark_real.py``):
#: DiLiGenT's ball 0.089 (16-bit) and 0.105 (encoded as 8-bit sRGB JPEGs), where the rules bring the error against
#: its measured normals from 4.11 to 3.27 deg (JPEG: 4.13 to 3.45) and its halves closer; the RTI captures
#: lion relief 0.66 and painted icon 0.80, where every rule makes the halves of their lamps agree less (icon 2.44 ->
#: 3.62 deg, lion 1.14 -> 2.10). Synthetic captures 0.006-0.034.
SCREENED_RESIDUAL_MAX = 0.25


def sample_mode(samples: str, screened_residual: Optional[float] = None) -> tuple:
    """Which samples the normals use, and why: ``("screened" | "all", reason)``.

    "screened": saturated samples (any channel), samples darker than 2 % of the pixel's brightest and those
    the first solve puts in attached shadow are left out (:func:`uvps.core.stereo.solve_normals`'s rules).
    "all": plain least squares over every sample (:data:`uvps.core.stereo.EVERY_SAMPLE`). "auto": screened,
    unless the screened solve leaves more than :data:`SCREENED_RESIDUAL_MAX` of the signal unexplained
    (``screened_residual``): the rules leave samples out as outliers of the lamp-and-matte model, and where
    the model explains little, that choice follows its misfit and only adds noise (docs/benchmarks.md,
    "Normals on real photographs"; each rule alone: docs/decisions/normals.md, "``--samples auto``:
    every sample where the model explains little").
    """
    if samples in ("screened", "all"):
        return samples, f"samples={samples} was given"
    if screened_residual is not None and screened_residual > SCREENED_RESIDUAL_MAX:
        return "all", (f"the fit leaving out saturated and shadowed samples left {100 * screened_residual:.0f} % of "
                       f"the signal unexplained (over {100 * SCREENED_RESIDUAL_MAX:.0f} %: the lamps and a matte "
                       "surface do not hold), so every sample is kept, as plain least squares: on real captures "
                       "like this the left-out samples made two halves of the lamps agree less")
    shown = "" if screened_residual is None else f" (the fit leaves {100 * screened_residual:.0f} % unexplained)"
    return "screened", (f"saturated, dark and attached-shadow samples left out{shown}: on a real object with "
                        "measured normals (DiLiGenT's ball) this is 3.3 deg off against 4.1 with every sample")


def fit_checks(st, n_px: int, *, lights_source: str, pixel_size_um: float, robust: bool = False) -> dict:
    """Whether the fit holds: one warning per cause that names it and the next step.

    - the residual: the rms relative residual above :data:`FIT_RESIDUAL_WARN` (the images are not
      explained by the lamps and a matte surface: lamp directions from another set-up or frame,
      gloss, gamma-encoded images);
    - invalid pixels: more than :data:`INVALID_FRACTION_WARN` of the pixels with fewer than 3 usable
      lamps (shadowed, dark or saturated);
    - a ramp: the mean normal tilted by more than :data:`MEAN_TILT_WARN_DEG` (the heights climb across
      the field: the lamps' directions are off by about that much, or the camera looks obliquely).

    Returns ``{"warnings": [...], "diagnostics": {...}}`` (the diagnostics go into ``run.json``).
    """
    warnings = []
    given = lights_source != "estimated"
    fix = ("check that the light file belongs to these images and uses uvps's frame (x right, y up, z toward "
           "the camera; vectors from the surface to the lamp), or leave --lights out to estimate the lamps"
           if given else "give measured lamp positions (--lights)")
    causes = []
    if st.residual_rms > FIT_RESIDUAL_WARN:
        causes.append(f"the lamps and a matte surface leave {100 * st.residual_rms:.0f} % of the signal unexplained "
                      "(a good capture leaves about 1 %)")
    p, q, n_ok = mean_slopes(st.normals)
    tilt = float("nan")
    if n_ok:
        tilt = float(np.degrees(np.arctan(np.hypot(p, q))))
        width_mm = max(st.normals.shape[:2]) * pixel_size_um / 1000.0
        if tilt > MEAN_TILT_WARN_DEG:
            causes.append(f"the heights ramp by about {width_mm * np.hypot(p, q):.3g} mm across the field (mean "
                          f"normal tilted {tilt:.0f} deg: lamp directions off by about that much, or an oblique "
                          "camera)")
    if causes:
        gloss = ("" if robust or st.residual_rms <= FIT_RESIDUAL_WARN else
                 "; for gloss or cast shadows, --robust leaves out each pixel's brightest and darkest samples")
        warnings.append(f"the fit does not hold: {'; '.join(causes)}; normals and heights are not reliable: "
                        f"{fix}{gloss}")
    frac = st.n_invalid / max(n_px, 1)
    if frac > INVALID_FRACTION_WARN:
        warnings.append(f"{100 * frac:.0f} % of the pixels have no normal (fewer than 3 lamps light them unshadowed "
                        "and unsaturated): check the exposure (saturated or very dark images) and that the lamps "
                        "light the whole field from several sides")
    return {"warnings": warnings, "diagnostics": {"invalid_fraction": round(frac, 5),
                                                  "mean_tilt_deg": round(tilt, 2) if np.isfinite(tilt) else None}}


#: Rows per band of :func:`mean_slopes`.
SLOPE_BAND_ROWS = 256


def mean_slopes(normals) -> tuple:
    """``(p, q, n)``: the mean slopes ``-n_x / n_z`` and ``-n_y / n_z`` of the ``n`` pixels whose normal has
    ``n_z > 0.05`` (NaN, NaN, 0 with none), in bands of rows over two threads (the bands fixed, their sums added
    in order: the same whatever the threads; against one ``np.mean`` of the whole image, the float32 sums are
    taken in another order, ~1e-7 relative). The whole image's boolean gathers from the normals' strided planes
    took 0.27-0.34 s of CPU in one thread at 4000 x 3000 (``scripts/benchmark_speed.py --profile``); in bands,
    0.05 s in one thread."""
    def band(rows):
        n = normals[rows]
        nz = n[..., 2]
        ok = np.isfinite(nz) & (nz > 0.05)
        z = nz[ok]
        return float(np.sum(-n[..., 0][ok] / z)), float(np.sum(-n[..., 1][ok] / z)), int(z.size)

    parts = map_bands(band, normals.shape[0], size=SLOPE_BAND_ROWS, threads=default_threads(2))
    n_ok = sum(b[2] for b in parts)
    if not n_ok:
        return float("nan"), float("nan"), 0
    return sum(b[0] for b in parts) / n_ok, sum(b[1] for b in parts) / n_ok, n_ok


def _level_card(res: RunResult, st: StereoResult, progress: Progress) -> StereoResult:
    """Divide out the card's tilt against the painting, and solve the normals again.

    Divided by a card, the normals are the painting's relative to the card: a card tilted by ``t``
    tilts them all by ``-t`` (:mod:`uvps.core.card`). The mean surface plane is z = 0
    (architecture.md), so the mean normal gives the card's tilt; the gains are made those of the
    tilted card (:meth:`uvps.core.card.CardCalibration.tilted`) and the normals solved once more (the
    tilt left after that is second order: reported).
    """
    cap, lights = res.capture, res.lights

    def mean_slope(normals):
        n = normals.reshape(-1, 3)
        n = n[np.all(np.isfinite(n), axis=1)]
        m = n.mean(axis=0)
        return m[:2] / m[2]

    slope = mean_slope(st.normals)
    card = lights.card.tilted(slope, lights.model, pixel_size_um=cap.pixel_size_um)
    images = apply_card(lights.images.base, card)
    st = solve_normals(images, lights.model, pixel_size_um=cap.pixel_size_um, mask=cap.mask,
                       saturation=cap.saturation, robust=res.options.robust, progress=progress)
    left = mean_slope(st.normals)
    res.capture = dataclasses.replace(cap, images=images)
    res.lights.card, res.lights.images = card, images
    d = card.to_json()
    d["tilt_to_painting_deg"] = round(float(np.degrees(np.arctan(np.hypot(*slope)))), 4)
    d["tilt_to_painting_azimuth_deg"] = round(float(np.degrees(np.arctan2(slope[1], slope[0])) % 360.0), 2)
    d["tilt_left_deg"] = round(float(np.degrees(np.arctan(np.hypot(*left)))), 4)
    res.diagnostics["card"] = d
    return st


def lights_diagnostics(lights: LightsResult) -> dict:
    """What ``run.json`` says about the lights: source, count, the estimate's cost and confidence."""
    d = {"source": lights.source, "n_lights": int(len(lights.model.intensities)), "card": lights.card is not None}
    if lights.beam_rms is not None:
        d["dropoff_beyond_model_rms"] = round(lights.beam_rms, 6)
    if lights.estimate is not None:
        d["m_mm"] = lights.estimate.m_mm
        d["final_cost"] = lights.estimate.residual_history[-1]["cost"] if lights.estimate.residual_history else None
        per_light = [h for h in lights.estimate.residual_history if h["stage"] == "per-light"]
        if per_light:
            d["refinement_converged"] = bool(per_light[-1]["converged"])
        if lights.estimate.uncertainty is not None:
            u = lights.estimate.uncertainty
            d["height_uncertainty_relative"] = round(float(u.height_rel), 5)
            d["height_uncertainty_relative_95"] = round(float(u.height_rel_95), 5)
            d["height_uncertainty_from_misfit"] = round(float(u.height_rel_misfit), 5)
            d["direction_uncertainty_deg_max"] = round(float(np.max(u.direction_deg)), 4)
    return d


def integration_diagnostics(res: IntegrationResult) -> dict:
    """What ``run.json`` says about the integration."""
    return {"method": res.method, "residual_rms": res.residual_rms, "integrability": res.integrability,
            "height_range_um": [float(np.nanmin(res.height_um)), float(np.nanmax(res.height_um))]}


def protrusion_diagnostics(prot: Protrusions, pixel_size_um: float) -> dict:
    """What ``run.json`` and ``detect`` report of a detection: counts by cue, rejections by rule."""
    src, n = np.unique(np.asarray(prot.table["source"], dtype=str), return_counts=True)
    return {"n_protrusions": int(len(prot.table["id"])), "by_source": {str(s): int(c) for s, c in zip(src, n)},
            "n_craters": int(np.sum(prot.table["crater"])), "rejected": dict(prot.rejected),
            "noise_um": float(prot.noise_um) if np.isfinite(prot.noise_um) else None,
            "n_areas": len(prot.regions.ids) if prot.regions is not None else None,
            "pixel_size_um": pixel_size_um}


class DetectionHeight(NamedTuple):
    """What :func:`detection_height` returns."""
    height_um: np.ndarray               # the height the detection reads
    left_out: Optional[np.ndarray]      # bool, the pixels whose gradients it was integrated without


def detection_height(height_um, normals, *, pixel_size_um: float, params: DetectionParams,
                     gradients: Optional[Gradients] = None) -> DetectionHeight:
    """The height a run's detection reads: the normals integrated again (Frankot-Chellappa) without the
    gradients of long non-integrable patches (:func:`uvps.core.integrate.nonintegrable_patches`, the
    walls of cracks) where ``params.curl_k`` is set and there are any, else ``height_um`` itself (also
    without normals).
    The protrusions are measured on ``height_um``; the detection's ``artefact`` rule compares the
    height's slope with the normals' away from the patches (``detect_protrusions(left_out=)``).

    On the detection benchmark's end-to-end captures (``scripts/benchmark_detection.py --pipeline``)
    the crack walls' normals are 5 deg off at the median and their relief spreads along the strokes
    (stroke bumps 7.8 um high at the median against 1.4 um in the true height), which set the
    ``stroke`` rule's bar above 9 of the 13 protrusions it missed on seed 1.

    ``gradients``: :func:`uvps.core.integrate.gradients_from_normals` of ``normals`` (default ``max_slope``)
    already computed (the run's height stage keeps them, :func:`run`), used, and left unchanged, when
    their mask (``Gradients.mask``) is the one this function computes with (None where every height is
    finite, else the finite heights'), else computed again.

    Returns
    -------
    DetectionHeight
        ``height_um``: the height to detect on; ``left_out``: the patches left out (bool), None
        when nothing was.
    """
    if normals is None or not params.curl_k > 0:
        return DetectionHeight(height_um, None)
    valid = np.isfinite(height_um)
    mask = None if valid.all() else valid
    reused = gradients is not None and _same_mask(gradients.mask, mask)
    g = gradients if reused else gradients_from_normals(normals, mask=mask)
    left_out = nonintegrable_patches(g.p, g.q, min_extent_px=params.max_width_um / pixel_size_um, k=params.curl_k,
                                     mask=mask)
    log.info("detection: %.1f %% of the gradients (long non-integrable patches) left out of its height",
             100.0 * left_out.mean())
    if not left_out.any():      # nothing to leave out: the run's own height (its integration, its scale)
        return DetectionHeight(height_um, None)
    # zeroed where left out, in copies when the gradients are the caller's; solved in place (frankot_chellappa
    # would copy them again: 96 MB more at 4000 x 3000)
    p, q = (g.p.copy(), g.q.copy()) if reused else (g.p, g.q)
    p[left_out] = 0.0
    q[left_out] = 0.0
    height = _frankot_chellappa(p, q, pixel_size_um=pixel_size_um, pad="reflect", mask=mask, copy=False).height_um
    return DetectionHeight(height, left_out)


def _handed_over(height: IntegrationResult):
    """``height.gradients``, cleared there: the callee it is passed to holds the only reference, and drops
    it when done (:func:`find_protrusions`, once its height is made)."""
    g, height.gradients = height.gradients, None
    return g


def _same_mask(a, b) -> bool:
    """Both None, or both arrays equal element by element (the same pixels masked)."""
    if a is None or b is None:
        return a is None and b is None
    return a.shape == b.shape and bool(np.array_equal(a, b))


def find_protrusions(albedo, height_um, normals=None, *, pixel_size_um: float, regions=None, n_areas=None,
                     seed: int = 0, params: DetectionParams = None, gradients: Optional[Gradients] = None,
                     progress: Progress = None) -> Protrusions:
    """Colour areas and the automated protrusions of a run (paper section 3: albedo colour + height).

    ``regions``: None (the whole image), "auto" (proposed from the albedo colour,
    :func:`uvps.core.regions.propose_regions`), or a :class:`~uvps.core.regions.RegionMap` (from files:
    :func:`uvps.files.tables.load_regions`). With areas,
    detection is restricted to them (the paper masks each area) and each protrusion gets its area.
    ``gradients``: the normals' own, for :func:`detection_height` (reused where their mask is its).
    """
    proposed = isinstance(regions, str) and regions == "auto"
    if not proposed and regions is not None and not isinstance(regions, RegionMap):
        raise UVPSInputError(f"regions must be None, 'auto' or a RegionMap (files: uvps.files.tables.load_regions); "
                             f"got {type(regions).__name__}")
    params = params or _detector("DetectionParams")()
    height = functools.partial(detection_height, height_um, normals, pixel_size_um=pixel_size_um, params=params,
                               gradients=gradients)
    if proposed:    # the areas from the albedo, the detection's height from the normals: side by side
        dh, regions = concurrently(height, functools.partial(propose_regions, albedo, pixel_size_um=pixel_size_um,
                                                             n_areas=n_areas, seed=seed))
    else:
        dh = height()
    # the kept gradients (96 MB at 4000 x 3000) dropped before the detector, whose temporaries make a run's peak
    height = gradients = None
    mask = regions.labels > 0 if regions is not None else None
    det = _detector("detect_protrusions")(albedo, dh.height_um, pixel_size_um=pixel_size_um, normals=normals, mask=mask,
                             params=params, left_out=dh.left_out,
                             progress=sub_progress(progress, 0.0, 0.85))
    report(progress, 0.9, "measuring")
    source = {i + 1: str(s) for i, s in enumerate(det.source)}
    table = measure_protrusions(det.labels, albedo=albedo, height_um=height_um, pixel_size_um=pixel_size_um,
                                regions=regions, source=source)
    return Protrusions(table, det.labels, regions, proposed, dict(det.rejected), float(det.noise_um))


#: Input bit depths on which the additive term is not measured by default (``offset="auto"``).
EIGHT_BIT = ("uint8", "int8")
#: The measured additive term must be pinned to this fraction of the median signal: an error of 0.2 %
#: moved the estimated lamps by 5 degrees on the benchmark captures (``scripts/benchmark_robustness.py``).
OFFSET_TOLERANCE = 0.001
#: A measured additive term smaller than this many standard errors is not subtracted.
SIGNIFICANT = 2.0
#: An additive term above this fraction of the median signal: the images are mostly pedestal.
OFFSET_MAX = 0.5


def _median_signal(images, mask) -> float:
    """The median count of up to four of the images, every 8th pixel, inside ``mask`` (a masked
    object's background is no signal)."""
    k = np.linspace(0, images.shape[0] - 1, min(4, images.shape[0])).astype(int)
    sub = np.asarray(images[k, ::8, ::8], dtype=np.float32)
    if mask is not None:
        sub = sub[:, mask[::8, ::8]]
    return float(np.median(sub))


def remove_additive(capture: Capture, *, options: RunOptions, dark_given=False) -> tuple:
    """The capture with its additive term (black level, stray light) removed, and that term.

    A given term beats a measured one. Given black level (``options.black_level``): that. A dark frame
    (already subtracted on reading), or camera raw files (their metadata's black level subtracted on
    reading, :func:`uvps.files.io.read_raw`): nothing more is removed. ``options.offset == "none"``: nothing;
    ``"auto"`` on 8-bit input (:data:`EIGHT_BIT`: a linearised JPEG's tone curve is no pedestal):
    nothing. Otherwise the term is measured from the images (:func:`uvps.core.offset.estimate_additive`)
    and subtracted only when it lies more than :data:`SIGNIFICANT` standard errors above 0. The images are not copied: the result's
    ``images`` is a view that subtracts on access (:class:`uvps.core.offset.OffsetImages`).

    Returns
    -------
    (Capture, AdditiveTerm, list of str)
        The capture to use, the term, and warnings (only when the term is poorly pinned).
    """
    term = _additive_term(capture, options, dark_given)
    subtract, warnings = _judge_additive(capture, term)
    if not subtract or term.is_zero:
        return capture, term, warnings
    return dataclasses.replace(capture, images=OffsetImages(capture.images, term)), term, warnings


def _additive_term(capture: Capture, options: RunOptions, dark_given) -> AdditiveTerm:
    """The additive term, given or measured (see :func:`remove_additive` for which wins), its
    median signal filled in; refuses images that are mostly pedestal (more than
    :data:`OFFSET_MAX` of the median signal), which no subtraction can rescue."""
    images = capture.images
    M, N = images.shape[1:3]
    C = images.shape[3] if images.ndim == 4 else 1
    if options.black_level is not None:
        term = known_additive(options.black_level, shape=(M, N), channels=C)
    elif dark_given or options.offset == "none":
        term = known_additive(0.0, shape=(M, N), channels=C, source="dark frame" if dark_given else "none")
    elif getattr(capture, "raw", None) is not None:
        # camera raw files: LibRaw subtracted the black level of their metadata on reading
        term = known_additive(0.0, shape=(M, N), channels=C, source="raw metadata")
        term.diagnostics["raw_black_level"] = [lv["black_level"] for lv in capture.raw["levels"]]
        term.diagnostics["raw_white_level"] = [lv["white_level"] for lv in capture.raw["levels"]]
    elif options.offset == "auto" and capture.bit_depth in EIGHT_BIT:
        # 8-bit files (linearised JPEGs above all) carry a tone curve's remnant, not a pedestal: on a
        # real RTI capture of a canvas a term measured as 5 % of the signal and subtracted set the two
        # halves of the lamps' normals 3.16 deg apart, 2.40 with none (a capture outside ../shared/data)
        term = known_additive(0.0, shape=(M, N), channels=C, source="none")
        term.diagnostics["note"] = (f"{capture.bit_depth} input: not measured (offset=measure to measure it, or give "
                                    "black_level or a dark frame)")
    else:
        term = estimate_additive(images, mask=capture.mask, saturation=capture.saturation,
                                 degree=int(options.offset_degree), dropoff_degree=int(options.degree))
    if not np.isfinite(term.median_signal):
        term.median_signal = _median_signal(images, capture.mask) - float(term.mean.mean())
    frac = float(term.mean.mean()) / max(term.median_signal, 1e-12)
    if not term.is_zero and (term.median_signal <= 0 or frac > OFFSET_MAX):
        raise UVPSInputError(
            f"the images are mostly pedestal: the additive term ({term.source}, {term.mean.mean():.1f} counts) is "
            f"{100 * frac:.0f} % of the median signal; check the exposure, the black level or the dark frame")
    return term


def _judge_additive(capture: Capture, term) -> tuple:
    """Whether to subtract a measured term, and the warnings: not when it could not be measured
    (non-finite error), is negative (a pedestal or stray light never is: the model's error, e.g.
    a JPEG's tone curve) or is within :data:`SIGNIFICANT` standard errors of 0 (subtracting it
    would only add its noise); a warning when it is pinned worse than :data:`OFFSET_TOLERANCE`
    of the signal. Records the decision in ``term.diagnostics``. A given term is always used."""
    warnings = []
    if term.stderr is not None and not np.isfinite(term.stderr).all():
        term.diagnostics["used"] = False
        if capture.light_positions_mm is None and capture.light_directions is None:   # lamps to estimate
            warnings.append(f"the black level could not be measured ({term.diagnostics.get('note', '')}); "
                            "estimated lamp elevations and heights may be off; give the camera's black level "
                            "or a dark frame")
        return False, warnings
    if term.stderr is not None and float(term.mean.mean()) <= 0:
        term.diagnostics["used"] = False
        term.diagnostics["note"] = "negative: not subtracted"
        return False, warnings
    if term.stderr is not None:
        term.diagnostics["measured_counts"] = [round(float(v), 3) for v in term.mean]
        term.coeffs[:, 0, 0] = np.maximum(term.coeffs[:, 0, 0], 0.0)   # per channel, likewise
        se = float(np.sqrt(np.mean(term.stderr ** 2)))
        if abs(float(term.mean.mean())) < SIGNIFICANT * se:
            # consistent with no offset: a clean capture is then processed exactly as if no
            # additive term were modelled
            term.diagnostics["used"] = False
            term.diagnostics["note"] = f"not significant (|c| < {SIGNIFICANT:g} standard errors): not subtracted"
            return False, warnings
        if se > OFFSET_TOLERANCE * term.median_signal:
            lamps_given = capture.light_positions_mm is not None or capture.light_directions is not None
            effect = ("normals of dark paint may be tilted" if lamps_given else
                      "estimated lamp elevations and heights may be off")
            warnings.append(
                f"the black level could only be measured to +-{se:.2g} counts ({100 * se / term.median_signal:.2f} % "
                f"of the signal; the field may hold too little dark and bright paint): {effect}; give the camera's "
                "black level or a dark frame")
    return True, warnings


def _lamp_beams(options) -> str:
    """``options.lamp_beams`` as one of :data:`LAMP_BEAMS` (run folders written before it was a choice
    hold true / false)."""
    v = options.lamp_beams
    if isinstance(v, bool):
        return "all" if v else "none"
    return v


def estimate_capture_lights(capture: Capture, *, options: RunOptions, offset_stderr=None,
                            card: Optional[CardCalibration] = None, flatfield: bool = True,
                            progress: Progress = None) -> LightsResult:
    """Drop-off fits for every image, and the lights: given (positions or directions) or estimated.

    Known positions (a calibrated near-light file) are used as they are, with each lamp's relative
    intensity from the file when it gives them, otherwise measured from the images by the photometric
    residual with the positions held (:func:`uvps.core.lights.refine_intensities`). Known
    directions (an RTI ``.lp`` file) give far lights with the file's intensities, or equal ones when it
    gives none: an ``.lp`` file says nothing about intensities, and levels read as if the surface were
    flat and facing the camera are wrong on a relief. ``options.estimate_intensities`` measures them
    from the images for either kind (far lights: from the levels), even over the file's. Otherwise
    the near-light positions are estimated from the images (:func:`uvps.core.lights.estimate_lights`);
    ``offset_stderr`` (grey counts, from :func:`remove_additive`) goes into their uncertainty.

    ``flatfield``: the fits are those of the images as the stages see them (the flat-fielded images,
    :func:`uvps.files.runfolder.write_flatfield`, divide those by them). False, with known positions whose
    beams are divided out: one pass over the stack instead of two; with the intensities given, the fits of
    the images as captured, made once for the beams, are kept (the lights, normals and all else the same);
    with the intensities measured, the fits of the first pass's blocks divided by the beams' gains
    (:func:`uvps.core.flatfield.divided_grid`: the same intensities, drop-offs within ~1e-5).

    With a ``card`` (:mod:`uvps.core.card`, known lamps only) every image is first divided by the card's
    gain for its lamp: the lamps are then equal (``E_k = 1``) and beamless, and ``lamp_beams`` has
    nothing left to do.
    """
    px = capture.pixel_size_um
    if card is not None:
        given_lights(capture)                       # the card needs them
        capture = dataclasses.replace(capture, images=apply_card(capture.images, card),
                                      light_intensities=np.ones(capture.images.shape[0]))
        options = dataclasses.replace(options, lamp_beams="none")
    report(progress, 0.0, "drop-off fits")
    grid = block_grid(capture.images, mask=capture.mask, saturation=capture.saturation)
    fits = fit_dropoffs(grid, degree=int(options.degree))
    shape = grid.shape

    # At most one pixel in 16 (a denser sample adds neighbours whose texture is correlated, and time),
    # and at most MAX_RESIDUALS residuals (lamps x pixels: an evaluation's cost)
    n = min(int(options.sample_pixels), max(5000, shape[0] * shape[1] // 16))
    n_known = min(n, max(2000, KNOWN_POSITIONS_RESIDUALS // len(fits)), 20000)
    n = min(n, max(2000, MAX_RESIDUALS // len(fits)))
    if capture.light_positions_mm is not None:
        return _lights_at_given_positions(capture, options, grid, fits, n_known=n_known,
                                          flatfield=flatfield, card=card)
    if capture.light_directions is not None:
        # far lights: no drop-off model; the fits stay relative to the stack's geometric mean.
        # Intensities: given, else equal (None); from the levels only when asked.
        D = capture.light_directions
        E = capture.light_intensities
        if options.estimate_intensities:
            E = intensities_from_levels([f.level for f in fits], None, shape, px, directions=D)
        return LightsResult(LightModel.from_directions(D, None if E is None else E / np.median(E)), fits,
                            "directions", images=capture.images if card is not None else None, card=card)
    sample = sample_pixels(capture.images, fits, mask=capture.mask, saturation=capture.saturation,
                           pixel_size_um=px, n=n)
    sub = None if progress is None else (lambda f, m: progress(0.05 + 0.95 * f, m))
    est = estimate_lights(grid, fits, sample, pixel_size_um=px, refine=options.refine_lights,
                          offset_stderr=offset_stderr, normals_of=_central_normals(capture), progress=sub)
    return LightsResult(est.model, est.fits, "estimated", est)


def _lights_at_given_positions(capture: Capture, options: RunOptions, grid, fits, *, n_known,
                               flatfield, card) -> LightsResult:
    """The lights of a capture whose lamp positions are given: what each image's drop-off holds
    beyond the point-light model (a lamp's beam, its aim) measured from the ratio maps, reported,
    and divided out (a narrow lamp aimed 5 deg off tilted every normal by 1-9 deg), and the
    intensities given or measured by the photometric residual with the positions held. The
    shading of the canvas's own large-scale shape (bow) is in the drop-off too; by default the
    part a tilt of the canvas explains is left to the relief (:func:`uvps.core.lights.beyond_model`)."""
    px = capture.pixel_size_um
    shape = grid.shape
    P = capture.light_positions_mm
    beams = _lamp_beams(options)
    rows, cols, delta = beyond_model(fits, P, shape, px, keep_relief=beams != "all")
    beam_rms = float(np.sqrt(np.mean(delta ** 2)))
    E = capture.light_intensities   # given (median 1 like an estimate), else from the images
    measure_E = E is None or options.estimate_intensities
    if beams != "none":
        gains = fit_log_grid(delta, rows, cols, shape, int(options.degree))
        capture = dataclasses.replace(capture, images=GainCorrected(capture.images, gains))
        # the intensities are measured on the images with the beams divided out, and the flat-fielded
        # images are those images over their drop-off: their own fits. The flat-fielded images take a
        # second pass over the stack (their drop-off exactly theirs); the intensities alone take the
        # first pass's blocks divided by the gains (divided_grid: the same intensities to 2e-12). With
        # the intensities given (a rig, a calibration that holds them) and no flat-fielded images asked
        # for, nothing else uses these fits: dropoff.tif and lights.json then hold the drop-off of the
        # images as captured (the fits above, the beams included).
        if flatfield or measure_E:
            grid = (block_grid(capture.images, mask=capture.mask, saturation=capture.saturation) if flatfield
                    else divided_grid(grid, gains))
            fits = fit_dropoffs(grid, degree=int(options.degree))
    fits = with_common(fits, grid, dropoff_common(P, shape, px))
    if measure_E:
        # by the photometric residual with the positions held: the levels alone assume a flat
        # canvas facing the camera (1.2 deg normals on a cupped capture, 0.13 deg this way)
        E = intensities_from_levels([f.level for f in fits], P, shape, px)
        sample = sample_pixels(capture.images, fits, mask=capture.mask, saturation=capture.saturation,
                               pixel_size_um=px, n=n_known)
        E = refine_intensities(sample, P, E)
    return LightsResult(LightModel.from_positions(P, E / np.median(E)), fits, "positions",
                        images=capture.images if beams != "none" or card is not None else None,
                        beam_rms=beam_rms, card=card)


#: The central patch whose normals the estimated lamps are made integrable on
#: (:func:`uvps.core.lights.integrability_correction`): at most 1024 pixels a side and this many samples
#: (lamps x pixels; 64 lamps: 433 pixels, 6.5 mm at 15 um), the whole image when smaller. The patch
#: only needs texture: its curl, not the field's geometry, carries the correction.
INTEGRABILITY_SAMPLES = 12_000_000


def _central_normals(capture: Capture):
    """``normals_of(model)`` for :func:`uvps.core.lights.estimate_lights`: the normals of a central patch
    (:data:`INTEGRABILITY_SAMPLES`) solved under ``model``. The patch has the image's centre (equal
    margins), so the lamps' positions hold for it as they are."""
    K, M, N = capture.images.shape[:3]
    side = int(min(1024, np.sqrt(INTEGRABILITY_SAMPLES / K)))
    r0, c0 = max(0, (M - side) // 2), max(0, (N - side) // 2)
    rows, cols = slice(r0, M - r0), slice(c0, N - c0)

    def normals_of(model):
        mask = None if capture.mask is None else capture.mask[rows, cols]
        images = capture.images[:, rows, cols]
        return solve_normals(images, model, pixel_size_um=capture.pixel_size_um, mask=mask,
                             saturation=capture.saturation).normals
    return normals_of


