"""A card's files: its images read and calibrated (:func:`load_card`), a calibrated card written to
and read from a folder (``card.tif``, ``card.json``). The numbers are :mod:`uvps.core.card`'s."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from ..core.card import CardCalibration, calibrate_card
from ..errors import UVPSInputError
from .io import read_capture, read_image, write_imagej_tiff
from .outputs import write_json_atomic

__all__ = ["CARD_FILES", "write_card", "read_card", "load_card"]

#: Files of a stored card: the gains (ImageJ TIFF, one slice per lamp) and their description.
CARD_FILES = ("card.tif", "card.json")


def write_card(card: CardCalibration, folder, *, pixel_size_um: float) -> list:
    """``card.tif`` (the gains, (K, M, N) float32) and ``card.json`` (the coefficients and
    figures) in ``folder``, each written atomically. Returns the paths."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    tif = write_imagej_tiff(folder / CARD_FILES[0], card.gains, axes="ZYX", pixel_size_um=pixel_size_um,
                            unit="um", labels=[f"lamp {k + 1}" for k in range(card.n_lamps)])
    meta = {"format": "uvps-card", "version": 1, **card.to_json(), "coeffs": card.coeffs.tolist()}
    write_json_atomic(folder / CARD_FILES[1], meta)
    return [Path(tif), folder / CARD_FILES[1]]


def read_card(folder) -> CardCalibration:
    """A card written by :func:`write_card` (its ``card.json``; ``card.tif`` holds the same gains)."""
    path = Path(folder) / CARD_FILES[1]
    try:
        meta = json.loads(path.read_text(encoding="utf-8"))
        coeffs = np.asarray(meta["coeffs"], dtype=float)
        shape = tuple(int(v) for v in meta["image_shape"])
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise UVPSInputError(f"card {path}: not a uvps card description ({exc})") from None
    if meta.get("format") != "uvps-card" or coeffs.ndim != 3 or coeffs.shape[1] != coeffs.shape[2]:
        raise UVPSInputError(f"card {path}: not a uvps card description (format uvps-card, coeffs (K, n, n))")
    known = {"n_lamps", "image_shape", "degree", "tilt_deg", "tilt_azimuth_deg", "unevenness", "relief_deg",
             "format", "version", "coeffs"}
    return CardCalibration(coeffs, shape, float(meta["tilt_deg"]), float(meta["tilt_azimuth_deg"]),
                           float(meta["unevenness"]), float(meta["relief_deg"]),
                           {k: v for k, v in meta.items() if k not in known})


def load_card(path, *, lights, pixel_size_um: float, dark=None, linearize: str = "auto") -> CardCalibration:
    """A card from ``path``: a folder written by :func:`write_card` (``card.json``), or the
    card's images (a folder or multi-page TIFF, one image per lamp in the capture's order), calibrated
    with ``lights`` and the dark frame ``dark`` (a path) by :func:`uvps.core.card.calibrate_card`."""
    path = Path(path)
    if path.is_dir() and (path / CARD_FILES[1]).is_file():
        return read_card(path)
    if not path.exists():
        raise UVPSInputError(f"card {path} does not exist (a folder of card images, one per lamp, or a stored card)")
    cap = read_capture(path, pixel_size_um=pixel_size_um, linearize=linearize)
    d = None
    if dark is not None:
        d = read_image(Path(dark))
    return calibrate_card(cap.images, lights=lights, pixel_size_um=pixel_size_um, dark=d,
                          saturation=cap.saturation)
