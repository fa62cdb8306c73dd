"""The fast paths give the straightforward results: the normals kernel against a per-pixel
``np.linalg.lstsq``, memory-mapped captures processed in tiny bands against the in-memory path."""
import os
from concurrent.futures import ThreadPoolExecutor

import numpy as np
import pytest

from uvps.files.io import MappedStack, read_capture
from uvps.core.lights import LightModel, pixel_coordinates_mm
from uvps.core.pipeline import RunOptions, run
from uvps.core.stereo import solve_normals
from uvps.testing.synthetic import make_capture, write_capture

M, N, PX = 40, 56, 20.0


def _lights(near):
    rng = np.random.default_rng(3)
    az = np.radians(np.arange(8) * 45 + rng.uniform(-10, 10, 8))
    el = np.radians(rng.uniform(40, 65, 8))
    P = 200 * np.stack([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)], axis=1)
    E = rng.uniform(0.8, 1.2, 8)
    return LightModel.from_positions(P, E) if near else LightModel.from_directions(P, E)


def _scene(model):
    """Normals within 25 deg of +z, RGB albedo, every sample lit: I_kc = albedo_c n . v_k (float32)."""
    rng = np.random.default_rng(0)
    t = np.radians(rng.uniform(0, 25, (M, N)))
    p = rng.uniform(0, 2 * np.pi, (M, N))
    n = np.dstack([np.sin(t) * np.cos(p), np.sin(t) * np.sin(p), np.cos(t)])
    albedo = rng.uniform(500, 3000, (M, N, 3))
    r, c = np.mgrid[0:M, 0:N]
    V = np.broadcast_to(model.vectors(pixel_coordinates_mm(r, c, (M, N), PX)), (8, M, N, 3))
    shade = np.einsum("kmni,mni->kmn", V, n)
    assert shade.min() > 0.2
    return (shade[..., None] * albedo).astype(np.float32), V


@pytest.mark.parametrize("near", [True, False])
def test_normals_kernel_equals_per_pixel_lstsq(near):
    model = _lights(near)
    images, V = _scene(model)
    res = solve_normals(images, model, pixel_size_um=PX, chunk_pixels=333)
    assert (res.n_used == 8).all()
    grey = images.astype(np.float64).mean(axis=-1)
    for i in range(0, M, 3):
        for j in range(0, N, 5):
            b = np.linalg.lstsq(V[:, i, j], grey[:, i, j], rcond=None)[0]
            n_ref = b / np.linalg.norm(b)
            np.testing.assert_allclose(res.normals[i, j], n_ref, atol=1e-5)
            s = V[:, i, j] @ n_ref
            alb = np.linalg.lstsq(s[:, None], images[:, i, j].astype(np.float64), rcond=None)[0][0]
            np.testing.assert_allclose(res.albedo[i, j], alb, rtol=1e-5)


def test_normals_do_not_depend_on_bands_or_threads():
    model = _lights(True)
    images, _ = _scene(model)
    a = solve_normals(images, model, pixel_size_um=PX, workers=1, chunk_pixels=10 ** 6)
    b = solve_normals(images, model, pixel_size_um=PX, workers=3, chunk_pixels=97)
    np.testing.assert_array_equal(a.normals, b.normals)
    np.testing.assert_array_equal(a.albedo, b.albedo)


@pytest.fixture(scope="module")
def folder(tmp_path_factory):
    cap = make_capture(shape=(90, 120), n_lights=8, seed=2, pixel_size_um=30.0)
    out = tmp_path_factory.mktemp("cap") / "capture"
    write_capture(cap, out, truth=False)
    return out


def test_mapped_stack_indexes_like_an_array(folder):
    mapped = read_capture(folder).images
    whole = read_capture(folder, memory_map=False).images
    assert isinstance(mapped, MappedStack) and isinstance(whole, np.ndarray)
    assert mapped.shape == whole.shape and mapped.dtype == whole.dtype
    r, c = np.array([0, 5, 89]), np.array([3, 119, 7])
    for key in (2, (slice(None), slice(10, 20)), (3, slice(0, 90, 8), slice(1, 50)), (slice(None), r, c),
                (np.array([0, 3]), slice(None, None, 8), slice(None, None, 8)), (slice(2, 5), 7, slice(None))):
        np.testing.assert_array_equal(mapped[key], whole[key])
    np.testing.assert_array_equal(np.asarray(mapped), whole)
    # the normals' bands: the files converted straight into float32, the same values as indexing gives
    from uvps.core.stack import float_band
    for rows in (slice(0, 7), slice(40, 90), slice(89, 90)):
        band = float_band(mapped, rows)
        assert band.dtype == np.float32
        np.testing.assert_array_equal(band, whole[:, rows].astype(np.float32))
        np.testing.assert_array_equal(float_band(whole, rows), band)


def test_band_path_gives_the_in_memory_results(folder, monkeypatch):
    """A memory-mapped capture through bands of 97 pixels = the capture read whole, in one band."""
    import uvps.core.stereo

    opts = RunOptions(estimate_intensities=True)    # the lamps' intensities from the images too
    lights = folder / "lights_positions_mm.csv"
    whole = run(read_capture(folder, lights=lights, memory_map=False), opts, stages=("normals", "height"))
    monkeypatch.setattr(uvps.core.stereo, "CHUNK_PIXELS", 97)
    banded = run(read_capture(folder, lights=lights), opts, stages=("normals", "height"))
    np.testing.assert_array_equal(banded.lights.model.intensities, whole.lights.model.intensities)
    np.testing.assert_allclose(banded.lights.model.positions_mm, whole.lights.model.positions_mm, rtol=1e-9)
    np.testing.assert_array_equal(banded.stereo.normals, whole.stereo.normals)
    np.testing.assert_array_equal(banded.stereo.albedo, whole.stereo.albedo)
    np.testing.assert_array_equal(banded.height.height_um, whole.height.height_um)


