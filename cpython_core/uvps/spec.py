"""Each command declared once: its parameters, and everything derived from them.

A :class:`CommandSpec` names a command, its inputs and parameters (:class:`Param`: type, default,
choices, unit, help, the Fiji dialog's label) and the function that runs it. From the declarations:

- the ``uvps`` command line (:func:`add_parser`, :func:`request_from_args`; ``uvps.cli``),
- the checking and coercion of every request, from the CLI or the file bridge (:func:`coerce`:
  one-line errors naming the parameter, unknown keys reported, defaults filled in),
- the command table the Fiji side builds its dialogs from (:func:`to_json`, ``uvps spec``),
- the command reference ``docs/commands.md`` (:func:`markdown`; a test regenerates and compares it).

Adding a command is a declaration beside its function (in the module of its stage, listed once in
``uvps.commands.MODULES``), a menu script, and the regenerated reference.

Example
-------
>>> from uvps.spec import CommandSpec, Param, coerce
>>> spec = CommandSpec("hello", "say hello", run=None,
...                    params=(Param("times", "int", 1, help="how often", minimum=1),))
>>> coerce(spec, {}, {"times": "3", "colour": "red"})
({}, {'times': 3}, ["parameter 'colour' ignored (unknown to the command hello)"])
>>> coerce(spec, {}, {"times": 0})
Traceback (most recent call last):
...
uvps.errors.UVPSInputError: times must be an integer >= 1; got 0
"""
from __future__ import annotations

import argparse
import math
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any, Callable, Optional

from .errors import UVPSInputError, check_plausible_pixel_size

#: Parameter types: how a value is checked, coerced, put on the command line and in a dialog.
TYPES = ("str", "int", "float", "bool", "numbers", "path", "paths", "choice", "shape")


@dataclass(frozen=True)
class Param:
    """One input or parameter of a command.

    Attributes
    ----------
    name : str
        The request key (``params`` or ``inputs``) and, with dashes, the CLI flag ``--name``.
    type : str
        One of :data:`TYPES`. ``numbers``: one number or several (a list, or comma-separated);
        ``path``: a file (resolved against the request folder by the bridge); ``paths``: a list;
        ``shape``: two positive integers (rows, columns).
    default : object
        Used when the key is absent or null. ``None`` means "not set" (the command decides).
    help : str
        One line for the CLI, the reference and the dialog's tooltip.
    choices : tuple
        Allowed values (``choice``), or keywords a ``path`` may also be (e.g. ``"auto"``).
    unit : str
        Unit of a number ("um", "mm", "deg", "counts").
    minimum, maximum : float, optional
        Inclusive bounds; ``exclusive_minimum`` makes the lower one strict (e.g. a pixel size > 0).
    required : bool
        The request must give it.
    where : str
        ``"params"`` or ``"inputs"`` (files the command reads: images, points, tables).
    positional : bool
        On the command line a positional argument (``nargs`` "+" for ``paths``).
    label : str
        The Fiji dialog's label; its first word, lower-cased, is the macro key.
    """

    name: str
    type: str
    default: Any = None
    help: str = ""
    choices: tuple = ()
    unit: str = ""
    minimum: Optional[float] = None
    maximum: Optional[float] = None
    exclusive_minimum: bool = False
    required: bool = False
    where: str = "params"
    positional: bool = False
    label: str = ""

    def __post_init__(self):
        if self.type not in TYPES:
            raise ValueError(f"parameter {self.name}: unknown type {self.type!r}")
        if self.where not in ("params", "inputs"):
            raise ValueError(f"parameter {self.name}: where must be 'params' or 'inputs'")

    @property
    def flag(self) -> str:
        """The CLI flag: ``--pixel-size-um``; a bool that defaults to true is ``--no-<name>``."""
        name = self.name.replace("_", "-")
        return f"--no-{name}" if self.type == "bool" and self.default else f"--{name}"


