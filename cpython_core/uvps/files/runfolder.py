"""The run folder: its file names, writing a run into it, reading it back, and ``uvps info``.

Every command writes and reads a run folder through this module (docs/architecture.md, "Output folder
of a run"): file names, axes, pixel size and channel layout are decided here once. Images are
ImageJ TIFFs with the pixel size in um; channel-first on disk (``CYX``), channel-last in memory
(``(M, N, C)``).
"""
from __future__ import annotations

import hashlib
import json
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Optional

import numpy as np
import tifffile

from .. import __version__
from ..errors import UVPSInputError, check_pixel_size
from ..core.flatfield import flatfield
from ..core.integrate import gradients_from_normals
from .io import BAND_BYTES, Capture, imagej_tiff_writer, input_hashes, read_tiff, write_imagej_tiff
from .tables import not_counted, write_label_tiff, write_protrusions_csv
from .omezarr import write_ome_zarr
from ..core.stack import release_caches, row_bands
from ..core.threads import default_threads, map_bands
from .outputs import OutputSpec, Progress, _link_or_copy, _link_tree, report, write_json_atomic
from ..core.regions import region_statistics
from .tables import write_regions_csv

#: The files of a run folder: name -> (file, kind, axes, units). One place for every file name.
FILES = {
    "lights": ("lights.json", "json", None, None),
    "dropoff": ("dropoff.tif", "image", "ZYX", "1"),
    "flatfield": ("flatfield", "folder", None, "counts"),
    "normals": ("normals.tif", "image", "CYX", "1"),
    "albedo": ("albedo.tif", "image", None, "counts"),
    "gradients": ("gradients.tif", "image", "CYX", "1"),
    "depth": ("depth.tif", "image", "YX", "um"),
    "protrusions": ("protrusions.csv", "table", None, "um"),
    "protrusions_labels": ("protrusions_labels.tif", "image", "YX", "label"),
    "protrusions_manual": ("protrusions_manual.csv", "table", None, "um"),
    "protrusions_manual_labels": ("protrusions_manual_labels.tif", "image", "YX", "label"),
    "regions_labels": ("regions_labels.tif", "image", "YX", "label"),
    "regions": ("regions.csv", "table", None, "cm^-2"),
    "run": ("run.json", "json", None, None),
    "report": ("report.html", "html", None, None),
    "comparison": ("comparison.csv", "table", None, "cm^-2"),
    "depth_zarr": ("depth.ome.zarr", "folder", "YX", "um"),
    "normals_zarr": ("normals.ome.zarr", "folder", "CYX", "1"),
    "albedo_zarr": ("albedo.ome.zarr", "folder", None, "counts"),
}
#: What a person made in a run folder: the wand's count and outlines, a comparison and its map. A new
#: ``run`` does not replace them: they move aside with the run they were measured on
#: (:func:`set_aside_manual_work`). The first three say that there is manual work.
MANUAL_FILES = ("protrusions_manual.csv", "protrusions_manual_labels.tif", "comparison.csv",
                "figures/comparison_map.png")
#: What manual work was measured on, moved aside with it: the run's record, its images (the albedo
#: outlined, the height measured) and the automated count and areas a comparison used.
MEASURED_ON = ("run.json", "lights.json", "albedo.tif", "depth.tif", "normals.tif", "protrusions.csv",
               "protrusions_labels.tif", "regions_labels.tif", "regions.csv", "report.html")
#: What each step that rewrites it in place replaces of what manual work was measured on
#: (:func:`set_aside_for_step`): ``normals`` the albedo outlined, ``integrate`` the height measured.
STEP_REWRITES = {"normals": "albedo", "integrate": "height"}
#: The subfolder of a run folder that holds earlier runs' manual work, one folder each.
EARLIER = "earlier"
#: The record of one set-aside folder.
EARLIER_RECORD = "earlier.json"

#: The command that writes each image a later command needs (for the "run X first" message).
MADE_BY = {"albedo": "normals", "normals": "normals", "depth": "integrate"}


def output_spec(run_dir, name: str, *, axes: Optional[str] = None) -> OutputSpec:
    """The :class:`~uvps.files.outputs.OutputSpec` of run-folder file ``name`` (a key of :data:`FILES`)."""
    file, kind, ax, units = FILES[name]
    path = Path(run_dir) / file
    dtype = None
    if kind == "image":
        dtype = "float32" if units != "label" else _tiff_dtype(path)
    elif kind == "folder":
        dtype = "float32"
    return OutputSpec(name, str(path), kind=kind, axes=axes or ax, dtype=dtype, units=units)


