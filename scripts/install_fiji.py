#!/usr/bin/env python3
"""Install (or remove) the uvps plugins in a Fiji or ImageJ 1.x folder.

Layout written (the plugin scripts rely on it):

- menu: ``<root>/plugins/UV_Photometric_Stereo.jar`` holding only a ``plugins.config`` that lists
  Plugins > UV Photometric Stereo in workflow order (:data:`MENU_ORDER`, with separators; ImageJ
  sorts the ``.py`` files of a plugins folder alphabetically, but keeps a ``plugins.config``'s
  order), each item ``ij.plugin.Macro_Runner("<script>")``; the scripts in
  ``<root>/plugins/jars/uvps_menu/UV_Photometric_Stereo/*.py`` (depth 3: not scanned into menus
  of their own);
- Jython library, Fiji: ``<root>/jars/Lib/uvps_fiji/`` (Fiji puts ``jars/Lib`` on Jython's path);
- Jython library, plain ImageJ 1.x: ``<root>/plugins/jars/Lib/uvps_fiji/`` (ImageJ turns every
  ``.py`` at depth <= 2 under ``plugins/`` into a menu command, so helpers must live at depth >= 3);
- ``<lib>/uvps_fiji/uvps_fiji.cfg``: ``python = /abs/path/to/python``, the CPython that has uvps
  installed (read by ``uvps_fiji.bridge_logic.read_config``);
- ``<lib>/uvps_fiji/commands.json``: the core's command declarations, the output of
  ``<python> -m uvps spec`` (names, parameters, defaults, choices, help); the dialogs and requests
  of the Fiji side are built from it (``uvps_fiji.bridge_logic.load_spec``).

- plain ImageJ 1.x only: ``<root>/plugins/jars/uvps_jython_interpreter.jar``, the ``Jython``
  interpreter class that ImageJ 1.x needs to run ``.py`` menu items (compiled here from
  ``jython_lib/uvps_fiji/imagej1/Jython.java`` with ``javac``), and a copy of ``jython.jar``
  (Debian: ``apt install jython``). Without them plain ImageJ offers to download Jython in a modal
  dialog, which hangs offline and in ``-batch`` runs. Fiji ships Jython: nothing is added.
  When ``javac`` or a ``jython.jar`` is missing, the installer says what to install (one line)
  and installs the rest.

Each menu script adds ``IJ.getDirectory("imagej") + "jars/Lib"`` and
``IJ.getDirectory("plugins") + "jars/Lib"`` to ``sys.path`` before importing ``uvps_fiji``.

Usage::

    python scripts/install_fiji.py /path/to/Fiji.app [--python /path/to/python]
    python scripts/install_fiji.py /path/to/Fiji.app --uninstall
    python scripts/install_fiji.py /path/to/ImageJ [--jython-jar /usr/share/java/jython.jar]

Pure CPython standard library, so that it runs before anything else is set up.
"""
import argparse
import json
import os
import shutil
import subprocess
import sys
import tempfile
import zipfile

MENU_FOLDER = "UV_Photometric_Stereo"
MENU_NAME = "UV Photometric Stereo"
#: Where the menu scripts go, relative to ``plugins/`` (see the module docstring).
MENU_SCRIPTS = os.path.join("jars", "uvps_menu", MENU_FOLDER)
#: The jar whose plugins.config makes the menu.
MENU_JAR = MENU_FOLDER + ".jar"
#: The menu in workflow order ("-": a separator); scripts not listed come before the settings.
MENU_ORDER = ["Calibrate_Lamps", "Run_Whole_Pipeline", "-",
              "Estimate_Lights", "Flat_Field", "Normals_and_Albedo", "Integrate_Height", "-",
              "Colour_Areas", "Detect_Protrusions", "Wand_Count", "Compare_Counts",
              "Statistics_and_Report", "-",
              "Relight", "Compare_Captures", "Element_Maps", "Stitch_Painting", "Run_Info", "-",
              "UVPS_Settings"]
PACKAGE = "uvps_fiji"
CONFIG_NAME = "uvps_fiji.cfg"
SPEC_NAME = "commands.json"
REPO_ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
#: The interpreter jar written into plain ImageJ's plugins/jars/ (with jython.jar beside it).
INTERPRETER_JAR = "uvps_jython_interpreter.jar"
JYTHON_COPY = "jython.jar"
DEBIAN_JARS = {"jython": "/usr/share/java/jython.jar", "ij": "/usr/share/java/ij.jar"}
INTERPRETER_HINT = ("plain ImageJ needs a Jython interpreter to run the .py menu items: install a "
                    "JDK and Jython (Debian: apt install default-jdk-headless jython) and run this "
                    "installer again, or (online) put Jython.jar from "
                    "https://imagej.net/ij/plugins/jython/ into %s")


