"""CPython tests of the pure logic of the Fiji side (jython_lib/uvps_fiji/bridge_logic.py)."""
import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "jython_lib"))

from uvps_fiji import bridge_logic as bl  # noqa: E402


@pytest.fixture(scope="module")
def spec_table():
    """The core's declarations as the installer writes them (`uvps spec`)."""
    out = subprocess.run([sys.executable, "-m", "uvps", "spec"], check=True, timeout=120,
                         stdout=subprocess.PIPE, universal_newlines=True).stdout
    return bl.parse_spec(out, "uvps spec")


@pytest.fixture(autouse=True)
def _use_spec(spec_table):
    bl.use_spec(spec_table)
    yield
    bl.use_spec(None)


# --------------------------------------------------------------------------- requests

def test_build_request_has_the_documented_schema(tmp_path):
    req = bl.build_request("lights", {"images": [str(tmp_path / "a.tif")]},
                           {"degree": 4, "lights": None}, str(tmp_path / "run"))
    assert req == {
        "schema_version": 1,
        "command": "lights",
        "inputs": {"images": [str(tmp_path / "a.tif")]},
        "params": {"degree": 4, "lights": None},
        "output_dir": str(tmp_path / "run"),
    }


@pytest.mark.parametrize("command,out,msg", [
    ("estimate", "/abs/run", "unknown uvps command 'estimate'"),
    ("run", "relative/run", "must be an absolute path"),
    ("run", "  ", "run folder is empty"),
])
def test_build_request_rejects_bad_values(command, out, msg):
    with pytest.raises(bl.BridgeError, match=msg):
        bl.build_request(command, {}, {}, out)


def test_request_round_trips_through_a_fresh_folder(tmp_path):
    d1 = bl.make_request_dir(str(tmp_path))
    d2 = bl.make_request_dir(str(tmp_path))
    assert d1 != d2 and os.listdir(d1) == [] and os.listdir(d2) == []
    req = bl.build_request("relight", None, {"azimuth_deg": 315.0, "elevation_deg": 15.0},
                           str(tmp_path / "my run"))
    path = bl.write_request(req, d1)
    assert path == os.path.join(d1, "request.json")
    assert json.loads(Path(path).read_text()) == req
    assert sorted(os.listdir(d1)) == ["request.json"]


def test_command_is_an_argument_list_without_shell(tmp_path):
    req_path = str(tmp_path / "dir with spaces" / "request.json")
    args = bl.build_command("/opt/py 3/bin/python", req_path)
    assert args == ["/opt/py 3/bin/python", "-m", "uvps", "bridge", req_path]
    assert bl.format_command(args) == '"/opt/py 3/bin/python" -m uvps bridge "%s"' % req_path
    with pytest.raises(bl.BridgeError, match="no CPython configured"):
        bl.build_command("", req_path)


def test_check_command_runs_in_this_python():
    out = subprocess.run(bl.build_check_command(sys.executable), capture_output=True, text=True,
                         timeout=60)
    import uvps
    assert out.returncode == 0, out.stderr
    assert out.stdout == uvps.__version__


# --------------------------------------------------------------------------- progress

@pytest.mark.parametrize("line,expected", [
    ("PROGRESS 0.25 fitting drop-off 3/12\n", (0.25, "fitting drop-off 3/12")),
    ("PROGRESS 1 done", (1.0, "done")),
    ("PROGRESS 0.5", (0.5, "")),
    ("PROGRESS 1.7 over", (1.0, "over")),
    ("PROGRESS -0.2 under", (0.0, "under")),
    ("PROGRESS nan x", None),
    ("PROGRESS abc x", None),
    ("PROGRESSIVE 0.5 x", None),
    ("INFO reading", None),
    ("", None),
])
def test_parse_progress(line, expected):
    assert bl.parse_progress(line) == expected


# --------------------------------------------------------------------------- responses

def _ok_response(tmp_path, names=("normals",), create=True):
    outputs = []
    for name in names:
        path = tmp_path / (name + ".tif")
        if create:
            path.write_bytes(b"II*\x00")
        outputs.append({"name": name, "path": str(path), "kind": "image"})
    return {"schema_version": 1, "status": "ok", "command": "normals", "error": None,
            "outputs": outputs, "diagnostics": {"k": 8}, "version": "0.1.0", "elapsed_s": 1.5}


def test_ok_response_is_validated_and_gives_paths(tmp_path):
    resp = bl.validate_response(_ok_response(tmp_path, ("normals", "albedo")), command="normals")
    assert resp.path("albedo") == str(tmp_path / "albedo.tif")
    assert resp.has("normals") and not resp.has("depth")
    assert resp.diagnostics == {"k": 8} and resp.elapsed_s == 1.5
    assert bl.require_outputs(resp, ["normals", "albedo"]) == [
        str(tmp_path / "normals.tif"), str(tmp_path / "albedo.tif")]
    with pytest.raises(bl.BridgeError, match="did not produce the output 'depth'"):
        resp.path("depth")
    assert resp.file("albedo.tif") == str(tmp_path / "albedo.tif")
    assert resp.has_file("normals.tif") and not resp.has_file("depth.tif")
    with pytest.raises(bl.BridgeError, match="did not produce depth.tif"):
        resp.file("depth.tif")


def test_missing_output_file_is_an_error_not_a_blank_result(tmp_path):
    raw = _ok_response(tmp_path, ("protrusions",), create=False)
    with pytest.raises(bl.BridgeError, match="'protrusions' but .* does not exist"):
        bl.validate_response(raw)


def test_error_response_carries_the_core_message(tmp_path):
    raw = {"schema_version": 1, "status": "error", "command": "run",
           "error": {"type": "UVPSInputError",
                     "message": "lights.lp lists 7 lights; the capture has 8 images"},
           "outputs": []}
    with pytest.raises(bl.BridgeError) as info:
        bl.validate_response(raw, exit_code=1)
    assert info.value.error_type == "UVPSInputError"
    assert info.value.message == "lights.lp lists 7 lights; the capture has 8 images"
    assert info.value.exit_code == 1