def _tiff_dtype(path: Path) -> str:
    with tifffile.TiffFile(path) as tif:
        return str(tif.series[0].dtype)


# ------------------------------------------------------------------------------------------------
# run.json
# ------------------------------------------------------------------------------------------------

@dataclass
class RunLog:
    """What run.json records: parameters, inputs, timings, warnings."""

    command: str
    params: dict
    inputs: list = field(default_factory=list)
    timings_s: dict = field(default_factory=dict)
    warnings: list = field(default_factory=list)
    diagnostics: dict = field(default_factory=dict)
    relief: Optional[dict] = None      # the relief's scale (:func:`relief_of`); None: not a run of a capture
    level: Optional[dict] = None       # what was removed from depth.tif (:meth:`uvps.core.level.Levelling.to_json`)

    def time(self, stage, t0):
        self.timings_s[stage] = round(time.perf_counter() - t0, 3)

    def write(self, path):
        data = {"version": __version__, **asdict(self)}
        for key in ("relief", "level"):
            if data[key] is None:
                del data[key]
        write_json_atomic(path, data)


#: run.json ``relief`` of a folder that has none (written before relief was recorded, or made by a
#: command that does not estimate lamps): heights were always reported in micrometres.
_RELIEF_DEFAULT = {"scale": "absolute", "lamps": None, "reason": "no relief recorded (an older run folder)"}


def relief_of(run_json: Optional[dict]) -> dict:
    """The relief's scale of a run: run.json's ``relief`` object, the one reader of it.

    Returns ``{"scale": "absolute" | "relative", "lamps": "calibration" | "positions" | "directions" |
    "estimated" | None, "reason": str}``. "relative": the lamps' elevation, and so the heights' scale,
    is not pinned (lamps estimated from the images that do not determine it): normals, albedo, counts
    and widths hold, heights in micrometres do not. A missing or malformed entry reads as "absolute"
    (older folders).

    Example
    -------
    >>> relief_of({"relief": {"scale": "relative", "lamps": "estimated", "reason": "..."}})["scale"]
    'relative'
    >>> relief_of({})["scale"]
    'absolute'
    """
    relief = (run_json or {}).get("relief") or {}
    if not isinstance(relief, dict) or relief.get("scale") not in ("absolute", "relative"):
        return dict(_RELIEF_DEFAULT)
    return {"scale": relief["scale"], "lamps": relief.get("lamps"), "reason": str(relief.get("reason", ""))}


def run_record(run_dir) -> Optional[dict]:
    """The run folder's ``run.json`` as a dict; None when it has none or it is unreadable (the one
    tolerant reader of it: :func:`relief_in`, :func:`level_of`, :func:`set_level`, the set-aside)."""
    try:
        data = json.loads((Path(run_dir) / FILES["run"][0]).read_text(encoding="utf-8"))
    except (OSError, ValueError):       # ValueError: UnicodeDecodeError and json.JSONDecodeError
        return None
    return data if isinstance(data, dict) else None


def relief_in(run_dir) -> dict:
    """:func:`relief_of` the run folder's ``run.json`` (absolute when it has none or it is unreadable)."""
    return relief_of(run_record(run_dir))


def is_relative(relief: Optional[dict]) -> bool:
    """True when ``relief`` (a :func:`relief_of` dict, or None) says the heights have no scale."""
    return bool(relief) and relief.get("scale") == "relative"


# ------------------------------------------------------------------------------------------------
# writing
# ------------------------------------------------------------------------------------------------

