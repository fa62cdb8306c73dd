"""Light files the user gives: RTI ``.lp`` directions and lamp positions (CSV or uvps ``lights.json``).

Split from :mod:`uvps.files.io`, which re-exports every name here. Every error in the input raises
:class:`~uvps.errors.UVPSInputError` with one line naming the file and what was expected.
"""
from __future__ import annotations

import csv
import json
import math
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Optional, Union

import numpy as np

from ..errors import UVPSInputError

PathLike = Union[str, os.PathLike]


def read_text(path: PathLike, what: str, expected: str) -> str:
    """The text of a file the user gave as text (a table, a light file, a list), UTF-8 with or
    without a BOM; a binary file (an image given for a table) is a one-line
    :class:`UVPSInputError` naming ``what`` and the file and saying what was ``expected``,
    not a UnicodeDecodeError."""
    try:
        return Path(path).read_text(encoding="utf-8-sig")
    except UnicodeDecodeError:
        raise UVPSInputError(f"{what} {path} is not a text file (an image?); expected {expected}") from None


@dataclass
class LightFile:
    """An RTI ``.lp`` light file: one unit direction (and optionally an intensity) per image file."""

    path: str
    files: list
    directions: np.ndarray  # (K, 3) unit
    intensities: Optional[np.ndarray] = None  # (K,) > 0, when the file has a 4th column


@dataclass
class LightPositions:
    """Known lights from a positions file (CSV or uvps ``lights.json``)."""

    path: str
    files: Optional[list]  # None when the file gives no names (then: image order)
    positions_mm: Optional[np.ndarray]  # (K, 3) mm from the image centre
    directions: Optional[np.ndarray]  # (K, 3) unit
    intensities: Optional[np.ndarray] = None  # (K,) > 0, when the file gives them


def _number(token: str) -> Optional[float]:
    """``float(token)``, or None when the token is not a number."""
    try:
        return float(token)
    except ValueError:
        return None


def _check_intensity(value: Optional[float], token: str, where: str) -> float:
    """A given lamp intensity: a finite number > 0, else a one-line error naming ``where``."""
    if value is None:
        raise UVPSInputError(f"{where}: intensity {token!r} is not a number")
    if not (math.isfinite(value) and value > 0):
        raise UVPSInputError(f"{where}: intensity {token!r} must be a finite number > 0")
    return value


def read_lp(path: PathLike) -> LightFile:
    """Read an RTI ``.lp`` light file.

    Parameters
    ----------
    path : path
        First line: the number of images K; then K lines ``filename x y z`` (light direction,
        normalised here), or ``filename x y z intensity`` on every line (the lamp's relative
        intensity ``E_k``, a number > 0). Blank lines and lines starting with ``#`` are skipped.

    Returns
    -------
    LightFile
        ``intensities`` is None when the file has no 4th column: an ``.lp`` file says nothing
        about the lamps' intensities, and uvps then takes them as equal.
    """
    path = Path(path)
    if not path.is_file():
        raise UVPSInputError(f"light file {path} does not exist")
    numbered = [(i, ln.strip()) for i, ln in
                enumerate(read_text(path, "light file", "a count then 'file x y z' lines").splitlines(),
                          start=1)]
    numbered = [(i, ln) for i, ln in numbered if ln and not ln.startswith("#")]
    if not numbered:
        raise UVPSInputError(
            f"light file {path} is empty; expected a count then 'file x y z' lines"
        )
    try:
        count = int(numbered[0][1].split()[0])
    except ValueError:
        raise UVPSInputError(
            f"light file {path}: first line must be the number of images; got {numbered[0][1]!r}"
        )
    rows = numbered[1:]
    if len(rows) != count:
        raise UVPSInputError(f"light file {path} announces {count} lights but lists {len(rows)}")
    files, dirs, intensities = [], [], []
    first_layout = None  # (line, 3 or 4 numbers) of the first row: every row must match it
    for i, row in rows:
        where = f"light file {path} line {i}"
        parts = row.split()
        values = [_number(t) for t in parts]
        # trailing numbers (at most 4), leaving at least one token for the file name
        n_num = 0
        while n_num < min(4, len(parts) - 1) and values[-1 - n_num] is not None:
            n_num += 1
        if n_num < 3 and len(parts) >= 5 and all(v is not None for v in values[-4:-1]):
            _check_intensity(values[-1], parts[-1], where)  # 'file x y z junk': raises
        if n_num < 3:
            raise UVPSInputError(f"{where}: expected 'file x y z [intensity]'; got {row!r}")
        if first_layout is None:
            first_layout = (i, n_num)
        elif n_num != first_layout[1]:
            has = "has" if n_num == 4 else "has no"
            other = "does not" if n_num == 4 else "does"
            raise UVPSInputError(
                f"{where} {has} intensity column but line {first_layout[0]} {other};"
                " give 'file x y z' or 'file x y z intensity' on every line"
            )
        vec = values[len(parts) - n_num:][:3]
        if n_num == 4:
            intensities.append(_check_intensity(values[-1], parts[-1], where))
        norm = math.sqrt(sum(v * v for v in vec))
        if not math.isfinite(norm) or norm == 0:
            raise UVPSInputError(f"{where}: direction {vec} has no length")
        files.append(" ".join(parts[:len(parts) - n_num]))
        dirs.append([v / norm for v in vec])
    return LightFile(str(path), files, np.asarray(dirs, dtype=np.float64),
                     np.asarray(intensities, dtype=np.float64) if intensities else None)


