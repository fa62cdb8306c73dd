"""``uvps batch``: many captures on Dask, each as ``uvps run`` would, and mosaics of one painting.

Each capture folder is run through the ``run`` command into ``OUT/<capture name>/`` by a task on a
``dask.distributed`` cluster (a local one by default, or ``scheduler``'s). A task runs into a
temporary folder inside ``OUT`` and renames it into place when the run is complete, so a killed
worker, a failure or a re-run never leaves a half-written run folder; a capture whose run folder is
complete (its inputs' SHA-256 and the parameters unchanged) is skipped unless ``force``. A capture
that fails is listed with its one-line error; the others go on. ``OUT/batch_summary.csv`` and
``OUT/batch.json`` sum up the batch (counts and densities per colour area).

With a mosaic layout (each tile's nominal corner in the painting, in pixels) or a regular grid, the
tiles are registered on their overlaps and merged into ``OUT/painting/``: the refined layout, one
protrusion table (painting coordinates, each protrusion of an overlap once) and one density table
per colour area of the painting (:mod:`uvps.painting`). See docs/painting.md.

Dask is imported inside the functions that use it: importing it costs every other command about a
second. So is the numeric core (the tiles' run, the painting, :mod:`uvps.painting`): the batch's
process starts its cluster before it imports them, and imports them while the workers start
(:data:`STITCH_PROCESS_IMPORTS`), instead of 0.7 s earlier on one core.
"""
from __future__ import annotations

import contextlib
import csv
import json
import logging
import os
import shutil
import time
import uuid
from dataclasses import dataclass, field
from io import StringIO
from pathlib import Path
from typing import Optional

import tifffile

from .. import __version__
from ..errors import UVPSComputeError, UVPSError, UVPSInputError
from ..files.io import IMAGE_EXTS, TIFF_EXTS, read_image, read_text, sha256_file
from ..files.outputs import (CommandResult, OutputSpec, Progress, check_output_dir, replace_dir, report,
                            write_json_atomic)
from ..core.tiles import overlap_box
from ..files.paintingfolder import PAINTING_DIR, PAINTING_LAYOUT, PAINTING_PROTRUSIONS, PAINTING_REGIONS
from ..core.threads import THREADS_VARIABLE
from ..workers import exit_at_teardown
from ..workflow import CAPTURE_PARAMS, OPTION_PARAMS, OUTPUT_PARAMS, PROTRUSION_PARAMS, RUN, run_into_folder
from ..spec import CommandSpec, Param, coerce_value

log = logging.getLogger(__name__)

#: Parameters of ``run`` that name a file: one file for every capture when it exists, else looked
#: up by its name in each capture folder (``lights_positions_mm.csv`` beside each capture's images).
PER_CAPTURE_FILES = ("lights", "mask", "dark", "regions")
#: Keywords these parameters take instead of a file (from the run command's declaration).
_KEYWORDS = {p.name: p.choices for p in CAPTURE_PARAMS + PROTRUSION_PARAMS if p.name in PER_CAPTURE_FILES}
#: What a batch writes beside the run folders.
SUMMARY, BATCH_JSON = "batch_summary.csv", "batch.json"
#: Written last into each run folder: the request it was run with (for the skip rule).
REQUEST_RECORD = "batch_request.json"
_TMP, _OLD = ".batch-tmp-", ".batch-old-"


@dataclass
class Job:
    """One capture of a batch: its name (the folder's), folder, and the ``run`` parameters for it."""

    name: str
    folder: Path
    params: dict
    error: Optional[str] = None     # known before any work (e.g. no lights file in the folder)


@dataclass
class BatchResult:
    """What :func:`run_batch` did: one record per capture (input order), the cluster, the mosaic."""

    records: list
    out_dir: Path
    cluster: dict
    mosaic: Optional[dict] = None
    warnings: list = field(default_factory=list)
    elapsed_s: float = 0.0
    timings: dict = field(default_factory=dict)   # the batch's parts (s): cluster_start, tiles, stitch, close

    def count(self, status: str) -> int:
        return sum(r["status"] == status for r in self.records)


# ------------------------------------------------------------------------------------------------
# which captures, and with which files
# ------------------------------------------------------------------------------------------------

def _has_images(folder: Path) -> bool:
    return any(p.is_file() and p.suffix.lower() in IMAGE_EXTS and not p.name.startswith(".")
               for p in folder.iterdir())


def list_captures(items) -> list:
    """Capture folders from ``items``: capture folders (a folder holding images), folders of
    capture folders (their sub-folders that hold images, sorted by name), or text files listing
    either (one a line; ``#`` starts a comment; relative to the text file's folder)."""
    out = []
    for item in items:
        p = Path(item)
        if p.is_file():
            base = p.parent
            lines = [ln.split("#", 1)[0].strip() for ln in read_text(p, "captures: the list", "one capture folder a line").splitlines()]
            listed = [base / ln if not Path(ln).is_absolute() else Path(ln) for ln in lines if ln]
            if not listed:
                raise UVPSInputError(f"captures: the list {p} names no capture folder")
            for q in listed:
                if not q.is_dir():
                    raise UVPSInputError(f"captures: {q} (listed in {p.name}) is not a folder")
            out += list_captures(listed)
        elif p.is_dir():
            if _has_images(p):
                out.append(p.resolve())
                continue
            subs = sorted(q.resolve() for q in p.iterdir() if q.is_dir() and not q.name.startswith(".")
                          and _has_images(q))
            if not subs:
                raise UVPSInputError(f"captures: {p} holds no images and no capture folders")
            out += subs
        else:
            raise UVPSInputError(f"captures: {p} does not exist")
    names = [q.name for q in out]
    dup = sorted({n for n in names if names.count(n) > 1})
    if dup:
        raise UVPSInputError(f"captures: two capture folders are named {dup[0]}; each writes OUT/<name>/, "
                             "so names must differ")
    return out


