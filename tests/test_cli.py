"""The whole pipeline through the real `uvps` command (a subprocess) and every bad input."""
import hashlib
import csv
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import tifffile

from uvps import cli
from uvps.testing.synthetic import make_capture, write_capture

PX = 15.0


def uvps(*args, cwd=None):
    return subprocess.run([sys.executable, "-m", "uvps", *map(str, args)], capture_output=True, text=True,
                          cwd=cwd, timeout=600)


@pytest.fixture(scope="module")
def capture_dir(tmp_path_factory):
    cap = make_capture(shape=(240, 320), n_lights=8, seed=5)
    folder = tmp_path_factory.mktemp("cap")
    write_capture(cap, folder)
    return cap, folder


def _images(folder):
    return sorted(Path(folder).glob("uv_*.tif"))


def _angle(a, b):
    return np.degrees(np.arccos(np.clip(np.sum(a * b, -1), -1, 1)))


def _digest(folder):
    return {p.name: hashlib.sha256(p.read_bytes()).hexdigest() for p in sorted(Path(folder).rglob("*")) if p.is_file()}


def test_run_with_calibrated_lights(capture_dir, tmp_path):
    cap, folder = capture_dir
    before = _digest(folder)
    out = tmp_path / "run"
    r = uvps("run", *_images(folder), "-o", out, "--lights", folder / "lights_positions_mm.csv")
    assert r.returncode == 0, r.stderr
    assert _digest(folder) == before  # inputs untouched
    with tifffile.TiffFile(out / "normals.tif") as t:
        normals = np.moveaxis(t.asarray(), 0, -1)
        assert t.imagej_metadata["unit"] == "micron"
        xres = t.pages[0].tags["XResolution"].value
        assert abs(xres[1] / xres[0] - PX) < 1e-6
    assert _angle(normals, cap.normals).mean() < 1.0
    depth = tifffile.imread(out / "depth.tif")
    h = cap.height_um - np.median(cap.height_um)
    assert np.corrcoef(depth.ravel(), h.ravel())[0, 1] > 0.9
    albedo = tifffile.imread(out / "albedo.tif")
    assert albedo.shape == (3, 240, 320)
    assert tifffile.imread(out / "gradients.tif").shape == (2, 240, 320)
    assert not (out / "flatfield").exists()      # only with --flatfield-images (below), or `uvps flatfield`
    run = json.loads((out / "run.json").read_text())
    assert {i["sha256"] for i in run["inputs"]} == {hashlib.sha256(p.read_bytes()).hexdigest() for p in _images(folder)}
    assert set(run["timings_s"]) >= {"lights", "normals", "integrate"}
    lights = json.loads((out / "lights.json").read_text())
    assert lights["source"] == "positions"
    np.testing.assert_allclose([l["position_mm"] for l in lights["lights"]], cap.light_positions_mm, rtol=1e-5)
    E = np.array([l["intensity"] for l in lights["lights"]])
    np.testing.assert_allclose(E / E.mean(), cap.intensities / cap.intensities.mean(), rtol=0.03)