def test_run_progress_advances_band_by_band(folder, monkeypatch):
    """The run's progress never goes back and moves within the normals (one report per band)."""
    import uvps.core.stereo

    monkeypatch.setattr(uvps.core.stereo, "CHUNK_PIXELS", 1200)     # 10 rows of 120: 9 bands
    seen = []
    run(read_capture(folder, lights=folder / "lights_positions_mm.csv"), RunOptions(), stages=("normals", "height"),
        progress=lambda f, m: seen.append((f, m)))
    fractions = [f for f, _ in seen]
    assert fractions == sorted(fractions) and fractions[0] == 0.0 and fractions[-1] == 1.0
    normals = [f for f, m in seen if m.startswith("normals: rows")]
    assert len(normals) == 9 and len(set(normals)) == 9


def _rewritten(folder, out, **tiff_options):
    """The capture's images re-written into ``out`` with ``tiff_options`` (compression, byte order),
    the calibration and the lamp file kept."""
    import tifffile

    from uvps.testing.synthetic import _write_camera_tiff

    out.mkdir()
    for f in sorted(folder.glob("uv_*.tif")):
        _write_camera_tiff(out / f.name, tifffile.imread(f), 30.0, **tiff_options)
    (out / "lights_positions_mm.csv").write_bytes((folder / "lights_positions_mm.csv").read_bytes())
    return out


def test_compressed_files_of_a_large_stack_are_decoded_to_scratch_and_mapped(folder, tmp_path, monkeypatch):
    """Compressed TIFFs (Deflate, as raw converters write them) cannot be memory-mapped: above
    io.SCRATCH_ABOVE_BYTES (0 here) they are decoded once into unlinked scratch files in TMPDIR and
    mapped there: the same counts as the files, the same run, and nothing left in TMPDIR."""
    import tempfile

    import uvps.files.io

    packed = _rewritten(folder, tmp_path / "packed", compression="zlib")
    scratch = tmp_path / "scratch"
    scratch.mkdir()
    monkeypatch.setattr(tempfile, "tempdir", str(scratch))
    small = read_capture(packed)                              # a small stack stays in memory
    assert isinstance(small.images, np.ndarray)
    monkeypatch.setattr(uvps.files.io, "SCRATCH_ABOVE_BYTES", 0)
    cap = read_capture(packed, lights=packed / "lights_positions_mm.csv")
    assert isinstance(cap.images, MappedStack)
    assert list(scratch.iterdir()) == []                     # unlinked once mapped
    plain = read_capture(folder, lights=folder / "lights_positions_mm.csv", memory_map=False)
    np.testing.assert_array_equal(np.asarray(cap.images), plain.images)
    a = run(cap, RunOptions(), stages=("normals",))
    b = run(plain, RunOptions(), stages=("normals",))
    np.testing.assert_array_equal(a.stereo.normals, b.stereo.normals)


@pytest.mark.parametrize("layout", ["ZCYX", "KYXS", "deflate", "deflate-small", "big-endian"])
def test_an_integer_multipage_stack_is_mapped_not_copied_to_float(folder, tmp_path, monkeypatch, layout):
    """One multi-page TIFF (ImageJ hyperstack with planar or interleaved colour, or a Deflate-compressed
    stack above io.SCRATCH_ABOVE_BYTES, decoded into a scratch file, or under it, read whole) is seen as a MappedStack in its own dtype, as a folder of
    files is: the same counts and the same normals as the files read whole; nothing left in TMPDIR."""
    import tempfile

    import tifffile

    import uvps.files.io
    from uvps.files.io import write_imagej_tiff

    files = sorted(folder.glob("uv_*.tif"))
    data = np.stack([tifffile.imread(f) for f in files])           # (K, M, N, 3) uint16
    stack = tmp_path / "stack.tif"
    if layout == "ZCYX":
        write_imagej_tiff(stack, np.moveaxis(data, -1, 1), axes="ZCYX", pixel_size_um=30.0)
    elif layout == "big-endian":    # as ImageJ saves a stack: Motorola byte order
        tifffile.imwrite(stack, np.moveaxis(data, -1, 1), byteorder=">", imagej=True,
                         resolution=(1 / 30.0, 1 / 30.0), metadata={"axes": "ZCYX", "unit": "micron"})
    else:   # a plain multi-page RGB TIFF (interleaved samples), uncompressed or Deflate
        tifffile.imwrite(stack, data, photometric="rgb", compression="zlib" if "deflate" in layout else None,
                         resolution=(1 / 30.0, 1 / 30.0), resolutionunit="NONE",
                         description="ImageJ=1.54f\nunit=micron\n", metadata=None)
        # "deflate-small": under the threshold, read whole, but still views in uint16, no float32 copy
        monkeypatch.setattr(uvps.files.io, "SCRATCH_ABOVE_BYTES", 0 if layout == "deflate" else 10 ** 12)
    scratch = tmp_path / "scratch"
    scratch.mkdir()
    monkeypatch.setattr(tempfile, "tempdir", str(scratch))
    lp = tmp_path / "lamps.csv"
    lp.write_text("\n".join(["file,x_mm,y_mm,z_mm"] + [
        f"stack.tif#{i + 1}," + ",".join(line.split(",")[1:4])
        for i, line in enumerate((folder / "lights_positions_mm.csv").read_text().splitlines()[1:])]) + "\n")
    cap = read_capture(stack, lights=lp)
    assert isinstance(cap.images, MappedStack) and cap.images.dtype == np.dtype("=u2")
    assert cap.images[0].dtype.isnative and cap.bit_depth == "uint16"
    assert cap.images.shape == data.shape and list(scratch.iterdir()) == []
    np.testing.assert_array_equal(np.asarray(cap.images), data)
    np.testing.assert_array_equal(cap.images[3, 10:20, 5:9], data[3, 10:20, 5:9])
    plain = read_capture(folder, lights=folder / "lights_positions_mm.csv", memory_map=False)
    np.testing.assert_array_equal(cap.light_positions_mm, plain.light_positions_mm)
    a = run(cap, RunOptions(), stages=("normals",))
    b = run(plain, RunOptions(), stages=("normals",))
    np.testing.assert_array_equal(a.stereo.normals, b.stereo.normals)
    # without mapping (memory_map=False) the same stack is read whole into float32, as before
    whole = read_capture(stack, lights=lp, memory_map=False)
    assert isinstance(whole.images, np.ndarray) and whole.images.dtype == np.float32


