"""Show the core's outputs in ImageJ/Fiji (Jython 2.7).

Images open with ``IJ.openImage``, which reads the ImageJ metadata that tifffile writes (hyperstack
axes, ``micron`` unit, pixel size), so calibration and the scale bar are right. Tables open as
ResultsTables; protrusions become ROIs in the ROI Manager and an overlay on the albedo; lights are
drawn as a top view of the lamps.
"""
import json
import math
import os

from java.awt import Color

from ij import IJ, ImagePlus, WindowManager
from ij.gui import OvalRoi, Overlay, Plot, PolygonRoi, Roi, Wand
from ij.measure import ResultsTable
from ij.plugin.frame import RoiManager

from uvps_fiji import bridge_logic
from uvps_fiji.bridge_logic import BridgeError

#: Colours of protrusion outlines by source (``bridge_logic.OUTLINE_KINDS``): the automatic
#: ones red (the paper's figure 3b), the manual ones yellow, so both can be seen on one albedo.
OUTLINE_COLOURS = {"auto": Color(255, 0, 0), "manual": Color(255, 220, 0)}


def open_image(path, title=None, show=True):
    """Open a TIFF output (BridgeError if missing or unreadable) and show it.

    A window with the same title is closed first, so re-running a step replaces its result.
    """
    if not os.path.isfile(path):
        raise BridgeError("output image %s is missing" % path)
    imp = IJ.openImage(path)
    if imp is None:
        raise BridgeError("ImageJ cannot open the output image %s" % path)
    if title:
        imp.setTitle(title)
    if show:
        _show_replacing(imp)
    return imp


def _show_replacing(imp):
    """Show ``imp``, first closing (without asking to save) a window with the same title."""
    old = WindowManager.getImage(imp.getTitle())
    if old is not None:
        old.changes = False
        old.close()
    imp.show()
    keep_on_screen(imp.getWindow())


def keep_on_screen(window):
    """Move ``window`` (an AWT window; None is ignored) so that it lies on the screen as far as
    its size allows: ImageJ cascades new windows and some opened partly off-screen."""
    from java.awt import GraphicsEnvironment
    if window is None or GraphicsEnvironment.isHeadless():
        return
    screen = GraphicsEnvironment.getLocalGraphicsEnvironment().getMaximumWindowBounds()
    r = window.getBounds()
    x = min(max(r.x, screen.x), max(screen.x, screen.x + screen.width - r.width))
    y = min(max(r.y, screen.y), max(screen.y, screen.y + screen.height - r.height))
    if (x, y) != (r.x, r.y):
        window.setLocation(x, y)


