"""A run folder is all old or all new: the real `uvps run` (a subprocess), Ctrl-C at five points of a
run that writes a report over an older folder, into a new folder, and output locations that cannot be
written."""
import hashlib
import json
import os
import shutil
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

from uvps.files import outputs
from uvps.errors import UVPSInputError
from uvps.testing.synthetic import make_capture, write_capture

#: Log lines of `uvps run --regions auto` at which the Ctrl-C is sent: reading done, detection done,
#: measurement done (the run folder's files are being written), the report started, the report done.
POINTS = ("uvps.files.io: capture:", "uvps.core.detect: detect:", "uvps.core.measure: measured", "area names from",
          "uvps.report.page: report:")


def _start(args):
    return subprocess.Popen([sys.executable, "-m", "uvps", *map(str, args)], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)


def _interrupt_at(args, marker):
    """Run uvps, send SIGINT the moment its log prints ``marker``; (exit status, stderr)."""
    proc = _start(args)
    lines = []

    def read():
        for line in proc.stderr:
            lines.append(line)
            if marker in line and proc.poll() is None:
                proc.send_signal(signal.SIGINT)

    reader = threading.Thread(target=read)
    reader.start()
    proc.wait(timeout=600)
    reader.join(timeout=60)
    proc.stdout.close()
    proc.stderr.close()
    return proc.returncode, "".join(lines)


def _snapshot(folder):
    return {str(p.relative_to(folder)): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(Path(folder).rglob("*")) if p.is_file()}


@pytest.fixture(scope="module")
def capture(tmp_path_factory):
    folder = tmp_path_factory.mktemp("cap")
    write_capture(make_capture(shape=(200, 260), n_lights=8, seed=3, pixel_size_um=30.0), folder)
    return folder


@pytest.mark.slow
def test_ctrl_c_at_five_points_leaves_the_old_folder_or_a_whole_new_one(capture, tmp_path, tmp_path_factory, ctrl_c):
    """Each point is tried on the same old folder: a run that finishes before its Ctrl-C lands (on a
    loaded machine the log line can reach the test after the swap began) must leave a whole new folder;
    the old one is then put back, byte for byte, and the point tried once more. At least four of the
    five points must see the run interrupted with the old folder left as it was."""
    lights = capture / "lights_positions_mm.csv"
    run = tmp_path / "run"
    old = subprocess.run([sys.executable, "-m", "uvps", "run", str(capture), "-o", str(run), "--regions", "auto",
                          "--pixel-size-um", "30", "--lights", str(lights)], capture_output=True, text=True, timeout=600)
    assert old.returncode == 0, old.stderr
    (run / "notes.txt").write_text("the conservator's own notes")             # not the run's: carried over
    (run / "protrusions_manual.csv").write_text("id\n")                        # an earlier wand's result: set aside
    before = _snapshot(run)
    saved = tmp_path_factory.mktemp("old_run") / "run"
    shutil.copytree(run, saved)
    ran_over = interrupted = 0
    for marker in POINTS:
        for _ in range(2):      # a point whose run finished first is tried once more
            t0 = time.time()
            time.sleep(0.05)
            code, err = _interrupt_at(["run", capture, "-o", run, "--regions", "auto", "--pixel-size-um", 15,
                                       "--lights", lights], marker)
            assert "Traceback" not in err, err
            assert sorted(p.name for p in tmp_path.iterdir()) == ["run"], marker   # no leftovers beside it
            after = _snapshot(run)
            log = json.loads((run / "run.json").read_text())
            if code == 130 and "left as it was" in err.splitlines()[-1]:
                interrupted += 1
                assert after == before, marker                                     # byte for byte the old run
                assert err.splitlines()[-1] == f"uvps run: interrupted; {run} left as it was (nothing of this run written)"
                break
            else:
                ran_over += 1
                assert code in (0, 130), err
                assert log["params"]["pixel_size_um"] == 15.0
                assert "protrusions_manual.csv" not in after and (run / "notes.txt").read_text().startswith("the")
                assert {"report.html", "run.json", "depth.tif", "regions.csv"} <= set(after)
                # the manual count moved aside with the run it was measured on, byte for byte
                (aside,) = {k.split("/")[1] for k in after if k.startswith("earlier/")}
                for name in ("protrusions_manual.csv", "run.json", "depth.tif", "albedo.tif"):
                    assert after[f"earlier/{aside}/{name}"] == before[name], name
                now = {k for k in after if not k.startswith("earlier/")}
                assert now - {"notes.txt"} == {k for k in before if k != "protrusions_manual.csv"} - {"notes.txt"}
                for rel in now:
                    if rel != "notes.txt":
                        assert (run / rel).stat().st_mtime >= t0, rel                # every file of this run
                shutil.rmtree(run)                                       # the old folder again, for the next point
                shutil.copytree(saved, run)
                assert _snapshot(run) == before
    assert interrupted >= 4, (interrupted, ran_over)


@pytest.mark.slow
def test_ctrl_c_into_a_new_nested_folder_leaves_nothing(capture, tmp_path, ctrl_c):
    out = tmp_path / "runs" / "region1"
    code, err = _interrupt_at(["run", capture, "-o", out, "--regions", "auto", "--lights",
                               capture / "lights_positions_mm.csv"], "uvps.core.detect: detect:")
    assert code == 130, err
    assert err.splitlines()[-1] == f"uvps run: interrupted; nothing written ({out} not created)"
    assert list(tmp_path.iterdir()) == []                                      # not even runs/


