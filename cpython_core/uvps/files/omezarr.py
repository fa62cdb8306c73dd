"""OME-Zarr copies of a run folder's results: multiscale image pyramids for large-image viewers.

A run folder holds its results as ImageJ TIFFs (``depth.tif``, ``normals.tif``, ``albedo.tif``). A
whole painting at 15 um per pixel is tens of thousands of pixels a side; viewers that stream such
images by tiles and levels (napari with napari-ome-zarr, Fiji's "HDF5/N5/Zarr/OME-NGFF" reader,
BigDataViewer and MoBIE, vizarr in a browser) read OME-Zarr. :func:`write_ome_zarr` writes one
OME-Zarr image per result beside the TIFFs (``uvps run --ome-zarr``, or ``uvps ome-zarr RUN`` for
an existing run folder):

- ``depth.ome.zarr`` (y, x), micrometres; ``normals.ome.zarr`` (c, y, x: nx, ny, nz);
  ``albedo.ome.zarr`` ((c,) y, x), with the protrusion and colour-area label images, when the run
  has them, as OME-Zarr labels (``albedo.ome.zarr/labels/protrusions``, ``.../labels/regions``) so
  a viewer overlays them on the albedo.
- OME-NGFF 0.4 (Zarr format 2, chunk keys with "/"): the version the Fiji and napari readers of
  2024-2026 all read. Level 0 holds the TIFF's float32 values exactly; level k averages 2 x 2
  pixels of level k-1 (normals renormalised, labels take the top-left pixel: a label is never
  averaged), down to the first level under :data:`MIN_LEVEL_PX` a side. Each level's scale is the
  pixel size times 2^k and its translation puts the pixel centre where the averaged pixels' centre
  was, so every level overlays level 0 in micrometres.

The conversion reads the TIFFs memory-mapped and writes band by band (:data:`uvps.files.io.BAND_BYTES`),
so memory stays at a few bands whatever the image's size. The zarr library does the chunking and
compression (Blosc zstd with byte shuffle); the NGFF metadata (``multiscales``, ``omero``,
``image-label``) are written here because they are plain JSON attributes of the group.

Reference: OME-NGFF 0.4, https://ngff.openmicroscopy.org/0.4/ (Moore et al., Nature Methods 18, 2021).
"""
from __future__ import annotations

import logging
import shutil
import tempfile
from dataclasses import dataclass
from pathlib import Path
from typing import Optional

import numpy as np
import tifffile

from .. import __version__
from ..errors import UVPSInputError
from .io import BAND_BYTES, _tiff_pixel_size_um, read_tiff
from .outputs import Progress, replace_dir, report

log = logging.getLogger(__name__)

__all__ = ["NGFF_VERSION", "MIN_LEVEL_PX", "CHUNK_PX", "ZarrImage", "IMAGES", "LABELS", "write_ome_zarr",
           "write_dask_ome_zarr", "write_dask_ome_labels", "StoreBatch"]

#: The OME-NGFF version written (Zarr format 2).
NGFF_VERSION = "0.4"
#: Levels are added until the image is under this many pixels on its longer side.
MIN_LEVEL_PX = 512
#: Chunks of CHUNK_PX x CHUNK_PX pixels (one channel each): 4 MB of float32, a viewer's tile.
CHUNK_PX = 1024


@dataclass(frozen=True)
class ZarrImage:
    """One result written as OME-Zarr: its TIFF in the run folder and how to describe it."""

    name: str            # the store is <name>.ome.zarr
    tiff: str
    channels: tuple      # channel labels of a (C, Y, X) image; () for (Y, X)
    kind: str = "float"  # float | normals | label
    unit: str = ""       # the values' unit, recorded in the group's "uvps" attributes


