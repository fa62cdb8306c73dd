"""A user's ImageJ session under Xvfb and a window manager: shared by the real-ImageJ GUI tests
(test_gui_session.py) and scripts/fiji_screenshots.py. Standard library only.

``-batch`` hides what a user meets (no Log window, no error dialogs, no window placement). Here
ImageJ starts normally (``UvpsMacroQueue``, java/UvpsMacroQueue.java) on a private Xvfb with
openbox; :meth:`GuiSession.run` drops a macro into the queue folder as *Plugins > Macros > Run*
would run it, and answers the dialogs it opens with xdotool (Return = OK, Escape = Cancel), as a
user does. :meth:`GuiSession.log` reads the Log window, :meth:`GuiSession.windows` the open
windows, :meth:`GuiSession.screenshot` saves the screen (xwd + ImageMagick).
"""
import os
import shutil
import signal
import subprocess
import time
from pathlib import Path

from xvfb_display import start_xvfb, stop_xvfb

#: Debian packages the session needs beyond the batch harness's (scripts/install_imagej_deps.sh).
GUI_TOOLS = ("openbox", "xdotool", "xwd", "convert")


def missing_gui_tools():
    return [t for t in GUI_TOOLS if shutil.which(t) is None]


class GuiSession:
    """ImageJ with its windows, driven by queued macros; use as a context manager.

    Parameters
    ----------
    java, classpath : str
        The JVM and a classpath holding ij.jar, jython.jar and the compiled java/ classes.
    home : Path
        An ImageJ folder with uvps installed (``-ijpath``).
    work : Path
        A scratch folder (queue, user home, logs).
    screen : str
        Xvfb's screen, ``WIDTHxHEIGHTxDEPTH``.
    """

    def __init__(self, java, classpath, home, work, screen="1600x1000x24", env=None):
        self.java, self.classpath, self.home = java, classpath, Path(home).resolve()
        self.work = Path(work).resolve()
        self.screen = screen
        self.env_extra = env or {}
        self.queue = self.work / "queue"
        self.counter = 0
        self.xvfb = self.wm = self.ij = None
        self.display = None

    # -- start / stop ---------------------------------------------------------------------------
    def __enter__(self):
        self.queue.mkdir(parents=True, exist_ok=True)
        (self.work / "user_home").mkdir(exist_ok=True)
        self.xvfb, self.display = start_xvfb(str(self.work / "xvfb.log"), screen=self.screen)
        self.env = dict(os.environ, DISPLAY=self.display, **self.env_extra)
        self.wm = subprocess.Popen(["openbox"], env=self.env, stdout=subprocess.DEVNULL,
                                   stderr=subprocess.DEVNULL, start_new_session=True)
        time.sleep(0.5)
        self.ij_out = open(self.work / "imagej.out", "w")
        self.ij = subprocess.Popen(
            [self.java, "-Duser.home=%s" % (self.work / "user_home"),
             "-Duvps.queue.dir=%s" % self.queue, "-cp", self.classpath, "UvpsMacroQueue",
             "-ijpath", str(self.home)],
            env=self.env, stdout=self.ij_out, stderr=subprocess.STDOUT, cwd=str(self.work),
            start_new_session=True)
        # ImageJ is up when a first queued step has run
        self.run('print("uvps gui session");', timeout=120)
        return self

    def __exit__(self, *exc):
        for proc in (self.ij, self.wm):
            if proc is not None and proc.poll() is None:
                os.killpg(proc.pid, signal.SIGKILL)
                proc.wait()
        if getattr(self, "ij_out", None):
            self.ij_out.close()
        if self.xvfb is not None:
            stop_xvfb(self.xvfb)

    def output(self):
        """ImageJ's standard output and error so far (Java and Jython print there)."""
        return (self.work / "imagej.out").read_text(errors="replace")

    # -- steps ----------------------------------------------------------------------------------
    def run(self, macro, answers=(), timeout=300):
        """Run ``macro`` as Plugins > Macros > Run does and wait until it is over.

        ``answers``: ``(title_regex, key)`` pairs, in order; each waits for a visible window whose
        title matches (e.g. ``"^uvps: Run Info$"``) and presses ``key`` in it (``"Return"``: OK,
        ``"Escape"``: Cancel). Returns the list of the answered windows' titles. Fails (an
        AssertionError) when a dialog does not come or the step does not end in ``timeout`` s.
        """
        done = self.queue_step(macro)
        deadline = time.monotonic() + timeout
        answered = []
        for pattern, key in answers:
            wid = self.wait_window(pattern, deadline)
            answered.append(self.window_name(wid))
            self.press(wid, key)
        while not done.exists():
            if self.ij.poll() is not None:
                raise AssertionError("ImageJ ended (status %s):\n%s" % (self.ij.returncode,
                                                                      self.output()[-3000:]))
            if time.monotonic() > deadline:
                raise AssertionError("step %s did not end within %s s; windows: %s\n%s"
                                     % (name, timeout, self.visible_windows(), macro))
            time.sleep(0.1)
        return answered

    def queue_step(self, macro):
        """Drop ``macro`` into the queue (written whole, then renamed: the queue never reads half a
        file) and return the path of the ``.done`` file that appears when the step is over."""
        self.counter += 1
        name = "%04d" % self.counter
        tmp = self.queue / (name + ".tmp")
        tmp.write_text(macro, encoding="utf-8")
        tmp.rename(self.queue / (name + ".ijm"))
        return self.queue / (name + ".done")

    def press(self, wid, key, tries=3):
        """Activate window ``wid`` and press ``key`` (XTEST, as a keyboard does: Java ignores
        synthetic events sent to a window) until the window is gone. A key goes to whatever window
        has the focus: it is pressed again only while ``wid`` is still there, after waiting long
        enough for a loaded machine, else a slow close would answer the next dialog too."""
        for _ in range(tries):
            time.sleep(0.5)
            if not self._visible(wid):
                return
            self._xdotool("windowactivate", "--sync", wid)
            self._xdotool("key", "--clearmodifiers", key)
            end = time.monotonic() + 15
            while time.monotonic() < end:
                if not self._visible(wid):
                    return
                time.sleep(0.2)
        raise AssertionError("window %s did not close on %s" % (self.window_name(wid), key))

    def _visible(self, wid):
        return wid in self._xdotool("search", "--onlyvisible", "--name", ".").stdout.split()

    def _xdotool(self, *args):
        return subprocess.run(["xdotool"] + [str(a) for a in args], env=self.env,
                              stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                              universal_newlines=True, timeout=30)

    def wait_window(self, pattern, deadline):
        """The id of the first visible window whose title matches ``pattern`` (a regex)."""
        while time.monotonic() < deadline:
            out = self._xdotool("search", "--onlyvisible", "--name", pattern).stdout.split()
            if out:
                return out[0]
            if self.ij.poll() is not None:
                raise AssertionError("ImageJ ended while waiting for '%s'" % pattern)
            time.sleep(0.2)
        raise AssertionError("no window '%s' came; visible: %s\nImageJ output:\n%s"
                             % (pattern, self.visible_windows(), self.output()[-3000:]))

    def window_name(self, wid):
        return self._xdotool("getwindowname", wid).stdout.strip()

    def visible_windows(self):
        """Titles of the visible top-level windows (X's view: what a user sees)."""
        ids = self._xdotool("search", "--onlyvisible", "--name", ".").stdout.split()
        return [self.window_name(w) for w in ids]

    def window_geometry(self, pattern):
        """``(x, y, width, height)`` of the visible window whose title matches ``pattern``."""
        wid = self.wait_window(pattern, time.monotonic() + 10)
        out = self._xdotool("getwindowgeometry", "--shell", wid).stdout
        vals = dict(line.split("=", 1) for line in out.split() if "=" in line)
        return int(vals["X"]), int(vals["Y"]), int(vals["WIDTH"]), int(vals["HEIGHT"])

    # -- what a user sees -----------------------------------------------------------------------
    def log(self):
        """The Log window's text."""
        path = self.work / ("log_%d.txt" % (self.counter + 1))
        self.run('File.saveString(getInfo("log"), "%s");' % path)
        return path.read_text(errors="replace")

    def clear_log(self):
        self.run('print("\\\\Clear");')

    def windows(self):
        """ImageJ's open windows (images and non-image windows), by title."""
        path = self.work / ("windows_%d.txt" % (self.counter + 1))
        self.run('t = getList("image.titles"); w = getList("window.titles");\n'
                 's = ""; for (i = 0; i < t.length; i++) s = s + t[i] + "\\n";\n'
                 'for (i = 0; i < w.length; i++) s = s + w[i] + "\\n";\n'
                 'File.saveString(s, "%s");' % path)
        return [line for line in path.read_text().splitlines() if line]

    def status(self):
        """ImageJ's status bar text when the last step ended."""
        return (self.queue / ("%04d.done" % self.counter)).read_text(errors="replace")

    def screenshot(self, path, crop=None, scale=None):
        """Save the screen as PNG (``crop``: ImageMagick geometry ``WxH+X+Y``; ``scale``: e.g.
        ``"75%"``)."""
        raw = self.work / "screen.xwd"
        with open(raw, "wb") as fh:
            subprocess.run(["xwd", "-root", "-silent", "-display", self.display], stdout=fh,
                           check=True, timeout=60)
        cmd = ["convert", "xwd:%s" % raw]
        if crop:
            cmd += ["-crop", crop, "+repage"]
        if scale:
            cmd += ["-resize", scale]
        cmd += ["-strip", "-define", "png:compression-level=9", str(path)]
        subprocess.run(cmd, check=True, timeout=120)
        return Path(path)


TRACE_MARKERS = ("Traceback", "Exception", "at java.", "at org.python", "ThreadDeath")


def trace_lines(text):
    """The lines of ``text`` that belong to a stack trace (what a user must never see)."""
    return [line for line in text.splitlines() if any(m in line for m in TRACE_MARKERS)]


def move_window(session, pattern, x, y, width=None, height=None):
    """Move (and size) the visible window whose title matches ``pattern``, as a user drags it."""
    wid = session.wait_window(pattern, time.monotonic() + 10)
    session._xdotool("windowmove", wid, x, y)
    if width and height:
        session._xdotool("windowsize", wid, width, height)
