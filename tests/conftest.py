"""Markers shared by the whole suite: the real-ImageJ tests (each starts a JVM) count as slow, so
``python -m pytest -m "not slow"`` is the quick suite (core, bridge and CLI) for everyday work."""
import pytest


def pytest_collection_modifyitems(config, items):
    for item in items:
        if item.get_closest_marker("imagej") is not None:
            item.add_marker(pytest.mark.slow)