@dataclass(frozen=True)
class CommandSpec:
    """A command: name, one-line help, parameters and the function that runs it.

    ``run(inputs, params, output_dir, *, progress)`` receives the coerced request (every declared
    key present, defaults filled in) and returns a :class:`uvps.files.outputs.CommandResult`. Calling the
    spec coerces first: ``spec(inputs, params, output_dir, progress=None)``.
    """

    name: str
    help: str
    run: Optional[Callable]
    params: tuple = ()
    output: str = "run folder"         # what -o names; "" for commands without an output folder
    output_default: Optional[str] = None   # -o default (None: required)
    aliases: tuple = ()
    description: str = ""
    output_note: str = ""              # what happens to the -o folder's files (default: replaced one by one)
    menu: str = ""                     # its Fiji menu item (Plugins > UV Photometric Stereo), "" for none

    def param(self, name: str) -> Param:
        for p in self.params:
            if p.name == name:
                return p
        raise KeyError(f"{self.name} has no parameter {name!r}")

    def __call__(self, inputs, params, output_dir, *, progress=None):
        inputs, params, warnings = coerce(self, inputs or {}, params or {})
        result = self.run(inputs, params, output_dir, progress=progress)
        result.warnings[:0] = warnings
        return result


def with_defaults(params: tuple, **defaults) -> tuple:
    """``params`` with some defaults replaced (a shared group declared once, tuned per command)."""
    return tuple(replace(p, default=defaults.pop(p.name)) if p.name in defaults else p for p in params)


# ------------------------------------------------------------------------------------------------
# checking and coercion: one place for every "must be a positive number" message
# ------------------------------------------------------------------------------------------------

def _number(p: Param, v, kind=float):
    if isinstance(v, bool):
        raise UVPSInputError(f"{p.name} must be {_expected(p)}; got {v!r}")
    try:
        f = float(v)
    except (TypeError, ValueError):
        raise UVPSInputError(f"{p.name} must be {_expected(p)}; got {v!r}") from None
    if not math.isfinite(f) or (kind is int and f != int(f)):
        raise UVPSInputError(f"{p.name} must be {_expected(p)}; got {v!r}")
    lo_bad = p.minimum is not None and (f <= p.minimum if p.exclusive_minimum else f < p.minimum)
    if lo_bad or (p.maximum is not None and f > p.maximum):
        raise UVPSInputError(f"{p.name} must be {_expected(p)}; got {v!r}")
    if p.name == "pixel_size_um":
        # a size the user typed: refused outside what a photograph of a painting has (mm typed as um)
        check_plausible_pixel_size(f, p.name)
    return int(f) if kind is int else f


def _expected(p: Param) -> str:
    what = {"int": "an integer", "float": "a number", "numbers": "a number or comma-separated numbers",
            "shape": "two positive integers (rows, columns)"}.get(p.type, p.type)
    lo, hi, strict = p.minimum, p.maximum, p.exclusive_minimum
    if lo is not None and hi is not None:
        what += f" above {lo:g} and at most {hi:g}" if strict else f" from {lo:g} to {hi:g}"
    elif p.type == "float" and strict and lo == 0:
        what = "a positive number" + (" (micrometres)" if p.unit == "um" else "")
    elif lo is not None:
        what += f" {'>' if strict else '>='} {lo:g}"
    elif hi is not None:
        what += f" <= {hi:g}"
    return what


def _bool(p: Param, v):
    if isinstance(v, bool):
        return v
    s = str(v).strip().lower()
    if s in ("1", "true", "yes", "on"):
        return True
    if s in ("0", "false", "no", "off", ""):
        return False
    raise UVPSInputError(f"{p.name} must be true or false; got {v!r}")


