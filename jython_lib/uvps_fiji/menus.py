"""One function per menu item: dialog values -> one bridge call -> results shown (Jython 2.7).

Each function takes the dict returned by ``dialogs.UVPSDialog.show()`` (keys = macro keys) and
raises BridgeError on any failure; the menu script reports it (``runner.run_menu``). Output files
are found by the names fixed in docs/architecture.md ("Output folder of a run").
"""
import os

from ij import IJ

from uvps_fiji import bridge_logic, capture, display, runner
from uvps_fiji.bridge_logic import BridgeError, optional_path
from uvps_fiji.dialogs import number_or_none

INTEGRATIONS = {"Frankot-Chellappa (FFT)": "fc", "DCT Poisson (Neumann)": "dct"}
INTEGRATION_CHOICES = ["Frankot-Chellappa (FFT)", "DCT Poisson (Neumann)"]
AREA_SOURCES = ["ROI Manager", "Automatic", "Label image"]


def run_folder(values):
    """The run folder (key ``run``): absolute, its parent must exist (the core creates it)."""
    path = (values.get("run") or "").strip()
    if not path:
        raise BridgeError("no run folder given: choose the folder for the outputs (key run=)")
    if not os.path.isabs(path):
        raise BridgeError("the run folder must be an absolute path; got '%s'" % path)
    return os.path.normpath(path)


def _run_file(values, name):
    path = os.path.join(run_folder(values), name)
    if not os.path.isfile(path):
        raise BridgeError("%s is missing; run the earlier steps into this run folder first" % path)
    return path


def _light_params(values):
    return {
        "degree": int(round(values.get("degree", 4))),
        "mask": optional_path(values.get("mask")),
        "dark": optional_path(values.get("dark")),
        "pixel_size_um": capture.pixel_size_of_current(values),
    }


def _regions_param(text):
    """Empty -> None, ``auto`` -> "auto", else an existing label TIFF."""
    text = optional_path(text)
    if text is None:
        return None
    if text.lower() in ("auto", "automatic"):
        return "auto"
    if not os.path.isfile(text):
        raise BridgeError("regions label image %s does not exist (give a TIFF, auto, or nothing)"
                          % text)
    return text


def _show_protrusions(response, csv_name, labels_name, run_dir, title):
    """Open the protrusion table, its ROIs, and the albedo with the outlines as overlay."""
    albedo = None
    albedo_path = os.path.join(run_dir, "albedo.tif")
    if os.path.isfile(albedo_path):
        albedo = display.open_image(albedo_path, "albedo")
    labels = response.file(labels_name) if response.has_file(labels_name) else None
    return display.show_protrusions(response.file(csv_name), labels, albedo, title)


def estimate_lights(values):
    """``lights``: lamp directions from the capture's drop-off (paper, figure 1b-f)."""
    out = run_folder(values)
    request_dir = bridge_logic.make_request_dir()
    params = _light_params(values)
    params["lights"] = optional_path(values.get("lights"))
    response = runner.call("lights", capture.capture_inputs(values, request_dir), params, out,
                           request_dir=request_dir)
    display.show_lights(response.file("lights.json"))
    display.open_image(response.file("dropoff.tif"), "dropoff")
    return response


def flat_field(values):
    """``flatfield``: divide each image by its Legendre drop-off fit."""
    out = run_folder(values)
    request_dir = bridge_logic.make_request_dir()
    response = runner.call("flatfield", capture.capture_inputs(values, request_dir),
                           _light_params(values), out, request_dir=request_dir)
    display.open_image(response.file("dropoff.tif"), "dropoff")
    # One float32 TIFF per image in <run>/flatfield/ (3 channels each for an RGB capture).
    display.open_folder_stack(response.path("flatfield"), "flatfield")
    return response

def normals_and_albedo(values):
    """``normals``: per-pixel least squares for normals and the RGB fluorescence albedo."""
    out = run_folder(values)
    request_dir = bridge_logic.make_request_dir()
    params = _light_params(values)
    params["lights"] = optional_path(values.get("lights"))
    params["robust"] = bool(values.get("robust"))
    response = runner.call("normals", capture.capture_inputs(values, request_dir), params, out,
                           request_dir=request_dir)
    display.open_image(response.file("normals.tif"), "normals")
    display.open_image(response.file("albedo.tif"), "albedo")
    return response


def integrate_height(values):
    """``integrate``: height in um from the run's normals."""
    out = run_folder(values)
    _run_file(values, "normals.tif")
    method = INTEGRATIONS[values.get("integration")]
    response = runner.call("integrate", {}, {"integration": method}, out)
    display.open_image(response.file("depth.tif"), "depth")
    return response


def detect_protrusions(values):
    """``detect``: automated protrusion detection (albedo colour + template, height blobs)."""
    out = run_folder(values)
    _run_file(values, "albedo.tif")
    params = {"regions": _regions_param(values.get("regions"))}
    response = runner.call("detect", {}, params, out)
    _show_protrusions(response, "protrusions.csv", "protrusions_labels.tif", out, "Protrusions")
    return response


def wand_points(values, request_dir):
    """The wand's clicks: the ``points`` CSV option, else the current point selection / ROI
    Manager points, written to the request folder."""
    path = optional_path(values.get("points"))
    if path is not None:
        if not os.path.isfile(path):
            raise BridgeError("points file %s does not exist" % path)
        return path  # the core reads and checks it (CSV, tab-separated or ImageJ XY)
    points = capture.point_selection()
    if not points:
        raise BridgeError("no points: click the protrusions with the multi-point tool (or add "
                          "points to the ROI Manager), or give a CSV with x_px,y_px (key points=)")
    return capture.write_points(points, request_dir)


