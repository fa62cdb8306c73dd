"""The robustness benchmark (scripts/benchmark_robustness.py) end to end on a tiny capture.

It runs the real ``run`` command on captures written to disk: 17-20 s on 2 busy cores, up to a minute
when the light refinement runs to its cap on this 3 x 2.4 mm field; marked slow.
"""
from __future__ import annotations

import importlib.util
import json
import math
import sys
from pathlib import Path

import pytest

SCRIPT = Path(__file__).resolve().parents[1] / "scripts" / "benchmark_robustness.py"


def _load():
    spec = importlib.util.spec_from_file_location("benchmark_robustness", SCRIPT)
    mod = importlib.util.module_from_spec(spec)
    sys.modules.setdefault("benchmark_robustness", mod)
    spec.loader.exec_module(mod)
    return mod


@pytest.mark.slow
def test_benchmark_robustness_tiny(tmp_path, capsys):
    bench = _load()
    work = tmp_path / "work"
    argv = ["--rows", "none", "black_level", "--seeds", "0", "--lights-counts", "8", "--shape", "160", "200",
            "--modes", "estimated", "--workdir", str(work)]
    assert bench.main(argv) == 0
    out = capsys.readouterr().out
    assert "## Robustness\n" in out and "| none | 8 | estimated |" in out
    data = json.loads((work / "robustness_results.json").read_text())
    results = {r["row"]: r for r in data["results"]}
    assert set(results) == {"none", "black_level"}
    for r in results.values():
        assert r["error"] is None, r.get("traceback")
        assert math.isfinite(r["light_mean_deg"]) and math.isfinite(r["light_max_deg"])
        assert math.isfinite(r["normals_mean_deg"])
        assert len(r["light_errors_deg"]) == 8
    # the run measured the additive term (run.json diagnostics) within 30 % of the truth's black level
    bl = results["black_level"]
    truth = bl["truth_nuisances"]["black_level_counts"]
    assert min(truth) > 0
    measured = bl["additive_counts"]
    assert len(measured) == len(truth)
    for m, t in zip(measured, truth):
        assert abs(m - t) <= 0.3 * t, (measured, truth)
    # captures and run folders are removed without --keep; the results are cached per run
    assert not any((work / "captures").iterdir())
    assert not any((work / "runs").iterdir())
    assert (work / "results" / "black_level__seed0__k8__estimated.json").exists()
    # a second call resumes: nothing to run, same numbers
    assert bench.main(argv) == 0
    again = json.loads((work / "robustness_results.json").read_text())
    assert [r["light_mean_deg"] for r in again["results"]] == [r["light_mean_deg"] for r in data["results"]]


@pytest.mark.slow
def test_benchmark_robustness_doc_rewrites_its_row_from_a_real_run(tmp_path, monkeypatch):
    """``--doc`` after a real (tiny) run with 12 lamps: the run's seed replaces the kept one in a copy of
    docs/benchmarks/robustness.json, the row's seed-0 cells are this run's, and the check passes."""
    import shutil
    import subprocess

    bench = _load()
    import benchdoc
    md, jd = tmp_path / "benchmarks.md", tmp_path / "json"
    shutil.copy(benchdoc.DOC, md)
    shutil.copytree(benchdoc.JSON_DIR, jd)
    monkeypatch.setattr(benchdoc, "DOC", md)
    monkeypatch.setattr(benchdoc, "JSON_DIR", jd)
    argv = ["--rows", "vignetting", "--seeds", "0", "--lights-counts", "12", "--shape", "160", "200",
            "--modes", "estimated", "--no-detect", "--workdir", str(tmp_path / "work"), "--doc"]
    assert bench.main(argv) == 0
    run = json.loads((tmp_path / "work" / "robustness_results.json").read_text())["results"][0]
    kept = [r for r in json.loads((jd / "robustness.json").read_text())["runs"]
            if (r["row"], r["mode"]) == ("vignetting", "estimated")]
    assert [r["seed"] for r in kept] == [0, 1, 2] and kept[0]["light_mean_deg"] == run["light_mean_deg"]
    line = next(x for x in benchdoc.read_section(md, "robustness").splitlines() if x.startswith("| vignetting |"))
    assert line.startswith(f"| vignetting | {run['light_mean_deg']:.2f} / 0.73 / 0.54")
    check = [sys.executable, str(SCRIPT.parent / "benchmark_docs.py"), "--check", "--md", str(md), "--json-dir", str(jd)]
    assert subprocess.run(check, capture_output=True, text=True).returncode == 0


def test_every_sphere_mode_names_the_spheres_it_renders():
    """Each sphere mode of the benchmark describes its spheres as the generator takes them (a mode's name
    hidden by another table made every sphere run fail before it started)."""
    from uvps.testing.synthetic_spheres import SphereSpec
    bench = _load()
    assert set(bench.SPHERE_MODES) == set(bench.SPHERE_DOC_MODES)
    for mode, spheres in bench.SPHERE_MODES.items():
        specs = [SphereSpec(*s) for s in spheres]
        assert len(specs) == 2 and {s.kind for s in specs} == {"matte" if mode.startswith("matte") else "glossy"}
