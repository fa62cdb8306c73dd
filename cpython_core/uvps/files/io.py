"""Reading captures, light files and masks; writing ImageJ TIFFs; SHA-256 of files.

A *capture* is K photographs of the same field of view, one per lamp position, as a float32
stack ``(K, M, N)`` (grey) or ``(K, M, N, 3)`` (RGB) in the file's own counts (see
:class:`Capture`). Nothing here rescales intensities: a uint16 TIFF stays in 0..65535 and a
uint8 JPEG in 0..255, so a saturation threshold and a dark frame keep their meaning.

Formats: TIFF (tifffile; uint8, uint16, float32, grey or RGB, single files or one multi-page
stack including ImageJ hyperstacks), PNG (8/16-bit, read with OpenCV because Pillow silently
reduces 16-bit RGB PNGs to 8 bits) and JPEG (imageio). Alpha channels are dropped.

Every error in the input raises :class:`~uvps.errors.UVPSInputError` with one line naming the
file or parameter. Inputs are only ever opened for reading.
"""
from __future__ import annotations

import contextlib
import dataclasses
import fnmatch
import functools
import hashlib
import logging
import math
import mmap
import os
import re
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import NamedTuple, Optional, Sequence, Union

import numpy as np
import tifffile

from ..errors import UVPSInputError, check_pixel_size
from ..core.progress import Progress, report
from ..core.stack import Capture, LazyStack, RawParts, StackView, raw_parts, row_bands
from ..core.threads import Background, default_threads
from .atomic import atomic_path
from .lightfiles import LightFile, LightPositions, read_lp, read_positions, read_text  # noqa: F401  (re-exported)
from .raw import RAW_DEVELOP, _rawpy, raw_image_size, raw_reading, read_raw  # noqa: F401  (camera raw files; RAW_DEVELOP re-exported)

log = logging.getLogger(__name__)

PathLike = Union[str, os.PathLike]


TIFF_EXTS = (".tif", ".tiff")
PNG_EXTS = (".png",)
JPEG_EXTS = (".jpg", ".jpeg")
#: Camera raw files, read linearly by LibRaw (rawpy): :func:`read_raw`.
RAW_EXTS = (".dng", ".cr2", ".cr3", ".nef", ".arw")
IMAGE_EXTS = TIFF_EXTS + PNG_EXTS + JPEG_EXTS + RAW_EXTS

#: Length units found in TIFF/ImageJ metadata, in micrometres.
_UNIT_UM = {
    "micron": 1.0, "microns": 1.0, "um": 1.0, "\u00b5m": 1.0, "\u03bcm": 1.0,
    "\\u00b5m": 1.0, "nm": 1e-3, "mm": 1e3, "cm": 1e4, "m": 1e6, "inch": 25400.0, "in": 25400.0,
}
#: Resolutions (dots per inch) that software writes when it does not know the physical size
#: (screen and print defaults); a TIFF claiming one of them is treated as uncalibrated.
_DEFAULT_DPI = frozenset({72.0, 96.0, 150.0, 240.0, 300.0, 350.0})
#: ImageJ hyperstack axis order (a written stack's axes must be a subsequence of it).
_IMAGEJ_AXES = "TZCYXS"
#: Above this many bytes tifffile writes ImageJ's own > 4 GB layout (see write_imagej_tiff).
#: tifffile's own BigTIFF threshold, 4 GiB less 32 MiB for the metadata.
LARGE_TIFF_BYTES = 2**32 - 2**25


class MappedStack(LazyStack):
    """K image files of one shape and dtype seen as one ``(K, M, N[, C])`` stack, never loaded whole.

    Each file is memory-mapped read-only (uncompressed TIFFs: :func:`tifffile.memmap`); indexing
    returns a copy in the files' dtype, as indexing an array would (``[k]``, ``[k, rows, cols]``,
    ``[:, rows, cols]`` with slices or ints, ``[:, r, c]`` with two index arrays of one shape), then
    tells the kernel that this process no longer needs the pages it touched: they stay in the page
    cache (a second pass reads them from memory) but not in the process's resident set, so a stack
    larger than the memory can be processed band by band, and peak memory is that of the bands.
    """

    def __init__(self, maps):
        self.maps = list(maps)
        self.shape = (len(self.maps),) + tuple(self.maps[0].shape)
        self.ndim = len(self.shape)
        # in this machine's byte order: ImageJ writes big-endian TIFFs, which compiled kernels cannot
        # read; each indexed copy is converted as it is made
        self.dtype = self.maps[0].dtype.newbyteorder("=")
        self.nbytes = int(np.prod(self.shape)) * self.dtype.itemsize

    def __getitem__(self, key):
        key = key if isinstance(key, tuple) else (key,)
        if any(k is Ellipsis or k is None for k in key):
            # `[...]` on an array is the whole array: here that would read every file; say so instead
            raise IndexError("a MappedStack is indexed by image and band ([k], [k, rows, cols], [:, rows, cols]); "
                             "its whole content is .load()")
        kk, rest = key[0], key[1:]
        if isinstance(kk, (int, np.integer)):
            return self._take(int(kk), rest)
        ks = np.arange(self.shape[0])[kk]
        parts = [self._take(int(k), rest) for k in ks]
        if not parts:
            return np.empty((0,) + self.shape[1:], self.dtype)[(slice(None),) + rest]
        return np.stack(parts)

    def _take(self, k, rest):
        m = self.maps[k]
        out = np.array(m[rest], dtype=self.dtype, copy=True)
        release(m)
        return out

    def raw_parts(self, k: int, rows: slice, cols: slice):
        """Image ``k``'s band as mapped, its pages released once read (:class:`uvps.core.stack.RawParts`)."""
        m = self.maps[k]
        return RawParts(m[rows, cols], done=lambda: release(m)) if m.dtype.isnative else None


def release(arr) -> None:
    """Drop a memory-mapped array's pages from this process's resident set (they stay cached)."""
    mm = getattr(arr, "_mmap", None)
    if mm is not None and hasattr(mm, "madvise") and hasattr(mmap, "MADV_DONTNEED"):
        with contextlib.suppress(OSError, ValueError):
            mm.madvise(mmap.MADV_DONTNEED)


def _map_tiff(path: Path):
    """A one-image uncompressed TIFF memory-mapped as ``(M, N)`` or ``(M, N, 3)`` and its pixel size
    in um (or None); None for anything else (compressed, planar, several pages, not a TIFF)."""
    if _kind(path) != "tiff":
        return None
    with contextlib.suppress(Exception):
        with tifffile.TiffFile(path) as tif:
            series = tif.series[0]
            if series.dataoffset is None or len(tif.pages) != 1:
                return None
            axes = series.axes.upper()
            px = _tiff_pixel_size_um(tif)
        if axes not in ("YX", "YXS"):
            return None
        arr = tifffile.memmap(path, mode="r")
        if arr.ndim == 3 and arr.shape[2] == 4:
            arr = arr[..., :3]
        return arr, px
    return None


#: Compressed TIFFs whose stack is larger than this (bytes; None: the environment variable
#: ``UVPS_SCRATCH_ABOVE_BYTES`` if set, else a quarter of the physical memory) are decoded once into
#: scratch files and memory-mapped (:func:`_scratch_tiff`), not held in memory.
SCRATCH_ABOVE_BYTES: Optional[int] = None


