"""The whole run, stage by stage: capture -> drop-off fits -> lights -> normals/albedo -> height.

Each stage is a function on arrays; the ``write_*`` functions put its results in a (temporary) run
folder in the formats of docs/architecture.md. ``uvps.commands`` strings them together for the CLI and
the file bridge.
"""
from __future__ import annotations

import dataclasses
import logging
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Optional

import numpy as np

from . import __version__
from .errors import UVPSInputError
from .flatfield import GainCorrected, block_grid, fit_dropoffs, fit_log_grid, flatfield, set_common
from .integrate import integrate_normals
from .io import Capture, sha256_file, write_imagej_tiff
from .lights import (LightEstimate, LightModel, estimate_lights, intensities_from_levels, pixel_coordinates_mm,
                     ratio_samples, refine_intensities, sample_pixels, _model_logs)
from .offset import OffsetImages, estimate_additive, known_additive
from .outputs import Progress, report, write_json_atomic
from .stereo import StereoResult

log = logging.getLogger(__name__)

__all__ = ["RunOptions", "LightsResult", "estimate_capture_lights", "write_lights", "write_flatfield",
           "write_stereo", "write_depth", "RunLog"]


@dataclass
class RunOptions:
    """Options of the photometric-stereo stages (everything else is read from the capture)."""

    degree: int = 4                 # Legendre degree of the drop-off fit
    robust: bool = False            # rank-trimmed stereo: per pixel, drop the darkest 25 % and brightest 10 %
    integration: str = "fc"         # "fc" (Frankot-Chellappa) or "dct" (Poisson, Neumann)
    refine_lights: bool = True      # per-light refinement after the equidistant solution
    sample_pixels: int = 30000      # pixels used by the photometric residual (at most 1 in 16)
    estimate_intensities: bool = False  # known lights: intensities from the images even over the light
    #                                     file's own (positions: photometric residual; directions: levels)
    black_level: Optional[object] = None  # known additive term in counts (one number or one per channel)
    offset: str = "auto"            # additive term: "auto" (measured from the images) or "none"
    offset_degree: int = 0          # 0: a constant black level; 1-2: also smooth stray light
    lamp_beams: bool = False        # known positions: divide out each lamp's beam (and the canvas's bow)

    def __post_init__(self):
        if not (isinstance(self.degree, (int, np.integer)) and 1 <= int(self.degree) <= 8):
            raise UVPSInputError(f"degree must be an integer from 1 to 8; got {self.degree!r}")
        if self.integration not in ("fc", "dct"):
            raise UVPSInputError(f"integration must be 'fc' or 'dct'; got {self.integration!r}")
        if int(self.sample_pixels) < 500:
            raise UVPSInputError(f"sample_pixels must be >= 500; got {self.sample_pixels!r}")
        if self.offset not in ("auto", "none"):
            raise UVPSInputError(f"offset must be 'auto' or 'none'; got {self.offset!r}")
        if self.offset_degree not in (0, 1, 2):
            raise UVPSInputError(f"offset_degree must be 0, 1 or 2; got {self.offset_degree!r}")


@dataclass
class LightsResult:
    """Lights of a capture and how they were obtained."""

    model: LightModel
    fits: list
    source: str                          # "estimated", "positions" or "directions"
    estimate: Optional[LightEstimate] = None
    images: Optional[object] = None      # the stack as the lights see it (known positions: beams divided out)
    beam_rms: Optional[float] = None     # known positions: rms of the drop-off beyond the model (log units)


@dataclass
class RunLog:
    """What run.json records: parameters, inputs, timings, warnings."""

    command: str
    params: dict
    inputs: list = field(default_factory=list)
    timings_s: dict = field(default_factory=dict)
    warnings: list = field(default_factory=list)
    diagnostics: dict = field(default_factory=dict)

    def time(self, stage, t0):
        self.timings_s[stage] = round(time.perf_counter() - t0, 3)

    def write(self, path):
        d = asdict(self)
        d = {"version": __version__, **d}
        write_json_atomic(path, d)


def input_hashes(capture: Capture) -> list:
    """SHA-256 of every input file (a stack is hashed once)."""
    seen, out = set(), []
    for f in capture.files:
        p = f.rsplit("#", 1)[0] if "#" in f and not Path(f).exists() else f   # "stack.tif#k"
        if p in seen:
            continue
        seen.add(p)
        out.append({"path": str(p), "sha256": sha256_file(p)})
    return out


