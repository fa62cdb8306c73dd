"""The capture commands (run, flatfield, lights, normals) and integrate, relight, demo: each declared
once, as a :class:`uvps.spec.CommandSpec` beside its function (registered by :mod:`uvps.commands`).

A spec is called as ``spec(inputs, params, output_dir, progress=None)`` and returns a
:class:`~uvps.files.outputs.CommandResult` (docs/architecture.md, "Commands").

The numeric core is imported by the commands' functions, not here: declaring the commands (parsing
a command line, ``uvps spec``) imports no numba or scipy (:mod:`uvps.workflow`).
"""
from __future__ import annotations

import dataclasses
import logging

import numpy as np

from ..files.io import write_imagej_tiff
from ..files.outputs import CommandResult, OutputSpec, atomic_output_dir, check_output_dir, report, sub_progress
from ..spec import CommandSpec, Param
from ..workflow import (CAPTURE_PARAMS, FLATFIELD, LIGHTS, NORMALS, OPTION_PARAMS, OUTPUT_PARAMS,
                        PROTRUSION_PARAMS, RUN, CaptureStep, kept_aside, run_into_folder)

log = logging.getLogger(__name__)

_LIGHT_OPTIONS = tuple(p for p in OPTION_PARAMS if p.name not in ("robust", "samples", "integration", "level"))


def _capture_command(step: CaptureStep):
    def cmd(inputs, params, output_dir, *, progress=None):
        return run_into_folder(step, inputs, params, output_dir, progress=progress)

    cmd.__name__ = f"cmd_{step.name}"
    cmd.__doc__ = (f"``{step.name}``: read a capture and write {', '.join(step.stages) or 'the lights'} "
                   "into the run folder.")
    return cmd


def _cmd_integrate(inputs, params, output_dir, *, progress=None):
    """``integrate``: height in um from ``<run>/normals.tif``."""
    from ..core.integrate import integrate_normals
    from ..core.level import level_height
    from ..core.pipeline import integration_diagnostics
    from ..files import runfolder

    run_dir = check_output_dir(output_dir)
    images = runfolder.read_run(run_dir, need=("normals",), pixel_size_um=params["pixel_size_um"])
    report(progress, 0.2, "integrating")
    res = integrate_normals(images.normals, pixel_size_um=images.pixel_size_um, method=params["integration"])
    # levelled as a run's (uvps.core.level); the run.json of the folder records what was removed
    _, level = level_height(res.height_um, method=params["level"], pixel_size_um=images.pixel_size_um,
                            out=res.height_um)
    with atomic_output_dir(run_dir) as tmp:
        # a manual count measured its heights on the depth.tif replaced here: it moves aside with it
        kept = runfolder.set_aside_for_step(run_dir, tmp, step="integrate")
        runfolder.write_height(tmp, res.height_um, images.pixel_size_um, res.method,
                               relief=runfolder.relief_in(run_dir), level=level)
        runfolder.set_level(run_dir, level, into=tmp)
    report(progress, 1.0, "integrate: done")
    diagnostics = {**integration_diagnostics(res), "level": level.to_json()}
    out = CommandResult([runfolder.output_spec(run_dir, "depth")], diagnostics, [])
    if kept is not None:
        kept_aside(run_dir, run_dir / kept.relative_to(tmp), out, step="integrate")
    return out