class InstallError(Exception):
    """A one-line reason why installing cannot go on."""


def is_fiji(root):
    """Return True when ``root`` looks like ``Fiji.app``: ``jars/`` plus a launcher
    (``ImageJ-*``, or ``fiji-*`` since 2025), a macOS ``Contents/`` folder or ``jars/ij-*.jar``."""
    jars = os.path.join(root, "jars")
    if not os.path.isdir(jars):
        return False
    if os.path.isdir(os.path.join(root, "Contents")):
        return True
    if any(name.startswith(("ImageJ-", "fiji-")) for name in os.listdir(root)):
        return True
    return any(name.startswith("ij-") and name.endswith(".jar") for name in os.listdir(jars))


def library_dir(root):
    """Return the folder that receives ``uvps_fiji/`` for this installation."""
    if is_fiji(root):
        return os.path.join(root, "jars", "Lib")
    return os.path.join(root, "plugins", "jars", "Lib")


def check_root(root):
    if not os.path.isdir(os.path.join(root, "plugins")):
        raise InstallError("%s is not a Fiji or ImageJ folder: expected a plugins/ folder in it"
                           % root)


def check_python(python):
    """Return the uvps version that ``python`` imports, or raise InstallError."""
    try:
        proc = subprocess.run(
            [python, "-c", "import uvps, sys; sys.stdout.write(uvps.__version__)"],
            stdout=subprocess.PIPE, stderr=subprocess.PIPE, universal_newlines=True, timeout=120)
    except OSError as exc:
        raise InstallError("--python %s cannot be run: %s" % (python, exc))
    if proc.returncode != 0:
        last = (proc.stderr.strip().splitlines() or ["exit status %d" % proc.returncode])[-1]
        raise InstallError("--python %s cannot import uvps (%s); install uvps into it first "
                           "(pip install /path/to/uvps) or pass --python" % (python, last))
    return proc.stdout.strip()


def command_table(python):
    """Return the JSON text of ``python -m uvps spec`` (checked), or raise InstallError."""
    try:
        proc = subprocess.run([python, "-m", "uvps", "spec"], stdout=subprocess.PIPE,
                              stderr=subprocess.PIPE, universal_newlines=True, timeout=120)
    except OSError as exc:
        raise InstallError("--python %s cannot be run: %s" % (python, exc))
    last = (proc.stderr.strip().splitlines() or ["exit status %d" % proc.returncode])[-1]
    if proc.returncode != 0:
        raise InstallError("%s -m uvps spec failed (%s); this uvps is too old for these plugins"
                           % (python, last))
    try:
        table = json.loads(proc.stdout)
    except ValueError as exc:
        raise InstallError("%s -m uvps spec printed no JSON (%s)" % (python, exc))
    if not isinstance(table, dict) or table.get("schema_version") != 1 \
            or not isinstance(table.get("commands"), dict):
        raise InstallError("%s -m uvps spec printed an unknown command table (schema_version %r)"
                           % (python, table.get("schema_version") if isinstance(table, dict)
                              else None))
    return json.dumps(table, indent=1, sort_keys=True) + "\n"


def source_files(source_root):
    """Return (menu scripts, library folder) found under ``source_root``."""
    menu_dir = os.path.join(source_root, "plugins", MENU_FOLDER)
    lib_dir = os.path.join(source_root, "jython_lib", PACKAGE)
    scripts = sorted(name for name in os.listdir(menu_dir) if name.endswith(".py")) \
        if os.path.isdir(menu_dir) else []
    if not scripts:
        raise InstallError("no menu scripts (*.py) in %s" % menu_dir)
    if not os.path.isfile(os.path.join(lib_dir, "__init__.py")):
        raise InstallError("no Jython library in %s (expected __init__.py)" % lib_dir)
    return [os.path.join(menu_dir, name) for name in scripts], lib_dir


