"""One function per menu item: dialog values -> one bridge call -> results shown (Jython 2.7).

Each function takes the dict returned by ``dialogs.UVPSDialog.show()`` (keys = macro keys) and
raises BridgeError on any failure; the menu script reports it (``runner.run_menu``). The request
is built from the core's declarations (:func:`run_command`: every declared parameter whose macro
key the dialog showed); a function here adds only what ImageJ itself holds (the current stack,
point selections, ROIs) and shows the results. Output files are found by the names fixed in
docs/architecture.md ("Output folder of a run").
"""
import os

from ij import IJ

from uvps_fiji import bridge_logic, capture, display, runner
from uvps_fiji.bridge_logic import BridgeError, optional_path

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


def run_command(command, values, inputs=None, params=None, request_dir=None, skip=()):
    """Run any core command from dialog values: the generic menu item.

    The request holds every parameter of ``command``'s declaration whose macro key is in
    ``values`` (``bridge_logic.request_from_values``), then ``inputs`` and ``params`` (what the
    caller took from ImageJ; ``skip`` names declared parameters the caller fills itself). The run
    folder is ``values["run"]``. A command's plain-text answer (``uvps info``), or for a command
    without output files its diagnostics, goes to the Log.

    Returns
    -------
    bridge_logic.Response
    """
    table = runner.command_table()
    spec = bridge_logic.command_spec(command, table)
    got_inputs, got_params = bridge_logic.request_from_values(command, values, table, skip=skip)
    got_inputs.update(inputs or {})
    got_params.update(params or {})
    response = runner.call(command, got_inputs, got_params, run_folder(values),
                           request_dir=request_dir)
    if (response.text or not spec.get("output")) \
            and response.text != (response.diagnostics or {}).get("summary"):
        # (a summary the diagnostics carry is one of the Log lines below)
        IJ.log(bridge_logic.response_text(response))
    report_response(command, response, table,
                    user_gave_lights=bool(optional_path(values.get("lights"))))
    return response


def report_response(command, response, table=None, user_gave_lights=False):
    """The response's warnings and diagnostics in the Log, in the menu user's words; warnings
    that change the result also in a (non-modal) window when a user clicked the menu item."""
    table = table or runner.command_table()
    for line in bridge_logic.diagnostic_lines(command, response.diagnostics, user_gave_lights, table):
        IJ.log(line)
    lines = bridge_logic.warning_lines(response, command, table)
    for line in lines:
        IJ.log(line)
    serious = [line for line, w in zip(lines, response.warnings)
               if bridge_logic.affects_result(w)]
    if serious and runner.is_interactive():
        display.show_warnings(bridge_logic.menu_title(command, table), serious)


def _capture_call(command, values, params=None):
    """A command on the capture (run, flatfield, lights, normals): the images and the pixel size
    come from ImageJ when the capture is the current stack."""
    table = runner.command_table()
    field = 'the field "%s"' % bridge_logic.field_name(
        bridge_logic.param_spec(command, "pixel_size_um", table))
    # checked before the stack is copied and the core started
    extra = {"pixel_size_um": capture.pixel_size_of_current(values, field)}
    request_dir = runner.new_request_dir()
    inputs = capture.capture_inputs(values, request_dir)
    extra.update(params or {})
    return run_command(command, values, inputs, extra, request_dir,
                       skip=("images", "pixel_size_um"))


def titled(name, run_dir):
    """The title of one of the run's windows or tables: ``"albedo - region1"``."""
    return bridge_logic.run_title(name, run_dir)


def height_title(run_dir):
    """``height (um) - <run>``, or ``relative height - <run>`` when the run's height scale is
    relative."""
    return titled(bridge_logic.HEIGHT_WORDS[bridge_logic.relief_scale(run_dir)][0], run_dir)


def show_height(path, run_dir):
    """The height map titled by :func:`height_title`, its unit on the colour bar; the Log says what
    levelling removed (``bridge_logic.level_line``)."""
    line = bridge_logic.level_line(run_dir)
    if line:
        IJ.log("uvps: " + line)
    return display.show_height(path, height_title(run_dir), bridge_logic.relief_scale(run_dir))