def write_run(folder: Path, result, *, command: str, params: dict, final: Optional[Path] = None, warnings=(),
              progress: Progress = None, inputs=None) -> list:
    """Write a :class:`uvps.core.pipeline.RunResult` into ``folder``.

    ``folder`` is usually the temporary folder of :func:`uvps.files.outputs.atomic_output_dir`, moved to
    the run folder ``final`` afterwards. ``params`` (the request's) and ``warnings`` go into
    ``run.json`` with the result's diagnostics and timings. ``inputs``: the input files' hashes
    (:func:`uvps.files.io.input_hashes`), a list or an :class:`uvps.files.io.InputHashes` (hashed while the
    run computed: :func:`uvps.files.io.hash_inputs_meanwhile`); None hashes them here. Returns the
    :class:`~uvps.files.outputs.OutputSpec` of every file written, with its path under ``final``.

    The lights, normals, albedo, gradients and depth files are written two at a time (:data:`WRITERS`
    threads: tifffile's writes and numpy's copies release the GIL); each file is the one a single thread
    writes.
    """
    final = Path(final or folder)
    cap = result.capture
    relief = getattr(result, "relief", None) or None
    names = ["lights", "dropoff"]
    if "flatfield" in result.stages:
        write_flatfield(folder, cap, result.lights, progress=progress)
        release_caches(cap.images)        # the stack read again: what its views made for it is dropped
        names.append("flatfield")
    jobs = [lambda: write_lights(folder, cap, result.lights)]
    if result.stereo is not None:
        jobs += stereo_writers(folder, result.stereo, cap.pixel_size_um)
        names += ["normals", "albedo", "gradients"]
    if result.height is not None:
        jobs.append(lambda: write_height(folder, result.height.height_um, cap.pixel_size_um, result.height.method,
                                         relief=relief, level=getattr(result, "level", None)))
        names.append("depth")
    _write_all(jobs)
    if result.protrusions is not None:
        names += write_protrusions(folder, result.protrusions, cap.pixel_size_um,
                                   bins_um=params.get("bins_um") or 100.0, relief=relief)
    if params.get("ome_zarr") and (result.stereo is not None or result.height is not None):
        # from the TIFFs just written (memory-mapped): the stores hold the same float32 values
        stores = write_ome_zarr(folder, pixel_size_um=cap.pixel_size_um)
        names += [s.name.split(".")[0] + "_zarr" for s in stores]
    log = RunLog(command, dict(params), warnings=list(warnings) + list(result.warnings))
    if inputs is None:
        inputs = input_hashes(cap)
    log.inputs = inputs.result() if hasattr(inputs, "result") else inputs
    log.params.update({**asdict(result.options), "pixel_size_um": cap.pixel_size_um,
                       "image_shape": list(cap.images.shape[1:]), "bit_depth": cap.bit_depth})
    log.timings_s = dict(result.timings_s)
    log.diagnostics = dict(result.diagnostics)
    log.relief = relief
    if getattr(result, "level", None) is not None:
        log.level = result.level.to_json()
    log.write(folder / "run.json")
    names.append("run")
    # dtypes of label images are read from the files just written
    return [_spec_in(final, folder, n) for n in names]


#: Threads writing a run folder's files (each file by one of them).
WRITERS = 2


def _write_all(jobs) -> None:
    """Call every job (a file's writer), :data:`WRITERS` at a time (at most ``UVPS_THREADS``); the first
    error is raised once all have ended."""
    workers = min(len(jobs), default_threads(WRITERS))
    if workers <= 1:
        for job in jobs:
            job()
        return
    with ThreadPoolExecutor(workers, thread_name_prefix="uvps-write") as pool:
        futures = [pool.submit(job) for job in jobs]
    for f in futures:
        f.result()


def _spec_in(final: Path, written: Path, name: str) -> OutputSpec:
    spec = output_spec(written, name)
    spec.path = str(final / FILES[name][0])
    return spec


def write_lights(folder: Path, capture: Capture, lights) -> dict:
    """``lights.json`` and ``dropoff.tif`` (the fitted drop-off maps, at most 1024 px wide)."""
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
    M, N = capture.images.shape[1:3]
    step = max(1, int(np.ceil(max(M, N) / 1024)))
    rows, cols = np.arange(0, M, step), np.arange(0, N, step)
    maps = np.stack([f.evaluate(rows, cols) for f in lights.fits]).astype(np.float32)
    write_imagej_tiff(folder / "dropoff.tif", maps, axes="ZYX", pixel_size_um=capture.pixel_size_um * step,
                      labels=[Path(f).name for f in capture.files],
                      metadata={"Info": f"uvps drop-off maps (mean 1), sampled every {step} px"})
    return data


