"""How ``uvps batch``'s processes end: the worker processes of its own local cluster, and its own.

A module of its own, importing nothing of uvps's pipeline: the cluster's start waits for the workers
to import it (the tiles' tasks import :mod:`uvps.commands.batch` and the pipeline as before).
"""
from __future__ import annotations

import contextlib
import os


def exit_after_atexit() -> None:
    """Make this (worker) process end, when it exits, right after its ``atexit`` handlers, without the
    interpreter's teardown of its modules and objects.

    Once a worker of the batch's own cluster has closed, that teardown is all that is left of it, and
    after a tile's run (numpy, SciPy, OpenCV, numba, zarr loaded) it took 0.7-3.7 s at load 2-9, past
    the nanny's 4 s wait at times ("Worker process still alive after 4.0 seconds, killing"); the batch's
    close waited for it (docs/decisions/painting.md, "The batch's fixed costs (small tiles)"). The
    interpreter ends as usual (its threads joined, every ``atexit`` handler run once, stdout and stderr
    flushed), and at the garbage collection that starts its teardown the process ends with status 0.
    (An ``atexit`` handler of this process's own cannot be the last one to run: handlers registered
    before it, by distributed and the modules it imported, run after it.) A process whose garbage
    collector is off at its exit just ends as usual. Only for the batch's own local worker processes:
    never a ``--scheduler`` cluster's, nor the batch's process (``processes=False``).
    """
    import gc
    import sys

    def _at_teardown(phase, info):
        if phase == "start" and sys.is_finalizing():
            for stream in (sys.stdout, sys.stderr):
                with contextlib.suppress(Exception):
                    stream.flush()
            os._exit(0)

    if _at_teardown not in gc.callbacks:
        gc.callbacks.append(_at_teardown)


def exit_now(status: int) -> None:
    """End this process now with ``status``, as the interpreter would but for its teardown: the threads
    that are not daemons joined, every ``atexit`` handler run, stdout and stderr flushed, then
    ``os._exit``. For a process whose work is all written (the batch's files are written atomically and
    closed); the teardown only frees what the process held."""
    import atexit
    import sys
    import threading

    # what the interpreter does first at its exit: concurrent.futures' executors told to end, the threads
    # that are not daemons joined (a no-op when the interpreter has done it, as before atexit handlers)
    getattr(threading, "_shutdown", lambda: None)()
    atexit._run_exitfuncs()   # every handler, as the interpreter would run them
    for stream in (sys.stdout, sys.stderr):
        with contextlib.suppress(Exception):
            stream.flush()
    os._exit(status)
