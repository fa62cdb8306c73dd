"""Run one uvps bridge command from ImageJ/Fiji (Jython 2.7).

The core runs as a separate CPython process started with ``java.lang.ProcessBuilder`` from an
argument list (no shell). Its ``PROGRESS`` lines go to ImageJ's status and progress bars, Esc
cancels (the process is destroyed), a timeout ends it, and the result counts only when the exit
status is 0, ``response.json`` says ``ok`` and every listed output exists (see
``bridge_logic.finish_call``).

Errors: :func:`report_error` writes the message to the Log, CLI flags in it turned into the
dialog's field names; when a user clicked the menu item it also shows it in an ``IJ.error``
dialog; when a macro (or ``ImageJ -batch``) ran the command it aborts the macro (``-batch`` then
exits with status 1). Only under the test harness (``-Duvps.test``) does it raise
:class:`PluginError` (the harness turns it into status 4): elsewhere an exception would put
Jython's and Java's stack traces in the Log for what is a user's mistake.
"""
import os
import threading
import time

from java.awt import GraphicsEnvironment
from java.io import BufferedReader, File, InputStreamReader
from java.lang import ProcessBuilder, System, Throwable
from java.util.concurrent import TimeUnit

from ij import IJ, Macro, Prefs
from ij.macro import Interpreter

from uvps_fiji import bridge_logic
from uvps_fiji.bridge_logic import BridgeError

#: ij.Prefs key of the CPython chosen in the Settings menu item.
PYTHON_PREF = "uvps.python"

#: Default timeout of one call, in seconds (a whole 12-megapixel run takes minutes).
DEFAULT_TIMEOUT_S = 4 * 3600


class PluginError(Exception):
    """Raised at the end of a failed menu command run from a macro, so the macro fails."""


class Cancelled(Exception):
    """A dialog was cancelled: the menu item ends with "cancelled" (:func:`report_cancel`)."""


def python_command():
    """Return (python, source) following ``bridge_logic.find_python``'s order."""
    setting = Prefs.get(PYTHON_PREF, "")
    config_path = bridge_logic.default_config_path()
    return bridge_logic.find_python(setting, None, config_path)


def command_table():
    """The core's command table (``commands.json`` beside the library, else asked once from the
    configured CPython with ``python -m uvps spec``); see ``bridge_logic.load_spec``."""
    return bridge_logic.load_spec(
        python=python_command()[0],
        run=lambda args: run_process(args, timeout_s=120, on_line=None))


#: Request folders made for the menu command now running (deleted at its end, see call).
_PENDING = []


def new_request_dir():
    """A fresh request folder for one call; :func:`call` (or :func:`run_menu` if the call never
    happens) deletes it once the response has been read."""
    path = bridge_logic.make_request_dir()
    _PENDING.append(path)
    return path


def remove_request_dir(path, failed):
    """Delete ``path``; a failed call keeps it when ``UVPS_KEEP_FAILED_REQUESTS=1`` (or
    ``keep_failed_requests = true`` in uvps_fiji.cfg), and the Log says where it is."""
    if path in _PENDING:
        _PENDING.remove(path)
    keep = failed and bridge_logic.keep_failed_requests()
    if bridge_logic.remove_request_dir(path, failed=failed, keep_failed=keep):
        IJ.log("uvps: request folder kept for inspection: " + path)


def remove_pending_request_dirs():
    """Delete the request folders of calls that never ran (an error before the call, e.g. a
    stack refused by ``bridge_logic.stack_layout``)."""
    for path in list(_PENDING):
        remove_request_dir(path, failed=True)


def is_interactive():
    """True when a user clicked the menu item (no macro running, no batch mode, a display)."""
    if GraphicsEnvironment.isHeadless():
        return False
    if Macro.getOptions() is not None:
        return False
    if Interpreter.isBatchMode() or Interpreter.getInstance() is not None:
        return False
    if System.getProperty("uvps.test") is not None:
        return False
    return True


