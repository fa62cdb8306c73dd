"""The commands shared by the CLI (``uvps <command>``) and the file bridge (``uvps bridge``).

Every command is ``cmd(inputs: dict, params: dict, output_dir, *, progress=None) -> CommandResult``
(docs/architecture.md, "Commands"); :data:`COMMANDS` maps names to them. :func:`cli_main` turns
command-line flags into the same dictionaries.
"""
from __future__ import annotations

import argparse
import dataclasses
import logging
import sys
import time
from pathlib import Path

import numpy as np

from . import __version__
from .errors import UVPSError, UVPSInputError
from .outputs import CommandResult, OutputSpec, atomic_output_dir, check_output_dir, report

log = logging.getLogger(__name__)

_CAPTURE_KEYS = {"lights", "mask", "dark", "pixel_size_um", "linearize"}
_OPTION_KEYS = {"degree", "robust", "integration", "refine_lights", "sample_pixels", "estimate_intensities",
                "black_level", "offset", "offset_degree", "lamp_beams"}


def _unknown(params, known, warnings):
    for k in sorted(set(params) - set(known)):
        warnings.append(f"unknown parameter {k!r} ignored")


def _read(inputs, params, progress):
    from .io import read_capture

    images = inputs.get("images")
    if images is None or (isinstance(images, (list, tuple)) and len(images) == 0):
        raise UVPSInputError("inputs.images is missing: give image files, a folder or a multi-page TIFF")
    if isinstance(images, (list, tuple)) and len(images) == 1:
        images = images[0]
    return read_capture(images, lights=params.get("lights"), mask=params.get("mask"), dark=params.get("dark"),
                        pixel_size_um=params.get("pixel_size_um"), linearize=params.get("linearize") or "auto",
                        progress=progress)


def _options(params):
    from .pipeline import RunOptions

    kw = {k: params[k] for k in _OPTION_KEYS if params.get(k) is not None}
    if "degree" in kw:
        kw["degree"] = _as_int(kw["degree"], "degree")
    for key in ("robust", "refine_lights", "estimate_intensities", "lamp_beams"):
        if key in kw:
            kw[key] = _as_bool(kw[key], key)
    if "offset_degree" in kw:
        kw["offset_degree"] = _as_int(kw["offset_degree"], "offset_degree")
    if "black_level" in kw:
        kw["black_level"] = _as_numbers(kw["black_level"], "black_level")
    return RunOptions(**kw)


def _as_numbers(v, name):
    """One number or a list of numbers (given as a list, or a comma-separated string)."""
    items = v if isinstance(v, (list, tuple)) else str(v).split(",")
    try:
        out = [float(x) for x in items]
    except (TypeError, ValueError):
        raise UVPSInputError(f"{name} must be a number or comma-separated numbers; got {v!r}") from None
    return out[0] if len(out) == 1 else out


def _as_int(v, name):
    try:
        f = float(v)
    except (TypeError, ValueError):
        raise UVPSInputError(f"{name} must be an integer; got {v!r}") from None
    if f != int(f):
        raise UVPSInputError(f"{name} must be an integer; got {v!r}")
    return int(f)


def _as_bool(v, name):
    if isinstance(v, bool):
        return v
    if str(v).lower() in ("1", "true", "yes", "on"):
        return True
    if str(v).lower() in ("0", "false", "no", "off", ""):
        return False
    raise UVPSInputError(f"{name} must be true or false; got {v!r}")


def _sub(progress, a, b):
    return None if progress is None else (lambda f, m: progress(a + (b - a) * f, m))


def _image_out(name, path, axes, units):
    return OutputSpec(name, str(path), kind="image", axes=axes, dtype="float32", units=units)


