#!/usr/bin/env python
"""Write the texts generated from the detector's rule declarations (``uvps.core.detect.rules.RULES``):
the rejection tables of ``docs/architecture.md`` and ``docs/protrusions.md`` (between
``<!-- rules:begin -->`` and ``<!-- rules:end -->``) and ``jython_lib/uvps_fiji/rejection_words.py``
(the Fiji Log's words). ``--check`` exits 1 when one is stale (``tests/test_detect_package.py``).

    .venv/bin/python scripts/detection_docs.py
"""
from __future__ import annotations

import argparse
import re
import sys
from pathlib import Path

from uvps.core.detect.rules import jython_words_module, rules_markdown

ROOT = Path(__file__).resolve().parents[1]
BEGIN, END = "<!-- rules:begin -->", "<!-- rules:end -->"
DOCS = (ROOT / "docs" / "architecture.md", ROOT / "docs" / "protrusions.md")
WORDS = ROOT / "jython_lib" / "uvps_fiji" / "rejection_words.py"


def expected() -> dict:
    """path -> the text it should hold."""
    out = {}
    table = rules_markdown()
    for path in DOCS:
        text = path.read_text(encoding="utf-8")
        pat = re.compile(re.escape(BEGIN) + r".*?" + re.escape(END), re.S)
        if not pat.search(text):
            raise SystemExit(f"{path}: no {BEGIN} ... {END} block")
        out[path] = pat.sub(lambda m: f"{BEGIN}\n{table}{END}", text)
    out[WORDS] = jython_words_module()
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--check", action="store_true", help="exit 1 when a generated text is stale")
    args = ap.parse_args(argv)
    texts = expected()
    stale = [p for p, t in texts.items() if not p.exists() or p.read_text(encoding="utf-8") != t]
    if args.check:
        for p in stale:
            print(f"{p.relative_to(ROOT)} is stale: run python scripts/detection_docs.py", file=sys.stderr)
        return 1 if stale else 0
    for p in stale:
        p.write_text(texts[p], encoding="utf-8")
    return 0


if __name__ == "__main__":
    sys.exit(main())
