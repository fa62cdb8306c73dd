"""The file bridge between the Fiji side and the numpy core: ``uvps bridge REQUEST.json``.

One request folder per call holds ``request.json``::

    {"schema_version": 1, "command": "run", "inputs": {...}, "params": {...},
     "output_dir": "/abs/out"}

:func:`run_bridge` validates it, runs ``uvps.commands.COMMANDS[command](inputs, params,
output_dir, progress=...)`` and always writes ``response.json`` beside the request (atomically),
on success and on failure alike. Progress goes to stdout as ``PROGRESS <fraction> <message>``
lines, logs and tracebacks to stderr; anything else a library prints is diverted to stderr so
stdout carries only the protocol. Exit status: 0 ok, 1 bad request or input
(:class:`~uvps.errors.UVPSInputError`), 2 anything else. See ``docs/bridge.md``.
"""
from __future__ import annotations

import contextlib
import json
import logging
import math
import os
import signal
import sys
import threading
import time
import traceback
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

import numpy as np

from . import __version__
from .errors import UVPSComputeError, UVPSInputError, in_chain
from .files.outputs import CommandResult, OutputSpec, check_output_dir, write_json_atomic

log = logging.getLogger(__name__)

SCHEMA_VERSION = 1
RESPONSE_NAME = "response.json"

_REQUEST_KEYS = frozenset({"schema_version", "command", "inputs", "params", "output_dir"})


class Cancelled(Exception):
    """The bridge process was asked to stop (SIGTERM, e.g. Cancel on the Fiji side)."""


@dataclass
class BridgeRequest:
    """A validated request: absolute paths, known command."""

    command: str
    inputs: dict
    params: dict
    output_dir: Path
    warnings: list = field(default_factory=list)


def _one_line(exc: BaseException) -> str:
    text = str(exc).strip()
    line = text.splitlines()[0].strip() if text else ""
    return line or type(exc).__name__


def _resolve(value: Any, base: Path, keywords=()) -> Any:
    """Resolve a path string (or a list of them) against ``base``; other values and the
    parameter's keywords (e.g. ``regions="auto"``) unchanged."""
    if isinstance(value, str):
        if value in keywords or not value:
            return value
        p = Path(os.path.expanduser(value))
        return str(p if p.is_absolute() else (base / p))
    if isinstance(value, list):
        return [_resolve(v, base, keywords) for v in value]
    return value


def load_request(request_path, *, commands: dict) -> BridgeRequest:
    """Read and validate ``request.json``.

    Parameters
    ----------
    request_path : path
        The request file.
    commands : dict
        The command registry, name -> spec (``uvps.commands.COMMANDS``; the CLI passes it).

    Returns
    -------
    BridgeRequest
        Relative paths (``output_dir``, every string in ``inputs``, and the parameters the command
        declares as files) resolved against the request's folder. Types and values are checked by
        the command's declaration when it runs (:func:`uvps.spec.coerce`).

    Raises
    ------
    UVPSInputError
        Missing file, bad JSON, wrong schema version, unknown command, wrong field types, an
        output folder that is a file or whose parent does not exist.
    """
    path = Path(request_path)
    if not path.is_file():
        raise UVPSInputError(f"request file {path} does not exist")
    try:
        raw = json.loads(path.read_text(encoding="utf-8"))
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise UVPSInputError(f"request file {path} is not valid JSON ({_one_line(exc)})")
    if not isinstance(raw, dict):
        raise UVPSInputError(f"request file {path}: expected a JSON object; got {type(raw).__name__}")
    version = raw.get("schema_version")
    if version != SCHEMA_VERSION or isinstance(version, bool):
        raise UVPSInputError(
            f"request file {path}: schema_version must be {SCHEMA_VERSION}; got {version!r}"
        )
    command = raw.get("command")
    if not isinstance(command, str) or command not in commands:
        raise UVPSInputError(
            f"request file {path}: unknown command {command!r}; expected one of "
            f"{', '.join(sorted(commands))}"
        )
    inputs = raw.get("inputs", {})
    params = raw.get("params", {})
    for name, value in (("inputs", inputs), ("params", params)):
        if not isinstance(value, dict):
            raise UVPSInputError(
                f"request file {path}: '{name}' must be a JSON object; got {type(value).__name__}"
            )
    out = raw.get("output_dir")
    if not isinstance(out, str) or not out.strip():
        raise UVPSInputError(f"request file {path}: 'output_dir' must be a folder path; got {out!r}")
    base = path.parent.absolute()
    warnings = [f"request key '{k}' ignored (unknown)" for k in sorted(set(raw) - _REQUEST_KEYS)]
    inputs = {k: _resolve(v, base) for k, v in inputs.items()}
    files = {p.name: p.choices for p in getattr(commands[command], "params", ()) if p.type in ("path", "paths")}
    params = {k: (_resolve(v, base, files[k]) if k in files else v) for k, v in params.items()}
    output_dir = check_output_dir(Path(_resolve(out, base)))
    return BridgeRequest(command, inputs, params, output_dir, warnings)


