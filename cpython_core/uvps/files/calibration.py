"""The calibration folder: lamps pinned once by spheres (or a measured rig), reused for every capture
taken with the same lamp positions (``uvps calibrate``, ``uvps run --calibration CAL``).

A calibration folder ``CAL`` holds (docs/capture.md, the contract in docs/architecture.md):

- ``calibration.json``: ``{"format": "uvps-calibration", "version": 1, "pixel_size_um", "image_shape",
  "n_lamps", "route": "spheres" | "positions" | "dome" | "lp", "spheres": [...], "camera_distance_mm": null |
  mm (the spheres read through a pinhole camera that far above the image centre), "lamps": [...],
  "inputs": {path: sha256}, "card": {...} or null, "dark": bool}``;
- ``lights.json``: the run folder's format (a direction per lamp; a position in mm where two or more
  spheres, a positions file or a 3-D dome give one), matched to a capture's images by order;
- ``rig.dome``: the same lamps as a relight dome file (JSON; :func:`write_dome`), for RTI tools;
- ``dark.tif``: the dark frame as given (counts), when one was;
- ``spheres.png``: the sphere capture's mean with the spheres found drawn on it, to check.

Relight's ``.dome`` (cnr-isti-vclab/relight, docs/dome.md there): a JSON object with ``label``,
``notes``, ``imageWidth``, ``domeDiameter``, ``verticalOffset``, ``lightConfiguration``
("directional", "spherical" or "lights3d"), ``directions``, ``positionsSphere`` and ``positions3d``
(each a list of ``{"x", "y", "z"}``; origin the image centre, x right, y toward the top of the
image, z up toward the camera: uvps's frame) and ``ledAdjust``. Its unit is the file's own (recent
relight: mm; older files: cm); only the ratio to ``imageWidth`` matters to relight. uvps writes mm
with ``imageWidth`` the field's width in mm, and reads positions in mm, or scaled by the field's
width over ``imageWidth`` when both are known.
"""
from __future__ import annotations

import json
import logging
from dataclasses import dataclass
from pathlib import Path
from typing import Optional

import numpy as np

from ..errors import UVPSInputError
from .io import read_positions, sha256_file
from .outputs import write_json_atomic

log = logging.getLogger(__name__)

FORMAT = "uvps-calibration"
VERSION = 1
FILES = {"calibration": "calibration.json", "lights": "lights.json", "dome": "rig.dome", "dark": "dark.tif",
         "spheres_png": "spheres.png", "card": "card.tif"}


# ------------------------------------------------------------------------------------------------
# relight's .dome
# ------------------------------------------------------------------------------------------------

@dataclass
class DomeRig:
    """Lamps of a relight ``.dome`` file: directions (K, 3) unit, positions (K, 3) in the file's
    unit or None, ``image_width`` (the file's unit, 0 = not given), ``label``, ``notes``."""

    directions: np.ndarray
    positions: Optional[np.ndarray]
    image_width: float
    label: str = ""
    notes: str = ""


def _vectors(values, path, key) -> Optional[np.ndarray]:
    if values in (None, []):
        return None
    try:
        arr = np.array([[float(v["x"]), float(v["y"]), float(v["z"])] for v in values])
    except (TypeError, KeyError, ValueError):
        raise UVPSInputError(f"dome file {path}: {key} must be a list of {{\"x\", \"y\", \"z\"}} numbers") from None
    if not np.isfinite(arr).all():
        raise UVPSInputError(f"dome file {path}: {key} holds a value that is not finite")
    return arr


