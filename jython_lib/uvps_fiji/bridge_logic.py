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

# the detection's rejection rules in a conservator's words, generated from the rules' declarations
# (uvps.core.detect.rules.RULES) by scripts/detection_docs.py
from uvps_fiji.rejection_words import REJECTION_WORDS  # noqa: F401

try:  # Python 2 / Jython
    STRING_TYPES = (basestring,)  # noqa: F821
except NameError:  # Python 3
    STRING_TYPES = (str,)

SCHEMA_VERSION = 1

#: The core's command table (``python -m uvps spec``), written by scripts/install_fiji.py.
SPEC_NAME = "commands.json"

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
    text : str
        The command's plain-text answer (e.g. ``info``), "" if it gave none.
    elapsed_s : float or None
    raw : dict
        The whole response as read.
    """

    def __init__(self, raw):
        self.raw = raw
        self.command = raw.get("command")
        self.outputs = list(raw.get("outputs") or [])
        self.diagnostics = raw.get("diagnostics") or {}
        self.text = raw.get("text") or ""
        self.warnings = [w for w in (raw.get("warnings") or []) if w]
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
        A command of the core's table (:func:`command_names`).
    inputs, params : dict or None
        As in the command table; ``None`` values in ``params`` are kept (they mean "default").
    output_dir : str
        The run folder, absolute.

    Returns
    -------
    dict
        ``{"schema_version": 1, "command", "inputs", "params", "output_dir"}``.
    """
    names = command_names()
    if command not in names:
        raise BridgeError("unknown uvps command '%s'; expected one of %s"
                          % (command, ", ".join(names)))
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


#: Prefix of every request folder (what :func:`remove_request_dir` agrees to delete).
REQUEST_PREFIX = "uvps-request-"

#: Environment variable that keeps the request folder of a failed call (for debugging).
KEEP_ENV = "UVPS_KEEP_FAILED_REQUESTS"


def make_request_dir(base=None, prefix=REQUEST_PREFIX):
    """Create and return a fresh, empty request folder (in ``base`` or the system temp folder)."""
    return tempfile.mkdtemp(prefix=prefix, dir=base)


def keep_failed_requests(environ=None, config_path=None):
    """Whether a failed call keeps its request folder: ``UVPS_KEEP_FAILED_REQUESTS=1`` or
    ``keep_failed_requests = true`` in ``uvps_fiji.cfg`` (default: no, every folder is deleted)."""
    env = os.environ if environ is None else environ
    value = env.get(KEEP_ENV)
    if value is None:
        config = read_config(config_path if config_path is not None else default_config_path())
        value = config.get("keep_failed_requests")
    return (value or "").strip().lower() in ("1", "true", "yes", "on")


def remove_request_dir(request_dir, failed=False, keep_failed=False):
    """Delete a request folder (with any stack copied into it) once its response was read.

    Returns
    -------
    bool
        True when the folder was kept: only a failed call with ``keep_failed`` set keeps it.
    """
    if not request_dir or not os.path.isdir(request_dir):
        return False
    if failed and keep_failed:
        return True
    if not os.path.basename(os.path.normpath(request_dir)).startswith(REQUEST_PREFIX):
        raise BridgeError("refusing to delete %s: not a uvps request folder" % request_dir)
    import shutil
    shutil.rmtree(request_dir, True)
    return False


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
# The core's command declarations (``uvps spec``): names, parameters, defaults, choices, help
# ---------------------------------------------------------------------------------------------

#: The command table once read (one per ImageJ session; :func:`use_spec` replaces it).
_TABLE = [None]

#: Fiji's words for some choice values; the request carries the core's value (e.g. ``fc``).
CHOICE_LABELS = {"integration": {"fc": "Frankot-Chellappa (FFT)", "dct": "DCT Poisson (Neumann)"},
                 "points_unit": {"auto": "Automatic", "px": "Pixels",
                                 "um": "Calibrated (um, as Analyze > Measure)"}}

#: How a unit of the declarations is shown beside a number field.
UNIT_LABELS = {"um": u"\u00b5m", "deg": "deg", "mm": "mm", "counts": "counts"}


def default_spec_path():
    """Return the path of ``commands.json`` beside this package (written by the installer)."""
    return os.path.join(os.path.dirname(os.path.abspath(__file__)), SPEC_NAME)


def build_spec_command(python):
    """Return the argument list that prints the core's command table as JSON."""
    return [python, "-m", "uvps", "spec"]


def parse_spec(text, source):
    """Parse and check the JSON of ``uvps spec``; ``source`` names it in error messages."""
    try:
        table = json.loads(text)
    except ValueError as exc:
        raise BridgeError("the command table from %s is not valid JSON (%s)" % (source, exc),
                          error_type="Configuration")
    if not isinstance(table, dict) or not isinstance(table.get("commands"), dict):
        raise BridgeError("the command table from %s has no commands" % source,
                          error_type="Configuration")
    if table.get("schema_version") != SCHEMA_VERSION:
        raise BridgeError("the command table from %s has schema_version %r; this plugin reads %d "
                          "(reinstall with scripts/install_fiji.py)"
                          % (source, table.get("schema_version"), SCHEMA_VERSION),
                          error_type="Configuration")
    return table


