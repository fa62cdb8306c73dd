#!/usr/bin/env python
"""Write the texts generated from the detector's rule declarations (``uvps.core.detect.rules.RULES``):
the rejection tables of ``docs/architecture.md`` and ``docs/protrusions.md`` (between
``<!-- rules:begin -->`` and ``<!-- rules:end -->``) and ``jython_lib/uvps_fiji/rejection_words.py``
(the Fiji Log's words), and the example of the Log's detection lines in
``docs/fiji/Detect_Protrusions.md`` (between ``<!-- log:begin -->`` and ``<!-- log:end -->``, written
by the Fiji side's own formatter, ``bridge_logic.diagnostic_lines``). ``--check`` exits 1 when one is
stale (``tests/test_detect_package.py``).

    .venv/bin/python scripts/detection_docs.py
"""
from __future__ import annotations

import argparse
import re
import subprocess
import sys
from pathlib import Path

from uvps.core.detect.rules import jython_words_module, rules_markdown

ROOT = Path(__file__).resolve().parents[1]
BEGIN, END = "<!-- rules:begin -->", "<!-- rules:end -->"
DOCS = (ROOT / "docs" / "architecture.md", ROOT / "docs" / "protrusions.md")
WORDS = ROOT / "jython_lib" / "uvps_fiji" / "rejection_words.py"
FIJI_PAGE = ROOT / "docs" / "fiji" / "Detect_Protrusions.md"
LOG_BEGIN, LOG_END = "<!-- log:begin -->", "<!-- log:end -->"
#: The detection diagnostics the Fiji page's example Log is written from.
EXAMPLE = {"n_protrusions": 6, "noise_um": 0.0467,
           "rejected": {"flat_bright": 9, "too_small": 7, "ridge": 4, "weave": 4}}


def _between(path: Path, begin: str, end: str, body: str) -> str:
    """``path``'s text with what lies between ``begin`` and ``end`` replaced by ``body``."""
    text = path.read_text(encoding="utf-8")
    pat = re.compile(re.escape(begin) + r".*?" + re.escape(end), re.S)
    if not pat.search(text):
        raise SystemExit(f"{path}: no {begin} ... {end} block")
    return pat.sub(lambda m: f"{begin}\n{body}{end}", text)


def example_log() -> str:
    """The Fiji Log's detection lines for :data:`EXAMPLE`, as a fenced block, from the Fiji side's
    formatter with the core's command table (``uvps spec``, as the installer writes it)."""
    sys.path.insert(0, str(ROOT / "jython_lib"))
    from uvps_fiji import bridge_logic
    from uvps.core.detect.rules import REJECTION_WORDS
    # the words as declared now: rejection_words.py, which bridge_logic imported, may be the
    # stale file this run is rewriting
    bridge_logic.REJECTION_WORDS = REJECTION_WORDS
    spec = subprocess.run([sys.executable, "-m", "uvps", "spec"], check=True, timeout=120,
                          stdout=subprocess.PIPE, universal_newlines=True).stdout
    lines = bridge_logic.diagnostic_lines("detect", EXAMPLE, table=bridge_logic.parse_spec(spec, "uvps spec"))
    return "```\n" + "\n".join(lines) + "\n```\n"


def expected() -> dict:
    """path -> the text it should hold."""
    table = rules_markdown()
    out = {path: _between(path, BEGIN, END, table) for path in DOCS}
    out[WORDS] = jython_words_module()
    out[FIJI_PAGE] = _between(FIJI_PAGE, LOG_BEGIN, LOG_END, example_log())
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
