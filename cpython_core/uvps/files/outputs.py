"""Command results and atomic writing of outputs.

Every file uvps writes goes first to a temporary name in the same folder and is then renamed into
place (``os.replace`` is atomic on one file system), so a crash never leaves a half-written output
and inputs are never touched.
"""
from __future__ import annotations

import contextlib
import os
import shutil
import signal
import tempfile
import threading
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Callable, Iterator, Optional


from ..core.progress import Progress, report, sub_progress  # noqa: F401 - the commands' progress helpers
from ..errors import UVPSInputError
from .atomic import _umask, atomic_path, file_mode, write_json_atomic  # noqa: F401 - re-exported

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


def check_output_dir(path) -> Path:
    """Validate an output folder path before anything is computed.

    It may exist as a folder (not a file); missing parent folders are allowed (they are made when
    the outputs are moved into place, :func:`make_parents`); the nearest existing one must be a
    folder this process can write in, so a read-only location fails here in one line, not after
    the whole computation.
    """
    path = Path(path)
    if path.exists() and not path.is_dir():
        raise UVPSInputError(f"output folder {path} is an existing file; expected a folder path")
    ancestor = path.parent
    while not ancestor.exists() and ancestor != ancestor.parent:
        ancestor = ancestor.parent
    if not ancestor.is_dir():
        raise UVPSInputError(f"output folder {path}: {ancestor} is a file, not a folder; choose another output folder")
    for where in ([path] if path.is_dir() else []) + [ancestor]:
        if not os.access(where, os.W_OK | os.X_OK):
            raise UVPSInputError(f"output folder {path}: cannot write in {where} (read-only or no permission); "
                                 "choose another output folder")
    return path


def make_parents(path: Path) -> list:
    """Make the missing parent folders of ``path``; return those made, outermost first (to remove
    them again when nothing is written)."""
    made = []
    parent = Path(path).parent
    while not parent.exists():
        made.append(parent)
        parent = parent.parent
    made.reverse()
    for d in made:
        d.mkdir(exist_ok=True)
    return made


def _remove_empty(folders: list) -> None:
    for d in reversed(folders):
        with contextlib.suppress(OSError):
            d.rmdir()


#: Output folders this process has finished writing (moved into place whole): after a Ctrl-C that
#: arrives during the final move (it is deferred to its end), the CLI says the folder is complete.
COMMITTED: set = set()


@contextlib.contextmanager
def deferred_signals() -> Iterator[None]:
    """Hold SIGINT and SIGTERM for the duration of a few renames, then deliver them.

    A Ctrl-C between two renames of a swap would leave neither folder in place; Python runs signal
    handlers in the main thread only, so a handler that records the signal keeps the renames whole
    whichever thread the kernel delivers it to. Outside the main thread (a worker) nothing is held.
    """
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    got = []
    old = {s: signal.signal(s, lambda n, _f: got.append(n)) for s in (signal.SIGINT, signal.SIGTERM)}
    try:
        yield
    finally:
        for s, h in old.items():
            signal.signal(s, h)
        if got:
            handler = old[got[0]]
            if callable(handler):
                handler(got[0], None)
            elif handler == signal.SIG_DFL:
                os.kill(os.getpid(), got[0])


def _exchange(a: Path, b: Path) -> bool:
    """Swap two folders in one step (Linux ``renameat2(RENAME_EXCHANGE)``); False where the system
    has no such call (then the caller uses two renames with signals held)."""
    import ctypes

    try:
        libc = ctypes.CDLL(None, use_errno=True)
        fn = libc.renameat2
    except (OSError, AttributeError):
        return False
    at_fdcwd, rename_exchange = -100, 2
    return fn(at_fdcwd, os.fsencode(str(a)), at_fdcwd, os.fsencode(str(b)), rename_exchange) == 0