def write_flatfield(folder: Path, capture: Capture, lights, *, workers: int = 2, progress: Progress = None) -> Path:
    """``flatfield/<k>_<name>.tif``: each image divided by its drop-off map, one float32 file each.

    Each file is filled band by band (:data:`uvps.files.io.BAND_BYTES` of output at a time) as it is read, one
    image per worker (``workers`` threads: numpy and the file writes release the GIL), so memory holds
    ``workers`` bands, never an image (a 10000 x 8000 RGB one is 0.96 GB as float32).
    """
    out = folder / "flatfield"
    out.mkdir(exist_ok=True)
    K, M, N = capture.images.shape[:3]
    C = capture.images.shape[3] if capture.images.ndim == 4 else 0
    shape, axes = ((C, M, N), "CYX") if C else ((M, N), "YX")

    def one(k):
        name = Path(capture.files[k].replace("#", "_")).stem
        with imagej_tiff_writer(out / f"{k:03d}_{name}.tif", shape, np.float32, axes=axes,
                                pixel_size_um=capture.pixel_size_um) as tif:
            for rows in row_bands(M, N * max(C, 1) * 4, BAND_BYTES):
                ff = flatfield(capture.images[k, rows], lights.fits[k], channels_first=True, row0=rows.start)
                tif.write((slice(None), rows) if C else rows, ff)

    # the first image alone: compiled readers (numba) are typed on their first call, never in two at once
    map_bands(lambda k: one(k.start), K, size=1, threads=workers, first_alone=True,
              each=lambda k, _: report(progress, k.stop / K, f"flat field {k.stop}/{K}"))
    return out


def write_stereo(folder: Path, res, pixel_size_um: float) -> None:
    """``normals.tif`` (3, M, N), ``albedo.tif`` ((C,) M, N) and ``gradients.tif`` (2, M, N).

    The channel-last arrays are written channel-first band by band (never transposed whole)."""
    for job in stereo_writers(folder, res, pixel_size_um):
        job()


def stereo_writers(folder: Path, res, pixel_size_um: float) -> list:
    """The writers of :func:`write_stereo`'s three files, one callable each (independent of one another)."""
    def normals():
        write_imagej_tiff(folder / "normals.tif", np.moveaxis(res.normals, -1, 0), axes="CYX",
                          pixel_size_um=pixel_size_um, labels=["nx", "ny", "nz"])

    def albedo():
        if res.albedo.ndim == 3:
            write_imagej_tiff(folder / "albedo.tif", np.moveaxis(res.albedo, -1, 0), axes="CYX",
                              pixel_size_um=pixel_size_um, labels=["R", "G", "B"][:res.albedo.shape[-1]])
        else:
            write_imagej_tiff(folder / "albedo.tif", res.albedo, axes="YX", pixel_size_um=pixel_size_um)

    def gradients_tif():
        g = gradients_from_normals(res.normals)
        with imagej_tiff_writer(folder / "gradients.tif", (2,) + g.p.shape, np.float32, axes="CYX",
                                pixel_size_um=pixel_size_um, labels=["p = dz/dx", "q = dz/dy (y up)"]) as tif:
            tif.put(0, g.p)
            tif.put(1, g.q)
    return [normals, albedo, gradients_tif]


#: ImageJ's value unit (``vunit`` in the TIFF's ImageJ description) of a height map without a scale.
RELATIVE_UNIT = "relative"


def write_height(folder: Path, height_um, pixel_size_um: float, method: str, *, relief: Optional[dict] = None,
                 level=None) -> None:
    """``depth.tif``: height in micrometres (median 0); with a relative ``relief`` (:func:`relief_of`)
    the same map labelled relative: ImageJ value unit "relative" and the Info saying why. ``level``
    (:class:`uvps.core.level.Levelling`): what was removed, said in the Info (:func:`level_words`)."""
    levelled = "" if level is None else " " + level_words(level.to_json())
    if is_relative(relief):
        meta = {"Info": f"uvps relative height ({method}), median 0: NOT micrometres.{levelled} "
                        f"{relief.get('reason', '')}", "vunit": RELATIVE_UNIT}
    else:
        meta = {"Info": f"uvps height in micrometres ({method}), median 0.{levelled}", "vunit": "um"}
    write_imagej_tiff(folder / "depth.tif", height_um, axes="YX", pixel_size_um=pixel_size_um, metadata=meta)


def level_words(level: Optional[dict]) -> str:
    """One sentence on what was removed from ``depth.tif`` (run.json ``level``), for its Info, the Log
    and ``uvps info``; "" when nothing is recorded (a folder written before levelling)."""
    if not isinstance(level, dict) or "method" not in level:
        return ""
    sx, sy = level.get("slope_x_um_per_mm"), level.get("slope_y_um_per_mm")
    plane = f"x {sx:+.3g}, y {sy:+.3g} um/mm (x right, y up)" if sx is not None and sy is not None else "?"
    method = level["method"]
    if method == "plane":
        return (f"Levelled: the best plane ({plane}) removed; raw = this + that plane (run.json level).")
    if method == "form":
        return (f"Levelled: a Legendre form of degree {level.get('degree')} removed ({level.get('removed_rms_um', 0):.3g}"
                f" um rms; best plane {plane}); raw = this + that form (run.json level).")
    return f"Not levelled (level none): the heights as integrated, best plane {plane}."


