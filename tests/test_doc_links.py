"""Every Markdown link in README.md and docs/ leads somewhere: the file it names exists and, where it
names a section (``file.md#anchor`` or ``#anchor``), a heading of that file has that anchor by
GitHub's rules (lower case; punctuation other than '-' and '_' dropped; each space a '-'; a repeated
heading gets '-1', '-2', ...). Links to the web, and links inside code, are not followed.

Comments, docstrings and docs also cite a section in words, ``docs/benchmarks.md, "Speed and memory"``:
the file exists under docs/ and has a heading (or a bold paragraph lead, ``**Known positions with a
card**``) of that name, whole or up to its bracket or colon ("Levelling" for "Levelling (`--level`)")."""
from __future__ import annotations

import re
import sys
from pathlib import Path
from urllib.parse import unquote

REPO = Path(__file__).resolve().parents[1]

_FENCE = re.compile(r"^\s*(```|~~~)")
_CODE_SPAN = re.compile(r"(`+)(?:.+?)\1")
#: [text](target) or ![alt](target), the target up to a space (a title may follow) or ')'
_LINK = re.compile(r"!?\[(?:[^\[\]]|\[[^\]]*\])*\]\(\s*<?([^)\s>]+)>?(?:\s+\"[^\"]*\")?\s*\)")
_HEADING = re.compile(r"^ {0,3}(#{1,6})\s+(.*?)\s*#*\s*$")
_HTML_ID = re.compile(r"""<a\s+(?:name|id)\s*=\s*["']([^"']+)["']""", re.I)


def _prose_lines(text: str):
    """(line number, line) of the lines outside fenced code blocks."""
    fenced = False
    for i, line in enumerate(text.splitlines(), 1):
        if _FENCE.match(line):
            fenced = not fenced
            continue
        if not fenced:
            yield i, line


def github_anchor(heading: str) -> str:
    """The anchor GitHub gives a heading's text: the text as rendered (markup and link targets
    dropped), lower case, every character but letters, digits, '_', '-' and spaces dropped, each
    space a '-'."""
    text = re.sub(r"\[([^\]]*)\]\([^)]*\)", r"\1", heading)       # a link keeps its text
    text = re.sub(r"<[^>]+>", "", text)                            # inline HTML
    text = text.lower()
    text = re.sub(r"[^\w\- ]", "", text)
    return text.replace(" ", "-")


def anchors(path: Path) -> set[str]:
    """The anchors of a Markdown file's headings (repeats numbered as GitHub numbers them) and of its
    HTML ``<a name=...>`` / ``<a id=...>``."""
    seen: dict[str, int] = {}
    out = set()
    for _, line in _prose_lines(path.read_text(encoding="utf-8")):
        m = _HEADING.match(line)
        if m:
            base = github_anchor(m.group(2))
            n = seen.get(base, 0)
            out.add(base if n == 0 else f"{base}-{n}")
            seen[base] = n + 1
        out.update(a.lower() for a in _HTML_ID.findall(line))
    return out


def links(md: Path):
    """(line number, target) of each link of ``md`` into the project (not to the web, not in code)."""
    for lineno, line in _prose_lines(md.read_text(encoding="utf-8")):
        for target in _LINK.findall(_CODE_SPAN.sub("", line)):
            if not re.match(r"^[a-z][a-z0-9+.-]*:", target, re.I):   # http:, https:, mailto:
                yield lineno, target


def broken_links(md: Path) -> list[str]:
    """Each link of ``md`` that leads nowhere, as 'file:line: target: why'."""
    bad = []
    cache: dict[Path, set[str]] = {}
    for lineno, target in links(md):
        path_part, _, anchor = target.partition("#")
        dest = (md.parent / unquote(path_part)).resolve() if path_part else md
        where = f"{md.relative_to(REPO) if md.is_relative_to(REPO) else md}:{lineno}: {target}"
        if not dest.exists():
            bad.append(f"{where}: no such file")
            continue
        if anchor and dest.suffix == ".md":
            if dest not in cache:
                cache[dest] = anchors(dest)
            if unquote(anchor).lower() not in cache[dest]:
                bad.append(f"{where}: no heading with this anchor in {dest.name}")
    return bad


#: a path ending in .md, then (after an optional closing backquote, bracket and comma) a quoted name
_CITE = re.compile(r"((?:docs/)?(?:decisions/)?[A-Za-z_]+\.md)`{0,2}\)?,?\s+\(?\"([^\"]{3,120})\"")


def _norm(name: str) -> str:
    return re.sub(r"\s+", " ", name.replace("`", "")).strip().rstrip(".:").lower()


def section_names(path: Path) -> set[str]:
    """The names a file's sections are cited by: its headings' and its bold paragraph leads' text."""
    text = path.read_text(encoding="utf-8")
    names = [m.group(2) for _, line in _prose_lines(text) if (m := _HEADING.match(line))]
    names += re.findall(r"\*\*([^*]+)\*\*", text)
    return {_norm(n) for n in names}


def citations(path: Path):
    """(cited file under docs/, cited section) of each ``docs/X.md, "Section"`` in ``path``; in Python,
    comment markers at the start of a line are dropped first, so a citation may run over lines."""
    text = path.read_text(encoding="utf-8")
    if path.suffix == ".py":
        text = re.sub(r"\n[ \t]*#+:?[ \t]*", "\n", text)
    text = re.sub(r"[ \t]*\n[ \t]*", " ", text)
    for m in _CITE.finditer(text):
        yield REPO / "docs" / m.group(1).removeprefix("docs/"), m.group(2)


