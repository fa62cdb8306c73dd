#!/usr/bin/env python3
"""Real cameras' raw files through uvps: what LibRaw reads of each, and a capture built on each real DNG through
``uvps calibrate`` and ``uvps run``.

    OMP_NUM_THREADS=1 .venv/bin/python scripts/benchmark_raw.py [--folder FOLDER] [--doc]

FOLDER (default: ``$UVPS_REAL_RAW``, else ``../shared/data/raw_cameras``) holds the real files, under the names of
:data:`SOURCES`, which says where each came from and under which licence; none ships with the project. A file of
another name is measured too, with no source given.

Per file: the camera it names, its format, the image size, the black level per CFA channel, the white level and the
saturation level (the white level or the top of the file's linearization curve, the lower), whether it holds a
colour matrix, and whether ``uvps.files.raw.read_raw`` reads it or refuses it (the refusal's words). For a file read:
its counts against LibRaw's own mosaic at each pixel's own colour (``raw_image_visible`` less the black level): the
largest difference in counts (no gamma, no scaling, the black level subtracted, the linearization applied).

A real multi-light raw capture is not to be had, so for each real DNG one is made (:func:`render_capture`), keeping
what is real and saying what is rendered:

- real: the file's tags (camera, CFA pattern, black and white levels, linearization table, colour matrices,
  calibration illuminants, white balance; not its DefaultCrop, the window lying inside it), and the sensor's
  counts of a ``--crop``-sized window of its frame (its scene as the albedo, its noise, its mosaic, its clipping);
- rendered: each lamp image is those counts (above the black level) times the shading of a known relief
  (``uvps.testing.synthetic.make_capture``'s surface and near lamps) under lamp k, scaled so that the brightest is
  the file's brightest, then put back through the file's own linearization table; the frame's own noise, scaled
  by the shading, is topped up with each lamp's own shot noise at the level the frame shows
  (:func:`shot_noise_factor`). The sphere capture (two glossy spheres, :func:`make_sphere_capture`) is rendered
  whole, then mosaicked in the file's CFA pattern, put at its black level and saturation and written with its tags.

Written uncompressed (16-bit codes of the table; the original is lossless-JPEG tiles). The capture then goes through
``uvps calibrate --spheres`` and ``uvps run --calibration`` (also with ``--estimate-intensities``, and ``uvps run
--lights`` with the true lamps): the
lamps' directions against the true ones (deg) and the normals' angular error against the relief (median, 90th percentile) over the
pixels whose real counts are above :data:`MIN_COUNTS` (the frame's darkest parts hold noise only), and
``run.json``'s record of the raw levels.

``--doc`` writes docs/benchmarks.md's "Camera raw" table (section ``raw``, :func:`render_doc`) and
docs/benchmarks/raw.json (scripts/benchdoc.py).
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import tifffile

DOC_SECTION = "raw"

DATA = next((p / "shared" / "data" for p in Path(__file__).resolve().parents if (p / "shared" / "data").is_dir()),
            Path("/work/shared/data"))

#: Where each real file came from (a public repository's test data) and its licence as the source states it.
SOURCES = {
    "Blackmagic_PocketCinema4K.dng": ("imageio/test_images `Blackmagic.dng`", "none stated"),
    "Canon_EOS_6D_linear.dng": ("photoprism/photoprism `assets/examples/canon_eos_6d.dng`", "repository AGPL-3.0"),
    "Nikon_COOLSCAN_IV_ED.nef": ("imageio/test_images `Nikon_uncompressed.nef`", "none stated"),
    "RAW_KODAK_DC50.KDC": ("letmaik/rawpy `test/RAW_KODAK_DC50_é.KDC` (rawsamples.ch)", "CC BY-NC-SA 4.0"),
    "Leica_M10_truncated.dng": ("sindresorhus/file-type `fixture/fixture-Leica-M10.dng`", "MIT"),
    "Sony_ZV-E10_truncated.arw": ("sindresorhus/file-type `fixture/fixture-sony-zv-e10.arw`", "MIT"),
    "Nikon_truncated_issue247-1.nef": ("drewnoakes/metadata-extractor-images `nef/Issue 247-1.nef`",
                                       "free to use (README)"),
}

#: Pixels whose real counts above black (green channel) are below this are left out of the normals' error.
MIN_COUNTS = 2000.0
#: Lamps of the rendered capture, its relief's seed, its pixel size (um).
N_LIGHTS, SEED, PIXEL_UM = 8, 7, 15.0

# storage tags the rendered files set themselves (size, samples, compression, strips or tiles)
_STORAGE = {254, 256, 257, 258, 259, 262, 273, 277, 278, 279, 284, 305, 322, 323, 324, 325, 50719, 50720}


def default_folder() -> Path:
    return Path(os.environ.get("UVPS_REAL_RAW") or DATA / "raw_cameras")


def _fmt_error(e) -> str:
    return str(e).split(": ", 1)[-1] if ": " in str(e) else str(e)


def describe(path) -> dict:
    """What uvps reads of one raw file (or its refusal), and its counts against LibRaw's mosaic."""
    import rawpy

    from uvps.errors import UVPSInputError
    from uvps.files.io import IMAGE_EXTS, RAW_EXTS
    from uvps.files.raw import raw_reading, read_raw

    from uvps.files.raw import _camera

    path = Path(path)
    row = {"name": path.name, "camera": _camera(path), "format": path.suffix.lower().lstrip("."), "bytes": path.stat().st_size,
           "source": SOURCES.get(path.name, ("", ""))[0], "licence": SOURCES.get(path.name, ("", ""))[1]}
    try:
        with rawpy.imread(str(path)) as raw:
            row["libraw"] = {"raw_type": raw.raw_type.name, "colours": int(raw.num_colors),
                             "size_px": [int(raw.sizes.width), int(raw.sizes.height)]}
    except Exception as e:  # noqa: BLE001 - recorded
        row["libraw"] = {"error": str(e.args[0] if e.args else e)[:120]}
    if path.suffix.lower() not in RAW_EXTS:
        from uvps.files.io import _kind
        try:
            _kind(path)
            row["refused"] = None
        except UVPSInputError as e:
            row["refused"] = _fmt_error(e).replace(", ".join(IMAGE_EXTS), "the image extensions")
        row["read"] = False
        return row
    try:
        lv = raw_reading([path])["levels"][0]
        t0 = time.perf_counter()
        img = read_raw(path)
        row["read_s"] = time.perf_counter() - t0
    except UVPSInputError as e:
        row.update(read=False, refused=_fmt_error(e))
        return row
    cm = np.asarray(lv["colour_matrix"], float)[:, :3]
    row.update(read=True, refused=None, camera=lv["camera"], size_px=lv["image_px"], black=lv["black_level"],
               white=lv["white_level"], saturation=lv["saturation_level"], cfa=lv["cfa"],
               default_crop_px=lv["default_crop_px"], margins_px=lv["margins_px"],
               colour_matrix=bool(np.any(cm != 0) and not np.allclose(cm, np.eye(3))))
    with rawpy.imread(str(path)) as raw:
        mos = raw.raw_image_visible.astype(np.float64)
        cols = raw.raw_colors_visible.copy()
        black = np.asarray(raw.black_level_per_channel, float)
        desc = raw.color_desc.decode("ascii")
    if lv["default_crop_px"]:
        x, y, w, h = lv["default_crop_px"]
        mos, cols = mos[y:y + h, x:x + w], cols[y:y + h, x:x + w]
    chan = np.array(["RGB".index(c) for c in desc])[cols]      # each site's own channel in the RGB output
    own = np.take_along_axis(img, chan[..., None], axis=2)[..., 0].astype(np.float64)
    above = np.clip(mos - black[cols], 0, None)
    inner = (slice(2, -2), slice(2, -2))
    d = own[inner] - above[inner]
    row["vs_mosaic_max_counts"] = float(np.abs(d).max())
    row["vs_mosaic_mean_counts"] = float(d.mean())
    return row


