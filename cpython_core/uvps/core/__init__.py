"""The numeric library: arrays and dataclasses in, arrays and dataclasses out.

Nothing here reads or writes files, parses command lines or knows a command, a ``Param`` or a report
(``tests/test_layers.py`` holds that). Progress goes through an optional ``progress(fraction,
message)`` callback (:mod:`uvps.core.progress`), messages through ``logging``. The layers are drawn in
``docs/architecture.md``.
"""
