"""uvps.core.threads.concurrently: independent steps side by side, their results in order, the same
whatever the thread count; and the run's detection (its steps side by side) the same in one thread
and in two."""
import threading

import numpy as np
import pytest

from uvps.core import threads
from uvps.core.threads import concurrently


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