def _scratch_tiff(path: Path):
    """A one-image integer TIFF that cannot be mapped (compressed: LZW, Deflate... as raw converters
    write them) decoded into an unlinked scratch file in the temporary folder (``TMPDIR``) and
    memory-mapped there, as :func:`_map_tiff` returns it; None for anything else.

    The file is unlinked as soon as it is mapped: the mapping keeps its data, and the disk space is
    freed when the stack is, even if the process is killed. Decoded by tifffile straight into the
    map (:func:`_decode_to_scratch`): the process never holds the image.
    """
    if _kind(path) != "tiff":
        return None
    with contextlib.suppress(Exception):
        with tifffile.TiffFile(path) as tif:
            series = tif.series[0]
            if len(tif.pages) != 1 or series.axes.upper() not in ("YX", "YXS"):
                return None
            shape, dtype, px = tuple(series.shape), np.dtype(series.dtype), _tiff_pixel_size_um(tif)
        if not np.issubdtype(dtype, np.integer):
            return None
        arr = _decode_to_scratch(path, shape, dtype)
        if arr.ndim == 3 and arr.shape[2] == 4:
            arr = arr[..., :3]
        return arr, px
    return None


def _scratch_wanted(sources: list) -> bool:
    """Whether the files' stack is large enough to go to scratch files (:data:`SCRATCH_ABOVE_BYTES`)
    and the temporary folder has room for it."""
    import shutil
    import tempfile

    limit = SCRATCH_ABOVE_BYTES
    env = os.environ.get("UVPS_SCRATCH_ABOVE_BYTES")
    if limit is None and env:
        try:
            limit = int(env)
        except ValueError:
            raise UVPSInputError(f"UVPS_SCRATCH_ABOVE_BYTES must be a whole number of bytes; got {env!r}") from None
    with contextlib.suppress(Exception):
        with tifffile.TiffFile(sources[0].path) as tif:
            nbytes = len(sources) * int(np.prod(tif.series[0].shape)) * np.dtype(tif.series[0].dtype).itemsize
        if limit is None:
            limit = os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES") // 4
        if nbytes <= limit:
            return False
        free = shutil.disk_usage(tempfile.gettempdir()).free
        if free < 1.1 * nbytes:
            log.info("the compressed stack (%.1f GB) is read into memory: the temporary folder %s has "
                     "%.1f GB free", nbytes / 1e9, tempfile.gettempdir(), free / 1e9)
            return False
        return True
    return False


def _check_like_first(arr, px, path, first_path, *, shape, dtype, tag_px) -> None:
    """One image of a capture read from files: the first file's shape and dtype, its pixel size when
    ``tag_px`` (the first file's, None: not checked) and both carry one, and a usable image
    (:func:`_check_image`)."""
    if tag_px is not None and px is not None and not math.isclose(px, tag_px, rel_tol=1e-4):
        raise UVPSInputError(f"image {path} has pixel size {px:.6g} um in its TIFF tags;"
                             f" expected {tag_px:.6g} um like {Path(first_path).name}")
    if arr.shape != shape or arr.dtype != dtype:
        raise UVPSInputError(f"image {path} is {arr.shape} {arr.dtype};"
                             f" expected {shape} {dtype} like {Path(first_path).name}")
    _check_image(arr, str(path))


def _map_files(sources: list, progress: Progress, *, check_px: bool, mapper=None):
    """The files as a :class:`MappedStack` (-> (stack, dtype, pixel size or None)), or None when one
    of them cannot be mapped (compressed, planar, not a TIFF) or is not integer. ``mapper`` (default
    :func:`_map_tiff`) maps one file."""
    mapper = _map_tiff if mapper is None else mapper
    first = mapper(sources[0].path)
    if first is None or not np.issubdtype(first[0].dtype, np.integer):
        return None
    maps, tag_px = [], first[1]
    shape, dtype = first[0].shape, first[0].dtype
    for i, src in enumerate(sources):
        got = first if i == 0 else mapper(src.path)
        if got is None:
            return None
        arr, px = got
        _check_like_first(arr, px, src.path, sources[0].path, shape=shape, dtype=dtype,
                          tag_px=tag_px if check_px else None)
        release(arr)
        maps.append(arr)
        report(progress, (i + 1) / (len(sources) + 1), f"mapped {src.path.name}")
    return MappedStack(maps), np.dtype(dtype).newbyteorder("="), tag_px


class TiffData(NamedTuple):
    """A TIFF read back: the array as stored and the pixel size (um) if the file has one."""

    data: np.ndarray
    pixel_size_um: Optional[float]


@dataclass
class _Source:
    """One image of a capture: a file, or one plane of a stack."""

    label: str
    path: Path


# ---------------------------------------------------------------------------------------------
# small helpers


def _natural_key(name: str):
    # Natural order ("img2" before "img10"); the standard library has no such sort and natsort
    # is not a dependency.
    return [int(t) if t.isdigit() else t.lower() for t in re.split(r"(\d+)", name)]


def _is_image(path: Path) -> bool:
    return path.suffix.lower() in IMAGE_EXTS


def _kind(path: Path) -> str:
    ext = path.suffix.lower()
    if ext in TIFF_EXTS:
        return "tiff"
    if ext in PNG_EXTS:
        return "png"
    if ext in JPEG_EXTS:
        return "jpeg"
    if ext in RAW_EXTS:
        return "raw"
    raise UVPSInputError(
        f"{path}: not a supported image file; expected one of {', '.join(IMAGE_EXTS)}"
    )


def _basename(name: str) -> str:
    # .lp files written on Windows use backslashes.
    return name.replace("\\", "/").rsplit("/", 1)[-1]


def _drop_alpha(arr: np.ndarray) -> np.ndarray:
    """(M, N, 4) -> (M, N, 3), (M, N, 2) grey+alpha -> (M, N), (M, N, 1) -> (M, N)."""
    if arr.ndim == 3:
        if arr.shape[2] == 4:
            return arr[..., :3]
        if arr.shape[2] in (1, 2):
            return arr[..., 0]
    return arr


def _saturation_of(dtype: np.dtype) -> Optional[float]:
    return float(np.iinfo(dtype).max) if np.issubdtype(dtype, np.integer) else None


def srgb_to_linear(values: np.ndarray, full_scale: float, *, out: Optional[np.ndarray] = None
                   ) -> np.ndarray:
    """Apply the sRGB EOTF (IEC 61966-2-1) to counts in ``0..full_scale``.

    Parameters
    ----------
    values : ndarray
        sRGB-encoded counts.
    full_scale : float
        The count of encoded 1.0 (255 for 8-bit files).
    out : ndarray, optional
        float32 array to write into (may be ``values`` itself), to avoid a copy.

    Returns
    -------
    ndarray
        float32 linear values in the same ``0..full_scale`` range.

    Notes
    -----
    Written out because neither numpy nor scikit-image exposes the bare transfer function
    (skimage applies it only inside colour-space conversions that also change the primaries).
    Works in place with one temporary of the upper branch, so linearising a large image costs
    about one extra float32 image.
    """
    if out is None:
        out = np.empty(np.shape(values), dtype=np.float32)
    np.divide(values, np.float32(full_scale), out=out, dtype=np.float32, casting="unsafe")
    np.clip(out, 0.0, 1.0, out=out)
    high = out > 0.04045
    upper = out[high]
    upper += np.float32(0.055)
    upper /= np.float32(1.055)
    np.power(upper, np.float32(2.4), out=upper)
    out /= np.float32(12.92)
    out[high] = upper
    out *= np.float32(full_scale)
    return out


# ---------------------------------------------------------------------------------------------
# reading single images


def read_image(path: PathLike) -> np.ndarray:
    """Read one image file as stored: ``(M, N)`` or ``(M, N, 3)`` in its own dtype.

    Parameters
    ----------
    path : path
        A TIFF, PNG or JPEG file. A multi-page TIFF is refused here (see :func:`read_capture`).

    Returns
    -------
    ndarray
        The pixels, alpha dropped, never rescaled.
    """
    return _read_image_px(path)[0]