def _show_protrusions(response, kind, run_dir):
    """Open one kind's protrusion table (``bridge_logic.OUTLINE_KINDS``: "auto" from Detect
    Protrusions, "manual" from Wand Count), its ROIs, and the albedo (RGB) and the height map
    with the outlines as overlay. The albedo and the height are opened afresh, with the other
    kind's outlines of the run carried over while the run folder still holds its table: both
    kinds of one run are shown together, each replacing only its own."""
    csv_name, title = bridge_logic.OUTLINE_KINDS[kind]
    labels_name = csv_name.replace(".csv", "_labels.tif")
    other = [k for k in bridge_logic.OUTLINE_KINDS if k != kind][0]
    other_kept = os.path.isfile(os.path.join(run_dir, bridge_logic.OUTLINE_KINDS[other][0]))

    def reopened(window_title, opener):
        kept = display.outlines_on(window_title, run_dir) if other_kept else []
        areas = display.areas_on(window_title, run_dir)   # the colour areas drawn on it stay
        imp = opener()
        display.add_to_overlay(imp, areas + [r for r in kept if bridge_logic.outline_kind(
            r.getName(), run_dir) == other])
        return imp

    albedo = height = None
    albedo_path = os.path.join(run_dir, "albedo.tif")
    if os.path.isfile(albedo_path):
        albedo = reopened(titled("albedo", run_dir),
                          lambda: display.show_albedo(albedo_path, titled("albedo", run_dir)))
    height_path = os.path.join(run_dir, "depth.tif")
    if os.path.isfile(height_path):
        height = reopened(height_title(run_dir), lambda: show_height(height_path, run_dir))
    labels = response.file(labels_name) if response.has_file(labels_name) else None
    return display.show_protrusions(response.file(csv_name), labels, albedo, titled(title, run_dir),
                                    images=[height], kind=kind, run_dir=run_dir,
                                    replace=[] if other_kept else [other])


def _show_lights(response, run_dir):
    display.show_lights(response.file("lights.json"), titled("Lights (top view)", run_dir),
                        titled("Lights", run_dir))


def estimate_lights(values):
    """``lights``: lamp directions from the capture's drop-off (paper, figure 1b-f)."""
    response = _capture_call("lights", values)
    out = run_folder(values)
    _show_lights(response, out)
    display.open_image(response.file("dropoff.tif"), titled("dropoff", out))
    return response


def flat_field(values):
    """``flatfield``: divide each image by its Legendre drop-off fit."""
    response = _capture_call("flatfield", values)
    out = run_folder(values)
    display.open_image(response.file("dropoff.tif"), titled("dropoff", out))
    # One float32 TIFF per image in <run>/flatfield/ (3 channels each for an RGB capture).
    display.open_folder_stack(response.path("flatfield"), titled("flatfield", out))
    return response


def normals_and_albedo(values):
    """``normals``: per-pixel least squares for normals and the RGB fluorescence albedo."""
    response = _capture_call("normals", values)
    out = run_folder(values)
    display.show_normals(response.file("normals.tif"), titled("normals", out))
    display.show_albedo(response.file("albedo.tif"), titled("albedo", out))
    return response


def integrate_height(values):
    """``integrate``: height in um from the run's normals."""
    _run_file(values, "normals.tif")
    response = run_command("integrate", values)
    show_height(response.file("depth.tif"), run_folder(values))
    return response


def detect_protrusions(values):
    """``detect``: automated protrusion detection (albedo colour + template, height blobs)."""
    out = run_folder(values)
    _run_file(values, "albedo.tif")
    response = run_command("detect", values)
    _show_protrusions(response, "auto", out)
    return response


def wand_points(values, request_dir):
    """The wand's clicks: the ``points`` file as the user gave it (the core reads it, in the unit
    its header names: ``wand.read_seed_file``), else the current point selection / ROI Manager
    points, written in pixels to the request folder."""
    path = optional_path(values.get("points"))
    if path is not None:
        if not os.path.isfile(path):
            raise BridgeError("points file %s does not exist" % path)
        return path, "the file %s" % path
    points = capture.point_selection()
    if not points:
        raise BridgeError("no points: click the protrusions with the multi-point tool (or "
                          "add points to the ROI Manager), or give a CSV with x_px,y_px "
                          "(key points=)")
    return capture.write_points(points, request_dir), "the point selection"


def wand_count(values):
    """``wand``: the manual method; one wand selection per click on the albedo, then counted.
    Only clicks that outlined a protrusion are counted; the Log's line "7 clicks: 5 outlined, 2 not
    (bare paint at (x, y) px; ...)" names the others, which stay in the table as clicks (``counted``
    0, and why) with no outline. The grey (R+G+B)/3 image the wand works on opens as
    ``albedo (R+G+B)/3`` for wanding by hand."""
    out = run_folder(values)
    albedo_path = _run_file(values, "albedo.tif")
    request_dir = runner.new_request_dir()
    points_path, where = wand_points(values, request_dir)
    response = run_command("wand", values, {"points": points_path}, None, request_dir,
                           skip=("points",))
    IJ.log("uvps Wand Count: %s" % bridge_logic.clicks_line(
        response.diagnostics, where, automatic=values.get("units") in (None, "", "Automatic")))
    count = _show_protrusions(response, "manual", out)
    display.show_wand_image(albedo_path, titled("albedo (R+G+B)/3", out))
    IJ.log("uvps Wand Count: %d protrusions" % count)
    return response


