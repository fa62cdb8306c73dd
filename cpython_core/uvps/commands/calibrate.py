"""``uvps calibrate``: lamps pinned once by spheres (or a measured rig) into a calibration folder, reused
for every capture taken with the same lamp positions (``uvps run --calibration CAL``). The folder's
contents and the relight ``.dome`` format: :mod:`uvps.files.calibration`.
"""
from __future__ import annotations

import logging
import math
import shutil
import tempfile
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np

from ..files.cards import load_card, write_card
from ..errors import UVPSInputError
from ..files.io import read_capture, read_image, read_lp, read_positions, sha256_file
from ..files.outputs import CommandResult, OutputSpec, check_output_dir, replace_dir, report, sub_progress, write_json_atomic
from ..spec import CommandSpec, Param
from ..core.spheres import KINDS, REFERENCE_RIM_FRACTION, Sphere, calibrate_spheres, detect_spheres, read_sphere_circles

from ..files.calibration import FORMAT, VERSION, FILES, read_dome, write_dome

log = logging.getLogger(__name__)

def _lights_json(directions, positions, pixel_size_um, image_shape, sources) -> dict:
    lights = []
    for k, d in enumerate(directions):
        lights.append({"file": None, "calibration_image": sources[k] if sources else None,
                       "direction": [float(v) for v in d],
                       "position_mm": None if positions is None else [float(v) for v in positions[k]],
                       "azimuth_deg": float(np.degrees(np.arctan2(d[1], d[0])) % 360.0),
                       "elevation_deg": float(np.degrees(np.arcsin(np.clip(d[2], -1, 1))))})
    return {"mode": "far" if positions is None else "near", "pixel_size_um": pixel_size_um,
            "image_shape": None if image_shape is None else list(image_shape), "source": "calibration",
            "lights": lights}


def _spheres_png(path, images, spheres) -> None:
    """The mean of the sphere capture (every 1-4th pixel) with each sphere's circle drawn on it: each
    sphere shows its shading and a highlight per lamp, so a wrong circle is seen at once."""
    import cv2
    from skimage.draw import circle_perimeter

    from ..core.spheres import _mean_image, _to8

    K, M, N = images.shape[:3]
    step = max(1, int(math.ceil(max(M, N) / 1600)))
    med = _mean_image(images, step)
    g = _to8(med)
    g = np.zeros(med.shape, np.uint8) if g is None else g
    rgb = np.repeat(g[..., None], 3, axis=2)
    for s in spheres:
        for dr in (-1, 0, 1):
            rr, cc = circle_perimeter(int(round(s.centre_px[1] / step)), int(round(s.centre_px[0] / step)),
                                      max(1, int(round(s.radius_px / step)) + dr), shape=med.shape)
            rgb[rr, cc] = (0, 200, 255) if s.kind == "matte" else (255, 60, 0)
    # a picture to look at: fast PNG compression (level 1 is a third of the default's time)
    if not cv2.imwrite(str(path), rgb[..., ::-1], [cv2.IMWRITE_PNG_COMPRESSION, 1]):
        raise OSError(f"could not write {path}")


def _hashes(paths) -> dict:
    return {str(p): sha256_file(p) for p in paths if p and Path(p).is_file()}


def _capture_files(cap) -> list:
    seen = []
    for f in cap.files:
        p = f.rsplit("#", 1)[0] if "#" in f and not Path(f).exists() else f
        if p not in seen:
            seen.append(p)
    return seen


def _spheres_on_reference(path, shape) -> list:
    """The spheres found on a room-lit picture of them in place (the same camera and framing as the sphere
    capture): for a dark sphere on a dark ground, whose rim the lamps alone do not show."""
    ref = read_image(path)
    if ref.shape[:2] != tuple(shape):
        raise UVPSInputError(f"sphere reference {path} is {ref.shape[1]} x {ref.shape[0]} px; expected "
                             f"{shape[1]} x {shape[0]} like the sphere capture (the same camera and framing)")
    found = detect_spheres(ref[None], min_rim_fraction=REFERENCE_RIM_FRACTION)
    if not found:
        raise UVPSInputError(f"sphere reference {path}: no sphere found; expected the spheres in place, lit by the "
                             "room, or give the circles with --sphere-circles (col,row,radius_px)")
    return [Sphere(s.centre_px, s.radius_px, s.kind, "reference") for s in found]


