"""OME-Zarr output: `uvps run --ome-zarr` and `uvps ome-zarr RUN` write OME-NGFF 0.4
pyramids that an independent validator accepts, whose level 0 equals the TIFFs and whose levels
overlay it in micrometres; a store is replaced whole, never merged, and a failed write leaves the old
one."""
import json
import subprocess
import sys

import numpy as np
import pytest
import tifffile
import zarr
from ome_zarr_models import open_ome_zarr
from ome_zarr_models.v04.image import Image
from ome_zarr_models.v04.image_label import ImageLabel

from uvps.files import omezarr
from uvps.files.io import write_imagej_tiff
from uvps.testing.synthetic import make_capture, write_capture

PX = 15.0


@pytest.fixture(scope="module")
def run_dir(tmp_path_factory):
    """A real run with detection and colour areas, through the CLI with --ome-zarr."""
    cap = make_capture(shape=(320, 560), n_lights=8, seed=4)
    d = tmp_path_factory.mktemp("omezarr")
    write_capture(cap, d / "cap")
    r = subprocess.run([sys.executable, "-m", "uvps", "run", str(d / "cap"), "-o", str(d / "run"), "--lights",
                        str(d / "cap" / "lights_positions_mm.csv"), "--regions", "auto", "--ome-zarr"],
                       capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr
    return d / "run"


def _level(store, k, sub=""):
    return np.asarray(zarr.open_group(str(store / sub) if sub else str(store), mode="r")[str(k)])


def test_run_writes_valid_ome_ngff_whose_level_0_is_the_tiffs(run_dir):
    for name, tiff in (("depth", "depth.tif"), ("normals", "normals.tif"), ("albedo", "albedo.tif")):
        store = run_dir / f"{name}.ome.zarr"
        model = open_ome_zarr(zarr.open_group(str(store), mode="r"))
        assert isinstance(model, Image), name
        np.testing.assert_array_equal(_level(store, 0), tifffile.imread(run_dir / tiff))
    for name in ("protrusions", "regions"):
        sub = f"labels/{name}"
        assert isinstance(open_ome_zarr(zarr.open_group(str(run_dir / "albedo.ome.zarr" / sub), mode="r")),
                          ImageLabel)
        labels = _level(run_dir / "albedo.ome.zarr", 0, sub)
        np.testing.assert_array_equal(labels, tifffile.imread(run_dir / f"{name}_labels.tif"))
        assert np.issubdtype(labels.dtype, np.integer) and labels.max() > 0
    spec = json.loads((run_dir / "run.json").read_text())
    assert spec["params"]["ome_zarr"] is True


def test_levels_are_2x2_means_that_overlay_level_0_in_micrometres(run_dir):
    store = run_dir / "depth.ome.zarr"
    attrs = json.loads((store / ".zattrs").read_text())["multiscales"][0]
    assert attrs["version"] == "0.4" and [a["unit"] for a in attrs["axes"]] == ["micrometer", "micrometer"]
    d0, d1 = _level(store, 0), _level(store, 1)
    assert d1.shape == (160, 280) and len(attrs["datasets"]) == 2   # 560 px: one more level, under 512
    expect = d0.reshape(160, 2, 280, 2).astype(np.float64).mean(axis=(1, 3))
    np.testing.assert_allclose(d1, expect, rtol=1e-5, atol=1e-4)
    # level 1's pixel (0, 0) averages level 0's (0..1, 0..1): its centre is half a level-0 pixel in
    scale, shift = attrs["datasets"][1]["coordinateTransformations"]
    assert scale["scale"] == [2 * PX, 2 * PX] and shift["translation"] == [PX / 2, PX / 2]
    n1 = _level(run_dir / "normals.ome.zarr", 1)
    np.testing.assert_allclose(np.linalg.norm(n1, axis=0), 1.0, atol=1e-5)
    # labels are never averaged: every label of level 1 is one of level 0's
    p0, p1 = (_level(run_dir / "albedo.ome.zarr", k, "labels/protrusions") for k in (0, 1))
    np.testing.assert_array_equal(p1, p0[::2, ::2])


def test_band_by_band_equals_one_band(tmp_path, monkeypatch):
    """A large image is written in bands of rows; the result does not depend on the band size."""
    rng = np.random.default_rng(1)
    depth = rng.normal(size=(1100, 700)).astype(np.float32)
    write_imagej_tiff(tmp_path / "depth.tif", depth, axes="YX", pixel_size_um=PX)
    one = omezarr.write_ome_zarr(tmp_path, out_dir=tmp_path)[0]
    levels_one = [_level(one, k) for k in range(3)]
    monkeypatch.setattr(omezarr, "CHUNK_PX", 64)
    monkeypatch.setattr(omezarr, "BAND_BYTES", 64 * 700 * 4)
    (tmp_path / "bands").mkdir()
    banded = omezarr.write_ome_zarr(tmp_path, out_dir=tmp_path / "bands")[0]
    assert zarr.open_group(str(banded), mode="r")["0"].chunks == (64, 64)
    for k in range(3):          # 1100 x 700 -> 550 x 350 -> 275 x 175
        np.testing.assert_array_equal(_level(banded, k), levels_one[k])
    assert levels_one[2].shape == (275, 175)


def test_a_store_is_replaced_whole_and_a_failed_write_keeps_the_old_one(tmp_path, monkeypatch):
    ones = np.ones((600, 600), np.float32)
    write_imagej_tiff(tmp_path / "depth.tif", ones, axes="YX", pixel_size_um=PX)
    store = omezarr.write_ome_zarr(tmp_path)[0]
    # zeros: zarr would skip all-zero chunks, and a store merged into the old one would read ones
    write_imagej_tiff(tmp_path / "depth.tif", np.zeros((300, 200), np.float32), axes="YX", pixel_size_um=PX)
    omezarr.write_ome_zarr(tmp_path)
    assert _level(store, 0).shape == (300, 200) and not _level(store, 0).any()
    assert not (store / "1").exists()          # 300 px: no second level, and the old one is gone

    def boom(block, kind):
        raise RuntimeError("disk full")

    write_imagej_tiff(tmp_path / "depth.tif", ones, axes="YX", pixel_size_um=PX)
    monkeypatch.setattr(omezarr, "_halve", boom)
    with pytest.raises(RuntimeError):
        omezarr.write_ome_zarr(tmp_path)
    assert _level(store, 0).shape == (300, 200)        # the old store, untouched
    assert sorted(p.name for p in tmp_path.iterdir()) == ["depth.ome.zarr", "depth.tif"]


def test_ome_zarr_command_converts_an_existing_run_and_rejects_bad_folders(run_dir, tmp_path):
    (tmp_path / "run").mkdir()
    for f in ("depth.tif", "normals.tif"):
        (tmp_path / "run" / f).write_bytes((run_dir / f).read_bytes())
    r = subprocess.run([sys.executable, "-m", "uvps", "ome-zarr", str(tmp_path / "run")], capture_output=True,
                       text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    assert sorted(p.name for p in (tmp_path / "run").glob("*.zarr")) == ["depth.ome.zarr", "normals.ome.zarr"]
    np.testing.assert_array_equal(_level(tmp_path / "run" / "normals.ome.zarr", 1),
                                  _level(run_dir / "normals.ome.zarr", 1))
    empty = tmp_path / "empty"
    empty.mkdir()
    r = subprocess.run([sys.executable, "-m", "uvps", "ome-zarr", str(empty)], capture_output=True, text=True,
                       timeout=120)
    assert r.returncode == 1 and len(r.stderr.strip().splitlines()) == 1
    assert f"run folder {empty} has none of depth.tif, normals.tif, albedo.tif" in r.stderr
    assert list(empty.iterdir()) == []


def test_through_the_bridge(run_dir, tmp_path):
    req = tmp_path / "request.json"
    (tmp_path / "run").mkdir()
    (tmp_path / "run" / "depth.tif").write_bytes((run_dir / "depth.tif").read_bytes())
    req.write_text(json.dumps({"schema_version": 1, "command": "ome-zarr", "inputs": {"run": str(tmp_path / "run")},
                               "params": {}, "output_dir": str(tmp_path / "run")}))
    r = subprocess.run([sys.executable, "-m", "uvps", "bridge", str(req)], capture_output=True, text=True,
                       timeout=120)
    assert r.returncode == 0, r.stderr
    resp = json.loads((tmp_path / "response.json").read_text())
    assert resp["status"] == "ok" and resp["diagnostics"]["ngff_version"] == "0.4"
    assert [o["name"] for o in resp["outputs"]] == ["depth_zarr"]
    np.testing.assert_array_equal(_level(tmp_path / "run" / "depth.ome.zarr", 0), tifffile.imread(run_dir / "depth.tif"))


def _painting_like(folder, batch=None):
    """Labels of their own (two images), an RGB albedo with those labels attached by copy, and a height:
    the painting's stores, each written alone or all added to ``batch``."""
    import dask.array as da

    rng = np.random.default_rng(3)
    M, N = 700, 900
    alb = da.from_array(rng.uniform(0, 900, (3, M, N)).astype(np.float32), chunks=(1, 256, 256))
    height = da.from_array(rng.normal(0, 20, (M, N)).astype(np.float32), chunks=(256, 256))
    labs = [da.from_array((rng.uniform(0, 1, (M, N)) * k * 40).astype(np.uint32), chunks=(256, 256))
            for k in (1, 2)]
    kw = {} if batch is None else {"batch": batch}
    labels = omezarr.write_dask_ome_labels(folder / "labels.ome.zarr", list(zip(omezarr.LABELS, labs)), PX,
                                           image="../../albedo.ome.zarr", chunk_px=256, **kw)
    omezarr.write_dask_ome_zarr(folder / "albedo.ome.zarr", omezarr.ZarrImage("albedo", "", ("R", "G", "B")), alb,
                                PX, chunk_px=256, labels=[(lb, labels / lb.name) for lb in omezarr.LABELS], **kw)
    omezarr.write_dask_ome_zarr(folder / "height.ome.zarr", omezarr.ZarrImage("height", "", (), unit="micrometer"),
                                height, PX, chunk_px=256, **kw)
    if batch is not None:
        assert not (folder / "albedo.ome.zarr").exists()       # nothing in place before the batch runs
        batch.run()


def test_a_batch_of_stores_writes_the_same_files_as_each_store_alone(tmp_path):
    """The painting stores its maps as one Dask graph per level (StoreBatch): the same files, byte for
    byte, as one store after the other, the labels copied into the albedo once they are written."""
    (tmp_path / "alone").mkdir()
    (tmp_path / "batch").mkdir()
    _painting_like(tmp_path / "alone")
    _painting_like(tmp_path / "batch", omezarr.StoreBatch())

    def files(root):
        return {str(p.relative_to(root)): p.read_bytes() for p in sorted(root.rglob("*")) if p.is_file()}

    alone, batched = files(tmp_path / "alone"), files(tmp_path / "batch")
    assert len(alone) > 40 and any("albedo.ome.zarr/labels/protrusions/1/" in k for k in alone)
    assert sorted(alone) == sorted(batched)
    assert [k for k in alone if alone[k] != batched[k]] == []
    assert sorted(p.name for p in (tmp_path / "batch").iterdir()) == ["albedo.ome.zarr", "height.ome.zarr",
                                                                       "labels.ome.zarr"]


def test_a_failed_batch_leaves_no_store_and_no_temporary(tmp_path, monkeypatch):
    def boom(block, kind):
        raise RuntimeError("disk full")

    monkeypatch.setattr(omezarr, "_halve", boom)
    with pytest.raises(RuntimeError, match="disk full"):
        _painting_like(tmp_path, omezarr.StoreBatch())
    assert list(tmp_path.iterdir()) == []