def colour_areas(values):
    """``regions``: colour areas from the ROI Manager, a label image, or the automatic proposal."""
    source = values.get("source")
    request_dir = runner.new_request_dir()
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
        params = {"auto": True}
    skip = ("labels", "n_areas") if source != "Automatic" else ("labels",)
    response = run_command("regions", values, inputs, params, request_dir, skip=skip)
    out = run_folder(values)
    display.open_image(response.file("regions_labels.tif"), titled("regions_labels", out))
    albedo = None
    if os.path.isfile(os.path.join(out, "albedo.tif")):
        albedo = display.show_albedo(os.path.join(out, "albedo.tif"), titled("albedo", out))
    _show_areas(response, out, [albedo])
    return response


def _show_areas(response, run_dir, images):
    """The run's colour areas as outlines with their numbers and names (the report's "area 5")
    on ``images``, and ``regions.csv`` as the table "Regions - <run>"."""
    csv_path = response.file("regions.csv") if response.has_file("regions.csv") else \
        os.path.join(run_dir, "regions.csv")
    display.show_areas(response.file("regions_labels.tif"), csv_path, images, run_dir,
                       titled("Regions", run_dir))


def statistics_and_report(values):
    """``stats``: densities per cm^2 by width per colour area, report.html and figures."""
    response = run_command("stats", values)
    if response.has_file("regions.csv"):
        display.open_table(response.file("regions.csv"), titled("Regions", run_folder(values)))
    display.show_report(response.file("report.html"), runner.is_interactive())
    return response


def compare_counts(values):
    """``compare``: match two protrusion tables (e.g. manual vs automated) within a radius."""
    for key in ("first", "second"):
        path = optional_path(values.get(key))
        if path is None or not os.path.isfile(path):
            raise BridgeError("protrusion table '%s' (key %s) does not exist" % (path or "", key))
    response = run_command("compare", values)
    display.open_table(response.file("comparison.csv"), titled("Comparison", run_folder(values)))
    return response


def relight(values):
    """``relight``: render the run's normals and albedo under a virtual raking light."""
    _run_file(values, "normals.tif")
    response = run_command("relight", values)
    display.show_relight(response.file("relight.tif"), titled(
        "relight az%g el%g" % (values.get("azimuth"), values.get("elevation")), run_folder(values)))
    return response


def confirm_replacing(out, title):
    """Before a run replaces the run folder ``out``: when it holds manual work (the wand's count, a
    comparison), ask whether to run, keeping it aside with the run it was measured on (the core moves
    it to ``earlier/<date>_<run id>/``), or to change nothing (a cancel). Asked whenever ImageJ has a
    display, from a macro too: a re-run is the moment the clicks of an afternoon could be lost."""
    from java.awt import GraphicsEnvironment

    found = bridge_logic.manual_work_in(out)
    if not found:
        return
    if not GraphicsEnvironment.isHeadless():
        runner.ask_or_cancel(title + ": manual work in the run folder",
                             bridge_logic.manual_work_question(out, found),
                             bridge_logic.KEEP_AND_RUN, bridge_logic.DO_NOT_RUN,
                             "cancelled: %s is unchanged, its manual work (%s) in place; to keep both "
                             "runs side by side, choose another run folder" % (out, ", ".join(found)))
    IJ.log("uvps %s: the manual work in %s (%s) is kept with the run it was measured on, in its "
           "earlier/ folder" % (title, out, ", ".join(found)))


def run_whole_pipeline(values):
    """``run``: capture -> lights, flat-field, normals, albedo, height (+ areas, detection). A run
    folder holding manual work is replaced only when the user says so (:func:`confirm_replacing`)."""
    out = run_folder(values)
    confirm_replacing(out, "Run Whole Pipeline")
    response = _capture_call("run", values)
    display.show_normals(response.file("normals.tif"), titled("normals", out))
    _show_lights(response, out)
    # The core detects whenever regions are set (or detect is ticked): show what it listed.
    if response.has_file("protrusions.csv"):
        _show_protrusions(response, "auto", out)
    else:
        # the new run folder holds no protrusion table: the earlier run's outlines are gone with it
        display.forget_outlines(out)
        show_height(response.file("depth.tif"), out)
        display.show_albedo(response.file("albedo.tif"), titled("albedo", out))
    if response.has_file("regions_labels.tif"):
        from ij import WindowManager
        _show_areas(response, out, [WindowManager.getImage(titled("albedo", out))])
    if response.has_file("report.html"):
        display.show_report(response.file("report.html"), runner.is_interactive())
    IJ.log("uvps Run Whole Pipeline: outputs in " + out)
    return response


