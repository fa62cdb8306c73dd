"""Pure logic of the Fiji side of the uvps file bridge (no ``ij`` imports).

This module runs both under Jython 2.7 (inside ImageJ/Fiji) and under CPython 3 (pytest), so it
uses only the common subset: no f-strings, no annotations, ASCII source, ``os``/``json``/``tempfile``.

The protocol is the one of ``docs/architecture.md`` ("The file bridge"): one fresh request folder
per call holding ``request.json``; the core is started as the argument list
``[python, "-m", "uvps", "bridge", request_path]`` (never through a shell); it prints
``PROGRESS <fraction> <message>`` lines on stdout and writes ``response.json`` beside the request.
A call succeeds only when the exit status is 0, the response says ``"ok"`` and every output file it
lists exists: a missing output is an error, never an empty result.
"""
from __future__ import division

import json
import os
import tempfile

try:  # Python 2 / Jython
    STRING_TYPES = (basestring,)  # noqa: F821
except NameError:  # Python 3
    STRING_TYPES = (str,)

SCHEMA_VERSION = 1

#: Bridge commands of docs/architecture.md ("Commands").
COMMANDS = ("run", "flatfield", "lights", "normals", "integrate", "relight", "detect", "wand",
            "regions", "stats", "report", "compare", "demo")

#: Environment variable naming the CPython that has uvps installed.
PYTHON_ENV = "UVPS_PYTHON"

#: Config file written by the installer beside the ``uvps_fiji`` package.
CONFIG_NAME = "uvps_fiji.cfg"

#: Extensions the core reads as a capture stack.
TIFF_EXTENSIONS = (".tif", ".tiff")


class BridgeError(Exception):
    """A bridge call failed: bad request, the core reported an error, or an output is missing.

    Attributes
    ----------
    message : str
        One line for the user (the core's own ``error.message`` when it sent one).
    error_type : str
        ``UVPSInputError``, ``UVPSComputeError``, ``BridgeError``, ``Cancelled``, ``Timeout``...
    exit_code : int or None
        The core's exit status, when it ran.
    log : str
        The core's stderr, for the Log window.
    """

    def __init__(self, message, error_type="BridgeError", exit_code=None, log=""):
        Exception.__init__(self, message)
        self.message = message
        self.error_type = error_type
        self.exit_code = exit_code
        self.log = log

    def __str__(self):
        return "%s: %s" % (self.error_type, self.message)


class Response(object):
    """A validated ``response.json``.

    Attributes
    ----------
    command : str
    outputs : list of dict
        Each with at least ``name``, ``path`` and ``kind``.
    diagnostics : dict
    elapsed_s : float or None
    raw : dict
        The whole response as read.
    """

    def __init__(self, raw):
        self.raw = raw
        self.command = raw.get("command")
        self.outputs = list(raw.get("outputs") or [])
        self.diagnostics = raw.get("diagnostics") or {}
        self.elapsed_s = raw.get("elapsed_s")
        self.version = raw.get("version")

    def output(self, name):
        """Return the output dict called ``name``; BridgeError if the core did not list it."""
        for out in self.outputs:
            if out.get("name") == name:
                return out
        raise BridgeError("the core did not produce the output '%s' (it listed: %s)"
                          % (name, ", ".join(o.get("name", "?") for o in self.outputs) or "nothing"))

    def path(self, name):
        """Return the path of output ``name`` (which exists: checked at validation)."""
        return self.output(name)["path"]

    def file(self, filename):
        """Return the path of the listed output whose file name is ``filename`` (e.g.
        ``albedo.tif``, the names of docs/architecture.md); BridgeError if not listed."""
        for out in self.outputs:
            if os.path.basename(out.get("path", "")) == filename:
                return out["path"]
        raise BridgeError("the core did not produce %s (it listed: %s)"
                          % (filename, ", ".join(os.path.basename(o.get("path", "?"))
                                                 for o in self.outputs) or "nothing"))

    def has_file(self, filename):
        for out in self.outputs:
            if os.path.basename(out.get("path", "")) == filename:
                return True
        return False

    def has(self, name):
        for out in self.outputs:
            if out.get("name") == name:
                return True
        return False


# ---------------------------------------------------------------------------------------------
# Requests
# ---------------------------------------------------------------------------------------------

