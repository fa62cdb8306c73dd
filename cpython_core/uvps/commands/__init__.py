"""The registry of the commands of the CLI (``uvps <command>``) and the file bridge (``uvps bridge``).

Each command is declared once, as a :class:`uvps.spec.CommandSpec` beside its function, in the module
of its stage: the capture commands, integrate, relight and demo in :mod:`uvps.commands.capture`; the
protrusion commands in :mod:`uvps.commands.protrusions`; ``info`` in :mod:`uvps.files.runfolder`; ``ome-zarr`` in :mod:`uvps.files.omezarr`; ``batch``
in :mod:`uvps.commands.batch`; ``changes`` in :mod:`uvps.core.changes`; ``calibrate`` in :mod:`uvps.commands.calibrate`; ``elements`` in
:mod:`uvps.commands.elements`. :data:`COMMANDS` maps every name (and
alias) to its spec. This module only collects: no command module imports it.
"""
from __future__ import annotations

from . import batch, calibrate, capture, changes, elements, info, ome_zarr, protrusions

#: The modules that declare commands (a ``SPECS`` tuple each). A command added to one of them is
#: registered; a new module is added here.
MODULES = (capture.SPECS, protrusions.SPECS, info.SPECS, ome_zarr.SPECS, batch.SPECS, changes.SPECS,
           calibrate.SPECS, elements.SPECS)


def _registry() -> dict:
    out = {}
    for specs in MODULES:
        for s in specs:
            for name in (s.name,) + tuple(s.aliases):
                if name in out:
                    raise RuntimeError(f"command {name!r} declared twice")
                out[name] = s
    return out


#: Every command by name (aliases included): ``COMMANDS["run"](inputs, params, output_dir)``.
COMMANDS = _registry()