def _read_image_px(path: PathLike) -> tuple:
    """(pixels as :func:`read_image`, pixel size in um from the TIFF tags or None)."""
    path = Path(path)
    if not path.is_file():
        raise UVPSInputError(f"image file {path} does not exist")
    kind = _kind(path)
    px = None
    if kind == "raw":
        return read_raw(path), None
    try:
        if kind == "tiff":
            with tifffile.TiffFile(path) as tif:
                series = tif.series[0]
                arr = series.asarray()
                px = _tiff_pixel_size_um(tif)
                if series.axes.upper() in ("SYX", "CYX") and arr.shape[0] in (3, 4) and (
                    series.axes.upper() == "SYX" or tif.pages.first.photometric == 2
                ):
                    arr = np.moveaxis(arr, 0, -1)  # planar RGB -> channels last
        elif kind == "png":
            # OpenCV keeps 16-bit colour PNGs (Pillow would reduce them to 8 bits). cv2 and imageio are
            # imported where a PNG or JPEG is read: a run on TIFFs does not pay their start-up.
            import cv2

            buf = np.fromfile(path, dtype=np.uint8)
            arr = cv2.imdecode(buf, cv2.IMREAD_UNCHANGED)
            if arr is None:
                raise ValueError("OpenCV could not decode it")
            if arr.ndim == 3:
                arr = arr[..., [2, 1, 0, 3][: arr.shape[2]]] if arr.shape[2] >= 3 else arr
        else:
            import imageio.v3 as iio

            arr = iio.imread(path)
    except UVPSInputError:
        raise
    except Exception as exc:  # any decoder failure is bad input: name the file
        msg = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        raise UVPSInputError(f"{path}: cannot read as {kind.upper()} image ({msg})") from exc
    arr = _drop_alpha(np.asarray(arr))
    if arr.ndim not in (2, 3) or (arr.ndim == 3 and arr.shape[2] != 3):
        raise UVPSInputError(
            f"{path}: expected a single grey (M, N) or RGB (M, N, 3) image; got shape {arr.shape}"
            " (a multi-page stack must be given alone, as the only input)"
        )
    if arr.dtype not in (np.uint8, np.uint16, np.float32, np.float64):
        raise UVPSInputError(
            f"{path}: unsupported pixel type {arr.dtype}; expected uint8, uint16 or float32"
        )
    return arr, px


def _tiff_pixel_size_um(tif) -> Optional[float]:
    """Pixel size from a TIFF's resolution tags / ImageJ metadata, or None.

    tifffile's ``page.resolution`` is (X, Y) in *pixels per unit*; the unit is the
    ResolutionUnit tag (1 none, 2 inch, 3 cm) or, for ImageJ files (which write unit NONE),
    the ``unit`` entry of the ImageJ description.
    """
    page = tif.pages.first
    tags = page.tags
    if "XResolution" not in tags:
        return None
    num, den = tags["XResolution"].value
    if not num or not den:
        return None
    per_unit = num / den  # pixels per unit
    resunit = int(tags["ResolutionUnit"].value) if "ResolutionUnit" in tags else 2
    ij_unit = str((tif.imagej_metadata or {}).get("unit", "")).strip().lower()
    if ij_unit:
        unit_um = _UNIT_UM.get(ij_unit)  # None for "pixel" and unknown units
    else:
        unit_um = {2: _UNIT_UM["inch"], 3: _UNIT_UM["cm"]}.get(resunit)
        if resunit == 2 and round(per_unit, 6) in _DEFAULT_DPI:
            log.warning("%s: %g dpi is a software default, not a physical size; ignored",
                        tif.filename, per_unit)
            return None
    if unit_um is None:
        return None
    size = unit_um / per_unit
    return size if math.isfinite(size) and size > 0 else None


def read_tiff(path: PathLike) -> TiffData:
    """Read a TIFF written by uvps (or any TIFF) as stored, with its pixel size.

    Parameters
    ----------
    path : path
        The TIFF file.

    Returns
    -------
    TiffData
        ``(data, pixel_size_um)``; ``pixel_size_um`` is None when the file has no physical
        calibration.
    """
    path = Path(path)
    if not path.is_file():
        raise UVPSInputError(f"TIFF file {path} does not exist")
    try:
        with tifffile.TiffFile(path) as tif:
            data = tif.series[0].asarray()
            px = _tiff_pixel_size_um(tif)
    except Exception as exc:
        raise UVPSInputError(f"{path}: cannot read as TIFF ({str(exc).splitlines()[0]})") from exc
    return TiffData(data, px)


# ---------------------------------------------------------------------------------------------
# light files


def _order_by_name(lightfile_path: str, names: Sequence[str], sources: list, by_name: bool):
    """Index array mapping each image to its row in a light file (by file name or order)."""
    k = len(sources)
    if len(names) != k:
        raise UVPSInputError(
            f"light file {lightfile_path} lists {len(names)} lights for {k} images"
        )
    if not by_name:
        return np.arange(k)
    base = {_basename(n): i for i, n in enumerate(names)}
    stem = {}
    for i, n in enumerate(names):
        stem.setdefault(Path(_basename(n)).stem, []).append(i)
    order = []
    for src in sources:
        name = src.path.name
        if name in base:
            order.append(base[name])
        elif len(stem.get(src.path.stem, [])) == 1:
            order.append(stem[src.path.stem][0])
        else:
            raise UVPSInputError(f"light file {lightfile_path} has no entry for image {name}")
    if len(set(order)) != k:
        raise UVPSInputError(f"light file {lightfile_path} names the same image twice")
    return np.asarray(order)


def _attach_lights(lights, sources, by_name):
    """(light_directions, light_positions_mm, light_intensities) for the capture, in image order."""
    path = Path(lights)
    if not path.is_file():
        raise UVPSInputError(f"lights: file {path} does not exist")
    if path.suffix.lower() == ".lp":
        lp = read_lp(path)
        if len(lp.files) != len(sources):
            raise UVPSInputError(
                f"light file {path} lists {len(lp.files)} lights for {len(sources)} images"
            )
        if by_name:
            missing = [_basename(n) for n in lp.files
                       if _basename(n) not in {s.path.name for s in sources}
                       and Path(_basename(n)).stem not in {s.path.stem for s in sources}]
            if missing:
                raise UVPSInputError(
                    f"light file {path} names {missing[0]}, which is not among the images"
                )
        order = _order_by_name(str(path), lp.files, sources, by_name)
        return lp.directions[order], None, None if lp.intensities is None else lp.intensities[order]
    if path.suffix.lower() in (".csv", ".json", ".txt"):
        lpos = read_positions(path)
        use_names = by_name and lpos.files is not None
        n = len(lpos.positions_mm if lpos.positions_mm is not None else lpos.directions)
        order = _order_by_name(str(path), lpos.files if use_names else [""] * n, sources, use_names)
        pos = lpos.positions_mm[order] if lpos.positions_mm is not None else None
        dirs = lpos.directions[order] if lpos.directions is not None else None
        return dirs, pos, None if lpos.intensities is None else lpos.intensities[order]
    raise UVPSInputError(
        f"lights: {path} is neither an .lp direction file nor a .csv/.json positions file"
    )


# ---------------------------------------------------------------------------------------------
# capture


#: Words in a file name (split at anything but letters) that mark a file of a capture folder that
#: is not a lamp image, with what it is and what to do with it.
NOT_LAMP_WORDS = {
    "mask": "a mask (give it with --mask)",
    "dark": "a dark frame (give it with --dark)", "black": "a dark frame (give it with --dark)",
    "thumb": "a thumbnail", "thumbnail": "a thumbnail", "preview": "a thumbnail", "small": "a thumbnail",
    "ref": "a reference image", "reference": "a reference image", "ambient": "a reference image",
    "roomlight": "a reference image", "flat": "a flat-field frame", "white": "a flat-field frame",
}


