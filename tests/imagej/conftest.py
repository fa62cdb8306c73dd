"""Fixtures that run the real ImageJ 1.x (Debian's ij.jar + jython.jar) under a private Xvfb.

See tests/imagej/README.md. In short: one Xvfb and one compilation of ``java/*.java`` (into
pytest's temp folder) per session; a fresh ImageJ folder per test, filled by
``scripts/install_fiji.py`` (the real installer); one fresh JVM per macro (``UvpsTestLauncher ...
-batch macro.ijm``), killed with its process group on timeout. A modal dialog halts the JVM with
status 3, an uncaught Python exception with status 4.
"""
import dataclasses
import os
import re
import shutil
import signal
import subprocess
import sys
from pathlib import Path
from typing import List

import pytest

from xvfb_display import XvfbError, start_xvfb, stop_xvfb

HERE = Path(__file__).resolve().parent
REPO = HERE.parent.parent
#: The test launcher, and the Jython interpreter class that install_fiji.py installs in plain ImageJ.
JAVA_SOURCES = sorted((HERE / "java").glob("*.java")) + [
    REPO / "jython_lib" / "uvps_fiji" / "imagej1" / "Jython.java"]
DEPS_SCRIPT = REPO / "scripts" / "install_imagej_deps.sh"
INSTALLER = REPO / "scripts" / "install_fiji.py"
IJ_JAR = Path(os.environ.get("UVPS_IJ_JAR", "/usr/share/java/ij.jar"))
JYTHON_JAR = Path(os.environ.get("UVPS_JYTHON_JAR", "/usr/share/java/jython.jar"))

#: JVM exit status when a modal dialog opened (UvpsTestLauncher.DIALOG_STATUS).
DIALOG_STATUS = 3
#: JVM exit status for an uncaught Python exception in a plugin (Jython.PYTHON_EXCEPTION_STATUS).
PYTHON_EXCEPTION_STATUS = 4

_SCREENSHOT_RE = re.compile(r"^UVPS-SCREENSHOT: (/.*\.png)$", re.MULTILINE)


@dataclasses.dataclass
class ImageJEnv:
    """What a session needs to start ImageJ: the JVM, its classpath and the X display."""

    java: str
    classpath: str
    display: str


@dataclasses.dataclass
class MacroResult:
    """Outcome of one ``run_macro`` call.

    ``log_text`` is ImageJ's Log: in ``-batch`` mode there is no Log window and ImageJ writes
    ``print``/``IJ.log`` (and ``showMessage``/``IJ.error`` outside a macro) to stdout, where
    Python ``print`` also goes, so it equals ``stdout``.
    """

    returncode: int
    stdout: str
    stderr: str
    log_text: str
    screenshots: List[Path] = dataclasses.field(default_factory=list)

    def check(self):
        """Raise AssertionError with the whole output unless ImageJ exited with status 0."""
        if self.returncode != 0:
            raise AssertionError("ImageJ exited with status %d\n--- stdout ---\n%s\n"
                                 "--- stderr ---\n%s"
                                 % (self.returncode, self.stdout, self.stderr))
        return self


def _missing_tools():
    missing = [str(p) for p in (IJ_JAR, JYTHON_JAR) if not p.is_file()]
    missing += [tool for tool in ("java", "javac", "Xvfb") if shutil.which(tool) is None]
    return missing


def _in_ci():
    return os.environ.get("CI", "").lower() in ("1", "true", "yes")


def _unavailable(reason):
    """Fail in CI (these tests must run there), skip elsewhere."""
    if _in_ci():
        pytest.fail("ImageJ tests cannot run in CI: %s" % reason, pytrace=False)
    pytest.skip(reason)


def _ensure_tools():
    missing = _missing_tools()
    if not missing:
        return
    may_install = (os.geteuid() == 0 or os.environ.get("UVPS_INSTALL_DEPS") == "1"
                   or _in_ci())
    if not may_install:
        _unavailable("ImageJ harness needs %s; run scripts/install_imagej_deps.sh as root or set "
                     "UVPS_INSTALL_DEPS=1" % ", ".join(missing))
    proc = subprocess.run(["sh", str(DEPS_SCRIPT)], stdout=subprocess.PIPE,
                          stderr=subprocess.STDOUT, universal_newlines=True, timeout=1200)
    missing = _missing_tools()
    if missing:
        _unavailable("installing the ImageJ dependencies failed (missing %s): %s"
                     % (", ".join(missing), proc.stdout.strip()[-2000:]))


def _compile(build_dir):
    classpath = os.pathsep.join([str(IJ_JAR), str(JYTHON_JAR)])
    proc = subprocess.run(["javac", "-nowarn", "-encoding", "UTF-8", "-d", str(build_dir),
                           "-cp", classpath] + [str(p) for p in JAVA_SOURCES],
                          stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                          universal_newlines=True, timeout=300)
    if proc.returncode != 0:
        pytest.fail("javac failed for tests/imagej/java:\n%s" % proc.stdout, pytrace=False)


