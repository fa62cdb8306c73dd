"""Command results and atomic writing of outputs.

Every file uvps writes goes first to a temporary name in the same folder and is then renamed into
place (``os.replace`` is atomic on one file system), so a crash never leaves a half-written output
and inputs are never touched.
"""
from __future__ import annotations

import contextlib
import json
import os
import shutil
import tempfile
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, Callable, Iterator, Optional

import numpy as np

from .errors import UVPSInputError

#: A progress callback: fraction in [0, 1] and a short message.
Progress = Optional[Callable[[float, str], None]]


@dataclass
class OutputSpec:
    """One output file of a command, as reported in the bridge response."""

    name: str
    path: str
    kind: str = "image"  # image | table | json | html | pdf | folder
    axes: Optional[str] = None
    dtype: Optional[str] = None
    units: Optional[str] = None

    def to_dict(self) -> dict:
        return asdict(self)


@dataclass
class CommandResult:
    """What a command produced: its outputs and diagnostics (JSON-serialisable)."""

    outputs: list = field(default_factory=list)
    diagnostics: dict = field(default_factory=dict)
    warnings: list = field(default_factory=list)
    text: str = ""      # a plain-text answer the CLI prints (e.g. ``uvps info``)


def report(progress: Progress, fraction: float, message: str) -> None:
    """Call ``progress`` if given."""
    if progress is not None:
        progress(float(min(max(fraction, 0.0), 1.0)), message)


def sub_progress(progress: Progress, start: float, stop: float) -> Progress:
    """A progress callback for a sub-step that covers ``[start, stop]`` of ``progress``."""
    if progress is None:
        return None
    return lambda fraction, message: progress(start + (stop - start) * fraction, message)


def check_output_dir(path) -> Path:
    """Validate an output folder path: it may exist as a folder, must not be a file."""
    path = Path(path)
    if path.exists() and not path.is_dir():
        raise UVPSInputError(f"output folder {path} is an existing file; expected a folder path")
    if not path.parent.exists():
        raise UVPSInputError(f"output folder {path}: its parent folder {path.parent} does not exist")
    return path


@contextlib.contextmanager
def atomic_output_dir(path) -> Iterator[Path]:
    """Yield a fresh temporary folder beside ``path``; on success move its files into ``path``.

    Files already in ``path`` that the run did not write are kept; files it wrote replace old
    ones one by one with ``os.replace``. On an exception the temporary folder is removed and
    ``path`` is untouched.
    """
    path = check_output_dir(path)
    tmp = Path(tempfile.mkdtemp(prefix="." + path.name + ".tmp-", dir=path.parent))
    # mkdtemp makes 0700; a new run folder is this folder renamed, so give it a plain mkdir's mode
    os.chmod(tmp, 0o777 & ~_umask())
    try:
        yield tmp
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    if not path.exists():
        os.replace(tmp, path)
        return
    try:
        stores = [p for p in tmp.iterdir() if p.is_dir() and p.name.endswith(STORE_SUFFIXES)]
        for src in stores:
            replace_dir(src, path / src.name)
        for src in sorted(tmp.rglob("*")):
            rel = src.relative_to(tmp)
            dst = path / rel
            if src.is_dir():
                dst.mkdir(parents=True, exist_ok=True)
            else:
                dst.parent.mkdir(parents=True, exist_ok=True)
                os.replace(src, dst)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


#: Folders that are one output each (a zarr store): replaced whole, never merged file by file (a
#: store merged into an older one would keep the old store's chunks that the new one did not write).
STORE_SUFFIXES = (".zarr",)


def replace_dir(src: Path, dst: Path) -> None:
    """Move the folder ``src`` to ``dst`` (same file system), replacing an existing ``dst`` whole.

    The old ``dst`` is renamed aside first and removed after the new one is in place: a reader
    sees the old store or the new one, or (for the instant between the two renames) none, never a
    mixture of the two.
    """
    src, dst = Path(src), Path(dst)
    os.chmod(src, 0o777 & ~_umask())
    if not dst.exists():
        os.replace(src, dst)
        return
    old = Path(tempfile.mkdtemp(prefix="." + dst.name + ".old-", dir=dst.parent))
    os.rmdir(old)
    os.replace(dst, old)
    os.replace(src, dst)
    shutil.rmtree(old, ignore_errors=True)


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


def file_mode() -> int:
    """The permission bits a plain ``open`` would give a new file (0o666 minus the umask).

    ``tempfile.mkstemp`` creates files 0o600; outputs get the usual mode before being renamed.
    """
    return 0o666 & ~_umask()


@contextlib.contextmanager
def atomic_path(path, *, suffix: str = ".tmp") -> Iterator[Path]:
    """Yield a temporary path beside ``path``; on success give it the usual mode and rename it into
    place (``os.replace``), on an exception remove it. The one atomic-write pattern of uvps."""
    path = Path(path)
    fd, tmp = tempfile.mkstemp(prefix="." + path.name + ".", suffix=suffix, dir=path.parent)
    os.close(fd)
    try:
        yield Path(tmp)
        os.chmod(tmp, file_mode())
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        raise


def write_json_atomic(path, obj: Any) -> None:
    """Write ``obj`` as indented JSON to ``path`` atomically."""
    with atomic_path(path) as tmp:
        with open(tmp, "w", encoding="utf-8") as fh:
            json.dump(obj, fh, indent=2, allow_nan=False, default=_json_default)
            fh.write("\n")


def _json_default(obj):
    if isinstance(obj, np.integer):
        return int(obj)
    if isinstance(obj, np.floating):
        return None if not np.isfinite(obj) else float(obj)
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    if isinstance(obj, Path):
        return str(obj)
    raise TypeError(f"not JSON serialisable: {type(obj).__name__}")


def row_bands(n_rows: int, row_cost: int, budget: int) -> list:
    """Row slices covering ``n_rows`` rows, each of at most ``budget`` (at least one row), a row
    costing ``row_cost`` (pixels or bytes): how every band-by-band step cuts an image."""
    step = max(1, int(budget) // max(int(row_cost), 1))
    return [slice(r0, min(n_rows, r0 + step)) for r0 in range(0, n_rows, step)]