def _stage_outputs(run_dir, names):
    table = {
        "normals": ("normals.tif", "CYX", "1"),
        "albedo": ("albedo.tif", None, "counts"),
        "gradients": ("gradients.tif", "CYX", "1"),
        "depth": ("depth.tif", "YX", "um"),
        "dropoff": ("dropoff.tif", "ZYX", "1"),
    }
    out = []
    for n in names:
        if n == "lights":
            out.append(OutputSpec("lights", str(run_dir / "lights.json"), kind="json"))
        elif n == "flatfield":
            out.append(OutputSpec("flatfield", str(run_dir / "flatfield"), kind="folder", dtype="float32",
                                  units="counts"))
        elif n == "run":
            out.append(OutputSpec("run", str(run_dir / "run.json"), kind="json"))
        else:
            f, axes, units = table[n]
            out.append(_image_out(n, run_dir / f, axes, units))
    return out


#: A run whose lamps leave more than this fraction of the pixels with fewer than 3 usable samples
#: stops: no model fits the images.
NO_MODEL_FRACTION = 0.5
#: Relative standard uncertainty of heights from the estimated lamps beyond which a run warns, and
#: beyond which it says the heights' scale is not determined. The reported uncertainty is
#: conservative: on the benchmark's 24 x 18 mm field it was 2-6x the true height error (8-15 % for
#: true errors of 2-4 %, docs/benchmarks.md), so the warning starts at 20 %, not on every run.
#: Stray light the additive term misses gave 250-15000 %; a 3.6 x 4.8 mm field 140 %.
HEIGHT_UNCERTAINTY_WARN = 0.20
HEIGHT_UNCERTAINTY_UNDETERMINED = 1.0


def _lights_diag(lights):
    d = {"source": lights.source, "n_lights": int(len(lights.model.intensities))}
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
            d["direction_uncertainty_deg_max"] = round(float(np.max(u.direction_deg)), 4)
    return d


def _ps_core(capture, params, run_dir, tmp, runlog, progress, *, stages):
    """Shared body of run / flatfield / lights / normals."""
    from .pipeline import (estimate_capture_lights, remove_additive, write_depth, write_flatfield, write_lights,
                           write_stereo)
    from .stereo import solve_normals

    options = _options(params)
    runlog.params.update({"options": options.__dict__, "pixel_size_um": capture.pixel_size_um,
                          "image_shape": list(capture.images.shape[1:]), "bit_depth": capture.bit_depth})
    t0 = time.perf_counter()
    capture, additive, warn = remove_additive(capture, options=options, dark_given=params.get("dark") is not None)
    runlog.time("additive", t0)
    runlog.diagnostics["additive"] = additive.to_json()
    runlog.warnings += warn
    t0 = time.perf_counter()
    se = additive.stderr
    offset_se = float(np.mean(se)) if se is not None and np.all(np.isfinite(se)) else None
    lights = estimate_capture_lights(capture, options=options, offset_stderr=offset_se,
                                     progress=_sub(progress, 0.1, 0.45))
    runlog.time("lights", t0)
    runlog.diagnostics["lights"] = _lights_diag(lights)
    if lights.images is not None:       # known positions: the images with the lamps' beams divided out
        capture = dataclasses.replace(capture, images=lights.images)
    unc = lights.estimate.uncertainty if lights.estimate is not None else None
    if unc is not None and unc.height_rel > HEIGHT_UNCERTAINTY_UNDETERMINED:
        # the lamps are not determined by these images: the relief's shape may still serve (protrusions
        # show), its scale does not; said once, with what to do
        runlog.warnings.append(
            f"the heights' scale is not determined by these images (uncertain by +-{100 * unc.height_rel:.0f} %: "
            "a small field, or stray light or lamp beams the model does not hold): give measured lamp positions "
            "(--lights), and a dark frame (--dark) if there is stray light")
    elif unc is not None and unc.height_rel > HEIGHT_UNCERTAINTY_WARN:
        # a warning only when the lamps' uncertainty makes the heights clearly uncertain: it then says
        # which cause dominates and what to do (reported once: the CLI prints it, the bridge returns it)
        cause = ("the black level could not be measured precisely enough; give the camera's black level or a "
                 "dark frame" if unc.height_rel_offset > unc.height_rel_noise else
                 "the field is too small (or the lamps too far) for the lamps' distance and elevation to be told "
                 "apart; give measured lamp positions")
        runlog.warnings.append(f"heights may be off by +-{100 * unc.height_rel:.0f} % (the estimated lamps' "
                               f"elevations are uncertain): {cause}")
    write_lights(tmp, capture, lights)
    if "flatfield" in stages:
        t0 = time.perf_counter()
        write_flatfield(tmp, capture, lights, progress=_sub(progress, 0.45, 0.55))
        runlog.time("flatfield", t0)
    if "normals" in stages:
        t0 = time.perf_counter()
        res = solve_normals(capture.images, lights.model, pixel_size_um=capture.pixel_size_um, mask=capture.mask,
                            saturation=capture.saturation, robust=options.robust,
                            progress=_sub(progress, 0.55, 0.85))
        runlog.time("normals", t0)
        runlog.diagnostics["normals"] = {"n_invalid": res.n_invalid, "residual_rms": res.residual_rms}
        n_px = int(capture.mask.sum()) if capture.mask is not None else int(np.prod(capture.images.shape[1:3]))
        if res.n_invalid > NO_MODEL_FRACTION * n_px:
            # the lamps explain the images nowhere: no heights rather than wrong ones
            raise UVPSInputError(
                f"no lamp model fits these images: {100 * res.n_invalid / n_px:.0f} % of the pixels are lit by fewer "
                f"than 3 lamps as {lights.source} (lamps with narrow beams or stray light the lamp model does not "
                "hold?); give measured lamp positions (--lights) or a dark frame (--dark)")
        if res.n_invalid:
            runlog.warnings.append(f"{res.n_invalid} pixels had fewer than 3 usable lights (NaN)")
        write_stereo(tmp, res, capture.pixel_size_um)
        if "depth" in stages:
            t0 = time.perf_counter()
            report(progress, 0.87, "integrating the height")
            runlog.diagnostics["integration"] = write_depth(tmp, res.normals, capture.pixel_size_um,
                                                            method=options.integration, mask=capture.mask)
            runlog.time("integrate", t0)
    runlog.write(tmp / "run.json")


