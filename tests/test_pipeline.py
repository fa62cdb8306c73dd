"""pipeline.run: the whole run in memory, the same as what `uvps run` writes; stages and refusals."""
import json

import numpy as np
import pytest
import tifffile

from uvps.commands import COMMANDS
from uvps.errors import UVPSInputError
from uvps.files.io import read_capture
from uvps.core.pipeline import STAGES, RunOptions, run
from uvps.files.runfolder import read_run, write_run
from uvps.testing.synthetic import make_capture, write_capture


@pytest.fixture(scope="module")
def synthetic():
    return make_capture(shape=(200, 260), n_lights=8, seed=7)


def _angle(a, b):
    return np.degrees(np.arccos(np.clip(np.sum(a * b, -1), -1, 1)))


def test_run_in_memory_with_known_lamps_recovers_the_surface(synthetic):
    res = run(synthetic.as_capture(lights="positions"), RunOptions(), stages=("height",))
    assert res.stages == ("normals", "height")               # height implies normals
    assert res.lights.source == "positions"
    assert np.nanmean(_angle(res.stereo.normals, synthetic.normals)) < 1.0
    h = synthetic.height_um - np.median(synthetic.height_um)
    assert np.corrcoef(res.height.height_um.ravel(), h.ravel())[0, 1] > 0.9
    assert set(res.timings_s) >= {"additive", "lights", "normals", "integrate"}
    assert res.protrusions is None and res.warnings == []


def test_the_command_writes_exactly_what_run_computes(synthetic, tmp_path):
    """`uvps run` is read -> pipeline.run -> runfolder.write_run: the files hold the in-memory arrays."""
    write_capture(synthetic, tmp_path / "cap")
    out = tmp_path / "run"
    lamps = str(tmp_path / "cap" / "lights_positions_mm.csv")
    result = COMMANDS["run"]({"images": [str(tmp_path / "cap")]}, {"regions": "auto", "lights": lamps}, out)
    res = run(read_capture(tmp_path / "cap", lights=lamps), RunOptions(), stages=STAGES, regions="auto")
    images = read_run(out, need=("albedo", "depth", "normals"))
    np.testing.assert_array_equal(images.normals, res.stereo.normals)
    np.testing.assert_array_equal(images.height_um, res.height.height_um)
    np.testing.assert_array_equal(images.albedo, res.stereo.albedo)
    labels = tifffile.imread(out / "protrusions_labels.tif")
    np.testing.assert_array_equal(labels, res.protrusions.labels)
    assert result.diagnostics["detect"]["n_protrusions"] == len(res.protrusions.table["id"]) > 0
    # run.json records the whole request, with the defaults that applied
    log = json.loads((out / "run.json").read_text())
    assert log["params"]["degree"] == 4 and log["params"]["regions"] == "auto"
    # run.json holds the detection's counts and rejections, as the response does
    assert log["diagnostics"]["detect"] == json.loads(json.dumps(result.diagnostics["detect"]))
    assert sum(log["diagnostics"]["detect"]["rejected"].values()) > 0
    assert "detect" in result.diagnostics and "stats" in result.diagnostics


def test_write_run_lists_every_file_it_wrote(synthetic, tmp_path):
    res = run(synthetic.as_capture(lights="positions"), stages=("flatfield", "normals"))
    outputs = write_run(tmp_path, res, command="normals", params={})
    names = [o.name for o in outputs]
    assert names == ["lights", "dropoff", "flatfield", "normals", "albedo", "gradients", "run"]
    for o in outputs:
        assert (tmp_path / o.path.rsplit("/", 1)[-1]).exists()
    assert len(list((tmp_path / "flatfield").glob("*.tif"))) == 8


def test_unknown_stage_and_bad_options_are_refused(synthetic):
    with pytest.raises(UVPSInputError, match="stages: unknown heights"):
        run(synthetic.as_capture(), stages=("heights",))
    with pytest.raises(UVPSInputError, match="integration must be one of fc, dct"):
        RunOptions(integration="poisson")
