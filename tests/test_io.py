"""Tests of uvps.files.io: reading captures and light files, writing ImageJ TIFFs."""
import json
import os
from pathlib import Path

import cv2
import imageio.v3 as iio
import numpy as np
import pytest
import tifffile

from uvps.errors import UVPSInputError
from uvps.files.io import (
    Capture,
    imagej_tiff_writer,
    read_capture,
    read_lp,
    read_positions,
    read_tiff,
    sha256_file,
    srgb_to_linear,
    write_imagej_tiff,
)


def _images(k=4, shape=(12, 16), dtype=np.uint16, rgb=False, seed=0):
    rng = np.random.default_rng(seed)
    hi = 1.0 if dtype == np.float32 else np.iinfo(dtype).max - 1
    full = (k,) + shape + ((3,) if rgb else ())
    arr = rng.uniform(1, hi, full) if dtype == np.float32 else rng.integers(1, hi, full)
    return arr.astype(dtype)


def _write_tiffs(folder, arr, px=None, names=None):
    paths = []
    for i, img in enumerate(arr):
        p = folder / (names[i] if names else f"img{i + 1}.tif")
        kw = {}
        if px is not None:
            kw = dict(resolution=(1e4 / px, 1e4 / px), resolutionunit="CENTIMETER")
        tifffile.imwrite(p, img, photometric="rgb" if img.ndim == 3 else "minisblack", **kw)
        paths.append(p)
    return paths


def _snapshot(folder):
    return {p: (p.stat().st_mtime_ns, sha256_file(p)) for p in sorted(folder.rglob("*")) if p.is_file()}


@pytest.mark.parametrize("dtype", [np.uint8, np.uint16, np.float32])
@pytest.mark.parametrize("rgb", [False, True])
def test_folder_of_tiffs_keeps_counts_and_natural_order(tmp_path, dtype, rgb):
    arr = _images(k=11, dtype=dtype, rgb=rgb)
    names = [f"img{i}.tif" for i in range(1, 12)]  # img10 after img9 only in natural order
    _write_tiffs(tmp_path, arr, px=12.5, names=names)
    (tmp_path / "notes.csv").write_text("a,b\n")
    (tmp_path / "capture.lp").write_text("0\n")
    (tmp_path / "sub").mkdir()
    before = _snapshot(tmp_path)
    cap = read_capture(tmp_path)
    assert isinstance(cap, Capture)
    assert [os.path.basename(f) for f in cap.files] == names
    # integer files needing no conversion keep their dtype (half the memory), float stays float32
    assert cap.images.dtype == np.dtype(dtype) and cap.images.shape == arr.shape
    np.testing.assert_array_equal(cap.images, arr.astype(np.float32))
    assert cap.pixel_size_um == pytest.approx(12.5, rel=1e-6)
    assert cap.bit_depth == np.dtype(dtype).name
    expected_sat = None if dtype == np.float32 else float(np.iinfo(dtype).max)
    assert cap.saturation == expected_sat
    assert _snapshot(tmp_path) == before


def test_list_of_files_and_explicit_pixel_size_overrides_tags(tmp_path):
    arr = _images(k=3)
    paths = _write_tiffs(tmp_path, arr, px=10.0)
    cap = read_capture([str(p) for p in paths[::-1]], pixel_size_um=4.0)
    assert cap.pixel_size_um == 4.0
    np.testing.assert_array_equal(cap.images, arr[::-1].astype(np.float32))
    # a list holding one folder is that folder
    np.testing.assert_array_equal(read_capture([str(tmp_path)]).images, arr.astype(np.float32))


def test_png_16bit_grey_and_rgb_are_not_reduced(tmp_path):
    grey = _images(k=3, dtype=np.uint16)
    rgb = _images(k=3, dtype=np.uint16, rgb=True, seed=1)
    for i in range(3):
        iio.imwrite(tmp_path / f"g{i}.png", grey[i])
        # Pillow cannot write 16-bit RGB PNGs; OpenCV writes BGR order.
        cv2.imwrite(str(tmp_path / f"c{i}.png"), rgb[i][..., ::-1])
    cap = read_capture([tmp_path / f"g{i}.png" for i in range(3)], pixel_size_um=5)
    np.testing.assert_array_equal(cap.images, grey.astype(np.float32))
    cap = read_capture([tmp_path / f"c{i}.png" for i in range(3)], pixel_size_um=5)
    np.testing.assert_array_equal(cap.images, rgb.astype(np.float32))
    assert cap.saturation == 65535.0


