"""docs/benchmarks.md's sections written by the benchmark scripts (scripts/benchdoc.py) and the check that
regenerating them at HEAD changes nothing (scripts/benchmark_docs.py --check), on real files: the project's
own document and temporary copies of a small one."""
from __future__ import annotations

import json
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "scripts"))

import benchdoc  # noqa: E402
from benchdoc import SectionError, read_section, write_doc, write_section  # noqa: E402

CHECK = [sys.executable, str(ROOT / "scripts" / "benchmark_docs.py"), "--check"]
SMALL = """# Benchmarks

Prose before.
<!-- begin painting: written by scripts/benchmark_painting.py -->
| old table |
<!-- end painting -->
Prose after, kept byte for byte.\r
"""


@pytest.fixture
def doc_copy(tmp_path, monkeypatch):
    """A copy of docs/benchmarks.md and its JSONs in ``tmp_path``, which benchdoc writes to: (md, json dir)."""
    md, jd = tmp_path / "benchmarks.md", tmp_path / "json"
    shutil.copy(benchdoc.DOC, md)
    shutil.copytree(benchdoc.JSON_DIR, jd)
    monkeypatch.setattr(benchdoc, "DOC", md)
    monkeypatch.setattr(benchdoc, "JSON_DIR", jd)
    return md, jd


@pytest.fixture
def small(tmp_path):
    md = tmp_path / "benchmarks.md"
    md.write_bytes(SMALL.encode())
    return md


def _check(md: Path, json_dir: Path):
    return subprocess.run(CHECK + ["--md", str(md), "--json-dir", str(json_dir)], capture_output=True, text=True,
                          cwd=ROOT)


def test_write_section_replaces_only_the_section(small):
    assert read_section(small, "painting") == "| old table |\n"
    assert write_section(small, "painting", "| a |\n|---|\n| 1 |", source="scripts/benchmark_painting.py")
    after = small.read_bytes().decode()
    assert after == SMALL.replace("| old table |\n", "| a |\n|---|\n| 1 |\n")
    assert read_section(small, "painting") == "| a |\n|---|\n| 1 |\n"
    # the same text again: nothing written
    assert not write_section(small, "painting", "| a |\n|---|\n| 1 |\n", source="scripts/benchmark_painting.py")
    assert not list(small.parent.glob(".*.tmp"))


@pytest.mark.parametrize("text, words", [
    (SMALL.replace("<!-- end painting -->\n", ""), "has 0 end markers"),
    (SMALL.replace("<!-- begin painting: written by scripts/benchmark_painting.py -->\n", ""), "has no begin marker"),
    (SMALL + "<!-- begin painting: written by scripts/benchmark_painting.py -->\nx\n<!-- end painting -->\n",
     "marked twice"),
    (SMALL.replace("<!-- end painting -->", "<!-- end painting"), "has 0 end markers"),
    (SMALL.replace("begin painting: written by", "begin painting written by"), "ill-formed marker"),
])
def test_bad_markers_are_refused_in_one_line_naming_the_file(small, text, words):
    small.write_text(text, encoding="utf-8")
    before = small.read_bytes()
    with pytest.raises(SectionError) as e:
        write_section(small, "painting", "| new |\n", source="scripts/benchmark_painting.py")
    msg = str(e.value)
    assert words in msg and str(small) in msg and "\n" not in msg
    assert small.read_bytes() == before


def test_a_section_is_written_only_by_the_script_its_marker_names(small):
    with pytest.raises(SectionError, match="written by scripts/benchmark_painting.py, not scripts/benchmark_level.py"):
        write_section(small, "painting", "x\n", source="scripts/benchmark_level.py")
    with pytest.raises(SectionError, match="no section 'level'"):
        read_section(small, "level")
    with pytest.raises(SectionError, match="holds a marker line"):
        write_section(small, "painting", "| t |\n<!-- end painting -->\n", source="scripts/benchmark_painting.py")
    assert small.read_bytes() == SMALL.encode()


def test_write_doc_keeps_the_raw_results_and_refuses_before_writing(small, tmp_path):
    small.chmod(0o664)
    out = write_doc("painting", {"rows": [1, 2]}, "| t |\n", source="scripts/benchmark_painting.py",
                    md_path=small, json_dir=tmp_path / "json")
    assert json.loads(out.read_text()) == {"rows": [1, 2]} and out == tmp_path / "json" / "painting.json"
    assert small.stat().st_mode & 0o777 == 0o664 and out.stat().st_mode & 0o777 == 0o644
    assert read_section(small, "painting") == "| t |\n"
    with pytest.raises(SectionError):
        write_doc("lights", {"rows": []}, "x\n", source="scripts/benchmark_lights.py", md_path=small,
                  json_dir=tmp_path / "json")
    assert not (tmp_path / "json" / "lights.json").exists()