def test_flatfield_images_with_the_flag_or_later_from_the_run_folder_are_the_same(capture_dir, tmp_path):
    """`run` writes flatfield/ only with --flatfield-images; `uvps flatfield` into a run folder without
    them writes the same files from the run's lights.json."""
    cap, folder = capture_dir
    lamps = folder / "lights_positions_mm.csv"
    r = uvps("run", folder, "-o", tmp_path / "with", "--lights", lamps, "--flatfield-images")
    assert r.returncode == 0, r.stderr
    with_flag = sorted((tmp_path / "with" / "flatfield").glob("*.tif"))
    assert len(with_flag) == 8
    r = uvps("run", folder, "-o", tmp_path / "later", "--lights", lamps)
    assert r.returncode == 0 and not (tmp_path / "later" / "flatfield").exists()
    r = uvps("flatfield", folder, "-o", tmp_path / "later")
    assert r.returncode == 0, r.stderr
    later = sorted((tmp_path / "later" / "flatfield").glob("*.tif"))
    assert [p.name for p in later] == [p.name for p in with_flag]
    for a, b in zip(with_flag, later):
        np.testing.assert_array_equal(tifffile.imread(a), tifffile.imread(b))
    assert json.loads((tmp_path / "with" / "run.json").read_text())["params"]["flatfield_images"] is True
    # a run without the flags removes the flat-fielded images and OME-Zarr stores of an earlier run
    r = uvps("run", folder, "-o", tmp_path / "with", "--lights", lamps, "--flatfield-images", "--ome-zarr")
    assert r.returncode == 0 and (tmp_path / "with" / "depth.ome.zarr").is_dir()
    r = uvps("run", folder, "-o", tmp_path / "with", "--lights", lamps)
    assert r.returncode == 0, r.stderr
    left = sorted(p.name for p in (tmp_path / "with").iterdir())
    assert "flatfield" not in left and not [n for n in left if n.endswith(".zarr")] and "depth.tif" in left


@pytest.mark.slow
def test_run_estimating_lights_with_detection_and_report(capture_dir, tmp_path):
    cap, folder = capture_dir
    out = tmp_path / "run"
    r = uvps("run", folder, "-o", out, "--regions", "auto")
    assert r.returncode == 0, r.stderr
    normals = np.moveaxis(tifffile.imread(out / "normals.tif"), 0, -1)
    # a 3.6 x 4.8 mm field: the lamps' distance is weakly observable, a bowl of a few degrees
    # remains (scripts/benchmark_core.py measures the 24 x 18 mm case)
    assert _angle(normals, cap.normals).mean() < 4.0
    lights = json.loads((out / "lights.json").read_text())
    assert lights["source"] == "estimated" and len(lights["residual_history"]) > 3
    # whether the per-light refinement converged is recorded; the lamps' uncertainty is, and the run
    # warns (once, saying what to do) only when it makes the heights uncertain beyond 5 %: on a
    # 3.6 x 4.8 mm field it does
    run = json.loads((out / "run.json").read_text())
    assert isinstance(run["diagnostics"]["lights"]["refinement_converged"], bool)
    unc = run["diagnostics"]["lights"]["height_uncertainty_relative"]
    # the reported direction uncertainty is conservative, not decoration: it covers the true error
    # of every lamp's direction at the field's centre (on this 3.6 x 4.8 mm field: true errors of
    # 6-16 deg against 16-24 deg reported)
    est = np.array([l["position_mm"] for l in lights["lights"]])
    true_err = _angle(est / np.linalg.norm(est, axis=1, keepdims=True),
                      cap.light_positions_mm / np.linalg.norm(cap.light_positions_mm, axis=1, keepdims=True))
    reported = np.array(lights["uncertainty"]["direction_deg"])
    assert len(reported) == len(lights["lights"]) and np.all(reported > 0)
    assert np.all(true_err < reported)
    assert unc > 0.05
    # beyond 20 % (95 %) the heights are relative, above 100 % (standard) their scale is not determined
    # (on this field it is one or the other depending on how far the refinement crawls along the valley)
    warned = [w for w in run["warnings"] if "heights are relative" in w or "scale is not determined" in w]
    assert len(warned) == 1 and "measured lamp positions" in warned[0]
    assert warned[0].startswith("heights are relative") == (unc <= 1.0), warned[0]
    assert len([ln for ln in r.stderr.splitlines() if ln.startswith("warning:")
                and ("heights are relative" in ln or "scale is not determined" in ln)]) == 1, r.stderr
    assert run["relief"]["scale"] == "relative"
    for f in ("protrusions.csv", "protrusions_labels.tif", "regions.csv", "regions_labels.tif", "report.html"):
        assert (out / f).is_file(), f
    assert "report:" in r.stdout
    # what it found, in one line, as regions.csv has it (its "all" row not counted twice)
    with open(out / "regions.csv", newline="", encoding="utf-8") as fh:
        areas = [row for row in csv.DictReader(fh)]
    total = next(row for row in areas if row["label"] == "all")
    n_areas = len(areas) - 1
    found = [ln for ln in r.stdout.splitlines() if ln.startswith("found: ")]
    assert found == [f"found: {total['count']} protrusion{'s' if total['count'] != '1' else ''} in "
                     f"{n_areas} colour area{'s' if n_areas != 1 else ''} "
                     f"({float(total['area_cm2']):.3g} cm\u00b2, {float(total['density_per_cm2']):.3g} per cm\u00b2)"], r.stdout
    with open(out / "protrusions.csv", newline="", encoding="utf-8") as fh:
        assert int(total["count"]) == len(list(csv.DictReader(fh)))


