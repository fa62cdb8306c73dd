"""The painting report's zoomable view: Deep Zoom (DZI) tile pyramids of the painting-wide maps,
shown with OpenSeadragon (vendored in ``report/vendor/openseadragon``, its licence and version beside it).

Three layers, in ``OUT/painting/view/``: ``albedo`` (RGB, JPEG), ``height`` (the levelled height,
coloured with viridis over its 1st-99th percentile, JPEG) and ``outlines`` (the protrusions'
outlines, transparent PNG over either). The full-resolution level is cut from the OME-Zarr stores
one stored chunk at a time (a chunk is a whole number of DZI tiles), every lower level from the
four tiles of the level above: neither the painting nor a whole level is ever in memory. The DZI
layout (``NAME_files/LEVEL/COL_ROW.ext``, level ``ceil(log2(max side))`` full resolution, each
lower level halved, rounding up) is Microsoft's Deep Zoom format, as OpenSeadragon and vips write
and read it; it is written here rather than with pyvips (a C library the project does not ship)
because the tiles come from the OME-Zarr chunks the stitching already wrote.

The descriptors are given to OpenSeadragon inline in the page, not fetched: a report opened from a
disk (``file://``, a museum offline) cannot fetch files, but its images load.
"""
from __future__ import annotations

import json
import math
import shutil
from pathlib import Path

import numpy as np

#: Side of a DZI tile (no overlap between tiles); a divisor of the maps' chunk side.
TILE_PX = 256
VENDOR = Path(__file__).with_name("vendor") / "openseadragon"
LAYERS = ("albedo", "height", "outlines")


def _levels(rows: int, cols: int) -> list:
    """(rows, cols) of DZI levels 0..max: level max is the full image, each lower one halved up."""
    top = int(math.ceil(math.log2(max(rows, cols, 1))))
    return [(int(math.ceil(rows / 2 ** (top - k))), int(math.ceil(cols / 2 ** (top - k)))) for k in range(top + 1)]


def _save(img: np.ndarray, path: Path, fmt: str) -> None:
    from PIL import Image

    path.parent.mkdir(parents=True, exist_ok=True)
    if fmt == "jpg":
        Image.fromarray(img[..., :3]).save(path, quality=88)
    else:
        Image.fromarray(img).save(path, optimize=False)


def _load(path: Path) -> np.ndarray:
    from PIL import Image

    with Image.open(path) as im:
        return np.asarray(im)