def build_request(command, inputs=None, params=None, output_dir=None):
    """Build the request dict of one bridge call.

    Parameters
    ----------
    command : str
        One of :data:`COMMANDS`.
    inputs, params : dict or None
        As in the command table; ``None`` values in ``params`` are kept (they mean "default").
    output_dir : str
        The run folder, absolute.

    Returns
    -------
    dict
        ``{"schema_version": 1, "command", "inputs", "params", "output_dir"}``.
    """
    if command not in COMMANDS:
        raise BridgeError("unknown uvps command '%s'; expected one of %s"
                          % (command, ", ".join(COMMANDS)))
    if not isinstance(output_dir, STRING_TYPES) or not output_dir.strip():
        raise BridgeError("the run folder is empty; choose a folder for the outputs")
    if not os.path.isabs(output_dir):
        raise BridgeError("the run folder must be an absolute path; got '%s'" % output_dir)
    for name, value in (("inputs", inputs), ("params", params)):
        if value is not None and not isinstance(value, dict):
            raise BridgeError("%s must be a dict; got %s" % (name, type(value).__name__))
    return {
        "schema_version": SCHEMA_VERSION,
        "command": command,
        "inputs": dict(inputs or {}),
        "params": dict(params or {}),
        "output_dir": os.path.normpath(output_dir),
    }


def make_request_dir(base=None, prefix="uvps-request-"):
    """Create and return a fresh, empty request folder (in ``base`` or the system temp folder)."""
    return tempfile.mkdtemp(prefix=prefix, dir=base)


def write_request(request, request_dir):
    """Write ``request`` as ``request_dir/request.json`` and return that path."""
    path = os.path.join(request_dir, "request.json")
    tmp = path + ".part"
    fh = open(tmp, "w")
    try:
        fh.write(json.dumps(request, indent=2, sort_keys=True))
        fh.write("\n")
    finally:
        fh.close()
    os.rename(tmp, path)
    return path


def build_command(python, request_path):
    """Return the argument list that runs the core on ``request_path`` (no shell involved)."""
    if not python:
        raise BridgeError("no CPython configured; use UV Photometric Stereo > UVPS Settings")
    return [python, "-m", "uvps", "bridge", request_path]


def build_check_command(python):
    """Return the argument list that checks ``python`` can import uvps and prints its version."""
    return [python, "-c", "import uvps, sys; sys.stdout.write(uvps.__version__)"]


def format_command(args):
    """Return ``args`` as one line for the Log, quoting arguments with spaces (display only)."""
    out = []
    for arg in args:
        if not arg or any(ch in arg for ch in " \t\"'"):
            out.append('"%s"' % arg.replace('"', '\\"'))
        else:
            out.append(arg)
    return " ".join(out)


# ---------------------------------------------------------------------------------------------
# Progress and responses
# ---------------------------------------------------------------------------------------------

def parse_progress(line):
    """Parse one stdout line ``PROGRESS <fraction> <message>``.

    Returns
    -------
    (float, str) or None
        The fraction clipped to [0, 1] and the message; ``None`` for any other line.
    """
    if line is None:
        return None
    line = line.strip()
    if not line.startswith("PROGRESS"):
        return None
    parts = line.split(None, 2)
    if len(parts) < 2 or parts[0] != "PROGRESS":
        return None
    try:
        fraction = float(parts[1])
    except ValueError:
        return None
    if fraction != fraction:  # NaN
        return None
    fraction = min(max(fraction, 0.0), 1.0)
    message = parts[2] if len(parts) > 2 else ""
    return fraction, message


def response_path_for(request_path):
    """Return the path of ``response.json`` beside ``request_path``."""
    return os.path.join(os.path.dirname(request_path), "response.json")


def read_response(path):
    """Read and validate ``response.json`` (see :func:`validate_response`)."""
    if not os.path.isfile(path):
        raise BridgeError("the core wrote no response file %s" % path)
    fh = open(path, "r")
    try:
        text = fh.read()
    finally:
        fh.close()
    try:
        raw = json.loads(text)
    except ValueError as exc:
        raise BridgeError("the response file %s is not valid JSON (%s)" % (path, exc))
    return validate_response(raw)