def test_lp_directions_give_far_lights(capture_dir, tmp_path):
    cap, folder = capture_dir
    out = tmp_path / "run"
    r = uvps("normals", folder, "-o", out, "--lights", folder / "lights.lp")
    assert r.returncode == 0, r.stderr
    lights = json.loads((out / "lights.json").read_text())
    assert lights["mode"] == "far"
    normals = np.moveaxis(tifffile.imread(out / "normals.tif"), 0, -1)
    assert _angle(normals, cap.normals).mean() < 5.0  # near lights solved as far: a few degrees


def _bad_cases(folder, tmp):
    imgs = _images(folder)
    other = tmp / "other"
    other.mkdir()
    small = other / "small.tif"
    tifffile.imwrite(small, np.ones((100, 100, 3), np.uint16) * 1000)
    eight = other / "eight.tif"
    tifffile.imwrite(eight, np.ones((240, 320, 3), np.uint8) * 100)
    junk = other / "junk.tif"
    junk.write_bytes(b"not an image at all")
    trunc = other / "trunc.tif"
    trunc.write_bytes(imgs[0].read_bytes()[:5000])
    black = other / "black.tif"
    tifffile.imwrite(black, np.zeros((240, 320, 3), np.uint16))
    satur = other / "sat.tif"
    tifffile.imwrite(satur, np.full((240, 320, 3), 65535, np.uint16))
    lp_count = other / "count.lp"
    lines = (folder / "lights.lp").read_text().splitlines()
    lp_count.write_text("\n".join([str(int(lines[0]) + 1)] + lines[1:]) + "\n")
    lp_missing = other / "missing.lp"
    lp_missing.write_text("\n".join(lines[:2] + ["nothere.tif 0 0 1"] + lines[3:]) + "\n")
    empty_mask = other / "mask.tif"
    tifffile.imwrite(empty_mask, np.zeros((240, 320), np.uint8))
    a_file = other / "a_file"
    a_file.write_text("x")
    flat = other / "flat"
    flat.mkdir()
    for k, d in enumerate([(0.5, 0, 0.866), (-0.25, 0.433, 0.866), (-0.25, -0.433, 0.866)]):
        tifffile.imwrite(flat / f"f{k}.tif", np.full((240, 320), 20000, np.uint16),
                         resolution=(1 / PX, 1 / PX), imagej=True, metadata={"unit": "micron"})
    o = tmp / "out"
    return {
        "fewer than 3 images": (["run", imgs[0], imgs[1], "-o", o], "3"),
        "different sizes": (["run", *imgs[:3], small, "-o", o], "small.tif"),
        "different bit depths": (["run", *imgs[:3], eight, "-o", o], "eight.tif"),
        "non-image": (["run", *imgs[:3], junk, "-o", o], "junk.tif"),
        "truncated": (["run", *imgs[:3], trunc, "-o", o], "trunc.tif"),
        "all black": (["run", *imgs[:3], black, "-o", o], "black.tif"),
        "saturated": (["run", *imgs[:3], satur, "-o", o], "sat.tif"),
        "lp wrong count": (["run", folder, "-o", o, "--lights", lp_count], "count.lp"),
        "lp missing file": (["run", folder, "-o", o, "--lights", lp_missing], "nothere.tif"),
        "empty mask": (["run", folder, "-o", o, "--mask", empty_mask], "mask"),
        "pixel size <= 0": (["run", folder, "-o", o, "--pixel-size-um", "0"], "pixel_size_um"),
        "output is a file": (["run", folder, "-o", a_file], "a_file"),
        "no drop-off": (["run", flat, "-o", o], "calibrated lights"),
    }


