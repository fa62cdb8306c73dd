"""GenericDialog helpers that remember values and are macro-recordable (Jython 2.7).

A field's macro key is the first word of its label, lower-cased (ImageJ's ``Macro.trimKey``), so
every label here starts with a unique, stable word: ``Degree of the drop-off fit`` is ``degree=4``
in a macro. Values are remembered in ``ij.Prefs`` under ``uvps.<key>`` (shared by all menu items:
the run folder chosen once is offered everywhere) and saved only when a user clicked OK, so a
batch macro does not change the user's defaults; a key a macro leaves out takes the built-in
default, not the remembered value, so a macro is reproducible.
"""
from ij import IJ, Macro, Prefs
from ij.gui import GenericDialog

PREFIX = "uvps."

#: Choices of the ``capture`` field.
CAPTURE_CURRENT = "Current stack"
CAPTURE_FILES = "Folder or files"
CAPTURE_CHOICES = [CAPTURE_CURRENT, CAPTURE_FILES]


def macro_key(label):
    """Return ImageJ's macro key of a label (first word, up to ':', lower-cased)."""
    key = label.split(" ")[0].split(":")[0]
    return key.lower()


class UVPSDialog(object):
    """A GenericDialog whose fields are read back into a dict keyed by macro key.

    Example
    -------
    >>> dlg = UVPSDialog("Estimate Lights")
    >>> dlg.number("Degree of the drop-off fit", 4, decimals=0)
    >>> values = dlg.show()          # None when cancelled
    >>> values["degree"]
    """

    def __init__(self, title):
        self.title = title
        self.gd = GenericDialog("uvps: " + title)
        self.fields = []

    def _remember(self, label, kind, default):
        key = macro_key(label)
        for k, _ in self.fields:
            if k == key:
                raise ValueError("two fields of dialog '%s' share the macro key '%s'"
                                 % (self.title, key))
        self.fields.append((key, kind))
        if Macro.getOptions() is not None:
            # A macro gets the built-in defaults for keys it leaves out, not the user's last
            # values, so the same macro gives the same result on every machine.
            return default if default is not None else ""
        pref = PREFIX + key
        if kind == "number":
            return Prefs.get(pref, float(default))
        if kind == "checkbox":
            # Jython resolves Prefs.get(String, bool) to the double overload: keep text.
            return Prefs.get(pref, "true" if default else "false") == "true"
        return Prefs.get(pref, default if default is not None else "")

    def number(self, label, default, decimals=2, units=None):
        value = self._remember(label, "number", default)
        if units:
            self.gd.addNumericField(label, value, decimals, 8, units)
        else:
            self.gd.addNumericField(label, value, decimals)

    def string(self, label, default="", columns=40):
        self.gd.addStringField(label, self._remember(label, "string", default), columns)

    def directory(self, label, default=""):
        self.gd.addDirectoryField(label, self._remember(label, "string", default), 40)

    def file(self, label, default=""):
        self.gd.addFileField(label, self._remember(label, "string", default), 40)

    def choice(self, label, items, default):
        value = self._remember(label, "choice", default)
        if value not in items:
            value = default
        self.gd.addChoice(label, list(items), value)

    def checkbox(self, label, default):
        self.gd.addCheckbox(label, self._remember(label, "checkbox", default))

    def message(self, text):
        self.gd.addMessage(text)

    def help(self, text):
        self.gd.addHelp(text)

    def show(self):
        """Show the dialog (or read the macro options); return the values, None if cancelled."""
        self.gd.showDialog()
        if self.gd.wasCanceled():
            return None
        values = {}
        for key, kind in self.fields:
            if kind == "number":
                values[key] = self.gd.getNextNumber()
            elif kind == "checkbox":
                values[key] = self.gd.getNextBoolean()
            elif kind == "choice":
                values[key] = self.gd.getNextChoice()
            else:
                values[key] = self.gd.getNextString().strip()
        if self.gd.invalidNumber():
            raise ValueError("a number field of '%s' holds no number" % self.title)
        if Macro.getOptions() is None:
            for key, kind in self.fields:
                value = values[key]
                if kind == "checkbox":
                    value = "true" if value else "false"
                Prefs.set(PREFIX + key, value)
        return values


def add_capture_fields(dlg, with_pixel_size=True):
    """Fields that say where the capture comes from: keys capture, images, pixel."""
    dlg.choice("Capture source", CAPTURE_CHOICES, CAPTURE_CURRENT)
    dlg.string("Images (folder, multi-page TIFF, or files separated by ;)", "")
    if with_pixel_size:
        dlg.number("Pixel size (0 = from the TIFF tags)", 0.0, decimals=3, units=u"\u00b5m")


def add_run_field(dlg):
    """The run folder (key ``run``), shared by every menu item."""
    dlg.directory("Run folder (outputs)", "")


def add_light_fields(dlg):
    """Optional known lights, mask, dark frame, drop-off degree: keys lights, mask, dark, degree."""
    dlg.file("Lights file (.lp or positions; empty = estimate)", "")
    dlg.file("Mask image (optional)", "")
    dlg.file("Dark frame (optional)", "")
    dlg.number("Degree of the Legendre drop-off fit", 4, decimals=0)


def number_or_none(value):
    """0 (or less) means "not set" for optional numbers such as the pixel size."""
    if value is None or value != value or value <= 0:
        return None
    return float(value)


def log_values(title, values):
    """Write the values used to the Log (what ran, for the record)."""
    parts = ["%s=%s" % (k, values[k]) for k in sorted(values)]
    IJ.log("uvps %s: %s" % (title, " ".join(parts)))