def test_a_folder_of_big_endian_tiffs_as_imagej_saves_them_is_mapped_and_runs(folder, tmp_path):
    """ImageJ saves TIFFs in Motorola (big-endian) byte order; mapped as they are, the compiled kernels
    refused them (numba: unsupported array dtype >u2). The mapped stack hands out native copies."""
    be = _rewritten(folder, tmp_path / "be", byteorder=">")
    cap = read_capture(be, lights=be / "lights_positions_mm.csv")
    assert isinstance(cap.images, MappedStack) and cap.images.maps[0].dtype == np.dtype(">u2")
    assert cap.images[2, 5:9].dtype.isnative and cap.bit_depth == "uint16"
    plain = read_capture(folder, lights=folder / "lights_positions_mm.csv", memory_map=False)
    a = run(cap, RunOptions(), stages=("normals",))
    b = run(plain, RunOptions(), stages=("normals",))
    np.testing.assert_array_equal(a.stereo.normals, b.stereo.normals)


# ------------------------------------------------------------------------------------------------
# The calibrated route (lamps and intensities given, a dark frame): one pass of drop-off fits, the
# dark frame subtracted as the files are read, the outputs those of the route before either change
# (tests/golden/calibrated_run.npz, written by this module's _calibrated_outputs: ``python
# tests/test_speed.py GOLDEN``). First written with the code before both changes (0a8dddd); written again
# when the glossy spheres' fit changed the calibration and depth.tif became levelled, after checking that
# the code before the speed changes with the new sphere fit (6f9a8f9) gives the same normals, albedo and
# labels to the bit. Written again when the sphere rims' RANSAC band and pooled views moved the second
# sphere's circle by 0.05 px (to within 0.03 px of the truth; its lamps' positions 1-6 points closer): written by
# the code with that rim change alone (d17cdaa), which today's code (the normals' lanes, the detection's
# threads) matches.
# ------------------------------------------------------------------------------------------------

GOLDEN_CALIBRATED = __import__("pathlib").Path(__file__).parent / "golden" / "calibrated_run.npz"


def _calibrated_scene(root):
    from uvps.testing.synthetic_spheres import SphereSpec, make_sphere_capture, write_sphere_capture

    cap = make_capture(shape=(150, 200), n_lights=6, seed=4, pixel_size_um=120.0, rgb=True, black_level=200.0)
    write_capture(cap, root / "cap", dark_frame=True)
    sc = make_sphere_capture(cap, [SphereSpec("glossy", (0.15, 0.2), 3.0), SphereSpec("glossy", (0.85, 0.8), 3.0)])
    write_sphere_capture(sc, root / "spheres")
    return root


def _calibrated_outputs(root) -> dict:
    """``uvps calibrate`` (spheres, dark frame) and ``uvps run --calibration --detect`` in this process:
    the run's normals, albedo, depth and protrusion labels."""
    import tifffile

    from uvps.cli import main

    assert main(["calibrate", "--spheres", str(root / "spheres"), "--dark", str(root / "cap" / "dark" / "dark.tif"),
                 "-o", str(root / "cal")]) == 0
    assert main(["run", str(root / "cap"), "--calibration", str(root / "cal"), "--detect", "-o",
                 str(root / "run")]) == 0
    return {n: tifffile.imread(root / "run" / f"{n}.tif") for n in ("normals", "albedo", "depth", "protrusions_labels")}


def _counting(monkeypatch, *names):
    """Count the calls of ``uvps.core.pipeline``'s ``names`` (the real functions still run)."""
    import uvps.core.pipeline as pipeline

    calls = dict.fromkeys(names, 0)

    def spy(name):
        real = getattr(pipeline, name)

        def counted(*args, **kw):
            calls[name] += 1
            return real(*args, **kw)
        return counted

    for name in names:
        monkeypatch.setattr(pipeline, name, spy(name))
    return calls