class _LineReader(threading.Thread):
    """Read a child's stream line by line on its own thread (so the pipe never fills up)."""

    def __init__(self, stream, on_line=None):
        threading.Thread.__init__(self)
        self.daemon = True
        self.reader = BufferedReader(InputStreamReader(stream, "UTF-8"))
        self.on_line = on_line
        self.lines = []

    def run(self):
        while True:
            line = self.reader.readLine()
            if line is None:
                break
            line = unicode(line)  # noqa: F821 (Jython)
            self.lines.append(line)
            if self.on_line is not None:
                try:
                    self.on_line(line)
                except (Exception, Throwable):  # a display problem must not stop the reading
                    pass

    def text(self):
        return u"\n".join(self.lines)


def _show_progress(line):
    parsed = bridge_logic.parse_progress(line)
    if parsed is None:
        return
    fraction, message = parsed
    IJ.showStatus("uvps: " + message)
    IJ.showProgress(fraction)


def _stop(process):
    """End the core: SIGTERM first (it removes its temporary output and answers within its 2 s
    grace), SIGKILL after 5 s. ImageJ may stop this thread again while it waits (a second Esc, or
    the macro's abort: ThreadDeath); then the core is killed at once before that propagates, so
    it never outlives the menu item."""
    process.destroy()
    try:
        if not process.waitFor(5, TimeUnit.SECONDS):
            process.destroyForcibly()
            process.waitFor()
    except (Exception, Throwable):
        process.destroyForcibly()
        raise


def run_process(args, timeout_s=DEFAULT_TIMEOUT_S, on_line=_show_progress, cwd=None):
    """Run ``args`` and return (exit_code, stdout_text, stderr_text).

    Esc cancels; a timeout ends the process. Both raise BridgeError (types ``Cancelled`` and
    ``Timeout``) after the process is destroyed.
    """
    builder = ProcessBuilder(args)
    if cwd:
        builder.directory(File(cwd))
    env = builder.environment()
    env.put("PYTHONUNBUFFERED", "1")
    env.put("PYTHONIOENCODING", "utf-8")
    try:
        process = builder.start()
    except (Exception, Throwable) as exc:  # java.io.IOException: the python was not found
        raise BridgeError("cannot start %s (%s); choose the CPython with uvps installed in "
                          "Plugins > UV Photometric Stereo > UVPS Settings" % (args[0], exc),
                          error_type="Configuration")
    process.getOutputStream().close()
    out = _LineReader(process.getInputStream(), on_line)
    err = _LineReader(process.getErrorStream())
    out.start()
    err.start()
    IJ.resetEscape()
    start = time.time()
    stop = None
    try:
        while not process.waitFor(200, TimeUnit.MILLISECONDS):
            if IJ.escapePressed():
                stop = BridgeError("cancelled with Esc; the core was stopped",
                                   error_type="Cancelled")
            elif timeout_s and time.time() - start > timeout_s:
                stop = BridgeError("the core did not finish within %d s and was stopped"
                                   % timeout_s, error_type="Timeout")
            if stop is not None:
                break
    finally:
        # also when ImageJ stops this thread (Esc in a macro: ThreadDeath): the core never
        # outlives the menu item
        if process.isAlive():
            _stop(process)
    out.join(10)
    err.join(10)
    IJ.showProgress(1.0)
    if stop is not None:
        IJ.resetEscape()
        stop.log = err.text()
        raise stop
    return process.exitValue(), out.text(), err.text()