CASES = ["fewer than 3 images", "different sizes", "different bit depths", "non-image", "truncated", "all black",
         "saturated", "lp wrong count", "lp missing file", "empty mask", "pixel size <= 0", "output is a file",
         "no drop-off"]


@pytest.mark.parametrize("case", CASES)
def test_bad_input_one_line_exit_1_nothing_written(case, capture_dir, tmp_path, capsys):
    """Every bad input through the CLI's own entry point (in this process: the same code a `uvps`
    process runs, without its 0.8 s start-up); the first case also through a real process."""
    cap, folder = capture_dir
    args, needle = _bad_cases(folder, tmp_path)[case]
    before = _digest(folder)
    if case == CASES[0]:
        r = uvps(*args)
        code, stderr = r.returncode, r.stderr
    else:
        code = cli.main([str(a) for a in args])
        stderr = capsys.readouterr().err
    assert code == 1, (code, stderr)
    err = [l for l in stderr.splitlines() if "error" in l]
    assert len(err) == 1 and needle in err[0], stderr
    assert not (tmp_path / "out").exists()
    assert not list(tmp_path.glob(".out.tmp-*"))
    assert _digest(folder) == before


@pytest.mark.slow
def test_integrate_and_relight_on_a_run_folder(capture_dir, tmp_path):
    cap, folder = capture_dir
    out = tmp_path / "run"
    assert uvps("normals", folder, "-o", out, "--lights", folder / "lights_positions_mm.csv").returncode == 0
    assert not (out / "depth.tif").exists()
    r = uvps("integrate", "-o", out, "--integration", "dct")
    assert r.returncode == 0, r.stderr
    assert tifffile.imread(out / "depth.tif").shape == (240, 320)
    r = uvps("relight", "-o", out, "--azimuth-deg", "0", "--elevation-deg", "20")
    assert r.returncode == 0, r.stderr
    rel = tifffile.imread(out / "relight.tif")
    assert rel.shape == (3, 240, 320) and np.isfinite(rel).mean() > 0.99


def test_version_and_help():
    r = uvps("--version")
    assert r.returncode == 0 and r.stdout.startswith("uvps ")
    assert uvps("--help").returncode == 0


@pytest.mark.slow
def test_protrusion_commands_from_the_command_line(capture_dir, tmp_path):
    """regions / detect / wand / compare / report on a run folder, through the real CLI."""
    import csv

    def rows_of(path):
        with open(path, newline="") as fh:
            return list(csv.DictReader(fh))

    cap, folder = capture_dir
    out = tmp_path / "run"
    assert uvps("run", folder, "-o", out, "--lights", folder / "lights_positions_mm.csv").returncode == 0
    r = uvps("regions", "-o", out, "--auto")
    assert r.returncode == 0, r.stderr
    assert (out / "regions_labels.tif").is_file()
    r = uvps("detect", "-o", out)
    assert r.returncode == 0, r.stderr
    rows = rows_of(out / "protrusions.csv")
    assert len(rows) > 0
    clicks = tmp_path / "clicks.csv"
    picked = rows[: min(5, len(rows))]
    clicks.write_text("x_px,y_px\n" + "".join(f"{float(p['x_px']):.0f},{float(p['y_px']):.0f}\n" for p in picked))
    r = uvps("wand", clicks, "-o", out)                      # the default: each click's own contrast
    assert r.returncode == 0, r.stderr
    manual = rows_of(out / "protrusions_manual.csv")
    assert len(manual) == len(picked)                        # one row per click
    counted = sum(row["counted"] == "1" for row in manual)
    assert counted >= len(picked) - 1 and r.stdout.startswith(f"{len(picked)} clicks: {counted} outlined")
    r = uvps("compare", out / "protrusions_manual.csv", out / "protrusions.csv", "-o", out)
    assert r.returncode == 0, r.stderr
    comp = {row["label"]: row for row in rows_of(out / "comparison.csv")}
    total = comp.get("all") or comp.get("all areas")
    assert int(total["matched"]) == counted and int(total["missed"]) == 0       # the counted clicks alone
    r = uvps("report", "-o", out, "--bins-um", "0", "100", "300", "1000")
    assert r.returncode == 0, r.stderr
    header = (out / "regions.csv").read_text().splitlines()[0]
    assert "count_100-300um" in header and "report:" in r.stdout
    # bad input: bins that are not increasing, a tolerance out of range
    r = uvps("report", "-o", out, "--bins-um", "0", "300", "100")
    assert r.returncode == 1 and "bins" in r.stderr.lower()
    r = uvps("wand", clicks, "-o", out, "--tolerance", "-1")
    assert r.returncode == 1 and "tolerance" in r.stderr
    r = uvps("wand", clicks, "-o", out, "--method", "imagej")
    assert r.returncode == 1 and "needs a tolerance in albedo units" in r.stderr