def _run_subprocess(args):
    """Run ``args`` (no shell) and return (exit_code, stdout, stderr) as text."""
    import subprocess
    proc = subprocess.Popen(args, stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    out, err = proc.communicate()
    if not isinstance(out, STRING_TYPES):
        out, err = out.decode("utf-8", "replace"), err.decode("utf-8", "replace")
    return proc.returncode, out, err


def load_spec(path=None, python=None, run=None, reload=False):
    """Return the core's command table (the JSON of ``uvps spec``), read once per session.

    Parameters
    ----------
    path : str, optional
        ``commands.json``; defaults to :func:`default_spec_path` (written by the installer).
    python : str, optional
        When the file is absent (running from the source tree), the table is asked once from
        ``python -m uvps spec``; defaults to :func:`find_python`'s choice.
    run : callable, optional
        ``run(args) -> (exit_code, stdout, stderr)``; defaults to :mod:`subprocess`.
    reload : bool
        Read again even if a table was read before.

    Raises
    ------
    BridgeError
        ``Configuration``: neither the file nor the core could give the table.
    """
    if _TABLE[0] is not None and not reload:
        return _TABLE[0]
    path = default_spec_path() if path is None else path
    if os.path.isfile(path):
        fh = open(path, "r")
        try:
            text = fh.read()
        finally:
            fh.close()
        table = parse_spec(text, path)
    else:
        if python is None:
            python = find_python()[0]
        args = build_spec_command(python)
        try:
            code, out, err = (run or _run_subprocess)(args)
        except (OSError, IOError) as exc:
            code, out, err = None, "", str(exc)
        if code != 0:
            raise BridgeError("no command table %s (install with scripts/install_fiji.py), and "
                              "'%s' failed: %s" % (path, format_command(args),
                                                   last_line(err) or "exit status %s" % code),
                              error_type="Configuration")
        table = parse_spec(out, format_command(args))
    _TABLE[0] = table
    return table


def use_spec(table):
    """Use ``table`` (a parsed ``uvps spec``) as the command table; ``None`` forgets it."""
    _TABLE[0] = table


def command_names(table=None):
    """Return the core's command names, sorted."""
    return sorted((table or load_spec())["commands"])


def command_spec(command, table=None):
    """Return the declaration of ``command``: ``{"help", "output", "params": [...]}``."""
    commands = (table or load_spec())["commands"]
    if command not in commands:
        raise BridgeError("unknown uvps command '%s'; expected one of %s"
                          % (command, ", ".join(sorted(commands))))
    return commands[command]


def param_spec(command, name, table=None):
    """Return the declaration of parameter ``name`` of ``command`` (a dict, see docs/commands.md)."""
    for param in command_spec(command, table)["params"]:
        if param["name"] == name:
            return param
    raise BridgeError("the uvps command '%s' has no parameter '%s'" % (command, name))


def param_default(command, name, table=None):
    """Return the declared default of ``command``'s parameter ``name`` (None: not set)."""
    return param_spec(command, name, table).get("default")


def macro_key(label):
    """Return ImageJ's macro key of a dialog label (first word, up to ':', lower-cased)."""
    return label.split(" ")[0].split(":")[0].lower()


def param_label(param):
    """The dialog label of a declared parameter: its label in the core's declaration (every label
    the dialogs use is declared there, e.g. detect's ``dynamic_k`` "Sensitivity ..."), else its name."""
    return param.get("label") or param["name"]


def param_key(param):
    """Return the macro key of a declared parameter: its dialog label's first word."""
    return macro_key(param_label(param))


def field_name(param):
    """The name a user sees for a declared parameter's dialog field: its label before any
    ``(...)`` or ``:`` (``Pixel size on the painting``)."""
    return param_label(param).split(" (")[0].split(":")[0].strip()


def not_set_words(param):
    """What a field left at 0 means, from its label's ``(0 = ...)`` (else "not set")."""
    label = param_label(param)
    if "(0 = " in label:
        return label.split("(0 = ", 1)[1].split(")")[0]
    return "not set"


#: Pixel sizes (um) the capture menu items accept: a photograph of a painting (the paper's is
#: about 30 um per pixel; a macro lens at 1:1 about 4 um). Outside, the value is almost surely
#: in another unit (0.1 typed as mm, a dpi, an inch), refused before the core runs.
PIXEL_SIZE_RANGE_UM = (1.0, 1000.0)


def check_pixel_size(value, where):
    """A pixel size (um) from a dialog field or an image's calibration, checked before the core
    runs: ``None`` (0 or empty: not given) or a plausible size; BridgeError naming ``where``
    (``the field "Pixel size on the painting"``) otherwise.
    """
    if value is None or value == "":
        return None
    try:
        size = float(value)
    except (TypeError, ValueError):
        raise BridgeError("%s holds '%s', not a number of micrometres" % (where, value))
    if size != size or size == 0:
        return None
    low, high = PIXEL_SIZE_RANGE_UM
    if size < 0:
        raise BridgeError("%s holds %g um; a pixel size is positive (0 = from the image file)"
                          % (where, size))
    if size < low or size > high:
        hint = (" (0.1 mm = 100 um)" if size < low else
                " (a size in nm or a dpi? 300 dpi = 84.7 um)")
        raise BridgeError("%s holds %g um, not a pixel size on a painting (%g-%g um); give it in "
                          "micrometres%s" % (where, size, low, high, hint))
    return size


def _format_default(value):
    if value is None:
        return ""
    if isinstance(value, (list, tuple)):
        return ",".join(_format_default(v) for v in value)
    if isinstance(value, float):
        return "%g" % value
    return "%s" % value


def dialog_field(param, label=None, default=None, decimals=None):
    """Describe the dialog field of a declared parameter (pure: ``dialogs.add_param`` shows it).

    Parameters
    ----------
    param : dict
        A parameter of the command table.
    label : str, optional
        Overrides the declared label (its macro key must stay the same).
    default : optional
        Only for a parameter the core declares without default (e.g. the wand's tolerance).
    decimals : int, optional
        Digits shown by a number field (int: 0, float: 2 unless given).

    Returns
    -------
    dict
        ``key``, ``kind`` (checkbox, choice, number, string, file, directory), ``label``, ``default``,
        ``items`` (choice), ``decimals``, ``units`` (number) and ``help``.
    """
    label = label or param_label(param)
    declared = param.get("default")
    if default is not None and declared is not None and default != declared:
        raise BridgeError("the dialog default %r of '%s' differs from the core's %r"
                          % (default, param["name"], declared))
    value = declared if declared is not None else default
    field = {"key": macro_key(label), "label": label, "help": param.get("help", ""),
             "name": param["name"]}
    kind = param["type"]
    if kind == "bool":
        field.update(kind="checkbox", default=bool(value))
    elif kind == "choice":
        words = CHOICE_LABELS.get(param["name"], {})
        items = [words.get(c, "%s" % c) for c in param["choices"]]
        field.update(kind="choice", items=items,
                     default=words.get(value, "%s" % value) if value is not None else items[0])
    elif kind in ("int", "float"):
        if decimals is None:
            decimals = 0 if kind == "int" else 2
        field.update(kind="number", default=value if value is not None else 0,
                     decimals=decimals, units=UNIT_LABELS.get(param.get("unit", ""),
                                                             param.get("unit") or None))
    elif kind == "path":
        # a path whose label names a folder gets a folder chooser
        field.update(kind="directory" if "folder" in label.lower().split("(")[0] else "file",
                     default=_format_default(value))
    elif kind == "paths":
        # a folder of images (the usual capture) is browsed for; a multi-page TIFF or files
        # separated by ; are typed (or dropped) into the field
        field.update(kind="directory", default=_format_default(value))
    else:  # str, paths, numbers, shape: typed as text, checked by the core
        field.update(kind="string", default=_format_default(value))
    return field


def value_of(param, value):
    """Turn a dialog value into the request value of a declared parameter.

    A number field of a parameter declared without default means "not set" at 0 (or less); an
    empty text or file field is "not set"; a path may be one of the declared keywords (``auto``,
    also written ``automatic``) or an absolute path; a choice shown in Fiji's words becomes the
    core's value.
    """
    kind = param["type"]
    if kind == "bool":
        return bool(value)
    if kind == "choice":
        words = CHOICE_LABELS.get(param["name"], {})
        for choice in param["choices"]:
            if value == words.get(choice) or "%s" % value == "%s" % choice:
                return choice
        raise BridgeError("%s must be one of %s; got '%s'" % (
            param["name"], ", ".join(words.get(c, "%s" % c) for c in param["choices"]), value))
    if kind in ("int", "float"):
        if isinstance(value, STRING_TYPES):
            value = value.strip()
            if not value:
                return None
            try:
                value = float(value)
            except ValueError:
                raise BridgeError("%s must be a number; got '%s'" % (param["name"], value))
        if value is None or value != value:
            return None
        if param.get("default") is None and value <= 0:
            if value < 0 and param.get("minimum") is not None and param["minimum"] >= 0:
                # 0 means "not set"; a negative value is a typing mistake, never dropped silently
                raise BridgeError('the field "%s" holds %g; it must be positive (0 = %s)' % (
                    field_name(param), value, not_set_words(param)))
            return None
        return int(round(value)) if kind == "int" else float(value)
    if kind == "path":
        text = optional_path(value if isinstance(value, STRING_TYPES) else None)
        if text is None:
            return None
        for choice in param.get("choices") or ():
            if text.lower() == choice or (choice == "auto" and text.lower() == "automatic"):
                return choice
        if not os.path.isabs(text):
            raise BridgeError("%s must be an absolute path%s; got '%s'" % (
                param["name"], "".join(" or " + c for c in param.get("choices") or ()), text))
        return os.path.normpath(text)
    if kind == "paths":
        return split_paths(value) or None
    text = ("%s" % value).strip() if value is not None else ""
    return text or None


def request_from_values(command, values, table=None, skip=()):
    """Return ``(inputs, params)`` of ``command`` from dialog values keyed by macro key.

    Every declared parameter whose key (:func:`param_key`) is in ``values`` is converted by
    :func:`value_of`; parameters the dialog did not show are left out (the core's defaults apply).
    ``skip`` names parameters the caller fills itself (e.g. ``images`` from the current stack).
    """
    inputs, params = {}, {}
    for param in command_spec(command, table)["params"]:
        key = param_key(param)
        if param["name"] in skip or key not in values:
            continue
        target = inputs if param.get("where") == "inputs" else params
        target[param["name"]] = value_of(param, values[key])
    return inputs, params


def response_text(response):
    """The plain-text answer of a response: its ``text``, else its diagnostics as lines."""
    if response.text:
        return response.text
    lines = []
    for key in sorted(response.diagnostics):
        value = response.diagnostics[key]
        if not isinstance(value, (dict, list)) or value:
            lines.append("%s: %s" % (key, json.dumps(value, sort_keys=True)
                                     if isinstance(value, (dict, list)) else value))
    return "\n".join(lines)


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



# ---------------------------------------------------------------------------------------------
# What the core says, in the words of the menu user
# ---------------------------------------------------------------------------------------------

# ---------------------------------------------------------------------------------------------
# Names of a run's windows, and its relief scale
# ---------------------------------------------------------------------------------------------

def run_label(run_dir):
    """The name a run goes by in titles: its folder's name (``"region1"``)."""
    return os.path.basename(os.path.normpath(run_dir or "")) or "run"


def run_title(name, run_dir):
    """The title of a window, table or ROI set of one run: ``"albedo - region1"`` (the run
    folder's name), so that two runs' results never share a title."""
    return "%s - %s" % (name, run_label(run_dir))


#: The two sources of protrusion outlines: the ROI names' first word -> (the run folder's table
#: of them, the title of its table window). Wand Count's manual outlines and Detect Protrusions'
#: automatic ones are kept apart: each replaces only its own kind of the same run.
OUTLINE_KINDS = {"auto": ("protrusions.csv", "Protrusions"),
                 "manual": ("protrusions_manual.csv", "Manual protrusions")}


def outline_name(kind, number, run_dir):
    """The ROI name of protrusion ``number`` of one kind and run: ``"manual 12 - region1"``."""
    return "%s %d - %s" % (kind, number, run_label(run_dir))


def outline_kind(name, run_dir=None):
    """``"auto"`` or ``"manual"`` when ``name`` is a protrusion outline's ROI name (of the run
    ``run_dir``, when given), else None (a user's ROI, a sphere, another run's outline)."""
    import re
    match = re.match(r"^(auto|manual) \d+ - (.+)$", name or "")
    if match is None:
        return None
    if run_dir is not None and match.group(2) != run_label(run_dir):
        return None
    return match.group(1)


def added_by_uvps(name):
    """Whether a ROI name is one uvps gives (a protrusion outline, a calibration sphere's circle:
    ``display.show_spheres``), so that Colour Areas never reads it as a user's colour area."""
    import re
    return outline_kind(name) is not None or re.match(r"^sphere \d+ \(", name or "") is not None


def _run_log(run_dir):
    """The run folder's run.json as read by json, or None when it is missing or unreadable."""
    try:
        fh = open(os.path.join(run_dir, "run.json"), "r")
        try:
            return json.load(fh)
        finally:
            fh.close()
    except (IOError, OSError, ValueError):
        return None


def relief_scale(run_dir):
    """``"absolute"`` or ``"relative"``: the ``relief.scale`` of the run folder's run.json
    (``"relative"`` when the lamps' elevation, hence the height scale, is not pinned by known
    geometry). A missing file, key or unreadable run.json is ``"absolute"`` (older folders)."""
    log = _run_log(run_dir)
    relief = log.get("relief") if isinstance(log, dict) else None
    scale = relief.get("scale") if isinstance(relief, dict) else None
    return "relative" if scale == "relative" else "absolute"


def level_line(run_dir):
    """One Log line on what was removed from the run's ``depth.tif`` (run.json ``level``, written by
    the core's ``uvps.core.level``), or "" when the run records none (a folder from before levelling)."""
    log = _run_log(run_dir)
    level = log.get("level") if isinstance(log, dict) else None
    if not isinstance(level, dict) or level.get("slope_x_um_per_mm") is None:
        return ""
    plane = "x %+.3g, y %+.3g um/mm (x right, y up)" % (float(level["slope_x_um_per_mm"]),
                                                          float(level.get("slope_y_um_per_mm") or 0.0))
    method = level.get("method")
    if method == "plane":
        return ("height levelled: its best plane removed (%s); raw height = depth.tif + that plane "
                "(run.json level)" % plane)
    if method == "form":
        return ("height levelled: a Legendre form of degree %s removed (best plane %s); raw height = "
                "depth.tif + that form (run.json level)" % (level.get("degree"), plane))
    return "height not levelled (level none): it holds a plane of %s" % plane


#: How the height map is named and labelled: (window name, value unit, bar label).
HEIGHT_WORDS = {"absolute": ("height (um)", u"\u00b5m", u"height (\u00b5m)"),
                "relative": ("relative height", "relative", "relative height (no unit)")}


def menu_titles(table=None):
    """The menu item that runs each core command (the Log names it), from the core's declarations:
    each command's ``menu`` in ``uvps spec`` (a command without one is named by itself)."""
    table = load_spec() if table is None else table
    return dict((name, c.get("menu") or name) for name, c in table["commands"].items())


def menu_title(command, table=None):
    """The menu item of one core command (:func:`menu_titles`)."""
    return menu_titles(table).get(command, command)


def calibration_spheres(path):
    """The spheres of a calibration folder's ``calibration.json``: a list of
    ``(x, y, diameter, name)`` in ImageJ's pixel coordinates (a pixel's centre at +0.5), for the
    circle overlays that let the user check the detection."""
    with open(path) as fh:
        doc = json.load(fh)
    out = []
    for i, s in enumerate(doc.get("spheres") or []):
        col, row = s["centre_px"]
        r = float(s["radius_px"])
        out.append((col + 0.5 - r, row + 0.5 - r, 2.0 * r,
                    "sphere %d (%s, %s)" % (i + 1, s.get("kind", "?"), s.get("source", "?"))))
    return out


def first_image(paths):
    """The first image of a capture given as a folder, a ``;``-separated list or one file (None if
    none): the picture the detections are drawn on."""
    if not paths:
        return None
    items = [p.strip() for p in (paths if isinstance(paths, list) else paths.split(";")) if p.strip()]
    if not items:
        return None
    if os.path.isdir(items[0]):
        names = sorted(n for n in os.listdir(items[0])
                       if os.path.splitext(n)[1].lower() in (".tif", ".tiff", ".png", ".jpg", ".jpeg")
                       and not n.startswith("."))
        return os.path.join(items[0], names[0]) if names else None
    return items[0] if os.path.isfile(items[0]) else None


def cli_flag(name):
    """The command line's flag of a parameter: ``pixel_size_um`` -> ``--pixel-size-um``."""
    return "--" + name.replace("_", "-")


def field_names(command=None, table=None):
    """``{flag: dialog field}`` for every parameter shown in a dialog (one with a label).

    ``command``'s own parameters win over another command's of the same name; bool flags also
    get their ``--no-`` form.
    """
    commands = (table or load_spec())["commands"]
    order = sorted(commands)
    if command in commands:
        order.remove(command)
        order.append(command)
    names = {}
    for name in order:
        for param in commands[name]["params"]:
            if not param.get("label"):
                continue
            field = field_name(param)
            names[cli_flag(param["name"])] = field
            if param["type"] == "bool":
                names["--no-" + param["name"].replace("_", "-")] = field
    return names


def user_words(text, command=None, table=None):
    """Rewrite a core message for the menu user: a CLI flag becomes the dialog field.

    ``"give measured lamp positions (--lights)"`` -> ``give measured lamp positions (field
    "Lights file")``; ``"pass --pixel-size-um"`` -> ``pass the field "Pixel size"``. Flags
    without a dialog field stay as they are.
    """
    import re
    names = field_names(command, table)

    def swap(match):
        field = names.get(match.group(2))
        if field is None:
            return match.group(0)
        return '%sfield "%s"' % ("(" if match.group(1) else "the ", field)

    text = re.sub(r" \(params '[a-z0-9_]+'\)", "", text or "")
    return re.sub(r"(\()?(--[a-z][a-z0-9-]*)(?![a-z0-9-])", swap, text)


def affects_result(warning):
    """Whether a core warning is about the result (shown in a window when interactive), not
    about the request (an ignored key)."""
    return not warning.startswith("request key")


def warning_lines(response, command, table=None):
    """The Log lines of a response's warnings: ``uvps <menu item> warning: <text>``."""
    title = menu_title(command, table)
    return ["uvps %s warning: %s" % (title, user_words(w, command, table))
            for w in getattr(response, "warnings", [])]


def _count_text(counts, words):
    parts = []
    for name, count in sorted(counts.items(), key=lambda kv: (-kv[1], kv[0])):
        if count:
            parts.append("%d %s (%s)" % (count, words.get(name, name), name))
    return ", ".join(parts)


def detection_lines(diag):
    """Detection's candidate and rejection counts (``detect``'s diagnostics) as Log lines."""
    if not isinstance(diag, dict) or "n_protrusions" not in diag:
        return []
    kept = int(diag["n_protrusions"])
    rejected = dict((k, int(v)) for k, v in (diag.get("rejected") or {}).items())
    n_rejected = sum(rejected.values())
    line = "detection: %d candidates, %d protrusions kept, %d rejected" % (
        kept + n_rejected, kept, n_rejected)
    if n_rejected:
        line += ": " + _count_text(rejected, REJECTION_WORDS)
    lines = [line]
    if diag.get("noise_um") is not None:
        lines.append("detection: height noise %.3g um (the Sensitivity multiplies it)"
                     % diag["noise_um"])
    if kept == 0:
        lines.append("detection: no protrusion kept; a lower Sensitivity or a smaller Smallest "
                     "width (Detect Protrusions) finds more")
    return lines


def lights_lines(diag, lights_file=None, user_gave_lights=False):
    """Where the lamps came from (``lights`` diagnostics of a response) as Log lines."""
    if not isinstance(diag, dict) or not diag.get("source"):
        return []
    n = diag.get("n_lights")
    lamps = "%s lamps" % n if n is not None else "the lamps"
    if lights_file and not user_gave_lights:
        if os.path.isfile(os.path.join(os.path.dirname(lights_file), "calibration.json")):
            # Calibrate Lamps' folder, given as the Calibration field: not the run folder
            return ["lights: %s from the calibration folder's %s (Calibrate Lamps)"
                    % (lamps, lights_file)]
        return ["lights: %s from the run folder's %s (not estimated again; give a Lights file "
                "to use others)" % (lamps, lights_file)]
    if diag["source"] == "estimated":
        line = "lights: %s estimated from the images" % lamps
        if diag.get("refinement_converged") is False:
            line += "; the lamp refinement stopped before converging"
        rel = diag.get("height_uncertainty_relative")
        if rel is not None:
            line += "; heights uncertain by +-%.0f %%" % (100.0 * rel)
        return [line]
    return ["lights: %s as given (%s)" % (lamps, lights_file or diag["source"])]


def diagnostic_lines(command, diagnostics, user_gave_lights=False, table=None):
    """The Log lines of a response's diagnostics that a user acts on: where the lamps came
    from, detection's candidates and rejections, the wand's clicks."""
    d = diagnostics or {}
    lines = []
    if isinstance(d.get("lights"), dict):
        lines += lights_lines(d["lights"], d.get("lights_file"), user_gave_lights)
    elif command == "lights":
        lines += lights_lines(d, d.get("lights_file"), user_gave_lights)
    # `info`'s answer says the counts of the run itself (its text); its n_protrusions alone
    # must not read as "N candidates, N kept, 0 rejected"
    if command in ("run", "detect"):
        lines += detection_lines(d.get("detect") if command == "run" else d)
    if command == "wand" and "n_points" in d and not d.get("summary"):
        lines.append("wand: %d clicks, %d protrusions" % (d["n_points"], d.get("n_protrusions", 0)))
    title = menu_title(command, table)
    out = ["uvps %s %s" % (title, line) for line in lines]
    if command == "wand" and d.get("summary"):
        # "uvps Wand Count: 7 clicks: 5 outlined, 2 not (bare paint at (412, 300) px; ...)": only
        # the outlined are counted
        out.append("uvps %s: %s" % (title, d["summary"]))
    return out


# ---------------------------------------------------------------------------------------------
# Macro options and batch runs
# ---------------------------------------------------------------------------------------------

def unknown_macro_keys(options, keys):
    """The keys of macro ``options`` that the dialog does not have (sorted)."""
    known = set(keys)
    return sorted(k for k in parse_macro_options(options) if k and k not in known)


def unknown_keys_message(title, unknown, keys):
    return ("unknown macro key%s %s for %s; the valid keys are: %s"
            % ("s" if len(unknown) > 1 else "", ", ".join("'%s'" % k for k in unknown), title,
               ", ".join(sorted(keys))))


#: Environment variable: 1 = a failed menu item ends ImageJ with status 1, 0 = never.
EXIT_ENV = "UVPS_EXIT_ON_ERROR"

#: The JVM status of ``ImageJ -batch`` after a failed menu item.
FAILURE_EXIT_STATUS = 1


def exit_on_failure(java_command, environ=None):
    """Whether a failed menu item should end ImageJ with a non-zero status.

    Yes when ImageJ was started with ``-batch`` (``java_command``: the JVM's
    ``sun.java.command``), where ImageJ would otherwise exit 0 after a failed item; never in
    an interactive session or an embedding JVM (PyImageJ). ``UVPS_EXIT_ON_ERROR=1``/``0``
    decides instead.
    """
    env = os.environ if environ is None else environ
    value = (env.get(EXIT_ENV) or "").strip().lower()
    if value in ("1", "true", "yes", "on"):
        return True
    if value in ("0", "false", "no", "off"):
        return False
    return "-batch" in (java_command or "").split()


# ---------------------------------------------------------------------------------------------
# The current stack: lamps, channels
# ---------------------------------------------------------------------------------------------

#: Choices of the ``channels`` field of the capture dialogs.
CHANNELS_AUTO = "Automatic"
CHANNELS_GREY = "1 (grey)"
CHANNELS_RGB = "3 (R, G, B per lamp)"
CHANNEL_CHOICES = [CHANNELS_AUTO, CHANNELS_GREY, CHANNELS_RGB]


def lights_file_count(path):
    """The number of lamps a lights file lists (``.lp``, ``.json``, ``.csv``), or None."""
    if not path or not os.path.isfile(path):
        return None
    try:
        fh = open(path, "r")
        try:
            text = fh.read()
        finally:
            fh.close()
        if path.lower().endswith(".json"):
            data = json.loads(text)
            lights = data.get("lights") if isinstance(data, dict) else data
            return len(lights) if isinstance(lights, list) else None
        rows = [ln.strip() for ln in text.splitlines() if ln.strip() and not ln.startswith("#")]
        if path.lower().endswith(".lp"):
            return int(rows[0].split()[0])
        count = 0
        for row in rows:
            try:
                float(row.replace(";", ",").replace("\t", ",").split(",")[-1])
                count += 1
            except ValueError:
                pass
        return count or None
    except (ValueError, IndexError, IOError, OSError):
        return None


def looks_like_rgb_sequence(labels):
    """Whether slice labels come in R, G, B triples of one file each (``uv_00.tif:Red``, ...),
    as *File > Import > Image Sequence* gives for RGB files."""
    labels = list(labels or [])
    if len(labels) < 3 or len(labels) % 3:
        return False
    prefixes = []
    for i in range(0, len(labels), 3):
        triple = [lb or "" for lb in labels[i:i + 3]]
        if not all(":" in lb for lb in triple):
            return False
        heads = set(lb.rsplit(":", 1)[0] for lb in triple)
        if len(heads) != 1:
            return False
        prefixes.append(heads.pop())
    return len(set(prefixes)) == len(prefixes)


def stack_layout(title, n_images, n_channels, bit_depth, labels=None, lamps_hint=None,
                 hint_source="", choice=CHANNELS_AUTO):
    """How an open stack maps to lamps and colour channels.

    Parameters
    ----------
    title : str
    n_images : int
        All planes of the stack (``getStackSize``).
    n_channels : int
        Its channels (3 for a composite of R, G, B; 1 for a plain stack).
    bit_depth : int
        8, 16, 32, or 24 for RGB.
    labels : list of str, optional
        Slice labels (to recognise an RGB image sequence opened as grey slices).
    lamps_hint : int, optional
        Lamps a lights file lists (``hint_source`` names it).
    choice : str
        The dialog's *Channels per lamp* (:data:`CHANNEL_CHOICES`).

    Returns
    -------
    dict
        ``lamps``, ``channels``, ``regroup`` (True: grey slices to be written as a hyperstack of
        3 channels) and ``why``.

    Raises
    ------
    BridgeError
        A grey stack that looks like R, G, B slices of an RGB sequence, with nothing to say so.
    """
    if bit_depth == 24:
        return {"lamps": n_images, "channels": 3, "regroup": False, "why": "RGB image"}
    if n_channels > 1 and n_images == n_channels:
        # only channels (no slices or frames): one grey image per lamp, as ImageJ opens a
        # stack saved without hyperstack axes (3 alone would be one RGB lamp: no stereo)
        return {"lamps": n_images, "channels": 1, "regroup": False,
                "why": "%d channels, one image per lamp" % n_channels}
    if n_channels == 3:
        return {"lamps": n_images // 3, "channels": 3, "regroup": False,
                "why": "3 channels (composite or hyperstack)"}
    if n_channels != 1:
        raise BridgeError("the stack '%s' has %d channels; a capture has 1 (grey) or 3 (R, G, B) "
                          "per lamp" % (title, n_channels))
    triples = n_images % 3 == 0 and n_images >= 9
    if choice == CHANNELS_RGB:
        if n_images % 3:
            raise BridgeError("the stack '%s' has %d slices, not a multiple of 3: it cannot be "
                              "R, G, B per lamp" % (title, n_images))
        return {"lamps": n_images // 3, "channels": 3, "regroup": True,
                "why": "Channels per lamp = 3"}
    if choice == CHANNELS_GREY:
        return {"lamps": n_images, "channels": 1, "regroup": False, "why": "Channels per lamp = 1"}
    if triples and lamps_hint == n_images // 3:
        return {"lamps": n_images // 3, "channels": 3, "regroup": True,
                "why": "%s lists %d lamps" % (hint_source or "the lights file", lamps_hint)}
    if lamps_hint != n_images and triples and looks_like_rgb_sequence(labels):
        raise BridgeError(
            "the stack '%s' holds %d grey slices that are the R, G, B of %d RGB images (an RGB "
            "image sequence): make it a hyperstack first with Image > Hyperstacks > Stack to "
            "Hyperstack, channels=3 (order xyczt), or set Channels per lamp to 3 (to use them "
            "as %d grey images, set it to 1)" % (title, n_images, n_images // 3, n_images))
    return {"lamps": n_images, "channels": 1, "regroup": False, "why": "grey stack"}


# ---------------------------------------------------------------------------------------------
# Manual work in a run folder that a new run would replace (uvps.files.runfolder.MANUAL_FILES)
# ---------------------------------------------------------------------------------------------

#: What a person made in a run folder: the wand's count and a comparison (the core moves them aside,
#: with the run they were measured on, into earlier/<date>_<run id>/ when a new run replaces the folder).
MANUAL_WORK = ("protrusions_manual.csv", "comparison.csv")
#: The buttons of the question asked before a run replaces a folder holding manual work.
KEEP_AND_RUN, DO_NOT_RUN = "Keep it and run", "Do not run"


def manual_work_in(run_dir):
    """The manual files (:data:`MANUAL_WORK`) ``run_dir`` holds, each with a few words: the wand's
    count as "protrusions_manual.csv (5 counted of 7 clicks)"."""
    found = []
    for name in MANUAL_WORK:
        path = os.path.join(run_dir, name)
        if not os.path.isfile(path):
            continue
        if name == MANUAL_WORK[0]:
            counts = _click_counts(path)
            if counts is not None:
                name = "%s (%d counted of %d clicks)" % (name, counts[1], counts[0])
        found.append(name)
    return found


def _click_counts(path):
    """(clicks, counted) of a wand table, or None when unreadable."""
    import csv
    try:
        with open(path) as fh:
            rows = list(csv.DictReader(fh))
    except (IOError, OSError, csv.Error):
        return None
    counted = [r for r in rows if (r.get("counted") or "1").strip() not in ("0", "no", "false")]
    return len(rows), len(counted)


def manual_work_question(run_dir, found):
    """The question asked before a new run replaces ``run_dir`` that holds manual work ``found``."""
    return ("The run folder\n%s\nholds manual work: %s.\n\n"
            "It was measured on this folder's present run. A new run replaces the run; the manual work\n"
            "is kept, byte for byte, with the run it was measured on in earlier/<date>_<run id>/\n"
            "(Run Info and the report list it there).\n\n"
            "%s: run, keeping the manual work aside.  %s: change nothing."
            % (run_dir, ", ".join(found), KEEP_AND_RUN, DO_NOT_RUN))


# ---------------------------------------------------------------------------------------------
# Wand clicks (the core reads the points file: uvps.core.wand.read_seed_file)
# ---------------------------------------------------------------------------------------------

#: What the core's ``points_unit`` of the wand means, in words.
UNIT_WORDS = {"px": "pixels", "um": "um", "mm": "mm"}


def clicks_line(diag, where, automatic=True):
    """One Log line on the wand's clicks from its diagnostics: how many, from where, read in
    which unit (and divided by which pixel size)."""
    unit = diag.get("points_unit") or "px"
    line = "%d clicks from %s, read in %s" % (diag.get("n_points", 0), where,
                                              UNIT_WORDS.get(unit, unit))
    if unit != "px" and diag.get("pixel_size_um"):
        line += " (the albedo's pixel size is %g um)" % diag["pixel_size_um"]
    if unit != "px":
        if diag.get("points_unit_said"):
            line += " as the file's header says"
        elif automatic:
            line += ": its X, Y fit the image only in um"
        else:
            line += " as the field \"Units of the points file\" says"
    return line


#: Element Maps' composite by default: lead (the metal of the soaps) in red, the next two maps
#: of the stack in green and blue.
COMPOSITE_DEFAULT = ("Pb", "auto", "auto")


def element_of(name):
    """The element symbol of a map name: ``"Pb_L"`` -> ``"pb"``, ``"Cd L"`` -> ``"cd"``."""
    import re
    match = re.match(r"^([A-Za-z]{1,2})(?![a-z])", (name or "").strip())
    return match.group(1).lower() if match else (name or "").strip().lower()


def composite_channels(names, wanted=COMPOSITE_DEFAULT):
    """The three maps of an element composite (red, green, blue) among the stack's ``names``.

    Each of ``wanted`` is an element (``"Pb"`` takes the map ``"Pb_L"``), a map's whole name, or
    ``"auto"``/empty: the first maps not otherwise chosen, in stack order. Returns ``(maps,
    notes)``: up to three names, and a Log line for each wanted element that has no map."""
    chosen, notes = [None] * 3, []
    wanted = list(wanted or ()) + [""] * (3 - len(wanted or ()))
    for i, want in enumerate(wanted[:3]):
        want = (want or "").strip()
        if not want or want.lower() == "auto":
            continue
        hits = [n for n in names if n == want] or \
            [n for n in names if element_of(n) == element_of(want)]
        if hits and hits[0] not in chosen:
            chosen[i] = hits[0]
        elif not hits:
            notes.append("no %s map among %s; %s shows another element"
                         % (want, ", ".join(names), ("red", "green", "blue")[i]))
    rest = [n for n in names if n not in chosen]
    for i in range(3):
        if chosen[i] is None and rest:
            chosen[i] = rest.pop(0)
    return [c for c in chosen if c is not None], notes


#: The statuses of ``changes.csv`` in the order the Log and the legend give them.
CHANGE_STATUSES = ("new", "grown", "shrunk", "unchanged", "gone", "merged", "split")


def status_counts(rows):
    """``[(status, count), ...]`` of the change table's rows (dicts with a ``status``), in
    :data:`CHANGE_STATUSES` order, statuses that occur only."""
    counts = {}
    for row in rows:
        status = (row.get("status") or "").strip()
        counts[status] = counts.get(status, 0) + 1
    order = list(CHANGE_STATUSES) + sorted(s for s in counts if s not in CHANGE_STATUSES)
    return [(s, counts[s]) for s in order if counts.get(s)]
