#!/usr/bin/env python3
"""Write the menu table of docs/fiji/index.md from the command declarations and the menu scripts.

    .venv/bin/python scripts/fiji_index.py [--check]

The table sits between :data:`install_fiji.INDEX_BEGIN` and :data:`install_fiji.INDEX_END`; each row is
a menu item in the installed menu's order, its page, its command's help (``CommandSpec.help``) and the
command. ``--check`` exits 1 when the file differs from what would be written (tests/test_install_fiji.py).
"""
import argparse
import os
import sys

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import install_fiji  # noqa: E402

from uvps.commands import COMMANDS  # noqa: E402
from uvps.spec import to_json  # noqa: E402

ROOT = install_fiji.REPO_ROOT
INDEX = os.path.join(ROOT, "docs", "fiji", "index.md")


def generated(text, commands):
    """``text`` (the index page) with its menu table regenerated."""
    table = install_fiji.fiji_index_table(commands, os.path.join(ROOT, "plugins", install_fiji.MENU_FOLDER),
                                          os.path.dirname(INDEX))
    head, sep, rest = text.partition(install_fiji.INDEX_BEGIN)
    _, sep2, tail = rest.partition(install_fiji.INDEX_END)
    if not sep or not sep2:
        raise SystemExit("%s: the markers of the menu table are missing" % INDEX)
    return head + install_fiji.INDEX_BEGIN + "\n" + table + install_fiji.INDEX_END + tail


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--check", action="store_true", help="exit 1 if docs/fiji/index.md is not up to date")
    args = ap.parse_args(argv)
    with open(INDEX, encoding="utf-8") as f:
        text = f.read()
    new = generated(text, to_json(COMMANDS)["commands"])
    if args.check:
        return 0 if new == text else 1
    if new != text:
        with open(INDEX + ".part", "w", encoding="utf-8") as f:
            f.write(new)
        os.replace(INDEX + ".part", INDEX)
    return 0


if __name__ == "__main__":
    sys.exit(main())