def set_level(run_dir: Path, level, *, into: Optional[Path] = None) -> None:
    """Record ``level`` (:class:`uvps.core.level.Levelling`) in the run folder's ``run.json`` (a command
    that rewrites ``depth.tif`` in a run folder: ``integrate``), written to ``into`` (the temporary
    folder ``depth.tif`` is moved in from, so the two arrive together; default ``run_dir``); nothing
    when the folder has none."""
    data = run_record(run_dir)
    if data is not None:
        data["level"] = level.to_json()
        write_json_atomic(Path(into or run_dir) / FILES["run"][0], data)


def level_of(run_dir) -> Optional[dict]:
    """run.json's ``level`` of a run folder (None: not recorded, a folder written before levelling)."""
    level = (run_record(run_dir) or {}).get("level")
    return level if isinstance(level, dict) else None


def height_unit(path) -> str:
    """The value unit of a height map written by :func:`write_height` ("um", or "relative")."""
    with tifffile.TiffFile(path) as tif:
        meta = tif.imagej_metadata or {}
    return str(meta.get("vunit", "um"))


def write_protrusions(folder: Path, prot, pixel_size_um: float, *, bins_um=100.0, relief: Optional[dict] = None) -> list:
    """``protrusions.csv``, ``protrusions_labels.tif`` and, with colour areas (proposed or given),
    ``regions_labels.tif`` and ``regions.csv`` (their names and densities): the run folder records
    the areas it counted in, so statistics and the report use them. Returns the names written.
    With a relative ``relief`` the table's heights are ``relative_height`` (no unit)."""
    write_protrusions_csv(folder / "protrusions.csv", prot.table, relative=is_relative(relief))
    write_label_tiff(folder / "protrusions_labels.tif", prot.labels, pixel_size_um=pixel_size_um,
                     metadata={"Info": "uvps detect: protrusion labels (0 = background; id as in protrusions.csv)"})
    names = ["protrusions", "protrusions_labels"]
    if prot.regions is not None:
        write_label_tiff(folder / "regions_labels.tif", prot.regions.labels, pixel_size_um=pixel_size_um,
                         metadata={"Info": "uvps: colour areas (0 = none; names in regions.csv)"})
        stats = region_statistics(prot.table, prot.regions, pixel_size_um=pixel_size_um, bins_um=bins_um)
        write_regions_csv(folder / "regions.csv", stats)
        names += ["regions_labels", "regions"]
    return names


# ------------------------------------------------------------------------------------------------
# manual work across re-runs
# ------------------------------------------------------------------------------------------------

def manual_work(run_dir) -> list:
    """The manual files (:data:`MANUAL_FILES`: the wand's count, a comparison) ``run_dir`` holds."""
    return [f for f in MANUAL_FILES[:3] if (Path(run_dir) / f).is_file()]


def _run_identity(run_dir: Path) -> tuple:
    """(written, run id) of the run in ``run_dir``: run.json's time of writing (UTC) and the first 8
    hex digits of its SHA-256 (two runs' records differ in their timings and parameters)."""
    record = run_dir / FILES["run"][0]
    if record.is_file():
        stamp = record.stat().st_mtime
        digest = hashlib.sha256(record.read_bytes()).hexdigest()[:8]
    else:                           # manual work in a folder that never held a run
        stamp = max((run_dir / f).stat().st_mtime for f in manual_work(run_dir))
        digest = "no-run"
    return time.strftime("%Y-%m-%d_%H%M", time.gmtime(stamp)), digest