def broken_citations(path: Path) -> list[str]:
    """Each cited section of ``path`` that its file does not have, as 'file: cited: why'."""
    bad = []
    for dest, name in citations(path):
        cited = f"{path.name}: {dest.name}, \"{name}\""
        if not dest.exists():
            bad.append(f"{cited}: no such file under docs/")
            continue
        n = _norm(name)
        if not any(s == n or s.startswith((n + " (", n + ":")) for s in section_names(dest)):
            bad.append(f"{cited}: no such section")
    return bad


def _project_markdown() -> list[Path]:
    return [REPO / "README.md"] + sorted((REPO / "docs").rglob("*.md"))


def test_github_anchor_follows_githubs_rules():
    assert github_anchor("Calibration and spheres (`uvps calibrate`)") == "calibration-and-spheres-uvps-calibrate"
    assert github_anchor("Levelling (`--level`)") == "levelling---level"
    assert github_anchor("Painting in tiles (`uvps batch --mosaic`)") == "painting-in-tiles-uvps-batch---mosaic"
    assert github_anchor("A weak peak's `split_fraction`, 0.15") == "a-weak-peaks-split_fraction-015"
    assert github_anchor("See [the log](decisions/wand.md)") == "see-the-log"


def test_anchors_number_repeated_headings(tmp_path):
    md = tmp_path / "a.md"
    md.write_text("# Title\n\n## Limits\n\ntext\n\n## Limits\n\n```\n## not a heading\n```\n", encoding="utf-8")
    assert anchors(md) == {"title", "limits", "limits-1"}


def test_the_checker_finds_a_missing_file_and_a_missing_heading(tmp_path):
    (tmp_path / "other.md").write_text("# Other\n\n## Speed and memory\n", encoding="utf-8")
    md = tmp_path / "doc.md"
    md.write_text("# Doc\n\n"
                  "Good: [speed](other.md#speed-and-memory), [self](#doc), [file](other.md),\n"
                  "[web](https://example.org/x#y), `[in code](missing.md)`.\n"
                  "Bad: [gone](missing.md), [no section](other.md#speed), [no self](#nowhere).\n"
                  "```\n[in a fence](missing.md)\n```\n", encoding="utf-8")
    bad = broken_links(md)
    assert len(bad) == 3, bad
    assert bad[0].endswith("doc.md:5: missing.md: no such file")
    assert bad[1].endswith("doc.md:5: other.md#speed: no heading with this anchor in other.md")
    assert bad[2].endswith("doc.md:5: #nowhere: no heading with this anchor in doc.md")


def test_benchmarks_contents_line_resolves():
    """docs/benchmarks.md's contents line links each of its sections; each resolves."""
    bench = REPO / "docs" / "benchmarks.md"
    targets = [t for _, t in links(bench) if t.startswith("#")]
    assert len(targets) >= 10, targets
    assert {t[1:] for t in targets} <= anchors(bench)
    assert broken_links(bench) == []


def test_every_link_in_the_docs_and_readme_resolves():
    files = _project_markdown()
    assert len(files) > 20
    into_sections = [t for md in files for _, t in links(md) if "#" in t]
    assert len(into_sections) >= 20, into_sections                 # anchors are checked, not only files
    bad = [b for md in files for b in broken_links(md)]
    assert bad == [], "links that lead nowhere:\n" + "\n".join(bad)


def test_the_citation_checker_finds_a_missing_section(tmp_path, monkeypatch):
    docs = tmp_path / "docs"
    (docs / "decisions").mkdir(parents=True)
    (docs / "benchmarks.md").write_text("# B\n\n## Levelling (`--level`)\n\n**Known positions with a card** (x)\n",
                                        encoding="utf-8")
    (docs / "decisions" / "wand.md").write_text("# W\n\n### Clicks judged before they count (`judge`)\n",
                                                encoding="utf-8")
    src = tmp_path / "mod.py"
    src.write_text('X = 1  # docs/benchmarks.md, "Levelling"; docs/benchmarks.md "Known positions with a card"\n'
                   '#: measured (``docs/decisions/wand.md``, "Clicks judged\n'
                   '#: before they count"); docs/benchmarks.md, "The wand\'s default"; docs/nowhere.md, "Any"\n',
                   encoding="utf-8")
    monkeypatch.setattr(sys.modules[__name__], "REPO", tmp_path)
    assert [name for _, name in citations(src)] == ["Levelling", "Known positions with a card",
                                                    "Clicks judged before they count", "The wand's default", "Any"]
    assert broken_citations(src) == ["mod.py: benchmarks.md, \"The wand's default\": no such section",
                                     "mod.py: nowhere.md, \"Any\": no such file under docs/"]


def test_every_cited_section_exists():
    """Code, scripts, tests, README.md and docs cite sections that their files have."""
    files = [p for d in ("cpython_core", "jython_lib", "plugins", "scripts", "tests") for p in (REPO / d).rglob("*.py")
             if p.resolve() != Path(__file__).resolve()]            # not this file's examples
    files += _project_markdown()
    cited = [c for f in files for c in citations(f)]
    assert len(cited) >= 80                                        # the scan finds them
    assert sum(dest.name == "benchmarks.md" for dest, _ in cited) >= 25
    bad = [b for f in files for b in broken_citations(f)]
    assert bad == [], "sections cited that do not exist:\n" + "\n".join(bad)