def validate_response(raw, exit_code=0, command=None):
    """Validate a response dict and return a :class:`Response`; raise BridgeError otherwise.

    Parameters
    ----------
    raw : dict
        The parsed ``response.json``.
    exit_code : int
        The core's exit status; non-zero is an error even if the response said ``ok``.
    command : str, optional
        The command that was requested; the response must name the same one.

    Notes
    -----
    An ``error`` response raises BridgeError carrying the core's ``error.type`` and
    ``error.message`` unchanged. An ``ok`` response must list its outputs, each with a ``name``
    and a ``path`` that exists: a missing file is an error (never replaced by a blank result).
    """
    if not isinstance(raw, dict):
        raise BridgeError("the response is not a JSON object")
    if raw.get("schema_version") != SCHEMA_VERSION:
        raise BridgeError("the response has schema_version %r; this plugin reads %d"
                          % (raw.get("schema_version"), SCHEMA_VERSION))
    status = raw.get("status")
    if status == "error":
        err = raw.get("error") or {}
        if not isinstance(err, dict):
            err = {"message": str(err)}
        message = err.get("message") or "the core reported an error without a message"
        raise BridgeError(message, error_type=err.get("type") or "UVPSError",
                          exit_code=exit_code)
    if status != "ok":
        raise BridgeError("the response status is %r; expected 'ok' or 'error'" % (status,),
                          exit_code=exit_code)
    if exit_code not in (0, None):
        raise BridgeError("the core exited with status %s although its response says ok"
                          % exit_code, exit_code=exit_code)
    if command is not None and raw.get("command") != command:
        raise BridgeError("the response is for command %r; expected %r"
                          % (raw.get("command"), command))
    outputs = raw.get("outputs")
    if not isinstance(outputs, list):
        raise BridgeError("the response has no outputs list")
    for out in outputs:
        if not isinstance(out, dict) or not out.get("name") or not out.get("path"):
            raise BridgeError("the response lists an output without name or path: %r" % (out,))
        if not os.path.exists(out["path"]):
            raise BridgeError("the core listed the output '%s' but %s does not exist"
                              % (out["name"], out["path"]))
    return Response(raw)


def finish_call(exit_code, request_path, command=None, stderr=""):
    """Turn a finished core process into a Response or a BridgeError.

    Parameters
    ----------
    exit_code : int
        The core's exit status.
    request_path : str
        The request it ran; ``response.json`` is read beside it.
    command : str, optional
        The command requested (checked against the response).
    stderr : str
        The core's stderr, attached to the error for the Log.
    """
    path = response_path_for(request_path)
    if not os.path.isfile(path):
        last = last_line(stderr)
        raise BridgeError("the core exited with status %s and wrote no response%s"
                          % (exit_code, (" (" + last + ")") if last else ""),
                          exit_code=exit_code, log=stderr)
    try:
        raw = read_response(path).raw
        return validate_response(raw, exit_code=exit_code, command=command)
    except BridgeError as exc:
        exc.exit_code = exit_code
        exc.log = stderr
        raise


def require_outputs(response, names):
    """Check that ``response`` lists every output in ``names``; return their paths in order."""
    return [response.path(name) for name in names]


def last_line(text):
    """Return the last non-empty line of ``text`` (or "")."""
    lines = [ln.strip() for ln in (text or "").splitlines() if ln.strip()]
    return lines[-1] if lines else ""


# ---------------------------------------------------------------------------------------------
# Configuration
# ---------------------------------------------------------------------------------------------

def read_config(path):
    """Read ``uvps_fiji.cfg``: ``key = value`` lines, ``#`` comments; a lone path means python.

    Returns
    -------
    dict
        Keys lower-cased; ``{}`` when the file does not exist.
    """
    if not path or not os.path.isfile(path):
        return {}
    fh = open(path, "r")
    try:
        lines = fh.read().splitlines()
    finally:
        fh.close()
    config = {}
    for line in lines:
        line = line.strip()
        if not line or line.startswith("#") or line.startswith(";") or line.startswith("["):
            continue
        if "=" in line:
            key, value = line.split("=", 1)
            config[key.strip().lower()] = _unquote(value.strip())
        elif ":" in line and not os.path.isabs(line) and not _is_windows_path(line):
            key, value = line.split(":", 1)
            config[key.strip().lower()] = _unquote(value.strip())
        else:
            config.setdefault("python", _unquote(line))
    return config


def _is_windows_path(text):
    return len(text) > 2 and text[1] == ":" and text[2] in "\\/"


def _unquote(text):
    if len(text) >= 2 and text[0] == text[-1] and text[0] in "\"'":
        return text[1:-1]
    return text


def default_config_path():
    """Return the path of ``uvps_fiji.cfg`` beside this package."""
    return os.path.join(os.path.dirname(os.path.abspath(__file__)), CONFIG_NAME)


def find_python(setting=None, environ=None, config_path=None):
    """Choose the CPython that runs the core.

    Order: ``setting`` (saved by the Settings menu item), the ``UVPS_PYTHON`` environment
    variable, ``python`` in ``uvps_fiji.cfg`` beside the package, then ``"python3"``.

    Parameters
    ----------
    setting : str, optional
    environ : mapping, optional
        Defaults to ``os.environ``.
    config_path : str, optional
        Defaults to :func:`default_config_path`.

    Returns
    -------
    (str, str)
        The python command and where it came from (``settings``, ``environment``, ``config``,
        ``default``).
    """
    if setting and setting.strip():
        return setting.strip(), "settings"
    env = os.environ if environ is None else environ
    value = env.get(PYTHON_ENV)
    if value and value.strip():
        return value.strip(), "environment"
    config = read_config(config_path if config_path is not None else default_config_path())
    value = config.get("python")
    if value:
        return value, "config"
    return "python3", "default"