def set_aside_manual_work(old, new, *, beside: Optional[Path] = None, reason: Optional[str] = None) -> Optional[Path]:
    """Keep the manual work of run folder ``old`` in ``new/earlier/<date>_<run id>/`` with the run it
    was measured on, before ``new`` replaces ``old``.

    A re-run makes a new albedo and height: a manual count outlined and measured on the earlier ones,
    and a comparison with the earlier automated count, belong to that run, not to the new one. So
    they are not deleted, nor left beside the new run as if measured on it: the files of
    :data:`MANUAL_FILES` and :data:`MEASURED_ON` that ``old`` holds are hard-linked (copied where a
    link is refused) into ``new/earlier/<date>_<run id>/`` (``<date>``: when the earlier run.json was
    written, UTC; ``<run id>``: its SHA-256's first 8 hex digits), byte for byte, with
    ``earlier.json`` recording what and why. The folders of ``old/earlier/`` are kept too. Nothing
    is written when ``old`` holds no manual work. ``beside``: a folder whose ``earlier/`` the new
    folder's is merged into (a step's temporary folder is moved into the run folder file by file), so
    that no name already there is taken.

    Returns
    -------
    Path or None
        The folder in ``new`` (under ``earlier/``) that holds the manual work.
    """
    old, new = Path(old), Path(new)
    present = manual_work(old) if old.is_dir() else []
    if not present:
        return None
    if (old / EARLIER).is_dir() and not (new / EARLIER).exists():
        _link_tree(old / EARLIER, new / EARLIER)
    written, run_id = _run_identity(old)
    dest = new / EARLIER / f"{written}_{run_id}"
    k = 2
    while dest.exists() or (beside is not None and (Path(beside) / EARLIER / dest.name).exists()):
        dest = new / EARLIER / f"{written}_{run_id}-{k}"
        k += 1
    dest.mkdir(parents=True)
    files = []
    for name in MANUAL_FILES + MEASURED_ON:
        src = old / name
        if src.is_file():
            (dest / name).parent.mkdir(parents=True, exist_ok=True)
            _link_or_copy(src, dest / name)
            files.append(name)
    run = run_record(old) or {}
    write_json_atomic(dest / EARLIER_RECORD, {
        "set_aside_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
        "reason": reason or "a new run of the folder made a new albedo and height; this manual work was "
                            "measured on the earlier run, kept here with it",
        "measured_on": {"run_id": run_id, "written_utc": written.replace("_", " "), "command": run.get("command"),
                        "version": run.get("version")},
        "manual_files": present, "files": files})
    return dest


def set_aside_for_step(run_dir, tmp, *, step: str) -> Optional[Path]:
    """:func:`set_aside_manual_work` for a step that rewrites, in place, what manual work was measured on
    (``normals``: the albedo outlined; ``integrate``: the height measured): the manual work of
    ``run_dir`` and the files it was measured on are linked into ``tmp/earlier/<date>_<run id>/``
    (``tmp``: the step's :func:`~uvps.files.outputs.atomic_output_dir`, moved into ``run_dir`` with
    the step's files; ``reason`` goes into ``earlier.json``). Once that is in place, :func:`drop_manual_work` removes the manual files from
    ``run_dir``: they are not left beside images they were not measured on. Returns the folder in
    ``tmp`` or None (no manual work)."""
    run_dir, tmp = Path(run_dir), Path(tmp)
    if not manual_work(run_dir):
        return None
    (tmp / EARLIER).mkdir(exist_ok=True)   # run_dir/earlier/ stays where it is: not linked again
    what = STEP_REWRITES[step]
    return set_aside_manual_work(run_dir, tmp, beside=run_dir,
                                 reason=f"`uvps {step}` wrote a new {what} into the folder; this manual work was "
                                        "measured on the earlier one, kept here with it")


#: A comparison of two counts (``uvps compare``): what a new count makes stale.
COMPARISON_FILES = ("comparison.csv", "figures/comparison_map.png")
#: What each step that rewrites a count a comparison reads replaces (:func:`set_aside_comparison`).
RECOUNTS = {"detect": "automated count (protrusions.csv)", "wand": "manual count (protrusions_manual.csv)"}


def set_aside_comparison(run_dir, tmp, *, step: str) -> Optional[Path]:
    """Before ``step`` (``detect`` or ``wand``) writes a new count into ``run_dir``: a comparison made with
    the earlier count (``comparison.csv`` and its map) would otherwise stay beside a count it was not
    made with. Like :func:`set_aside_for_step`, the folder's manual work and what it was measured on,
    the earlier counts included, are linked into ``tmp/earlier/<date>_<run id>/`` with ``earlier.json``
    saying why; then :func:`drop_comparison` removes the comparison from ``run_dir`` (the manual count
    stays: the albedo and the height it was measured on are unchanged). Returns the folder in ``tmp``,
    or None when ``run_dir`` holds no comparison."""
    run_dir, tmp = Path(run_dir), Path(tmp)
    if not (run_dir / COMPARISON_FILES[0]).is_file():
        return None
    (tmp / EARLIER).mkdir(exist_ok=True)
    return set_aside_manual_work(run_dir, tmp, beside=run_dir,
                                 reason=f"`uvps {step}` wrote a new {RECOUNTS[step]} into the folder; this "
                                        "comparison was made with the earlier one, kept here with it")