def test_calibrated_route_keeps_its_outputs(tmp_path, monkeypatch):
    """``uvps calibrate`` from spheres with a dark frame, then ``uvps run --calibration --detect``: the
    normals, albedo, depth and protrusions of the code before the dark frame was subtracted as the
    files are read and before the beams' gain maps were evaluated as matrix products (labels to the
    bit, maps to 1e-6 of their range: the gain maps' float64 sums are taken in another order). The
    sphere calibration gives no intensities: they are measured on the images with the beams divided
    out, fitted again on the one pass's blocks divided by the beams' gains (one pass over the stack, two
    drop-off fits)."""
    root = _calibrated_scene(tmp_path)
    calls = _counting(monkeypatch, "block_grid", "fit_dropoffs")
    out = _calibrated_outputs(root)
    assert calls == {"block_grid": 1, "fit_dropoffs": 2}
    ref = np.load(GOLDEN_CALIBRATED)
    for name, value in out.items():
        want = ref[name]
        assert value.shape == want.shape and value.dtype == want.dtype, name
        if name == "protrusions_labels":
            np.testing.assert_array_equal(value, want)
        else:
            np.testing.assert_allclose(value, want, rtol=0, atol=1e-6 * float(np.nanmax(np.abs(want))), err_msg=name)


def test_given_intensities_fit_the_dropoff_once(folder, tmp_path, monkeypatch):
    """Known positions and intensities (a rig's light file): the drop-off is fitted once, for the lamps'
    beams; the images with the beams divided out are not fitted again (nothing but dropoff.tif used
    those fits: it now holds the drop-off as captured, beam included). The normals are those of the
    images divided by those beams under the given lamps; measured intensities take a second fit (on the
    first pass's blocks, :func:`uvps.core.flatfield.divided_grid`), the flat-fielded images two passes."""
    from uvps.core.flatfield import block_grid, fit_dropoffs
    from uvps.core.pipeline import with_common
    from uvps.core.lights import dropoff_common

    E = np.linspace(0.8, 1.2, 8)
    rows = (folder / "lights_positions_mm.csv").read_text().splitlines()
    lp = tmp_path / "lamps.csv"
    lp.write_text("\n".join([rows[0] + ",intensity"] + [f"{r},{float(e)!r}" for r, e in zip(rows[1:], E)]) + "\n")
    cap = read_capture(folder, lights=lp)
    calls = _counting(monkeypatch, "block_grid", "fit_dropoffs")
    res = run(cap, RunOptions(), stages=("normals",))
    assert calls == {"block_grid": 1, "fit_dropoffs": 1}
    np.testing.assert_allclose(res.lights.model.intensities, E / np.median(E))
    again = solve_normals(res.lights.images, res.lights.model, pixel_size_um=cap.pixel_size_um)
    np.testing.assert_array_equal(res.stereo.normals, again.normals)
    grid = block_grid(cap.images, mask=cap.mask, saturation=cap.saturation)
    captured = with_common(fit_dropoffs(grid, degree=4), grid,
                           dropoff_common(cap.light_positions_mm, grid.shape, cap.pixel_size_um))
    for f, g in zip(res.lights.fits, captured):
        np.testing.assert_array_equal(f.coeffs, g.coeffs)
        assert f.level == g.level
    calls = _counting(monkeypatch, "block_grid", "fit_dropoffs")
    run(cap, RunOptions(estimate_intensities=True), stages=("normals",))
    assert calls == {"block_grid": 1, "fit_dropoffs": 2}     # refitted on the first pass's blocks
    # the flat-fielded images asked for: the images with the beams divided out, over their own drop-off
    calls = _counting(monkeypatch, "block_grid", "fit_dropoffs")
    ff = run(cap, RunOptions(), stages=("flatfield", "normals"))
    assert calls == {"block_grid": 2, "fit_dropoffs": 2}
    np.testing.assert_array_equal(ff.stereo.normals, res.stereo.normals)


@pytest.fixture(scope="module")
def beams_capture(tmp_path_factory):
    """A capture with lamp beams aimed off the centre (so the beams' gains are not 1) and its dark frame."""
    cap = make_capture(shape=(120, 160), n_lights=8, seed=3, pixel_size_um=30.0, black_level=300.0,
                       beam_exponent=30.0, beam_aim_error_deg=5.0)
    out = tmp_path_factory.mktemp("beams") / "cap"
    write_capture(cap, out, truth=False, dark_frame=True)
    return out