@pytest.mark.parametrize("mutate,msg", [
    (lambda r: r.update(schema_version=2), "schema_version 2"),
    (lambda r: r.update(status="maybe"), "status is 'maybe'"),
    (lambda r: r.update(outputs=None), "no outputs list"),
    (lambda r: r.update(outputs=[{"name": "x"}]), "without name or path"),
    (lambda r: r.update(command="run"), "for command 'run'; expected 'normals'"),
])
def test_malformed_responses_are_rejected(tmp_path, mutate, msg):
    raw = _ok_response(tmp_path)
    mutate(raw)
    with pytest.raises(bl.BridgeError, match=msg):
        bl.validate_response(raw, command="normals")


def test_nonzero_exit_with_ok_status_is_an_error(tmp_path):
    with pytest.raises(bl.BridgeError, match="exited with status 2 although"):
        bl.validate_response(_ok_response(tmp_path), exit_code=2)


def test_finish_call_reads_the_response_beside_the_request(tmp_path):
    req = tmp_path / "request.json"
    req.write_text("{}")
    with pytest.raises(bl.BridgeError, match=r"status 1 and wrote no response \(Killed\)") as info:
        bl.finish_call(1, str(req), stderr="Traceback...\nKilled\n")
    assert info.value.log.startswith("Traceback")
    (tmp_path / "response.json").write_text(json.dumps(_ok_response(tmp_path)))
    assert bl.finish_call(0, str(req), command="normals").has("normals")
    (tmp_path / "response.json").write_text("{not json")
    with pytest.raises(bl.BridgeError, match="not valid JSON"):
        bl.finish_call(0, str(req))


# --------------------------------------------------------------------------- configuration

def test_python_lookup_order(tmp_path):
    cfg = tmp_path / "uvps_fiji.cfg"
    cfg.write_text("# written by the installer\npython = /opt/conda/bin/python\n")
    env = {"UVPS_PYTHON": "/env/python"}
    assert bl.find_python("/set/python", env, str(cfg)) == ("/set/python", "settings")
    assert bl.find_python("", env, str(cfg)) == ("/env/python", "environment")
    assert bl.find_python(None, {}, str(cfg)) == ("/opt/conda/bin/python", "config")
    assert bl.find_python(None, {}, str(tmp_path / "absent.cfg")) == ("python3", "default")


@pytest.mark.parametrize("text,expected", [
    ("python=/usr/bin/python3\n", "/usr/bin/python3"),
    ('[uvps]\npython = "/path with spaces/python"\n', "/path with spaces/python"),
    ("python: /x/python\n", "/x/python"),
    ("/only/a/path/python\n", "/only/a/path/python"),
    ("C:\\Python311\\python.exe\n", "C:\\Python311\\python.exe"),
])
def test_config_formats(tmp_path, text, expected):
    cfg = tmp_path / "uvps_fiji.cfg"
    cfg.write_text(text)
    assert bl.read_config(str(cfg))["python"] == expected


def test_default_config_path_is_beside_the_package():
    assert bl.default_config_path() == str(ROOT / "jython_lib" / "uvps_fiji" / "uvps_fiji.cfg")


# --------------------------------------------------------------------------- options and inputs

def test_parse_macro_options():
    opts = bl.parse_macro_options(
        "degree=4 output=[/path with spaces/run] robust capture=[Folder] pixel=15.5")
    assert opts == {"degree": "4", "output": "/path with spaces/run", "robust": True,
                    "capture": "Folder", "pixel": "15.5"}
    assert bl.parse_macro_options("") == {}
    with pytest.raises(bl.BridgeError, match="unclosed"):
        bl.parse_macro_options("output=[/a b")


def test_images_input(tmp_path):
    a, b = tmp_path / "a.tif", tmp_path / "b.tif"
    a.write_bytes(b"x")
    b.write_bytes(b"x")
    assert bl.images_input(str(tmp_path)) == [str(tmp_path)]
    assert bl.images_input("%s; %s" % (a, b)) == [str(a), str(b)]
    with pytest.raises(bl.BridgeError, match="does not exist"):
        bl.images_input(str(tmp_path / "c.tif"))
    with pytest.raises(bl.BridgeError, match="no capture given"):
        bl.images_input(" ; ")
    with pytest.raises(bl.BridgeError, match="must be absolute"):
        bl.images_input("a.tif")
    with pytest.raises(bl.BridgeError, match="is a folder"):
        bl.images_input("%s;%s" % (tmp_path, a))


def test_stack_source_decision(tmp_path):
    saved = tmp_path / "capture.tif"
    saved.write_bytes(b"x")
    assert bl.stack_source(str(saved), False, 8, 8) == str(saved)
    assert bl.stack_source(str(saved), False, 8, None) == str(saved)
    assert bl.stack_source(str(saved), True, 8, 8) is None            # unsaved changes
    assert bl.stack_source(str(saved), False, 4, 8) is None           # a substack
    assert bl.stack_source(None, False, 8, None) is None              # never saved
    assert bl.stack_source(str(tmp_path / "gone.tif"), False, 8, 8) is None
    png = tmp_path / "a.png"
    png.write_bytes(b"x")
    assert bl.stack_source(str(png), False, 8, 8) is None
    assert bl.stack_request_path("/r", "My capture.tif") == os.path.join("/r", "My_capture.tif")
    assert bl.stack_request_path("/r", "") == os.path.join("/r", "capture.tif")


def test_points_csv_text():
    assert bl.points_csv_text([(10, 20.5), (3.25, 4)]) == "x_px,y_px\n10.0,20.5\n3.25,4.0\n"


# --------------------------------------------------------------------------- Jython

@pytest.mark.skipif(shutil.which("jython") is None, reason="Debian's jython is not installed")
@pytest.mark.slow
def test_library_compiles_and_runs_under_jython(tmp_path):
    """The pure logic must also run under Jython 2.7 (ImageJ's interpreter)."""
    script = (
        "import sys\n"
        "sys.dont_write_bytecode = True\n"
        "sys.path.insert(0, %r)\n"
        "from uvps_fiji import bridge_logic as bl\n"
        "req = bl.build_request('lights', {'images': ['/a.tif']}, {'degree': 4}, '/out')\n"
        "d = bl.make_request_dir(%r)\n"
        "bl.write_request(req, d)\n"
        "print(bl.parse_progress('PROGRESS 0.5 half')[0])\n"
        "print(bl.parse_macro_options('output=[/a b] robust')['output'])\n"
        % (str(ROOT / "jython_lib"), str(tmp_path)))
    # No commands.json in the source tree: the table comes from `$UVPS_PYTHON -m uvps spec`.
    out = subprocess.run(["jython", "-c", script], capture_output=True, text=True, timeout=120,
                         env=dict(os.environ, UVPS_PYTHON=sys.executable))
    assert out.returncode == 0, out.stderr
    assert out.stdout.split() == ["0.5", "/a", "b"]
    for src in (ROOT / "jython_lib" / "uvps_fiji").glob("*.py"):
        src.read_bytes().decode("ascii")  # Jython sources must stay ASCII


