"""scripts/install_fiji.py run as users run it (a subprocess) on Fiji-like and ImageJ-like
folders in tmp_path, with a small source tree so the expected files are known exactly."""
import json
import subprocess
import sys
import zipfile
from pathlib import Path

import pytest

INSTALLER = Path(__file__).resolve().parent.parent / "scripts" / "install_fiji.py"


def run_installer(*args):
    return subprocess.run([sys.executable, str(INSTALLER)] + [str(a) for a in args],
                          stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                          universal_newlines=True, timeout=120)


@pytest.fixture
def source(tmp_path):
    root = tmp_path / "source"
    menu = root / "plugins" / "UV_Photometric_Stereo"
    lib = root / "jython_lib" / "uvps_fiji"
    menu.mkdir(parents=True)
    lib.mkdir(parents=True)
    (menu / "Run_Whole_Pipeline.py").write_text("print('run')\n")
    (menu / "UVPS_Settings.py").write_text("print('settings')\n")
    (menu / "notes.txt").write_text("not a script\n")
    (lib / "__init__.py").write_text("")
    (lib / "bridge_logic.py").write_text("X = 1\n")
    (lib / "bridge_logic$py.class").write_bytes(b"\xca\xfe")
    (lib / "uvps_fiji.cfg").write_text("python = /a/developer/python\n")
    (lib / "commands.json").write_text("{}\n")  # a developer's stale table: replaced
    (lib / "widgets").mkdir()
    (lib / "widgets" / "__init__.py").write_text("Y = 2\n")
    return root


def make_fiji(tmp_path, marker="ImageJ-linux64"):
    root = tmp_path / "Fiji.app"
    (root / "plugins").mkdir(parents=True)
    (root / "jars").mkdir()
    if marker == "Contents":
        (root / "Contents").mkdir()
    elif marker.endswith(".jar"):
        (root / "jars" / marker).write_text("")
    else:
        (root / marker).write_text("")
    return root


def read_cfg(path):
    lines = [ln for ln in path.read_text().splitlines() if ln and not ln.startswith("#")]
    return dict((k.strip(), v.strip()) for k, v in (ln.split("=", 1) for ln in lines))


@pytest.mark.parametrize("marker", ["ImageJ-linux64", "fiji-linux-x64", "Contents",
                                    "ij-1.54f.jar"])
def test_fiji_layout(tmp_path, source, marker):
    root = make_fiji(tmp_path, marker)
    proc = run_installer(root, "--source-root", source)
    assert proc.returncode == 0, proc.stderr
    menu = root / "plugins" / "jars" / "uvps_menu" / "UV_Photometric_Stereo"
    lib = root / "jars" / "Lib" / "uvps_fiji"
    assert sorted(p.name for p in menu.iterdir()) == ["Run_Whole_Pipeline.py", "UVPS_Settings.py"]
    assert not (root / "plugins" / "UV_Photometric_Stereo").exists()
    with zipfile.ZipFile(str(root / "plugins" / "UV_Photometric_Stereo.jar")) as jar:
        assert jar.read("plugins.config").decode() == (
            'Plugins>UV Photometric Stereo, "Run Whole Pipeline", ij.plugin.Macro_Runner('
            '"jars/uvps_menu/UV_Photometric_Stereo/Run_Whole_Pipeline.py")\n'
            'Plugins>UV Photometric Stereo, "-"\n'
            'Plugins>UV Photometric Stereo, "UVPS Settings", ij.plugin.Macro_Runner('
            '"jars/uvps_menu/UV_Photometric_Stereo/UVPS_Settings.py")\n')
    assert sorted(p.name for p in lib.iterdir()) == ["__init__.py", "bridge_logic.py",
                                                     "commands.json", "uvps_fiji.cfg", "widgets"]
    assert (lib / "widgets" / "__init__.py").read_text() == "Y = 2\n"
    cfg = read_cfg(lib / "uvps_fiji.cfg")
    assert cfg["python"] == sys.executable
    import uvps
    assert cfg["uvps_version"] == uvps.__version__
    assert sorted(p.name for p in (root / "plugins" / "jars").iterdir()) == ["uvps_menu"]


def test_the_command_table_is_the_cores_declarations(tmp_path, source):
    """commands.json beside the library is exactly what `<python> -m uvps spec` prints."""
    root = make_fiji(tmp_path)
    assert run_installer(root, "--source-root", source).returncode == 0
    table = json.loads((root / "jars" / "Lib" / "uvps_fiji" / "commands.json").read_text())
    spec = json.loads(subprocess.run([sys.executable, "-m", "uvps", "spec"], check=True,
                                     stdout=subprocess.PIPE, timeout=120).stdout)
    assert table == spec
    assert {"run", "info", "wand"} <= set(table["commands"])
    assert table["commands"]["run"]["params"][0]["name"] == "images"


