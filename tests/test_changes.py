"""uvps changes: registration on a known transform, matching with known changes, the
unchanged pair, bad inputs, the output contract; and the generator's later capture."""
import csv
import json

import numpy as np
import pytest

from uvps import cli
from uvps.core.changes import COLUMNS, NOISE_MODEL, change_uncertainty, classify_changes, pair_inflation, register
from uvps.commands.changes import date_record
from uvps.commands import COMMANDS
from uvps.files.io import read_tiff
from uvps.testing.synthetic import (LaterSpec, SyntheticSpec, make_capture_pair, similarity_matrix, write_capture,
                             write_truth_run)

SPEC = SyntheticSpec(shape=(300, 400), n_lights=8, protrusion_density_light=150.0,
                     protrusion_density_dark=30.0, seed=0)
POSE = dict(shift_px=(40.0, -25.0), rotation_deg=2.5, scale=1.015)


def _field_error(T_true, T_est, shape):
    yy, xx = np.mgrid[0:shape[0]:10, 0:shape[1]:10]
    p = np.stack([xx.ravel(), yy.ravel(), np.ones(xx.size)])
    e = (np.asarray(T_true) @ p)[:2] - (np.asarray(T_est) @ p)[:2]
    return float(np.sqrt(np.mean(np.sum(e * e, axis=0))))


@pytest.fixture(scope="module")
def pair():
    return make_capture_pair(SPEC, LaterSpec(seed=3, new_per_cm2=40.0, grown_fraction=0.3, **POSE))


@pytest.fixture(scope="module")
def same():
    return make_capture_pair(SPEC, LaterSpec.unchanged(seed=4, **POSE))


def _truth_run(folder, cap, px):
    return write_truth_run(cap, folder, pixel_size_um=px)


# ------------------------------------------------------------------------------------------------
# the generator


def test_pair_truth_is_consistent(pair):
    T = similarity_matrix(SPEC.shape, **POSE)
    np.testing.assert_allclose(pair.b_to_a, T)
    assert pair.b.spec.pixel_size_um == pytest.approx(15.0 * 1.015)
    c = pair.changes
    both = (c["id_a"] > 0) & (c["id_b"] > 0)
    xy_b = np.column_stack([c["x_px_b"][both], c["y_px_b"][both], np.ones(both.sum())])
    np.testing.assert_allclose((xy_b @ T.T)[:, :2], np.column_stack([c["x_px_a"][both], c["y_px_a"][both]]),
                               atol=1e-6)
    assert set(c["status"]) >= {"unchanged", "grown", "new"}
    g = c["status"] == "grown"
    assert np.all(c["width_um_b"][g] >= 1.19 * c["width_um_a"][g])
    assert np.all(np.isnan(c["width_um_b"][c["status"] == "gone"]))


def test_unchanged_pair_has_no_changes_and_the_same_a(pair, same):
    assert set(same.changes["status"]) == {"unchanged"}
    np.testing.assert_array_equal(pair.a.images, same.a.images)   # one A for every later capture


# ------------------------------------------------------------------------------------------------
# registration


def test_register_known_transform(pair):
    reg = register(pair.a.albedo, pair.b.albedo)
    assert reg.model == "similarity"
    assert reg.matches >= 50
    assert _field_error(pair.b_to_a, reg.b_to_a, SPEC.shape) < 0.1
    assert reg.scale == pytest.approx(1.015, abs=1e-3)
    assert reg.rotation_deg == pytest.approx(2.5, abs=0.02)


def test_register_refuses_two_different_regions(pair):
    other = make_capture_pair(SPEC, LaterSpec.unchanged(seed=4), seed=99)
    with pytest.raises(ValueError, match="too few"):
        register(pair.a.albedo, other.b.albedo)


# ------------------------------------------------------------------------------------------------
# the command on run folders made from the truth


@pytest.fixture(scope="module")
def truth_runs(pair, same, tmp_path_factory):
    d = tmp_path_factory.mktemp("truth_runs")
    return {"a": _truth_run(d / "a", pair.a, 15.0), "b": _truth_run(d / "b", pair.b, 15.0 * 1.015),
            "same": _truth_run(d / "same", same.b, 15.0 * 1.015), "root": d}