def _jsonable(obj: Any) -> Any:
    """A JSON-safe copy: numpy scalars/arrays to Python, NaN/inf to None, paths to str."""
    if isinstance(obj, dict):
        return {str(k): _jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_jsonable(v) for v in obj]
    if isinstance(obj, OutputSpec):
        return _jsonable(obj.to_dict())
    if isinstance(obj, (str, bool)) or obj is None:
        return obj
    if isinstance(obj, int):
        return obj
    if isinstance(obj, float):
        return obj if math.isfinite(obj) else None
    if isinstance(obj, Path):
        return str(obj)
    if isinstance(obj, np.ndarray):
        return _jsonable(obj.tolist())
    if isinstance(obj, np.generic):
        return _jsonable(obj.item())
    return str(obj)


#: Set by SIGTERM while a command runs (:func:`_sigterm_cancels`); the next progress report raises
#: :class:`Cancelled` there.
_CANCEL = threading.Event()
#: Seconds after a first SIGTERM before the command is interrupted wherever it is.
CANCEL_GRACE_S = 2.0


def _progress_printer(stream) -> Callable[[float, str], None]:
    def progress(fraction: float, message: str) -> None:
        if _CANCEL.is_set():
            raise Cancelled("cancelled: the bridge received SIGTERM")
        fraction = min(max(float(fraction), 0.0), 1.0) if math.isfinite(fraction) else 0.0
        text = " ".join(str(message).split())
        stream.write(f"PROGRESS {fraction:.4f} {text}\n")
        stream.flush()

    return progress


def _configure_logging() -> None:
    """Log to stderr (INFO, or $UVPS_LOG_LEVEL) unless the host already configured logging."""
    level = os.environ.get("UVPS_LOG_LEVEL", "INFO").upper()
    root = logging.getLogger()
    if not root.handlers:
        handler = logging.StreamHandler(sys.stderr)
        handler.setFormatter(logging.Formatter("%(asctime)s %(levelname)s %(name)s: %(message)s"))
        root.addHandler(handler)
        root.setLevel(getattr(logging, level, logging.INFO))
    logging.captureWarnings(True)
    # library warnings (numpy's RuntimeWarnings) only with UVPS_LOG_LEVEL=DEBUG, not in Fiji's Log
    logging.getLogger("py.warnings").setLevel(logging.DEBUG if level == "DEBUG" else logging.CRITICAL)


def _outputs_of(result: Any, command: str) -> tuple:
    if not isinstance(result, CommandResult):
        raise UVPSComputeError(
            f"command {command} returned {type(result).__name__}; expected a CommandResult"
        )
    outputs = []
    for spec in result.outputs:
        d = spec.to_dict() if isinstance(spec, OutputSpec) else dict(spec)
        d["path"] = str(Path(d["path"]).absolute())
        outputs.append(d)
    return outputs, result.diagnostics, [str(w) for w in result.warnings]


@contextlib.contextmanager
def _sigterm_cancels():
    """Turn SIGTERM into :class:`Cancelled` while a command runs (main thread only).

    So a Cancel on the Fiji side (which terminates the process) unwinds normally: the command's
    temporary output folder is removed, the run folder stays as it was, and the response says
    ``Cancelled``. The first SIGTERM sets :data:`_CANCEL`, and the command stops at its next progress
    report, between two steps; only when none comes within :data:`CANCEL_GRACE_S` does a second
    SIGTERM raise :class:`Cancelled` wherever the command is. (An exception raised by a signal handler
    while a compiled (numba) function is being called can crash the interpreter: seen as a
    segmentation fault in ``offset.block_stats``; the Fiji side kills the process 5 s after its
    SIGTERM anyway.)
    """
    if threading.current_thread() is not threading.main_thread():
        yield
        return

    timers = []

    def handler(signum, frame):
        if _CANCEL.is_set():
            raise Cancelled("cancelled: the bridge received SIGTERM")
        _CANCEL.set()
        timers.append(threading.Timer(CANCEL_GRACE_S, os.kill, (os.getpid(), signal.SIGTERM)))
        timers[-1].daemon = True
        timers[-1].start()

    _CANCEL.clear()
    old = signal.signal(signal.SIGTERM, handler)
    try:
        yield      # a command that ends before its next progress report has its whole result: it stands
    finally:
        for t in timers:
            t.cancel()
        signal.signal(signal.SIGTERM, old)
        _CANCEL.clear()


