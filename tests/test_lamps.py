"""`uvps lamps`: a run's or calibration's lamps as an RTI .lp and a positions CSV, read back by the
same readers `--lights` uses (so the numbers survive the round trip)."""
import json
import subprocess
import sys

import numpy as np
import pytest

from uvps.commands import COMMANDS
from uvps.core.irradiance import LightModel
from uvps.errors import UVPSInputError
from uvps.files.io import read_lp, read_positions


def _lights_json(folder, model, files):
    """lights.json as a run writes it; a calibration's names no file (lamps matched by order)."""
    folder.mkdir(parents=True, exist_ok=True)
    doc = model.to_json(files)
    for lamp, f in zip(doc["lights"], files):
        lamp["file"] = f
    (folder / "lights.json").write_text(json.dumps(doc))
    return folder


def test_near_lamps_round_trip_through_lp_and_csv(tmp_path):
    P = np.array([[300.0, 0, 250], [-150, 260, 300], [-150, -260, 280], [10, -5, 400]])
    E = np.array([1.0, 0.9, 1.2, 0.8])
    run = _lights_json(tmp_path / "run", LightModel.from_positions(P, E), [f"/cap/uv_{k}.tif" for k in range(4)])
    res = COMMANDS["lamps"]({"run": str(run)}, {}, tmp_path / "out")
    assert res.diagnostics["n_lamps"] == 4 and res.diagnostics["near"]
    lp = read_lp(tmp_path / "out" / "lamps.lp")
    assert lp.files == [f"uv_{k}.tif" for k in range(4)]
    np.testing.assert_allclose(lp.directions, P / np.linalg.norm(P, axis=1, keepdims=True), atol=1e-7)
    back = read_positions(tmp_path / "out" / "lamps_mm.csv")
    np.testing.assert_allclose(back.positions_mm, P, atol=1e-6)
    np.testing.assert_allclose(back.intensities, E, atol=1e-6)


def test_far_lamps_of_a_calibration_give_the_lp_alone_named_by_order(tmp_path):
    D = np.array([[1.0, 0, 1], [0, 1, 1], [-1, 0, 1]])
    cal = _lights_json(tmp_path / "cal", LightModel.from_directions(D), [None, None, None])
    out = tmp_path / "cal"                      # written into the folder itself, as from Fiji
    COMMANDS["lamps"]({"run": str(cal)}, {}, out)
    lp = read_lp(out / "lamps.lp")
    assert lp.files == ["lamp_01", "lamp_02", "lamp_03"]
    np.testing.assert_allclose(lp.directions, D / np.sqrt(2), atol=1e-7)
    assert not (out / "lamps_mm.csv").exists() and (out / "lights.json").is_file()


def test_a_folder_without_lamps_is_one_line_and_the_cli_exits_1(tmp_path):
    with pytest.raises(UVPSInputError, match="holds no lights.json"):
        COMMANDS["lamps"]({"run": str(tmp_path)}, {}, tmp_path / "out")
    proc = subprocess.run([sys.executable, "-m", "uvps", "lamps", str(tmp_path), "-o", str(tmp_path / "out")],
                          capture_output=True, text=True, timeout=120)
    assert proc.returncode == 1 and len(proc.stderr.strip().splitlines()) == 1, proc.stderr
    assert not (tmp_path / "out").exists()