def test_a_python_whose_uvps_has_no_spec_is_refused(tmp_path, source):
    root = make_fiji(tmp_path)
    fake = tmp_path / "old_python"
    fake.write_text("#!/bin/sh\ncase \"$*\" in *spec*) echo 'invalid choice: spec' >&2; exit 2;; "
                    "esac\nprintf 0.0.1\n")
    fake.chmod(0o755)
    proc = run_installer(root, "--python", fake, "--source-root", source)
    assert proc.returncode == 1
    assert "-m uvps spec failed (invalid choice: spec)" in proc.stderr
    assert not (root / "jars" / "Lib" / "uvps_fiji").exists()


def test_plain_imagej_layout_puts_library_at_depth_three(tmp_path, source):
    root = tmp_path / "ImageJ"
    (root / "plugins").mkdir(parents=True)
    (root / "jars").mkdir()  # jars/ without a launcher is not Fiji
    proc = run_installer(root, "--source-root", source)
    assert proc.returncode == 0, proc.stderr
    lib = root / "plugins" / "jars" / "Lib" / "uvps_fiji"
    assert (lib / "bridge_logic.py").read_text() == "X = 1\n"
    assert read_cfg(lib / "uvps_fiji.cfg")["python"] == sys.executable
    assert not (root / "jars" / "Lib").exists()


def test_reinstall_replaces_stale_files_and_uninstall_removes_all(tmp_path, source):
    root = make_fiji(tmp_path)
    assert run_installer(root, "--source-root", source).returncode == 0
    stale = root / "plugins" / "jars" / "uvps_menu" / "UV_Photometric_Stereo" / "Old_Command.py"
    stale.write_text("print('old')\n")
    # an older install's menu folder (scripts at depth 2, sorted by ImageJ) goes too
    older = root / "plugins" / "UV_Photometric_Stereo" / "Run_Whole_Pipeline.py"
    older.parent.mkdir()
    older.write_text("print('old')\n")
    (root / "plugins" / "Other_Plugin.py").write_text("print('not ours')\n")
    assert run_installer(root, "--source-root", source).returncode == 0
    assert not stale.exists() and not older.parent.exists()
    proc = run_installer(root, "--uninstall")
    assert proc.returncode == 0, proc.stderr
    assert not (root / "plugins" / "UV_Photometric_Stereo").exists()
    assert not (root / "plugins" / "UV_Photometric_Stereo.jar").exists()
    assert not (root / "plugins" / "jars" / "uvps_menu").exists()
    assert not (root / "jars" / "Lib" / "uvps_fiji").exists()
    assert (root / "plugins" / "Other_Plugin.py").is_file()
    assert "nothing to remove" in run_installer(root, "--uninstall").stdout


def test_python_without_uvps_is_refused(tmp_path, source):
    root = make_fiji(tmp_path)
    fake = tmp_path / "fake_python"
    fake.write_text("#!/bin/sh\necho \"ModuleNotFoundError: No module named 'uvps'\" >&2\nexit 1\n")
    fake.chmod(0o755)
    proc = run_installer(root, "--python", fake, "--source-root", source)
    assert proc.returncode == 1
    assert "cannot import uvps" in proc.stderr and str(fake) in proc.stderr
    assert len(proc.stderr.strip().splitlines()) == 1
    assert not (root / "plugins" / "UV_Photometric_Stereo.jar").exists()


def test_the_menu_lists_every_script_in_workflow_order():
    """Scripts the order does not list (a new menu item) come before the settings, never lost."""
    sys.path.insert(0, str(INSTALLER.parent))
    try:
        import install_fiji
    finally:
        sys.path.pop(0)
    names = sorted(p.name for p in (INSTALLER.parent.parent / "plugins" / "UV_Photometric_Stereo").glob("*.py"))
    config = install_fiji.menu_config(names + ["New_Item.py"])
    items = [ln.split('"')[1] for ln in config.splitlines()]
    assert items[:2] == ["Calibrate Lamps", "Run Whole Pipeline"] and items[-1] == "UVPS Settings"
    assert sorted(i for i in items if i != "-") == sorted(n[:-3].replace("_", " ") for n in names + ["New_Item.py"])
    assert items.index("Estimate Lights") < items.index("Normals and Albedo") < items.index("Integrate Height") \
        < items.index("Detect Protrusions") < items.index("Statistics and Report") < items.index("New Item")
    assert "--" not in "".join(items) and items.count("-") == 5


