"""Atomic writing of one file: a temporary name in the same folder, renamed into place
(``os.replace`` is atomic on one file system), so a crash never leaves a half-written output."""
from __future__ import annotations

import contextlib
import json
import os
import tempfile
import threading
from pathlib import Path
from typing import Any, Iterator

import numpy as np


_UMASK_LOCK = threading.Lock()


def _umask() -> int:
    """The process's umask, unchanged. Linux says it in ``/proc/self/status``; elsewhere ``os.umask``, the only
    call that reads it, also sets it for every thread: set and restored under a lock (two threads writing files
    interleaved their calls, which gave a file mode 0o666 and could leave the umask 0)."""
    with contextlib.suppress(OSError, ValueError):
        with open("/proc/self/status", encoding="ascii", errors="replace") as f:
            for line in f:
                if line.startswith("Umask:"):
                    return int(line.split()[1], 8)
    with _UMASK_LOCK:
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