#: The measured additive term must be pinned to this fraction of the median signal: an error of 0.2 %
#: moved the estimated lamps by 5 degrees on the benchmark captures (docs/benchmarks.md).
OFFSET_TOLERANCE = 0.001
#: A measured additive term smaller than this many standard errors is not subtracted.
SIGNIFICANT = 2.0
#: An additive term above this fraction of the median signal: the images are mostly pedestal.
OFFSET_MAX = 0.5


def remove_additive(capture: Capture, *, options: RunOptions, dark_given=False) -> tuple:
    """The capture with its additive term (black level, stray light) removed, and that term.

    Given black level (``options.black_level``): that. A dark frame (already subtracted on reading):
    nothing more is removed. ``options.offset == "none"``: nothing. Otherwise the term is measured
    from the images (:func:`uvps.offset.estimate_additive`). The images are not copied: the result's
    ``images`` is a view that subtracts on access (:class:`uvps.offset.OffsetImages`).

    Returns
    -------
    (Capture, AdditiveTerm, list of str)
        The capture to use, the term, and warnings (only when the term is poorly pinned).
    """
    images = capture.images
    M, N = images.shape[1:3]
    C = images.shape[3] if images.ndim == 4 else 1
    warnings = []
    if options.black_level is not None:
        term = known_additive(options.black_level, shape=(M, N), channels=C)
    elif dark_given or options.offset == "none":
        term = known_additive(0.0, shape=(M, N), channels=C, source="dark frame" if dark_given else "none")
    else:
        term = estimate_additive(images, mask=capture.mask, saturation=capture.saturation,
                                 degree=int(options.offset_degree), dropoff_degree=int(options.degree))
    if not np.isfinite(term.median_signal):
        k = np.linspace(0, images.shape[0] - 1, min(4, images.shape[0])).astype(int)
        sub = np.asarray(images[k, ::8, ::8], dtype=np.float32)
        if capture.mask is not None:                  # a masked object: its background is no signal
            sub = sub[:, capture.mask[::8, ::8]]
        term.median_signal = float(np.median(sub)) - float(term.mean.mean())
    frac = float(term.mean.mean()) / max(term.median_signal, 1e-12)
    if not term.is_zero and (term.median_signal <= 0 or frac > OFFSET_MAX):
        raise UVPSInputError(
            f"the images are mostly pedestal: the additive term ({term.source}, {term.mean.mean():.1f} counts) is "
            f"{100 * frac:.0f} % of the median signal; check the exposure, the black level or the dark frame")
    if term.stderr is not None and not np.isfinite(term.stderr).all():
        term.diagnostics["used"] = False
        if capture.light_positions_mm is None and capture.light_directions is None:   # lamps to estimate
            warnings.append(f"the black level could not be measured ({term.diagnostics.get('note', '')}); "
                            "estimated lamp elevations and heights may be off; give the camera's black level "
                            "or a dark frame")
        return capture, term, warnings
    if term.stderr is not None and float(term.mean.mean()) <= 0:
        # a pedestal or stray light is never negative: a negative measure is the model's error
        # (e.g. a JPEG's tone curve), not something to add back
        term.diagnostics["used"] = False
        term.diagnostics["note"] = "negative: not subtracted"
        return capture, term, warnings
    if term.stderr is not None:
        term.diagnostics["measured_counts"] = [round(float(v), 3) for v in term.mean]
        term.coeffs[:, 0, 0] = np.maximum(term.coeffs[:, 0, 0], 0.0)   # per channel, likewise
        se = float(np.sqrt(np.mean(term.stderr ** 2)))
        if abs(float(term.mean.mean())) < SIGNIFICANT * se:
            # consistent with no offset: subtracting it would only add its noise (a clean capture is
            # then processed exactly as it was before the additive term was modelled)
            term.diagnostics["used"] = False
            term.diagnostics["note"] = f"not significant (|c| < {SIGNIFICANT:g} standard errors): not subtracted"
            return capture, term, warnings
        if se > OFFSET_TOLERANCE * term.median_signal:
            warnings.append(
                f"the black level could only be measured to +-{se:.0f} counts ({100 * se / term.median_signal:.2f} % "
                "of the signal; the field may hold too little dark and bright paint): estimated lamp elevations "
                "and heights may be off; give the camera's black level or a dark frame")
    if term.is_zero:
        return capture, term, warnings
    return dataclasses.replace(capture, images=OffsetImages(images, term)), term, warnings