def test_rgba_png_drops_alpha(tmp_path):
    arr = _images(k=3, dtype=np.uint8, rgb=True)
    for i in range(3):
        rgba = np.concatenate([arr[i], np.full(arr[i].shape[:2] + (1,), 7, np.uint8)], axis=2)
        iio.imwrite(tmp_path / f"a{i}.png", rgba)
    cap = read_capture(tmp_path, pixel_size_um=5)
    np.testing.assert_array_equal(cap.images, arr.astype(np.float32))


def test_jpeg_linearised_by_default_and_not_with_none(tmp_path):
    arr = np.stack([np.full((16, 16, 3), v, np.uint8) for v in (40, 128, 200)])
    for i, img in enumerate(arr):
        iio.imwrite(tmp_path / f"j{i}.jpg", img, quality=100)
    raw = read_capture(tmp_path, pixel_size_um=5, linearize="none")
    lin = read_capture(tmp_path, pixel_size_um=5)
    v = raw.images[:, 8, 8, 0] / 255.0
    expected = np.where(v <= 0.04045, v / 12.92, ((v + 0.055) / 1.055) ** 2.4) * 255.0
    np.testing.assert_allclose(lin.images[:, 8, 8, 0], expected, rtol=1e-5)
    # sRGB mid-grey 128 is about 21.6 % linear, still in 0..255 counts
    assert lin.images[1, 8, 8, 0] == pytest.approx(0.2159 * 255, abs=1.0)


def test_srgb_option_linearises_png_and_auto_does_not(tmp_path):
    arr = _images(k=3, dtype=np.uint8)
    for i in range(3):
        iio.imwrite(tmp_path / f"p{i}.png", arr[i])
    auto = read_capture(tmp_path, pixel_size_um=5)
    srgb = read_capture(tmp_path, pixel_size_um=5, linearize="srgb")
    np.testing.assert_array_equal(auto.images, arr.astype(np.float32))
    np.testing.assert_allclose(srgb.images, srgb_to_linear(arr.astype(np.float32), 255.0))
    assert np.all(srgb.images <= auto.images + 1e-3)


@pytest.mark.parametrize("axes,shape,colour", [
    ("ZYX", (5, 10, 12), False),
    ("ZCYX", (4, 3, 10, 12), True),
    ("TZYX", (2, 3, 10, 12), False),
])
def test_imagej_hyperstack_is_one_capture(tmp_path, axes, shape, colour):
    rng = np.random.default_rng(3)
    data = rng.integers(1, 60000, shape).astype(np.uint16)
    p = tmp_path / "stack.tif"
    write_imagej_tiff(p, data, axes=axes, pixel_size_um=7.5)
    cap = read_capture(p)
    if colour:
        expected = np.moveaxis(data, 1, -1)
    else:
        expected = data.reshape((-1,) + shape[-2:])
    np.testing.assert_array_equal(cap.images, expected.astype(np.float32))
    assert cap.files[0] == f"{tmp_path / 'stack.tif'}#1" and len(cap.files) == expected.shape[0]
    assert cap.pixel_size_um == pytest.approx(7.5, rel=1e-6)


def test_plain_multipage_rgb_stack(tmp_path):
    data = _images(k=4, dtype=np.uint8, rgb=True)
    p = tmp_path / "s.tif"
    tifffile.imwrite(p, data, photometric="rgb")
    cap = read_capture([p], pixel_size_um=2)
    np.testing.assert_array_equal(cap.images, data.astype(np.float32))


def test_dark_frame_subtracted_and_clipped(tmp_path):
    arr = _images(k=3, dtype=np.uint16)
    cap_dir = tmp_path / "cap"
    cap_dir.mkdir()
    _write_tiffs(cap_dir, arr, px=5)
    dark = np.full(arr.shape[1:], 30000, np.uint16)
    tifffile.imwrite(tmp_path / "dark.tif", dark)
    cap = read_capture(cap_dir, dark=tmp_path / "dark.tif")
    np.testing.assert_array_equal(cap.images, np.maximum(arr.astype(np.float32) - 30000, 0))


def test_mask_read_and_checked(tmp_path):
    arr = _images(k=3)
    _write_tiffs(tmp_path, arr, px=5)
    m = np.zeros(arr.shape[1:], np.uint8)
    m[2:5, 3:9] = 255
    mpath = tmp_path.parent / (tmp_path.name + "_mask.png")
    iio.imwrite(mpath, m)
    cap = read_capture(tmp_path, mask=mpath)
    np.testing.assert_array_equal(cap.mask, m > 0)
    with pytest.raises(UVPSInputError, match="empty"):
        read_capture(tmp_path, mask=np.zeros(arr.shape[1:], bool))
    with pytest.raises(UVPSInputError, match=r"mask has shape \(3, 3\)"):
        read_capture(tmp_path, mask=np.ones((3, 3), bool))


