"""Inputs of a bridge call taken from ImageJ: the capture stack, points, ROIs (Jython 2.7).

The current stack is passed by its file when it was opened from a multi-page TIFF and is
unchanged; otherwise it is written as an ImageJ TIFF into the request folder (with
``ij.io.TiffEncoder``, so the user's window keeps its title and file).
"""
import os
import time

from java.io import BufferedOutputStream, DataOutputStream, FileOutputStream
from java.lang import Throwable

from ij import IJ, WindowManager
from ij.gui import Roi
from ij.io import FileSaver, Opener, TiffEncoder
from ij.plugin.frame import RoiManager
from ij.process import ShortProcessor
from ij import ImagePlus

from uvps_fiji import bridge_logic
from uvps_fiji.bridge_logic import BridgeError
from uvps_fiji.dialogs import CAPTURE_CURRENT


def _saved_path(imp):
    info = imp.getOriginalFileInfo()
    if info is None or not info.fileName or not info.directory:
        return None
    return os.path.join(info.directory, info.fileName)


def _file_slices(path):
    try:
        infos = Opener.getTiffFileInfo(path)
    except (Exception, Throwable):
        return None
    if not infos:
        return None
    if len(infos) == 1:
        return max(infos[0].nImages, 1)
    return len(infos)


def write_stack(imp, path):
    """Write ``imp`` as an ImageJ TIFF stack at ``path`` without changing the open image."""
    if imp.getStack().isVirtual():
        imp = imp.duplicate()
    info = imp.getFileInfo()
    info.description = FileSaver(imp).getDescriptionString()
    info.nImages = imp.getStackSize()
    out = DataOutputStream(BufferedOutputStream(FileOutputStream(path), 1 << 20))
    try:
        TiffEncoder(info).write(out)
    finally:
        out.close()
    return path


def _lamps_hint(values):
    """Lamps a lights file names: the dialog's *Lights file*, else the run folder's lights.json
    (which later steps reuse). Returns (count or None, where)."""
    path = bridge_logic.optional_path(values.get("lights"))
    if path is None and values.get("run"):
        path = os.path.join(values.get("run"), "lights.json")
    count = bridge_logic.lights_file_count(path)
    return count, (os.path.basename(path) if count else "")


def _slice_labels(imp):
    stack = imp.getStack()
    return [stack.getSliceLabel(i + 1) or "" for i in range(stack.getSize())]


def current_stack_input(request_dir, values=None):
    """Return ``inputs["images"]`` for the current image: its file or a copy in the request
    folder. The stack's lamps, channels and bit depth are logged first; a grey stack holding the
    R, G, B slices of RGB images is written as a 3-channel hyperstack (or refused, see
    ``bridge_logic.stack_layout``)."""
    values = values or {}
    imp = WindowManager.getCurrentImage()
    if imp is None:
        raise BridgeError("no image is open; open the capture as a stack, or choose "
                          "'Folder or files' and give the images")
    n = imp.getStackSize()
    if n < 2:
        raise BridgeError("the current image '%s' has 1 slice; photometric stereo needs a stack "
                          "with one image per light" % imp.getTitle())
    hint, hint_source = _lamps_hint(values)
    layout = bridge_logic.stack_layout(
        imp.getTitle(), n, imp.getNChannels(), imp.getBitDepth(), _slice_labels(imp), hint,
        hint_source, values.get("channels") or bridge_logic.CHANNELS_AUTO)
    depth = "8-bit RGB" if imp.getBitDepth() == 24 else "%d-bit" % imp.getBitDepth()
    IJ.log("uvps: current stack '%s': %d lamps, %d channel%s, %s, %d x %d pixels (%s)"
           % (imp.getTitle(), layout["lamps"], layout["channels"],
              "s" if layout["channels"] > 1 else "", depth, imp.getWidth(), imp.getHeight(),
              layout["why"]))
    if layout["lamps"] < 3:
        raise BridgeError("the current stack '%s' holds %d lamps; photometric stereo needs at "
                          "least 3" % (imp.getTitle(), layout["lamps"]))
    saved = _saved_path(imp)
    path = None
    if not layout["regroup"]:
        path = bridge_logic.stack_source(saved, imp.changes, n,
                                         _file_slices(saved) if saved else None)
    if path is None:
        path = bridge_logic.stack_request_path(request_dir, imp.getTitle())
        IJ.showStatus("uvps: writing %s (%d images)..." % (imp.getTitle(), n))
        start = time.time()
        target = imp
        if layout["regroup"]:
            # the same pixels (no copy) seen as 3 channels x lamps: written as a hyperstack
            target = ImagePlus(imp.getTitle(), imp.getStack())
            target.setCalibration(imp.getCalibration())
            target.setDimensions(3, layout["lamps"], 1)
            target.setOpenAsHyperStack(True)
        write_stack(target, path)
        IJ.log("uvps: wrote the stack '%s' (%d images) in %.2f s"
               % (imp.getTitle(), n, time.time() - start))
    return [path]


