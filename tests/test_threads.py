"""uvps.core.threads.concurrently: independent steps side by side, their results in order, the same
whatever the thread count; and the run's detection (its steps side by side) the same in one thread
and in two. uvps.core.threads.map_bands: its bands, their results in order, a sum over them the same
to the bit whatever the thread count, its exceptions, its one-thread path and its nesting."""
import threading

import numpy as np
import pytest

from uvps.core import threads
from uvps.core.threads import concurrently, map_bands


def test_concurrently_returns_the_results_in_order(monkeypatch):
    calls = (lambda: 1, lambda: "two", lambda: [3])
    assert concurrently(*calls) == [1, "two", [3]]
    monkeypatch.setenv(threads.THREADS_VARIABLE, "1")
    assert concurrently(*calls) == [1, "two", [3]]
    assert concurrently() == []


def test_concurrently_runs_the_calls_side_by_side_with_two_threads(monkeypatch):
    """Two calls that each wait for the other finish only when they run at the same time."""
    monkeypatch.setattr(threads, "default_threads", lambda most: min(most, 2))
    meet = threading.Barrier(2, timeout=10)
    assert concurrently(lambda: meet.wait() * 0 + 1, lambda: meet.wait() * 0 + 2) == [1, 2]


def test_concurrently_one_after_the_other_with_one_thread(monkeypatch):
    monkeypatch.setenv(threads.THREADS_VARIABLE, "1")
    seen = []
    concurrently(lambda: seen.append(threading.get_ident()), lambda: seen.append(threading.get_ident()))
    assert seen == [threading.get_ident()] * 2


def test_concurrently_raises_once_every_call_has_ended(monkeypatch):
    monkeypatch.setattr(threads, "default_threads", lambda most: min(most, 2))
    ended = threading.Event()

    def slow():
        ended.wait(0.2)
        ended.set()
        return 0

    with pytest.raises(ZeroDivisionError):
        concurrently(lambda: 1 / 0, slow)
    assert ended.is_set()
    with pytest.raises(KeyError):
        concurrently(slow, lambda: {}["x"])


def test_detection_the_same_in_one_and_two_threads(monkeypatch):
    """find_protrusions with areas proposed (the areas beside the detection's height, the albedo
    cue beside the surface, the noise beside the weave, the curvature beside the peaks): labels,
    areas and table equal to the bit in one thread and in two."""
    from uvps.core.pipeline import find_protrusions
    from uvps.testing.synthetic import SyntheticSpec, make_capture

    spec = SyntheticSpec.realistic("top", shape=(300, 400), seed=1)
    cap = make_capture(spec, n_lights=3, noise=False, cast_shadows=False)
    got = {}
    for n in (1, 2):
        monkeypatch.setattr(threads, "default_threads", lambda most, n=n: min(most, n))
        got[n] = find_protrusions(cap.albedo, cap.height_um, cap.normals, pixel_size_um=spec.pixel_size_um,
                                  regions="auto")
    one, two = got[1], got[2]
    assert one.labels.max() >= 3 and one.regions.labels.max() >= 2 and sum(one.rejected.values()) > 50
    np.testing.assert_array_equal(one.labels, two.labels)
    np.testing.assert_array_equal(one.regions.labels, two.regions.labels)
    assert one.rejected == two.rejected and one.noise_um == two.noise_um
    assert sorted(one.table) == sorted(two.table)
    for k in one.table:
        np.testing.assert_array_equal(np.asarray(one.table[k]), np.asarray(two.table[k]), err_msg=k)


def _span(rows):
    return (rows.start, rows.stop)


def test_map_bands_cuts_as_asked():
    """``size``: fixed rows, the last band the rest; ``parts``: np.linspace edges; ``step``: bands on the
    grid of every step-th row, the last ending at n."""
    assert map_bands(_span, 10, size=4, threads=1) == [(0, 4), (4, 8), (8, 10)]
    assert map_bands(_span, 10, parts=3, threads=1) == [(0, 3), (3, 6), (6, 10)]
    assert map_bands(_span, 2, parts=4, threads=1) == [(0, 1), (1, 2)]          # one row per band at most
    assert map_bands(_span, 11, parts=2, step=3, threads=1) == [(0, 6), (6, 11)]   # grid 0 3 6 9
    assert map_bands(_span, 3, parts=2, step=3, threads=1) == [(0, 3)]            # one grid row: one band
    assert map_bands(_span, 0, size=4) == []
    with pytest.raises(ValueError):
        map_bands(_span, 10, threads=1)
    with pytest.raises(ValueError):
        map_bands(_span, 10, size=2, parts=2)