def coerce_value(p: Param, v):
    """``v`` checked and converted to ``p``'s type; one-line :class:`UVPSInputError` otherwise."""
    t = p.type
    if t == "int":
        return _number(p, v, int)
    if t == "float":
        return _number(p, v)
    if t == "bool":
        return _bool(p, v)
    if t == "numbers":
        items = [y for x in (v if isinstance(v, (list, tuple)) else [v])
                 for y in (str(x).replace(" ", ",").split(",") if isinstance(x, str) else [x])]
        out = [_number(p, x) for x in items if str(x).strip() != ""]
        if not out:
            raise UVPSInputError(f"{p.name} must be {_expected(p)}; got {v!r}")
        return out[0] if len(out) == 1 else out
    if t == "shape":
        items = list(v) if isinstance(v, (list, tuple)) else str(v).replace("x", ",").split(",")
        if len(items) != 2:
            raise UVPSInputError(f"{p.name} must be {_expected(p)}; got {v!r}")
        return tuple(_number(replace(p, minimum=1), x, int) for x in items)
    if t == "choice":
        for c in p.choices:     # 8 from a JSON request is the choice "8"
            if v == c or (not isinstance(v, bool) and str(v) == str(c)):
                return c
        raise UVPSInputError(f"{p.name} must be one of {', '.join(map(str, p.choices))}; got {v!r}")
    if t == "paths":
        items = [v] if isinstance(v, str) else v
        if not isinstance(items, (list, tuple)) or not all(isinstance(x, str) for x in items):
            raise UVPSInputError(f"{p.name} must be a file path or a list of them; got {v!r}")
        return list(items)
    if t in ("path", "str"):
        if not isinstance(v, str):
            # a list where one file is declared (regions as masks, points as [[x, y], ...]) is passed
            # on: the reader of that file checks it
            if t == "path" and isinstance(v, (list, tuple)):
                return list(v)
            raise UVPSInputError(f"{p.name} must be a {'file path' if t == 'path' else 'text'}; got {v!r}")
        return v
    raise AssertionError(t)


def coerce(spec: CommandSpec, inputs: dict, params: dict) -> tuple:
    """Check a request against ``spec``: ``(inputs, params, warnings)`` with every declared key.

    Absent or null keys take their default; a required one raises. Keys the command does not
    declare are reported (one warning each) and dropped.
    """
    warnings = [f"parameter '{k}' ignored (unknown to the command {spec.name})"
                for k in sorted(set(params) - {p.name for p in spec.params if p.where == "params"})]
    warnings += [f"input '{k}' ignored (unknown to the command {spec.name})"
                 for k in sorted(set(inputs) - {p.name for p in spec.params if p.where == "inputs"})]
    out = {"inputs": {}, "params": {}}
    for p in spec.params:
        given = (inputs if p.where == "inputs" else params).get(p.name)
        if given is None or (p.type in ("paths",) and given == []) or (p.type == "path" and given == ""):
            if p.required:
                raise UVPSInputError(f"{spec.name}: {p.where}.{p.name} is required ({p.help})")
            value = p.default
        else:
            value = coerce_value(p, given)
        out[p.where][p.name] = value
    return out["inputs"], out["params"], warnings


# ------------------------------------------------------------------------------------------------
# the command line
# ------------------------------------------------------------------------------------------------

def _cli_help(p: Param) -> str:
    text = p.help.replace("%", "%%")
    if p.type == "bool" and p.default and not p.positional:
        # the flag is --no-<name>: its help says what it turns off (the declaration says what is on)
        text = f"do not {text[0].lower()}{text[1:]} (on by default)"
    if p.unit:
        text += f" [{p.unit}]"
    if p.default not in (None, False, True, "") and not p.positional:
        text += f" (default {_show(p.default)})"
    return text


def _show(v) -> str:
    if isinstance(v, (list, tuple)):
        return " ".join(_show(x) for x in v)
    return f"{v:g}" if isinstance(v, float) else str(v)


