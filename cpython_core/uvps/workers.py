"""How ``uvps batch``'s processes end: the worker processes of its own local cluster, and its own.

A module of its own, importing nothing of uvps's pipeline: the batch's process imports it at its exit
whatever it ran, and the batch's workers call it from :func:`uvps.commands.batch.dask_setup` as they start.
"""
from __future__ import annotations

import contextlib
import os


def exit_at_teardown(status: int = 0) -> None:
    """Make this process end with ``status``, when it exits, right after its ``atexit`` handlers, without
    the interpreter's teardown of its modules and objects.

    Once a worker of the batch's own cluster has closed, that teardown is all that is left of it, and
    after a tile's run (numpy, SciPy, OpenCV, numba, zarr loaded) it took 0.7-3.7 s at load 2-9, past
    the nanny's 4 s wait at times ("Worker process still alive after 4.0 seconds, killing"); the batch's
    close waited for it; the batch's own process (Dask, distributed, zarr, matplotlib) took ~1 s
    (docs/decisions/painting.md, "The batch's fixed costs (small tiles)"). The interpreter ends as usual
    (its threads joined, every ``atexit`` handler run once, stdout and stderr flushed), and at the garbage
    collection that starts its teardown the process ends. (An ``atexit`` handler cannot be the last one
    to run: handlers registered before it run after it.) A process whose garbage collector is off at its
    exit ends as usual. For the batch's own local worker processes (status 0: a worker ends so when it
    closes; never a ``--scheduler`` cluster's) and the batch's process from the console entry (its status).
    """
    import gc
    import sys

    def _at_teardown(phase, info):
        if phase == "start" and sys.is_finalizing():
            for stream in (sys.stdout, sys.stderr):
                with contextlib.suppress(Exception):
                    stream.flush()
            os._exit(int(status))

    gc.callbacks[:] = [cb for cb in gc.callbacks if getattr(cb, "__qualname__", "") != _at_teardown.__qualname__]
    gc.callbacks.append(_at_teardown)