def read_dome(path) -> DomeRig:
    """Read a relight ``.dome`` file (see the module notes).

    ``lights3d`` takes ``positions3d``, ``spherical`` ``positionsSphere``, ``directional`` the
    directions only; a file without ``lightConfiguration`` takes positions where it has them.

    Examples
    --------
    >>> import tempfile, os, numpy as np
    >>> p = os.path.join(tempfile.mkdtemp(), "rig.dome")
    >>> write_dome(p, directions=np.array([[0, 0.6, 0.8], [0.6, 0, 0.8], [0, -0.6, 0.8]]), image_width_mm=24.0)
    >>> rig = read_dome(p)
    >>> rig.directions.shape, rig.positions, rig.image_width
    ((3, 3), None, 24.0)
    """
    path = Path(path)
    if not path.is_file():
        raise UVPSInputError(f"dome file {path} does not exist")
    try:
        doc = json.loads(path.read_text(encoding="utf-8"))
        if not isinstance(doc, dict):
            raise ValueError("not a JSON object")
    except (ValueError, UnicodeDecodeError) as exc:
        raise UVPSInputError(f"dome file {path}: expected relight's JSON dome format ({exc})") from None
    config = str(doc.get("lightConfiguration") or "").lower()
    dirs = _vectors(doc.get("directions"), path, "directions")
    p3 = _vectors(doc.get("positions3d"), path, "positions3d")
    ps = _vectors(doc.get("positionsSphere"), path, "positionsSphere")
    positions = {"lights3d": p3, "spherical": ps if ps is not None else p3, "directional": None}.get(
        config, p3 if p3 is not None else ps)
    if dirs is None and positions is None:
        raise UVPSInputError(f"dome file {path} has no directions or positions; expected relight's dome format")
    if dirs is None:
        dirs = positions
    n = np.linalg.norm(dirs, axis=1)
    if np.any(n == 0) or np.any(dirs[:, 2] <= 0):
        k = int(np.flatnonzero((n == 0) | (dirs[:, 2] <= 0))[0])
        raise UVPSInputError(f"dome file {path}: light {k + 1} points away from the camera (z <= 0); expected z up")
    if positions is not None and len(positions) != len(dirs):
        raise UVPSInputError(f"dome file {path}: {len(dirs)} directions but {len(positions)} positions")
    try:
        width = float(doc.get("imageWidth") or 0.0)
    except (TypeError, ValueError):
        raise UVPSInputError(f"dome file {path}: imageWidth must be a number") from None
    return DomeRig(dirs / n[:, None], positions, width, str(doc.get("label") or ""), str(doc.get("notes") or ""))


def write_dome(path, *, directions, positions_mm=None, image_width_mm: float = 0.0, label: str = "",
               notes: str = "") -> None:
    """Write lamps as a relight ``.dome`` file (mm; ``lights3d`` with positions, else ``directional``)."""
    def vec(a):
        return [{"x": float(v[0]), "y": float(v[1]), "z": float(v[2])} for v in a]

    D = np.asarray(directions, float)
    doc = {"label": label, "notes": notes, "imageWidth": float(image_width_mm), "domeDiameter": 0.0,
           "verticalOffset": 0.0, "lightConfiguration": "directional" if positions_mm is None else "lights3d",
           "directions": vec(D / np.linalg.norm(D, axis=1, keepdims=True)), "positionsSphere": [],
           "positions3d": [] if positions_mm is None else vec(positions_mm), "ledAdjust": []}
    write_json_atomic(path, doc)


# ------------------------------------------------------------------------------------------------
# the folder
# ------------------------------------------------------------------------------------------------

@dataclass
class Calibration:
    """A calibration folder as read back (:func:`read_calibration`)."""

    folder: Path
    doc: dict

    @property
    def n_lamps(self) -> int:
        return int(self.doc["n_lamps"])

    @property
    def image_shape(self) -> Optional[tuple]:
        s = self.doc.get("image_shape")
        return tuple(int(v) for v in s) if s else None

    @property
    def pixel_size_um(self) -> Optional[float]:
        v = self.doc.get("pixel_size_um")
        return float(v) if v else None

    @property
    def lights(self) -> Path:
        return self.folder / FILES["lights"]

    @property
    def dark(self) -> Optional[Path]:
        p = self.folder / FILES["dark"]
        return p if p.is_file() else None

    @property
    def card(self) -> Optional[Path]:
        p = self.folder / FILES["card"]
        return p if p.is_file() else None

    def summary(self) -> dict:
        """What a run records of the calibration it used (run.json ``diagnostics.calibration``)."""
        return {"folder": str(self.folder.resolve()), "route": self.doc.get("route"), "n_lamps": self.n_lamps,
                "created_utc": self.doc.get("created_utc"),
                "sha256": sha256_file(self.folder / FILES["calibration"]),
                "positions": any(lp.get("position_mm") is not None for lp in self.doc.get("lamps", [])),
                "dark": bool(self.doc.get("dark")), "card": self.doc.get("card") is not None,
                "camera_distance_mm": self.doc.get("camera_distance_mm")}


