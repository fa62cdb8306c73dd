"""The detector's outputs pinned bit for bit (``scripts/detect_golden.py``): labels, candidate
labels, rejection reasons, sources, the two cue masks, the rejection counts and every
diagnostic, on the analytic scenes of ``tests/test_detect.py`` and the benchmark's ``top``,
``impasto`` and ``on_strokes`` scenes (seeds 0-2). A restructuring must leave them unchanged; a
change of behaviour regenerates them (``python scripts/detect_golden.py [--full]``) in its own
commit, which says why."""
import json
import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "scripts"))
import detect_golden as golden  # noqa: E402


def _expected(path):
    assert path.exists(), f"{path} missing: python scripts/detect_golden.py [--full]"
    with np.load(path) as z:
        return {k: z[k] for k in z.files}


def _same(got, want, where):
    """Equal to the letter, except floats: those to 1e-12 relative (a diagnostic summed by OpenCV's
    or numba's threads differs in its last bit with the number of threads; labels, reasons and
    counts are compared exactly)."""
    if isinstance(want, dict):
        assert isinstance(got, dict) and sorted(got) == sorted(want), where
        for k in want:
            _same(got[k], want[k], f"{where}/{k}")
    elif isinstance(want, list):
        assert isinstance(got, list) and len(got) == len(want), where
        for i, (g, w) in enumerate(zip(got, want)):
            _same(g, w, f"{where}[{i}]")
    elif isinstance(want, float) and isinstance(got, float):
        assert got == pytest.approx(want, rel=1e-12, abs=1e-300), where
    else:
        assert got == want, where


def _check(full, name):
    want = _expected(golden.FULL if full else golden.QUICK)
    got = golden.compute(full, only={name})
    keys = sorted(k for k in want if k.startswith(name + "::"))
    assert keys and sorted(got) == keys
    for k in keys:
        if k.endswith("::rest"):
            _same(json.loads(str(got[k])), json.loads(str(want[k])), k)
        else:
            assert got[k].dtype == want[k].dtype and got[k].shape == want[k].shape, k
            np.testing.assert_array_equal(got[k], want[k], err_msg=k)


def test_golden_files_cover_every_scene():
    for full, path in ((False, golden.QUICK), (True, golden.FULL)):
        names = {k.split("::")[0] for k in _expected(path)}
        assert names == set(golden.all_scenes(full)), path


@pytest.mark.parametrize("name", sorted(golden.all_scenes(False)))
def test_detection_matches_the_golden_file(name):
    _check(False, name)


@pytest.mark.slow
@pytest.mark.parametrize("name", sorted(golden.all_scenes(True)))
def test_detection_matches_the_golden_file_at_the_benchmarks_size(name):
    _check(True, name)
