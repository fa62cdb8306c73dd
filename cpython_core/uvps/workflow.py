"""What the run command and batch share, above the library: the run's declared parameters, one
capture run into a run folder, and a run folder's statistics and report.

Not a command (it declares none): ``run``, ``flatfield``, ``lights``, ``normals`` (in
:mod:`uvps.commands.capture`), ``stats`` (in :mod:`uvps.commands.protrusions`) and ``batch`` call it,
so that no command calls another. It calls the library (:mod:`uvps.core`), the file layer
(:mod:`uvps.files`) and the report (:mod:`uvps.report`).
"""
from __future__ import annotations

import functools
import json
import logging
import time
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Optional

import numpy as np

# Only what declaring the commands' parameters and reading a capture need is imported here: the
# numeric core (numba, scipy, scikit-image: 0.7 s on one core) is imported by the functions that
# run it, so that a command line is parsed, and a capture's hashing started, before it
# (:func:`run_into_folder`; ``python -X importtime -m uvps run --help``).
from .core.level import LEVELS
from .core.options import LAMP_BEAMS, SAMPLE_MODES, RunOptions
from .errors import UVPSInputError
from .files.calibration import apply as apply_calibration, run_params
from .files.io import hash_inputs_meanwhile, read_capture
from .files.outputs import (CommandResult, OutputSpec, Progress, atomic_output_dir, check_output_dir, new_output_dir,
                            report, sub_progress)
from .spec import Param

if TYPE_CHECKING:
    from .files.runfolder import RunImages

log = logging.getLogger(__name__)

_RUN = RunOptions()

