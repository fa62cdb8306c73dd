"""How many threads a stage's own parallel work may take: the CPUs this process may use, capped.

The stages split their per-pixel work over threads (the normals' bands, :mod:`uvps.core.stereo`; the lamp
refinement's pixels, :mod:`uvps.core.lights`): compiled kernels, numpy and BLAS release the GIL there.
Their count is the CPUs the process may run on (``os.sched_getaffinity``: a ``taskset`` or a container's
limit counts), at most the stage's own cap, and at most ``UVPS_THREADS`` when that is set in the
environment: ``uvps batch``'s local worker processes set it to 1, so each capture keeps to its one
thread and ``--workers 2`` takes 2 cores, not 4. BLAS's own threads are set apart (``uvps._entry``).
"""
from __future__ import annotations

import os

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