def test_lp_file_matched_by_name(tmp_path):
    arr = _images(k=3)
    _write_tiffs(tmp_path, arr, px=5, names=["a.tif", "b.tif", "c.tif"])
    dirs = np.array([[1, 0, 1], [0, 2, 2], [-3, 0, 3]], float)
    lp = tmp_path / "lights.lp"
    # listed in another order, with Windows-style folders
    lp.write_text("3\n" + "".join(
        f"C:\\cap\\{n} {d[0]} {d[1]} {d[2]}\n" for n, d in zip(["c.tif", "a.tif", "b.tif"], dirs[[2, 0, 1]])))
    cap = read_capture(tmp_path, lights=lp)
    np.testing.assert_allclose(cap.light_directions, dirs / np.linalg.norm(dirs, axis=1)[:, None])
    np.testing.assert_allclose(np.linalg.norm(read_lp(lp).directions, axis=1), 1.0)


def test_lp_errors_name_the_file(tmp_path):
    arr = _images(k=3)
    _write_tiffs(tmp_path, arr, px=5, names=["a.tif", "b.tif", "c.tif"])
    lp = tmp_path / "l.lp"
    lp.write_text("3\na.tif 0 0 1\nb.tif 0 1 1\nzzz.tif 1 0 1\n")
    with pytest.raises(UVPSInputError, match=r"l\.lp.*zzz\.tif"):
        read_capture(tmp_path, lights=lp)
    lp.write_text("2\na.tif 0 0 1\nb.tif 0 1 1\n")
    with pytest.raises(UVPSInputError, match=r"l\.lp lists 2 lights for 3 images"):
        read_capture(tmp_path, lights=lp)
    lp.write_text("4\na.tif 0 0 1\nb.tif 0 1 1\n")
    with pytest.raises(UVPSInputError, match="announces 4"):
        read_lp(lp)


def test_lp_fourth_column_gives_intensities_in_image_order(tmp_path):
    arr = _images(k=3)
    _write_tiffs(tmp_path, arr, px=5, names=["a.tif", "b.tif", "c.tif"])
    lp = tmp_path.parent / (tmp_path.name + "_i.lp")
    # a comment and a blank line do not shift the line numbers; listed in another order
    lp.write_text("# lights with intensities\n3\n\nc.tif 0 0 1 0.5\na.tif 1 0 1 2\nb.tif 0 1 1 1.25\n")
    lf = read_lp(lp)
    assert lf.files == ["c.tif", "a.tif", "b.tif"]
    np.testing.assert_allclose(lf.intensities, [0.5, 2.0, 1.25])
    cap = read_capture(tmp_path, lights=lp)
    np.testing.assert_allclose(cap.light_intensities, [2.0, 1.25, 0.5])
    np.testing.assert_allclose(cap.light_directions[0], np.array([1, 0, 1]) / np.sqrt(2))
    # the usual three columns: no intensities (uvps takes them as equal)
    lp.write_text("3\nc.tif 0 0 1\na.tif 1 0 1\nb.tif 0 1 1\n")
    assert read_lp(lp).intensities is None and read_capture(tmp_path, lights=lp).light_intensities is None


@pytest.mark.parametrize("bad,match", [
    ("0", r"must be a finite number > 0"), ("-1.5", r"must be a finite number > 0"),
    ("nan", r"must be a finite number > 0"), ("inf", r"must be a finite number > 0"),
    ("bright", r"'bright' is not a number"),
])
def test_lp_bad_intensity_is_one_line_naming_file_and_line(tmp_path, bad, match):
    lp = tmp_path / "l.lp"
    lp.write_text(f"3\na.tif 0 0 1 1\n# a comment\nb.tif 0 1 1 {bad}\nc.tif 1 0 1 1\n")
    with pytest.raises(UVPSInputError, match=r"l\.lp line 4: intensity .*" + match) as err:
        read_lp(lp)
    assert "\n" not in str(err.value)


