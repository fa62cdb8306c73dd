"""The package's two layers, read from the source with ``ast`` (nothing is imported or run).

- ``uvps.core`` (the numeric library) imports only itself and ``uvps.errors``: no file layer, report,
  command, declaration (``uvps.spec``), front end or generator (``uvps.testing``).
- A command module (``uvps.commands.<name>``) never imports another command module; it calls the
  library, the file layer and the report. The registry ``uvps.commands`` itself is imported only by
  the front ends and by ``demo`` (which runs ``calibrate`` by name, as a user would).
- The longest chain of imports from ``uvps.cli`` down to ``uvps.errors`` is at most 9 modules.

The picture of the layers is in docs/architecture.md, "Two layers".
"""
from __future__ import annotations

import ast
from functools import lru_cache
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1] / "cpython_core" / "uvps"
MAX_CHAIN = 9


def _module_name(path: Path) -> str:
    parts = path.relative_to(ROOT.parent).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


@lru_cache(maxsize=None)
def modules() -> dict:
    """Every uvps module by name -> its source path."""
    return {_module_name(p): p for p in ROOT.rglob("*.py")}


def _resolve(module: str, is_package: bool, node: ast.ImportFrom) -> str:
    if not node.level:
        return node.module or ""
    base = module.split(".")
    base = base if is_package else base[:-1]
    base = base[:len(base) - (node.level - 1)]
    return ".".join(base + ([node.module] if node.module else []))


def imports_of(source: str, module: str, is_package: bool) -> set:
    """The uvps modules a source imports anywhere in it (module level or inside a function)."""
    known = modules()
    out = set()
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.Import):
            names = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            target = _resolve(module, is_package, node)
            # `from pkg import mod` imports the module pkg.mod; `from mod import name` the module mod
            names = [f"{target}.{a.name}" if f"{target}.{a.name}" in known else target for a in node.names]
        else:
            continue
        out |= {n for n in names if n.split(".")[0] == "uvps" and n in known}
    out.discard(module)
    return out


@lru_cache(maxsize=None)
def graph() -> dict:
    return {m: frozenset(imports_of(p.read_text(), m, p.name == "__init__.py")) for m, p in modules().items()}


def core_violations(g: dict) -> list:
    allowed = ("uvps.core", "uvps.errors")
    return sorted(f"{m} imports {t}" for m, ts in g.items() if m.startswith("uvps.core")
                  for t in ts if not t.startswith(allowed) and t != "uvps")


def command_violations(g: dict) -> list:
    def is_command(m):
        return m.startswith("uvps.commands.")
    bad = [f"{m} imports {t}" for m, ts in g.items() if is_command(m) for t in ts if is_command(t)]
    registry_users = {"uvps.cli", "uvps.bridge", "uvps.commands.capture"}
    bad += [f"{m} imports the registry uvps.commands" for m, ts in g.items()
            if "uvps.commands" in ts and m not in registry_users]
    return sorted(bad)


def longest_chain(g: dict, start: str, end: str) -> list:
    """The longest simple path of imports from ``start`` to ``end`` (modules, both ends included)."""
    best: list = []

    def walk(m, path, seen):
        nonlocal best
        if m == end:
            if len(path) > len(best):
                best = list(path)
            return
        for t in sorted(g.get(m, ())):
            if t not in seen:
                seen.add(t)
                path.append(t)
                walk(t, path, seen)
                path.pop()
                seen.discard(t)

    walk(start, [start], {start})
    return best


def test_the_reader_sees_imports():
    """The parser finds relative, absolute, lazy and `from pkg import module` imports."""
    src = ("from ..files.io import read_tiff\nfrom .. import errors\nimport uvps.core.lights\n"
           "def f():\n    from .stereo import solve_normals\n")
    got = imports_of(src, "uvps.core.pipeline", False)
    assert got == {"uvps.files.io", "uvps.errors", "uvps.core.lights", "uvps.core.stereo"}
    g = {"uvps.core.a": {"uvps.files.io"}, "uvps.commands.x": {"uvps.commands.y"}, "uvps.commands.y": set()}
    assert core_violations(g) == ["uvps.core.a imports uvps.files.io"]
    assert command_violations(g) == ["uvps.commands.x imports uvps.commands.y"]
    chain = {"a": {"b", "e"}, "b": {"c"}, "c": {"e"}, "e": set()}
    assert longest_chain(chain, "a", "e") == ["a", "b", "c", "e"]


