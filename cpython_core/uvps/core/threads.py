"""How many threads a stage's own parallel work may take: the CPUs this process may use, capped.

The stages split their per-pixel work over threads (the normals' bands, :mod:`uvps.core.stereo`; the lamp
refinement's pixels, :mod:`uvps.core.lights`): compiled kernels, numpy and BLAS release the GIL there.
Their count is the CPUs the process may run on (``os.sched_getaffinity``: a ``taskset`` or a container's
limit counts), at most the stage's own cap, and at most ``UVPS_THREADS`` when that is set in the
environment: ``uvps batch``'s local worker processes set it to 1, so each capture keeps to its one
thread and ``--workers 2`` takes 2 cores, not 4. BLAS's own threads are set apart (``uvps._entry``).
Independent steps of one stage run side by side with :func:`concurrently` (the detection's cues and
surface, :mod:`uvps.core.detect`).
"""
from __future__ import annotations

import os
from concurrent.futures import ThreadPoolExecutor

#: Environment variable capping every stage's threads (a positive integer).
THREADS_VARIABLE = "UVPS_THREADS"


def default_threads(most: int) -> int:
    """Threads for a stage's parallel work: the usable CPUs, at most ``most`` and :data:`THREADS_VARIABLE`."""
    n = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1
    n = min(int(most), n)
    cap = os.environ.get(THREADS_VARIABLE, "").strip()
    if cap.isdigit() and int(cap) > 0:
        n = min(n, int(cap))
    return max(1, n)


def concurrently(*calls) -> list:
    """The results of the zero-argument callables ``calls``, in their order: the first in this thread,
    the others in threads of their own while it runs (at most :func:`default_threads` in all, the rest
    queued), or one after the other when one thread is all there is.

    For independent steps whose work releases the GIL (numpy, scipy.ndimage, OpenCV, numba's ``nogil``
    kernels), each only reading what it shares with the others: every call's arithmetic is its
    one-thread arithmetic, so the results are the same to the bit whatever the thread count
    (``tests/test_threads.py``). An exception in any call is raised once all have ended (the first
    call's own, else the earliest other's). The cap holds per call: a call that itself calls
    ``concurrently`` (the detector's surface inside its steps) can have one more thread busy.
    """
    n = min(len(calls), default_threads(len(calls)))
    if n <= 1:
        return [call() for call in calls]
    with ThreadPoolExecutor(n - 1, thread_name_prefix="uvps-step") as pool:
        rest = [pool.submit(call) for call in calls[1:]]
        try:
            first = calls[0]()
        finally:
            done = [f.exception() for f in rest]        # wait for all, whatever the first did
        bad = next((e for e in done if e is not None), None)
        if bad is not None:
            raise bad
        return [first] + [f.result() for f in rest]
