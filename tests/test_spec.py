"""Each command declared once: the CLI, the bridge's checks and the docs' reference agree with the
declarations (uvps.spec), and a change to one without the others fails here."""
import argparse
import json
import subprocess
import sys
from pathlib import Path

import pytest

from uvps.cli import build_parser
from uvps.commands import COMMANDS
from uvps.errors import UVPSInputError
from uvps.core.pipeline import RunOptions
from uvps.workflow import OPTION_PARAMS
from uvps.spec import coerce, markdown, request_from_args, to_json

ROOT = Path(__file__).resolve().parents[1]
SPECS = [s for name, s in COMMANDS.items() if name == s.name]


def _subparsers():
    ap = build_parser()
    action = next(a for a in ap._actions if isinstance(a, argparse._SubParsersAction))
    return ap, action.choices


def test_docs_command_reference_is_generated_from_the_declarations():
    text = (ROOT / "docs" / "commands.md").read_text(encoding="utf-8")
    assert text.strip() == markdown(COMMANDS).strip(), \
        "docs/commands.md is stale: run `uvps spec --markdown > docs/commands.md`"


@pytest.mark.parametrize("spec", SPECS, ids=lambda s: s.name)
def test_every_declared_parameter_is_a_cli_argument_with_its_choices(spec):
    _, subs = _subparsers()
    sub = subs[spec.name]
    dests = {a.dest: a for a in sub._actions}
    for p in spec.params:
        a = dests[p.name]
        if p.positional:
            assert not a.option_strings
        else:
            assert a.option_strings == [p.flag]
            assert a.default is None          # absent flags leave the declared default to the command
        if p.type == "choice":
            assert list(a.choices) == list(p.choices)
    # nothing on the command line that the declaration does not hold
    extra = set(dests) - {p.name for p in spec.params} - {"help", "output"}
    assert not extra, extra


@pytest.mark.parametrize("spec", SPECS, ids=lambda s: s.name)
def test_an_empty_request_takes_every_declared_default(spec):
    required = [p for p in spec.params if p.required]
    inputs = {p.name: ["x.tif"] if p.type == "paths" else "x.csv" for p in required if p.where == "inputs"}
    params = {p.name: 1.0 for p in required if p.where == "params"}
    got_inputs, got_params, warnings = coerce(spec, inputs, params)
    assert warnings == []
    for p in spec.params:
        if not p.required:
            assert (got_inputs if p.where == "inputs" else got_params)[p.name] == p.default


def test_cli_flags_become_the_same_request_as_the_bridge_gets(tmp_path):
    ap, _ = _subparsers()
    a = ap.parse_args(["run", str(tmp_path / "a.tif"), str(tmp_path / "b.tif"), "-o", str(tmp_path / "r"),
                       "--degree", "3", "--black-level", "100,110,120", "--no-refine-lights", "--regions", "auto",
                       "--bins-um", "0", "100", "300"])
    inputs, params = request_from_args(COMMANDS["run"], a)
    assert inputs == {"images": [str(tmp_path / "a.tif"), str(tmp_path / "b.tif")]}
    _, p, _ = coerce(COMMANDS["run"], inputs, params)
    assert p["degree"] == 3 and p["black_level"] == [100.0, 110.0, 120.0] and p["refine_lights"] is False
    assert p["regions"] == "auto" and p["bins_um"] == [0.0, 100.0, 300.0]
    # the same values as a JSON request (strings, as a Fiji dialog may send them)
    _, q, _ = coerce(COMMANDS["run"], inputs, {"degree": "3", "black_level": [100, 110, 120],
                                                "refine_lights": "false", "regions": "auto", "bins_um": "0,100,300"})
    assert {k: q[k] for k in params} == {k: p[k] for k in params}


@pytest.mark.parametrize("command,params,message", [
    ("run", {"degree": 9}, "degree must be an integer from 1 to 8; got 9"),
    ("run", {"degree": 2.5}, "degree must be an integer from 1 to 8; got 2.5"),
    ("run", {"pixel_size_um": 0}, "pixel_size_um must be a positive number (micrometres); got 0"),
    ("run", {"pixel_size_um": "abc"}, "pixel_size_um must be a positive number"),
    ("run", {"integration": "poisson"}, "integration must be one of fc, dct; got 'poisson'"),
    ("run", {"robust": "maybe"}, "robust must be true or false; got 'maybe'"),
    ("run", {"black_level": "-5"}, "black_level must be a number or comma-separated numbers >= 0"),
    ("relight", {"elevation_deg": 95}, "elevation_deg must be a number above 0 and at most 90; got 95"),
    ("demo", {"shape": [10]}, "shape must be two positive integers"),
    ("wand", {"method": "exact"}, "method must be one of"),
])
def test_bad_parameters_give_one_line_naming_the_parameter(command, params, message):
    inputs = {"images": ["a.tif"], "points": "p.csv"}
    inputs = {k: v for k, v in inputs.items() if any(p.name == k for p in COMMANDS[command].params)}
    with pytest.raises(UVPSInputError) as e:
        coerce(COMMANDS[command], inputs, params)
    assert message in str(e.value) and "\n" not in str(e.value)


def test_unknown_keys_are_reported_not_silently_used():
    _, params, warnings = coerce(COMMANDS["run"], {"images": ["a.tif"]}, {"seed": 3, "degre": 2})
    assert "seed" not in params and "degre" not in params and params["degree"] == 4
    assert warnings == ["parameter 'degre' ignored (unknown to the command run)",
                        "parameter 'seed' ignored (unknown to the command run)"]


def test_run_options_take_their_defaults_and_checks_from_the_same_declaration():
    opts = RunOptions()
    for p in OPTION_PARAMS:
        assert getattr(opts, p.name) == p.default
    with pytest.raises(UVPSInputError, match="offset_degree must be an integer from 0 to 2; got 3"):
        RunOptions(offset_degree=3)


def test_uvps_spec_prints_the_table_the_fiji_side_reads():
    out = subprocess.run([sys.executable, "-m", "uvps", "spec"], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    table = json.loads(out.stdout)
    assert table == json.loads(json.dumps(to_json(COMMANDS)))
    degree = next(p for p in table["commands"]["run"]["params"] if p["name"] == "degree")
    assert degree["default"] == 4 and degree["minimum"] == 1 and degree["maximum"] == 8
    assert set(table["commands"]) == {s.name for s in SPECS}