@pytest.mark.slow
def test_lp_intensity_column_is_used_and_equal_intensities_otherwise(tmp_path):
    """Far lights from an .lp file: its 4th column gives the intensities; without it they are equal
    (not re-estimated from the levels) unless --estimate-intensities asks for that."""
    from uvps.testing.synthetic import normals_from_height, render_images

    r, c = np.mgrid[0:120, 0:160].astype(float)
    h = 40 * np.sin(2 * np.pi * c / 80) * np.cos(2 * np.pi * r / 60)
    albedo = np.where(c < 80, 150.0, 1000.0)               # a dark and a bright half
    el = np.radians(np.linspace(30, 70, 8))
    az = np.radians(np.arange(8) * 137.5)
    dirs = np.stack([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)], axis=1)
    E = np.array([0.6, 1.4, 0.9, 1.1, 2.0, 0.7, 1.0, 1.2])
    images = render_images(h, albedo, pixel_size_um=PX, light_directions=dirs, intensities=E,
                           noise=False, dtype=None).astype(np.float32)
    names = [f"l{k}.tif" for k in range(8)]
    for name, img in zip(names, images):
        tifffile.imwrite(tmp_path / name, img)
    files = [tmp_path / n for n in names]
    lp4, lp3 = tmp_path / "with_e.lp", tmp_path / "plain.lp"
    lp4.write_text("8\n" + "".join(f"{n} {d[0]} {d[1]} {d[2]} {e}\n" for n, d, e in zip(names, dirs, E)))
    lp3.write_text("8\n" + "".join(f"{n} {d[0]} {d[1]} {d[2]}\n" for n, d in zip(names, dirs)))
    truth = normals_from_height(h, pixel_size_um=PX)

    def run(lp, *extra):
        out = tmp_path / f"run_{lp.stem}{'_est' if extra else ''}"
        res = uvps("normals", *files, "-o", out, "--lights", lp, "--pixel-size-um", PX, "--degree", "1", *extra)
        assert res.returncode == 0, res.stderr
        E_run = np.array([l["intensity"] for l in json.loads((out / "lights.json").read_text())["lights"]])
        err = _angle(np.moveaxis(tifffile.imread(out / "normals.tif"), 0, -1), truth)
        return E_run, np.nanmean(err)

    E_given, err_given = run(lp4)
    np.testing.assert_allclose(E_given, E / np.median(E), rtol=1e-5)
    assert err_given < 0.5, err_given                     # 0.005 deg measured
    E_equal, err_equal = run(lp3)
    np.testing.assert_array_equal(E_equal, 1.0)
    assert err_equal > 1.0, err_equal                     # these lamps are not equal: 24 deg
    E_levels, _ = run(lp3, "--estimate-intensities")
    assert np.ptp(E_levels) > 0.1


