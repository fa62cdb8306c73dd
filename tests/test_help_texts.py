"""Every help text of the command declarations, read for the mismatches a user meets in `--help`: a
flag that does not exist, a default that differs from the declared one, a `--no-` flag described by
what it turns on, a shared parameter speaking of other commands."""
import re

import pytest

from uvps import cli
from uvps.workflow import REUSE_LIGHTS
from uvps.commands import COMMANDS
from uvps.spec import _cli_help

SPECS = sorted({spec.name: spec for spec in COMMANDS.values()}.items())
ALL = [(name, p) for name, spec in SPECS for p in spec.params]


def _flags(spec):
    return {p.flag for p in spec.params if not p.positional} | {"--output", "--help", "--verbose", "--version"}


@pytest.mark.parametrize("name, spec", SPECS)
def test_every_flag_a_help_text_names_exists_in_that_command(name, spec):
    texts = [spec.help, spec.description, spec.output_note] + [p.help for p in spec.params]
    named = {m for t in texts for m in re.findall(r"(?<![\w-])--[a-z][a-z0-9-]+", t or "")}
    # `uvps flatfield CAPTURE -o RUN` style examples name other commands' flags: only this command's
    own = {f for f in named if not any(f"uvps {other}" in (t or "") for t in texts for other, _ in SPECS
                                        if other != name)}
    assert own <= _flags(spec), (name, own - _flags(spec))


@pytest.mark.parametrize("command, p", ALL, ids=[f"{c}.{p.name}" for c, p in ALL])
def test_each_help_text_agrees_with_its_declaration(command, p):
    text = p.help
    assert text and "\n" not in text and text == text.strip(), (command, p.name)
    cli_text = _cli_help(p)
    if p.type == "bool" and p.default:
        # the flag is --no-<name>: its help must say what it turns off, and the declaration what is on
        assert p.flag == f"--no-{p.name.replace('_', '-')}"
        assert cli_text.startswith("do not ") and not re.match(r"(do not|don't|no |skip|without)\b", text), text
    # a default quoted in the text is the declared one
    for quoted in re.findall(r"\(default (-?[0-9.]+)\)", text):
        assert p.default is not None and float(quoted) == pytest.approx(float(p.default)), (command, p.name, text)
    # a unit spelled in the text matches the declared one
    if p.unit == "um":
        assert not re.search(r"\bmm\b", text) or "mm" in p.name, (command, p.name, text)
    # lights: only the commands that read the run folder's lights.json say they do
    if p.name == "lights" and command not in REUSE_LIGHTS:
        assert "flatfield and normals" not in text and "run folder's lights.json for" not in text, (command, text)


def test_run_says_there_is_no_report_without_regions_or_detect():
    run = COMMANDS["run"]
    assert "without either, no protrusions and no report" in run.description
    helps = {p.name: p.help for p in run.params}
    assert "report" in helps["regions"] and "report" in helps["detect"]
    assert "replaced by this run's in one step" in run.output_note


def test_the_parsers_help_is_the_declarations(capsys):
    """`uvps run --help` shows the turned-off wording and the run's own lights text."""
    with pytest.raises(SystemExit):
        cli.main(["run", "--help"])
    out = " ".join(capsys.readouterr().out.split())
    assert "--no-refine-lights do not refine each lamp" in out
    assert "default: estimated from the images" in out and "for flatfield and normals" not in out
    assert "created, with missing parent folders" in out