def _capture_command(stages, name):
    def cmd(inputs, params, output_dir, *, progress=None):
        from .pipeline import RunLog, input_hashes

        run_dir = check_output_dir(output_dir)
        warnings = []
        _unknown(params, _CAPTURE_KEYS | _OPTION_KEYS | {"regions", "detect", "bins_um", "n_areas", "seed"},
                 warnings)
        t_all = time.perf_counter()
        capture = _read(inputs, params, _sub(progress, 0.0, 0.1))
        runlog = RunLog(name, {k: v for k, v in params.items()}, warnings=warnings)
        runlog.inputs = input_hashes(capture)
        with atomic_output_dir(run_dir) as tmp:
            _ps_core(capture, params, run_dir, tmp, runlog, progress, stages=stages)
        names = ["lights", "dropoff", "run"] + (["flatfield"] if "flatfield" in stages else []) + \
            (["normals", "albedo", "gradients"] if "normals" in stages else []) + (["depth"] if "depth" in stages else [])
        result = CommandResult(_stage_outputs(run_dir, names), dict(runlog.diagnostics), runlog.warnings)
        if name == "run":
            result = _run_protrusions(run_dir, params, result, progress)
        result.diagnostics["elapsed_s"] = round(time.perf_counter() - t_all, 3)
        report(progress, 1.0, f"{name}: done")
        return result

    cmd.__name__ = f"cmd_{name}"
    cmd.__doc__ = f"``{name}``: read a capture and write {', '.join(stages)} into the run folder."
    return cmd