@pytest.mark.slow
def test_lamps_that_fit_no_pixel_stop_the_run_without_heights(capture_dir, tmp_path):
    """Lamps given at grazing incidence (0.5 mm above the canvas plane) light no pixel as the images
    show it: one line, exit 1, nothing written. Lamps below the canvas are refused on reading."""
    cap, folder = capture_dir
    for z, needle in ((0.5, "no lamp model fits"), (-100.0, "z > 0")):
        csv = tmp_path / f"lamps_{z}.csv"
        rows = ["file,x_mm,y_mm,z_mm"] + [f"{p.name},{x:.3f},{y:.3f},{z:.3f}"
                                          for p, (x, y, _) in zip(_images(folder), cap.light_positions_mm)]
        csv.write_text("\n".join(rows) + "\n")
        out = tmp_path / "out"
        r = uvps("run", folder, "-o", out, "--lights", csv)
        assert r.returncode == 1, r.stderr
        err = [l for l in r.stderr.splitlines() if "error" in l]
        assert len(err) == 1 and needle in err[0], r.stderr
        assert not out.exists()


@pytest.mark.slow
def test_images_no_lamp_model_explains_stop_the_run_with_estimated_lamps(capture_dir, tmp_path):
    """Each image under its own dappled light (an independent smooth gain of 15 % per image, as no
    point lamp casts): the lamps estimated from them leave ~10 % of the signal unexplained, where a
    Lambertian capture leaves ~0.5 %; the run says so in one line, exits 1 and writes nothing (a real
    gilded icon under visible-light RTI gave lamps 52 deg off with a 0.8 % height uncertainty before
    this rule)."""
    from scipy import ndimage

    _, folder = capture_dir
    rng = np.random.default_rng(0)
    dappled = tmp_path / "dappled"
    dappled.mkdir()
    for p in _images(folder):
        img = tifffile.imread(p).astype(np.float64)
        g = ndimage.gaussian_filter(rng.standard_normal(img.shape[:2]), 3)
        gain = 1 + 0.15 * g / g.std()
        tifffile.imwrite(dappled / p.name, np.clip(img * gain[..., None], 0, 65535).astype(np.uint16))
    out = tmp_path / "out"
    r = uvps("run", dappled, "-o", out, "--pixel-size-um", PX)
    assert r.returncode == 1, r.stderr
    err = [l for l in r.stderr.splitlines() if "error" in l]
    assert len(err) == 1 and "no lamp model fits" in err[0] and "unexplained" in err[0], r.stderr
    assert not out.exists()
    ok = uvps("run", folder, "-o", tmp_path / "clean", "--pixel-size-um", PX)
    assert ok.returncode == 0, ok.stderr


def test_the_command_runs_with_one_blas_thread_unless_told_otherwise(monkeypatch):
    """The console script (uvps._entry) sets OPENBLAS/MKL_NUM_THREADS=1 before numpy loads in a
    fresh process, and keeps a value the user set."""
    import subprocess
    import sys

    import uvps.cli
    from uvps import _entry

    seen = {}
    monkeypatch.setattr(uvps.cli, "main", lambda argv=None: seen.update(
        {k: __import__("os").environ.get(k) for k in _entry.BLAS_THREAD_VARIABLES}) or 0)
    monkeypatch.delenv("OPENBLAS_NUM_THREADS", raising=False)
    monkeypatch.setenv("MKL_NUM_THREADS", "3")
    assert _entry.main([]) == 0
    assert seen == {"OPENBLAS_NUM_THREADS": "1", "MKL_NUM_THREADS": "3"}
    # in a fresh process the entry point runs before numpy is imported (OpenBLAS reads the variable
    # when numpy loads it)
    out = subprocess.run([sys.executable, "-c", "import sys, uvps._entry; print('numpy' in sys.modules)"],
                         capture_output=True, text=True, check=True).stdout
    assert out.strip() == "False"