def _halve(img: np.ndarray, alpha_max: bool) -> np.ndarray:
    """A (M, N, C) uint8 tile halved (2 x 2 means, an odd edge kept); outlines keep their lines (max)."""
    m, n = img.shape[:2]
    if m % 2 or n % 2:
        img = np.pad(img, ((0, m % 2), (0, n % 2), (0, 0)), mode="edge")
    b = img.reshape(img.shape[0] // 2, 2, img.shape[1] // 2, 2, img.shape[2]).astype(np.float32)
    out = b.max(axis=(1, 3)) if alpha_max else b.mean(axis=(1, 3))
    return np.round(out).astype(np.uint8)


def _colour(kind: str, block: np.ndarray, scale) -> np.ndarray:
    """A chunk of a map as (M, N, 3 or 4) uint8 for its layer."""
    if kind == "albedo":
        a = block if block.ndim == 2 else np.moveaxis(block, 0, -1)
        if a.ndim == 2:
            a = np.repeat(a[..., None], 3, axis=2)
        return (np.clip(np.nan_to_num(a[..., :3] / scale), 0, 1) * 255 + 0.5).astype(np.uint8)
    if kind == "height":
        import matplotlib

        lo, hi = scale
        t = np.clip((block - lo) / ((hi - lo) or 1.0), 0, 1)
        rgb = (matplotlib.colormaps["viridis"](np.nan_to_num(t))[..., :3] * 255 + 0.5).astype(np.uint8)
        rgb[~np.isfinite(block)] = 0
        return rgb
    from .page import inner_boundaries

    edge = inner_boundaries(block)
    out = np.zeros(block.shape + (4,), np.uint8)
    out[edge] = (0, 255, 255, 255)                         # cyan, as the overview's circles
    return out


def _write_layer(zarr_array, kind: str, folder: Path, scale, *, fmt: str) -> dict:
    """Write ``folder/KIND_files/`` from a zarr array (level 0 of an OME-Zarr image) chunk by chunk."""
    rows, cols = zarr_array.shape[-2:]
    levels = _levels(rows, cols)
    top = len(levels) - 1
    files = folder / f"{kind}_files"
    chunk = max(TILE_PX, (int(zarr_array.chunks[-1]) // TILE_PX) * TILE_PX)
    for r0 in range(0, rows, chunk):
        for c0 in range(0, cols, chunk):
            # one margin pixel around the chunk so an outline on its border is drawn as in the whole map
            mr0, mc0 = max(0, r0 - 1), max(0, c0 - 1)
            block = np.asarray(zarr_array[..., mr0:min(rows, r0 + chunk + 1), mc0:min(cols, c0 + chunk + 1)])
            img = _colour(kind, block, scale)[r0 - mr0:r0 - mr0 + chunk, c0 - mc0:c0 - mc0 + chunk]
            for tr in range(0, img.shape[0], TILE_PX):
                for tc in range(0, img.shape[1], TILE_PX):
                    _save(img[tr:tr + TILE_PX, tc:tc + TILE_PX], files / str(top) /
                          f"{(c0 + tc) // TILE_PX}_{(r0 + tr) // TILE_PX}.{fmt}", fmt)
    for k in range(top - 1, -1, -1):
        m, n = levels[k]
        for i in range(-(-m // TILE_PX)):
            for j in range(-(-n // TILE_PX)):
                parts = [[files / str(k + 1) / f"{2 * j + dj}_{2 * i + di}.{fmt}" for dj in (0, 1)] for di in (0, 1)]
                row_imgs = []
                for di in (0, 1):
                    got = [_load(p) for p in parts[di] if p.is_file()]
                    if got:
                        row_imgs.append(np.concatenate(got, axis=1))
                _save(_halve(np.concatenate(row_imgs, axis=0), kind == "outlines"),
                      files / str(k) / f"{j}_{i}.{fmt}", fmt)
    return {"Image": {"xmlns": "http://schemas.microsoft.com/deepzoom/2008", "Url": f"view/{kind}_files/",
                      "Format": fmt, "Overlap": "0", "TileSize": str(TILE_PX),
                      "Size": {"Width": str(cols), "Height": str(rows)}}}


def _dzi_xml(desc: dict) -> str:
    im = desc["Image"]
    return (f'<?xml version="1.0" encoding="UTF-8"?>\n<Image xmlns="{im["xmlns"]}" Format="{im["Format"]}" '
            f'Overlap="0" TileSize="{im["TileSize"]}">\n  <Size Width="{im["Size"]["Width"]}" '
            f'Height="{im["Size"]["Height"]}"/>\n</Image>\n')


def write_view(painting_dir, *, albedo_scale: float | None = None) -> dict:
    """Write ``painting_dir/view/``: the DZI pyramids of the albedo, height and outlines and the
    viewer's script and licence; return the three descriptors (for the page, inline).

    ``painting_dir`` holds ``albedo.ome.zarr`` (with ``labels/protrusions``) and ``height.ome.zarr``.
    The albedo's display scale (white) is ``albedo_scale`` (default: the 99.5th percentile of the
    store's coarsest level); the height's colours span its 1st-99th percentile there.
    """
    import zarr

    painting_dir = Path(painting_dir)
    view = painting_dir / "view"
    view.mkdir(exist_ok=True)
    alb = zarr.open_group(str(painting_dir / "albedo.ome.zarr"), mode="r")
    hgt = zarr.open_group(str(painting_dir / "height.ome.zarr"), mode="r")

    def coarsest(group):
        keys = sorted((k for k in group.array_keys() if k.isdigit()), key=int)
        return np.asarray(group[keys[-1]], np.float64)

    if albedo_scale is None:
        low = coarsest(alb)
        finite = low[np.isfinite(low) & (low > 0)]
        albedo_scale = float(np.percentile(finite, 99.5)) if finite.size else 1.0
    low_h = coarsest(hgt)
    finite = low_h[np.isfinite(low_h)]
    h_range = tuple(float(v) for v in np.percentile(finite, [1, 99])) if finite.size else (0.0, 1.0)
    descs = {"albedo": _write_layer(alb["0"], "albedo", view, albedo_scale or 1.0, fmt="jpg"),
             "height": _write_layer(hgt["0"], "height", view, h_range, fmt="jpg"),
             "outlines": _write_layer(alb["labels/protrusions/0"], "outlines", view, None, fmt="png")}
    for k, d in descs.items():
        (view / f"{k}.dzi").write_text(_dzi_xml(d))          # for other DZI viewers; the page inlines them
    for name in ("openseadragon.min.js", "LICENSE.txt", "VERSION"):
        shutil.copyfile(VENDOR / name, view / ("openseadragon-" + name if name != "openseadragon.min.js" else name))
    return {"layers": descs, "height_range_um": list(h_range), "albedo_white": albedo_scale}


def viewer_html(view: dict) -> str:
    """The report's section holding the zoomable view (OpenSeadragon over the inline descriptors)."""
    lo, hi = view["height_range_um"]
    return f"""<h2>Zoomable view (full resolution)</h2>
<p>Drag to pan, scroll to zoom (to single pixels); layer:
<label><input type="radio" name="uvps-layer" value="albedo" checked> albedo</label>
<label><input type="radio" name="uvps-layer" value="height"> height ({lo:.1f} to {hi:.1f} um, viridis)</label>
<label><input type="checkbox" id="uvps-outlines" checked> protrusion outlines</label>
<button type="button" id="uvps-home">whole painting</button>
<small>OpenSeadragon (BSD-3-Clause, view/openseadragon-LICENSE.txt); tiles in view/ (Deep Zoom).
<span id="uvps-status" data-loaded="0" data-failed="0">tiles: loading</span></small></p>
<div id="uvps-view" style="width:100%;height:640px;background:#111"></div>
<script src="view/openseadragon.min.js"></script>
<script>
(function() {{
  var layers = {json.dumps(view["layers"])};
  var viewer = OpenSeadragon({{id: "uvps-view", showNavigationControl: false, showNavigator: true,
    drawer: "canvas", maxZoomPixelRatio: 8, imageSmoothingEnabled: false,
    tileSources: [{{tileSource: layers.albedo}}, {{tileSource: layers.height, opacity: 0}},
                  {{tileSource: layers.outlines}}]}});
  window.uvpsViewer = viewer;
  var status = document.getElementById("uvps-status");
  function count(key, text) {{
    status.dataset[key] = String(Number(status.dataset[key]) + 1);
    status.textContent = "tiles: " + status.dataset.loaded + " loaded" +
      (Number(status.dataset.failed) ? ", " + status.dataset.failed + " missing (" + text + ")" : "");
  }}
  viewer.addHandler("tile-loaded", function() {{ count("loaded", ""); }});
  viewer.addHandler("tile-load-failed", function(e) {{ count("failed", e.message || "view/ folder?"); }});
  function show() {{
    var h = document.querySelector('input[name="uvps-layer"]:checked').value === "height";
    viewer.world.getItemAt(0).setOpacity(h ? 0 : 1);
    viewer.world.getItemAt(1).setOpacity(h ? 1 : 0);
    viewer.world.getItemAt(2).setOpacity(document.getElementById("uvps-outlines").checked ? 1 : 0);
  }}
  document.querySelectorAll('input[name="uvps-layer"]').forEach(function(e) {{ e.addEventListener("change", show); }});
  document.getElementById("uvps-outlines").addEventListener("change", show);
  document.getElementById("uvps-home").addEventListener("click", function() {{ viewer.viewport.goHome(); }});
}})();
</script>
"""