def call(command, inputs=None, params=None, output_dir=None, request_dir=None,
         timeout_s=DEFAULT_TIMEOUT_S, python=None):
    """Run one bridge command and return its validated :class:`bridge_logic.Response`.

    Parameters
    ----------
    command : str
        A command of the table in docs/architecture.md.
    inputs, params : dict
    output_dir : str
        The run folder (absolute).
    request_dir : str, optional
        An existing request folder (from :func:`new_request_dir`, when the caller already wrote
        inputs into it); a fresh one is made otherwise. It is deleted once the response has been
        read (see :func:`remove_request_dir`).
    timeout_s : float
    python : str, optional
        Overrides the configured CPython.

    Raises
    ------
    BridgeError
        For every failure; its message is the core's own ``error.message`` when it sent one.
    """
    if request_dir is None:
        request_dir = new_request_dir()
    failed = True
    try:
        command_table()
        request = bridge_logic.build_request(command, inputs, params, output_dir)
        request_path = bridge_logic.write_request(request, request_dir)
        if python is None:
            python = python_command()[0]
        args = bridge_logic.build_command(python, request_path)
        IJ.log("uvps: " + bridge_logic.format_command(args))
        IJ.showStatus("uvps: %s..." % command)
        # The core runs in the request folder, never in ImageJ's (arbitrary) working folder.
        exit_code, _, stderr = run_process(args, timeout_s=timeout_s, cwd=request_dir)
        response = bridge_logic.finish_call(exit_code, request_path, command=command,
                                            stderr=stderr)
        failed = False
    finally:
        remove_request_dir(request_dir, failed)
    done = "uvps: %s done; core %.2f s" % (command, response.elapsed_s or 0.0)
    IJ.showStatus(done)
    IJ.log(done)
    return response


def menu_words(title, message):
    """A core message in the menu user's words: CLI flags become the dialog fields of the menu
    item ``title`` (``bridge_logic.user_words``); unchanged when the table cannot be read."""
    try:
        table = command_table()
        commands = dict((v, k) for k, v in bridge_logic.menu_titles(table).items())
        return bridge_logic.user_words(message, commands.get(title), table)
    except (Exception, Throwable):  # the message matters more than its wording
        return message


def is_cancel(exc):
    """Whether ``exc`` is a user's cancel, not a failure: Esc during a bridge call (BridgeError
    ``Cancelled``), ImageJ stopping the macro thread (ThreadDeath, an interrupt) or a macro's
    abort (ImageJ's RuntimeException "Macro canceled", thrown e.g. by a cancelled dialog)."""
    from java.lang import InterruptedException, ThreadDeath
    if isinstance(exc, BridgeError):
        return exc.error_type == "Cancelled"
    if isinstance(exc, (ThreadDeath, InterruptedException)):
        return True
    message = exc.getMessage() if isinstance(exc, Throwable) else str(exc)
    return bool(message) and Macro.MACRO_CANCELED in message


def shows_dialogs():
    """Whether a person sees ImageJ's windows (a display, ImageJ's main window, no batch mode,
    not the test harness): then an error is shown in a dialog, also when a macro ran the item."""
    return not GraphicsEnvironment.isHeadless() and IJ.getInstance() is not None \
        and not Interpreter.isBatchMode() and System.getProperty("uvps.test") is None


def report_cancel(title, how="cancelled"):
    """A cancel: one Log line and the status bar say "cancelled" (no dialog, no trace); the
    calling macro stops, as ImageJ's own commands do on Cancel."""
    line = "uvps %s: %s" % (title, how)
    IJ.log(line)
    IJ.showStatus("uvps: %s cancelled" % title)
    IJ.showProgress(1.0)
    _stop_macro("uvps: %s cancelled" % title)


def _stop_macro(status=None):
    """Stop the macro that ran the menu item, if any (ImageJ would run its next line); the
    status bar then says ``status`` again (ImageJ writes "Macro aborted" once the macro ends)."""
    if Interpreter.getInstance() is None:
        return
    try:
        Interpreter.abort()
    except (Exception, Throwable):  # ImageJ signals the abort with "Macro canceled"
        pass
    if status:
        IJ.showStatus(status)   # after the abort, which wrote "Macro aborted"


def ask_or_cancel(window_title, question, yes, no, cancelled):
    """Ask ``question`` in a modal window with the buttons ``yes`` and ``no`` (and Cancel): any
    answer but ``yes`` raises the Cancelled BridgeError ``cancelled`` (the Log's line, which starts
    with "cancelled" and says what stays unchanged): nothing is written."""
    from java.awt import Frame
    from ij.gui import YesNoCancelDialog
    dialog = YesNoCancelDialog(IJ.getInstance() or Frame(), window_title, question, yes, no)
    if not dialog.yesPressed():
        raise BridgeError(cancelled, error_type="Cancelled")