def estimate_capture_lights(capture: Capture, *, options: RunOptions, offset_stderr=None,
                            progress: Progress = None) -> LightsResult:
    """Drop-off fits for every image, and the lights: given (positions or directions) or estimated.

    Known positions (a calibrated near-light file) are used as they are, with each lamp's relative
    intensity from the file when it gives them, otherwise measured from the images by the photometric
    residual with the positions held (:func:`uvps.lights.refine_intensities`). Known
    directions (an RTI ``.lp`` file) give far lights with the file's intensities, or equal ones when it
    gives none: an ``.lp`` file says nothing about intensities, and levels read as if the surface were
    flat and facing the camera are wrong on a relief. ``options.estimate_intensities`` measures them
    from the images for either kind (far lights: from the levels), even over the file's. Otherwise
    the near-light positions are estimated from the images (:func:`uvps.lights.estimate_lights`);
    ``offset_stderr`` (grey counts, from :func:`remove_additive`) goes into their uncertainty.
    """
    px = capture.pixel_size_um
    report(progress, 0.0, "drop-off fits")
    grid = block_grid(capture.images, mask=capture.mask, saturation=capture.saturation)
    fits = fit_dropoffs(grid, degree=int(options.degree))
    shape = grid.shape

    def common_of(P):
        return lambda r, c: _model_logs(P, pixel_coordinates_mm(np.asarray(r)[:, None], np.asarray(c)[None, :],
                                                                  shape, px)).mean(axis=0)

    # At most one pixel in 16 (a denser sample adds neighbours whose texture is correlated, and time),
    # and at most 150000 residuals (12500 pixels x 12 lights; as accurate as 30000 on the benchmark,
    # docs/benchmarks.md): the refinement's Jacobian holds lights x pixels x 4 lights float64 values,
    # so its memory and time grow as K^2.
    n = min(int(options.sample_pixels), max(5000, shape[0] * shape[1] // 16), max(2000, 150000 // len(fits)))
    if capture.light_positions_mm is not None:
        P = capture.light_positions_mm
        # What each image's drop-off holds beyond the point-light model of the given positions (a
        # lamp's beam, its aim): measured from the ratio maps and reported; with lamp_beams it is
        # divided out (a narrow lamp aimed 5 deg off tilted every normal by 1-9 deg; divided out,
        # 0.2 deg), leaving the lamps' relative irradiance at every pixel to the model. It cannot be
        # told from the shading of the canvas's own large-scale shape (bow), which goes with it: off
        # by default.
        rows, cols, R = ratio_samples(fits, shape)
        X = pixel_coordinates_mm(rows[:, None], cols[None, :], shape, px)
        h = _model_logs(P, X)
        delta = R - h + h.mean(axis=0)
        delta -= delta.mean(axis=0)
        beam_rms = float(np.sqrt(np.mean(delta ** 2)))
        if options.lamp_beams:
            gains = fit_log_grid(delta, rows, cols, shape, int(options.degree))
            capture = dataclasses.replace(capture, images=GainCorrected(capture.images, gains))
            grid = block_grid(capture.images, mask=capture.mask, saturation=capture.saturation)
            fits = fit_dropoffs(grid, degree=int(options.degree))
        set_common(fits, grid, common_of(P))
        E = capture.light_intensities   # given (median 1 like an estimate), else from the images
        if E is None or options.estimate_intensities:
            # by the photometric residual with the positions held: the levels alone assume a flat
            # canvas facing the camera (1.2 deg normals on a cupped capture, 0.13 deg this way)
            E = intensities_from_levels([f.level for f in fits], P, shape, px)
            sample = sample_pixels(capture.images, fits, mask=capture.mask, saturation=capture.saturation,
                                   pixel_size_um=px, n=min(n, 20000))
            E = refine_intensities(sample, P, E)
        return LightsResult(LightModel.from_positions(P, E / np.median(E)), fits, "positions",
                            images=capture.images if options.lamp_beams else None, beam_rms=beam_rms)
    if capture.light_directions is not None:
        # far lights: no drop-off model; the fits stay relative to the stack's geometric mean.
        # Intensities: given, else equal (None); from the levels only when asked.
        D = capture.light_directions
        E = capture.light_intensities
        if options.estimate_intensities:
            E = intensities_from_levels([f.level for f in fits], None, shape, px, directions=D)
        return LightsResult(LightModel.from_directions(D, None if E is None else E / np.median(E)), fits,
                            "directions")
    sample = sample_pixels(capture.images, fits, mask=capture.mask, saturation=capture.saturation,
                           pixel_size_um=px, n=n)
    sub = None if progress is None else (lambda f, m: progress(0.05 + 0.95 * f, m))
    est = estimate_lights(grid, fits, sample, pixel_size_um=px, refine=options.refine_lights,
                          offset_stderr=offset_stderr, progress=sub)
    return LightsResult(est.model, fits, "estimated", est)


def write_lights(folder: Path, capture: Capture, lights: LightsResult, *, dropoff=True) -> dict:
    """``lights.json`` (and ``dropoff.tif``, the fitted drop-off maps, at most 1024 px wide)."""
    extra = {"pixel_size_um": capture.pixel_size_um, "image_shape": list(capture.images.shape[1:3]),
             "source": lights.source,
             "dropoff": [{"degree": f.degree, "legendre_coeffs": f.coeffs.tolist(), "level": f.level}
                         for f in lights.fits]}
    if lights.beam_rms is not None:
        extra["dropoff_beyond_model_rms"] = round(lights.beam_rms, 6)
    if lights.estimate is not None:
        est = lights.estimate
        if est.uncertainty is not None:
            extra["uncertainty"] = est.uncertainty.to_json()
        extra.update({"m_mm": est.m_mm, "residual_history": est.residual_history,
                      "azimuth_polar_deg": [float(a) for a in est.azimuth_polar_deg],
                      "equidistant_positions_mm": est.equidistant.positions_mm.tolist()})
    data = lights.model.to_json([Path(f).name for f in capture.files], extra=extra)
    write_json_atomic(folder / "lights.json", data)
    if dropoff:
        M, N = capture.images.shape[1:3]
        step = max(1, int(np.ceil(max(M, N) / 1024)))
        rows, cols = np.arange(0, M, step), np.arange(0, N, step)
        maps = np.stack([f.evaluate(rows, cols) for f in lights.fits]).astype(np.float32)
        write_imagej_tiff(folder / "dropoff.tif", maps, axes="ZYX", pixel_size_um=capture.pixel_size_um * step,
                          labels=[Path(f).name for f in capture.files],
                          metadata={"Info": f"uvps drop-off maps (mean 1), sampled every {step} px"})
    return data


def write_flatfield(folder: Path, capture: Capture, lights: LightsResult, *, progress: Progress = None) -> Path:
    """``flatfield/<name>.tif``: each image divided by its drop-off map, one float32 file per image."""
    out = folder / "flatfield"
    out.mkdir(exist_ok=True)
    K = capture.images.shape[0]
    for k, (img, fit) in enumerate(zip(capture.images, lights.fits)):
        ff = flatfield(img, fit)
        axes = "YX"
        if ff.ndim == 3:
            ff, axes = np.moveaxis(ff, -1, 0), "CYX"
        name = Path(capture.files[k].replace("#", "_")).stem
        write_imagej_tiff(out / f"{k:03d}_{name}.tif", ff, axes=axes, pixel_size_um=capture.pixel_size_um)
        report(progress, (k + 1) / K, f"flat field {k + 1}/{K}")
    return out


def write_stereo(folder: Path, res: StereoResult, pixel_size_um: float) -> None:
    """``normals.tif`` (3, M, N), ``albedo.tif`` ((3,) M, N) and ``gradients.tif`` (2, M, N)."""
    from .integrate import gradients_from_normals

    write_imagej_tiff(folder / "normals.tif", np.moveaxis(res.normals, -1, 0), axes="CYX",
                      pixel_size_um=pixel_size_um, labels=["nx", "ny", "nz"])
    if res.albedo.ndim == 3:
        write_imagej_tiff(folder / "albedo.tif", np.moveaxis(res.albedo, -1, 0), axes="CYX",
                          pixel_size_um=pixel_size_um, labels=["R", "G", "B"][:res.albedo.shape[-1]])
    else:
        write_imagej_tiff(folder / "albedo.tif", res.albedo, axes="YX", pixel_size_um=pixel_size_um)
    g = gradients_from_normals(res.normals)
    write_imagej_tiff(folder / "gradients.tif", np.stack([g.p, g.q]), axes="CYX",
                      pixel_size_um=pixel_size_um, labels=["p = dz/dx", "q = dz/dy (y up)"])


def write_depth(folder: Path, normals, pixel_size_um: float, *, method="fc", mask=None) -> dict:
    """``depth.tif``: height in micrometres (median 0), from the normals."""
    res = integrate_normals(normals, pixel_size_um=pixel_size_um, method=method, mask=mask)
    write_imagej_tiff(folder / "depth.tif", res.height_um, axes="YX", pixel_size_um=pixel_size_um,
                      metadata={"Info": f"uvps height in micrometres ({res.method}), median 0"})
    return {"method": res.method, "residual_rms": res.residual_rms, "integrability": res.integrability,
            "height_range_um": [float(np.nanmin(res.height_um)), float(np.nanmax(res.height_um))]}
