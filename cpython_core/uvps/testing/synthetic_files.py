"""Writing a synthetic capture to files: camera TIFFs, DNGs, the dark frame and ``truth/``.

Part of :mod:`uvps.testing.synthetic`, which exposes every public name; import from there.
"""
from __future__ import annotations

import csv
import dataclasses
from pathlib import Path
from typing import Optional

import numpy as np
import tifffile

from ..files.io import write_imagej_tiff
from ..files.outputs import atomic_output_dir, write_json_atomic
from .synthetic_spec import SyntheticCapture
from .synthetic_render import render_dark_frame


# --------------------------------------------------------------------------------------------
# Writing
# --------------------------------------------------------------------------------------------


def write_truth_run(capture: SyntheticCapture, folder, *, pixel_size_um=None) -> Path:
    """A run folder made of the capture's truth: ``albedo.tif``, ``depth.tif`` and ``protrusions.csv``
    (id, x_px, y_px, width_um, height_um), as ``uvps run --detect`` would write them with no error
    of its own: for testing what reads run folders (``changes``, ``stats``) apart from the pipeline.
    """
    folder = Path(folder)
    folder.mkdir(parents=True)
    px = capture.spec.pixel_size_um if pixel_size_um is None else float(pixel_size_um)
    write_imagej_tiff(folder / "albedo.tif", np.moveaxis(capture.albedo, -1, 0), axes="CYX", pixel_size_um=px)
    write_imagej_tiff(folder / "depth.tif", capture.height_um, axes="YX", pixel_size_um=px)
    t = capture.protrusions
    with open(folder / "protrusions.csv", "w", newline="", encoding="utf-8") as fh:
        w = csv.writer(fh)
        w.writerow(["id", "x_px", "y_px", "width_um", "height_um"])
        for i in range(t["id"].size):
            w.writerow([int(t["id"][i]), t["x_px"][i], t["y_px"][i], t["width_um"][i], t["height_um"][i]])
    return folder


#: The black and white levels of the DNG files :func:`write_dng` writes (a 14-bit sensor).
DNG_BLACK, DNG_WHITE = 512, 16383


def write_dng(path, rgb, *, black=DNG_BLACK, white=DNG_WHITE, linearization=None, default_crop=None):
    """A minimal CFA DNG of the linear scene ``rgb`` (M, N, 3) counts above ``black``: the RGGB mosaic
    plus ``black``, 16-bit, with the tags LibRaw needs (CFA layout, DNG version, camera model, black
    and white levels, an identity colour matrix, a neutral white balance). ``black``: one level, or four, one per
    site of the 2 x 2 tile in row order (R, G, G, B).

    ``linearization``: a LinearizationTable (increasing counts, one per stored code); the mosaic is then
    stored as the codes whose table values are nearest (a camera storing 12-bit codes of 16-bit counts), clipped
    at the table's top. ``default_crop``: ``(left, top, width, height)`` written as DefaultCropOrigin and
    DefaultCropSize."""
    rgb = np.asarray(rgb, dtype=np.float64)
    M, N = rgb.shape[:2]
    pattern = np.array([[0, 1], [1, 2]])                      # R G / G B
    ch = pattern[np.arange(M)[:, None] % 2, np.arange(N)[None, :] % 2]
    blacks = np.broadcast_to(np.asarray(black, dtype=np.float64).ravel(), (4,)).reshape(2, 2)   # per 2 x 2 site
    mosaic = np.take_along_axis(rgb, ch[..., None], axis=2)[..., 0] + blacks[np.arange(M)[:, None] % 2,
                                                                               np.arange(N)[None, :] % 2]
    mosaic = np.clip(np.rint(mosaic), 0, white)
    extra = []
    if linearization is not None:
        table = np.asarray(linearization, dtype=np.float64)
        hi = np.clip(np.searchsorted(table, mosaic), 1, table.size - 1)          # the nearest code (table increasing)
        mosaic = np.where(mosaic - table[hi - 1] <= table[hi] - mosaic, hi - 1, hi)
        extra.append((50712, "H", table.size, tuple(int(v) for v in table), True))    # LinearizationTable
    if default_crop is not None:
        left, top, width, height = (int(v) for v in default_crop)
        extra += [(50719, "H", 2, (left, top), True), (50720, "H", 2, (width, height), True)]
    mosaic = mosaic.astype(np.uint16)

    def rational(values, den=10000):
        return tuple(x for v in values for x in (int(round(v * den)), den))

    extratags = [
        (33421, "H", 2, (2, 2), True),                         # CFARepeatPatternDim
        (33422, "B", 4, (0, 1, 1, 2), True),                   # CFAPattern: R G G B
        (50706, "B", 4, (1, 4, 0, 0), True),                   # DNGVersion
        (50707, "B", 4, (1, 1, 0, 0), True),                   # DNGBackwardVersion
        (50708, "s", 0, "uvps test camera", True),             # UniqueCameraModel
        (50713, "H", 2, (2, 2), True),                         # BlackLevelRepeatDim
        (50714, "H", 4, tuple(int(v) for v in blacks.ravel()), True),   # BlackLevel, per site of the 2 x 2 tile
        (50717, "H", 1, (int(white),), True),                  # WhiteLevel
        (50721, "2i", 9, rational([1, 0, 0, 0, 1, 0, 0, 0, 1]), True),   # ColorMatrix1
        (50728, "2I", 3, rational([1, 1, 1]), True),           # AsShotNeutral
        (50778, "H", 1, (21,), True),                          # CalibrationIlluminant1: D65
    ] + extra
    tifffile.imwrite(path, mosaic, photometric=32803, extratags=extratags, metadata=None, subfiletype=0)
    return path



