"""Tests of the file bridge: real subprocesses on real requests, and every failure path."""
import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from uvps import bridge
from uvps.errors import UVPSComputeError
from uvps.files.io import read_capture, read_tiff, sha256_file, write_imagej_tiff
from uvps.files.outputs import CommandResult, OutputSpec, atomic_output_dir

PX_UM = 20.0


def _capture(folder, k=4, shape=(16, 20)):
    folder.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(7)
    imgs = rng.integers(100, 5000, (k,) + shape).astype(np.uint16)
    for i, img in enumerate(imgs):
        write_imagej_tiff(folder / f"img{i + 1:02d}.tif", img, axes="YX", pixel_size_um=PX_UM)
    return imgs


def _mean_command(inputs, params, output_dir, *, progress=None):
    """A small real command: the mean image of a capture, written as an ImageJ TIFF."""
    cap = read_capture(inputs["images"], pixel_size_um=params.get("pixel_size_um"))
    if params.get("fail") == "compute":
        raise UVPSComputeError("the mean is undefined\nsecond line of detail")
    with atomic_output_dir(output_dir) as tmp:
        for k in range(cap.images.shape[0]):
            if progress:
                progress(k / cap.images.shape[0], f"image {k + 1}\nof {cap.images.shape[0]}")
        if params.get("fail") == "crash":
            (tmp / "mean.tif").write_bytes(b"half")
            raise ZeroDivisionError("boom")
        write_imagej_tiff(tmp / "mean.tif", np.asarray(cap.images).mean(axis=0), axes="YX",
                          pixel_size_um=cap.pixel_size_um)
    print("a stray print from a library")
    out = OutputSpec("mean", str(output_dir / "mean.tif"), axes="YX", dtype="float32", units="counts")
    return CommandResult([out], {"k": np.int64(cap.images.shape[0]), "ratio": float("nan"),
                                 "pixel_size_um": np.float32(cap.pixel_size_um)}, ["a warning"])


@pytest.fixture
def registry():
    return {"mean": _mean_command}


def _request(folder, **fields):
    folder.mkdir(parents=True, exist_ok=True)
    req = {"schema_version": 1, "command": "mean", "inputs": {}, "params": {},
           "output_dir": str(folder / "out")}
    req.update(fields)
    path = folder / "request.json"
    path.write_text(json.dumps(req))
    return path


def _response(req_path):
    return json.loads((req_path.parent / "response.json").read_text())


def test_in_process_round_trip_with_relative_paths(tmp_path, registry, capsys):
    imgs = _capture(tmp_path / "req" / "cap")
    req = _request(tmp_path / "req", inputs={"images": "cap"}, output_dir="out", extra=1)
    assert bridge.run_bridge(req, registry) == 0
    resp = _response(req)
    assert resp["status"] == "ok" and resp["error"] is None and resp["command"] == "mean"
    out = resp["outputs"][0]
    assert out["path"] == str(tmp_path / "req" / "out" / "mean.tif")
    data, px = read_tiff(out["path"])
    np.testing.assert_allclose(data, imgs.astype(np.float32).mean(axis=0), rtol=1e-6)
    assert px == pytest.approx(PX_UM, rel=1e-6)
    assert resp["diagnostics"] == {"k": 4, "ratio": None, "pixel_size_um": PX_UM}
    assert resp["warnings"] == ["request key 'extra' ignored (unknown)", "a warning"]
    assert resp["version"] and resp["elapsed_s"] >= 0
    stdout = capsys.readouterr().out.splitlines()
    assert stdout == [f"PROGRESS {k / 4:.4f} image {k + 1} of 4" for k in range(4)]


def _req_text(**fields):
    return json.dumps({"schema_version": 1, "command": "mean", "output_dir": "o", **fields})