def _from_spheres(inputs, params, progress, pool):
    """The sphere route: (capture, LampCalibration, image names, the capture files' SHA-256 as a future).

    The files are hashed on a thread of ``pool`` while the spheres are fitted (hashlib works without
    the GIL): 64 images of 4000 x 3000 are 1.5 GB to hash, seconds that would otherwise add up."""
    px = params["pixel_size_um"]
    images = inputs["spheres"]
    cap = read_capture(images[0] if len(images) == 1 else images, dark=inputs["dark"], pixel_size_um=px,
                       linearize=params["linearize"], progress=sub_progress(progress, 0.0, 0.3))
    hashes = pool.submit(_hashes, _capture_files(cap))
    given = read_sphere_circles(inputs["sphere_circles"]) if inputs["sphere_circles"] else None
    if given is None and inputs.get("sphere_reference"):
        given = _spheres_on_reference(inputs["sphere_reference"], cap.images.shape[1:3])
    if given is not None and params["sphere_kind"] != "auto":
        given = [Sphere(s.centre_px, s.radius_px, params["sphere_kind"] if s.kind == "auto" else s.kind, s.source)
                 for s in given]
    capture_name = str(images[0]) if len(images) == 1 else f"{images[0]} (and {len(images) - 1} more)"
    names = [Path(f).name for f in cap.files]
    saturation = cap.saturation
    if saturation is not None and inputs["dark"] is not None:
        # a saturated sample is at the file's maximum before the dark frame is subtracted
        saturation = saturation - float(np.max(read_image(inputs["dark"])))
    # the kind given applies to detected spheres too, before their fit
    cal = calibrate_spheres(cap.images, pixel_size_um=cap.pixel_size_um, spheres=given, saturation=saturation,
                            files=names, kind=params["sphere_kind"], capture=capture_name,
                            camera_distance_mm=params.get("camera_distance_mm"),
                            progress=sub_progress(progress, 0.3, 0.9))
    return cap, cal, names, hashes


def _cmd_calibrate(inputs, params, output_dir, *, progress=None):
    """``calibrate``: a calibration folder from a sphere capture, a relight dome or a light file."""
    t0 = time.perf_counter()
    out = check_output_dir(output_dir)
    if out.exists() and any(out.iterdir()) and not (out / FILES["calibration"]).is_file():
        raise UVPSInputError(f"output folder {out} exists and is not a calibration folder; give a new folder")
    routes = [k for k in ("spheres", "dome", "lights") if inputs.get(k)]
    if len(routes) != 1:
        raise UVPSInputError("calibrate needs exactly one of spheres (a sphere capture), dome (a relight .dome "
                             f"file) or lights (.lp or a positions file); got {', '.join(routes) or 'none'}")
    route = routes[0]
    if route != "spheres" and params.get("camera_distance_mm") is not None:
        raise UVPSInputError(f"camera_distance_mm applies to spheres (how the camera sees them); calibrate from "
                             f"{route} takes the lamps as the file gives them: leave it out")
    with ThreadPoolExecutor(max_workers=1) as pool:
        return _calibrate(route, inputs, params, out, pool, t0, progress)


def _lamps_from_file(route, inputs, params):
    """Directions, positions (or None), the route as recorded and the lamps' JSON from a rig or light file."""
    path = inputs[route]
    if route == "dome":
        rig = read_dome(path)
        directions, positions = rig.directions, rig.positions
        if positions is not None and rig.image_width > 0 and params["image_width_mm"]:
            positions = positions * (params["image_width_mm"] / rig.image_width)
    elif Path(path).suffix.lower() == ".lp":
        lp = read_lp(path)
        directions, positions, route = lp.directions, None, "lp"
    else:
        lpos = read_positions(path)
        positions, route = lpos.positions_mm, "positions"
        directions = (lpos.directions if positions is None
                      else positions / np.linalg.norm(positions, axis=1, keepdims=True))
    lamps = [{"direction": [float(v) for v in d], "direction_sigma_deg": None,
              "position_mm": None if positions is None else [float(v) for v in positions[k]],
              "position_sigma_mm": None, "distance_sigma_pct": None} for k, d in enumerate(directions)]
    return directions, positions, route, lamps


def _card_for(inputs, lights, K, px, image_shape, dark_path):
    """The card's gains for the lamps just found (:mod:`uvps.core.card`) and the files to hash; (None, [])
    without a card."""
    if not inputs.get("card"):
        return None, []
    if px is None:
        raise UVPSInputError("card: the pixel size is needed (give pixel_size_um)")
    card = load_card(inputs["card"], lights=lights, pixel_size_um=px, dark=dark_path)
    if card.n_lamps != K:
        raise UVPSInputError(f"card {inputs['card']}: {card.n_lamps} images for {K} lamps; one card image per "
                             "lamp position, in the same order")
    if image_shape is not None and tuple(card.shape) != tuple(image_shape):
        raise UVPSInputError(f"card {inputs['card']}: images of {card.shape[1]} x {card.shape[0]} px; "
                             f"expected {image_shape[1]} x {image_shape[0]} like the sphere capture")
    card_path = Path(inputs["card"])
    return card, sorted(p for p in card_path.iterdir() if p.is_file()) if card_path.is_dir() else [card_path]