def write_raw_capture(capture: SyntheticCapture, folder) -> list:
    """Write a capture as camera raw files: ``uv_NN.dng`` (:func:`write_dng`, counts / 4: the mosaic's
    14 bits) and ``lights.csv`` (``file,x_mm,y_mm,z_mm``). Returns the paths written."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=False)
    paths = []
    for k, img in enumerate(capture.images):
        rgb = np.asarray(img, np.float64)
        rgb = rgb if rgb.ndim == 3 else np.repeat(rgb[..., None], 3, axis=2)
        paths.append(write_dng(folder / f"uv_{k:02d}.dng", rgb / 4.0))
    lines = ["file,x_mm,y_mm,z_mm"] + [f"uv_{k:02d}.dng," + ",".join(f"{v:.6f}" for v in p)
                                       for k, p in enumerate(capture.light_positions_mm)]
    (folder / "lights.csv").write_text("\n".join(lines) + "\n")
    return paths + [folder / "lights.csv"]



def write_capture(capture: SyntheticCapture, folder, *, truth: bool = True, dark_frame: bool = False,
                  card: Optional[np.ndarray] = None) -> list:
    """Write a capture as a folder of 16-bit TIFFs, light files and (optionally) ground truth.

    Parameters
    ----------
    capture : SyntheticCapture
    folder : path
        Created if missing (its parent must exist); files are moved in atomically.
    truth : bool
        Also write ``truth/``.
    dark_frame : bool
        Also write ``dark/dark.tif`` (:func:`render_dark_frame`), for ``run``'s ``dark``
        parameter (in a folder of its own, so that the folder's images stay the lamps' ones).
    card : (K, M, N[, C]) array, optional
        A card's images (:func:`render_card`), written as ``card/`` with the images' names (``run``'s
        ``card`` parameter).

    Returns
    -------
    paths : list of Path
        Every file written, images first.

    Notes
    -----
    Images: ``uv_00.tif``... 16-bit RGB (interleaved, as a camera converter writes them) or grey,
    with XResolution = YResolution = 1 / pixel size (pixels per um) and an ImageJ description
    ``unit=micron`` so that ImageJ's calibration is right. ``lights_positions_mm.csv``
    (file,x_mm,y_mm,z_mm) and ``lights.lp`` (RTI format: K, then ``file x y z``, the unit
    direction from the image centre to each light). ``truth/``: ``height_um.tif``,
    ``normals.tif`` (3, M, N) CYX, ``albedo.tif``, ``regions.tif`` (labels, uint16 as ImageJ has
    no 32-bit integers), ``protrusions.csv`` (columns as ``uvps.core.measure``'s, plus ``weak``,
    ``aspect``, ``angle_deg``, ``region_name``, ``shape``, ``cluster``, ``dark``),
    ``truth.json`` (with ``nuisances``: black level per channel, stray light's fraction and mean
    counts per channel, vignetting parameters, each lamp's beam axis, aim point and factor at
    the centre, each lamp's position, ``E_k`` and irradiance at the centre, cast-shadow
    fractions, crack parameters: whichever are present) and, when present, ``vignetting.tif``,
    ``stray_light_counts.tif``, ``shadows.tif`` (K planes, 1 = shadowed) and ``cracks.tif``.
    Truth TIFFs are ImageJ hyperstacks written by :func:`uvps.files.io.write_imagej_tiff`.
    """
    px = float(capture.spec.pixel_size_um)
    k = capture.images.shape[0]
    digits = max(2, len(str(k - 1)))
    names = [f"uv_{i:0{digits}d}.tif" for i in range(k)]
    folder = Path(folder)
    with atomic_output_dir(folder) as tmp:
        written = []
        for name, img in zip(names, capture.images):
            _write_camera_tiff(tmp / name, img, px)
            written.append(name)
        pos = capture.light_positions_mm
        with open(tmp / "lights_positions_mm.csv", "w", newline="", encoding="utf-8") as fh:
            wr = csv.writer(fh)
            wr.writerow(["file", "x_mm", "y_mm", "z_mm"])
            for name, p in zip(names, pos):
                wr.writerow([name] + [f"{v:.6f}" for v in p])
        directions = pos / np.linalg.norm(pos, axis=1, keepdims=True)
        with open(tmp / "lights.lp", "w", encoding="utf-8") as fh:
            fh.write(f"{k}\n")
            for name, d in zip(names, directions):
                fh.write(f"{name} {d[0]:.8f} {d[1]:.8f} {d[2]:.8f}\n")
        written += ["lights_positions_mm.csv", "lights.lp"]
        if dark_frame:
            (tmp / "dark").mkdir()
            _write_camera_tiff(tmp / "dark" / "dark.tif", render_dark_frame(capture), px)
            written.append("dark/dark.tif")
        if card is not None:
            (tmp / "card").mkdir()
            for name, img in zip(names, card):
                _write_camera_tiff(tmp / "card" / name, img, px)
                written.append(f"card/{name}")
        if truth:
            written += _write_truth(capture, tmp / "truth", names)
    return [folder / w for w in written]


def _write_camera_tiff(path, img, px, **tiff_options):
    """One image as a camera converter writes it (interleaved RGB or grey), calibrated in um;
    ``tiff_options`` go to ``tifffile.imwrite`` (e.g. ``compression``, ``byteorder``)."""
    tifffile.imwrite(path, img, photometric="rgb" if img.ndim == 3 else "minisblack",
                     resolution=(1 / px, 1 / px), resolutionunit="NONE",
                     description="ImageJ=1.54f\nunit=micron\n", metadata=None, **tiff_options)


def _write_truth(capture, folder, image_names):
    """Write the ground truth of ``capture`` into ``folder`` (new): height, normals, albedo and
    colour areas as calibrated ImageJ TIFFs, the protrusion table, the nuisances' maps and
    ``truth.json`` (lamps, exposure, spec, nuisances' draws, frames). Returns the files written,
    relative to the capture folder."""
    folder.mkdir()
    px = float(capture.spec.pixel_size_um)
    # Truth TIFFs are ImageJ hyperstacks through the shared writer (atomic, calibrated in um).

    def imagej(name, data, axes, labels=None):
        write_imagej_tiff(folder / name, data, axes=axes, pixel_size_um=px, labels=labels)

    imagej("height_um.tif", capture.height_um.astype(np.float32), "YX")
    imagej("normals.tif", np.moveaxis(capture.normals, -1, 0).astype(np.float32), "CYX",
           ["nx", "ny", "nz"])
    alb = capture.albedo.astype(np.float32)
    if alb.ndim == 3:
        imagej("albedo.tif", np.moveaxis(alb, -1, 0), "CYX", ["R", "G", "B"])
    else:
        imagej("albedo.tif", alb, "YX")
    imagej("regions.tif", capture.regions.astype(np.int32), "YX")
    _write_truth_protrusions(capture, folder / "protrusions.csv")
    nz = capture.nuisances
    files = ["height_um.tif", "normals.tif", "albedo.tif", "regions.tif"]
    files += _write_nuisance_maps(capture, imagej, image_names)
    spec = dataclasses.asdict(capture.spec)
    write_json_atomic(folder / "truth.json", {
        "schema_version": 1,
        "pixel_size_um": px,
        "image_shape": list(capture.height_um.shape),
        "files": image_names,
        "light_positions_mm": capture.light_positions_mm,
        "intensities": capture.intensities,
        "exposure": capture.exposure,
        "gain": capture.gain,
        "region_names": capture.region_names,
        "region_light": [bool(b) for b in capture.region_light],
        "n_protrusions": int(capture.protrusions["id"].size),
        "spec": {key: list(val) if isinstance(val, tuple) else val for key, val in spec.items()},
        "nuisances": nz.info,
        "frames": "x right, y up, z toward camera; positions in mm from the image centre; "
                  "heights in um (median 0); normals.tif channels nx, ny, nz",
    })
    return [f"truth/{f}" for f in files + ["protrusions.csv", "truth.json"]]


def _write_truth_protrusions(capture, path):
    """The true protrusions as CSV, with the same leading columns as :mod:`uvps.core.measure`'s
    ``protrusions.csv`` (so ``compare`` takes it as is), then the area's name and the
    generator's own columns (shape, cluster, dark, on_stroke) where present."""
    prot = dict(capture.protrusions)
    prot["area_um2"] = np.pi * prot["width_um"] ** 2 / 4
    columns = ["id", "x_px", "y_px", "width_um", "area_um2", "height_um", "crater", "region",
               "weak", "aspect", "angle_deg"]
    extra = [c for c in ("shape", "cluster", "dark", "on_stroke") if c in prot]
    with open(path, "w", newline="", encoding="utf-8") as fh:
        wr = csv.writer(fh)
        wr.writerow(columns + ["region_name"] + extra)
        for i in range(prot["id"].size):
            row = []
            for c in columns:
                v = prot[c][i]
                row.append(int(v) if v.dtype.kind in "biu" else f"{float(v):.4f}")
            row.append(capture.region_names[int(prot["region"][i]) - 1])
            row += [str(prot[c][i]) if prot[c].dtype.kind == "U" else int(prot[c][i])
                    for c in extra]
            wr.writerow(row)


def _write_nuisance_maps(capture, imagej, image_names):
    """The maps of the nuisances the capture holds (vignetting, stray light in counts, each
    image's cast shadows, cracks) through ``imagej(name, data, axes, labels)``; returns their
    names."""
    nz = capture.nuisances
    files = []
    if nz.vignetting is not None:
        imagej("vignetting.tif", nz.vignetting.astype(np.float32), "YX")
        files.append("vignetting.tif")
    if nz.stray_light is not None:
        stray = (capture.exposure * nz.stray_light).astype(np.float32)   # counts
        if stray.ndim == 3:
            imagej("stray_light_counts.tif", np.moveaxis(stray, -1, 0), "CYX", ["R", "G", "B"])
        else:
            imagej("stray_light_counts.tif", stray, "YX")
        files.append("stray_light_counts.tif")
    if nz.shadowed is not None:
        imagej("shadows.tif", nz.shadowed.astype(np.uint8), "ZYX", image_names)
        files.append("shadows.tif")
    if nz.cracks is not None:
        imagej("cracks.tif", nz.cracks.astype(np.uint8), "YX")
        files.append("cracks.tif")
    return files