@pytest.mark.parametrize("text,match", [
    ("{not json", "not valid JSON"),
    ("[1, 2]", "expected a JSON object"),
    (_req_text(schema_version=2), "schema_version must be 1; got 2"),
    (_req_text(schema_version=True), "schema_version must be 1; got True"),
    (_req_text(command="nope"), "unknown command 'nope'"),
    (_req_text(inputs=[]), "'inputs' must be"),
    (_req_text(params="x"), "'params' must be"),
    (_req_text(output_dir=None), "'output_dir' must be"),
    (_req_text(output_dir="a_file"), "is an existing file"),
    (_req_text(output_dir="a_file/out"), "is a file, not a folder"),
])
def test_bad_requests_exit_1_with_one_line(tmp_path, registry, text, match):
    (tmp_path / "a_file").write_text("x")
    req = tmp_path / "request.json"
    req.write_text(text)
    assert bridge.run_bridge(req, registry) == 1
    resp = _response(req)
    assert resp["status"] == "error" and resp["error"]["type"] == "UVPSInputError"
    assert match in resp["error"]["message"] and "\n" not in resp["error"]["message"]
    assert resp["outputs"] == []


def test_missing_request_file_still_answers(tmp_path, registry):
    assert bridge.run_bridge(tmp_path / "request.json", registry) == 1
    assert "does not exist" in _response(tmp_path / "request.json")["error"]["message"]


def test_input_error_from_command_leaves_output_untouched(tmp_path, registry):
    out = tmp_path / "out"
    out.mkdir()
    (out / "old.txt").write_text("keep")
    before = {p.name: sha256_file(p) for p in out.iterdir()}
    req = _request(tmp_path, inputs={"images": str(tmp_path / "missing")})
    assert bridge.run_bridge(req, registry) == 1
    resp = _response(req)
    assert resp["error"]["type"] == "UVPSInputError" and "missing" in resp["error"]["message"]
    assert {p.name: sha256_file(p) for p in out.iterdir()} == before


@pytest.mark.parametrize("fail,exc_type,message", [
    ("compute", "UVPSComputeError", "the mean is undefined"),
    ("crash", "ZeroDivisionError", "boom"),
])
def test_other_errors_exit_2_traceback_on_stderr_only(tmp_path, registry, capsys, fail, exc_type,
                                                      message):
    _capture(tmp_path / "cap")
    out = tmp_path / "out"
    out.mkdir()
    (out / "mean.tif").write_bytes(b"previous result")
    req = _request(tmp_path, inputs={"images": str(tmp_path / "cap")}, params={"fail": fail})
    assert bridge.run_bridge(req, registry) == 2
    resp = _response(req)
    assert resp["error"] == {"type": exc_type, "message": message}
    assert resp["status"] == "error" and resp["outputs"] == []
    captured = capsys.readouterr()
    assert "Traceback" not in captured.out and all(
        ln.startswith("PROGRESS ") for ln in captured.out.splitlines())
    if fail == "crash":
        assert "Traceback" in captured.err and "ZeroDivisionError" in captured.err
    assert (out / "mean.tif").read_bytes() == b"previous result"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["cap", "out", "request.json", "response.json"]


def test_command_returning_wrong_type_is_compute_error(tmp_path, registry):
    registry["mean"] = lambda inputs, params, output_dir, *, progress=None: {"outputs": []}
    req = _request(tmp_path)
    assert bridge.run_bridge(req, registry) == 2
    assert _response(req)["error"]["type"] == "UVPSComputeError"


def test_jsonable_makes_strict_json():
    obj = {"a": np.float64("inf"), "b": [np.int32(3), np.array([1.5, np.nan])], 4: Path("/x")}
    text = json.dumps(bridge._jsonable(obj), allow_nan=False)
    assert json.loads(text) == {"a": None, "b": [3, [1.5, None]], "4": "/x"}


# --- real subprocesses, real commands -----------------------------------------------------------


def _run(req, *, module="uvps", extra=("bridge",)):
    env = dict(os.environ, PYTHONWARNINGS="error")
    return subprocess.run([sys.executable, "-m", module, *extra, str(req)], capture_output=True,
                          text=True, env=env, timeout=120)