def wand_count(values):
    """``wand``: the manual method; one wand selection per click on the albedo, then counted."""
    out = run_folder(values)
    _run_file(values, "albedo.tif")
    request_dir = bridge_logic.make_request_dir()
    points_path = wand_points(values, request_dir)
    params = {
        "tolerance": float(values.get("tolerance")),
        "connectivity": int(values.get("connectivity")),
        "regions": _regions_param(values.get("regions")),
    }
    response = runner.call("wand", {"points": points_path}, params, out, request_dir=request_dir)
    count = _show_protrusions(response, "protrusions_manual.csv",
                              "protrusions_manual_labels.tif", out, "Manual protrusions")
    IJ.log("uvps Wand Count: %d protrusions" % count)
    return response


def colour_areas(values):
    """``regions``: colour areas from the ROI Manager, a label image, or the automatic proposal."""
    out = run_folder(values)
    source = values.get("source")
    request_dir = bridge_logic.make_request_dir()
    inputs = {}
    params = {"auto": False, "n_areas": None}
    if source == "ROI Manager":
        rois = capture.area_rois()
        if not rois:
            raise BridgeError("the ROI Manager holds no area selections; draw one per colour "
                              "area and press Add [t], or choose Automatic")
        width, height = display.image_size(_run_file(values, "albedo.tif"))
        inputs["labels"] = capture.write_label_image(
            rois, width, height, os.path.join(request_dir, "areas_from_rois.tif"))
    elif source == "Label image":
        path = optional_path(values.get("label"))
        if path is None or not os.path.isfile(path):
            raise BridgeError("label image '%s' does not exist" % (path or ""))
        inputs["labels"] = path
    else:
        params["auto"] = True
        n = int(round(values.get("number") or 0))
        params["n_areas"] = n if n > 0 else None
    response = runner.call("regions", inputs, params, out, request_dir=request_dir)
    display.open_image(response.file("regions_labels.tif"), "regions_labels")
    display.open_table(response.file("regions.csv"), "Regions")
    return response


def statistics_and_report(values):
    """``report``: densities per cm^2 by width per colour area, report.html and figures."""
    out = run_folder(values)
    response = runner.call("report", {}, {"bins_um": float(values.get("bins"))}, out)
    if response.has_file("regions.csv"):
        display.open_table(response.file("regions.csv"), "Regions")
    display.show_report(response.file("report.html"), runner.is_interactive())
    return response


def compare_counts(values):
    """``compare``: match two protrusion tables (e.g. manual vs automated) within a radius."""
    out = run_folder(values)
    paths = []
    for key in ("first", "second"):
        path = optional_path(values.get(key))
        if path is None or not os.path.isfile(path):
            raise BridgeError("protrusion table '%s' (key %s) does not exist" % (path or "", key))
        paths.append(path)
    response = runner.call("compare", {"a": paths[0], "b": paths[1]},
                           {"match_radius_um": number_or_none(values.get("match"))}, out)
    display.open_table(response.file("comparison.csv"), "Comparison")
    return response


def relight(values):
    """``relight``: render the run's normals and albedo under a virtual raking light."""
    out = run_folder(values)
    _run_file(values, "normals.tif")
    params = {"azimuth_deg": float(values.get("azimuth")),
              "elevation_deg": float(values.get("elevation"))}
    response = runner.call("relight", {}, params, out)
    display.open_image(response.file("relight.tif"),
                       "relight az%g el%g" % (params["azimuth_deg"], params["elevation_deg"]))
    return response


def run_whole_pipeline(values):
    """``run``: capture -> lights, flat-field, normals, albedo, height (+ areas, detection)."""
    out = run_folder(values)
    request_dir = bridge_logic.make_request_dir()
    params = _light_params(values)
    params["lights"] = optional_path(values.get("lights"))
    params["robust"] = bool(values.get("robust"))
    params["integration"] = INTEGRATIONS[values.get("integration")]
    params["regions"] = _regions_param(values.get("regions"))
    params["detect"] = bool(values.get("detect"))
    response = runner.call("run", capture.capture_inputs(values, request_dir), params, out,
                           request_dir=request_dir)
    display.open_image(response.file("normals.tif"), "normals")
    display.open_image(response.file("depth.tif"), "depth")
    display.show_lights(response.file("lights.json"))
    if params["detect"]:
        _show_protrusions(response, "protrusions.csv", "protrusions_labels.tif", out,
                          "Protrusions")
    else:
        display.open_image(response.file("albedo.tif"), "albedo")
    if response.has_file("report.html"):
        display.show_report(response.file("report.html"), runner.is_interactive())
    IJ.log("uvps Run Whole Pipeline: outputs in " + out)
    return response


def settings(values, previous=""):
    """Save the CPython path (Prefs ``uvps.python``) after checking that it imports uvps;
    on failure the ``previous`` setting is put back."""
    from ij import Prefs
    chosen = (values.get("python") or "").strip()
    python, source = bridge_logic.find_python(chosen, None, bridge_logic.default_config_path())
    ok, text = runner.check_python(python)
    if not ok:
        Prefs.set(runner.PYTHON_PREF, previous)
        raise BridgeError(text + "; install uvps into that Python (pip install uvps) or choose "
                          "another one", error_type="Configuration")
    # An empty field clears the setting: the environment, uvps_fiji.cfg or python3 then apply.
    Prefs.set(runner.PYTHON_PREF, chosen)
    text = "%s (from %s)" % (text, source)
    Prefs.savePreferences()
    IJ.log("uvps Settings: " + text)
    IJ.showStatus("uvps: " + text)
    return text