def _dng_tags(path) -> list:
    """The real DNG's tags but its storage ones, as tifffile extratags (value and type as in the file)."""
    out = []
    with tifffile.TiffFile(path) as tif:
        for tag in tif.pages[0].tags.values():
            if tag.code in _STORAGE:
                continue
            v, dt = tag.value, int(tag.dtype)
            if dt == 2:
                out.append((tag.code, 2, 0, str(v), True))
                continue
            if isinstance(v, (bytes, bytearray)):
                v = tuple(v)
            elif isinstance(v, np.ndarray):
                v = tuple(int(x) for x in v.ravel())
            elif not isinstance(v, tuple):
                v = (int(v),)
            count = len(v) // 2 if dt in (5, 10) else len(v)
            out.append((tag.code, dt, count, v, True))
    return out


def shot_noise_factor(mos, green, black) -> float:
    """The frame's own shot noise, ``variance = a * counts``, from differences of neighbouring sites of one green
    plane (2 px apart), binned by level: the 25th percentile of ``variance / level`` over the bins above 2000 counts
    (the smoothest parts of the scene; texture only adds to a bin's spread)."""
    i, j = next((i, j) for i in range(2) for j in range(2) if green[i, j])      # a green site of the 2 x 2 tile
    plane = mos[i::2, j::2].astype(np.float64)
    d = plane[:, 1:] - plane[:, :-1]
    m = (plane[:, 1:] + plane[:, :-1]) / 2 - float(np.max(black))
    edges = np.quantile(m, np.linspace(0.02, 0.98, 25))
    ratios = []
    for lo, hi in zip(edges[:-1], edges[1:]):
        sel = (m >= lo) & (m < hi)
        if sel.sum() > 100 and m[sel].mean() > 2000:
            mad = np.median(np.abs(d[sel] - np.median(d[sel])))
            ratios.append((1.4826 * mad) ** 2 / 2 / m[sel].mean())
    return float(np.percentile(ratios, 25)) if ratios else 0.0


