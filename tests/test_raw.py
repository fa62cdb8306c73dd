"""Camera raw files (.dng .cr2 .cr3 .nef .arw) read linearly by LibRaw (rawpy), on DNG files the tests
write themselves: a Bayer mosaic (RGGB) with the DNG tags LibRaw needs, its black and white levels."""
import json
import subprocess
import sys

import numpy as np
import pytest
import tifffile

rawpy = pytest.importorskip("rawpy")

from uvps.files.io import RAW_DEVELOP, read_capture, read_raw  # noqa: E402

from uvps.testing.synthetic import DNG_BLACK as BLACK, DNG_WHITE as WHITE, write_dng  # noqa: E402


def _ramps(M=48, N=64, scale=1.0):
    r, c = np.mgrid[:M, :N].astype(np.float64)
    return scale * np.stack([800 + 40 * c + 10 * r, 1500 + 25 * r + 5 * c, 300 + 12 * c + 30 * r], axis=-1)


def test_a_written_dng_is_read_by_libraw_with_its_levels(tmp_path):
    path = write_dng(tmp_path / "a.dng", _ramps())
    with rawpy.imread(str(path)) as raw:
        assert raw.raw_type == rawpy.RawType.Flat
        assert list(raw.black_level_per_channel) == [BLACK] * 4 and raw.white_level == WHITE
        assert raw.color_desc == b"RGBG"


def test_raw_values_round_trip_linearly(tmp_path):
    """Counts above the black level come back as they were: a linear ramp per channel (which bilinear
    demosaicing reproduces exactly away from the border) within 0.5 count, and twice the light gives
    twice the counts: no gamma, no automatic brightness, no white balance."""
    scene = _ramps()
    got = read_raw(write_dng(tmp_path / "a.dng", scene))
    assert got.shape == scene.shape and got.dtype == np.float32
    inner = (slice(2, -2), slice(2, -2))
    assert np.abs(got[inner] - scene[inner]).max() < 0.5
    twice = read_raw(write_dng(tmp_path / "b.dng", 2 * scene))
    ratio = twice[inner] / got[inner]
    assert np.allclose(ratio, 2.0, rtol=2e-3)
    assert RAW_DEVELOP["gamma"] == [1, 1] and RAW_DEVELOP["white_balance"] == [1, 1, 1, 1]


def _raw_capture(tmp_path, n=6, seed=3):
    """A synthetic capture written as DNG files (counts / 4: the mosaic's 14 bits)."""
    from uvps.testing.synthetic import make_capture, write_raw_capture

    cap = make_capture(shape=(96, 128), n_lights=n, seed=seed)
    folder = tmp_path / "raw_capture"
    write_raw_capture(cap, folder)
    (tmp_path / "lights.csv").write_text((folder / "lights.csv").read_text())
    (folder / "lights.csv").unlink()
    return cap, folder


def test_a_folder_of_raw_files_is_a_capture_with_its_levels_recorded(tmp_path):
    cap, folder = _raw_capture(tmp_path)
    c = read_capture(folder, pixel_size_um=15.0)
    assert c.images.shape == (6, 96, 128, 3) and c.bit_depth == "raw"
    assert c.raw["levels"][0]["black_level"] == [BLACK] * 4 and c.raw["levels"][0]["white_level"] == WHITE
    assert c.raw["saturation_counts"] == WHITE - BLACK == c.saturation
    assert c.raw["develop"]["demosaic"] == "LINEAR"
    # linear and black-subtracted: the synthetic counts / 4 (bilinear demosaic of a textured scene)
    truth = np.asarray(cap.images, np.float64)[:, 4:-4, 4:-4] / 4.0
    got = np.asarray(c.images, np.float64)[:, 4:-4, 4:-4]
    lit = truth > 50
    assert lit.mean() > 0.9 and abs(np.median(got[lit] / truth[lit]) - 1.0) < 0.01


def test_run_on_raw_files_records_the_levels_and_measures_no_additive_term(tmp_path):
    from uvps.commands import COMMANDS

    _, folder = _raw_capture(tmp_path)
    out = tmp_path / "run"
    COMMANDS["run"]({"images": [str(folder)]}, {"pixel_size_um": 15.0, "lights": str(tmp_path / "lights.csv")}, out)
    log = json.loads((out / "run.json").read_text())
    add = log["diagnostics"]["additive"]
    assert add["source"] == "raw metadata" and add["raw_black_level"] == [[BLACK] * 4]
    assert add["raw_white_level"] == [WHITE]
    assert log["diagnostics"]["raw"]["develop"]["white_balance"] == [1, 1, 1, 1]
    assert log["params"]["bit_depth"] == "raw"