@pytest.mark.parametrize("intensities", [False, True])
def test_calibrated_route_fits_only_what_it_uses(beams_capture, tmp_path, monkeypatch, intensities):
    """``uvps calibrate --lights`` (positions; with an intensity column, intensities too) and ``uvps run
    --calibration --dark``: the stack is read ONCE for the drop-off (one block pass, each image's blocks read
    once). Measured intensities are fitted again on those blocks with the beams divided out
    (:func:`uvps.core.flatfield.divided_grid`), not on a second pass, and give the intensities of that second
    pass (to 1e-9) and the same normals; given intensities are not fitted again at all, and no pixels are
    sampled nor intensities refined for them. Asking for the flat-fielded images, whose drop-off must be theirs
    exactly, takes the second pass. A change that refits, resamples or rereads what the run does not use fails
    here."""
    import json

    import tifffile
    import uvps.core.flatfield as ff
    from uvps.cli import main

    K = 8
    dark = beams_capture / "dark" / "dark.tif"
    assert main(["calibrate", "--lights", str(beams_capture / "lights_positions_mm.csv"), "--dark", str(dark),
                 "--pixel-size-um", "30", "-o", str(tmp_path / "cal")]) == 0
    if intensities:   # a calibration that holds them (uvps calibrate --lights keeps the positions only)
        E = np.linspace(0.8, 1.2, K)
        doc = json.loads((tmp_path / "cal" / "lights.json").read_text())
        for lamp, e in zip(doc["lights"], E):
            lamp["intensity"] = float(e)
        (tmp_path / "cal" / "lights.json").write_text(json.dumps(doc))
    read = []
    real = ff.image_block_stats
    monkeypatch.setattr(ff, "image_block_stats", lambda images, k, *a, **kw: (read.append(k), real(images, k, *a, **kw))[1])
    out = {}
    measured = 0 if intensities else 1      # the pixel sample and the refinement of the intensities
    for extra, want in (([], (1, 1 if intensities else 2)), (["--flatfield-images"], (2, 2))):
        read.clear()
        calls = _counting(monkeypatch, "block_grid", "fit_dropoffs", "sample_pixels", "refine_intensities")
        run_dir = tmp_path / ("run" + "".join(extra))
        assert main(["run", str(beams_capture), "--calibration", str(tmp_path / "cal"), "-o", str(run_dir)] + extra) == 0
        assert calls == {"block_grid": want[0], "fit_dropoffs": want[1], "sample_pixels": measured,
                         "refine_intensities": measured}, extra
        assert sorted(read) == sorted(list(range(K)) * want[0]), extra        # each image's blocks read once a pass
        lights = json.loads((run_dir / "lights.json").read_text())
        out[bool(extra)] = (np.array([lamp["intensity"] for lamp in lights["lights"]]),
                            tifffile.imread(run_dir / "normals.tif"))
    (E_one, n_one), (E_two, n_two) = out[False], out[True]
    assert lights["dropoff_beyond_model_rms"] > 0.003       # 0.0055: the beams' gains are there to divide out
    if intensities:
        np.testing.assert_allclose(E_one, E / np.median(E), rtol=1e-9)
    np.testing.assert_allclose(E_one, E_two, rtol=1e-9)
    np.testing.assert_allclose(n_one, n_two, rtol=0, atol=1e-6)


def test_dark_frame_is_subtracted_in_the_files_counts(tmp_path):
    """A dark frame keeps an integer stack in its dtype (half the memory of float32), subtracted as each
    file is read and clipped at 0: the counts float32 gave."""
    import tifffile

    cap = make_capture(shape=(60, 80), n_lights=4, seed=1, pixel_size_um=30.0, black_level=300.0)
    write_capture(cap, tmp_path / "cap", truth=False, dark_frame=True)
    d = tifffile.imread(tmp_path / "cap" / "dark" / "dark.tif")
    d[:10] = 9000                                       # a band above some of the signal: it clips
    dark = tmp_path / "dark.tif"
    tifffile.imwrite(dark, d, photometric="rgb")
    got = read_capture(tmp_path / "cap", dark=dark, memory_map=False)
    assert isinstance(got.images, np.ndarray) and got.images.dtype == np.uint16 and got.bit_depth == "uint16"
    raw = np.stack([tifffile.imread(f) for f in sorted((tmp_path / "cap").glob("uv_*.tif"))]).astype(np.float32)
    want = np.maximum(raw - tifffile.imread(dark).astype(np.float32), 0)
    assert (raw < d).any() and (raw > d).any()
    np.testing.assert_array_equal(got.images.astype(np.float32), want)
    # memory-mapped (the default): the files seen with the dark frame subtracted band by band, the same values
    from uvps.files.io import DarkSubtracted
    mapped = read_capture(tmp_path / "cap", dark=dark)
    assert isinstance(mapped.images, DarkSubtracted) and mapped.bit_depth == "uint16"
    r, c = np.array([0, 5, 59]), np.array([3, 79, 7])
    for key in (2, (slice(None), slice(3, 20)), (1, slice(0, 60, 8), slice(1, 50)), (slice(None), r, c)):
        np.testing.assert_array_equal(mapped.images[key], want[key])
    lp = tmp_path / "cap" / "lights_positions_mm.csv"
    a = run(read_capture(tmp_path / "cap", dark=dark, lights=lp), RunOptions(), stages=("normals",), dark_given=True)
    b = run(read_capture(tmp_path / "cap", dark=dark, lights=lp, memory_map=False), RunOptions(),
            stages=("normals",), dark_given=True)
    np.testing.assert_array_equal(a.stereo.normals, b.stereo.normals)
    np.testing.assert_array_equal(a.stereo.albedo, b.stereo.albedo)
    # one multi-page TIFF likewise: copied in its dtype with the dark frame subtracted page by page
    stack = tmp_path / "stack.tif"
    tifffile.imwrite(stack, raw.astype(np.uint16), photometric="rgb", resolution=(1 / 30.0, 1 / 30.0),
                     resolutionunit="NONE", description="ImageJ=1.54f\nunit=micron\n", metadata=None)
    from_stack = read_capture(stack, dark=dark)
    assert from_stack.images.dtype == np.uint16
    np.testing.assert_array_equal(from_stack.images.astype(np.float32), want)
    for f in sorted((tmp_path / "cap").glob("uv_*.tif")):   # the inputs untouched
        assert tifffile.imread(f).astype(np.float32).sum() == raw[sorted((tmp_path / "cap").glob("uv_*.tif")).index(f)].sum()



