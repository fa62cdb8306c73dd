"""Real cameras' raw files through uvps, when they are at hand: the folder ``$UVPS_REAL_RAW``, else
``../shared/data/raw_cameras`` (none ships with the project; scripts/benchmark_raw.py's SOURCES names each file's
public source and licence). Skipped when neither folder exists; each file's test skipped when that file is absent.

    UVPS_REAL_RAW=/path/to/raw_cameras .venv/bin/python -m pytest tests/test_raw_real.py

What each real file holds was read with LibRaw and exiftool; the numbers asserted are the files' own.
"""
import json
import sys
from pathlib import Path

import numpy as np
import pytest

rawpy = pytest.importorskip("rawpy")

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "scripts"))
import benchmark_raw  # noqa: E402

FOLDER = benchmark_raw.default_folder()
pytestmark = pytest.mark.skipif(not FOLDER.is_dir(), reason=f"no real raw files: {FOLDER} is absent "
                                                              "(set UVPS_REAL_RAW)")


def _file(name) -> Path:
    path = FOLDER / name
    if not path.is_file():
        pytest.skip(f"{path} is absent")
    return path


def test_a_real_cinema_dng_is_read_with_its_levels_crop_and_colour_matrix():
    """Blackmagic Pocket Cinema Camera 4K (12-bit codes, lossless-JPEG tiles, a LinearizationTable ending at 65472
    under its WhiteLevel 65535, black 512, DefaultCrop 16, 8, 4096 x 2160, two colour matrices): read with the table's
    top as saturation and the crop applied, each pixel's own colour within one count of LibRaw's mosaic."""
    row = benchmark_raw.describe(_file("Blackmagic_PocketCinema4K.dng"))
    assert row["read"] and row["camera"] == "Blackmagic Pocket Cinema Camera 4K"
    assert row["black"] == [512.0] * 4 and row["white"] == 65535.0 and row["saturation"] == 65472.0
    assert row["default_crop_px"] == [16, 8, 4096, 2160] and row["size_px"] == [4096, 2160]
    assert row["colour_matrix"] and row["cfa"] == "RGBG"
    assert row["vs_mosaic_max_counts"] <= 1.0                    # LibRaw's truncation to its 16 bits
    from uvps.files.raw import read_raw
    img = read_raw(FOLDER / "Blackmagic_PocketCinema4K.dng")
    assert img.shape == (2160, 4096, 3) and img.min() >= 0 and img.max() <= 65472 - 512
    assert np.isfinite(img).all() and (img[:, -1] > 0).mean() > 0.99     # no dead column left in


@pytest.mark.parametrize("name, words", [
    ("Canon_EOS_6D_linear.dng", "Stack raw file"),               # Camera Raw's lossy linear DNG: demosaiced
    ("Nikon_COOLSCAN_IV_ED.nef", "Stack raw file"),              # a film scanner's RGB NEF
    ("Leica_M10_truncated.dng", "LibRaw cannot read it"),        # public samples cut to their first 100000 bytes
    ("Sony_ZV-E10_truncated.arw", "LibRaw cannot read it"),
    ("Nikon_truncated_issue247-1.nef", "LibRaw cannot read it"),
    ("RAW_KODAK_DC50.KDC", "not a supported image file"),        # LibRaw reads it; .kdc is not a capture's extension
])
def test_what_is_not_supported_is_refused_by_name(name, words):
    row = benchmark_raw.describe(_file(name))
    assert not row["read"] and words in row["refused"], row
    from uvps.errors import UVPSInputError
    from uvps.files.io import read_image
    with pytest.raises(UVPSInputError) as e:
        read_image(FOLDER / name)
    assert name in str(e.value) and "\n" not in str(e.value)


@pytest.mark.slow
def test_a_capture_built_on_a_real_dng_goes_through_calibrate_and_run(tmp_path):
    """Eight lamp images and a sphere capture built on the real DNG (its tags, its sensor's counts as the albedo, the
    shading of a known relief: scripts/benchmark_raw.py) through ``uvps calibrate --spheres`` and ``uvps run``: the
    spheres' lamp directions within 1 deg of the truth, the normals with the true lamps within 0.5 deg (median),
    with the sphere calibration (directions only, the lamps' own intensities unknown to it) within 4 deg (2 with
    ``--estimate-intensities``); run.json
    records the file's camera, black per channel, white and saturation levels."""
    made = benchmark_raw.render_capture(_file("Blackmagic_PocketCinema4K.dng"), tmp_path / "made")
    assert made["clipped_real_px"] == 0
    res = benchmark_raw.run_capture(tmp_path / "made")
    assert res["lamp_direction_deg_max"] < 1.0
    assert res["lights"]["median_deg"] < 0.5 and res["calibration"]["median_deg"] < 4.0
    assert res["estimated"]["median_deg"] < 2.0                 # the lamps' intensities measured from the images
    rec = res["lights"]["recorded"]
    assert rec == {"camera": "Blackmagic Pocket Cinema Camera 4K", "black_level": [512.0] * 4, "white_level": 65535.0,
                   "saturation_level": 65472.0}
    assert res["lights"]["saturation_counts"] == 65472.0 - 512.0
    assert res["lights"]["additive_source"] == "raw metadata"
    log = json.loads((tmp_path / "made" / "lights" / "run.json").read_text())
    assert log["params"]["bit_depth"] == "raw"