def test_missing_parent_folders_are_made(capture, tmp_path):
    out = tmp_path / "runs" / "deeper" / "region1"
    r = subprocess.run([sys.executable, "-m", "uvps", "run", str(capture), "-o", str(out), "--lights",
                        str(capture / "lights_positions_mm.csv")], capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stderr
    assert (out / "run.json").is_file() and (out / "depth.tif").is_file()
    assert sorted(p.name for p in out.parent.iterdir()) == ["region1"]         # no temporary left


@pytest.mark.skipif(os.geteuid() == 0, reason="root writes into read-only folders")
def test_an_unwritable_location_fails_before_computing(capture, tmp_path):
    ro = tmp_path / "ro"
    ro.mkdir()
    ro.chmod(0o555)
    try:
        t0 = time.perf_counter()
        r = subprocess.run([sys.executable, "-m", "uvps", "run", str(capture), "-o", str(ro / "a" / "run")],
                           capture_output=True, text=True, timeout=600)
        assert r.returncode == 1
        assert r.stderr.strip().splitlines()[-1] == (f"uvps run: error: output folder {ro / 'a' / 'run'}: cannot "
                                                     f"write in {ro} (read-only or no permission); choose another "
                                                     "output folder")
        assert "lights" not in r.stderr and time.perf_counter() - t0 < 60
    finally:
        ro.chmod(0o755)


def test_the_writability_check_names_the_folder(tmp_path, monkeypatch):
    """As root a mode of 0o555 does not stop writing; a read-only file system does (os.access says so)."""
    real = os.access
    monkeypatch.setattr(outputs.os, "access", lambda p, mode: False if Path(p) == tmp_path else real(p, mode))
    with pytest.raises(UVPSInputError, match=r"cannot write in .* \(read-only or no permission\)"):
        outputs.check_output_dir(tmp_path / "x" / "run")
    (tmp_path / "f").write_text("")
    with pytest.raises(UVPSInputError, match="is a file, not a folder"):
        outputs.check_output_dir(tmp_path / "f" / "run")


def test_new_output_dir_swaps_whole_and_carries_the_users_files(tmp_path):
    run = tmp_path / "run"
    run.mkdir()
    (run / "depth.tif").write_text("old")
    (run / "clicks.csv").write_text("x_px,y_px\n1,2\n")
    (run / "figures").mkdir()
    (run / "figures" / "old.png").write_text("old")
    with outputs.new_output_dir(run, carry_over=lambda name: name == "clicks.csv") as new:
        assert new.name == "run" and new.parent.parent == tmp_path
        (new / "depth.tif").write_text("new")
    assert _snapshot(run).keys() == {"depth.tif", "clicks.csv"}
    assert (run / "depth.tif").read_text() == "new" and str(run) in outputs.COMMITTED
    assert sorted(p.name for p in tmp_path.iterdir()) == ["run"]
    before = _snapshot(run)
    with pytest.raises(KeyboardInterrupt):
        with outputs.new_output_dir(run) as new:
            (new / "depth.tif").write_text("newer")
            raise KeyboardInterrupt
    assert _snapshot(run) == before and sorted(p.name for p in tmp_path.iterdir()) == ["run"]


def test_a_signal_during_the_swap_waits_for_its_end(tmp_path, ctrl_c):
    """SIGINT raised inside deferred_signals is delivered after the block, not in the middle."""
    done = []
    with pytest.raises(KeyboardInterrupt):
        with outputs.deferred_signals():
            os.kill(os.getpid(), signal.SIGINT)
            time.sleep(0.05)
            done.append(1)
    assert done == [1]


@pytest.mark.parametrize("exchange", [True, False], ids=["renameat2-exchange", "two-renames"])
def test_replace_dir_swaps_a_folder_whole_and_leaves_nothing_beside_it(tmp_path, monkeypatch, exchange):
    """The one folder swap (run folders, the painting, calibrations, zarr stores): the new folder in
    place whole, the old one gone, nothing left beside it, a plain mkdir's mode; the same without the
    exchange call (two renames with signals held)."""
    if not exchange:
        monkeypatch.setattr(outputs, "_exchange", lambda a, b: False)
    dst = tmp_path / "run"
    dst.mkdir()
    (dst / "depth.tif").write_text("old")
    (dst / "old_only.txt").write_text("old")
    src = tmp_path / ".run.new"
    src.mkdir(mode=0o700)
    (src / "depth.tif").write_text("new")
    outputs.replace_dir(src, dst)
    assert _snapshot(dst) == {"depth.tif": hashlib.sha256(b"new").hexdigest()}
    assert sorted(p.name for p in tmp_path.iterdir()) == ["run"]
    assert dst.stat().st_mode & 0o777 == 0o777 & ~outputs._umask()
    fresh = tmp_path / ".fresh"
    fresh.mkdir()
    outputs.replace_dir(fresh, tmp_path / "new_run")                   # nothing there yet: one rename
    assert sorted(p.name for p in tmp_path.iterdir()) == ["new_run", "run"]
