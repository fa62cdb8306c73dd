"""uvps batch: many captures on a real Dask LocalCluster, the skip rule, failures, a killed worker,
and a mosaic of two overlapping tiles counted once."""
import csv
import dataclasses
import json
import os
import shutil
import signal
import socket
import subprocess
import sys
import threading
import time

import distributed   # a dependency of uvps (pyproject.toml): no skip if it is missing
import numpy as np
import pytest
import tifffile

from uvps.commands.batch import SUMMARY, _import_modules, _StitchWarmUp, complete, list_captures, run_batch
from uvps.commands import COMMANDS
from uvps.errors import UVPSInputError
from uvps.testing.synthetic import make_capture, write_capture


LAMPS = "lights_positions_mm.csv"          # written by write_capture into each capture folder
PARAMS = {"lights": LAMPS, "regions": "auto"}


@pytest.fixture(scope="module")
def client():
    """Two worker processes of one thread each, as `uvps batch` starts on this 2-core machine
    (processes, not threads: each worker imports uvps and unpickles the task as on a real cluster;
    about 5 s to start, once for the module)."""
    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True,
                                  dashboard_address=":0") as cluster, distributed.Client(cluster) as c:
        yield c


@pytest.fixture(scope="module")
def captures(tmp_path_factory):
    root = tmp_path_factory.mktemp("captures")
    for seed in (1, 2, 3):
        write_capture(make_capture(shape=(120, 160), n_lights=8, seed=seed), root / f"cap{seed}", truth=False)
    return root


def _summary(out):
    with open(out / SUMMARY, newline="", encoding="utf-8") as fh:
        return {r["capture"]: r for r in csv.DictReader(fh)}


def _rows(path):
    with open(path, newline="", encoding="utf-8") as fh:
        return list(csv.DictReader(fh))


@pytest.mark.slow
def test_three_captures_run_as_uvps_run_then_a_rerun_skips_them(captures, client, tmp_path):
    out = tmp_path / "not yet made" / "out"             # missing parents are made, as by uvps run
    t0 = time.perf_counter()
    res = run_batch([captures], out, PARAMS, client=client)
    elapsed = time.perf_counter() - t0
    assert [r["status"] for r in res.records] == ["done"] * 3, res.records
    print(f"3 captures on 2 workers: {elapsed:.1f} s")
    summary = _summary(out)
    assert list(summary) == ["cap1", "cap2", "cap3"]
    for name, row in summary.items():
        run_dir = out / name
        assert row["status"] == "done" and row["error"] == ""
        assert int(row["n_protrusions"]) == len(_rows(run_dir / "protrusions.csv"))
        page = (run_dir / "report.html").read_text(encoding="utf-8")
        assert f"<title>Protrusion report: {name}</title>" in page    # the run folder's name, not its stage's
        assert "batch-tmp" not in page
        for area in _rows(run_dir / "regions.csv"):
            if area["label"] != "all":
                assert int(row[f"{area['name']}: count"]) == int(area["count"])
                assert float(row[f"{area['name']}: density_per_cm2"]) == pytest.approx(float(area["density_per_cm2"]))
    # a batch run is `uvps run`: the same heights and protrusions as a single run of the capture
    single = tmp_path / "single"
    COMMANDS["run"]({"images": [str(captures / "cap2")]}, {**PARAMS, "lights": str(captures / "cap2" / LAMPS)}, single)
    np.testing.assert_array_equal(tifffile.imread(out / "cap2" / "depth.tif"), tifffile.imread(single / "depth.tif"))
    assert (out / "cap2" / "protrusions.csv").read_text() == (single / "protrusions.csv").read_text()
    log = json.loads((out / "batch.json").read_text())
    assert log["counts"] == {"done": 3, "skipped": 0, "failed": 0}
    # the batch's parts add up to (at most) its whole: where a batch's time beyond its tiles goes
    parts = log["timings"]
    assert set(parts) == {"cluster_start_s", "tiles_s", "stitch_s", "close_s"}
    # each time is rounded to 1 ms (batch.json): the parts' sum may pass the whole by the roundings alone
    assert all(v >= 0 for v in parts.values()) and sum(parts.values()) <= log["elapsed_s"] + 0.0005 * (len(parts) + 1)
    assert parts["tiles_s"] >= max(c["elapsed_s"] for c in log["captures"])
    # a re-run skips all three and leaves their files alone
    mtime = (out / "cap1" / "run.json").stat().st_mtime_ns
    seen = []
    res = run_batch([captures], out, PARAMS, client=client, progress=lambda f, m: seen.append((f, m)))
    assert [r["status"] for r in res.records] == ["skipped"] * 3
    assert (out / "cap1" / "run.json").stat().st_mtime_ns == mtime
    assert seen[-1] == (1.0, "3/3 captures: 0 done, 3 skipped, 0 failed")
    assert _summary(out)["cap3"]["n_protrusions"] == summary["cap3"]["n_protrusions"]
    # ... unless the parameters change
    assert complete(out / "cap1", captures / "cap1", {**res_params(out, "cap1"), "degree": 3})[0] is False
    assert not [p for p in out.iterdir() if p.name.startswith(".")]