def test_lp_intensity_column_on_every_line_or_none(tmp_path):
    lp = tmp_path / "l.lp"
    lp.write_text("3\na.tif 0 0 1\nb.tif 0 1 1 2.0\nc.tif 1 0 1\n")
    with pytest.raises(UVPSInputError, match=r"l\.lp line 3 has intensity column but line 2 does not"):
        read_lp(lp)
    lp.write_text("3\na.tif 0 0 1 1\nb.tif 0 1 1\nc.tif 1 0 1 1\n")
    with pytest.raises(UVPSInputError, match=r"l\.lp line 3 has no intensity column but line 2 does"):
        read_lp(lp)
    lp.write_text("3\na.tif 0 0 1\nb.tif 0 one 1\nc.tif 1 0 1\n")
    with pytest.raises(UVPSInputError, match=r"l\.lp line 3: expected 'file x y z \[intensity\]'"):
        read_lp(lp)


def test_positions_csv_intensity_column(tmp_path):
    arr = _images(k=3)
    _write_tiffs(tmp_path, arr, px=5, names=["a.tif", "b.tif", "c.tif"])
    pos = np.array([[100.0, 0, 300], [0, 100, 300], [-100, 0, 300]])
    csvp = tmp_path.parent / (tmp_path.name + "_posi.csv")
    csvp.write_text("file,x_mm,y_mm,z_mm,intensity\n" + "".join(
        f"{n},{p[0]},{p[1]},{p[2]},{e}\n" for n, p, e in zip(["b.tif", "c.tif", "a.tif"], pos[[1, 2, 0]],
                                                             [0.9, 1.3, 1.1])))
    cap = read_capture(tmp_path, lights=csvp)
    np.testing.assert_allclose(cap.light_positions_mm, pos)
    np.testing.assert_allclose(cap.light_intensities, [1.1, 0.9, 1.3])
    csvp.write_text("file,x_mm,y_mm,z_mm,intensity\na.tif,1,0,300,1\nb.tif,0,1,300,\nc.tif,0,0,300,1\n")
    with pytest.raises(UVPSInputError, match=r"_posi\.csv line 3: intensity '' is not a number"):
        read_positions(csvp)
    csvp.write_text("file,x_mm,y_mm,z_mm,intensity\na.tif,1,0,300,1\nb.tif,0,1,300,1\nc.tif,0,0,300,-2\n")
    with pytest.raises(UVPSInputError, match=r"_posi\.csv line 4: intensity '-2' must be a finite number > 0"):
        read_positions(csvp)
    # uvps lights.json: the intensities it wrote are read back
    jp = tmp_path.parent / (tmp_path.name + "_li.json")
    jp.write_text(json.dumps({"lights": [{"file": n, "position_mm": list(p), "intensity": e}
                                         for n, p, e in zip(["a.tif", "b.tif", "c.tif"], pos, [1.0, 0.8, 1.2])]}))
    np.testing.assert_allclose(read_capture(tmp_path, lights=jp).light_intensities, [1.0, 0.8, 1.2])


def test_positions_csv_and_lights_json(tmp_path):
    arr = _images(k=3)
    _write_tiffs(tmp_path, arr, px=5, names=["a.tif", "b.tif", "c.tif"])
    pos = np.array([[100.0, 0, 300], [0, 100, 300], [-100, 0, 300]])
    csvp = tmp_path.parent / (tmp_path.name + "_pos.csv")
    csvp.write_text("file,x_mm,y_mm,z_mm\n" + "".join(
        f"{n},{p[0]},{p[1]},{p[2]}\n" for n, p in zip(["b.tif", "c.tif", "a.tif"], pos[[1, 2, 0]])))
    cap = read_capture(tmp_path, lights=csvp)
    np.testing.assert_allclose(cap.light_positions_mm, pos)
    assert cap.light_directions is None
    # no file column: image order
    csvp.write_text("x_mm,y_mm,z_mm\n" + "".join(f"{p[0]},{p[1]},{p[2]}\n" for p in pos))
    np.testing.assert_allclose(read_capture(tmp_path, lights=csvp).light_positions_mm, pos)
    jp = tmp_path.parent / (tmp_path.name + "_lights.json")
    doc = {"mode": "near", "lights": [
        {"file": n, "direction": list(p / np.linalg.norm(p)), "position_mm": list(p)}
        for n, p in zip(["a.tif", "b.tif", "c.tif"], pos)]}
    jp.write_text(json.dumps(doc))
    lp = read_positions(jp)
    assert lp.files == ["a.tif", "b.tif", "c.tif"]
    cap = read_capture(tmp_path, lights=jp)
    np.testing.assert_allclose(cap.light_positions_mm, pos)
    np.testing.assert_allclose(cap.light_directions, pos / np.linalg.norm(pos, axis=1)[:, None])