def test_a_raw_file_libraw_cannot_read_is_one_line_and_nothing_written(tmp_path):
    _, folder = _raw_capture(tmp_path, n=3)
    bad = folder / "uv_01.nef"
    (folder / "uv_01.dng").unlink()
    bad.write_bytes(b"not a raw file at all" * 100)
    out = tmp_path / "run"
    r = subprocess.run([sys.executable, "-m", "uvps", "run", str(folder), "-o", str(out), "--pixel-size-um", "15"],
                       capture_output=True, text=True, timeout=300)
    assert r.returncode == 1
    lines = [ln for ln in r.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1 and "uv_01.nef" in lines[0] and "LibRaw cannot read it" in lines[0], r.stderr
    assert not out.exists() and not list(tmp_path.glob(".run.tmp-*"))


def test_a_raw_file_of_another_sensor_size_is_one_line_and_nothing_written(tmp_path):
    """A raw file from another camera (another sensor size) among a capture's: refused naming it, exit 1."""
    _, folder = _raw_capture(tmp_path, n=3)
    (folder / "uv_02.dng").unlink()
    write_dng(folder / "uv_02.dng", _ramps(M=64, N=80))
    out = tmp_path / "run"
    r = subprocess.run([sys.executable, "-m", "uvps", "run", str(folder / "uv_00.dng"), str(folder / "uv_01.dng"),
                        str(folder / "uv_02.dng"), "-o", str(out), "--pixel-size-um", "15"],
                       capture_output=True, text=True, timeout=300)
    assert r.returncode == 1
    lines = [ln for ln in r.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1 and "uv_02.dng" in lines[0] and "(64, 80, 3)" in lines[0], r.stderr
    assert not out.exists() and not list(tmp_path.glob(".run.tmp-*"))


def test_the_raw_metadata_is_recorded_colour_matrix_and_sizes_too(tmp_path):
    """run.json's raw levels: black per CFA channel, white, the sensor's and the image's size, the camera's colour
    matrices and white balance (recorded, not applied: the counts stay the camera's channels)."""
    _, folder = _raw_capture(tmp_path, n=3)
    c = read_capture(folder, pixel_size_um=15.0)
    lv = c.raw["levels"][0]
    assert lv["black_level"] == [BLACK] * 4 and lv["white_level"] == WHITE
    assert lv["image_px"] == [128, 96] and lv["sensor_px"][0] >= 128 and lv["sensor_px"][1] >= 96
    assert np.asarray(lv["colour_matrix"]).shape == (3, 4) and np.asarray(lv["rgb_xyz_matrix"]).shape == (4, 3)
    assert len(lv["camera_white_balance"]) == 4
    assert c.raw["develop"]["colour"] == "camera raw (no colour matrix)"


def test_saturation_is_where_the_linearization_table_ends_not_at_a_white_level_no_count_reaches(tmp_path):
    """A DNG storing 12-bit codes through a LinearizationTable that ends below its WhiteLevel (as a Blackmagic Pocket
    Cinema Camera 4K's does: 65472 under 65535): its clipped pixels sit at the table's top, and that is where
    saturation is looked for, in counts above black."""
    table = np.arange(4096) * 16                                  # codes -> counts, top 65520
    scene = _ramps()
    scene[:8, :8] = 70000.0                                       # clipped by the sensor: the table's top
    path = write_dng(tmp_path / "a.dng", scene, white=65535, linearization=table)
    from uvps.files.io import raw_reading
    r = raw_reading([path])
    lv = r["levels"][0]
    assert lv["white_level"] == 65535 and lv["saturation_level"] == 65520
    assert r["saturation_counts"] == 65520 - BLACK
    got = read_raw(path)
    assert got[2:6, 2:6].min() == pytest.approx(65520 - BLACK, abs=1.0)      # clipped = the saturation counts
    inner = (slice(10, -2), slice(10, -2))
    # the codes' step (16) halved, the scene's rounding to whole counts (0.5), LibRaw's truncation to its 16 bits (1)
    assert np.abs(got[inner] - scene[inner]).max() <= 10.0


def test_a_dng_default_crop_is_applied_and_recorded(tmp_path):
    """A DNG's DefaultCrop is the image the camera means (outside it a camera leaves what is not image: a Blackmagic
    Pocket Cinema Camera 4K's last 4 columns are at 0, below its black level): read_raw keeps that window, the
    folder's header sizes agree, and run.json records it and the camera's name."""
    scene = _ramps(M=52, N=68)
    scene[:, -4:] = -BLACK                                          # dead columns: stored 0, below the black level
    _, folder = _raw_capture(tmp_path, n=3)
    crop = (2, 2, 60, 48)
    path = write_dng(tmp_path / "c.dng", scene, default_crop=crop)
    got = read_raw(path)
    assert got.shape == (48, 60, 3)
    inner = (slice(2, -2), slice(2, -2))
    assert np.abs(got[inner] - scene[2:50, 2:62][inner]).max() < 0.5
    c = read_capture(folder, pixel_size_um=15.0)
    lv = c.raw["levels"][0]
    assert lv["default_crop_px"] is None and lv["camera"] == "uvps test camera"
    from uvps.files.io import raw_reading
    lv = raw_reading([path])["levels"][0]
    assert lv["default_crop_px"] == list(crop) and lv["image_px"] == [60, 48] and lv["sensor_px"] == [68, 52]
    from uvps.files.io import _image_size
    assert _image_size(path) == (48, 60)


def test_a_linear_dng_is_refused_naming_it_and_nothing_written(tmp_path):
    """A linear DNG (three values per pixel, demosaiced: Adobe's converter, a phone's) is refused by name with what to
    do, one line, exit 1, nothing written: as a real Canon EOS 6D file saved so by Camera Raw is."""
    _, folder = _raw_capture(tmp_path, n=3)
    (folder / "uv_01.dng").unlink()
    rgb = (_ramps(M=96, N=128) + BLACK).astype(np.uint16)
    tifffile.imwrite(folder / "uv_01.dng", rgb, photometric=34892, subfiletype=0, metadata=None,
                     extratags=[(50706, "B", 4, (1, 4, 0, 0), True), (50708, "s", 0, "uvps test camera", True),
                                (50714, "H", 1, (BLACK,), True), (50717, "H", 1, (WHITE,), True),
                                (50721, "2i", 9, (1, 1, 0, 1, 0, 1, 0, 1, 1, 1, 0, 1, 0, 1, 0, 1, 1, 1), True)])
    with rawpy.imread(str(folder / "uv_01.dng")) as raw:
        assert raw.raw_type == rawpy.RawType.Stack               # LibRaw reads it: uvps refuses it
    out = tmp_path / "run"
    r = subprocess.run([sys.executable, "-m", "uvps", "run", str(folder), "-o", str(out), "--pixel-size-um", "15",
                        "--lights", str(tmp_path / "lights.csv")], capture_output=True, text=True, timeout=300)
    assert r.returncode == 1
    lines = [ln for ln in r.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1 and "uv_01.dng" in lines[0] and "Stack raw file" in lines[0] and "linear DNG" in lines[0]
    assert "TIFF" in lines[0], r.stderr
    assert not out.exists() and not list(tmp_path.glob(".run.tmp-*"))


def test_a_truncated_raw_file_is_refused_naming_it(tmp_path):
    """A raw file cut short (a copy interrupted, a sample stripped of its image data, as the public file-type and
    metadata-extractor samples are): one line naming the file and LibRaw's reason, in words."""
    path = write_dng(tmp_path / "a.dng", _ramps(M=96, N=128))
    cut = tmp_path / "cut.dng"
    cut.write_bytes(path.read_bytes()[:4000])
    from uvps.errors import UVPSInputError
    with pytest.raises(UVPSInputError) as e:
        read_raw(cut)
    msg = str(e.value)
    assert "cut.dng" in msg and "LibRaw cannot read it" in msg and "b'" not in msg and "\n" not in msg


def test_uvps_info_says_how_the_raw_files_were_read(tmp_path):
    """``uvps info RUN`` on a run of raw files: the camera, its mosaic, black per channel, white and saturation levels
    and counts, the colour matrix recorded and not applied, the reader; a run of TIFFs has no such line."""
    from uvps.commands import COMMANDS
    from uvps.commands.info import info_text
    from uvps.files.runfolder import describe

    _, folder = _raw_capture(tmp_path, n=4)
    out = tmp_path / "run"
    COMMANDS["run"]({"images": [str(folder)]}, {"pixel_size_um": 15.0, "lights": str(tmp_path / "lights.csv")}, out)
    raw_lines = [ln for ln in info_text(describe(out)).splitlines() if ln.startswith("raw files:")]
    assert raw_lines[0] == (f"raw files:  uvps test camera, RGBG mosaic, black {BLACK}, white {WHITE}, saturation "
                            f"{WHITE} ({WHITE - BLACK} counts above black); colour matrix recorded, not applied")
    assert raw_lines[1].startswith("raw files:  read by LibRaw ")
    r = subprocess.run([sys.executable, "-m", "uvps", "info", str(out)], capture_output=True, text=True, timeout=120)
    assert r.returncode == 0 and raw_lines[0] in r.stdout
    (out / "run.json").write_text(json.dumps(dict(json.loads((out / "run.json").read_text()), diagnostics={})))
    assert "raw files:" not in info_text(describe(out))


def test_a_raw_file_of_another_size_in_a_capture_folder_is_refused_not_left_out(tmp_path):
    """In a folder, an image of another size is left out (a thumbnail, a preview); a raw file is no thumbnail: another
    size is another camera or mode (a real Canon EOS 6D linear DNG of 1224 x 816 among 600 x 800 frames was left
    out in silence). One line naming it, exit 1, nothing written."""
    _, folder = _raw_capture(tmp_path, n=4)
    write_dng(folder / "uv_04.dng", _ramps(M=64, N=80))
    out = tmp_path / "run"
    r = subprocess.run([sys.executable, "-m", "uvps", "run", str(folder), "-o", str(out), "--pixel-size-um", "15"],
                       capture_output=True, text=True, timeout=300)
    assert r.returncode == 1
    lines = [ln for ln in r.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1 and "uv_04.dng" in lines[0] and "camera raw file of another size (64 x 80 px" in lines[0]
    assert "96 x 128" in lines[0], r.stderr
    assert not out.exists() and not list(tmp_path.glob(".run.tmp-*"))


def test_the_raw_benchmark_reads_refuses_and_rebuilds_a_dng_keeping_its_tags(tmp_path):
    """scripts/benchmark_raw.py on files the test writes: a DNG with a LinearizationTable and a DefaultCrop is read
    (levels, crop, counts against LibRaw's mosaic within a count); a truncated DNG and a ``.kdc`` are refused by name;
    a capture built on the DNG keeps its tags (camera, black, white, the table) and holds its counts times each lamp's
    shading, as LibRaw reads them back."""
    sys.path.insert(0, str(__import__("pathlib").Path(__file__).resolve().parents[1] / "scripts"))
    import benchmark_raw

    folder = tmp_path / "raw"
    folder.mkdir()
    table = np.arange(4096) * 16
    r, c = np.mgrid[:220, :300].astype(np.float64)
    scene = np.stack([20000 + 30 * c, 30000 + 40 * r, 15000 + 20 * (r + c)], axis=-1)
    dng = write_dng(folder / "cam.dng", scene, white=65535, linearization=table, default_crop=(4, 2, 292, 216))
    (folder / "cut.dng").write_bytes(dng.read_bytes()[:3000])
    (folder / "old.kdc").write_bytes(b"\0" * 100)
    rows = {row["name"]: row for row in (benchmark_raw.describe(p) for p in sorted(folder.iterdir()))}
    cam = rows["cam.dng"]
    assert cam["read"] and cam["camera"] == "uvps test camera" and cam["size_px"] == [292, 216]
    assert cam["black"] == [BLACK] * 4 and cam["white"] == 65535 and cam["saturation"] == 65520
    assert cam["default_crop_px"] == [4, 2, 292, 216] and cam["vs_mosaic_max_counts"] <= 1.0
    assert not rows["cut.dng"]["read"] and "LibRaw cannot read it" in rows["cut.dng"]["refused"]
    assert not rows["old.kdc"]["read"] and "not a supported image file" in rows["old.kdc"]["refused"]
    text = benchmark_raw.render_doc({"rows": list(rows.values())})
    assert "| cam.dng |" in text and "65535 / 65520" in text and "refused: LibRaw cannot read it" in text

    made = benchmark_raw.render_capture(dng, tmp_path / "made", crop=(96, 128), n_lights=4)
    r0, c0 = made["window"][:2]
    assert r0 % 2 == 0 and c0 % 2 == 0 and 2 <= r0 <= 216 + 2 - 96 and 4 <= c0 <= 292 + 4 - 128
    truth = np.load(tmp_path / "made" / "truth.npz")
    with rawpy.imread(str(dng)) as raw:
        real = raw.raw_image_visible[r0:r0 + 96, c0:c0 + 128].astype(np.float64) - BLACK
    assert np.array_equal(truth["real"], real)
    lv = benchmark_raw.describe(tmp_path / "made" / "capture" / "uv_00.dng")
    assert lv["camera"] == "uvps test camera" and lv["black"] == [BLACK] * 4 and lv["saturation"] == 65520
    from uvps.testing.synthetic import render_images
    from uvps.testing.synthetic_capture import make_capture
    cap = make_capture(shape=(96, 128), n_lights=4, seed=benchmark_raw.SEED, rgb=False,
                       pixel_size_um=benchmark_raw.PIXEL_UM)
    shading = render_images(cap.height_um, np.ones((96, 128)), pixel_size_um=benchmark_raw.PIXEL_UM,
                            light_positions_mm=cap.light_positions_mm, intensities=cap.intensities, noise=False,
                            dtype=None, exposure=1.0)
    shading /= shading.max()
    for k in range(4):
        with rawpy.imread(str(tmp_path / "made" / "capture" / f"uv_{k:02d}.dng")) as raw:
            got = raw.raw_image_visible.astype(np.float64) - BLACK
        want = real * shading[k]
        # the table's step (16) halved, and the lamp's own shot noise (variance a * counts) within 5 sigma
        noise = np.sqrt(made["shot_noise_variance_per_count"] * want)
        assert (np.abs(got - want) <= 8.0 + 5 * noise + 1e-9).all()


def test_a_black_level_per_channel_is_subtracted_per_channel_and_nothing_rescaled(tmp_path):
    """A DNG whose black level differs per CFA site (500 / 510 / 520 / 530, as cameras with per-channel masked-area
    blacks write them): each channel comes back as the scene's counts above its own black within 0.5 count (LibRaw
    scales by white less the smallest black: dividing by the largest read 4.5 counts low per 2000), recorded per
    channel; saturation is looked for at the white level less the largest black (the channel that saturates first)."""
    scene = _ramps()
    path = write_dng(tmp_path / "a.dng", scene, black=(500, 510, 520, 530))
    from uvps.files.io import raw_reading
    r = raw_reading([path])
    assert sorted(r["levels"][0]["black_level"]) == [500, 510, 520, 530]
    assert r["saturation_counts"] == WHITE - 530
    got = read_raw(path)
    inner = (slice(2, -2), slice(2, -2))
    assert np.abs(got[inner] - scene[inner]).max() < 0.5


def test_masked_areas_give_the_black_level_per_channel_and_are_cut_off(tmp_path):
    """A DNG with 8 masked (optically black) columns at the left, its ActiveArea beside them, MaskedAreas naming them,
    and a BlackLevel tag of 512 that the masked pixels (600 +- 2) contradict: LibRaw measures each channel's black
    from the masked pixels (its integer mean, 599-600), uvps records those, reads only the active area, and the counts
    come back above them within a count (LibRaw's black is a whole count)."""
    M, N, L = 48, 64, 8
    scene = _ramps(M=M, N=N)
    pattern = np.array([[0, 1], [1, 2]])
    ch = pattern[np.arange(M)[:, None] % 2, np.arange(N)[None, :] % 2]
    full = np.full((M, N + L), 600.0)
    full[:, L:] += np.take_along_axis(scene, ch[..., None], axis=2)[..., 0]
    full[:, :L] += np.random.default_rng(0).normal(0, 2, (M, L))
    eye = (1, 1, 0, 1, 0, 1, 0, 1, 1, 1, 0, 1, 0, 1, 0, 1, 1, 1)
    tifffile.imwrite(tmp_path / "m.dng", np.rint(full).astype(np.uint16), photometric=32803, subfiletype=0,
                     metadata=None,
                     extratags=[(33421, "H", 2, (2, 2), True), (33422, "B", 4, (0, 1, 1, 2), True),
                                (50706, "B", 4, (1, 4, 0, 0), True), (50708, "s", 0, "uvps test camera", True),
                                (50714, "H", 1, (512,), True), (50717, "H", 1, (WHITE,), True),
                                (50721, "2i", 9, eye, True), (50829, "I", 4, (0, L, M, N + L), True),   # ActiveArea
                                (50830, "I", 4, (0, 0, M, L), True)])                                  # MaskedAreas
    from uvps.files.io import raw_reading
    lv = raw_reading([tmp_path / "m.dng"])["levels"][0]
    assert all(599 <= b <= 600 for b in lv["black_level"]) and lv["margins_px"] == [L, 0]
    assert lv["image_px"] == [N, M] and lv["sensor_px"] == [N + L, M]
    got = read_raw(tmp_path / "m.dng")
    inner = (slice(2, -2), slice(2, -2))
    assert got.shape == (M, N, 3) and np.abs(got[inner] - scene[inner]).max() <= 1.0