def drop_comparison(run_dir) -> None:
    """Remove :data:`COMPARISON_FILES` from ``run_dir`` after :func:`set_aside_comparison` kept them."""
    for name in COMPARISON_FILES:
        (Path(run_dir) / name).unlink(missing_ok=True)


def drop_manual_work(run_dir) -> None:
    """Remove :data:`MANUAL_FILES` from ``run_dir`` after :func:`set_aside_for_step` kept them in
    ``earlier/`` (hard links or copies: the bytes stay there)."""
    for name in MANUAL_FILES:
        (Path(run_dir) / name).unlink(missing_ok=True)


def _clicks_of(path: Path) -> dict:
    """``{"clicks": n, "counted": k}`` of a wand table (a table without ``counted``: every row counted)."""
    import csv

    try:
        with open(path, newline="", encoding="utf-8") as fh:
            rows = list(csv.DictReader(fh))
    except (OSError, UnicodeDecodeError, csv.Error):
        return {}
    counted = sum(1 for r in rows if not not_counted(r.get("counted") or "1"))
    return {"clicks": len(rows), "counted": counted}


def _earlier_record(folder: Path) -> dict:
    """A set-aside folder's ``earlier.json``, or {} when it is missing or unreadable."""
    try:
        return json.loads((folder / EARLIER_RECORD).read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError):
        return {}


def earlier_work(run_dir) -> list:
    """The manual work of earlier runs kept in ``run_dir/earlier/`` (:func:`set_aside_manual_work`),
    oldest first (by when it was set aside: two runs of one minute share the name's date):
    ``{"folder": "earlier/<name>", "measured_on": date, "run_id", "manual_files",
    "clicks", "counted"}`` each."""
    base = Path(run_dir) / EARLIER
    out = []
    if not base.is_dir():
        return out
    for folder, rec in sorted(((p, _earlier_record(p)) for p in base.iterdir() if p.is_dir()),
                              key=lambda fr: (str(fr[1].get("set_aside_utc", "")), fr[0].name)):
        on = rec.get("measured_on") or {}
        item = {"folder": f"{EARLIER}/{folder.name}", "measured_on": on.get("written_utc"),
                "run_id": on.get("run_id"), "manual_files": rec.get("manual_files") or manual_work(folder)}
        if (folder / MANUAL_FILES[0]).is_file():
            item.update(_clicks_of(folder / MANUAL_FILES[0]))
        out.append(item)
    return out


def earlier_line(item: dict) -> str:
    """One line on an :func:`earlier_work` item, for ``uvps info``, the CLI and the Log."""
    what = []
    for f in item["manual_files"]:
        if f == MANUAL_FILES[0] and "clicks" in item:
            what.append(f"{f} ({item['counted']} counted of {item['clicks']} clicks)")
        elif f != MANUAL_FILES[1]:
            what.append(f)
    when = f"the run of {item['measured_on']} UTC" if item.get("measured_on") else "an earlier run"
    return f"{item['folder']}/: {', '.join(what) or 'files'}, measured on {when} (not on this run)"


# ------------------------------------------------------------------------------------------------
# reading
# ------------------------------------------------------------------------------------------------

@dataclass
class RunImages:
    """What a run folder holds for protrusion work (None when the file is absent)."""

    albedo: Optional[np.ndarray]      # (M, N) or (M, N, C)
    height_um: Optional[np.ndarray]   # (M, N) float32
    normals: Optional[np.ndarray]     # (M, N, 3) float32
    pixel_size_um: Optional[float]
    shape: Optional[tuple]


def _channels_last(arr: np.ndarray) -> np.ndarray:
    if arr.ndim == 3 and arr.shape[0] == 3:
        return np.moveaxis(arr, 0, -1)
    return arr


