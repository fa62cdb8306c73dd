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
    out = subprocess.run(["jython", "-c", script], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    assert out.stdout.split() == ["0.5", "/a", "b"]
    for src in (ROOT / "jython_lib" / "uvps_fiji").glob("*.py"):
        src.read_bytes().decode("ascii")  # Jython sources must stay ASCII


@pytest.mark.skipif(shutil.which("jython") is None, reason="Debian's jython is not installed")
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


def test_a_real_core_run_is_accepted_with_its_outputs(tmp_path):
    from uvps.synthetic import make_capture, write_capture

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