#: The parameters of ``uvps run`` (all of them but its images): each capture runs with them.
RUN_PARAMS = tuple(p for p in CAPTURE_PARAMS + OPTION_PARAMS + PROTRUSION_PARAMS + OUTPUT_PARAMS if p.where == "params")


def _run_param_names() -> tuple:
    return tuple(p.name for p in RUN_PARAMS)


def _run_params(params: dict) -> dict:
    """``run``'s parameters among ``params``, checked as ``uvps run`` checks them; absent or empty
    ones take their default."""
    out = {}
    for p in RUN_PARAMS:
        given = params.get(p.name)
        empty = given is None or (p.type == "paths" and given == []) or (p.type == "path" and given == "")
        out[p.name] = p.default if empty else coerce_value(p, given)
    return out


def make_jobs(folders, params: dict) -> list:
    """A :class:`Job` per capture folder: the ``run`` parameters among ``params``, with the file
    parameters (:data:`PER_CAPTURE_FILES`) resolved for each folder."""
    run_params = _run_params(params)
    jobs = []
    for folder in folders:
        p, error = dict(run_params), None
        for key in PER_CAPTURE_FILES:
            value = p.get(key)
            if not isinstance(value, str) or value in _KEYWORDS.get(key, ()):
                continue
            if Path(value).is_file():
                p[key] = str(Path(value).resolve())
            elif (folder / Path(value).name).is_file():
                p[key] = str(folder / Path(value).name)
            else:
                error = f"{key}: {value} is no file, and capture folder {folder.name} has no {Path(value).name}"
        jobs.append(Job(folder.name, folder, p, error))
    for key in PER_CAPTURE_FILES:
        if jobs and all(j.error and j.error.startswith(key + ":") for j in jobs):
            value = jobs[0].params.get(key)
            raise UVPSInputError(f"{key}: {value} is no file, and none of the capture folders holds "
                                 f"{Path(value).name}")
    return jobs


# ------------------------------------------------------------------------------------------------
# one capture (runs on a worker)
# ------------------------------------------------------------------------------------------------

def _jsonable(obj):
    return json.loads(json.dumps(obj, default=str))


def _side_files(params: dict) -> dict:
    out = {k: {"path": params[k], "sha256": sha256_file(params[k])}
           for k in PER_CAPTURE_FILES if isinstance(params.get(k), str) and Path(params[k]).is_file()}
    cal = params.get("calibration")
    if isinstance(cal, str) and (Path(cal) / "calibration.json").is_file():
        # a calibration made again into the same folder makes the runs stale
        out["calibration"] = {"path": str(Path(cal) / "calibration.json"),
                              "sha256": sha256_file(Path(cal) / "calibration.json")}
    return out


def _image_files(folder: Path) -> set:
    return {str(p) for p in folder.iterdir()
            if p.is_file() and p.suffix.lower() in IMAGE_EXTS and not p.name.startswith(".")}


