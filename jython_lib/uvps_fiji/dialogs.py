"""GenericDialog helpers that remember values and are macro-recordable (Jython 2.7).

A field's macro key is the first word of its label, lower-cased (ImageJ's ``Macro.trimKey``), so
every label here starts with a unique, stable word: ``Degree of the drop-off fit`` is ``degree=4``
in a macro. Values are remembered in ``ij.Prefs`` under ``uvps.<key>`` (shared by all menu items:
the run folder chosen once is offered everywhere) and saved only when a user clicked OK, so a
batch macro does not change the user's defaults; a key a macro leaves out takes the built-in
default, not the remembered value, so a macro is reproducible.
"""
import os

from java.lang import Throwable

from ij import Macro, Prefs
from ij.gui import GenericDialog

from uvps_fiji import bridge_logic, runner
from uvps_fiji.bridge_logic import BridgeError

PREFIX = "uvps."

#: Where the menu items' pages are (the Help button names the page of its item).
DOCS_URL = "docs/fiji/index.md"


def doc_page(title):
    """The page of a menu item in the uvps folder: ``docs/fiji/Estimate_Lights.md``."""
    return "docs/fiji/%s.md" % title.replace(" ", "_")


def doc_help(title, doc):
    """The Help text of a menu item from its script's docstring: the paragraphs before the
    ``Macro:`` example, then the example."""
    paragraphs = [" ".join(p.split()) for p in (doc or "").strip().split("\n\n") if p.strip()]
    body = ["<b>%s</b>" % _html(title)]
    for text in paragraphs:
        if text.startswith("Macro:"):
            body.append("<p>Macro: <tt>%s</tt></p>" % _html(text[len("Macro:"):].strip()))
        else:
            body.append("<p>%s</p>" % _html(text))
    return "".join(body)

#: Choices of the ``capture`` field.
CAPTURE_CURRENT = "Current stack"
CAPTURE_FILES = "Folder or files"
CAPTURE_CHOICES = [CAPTURE_CURRENT, CAPTURE_FILES]


macro_key = bridge_logic.macro_key

#: Fields that name one run's own files (a colour-area label image): remembered together with
#: the run folder they were chosen for and offered again only with that run folder, so that a
#: new run never silently uses another run's regions_labels.tif.
RUN_OWN_KEYS = ("regions", "label")

#: The run folder is remembered with the capture whose outputs went into it (``uvps.run.capture``,
#: and ``uvps.run.capture.for``: that run folder): a dialog with capture fields whose run folder is
#: left as remembered while the capture is another one asks before writing into it
#: (:meth:`UVPSDialog._not_another_captures_run`).
CAPTURE_PREF = PREFIX + "run.capture"
#: The answers of that question.
WRITE_INTO_IT, DO_NOT_WRITE = "Write into it", "Do not run"


