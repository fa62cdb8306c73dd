"""Command-line interface: ``uvps COMMAND ...``, generated from the command declarations.

Every sub-command's flags come from its :class:`uvps.spec.CommandSpec` (``uvps.commands.COMMANDS``);
two more are the CLI's own: ``uvps bridge REQUEST.json`` (the Fiji side's entry, ``uvps.bridge``) and
``uvps spec`` (the declarations as JSON for the Fiji side, or as the Markdown of docs/commands.md).
Exit status: 0 ok, 1 bad input (a mistyped command line included), 2 anything else.
"""
from __future__ import annotations

import argparse
import json
import logging
import sys
from pathlib import Path

from . import __version__
from .bridge import run_bridge
from .commands import COMMANDS, DECLARED_IN
from .errors import UVPSError, in_chain
from .files.outputs import COMMITTED
from .spec import add_parser, markdown, request_from_args, to_json

log = logging.getLogger(__name__)

#: Commands whose answer includes the report: the CLI prints where it is.
_REPORTING = ("demo", "run", "stats", "report")


class _Parser(argparse.ArgumentParser):
    """argparse's parser, but a mistyped command line is bad input like any other: one line naming
    the argument and where to look (not argparse's usage block above it, which buried that line under
    a dozen of options), exit status 1 (argparse's own is 2, which uvps keeps for failures the user
    cannot fix). Sub-command parsers are of this class too."""

    def error(self, message):
        self.exit(1, f"{self.prog}: error: {message}; see {self.prog} --help\n")


def build_parser(commands=None) -> argparse.ArgumentParser:
    """The ``uvps`` parser: one sub-command per declared command (of ``commands``, a name -> spec
    mapping; default every one), plus ``bridge`` and ``spec``."""
    ap = _Parser(prog="uvps", description="Photometric stereo by UV-induced fluorescence "
                                 "(lights from the images, normals, albedo, height, protrusions).")
    ap.add_argument("--version", action="version", version=f"uvps {__version__}")
    ap.add_argument("-v", "--verbose", action="store_true", help="debug logging")
    sp = ap.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for name, spec in (COMMANDS if commands is None else commands).items():
        if name == spec.name:
            add_parser(sp, spec)
    p = sp.add_parser("bridge", help="the file bridge for the Fiji side: run a request.json")
    p.add_argument("request")
    p = sp.add_parser("spec", help="the command declarations, as JSON (Fiji side) or Markdown (docs)")
    p.add_argument("--markdown", action="store_true", help="docs/commands.md instead of JSON")
    return ap


class _Bar:
    """A tqdm progress bar on stderr driven by the progress callback (CLI only).

    The bar never moves back (a sub-step may start below where the last one ended), and the time
    left is the elapsed time scaled by the fraction still to do (the stages report fractions in
    proportion to their measured time). Redrawn at most every 0.2 s.
    """

    def __init__(self, name):
        from tqdm import tqdm   # the CLI's own dependency: not imported by the library

        self.bar = tqdm(total=1000, desc=name, file=sys.stderr, leave=False, mininterval=0.2, smoothing=0,
                        bar_format="{desc}: {percentage:3.0f}%|{bar}| {elapsed}<{remaining} {postfix}")

    def __call__(self, fraction, message):
        n = min(1000, int(1000 * fraction))
        if n > self.bar.n:
            self.bar.update(n - self.bar.n)
        self.bar.set_postfix_str(message[:60], refresh=False)

    def close(self):
        self.bar.close()