#: The run folder's results written by :func:`write_ome_zarr`, in order.
IMAGES = (
    ZarrImage("depth", "depth.tif", (), unit="micrometer"),
    ZarrImage("normals", "normals.tif", ("nx", "ny", "nz"), kind="normals"),
    ZarrImage("albedo", "albedo.tif", ("R", "G", "B"), unit="counts"),
)
#: Label images attached to the albedo when the run folder has them.
LABELS = (
    ZarrImage("protrusions", "protrusions_labels.tif", (), kind="label"),
    ZarrImage("regions", "regions_labels.tif", (), kind="label"),
)


def _zarr():
    try:
        import zarr
    except ImportError as exc:  # Python < 3.11 installs uvps without zarr (zarr 3 needs 3.11)
        raise UVPSInputError("OME-Zarr output needs the zarr package (Python >= 3.11): "
                             "pip install 'zarr>=3.1'") from exc
    return zarr


def open_tiff(path: Path) -> np.ndarray:
    """The TIFF's data memory-mapped read-only (uvps writes them uncompressed), else read whole."""
    try:
        return tifffile.memmap(path, mode="r")
    except (ValueError, OSError):
        return np.asarray(read_tiff(path).data)


def _levels(shape_yx: tuple) -> list:
    """(rows, cols) of every level: level k is level k-1 halved (floor), until under MIN_LEVEL_PX."""
    levels = [tuple(int(n) for n in shape_yx)]
    while max(levels[-1]) > MIN_LEVEL_PX and min(levels[-1]) >= 2:
        levels.append((levels[-1][0] // 2, levels[-1][1] // 2))
    return levels


def _halve(block: np.ndarray, kind: str) -> np.ndarray:
    """2 x 2 reduction of a (..., 2r, 2c) block: mean for values (normals renormalised), the
    top-left pixel for labels."""
    if kind == "label":
        return block[..., ::2, ::2]
    r, c = block.shape[-2] // 2, block.shape[-1] // 2
    b = block[..., :2 * r, :2 * c].astype(np.float32, copy=False)
    out = 0.25 * (b[..., 0::2, 0::2] + b[..., 1::2, 0::2] + b[..., 0::2, 1::2] + b[..., 1::2, 1::2])
    if kind == "normals":
        norm = np.sqrt(np.sum(out * out, axis=0, keepdims=True))
        out = out / np.where(norm > 0, norm, 1.0)
    return out.astype(np.float32, copy=False)


def _multiscales(name: str, levels: list, channel: bool, pixel_size_um: float) -> list:
    axes = ([{"name": "c", "type": "channel"}] if channel else []) + [
        {"name": "y", "type": "space", "unit": "micrometer"},
        {"name": "x", "type": "space", "unit": "micrometer"}]
    datasets = []
    for k in range(len(levels)):
        s = pixel_size_um * 2 ** k
        # a level-k pixel averages 2^k x 2^k level-0 pixels: its centre is (2^k - 1) / 2 of them in
        t = pixel_size_um * (2 ** k - 1) / 2.0
        lead = [1.0] if channel else []
        zero = [0.0] if channel else []
        datasets.append({"path": str(k), "coordinateTransformations": [
            {"type": "scale", "scale": lead + [s, s]}, {"type": "translation", "translation": zero + [t, t]}]})
    return [{"version": NGFF_VERSION, "name": name, "axes": axes, "datasets": datasets,
             "type": "mean (2 x 2)", "metadata": {"method": "uvps.files.omezarr._halve", "version": __version__}}]


def _omero(image: ZarrImage, channels: list, low: np.ndarray) -> dict:
    """Display settings: each channel's label and its 0.5-99.5 % range (from the smallest level)."""
    chans = []
    colours = {"R": "FF0000", "G": "00FF00", "B": "0000FF"}
    for i, label in enumerate(channels or [image.name]):
        plane = low[i] if channels else low
        finite = plane[np.isfinite(plane)]
        lo, hi = (np.percentile(finite, [0.5, 99.5]).tolist() if finite.size else [0.0, 1.0])
        if hi <= lo:
            hi = lo + 1.0
        chans.append({"label": str(label), "active": True, "coefficient": 1.0, "family": "linear",
                      "inverted": False, "color": colours.get(str(label), "FFFFFF"),
                      "window": {"start": float(lo), "end": float(hi),
                                 "min": float(np.nanmin(plane)) if finite.size else 0.0,
                                 "max": float(np.nanmax(plane)) if finite.size else 1.0}})
    return {"name": image.name, "version": NGFF_VERSION, "channels": chans,
            "rdefs": {"model": "color" if len(chans) == 3 and image.kind != "normals" else "greyscale"}}


def _write_image(group, image: ZarrImage, data: np.ndarray, pixel_size_um: float) -> list:
    """Write ``data`` ((Y, X) or (C, Y, X)) and its pyramid into the zarr ``group``; returns the
    levels' shapes (rows, cols)."""
    from numcodecs import Blosc

    channel = data.ndim == 3
    lead = data.shape[:1] if channel else ()
    levels = _levels(data.shape[-2:])
    # labels stay integers (ImageJ holds more than 65535 labels as float32: uint32 here, as NGFF asks)
    dtype = np.dtype(np.float32) if image.kind != "label" else (
        np.dtype(data.dtype) if np.issubdtype(data.dtype, np.integer) else np.dtype(np.uint32))
    compressor = Blosc(cname="zstd", clevel=3, shuffle=Blosc.SHUFFLE)
    arrays = []
    for k, (rows, cols) in enumerate(levels):
        arrays.append(group.create_array(
            str(k), shape=lead + (rows, cols), chunks=(1,) * len(lead) + (min(CHUNK_PX, rows), min(CHUNK_PX, cols)),
            dtype=dtype, compressors=compressor, fill_value=0,
            chunk_key_encoding={"name": "v2", "separator": "/"},
            # every chunk is written, also one that is all zero: a store never holds a chunk that
            # is not this run's (zarr skips empty chunks by default)
            config={"write_empty_chunks": True}))
    # level 0: the TIFF's values, band by band; each later level from the one before, read back
    row_bytes = int(np.prod(lead or (1,))) * data.shape[-1] * dtype.itemsize
    band = max(2 * CHUNK_PX, (BAND_BYTES // max(row_bytes, 1)) // CHUNK_PX * CHUNK_PX)
    for r0 in range(0, data.shape[-2], band):
        rows = slice(r0, min(data.shape[-2], r0 + band))
        arrays[0][(slice(None),) * len(lead) + (rows,)] = np.asarray(data[..., rows, :]).astype(dtype, copy=False)
    for k in range(1, len(levels)):
        src, dst = arrays[k - 1], arrays[k]
        for r0 in range(0, levels[k][0], band // 2):
            r1 = min(levels[k][0], r0 + band // 2)
            block = np.asarray(src[(slice(None),) * len(lead) + (slice(2 * r0, 2 * r1),)])
            dst[(slice(None),) * len(lead) + (slice(r0, r1),)] = \
                _halve(block, image.kind)[..., :r1 - r0, :levels[k][1]].astype(dtype, copy=False)
    return levels


def write_ome_zarr(run_dir, *, out_dir=None, pixel_size_um: Optional[float] = None,
                   progress: Progress = None) -> list:
    """Write the run folder's results as OME-Zarr image pyramids (OME-NGFF 0.4).

    Parameters
    ----------
    run_dir : path
        A run folder holding at least one of ``depth.tif``, ``normals.tif``, ``albedo.tif``.
    out_dir : path, optional
        Where the ``<name>.ome.zarr`` stores go (default ``run_dir``). Each store is written to a
        temporary folder beside it and renamed into place; an older store of that name is replaced
        whole, never merged.
    pixel_size_um : float, optional
        Overrides the TIFFs' calibration.
    progress : callable, optional
        ``progress(fraction, message)``.

    Returns
    -------
    list of Path
        The stores written.
    """
    zarr = _zarr()
    run_dir = Path(run_dir)
    out_dir = Path(out_dir) if out_dir is not None else run_dir
    todo = [im for im in IMAGES if (run_dir / im.tiff).is_file()]
    if not todo:
        raise UVPSInputError(f"run folder {run_dir} has none of depth.tif, normals.tif, albedo.tif; "
                             "run the 'run' command first")
    labels = [lb for lb in LABELS if (run_dir / lb.tiff).is_file()]
    written = []
    for i, image in enumerate(todo):
        path = run_dir / image.tiff
        data = open_tiff(path)
        px = pixel_size_um or read_tiff_pixel_size(path)
        if px is None:
            raise UVPSInputError(f"{path}: no pixel size in the TIFF; give pixel_size_um")
        if data.ndim not in (2, 3):
            raise UVPSInputError(f"{path}: expected a (Y, X) or (C, Y, X) image; got shape {data.shape}")
        channels = list(image.channels[:data.shape[0]]) if data.ndim == 3 else []
        final = out_dir / f"{image.name}.ome.zarr"
        tmp = Path(tempfile.mkdtemp(prefix="." + final.name + ".tmp-", dir=out_dir))
        try:
            root = zarr.open_group(str(tmp), mode="w", zarr_format=2)
            levels = _write_image(root, image, data, px)
            low = np.asarray(root[str(len(levels) - 1)])
            root.attrs.update({"multiscales": _multiscales(image.name, levels, data.ndim == 3, px),
                               "omero": _omero(image, channels, low),
                               "uvps": {"source": image.tiff, "unit": image.unit, "version": __version__}})
            if image.name == "albedo" and labels:
                group = root.create_group("labels")
                names = []
                for lb in labels:
                    lab = open_tiff(run_dir / lb.tiff)
                    if lab.shape != data.shape[-2:]:
                        log.warning("%s: %s is not the albedo's size; not attached", final, lb.tiff)
                        continue
                    sub = group.create_group(lb.name)
                    lv = _write_image(sub, lb, lab, px)
                    sub.attrs.update({"multiscales": _multiscales(lb.name, lv, False, px),
                                      "image-label": {"version": NGFF_VERSION, "source": {"image": "../../"}}})
                    names.append(lb.name)
                group.attrs["labels"] = names
            del root
            replace_dir(tmp, final)
        except BaseException:
            shutil.rmtree(tmp, ignore_errors=True)
            raise
        written.append(final)
        report(progress, (i + 1) / len(todo), f"OME-Zarr {final.name}")
    return written


def read_tiff_pixel_size(path: Path) -> Optional[float]:
    """The pixel size (um) a TIFF written by uvps records, or None."""
    with tifffile.TiffFile(path) as tif:
        return _tiff_pixel_size_um(tif)


class StoreBatch:
    """The stores of several OME-Zarr pyramids run together: one Dask graph per pyramid level for all
    of them (:func:`write_dask_ome_zarr`, :func:`write_dask_ome_labels` with ``batch=``), then each
    store's last step (its metadata, the rename into place) in the order the stores were added.

    On a ``distributed`` cluster a graph is a round trip of the scheduler and its workers: the five
    maps of a small painting as one graph per map and level took 10 graphs (``uvps.painting``); a
    batch takes one per level. Level k of every pyramid is read back from level k-1 of its store, so
    the levels run one after the other.
    """

    def __init__(self, *, joint: bool = True):
        self.joint = joint
        self.levels = []      # per level: [(dask array, zarr array)]
        self.finish = []      # callables, in order
        self.temporaries = []

    def store(self, k: int, source, target) -> None:
        """Store ``source`` (level ``k`` of a pyramid) into ``target`` when the batch runs. Not ``joint``:
        each store a graph of its own, in the order they were added (as a store written alone: the
        caller's in-memory arrays embedded in one graph each, not in one graph together, which
        distributed warns about above 10 MB)."""
        if not self.joint:
            self.levels.append([(source, target)])
            return
        while len(self.levels) <= k:
            self.levels.append([])
        self.levels[k].append((source, target))

    def run(self) -> None:
        """Every level's stores (one ``dask.array.store`` each), then every store's last step; on an
        error, the stores' temporary folders are removed."""
        import dask.array as da
        try:
            for pairs in self.levels:
                da.store([src for src, _ in pairs], [dst for _, dst in pairs], lock=False)
            for fn in self.finish:
                fn()
        except BaseException:
            for tmp in self.temporaries:
                shutil.rmtree(tmp, ignore_errors=True)
            raise


def write_dask_ome_zarr(final, image: ZarrImage, data, pixel_size_um: float, *, chunk_px: int = CHUNK_PX,
                        labels=(), origin_um=(0.0, 0.0), batch: Optional[StoreBatch] = None) -> Path:
    """Write a Dask array ((Y, X) or (C, Y, X), chunked ``chunk_px`` a side) as an OME-Zarr image
    pyramid, chunk by chunk: no level is ever whole in memory, and on a ``distributed`` cluster the
    chunks are computed and written by its workers (they must see ``final``'s folder).

    Level 0 is ``data``; level k halves level k-1 as :func:`write_ome_zarr` does (read back from
    the store, 2 x 2 chunks of level k-1 per chunk of level k). ``labels``: ``(ZarrImage, dask
    array)`` pairs attached as OME-Zarr labels of this image, or ``(ZarrImage, path)`` of a label
    image already stored (:func:`write_dask_ome_labels`), whose files are copied. ``origin_um``:
    the (y, x) translation of pixel (0, 0). Written to a temporary folder and renamed into place.
    ``batch``: only added to it (written by ``batch.run()``, with the batch's other stores; a label
    image given as a path is copied then, so it may be one of the batch's own, added before).
    """
    zarr = _zarr()
    final = Path(final)
    tmp = Path(tempfile.mkdtemp(prefix="." + final.name + ".tmp-", dir=final.parent))
    own = batch is None
    batch = StoreBatch(joint=False) if own else batch
    batch.temporaries.append(tmp)
    try:
        root = zarr.open_group(str(tmp), mode="w", zarr_format=2)
        levels = _store_pyramid(root, image, data, chunk_px, batch)
        after_labels = _store_labels(zarr, tmp / "labels", labels, pixel_size_um, chunk_px, origin_um,
                                     source="../../", batch=batch) if labels else None

        def finish():
            low = np.asarray(root[str(len(levels) - 1)])
            ms = _multiscales(image.name, levels, data.ndim == 3, pixel_size_um)
            _translate(ms, origin_um, data.ndim == 3)
            channels = list(image.channels[:data.shape[0]]) if data.ndim == 3 else []
            root.attrs.update({"multiscales": ms, "omero": _omero(image, channels, low),
                               "uvps": {"unit": image.unit, "version": __version__}})
            if after_labels is not None:
                after_labels()
            replace_dir(tmp, final)

        batch.finish.append(finish)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    if own:
        batch.run()
    return final


def write_dask_ome_labels(final, labels, pixel_size_um: float, *, image: str, chunk_px: int = CHUNK_PX,
                          origin_um=(0.0, 0.0), batch: Optional[StoreBatch] = None) -> Path:
    """Write label images (``(ZarrImage, dask array)`` pairs, (Y, X) integers) as an OME-Zarr store
    of their own: an NGFF labels group (``{"labels": [...]}``) at its root, each label image a
    multiscale image-label under it (``final/<name>/0, 1, ...``, pyramids as
    :func:`write_dask_ome_zarr` builds them) whose ``source`` is ``image`` (the path, from the
    label image, of the image it labels, e.g. ``"../../albedo.ome.zarr"``). Chunk by chunk; written
    to a temporary folder and renamed into place (``batch``: as :func:`write_dask_ome_zarr`'s).
    """
    zarr = _zarr()
    final = Path(final)
    tmp = Path(tempfile.mkdtemp(prefix="." + final.name + ".tmp-", dir=final.parent))
    own = batch is None
    batch = StoreBatch(joint=False) if own else batch
    batch.temporaries.append(tmp)
    try:
        after = _store_labels(zarr, tmp, labels, pixel_size_um, chunk_px, origin_um, source=image, batch=batch)

        def finish():
            after()
            replace_dir(tmp, final)

        batch.finish.append(finish)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    if own:
        batch.run()
    return final


def _store_labels(zarr, folder: Path, labels, pixel_size_um, chunk_px, origin_um, *, source: str, batch: StoreBatch):
    """An NGFF labels group at ``folder``: each label image stored from its Dask array (added to
    ``batch``), or copied file by file from a label image already stored (a path); returns the step
    to take once ``batch``'s stores are written: the copies, and every label image pointed at ``source``."""
    group = zarr.open_group(str(folder), mode="w", zarr_format=2)
    stored = []
    for lb, arr in labels:
        if isinstance(arr, (str, Path)):
            continue
        sub = group.create_group(lb.name)
        lv = _store_pyramid(sub, lb, arr, chunk_px, batch)
        ms = _multiscales(lb.name, lv, False, pixel_size_um)
        _translate(ms, origin_um, False)
        sub.attrs["multiscales"] = ms
        stored.append(lb.name)

    def after():
        for lb, arr in labels:
            if isinstance(arr, (str, Path)):
                # the same chunks, compressor and metadata: a copy of the files is the same label image
                shutil.copytree(arr, folder / lb.name)
                sub = zarr.open_group(str(folder / lb.name), mode="r+", zarr_format=2)
            else:
                sub = group[lb.name]
            sub.attrs["image-label"] = {"version": NGFF_VERSION, "source": {"image": source}}
        group.attrs["labels"] = [lb.name for lb, _ in labels]

    return after


def _translate(ms: list, origin_um, channel: bool) -> None:
    for d in ms[0]["datasets"]:
        t = d["coordinateTransformations"][1]["translation"]
        t[-2] += float(origin_um[0])
        t[-1] += float(origin_um[1])


def _store_pyramid(group, image: ZarrImage, data, chunk_px: int, batch: StoreBatch) -> list:
    """Every level of ``data`` (a Dask array) added to ``batch``'s stores, into ``group`` chunk by chunk."""
    import dask.array as da
    from numcodecs import Blosc

    lead = data.shape[:-2]
    levels = _levels(data.shape[-2:])
    dtype = np.dtype(np.float32) if image.kind != "label" else np.dtype(np.uint32)
    compressor = Blosc(cname="zstd", clevel=3, shuffle=Blosc.SHUFFLE)
    arrays = [group.create_array(
        str(k), shape=lead + (rows, cols), chunks=(1,) * len(lead) + (min(chunk_px, rows), min(chunk_px, cols)),
        dtype=dtype, compressors=compressor, fill_value=0, chunk_key_encoding={"name": "v2", "separator": "/"},
        config={"write_empty_chunks": True}) for k, (rows, cols) in enumerate(levels)]
    level = data.astype(dtype).rechunk((1,) * len(lead) + (chunk_px, chunk_px))
    batch.store(0, level, arrays[0])
    for k in range(1, len(levels)):
        # normals are renormalised over their channels: a block holds all of them
        lead_chunks = tuple(lead) if image.kind == "normals" else (1,) * len(lead)
        prev = da.from_array(arrays[k - 1], chunks=lead_chunks + (2 * chunk_px, 2 * chunk_px))
        rows, cols = levels[k]
        half = prev.map_blocks(lambda b: _halve(b, image.kind).astype(dtype, copy=False), dtype=dtype,
                               chunks=prev.chunks[:-2] + (tuple(c // 2 for c in prev.chunks[-2]),
                                                          tuple(c // 2 for c in prev.chunks[-1])))
        half = half[..., :rows, :cols].rechunk((1,) * len(lead) + (chunk_px, chunk_px))
        batch.store(k, half, arrays[k])
    return levels