def render_capture(path, folder, *, crop=(600, 800), origin=None, n_lights=N_LIGHTS, seed=SEED) -> dict:
    """A multi-light capture and a sphere capture built on a real DNG (module docstring: what is real and what is
    rendered): ``folder/capture/uv_NN.dng``, ``folder/spheres/sph_NN.dng``, ``folder/lights.csv`` (the true lamps,
    mm) and ``folder/truth.npz`` (normals, the real counts of the window, the lamps). Returns what was made."""
    import rawpy

    from uvps.testing.synthetic import make_capture, render_images
    from uvps.testing.synthetic_spheres import SphereSpec, make_sphere_capture

    path, folder = Path(path), Path(folder)
    with rawpy.imread(str(path)) as raw:
        mos = raw.raw_image_visible.astype(np.float64)
        cols = raw.raw_colors_visible.copy()
        black = np.asarray(raw.black_level_per_channel, float)
        curve = np.asarray(raw.tone_curve, np.float64)
        desc = raw.color_desc.decode("ascii")
        sat = min(float(raw.white_level), float(curve.max()))
        from uvps.files.raw import default_crop
        dcrop = default_crop(raw)
    M, N = crop
    H, W = mos.shape
    if origin is None:
        # among 5 x 5 windows (even offsets), one with no clipped count, 90 % of it above
        # MIN_COUNTS, and the most texture (spread of log counts): a scene like a painting's, not a plain sky
        def key(rc):
            w = mos[rc[0]:rc[0] + M, rc[1]:rc[1] + N] - black.max()
            return (int((w + black.max() >= sat).sum()), not np.mean(w >= MIN_COUNTS) >= 0.9,
                    -float(np.std(np.log(np.clip(w, 1, None)))))
        x, y, w, h = dcrop or [0, 0, W, H]       # inside the file's DefaultCrop (outside it is not image)
        even = lambda v: int(-(-v // 2) * 2)     # noqa: E731 - rounded up to even: the CFA phase kept
        origin = min(((even(r), even(c)) for r in y + np.linspace(0, h - M - 1, 5).astype(int)
                      for c in x + np.linspace(0, w - N - 1, 5).astype(int)), key=key)
    r0, c0 = (int(v) for v in origin)
    win = mos[r0:r0 + M, c0:c0 + N]
    wcols = cols[r0:r0 + M, c0:c0 + N]
    real = np.clip(win - black[wcols], 0, None)                  # the real counts above black
    cap = make_capture(shape=(M, N), n_lights=n_lights, seed=seed, rgb=False, pixel_size_um=PIXEL_UM)
    shading = render_images(cap.height_um, np.ones((M, N)), pixel_size_um=PIXEL_UM,
                            light_positions_mm=cap.light_positions_mm, intensities=cap.intensities,
                            noise=False, dtype=None, exposure=1.0)
    shading = shading / shading.max()
    # the table's inverse: the code whose linear value is nearest (codes past the table's top repeat it)
    top = int(np.argmax(curve >= curve.max()))
    table = curve[:top + 1]

    def encode(linear):
        idx = np.clip(np.searchsorted(table, linear), 1, top)
        lo = table[idx - 1]
        return np.where(np.abs(linear - lo) <= np.abs(table[idx] - linear), idx - 1, idx).astype(np.uint16)

    tags = _dng_tags(path)
    note = (f"rendered by uvps scripts/benchmark_raw.py from {path.name} ({M}x{N} window at row {r0}, col {c0}): "
            "{what}; every other tag is the original's")
    (folder / "capture").mkdir(parents=True)
    (folder / "spheres").mkdir()
    # each lamp image its own shot noise: what the frame's noise (a * counts, scaled by the shading) lacks
    x0, y0, w0, h0 = dcrop or [0, 0, W, H]
    green = np.array([c == "G" for c in desc])[cols[y0:y0 + 2, x0:x0 + 2]]
    a = shot_noise_factor(mos[y0:y0 + h0, x0:x0 + w0], green, black)
    rng = np.random.default_rng(seed)
    for k in range(n_lights):
        lin = black[wcols] + real * shading[k]
        lin += rng.standard_normal(lin.shape) * np.sqrt(a * real * shading[k] * (1.0 - shading[k]))
        desc_k = note.format(what=f"the sensor's counts above black times the shading of a known relief, lamp {k}")
        tifffile.imwrite(folder / "capture" / f"uv_{k:02d}.dng", encode(lin), photometric=32803, subfiletype=0,
                         metadata=None, software="uvps scripts/benchmark_raw.py",
                         extratags=tags + [(270, 2, 0, desc_k, True)])
    # two glossy spheres in opposite corners, a tenth of the field's height in radius (as uvps demo makes them)
    r_mm = 0.1 * M * PIXEL_UM / 1000.0
    sc = make_sphere_capture(cap, (SphereSpec("glossy", (0.15, 0.2), r_mm), SphereSpec("glossy", (0.85, 0.8), r_mm)),
                             seed=seed)
    rgb_of_site = np.array(["RGB".index(c) for c in desc])[wcols]
    for k in range(n_lights):
        img = np.asarray(sc.images[k], np.float64)
        site = img if img.ndim == 2 else np.take_along_axis(img, rgb_of_site[..., None], axis=2)[..., 0]
        lin = black[wcols] + site * (sat - black.max()) / 65535.0
        desc_k = note.format(what=f"two glossy spheres rendered whole under lamp {k}, mosaicked")
        tifffile.imwrite(folder / "spheres" / f"sph_{k:02d}.dng", encode(lin), photometric=32803, subfiletype=0,
                         metadata=None, software="uvps scripts/benchmark_raw.py",
                         extratags=tags + [(270, 2, 0, desc_k, True)])
    lines = ["file,x_mm,y_mm,z_mm"] + [f"uv_{k:02d}.dng," + ",".join(f"{v:.6f}" for v in p)
                                       for k, p in enumerate(cap.light_positions_mm)]
    (folder / "lights.csv").write_text("\n".join(lines) + "\n")
    np.savez(folder / "truth.npz", normals=cap.normals, real=real, sites=rgb_of_site, lamps_mm=cap.light_positions_mm)
    return {"window": [r0, c0, M, N], "lamps": n_lights, "shot_noise_variance_per_count": a,
            "clipped_real_px": int((win >= sat).sum()), "saturation": sat}


def _angle_deg(a, b):
    c = np.einsum("...i,...i->...", a, b) / (np.linalg.norm(a, axis=-1) * np.linalg.norm(b, axis=-1))
    return np.degrees(np.arccos(np.clip(c, -1.0, 1.0)))


def _bright(real, sites) -> np.ndarray:
    """Pixels whose green counts (mean of the 3 x 3 neighbourhood's green sites) reach :data:`MIN_COUNTS`."""
    from scipy.ndimage import uniform_filter
    g = np.where(sites == 1, real, 0.0)
    n = uniform_filter((sites == 1).astype(float), 3)
    return uniform_filter(g, 3) / np.maximum(n, 1e-9) >= MIN_COUNTS


def run_capture(folder) -> dict:
    """``uvps calibrate`` on the rendered spheres, ``uvps run`` with that calibration and with the true lamps:
    the lamps' and normals' errors, and run.json's record of the raw levels."""
    import tifffile as tf

    from uvps.commands import COMMANDS

    folder = Path(folder)
    truth = np.load(folder / "truth.npz")
    bright = _bright(truth["real"], truth["sites"])
    out = {"bright_fraction": float(bright.mean())}
    t0 = time.perf_counter()
    COMMANDS["calibrate"]({"spheres": [str(folder / "spheres")]}, {"pixel_size_um": PIXEL_UM}, folder / "CAL")
    out["calibrate_s"] = time.perf_counter() - t0
    cal = json.loads((folder / "CAL" / "calibration.json").read_text())
    # directions (the spheres, a field's width apart, do not triangulate lamps hundreds of mm away), against the
    # true lamps' directions from the field's centre
    d = _angle_deg(np.array([lamp["direction"] for lamp in cal["lamps"]], float), truth["lamps_mm"])
    out["spheres"] = [s["kind"] for s in cal["spheres"]]
    out["lamp_direction_deg_median"], out["lamp_direction_deg_max"] = float(np.median(d)), float(d.max())
    for name, params in (("calibration", {"calibration": str(folder / "CAL")}),
                         ("estimated", {"calibration": str(folder / "CAL"), "estimate_intensities": True}),
                         ("lights", {"lights": str(folder / "lights.csv")})):
        t0 = time.perf_counter()
        COMMANDS["run"]({"images": [str(folder / "capture")]}, dict(params, pixel_size_um=PIXEL_UM), folder / name)
        dt = time.perf_counter() - t0
        nrm = np.moveaxis(tf.imread(folder / name / "normals.tif"), 0, -1).astype(np.float64)
        ang = _angle_deg(nrm, truth["normals"])
        ok = np.isfinite(ang) & bright
        log = json.loads((folder / name / "run.json").read_text())
        lv = log["diagnostics"]["raw"]["levels"][0]
        out[name] = {"s": dt, "median_deg": float(np.median(ang[ok])), "p90_deg": float(np.percentile(ang[ok], 90)),
                     "recorded": {k: lv[k] for k in ("camera", "black_level", "white_level", "saturation_level")},
                     "saturation_counts": log["diagnostics"]["raw"]["saturation_counts"],
                     "additive_source": log["diagnostics"]["additive"].get("source")}
    return out


def measure(folder, *, crop=(600, 800)) -> list:
    rows = []
    for path in sorted(p for p in Path(folder).iterdir()
                       if p.is_file() and not p.name.startswith(".") and p.suffix.lower() not in (".txt", ".md")):
        row = describe(path)
        print(json.dumps({k: v for k, v in row.items() if k not in ("source", "licence")}), flush=True)
        if row.get("read") and row["format"] == "dng":
            with tempfile.TemporaryDirectory() as tmp:
                row["rendered"] = render_capture(path, Path(tmp) / "made", crop=crop)
                try:
                    row["run"] = run_capture(Path(tmp) / "made")
                except Exception as e:  # noqa: BLE001 - a refusal is a result
                    row["run"] = {"refused": str(e)}
            print(json.dumps(row["run"]), flush=True)
        rows.append(row)
    return rows


def _levels(v) -> str:
    return "/".join(f"{x:g}" for x in v) if len(set(v)) > 1 else f"{v[0]:g}"


def render_doc(results: dict) -> str:
    """docs/benchmarks.md's camera raw table: one row per real file, then one per rendered capture.

    Parameters
    ----------
    results : dict
        ``{"rows": [describe()'s dicts, with "rendered" and "run" for the DNGs run], "argv"}`` as
        docs/benchmarks/raw.json keeps them.
    """
    lines = ["| file | source (licence) | camera | format | size (px) | black per channel | white / saturation | "
             "colour matrix | uvps reads it | a capture built on it: calibrate (lamps) / run (normals, median / p90) |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    for r in results["rows"]:
        src = f"{r['source']} ({r['licence']})" if r.get("source") else ""
        head = f"| {r['name']} | {src} | {r.get('camera') or ''} | {r['format']} |"
        if not r.get("read"):
            lib = r.get("libraw", {})
            seen = (f"{lib['size_px'][0]} x {lib['size_px'][1]} ({lib['raw_type']})" if "size_px" in lib
                    else "LibRaw: no")
            lines.append(f"{head} {seen} | | | | refused: {r['refused'].split(';')[0]} | |")
            continue
        u = r.get("run") or {}
        if "refused" in u:
            run = f"refused: {u['refused']}"
        elif u:
            c, t = u["calibration"], u["lights"]
            e = u.get("estimated", c)
            run = (f"window {', '.join(str(v) for v in r['rendered']['window'])}: lamps "
                   f"{u['lamp_direction_deg_median']:.2f} / {u['lamp_direction_deg_max']:.2f} deg (median / max); "
                   f"normals {c['median_deg']:.2f} / {c['p90_deg']:.2f} deg (`--estimate-intensities` "
                   f"{e['median_deg']:.2f} / {e['p90_deg']:.2f}), with the true lamps {t['median_deg']:.2f} / "
                   f"{t['p90_deg']:.2f}; run.json: black {_levels(c['recorded']['black_level'])}, saturation "
                   f"{c['saturation_counts']:g} counts")
        else:
            run = ""
        lines.append(f"{head} {r['size_px'][0]} x {r['size_px'][1]} | {_levels(r['black'])} | "
                     f"{r['white']:g} / {r['saturation']:g} | {'yes' if r['colour_matrix'] else 'no'} | "
                     f"yes; each pixel's own colour within {r['vs_mosaic_max_counts']:.2f} count of LibRaw's mosaic | "
                     f"{run} |")
    return "\n".join(lines) + "\n"


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--folder", type=Path, default=None, help="the real raw files (default $UVPS_REAL_RAW, else "
                                                              "../shared/data/raw_cameras)")
    ap.add_argument("--crop", type=int, nargs=2, default=(600, 800), metavar=("ROWS", "COLS"),
                    help="the window of a real DNG the capture is built on")
    ap.add_argument("--doc", action="store_true",
                    help="write the table into docs/benchmarks.md (section raw) and docs/benchmarks/raw.json")
    args = ap.parse_args(argv)
    folder = args.folder or default_folder()
    if not folder.is_dir():
        print(f"{folder}: no such folder (give --folder or set UVPS_REAL_RAW)", file=sys.stderr)
        return 1
    rows = measure(folder, crop=tuple(args.crop))
    doc = {"rows": rows, "argv": ["--crop", *map(str, args.crop)]}
    print(render_doc(doc))
    if args.doc:
        sys.path.insert(0, str(Path(__file__).resolve().parent))
        import benchdoc
        print("wrote", benchdoc.write_doc(DOC_SECTION, doc, render_doc(doc), source="scripts/benchmark_raw.py"))
    return 0


if __name__ == "__main__":
    sys.exit(main())