def _run_protrusions(run_dir, params, result, progress):
    """``run`` with ``regions`` (or ``detect``): detection, statistics and the report."""
    from .protrusion_commands import cmd_detect, cmd_regions, cmd_stats

    regions = params.get("regions")
    if not (regions or _as_bool(params.get("detect", False), "detect")):
        return result
    steps = []
    if regions == "auto":
        p = {"auto": True}
        if params.get("n_areas") is not None:
            p["n_areas"] = params["n_areas"]
        steps.append(("regions", cmd_regions, {}, p))
    elif regions:
        steps.append(("regions", cmd_regions, {"labels": regions}, {}))
    steps.append(("detect", cmd_detect, {}, {}))
    steps.append(("stats", cmd_stats, {}, {"bins_um": params.get("bins_um", 100.0)}))
    for i, (name, fn, inp, p) in enumerate(steps):
        r = fn(inp, p, run_dir, progress=_sub(progress, 0.9 + 0.09 * i / len(steps), 0.9 + 0.09 * (i + 1) / len(steps)))
        result.outputs += r.outputs
        result.diagnostics[name] = r.diagnostics
        # the areas are registered before detection: their "no protrusions yet" note is moot here
        result.warnings += [w for w in r.warnings if not (name == "regions" and "protrusions.csv" in w)]
    return result


cmd_run = _capture_command(("flatfield", "normals", "depth"), "run")
cmd_flatfield = _capture_command(("flatfield",), "flatfield")
cmd_lights = _capture_command((), "lights")
cmd_normals = _capture_command(("normals",), "normals")


def cmd_integrate(inputs, params, output_dir, *, progress=None):
    """``integrate``: height in um from ``<run>/normals.tif`` (``integration`` = "fc" or "dct")."""
    from .pipeline import write_depth
    from .protrusion_commands import read_run

    run_dir = check_output_dir(output_dir)
    warnings = []
    _unknown(params, {"integration", "pixel_size_um"}, warnings)
    method = params.get("integration") or "fc"
    if method not in ("fc", "dct"):
        raise UVPSInputError(f"integration must be 'fc' or 'dct'; got {method!r}")
    run = read_run(run_dir, need=("normals",), pixel_size_um=params.get("pixel_size_um"))
    report(progress, 0.2, "integrating")
    with atomic_output_dir(run_dir) as tmp:
        diag = write_depth(tmp, run.normals, run.pixel_size_um, method=method)
    report(progress, 1.0, "integrate: done")
    return CommandResult(_stage_outputs(run_dir, ["depth"]), diag, warnings)


def cmd_relight(inputs, params, output_dir, *, progress=None):
    """``relight``: the surface under a virtual raking light (``azimuth_deg``, ``elevation_deg``)."""
    from .io import write_imagej_tiff
    from .protrusion_commands import read_run
    from .relight import relight

    run_dir = check_output_dir(output_dir)
    warnings = []
    _unknown(params, {"azimuth_deg", "elevation_deg", "ambient", "pixel_size_um"}, warnings)
    try:
        az = float(params.get("azimuth_deg", 315.0))
        el = float(params.get("elevation_deg", 15.0))
        amb = float(params.get("ambient", 0.0))
    except (TypeError, ValueError):
        raise UVPSInputError("azimuth_deg, elevation_deg and ambient must be numbers") from None
    if not 0 < el <= 90:
        raise UVPSInputError(f"elevation_deg must be in (0, 90]; got {el}")
    run = read_run(run_dir, need=("normals",), pixel_size_um=params.get("pixel_size_um"))
    px, albedo = run.pixel_size_um, run.albedo
    if albedo is None:
        warnings.append("no albedo.tif: relit with a uniform albedo")
        albedo = np.ones(run.normals.shape[:2], np.float32)
    img = relight(run.normals, albedo, azimuth_deg=az, elevation_deg=el, ambient=amb)
    with atomic_output_dir(run_dir) as tmp:
        if img.ndim == 3:
            write_imagej_tiff(tmp / "relight.tif", np.moveaxis(img, -1, 0), axes="CYX", pixel_size_um=px)
        else:
            write_imagej_tiff(tmp / "relight.tif", img, axes="YX", pixel_size_um=px)
    return CommandResult([_image_out("relight", run_dir / "relight.tif", "CYX" if img.ndim == 3 else "YX", "counts")],
                         {"azimuth_deg": az, "elevation_deg": el}, warnings)


#: The demo's pixel: 600 x 800 px of 30 um show the 18 x 24 mm field a real capture has (the lamps'
#: distance and elevation are told apart by the field's size, not its pixels; at 15 um the 9 x 12 mm
#: crop leaves heights uncertain by ~25 % and the light estimate crawls along its valley).
DEMO_PIXEL_UM = 30.0