def read_positions(path: PathLike) -> LightPositions:
    """Read known light positions (mm) or directions from a CSV or uvps ``lights.json``.

    Parameters
    ----------
    path : path
        CSV with header ``file,x_mm,y_mm,z_mm`` (or just ``x_mm,y_mm,z_mm`` in image order) and
        optionally an ``intensity`` column (each lamp's relative intensity, a number > 0), or JSON
        as written by uvps (``lights.json``: a ``lights`` list whose entries have ``position_mm``
        and/or ``direction``, and ``intensity``).

    Returns
    -------
    LightPositions
        Positions are in the world frame (x right, y up, z toward the camera), mm from the image
        centre; directions are normalised; ``intensities`` is None unless every light has one.
    """
    path = Path(path)
    if not path.is_file():
        raise UVPSInputError(f"light positions file {path} does not exist")
    read = _positions_json if path.suffix.lower() == ".json" else _positions_csv
    names, positions, directions, intensities = read(path)
    for name, arr in (("position_mm", positions), ("direction", directions)):
        if arr is not None and (arr.ndim != 2 or arr.shape[1] != 3 or not np.isfinite(arr).all()):
            raise UVPSInputError(
                f"light positions file {path}: each {name} must be 3 finite numbers;"
                f" got shape {arr.shape}"
            )
    for name, arr in (("z_mm", positions), ("direction z", directions)):
        if arr is not None and np.any(arr[:, 2] <= 0):
            k = int(np.flatnonzero(arr[:, 2] <= 0)[0])
            raise UVPSInputError(f"light positions file {path}: light {k + 1} has {name} = {arr[k, 2]:g}; lamps "
                                 "light the canvas from the camera's side (z > 0, toward the camera)")
    if directions is not None:
        norms = np.linalg.norm(directions, axis=1)
        if np.any(norms == 0):
            raise UVPSInputError(f"light positions file {path}: a direction has zero length")
        directions = directions / norms[:, None]
    if intensities is not None:
        intensities = np.asarray(intensities, dtype=np.float64)
    return LightPositions(str(path), names, positions, directions, intensities)


def _positions_json(path: Path) -> tuple:
    """``(names, positions, directions, intensities)`` of a uvps ``lights.json`` (:func:`read_positions`)."""
    try:
        doc = json.loads(path.read_text(encoding="utf-8"))
        lights = doc["lights"] if isinstance(doc, dict) else doc
        if not isinstance(lights, list) or not lights:
            raise ValueError("no 'lights' list")
    except (ValueError, KeyError, TypeError) as exc:
        raise UVPSInputError(
            f"light positions file {path}: expected uvps lights.json with a 'lights' list"
            f" ({exc})"
        )
    files = [lt.get("file") for lt in lights]
    pos = [lt.get("position_mm") for lt in lights]
    dirs = [lt.get("direction") for lt in lights]
    positions = np.asarray(pos, dtype=np.float64) if all(p is not None for p in pos) else None
    directions = (np.asarray(dirs, dtype=np.float64)
                  if all(d is not None for d in dirs) else None)
    if positions is None and directions is None:
        raise UVPSInputError(
            f"light positions file {path}: every light needs 'position_mm' or 'direction'"
        )
    names = files if all(isinstance(f, str) and f for f in files) else None
    intensities = None
    if all(lt.get("intensity") is not None for lt in lights):
        intensities = []
        for k, lt in enumerate(lights):
            value = lt["intensity"]
            number = (float(value) if isinstance(value, (int, float)) and not isinstance(value, bool)
                      else None)
            intensities.append(_check_intensity(number, str(value),
                                                f"light positions file {path} light {k + 1}"))
    return names, positions, directions, intensities


def _positions_csv(path: Path) -> tuple:
    """``(names, positions, directions, intensities)`` of a positions CSV (:func:`read_positions`)."""
    text = read_text(path, "light positions file", "a CSV with columns file,x_mm,y_mm,z_mm")
    rows = list(csv.DictReader(text.splitlines()))
    need = ("x_mm", "y_mm", "z_mm")
    if not rows or any(k not in rows[0] for k in need):
        raise UVPSInputError(
            f"light positions file {path}: expected a CSV with columns file,x_mm,y_mm,z_mm"
        )
    try:
        positions = np.array([[float(r[k]) for k in need] for r in rows])
    except (TypeError, ValueError):
        raise UVPSInputError(f"light positions file {path}: non-numeric x_mm/y_mm/z_mm value")
    names = [r["file"] for r in rows] if "file" in rows[0] else None
    directions = None
    intensities = None
    if "intensity" in rows[0]:
        # line numbers: the header is line 1 (a CSV row spanning lines is not expected here)
        intensities = [_check_intensity(_number(r["intensity"] or ""), r["intensity"] or "",
                                        f"light positions file {path} line {k + 2}")
                       for k, r in enumerate(rows)]
    return names, positions, directions, intensities