@contextlib.contextmanager
def new_output_dir(path, *, carry_over: Callable[[str], bool] = lambda name: False) -> Iterator[Path]:
    """Yield an empty folder to build a complete new ``path`` in; on success it replaces ``path`` whole.

    The folder is ``<parent>/.<name>.uvps-new-XXXX/<name>`` (its own name is ``path``'s, so a report
    written into it names the folder as it will be). At the end, entries of the old ``path`` for
    which ``carry_over(name)`` is true (files the command does not own: the user's notes, clicks,
    the demo's capture) are hard-linked (or copied) into it, and the two folders are swapped in one
    step (``renameat2(RENAME_EXCHANGE)``; elsewhere two renames with Ctrl-C held). A reader sees
    the old folder or the new one, never a mixture. On an exception or Ctrl-C before the swap the
    new folder is removed, ``path`` is exactly as it was (or still absent, with no parent folder
    left behind) and the exception propagates. Missing parent folders are made.
    """
    path = check_output_dir(path)
    made = make_parents(path)
    try:
        stage = Path(tempfile.mkdtemp(prefix="." + path.name + ".uvps-new-", dir=path.parent))
    except BaseException:
        _remove_empty(made)
        raise
    new = stage / path.name
    try:
        new.mkdir(mode=0o777 & ~_umask())
        yield new
        if path.is_dir():
            for entry in sorted(path.iterdir()):
                if carry_over(entry.name) and not (new / entry.name).exists():
                    _link_tree(entry, new / entry.name)
        with deferred_signals():
            if path.is_dir():
                if not _exchange(new, path):
                    os.replace(path, stage / (path.name + ".old"))
                    os.replace(new, path)
            else:
                os.replace(new, path)
            COMMITTED.add(str(path))
            shutil.rmtree(stage, ignore_errors=True)
    except BaseException:
        shutil.rmtree(stage, ignore_errors=True)
        if str(path) not in COMMITTED:
            _remove_empty(made)
        raise


def _link_tree(src: Path, dst: Path) -> None:
    """``src`` (a file or folder) at ``dst`` by hard links, copying where a link is refused."""
    if src.is_dir() and not src.is_symlink():
        shutil.copytree(src, dst, symlinks=True, copy_function=_link_or_copy)
    else:
        _link_or_copy(src, dst)


def _link_or_copy(src, dst) -> None:
    try:
        os.link(src, dst, follow_symlinks=False)
    except OSError:
        shutil.copy2(src, dst, follow_symlinks=False)


@contextlib.contextmanager
def atomic_output_dir(path) -> Iterator[Path]:
    """Yield a fresh temporary folder beside ``path``; on success move its files into ``path``.

    For commands that add to a run folder (detect, wand, regions, stats, compare): files already in
    ``path`` that the command did not write are kept; files it wrote replace old ones one by one
    with ``os.replace``, with Ctrl-C held until the last is in place. On an exception the
    temporary folder is removed and ``path`` is untouched. Missing parent folders are made.
    (``run`` replaces its folder whole: :func:`new_output_dir`.)
    """
    path = check_output_dir(path)
    made = make_parents(path)
    tmp = Path(tempfile.mkdtemp(prefix="." + path.name + ".tmp-", dir=path.parent))
    # mkdtemp makes 0700; a new run folder is this folder renamed, so give it a plain mkdir's mode
    os.chmod(tmp, 0o777 & ~_umask())
    try:
        yield tmp
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        _remove_empty(made)
        raise
    with deferred_signals():
        if not path.exists():
            os.replace(tmp, path)
            COMMITTED.add(str(path))
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
            COMMITTED.add(str(path))
        finally:
            shutil.rmtree(tmp, ignore_errors=True)


#: Folders that are one output each (a zarr store): replaced whole, never merged file by file (a
#: store merged into an older one would keep the old store's chunks that the new one did not write).
STORE_SUFFIXES = (".zarr",)


def replace_dir(src: Path, dst: Path, *, aside: str = ".old-") -> None:
    """Move the folder ``src`` to ``dst`` (same file system), replacing an existing ``dst`` whole.

    The old ``dst`` is renamed aside first (to ``.<name><aside>XXXX`` beside it) and removed after
    the new one is in place: a reader sees the old folder or the new one, or (for the instant
    between the two renames) none, never a mixture of the two.
    """
    src, dst = Path(src), Path(dst)
    os.chmod(src, 0o777 & ~_umask())
    if not dst.exists():
        os.replace(src, dst)
        return
    old = Path(tempfile.mkdtemp(prefix="." + dst.name + aside, dir=dst.parent))
    os.rmdir(old)
    os.replace(dst, old)
    os.replace(src, dst)
    shutil.rmtree(old, ignore_errors=True)