#: The options of the photometric-stereo stages as the commands declare them (help, Fiji labels); their
#: defaults are :class:`~uvps.core.pipeline.RunOptions`'s, the CLI flags, the bridge's keys and the Fiji
#: fields come from here.
OPTION_PARAMS = (
    Param("degree", "int", _RUN.degree, minimum=1, maximum=8, label="Degree of the lamps' drop-off fit (4 suits most captures)",
          help="Legendre degree of each image's drop-off fit (the lamp's fall-off across the field)"),
    Param("robust", "bool", _RUN.robust, label="Robust: rank-trimmed (leave out highlights and cast shadows)",
          help="rank-trimmed stereo: per pixel, leave out the darkest 25 % and brightest 10 % of samples "
               "(cast shadows, highlights; many lights); the samples rule applies as without it"),
    Param("samples", "choice", _RUN.samples, choices=SAMPLE_MODES,
          label="Samples: which the normals use (auto: by how well the fit holds)",
          help="which samples each pixel's normal is solved from: screened leaves out saturated, dark and "
               "attached-shadow samples; all keeps every one (plain least squares); auto: screened, unless that fit "
               "leaves over 25 % of the signal unexplained (the lamps and a matte surface do not hold): then all"),
    Param("integration", "choice", _RUN.integration, choices=("fc", "dct"), label="Integration method",
          help="height integration: fc (Frankot-Chellappa) or dct (Poisson, Neumann boundary)"),
    Param("level", "choice", _RUN.level, choices=LEVELS, label="Level the height (remove the best plane, or a form)",
          help="what is removed from the height map (recorded in run.json level, so the raw height is rebuilt): "
               "plane (default): the best plane, the ramp a mean normal bias of 0.1-0.2 deg gives (17.5 um/mm per "
               "deg); form: a Legendre polynomial of degree 3 too (a canvas's bow); none: the heights as integrated"),
    Param("refine_lights", "bool", _RUN.refine_lights, help="refine each lamp after the paper's equidistant solution"),
    Param("sample_pixels", "int", _RUN.sample_pixels, minimum=500, help="pixels sampled by the photometric residual (at most 1 in 16)"),
    Param("estimate_intensities", "bool", _RUN.estimate_intensities,
          help="with known lights: each lamp's intensity from the images even over the light file's own"),
    Param("black_level", "numbers", _RUN.black_level, unit="counts", minimum=0, label="Black level",
          help="the camera's black level left in the files (one number, or R,G,B): subtracted instead of "
               "measuring it from the images"),
    Param("offset", "choice", _RUN.offset, choices=("auto", "measure", "none"),
          help="additive term (black level, stray light) when none is given (black_level, dark, a raw file's "
               "levels): auto measures it from the images of more than 8 bits and subtracts it where the fit pins "
               "it; measure: also on 8-bit and linearised JPEG images; none: nothing"),
    Param("offset_degree", "int", _RUN.offset_degree, minimum=0, maximum=2,
          help="0: a constant black level; 1-2: also stray light varying smoothly across the field"),
    Param("lamp_beams", "choice", _RUN.lamp_beams, choices=LAMP_BEAMS,
          help="with lamp positions given, each image's drop-off beyond the point-light model (a lamp's beam, its "
               "aim): auto divides out what no tilt of the canvas explains (the canvas's bow kept); all divides out "
               "all of it (narrowest beams; the bow goes from the heights too); none keeps it"),
    Param("card", "path", label="Card: images of a flat fluorescent card under each lamp (needs the lights)",
          help="a flat fluorescent card on the painting under each lamp position, in the capture's order (a folder "
               "or stack, dark frame subtracted as the capture's; or a stored card): divides out each lamp's beam, "
               "power and the vignetting; needs the lamps (--lights)"),
)
#: Where the capture comes from: shared by run, flatfield, lights and normals.
CAPTURE_PARAMS = (
    Param("images", "paths", where="inputs", positional=True, required=True,
          label="Images (folder, multi-page TIFF, or files separated by ;)",
          help="image files, a folder, or one multi-page TIFF"),
    Param("lights", "path", choices=("estimate",),
          label="Lights file (.lp, or lamp positions in mm; empty = the run folder's, else estimated)",
          help="RTI .lp (directions) or positions file (.csv/.json, mm); 'estimate': from the images even where "
               "the run folder has lights.json; default: the run folder's lights.json (flatfield, normals), "
               "else estimated"),
    Param("calibration", "path", label="Calibration folder (optional: from Calibrate Lamps)",
          help="a calibration folder from `uvps calibrate`: its lamps (matched to the images by order), its dark "
               "frame unless dark is given, its pixel size unless given"),
    Param("mask", "path", label="Mask image (optional: white = the part of the painting to use)", help="mask image (non-zero = use)"),
    Param("dark", "path", label="Dark frame (optional: a picture taken with the UV lamps off)", help="a frame with the UV lamp off (or the camera's dark frame), "
          "subtracted from every image"),
    Param("pixel_size_um", "float", minimum=0, exclusive_minimum=True, unit="um", label="Pixel size on the painting (0 = from the image file)",
          help="pixel size on the painting (default: from the TIFF tags)"),
    Param("linearize", "choice", "auto", choices=("auto", "srgb", "none"),
          help="sRGB -> linear (auto: JPEG only)"),
    Param("pattern", "str", label="Pattern (of a folder's image names, e.g. uv_*.tif; empty = the lamp images)",
          help="with a folder: only its files whose names match this pattern (e.g. 'uv_*.tif'); without it, "
               "files named as a mask, dark frame, thumbnail or reference, or of another size than most, are "
               "left out"),
)
#: ``run`` adds the protrusion stages.
PROTRUSION_PARAMS = (
    Param("regions", "path", choices=("auto",), label="Regions: colour areas to count in (auto = from the colours, a label image, or empty = none)",
          help="colour-area label TIFF, or 'auto' (proposed from the albedo colour): adds detection, statistics "
               "and the report"),
    Param("detect", "bool", False, label="Detect protrusions (also without regions)", help="detect protrusions, with statistics and the report, even without regions (counted over the whole image)"),
    Param("n_areas", "int", minimum=1, help="number of colour areas for regions='auto' (default: chosen)"),
    Param("bins_um", "numbers", 100.0, unit="um", minimum=0, help="width bin of the histograms, or increasing edges"),
)

#: What ``run`` writes beyond its results (normals, albedo, gradients, height, lights, drop-off maps).
OUTPUT_PARAMS = (
    Param("flatfield_images", "bool", False, label="Flatfield images: also write them (twice the capture's size)",
          help="also write flatfield/: each image divided by its drop-off fit, one float32 TIFF per image "
               "(twice the capture's size on disk; `uvps flatfield CAPTURE -o RUN` writes them later from the "
               "run's lights.json)"),
    Param("ome_zarr", "bool", False, label="Zarr: also write OME-Zarr image pyramids (napari, BigDataViewer)",
          help="also write depth, normals and albedo (with the label images) as OME-Zarr pyramids "
               "(OME-NGFF 0.4), for napari, BigDataViewer/MoBIE and web viewers of whole paintings"),
)