def cmd_demo(inputs, params, output_dir, *, progress=None):
    """``demo``: a synthetic capture written to ``<run>/capture/`` and the whole run on it."""
    from .synthetic import make_capture, write_capture

    run_dir = check_output_dir(output_dir)
    shape = tuple(int(v) for v in params.get("shape", (600, 800)))
    n = _as_int(params.get("n_lights", 12), "n_lights")
    seed = _as_int(params.get("seed", 0), "seed")
    px = float(params.get("pixel_size_um", DEMO_PIXEL_UM))
    report(progress, 0.0, "demo: making a synthetic capture")
    cap = make_capture(shape=shape, n_lights=n, seed=seed, pixel_size_um=px)
    run_dir.mkdir(exist_ok=True)
    cap_dir = run_dir / "capture"
    write_capture(cap, cap_dir)
    images = sorted(cap_dir.glob("uv_*.tif"))
    # the colour areas are proposed from the albedo, as a user would accept them (the truth stays unread)
    run_params = {"regions": "auto", "bins_um": 100.0}
    result = cmd_run({"images": [str(p) for p in images]}, run_params, run_dir, progress=_sub(progress, 0.05, 1.0))
    result.outputs.insert(0, OutputSpec("capture", str(cap_dir), kind="folder"))
    result.diagnostics["truth_light_positions_mm"] = cap.light_positions_mm.tolist()
    return result


def _protrusion_commands():
    from .protrusion_commands import PROTRUSION_COMMANDS

    return PROTRUSION_COMMANDS


COMMANDS = {
    "run": cmd_run,
    "flatfield": cmd_flatfield,
    "lights": cmd_lights,
    "normals": cmd_normals,
    "integrate": cmd_integrate,
    "relight": cmd_relight,
    "demo": cmd_demo,
}
COMMANDS.update(_protrusion_commands())


# ------------------------------------------------------------------------------------------------
# command line
# ------------------------------------------------------------------------------------------------

def _capture_args(p, *, stages=True):
    p.add_argument("images", nargs="+", help="image files, a folder, or one multi-page TIFF")
    p.add_argument("-o", "--output", required=True, help="run folder (created; files inside are replaced)")
    p.add_argument("--lights", help="RTI .lp (directions) or positions file (.csv/.json, mm); default: estimate")
    p.add_argument("--mask", help="mask image (non-zero = use)")
    p.add_argument("--dark", help="ambient/dark frame to subtract")
    p.add_argument("--pixel-size-um", type=float, help="pixel size on the painting (default: TIFF tags)")
    p.add_argument("--linearize", choices=["auto", "srgb", "none"], default="auto",
                   help="sRGB -> linear (auto: JPEG only)")
    p.add_argument("--degree", type=int, default=4, help="Legendre degree of the drop-off fit (4)")
    if stages:
        p.add_argument("--robust", action="store_true",
                       help="rank-trimmed stereo: per pixel, leave out the darkest 25 %% and brightest 10 %% of "
                            "samples (cast shadows, highlights; many lights)")
        p.add_argument("--integration", choices=["fc", "dct"], default="fc", help="height integration method")
    p.add_argument("--no-refine-lights", action="store_true", help="keep the paper's equidistant lights")
    p.add_argument("--black-level", metavar="COUNTS",
                   help="the camera's black level left in the files (one number, or R,G,B): subtracted instead of "
                        "measuring it from the images")
    p.add_argument("--offset", choices=["auto", "none"], default="auto",
                   help="additive term (black level, stray light): measured from the images (auto) or none")
    p.add_argument("--lamp-beams", action="store_true",
                   help="with --lights positions: divide out each lamp's beam (narrow or mis-aimed lamps); "
                        "also removes the canvas's large-scale shape (bow) from the heights")
    p.add_argument("--offset-degree", type=int, choices=[0, 1, 2], default=0,
                   help="0: a constant black level; 1-2: also stray light varying smoothly across the field")
    p.add_argument("--estimate-intensities", action="store_true",
                   help="with --lights: each lamp's intensity from the image levels (flat surface assumed); "
                        "default: the light file's intensity column, else equal (.lp) or from the levels (positions)")