def _image_size(path: Path):
    """(rows, columns) of an image file from its header, or None if it cannot be read."""
    try:
        if path.suffix.lower() in TIFF_EXTS:
            with tifffile.TiffFile(path) as tif:
                shape, axes = tif.series[0].shape, tif.series[0].axes
                return tuple(shape[axes.index(a)] for a in "YX")
        if path.suffix.lower() in RAW_EXTS:
            # LibRaw's own header read (imageio would hand a DNG to OpenCV, which prints warnings)
            with _rawpy().imread(str(path)) as raw:
                return raw_image_size(raw)
        import imageio.v3 as iio

        return tuple(iio.improps(path).shape[:2])
    except Exception:   # an unreadable file is reported by the reader itself, with its own message
        return None


def lamp_images(files: list) -> tuple:
    """The lamp images among a capture folder's image files, and the others with why.

    A file is left out when a word of its name says it is a mask, a dark frame, a thumbnail, a
    reference or a flat-field frame (:data:`NOT_LAMP_WORDS`), or when its size differs from the
    size most of the folder's images share (at least 3 of them); a camera raw file of another size is
    refused (:class:`UVPSInputError`). Returns ``(lamps, [(path, why)])``.
    """
    kept, left = [], []
    for f in files:
        words = [w for w in re.split(r"[^a-z]+", f.stem.lower()) if w]
        why = next((NOT_LAMP_WORDS[w] for w in words if w in NOT_LAMP_WORDS), None)
        (left.append((f, why + ", by its name")) if why else kept.append(f))
    sizes = {f: _image_size(f) for f in kept}
    counts = {}
    for size in sizes.values():
        if size is not None:
            counts[size] = counts.get(size, 0) + 1
    if counts:
        common, n = max(counts.items(), key=lambda kv: kv[1])
        if n >= 3 and n > len(kept) / 2:
            odd = [f for f in kept if sizes[f] is not None and sizes[f] != common]
            for f in odd:   # a raw file is no thumbnail: another size is another camera or mode, refused
                if f.suffix.lower() in RAW_EXTS:
                    raise UVPSInputError(f"{f}: a camera raw file of another size ({sizes[f][0]} x {sizes[f][1]} px; "
                                         f"the lamp images are {common[0]} x {common[1]}): another camera or mode? "
                                         "Remove it, or choose the images with --pattern")
            left += [(f, f"another size ({sizes[f][0]} x {sizes[f][1]} px; the lamp images are {common[0]} x "
                         f"{common[1]})") for f in odd]
            kept = [f for f in kept if f not in odd]
    return kept, left


def _list_sources(images, pattern=None) -> tuple:
    """-> (sources, stack_path or None, by_name)."""
    if isinstance(images, (list, tuple)) and len(images) == 1:
        images = images[0]  # ["folder"] or ["stack.tif"], as the bridge may send them
    if isinstance(images, (str, os.PathLike)):
        root = Path(images)
        if not root.exists():
            raise UVPSInputError(f"images: {root} does not exist")
        if root.is_dir():
            files = sorted(
                (p for p in root.iterdir()
                 if p.is_file() and _is_image(p) and not p.name.startswith(".")),
                key=lambda p: _natural_key(p.name),
            )
            if pattern:
                files = [p for p in files if fnmatch.fnmatch(p.name, pattern)]
                if not files:
                    raise UVPSInputError(f"images: no file of folder {root} matches the pattern {pattern!r}")
            elif files:
                files, left = lamp_images(files)
                if left:
                    log.info("capture folder %s: %d lamp images; left out %s (choose the images with --pattern)",
                             root, len(files), "; ".join(f"{f.name}: {why}" for f, why in left))
            if not files:
                raise UVPSInputError(f"images: folder {root} holds no TIFF/PNG/JPEG files")
        else:
            files = [root]
    else:
        files = [Path(p) for p in images]
        if not files:
            raise UVPSInputError("images: empty list; expected at least 3 image files")
    for f in files:
        if not f.exists():
            raise UVPSInputError(f"images: {f} does not exist")
        if f.is_dir():
            raise UVPSInputError(f"images: {f} is a folder; give a folder alone or a list of files")
        _kind(f)
    if len(files) == 1 and files[0].suffix.lower() in TIFF_EXTS:
        return [], files[0], False
    return [_Source(str(f), f) for f in files], None, True


def _stack_layout(shape: tuple, axes: str, path: Path) -> tuple:
    """How to view a TIFF series as (K, M, N[, 3]): returns (transpose order, colour?).

    Y and X are the image axes; S (samples) of size 3/4 is colour (alpha dropped); an ImageJ
    ``C`` axis of size 3 is colour when another frame axis (Z, T, ...) holds the lights,
    otherwise the C planes are the images. All remaining axes are flattened into K.
    """
    axes = axes.upper()
    if "Y" not in axes or "X" not in axes:
        raise UVPSInputError(f"{path}: TIFF series has axes {axes}; expected Y and X axes")
    frame = [i for i, a in enumerate(axes) if a not in "YXS"]
    colour_axis = None
    if "S" in axes:
        colour_axis = axes.index("S")
    elif "C" in axes and shape[axes.index("C")] == 3:
        others = [i for i in frame if axes[i] != "C" and shape[i] > 1]
        if others:
            colour_axis = axes.index("C")
    frame = [i for i in frame if i != colour_axis]
    order = frame + [axes.index("Y"), axes.index("X")]
    if colour_axis is not None:
        order.append(colour_axis)
    return order, colour_axis is not None


