"""Camera raw files (:data:`uvps.files.io.RAW_EXTS`) read linearly with LibRaw (rawpy).

Part of the file reading; :mod:`uvps.files.io` exposes these names and calls :func:`read_raw`.
"""
from __future__ import annotations

import os
from pathlib import Path
from typing import Union

import numpy as np

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


def _raw_levels(raw, path) -> dict:
    """A raw file's metadata as :func:`read_raw` uses it (levels, its mosaic) and records it (the camera's colour
    matrices and white balance, not applied: the counts stay the sensor's); refuses what it cannot read linearly."""
    colours = int(raw.num_colors)
    if colours != 3:
        raise UVPSInputError(f"{path}: a {colours}-colour sensor ({raw.color_desc.decode('ascii', 'replace')}) is not "
                             "supported; expected a 3-colour (RGB) mosaic")
    if raw.raw_type != _rawpy().RawType.Flat:
        raise UVPSInputError(f"{path}: a {raw.raw_type.name} raw file (several values per pixel: Foveon, sRAW, a "
                             "linear DNG) is not supported; expected one colour mosaic (Bayer) value per pixel")
    black = [float(v) for v in raw.black_level_per_channel]
    white = float(raw.white_level)
    if not white > max(black):
        raise UVPSInputError(f"{path}: its white level ({white:g}) is not above its black level ({max(black):g})")
    sz = raw.sizes
    return {"black_level": black, "white_level": white, "cfa": raw.color_desc.decode("ascii", "replace"),
            "pattern": np.asarray(raw.raw_pattern).tolist() if raw.raw_pattern is not None else None,
            "sensor_px": [int(sz.raw_width), int(sz.raw_height)], "image_px": [int(sz.width), int(sz.height)],
            "margins_px": [int(sz.left_margin), int(sz.top_margin)],
            # recorded, not applied: the counts stay in the camera's channels (RAW_DEVELOP)
            "colour_matrix": np.round(np.asarray(raw.color_matrix, float), 6).tolist(),
            "rgb_xyz_matrix": np.round(np.asarray(raw.rgb_xyz_matrix, float), 6).tolist(),
            "camera_white_balance": [float(v) for v in raw.camera_whitebalance]}


def read_raw(path: PathLike) -> np.ndarray:
    """A camera raw file (:data:`RAW_EXTS`) as linear ``(M, N, 3)`` float32 counts above its black level.

    LibRaw (through rawpy) develops it as :data:`RAW_DEVELOP` says: no gamma, no automatic
    brightness, white balance fixed (1 for every channel), the camera's colour channels, bilinear
    demosaic. It subtracts the black level of the file's metadata and scales to 16 bits by
    ``65535 / (white - black)``; that scale is divided back out here, so a count is the sensor's count
    above its black level (saturated at ``white - black``): nothing is rescaled.

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
        msg = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        raise UVPSInputError(f"{path}: LibRaw cannot read it as a camera raw file ({msg})") from None
    # LibRaw's scale to 16 bits uses the largest black level
    scale = 65535.0 / (levels["white_level"] - max(levels["black_level"]))
    return (out.astype(np.float32) / np.float32(scale)).astype(np.float32)


def raw_reading(paths) -> dict:
    """What :func:`read_raw` did to these raw files, for ``run.json``: the develop settings
    (:data:`RAW_DEVELOP`), each distinct black level (per CFA channel) and white level, and the
    saturation in the counts read (white - black)."""
    rawpy = _rawpy()
    levels = []
    for p in paths:
        try:
            with rawpy.imread(str(p)) as raw:
                lv = _raw_levels(raw, p)
        except UVPSInputError:
            raise
        except Exception as exc:
            raise UVPSInputError(f"{p}: LibRaw cannot read it as a camera raw file ({exc})") from None
        if lv not in levels:
            levels.append(lv)
    return {"reader": f"LibRaw {'.'.join(map(str, rawpy.libraw_version))} (rawpy {rawpy.__version__})",
            "develop": dict(RAW_DEVELOP), "levels": levels,
            "black_level_subtracted": True,
            "saturation_counts": min(lv["white_level"] - max(lv["black_level"]) for lv in levels)}
