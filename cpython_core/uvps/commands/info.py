"""``uvps info RUN``: what a run folder holds, its parameters, lights and warnings (nothing is written)."""
from __future__ import annotations

from ..files.outputs import CommandResult, Progress
from ..files.runfolder import describe, relief_of
from ..spec import CommandSpec, Param


def info_text(info: dict) -> str:
    """:func:`describe`'s answer as lines for a terminal or ImageJ's Log."""
    opts = {k: v for k, v in info["params"].items() if v is not None and v is not False
            and k not in ("image_shape", "pixel_size_um", "bit_depth", "options")}
    lines = [f"run folder: {info['run_dir']}",
             f"made by:    uvps {info['command']} (version {info['version']})",
             f"files:      {', '.join(info['files'])}"]
    if "image_shape" in info["params"]:
        shape = info["params"]["image_shape"]
        lines.append(f"capture:    {shape[0]} x {shape[1]} px{f' x {shape[2]} channels' if len(shape) > 2 else ''} of "
                     f"{info['params'].get('pixel_size_um')} um, {info['lights'].get('n_lights', '?')} lights "
                     f"({info['lights'].get('source', '?')})")
    if opts:
        lines.append("parameters: " + ", ".join(f"{k}={v}" for k, v in sorted(opts.items())))
    relief = info.get("relief") or relief_of({})
    if relief["scale"] == "relative":
        lines.append(f"relief:     RELATIVE: heights have no scale in micrometres ({relief['reason']})")
    elif relief.get("lamps"):
        lines.append(f"relief:     absolute (lamps: {relief['lamps']})")
    if "height_uncertainty_relative_95" in info["lights"]:
        lines.append(f"heights:    uncertain by +-{100 * info['lights']['height_uncertainty_relative_95']:.1f} % "
                     "(95 %, from the estimated lamps)")
    elif "height_uncertainty_relative" in info["lights"]:
        lines.append(f"heights:    uncertain by +-{100 * info['lights']['height_uncertainty_relative']:.1f} % "
                     "(from the estimated lamps)")
    if "detection" in info:
        det = info["detection"]
        lines.append(f"protrusions: {det['kept']} kept of {det['candidates']} candidates "
                     f"({det['candidates'] - det['kept']} rejected by the detection's rules)")
    elif "n_protrusions" in info:
        lines.append(f"protrusions: {info['n_protrusions']}")
    lines += [f"warning:    {w}" for w in info["warnings"]] or ["warnings:   none"]
    return "\n".join(lines)


def cmd_info(inputs: dict, params: dict, output_dir, *, progress: Progress = None) -> CommandResult:
    """``info``: what a run folder holds, its parameters and warnings (nothing is written)."""
    info = describe(inputs["run"])
    return CommandResult([], info, [], text=info_text(info))


SPECS = (
    CommandSpec("info", "what a run folder holds: files, parameters, lights, warnings", cmd_info, menu="Run Info", output="",
                params=(Param("run", "path", where="inputs", positional=True, required=True,
                              label="Run folder", help="the run folder to describe"),)),
)
