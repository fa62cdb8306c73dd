"""What a run folder holds: ``uvps info RUN`` (its files, parameters, lights and warnings; nothing
is written) and ``uvps lamps RUN -o OUT`` (its lamps for other tools: an RTI ``.lp`` and a CSV)."""
from __future__ import annotations

from pathlib import Path

import numpy as np

from ..errors import UVPSInputError
from ..files.io import read_positions
from ..files.outputs import CommandResult, OutputSpec, Progress, atomic_output_dir
from ..files.runfolder import describe, earlier_line, relief_of
from ..spec import CommandSpec, Param


def raw_lines(raw) -> list:
    """run.json's ``diagnostics.raw`` (camera raw files, :func:`uvps.files.io.raw_reading`) in words: one line per
    distinct camera and levels."""
    if not raw:
        return []
    out = []
    for lv in raw.get("levels", []):
        black = lv["black_level"]
        black = f"{black[0]:g}" if len(set(black)) == 1 else "/".join(f"{b:g}" for b in black) + " (per channel)"
        sat = lv.get("saturation_level", lv["white_level"])
        crop = lv.get("default_crop_px")
        matrix = any(any(v != 0 for v in row[:3]) for row in lv.get("colour_matrix") or [])
        out.append(f"{lv.get('camera') or 'camera not named'}, {lv.get('cfa', '')} mosaic, black {black}, white "
                   f"{lv['white_level']:g}, saturation {sat:g} ({sat - max(lv['black_level']):g} counts above black)"
                   + (f", DefaultCrop {crop[0]}, {crop[1]}, {crop[2]} x {crop[3]} applied" if crop else "")
                   + ("; colour matrix recorded, not applied" if matrix else "; no colour matrix"))
    return out + ([f"read by {raw['reader']}"] if raw.get("reader") else [])


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
    lines += [f"raw files:  {line}" for line in raw_lines(info.get("raw"))]
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
    if info.get("level"):
        lines.append(f"levelling:  {info['level']}")
    if "detection" in info:
        det = info["detection"]
        lines.append(f"protrusions: {det['kept']} kept of {det['candidates']} candidates "
                     f"({det['candidates'] - det['kept']} rejected by the detection's rules)")
    elif "n_protrusions" in info:
        lines.append(f"protrusions: {info['n_protrusions']}")
    if info.get("manual"):
        m = info["manual"]
        lines.append(f"manual:     protrusions_manual.csv: {m['counted']} counted of {m['clicks']} clicks (this run)")
    for item in info.get("earlier") or ():
        lines.append(f"earlier:    {earlier_line(item)}")
    lines += [f"warning:    {w}" for w in info["warnings"]] or ["warnings:   none"]
    return "\n".join(lines)


def cmd_info(inputs: dict, params: dict, output_dir, *, progress: Progress = None) -> CommandResult:
    """``info``: what a run folder holds, its parameters and warnings (nothing is written)."""
    info = describe(inputs["run"])
    return CommandResult([], info, [], text=info_text(info))


#: What ``lamps`` writes: the directions as an RTI light file, the positions (near lamps) as a CSV.
LAMP_FILES = ("lamps.lp", "lamps_mm.csv")


def cmd_lamps(inputs: dict, params: dict, output_dir, *, progress: Progress = None) -> CommandResult:
    """``lamps``: the lamps of a run or calibration folder (its ``lights.json``) as ``lamps.lp``
    (``K``, then ``file x y z``: unit directions toward the lamps, RTI Builder and relight read it)
    and, when the lamps are near ones, ``lamps_mm.csv`` (``file,x_mm,y_mm,z_mm,intensity``: mm from
    the image centre, x right, y up, z toward the camera). Both are read back by ``--lights``."""
    src = Path(inputs["run"])
    path = src / "lights.json" if src.is_dir() else src
    if not path.is_file():
        raise UVPSInputError(f"run: {src} holds no lights.json (expected a run folder, a calibration "
                             "folder or a lights.json)")
    lamps = read_positions(path)
    D = lamps.directions
    if D is None:
        D = lamps.positions_mm / np.linalg.norm(lamps.positions_mm, axis=1, keepdims=True)
    k = len(D)
    names = [Path(f).name if f else f"lamp_{i + 1:02d}" for i, f in enumerate(lamps.files or [None] * k)]
    lp = [str(k)] + [f"{n} {d[0]:.8f} {d[1]:.8f} {d[2]:.8f}" for n, d in zip(names, D)]
    out = Path(output_dir)
    written = [out / LAMP_FILES[0]]
    with atomic_output_dir(out) as tmp:
        (tmp / LAMP_FILES[0]).write_text("\n".join(lp) + "\n", encoding="utf-8")
        if lamps.positions_mm is not None:
            E = lamps.intensities if lamps.intensities is not None else np.ones(k)
            rows = ["file,x_mm,y_mm,z_mm,intensity"] + [f"{n},{p[0]:.6f},{p[1]:.6f},{p[2]:.6f},{e:.6f}"
                                                        for n, p, e in zip(names, lamps.positions_mm, E)]
            (tmp / LAMP_FILES[1]).write_text("\n".join(rows) + "\n", encoding="utf-8")
            written.append(out / LAMP_FILES[1])
    outputs = [OutputSpec(w.stem, str(w), kind="table") for w in written]
    return CommandResult(outputs, {"n_lamps": k, "near": lamps.positions_mm is not None, "source": str(path)}, [],
                         text="\n".join(str(w) for w in written))


SPECS = (
    CommandSpec("info", "what a run folder holds: files, parameters, lights, warnings", cmd_info, menu="Run Info", output="",
                params=(Param("run", "path", where="inputs", positional=True, required=True,
                              label="Run folder", help="the run folder to describe"),)),
    CommandSpec("lamps", "a run's or calibration's lamps as an RTI .lp and a positions CSV", cmd_lamps,
                menu="Export Lamps", output="folder for lamps.lp and lamps_mm.csv",
                params=(Param("run", "path", where="inputs", positional=True, required=True,
                              label="Run or calibration folder",
                              help="a run folder, a calibration folder or a lights.json"),)),
)