def test_pixel_size_required_for_png_and_validated(tmp_path):
    arr = _images(k=3, dtype=np.uint8)
    for i in range(3):
        iio.imwrite(tmp_path / f"p{i}.png", arr[i])
    with pytest.raises(UVPSInputError, match="--pixel-size-um"):
        read_capture(tmp_path)
    for bad in (0, -1, float("nan"), float("inf"), "abc"):
        with pytest.raises(UVPSInputError, match="pixel_size_um"):
            read_capture(tmp_path, pixel_size_um=bad)


def test_uncalibrated_tiff_needs_pixel_size(tmp_path):
    _write_tiffs(tmp_path, _images(k=3))
    with pytest.raises(UVPSInputError, match="pixel size unknown"):
        read_capture(tmp_path)


@pytest.mark.parametrize("dpi,expected_um", [(72, None), (300, None), (2540, 10.0)])
def test_inch_resolution_defaults_are_not_a_calibration(tmp_path, dpi, expected_um):
    for i, img in enumerate(_images(k=3)):
        tifffile.imwrite(tmp_path / f"i{i}.tif", img, resolution=(dpi, dpi), resolutionunit="INCH")
    if expected_um is None:
        with pytest.raises(UVPSInputError, match="software default"):
            read_capture(tmp_path)
    else:
        assert read_capture(tmp_path).pixel_size_um == pytest.approx(expected_um, rel=1e-6)


def test_files_with_different_calibrations(tmp_path):
    arr = _images(k=3)
    paths = _write_tiffs(tmp_path, arr[:2], px=10.0)
    paths += _write_tiffs(tmp_path, arr[2:], px=12.0, names=["other.tif"])
    with pytest.raises(UVPSInputError, match=r"other\.tif has pixel size 12 um .* expected 10 um"):
        read_capture(paths)
    assert read_capture(paths, pixel_size_um=11.0).pixel_size_um == 11.0


def test_missing_mask_and_dark_are_named(tmp_path):
    _write_tiffs(tmp_path, _images(k=3), px=5)
    with pytest.raises(UVPSInputError, match=r"mask file .*nomask\.png does not exist"):
        read_capture(tmp_path, mask=tmp_path / "nomask.png")
    with pytest.raises(UVPSInputError, match=r"dark frame .*nodark\.tif does not exist"):
        read_capture(tmp_path, dark=tmp_path / "nodark.tif")


def test_bad_inputs_one_line_messages(tmp_path):
    arr = _images(k=3)
    paths = _write_tiffs(tmp_path, arr, px=5)

    def raises(match, *args, **kw):
        with pytest.raises(UVPSInputError, match=match) as info:
            read_capture(*args, **kw)
        assert "\n" not in str(info.value)

    raises("at least 3 images; got 2", paths[:2])
    raises("does not exist", tmp_path / "nope")
    raises("does not exist", [paths[0], tmp_path / "nope.tif", paths[1]])
    other = tmp_path.parent / (tmp_path.name + "_o")
    other.mkdir()
    small = _write_tiffs(other, _images(k=1, shape=(10, 16)), names=["small.tif"])[0]
    raises(r"small\.tif is \(10, 16\) uint16; expected \(12, 16\) uint16", paths[:2] + [small])
    eight = _write_tiffs(other, _images(k=1, dtype=np.uint8), names=["eight.tif"])[0]
    raises(r"eight\.tif .* uint8; expected .* uint16", paths[:2] + [eight])
    black = _write_tiffs(other, np.zeros((1, 12, 16), np.uint16), names=["black.tif"])[0]
    raises(r"black\.tif is all black", paths[:2] + [black])
    sat = _write_tiffs(other, np.full((1, 12, 16), 65535, np.uint16), names=["sat.tif"])[0]
    raises(r"sat\.tif is fully saturated", paths[:2] + [sat])
    text = other / "text.png"
    text.write_text("this is not a PNG")
    raises(r"text\.png: cannot read", paths[:2] + [text])
    trunc = other / "trunc.png"
    iio.imwrite(other / "full.png", arr[0])
    trunc.write_bytes((other / "full.png").read_bytes()[:60])
    raises(r"trunc\.png: cannot read", paths[:2] + [trunc])
    raises("linearize", tmp_path, linearize="gamma")
    raises("dark frame", tmp_path, dark=small)