def run_options(params: dict) -> RunOptions:
    """The :class:`~uvps.core.pipeline.RunOptions` among a request's (coerced) parameters; absent
    ones take their default."""
    return RunOptions(**{p.name: params[p.name] for p in OPTION_PARAMS if params.get(p.name) is not None})


def read_request_capture(inputs: dict, params: dict, progress=None):
    """The capture a request names (``inputs.images`` and the capture parameters)."""
    images = inputs["images"]
    if len(images) == 1:
        images = images[0]
    lights = None if params["lights"] == "estimate" else params["lights"]
    return read_capture(images, lights=lights, mask=params["mask"], dark=params["dark"],
                        pixel_size_um=params["pixel_size_um"], linearize=params["linearize"],
                        pattern=params.get("pattern"), progress=progress)


@dataclass(frozen=True)
class CaptureStep:
    """What a command that reads a capture and writes a run folder is (declared once, with the
    command: ``uvps.commands.capture``; ``batch`` runs :data:`RUN`). :func:`run_into_folder`
    reads only this, never the command's name.

    Attributes
    ----------
    name : str
        The command (its files' ``run.json`` record and the progress messages).
    stages : tuple
        The pipeline's stages (:func:`uvps.core.pipeline.run`).
    reuse_lights : bool
        With no lights given, take the run folder's ``lights.json`` (its ``lights`` step's lamps,
        not a second estimate that could differ; lamps it estimated divide no beams out).
    whole_run : bool
        The whole run: protrusions with ``regions`` or ``detect``, the ``flatfield`` stage only
        with ``flatfield_images``, and the whole folder (report included) built anew and
        swapped in in one step; a step (False) moves its files into the folder one by one.
    """

    name: str
    stages: tuple
    reuse_lights: bool = False
    whole_run: bool = False


RUN = CaptureStep("run", ("flatfield", "normals", "height"), whole_run=True)
FLATFIELD = CaptureStep("flatfield", ("flatfield",), reuse_lights=True)
LIGHTS = CaptureStep("lights", ())
NORMALS = CaptureStep("normals", ("normals",), reuse_lights=True)
#: Step-by-step commands that take the run folder's ``lights.json`` when no lights are given.
REUSE_LIGHTS = tuple(s.name for s in (RUN, FLATFIELD, LIGHTS, NORMALS) if s.reuse_lights)




def _lights_source(path) -> Optional[str]:
    """The ``source`` a run folder's ``lights.json`` records (None when unreadable)."""
    try:
        return json.loads(Path(path).read_text()).get("source")
    except (OSError, ValueError, AttributeError):
        return None


