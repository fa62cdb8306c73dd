"""Camera raw files (:data:`uvps.files.io.RAW_EXTS`) read linearly with LibRaw (rawpy).

Part of the file reading; :mod:`uvps.files.io` exposes these names and calls :func:`read_raw`.
"""
from __future__ import annotations

import os
from pathlib import Path
from typing import Optional, Union

import numpy as np
import tifffile

from ..errors import UVPSInputError

PathLike = Union[str, os.PathLike]


#: How :func:`read_raw` has LibRaw develop a raw file: linear (gamma 1), no automatic brightness or
#: maximum, white balance fixed at 1 for every channel, the camera's own colour channels (no colour
#: matrix), bilinear demosaic (LINEAR: it mixes no channel into another and keeps the counts'
#: linearity; AHD and its kin are tuned for a tone-mapped look), the image as stored (no rotation).
RAW_DEVELOP = {"gamma": [1, 1], "no_auto_bright": True, "adjust_maximum_thr": 0.0, "white_balance": [1, 1, 1, 1],
               "demosaic": "LINEAR", "colour": "camera raw (no colour matrix)", "flip": 0, "output_bps": 16}


def _rawpy():
    try:
        import rawpy
    except ImportError:  # pragma: no cover - a dependency
        raise UVPSInputError("camera raw files need rawpy (pip install rawpy)") from None
    return rawpy


def _libraw_message(exc) -> str:
    """LibRaw's reason in words, on one line (rawpy hands it over as bytes); an input/output error is what LibRaw says
    of a file cut short (a truncated copy, a sample stripped of its image data)."""
    arg = exc.args[0] if exc.args else ""
    msg = (arg.decode("utf-8", "replace") if isinstance(arg, bytes) else str(arg)).strip()
    msg = msg.splitlines()[0] if msg else type(exc).__name__
    return msg + ": truncated or damaged?" if msg.lower() == "input/output error" else msg


def default_crop(raw) -> Optional[list]:
    """A DNG's DefaultCrop as ``[left, top, width, height]`` in the image LibRaw develops (its margins, the masked
    areas, already cut), or None when the file gives none (or one that does not fit).

    :func:`read_raw` keeps only this window: outside it a camera leaves what is not image (a Blackmagic Pocket
    Cinema Camera 4K DNG's last 4 columns are at 0, below its black level, and gave non-finite normals)."""
    sz = raw.sizes
    # (rawpy builds older than LibRaw 0.21's inset crops have no such fields: no crop)
    left, top, w, h = (int(getattr(sz, f, 0)) for f in ("crop_left_margin", "crop_top_margin", "crop_width",
                                                         "crop_height"))
    if w <= 0 or h <= 0:
        return None
    # LibRaw may count the origin from the sensor's corner (margins included) or from the image's: take the
    # reading that fits inside the image
    for dx, dy in ((int(sz.left_margin), int(sz.top_margin)), (0, 0)):
        x, y = left - dx, top - dy
        if x >= 0 and y >= 0 and x + w <= int(sz.width) and y + h <= int(sz.height):
            return [x, y, w, h]
    return None


def raw_image_size(raw) -> tuple:
    """``(rows, columns)`` of the image :func:`read_raw` returns for an open rawpy file (its DefaultCrop's)."""
    crop = default_crop(raw)
    return (crop[3], crop[2]) if crop else (int(raw.sizes.height), int(raw.sizes.width))


def _saturation_level(raw, white: float, black: list) -> float:
    """The largest count a raw file can hold: its white level or, below it, the top of the linearization curve LibRaw
    applied on reading (a DNG's LinearizationTable, a camera's tone curve). A Blackmagic Pocket Cinema Camera 4K
    DNG states a white level of 65535 while its table ends at 65472, where its clipped pixels sit: saturation is
    looked for at the table's top, not at a white level no pixel reaches."""
    try:
        top = float(np.asarray(raw.tone_curve).max())
    except Exception:  # pragma: no cover - a LibRaw without the curve: the metadata's white level
        return white
    return min(white, top) if top > max(black) else white


def _camera(path) -> Optional[str]:
    """The camera named in a TIFF-based raw file (DNG's UniqueCameraModel, else Make and Model), for the record;
    None when the file is not TIFF-based (CR3) or names none. rawpy does not expose LibRaw's make and model."""
    try:
        with tifffile.TiffFile(path) as tif:
            tags = tif.pages[0].tags
            names = {n: str(tags[n].value).strip("\x00 ") for n in ("UniqueCameraModel", "Make", "Model") if n in tags}
    except Exception:
        return None
    if names.get("UniqueCameraModel"):
        return names["UniqueCameraModel"]
    make, model = names.get("Make", ""), names.get("Model", "")
    name = model if make and model.lower().startswith(make.split()[0].lower()) else f"{make} {model}".strip()
    return name or None


