"""The registry of the commands of the CLI (``uvps <command>``) and the file bridge (``uvps bridge``).

Each command is declared once, as a :class:`uvps.spec.CommandSpec` beside its function, in the module
of its stage: the capture commands, integrate, relight and demo in :mod:`uvps.commands.capture`; the
protrusion commands in :mod:`uvps.commands.protrusions`; ``info`` and ``lamps`` in :mod:`uvps.commands.info`;
``ome-zarr`` in :mod:`uvps.commands.ome_zarr`; ``batch`` in :mod:`uvps.commands.batch`; ``changes`` in
:mod:`uvps.commands.changes`; ``calibrate`` in :mod:`uvps.commands.calibrate`; ``elements`` in
:mod:`uvps.commands.elements`. :data:`COMMANDS` maps every name (and alias) to its spec. This module only
collects: no command module imports it at import time.

The command modules are imported when a command is first asked for (``COMMANDS[name]`` imports the one
module that declares it, :data:`DECLARED_IN`; iterating imports them all): importing every one took
1.4 s of each ``uvps`` command, ``uvps calibrate``'s own 1.0 s.
"""
from __future__ import annotations

import importlib
from collections.abc import MutableMapping

#: The modules that declare commands (a ``SPECS`` tuple each), in the order of the CLI's listing. A
#: command added to one of them is added to :data:`DECLARED_IN` too; a new module is added here.
MODULE_NAMES = ("capture", "protrusions", "info", "ome_zarr", "batch", "changes", "calibrate", "elements")

#: Every command name and alias, and the module that declares it (building :data:`COMMANDS` whole
#: checks this against the modules' declarations).
DECLARED_IN = {
    "run": "capture", "flatfield": "capture", "lights": "capture", "normals": "capture", "integrate": "capture",
    "relight": "capture", "demo": "capture",
    "detect": "protrusions", "wand": "protrusions", "regions": "protrusions", "stats": "protrusions",
    "report": "protrusions", "compare": "protrusions",
    "info": "info", "lamps": "info",
    "ome-zarr": "ome_zarr",
    "batch": "batch",
    "changes": "changes",
    "calibrate": "calibrate",
    "elements": "elements",
}


def _specs(module: str) -> tuple:
    return importlib.import_module(f"{__name__}.{module}").SPECS


def _registry() -> dict:
    out = {}
    for module in MODULE_NAMES:
        for s in _specs(module):
            for name in (s.name,) + tuple(s.aliases):
                if name in out:
                    raise RuntimeError(f"command {name!r} declared twice")
                if DECLARED_IN.get(name) != module:
                    raise RuntimeError(f"command {name!r} is declared in uvps.commands.{module}; "
                                       f"DECLARED_IN says {DECLARED_IN.get(name)!r}")
                out[name] = s
    missing = set(DECLARED_IN) - set(out)
    if missing:
        raise RuntimeError(f"DECLARED_IN names commands no module declares: {sorted(missing)}")
    return out


class _Registry(MutableMapping):
    """Name (or alias) -> :class:`uvps.spec.CommandSpec`, importing a command's module when it is
    first asked for; iteration, ``len`` and ``in`` on an unknown name build the whole registry. A
    spec set by name (a test's stand-in) takes the declared one's place until it is deleted."""

    def __init__(self):
        self._all = None
        self._set = {}

    def _whole(self) -> dict:
        if self._all is None:
            self._all = _registry()
        return {**self._all, **self._set}

    def __getitem__(self, name):
        if name in self._set:
            return self._set[name]
        if self._all is None and name in DECLARED_IN:
            for s in _specs(DECLARED_IN[name]):
                if name == s.name or name in s.aliases:
                    return s
        return self._whole()[name]

    def __setitem__(self, name, spec):
        self._set[name] = spec

    def __delitem__(self, name):
        del self._set[name]

    def __contains__(self, name):
        return name in self._set or name in DECLARED_IN or name in self._whole()

    def __iter__(self):
        return iter(self._whole())

    def __len__(self):
        return len(self._whole())


#: Every command by name (aliases included): ``COMMANDS["run"](inputs, params, output_dir)``.
COMMANDS = _Registry()


def __getattr__(name):
    # MODULES: every module's SPECS (imports them all)
    if name == "MODULES":
        return tuple(_specs(m) for m in MODULE_NAMES)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