def run_into_folder(step: CaptureStep, inputs: dict, params: dict, output_dir, *, progress: Progress = None
                    ) -> CommandResult:
    """Read a capture, run :func:`uvps.core.pipeline.run` on it and write the run folder
    (:func:`uvps.files.runfolder.write_run`): what ``run``, ``flatfield``, ``lights`` and ``normals``
    do (``step``, their declaration) and what ``batch`` does for each capture (:data:`RUN`).
    ``params`` are the command's, coerced (every declared key present)."""
    run_dir = check_output_dir(output_dir)
    t_all = time.perf_counter()
    params, cal = run_params(params)     # the calibration's lamps, dark frame, pixel size
    if cal is None and step.reuse_lights:
        params = _folder_lights(run_dir, params)
    if step.whole_run and params.get("regions") not in (None, "auto"):
        from .files.tables import check_region_files
        check_region_files(params["regions"])      # a typo of auto, before the images are read
    capture = read_request_capture(inputs, params, sub_progress(progress, 0.0, 0.1))
    if cal is not None:
        capture = apply_calibration(cal, capture)
    # run.json's input hashes, made on the other core while this one imports the numeric core and runs
    hashes = hash_inputs_meanwhile(capture)
    from .core.pipeline import given_lights, run
    from .files.cards import load_card
    from .files.tables import load_regions
    protrusions = step.whole_run and bool(params.get("regions") or params.get("detect"))
    regions = params.get("regions") if protrusions else None
    if regions is not None and regions != "auto":
        # a label image or masks, read before the run computes (and sized as the capture)
        regions = load_regions([Path(p) for p in regions] if isinstance(regions, (list, tuple)) else Path(regions),
                               shape=capture.images.shape[1:3])
    todo = step.stages
    if step.whole_run and not params.get("flatfield_images"):
        # the flat-fielded images are twice the capture on disk (15 GB for 10000 x 8000 x 16) and
        # 4.3 of a 4000 x 3000 run's 16 s; the normals divide by the same drop-off in memory
        todo = tuple(s for s in step.stages if s != "flatfield")
    card = None
    if params.get("card"):
        # the card's images with the capture's dark frame subtracted, as the capture's were
        card = load_card(params["card"], lights=given_lights(capture), pixel_size_um=capture.pixel_size_um,
                         dark=params["dark"], linearize=params["linearize"])
    result = run(capture, run_options(params), stages=todo + (("protrusions",) if protrusions else ()),
                 dark_given=params["dark"] is not None, regions=regions, card=card,
                 n_areas=params.get("n_areas"), progress=sub_progress(progress, 0.1, 0.9))
    if cal is not None:
        _with_calibration(result, cal)
    out = _write_folder(step, run_dir, result, params, protrusions, progress, inputs=hashes)
    out.diagnostics["lights_file"] = params["lights"] if cal is None else str(cal.lights)
    out.diagnostics["elapsed_s"] = round(time.perf_counter() - t_all, 3)
    report(progress, 1.0, f"{step.name}: done")
    return out


def _folder_lights(run_dir: Path, params: dict) -> dict:
    """A step's params with the run folder's ``lights.json`` when none are given (step by step:
    the lamps of the folder's ``lights`` step, not a second estimate that could differ, and costs
    the most time)."""
    if params["lights"] is not None or not (run_dir / "lights.json").is_file():
        return params
    params = {**params, "lights": str(run_dir / "lights.json")}
    log.info("lights from %s (the run folder's; give lights to override)", params["lights"])
    if _lights_source(run_dir / "lights.json") == "estimated":
        # lamps fitted to these images' own drop-off: nothing beyond their model to divide out, as in
        # `run`, which estimates them and divides nothing (the steps give the whole run's normals)
        params = {**params, "lamp_beams": "none"}
    return params


def _with_calibration(result, cal) -> None:
    """Record the calibration in the run's diagnostics and its relief's origin (in place)."""
    result.diagnostics["calibration"] = cal.summary()
    if result.relief:
        result.relief = {**result.relief, "lamps": "calibration",
                         "reason": f"the lamps come from the calibration {cal.folder} "
                                   f"({result.diagnostics['calibration'].get('route')}), which fixes "
                                   "their elevation and so the heights' scale"}


def _write_folder(step: CaptureStep, run_dir: Path, result, params: dict, protrusions: bool,
                  progress, *, inputs=None) -> CommandResult:
    """Write the run's files into ``run_dir``: a step's moved in one by one; the whole run's (report
    included) built in a new folder that replaces the old one in one step, so that a run folder is
    never a mixture of two runs."""
    from .files.runfolder import manual_work, set_aside_for_step, set_aside_manual_work, write_run

    if not step.whole_run:
        # a step that rewrites the albedo or the height in place sets the manual work measured on them
        # aside as a whole run does; flatfield and lights alone leave albedo and height as they are
        rewrites = result.stereo is not None or result.height is not None
        with atomic_output_dir(run_dir) as tmp:
            kept = set_aside_for_step(run_dir, tmp, step=step.name) if rewrites else None
            outputs = write_run(tmp, result, command=step.name, params=params, final=run_dir,
                                progress=sub_progress(progress, 0.9, 0.95), inputs=inputs)
        out = CommandResult(outputs, dict(result.diagnostics), list(result.warnings))
        if kept is not None:
            kept_aside(run_dir, run_dir / kept.relative_to(tmp), out, step=step.name)
        return out
    # the manual work of the earlier run moves aside with the run it was measured on
    # (earlier/<date>_<run id>/): nothing a user made is lost by a re-run
    with new_output_dir(run_dir, carry_over=carried_over) as new:
        kept = set_aside_manual_work(run_dir, new)
        outputs = write_run(new, result, command=step.name, params=params, final=run_dir,
                            progress=sub_progress(progress, 0.9, 0.95), inputs=inputs)
        out = CommandResult(outputs, dict(result.diagnostics), list(result.warnings))
        if protrusions:
            out = _statistics_and_report(new, result, params, out, sub_progress(progress, 0.95, 1.0))
            for o in out.outputs:
                if Path(o.path).is_relative_to(new):
                    o.path = str(run_dir / Path(o.path).relative_to(new))
    if kept is not None:
        out.diagnostics["earlier_manual_work"] = str(run_dir / kept.relative_to(new))
        out.warnings.append(f"the manual work in {run_dir} ({', '.join(manual_work(kept))}) was measured on the "
                            f"earlier run: kept with that run in {run_dir / kept.relative_to(new)}; this run "
                            "has no manual count of its own until one is made on it")
    return out