def _run_command(a) -> int:
    spec = COMMANDS[a.command]
    inputs, params = request_from_args(spec, a)
    out = Path(a.output).resolve() if spec.output else None
    bar = _Bar(a.command) if sys.stderr.isatty() else None
    existed = out is not None and out.exists()
    try:
        result = spec(inputs, params, out, progress=bar)
    except UVPSError as exc:
        for line in getattr(exc, "details", ()):   # e.g. one line per failed capture of a batch
            print(f"uvps {a.command}: {line}", file=sys.stderr)
        print(f"uvps {a.command}: error: {str(exc).splitlines()[0] if str(exc) else type(exc).__name__}",
              file=sys.stderr)
        return exc.exit_code
    except KeyboardInterrupt:
        return _interrupted(a, out, existed)
    except Exception as exc:  # an unexpected failure: one line, the traceback in the log
        if in_chain(exc, KeyboardInterrupt) is not None:
            # Ctrl-C inside a compiled (numba) kernel surfaces as a SystemError ("returned a result
            # with an exception set") with the KeyboardInterrupt down its chain
            return _interrupted(a, out, existed)
        log.debug("traceback", exc_info=True)
        print(f"uvps {a.command}: internal error: {type(exc).__name__}: {exc}".splitlines()[0], file=sys.stderr)
        return 2
    finally:
        if bar:
            bar.close()
    for w in result.warnings:
        print(f"warning: {w}", file=sys.stderr)
    if result.text:
        print(result.text)
    if out is not None:
        print(f"uvps {a.command}: wrote {out}")
        if a.command in _REPORTING and (out / "report.html").is_file():
            found = _found(out)
            if found:
                print(found)
            print(f"report: {out / 'report.html'}")
    return 0


def _found(run_dir: Path) -> str:
    """What a run found, in one line, from its ``regions.csv`` (:func:`uvps.files.tables.read_counts`):
    "found: 97 protrusions in 8 colour areas (4.32 cm², 22.5 per cm²)"; empty without that table."""
    from .files.tables import read_counts

    try:
        areas = read_counts(run_dir)["areas"]
    except (OSError, KeyError, ValueError):
        return ""
    if not areas:
        return ""
    count = sum(a["count"] for a in areas)
    area = sum(a["area_cm2"] for a in areas)
    where = f"{len(areas)} colour area{'s' if len(areas) != 1 else ''}"
    density = f", {count / area:.3g} per cm\u00b2" if area > 0 else ""
    return f"found: {count} protrusion{'s' if count != 1 else ''} in {where} ({area:.3g} cm\u00b2{density})"


def _interrupted(a, out, existed: bool) -> int:
    """Ctrl-C: one line saying what the output folder holds, and exit status 130 (128 + SIGINT), as a
    shell reports it. Outputs are built in a temporary folder and moved into place whole (a Ctrl-C
    during that move waits for its end), so ``out`` is as it was, or absent, or wholly new."""
    if out is None:
        where = ""
    elif str(out) in COMMITTED:
        where = f"; {out} was already written whole (this run's)"
    elif existed:
        where = f"; {out} left as it was (nothing of this run written)"
    else:
        where = f"; nothing written ({out} not created)"
    print(f"uvps {a.command}: interrupted{where}", file=sys.stderr)
    return 130


def quiet_library_warnings(*, verbose: bool = False) -> None:
    """Library warnings (numpy's "divide by zero" RuntimeWarning, a library's DeprecationWarning) go to
    the log, shown only with ``-v``: what a user must know, uvps says in its own warnings."""
    logging.captureWarnings(True)
    logging.getLogger("py.warnings").setLevel(logging.DEBUG if verbose else logging.CRITICAL)


def main(argv=None) -> int:
    """``uvps`` entry point; returns the exit status (0 ok, 1 bad input, 2 compute error)."""
    argv = sys.argv[1:] if argv is None else list(argv)
    # the command named (the first word: uvps's own options take no value) is the only one whose
    # module is imported; a name that is not a command gets the whole parser, and its message
    named = next((w for w in argv if not w.startswith("-")), None)
    only = None
    if named in DECLARED_IN:
        spec = COMMANDS[named]
        only = {spec.name: spec}
    a = build_parser(only).parse_args(argv)
    logging.basicConfig(level=logging.DEBUG if a.verbose else logging.INFO, stream=sys.stderr,
                        format="%(levelname)s %(name)s: %(message)s")
    quiet_library_warnings(verbose=a.verbose)
    if a.command == "bridge":
        return run_bridge(a.request, COMMANDS)
    if a.command == "spec":
        print(markdown(COMMANDS) if a.markdown else json.dumps(to_json(COMMANDS), indent=1))
        return 0
    return _run_command(a)


if __name__ == "__main__":
    sys.exit(main())
