"""The README's example commands, as written, on a demo capture (a real subprocess each).

The files they name (`captures/region1/`, `painting/` (tiles of a painting and their layout), `spheres/` (two glossy spheres under its lamps), `raw_capture/` (DNG files), `xrf_maps/` (element maps), `areas.tif`, `lights.lp`, `clicks.csv`, ...) are made from a
synthetic capture in a fresh folder, as a user would have them; nothing else is changed in a command
but `uvps` itself, which runs as `python -m uvps`. The one line that needs a Dask scheduler at
`tcp://host:8786` is left out, and `uvps changes` runs after the two runs it compares.
"""
import csv
import glob
import re
import shlex
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import tifffile

from uvps.files.io import write_imagej_tiff
from uvps.testing.painting import make_painting, write_painting
from uvps.testing.synthetic import make_capture, render_element_maps, write_capture, write_raw_capture
from uvps.testing.synthetic_spheres import SphereSpec, make_sphere_capture, write_sphere_capture

README = Path(__file__).resolve().parents[1] / "README.md"


def readme_commands() -> list:
    """Every `uvps ...` line of the README's bash blocks after the set-up block, comments cut."""
    text = README.read_text(encoding="utf-8")
    blocks = re.findall(r"```bash\n(.*?)```", text, re.S)[1:]          # the first one is set-up and tests
    lines = []
    for block in blocks:
        for line in block.splitlines():
            line = re.split(r"\s{2,}#|\s#\s", line)[0].strip()
            if line.startswith("uvps ") and "tcp://" not in line:
                lines.append(line)
    return lines


def _sandbox(root: Path) -> None:
    cap = make_capture(shape=(200, 260), n_lights=8, seed=2)
    region = root / "captures" / "region1"
    write_capture(cap, region)
    # two glossy spheres a tenth of the field's height across, in opposite corners, as the demo's
    spheres = (SphereSpec("glossy", (0.15, 0.2), 0.3), SphereSpec("glossy", (0.85, 0.8), 0.3))
    write_sphere_capture(make_sphere_capture(cap, spheres), root / "spheres", truth=False)
    tifffile.imwrite(root / "areas.tif", cap.regions.astype(np.uint16))
    names = sorted(p.name for p in region.glob("uv_*.tif"))
    lp = (region / "lights.lp").read_text().splitlines()
    (root / "lights.lp").write_text("\n".join([lp[0]] + [line.replace("uv_", "img_", 1) for line in lp[1:]]) + "\n")
    for name in names:
        shutil.copy(region / name, root / name.replace("uv_", "img_"))
    stack = np.stack([tifffile.imread(region / n) for n in names])          # (K, M, N, 3)
    write_imagej_tiff(root / "stack.tif", np.moveaxis(stack, -1, 1), axes="ZCYX", pixel_size_um=cap.spec.pixel_size_um)
    shutil.copy(region / "lights_positions_mm.csv", root / "positions_mm.csv")
    shutil.copy(region / "lights_positions_mm.csv", root / "lights.csv")
    tifffile.imwrite(root / "dark.tif", np.full(cap.images.shape[1:], 20, np.uint16))
    big = cap.protrusions["width_um"] >= 100
    with open(root / "clicks.csv", "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["x_px", "y_px"])
        w.writerows(np.column_stack([cap.protrusions["x_px"][big], cap.protrusions["y_px"][big]]).astype(int).tolist())
    truth = render_element_maps(cap, step_um=250.0, seed=1)         # XRF maps of the same region
    (root / "xrf_maps").mkdir()
    for name, m in zip(truth.maps.names, truth.maps.data):
        tifffile.imwrite(root / "xrf_maps" / f"scan_{name}.tif", m.astype(np.float32), imagej=True,
                         resolution=(1 / 250.0, 1 / 250.0), metadata={"unit": "um"})
    write_raw_capture(make_capture(shape=(96, 128), n_lights=6, seed=3), root / "raw_capture")
    for date in ("capture_2019", "capture_2024"):
        shutil.copytree(region, root / date)
        shutil.copy(region / "lights_positions_mm.csv", root / date / "lamps_mm.csv")   # measured positions
    # a painting in 3 x 2 tiles of a rig, its stage off by up to 12 px: painting/tiles/, painting/layout.csv
    write_painting(make_painting(grid=(3, 2), tile_shape=(120, 160), stage_error_px=12.0, n_lights=6, seed=4),
                   root / "painting")


@pytest.mark.slow
def test_the_readmes_examples_run_as_written(tmp_path):
    commands = readme_commands()
    assert any(c.startswith("uvps run captures/region1/ -o runs/region1") for c in commands), commands
    assert any(c.startswith("uvps wand") for c in commands) and any(c.startswith("uvps changes") for c in commands)
    _sandbox(tmp_path)
    # the Use block's `uvps changes run_2019 run_2024` needs the monitoring block's two runs first
    later = [c for c in commands if c.startswith("uvps changes")]
    for line in [c for c in commands if c not in later] + later:
        args = []
        for word in shlex.split(line)[1:]:
            matched = sorted(glob.glob(word, root_dir=tmp_path)) if any(ch in word for ch in "*?[") else []
            args += matched or [word]
        r = subprocess.run([sys.executable, "-m", "uvps", *args], cwd=tmp_path, capture_output=True, text=True,
                           timeout=900)
        assert r.returncode == 0, (line, r.stderr[-2000:])
        assert "Traceback" not in r.stderr and "RuntimeWarning" not in r.stderr, (line, r.stderr[-2000:])
        if line.startswith("uvps compare"):      # the run with areas, the wand and compare, before batch
            assert {"report.html", "protrusions_manual.csv", "comparison.csv"} <= {
                p.name for p in (tmp_path / "runs" / "region1").iterdir()}
    # `uvps batch captures/ -o runs/` then made runs/region1 anew (a run without areas: no report)
    assert (tmp_path / "runs" / "batch_summary.csv").is_file() and (tmp_path / "runs" / "region1" / "run.json").is_file()
    assert (tmp_path / "run_2019" / "report.html").is_file()
    assert (tmp_path / "changes_2019_2024" / "changes.csv").is_file()
    assert {"layout.csv", "painting_protrusions.csv", "height.ome.zarr"} <= {
        p.name for p in (tmp_path / "painting_run" / "painting").iterdir()}