def kept_aside(run_dir: Path, kept: Path, out: CommandResult, *, step: str) -> None:
    """After a step's :func:`uvps.files.runfolder.set_aside_for_step`: the manual files leave ``run_dir``
    (kept in ``kept``, under ``earlier/``), and the result says where, in one warning."""
    from .files.runfolder import STEP_REWRITES, drop_manual_work, manual_work

    drop_manual_work(run_dir)
    what = STEP_REWRITES[step]
    out.diagnostics["earlier_manual_work"] = str(kept)
    out.warnings.append(f"the manual work in {run_dir} ({', '.join(manual_work(kept))}) was measured on the "
                        f"{what} that `{step}` replaced: kept with the run it was measured on in {kept}; the new "
                        f"{what} has no manual count of its own until one is made on it")


@functools.cache
def run_owned() -> frozenset:
    """What a run folder holds that ``run`` owns: every file of :data:`uvps.files.runfolder.FILES`, the
    report's figures and ``relight.tif`` (made from the run's normals). A new ``run`` replaces them all:
    those of an earlier run (its flat-field, OME-Zarr stores) were made under its lamps and heights; the
    manual work among them (the wand's count, a comparison) moves to ``earlier/<date>_<run id>/`` with the
    files it was measured on (:func:`uvps.files.runfolder.set_aside_manual_work`). Anything else in the
    folder (the user's clicks or notes, ``earlier/``, the demo's ``capture/``) is carried into the new
    folder unchanged."""
    from .files.runfolder import FILES

    return frozenset(f for f, *_ in FILES.values()) | {"figures", "relight.tif"}


def carried_over(name: str) -> bool:
    """Whether a new ``run`` keeps the entry ``name`` of the folder it replaces (see :func:`run_owned`;
    leftovers of an interrupted write, hidden ``.*.tmp`` names, are not kept)."""
    return name not in run_owned() and not (name.startswith(".") and (".tmp" in name or ".uvps-new-" in name))


def _statistics_and_report(run_dir, result, params, out, progress):
    """``run`` with colour areas or detection: statistics and the report, from the arrays in memory
    (the files just written hold the same float32 values)."""
    from .files.runfolder import RunImages

    st = result.stereo
    images = RunImages(st.albedo, result.height.height_um, st.normals, result.capture.pixel_size_um,
                       result.height.height_um.shape)
    r = statistics_and_report(run_dir, images, bins_um=params["bins_um"], progress=progress)
    out.outputs += r.outputs
    out.diagnostics["stats"] = r.diagnostics
    out.warnings += r.warnings
    return out


def regions_for(spec, run_dir: Path, images, *, n_areas=None, seed=0):
    """Colour areas from ``params.regions``: a label TIFF path, "auto", or None (the run's
    ``regions_labels.tif`` when present, else None). Returns (RegionMap or None, proposed?)."""
    from .core.regions import propose_regions
    from .files.tables import load_regions

    if spec is None:
        spec = run_dir / "regions_labels.tif"
        if not spec.is_file():
            return None, False
    if isinstance(spec, str) and spec == "auto":
        if images.albedo is None:
            raise UVPSInputError("regions='auto' needs the run's albedo.tif")
        return propose_regions(images.albedo, pixel_size_um=images.pixel_size_um, n_areas=n_areas, seed=seed), True
    if isinstance(spec, (list, tuple)):
        return load_regions([Path(p) for p in spec], shape=images.shape), False
    return load_regions(Path(spec), shape=images.shape), False



