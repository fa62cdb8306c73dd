"""Failures say what to try: no library warning on the terminal, user-caused failures exit 1 with a
next step, `uvps compare` against a truth table (real subprocesses)."""
import subprocess
import sys

import numpy as np
import pytest

from uvps.core import lights
from uvps.errors import UVPSInputError
from uvps.testing.synthetic import make_capture, write_capture

#: A command that trips numpy's divide-by-zero RuntimeWarning and a library DeprecationWarning, then
#: fails on bad input, run through the real `uvps` entry point.
_WARNING_COMMAND = """
import dataclasses, sys, warnings
import numpy as np
from uvps import cli
from uvps.errors import UVPSInputError

def noisy(*args, **kwargs):
    np.log(np.zeros(3))
    np.float64(1.0) / np.zeros(2)
    warnings.warn("a library's own warning", DeprecationWarning)
    raise UVPSInputError("run folder x: the answer a user reads")

cli.COMMANDS["info"] = dataclasses.replace(cli.COMMANDS["info"], run=noisy)
sys.exit(cli.main(sys.argv[1:]))
"""


@pytest.mark.parametrize("verbose", [False, True])
def test_no_library_warning_reaches_the_terminal(tmp_path, verbose):
    args = (["-v"] if verbose else []) + ["info", str(tmp_path)]
    r = subprocess.run([sys.executable, "-W", "default", "-c", _WARNING_COMMAND, *args], capture_output=True,
                       text=True, timeout=120)
    assert r.returncode == 1
    if verbose:      # -v: the log shows them, for a developer
        assert "RuntimeWarning" in r.stderr and "divide by zero" in r.stderr
    else:
        assert r.stderr.strip().splitlines() == ["uvps info: error: run folder x: the answer a user reads"]


def test_too_few_lit_pixels_is_bad_input_with_a_next_step(monkeypatch):
    """The light estimate's sample: a user's capture (exposure, mask) leaves too few pixels."""
    monkeypatch.setattr(lights, "_eval_points", lambda fit, r, c: np.zeros(len(r)))
    images = np.full((4, 60, 60), 1000, np.uint16)
    mask = np.zeros((60, 60), bool)
    mask[10:17, 10:17] = True                      # 49 pixels
    with pytest.raises(UVPSInputError, match=r"too few pixels lit by enough lights .*\(49 of .*lit by at least 4 "
                                             r"images.* check the images' "
                                             r"exposure.*give measured lamp positions \(--lights\)"):
        lights.sample_pixels(images, [None] * 4, mask=mask, saturation=65535.0, pixel_size_um=15.0)


def test_too_few_lit_pixels_names_the_lamps_that_leave_the_field_dark(monkeypatch):
    """A dome's low lamps light part of the field each: the refusal says which lamps (1-based) and how much."""
    monkeypatch.setattr(lights, "_eval_points", lambda fit, r, c: np.zeros(len(r)))
    images = np.full((5, 60, 60), 1000, np.uint16)
    images[1, :, :29] = 20                          # low lamps: each lights part of the field
    images[3, :, 29:58] = 20
    images[4, :, 56:] = 20
    with pytest.raises(UVPSInputError, match=r"too few pixels lit by enough lights .*\(0 of .*lamps leaving the most of "
                                             r"them dark or saturated: image 2 \(48 %\), 4 \(48 %\)\)"):
        lights.sample_pixels(images, [None] * 5, saturation=65535.0, pixel_size_um=15.0)