def capture_inputs(values, request_dir):
    """Build ``{"images": [...]}`` from the capture fields (keys capture, images, channels)."""
    if values.get("capture") == CAPTURE_CURRENT:
        images = current_stack_input(request_dir, values)
    else:
        images = bridge_logic.images_input(values.get("images"))
    IJ.log("uvps: capture " + "; ".join(images))
    return {"images": images}


def pixel_size_of_current(values, field="the pixel size field"):
    """Pixel size in um from the dialog field (key ``pixel``), else from the current stack's
    calibration, else None; an implausible size is refused naming where it came from
    (``bridge_logic.check_pixel_size``)."""
    size = bridge_logic.check_pixel_size(values.get("pixel"), field)
    if size is not None:
        return size
    if values.get("capture") != CAPTURE_CURRENT:
        return None
    imp = WindowManager.getCurrentImage()
    if imp is None:
        return None
    cal = imp.getCalibration()
    unit = (cal.getUnit() or "").lower()
    factor = {"micron": 1.0, u"\u00b5m": 1.0, "um": 1.0, "mm": 1000.0, "nm": 0.001}.get(unit)
    if factor is None or not cal.scaled():
        return None
    return bridge_logic.check_pixel_size(
        cal.pixelWidth * factor, "the calibration of '%s' (Image > Properties; or type the size "
        "into %s)" % (imp.getTitle(), field))


def point_selection():
    """Return the (x, y) pixel points of the current image's point selection, or of the point
    ROIs in the ROI Manager; [] when there are none."""
    points = []
    imp = WindowManager.getCurrentImage()
    if imp is not None:
        roi = imp.getRoi()
        if roi is not None and roi.getType() == Roi.POINT:
            poly = roi.getFloatPolygon()
            for i in range(poly.npoints):
                points.append((poly.xpoints[i], poly.ypoints[i]))
    if points:
        return points
    manager = RoiManager.getInstance()
    if manager is not None:
        for roi in manager.getRoisAsArray():
            if roi.getType() == Roi.POINT:
                poly = roi.getFloatPolygon()
                for i in range(poly.npoints):
                    points.append((poly.xpoints[i], poly.ypoints[i]))
    return points


def write_points(points, request_dir):
    """Write points as ``points.csv`` (x_px, y_px) in the request folder and return its path."""
    path = os.path.join(request_dir, "points.csv")
    fh = open(path, "w")
    try:
        fh.write(bridge_logic.points_csv_text(points))
    finally:
        fh.close()
    return path


def area_rois():
    """Return the area ROIs (not points, not lines) of the ROI Manager, in its order, leaving
    out the ROIs uvps added itself (protrusion outlines, sphere circles)."""
    manager = RoiManager.getInstance()
    if manager is None:
        return []
    return [roi for roi in manager.getRoisAsArray()
            if roi.isArea() and not bridge_logic.added_by_uvps(roi.getName())]


def write_label_image(rois, width, height, path):
    """Fill ROI i (1-based, later ROIs on top) into a 16-bit label image and save it as TIFF."""
    if len(rois) > 65535:
        raise BridgeError("too many areas (%d); at most 65535" % len(rois))
    ip = ShortProcessor(width, height)
    for i, roi in enumerate(rois):
        ip.setValue(i + 1)
        ip.fill(roi)
    imp = ImagePlus("regions_labels", ip)
    if not FileSaver(imp).saveAsTiff(path):
        raise BridgeError("cannot write the label image %s" % path)
    return path