def read_run(run_dir: Path, *, need=("albedo", "depth"), pixel_size_um=None,
             require_pixel_size: bool = True) -> RunImages:
    """Read ``albedo.tif``, ``depth.tif`` and ``normals.tif`` of a run folder, once.

    Parameters
    ----------
    run_dir : Path
    need : tuple of str
        Files that must exist ("albedo", "depth", "normals"); a missing one raises
        UVPSInputError naming the command that makes it.
    pixel_size_um : float, optional
        Overrides the TIFFs' calibration (required when they have none).
    require_pixel_size : bool
        False: a folder whose TIFFs carry no pixel size is read with ``pixel_size_um`` None (the
        report finds it elsewhere) instead of raising.
    """
    run_dir = Path(run_dir)
    out, px_found = {}, []
    for name in ("albedo", "depth", "normals"):
        path = run_dir / FILES[name][0]
        if not path.is_file():
            if name in need:
                raise UVPSInputError(f"run folder {run_dir} has no {path.name}; run the '{MADE_BY[name]}' "
                                     "command first")
            out[name] = None
            continue
        data, px = read_tiff(path)
        out[name] = np.asarray(data)
        if px:
            px_found.append(px)
    albedo = _channels_last(out["albedo"]) if out["albedo"] is not None else None
    normals = _channels_last(out["normals"]).astype(np.float32) if out["normals"] is not None else None
    height = out["depth"].astype(np.float32) if out["depth"] is not None else None
    shapes = {a.shape[:2] for a in (albedo, height, normals) if a is not None}
    if len(shapes) > 1:
        raise UVPSInputError(f"run folder {run_dir}: albedo.tif, depth.tif and normals.tif differ in size: "
                             f"{sorted(shapes)}")
    if pixel_size_um is not None:
        px = check_pixel_size(pixel_size_um)
    elif px_found:
        px = float(px_found[0])
    elif shapes and require_pixel_size:
        raise UVPSInputError(f"{run_dir}: no pixel size in the TIFFs; give pixel_size_um")
    else:
        px = None
    return RunImages(albedo, height, normals, px, shapes.pop() if shapes else None)


# ------------------------------------------------------------------------------------------------
# uvps info: what a run folder holds
# ------------------------------------------------------------------------------------------------

def describe(run_dir) -> dict:
    """What a run folder holds: its files, the command and parameters that made it, the lights, the
    warnings it gave, and the protrusion count.

    Example
    -------
    >>> import tempfile, json, pathlib
    >>> d = pathlib.Path(tempfile.mkdtemp())
    >>> _ = (d / "run.json").write_text(json.dumps({"version": "0", "command": "run", "params": {},
    ...     "warnings": ["heights may be off by +-25 %"], "diagnostics": {"lights": {"source": "estimated"}}}))
    >>> info = describe(d)
    >>> info["command"], info["warnings"], info["files"]
    ('run', ['heights may be off by +-25 %'], ['run.json'])
    """
    run_dir = Path(run_dir)
    if not run_dir.is_dir():
        raise UVPSInputError(f"run folder {run_dir} does not exist")
    run_json = run_dir / FILES["run"][0]
    if not run_json.is_file():
        raise UVPSInputError(f"{run_dir} is not a run folder: it has no run.json (made by uvps run, lights, "
                             "flatfield or normals)")
    try:
        log = json.loads(run_json.read_text(encoding="utf-8"))
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise UVPSInputError(f"{run_json} is not valid JSON ({exc})") from None
    files = sorted(f for name, (f, *_rest) in FILES.items() if (run_dir / f).exists())
    info = {"run_dir": str(run_dir), "version": log.get("version"), "command": log.get("command"),
            "params": log.get("params", {}), "warnings": list(log.get("warnings", [])), "files": files,
            "lights": log.get("diagnostics", {}).get("lights", {}), "timings_s": log.get("timings_s", {}),
            "relief": relief_of(log), "level": level_words(log.get("level"))}
    if log.get("diagnostics", {}).get("raw"):
        info["raw"] = log["diagnostics"]["raw"]       # camera raw files: how LibRaw read them
    table = run_dir / FILES["protrusions"][0]
    if table.is_file():
        with open(table, encoding="utf-8") as fh:
            info["n_protrusions"] = max(0, sum(1 for line in fh if line.strip()) - 1)
        det = log.get("diagnostics", {}).get("detect") or {}
        rejected = det.get("rejected")
        if det.get("n_protrusions") == info["n_protrusions"] and isinstance(rejected, dict):
            # the detection run.json describes made this table (a later `uvps detect` does not
            # update run.json: then only the table's count is known)
            info["detection"] = {"candidates": info["n_protrusions"] + sum(rejected.values()),
                                 "kept": info["n_protrusions"], "rejected": dict(rejected)}
    manual = run_dir / MANUAL_FILES[0]
    if manual.is_file():
        info["manual"] = _clicks_of(manual)
    info["earlier"] = earlier_work(run_dir)
    return info