def test_write_imagej_tiff_calibration_labels_and_dtypes(tmp_path):
    rng = np.random.default_rng(5)
    normals = rng.normal(size=(3, 8, 9)).astype(np.float32)
    p = tmp_path / "normals.tif"
    write_imagej_tiff(p, normals, axes="CYX", pixel_size_um=15.0, labels=["nx", "ny", "nz"])
    with tifffile.TiffFile(p) as tif:
        ij = tif.imagej_metadata
        assert ij["unit"] == "micron" and ij["channels"] == 3
        assert ij["Labels"] == ["nx", "ny", "nz"]
        num, den = tif.pages.first.tags["XResolution"].value
        assert num / den == pytest.approx(1 / 15.0, rel=1e-6)
        assert tif.series[0].axes == "CYX"
    back = read_tiff(p)
    np.testing.assert_array_equal(back.data, normals)
    assert back.pixel_size_um == pytest.approx(15.0, rel=1e-6)
    assert [f.name for f in tmp_path.iterdir()] == ["normals.tif"]  # no temp file left

    stack = rng.normal(size=(2, 3, 4, 5)).astype(np.float64)
    write_imagej_tiff(tmp_path / "ff.tif", stack, axes="ZCYX", pixel_size_um=2, labels=["R", "G", "B"])
    with tifffile.TiffFile(tmp_path / "ff.tif") as tif:
        assert tif.imagej_metadata["Labels"] == ["R", "G", "B"] * 2
        assert tif.series[0].dtype == np.float32 and tif.series[0].axes == "ZCYX"

    small_labels = np.arange(20, dtype=np.int32).reshape(4, 5) * 3000
    write_imagej_tiff(tmp_path / "l16.tif", small_labels, axes="YX", pixel_size_um=1)
    back = read_tiff(tmp_path / "l16.tif").data
    assert back.dtype == np.uint16 and np.array_equal(back, small_labels)
    big_labels = small_labels * 100
    write_imagej_tiff(tmp_path / "l32.tif", big_labels, axes="YX", pixel_size_um=1)
    back = read_tiff(tmp_path / "l32.tif").data
    assert back.dtype == np.float32 and np.array_equal(back, big_labels)


def test_write_imagej_tiff_rejects_bad_arguments(tmp_path):
    data = np.zeros((3, 4, 5), np.float32)
    with pytest.raises(UVPSInputError, match="axes"):
        write_imagej_tiff(tmp_path / "a.tif", data, axes="YX", pixel_size_um=1)
    with pytest.raises(UVPSInputError, match="axes"):
        write_imagej_tiff(tmp_path / "a.tif", data, axes="YXC", pixel_size_um=1)
    with pytest.raises(UVPSInputError, match="pixel_size_um"):
        write_imagej_tiff(tmp_path / "a.tif", data, axes="CYX", pixel_size_um=0)
    with pytest.raises(UVPSInputError, match="labels"):
        write_imagej_tiff(tmp_path / "a.tif", data, axes="CYX", pixel_size_um=1, labels=["a", "b"])
    assert not any(tmp_path.iterdir())


def test_write_is_atomic_on_failure(tmp_path, monkeypatch):
    p = tmp_path / "keep.tif"
    p.write_bytes(b"old")
    # a failure while the data are being filled (a band that cannot be computed, a full disk)
    with pytest.raises(OSError, match="disk full"):
        with imagej_tiff_writer(p, (4, 2), np.float32, axes="YX", pixel_size_um=1) as out:
            out.write(slice(0, 2), 1.0)
            raise OSError("disk full")
    assert p.read_bytes() == b"old"
    assert [f.name for f in tmp_path.iterdir()] == ["keep.tif"]

    # a failure while the file is created
    def half_write(path, **kw):
        with open(path, "wb") as fh:
            fh.write(b"partial")
        raise OSError("disk full")

    monkeypatch.setattr(tifffile, "memmap", half_write)
    with pytest.raises(OSError, match="disk full"):
        write_imagej_tiff(p, np.ones((2, 2), np.float32), axes="YX", pixel_size_um=1)
    assert p.read_bytes() == b"old"
    assert [f.name for f in tmp_path.iterdir()] == ["keep.tif"]