def read_calibration(path) -> Calibration:
    """Read and check a calibration folder (one-line errors naming it)."""
    folder = Path(path)
    cj = folder / FILES["calibration"]
    if not folder.is_dir() or not cj.is_file():
        raise UVPSInputError(f"calibration {folder}: expected a folder written by `uvps calibrate` (with "
                             "calibration.json)")
    try:
        doc = json.loads(cj.read_text(encoding="utf-8"))
    except ValueError as exc:
        raise UVPSInputError(f"calibration {cj}: not JSON ({exc})") from None
    if not isinstance(doc, dict) or doc.get("format") != FORMAT:
        raise UVPSInputError(f"calibration {cj}: format is not {FORMAT!r}")
    if int(doc.get("version", 0)) > VERSION:
        raise UVPSInputError(f"calibration {cj}: version {doc.get('version')} is newer than this uvps reads "
                             f"({VERSION}); update uvps")
    if not (folder / FILES["lights"]).is_file():
        raise UVPSInputError(f"calibration {folder}: lights.json is missing")
    return Calibration(folder, doc)


def run_params(params: dict) -> tuple:
    """``(params, calibration)``: a capture command's parameters with a calibration's dark frame and
    pixel size filled in (its lamps are attached to the capture read: :func:`apply`); ``(params, None)``
    without ``calibration``."""
    if not params.get("calibration"):
        return params, None
    cal = read_calibration(params["calibration"])
    if params.get("lights") is not None:
        raise UVPSInputError(f"give calibration or lights, not both (calibration {cal.folder} holds the lamps)")
    out = dict(params)
    if params.get("dark") is None and cal.dark is not None:
        out["dark"] = str(cal.dark)
    if params.get("pixel_size_um") is None and cal.pixel_size_um:
        out["pixel_size_um"] = cal.pixel_size_um
    # the card part (uvps.core.card, contract C): a calibration holding card.tif is a stored card for the
    # run's `card` parameter, where the run declares one and none is given
    if "card" in params and params.get("card") is None and cal.card is not None:
        out["card"] = str(cal.folder)
    return out, cal


def apply(cal: Calibration, capture):
    """The capture with the calibration's lamps (matched to its images by order), after
    :func:`check_capture`."""
    import dataclasses

    check_capture(cal, capture)
    lp = read_positions(cal.lights)
    return dataclasses.replace(capture, light_positions_mm=lp.positions_mm,
                               light_directions=None if lp.positions_mm is not None else lp.directions,
                               light_intensities=lp.intensities)


def check_capture(cal: Calibration, capture) -> None:
    """Lamps matched to images by order: the count and the image size must be the calibration's."""
    K = capture.images.shape[0]
    if K != cal.n_lamps:
        raise UVPSInputError(f"calibration {cal.folder} has {cal.n_lamps} lamps; the capture has {K} images "
                             "(lamps are matched to the images by order)")
    shape = tuple(capture.images.shape[1:3])
    if cal.image_shape is not None and shape != cal.image_shape:
        raise UVPSInputError(f"calibration {cal.folder} was made on {cal.image_shape[1]} x {cal.image_shape[0]} px "
                             f"images; the capture is {shape[1]} x {shape[0]} px (same camera and framing expected)")


def calibration_of_run(run_dir) -> dict:
    """What a run folder's ``run.json`` records of its lamps: the calibration it used (folder, route,
    SHA-256 of its calibration.json), else where its lamps came from (``lights`` file or estimated)."""
    try:
        log_ = json.loads((Path(run_dir) / "run.json").read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return {"calibration": None, "lamps": "unknown (no readable run.json)"}
    cal = (log_.get("diagnostics") or {}).get("calibration")
    if cal:
        return {"calibration": cal, "lamps": "calibration"}
    lights = (log_.get("params") or {}).get("lights")
    return {"calibration": None, "lamps": f"light file {lights}" if lights and lights != "estimate" else "estimated"}