@pytest.mark.parametrize("layout, message", [
    ("no_plugins", "is not a Fiji or ImageJ folder"),
    ("no_scripts", "no menu scripts"),
])
def test_bad_folders_are_refused(tmp_path, source, layout, message):
    root = tmp_path / "target"
    root.mkdir()
    if layout == "no_scripts":
        (root / "plugins").mkdir()
        for script in (source / "plugins" / "UV_Photometric_Stereo").glob("*.py"):
            script.unlink()
    proc = run_installer(root, "--source-root", source)
    assert proc.returncode == 1
    assert message in proc.stderr


# --------------------------------------------------------------------------- plain ImageJ's Jython

REPO = INSTALLER.parent.parent
HAVE_JDK = (subprocess.run(["sh", "-c", "command -v javac"], stdout=subprocess.PIPE).returncode == 0
            and Path("/usr/share/java/jython.jar").is_file()
            and Path("/usr/share/java/ij.jar").is_file())


@pytest.mark.skipif(not HAVE_JDK, reason="needs javac and Debian's jython.jar and ij.jar")
@pytest.mark.slow
def test_plain_imagej_gets_a_jython_interpreter_and_uninstall_takes_it_back(tmp_path):
    import zipfile

    root = tmp_path / "ImageJ"
    (root / "plugins" / "jars").mkdir(parents=True)
    (root / "plugins" / "jars" / "user.jar").write_bytes(b"not ours")
    proc = run_installer(root, "--python", sys.executable)
    assert proc.returncode == 0, proc.stderr
    jars = root / "plugins" / "jars"
    assert "Jython.class" in zipfile.ZipFile(jars / "uvps_jython_interpreter.jar").namelist()
    assert (jars / "jython.jar").stat().st_size == Path("/usr/share/java/jython.jar").stat().st_size
    assert "Jython interpreter for plain ImageJ installed" in proc.stdout
    assert not (jars / "Lib" / "uvps_fiji" / "imagej1").exists()
    # a second install replaces ours (it is not a Jython.jar the user put there)
    assert "already present" not in run_installer(root, "--python", sys.executable).stdout
    proc = run_installer(root, "--uninstall")
    assert proc.returncode == 0
    assert sorted(p.name for p in jars.glob("*.jar")) == ["user.jar"]


def test_without_javac_the_installer_says_what_to_install(tmp_path):
    root = tmp_path / "ImageJ"
    (root / "plugins").mkdir(parents=True)
    proc = subprocess.run([sys.executable, str(INSTALLER), str(root), "--python", sys.executable],
                          stdout=subprocess.PIPE, stderr=subprocess.PIPE, universal_newlines=True,
                          timeout=120, env={"PATH": str(tmp_path / "empty")})
    assert proc.returncode == 0, proc.stderr
    assert "not found: javac" in proc.stdout
    assert "apt install default-jdk-headless jython" in proc.stdout
    assert not (root / "plugins" / "jars" / "uvps_jython_interpreter.jar").exists()


def test_fiji_gets_no_interpreter(tmp_path, source):
    root = make_fiji(tmp_path)
    proc = run_installer(root, "--source-root", source)
    assert proc.returncode == 0 and "Fiji ships Jython" in proc.stdout
    assert sorted(p.name for p in (root / "plugins" / "jars").iterdir()) == ["uvps_menu"]


def test_the_fiji_index_table_is_generated_from_the_declarations(tmp_path):
    """docs/fiji/index.md's menu table is what scripts/fiji_index.py writes; a new menu script with its
    declaration appears in menu order with its help, linked to the command reference until it has a page."""
    proc = subprocess.run([sys.executable, str(INSTALLER.parent / "fiji_index.py"), "--check"],
                          capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, "docs/fiji/index.md is stale: run scripts/fiji_index.py"
    sys.path.insert(0, str(INSTALLER.parent))
    try:
        import install_fiji
    finally:
        sys.path.pop(0)
    menu, docs = tmp_path / "menu", tmp_path / "docs"
    menu.mkdir()
    docs.mkdir()
    for stem in ("Run_Whole_Pipeline", "New_Item", "UVPS_Settings"):
        (menu / (stem + ".py")).write_text("")
    (docs / "Run_Whole_Pipeline.md").write_text("")
    commands = {"run": {"help": "the whole pipeline", "menu": "Run Whole Pipeline"},
                "new": {"help": "what <run> gains", "menu": "New Item"}, "demo": {"help": "x", "menu": ""}}
    rows = install_fiji.fiji_index_table(commands, menu, docs).splitlines()[2:]
    assert rows == ["| [Run Whole Pipeline](Run_Whole_Pipeline.md) | the whole pipeline | `run` |",
                    "| [New Item](../commands.md#uvps-new) | what &lt;run&gt; gains | `new` |",
                    "| [UVPS Settings]() | choose and check the CPython | - |"]