def _parser():
    ap = argparse.ArgumentParser(prog="uvps", description="Photometric stereo by UV-induced fluorescence "
                                 "(lights from the images, normals, albedo, height, protrusions).")
    ap.add_argument("--version", action="version", version=f"uvps {__version__}")
    ap.add_argument("-v", "--verbose", action="store_true", help="debug logging")
    sp = ap.add_subparsers(dest="command", required=True, metavar="COMMAND")
    p = sp.add_parser("run", help="the whole pipeline on a capture")
    _capture_args(p)
    p.add_argument("--regions", help="colour-area label TIFF, or 'auto': adds detection, statistics and the report")
    p.add_argument("--detect", action="store_true", help="detect protrusions even without --regions")
    p.add_argument("--bins-um", type=float, default=100.0, help="width bin of the histograms (um)")
    p = sp.add_parser("flatfield", help="drop-off fits and flat-fielded images")
    _capture_args(p, stages=False)
    p = sp.add_parser("lights", help="light directions and positions")
    _capture_args(p, stages=False)
    p = sp.add_parser("normals", help="normals, albedo and gradients")
    _capture_args(p)
    p = sp.add_parser("integrate", help="height from <run>/normals.tif")
    p.add_argument("-o", "--output", required=True, help="run folder")
    p.add_argument("--integration", choices=["fc", "dct"], default="fc")
    p = sp.add_parser("relight", help="render under a virtual raking light")
    p.add_argument("-o", "--output", required=True, help="run folder")
    p.add_argument("--azimuth-deg", type=float, default=315.0)
    p.add_argument("--elevation-deg", type=float, default=15.0)
    p = sp.add_parser("detect", help="automated protrusion detection on a run folder")
    p.add_argument("-o", "--output", required=True, help="run folder")
    p.add_argument("--regions", help="colour-area label TIFF or 'auto'")
    p = sp.add_parser("wand", help="the manual method: wand at given points")
    p.add_argument("points", help="CSV with x_px,y_px (ImageJ point export works)")
    p.add_argument("-o", "--output", required=True, help="run folder")
    p.add_argument("--tolerance", type=float, required=True, help="wand tolerance (albedo units)")
    p.add_argument("--connectivity", type=int, choices=[4, 8], default=8)
    p.add_argument("--regions", help="colour-area label TIFF")
    p = sp.add_parser("regions", help="colour areas: from labels/masks or an automatic proposal")
    p.add_argument("-o", "--output", required=True, help="run folder")
    p.add_argument("--labels", help="label TIFF (0 = none)")
    p.add_argument("--masks", nargs="+", help="one mask TIFF per area")
    p.add_argument("--auto", action="store_true", help="propose areas by clustering the albedo colour")
    p.add_argument("--n-areas", type=int)
    for name in ("stats", "report"):
        p = sp.add_parser(name, help="per-area statistics and report.html")
        p.add_argument("-o", "--output", required=True, help="run folder")
        p.add_argument("--bins-um", type=float, nargs="+", default=[100.0],
                       help="bin width, or increasing bin edges (um)")
    p = sp.add_parser("compare", help="compare two protrusion tables (e.g. manual vs automated)")
    p.add_argument("a")
    p.add_argument("b")
    p.add_argument("-o", "--output", required=True, help="run folder")
    p.add_argument("--match-radius-um", type=float)
    p = sp.add_parser("demo", help="a synthetic capture and the whole run on it")
    p.add_argument("-o", "--output", default="uvps_demo", help="folder (default ./uvps_demo)")
    p.add_argument("--shape", type=int, nargs=2, default=[600, 800], metavar=("ROWS", "COLS"))
    p.add_argument("--n-lights", type=int, default=12)
    p.add_argument("--seed", type=int, default=0)
    p = sp.add_parser("bridge", help="the file bridge for the Fiji side: run a request.json")
    p.add_argument("request")
    return ap


