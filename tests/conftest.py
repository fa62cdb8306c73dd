"""Markers shared by the whole suite: the real-ImageJ tests (each starts a JVM) count as slow, so
``python -m pytest -m "not slow"`` is the quick suite (core, bridge and CLI) for everyday work; and
``ctrl_c``, Ctrl-C as a terminal delivers it, for the tests that send SIGINT."""
import signal

import pytest


@pytest.fixture
def ctrl_c():
    """SIGINT raises KeyboardInterrupt in this process and in the processes it starts, as at a terminal.

    A suite started in the background by a shell without job control (``cmd &`` in a script, some CI
    runners) inherits SIGINT ignored, and Python then leaves it ignored in every process it starts:
    a test of what Ctrl-C does would see the run finish. A Python handler here resets to the default
    in a child at exec, where Python installs its own again."""
    old = signal.signal(signal.SIGINT, signal.default_int_handler)
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, old)


def pytest_collection_modifyitems(config, items):
    for item in items:
        if item.get_closest_marker("imagej") is not None:
            item.add_marker(pytest.mark.slow)