def res_params(out, name):
    return json.loads((out / name / "batch_request.json").read_text())["params"]


@pytest.mark.slow
def test_a_corrupted_capture_fails_alone_with_its_message(captures, client, tmp_path):
    bad = tmp_path / "bad"
    shutil.copytree(captures / "cap1", bad)
    (bad / "uv_03.tif").write_bytes(b"not a tiff at all")
    listing = tmp_path / "list.txt"
    listing.write_text(f"# two good, one bad\n{captures / 'cap2'}\nbad\n{captures / 'cap3'}\n")
    out = tmp_path / "out"
    res = run_batch([listing], out, PARAMS, client=client)
    status = {r["capture"]: r for r in res.records}
    assert [status[n]["status"] for n in ("cap2", "bad", "cap3")] == ["done", "failed", "done"]
    error = status["bad"]["error"]
    assert "uv_03.tif" in error and "\n" not in error
    assert _summary(out)["bad"]["error"] == error
    assert res.warnings == [f"bad failed: {error}"]
    assert not (out / "bad").exists()                            # nothing half-written
    # a re-run runs the failed one again (still failing) and skips the others
    res = run_batch([listing], out, PARAMS, client=client)
    assert [r["status"] for r in res.records] == ["skipped", "failed", "skipped"]
    # a changed input runs again
    changed = tmp_path / "cap2"
    shutil.copytree(captures / "cap2", changed)
    out2 = tmp_path / "out2"
    run_batch([changed], out2, PARAMS, client=client)
    img = tifffile.imread(changed / "uv_00.tif")
    tifffile.imwrite(changed / "uv_00.tif", img // 2 + 1, photometric="rgb")
    assert complete(out2 / "cap2", changed, res_params(out2, "cap2")) == (False, "uv_00.tif changed")


@pytest.mark.slow
def test_a_killed_worker_leaves_nothing_half_written(captures, client, tmp_path):
    """One worker process killed (SIGKILL) while a capture is being written (or, if its new folder is
    not seen in time, while it runs): the nanny starts a new worker, the scheduler runs the task
    again, every run folder is whole, no temporary is left."""
    out = tmp_path / "out"
    pids = list(client.run(os.getpid).values())
    killed = []

    # a small capture is written in a few milliseconds: each worker holds its new folder open for a
    # second after writing it (before the swap), so that the kill falls inside the write, not beside it.
    # The hold wraps the name the workflow calls (uvps.files.runfolder.write_run, which the workflow
    # imports where it writes); a kill that fell after the swap found the capture whole on the rerun
    # ("skipped", not "done")
    def hold_new_folders(seconds):
        import uvps.files.runfolder as wf

        original = getattr(wf, "_write_run_unheld", wf.write_run)

        def write_run(*args, **kwargs):
            written = original(*args, **kwargs)
            time.sleep(seconds)
            return written

        wf._write_run_unheld = original
        wf.write_run = write_run if seconds else original

    client.run(hold_new_folders, 1.0)

    def kill_when_writing():
        deadline = time.time() + 60
        started = time.time()
        while time.time() < deadline and not killed:
            writing = out.is_dir() and any(p.name.startswith(".cap") for p in out.iterdir())
            # or, where the new folder is not seen in time, while the worker runs a capture
            running = time.time() > started + 3 and any(client.processing(workers=None).values())
            if writing or running:
                os.kill(pids[0], signal.SIGKILL)
                killed.append(pids[0])
            time.sleep(0.01)

    watcher = threading.Thread(target=kill_when_writing)
    watcher.start()
    try:
        res = run_batch([captures], out, PARAMS, client=client)
    finally:
        watcher.join()
        client.run(hold_new_folders, 0)
    assert killed, "no capture was seen being run or written"
    assert [r["status"] for r in res.records] == ["done"] * 3, res.records
    for name in ("cap1", "cap2", "cap3"):
        assert complete(out / name, captures / name, res_params(out, name))[0]
        assert (out / name / "report.html").is_file()
    assert not [p for p in out.iterdir() if p.name.startswith(".")]
    client.wait_for_workers(2, timeout=60)


@pytest.fixture(scope="module")
def mosaic(tmp_path_factory):
    """One capture (160 x 280 px, 45 protrusions) and two tiles cut from it: columns 0-169 and
    110-279 (a 60 px = 0.9 mm overlap), each with its lamps moved to its own centre."""
    root = tmp_path_factory.mktemp("mosaic")
    cap = make_capture(shape=(160, 280), n_lights=8, seed=3, protrusion_density_light=400.0,
                       protrusion_density_dark=400.0, width_um=(90.0, 240.0))
    write_capture(cap, root / "whole", truth=False)
    (root / "tiles").mkdir()
    N, px_mm = cap.images.shape[2], cap.spec.pixel_size_um / 1000
    for name, c0, c1 in (("A", 0, 170), ("B", 110, 280)):
        centre = np.array([(c0 + (c1 - c0 - 1) / 2 - (N - 1) / 2) * px_mm, 0.0, 0.0])
        tile = dataclasses.replace(cap, images=np.ascontiguousarray(cap.images[:, :, c0:c1]),
                                   light_positions_mm=cap.light_positions_mm - centre)
        write_capture(tile, root / "tiles" / name, truth=False)
    (root / "layout.csv").write_text("capture,x_px,y_px\nA,0,0\nB,110,0\n")
    return root


@pytest.mark.slow
def test_a_mosaic_counts_each_protrusion_of_the_overlap_once(mosaic, client, tmp_path):
    whole = tmp_path / "whole"
    COMMANDS["run"]({"images": [str(mosaic / "whole")]}, {**PARAMS, "lights": str(mosaic / "whole" / LAMPS)}, whole)
    n_whole = len(_rows(whole / "protrusions.csv"))
    out = tmp_path / "out"
    res = run_batch([mosaic / "tiles"], out, PARAMS, mosaic=mosaic / "layout.csv", client=client)
    assert [r["status"] for r in res.records] == ["done", "done"]
    merged = _rows(out / "painting" / "painting_protrusions.csv")
    n_tiles = sum(r["n_protrusions"] for r in res.records)
    # the tiles' own outer edges are the capture's, so only their noise and weave estimates (per
    # image) and protrusions cut by a tile's edge inside the overlap can make the counts differ: 2
    # or 10 % (seen: 45 = 45, with 52 in the two tiles together)
    assert abs(len(merged) - n_whole) <= max(2, 0.1 * n_whole), (len(merged), n_whole, n_tiles)
    assert n_tiles - len(merged) == res.mosaic["duplicates_removed"] > 0
    # painting coordinates: tile B's protrusions moved by its offset; no two kept within the match distance
    xy = np.array([[float(r["x_px"]), float(r["y_px"])] for r in merged])
    w = np.array([float(r["width_um"]) for r in merged]) / 15.0
    d = np.hypot(*(xy[:, None, :] - xy[None, :, :]).transpose(2, 0, 1)) + np.eye(len(xy)) * 1e9
    assert not np.any(d < 0.5 * np.maximum(w[:, None], w[None, :]))
    b = [r for r in merged if r["tile"] == "B"]
    # the layout is exact here: registration keeps it (within a tenth of a pixel)
    assert all(float(r["x_px"]) == pytest.approx(float(r["x_tile_px"]) + 110, abs=0.1) for r in b)
    # one density table for the painting: the overlap's area counted once, names merged
    regions = _rows(out / "painting" / "painting_regions.csv")
    total = regions[-1]
    assert total["name"] == "all areas" and int(total["count"]) == len(merged)
    assert float(total["area_cm2"]) == pytest.approx(160 * 280 * 15.0**2 / 1e8)
    assert sum(int(r["count"]) for r in regions[:-1]) <= len(merged)
    assert sum(float(r["area_cm2"]) for r in regions[:-1]) == pytest.approx(float(total["area_cm2"]))


def test_the_stitching_warm_up_never_fails_a_batch():
    """The stitching's imports, done while the last tiles run, leave a module that fails to import to fail where
    the stitching uses it, and a worker that cannot be asked (gone, a scheduler's error) to the maps."""
    _import_modules(("uvps_no_such_module", "json"))
    assert "json" in sys.modules

    class Gone:
        info = {"workers": 2, "local": True}

        class client:
            @staticmethod
            def who_has(futures):
                raise OSError("the scheduler is gone")

    class Done:
        key = "a-tile"

    warm = _StitchWarmUp()
    warm.start(Gone(), Done())
    warm.start(Gone(), Done())      # this process's thread once
    warm.wait()
    assert not warm.thread.is_alive() and warm.warmed == set()


@pytest.mark.parametrize("layout,message", [
    ("capture,x_px,y_px\nA,0,0\nC,110,0\n", "layout names tile 'C', which is not among the captures"),
    ("capture,x_px,y_px\nA,0,0\nB,400,0\n", "tile A at (0, 0) overlaps no other tile"),
    ("capture,x_px,y_px\nA,0,0\n", "capture B is not in the layout"),
    ("capture,x_px,y_px\nA,0,0\nA,110,0\nB,110,0\n", "layout names tile 'A' twice"),
])
def test_a_bad_layout_is_one_line_before_any_work(mosaic, tmp_path, layout, message):
    (tmp_path / "layout.csv").write_text(layout)
    with pytest.raises(UVPSInputError, match=message.replace("(", r"\(").replace(")", r"\)")):
        run_batch([mosaic / "tiles"], tmp_path / "out", PARAMS, mosaic=tmp_path / "layout.csv")
    assert not (tmp_path / "out").exists()


def test_inputs_folders_lists_and_names(captures, tmp_path):
    assert [p.name for p in list_captures([captures])] == ["cap1", "cap2", "cap3"]
    assert [p.name for p in list_captures([captures / "cap2"])] == ["cap2"]
    with pytest.raises(UVPSInputError, match="two capture folders are named cap1"):
        list_captures([captures / "cap1", captures])
    with pytest.raises(UVPSInputError, match="holds no images and no capture folders"):
        list_captures([tmp_path])
    with pytest.raises(UVPSInputError, match="lights: nolamps.csv is no file, and none of the capture folders holds nolamps.csv"):
        run_batch([captures], tmp_path / "out", {"lights": "nolamps.csv"})


@pytest.mark.slow
def test_the_command_line_on_the_default_local_cluster(captures, tmp_path):
    """Its own LocalCluster, with the dashboard's usual port 8787 taken (as by a second batch on the
    machine): the batch runs, and its log (``-v``, which shows the warnings) has no warning about
    the port: the dashboard takes a free one."""
    out = tmp_path / "out"
    shutil.copytree(captures / "cap1", tmp_path / "caps" / "cap1")
    cmd = [sys.executable, "-m", "uvps", "batch", str(tmp_path / "caps"), "-o", str(out), "--lights", LAMPS,
           "--regions", "auto", "--workers", "1"]
    with socket.socket() as held:
        try:
            held.bind(("", 8787))
            held.listen()
        except OSError:
            pass            # taken already: the same situation
        r = subprocess.run(cmd[:3] + ["-v"] + cmd[3:], capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr
    assert "Dask dashboard: http" in r.stderr, r.stderr
    assert "8787" not in r.stderr and "already in use" not in r.stderr, r.stderr
    assert "cap1: done" in r.stdout and "1 done, 0 skipped, 0 failed" in r.stdout and "on 1 workers" in r.stdout
    r = subprocess.run(cmd + ["--force"], capture_output=True, text=True, timeout=300)
    assert r.returncode == 0 and "cap1: done" in r.stdout, r.stderr


def test_importing_uvps_commands_does_not_import_dask():
    code = "import sys, uvps.cli; print(any(m.split('.')[0] in ('dask', 'distributed') for m in sys.modules))"
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert r.stdout.strip() == "False", r.stderr


@pytest.mark.slow
def test_the_command_line_exit_status_when_captures_fail_on_bad_input(captures, tmp_path):
    """Every capture failing on bad input (a .tif that is no TIFF, two images only) is the user's
    to fix: exit 1, one line per capture naming it and its problem, then one summary line; the
    summary is still written. One good capture beside a bad one: exit 0, the bad one a warning
    and a line of the summary."""
    caps = tmp_path / "caps"
    (caps / "notiff").mkdir(parents=True)
    for name in ("a.tif", "b.tif", "c.tif"):
        (caps / "notiff" / name).write_text("not an image\n")
    (caps / "two").mkdir()
    for name in ("uv_00.tif", "uv_01.tif", LAMPS):
        shutil.copy(captures / "cap1" / name, caps / "two" / name)
    out = tmp_path / "out"
    cmd = [sys.executable, "-m", "uvps", "batch", "-o", str(out), "--workers", "1"]
    r = subprocess.run(cmd + [str(caps)], capture_output=True, text=True, timeout=300)
    assert r.returncode == 1, r.stderr
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 3, lines
    assert lines[0].startswith("uvps batch: notiff: ") and "a.tif" in lines[0] and "TIFF" in lines[0], lines
    assert lines[1].startswith("uvps batch: two: ") and "at least 3 images; got 2" in lines[1], lines
    assert lines[2].startswith("uvps batch: error: every capture failed on bad input (2") and \
        str(out / SUMMARY) in lines[2], lines
    assert "Traceback" not in r.stderr and "internal error" not in r.stderr
    summary = _summary(out)
    assert [summary[n]["status"] for n in ("notiff", "two")] == ["failed", "failed"]
    assert lines[1].endswith(summary["two"]["error"])
    assert [c["failure"] for c in json.loads((out / "batch.json").read_text())["captures"]] == ["input", "input"]
    # one good capture beside a bad one: the batch did its work
    shutil.copytree(captures / "cap1", caps / "cap1")
    r = subprocess.run(cmd + ["--lights", LAMPS, str(caps / "cap1"), str(caps / "two")],
                       capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr
    assert "warning: two failed: images: photometric stereo needs at least 3 images" in r.stderr
    assert "1 done, 0 skipped, 1 failed" in r.stdout and "two: failed (images:" in r.stdout


def test_the_batch_workers_keep_each_capture_to_one_thread():
    """uvps batch's own local worker processes (one thread each) set UVPS_THREADS=1, so a capture's
    stages (the normals' bands, the lamp refinement) take one thread there too, not one per CPU."""
    from uvps.commands.batch import _Cluster
    from uvps.core.threads import default_threads

    cluster = _Cluster(n_workers=1, processes=True)
    try:
        got = cluster.client.run(lambda: (os.environ.get("UVPS_THREADS"), default_threads(4)))
    finally:
        cluster.close()
    assert list(got.values()) == [("1", 1)]


def _started_as_the_batchs_worker() -> tuple:
    """In a worker: (the pipeline and the maps' zarr imported, uvps.workers.exit_at_teardown's hook set)."""
    import gc
    return ("uvps.core.pipeline" in sys.modules and "zarr" in sys.modules,
            any(getattr(cb, "__qualname__", "").startswith("exit_at_teardown.") for cb in gc.callbacks))


def test_the_batch_workers_import_the_pipeline_as_they_start_and_a_given_clusters_do_not(captures, client,
                                                                                         tmp_path):
    """uvps batch's own local workers import uvps.commands.batch (and with it the pipeline) and the maps'
    modules while the cluster starts (distributed's preload), before any task, and end without the
    interpreter's teardown; the workers of a cluster given to the batch (--scheduler, or a client) are left
    as they are, also after a batch ran there."""
    from uvps.commands.batch import _Cluster

    cluster = _Cluster(n_workers=1, processes=True)
    try:
        got = cluster.client.run(_started_as_the_batchs_worker)
    finally:
        cluster.close()
    assert list(got.values()) == [(True, True)]
    res = run_batch([captures / "cap1"], tmp_path / "out", PARAMS, client=client)
    assert [r["status"] for r in res.records] == ["done"]
    assert {hook for _, hook in client.run(_started_as_the_batchs_worker).values()} == {False}


def _has_mailbox() -> bool:
    return "mailbox" in sys.modules


def test_the_users_own_preload_given_as_one_string_is_kept():
    """A ``distributed.worker.preload`` of one module name (as ``DASK_DISTRIBUTED__WORKER__PRELOAD=mailbox``
    sets it; distributed reads it as one preload) stays one preload beside the batch's own: read as a list
    of characters the workers failed to start ("No module named 'm'")."""
    import dask
    from uvps.commands.batch import _Cluster

    with dask.config.set({"distributed.worker.preload": "mailbox", "distributed.worker.preload-argv": "-x"}):
        cluster = _Cluster(n_workers=1, processes=True)
    try:
        got = cluster.client.run(_has_mailbox)
    finally:
        cluster.close()
    assert list(got.values()) == [True]


def test_the_workers_preloads_one_argv_list_per_preload_or_one_for_all():
    import dask
    from uvps.commands.batch import _worker_preloads

    with dask.config.set({"distributed.worker.preload": "mailbox", "distributed.worker.preload-argv": "-x"}):
        assert _worker_preloads("b") == (["mailbox", "b"], ["-x"])
    with dask.config.set({"distributed.worker.preload": ["mailbox"],
                          "distributed.worker.preload-argv": [["-x"]]}):
        assert _worker_preloads("b") == (["mailbox", "b"], [["-x"], []])


def test_the_batch_workers_keep_glibcs_own_allocator_settings(monkeypatch):
    """uvps batch's own local workers run with glibc's allocator as a `uvps run` process does: no
    MALLOC_TRIM_THRESHOLD_ (distributed's nanny sets 65536 by default, which fixes the mmap threshold
    and makes every large numpy temporary a fresh mmap: twice the maps' CPU in a worker); the
    process's own Dask configuration is left as it was."""
    import dask
    from uvps.commands.batch import MALLOC_TRIM_KEY, _Cluster, _malloc_trim

    assert dask.config.get(MALLOC_TRIM_KEY) == 65536      # distributed's default, which the batch overrides
    # a nanny started earlier in this process leaves its value in os.environ (the module's client did)
    monkeypatch.setenv("MALLOC_TRIM_THRESHOLD_", "65536")
    cluster = _Cluster(n_workers=1, processes=True)
    try:
        got = cluster.client.run(lambda: os.environ.get("MALLOC_TRIM_THRESHOLD_"))
        cluster.trim()                                      # what the batch calls between tiles and stitching
        trimmed = cluster.client.run(_malloc_trim)
    finally:
        cluster.close()
    assert list(got.values()) == [None]
    assert list(trimmed.values()) in ([0], [1])             # glibc's malloc_trim ran in the worker
    assert os.environ["MALLOC_TRIM_THRESHOLD_"] == "65536"  # this process's environment is left as it was
    assert dask.config.get(MALLOC_TRIM_KEY) == 65536      # only for the batch's own cluster


def test_a_worker_process_ends_after_its_atexit_handlers_with_its_output_flushed(tmp_path):
    """The batch's own workers end right after their atexit handlers (uvps.workers): every handler
    still runs, once (one registered before the hook and one after), buffered output still reaches the
    pipe, the status is 0, and the objects' teardown does not run (a finaliser left for it never writes)."""
    code = ("import atexit, sys\n"
            "from uvps.workers import exit_at_teardown\n"
            f"atexit.register(lambda: open({str(tmp_path / 'before')!r}, 'a').write('ran'))\n"
            "exit_at_teardown()\n"
            f"atexit.register(lambda: open({str(tmp_path / 'after')!r}, 'a').write('ran'))\n"
            "class Left:\n"
            f"    def __del__(self, _open=open): _open({str(tmp_path / 'teardown')!r}, 'w').write('ran')\n"
            "left = Left()\n"
            "sys.stdout.write('buffered, no newline')\n")
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert done.returncode == 0, done.stderr
    assert done.stdout == "buffered, no newline"
    assert (tmp_path / "before").read_text() == "ran" and (tmp_path / "after").read_text() == "ran"
    assert not (tmp_path / "teardown").exists()
    # without the hook the same script's teardown runs the finaliser (the test sees the difference)
    plain = subprocess.run([sys.executable, "-c", code.replace("exit_at_teardown()\n", "")], capture_output=True,
                           text=True, timeout=60)
    assert plain.returncode == 0 and (tmp_path / "teardown").read_text() == "ran"


@pytest.mark.parametrize("status", [0, 1, 2])
def test_the_batch_process_ends_with_its_status_after_its_threads_and_atexit_handlers(tmp_path, status):
    """uvps.workers.exit_at_teardown as the batch's own process takes it (its status, from the console
    entry): the status kept, a thread that is not a daemon finished first, an executor's idle threads
    told to end, the atexit handlers run, output flushed."""
    code = ("import atexit, sys, threading, time\n"
            "from concurrent.futures import ThreadPoolExecutor\n"
            "from uvps.workers import exit_at_teardown\n"
            f"atexit.register(lambda: open({str(tmp_path / 'atexit')!r}, 'w').write('ran'))\n"
            "pool = ThreadPoolExecutor(2)\n"
            "pool.submit(time.sleep, 0.01).result()\n"       # an idle worker thread, never shut down
            f"threading.Thread(target=lambda: (time.sleep(0.5), open({str(tmp_path / 'thread')!r}, 'w')"
            ".write('done'))).start()\n"
            "sys.stdout.write('buffered')\n"
            f"exit_at_teardown({status})\n"
            f"sys.exit({status})\n")
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert done.returncode == status, done.stderr
    assert done.stdout == "buffered"
    assert (tmp_path / "atexit").read_text() == "ran" and (tmp_path / "thread").read_text() == "done"