@pytest.mark.parametrize("byteorder,frame", [("<", "rgb"), (">", "rgb"), ("<", "grey"), ("<", "rgba"), ("<", "grey_alpha")])
def test_dark_frame_is_read_as_stored_never_copied_whole(tmp_path, byteorder, frame):
    """A memory-mapped capture's integer dark frame is kept as stored: memory-mapped from its uncompressed
    file when it is the images' shape and type (a big-endian one, as ImageJ writes, or one with an alpha
    channel is read, alpha dropped); a run never converts the whole frame (a float32 copy of it was 0.14 GB
    of a 4000 x 3000 RGB run's memory) and holds no copy after it; every way the stages read the view (bands,
    single images, scattered pixels, the compiled block and band kernels, through the beams' view too)
    gives the counts minus the frame, clipped at 0, as float32 computes them."""
    import tifffile
    from uvps.core.flatfield import GainCorrected, block_grid
    from uvps.core.stack import StackView
    from uvps.files.io import DarkSubtracted

    cap = make_capture(shape=(60, 80), n_lights=4, seed=1, pixel_size_um=30.0, black_level=300.0)
    write_capture(cap, tmp_path / "cap", truth=False, dark_frame=True)
    d = tifffile.imread(tmp_path / "cap" / "dark" / "dark.tif")
    grey = frame.startswith("grey")
    if grey:
        for f in (tmp_path / "cap").glob("uv_*.tif"):
            tifffile.imwrite(f, tifffile.imread(f)[..., 1])
        d = d[..., 1].copy()
    d[:10] = 20000                                         # clips part of the signal at 0
    stored = {"rgba": lambda: np.dstack([d, np.full(d.shape[:2], 65535, d.dtype)]),
              "grey_alpha": lambda: np.dstack([d, np.full(d.shape, 65535, d.dtype)])}.get(frame, lambda: d)()
    dark = tmp_path / "dark.tif"
    tifffile.imwrite(dark, stored, byteorder=byteorder,
                     **({"photometric": "minisblack", "extrasamples": ["unassalpha"]} if frame == "grey_alpha" else {}))
    capture = read_capture(tmp_path / "cap", dark=dark, lights=tmp_path / "cap" / "lights_positions_mm.csv",
                           pixel_size_um=30.0)
    view = capture.images
    assert isinstance(view, DarkSubtracted) and view.dark.dtype == np.uint16 and view.dark.dtype.isnative
    assert view.dark.shape == d.shape
    assert isinstance(view.dark, np.memmap) == (byteorder == "<" and frame in ("rgb", "grey", "rgba"))
    whole = []
    real_astype = np.ndarray.astype

    class Counting(type(view.dark)):
        def astype(self, *a, **k):
            if self.shape == d.shape:
                whole.append(self.shape)
            return real_astype(np.asarray(self), *a, **k)

    view.dark = frame_seen = view.dark.view(Counting)
    res = run(capture, RunOptions(), stages=("normals", "height", "protrusions"), dark_given=True)
    assert res.protrusions is not None and whole == []     # never converted whole (the code before: once)
    assert view.dark is frame_seen
    held = [v for v in vars(view).values() if isinstance(v, np.ndarray) and v.shape == d.shape]
    assert [h is frame_seen for h in held] == [True]       # and no other copy of it held
    want = np.maximum(np.stack([tifffile.imread(f) for f in sorted((tmp_path / "cap").glob("uv_*.tif"))])
                      .astype(np.float32) - d.astype(np.float32), 0)
    assert (want[:, :10] == 0).any() and (want[:, 10:] > 0).all()
    np.testing.assert_array_equal(view[:, 5:30], want[:, 5:30])
    np.testing.assert_array_equal(view[2], want[2])
    r, c = np.array([0, 7, 33, 59]), np.array([79, 3, 40, 0])
    np.testing.assert_array_equal(view[:, r, c], want[:, r, c])
    np.testing.assert_array_equal(block_grid(view, target=20).values, block_grid(want, target=20).values)
    coeffs = np.random.default_rng(2).normal(0, 0.1, (4, 5, 5))
    beams = GainCorrected(view, coeffs)
    np.testing.assert_array_equal(beams[:, 3:40], StackView.__getitem__(beams, (slice(None), slice(3, 40))))
    assert whole == []


@pytest.mark.parametrize("grey", [False, True])
def test_block_grid_reads_a_view_as_stored_to_the_bit(tmp_path, monkeypatch, grey):
    """The drop-off's block grid of memory-mapped files seen through a dark frame, and through a dark frame
    and the lamps' beams (:class:`uvps.core.flatfield.GainCorrected`), reads each file once as stored and
    corrects every sample as it is read (one pass, no float32 copy of the image): the same block means,
    minima and validity as the views' own float32 values give, to the bit; the files' pages are released."""
    import tifffile
    import uvps.files.io as fio
    from uvps.core.flatfield import GainCorrected, block_grid
    from uvps.core.stack import StackView

    cap = make_capture(shape=(90, 120), n_lights=4, seed=5, pixel_size_um=30.0, black_level=300.0)
    write_capture(cap, tmp_path / "cap", truth=False, dark_frame=True)
    if grey:
        for f in list((tmp_path / "cap").glob("uv_*.tif")) + [tmp_path / "cap" / "dark" / "dark.tif"]:
            tifffile.imwrite(f, tifffile.imread(f)[..., 1])
    d = tifffile.imread(tmp_path / "cap" / "dark" / "dark.tif")
    d[:12] = 20000                                          # clips part of the signal at 0
    dark = tmp_path / "dark.tif"
    tifffile.imwrite(dark, d)
    view = read_capture(tmp_path / "cap", dark=dark, pixel_size_um=30.0).images
    assert isinstance(view, fio.DarkSubtracted) and view.ndim == (3 if grey else 4)
    coeffs = np.random.default_rng(1).normal(0, 0.1, (4, 5, 5))
    released = []
    real_release = fio.release
    monkeypatch.setattr(fio, "release", lambda arr: (released.append(arr), real_release(arr)))
    for stack in (view, GainCorrected(view, coeffs)):
        released.clear()
        got = block_grid(stack, saturation=65535.0)
        assert len(released) == 4                           # each file read once, its pages released
        want = block_grid(np.asarray(stack), saturation=65535.0)   # the view's float32 values in memory
        np.testing.assert_array_equal(got.values, want.values)
        np.testing.assert_array_equal(got.valid, want.valid)
        assert not got.valid.all() and got.valid.any()      # the clipped band: blocks with a dark pixel
    # the beams' view read in bands (the normals') likewise: each file's band corrected as it is read
    beams = GainCorrected(view, coeffs)
    for key in (2, (slice(None), slice(3, 20)), (1, slice(0, 90, 8), slice(1, 50)), (slice(1, 4, 2), slice(5, 6))):
        np.testing.assert_array_equal(beams[key], StackView.__getitem__(beams, key))