def _cmd_relight(inputs, params, output_dir, *, progress=None):
    """``relight``: the surface under a virtual raking light (``azimuth_deg``, ``elevation_deg``)."""
    from ..core.relight import relight
    from ..files import runfolder

    run_dir = check_output_dir(output_dir)
    warnings = []
    images = runfolder.read_run(run_dir, need=("normals",), pixel_size_um=params["pixel_size_um"])
    albedo = images.albedo
    if albedo is None:
        warnings.append("no albedo.tif: relit with a uniform albedo")
        albedo = np.ones(images.normals.shape[:2], np.float32)
    img = relight(images.normals, albedo, azimuth_deg=params["azimuth_deg"], elevation_deg=params["elevation_deg"],
                  ambient=params["ambient"])
    axes = "CYX" if img.ndim == 3 else "YX"
    with atomic_output_dir(run_dir) as tmp:
        write_imagej_tiff(tmp / "relight.tif", np.moveaxis(img, -1, 0) if img.ndim == 3 else img, axes=axes,
                          pixel_size_um=images.pixel_size_um)
    return CommandResult([OutputSpec("relight", str(run_dir / "relight.tif"), kind="image", axes=axes,
                                     dtype="float32", units="counts")],
                         {"azimuth_deg": params["azimuth_deg"], "elevation_deg": params["elevation_deg"]}, warnings)


#: The demo's pixel: 600 x 800 px of 30 um show the 18 x 24 mm field a real capture has (the lamps'
#: distance and elevation are told apart by the field's size, not its pixels; at 15 um the 9 x 12 mm
#: crop leaves heights uncertain by ~25 % and the light estimate crawls along its valley).
DEMO_PIXEL_UM = 30.0


def _cmd_demo(inputs, params, output_dir, *, progress=None):
    """``demo``: the calibrated route on synthetic captures: a painting capture written to
    ``<run>/capture/``, two glossy spheres under the same lamps to ``<run>/spheres/``, ``uvps
    calibrate`` on them into ``<run>/calibration/``, and the whole run with that calibration."""
    from ..commands import COMMANDS       # calibrate is declared in uvps.commands.calibrate
    # the generator is test data: imported when the demo runs, not with every command
    from ..testing.synthetic import make_capture, write_capture
    from ..testing.synthetic_spheres import SphereSpec, make_sphere_capture, write_sphere_capture

    run_dir = check_output_dir(output_dir)
    report(progress, 0.0, "demo: making a synthetic capture")
    cap = make_capture(shape=tuple(params["shape"]), n_lights=params["n_lights"], seed=params["seed"],
                       pixel_size_um=params["pixel_size_um"])
    run_dir.mkdir(parents=True, exist_ok=True)
    cap_dir = run_dir / "capture"
    write_capture(cap, cap_dir)
    images = sorted(cap_dir.glob("uv_*.tif"))
    report(progress, 0.05, "demo: the sphere capture and uvps calibrate")
    sphere_dir, cal_dir = run_dir / "spheres", run_dir / "calibration"
    # two glossy spheres in opposite corners (RTI practice), 2.5 mm or a tenth of the field's height
    r_mm = min(2.5, 0.1 * params["shape"][0] * params["pixel_size_um"] / 1000.0)
    spheres = (SphereSpec("glossy", (0.15, 0.2), r_mm), SphereSpec("glossy", (0.85, 0.8), r_mm))
    write_sphere_capture(make_sphere_capture(cap, spheres, seed=params["seed"]), sphere_dir, truth=False)
    COMMANDS["calibrate"]({"spheres": [str(sphere_dir)]}, {"pixel_size_um": float(params["pixel_size_um"])},
                          cal_dir, progress=sub_progress(progress, 0.05, 0.15))
    # the colour areas are proposed from the albedo, as a user would accept them (the truth stays unread)
    result = SPECS_BY_NAME["run"]({"images": [str(p) for p in images]},
                                  {"regions": "auto", "bins_um": 100.0, "calibration": str(cal_dir)},
                                  run_dir, progress=sub_progress(progress, 0.15, 1.0))
    result.outputs.insert(0, OutputSpec("calibration", str(cal_dir), kind="folder"))
    result.outputs.insert(0, OutputSpec("capture", str(cap_dir), kind="folder"))
    result.diagnostics["truth_light_positions_mm"] = cap.light_positions_mm.tolist()
    return result