@pytest.mark.skipif(shutil.which("jython") is None, reason="Debian's jython is not installed")
@pytest.mark.slow
def test_every_jython_source_compiles_under_jython_2_7():
    """Menu scripts and the ImageJ-side modules are Jython 2.7 code: compile (not run) them."""
    sources = sorted((ROOT / "jython_lib" / "uvps_fiji").glob("*.py"))
    sources += sorted((ROOT / "plugins" / "UV_Photometric_Stereo").glob("*.py"))
    assert len(sources) >= 12
    script = ("import sys\nbad = []\nfor p in sys.argv[1:]:\n"
              "    try:\n        compile(open(p).read(), p, 'exec')\n"
              "    except SyntaxError as e:\n        bad.append('%s: %s' % (p, e))\n"
              "print('\\n'.join(bad) or 'ok')\n")
    out = subprocess.run(["jython", "-c", script] + [str(p) for p in sources],
                         capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "ok"
    for src in sources:
        src.read_bytes().decode("ascii")


# --------------------------------------------------------------------------- with the real core

def _run_core(request, tmp_path):
    req_dir = bl.make_request_dir(str(tmp_path))
    req_path = bl.write_request(request, req_dir)
    proc = subprocess.run(bl.build_command(sys.executable, req_path), capture_output=True,
                          text=True, timeout=300)
    return proc, req_path


def test_an_error_of_the_real_core_reaches_the_fiji_side(tmp_path):
    """`uvps bridge` on a request the core rejects: BridgeError with the core's type and text."""
    request = bl.build_request("wand", {}, {"tolerance": 0.05}, str(tmp_path / "run"))
    proc, req_path = _run_core(request, tmp_path)
    assert proc.returncode == 1
    with pytest.raises(bl.BridgeError) as info:
        bl.finish_call(proc.returncode, req_path, command="wand", stderr=proc.stderr)
    assert info.value.error_type == "UVPSInputError"
    assert "points" in info.value.message and info.value.exit_code == 1


@pytest.mark.slow
def test_a_real_core_run_is_accepted_with_its_outputs(tmp_path):
    from uvps.testing.synthetic import make_capture, write_capture

    write_capture(make_capture(shape=(60, 80), n_lights=6, seed=2), tmp_path / "cap",
                  truth=False)
    request = bl.build_request("lights", {"images": [str(tmp_path / "cap")]}, {"degree": 2},
                               str(tmp_path / "run"))
    proc, req_path = _run_core(request, tmp_path)
    assert proc.returncode == 0, proc.stderr
    progress = [bl.parse_progress(line) for line in proc.stdout.splitlines()]
    assert progress and all(p is not None for p in progress)
    assert [f for f, _ in progress] == sorted(f for f, _ in progress)
    response = bl.finish_call(proc.returncode, req_path, command="lights", stderr=proc.stderr)
    lights = json.loads(Path(response.file("lights.json")).read_text())
    assert len(lights["lights"]) == 6


# --------------------------------------------------------------------------- the command table


def test_command_table_is_read_from_the_file_or_asked_once(tmp_path, spec_table):
    bl.use_spec(None)
    path = tmp_path / "commands.json"
    path.write_text(json.dumps(spec_table))
    assert bl.load_spec(str(path)) == spec_table
    assert bl.command_names() == sorted(spec_table["commands"])
    bl.use_spec(None)
    calls = []

    def run(args):
        calls.append(args)
        return 0, json.dumps(spec_table), ""

    assert bl.load_spec(str(tmp_path / "absent.json"), python="/py", run=run) == spec_table
    assert bl.load_spec(str(tmp_path / "absent.json"), python="/py", run=run) == spec_table
    assert calls == [["/py", "-m", "uvps", "spec"]]
    bl.use_spec(None)
    with pytest.raises(bl.BridgeError, match="no command table .*absent.json.*uvps spec' failed: "
                                             "No module named uvps"):
        bl.load_spec(str(tmp_path / "absent.json"), python="/py",
                     run=lambda args: (1, "", "Traceback\nNo module named uvps\n"))
    path.write_text(json.dumps({"schema_version": 2, "commands": {}}))
    with pytest.raises(bl.BridgeError, match="schema_version 2"):
        bl.load_spec(str(path))


def test_commands_come_from_the_table():
    assert "info" in bl.command_names() and "report" not in bl.command_names()
    assert bl.param_default("run", "degree") == 4
    with pytest.raises(bl.BridgeError, match="has no parameter 'colour'"):
        bl.param_spec("run", "colour")


def test_request_from_dialog_values(tmp_path):
    lights = str(tmp_path / "l.lp")
    inputs, params = bl.request_from_values("run", {
        "degree": 3.0, "robust": True, "integration": "DCT Poisson (Neumann)", "regions": "automatic",
        "detect": False, "lights": lights, "mask": "", "dark": "none", "pixel": 0.0, "run": "/r",
        "capture": "Current stack", "images": "/a.tif;/b.tif"}, skip=("pixel_size_um",))
    assert inputs == {"images": ["/a.tif", "/b.tif"]}
    assert params == {"degree": 3, "robust": True, "integration": "dct", "regions": "auto",
                      "detect": False, "lights": lights, "mask": None, "dark": None}
    _, params = bl.request_from_values("compare", {"match": 0.0, "first": "/a.csv"})
    assert params == {"match_radius_um": None}
    _, params = bl.request_from_values("relight", {"azimuth": 0.0, "elevation": 15.0})
    assert params == {"azimuth_deg": 0.0, "elevation_deg": 15.0}
    _, params = bl.request_from_values("stats", {"bins": "50, 100,200"})
    assert params == {"bins_um": "50, 100,200"}
    with pytest.raises(bl.BridgeError, match="regions must be an absolute path or auto"):
        bl.request_from_values("detect", {"regions": "labels.tif"})
    with pytest.raises(bl.BridgeError, match="integration must be one of Frankot"):
        bl.request_from_values("integrate", {"integration": "fft"})


def test_response_text_is_the_commands_answer_else_its_diagnostics():
    raw = {"schema_version": 1, "status": "ok", "command": "info", "outputs": [],
           "diagnostics": {"n_protrusions": 7, "files": ["run.json"], "lights": {}}}
    assert bl.response_text(bl.validate_response(raw)) == 'files: ["run.json"]\nn_protrusions: 7'
    raw["text"] = "made by:    uvps run"
    assert bl.response_text(bl.validate_response(raw)) == "made by:    uvps run"


def test_request_folders_are_deleted_unless_a_failed_one_is_kept(tmp_path):
    d = bl.make_request_dir(str(tmp_path))
    (Path(d) / "capture.tif").write_bytes(b"x" * 10)
    assert bl.remove_request_dir(d, failed=True, keep_failed=True) is True and os.path.isdir(d)
    assert bl.remove_request_dir(d, failed=False, keep_failed=True) is False
    assert not os.path.exists(d)
    other = tmp_path / "my data"
    other.mkdir()
    with pytest.raises(bl.BridgeError, match="not a uvps request folder"):
        bl.remove_request_dir(str(other))
    assert other.is_dir()
    cfg = tmp_path / "uvps_fiji.cfg"
    cfg.write_text("python = /p\nkeep_failed_requests = true\n")
    assert bl.keep_failed_requests({}, str(cfg)) is True
    assert bl.keep_failed_requests({bl.KEEP_ENV: "0"}, str(cfg)) is False
    assert bl.keep_failed_requests({}, str(tmp_path / "none.cfg")) is False


# --------------------------------------------------------------------------- the dialogs


class FakeGenericDialog(object):
    """Records the fields a menu script adds; its Cancel makes the script stop there."""

    made = []

    def __init__(self, title):
        self.title = title
        self.fields = []
        FakeGenericDialog.made.append(self)

    def addNumericField(self, label, value, decimals, *rest):
        self.fields.append(("number", label, value, None))

    def addStringField(self, label, value, columns=0):
        self.fields.append(("string", label, value, None))

    def addDirectoryField(self, label, value, columns=0):
        self.fields.append(("directory", label, value, None))

    def addFileField(self, label, value, columns=0):
        self.fields.append(("file", label, value, None))

    def addChoice(self, label, items, value):
        self.fields.append(("choice", label, value, list(items)))

    def addCheckbox(self, label, value):
        self.fields.append(("checkbox", label, value, None))

    def addMessage(self, text):
        pass

    def addHelp(self, text):
        self.help = text

    def showDialog(self):
        pass

    def wasCanceled(self):
        return True


def _fake_module(name, **attrs):
    import types
    from unittest import mock

    module = types.ModuleType(name)
    module.__getattr__ = lambda attr: mock.MagicMock(name="%s.%s" % (name, attr))
    module.__dict__.update(attrs)
    return module


def _install_fake_imagej(monkeypatch, ij, gui):
    """Put fake ImageJ and Java modules in ``sys.modules`` for this test: ``ij`` and ``ij.gui`` as
    given, a ``java.lang.Throwable``, and the other packages the Jython side imports as mocks."""
    fakes = {"ij": ij, "ij.gui": gui,
             "java.lang": _fake_module("java.lang", Throwable=type("Throwable", (Exception,), {}))}
    for name in ("ij.io", "ij.plugin", "ij.plugin.frame", "ij.measure", "ij.process", "ij.macro",
                 "java", "java.awt", "java.io", "java.util", "java.util.concurrent"):
        fakes[name] = _fake_module(name)
    for name, module in fakes.items():
        monkeypatch.setitem(sys.modules, name, module)


@pytest.fixture
def menu_scripts(monkeypatch):
    """Run every menu script in CPython with fake ImageJ/Java modules (a macro is running, so
    each field shows its built-in default); return {script: (COMMAND, [fields])}."""
    from unittest import mock

    ij = _fake_module("ij", IJ=mock.MagicMock(getDirectory=lambda key: None),
                      Macro=mock.MagicMock(getOptions=lambda: " "),
                      Prefs=mock.MagicMock())
    _install_fake_imagej(monkeypatch, ij, _fake_module("ij.gui", GenericDialog=FakeGenericDialog))
    for name in ("dialogs", "runner", "menus", "capture", "display"):
        monkeypatch.delitem(sys.modules, "uvps_fiji." + name, raising=False)
    from uvps_fiji import runner
    monkeypatch.setattr(runner, "command_table", bl.load_spec)
    scripts = {}
    for path in sorted((ROOT / "plugins" / "UV_Photometric_Stereo").glob("*.py")):
        FakeGenericDialog.made = []
        namespace = {"__name__": "__main__", "__file__": str(path)}
        exec(compile(path.read_text(), str(path), "exec"), namespace)
        assert len(FakeGenericDialog.made) == 1, path.name
        scripts[path.name] = (namespace.get("COMMAND"), FakeGenericDialog.made[0].fields)
    for name in ("dialogs", "runner", "menus", "capture", "display"):
        sys.modules.pop("uvps_fiji." + name, None)
    return scripts


#: Macro keys that recorded macros and tests/imagej use: they must keep working.
MACRO_KEYS = ("degree robust integration regions detect lights mask dark pixel capture images run "
              "tolerance connectivity points source label number bins first second match azimuth "
              "elevation python sensitivity smallest units channels").split()


def test_dialogs_show_the_cores_defaults_choices_and_labels(menu_scripts, spec_table):
    """Every dialog field of a declared parameter: the declared label, default and choices (in
    Fiji's words for the integration); a dialog that disagrees with `uvps spec` fails here."""
    keys = set()
    checked = 0
    for script, (command, fields) in menu_scripts.items():
        params = {}
        if command is not None:
            params = {bl.param_key(p): p for p in spec_table["commands"][command]["params"]}
        for kind, label, value, items in fields:
            key = bl.macro_key(label)
            keys.add(key)
            p = params.get(key)
            if p is None:
                continue
            checked += 1
            where = "%s: field %r (%s.%s)" % (script, label, command, p["name"])
            assert label == bl.param_label(p), where
            default = p.get("default")
            if p["type"] == "bool":
                assert kind == "checkbox" and value is default, where
            elif p["type"] == "choice":
                words = bl.CHOICE_LABELS.get(p["name"], {})
                assert kind == "choice", where
                assert [next((c for c in p["choices"] if words.get(c, c) == item), None)
                        for item in items] == p["choices"], where
                assert next(c for c in p["choices"] if words.get(c, c) == value) == default, where
            elif p["type"] in ("int", "float"):
                assert kind == "number", where
                if default is None and not p.get("required"):
                    assert value == 0, where   # 0 = not set: the core decides
                elif default is not None:
                    assert value == default, where
            else:
                assert kind in ("string", "file", "directory"), where
                expected = "" if default is None else ",".join("%g" % v for v in (
                    default if isinstance(default, list) else [default]))
                assert value == expected, where
    assert checked >= 30
    assert set(MACRO_KEYS) <= keys, sorted(set(MACRO_KEYS) - keys)
    assert menu_scripts["Run_Info.py"][0] == "info"
    assert set(c for c, _ in menu_scripts.values() if c) <= set(spec_table["commands"])


def test_a_dialog_default_that_disagrees_with_the_core_is_refused(spec_table):
    degree = bl.param_spec("run", "degree")
    assert bl.dialog_field(degree)["default"] == 4
    with pytest.raises(bl.BridgeError, match="dialog default 5 of 'degree' differs"):
        bl.dialog_field(degree, default=5)
    robust = bl.dialog_field(bl.param_spec("normals", "robust"))
    assert robust["key"] == "robust" and robust["kind"] == "checkbox"
    assert "darkest 25 % and brightest 10 %" in robust["help"]
    assert "saturated" not in robust["label"].lower()


# --------------------------------------------------------------------------- the user's words

def test_cli_flags_become_dialog_fields():
    text = ("give measured lamp positions (--lights), and a dark frame (--dark) if there is "
            "stray light; pass --pixel-size-um or --lights-x")
    assert bl.user_words(text, "run") == (
        'give measured lamp positions (field "Lights file"), and a dark frame (field "Dark '
        'frame") if there is stray light; pass the field "Pixel size on the painting" or --lights-x')


def test_warning_lines_name_the_menu_item_and_the_field():
    response = bl.Response({"warnings": ["heights may be off (--lights)",
                                         "request key 'x' ignored (unknown)"]})
    lines = bl.warning_lines(response, "normals")
    assert lines[0] == 'uvps Normals and Albedo warning: heights may be off (field "Lights file")'
    assert [bl.affects_result(w) for w in response.warnings] == [True, False]


def test_detection_counts_in_the_log():
    diag = {"n_protrusions": 6, "noise_um": 0.05,
            "rejected": {"weave": 4, "flat_bright": 9, "too_small": 7, "crack": 0}}
    lines = bl.diagnostic_lines("detect", diag)
    words = bl.REJECTION_WORDS   # the rules' declarations (uvps.core.detect.rules.RULES)
    assert lines[0] == ("uvps Detect Protrusions detection: 26 candidates, 6 protrusions kept, "
                        "20 rejected: 9 %s (flat_bright), 7 %s (too_small), 4 %s (weave)"
                        % (words["flat_bright"], words["too_small"], words["weave"]))
    assert "height noise 0.05 um" in lines[1]
    # run nests them under "detect"; none kept says how to find more
    lines = bl.diagnostic_lines("run", {"detect": {"n_protrusions": 0, "rejected": {}}})
    assert lines[0].endswith("0 candidates, 0 protrusions kept, 0 rejected")
    assert "lower Sensitivity" in lines[-1]


def test_run_info_diagnostics_give_no_detection_counts_of_their_own():
    """Run Info's diagnostics hold the table's row count only: no "104 candidates, 104 kept,
    0 rejected" where the run had 321 candidates (its text says the run's counts)."""
    info = {"n_protrusions": 104, "detection": {"candidates": 321, "kept": 104,
                                                "rejected": {"ridge": 217}}}
    assert bl.diagnostic_lines("info", info) == []


def test_lights_lines_say_where_the_lamps_came_from():
    reused = {"lights": {"source": "positions", "n_lights": 8}, "lights_file": "/r/lights.json"}
    assert bl.diagnostic_lines("normals", reused) == [
        "uvps Normals and Albedo lights: 8 lamps from the run folder's /r/lights.json (not "
        "estimated again; give a Lights file to use others)"]
    assert "as given" in bl.diagnostic_lines("normals", reused, user_gave_lights=True)[0]
    est = {"lights": {"source": "estimated", "n_lights": 12, "refinement_converged": False,
                      "height_uncertainty_relative": 0.25}}
    assert bl.diagnostic_lines("run", est) == [
        "uvps Run Whole Pipeline lights: 12 lamps estimated from the images; the lamp "
        "refinement stopped before converging; heights uncertain by +-25 %"]


def test_lamps_of_a_calibration_folder_are_not_called_the_run_folders(tmp_path):
    """The Calibration field's lamps: the Log names Calibrate Lamps' folder, not the run folder."""
    cal = tmp_path / "calibration"
    cal.mkdir()
    (cal / "calibration.json").write_text("{}")
    diag = {"lights": {"source": "positions", "n_lights": 8}, "lights_file": str(cal / "lights.json")}
    assert bl.diagnostic_lines("run", diag) == [
        "uvps Run Whole Pipeline lights: 8 lamps from the calibration folder's %s (Calibrate Lamps)"
        % (cal / "lights.json")]


@pytest.mark.parametrize("names,wanted,expected,n_notes", [
    # the default: lead in red whatever the stack's order, then the next maps
    (["Cd_L", "Cr_K", "Fe_K", "Pb_L"], bl.COMPOSITE_DEFAULT, ["Pb_L", "Cd_L", "Cr_K"], 0),
    (["Cd_L", "Cr_K", "Fe_K", "Pb_L"], ("Fe", "Pb", "auto"), ["Fe_K", "Pb_L", "Cd_L"], 0),
    (["Zn K", "Pb M", "Ca"], ("Pb", "zn", "Ca"), ["Pb M", "Zn K", "Ca"], 0),
    # no lead map: said in the Log, the other maps shown
    (["Cd_L", "Cr_K"], bl.COMPOSITE_DEFAULT, ["Cd_L", "Cr_K"], 1),
    # an element absent, a map's whole name, and "C" not taking "Cd_L" or "Cr_K"
    (["Cd_L", "Cr_K", "C"], ("Sn", "Cr_K", "C"), ["Cd_L", "Cr_K", "C"], 1),
])
def test_element_composite_channels(names, wanted, expected, n_notes):
    channels, notes = bl.composite_channels(names, wanted)
    assert channels == expected
    assert len(notes) == n_notes


def test_status_counts_follow_the_reports_order():
    rows = [{"status": s} for s in ("unchanged", "grown", "new", "unchanged", "gone", "odd")]
    assert bl.status_counts(rows) == [("new", 1), ("grown", 1), ("unchanged", 2), ("gone", 1),
                                      ("odd", 1)]


# --------------------------------------------------------------------------- macro keys, exit

def test_unknown_macro_keys_are_named_with_the_valid_ones():
    keys = ["run", "azimuth", "elevation"]
    assert bl.unknown_macro_keys("run=[/a b] azimut=45 elevation=15", keys) == ["azimut"]
    assert bl.unknown_macro_keys("run=[/a b=c] azimuth=4 ", keys) == []
    assert bl.unknown_keys_message("Relight", ["azimut"], keys) == (
        "unknown macro key 'azimut' for Relight; the valid keys are: azimuth, elevation, run")


@pytest.mark.parametrize("command,env,expected", [
    ("ij.ImageJ -ijpath /x -batch m.ijm", {}, True),
    ("ij.ImageJ -ijpath /x", {}, False),
    ("org.scijava.Main", {"UVPS_EXIT_ON_ERROR": "1"}, True),
    ("ij.ImageJ -batch m.ijm", {"UVPS_EXIT_ON_ERROR": "0"}, False),
    (None, {}, False),
])
def test_exit_on_failure_only_in_batch_runs(command, env, expected):
    assert bl.exit_on_failure(command, env) is expected


# --------------------------------------------------------------------------- the current stack

SEQ = ["uv_%02d.tif:%s" % (i, c) for i in range(8) for c in ("Red", "Green", "Blue")]


def test_an_rgb_sequence_of_grey_slices_is_refused_with_the_way_out():
    assert bl.looks_like_rgb_sequence(SEQ)
    assert not bl.looks_like_rgb_sequence(["uv_%02d.tif" % i for i in range(24)])
    with pytest.raises(bl.BridgeError, match=r"Stack to Hyperstack, channels=3"):
        bl.stack_layout("seq", 24, 1, 16, SEQ)


@pytest.mark.parametrize("args,kw,lamps,channels,regroup", [
    ((24, 1, 16, SEQ), {"lamps_hint": 8}, 8, 3, True),              # the lights file says so
    ((24, 1, 16, SEQ), {"choice": bl.CHANNELS_RGB}, 8, 3, True),    # the user says so
    ((24, 1, 16, SEQ), {"choice": bl.CHANNELS_GREY}, 24, 1, False),
    ((24, 1, 16, SEQ), {"lamps_hint": 24}, 24, 1, False),
    ((24, 3, 16, None), {}, 8, 3, False),                           # composite
    ((8, 8, 16, None), {}, 8, 1, False),                            # 8 channels, one per lamp
    ((8, 1, 24, None), {}, 8, 3, False),                            # RGB stack
    ((12, 1, 16, ["a%d" % i for i in range(12)]), {}, 12, 1, False),
])
def test_stack_layout(args, kw, lamps, channels, regroup):
    got = bl.stack_layout("s", *args, **kw)
    assert (got["lamps"], got["channels"], got["regroup"]) == (lamps, channels, regroup)


def test_lights_file_count(tmp_path):
    lp = tmp_path / "a.lp"
    lp.write_text("3\na.tif 0 0 1\nb.tif 0 1 0\nc.tif 1 0 0\n")
    js = tmp_path / "lights.json"
    js.write_text(json.dumps({"lights": [{}, {}]}))
    csv = tmp_path / "p.csv"
    csv.write_text("x_mm,y_mm,z_mm\n1,2,3\n4,5,6\n")
    assert [bl.lights_file_count(str(p)) for p in (lp, js, csv)] == [3, 2, 2]
    assert bl.lights_file_count(str(tmp_path / "none.lp")) is None


# --------------------------------------------------------------------------- wand points

def test_the_clicks_line_says_the_unit_the_core_read():
    diag = {"n_points": 3, "points_unit": "mm", "points_unit_said": True, "pixel_size_um": 15.0}
    assert bl.clicks_line(diag, "the file /a.csv") == (
        "3 clicks from the file /a.csv, read in mm (the albedo's pixel size is 15 um) "
        "as the file's header says")
    assert bl.clicks_line({"n_points": 2, "points_unit": "px"}, "the point selection") == (
        "2 clicks from the point selection, read in pixels")


def test_fiji_has_no_points_parser_of_its_own():
    """The core's wand.read_seed_file is the one parser (Fiji's read x_mm as um, 1000x off)."""
    assert not hasattr(bl, "read_points_text") and not hasattr(bl, "points_in_pixels")


def test_outline_names_say_their_source_and_run():
    """Manual and automatic outlines are told apart by name, and so are two runs' outlines
    (a run whose name ends like another's included); a user's ROI is no outline."""
    assert bl.outline_name("manual", 12, "/data/region1") == "manual 12 - region1"
    assert bl.outline_name("auto", 3, "/data/region1/") == "auto 3 - region1"
    assert bl.outline_kind("manual 12 - region1", "/x/region1") == "manual"
    assert bl.outline_kind("auto 3 - region1", "/x/region1") == "auto"
    assert bl.outline_kind("auto 3 - region1") == "auto"
    assert bl.outline_kind("auto 3 - old region1", "/x/region1") is None
    assert bl.outline_kind("auto 3 - region1", "/x/old region1") is None
    for name in ("0001-0123", "sphere 1 (matte, found)", "auto - region1", "automatic 3 - region1",
                 None, ""):
        assert bl.outline_kind(name, "/x/region1") is None
    assert bl.added_by_uvps("manual 12 - region1") and bl.added_by_uvps("sphere 2 (matte, found)")
    assert not bl.added_by_uvps("0001-0123") and not bl.added_by_uvps(None)


def test_detection_settings_and_browse_buttons_come_with_fields(spec_table):
    sens = bl.dialog_field(bl.param_spec("detect", "dynamic_k"))
    width = bl.dialog_field(bl.param_spec("detect", "min_width_um"))
    assert (sens["key"], sens["default"]) == ("sensitivity", 5.0)
    assert (width["key"], width["default"], width["units"]) == ("smallest", 30.0, u"\u00b5m")
    inputs, params = bl.request_from_values("detect", {"sensitivity": 3.0, "smallest": 50.0,
                                                       "regions": ""})
    assert params == {"dynamic_k": 3.0, "min_width_um": 50.0, "regions": None}
    # every path field has a Browse button (a file or folder chooser)
    assert bl.dialog_field(bl.param_spec("run", "images"))["kind"] == "directory"
    for command, spec in spec_table["commands"].items():
        for param in spec["params"]:
            if param["type"] in ("path", "paths"):
                assert bl.dialog_field(param)["kind"] in ("file", "directory"), param


def test_pixel_sizes_are_checked_naming_where_they_came_from():
    where = 'the field "Pixel size on the painting"'
    assert bl.check_pixel_size(30.0, where) == 30.0
    assert bl.check_pixel_size(0, where) is None and bl.check_pixel_size("", where) is None
    for bad, words in ((0.1, "(0.1 mm = 100 um)"), (-100, "a pixel size is positive"),
                       (25400.0, "300 dpi = 84.7 um"), ("abc", "not a number")):
        with pytest.raises(bl.BridgeError) as info:
            bl.check_pixel_size(bad, where)
        assert info.value.message.startswith(where + " holds ") and words in info.value.message


def test_a_negative_number_in_a_field_without_default_is_refused_not_dropped():
    param = bl.param_spec("wand", "pixel_size_um")
    assert bl.value_of(param, 0) is None
    with pytest.raises(bl.BridgeError, match="must be positive"):
        bl.value_of(param, -100)


def test_core_messages_lose_their_cli_flags_in_fiji():
    text = ("pixel size unknown: the images carry no physical resolution; pass --pixel-size-um "
            "(params 'pixel_size_um')")
    assert bl.user_words(text, "run") == (
        'pixel size unknown: the images carry no physical resolution; pass the field '
        '"Pixel size on the painting"')


def test_menu_titles_come_from_the_declarations(spec_table):
    """The Log's name of each command is its declared `menu` (uvps spec), which is the title of the
    menu script that runs it: no hand-kept list to go stale."""
    import re
    titles = bl.menu_titles(spec_table)
    assert titles["run"] == "Run Whole Pipeline"
    scripts = 0
    for path in sorted((ROOT / "plugins" / "UV_Photometric_Stereo").glob("*.py")):
        text = path.read_text()
        command = re.search(r'^COMMAND = "([\w-]+)"', text, re.M)
        if command is None:
            continue
        scripts += 1
        title = re.search(r'^TITLE = "([^"]+)"', text, re.M).group(1)
        assert titles[command.group(1)] == title, path.name
    assert scripts >= 14
    assert bl.menu_title("no-such-command", spec_table) == "no-such-command"


def test_the_question_before_a_run_replaces_manual_work_names_it(tmp_path):
    """Run Whole Pipeline asks before replacing a run folder that holds manual work: the files, the wand's
    counted and clicked, and what each answer does."""
    assert bl.manual_work_in(str(tmp_path)) == []
    (tmp_path / "protrusions_manual.csv").write_text(
        "id,x_px,y_px,width_um,counted,note\n1,5,5,100,1,\n2,9,9,,0,no contrast in the albedo: nothing outlined\n")
    (tmp_path / "comparison.csv").write_text("label\n")
    found = bl.manual_work_in(str(tmp_path))
    assert found == ["protrusions_manual.csv (1 counted of 2 clicks)", "comparison.csv"]
    text = bl.manual_work_question(str(tmp_path), found)
    assert str(tmp_path) in text and "protrusions_manual.csv (1 counted of 2 clicks), comparison.csv" in text
    assert "earlier/<date>_<run id>/" in text and bl.KEEP_AND_RUN in text and bl.DO_NOT_RUN in text


def test_the_wand_summary_is_one_log_line():
    d = {"n_points": 7, "n_protrusions": 5, "summary": "7 clicks: 5 outlined, 2 not (bare paint at (4, 5) px; "
         "height only at (8, 9) px)"}
    assert bl.diagnostic_lines("wand", d) == ["uvps Wand Count: " + d["summary"]]


class _Prefs(object):
    """ij.Prefs as a dict."""

    def __init__(self):
        self.values = {}

    def get(self, key, default):
        return self.values.get(key, default)

    def set(self, key, value):
        self.values[key] = value


class _AnsweringDialog(FakeGenericDialog):
    """A dialog whose user changes some fields (``answers``: label -> value) and presses OK."""

    answers = {}

    def wasCanceled(self):
        self._next = iter(self.fields)
        return False

    def _value(self):
        kind, label, value, _ = next(self._next)
        return _AnsweringDialog.answers.get(label, value)

    getNextString = getNextChoice = getNextNumber = getNextBoolean = _value

    def invalidNumber(self):
        return False


class _Question(object):
    """ij.gui.YesNoCancelDialog: records its text; the user presses the first button when ``yes``."""

    yes = False
    asked = []

    def __init__(self, parent, title, text, yes_label, no_label):
        _Question.asked.append((text, yes_label, no_label))

    def yesPressed(self):
        return _Question.yes


@pytest.fixture
def dialog_module(monkeypatch):
    """uvps_fiji.dialogs with fake ImageJ classes: a user at the dialog (no macro options)."""
    from unittest import mock

    prefs = _Prefs()
    logged = []
    ij = _fake_module("ij", IJ=mock.MagicMock(log=logged.append),
                      Macro=mock.MagicMock(getOptions=lambda: None), Prefs=prefs)
    _install_fake_imagej(monkeypatch, ij, _fake_module("ij.gui", GenericDialog=_AnsweringDialog,
                                                        YesNoCancelDialog=_Question))
    import importlib

    import uvps_fiji
    for name in ("dialogs", "runner"):
        monkeypatch.delitem(sys.modules, "uvps_fiji." + name, raising=False)
        monkeypatch.delattr(uvps_fiji, name, raising=False)   # else `from` finds a stale one
    dialogs = importlib.import_module("uvps_fiji.dialogs")
    yield dialogs, prefs, logged
    for name in ("dialogs", "runner"):
        sys.modules.pop("uvps_fiji." + name, None)


def _regions_dialog(dialogs, answers):
    _AnsweringDialog.answers = answers
    dlg = dialogs.UVPSDialog("Detect Protrusions")
    dialogs.add_run_field(dlg)
    dlg.string("Regions: colour areas", "")
    values = dlg.show()
    return values, dlg.gd.fields


def test_a_runs_regions_file_is_not_carried_over_to_another_run(dialog_module):
    """The Regions field names one run's own label image: it is offered again with that run only,
    and not used when the user changes the run folder but leaves it (the Log says so)."""
    dialogs, prefs, logged = dialog_module
    mine = "/data/region1/regions_labels.tif"
    values, _ = _regions_dialog(dialogs, {"Run folder (outputs)": "/data/region1",
                                          "Regions: colour areas": mine})
    assert values["regions"] == mine
    # the same run again: offered
    values, fields = _regions_dialog(dialogs, {})
    assert [f[2] for f in fields] == ["/data/region1", mine] and values["regions"] == mine
    # the user changes the run folder only: the other run's file is not used
    values, _ = _regions_dialog(dialogs, {"Run folder (outputs)": "/data/region2"})
    assert values == {"run": "/data/region2", "regions": ""}
    assert len(logged) == 1 and mine in logged[0] and "not used" in logged[0]
    # next time, with region2, nothing is pre-filled; choosing the file again uses it
    values, fields = _regions_dialog(dialogs, {"Regions: colour areas": mine})
    assert [f[2] for f in fields] == ["/data/region2", ""] and values["regions"] == mine
    # a run folder chosen elsewhere (another menu item) : the field starts empty
    prefs.set("uvps.run", "/data/region3")
    _, fields = _regions_dialog(dialogs, {})
    assert [f[2] for f in fields] == ["/data/region3", ""]


def _capture_dialog(dialogs, answers):
    _AnsweringDialog.answers = answers
    dlg = dialogs.UVPSDialog("Run Whole Pipeline")
    dlg.choice("Capture source", dialogs.CAPTURE_CHOICES, dialogs.CAPTURE_CURRENT)
    dlg.string("Images: folder or files", "")
    dialogs.add_run_field(dlg)
    return dlg.show()


def test_a_run_folder_is_not_silently_filled_with_another_captures_outputs(dialog_module, tmp_path):
    """The run folder is remembered with the capture whose outputs went into it: a new capture with
    the old run folder left in the field is asked about (one question naming the folder and both
    captures); "Do not run" cancels, naming them; "Write into it" goes on; an empty folder, a folder
    the user typed, or the same capture again are not asked about."""
    dialogs, prefs, logged = dialog_module
    _Question.asked[:] = []
    files = dialogs.CAPTURE_FILES
    run1 = tmp_path / "region1"
    cap1, cap2 = str(tmp_path / "capture 2019"), str(tmp_path / "capture 2024")
    first = {"Capture source": files, "Images: folder or files": cap1, "Run folder (outputs)": str(run1)}
    assert _capture_dialog(dialogs, first)["run"] == str(run1)
    # the run writes into the folder; the same capture again is not asked about
    run1.mkdir()
    (run1 / "run.json").write_text("{}")
    assert _capture_dialog(dialogs, {"Capture source": files})["images"] == cap1 and _Question.asked == []
    # another capture, the run folder left as it was: asked, naming both; "Do not run" writes nothing
    other = {"Capture source": files, "Images: folder or files": cap2}
    with pytest.raises(dialogs.BridgeError) as err:
        _capture_dialog(dialogs, other)
    assert err.value.error_type == "Cancelled"
    assert str(run1) in err.value.message and cap1 in err.value.message and cap2 in err.value.message
    ((text, yes, no),) = _Question.asked
    assert str(run1) in text and cap1 in text and cap2 in text and (yes, no) == (dialogs.WRITE_INTO_IT,
                                                                                 dialogs.DO_NOT_WRITE)
    assert prefs.get("uvps.images", "") == cap1          # nothing remembered from a refused dialog
    # "Write into it": the run goes on, and the folder is now remembered with the new capture
    _Question.yes = True
    try:
        assert _capture_dialog(dialogs, other)["run"] == str(run1)
        assert prefs.get("uvps.run.capture", "") == os.path.normpath(cap2)
        assert len(_Question.asked) == 2
        _Question.yes = False
        # back to the first capture: asked again (the folder now holds the second's outputs)
        with pytest.raises(dialogs.BridgeError):
            _capture_dialog(dialogs, {"Capture source": files, "Images: folder or files": cap1})
        assert len(_Question.asked) == 3
        # a run folder the user chose (typed or browsed to another one) is not asked about
        run2 = tmp_path / "region2"
        run2.mkdir()
        (run2 / "notes.txt").write_text("x")
        values = _capture_dialog(dialogs, {"Capture source": files, "Images: folder or files": cap1,
                                           "Run folder (outputs)": str(run2)})
        assert values["run"] == str(run2) and len(_Question.asked) == 3
        # an empty folder left in the field: no question, nothing in it to mix with
        empty = tmp_path / "region3"
        empty.mkdir()
        _capture_dialog(dialogs, {"Capture source": files, "Images: folder or files": cap1,
                                  "Run folder (outputs)": str(empty)})
        assert _capture_dialog(dialogs, other)["run"] == str(empty) and len(_Question.asked) == 3
    finally:
        _Question.yes = False