def test_tiff_written_band_by_band_equals_the_array(tmp_path, monkeypatch):
    """Writing in bands of a few rows (from a strided view, cast on the way) gives the file that
    holds the array; above LARGE_TIFF_BYTES the file is in ImageJ's one-IFD large-file layout."""
    import uvps.files.io

    rng = np.random.default_rng(1)
    normals = rng.normal(size=(37, 23, 3))                      # float64, channels last
    monkeypatch.setattr(uvps.files.io, "BAND_BYTES", 5 * 23 * 4)     # 5 rows per band
    write_imagej_tiff(tmp_path / "n.tif", np.moveaxis(normals, -1, 0), axes="CYX", pixel_size_um=15,
                      labels=["nx", "ny", "nz"])
    with tifffile.TiffFile(tmp_path / "n.tif") as tif:
        assert tif.series[0].axes == "CYX" and tif.imagej_metadata["Labels"] == ["nx", "ny", "nz"]
        np.testing.assert_array_equal(tif.asarray(), np.moveaxis(normals, -1, 0).astype(np.float32))
        assert len(tif.pages) == 3
    monkeypatch.setattr(uvps.files.io, "LARGE_TIFF_BYTES", 1000)
    stack = rng.integers(0, 4000, size=(4, 2, 19, 17)).astype(np.uint16)
    write_imagej_tiff(tmp_path / "big.tif", stack, axes="ZCYX", pixel_size_um=2)
    with tifffile.TiffFile(tmp_path / "big.tif") as tif:
        assert len(tif.pages) == 1 and tif.imagej_metadata["images"] == 8      # one IFD
        assert tif.series[0].axes == "ZCYX"
        np.testing.assert_array_equal(tif.asarray(), stack)
    np.testing.assert_array_equal(tifffile.memmap(tmp_path / "big.tif", mode="r"), stack)   # contiguous