def test_block_passes_keep_to_uvps_threads(folder, monkeypatch):
    """The block grid and the additive term's blocks read a mapped stack in place, in two threads, and in the
    calling thread alone with UVPS_THREADS=1 (uvps batch's worker processes): the same blocks as the images
    read whole into memory."""
    import uvps.core.flatfield as ff
    import uvps.core.offset as off
    import uvps.core.threads as th

    images = read_capture(folder).images
    whole = np.asarray(images)
    pools = []       # each pass's pool: one thread beside the calling one (map_bands), two in all
    monkeypatch.setattr(th, "ThreadPoolExecutor", lambda n, **kw: pools.append(n) or ThreadPoolExecutor(n, **kw))
    for threads, want in (("1", []), ("2", [1] if len(os.sched_getaffinity(0)) >= 2 else [])):
        monkeypatch.setenv("UVPS_THREADS", threads)
        pools.clear()
        got, ref = ff.block_grid(images, saturation=65535.0), ff.block_grid(whole, saturation=65535.0)
        np.testing.assert_array_equal(got.values, ref.values)
        np.testing.assert_array_equal(got.valid, ref.valid)
        got, ref = (off._channel_blocks(x, block=16, mask=None, saturation=65535.0) for x in (images, whole))
        for a, b in zip(got, ref):
            np.testing.assert_array_equal(a, b)
        assert pools == want * 4


if __name__ == "__main__":
    import sys
    import tempfile
    from pathlib import Path

    if sys.argv[1:] == ["GOLDEN"]:
        with tempfile.TemporaryDirectory() as tmp:
            np.savez_compressed(GOLDEN_CALIBRATED, **_calibrated_outputs(_calibrated_scene(Path(tmp))))


def test_run_folder_written_beside_the_run_holds_the_same_files(folder, tmp_path, monkeypatch):
    """The input files hashed in a background thread while the run computes, and the run folder's files written
    two at a time: the same TIFFs, byte for byte, as one writer after the run, and run.json's input hashes are
    the files' own SHA-256."""
    import hashlib
    import json
    from pathlib import Path

    import uvps.files.runfolder as runfolder
    import uvps.workflow as workflow
    from uvps.cli import main

    assert main(["run", str(folder), "-o", str(tmp_path / "now")]) == 0
    monkeypatch.setattr(runfolder, "WRITERS", 1)
    monkeypatch.setattr(workflow, "hash_inputs_meanwhile", lambda capture: None)   # hashed by write_run, after
    assert main(["run", str(folder), "-o", str(tmp_path / "serial")]) == 0
    tiffs = sorted(p.name for p in (tmp_path / "now").glob("*.tif"))
    assert {"normals.tif", "albedo.tif", "gradients.tif", "depth.tif", "dropoff.tif"} <= set(tiffs)
    assert tiffs == sorted(p.name for p in (tmp_path / "serial").glob("*.tif"))
    for name in tiffs:
        assert (tmp_path / "now" / name).read_bytes() == (tmp_path / "serial" / name).read_bytes(), name
    inputs = [json.loads((tmp_path / d / "run.json").read_text())["inputs"] for d in ("now", "serial")]
    files = sorted(folder.glob("uv_*.tif"))
    assert inputs[0] == inputs[1] and len(inputs[0]) == len(files)
    for entry in inputs[0]:
        assert entry["sha256"] == hashlib.sha256(Path(entry["path"]).read_bytes()).hexdigest()


@pytest.mark.parametrize("near, colour, every", [(True, True, False), (False, True, False), (True, False, False),
                                                 (True, True, True)])