def test_map_bands_returns_the_results_in_order_whatever_the_thread_count():
    """Bands that end in the reverse of their order still come back in their order, and ``each`` sees
    them in order, in the calling thread."""
    me = threading.get_ident()
    for n_threads in (1, 2, 3, 8):
        seen = []

        def slow_first(rows):
            threading.Event().wait(0.002 * (20 - rows.start))
            return rows.start * 10

        def each(rows, result):
            assert threading.get_ident() == me
            seen.append((rows.start, result))

        got = map_bands(slow_first, 20, size=1, threads=n_threads, each=each)
        assert got == [10 * k for k in range(20)]
        assert seen == [(k, 10 * k) for k in range(20)]


def test_map_bands_sum_the_same_to_the_bit_whatever_the_thread_count():
    """Float sums over fixed bands, added in the bands' order: the same bits in 1, 2, 3 and 5 threads,
    and different from the sum over other bands (so the test can tell)."""
    x = np.random.default_rng(3).standard_normal(100_003) * 10.0 ** np.random.default_rng(4).integers(-8, 8, 100_003)

    def total(n_threads, size=1000):
        return sum(map_bands(lambda rows: float(np.sum(x[rows])), x.size, size=size, threads=n_threads))

    one = total(1)
    assert all(total(n).hex() == one.hex() for n in (2, 3, 5))
    assert total(1, size=997).hex() != one.hex()


def test_map_bands_runs_the_bands_side_by_side(monkeypatch):
    """Two bands that each wait for the other end only when they run at the same time; the default
    threads are default_threads' (monkeypatched to 2)."""
    monkeypatch.setattr(threads, "default_threads", lambda most: min(most, 2))
    meet = threading.Barrier(2, timeout=10)
    assert map_bands(lambda rows: meet.wait() * 0 + rows.start, 2, size=1) == [0, 1]


def test_map_bands_one_thread_in_order_in_this_thread(monkeypatch):
    """UVPS_THREADS=1 (or threads=1): every band in the calling thread, one after the other."""
    monkeypatch.setenv(threads.THREADS_VARIABLE, "1")
    order = []
    assert map_bands(lambda rows: order.append((rows.start, threading.get_ident())) or rows.start, 5,
                     size=2) == [0, 2, 4]
    assert order == [(0, threading.get_ident()), (2, threading.get_ident()), (4, threading.get_ident())]


def test_map_bands_first_alone_ends_before_the_others_begin():
    log = []

    def band(rows):
        log.append(("begin", rows.start))
        threading.Event().wait(0.01)
        log.append(("end", rows.start))

    map_bands(band, 4, size=1, threads=3, first_alone=True)
    assert log[:2] == [("begin", 0), ("end", 0)] and len(log) == 8


def test_map_bands_raises_the_earliest_failed_band_once_the_begun_have_ended():
    """A failing band stops the bands not begun; the exception is raised after the running ones end."""
    ended = threading.Event()
    begun = []

    def band(rows):
        begun.append(rows.start)
        if rows.start == 0:
            ended.wait(0.2)              # band 1 fails meanwhile
            ended.set()
            return 0
        if rows.start == 1:
            raise KeyError(rows.start)
        return rows.start

    with pytest.raises(KeyError):
        map_bands(band, 50, size=1, threads=2)
    assert ended.is_set() and len(begun) < 50
    with pytest.raises(ZeroDivisionError):      # the earlier band's exception when two fail
        map_bands(lambda rows: 1 / 0 if rows.start == 0 else {}[rows.start], 2, size=1, threads=2)
    with pytest.raises(ZeroDivisionError):      # and in one thread
        map_bands(lambda rows: 1 / rows.start, 3, size=1, threads=1)


def test_map_bands_inside_concurrently_keeps_to_its_thread(monkeypatch):
    """Called from either side of concurrently's parallel part (or from a band), map_bands runs its bands
    in the thread it is called from: no more threads busy than concurrently's."""
    monkeypatch.setattr(threads, "default_threads", lambda most: min(most, 2))

    def bands_threads():
        me = threading.get_ident()
        return set(map_bands(lambda rows: threading.get_ident(), 4, size=1, threads=4)) == {me}

    assert concurrently(bands_threads, bands_threads) == [True, True]
    assert all(map_bands(lambda rows: bands_threads(), 2, size=1, threads=2))
    assert len(set(map_bands(lambda rows: threading.Event().wait(0.01) or threading.get_ident(), 4, size=1,
                             threads=2))) == 2       # outside: both threads


def test_background_jobs_give_their_results_in_order_and_the_earliest_error():
    """Background: every job's result in the jobs' order (whoever ran it); a job's error is raised by results()
    (the earliest job's)."""
    import time

    jobs = [lambda i=i: (time.sleep(0.01 * (i % 3)), i * i)[1] for i in range(12)]
    assert threads.Background(jobs, threads=2).results() == [i * i for i in range(12)]
    assert threads.Background(jobs, threads=0).results() == [i * i for i in range(12)]    # the caller alone

    def bad(i):
        raise ValueError(f"job {i}")

    with pytest.raises(ValueError, match="job 3"):
        threads.Background([lambda: 0, lambda: 1, lambda: 2, lambda: bad(3), lambda: bad(5)], threads=2).results()