def test_the_projects_document_is_current():
    """Regenerating at HEAD changes nothing: every marked section re-renders from its JSON exactly."""
    r = subprocess.run(CHECK, capture_output=True, text=True, cwd=ROOT)
    assert r.returncode == 0, r.stderr
    found = benchdoc.sections(benchdoc.DOC.read_text(encoding="utf-8"))
    assert {"painting", "lights", "real", "elements", "robustness", "spheres", "detection", "spheres_real", "speed", "speed_load", "raw"} <= set(found)
    for name, s in found.items():
        assert (ROOT / s.source).is_file()
        assert '"--doc"' in (ROOT / s.source).read_text(encoding="utf-8")
        assert benchdoc.json_path(name).is_file(), name          # so the check above re-rendered every section


def test_the_reference_stays_a_reference():
    """docs/benchmarks.md holds each figure once, the current one, in at most 400 lines; the history
    of what was tried lives in docs/decisions/ (each of which it links)."""
    text = benchdoc.DOC.read_text(encoding="utf-8")
    assert len(text.splitlines()) <= 400
    for log in (ROOT / "docs" / "decisions").glob("*.md"):
        assert f"decisions/{log.name}" in text, log.name


def test_a_stale_section_fails_the_check_and_is_rewritten_from_its_json(tmp_path):
    md, jd = tmp_path / "benchmarks.md", tmp_path / "json"
    shutil.copy(benchdoc.DOC, md)
    shutil.copytree(benchdoc.JSON_DIR, jd)
    assert _check(md, jd).returncode == 0
    data = json.loads((jd / "painting.json").read_text())
    data["rows"][0]["f1"] = 0.5
    (jd / "painting.json").write_text(json.dumps(data))
    r = _check(md, jd)
    assert r.returncode == 1 and "section 'painting' is stale" in r.stderr
    assert "run python scripts/benchmark_painting.py --seeds 1 2 3 --doc" in r.stderr and r.stderr.count("\n") == 1
    assert md.read_bytes() == benchdoc.DOC.read_bytes()          # --check writes nothing
    r = subprocess.run(CHECK[:-1] + ["--md", str(md), "--json-dir", str(jd)], capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    text = md.read_text()
    row = data["rows"][0]       # seed 1's figures as the table rounds them, its F1 the one changed
    corner, residual = f"{row['corner_err_px']:.2f}", f"{row['max_residual_px']:.2f}"
    assert f"| 1 | {corner} | {residual} | 0.500 |" in text
    assert "| 0.500 |" not in benchdoc.DOC.read_text() and "| **0.500** |" in text
    assert _check(md, jd).returncode == 0


def test_sections_must_name_an_existing_script_with_a_doc_flag(small, tmp_path):
    small.write_text(SMALL.replace("benchmark_painting.py", "benchmark_nothing.py"), encoding="utf-8")
    r = _check(small, tmp_path)
    assert r.returncode == 1 and "names scripts/benchmark_nothing.py, which does not exist" in r.stderr
    small.write_text(SMALL.replace("benchmark_painting.py", "detection_docs.py"), encoding="utf-8")
    r = _check(small, tmp_path)
    assert r.returncode == 1 and "names scripts/detection_docs.py, which has no --doc flag" in r.stderr


def test_the_check_refuses_broken_markers_in_one_line(small, tmp_path):
    small.write_text(SMALL.replace("<!-- end painting -->\n", ""), encoding="utf-8")
    r = _check(small, tmp_path)
    assert r.returncode == 1 and r.stderr.count("\n") == 1 and str(small) in r.stderr and "end markers" in r.stderr


@pytest.mark.slow
def test_benchmark_lights_doc_writes_its_section_and_json(tmp_path, monkeypatch):
    """``--doc`` end to end on a small capture (the light estimate runs: 5-25 s): the paragraph holds what was
    just measured, the JSON its rows, and the check passes on the result (nothing else in the document moved)."""
    md, jd = tmp_path / "benchmarks.md", tmp_path / "json"
    shutil.copy(benchdoc.DOC, md)
    monkeypatch.setattr(benchdoc, "DOC", md)
    monkeypatch.setattr(benchdoc, "JSON_DIR", jd)
    import benchmark_lights
    before = read_section(md, "lights")
    benchmark_lights.main(["--lamps", "6", "--shape", "150", "200", "--seeds", "3", "--doc"])
    data = json.loads((jd / "lights.json").read_text())
    assert [r[:2] for r in data["rows"]] == [[6, 3]] and data["argv"][-1] == "--doc"
    text = read_section(md, "lights")
    assert text != before and text.startswith("**Light estimate with 6 lamps** (`.venv/bin/python "
                                              "scripts/benchmark_lights.py --lamps 6 --shape 150 200 --seeds 3`")
    assert f"directions max {data['rows'][0][5]:.2f} deg" in text
    assert (ROOT / "docs" / "benchmarks.md").read_text().replace(before, text) == md.read_text()
    assert _check(md, jd).returncode == 0


def test_a_json_without_its_section_fails_the_check(small, tmp_path):
    jd = tmp_path / "json"
    jd.mkdir()
    (jd / "painting.json").write_text(json.dumps({"rows": [{"seed": 1, "corner_err_px": 0.1, "max_residual_px": 0.1,
        "f1": 1.0, "twice": 0, "count_ratio": 1.0, "height_rms_um": 0.1, "height_overlap_rms_um": 0.1, "batch_s": 1,
        "tiles_sum_s": 2, "workers": 2, "stitch_total_s": 1, "stitch_maps_s": 1}]}))
    (jd / "gone.json").write_text("{}")
    r = _check(small, jd)
    assert r.returncode == 1 and "gone.json: no section 'gone'" in r.stderr
    assert "section 'painting' is stale" in r.stderr      # '| old table |' is not what the JSON renders


def test_benchmark_real_doc_keeps_the_rows_it_did_not_measure(tmp_path, doc_copy):
    """Without --diligent a run measures the split halves only: the DiLiGenT rows stay as the last run left them."""
    md, jd = doc_copy
    import benchmark_real
    before = json.loads((jd / "real.json").read_text())["rows"]
    icon = {"capture": "painted_icon_rti", "kind": "halves", "size": [402, 395], "lamps": 36,
            "methods": {"defaults": [2.5, 2.25, 1000], "plain LS": [2.6, 2.3, 1000]}}
    benchmark_real.write_doc_section([icon], ["--doc"])
    rows = json.loads((jd / "real.json").read_text())["rows"]
    assert rows[0] == icon and rows[1:] == before[1:]
    text = read_section(md, "real")
    assert "| painted_icon_rti (402 x 395), halves | 36 | **2.50** / 2.25 | 2.60 / 2.30 | - | - |\n" in text
    assert text.count("DiLiGenT ball") == 2 and "| **3.27** / 2.52 | 4.11 / 2.44 |" in text
    assert _check(md, jd).returncode == 0


def test_benchmark_protrusions_wand_doc_changes_only_its_rows(tmp_path, monkeypatch):
    """``--wand --doc`` on one small capture (a few seconds): the wand table's rows are this run's, every
    other byte of the document is as it was, and the JSON keeps each click's area ratio."""
    md, jd = tmp_path / "benchmarks.md", tmp_path / "json"
    shutil.copy(benchdoc.DOC, md)
    monkeypatch.setattr(benchdoc, "DOC", md)
    monkeypatch.setattr(benchdoc, "JSON_DIR", jd)
    import benchmark_protrusions
    before = read_section(md, "wand")
    benchmark_protrusions.main(["--wand", "--seeds", "0", "--shape", "240", "320", "--doc"])
    data = json.loads((jd / "wand.json").read_text())
    n = len(data["ratios"]["relative 0.5 (default)"][0])
    assert n > 0 and [r["clicks"] for r in data["rows"]] == [n] * 4
    text = read_section(md, "wand")
    assert text.splitlines()[:2] == before.splitlines()[:2] and f"| relative 0.5 (default) | {n} | " in text
    assert (ROOT / "docs" / "benchmarks.md").read_text().replace(before, text) == md.read_text()
    assert _check(md, jd).returncode == 0
    with pytest.raises(SystemExit):
        benchmark_protrusions.main(["--doc"])          # detection's tables are not written: refused


def test_benchmark_robustness_doc_replaces_the_runs_it_measured(tmp_path, doc_copy):
    """``--doc`` merges a run into the kept ones: a new estimated run of ``cupping`` seed 0 changes that row's
    cells only (its **x** marks from the targets), a stopped run reads ``stop``, and the check still passes."""
    md, jd = doc_copy
    import benchmark_robustness
    before = read_section(md, "robustness")
    run = {"row": "cupping", "mode": "estimated", "seed": 0, "lamps": 12, "normals_mean_deg": 0.61,
           "height_median_pct": 0.3, "light_mean_deg": 0.4, "height_unc95_pct": 12.4, "unc_covers": 1.0,
           "relative": 0.0, "error": None}
    stopped = {"row": "weave", "mode": "estimated", "seed": 2, "lamps": 12, "error": "UVPSInputError: lamps off"}
    benchmark_robustness.write_doc_section([run, stopped, dict(run, lamps=8, seed=1)], ["--doc"])
    text = read_section(md, "robustness")
    changed = [(a, b) for a, b in zip(before.splitlines(), text.splitlines()) if a != b]
    assert changed == [
        ("| cupping | 1.28 / 0.22 / 0.46 **x** | 0.294 | 5.1 / 0.4 / 0.6 **x** | 14 / 14 / 19 | 3 of 3 | 0 of 3 | "
         "0.155 / 0.2 |",
         "| cupping | 0.40 / 0.22 / 0.46 | 0.610 **x** | 0.3 / 0.4 / 0.6 | 12 / 14 / 19 | 3 of 3 | 0 of 3 | "
         "0.155 / 0.2 |"),
        ("| weave | 0.83 / 0.14 / 0.31 | 0.214 | 2.8 / 0.3 / 1.2 | 27 / 13 / 11 | 3 of 3 | 1 of 3 | 0.168 / 0.1 |",
         "| weave | 0.83 / 0.14 / stop (lamps off) **x** | 0.214 | 2.8 / 0.3 / stop **x** | 27 / 13 / stop | "
         "2 of 2 | 1 of 2 | 0.168 / 0.1 |")]
    assert _check(md, jd).returncode == 0


def test_benchmark_robustness_doc_writes_the_spheres_table_from_sphere_runs(tmp_path, doc_copy):
    """Sphere runs go to the spheres section only (robustness.json untouched); a mode not run yet on a row
    fills its ``-`` cell, worst of the seeds, **x** where normals miss 0.5 deg."""
    md, jd = doc_copy
    import benchmark_robustness
    rob = (jd / "robustness.json").read_text()
    run = {"row": "weave", "mode": "spheres_card", "lamps": 12, "cal_light_max_deg": 0.031, "cal_position_max_pct": 1.24,
           "normals_mean_deg": 0.2, "height_median_pct": 0.3, "error": None}
    written = benchmark_robustness.write_doc_section([dict(run, seed=0), dict(run, seed=1, normals_mean_deg=0.55)],
                                                     ["--doc"])
    assert written == [jd / "spheres.json"] and (jd / "robustness.json").read_text() == rob
    line = [x for x in read_section(md, "spheres").splitlines() if x.startswith("| weave |")]
    assert line == ["| weave | 0.04 / 1.0 / 0.173 / 0.20 | 0.03 / 1.2 / 0.550 / 0.30 **x** | 0.03 / 2.2 / 0.165 / 0.13 |"]
    assert _check(md, jd).returncode == 0


def test_benchmark_detection_doc_replaces_its_scenes_row(tmp_path, doc_copy):
    """A scene's seeds' scores become its row (worst seed per column, the 60-100 um recall pooled with its
    Wilson interval, **x** on a missed target); the other scenes' rows stay; the check passes."""
    md, jd = doc_copy
    import benchmark_detection
    before = read_section(md, "detection").splitlines()
    seed = {"precision": 0.99, "recall": 0.97, "f1": 0.98, "recall_200": 1.0, "width_err": 0.061, "fp_stroke": 1,
            "fp_other": 0, "bin_60": (28, 30, 28, 28)}
    scores = [dict(seed, seed=0), dict(seed, seed=1, f1=0.94, width_err=0.072, fp_stroke=0, bin_60=(30, 30, 30, 30))]
    benchmark_detection.write_doc_section(scores, "impasto", ["--scene", "impasto", "--doc"])
    after = read_section(md, "detection").splitlines()
    assert after[:3] == before[:3] and after[4:] == before[4:]
    # 58 of 60 pooled: 0.967, Wilson 95 % 0.886-0.991 (scipy.stats.binomtest)
    assert after[3] == ("| impasto | 0.990 | 0.970 | **0.940** **x** | **1.000** | **0.933** | 0.967 (0.89-0.99) | "
                        "7.2 % | 0-1 (1 of 1 on strokes) |")
    assert _check(md, jd).returncode == 0
    with pytest.raises(SystemExit):
        benchmark_detection.main(["--pipeline", "--doc"])      # the table is of the true maps: refused before running


def test_benchmark_spheres_real_doc_replaces_a_captures_row_keeping_its_label(tmp_path, doc_copy):
    """A capture measured again replaces its row (its source's description kept, bold within 1 deg); a new
    capture is appended under its name; the check passes."""
    md, jd = doc_copy
    import benchmark_spheres_real
    before = read_section(md, "spheres_real").splitlines()
    rows = [{"name": "psbox_lightprobe1", "centre_px": [536.84, 480.46], "radius_px": 423.61, "kind": "mirror",
             "median_deg": 0.874, "max_deg": 1.204, "time_s": 9.96},
            {"name": "mine", "centre_px": [10.0, 20.0], "radius_px": 5.0, "kind": "glossy", "time_s": 1.0}]
    benchmark_spheres_real.write_doc_section(rows, ["--doc"])
    after = read_section(md, "spheres_real").splitlines()
    assert after[:3] == before[:3] and after[4:6] == before[4:6]
    assert after[3] == ("| PSBox LightProbe-1 (github.com/yxiong/PSBox `data/LightProbe-1`, MIT; circle 535.9, 478.0, "
                        "421.1) | (536.8, 480.5), 423.6 | mirror | **0.87** / 1.20 | 10.0 |")
    assert after[6:] == ["| mine | (10.0, 20.0), 5.0 | glossy |  | 1.0 |"]
    assert _check(md, jd).returncode == 0


def test_benchmark_speed_doc_rows_render_as_the_table(tmp_path, monkeypatch):
    """The processes measured become the doc's rows (the read's own time, ratios to the read and the raw stack,
    the demo's peak RSS in GiB, stages in run order, ``uvps run``'s wall bold; with detection too); the other
    processes (``--ome-zarr``) are left out; --doc on another capture is refused before anything is made."""
    import benchmark_speed as bs
    gib = 2 ** 30
    ms = [bs.Measure("read the stack with tifffile", 0.4, 1.2, 0, inner_s=0.25, cpu_s=0.38),
          bs.Measure("uvps run", 11.26, 0.8, 0, cpu_s=16.89, stages={"additive": 1.04, "lights": 3.0, "integrate": 0.55}),
          bs.Measure("uvps run --regions auto", 15.0, 0.9, 0, cpu_s=18.0, stages={"protrusions": 4.0}),
          bs.Measure("uvps run --ome-zarr", 12.0, 0.9, 0),
          bs.Measure("uvps demo (600 x 800, 12 lights)", 8.04, 0.5, 0)]
    text = bs.render_doc({"rows": bs.doc_rows(ms, 0.25, 1.0 * gib)})
    assert text.splitlines()[2:] == [      # CPU / wall over the process's own wall (a demo not measured: blank)
        "| read the stack with tifffile | 0.25 | 1 | 0.95 | 1.20 | |",
        "| `uvps run` | **11.3** | 45 | 1.50 | 0.80 | additive 1.0, lights 3.0, integrate 0.6 |",
        "| `uvps run --regions auto` | 15.0 | 60 | 1.20 | 0.90 | protrusions 4.0 |",
        "| `uvps demo` (600 x 800, 12 lamps) | 8.0 | | | (0.50 GiB) | |"]
    with pytest.raises(SystemExit):
        bs.main(["--shape", "300", "400", "--work", str(tmp_path), "--doc"])
    assert not any(tmp_path.iterdir())


def test_benchmark_speed_load_doc_keeps_the_last_three_invocations(tmp_path, doc_copy):
    """At 1500 x 2000 each --doc adds its measures to the rows it measured: best (-worst) of the last 3, peak RSS
    as a range; a row not measured again stays as the table had it; the check passes."""
    import benchmark_speed as bs
    md, jd = doc_copy
    before = read_section(md, "speed_load").splitlines()
    gib = 2 ** 30
    for wall, rss in ((12.0, 0.61), (20.0, 0.64), (11.0, 0.62), (30.0, 0.60)):
        ms = [bs.Measure("uvps run", wall, rss, 0, cpu_s=wall / 2, stages={"additive": 1.0, "lights": wall / 4})]
        bs.write_load_doc(ms, 0.1, 0.25 * gib, ["--shape", "1500", "2000", "--doc"])
    after = read_section(md, "speed_load").splitlines()
    assert after[:3] == before[:3] and after[4:] == before[4:]
    # the last three: 20.0 / 0.64, 11.0 / 0.62, 30.0 / 0.60
    assert after[3] == "| `uvps run` (lamps estimated) | 11.0 (-30.0) | 110 | 0.50 | 0.60-0.64 | 2.40-2.56 | additive 1.0, lights 2.8 |"
    assert _check(md, jd).returncode == 0