def complete(run_dir: Path, folder: Path, params: dict) -> tuple:
    """``(True, "")`` when ``run_dir`` holds a finished batch run of ``folder`` with ``params``:
    ``run.json`` and the request record present, the same parameters, the same image files with
    unchanged SHA-256, and unchanged light, mask, dark and region files; else ``(False, why)``."""
    run_json, record = run_dir / "run.json", run_dir / REQUEST_RECORD
    if not (run_json.is_file() and record.is_file()):
        return False, "no finished run folder"
    try:
        log_ = json.loads(run_json.read_text(encoding="utf-8"))
        req = json.loads(record.read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return False, "unreadable run.json"
    if req.get("params") != _jsonable(params):
        return False, "parameters changed"
    recorded = {i["path"]: i["sha256"] for i in log_.get("inputs", [])}
    if set(recorded) != _image_files(folder):
        return False, "image files added or removed"
    for path, digest in recorded.items():
        if sha256_file(path) != digest:
            return False, f"{Path(path).name} changed"
    for key, f in req.get("files", {}).items():
        if not Path(f["path"]).is_file() or sha256_file(f["path"]) != f["sha256"]:
            return False, f"{key} file changed"
    if set(req.get("files", {})) != set(_side_files(params)):
        return False, "parameters changed"
    return True, ""


def _one_line(exc: BaseException) -> str:
    text = str(exc).strip().splitlines()[0].strip() if str(exc).strip() else ""
    if isinstance(exc, UVPSError):
        return text or type(exc).__name__
    return f"{type(exc).__name__}: {text}" if text else type(exc).__name__


def failure_kind(exc: BaseException) -> str:
    """Why a capture failed, as the exit status counts it: ``"input"`` (bad input the user can
    fix: :class:`UVPSInputError`), ``"compute"`` (:class:`UVPSComputeError`) or ``"internal"``
    (anything else: a bug, a worker killed)."""
    if isinstance(exc, UVPSInputError):
        return "input"
    return "compute" if isinstance(exc, UVPSComputeError) else "internal"


def run_capture(name: str, folder: str, out_dir: str, params: dict, force: bool = False) -> dict:
    """Run one capture as ``uvps run`` would into ``out_dir/name`` (the task a worker runs).

    Never raises: a failure is the record's ``status`` "failed" with its one-line ``error``.
    Returns a JSON-ready record: capture, folder, status (done, skipped, failed), error,
    n_protrusions, areas, elapsed_s, warnings.
    """
    t0 = time.perf_counter()
    folder, out_dir = Path(folder), Path(out_dir)
    target = out_dir / name
    record = {"capture": name, "folder": str(folder), "status": "done", "error": None, "warnings": []}
    # built in <out>/.<name>.batch-tmp-XXXX/<name>: its own name is the capture's, so the report written
    # into it names the run folder as it will be (title, "Run folder", the stats command), not the stage
    stage = out_dir / f".{name}{_TMP}{uuid.uuid4().hex[:8]}"
    tmp = stage / name
    try:
        done, why = (False, "forced") if force else complete(target, folder, params)
        if done:
            record["status"] = "skipped"
        else:
            log.info("%s: running (%s)", name, why)
            result = run_into_folder(RUN, {"images": [str(folder)]}, params, tmp)
            write_json_atomic(tmp / REQUEST_RECORD, {"version": __version__, "capture": str(folder),
                                                     "params": _jsonable(params), "files": _side_files(params)})
            # the old run or the new one, never a mix, whenever the process is killed (replace_dir)
            replace_dir(tmp, target, aside=_OLD)
            record["warnings"] = list(result.warnings)
        from ..files.tables import read_counts
        record.update(read_counts(target))
    except Exception as exc:  # noqa: BLE001 - one capture's failure is its record, not the batch's
        log.debug("%s failed", name, exc_info=True)
        record.update(status="failed", error=_one_line(exc), failure=failure_kind(exc))
    finally:
        shutil.rmtree(stage, ignore_errors=True)
    record["elapsed_s"] = round(time.perf_counter() - t0, 3)
    return record


# ------------------------------------------------------------------------------------------------
# the batch
# ------------------------------------------------------------------------------------------------

def default_workers(n_captures: int) -> int:
    """Local workers: one process per core, at most one per capture (each with one thread)."""
    return max(1, min(os.cpu_count() or 1, n_captures))


#: The nanny's setting that :class:`_Cluster` leaves unset in its local workers (distributed's default 65536).
MALLOC_TRIM_KEY = "distributed.nanny.pre-spawn-environ.MALLOC_TRIM_THRESHOLD_"


class _Cluster:
    """A ``distributed.Client``: the one given, one on ``scheduler``, or on a new ``LocalCluster``."""

    def __init__(self, client=None, scheduler=None, n_workers=1, processes=True, while_starting=None):
        import dask
        from distributed import Client, LocalCluster   # lazily: dask costs every other command its import

        if while_starting is not None:
            while_starting()    # after dask's and distributed's imports here, which its thread then finds done

        if not log.isEnabledFor(logging.DEBUG):
            # the scheduler's and workers' INFO lines (ports, nannies) bury the batch's own (uvps -v shows them)
            logging.getLogger("distributed").setLevel(logging.WARNING)
            dask.config.set({"logging.distributed": "warning"})
        self.own = []
        self.preloaded = False      # the workers imported this module and the maps' modules as they started
        if client is None and scheduler:
            client = Client(scheduler, timeout="30s")
            self.own = [client]
        elif client is None:
            # one thread per worker: the pipeline's Python parts hold the GIL, and one capture per
            # process bounds the memory to one capture per worker (the nanny also sets
            # OMP/MKL/OPENBLAS_NUM_THREADS=1 in each worker, so numpy does not oversubscribe)
            # its dashboard on a free port (":0"): None still takes 8787, so a second batch on the
            # machine warned "Port 8787 is already in use"; the link is in the log (uvps -v)
            # UVPS_THREADS=1 keeps each capture's own stages (the normals' bands, the lamp refinement) to
            # that one thread too (uvps.core.threads)
            # each worker process imports this module, and with it the pipeline, as it starts (distributed's
            # preload; its `dask_setup` below), beside this process's own imports and before it registers,
            # rather than when its first tile's task is unpickled after the cluster is up (after the user's own
            # preloads, which the argument would otherwise replace)
            preload, argv = _worker_preloads(__name__)
            extra = {"env": {THREADS_VARIABLE: "1"}, "preload": preload, "preload_argv": argv} if processes else {}
            # glibc's own allocator settings in the workers, as in a `uvps run` process: the nanny's
            # default MALLOC_TRIM_THRESHOLD_=65536 also freezes glibc's mmap threshold at 128 KB, so
            # every large numpy temporary is mmapped, page-faulted and unmapped again; the painting
            # maps of a 4 x 3 painting of 1200 x 900 px tiles took 7.9 s of system CPU in a worker
            # with it, 1.9 s without (docs/decisions/painting.md, "The batch's fixed costs at 1200 x 900 px tiles")
            # (an earlier nanny in this process left its value in os.environ, which new workers would inherit)
            with dask.config.set({MALLOC_TRIM_KEY: None}), _without_nanny_trim():
                cluster = LocalCluster(n_workers=n_workers, threads_per_worker=1, processes=processes,
                                       dashboard_address=":0", **extra)
            client = Client(cluster)
            self.own = [client, cluster]
            self.preloaded = processes
            log.debug("Dask dashboard: %s", client.dashboard_link)
        self.client = client
        info = client.scheduler_info()
        workers = info.get("workers", {})
        self.info = {"scheduler": info.get("address"), "local": bool(self.own) and not scheduler,
                     "workers": len(workers), "threads": sum(w.get("nthreads", 0) for w in workers.values())}

    def trim(self) -> None:
        """Hand the memory the tiles' runs freed back to the system in this batch's own local workers
        (glibc's ``malloc_trim``, as distributed's documentation advises for unmanaged memory): they
        keep glibc's allocator settings (above), which hold freed heap for reuse, and would otherwise
        hold it through the stitching."""
        if self.info["local"]:
            self.client.run(_malloc_trim)

    def close(self):
        for obj in self.own:
            obj.close()


def _worker_preloads(name: str) -> tuple:
    """(preloads, their argv) for a worker: the user's own (``distributed.worker.preload`` and
    ``-argv``), then the module ``name`` with no argument. Either setting may be one string, as
    distributed reads it (a ``DASK_DISTRIBUTED__WORKER__PRELOAD=mymodule`` environment variable gives
    one): one preload, one argument for every preload."""
    import dask

    preload = dask.config.get("distributed.worker.preload", None) or []
    preload = [preload] if isinstance(preload, str) else list(preload)
    argv = dask.config.get("distributed.worker.preload-argv", None) or []
    argv = [argv] if isinstance(argv, str) else list(argv)
    if argv and not isinstance(argv[0], str):
        argv = argv + [[]]                      # one list per preload
    return preload + [name], argv


def dask_setup(worker) -> None:
    """A worker process of the batch's own local cluster, as it starts (distributed's preload of this module,
    :class:`_Cluster`; never a ``--scheduler`` cluster's workers): it ends without the interpreter's teardown
    (:func:`uvps.workers.exit_at_teardown`), and it imports what a tile's run imports (:data:`RUN_IMPORTS`),
    and what the painting's maps import on a worker (:data:`STITCH_IMPORTS`), which the last worker to finish
    its tiles otherwise imported while the registration's tasks ran."""
    exit_at_teardown()
    _import_modules(RUN_IMPORTS + STITCH_IMPORTS)


@contextlib.contextmanager
def _without_nanny_trim():
    """``MALLOC_TRIM_THRESHOLD_`` out of this process's environment while the batch's workers start, when it
    holds distributed's default (a nanny started earlier in this process sets it there, "poisoning" the
    process, as distributed's documentation says); a value of the user's own is kept."""
    name = "MALLOC_TRIM_THRESHOLD_"
    old = os.environ.get(name)
    if old != "65536":
        yield
        return
    del os.environ[name]
    try:
        yield
    finally:
        os.environ[name] = old


def _malloc_trim() -> int:
    """glibc's ``malloc_trim(0)`` in this process (1 if memory was released); 0 where there is no glibc."""
    import ctypes
    try:
        return int(ctypes.CDLL("libc.so.6").malloc_trim(0))
    except (OSError, AttributeError):
        return 0


def _clean_temporaries(out_dir: Path) -> None:
    """Remove what killed tasks left (``OUT/.<name>.batch-tmp-*``, ``.batch-old-*``, and the painting's
    staging folder ``OUT/.painting.uvps-new-*``, :func:`uvps.files.outputs.new_output_dir`)."""
    for p in out_dir.glob(".*.batch-*-*"):
        if _TMP in p.name or _OLD in p.name:
            shutil.rmtree(p, ignore_errors=True)
    for p in out_dir.glob(f".{PAINTING_DIR}.uvps-new-*"):
        shutil.rmtree(p, ignore_errors=True)


def run_batch(captures, out_dir, params: dict, *, force: bool = False, mosaic=None, grid=None,
              painting_regions=None, painting_chunk_px: Optional[int] = None, client=None,
              scheduler: Optional[str] = None,
              n_workers: Optional[int] = None, processes: bool = True,
              progress: Progress = None) -> BatchResult:
    """Run every capture as ``uvps run`` would, on a Dask cluster, and sum them up.

    Parameters
    ----------
    captures : list of path
        Capture folders, folders of capture folders, or text files listing them (:func:`list_captures`).
    out_dir : path
        The batch folder: ``<out_dir>/<capture name>/`` per capture, the summary beside them.
    params : dict
        Parameters of ``run`` (coerced; absent ones take ``run``'s defaults). The file parameters
        (:data:`PER_CAPTURE_FILES`) name one file for all, or a file name found in each capture folder.
    force : bool
        Run captures whose run folder is complete too.
    mosaic : path, optional
        Layout CSV (``capture,x_px,y_px``, the stage's nominal corners): register the tiles and
        merge them into ``OUT/painting/`` (:func:`uvps.painting.stitch_painting`).
    grid : str, optional
        Instead of a layout, a regular grid ``"COLUMNS,ROWS,OVERLAP[,ORDER]"`` (:func:`grid_layout`).
    painting_regions : path, optional
        A painting-wide label TIFF in the layout's frame: the painting's colour areas (default:
        proposed on the painting's albedo with ``regions="auto"``, else one area).
    painting_chunk_px : int, optional
        The painting maps' chunk side (default :data:`uvps.files.omezarr.CHUNK_PX`).
    client : distributed.Client, optional
        Use this client; else one on ``scheduler``; else a ``LocalCluster`` of ``n_workers``
        processes (default :func:`default_workers`), one thread each (``processes=False``: threads).
    progress : callable(fraction, message), optional
        Called as each capture finishes (fraction of captures finished, counts so far).

    Returns
    -------
    BatchResult

    Raises
    ------
    UVPSInputError
        Before any work: no captures, two with one name, a file parameter found nowhere, a bad
        mosaic layout (a tile it names is not among the captures, or a tile overlaps no other).
    UVPSComputeError
        Every capture failed (the summary is written first).
    """
    t0 = time.perf_counter()
    out_dir = check_output_dir(out_dir)
    folders = list_captures(captures)
    if not folders:
        raise UVPSInputError("captures: no capture folders given")
    jobs = make_jobs(folders, params)
    if mosaic and grid:
        raise UVPSInputError("mosaic: give a layout (--mosaic) or a grid (--grid), not both")
    layout = read_layout(mosaic, jobs) if mosaic else grid_layout(grid, jobs) if grid else None
    if painting_regions and layout is None:
        raise UVPSInputError("painting regions: a painting-wide label image needs --mosaic or --grid")
    if painting_regions and not Path(painting_regions).is_file():
        raise UVPSInputError(f"painting regions: {painting_regions} does not exist")
    out_dir.mkdir(parents=True, exist_ok=True)          # missing parents made, as every command makes them
    _clean_temporaries(out_dir)
    records = {j.name: {"capture": j.name, "folder": str(j.folder), "status": "failed", "error": j.error,
                        "failure": "input", "warnings": [], "elapsed_s": 0.0} for j in jobs if j.error}
    todo = [j for j in jobs if not j.error]
    report(progress, 0.0, f"starting the cluster for {len(todo)} captures")
    timings = {}
    t_part = time.perf_counter()
    warm = _StitchWarmUp() if layout is not None else None
    # this process's imports for the stitching while the cluster starts: it waits for its workers then
    cluster = _Cluster(client, scheduler, n_workers or default_workers(len(todo)), processes,
                       while_starting=warm and warm.start) if todo else None
    timings["cluster_start_s"] = round(time.perf_counter() - t_part, 3)
    try:
        t_part = time.perf_counter()
        # a worker with no tile left imports the maps' modules, unless it did as it started (the batch's own)
        idle = warm.start if warm is not None and cluster is not None and not cluster.preloaded else None
        _run_tiles(cluster, todo, records, len(jobs), out_dir, force, progress, on_idle=idle)
        result = BatchResult([records[j.name] for j in jobs], out_dir,
                             cluster.info if cluster else {"workers": 0})
        result.warnings = [f"{r['capture']} failed: {r['error']}" for r in result.records
                           if r["status"] == "failed"]
        timings["tiles_s"] = round(time.perf_counter() - t_part, 3)
        if cluster is not None:
            cluster.trim()
        t_part = time.perf_counter()
        if layout is not None:
            warm.start(cluster)     # when no tile ran (all skipped or failed on their input)
            warm.wait()
            _painting(result, cluster, layout, params, painting_regions, progress, painting_chunk_px)
        timings["stitch_s"] = round(time.perf_counter() - t_part, 3)
    finally:
        t_part = time.perf_counter()
        if cluster is not None:
            cluster.close()
        _clean_temporaries(out_dir)
        timings["close_s"] = round(time.perf_counter() - t_part, 3)
    result.elapsed_s = round(time.perf_counter() - t0, 3)
    result.timings = timings
    write_summary(result, params)
    if result.count("failed") == len(jobs):
        raise all_failed(result.records, out_dir / SUMMARY)
    return result


def _run_tiles(cluster, todo, records: dict, n_jobs: int, out_dir: Path, force: bool, progress,
               on_idle=None) -> None:
    """Every capture of ``todo`` as a task of the cluster; each one's record into ``records`` as it finishes.
    ``on_idle(cluster, future)``, when given, is called as soon as fewer captures are left than the cluster has
    workers (the worker that ran ``future``'s capture has nothing left to run), and after each later one."""
    from distributed import as_completed   # lazily, as above

    futures = {cluster.client.submit(run_capture, j.name, str(j.folder), str(out_dir), j.params, force,
                                     key=f"uvps-batch-{j.name}-{uuid.uuid4().hex[:8]}", pure=False): j
               for j in todo}
    _report_counts(progress, records, n_jobs)
    left = len(futures)
    for fut in as_completed(futures):
        left -= 1
        if on_idle is not None and left < cluster.info["workers"]:
            on_idle(cluster, fut)
        j = futures[fut]
        try:
            rec = fut.result()
        except Exception as exc:  # noqa: BLE001 - a worker died (KilledWorker) or the scheduler left
            rec = {"capture": j.name, "folder": str(j.folder), "status": "failed",
                   "error": _one_line(exc), "failure": "internal", "warnings": [], "elapsed_s": None}
        records[j.name] = rec
        _report_counts(progress, records, n_jobs)


#: What the painting's stitching imports at its first use of them, and a process of the batch's cluster
#: otherwise imports while the painting waits: the maps' stores (zarr, its codecs, dask.array) on the workers
#: and in the batch's process, which also draws the report's figures (matplotlib) and the zoomable view.
STITCH_IMPORTS = ("zarr", "numcodecs", "dask.array")
#: What a tile's run imports (:func:`uvps.workflow.run_into_folder` imports the numeric core when it runs) and the
#: painting: a worker of the batch's own cluster imports them as it starts (:func:`dask_setup`), the batch's
#: process while its cluster starts (:data:`STITCH_PROCESS_IMPORTS`), not before it.
RUN_IMPORTS = ("uvps.core.pipeline", "uvps.core.regions", "uvps.files.cards", "uvps.files.runfolder",
               "uvps.files.tables", "uvps.painting")
STITCH_PROCESS_IMPORTS = STITCH_IMPORTS + ("uvps.painting", "matplotlib.figure", "matplotlib.collections",
                                           "matplotlib.patches", "PIL.Image", "cv2", "uvps.report.painting",
                                           "uvps.report.deepzoom")


def _import_modules(names=STITCH_IMPORTS) -> None:
    """Import ``names``; one that fails (whatever it raises) is left to fail where it is used, with its
    error there, and the others are still imported."""
    import importlib
    for name in names:
        with contextlib.suppress(Exception):
            importlib.import_module(name)


def _import_beside(names=STITCH_IMPORTS) -> None:
    """:func:`_import_modules` in a thread of its own of this process (a worker's: its task thread stays free)."""
    import threading
    threading.Thread(target=_import_modules, args=(names,), name="uvps-stitch-imports", daemon=True).start()


class _StitchWarmUp:
    """The stitching's imports done before the stitching: in a thread of the batch's process while its
    cluster starts (it only waits for its workers then), and, for a cluster the batch did not start (its own
    workers import them as they start, :func:`dask_setup`), in a thread of each worker once it has no tile
    left, not as a task, so that a pair of the registration never waits behind it. Without it the painting
    began with them: the maps' first graph waited for zarr and dask.array in this process and in each worker,
    the report's first figure for matplotlib (this process: ~0.7 s for matplotlib's Figure, ~0.7 s for zarr
    and dask.array in a cProfile of the stitching; docs/decisions/painting.md, "The batch's fixed costs
    (small tiles)"). Nothing of the painting's outputs depends on when a module was imported."""

    def __init__(self):
        self.thread = None
        self.warmed = set()     # workers told to import

    def start(self, cluster=None, future=None) -> None:
        """This process's imports (once); and those of the worker that ran ``future`` (once a worker)."""
        if self.thread is None:
            import threading
            self.thread = threading.Thread(target=_import_modules, args=(STITCH_PROCESS_IMPORTS,),
                                           name="uvps-stitch-imports", daemon=True)
            self.thread.start()
        if cluster is None or future is None:
            return
        with contextlib.suppress(Exception):    # a worker gone, or the scheduler: its imports are then the maps'
            idle = set(cluster.client.who_has([future]).get(future.key, ())) - self.warmed
            if idle:
                cluster.client.run(_import_beside, workers=sorted(idle))
                self.warmed |= idle

    def wait(self) -> None:
        """Until this process's imports are done (they are the stitching's own first step otherwise); an
        import that failed fails again, with its error, where the stitching imports the module."""
        if self.thread is not None:
            self.thread.join()


def _painting(result: BatchResult, cluster, layout: dict, params: dict, painting_regions, progress, chunk_px) -> None:
    """The batch's painting into ``result.mosaic`` (on the batch's cluster), or, when a tile failed, none:
    an earlier batch's painting is removed (it would not be this batch's) and a warning says why."""
    out_dir = result.out_dir
    failed = [r["capture"] for r in result.records if r["status"] == "failed"]
    if failed:
        shutil.rmtree(out_dir / PAINTING_DIR, ignore_errors=True)
        result.warnings.append(f"mosaic not merged: tile {failed[0]} failed")
        return
    # on the same cluster: the painting's map chunks are its tasks
    with cluster.client.as_current():
        result.mosaic = _stitch(out_dir, layout, params, painting_regions, progress, result.warnings, chunk_px)


def all_failed(records, summary: Path) -> UVPSError:
    """The error of a batch in which every capture failed: a :class:`UVPSInputError` (exit
    status 1) when every failure is bad input the user can fix, else a
    :class:`UVPSComputeError` (exit status 2). Its ``details`` are one line per capture
    (``"<capture>: <its problem>"``), printed before the message by the command line."""
    kinds = [r.get("failure") or "internal" for r in records]
    n_input = kinds.count("input")
    if n_input == len(records):
        exc = UVPSInputError(f"every capture failed on bad input ({len(records)}, each named with its problem "
                             f"above and in {summary}); fix them and run again")
    else:
        exc = UVPSComputeError(f"every capture failed ({len(records)}: {n_input} on bad input, "
                               f"{len(records) - n_input} while computing; each named with its problem above "
                               f"and in {summary})")
    exc.details = [f"{r['capture']}: {r['error']}" for r in records]
    return exc


def _report_counts(progress, records, total):
    n = {s: sum(r["status"] == s for r in records.values()) for s in ("done", "skipped", "failed")}
    report(progress, len(records) / total, f"{len(records)}/{total} captures: {n['done']} done, "
                                           f"{n['skipped']} skipped, {n['failed']} failed")


def write_summary(result: BatchResult, params: dict) -> None:
    """``batch_summary.csv`` (a row per capture) and ``batch.json`` (everything), atomically.

    Columns: capture, status, n_protrusions, then for each colour-area name (in order of first
    appearance) ``<name>: count``, ``<name>: area_cm2``, ``<name>: density_per_cm2``, then
    elapsed_s and error. Empty cells where a capture has no such area or failed.
    """
    names = []
    for r in result.records:
        names += [a["name"] for a in r.get("areas", []) if a["name"] not in names]
    header = ["capture", "status", "n_protrusions"]
    header += [f"{n}: {k}" for n in names for k in ("count", "area_cm2", "density_per_cm2")]
    header += ["elapsed_s", "error"]
    from ..files.tables import atomic_write_text

    buf = StringIO()
    wr = csv.writer(buf, lineterminator="\n")
    wr.writerow(header)
    for r in result.records:
        areas = {a["name"]: a for a in r.get("areas", [])}
        row = [r["capture"], r["status"], _cell(r.get("n_protrusions"))]
        for n in names:
            a = areas.get(n, {})
            row += [_cell(a.get("count")), _cell(a.get("area_cm2")), _cell(a.get("density_per_cm2"))]
        row += [_cell(r.get("elapsed_s")), r.get("error") or ""]
        wr.writerow(row)
    atomic_write_text(result.out_dir / SUMMARY, buf.getvalue())
    write_json_atomic(result.out_dir / BATCH_JSON, _jsonable({
        "version": __version__, "cluster": result.cluster, "elapsed_s": result.elapsed_s, "timings": result.timings,
        "counts": {s: result.count(s) for s in ("done", "skipped", "failed")},
        "params": params, "captures": result.records, "mosaic": result.mosaic, "warnings": result.warnings}))


def _cell(v) -> str:
    if v is None:
        return ""
    return f"{v:.8g}" if isinstance(v, float) else str(v)


# ------------------------------------------------------------------------------------------------
# mosaics
# ------------------------------------------------------------------------------------------------

@dataclass
class Tile:
    """A tile of a mosaic: its offset in the painting (pixels) and its shape (rows, columns)."""

    name: str
    x0: float
    y0: float
    shape: tuple

    def overlap(self, other: "Tile") -> Optional[tuple]:
        """``(x_lo, y_lo, x_hi, y_hi)`` of the overlap in painting pixels, or None."""
        return overlap_box((self.x0, self.y0), self.shape, (other.x0, other.y0), other.shape)


def _first_image_shape(folder: Path) -> tuple:
    first = min(_image_files(folder))
    if Path(first).suffix.lower() in TIFF_EXTS:
        with tifffile.TiffFile(first) as tif:     # the header only
            return int(tif.pages[0].imagelength), int(tif.pages[0].imagewidth)
    return tuple(read_image(first).shape[:2])


def read_layout(path, jobs) -> dict:
    """The mosaic layout: ``{capture name: Tile}`` from a CSV with columns ``capture,x_px,y_px``.

    Checked before any work: every tile it names is a capture of the batch and every capture a tile;
    each tile overlaps another (when there are several). Shapes are read from the first image's header.
    """
    path = Path(path)
    if not path.is_file():
        raise UVPSInputError(f"mosaic: layout {path} does not exist")
    rows = list(csv.DictReader(read_text(path, "mosaic: layout", "a CSV with columns capture,x_px,y_px")
                               .splitlines()))
    if not rows or not {"capture", "x_px", "y_px"} <= set(rows[0]):
        raise UVPSInputError(f"mosaic: layout {path} must have the columns capture,x_px,y_px")
    by_name = {j.name: j for j in jobs}
    tiles = {}
    for r in rows:
        name = (r["capture"] or "").strip()
        name = Path(name).name if name not in by_name else name
        if name not in by_name:
            raise UVPSInputError(f"mosaic: layout names tile {name!r}, which is not among the captures")
        if name in tiles:
            raise UVPSInputError(f"mosaic: layout names tile {name!r} twice")
        try:
            x0, y0 = float(r["x_px"]), float(r["y_px"])
        except (TypeError, ValueError):
            raise UVPSInputError(f"mosaic: tile {name}: x_px and y_px must be numbers; got "
                                 f"{r['x_px']!r}, {r['y_px']!r}") from None
        tiles[name] = Tile(name, x0, y0, _first_image_shape(by_name[name].folder))
    missing = [j.name for j in jobs if j.name not in tiles]
    if missing:
        raise UVPSInputError(f"mosaic: capture {missing[0]} is not in the layout {path.name}")
    return _checked_tiles(tiles)


def _checked_tiles(tiles: dict) -> dict:
    """One image size for all tiles, each overlapping another: else one line naming the tile."""
    first = next(iter(tiles.values()))
    for t in tiles.values():
        if tuple(t.shape) != tuple(first.shape):
            raise UVPSInputError(f"mosaic: tile {t.name} is {t.shape[1]} x {t.shape[0]} px, tile {first.name} "
                                 f"{first.shape[1]} x {first.shape[0]} px; the tiles of a painting need one image size")
    for t in tiles.values():
        if len(tiles) > 1 and not any(t.overlap(u) for u in tiles.values() if u is not t):
            raise UVPSInputError(f"mosaic: tile {t.name} at ({t.x0:g}, {t.y0:g}) overlaps no other tile")
    return tiles


#: Orders of a grid's tiles (the captures' order): row by row left to right, or serpentine (every
#: other row right to left, as many stages move), or column by column.
GRID_ORDERS = ("rows", "snake", "columns")


def grid_layout(grid: str, jobs) -> dict:
    """The nominal layout of a regular grid: ``"COLUMNS,ROWS,OVERLAP[,ORDER]"`` (overlap a fraction of
    the tile, e.g. ``4,3,0.2``; ORDER one of :data:`GRID_ORDERS`, default ``rows``), the captures
    taken in their order (by name for a folder of captures) as the grid's tiles."""
    parts = [p.strip() for p in str(grid).split(",")]
    try:
        cols, rows, overlap = int(parts[0]), int(parts[1]), float(parts[2])
        order = parts[3] if len(parts) > 3 else "rows"
        if len(parts) > 4 or order not in GRID_ORDERS or cols < 1 or rows < 1 or not 0 < overlap < 1:
            raise ValueError
    except (ValueError, IndexError):
        raise UVPSInputError(f"mosaic: grid {grid!r}: expected COLUMNS,ROWS,OVERLAP[,ORDER] (e.g. 4,3,0.2,rows; "
                             f"overlap a fraction in (0, 1), order one of {', '.join(GRID_ORDERS)})") from None
    if cols * rows != len(jobs):
        raise UVPSInputError(f"mosaic: grid {grid!r} has {cols * rows} tiles, the batch {len(jobs)} captures")
    shapes = {j.name: _first_image_shape(j.folder) for j in jobs}
    M, N = next(iter(shapes.values()))
    step_x, step_y = round(N * (1 - overlap)), round(M * (1 - overlap))
    tiles = {}
    for k, j in enumerate(jobs):
        if order == "columns":
            c, r = divmod(k, rows)
        else:
            r, c = divmod(k, cols)
            if order == "snake" and r % 2:
                c = cols - 1 - c
        tiles[j.name] = Tile(j.name, float(c * step_x), float(r * step_y), shapes[j.name])
    return _checked_tiles(tiles)


def _stitch(out_dir: Path, layout: dict, params: dict, painting_regions, progress, warnings,
            chunk_px=None) -> dict:
    """Register and merge the tiles into ``OUT/painting/`` (:func:`uvps.painting.stitch_painting`)."""
    pxs = {}
    for t in layout.values():
        px, shape = _run_meta(out_dir / t.name)
        pxs[t.name] = px
        t.shape = tuple(shape)
    ref_name, ref = next(iter(pxs.items()))
    for name, px in pxs.items():
        if abs(px - ref) > 1e-6 * ref:
            raise UVPSInputError(f"mosaic: tile {name} has {px:g} um pixels, tile {ref_name} {ref:g} um; "
                                 "the tiles of a painting need one pixel size")
    regions = painting_regions or ("auto" if params.get("regions") == "auto" else None)
    from ..painting import stitch_painting

    res = stitch_painting(out_dir, {t.name: (t.x0, t.y0, t.shape) for t in layout.values()}, pixel_size_um=ref,
                          regions=regions, n_areas=params.get("n_areas"), chunk_px=chunk_px, progress=progress)
    warnings += res.warnings
    return res.as_dict()


def _run_meta(run_dir: Path) -> tuple:
    p = json.loads((run_dir / "run.json").read_text(encoding="utf-8"))["params"]
    return float(p["pixel_size_um"]), tuple(int(n) for n in p["image_shape"][:2])


# ------------------------------------------------------------------------------------------------
# the command
# ------------------------------------------------------------------------------------------------

def _cmd_batch(inputs: dict, params: dict, output_dir, *, progress: Progress = None) -> CommandResult:
    """``batch``: every capture run into ``OUT/<name>/`` on Dask, the summary and the mosaic."""
    own = {p.name for p in BATCH_PARAMS}
    run_params = {k: v for k, v in params.items() if k not in own}
    res = run_batch(inputs["captures"], output_dir, run_params, force=params["force"], mosaic=params["mosaic"],
                    grid=params["grid"], painting_regions=params["painting_regions"],
                    scheduler=params["scheduler"], n_workers=params["workers"], progress=progress)
    out = res.out_dir
    outputs = [OutputSpec("batch_summary", str(out / SUMMARY), kind="table"),
               OutputSpec("batch", str(out / BATCH_JSON), kind="json")]
    if res.mosaic:
        painting = out / PAINTING_DIR
        outputs += [OutputSpec("painting_protrusions", str(painting / PAINTING_PROTRUSIONS), kind="table", units="um"),
                    OutputSpec("painting_regions", str(painting / PAINTING_REGIONS), kind="table", units="cm^-2"),
                    OutputSpec("painting_layout", str(painting / PAINTING_LAYOUT), kind="table", units="px")]
    outputs += [OutputSpec(r["capture"], str(out / r["capture"]), kind="folder") for r in res.records
                if r["status"] != "failed"]
    lines = [f"{r['capture']}: {r['status']}" + (f", {r['n_protrusions']} protrusions" if r.get("n_protrusions")
                                                 is not None else "") + (f" ({r['error']})" if r["error"] else "")
             for r in res.records]
    lines.append(f"{res.count('done')} done, {res.count('skipped')} skipped, {res.count('failed')} failed in "
                 f"{res.elapsed_s:.1f} s on {res.cluster.get('workers')} workers; summary: {out / SUMMARY}")
    if res.mosaic:
        lines.append(f"painting: {res.mosaic['tiles']} tiles registered (largest pair residual "
                     f"{res.mosaic['max_residual_px']:.2f} px), {res.mosaic['n_protrusions']} protrusions "
                     f"({res.mosaic['duplicates_removed']} seen twice in overlaps); {out / PAINTING_DIR}")
    diagnostics = {"counts": {s: res.count(s) for s in ("done", "skipped", "failed")}, "cluster": res.cluster,
                   "captures": res.records, "mosaic": res.mosaic, "elapsed_s": res.elapsed_s}
    return CommandResult(outputs, diagnostics, list(res.warnings), text="\n".join(lines))


#: ``batch``'s own parameters (the others are ``run``'s).
BATCH_PARAMS = (
    Param("captures", "paths", where="inputs", positional=True, required=True,
          label="Captures (folders, a folder of capture folders, or a text list)",
          help="capture folders, a folder of capture folders, or a text file listing them (one a line)"),
    Param("scheduler", "str", label="Dask scheduler address (empty = local cluster)",
          help="address of a running Dask scheduler (e.g. tcp://host:8786); default: a local cluster"),
    Param("workers", "int", minimum=1, help="local cluster: worker processes of one thread each "
          "(default: one per core, at most one per capture)"),
    Param("force", "bool", False, help="run every capture again, even those whose run folder is complete"),
    Param("mosaic", "path", label="Mosaic layout CSV (optional)",
          help="layout CSV (capture,x_px,y_px: each tile's nominal corner in the painting, in pixels): register "
               "the tiles and merge them into OUT/painting/ (refined layout.csv, painting_protrusions.csv, "
               "painting_regions.csv)"),
    Param("grid", "str", label="Grid of the tiles COLUMNS,ROWS,OVERLAP[,ORDER] (instead of a layout)",
          help="instead of a layout: the captures (in order) are a regular grid, e.g. 4,3,0.2 (overlap a "
               "fraction of the tile) or 4,3,0.2,snake (orders: rows, snake, columns)"),
    Param("painting_regions", "path", label="Painting-wide colour-area label TIFF (optional)",
          help="a label TIFF in the layout's frame (names in a CSV beside it): the painting's colour areas; "
               "default: proposed on the painting's albedo with --regions auto"),
)


def _batch_spec() -> CommandSpec:
    params = BATCH_PARAMS[:1] + tuple(p for p in CAPTURE_PARAMS if p.name != "images") + OPTION_PARAMS \
        + PROTRUSION_PARAMS + OUTPUT_PARAMS + BATCH_PARAMS[1:]
    return CommandSpec(
        "batch", "many captures, each as uvps run, on a Dask cluster; summary and mosaics", _cmd_batch,
        params=params, output="batch folder", menu="Stitch Painting",
        description="Each capture folder is run as `uvps run` (same parameters) into OUT/<capture name>/ on a "
                    "Dask cluster (a local one of one process per core, or --scheduler); run folders appear "
                    "whole or not at all, complete ones are skipped (unless --force), a failing capture is "
                    "listed with its error. lights, mask, dark and regions name one file for all captures or "
                    "a file name found in each capture folder. Writes batch_summary.csv and batch.json; with "
                    "--mosaic or --grid the tiles are registered and merged into OUT/painting/ (docs/painting.md).")


SPECS = (_batch_spec(),)