def _args_to_request(a):
    """Map parsed CLI arguments to (inputs, params) for the command."""
    inputs, params = {}, {}
    c = a.command
    if hasattr(a, "images"):
        inputs["images"] = [str(Path(p).resolve()) for p in a.images]
        for k in ("lights", "mask", "dark", "pixel_size_um", "linearize", "degree", "robust", "integration",
                  "black_level", "offset", "offset_degree"):
            v = getattr(a, k, None)
            if v is not None:
                params[k] = v
        params["refine_lights"] = not a.no_refine_lights
        params["estimate_intensities"] = a.estimate_intensities
        params["lamp_beams"] = a.lamp_beams
    if c == "run":
        if a.regions:
            params["regions"] = a.regions
        params["detect"] = a.detect
        params["bins_um"] = a.bins_um
    elif c == "integrate":
        params["integration"] = a.integration
    elif c == "relight":
        params.update(azimuth_deg=a.azimuth_deg, elevation_deg=a.elevation_deg)
    elif c == "detect":
        if a.regions:
            params["regions"] = a.regions
    elif c == "wand":
        inputs["points"] = a.points
        params.update(tolerance=a.tolerance, connectivity=a.connectivity)
        if a.regions:
            params["regions"] = a.regions
    elif c == "regions":
        if a.labels:
            inputs["labels"] = a.labels
        if a.masks:
            inputs["masks"] = a.masks
        params["auto"] = a.auto
        if a.n_areas is not None:
            params["n_areas"] = a.n_areas
    elif c in ("stats", "report"):
        params["bins_um"] = a.bins_um[0] if len(a.bins_um) == 1 else a.bins_um
    elif c == "compare":
        inputs.update(a=a.a, b=a.b)
        if a.match_radius_um is not None:
            params["match_radius_um"] = a.match_radius_um
    elif c == "demo":
        params.update(shape=a.shape, n_lights=a.n_lights, seed=a.seed)
    return inputs, params


class _Bar:
    """A tqdm progress bar on stderr driven by the progress callback (CLI only)."""

    def __init__(self, name):
        from tqdm import tqdm

        self.bar = tqdm(total=1000, desc=name, file=sys.stderr, leave=False,
                        bar_format="{desc}: {percentage:3.0f}%|{bar}| {postfix}")

    def __call__(self, fraction, message):
        self.bar.n = int(1000 * fraction)
        self.bar.set_postfix_str(message[:60], refresh=True)

    def close(self):
        self.bar.close()


def cli_main(argv) -> int:
    """``uvps`` entry point; returns the exit status (0 ok, 1 bad input, 2 compute error)."""
    ap = _parser()
    a = ap.parse_args(argv)
    logging.basicConfig(level=logging.DEBUG if a.verbose else logging.INFO, stream=sys.stderr,
                        format="%(levelname)s %(name)s: %(message)s")
    if a.command == "bridge":
        from .bridge import run_bridge

        return run_bridge(a.request)
    inputs, params = _args_to_request(a)
    bar = _Bar(a.command) if sys.stderr.isatty() else None
    try:
        result = COMMANDS[a.command](inputs, params, Path(a.output).resolve(), progress=bar)
    except UVPSError as exc:
        if bar:
            bar.close()
        print(f"uvps {a.command}: error: {str(exc).splitlines()[0] if str(exc) else type(exc).__name__}",
              file=sys.stderr)
        return exc.exit_code
    except Exception as exc:  # an unexpected failure: one line, the traceback in the log
        if bar:
            bar.close()
        log.debug("traceback", exc_info=True)
        print(f"uvps {a.command}: internal error: {type(exc).__name__}: {exc}".splitlines()[0], file=sys.stderr)
        return 2
    if bar:
        bar.close()
    for w in result.warnings:
        print(f"warning: {w}", file=sys.stderr)
    out = Path(a.output).resolve()
    print(f"uvps {a.command}: wrote {out}")
    report_html = out / "report.html"
    if a.command in ("demo", "run", "stats", "report") and report_html.is_file():
        print(f"report: {report_html}")
    return 0