def test_normals_in_lanes_same_as_one_pixel_at_a_time(near, colour, every):
    """stereo._solve_lanes (LANES pixels side by side, the default solve) writes the outputs of the
    one-pixel-at-a-time kernel _solve_pixels to the bit, with the same sums of squares, on samples that
    exercise every rule: shadowed (dark and attached), saturated, masked-out pixels, a pixel with fewer
    than 3 usable lamps, near and far lamps, grey and RGB, a pixel count that is no multiple of LANES, and
    every sample kept (EVERY_SAMPLE)."""
    from uvps.core import stereo

    model = _lights(near)
    images, _ = _scene(model)
    rng = np.random.default_rng(7)
    images = images * rng.uniform(0.7, 1.3, images.shape[:3] + (1,)).astype(np.float32)   # misfit: residuals
    images[rng.random(images.shape[:3]) < 0.08] = 0.0                                      # cast shadows
    images[:, 3, 5] = 0.0
    images[:2, 3, 6] = 4000.0                                                              # few lamps usable
    sat = np.float32(np.quantile(images, 0.97))                                            # some saturated
    band = images[:, :, :N - 3] if colour else images[:, :, :N - 3].mean(axis=-1)
    K, m, n = band.shape[:3]
    P = m * n
    assert P % stereo.LANES
    flat = np.ascontiguousarray(band.reshape(K, P, -1))
    X = pixel_coordinates_mm(np.arange(m)[:, None], np.arange(n)[None, :], (M, N), PX)
    xs, ys = (X[..., i].astype(np.float32).ravel() for i in (0, 1))
    use = rng.random(P) > 0.05
    L = model.positions_mm if near else np.zeros((K, 3))
    dirs = (model.directions * model.intensities[:, None]).astype(np.float32)
    rules = (np.float32(0), -1.0, float("-inf")) if every else (sat, 0.02, 0.05)
    args = (flat, colour, np.ascontiguousarray(L, dtype=np.float64), model.intensities.astype(np.float64), dirs,
            near, xs, ys, use) + rules
    outs = {}
    for name in ("pixels", "lanes"):
        out = (np.full((P, 3), np.nan, np.float32), np.full((P, flat.shape[2]), np.nan, np.float32),
               np.zeros(P, np.uint8))
        sums = (stereo._solve_pixels(*args, 0, 0, *out) if name == "pixels" else stereo._solve_lanes(*args, *out))
        outs[name] = (out, sums)
    (a, sa), (b, sb) = outs["pixels"], outs["lanes"]
    assert sa == sb and sa[2] > 0 and sa[0] > 0
    for x, y in zip(a, b):
        assert np.array_equal(x, y, equal_nan=True)
    assert np.isnan(a[0]).any() and (a[2] < K).any() and np.isfinite(a[0]).mean() > 0.5


def _counting_gradients(monkeypatch) -> list:
    """Count :func:`uvps.core.integrate.gradients_from_normals`'s calls wherever a run makes them (the height
    stage, the detection's height, gradients.tif's writer): a list of each call's mask (None or an array)."""
    import uvps.core.integrate as integrate
    import uvps.core.pipeline as pipeline
    import uvps.files.runfolder as runfolder

    masks = []
    real = integrate.gradients_from_normals

    def counted(normals, **kw):
        masks.append(kw.get("mask"))
        return real(normals, **kw)

    for module in (integrate, pipeline, runfolder):
        monkeypatch.setattr(module, "gradients_from_normals", counted)
    return masks


@pytest.mark.parametrize("masked", [False, True])
def test_the_detection_reuses_the_height_stages_gradients(folder, tmp_path, monkeypatch, masked):
    """``uvps run --detect``: the normals' gradients computed by the height stage are reused by the
    detection's height (the same mask: none, or the run's where every height inside it is finite), then
    dropped; gradients.tif's are computed by its writer, without a mask (held to the writing, the kept ones
    raised a 10000 x 8000 run's peak by 0.6 GB). The written gradients are those computed from the written
    normals, and the depth and labels those of a run whose every step computes its own (no bit changes)."""
    import tifffile

    import uvps.core.pipeline as pipeline
    from uvps.cli import main
    from uvps.core.integrate import gradients_from_normals

    args = ["run", str(folder), "--detect"]
    if masked:
        mask = np.ones((90, 120), np.uint8)
        mask[:20, :30] = 0
        tifffile.imwrite(tmp_path / "mask.tif", mask)
        args += ["--mask", str(tmp_path / "mask.tif")]
    masks = _counting_gradients(monkeypatch)
    assert main(args + ["-o", str(tmp_path / "once")]) == 0
    # the height stage's (the detection's too), then gradients.tif's without a mask
    assert len(masks) == 2 and (masks[0] is not None) == masked and masks[1] is None
    out = {n: tifffile.imread(tmp_path / "once" / f"{n}.tif") for n in ("normals", "gradients", "depth",
                                                                         "protrusions_labels")}
    g = gradients_from_normals(np.ascontiguousarray(np.moveaxis(out["normals"], 0, -1)))
    np.testing.assert_array_equal(out["gradients"], np.stack([g.p, g.q]))
    # every step its own gradients: the detection's height and gradients.tif's computed again
    monkeypatch.setattr(pipeline, "_same_mask", lambda a, b: False)
    masks.clear()
    assert main(args + ["-o", str(tmp_path / "each")]) == 0
    assert len(masks) == 3
    for name, value in out.items():
        np.testing.assert_array_equal(tifffile.imread(tmp_path / "each" / f"{name}.tif"), value, err_msg=name)


def test_the_kept_gradients_are_not_held_past_the_detection(folder, monkeypatch):
    """The height stage keeps the normals' gradients only for a run that detects, and the run hands them to
    the detection, which drops them: a run's result holds none, so they are not held through the detector
    nor the writing (0.6 GB at 10000 x 8000)."""
    import weakref

    import uvps.core.pipeline as pipeline
    from uvps.files.io import read_capture

    cap = read_capture(folder, lights=folder / "lights_positions_mm.csv")
    seen = []
    real = pipeline.detection_height

    def height(*args, gradients=None, **kw):
        seen.append(weakref.ref(gradients))
        return real(*args, gradients=gradients, **kw)

    plain = pipeline.run(cap, stages=("normals", "height"))
    assert plain.height.gradients is None
    monkeypatch.setattr(pipeline, "detection_height", height)
    res = pipeline.run(cap, stages=("normals", "height", "protrusions"))
    assert res.height.gradients is None and res.protrusions is not None
    assert len(seen) == 1 and seen[0]() is None      # handed over, used, and freed with the run still held