class UVPSDialog(object):
    """A GenericDialog whose fields are read back into a dict keyed by macro key.

    Example
    -------
    >>> dlg = UVPSDialog("Estimate Lights")
    >>> dlg.number("Degree of the drop-off fit", 4, decimals=0)
    >>> values = dlg.show()          # None when cancelled
    >>> values["degree"]
    """

    def __init__(self, title, doc=None):
        self.title = title
        self.gd = GenericDialog("uvps: " + title)
        self.fields = []
        self.help_text = doc_help(title, doc) if doc else ""
        self.field_help = []
        self.defaults = {}

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
        self.defaults[key] = default
        if key in RUN_OWN_KEYS and Prefs.get(pref + ".run", "") != Prefs.get(PREFIX + "run", ""):
            return default if default is not None else ""
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
        """Text shown by the dialog's Help button, above the fields' own help."""
        self.help_text = text

    def describe(self, label, text):
        """One field's help (from the core's declaration), listed by the Help button."""
        if text:
            self.field_help.append((label, text))

    def _add_help(self):
        body = self.help_text or "<b>%s</b>" % _html(self.title)
        if body.startswith("<html>"):
            body = body[len("<html>"):]
        if body.endswith("</html>"):
            body = body[:-len("</html>")]
        items = "".join("<li><b>%s</b>: %s</li>" % (_html(label), _html(text))
                        for label, text in self.field_help)
        self.gd.addHelp("<html>%s%s<p>More: <tt>%s</tt> in the uvps folder (%s).</p></html>"
                        % (body, "<ul>%s</ul>" % items if items else "", doc_page(self.title),
                           DOCS_URL))

    def check_macro_keys(self):
        """A macro key this dialog does not have is an error naming it and the valid keys (a
        misspelt key would otherwise be ignored and its default used)."""
        options = Macro.getOptions()
        if options is None:
            return
        keys = [k for k, _ in self.fields]
        unknown = bridge_logic.unknown_macro_keys(options, keys)
        if unknown:
            raise BridgeError(bridge_logic.unknown_keys_message(self.title, unknown, keys),
                              error_type="MacroOptions")

    def show(self):
        """Show the dialog (or read the macro options); return the values, None if cancelled."""
        self.check_macro_keys()
        self._add_help()
        self.gd.showDialog()
        try:
            cancelled = self.gd.wasCanceled()
        except (Exception, Throwable) as exc:
            # in a macro ImageJ aborts it on Cancel by throwing "Macro canceled"
            if not runner.is_cancel(exc):
                raise
            cancelled = True
        if cancelled:
            raise runner.Cancelled(self.title)
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
            self._not_another_runs(values)
            capture = self._not_another_captures_run(values)
            if capture is not None:
                Prefs.set(CAPTURE_PREF, capture)
                Prefs.set(CAPTURE_PREF + ".for", values.get("run") or "")
            for key, kind in self.fields:
                value = values[key]
                if kind == "checkbox":
                    value = "true" if value else "false"
                Prefs.set(PREFIX + key, value)
                if key in RUN_OWN_KEYS:
                    Prefs.set(PREFIX + key + ".run", values.get("run") or "")
        return values

    def _not_another_runs(self, values):
        """A run's own file (``RUN_OWN_KEYS``) left as remembered while the run folder was
        changed in the dialog is not carried over: the field's default is used and the Log says
        so (choosing the file again in the dialog uses it)."""
        from ij import IJ
        run = (values.get("run") or "").strip()
        for key in RUN_OWN_KEYS:
            value = values.get(key)
            if key not in values or not value or value == "auto" or not run:
                continue
            was_for = Prefs.get(PREFIX + key + ".run", "")
            if value == Prefs.get(PREFIX + key, "") and was_for and \
                    os.path.normpath(was_for) != os.path.normpath(run):
                default = self.defaults.get(key)
                values[key] = default if default is not None else ""
                IJ.log("uvps %s: %s was chosen for the run folder %s, not %s: not used (%s "
                       "instead; choose it again to use it)"
                       % (self.title, value, was_for, run, values[key] or "none"))

    def _not_another_captures_run(self, values):
        """A run folder left as remembered while the capture is another one than the capture whose
        outputs went into it: asked (one question naming the folder and both captures) before this
        capture's outputs are written there, unless the folder is empty or absent. *Do not run* (or
        closing the question) cancels: nothing is written. Returns the capture of a dialog with
        capture fields (to be remembered with its run folder), else None."""
        if "capture" not in values or "run" not in values:
            return None
        capture = capture_identity(values)
        run = (values.get("run") or "").strip()
        was = Prefs.get(CAPTURE_PREF, "")
        was_for = Prefs.get(CAPTURE_PREF + ".for", "")
        left_as_remembered = run and run == Prefs.get(PREFIX + "run", "")
        if not (capture and was and left_as_remembered and was_for
                and os.path.normpath(was_for) == os.path.normpath(run) and was != capture
                and _holds_files(run)):
            return capture
        question = ("The run folder %s holds the outputs of %s, not of %s: write %s's outputs into it "
                    "(%s), or choose another run folder (%s)?"
                    % (run, was, capture, capture, WRITE_INTO_IT, DO_NOT_WRITE))
        runner.ask_or_cancel("uvps: %s: another capture's run folder" % self.title, question,
                             WRITE_INTO_IT, DO_NOT_WRITE,
                             "cancelled: the run folder %s holds the outputs of %s, not of %s; nothing "
                             "was written: choose another run folder" % (run, was, capture))
        return capture


def capture_identity(values):
    """What a capture dialog's capture is, in words: its folder or files (key ``images``), or the
    open stack's title (``Current stack``); "" when unknown."""
    if values.get("capture") == CAPTURE_FILES:
        images = (values.get("images") or "").strip()
        return os.path.normpath(images) if images else ""
    try:
        from ij import WindowManager
        imp = WindowManager.getCurrentImage()
        title = imp.getTitle() if imp is not None else None
    except (Exception, Throwable):
        return ""
    return "the open stack '%s'" % title if isinstance(title, bridge_logic.STRING_TYPES) and title else ""