@pytest.fixture(scope="module")
def small_run(tmp_path_factory):
    root = tmp_path_factory.mktemp("cmp")
    write_capture(make_capture(shape=(200, 260), n_lights=8, seed=4), root / "cap")
    r = subprocess.run([sys.executable, "-m", "uvps", "run", str(root / "cap"), "-o", str(root / "run"), "--detect",
                        "--lights", str(root / "cap" / "lights_positions_mm.csv")],
                       capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stderr
    return root


def test_compare_against_a_truth_table_takes_the_runs_pixel_size(small_run):
    out = small_run / "cmp"
    r = subprocess.run([sys.executable, "-m", "uvps", "compare", str(small_run / "cap" / "truth" / "protrusions.csv"),
                        str(small_run / "run" / "protrusions.csv"), "-o", str(out)],
                       capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr
    assert "pixel size 15 um from the run folder" in r.stderr
    rows = (out / "comparison.csv").read_text().splitlines()
    assert len(rows) >= 2 and "matched" in rows[0]
    # with no run anywhere near: a one-line message naming what to give
    lone = small_run / "lone.csv"
    lone.write_text("id,x_px,y_px,width_um\n1,10,10,100\n")
    r = subprocess.run([sys.executable, "-m", "uvps", "compare", str(lone), str(lone), "-o", str(small_run / "c2")],
                       capture_output=True, text=True, timeout=300)
    assert r.returncode == 1
    assert r.stderr.strip().splitlines()[-1].endswith("give pixel_size_um (--pixel-size-um), or -o the run folder "
                                                      "of one of the tables")


def _binary(path):
    """A TIFF given where a text file is expected (a table, a light file, a list)."""
    import tifffile

    tifffile.imwrite(str(path), (np.arange(64, dtype=np.uint16) * 1000).reshape(8, 8))
    return path


#: Bad inputs a new user types (each once an exit 2: a library error, "internal error"): the
#: arguments (``{run}``, ``{cap}``, ``{bin}``: the run folder, its capture, a TIFF named .csv)
#: and the start of the one line expected after "uvps <command>: error: ".
USER_MISTAKES = {
    "pixel size of a km": (["run", "{cap}", "-o", "{tmp}/o1", "--pixel-size-um", "1e9"],
                           "pixel_size_um 1e+09 um is not a pixel size on a painting (1-1000 um)"),
    "pixel size in mm": (["detect", "-o", "{run}", "--pixel-size-um", "0.1"],
                         "pixel_size_um 0.1 um is not a pixel size on a painting (1-1000 um); give it in "
                         "micrometres (0.1 mm = 100 um)"),
    "an image as a table": (["compare", "{bin}", "{run}/protrusions.csv", "-o", "{tmp}/o2"],
                            "protrusion table {bin} is not a text file (an image?)"),
    "an image as a lights file": (["run", "{cap}", "-o", "{tmp}/o3", "--lights", "{bin}"],
                                  "light positions file {bin} is not a text file (an image?)"),
    "an image as a batch list": (["batch", "{bin}", "-o", "{tmp}/o4"],
                                 "captures: the list {bin} is not a text file (an image?)"),
    "a lights file as clicks": (["wand", "{cap}/lights_positions_mm.csv", "-o", "{run}"],
                                "click 1 at (x="),
    "an unknown flag": (["detect", "-o", "{run}", "--sensitivty", "5"],
                        "unrecognized arguments: --sensitivty 5; see uvps --help"),
    "a missing argument": (["compare", "-o", "{tmp}/o5"],
                           "the following arguments are required: a, b; see uvps compare --help"),
    "a typo of auto": (["run", "{cap}", "-o", "{tmp}/o6", "--regions", "autp"],
                       "region file autp does not exist (or give auto: colour areas proposed from the albedo)"),
    "a value not among the choices": (["run", "{cap}", "-o", "{tmp}/o7", "--level", "plan"],
                                      "argument --level: invalid choice: 'plan'"),
    "a batch's lights file in no folder": (["batch", "{cap}", "-o", "{tmp}/o8", "--lights", "lamps.csv"],
                                           "lights: lamps.csv is no file, and none of the capture folders holds lamps.csv"),
}


@pytest.mark.parametrize("mistake", sorted(USER_MISTAKES))
def test_a_users_mistake_exits_1_with_one_line(small_run, tmp_path, mistake):
    """No exit 2 (kept for failures a user cannot fix) and no traceback or library warning for what a
    user typed wrong: exit 1, one line naming the value or file and what was expected."""
    args, expected = USER_MISTAKES[mistake]
    names = {"run": small_run / "run", "cap": small_run / "cap", "bin": _binary(tmp_path / "table.csv"),
             "tmp": tmp_path}
    args = [a.format(**names) for a in args]
    r = subprocess.run([sys.executable, "-m", "uvps", *args], capture_output=True, text=True, timeout=300)
    assert r.returncode == 1, r.stderr
    # one line: no usage block above it, and a mistake known before the images are read is caught first
    lines = [ln for ln in r.stderr.splitlines() if not ln.startswith("INFO ") or mistake != "a typo of auto"]
    assert len(lines) == 1, r.stderr
    assert lines[0].split(": error: ", 1)[1].startswith(expected.format(**names)), lines
    assert "Traceback" not in r.stderr and "Warning" not in r.stderr