def add_parser(subparsers, spec: CommandSpec) -> argparse.ArgumentParser:
    """A sub-command of ``uvps`` with one argument per declared parameter."""
    ap = subparsers.add_parser(spec.name, help=spec.help, description=spec.description or spec.help,
                               aliases=list(spec.aliases))
    for p in spec.params:
        kw = {"help": _cli_help(p), "dest": p.name}
        if p.positional:
            kw.pop("dest")
            ap.add_argument(p.name, nargs="+" if p.type == "paths" else None, help=_cli_help(p))
            continue
        if p.type == "bool":
            kw["action"] = "store_false" if p.default else "store_true"
            kw["default"] = None
        elif p.type == "choice":
            kw["choices"] = list(p.choices)
        elif p.type == "paths":
            kw["nargs"] = "+"
        elif p.type in ("numbers", "shape"):
            kw["nargs"] = "+" if p.type == "numbers" else 2
            kw["metavar"] = ("ROWS", "COLS") if p.type == "shape" else p.unit.upper() or "N"
        if p.required:
            kw["required"] = True
        ap.add_argument(p.flag, **kw)
    if spec.output:
        if spec.output_default is None:
            ap.add_argument("-o", "--output", required=True, help=f"{spec.output} (created, with missing parent "
                            "folders; " + (spec.output_note or "the command's files in it are replaced") + ")")
        else:
            ap.add_argument("-o", "--output", default=spec.output_default,
                            help=f"{spec.output} (default ./{spec.output_default})")
    return ap


def request_from_args(spec: CommandSpec, ns: argparse.Namespace) -> tuple:
    """``(inputs, params)`` of a parsed command line: flags the user did not give are left out,
    so the declared defaults apply (as for a bridge request)."""
    inputs, params = {}, {}
    for p in spec.params:
        v = getattr(ns, p.name, None)
        if v is None:
            continue
        if p.type in ("path", "paths") and p.where == "inputs":
            v = [str(Path(x).resolve()) for x in v] if isinstance(v, list) else str(Path(v).resolve())
        (inputs if p.where == "inputs" else params)[p.name] = v
    return inputs, params


# ------------------------------------------------------------------------------------------------
# exports: the Fiji side's table and the docs' reference
# ------------------------------------------------------------------------------------------------

def param_json(p: Param) -> dict:
    """A parameter as plain JSON (the Fiji side reads this)."""
    d = {"name": p.name, "type": p.type, "default": list(p.default) if isinstance(p.default, tuple) else p.default,
         "help": p.help, "where": p.where}
    for key in ("choices", "unit", "minimum", "maximum", "label"):
        v = getattr(p, key)
        if v not in ((), "", None):
            d[key] = list(v) if isinstance(v, tuple) else v
    if p.required:
        d["required"] = True
    return d


def to_json(specs: dict) -> dict:
    """The command table: ``{"schema_version": 1, "commands": {name: {help, params}}}``."""
    return {"schema_version": 1,
            "commands": {name: {"help": s.help, "output": s.output, "menu": s.menu,
                                "params": [param_json(p) for p in s.params]}
                         for name, s in specs.items() if name == s.name}}


def markdown(specs: dict) -> str:
    """``docs/commands.md``: one section per command, one table row per parameter."""
    lines = ["# Command reference", "",
             "Generated from the command declarations (`uvps spec --markdown > docs/commands.md`); a test",
             "fails when this file and the declarations disagree. The same names are the keys of a bridge",
             "request (`docs/bridge.md`); on the command line `pixel_size_um` is `--pixel-size-um`.", ""]
    for name, s in specs.items():
        if name != s.name:
            continue
        alias = f" (also `{'`, `'.join(s.aliases)}`)" if s.aliases else ""
        lines += [f"## `uvps {name}`{alias}", "", s.description or s.help, ""]
        if s.menu:
            lines += [f"Fiji: *Plugins > UV Photometric Stereo > {s.menu}*.", ""]
        if s.output:
            lines += [f"`-o/--output`: the {s.output}" + (f" (default `{s.output_default}`)." if s.output_default
                                                          else "."), ""]
        if s.params:
            lines += ["| key | in | type | default | unit | meaning |", "|---|---|---|---|---|---|"]
            for p in s.params:
                t = p.type + (f": {', '.join(map(str, p.choices))}" if p.choices else "")
                d = "required" if p.required else ("" if p.default is None else f"`{_show(p.default)}`")
                lines.append(f"| `{p.name}` | {p.where} | {t} | {d} | {p.unit} | {p.help} |")
            lines.append("")
    return "\n".join(lines)