# ---------------------------------------------------------------------------------------------
# Values from dialogs and macro options
# ---------------------------------------------------------------------------------------------

def parse_macro_options(options):
    """Parse an ImageJ macro options string into a dict.

    ``degree=4 output=[/path with spaces] robust`` gives
    ``{"degree": "4", "output": "/path with spaces", "robust": True}`` (a bare key is a ticked
    checkbox, as in ImageJ).
    """
    result = {}
    text = options or ""
    i, n = 0, len(text)
    while i < n:
        while i < n and text[i].isspace():
            i += 1
        if i >= n:
            break
        start = i
        while i < n and not text[i].isspace() and text[i] != "=":
            i += 1
        key = text[start:i].lower()
        if i < n and text[i] == "=":
            i += 1
            if i < n and text[i] == "[":
                end = text.find("]", i + 1)
                if end < 0:
                    raise BridgeError("unclosed '[' in macro options for key '%s'" % key)
                value = text[i + 1:end]
                i = end + 1
            else:
                start = i
                while i < n and not text[i].isspace():
                    i += 1
                value = text[start:i]
            result[key] = value
        elif key:
            result[key] = True
    return result


def split_paths(text):
    """Split a file-list option into paths: ``;`` or new lines separate entries; blanks dropped."""
    if not text:
        return []
    out = []
    for chunk in text.replace("\r", "\n").replace(";", "\n").split("\n"):
        chunk = chunk.strip()
        if chunk:
            out.append(chunk)
    return out


def optional_path(text):
    """Return a stripped path, or ``None`` for an empty value / ``none``."""
    if text is None:
        return None
    text = text.strip()
    if not text or text.lower() in ("none", "null", "-"):
        return None
    return text


def images_input(text):
    """Turn the ``images`` option into the ``inputs["images"]`` list of absolute paths.

    One folder, one multi-page TIFF, or several files separated by ``;``. Paths must exist.
    """
    paths = split_paths(text)
    if not paths:
        raise BridgeError("no capture given: choose a folder, a multi-page TIFF or a list of images")
    result = []
    for path in paths:
        if not os.path.isabs(path):
            raise BridgeError("capture path must be absolute; got '%s'" % path)
        if not os.path.exists(path):
            raise BridgeError("capture path %s does not exist" % path)
        result.append(os.path.normpath(path))
    if len(result) > 1:
        for path in result:
            if os.path.isdir(path):
                raise BridgeError("give either one folder or a list of files; %s is a folder" % path)
    return result


def stack_source(saved_path, modified, n_slices, file_slices=None):
    """Decide whether an open stack can be passed by its file or must be written out.

    Parameters
    ----------
    saved_path : str or None
        The file the stack was opened from (``None`` if never saved).
    modified : bool
        Whether the image has unsaved changes.
    n_slices : int
        Images in the open stack.
    file_slices : int or None
        Images in the file (``None`` if unknown).

    Returns
    -------
    str or None
        The path to pass as ``inputs["images"]``, or ``None`` when the stack must be written to
        the request folder (unsaved, modified, not a TIFF, missing, or the file holds a
        different number of images than the window, as for a substack).
    """
    if not saved_path or modified:
        return None
    if not saved_path.lower().endswith(TIFF_EXTENSIONS):
        return None
    if not os.path.isfile(saved_path):
        return None
    if file_slices is not None and file_slices != n_slices:
        return None
    if n_slices < 2:
        return None
    return os.path.abspath(saved_path)


def stack_request_path(request_dir, title):
    """Return the file name the open stack is written to inside the request folder."""
    safe = "".join(ch if (ch.isalnum() or ch in "-_.") else "_" for ch in (title or "capture"))
    safe = safe.strip("._") or "capture"
    if safe.lower().endswith(TIFF_EXTENSIONS):
        safe = safe.rsplit(".", 1)[0]
    return os.path.join(request_dir, safe + ".tif")


def points_csv_text(points):
    """Return ``x_px,y_px`` CSV text for a list of (x, y) pixel points."""
    lines = ["x_px,y_px"]
    for x, y in points:
        lines.append("%r,%r" % (float(x), float(y)))
    return "\n".join(lines) + "\n"