def menu_order(script_names):
    """The menu's items (script stems) and separators ("-"): :data:`MENU_ORDER`, with the scripts
    it does not list as one group before the last one."""
    stems = [os.path.splitext(name)[0] for name in script_names]
    order = list(MENU_ORDER)
    extra = sorted(stem for stem in stems if stem not in order)
    if extra:
        order[-1:-1] = extra + ["-"]
    return [item for item in order if item == "-" or item in stems]


def menu_items(menu_folder):
    """The titles of the menu scripts in ``menu_folder``, in the installed menu's order."""
    names = [p for p in os.listdir(str(menu_folder)) if p.endswith(".py")]
    return [stem.replace("_", " ") for stem in menu_order(names) if stem != "-"]


#: Menu items that run no command of the core: what the Fiji index says of them.
NON_COMMAND_ITEMS = {"UVPS Settings": "choose and check the CPython"}
#: The markers of the generated menu table in ``docs/fiji/index.md``.
INDEX_BEGIN = "<!-- menu table: generated by scripts/fiji_index.py from the command declarations -->"
INDEX_END = "<!-- end of the generated menu table -->"


def fiji_index_table(commands, menu_folder, docs_folder):
    """The menu table of ``docs/fiji/index.md``: every menu item in the installed order, with its page
    (``docs/fiji/<Item>.md``, else the command's reference), its command's help and the command.

    ``commands``: the ``commands`` table of ``python -m uvps spec``.
    """
    by_menu = dict((c.get("menu"), name) for name, c in commands.items() if c.get("menu"))
    rows = ["| menu item | what | bridge command |", "|---|---|---|"]
    for title in menu_items(menu_folder):
        page = title.replace(" ", "_") + ".md"
        link = page if os.path.isfile(os.path.join(str(docs_folder), page)) else None
        name = by_menu.get(title)
        if name is None:
            rows.append("| [%s](%s) | %s | - |" % (title, link or "", NON_COMMAND_ITEMS.get(title, "")))
        else:
            what = commands[name]["help"].replace("<", "&lt;").replace(">", "&gt;")
            rows.append("| [%s](%s) | %s | `%s` |" % (title, link or "../commands.md#uvps-" + name, what, name))
    return "\n".join(rows) + "\n"


def menu_config(script_names):
    """The ``plugins.config`` text of the menu: the scripts (file names) in :func:`menu_order`,
    separators only between groups."""
    stems = [os.path.splitext(name)[0] for name in script_names]
    order = menu_order(script_names)
    lines, group = [], []
    for item in order + ["-"]:
        if item != "-":
            if item in stems:
                group.append(item)
            continue
        if group:
            if lines:
                lines.append('Plugins>%s, "-"' % MENU_NAME)
            for stem in group:
                path = "/".join(MENU_SCRIPTS.split(os.sep) + [stem + ".py"])
                lines.append('Plugins>%s, "%s", ij.plugin.Macro_Runner("%s")'
                             % (MENU_NAME, stem.replace("_", " "), path))
            group = []
    return "\n".join(lines) + "\n"


def write_menu_jar(path, config):
    """Write the jar holding ``plugins.config`` (atomically: a half-written jar breaks ImageJ's
    menus)."""
    tmp = path + ".part"
    with zipfile.ZipFile(tmp, "w") as jar:
        jar.writestr("plugins.config", config)
    os.replace(tmp, path)


def _replace_dir(target, fill):
    """Build the new folder beside ``target`` with ``fill(tmp)``, then swap it in."""
    parent = os.path.dirname(target)
    if not os.path.isdir(parent):
        os.makedirs(parent)
    tmp = tempfile.mkdtemp(prefix="." + os.path.basename(target) + ".", dir=parent)
    try:
        fill(tmp)
        if os.path.isdir(target):
            shutil.rmtree(target)
        os.rename(tmp, target)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    os.chmod(target, 0o755)