# ``run`` reads no run folder's lights.json: its lights help says only what it does
_RUN_LIGHTS = tuple(dataclasses.replace(
    p, label="Lights file (.lp, or lamp positions in mm; empty = estimated from the images)",
    help="the lamps: an RTI .lp file (directions), a positions file (.csv/.json, mm from the image centre) or a "
         "lights.json; default: estimated from the images") if p.name == "lights" else p for p in CAPTURE_PARAMS)

_PX_OVERRIDE = Param("pixel_size_um", "float", minimum=0, exclusive_minimum=True, unit="um",
                     help="pixel size (default: the run's TIFF calibration)")
_STEREO = tuple(p for p in OPTION_PARAMS if p.name in ("robust", "samples", "integration", "level"))

SPECS = (
    CommandSpec("run", "the whole pipeline on a capture", _capture_command(RUN),
                menu="Run Whole Pipeline", params=_RUN_LIGHTS + OPTION_PARAMS + PROTRUSION_PARAMS + OUTPUT_PARAMS,
                description="Lights (estimated or given), flat-field, normals and albedo, height; with regions or "
                            "detect also colour areas, protrusions, statistics and report.html (without either, "
                            "no protrusions and no report). The flat-fielded images themselves are written with "
                            "--flatfield-images (or later by `uvps flatfield`).",
                output_note="the whole folder is replaced by this run's in one step, keeping files uvps does not "
                            "write"),
    CommandSpec("flatfield", "drop-off fits and flat-fielded images", _capture_command(FLATFIELD),
                menu="Flat Field", params=CAPTURE_PARAMS + _LIGHT_OPTIONS),
    CommandSpec("lights", "light directions and positions", _capture_command(LIGHTS),
                menu="Estimate Lights", params=CAPTURE_PARAMS + _LIGHT_OPTIONS),
    CommandSpec("normals", "normals, albedo and gradients", _capture_command(NORMALS),
                menu="Normals and Albedo", params=CAPTURE_PARAMS + tuple(p for p in OPTION_PARAMS if p.name != "level")),
    CommandSpec("integrate", "height from <run>/normals.tif", _cmd_integrate,
                menu="Integrate Height", params=tuple(p for p in _STEREO if p.name in ("integration", "level")) + (_PX_OVERRIDE,)),
    CommandSpec("relight", "render under a virtual raking light", _cmd_relight, menu="Relight", params=(
        Param("azimuth_deg", "float", 315.0, unit="deg", label="Azimuth (from image right, counter-clockwise)", help="the light's azimuth, "
              "counter-clockwise from +x (right)"),
        Param("elevation_deg", "float", 15.0, unit="deg", minimum=0, exclusive_minimum=True, maximum=90,
              label="Elevation (above the canvas)", help="the light's elevation above the canvas"),
        Param("ambient", "float", 0.0, minimum=0, help="ambient term added to the shading"),
        _PX_OVERRIDE)),
    CommandSpec("demo", "synthetic captures (a painting, two spheres), their calibration and the whole run",
                _cmd_demo, output="folder",
                output_default="uvps_demo", params=(
                    Param("shape", "shape", (600, 800), help="rows and columns of the synthetic capture"),
                    Param("n_lights", "int", 12, minimum=3, help="number of lamps"),
                    Param("seed", "int", 0, help="random seed of the synthetic painting"),
                    Param("pixel_size_um", "float", DEMO_PIXEL_UM, minimum=0, exclusive_minimum=True, unit="um",
                          help="pixel size of the synthetic capture"))),
)
SPECS_BY_NAME = {s.name: s for s in SPECS}
# the commands as callables that check their request first (``cmd_run(inputs, params, run_dir)``)
cmd_run, cmd_flatfield, cmd_lights, cmd_normals, cmd_integrate, cmd_relight, cmd_demo = (
    SPECS_BY_NAME[n] for n in ("run", "flatfield", "lights", "normals", "integrate", "relight", "demo"))