def run_bridge(request_path, commands: dict) -> int:
    """Run one bridge request and write ``response.json`` beside it.

    Parameters
    ----------
    request_path : path
        ``request.json`` (see the module docstring and ``docs/bridge.md``).
    commands : dict
        The command registry, name -> spec (``uvps.commands.COMMANDS``; the CLI passes it, so that
        the bridge sits beside the commands, not above them).

    Returns
    -------
    int
        Exit status: 0 ok, 1 bad request or :class:`~uvps.errors.UVPSInputError`, 2 any other
        exception (:class:`~uvps.errors.UVPSComputeError`, :class:`Cancelled` on SIGTERM, or
        unexpected). The error message in the response is one line; the full traceback of an
        unexpected error goes to stderr only.
    """
    t0 = time.monotonic()
    _configure_logging()
    request_path = Path(request_path).absolute()
    response = {
        "schema_version": SCHEMA_VERSION, "status": "error", "command": None, "error": None,
        "outputs": [], "diagnostics": {}, "warnings": [], "version": __version__, "elapsed_s": 0.0,
    }
    progress = _progress_printer(sys.stdout)
    code = 2
    try:
        request = load_request(request_path, commands=commands)
        response["command"] = request.command
        response["warnings"] = list(request.warnings)
        for w in request.warnings:
            log.warning("%s", w)
        func = commands[request.command]
        log.info("bridge: %s -> %s", request.command, request.output_dir)
        # Only PROGRESS lines may reach stdout: divert anything printed by libraries.
        with contextlib.redirect_stdout(sys.stderr), _sigterm_cancels():
            result = func(request.inputs, request.params, request.output_dir, progress=progress)
        outputs, diagnostics, warnings = _outputs_of(result, request.command)
        response.update(status="ok", outputs=outputs, diagnostics=diagnostics, text=result.text)
        response["warnings"] += warnings
        code = 0
    except UVPSInputError as exc:
        code = 1
        response["error"] = {"type": type(exc).__name__, "message": _one_line(exc)}
        response["warnings"] += list(getattr(exc, "details", ()))
        log.error("%s: %s", type(exc).__name__, _one_line(exc))
    except Exception as exc:  # noqa: BLE001 - the bridge must answer whatever happened
        code = 2
        exc = _cancellation_in(exc) or exc
        response["error"] = {"type": type(exc).__name__, "message": _one_line(exc)}
        response["warnings"] += list(getattr(exc, "details", ()))
        if isinstance(exc, Cancelled):
            log.error("%s", _one_line(exc))
        else:
            traceback.print_exc(file=sys.stderr)
    response["elapsed_s"] = round(time.monotonic() - t0, 3)
    _write_response(request_path.parent / RESPONSE_NAME, response)
    return code


def _cancellation_in(exc: BaseException):
    """The :class:`Cancelled` that ``exc`` wraps, if any: SIGTERM's handler raises it wherever the
    command is, and when that is inside a compiled (numba) function the interpreter reports a
    ``SystemError`` ("returned a result with an exception set") with the Cancelled down its chain."""
    return in_chain(exc, Cancelled)


def _write_response(path: Path, response: dict) -> None:
    try:
        write_json_atomic(path, _jsonable(response))
    except OSError as exc:
        # No folder to answer in (e.g. the request path's folder does not exist): stderr only.
        print(f"uvps bridge: cannot write {path}: {_one_line(exc)}", file=sys.stderr)


def main(argv=None) -> int:
    """``python -m uvps.bridge REQUEST.json``: the same as ``uvps bridge REQUEST.json``."""
    from .cli import main as cli_main      # the CLI holds the registry; the bridge is called by it

    argv = sys.argv[1:] if argv is None else list(argv)
    if len(argv) != 1 or argv[0] in ("-h", "--help"):
        print("usage: uvps bridge REQUEST.json", file=sys.stderr)
        return 0 if argv and argv[0] in ("-h", "--help") else 1
    return cli_main(["bridge", argv[0]])


if __name__ == "__main__":
    sys.exit(main())