def test_ctrl_c_ends_with_one_line_exit_130_and_no_partial_output(tmp_path, ctrl_c):
    """A real SIGINT to a running `uvps run`: the shell's status 130, one line, no run folder."""
    import signal

    cap = make_capture(shape=(900, 1200), n_lights=12, seed=1)
    write_capture(cap, tmp_path / "cap")
    out = tmp_path / "run"
    proc = subprocess.Popen([sys.executable, "-m", "uvps", "run", str(tmp_path / "cap"), "-o", str(out)],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    lines = []
    for line in proc.stderr:      # reading done: inside the light estimate (~4 s)
        lines.append(line)
        if "uvps.files.io: capture:" in line:
            break
    assert proc.poll() is None, "the run ended before it could be interrupted"
    proc.send_signal(signal.SIGINT)
    _, err = proc.communicate(timeout=120)
    err = "".join(lines) + err
    assert proc.returncode == 130, err
    assert err.strip().splitlines()[-1] == f"uvps run: interrupted; nothing written ({out} not created)"
    assert "Traceback" not in err and not out.exists()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["cap"]


def test_ctrl_c_inside_a_compiled_kernel_is_an_interruption_not_an_internal_error(monkeypatch, tmp_path, capsys):
    """numba reports a KeyboardInterrupt raised in its kernel as a SystemError wrapping it."""
    import dataclasses

    def kernel(*args, **kwargs):
        try:
            raise KeyboardInterrupt
        except KeyboardInterrupt as exc:
            raise SystemError("<numba kernel> returned a result with an exception set") from exc

    spec = dataclasses.replace(cli.COMMANDS["info"], run=kernel)
    monkeypatch.setitem(cli.COMMANDS, "info", spec)
    assert cli.main(["info", str(tmp_path)]) == 130
    assert capsys.readouterr().err.strip().splitlines()[-1] == "uvps info: interrupted"
    def failing(*args, **kwargs):
        raise SystemError("a real internal error")

    monkeypatch.setitem(cli.COMMANDS, "info", dataclasses.replace(spec, run=failing))
    assert cli.main(["info", str(tmp_path)]) == 2
    assert "internal error: SystemError: a real internal error" in capsys.readouterr().err


#: The numeric core's libraries: none is imported to parse a capture command's or batch's command line.
_NUMERIC = ("numba", "scipy", "skimage", "dask", "matplotlib")


def _fresh_python(code: str, timeout: float) -> str:
    """``code`` run by a fresh interpreter (nothing imported yet); its standard output, once it succeeded."""
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=timeout)
    assert r.returncode == 0, r.stderr
    return r.stdout


def test_parsing_the_capture_commands_and_batch_imports_no_numeric_core():
    """`uvps run`, the steps and `uvps batch` declare their parameters without the numeric core: the
    command line is parsed (and `run` starts hashing its capture, `batch` its cluster) before numba,
    scipy and scikit-image are imported (0.7 s on one core)."""
    code = ("import sys; from uvps.cli import build_parser; from uvps.commands import COMMANDS; "
            "specs = {n: COMMANDS[n] for n in ('run', 'flatfield', 'lights', 'normals', 'batch')}; "
            "build_parser(specs).parse_args(['run', 'cap', '-o', 'out', '--regions', 'auto']); "
            f"print(sorted(m for m in {_NUMERIC!r} if m in sys.modules))")
    assert _fresh_python(code, 120).strip() == "[]"