def _stats_and_csv(tmp: Path, run_dir: Path, regions, px: float, bins_um, warnings: list,
                   path: Optional[Path] = None):
    from .core.measure import empty_table
    from .core.regions import region_statistics
    from .files.tables import read_protrusions_csv, write_regions_csv

    # areas are usually registered before detection: no table yet means counts of 0, not a warning
    path = path or run_dir / "protrusions.csv"
    table = read_protrusions_csv(path) if path.is_file() else empty_table()
    stats = region_statistics(table, regions, pixel_size_um=px, bins_um=bins_um)
    write_regions_csv(tmp / "regions.csv", stats)
    return stats



def statistics(run_dir, *, table=None, regions=None, bins_um=100.0, pixel_size_um=None, pdf=False,
               images: Optional[RunImages] = None, progress: Progress = None) -> CommandResult:
    """Per-area statistics (``regions.csv``) and the report (``report.html``, ``figures/``).

    ``regions``: a label TIFF, default the run's ``regions_labels.tif``, else the whole image;
    ``table``: default ``protrusions.csv``, else ``protrusions_manual.csv`` when only the wand ran.
    """
    from .core.regions import whole_image
    from .files.runfolder import read_run

    run_dir = Path(run_dir)
    warnings = []
    if table:
        table_path = Path(table)
        table_path = table_path if table_path.is_absolute() else run_dir / table_path
        if not table_path.is_file():
            raise UVPSInputError(f"table: protrusion CSV {table_path} does not exist")
    elif (run_dir / "protrusions.csv").is_file():
        table_path = run_dir / "protrusions.csv"
    elif (run_dir / "protrusions_manual.csv").is_file():
        table_path = run_dir / "protrusions_manual.csv"
        warnings.append("no protrusions.csv: statistics of the wand count "
                        "(protrusions_manual.csv)")
    else:
        raise UVPSInputError(f"run folder {run_dir} has no protrusions.csv; run the 'detect' or "
                             "'wand' command first")
    if images is None:
        images = read_run(run_dir, need=(), pixel_size_um=pixel_size_um)
    if images.shape is None:
        raise UVPSInputError(f"run folder {run_dir} has no albedo.tif or depth.tif to size the "
                             "colour areas")
    regions, _ = regions_for(regions, run_dir, images)
    if regions is None:
        regions = whole_image(images.shape)
        warnings.append("no colour areas (regions_labels.tif): statistics over the whole image")
    from .report.page import print_pdf, write_report   # here: a run without detection never imports the report

    report(progress, 0.05, "statistics")
    with atomic_output_dir(run_dir) as tmp:
        stats = _stats_and_csv(tmp, run_dir, regions, images.pixel_size_um,
                               bins_um, warnings, table_path)
    html = write_report(run_dir, stats=stats, regions=regions, warnings=list(warnings), images=images,
                        table=table_path, progress=sub_progress(progress, 0.1, 1.0))
    figures = sorted((run_dir / "figures").glob("*.png"))
    outputs = [OutputSpec("regions", str(run_dir / "regions.csv"), kind="table", units="cm^-2"),
               OutputSpec("report", str(html), kind="html")]
    if pdf:
        report(progress, 0.98, "printing the report to PDF")
        outputs.append(OutputSpec("report_pdf", str(print_pdf(html)), kind="pdf"))
    outputs += [OutputSpec(f"figure_{p.stem}", str(p), kind="image", axes="YXS", dtype="uint8")
                for p in figures]
    diagnostics = {r.name: {"count": r.count, "area_cm2": r.area_cm2,
                            "density_per_cm2": r.density_per_cm2} for r in stats.rows}
    return CommandResult(outputs, {"areas": diagnostics, "outside": stats.outside,
                                   "table": str(table_path),
                                   "edges_um": [float(e) if np.isfinite(e) else None
                                                for e in stats.edges_um]}, warnings)


def statistics_and_report(run_dir, images: RunImages, *, bins_um=100.0, progress: Progress = None) -> CommandResult:
    """:func:`statistics` on a run folder whose images the caller holds in memory (``run`` with
    detection has just written them), without reading the TIFFs back."""
    return statistics(run_dir, bins_um=bins_um, images=images, progress=progress)