def _write_folder(out, doc, lights_json, *, directions, positions, route, px, image_shape, dark_path, cap, cal,
                  card):
    """The calibration folder, built beside ``out`` and swapped in whole."""
    tmp = Path(tempfile.mkdtemp(prefix="." + out.name + ".tmp-", dir=out.parent))
    try:
        write_json_atomic(tmp / FILES["calibration"], doc)
        write_json_atomic(tmp / FILES["lights"], lights_json)
        width = None if image_shape is None or px is None else image_shape[1] * px / 1000.0
        write_dome(tmp / FILES["dome"], directions=directions, positions_mm=positions, image_width_mm=width or 0.0,
                   label="uvps calibration", notes=f"uvps calibrate ({route}); units mm; x right, y up, z toward "
                                                   "the camera, from the image centre")
        if dark_path is not None:
            # as given: the same counts and layout (interleaved RGB or grey), so that it reads as the file did
            import tifffile

            d = read_image(dark_path)
            tifffile.imwrite(tmp / FILES["dark"], d, photometric="rgb" if d.ndim == 3 else "minisblack",
                             metadata=None)
        if cap is not None:
            _spheres_png(tmp / FILES["spheres_png"], cap.images, cal.spheres)
        if card is not None:
            write_card(card, tmp, pixel_size_um=px)
        replace_dir(tmp, out)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise


def _result(out, route, K, spheres_json, positions, cap, cal, t0, warnings):
    outputs = [OutputSpec("calibration", str(out / FILES["calibration"]), kind="json"),
               OutputSpec("lights", str(out / FILES["lights"]), kind="json"),
               OutputSpec("dome", str(out / FILES["dome"]), kind="json")]
    if cap is not None:
        outputs.append(OutputSpec("spheres_png", str(out / FILES["spheres_png"]), kind="image", axes="YXS",
                                  dtype="uint8", units="counts"))
    diag = {"route": route, "n_lamps": K, "spheres": spheres_json, "positions": positions is not None,
            "elapsed_s": round(time.perf_counter() - t0, 3)}
    if cal is not None:
        diag["direction_sigma_deg_max"] = float(np.max(cal.direction_sigma_deg))
        if cal.distance_sigma_pct is not None:
            diag["distance_sigma_pct_max"] = float(np.max(cal.distance_sigma_pct))
    return CommandResult(outputs, diag, warnings)