def _raw_levels(raw, path) -> dict:
    """A raw file's metadata as :func:`read_raw` uses it (levels, its mosaic) and records it (the camera's colour
    matrices and white balance, not applied: the counts stay the sensor's); refuses what it cannot read linearly."""
    colours = int(raw.num_colors)
    if colours != 3:
        raise UVPSInputError(f"{path}: a {colours}-colour sensor ({raw.color_desc.decode('ascii', 'replace')}) is not "
                             "supported; expected a 3-colour (RGB) mosaic")
    if raw.raw_type != _rawpy().RawType.Flat:
        raise UVPSInputError(f"{path}: a {raw.raw_type.name} raw file (several values per pixel: Foveon, sRAW, a "
                             "linear DNG, a scanner's RGB) is not supported; expected one colour mosaic (Bayer) value "
                             "per pixel; develop it to a linear 16-bit TIFF")
    black = [float(v) for v in raw.black_level_per_channel]
    white = float(raw.white_level)
    if not white > max(black):
        raise UVPSInputError(f"{path}: its white level ({white:g}) is not above its black level ({max(black):g})")
    sz = raw.sizes
    crop = default_crop(raw)
    return {"camera": _camera(path), "black_level": black, "white_level": white,
            "saturation_level": _saturation_level(raw, white, black),
            "cfa": raw.color_desc.decode("ascii", "replace"),
            "pattern": np.asarray(raw.raw_pattern).tolist() if raw.raw_pattern is not None else None,
            "sensor_px": [int(sz.raw_width), int(sz.raw_height)],
            "image_px": [crop[2], crop[3]] if crop else [int(sz.width), int(sz.height)],
            "margins_px": [int(sz.left_margin), int(sz.top_margin)],
            # a DNG's DefaultCrop (left, top, width, height in the image LibRaw develops), applied on reading
            "default_crop_px": crop,
            # recorded, not applied: the counts stay in the camera's channels (RAW_DEVELOP)
            "colour_matrix": np.round(np.asarray(raw.color_matrix, float), 6).tolist(),
            "rgb_xyz_matrix": np.round(np.asarray(raw.rgb_xyz_matrix, float), 6).tolist(),
            "camera_white_balance": [float(v) for v in raw.camera_whitebalance]}


def read_raw(path: PathLike) -> np.ndarray:
    """A camera raw file (:data:`RAW_EXTS`) as linear ``(M, N, 3)`` float32 counts above its black level.

    LibRaw (through rawpy) develops it as :data:`RAW_DEVELOP` says: no gamma, no automatic
    brightness, white balance fixed (1 for every channel), the camera's colour channels, bilinear
    demosaic. It subtracts the black level of the file's metadata (per CFA channel) and scales to 16 bits by
    ``65535 / (white - the smallest black level)``; that scale is divided back out here, so a count is the sensor's count
    above its black level (saturated at ``white - black``, or below where the file's linearization table ends):
    nothing is rescaled. A DNG's DefaultCrop is applied (:func:`default_crop`).

    Raises
    ------
    UVPSInputError
        The file is missing, or LibRaw cannot read it (one line naming the file).
    """
    path = Path(path)
    if not path.is_file():
        raise UVPSInputError(f"image file {path} does not exist")
    rawpy = _rawpy()
    try:
        with rawpy.imread(str(path)) as raw:
            levels = _raw_levels(raw, path)
            out = raw.postprocess(demosaic_algorithm=rawpy.DemosaicAlgorithm.LINEAR, gamma=(1, 1),
                                  no_auto_bright=True, adjust_maximum_thr=0.0, output_bps=16,
                                  use_camera_wb=False, use_auto_wb=False, user_wb=[1.0, 1.0, 1.0, 1.0],
                                  output_color=rawpy.ColorSpace.raw, user_flip=0)
    except UVPSInputError:
        raise
    except Exception as exc:  # LibRawError and kin: bad input, name the file
        raise UVPSInputError(f"{path}: LibRaw cannot read it as a camera raw file ({_libraw_message(exc)})") from None
    # LibRaw subtracts each channel's black level, then scales to 16 bits by 65535 / (white - the smallest black
    # level): the part common to all channels (its adjust_bl). A DNG with blacks of 500-530 per site read 4.5
    # counts low per 2000 when the largest was divided out.
    scale = 65535.0 / (levels["white_level"] - min(levels["black_level"]))
    crop = levels["default_crop_px"]
    if crop:
        out = out[crop[1]:crop[1] + crop[3], crop[0]:crop[0] + crop[2]]
    return (out.astype(np.float32) / np.float32(scale)).astype(np.float32)


def raw_reading(paths) -> dict:
    """What :func:`read_raw` did to these raw files, for ``run.json``: the develop settings
    (:data:`RAW_DEVELOP`), each distinct black level (per CFA channel), white level and saturation level (the white
    level or the top of the file's linearization curve, the lower), and the saturation in the counts read
    (saturation level - black)."""
    rawpy = _rawpy()
    levels = []
    for p in paths:
        try:
            with rawpy.imread(str(p)) as raw:
                lv = _raw_levels(raw, p)
        except UVPSInputError:
            raise
        except Exception as exc:
            raise UVPSInputError(f"{p}: LibRaw cannot read it as a camera raw file ({_libraw_message(exc)})") from None
        if lv not in levels:
            levels.append(lv)
    return {"reader": f"LibRaw {'.'.join(map(str, rawpy.libraw_version))} (rawpy {rawpy.__version__})",
            "develop": dict(RAW_DEVELOP), "levels": levels,
            "black_level_subtracted": True,
            "saturation_counts": min(lv["saturation_level"] - max(lv["black_level"]) for lv in levels)}