def install(root, python, source_root=REPO_ROOT):
    """Copy the menu scripts and the library into ``root`` and write the config.

    Returns
    -------
    list of str
        The folders written.
    """
    root = os.path.abspath(root)
    check_root(root)
    scripts, lib_src = source_files(source_root)
    version = check_python(python)
    spec = command_table(python)
    menu_target = os.path.join(root, "plugins", MENU_SCRIPTS)
    lib_target = os.path.join(library_dir(root), PACKAGE)
    # an older install's scripts at plugins/UV_Photometric_Stereo/ would be a second menu
    old_menu = os.path.join(root, "plugins", MENU_FOLDER)
    if os.path.isdir(old_menu):
        shutil.rmtree(old_menu)

    def fill_menu(tmp):
        for path in scripts:
            shutil.copy2(path, tmp)

    def fill_lib(tmp):
        shutil.copytree(lib_src, tmp, dirs_exist_ok=True, ignore=shutil.ignore_patterns(
            "*$py.class", "*.pyc", "__pycache__", CONFIG_NAME, SPEC_NAME, "imagej1"))
        with open(os.path.join(tmp, CONFIG_NAME), "w") as fh:
            fh.write("# written by scripts/install_fiji.py; the CPython that runs the uvps core\n")
            fh.write("python = %s\n" % python)
            fh.write("uvps_version = %s\n" % version)
        with open(os.path.join(tmp, SPEC_NAME), "w") as fh:
            fh.write(spec)

    _replace_dir(menu_target, fill_menu)
    _replace_dir(lib_target, fill_lib)
    jar = os.path.join(root, "plugins", MENU_JAR)
    write_menu_jar(jar, menu_config([os.path.basename(p) for p in scripts]))
    return [menu_target, lib_target, jar]


def _has_class(jar, name):
    try:
        with zipfile.ZipFile(jar) as zf:
            return name in zf.namelist()
    except (OSError, zipfile.BadZipFile):
        return False


def _jars(folder):
    if not os.path.isdir(folder):
        return []
    return sorted(os.path.join(folder, n) for n in os.listdir(folder) if n.endswith(".jar"))


def find_jar(root, kind, given=None):
    """The ``jython`` or ``ij`` jar: ``given``, else one in the ImageJ folder, else Debian's."""
    if given:
        if not os.path.isfile(given):
            raise InstallError("--%s-jar %s does not exist" % (kind, given))
        return os.path.abspath(given)
    folders = [os.path.join(root, "plugins", "jars"), os.path.join(root, "jars"), root]
    for folder in folders:
        for jar in _jars(folder):
            name = os.path.basename(jar).lower()
            if name.startswith(kind) and name != INTERPRETER_JAR:
                if kind == "ij" and not _has_class(jar, "ij/ImageJ.class"):
                    continue
                if kind == "jython" and not _has_class(jar, "org/python/util/PythonInterpreter.class"):
                    continue
                return jar
    return DEBIAN_JARS[kind] if os.path.isfile(DEBIAN_JARS[kind]) else None


def interpreter_present(root):
    """Whether plain ImageJ in ``root`` already has a ``Jython`` plugin class (a downloaded
    Jython.jar, or ours)."""
    for folder in (os.path.join(root, "plugins"), os.path.join(root, "plugins", "jars")):
        for jar in _jars(folder):
            if os.path.basename(jar) != INTERPRETER_JAR and _has_class(jar, "Jython.class"):
                return jar
    return None


def install_interpreter(root, source_root=REPO_ROOT, jython_jar=None, ij_jar=None, javac=None):
    """Give plain ImageJ 1.x in ``root`` the ``Jython`` class that runs ``.py`` menu items.

    Returns
    -------
    (list of str, str)
        The files written and a one-line note for the user (what was done, or what to install).
    """
    plugins_jars = os.path.join(root, "plugins", "jars")
    present = interpreter_present(root)
    if present:
        return [], "Jython interpreter already present: %s" % present
    jython = find_jar(root, "jython", jython_jar)
    ij = find_jar(root, "ij", ij_jar)
    javac = javac or shutil.which("javac")
    missing = [what for what, have in (("javac", javac), ("jython.jar", jython), ("ij.jar", ij))
               if not have]
    if missing:
        return [], "not found: %s; %s" % (", ".join(missing), INTERPRETER_HINT % plugins_jars)
    source = os.path.join(source_root, "jython_lib", PACKAGE, "imagej1", "Jython.java")
    if not os.path.isfile(source):
        return [], "no %s; %s" % (source, INTERPRETER_HINT % plugins_jars)
    build = tempfile.mkdtemp(prefix="uvps-jython-")
    try:
        base = [javac, "-nowarn", "-encoding", "UTF-8", "-d", build,
                "-cp", os.pathsep.join([ij, jython])]
        proc = None
        for release in (["--release", "8"], []):
            proc = subprocess.run(base + release + [source], stdout=subprocess.PIPE,
                                  stderr=subprocess.STDOUT, universal_newlines=True, timeout=300)
            if proc.returncode == 0:
                break
        if proc.returncode != 0:
            raise InstallError("javac failed on %s: %s" % (source, proc.stdout.strip()[-500:]))
        if not os.path.isdir(plugins_jars):
            os.makedirs(plugins_jars)
        written = []
        target = os.path.join(plugins_jars, INTERPRETER_JAR)
        with zipfile.ZipFile(target + ".part", "w", zipfile.ZIP_DEFLATED) as zf:
            for name in sorted(os.listdir(build)):
                zf.write(os.path.join(build, name), name)
        os.replace(target + ".part", target)
        written.append(target)
        if os.path.dirname(os.path.abspath(jython)) != os.path.abspath(plugins_jars):
            copy = os.path.join(plugins_jars, JYTHON_COPY)
            shutil.copyfile(jython, copy + ".part")
            os.replace(copy + ".part", copy)
            written.append(copy)
    finally:
        shutil.rmtree(build, ignore_errors=True)
    return written, "Jython interpreter for plain ImageJ installed (jython from %s)" % jython


