"""The registry of the commands of the CLI (``uvps <command>``) and the file bridge (``uvps bridge``).

Each command is declared once, as a :class:`uvps.spec.CommandSpec` beside its function, in the module
of its stage: the capture commands, integrate, relight and demo in :mod:`uvps.capture_commands`; the
protrusion commands in :mod:`uvps.protrusion_commands`; ``info`` in :mod:`uvps.runfolder`; ``ome-zarr`` in :mod:`uvps.omezarr`; ``batch``
in :mod:`uvps.batch`; ``changes`` in :mod:`uvps.changes`; ``calibrate`` in :mod:`uvps.calibration`; ``elements`` in
:mod:`uvps.element_commands`. :data:`COMMANDS` maps every name (and
alias) to its spec. This module only collects: no command module imports it.
"""
from __future__ import annotations

from . import batch, calibration, capture_commands, changes, element_commands, omezarr, protrusion_commands, runfolder

#: The modules that declare commands (a ``SPECS`` tuple each). A command added to one of them is
#: registered; a new module is added here.
MODULES = (capture_commands.SPECS, protrusion_commands.SPECS, runfolder.SPECS, omezarr.SPECS, batch.SPECS,
           changes.SPECS, calibration.SPECS, element_commands.SPECS)


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