def _bump_run(folder, shape=(48, 64)):
    """A run folder holding normals.tif of an analytic Gaussian bump; returns its height (um)."""
    from uvps.testing.synthetic import normals_from_height

    m, n = shape
    r, c = np.mgrid[:m, :n]
    height = (30.0 * np.exp(-((c - n / 2) ** 2 + (r - m / 2) ** 2) / (2 * 8.0 ** 2))).astype(np.float32)
    normals = normals_from_height(height, pixel_size_um=PX_UM)
    (folder / "run").mkdir(parents=True)
    write_imagej_tiff(folder / "run" / "normals.tif", np.moveaxis(normals, -1, 0), axes="CYX",
                      pixel_size_um=PX_UM)
    return height - np.median(height)


def _snapshot(folder):
    return {p.relative_to(folder): (p.stat().st_mtime_ns, sha256_file(p))
            for p in sorted(folder.rglob("*")) if p.is_file()}


@pytest.mark.parametrize("method", ["fc", "dct"])
def test_subprocess_integrate_round_trip(tmp_path, method):
    height = _bump_run(tmp_path)
    req = _request(tmp_path, command="integrate", params={"integration": method}, output_dir="run")
    proc = _run(req)
    assert proc.returncode == 0, proc.stderr
    lines = proc.stdout.splitlines()
    assert lines and all(ln.startswith("PROGRESS ") for ln in lines)
    fractions = [float(ln.split()[1]) for ln in lines]
    assert fractions == sorted(fractions) and fractions[-1] == 1.0
    assert "uvps.bridge" in proc.stderr  # the log goes to stderr
    resp = _response(req)
    assert resp["status"] == "ok" and resp["command"] == "integrate" and resp["error"] is None
    (depth,) = [o for o in resp["outputs"] if o["name"] == "depth"]
    assert depth["path"] == str(tmp_path / "run" / "depth.tif") and depth["units"] == "um"
    data, px = read_tiff(depth["path"])
    assert px == pytest.approx(PX_UM, rel=1e-6)
    # a 30 um bump recovered to within 1 um (FC's periodic/mirror boundary costs a little)
    assert np.abs(data - height).max() < 1.0
    assert resp["elapsed_s"] > 0 and isinstance(resp["diagnostics"], dict)


@pytest.mark.slow
def test_subprocess_input_errors_exit_1_and_leave_run_folder(tmp_path):
    (tmp_path / "run").mkdir()
    (tmp_path / "run" / "notes.txt").write_text("mine")
    before = _snapshot(tmp_path / "run")
    cases = [
        ({"command": "integrate"}, "no normals.tif"),
        ({"command": "integrate", "params": {"integration": "poisson"}}, "integration"),
        ({"command": "nonsense"}, "unknown command 'nonsense'"),
        ({"command": "integrate", "schema_version": 7}, "schema_version must be 1"),
        ({"command": "integrate", "output_dir": str(tmp_path / "run" / "notes.txt")},
         "is an existing file"),
    ]
    for fields, match in cases:
        req = _request(tmp_path, **{"output_dir": "run", **fields})
        proc = _run(req)
        assert proc.returncode == 1, (fields, proc.stderr)
        resp = _response(req)
        assert resp["status"] == "error" and resp["error"]["type"] == "UVPSInputError"
        assert match in resp["error"]["message"] and "\n" not in resp["error"]["message"]
        assert "Traceback" not in proc.stderr and "Traceback" not in proc.stdout
        assert _snapshot(tmp_path / "run") == before
    req = tmp_path / "request.json"
    req.write_text("{broken")
    proc = _run(req)
    assert proc.returncode == 1 and proc.stdout == ""
    assert "not valid JSON" in _response(req)["error"]["message"]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["request.json", "response.json", "run"]