def uninstall(root):
    """Remove what ``install`` wrote (both library locations). Returns the folders removed."""
    root = os.path.abspath(root)
    check_root(root)
    removed = []
    for path in (os.path.join(root, "plugins", MENU_FOLDER),
                 os.path.join(root, "plugins", os.path.dirname(MENU_SCRIPTS)),
                 os.path.join(root, "jars", "Lib", PACKAGE),
                 os.path.join(root, "plugins", "jars", "Lib", PACKAGE)):
        if os.path.isdir(path):
            shutil.rmtree(path)
            removed.append(path)
    jar = os.path.join(root, "plugins", MENU_JAR)
    if os.path.isfile(jar):
        os.remove(jar)
        removed.append(jar)
    interpreter = os.path.join(root, "plugins", "jars", INTERPRETER_JAR)
    if os.path.isfile(interpreter):
        # the jython.jar copy came with it (a Jython.jar the user put there is left alone)
        for path in (interpreter, os.path.join(root, "plugins", "jars", JYTHON_COPY)):
            if os.path.isfile(path):
                os.remove(path)
                removed.append(path)
    return removed


def main(argv=None):
    parser = argparse.ArgumentParser(
        description="Install the uvps menu commands into Fiji or ImageJ 1.x.")
    parser.add_argument("root", help="the Fiji.app or ImageJ folder (the one holding plugins/)")
    parser.add_argument("--python", default=sys.executable,
                        help="CPython with uvps installed (default: this interpreter, %(default)s)")
    parser.add_argument("--uninstall", action="store_true",
                        help="remove the uvps menu commands and library instead")
    parser.add_argument("--jython-jar", help="plain ImageJ: the jython.jar to use (default: one "
                        "in the ImageJ folder, else %s)" % DEBIAN_JARS["jython"])
    parser.add_argument("--ij-jar", help="plain ImageJ: the ij.jar to compile against (default: "
                        "the ImageJ folder's, else %s)" % DEBIAN_JARS["ij"])
    parser.add_argument("--no-interpreter", action="store_true",
                        help="plain ImageJ: do not install the Jython interpreter")
    parser.add_argument("--source-root", default=REPO_ROOT, help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    try:
        if args.uninstall:
            removed = uninstall(args.root)
            for path in removed:
                print("removed %s" % path)
            if not removed:
                print("nothing to remove in %s" % os.path.abspath(args.root))
        else:
            # A bare name is looked up on PATH now: ImageJ may start with a different PATH.
            # abspath, not realpath: a venv's python is a symlink that must stay one.
            python = args.python if os.sep in args.python else (
                shutil.which(args.python) or args.python)
            python = os.path.abspath(python)
            for path in install(args.root, python, source_root=args.source_root):
                print("installed %s" % path)
            root = os.path.abspath(args.root)
            if is_fiji(root):
                print("Fiji ships Jython: no interpreter needed")
            elif not args.no_interpreter:
                written, note = install_interpreter(root, args.source_root, args.jython_jar,
                                                    args.ij_jar)
                for path in written:
                    print("installed %s" % path)
                print(note)
            print("uvps core runs with %s; restart Fiji/ImageJ to see "
                  "Plugins > UV Photometric Stereo" % python)
    except (InstallError, OSError) as exc:
        print("install_fiji.py: error: %s" % exc, file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