def show_error_dialog(title, message):
    """One modal message (ImageJ's MessageDialog: unlike IJ.error it does not abort the macro
    itself, which put "Macro canceled" and a stack trace in the Log after OK)."""
    from ij.gui import MessageDialog
    MessageDialog(IJ.getInstance(), "uvps: " + title, message)


#: Error types that are a user's mistake: one Log line, the core's log left out.
USER_ERRORS = ("UVPSInputError", "MacroOptions", "Configuration", "Timeout")


def report_error(title, exc):
    """Show a failure: Log always; a dialog when interactive; abort + raise in a macro.

    Parameters
    ----------
    title : str
        The menu item's name.
    exc : Exception
        A BridgeError (its ``message`` and ``log`` are used) or any other exception.
    """
    if is_cancel(exc):
        how = "cancelled"
        if isinstance(exc, BridgeError):
            # its message says why: "cancelled with Esc; the core was stopped"
            how = exc.message if exc.message.startswith("cancelled") else "cancelled (%s)" % exc.message
        report_cancel(title, how)
        return
    if isinstance(exc, BridgeError):
        message = menu_words(title, exc.message)
        kind = exc.error_type
        log = exc.log
    else:
        message = (exc.getMessage() if isinstance(exc, Throwable) else str(exc)) \
            or exc.__class__.__name__
        kind = exc.__class__.__name__
        log = ""
    line = "uvps %s failed (%s): %s" % (title, kind, message)
    IJ.log(line)
    if log and log.strip() and kind not in USER_ERRORS:
        # the core's log helps with an unexpected failure; a user's mistake is the line above
        IJ.log("uvps core log:\n" + log.strip())
    System.err.println(line)
    IJ.showStatus("uvps: " + title + " failed")
    IJ.showProgress(1.0)
    interactive = is_interactive()
    if shows_dialogs():
        show_error_dialog(title, message)
    # Stop the calling macro: without this, ImageJ would run its next line after a Python
    # exception in a menu command (tried with ImageJ 1.53t -batch).
    _stop_macro("uvps: " + title + " failed")
    if not interactive and System.getProperty("uvps.test") is None and IJ.getInstance() is None \
            and bridge_logic.exit_on_failure(System.getProperty("sun.java.command")):
        # Plain `ImageJ -batch` exits 0 after an aborted macro: end it with a failure status so a
        # script can tell (an interactive session or PyImageJ is never ended; the test harness
        # has its own status, see tests/imagej/README.md). System.exit skips run_menu's
        # `finally`: the request folders go first.
        remove_pending_request_dirs()
        System.out.flush()
        System.exit(bridge_logic.FAILURE_EXIT_STATUS)
    if not interactive and System.getProperty("uvps.test") is not None:
        # The test harness turns this into a non-zero status. Elsewhere the message above is
        # all a user sees: an exception would add Jython's and Java's stack traces to the Log
        # for what is a user's mistake (the macro is already aborted).
        raise PluginError(line)


def run_menu(title, func):
    """Run a menu script's body ``func()``; failures go through :func:`report_error`.

    Request folders made for calls that never ran (an error before the call) are deleted."""
    try:
        return func()
    except PluginError:
        raise
    except Cancelled:
        report_cancel(title)
    except BridgeError as exc:
        report_error(title, exc)
    except (Exception, Throwable) as exc:  # Java exceptions are not Python Exceptions
        report_error(title, exc)
    finally:
        remove_pending_request_dirs()


def check_python(python):
    """Return (ok, text): whether ``python`` imports uvps, with its version or the error."""
    args = bridge_logic.build_check_command(python)
    try:
        code, out, err = run_process(args, timeout_s=120, on_line=None)
    except BridgeError as exc:
        return False, exc.message
    if code != 0:
        return False, "%s cannot import uvps: %s" % (python, bridge_logic.last_line(err))
    return True, "%s has uvps %s" % (python, out.strip())