def test_core_imports_no_application_module():
    assert core_violations(graph()) == []


def test_no_command_imports_another():
    assert command_violations(graph()) == []


def test_import_chain_from_cli_to_errors():
    chain = longest_chain(graph(), "uvps.cli", "uvps.errors")
    assert chain, "uvps.cli does not reach uvps.errors"
    assert len(chain) <= MAX_CHAIN, " -> ".join(chain)


@pytest.mark.parametrize("package", ["core", "files", "report", "commands", "testing"])
def test_every_layer_is_a_package(package):
    """setuptools finds a sub-package only with its __init__.py (pyproject: packages.find)."""
    assert (ROOT / package / "__init__.py").is_file()



MAX_FILE_LINES = 1500


def long_files(root: Path, limit: int = MAX_FILE_LINES) -> dict:
    """The ``.py`` files under ``root`` longer than ``limit`` lines, by path relative to ``root``."""
    return {str(p.relative_to(root)): n for p in sorted(root.rglob("*.py"))
            if (n := len(p.read_text(encoding="utf-8").splitlines())) > limit}


def test_the_line_count_finds_a_long_file(tmp_path):
    (tmp_path / "pkg").mkdir()
    (tmp_path / "pkg" / "long.py").write_text("x = 1\n" * (MAX_FILE_LINES + 1), encoding="utf-8")
    (tmp_path / "short.py").write_text("x = 1\n" * MAX_FILE_LINES, encoding="utf-8")
    assert long_files(tmp_path) == {str(Path("pkg") / "long.py"): MAX_FILE_LINES + 1}


def test_no_file_over_max_lines():
    """No source file of the package is over MAX_FILE_LINES lines: a longer one is split into modules
    by part (as ``uvps.testing.synthetic`` and ``uvps.core.detect`` are)."""
    assert long_files(ROOT) == {}, f"split these files (over {MAX_FILE_LINES} lines)"


MAX_FUNCTION_LINES = 60


def function_lengths(source: str) -> dict:
    """Every function (and method) of ``source`` by ``name:line`` -> its length in lines, counted from
    the line after its docstring (after its ``def`` when it has none) to its last line."""
    out = {}
    for node in ast.walk(ast.parse(source)):
        if not isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
            continue
        start = node.lineno
        first = node.body[0]
        if isinstance(first, ast.Expr) and isinstance(first.value, ast.Constant) \
                and isinstance(first.value.value, str):
            start = first.end_lineno
        out[f"{node.name}:{node.lineno}"] = node.end_lineno - start
    return out


def long_functions(root: Path, limit: int = MAX_FUNCTION_LINES) -> dict:
    """The functions under ``root`` longer than ``limit`` lines (docstring excluded), by
    ``path:name:line`` relative to ``root``."""
    return {f"{p.relative_to(root)}:{name}": n for p in sorted(root.rglob("*.py"))
            for name, n in function_lengths(p.read_text(encoding="utf-8")).items() if n > limit}


def test_the_line_count_finds_a_long_function(tmp_path):
    body = "".join(f"    x{i} = {i}\n" for i in range(MAX_FUNCTION_LINES + 1))
    doc = '    """A docstring\n' + "    of many lines\n" * 20 + '    """\n'
    (tmp_path / "pkg").mkdir()
    (tmp_path / "pkg" / "long.py").write_text(
        "def long():\n" + body + "\n\nclass A:\n    def method(self):\n" + "    " + body.replace("\n    ", "\n        "),
        encoding="utf-8")
    # the docstring is not counted: 20 lines of it and MAX_FUNCTION_LINES of code is not too long
    (tmp_path / "short.py").write_text("def short():\n" + doc + body.split("\n", 1)[1], encoding="utf-8")
    assert long_functions(tmp_path) == {str(Path("pkg") / "long.py") + ":long:1": MAX_FUNCTION_LINES + 1,
                                        str(Path("pkg") / "long.py") + ":method:66": MAX_FUNCTION_LINES + 1}


def test_no_function_over_max_lines():
    """No function of the package is over MAX_FUNCTION_LINES lines, its docstring excluded: a longer
    one is split into named stages, each a helper whose docstring says what it does and why."""
    assert long_functions(ROOT) == {}, f"split these functions (over {MAX_FUNCTION_LINES} lines)"