def test_truncated_tiff_is_input_error(tmp_path):
    arr = _images(k=3, shape=(64, 64))
    paths = _write_tiffs(tmp_path, arr, px=5)
    data = paths[2].read_bytes()
    paths[2].write_bytes(data[: len(data) // 2])
    with pytest.raises(UVPSInputError, match=r"img3\.tif: cannot read as TIFF"):
        read_capture(paths)


@pytest.mark.parametrize("layout,linearize", [("folder", "none"), ("folder", "srgb"),
                                             ("stack", "none")])
def test_reading_holds_one_float_stack_plus_about_one_file(tmp_path, layout, linearize):
    import tracemalloc

    arr = _images(k=6, shape=(120, 160), rgb=True)
    if layout == "folder":
        _write_tiffs(tmp_path, arr, px=5)
        src = tmp_path
    else:
        src = tmp_path / "stack.tif"
        write_imagej_tiff(src, np.moveaxis(arr, -1, 1), axes="ZCYX", pixel_size_um=5)
    read_capture(src, linearize=linearize)  # warm up imports and caches
    tracemalloc.start()
    try:
        base = tracemalloc.get_traced_memory()[0]
        cap = read_capture(src, linearize=linearize)
        peak = tracemalloc.get_traced_memory()[1] - base
    finally:
        tracemalloc.stop()
    np.testing.assert_array_equal(np.asarray(cap.images)[..., 0] > 0, arr[..., 0] > 0)   # the whole stack: explicit
    one_float_image = cap.images[0].nbytes
    # the stack, one file in its own dtype (half a float32 image; a stack file is memory-mapped)
    # and, for the sRGB curve, one float32 temporary of part of an image plus a boolean mask
    assert peak <= cap.images.nbytes + (2.5 if layout == "folder" else 0.2) * one_float_image


def test_truncated_stack_is_input_error(tmp_path):
    p = tmp_path / "stack.tif"
    write_imagej_tiff(p, _images(k=4, shape=(64, 64)), axes="ZYX", pixel_size_um=5)
    data = p.read_bytes()
    p.write_bytes(data[: len(data) * 3 // 4])
    with pytest.raises(UVPSInputError, match=r"stack\.tif: truncated .* announces 4 images"):
        read_capture(p)


def test_sha256_file_matches_hashlib(tmp_path):
    import hashlib

    data = np.random.default_rng(0).bytes(3_000_001)
    p = tmp_path / "x.bin"
    p.write_bytes(data)
    assert sha256_file(p, chunk_bytes=65536) == hashlib.sha256(data).hexdigest()


def test_lp_with_a_stack_goes_by_order_and_progress_reaches_one(tmp_path):
    data = _images(k=4)
    stack = tmp_path / "stack.tif"
    write_imagej_tiff(stack, data, axes="ZYX", pixel_size_um=5)
    dirs = np.array([[1, 0, 2], [0, 1, 2], [-1, 0, 2], [0, -1, 2]], float)
    lp = tmp_path / "l.lp"
    lp.write_text("4\n" + "".join(f"photo_{i}.jpg {d[0]} {d[1]} {d[2]}\n" for i, d in enumerate(dirs)))
    calls = []
    cap = read_capture(stack, lights=lp, progress=lambda f, m: calls.append((f, m)))
    np.testing.assert_allclose(cap.light_directions, dirs / np.sqrt(5))
    fractions = [f for f, _ in calls]
    assert fractions == sorted(fractions) and fractions[-1] == 1.0 and len(calls) == 5


def test_lights_json_with_directions_only(tmp_path):
    _write_tiffs(tmp_path, _images(k=3), px=5)
    dirs = [[0.0, 0.6, 0.8], [0.6, 0.0, 0.8], [0.0, 0.0, 2.0]]
    jp = tmp_path.parent / (tmp_path.name + "_far.json")
    jp.write_text(json.dumps({"mode": "far", "lights": [{"direction": d} for d in dirs]}))
    cap = read_capture(tmp_path, lights=jp)
    assert cap.light_positions_mm is None
    np.testing.assert_allclose(cap.light_directions, [[0, 0.6, 0.8], [0.6, 0, 0.8], [0, 0, 1]])


def test_a_capture_folder_leaves_out_what_is_not_a_lamp_image(tmp_path, caplog):
    """A mask, a dark frame (by name) and a thumbnail (by size) beside 4 lamp images: never read as
    lamps, each named in the log with why; ``pattern`` chooses the files instead."""
    import logging

    rng = np.random.default_rng(0)
    for k in range(4):
        tifffile.imwrite(tmp_path / f"uv_{k:02d}.tif", rng.integers(1000, 2000, (40, 50), dtype=np.uint16))
    tifffile.imwrite(tmp_path / "mask.tif", np.full((40, 50), 255, np.uint8))
    tifffile.imwrite(tmp_path / "uv_dark.tif", np.full((40, 50), 20, np.uint16))
    tifffile.imwrite(tmp_path / "uv_04.tif", rng.integers(1000, 2000, (10, 12), dtype=np.uint16))
    with caplog.at_level(logging.INFO, logger="uvps.files.io"):
        cap = read_capture(tmp_path, pixel_size_um=15.0)
    assert [Path(f).name for f in cap.files] == [f"uv_{k:02d}.tif" for k in range(4)]
    text = caplog.text
    assert "mask.tif: a mask (give it with --mask), by its name" in text
    assert "uv_dark.tif: a dark frame (give it with --dark)" in text
    assert "uv_04.tif: another size (10 x 12 px; the lamp images are 40 x 50)" in text
    cap = read_capture(tmp_path, pixel_size_um=15.0, pattern="uv_0[0-2].tif")
    assert [Path(f).name for f in cap.files] == ["uv_00.tif", "uv_01.tif", "uv_02.tif"]
    with pytest.raises(UVPSInputError, match=r"no file of folder .* matches the pattern 'x\*'"):
        read_capture(tmp_path, pixel_size_um=15.0, pattern="x*")


class _CountingMap:
    """An image file's memory map that records which part of it each read asks for."""

    def __init__(self, arr):
        self.arr, self.shape, self.dtype, self.reads = arr, arr.shape, arr.dtype, []

    def __getitem__(self, key):
        part = self.arr[key]
        self.reads.append(part.size)
        return part


def test_a_mapped_stack_reads_a_band_not_the_whole_file_and_loads_only_when_asked():
    """The lazy-stack protocol (docs/architecture.md, "Lazy stacks"): a band of every image reads
    that band of each file; `[...]` is refused; the whole stack is `.load()`."""
    from uvps.files.io import MappedStack

    arrays = [np.full((40, 30), k, np.uint16) for k in range(3)]
    maps = [_CountingMap(a) for a in arrays]
    stack = MappedStack(maps)
    band = stack[:, 10:14]
    assert band.shape == (3, 4, 30) and [m.reads for m in maps] == [[4 * 30]] * 3
    assert stack[1, 5:7, 2:4].tolist() == [[1, 1], [1, 1]]
    with pytest.raises(IndexError, match=r"\.load\(\)"):
        stack[...]
    assert all(sum(m.reads) < m.arr.size for m in maps)
    whole = stack.load()
    assert whole.shape == (3, 40, 30) and np.array_equal(whole[2], arrays[2])
    from uvps.core.stack import Stack, load
    assert isinstance(stack, Stack) and isinstance(whole, Stack)     # an array is a stack too
    assert np.array_equal(load(stack), whole) and load(whole) is whole
