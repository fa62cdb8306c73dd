"""The TIFFs written by uvps.files.io.write_imagej_tiff, opened in the real ImageJ 1.x: hyperstack
dimensions (channels as channels), the micrometre calibration, slice labels, values."""
import numpy as np
import pytest

from uvps.files.io import write_imagej_tiff

pytestmark = pytest.mark.imagej

MACRO = '''open("%s");
getDimensions(w, h, c, z, t);
getPixelSize(unit, pw, ph);
print("dims " + w + " " + h + " " + c + " " + z + " " + t);
print("bits " + bitDepth());
print("scale " + unit + " " + d2s(pw, 6) + " " + d2s(ph, 6));
Stack.setPosition(%d, %d, 1);
print("label " + getInfo("slice.label"));
print("value " + d2s(getPixel(%d, %d), 4));
'''


def _open(run_macro, bare_imagej_home, path, c=1, z=1, x=0, y=0):
    result = run_macro(MACRO % (path, c, z, x, y), home=bare_imagej_home).check()
    return dict(line.split(" ", 1) for line in result.log_text.splitlines() if " " in line)


def test_channels_calibration_and_labels_in_imagej(run_macro, bare_imagej_home, tmp_path):
    rng = np.random.default_rng(2)
    data = rng.normal(size=(4, 3, 6, 7)).astype(np.float32)  # K=4 images, RGB, 6 x 7
    path = tmp_path / "flatfield.tif"
    write_imagej_tiff(path, data, axes="ZCYX", pixel_size_um=15.0, labels=["R", "G", "B"])
    out = _open(run_macro, bare_imagej_home, path, c=2, z=3, x=5, y=4)
    assert out["dims"] == "7 6 3 4 1"
    assert out["bits"] == "32"
    unit, pw, ph = out["scale"].split()
    assert unit in ("micron", "microns", "\u00b5m") and float(pw) == pytest.approx(15.0, rel=1e-5)
    assert float(ph) == pytest.approx(15.0, rel=1e-5)
    assert out["label"] == "G"
    assert float(out["value"]) == pytest.approx(data[2, 1, 4, 5], abs=1e-4)


def test_int32_labels_open_as_16_bit(run_macro, bare_imagej_home, tmp_path):
    labels = np.zeros((5, 8), np.int32)
    labels[1:3, 2:6] = 40000
    path = tmp_path / "protrusions_labels.tif"
    write_imagej_tiff(path, labels, axes="YX", pixel_size_um=2.5)
    out = _open(run_macro, bare_imagej_home, path, x=3, y=2)
    assert out["dims"] == "8 5 1 1 1" and out["bits"] == "16"
    assert float(out["value"]) == 40000
    assert float(out["scale"].split()[1]) == pytest.approx(2.5, rel=1e-5)