def compare_captures(values):
    """``changes``: two dates of one region; the height change in blue-white-red with its
    calibration bar beside it and the earlier date's outlines coloured by status, both dates'
    albedos with their outlines by status, and the change table."""
    response = run_command("changes", values)
    out = run_folder(values)
    changes = response.file("changes.csv")
    rows = display.read_csv_rows(changes)
    dates = []
    for key, date in (("earlier", "a"), ("later", "b")):
        run = os.path.normpath(optional_path(values.get(key)) or "")
        rois = display.change_rois(rows, date, os.path.join(run, "protrusions_labels.tif"))
        dates.append((key, run, rois))
    height = display.show_height_change(response.file("height_change.tif"),
                                        titled("height change (um)", out))
    statuses = bridge_logic.status_counts(rows)
    display.add_to_overlay(height, [r.clone() for r in dates[0][2]])
    display.status_legend(height, [s for s, _ in statuses if s in display.STATUS_COLOURS])
    for key, run, rois in dates:
        path = os.path.join(run, "albedo.tif")
        if os.path.isfile(path):
            albedo = display.show_albedo(path, titled("albedo (%s)" % key, run))
            display.add_to_overlay(albedo, rois)
    display.open_table(changes, titled("Changes", out))
    IJ.log("uvps Compare Captures: %s; outlines coloured by status on the height change and on "
           "both dates' albedos" % ", ".join("%d %s" % (n, s) for s, n in statuses))
    IJ.selectWindow(height.getID())   # the height change in front, as before
    return response


def stitch_painting(values):
    """``batch`` with a mosaic layout or a grid: the tiles run, registered and merged into
    RUN/painting/; opens the painting at overview (protrusions, colour areas), the painting's
    colour-area table and its protrusion table, and names the report in the Log."""
    if not (optional_path(values.get("mosaic")) or (values.get("grid") or "").strip()):
        raise BridgeError("no layout: choose the tiles' layout CSV (key mosaic=) or give a grid "
                          "COLUMNS,ROWS,OVERLAP (key grid=)")
    response = run_command("batch", values)
    out = run_folder(values)
    painting = os.path.join(out, "painting")
    overview = display.open_image(os.path.join(painting, "figures", "painting_overview.png"),
                                  titled("painting overview", out))
    display.open_table(os.path.join(painting, "painting_regions.csv"), titled("Painting areas", out))
    display.open_table(os.path.join(painting, "painting_protrusions.csv"),
                       titled("Painting protrusions", out))
    IJ.log("uvps Stitch Painting: %s; the report with its zoomable view (open it in a web browser): %s"
           % (os.path.join(painting, "painting_regions.csv"), os.path.join(painting, "report.html")))
    IJ.selectWindow(overview.getID())
    return response


def element_maps(values):
    """``elements``: the registered element maps as a stack, and a composite of three of them
    (red, green, blue: keys red, green, blue; lead first by default)."""
    response = run_command("elements", values)
    stack = display.open_image(response.file("elements.tif"), "element maps (run frame)")
    wanted = [values.get(k) for k in ("red", "green", "blue")]
    channels, notes = bridge_logic.composite_channels(display.slice_labels(stack), wanted)
    for note in notes:
        IJ.log("uvps Element Maps: " + note)
    display.element_composite(stack, channels)
    IJ.log("uvps Element Maps: composite %s (choose with Red, Green, Blue element)" % ", ".join(
        "%s %s" % (c, n) for c, n in zip(("red", "green", "blue"), channels)))
    return response


def calibrate_lamps(values):
    """``calibrate``: lamps from a sphere capture (or a rig file) into a calibration folder (key
    ``calibration``); the spheres found drawn as circles on the sphere capture's first image, to check."""
    values = dict(values)
    values["run"] = values.get("calibration") or ""
    response = run_command("calibrate", values)
    cal = run_folder(values)
    image = bridge_logic.first_image(values.get("spheres"))
    if image is not None and os.path.isfile(os.path.join(cal, "calibration.json")):
        spheres = bridge_logic.calibration_spheres(os.path.join(cal, "calibration.json"))
        display.show_spheres(image, spheres)
        for x, y, d, name in spheres:
            IJ.log("uvps Calibrate Lamps: %s at (%.1f, %.1f) px, radius %.1f px"
                   % (name, x + d / 2.0 - 0.5, y + d / 2.0 - 0.5, d / 2.0))
    IJ.log("uvps Calibrate Lamps: calibration in " + cal + " (give it to Run Whole Pipeline)")
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