def test_subprocess_unexpected_error_exit_2(tmp_path):
    _bump_run(tmp_path)
    (tmp_path / "run" / "depth.tif").mkdir()  # the output cannot replace a folder
    req = _request(tmp_path, command="integrate", output_dir="run")
    proc = _run(req)
    assert proc.returncode == 2
    resp = _response(req)
    assert resp["status"] == "error" and resp["error"]["type"] == "IsADirectoryError"
    assert "\n" not in resp["error"]["message"]
    assert "Traceback" in proc.stderr and "Traceback" not in proc.stdout
    assert (tmp_path / "run" / "depth.tif").is_dir()


def test_subprocess_missing_request_and_python_m_uvps_bridge(tmp_path):
    proc = _run(tmp_path / "nowhere" / "request.json")
    assert proc.returncode == 1 and "does not exist" in proc.stderr
    assert not (tmp_path / "nowhere").exists()
    proc = _run(tmp_path / "request.json", module="uvps.bridge", extra=())
    assert proc.returncode == 1
    assert "does not exist" in _response(tmp_path / "request.json")["error"]["message"]


def test_subprocess_sigterm_cancels_cleanly(tmp_path):
    from uvps.testing.synthetic import make_capture, write_capture

    write_capture(make_capture(shape=(120, 160), n_lights=6), tmp_path / "cap", truth=False)
    (tmp_path / "run").mkdir()
    (tmp_path / "run" / "old.txt").write_text("previous")
    before = _snapshot(tmp_path / "run")
    req = _request(tmp_path, command="flatfield", inputs={"images": "cap"}, output_dir="run")
    proc = subprocess.Popen([sys.executable, "-m", "uvps", "bridge", str(req)],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        for line in proc.stdout:  # wait until the command works inside its temporary folder
            if float(line.split()[1]) > 0.1:
                break
        proc.terminate()
        proc.communicate(timeout=60)
    finally:
        proc.kill()
    assert proc.returncode == 2
    resp = _response(req)
    assert resp["error"]["type"] == "Cancelled" and resp["status"] == "error"
    assert _snapshot(tmp_path / "run") == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["cap", "request.json", "response.json", "run"]


def test_a_cancellation_inside_compiled_code_is_reported_as_cancelled():
    """A Cancelled raised while a numba function runs comes out as a SystemError chain ("returned a
    result with an exception set"); the bridge finds it down the chain and answers Cancelled."""
    from uvps.bridge import Cancelled, _cancellation_in

    try:
        try:
            raise Cancelled("cancelled: the bridge received SIGTERM")
        except Cancelled as inner:
            raise SystemError("<numba dispatcher> returned a result with an exception set") from inner
    except SystemError as exc:
        found = _cancellation_in(exc)
    assert isinstance(found, Cancelled), repr(found)
    assert _cancellation_in(ValueError("other")) is None


def test_sigterm_stops_a_command_at_its_next_progress_report_and_a_second_one_at_once():
    """SIGTERM only sets a flag (an exception raised by a signal handler inside a compiled call can
    crash the interpreter); the command stops at its next progress report; when none comes within
    the grace period, a second SIGTERM interrupts it wherever it is."""
    import os
    import signal
    import time

    import uvps.bridge as bridge

    import io

    printer = bridge._progress_printer(io.StringIO())
    with pytest.raises(bridge.Cancelled):
        with bridge._sigterm_cancels():
            os.kill(os.getpid(), signal.SIGTERM)
            time.sleep(0.05)                     # the handler runs: nothing is raised yet
            assert bridge._CANCEL.is_set()
            printer(0.5, "next step")
    assert not bridge._CANCEL.is_set()
    old, bridge.CANCEL_GRACE_S = bridge.CANCEL_GRACE_S, 0.2
    t0 = time.monotonic()
    try:
        with pytest.raises(bridge.Cancelled):
            with bridge._sigterm_cancels():
                os.kill(os.getpid(), signal.SIGTERM)
                while time.monotonic() - t0 < 30:   # a long step that reports no progress
                    time.sleep(0.01)
    finally:
        bridge.CANCEL_GRACE_S = old
    assert time.monotonic() - t0 < 10
