"""How many threads a stage's own parallel work may take: the CPUs this process may use, capped.

The stages split their per-pixel work over threads (the normals' bands, :mod:`uvps.core.stereo`; the lamp
refinement's pixels, :mod:`uvps.core.lights`): compiled kernels, numpy and BLAS release the GIL there.
Their count is the CPUs the process may run on (``os.sched_getaffinity``: a ``taskset`` or a container's
limit counts), at most the stage's own cap, and at most ``UVPS_THREADS`` when that is set in the
environment: ``uvps batch``'s local worker processes set it to 1, so each capture keeps to its one
thread and ``--workers 2`` takes 2 cores, not 4. BLAS's own threads are set apart (``uvps._entry``).
Independent steps of one stage run side by side with :func:`concurrently` (the detection's cues and
surface, :mod:`uvps.core.detect`); a stage's rows, pixels or images cut into bands run with
:func:`map_bands`.
"""
from __future__ import annotations

import os
import sys
import threading
from concurrent.futures import ThreadPoolExecutor

import numpy as np

#: Environment variable capping every stage's threads (a positive integer).
THREADS_VARIABLE = "UVPS_THREADS"

# how deep the running thread is in a parallel part of concurrently / map_bands (0: in none); the pools'
# threads start at 1 (their initializer): a map_bands called there runs in one thread
_INSIDE = threading.local()


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
    ``concurrently`` (the detector's surface inside its steps) can have one more thread busy; one that
    calls :func:`map_bands` runs its bands in its one thread.
    """
    n = min(len(calls), default_threads(len(calls)))
    if n <= 1:
        return [call() for call in calls]
    with ThreadPoolExecutor(n - 1, thread_name_prefix="uvps-step", initializer=_enter) as pool:
        rest = [pool.submit(call) for call in calls[1:]]
        try:
            _enter()
            first = calls[0]()
        finally:
            _INSIDE.depth -= 1
            done = [f.exception() for f in rest]        # wait for all, whatever the first did
        bad = next((e for e in done if e is not None), None)
        if bad is not None:
            raise bad
        return [first] + [f.result() for f in rest]


def map_bands(func, n: int, *, size=None, parts=None, step: int = 1, threads=None, first_alone: bool = False,
              each=None) -> list:
    """``[func(band) for band in bands]``: ``n`` rows (or pixels, or images) cut into bands, the bands
    run on a pool of threads, the results in the bands' order.

    Parameters
    ----------
    func : callable
        ``func(band)`` with ``band`` a ``slice(r0, r1)`` of ``range(n)``; its work should release the GIL
        (numpy, BLAS, numba's ``nogil`` kernels, file reads) and each band should write only its own
        part of any shared output.
    n : int
        Rows (or pixels, or images) to cut.
    size : int, optional
        Rows per band (the last band the rest): the bands are the same whatever the thread count.
    parts : int, optional
        Bands instead, of equal rows to one (``np.linspace`` edges), at most one per row of the grid.
        Exactly one of ``size`` and ``parts`` is given.
    step : int
        Bands start on the grid of every ``step``-th row (the last ends at ``n``), so a band's
        ``r0:r1:step`` rows are those of ``0:n:step``; ``size`` and ``parts`` count the grid's rows.
    threads : int, optional
        Threads in all, this one included (default :func:`default_threads` of the number of bands: the
        usable CPUs and ``UVPS_THREADS``). A stage passes its own cap (``default_threads(4)``) or
        the count it was asked for. One thread, one band, or a call from inside another
        :func:`map_bands` or :func:`concurrently`'s parallel part: every band in this thread, in order.
    first_alone : bool
        The first band runs in this thread before any other starts: a numba kernel's first call types
        it, and two threads making that call at once can fail to ("Unknown attribute 'shape'").
    each : callable, optional
        ``each(band, result)`` in this thread and in the bands' order once a band and all before it
        have ended (a progress report).

    Returns
    -------
    list
        ``func``'s results in the bands' order: a sum over them in that order is the same to the bit
        whatever the thread count when ``size`` fixes the bands (``tests/test_threads.py``).

    Notes
    -----
    This thread takes bands as the pool's ``threads - 1`` threads do, from one queue, so the threads
    stay busy to the last band. An exception in a band stops the bands not yet begun; once the begun
    ones have ended it is raised (the earliest band's, when several failed). Hand-written over
    :class:`concurrent.futures.ThreadPoolExecutor`: its ``map`` keeps this thread idle, queues every
    band at once, and does not type a kernel first.
    """
    bands = _cut(int(n), size, parts, max(1, int(step)))
    out = [None] * len(bands)
    start = 0
    if first_alone and bands:
        out[0] = func(bands[0])
        if each is not None:
            each(bands[0], out[0])
        start = 1
    threads = default_threads(len(bands)) if threads is None else max(1, int(threads))
    t = min(threads, len(bands) - start)
    if t <= 1 or getattr(_INSIDE, "depth", 0) > 0:
        for i in range(start, len(bands)):
            out[i] = func(bands[i])
            if each is not None:
                each(bands[i], out[i])
        return out
    _shared_queue(func, bands, out, start, t, each)
    return out


def _shared_queue(func, bands, out, start, t, each) -> None:
    """:func:`map_bands`'s parallel part: bands ``start:`` into ``out`` by this thread and ``t - 1`` others."""
    lock = threading.Lock()
    todo = iter(range(start, len(bands)))
    failed = {}                          # band index -> its exception; len(bands): each's exception
    ended = [i < start for i in range(len(bands))]
    reported = [start]

    def take():
        while True:
            with lock:
                i = None if failed else next(todo, None)
            if i is None:
                return
            try:
                out[i] = func(bands[i])
            except BaseException as e:   # noqa: BLE001 - raised by map_bands once the others end
                with lock:
                    failed[i] = e
                return
            ended[i] = True
            if each is not None and threading.current_thread() is caller:
                _report(each, bands, out, ended, reported)

    caller = threading.current_thread()
    with ThreadPoolExecutor(t - 1, thread_name_prefix="uvps-band", initializer=_enter) as pool:
        helpers = [pool.submit(take) for _ in range(t - 1)]
        _enter()
        try:
            take()
        except BaseException as e:       # noqa: BLE001 - each's: the others take no more bands
            with lock:
                failed[len(bands)] = e
        finally:
            _INSIDE.depth -= 1
    for f in helpers:
        f.result()
    if failed:
        raise failed[min(failed)]
    if each is not None:
        _report(each, bands, out, ended, reported)


def _report(each, bands, out, ended, reported) -> None:
    """``each`` of the bands ended since the last report, in order, up to the first not ended."""
    i = reported[0]
    while i < len(bands) and ended[i]:
        each(bands[i], out[i])
        i += 1
        reported[0] = i


def _cut(n: int, size, parts, step: int) -> list:
    """:func:`map_bands`'s bands: slices of ``range(n)`` starting on the grid of every ``step``-th row."""
    if (size is None) == (parts is None):
        raise ValueError("map_bands: give one of size and parts")
    grid = len(range(0, n, step))
    if size is not None:
        size = max(1, int(size))
        return [slice(step * g, min(n, step * (g + size))) for g in range(0, grid, size)]
    edges = step * np.linspace(0, grid, max(1, min(int(parts), grid)) + 1).astype(int)
    edges[-1] = n
    return [slice(int(a), int(b)) for a, b in zip(edges[:-1], edges[1:])]


def _enter() -> None:
    """Mark this thread as inside a parallel part (:func:`map_bands` then runs its bands in it alone)."""
    _INSIDE.depth = getattr(_INSIDE, "depth", 0) + 1


class Background:
    """Zero-argument ``jobs`` taken in order from one queue by ``threads`` daemon threads at the lowest scheduling
    priority (:func:`lowest_priority`) and, once :meth:`results` is called, by the calling thread at its own.

    For work a run needs only at its end (run.json's input hashes, :class:`uvps.files.io.InputHashes`): it takes the
    cores the run's own stages leave idle (imports, one-thread steps) instead of a share of their two threads, and
    a run whose cores other processes hold (a batch's workers on every core) does what the threads have not begun
    itself, waiting only for the jobs they have. Daemon threads: a run that fails does not wait for them at exit.
    """

    def __init__(self, jobs, *, threads: int = 2, name: str = "uvps-background"):
        self._jobs = list(jobs)
        self._results = [None] * len(self._jobs)
        self._errors = {}
        self._lock = threading.Lock()
        self._next = 0
        self._threads = [threading.Thread(target=self._work, args=(True,), daemon=True, name=f"{name}-{i}")
                         for i in range(max(0, min(int(threads), len(self._jobs))))]
        for t in self._threads:
            t.start()

    def _work(self, low: bool) -> None:
        if low:
            lowest_priority()
        while True:
            with self._lock:
                i, self._next = self._next, self._next + 1
            if i >= len(self._jobs):
                return
            try:
                self._results[i] = self._jobs[i]()
            except BaseException as e:      # noqa: BLE001 - raised by results(), in the caller
                self._errors[i] = e

    def results(self) -> list:
        """The jobs' results in their order, once all are done (this thread takes those not begun); the earliest
        job's error raised."""
        self._work(False)
        for t in self._threads:
            t.join()
        if self._errors:
            raise self._errors[min(self._errors)]
        return list(self._results)


def lowest_priority() -> None:
    """This thread at the lowest scheduling priority (nice 19), on Linux, where a thread has its own (the threads it
    starts inherit it); elsewhere (``setpriority`` takes a process id there) nothing."""
    if sys.platform.startswith("linux"):
        try:
            os.setpriority(os.PRIO_PROCESS, threading.get_native_id(), 19)
        except Exception:       # noqa: BLE001 - a priority refused leaves the thread at its own
            pass