def _read_changes(out):
    with open(out / "changes.csv", newline="") as fh:
        return list(csv.DictReader(fh))


def test_changes_known_changes_and_output_contract(pair, truth_runs):
    out = truth_runs["root"] / "out"
    assert cli.main(["changes", str(truth_runs["a"]), str(truth_runs["b"]), "-o", str(out)]) == 0
    reg = json.loads((out / "registration.json").read_text())
    assert {"b_to_a", "model", "matches", "rms_px"} <= set(reg)
    assert np.shape(reg["b_to_a"]) == (3, 3)
    assert _field_error(pair.b_to_a, reg["b_to_a"], SPEC.shape) < 0.1
    with open(out / "changes.csv", newline="") as fh:
        assert tuple(next(csv.reader(fh))) == COLUMNS
    rows = _read_changes(out)
    change, px = read_tiff(out / "height_change.tif")
    assert change.shape == SPEC.shape and px == pytest.approx(15.0)
    run = json.loads((out / "run.json").read_text())
    assert run["command"] == "changes" and run["diagnostics"]["pixel_size"]["rescaled"]
    assert any("pixel sizes differ" in w for w in run["warnings"])
    assert (out / "report.html").is_file() and (out / "figures" / "changes_height.png").is_file()
    assert (out / "figures" / "changes_map.png").is_file()
    page = (out / "report.html").read_text()
    assert "changes_map.png" in page and "The two dates: lamps and calibration" in page
    # every true status among the rows found, by A's id (B's for new ones)
    t = pair.changes
    truth_by_a = {int(i): s for i, s in zip(t["id_a"], t["status"]) if i > 0}
    truth_by_b = {int(i): s for i, s in zip(t["id_b"], t["status"]) if i > 0}
    agree = 0
    for r in rows:
        true = truth_by_a[int(r["id_a"])] if r["id_a"] else truth_by_b[int(r["id_b"])]
        found = r["status"]
        agree += found == true or (true == "grown" and found == "unchanged")   # small growths
        assert not (true == "unchanged" and found != "unchanged"), r
        if found in ("new", "gone"):
            assert (r["id_a"] == "") == (found == "new") and (r["id_b"] == "") == (found == "gone")
    statuses = [r["status"] for r in rows]
    assert statuses.count("new") >= 0.8 * sum(s == "new" for s in truth_by_b.values() if s == "new") - 1
    assert statuses.count("grown") >= 3
    assert agree == len(rows)


def test_unchanged_pair_flags_nothing(truth_runs):
    out = truth_runs["root"] / "out_same"
    assert cli.main(["changes", str(truth_runs["a"]), str(truth_runs["same"]), "-o", str(out)]) == 0
    rows = _read_changes(out)
    assert len(rows) > 20
    assert all(r["status"] == "unchanged" for r in rows)


# ------------------------------------------------------------------------------------------------
# bad input