def open_folder_stack(path, title):
    """Open a folder of TIFFs (one per light, e.g. ``flatfield/``) as one stack and show it;
    files with C > 1 channels (RGB float) give a hyperstack of C channels x lights."""
    from ij.plugin import FolderOpener
    if not os.path.isdir(path):
        raise BridgeError("output folder %s is missing" % path)
    files = sorted(f for f in os.listdir(path) if f.lower().endswith(".tif"))
    if not files:
        raise BridgeError("output folder %s holds no TIFF" % path)
    probe = IJ.openImage(os.path.join(path, files[0]))
    channels = probe.getNChannels() if probe is not None else 1
    imp = FolderOpener.open(path)
    if imp is None or imp.getStackSize() == 0:
        raise BridgeError("ImageJ cannot open the images in %s" % path)
    n = imp.getStackSize()
    if channels > 1 and n % channels == 0:
        imp.setDimensions(channels, 1, n // channels)
        imp.setOpenAsHyperStack(True)
    imp.setTitle(title)
    _show_replacing(imp)
    return imp


def open_table(path, title):
    """Open a CSV output as a ResultsTable window called ``title`` and return the table."""
    if not os.path.isfile(path):
        raise BridgeError("output table %s is missing" % path)
    table = ResultsTable.open(path)
    if table is None:
        raise BridgeError("ImageJ cannot read the table %s" % path)
    table.setPrecision(4)
    table.show(title)
    keep_on_screen(WindowManager.getWindow(title))
    return table


def _column(table, name):
    if not table.columnExists(name):
        return None
    return table.getColumnAsDoubles(table.getColumnIndex(name))


def protrusion_rois(table, labels_imp=None, pixel_size_um=None, kind="auto", run_dir=None):
    """Make one ROI per protrusion row, named by its source and run (``"auto 12 - region1"``,
    ``bridge_logic.outline_name``) and coloured by its source (:data:`OUTLINE_COLOURS`).

    The outline is traced in the label image (``protrusions_labels.tif``) from the centroid with
    ImageJ's Wand when the centroid lies inside its own label; otherwise (ring-shaped label, no
    label image) a circle of the row's ``width_um`` around the centroid is used. Rows whose
    ``counted`` is 0 (the wand's clicks that outlined no protrusion) get none.
    """
    xs = _column(table, "x_px")
    counted = _column(table, "counted")
    ys = _column(table, "y_px")
    if xs is None or ys is None:
        raise BridgeError("the protrusion table has no x_px, y_px columns")
    ids = _column(table, "id")
    widths = _column(table, "width_um")
    ip = labels_imp.getProcessor() if labels_imp is not None else None
    if pixel_size_um is None and labels_imp is not None:
        cal = labels_imp.getCalibration()
        if cal.scaled():
            pixel_size_um = cal.pixelWidth
    rois = []
    for i in range(len(xs)):
        if counted is not None and not counted[i] > 0:
            continue
        label = int(ids[i]) if ids is not None else i + 1
        roi = outline(ip, label, xs[i], ys[i], widths[i] if widths is not None else None,
                      pixel_size_um)
        roi.setName(bridge_logic.outline_name(kind, label, run_dir))
        roi.setStrokeColor(OUTLINE_COLOURS[kind])
        rois.append(roi)
    return rois


def outline(ip, label, x, y, width_um=None, pixel_size_um=None):
    """The outline of protrusion ``label`` whose centroid is ``(x, y)`` px: traced in the label
    image's processor ``ip`` with ImageJ's Wand when the centroid lies inside its own label,
    else (ring-shaped label, no label image) a circle of ``width_um`` (3 px when unknown)."""
    xi, yi = int(math.floor(x)), int(math.floor(y))
    if ip is not None and 0 <= xi < ip.getWidth() and 0 <= yi < ip.getHeight() \
            and int(round(ip.getPixelValue(xi, yi))) == label:
        wand = Wand(ip)
        wand.autoOutline(xi, yi, label - 0.5, label + 0.5, Wand.EIGHT_CONNECTED)
        if wand.npoints > 0:
            return PolygonRoi(wand.xpoints, wand.ypoints, wand.npoints, Roi.TRACED_ROI)
    d = 3.0
    if width_um is not None and pixel_size_um and width_um == width_um:
        d = max(width_um / pixel_size_um, 1.0)
    return OvalRoi(x + 0.5 - d / 2.0, y + 0.5 - d / 2.0, d, d)


#: Colour of the sphere circles of Calibrate Lamps.
SPHERE_COLOUR = Color(0, 200, 255)


def show_spheres(image_path, spheres, title="sphere capture (detections)"):
    """Open the sphere capture's first image with each sphere's circle as an overlay (and in the
    ROI Manager), so that the user checks the detection; ``spheres``: ``(x, y, d, name)`` from
    ``bridge_logic.calibration_spheres``."""
    imp = IJ.openImage(image_path)
    if imp is None:
        raise BridgeError("ImageJ cannot open the sphere image %s" % image_path)
    imp.setTitle(title)
    overlay = Overlay()
    rois = []
    for x, y, d, name in spheres:
        roi = OvalRoi(x, y, d, d)
        roi.setName(name)
        roi.setStrokeColor(SPHERE_COLOUR)
        roi.setStrokeWidth(2)
        overlay.add(roi)
        rois.append(roi)
    imp.setOverlay(overlay)
    _show_replacing(imp)
    manager = RoiManager.getInstance() or RoiManager()
    replace_rois(manager, "sphere ")
    for roi in rois:
        manager.addRoi(roi)
    return imp


def show_protrusions(csv_path, labels_path=None, albedo_imp=None, title="Protrusions",
                     images=(), kind="auto", run_dir=None, replace=None):
    """Open a protrusion table (``protrusions.csv`` or ``protrusions_manual.csv``) as the table
    window ``title``, its outlines in the ROI Manager and as an overlay on the albedo and
    ``images`` (e.g. the height map).

    Only the outlines of ``kind`` of the same run are replaced (and those of the kinds listed in
    ``replace``, e.g. a kind whose table the run folder no longer holds): the other source's
    outlines, other runs' and the user's ROIs, and the images' other overlay items stay.

    Returns
    -------
    int
        The number of protrusions (rows with ``counted`` 0, the wand's clicks not counted, are none).
    """
    table = open_table(csv_path, title)
    labels_imp = None
    if labels_path:
        if not os.path.isfile(labels_path):
            raise BridgeError("output label image %s is missing" % labels_path)
        labels_imp = IJ.openImage(labels_path)
    rois = protrusion_rois(table, labels_imp, kind=kind, run_dir=run_dir)
    gone = set([kind] + list(replace or ()))

    def replaced(roi):
        return bridge_logic.outline_kind(roi.getName(), run_dir) in gone

    manager = RoiManager.getInstance() or RoiManager()
    delete_rois(manager, replaced)
    for roi in rois:
        manager.addRoi(roi)
    for imp in [albedo_imp] + list(images):
        if imp is None:
            continue
        overlay = imp.getOverlay() or Overlay()
        for i in reversed(range(overlay.size())):
            if replaced(overlay.get(i)):
                overlay.remove(i)
        for roi in rois:
            overlay.add(roi.clone())
        imp.setOverlay(overlay)
    if table.columnExists("counted"):
        # a wand table lists every click: the Log counts the outlined ones, as the core does
        IJ.log("uvps: %d protrusions of %d clicks (%s)" % (len(rois), table.size(), csv_path))
    else:
        IJ.log("uvps: %d protrusions (%s)" % (table.size(), csv_path))
    return len(rois)   # the counted rows (a wand table also lists the clicks it did not count)


def _overlay_copies(title, keep):
    """Copies of the items of the open image ``title``'s overlay whose name ``keep`` accepts
    (none if it is not open or has no overlay)."""
    imp = WindowManager.getImage(title)
    overlay = imp.getOverlay() if imp is not None else None
    if overlay is None:
        return []
    return [overlay.get(i).clone() for i in range(overlay.size()) if keep(overlay.get(i).getName())]


def outlines_on(title, run_dir):
    """Copies of the protrusion outlines of run ``run_dir`` on the overlay of the open image
    ``title`` (none if it is not open): what a re-opened image should show again."""
    return _overlay_copies(title, lambda name: bridge_logic.outline_kind(name, run_dir) is not None)


def is_area_item(name, run_dir):
    """Whether an overlay item's name is one of run ``run_dir``'s colour areas (outline or tag,
    :func:`area_name`)."""
    suffix = " - " + bridge_logic.run_label(run_dir)
    name = name or ""
    return name.startswith("area ") and (name.endswith(suffix) or name.endswith(suffix + " tag"))


def areas_on(title, run_dir):
    """Copies of run ``run_dir``'s colour-area outlines and tags on the overlay of the open image
    ``title`` (none if it is not open): what a re-opened albedo should show again."""
    return _overlay_copies(title, lambda name: is_area_item(name, run_dir))


def add_to_overlay(imp, rois):
    """Add ``rois`` to the overlay of ``imp`` (kept items first)."""
    if imp is None or not rois:
        return
    overlay = imp.getOverlay() or Overlay()
    for roi in rois:
        overlay.add(roi)
    imp.setOverlay(overlay)


def forget_outlines(run_dir):
    """Delete the ROI Manager's protrusion outlines of run ``run_dir`` (both kinds)."""
    manager = RoiManager.getInstance()
    if manager is not None:
        delete_rois(manager, lambda roi: bridge_logic.outline_kind(roi.getName(), run_dir) is not None)


def delete_rois(manager, which):
    """Delete the ROI Manager's ROIs for which ``which(roi)`` holds; keep the others."""
    old = [i for i, roi in enumerate(manager.getRoisAsArray()) if which(roi)]
    if old:
        manager.setSelectedIndexes(old)
        manager.runCommand("Delete")


def replace_rois(manager, prefix):
    """Delete the ROIs whose names start with ``prefix`` (an earlier run's), keep the user's."""
    delete_rois(manager, lambda roi: (roi.getName() or "").startswith(prefix))


def read_lights(path):
    """Read ``lights.json`` (BridgeError if missing or without lights)."""
    if not os.path.isfile(path):
        raise BridgeError("lights file %s is missing" % path)
    fh = open(path, "r")
    try:
        data = json.load(fh)
    finally:
        fh.close()
    if not data.get("lights"):
        raise BridgeError("lights file %s lists no lights" % path)
    return data


def show_lights(path, title="Lights (top view)", table_title="Lights"):
    """Plot the lamps seen from the camera and open a "Lights" table; return the Plot.

    Each lamp sits at ``(cos(el) cos(az), cos(el) sin(az))`` (azimuth from +x toward +y, the
    world frame of docs/architecture.md), so the centre is a lamp overhead and the unit circle
    the horizon.
    """
    data = read_lights(path)
    table = ResultsTable()
    xs, ys = [], []
    for i, light in enumerate(data["lights"]):
        az = light.get("azimuth_deg")
        el = light.get("elevation_deg")
        table.incrementCounter()
        table.addValue("light", i + 1)
        table.addValue("file", os.path.basename(light.get("file") or ""))
        table.addValue("azimuth_deg", az if az is not None else float("nan"))
        table.addValue("elevation_deg", el if el is not None else float("nan"))
        table.addValue("intensity", light.get("intensity") or float("nan"))
        pos = light.get("position_mm") or [float("nan")] * 3
        for axis, value in zip("xyz", pos):
            table.addValue(axis + "_mm", value if value is not None else float("nan"))
        if az is None:
            continue
        r = math.cos(math.radians(el)) if el is not None else 1.0
        xs.append(r * math.cos(math.radians(az)))
        ys.append(r * math.sin(math.radians(az)))
    table.setPrecision(3)
    table.show(table_title)
    keep_on_screen(WindowManager.getWindow(table_title))
    plot = Plot(title, "x (toward image right)", "y (toward image top)")
    plot.setLimits(-1.15, 1.15, -1.15, 1.15)
    circle_x = [math.cos(2 * math.pi * t / 90.0) for t in range(91)]
    circle_y = [math.sin(2 * math.pi * t / 90.0) for t in range(91)]
    plot.setColor(Color.gray)
    plot.addPoints(circle_x, circle_y, Plot.LINE)
    plot.setColor(Color(0, 90, 200))
    plot.addPoints(xs, ys, Plot.CIRCLE)
    plot.setColor(Color.black)
    for i in range(len(xs)):
        plot.addText(str(i + 1), xs[i] + 0.04, ys[i] + 0.04)
    plot.setColor(Color.black)
    # shown as a plain image: Window > Tile refuses plot windows that are not frozen (the
    # numbers are in the Lights table)
    imp = ImagePlus(title, plot.getProcessor().duplicate())
    _show_replacing(imp)
    return plot


def show_report(path, interactive):
    """Open ``report.html`` in the browser when interactive; always log its path."""
    if not os.path.isfile(path):
        raise BridgeError("report %s is missing" % path)
    IJ.log("uvps: report " + path)
    if interactive:
        from ij.plugin import BrowserLauncher
        BrowserLauncher.openURL("file://" + path)


def image_size(path):
    """Return (width, height) of a TIFF without reading its pixels."""
    from ij.io import Opener
    infos = Opener.getTiffFileInfo(path)
    if not infos:
        raise BridgeError("cannot read the TIFF header of %s" % path)
    return infos[0].width, infos[0].height


def show_warnings(title, lines):
    """Show warnings in a non-modal text window (never a modal dialog: a batch run would hang);
    an earlier window of the same item is replaced."""
    from ij.text import TextWindow
    name = "uvps warnings: " + title
    old = WindowManager.getWindow(name)
    if old is not None:
        old.dispose()
    TextWindow(name, "\n".join(lines), 700, 200)


# ---------------------------------------------------------------------------------------------
# Height, albedo and the wand's image as a person looks at them (display only: files unchanged)
# ---------------------------------------------------------------------------------------------

#: matplotlib's viridis at 0, 1/8, ..., 1: the LUT built when ImageJ has no "mpl-viridis".
VIRIDIS = [(68, 1, 84), (71, 45, 123), (59, 82, 139), (44, 114, 142), (33, 145, 140),
           (40, 174, 128), (94, 201, 98), (173, 220, 48), (253, 231, 37)]

MICRONS = u"\u00b5m"


def viridis_lut():
    """ImageJ's ``mpl-viridis`` LUT (Fiji's luts/ folder) if present, else viridis interpolated
    from :data:`VIRIDIS`: perceptually uniform, readable in grey and by colour-blind people."""
    luts = IJ.getDirectory("luts")
    path = os.path.join(luts, "mpl-viridis.lut") if luts else None
    if path and os.path.isfile(path):
        from ij.plugin import LutLoader
        lut = LutLoader.openLut(path)
        if lut is not None:
            return lut
    return lut_from(VIRIDIS)


#: ColorBrewer's RdBu (9 classes) from negative (blue) through zero (white) to positive (red):
#: a height change's map, loss blue, gain red, no change white.
BLUE_WHITE_RED = [(33, 102, 172), (67, 147, 195), (146, 197, 222), (209, 229, 240),
                  (247, 247, 247), (253, 219, 199), (244, 165, 130), (214, 96, 77), (178, 24, 43)]


def lut_from(anchors):
    """A 256-entry ImageJ LUT interpolated linearly between the evenly spaced RGB ``anchors``
    (ImageJ builds LUTs from byte arrays; no interpolating constructor exists in 1.x)."""
    from jarray import array
    from ij.process import LUT
    reds, greens, blues = [], [], []
    for i in range(256):
        t = i / 255.0 * (len(anchors) - 1)
        k = min(int(t), len(anchors) - 2)
        f = t - k
        a, b = anchors[k], anchors[k + 1]
        rgb = [int(round(a[c] + f * (b[c] - a[c]))) for c in range(3)]
        for out, v in zip((reds, greens, blues), rgb):
            out.append(v - 256 if v > 127 else v)
    return LUT(array(reds, "b"), array(greens, "b"), array(blues, "b"))


def show_height(path, title, scale="absolute"):
    """Open the height map with its value unit (um; "relative" when the run's height scale is
    not pinned, see ``bridge_logic.relief_scale``), a viridis LUT and ImageJ's calibration bar
    beside it, its unit under it (:func:`bar_beside`: the heights keep their pixels)."""
    _, unit, bar_label = bridge_logic.HEIGHT_WORDS[scale]
    imp = open_image(path, title, show=False)
    imp.getCalibration().setValueUnit(unit)
    imp.setLut(viridis_lut())
    imp.resetDisplayRange()
    return bar_beside(imp, bar_label, "depth.tif")


#: Names of the overlay items of :func:`bar_beside` (tests and probes look for them).
BAR_NAME, BAR_UNIT_NAME, BAR_MARGIN_NAME = ("calibration bar", "calibration bar unit",
                                            "calibration bar margin")


def bar_zoom(height):
    """The calibration bar's zoom for an image ``height`` px tall: ImageJ shows a large image
    reduced to fit the screen, so the bar grows with it to stay readable."""
    return max(1, int(math.ceil(height / 900.0)))


def _widened(imp, margin):
    """``imp`` (one float plane) with ``margin`` columns of NaN added on the right (ImageJ's
    statistics and histograms skip NaN, so the margin never enters a measurement); the pixels
    at (x, y) stay those of the file."""
    from java.lang import Float
    from java.util import Arrays
    from ij.process import FloatProcessor
    ip = imp.getProcessor().convertToFloat()
    w, h = ip.getWidth(), ip.getHeight()
    out = FloatProcessor(w + margin, h)
    Arrays.fill(out.getPixels(), Float.NaN)
    out.insert(ip, 0, 0)
    out.setLut(imp.getProcessor().getLut())
    out.setMinAndMax(ip.getMin(), ip.getMax())
    wide = ImagePlus(imp.getTitle(), out)
    wide.setCalibration(imp.getCalibration())
    return wide


def bar_beside(imp, label, what, decimals=1):
    """Show the float image ``imp`` (LUT and display range set) with ImageJ's calibration bar
    (*Analyze > Tools > Calibration Bar*) beside it, not over it: the canvas is widened on the
    right by a blank margin (NaN pixels, white on screen) that holds the bar and ``label`` (the
    unit) under it. Pixels at (x, y) are the file's; the image's Info says so. Returns the
    shown ImagePlus."""
    from ij.gui import TextRoi
    from java.awt import Font
    w, h = imp.getWidth(), imp.getHeight()
    zoom = bar_zoom(h)
    font = Font("SansSerif", Font.PLAIN, 12 * zoom)
    label_width = TextRoi(0, 0, label, font).getBounds().width
    margin = max(100 * zoom, label_width + 8 * zoom)
    for _ in range(3):
        shown = _widened(imp, margin)
        _show_replacing(shown)
        IJ.run(shown, "Calibration Bar...", "location=[Upper Right] fill=White label=Black "
               "number=5 decimal=%d font=12 zoom=%d overlay" % (decimals, zoom))
        overlay = shown.getOverlay() or Overlay()
        bar = None
        for i in range(overlay.size()):
            overlay.get(i).setName(BAR_NAME)
            b = overlay.get(i).getBounds()
            bar = b if bar is None else bar.union(b)
        if bar is None or bar.x >= w + 2:
            break
        margin += w + 2 * zoom + 2 - bar.x   # the bar did not fit: widen by what it lacked
    blank = Roi(w, 0, shown.getWidth() - w, h)
    blank.setFillColor(Color.white)
    blank.setName(BAR_MARGIN_NAME)
    items = [blank] + [overlay.get(i) for i in range(overlay.size())]
    x = (bar.x + bar.width - label_width) if bar is not None else w + 2
    y = (bar.y + bar.height) if bar is not None else 2
    text = TextRoi(max(w + 1, x), y, label, font)
    text.setStrokeColor(Color.black)
    text.setFillColor(Color.white)
    text.setName(BAR_UNIT_NAME)
    items.append(text)
    fresh = Overlay()
    for item in items:
        fresh.add(item)
    shown.setOverlay(fresh)
    shown.setProperty("Info", "uvps: %s; columns %d and right of it are a blank margin (NaN) "
                      "that holds the calibration bar, not part of the file" % (what, w))
    return shown


def _sample_top(processors, fraction=0.995, n=200000):
    """The ``fraction`` quantile of the finite values of ``processors`` (a sample of them)."""
    values = []
    for ip in processors:
        pixels = ip.getPixels()
        step = max(1, len(pixels) * len(processors) // n)
        values.extend(v for v in pixels[::step] if v == v)
    if not values:
        return 1.0
    values.sort()
    return values[min(len(values) - 1, int(fraction * len(values)))] or 1.0


def rgb_image(float_imp, title, low=None, high=None, what="albedo.tif"):
    """The colour a person sees of a 3-channel float image: one RGB image, every channel mapped
    from [low, high] to 0-255 by the same factor (default: 0 to the 99.5 % quantile of the
    values). Display only; an image without 3 channels is returned unchanged."""
    from ij.process import ColorProcessor
    stack = float_imp.getStack()
    if stack.getSize() != 3:
        return float_imp
    channels = [stack.getProcessor(i + 1) for i in range(3)]
    low = 0.0 if low is None else low
    high = _sample_top(channels) if high is None else high
    planes = []
    for ip in channels:
        ip = ip.duplicate()
        ip.setMinAndMax(low, high)
        planes.append(ip.convertToByte(True).getPixels())
    cp = ColorProcessor(float_imp.getWidth(), float_imp.getHeight())
    cp.setRGB(planes[0], planes[1], planes[2])
    imp = ImagePlus(title, cp)
    imp.setCalibration(float_imp.getCalibration())
    imp.setProperty("Info", "uvps: %s shown as RGB (channels %g..%g mapped to 0..255 for "
                    "display; the values are in the file)" % (what, low, high))
    return imp


def albedo_rgb(float_imp, title="albedo"):
    """The 3 float channels of ``albedo.tif`` as one RGB image (99.5 % of the values below
    white). Display only."""
    return rgb_image(float_imp, title)


def show_normals(path, title):
    """``normals.tif`` (nx, ny, nz in [-1, 1]) as the usual normal-map colours: R, G, B =
    (n + 1) / 2 (x right, y up, z toward the camera: a flat area facing the camera is lilac).
    Display only; the file keeps the float normals."""
    imp = rgb_image(open_image(path, title, show=False), title, -1.0, 1.0, "normals.tif")
    _show_replacing(imp)
    return imp


def show_relight(path, title):
    """``relight.tif`` as a colour image when it has R, G, B (a colour albedo), else grey."""
    imp = rgb_image(open_image(path, title, show=False), title, what="relight.tif")
    _show_replacing(imp)
    return imp


def show_albedo(path, title="albedo"):
    """Open ``albedo.tif`` as an RGB image (display only; the file keeps its float values)."""
    imp = albedo_rgb(open_image(path, title, show=False), title)
    _show_replacing(imp)
    return imp


def wand_image(albedo_path, title):
    """The grey image the wand works on: (R + G + B) / 3 of the float albedo (ImageJ's own wand
    on an RGB image uses the same mean), calibrated like the albedo."""
    from ij.process import Blitter
    imp = open_image(albedo_path, show=False)
    stack = imp.getStack()
    grey = stack.getProcessor(1).duplicate().convertToFloat()
    for i in range(2, stack.getSize() + 1):
        grey.copyBits(stack.getProcessor(i).convertToFloat(), 0, 0, Blitter.ADD)
    grey.multiply(1.0 / stack.getSize())
    grey.resetMinAndMax()
    out = ImagePlus(title, grey)
    out.setCalibration(imp.getCalibration())
    return out


def show_wand_image(albedo_path, title):
    imp = wand_image(albedo_path, title)
    _show_replacing(imp)
    IJ.log("uvps: '%s' is the grey image the wand works on: use ImageJ's wand tool on it with "
           "the same tolerance to check a selection by hand" % title)
    return imp


# ---------------------------------------------------------------------------------------------
# Colour areas, height change and element maps as the report names them
# ---------------------------------------------------------------------------------------------

#: Colours of the colour areas' outlines and names (Tableau 10, distinct on an albedo), by label.
AREA_COLOURS = [(31, 119, 180), (255, 127, 14), (44, 160, 44), (214, 39, 40), (148, 103, 189),
                (140, 86, 75), (227, 119, 194), (127, 127, 127), (188, 189, 34), (23, 190, 207)]


def area_name(label, name, run_dir):
    """The overlay name of colour area ``label``: ``"area 5 (blue) - region1"``, the report's
    "area 5" with the name regions.csv gives it."""
    return bridge_logic.run_title("area %d (%s)" % (label, name), run_dir) if name \
        else bridge_logic.run_title("area %d" % label, run_dir)


def read_csv_rows(path):
    """The rows of a CSV output as dicts (the csv module: quoted names with commas are kept)."""
    import csv
    fh = open(path, "rb")
    try:
        return list(csv.DictReader(fh))
    finally:
        fh.close()


def area_rois(labels_path, regions_csv, run_dir):
    """One outline (ImageJ's *Edit > Selection > Create Selection* of the label's pixels) and
    one name tag per colour area of ``regions_labels.tif``, named by :func:`area_name`."""
    from ij.gui import TextRoi
    from ij.plugin.filter import ThresholdToSelection
    from ij.process import ImageProcessor
    from java.awt import Font
    if not os.path.isfile(labels_path):
        raise BridgeError("output label image %s is missing" % labels_path)
    labels = IJ.openImage(labels_path)
    if labels is None:
        raise BridgeError("ImageJ cannot open the label image %s" % labels_path)
    names = {}
    if regions_csv and os.path.isfile(regions_csv):
        for row in read_csv_rows(regions_csv):
            try:
                names[int(float(row.get("label", "")))] = (row.get("name") or "").strip()
            except ValueError:
                pass  # the "all" row
    ip = labels.getProcessor()
    top = int(ip.getStatistics().max)
    zoom = bar_zoom(labels.getHeight())
    font = Font("SansSerif", Font.BOLD, 14 * zoom)
    rois = []
    for label in range(1, top + 1):
        ip.setThreshold(label - 0.5, label + 0.5, ImageProcessor.NO_LUT_UPDATE)
        roi = ThresholdToSelection.run(labels)
        ip.resetThreshold()
        if roi is None:
            continue
        colour = Color(*AREA_COLOURS[(label - 1) % len(AREA_COLOURS)])
        name = area_name(label, names.get(label), run_dir)
        roi.setName(name)
        roi.setStrokeColor(colour)
        roi.setStrokeWidth(2 * zoom)
        rois.append(roi)
        # the tag inside the area, at its largest piece's centre when that lies inside it
        pieces = roi.getRois() if hasattr(roi, "getRois") else [roi]
        piece = max(pieces, key=lambda r: r.getStatistics().pixelCount) if pieces else roi
        b = piece.getBounds()
        x, y = b.x + b.width // 2, b.y + b.height // 2
        if not roi.contains(x, y):
            points = piece.getContainedPoints()
            if points:
                x, y = points[len(points) // 2].x, points[len(points) // 2].y
        word = "area %d" % label
        if names.get(label) and names[label] != word:
            word += " (%s)" % names[label]
        tag = TextRoi(x, y, word, font)
        tb = tag.getBounds()
        tag.setLocation(max(0, x - tb.width // 2), max(0, y - tb.height // 2))
        tag.setStrokeColor(Color.white)
        tag.setFillColor(Color(colour.getRed(), colour.getGreen(), colour.getBlue(), 170))
        tag.setName(name + " tag")
        rois.append(tag)
    return rois


def show_areas(labels_path, regions_csv, images, run_dir, table_title=None):
    """Draw the colour areas (outlines and name tags, :func:`area_rois`) on ``images`` (the
    albedo, the height map: an earlier drawing of the same run's areas is replaced) and open
    ``regions.csv`` as the table ``table_title``; return the number of areas."""
    rois = area_rois(labels_path, regions_csv, run_dir)
    for imp in images:
        if imp is None:
            continue
        overlay = imp.getOverlay() or Overlay()
        for i in reversed(range(overlay.size())):
            if is_area_item(overlay.get(i).getName(), run_dir):
                overlay.remove(i)
        for roi in rois:
            overlay.add(roi.clone())
        imp.setOverlay(overlay)
    if table_title and regions_csv and os.path.isfile(regions_csv):
        open_table(regions_csv, table_title)
    n = len([r for r in rois if not (r.getName() or "").endswith(" tag")])
    IJ.log("uvps: %d colour areas drawn with their names (%s)" % (n, labels_path))
    return n


#: Outline colours of Compare Captures by status (the report's, unchanged grey instead of
#: near-white so that it shows on a light albedo).
STATUS_COLOURS = {"new": Color(26, 150, 65), "grown": Color(215, 25, 28),
                  "shrunk": Color(253, 174, 97), "unchanged": Color(150, 150, 150),
                  "gone": Color(44, 123, 182), "merged": Color(123, 50, 148),
                  "split": Color(197, 27, 125)}


def change_rois(rows, date, labels_path=None, pixel_size_um=None):
    """The outlines of one date's protrusions among ``changes.csv``'s ``rows`` (dicts,
    :func:`read_csv_rows`), coloured by status (:data:`STATUS_COLOURS`) and named
    ``"grown 12 (later)"``. ``date``: ``"a"`` (the earlier run, ids ``id_a``) or ``"b"``; outlines
    traced in that run's ``protrusions_labels.tif``."""
    labels = IJ.openImage(labels_path) if labels_path and os.path.isfile(labels_path) else None
    ip = labels.getProcessor() if labels is not None else None
    if pixel_size_um is None and labels is not None and labels.getCalibration().scaled():
        pixel_size_um = labels.getCalibration().pixelWidth
    word = {"a": "earlier", "b": "later"}[date]
    rois = []
    for row in rows:
        ident = (row.get("id_" + date) or "").strip()
        if not ident:
            continue
        try:
            label = int(float(ident))
            x, y = float(row["x_px_" + date]), float(row["y_px_" + date])
        except (KeyError, ValueError):
            continue
        try:
            width = float(row.get("width_um_" + date) or "nan")
        except ValueError:
            width = None
        status = (row.get("status") or "").strip()
        roi = outline(ip, label, x, y, width, pixel_size_um)
        roi.setName("%s %d (%s)" % (status, label, word))
        roi.setStrokeColor(STATUS_COLOURS.get(status, Color.white))
        rois.append(roi)
    return rois


def status_legend(imp, statuses):
    """The status colours as text lines on the overlay of ``imp`` under its calibration bar's unit
    (:func:`bar_beside`'s margin): what each outline colour means. Nothing without a bar."""
    from ij.gui import TextRoi
    from java.awt import Font
    overlay = imp.getOverlay() or Overlay()
    units = [overlay.get(i) for i in range(overlay.size())
             if overlay.get(i).getName() == BAR_UNIT_NAME]
    if not units:
        return
    b = units[0].getBounds()
    x, y = b.x, b.y + b.height + 6
    zoom = bar_zoom(imp.getHeight())
    font = Font("SansSerif", Font.BOLD, 12 * zoom)
    for status in statuses:
        text = TextRoi(x, y, status, font)
        text.setStrokeColor(STATUS_COLOURS[status])
        text.setName("legend " + status)
        overlay.add(text)
        y += text.getBounds().height
    imp.setOverlay(overlay)


def show_height_change(path, title):
    """``height_change.tif`` (later minus earlier, um, the earlier run's frame) in blue-white-red
    (:data:`BLUE_WHITE_RED`), symmetric about 0 (99.5 % of the values within the range), with
    ImageJ's calibration bar beside it (:func:`bar_beside`)."""
    imp = open_image(path, title, show=False)
    imp.getCalibration().setValueUnit(u"\u00b5m")
    imp.setLut(lut_from(BLUE_WHITE_RED))
    ip = imp.getProcessor()
    top = _sample_top([_absolute(ip)])
    ip.setMinAndMax(-top, top)
    return bar_beside(imp, u"height change (\u00b5m)", "height_change.tif", decimals=2)


def _absolute(ip):
    out = ip.duplicate().convertToFloat()
    out.abs()
    return out


def element_composite(stack_imp, channels):
    """The open ``elements.tif`` stack ``stack_imp`` as an ImageJ composite of the three elements
    ``channels`` (red, green, blue; names as the stack's slice labels, :func:`slice_labels`), each
    channel from 0 to its 99.5 % quantile; the whole stack stays open beside it for the other
    elements. Returns the composite."""
    from ij import CompositeImage, ImageStack
    from ij.process import LUT
    stack = stack_imp.getStack()
    labels = slice_labels(stack_imp)
    picked = ImageStack(stack_imp.getWidth(), stack_imp.getHeight())
    for name in channels:
        ip = stack.getProcessor(labels.index(name) + 1).duplicate()
        picked.addSlice(name, ip)
    comp_title = "%s (%s)" % (stack_imp.getTitle(), "/".join(channels))
    imp = ImagePlus(comp_title, picked)
    imp.setDimensions(len(channels), 1, 1)
    imp.setCalibration(stack_imp.getCalibration())
    comp = CompositeImage(imp, CompositeImage.COMPOSITE)
    for c, colour in enumerate((Color.red, Color.green, Color.blue)[:len(channels)]):
        comp.setC(c + 1)
        comp.setChannelLut(LUT.createLutFromColor(colour))
        top = _sample_top([picked.getProcessor(c + 1)])
        comp.setDisplayRange(0.0, top)
    comp.setC(1)
    comp.setTitle(comp_title)
    info = stack_imp.getOriginalFileInfo()
    source = os.path.join(info.directory, info.fileName) \
        if info is not None and info.directory and info.fileName else stack_imp.getTitle()
    comp.setProperty("Info", "uvps: elements %s of %s as red, green, blue (display only)"
                     % (", ".join(channels), source))
    _show_replacing(comp)
    return comp


def slice_labels(imp):
    """The slice labels of a stack (e.g. ``elements.tif``'s element names), stripped."""
    stack = imp.getStack()
    return [(stack.getSliceLabel(i + 1) or "").strip() for i in range(stack.getSize())]
