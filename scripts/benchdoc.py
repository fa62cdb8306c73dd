"""Sections of ``docs/benchmarks.md`` written by the benchmark scripts themselves.

A section is the text between two HTML comments, each on a line of its own (so the rendered
Markdown does not change)::

    <!-- begin painting: written by scripts/benchmark_painting.py -->
    | seed | corner error (px) | ...
    <!-- end painting -->

A script's ``--doc`` renders what it just measured into its section (:func:`write_doc`) and keeps
the raw results beside it, ``docs/benchmarks/NAME.json``, from which ``scripts/benchmark_docs.py
--check`` renders the section again: regenerating at HEAD changes nothing. The scripts import this
module the way they import each other (``scripts/`` is the running script's folder).
"""
from __future__ import annotations

import json
import os
import re
import tempfile
from dataclasses import dataclass
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
DOC = ROOT / "docs" / "benchmarks.md"
JSON_DIR = ROOT / "docs" / "benchmarks"
_BEGIN = re.compile(r"^<!-- begin ([A-Za-z0-9_.-]+): written by (scripts/[A-Za-z0-9_.-]+\.py) -->\n", re.M)
_END = re.compile(r"^<!-- end ([A-Za-z0-9_.-]+) -->$", re.M)
_ANY = re.compile(r"^<!-- (?:begin|end) .*-->$", re.M)


class SectionError(ValueError):
    """A section's markers are missing, doubled or ill-formed (the message is one line naming the file)."""


@dataclass(frozen=True)
class Section:
    """One marked section: its ``name``, the ``source`` script that writes it and its text's span."""
    name: str
    source: str
    start: int
    end: int


def sections(text: str, *, path: Path | str = "docs/benchmarks.md") -> dict[str, Section]:
    """Every marked section of a Markdown text, by name.

    Parameters
    ----------
    text : str
        The Markdown.
    path : Path or str
        Named in the error messages.

    Returns
    -------
    dict of str to Section
        In the order of the text.

    Raises
    ------
    SectionError
        A begin without its end, an end without its begin, a name marked twice, sections nested, or a
        marker-like comment that is neither form.
    """
    out: dict[str, Section] = {}
    ends = {m.group(1): m for m in _END.finditer(text)}
    names_end = [m.group(1) for m in _END.finditer(text)]
    for m in _ANY.finditer(text):
        if not (_BEGIN.match(text, m.start()) or _END.match(text, m.start())):
            raise SectionError(f"{path}: ill-formed marker {m.group(0)!r} (expected '<!-- begin NAME: written by "
                               f"scripts/X.py -->' or '<!-- end NAME -->')")
    names_begin = [b.group(1) for b in _BEGIN.finditer(text)]
    for name in names_begin:
        if names_begin.count(name) > 1:
            raise SectionError(f"{path}: section {name!r} is marked twice")
    last = 0
    for b in _BEGIN.finditer(text):
        name = b.group(1)
        if names_end.count(name) != 1:
            raise SectionError(f"{path}: section {name!r} has {names_end.count(name)} end markers "
                               f"'<!-- end {name} -->' (expected 1)")
        e = ends[name]
        if e.start() < b.end() or b.start() < last:
            raise SectionError(f"{path}: section {name!r} ends before it begins or overlaps another")
        out[name] = Section(name, b.group(2), b.end(), e.start())
        last = e.end()
    for name in names_end:
        if name not in out:
            raise SectionError(f"{path}: '<!-- end {name} -->' has no begin marker")
    return out


def read_text(path: Path | str) -> str:
    """A text file exactly as stored (line endings untranslated), so a rewrite keeps the rest byte for byte."""
    return Path(path).read_bytes().decode("utf-8")


def _section(md_path: Path, name: str) -> tuple[str, Section]:
    text = read_text(md_path)
    found = sections(text, path=md_path)
    if name not in found:
        raise SectionError(f"{md_path}: no section {name!r} (expected '<!-- begin {name}: written by scripts/X.py -->'"
                           f" ... '<!-- end {name} -->')")
    return text, found[name]


def read_section(md_path: Path | str, name: str) -> str:
    """The text between a section's markers (the marker lines excluded).

    Raises
    ------
    SectionError
        The markers are missing, doubled or ill-formed.
    """
    text, s = _section(Path(md_path), name)
    return text[s.start:s.end]


def atomic_write_text(path: Path | str, text: str) -> None:
    """Write a text file through a temporary file in its folder and ``os.replace``: never half-written.

    The file keeps its permissions (a new one gets 0644: ``mkstemp``'s own 0600 would hide it from others).
    """
    path = Path(path)
    mode = path.stat().st_mode & 0o777 if path.exists() else 0o644
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        with os.fdopen(fd, "w", encoding="utf-8", newline="") as fh:
            fh.write(text)
        os.chmod(tmp, mode)
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def write_section(md_path: Path | str, name: str, text: str, *, source: str) -> bool:
    """Replace a section's text, atomically; the rest of the file is kept byte for byte.

    Parameters
    ----------
    md_path : Path or str
        The Markdown file (``docs/benchmarks.md``).
    name : str
        The section's name in its markers.
    text : str
        The new text; ends with a newline (the end marker keeps a line of its own).
    source : str
        The writing script, ``scripts/X.py``: must be the one its begin marker names.

    Returns
    -------
    bool
        Whether the file changed.

    Raises
    ------
    SectionError
        Markers missing, doubled or ill-formed, naming another script, or a marker line in ``text``.
    """
    md_path = Path(md_path)
    whole, s = _section(md_path, name)
    if s.source != source:
        raise SectionError(f"{md_path}: section {name!r} is written by {s.source}, not {source}")
    if _ANY.search(text):
        raise SectionError(f"{md_path}: the text for section {name!r} holds a marker line ({_ANY.search(text)[0]!r})")
    if not text.endswith("\n"):
        text += "\n"
    new = whole[:s.start] + text + whole[s.end:]
    if new == whole:
        return False
    atomic_write_text(md_path, new)
    return True


def json_path(name: str, *, json_dir: Path | str = JSON_DIR) -> Path:
    """Where a section's raw results are kept: ``docs/benchmarks/NAME.json``."""
    return Path(json_dir) / f"{name}.json"


def write_doc(name: str, results: dict, text: str, *, source: str, md_path: Path | str | None = None,
              json_dir: Path | str | None = None) -> Path:
    """A script's ``--doc``: its raw results as JSON beside the document, then its section.

    ``md_path`` and ``json_dir`` default to this module's ``DOC`` and ``JSON_DIR``. The markers are
    checked before anything is written, so a refused section leaves both files as they were. Returns
    the JSON's path.
    """
    md_path = DOC if md_path is None else md_path
    json_dir = JSON_DIR if json_dir is None else json_dir
    read_section(md_path, name)
    out = json_path(name, json_dir=json_dir)
    out.parent.mkdir(parents=True, exist_ok=True)
    atomic_write_text(out, json.dumps(results, indent=1, sort_keys=True) + "\n")
    write_section(md_path, name, text, source=source)
    return out