def _check_image(arr: np.ndarray, label: str) -> None:
    if arr.size == 0:
        raise UVPSInputError(f"image {label} is empty")
    sat = _saturation_of(arr.dtype)
    if np.issubdtype(arr.dtype, np.integer):
        # about 64 rows decide for any usable image (a pixel above 0 and one below saturation; an
        # integer has no NaN): the two full passes cost 0.1 s per 22 MP RGB image, 1.6 s of a
        # 16-image capture's reading, and touch every page of a mapped file
        rows = arr[::max(1, arr.shape[0] // 64)]
        if rows.max() > 0 and (sat is None or rows.min() < sat):
            return
    mx = arr.max()
    if not np.isfinite(mx) or not np.isfinite(arr.min()):
        raise UVPSInputError(f"image {label} contains NaN or infinite values")
    if mx <= 0:
        raise UVPSInputError(f"image {label} is all black (no pixel above 0)")
    if sat is not None and arr.min() >= sat:
        raise UVPSInputError(f"image {label} is fully saturated (every pixel at {int(sat)})")


def _read_mask(mask, shape2d: tuple) -> np.ndarray:
    if isinstance(mask, np.ndarray):
        arr, name = mask, "mask"
    else:
        if not Path(mask).is_file():
            raise UVPSInputError(f"mask file {mask} does not exist")
        arr, name = read_image(mask), f"mask {mask}"
    arr = np.asarray(arr)
    if arr.ndim == 3:
        arr = arr.any(axis=2)
    if arr.shape != tuple(shape2d):
        raise UVPSInputError(
            f"{name} has shape {arr.shape}; expected the image shape {tuple(shape2d)}"
        )
    out = arr != 0
    if not out.any():
        raise UVPSInputError(f"{name} is empty (no pixel selected); expected True/non-zero = use")
    return out


def _pixel_size_from_tags(tag_px) -> float:
    """The pixel size the files' resolution tags give, or the one-line error asking for it."""
    if tag_px is None:
        raise UVPSInputError(
            "pixel size unknown: the images carry no physical resolution (PNG/JPEG, an "
            "uncalibrated TIFF, or a 72/96/300 dpi software default); pass --pixel-size-um "
            "(params 'pixel_size_um')"
        )
    return check_pixel_size(tag_px, "pixel size from the TIFF resolution tags")


def read_capture(images, *, lights=None, mask=None, dark=None, pixel_size_um=None,
                 linearize: str = "auto", memory_map: bool = True, pattern: Optional[str] = None,
                 progress: Progress = None) -> Capture:
    """Read a capture (K images, one per light) into one stack (no rescaling).

    Parameters
    ----------
    images : path or list of paths
        A folder (its TIFF/PNG/JPEG lamp images, natural order: files named as a mask, dark
        frame, thumbnail, reference or flat-field frame, or of another size than most, are left
        out and logged, :func:`lamp_images`; other files and subfolders are ignored), a list of image files, or ONE multi-page TIFF (``(K, M, N)``,
        ``(K, M, N, 3)``, ImageJ hyperstacks: Y, X and colour (S, or C of size 3 beside another
        frame axis) are the image, every other axis is flattened into K).
    lights : path, optional
        An RTI ``.lp`` file (directions, matched to the images by file name for a folder/list,
        by order for a stack) or a positions file (``.csv`` ``file,x_mm,y_mm,z_mm`` or uvps
        ``lights.json``), see :func:`read_lp` and :func:`read_positions`. Either may give each
        lamp's intensity (``.lp`` 4th column, CSV ``intensity`` column).
    mask : path or ndarray, optional
        ``(M, N)`` image; non-zero = use. An empty mask is an error.
    dark : path, optional
        A dark frame of the same shape and type; subtracted after linearisation, clipped at 0.
    pixel_size_um : float, optional
        Overrides the TIFF calibration. Without it the calibration is read from the TIFF tags
        (ImageJ ``unit`` + X resolution, or ResolutionUnit inch/cm + X resolution; tifffile's
        resolution is pixels per unit); files calibrated differently are an error. Required
        for PNG/JPEG captures, uncalibrated TIFFs and TIFFs claiming a software-default
        72/96/150/240/300/350 dpi (none of which is a physical size).
    linearize : {"auto", "srgb", "none"}
        "auto" applies the sRGB EOTF to JPEG files only (8-bit PNGs are often written linear by
        scientific cameras: pass "srgb" if yours are sRGB-encoded), "srgb" to every integer
        image, "none" to none. The result stays in the file's range (a linearised JPEG is in
        0..255 linear counts). Float images are never linearised.
    memory_map : bool
        Files that are uncompressed one-image TIFFs of an integer type, with nothing to convert (no
        sRGB), are memory-mapped instead of read (:class:`MappedStack`; with a dark frame seen through
        :class:`DarkSubtracted`, which subtracts it from the band asked for): the stages
        read them band by band and the capture may be larger than the memory. Compressed ones
        whose stack is larger than a quarter of the memory (:data:`SCRATCH_ABOVE_BYTES`) are
        decoded once into scratch files in the temporary folder (``TMPDIR``, which needs the
        stack's size free) and mapped there. False: read whole.
    pattern : str, optional
        With a folder: only its files whose names match this shell pattern (``"uv_*.tif"``), and
        no file left out by name or size.
    progress : callable, optional
        ``progress(fraction, message)``.

    Returns
    -------
    Capture

    Notes
    -----
    Memory: the stack is preallocated and filled one file at a time, so reading needs the stack
    plus one file in its own dtype. Integer files that need no sRGB conversion stay in their own dtype
    (uint16 counts are exact either way; a dark frame subtracted in it, clipped at 0), others become float32. An integer
    multi-page TIFF is seen the same way: memory-mapped read-only when uncompressed, decoded into a
    scratch file when compressed and larger than :data:`SCRATCH_ABOVE_BYTES`, read whole otherwise. Measured on 6 RGB uint16 images: peak = stack
    + 1.1 single float32 images (1.8 with ``linearize="srgb"``; 0.02 for a stack file).

    Images of a stack are named ``"/path/stack.tif#k"``, k = 1..K (ImageJ's slice numbers).
    Each image is checked: same shape and dtype as the first, not all black, not fully
    saturated (every pixel at the dtype maximum), finite.
    """
    if linearize not in ("auto", "srgb", "none"):
        raise UVPSInputError(f"linearize must be 'auto', 'srgb' or 'none'; got {linearize!r}")
    if pixel_size_um is not None:
        pixel_size_um = check_pixel_size(pixel_size_um)
    sources, stack_path, by_name = _list_sources(images, pattern)

    if stack_path is not None:
        lazy = memory_map and dark is None and linearize != "srgb"
        stack, labels, first_kind, tag_px = _read_stack(stack_path, progress, lazy=lazy, linearize=linearize,
                                                        dark=None if dark is None else Path(dark))
        sources = [_Source(lb, stack_path) for lb in labels]
        dtype = stack.dtype_in
        arr = stack.images
    else:
        arr, dtype, tag_px = None, None, None
    if len(sources) < 3:
        what = stack_path if stack_path is not None else images
        raise UVPSInputError(
            f"images: photometric stereo needs at least 3 images; got {len(sources)} from {what}"
        )
    if stack_path is None:
        # a dark frame is subtracted file by file as the stack is filled (no second pass over it)
        arr, dtype, tag_px = _read_files(sources, linearize, progress, check_px=pixel_size_um is None,
                                         keep_dtype=True, memory_map=memory_map,
                                         dark=None if dark is None else Path(dark))
    elif _needs_linearize(first_kind, dtype, linearize):
        for k in range(arr.shape[0]):
            srgb_to_linear(arr[k], _saturation_of(dtype), out=arr[k])

    shape_img = arr.shape[1:]
    if dark is not None and stack_path is not None and not stack.dark_subtracted:
        _subtract_dark(arr, Path(dark), dtype, linearize)

    if pixel_size_um is None:
        pixel_size_um = _pixel_size_from_tags(tag_px)

    mask_arr = _read_mask(mask, shape_img[:2]) if mask is not None else None
    directions = positions = intensities = None
    if lights is not None:
        directions, positions, intensities = _attach_lights(lights, sources, by_name)
    raw = None
    saturation = _saturation_of(dtype)
    if stack_path is None and any(_kind(Path(s.path)) == "raw" for s in sources):
        raw = raw_reading([s.path for s in sources])
        saturation = raw["saturation_counts"]
    report(progress, 1.0, f"read {len(sources)} images {shape_img} {dtype}")
    log.info("capture: %d images %s %s, pixel %.4g um, from %s", len(sources), shape_img, dtype, pixel_size_um,
             stack_path or Path(sources[0].path).parent)
    return Capture(
        images=arr,
        files=[s.label for s in sources],
        pixel_size_um=float(pixel_size_um),
        mask=mask_arr,
        saturation=saturation,
        light_directions=directions,
        light_positions_mm=positions,
        bit_depth="raw" if raw is not None else str(dtype),
        light_intensities=intensities,
        raw=raw,
    )


def _subtract_dark(arr, dark_path: Path, dtype, linearize: str) -> None:
    """Subtract the dark frame from every image of ``arr`` (float32, in place), clipped at 0."""
    d = _read_dark(dark_path, arr.shape[1:], dtype, linearize, as_float=True)
    for k in range(arr.shape[0]):
        _minus_dark(arr[k], d)


def _read_dark(dark_path: Path, shape_img, dtype, linearize: str, *, as_float: bool) -> np.ndarray:
    """The dark frame, checked against the images' shape and dtype: float32 (linearised as the
    images are) with ``as_float``, else in its own integer dtype (the images' counts kept)."""
    if not dark_path.is_file():
        raise UVPSInputError(f"dark frame {dark_path} does not exist")
    # kept integer, an uncompressed frame of the images' own shape and pixel type is memory-mapped: its pages
    # are the page cache's, read from the file as the bands need them, not 72 MB more of the process's own
    # memory at 4000 x 3000 RGB. Anything else (big-endian, compressed, with an alpha channel read_image
    # drops, another pixel type read_image judges) is read
    mapped = None if as_float else _map_tiff(dark_path)
    usable = (mapped is not None and mapped[0].dtype.isnative and mapped[0].shape == tuple(shape_img)
              and mapped[0].dtype in (np.uint8, np.uint16))
    d = mapped[0] if usable else read_image(dark_path)
    if d.shape != tuple(shape_img) or d.dtype.newbyteorder("=") != np.dtype(dtype).newbyteorder("="):
        raise UVPSInputError(
            f"dark frame {dark_path} is {d.shape} {d.dtype};"
            f" expected {tuple(shape_img)} {dtype} like the images"
        )
    if not as_float:
        return d
    d = d.astype(np.float32)
    if _needs_linearize(_kind(dark_path), dtype, linearize):
        d = srgb_to_linear(d, _saturation_of(dtype))
    return d


def _minus_dark(image: np.ndarray, d: np.ndarray) -> None:
    """``image - d`` clipped at 0, in place. Integer counts: ``max(image, d) - d``, never wrapping, the
    same counts as in float32 (exact below 2**24)."""
    if np.issubdtype(image.dtype, np.integer):
        np.maximum(image, d, out=image)
        np.subtract(image, d, out=image)
    else:
        np.subtract(image, d, out=image)
        np.maximum(image, 0, out=image)


class DarkSubtracted(StackView):
    """Memory-mapped files seen with a dark frame subtracted, clipped at 0, computed on access (float32).

    The values of the stack read whole with the dark frame subtracted (the counts, as float32), for
    the band the stages ask for: the files stay mapped, never copied (the stack read whole, a 0.27 GiB
    one, took 0.24 GiB more at the peak of a calibrated run). The access patterns of
    :class:`uvps.core.stack.StackView`.
    """

    def __init__(self, images, dark):
        super().__init__(images)
        # an integer dark frame is kept as it is stored (memory-mapped where its file allows: _read_dark),
        # and each sample converted where it is read (exact below 2**24): the compiled kernels convert it
        # sample by sample, the other reads band by band. A float32 copy of the whole frame, made once,
        # was 0.14 GB of a 4000 x 3000 RGB run's memory held through its normals and integration, and its
        # first touch of fresh memory (docs/decisions/speed.md, "Memory first touched; the dark frame as stored").
        # Like the images' files, a mapped frame must not be rewritten while a run reads it
        dark = np.asanyarray(dark)               # a np.memmap stays one
        if not np.issubdtype(dark.dtype, np.integer):
            dark = dark.astype(np.float32, copy=False)
        elif not dark.dtype.isnative:        # the compiled kernels read this machine's byte order
            dark = dark.astype(dark.dtype.newbyteorder("="))
        self.dark = dark

    def correct(self, out, kk, rk, ck):
        v = np.subtract(out, self.dark[rk, ck], dtype=np.float32)
        return np.maximum(v, 0, out=v)

    def raw_parts(self, k: int, rows: slice, cols: slice):
        """The files' band with this dark frame to subtract (:class:`uvps.core.stack.RawParts`)."""
        p = raw_parts(self.base, k, rows, cols)
        if p is None or p.dark is not None or p.factor is not None:
            return None
        return dataclasses.replace(p, dark=self.dark[rows, cols])


def _needs_linearize(kind: str, dtype, linearize: str) -> bool:
    if linearize == "none" or not np.issubdtype(dtype, np.integer):
        return False
    return linearize == "srgb" or kind == "jpeg"


def _read_files(sources: list, linearize: str, progress: Progress, *, check_px: bool = True,
                keep_dtype: bool = False, memory_map: bool = False, dark: Optional[Path] = None):
    """Fill a preallocated stack file by file; -> (stack, dtype, pixel size or None).

    The stack is float32, or, with ``keep_dtype`` and integer files that need no conversion (no
    sRGB linearisation), the files' own dtype: the same counts in half the memory (a 22 MP,
    16-light RGB uint16 capture is 1.15 GB instead of 2.3 GB); every stage converts band by band.
    A ``dark`` frame is subtracted from each image as it is stored (clipped at 0): in the files'
    integer dtype when neither needs linearising (the counts float32 would hold, in half the
    memory), else in float32 after linearisation.

    The pixel size comes from the first file's tags; a later file with another calibration is
    an error (a mixed capture) when ``check_px`` (no explicit pixel size was given).
    """
    if memory_map and keep_dtype and not any(_needs_linearize(_kind(s.path), np.uint16, linearize) for s in sources):
        mapped = _map_files(sources, progress, check_px=check_px)
        if mapped is None and _scratch_wanted(sources):
            mapped = _map_files(sources, progress, check_px=check_px, mapper=_scratch_tiff)
        if mapped is not None and dark is not None:
            arr, dtype, tag_px = mapped
            as_float = _needs_linearize(_kind(dark), dtype, linearize)    # else its counts, kept integer
            return DarkSubtracted(arr, _read_dark(dark, arr.shape[1:], dtype, linearize, as_float=as_float)), dtype, tag_px
        if mapped is not None:
            return mapped
    k = len(sources)
    first, tag_px = _read_image_px(sources[0].path)
    dtype, shape = first.dtype, first.shape
    keep = (keep_dtype and np.issubdtype(dtype, np.integer)
            and not any(_needs_linearize(_kind(s.path), dtype, linearize) for s in sources))
    d = None
    if dark is not None:
        keep = keep and not _needs_linearize(_kind(dark), dtype, linearize)
        d = _read_dark(dark, shape, dtype, linearize, as_float=not keep)
    out = np.empty((k,) + shape, dtype=dtype if keep else np.float32)
    for i, src in enumerate(sources):
        if i == 0:
            (img, px), first = (first, tag_px), None
        else:
            img, px = _read_image_px(src.path)
        _check_like_first(img, px, src.path, sources[0].path, shape=shape, dtype=dtype,
                          tag_px=tag_px if check_px else None)
        out[i] = img
        if _needs_linearize(_kind(src.path), dtype, linearize):
            srgb_to_linear(out[i], _saturation_of(dtype), out=out[i])
        if d is not None:
            _minus_dark(out[i], d)
        report(progress, (i + 1) / (k + 1), f"read {src.path.name}")
    return out, dtype, tag_px


class _Stack(NamedTuple):
    images: np.ndarray
    dtype_in: np.dtype
    dark_subtracted: bool = False


def _read_stack(path: Path, progress: Progress, *, lazy: bool = False, dark: Optional[Path] = None,
                linearize: str = "auto"):
    """A multi-page TIFF as (K, M, N[, 3]) images -> (_Stack, labels, kind, pixel size).

    ``lazy`` (an integer stack with nothing to convert): the images are views, as a
    :class:`MappedStack` in the file's dtype, into the file memory-mapped read-only (uncompressed),
    into a scratch file it is decoded into once (compressed and larger than
    :data:`SCRATCH_ABOVE_BYTES`), or into the stack read whole: no float32 copy, and a stack larger
    than the memory is processed band by band as a folder of files is. Otherwise a float32 copy
    (sRGB to linearise, a dark frame to subtract, float data, ``memory_map=False``), except that an
    integer stack with a ``dark`` frame, neither to linearise (``linearize``), is copied in its own dtype,
    the dark frame subtracted from each image as it is copied (:func:`_minus_dark`; ``dark_subtracted``),
    as :func:`_read_files` does.
    """
    raw, order, colour, dtype, tag_px, lazy = _map_stack(path, lazy)
    views = _image_views(raw, order, colour, path)
    k = len(views)
    native = np.dtype(dtype).newbyteorder("=")
    d = None
    if (dark is not None and not lazy and np.issubdtype(native, np.integer)
            and not any(_needs_linearize(kind, native, linearize) for kind in ("tiff", _kind(dark)))):
        d = _read_dark(dark, views[0].shape, native, linearize, as_float=False)
    out = None if lazy else np.empty((k,) + views[0].shape, dtype=native if d is not None else np.float32)
    labels = []
    for i, view in enumerate(views):
        label = f"{path}#{i + 1}"
        _check_image(view, label)
        if lazy:
            release(view)
        else:
            out[i] = view
            if d is not None:
                _minus_dark(out[i], d)
        labels.append(label)
        report(progress, (i + 1) / (k + 1), f"read {label}")
    return (_Stack(MappedStack(views) if lazy else out, native, d is not None), labels, "tiff", tag_px)


def _map_stack(path: Path, lazy: bool):
    """Open a multi-page TIFF without copying it to float: check its pixel type and that its
    ImageJ header's image count matches the file (a truncated stack is refused), then map it
    read-only (uncompressed), decode it into a scratch file (compressed, lazy and large), or read
    it whole. Returns the raw array, the axis order and colour flag of :func:`_stack_layout`, the
    file's dtype, its pixel size from the tags, and whether it is read lazily (integer only)."""
    try:
        with tifffile.TiffFile(path) as tif:
            series = tif.series[0]
            shape, axes, dtype = tuple(series.shape), series.axes, series.dtype
            order, colour = _stack_layout(shape, axes, path)
            if dtype not in (np.uint8, np.uint16, np.float32, np.float64):
                raise UVPSInputError(
                    f"{path}: unsupported pixel type {dtype}; expected uint8, uint16 or float32"
                )
            announced = (tif.imagej_metadata or {}).get("images")
            planes = int(np.prod([n for a, n in zip(axes, shape) if a not in "YXS"]))
            if announced is not None and int(announced) != planes:
                raise UVPSInputError(
                    f"{path}: truncated or corrupted stack: its ImageJ header announces "
                    f"{announced} images, the file holds {planes}"
                )
            tag_px = _tiff_pixel_size_um(tif)
            contiguous = series.dataoffset is not None
        lazy = lazy and np.issubdtype(dtype, np.integer)
        raw = None
        if contiguous:
            # Uncompressed contiguous data (ImageJ hyperstacks, plain stacks): map the file
            # read-only so that only the float32 stack (or nothing, when lazy) is held in memory.
            with contextlib.suppress(ValueError, OSError):
                raw = tifffile.memmap(path, mode="r")
        if raw is None and lazy and _scratch_wanted([_Source(str(path), path)]):
            raw = _decode_to_scratch(path, shape, dtype)
        if raw is None:
            # read whole; an integer stack is still not copied to float32 (views of it, in its dtype)
            with tifffile.TiffFile(path) as tif:
                raw = tif.series[0].asarray()
    except UVPSInputError:
        raise
    except Exception as exc:
        raise UVPSInputError(f"{path}: cannot read as TIFF ({str(exc).splitlines()[0]})") from exc
    return raw, order, colour, dtype, tag_px, lazy


def _image_views(raw, order, colour, path):
    """One view per image of the raw stack, over its leading (frame) axes, RGB of an RGBA (a
    reshape of the transposed map could copy it; views never do)."""
    raw = np.transpose(raw, order)
    nimg = 2 + colour
    if colour and raw.shape[-1] not in (3, 4):
        raise UVPSInputError(
            f"{path}: colour axis has {raw.shape[-1]} samples; expected 3 (RGB) or 4 (RGBA)"
        )
    views = [raw[index] for index in np.ndindex(*raw.shape[:-nimg])]
    if colour:
        views = [v[..., :3] for v in views]
    return views


def _decode_to_scratch(path: Path, shape, dtype) -> np.memmap:
    """A compressed TIFF decoded page by page into a scratch array (:func:`_scratch_array`),
    each page's memory released from this process as it is written (decoding the whole series at
    once kept every decoded page resident: 1.26x the stack at peak instead of 0.9x)."""
    raw = _scratch_array(shape, dtype)
    with tifffile.TiffFile(path) as tif:
        pages = tif.series[0].pages
        if all(p is not None for p in pages) and len(pages) * math.prod(pages[0].shape) == raw.size:
            flat = raw.reshape((len(pages),) + tuple(pages[0].shape))
            for k, page in enumerate(pages):
                page.asarray(out=flat[k])
                release(flat)
            return raw
    tifffile.imread(path, out=raw)
    return raw


def _scratch_array(shape, dtype) -> np.memmap:
    """A writable array of ``shape`` and ``dtype`` backed by a scratch file in the temporary folder,
    unlinked at once (the mapping keeps it; its space is freed with the array, even on a kill)."""
    import tempfile

    fd, name = tempfile.mkstemp(prefix="uvps-scratch-", suffix=".raw")
    try:
        os.close(fd)
        return np.memmap(name, dtype=dtype, mode="w+", shape=tuple(shape))
    finally:
        os.unlink(name)


# ---------------------------------------------------------------------------------------------
# writing


def _imagej_dtype(data: np.ndarray) -> np.dtype:
    """The type ImageJ hyperstacks hold (uint8, uint16, float32) that ``data`` is written as.

    ImageJ has no int32/uint32 images (tifffile refuses them with ``imagej=True``): integer
    label images are written uint16 when all values fit in 0..65535, else float32 (exact up to
    2**24 labels).
    """
    if data.dtype == np.bool_:
        return np.dtype(np.uint8)
    if data.dtype in (np.uint8, np.uint16, np.float32):
        return data.dtype
    if np.issubdtype(data.dtype, np.integer):
        lo, hi = (int(data.min()), int(data.max())) if data.size else (0, 0)
        if lo >= 0 and hi <= 65535:
            return np.dtype(np.uint16)
        if abs(lo) > 2**24 or abs(hi) > 2**24:
            raise UVPSInputError(f"integer image values {lo}..{hi} do not fit float32 exactly")
        return np.dtype(np.float32)
    if np.issubdtype(data.dtype, np.floating):
        return np.dtype(np.float32)
    raise UVPSInputError(f"cannot write {data.dtype} data as an ImageJ TIFF")


def _check_imagej_axes(axes: str, shape: tuple) -> str:
    axes = str(axes).upper()
    if len(axes) != len(shape):
        raise UVPSInputError(
            f"axes {axes!r} has {len(axes)} letters for data of shape {tuple(shape)}"
        )
    it = iter(_IMAGEJ_AXES)
    if not axes.endswith("YX") and not axes.endswith("YXS") or not all(a in it for a in axes):
        raise UVPSInputError(
            f"axes {axes!r} must be a subsequence of ImageJ's 'TZCYXS' ending in YX"
        )
    return axes


#: Bytes copied into a TIFF being written before its pages are released (see :class:`TiffBands`).
BAND_BYTES = 1 << 26


class TiffBands:
    """The image data of a TIFF being written (:func:`imagej_tiff_writer`), filled band by band.

    ``array`` is the file's data memory-mapped read-write, in the file's layout (e.g. ``(C, M, N)``);
    :meth:`write` copies values into it and then drops the written pages from the process's resident
    set: they stay in the page cache and reach the disk as any write does, so a file larger than the
    memory is written with the memory of one band.
    """

    def __init__(self, array: np.ndarray):
        self.array = array
        self.dtype = array.dtype

    def write(self, key, values) -> None:
        """``array[key] = values`` (cast to the file's type), then release the pages."""
        self.array[key] = values
        release(self.array)

    def put(self, index: tuple, plane) -> None:
        """Copy one plane (``(M, N)``, or ``(M, N, S)`` for RGB samples) to the plane at ``index``
        (the indices of the axes before Y), :data:`BAND_BYTES` at a time: ``plane`` may be any
        array (a strided view, another dtype) and is never copied whole."""
        index = tuple(index) if isinstance(index, (tuple, list)) else (index,)
        for rows in row_bands(plane.shape[0], int(np.prod(plane.shape[1:])) * self.dtype.itemsize, BAND_BYTES):
            self.write(index + (rows,), plane[rows])


@contextlib.contextmanager
def imagej_tiff_writer(path: PathLike, shape, dtype, *, axes: str, pixel_size_um: float,
                       unit: str = "um", labels: Optional[Sequence[str]] = None,
                       metadata: Optional[dict] = None):
    """Create an ImageJ hyperstack TIFF of ``shape`` and ``dtype`` and yield its data to fill
    (:class:`TiffBands`); the file is written to a temporary file and renamed into place when the
    block ends without an exception (removed otherwise).

    Parameters are those of :func:`write_imagej_tiff`; ``dtype`` is one ImageJ holds (uint8,
    uint16, float32). The data are uncompressed and contiguous, so tifffile, ImageJ and
    :func:`read_capture` (memory-mapped) read the file. Above :data:`LARGE_TIFF_BYTES` the file is
    in ImageJ's own large-file layout (one IFD, the data contiguous after it: what ImageJ's "Save
    As Tiff" writes and ImageJ 1.x opens natively; BigTIFF would need Bio-Formats); tifffile reads
    both.
    """
    path = Path(path)
    px = check_pixel_size(pixel_size_um)
    if unit not in ("um", "micron", "\u00b5m"):
        raise UVPSInputError(f"unit must be 'um' (micrometres); got {unit!r}")
    shape = tuple(int(n) for n in shape)
    axes = _check_imagej_axes(axes, shape)
    dtype = np.dtype(dtype)
    if dtype not in (np.uint8, np.uint16, np.float32):
        raise UVPSInputError(f"ImageJ TIFFs hold uint8, uint16 or float32; got {dtype}")
    meta = {"axes": axes, "unit": "micron"}
    if labels is not None:
        labels = [str(s) for s in labels]
        nplanes = int(np.prod([n for a, n in zip(axes, shape) if a in "TZC"] or [1]))
        nc = shape[axes.index("C")] if "C" in axes else 1
        if len(labels) == nc and nplanes != nc:
            labels = labels * (nplanes // nc)  # ImageJ plane order: C fastest, then Z, then T
        if len(labels) != nplanes:
            raise UVPSInputError(
                f"labels: got {len(labels)}; expected one per channel ({nc})"
                f" or per plane ({nplanes})"
            )
        meta["Labels"] = labels
    if metadata:
        meta.update(metadata)
    if not path.parent.is_dir():
        raise UVPSInputError(f"output folder {path.parent} does not exist")
    nbytes = int(np.prod(shape)) * dtype.itemsize
    with atomic_path(path) as tmp, warnings.catch_warnings():
        large = nbytes > LARGE_TIFF_BYTES
        if large:
            log.info("%s: %.2f GB, ImageJ large-file layout", path, nbytes / 2**30)
            warnings.filterwarnings("ignore", message=".*truncating ImageJ file")
        arr = tifffile.memmap(
            tmp, shape=shape, dtype=dtype, imagej=True, resolution=(1.0 / px, 1.0 / px),
            metadata=meta, photometric="rgb" if axes.endswith("S") else "minisblack",
            truncate=large,
        )
        bands = TiffBands(arr)
        del arr
        try:
            yield bands
        finally:
            # unmapped here (the last reference): the data are in the page cache, as after write()
            bands.array = None


def write_imagej_tiff(path: PathLike, data: np.ndarray, *, axes: str, pixel_size_um: float,
                      unit: str = "um", labels: Optional[Sequence[str]] = None,
                      metadata: Optional[dict] = None) -> Path:
    """Write an ImageJ hyperstack TIFF with a micrometre calibration, atomically.

    Parameters
    ----------
    path : path
        Output file; written to a temporary file in the same folder, then renamed into place.
    data : ndarray
        float32, uint16 or uint8 (bool -> uint8, float64 -> float32; int32 labels -> uint16 if
        they fit, else float32: ImageJ has no 32-bit integer images). Any layout: a strided view
        (``np.moveaxis(normals, -1, 0)``) is written as it is, band by band, never copied whole.
    axes : str
        One letter per dimension, a subsequence of ImageJ's ``TZCYXS`` ending in ``YX``:
        ``"YX"``, ``"CYX"`` (channels), ``"ZYX"`` (a stack of K images), ``"ZCYX"``.
    pixel_size_um : float
        Pixel size; written as X/YResolution = 1 / pixel size (pixels per micron) with ImageJ
        ``unit='micron'``, so ImageJ's scale bar is right.
    unit : str
        Only "um" (micrometres) is written by uvps; kept explicit for readers.
    labels : sequence of str, optional
        Channel labels (one per C) or one per plane; shown as ImageJ slice labels.
    metadata : dict, optional
        Extra ImageJ metadata (e.g. ``{"Info": "..."}``); stored in the ImageJ description.

    Returns
    -------
    Path
        The written file.

    Notes
    -----
    Files above about 3.9 GB are written in ImageJ's own large-file layout (one IFD, the data
    contiguous after it, as ImageJ's "Save As Tiff" does) rather than BigTIFF, because ImageJ
    1.x opens that layout natively but needs Bio-Formats for BigTIFF; tifffile reads both
    (:func:`imagej_tiff_writer`). Memory: one band of :data:`BAND_BYTES` beyond ``data``.
    """
    data = np.asarray(data)
    axes = _check_imagej_axes(axes, data.shape)
    dtype = _imagej_dtype(data)
    n_lead = axes.index("Y")
    with imagej_tiff_writer(path, data.shape, dtype, axes=axes, pixel_size_um=pixel_size_um, unit=unit,
                            labels=labels, metadata=metadata) as out:
        for index in np.ndindex(*data.shape[:n_lead]):
            out.put(index, data[index])
    return Path(path)


def sha256_file(path: PathLike, *, chunk_bytes: int = 1 << 20) -> str:
    """SHA-256 hex digest of a file, read in chunks of ``chunk_bytes``."""
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        for block in iter(lambda: fh.read(chunk_bytes), b""):
            h.update(block)
    return h.hexdigest()


def _input_paths(capture: Capture) -> list:
    """The capture's input files, each once (a stack's ``stack.tif#k`` images are one file)."""
    paths = []
    for f in capture.files:
        p = f.rsplit("#", 1)[0] if "#" in f and not Path(f).exists() else f   # "stack.tif#k"
        if p not in paths:
            paths.append(p)
    return paths


def _digest(path) -> Optional[str]:
    return sha256_file(path) if Path(path).is_file() else None


def input_hashes(capture: Capture) -> list:
    """SHA-256 of every input file (a stack is hashed once; null for an image that is no file, e.g. a
    capture made in memory)."""
    # two files at a time, this thread and another: hashlib releases the GIL (16 files, 1.15 GB: 1.18 s -> 0.68 s
    # on 2 cores)
    return InputHashes(_input_paths(capture), background=1).result()


def hash_inputs_meanwhile(capture: Capture) -> "InputHashes":
    """:func:`input_hashes` of ``capture`` begun in two background threads (at most ``UVPS_THREADS``) at the
    lowest priority (:class:`InputHashes`; its ``result()`` is the list).

    The hashing of a 1 GB stack (0.85 CPU s: SHA-256 at 1.35 GB/s here) runs on what the run leaves idle instead
    of following it or taking a share of its two-thread stages: :func:`uvps.workflow.run_into_folder` starts it
    as soon as the capture is read, before it imports the numeric core (0.7 s on one core; ``python -X
    importtime``). The files are those just read; a run that fails leaves the threads to end on their own
    (daemon threads: they do not hold the process's exit)."""
    return InputHashes(_input_paths(capture), background=default_threads(2))


class InputHashes:
    """The SHA-256 of ``paths``, file by file, made by :class:`uvps.core.threads.Background` (``background``
    threads at the lowest priority: the calibrated 4000 x 3000 x 16 run, docs/decisions/speed.md, "The report's
    figures in two threads; the input hashes at the lowest priority"; :meth:`result` hashes what they have not
    begun in the calling thread)."""

    def __init__(self, paths, *, background: int = 2):
        self.paths = list(paths)
        self._jobs = Background([functools.partial(_digest, p) for p in self.paths], threads=background,
                                name="uvps-hash")

    def result(self) -> list:
        """``[{"path", "sha256"}, ...]`` in the files' order, once every file is hashed; a file's error raised."""
        return [{"path": str(p), "sha256": d} for p, d in zip(self.paths, self._jobs.results())]