def _calibrate(route, inputs, params, out, pool, t0, progress):
    """The body of ``calibrate`` for one route, hashing on ``pool`` (:func:`_from_spheres`)."""
    warnings = []
    spheres_json, sources, cap, cal, image_shape, hashed_capture = [], None, None, None, None, None
    px = params["pixel_size_um"]
    dark_path = inputs["dark"]
    if route == "spheres":
        cap, cal, sources, hashed_capture = _from_spheres(inputs, params, progress, pool)
        px = cap.pixel_size_um
        image_shape = tuple(cap.images.shape[1:3])
        directions, positions = cal.directions, cal.positions_mm
        spheres_json = [f.sphere.to_json() for f in cal.fits]
        lamps = cal.lamps_json()
        hashed = [inputs["sphere_circles"], inputs.get("sphere_reference")]
        if cal.positions_mm is None and len(cal.fits) > 1:
            warnings.append(cal.diagnostics["positions"])
    else:
        if px is None:
            raise UVPSInputError(f"calibrate from {route}: pixel_size_um is required (the pixel on the painting)")
        if dark_path is not None and not Path(dark_path).is_file():
            raise UVPSInputError(f"dark frame {dark_path} does not exist")
        hashed = [inputs[route]]
        directions, positions, route, lamps = _lamps_from_file(route, inputs, params)
    if dark_path is not None:
        d = read_image(dark_path)
        if image_shape is not None and d.shape[:2] != image_shape:
            raise UVPSInputError(f"dark frame {dark_path} is {d.shape[1]} x {d.shape[0]} px; expected "
                                 f"{image_shape[1]} x {image_shape[0]} like the sphere capture")
        hashed.append(dark_path)
    K = len(directions)
    # a flat card under every lamp position: per-lamp flat-field gains for the lamps just found, stored
    # beside them; a run given this folder divides them out
    card, card_files = _card_for(inputs, positions if positions is not None else directions, K, px, image_shape,
                                 dark_path)
    hashed += card_files
    doc = {"format": FORMAT, "version": VERSION, "pixel_size_um": px,
           "image_shape": None if image_shape is None else list(image_shape), "n_lamps": K, "route": route,
           "spheres": spheres_json, "lamps": lamps,
           "camera_distance_mm": params.get("camera_distance_mm") if route == "spheres" else None,
           "inputs": {**(hashed_capture.result() if hashed_capture is not None else {}), **_hashes(hashed)},
           "card": None if card is None else card.to_json(),
           "dark": dark_path is not None, "created_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())}
    if cal is not None:
        doc["diagnostics"] = cal.diagnostics
    report(progress, 0.9, "calibrate: writing")
    _write_folder(out, doc, _lights_json(directions, positions, px, image_shape, sources), directions=directions,
                  positions=positions, route=route, px=px, image_shape=image_shape, dark_path=dark_path, cap=cap,
                  cal=cal, card=card)
    report(progress, 1.0, "calibrate: done")
    return _result(out, route, K, spheres_json, positions, cap, cal, t0, warnings)


SPECS = (
    CommandSpec("calibrate", "lamps from spheres (or a rig file) into a calibration folder", _cmd_calibrate,
                menu="Calibrate Lamps", output="calibration folder", params=(
                    Param("spheres", "paths", where="inputs",
                          label="Spheres: the sphere capture (folder, or files separated by ;)",
                          help="the sphere capture: one image per lamp position, in the order of the painting "
                               "captures' images (a folder, files or one multi-page TIFF)"),
                    Param("sphere_circles", "path", where="inputs",
                          label="Circles of the spheres, CSV (optional: overrides the detection)",
                          help="CSV col,row,radius_px[,kind] of each sphere (pixels): overrides the detection"),
                    Param("sphere_reference", "path", where="inputs",
                          label="Reference picture of the spheres (optional: room-lit, to find them)",
                          help="a picture of the spheres in place lit by the room (same camera and framing): "
                               "the spheres are found on it, for a dark sphere on a dark ground whose rim the "
                               "lamps do not show"),
                    Param("sphere_kind", "choice", "auto", choices=("auto",) + KINDS, label="Kind of sphere",
                          help="matte (white or grey: shading), glossy (black: a highlight's lobe) or mirror "
                               "(chrome: the lamp's small image); auto: from the highlight; applies to detected "
                               "spheres and to given circles without a kind"),
                    Param("camera_distance_mm", "float", minimum=0, exclusive_minimum=True, unit="mm",
                          label="Camera distance, mm (0 = orthographic: a far camera)",
                          help="mm from the painting to the lens's centre of projection (about f (1 + 1/m), "
                               "docs/capture.md): a glossy or mirror sphere off the lens's axis reflects the "
                               "view from the camera, not from straight above, and every sphere's outline is "
                               "that camera's; default: orthographic (a sphere read so is off by about its angle "
                               "off the axis: 8 mm off the axis of a camera 300 mm away, about 1.5 deg)"),
                    Param("dark", "path", where="inputs", label="Dark frame (optional: the UV lamps off)",
                          help="a frame with the UV lamps off: subtracted from the sphere capture and kept in "
                               "the calibration for the captures that use it"),
                    Param("card", "path", where="inputs",
                          label="Card (optional: a flat fluorescent card under each lamp)",
                          help="a folder (or stack) of a flat fluorescent card under each lamp position, in the "
                               "lamps' order: per-lamp flat-field gains (beams, power, vignetting) stored in the "
                               "calibration (docs/capture.md)"),
                    Param("dome", "path", where="inputs", label="Dome file (optional: a relight .dome rig instead of spheres)",
                          help="a relight .dome file (a rig calibrated before)"),
                    Param("lights", "path", where="inputs",
                          label="Lights file (optional: .lp or lamp positions in mm of a measured rig)",
                          help="an RTI .lp file or lamp positions (.csv/.json, mm) of a measured rig"),
                    Param("pixel_size_um", "float", minimum=0, exclusive_minimum=True, unit="um",
                          label="Pixel size on the painting (0 = from the image file)",
                          help="pixel size on the painting (default: from the TIFF tags; required for dome "
                               "and lights)"),
                    Param("image_width_mm", "float", minimum=0, exclusive_minimum=True, unit="mm",
                          label="Image width on the painting (dome only; 0 = the dome's positions in mm)",
                          help="with dome: the field's width in mm, to scale the dome's positions by its "
                               "imageWidth (default: the positions are in mm)"),
                    Param("linearize", "choice", "auto", choices=("auto", "srgb", "none"),
                          help="sRGB -> linear (auto: JPEG only)")),
                description="Writes a calibration folder (calibration.json, lights.json, rig.dome, dark.tif, "
                            "spheres.png) from a capture of spheres under the same lamp positions as the "
                            "painting (one sphere: lamp directions; two or more: 3-D positions), a relight "
                            ".dome file or a light file. `uvps run CAPTURE --calibration CAL` uses it."),
)