@pytest.fixture(scope="session")
def imagej_env(tmp_path_factory):
    """Dependencies checked (installed when allowed), Java helpers compiled, Xvfb running."""
    _ensure_tools()
    # Classes go to this session's private temp folder, not into the working tree: several
    # pytest sessions may run at once in a shared checkout, and javac rewriting class files
    # while another session's JVM loads them would make both flaky.
    build_dir = tmp_path_factory.mktemp("ij_classes")
    _compile(build_dir)
    try:
        xvfb, display = start_xvfb(str(tmp_path_factory.mktemp("xvfb") / "xvfb.log"))
    except XvfbError as exc:
        pytest.fail(str(exc), pytrace=False)
    classpath = os.pathsep.join([str(IJ_JAR), str(JYTHON_JAR), str(build_dir)])
    try:
        yield ImageJEnv(java=shutil.which("java"), classpath=classpath, display=display)
    finally:
        stop_xvfb(xvfb)


def make_imagej_home(path):
    """Create an empty ImageJ 1.x folder (``plugins/``) at ``path`` and return it, absolute."""
    path = Path(path).resolve()
    (path / "plugins").mkdir(parents=True, exist_ok=True)
    return path


@pytest.fixture
def bare_imagej_home(tmp_path):
    """A fresh ImageJ folder with an empty ``plugins/`` (nothing installed)."""
    return make_imagej_home(tmp_path / "ImageJ_bare")


@pytest.fixture
def imagej_home(tmp_path):
    """A fresh ImageJ folder with uvps installed by ``scripts/install_fiji.py`` (this python)."""
    home = make_imagej_home(tmp_path / "ImageJ")
    # The interpreter class is on the harness's classpath (test_install_fiji tests installing it).
    proc = subprocess.run([sys.executable, str(INSTALLER), str(home), "--python", sys.executable,
                           "--no-interpreter"],
                          stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                          universal_newlines=True, timeout=300)
    if proc.returncode != 0:
        pytest.fail("scripts/install_fiji.py failed:\n%s" % proc.stdout, pytrace=False)
    return home


@pytest.fixture
def run_macro(imagej_env, tmp_path, request):
    """Return ``run_macro(macro_text, *, timeout=120, home=None, arg="", screenshot_dir=None,
    plain=False, env=None, props=None)``.

    Runs ``macro_text`` in a fresh ImageJ JVM (``-batch``) and returns a MacroResult. ``home``
    defaults to this test's ``imagej_home`` (uvps installed). With ``screenshot_dir`` every dialog
    is saved there as ``<title>.png`` and confirmed with OK instead of halting the JVM. On
    timeout the whole process group is killed and the test fails. ``plain=True`` runs ImageJ as
    a user would (main class ``ij.ImageJ``, no ``-Duvps.test``: no dialog guard, no status 4);
    ``env`` adds environment variables, ``props`` Java system properties (e.g.
    ``{"uvps.screenshot.button": "No"}``: the button that answers a dialog).
    """
    counter = [0]
    user_home = tmp_path / "user_home"
    user_home.mkdir(exist_ok=True)

    def _run(macro_text, *, timeout=120, home=None, arg="", screenshot_dir=None,
             plain=False, env=None, props=None):
        if home is None:
            home = request.getfixturevalue("imagej_home")
        counter[0] += 1
        macro = tmp_path / ("macro_%d.ijm" % counter[0])
        macro.write_text(macro_text, encoding="utf-8")
        cmd = [imagej_env.java] + ([] if plain else ["-Duvps.test=1"])
        cmd.append("-Duser.home=%s" % user_home)
        if screenshot_dir is not None:
            cmd.append("-Duvps.screenshot.dir=%s" % Path(screenshot_dir).resolve())
        cmd += ["-D%s=%s" % kv for kv in sorted((props or {}).items())]
        cmd += ["-cp", imagej_env.classpath, "ij.ImageJ" if plain else "UvpsTestLauncher",
                "-ijpath", str(Path(home).resolve()), "-batch", str(macro), arg]
        env = dict(os.environ, DISPLAY=imagej_env.display, **(env or {}))
        proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                                env=env, cwd=str(tmp_path), start_new_session=True,
                                universal_newlines=True)
        try:
            stdout, stderr = proc.communicate(timeout=timeout)
        except subprocess.TimeoutExpired:
            os.killpg(proc.pid, signal.SIGKILL)
            stdout, stderr = proc.communicate()
            pytest.fail("ImageJ did not finish within %s s (killed)\n--- macro ---\n%s\n"
                        "--- stdout ---\n%s\n--- stderr ---\n%s"
                        % (timeout, macro_text, stdout, stderr), pytrace=False)
        shots = [Path(p) for p in _SCREENSHOT_RE.findall(stderr)]
        return MacroResult(returncode=proc.returncode, stdout=stdout, stderr=stderr,
                           log_text=stdout, screenshots=shots)

    return _run


@pytest.fixture
def write_plugin():
    """Return ``write_plugin(home, menu_path, source) -> Path``: write a Jython menu script
    ``<home>/plugins/<menu_path>`` (e.g. ``"Test/Say_Hi.py"`` -> Plugins > Test > Say Hi). ImageJ
    scans ``plugins/`` when it starts, so write before ``run_macro``. Sources must be ASCII."""

    def _write(home, menu_path, source):
        path = Path(home) / "plugins" / menu_path
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(source, encoding="ascii")
        return path

    return _write