def _holds_files(folder):
    """Whether ``folder`` exists and holds anything besides hidden entries."""
    try:
        return any(not n.startswith(".") for n in os.listdir(folder))
    except OSError:
        return False


def _html(text):
    return text.replace("&", "&amp;").replace("<", "&lt;").replace(">", "&gt;")


def spec_param(command, name):
    """The core's declaration of ``command``'s parameter ``name`` (``uvps spec``)."""
    return bridge_logic.param_spec(command, name, runner.command_table())


def add_param(dlg, param, key=None, label=None, default=None, decimals=None):
    """Add the field of a declared parameter: label, default, choices, unit and help all come
    from the core's declaration (``bridge_logic.dialog_field``).

    Parameters
    ----------
    dlg : UVPSDialog
    param : dict or (str, str)
        A parameter of the command table, or ``(command, name)``.
    key : str, optional
        The macro key the field must have (macros rely on it): a ValueError if the declared
        label's first word gives another one.
    label, default, decimals : optional
        See ``bridge_logic.dialog_field`` (``default`` only where the core declares none).
    """
    if isinstance(param, tuple):
        param = spec_param(*param)
    field = bridge_logic.dialog_field(param, label=label, default=default, decimals=decimals)
    if key is not None and field["key"] != key:
        raise ValueError("the label '%s' of parameter %s gives the macro key '%s'; macros use '%s'"
                         % (field["label"], param["name"], field["key"], key))
    kind = field["kind"]
    if kind == "checkbox":
        dlg.checkbox(field["label"], field["default"])
    elif kind == "choice":
        dlg.choice(field["label"], field["items"], field["default"])
    elif kind == "number":
        dlg.number(field["label"], field["default"], decimals=field["decimals"],
                   units=field["units"])
    elif kind == "file":
        dlg.file(field["label"], field["default"])
    elif kind == "directory":
        dlg.directory(field["label"], field["default"])
    else:
        dlg.string(field["label"], field["default"])
    dlg.describe(field["label"], field["help"])
    return field


def add_capture_fields(dlg, command):
    """Fields that say where the capture comes from: keys capture, images, channels, pixel."""
    dlg.choice("Capture source", CAPTURE_CHOICES, CAPTURE_CURRENT)
    dlg.describe("Capture source", "the open image stack (one image per lamp; an RGB stack, a "
                 "composite of 3 channels or a grey stack), or the images on disk")
    add_param(dlg, (command, "images"), key="images")
    dlg.choice("Channels per lamp (current stack)", bridge_logic.CHANNEL_CHOICES,
               bridge_logic.CHANNELS_AUTO)
    dlg.describe("Channels per lamp (current stack)",
                 "Automatic: an RGB image or a 3-channel composite is colour, a grey stack is one "
                 "slice per lamp unless a lights file lists a third as many lamps. 3: a grey stack "
                 "from File > Import > Image Sequence of RGB files holds R, G, B of each lamp")
    add_param(dlg, (command, "pixel_size_um"), key="pixel", decimals=3)


def add_run_field(dlg):
    """The run folder (key ``run``), shared by every menu item."""
    dlg.directory("Run folder (outputs)", "")
    dlg.describe("Run folder (outputs)", "the folder of this capture's results; every menu item "
                 "reads the earlier steps' files from it and writes its own there")


def add_light_fields(dlg, command, lights=True):
    """Optional known lights, mask, dark frame, drop-off degree: keys lights, mask, dark, degree."""
    if lights:
        add_param(dlg, (command, "lights"), key="lights")
    add_param(dlg, (command, "mask"), key="mask")
    add_param(dlg, (command, "dark"), key="dark")
    add_param(dlg, (command, "degree"), key="degree")


def add_composite_fields(dlg, defaults=bridge_logic.COMPOSITE_DEFAULT):
    """Element Maps' composite: the elements shown in red, green and blue (keys red, green, blue;
    display only, the core is not asked); lead in red by default."""
    for colour, default in zip(("Red", "Green", "Blue"), defaults):
        label = "%s element (composite)" % colour
        dlg.string(label, default, columns=8)
        dlg.describe(label, "an element (Pb takes the map Pb_L) or a map's name; auto: the next "
                     "map of the stack")