def test_a_run_hashes_its_capture_while_it_imports_the_numeric_core(tmp_path):
    """`uvps run` starts hashing its input files (run.json's SHA-256, ~0.85 CPU s for a 1.15 GB stack) before
    it imports the pipeline, so that the hashing takes the other core while this one imports; the hashes
    written are the files'."""
    cap = make_capture(shape=(60, 80), n_lights=6, seed=3)
    write_capture(cap, tmp_path / "cap")
    code = ("import sys, uvps.workflow as w, uvps.files.io as io; seen = []; h = io.hash_inputs_meanwhile; "
            "w.hash_inputs_meanwhile = lambda c: seen.append('uvps.core.pipeline' in sys.modules) or h(c); "
            "from uvps.cli import main; "
            f"s = main(['run', {str(tmp_path / 'cap')!r}, '-o', {str(tmp_path / 'run')!r}]); print(s, seen)")
    out = _fresh_python(code, 300)
    assert out.split()[-2:] == ["0", "[False]"], out
    inputs = json.loads((tmp_path / "run" / "run.json").read_text())["inputs"]
    files = sorted((tmp_path / "cap").glob("uv_*.tif"))
    assert sorted(Path(i["path"]).name for i in inputs) == [f.name for f in files]
    for i in inputs:
        assert i["sha256"] == hashlib.sha256(Path(i["path"]).read_bytes()).hexdigest()


def test_the_hashes_run_at_the_lowest_priority_and_leave_the_runs_own(tmp_path, monkeypatch):
    """run.json's hashes are made in background threads at nice 19 on Linux, where a thread has its own priority
    (they take the cores the run leaves idle, not a share of its two-thread stages), at the caller's elsewhere; the
    calling thread keeps its priority, and the hashes are the files' SHA-256."""
    import os
    import threading

    import uvps.files.io as io

    cap = make_capture(shape=(60, 80), n_lights=6, seed=3)
    write_capture(cap, tmp_path / "cap")
    capture = io.read_capture(tmp_path / "cap")
    linux = sys.platform.startswith("linux")

    def priority():     # this thread's (Linux), else the process's
        return os.getpriority(os.PRIO_PROCESS, threading.get_native_id() if linux else 0)

    seen = []
    sha = io.sha256_file
    main = threading.get_ident()
    before = priority()

    def spy(path, **kw):
        if threading.get_ident() != main:
            seen.append(priority())
        return sha(path, **kw)

    monkeypatch.setattr(io, "sha256_file", spy)
    hashes = io.hash_inputs_meanwhile(capture)
    for t in hashes._jobs._threads:
        t.join(60)
    got = hashes.result()
    assert priority() == before
    assert len(seen) == 6 and set(seen) == ({19} if linux else {before})
    for entry in got:
        assert entry["sha256"] == hashlib.sha256(Path(entry["path"]).read_bytes()).hexdigest()


def test_hashes_the_background_threads_have_not_begun_are_made_by_the_caller(tmp_path, monkeypatch):
    """Background threads that get no core (here: each held on its first file) delay run.json only by the files
    they have begun: ``result()`` hashes the others in the calling thread, then waits for those; a file that
    cannot be read is raised there."""
    import threading

    import uvps.files.io as io

    cap = make_capture(shape=(60, 80), n_lights=6, seed=3)
    write_capture(cap, tmp_path / "cap")
    capture = io.read_capture(tmp_path / "cap")
    main = threading.get_ident()
    go, begun, by_main = threading.Event(), threading.Semaphore(0), []
    sha = io.sha256_file

    def held(path, **kw):
        if threading.get_ident() == main:
            by_main.append(Path(path).name)
        else:
            begun.release()
            go.wait(60)
        return sha(path, **kw)

    monkeypatch.setattr(io, "sha256_file", held)
    hashes = io.hash_inputs_meanwhile(capture)
    assert begun.acquire(timeout=60) and begun.acquire(timeout=60)      # both threads on their first file
    threading.Timer(0.5, go.set).start()
    got = hashes.result()
    assert len(by_main) == 4 and len(got) == 6
    for entry in got:
        assert entry["sha256"] == hashlib.sha256(Path(entry["path"]).read_bytes()).hexdigest()
    monkeypatch.setattr(io, "sha256_file", lambda path, **kw: (_ for _ in ()).throw(PermissionError(path)))
    with pytest.raises(PermissionError):
        io.hash_inputs_meanwhile(capture).result()
