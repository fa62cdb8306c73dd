#!/usr/bin/env python
"""Check (or rewrite) the sections of ``docs/benchmarks.md`` that the benchmark scripts write.

Each section between ``<!-- begin NAME: written by scripts/X.py -->`` and ``<!-- end NAME -->`` must
name a script that exists and has a ``--doc`` flag; where ``docs/benchmarks/NAME.json`` (the raw
results its last ``--doc`` kept) exists, the script's ``render_doc`` of it (or ``DOC_SECTIONS[NAME]``'s, for
a script writing several sections) must give the section's
text exactly: regenerating at HEAD changes nothing. ``--check`` exits 1 and names each stale or broken
section (``tests/test_benchmark_docs.py``); without it, the sections with a JSON are rewritten from it
(no benchmark is run).

    .venv/bin/python scripts/benchmark_docs.py --check
"""
from __future__ import annotations

import argparse
import importlib.util
import json
import re
import sys
from pathlib import Path

SCRIPTS = Path(__file__).resolve().parent
if str(SCRIPTS) not in sys.path:
    sys.path.insert(0, str(SCRIPTS))

from benchdoc import DOC, JSON_DIR, ROOT, SectionError, json_path, read_text, sections, write_section  # noqa: E402

_DOC_FLAG = re.compile(r"""add_argument\(\s*["']--doc["']""")


def _rel(path: Path) -> str:
    """A path as the project writes it: relative to the project folder when inside it."""
    try:
        return str(Path(path).resolve().relative_to(ROOT))
    except ValueError:
        return str(path)


def load_script(path: Path):
    """Import a benchmark script as a module (its imports run; nothing is measured)."""
    spec = importlib.util.spec_from_file_location(f"_benchdoc_{path.stem}", path)
    mod = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = mod        # registered under its own name: a dataclass looks its module up there
    spec.loader.exec_module(mod)
    return mod


def renderer(mod, name: str):
    """A script's renderer of section ``name``: ``render_doc`` where ``DOC_SECTION == name``, else the entry of
    ``DOC_SECTIONS`` (a dict of section name to renderer, for a script writing several tables); None if neither."""
    if getattr(mod, "DOC_SECTION", None) == name and callable(getattr(mod, "render_doc", None)):
        return mod.render_doc
    render = (getattr(mod, "DOC_SECTIONS", None) or {}).get(name)
    return render if callable(render) else None


def rendered(md_path: Path, json_dir: Path, root: Path = ROOT) -> tuple[dict, list[str]]:
    """Each section's expected text and the problems found.

    Returns
    -------
    expected : dict of str to str
        Section name -> the text its script renders from its JSON (only sections with a JSON).
    problems : list of str
        One line each: a missing script, a script without ``--doc`` or ``render_doc``, a JSON it cannot
        render, a JSON without a section.
    """
    text = read_text(md_path)
    found = sections(text, path=_rel(md_path))
    expected, problems = {}, []
    for name, s in found.items():
        script = root / s.source
        if not script.is_file():
            problems.append(f"{_rel(md_path)}: section {name!r} names {s.source}, which does not exist")
            continue
        if not _DOC_FLAG.search(script.read_text(encoding="utf-8")):
            problems.append(f"{_rel(md_path)}: section {name!r} names {s.source}, which has no --doc flag")
            continue
        jp = json_path(name, json_dir=json_dir)
        if not jp.is_file():
            continue
        mod = load_script(script)
        render = renderer(mod, name)
        if render is None:
            problems.append(f"{s.source}: expected DOC_SECTION = {name!r} and a render_doc(results) function "
                            f"(or DOC_SECTIONS mapping {name!r} to its renderer)")
            continue
        try:
            t = render(json.loads(jp.read_text(encoding="utf-8")))
            expected[name] = t if t.endswith("\n") else t + "\n"     # as write_section writes it
        except (ValueError, KeyError, TypeError, IndexError) as e:
            problems.append(f"{_rel(jp)}: {s.source} cannot render it ({type(e).__name__}: {e})")
    for jp in sorted(Path(json_dir).glob("*.json")):
        if jp.stem not in found:
            problems.append(f"{_rel(jp)}: no section {jp.stem!r} in {_rel(md_path)} (a renamed or removed section?)")
    return expected, problems


def _command(name: str, source: str, args) -> str:
    """The command that last wrote a section (its JSON's ``argv``), else the script with ``--doc``."""
    try:
        argv = json.loads(json_path(name, json_dir=args.json_dir).read_text(encoding="utf-8"))["argv"]
    except (OSError, ValueError, KeyError, TypeError):
        argv = []
    argv = [a for a in argv if a != "--doc"]
    return " ".join([source] + argv + ["--doc"])


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--check", action="store_true", help="exit 1 when a section is stale or its markers are broken")
    ap.add_argument("--md", type=Path, default=DOC, help="the Markdown file (default docs/benchmarks.md)")
    ap.add_argument("--json-dir", type=Path, default=JSON_DIR, help="the raw results (default docs/benchmarks/)")
    args = ap.parse_args(argv)
    try:
        expected, problems = rendered(args.md, args.json_dir)
        text = read_text(args.md)
        found = sections(text, path=_rel(args.md))
    except (SectionError, OSError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 1
    stale = [n for n, t in expected.items() if text[found[n].start:found[n].end] != t]
    for line in problems:
        print(f"error: {line}", file=sys.stderr)
    if args.check:
        for n in stale:
            print(f"error: {_rel(args.md)}: section {n!r} is stale: run "
                  f"python {_command(n, found[n].source, args)} (or "
                  f"python scripts/benchmark_docs.py to render it from {_rel(json_path(n, json_dir=args.json_dir))})",
                  file=sys.stderr)
        return 1 if stale or problems else 0
    for n in stale:
        write_section(args.md, n, expected[n], source=found[n].source)
        print(f"{_rel(args.md)}: section {n!r} rewritten from its JSON")
    return 1 if problems else 0


if __name__ == "__main__":
    sys.exit(main())