def test_different_regions_one_line_exit_1(pair, truth_runs, tmp_path, capsys):
    other = make_capture_pair(SPEC, LaterSpec.unchanged(seed=4), seed=99)
    b = _truth_run(tmp_path / "other", other.a, 15.0)
    out = tmp_path / "out"
    assert cli.main(["changes", str(truth_runs["a"]), str(b), "-o", str(out)]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len([line for line in err if "too few" in line]) == 1
    assert not out.exists()                 # nothing written, no alignment invented


def test_run_without_detection_names_the_file(truth_runs, tmp_path, capsys):
    b = tmp_path / "nodetect"
    b.mkdir()
    for f in ("albedo.tif", "depth.tif"):
        (b / f).write_bytes((truth_runs["b"] / f).read_bytes())
    assert cli.main(["changes", str(truth_runs["a"]), str(b), "-o", str(tmp_path / "out")]) == 1
    err = capsys.readouterr().err
    assert "protrusions.csv" in err and str(b) in err


def _table(x, y, w, h):
    n = len(x)
    return {"id": np.arange(1, n + 1), "x_px": np.asarray(x, float), "y_px": np.asarray(y, float),
            "width_um": np.asarray(w, float), "height_um": np.asarray(h, float)}


def _classify(a, b, **kw):
    rows, _, left, unc = classify_changes(a, b, np.eye(3), shape_a=(100, 200), shape_b=(100, 200),
                                          pixel_size_um=15.0, **kw)
    return rows, left, unc


def test_classify_uncertainty_decides_grown_and_shrunk():
    a = _table([40.0, 100.0, 160.0], [50.0] * 3, [150.0] * 3, [40.0] * 3)
    b = _table([40.0, 100.0, 160.0], [50.0] * 3, [153.0, 190.0, 150.0], [41.0, 40.0, 30.0])
    rows, left, _ = _classify(a, b)
    assert rows["status"].tolist() == ["unchanged", "grown", "shrunk"]
    assert rows["d_width_um"].tolist() == pytest.approx([3.0, 40.0, 0.0])
    assert left == {"a": 0, "b": 0}
    # the columns' uncertainty is the model's, and the significance the larger of the two z-scores
    sw, sh = change_uncertainty(rows["width_um_a"], rows["width_um_b"], rows["height_um_a"], rows["height_um_b"],
                                pixel_size_um_a=15.0, pixel_size_um_b=15.0)
    np.testing.assert_allclose(rows["d_width_sd_um"], sw)
    np.testing.assert_allclose(rows["d_height_sd_um"], sh)
    z = np.maximum(np.abs(rows["d_width_um"] / sw), np.abs(rows["d_height_um"] / sh))
    np.testing.assert_allclose(rows["significance"], z)
    assert rows["significance"][0] < 4 < rows["significance"][1]


def test_uncertainty_grows_with_the_peak_sampling_and_the_pixel():
    # a narrow tall protrusion's height is sampled at another phase when the camera moves:
    # its uncertainty is the larger, and so is a coarser pixel's width uncertainty
    _, sh_narrow = change_uncertainty(60.0, 60.0, 20.0, 20.0, pixel_size_um_a=15.0, pixel_size_um_b=15.0)
    _, sh_wide = change_uncertainty(300.0, 300.0, 20.0, 20.0, pixel_size_um_a=15.0, pixel_size_um_b=15.0)
    assert sh_narrow > 3 * sh_wide
    sw_fine, _ = change_uncertainty(100.0, 100.0, 10.0, 10.0, pixel_size_um_a=5.0, pixel_size_um_b=5.0)
    sw_coarse, _ = change_uncertainty(100.0, 100.0, 10.0, 10.0, pixel_size_um_a=20.0, pixel_size_um_b=20.0)
    assert sw_coarse > sw_fine
    assert NOISE_MODEL.source       # the model says where it was fitted


def test_pair_inflation_measures_a_noisier_pair_and_ignores_the_grown():
    rng = np.random.default_rng(0)
    assert pair_inflation(rng.normal(0, 1, 400)) == pytest.approx(1.0, abs=0.1)
    z = np.concatenate([rng.normal(0, 2.0, 300), rng.uniform(15, 30, 100)])   # 25 % grown far out
    assert pair_inflation(z) == pytest.approx(2.0, rel=0.15)
    assert pair_inflation(rng.normal(0, 0.3, 400)) == 1.0          # never below the model


def test_new_and_gone_and_the_frame_edge():
    a = _table([40.0, 100.0, 160.0], [50.0, 50.0, 1.0], [90.0] * 3, [20.0] * 3)
    b = _table([40.0, 130.0, 160.0], [50.0, 20.0, 1.0], [90.0] * 3, [20.0] * 3)
    rows, left, _ = _classify(a, b)
    st = dict(zip(zip(rows["id_a"].tolist(), rows["id_b"].tolist()), rows["status"].tolist()))
    assert st == {(1, 1): "unchanged", (2, 0): "gone", (0, 2): "new"}
    assert left == {"a": 1, "b": 1}     # the protrusion cut by the frame's edge, at both dates


def test_merged_and_split_neighbours():
    # two neighbours of A became one wider protrusion in B between them: both merged into it
    a = _table([94.0, 106.0, 40.0], [50.0, 50.0, 50.0], [120.0, 120.0, 90.0], [20.0, 20.0, 20.0])
    b = _table([100.0, 40.0], [50.0, 50.0], [300.0, 90.0], [25.0, 20.0])
    rows, _, _ = _classify(a, b)
    merged = rows["status"] == "merged"
    assert merged.sum() == 2 and set(rows["id_a"][merged].tolist()) == {1, 2}
    assert set(rows["id_b"][merged].tolist()) == {1}
    assert rows["status"][rows["id_a"] == 3].tolist() == ["unchanged"]
    # the other way round: one split into two
    rows, _, _ = _classify(b, a)
    split = rows["status"] == "split"
    assert split.sum() == 2 and set(rows["id_b"][split].tolist()) == {1, 2}
    assert set(rows["id_a"][split].tolist()) == {1}
    assert not np.isin(rows["status"], ("new", "gone")).any()


def test_widths_only_leaves_heights_out():
    a = _table([40.0, 100.0], [50.0] * 2, [150.0] * 2, [40.0] * 2)
    b = _table([40.0, 100.0], [50.0] * 2, [150.0, 150.0], [40.0, 80.0])
    rows, _, unc = _classify(a, b, heights=False)
    assert rows["status"].tolist() == ["unchanged", "unchanged"]
    assert np.isnan(rows["d_height_um"]).all() and not unc["heights"]


# ------------------------------------------------------------------------------------------------
# end to end: the pipeline's runs (known lights) of the changed pair


@pytest.mark.filterwarnings("ignore::RuntimeWarning")
@pytest.mark.slow
def test_end_to_end_with_detection(pair, tmp_path):
    runs = {}
    for name, cap in (("a", pair.a), ("b", pair.b)):
        write_capture(cap, tmp_path / f"cap_{name}", truth=False)
        runs[name] = tmp_path / f"run_{name}"
        COMMANDS["run"]({"images": [str(tmp_path / f"cap_{name}")]},
                        {"lights": str(tmp_path / f"cap_{name}" / "lights_positions_mm.csv"), "detect": True},
                        runs[name])
    out = tmp_path / "out"
    res = COMMANDS["changes"]({"run_a": str(runs["a"]), "run_b": str(runs["b"])}, {}, out)
    assert res.diagnostics["registration"]["rms_px"] < 0.3
    reg = json.loads((out / "registration.json").read_text())
    assert _field_error(pair.b_to_a, reg["b_to_a"], SPEC.shape) < 0.3
    counts = res.diagnostics["counts"]
    assert counts["new"] >= 3 and counts["grown"] >= 2
    assert "registration:" in res.text


# ------------------------------------------------------------------------------------------------
# the reversed pair (shrunk, gone), each date's calibration, the relative relief


def test_reversed_pair_gives_shrunk_and_gone(pair, truth_runs):
    out = truth_runs["root"] / "out_reversed"
    assert cli.main(["changes", str(truth_runs["b"]), str(truth_runs["a"]), "-o", str(out)]) == 0
    rows = _read_changes(out)
    t = pair.changes
    truth_by_b = {int(i): s for i, s in zip(t["id_b"], t["status"]) if i > 0}   # B is now the earlier date
    statuses = {"shrunk": 0, "gone": 0}
    for r in rows:
        if r["id_a"]:
            true = truth_by_b[int(r["id_a"])]
            assert r["status"] in {"grown": ("shrunk", "unchanged"), "new": ("gone",),
                                   "unchanged": ("unchanged",)}[true], (true, r)
        if r["status"] in statuses:
            statuses[r["status"]] += 1
    assert statuses["shrunk"] >= 3 and statuses["gone"] >= 3


def _with_run_json(src, dst, **fields):
    import shutil
    shutil.copytree(src, dst)
    log = {"version": "0", "command": "run", "params": {"lights": "lamps.csv"},
           "diagnostics": {"lights": {"source": "positions", "n_lights": 8}}, **fields}
    (dst / "run.json").write_text(json.dumps(log))
    return dst


def test_each_dates_calibration_is_recorded(truth_runs, tmp_path):
    b = _with_run_json(truth_runs["same"], tmp_path / "b_cal", relief={"scale": "absolute", "lamps": "calibration",
                                                                       "reason": "spheres pin the lamps"})
    rec = date_record(b)
    assert rec["lamps"] == "positions" and rec["lights_file"] == "lamps.csv" and rec["relief"]["scale"] == "absolute"
    from uvps.files.runfolder import relief_of
    assert date_record(truth_runs["a"]) == {"run_json": False, "lamps": "unknown", "relief": relief_of({})}
    assert relief_of({})["scale"] == "absolute"
    out = tmp_path / "out"
    assert cli.main(["changes", str(truth_runs["a"]), str(b), "-o", str(out)]) == 0
    run = json.loads((out / "run.json").read_text())
    assert run["diagnostics"]["dates"]["b"]["lamps"] == "positions"
    assert run["diagnostics"]["dates"]["a"]["run_json"] is False
    assert "lamps.csv" in (out / "report.html").read_text()


def test_relative_relief_refuses_height_growth(truth_runs, tmp_path, capsys):
    b = _with_run_json(truth_runs["same"], tmp_path / "b_rel",
                       relief={"scale": "relative", "lamps": "estimated",
                               "reason": "the lamps' elevation is not pinned by the images."})
    out = tmp_path / "out"
    assert cli.main(["changes", str(truth_runs["a"]), str(b), "-o", str(out)]) == 1
    err = [line for line in capsys.readouterr().err.strip().splitlines() if line.strip()]
    assert len(err) == 1
    assert "relative relief" in err[0] and str(b) in err[0]
    assert "uvps calibrate" in err[0] and "--calibration" in err[0] and "--lights" in err[0]
    assert not out.exists()
    # widths and counts alone are still compared: heights empty, no height map
    assert cli.main(["changes", str(truth_runs["a"]), str(b), "-o", str(out), "--widths-only"]) == 0
    rows = _read_changes(out)
    assert rows and all(r["d_height_um"] == "" and r["height_um_b"] == "" for r in rows)
    assert all(r["status"] == "unchanged" for r in rows)
    assert not (out / "height_change.tif").exists()


# ------------------------------------------------------------------------------------------------
# protrusions a few pixels wide: their repeatability ("alarms that hold")

#: Protrusions 40-90 um wide (3-6 px of 15 um), the camera moved: a pose and seed the model was not fitted on.
SMALL = SyntheticSpec(shape=(450, 600), n_lights=12, width_um=(40.0, 90.0), protrusion_density_light=150.0,
                      protrusion_density_dark=30.0, seed=0)
SMALL_POSE = dict(shift_px=(37.3, -21.6), rotation_deg=1.5, scale=1.0)


def test_uncertainty_grows_for_protrusions_a_few_pixels_wide():
    from uvps.core.changes import NOISE_MODEL_FIXED_PEAK
    # the height's uncertainty, as a share of the height, grows as the protrusion spans fewer pixels,
    # faster than the fixed-exponent model's; the width's too (its outline on fewer pixels)
    w = np.array([60.0, 75.0, 150.0, 300.0])
    sw, sh = change_uncertainty(w, w, 0.2 * w, 0.2 * w, pixel_size_um_a=15.0, pixel_size_um_b=15.0)
    rel = sh / (0.2 * w)
    assert np.all(np.diff(rel) < 0) and np.all(np.diff(sw) <= 0)
    assert rel[0] > 4 * rel[2]
    sw_old, sh_old = change_uncertainty(w, w, 0.2 * w, 0.2 * w, pixel_size_um_a=15.0, pixel_size_um_b=15.0,
                                        model=NOISE_MODEL_FIXED_PEAK)
    assert sh[0] > 1.2 * sh_old[0] and sw[0] > 1.3 * sw_old[0]
    # what it is in pixels, not in um: the same protrusion at a 3x finer pixel repeats as a wide one
    _, sh_fine = change_uncertainty(60.0, 60.0, 12.0, 12.0, pixel_size_um_a=5.0, pixel_size_um_b=5.0)
    _, sh_wide = change_uncertainty(180.0, 180.0, 36.0, 36.0, pixel_size_um_a=15.0, pixel_size_um_b=15.0)
    assert sh_fine == pytest.approx(sh_wide / 3.0, rel=0.05)


@pytest.fixture(scope="module")
def small_runs(tmp_path_factory):
    """Run folders (``uvps run --detect``, the true lamp positions) of A, an unchanged B seen by a
    moved camera under other lamps, and a B where 30 % of the lone protrusions grew."""
    root = tmp_path_factory.mktemp("small")
    same = make_capture_pair(SMALL, LaterSpec.unchanged(seed=5, **SMALL_POSE))
    grown = make_capture_pair(SMALL, LaterSpec(seed=6, grown_fraction=0.3, new_per_cm2=0.0, gone_fraction=0.0,
                                               **SMALL_POSE))
    runs = {}
    for name, cap in (("a", same.a), ("same", same.b), ("grown", grown.b)):
        write_capture(cap, root / f"cap_{name}", truth=False)
        runs[name] = root / f"run_{name}"
        COMMANDS["run"]({"images": [str(root / f"cap_{name}")]},
                        {"lights": str(root / f"cap_{name}" / "lights_positions_mm.csv"), "detect": True},
                        runs[name])
    return runs, grown.changes


@pytest.mark.filterwarnings("ignore::RuntimeWarning")
@pytest.mark.slow
def test_small_protrusions_moved_camera_repeat_as_the_model_says(small_runs):
    from uvps.commands.changes import compute_changes
    from uvps.core.changes import NOISE_MODEL_FIXED_PEAK
    runs, _ = small_runs

    def decide(model):
        res = compute_changes(runs["a"], runs["same"], noise_model=model)
        rows = res["rows"]
        matched = np.isin(rows["status"], ("grown", "shrunk", "unchanged"))
        small = matched & (np.fmin(rows["width_um_a"], rows["width_um_b"]) < 80)
        return (int(np.isin(rows["status"], ("grown", "shrunk")).sum()), int(matched.sum()), int(small.sum()),
                res["diagnostics"]["uncertainty"])

    n_flag, n, n_small, unc = decide(NOISE_MODEL)
    assert n >= 40 and n_small >= 30          # most of them 3-5 px wide
    assert n_flag <= 0.02 * n
    # the changes of an unchanged pair are as large as the model says (the robust sd of their
    # z-scores, changes.pair_inflation): the pair need not widen the model to hold
    assert unc["inflation_width"] < 1.2 and unc["inflation_height"] < 1.2
    # the model whose terms did not grow with the size in pixels said the changes were smaller than
    # they are: it held only by widening every uncertainty of the pair
    _, _, _, unc_old = decide(NOISE_MODEL_FIXED_PEAK)
    assert unc_old["inflation_width"] > 1.2 and unc_old["inflation_height"] > 1.2


@pytest.mark.filterwarnings("ignore::RuntimeWarning")
@pytest.mark.slow
def test_small_protrusions_that_grew_are_still_found(small_runs):
    from uvps.commands.changes import compute_changes
    runs, truth = small_runs
    rows = compute_changes(runs["a"], runs["grown"])["rows"]
    status = dict(zip(truth["id_a"].tolist(), truth["status"].tolist()))
    grew = (truth["status"] == "grown") & (((truth["width_um_b"] - truth["width_um_a"]) >= 20)
                                           | ((truth["height_um_b"] - truth["height_um_a"]) >= 5))
    clear = dict(zip(truth["id_a"].tolist(), grew.tolist()))
    width = dict(zip(truth["id_a"].tolist(), truth["width_um_a"].tolist()))
    # each row's true protrusion: the nearest of the truth's A positions within 8 px (the run's ids are
    # its own detection's)
    tx, ty = truth["x_px_a"], truth["y_px_a"]
    ids = []
    for x, y in zip(rows["x_px_a"], rows["y_px_a"]):
        d = np.where(np.isfinite(tx), np.hypot(tx - x, ty - y), np.inf)
        ids.append(int(truth["id_a"][np.argmin(d)]) if np.isfinite(x) and d.min() < 8 else 0)
    seen = [(i, s) for i, s in zip(ids, rows["status"]) if i > 0 and clear.get(i)]
    found = [i for i, s in seen if s == "grown"]
    small = [i for i, _ in seen if width[i] < 80]
    assert len(seen) >= 10 and len(small) >= 5
    assert len(found) >= 0.85 * len(seen)
    assert sum(i in found for i in small) >= 0.75 * len(small)
    # no unchanged protrusion called grown
    assert not any(s == "grown" and status.get(i) != "grown" for i, s in zip(ids, rows["status"]))
